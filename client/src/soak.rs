//! `pntr bench --soak`: does the server's memory stay flat under hours of load?
//!
//! The soak runs load phases one after another, each for `--warmup` then `--duration` seconds,
//! while it reads the server's memory from its `/metrics` every `--sample-s` seconds
//! (`process_resident_memory_bytes`, and `pntr_heap_allocated_bytes`: the bytes glibc's malloc
//! holds for live allocations, Rust's and the C++ libraries' alike). For each phase it reports, over
//! the measured part (after the warm-up), the growth per answered request and per hour, both as
//! the team measures it (end minus start, divided) and as the least-squares slope of memory against
//! requests answered over every reading (less sensitive to where the allocator happens to stand at
//! the two ends). Phases:
//! - `single`: `--concurrency` clients sending single Localize calls back to back;
//! - `streams`: `--robots` LocalizeStreams sending frames in order (at `--rate-hz`, else back to
//!   back) that stay open for the whole phase;
//! - `churn`: the same robots, each leaving after `--churn-frames` frames and coming back on a new
//!   stream (robots that connect and leave);
//! - `replace`: single calls as in `single` while the served map is replaced (`ReplaceMap` with
//!   `--replace-file`) every `--replace-every-s` seconds: every replace must give its old map back.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use http_body_util::BodyExt;
use pntr_service::proto::{
    self, localizer_client::LocalizerClient, map_admin_client::MapAdminClient,
};
use pntr_service::tokio;
use pntr_service::tonic::transport::Channel;
use serde::Serialize;

use crate::load::{drive, one, Record, RobotTally, Robots};
use crate::remote::{authorized, ConnectArgs};

/// The soak's own flags of `pntr bench`.
#[derive(clap::Args, Debug, Clone)]
pub struct SoakArgs {
    /// Soak the server: run the load phases (--phases) one after another, each for --warmup then
    /// --duration seconds, read the server's memory from its /metrics (--metrics-addr) as they run,
    /// and report each phase's growth per request and per hour (with --plot, a picture of memory
    /// over time; with --json, every reading).
    #[arg(long, requires = "metrics_addr")]
    pub soak: bool,
    /// The server's metrics address, HOST:PORT (`pntr-server --metrics-addr`; it prints it on its
    /// `listening` line).
    #[arg(long, value_name = "HOST:PORT")]
    pub metrics_addr: Option<String>,
    /// The soak's phases in order, from `single`, `streams`, `churn`, `replace` (default: single,
    /// streams, churn, and replace when --replace-file is given).
    #[arg(long, value_delimiter = ',')]
    pub phases: Option<Vec<String>>,
    /// Seconds between two readings of the server's memory.
    #[arg(long, default_value_t = 5.0)]
    pub sample_s: f64,
    /// The `replace` phase: a map file on the server, holding the served map's id, that replaces it
    /// (`pntr.v1.MapAdmin/ReplaceMap`) every --replace-every-s seconds.
    #[arg(long, value_name = "MAP.pntrmap")]
    pub replace_file: Option<String>,
    /// Seconds between two map replaces in the `replace` phase.
    #[arg(long, default_value_t = 30.0)]
    pub replace_every_s: f64,
    /// The server's admin token (`pntr-server --admin-token`), for the replaces; or
    /// PNTR_ADMIN_TOKEN.
    #[arg(long, env = "PNTR_ADMIN_TOKEN", hide_env_values = true)]
    pub admin_token: Option<String>,
}

/// A load phase of the soak.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    Single,
    Streams,
    Churn,
    Replace,
}

impl Phase {
    fn parse(name: &str) -> Result<Self> {
        Ok(match name {
            "single" => Self::Single,
            "streams" => Self::Streams,
            "churn" => Self::Churn,
            "replace" => Self::Replace,
            other => bail!("--phases: unknown phase `{other}` (single, streams, churn, replace)"),
        })
    }

    fn name(self) -> &'static str {
        match self {
            Self::Single => "single",
            Self::Streams => "streams",
            Self::Churn => "churn",
            Self::Replace => "replace",
        }
    }
}

/// The server's memory at one moment.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Memory {
    /// `process_resident_memory_bytes`.
    pub rss_bytes: f64,
    /// `pntr_heap_allocated_bytes` (NaN when the server does not export it).
    pub heap_bytes: f64,
}

/// One reading during the soak.
#[derive(Debug, Clone, Serialize)]
struct Sample {
    /// Seconds since the soak started.
    t_s: f64,
    phase: &'static str,
    /// Whether it fell in the phase's measured part (after its warm-up).
    measured: bool,
    /// Requests answered since the soak started.
    answered: u64,
    #[serde(flatten)]
    memory: Memory,
}

/// One phase's figures.
#[derive(Debug, Clone, Serialize)]
struct PhaseReport {
    phase: &'static str,
    warmup_s: f64,
    duration_s: f64,
    /// Requests answered in the measured part.
    requests: u64,
    /// Failed calls in the measured part.
    errors: u64,
    errors_by_code: BTreeMap<String, u64>,
    /// Answers per second in the measured part.
    fps: f64,
    start: Memory,
    end: Memory,
    /// (end - start) / requests: the team's measure.
    rss_bytes_per_request: f64,
    heap_bytes_per_request: f64,
    /// Least-squares slope of memory against answered requests over the measured readings.
    rss_slope_bytes_per_request: f64,
    heap_slope_bytes_per_request: f64,
    /// (end - start) per hour of this load.
    rss_mb_per_hour: f64,
    heap_mb_per_hour: f64,
    /// Streams opened (streams, churn).
    streams_opened: u64,
    /// Camera slots missed (streams and churn with --rate-hz).
    missed_slots: u64,
    /// Map replaces done, and refused (replace).
    replaces: u64,
    replaces_failed: u64,
}

/// What `pntr bench --soak` needs from the rest of the command.
pub(crate) struct SoakLoad<'a> {
    pub connect: &'a ConnectArgs,
    pub frames: Arc<Vec<proto::LocalizeRequest>>,
    pub concurrency: usize,
    pub robots: Robots,
    pub warmup_s: f64,
    pub duration_s: f64,
    pub plot: Option<PathBuf>,
    pub json: Option<PathBuf>,
}

/// Read `name`'s value from Prometheus text (the first series whose name is exactly `name`).
fn series(text: &str, name: &str) -> Option<f64> {
    text.lines().find_map(|l| {
        let (key, value) = l.rsplit_once(' ')?;
        let key = key.trim();
        (key == name || key.strip_prefix(name)?.starts_with('{'))
            .then(|| value.trim().parse().ok())
            .flatten()
    })
}

/// The server's memory, read from its /metrics at `addr` (HOST:PORT). Errors name `--metrics-addr`
/// and what went wrong (nothing listening, not HTTP, not pntr-server's metrics).
pub(crate) async fn read_memory(addr: &str) -> Result<Memory> {
    let text = scrape(addr)
        .await
        .with_context(|| format!("--metrics-addr {addr}: reading /metrics (is it pntr-server's metrics address, the second on its `listening` line?)"))?;
    let rss = series(&text, "process_resident_memory_bytes").with_context(|| {
        format!("--metrics-addr {addr}: no process_resident_memory_bytes on /metrics (is it pntr-server's metrics port?)")
    })?;
    Ok(Memory {
        rss_bytes: rss,
        heap_bytes: series(&text, pntr_service::telemetry::HEAP_ALLOCATED).unwrap_or(f64::NAN),
    })
}

/// `GET /metrics` at `addr` over HTTP/1.1: the body.
async fn scrape(addr: &str) -> Result<String> {
    let stream = tokio::net::TcpStream::connect(addr).await?;
    let (mut sender, conn) =
        hyper::client::conn::http1::handshake(hyper_util::rt::TokioIo::new(stream)).await?;
    let conn = tokio::spawn(conn);
    let req = hyper::Request::get("/metrics")
        .header("host", addr)
        .body(http_body_util::Empty::<hyper::body::Bytes>::new())?;
    let resp = tokio::time::timeout(Duration::from_secs(10), sender.send_request(req))
        .await
        .context("no answer within 10 s")??;
    if !resp.status().is_success() {
        bail!("/metrics answered {}", resp.status());
    }
    let body = resp.into_body().collect().await?.to_bytes();
    drop(sender);
    let _ = conn.await;
    Ok(String::from_utf8_lossy(&body).into_owned())
}

/// Least-squares slope of `y` against `x`; 0 with fewer than two distinct x.
fn slope(points: &[(f64, f64)]) -> f64 {
    let points: Vec<&(f64, f64)> = points.iter().filter(|(_, y)| y.is_finite()).collect();
    let n = points.len() as f64;
    if n < 2.0 {
        return 0.0;
    }
    let mx = points.iter().map(|p| p.0).sum::<f64>() / n;
    let my = points.iter().map(|p| p.1).sum::<f64>() / n;
    let sxx: f64 = points.iter().map(|p| (p.0 - mx).powi(2)).sum();
    let sxy: f64 = points.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    if sxx <= 0.0 {
        0.0
    } else {
        sxy / sxx
    }
}

/// Counts of what the load got back.
#[derive(Default)]
struct Counts {
    answered: AtomicU64,
    errors: AtomicU64,
    by_code: Mutex<BTreeMap<String, u64>>,
}

impl Counts {
    fn add(&self, r: Record) {
        match r.code {
            None => {
                self.answered.fetch_add(1, Ordering::Relaxed);
            }
            Some(code) => {
                self.errors.fetch_add(1, Ordering::Relaxed);
                *self
                    .by_code
                    .lock()
                    .expect("counts")
                    .entry(code)
                    .or_insert(0) += 1;
            }
        }
    }
}

/// The phases to run, from --phases or the default.
fn phases(args: &SoakArgs) -> Result<Vec<Phase>> {
    let list = match &args.phases {
        Some(names) => names
            .iter()
            .map(|n| Phase::parse(n.trim()))
            .collect::<Result<Vec<_>>>()?,
        None => {
            let mut v = vec![Phase::Single, Phase::Streams, Phase::Churn];
            if args.replace_file.is_some() {
                v.push(Phase::Replace);
            }
            v
        }
    };
    if list.is_empty() {
        bail!("--phases: name at least one phase");
    }
    if list.contains(&Phase::Replace) {
        if args.replace_file.is_none() {
            bail!("the replace phase needs --replace-file (a map file on the server with the served map's id)");
        }
        if args.admin_token.is_none() {
            bail!("the replace phase needs the server's admin token: --admin-token or PNTR_ADMIN_TOKEN");
        }
        if !(args.replace_every_s.is_finite() && args.replace_every_s > 0.0) {
            bail!("--replace-every-s must be a positive number of seconds");
        }
    }
    if !(args.sample_s.is_finite() && args.sample_s > 0.0) {
        bail!("--sample-s must be a positive number of seconds");
    }
    Ok(list)
}

/// Single calls from `concurrency` clients until `end`.
async fn single_calls(
    c: LocalizerClient<Channel>,
    connect: ConnectArgs,
    frames: Arc<Vec<proto::LocalizeRequest>>,
    concurrency: usize,
    end: Instant,
    counts: Arc<Counts>,
) {
    let next = Arc::new(AtomicUsize::new(0));
    let tasks: Vec<_> = (0..concurrency.max(1))
        .map(|_| {
            let (c, connect, frames, next, counts) = (
                c.clone(),
                connect.clone(),
                frames.clone(),
                next.clone(),
                counts.clone(),
            );
            tokio::spawn(async move {
                while Instant::now() < end {
                    let i = next.fetch_add(1, Ordering::Relaxed) % frames.len();
                    counts.add(one(c.clone(), &connect, frames[i].clone(), Instant::now()).await);
                }
            })
        })
        .collect();
    for t in tasks {
        let _ = t.await;
    }
}

/// The map a replace swaps: --map-id, else the server's only map.
async fn served_map(
    admin: &mut MapAdminClient<Channel>,
    admin_connect: &ConnectArgs,
    map_id: &str,
) -> Result<String> {
    if !map_id.is_empty() {
        return Ok(map_id.to_string());
    }
    let maps = admin
        .list_maps(authorized(admin_connect, proto::ListMapsRequest {})?)
        .await
        .map_err(|s| anyhow::anyhow!("ListMaps: {}", s.message()))?
        .into_inner()
        .maps;
    match maps.as_slice() {
        [m] => Ok(m.map_id.clone()),
        _ => bail!(
            "the server holds {} maps: name the one to replace with --map-id",
            maps.len()
        ),
    }
}

/// Replace `map_id` by `file` every `every` until `end`: (done, refused).
async fn replaces(
    mut admin: MapAdminClient<Channel>,
    connect: ConnectArgs,
    map_id: String,
    file: String,
    every: Duration,
    end: Instant,
) -> (u64, u64) {
    let (mut done, mut failed) = (0, 0);
    loop {
        let at = Instant::now() + every;
        if at >= end {
            return (done, failed);
        }
        tokio::time::sleep_until(at.into()).await;
        let req = proto::ReplaceMapRequest {
            map_id: map_id.clone(),
            file: file.clone(),
        };
        let ok = match authorized(&connect, req) {
            Ok(r) => admin.replace_map(r).await.is_ok(),
            Err(_) => false,
        };
        if ok {
            done += 1;
        } else {
            failed += 1;
        }
    }
}

/// Run the soak: every phase in turn, memory read as it goes; prints the table, writes the JSON and
/// the picture.
pub(crate) fn run(
    args: &SoakArgs,
    load: SoakLoad<'_>,
    rt: &tokio::runtime::Runtime,
    c: LocalizerClient<Channel>,
) -> Result<()> {
    let list = phases(args)?;
    let metrics = args
        .metrics_addr
        .clone()
        .context("--soak needs --metrics-addr")?;
    // Fail before any load when the metrics are not there.
    let first = rt.block_on(read_memory(&metrics))?;
    if first.heap_bytes.is_nan() {
        eprintln!(
            "warning: the server exports no {}: only its resident memory is measured",
            pntr_service::telemetry::HEAP_ALLOCATED
        );
    }
    let t0 = Instant::now();
    let counts = Arc::new(Counts::default());
    let samples: Arc<Mutex<Vec<Sample>>> = Arc::new(Mutex::new(Vec::new()));
    let current: Arc<Mutex<(&'static str, bool)>> = Arc::new(Mutex::new(("", false)));
    let sampler = {
        let (metrics, counts, samples, current) = (
            metrics.clone(),
            counts.clone(),
            samples.clone(),
            current.clone(),
        );
        let every = Duration::from_secs_f64(args.sample_s);
        rt.spawn(async move {
            loop {
                let (phase, measured) = *current.lock().expect("phase");
                if phase.is_empty() {
                    // Before the first phase starts.
                } else if let Ok(memory) = read_memory(&metrics).await {
                    samples.lock().expect("samples").push(Sample {
                        t_s: t0.elapsed().as_secs_f64(),
                        phase,
                        measured,
                        answered: counts.answered.load(Ordering::Relaxed),
                        memory,
                    });
                }
                tokio::time::sleep(every).await;
            }
        })
    };
    let admin = match list.contains(&Phase::Replace) {
        true => Some(MapAdminClient::new(
            rt.block_on(crate::remote::channel(load.connect))?,
        )),
        false => None,
    };
    let admin_connect = ConnectArgs {
        token: args.admin_token.clone(),
        map_id: String::new(),
        ..load.connect.clone()
    };
    let map_id = match &admin {
        Some(a) => Some(rt.block_on(served_map(
            &mut a.clone(),
            &admin_connect,
            &load.connect.map_id,
        ))?),
        None => None,
    };
    println!(
        "{:>8} {:>9} {:>7} {:>8} {:>21} {:>9} {:>9} {:>21} {:>9} {:>11} {:>9} {:>8}",
        "phase",
        "requests",
        "errors",
        "fps",
        "resident MB",
        "B/req",
        "MB/hour",
        "heap MB",
        "B/req",
        "slope B/req",
        "MB/hour",
        "replaces"
    );
    if load.duration_s < 600.0 {
        eprintln!(
            "note: growth per hour is extrapolated from {:.0} s a phase; the allocator settles for minutes, so judge it over phases of 10 minutes or more",
            load.duration_s
        );
    }
    let mut reports = Vec::new();
    for phase in list {
        eprintln!(
            "{}: {:.0} s of warm-up, then {:.0} s measured",
            phase.name(),
            load.warmup_s,
            load.duration_s
        );
        *current.lock().expect("phase") = (phase.name(), false);
        let tally = Arc::new(RobotTally::default());
        let end = Instant::now() + Duration::from_secs_f64(load.warmup_s + load.duration_s);
        let sink: Arc<dyn Fn(Record) + Send + Sync> = {
            let counts = counts.clone();
            Arc::new(move |r| counts.add(r))
        };
        let work = match phase {
            Phase::Single | Phase::Replace => rt.spawn(single_calls(
                c.clone(),
                load.connect.clone(),
                load.frames.clone(),
                load.concurrency,
                end,
                counts.clone(),
            )),
            Phase::Streams | Phase::Churn => {
                let robots = Robots {
                    churn_frames: if phase == Phase::Churn {
                        load.robots.churn_frames.max(1)
                    } else {
                        0
                    },
                    ..load.robots
                };
                rt.spawn(drive(
                    c.clone(),
                    load.connect.clone(),
                    load.frames.clone(),
                    robots,
                    end,
                    sink,
                    tally.clone(),
                ))
            }
        };
        let replacer = match (phase, &admin, &map_id, &args.replace_file) {
            (Phase::Replace, Some(a), Some(id), Some(file)) => Some(rt.spawn(replaces(
                a.clone(),
                admin_connect.clone(),
                id.clone(),
                file.clone(),
                Duration::from_secs_f64(args.replace_every_s),
                end,
            ))),
            _ => None,
        };
        rt.block_on(async { tokio::time::sleep(Duration::from_secs_f64(load.warmup_s)).await });
        let mark = |measured: bool| -> Result<Sample> {
            let memory = rt.block_on(read_memory(&metrics))?;
            let s = Sample {
                t_s: t0.elapsed().as_secs_f64(),
                phase: phase.name(),
                measured,
                answered: counts.answered.load(Ordering::Relaxed),
                memory,
            };
            samples.lock().expect("samples").push(s.clone());
            Ok(s)
        };
        let errors_before = counts.errors.load(Ordering::Relaxed);
        let codes_before = counts.by_code.lock().expect("counts").clone();
        let (opened_before, missed_before) = (
            tally.streams_opened.load(Ordering::Relaxed),
            tally.missed_slots.load(Ordering::Relaxed),
        );
        let start = mark(true)?;
        *current.lock().expect("phase") = (phase.name(), true);
        rt.block_on(async { tokio::time::sleep_until(end.into()).await });
        let stop = mark(true)?;
        *current.lock().expect("phase") = (phase.name(), false);
        let _ = rt.block_on(work);
        let (replaced, replace_failed) = match replacer {
            Some(t) => rt.block_on(t).unwrap_or((0, 0)),
            None => (0, 0),
        };
        let requests = stop.answered - start.answered;
        let wall = stop.t_s - start.t_s;
        let per_request = |a: f64, b: f64| (b - a) / (requests.max(1) as f64);
        let per_hour = |a: f64, b: f64| (b - a) / 1e6 / wall.max(1e-9) * 3600.0;
        let measured: Vec<Sample> = samples
            .lock()
            .expect("samples")
            .iter()
            .filter(|s| {
                s.phase == phase.name() && s.measured && s.t_s >= start.t_s && s.t_s <= stop.t_s
            })
            .cloned()
            .collect();
        let along = |f: fn(&Memory) -> f64| -> Vec<(f64, f64)> {
            measured
                .iter()
                .map(|s| (s.answered as f64, f(&s.memory)))
                .collect()
        };
        let codes_after = counts.by_code.lock().expect("counts").clone();
        let report = PhaseReport {
            phase: phase.name(),
            warmup_s: load.warmup_s,
            duration_s: wall,
            requests,
            errors: counts.errors.load(Ordering::Relaxed) - errors_before,
            errors_by_code: codes_after
                .into_iter()
                .map(|(k, v)| {
                    let before = codes_before.get(&k).copied().unwrap_or(0);
                    (k, v - before)
                })
                .filter(|(_, v)| *v > 0)
                .collect(),
            fps: requests as f64 / wall.max(1e-9),
            start: start.memory,
            end: stop.memory,
            rss_bytes_per_request: per_request(start.memory.rss_bytes, stop.memory.rss_bytes),
            heap_bytes_per_request: per_request(start.memory.heap_bytes, stop.memory.heap_bytes),
            rss_slope_bytes_per_request: slope(&along(|m| m.rss_bytes)),
            heap_slope_bytes_per_request: slope(&along(|m| m.heap_bytes)),
            rss_mb_per_hour: per_hour(start.memory.rss_bytes, stop.memory.rss_bytes),
            heap_mb_per_hour: per_hour(start.memory.heap_bytes, stop.memory.heap_bytes),
            streams_opened: tally.streams_opened.load(Ordering::Relaxed) - opened_before,
            missed_slots: tally.missed_slots.load(Ordering::Relaxed) - missed_before,
            replaces: replaced,
            replaces_failed: replace_failed,
        };
        print_row(&report);
        if phase == Phase::Replace && (report.replaces_failed > 0 || report.replaces == 0) {
            eprintln!(
                "warning: {} of {} map replaces were refused (--replace-file must be a map file on the server holding the served map's id), and a phase shorter than --replace-every-s replaces nothing",
                report.replaces_failed,
                report.replaces + report.replaces_failed
            );
        }
        for (code, n) in &report.errors_by_code {
            eprintln!("{}: {n} requests failed with {code}", report.phase);
        }
        reports.push(report);
    }
    sampler.abort();
    let samples = std::mem::take(&mut *samples.lock().expect("samples"));
    if let Some(dir) = &load.plot {
        let points: Vec<crate::plot::SoakPoint> = samples
            .iter()
            .map(|s| crate::plot::SoakPoint {
                minutes: s.t_s / 60.0,
                phase: s.phase.to_string(),
                rss_mb: s.memory.rss_bytes / 1e6,
                heap_mb: s.memory.heap_bytes / 1e6,
            })
            .collect();
        let title = format!(
            "pntr-server memory under pntr bench --soak ({:.0} s a phase after {:.0} s of warm-up)",
            load.duration_s, load.warmup_s
        );
        let files = crate::plot::soak_plot(&points, dir, &title)?;
        eprintln!("{} pictures written to {}", files.len(), dir.display());
    }
    if let Some(path) = &load.json {
        let v = serde_json::json!({ "soak": reports, "samples": samples });
        crate::output::write_json(path, &v)?;
        eprintln!("report written to {}", path.display());
    }
    Ok(())
}

fn print_row(r: &PhaseReport) {
    let mb = |b: f64| b / 1e6;
    println!(
        "{:>8} {:>9} {:>7} {:>8.1} {:>9.1} -> {:>8.1} {:>9.0} {:>9.1} {:>9.1} -> {:>8.1} {:>9.0} {:>11.0} {:>9.1} {:>8}",
        r.phase,
        r.requests,
        r.errors,
        r.fps,
        mb(r.start.rss_bytes),
        mb(r.end.rss_bytes),
        r.rss_bytes_per_request,
        r.rss_mb_per_hour,
        mb(r.start.heap_bytes),
        mb(r.end.heap_bytes),
        r.heap_bytes_per_request,
        r.heap_slope_bytes_per_request,
        r.heap_mb_per_hour,
        r.replaces
    );
}

#[cfg(test)]
mod tests {
    use super::{series, slope};

    #[test]
    fn series_are_read_by_their_exact_name() {
        let text = "# HELP process_resident_memory_bytes x\nprocess_resident_memory_bytes 1.5e8\nprocess_resident_memory_bytes_max 9\npntr_heap_allocated_bytes{a=\"b\"} 42\n";
        assert_eq!(series(text, "process_resident_memory_bytes"), Some(1.5e8));
        assert_eq!(series(text, "pntr_heap_allocated_bytes"), Some(42.0));
        assert_eq!(series(text, "pntr_heap"), None);
    }

    #[test]
    fn the_slope_of_a_line_is_its_growth() {
        let line: Vec<(f64, f64)> = (0..10)
            .map(|i| (i as f64 * 100.0, 5e7 + 2.5e3 * i as f64 * 100.0))
            .collect();
        assert!((slope(&line) - 2500.0).abs() < 1e-6);
        assert_eq!(slope(&[(1.0, 2.0)]), 0.0);
        assert_eq!(slope(&[(1.0, 2.0), (1.0, 3.0)]), 0.0);
    }
}
