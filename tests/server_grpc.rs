//! `pntr-server` end to end: a real server (the `pntr-service` library, started in-process on
//! 127.0.0.1:0 exactly as the binary starts it) over a map built here from a synthetic scene, called
//! through real gRPC clients.
//!
//! Covered: health flips to SERVING after loading; Localize (raw and PNG/PNG16 frames) and
//! LocalizeStream answer with poses within 0.25 m; GetMapInfo; reflection lists the service; every
//! kind of bad input gets its code and message and the server keeps answering; missing depth is
//! skipped; a full queue gives RESOURCE_EXHAUSTED and a deadline passed while queued
//! DEADLINE_EXCEEDED; a token-protected server refuses calls without the token; a /metrics scrape shows
//! the metrics; shutdown drains an in-flight request.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use pntr_core::{DepthMap, Intrinsics, RgbImage};
use pntr_dataset::View;
use pntr_pipeline::mapfile;
use pntr_service::config::Settings;
use pntr_service::proto::localizer_client::LocalizerClient;
use pntr_service::proto::{self, DepthEncoding, ImageEncoding};
use pntr_service::tokio;
use pntr_service::tokio_stream::wrappers::ReceiverStream;
use pntr_service::tonic::transport::{Channel, Endpoint};
use pntr_service::tonic::{Code, Request};
use pntr_service::tonic_health::pb::health_check_response::ServingStatus;
use pntr_service::tonic_health::pb::health_client::HealthClient;
use pntr_service::tonic_health::pb::HealthCheckRequest;
use pntr_service::{wire, Running};
use pntr_tests::{authed, channel, client, request, runtime, scrape, stop, wait_until};

/// The dataset and map, made once for all tests of this file.
struct Fixture {
    _dir: tempfile::TempDir,
    /// Map `all`.
    map: PathBuf,
    /// The same map saved under the id `copy` (a second map for the server to hold).
    copy: PathBuf,
    /// Query views of the dataset.
    queries: Vec<View>,
}

fn fixture() -> &'static Fixture {
    static F: OnceLock<Fixture> = OnceLock::new();
    F.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let index = pntr_tests::synthetic_dataset(dir.path(), 4, 4, 5);
        let mut built = pntr_tests::build_map(&index, "fast", "all");
        let path = dir.path().join("all.pntrmap");
        mapfile::save(&built, &path).unwrap();
        built.header.map_id = "copy".into();
        // The copy carries a calibration of its own (the shipped weights, a threshold a hair
        // higher, so its answers stay those of `all`): GetMapInfo and the answers say so.
        built.header.calibration = Some(own_calibration(&built));
        let copy = dir.path().join("copy.pntrmap");
        mapfile::save(&built, &copy).unwrap();
        let queries = pntr_tests::query_views(&index);
        assert!(queries.len() >= 8, "{} queries", queries.len());
        Fixture {
            _dir: dir,
            map: path,
            copy,
            queries,
        }
    })
}

/// A map's own calibration as `pntr build-db` would store it, with the shipped weights and
/// [`own_threshold`].
fn own_calibration(map: &pntr_pipeline::map::Map) -> pntr_pipeline::calibration::MapCalibration {
    use pntr_pipeline::calibration::{Calibration, MapCalibration, MAP_FORMAT, MAP_VERSION};
    let base = Calibration::embedded();
    MapCalibration {
        format: MAP_FORMAT.into(),
        version: MAP_VERSION,
        calibration: Calibration {
            threshold: own_threshold(),
            ..base.clone()
        },
        method: "threshold".into(),
        base_threshold: base.threshold,
        base_checksum: base.checksum.clone(),
        regions: 2,
        in_map_queries: 10,
        held_out_queries: 10,
        held_out_right: 1,
        negatives: 9,
        false_positives_base: 1,
        false_positives: 0,
        in_map_recall_base: 1.0,
        in_map_recall: 1.0,
        expected_precision: 1.0,
        images: map.images.len(),
        fingerprint: map.image_fingerprint(),
        checksum: String::new(),
    }
    .sealed()
}

/// The LOCALIZED threshold of map `copy`'s own calibration.
fn own_threshold() -> f64 {
    pntr_pipeline::calibration::Calibration::embedded().threshold + 1e-9
}

async fn health(addr: SocketAddr, service: &str) -> ServingStatus {
    let r = HealthClient::new(channel(addr).await)
        .check(HealthCheckRequest {
            service: service.into(),
        })
        .await
        .unwrap()
        .into_inner();
    ServingStatus::try_from(r.status).unwrap()
}

/// Poll health until SERVING; returns the statuses seen before.
async fn wait_serving(addr: SocketAddr) -> Vec<ServingStatus> {
    let t = Instant::now();
    let mut seen = Vec::new();
    loop {
        let s = health(addr, pntr_service::SERVICE_NAME).await;
        if s == ServingStatus::Serving {
            assert_eq!(health(addr, "").await, ServingStatus::Serving);
            return seen;
        }
        seen.push(s);
        assert!(t.elapsed() < Duration::from_secs(120), "never SERVING");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// How far (metres) the pose of an answer is from `v`'s; `None` when it has no pose.
fn translation_error(r: &proto::LocalizeResponse, v: &View) -> Option<f64> {
    pntr_tests::translation_error(r, &v.world_from_camera)
}

fn in_all(r: proto::LocalizeRequest) -> proto::LocalizeRequest {
    proto::LocalizeRequest {
        map_id: "all".into(),
        ..r
    }
}

/// Call Localize and return the status code (Ok or the error's) with the message.
async fn code_of(c: &mut LocalizerClient<Channel>, r: proto::LocalizeRequest) -> (Code, String) {
    match c.localize(r).await {
        Ok(r) => (Code::Ok, r.into_inner().reason),
        Err(e) => (e.code(), e.message().to_string()),
    }
}

fn settings(dbs: &[&Path]) -> Settings {
    Settings::local(
        dbs.iter().map(|p| p.to_path_buf()).collect(),
        pntr_tests::models(),
    )
}

/// Wait until the worker pool is in the given state (jobs running, jobs queued).
async fn pool_state(running: &Running, busy: usize, queued: usize) {
    let engine = running.state.engine().expect("loaded");
    let t = Instant::now();
    while !(engine.busy() == busy && engine.queued() == queued) {
        assert!(
            t.elapsed() < Duration::from_secs(30),
            "the pool never reached {busy} running, {queued} queued (now {}, {})",
            engine.busy(),
            engine.queued()
        );
        tokio::time::sleep(Duration::from_millis(1)).await;
    }
}

#[test]
fn localizes_reports_and_refuses_bad_input() {
    let f = fixture();
    runtime().block_on(async {
        let mut s = settings(&[&f.map, &f.copy]);
        s.workers = 2;
        s.queue = 16;
        s.max_message_bytes = 1 << 20;
        s.max_image_width = 512;
        s.max_image_height = 512;
        let running = pntr_service::start(s).await.unwrap();
        let addr = running.addr;
        // Loading takes hundreds of milliseconds (two workers' model sessions): health says so.
        let before = wait_serving(addr).await;
        assert!(
            before.iter().all(|s| *s == ServingStatus::NotServing),
            "{before:?}"
        );
        assert!(
            !before.is_empty(),
            "health was SERVING before the models were loaded"
        );
        let mut c = client(addr).await;

        // Raw frames.
        let (mut good, mut total) = (0, 0);
        for (i, v) in f.queries.iter().enumerate() {
            let mut req = Request::new(request(v, "all"));
            if i == 0 {
                req.metadata_mut()
                    .insert("x-request-id", "from-metadata".parse().unwrap());
            }
            let resp = c.localize(req).await.unwrap();
            let echoed = resp.metadata().get("x-request-id").cloned();
            let r = resp.into_inner();
            if i == 0 {
                assert_eq!(r.request_id, "from-metadata");
                assert_eq!(echoed.unwrap(), "from-metadata");
            } else {
                assert_eq!(r.request_id.len(), 16, "a generated id");
            }
            assert_eq!(r.map_id, "all");
            let stages: Vec<&str> = r.timings.iter().map(|t| t.stage.as_str()).collect();
            assert_eq!(
                stages,
                [
                    "queue",
                    "resampling",
                    "extraction",
                    "retrieval",
                    "matching",
                    "registration",
                    "verification",
                    "total"
                ]
            );
            assert!(!r.retrieved_image_ids.is_empty());
            total += 1;
            if r.status == proto::Status::Localized as i32 {
                assert!(r.reason.is_empty() && r.inliers >= 12 && !r.matched_image_id.is_empty());
                assert!(r.confidence >= r.min_confidence && r.confidence <= 1.0);
                assert_eq!(r.covariance.len(), 36);
                good += translation_error(&r, v).is_some_and(|e| e < 0.25) as usize;
            } else {
                assert_eq!(r.status, proto::Status::NotLocalized as i32);
                assert!(r.pose.is_none() && !r.reason.is_empty() && r.covariance.is_empty());
            }
        }
        eprintln!("{good} of {total} raw queries within 0.25 m");
        assert!(good as f64 >= 0.7 * total as f64, "{good} of {total}");

        // A PNG + PNG16 pair, with explicit intrinsics and its own request id.
        let v = &f.queries[0];
        let k = Intrinsics::hpointloc();
        let mut req = wire::png_request(&v.rgb, &v.depth, Some(&k)).unwrap();
        req.request_id = "png-1".into();
        req.map_id = "all".into();
        let r = c.localize(req).await.unwrap().into_inner();
        assert_eq!(r.request_id, "png-1");
        let e = translation_error(&r, v).expect("the PNG frame localizes");
        assert!(e < 0.25, "PNG frame off by {e} m");

        // Missing depth in every form (NaN, 0, negative, inf) is skipped, not refused.
        let mut depth = v.depth.clone();
        for (i, d) in depth.data.iter_mut().enumerate() {
            if (i / 256) % 2 == 1 {
                *d = [f32::NAN, 0.0, -1.0, f32::INFINITY][i % 4];
            }
        }
        let (code, msg) = code_of(&mut c, {
            let mut q = wire::raw_request(&v.rgb, &depth, None);
            q.map_id = "all".into();
            q
        })
        .await;
        assert_eq!(code, Code::Ok, "{msg}");

        // The stream answers each frame in order.
        let frames: Vec<proto::LocalizeRequest> = f.queries[..3]
            .iter()
            .enumerate()
            .map(|(i, v)| proto::LocalizeRequest {
                request_id: format!("s{i}"),
                ..request(v, "copy")
            })
            .collect();
        let mut out = c
            .localize_stream(tokio_stream(frames))
            .await
            .unwrap()
            .into_inner();
        let mut ids = Vec::new();
        while let Some(r) = out.message().await.unwrap() {
            assert_eq!(r.map_id, "copy");
            ids.push(r.request_id);
        }
        assert_eq!(ids, ["s0", "s1", "s2"]);

        // GetMapInfo.
        let info = c
            .get_map_info(proto::GetMapInfoRequest {
                map_id: "all".into(),
            })
            .await
            .unwrap()
            .into_inner();
        assert_eq!(info.map_id, "all");
        assert_eq!(info.points, 4);
        assert_eq!(info.images, 24);
        assert_eq!(info.preset, "fast");
        assert_eq!(info.camera_axes, "habitat");
        assert_eq!((info.image_width, info.image_height), (256, 256));
        assert_eq!(info.loaded_map_ids, ["all", "copy"]);
        // Which calibration answers use, and what it was fitted on.
        let cal = info.calibration.unwrap();
        assert_eq!(cal.source, "shipped");
        let shipped = pntr_pipeline::calibration::Calibration::embedded();
        assert_eq!(cal.threshold, shipped.threshold);
        assert_eq!(cal.fitted_on, shipped.fitted_on.datasets);
        let copy = c
            .get_map_info(proto::GetMapInfoRequest {
                map_id: "copy".into(),
            })
            .await
            .unwrap()
            .into_inner()
            .calibration
            .unwrap();
        assert_eq!(copy.source, "map");
        assert_eq!(copy.threshold, own_threshold());
        assert_eq!(
            (copy.regions, copy.negatives, copy.false_positives),
            (2, 9, 0)
        );
        assert!(!copy.stale);
        let answer = c.localize(request(v, "copy")).await.unwrap().into_inner();
        assert_eq!(answer.min_confidence, own_threshold());
        let e = c
            .get_map_info(proto::GetMapInfoRequest::default())
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument);
        assert!(e.message().contains("2 maps"), "{}", e.message());

        // Every bad input: its code and a message that says what is wrong.
        let rgb = &v.rgb;
        let good_req = request(v, "all");
        let with = |edit: &dyn Fn(&mut proto::LocalizeRequest)| {
            let mut r = good_req.clone();
            edit(&mut r);
            r
        };
        // HPointLoc's principal point with the focal lengths given.
        let focal = |fx: f64, fy: f64| {
            Some(proto::Intrinsics {
                fx,
                fy,
                cx: 127.5,
                cy: 127.5,
                distortion: Vec::new(),
            })
        };
        let small = RgbImage::new(128, 256, rgb.data[..128 * 256 * 3].to_vec()).unwrap();
        let big = (600u32, 100u32);
        let cases: Vec<(&str, proto::LocalizeRequest, Code, &str)> = vec![
            (
                "no rgb",
                with(&|r| r.rgb = None),
                Code::InvalidArgument,
                "rgb is missing",
            ),
            (
                "no depth",
                with(&|r| r.depth = None),
                Code::InvalidArgument,
                "depth is missing",
            ),
            (
                "width vs data",
                with(&|r| r.rgb.as_mut().unwrap().width = 250),
                Code::InvalidArgument,
                "bytes",
            ),
            (
                "depth height vs data",
                with(&|r| r.depth.as_mut().unwrap().height = 200),
                Code::InvalidArgument,
                "bytes",
            ),
            (
                "rgb vs depth size",
                with(&|r| r.rgb = wire::raw_request(&small, &v.depth, None).rgb),
                Code::InvalidArgument,
                "same size",
            ),
            (
                "bad PNG",
                with(&|r| r.rgb.as_mut().unwrap().encoding = ImageEncoding::Png as i32),
                Code::InvalidArgument,
                "not a readable PNG",
            ),
            (
                "bad JPEG",
                with(&|r| {
                    let im = r.rgb.as_mut().unwrap();
                    im.encoding = ImageEncoding::Jpeg as i32;
                    im.data = b"\xff\xd8\xff\xe0 definitely not a jpeg".to_vec();
                }),
                Code::InvalidArgument,
                "JPEG",
            ),
            (
                "bad PNG16",
                with(&|r| {
                    let d = r.depth.as_mut().unwrap();
                    d.encoding = DepthEncoding::Png16Millimeters as i32;
                    d.data = b"\x89PNG\r\n\x1a\n truncated".to_vec();
                }),
                Code::InvalidArgument,
                "PNG",
            ),
            (
                "unspecified image encoding",
                with(&|r| r.rgb.as_mut().unwrap().encoding = 0),
                Code::InvalidArgument,
                "IMAGE_ENCODING_UNSPECIFIED",
            ),
            (
                "unspecified depth encoding",
                with(&|r| r.depth.as_mut().unwrap().encoding = 0),
                Code::InvalidArgument,
                "DEPTH_ENCODING_UNSPECIFIED",
            ),
            (
                "zero focal length",
                with(&|r| r.intrinsics = focal(0.0, 128.0)),
                Code::InvalidArgument,
                "focal",
            ),
            (
                "negative focal length",
                with(&|r| r.intrinsics = focal(128.0, -128.0)),
                Code::InvalidArgument,
                "focal",
            ),
            (
                "NaN focal length",
                with(&|r| r.intrinsics = focal(f64::NAN, 128.0)),
                Code::InvalidArgument,
                "focal",
            ),
            (
                "no intrinsics for a non-HPointLoc size",
                {
                    let rgb = RgbImage::new(64, 32, vec![100; 64 * 32 * 3]).unwrap();
                    let d = DepthMap::from_metres(64, 32, vec![1.0; 64 * 32]).unwrap();
                    in_all(wire::raw_request(&rgb, &d, None))
                },
                Code::InvalidArgument,
                "intrinsics required",
            ),
            (
                "too large",
                {
                    let rgb = RgbImage::new(big.0, big.1, vec![100; 600 * 100 * 3]).unwrap();
                    let d = DepthMap::from_metres(big.0, big.1, vec![1.0; 600 * 100]).unwrap();
                    let k = Intrinsics::from_fov(big.0, big.1, 90.0);
                    in_all(wire::raw_request(&rgb, &d, Some(&k)))
                },
                Code::InvalidArgument,
                "limit of 512x512",
            ),
            (
                "no valid depth",
                {
                    let d = DepthMap {
                        width: 256,
                        height: 256,
                        data: [f32::NAN, 0.0, -3.0, f32::INFINITY]
                            .into_iter()
                            .cycle()
                            .take(256 * 256)
                            .collect(),
                    };
                    in_all(wire::raw_request(rgb, &d, None))
                },
                Code::InvalidArgument,
                "no valid pixel",
            ),
            (
                "several maps, none named",
                with(&|r| r.map_id.clear()),
                Code::InvalidArgument,
                "holds 2 maps",
            ),
            (
                "unknown map",
                with(&|r| r.map_id = "nope".into()),
                Code::NotFound,
                "nope",
            ),
            (
                "oversized message",
                {
                    // 1.2 MB of pixels: over the server's 1 MiB message limit.
                    let (w, h) = (400u32, 400u32);
                    let rgb = RgbImage::new(w, h, vec![7; (w * h * 3) as usize]).unwrap();
                    let d = DepthMap::from_metres(w, h, vec![1.0; (w * h) as usize]).unwrap();
                    in_all(wire::raw_request(
                        &rgb,
                        &d,
                        Some(&Intrinsics::from_fov(w, h, 90.0)),
                    ))
                },
                Code::OutOfRange,
                "too large",
            ),
        ];
        for (name, req, want, text) in cases {
            let (code, msg) = code_of(&mut c, req).await;
            assert_eq!(code, want, "{name}: {msg}");
            assert!(msg.contains(text), "{name}: `{msg}` lacks `{text}`");
        }
        // Still healthy and still answering.
        assert_eq!(health(addr, "").await, ServingStatus::Serving);
        let r = c.localize(request(v, "all")).await.unwrap().into_inner();
        assert!(translation_error(&r, v).is_some_and(|e| e < 0.25), "{r:?}");

        // Reflection lists the service, in both protocol versions (older grpcurl, Python's
        // grpcio-reflection and GUI clients speak only v1alpha).
        let services = reflection_services(addr).await;
        let alpha = reflection_services_v1alpha(addr).await;
        for s in ["pntr.v1.Localizer", "grpc.health.v1.Health"] {
            assert!(alpha.iter().any(|x| x == s), "v1alpha lacks {s}: {alpha:?}");
        }
        assert!(
            services.iter().any(|s| s == "pntr.v1.Localizer"),
            "{services:?}"
        );
        assert!(
            services.iter().any(|s| s == "grpc.health.v1.Health"),
            "{services:?}"
        );

        // Metrics.
        let text = scrape(running.metrics_addr);
        for name in [
            "pntr_stage_duration_seconds_bucket{stage=\"extraction\"",
            "pntr_stage_duration_seconds_bucket{stage=\"queue\"",
            "pntr_stage_duration_seconds_bucket{stage=\"verification\"",
            "pntr_stage_duration_seconds_count{stage=\"total\",map_id=\"all\"}",
            "pntr_requests_total{status=\"LOCALIZED\",code=\"OK\",map_id=\"all\"}",
            "pntr_requests_total{status=\"ERROR\",code=\"INVALID_ARGUMENT\",map_id=",
            // A map id the server does not hold never becomes a label value.
            "pntr_requests_total{status=\"ERROR\",code=\"NOT_FOUND\",map_id=\"\"}",
            "pntr_answers_total{mode=\"GLOBAL\",map_id=\"all\"}",
            "pntr_in_flight_requests",
            "pntr_queue_depth",
            "pntr_map_images{map_id=\"all\"} 24",
            // What a fleet's supervisor watches: how close answers sit to the threshold, and
            // whether a map's calibration is stale.
            "pntr_answer_confidence_bucket{status=\"LOCALIZED\",map_id=\"all\",le=\"0.5\"}",
            "pntr_answer_confidence_count{status=\"LOCALIZED\",map_id=\"all\"}",
            "pntr_map_calibration_stale{map_id=\"all\"} 0",
        ] {
            assert!(text.contains(name), "the scrape lacks {name}:\n{text}");
        }
        // Nothing from requests' content in the labels.
        assert!(!text.contains("png-1") && !text.contains("from-metadata"));
        stop(running).await;
    });
}

/// The answers of one LocalizeStream call over `frames`, sent one at a time; the first error.
async fn stream_answers(
    c: &mut LocalizerClient<Channel>,
    frames: Vec<proto::LocalizeRequest>,
) -> Result<Vec<proto::LocalizeResponse>, pntr_service::tonic::Status> {
    let (tx, rx) = tokio::sync::mpsc::channel(1);
    let mut out = c
        .localize_stream(ReceiverStream::new(rx))
        .await?
        .into_inner();
    let mut answers = Vec::new();
    for frame in frames {
        tx.send(frame).await.expect("the stream is open");
        match out.message().await? {
            Some(r) => answers.push(r),
            None => break,
        }
    }
    Ok(answers)
}

fn tokio_stream(
    frames: Vec<proto::LocalizeRequest>,
) -> impl pntr_service::tokio_stream::Stream<Item = proto::LocalizeRequest> {
    pntr_service::tokio_stream::iter(frames)
}

/// The services a reflection client of one protocol version lists.
macro_rules! reflection_services {
    ($name:ident, $version:ident) => {
        async fn $name(addr: SocketAddr) -> Vec<String> {
            use pntr_service::tonic_reflection::pb::$version::server_reflection_client::ServerReflectionClient;
            use pntr_service::tonic_reflection::pb::$version::server_reflection_request::MessageRequest;
            use pntr_service::tonic_reflection::pb::$version::server_reflection_response::MessageResponse;
            use pntr_service::tonic_reflection::pb::$version::ServerReflectionRequest;
            let req = ServerReflectionRequest {
                host: String::new(),
                message_request: Some(MessageRequest::ListServices(String::new())),
            };
            let mut out = ServerReflectionClient::new(channel(addr).await)
                .server_reflection_info(tokio_stream_one(req))
                .await
                .unwrap()
                .into_inner();
            let r = out.message().await.unwrap().unwrap();
            match r.message_response {
                Some(MessageResponse::ListServicesResponse(l)) => {
                    l.service.into_iter().map(|s| s.name).collect()
                }
                other => panic!("unexpected reflection answer {other:?}"),
            }
        }
    };
}
reflection_services!(reflection_services, v1);
reflection_services!(reflection_services_v1alpha, v1alpha);

fn tokio_stream_one<T: Send + 'static>(x: T) -> impl pntr_service::tokio_stream::Stream<Item = T> {
    pntr_service::tokio_stream::iter([x])
}

/// A request for `v` in ROS or map conventions (`None`: the server's default), naming the map only
/// in `x-pntr-map-id` metadata, as a proxy-routed client does.
fn routed(
    v: &View,
    map_id: &str,
    convention: Option<proto::FrameConvention>,
) -> Request<proto::LocalizeRequest> {
    let mut req = Request::new(proto::LocalizeRequest {
        frame_convention: convention.map_or(0, |c| c as i32),
        ..wire::raw_request(&v.rgb, &v.depth, None)
    });
    req.metadata_mut().insert(
        pntr_service::service::MAP_ID_HEADER,
        map_id.parse().unwrap(),
    );
    req
}

#[test]
fn ros_conventions_and_routing_by_map_id_metadata() {
    use pntr_core::pose::{map_to_ros, ros_from_map_world, rotate_covariance, UpAxis};
    let f = fixture();
    runtime().block_on(async {
        let mut s = settings(&[&f.map, &f.copy]);
        s.frame_convention = proto::FrameConvention::Ros;
        let running = pntr_service::start(s).await.unwrap();
        wait_serving(running.addr).await;
        let mut c = client(running.addr).await;

        // GetMapInfo names the map by metadata too, and says how to turn its frame into ROS's.
        let mut req = Request::new(proto::GetMapInfoRequest::default());
        req.metadata_mut().insert(
            pntr_service::service::MAP_ID_HEADER,
            "copy".parse().unwrap(),
        );
        let info = c.get_map_info(req).await.unwrap().into_inner();
        assert_eq!(info.map_id, "copy");
        assert_eq!(info.frame_convention, proto::FrameConvention::Ros as i32);
        let q = info.ros_from_map.and_then(|p| p.rotation).unwrap();
        let want = ros_from_map_world(UpAxis::Y);
        assert!(
            (q.w - want.w).abs() < 1e-12 && (q.x - want.i).abs() < 1e-12,
            "{q:?}"
        );

        let mut compared = 0;
        for v in f.queries.iter().take(6) {
            // The server's default (ROS here) against an explicit MAP answer of the same frame.
            let ros = c
                .localize(routed(v, "copy", None))
                .await
                .unwrap()
                .into_inner();
            let map = c
                .localize(routed(v, "copy", Some(proto::FrameConvention::Map)))
                .await
                .unwrap()
                .into_inner();
            assert_eq!(ros.map_id, "copy", "the metadata named the map");
            assert_eq!(ros.frame_convention, proto::FrameConvention::Ros as i32);
            assert_eq!(map.frame_convention, proto::FrameConvention::Map as i32);
            let (Some(pr), Some(pm)) =
                (wire::pose(ros.pose.as_ref()), wire::pose(map.pose.as_ref()))
            else {
                continue;
            };
            assert!(ros.pose.as_ref().unwrap().rotation.as_ref().unwrap().w >= 0.0);
            assert!(map.pose.as_ref().unwrap().rotation.as_ref().unwrap().w >= 0.0);
            // The same answer, re-expressed: z-up world, optical camera.
            let expect = map_to_ros(&pm, UpAxis::Y, pntr_core::CameraAxes::Habitat);
            assert!(
                (pr.translation.vector - expect.translation.vector).norm() < 1e-3,
                "{pr} vs {expect}"
            );
            assert!(pr.rotation.angle_to(&expect.rotation).to_degrees() < 0.05);
            // The camera's height (the map's y) is ROS's z; the optical z axis is the view direction.
            let truth = map_to_ros(
                &v.world_from_camera,
                UpAxis::Y,
                pntr_core::CameraAxes::Habitat,
            );
            if (pm.translation.vector - v.world_from_camera.translation.vector).norm() < 0.25 {
                assert!((pr.translation.z - v.world_from_camera.translation.y).abs() < 0.25);
                let forward = pr.rotation * nalgebra::Vector3::z();
                let forward_truth = truth.rotation * nalgebra::Vector3::z();
                assert!(
                    forward.dot(&forward_truth) > 0.99,
                    "{forward} vs {forward_truth}"
                );
            }
            let rotated =
                rotate_covariance(&map.covariance, &ros_from_map_world(UpAxis::Y)).unwrap();
            for (a, b) in ros.covariance.iter().zip(&rotated) {
                assert!(
                    (a - b).abs() <= 1e-3 * b.abs().max(1e-9),
                    "{:?}\nvs\n{rotated:?}",
                    ros.covariance
                );
            }
            // A prior given in ROS conventions is read in ROS conventions: a 1.5 m region around
            // the ROS position answers through the prior.
            if compared == 0 {
                let mut req = routed(v, "copy", Some(proto::FrameConvention::Ros));
                req.get_mut().prior = Some(proto::Prior {
                    pose: Some(wire::to_proto_pose(&pr)),
                    covariance: Vec::new(),
                    radius_m: 1.5,
                });
                let r = c.localize(req).await.unwrap().into_inner();
                assert_eq!(r.status, proto::Status::Localized as i32, "{}", r.reason);
                assert_eq!(r.mode, proto::Mode::Prior as i32);
            }
            compared += 1;
        }
        assert!(
            compared >= 3,
            "only {compared} of 6 frames localized in both conventions"
        );

        // A convention this server does not know is the caller's mistake.
        let mut req = routed(&f.queries[0], "copy", None);
        req.get_mut().frame_convention = 7;
        let e = c.localize(req).await.unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument);
        assert!(e.message().contains("frame_convention"), "{}", e.message());
        // Frames and cameras no sensor makes are the caller's mistake, named, before any work.
        let strip = |w: u32, h: u32| {
            let rgb = pntr_core::RgbImage {
                width: w,
                height: h,
                data: vec![128; (w * h * 3) as usize],
            };
            let depth = pntr_core::DepthMap {
                width: w,
                height: h,
                data: vec![2.0; (w * h) as usize],
            };
            (rgb, depth)
        };
        let (rgb, depth) = strip(4096, 2);
        let k = pntr_core::Intrinsics {
            fx: 2000.0,
            fy: 2000.0,
            cx: 2047.5,
            cy: 0.5,
            width: 4096,
            height: 2,
            distortion: [0.0; 5],
        };
        let (rgb256, depth256) = strip(256, 256);
        let camera = |fx: f64, fy: f64| pntr_core::Intrinsics {
            fx,
            fy,
            ..pntr_core::Intrinsics::hpointloc()
        };
        for (req, needle) in [
            (wire::raw_request(&rgb, &depth, Some(&k)), "aspect ratio"),
            (
                wire::raw_request(&rgb256, &depth256, Some(&camera(1.0, 1e6))),
                "differ by a factor",
            ),
            (
                wire::raw_request(&rgb256, &depth256, Some(&camera(1.0, 1.0))),
                "field of view",
            ),
        ] {
            let (code, message) = code_of(&mut c, in_all(req)).await;
            assert_eq!(code, Code::InvalidArgument, "{needle}: {message}");
            assert!(message.contains(needle), "{message}");
        }
        // The message's map_id wins over the metadata; an unknown id never becomes a label.
        let mut req = routed(&f.queries[0], "nosuch-building", None);
        req.get_mut().map_id = "all".into();
        assert_eq!(c.localize(req).await.unwrap().into_inner().map_id, "all");
        let e = c
            .localize(routed(&f.queries[0], "nosuch-building", None))
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::NotFound);
        let text = scrape(running.metrics_addr);
        assert!(text.contains("map_id=\"copy\""), "{text}");
        assert!(!text.contains("nosuch-building"), "{text}");
        stop(running).await;
    });
}

/// `--foxglove`: a plain WebSocket client speaking the Foxglove protocol (subprotocol
/// `foxglove.sdk.v1`) sees the channels advertised with their schemas, subscribes to the answers and
/// the poses, and receives the pose of a frame another client localizes over gRPC.
#[test]
fn foxglove_live_view_streams_answers_to_a_websocket_client() {
    use futures_util::{SinkExt, StreamExt};
    use tokio_tungstenite::tungstenite::{client::IntoClientRequest, Message};
    let f = fixture();
    runtime().block_on(async {
        let mut s = settings(&[&f.map]);
        s.foxglove = Some("127.0.0.1:0".parse().unwrap());
        let running = pntr_service::start(s).await.unwrap();
        running.ready().await.unwrap();
        let ws_addr = running.foxglove_addr.expect("the live view is on");
        let offering = |protocol: Option<&str>| {
            let mut req = format!("ws://{ws_addr}").into_client_request().unwrap();
            if let Some(p) = protocol {
                req.headers_mut()
                    .insert("sec-websocket-protocol", p.parse().unwrap());
            }
            req
        };
        // A viewer offering nothing the view speaks is told which names work.
        for offer in [None, Some("graphql-ws")] {
            let e = tokio_tungstenite::connect_async(offering(offer))
                .await
                .unwrap_err();
            let tokio_tungstenite::tungstenite::Error::Http(r) = e else {
                panic!("{offer:?}: {e}");
            };
            assert_eq!(r.status(), 400);
            let body =
                String::from_utf8_lossy(r.body().as_deref().unwrap_or_default()).into_owned();
            assert!(
                body.contains("foxglove.sdk.v1") && body.contains("foxglove.websocket.v1"),
                "{body}"
            );
        }
        // A viewer that subscribes to everything and never reads (a stalled laptop on Wi-Fi): its
        // messages are dropped, the robots' answers and the other viewer go on.
        let (mut stalled, r) = tokio_tungstenite::connect_async(offering(Some("foxglove.sdk.v1")))
            .await
            .unwrap();
        assert_eq!(r.headers()["sec-websocket-protocol"], "foxglove.sdk.v1");
        let mut stalled_channels = Vec::new();
        while stalled_channels.len() < 7 {
            if let Some(Ok(Message::Text(t))) = stalled.next().await {
                let v: serde_json::Value = serde_json::from_str(&t).unwrap();
                if v["op"] == "advertise" {
                    stalled_channels.extend(
                        v["channels"]
                            .as_array()
                            .unwrap()
                            .iter()
                            .map(|c| c["id"].as_u64().unwrap()),
                    );
                }
            }
        }
        let all: Vec<_> = stalled_channels
            .iter()
            .enumerate()
            .map(|(i, c)| serde_json::json!({"id": i, "channelId": c}))
            .collect();
        stalled
            .send(Message::Text(
                serde_json::json!({"op": "subscribe", "subscriptions": all})
                    .to_string()
                    .into(),
            ))
            .await
            .unwrap();
        // The viewer followed below asks for the protocol's earlier name, as older Foxglove and
        // Lichtblick do, and is answered under it.
        let (mut ws, r) = tokio_tungstenite::connect_async(offering(Some("foxglove.websocket.v1")))
            .await
            .unwrap();
        assert_eq!(
            r.headers()["sec-websocket-protocol"],
            "foxglove.websocket.v1"
        );
        // serverInfo, then the advertisements.
        let mut channels: BTreeMap<String, (u64, String)> = BTreeMap::new();
        let deadline = Instant::now() + Duration::from_secs(20);
        while channels.len() < 7 {
            assert!(Instant::now() < deadline, "advertised only {channels:?}");
            let Some(Ok(Message::Text(t))) = ws.next().await else {
                continue;
            };
            let v: serde_json::Value = serde_json::from_str(&t).unwrap();
            if v["op"] == "advertise" {
                for c in v["channels"].as_array().unwrap() {
                    channels.insert(
                        c["topic"].as_str().unwrap().into(),
                        (
                            c["id"].as_u64().unwrap(),
                            c["schemaName"].as_str().unwrap_or("").into(),
                        ),
                    );
                }
            }
        }
        assert_eq!(
            channels["/pntr/pose"].1, "foxglove.PoseInFrame",
            "{channels:?}"
        );
        assert_eq!(channels["/pntr/camera/image"].1, "foxglove.CompressedImage");
        assert_eq!(channels["/pntr/answer"].1, "pntr.Answer");
        let subscribe = serde_json::json!({"op": "subscribe", "subscriptions": [
            {"id": 1, "channelId": channels["/pntr/answer"].0},
            {"id": 2, "channelId": channels["/pntr/pose"].0},
            {"id": 3, "channelId": channels["/pntr/camera/image"].0},
            {"id": 4, "channelId": channels["/pntr/map/cameras"].0},
        ]});
        ws.send(Message::Text(subscribe.to_string().into()))
            .await
            .unwrap();
        // Localize over gRPC until the view shows a LOCALIZED answer with its pose and image.
        let mut c = client(running.addr).await;
        let (mut answers, mut poses, mut images, mut map_cameras) = (Vec::new(), 0, 0, 0);
        let deadline = Instant::now() + Duration::from_secs(60);
        let (mut sent, mut last_sent) = (0, Instant::now());
        while !(answers
            .iter()
            .any(|a: &serde_json::Value| a["status"] == "LOCALIZED")
            && poses > 0
            && images > 0
            && map_cameras > 0)
        {
            assert!(
                Instant::now() < deadline,
                "{answers:?} {poses} {images} {map_cameras}"
            );
            // The next frame once this one is shown, or after a second (a frame is skipped when the
            // view's thread is busy).
            if sent < f.queries.len()
                && (answers.len() == sent || last_sent.elapsed() > Duration::from_secs(1))
            {
                c.localize(request(&f.queries[sent], "")).await.unwrap();
                sent += 1;
                last_sent = Instant::now();
            }
            let next = tokio::time::timeout(Duration::from_millis(500), ws.next()).await;
            let Ok(Some(Ok(Message::Binary(b)))) = next else {
                continue;
            };
            // Opcode 1 (message data), subscription id, log time, payload.
            assert_eq!(b[0], 1);
            let sub = u32::from_le_bytes(b[1..5].try_into().unwrap());
            let payload = &b[13..];
            match sub {
                1 => answers.push(serde_json::from_slice(payload).unwrap()),
                2 => poses += 1,
                3 => images += 1,
                4 => map_cameras += 1,
                other => panic!("subscription {other}"),
            }
        }
        let a = answers.iter().find(|a| a["status"] == "LOCALIZED").unwrap();
        assert_eq!(a["map_id"], "all");
        assert_eq!(a["track_state"], "", "a single frame has no track");
        // ROS conventions: the y-up scene's camera height is the pose's z.
        let z = a["pose"]["position"][2].as_f64().unwrap();
        assert!((0.5..2.0).contains(&z), "{a}");
        // Many more frames while the stalled viewer still reads nothing: every one answered, and
        // the reading viewer keeps up to the end (frames are skipped when the view's thread is
        // busy, so frames go on until one of the 40th or later is shown).
        let late = |i: usize| proto::LocalizeRequest {
            request_id: format!("late-{i}"),
            ..request(&f.queries[i % f.queries.len()], "")
        };
        for i in 0..40 {
            c.localize(late(i)).await.unwrap();
        }
        let (deadline, mut i) = (Instant::now() + Duration::from_secs(60), 40);
        'shown: loop {
            assert!(
                Instant::now() < deadline,
                "late frames never reached the reading viewer"
            );
            while let Ok(Some(Ok(m))) =
                tokio::time::timeout(Duration::from_millis(300), ws.next()).await
            {
                let Some(a) = shown_answer(m) else { continue };
                let n = a["request_id"]
                    .as_str()
                    .and_then(|r| r.strip_prefix("late-"));
                if n.and_then(|n| n.parse::<usize>().ok())
                    .is_some_and(|n| n >= 39)
                {
                    break 'shown;
                }
            }
            c.localize(late(i)).await.unwrap();
            i += 1;
        }
        // A stream's answers are shown as the stream gives them (after its track took them),
        // with the track's state.
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        let mut replies = c
            .localize_stream(ReceiverStream::new(rx))
            .await
            .unwrap()
            .into_inner();
        let mut given = std::collections::HashMap::new();
        let deadline = Instant::now() + Duration::from_secs(60);
        let mut k = 0;
        'streamed: loop {
            assert!(
                Instant::now() < deadline,
                "no stream answer reached the viewer"
            );
            let frame = proto::LocalizeRequest {
                request_id: format!("streamed-{k}"),
                ..request(&f.queries[k % f.queries.len()], "")
            };
            tx.send(frame).await.unwrap();
            let r = replies.message().await.unwrap().unwrap();
            given.insert(r.request_id.clone(), r);
            k += 1;
            while let Ok(Some(Ok(m))) =
                tokio::time::timeout(Duration::from_millis(300), ws.next()).await
            {
                let Some(a) = shown_answer(m) else { continue };
                let Some(r) = a["request_id"].as_str().and_then(|id| given.get(id)) else {
                    continue;
                };
                let state = wire::track_state_label(r.track_state);
                assert!(!state.is_empty(), "{r:?}");
                assert_eq!(a["track_state"], state, "{a}");
                let localized = r.status == proto::Status::Localized as i32;
                assert_eq!(
                    a["status"],
                    if localized {
                        "LOCALIZED"
                    } else {
                        "NOT_LOCALIZED"
                    },
                    "{a}"
                );
                assert_eq!(a["reason"], r.reason.as_str(), "{a}");
                assert_eq!(a["pose"].is_null(), !localized, "{a}");
                break 'streamed;
            }
        }
        drop(tx);
        assert_eq!(
            running.state.live().map(|l| l.clients()),
            Some(2),
            "both viewers are still connected"
        );
        drop(stalled);
        stop(running).await;
    });
}

/// The `/pntr/answer` JSON a live-view message carries, when it is one (subscription 1; opcode,
/// subscription id, log time, then the payload).
fn shown_answer(m: tokio_tungstenite::tungstenite::Message) -> Option<serde_json::Value> {
    use tokio_tungstenite::tungstenite::Message;
    let Message::Binary(b) = m else { return None };
    (u32::from_le_bytes(b[1..5].try_into().unwrap()) == 1)
        .then(|| serde_json::from_slice(&b[13..]).unwrap())
}

#[test]
fn overload_deadlines_auth_and_drain() {
    let f = fixture();
    runtime().block_on(async {
        let mut s = settings(&[&f.map]);
        s.workers = 1;
        s.queue = 1;
        s.token = Some("t0ken-for-tests".into());
        let mut running = pntr_service::start(s).await.unwrap();
        let addr = running.addr;
        running.ready().await.unwrap();
        // Health needs no token.
        assert_eq!(health(addr, "").await, ServingStatus::Serving);
        let mut c = client(addr).await;
        let v = &f.queries[0];

        // Without the token, or with a wrong one: UNAUTHENTICATED, for every RPC.
        let e = c.localize(request(v, "")).await.unwrap_err();
        assert_eq!(e.code(), Code::Unauthenticated);
        assert!(!e.message().contains("t0ken"), "{}", e.message());
        let e = c
            .localize(authed(request(v, ""), "wrong"))
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::Unauthenticated);
        let e = c
            .get_map_info(proto::GetMapInfoRequest::default())
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::Unauthenticated);
        let r = c
            .localize(authed(request(v, ""), "t0ken-for-tests"))
            .await
            .unwrap()
            .into_inner();
        assert_eq!(r.map_id, "all", "an empty map id means the only map");
        let single_s = r
            .timings
            .iter()
            .find(|t| t.stage == "total")
            .unwrap()
            .seconds;
        eprintln!("one localization: {:.0} ms", single_s * 1e3);

        // Overload: one worker, one queue slot, many concurrent calls.
        let mut tasks = Vec::new();
        for _ in 0..8 {
            let mut c = c.clone();
            let req = authed(request(v, ""), "t0ken-for-tests");
            tasks.push(tokio::spawn(async move {
                match c.localize(req).await {
                    Ok(_) => (Code::Ok, String::new()),
                    Err(e) => (e.code(), e.message().to_string()),
                }
            }));
        }
        let mut codes = Vec::new();
        for t in tasks {
            codes.push(t.await.unwrap());
        }
        let ok = codes.iter().filter(|(c, _)| *c == Code::Ok).count();
        let busy: Vec<_> = codes
            .iter()
            .filter(|(c, _)| *c == Code::ResourceExhausted)
            .collect();
        assert_eq!(ok + busy.len(), codes.len(), "{codes:?}");
        assert!(ok >= 1 && !busy.is_empty(), "{codes:?}");
        assert!(busy[0].1.contains("busy"), "{}", busy[0].1);

        // A deadline that passes while the request waits for the busy worker: DEADLINE_EXCEEDED.
        pool_state(&running, 0, 0).await;
        let mut c1 = c.clone();
        let long = tokio::spawn({
            let req = authed(request(v, ""), "t0ken-for-tests");
            async move { c1.localize(req).await.map(|_| ()) }
        });
        pool_state(&running, 1, 0).await;
        let mut req = authed(request(v, ""), "t0ken-for-tests");
        // Three quarters of a localization: ample to send the frame, short of the time the worker
        // needs before it could answer (the rest of the first request's run, then this one's
        // whole run). (A deadline that passes before the message is even received is answered
        // by tonic's transport, as CANCELLED; the service answers DEADLINE_EXCEEDED from then on.
        // Half a localization was at times too short to deliver the frame under the parallel
        // test runner.)
        let budget = Duration::from_secs_f64((0.75 * single_s).clamp(0.02, 0.5));
        req.set_timeout(budget);
        let e = c.localize(req).await.unwrap_err();
        assert_eq!(e.code(), Code::DeadlineExceeded, "{}", e.message());
        long.await.unwrap().unwrap();

        // Shutdown drains an in-flight request, then stops. (The expired request above is still
        // queued until the worker is free; it is dropped without running.)
        pool_state(&running, 0, 0).await;
        let mut c2 = c.clone();
        let in_flight = tokio::spawn({
            let req = authed(request(v, ""), "t0ken-for-tests");
            async move { c2.localize(req).await }
        });
        pool_state(&running, 1, 0).await;
        running.shutdown();
        let r = in_flight
            .await
            .unwrap()
            .expect("the in-flight request finishes");
        assert!(!r.into_inner().map_id.is_empty());
        tokio::time::timeout(Duration::from_secs(30), running.wait())
            .await
            .expect("stops after draining")
            .unwrap();
        assert!(
            Endpoint::from_shared(format!("http://{addr}"))
                .unwrap()
                .connect()
                .await
                .is_err(),
            "still accepting after shutdown"
        );
    });
}

/// A prior of `radius_m` around `center` (map frame, metres).
fn prior_at(center: nalgebra::Vector3<f64>, radius_m: f64) -> proto::Prior {
    wire::prior_message(&pntr_pipeline::prior::Region {
        center_m: center,
        radius_m,
    })
}

fn mode_of(r: &proto::LocalizeResponse) -> proto::Mode {
    proto::Mode::try_from(r.mode).unwrap()
}

/// Priors: a right one answers through the prior region, a wrong or empty one falls back to global
/// retrieval and still localizes, a broken one is refused; LocalizeStream tracks from its last pose and
/// frees its state when the client goes away.
#[test]
fn priors_fall_back_and_streams_track() {
    let f = fixture();
    let rt = runtime();
    rt.block_on(async {
        let running = pntr_service::start(settings(&[&f.map])).await.unwrap();
        running.ready().await.unwrap();
        let mut c = client(running.addr).await;
        let v = &f.queries[0];
        let truth = v.world_from_camera.translation.vector;
        let localize = |prior: Option<proto::Prior>| proto::LocalizeRequest {
            prior,
            ..request(v, "")
        };
        let check = |r: &proto::LocalizeResponse, mode: proto::Mode, what: &str| {
            assert_eq!(
                r.status,
                proto::Status::Localized as i32,
                "{what}: {}",
                r.reason
            );
            let e = translation_error(r, v).unwrap();
            assert!(e < 0.25, "{what}: {e} m off");
            assert_eq!(mode_of(r), mode, "{what}");
        };

        // No prior: global retrieval.
        let r = c.localize(localize(None)).await.unwrap().into_inner();
        check(&r, proto::Mode::Global, "no prior");
        // A right prior, by radius and by covariance (3 sigma of 0.3 m).
        let near = truth + nalgebra::Vector3::new(0.3, 0.0, -0.2);
        let r = c
            .localize(localize(Some(prior_at(near, 1.0))))
            .await
            .unwrap()
            .into_inner();
        check(&r, proto::Mode::Prior, "right prior");
        let mut by_cov = prior_at(near, 0.0);
        by_cov.covariance = (0..36)
            .map(|i| if i % 7 == 0 { 0.09 } else { 0.0 })
            .collect();
        let r = c
            .localize(localize(Some(by_cov)))
            .await
            .unwrap()
            .into_inner();
        check(&r, proto::Mode::Prior, "covariance prior");
        // A prior around another Point of the apartment (its images do not verify this frame) and
        // one where the map has no image at all: both fall back to the whole map.
        let map = mapfile::load(&f.map, |_| panic!("no onnx model in this map")).unwrap();
        let other = map
            .images
            .iter()
            .map(|im| im.world_from_camera.translation.vector)
            .max_by(|a, b| (a - truth).norm().total_cmp(&(b - truth).norm()))
            .unwrap();
        assert!(
            (other - truth).norm() > 1.5,
            "the fixture's Points are apart"
        );
        let r = c
            .localize(localize(Some(prior_at(other, 0.5))))
            .await
            .unwrap()
            .into_inner();
        check(&r, proto::Mode::Global, "prior at another Point");
        let far = truth + nalgebra::Vector3::new(100.0, 0.0, 0.0);
        let r = c
            .localize(localize(Some(prior_at(far, 1.0))))
            .await
            .unwrap()
            .into_inner();
        check(&r, proto::Mode::Global, "prior where the map is empty");
        // Broken priors are refused with the mistake named.
        let mut no_region = prior_at(near, 0.0);
        no_region.covariance.clear();
        let mut short_cov = prior_at(near, 0.0);
        short_cov.covariance = vec![0.1; 35];
        let no_pose = proto::Prior {
            radius_m: 1.0,
            ..Default::default()
        };
        for (prior, want) in [
            (prior_at(near, -1.0), "radius"),
            (no_region, "radius_m > 0 or a 36-value covariance"),
            (short_cov, "35 values"),
            (no_pose, "pose.translation"),
        ] {
            let (code, msg) = code_of(&mut c, localize(Some(prior))).await;
            assert_eq!(code, Code::InvalidArgument, "{msg}");
            assert!(msg.contains("prior") && msg.contains(want), "{msg}");
        }

        // A stream tracks: once two fixes agree, the next frames answer through tracking,
        // and a frame's own prior wins over tracking.
        let gauge = |text: &str| -> f64 {
            text.lines()
                .find_map(|l| l.strip_prefix("pntr_streams_active "))
                .map(|v| v.trim().parse().unwrap())
                .unwrap_or(f64::NAN)
        };
        // A robot standing still sends the same view: a camera's stream turns and moves smoothly
        // (queries of one Point in other directions would be turns no camera makes in 0.1 s, which
        // tracking refuses).
        let still = f
            .queries
            .iter()
            .find(|q| (q.world_from_camera.translation.vector - truth).norm() < 0.9)
            .expect("a query at the Point");
        let same_place: Vec<&View> = vec![still; 4];
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        let mut out = c
            .localize_stream(ReceiverStream::new(rx))
            .await
            .unwrap()
            .into_inner();
        let mut modes = Vec::new();
        for (i, q) in same_place.iter().enumerate() {
            tx.send(request(q, "")).await.unwrap();
            let r = out.message().await.unwrap().unwrap();
            assert_eq!(
                r.status,
                proto::Status::Localized as i32,
                "frame {i}: {}",
                r.reason
            );
            assert!(translation_error(&r, q).unwrap() < 0.25, "frame {i}");
            modes.push(mode_of(&r));
        }
        // The first fix is global, the second (global too) confirms it, then the stream tracks.
        assert_eq!(modes[..2], [proto::Mode::Global; 2], "{modes:?}");
        assert!(
            modes[2..].iter().all(|m| *m == proto::Mode::Tracking),
            "{modes:?}"
        );
        tx.send(localize(Some(prior_at(near, 1.0)))).await.unwrap();
        let r = out.message().await.unwrap().unwrap();
        assert_eq!(mode_of(&r), proto::Mode::Prior);
        assert!(gauge(&scrape(running.metrics_addr)) >= 1.0);

        // Capture stamps, not arrival, tell how far the camera can have moved. The same frames
        // sent back to back, stamped 0.1 s apart, are tracked; stamped 10 s apart (every 100th
        // frame of a recording), no track holds over the gap and each is found on the map alone;
        // a stamp that goes back (a recording started again) starts afresh.
        let mut c3 = client(running.addr).await;
        let stamped = |stamps: &[f64]| -> Vec<proto::LocalizeRequest> {
            stamps
                .iter()
                .map(|&t| proto::LocalizeRequest {
                    stamp_s: Some(t),
                    ..request(still, "")
                })
                .collect()
        };
        let modes_of = |answers: &[proto::LocalizeResponse]| -> Vec<proto::Mode> {
            answers
                .iter()
                .inspect(|r| assert_eq!(r.status, proto::Status::Localized as i32, "{}", r.reason))
                .map(mode_of)
                .collect()
        };
        let close = stream_answers(
            &mut c3,
            stamped(&[100.0, 100.1, 100.2, 100.3, 99.0, 99.1, 99.2]),
        )
        .await
        .unwrap();
        let tracked = [
            proto::Mode::Global,
            proto::Mode::Global,
            proto::Mode::Tracking,
            proto::Mode::Tracking,
        ];
        assert_eq!(modes_of(&close)[..4], tracked);
        assert_eq!(modes_of(&close)[4..], tracked[..3], "went back: afresh");
        let apart = stream_answers(&mut c3, stamped(&[100.0, 110.0, 120.0, 130.0]))
            .await
            .unwrap();
        assert_eq!(modes_of(&apart), [proto::Mode::Global; 4]);
        // Stamps in another unit are refused by name, in a stream and in a unary call.
        let e = stream_answers(&mut c3, stamped(&[1.767e12]))
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument);
        assert!(e.message().contains("milliseconds"), "{}", e.message());
        // The error ends the stream and names the frame it refused: the third here.
        let e = stream_answers(&mut c3, stamped(&[100.0, 100.1, 1.767e12, 100.3]))
            .await
            .unwrap_err();
        assert!(
            e.message()
                .starts_with("frame 3 of this stream (the first is 1")
                && e.message().contains("milliseconds"),
            "{}",
            e.message()
        );
        let (code, msg) = code_of(&mut c3, stamped(&[1.767e18]).remove(0)).await;
        assert_eq!(code, Code::InvalidArgument);
        assert!(msg.contains("nanoseconds"), "{msg}");
        // A stream that continues an earlier one's track (a client that re-opened it) holds its
        // first map fix to where the camera can have moved since: 5 m off the continued pose
        // 0.2 s later, the fix is a look-alike; at the continued pose, it is answered.
        let continued = |at: nalgebra::Vector3<f64>| proto::LocalizeRequest {
            stamp_s: Some(200.2),
            continuation: Some(proto::TrackContinuation {
                pose: Some(wire::to_proto_pose(&nalgebra::Isometry3::from_parts(
                    at.into(),
                    still.world_from_camera.rotation,
                ))),
                stamp_s: Some(200.0),
                sigma_m: 0.05,
            }),
            ..request(still, "")
        };
        let here = still.world_from_camera.translation.vector;
        let away = stream_answers(
            &mut c3,
            vec![continued(here + nalgebra::Vector3::new(5.0, 0.0, 0.0))],
        )
        .await
        .unwrap();
        assert_eq!(away[0].status, proto::Status::NotLocalized as i32);
        assert_eq!(
            away[0].cause,
            proto::NotLocalizedCause::LookAlike as i32,
            "{}",
            away[0].reason
        );
        assert!(
            away[0].reason.contains("motion puts the camera")
                || away[0].reason.contains("camera's motion"),
            "{}",
            away[0].reason
        );
        let at_home = stream_answers(&mut c3, vec![continued(here)])
            .await
            .unwrap();
        assert_eq!(
            at_home[0].status,
            proto::Status::Localized as i32,
            "{}",
            at_home[0].reason
        );
        // The robot's odometry pose must be a pose: refused by name otherwise.
        let bad_odometry = proto::LocalizeRequest {
            odometry: Some(proto::Pose {
                translation: Some(proto::Vector3 {
                    x: f64::NAN,
                    y: 0.0,
                    z: 0.0,
                }),
                rotation: None,
            }),
            ..request(still, "")
        };
        let e = stream_answers(&mut c3, vec![bad_odometry])
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument);
        assert!(e.message().contains("odometry"), "{}", e.message());
        // A rotation that is not a unit quaternion is a mistake, named.
        let long_quaternion = proto::LocalizeRequest {
            odometry: Some(proto::Pose {
                translation: Some(proto::Vector3 {
                    x: 0.0,
                    y: 0.0,
                    z: 0.0,
                }),
                rotation: Some(proto::Quaternion {
                    x: 0.0,
                    y: 0.0,
                    z: 0.0,
                    w: 2.0,
                }),
            }),
            ..request(still, "")
        };
        let e = stream_answers(&mut c3, vec![long_quaternion])
            .await
            .unwrap_err();
        assert!(e.message().contains("unit quaternion"), "{}", e.message());
        // A continuation without a pose, or from after the frame, continues nothing: refused.
        let mut no_pose = continued(here);
        no_pose.continuation.as_mut().unwrap().pose = None;
        let mut later = continued(here);
        later.continuation.as_mut().unwrap().stamp_s = Some(300.0);
        for (bad, want) in [(no_pose, "continuation.pose"), (later, "later than")] {
            let e = stream_answers(&mut c3, vec![bad]).await.unwrap_err();
            assert_eq!(e.code(), Code::InvalidArgument);
            assert!(e.message().contains(want), "{}", e.message());
        }
        // The client goes away without closing its stream: the server frees the stream's state.
        drop(out);
        drop(tx);
        drop(c);
        let streams = || gauge(&scrape(running.metrics_addr));
        let (limit, poll) = (Duration::from_secs(20), Duration::from_millis(50));
        let gone = "stream state still held after the client left";
        wait_until(|| streams() == 0.0, limit, poll, gone).await;
        // A client that stops reading its answers, keeps sending, then cancels the call: the
        // stream's state and its count in pntr_streams_active go with it.
        let mut c2 = client(running.addr).await;
        let (tx, rx) = tokio::sync::mpsc::channel(16);
        let call = tokio::spawn(async move {
            let mut out = c2
                .localize_stream(ReceiverStream::new(rx))
                .await
                .unwrap()
                .into_inner();
            // One answer read, then none.
            let _ = out.message().await;
            std::future::pending::<()>().await;
        });
        for _ in 0..12 {
            if tx.send(request(still, "")).await.is_err() {
                break;
            }
        }
        wait_until(|| streams() >= 1.0, limit, poll, "the stream never opened").await;
        tokio::time::sleep(Duration::from_millis(500)).await;
        call.abort();
        let _ = call.await;
        drop(tx);
        let counted = "a cancelled stream whose client had stopped reading is still counted";
        wait_until(|| streams() == 0.0, limit, poll, counted).await;
        let text = scrape(running.metrics_addr);
        for mode in ["GLOBAL", "PRIOR", "TRACKING"] {
            assert!(
                text.contains(&format!("pntr_answers_total{{mode=\"{mode}\",map_id=")),
                "{text}"
            );
        }
        stop(running).await;
    });
}
