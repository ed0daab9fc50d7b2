//! Live maps end to end: a real server (in-process on 127.0.0.1:0) whose maps are replaced, loaded,
//! unloaded and reloaded through `pntr.v1.MapAdmin` while clients keep localizing.
//!
//! Covered: the admin token (required, distinct from the clients'); versions in ListMaps,
//! GetMapInfo, every LocalizeResponse and /metrics (old versions' series gone); replacement under
//! concurrent load with no failed request; a stream's track carried onto a map of the same frame and
//! reset on a map of another frame (answers then in the new frame); refusals that leave the served
//! map untouched (missing, damaged, another id, an id already loaded); the replaced maps' memory freed
//! once drained; reload of changed files only; shutdown ending an open stream with UNAVAILABLE at
//! once rather than at the drain's end.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use pntr_dataset::View;
use pntr_pipeline::mapfile;
use pntr_service::config::Settings;
use pntr_service::proto;
use pntr_service::proto::localizer_client::LocalizerClient;
use pntr_service::proto::map_admin_client::MapAdminClient;
use pntr_service::tokio;
use pntr_service::tonic::{Code, Request};
use pntr_tests::{authed, channel, runtime, scrape, wait_until};

const ADMIN: &str = "admin-s3cret";
const CLIENT: &str = "client-s3cret";

/// `map` with every pose moved by `t` (as a second SLAM session starting elsewhere would record it),
/// saved to `path`.
fn save_moved(map: &mut pntr_pipeline::map::Map, t: &Isometry3<f64>, path: &Path) {
    for im in &mut map.images {
        im.world_from_camera = t * im.world_from_camera;
    }
    mapfile::save(map, path).unwrap();
    for im in &mut map.images {
        im.world_from_camera = t.inverse() * im.world_from_camera;
    }
}

/// A ReplaceMap request: map `map_id` by the map in `file`.
fn replacement(map_id: &str, file: &Path) -> proto::ReplaceMapRequest {
    proto::ReplaceMapRequest {
        map_id: map_id.into(),
        file: file.display().to_string(),
    }
}

fn request(v: &View) -> proto::LocalizeRequest {
    pntr_tests::request(v, "all")
}

fn error_m(r: &proto::LocalizeResponse, truth: &Isometry3<f64>) -> f64 {
    pntr_tests::translation_error(r, truth).expect("a pose")
}

#[test]
fn maps_change_under_load_and_streams() {
    let dir = tempfile::tempdir().unwrap();
    let index = pntr_tests::synthetic_dataset(dir.path(), 4, 4, 5);
    let mut built = pntr_tests::build_map(&index, "fast", "all");
    let v1_path = dir.path().join("all.pntrmap");
    mapfile::save(&built, &v1_path).unwrap();
    // The same map rebuilt later: same frame, another version.
    let v2_path = dir.path().join("all-v2.pntrmap");
    built.header.built_at_unix_s = built.header.built_at_unix_s.map(|s| s + 3600.0);
    mapfile::save(&built, &v2_path).unwrap();
    // The same place mapped by a session whose SLAM started 6 m away and turned 40 degrees.
    let moved = Isometry3::from_parts(
        Translation3::new(4.0, 0.5, -4.5),
        UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 40f64.to_radians()),
    );
    let moved_path = dir.path().join("all-moved.pntrmap");
    save_moved(&mut built, &moved, &moved_path);
    // Another map id, a damaged file.
    built.header.map_id = "copy".into();
    let copy_path = dir.path().join("copy.pntrmap");
    mapfile::save(&built, &copy_path).unwrap();
    // The same data mapped with another preset (MNN matching instead of LighterGlue).
    let mnn_path = dir.path().join("all-mnn.pntrmap");
    mapfile::save(
        &pntr_tests::build_map(&index, "xfeat-mnn", "all"),
        &mnn_path,
    )
    .unwrap();
    let damaged = dir.path().join("damaged.pntrmap");
    let bytes = std::fs::read(&v2_path).unwrap();
    std::fs::write(&damaged, &bytes[..bytes.len() / 2]).unwrap();

    let queries = pntr_tests::query_views(&index);
    let still = queries[0].clone();

    let rt = runtime();
    rt.block_on(async {
        let mut s = Settings::local(vec![v1_path.clone()], pntr_tests::models());
        s.workers = 2;
        s.token = Some(CLIENT.into());
        s.admin_token = Some(ADMIN.into());
        // Long enough that a stream held open to the drain's end would fail the check below.
        s.drain_timeout = Duration::from_secs(300);
        let mut running = pntr_service::start(s).await.unwrap();
        running.ready().await.unwrap();
        let addr = running.addr;
        let ch = channel(addr).await;
        let mut admin = MapAdminClient::new(ch.clone());
        let mut client = LocalizerClient::new(ch.clone()).max_decoding_message_size(64 << 20);

        // The admin token, and only it, opens the admin API.
        for token in [None, Some(CLIENT), Some("wrong")] {
            let req = match token {
                Some(t) => authed(proto::ListMapsRequest {}, t),
                None => Request::new(proto::ListMapsRequest {}),
            };
            let e = admin.list_maps(req).await.unwrap_err();
            assert_eq!(
                e.code(),
                Code::Unauthenticated,
                "{token:?}: {}",
                e.message()
            );
        }
        let e = client
            .get_map_info(authed(proto::GetMapInfoRequest::default(), ADMIN))
            .await
            .unwrap_err();
        assert_eq!(
            e.code(),
            Code::Unauthenticated,
            "the admin token is not a client token"
        );
        let maps = admin
            .list_maps(authed(proto::ListMapsRequest {}, ADMIN))
            .await
            .unwrap()
            .into_inner()
            .maps;
        assert_eq!(maps.len(), 1);
        let v1 = maps[0].version.clone();
        assert_eq!(maps[0].map_id, "all");
        assert_eq!(maps[0].file, v1_path.display().to_string());
        assert_eq!(maps[0].images, 24);
        assert!(
            v1.len() > 16 && !maps[0].built_at.is_empty(),
            "{:?}",
            maps[0]
        );
        let info = client
            .get_map_info(authed(proto::GetMapInfoRequest::default(), CLIENT))
            .await
            .unwrap()
            .into_inner();
        assert_eq!(info.version, v1);
        let old_maps: Vec<std::sync::Weak<pntr_pipeline::map::Map>> = vec![Arc::downgrade(
            &running.state.engine().unwrap().maps()[0].map,
        )];

        // Load from two clients for the whole test: every answer must be an answer.
        let stop = Arc::new(AtomicBool::new(false));
        let seen: Arc<Mutex<Vec<(Code, String)>>> = Arc::default();
        let mut load = Vec::new();
        for k in 0..2 {
            let mut c = client.clone();
            let (stop, seen) = (stop.clone(), seen.clone());
            let frames: Vec<_> = queries.iter().skip(k).step_by(2).map(request).collect();
            load.push(tokio::spawn(async move {
                let mut i = 0;
                while !stop.load(Ordering::SeqCst) {
                    let r = c
                        .localize(authed(frames[i % frames.len()].clone(), CLIENT))
                        .await;
                    seen.lock().unwrap().push(match r {
                        Ok(r) => (Code::Ok, r.into_inner().map_version),
                        Err(e) => (e.code(), e.message().to_string()),
                    });
                    i += 1;
                }
            }));
        }

        // A robot standing still streams the same view; its track is confirmed by two fixes.
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        let mut stream = client
            .localize_stream(authed(
                pntr_service::tokio_stream::wrappers::ReceiverStream::new(rx),
                CLIENT,
            ))
            .await
            .unwrap()
            .into_inner();
        let mut frame = async |truth: &Isometry3<f64>| {
            tx.send(request(&still)).await.unwrap();
            let r = stream.message().await.unwrap().unwrap();
            assert_eq!(r.status, proto::Status::Localized as i32, "{}", r.reason);
            assert!(error_m(&r, truth) < 0.25, "{} m off", error_m(&r, truth));
            r
        };
        for _ in 0..3 {
            let r = frame(&still.world_from_camera).await;
            assert_eq!(r.map_version, v1);
        }
        assert_eq!(
            frame(&still.world_from_camera).await.mode,
            proto::Mode::Tracking as i32
        );

        // Map `all` replaced by the map in `file` with the admin token: the change.
        let replacer = admin.clone();
        let replace_all = move |file: &Path| {
            let (mut admin, req) = (replacer.clone(), authed(replacement("all", file), ADMIN));
            async move { admin.replace_map(req).await.unwrap().into_inner() }
        };

        // Replaced by a rebuild in the same frame: later answers carry the new version and the
        // stream keeps tracking.
        let c = replace_all(&v2_path).await;
        let v2 = c.map.as_ref().unwrap().version.clone();
        assert_ne!(v2, v1);
        assert_eq!(c.previous_version, v1);
        assert!(c.same_frame, "a rebuild of the same data shares the frame");
        let mut old_maps = old_maps;
        old_maps.push(Arc::downgrade(
            &running.state.engine().unwrap().maps()[0].map,
        ));
        let r = frame(&still.world_from_camera).await;
        assert_eq!(r.map_version, v2);
        assert_eq!(
            r.mode,
            proto::Mode::Tracking as i32,
            "the track carried over"
        );

        // Replaced by a session in another frame: the track starts afresh and answers come in the
        // new frame.
        let c = replace_all(&moved_path).await;
        let v3 = c.map.as_ref().unwrap().version.clone();
        assert!(
            !c.same_frame,
            "a session 6 m and 40 degrees away is another frame"
        );
        assert_eq!(c.previous_version, v2);
        let truth_moved = moved * still.world_from_camera;
        let r = frame(&truth_moved).await;
        assert_eq!(r.map_version, v3);
        assert_eq!(r.mode, proto::Mode::Global as i32, "the track was reset");

        // Refusals leave the served map as it is.
        let refuse = |m: proto::ReplaceMapRequest| {
            let mut admin = admin.clone();
            async move { admin.replace_map(authed(m, ADMIN)).await.unwrap_err() }
        };
        let e = refuse(replacement("all", &damaged)).await;
        assert_eq!(e.code(), Code::FailedPrecondition, "{}", e.message());
        assert!(e.message().contains("damaged.pntrmap"), "{}", e.message());
        let e = refuse(replacement("all", &copy_path)).await;
        assert_eq!(e.code(), Code::FailedPrecondition, "{}", e.message());
        assert!(e.message().contains("`copy`"), "{}", e.message());
        let e = refuse(replacement("all", &dir.path().join("nope.pntrmap"))).await;
        assert_eq!(e.code(), Code::NotFound, "{}", e.message());
        let e = refuse(replacement("elsewhere", &copy_path)).await;
        assert_eq!(e.code(), Code::NotFound, "{}", e.message());
        assert_eq!(frame(&truth_moved).await.map_version, v3);

        // A second map loaded and unloaded; loading an id already served is refused.
        let load_copy = || {
            let file = copy_path.display().to_string();
            authed(proto::LoadMapRequest { file }, ADMIN)
        };
        let c = admin.load_map(load_copy()).await.unwrap().into_inner();
        assert_eq!(c.map.unwrap().map_id, "copy");
        let in_copy = || authed(pntr_tests::request(&still, "copy"), CLIENT);
        let r = client.localize(in_copy()).await.unwrap().into_inner();
        assert_eq!(r.status, proto::Status::Localized as i32);
        let e = admin.load_map(load_copy()).await.unwrap_err();
        assert_eq!(e.code(), Code::AlreadyExists, "{}", e.message());
        admin
            .unload_map(authed(
                proto::UnloadMapRequest {
                    map_id: "copy".into(),
                },
                ADMIN,
            ))
            .await
            .unwrap();
        let e = client.localize(in_copy()).await.unwrap_err();
        assert_eq!(e.code(), Code::NotFound);

        // A replacement may bring another preset: its models are loaded beside the served ones.
        let c = replace_all(&mnn_path).await;
        assert_eq!(
            c.map.as_ref().unwrap().preset,
            pntr_tests::served_xfeat_mnn()
        );
        let info = client
            .get_map_info(authed(proto::GetMapInfoRequest::default(), CLIENT))
            .await
            .unwrap()
            .into_inner();
        assert_eq!(
            (
                info.preset.as_str(),
                info.built_preset.as_str(),
                info.matcher.as_str()
            ),
            (pntr_tests::served_xfeat_mnn(), "xfeat-mnn", "mnn")
        );
        let v_mnn = c.map.unwrap().version;
        let r = frame(&still.world_from_camera).await;
        assert_eq!(r.map_version, v_mnn);
        // Back to the moved map for the reload below.
        replace_all(&moved_path).await;

        // Reload: only a changed file is read again (here the moved map's file now holds v1).
        let r = running.reload().await.unwrap();
        assert_eq!(r.unchanged_map_ids, ["all"]);
        std::fs::copy(&v1_path, dir.path().join("tmp")).unwrap();
        std::fs::rename(dir.path().join("tmp"), &moved_path).unwrap();
        let r = running.reload().await.unwrap();
        assert_eq!(r.reloaded.len(), 1, "{r:?}");
        assert_eq!(r.reloaded[0].map.as_ref().unwrap().version, v1);
        assert!(!r.reloaded[0].same_frame);
        assert_eq!(frame(&still.world_from_camera).await.map_version, v1);

        // The load saw only answers, each from a version that was being served.
        stop.store(true, Ordering::SeqCst);
        for t in load {
            t.await.unwrap();
        }
        let seen = seen.lock().unwrap().clone();
        assert!(seen.len() >= 4, "{} requests", seen.len());
        for (code, version) in &seen {
            assert_eq!(*code, Code::Ok, "{version}");
            assert!([&v1, &v2, &v3, &v_mnn].contains(&version), "{version}");
        }

        // The replaced maps are freed once their requests are done.
        wait_until(
            || old_maps.iter().all(|w| w.upgrade().is_none()),
            Duration::from_secs(30),
            Duration::from_millis(50),
            "a replaced map is still held",
        )
        .await;

        // /metrics shows the served version only.
        let text = scrape(running.metrics_addr);
        assert!(
            text.contains(&format!(
                "pntr_map_info{{map_id=\"all\",version=\"{v1}\"}} 1"
            )),
            "{text}"
        );
        assert!(
            !text.contains(&v2) && !text.contains(&v3) && !text.contains(&v_mnn),
            "{text}"
        );
        // The unloaded map's gauges are gone; its request counters stay, as counters do (the
        // label takes only ids of maps the server has held).
        assert!(
            !text.contains("pntr_map_info{map_id=\"copy\"")
                && !text.contains("pntr_map_images{map_id=\"copy\""),
            "{text}"
        );

        // Shutdown ends the open stream with UNAVAILABLE at once, not at the 300 s drain's end.
        running.shutdown();
        let e = tokio::time::timeout(Duration::from_secs(60), stream.message())
            .await
            .expect("the stream is ended")
            .unwrap_err();
        assert_eq!(e.code(), Code::Unavailable, "{}", e.message());
        assert!(e.message().contains("reconnect"), "{}", e.message());
        tokio::time::timeout(Duration::from_secs(60), running.wait())
            .await
            .expect("the server stops without waiting for the drain timeout")
            .unwrap();
        drop(tx);
    });
}
