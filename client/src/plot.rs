//! Pictures of evaluation and benchmark results (`pntr eval --plot DIR`, `pntr bench --sweep --plot DIR`),
//! drawn with plotters, each as PNG and SVG.
//!
//! - `errors_cdf`: cumulative share of all queries within a translation / rotation error (the standard
//!   visual-localization plot; queries not localized never count as within), for the pipeline and for
//!   the top retrieved database pose used as the answer (retrieval only), with the protocol's thresholds.
//! - `precision_recall`: precision and recall of LOCALIZED answers, and the out-of-map false-positive
//!   rate, as the threshold on the calibrated confidence varies; the threshold in use is marked.
//! - `map_<scene>`: the scene seen from above: database camera positions and each query at its true
//!   position, coloured by how its answer turned out.
//! - `map_check` (`pntr build-db --sequence ... --plot DIR`): a map built from a recording from
//!   above, with each checked frame coloured by how its answer turned out.
//! - `bench_sweep`: frames per second and latency percentiles against the number of clients.
//!
//! Text is drawn with the DejaVu Sans font bundled by the `dejavu` crate, so the pictures look the same
//! on a machine without fonts.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Once;

use anyhow::{Context, Result};
use plotters::coord::Shift;
use plotters::prelude::*;
use pntr_pipeline::eval::{EvalReport, QueryOutcome};

/// Size of every picture, pixels.
const SIZE: (u32, u32) = (1200, 560);
/// Square size of the top-down maps, pixels.
const MAP_SIZE: (u32, u32) = (900, 900);
/// The protocol's translation thresholds, metres, marked on the error plot.
const THRESHOLDS_M: [f64; 4] = [0.25, 0.5, 1.0, 5.0];
/// ... and its rotation thresholds, degrees.
const THRESHOLDS_DEG: [f64; 4] = [2.0, 5.0, 10.0, 20.0];
const FONT: &str = "sans-serif";

fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The bundled font is known good; a failure would only leave text out.
        let _ = plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular());
    });
}

/// Draw `draw` into `dir/name.png` and `dir/name.svg` (each written to a temporary name, then
/// renamed); returns both paths.
fn save_both(
    dir: &Path,
    name: &str,
    size: (u32, u32),
    draw_png: impl FnOnce(&DrawingArea<BitMapBackend<'_>, Shift>) -> Result<()>,
    draw_svg: impl FnOnce(&DrawingArea<SVGBackend<'_>, Shift>) -> Result<()>,
) -> Result<Vec<PathBuf>> {
    register_font();
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut rgb = vec![0u8; (size.0 * size.1 * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, size).into_drawing_area();
        draw_png(&root).with_context(|| format!("drawing {name}.png"))?;
        root.present()?;
    }
    let png = dir.join(format!("{name}.png"));
    let image = image::RgbImage::from_raw(size.0, size.1, rgb).context("picture buffer")?;
    let tmp = png.with_extension(format!("png.partial-{}", std::process::id()));
    image
        .save_with_format(&tmp, image::ImageFormat::Png)
        .with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, &png).with_context(|| format!("writing {}", png.display()))?;
    let mut svg_text = String::new();
    {
        let root = SVGBackend::with_string(&mut svg_text, size).into_drawing_area();
        draw_svg(&root).with_context(|| format!("drawing {name}.svg"))?;
        root.present()?;
    }
    let svg = dir.join(format!("{name}.svg"));
    crate::map_cmd::write_text(&svg, &svg_text)?;
    Ok(vec![png, svg])
}

/// Points of a stepped cumulative distribution of `errors` (None = never within) over `n` queries,
/// clamped to the plot's range `lo..hi`.
fn cdf(errors: &[Option<f64>], lo: f64, hi: f64) -> Vec<(f64, f64)> {
    let n = errors.len().max(1) as f64;
    let mut e: Vec<f64> = errors.iter().flatten().map(|v| v.clamp(lo, hi)).collect();
    e.sort_by(f64::total_cmp);
    let mut pts = vec![(lo, 0.0)];
    for (i, v) in e.iter().enumerate() {
        pts.push((*v, i as f64 / n));
        pts.push((*v, (i + 1) as f64 / n));
    }
    pts.push((hi, e.len() as f64 / n));
    pts
}

fn draw_cdf<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    report: &EvalReport,
    title: &str,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE)?;
    let root = root.titled(title, (FONT, 22))?;
    let (left, right) = root.split_horizontally(SIZE.0 / 2);
    let q = &report.per_query;
    let series = [
        (
            "pipeline (LOCALIZED answers)",
            q.iter().map(|o| o.error).collect::<Vec<_>>(),
            BLUE,
        ),
        (
            "retrieval only (top-1 database pose)",
            q.iter().map(|o| o.retrieval_error).collect::<Vec<_>>(),
            RGBColor(230, 120, 0),
        ),
    ];
    for (area, axis, (lo, hi), marks, x_desc) in [
        (
            &left,
            0usize,
            (0.01, 10.0),
            &THRESHOLDS_M,
            "translation error (m)",
        ),
        (
            &right,
            1usize,
            (0.1, 180.0),
            &THRESHOLDS_DEG,
            "rotation error (deg)",
        ),
    ] {
        let mut chart = ChartBuilder::on(area)
            .margin(12)
            .x_label_area_size(45)
            .y_label_area_size(55)
            .build_cartesian_2d((lo..hi).log_scale(), 0.0..1.0)?;
        chart
            .configure_mesh()
            .x_desc(x_desc)
            .y_desc("share of all queries within")
            .label_style((FONT, 14))
            .draw()?;
        for &m in marks.iter() {
            chart.draw_series(LineSeries::new(
                [(m, 0.0), (m, 1.0)],
                BLACK.mix(0.25).stroke_width(1),
            ))?;
        }
        for (label, errors, colour) in &series {
            let e: Vec<Option<f64>> = errors
                .iter()
                .map(|x| x.map(|(t, r)| if axis == 0 { t } else { r }))
                .collect();
            chart
                .draw_series(LineSeries::new(cdf(&e, lo, hi), colour.stroke_width(2)))?
                .label(*label)
                .legend(move |(x, y)| {
                    PathElement::new([(x, y), (x + 20, y)], colour.stroke_width(2))
                });
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperLeft)
            .label_font((FONT, 14))
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()?;
    }
    Ok(())
}

fn draw_precision_recall<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    report: &EvalReport,
    title: &str,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE)?;
    let root = root.titled(title, (FONT, 22))?;
    let mut chart = ChartBuilder::on(&root)
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(55)
        .build_cartesian_2d(0.0..1.0, 0.0..1.0)?;
    chart
        .configure_mesh()
        .x_desc("threshold on the calibrated confidence")
        .y_desc("share")
        .label_style((FONT, 14))
        .draw()?;
    let c = &report.precision_recall;
    let negatives = report.negatives.is_some();
    let lines: Vec<Line<'_>> = [
        (
            "precision of LOCALIZED (1 m, 10 deg)",
            c.iter()
                .filter(|p| p.precision_1m_10deg.is_finite())
                .map(|p| (p.threshold, p.precision_1m_10deg))
                .collect(),
            RGBColor(0, 140, 60),
        ),
        (
            "recall (1 m, 10 deg)",
            c.iter().map(|p| (p.threshold, p.recall_1m_10deg)).collect(),
            BLUE,
        ),
        (
            "recall (0.25 m, 2 deg)",
            c.iter()
                .map(|p| (p.threshold, p.recall_0_25m_2deg))
                .collect(),
            RGBColor(100, 60, 200),
        ),
        (
            "out-of-map queries LOCALIZED (false-positive rate)",
            if negatives {
                c.iter()
                    .map(|p| (p.threshold, p.false_positive_rate))
                    .collect()
            } else {
                Vec::new()
            },
            RED,
        ),
    ]
    .into_iter()
    .filter(|l| !l.1.is_empty())
    .collect();
    for (label, pts, colour) in lines {
        chart
            .draw_series(LineSeries::new(pts, colour.stroke_width(2)))?
            .label(label)
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], colour.stroke_width(2)));
    }
    if report.min_confidence.is_finite() {
        let t = report.min_confidence;
        chart
            .draw_series(LineSeries::new(
                [(t, 0.0), (t, 1.0)],
                BLACK.mix(0.6).stroke_width(1),
            ))?
            .label(format!("threshold in use ({t:.2})"))
            .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], BLACK.mix(0.6)));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerLeft)
        .label_font((FONT, 14))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()?;
    Ok(())
}

/// A labelled, coloured polyline.
type Line<'a> = (&'a str, Vec<(f64, f64)>, RGBColor);

/// How a query's answer turned out, for the map's colours.
fn outcome_class(o: &QueryOutcome) -> usize {
    match o.error {
        None => 3,
        Some((t, r)) if t <= 0.25 && r <= 2.0 => 0,
        Some((t, r)) if t <= 1.0 && r <= 10.0 => 1,
        Some(_) => 2,
    }
}

const CLASSES: [(&str, RGBColor); 4] = [
    ("LOCALIZED within (0.25 m, 2 deg)", RGBColor(0, 150, 60)),
    ("LOCALIZED within (1 m, 10 deg)", RGBColor(230, 160, 0)),
    (
        "LOCALIZED, wrong (beyond 1 m or 10 deg)",
        RGBColor(220, 0, 0),
    ),
    ("NOT_LOCALIZED", RGBColor(150, 150, 150)),
];

/// The two axes of the ground plane: the pair other than the axis along which the database
/// cameras vary least (the up axis).
fn ground_axes(points: &[[f64; 3]]) -> (usize, usize) {
    let n = points.len().max(1) as f64;
    let var: Vec<f64> = (0..3)
        .map(|a| {
            let m = points.iter().map(|p| p[a]).sum::<f64>() / n;
            points.iter().map(|p| (p[a] - m).powi(2)).sum::<f64>() / n
        })
        .collect();
    let up = (0..3)
        .min_by(|&a, &b| var[a].total_cmp(&var[b]))
        .unwrap_or(1);
    match up {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    }
}

fn draw_map<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    scene: &str,
    db: &[[f64; 3]],
    queries: &[&QueryOutcome],
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE)?;
    let (a, b) = ground_axes(db);
    let all: Vec<(f64, f64)> = db
        .iter()
        .map(|p| (p[a], p[b]))
        .chain(queries.iter().map(|q| (q.position_m[a], q.position_m[b])))
        .collect();
    let (mut x0, mut x1, mut y0, mut y1) = all.iter().fold(
        (
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ),
        |(x0, x1, y0, y1), &(x, y)| (x0.min(x), x1.max(x), y0.min(y), y1.max(y)),
    );
    if !x0.is_finite() {
        (x0, x1, y0, y1) = (-1.0, 1.0, -1.0, 1.0);
    }
    // Equal scales on both axes, with a margin.
    let half = 0.5 * (x1 - x0).max(y1 - y0).max(1.0) + 0.5;
    let (cx, cy) = (0.5 * (x0 + x1), 0.5 * (y0 + y1));
    let axis = ["x", "y", "z"];
    let counts: Vec<usize> = (0..4)
        .map(|k| queries.iter().filter(|q| outcome_class(q) == k).count())
        .collect();
    let title = format!(
        "{scene}: {} queries, {} within (0.25 m, 2 deg), {} wrong, {} not localized",
        queries.len(),
        counts[0],
        counts[2],
        counts[3]
    );
    let root = root.titled(&title, (FONT, 18))?;
    let mut chart = ChartBuilder::on(&root)
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(50)
        .build_cartesian_2d(cx - half..cx + half, cy - half..cy + half)?;
    chart
        .configure_mesh()
        .x_desc(format!("{} (m)", axis[a]))
        .y_desc(format!("{} (m)", axis[b]))
        .label_style((FONT, 14))
        .draw()?;
    chart
        .draw_series(db.iter().map(|p| {
            Rectangle::new(
                [(p[a] - 0.06, p[b] - 0.06), (p[a] + 0.06, p[b] + 0.06)],
                BLACK.mix(0.5).filled(),
            )
        }))?
        .label("database cameras")
        .legend(|(x, y)| Rectangle::new([(x, y - 4), (x + 8, y + 4)], BLACK.mix(0.5).filled()));
    for (k, (label, colour)) in CLASSES.iter().enumerate() {
        let colour = *colour;
        chart
            .draw_series(
                queries
                    .iter()
                    .filter(|q| outcome_class(q) == k)
                    .map(move |q| {
                        Circle::new((q.position_m[a], q.position_m[b]), 4, colour.filled())
                    }),
            )?
            .label(*label)
            .legend(move |(x, y)| Circle::new((x + 4, y), 4, colour.filled()));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .label_font((FONT, 13))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()?;
    Ok(())
}

/// Most scenes drawn as maps by `eval --plot` (one picture each).
pub const MAX_MAP_SCENES: usize = 8;

/// Write the evaluation pictures of `report` into `dir`; `title` names the run. Returns the files.
pub fn eval_plots(report: &EvalReport, dir: &Path, title: &str) -> Result<Vec<PathBuf>> {
    let mut files = save_both(
        dir,
        "errors_cdf",
        SIZE,
        |r| draw_cdf(r, report, title),
        |r| draw_cdf(r, report, title),
    )?;
    files.extend(save_both(
        dir,
        "precision_recall",
        SIZE,
        |r| draw_precision_recall(r, report, title),
        |r| draw_precision_recall(r, report, title),
    )?);
    let mut scenes: BTreeMap<&str, (Vec<[f64; 3]>, Vec<&QueryOutcome>)> = BTreeMap::new();
    for (scene, p) in &report.map_positions_m {
        scenes.entry(scene.as_str()).or_default().0.push(*p);
    }
    for q in &report.per_query {
        let scene = q.id.split('/').next().unwrap_or_default();
        scenes.entry(scene).or_default().1.push(q);
    }
    for (scene, (db, queries)) in scenes.iter().take(MAX_MAP_SCENES) {
        let name = format!("map_{}", sanitize(scene));
        files.extend(save_both(
            dir,
            &name,
            MAP_SIZE,
            |r| draw_map(r, scene, db, queries),
            |r| draw_map(r, scene, db, queries),
        )?);
    }
    Ok(files)
}

/// A scene name safe as part of a file name.
fn sanitize(s: &str) -> String {
    s.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// A square chart of the ground plane `(a, b)` (indices of x, y, z) around `points`, equal scales, a
/// margin, axes labelled in metres.
fn top_down_chart<'a, DB: DrawingBackend>(
    root: &'a DrawingArea<DB, Shift>,
    points: &[[f64; 3]],
    (a, b): (usize, usize),
    title: &str,
) -> Result<
    ChartContext<
        'a,
        DB,
        Cartesian2d<plotters::coord::types::RangedCoordf64, plotters::coord::types::RangedCoordf64>,
    >,
>
where
    DB::ErrorType: 'static,
{
    let (mut x0, mut x1, mut y0, mut y1) = points.iter().fold(
        (
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ),
        |(x0, x1, y0, y1), p| (x0.min(p[a]), x1.max(p[a]), y0.min(p[b]), y1.max(p[b])),
    );
    if !x0.is_finite() {
        (x0, x1, y0, y1) = (-1.0, 1.0, -1.0, 1.0);
    }
    let half = 0.5 * (x1 - x0).max(y1 - y0).max(1.0) + 0.5;
    let (cx, cy) = (0.5 * (x0 + x1), 0.5 * (y0 + y1));
    let root = root.titled(title, (FONT, 16))?;
    let axis = ["x", "y", "z"];
    let mut chart = ChartBuilder::on(&root)
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(50)
        .build_cartesian_2d(cx - half..cx + half, cy - half..cy + half)?;
    chart
        .configure_mesh()
        .x_desc(format!("{} (m)", axis[a]))
        .y_desc(format!("{} (m)", axis[b]))
        .label_style((FONT, 14))
        .draw()?;
    Ok(chart)
}

/// The ground plane of a world whose up axis is `up` (`y` or `z`): the other two axes.
pub fn ground_of(up: &str) -> (usize, usize) {
    if up.eq_ignore_ascii_case("z") {
        (0, 1)
    } else {
        (0, 2)
    }
}

/// A class of checked frames: legend text, colour, and which errors (`None`: not localized) it holds.
type CheckClass = (&'static str, RGBColor, fn(Option<f64>) -> bool);

fn draw_check<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    map: &[[f64; 3]],
    frames: &[([f64; 3], Option<f64>)],
    ground: (usize, usize),
    title: &str,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE)?;
    let (a, b) = ground;
    let all: Vec<[f64; 3]> = map
        .iter()
        .copied()
        .chain(frames.iter().map(|f| f.0))
        .collect();
    let mut chart = top_down_chart(root, &all, ground, title)?;
    chart
        .draw_series(map.iter().map(|p| {
            Rectangle::new(
                [(p[a] - 0.04, p[b] - 0.04), (p[a] + 0.04, p[b] + 0.04)],
                BLACK.mix(0.4).filled(),
            )
        }))?
        .label("map images")
        .legend(|(x, y)| Rectangle::new([(x, y - 4), (x + 8, y + 4)], BLACK.mix(0.4).filled()));
    let classes: [CheckClass; 4] = [
        ("within 0.25 m", RGBColor(0, 150, 60), |e| {
            e.is_some_and(|e| e <= 0.25)
        }),
        ("0.25-1 m off", RGBColor(230, 140, 0), |e| {
            e.is_some_and(|e| e > 0.25 && e <= 1.0)
        }),
        ("more than 1 m off", RED, |e| e.is_some_and(|e| e > 1.0)),
        (
            "not localized (drive here again)",
            RGBColor(120, 0, 160),
            |e| e.is_none(),
        ),
    ];
    for (label, colour, pick) in classes {
        let n = frames.iter().filter(|f| pick(f.1)).count();
        chart
            .draw_series(
                frames
                    .iter()
                    .filter(|f| pick(f.1))
                    .map(move |f| Circle::new((f.0[a], f.0[b]), 3, colour.filled())),
            )?
            .label(format!("{label}: {n}"))
            .legend(move |(x, y)| Circle::new((x + 4, y), 4, colour.filled()));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .label_font((FONT, 13))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()?;
    Ok(())
}

/// Write `map_check.png` / `.svg` into `dir`: the map's camera positions from above (ground plane
/// `ground`, indices of x, y, z) and each checked frame at its recorded position, coloured by how far
/// its answer was off (`None`: not localized), so a team sees where to drive again.
pub fn check_plot(
    map: &[[f64; 3]],
    frames: &[([f64; 3], Option<f64>)],
    ground: (usize, usize),
    dir: &Path,
    title: &str,
) -> Result<Vec<PathBuf>> {
    save_both(
        dir,
        "map_check",
        MAP_SIZE,
        |r| draw_check(r, map, frames, ground, title),
        |r| draw_check(r, map, frames, ground, title),
    )
}

fn draw_trajectories<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    map: &[[f64; 3]],
    truth: &[[f64; 3]],
    estimate: &[[f64; 3]],
    title: &str,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE)?;
    let all: Vec<[f64; 3]> = map.iter().chain(truth).chain(estimate).copied().collect();
    let (a, b) = ground_axes(if map.len() >= 3 { map } else { &all });
    let mut chart = top_down_chart(root, &all, (a, b), title)?;
    if !map.is_empty() {
        chart
            .draw_series(map.iter().map(|p| {
                Rectangle::new(
                    [(p[a] - 0.06, p[b] - 0.06), (p[a] + 0.06, p[b] + 0.06)],
                    BLACK.mix(0.5).filled(),
                )
            }))?
            .label("map images (database cameras)")
            .legend(|(x, y)| Rectangle::new([(x, y - 4), (x + 8, y + 4)], BLACK.mix(0.5).filled()));
    }
    let green = RGBColor(0, 150, 60);
    chart
        .draw_series(LineSeries::new(
            truth.iter().map(|p| (p[a], p[b])),
            green.stroke_width(3),
        ))?
        .label("ground truth")
        .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], green.stroke_width(3)));
    chart
        .draw_series(
            estimate
                .iter()
                .map(|p| Circle::new((p[a], p[b]), 2, BLUE.filled())),
        )?
        .label("LOCALIZED answers")
        .legend(|(x, y)| Circle::new((x + 4, y), 3, BLUE.filled()));
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .label_font((FONT, 13))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()?;
    Ok(())
}

/// Write `trajectory.png` / `.svg` into `dir`: the ground-truth path and the LOCALIZED answers from
/// above, over the map's camera positions `map` (all map frame, metres).
pub fn trajectory_plot(
    map: &[[f64; 3]],
    truth: &[[f64; 3]],
    estimate: &[[f64; 3]],
    dir: &Path,
    title: &str,
) -> Result<Vec<PathBuf>> {
    save_both(
        dir,
        "trajectory",
        MAP_SIZE,
        |r| draw_trajectories(r, map, truth, estimate, title),
        |r| draw_trajectories(r, map, truth, estimate, title),
    )
}

/// One sweep level for [`bench_plot`].
#[derive(Debug, Clone, Copy)]
pub struct SweepPoint {
    /// Clients (closed loop) or the in-flight bound (open loop).
    pub concurrency: usize,
    /// Answered frames per second.
    pub fps: f64,
    /// Latency percentiles, ms.
    pub p50_ms: f64,
    /// 90th percentile, ms.
    pub p90_ms: f64,
    /// 99th percentile, ms.
    pub p99_ms: f64,
    /// Requests that failed.
    pub errors: usize,
}

fn draw_sweep<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    points: &[SweepPoint],
    title: &str,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE)?;
    let root = root.titled(title, (FONT, 22))?;
    let (left, right) = root.split_horizontally(SIZE.0 / 2);
    let c_max = points.iter().map(|p| p.concurrency).max().unwrap_or(1) as f64;
    let fps_max = points.iter().map(|p| p.fps).fold(0.0, f64::max).max(1.0) * 1.1;
    let mut chart = ChartBuilder::on(&left)
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(55)
        .build_cartesian_2d(0.0..c_max * 1.05 + 0.5, 0.0..fps_max)?;
    chart
        .configure_mesh()
        .x_desc("concurrent clients")
        .y_desc("frames per second")
        .label_style((FONT, 14))
        .draw()?;
    let fps: Vec<(f64, f64)> = points
        .iter()
        .map(|p| (p.concurrency as f64, p.fps))
        .collect();
    chart.draw_series(LineSeries::new(fps.clone(), BLUE.stroke_width(2)))?;
    chart.draw_series(
        fps.iter()
            .map(|&(x, y)| Circle::new((x, y), 4, BLUE.filled())),
    )?;
    chart.draw_series(
        points
            .iter()
            .filter(|p| p.errors > 0)
            .map(|p| Cross::new((p.concurrency as f64, p.fps), 7, RED.stroke_width(2))),
    )?;
    let lat_max = points.iter().map(|p| p.p99_ms).fold(0.0, f64::max).max(1.0) * 1.1;
    let mut chart = ChartBuilder::on(&right)
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(55)
        .build_cartesian_2d(0.0..c_max * 1.05 + 0.5, 0.0..lat_max)?;
    chart
        .configure_mesh()
        .x_desc("concurrent clients")
        .y_desc("latency (ms)")
        .label_style((FONT, 14))
        .draw()?;
    for (label, pick, colour) in [
        (
            "p50",
            (|p: &SweepPoint| p.p50_ms) as fn(&SweepPoint) -> f64,
            RGBColor(0, 140, 60),
        ),
        ("p90", |p: &SweepPoint| p.p90_ms, RGBColor(230, 120, 0)),
        ("p99", |p: &SweepPoint| p.p99_ms, RED),
    ] {
        chart
            .draw_series(LineSeries::new(
                points.iter().map(|p| (p.concurrency as f64, pick(p))),
                colour.stroke_width(2),
            ))?
            .label(label)
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], colour.stroke_width(2)));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .label_font((FONT, 14))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()?;
    Ok(())
}

/// Write `bench_sweep.png` / `.svg` (throughput and latency against concurrency) into `dir`.
pub fn bench_plot(points: &[SweepPoint], dir: &Path, title: &str) -> Result<Vec<PathBuf>> {
    save_both(
        dir,
        "bench_sweep",
        SIZE,
        |r| draw_sweep(r, points, title),
        |r| draw_sweep(r, points, title),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cdf_counts_failures_in_the_denominator_and_clamps_to_the_range() {
        let pts = cdf(&[Some(0.05), None, Some(100.0), Some(0.001)], 0.01, 10.0);
        assert_eq!(pts.first(), Some(&(0.01, 0.0)));
        // Three of four queries have an error; the curve ends at 3/4, never 1.
        assert_eq!(pts.last(), Some(&(10.0, 0.75)));
        assert!(pts.windows(2).all(|w| w[0].0 <= w[1].0 && w[0].1 <= w[1].1));
        assert!(pts.iter().all(|p| (0.01..=10.0).contains(&p.0)));
    }

    #[test]
    fn the_ground_plane_leaves_out_the_axis_that_varies_least() {
        let habitat = [[0.0, 1.5, 0.0], [4.0, 1.5, 1.0], [2.0, 1.6, 5.0]];
        assert_eq!(ground_axes(&habitat), (0, 2));
        let z_up = [[0.0, 0.0, 1.5], [4.0, 1.0, 1.5], [2.0, 5.0, 1.6]];
        assert_eq!(ground_axes(&z_up), (0, 1));
    }
}
