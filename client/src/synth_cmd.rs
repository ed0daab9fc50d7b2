//! `pntr synth`, `pntr info` and `pntr demo`.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
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
    let textures = match &args.textures {
        Some(dir) => pntr_synth::load_textures(dir)?,
        None => Vec::new(),
    };
    Ok(SynthConfig {
        scenes: args.scenes,
        points_per_scene: args.points_per_scene,
        queries_per_point: args.queries_per_point,
        seed: args.seed,
        tilt_sigma_deg: args.tilt_sigma_deg,
        textures,
        write: WriteOptions {
            gzip_level: (args.gzip_level > 0).then_some(args.gzip_level),
        },
    })
}

fn generate(cfg: &SynthConfig, out: &Path) -> Result<Summary> {
    let planned = pntr_synth::plan_all(cfg);
    let total = pntr_synth::planned_frames(&planned);
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
        })).collect::<Vec<_>>(),
    })
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
    let mut scenes = Vec::new();
    for scene in &index.scenes {
        let (mut db, mut q) = (0usize, 0usize);
        let mut size = None;
        for p in &scene.points {
            let r = p.open()?;
            db += r.count(Role::Database);
            q += r.count(Role::Query);
            size = Some((r.width(), r.height()));
        }
        scenes.push((
            scene.name.clone(),
            scene.points.len(),
            db,
            q,
            size.unwrap_or((0, 0)),
        ));
    }
    if as_json {
        let v: Vec<_> = scenes
            .iter()
            .map(|(n, p, d, q, (w, h))| {
                json!({"name": n, "points": p, "db_views": d, "queries": q, "width": w, "height": h})
            })
            .collect();
        println!("{}", serde_json::to_string_pretty(&json!({ "scenes": v }))?);
    } else {
        println!(
            "{:<16} {:>6} {:>8} {:>8} {:>9}",
            "scene", "points", "db_views", "queries", "size"
        );
        for (n, p, d, q, (w, h)) in scenes {
            println!("{n:<16} {p:>6} {d:>8} {q:>8} {:>9}", format!("{w}x{h}"));
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
    crate::map_cmd::serve_and_evaluate(&map, models, &[scene], queries)
}
