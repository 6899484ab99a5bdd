//! Step-response metrics of a trace, measured against the scenario's reference profile.

use drivelab_runtime::config::{profile_at, Scenario};
use drivelab_runtime::trace::TraceRow;
use serde::Serialize;

/// Speed-loop metrics (`summary.json` → `metrics`).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct SpeedMetrics {
    /// The stage that makes the speed loop's reference (`wref`), when one does: the metrics
    /// measured against the scenario's speed reference and load steps do not apply and are
    /// left out.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub speed_reference_from: Option<String>,
    /// Time from the first speed step to the first sample at or beyond the set-point, ms.
    pub rise_time_ms: Option<f64>,
    /// Peak beyond the set-point relative to the step size, % (before the next event).
    pub overshoot_pct: Option<f64>,
    /// Mean (ω_ref − ω_m) over the last 10 % of the run, rad/s.
    pub steady_state_error_rad_s: Option<f64>,
    /// Largest speed drop below the reference after the first load step, rad/s.
    pub load_dip_rad_s: Option<f64>,
    /// Time from the first load step until ω_m stays within ±2 % of the reference, ms.
    pub load_recovery_ms: Option<f64>,
    /// RMS of (i_d* − i_d) from 5 ms after the first i_d reference step to the end of the
    /// run, A (i_d* from the scenario's profile). It covers the settled field current and
    /// whatever the later events (the load step) do to it: the torque/flux decoupling.
    pub id_tracking_error_a: Option<f64>,
    /// Sensorless observer (`observer.mode` "sensorless" or "monitor") only: mean angle error
    /// θ̂_e − θ_e over the last 10 % of the run, degrees electrical.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub angle_error_ss_deg: Option<f64>,
    /// Sensorless observer only: time from t = 0 until the angle error stays within ±1° of
    /// `angle_error_ss_deg` for 20 ms (or to the end of the run), ms.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub observer_convergence_ms: Option<f64>,
    /// Current-reference scenarios (`reference.i_q_a`) only: 10–90 % rise time of i_q after
    /// the first i_q* step, µs.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub iq_rise_time_us: Option<f64>,
    /// Current-reference scenarios only: peak of i_q beyond i_q* after the first i_q* step,
    /// relative to the step, % (until the next current-reference event).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub iq_overshoot_pct: Option<f64>,
    /// Current-reference scenarios only: mean (i_q* − i_q) over the last 10 % of the run, A.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub iq_steady_state_error_a: Option<f64>,
    /// Current-reference scenarios only: largest i_d once each response has settled, i.e.
    /// over the last quarter of every interval between current-reference events (the
    /// interval before the first one included), A. Flux strengthening shows as i_d > 0.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub id_max_a: Option<f64>,
}

/// Start of the i_d tracking-error window after the first i_d reference step, s.
pub const ID_ERROR_DELAY_S: f64 = 5e-3;

fn first_step_time(steps: &[drivelab_runtime::config::Step], after: f64) -> Option<f64> {
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
    // No speed reference (a current-reference study at a prescribed speed): no speed error.
    let speed_study = !refs.is_empty() || sc.reference.i_q_a.is_empty();
    if !tail.is_empty() && speed_study {
        out.steady_state_error_rad_s = Some(tail.iter().sum::<f64>() / tail.len() as f64);
    }
    if let Some(tl) = loads.iter().find(|s| s.value != 0.0) {
        let t0 = tl.t_s;
        // The load response ends at the next event (a speed step or another load change):
        // what follows is the response to that event, not to this load step.
        let t_end = [first_step_time(refs, t0), first_step_time(loads, t0)]
            .into_iter()
            .flatten()
            .fold(f64::INFINITY, f64::min);
        let after: Vec<&TraceRow> = rows.iter().filter(|r| r.t >= t0 && r.t < t_end).collect();
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
    if let Some((ss, conv)) = drivelab_runtime::wiring::observer_sensorless::angle_metrics(sc, rows)
    {
        out.angle_error_ss_deg = Some(ss);
        out.observer_convergence_ms = conv;
    }
    current_step_metrics(sc, rows, &mut out);
    out
}

/// The i_q step metrics of a current-reference scenario (`reference.i_q_a` non-empty).
fn current_step_metrics(sc: &Scenario, rows: &[TraceRow], out: &mut SpeedMetrics) {
    let iqs = &sc.reference.i_q_a;
    if iqs.is_empty() || rows.is_empty() {
        return;
    }
    let end = rows.last().map(|r| r.t).unwrap_or(0.0);
    // Current-reference events: every step of i_q* or i_d* after t = 0.
    let mut events: Vec<f64> = iqs
        .iter()
        .chain(&sc.reference.i_d_a)
        .map(|s| s.t_s)
        .filter(|&t| t > 0.0)
        .collect();
    events.sort_by(f64::total_cmp);
    events.dedup();
    if let Some(step) = iqs
        .iter()
        .find(|s| s.value != profile_at(iqs, s.t_s - 1e-9) || (s.t_s == 0.0 && s.value != 0.0))
    {
        let t0 = step.t_s;
        let before = if t0 > 0.0 {
            profile_at(iqs, t0 - 1e-9)
        } else {
            0.0
        };
        let size = step.value - before;
        let dir = size.signum();
        let next = events
            .iter()
            .copied()
            .find(|&t| t > t0 + 1e-12)
            .unwrap_or(end + 1.0);
        let window: Vec<&TraceRow> = rows
            .iter()
            .filter(|r| r.t >= t0 - 1e-12 && r.t < next)
            .collect();
        let crossing = |frac: f64| {
            window
                .iter()
                .find(|r| (r.i_q - before) * dir >= frac * size.abs())
                .map(|r| r.t)
        };
        if let (Some(t10), Some(t90)) = (crossing(0.1), crossing(0.9)) {
            out.iq_rise_time_us = Some((t90 - t10) * 1e6);
        }
        let peak = window
            .iter()
            .map(|r| (r.i_q - step.value) * dir)
            .fold(f64::NEG_INFINITY, f64::max);
        if peak.is_finite() && size != 0.0 {
            out.iq_overshoot_pct = Some(peak.max(0.0) / size.abs() * 100.0);
        }
    }
    let tail: Vec<f64> = rows
        .iter()
        .filter(|r| r.t >= 0.9 * end)
        .map(|r| profile_at(iqs, r.t) - r.i_q)
        .collect();
    if !tail.is_empty() {
        out.iq_steady_state_error_a = Some(tail.iter().sum::<f64>() / tail.len() as f64);
    }
    let mut bounds = vec![0.0];
    bounds.extend(events.iter().copied().filter(|&t| t < end));
    bounds.push(end + 1e-9);
    let id_max = bounds
        .windows(2)
        .flat_map(|w| {
            let from = w[1] - 0.25 * (w[1] - w[0]);
            rows.iter()
                .filter(move |r| r.t >= from - 1e-12 && r.t < w[1])
                .map(|r| r.i_d)
        })
        .fold(f64::NEG_INFINITY, f64::max);
    if id_max.is_finite() {
        out.id_max_a = Some(id_max);
    }
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
        assert!(m.steady_state_error_rad_s.unwrap().abs() < 1e-9);
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

    #[test]
    fn load_metrics_end_at_the_next_speed_step() {
        // Load at 50 ms (dip 5 rad/s for 10 ms), then a speed step 100 → 200 at 80 ms that the
        // motor follows slowly: that error is the step's, not the load's.
        let mut sc = sc();
        sc.reference
            .speed_rad_s
            .push(drivelab_runtime::config::Step {
                t_s: 0.08,
                value: 200.0,
            });
        let rows: Vec<TraceRow> = (0..1000)
            .map(|k| {
                let t = k as f64 * 1e-4;
                let w = if (0.05..0.06).contains(&t) {
                    95.0
                } else if t >= 0.08 {
                    100.0 + 1000.0 * (t - 0.08)
                } else {
                    100.0
                };
                TraceRow {
                    k,
                    t,
                    omega_m: w,
                    ..Default::default()
                }
            })
            .collect();
        let m = speed_metrics(&sc, &rows);
        assert!((m.load_dip_rad_s.unwrap() - 5.0).abs() < 1e-9, "{m:?}");
        let rec = m.load_recovery_ms.unwrap();
        assert!((rec - 10.0).abs() < 0.11, "recovery {rec} ms");
    }
}
