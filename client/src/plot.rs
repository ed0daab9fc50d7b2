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
//! - `trajectory` (`pntr replay --plot DIR`): the ground-truth path and the LOCALIZED answers from above.
//! - `bench_sweep`: frames per second and latency percentiles against the number of clients.
//!
//! Every picture is a [`Figure`]: a title over panels side by side, each a [`Panel`] of labelled
//! [`Series`]. One frame ([`save`], [`draw_figure`], [`draw_panel`]) draws them all the same way, and
//! places each panel's legend where it covers no data: in a corner of the plotting area whose box holds
//! no plotted point or line (worked out in picture pixels), else in a band below the panel, sized from
//! the entries.
//!
//! Text is drawn with the DejaVu Sans font bundled by the `dejavu` crate, so the pictures look the same
//! on a machine without fonts.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Once;

use anyhow::{Context, Result};
use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use pntr_eval::{CurvePoint, EvalReport, QueryOutcome};

/// Size of every picture, pixels.
const SIZE: (u32, u32) = (1200, 560);
/// Square size of the top-down maps, pixels.
const MAP_SIZE: (u32, u32) = (900, 900);
/// The protocol's translation thresholds, metres, marked on the error plot.
const THRESHOLDS_M: [f64; 4] = [0.25, 0.5, 1.0, 5.0];
/// ... and its rotation thresholds, degrees.
const THRESHOLDS_DEG: [f64; 4] = [2.0, 5.0, 10.0, 20.0];
const FONT: &str = "sans-serif";

/// A point of the picture, pixels from its top-left corner.
type Px = (i32, i32);

/// Space around each panel, pixels.
const MARGIN: i32 = 12;
/// Space between a legend's border and its entries, pixels.
const LEGEND_PAD: i32 = 8;
/// Width of an entry's sample of the series, and the space after it, pixels.
const ICON_W: i32 = 20;
const ICON_GAP: i32 = 6;
/// Space between entries side by side in a legend band, and between rows, pixels.
const ENTRY_GAP: i32 = 24;
const ROW_GAP: i32 = 4;
/// Least distance kept between a legend box and any plotted ink, pixels.
const CLEARANCE: i32 = 4;

fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The bundled font is known good; a failure would only leave text out.
        let _ = plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular());
    });
}

/// How the points of a series are drawn.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Mark {
    /// A polyline this many pixels wide.
    Line(u32),
    /// A filled dot of this radius, pixels.
    Dot(u32),
    /// A filled square of this half side, in data units (metres on a map).
    Square(f64),
    /// A cross of this size, pixels.
    Cross(u32),
}

/// A set of points drawn one way; with a label, it has a legend entry.
#[derive(Debug, Clone)]
struct Series {
    label: Option<String>,
    colour: RGBAColor,
    mark: Mark,
    points: Vec<(f64, f64)>,
}

impl Series {
    fn labelled(
        label: impl Into<String>,
        colour: impl Color,
        mark: Mark,
        points: Vec<(f64, f64)>,
    ) -> Self {
        Self {
            label: Some(label.into()),
            ..Self::plain(colour, mark, points)
        }
    }

    fn plain(colour: impl Color, mark: Mark, points: Vec<(f64, f64)>) -> Self {
        Self {
            label: None,
            colour: colour.to_rgba(),
            mark,
            points,
        }
    }
}

/// One axis: its description and range, linear or logarithmic.
#[derive(Debug, Clone)]
struct Axis {
    desc: String,
    lo: f64,
    hi: f64,
    log: bool,
}

impl Axis {
    fn linear(desc: impl Into<String>, lo: f64, hi: f64) -> Self {
        Self {
            desc: desc.into(),
            lo,
            hi,
            log: false,
        }
    }

    fn log(desc: impl Into<String>, lo: f64, hi: f64) -> Self {
        Self {
            log: true,
            ..Self::linear(desc, lo, hi)
        }
    }
}

/// One chart: axes, series, and how it is laid out.
#[derive(Debug, Clone)]
struct Panel {
    x: Axis,
    y: Axis,
    /// A metre on x is as long as a metre on y (maps): the ranges widen to fit the plotting area.
    equal_scale: bool,
    /// Height of the x-label area and width of the y-label area, pixels.
    label_area: (u32, u32),
    legend_font: u32,
    series: Vec<Series>,
}

impl Panel {
    /// A chart of measurements.
    fn chart(x: Axis, y: Axis, series: Vec<Series>) -> Self {
        Self {
            x,
            y,
            equal_scale: false,
            label_area: (45, 55),
            legend_font: 14,
            series,
        }
    }

    /// A map of the ground plane from above, equal scales.
    fn map((x, y): (Axis, Axis), series: Vec<Series>) -> Self {
        Self {
            equal_scale: true,
            label_area: (40, 50),
            legend_font: 13,
            ..Self::chart(x, y, series)
        }
    }
}

/// A picture: `name.png` and `name.svg`, a title over panels of equal width side by side.
#[derive(Debug, Clone)]
struct Figure {
    name: String,
    size: (u32, u32),
    title: String,
    title_font: u32,
    panels: Vec<Panel>,
}

impl Figure {
    /// Charts of measurements side by side.
    fn charts(name: &str, title: &str, panels: Vec<Panel>) -> Self {
        Self {
            name: name.into(),
            size: SIZE,
            title: title.into(),
            title_font: 22,
            panels,
        }
    }

    /// `series` on the ground plane `ground` seen from above, around `points`.
    fn top_down(
        name: String,
        (title, title_font): (String, u32),
        points: &[[f64; 3]],
        ground: (usize, usize),
        series: Vec<Series>,
    ) -> Self {
        Self {
            name,
            size: MAP_SIZE,
            title,
            title_font,
            panels: vec![Panel::map(ground_view(points, ground), series)],
        }
    }
}

/// A rectangle of picture pixels, both corners included.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Rect {
    x0: i32,
    y0: i32,
    x1: i32,
    y1: i32,
}

impl Rect {
    fn at((x0, y0): Px, (w, h): (i32, i32)) -> Self {
        Self {
            x0,
            y0,
            x1: x0 + w,
            y1: y0 + h,
        }
    }

    fn grown(self, d: i32) -> Self {
        Self {
            x0: self.x0 - d,
            y0: self.y0 - d,
            x1: self.x1 + d,
            y1: self.y1 + d,
        }
    }

    fn contains(self, r: Rect) -> bool {
        self.x0 <= r.x0 && self.y0 <= r.y0 && r.x1 <= self.x1 && r.y1 <= self.y1
    }

    /// Whether some point of the segment `a`-`b` lies inside (Liang-Barsky clipping).
    fn meets(self, a: Px, b: Px) -> bool {
        let (ax, ay) = (f64::from(a.0), f64::from(a.1));
        let (dx, dy) = (f64::from(b.0) - ax, f64::from(b.1) - ay);
        let (mut t0, mut t1) = (0.0f64, 1.0f64);
        for (p, q) in [
            (-dx, ax - f64::from(self.x0)),
            (dx, f64::from(self.x1) - ax),
            (-dy, ay - f64::from(self.y0)),
            (dy, f64::from(self.y1) - ay),
        ] {
            if p == 0.0 {
                if q < 0.0 {
                    return false;
                }
            } else if p < 0.0 {
                t0 = t0.max(q / p);
            } else {
                t1 = t1.min(q / p);
            }
        }
        t0 <= t1
    }
}

/// Plotted data in picture pixels: a segment (a point when its ends are equal) and how far its ink
/// reaches either side.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Ink {
    a: Px,
    b: Px,
    reach: i32,
}

impl Ink {
    /// Whether this ink lies under `r`, or closer to it than the clearance.
    fn under(self, r: Rect) -> bool {
        r.grown(self.reach + CLEARANCE).meets(self.a, self.b)
    }
}

/// Where a panel's parts went, in picture pixels.
#[derive(Debug, Clone)]
#[cfg_attr(not(test), expect(dead_code, reason = "the tests check the layout"))]
struct Placed {
    /// The plotting area (inside the axes).
    plot: Rect,
    /// The legend's box; `None` when no series has a label.
    legend: Option<Rect>,
    /// Everything plotted.
    ink: Vec<Ink>,
}

/// Where a legend's entries go inside its box.
#[derive(Debug, Clone, PartialEq, Eq)]
struct LegendLayout {
    /// The box's width and height.
    size: (i32, i32),
    /// Height of one row of entries.
    row_h: i32,
    /// Top-left corner of each entry, from the box's top-left corner.
    at: Vec<(i32, i32)>,
}

/// The layout of legend entries whose texts measure `texts` (width, height), flowed left to right
/// into rows at most `max_w` wide (0: one entry a row).
fn legend_layout(texts: &[(u32, u32)], max_w: i32) -> LegendLayout {
    let row_h = texts.iter().map(|t| t.1 as i32).max().unwrap_or(0).max(10) + ROW_GAP;
    let (mut x, mut y, mut w) = (0, 0, 0);
    let mut at = Vec::with_capacity(texts.len());
    for (i, t) in texts.iter().enumerate() {
        let entry_w = ICON_W + ICON_GAP + t.0 as i32;
        if i > 0 {
            if x + ENTRY_GAP + entry_w + 2 * LEGEND_PAD <= max_w {
                x += ENTRY_GAP;
            } else {
                (x, y) = (0, y + row_h);
            }
        }
        at.push((LEGEND_PAD + x, LEGEND_PAD + y));
        x += entry_w;
        w = w.max(x);
    }
    LegendLayout {
        size: (w + 2 * LEGEND_PAD, y + row_h - ROW_GAP + 2 * LEGEND_PAD),
        row_h,
        at,
    }
}

/// Boxes of `size` in the corners of `plot`, most preferred first: upper left, upper right, lower
/// right, lower left.
fn corners(plot: Rect, (w, h): (i32, i32)) -> [Rect; 4] {
    let inset = 2 * CLEARANCE;
    let (left, right) = (plot.x0 + inset, plot.x1 - inset - w);
    let (top, bottom) = (plot.y0 + inset, plot.y1 - inset - h);
    [(left, top), (right, top), (right, bottom), (left, bottom)].map(|c| Rect::at(c, (w, h)))
}

/// The first corner box of `plot` that fits and holds none of `ink`.
fn free_corner(plot: Rect, size: (i32, i32), ink: &[Ink]) -> Option<Rect> {
    corners(plot, size)
        .into_iter()
        .find(|&c| plot.contains(c) && !ink.iter().any(|i| i.under(c)))
}

/// Draw `fig` into `dir/NAME.png` and `dir/NAME.svg` (each written to a temporary name, then
/// renamed); returns both paths.
fn save(dir: &Path, fig: &Figure) -> Result<Vec<PathBuf>> {
    register_font();
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let (name, size) = (&fig.name, fig.size);
    let mut rgb = vec![0u8; (size.0 * size.1 * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, size).into_drawing_area();
        draw_figure(&root, fig).with_context(|| format!("drawing {name}.png"))?;
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
        draw_figure(&root, fig).with_context(|| format!("drawing {name}.svg"))?;
        root.present()?;
    }
    let svg = dir.join(format!("{name}.svg"));
    crate::output::write_text(&svg, &svg_text)?;
    Ok(vec![png, svg])
}

/// Draw `fig` on the whole picture `root`; returns where each panel's parts went.
fn draw_figure<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    fig: &Figure,
) -> Result<Vec<Placed>>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE)?;
    let body = root.titled(&fig.title, (FONT, fig.title_font))?;
    body.split_evenly((1, fig.panels.len().max(1)))
        .iter()
        .zip(&fig.panels)
        .map(|(area, panel)| draw_panel(root, area, panel))
        .collect()
}

/// Draw `panel` in `area` of the picture `root`.
fn draw_panel<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    area: &DrawingArea<DB, Shift>,
    panel: &Panel,
) -> Result<Placed>
where
    DB::ErrorType: 'static,
{
    if panel.x.log {
        draw_panel_as(root, area, panel, |lo, hi| (lo..hi).log_scale())
    } else {
        draw_panel_as(root, area, panel, |lo, hi| lo..hi)
    }
}

/// A panel's chart, the x axis made by `x_spec` from its range.
type Chart<DB, XS> = ChartContext<
    'static,
    DB,
    Cartesian2d<<XS as plotters::coord::ranged1d::AsRangedCoord>::CoordDescType, RangedCoordf64>,
>;

fn draw_panel_as<DB, XS>(
    root: &DrawingArea<DB, Shift>,
    area: &DrawingArea<DB, Shift>,
    panel: &Panel,
    x_spec: impl Fn(f64, f64) -> XS,
) -> Result<Placed>
where
    DB: DrawingBackend,
    DB::ErrorType: 'static,
    XS: plotters::coord::ranged1d::AsRangedCoord<Value = f64>,
    XS::CoordDescType: plotters::coord::ranged1d::ValueFormatter<f64>,
{
    let style = TextStyle::from((FONT, panel.legend_font));
    let labelled: Vec<(&Series, &str)> = panel
        .series
        .iter()
        .filter_map(|s| Some((s, s.label.as_deref()?)))
        .collect();
    let texts = labelled
        .iter()
        .map(|(_, label)| root.estimate_text_size(label, &style))
        .collect::<Result<Vec<_>, _>>()?;
    let mut chart = build_chart(area, panel, &x_spec)?;
    let mut legend = None;
    if !labelled.is_empty() {
        // Inside, in a corner clear of the data ...
        let layout = legend_layout(&texts, 0);
        if let Some(r) = free_corner(plot_rect(&chart), layout.size, &ink(&chart, &panel.series)) {
            legend = Some((r, layout));
        } else {
            // ... else in a band below the panel, the chart above it.
            let (w, h) = area.dim_in_pixel();
            let (w, h) = (w as i32, h as i32);
            let layout = legend_layout(&texts, w - 2 * MARGIN);
            let band = (layout.size.1 + MARGIN).min(h / 2);
            let (upper, _) = area.split_vertically(h - band);
            chart = build_chart(&upper, panel, &x_spec)?;
            let (ax, ay) = area.get_base_pixel();
            let x0 = plot_rect(&chart)
                .x0
                .min(ax + w - MARGIN - layout.size.0)
                .max(ax + MARGIN);
            legend = Some((Rect::at((x0, ay + h - band), layout.size), layout));
        }
    }
    chart
        .configure_mesh()
        .x_desc(&panel.x.desc)
        .y_desc(&panel.y.desc)
        .label_style((FONT, 14))
        .draw()?;
    for s in &panel.series {
        draw_series(&mut chart, s)?;
    }
    if let Some((r, layout)) = &legend {
        root.draw(&Rectangle::new(
            [(r.x0, r.y0), (r.x1, r.y1)],
            WHITE.mix(0.85).filled(),
        ))?;
        root.draw(&Rectangle::new([(r.x0, r.y0), (r.x1, r.y1)], BLACK))?;
        let text = style.pos(Pos::new(HPos::Left, VPos::Center));
        for ((s, label), (dx, dy)) in labelled.iter().zip(&layout.at) {
            let (x, y) = (r.x0 + dx, r.y0 + dy + (layout.row_h - ROW_GAP) / 2);
            draw_icon(root, s, (x, y))?;
            root.draw(&Text::new(*label, (x + ICON_W + ICON_GAP, y), &text))?;
        }
    }
    Ok(Placed {
        plot: plot_rect(&chart),
        legend: legend.map(|l| l.0),
        ink: ink(&chart, &panel.series),
    })
}

/// `panel`'s chart in `area` (nothing drawn yet), its ranges widened to equal scales if asked.
fn build_chart<DB, XS>(
    area: &DrawingArea<DB, Shift>,
    panel: &Panel,
    x_spec: &impl Fn(f64, f64) -> XS,
) -> Result<Chart<DB, XS>>
where
    DB: DrawingBackend,
    DB::ErrorType: 'static,
    XS: plotters::coord::ranged1d::AsRangedCoord<Value = f64>,
{
    let build = |(x0, x1): (f64, f64), (y0, y1): (f64, f64)| {
        ChartBuilder::on(area)
            .margin(MARGIN)
            .x_label_area_size(panel.label_area.0)
            .y_label_area_size(panel.label_area.1)
            .build_cartesian_2d(x_spec(x0, x1), y0..y1)
    };
    let (x, y) = ((panel.x.lo, panel.x.hi), (panel.y.lo, panel.y.hi));
    let chart = build(x, y)?;
    if !panel.equal_scale {
        return Ok(chart);
    }
    let (w, h) = chart.plotting_area().dim_in_pixel();
    let per_unit = (f64::from(w) / (x.1 - x.0)).min(f64::from(h) / (y.1 - y.0));
    let around = |(lo, hi): (f64, f64), pixels: u32| {
        let (c, half) = (0.5 * (lo + hi), 0.5 * f64::from(pixels) / per_unit);
        (c - half, c + half)
    };
    Ok(build(around(x, w), around(y, h))?)
}

/// The plotting area of `chart`, picture pixels.
fn plot_rect<DB: DrawingBackend, X: Ranged>(
    chart: &ChartContext<'_, DB, Cartesian2d<X, RangedCoordf64>>,
) -> Rect {
    let (x, y) = chart.plotting_area().get_pixel_range();
    Rect {
        x0: x.start,
        y0: y.start,
        x1: x.end - 1,
        y1: y.end - 1,
    }
}

/// The ink of `series` drawn on `chart`, picture pixels.
fn ink<DB: DrawingBackend, X: Ranged<ValueType = f64>>(
    chart: &ChartContext<'_, DB, Cartesian2d<X, RangedCoordf64>>,
    series: &[Series],
) -> Vec<Ink> {
    let mut out = Vec::new();
    for s in series {
        let px: Vec<Px> = s.points.iter().map(|p| chart.backend_coord(p)).collect();
        let dot = |reach: i32| px.iter().map(move |&a| Ink { a, b: a, reach });
        match s.mark {
            Mark::Line(w) => {
                let reach = (w as i32 + 1) / 2;
                if px.len() == 1 {
                    out.extend(dot(reach));
                }
                out.extend(px.windows(2).map(|p| Ink {
                    a: p[0],
                    b: p[1],
                    reach,
                }));
            }
            Mark::Dot(r) | Mark::Cross(r) => out.extend(dot(r as i32)),
            Mark::Square(half) => {
                let reach = s.points.first().map_or(1, |&(x, y)| {
                    let (c, e) = (
                        chart.backend_coord(&(x, y)),
                        chart.backend_coord(&(x + half, y + half)),
                    );
                    (e.0 - c.0).abs().max((e.1 - c.1).abs()).max(1)
                });
                out.extend(dot(reach));
            }
        }
    }
    out
}

fn draw_series<DB: DrawingBackend, X: Ranged<ValueType = f64>>(
    chart: &mut ChartContext<'_, DB, Cartesian2d<X, RangedCoordf64>>,
    s: &Series,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let (c, points) = (s.colour, s.points.iter().copied());
    match s.mark {
        Mark::Line(w) => chart.draw_series(LineSeries::new(points, c.stroke_width(w)))?,
        Mark::Dot(r) => chart.draw_series(points.map(|p| Circle::new(p, r, c.filled())))?,
        Mark::Square(h) => chart.draw_series(
            points.map(|(x, y)| Rectangle::new([(x - h, y - h), (x + h, y + h)], c.filled())),
        )?,
        Mark::Cross(r) => chart.draw_series(points.map(|p| Cross::new(p, r, c.stroke_width(2))))?,
    };
    Ok(())
}

/// A legend entry's sample of `s`, `ICON_W` wide, its left end at `(x, y)`.
fn draw_icon<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    s: &Series,
    (x, y): Px,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let (c, mid) = (s.colour, x + ICON_W / 2);
    match s.mark {
        Mark::Line(w) => root.draw(&PathElement::new(
            [(x, y), (x + ICON_W, y)],
            c.stroke_width(w),
        ))?,
        // A little larger than on the chart, so the colour shows.
        Mark::Dot(r) => root.draw(&Circle::new((mid, y), (r + 1).clamp(3, 4), c.filled()))?,
        Mark::Square(_) => root.draw(&Rectangle::new(
            [(mid - 4, y - 4), (mid + 4, y + 4)],
            c.filled(),
        ))?,
        Mark::Cross(r) => root.draw(&Cross::new((mid, y), r.min(6), c.stroke_width(2)))?,
    }
    Ok(())
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

/// `errors_cdf`: for translation (left) and rotation (right), the share of `queries` within each
/// error, for the pipeline and for retrieval only, over the protocol's thresholds.
fn cdf_figure(queries: &[QueryOutcome], title: &str) -> Figure {
    let panel = |axis: usize, (lo, hi): (f64, f64), marks: &[f64], x_desc: &str| {
        let mut series: Vec<Series> = marks
            .iter()
            .map(|&m| Series::plain(BLACK.mix(0.25), Mark::Line(1), vec![(m, 0.0), (m, 1.0)]))
            .collect();
        let pick = |e: Option<(f64, f64)>| e.map(|(t, r)| if axis == 0 { t } else { r });
        let pipeline: Vec<Option<f64>> = queries.iter().map(|o| pick(o.error)).collect();
        let retrieval: Vec<Option<f64>> = queries.iter().map(|o| pick(o.retrieval_error)).collect();
        series.push(Series::labelled(
            "pipeline (LOCALIZED answers)",
            BLUE,
            Mark::Line(2),
            cdf(&pipeline, lo, hi),
        ));
        series.push(Series::labelled(
            "retrieval only (top-1 database pose)",
            RGBColor(230, 120, 0),
            Mark::Line(2),
            cdf(&retrieval, lo, hi),
        ));
        Panel::chart(
            Axis::log(x_desc, lo, hi),
            Axis::linear("share of all queries within", 0.0, 1.0),
            series,
        )
    };
    Figure::charts(
        "errors_cdf",
        title,
        vec![
            panel(0, (0.01, 10.0), &THRESHOLDS_M, "translation error (m)"),
            panel(1, (0.1, 180.0), &THRESHOLDS_DEG, "rotation error (deg)"),
        ],
    )
}

/// `precision_recall`: precision and recall along the curve `c`, the out-of-map false-positive rate
/// when there were out-of-map queries (`negatives`), and the threshold in use when known.
fn precision_recall_figure(
    c: &[CurvePoint],
    negatives: bool,
    min_confidence: f64,
    title: &str,
) -> Figure {
    let curve = |f: fn(&CurvePoint) -> f64| -> Vec<(f64, f64)> {
        c.iter()
            .map(|p| (p.threshold, f(p)))
            .filter(|p| p.1.is_finite())
            .collect()
    };
    let mut series: Vec<Series> = [
        (
            "precision of LOCALIZED (1 m, 10 deg)",
            curve(|p| p.precision_1m_10deg),
            RGBColor(0, 140, 60),
        ),
        ("recall (1 m, 10 deg)", curve(|p| p.recall_1m_10deg), BLUE),
        (
            "recall (0.25 m, 2 deg)",
            curve(|p| p.recall_0_25m_2deg),
            RGBColor(100, 60, 200),
        ),
        (
            "out-of-map queries LOCALIZED (false-positive rate)",
            if negatives {
                curve(|p| p.false_positive_rate)
            } else {
                Vec::new()
            },
            RED,
        ),
    ]
    .into_iter()
    .filter(|l| !l.1.is_empty())
    .map(|(label, pts, colour)| Series::labelled(label, colour, Mark::Line(2), pts))
    .collect();
    if min_confidence.is_finite() {
        let t = min_confidence;
        series.push(Series::labelled(
            format!("threshold in use ({t:.2})"),
            BLACK.mix(0.6),
            Mark::Line(1),
            vec![(t, 0.0), (t, 1.0)],
        ));
    }
    Figure::charts(
        "precision_recall",
        title,
        vec![Panel::chart(
            Axis::linear("threshold on the calibrated confidence", 0.0, 1.0),
            Axis::linear("share", 0.0, 1.0),
            series,
        )],
    )
}

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

/// The ground plane `(a, b)` (indices of x, y, z) of `points`: a square around them with a margin,
/// axes labelled in metres.
fn ground_view(points: &[[f64; 3]], (a, b): (usize, usize)) -> (Axis, Axis) {
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
    let axis = ["x", "y", "z"];
    (
        Axis::linear(format!("{} (m)", axis[a]), cx - half, cx + half),
        Axis::linear(format!("{} (m)", axis[b]), cy - half, cy + half),
    )
}

/// Positions `points` on the ground plane `(a, b)`.
fn on_ground<'a>(
    points: impl IntoIterator<Item = &'a [f64; 3]>,
    (a, b): (usize, usize),
) -> Vec<(f64, f64)> {
    points.into_iter().map(|p| (p[a], p[b])).collect()
}

/// Legend of the places where wrong answers put the camera on `map_<scene>`.
const WRONG_ESTIMATES: &str = "where the wrong answers put the camera";

/// `map_<scene>`: the database cameras `db` of `scene` from above and its `queries` at their true
/// positions, coloured by how they turned out; each wrong answer is joined to where it put the
/// camera (`estimate_world_from_camera`).
fn scene_figure(scene: &str, db: &[[f64; 3]], queries: &[&QueryOutcome]) -> Figure {
    let ground = ground_axes(db);
    // Wrong LOCALIZED answers: the true position and the estimate's.
    let wrong: Vec<([f64; 3], [f64; 3])> = queries
        .iter()
        .filter(|q| outcome_class(q) == 2)
        .filter_map(|q| {
            let e = q.estimate_world_from_camera?;
            Some((q.position_m, [e[0], e[1], e[2]]))
        })
        .collect();
    let all: Vec<[f64; 3]> = db
        .iter()
        .copied()
        .chain(queries.iter().map(|q| q.position_m))
        .chain(wrong.iter().map(|w| w.1))
        .collect();
    let mut series = vec![Series::labelled(
        "database cameras",
        BLACK.mix(0.5),
        Mark::Square(0.06),
        on_ground(db, ground),
    )];
    let wrong_colour = CLASSES[2].1;
    for (truth, estimate) in &wrong {
        series.push(Series::plain(
            wrong_colour.mix(0.6),
            Mark::Line(1),
            on_ground([truth, estimate], ground),
        ));
    }
    if !wrong.is_empty() {
        series.push(Series::labelled(
            WRONG_ESTIMATES,
            RGBColor(120, 0, 0),
            Mark::Dot(2),
            on_ground(wrong.iter().map(|w| &w.1), ground),
        ));
    }
    let mut counts = [0usize; 4];
    for (k, (label, colour)) in CLASSES.iter().enumerate() {
        let class: Vec<&QueryOutcome> = queries
            .iter()
            .copied()
            .filter(|q| outcome_class(q) == k)
            .collect();
        counts[k] = class.len();
        let at = on_ground(class.iter().map(|q| &q.position_m), ground);
        series.push(Series::labelled(*label, *colour, Mark::Dot(4), at));
    }
    let title = format!(
        "{scene}: {} queries, {} within (0.25 m, 2 deg), {} wrong, {} not localized",
        queries.len(),
        counts[0],
        counts[2],
        counts[3]
    );
    let name = format!("map_{}", sanitize(scene));
    Figure::top_down(name, (title, 18), &all, ground, series)
}

/// Most scenes drawn as maps by `eval --plot` (one picture each).
pub const MAX_MAP_SCENES: usize = 8;

/// Per scene: the cameras and the queries of its `map_<scene>` picture.
type SceneGroups<'a> = BTreeMap<&'a str, (Vec<[f64; 3]>, Vec<&'a QueryOutcome>)>;

/// Name of the picture of a map's images from recordings when the queries come from several scenes.
const RECORDED_MAP: &str = "map";

/// The cameras and queries of each scene's `map_<scene>` picture: the map's cameras of that scene
/// (`map_positions_m`), the scene's queries (the first part of their id), and the map's images
/// from recordings (empty scene name): on the queries' scene when there is one (they lie in its
/// world frame, where eval measures the answers), else on a picture of their own, `map_map`.
fn scene_groups<'a>(
    map_positions_m: &'a [(String, [f64; 3])],
    per_query: &'a [QueryOutcome],
) -> SceneGroups<'a> {
    let mut scenes: SceneGroups<'a> = BTreeMap::new();
    for q in per_query {
        let scene = q.id.split('/').next().unwrap_or_default();
        scenes.entry(scene).or_default().1.push(q);
    }
    let (recorded, named): (Vec<_>, Vec<_>) = map_positions_m
        .iter()
        .partition(|(scene, _)| scene.is_empty());
    // A recording covers one place: with several scenes it is not known which, so its cameras get
    // a picture of their own.
    let home = match scenes.len() {
        1 => *scenes.keys().next().expect("one scene"),
        _ => RECORDED_MAP,
    };
    for (scene, p) in named {
        scenes.entry(scene.as_str()).or_default().0.push(*p);
    }
    if !recorded.is_empty() {
        scenes
            .entry(home)
            .or_default()
            .0
            .extend(recorded.iter().map(|(_, p)| *p));
    }
    scenes
}

/// Write the evaluation pictures of `report` into `dir`; `title` names the run. Returns the files.
pub fn eval_plots(report: &EvalReport, dir: &Path, title: &str) -> Result<Vec<PathBuf>> {
    let mut figures = vec![
        cdf_figure(&report.per_query, title),
        precision_recall_figure(
            &report.precision_recall,
            report.negatives.is_some(),
            report.min_confidence,
            title,
        ),
    ];
    let scenes = scene_groups(&report.map_positions_m, &report.per_query);
    for (scene, (db, queries)) in scenes.iter().take(MAX_MAP_SCENES) {
        figures.push(scene_figure(scene, db, queries));
    }
    let mut files = Vec::new();
    for fig in &figures {
        files.extend(save(dir, fig)?);
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

/// The ground plane of a world whose up axis is `up` (`y` or `z`): the other two axes.
pub fn ground_of(up: &str) -> (usize, usize) {
    if up.eq_ignore_ascii_case("z") {
        (0, 1)
    } else {
        (0, 2)
    }
}

/// A class of checked frames: legend text, colour, and which errors (`None`: not localized) it holds.
/// A checked frame: recorded position, position error when LOCALIZED, and whether the map's
/// surfaces leave its view unexplained (outside the mapped area).
pub type CheckedPoint = ([f64; 3], Option<f64>, bool);

type CheckClass = (&'static str, RGBColor, fn(&CheckedPoint) -> bool);

/// `map_check`: see [`check_plot`].
fn check_figure(
    map: &[[f64; 3]],
    frames: &[CheckedPoint],
    ground: (usize, usize),
    title: &str,
) -> Figure {
    let all: Vec<[f64; 3]> = map
        .iter()
        .copied()
        .chain(frames.iter().map(|f| f.0))
        .collect();
    let classes: [CheckClass; 5] = [
        ("within 0.25 m", RGBColor(0, 150, 60), |f| {
            f.1.is_some_and(|e| e <= 0.25)
        }),
        ("0.25-1 m off", RGBColor(230, 140, 0), |f| {
            f.1.is_some_and(|e| e > 0.25 && e <= 1.0)
        }),
        ("more than 1 m off", RED, |f| f.1.is_some_and(|e| e > 1.0)),
        (
            "not localized (drive here again)",
            RGBColor(120, 0, 160),
            |f| f.1.is_none() && !f.2,
        ),
        (
            "not localized, outside the map (the map never saw this view)",
            RGBColor(60, 150, 230),
            |f| f.1.is_none() && f.2,
        ),
    ];
    let mut series = vec![Series::labelled(
        "map images",
        BLACK.mix(0.4),
        Mark::Square(0.04),
        on_ground(map, ground),
    )];
    for (label, colour, pick) in classes {
        let at = on_ground(frames.iter().filter(|f| pick(f)).map(|f| &f.0), ground);
        series.push(Series::labelled(
            format!("{label}: {}", at.len()),
            colour,
            Mark::Dot(3),
            at,
        ));
    }
    Figure::top_down("map_check".into(), (title.into(), 16), &all, ground, series)
}

/// Write `map_check.png` / `.svg` into `dir`: the map's camera positions from above (ground plane
/// `ground`, indices of x, y, z) and each checked frame at its recorded position, coloured by how far
/// its answer was off (`None`: not localized; grey where the map's surfaces do not explain the view,
/// a part the map does not cover), so a team sees where to drive again.
pub fn check_plot(
    map: &[[f64; 3]],
    frames: &[CheckedPoint],
    ground: (usize, usize),
    dir: &Path,
    title: &str,
) -> Result<Vec<PathBuf>> {
    save(dir, &check_figure(map, frames, ground, title))
}

/// `trajectory`: see [`trajectory_plot`].
fn trajectory_figure(
    map: &[[f64; 3]],
    truth: &[[f64; 3]],
    estimate: &[[f64; 3]],
    title: &str,
) -> Figure {
    let all: Vec<[f64; 3]> = map.iter().chain(truth).chain(estimate).copied().collect();
    let ground = ground_axes(if map.len() >= 3 { map } else { &all });
    let mut series = Vec::new();
    if !map.is_empty() {
        series.push(Series::labelled(
            "map images (database cameras)",
            BLACK.mix(0.5),
            Mark::Square(0.06),
            on_ground(map, ground),
        ));
    }
    series.push(Series::labelled(
        "ground truth",
        RGBColor(0, 150, 60),
        Mark::Line(3),
        on_ground(truth, ground),
    ));
    series.push(Series::labelled(
        "LOCALIZED answers",
        BLUE,
        Mark::Dot(2),
        on_ground(estimate, ground),
    ));
    Figure::top_down(
        "trajectory".into(),
        (title.into(), 16),
        &all,
        ground,
        series,
    )
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
    save(dir, &trajectory_figure(map, truth, estimate, title))
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

/// `bench_sweep`: throughput (left, failed levels crossed) and latency percentiles (right) against
/// concurrency.
fn sweep_figure(points: &[SweepPoint], title: &str) -> Figure {
    let c_max = points.iter().map(|p| p.concurrency).max().unwrap_or(1) as f64;
    let x = || Axis::linear("concurrent clients", 0.0, c_max * 1.05 + 0.5);
    let along = |f: fn(&SweepPoint) -> f64, keep: fn(&SweepPoint) -> bool| -> Vec<(f64, f64)> {
        points
            .iter()
            .filter(|p| keep(p))
            .map(|p| (p.concurrency as f64, f(p)))
            .collect()
    };
    let fps = along(|p| p.fps, |_| true);
    let fps_max = points.iter().map(|p| p.fps).fold(0.0, f64::max).max(1.0) * 1.1;
    let lat_max = points.iter().map(|p| p.p99_ms).fold(0.0, f64::max).max(1.0) * 1.1;
    let throughput = vec![
        Series::plain(BLUE, Mark::Line(2), fps.clone()),
        Series::plain(BLUE, Mark::Dot(4), fps),
        Series::plain(RED, Mark::Cross(7), along(|p| p.fps, |p| p.errors > 0)),
    ];
    let latency = [
        (
            "p50",
            (|p| p.p50_ms) as fn(&SweepPoint) -> f64,
            RGBColor(0, 140, 60),
        ),
        ("p90", |p| p.p90_ms, RGBColor(230, 120, 0)),
        ("p99", |p| p.p99_ms, RED),
    ]
    .into_iter()
    .map(|(label, f, colour)| Series::labelled(label, colour, Mark::Line(2), along(f, |_| true)))
    .collect();
    Figure::charts(
        "bench_sweep",
        title,
        vec![
            Panel::chart(
                x(),
                Axis::linear("frames per second", 0.0, fps_max),
                throughput,
            ),
            Panel::chart(x(), Axis::linear("latency (ms)", 0.0, lat_max), latency),
        ],
    )
}

/// Write `bench_sweep.png` / `.svg` (throughput and latency against concurrency) into `dir`.
pub fn bench_plot(points: &[SweepPoint], dir: &Path, title: &str) -> Result<Vec<PathBuf>> {
    save(dir, &sweep_figure(points, title))
}

/// One memory reading of a soak: minutes since the start, the load phase it fell in, and the
/// server's resident memory and live heap, MB.
#[derive(Debug, Clone)]
pub struct SoakPoint {
    /// Minutes since the soak started.
    pub minutes: f64,
    /// The phase's name (`single`, `streams`, `churn`, `replace`).
    pub phase: String,
    /// Resident memory, MB.
    pub rss_mb: f64,
    /// Live heap (glibc's allocated bytes), MB; NaN when the server does not export it.
    pub heap_mb: f64,
}

/// `soak_memory`: resident memory (left) and live heap (right) against time, one colour a phase.
fn soak_figure(points: &[SoakPoint], title: &str) -> Figure {
    let t_max = points
        .iter()
        .map(|p| p.minutes)
        .fold(0.0, f64::max)
        .max(1.0);
    let x = || Axis::linear("minutes", 0.0, t_max * 1.02);
    let colours = [
        BLUE,
        RGBColor(230, 120, 0),
        RGBColor(0, 140, 60),
        RED,
        MAGENTA,
    ];
    let mut phases: Vec<&str> = Vec::new();
    for p in points {
        if !phases.contains(&p.phase.as_str()) {
            phases.push(&p.phase);
        }
    }
    let panel = |desc: &str, f: fn(&SoakPoint) -> f64| {
        let finite: Vec<f64> = points.iter().map(f).filter(|v| v.is_finite()).collect();
        let hi = finite.iter().copied().fold(0.0, f64::max).max(1.0) * 1.1;
        let series = phases
            .iter()
            .enumerate()
            .map(|(i, phase)| {
                let along = points
                    .iter()
                    .filter(|p| p.phase == *phase && f(p).is_finite())
                    .map(|p| (p.minutes, f(p)))
                    .collect();
                Series::labelled(*phase, colours[i % colours.len()], Mark::Line(2), along)
            })
            .collect();
        Panel::chart(x(), Axis::linear(desc, 0.0, hi), series)
    };
    Figure::charts(
        "soak_memory",
        title,
        vec![
            panel("resident memory (MB)", |p| p.rss_mb),
            panel("live heap (MB)", |p| p.heap_mb),
        ],
    )
}

/// Write `soak_memory.png` / `.svg` (the server's memory against time through a soak) into `dir`.
pub fn soak_plot(points: &[SoakPoint], dir: &Path, title: &str) -> Result<Vec<PathBuf>> {
    save(dir, &soak_figure(points, title))
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

    #[test]
    fn segments_meet_a_rectangle_only_where_they_cross_it() {
        let r = Rect::at((10, 10), (10, 10));
        assert!(r.meets((15, 15), (15, 15)));
        assert!(r.meets((0, 0), (30, 30)));
        assert!(r.meets((15, 0), (15, 30)));
        assert!(!r.meets((0, 0), (5, 30)));
        assert!(!r.meets((0, 25), (25, 25)));
        assert!(!r.meets((0, 15), (9, 15)));
        assert!(!r.meets((0, 12), (12, 0)));
    }

    #[test]
    fn legend_entries_flow_into_rows_that_fit() {
        let texts = [(100, 14), (100, 14), (100, 14)];
        let column = legend_layout(&texts, 0);
        assert_eq!(column.at.len(), 3);
        assert!(column.at.iter().all(|a| a.0 == LEGEND_PAD));
        assert_eq!(column.size.1, 2 * LEGEND_PAD + 3 * column.row_h - ROW_GAP);
        let entry = ICON_W + ICON_GAP + 100;
        let two_a_row = legend_layout(&texts, 2 * entry + ENTRY_GAP + 2 * LEGEND_PAD);
        assert_eq!(
            two_a_row.at[1],
            (LEGEND_PAD + entry + ENTRY_GAP, LEGEND_PAD)
        );
        assert_eq!(two_a_row.at[2], (LEGEND_PAD, LEGEND_PAD + two_a_row.row_h));
        assert_eq!(two_a_row.size.0, 2 * entry + ENTRY_GAP + 2 * LEGEND_PAD);
    }

    /// Lay out `fig` (into an SVG held in memory) and check that every legend lies inside the
    /// picture and clear of every plotted point and line, sampled pixel by pixel.
    fn check_legends(fig: &Figure) -> Vec<Placed> {
        register_font();
        let mut svg = String::new();
        let placed = {
            let root = SVGBackend::with_string(&mut svg, fig.size).into_drawing_area();
            let placed = draw_figure(&root, fig).unwrap();
            root.present().unwrap();
            placed
        };
        let picture = Rect::at((0, 0), (fig.size.0 as i32 - 1, fig.size.1 as i32 - 1));
        for p in &placed {
            let Some(legend) = p.legend else { continue };
            assert!(picture.contains(legend), "{}: {legend:?}", fig.name);
            for ink in &p.ink {
                let steps = (ink.b.0 - ink.a.0)
                    .abs()
                    .max((ink.b.1 - ink.a.1).abs())
                    .max(1);
                for k in 0..=steps {
                    let t = f64::from(k) / f64::from(steps);
                    let at = (
                        ink.a.0 + (t * f64::from(ink.b.0 - ink.a.0)).round() as i32,
                        ink.a.1 + (t * f64::from(ink.b.1 - ink.a.1)).round() as i32,
                    );
                    assert!(
                        !legend.grown(ink.reach).meets(at, at),
                        "{}: the legend {legend:?} covers data at {at:?}",
                        fig.name
                    );
                }
            }
        }
        for label in fig
            .panels
            .iter()
            .flat_map(|p| &p.series)
            .filter_map(|s| s.label.as_deref())
        {
            assert!(svg.contains(label), "{}: {label}", fig.name);
        }
        placed
    }

    /// A map panel with `series` over the square -5..5 m.
    fn map_figure(series: Vec<Series>) -> Figure {
        Figure {
            name: "test".into(),
            size: MAP_SIZE,
            title: "test".into(),
            title_font: 16,
            panels: vec![Panel::map(
                (
                    Axis::linear("x (m)", -5.0, 5.0),
                    Axis::linear("z (m)", -5.0, 5.0),
                ),
                series,
            )],
        }
    }

    #[test]
    fn a_legend_leaves_data_in_every_corner_uncovered() {
        let corners = vec![
            (-4.9, -4.9),
            (-4.9, 4.9),
            (4.9, -4.9),
            (4.9, 4.9),
            (0.0, 0.0),
        ];
        let fig = map_figure(vec![
            Series::labelled("database cameras", BLACK, Mark::Square(0.06), corners),
            Series::labelled("queries", BLUE, Mark::Dot(4), vec![(1.0, 1.0)]),
        ]);
        let placed = check_legends(&fig);
        let (plot, legend) = (placed[0].plot, placed[0].legend.unwrap());
        // No corner is free: the legend goes below the plotting area.
        assert!(legend.y0 > plot.y1, "{legend:?} {plot:?}");
        // The map keeps equal scales though the band took height from it.
        let ink = &placed[0].ink;
        let (lo, hi) = (ink[0].a, ink[3].a);
        assert!(((hi.0 - lo.0) - (lo.1 - hi.1)).abs() <= 1, "{lo:?} {hi:?}");
    }

    #[test]
    fn a_free_corner_takes_the_legend_and_a_line_through_it_does_not() {
        // Data only in the lower half: the legend sits in the upper left corner.
        let low = vec![(-4.9, -4.9), (4.9, -4.9), (0.0, -1.0)];
        let cameras = Series::labelled("cameras", RED, Mark::Dot(3), low);
        let (plot, legend) = legend_inside(&map_figure(vec![cameras.clone()]));
        assert!(
            legend.x0 - plot.x0 < 20 && legend.y0 - plot.y0 < 20,
            "{legend:?}"
        );
        // A path through the upper left corner (no point of it there) moves it to the upper right.
        let path = vec![(-5.0, 4.0), (-4.0, 5.0)];
        let path = Series::labelled("path", BLUE, Mark::Line(3), path);
        let (plot, legend) = legend_inside(&map_figure(vec![cameras, path]));
        assert!(
            plot.x1 - legend.x1 < 20 && legend.y0 - plot.y0 < 20,
            "{legend:?}"
        );
    }

    /// The plotting area and the legend box of the one panel of `fig`, checking that the legend
    /// lies inside the plotting area.
    fn legend_inside(fig: &Figure) -> (Rect, Rect) {
        let placed = check_legends(fig);
        let (plot, legend) = (placed[0].plot, placed[0].legend.unwrap());
        assert!(plot.contains(legend), "{legend:?} {plot:?}");
        (plot, legend)
    }

    /// A query's outcome at `p` with `error` (also the estimate's) and the estimate at `at`.
    fn outcome(
        id: &str,
        p: [f64; 3],
        error: Option<(f64, f64)>,
        at: Option<[f64; 3]>,
    ) -> QueryOutcome {
        QueryOutcome {
            id: id.to_string(),
            position_m: p,
            world_from_camera: [p[0], p[1], p[2], 0.0, 0.0, 0.0, 1.0],
            estimate_world_from_camera: at.map(|a| [a[0], a[1], a[2], 0.0, 0.0, 0.0, 1.0]),
            error,
            estimate_error: error,
            estimate_offset_camera_m: None,
            retrieval_error: None,
            confidence: 0.5,
            right_point_rank: None,
            reason: None,
        }
    }

    #[test]
    fn a_map_from_recordings_is_drawn_on_the_queries_scene() {
        let query = |id: &str| outcome(id, [0.0; 3], None, None);
        let queries = vec![query("synth000/point0/q0"), query("synth001/point0/q0")];
        // A map from a recording: its images have no scene; the queries' scene's picture shows
        // them, and no picture is made for the empty name.
        let recorded = vec![
            (String::new(), [1.0, 1.5, 2.0]),
            (String::new(), [2.0, 1.5, 2.0]),
        ];
        let groups = scene_groups(&recorded, &queries[..1]);
        assert_eq!(groups.keys().copied().collect::<Vec<_>>(), ["synth000"]);
        assert_eq!(groups["synth000"].0.len(), 2);
        assert_eq!(groups["synth000"].1.len(), 1);
        // Queries of two scenes: which one the recording covers is not known.
        let groups = scene_groups(&recorded, &queries);
        assert_eq!(
            groups.keys().copied().collect::<Vec<_>>(),
            [RECORDED_MAP, "synth000", "synth001"]
        );
        assert_eq!(groups[RECORDED_MAP].0.len(), 2);
        assert!(groups["synth000"].0.is_empty() && groups["synth001"].0.is_empty());
        // The dataset's own views stay with their scene.
        let views = vec![("synth001".to_string(), [5.0, 1.5, 5.0])];
        let groups = scene_groups(&views, &queries);
        assert!(groups["synth000"].0.is_empty());
        assert_eq!(groups["synth001"].0, vec![[5.0, 1.5, 5.0]]);
    }

    #[test]
    fn scene_maps_join_each_wrong_answer_to_where_it_put_the_camera() {
        let query = |id: &str, p: [f64; 3], e: (f64, f64), at: [f64; 3]| {
            outcome(&format!("scene/{id}"), p, Some(e), Some(at))
        };
        let db: Vec<[f64; 3]> = (0..4).map(|i| [f64::from(i), 1.5, 0.0]).collect();
        let right = query("q0", [1.0, 1.5, 1.0], (0.01, 0.2), [1.01, 1.5, 1.0]);
        let wrong = query("q1", [2.0, 1.5, 1.0], (6.0, 90.0), [8.0, 1.5, 3.0]);
        let lines = |fig: &Figure| -> Vec<Vec<(f64, f64)>> {
            fig.panels[0]
                .series
                .iter()
                .filter(|s| s.label.is_none() && matches!(s.mark, Mark::Line(_)))
                .map(|s| s.points.clone())
                .collect()
        };
        let labelled = |fig: &Figure, label: &str| {
            fig.panels[0]
                .series
                .iter()
                .find(|s| s.label.as_deref() == Some(label))
                .map(|s| s.points.clone())
        };
        // Ground plane (x, z): the wrong answer's line runs from (2, 1) to (8, 3).
        let fig = scene_figure("scene", &db, &[&right, &wrong]);
        assert_eq!(lines(&fig), vec![vec![(2.0, 1.0), (8.0, 3.0)]]);
        // The picture reaches where the wrong answer put the camera (the cameras end at x = 3).
        assert!(fig.panels[0].x.hi >= 8.0, "{:?}", fig.panels[0].x.hi);
        assert_eq!(labelled(&fig, WRONG_ESTIMATES), Some(vec![(8.0, 3.0)]));
        // No wrong answer, nothing drawn for them.
        let fig = scene_figure("scene", &db, &[&right]);
        assert!(lines(&fig).is_empty());
        assert_eq!(labelled(&fig, WRONG_ESTIMATES), None);
    }

    #[test]
    fn no_picture_puts_a_legend_over_its_data() {
        let query = |id: &str, p: [f64; 3], e: Option<(f64, f64)>| QueryOutcome {
            retrieval_error: e.map(|(t, r)| (2.0 * t, 2.0 * r)),
            ..outcome(&format!("scene/{id}"), p, e, None)
        };
        let queries: Vec<QueryOutcome> = (0..40)
            .map(|i| {
                let f = f64::from(i);
                let e = (i % 5 != 0).then_some((0.02 * f, 0.3 * f));
                let mut q = query(&format!("q{i}"), [f % 7.0, 1.5, (f * 0.37) % 5.0], e);
                // The wrong answers (beyond 1 m or 10 deg) put the camera 2 m along x.
                let p = q.position_m;
                q.estimate_world_from_camera = Some([p[0] + 2.0, p[1], p[2], 0.0, 0.0, 0.0, 1.0]);
                q
            })
            .collect();
        let db: Vec<[f64; 3]> = (0..30)
            .map(|i| [f64::from(i % 6), 1.5, f64::from(i / 6)])
            .collect();
        let curve: Vec<CurvePoint> = (0..=20)
            .map(|i| {
                let t = f64::from(i) / 20.0;
                CurvePoint {
                    threshold: t,
                    precision_1m_10deg: 0.6 + 0.4 * t,
                    recall_1m_10deg: 0.9 * (1.0 - t),
                    recall_0_25m_2deg: 0.5 * (1.0 - t),
                    false_positive_rate: 0.3 * (1.0 - t),
                    ..CurvePoint::default()
                }
            })
            .collect();
        let path: Vec<[f64; 3]> = (0..100)
            .map(|i| {
                let a = f64::from(i) * 0.0628;
                [3.0 * a.cos(), 4.0 * a.sin(), 1.5]
            })
            .collect();
        let sweep: Vec<SweepPoint> = [1usize, 2, 4, 8]
            .into_iter()
            .map(|c| SweepPoint {
                concurrency: c,
                fps: 10.0 * c as f64,
                p50_ms: 20.0 * c as f64,
                p90_ms: 30.0 * c as f64,
                p99_ms: 40.0 * c as f64,
                errors: usize::from(c == 8),
            })
            .collect();
        let frames: Vec<CheckedPoint> = path
            .iter()
            .enumerate()
            .map(|(i, p)| {
                (
                    *p,
                    (i % 7 != 0).then_some(0.1 * (i % 15) as f64),
                    i % 14 == 0,
                )
            })
            .collect();
        let refs: Vec<&QueryOutcome> = queries.iter().collect();
        for fig in [
            cdf_figure(&queries, "cdf"),
            precision_recall_figure(&curve, true, 0.4, "pr"),
            scene_figure("scene", &db, &refs),
            check_figure(&path, &frames, (0, 1), "check"),
            trajectory_figure(&path, &path, &path[..50], "trajectory"),
            sweep_figure(&sweep, "sweep"),
        ] {
            let placed = check_legends(&fig);
            assert_eq!(placed.len(), fig.panels.len(), "{}", fig.name);
            for (p, panel) in placed.iter().zip(&fig.panels) {
                let labelled = panel.series.iter().any(|s| s.label.is_some());
                assert_eq!(p.legend.is_some(), labelled, "{}", fig.name);
            }
        }
    }
}
