//! The `pntr-server` binary and the signals operators send it: SIGHUP reloads a map file that was
//! replaced on disk (the server keeps answering), SIGTERM ends open streams with UNAVAILABLE right
//! away (so robots reconnect) and the process exits cleanly well before its drain timeout.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use pntr_pipeline::preset::Preset;
use pntr_pipeline::{map, mapfile};
use pntr_service::proto::localizer_client::LocalizerClient;
use pntr_service::proto::{self};
use pntr_service::tonic::transport::Endpoint;
use pntr_service::tonic::Code;

fn models() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models")
}

fn signal(child: &Child, name: &str) {
    let ok = Command::new("kill")
        .args([format!("-{name}"), child.id().to_string()])
        .status()
        .unwrap()
        .success();
    assert!(ok, "kill -{name}");
}

/// Kills the server if the test fails half-way.
struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[test]
fn sighup_reloads_and_sigterm_ends_streams() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = pntr_synth::SynthConfig {
        points_per_scene: 3,
        queries_per_point: 2,
        seed: 12,
        ..Default::default()
    };
    pntr_synth::synthesize(&cfg, dir.path(), pntr_synth::plan_all(&cfg), &|| {}).unwrap();
    let index = pntr_dataset::DatasetIndex::open(dir.path()).unwrap();
    let preset = Preset::named("fast").unwrap();
    let stage = preset.map_feature_config(models()).build().unwrap();
    let scenes: Vec<_> = index.scenes.iter().collect();
    let mut built =
        map::build("site", &scenes, &preset, &stage, &models(), &mut |_, _| {}).unwrap();
    let path = dir.path().join("site.pntrmap");
    mapfile::save(&built, &path).unwrap();
    let query = {
        let r = index.scenes[0].points[0].open().unwrap();
        r.view(pntr_dataset::Role::Query, 0).unwrap()
    };

    let mut child = Command::new(env!("CARGO_BIN_EXE_pntr-server"))
        .args(["--addr", "127.0.0.1:0", "--metrics-addr", "127.0.0.1:0"])
        .arg("--db")
        .arg(&path)
        .arg("--models")
        .arg(models())
        .args(["--workers", "1", "--drain-timeout-s", "300"])
        .env("PNTR_ADMIN_TOKEN", "admin-token-for-tests")
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let server = Server(child);
    let addr = line
        .split_whitespace()
        .nth(3)
        .unwrap_or_else(|| panic!("no address in {line:?}"))
        .to_string();

    let rt = pntr_service::tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let ch = Endpoint::from_shared(format!("http://{addr}"))
            .unwrap()
            .connect()
            .await
            .unwrap();
        let mut c = LocalizerClient::new(ch).max_decoding_message_size(64 << 20);
        let version = |mut c: LocalizerClient<_>| async move {
            let t = Instant::now();
            loop {
                match c.get_map_info(proto::GetMapInfoRequest::default()).await {
                    Ok(r) => return r.into_inner().version,
                    Err(e) if e.code() == Code::Unavailable => {
                        assert!(t.elapsed() < Duration::from_secs(120), "never loaded");
                        pntr_service::tokio::time::sleep(Duration::from_millis(50)).await;
                    }
                    Err(e) => panic!("{e}"),
                }
            }
        };
        let v1 = version(c.clone()).await;

        // A new build of the map is renamed over the file; SIGHUP makes the server serve it.
        built.header.built_at_unix_s = built.header.built_at_unix_s.map(|s| s + 60.0);
        mapfile::save(&built, &path).unwrap();
        signal(&server.0, "HUP");
        let t = Instant::now();
        let v2 = loop {
            let v = version(c.clone()).await;
            if v != v1 {
                break v;
            }
            assert!(
                t.elapsed() < Duration::from_secs(60),
                "SIGHUP did not reload"
            );
            pntr_service::tokio::time::sleep(Duration::from_millis(50)).await;
        };

        // An open stream answers from the new version; SIGTERM ends it with UNAVAILABLE.
        let (tx, rx) = pntr_service::tokio::sync::mpsc::channel(2);
        let mut out = c
            .localize_stream(pntr_service::tokio_stream::wrappers::ReceiverStream::new(
                rx,
            ))
            .await
            .unwrap()
            .into_inner();
        tx.send(pntr_service::wire::raw_request(
            &query.rgb,
            &query.depth,
            None,
        ))
        .await
        .unwrap();
        let r = out.message().await.unwrap().unwrap();
        assert_eq!(r.map_version, v2);
        signal(&server.0, "TERM");
        let e = pntr_service::tokio::time::timeout(Duration::from_secs(30), out.message())
            .await
            .expect("the stream ends at once, not at the drain's end")
            .unwrap_err();
        assert_eq!(e.code(), Code::Unavailable, "{}", e.message());
        drop(tx);
    });
    let mut server = server;
    let t = Instant::now();
    let status = loop {
        if let Some(s) = server.0.try_wait().unwrap() {
            break s;
        }
        assert!(
            t.elapsed() < Duration::from_secs(30),
            "the server did not exit after SIGTERM"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(status.success(), "{status:?}");
}

/// The line `pntr-server listening on ...` means "serving": it comes once the maps and models are
/// loaded, so a wrapper that waits for it is never fooled by a server whose map then fails to load
/// (here: a file whose header reads but whose body is cut short), and after it GetMapInfo answers
/// at once.
#[test]
fn the_ready_line_comes_only_after_loading() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = pntr_synth::SynthConfig {
        points_per_scene: 2,
        queries_per_point: 1,
        seed: 13,
        ..Default::default()
    };
    pntr_synth::synthesize(&cfg, dir.path(), pntr_synth::plan_all(&cfg), &|| {}).unwrap();
    let index = pntr_dataset::DatasetIndex::open(dir.path()).unwrap();
    let preset = Preset::named("fast").unwrap();
    let stage = preset.map_feature_config(models()).build().unwrap();
    let scenes: Vec<_> = index.scenes.iter().collect();
    let built = map::build("site", &scenes, &preset, &stage, &models(), &mut |_, _| {}).unwrap();
    let good = dir.path().join("good.pntrmap");
    mapfile::save(&built, &good).unwrap();
    let bytes = std::fs::read(&good).unwrap();
    let cut = dir.path().join("cut.pntrmap");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    mapfile::read_header(&cut).expect("the header still reads");

    let run = |db: &Path| {
        Command::new(env!("CARGO_BIN_EXE_pntr-server"))
            .args(["--addr", "127.0.0.1:0", "--metrics-addr", "127.0.0.1:0"])
            .arg("--db")
            .arg(db)
            .arg("--models")
            .arg(models())
            .args(["--workers", "1"])
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap()
    };
    let out = run(&cut).wait_with_output().unwrap();
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(!out.status.success(), "{stdout}{stderr}");
    assert!(
        !stdout.contains("listening"),
        "ready line before a failed load: {stdout}"
    );
    assert!(
        stderr.contains("cut.pntrmap"),
        "the error names the file: {stderr}"
    );

    let mut child = run(&good);
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let server = Server(child);
    let addr = line.split_whitespace().nth(3).unwrap().to_string();
    let rt = pntr_service::tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let ch = Endpoint::from_shared(format!("http://{addr}"))
            .unwrap()
            .connect()
            .await
            .unwrap();
        let info = LocalizerClient::new(ch)
            .get_map_info(proto::GetMapInfoRequest::default())
            .await
            .expect("serving once the line is printed");
        assert_eq!(info.into_inner().map_id, "site");
    });
    drop(server);
}
