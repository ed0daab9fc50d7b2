//! pntr-ros on a ROS 2 graph that another DDS stack speaks: `tests/robot.py` (Eclipse Cyclone DDS,
//! the PyPI `cyclonedds` package, as rmw_cyclonedds would put it on the wire) replays a generated
//! drive as a RealSense driver and a robot base publish it, a real pntr-server (in this process, on
//! 127.0.0.1) serves a map of the apartment, and the node between them is the built `pntr-ros`.
//!
//! DDS traffic stays inside a private user and network namespace the test makes for itself
//! (`unshare --user --map-root-user --net`, then this same test re-run inside it): `lo` for gRPC and
//! one veth pair `dds0`/`dds1` (10.255.42.1/24, multicast routed to `dds0`) for DDS, never the
//! machine's own interfaces.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use pntr_service::config::Settings;
use pntr_service::proto::localizer_client::LocalizerClient;
use pntr_service::proto::GetMapInfoRequest;
use pntr_service::tokio::runtime::Runtime;

const INSIDE: &str = "PNTR_ROS_TEST_INSIDE_NETNS";
const CYCLONE_ON_DDS0: &str = r#"<CycloneDDS><Domain Id="any"><General><Interfaces><NetworkInterface name="dds0" multicast="true"/></Interfaces><AllowMulticast>true</AllowMulticast></General></Domain></CycloneDDS>"#;

/// Re-run `test` inside a private user + network namespace; true when already inside.
fn inside_private_network(test: &str) -> bool {
    if std::env::var_os(INSIDE).is_some() {
        return true;
    }
    let status = Command::new("unshare")
        .args(["--user", "--map-root-user", "--net", "--"])
        .arg(std::env::current_exe().expect("the test binary"))
        .args([test, "--exact", "--nocapture", "--test-threads", "1"])
        .env(INSIDE, "1")
        .status()
        .expect("unshare (util-linux) runs");
    assert!(
        status.success(),
        "{test} failed inside its network namespace (see its output above); it needs unprivileged user namespaces (`unshare --user --map-root-user --net true` must work)"
    );
    false
}

fn sh(args: &[&str]) {
    let out = Command::new(args[0])
        .args(&args[1..])
        .output()
        .expect("ip (iproute2) runs");
    assert!(
        out.status.success(),
        "{args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// `lo` up, and the veth pair dds0/dds1 with multicast routed to dds0.
fn network() {
    sh(&["ip", "link", "set", "lo", "up"]);
    sh(&[
        "ip", "link", "add", "dds0", "type", "veth", "peer", "name", "dds1",
    ]);
    sh(&["ip", "addr", "add", "10.255.42.1/24", "dev", "dds0"]);
    sh(&["ip", "link", "set", "dds0", "up"]);
    sh(&["ip", "link", "set", "dds1", "up"]);
    sh(&["ip", "link", "set", "dds0", "multicast", "on"]);
    sh(&["ip", "route", "add", "224.0.0.0/4", "dev", "dds0"]);
}

/// A generated apartment (seed 3), a 24 s drive through it, and a map of its database views.
fn apartment(dir: &Path) -> (PathBuf, PathBuf) {
    let cfg = pntr_synth::SynthConfig {
        points_per_scene: 8,
        queries_per_point: 1,
        seed: 3,
        trajectory_seconds: Some(24.0),
        ..Default::default()
    };
    pntr_synth::synthesize(&cfg, dir, pntr_synth::plan_all(&cfg), &|| {}).expect("synthesize");
    let index = pntr_dataset::DatasetIndex::open(dir).expect("dataset");
    let map = pntr_tests::build_map(&index, "xfeat-mnn", "apartment");
    let path = dir.join("apartment.pntrmap");
    pntr_pipeline::mapfile::save(&map, &path).expect("save the map");
    (path, dir.join(pntr_synth::SEQUENCES_DIR).join("synth000"))
}

fn serve(rt: &Runtime, map: &Path, addr: Option<std::net::SocketAddr>) -> pntr_service::Running {
    let mut s = Settings::local(vec![map.to_path_buf()], pntr_tests::models());
    if let Some(a) = addr {
        s.addr = a;
    }
    rt.block_on(async {
        let r = pntr_service::start(s).await.expect("server starts");
        r.ready().await.expect("server loads");
        r
    })
}

fn stop(rt: &Runtime, mut s: pntr_service::Running) {
    rt.block_on(async move {
        s.shutdown();
        s.wait().await.expect("server stops");
    });
}

/// MapInfo.ros_from_map as w, x, y, z.
fn ros_from_map(rt: &Runtime, addr: std::net::SocketAddr) -> [f64; 4] {
    rt.block_on(async {
        let mut c = LocalizerClient::connect(format!("http://{addr}"))
            .await
            .unwrap();
        let info = c
            .get_map_info(GetMapInfoRequest::default())
            .await
            .unwrap()
            .into_inner();
        let q = info.ros_from_map.unwrap().rotation.unwrap();
        [q.w, q.x, q.y, q.z]
    })
}

/// Start the node; `rmw` is RMW_IMPLEMENTATION (unset: the relocalize service in both wire formats).
fn node(addr: std::net::SocketAddr, log: &Path, rmw: Option<&str>, ros_args: &[&str]) -> Child {
    let mut c = Command::new(env!("CARGO_BIN_EXE_pntr-ros"));
    match rmw {
        Some(r) => c.env("RMW_IMPLEMENTATION", r),
        None => c.env_remove("RMW_IMPLEMENTATION"),
    };
    c.args(["--addr", &addr.to_string(), "--ros-args"])
        .args(ros_args)
        .env_remove("ROS_DOMAIN_ID")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(log).unwrap())
        .spawn()
        .expect("pntr-ros starts")
}

/// SIGINT, then the node must exit 0 within 5 s.
fn interrupt(mut child: Child, log: &Path) {
    let sent = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(sent.success());
    let t = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            assert!(
                status.success(),
                "pntr-ros exited {status} on SIGINT:\n{}",
                std::fs::read_to_string(log).unwrap_or_default()
            );
            return;
        }
        assert!(
            t.elapsed() < Duration::from_secs(5),
            "pntr-ros still running 5 s after SIGINT"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// `$PNTR_PYTHON`, else set-up's venv; it must have cyclonedds, numpy and Pillow.
fn python() -> PathBuf {
    let p = std::env::var_os("PNTR_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| pntr_tests::workspace_root().join(".deps/venv/bin/python"));
    let ok = Command::new(&p)
        .args(["-c", "import cyclonedds, numpy, PIL"])
        .status()
        .is_ok_and(|s| s.success());
    assert!(
        ok,
        "{} cannot import cyclonedds, numpy and PIL: run `bash scripts/setup.sh` (or set PNTR_PYTHON)",
        p.display()
    );
    p
}

/// Start the robot; returns it once it has printed `ready`.
fn robot(seq: &Path, ros_from_map: [f64; 4], seconds: f64, out: &Path, extra: &[&str]) -> Child {
    let q: Vec<String> = ros_from_map.iter().map(|v| v.to_string()).collect();
    let mut child = Command::new(python())
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/robot.py"))
        .arg("--tum")
        .arg(seq)
        .arg("--ros-from-map")
        .args(&q)
        .args(["--seconds", &seconds.to_string(), "--out"])
        .arg(out)
        .args(extra)
        .env("CYCLONEDDS_URI", CYCLONE_ON_DDS0)
        .stdout(Stdio::piped())
        .spawn()
        .expect("robot.py starts");
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    assert_eq!(line.trim(), "ready", "robot.py did not start");
    child
}

fn finish(mut child: Child, out: &Path) -> serde_json::Value {
    assert!(child.wait().unwrap().success(), "robot.py failed");
    serde_json::from_str(&std::fs::read_to_string(out).unwrap()).unwrap()
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn vec_of(v: &serde_json::Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

fn angle_deg(a: &[f64], b: &[f64]) -> f64 {
    let dot: f64 = a.iter().zip(b).map(|(x, y)| x * y).sum();
    2.0 * dot.abs().min(1.0).acos().to_degrees()
}

fn distance(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// The poses against the truth of their frames: (median position error m, median rotation error deg).
fn pose_errors(report: &serde_json::Value) -> (f64, f64) {
    let frames: std::collections::HashMap<i64, &serde_json::Value> = report["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| (f["stamp_ns"].as_i64().unwrap(), f))
        .collect();
    let (mut dp, mut dq) = (Vec::new(), Vec::new());
    for p in report["poses"].as_array().unwrap() {
        let stamp = p["stamp_ns"].as_i64().unwrap();
        let f = frames
            .get(&stamp)
            .unwrap_or_else(|| panic!("a pose stamped {stamp} ns, which no image carried"));
        assert_eq!(p["frame_id"], "map");
        dp.push(distance(&vec_of(&p["p"]), &vec_of(&f["p"])));
        dq.push(angle_deg(&vec_of(&p["q"]), &vec_of(&f["q"])));
        let c = vec_of(&p["covariance"]);
        assert_eq!(c.len(), 36);
        for r in 0..6 {
            assert!(
                c[r * 6 + r] > 0.0,
                "covariance diagonal {r}: {}",
                c[r * 6 + r]
            );
            for col in 0..6 {
                assert!(
                    (c[r * 6 + col] - c[col * 6 + r]).abs() <= 1e-12 * c[r * 6 + r].abs().max(1.0)
                );
            }
        }
    }
    (median(dp), median(dq))
}

/// map -> odom as published, against the robot's known offset: (median m, median deg).
fn map_odom_errors(report: &serde_json::Value) -> (f64, f64) {
    let want_p = vec_of(&report["map_from_odom"][0]);
    let want_q = vec_of(&report["map_from_odom"][1]);
    let all = report["map_odom"].as_array().unwrap();
    assert!(!all.is_empty(), "no map -> odom on /tf");
    (
        median(
            all.iter()
                .map(|m| distance(&vec_of(&m["p"]), &want_p))
                .collect(),
        ),
        median(
            all.iter()
                .map(|m| angle_deg(&vec_of(&m["q"]), &want_q))
                .collect(),
        ),
    )
}

fn times(report: &serde_json::Value, key: &str) -> Vec<f64> {
    report[key]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|x| x["t"].as_f64())
        .collect()
}

#[test]
fn a_robot_on_cyclone_dds_gets_poses_tf_diagnostics_and_its_service() {
    if !inside_private_network("a_robot_on_cyclone_dds_gets_poses_tf_diagnostics_and_its_service") {
        return;
    }
    network();
    let dir = tempfile::tempdir().unwrap();
    let (map, seq) = apartment(dir.path());
    let rt = pntr_tests::runtime();
    let server = serve(&rt, &map, None);
    let addr = server.addr;
    let q = ros_from_map(&rt, addr);
    let rate_hz = 4.0;

    // 1. Raw images; RViz's "2D Pose Estimate" on /initialpose at 2 s; the relocalize service at
    // 4 s; the robot silent from 6 to 7.5 s.
    let log = dir.path().join("node1.log");
    let n = node(addr, &log, None, &["-p", "rate_hz:=4.0"]);
    let out = dir.path().join("raw.json");
    let seconds = 14.0;
    let r = finish(
        robot(
            &seq,
            q,
            seconds,
            &out,
            &[
                "--initialpose-at",
                "2",
                "--relocalize-at",
                "4",
                "--silent-at",
                "6",
                "--silent-for",
                "1.5",
            ],
        ),
        &out,
    );
    interrupt(n, &log);
    let context = || std::fs::read_to_string(&log).unwrap_or_default();
    // The node is on the graph with its readers and writers.
    let nodes = r["nodes"].as_array().unwrap();
    assert!(
        nodes.iter().any(|n| n["name"] == "pntr_ros"
            && n["namespace"] == "/"
            && n["readers"].as_u64().unwrap() >= 5
            && n["writers"].as_u64().unwrap() >= 3),
        "pntr_ros not on ros_discovery_info with its endpoints: {nodes:?}"
    );
    let poses = r["poses"].as_array().unwrap().len() as f64;
    let asked = (seconds - 1.5) * rate_hz;
    assert!(
        poses >= 0.8 * asked && poses <= seconds * rate_hz + 2.0,
        "{poses} poses for {asked} frames asked at {rate_hz} Hz\n{}",
        context()
    );
    let (dp, dq) = pose_errors(&r);
    let (mp, mq) = map_odom_errors(&r);
    let last = &r["diagnostics"].as_array().unwrap().last().unwrap()["values"];
    eprintln!(
        "raw: {poses} poses for {asked} frames asked; base pose median {dp:.4} m {dq:.3} deg; map -> odom median {mp:.4} m {mq:.3} deg; the node's counts: {last}"
    );
    assert!(
        dp < 0.05 && dq < 1.0,
        "base pose median error {dp} m, {dq} deg"
    );
    assert!(
        mp < 0.05 && mq < 1.0,
        "map -> odom median error {mp} m, {mq} deg"
    );
    assert!(
        context().contains("initial pose given"),
        "the node did not take /initialpose (the robot sent {})\n{}",
        r["initialpose"],
        context()
    );
    // Poses again after the silence.
    assert!(
        times(&r, "poses").iter().any(|t| *t > 8.0),
        "no pose after the robot's silence\n{}",
        context()
    );
    let diagnostics = r["diagnostics"].as_array().unwrap();
    assert!(
        diagnostics.len() >= 5,
        "{} diagnostics in {seconds} s",
        diagnostics.len()
    );
    assert!(diagnostics
        .iter()
        .any(|d| d["level"] == 0 && d["values"]["map_id"] == "apartment"));
    // The service answered as an rmw_cyclonedds client checks, its own request header echoed (the
    // node served both RMWs' formats: RMW_IMPLEMENTATION was unset).
    let services = r["services"].as_array().unwrap();
    assert!(
        services.iter().any(|s| s["success"] == true
            && s["seq"] == 1
            && s["client"].as_u64() == Some(0x0123_4567_89AB_CDEF)),
        "relocalize: {services:?}"
    );

    // 2. Compressed colour and compressedDepth; the node started after the robot has latched
    // /tf_static (it must get it as a late joiner, transient local); the server stops at 4 s and is
    // back at 6 s.
    let out = dir.path().join("compressed.json");
    let started = Instant::now();
    let running = robot(&seq, q, 12.0, &out, &["--relocalize-at", "9"]);
    std::thread::sleep(Duration::from_millis(500));
    let log = dir.path().join("node2.log");
    let n = node(
        addr,
        &log,
        Some("rmw_cyclonedds_cpp"),
        &[
            "-p",
            "rgb_topic:=/camera/color/image_raw/compressed",
            "-p",
            "depth_topic:=/camera/aligned_depth_to_color/image_raw/compressedDepth",
            "-p",
            "rate_hz:=4.0",
        ],
    );
    std::thread::sleep(Duration::from_secs(4).saturating_sub(started.elapsed()));
    stop(&rt, server);
    std::thread::sleep(Duration::from_secs(6).saturating_sub(started.elapsed()));
    let server = serve(&rt, &map, Some(addr));
    let r = finish(running, &out);
    interrupt(n, &log);
    let context = || std::fs::read_to_string(&log).unwrap_or_default();
    let t = times(&r, "poses");
    assert!(
        t.iter().any(|t| *t < 4.0),
        "no pose from compressed images\n{}",
        context()
    );
    assert!(
        t.iter().any(|t| *t > 8.0),
        "no pose after the server came back\n{}",
        context()
    );
    let (dp, dq) = pose_errors(&r);
    eprintln!(
        "compressed: {} poses in 12 s (server down from 4 to 6 s); median {dp:.4} m {dq:.3} deg",
        t.len()
    );
    assert!(
        dp < 0.05 && dq < 1.0,
        "compressed: median error {dp} m, {dq} deg"
    );
    assert!(
        r["diagnostics"]
            .as_array()
            .unwrap()
            .iter()
            .any(|d| d["level"] == 2 && d["values"]["connected"] == "false"),
        "the outage never showed on /diagnostics"
    );
    // RMW_IMPLEMENTATION=rmw_cyclonedds_cpp: the service in Cyclone's format only, answered.
    let services = r["services"].as_array().unwrap();
    assert!(
        services
            .iter()
            .any(|s| s["success"] == true && s["seq"] == 1),
        "relocalize with RMW_IMPLEMENTATION set: {services:?}"
    );
    stop(&rt, server);
}
