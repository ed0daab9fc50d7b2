//! Faults at start-up (issue 10): a corrupted map or a missing model stops the real `pntr-server`
//! binary with a message naming the problem and a non-zero exit, and health never says SERVING.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::{Duration, Instant};

use pntr_service::proto::localizer_client::LocalizerClient;
use pntr_service::tokio;
use pntr_service::tonic_health::pb::health_check_response::ServingStatus;

mod common;
use common::{gauge, models, scrape, sum_series};

/// Start the server, poll health until the process exits; return (exit code, stderr, ever SERVING).
fn run_until_exit(db: &Path, models: &Path) -> (Option<i32>, String, bool) {
    let mut child = common::server_command(db, models, &["--workers", "1"])
        .env("PNTR_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let line = common::first_line(&mut child);
    let mut serving = false;
    if let Some(addr) = line.split_whitespace().nth(3) {
        let addr: SocketAddr = addr.parse().unwrap();
        let rt = tokio::runtime::Runtime::new().unwrap();
        let t = Instant::now();
        while child.try_wait().unwrap().is_none() {
            assert!(
                t.elapsed() < Duration::from_secs(120),
                "the server neither served nor exited"
            );
            let s = rt.block_on(common::health(&format!("http://{addr}")));
            serving |= s == Some(ServingStatus::Serving as i32);
            std::thread::sleep(Duration::from_millis(20));
        }
    }
    let out = child.wait_with_output().unwrap();
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
        serving,
    )
}

fn variant(good: &Path, name: &str, edit: impl Fn(&mut Vec<u8>)) -> PathBuf {
    let mut b = std::fs::read(good).unwrap();
    edit(&mut b);
    let p = good.with_file_name(name);
    std::fs::write(&p, b).unwrap();
    p
}

#[test]
fn corrupted_maps_and_missing_models_stop_the_server_before_it_serves() {
    let dir = tempfile::tempdir().unwrap();
    let (good, _) = common::demo_map(dir.path());
    let len = std::fs::metadata(&good).unwrap().len() as usize;
    let cases = [
        (
            variant(&good, "truncated.pntrmap", |b| b.truncate(len / 2)),
            "truncated",
        ),
        (
            variant(&good, "flipped.pntrmap", |b| b[len / 2] ^= 0x08),
            "checksum",
        ),
        (variant(&good, "version.pntrmap", |b| b[8] = 7), "version 7"),
        (variant(&good, "empty.pntrmap", |b| b.clear()), "too short"),
    ];
    for (path, what) in &cases {
        let (code, err, serving) = run_until_exit(path, &models());
        assert!(
            code.is_some_and(|c| c != 0),
            "{}: exit {code:?}",
            path.display()
        );
        assert!(!serving, "{}: health said SERVING", path.display());
        let name = path.file_name().unwrap().to_string_lossy();
        assert!(
            err.contains(name.as_ref()) && err.contains(what),
            "{}: {err}",
            path.display()
        );
        assert!(!err.contains("panicked"), "{err}");
    }
    // The models: a folder without them, and an unreadable (garbage) model file.
    let (code, err, serving) = run_until_exit(&good, Path::new("/nonexistent/models"));
    assert!(code.is_some_and(|c| c != 0) && !serving, "{err}");
    assert!(err.contains("/nonexistent/models"), "{err}");
    let broken = dir.path().join("broken-models");
    std::fs::create_dir(&broken).unwrap();
    for f in std::fs::read_dir(models()).unwrap() {
        let f = f.unwrap().path();
        if f.extension().is_some_and(|e| e == "onnx") {
            std::fs::write(broken.join(f.file_name().unwrap()), b"not an onnx model").unwrap();
        }
    }
    let (code, err, serving) = run_until_exit(&good, &broken);
    assert!(code.is_some_and(|c| c != 0) && !serving, "{err}");
    assert!(err.contains("xfeat_backbone.onnx"), "{err}");
}

/// Pipeline runs that finished with an answer recorded (the `total` stage histogram's count, summed
/// over maps).
fn total_runs(text: &str) -> f64 {
    sum_series(text, "pntr_stage_duration_seconds_count{stage=\"total\"")
}

#[test]
fn clients_that_disconnect_while_queued_or_running_leave_no_work_and_right_gauges() {
    let dir = tempfile::tempdir().unwrap();
    let (db, query) = common::demo_map(dir.path());
    let mut s = pntr_service::config::Settings::local(vec![db], models());
    s.workers = 1;
    s.queue = 8;
    let rt = common::runtime();
    rt.block_on(async {
        let mut running = pntr_service::start(s).await.unwrap();
        running.ready().await.unwrap();
        let (addr, metrics) = (running.addr, running.metrics_addr);
        let url = format!("http://{addr}");
        let req = pntr_service::wire::raw_request(&query.rgb, &query.depth, None);
        // Until gauge `name` is `want` (or, with `at_least`, at least `want`).
        let wait_gauge = |name: &'static str, want: f64, at_least: bool| {
            let reached = move |g: f64| g == want || (at_least && g >= want);
            let what = format!("{name} never reached {want}");
            let limits = (Duration::from_secs(60), Duration::from_millis(1));
            async move { common::wait_gauge(metrics, name, reached, limits, &what).await }
        };
        let wait_for =
            |want: f64, at_least: bool| wait_gauge("pntr_in_flight_requests", want, at_least);
        let wait_busy = |want: f64| wait_gauge("pntr_busy_workers", want, false);
        // One request occupies the only worker; six more wait in the queue on another connection.
        let mut first = LocalizerClient::connect(url.clone()).await.unwrap();
        let r0 = req.clone();
        let a = tokio::spawn(async move { first.localize(r0).await });
        wait_for(1.0, false).await;
        let c = LocalizerClient::connect(url.clone()).await.unwrap();
        let mut queued = tokio::task::JoinSet::new();
        for _ in 0..6 {
            let (mut c, r) = (c.clone(), req.clone());
            queued.spawn(async move { c.localize(r).await });
        }
        // All six waiting (the first may have finished meanwhile).
        wait_for(6.0, true).await;
        // The waiting clients go away (their streams are reset).
        queued.abort_all();
        while queued.join_next().await.is_some() {}
        drop(c);
        assert!(
            a.await.unwrap().is_ok(),
            "the running request still completes"
        );
        wait_for(0.0, false).await;
        // The abandoned jobs leave the queue as the worker reaches them, skipping each.
        common::wait_gauge(
            metrics,
            "pntr_queue_depth",
            |g| g == 0.0,
            (Duration::from_secs(60), Duration::from_millis(5)),
            "the queue never drained",
        )
        .await;
        // At most one of them had started before its client left.
        let runs = total_runs(&scrape(metrics));
        assert!(
            runs <= 2.0,
            "{runs} pipeline runs for 1 answered + 6 abandoned requests"
        );
        // And the server keeps answering.
        let mut again = LocalizerClient::connect(url.clone()).await.unwrap();
        // The fastest of three answers: the deadline below is half a localization, and one slow
        // run (the parallel test runner loading the cores) would set it above a fast one.
        let mut single_s = f64::INFINITY;
        for _ in 0..3 {
            let answered = again.localize(req.clone()).await.unwrap().into_inner();
            let total = answered.timings.iter().find(|t| t.stage == "total");
            single_s = single_s.min(total.unwrap().seconds);
        }

        // A client that leaves while its request is *running*: the pipeline cannot be interrupted
        // mid-frame, so the worker finishes the frame and drops the answer; the gauges return to
        // zero and the request is counted once, as CANCELLED.
        let counter = |text: &str, code: &str| {
            // Summed over the map_id label.
            sum_series(
                text,
                &format!("pntr_requests_total{{status=\"ERROR\",code=\"{code}\","),
            )
        };
        wait_busy(0.0).await;
        let cancelled_before = counter(&scrape(metrics), "CANCELLED");
        let runs_before = total_runs(&scrape(metrics));
        let mut leaving = LocalizerClient::connect(url.clone()).await.unwrap();
        let r = req.clone();
        let call = tokio::spawn(async move { leaving.localize(r).await });
        wait_busy(1.0).await;
        call.abort();
        let _ = call.await;
        wait_for(0.0, false).await;
        wait_busy(0.0).await;
        let text = scrape(metrics);
        assert_eq!(
            counter(&text, "CANCELLED"),
            cancelled_before + 1.0,
            "{text}"
        );
        assert_eq!(gauge(&text, "pntr_queue_depth"), 0.0);
        // The frame was finished, not run twice or left half-done.
        assert_eq!(total_runs(&text), runs_before + 1.0);

        // A deadline shorter than the work: DEADLINE_EXCEEDED at the deadline, the worker still
        // frees itself, nothing stays in flight.
        let mut hurried = LocalizerClient::connect(url.clone()).await.unwrap();
        let mut r = pntr_service::tonic::Request::new(req.clone());
        // Half a localization: ample to send the frame, short of the work.
        r.set_timeout(Duration::from_secs_f64((single_s / 2.0).clamp(0.02, 0.5)));
        let e = hurried.localize(r).await.unwrap_err();
        assert_eq!(
            e.code(),
            pntr_service::tonic::Code::DeadlineExceeded,
            "{e:?}"
        );
        wait_for(0.0, false).await;
        wait_busy(0.0).await;
        assert!(again.localize(req).await.is_ok());
        running.shutdown();
        running.wait().await.unwrap();
    });
}
