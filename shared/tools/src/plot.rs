//! Plotting of run traces and latency distributions (PNG + SVG via `plotters`).
//!
//! Every figure is first described backend-independently (a figure made of stacked
//! panels, each holding line series, dashed horizontal reference lines and shaded
//! time windows) and then rendered by one generic drawing routine on both a
//! `BitMapBackend` (PNG) and an `SVGBackend` (SVG).
//!
//! Long series are decimated by min/max bucketing before drawing (at most about
//! [`MAX_POINTS_PER_SERIES`] points per series), which keeps spikes and the global extrema
//! visible while keeping 10⁶-row traces cheap to draw. Non-finite samples are dropped.
#![forbid(unsafe_code)]

use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use plotters::coord::ranged1d::{DefaultFormatting, KeyPointHint, Ranged};
use plotters::coord::Shift;
use plotters::element::DashedPathElement;
use plotters::prelude::*;

use drivelab_runtime::trace::TraceRow;

/// Pixel size of every figure (PNG) and its SVG viewport.
const FIGURE_SIZE: (u32, u32) = (1200, 700);

/// Upper bound (approximately) on the number of points drawn per series.
pub const MAX_POINTS_PER_SERIES: usize = 4000;

/// True: this build draws figures (cargo feature `plot`).
pub const AVAILABLE: bool = true;

const FONT: &str = "sans-serif";
const TITLE_FONT_PX: u32 = 28;
const AXIS_DESC_FONT_PX: u32 = 20;
const TICK_FONT_PX: u32 = 16;
const LEGEND_FONT_PX: u32 = 16;
const ANNOTATION_FONT_PX: u32 = 15;

/// Tableau-10 palette, used in order by [`plot_lines`] and [`plot_percentiles`].
const PALETTE: [RGBColor; 10] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
];
const C_BLUE: RGBColor = PALETTE[0];
const C_ORANGE: RGBColor = PALETTE[1];
const C_GREEN: RGBColor = PALETTE[2];
const C_RED: RGBColor = PALETTE[3];
const C_GRAY: RGBColor = PALETTE[7];
const C_REF: RGBColor = RGBColor(20, 20, 20);
const C_LIMIT: RGBColor = RGBColor(90, 90, 90);
const C_SHADE_TEXT: RGBColor = RGBColor(160, 20, 20);

// ---------------------------------------------------------------------------------------------
// Public API
// ---------------------------------------------------------------------------------------------

pub use crate::plot_options::{PercentileSeries, TraceFigureOptions};

/// Draws the trace figures into `out_dir` (created if missing), each as `.png` and `.svg`:
///
/// * `speed`: ω_ref (dashed), ω_m and ω̂ in rad/s (mechanical) vs t in ms, with the load
///   torque T_load in N·m as a second, smaller panel underneath;
/// * `currents`: i_d_ref, i_d, i_q_ref, i_q in A vs t in ms (references dashed), plus
///   ±[`TraceFigureOptions::current_limit_a`] (the speed loop's i_q* limit) as dashed lines;
/// * `voltages`: u_d, u_q in V vs t in ms, plus |u| and ±[`TraceFigureOptions::voltage_limit_v`]
///   as dashed lines when a voltage limit is given.
///
/// [`TraceFigureOptions::shaded_windows`] are shaded on every panel. Series that have no
/// finite sample are left out; a figure (or the load panel) with no drawable series at all
/// is skipped. Returns the list of files written.
///
/// # Errors
/// If `rows` is empty, the window is invalid or contains no rows, no figure has any finite
/// data, or a file cannot be written.
pub fn plot_trace(
    rows: &[TraceRow],
    out_dir: &Path,
    opts: &TraceFigureOptions,
) -> Result<Vec<PathBuf>> {
    if rows.is_empty() {
        bail!("plot_trace: the trace is empty (no rows)");
    }
    let rows: Vec<&TraceRow> = match opts.window_s {
        None => rows.iter().collect(),
        Some((t0, t1)) => {
            if !(t0.is_finite() && t1.is_finite() && t0 <= t1) {
                bail!("plot_trace: invalid time window [{t0}, {t1}] s");
            }
            rows.iter().filter(|r| r.t >= t0 && r.t <= t1).collect()
        }
    };
    if rows.is_empty() {
        bail!(
            "plot_trace: no trace rows inside the window {:?} s",
            opts.window_s.unwrap_or_default()
        );
    }
    std::fs::create_dir_all(out_dir)
        .with_context(|| format!("cannot create output directory {}", out_dir.display()))?;

    // One trace series: y = f(row) against t in ms.
    let trace_series = |label: &str, f: fn(&TraceRow) -> f64, color: RGBColor, style: Line| {
        Series::new(label, rows.iter().map(|r| (r.t * 1e3, f(r))), color, style)
    };
    let finite: Vec<(f64, f64, String)> = opts
        .shaded_windows
        .iter()
        .filter(|(a, b, _)| a.is_finite() && b.is_finite())
        .cloned()
        .collect();
    let (numbered, legend) = numbered_windows(&finite);
    let shades: Vec<Shade> = numbered
        .iter()
        .map(|(a, b, label)| Shade {
            x0: a.min(*b) * 1e3,
            x1: a.max(*b) * 1e3,
            label: label.clone(),
        })
        .collect();
    let panel = |y_label: &str, series: Vec<Series>, hlines: Vec<HLine>| {
        Panel::new("t [ms]", y_label, series)
            .with_hlines(hlines)
            .with_shades(shades.clone())
    };
    let title = |what: &str| {
        if opts.title.is_empty() {
            what.to_string()
        } else {
            format!("{} — {what}", opts.title)
        }
    };

    let speed = panel(
        "ω [rad/s]",
        vec![
            trace_series("ω_ref", |r| r.omega_ref, C_REF, Line::Dashed(2)),
            trace_series("ω_m", |r| r.omega_m, C_BLUE, Line::Solid(2)),
            trace_series("ω̂ (observer)", |r| r.omega_hat, C_ORANGE, Line::Solid(1)),
        ],
        vec![],
    );
    let load = panel(
        "T_load [N·m]",
        vec![trace_series(
            "T_load",
            |r| r.t_load,
            C_GREEN,
            Line::Solid(2),
        )],
        vec![],
    );
    let currents = panel(
        "i [A]",
        vec![
            trace_series("i_d_ref", |r| r.i_d_ref, C_BLUE, Line::Dashed(2)),
            trace_series("i_d", |r| r.i_d, C_BLUE, Line::Solid(1)),
            trace_series("i_q_ref", |r| r.i_q_ref, C_RED, Line::Dashed(2)),
            trace_series("i_q", |r| r.i_q, C_RED, Line::Solid(1)),
        ],
        symmetric_limit(opts.current_limit_a, "i_q,max", "A"),
    );
    let mut voltage_series = vec![
        trace_series("u_d", |r| r.u_d, C_BLUE, Line::Solid(1)),
        trace_series("u_q", |r| r.u_q, C_RED, Line::Solid(1)),
    ];
    if opts.voltage_limit_v.is_some() {
        voltage_series.push(trace_series(
            "|u|",
            |r| r.u_d.hypot(r.u_q),
            C_GRAY,
            Line::Solid(1),
        ));
    }
    let voltages = panel(
        "u [V]",
        voltage_series,
        symmetric_limit(opts.voltage_limit_v, "u_max", "V"),
    );

    // Speed panel on top (70 %), load panel below (30 %) when it has data.
    let mut speed_panels = Vec::new();
    if speed.has_data() {
        speed_panels.push((speed, 7));
    }
    if load.has_data() {
        speed_panels.push((load, 3));
    }
    let figures = [
        ("speed", title("speed"), speed_panels),
        ("currents", title("dq currents"), vec![(currents, 1)]),
        ("voltages", title("dq voltages"), vec![(voltages, 1)]),
    ];

    let mut written = Vec::new();
    let mut skipped = Vec::new();
    for (stem, title, panels) in figures {
        let panels: Vec<(Panel, u32)> = panels.into_iter().filter(|(p, _)| p.has_data()).collect();
        if panels.is_empty() {
            skipped.push(stem);
            continue;
        }
        let fig = Figure {
            title,
            panels,
            footer: legend.clone(),
        };
        written.extend(render(&fig, &out_dir.join(stem))?);
    }
    if written.is_empty() {
        bail!(
            "plot_trace: no finite samples to draw in any figure (skipped: {})",
            skipped.join(", ")
        );
    }
    Ok(written)
}

/// HdrHistogram-style percentile plot: x axis is "percentile" on a log scale of 1/(1-q)
/// (ticks labelled 0%, 90%, 99%, 99.9%, 99.99%, 99.999%), y axis latency in µs (linear, or log
/// if `log_y`). All series on one chart with a legend. An optional horizontal dashed budget
/// line (e.g. the sample time Ts in µs) with label. Writes `path_stem`.png and `path_stem`.svg.
///
/// Points with a percentile outside [0, 100), a non-finite value, or (with `log_y`) a
/// non-positive value are ignored; series left without points are skipped. The `.png` /
/// `.svg` suffix is appended to `path_stem` (an existing extension is kept). Returns the two
/// paths written.
///
/// # Errors
/// If there is no series with at least one usable point, or a file cannot be written.
pub fn plot_percentiles(
    series: &[PercentileSeries],
    title: &str,
    budget_us: Option<(f64, String)>,
    log_y: bool,
    path_stem: &Path,
) -> Result<Vec<PathBuf>> {
    if series.is_empty() {
        bail!("plot_percentiles: no series given");
    }
    let lines = series
        .iter()
        .enumerate()
        .map(|(i, (label, pts))| {
            let mut pts: Vec<(f64, f64)> = pts
                .iter()
                .filter(|(p, _)| (0.0..100.0).contains(p))
                .map(|&(p, v)| (percentile_to_nines(p), v))
                .collect();
            pts.sort_by(|a, b| a.0.total_cmp(&b.0));
            Series::new(label, pts, PALETTE[i % PALETTE.len()], Line::Solid(2))
        })
        .collect();
    let budget = budget_us
        .map(|(y, label)| HLine {
            y,
            label: Some(label),
            color: C_RED,
        })
        .into_iter()
        .collect();
    let mut panel = Panel::new("percentile", "latency [µs]", lines).with_hlines(budget);
    panel.x_kind = AxisKind::Nines;
    panel.y_kind = if log_y {
        AxisKind::Log
    } else {
        AxisKind::Linear
    };
    panel.y_from_zero = !log_y;
    if !panel.has_data() {
        bail!(
            "plot_percentiles: none of the {} series has a usable point",
            series.len()
        );
    }
    render(&Figure::single(title, panel), path_stem)
}

/// Simple multi-series x/y line chart helper for comparisons (e.g. several runs' speeds on one
/// axes): each series (label, points (x,y)). Writes path_stem.png and .svg.
///
/// `hlines` are drawn as labelled dashed horizontal lines. Non-finite points are ignored and
/// series left without points are skipped; points are drawn in the given order. Returns the
/// two paths written.
///
/// # Errors
/// If there is no series with at least one finite point, or a file cannot be written.
pub fn plot_lines(
    series: &[(String, Vec<(f64, f64)>)],
    title: &str,
    x_label: &str,
    y_label: &str,
    hlines: &[(f64, String)],
    path_stem: &Path,
) -> Result<Vec<PathBuf>> {
    if series.is_empty() {
        bail!("plot_lines: no series given");
    }
    let lines = series
        .iter()
        .enumerate()
        .map(|(i, (label, pts))| {
            Series::new(
                label,
                pts.iter().copied(),
                PALETTE[i % PALETTE.len()],
                Line::Solid(2),
            )
        })
        .collect();
    let hlines = hlines
        .iter()
        .enumerate()
        .map(|(i, (y, label))| HLine {
            y: *y,
            label: Some(label.clone()),
            color: if i == 0 {
                C_LIMIT
            } else {
                PALETTE[(i + 3) % PALETTE.len()]
            },
        })
        .collect();
    let panel = Panel::new(x_label, y_label, lines).with_hlines(hlines);
    if !panel.has_data() {
        bail!(
            "plot_lines: none of the {} series has a finite point",
            series.len()
        );
    }
    render(&Figure::single(title, panel), path_stem)
}

/// Min/max decimation for drawing: drops non-finite points, then, if more than `max_points`
/// remain, splits them (in order) into `max_points / 2` buckets and keeps from each bucket the
/// points with the smallest and largest y (in their original order), plus the very first and
/// last point. The global minimum and maximum of y are therefore always kept, and so are
/// single-sample spikes. `max_points` is clamped to at least 4.
pub fn decimate_min_max(points: &[(f64, f64)], max_points: usize) -> Vec<(f64, f64)> {
    decimate_finite(
        points.iter().copied().filter(is_finite_point).collect(),
        max_points,
    )
}

// ---------------------------------------------------------------------------------------------
// Figure description
// ---------------------------------------------------------------------------------------------

/// Line style of a series: solid or dashed, with a stroke width in pixels.
#[derive(Debug, Clone, Copy)]
enum Line {
    Solid(u32),
    Dashed(u32),
}

/// A labelled, already filtered and decimated polyline, in pieces where the data has gaps.
#[derive(Debug, Clone)]
struct Series {
    label: String,
    points: Vec<(f64, f64)>,
    /// Where each piece starts in `points` (the first at 0).
    starts: Vec<usize>,
    color: RGBColor,
    line: Line,
}

impl Series {
    /// Drops non-finite points and decimates to [`MAX_POINTS_PER_SERIES`]. A non-finite
    /// point is a gap in the data (a value no stage had: NaN): the line stops before it and
    /// starts again after it, rather than drawing values that never were across it.
    fn new(
        label: &str,
        points: impl IntoIterator<Item = (f64, f64)>,
        color: RGBColor,
        line: Line,
    ) -> Self {
        let mut pieces: Vec<Vec<(f64, f64)>> = vec![Vec::new()];
        for p in points {
            match pieces.last_mut() {
                Some(piece) if is_finite_point(&p) => piece.push(p),
                Some(piece) if !piece.is_empty() => pieces.push(Vec::new()),
                _ => {}
            }
        }
        let total: usize = pieces.iter().map(Vec::len).sum();
        let (mut all, mut starts) = (Vec::new(), Vec::new());
        for piece in pieces.into_iter().filter(|p| !p.is_empty()) {
            // Each piece its share of the points.
            let share = (MAX_POINTS_PER_SERIES * piece.len()).div_ceil(total);
            starts.push(all.len());
            all.extend(decimate_finite(piece, share));
        }
        Self {
            label: label.to_string(),
            points: all,
            starts,
            color,
            line,
        }
    }

    /// The pieces of the line, in order.
    fn pieces(&self) -> impl Iterator<Item = &[(f64, f64)]> {
        let ends = self
            .starts
            .iter()
            .skip(1)
            .copied()
            .chain([self.points.len()]);
        self.starts
            .iter()
            .zip(ends)
            .map(|(&a, b)| &self.points[a..b])
    }
}

/// Dashed horizontal reference line across the whole x range.
#[derive(Debug, Clone)]
struct HLine {
    y: f64,
    /// Legend entry; `None` for the second line of a ± pair.
    label: Option<String>,
    color: RGBColor,
}

/// Shaded x interval (light translucent red) with a label at its top-left corner.
#[derive(Debug, Clone)]
struct Shade {
    x0: f64,
    x1: f64,
    label: String,
}

/// How an axis maps values and places/labels its ticks.
#[derive(Debug, Clone, Copy, PartialEq)]
enum AxisKind {
    /// Linear, "nice" 1-2-5 ticks.
    Linear,
    /// Base-10 logarithmic (positive values only).
    Log,
    /// Linear in "nines" n = log10(1/(1-q)); ticks at integers labelled 0%, 90%, 99%, ...
    Nines,
}

/// One chart (one set of axes).
#[derive(Debug, Clone)]
struct Panel {
    x_label: String,
    y_label: String,
    series: Vec<Series>,
    hlines: Vec<HLine>,
    shades: Vec<Shade>,
    x_kind: AxisKind,
    y_kind: AxisKind,
    /// Extend the (linear) y range to include 0.
    y_from_zero: bool,
}

impl Panel {
    fn new(x_label: &str, y_label: &str, series: Vec<Series>) -> Self {
        Self {
            x_label: x_label.to_string(),
            y_label: y_label.to_string(),
            series,
            hlines: Vec::new(),
            shades: Vec::new(),
            x_kind: AxisKind::Linear,
            y_kind: AxisKind::Linear,
            y_from_zero: false,
        }
    }

    fn with_hlines(mut self, hlines: Vec<HLine>) -> Self {
        self.hlines = hlines;
        self
    }

    fn with_shades(mut self, shades: Vec<Shade>) -> Self {
        self.shades = shades;
        self
    }

    /// Points that can be drawn on this panel's axes (log axes need y > 0).
    fn drawable<'a>(&self, s: &'a Series) -> impl Iterator<Item = &'a (f64, f64)> + 'a {
        self.drawable_of(&s.points)
    }

    /// The same of some points.
    fn drawable_of<'a>(
        &self,
        points: &'a [(f64, f64)],
    ) -> impl Iterator<Item = &'a (f64, f64)> + 'a {
        let log_y = self.y_kind == AxisKind::Log;
        points.iter().filter(move |p| !log_y || p.1 > 0.0)
    }

    fn has_data(&self) -> bool {
        self.series
            .iter()
            .any(|s| self.drawable(s).next().is_some())
    }

    /// Computes the axes from the data (reference lines are included in the y range so they
    /// are always visible).
    fn axes(&self) -> Result<(Axis, Axis)> {
        let pts = || self.series.iter().flat_map(|s| self.drawable(s));
        let xs = pts().map(|p| p.0);
        let x = match self.x_kind {
            AxisKind::Nines => {
                let max = xs.fold(0.0_f64, f64::max);
                Axis::new(AxisKind::Nines, 0.0, (max - 1e-9).ceil().max(1.0))
            }
            kind => Axis::from_data(kind, xs, 0.0, false)?,
        };
        let ys = pts()
            .map(|p| p.1)
            .chain(self.hlines.iter().map(|h| h.y).filter(|y| y.is_finite()));
        let y = Axis::from_data(self.y_kind, ys, 0.05, self.y_from_zero)?;
        Ok((x, y))
    }
}

/// Vertically stacked panels under a common title; weights give relative panel heights.
#[derive(Debug, Clone)]
struct Figure {
    title: String,
    panels: Vec<(Panel, u32)>,
    /// Lines of text under the panels (the fault markers' legend).
    footer: Vec<String>,
}

impl Figure {
    fn single(title: &str, panel: Panel) -> Self {
        Self {
            title: title.to_string(),
            panels: vec![(panel, 1)],
            footer: Vec::new(),
        }
    }
}

/// Most legend entries drawn under a figure; the rest are counted.
const LEGEND_MAX: usize = 40;
/// Characters per legend line.
const LEGEND_LINE: usize = 130;

/// Numbers the shaded windows in time order: each window's label becomes its number, and
/// the legend lists `number label @ start`, packed into lines (at most [`LEGEND_MAX`]
/// entries; a last line counts the rest). Many windows then never overlap as text.
pub fn numbered_windows(windows: &[(f64, f64, String)]) -> (Vec<(f64, f64, String)>, Vec<String>) {
    let mut w: Vec<(f64, f64, String)> = windows.to_vec();
    w.sort_by(|a, b| a.0.total_cmp(&b.0));
    let entries: Vec<String> = w
        .iter()
        .enumerate()
        .map(|(i, (a, _, label))| format!("{} {label} @ {a:.3} s", i + 1))
        .collect();
    let mut lines: Vec<String> = Vec::new();
    for e in entries.iter().take(LEGEND_MAX) {
        match lines.last_mut() {
            Some(l) if l.len() + 4 + e.len() <= LEGEND_LINE => {
                l.push_str("  ·  ");
                l.push_str(e);
            }
            _ => lines.push(e.clone()),
        }
    }
    if entries.len() > LEGEND_MAX {
        lines.push(format!(
            "… and {} more (summary.json → faults)",
            entries.len() - LEGEND_MAX
        ));
    }
    let numbered = w
        .into_iter()
        .enumerate()
        .map(|(i, (a, b, _))| (a, b, (i + 1).to_string()))
        .collect();
    (numbered, lines)
}

/// `±limit` as a pair of dashed lines with one legend entry.
fn symmetric_limit(limit: Option<f64>, name: &str, unit: &str) -> Vec<HLine> {
    match limit.filter(|l| l.is_finite()).map(f64::abs) {
        None => Vec::new(),
        Some(l) => vec![
            HLine {
                y: l,
                label: Some(format!("±{name} = {} {unit}", fmt_tick(l))),
                color: C_LIMIT,
            },
            HLine {
                y: -l,
                label: None,
                color: C_LIMIT,
            },
        ],
    }
}

fn is_finite_point(p: &(f64, f64)) -> bool {
    p.0.is_finite() && p.1.is_finite()
}

/// Min/max bucketing of already-finite points, see [`decimate_min_max`].
fn decimate_finite(points: Vec<(f64, f64)>, max_points: usize) -> Vec<(f64, f64)> {
    let max_points = max_points.max(4);
    if points.len() <= max_points {
        return points;
    }
    let bucket = points.len().div_ceil(max_points / 2);
    let n_chunks = points.len().div_ceil(bucket);
    let mut out = Vec::with_capacity(max_points + 2);
    for (c, chunk) in points.chunks(bucket).enumerate() {
        let (mut lo, mut hi) = (0, 0);
        for (i, p) in chunk.iter().enumerate() {
            if p.1 < chunk[lo].1 {
                lo = i;
            }
            if p.1 > chunk[hi].1 {
                hi = i;
            }
        }
        let mut keep = [
            (c == 0).then_some(0),
            Some(lo.min(hi)),
            Some(lo.max(hi)),
            (c + 1 == n_chunks).then_some(chunk.len() - 1),
        ];
        keep.sort_unstable();
        let mut last = None;
        for i in keep.into_iter().flatten() {
            if last != Some(i) {
                out.push(chunk[i]);
                last = Some(i);
            }
        }
    }
    out
}

/// Percentile p in [0, 100) to "nines" log10(1/(1-q)), q = p/100.
fn percentile_to_nines(p: f64) -> f64 {
    -(-p / 100.0).ln_1p() / std::f64::consts::LN_10
}

// ---------------------------------------------------------------------------------------------
// Axis (custom plotters coordinate)
// ---------------------------------------------------------------------------------------------

/// A 1-D plotters coordinate over f64 with our own tick placement (linear, log10 or nines).
#[derive(Debug, Clone)]
struct Axis {
    kind: AxisKind,
    lo: f64,
    hi: f64,
}

impl Axis {
    fn new(kind: AxisKind, lo: f64, hi: f64) -> Self {
        Self { kind, lo, hi }
    }

    /// Range covering `values`, padded by `pad_frac` of the span on both sides (multiplicatively
    /// for log axes); a zero span is always padded so the range is never empty.
    fn from_data(
        kind: AxisKind,
        values: impl Iterator<Item = f64>,
        pad_frac: f64,
        include_zero: bool,
    ) -> Result<Self> {
        let log = kind == AxisKind::Log;
        let (mut lo, mut hi) = values
            .filter(|v| v.is_finite() && (!log || *v > 0.0))
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
                (a.min(v), b.max(v))
            });
        if lo > hi {
            bail!("no finite data to determine the axis range");
        }
        if log {
            let (l, h) = (lo.log10(), hi.log10());
            let pad = if h - l > 1e-9 {
                (h - l) * pad_frac
            } else {
                0.1
            };
            return Ok(Self::new(kind, 10f64.powf(l - pad), 10f64.powf(h + pad)));
        }
        if include_zero {
            lo = lo.min(0.0);
            hi = hi.max(0.0);
        }
        let scale = lo.abs().max(hi.abs());
        let span = hi - lo;
        if !span.is_finite() {
            bail!("data range [{lo}, {hi}] is too large to plot");
        }
        if span <= scale * 1e-12 {
            let pad = if scale > 0.0 { 0.1 * scale } else { 1.0 };
            lo -= pad;
            hi += pad;
        } else {
            let pad = span * pad_frac;
            // Don't push a zero-based range below zero.
            if !(include_zero && lo == 0.0) {
                lo -= pad;
            }
            hi += pad;
        }
        Ok(Self::new(kind, lo, hi))
    }

    /// Value → linear "model" coordinate.
    fn model(&self, v: f64) -> f64 {
        match self.kind {
            AxisKind::Log => v.max(f64::MIN_POSITIVE).log10(),
            AxisKind::Linear | AxisKind::Nines => v,
        }
    }

    /// Position in [0, 1] along the axis (outside for values out of range).
    fn normalized(&self, v: f64) -> f64 {
        let (a, b) = (self.model(self.lo), self.model(self.hi));
        (self.model(v) - a) / (b - a)
    }

    fn contains(&self, v: f64) -> bool {
        v >= self.lo && v <= self.hi
    }

    /// Major ticks (labelled) with at most about `max` entries.
    fn major_ticks(&self, max: usize) -> Vec<f64> {
        match self.kind {
            AxisKind::Linear => nice_ticks(self.lo, self.hi, max).0,
            AxisKind::Nines => int_ticks(self.lo, self.hi, max),
            AxisKind::Log => log_ticks(self.lo, self.hi, max).unwrap_or_else(|| {
                // Less than one usable decade: plain linear ticks look better.
                nice_ticks(self.lo, self.hi, max).0
            }),
        }
    }

    /// Minor grid positions with at most about `max` entries.
    fn minor_ticks(&self, major: usize, max: usize) -> Vec<f64> {
        let ticks = match self.kind {
            AxisKind::Linear => {
                let (_, step) = nice_ticks(self.lo, self.hi, major);
                let mantissa = step / 10f64.powf(step.log10().floor());
                let div = if (mantissa - 2.0).abs() < 0.1 {
                    4.0
                } else {
                    5.0
                };
                step_ticks(self.lo, self.hi, step / div)
            }
            AxisKind::Nines => int_ticks(self.lo, self.hi, usize::MAX)
                .into_iter()
                .flat_map(|n| (1..10).map(move |k| n + f64::from(k).log10()))
                .filter(|v| self.contains(*v))
                .collect(),
            AxisKind::Log => match log_ticks(self.lo, self.hi, major) {
                Some(_) => decade_ticks(self.lo, self.hi, &[1., 2., 3., 4., 5., 6., 7., 8., 9.]),
                None => Vec::new(),
            },
        };
        if ticks.len() > max.max(1) {
            self.major_ticks(major)
        } else {
            ticks
        }
    }

    /// Tick label text.
    fn label(&self, v: f64) -> String {
        match self.kind {
            AxisKind::Linear | AxisKind::Log => fmt_tick(v),
            AxisKind::Nines => {
                let n = v.round();
                if (v - n).abs() > 1e-6 || n < 0.0 {
                    return String::new();
                }
                let q = 100.0 * (1.0 - 10f64.powf(-n));
                format!("{q:.*}%", (n as usize).saturating_sub(2))
            }
        }
    }
}

impl Ranged for Axis {
    type FormatOption = DefaultFormatting;
    type ValueType = f64;

    fn map(&self, value: &f64, limit: (i32, i32)) -> i32 {
        let (p0, p1) = (f64::from(limit.0), f64::from(limit.1));
        let px = p0 + self.normalized(*value) * (p1 - p0);
        // Keep far-off values (should not happen) from producing huge rasterisation work.
        let guard = (p1 - p0).abs() + 1000.0;
        if px.is_nan() {
            return limit.0;
        }
        px.clamp(p0.min(p1) - guard, p0.max(p1) + guard).round() as i32
    }

    fn key_points<H: KeyPointHint>(&self, hint: H) -> Vec<f64> {
        if hint.weight().allow_light_points() {
            self.minor_ticks(hint.bold_points(), hint.max_num_points())
        } else {
            self.major_ticks(hint.max_num_points())
        }
    }

    fn range(&self) -> Range<f64> {
        self.lo..self.hi
    }
}

/// Multiples of `step` within [lo, hi].
fn step_ticks(lo: f64, hi: f64, step: f64) -> Vec<f64> {
    if !(step > 0.0 && step.is_finite()) {
        return Vec::new();
    }
    let (first, last) = ((lo / step).ceil() as i64, (hi / step).floor() as i64);
    if last < first || last - first > 10_000 {
        return Vec::new();
    }
    (first..=last)
        .map(|i| {
            let v = i as f64 * step;
            if v == 0.0 {
                0.0
            } else {
                v
            }
        })
        .collect()
}

/// "Nice" 1-2-5 ticks within [lo, hi], at most `max` of them; returns (ticks, step).
fn nice_ticks(lo: f64, hi: f64, max: usize) -> (Vec<f64>, f64) {
    let span = hi - lo;
    let max = max.max(2);
    if !(span > 0.0 && span.is_finite()) {
        return (Vec::new(), 0.0);
    }
    let mut exp = (span / max as f64).log10().floor();
    loop {
        for m in [1.0, 2.0, 5.0] {
            let step = m * 10f64.powf(exp);
            if (span / step).floor() + 1.0 <= max as f64 {
                return (step_ticks(lo, hi, step), step);
            }
        }
        exp += 1.0;
    }
}

/// Integers within [lo, hi], thinned to at most `max`.
fn int_ticks(lo: f64, hi: f64, max: usize) -> Vec<f64> {
    let all = step_ticks(lo, hi, 1.0);
    let stride = all.len().div_ceil(max.max(1)).max(1);
    all.into_iter().step_by(stride).collect()
}

/// m·10^k for the given mantissas, within [lo, hi] (lo > 0).
fn decade_ticks(lo: f64, hi: f64, mantissas: &[f64]) -> Vec<f64> {
    if !(lo > 0.0 && hi > lo && hi.is_finite()) {
        return Vec::new();
    }
    let (k0, k1) = (lo.log10().floor() as i32, hi.log10().ceil() as i32);
    (k0..=k1)
        .flat_map(|k| mantissas.iter().map(move |m| m * 10f64.powi(k)))
        .filter(|v| *v >= lo * (1.0 - 1e-12) && *v <= hi * (1.0 + 1e-12))
        .collect()
}

/// Log ticks: the coarsest of decades / 1-2-5 / 1..9 per decade giving at least 3 and at
/// most `max` ticks; decades are thinned if there are too many. None if no choice has 3 ticks.
fn log_ticks(lo: f64, hi: f64, max: usize) -> Option<Vec<f64>> {
    let max = max.max(3);
    let sets: [&[f64]; 3] = [
        &[1.0],
        &[1.0, 2.0, 5.0],
        &[1., 2., 3., 4., 5., 6., 7., 8., 9.],
    ];
    let decades = decade_ticks(lo, hi, sets[0]);
    if decades.len() > max {
        let stride = decades.len().div_ceil(max);
        return Some(decades.into_iter().step_by(stride).collect());
    }
    sets.iter()
        .map(|m| decade_ticks(lo, hi, m))
        .find(|t| t.len() >= 3 && t.len() <= max)
}

/// Compact tick/number text: up to 4 decimals without trailing zeros, scientific when tiny
/// or huge.
fn fmt_tick(v: f64) -> String {
    if !v.is_finite() {
        return String::new();
    }
    let a = v.abs();
    if a == 0.0 {
        return "0".to_string();
    }
    if !(1e-3..1e6).contains(&a) {
        return format!("{v:.1e}");
    }
    let s = format!("{v:.4}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" {
        "0".to_string()
    } else {
        s.to_string()
    }
}

// ---------------------------------------------------------------------------------------------
// Rendering (generic over the plotters backend)
// ---------------------------------------------------------------------------------------------

/// Converts plotters' backend-generic errors into anyhow errors with context.
trait PlotErr<T> {
    fn plot_err(self, what: &str) -> Result<T>;
}

impl<T, E: std::fmt::Display> PlotErr<T> for std::result::Result<T, E> {
    fn plot_err(self, what: &str) -> Result<T> {
        self.map_err(|e| anyhow!("plotting failed while {what}: {e}"))
    }
}

/// `stem` + "." + `ext` (keeps any dot already in the stem's file name).
fn with_suffix(stem: &Path, ext: &str) -> PathBuf {
    let mut s = stem.as_os_str().to_owned();
    s.push(".");
    s.push(ext);
    PathBuf::from(s)
}

/// Renders `fig` to `stem`.png and `stem`.svg; on failure removes partial outputs.
fn render(fig: &Figure, stem: &Path) -> Result<Vec<PathBuf>> {
    if stem.file_name().is_none() {
        bail!("invalid output path stem {}", stem.display());
    }
    if let Some(dir) = stem.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("cannot create output directory {}", dir.display()))?;
    }
    let png = with_suffix(stem, "png");
    let svg = with_suffix(stem, "svg");
    let (rgb, svg_text) = in_memory(
        FIGURE_SIZE,
        |root| draw_figure(root, fig),
        |root| draw_figure(root, fig),
    )
    .with_context(|| format!("drawing {}", png.display()))?;
    save(&png, &rgb, FIGURE_SIZE, &svg, &svg_text)?;
    Ok(vec![png, svg])
}

/// A figure of `size` pixels drawn twice in memory, by `bitmap` as RGB bytes and by `vector`
/// as SVG text: the backends' own saving would follow a symbolic link planted in place of
/// the file, so [`save`] writes them instead.
pub(crate) fn in_memory(
    size: (u32, u32),
    bitmap: impl FnOnce(&DrawingArea<BitMapBackend, Shift>) -> Result<()>,
    vector: impl FnOnce(&DrawingArea<SVGBackend, Shift>) -> Result<()>,
) -> Result<(Vec<u8>, String)> {
    let mut rgb = vec![0u8; size.0 as usize * size.1 as usize * 3];
    let mut svg = String::new();
    {
        let root = BitMapBackend::with_buffer(&mut rgb, size).into_drawing_area();
        bitmap(&root)?;
        root.present().plot_err("finishing the bitmap")?;
    }
    {
        let root = SVGBackend::with_string(&mut svg, size).into_drawing_area();
        vector(&root)?;
        root.present().plot_err("finishing the SVG")?;
    }
    Ok((rgb, svg))
}

/// Writes `rgb` (`size` pixels) as PNG file `png` and `svg_text` as file `svg`, each through
/// [`drivelab_runtime::files::write`] (a symbolic link in place of either is refused). On
/// failure neither is left half written.
pub(crate) fn save(
    png: &Path,
    rgb: &[u8],
    size: (u32, u32),
    svg: &Path,
    svg_text: &str,
) -> Result<()> {
    use image::ImageEncoder;
    let mut png_bytes = Vec::new();
    image::codecs::png::PngEncoder::new(&mut png_bytes)
        .write_image(rgb, size.0, size.1, image::ColorType::Rgb8)
        .with_context(|| format!("encoding {}", png.display()))?;
    for (path, bytes) in [(png, png_bytes.as_slice()), (svg, svg_text.as_bytes())] {
        if let Err(e) = drivelab_runtime::files::write(path, bytes) {
            // The files this call began go (a refused link is not one of them: it stays).
            let began: &[&Path] = if path == png { &[png] } else { &[png, svg] };
            for p in began {
                if p.symlink_metadata().is_ok_and(|m| m.is_file()) {
                    let _ = std::fs::remove_file(p);
                }
            }
            return Err(anyhow!("writing {}: {e}", path.display()));
        }
    }
    Ok(())
}

fn draw_figure<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, fig: &Figure) -> Result<()> {
    root.fill(&WHITE).plot_err("filling the background")?;
    let body = if fig.title.is_empty() {
        root.clone()
    } else {
        root.titled(&fig.title, (FONT, TITLE_FONT_PX))
            .plot_err("drawing the title")?
    };
    // The footer's lines at the bottom, the panels above.
    let body = if fig.footer.is_empty() {
        body
    } else {
        let line_px = ANNOTATION_FONT_PX as i32 + 5;
        let footer_px = line_px as u32 * fig.footer.len() as u32 + 10;
        let h = body.dim_in_pixel().1.saturating_sub(footer_px);
        let (panels, footer) = body.split_vertically(h);
        let style = (FONT, ANNOTATION_FONT_PX).into_font().color(&C_SHADE_TEXT);
        for (i, line) in fig.footer.iter().enumerate() {
            footer
                .draw_text(line, &style, (12, 4 + i as i32 * line_px))
                .plot_err("drawing the legend")?;
        }
        panels
    };
    let total: u32 = fig.panels.iter().map(|(_, w)| *w).sum::<u32>().max(1);
    let height = body.dim_in_pixel().1;
    let mut rest = body;
    for (i, (panel, weight)) in fig.panels.iter().enumerate() {
        if i + 1 == fig.panels.len() {
            draw_panel(&rest, panel)?;
        } else {
            let h = (u64::from(height) * u64::from(*weight) / u64::from(total)) as u32;
            let (top, bottom) = rest.split_vertically(h);
            draw_panel(&top, panel)?;
            rest = bottom;
        }
    }
    Ok(())
}

/// Draws one panel: grid and axes, shaded windows, series, reference lines and legend.
fn draw_panel<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, panel: &Panel) -> Result<()> {
    let (x_axis, y_axis) = panel.axes()?;
    let (x_range, y_range) = (x_axis.range(), y_axis.range());
    let legend_pos = legend_corner(panel, &x_axis, &y_axis);

    let mut chart = ChartBuilder::on(area)
        .margin(12)
        // Room for the last x tick label (long percent labels on nines axes).
        .margin_right(if panel.x_kind == AxisKind::Nines {
            64
        } else {
            28
        })
        .x_label_area_size(52)
        .y_label_area_size(84)
        .build_cartesian_2d(x_axis.clone(), y_axis.clone())
        .plot_err("building the chart")?;

    let x_fmt = |v: &f64| x_axis.label(*v);
    let y_fmt = |v: &f64| y_axis.label(*v);
    chart
        .configure_mesh()
        .x_desc(panel.x_label.as_str())
        .y_desc(panel.y_label.as_str())
        .x_label_formatter(&x_fmt)
        .y_label_formatter(&y_fmt)
        .x_labels(12)
        .y_labels(10)
        .label_style((FONT, TICK_FONT_PX))
        .axis_desc_style((FONT, AXIS_DESC_FONT_PX))
        .bold_line_style(BLACK.mix(0.18))
        .light_line_style(BLACK.mix(0.06))
        .draw()
        .plot_err("drawing the grid")?;

    for s in &panel.shades {
        let (x0, x1) = (s.x0.max(x_range.start), s.x1.min(x_range.end));
        if x0 > x1 {
            continue;
        }
        let rect = Rectangle::new(
            [(x0, y_range.start), (x1, y_range.end)],
            RED.mix(0.12).filled(),
        );
        let text_style = (FONT, ANNOTATION_FONT_PX).into_font().color(&C_SHADE_TEXT);
        // Numbered markers step down in three rows, so that close neighbours stay readable.
        let row = s.label.parse::<i32>().map_or(0, |n| (n - 1).rem_euclid(3));
        let text = EmptyElement::at((x0, y_range.end))
            + Text::new(s.label.clone(), (4, 4 + row * 15), text_style);
        chart.draw_series([rect]).plot_err("shading a window")?;
        chart.draw_series([text]).plot_err("labelling a window")?;
    }

    // Limits first: a trace that runs along one (i_d* at −i_q,max) stays visible on top.
    let mut has_legend = false;
    for h in &panel.hlines {
        if !y_axis.contains(h.y) {
            continue;
        }
        has_legend |= h.label.is_some();
        let pts = vec![(x_range.start, h.y), (x_range.end, h.y)];
        draw_line(
            &mut chart,
            pts,
            h.color,
            Line::Dashed(2),
            h.label.as_deref(),
        )?;
    }
    for s in &panel.series {
        // One legend entry, with the first piece drawn.
        let mut label = (!s.label.is_empty()).then_some(s.label.as_str());
        for piece in s.pieces() {
            let pts: Vec<(f64, f64)> = panel.drawable_of(piece).copied().collect();
            if pts.is_empty() {
                continue;
            }
            has_legend |= label.is_some();
            draw_line(&mut chart, pts, s.color, s.line, label.take())?;
        }
    }

    if has_legend {
        chart
            .configure_series_labels()
            .position(legend_pos)
            .margin(10)
            .legend_area_size(40)
            .label_font((FONT, LEGEND_FONT_PX))
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK.mix(0.4))
            .draw()
            .plot_err("drawing the legend")?;
    }
    Ok(())
}

/// Draws one polyline (solid or dashed) and registers its legend entry if labelled.
fn draw_line<DB: DrawingBackend>(
    chart: &mut ChartContext<'_, DB, Cartesian2d<Axis, Axis>>,
    points: Vec<(f64, f64)>,
    color: RGBColor,
    line: Line,
    label: Option<&str>,
) -> Result<()> {
    // Must stay below the legend area size set in `draw_panel`.
    const LEGEND_LEN: i32 = 30;
    let style = match line {
        Line::Solid(w) | Line::Dashed(w) => color.stroke_width(w),
    };
    match line {
        Line::Solid(_) => {
            let anno = chart
                .draw_series(LineSeries::new(points, style))
                .plot_err("drawing a series")?;
            if let Some(label) = label {
                anno.label(label).legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + LEGEND_LEN, y)], style)
                });
            }
        }
        Line::Dashed(_) => {
            let anno = chart
                .draw_series(DashedLineSeries::new(points, 8, 5, style))
                .plot_err("drawing a dashed series")?;
            if let Some(label) = label {
                anno.label(label).legend(move |(x, y)| {
                    DashedPathElement::new(vec![(x, y), (x + LEGEND_LEN, y)], 7, 4, style)
                });
            }
        }
    }
    Ok(())
}

/// Picks the plot corner whose 35 % × 35 % box holds the fewest data points.
fn legend_corner(panel: &Panel, x: &Axis, y: &Axis) -> SeriesLabelPosition {
    // (position, x side is right, y side is top)
    let corners = [
        (SeriesLabelPosition::UpperRight, true, true),
        (SeriesLabelPosition::UpperLeft, false, true),
        (SeriesLabelPosition::LowerRight, true, false),
        (SeriesLabelPosition::LowerLeft, false, false),
    ];
    let mut counts = [0usize; 4];
    for s in &panel.series {
        for &(px, py) in panel.drawable(s) {
            let (u, v) = (x.normalized(px), y.normalized(py));
            for (c, &(_, right, top)) in counts.iter_mut().zip(&corners) {
                let in_x = if right { u > 0.65 } else { u < 0.35 };
                let in_y = if top { v > 0.65 } else { v < 0.35 };
                *c += usize::from(in_x && in_y);
            }
        }
    }
    let best = (0..4).min_by_key(|&i| counts[i]).unwrap_or(0);
    corners[best].0.clone()
}

// ---------------------------------------------------------------------------------------------
// Tests
// ---------------------------------------------------------------------------------------------

#[cfg(test)]
mod tests {

    #[test]
    fn fault_windows_become_numbers_in_time_order_with_a_packed_legend() {
        let w = vec![
            (0.5, 0.6, "kill plant".to_string()),
            (0.1, 0.2, "stop for 0.02 s observer".to_string()),
        ];
        let (n, legend) = numbered_windows(&w);
        assert_eq!(
            n,
            vec![(0.1, 0.2, "1".to_string()), (0.5, 0.6, "2".to_string())]
        );
        assert_eq!(
            legend,
            vec!["1 stop for 0.02 s observer @ 0.100 s  ·  2 kill plant @ 0.500 s".to_string()]
        );
        // A hundred faults: every line within its width, 40 entries shown, the rest counted.
        let many: Vec<(f64, f64, String)> = (0..100)
            .map(|i| {
                (
                    f64::from(i) * 0.5,
                    f64::from(i) * 0.5 + 0.1,
                    "kill current-loop".into(),
                )
            })
            .collect();
        let (n, legend) = numbered_windows(&many);
        assert_eq!(n.len(), 100);
        assert_eq!(n[99].2, "100");
        assert!(
            legend.iter().all(|l| l.chars().count() <= LEGEND_LINE),
            "{legend:?}"
        );
        let shown: usize = legend.iter().map(|l| l.matches(" @ ").count()).sum();
        assert_eq!(shown, LEGEND_MAX);
        assert_eq!(
            legend.last().unwrap(),
            "… and 60 more (summary.json → faults)"
        );
    }

    use super::*;

    #[test]
    fn a_gap_in_the_data_is_a_gap_in_the_line() {
        // NaN at 3..5 (an estimate no stage had), and one more at the end.
        let y = [1.0, 2.0, 3.0, f64::NAN, f64::NAN, 6.0, 7.0, f64::NAN];
        let s = Series::new(
            "ω",
            y.iter().enumerate().map(|(i, v)| (i as f64, *v)),
            BLACK,
            Line::Solid(1),
        );
        let pieces: Vec<&[(f64, f64)]> = s.pieces().collect();
        assert_eq!(
            pieces,
            [
                &[(0.0, 1.0), (1.0, 2.0), (2.0, 3.0)][..],
                &[(5.0, 6.0), (6.0, 7.0)][..]
            ]
        );
        // No gap: one piece; nothing finite: none.
        let whole = Series::new("a", [(0.0, 1.0), (1.0, 2.0)], BLACK, Line::Solid(1));
        assert_eq!(whole.pieces().count(), 1);
        let none = Series::new("b", [(0.0, f64::NAN)], BLACK, Line::Solid(1));
        assert_eq!(none.pieces().count(), 0);
        // Long pieces share the point budget.
        let long = (0..20_000).map(|i| (i as f64, if i == 10_000 { f64::NAN } else { 1.0 }));
        let s = Series::new("c", long, BLACK, Line::Solid(1));
        assert_eq!(s.pieces().count(), 2);
        assert!(
            s.points.len() <= MAX_POINTS_PER_SERIES + 8,
            "{}",
            s.points.len()
        );
    }
    use std::sync::atomic::{AtomicUsize, Ordering};

    /// Unique temporary directory, removed on drop.
    struct TempDir(PathBuf);

    impl TempDir {
        fn new() -> Self {
            static COUNTER: AtomicUsize = AtomicUsize::new(0);
            let n = COUNTER.fetch_add(1, Ordering::Relaxed);
            let dir =
                std::env::temp_dir().join(format!("drivelab-plot-test-{}-{n}", std::process::id()));
            let _ = std::fs::remove_dir_all(&dir);
            std::fs::create_dir_all(&dir).expect("create temp dir");
            Self(dir)
        }
    }

    impl Drop for TempDir {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    fn assert_outputs(files: &[PathBuf]) {
        assert!(!files.is_empty());
        for f in files {
            let bytes = std::fs::read(f).unwrap_or_else(|e| panic!("{}: {e}", f.display()));
            match f.extension().and_then(|e| e.to_str()) {
                Some("png") => assert!(
                    bytes.starts_with(b"\x89PNG\r\n\x1a\n"),
                    "{} is not a PNG",
                    f.display()
                ),
                Some("svg") => assert!(
                    String::from_utf8_lossy(&bytes).contains("<svg"),
                    "{} is not an SVG",
                    f.display()
                ),
                other => panic!("unexpected output extension {other:?}"),
            }
        }
    }

    fn synthetic_trace(n: usize) -> Vec<TraceRow> {
        let ts = 1e-4;
        (0..n)
            .map(|k| {
                let t = k as f64 * ts;
                let omega_ref = if t < 0.01 { 0.0 } else { 100.0 };
                let omega_m = omega_ref * (1.0 - (-(t - 0.01).max(0.0) / 0.005).exp());
                TraceRow {
                    k: k as u64,
                    t,
                    omega_ref,
                    omega_m,
                    omega_hat: omega_m + 0.5 * (t * 2000.0).sin(),
                    theta_e: (t * 400.0).rem_euclid(std::f64::consts::TAU),
                    theta_hat: (t * 400.0 + 0.01).rem_euclid(std::f64::consts::TAU),
                    i_d_ref: 0.0,
                    i_q_ref: if t < 0.01 { 0.0 } else { 5.0 },
                    i_d: 0.05 * (t * 5000.0).sin(),
                    i_q: if t < 0.01 {
                        0.0
                    } else {
                        5.0 - 5.0 * (-(t - 0.01) / 0.001).exp()
                    },
                    u_d: -2.0 * (t * 300.0).cos(),
                    u_q: 10.0 * omega_m / 100.0 + 1.0,
                    t_load: if t > 0.03 { 0.2 } else { 0.0 },
                    miss: u8::from(k == n / 2),
                    ..Default::default()
                }
            })
            .collect()
    }

    #[test]
    fn plot_trace_writes_png_and_svg() {
        let dir = TempDir::new();
        let rows = synthetic_trace(500);
        let opts = TraceFigureOptions {
            window_s: None,
            current_limit_a: Some(8.0),
            voltage_limit_v: Some(24.0),
            shaded_windows: vec![(0.02, 0.025, "encoder fault".to_string())],
            title: "unit test".to_string(),
        };
        let files = plot_trace(&rows, &dir.0, &opts).expect("plot_trace");
        assert_eq!(files.len(), 6, "{files:?}");
        for stem in ["speed", "currents", "voltages"] {
            assert!(files.contains(&dir.0.join(format!("{stem}.png"))));
            assert!(files.contains(&dir.0.join(format!("{stem}.svg"))));
        }
        assert_outputs(&files);
    }

    #[test]
    fn plot_trace_long_trace_window_and_nan_series() {
        let dir = TempDir::new();
        let mut rows = synthetic_trace(200_000);
        for r in &mut rows {
            r.omega_hat = f64::NAN; // no observer: series skipped
            r.u_d = f64::NAN;
            r.u_q = f64::NAN; // whole voltage figure skipped
        }
        let opts = TraceFigureOptions {
            window_s: Some((0.005, 15.0)),
            ..Default::default()
        };
        let files = plot_trace(&rows, &dir.0, &opts).expect("plot_trace");
        assert_eq!(files.len(), 4, "{files:?}");
        assert!(!dir.0.join("voltages.png").exists());
        assert_outputs(&files);
    }

    /// All-zero signals (zero y span) and a single row (zero x span) still give every
    /// figure; how such a span is padded into an axis is checked in `axes_and_ticks`.
    #[test]
    fn plot_trace_draws_constant_signals_and_a_single_row() {
        let dir = TempDir::new();
        let rows: Vec<TraceRow> = (0..10)
            .map(|k| TraceRow {
                k,
                t: k as f64 * 1e-4,
                ..Default::default()
            })
            .collect();
        let files = plot_trace(&rows, &dir.0, &TraceFigureOptions::default()).expect("plot");
        assert_outputs(&files);
        // A single row (zero x span) also works.
        let files = plot_trace(&rows[..1], &dir.0, &TraceFigureOptions::default()).expect("plot");
        assert_outputs(&files);
    }

    #[test]
    fn empty_inputs_are_errors_not_panics() {
        let dir = TempDir::new();
        let opts = TraceFigureOptions::default();
        assert!(plot_trace(&[], &dir.0, &opts).is_err());

        let rows = synthetic_trace(10);
        let outside = TraceFigureOptions {
            window_s: Some((5.0, 6.0)),
            ..Default::default()
        };
        assert!(plot_trace(&rows, &dir.0, &outside).is_err());
        let reversed = TraceFigureOptions {
            window_s: Some((1.0, 0.0)),
            ..Default::default()
        };
        assert!(plot_trace(&rows, &dir.0, &reversed).is_err());

        let nan_rows: Vec<TraceRow> = rows
            .iter()
            .map(|r| TraceRow { t: f64::NAN, ..*r })
            .collect();
        assert!(plot_trace(&nan_rows, &dir.0, &opts).is_err());

        let stem = dir.0.join("p");
        assert!(plot_percentiles(&[], "t", None, false, &stem).is_err());
        let nan_series = vec![("a".to_string(), vec![(50.0, f64::NAN), (100.0, 3.0)])];
        assert!(plot_percentiles(&nan_series, "t", None, false, &stem).is_err());
        let zero_series = vec![("a".to_string(), vec![(50.0, 0.0)])];
        assert!(plot_percentiles(&zero_series, "t", None, true, &stem).is_err());

        assert!(plot_lines(&[], "t", "x", "y", &[], &stem).is_err());
        let nan_lines = vec![("a".to_string(), vec![(f64::NAN, 1.0), (1.0, f64::INFINITY)])];
        assert!(plot_lines(&nan_lines, "t", "x", "y", &[], &stem).is_err());
        assert!(plot_lines(&[("a".to_string(), vec![])], "t", "x", "y", &[], &stem).is_err());
        assert!(!with_suffix(&stem, "png").exists());
    }

    #[test]
    fn plot_percentiles_linear_and_log() {
        let dir = TempDir::new();
        let mk = |scale: f64| -> Vec<(f64, f64)> {
            (0..400)
                .map(|i| {
                    let p = 100.0 * (1.0 - 10f64.powf(-(i as f64) / 70.0));
                    (p, scale * (5.0 + 2.0 * (i as f64 / 70.0).powi(3)))
                })
                .collect()
        };
        let series = vec![
            ("controller".to_string(), mk(1.0)),
            ("plant".to_string(), mk(1.5)),
        ];
        for log_y in [false, true] {
            let stem = dir.0.join(format!("latency_{log_y}"));
            let files = plot_percentiles(
                &series,
                "loop latency",
                Some((100.0, "Ts = 100 µs".to_string())),
                log_y,
                &stem,
            )
            .expect("plot_percentiles");
            assert_eq!(
                files,
                vec![with_suffix(&stem, "png"), with_suffix(&stem, "svg")]
            );
            assert_outputs(&files);
        }
    }

    #[test]
    fn plot_lines_with_hlines_and_degenerate_series() {
        let dir = TempDir::new();
        let a: Vec<(f64, f64)> = (0..100_000)
            .map(|i| (i as f64 * 1e-3, (i as f64).sqrt()))
            .collect();
        let series = vec![
            ("run A".to_string(), a),
            ("constant".to_string(), vec![(0.0, 3.0), (50.0, 3.0)]),
            ("empty".to_string(), vec![]),
        ];
        let stem = dir.0.join("sub").join("cmp.runs");
        let files = plot_lines(
            &series,
            "comparison",
            "t [ms]",
            "ω [rad/s]",
            &[(200.0, "limit".to_string())],
            &stem,
        )
        .expect("plot_lines");
        assert_eq!(files[0], dir.0.join("sub").join("cmp.runs.png"));
        assert_outputs(&files);

        let single = vec![("one point".to_string(), vec![(1.0, 1.0)])];
        let files = plot_lines(&single, "", "x", "y", &[], &dir.0.join("single")).expect("plot");
        assert_outputs(&files);
    }

    #[test]
    fn decimation_keeps_global_extrema_and_bounds_size() {
        let n = 1_000_000;
        let mut pts: Vec<(f64, f64)> = (0..n)
            .map(|i| (i as f64, (i as f64 * 0.001).sin()))
            .collect();
        pts[123_457].1 = 42.0; // single-sample spikes
        pts[876_543].1 = -17.0;
        pts[500].1 = f64::NAN;
        let d = decimate_min_max(&pts, MAX_POINTS_PER_SERIES);
        assert!(d.len() <= MAX_POINTS_PER_SERIES + 2, "{}", d.len());
        assert!(d.len() >= MAX_POINTS_PER_SERIES / 2);
        let max = d.iter().map(|p| p.1).fold(f64::NEG_INFINITY, f64::max);
        let min = d.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
        assert_eq!(max, 42.0);
        assert_eq!(min, -17.0);
        assert!(d.contains(&(123_457.0, 42.0)) && d.contains(&(876_543.0, -17.0)));
        assert_eq!(d.first(), Some(&pts[0]));
        assert_eq!(d.last(), Some(&pts[n - 1]));
        assert!(d.windows(2).all(|w| w[0].0 < w[1].0), "order preserved");
        assert!(d.iter().all(|p| p.1.is_finite()));

        // Short inputs pass through (minus non-finite points).
        let short = [(0.0, 1.0), (1.0, f64::NAN), (2.0, 3.0)];
        assert_eq!(decimate_min_max(&short, 10), vec![(0.0, 1.0), (2.0, 3.0)]);
        assert!(decimate_min_max(&[], 10).is_empty());
        assert!(decimate_min_max(&[(0.0, f64::NAN)], 0).is_empty());
    }

    #[test]
    fn axes_and_ticks() {
        assert!((percentile_to_nines(99.9) - 3.0).abs() < 1e-9);
        assert_eq!(percentile_to_nines(0.0), 0.0);
        let nines = Axis::new(AxisKind::Nines, 0.0, 5.0);
        let labels: Vec<String> = nines
            .major_ticks(12)
            .iter()
            .map(|v| nines.label(*v))
            .collect();
        assert_eq!(labels, ["0%", "90%", "99%", "99.9%", "99.99%", "99.999%"]);

        let lin = Axis::from_data(AxisKind::Linear, [2.0, 2.0].into_iter(), 0.05, false).unwrap();
        assert!(lin.lo < 2.0 && lin.hi > 2.0);
        let zero = Axis::from_data(AxisKind::Linear, [0.0].into_iter(), 0.05, false).unwrap();
        assert!(zero.lo < 0.0 && zero.hi > 0.0);
        assert!(Axis::from_data(AxisKind::Linear, [f64::NAN].into_iter(), 0.05, false).is_err());
        assert!(Axis::from_data(AxisKind::Log, [-1.0, 0.0].into_iter(), 0.05, false).is_err());

        let log = Axis::from_data(AxisKind::Log, [3.0, 3000.0].into_iter(), 0.05, false).unwrap();
        let ticks = log.major_ticks(8);
        assert!(
            ticks.contains(&10.0) && ticks.contains(&1000.0),
            "{ticks:?}"
        );
        let narrow = Axis::from_data(AxisKind::Log, [12.0, 19.0].into_iter(), 0.05, false).unwrap();
        assert!(narrow.major_ticks(8).len() >= 3);

        let (t, step) = nice_ticks(-0.3, 1.7, 8);
        assert_eq!(step, 0.5);
        assert_eq!(t, vec![0.0, 0.5, 1.0, 1.5]);
        assert_eq!(fmt_tick(0.30000000000000004), "0.3");
        assert_eq!(fmt_tick(-0.0), "0");
        assert_eq!(fmt_tick(2500.0), "2500");
        assert_eq!(lin.map(&lin.lo, (0, 100)), 0);
        assert_eq!(lin.map(&lin.hi, (0, 100)), 100);
        assert_eq!(lin.map(&f64::NAN, (0, 100)), 0);
    }
}
