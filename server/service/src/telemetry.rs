//! Metrics (Prometheus text on its own port) and logs (tracing with an env filter).
//!
//! The recorder is process-wide (the `metrics` facade has one global recorder), installed by the first
//! server of the process; later servers in the same process (tests) share it. `/metrics` is served by
//! a few lines of hyper on a listener the server binds itself, so `--metrics-addr 127.0.0.1:0` works
//! and the bound port can be reported. Labels carry only stage names, status names, gRPC code names
//! map ids and the bounded NOT_LOCALIZED causes: nothing from a request's content.

use std::net::SocketAddr;
use std::sync::OnceLock;
use std::time::Duration;

use http_body_util::Full;
use hyper::body::Bytes;
use metrics_exporter_prometheus::{Matcher, PrometheusBuilder, PrometheusHandle};
use pntr_pipeline::pipeline::Cause;
use pntr_pipeline::prior::Mode;
use tokio::net::TcpListener;

/// Histogram of seconds per stage (`stage` = queue, extraction, retrieval, matching, registration, verification,
/// total; `map_id` = the map that answered).
pub const STAGE_DURATION: &str = "pntr_stage_duration_seconds";
/// Counter of finished requests (`status` = LOCALIZED, NOT_LOCALIZED or ERROR; `code` = gRPC code;
/// `map_id` = the map that answered, empty when the request was refused before a map was resolved,
/// so the label takes only the ids of maps the server has held; NOT_LOCALIZED answers also carry
/// `cause` = NO_MATCH, UNVERIFIED, LOOK_ALIKE, OUTSIDE_MAP or BAD_INPUT, the answer's
/// `NotLocalizedCause`).
pub const REQUESTS_TOTAL: &str = "pntr_requests_total";
/// Gauge of requests being handled (queued or running).
pub const IN_FLIGHT: &str = "pntr_in_flight_requests";
/// Gauge of requests waiting for a worker.
pub const QUEUE_DEPTH: &str = "pntr_queue_depth";
/// Gauge of workers running the pipeline now (work outlives a caller that left; this shows it end).
pub const BUSY_WORKERS: &str = "pntr_busy_workers";
/// Gauge of database images per loaded map (`map_id`), rendered from the loaded maps at each scrape.
pub const MAP_IMAGES: &str = "pntr_map_images";
/// Info gauge (always 1) of each loaded map's version (`map_id`, `version`), rendered from the loaded
/// maps at each scrape: a replaced version's series disappears with it.
pub const MAP_INFO: &str = "pntr_map_info";
/// Gauge: open `LocalizeStream` calls (each holds its tracking state until it ends).
pub const STREAMS_ACTIVE: &str = "pntr_streams_active";
/// Counter: answers by the path that produced them, labelled `mode` (GLOBAL, PRIOR, TRACKING) and
/// `map_id`.
pub const ANSWERS_BY_MODE: &str = "pntr_answers_total";

/// Histogram of answers' calibrated confidence (`status` = LOCALIZED or NOT_LOCALIZED, `map_id`):
/// how close a fleet's answers sit to the map's LOCALIZED threshold.
pub const ANSWER_CONFIDENCE: &str = "pntr_answer_confidence";
/// Gauge, 1 when a loaded map's own confidence calibration is stale (the map changed since it was
/// fitted: extended on a server, merged) and 0 otherwise (`map_id`); rendered at each scrape.
pub const MAP_CALIBRATION_STALE: &str = "pntr_map_calibration_stale";
/// Counter: answered frames the live Foxglove view did not draw because it was still drawing
/// earlier ones (a slow viewer, or images larger than it can encode at the frame rate).
pub const LIVE_VIEW_DROPPED: &str = "pntr_live_view_frames_dropped_total";

/// Gauge: bytes the process's C allocator (glibc malloc) holds for live allocations, Rust's and
/// faiss's, ONNX Runtime's and OpenVINO's alike (`mallinfo2`: `uordblks` + `hblkhd`), read at each
/// scrape. Flat under steady load when nothing leaks; the soak mode of `pntr bench` and the leak
/// test read it.
pub const HEAP_ALLOCATED: &str = "pntr_heap_allocated_bytes";
/// Gauge: bytes glibc malloc holds freed but not returned to the system (`mallinfo2.fordblks`):
/// resident memory above [`HEAP_ALLOCATED`] that later allocations reuse.
pub const HEAP_RETAINED: &str = "pntr_heap_retained_bytes";
/// Gauge of the approximate heap of each loaded map's images and retrieval vectors (`map_id`),
/// rendered from the loaded maps at each scrape: what a map replace adds until the old one drains.
pub const MAP_HEAP: &str = "pntr_map_heap_bytes";

/// Longest a connection to `/metrics` stays open, seconds (Prometheus reconnects; a peer that went
/// quiet does not hold a task for ever).
const METRICS_CONNECTION_S: u64 = 60;

/// Bucket bounds of the confidence histogram.
const CONFIDENCE_BUCKETS: [f64; 13] = [
    0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 0.99, 0.999, 1.0,
];

/// Bucket bounds of the stage histogram, seconds.
const BUCKETS: [f64; 16] = [
    0.001, 0.002, 0.005, 0.01, 0.02, 0.035, 0.05, 0.075, 0.1, 0.15, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
];

static HANDLE: OnceLock<Result<PrometheusHandle, String>> = OnceLock::new();

/// The process's Prometheus handle, installing the recorder on first use.
pub fn prometheus() -> Result<PrometheusHandle, String> {
    HANDLE
        .get_or_init(|| {
            let builder = PrometheusBuilder::new()
                .set_buckets_for_metric(Matcher::Full(STAGE_DURATION.into()), &BUCKETS)
                .and_then(|b| {
                    b.set_buckets_for_metric(
                        Matcher::Full(ANSWER_CONFIDENCE.into()),
                        &CONFIDENCE_BUCKETS,
                    )
                })
                .map_err(|e| e.to_string())?;
            let handle = builder.install_recorder().map_err(|e| {
                format!("installing the metrics recorder (is another one installed?): {e}")
            })?;
            metrics::describe_histogram!(
                STAGE_DURATION,
                metrics::Unit::Seconds,
                "Seconds spent per pipeline stage (queue = waiting for a worker)"
            );
            metrics::describe_counter!(
                REQUESTS_TOTAL,
                "Finished requests by outcome and gRPC code"
            );
            metrics::describe_histogram!(
                ANSWER_CONFIDENCE,
                "Calibrated confidence of answers, by status"
            );
            metrics::describe_gauge!(IN_FLIGHT, "Requests being handled (queued or running)");
            metrics::describe_gauge!(QUEUE_DEPTH, "Requests waiting for a worker");
            metrics::describe_gauge!(BUSY_WORKERS, "Workers running the pipeline");
            metrics::describe_gauge!(
                STREAMS_ACTIVE,
                "Open LocalizeStream calls, each holding its tracking state"
            );
            metrics::describe_counter!(
                ANSWERS_BY_MODE,
                "Answers (LOCALIZED or NOT_LOCALIZED) by the path that produced them"
            );
            metrics::describe_counter!(
                LIVE_VIEW_DROPPED,
                "Answered frames the live Foxglove view skipped while still drawing earlier ones"
            );
            // Register the series so a scrape shows them before the first request.
            metrics::gauge!(IN_FLIGHT).set(0.0);
            metrics::gauge!(QUEUE_DEPTH).set(0.0);
            metrics::gauge!(BUSY_WORKERS).set(0.0);
            metrics::gauge!(STREAMS_ACTIVE).set(0.0);
            metrics::counter!(LIVE_VIEW_DROPPED).increment(0);
            Ok(handle)
        })
        .clone()
}

/// Register a map's answer series at 0 (so rates and alerts see them before its first request),
/// leaving counts already made under that id as they are (a replaced map keeps its id's series).
pub fn register_map(map_id: &str) {
    metrics::counter!(REQUESTS_TOTAL, "status" => "LOCALIZED", "code" => "OK", "map_id" => map_id.to_string())
        .increment(0);
    for cause in Cause::ALL {
        metrics::counter!(REQUESTS_TOTAL, "status" => "NOT_LOCALIZED", "code" => "OK", "cause" => cause.name(), "map_id" => map_id.to_string())
            .increment(0);
    }
    for mode in [Mode::Global, Mode::Prior, Mode::Tracking] {
        metrics::counter!(ANSWERS_BY_MODE, "mode" => mode.name(), "map_id" => map_id.to_string())
            .increment(0);
    }
}

/// One loaded map as the per-map series show it.
pub struct MapSeries {
    /// Its id.
    pub map_id: String,
    /// Its version label.
    pub version: String,
    /// Database images.
    pub images: usize,
    /// Whether its own calibration is stale.
    pub calibration_stale: bool,
    /// Approximate heap of its images and retrieval vectors, bytes.
    pub heap_bytes: usize,
}

/// The per-map series, in Prometheus text: [`MAP_INFO`], [`MAP_IMAGES`] and
/// [`MAP_CALIBRATION_STALE`] for each loaded map. They are written from the maps loaded at the
/// time of the scrape rather than kept in the recorder, so a map that was unloaded or replaced
/// leaves no stale series behind.
pub fn render_maps(maps: &[MapSeries]) -> String {
    let escape = |v: &str| {
        v.replace('\\', "\\\\")
            .replace('"', "\\\"")
            .replace('\n', "\\n")
    };
    let mut out = String::new();
    // One gauge family: its help line, then one sample a map (labels, value).
    let mut family = |name: &str, help: &str, sample: &dyn Fn(&MapSeries) -> (String, String)| {
        out += &format!("# HELP {name} {help}\n# TYPE {name} gauge\n");
        for m in maps {
            let (labels, value) = sample(m);
            out += &format!("{name}{{{labels}}} {value}\n");
        }
    };
    let id = |m: &MapSeries| format!("map_id=\"{}\"", escape(&m.map_id));
    family(MAP_INFO, "Version of each loaded map (always 1)", &|m| {
        (
            format!("{},version=\"{}\"", id(m), escape(&m.version)),
            "1".into(),
        )
    });
    family(MAP_IMAGES, "Database images of each loaded map", &|m| {
        (id(m), m.images.to_string())
    });
    family(
        MAP_HEAP,
        "Approximate heap of each loaded map's images and retrieval vectors, bytes",
        &|m| (id(m), m.heap_bytes.to_string()),
    );
    family(
        MAP_CALIBRATION_STALE,
        "1 when a loaded map's own confidence calibration is stale (the map changed since it was fitted)",
        &|m| (id(m), u8::from(m.calibration_stale).to_string()),
    );
    out
}

/// The glibc allocator's view of the heap: (bytes in live allocations, bytes freed but retained).
/// `None` off glibc.
pub fn heap_bytes() -> Option<(u64, u64)> {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: mallinfo2 (glibc >= 2.33) takes no arguments, only reads the allocator's arenas
        // under their locks and returns a plain struct by value.
        #[allow(unsafe_code)]
        let m = unsafe { libc::mallinfo2() };
        Some(((m.uordblks + m.hblkhd) as u64, m.fordblks as u64))
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        None
    }
}

/// The process collector (Prometheus' `process_*` names: resident and virtual memory, open and
/// maximum file descriptors, start time, CPU seconds, threads), described once.
fn process_collector() -> &'static metrics_process::Collector {
    static COLLECTOR: OnceLock<metrics_process::Collector> = OnceLock::new();
    COLLECTOR.get_or_init(|| {
        let c = metrics_process::Collector::default();
        c.describe();
        metrics::describe_gauge!(
            HEAP_ALLOCATED,
            metrics::Unit::Bytes,
            "Bytes the C allocator holds for live allocations (glibc mallinfo2: uordblks + hblkhd)"
        );
        metrics::describe_gauge!(
            HEAP_RETAINED,
            metrics::Unit::Bytes,
            "Bytes the C allocator holds freed, not returned to the system (mallinfo2: fordblks)"
        );
        c
    })
}

/// Read the process figures and the heap into the recorder (at each scrape, before rendering).
pub fn collect_process() {
    process_collector().collect();
    if let Some((allocated, retained)) = heap_bytes() {
        metrics::gauge!(HEAP_ALLOCATED).set(allocated as f64);
        metrics::gauge!(HEAP_RETAINED).set(retained as f64);
    }
}

/// Serve `GET /metrics` (any path, in fact) on `listener` until `stop` resolves; also runs the
/// recorder's periodic upkeep. `maps` gives the loaded maps at each scrape ([`render_maps`]).
pub async fn serve_metrics(
    listener: TcpListener,
    handle: PrometheusHandle,
    mut stop: tokio::sync::watch::Receiver<bool>,
    maps: std::sync::Arc<dyn Fn() -> Vec<MapSeries> + Send + Sync>,
) {
    let upkeep = handle.clone();
    let upkeep_task = tokio::spawn(async move {
        loop {
            tokio::time::sleep(Duration::from_secs(5)).await;
            upkeep.run_upkeep();
        }
    });
    loop {
        let accepted = tokio::select! {
            a = listener.accept() => a,
            _ = crate::server::stopped(&mut stop) => break,
        };
        let Ok((stream, _)) = accepted else {
            continue;
        };
        let handle = handle.clone();
        let maps = maps.clone();
        tokio::spawn(async move {
            let svc =
                hyper::service::service_fn(move |req: hyper::Request<hyper::body::Incoming>| {
                    let handle = handle.clone();
                    let maps = maps.clone();
                    async move {
                        let resp = if req.uri().path() == "/metrics" {
                            collect_process();
                            let mut text = handle.render();
                            text += &render_maps(&maps());
                            hyper::Response::builder()
                                .header("content-type", "text/plain; version=0.0.4")
                                .body(Full::new(Bytes::from(text)))
                        } else {
                            hyper::Response::builder()
                                .status(404)
                                .body(Full::new(Bytes::from_static(b"see /metrics\n")))
                        };
                        resp
                    }
                });
            let io = hyper_util::rt::TokioIo::new(stream);
            // A scraper that connects and goes quiet holds a task and its buffers: each connection
            // gets METRICS_CONNECTION_S seconds, however many scrapes it carries.
            let served = hyper::server::conn::http1::Builder::new().serve_connection(io, svc);
            match tokio::time::timeout(Duration::from_secs(METRICS_CONNECTION_S), served).await {
                Ok(Err(e)) => tracing::debug!(error = %e, "metrics connection"),
                Ok(Ok(())) => {}
                Err(_) => {
                    tracing::debug!("metrics connection closed after {METRICS_CONNECTION_S} s")
                }
            }
        });
    }
    upkeep_task.abort();
}

/// Bind the metrics listener (separately, so that a busy port is a start-up error).
pub async fn bind_metrics(addr: SocketAddr) -> std::io::Result<TcpListener> {
    TcpListener::bind(addr).await
}

/// Logs to stderr (stdout carries the one "listening" line), filtered by `PNTR_LOG`, else `RUST_LOG`,
/// else `info`; colours only on a terminal (a file, journald or `docker logs` gets plain text). Safe to
/// call more than once.
pub fn init_tracing() {
    use std::io::IsTerminal;
    let mut filter = std::env::var("PNTR_LOG")
        .or_else(|_| std::env::var("RUST_LOG"))
        .unwrap_or_else(|_| "info".into());
    // The Foxglove SDK's "Started server on 127.0.0.1:PORT" names the port behind the live view's
    // front door, not the one viewers use (which the server logs itself): quiet unless asked for.
    if !filter.contains("foxglove") {
        filter.push_str(",foxglove::websocket::server=warn");
    }
    let _ = tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::new(filter))
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .try_init();
}
