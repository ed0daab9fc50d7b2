//! `pntr synth`, `pntr info` and `pntr demo`.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use pntr_core::Intrinsics;
use pntr_dataset::{DatasetIndex, Role, WriteOptions};
use pntr_synth::{Summary, SynthConfig};

use serde_json::json;

/// Arguments of `pntr synth`.
#[derive(Args, Debug)]
pub struct SynthArgs {
    /// Output root; scenes go to OUT/HPointLoc_dataset/<scene>/ (an existing scene of the same name
    /// is replaced once the new one is complete).
    #[arg(long)]
    pub out: PathBuf,
    /// Number of scenes.
    #[arg(long, default_value_t = 1)]
    pub scenes: usize,
    /// Points (key positions on the 2 m grid) per scene.
    #[arg(long, default_value_t = 23)]
    pub points_per_scene: usize,
    /// Query poses drawn per Point; those not in free space are discarded, as in the protocol.
    #[arg(long, default_value_t = 50)]
    pub queries_per_point: usize,
    /// Seed: the same seed gives the same dataset.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Standard deviation of query pitch and roll, degrees.
    #[arg(long, default_value_t = 2.0)]
    pub tilt_sigma_deg: f64,
    /// Folder of PNG/JPEG images to use as extra wall textures.
    #[arg(long)]
    pub textures: Option<PathBuf>,
    /// gzip level of the image fields (0 = uncompressed).
    #[arg(long, default_value_t = 1)]
    pub gzip_level: u8,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
    /// Database camera size `WxH` (default 256x256, HPointLoc's). Stored in the extra field
    /// `camera_base` when it is not HPointLoc's camera.
    #[arg(long, value_name = "WxH")]
    pub camera: Option<String>,
    /// Query camera size `WxH` (default: the database camera), stored in the extra field `camera`:
    /// renders a robot's camera against a map made with another.
    #[arg(long, value_name = "WxH")]
    pub query_camera: Option<String>,
    /// Horizontal field of view in degrees of the cameras named by `--camera` and `--query-camera`
    /// (default 90, HPointLoc's). With only `--query-camera` it sets the queries' field of view and
    /// the database keeps HPointLoc's camera.
    #[arg(long, value_name = "DEG", allow_negative_numbers = true)]
    pub hfov: Option<f64>,
    /// Horizontal field of view of the query camera in degrees, when it differs from `--hfov`.
    #[arg(long, value_name = "DEG", allow_negative_numbers = true)]
    pub query_hfov: Option<f64>,
    /// Lens distortion of the query camera, `k1,k2,p1,p2,k3` (OpenCV / ROS plumb_bob).
    #[arg(long, value_name = "K1,K2,P1,P2,K3", allow_hyphen_values = true)]
    pub query_distortion: Option<String>,
    /// Also render, per scene, a robot driving for this many seconds (0.5 m/s, 10 Hz, through the
    /// query camera, from Point to Point through the doors) into `OUT/sequences/<scene>/` in the TUM
    /// RGB-D layout: rgb/, depth/ (16-bit PNG, 5000 per metre), rgb.txt, depth.txt, groundtruth.txt
    /// (world_from_camera in the scene's y-up frame with the TUM convention's optical camera axes: x
    /// right, y down, z forward), calibration.txt.
    #[arg(long, value_name = "SECONDS")]
    pub trajectory_seconds: Option<f64>,
    /// Make the drive a mapping run, as an operator mapping a building drives: every Point the robot
    /// can reach visited once, a full circle in place at each, stopping after the last (`--trajectory-seconds` is then
    /// a cap).
    #[arg(long, requires = "trajectory_seconds")]
    pub mapping_run: bool,
    /// Drive another route through the same scene: another first Point and order of Points, so
    /// parts are driven the other way (with `--trajectory-seconds`).
    #[arg(long, value_name = "K", requires = "trajectory_seconds")]
    pub route_seed: Option<u64>,
    /// Render queries and drives as a robot's captures, database views clean: `none`, `robot`
    /// (everything), or a comma-separated list of `lighting` (each room's lamps at another level,
    /// ambient and light strengths and directions per query, drifting over 3 s in a drive), `exposure` (gain, gamma, white
    /// balance), `blur`, `noise`, `jpeg`, `depth` (noise growing with the square of the range,
    /// dropouts, lost edges). Deterministic per seed.
    #[arg(long, default_value = "none", value_name = "robot|none|GROUP,...")]
    pub realism: String,
    /// Put each apartment beside an exact copy of itself, joined by one door through the wall they
    /// share: every room has a look-alike one apartment-width away (`twin_offset_m` in the JSON).
    /// Database views, queries and `--mapping-run` cover the original half only; other drives go
    /// to both halves. A map of the original and a drive into the copy test what a stream answers
    /// in rooms that look exactly like mapped ones.
    #[arg(long)]
    pub twin: bool,
}

/// Parse a camera size `WxH` (`--camera`, `--query-camera`).
fn parse_size(flag: &str, s: &str) -> Result<(u32, u32)> {
    let parsed = s
        .split_once(['x', 'X'])
        .and_then(|(w, h)| Some((w.trim().parse::<u32>().ok()?, h.trim().parse::<u32>().ok()?)));
    match parsed {
        Some((w, h)) if (8..=4096).contains(&w) && (8..=4096).contains(&h) => Ok((w, h)),
        _ => bail!("--{flag} {s:?}: expected WIDTHxHEIGHT in pixels, each 8..4096 (e.g. 640x480)"),
    }
}

/// The database and query cameras `synth` renders with.
fn cameras(args: &SynthArgs) -> Result<(Intrinsics, Intrinsics)> {
    let fov = |flag: &str, v: f64| -> Result<f64> {
        if !(v.is_finite() && (10.0..=170.0).contains(&v)) {
            bail!("--{flag} {v}: the horizontal field of view must be within 10..170 degrees");
        }
        Ok(v)
    };
    let hfov = args.hfov.map(|v| fov("hfov", v)).transpose()?;
    // `--hfov` applies to the cameras named; with none named, to both.
    let db = if args.camera.is_some() || args.query_camera.is_none() {
        let (w, h) = match &args.camera {
            Some(s) => parse_size("camera", s)?,
            None => (256, 256),
        };
        Intrinsics::from_fov(w, h, hfov.unwrap_or(90.0))
    } else {
        Intrinsics::hpointloc()
    };
    let query_hfov = match args.query_hfov {
        Some(v) => Some(fov("query-hfov", v)?),
        None if args.query_camera.is_some() => hfov,
        None => None,
    };
    let mut query = match (&args.query_camera, query_hfov) {
        (Some(s), v) => {
            let (w, h) = parse_size("query-camera", s)?;
            Intrinsics::from_fov(w, h, v.unwrap_or(90.0))
        }
        (None, Some(v)) => Intrinsics::from_fov(db.width, db.height, v),
        (None, None) => db,
    };
    if let Some(d) = &args.query_distortion {
        let v: Vec<f64> = d
            .split(',')
            .map(|x| x.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|e| anyhow::anyhow!("--query-distortion {d:?}: {e}"))?;
        if v.len() != 5 {
            bail!("--query-distortion {d:?}: give 5 numbers k1,k2,p1,p2,k3");
        }
        query.distortion.copy_from_slice(&v);
        query
            .validate()
            .map_err(|e| anyhow::anyhow!("--query-distortion: {e}"))?;
    }
    Ok((db, query))
}

fn config(args: &SynthArgs) -> Result<SynthConfig> {
    if args.scenes == 0 || args.points_per_scene == 0 {
        bail!("--scenes and --points-per-scene must be at least 1");
    }
    if !(args.tilt_sigma_deg.is_finite() && (0.0..=30.0).contains(&args.tilt_sigma_deg)) {
        bail!("--tilt-sigma-deg must be within 0..30");
    }
    if args.gzip_level > 9 {
        bail!("--gzip-level must be within 0..9");
    }
    if let Some(t) = args.trajectory_seconds {
        if !(t.is_finite() && t > 0.0 && t <= 3600.0) {
            bail!("--trajectory-seconds must be within (0, 3600], not {t}");
        }
    }
    let textures = match &args.textures {
        Some(dir) => pntr_synth::load_textures(dir)?,
        None => Vec::new(),
    };
    let (db_camera, query_camera) = cameras(args)?;
    Ok(SynthConfig {
        db_camera,
        query_camera,
        scenes: args.scenes,
        points_per_scene: args.points_per_scene,
        queries_per_point: args.queries_per_point,
        seed: args.seed,
        trajectory_seconds: args.trajectory_seconds,
        mapping_run: args.mapping_run,
        route_seed: args.route_seed,
        twin: args.twin,
        realism: pntr_synth::effects::Realism::parse(&args.realism)
            .map_err(|e| anyhow::anyhow!("--realism: {e}"))?,
        tilt_sigma_deg: args.tilt_sigma_deg,
        textures,
        write: WriteOptions {
            gzip_level: (args.gzip_level > 0).then_some(args.gzip_level),
        },
    })
}

fn generate(cfg: &SynthConfig, out: &Path) -> Result<Summary> {
    let planned = pntr_synth::plan_all(cfg);
    let total = pntr_synth::planned_frames(&planned) + pntr_synth::planned_sequence_frames(cfg);
    let bar = ProgressBar::new(total);
    bar.set_style(
        ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} frames ({per_sec}, eta {eta})")
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar.set_message("rendering");
    let summary = pntr_synth::synthesize(cfg, out, planned, &|| bar.inc(1))
        .with_context(|| format!("writing {}", out.display()))?;
    bar.finish_and_clear();
    Ok(summary)
}

fn summary_json(s: &Summary) -> serde_json::Value {
    json!({
        "root": s.root.display().to_string(),
        "frames": s.frames,
        "seconds": s.seconds,
        "frames_per_second": s.frames as f64 / s.seconds.max(1e-9),
        "scenes": s.scenes.iter().map(|sc| json!({
            "name": sc.name,
            "points": sc.points,
            "db_views": sc.db_views,
            "queries": sc.queries,
            "discarded_queries": sc.discarded_queries,
            "rooms": sc.rooms,
            "boxes": sc.boxes,
            "size_m": [sc.size_m.0, sc.size_m.1],
            "sequence_frames": sc.sequence_frames,
            "mapping_run_seconds": sc.mapping_run_seconds,
            "twin_offset_m": sc.twin_offset_m,
            "unreachable_points": sc.unreachable_points.len(),
            "unreachable_point_ids": point_ids(&sc.unreachable_points),
        })).collect::<Vec<_>>(),
        "warnings": warnings(s),
    })
}

/// Points by the names the dataset's query ids use (`point7` of `synth000/point7/q3`).
fn point_ids(points: &[usize]) -> Vec<String> {
    points.iter().map(|i| format!("point{i}")).collect()
}

/// What the user should know about the run: a mapping run that `--trajectory-seconds` cut before it
/// visited every Point (a map built from it leaves part of the apartment out), and a drive that
/// cannot reach every Point (rooms the furniture closes off).
fn warnings(s: &Summary) -> Vec<String> {
    let closed_off = s
        .scenes
        .iter()
        .filter(|sc| sc.sequence_frames > 0 && !sc.unreachable_points.is_empty())
        .map(|sc| {
            format!(
                "{}: {} of its {} Points ({}) lie in rooms the furniture closes off to the robot: the drive in sequences/{} never reaches them{}",
                sc.name,
                sc.unreachable_points.len(),
                sc.points,
                point_ids(&sc.unreachable_points).join(", "),
                sc.name,
                if sc.mapping_run_seconds.is_some() {
                    ", and a map built from this mapping run leaves them out"
                } else {
                    ""
                }
            )
        });
    let cut = s.scenes
        .iter()
        .filter_map(|sc| {
            let whole = sc.mapping_run_seconds?;
            let drawn = sc.sequence_frames as f64 / pntr_synth::trajectory::DEFAULT_RATE_HZ;
            (whole > drawn + 1e-6).then(|| {
                format!(
                    "{}: the mapping run needs {whole:.1} s to visit every Point it can reach, and --trajectory-seconds cut it at {drawn:.1} s: a map built from it leaves part of the apartment out (give --trajectory-seconds {} for the whole run)",
                    sc.name,
                    whole.ceil()
                )
            })
        })
        .collect::<Vec<_>>();
    cut.into_iter().chain(closed_off).collect()
}

fn print_summary(s: &Summary) {
    println!(
        "{:<12} {:>6} {:>8} {:>8} {:>10} {:>6} {:>6} {:>12}",
        "scene", "points", "db_views", "queries", "discarded", "rooms", "boxes", "size_m"
    );
    for sc in &s.scenes {
        println!(
            "{:<12} {:>6} {:>8} {:>8} {:>10} {:>6} {:>6} {:>5.1}x{:<5.1}",
            sc.name,
            sc.points,
            sc.db_views,
            sc.queries,
            sc.discarded_queries,
            sc.rooms,
            sc.boxes,
            sc.size_m.0,
            sc.size_m.1
        );
    }
    for sc in s.scenes.iter().filter(|sc| sc.sequence_frames > 0) {
        println!(
            "{}: a drive of {} frames in {}",
            sc.name,
            sc.sequence_frames,
            s.root
                .join(pntr_synth::SEQUENCES_DIR)
                .join(&sc.name)
                .display()
        );
    }
    println!(
        "{} frames in {:.2} s ({:.1} frames/s) -> {}",
        s.frames,
        s.seconds,
        s.frames as f64 / s.seconds.max(1e-9),
        s.root.display()
    );
}

/// `pntr synth`.
pub fn run(args: &SynthArgs) -> Result<()> {
    let cfg = config(args)?;
    let summary = generate(&cfg, &args.out)?;
    for w in warnings(&summary) {
        eprintln!("warning: {w}");
    }
    if args.json {
        println!("{}", serde_json::to_string_pretty(&summary_json(&summary))?);
    } else {
        print_summary(&summary);
    }
    Ok(())
}

/// `pntr info`: list a dataset and open every file (validating all fields).
pub fn info(dataset: &Path, as_json: bool) -> Result<()> {
    let index = DatasetIndex::open(dataset)?;
    let camera = |k: &Intrinsics| json!({"fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy, "distortion": k.distortion});
    let mut scenes = Vec::new();
    let mut rows = Vec::new();
    for scene in &index.scenes {
        let (mut db, mut q) = (0usize, 0usize);
        let mut cams = None;
        for p in &scene.points {
            let r = p.open()?;
            db += r.count(Role::Database);
            q += r.count(Role::Query);
            cams = Some((r.camera(Role::Database), r.camera(Role::Query)));
        }
        let (kd, kq) = cams.unwrap_or((Intrinsics::hpointloc(), Intrinsics::hpointloc()));
        scenes.push(json!({
            "name": scene.name, "points": scene.points.len(), "db_views": db, "queries": q,
            "width": kd.width, "height": kd.height,
            "query_width": kq.width, "query_height": kq.height,
            "camera": camera(&kd), "query_camera": camera(&kq),
        }));
        rows.push((scene.name.clone(), scene.points.len(), db, q, kd, kq));
    }
    if as_json {
        println!(
            "{}",
            serde_json::to_string_pretty(&json!({ "scenes": scenes }))?
        );
    } else {
        println!(
            "{:<16} {:>6} {:>8} {:>8} {:>14} {:>14}",
            "scene", "points", "db_views", "queries", "db camera", "query camera"
        );
        // Size, focal length in pixels, and "+lens" when the camera has distortion.
        let cam = |k: &Intrinsics| {
            let lens = if k.is_distorted() { "+lens" } else { "" };
            format!("{}x{} f={:.0}{lens}", k.width, k.height, k.fx)
        };
        for (n, p, d, q, kd, kq) in rows {
            println!(
                "{n:<16} {p:>6} {d:>8} {q:>8} {:>14} {:>14}",
                cam(&kd),
                cam(&kq)
            );
        }
    }
    Ok(())
}

/// `pntr demo`: the embedded default job. The demo scene and its map are made once and cached in `out`
/// (as `pntr-server` with no `--db` does); a `pntr-server` is started in this process on 127.0.0.1 with an
/// ephemeral port, and `queries` evenly spaced queries are localised through it over gRPC.
pub fn demo(out: &Path, models: &Path, queries: usize) -> Result<()> {
    let t0 = std::time::Instant::now();
    let map =
        pntr_service::demo::ensure_demo_map(out, models, &mut |m| eprintln!("pntr demo: {m}"))
            .map_err(anyhow::Error::msg)?;
    let index = DatasetIndex::open(out)?;
    let scene = index.scene(&pntr_synth::scene_name(0))?;
    let (mut db, mut q) = (0, 0);
    for p in &scene.points {
        let r = p.open()?;
        db += r.count(Role::Database);
        q += r.count(Role::Query);
    }
    println!(
        "demo scene {}: {} Points, {db} database views, {q} queries; map {} ({:.1} s to prepare)",
        scene.name,
        scene.points.len(),
        map.display(),
        t0.elapsed().as_secs_f64()
    );
    crate::evaluation::serve_and_evaluate(&map, models, &[scene], queries)
}
