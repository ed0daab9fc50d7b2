//! Evaluation runs shared by `pntr eval` and `pntr synth --eval`: a map's pipeline over a dataset's
//! queries in this process or through a server (started here, or running), with the answers
//! optionally recorded for Foxglove or ROS tools.

use std::path::Path;

use crate::loading::load_map;
use crate::output::bar;
use anyhow::{Context, Result};
use pntr_dataset::SceneEntry;
use pntr_eval::{self as eval, Answer, EvalOptions, EvalReport};
use pntr_pipeline::map::Map;
use pntr_pipeline::mapfile;
use pntr_pipeline::pipeline::Pipeline;
use pntr_pipeline::prior::LocalizeOptions;

/// `--stability` counts by `perturbation/in_map` or `perturbation/out_of_map`.
pub type Stability = std::collections::BTreeMap<String, eval::StabilityCounts>;

/// Start a recording (`--record`) at `out` (a Foxglove MCAP file, or a ROS 2 bag folder when `out`
/// does not end in `.mcap`); with `db`, the map's cameras go in first, stamped
/// `time_s`.
pub fn start_recording(
    out: &Path,
    db: Option<&Path>,
    time_s: f64,
) -> Result<pntr_service::ros_bag::Recorder> {
    let rec = pntr_service::ros_bag::Recorder::create(out)
        .map_err(|e| anyhow::anyhow!("--record {e}"))?;
    if let Some(path) = db {
        let map = load_map(path, 1).with_context(|| format!("--db {}", path.display()))?;
        show_map_cameras(&rec, &map, time_s);
    }
    Ok(rec)
}

/// Write a map's image poses into a recording, in ROS conventions.
fn show_map_cameras(rec: &pntr_service::ros_bag::Recorder, map: &Map, time_s: f64) {
    let frames = pntr_service::wire::MapFrames::of(&map.header);
    rec.map_cameras(
        time_s,
        map.images
            .iter()
            .map(|im| frames.pose_to_ros(&im.world_from_camera)),
    );
}

/// Show one evaluated query in a recording: its image and camera, the answer and the ground truth,
/// in ROS conventions (the dataset's frame is y-up with Habitat camera axes). Queries are stamped
/// 0.1 s apart from the Unix epoch (datasets carry no time).
fn record_query(
    rec: &pntr_service::ros_bag::Recorder,
    n: &mut usize,
    q: &pntr_pipeline::pipeline::Query,
    truth: Option<&nalgebra::Isometry3<f64>>,
    a: &Answer,
) -> Result<()> {
    // Evaluation answers are in the dataset's frames: y up, Habitat axes.
    let frames = pntr_service::wire::MapFrames::default();
    let to_ros = |p: &nalgebra::Isometry3<f64>| frames.pose_to_ros(p);
    let covariance = a
        .covariance
        .map(|c| frames.covariance_to_ros(&c))
        .unwrap_or_default();
    let id = format!("query-{n}");
    let status = match a.status {
        Some(pntr_pipeline::pipeline::Status::Localized) => "LOCALIZED",
        Some(_) => "NOT_LOCALIZED",
        None => "ERROR",
    };
    rec.observe(&pntr_service::visual::Observation {
        time_s: *n as f64 * 0.1,
        picture: Some((pntr_service::visual::Picture::Raw(&q.rgb), &q.intrinsics)),
        request_id: &id,
        map_id: "",
        map_version: "",
        status,
        reason: a.reason.as_deref().unwrap_or(""),
        confidence: a.confidence,
        inliers: 0,
        mode: a.mode.map_or("UNKNOWN", |m| m.name()),
        track_state: "",
        matched_image_id: a.matched.as_deref().unwrap_or(""),
        pose: a.pose.as_ref().map(to_ros),
        covariance: &covariance,
        truth: truth.map(to_ros),
    })
    .map_err(|e| anyhow::anyhow!("--record: {e}"))?;
    *n += 1;
    Ok(())
}

/// Close a recording under its name and say where it is.
pub fn finish_recording(record: Option<pntr_service::ros_bag::Recorder>) -> Result<()> {
    if let Some(rec) = record {
        let path = rec.finish().map_err(|e| anyhow::anyhow!("--record {e}"))?;
        eprintln!("recording written to {}", path.display());
    }
    Ok(())
}

/// Run the in-process pipeline over the queries of `scenes`.
pub fn evaluate_in_process(
    pipeline: &Pipeline,
    scenes: &[&SceneEntry],
    opts: &EvalOptions,
    effects: Option<pntr_synth::effects::RobotEffects>,
    record: Option<&pntr_service::ros_bag::Recorder>,
    stability: bool,
    variant: Option<&Pipeline>,
) -> Result<(EvalReport, Stability)> {
    use pntr_synth::effects::Perturbation;
    let map = pipeline.map.clone();
    // With --stability, the answers to each query's perturbed copies (made in the localizer, which
    // sees the frame as localized), counted in the observer (which knows the truth).
    let pending: std::cell::RefCell<Vec<(String, Answer)>> = Default::default();
    let mut counts = Stability::new();
    let total: usize = scenes.iter().map(|s| s.points.len()).sum();
    let pb = bar(total, "localizing queries");
    let mut seed = 0u64;
    if let Some(rec) = record {
        show_map_cameras(rec, &map, 0.0);
    }
    let mut n = 0usize;
    // The first error writing --record: recording stops there and the run fails after it.
    let mut failed: Option<anyhow::Error> = None;
    let report = eval::run_observed(
        scenes,
        opts,
        &mut |q, prior| {
            seed += 1;
            let opts = prior
                .copied()
                .map(LocalizeOptions::prior)
                .unwrap_or_default();
            let mut q = q.clone();
            if let Some(fx) = &effects {
                fx.apply(&mut q.rgb, &mut q.depth, seed);
            }
            if stability {
                for kind in Perturbation::ALL {
                    let mut p = q.clone();
                    kind.apply(&mut p.rgb, &mut p.depth);
                    let a = pipeline
                        .localize_with(&p, &opts)
                        .map(|l| Answer::of(&l, &map));
                    pending
                        .borrow_mut()
                        .push((kind.name().to_string(), a.unwrap_or_default()));
                }
                // The same frame through another preset of the same descriptors (bf16 against
                // float, say).
                if let Some(v) = variant {
                    let a = v.localize_with(&q, &opts).map(|l| Answer::of(&l, &map));
                    pending
                        .borrow_mut()
                        .push((format!("preset:{}", v.preset.name), a.unwrap_or_default()));
                }
            }
            Ok(Answer::of(&pipeline.localize_with(&q, &opts)?, &map))
        },
        &mut |done, total| {
            pb.set_length(total as u64);
            pb.set_position(done as u64);
        },
        &mut |q, truth, a| {
            if let (Some(rec), None) = (record, &failed) {
                failed = record_query(rec, &mut n, q, truth, a).err();
            }
            for (kind, perturbed) in pending.borrow_mut().drain(..) {
                let side = if truth.is_some() {
                    "in_map"
                } else {
                    "out_of_map"
                };
                counts
                    .entry(format!("{kind}/{side}"))
                    .or_default()
                    .add(a, &perturbed, truth);
            }
        },
    )?;
    pb.finish_and_clear();
    if let Some(e) = failed {
        return Err(e);
    }
    Ok((report, counts))
}

/// The stability lines of the eval table.
pub fn stability_table(s: &Stability) -> String {
    let mut out = String::from(
        "stability (answers to perturbed copies of each query: changed status, pose moved > 0.25 m / 2 deg, became LOCALIZED and wrong, confident (> 0.9) and > 5 m / 20 deg off):\n",
    );
    for (k, c) in s {
        out += &format!(
            "  {k:<22} {:>5} queries: status changed {}, pose moved {}, became wrong {}, confident wrong {} (became so {})\n",
            c.queries, c.status_changed, c.pose_moved, c.became_wrong, c.confident_wrong, c.became_confident_wrong
        );
    }
    out
}

/// Localise queries of `scenes` through `remote`.
pub fn evaluate_remote(
    remote: &mut crate::remote::Remote,
    scenes: &[&SceneEntry],
    opts: &EvalOptions,
    record: Option<&pntr_service::ros_bag::Recorder>,
) -> Result<EvalReport> {
    let total: usize = scenes.iter().map(|s| s.points.len()).sum();
    let pb = bar(total, "localizing queries through the server");
    let mut n = 0usize;
    // The first error writing --record: recording stops there and the run fails after it.
    let mut failed: Option<anyhow::Error> = None;
    let report = eval::run_observed(
        scenes,
        opts,
        &mut |q, prior| remote.answer(q, prior),
        &mut |done, total| {
            pb.set_length(total as u64);
            pb.set_position(done as u64);
        },
        &mut |q, truth, a| {
            if let (Some(rec), None) = (record, &failed) {
                failed = record_query(rec, &mut n, q, truth, a).err();
            }
        },
    )?;
    pb.finish_and_clear();
    if let Some(e) = failed {
        return Err(e);
    }
    Ok(report)
}

/// Start a pntr-server on 127.0.0.1 (ephemeral port) serving `map`, localise up to `queries` queries of
/// `scenes` through it, print the recall table and stage timings, and shut it down gracefully.
pub fn serve_and_evaluate(
    map: &Path,
    models: &Path,
    scenes: &[&SceneEntry],
    queries: usize,
) -> Result<()> {
    use pntr_service::tokio;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let settings =
        pntr_service::config::Settings::local(vec![map.to_path_buf()], models.to_path_buf());
    let mut running = rt.block_on(async {
        let r = pntr_service::start(settings).await?;
        r.ready().await?;
        Ok::<_, pntr_service::ServerError>(r)
    })?;
    println!(
        "pntr-server serving {} on {} (Prometheus metrics on http://{}/metrics)",
        map.display(),
        running.addr,
        running.metrics_addr
    );
    let mut remote = crate::remote::Remote::connect(&crate::remote::ConnectArgs {
        addr: running.addr.to_string(),
        ..Default::default()
    })?;
    let header = mapfile::read_header(map)?;
    let opts = EvalOptions {
        max_queries: queries,
        preset: header.preset.name.clone(),
        ..EvalOptions::default()
    };
    let report = evaluate_remote(&mut remote, scenes, &opts, None);
    drop(remote);
    running.shutdown();
    rt.block_on(running.wait())?;
    let report = report?;
    println!(
        "preset {}: {} + {} + {} + {:?}, {} retrieval candidates re-ranked by geometry",
        header.preset.name,
        header.preset.global,
        header.preset.extractor,
        header.preset.matcher,
        header.preset.solver,
        header.preset.candidates
    );
    print!("{}", eval::table(&report));
    println!("(stage times as the server reports them; queries/s measured at the client, one request at a time)");
    Ok(())
}
