//! `pntr build-db --sequence`: a map from a robot's own recordings, and the check of where it works.

use std::path::Path;

use anyhow::{bail, Context, Result};
use pntr_core::Intrinsics;
use pntr_dataset::recording::{Recording, RecordingOptions};
use pntr_mapping::keyframes::KeyframeParams;
use pntr_mapping::recording_map::{self, Session};
use pntr_pipeline::mapfile;
use serde_json::json;

use crate::map_cmd::{bar, map_feature_stage, models_dir, BuildArgs};

/// The camera of `rec`: `--intrinsics` (at the size of the recording's first readable frame) or
/// the recording's own calibration.
fn camera_of(rec: &Recording, intrinsics: Option<&str>) -> Result<Intrinsics> {
    let Some(text) = intrinsics else {
        return rec.intrinsics().with_context(|| {
            format!(
                "{}: {}; give the camera with --intrinsics fx,fy,cx,cy[,k1,k2,p1,p2,k3]",
                rec.path.display(),
                rec.camera_problem()
                    .unwrap_or_else(|| "no calibration.txt or camera info".into())
            )
        });
    };
    let m = crate::localize_cmd::parse_intrinsics(&[text.to_string()])?;
    let (width, height) = rec.image_size().with_context(|| {
        format!(
            "{}: none of the first frames could be read",
            rec.path.display()
        )
    })?;
    let mut k = Intrinsics {
        fx: m.fx,
        fy: m.fy,
        cx: m.cx,
        cy: m.cy,
        width,
        height,
        ..Intrinsics::hpointloc()
    };
    for (d, v) in k.distortion.iter_mut().zip(&m.distortion) {
        *d = *v;
    }
    k.validate()
        .map_err(|e| anyhow::anyhow!("--intrinsics {text}: {e}"))?;
    Ok(k)
}

fn keyframe_params(args: &BuildArgs) -> Result<KeyframeParams> {
    let p = KeyframeParams {
        distance_m: args.keyframe_distance,
        angle_deg: args.keyframe_angle,
        min_overlap: args.keyframe_overlap,
        ..KeyframeParams::default()
    };
    if !(p.distance_m.is_finite() && p.distance_m > 0.0) {
        bail!(
            "--keyframe-distance must be a positive number of metres, not {}",
            p.distance_m
        );
    }
    if !(p.angle_deg.is_finite() && p.angle_deg > 0.0 && p.angle_deg <= 180.0) {
        bail!(
            "--keyframe-angle must be within (0, 180] degrees, not {}",
            p.angle_deg
        );
    }
    if !(0.0..=1.0).contains(&p.min_overlap) {
        bail!(
            "--keyframe-overlap must be within 0..1, not {}",
            p.min_overlap
        );
    }
    Ok(p)
}

fn open(
    path: &Path,
    args: &BuildArgs,
    trajectory: Option<&Path>,
) -> Result<(Recording, Intrinsics)> {
    open_recording(
        path,
        trajectory,
        &args.topics,
        args.depth_scale,
        args.intrinsics.as_deref(),
    )
}

/// Open recording `path` (`--sequence`) with its poses from `trajectory` when given, `topics` for a
/// bag, `depth_scale` units per metre and `intrinsics` (`fx,fy,cx,cy[,...]`) replacing what the
/// recording says; its camera.
pub(crate) fn open_recording(
    path: &Path,
    trajectory: Option<&Path>,
    topics: &crate::replay_cmd::TopicArgs,
    depth_scale: Option<f64>,
    intrinsics: Option<&str>,
) -> Result<(Recording, Intrinsics)> {
    let (depth_intrinsics, colour_from_depth) = topics.depth_camera()?;
    let opts = RecordingOptions {
        topics: topics.topics(),
        trajectory: trajectory.map(Path::to_path_buf),
        depth_units_per_m: depth_scale,
        depth_intrinsics,
        colour_from_depth,
    };
    let mut rec =
        Recording::open(path, &opts).with_context(|| format!("--sequence {}", path.display()))?;
    let camera = camera_of(&rec, intrinsics)?;
    rec.set_colour_camera(camera);
    Ok((rec, camera))
}

pub(crate) fn as_sessions(recs: &[(Recording, Intrinsics)]) -> Vec<Session<'_>> {
    recs.iter()
        .map(|(recording, camera)| Session {
            recording,
            camera: *camera,
        })
        .collect()
}

/// `pntr build-db --sequence ...`.
pub fn build_from_recordings(args: &BuildArgs) -> Result<()> {
    if !args.trajectory.is_empty() && args.trajectory.len() != args.sequence.len() {
        bail!(
            "--trajectory given {} times for {} --sequence: give one per sequence, in the same order",
            args.trajectory.len(),
            args.sequence.len()
        );
    }
    let up_axis = match args.up_axis.as_deref().map(str::to_ascii_lowercase) {
        None => None,
        Some(a) if a == "y" || a == "z" => Some(a),
        Some(a) => bail!("--up-axis {a}: give y or z"),
    };
    if args.scene.is_some() {
        bail!("--scene selects a scene of a --dataset; a --sequence map takes --map-id");
    }
    let params = keyframe_params(args)?;
    let recordings: Vec<(Recording, Intrinsics)> = args
        .sequence
        .iter()
        .enumerate()
        .map(|(i, p)| open(p, args, args.trajectory.get(i).map(|t| t.as_path())))
        .collect::<Result<_>>()?;
    let sessions = as_sessions(&recordings);
    let out = args
        .out
        .clone()
        .or_else(|| args.extend.clone())
        .context("--out is required")?;
    let models = models_dir(args.models.as_deref())?;
    let total: usize = sessions.iter().map(|s| s.recording.len()).sum();
    let pb = bar(total, "choosing keyframes");
    let mut progress = |done: usize, total: usize| {
        pb.set_length(total as u64);
        pb.set_position(done as u64);
    };
    let (map, report, preset) = match &args.extend {
        Some(base_path) => {
            if let Some(id) = &args.map_id {
                bail!("--map-id {id}: an extended map keeps its own id (give --out for a copy)");
            }
            let base = crate::map_cmd::load_map(base_path, args.threads)
                .with_context(|| format!("--extend {}", base_path.display()))?;
            let preset = base.header.preset.clone();
            let stage = map_feature_stage(&preset, &models, args.threads)?;
            let (map, report) =
                recording_map::extend(base, &sessions, params, &preset, &stage, &mut progress)
                    .with_context(|| format!("extending {}", base_path.display()))?;
            (map, report, preset)
        }
        None => {
            let map_id = args
                .map_id
                .clone()
                .unwrap_or_else(|| sessions[0].recording.name());
            let preset = crate::map_cmd::build_preset(args)?;
            let stage = map_feature_stage(&preset, &models, args.threads)?;
            let (map, report) = recording_map::build(
                &map_id,
                &sessions,
                params,
                up_axis.as_deref(),
                &preset,
                &stage,
                &models,
                &mut progress,
            )?;
            (map, report, preset)
        }
    };
    pb.finish_and_clear();
    for w in &report.warnings {
        eprintln!("warning: {w}");
    }
    let self_calibrate = !args.no_self_calibration;
    let mut self_calibration_s = 0.0;
    let (map, check) = if args.no_check && !self_calibrate {
        (map, None)
    } else {
        let opts = crate::selfcal_cmd::Options::of_build(args, &models);
        let (pipeline, base, regions, why) = crate::selfcal_cmd::for_recordings(map, &opts)?;
        let regions = regions.filter(|_| self_calibrate);
        if let (true, Some(why)) = (self_calibrate, &why) {
            eprintln!("warning: the map keeps the shipped calibration: {why}");
        }
        let other = args
            .check_sequence
            .as_deref()
            .map(|p| open(p, args, None))
            .transpose()?;
        let (check_sessions, frames, kind) = match &other {
            Some(o) => (
                as_sessions(std::slice::from_ref(o)),
                (0..o.0.len()).map(|i| (0, i)).collect::<Vec<_>>(),
                "another recording",
            ),
            None => (
                sessions,
                report.left_out.clone(),
                "frames between keyframes (the easy case: each is near one)",
            ),
        };
        let mut check = None;
        let mut used = recording_map::evenly(&frames, args.self_calibration_frames);
        if !args.no_check {
            let frames = recording_map::evenly(&frames, args.check_frames);
            let pb = bar(frames.len(), "checking the map");
            let c = recording_map::check(
                &pipeline,
                &check_sessions,
                &frames,
                kind,
                regions.as_ref(),
                &mut |d, n| {
                    pb.set_length(n as u64);
                    pb.set_position(d as u64);
                },
            )?;
            pb.finish_and_clear();
            check = Some(c);
            used = frames;
        }
        let t_cal = std::time::Instant::now();
        let map = match &regions {
            Some(r) => {
                // The check's answers are the in-map pass of the same frames.
                let in_map = check.as_mut().map(|c| std::mem::take(&mut c.answers));
                crate::selfcal_cmd::with_recordings(
                    pipeline,
                    &opts,
                    &base,
                    r,
                    &check_sessions,
                    &used,
                    in_map,
                )?
            }
            None => crate::selfcal_cmd::into_map(pipeline),
        };
        self_calibration_s = t_cal.elapsed().as_secs_f64();
        (map, check)
    };
    let t = std::time::Instant::now();
    mapfile::save(&map, &out).with_context(|| format!("writing {}", out.display()))?;
    let write_s = t.elapsed().as_secs_f64();
    let bytes = std::fs::metadata(&out)?.len();
    let map_positions: Vec<[f64; 3]> = map
        .images
        .iter()
        .map(|im| im.world_from_camera.translation.vector.into())
        .collect();
    let images = map.images.len();
    let heap = map.heap_bytes();
    let stale = map.calibration_is_stale();
    let header = map.header.clone();
    if let (Some(dir), Some(c)) = (&args.plot, &check) {
        let frames: Vec<crate::plot::CheckedPoint> = c
            .per_frame
            .iter()
            .map(|f| (f.position_m, f.error_m, f.outside_map))
            .collect();
        let title = format!(
            "{}: {images} map images; {} frames checked ({}), {:.1}% localized",
            header.map_id,
            c.frames,
            c.kind,
            100.0 * c.localized_share
        );
        let files = crate::plot::check_plot(
            &map_positions,
            &frames,
            crate::plot::ground_of(&header.up_axis),
            dir,
            &title,
        )?;
        eprintln!("{} pictures written to {}", files.len(), dir.display());
    }
    let mut stage_seconds = report.stage_seconds.clone();
    stage_seconds.insert("write".into(), write_s);
    if let Some(c) = &check {
        stage_seconds.insert("check".into(), c.seconds);
    }
    if self_calibration_s > 0.0 {
        stage_seconds.insert("self_calibration".into(), self_calibration_s);
    }
    let summary = json!({
        "map_id": header.map_id,
        "preset": preset.name,
        "images": images,
        "scenes": header.scenes,
        "file": out.display().to_string(),
        "extended": args.extend.as_ref().map(|p| p.display().to_string()),
        "base_images": report.base_images,
        "images_added": images - report.base_images,
        "file_bytes": bytes,
        "heap_bytes": heap,
        "build_seconds": header.build_seconds,
        "write_seconds": write_s,
        "frames": report.frames,
        "skipped": report.skipped,
        "places": report.places,
        "camera_axes": header.camera_axes,
        "up_axis": header.up_axis,
        "up_axis_inferred": report.up_axis_inferred,
        "stage_seconds": stage_seconds,
        "self_calibration_seconds": self_calibration_s,
        "sequences": args.sequence.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
        "check": check.as_ref().map(serde_json::to_value).transpose()?,
        "calibration": crate::selfcal_cmd::summary(header.calibration.as_ref(), stale),
        "warnings": report.warnings,
    });
    if args.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
        return Ok(());
    }
    let kept = if args.extend.is_some() {
        format!(
            "{} keyframes added to its {} images ({images} now) from",
            images - report.base_images,
            report.base_images
        )
    } else {
        format!("{images} keyframes of")
    };
    println!(
        "map {} ({} preset): {kept} {} frames in {} places (left out: {}), axes {} with up {}; {} written ({:.1} MB)",
        header.map_id,
        preset.name,
        report.frames,
        report.places,
        report
            .skipped
            .iter()
            .map(|(k, v)| format!("{v} {k}"))
            .collect::<Vec<_>>()
            .join(", "),
        header.camera_axes,
        header.up_axis,
        out.display(),
        bytes as f64 / 1e6
    );
    if let Some(c) = &check {
        println!(
            "check ({}): {} frames, {:.1}% localized, ATE {:.3} m, {} more than 1 m off, {} outside what the map covers",
            c.kind,
            c.frames,
            100.0 * c.localized_share,
            c.ate_rmse_m,
            c.frames_over_1m,
            c.frames_outside_map
        );
    }
    println!(
        "{}",
        crate::selfcal_cmd::line(header.calibration.as_ref(), stale)
    );
    Ok(())
}
