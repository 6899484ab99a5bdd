//! Step-response metrics of a trace, measured against the scenario's reference profile.

use crate::config::{profile_at, Scenario};
use crate::trace::TraceRow;
use serde::Serialize;

/// Speed-loop metrics (`summary.json` → `metrics`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct SpeedMetrics {
    /// Time from the first speed step to the first sample at or beyond the set-point, ms.
    pub rise_time_ms: Option<f64>,
    /// Peak beyond the set-point relative to the step size, % (before the next event).
    pub overshoot_pct: Option<f64>,
    /// Mean (ω_ref − ω_m) over the last 10 % of the run, rad/s.
    pub steady_state_error: Option<f64>,
    /// Largest speed drop below the reference after the first load step, rad/s.
    pub load_dip_rad_s: Option<f64>,
    /// Time from the first load step until ω_m stays within ±2 % of the reference, ms.
    pub load_recovery_ms: Option<f64>,
    /// RMS of (i_d* − i_d) from 5 ms after the first i_d reference step to the end of the
    /// run, A (i_d* from the scenario's profile). It covers the settled field current and
    /// whatever the later events (the load step) do to it: the torque/flux decoupling.
    pub id_tracking_error_a: Option<f64>,
}

/// Start of the i_d tracking-error window after the first i_d reference step, s.
pub const ID_ERROR_DELAY_S: f64 = 5e-3;

fn first_step_time(steps: &[crate::config::Step], after: f64) -> Option<f64> {
    steps.iter().map(|s| s.t_s).find(|&t| t > after)
}

/// Computes the speed metrics of `rows` for scenario `sc`.
pub fn speed_metrics(sc: &Scenario, rows: &[TraceRow]) -> SpeedMetrics {
    let mut out = SpeedMetrics::default();
    if rows.is_empty() {
        return out;
    }
    let refs = &sc.reference.speed_rad_s;
    let loads = &sc.load.torque_nm;
    let end = rows.last().map(|r| r.t).unwrap_or(0.0);
    // Events that end the step-response window: the next speed step or the first load step.
    if let Some(step) = refs
        .iter()
        .find(|s| s.value != profile_at(refs, s.t_s - 1e-9) || s.t_s == 0.0)
    {
        let t0 = step.t_s;
        let before = if t0 > 0.0 {
            profile_at(refs, t0 - 1e-9)
        } else {
            0.0
        };
        let target = step.value;
        let dir = (target - before).signum();
        let next_event = [
            first_step_time(refs, t0),
            first_step_time(loads, t0 - 1e-12),
        ]
        .into_iter()
        .flatten()
        .fold(end + 1.0, f64::min);
        if dir != 0.0 {
            out.rise_time_ms = rows
                .iter()
                .find(|r| r.t >= t0 && (r.omega_m - target) * dir >= 0.0)
                .map(|r| (r.t - t0) * 1e3);
            let peak = rows
                .iter()
                .filter(|r| r.t >= t0 && r.t < next_event)
                .map(|r| (r.omega_m - target) * dir)
                .fold(f64::NEG_INFINITY, f64::max);
            if peak.is_finite() {
                out.overshoot_pct = Some(peak.max(0.0) / (target - before).abs() * 100.0);
            }
        }
    }
    let tail_start = end * 0.9;
    let tail: Vec<f64> = rows
        .iter()
        .filter(|r| r.t >= tail_start)
        .map(|r| profile_at(refs, r.t) - r.omega_m)
        .collect();
    if !tail.is_empty() {
        out.steady_state_error = Some(tail.iter().sum::<f64>() / tail.len() as f64);
    }
    if let Some(tl) = loads.iter().find(|s| s.value != 0.0) {
        let t0 = tl.t_s;
        let after: Vec<&TraceRow> = rows.iter().filter(|r| r.t >= t0).collect();
        let dip = after
            .iter()
            .map(|r| profile_at(refs, r.t) - r.omega_m)
            .fold(f64::NEG_INFINITY, f64::max);
        if dip.is_finite() {
            out.load_dip_rad_s = Some(dip);
        }
        // Last sample outside the ±2 % band; recovered just after it.
        let outside = after.iter().rposition(|r| {
            let w = profile_at(refs, r.t);
            (r.omega_m - w).abs() > 0.02 * w.abs()
        });
        out.load_recovery_ms = match outside {
            None => Some(0.0),
            Some(i) if i + 1 < after.len() => Some((after[i + 1].t - t0) * 1e3),
            Some(_) => None, // never recovered within the run
        };
    }
    let ids = &sc.reference.i_d_a;
    if let Some(step) = ids
        .iter()
        .find(|s| s.value != profile_at(ids, s.t_s - 1e-9) || (s.t_s == 0.0 && s.value != 0.0))
    {
        let t0 = step.t_s + ID_ERROR_DELAY_S;
        let (sum, n) = rows
            .iter()
            .filter(|r| r.t >= t0 - 1e-12)
            .map(|r| profile_at(ids, r.t) - r.i_d)
            .fold((0.0, 0usize), |(s, n), e| (s + e * e, n + 1));
        if n > 0 {
            out.id_tracking_error_a = Some((sum / n as f64).sqrt());
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sc() -> Scenario {
        Scenario::from_toml(
            r#"
name = "m"
duration_s = 0.1
[motor]
preset = "kyslan2015"
[reference]
speed_rad_s = [{ t_s = 0.0, value = 100.0 }]
i_d_a = [{ t_s = 0.02, value = -1.0 }]
[load]
torque_nm = [{ t_s = 0.05, value = 0.1 }]
"#,
            "m",
        )
        .unwrap()
    }

    #[test]
    fn synthetic_response() {
        // ω rises linearly to 110 at 10 ms, falls to 100 at 20 ms, dips by 5 at 50 ms and
        // comes back at 60 ms.
        let rows: Vec<TraceRow> = (0..1000)
            .map(|k| {
                let t = k as f64 * 1e-4;
                let w = if t < 0.01 {
                    11_000.0 * t
                } else if t < 0.02 {
                    110.0 - 1000.0 * (t - 0.01)
                } else if (0.05..0.06).contains(&t) {
                    95.0
                } else {
                    100.0
                };
                // i_d: 0 before 20 ms, then −1 with an error of 0.1 A from 40 ms on.
                let i_d = if t < 0.02 {
                    0.0
                } else if t < 0.04 {
                    -1.0
                } else {
                    -0.9
                };
                TraceRow {
                    k,
                    t,
                    omega_m: w,
                    i_d,
                    ..Default::default()
                }
            })
            .collect();
        let m = speed_metrics(&sc(), &rows);
        let rise = m.rise_time_ms.unwrap();
        assert!((rise - 100.0 / 11_000.0 * 1e3).abs() < 0.11, "{rise}");
        assert!((m.overshoot_pct.unwrap() - 10.0).abs() < 0.2);
        assert!((m.load_dip_rad_s.unwrap() - 5.0).abs() < 1e-9);
        assert!((m.load_recovery_ms.unwrap() - 10.0).abs() < 0.11);
        assert!(m.steady_state_error.unwrap().abs() < 1e-9);
        // Window 25 ms..99.9 ms: 150 samples at 0, 600 at 0.1 A → RMS 0.1·√(600/750).
        let e = m.id_tracking_error_a.unwrap();
        assert!((e - 0.1 * (600.0f64 / 750.0).sqrt()).abs() < 1e-9, "{e}");
    }

    #[test]
    fn no_i_d_step_no_i_d_error() {
        let mut s = sc();
        s.reference.i_d_a.clear();
        let rows = [TraceRow::default()];
        assert_eq!(speed_metrics(&s, &rows).id_tracking_error_a, None);
    }
}
