//! `drivelab observer-error`: the relative truncation error ζ of Low et al. 1998 eq. (14)
//! against speed for given sample times (the paper's Fig. 3), and what it costs the observer:
//! the steady-state angle error the minimal-order observer settles to with the truncated model
//! of eq. (13), beside the exact discretisation.

use crate::expect::usage;
use anyhow::{Context, Result};
use drivelab_control::motor::MotorParams;
use drivelab_control::observer_sensorless::{
    predicted_angle_error, truncation_error, Discretisation,
};
use serde_json::json;
use std::fmt::Write;
use std::path::PathBuf;

/// Arguments of `drivelab observer-error`.
#[derive(Debug, clap::Args)]
pub struct ObserverErrorArgs {
    /// Sample times T_s, with a unit (s, ms, us), comma-separated, e.g. `0.1ms,0.2ms,0.5ms`.
    #[arg(long, value_delimiter = ',', default_value = "0.1ms,0.2ms,0.5ms,1ms")]
    pub ts: Vec<String>,
    /// Motor: a preset (kyslan2015, kyslan2015-sal618, low1998, miyajima) or a TOML file with a
    /// [motor] table.
    #[arg(long, default_value = "low1998")]
    pub motor: String,
    /// Highest speed of the sweep, rpm (mechanical); default: the motor's rated speed.
    #[arg(long, value_name = "RPM")]
    pub max_rpm: Option<f64>,
    /// Speed step of the sweep, rpm.
    #[arg(long, value_name = "RPM", default_value_t = 100.0)]
    pub step_rpm: f64,
    /// Observer time constant τ_o for the steady-state angle error, ms.
    #[arg(long, value_name = "MS", default_value_t = 1.0)]
    pub pole_tau_ms: f64,
    /// Output folder for observer_error.json and the plots zeta.{png,svg} and
    /// angle_error.{png,svg}.
    #[arg(long, value_name = "DIR", default_value = "runs/observer-error")]
    pub out: PathBuf,
    /// Do not draw the plots.
    #[arg(long)]
    pub no_plots: bool,
    /// Print the JSON on stdout instead of the table.
    #[arg(long)]
    pub json: bool,
}

/// Parses a duration with a unit: `0.2ms`, `200us`, `200µs`, `2e-4s`. Returns seconds.
pub fn parse_duration(text: &str) -> Result<f64> {
    let t = text.trim();
    let (num, scale) = if let Some(n) = t.strip_suffix("ms") {
        (n, 1e-3)
    } else if let Some(n) = t.strip_suffix("us").or_else(|| t.strip_suffix("µs")) {
        (n, 1e-6)
    } else if let Some(n) = t.strip_suffix('s') {
        (n, 1.0)
    } else {
        return Err(usage(format!(
            "--ts {t:?}: give a unit, e.g. 0.2ms, 200us or 2e-4s"
        )));
    };
    let v: f64 = num.trim().parse().map_err(|_| {
        usage(format!(
            "--ts {t:?}: {num:?} before the unit is not a number"
        ))
    })?;
    let s = v * scale;
    // Below a microsecond the truncation error is lost in rounding (NaN angle errors).
    if !(s.is_finite() && (1e-6..=0.1).contains(&s)) {
        return Err(usage(format!(
            "--ts {t:?}: must be between 1 µs and 100 ms"
        )));
    }
    Ok(s)
}

/// One sample time's sweep.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Sweep {
    /// Sample time, s.
    pub ts_s: f64,
    /// ζ (eq. 14) per speed, as a fraction.
    pub zeta: Vec<f64>,
    /// Steady-state θ̂_e − θ_e at no load with the truncated model (eq. 13), degrees.
    pub angle_error_truncated_deg: Vec<f64>,
    /// The same with the exact discretisation, degrees.
    pub angle_error_exact_deg: Vec<f64>,
}

/// Computes the sweeps: speeds (rpm) and one [`Sweep`] per sample time.
pub fn sweep(
    m: &MotorParams,
    ts: &[f64],
    max_rpm: f64,
    step_rpm: f64,
    pole_tau_s: f64,
) -> (Vec<f64>, Vec<Sweep>) {
    let n = (max_rpm / step_rpm).floor() as usize;
    let rpm: Vec<f64> = (0..=n).map(|i| i as f64 * step_rpm).collect();
    let w = |r: f64| r * std::f64::consts::PI / 30.0;
    let sweeps = ts
        .iter()
        .map(|&t| Sweep {
            ts_s: t,
            zeta: rpm.iter().map(|&r| truncation_error(m, t, w(r))).collect(),
            angle_error_truncated_deg: rpm
                .iter()
                .map(|&r| {
                    predicted_angle_error(
                        m,
                        t,
                        w(r),
                        0.0,
                        0.0,
                        pole_tau_s,
                        Discretisation::Truncated,
                    )
                    .to_degrees()
                })
                .collect(),
            angle_error_exact_deg: rpm
                .iter()
                .map(|&r| {
                    predicted_angle_error(m, t, w(r), 0.0, 0.0, pole_tau_s, Discretisation::Exact)
                        .to_degrees()
                })
                .collect(),
        })
        .collect();
    (rpm, sweeps)
}

fn ts_label(t: f64) -> String {
    if t < 1e-3 {
        format!("{} µs", (t * 1e6 * 1000.0).round() / 1000.0)
    } else {
        format!("{} ms", (t * 1e3 * 1000.0).round() / 1000.0)
    }
}

/// Runs the command.
pub fn run(a: &ObserverErrorArgs) -> Result<()> {
    let m = crate::replay::resolve_motor(&a.motor)?;
    if a.ts.is_empty() {
        return Err(usage("--ts: give at least one sample time".into()));
    }
    let ts: Vec<f64> =
        a.ts.iter()
            .map(|t| parse_duration(t))
            .collect::<Result<_>>()?;
    let max_rpm = a
        .max_rpm
        .unwrap_or(m.omega_rated_rad_s * 30.0 / std::f64::consts::PI);
    if !(max_rpm.is_finite() && max_rpm > 0.0 && max_rpm <= 1e6) {
        return Err(usage(format!(
            "--max-rpm {max_rpm}: must be more than 0 and at most 1000000 rpm"
        )));
    }
    if !(a.step_rpm.is_finite() && a.step_rpm > 0.0 && max_rpm / a.step_rpm <= 100_000.0) {
        return Err(usage(format!(
            "--step-rpm {}: must be more than 0 rpm and give at most 100000 speeds up to {max_rpm} rpm",
            a.step_rpm
        )));
    }
    if a.step_rpm > max_rpm {
        return Err(usage(format!(
            "--step-rpm {}: must be at most the sweep's highest speed, {max_rpm} rpm (--max-rpm)",
            a.step_rpm
        )));
    }
    if !(a.pole_tau_ms.is_finite() && a.pole_tau_ms > 0.0 && a.pole_tau_ms <= 1000.0) {
        return Err(usage(format!(
            "--pole-tau-ms {}: must be more than 0 and at most 1000 ms",
            a.pole_tau_ms
        )));
    }
    let tau = a.pole_tau_ms * 1e-3;
    if let Some(t) = ts.iter().find(|&&t| t > tau) {
        return Err(usage(format!(
            "--ts {} is longer than the observer time constant --pole-tau-ms {} ms",
            ts_label(*t),
            a.pole_tau_ms
        )));
    }
    let (rpm, sweeps) = sweep(&m, &ts, max_rpm, a.step_rpm, tau);
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create {}", a.out.display()))?;
    let report = json!({
        "motor": m,
        "equation": "zeta = ||exp(A Ts) - (I + A Ts)||_F / ||exp(A Ts)||_F (Low et al. 1998 eq. 14), state [i_alpha, i_beta, sin, cos]",
        "pole_tau_s": tau,
        "speed_rpm": rpm,
        "sweeps": sweeps,
    });
    drivelab_runtime::files::write(
        a.out.join("observer_error.json"),
        serde_json::to_vec_pretty(&report)?,
    )?;
    let mut files = Vec::new();
    if !a.no_plots {
        let zeta_series: Vec<(String, Vec<(f64, f64)>)> = sweeps
            .iter()
            .map(|s| {
                (
                    format!("T_s = {}", ts_label(s.ts_s)),
                    rpm.iter()
                        .zip(&s.zeta)
                        .map(|(r, z)| (*r, 100.0 * z))
                        .collect(),
                )
            })
            .collect();
        files.extend(drivelab_tools::plot::plot_lines(
            &zeta_series,
            "relative truncation error ζ of I + A·T_s (Low et al. eq. 14, Fig. 3)",
            "speed [rpm]",
            "ζ [%]",
            &[(2.0, "2 %".into())],
            &a.out.join("zeta"),
        )?);
        let mut err_series = Vec::new();
        for s in &sweeps {
            err_series.push((
                format!("truncated, T_s = {}", ts_label(s.ts_s)),
                rpm.iter()
                    .zip(&s.angle_error_truncated_deg)
                    .map(|(r, e)| (*r, *e))
                    .collect(),
            ));
        }
        if let Some(s) = sweeps.first() {
            err_series.push((
                format!("exact, T_s = {}", ts_label(s.ts_s)),
                rpm.iter()
                    .zip(&s.angle_error_exact_deg)
                    .map(|(r, e)| (*r, *e))
                    .collect(),
            ));
        }
        files.extend(drivelab_tools::plot::plot_lines(
            &err_series,
            &format!(
                "observer steady-state angle error at no load, τ_o = {} ms",
                a.pole_tau_ms
            ),
            "speed [rpm]",
            "θ̂_e − θ_e [°]",
            &[],
            &a.out.join("angle_error"),
        )?);
    }
    if a.json {
        crate::outln!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    crate::out!("{}", render_table(&m, &rpm, &sweeps, a.pole_tau_ms));
    crate::outln!("wrote {}", a.out.join("observer_error.json").display());
    for f in files {
        crate::outln!("wrote {}", f.display());
    }
    Ok(())
}

/// The printed table: ζ in % per speed and sample time, then the angle error at 1200 rpm.
pub fn render_table(m: &MotorParams, rpm: &[f64], sweeps: &[Sweep], pole_tau_ms: f64) -> String {
    let mut o = String::new();
    let _ = writeln!(
        o,
        "relative truncation error ζ = ‖e^(A·Ts) − (I + A·Ts)‖_F / ‖e^(A·Ts)‖_F (Low et al. 1998 eq. 14)"
    );
    let _ = writeln!(
        o,
        "motor: R = {} Ω, L = {} mH, p = {}, ke = p·ψ = {:.4} V·s/rad",
        m.r_ohm,
        m.l_d_h * 1e3,
        m.pole_pairs,
        m.p() * m.psi_pm_wb
    );
    let _ = write!(o, "{:>10}", "rpm");
    for s in sweeps {
        let _ = write!(o, " {:>14}", format!("ζ @ {}", ts_label(s.ts_s)));
    }
    let _ = writeln!(o);
    for (i, r) in rpm.iter().enumerate() {
        let _ = write!(o, "{r:>10.0}");
        for s in sweeps {
            let _ = write!(o, " {:>13.3}%", 100.0 * s.zeta[i]);
        }
        let _ = writeln!(o);
    }
    let w1200 = 1200.0 * std::f64::consts::PI / 30.0;
    for s in sweeps {
        let z = truncation_error(m, s.ts_s, w1200);
        let tau = pole_tau_ms * 1e-3;
        let t = predicted_angle_error(m, s.ts_s, w1200, 0.0, 0.0, tau, Discretisation::Truncated)
            .to_degrees();
        let x = predicted_angle_error(m, s.ts_s, w1200, 0.0, 0.0, tau, Discretisation::Exact)
            .to_degrees();
        let _ = writeln!(
            o,
            "T_s = {}: ζ(1200 rpm) = {:.3} %; observer steady-state angle error at 1200 rpm, no load, τ_o = {} ms: {:.3}° truncated (eq. 13), {:.3}° exact",
            ts_label(s.ts_s),
            100.0 * z,
            pole_tau_ms,
            t,
            x
        );
    }
    o
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_need_a_unit() {
        assert!((parse_duration("0.2ms").unwrap() - 2e-4).abs() < 1e-15);
        assert!((parse_duration("200us").unwrap() - 2e-4).abs() < 1e-15);
        assert!((parse_duration("200µs").unwrap() - 2e-4).abs() < 1e-15);
        assert!((parse_duration("2e-4s").unwrap() - 2e-4).abs() < 1e-15);
        assert!(parse_duration("0.2")
            .unwrap_err()
            .to_string()
            .contains("unit"));
        assert!(parse_duration("xms").is_err());
        assert!(parse_duration("-1ms").is_err());
    }

    #[test]
    fn zeta_grows_with_speed_and_sample_time() {
        let m = MotorParams::low1998();
        let (rpm, s) = sweep(&m, &[1e-4, 2e-4], 3000.0, 100.0, 1e-3);
        assert_eq!(rpm.len(), 31);
        for sw in &s {
            assert!(sw.zeta.windows(2).all(|w| w[1] >= w[0]));
        }
        assert!(s[1].zeta[12] > s[0].zeta[12]);
        // Paper: below 2 % at 1200 rpm with 0.2 ms.
        assert!(s[1].zeta[12] < 0.02, "{}", s[1].zeta[12]);
    }
}
