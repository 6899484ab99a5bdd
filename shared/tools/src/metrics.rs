//! Step-response metrics of a trace, measured against the scenario's reference profile.

use drivelab_runtime::config::{profile_at, Scenario};
use drivelab_runtime::trace::TraceRow;
use serde::Serialize;
use std::collections::BTreeMap;

/// Speed-loop metrics (`summary.json` → `metrics`).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct SpeedMetrics {
    /// The stage that makes the speed loop's reference (`wref`), when one does: the metrics
    /// measured against the scenario's speed reference and load steps do not apply and are
    /// left out.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub speed_reference_from: Option<String>,
    /// The speed a dynamometer held (`[mechanics] prescribed_speed_rad_s`), rad/s: the
    /// speed-response metrics (rise, overshoot, steady-state error, load dip and recovery)
    /// do not apply and are left out.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub speed_prescribed_rad_s: Option<f64>,
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
    /// The metrics whose window a fault's start fell into, each with what the fault did to
    /// it: `null` and "cut by the fault at T s (FAULT)" where the response had not settled
    /// before the fault (or, for a rise time, not reached the set-point), "measured up to the
    /// fault at …" where the figure is over the samples before it. Empty (left out) in a run
    /// without faults.
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub cut_by_fault: BTreeMap<String, String>,
}

/// Where a fault began (`summary.json` → `faults`: its `injected_t_s` and `fault`): it ends
/// every metrics window it falls into.
#[derive(Debug, Clone, PartialEq)]
pub struct FaultStart {
    /// The fault's first sample, s.
    pub t_s: f64,
    /// The fault as the report names it, e.g. `kill:current-loop@0.5`.
    pub fault: String,
}

impl FaultStart {
    /// Where its window ends: the rows before this are before the fault (a row's time and
    /// the fault's, both from the sample index, can differ in the last bit).
    fn cut_at(&self) -> f64 {
        self.t_s - 1e-9
    }
}

/// How long a response cut by a fault must have stayed within ±2 % of its reference just
/// before the fault for its figures over the samples before it to stand, s (the fault
/// reports' `speed_recovered_ms` holds as long).
pub const SETTLED_HOLD_S: f64 = 0.01;

/// The faults of a run, in order of their start.
struct Faults<'a> {
    starts: Vec<&'a FaultStart>,
    hold: usize,
}

impl<'a> Faults<'a> {
    fn new(sc: &Scenario, faults: &'a [FaultStart]) -> Self {
        let mut starts: Vec<&FaultStart> = faults.iter().filter(|f| f.t_s.is_finite()).collect();
        starts.sort_by(|a, b| a.t_s.total_cmp(&b.t_s));
        Faults {
            starts,
            hold: (SETTLED_HOLD_S * sc.rates.sample_hz).ceil().max(1.0) as usize,
        }
    }

    /// The first fault that starts in [from, to).
    fn within(&self, from: f64, to: f64) -> Option<&'a FaultStart> {
        self.starts
            .iter()
            .copied()
            .find(|f| f.t_s >= from - 1e-12 && f.t_s < to)
    }
}

/// Whether the last [`Faults::hold`] rows of `window` (the rows before a fault) are within
/// ±2 % of `reference`: the response had settled before the fault.
fn settled(window: &[&TraceRow], hold: usize, reference: impl Fn(&TraceRow) -> f64) -> bool {
    window.len() >= hold
        && window[window.len() - hold..].iter().all(|r| {
            let w = reference(r);
            (r.omega_m - w).abs() <= 0.02 * w.abs()
        })
}

/// Why `metric` is null: the fault `f` cut its window.
fn cut(out: &mut SpeedMetrics, metric: &str, f: &FaultStart) {
    out.cut_by_fault.insert(
        metric.into(),
        format!("cut by the fault at {:.3} s ({})", f.t_s, f.fault),
    );
}

/// Start of the i_d tracking-error window after the first i_d reference step, s.
pub const ID_ERROR_DELAY_S: f64 = 5e-3;

fn first_step_time(steps: &[drivelab_runtime::config::Step], after: f64) -> Option<f64> {
    steps.iter().map(|s| s.t_s).find(|&t| t > after)
}

/// Milliseconds from `t0` to `t` (s), to the nanosecond: a span of whole samples reads as
/// its exact decimal (196 samples at 10 kHz: 19.6 ms, not 19.599999999999998), so an
/// expectation's inclusive limit holds at it.
fn ms_after(t: f64, t0: f64) -> f64 {
    ((t - t0) * 1e9).round() / 1e6
}

/// Computes the speed metrics of `rows` for scenario `sc`, in a run without faults.
pub fn speed_metrics(sc: &Scenario, rows: &[TraceRow]) -> SpeedMetrics {
    speed_metrics_with_faults(sc, rows, &[])
}

/// Computes the speed metrics of `rows` for scenario `sc`, whose run had `faults`: a fault's
/// start ends every window it falls into, as the next reference or load step does. What
/// follows it is the fault's doing, not the response's: a figure whose response had not
/// completed before the fault is `None`, and `cut_by_fault` says why.
pub fn speed_metrics_with_faults(
    sc: &Scenario,
    rows: &[TraceRow],
    faults: &[FaultStart],
) -> SpeedMetrics {
    let mut out = SpeedMetrics::default();
    let faults = Faults::new(sc, faults);
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
            let rise = rows
                .iter()
                .find(|r| r.t >= t0 && (r.omega_m - target) * dir >= 0.0);
            // A fault before the speed reached the set-point: the rise is not the loop's.
            match (
                faults.within(t0, rise.map_or(f64::INFINITY, |r| r.t + 1e-12)),
                rise,
            ) {
                (Some(f), _) => cut(&mut out, "rise_time_ms", f),
                (None, r) => out.rise_time_ms = r.map(|r| ms_after(r.t, t0)),
            }
            let fault = faults.within(t0, next_event);
            let window: Vec<&TraceRow> = rows
                .iter()
                .filter(|r| r.t >= t0 && r.t < fault.map_or(next_event, FaultStart::cut_at))
                .collect();
            let peak = window
                .iter()
                .map(|r| (r.omega_m - target) * dir)
                .fold(f64::NEG_INFINITY, f64::max);
            match fault {
                // The peak before the fault is the overshoot only once the response had
                // settled: a later swing could have gone higher.
                Some(f) if !settled(&window, faults.hold, |_| target) => {
                    cut(&mut out, "overshoot_pct", f)
                }
                _ if peak.is_finite() => {
                    out.overshoot_pct = Some(peak.max(0.0) / (target - before).abs() * 100.0);
                }
                _ => {}
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
        // A fault within the last 10 %: the error there is the fault's, the part before it
        // too short a tail. So it is after an earlier fault the drive had not come back from
        // (the speed outside ±2 % of its reference somewhere in the last 10 %): a stage
        // killed for good, a drive left in its safe state.
        let tail_rows: Vec<&TraceRow> = rows.iter().filter(|r| r.t >= tail_start).collect();
        let earlier = faults.starts.iter().rev().find(|f| f.t_s < tail_start);
        match faults.within(tail_start, f64::INFINITY) {
            Some(f) => cut(&mut out, "steady_state_error_rad_s", f),
            None => match earlier {
                Some(f) if !settled(&tail_rows, tail_rows.len(), |r| profile_at(refs, r.t)) => {
                    out.cut_by_fault.insert(
                        "steady_state_error_rad_s".into(),
                        format!(
                            "cut by the fault at {:.3} s ({}): the speed was not back within \
                             ±2 % of its reference in the last 10 % of the run",
                            f.t_s, f.fault
                        ),
                    );
                }
                _ => {
                    out.steady_state_error_rad_s =
                        Some(tail.iter().sum::<f64>() / tail.len() as f64)
                }
            },
        }
    }
    if let Some(tl) = loads.iter().find(|s| s.value != 0.0) {
        let t0 = tl.t_s;
        // The load response ends at the next event (a speed step or another load change):
        // what follows is the response to that event, not to this load step.
        let t_end = [first_step_time(refs, t0), first_step_time(loads, t0)]
            .into_iter()
            .flatten()
            .fold(f64::INFINITY, f64::min);
        // So does a fault: the response to the load step is over only where the speed had
        // settled before it (the dip and the recovery over the samples before it stand).
        let first = faults.within(t0, t_end);
        let fault = first.filter(|f| {
            !settled(&pre_fault(rows, t0, f), faults.hold, |r| {
                profile_at(refs, r.t)
            })
        });
        if let Some(f) = fault {
            cut(&mut out, "load_dip_rad_s", f);
            cut(&mut out, "load_recovery_ms", f);
        }
        let t_end = first.map_or(t_end, FaultStart::cut_at);
        let after: Vec<&TraceRow> = rows.iter().filter(|r| r.t >= t0 && r.t < t_end).collect();
        let dip = after
            .iter()
            .map(|r| profile_at(refs, r.t) - r.omega_m)
            .fold(f64::NEG_INFINITY, f64::max);
        if dip.is_finite() && fault.is_none() {
            out.load_dip_rad_s = Some(dip);
        }
        // Last sample outside the ±2 % band; recovered just after it.
        let outside = after.iter().rposition(|r| {
            let w = profile_at(refs, r.t);
            (r.omega_m - w).abs() > 0.02 * w.abs()
        });
        out.load_recovery_ms = match outside {
            // A step at or after the last sample: no response to measure.
            _ if fault.is_some() || after.is_empty() => None,
            None => Some(0.0),
            Some(i) if i + 1 < after.len() => Some(ms_after(after[i + 1].t, t0)),
            Some(_) => None, // never recovered within the run
        };
    }
    let ids = &sc.reference.i_d_a;
    if let Some(step) = ids
        .iter()
        .find(|s| s.value != profile_at(ids, s.t_s - 1e-9) || (s.t_s == 0.0 && s.value != 0.0))
    {
        let t0 = step.t_s + ID_ERROR_DELAY_S;
        // Up to the end of the run or the first fault after the step: the error after it is
        // the fault's.
        let fault = faults.within(step.t_s, f64::INFINITY);
        let t_end = fault.map_or(f64::INFINITY, FaultStart::cut_at);
        let (sum, n) = rows
            .iter()
            .filter(|r| r.t >= t0 - 1e-12 && r.t < t_end)
            .map(|r| profile_at(ids, r.t) - r.i_d)
            .fold((0.0, 0usize), |(s, n), e| (s + e * e, n + 1));
        if n > 0 {
            out.id_tracking_error_a = Some((sum / n as f64).sqrt());
        }
        match fault {
            Some(f) if n > 0 => {
                out.cut_by_fault.insert(
                    "id_tracking_error_a".into(),
                    format!("measured up to the fault at {:.3} s ({})", f.t_s, f.fault),
                );
            }
            Some(f) => cut(&mut out, "id_tracking_error_a", f),
            None => {}
        }
    }
    if let Some((ss, conv)) = drivelab_runtime::wiring::observer_sensorless::angle_metrics(sc, rows)
    {
        out.angle_error_ss_deg = Some(ss);
        out.observer_convergence_ms = conv;
    }
    current_step_metrics(sc, rows, &faults, &mut out);
    if let Some(w) = sc.mechanics.prescribed_speed_rad_s {
        out.speed_prescribed_rad_s = Some(w);
        out.leave_out_speed_response();
    }
    out
}

impl SpeedMetrics {
    /// Leaves out the metrics of the speed's response to the scenario's reference and load
    /// steps (rise, overshoot, steady-state error, load dip and recovery), with any reason a
    /// fault gave for them: the speed did not follow that reference.
    pub fn leave_out_speed_response(&mut self) {
        self.rise_time_ms = None;
        self.overshoot_pct = None;
        self.steady_state_error_rad_s = None;
        self.load_dip_rad_s = None;
        self.load_recovery_ms = None;
        for m in [
            "rise_time_ms",
            "overshoot_pct",
            "steady_state_error_rad_s",
            "load_dip_rad_s",
            "load_recovery_ms",
        ] {
            self.cut_by_fault.remove(m);
        }
    }
}

/// The rows from `t0` up to the fault `f`.
fn pre_fault<'a>(rows: &'a [TraceRow], t0: f64, f: &FaultStart) -> Vec<&'a TraceRow> {
    rows.iter()
        .filter(|r| r.t >= t0 && r.t < f.cut_at())
        .collect()
}

/// The i_q step metrics of a current-reference scenario (`reference.i_q_a` non-empty).
fn current_step_metrics(sc: &Scenario, rows: &[TraceRow], faults: &Faults, out: &mut SpeedMetrics) {
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
        // A fault ends the window too: the rise stands where it was over before the fault,
        // the overshoot (whose peak could have come later) does not.
        let fault = faults.within(t0 - 1e-12, next);
        let window: Vec<&TraceRow> = rows
            .iter()
            .filter(|r| r.t >= t0 - 1e-12 && r.t < fault.map_or(next, FaultStart::cut_at))
            .collect();
        let crossing = |frac: f64| {
            window
                .iter()
                .find(|r| (r.i_q - before) * dir >= frac * size.abs())
                .map(|r| r.t)
        };
        match (crossing(0.1), crossing(0.9), fault) {
            (Some(t10), Some(t90), _) => out.iq_rise_time_us = Some((t90 - t10) * 1e6),
            (_, _, Some(f)) => cut(out, "iq_rise_time_us", f),
            _ => {}
        }
        let peak = window
            .iter()
            .map(|r| (r.i_q - step.value) * dir)
            .fold(f64::NEG_INFINITY, f64::max);
        match fault {
            Some(f) => cut(out, "iq_overshoot_pct", f),
            None if peak.is_finite() && size != 0.0 => {
                out.iq_overshoot_pct = Some(peak.max(0.0) / size.abs() * 100.0);
            }
            None => {}
        }
    }
    let tail: Vec<f64> = rows
        .iter()
        .filter(|r| r.t >= 0.9 * end)
        .map(|r| profile_at(iqs, r.t) - r.i_q)
        .collect();
    if !tail.is_empty() {
        match faults.within(0.9 * end, f64::INFINITY) {
            Some(f) => cut(out, "iq_steady_state_error_a", f),
            None => {
                out.iq_steady_state_error_a = Some(tail.iter().sum::<f64>() / tail.len() as f64)
            }
        }
    }
    let mut bounds = vec![0.0];
    bounds.extend(events.iter().copied().filter(|&t| t < end));
    bounds.push(end + 1e-9);
    // An interval a fault falls into has no settled quarter: the end of the interval is the
    // fault's doing. It is left out.
    let mut left_out = None;
    let id_max = bounds
        .windows(2)
        .filter(|w| match faults.within(w[0], w[1]) {
            Some(f) => {
                left_out.get_or_insert(f);
                false
            }
            None => true,
        })
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
    if let Some(f) = left_out {
        let why = if id_max.is_finite() {
            format!(
                "leaves out the interval cut by the fault at {:.3} s ({})",
                f.t_s, f.fault
            )
        } else {
            format!("cut by the fault at {:.3} s ({})", f.t_s, f.fault)
        };
        out.cut_by_fault.insert("id_max_a".into(), why);
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

    /// ω rises linearly to 110 at 10 ms, falls to 100 at 20 ms, dips by 5 at 50 ms and
    /// comes back at 60 ms.
    fn synthetic_speed(t: f64) -> f64 {
        if t < 0.01 {
            11_000.0 * t
        } else if t < 0.02 {
            110.0 - 1000.0 * (t - 0.01)
        } else if (0.05..0.06).contains(&t) {
            95.0
        } else {
            100.0
        }
    }

    #[test]
    fn synthetic_response() {
        let rows: Vec<TraceRow> = (0..1000)
            .map(|k| {
                let t = k as f64 * 1e-4;
                let w = synthetic_speed(t);
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

    /// A load step at or after the trace's last sample (a run that ends at it) has no
    /// response: no dip and no recovery, rather than a recovery of 0 ms.
    #[test]
    fn a_load_step_after_the_last_sample_has_no_metrics() {
        let rows: Vec<TraceRow> = (0..500)
            .map(|k| {
                let t = k as f64 * 1e-4;
                TraceRow {
                    k,
                    t,
                    omega_m: synthetic_speed(t),
                    ..Default::default()
                }
            })
            .collect();
        let m = speed_metrics(&sc(), &rows);
        assert_eq!(
            (m.load_dip_rad_s, m.load_recovery_ms),
            (None, None),
            "{m:?}"
        );
        // One sample after the step, in the band: a response of one sample, recovered.
        let mut one = rows.clone();
        one.push(TraceRow {
            k: 500,
            t: 0.05,
            omega_m: 100.0,
            ..Default::default()
        });
        let m = speed_metrics(&sc(), &one);
        assert_eq!(
            (m.load_dip_rad_s, m.load_recovery_ms),
            (Some(0.0), Some(0.0)),
            "{m:?}"
        );
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

    /// The synthetic response of `synthetic_response`, then at 80 ms a fault that drops the
    /// speed to 50 rad/s for the rest of the run.
    fn faulted_rows() -> Vec<TraceRow> {
        (0..1000)
            .map(|k| {
                let t = k as f64 * 1e-4;
                let w = if t >= 0.08 { 50.0 } else { synthetic_speed(t) };
                TraceRow {
                    k,
                    t,
                    omega_m: w,
                    i_d: if t < 0.02 { 0.0 } else { -1.0 },
                    ..Default::default()
                }
            })
            .collect()
    }

    fn fault_at(t_s: f64) -> Vec<FaultStart> {
        vec![FaultStart {
            t_s,
            fault: format!("kill:current-loop@{t_s}"),
        }]
    }

    #[test]
    fn a_fault_after_the_load_response_settled_leaves_it_as_it_was() {
        // Recovered at 60 ms, in the band until the fault at 80 ms: the fault is no part of
        // the load response (without the fault's start the drop at 80 ms never recovers).
        let rows = faulted_rows();
        assert_eq!(speed_metrics(&sc(), &rows).load_recovery_ms, None);
        let m = speed_metrics_with_faults(&sc(), &rows, &fault_at(0.08));
        assert!((m.load_dip_rad_s.unwrap() - 5.0).abs() < 1e-9, "{m:?}");
        assert!((m.load_recovery_ms.unwrap() - 10.0).abs() < 0.11, "{m:?}");
        assert!(!m.cut_by_fault.contains_key("load_recovery_ms"), "{m:?}");
        // The rise and the overshoot were over long before.
        assert!((m.rise_time_ms.unwrap() - 100.0 / 11_000.0 * 1e3).abs() < 0.11);
        assert!((m.overshoot_pct.unwrap() - 10.0).abs() < 0.2);
        // The i_d error is measured up to the fault, and says so.
        assert_eq!(m.id_tracking_error_a, Some(0.0), "{m:?}");
        assert_eq!(
            m.cut_by_fault["id_tracking_error_a"],
            "measured up to the fault at 0.080 s (kill:current-loop@0.08)"
        );
        // The last 10 % (90..99.9 ms) holds no fault's start, but the speed never came back
        // from the fault (50 rad/s off): its error is the fault's, not the loop's.
        assert_eq!(m.steady_state_error_rad_s, None, "{m:?}");
        assert_eq!(
            m.cut_by_fault["steady_state_error_rad_s"],
            "cut by the fault at 0.080 s (kill:current-loop@0.08): the speed was not back \
             within ±2 % of its reference in the last 10 % of the run"
        );
        // Without the fault, the same tail is the loop's error.
        assert!(
            (speed_metrics(&sc(), &rows)
                .steady_state_error_rad_s
                .unwrap()
                - 50.0)
                .abs()
                < 1e-9
        );
        // A fault the drive came back from (the load dip's speed, back at 100 rad/s from 60 ms
        // on): the last 10 % is the loop's again.
        let back: Vec<TraceRow> = (0..1000)
            .map(|k| TraceRow {
                k,
                t: k as f64 * 1e-4,
                omega_m: synthetic_speed(k as f64 * 1e-4),
                ..Default::default()
            })
            .collect();
        let m = speed_metrics_with_faults(&sc(), &back, &fault_at(0.055));
        assert_eq!(m.steady_state_error_rad_s, Some(0.0), "{m:?}");
        assert!(
            !m.cut_by_fault.contains_key("steady_state_error_rad_s"),
            "{m:?}"
        );
    }

    #[test]
    fn a_fault_inside_the_load_response_leaves_no_figure_measured_over_it() {
        // The fault at 55 ms falls into the dip (50..60 ms): the response is not over, so the
        // dip and the recovery are null, with why; before the fix they were measured over the
        // fault (a 50 rad/s dip that never recovered: recovery null without a reason).
        let rows = faulted_rows();
        let before = speed_metrics(&sc(), &rows);
        assert_eq!(before.load_dip_rad_s, Some(50.0));
        let m = speed_metrics_with_faults(&sc(), &rows, &fault_at(0.055));
        assert_eq!(
            (m.load_dip_rad_s, m.load_recovery_ms),
            (None, None),
            "{m:?}"
        );
        for metric in ["load_dip_rad_s", "load_recovery_ms"] {
            assert_eq!(
                m.cut_by_fault[metric], "cut by the fault at 0.055 s (kill:current-loop@0.055)",
                "{m:?}"
            );
        }
        // The fault during the rise: no rise time, no overshoot.
        let m = speed_metrics_with_faults(&sc(), &rows, &fault_at(0.005));
        assert_eq!((m.rise_time_ms, m.overshoot_pct), (None, None), "{m:?}");
        assert!(m.cut_by_fault.contains_key("rise_time_ms"), "{m:?}");
        assert!(m.cut_by_fault.contains_key("overshoot_pct"), "{m:?}");
        // After the speed reached the set-point, before it settled: the rise stands.
        let m = speed_metrics_with_faults(&sc(), &rows, &fault_at(0.015));
        assert!(
            m.rise_time_ms.is_some() && m.overshoot_pct.is_none(),
            "{m:?}"
        );
        // A fault in the last 10 %: no steady-state error.
        let m = speed_metrics_with_faults(&sc(), &rows, &fault_at(0.095));
        assert_eq!(m.steady_state_error_rad_s, None, "{m:?}");
        assert!(m.cut_by_fault.contains_key("steady_state_error_rad_s"));
    }

    #[test]
    fn a_load_response_cut_before_it_stayed_settled_is_null() {
        // Back in the band at 60 ms, the fault 5 ms later (less than the 10 ms hold): the
        // recovery is not known.
        let rows = faulted_rows();
        let m = speed_metrics_with_faults(&sc(), &rows, &fault_at(0.065));
        assert_eq!(m.load_recovery_ms, None, "{m:?}");
        assert!(m.cut_by_fault.contains_key("load_recovery_ms"), "{m:?}");
        // No fault: no reasons, and nothing of them in the JSON.
        let m = speed_metrics(&sc(), &rows);
        assert!(m.cut_by_fault.is_empty());
        let json = serde_json::to_value(&m).unwrap();
        assert!(json.get("cut_by_fault").is_none(), "{json}");
    }
    #[test]
    fn a_span_of_whole_samples_is_its_decimal_in_ms() {
        // 196 samples at 10 kHz after a step at 40 ms: 19.6 ms, which the plain difference
        // misses by one unit in the last place.
        let (t, t0) = (596.0 / 1e4, 0.04);
        assert_ne!((t - t0) * 1e3, 19.6);
        assert_eq!(ms_after(t, t0), 19.6);
        assert_eq!(ms_after(0.0081, 0.0), 8.1);
    }
}
