//! Per-stage figures of each second of a run, from the services' statuses: the statuses carry
//! counters and histograms since the service started, so one second's figures are the
//! difference between the first status at or past the second's end (on the grid of whole
//! seconds of simulated time) and the one that opened it. A restarted service (another pid) starts again from zero.

use drivelab_runtime::telemetry::{bucket_upper_ns, CompactHist, ServiceStatus, BUCKETS};
use serde::Serialize;

/// Percentiles of one histogram over one second, µs.
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct Pct {
    /// Values recorded.
    pub count: u64,
    /// Median, µs.
    pub p50: f64,
    /// 99th percentile, µs.
    pub p99: f64,
    /// 99.9th percentile, µs.
    pub p999: f64,
    /// Largest, µs.
    pub max: f64,
}

/// One stage over one second of the run (`/services` in `trace.mcap` and the live stream).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ServiceSecond {
    /// Stage.
    pub service: String,
    /// First sample of the second.
    pub k_from: u64,
    /// The sample after its last.
    pub k_to: u64,
    /// End of the second, simulated s.
    pub t_s: f64,
    /// Samples processed.
    pub samples: u64,
    /// Samples per wall second.
    pub rate_hz: f64,
    /// Deadline misses.
    pub misses: u64,
    /// Inputs not there when needed.
    pub stale_inputs: u64,
    /// Inputs rejected.
    pub rejected_inputs: u64,
    /// Plant: release lateness; controllers: bus hop, µs.
    pub wake_us: Option<Pct>,
    /// Execution time of the step, µs.
    pub exec_us: Option<Pct>,
    /// Plant only: cycle latency, µs.
    pub cycle_us: Option<Pct>,
}

/// `now − before` of two cumulative histograms of one process; None when nothing was
/// recorded in between. The maximum is exact when it grew, else the upper edge of the
/// highest bucket that grew.
fn diff(now: &CompactHist, before: &CompactHist) -> Option<Pct> {
    let mut h = CompactHist {
        count: now.count.saturating_sub(before.count),
        ..Default::default()
    };
    if h.count == 0 {
        return None;
    }
    for b in 0..BUCKETS {
        h.counts[b] = now.counts[b].saturating_sub(before.counts[b]);
    }
    h.max_ns = if now.max_ns > before.max_ns {
        now.max_ns
    } else {
        let top = (0..BUCKETS).rev().find(|&b| h.counts[b] > 0).unwrap_or(0);
        bucket_upper_ns(top).min(now.max_ns)
    };
    let us = |q: f64| h.quantile_ns(q) as f64 * 1e-3;
    Some(Pct {
        count: h.count,
        p50: us(0.5),
        p99: us(0.99),
        p999: us(0.999),
        max: h.max_ns as f64 * 1e-3,
    })
}

/// Turns each stage's statuses into one [`ServiceSecond`] per second of simulated time.
#[derive(Debug)]
pub struct PerSecond {
    samples_per_second: u64,
    sample_hz: f64,
    /// Per stage: the status that opened its current second (None: before its first).
    open: Vec<Option<ServiceStatus>>,
}

impl PerSecond {
    /// For `stages` stages sampled at `sample_hz`.
    pub fn new(stages: usize, sample_hz: f64) -> Self {
        Self {
            samples_per_second: (sample_hz.round() as u64).max(1),
            sample_hz,
            open: vec![None; stages],
        }
    }

    /// Takes stage `name`'s status (its index in the topology: `st.service`); returns the
    /// second it closes, if it does.
    pub fn offer(&mut self, name: &str, st: &ServiceStatus) -> Option<ServiceSecond> {
        let slot = self.open.get_mut(st.service as usize)?;
        let before = match slot {
            Some(b) if b.pid == st.pid && st.samples >= b.samples => *b,
            // A first status on a whole second (a drive's first, at sample 0) opens that
            // second itself, with its wall time: the second's rate is known.
            _ if st.hdr.k.is_multiple_of(self.samples_per_second) => {
                *slot = Some(*st);
                return None;
            }
            // A first status or a restarted process: its counters start at zero, its
            // second at the sample it had reached (rounded down to a whole second).
            _ => ServiceStatus {
                hdr: drivelab_runtime::messages::Header {
                    k: st.hdr.k - st.hdr.k % self.samples_per_second,
                    ..Default::default()
                },
                pid: st.pid,
                ..Default::default()
            },
        };
        if slot.is_none() || slot.is_some_and(|b| b.pid != st.pid) {
            *slot = Some(before);
        }
        // Seconds on the grid of whole seconds, whenever the statuses come.
        let end = (before.hdr.k / self.samples_per_second + 1) * self.samples_per_second;
        if st.hdr.k < end {
            return None;
        }
        *slot = Some(*st);
        Some(self.second(name, &before, st))
    }

    /// Closes stage `name`'s open second at its last status `st` (the run ended inside it):
    /// the part second up to `st`, if `st` is newer than the status that opened it.
    pub fn close(&mut self, name: &str, st: &ServiceStatus) -> Option<ServiceSecond> {
        let slot = self.open.get_mut(st.service as usize)?;
        let before = slot.filter(|b| b.pid == st.pid && st.hdr.k > b.hdr.k)?;
        *slot = Some(*st);
        Some(self.second(name, &before, st))
    }

    /// The figures between two statuses of one process.
    fn second(&self, name: &str, before: &ServiceStatus, st: &ServiceStatus) -> ServiceSecond {
        let dt_s = st.hdr.t_pub_ns.saturating_sub(before.hdr.t_pub_ns) as f64 * 1e-9;
        let samples = st.samples.saturating_sub(before.samples);
        ServiceSecond {
            service: name.to_string(),
            k_from: before.hdr.k,
            k_to: st.hdr.k,
            t_s: st.hdr.k as f64 / self.sample_hz,
            samples,
            rate_hz: if before.hdr.t_pub_ns > 0 && dt_s > 0.0 {
                samples as f64 / dt_s
            } else {
                0.0
            },
            misses: st.misses.saturating_sub(before.misses),
            stale_inputs: st.stale_inputs.saturating_sub(before.stale_inputs),
            rejected_inputs: st.rejected_inputs.saturating_sub(before.rejected_inputs),
            wake_us: diff(&st.wake, &before.wake),
            exec_us: diff(&st.exec, &before.exec),
            cycle_us: diff(&st.cycle, &before.cycle),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn status(k: u64, pid: u32, t_s: f64, exec_ns: &[i64]) -> ServiceStatus {
        let mut s = ServiceStatus {
            pid,
            samples: k,
            misses: k / 1000,
            ..Default::default()
        };
        s.hdr.k = k;
        s.hdr.t_pub_ns = (t_s * 1e9) as u64;
        for &v in exec_ns {
            s.exec.record_ns(v);
        }
        s
    }

    #[test]
    fn a_second_is_the_difference_of_the_statuses_around_it() {
        let mut p = PerSecond::new(1, 1000.0);
        // Cumulative: 3 values of 10 µs by sample 500, then 2 more of 40 µs by sample 1000.
        assert!(p
            .offer("plant", &status(500, 7, 0.5, &[10_000; 3]))
            .is_none());
        let mut s = status(1000, 7, 1.25, &[10_000; 3]);
        s.exec.record_ns(40_000);
        s.exec.record_ns(40_000);
        let sec = p.offer("plant", &s).unwrap();
        // The second opened at sample 0 (the first status, rounded down), with nothing yet.
        assert_eq!(
            (sec.k_from, sec.k_to, sec.samples, sec.misses),
            (0, 1000, 1000, 1)
        );
        assert_eq!(sec.rate_hz, 0.0, "no wall time for the opening: no rate");
        let e = sec.exec_us.unwrap();
        assert_eq!((e.count, e.max), (5, 40.0));
        assert!(e.p50 >= 10.0 && e.p50 < 12.0, "{e:?}");
        assert!(sec.cycle_us.is_none());
        // The next second: only what was recorded in it, its maximum within its bucket.
        let mut s2 = s;
        s2.hdr.k = 2000;
        s2.samples = 2000;
        s2.misses = 2;
        s2.hdr.t_pub_ns = 2_250_000_000;
        s2.exec.record_ns(20_000);
        let sec = p.offer("plant", &s2).unwrap();
        assert_eq!(
            (sec.k_from, sec.samples, sec.misses, sec.rate_hz),
            (1000, 1000, 1, 1000.0)
        );
        let e = sec.exec_us.unwrap();
        assert_eq!(e.count, 1);
        assert!(e.max >= 20.0 && e.max < 24.0, "{e:?}");
    }

    #[test]
    fn a_restarted_process_starts_from_zero() {
        let mut p = PerSecond::new(2, 1000.0);
        p.offer("observer", &{
            let mut s = status(900, 7, 0.9, &[10_000; 100]);
            s.service = 1;
            s
        });
        let mut s = status(1500, 8, 1.5, &[5_000; 2]);
        s.service = 1;
        s.samples = 2;
        assert!(p.offer("observer", &s).is_none());
        let mut s = status(2100, 8, 2.1, &[5_000; 3]);
        s.service = 1;
        s.samples = 602;
        let sec = p.offer("observer", &s).unwrap();
        assert_eq!((sec.k_from, sec.samples), (1000, 602));
        assert_eq!(sec.exec_us.unwrap().count, 3);
        // An index beyond the topology is ignored.
        let mut s = status(5000, 9, 5.0, &[]);
        s.service = 2;
        assert!(p.offer("x", &s).is_none());
    }

    #[test]
    fn a_first_status_at_sample_0_gives_the_first_second_its_rate_and_the_end_closes_the_last() {
        let mut p = PerSecond::new(1, 1000.0);
        assert!(p.offer("plant", &status(0, 7, 0.25, &[10_000])).is_none());
        let sec = p
            .offer("plant", &status(1000, 7, 1.25, &[10_000; 3]))
            .unwrap();
        assert_eq!((sec.k_from, sec.k_to, sec.samples), (0, 1000, 1000));
        assert_eq!(sec.rate_hz, 1000.0, "the opening status has its wall time");
        assert_eq!(
            sec.exec_us.unwrap().count,
            2,
            "the second after sample 0's status"
        );
        // The run ends at sample 1499: its last status closes the part second.
        let last = status(1499, 7, 1.75, &[10_000; 5]);
        assert!(p.offer("plant", &last).is_none(), "not a whole second");
        let sec = p.close("plant", &last).unwrap();
        assert_eq!((sec.k_from, sec.k_to, sec.samples), (1000, 1499, 499));
        assert_eq!(sec.rate_hz, 998.0);
        assert_eq!(sec.exec_us.unwrap().count, 2);
        // Nothing newer: nothing more to close; another process's status closes nothing.
        assert!(p.close("plant", &last).is_none());
        assert!(p.close("plant", &status(1600, 8, 1.9, &[])).is_none());
    }
}
