//! `pntr bench`: load-test a running server with real query frames.
//!
//! Closed loop (`--concurrency C`): C clients send back to back, so the server sets the pace and the
//! figure is the throughput it sustains at that concurrency. Open loop (`--rate R`): requests leave on a
//! fixed schedule whatever the answers do, and latency is counted from the scheduled send time, so a
//! slow server cannot hide its queueing (no coordinated omission). Robots (`--robots N`): N
//! LocalizeStreams sending frames in order as robots do ([`crate::load`]). Soak (`--soak`): load
//! phases for minutes to hours while the server's memory is read ([`crate::soak`]). Frames are read
//! from a dataset's queries or a recording (`--sequence`) and encoded before the clock starts; a
//! warm-up is sent and not counted.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use pntr_dataset::{DatasetIndex, Role};
use pntr_service::proto::{self, localizer_client::LocalizerClient};
use pntr_service::tonic::transport::Channel;
use pntr_service::{tokio, wire};
use serde::Serialize;

use crate::load::{one, Record, RobotTally, Robots};
use crate::remote::{channel, client, ConnectArgs};

/// Arguments of `pntr bench`.
#[derive(clap::Args, Debug)]
pub struct BenchArgs {
    /// Where the server is, and how to authenticate.
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// Dataset whose query frames are sent (or --sequence).
    #[arg(
        long,
        required_unless_present = "sequence",
        conflicts_with = "sequence"
    )]
    pub dataset: Option<PathBuf>,
    /// A recording whose frames are sent instead, read as `pntr replay` reads it: a TUM RGB-D
    /// folder, a ROS 2 bag (folder or `.mcap`) or a 7-Scenes folder; --frames of its frames, evenly
    /// spaced and in order, sent as a robot's compressed topics carry them (JPEG quality 90 colour,
    /// uint16 millimetre depth) at the recording's size.
    #[arg(long, value_name = "DIR|FILE.mcap")]
    pub sequence: Option<PathBuf>,
    /// ROS 2 bag topics and a separate depth camera (--sequence).
    #[command(flatten)]
    pub topics: crate::recordings::TopicArgs,
    /// --sequence: the colour camera as `fx,fy,cx,cy[,k1,k2,p1,p2[,k3]]` when the recording names
    /// none (7-Scenes: 525,525,320,240).
    #[arg(long, value_name = "FX,FY,CX,CY")]
    pub intrinsics: Option<String>,
    /// --sequence: depth units per metre, replacing what the recording's format says.
    #[arg(long, value_name = "UNITS_PER_M")]
    pub depth_scale: Option<f64>,
    /// Robots: this many LocalizeStreams, each sending the frames in order, forward then back,
    /// instead of single calls (--concurrency and --rate are then not used).
    #[arg(long, conflicts_with = "rate")]
    pub robots: Option<usize>,
    /// With --robots: frames per second each robot's camera delivers (a frame due while the robot's
    /// previous one is unanswered is a missed slot); default: back to back.
    #[arg(long, value_name = "HZ")]
    pub rate_hz: Option<f64>,
    /// With --robots: each robot leaves after this many answered frames and comes back on a new
    /// stream (robots that connect and leave); in a soak's `churn` phase, default 10.
    #[arg(long, value_name = "FRAMES")]
    pub churn_frames: Option<usize>,
    /// The soak mode.
    #[command(flatten)]
    pub soak: crate::soak::SoakArgs,
    /// Only this scene's queries.
    #[arg(long)]
    pub scene: Option<String>,
    /// Closed-loop clients sending back to back (with --rate: the most requests in flight, x64).
    #[arg(long, default_value_t = 1)]
    pub concurrency: usize,
    /// Seconds to measure (after the warm-up).
    #[arg(long, default_value_t = 10.0)]
    pub duration: f64,
    /// Open loop: requests per second on a fixed schedule instead of closed-loop clients.
    #[arg(long)]
    pub rate: Option<f64>,
    /// Run these concurrencies one after another (e.g. 1,2,4,8) and print a table and a plot.
    #[arg(long, value_delimiter = ',')]
    pub sweep: Option<Vec<usize>>,
    /// Seconds of warm-up, not counted.
    #[arg(long, default_value_t = 2.0)]
    pub warmup: f64,
    /// Distinct frames to cycle through (evenly spaced queries of the dataset).
    #[arg(long, default_value_t = 100)]
    pub frames: usize,
    /// Write the JSON report here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// With --sweep: also draw frames per second and latency against concurrency into this folder
    /// (bench_sweep.png and .svg); with --soak: the server's memory against time
    /// (soak_memory.png and .svg).
    #[arg(long, value_name = "DIR")]
    pub plot: Option<PathBuf>,
    /// Also measure the service's overhead: load this map in this process and time every frame
    /// through the server (one at a time) and through the in-process pipeline, alternately.
    #[arg(long)]
    pub compare_in_process: Option<PathBuf>,
    /// Folder of the ONNX models (for --compare-in-process).
    /// (default: `PNTR_MODELS`, `./models`, next to the executable, `../share/pntr/models`).
    #[arg(long)]
    pub models: Option<PathBuf>,
    /// ONNX Runtime threads of the in-process pipeline (match the server's --ort-threads).
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
}

/// Service overhead: the same frames through the server and in process, alternately, one at a time.
#[derive(Debug, Clone, Serialize)]
pub struct Overhead {
    pairs: usize,
    remote_ms_mean: f64,
    in_process_ms_mean: f64,
    remote_ms_p50: f64,
    in_process_ms_p50: f64,
    /// remote mean / in-process mean.
    ratio: f64,
}

/// Latency percentiles, ms.
#[derive(Debug, Clone, Serialize)]
pub struct Latency {
    p50: f64,
    p90: f64,
    p99: f64,
    max: f64,
    mean: f64,
}

/// One measured run (the JSON of `pntr bench`; a sweep writes a list of them).
#[derive(Debug, Clone, Serialize)]
pub struct BenchReport {
    requests: usize,
    errors: usize,
    fps: f64,
    latency_ms: Latency,
    errors_by_code: BTreeMap<String, usize>,
    stage_ms: BTreeMap<String, f64>,
    localized_share: f64,
    /// Answers per map version (`LocalizeResponse.map_version`): how many came from each version of
    /// the map while it was replaced or extended during the run.
    answers_by_map_version: BTreeMap<String, usize>,
    concurrency: usize,
    rate: Option<f64>,
    duration_s: f64,
    frames: usize,
    /// Robots (--robots): LocalizeStreams at once, streams opened and camera slots missed.
    #[serde(skip_serializing_if = "Option::is_none")]
    robots: Option<RobotsReport>,
}

/// What the robots of a run did.
#[derive(Debug, Clone, Serialize)]
pub struct RobotsReport {
    robots: usize,
    rate_hz: Option<f64>,
    streams_opened: u64,
    missed_slots: u64,
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let i = ((p / 100.0) * (sorted.len() - 1) as f64).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

fn report(
    records: &[Record],
    wall: f64,
    concurrency: usize,
    rate: Option<f64>,
    frames: usize,
) -> BenchReport {
    let ok: Vec<&Record> = records.iter().filter(|r| r.code.is_none()).collect();
    let mut lat: Vec<f64> = ok.iter().map(|r| 1e3 * r.latency).collect();
    lat.sort_by(f64::total_cmp);
    let mut errors_by_code = BTreeMap::new();
    for r in records {
        if let Some(c) = &r.code {
            *errors_by_code.entry(c.clone()).or_insert(0) += 1;
        }
    }
    let mut sums: BTreeMap<String, f64> = BTreeMap::new();
    for r in &ok {
        for (s, v) in &r.stages {
            *sums.entry(s.clone()).or_insert(0.0) += v;
        }
    }
    let n = ok.len().max(1) as f64;
    BenchReport {
        requests: records.len(),
        errors: records.len() - ok.len(),
        fps: ok.len() as f64 / wall.max(1e-9),
        latency_ms: Latency {
            p50: percentile(&lat, 50.0),
            p90: percentile(&lat, 90.0),
            p99: percentile(&lat, 99.0),
            max: lat.last().copied().unwrap_or(0.0),
            mean: lat.iter().sum::<f64>() / n,
        },
        errors_by_code,
        stage_ms: sums.into_iter().map(|(k, v)| (k, 1e3 * v / n)).collect(),
        localized_share: ok.iter().filter(|r| r.localized).count() as f64 / n,
        answers_by_map_version: ok.iter().fold(BTreeMap::new(), |mut m, r| {
            *m.entry(r.map_version.clone()).or_insert(0) += 1;
            m
        }),
        concurrency,
        rate,
        duration_s: wall,
        frames,
        robots: None,
    }
}

/// A frame as a robot's compressed topics carry it: JPEG quality 90 colour, uint16 millimetre depth.
fn compressed_request(
    rgb: &pntr_core::RgbImage,
    depth: &pntr_core::DepthMap,
    k: &pntr_core::Intrinsics,
) -> Result<proto::LocalizeRequest> {
    let mut jpeg = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 90)
        .encode(
            &rgb.data,
            rgb.width,
            rgb.height,
            image::ExtendedColorType::Rgb8,
        )
        .context("encoding a frame as JPEG")?;
    Ok(proto::LocalizeRequest {
        rgb: Some(proto::Image {
            width: rgb.width,
            height: rgb.height,
            encoding: proto::ImageEncoding::Jpeg as i32,
            data: jpeg,
        }),
        depth: Some(proto::Depth {
            width: depth.width,
            height: depth.height,
            encoding: proto::DepthEncoding::Uint16Millimeters as i32,
            data: depth
                .to_millimetres()
                .into_iter()
                .flat_map(u16::to_le_bytes)
                .collect(),
        }),
        intrinsics: Some(wire::intrinsics_message(k)),
        ..Default::default()
    })
}

/// `--frames` frames of the recording `--sequence`, evenly spaced and in order.
fn sequence_frames(
    args: &BenchArgs,
    path: &std::path::Path,
) -> Result<Vec<(proto::LocalizeRequest, pntr_pipeline::pipeline::Query)>> {
    let (rec, camera) = crate::recordings::open_recording(
        path,
        None,
        &args.topics,
        args.depth_scale,
        args.intrinsics.as_deref(),
    )?;
    for w in rec.warnings() {
        eprintln!("warning: {w}");
    }
    if rec.is_empty() {
        bail!("{}: no frames", path.display());
    }
    let n = args.frames.clamp(1, rec.len());
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let at = i * rec.len() / n;
        let (rgb, depth) = match rec.load(at) {
            Ok(f) => f,
            Err(e) => {
                eprintln!("warning: frame {at} skipped: {e}");
                continue;
            }
        };
        if (camera.width, camera.height) != (rgb.width, rgb.height) {
            bail!(
                "{}: the frames are {}x{} but the camera describes {}x{}: give --intrinsics for the recorded size",
                path.display(),
                rgb.width,
                rgb.height,
                camera.width,
                camera.height
            );
        }
        if let Some(hint) = pntr_dataset::recording::depth_unit_hint(&depth, args.depth_scale) {
            bail!("{}: frame {at}: {hint}", path.display());
        }
        out.push((
            compressed_request(&rgb, &depth, &camera)?,
            pntr_pipeline::pipeline::Query {
                rgb,
                depth,
                intrinsics: camera,
            },
        ));
    }
    if out.is_empty() {
        bail!("{}: none of its frames could be read", path.display());
    }
    Ok(out)
}

fn load_frames(
    args: &BenchArgs,
) -> Result<Vec<(proto::LocalizeRequest, pntr_pipeline::pipeline::Query)>> {
    let dataset = match (&args.dataset, &args.sequence) {
        (_, Some(seq)) => return sequence_frames(args, seq),
        (Some(d), None) => d,
        (None, None) => bail!("give --dataset or --sequence"),
    };
    let index = DatasetIndex::open(dataset)?;
    let scenes: Vec<_> = match &args.scene {
        Some(s) => vec![index.scene(s)?],
        None => index.scenes.iter().collect(),
    };
    let mut all = Vec::new();
    for s in &scenes {
        for p in &s.points {
            let r = p.open()?;
            for q in 0..r.count(Role::Query) {
                all.push((p.clone(), q));
            }
        }
    }
    if all.is_empty() {
        bail!("{}: no query frames", dataset.display());
    }
    let n = args.frames.clamp(1, all.len());
    let step = all.len() as f64 / n as f64;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let (p, q) = &all[(i as f64 * step) as usize];
        let v = p.open()?.view(Role::Query, *q)?;
        out.push((
            wire::raw_request(&v.rgb, &v.depth, Some(&v.intrinsics)),
            pntr_pipeline::pipeline::Query {
                rgb: v.rgb,
                depth: v.depth,
                intrinsics: v.intrinsics,
            },
        ));
    }
    Ok(out)
}

/// Run one measurement (closed loop at `concurrency`, or open loop at `rate`) for `duration` seconds.
async fn measure(
    args: &BenchArgs,
    frames: Arc<Vec<proto::LocalizeRequest>>,
    c: LocalizerClient<Channel>,
    concurrency: usize,
    rate: Option<f64>,
    duration: f64,
    live: bool,
) -> (Vec<Record>, f64, Option<RobotsReport>) {
    let records = Arc::new(Mutex::new(Vec::new()));
    let next = Arc::new(AtomicUsize::new(0));
    let t0 = Instant::now();
    let end = t0 + Duration::from_secs_f64(duration);
    let progress = {
        let records = records.clone();
        tokio::spawn(async move {
            if !live {
                return;
            }
            let mut tick = tokio::time::interval(Duration::from_secs(1));
            tick.tick().await;
            loop {
                tick.tick().await;
                let (n, e) = {
                    let r = records.lock().expect("records");
                    (
                        r.len(),
                        r.iter().filter(|x: &&Record| x.code.is_some()).count(),
                    )
                };
                eprint!(
                    "\r{:>5.0} s  {n} requests  {:.1}/s  {e} errors   ",
                    t0.elapsed().as_secs_f64(),
                    n as f64 / t0.elapsed().as_secs_f64()
                );
            }
        })
    };
    let mut tasks = Vec::new();
    let tally = Arc::new(RobotTally::default());
    match (rate, args.robots) {
        (_, Some(robots)) => {
            let sink: Arc<dyn Fn(Record) + Send + Sync> = {
                let records = records.clone();
                Arc::new(move |r| records.lock().expect("records").push(r))
            };
            let load = Robots {
                robots,
                rate_hz: args.rate_hz,
                churn_frames: args.churn_frames.unwrap_or(0),
            };
            tasks.push(tokio::spawn(crate::load::drive(
                c.clone(),
                args.connect.clone(),
                frames.clone(),
                load,
                end,
                sink,
                tally.clone(),
            )));
        }
        (None, None) => {
            for _ in 0..concurrency.max(1) {
                let (c, frames, next, records, connect) = (
                    c.clone(),
                    frames.clone(),
                    next.clone(),
                    records.clone(),
                    args.connect.clone(),
                );
                tasks.push(tokio::spawn(async move {
                    while Instant::now() < end {
                        let i = next.fetch_add(1, Ordering::Relaxed) % frames.len();
                        let rec = one(c.clone(), &connect, frames[i].clone(), Instant::now()).await;
                        records.lock().expect("records").push(rec);
                    }
                }));
            }
        }
        (Some(r), None) => {
            let period = Duration::from_secs_f64(1.0 / r.max(1e-3));
            let limit = Arc::new(tokio::sync::Semaphore::new(64 * concurrency.max(1)));
            let mut k: u32 = 0;
            loop {
                let at = t0 + period * k;
                if at >= end {
                    break;
                }
                tokio::time::sleep_until(at.into()).await;
                let permit = limit.clone().acquire_owned().await.expect("semaphore");
                let (c, frames, records, connect) = (
                    c.clone(),
                    frames.clone(),
                    records.clone(),
                    args.connect.clone(),
                );
                let i = k as usize % frames.len();
                tasks.push(tokio::spawn(async move {
                    // Latency from the scheduled time, not from when a slot freed up.
                    let rec = one(c, &connect, frames[i].clone(), at).await;
                    records.lock().expect("records").push(rec);
                    drop(permit);
                }));
                k += 1;
            }
        }
    }
    for t in tasks {
        let _ = t.await;
    }
    let wall = t0.elapsed().as_secs_f64();
    progress.abort();
    if live {
        eprintln!();
    }
    let records = std::mem::take(&mut *records.lock().expect("records"));
    let robots = args.robots.map(|robots| RobotsReport {
        robots,
        rate_hz: args.rate_hz,
        streams_opened: tally.streams_opened.load(Ordering::Relaxed),
        missed_slots: tally.missed_slots.load(Ordering::Relaxed),
    });
    (records, wall, robots)
}

fn print_row(r: &BenchReport) {
    let load = match (&r.robots, r.rate) {
        (Some(robots), _) => format!("robots={}", robots.robots),
        (None, Some(x)) => format!("{x}/s"),
        (None, None) => format!("c={}", r.concurrency),
    };
    println!(
        "{:>11} {:>8} {:>8.2} {:>9.1} {:>9.1} {:>9.1} {:>9.1} {:>7} {:>9.3}",
        load,
        r.requests,
        r.fps,
        r.latency_ms.p50,
        r.latency_ms.p90,
        r.latency_ms.p99,
        r.latency_ms.max,
        r.errors,
        r.localized_share
    );
}

/// `pntr bench`.
pub fn run(args: &BenchArgs) -> Result<()> {
    if !(args.duration.is_finite() && args.duration > 0.0 && args.warmup >= 0.0) {
        bail!("--duration must be positive and --warmup not negative");
    }
    if let Some(dir) = &args.plot {
        // Fail before the measurement, not after it.
        std::fs::create_dir_all(dir).with_context(|| format!("--plot {}", dir.display()))?;
    }
    if let Some(r) = args.rate {
        if !(r > 0.0 && r.is_finite()) {
            bail!("--rate must be a positive number of requests per second");
        }
    }
    if args.robots == Some(0) {
        bail!("--robots must be at least 1");
    }
    if let Some(r) = args.rate_hz {
        if !(r > 0.0 && r.is_finite()) {
            bail!("--rate-hz must be a positive number of frames per second");
        }
    }
    if args.robots.is_some() && args.sweep.is_some() {
        bail!(
            "--sweep varies --concurrency of single calls; with --robots give one number of robots"
        );
    }
    let loaded = load_frames(args)?;
    let frames = Arc::new(loaded.iter().map(|(r, _)| r.clone()).collect::<Vec<_>>());
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let c = client(rt.block_on(channel(&args.connect))?);
    if args.soak.soak {
        let load = crate::soak::SoakLoad {
            connect: &args.connect,
            frames,
            concurrency: args.concurrency,
            robots: Robots {
                robots: args.robots.unwrap_or(4),
                rate_hz: args.rate_hz,
                churn_frames: args.churn_frames.unwrap_or(10),
            },
            warmup_s: args.warmup,
            duration_s: args.duration,
            plot: args.plot.clone(),
            json: args.json.clone(),
        };
        return crate::soak::run(&args.soak, load, &rt, c);
    }
    let levels = args.sweep.clone().unwrap_or_else(|| vec![args.concurrency]);
    let mut reports = Vec::new();
    println!(
        "{:>11} {:>8} {:>8} {:>9} {:>9} {:>9} {:>9} {:>7} {:>9}",
        "load", "requests", "fps", "p50 ms", "p90 ms", "p99 ms", "max ms", "errors", "localized"
    );
    for &level in &levels {
        if args.warmup > 0.0 {
            rt.block_on(measure(
                args,
                frames.clone(),
                c.clone(),
                level,
                args.rate,
                args.warmup,
                false,
            ));
        }
        let (records, wall, robots) = rt.block_on(measure(
            args,
            frames.clone(),
            c.clone(),
            level,
            args.rate,
            args.duration,
            true,
        ));
        let mut r = report(&records, wall, level, args.rate, frames.len());
        r.robots = robots;
        print_row(&r);
        for (code, n) in &r.errors_by_code {
            eprintln!("{n} requests failed with {code}");
        }
        reports.push(r);
    }
    if reports.len() > 1 {
        let top = reports.iter().map(|r| r.fps).fold(0.0, f64::max).max(1e-9);
        println!("\nframes per second against concurrency");
        for r in &reports {
            let bar = "#".repeat((50.0 * r.fps / top).round() as usize);
            println!("c={:<4} {bar} {:.2}", r.concurrency, r.fps);
        }
    }
    let stages: Vec<String> = reports
        .last()
        .map(|r| {
            r.stage_ms
                .iter()
                .map(|(k, v)| format!("{k} {v:.1}"))
                .collect()
        })
        .unwrap_or_default();
    println!("server-reported mean ms (last run): {}", stages.join(", "));
    let overhead = match &args.compare_in_process {
        Some(map) => Some(compare(args, map, &loaded, &rt, &c)?),
        None => None,
    };
    if let Some(o) = &overhead {
        println!(
            "service overhead over {} frames: through the server {:.1} ms mean ({:.1} p50), in process {:.1} ms mean ({:.1} p50): ratio {:.3}",
            o.pairs, o.remote_ms_mean, o.remote_ms_p50, o.in_process_ms_mean, o.in_process_ms_p50, o.ratio
        );
    }
    if let Some(dir) = &args.plot {
        let points: Vec<crate::plot::SweepPoint> = reports
            .iter()
            .map(|r| crate::plot::SweepPoint {
                concurrency: r.concurrency,
                fps: r.fps,
                p50_ms: r.latency_ms.p50,
                p90_ms: r.latency_ms.p90,
                p99_ms: r.latency_ms.p99,
                errors: r.errors,
            })
            .collect();
        let title = format!(
            "pntr bench against {} ({} frames, {:.0} s per level)",
            args.connect.addr, args.frames, args.duration
        );
        let files = crate::plot::bench_plot(&points, dir, &title)?;
        eprintln!("{} pictures written to {}", files.len(), dir.display());
    }
    if let Some(path) = &args.json {
        let mut v = if reports.len() == 1 {
            serde_json::to_value(&reports[0])?
        } else {
            serde_json::json!({ "sweep": reports })
        };
        if let Some(o) = &overhead {
            v["overhead"] = serde_json::to_value(o)?;
        }
        crate::output::write_json(path, &v)?;
        eprintln!("report written to {}", path.display());
    }
    Ok(())
}

/// Time every frame through the server and through an in-process pipeline on the same map, alternately.
fn compare(
    args: &BenchArgs,
    map: &std::path::Path,
    frames: &[(proto::LocalizeRequest, pntr_pipeline::pipeline::Query)],
    rt: &tokio::runtime::Runtime,
    c: &LocalizerClient<Channel>,
) -> Result<Overhead> {
    use anyhow::Context;
    let models = crate::loading::models_dir(args.models.as_deref())?;
    let m = crate::loading::load_map(map, args.threads)?;
    let preset = m.header.preset.clone();
    let stage = pntr_features::config::FeatureConfig {
        runtime: pntr_features::runtime::RuntimeOptions {
            threads: args.threads,
            ..Default::default()
        },
        ..preset.feature_config(models.clone())
    }
    .build()
    .with_context(|| format!("loading the models from {}", models.display()))?;
    let pipeline = pntr_pipeline::pipeline::Pipeline::new(Arc::new(m), stage, preset)?;
    // One untimed pass of each warms both paths.
    let (req0, q0) = &frames[0];
    pipeline.localize(q0)?;
    rt.block_on(one(c.clone(), &args.connect, req0.clone(), Instant::now()));
    let (mut remote, mut local) = (Vec::new(), Vec::new());
    for (req, q) in frames {
        let r = rt.block_on(one(c.clone(), &args.connect, req.clone(), Instant::now()));
        if let Some(code) = r.code {
            bail!("the server answered {code} during the overhead measurement");
        }
        remote.push(1e3 * r.latency);
        let t = Instant::now();
        pipeline.localize(q)?;
        local.push(1e3 * t.elapsed().as_secs_f64());
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let p50 = |v: &[f64]| {
        let mut s = v.to_vec();
        s.sort_by(f64::total_cmp);
        percentile(&s, 50.0)
    };
    Ok(Overhead {
        pairs: frames.len(),
        remote_ms_mean: mean(&remote),
        in_process_ms_mean: mean(&local),
        remote_ms_p50: p50(&remote),
        in_process_ms_p50: p50(&local),
        ratio: mean(&remote) / mean(&local).max(1e-9),
    })
}
