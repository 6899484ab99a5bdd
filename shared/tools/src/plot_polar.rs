//! Paper-style panels of a polar-coordinate current-control run (Miyajima et al., Figs 2–3
//! and 7–8): (a) i_d, (b) i_q, (c) modulation index, (d) voltage phase, each against time
//! and each with its limit drawn dashed. Written as `polar_panels.png` and `.svg`.
//!
//! The modulation index and the phase come from the trace's applied voltages u_d, u_q (the
//! inverter's output in the rotor frame) and the scenario's DC bus, in the signed polar form
//! of [`drivelab_control::control::polar::dq_to_polar`] (|δ| ≤ π/2, V_a < 0 for v_q < 0):
//! M = V_a/(V_dc/2), so the linear range of space-vector modulation, |u| ≤ V_dc/√3, is
//! |M| ≤ M_max = 2/√3.
#![forbid(unsafe_code)]

use anyhow::{bail, Context, Result};
use drivelab_control::control::polar::{dq_to_polar, PolarMode, SpmsmModel, DELTA_MAX};
use drivelab_runtime::config::Scenario;
use drivelab_runtime::trace::TraceRow;
use drivelab_runtime::wiring::polar::mode_of;
use plotters::coord::Shift;
use plotters::element::DashedPathElement;
use plotters::prelude::*;
use std::path::{Path, PathBuf};

/// Pixel size of the figure.
const SIZE: (u32, u32) = (1200, 1400);
/// At most this many points per series are drawn (min/max decimation).
const MAX_POINTS: usize = 3000;

/// Maximum modulation index of the linear SVPWM range, M_max = (V_dc/√3)/(V_dc/2) = 2/√3.
pub fn m_max() -> f64 {
    2.0 / 3f64.sqrt()
}

/// Modulation index M = V_a/(V_dc/2) and voltage phase δ (rad) of a trace row, from the
/// applied u_d, u_q (signed polar form).
pub fn modulation_and_phase(row: &TraceRow, v_dc_v: f64) -> (f64, f64) {
    let (v_a, delta) = dq_to_polar(row.u_d, row.u_q);
    (v_a / (0.5 * v_dc_v), delta)
}

struct Curve {
    label: String,
    pts: Vec<(f64, f64)>,
    color: RGBColor,
    dashed: bool,
}

struct Limit {
    y: f64,
    label: Option<String>,
}

struct PanelSpec {
    y_label: String,
    curves: Vec<Curve>,
    limits: Vec<Limit>,
}

fn decimate(pts: Vec<(f64, f64)>) -> Vec<(f64, f64)> {
    let pts: Vec<(f64, f64)> = pts
        .into_iter()
        .filter(|(x, y)| x.is_finite() && y.is_finite())
        .collect();
    if pts.len() <= MAX_POINTS {
        return pts;
    }
    let buckets = MAX_POINTS / 2;
    let per = pts.len().div_ceil(buckets);
    let mut out = Vec::with_capacity(MAX_POINTS + 2);
    for chunk in pts.chunks(per) {
        let (mut lo, mut hi) = (0, 0);
        for (i, p) in chunk.iter().enumerate() {
            if p.1 < chunk[lo].1 {
                lo = i;
            }
            if p.1 > chunk[hi].1 {
                hi = i;
            }
        }
        let (a, b) = (lo.min(hi), lo.max(hi));
        out.push(chunk[a]);
        if b != a {
            out.push(chunk[b]);
        }
    }
    out
}

/// Draws the four panels of `rows` (a run of scenario `sc`) into `out_dir` as
/// `polar_panels.png` and `polar_panels.svg`; returns the two paths.
///
/// Limits: ±I_max (the motor's current limit) on the currents, ±M_max = ±2/√3 on the
/// modulation index, ±δ_max = ±π/2 on the phase, and for the flux-weakening laws also the
/// phase of largest torque φ = atan2(ω_e L, R) at the prescribed speed, up to which those
/// laws limit δ.
///
/// # Errors
/// If `rows` is empty or a file cannot be written.
pub fn plot_polar_panels(
    sc: &Scenario,
    rows: &[TraceRow],
    out_dir: &Path,
    title: &str,
) -> Result<Vec<PathBuf>> {
    if rows.is_empty() {
        bail!("plot_polar_panels: the trace is empty");
    }
    std::fs::create_dir_all(out_dir)
        .with_context(|| format!("cannot create {}", out_dir.display()))?;
    let m = sc.motor_params();
    let v_dc = sc.inverter.v_dc_v;
    let t = |r: &TraceRow| r.t * 1e3;
    let curve = |label: &str, f: &dyn Fn(&TraceRow) -> f64, color: RGBColor, dashed: bool| Curve {
        label: label.into(),
        pts: decimate(rows.iter().map(|r| (t(r), f(r))).collect()),
        color,
        dashed,
    };
    let pm = |y: f64, label: &str| {
        vec![
            Limit {
                y,
                label: Some(label.into()),
            },
            Limit { y: -y, label: None },
        ]
    };
    let blue = RGBColor(31, 119, 180);
    let red = RGBColor(214, 39, 40);
    let black = RGBColor(20, 20, 20);
    let mut phase_limits = pm(DELTA_MAX, "±δ_max = ±π/2");
    if matches!(
        mode_of(sc),
        Some(PolarMode::VoltagePhase | PolarMode::PolarFw)
    ) {
        let w = m.p() * sc.mechanics.prescribed_speed_rad_s.unwrap_or(0.0).abs();
        let phi = SpmsmModel::from_motor(&m).max_torque_phase(w);
        phase_limits.push(Limit {
            y: phi,
            label: Some(format!("φ = atan2(ω_e L, R) = {phi:.3} rad")),
        });
    }
    let panels = [
        PanelSpec {
            y_label: "(a) i_d [A]".into(),
            curves: vec![
                curve("i_d*", &|r| r.i_d_ref, black, true),
                curve("i_d", &|r| r.i_d, blue, false),
            ],
            limits: pm(m.i_max_a, &format!("±I_max = ±{} A", m.i_max_a)),
        },
        PanelSpec {
            y_label: "(b) i_q [A]".into(),
            curves: vec![
                curve("i_q*", &|r| r.i_q_ref, black, true),
                curve("i_q", &|r| r.i_q, red, false),
            ],
            limits: pm(m.i_max_a, &format!("±I_max = ±{} A", m.i_max_a)),
        },
        PanelSpec {
            y_label: "(c) modulation index M".into(),
            curves: vec![curve(
                "M = V_a/(V_dc/2)",
                &|r| modulation_and_phase(r, v_dc).0,
                blue,
                false,
            )],
            limits: pm(m_max(), "±M_max = ±2/√3"),
        },
        PanelSpec {
            y_label: "(d) voltage phase δ [rad]".into(),
            curves: vec![curve("δ", &|r| modulation_and_phase(r, v_dc).1, red, false)],
            limits: phase_limits,
        },
    ];
    let x_range = (
        t(&rows[0]),
        t(&rows[rows.len() - 1]).max(t(&rows[0]) + 1e-6),
    );
    let png = out_dir.join("polar_panels.png");
    let svg = out_dir.join("polar_panels.svg");
    let (rgb, svg_text) = crate::plot::in_memory(
        SIZE,
        |root| draw(root, title, &panels, x_range),
        |root| draw(root, title, &panels, x_range),
    )
    .with_context(|| format!("drawing {}", png.display()))?;
    crate::plot::save(&png, &rgb, SIZE, &svg, &svg_text)?;
    Ok(vec![png, svg])
}

fn err<E: std::fmt::Debug>(e: E) -> anyhow::Error {
    anyhow::anyhow!("{e:?}")
}

fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    panels: &[PanelSpec],
    x_range: (f64, f64),
) -> Result<()> {
    root.fill(&WHITE).map_err(err)?;
    let body = root.titled(title, ("sans-serif", 26)).map_err(err)?;
    let areas = body.split_evenly((panels.len(), 1));
    for (area, p) in areas.iter().zip(panels) {
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for c in &p.curves {
            for &(_, y) in &c.pts {
                lo = lo.min(y);
                hi = hi.max(y);
            }
        }
        for l in &p.limits {
            lo = lo.min(l.y);
            hi = hi.max(l.y);
        }
        if !(lo.is_finite() && hi.is_finite()) {
            (lo, hi) = (-1.0, 1.0);
        }
        let pad = 0.08 * (hi - lo).max(1e-6);
        let mut chart = ChartBuilder::on(area)
            .margin(8)
            .x_label_area_size(36)
            .y_label_area_size(80)
            .build_cartesian_2d(x_range.0..x_range.1, (lo - pad)..(hi + pad))
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc("t [ms]")
            .y_desc(p.y_label.as_str())
            .label_style(("sans-serif", 15))
            .axis_desc_style(("sans-serif", 18))
            .light_line_style(RGBColor(235, 235, 235))
            .draw()
            .map_err(err)?;
        let grey = RGBColor(90, 90, 90);
        for l in &p.limits {
            let s = chart
                .draw_series(std::iter::once(DashedPathElement::new(
                    vec![(x_range.0, l.y), (x_range.1, l.y)],
                    6,
                    4,
                    grey.stroke_width(1),
                )))
                .map_err(err)?;
            if let Some(label) = &l.label {
                s.label(label.as_str()).legend(move |(x, y)| {
                    DashedPathElement::new(vec![(x, y), (x + 20, y)], 4, 3, grey.stroke_width(1))
                });
            }
        }
        for c in &p.curves {
            let color = c.color;
            let s = if c.dashed {
                chart
                    .draw_series(std::iter::once(DashedPathElement::new(
                        c.pts.clone(),
                        8,
                        4,
                        color.stroke_width(2),
                    )))
                    .map_err(err)?
            } else {
                chart
                    .draw_series(LineSeries::new(c.pts.clone(), color.stroke_width(2)))
                    .map_err(err)?
            };
            s.label(c.label.as_str())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color));
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.85))
            .border_style(RGBColor(180, 180, 180))
            .label_font(("sans-serif", 14))
            .draw()
            .map_err(err)?;
    }
    root.present().map_err(err)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn modulation_index_and_phase_of_the_applied_vector() {
        let r = TraceRow {
            u_d: -3.0,
            u_q: 4.0,
            ..Default::default()
        };
        let (m, d) = modulation_and_phase(&r, 10.0);
        assert!((m - 1.0).abs() < 1e-12 && (d - (3.0f64).atan2(4.0)).abs() < 1e-12);
        // v_q < 0: negative amplitude, phase within ±π/2.
        let r = TraceRow {
            u_d: 0.0,
            u_q: -2.0,
            ..Default::default()
        };
        let (m, d) = modulation_and_phase(&r, 10.0);
        assert!((m + 0.4).abs() < 1e-12 && d.abs() < 1e-12, "{m} {d}");
        assert!((m_max() - 1.1547005383792517).abs() < 1e-12);
    }
}
