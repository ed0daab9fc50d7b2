//! A stream's frames registered against its keyframe (`pntr_pipeline::odometry`), on a generated drive
//! with the committed models: the tracked drive stays localized and accurate between map views, and a
//! keyframe that does not fit the frame never produces a pose, odometry carried where the map's
//! images never looked is outside the mapped area, a track that slipped where the map's views
//! contradict it is lost, and one that slipped less is anchored again by the map answer its views
//! prefer.

use std::sync::Arc;

use nalgebra::Vector3;
use pntr_dataset::tum::TumSequence;
use pntr_pipeline::odometry::{self, Keyframe};
use pntr_pipeline::pipeline::{
    Cause, Localization, Pipeline, Query, Status, FUSION_GATE_MIN_M, OUTSIDE_MAP_PREFIX, SLIP_MAX_M,
};
use pntr_pipeline::preset::Preset;
use pntr_pipeline::prior::{tracking_heading, LocalizeOptions, Mode, Region};

fn drive(root: &std::path::Path, seed: u64) -> (Pipeline, TumSequence) {
    let cfg = pntr_synth::SynthConfig {
        points_per_scene: 6,
        queries_per_point: 1,
        seed,
        trajectory_seconds: Some(8.0),
        ..Default::default()
    };
    pntr_synth::synthesize(&cfg, root, pntr_synth::plan_all(&cfg), &|| {}).expect("synthesize");
    let index = pntr_dataset::DatasetIndex::open(root).expect("dataset");
    let map = pntr_tests::build_map(&index, "xfeat-mnn", "drive");
    let preset = Preset::named("xfeat-mnn").unwrap();
    let stage = preset
        .feature_config(pntr_tests::models())
        .build()
        .expect("models load");
    let pipeline = Pipeline::new(Arc::new(map), stage, preset).expect("pipeline");
    let seq = TumSequence::open(&root.join(pntr_synth::SEQUENCES_DIR).join("synth000"))
        .expect("the drive's TUM folder");
    (pipeline, seq)
}

fn query(seq: &TumSequence, i: usize) -> Query {
    let (rgb, depth) = seq.load(i).expect("frame");
    Query {
        rgb,
        depth,
        intrinsics: seq.intrinsics.expect("calibration.txt"),
    }
}

fn position(loc: &Localization) -> Option<Vector3<f64>> {
    loc.pose.map(|p| p.translation.vector)
}

#[test]
fn a_tracked_drive_stays_localized_between_map_views_and_wrong_keyframes_give_no_pose() {
    for seed in [41u64, 42] {
        let dir = tempfile::tempdir().unwrap();
        let (pipeline, seq) = drive(dir.path(), seed);
        let n = seq.frames.len();
        assert_eq!(n, 80);
        let truth = |i: usize| seq.frames[i].world_from_camera.expect("ground truth");
        // The service's loop without its clock: the keyframe first, the map when it does not hold.
        let mut keyframe: Option<Arc<Keyframe>> = None;
        let mut last: Option<nalgebra::Isometry3<f64>> = None;
        let (mut localized, mut by_odometry, mut worst_m, mut squares) =
            (0usize, 0usize, 0.0f64, 0.0);
        let mut first_keyframe = None;
        let mut keyframes: Vec<(usize, Arc<Keyframe>)> = Vec::new();
        for i in 0..n {
            // Every fifth frame re-anchors (the map first), as the service does after 0.5 s.
            let opts = LocalizeOptions {
                keyframe: keyframe.clone(),
                want_keyframe: true,
                map_first: i % 5 == 0,
                // The service's bounds one frame (0.1 s) after the last answer.
                heading: last.map(|p| tracking_heading(p.rotation, 0.1)),
                ..match last {
                    Some(p) => {
                        LocalizeOptions::tracking(Region::new(p.translation.vector, 2.0).unwrap())
                    }
                    None => LocalizeOptions::default(),
                }
            };
            let loc = pipeline.localize_with(&query(&seq, i), &opts).unwrap();
            let Some(p) = position(&loc) else {
                continue;
            };
            localized += 1;
            by_odometry += loc.odometry as usize;
            if loc.odometry {
                assert_eq!(loc.mode, Mode::Tracking);
                assert!(loc.confidence >= pipeline.min_confidence(), "seed {seed}");
                let cov = loc.covariance.as_ref().expect("an odometry covariance");
                assert!((0..6).all(|k| cov[k * 7] > 0.0), "seed {seed} frame {i}");
            }
            let err = (p - truth(i).translation.vector).norm();
            worst_m = worst_m.max(err);
            squares += err * err;
            keyframe = loc.keyframe.clone();
            assert!(
                keyframe.is_some(),
                "a LOCALIZED stream answer gives a keyframe"
            );
            first_keyframe.get_or_insert_with(|| (i, keyframe.clone().unwrap()));
            keyframes.extend(keyframe.clone().map(|k| (i, k)));
            last = loc.pose;
        }
        let rmse = (squares / localized.max(1) as f64).sqrt();
        eprintln!("seed {seed}: localized {localized}/{n}, by odometry {by_odometry}, RMSE {rmse:.3} m, worst {worst_m:.3} m");
        assert!(
            localized as f64 >= 0.9 * n as f64,
            "seed {seed}: {localized}/{n}"
        );
        assert!(
            by_odometry as f64 >= 0.5 * n as f64,
            "seed {seed}: {by_odometry}/{n}"
        );
        assert!(worst_m < 0.25, "seed {seed}: an answer {worst_m:.2} m off");

        // A keyframe from the drive's start offered for its end, with the region at the end: the
        // frame sees other walls, so the hop fails or lands outside the region; the map answers.
        let (k, start) = first_keyframe.expect("one fix");
        let from_start =
            |i: usize| (truth(i).translation.vector - truth(k).translation.vector).norm();
        let end = (0..n)
            .max_by(|&a, &b| from_start(a).total_cmp(&from_start(b)))
            .unwrap();
        assert!(
            from_start(end) > 1.5,
            "seed {seed}: the drive stays near its start"
        );
        let at_end = |keyframe: Keyframe| LocalizeOptions {
            keyframe: Some(Arc::new(keyframe)),
            want_keyframe: true,
            ..LocalizeOptions::tracking(Region::new(truth(end).translation.vector, 1.0).unwrap())
        };
        let loc = pipeline
            .localize_with(&query(&seq, end), &at_end((*start).clone()))
            .unwrap();
        assert!(!loc.odometry, "seed {seed}: {:?}", loc.reason);
        if loc.status == Status::Localized {
            let err = (position(&loc).unwrap() - truth(end).translation.vector).norm();
            assert!(err < 0.25, "seed {seed}: {err} m");
        }
        // The same keyframe remembering a frame tracked just before the end: the hop from it holds,
        // and that frame is the keyframe from then on.
        let near = keyframes
            .iter()
            .rev()
            .find(|(i, _)| *i < end)
            .map(|(_, k)| Arc::clone(k))
            .expect("a keyframe before the end");
        let latest = Keyframe {
            latest: None,
            ..(*near).clone()
        };
        let remembering = Keyframe {
            latest: Some(Arc::new(latest.clone())),
            ..(*start).clone()
        };
        let loc = pipeline
            .localize_with(&query(&seq, end), &at_end(remembering))
            .unwrap();
        assert!(loc.odometry, "seed {seed}: {:?}", loc.reason);
        let err = (position(&loc).unwrap() - truth(end).translation.vector).norm();
        assert!(err < 0.25, "seed {seed}: {err} m");
        let next = loc.keyframe.expect("a keyframe");
        assert!(
            (next.world_from_camera.translation.vector
                - latest.world_from_camera.translation.vector)
                .norm()
                < 1.0,
            "seed {seed}: the remembered frame (or the frame itself) tracks next"
        );
        // A chain already MAX_PATH_M long gives no more odometry poses (drift).
        let worn = Keyframe {
            path_m: odometry::MAX_PATH_M,
            ..latest
        };
        let loc = pipeline
            .localize_with(&query(&seq, end), &at_end(worn))
            .unwrap();
        assert!(!loc.odometry, "seed {seed}: a worn chain still tracked");
        assert!(
            loc.reason.as_deref().unwrap_or("").contains("driven")
                || loc.status == Status::Localized,
            "seed {seed}: {:?}",
            loc.reason
        );
        // Odometry that carries the camera where the map's images never looked is not LOCALIZED:
        // the keyframe of a frame before the end, moved 30 m (beyond the apartment), tracks that
        // frame there. The answer is outside the mapped area, with the pose kept as the estimate
        // and the keyframe handed on so a stream can follow the camera; unmoved, it is LOCALIZED.
        let (ki, kf) = keyframes
            .iter()
            .rev()
            .find(|(i, _)| *i < end)
            .map(|(i, k)| {
                (
                    *i,
                    Keyframe {
                        latest: None,
                        ..(**k).clone()
                    },
                )
            })
            .unwrap();
        let shift = nalgebra::Isometry3::translation(30.0, 0.0, 0.0);
        let moved = Keyframe {
            world_from_camera: shift * kf.world_from_camera,
            ..kf.clone()
        };
        let there = truth(ki).translation.vector + Vector3::new(30.0, 0.0, 0.0);
        let follow = |keyframe: Keyframe, at: Vector3<f64>| LocalizeOptions {
            keyframe: Some(Arc::new(keyframe)),
            want_keyframe: true,
            ..LocalizeOptions::tracking(Region::new(at, 1.0).unwrap())
        };
        // A chain past its length still follows the camera there (drift stops answers, not the
        // motion): the same answer, from a keyframe MAX_PATH_M along its chain.
        let worn_there = pipeline
            .localize_with(
                &query(&seq, ki),
                &follow(
                    Keyframe {
                        path_m: odometry::MAX_PATH_M,
                        ..moved.clone()
                    },
                    there,
                ),
            )
            .unwrap();
        assert_eq!(
            worn_there.cause,
            Some(Cause::OutsideMap),
            "seed {seed}: {:?}",
            worn_there.reason
        );
        assert!(
            worn_there.odometry && worn_there.pose.is_none() && worn_there.keyframe.is_some(),
            "seed {seed}"
        );
        let followed = worn_there.estimate.expect("the followed pose");
        assert!(
            (followed.translation.vector - there).norm() < 0.25,
            "seed {seed}: {followed:?}"
        );
        let loc = pipeline
            .localize_with(&query(&seq, ki), &follow(moved, there))
            .unwrap();
        assert_eq!(loc.status, Status::NotLocalized, "seed {seed}");
        assert_eq!(
            loc.cause,
            Some(Cause::OutsideMap),
            "seed {seed}: {:?}",
            loc.reason
        );
        let reason = loc.reason.as_deref().unwrap();
        assert!(reason.starts_with(OUTSIDE_MAP_PREFIX), "{reason}");
        assert!(
            loc.odometry && loc.pose.is_none() && loc.keyframe.is_some(),
            "seed {seed}"
        );
        let followed = loc.estimate.expect("the followed pose").translation.vector;
        assert!(
            (followed - there).norm() < 0.25,
            "seed {seed}: {followed:?}"
        );
        let loc = pipeline
            .localize_with(
                &query(&seq, ki),
                &follow(kf.clone(), truth(ki).translation.vector),
            )
            .unwrap();
        assert_eq!(
            loc.status,
            Status::Localized,
            "seed {seed}: {:?}",
            loc.reason
        );
        assert!(loc.cause.is_none());

        assert!(!loc.track_lost, "seed {seed}: a right track is not lost");

        // A track that slipped inside the map (odometry that missed the camera's motion): the same
        // keyframe placed 0.5 m behind where it was. The hop carries the frame there, where its
        // walls stand in front of what the map's views saw: the map contradicts the pose, the
        // track is lost, and the frame is searched for over the whole map instead (a fix near the
        // truth, or no pose at all; never the slipped one).
        let slipped = Keyframe {
            world_from_camera: kf.world_from_camera
                * nalgebra::Isometry3::translation(0.0, 0.0, -0.5),
            ..kf.clone()
        };
        let at = slipped.world_from_camera.translation.vector;
        let loc = pipeline
            .localize_with(&query(&seq, ki), &follow(slipped, at))
            .unwrap();
        assert!(
            loc.track_lost,
            "seed {seed}: {:?} {:?}",
            loc.status, loc.reason
        );
        assert!(!loc.odometry, "seed {seed}");
        // The contradicted hop goes with the answer as the camera's motion (not an answer), with
        // the keyframe its chain goes on with: the stream judges map fixes by it.
        let carried = loc.contradicted.as_ref().expect("the contradicted hop");
        assert!(
            (carried.pose.translation.vector - at).norm() < 0.3,
            "seed {seed}: {:?}",
            carried.pose
        );
        assert!(
            carried.keyframe.is_some() && carried.sigma_m.is_some(),
            "seed {seed}"
        );
        match loc.status {
            Status::Localized => {
                assert_eq!(loc.mode, Mode::Global, "seed {seed}");
                let err = (position(&loc).unwrap() - truth(ki).translation.vector).norm();
                assert!(err < 0.25, "seed {seed}: {err} m");
            }
            Status::NotLocalized => {
                let reason = loc.reason.as_deref().unwrap_or("");
                assert!(
                    reason.contains("the map contradicts the tracked pose"),
                    "{reason}"
                );
            }
        }

        // A track that slipped less (the keyframe 0.1-0.3 m to the side): the hop still holds
        // (the map's views do not contradict it enough to lose the track), and the map, tried
        // first, answers near the truth, beyond the fusion gate. Its views agree with the frame at
        // the map's pose and contradict it at the track's: the map answer anchors the track
        // (`track_slipped`) instead of only challenging it. (Measured: 0.15-0.3 m are anchored;
        // 0.1 m stays a challenger, the views' margins not met; 0.4 m and more lose the track.)
        let mut anchored = 0;
        for side_m in [0.1, 0.15, 0.2, 0.3] {
            let slipped = Keyframe {
                world_from_camera: kf.world_from_camera
                    * nalgebra::Isometry3::translation(side_m, 0.0, 0.0),
                ..kf.clone()
            };
            let at = slipped.world_from_camera.translation.vector;
            let loc = pipeline
                .localize_with(
                    &query(&seq, ki),
                    &LocalizeOptions {
                        map_first: true,
                        ..follow(slipped, at)
                    },
                )
                .unwrap();
            eprintln!(
                "seed {seed}: slipped {side_m} m: {:?}, gap {:?}, track_slipped {}, lost {}",
                loc.status, loc.track_gap, loc.track_slipped, loc.track_lost
            );
            if !loc.track_slipped {
                continue;
            }
            assert_eq!(
                loc.status,
                Status::Localized,
                "seed {seed}: {:?}",
                loc.reason
            );
            assert!(!loc.odometry && loc.off_track.is_none(), "seed {seed}");
            let (gap_m, _) = loc.track_gap.expect("a gap to the track");
            assert!(gap_m > FUSION_GATE_MIN_M && gap_m <= SLIP_MAX_M, "{gap_m}");
            let err = (position(&loc).unwrap() - truth(ki).translation.vector).norm();
            assert!(err < 0.1, "seed {seed}: {err} m");
            let next = loc
                .keyframe
                .as_ref()
                .expect("the answer anchors the next keyframe");
            assert!(
                (next.world_from_camera.translation.vector - truth(ki).translation.vector).norm()
                    < 0.1,
                "seed {seed}: the keyframe lies at the map's pose"
            );
            anchored += 1;
        }
        assert!(
            anchored > 0,
            "seed {seed}: no slipped track was anchored by the map"
        );

        // Without a keyframe nothing is registered against one; unary calls get no keyframe back.
        let loc = pipeline
            .localize_with(&query(&seq, end), &LocalizeOptions::default())
            .unwrap();
        assert!(!loc.odometry && loc.keyframe.is_none());
    }
}
