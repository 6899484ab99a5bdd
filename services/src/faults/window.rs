//! The trace before a fault against the trace during it: deadline misses, speed and
//! current ripple and the angle estimate's error over two sample ranges, for the hog and the
//! sensor faults' reports (`summary.json → faults → window`).

use crate::launcher::FaultReport;
use drivelab_runtime::config::Scenario;
use drivelab_runtime::messages::FLAG_SAFE_STATE;
use drivelab_runtime::trace::TraceRow;
use serde::Serialize;
use std::ops::Range;

/// A figure before the fault and during it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Pair<T> {
    /// Over the samples before the fault.
    pub before: T,
    /// Over the samples during the fault (after it, for a fault that lasts to the end).
    pub during: T,
}

/// `summary.json → faults → window`.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct FaultWindow {
    /// Samples compared before the fault: [first, end).
    pub before_k: [u64; 2],
    /// Samples compared during the fault: [first, end).
    pub during_k: [u64; 2],
    /// Samples in the trace with `miss` = 1.
    pub deadline_misses: Pair<u64>,
    /// Cycle latency (t_k → command k published) p99, µs; real-time runs with a hog only.
    pub cycle_p99_us: Option<Pair<f64>>,
    /// A hog's recovery: the drive back on its schedule (every command before its deadline
    /// for 10 ms) after the hog's end, ms after the hog's start; None: not within the
    /// samples the recorder kept, or not a hog.
    pub cycle_recovered_ms: Option<f64>,
    /// Peak-to-peak true speed ω_m, mechanical rad/s.
    pub speed_p2p_rad_s: Pair<f64>,
    /// Peak-to-peak true d current, A.
    pub i_d_p2p_a: Pair<f64>,
    /// Peak-to-peak true q current, A.
    pub i_q_p2p_a: Pair<f64>,
    /// Largest |θ̂ − θ_e| (the controllers' angle against the true one), electrical rad.
    pub angle_error_max_rad: Pair<f64>,
}

/// Peak to peak of `f` over `rows` (0 for none).
fn p2p<'a>(rows: impl Iterator<Item = &'a TraceRow>, f: impl Fn(&TraceRow) -> f64) -> f64 {
    let (lo, hi) = rows.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), r| {
        (lo.min(f(r)), hi.max(f(r)))
    });
    if hi >= lo {
        hi - lo
    } else {
        0.0
    }
}

/// θ̂ − θ_e wrapped to [−π, π), rad.
pub fn angle_error(r: &TraceRow) -> f64 {
    use std::f64::consts::{PI, TAU};
    (r.theta_hat - r.theta_e + PI).rem_euclid(TAU) - PI
}

/// The rows of `rows` with k in `range`.
fn of<'a>(rows: &'a [TraceRow], range: &'a Range<u64>) -> impl Iterator<Item = &'a TraceRow> + 'a {
    rows.iter().filter(move |r| range.contains(&r.k))
}

/// The figures of `rows` over `before` and `during` (sample ranges).
pub fn window(rows: &[TraceRow], before: Range<u64>, during: Range<u64>) -> FaultWindow {
    let pair = |f: &dyn Fn(&Range<u64>) -> f64| Pair {
        before: f(&before),
        during: f(&during),
    };
    FaultWindow {
        before_k: [before.start, before.end],
        during_k: [during.start, during.end],
        deadline_misses: Pair {
            before: of(rows, &before).filter(|r| r.miss != 0).count() as u64,
            during: of(rows, &during).filter(|r| r.miss != 0).count() as u64,
        },
        cycle_p99_us: None,
        cycle_recovered_ms: None,
        speed_p2p_rad_s: pair(&|w| p2p(of(rows, w), |r| r.omega_m)),
        i_d_p2p_a: pair(&|w| p2p(of(rows, w), |r| r.i_d)),
        i_q_p2p_a: pair(&|w| p2p(of(rows, w), |r| r.i_q)),
        angle_error_max_rad: pair(&|w| {
            of(rows, w)
                .map(|r| angle_error(r).abs())
                .fold(0.0, f64::max)
        }),
    }
}

/// A report for a fault that no stage's liveness shows (a sensor fault): safe state, peak
/// current and speed recovery after the fault's end `k1`, in ms from its start `k0`, and
/// the window figures `w`. No detection or republication figures (nothing goes stale).
pub fn report(
    sc: &Scenario,
    rows: &[TraceRow],
    fault: String,
    k0: u64,
    k1: u64,
    w: FaultWindow,
) -> FaultReport {
    let fs = sc.rates.sample_hz;
    let ms = |dk: u64| dk as f64 * 1e3 / fs;
    let after: Vec<&TraceRow> = rows.iter().filter(|r| r.k >= k0).collect();
    let tail: Vec<&TraceRow> = after.iter().copied().filter(|r| r.k >= k1).collect();
    let rec = crate::launcher::speed_recovered(sc, &tail);
    let k_end = rec.unwrap_or(k1.saturating_add((0.2 * fs) as u64));
    FaultReport {
        fault,
        service: "-".into(),
        process: "-".into(),
        injected_k: k0,
        injected_t_s: k0 as f64 / fs,
        detected_data_path_ms: None,
        detected_by: None,
        detected_supervisor_ms: None,
        // Up to the recovery: a later safe state is not this fault's.
        safe_state_ms: after
            .iter()
            .take_while(|r| r.k <= k_end)
            .find(|r| r.plant_flags & FLAG_SAFE_STATE != 0)
            .map(|r| ms(r.k - k0)),
        peak_current_a: after
            .iter()
            .filter(|r| r.k <= k_end)
            .map(|r| r.i_d.hypot(r.i_q))
            .fold(0.0, f64::max),
        republished_ms: None,
        speed_recovered_ms: rec.map(|k| ms(k - k0)),
        plant_down: None,
        samples: crate::launcher::SampleCounts::of(
            after.iter().copied().take_while(|r| r.k <= k_end),
        ),
        bus: None,
        window: Some(w),
        why_null: {
            // What a null means here is not what it means for a kill: every stage went on
            // publishing fresh messages, only their values were wrong.
            let mut notes = crate::launcher::recovery_notes(sc, &tail, rec);
            for (figure, why) in [
                (
                    "detected_data_path_ms",
                    "a sensor fault: every input stayed fresh, its values were wrong (see window)",
                ),
                ("detected_supervisor_ms", "a sensor fault: no process died"),
                (
                    "republished_ms",
                    "a sensor fault: every stage went on publishing",
                ),
            ] {
                notes.insert(figure, why.to_string());
            }
            notes
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn figures_compare_the_two_ranges() {
        let rows: Vec<TraceRow> = (0..20u64)
            .map(|k| TraceRow {
                k,
                omega_m: if k >= 10 && k % 2 == 0 { 101.0 } else { 100.0 },
                i_q: if k >= 10 { (k % 3) as f64 } else { 1.0 },
                theta_e: 0.1,
                theta_hat: if k == 12 { 6.2 } else { 0.1 },
                miss: u8::from(k == 3 || k == 15 || k == 16),
                ..Default::default()
            })
            .collect();
        let w = window(&rows, 0..10, 10..20);
        assert_eq!(w.before_k, [0, 10]);
        assert_eq!(
            w.deadline_misses,
            Pair {
                before: 1,
                during: 2
            }
        );
        assert_eq!(
            w.speed_p2p_rad_s,
            Pair {
                before: 0.0,
                during: 1.0
            }
        );
        assert_eq!(
            w.i_q_p2p_a,
            Pair {
                before: 0.0,
                during: 2.0
            }
        );
        // 6.2 − 0.1 wraps to −0.18 rad.
        assert!((w.angle_error_max_rad.during - (std::f64::consts::TAU - 6.1)).abs() < 1e-12);
        assert_eq!(w.angle_error_max_rad.before, 0.0);
        assert_eq!(window(&rows, 30..40, 40..50).speed_p2p_rad_s.during, 0.0);
    }
}
