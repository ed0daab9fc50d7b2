//! The `pntr-server` binary and the signals operators send it: SIGHUP reloads a map file that was
//! replaced on disk (the server keeps answering), SIGTERM ends open streams with UNAVAILABLE right
//! away (so robots reconnect) and the process exits cleanly well before its drain timeout.

use std::path::Path;
use std::process::Stdio;
use std::time::{Duration, Instant};

use pntr_pipeline::mapfile;
use pntr_service::proto::localizer_client::LocalizerClient;
use pntr_service::proto::{self};
use pntr_service::tokio_stream::wrappers::ReceiverStream;
use pntr_service::tonic::Code;

mod common;
use common::{models, signal};

#[test]
fn sighup_reloads_and_sigterm_ends_streams() {
    let dir = tempfile::tempdir().unwrap();
    let (mut built, index) = common::synthetic_map(dir.path(), 3, 2, 12, "site");
    let path = dir.path().join("site.pntrmap");
    mapfile::save(&built, &path).unwrap();
    let query = common::first_query(&index);

    let (server, addr, _) = common::spawn(
        common::server_command(
            &path,
            &models(),
            &["--workers", "1", "--drain-timeout-s", "300"],
        )
        .env("PNTR_ADMIN_TOKEN", "admin-token-for-tests")
        .stderr(Stdio::null()),
    );

    let rt = pntr_service::tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let ch = common::channel(addr).await;
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
            .localize_stream(ReceiverStream::new(rx))
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
    let status = common::wait_exit(
        &mut server.0,
        Duration::from_secs(30),
        Duration::from_millis(50),
        "the server did not exit after SIGTERM",
    );
    assert!(status.success(), "{status:?}");
}

/// The line `pntr-server listening on ...` means "serving": it comes once the maps and models are
/// loaded, so a wrapper that waits for it is never fooled by a server whose map then fails to load
/// (here: a file whose header reads but whose body is cut short), and after it GetMapInfo answers
/// at once.
#[test]
fn the_ready_line_comes_only_after_loading() {
    let dir = tempfile::tempdir().unwrap();
    let (built, _) = common::synthetic_map(dir.path(), 2, 1, 13, "site");
    let good = dir.path().join("good.pntrmap");
    mapfile::save(&built, &good).unwrap();
    let bytes = std::fs::read(&good).unwrap();
    let cut = dir.path().join("cut.pntrmap");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    mapfile::read_header(&cut).expect("the header still reads");

    let run = |db: &Path| {
        let mut c = common::server_command(db, &models(), &["--workers", "1"]);
        c.stdout(Stdio::piped()).stderr(Stdio::piped());
        c
    };
    let out = run(&cut).spawn().unwrap().wait_with_output().unwrap();
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

    let (server, addr, _) = common::spawn(&mut run(&good));
    let rt = pntr_service::tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let ch = common::channel(addr).await;
        let info = LocalizerClient::new(ch)
            .get_map_info(proto::GetMapInfoRequest::default())
            .await
            .expect("serving once the line is printed");
        assert_eq!(info.into_inner().map_id, "site");
    });
    drop(server);
}
