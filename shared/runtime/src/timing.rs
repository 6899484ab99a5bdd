//! Preallocated latency histograms (HdrHistogram) and deadline-miss counting.
//!
//! Recording never allocates: the histogram is created once with fixed bounds and values
//! beyond them are clamped (and counted as such by the max).

use hdrhistogram::Histogram;
use serde::Serialize;

/// Highest value a histogram stores without clamping: 10 s in ns.
pub const MAX_NS: u64 = 10_000_000_000;

/// A named latency histogram in nanoseconds.
#[derive(Debug, Clone)]
pub struct LatencyHist {
    /// Name, e.g. `cycle` or `plant.lateness`.
    pub name: &'static str,
    h: Histogram<u64>,
    /// Values above [`MAX_NS`] (clamped).
    pub clamped: u64,
    /// The same values in a fixed-size histogram for live telemetry (`drivelab monitor`).
    pub compact: crate::telemetry::CompactHist,
}

/// Percentiles of one histogram in µs (`summary.json` → `latency_us.<name>`).
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct Percentiles {
    /// Median, µs.
    pub p50: f64,
    /// 99th percentile, µs.
    pub p99: f64,
    /// 99.9th percentile, µs.
    pub p999: f64,
    /// Maximum, µs.
    pub max: f64,
    /// Number of values.
    pub count: u64,
}

impl LatencyHist {
    /// Creates a histogram covering 1 ns .. 10 s at 3 significant digits.
    pub fn new(name: &'static str) -> Self {
        Self {
            name,
            h: Histogram::new_with_bounds(1, MAX_NS, 3).expect("static bounds are valid"),
            clamped: 0,
            compact: crate::telemetry::CompactHist::default(),
        }
    }

    /// Records one value in ns (negative deltas record as 0). No allocation.
    #[inline]
    pub fn record_ns(&mut self, v: i64) {
        self.compact.record_ns(v);
        let v = v.max(0) as u64;
        if v > MAX_NS {
            self.clamped += 1;
        }
        self.h.saturating_record(v.clamp(1, MAX_NS));
    }

    /// Number of values.
    pub fn len(&self) -> u64 {
        self.h.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.h.is_empty()
    }

    /// Number of values above `v` ns (a value within the resolution of `v`, 0.1 %, counts as
    /// not above).
    pub fn count_above_ns(&self, v: u64) -> u64 {
        self.h.len() - self.h.count_between(0, v.min(MAX_NS))
    }

    /// Value at quantile q (0..=1), ns.
    pub fn quantile_ns(&self, q: f64) -> u64 {
        self.h.value_at_quantile(q)
    }

    /// Adds `other`'s values to these (e.g. the rounds of a bench variant).
    pub fn add(&mut self, other: &LatencyHist) -> anyhow::Result<()> {
        self.h
            .add(&other.h)
            .map_err(|e| anyhow::anyhow!("merge histogram {}: {e:?}", self.name))?;
        self.clamped += other.clamped;
        self.compact.add(&other.compact);
        Ok(())
    }

    /// The usual tail summary in µs.
    pub fn percentiles(&self) -> Percentiles {
        let us = |v: u64| v as f64 / 1e3;
        Percentiles {
            p50: us(self.h.value_at_quantile(0.5)),
            p99: us(self.h.value_at_quantile(0.99)),
            p999: us(self.h.value_at_quantile(0.999)),
            max: us(self.h.max()),
            count: self.h.len(),
        }
    }

    /// Percentile curve (percentile, value µs) for plots, HdrHistogram-style.
    pub fn curve(&self) -> Vec<(f64, f64)> {
        let mut v = Vec::new();
        if self.h.is_empty() {
            return v;
        }
        for it in self.h.iter_quantiles(2) {
            let q = it.quantile_iterated_to();
            if q < 1.0 {
                v.push((q * 100.0, it.value_iterated_to() as f64 / 1e3));
            }
        }
        v
    }

    /// The `.hgrm` percentile-distribution text (HistogramLogProcessor format, values in µs).
    pub fn hgrm(&self) -> String {
        let mut s = String::from("       Value     Percentile TotalCount 1/(1-Percentile)\n\n");
        if self.h.is_empty() {
            return s;
        }
        for it in self.h.iter_quantiles(5) {
            let q = it.quantile_iterated_to();
            let inv = if q < 1.0 {
                format!("{:.2}", 1.0 / (1.0 - q))
            } else {
                "inf".into()
            };
            s.push_str(&format!(
                "{:12.3} {:14.12} {:10} {:>14}\n",
                it.value_iterated_to() as f64 / 1e3,
                q,
                it.count_since_last_iteration(),
                inv
            ));
        }
        let p = self.percentiles();
        s.push_str(&format!(
            "#[Mean    = {:12.3}, StdDeviation   = {:12.3}]\n#[Max     = {:12.3}, Total count    = {:12}]\n",
            self.h.mean() / 1e3,
            self.h.stdev() / 1e3,
            p.max,
            p.count
        ));
        s
    }

    /// Writes the histogram in the HdrHistogram V2 binary format (for merging by another
    /// process).
    pub fn write_v2(&self, path: &std::path::Path) -> anyhow::Result<()> {
        use hdrhistogram::serialization::{Serializer, V2Serializer};
        let mut buf = Vec::new();
        V2Serializer::new()
            .serialize(&self.h, &mut buf)
            .map_err(|e| anyhow::anyhow!("serialise {}: {e:?}", self.name))?;
        crate::files::write(path, buf).map_err(|e| anyhow::anyhow!("write {}: {e}", path.display()))
    }

    /// Reads a histogram written by [`LatencyHist::write_v2`].
    pub fn read_v2(name: &'static str, path: &std::path::Path) -> anyhow::Result<Self> {
        use hdrhistogram::serialization::Deserializer;
        let bytes =
            std::fs::read(path).map_err(|e| anyhow::anyhow!("read {}: {e}", path.display()))?;
        let h: Histogram<u64> = Deserializer::new()
            .deserialize(&mut &bytes[..])
            .map_err(|e| {
                use hdrhistogram::serialization::DeserializeError;
                // What a writer that was killed, or found the disk full, leaves: said plainly.
                let why = match e {
                    _ if bytes.is_empty() => "empty".to_string(),
                    DeserializeError::IoError(io)
                        if io.kind() == std::io::ErrorKind::UnexpectedEof =>
                    {
                        format!("cut short ({} bytes)", bytes.len())
                    }
                    other => format!("{other:?}"),
                };
                anyhow::anyhow!("{}: not an HdrHistogram V2 file: {why}", path.display())
            })?;
        // The compact twin is live telemetry only; a histogram read back has none.
        Ok(Self {
            name,
            h,
            clamped: 0,
            compact: crate::telemetry::CompactHist::default(),
        })
    }
}

/// Deadline-miss bookkeeping: total and longest run of consecutive misses.
#[derive(Debug, Clone, Copy, Default, Serialize, PartialEq, Eq)]
pub struct MissCounter {
    /// Samples that missed.
    pub misses: u64,
    /// Longest run of consecutive misses.
    pub longest_run: u64,
    run: u64,
}

impl MissCounter {
    /// Records whether this sample missed.
    #[inline]
    pub fn record(&mut self, missed: bool) {
        if missed {
            self.misses += 1;
            self.run += 1;
            self.longest_run = self.longest_run.max(self.run);
        } else {
            self.run = 0;
        }
    }
}

/// A wake-up this late or later is a stall: longer than any scheduling delay of an idle
/// core, and at 2 kHz and above it costs the drive at least one sample.
pub const STALL_NS: u64 = 500_000;
/// Stalls the source keeps, with their times (the count goes on past it).
pub const STALL_LOG: usize = 4096;
/// The period of the grid on which a host's CPU bandwidth limit ends its stalls: the Linux
/// CFS bandwidth period (`cpu.cfs_period_us`, `cpu.max`), 100 ms unless the host changed it.
pub const HOST_GRID_NS: u64 = 100_000_000;
/// How close to the grid a stall's end must fall: guest and host clocks drift apart by a few
/// µs a second, so consecutive stalls, about a second apart, stay well inside it.
pub const HOST_GRID_TOL_NS: u64 = 500_000;

/// The source's stalls, as (deadline, lateness) in ns of each one's latest wake-up, the
/// first [`STALL_LOG`] of them. A stall starts with a wake-up at least [`STALL_NS`] late and
/// lasts while the wake-ups after it (the samples it catches up on) are later than a sample
/// time (or than [`STALL_NS`], if that is shorter): until the source is back on time. Its
/// latest wake-up is the first unless the machine stopped again before it caught up (a
/// freeze during a stall): then the stall is that later, longer one's, and ends when it does.
/// Preallocated: recording never allocates.
#[derive(Debug, Clone)]
pub struct StallLog {
    log: Box<[(u64, u64)]>,
    len: usize,
    in_stall: bool,
    /// A wake-up this late inside a stall is still catching up.
    behind_ns: u64,
    /// Every stall, also those beyond the log.
    pub count: u64,
    /// Deadline misses decided at a wake-up inside a stall (see [`StallLog::misses_in_stall`]).
    pub misses: u64,
}

impl StallLog {
    /// A log for sample time `ts_ns` that keeps the first `room` stalls ([`STALL_LOG`]; 0
    /// for a host that is not the source: it still counts, and allocates nothing).
    pub fn new(room: usize, ts_ns: u64) -> Self {
        Self {
            log: vec![(0, 0); room].into_boxed_slice(),
            len: 0,
            in_stall: false,
            behind_ns: ts_ns.min(STALL_NS),
            count: 0,
            misses: 0,
        }
    }

    /// `n` deadline misses were decided at the wake-up recorded last: they are the stall's
    /// when that wake-up was in one, so that a run's misses split into those of the stalls
    /// (a frozen machine) and the rest (the drive's own lateness).
    #[inline]
    pub fn misses_in_stall(&mut self, n: u64) {
        if self.in_stall {
            self.misses += n;
        }
    }

    /// A wake-up `late_ns` after `deadline_ns`: kept if it starts a stall, or if it is the
    /// latest wake-up yet of the stall under way.
    #[inline]
    pub fn record(&mut self, deadline_ns: u64, late_ns: i64) {
        let starts = late_ns >= STALL_NS as i64 && !self.in_stall;
        let goes_on = !starts && self.in_stall && late_ns >= self.behind_ns as i64;
        self.in_stall = starts || goes_on;
        if goes_on {
            // The stall under way is the last entry when every stall so far was kept.
            if self.count == self.len as u64 {
                let last = &mut self.log[self.len - 1];
                if late_ns as u64 > last.1 {
                    *last = (deadline_ns, late_ns as u64);
                }
            }
            return;
        }
        if !starts {
            return;
        }
        self.count += 1;
        if self.len < self.log.len() {
            self.log[self.len] = (deadline_ns, late_ns as u64);
            self.len += 1;
        }
    }

    /// The stalls kept, in order.
    pub fn entries(&self) -> &[(u64, u64)] {
        &self.log[..self.len]
    }
}

/// What the stalls of a run say about the machine (`summary.json → timing.stalls`).
#[derive(Debug, Clone, Serialize, serde::Deserialize, PartialEq)]
pub struct StallReport {
    /// Wake-ups at least [`STALL_NS`] late.
    pub count: u64,
    /// The longest, ms.
    pub longest_ms: f64,
    /// Consecutive stalls compared (of those kept).
    pub pairs: usize,
    /// Pairs whose ends lie one or more whole [`HOST_GRID_NS`] apart, within
    /// [`HOST_GRID_TOL_NS`]. By chance that is 2 × tolerance / period (1 %) of them; far
    /// more means something outside this machine's scheduler ends them on a common clock:
    /// a host's CPU bandwidth limit releasing a throttled VM.
    pub on_host_grid: usize,
    /// Deadline misses decided at a wake-up inside a stall: the command not there when the
    /// plant woke late (for the floor: its own wake-ups later than a sample time). The run's
    /// other misses happened while the machine ran.
    #[serde(default)]
    pub misses: u64,
}

impl StallReport {
    /// The report of `stalls` ((deadline, lateness) ns in order; `count` of them in all).
    pub fn new(stalls: &[(u64, u64)], count: u64) -> Self {
        let ends: Vec<u64> = stalls.iter().map(|&(d, l)| d + l).collect();
        let on_host_grid = ends
            .windows(2)
            .filter(|w| {
                let d = w[1].abs_diff(w[0]);
                let r = d % HOST_GRID_NS;
                d >= HOST_GRID_NS / 2 && r.min(HOST_GRID_NS - r) <= HOST_GRID_TOL_NS
            })
            .count();
        Self {
            count,
            longest_ms: stalls.iter().map(|&(_, l)| l).max().unwrap_or(0) as f64 / 1e6,
            pairs: ends.len().saturating_sub(1),
            on_host_grid,
            misses: 0,
        }
    }

    /// The report of a log: its stalls and the misses in them.
    pub fn of(log: &StallLog) -> Self {
        Self {
            misses: log.misses,
            ..Self::new(log.entries(), log.count)
        }
    }

    /// Two runs' stalls together (pairs are only ever taken within a run).
    pub fn merged(&self, other: &Self) -> Self {
        Self {
            count: self.count + other.count,
            longest_ms: self.longest_ms.max(other.longest_ms),
            pairs: self.pairs + other.pairs,
            on_host_grid: self.on_host_grid + other.on_host_grid,
            misses: self.misses + other.misses,
        }
    }

    /// Whether the stalls are the host's: at least two pairs end on the grid, and they are
    /// at least half of the pairs (50 times what chance gives). Chance puts one pair of two
    /// there in 2 % of reports, two of up to four in under 0.06 %.
    pub fn host_throttled(&self) -> bool {
        self.on_host_grid >= 2 && 2 * self.on_host_grid >= self.pairs
    }

    /// One line for the run's report, or None without stalls.
    pub fn line(&self) -> Option<String> {
        self.line_of("the plant's")
    }

    /// The line of a run's report: the gaps on the host's grid only when they show the
    /// host throttling (the bench's lines give them always).
    pub fn run_line(&self) -> Option<String> {
        self.compose("the plant's", self.host_throttled())
    }

    /// The same line for the wake-ups of `whose` ("the floor's").
    pub fn line_of(&self, whose: &str) -> Option<String> {
        self.compose(whose, true)
    }

    fn compose(&self, whose: &str, grid: bool) -> Option<String> {
        if self.count == 0 {
            return None;
        }
        let mut l = format!(
            "stalls of {} ms or more at {whose} wake-up: {} (longest {:.1} ms)",
            STALL_NS as f64 / 1e6,
            self.count,
            self.longest_ms
        );
        if self.misses > 0 {
            l += &format!("; {} deadline misses in them", self.misses);
        }
        if self.pairs > 0 && grid {
            l += &format!(
                "; {} of {} gaps between consecutive stalls' ends are a multiple of {} ms",
                self.on_host_grid,
                self.pairs,
                HOST_GRID_NS / 1_000_000
            );
        }
        if self.host_throttled() {
            l += ": the host throttles this VM's CPU time (a CFS bandwidth limit), not the drive";
        }
        Some(l)
    }
}

/// Cycle bookkeeping of the plant against a clock (real or synthetic): for each sample the
/// command's availability time is compared with t_k + Ts.
#[derive(Debug, Clone)]
pub struct CycleMonitor {
    /// Cycle latency t(command k available) − t_k.
    pub cycle: LatencyHist,
    /// Misses: command k not there at t_{k+1}.
    pub misses: MissCounter,
    ts_ns: u64,
}

impl CycleMonitor {
    /// A monitor for sample time `ts_ns`.
    pub fn new(ts_ns: u64) -> Self {
        Self {
            cycle: LatencyHist::new("cycle"),
            misses: MissCounter::default(),
            ts_ns,
        }
    }

    /// At t_{k+1}: `cmd_available_ns` is when command k was published (None if it has not
    /// arrived). Records its latency from t_k and whether the deadline was missed.
    #[inline]
    pub fn at_deadline(&mut self, t_k_ns: u64, cmd_available_ns: Option<u64>) {
        match cmd_available_ns {
            Some(t) => {
                let lat = t as i64 - t_k_ns as i64;
                self.cycle.record_ns(lat);
                self.misses.record(lat > self.ts_ns as i64);
            }
            None => self.misses.record(true),
        }
    }

    /// A command that arrived after its deadline: its latency still goes in the histogram.
    #[inline]
    pub fn late_command(&mut self, t_k_ns: u64, published_ns: u64) {
        self.cycle.record_ns(published_ns as i64 - t_k_ns as i64);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_of_a_known_distribution() {
        let mut h = LatencyHist::new("x");
        for v in 1..=1000i64 {
            h.record_ns(v * 1000); // 1..1000 µs
        }
        let p = h.percentiles();
        assert!((p.p50 - 500.0).abs() < 1.0, "{p:?}");
        assert!((p.p99 - 990.0).abs() < 1.0, "{p:?}");
        assert!((p.max - 1000.0).abs() < 1.0);
        assert_eq!(p.count, 1000);
    }

    #[test]
    fn values_above_a_bound_are_counted() {
        let mut h = LatencyHist::new("x");
        for v in 1..=1000i64 {
            h.record_ns(v * 1000); // 1..1000 µs
        }
        h.record_ns(i64::MAX); // clamped: still above every bound
        assert_eq!(h.count_above_ns(990_000), 11);
        assert_eq!(h.count_above_ns(989_000), 12);
        assert_eq!(h.count_above_ns(0), 1001);
        assert_eq!(h.count_above_ns(u64::MAX), 0);
    }

    #[test]
    fn out_of_range_is_clamped_not_lost() {
        let mut h = LatencyHist::new("x");
        h.record_ns(-5);
        h.record_ns(i64::MAX);
        assert_eq!(h.len(), 2);
        assert_eq!(h.clamped, 1);
    }

    #[test]
    fn stalls_are_kept_with_their_times_and_counted_beyond_the_log() {
        let mut log = StallLog::new(STALL_LOG, 100_000);
        log.record(1_000, STALL_NS as i64 - 1); // not a stall
        log.record(2_000, -5);
        log.record(3_000, 2 * STALL_NS as i64);
        // The samples the stall caught up on are late too: the same stall.
        log.record(4_000, STALL_NS as i64);
        log.record(5_000, 200_000);
        assert_eq!(log.entries(), &[(3_000, 2 * STALL_NS)]);
        // Stopped again before it caught up: still the same stall, as long as the later stop.
        log.record(6_000, 4 * STALL_NS as i64);
        log.record(7_000, 3 * STALL_NS as i64);
        assert_eq!(log.entries(), &[(6_000, 4 * STALL_NS)]);
        assert_eq!(log.count, 1);
        log.record(8_000, 1_000);
        log.record(9_000, 3_000_000);
        assert_eq!(log.entries(), &[(6_000, 4 * STALL_NS), (9_000, 3_000_000)]);
        let ((), allocations) = crate::alloc_count::allocations_during(|| {
            for i in 0..(STALL_LOG as u64 + 10) {
                log.record(2 * i, 1_000);
                log.record(2 * i + 1, 1_000_000);
            }
        });
        assert_eq!(allocations, 0);
        assert_eq!(log.entries().len(), STALL_LOG);
        assert_eq!(log.count, STALL_LOG as u64 + 12);
        // A stall beyond the log changes no kept one.
        let kept = log.entries().last().copied();
        log.record(u64::MAX - 1, 9_000_000);
        assert_eq!(log.entries().last().copied(), kept);
    }

    #[test]
    fn misses_decided_at_a_wake_up_inside_a_stall_are_the_stalls() {
        // 10 kHz: a wake-up later than 100 µs inside a stall is still catching up.
        let mut log = StallLog::new(STALL_LOG, 100_000);
        log.record(1_000, 200_000); // late, not a stall
        log.misses_in_stall(1);
        log.record(2_000, STALL_NS as i64);
        log.misses_in_stall(3);
        log.record(3_000, 420_000); // caught up on: the same stall
        log.misses_in_stall(1);
        log.record(4_000, 100_000); // the last sample it catches up on
        log.misses_in_stall(1);
        log.record(5_000, 99_999); // back on time, out of it
        log.misses_in_stall(2);
        log.record(6_000, 200_000); // late again: no stall
        log.misses_in_stall(1);
        assert_eq!((log.count, log.misses), (1, 5));
        let r = StallReport::of(&log);
        assert_eq!((r.count, r.misses), (1, 5));
        assert!(r.line().unwrap().contains("; 5 deadline misses in them"));
        assert_eq!(r.merged(&r).misses, 10);
        // At 1 kHz a stall ends at the first wake-up under 0.5 ms late.
        let mut slow = StallLog::new(STALL_LOG, 1_000_000);
        slow.record(1_000, 2_000_000);
        slow.record(2_000, STALL_NS as i64 - 1);
        slow.misses_in_stall(1);
        assert_eq!(slow.misses, 0);
        // A host that is not the source keeps no log but still counts.
        let mut none = StallLog::new(0, 100_000);
        none.record(1_000, STALL_NS as i64);
        assert_eq!((none.count, none.entries().len()), (1, 0));
    }

    #[test]
    fn stalls_that_end_on_a_100_ms_grid_are_the_hosts_and_scattered_ones_are_not() {
        // Ends at 40.5 ms past each 100 ms boundary (with a few µs of drift), the lengths as
        // measured on a throttled VM: 0.6 to 24.7 ms.
        let lens = [
            600_000u64, 2_640_000, 1_570_000, 24_670_000, 720_000, 1_820_000,
        ];
        let grid: Vec<(u64, u64)> = lens
            .iter()
            .enumerate()
            .map(|(i, &l)| {
                let end = 7_000_000_000
                    + (i as u64 * 13 + 3) * HOST_GRID_NS
                    + 40_500_000
                    + i as u64 * 9_000;
                (end - l, l)
            })
            .collect();
        let r = StallReport::new(&grid, 6);
        assert_eq!((r.pairs, r.on_host_grid), (5, 5));
        assert!(r.host_throttled());
        assert!((r.longest_ms - 24.67).abs() < 1e-9);
        assert!(
            r.line().unwrap().contains("the host throttles"),
            "{:?}",
            r.line()
        );
        // The same stalls, each ending 7–60 ms off the grid of the one before: not the host.
        let offs = [
            0u64, 7_000_000, 31_000_000, 12_000_000, 60_000_000, 45_000_000,
        ];
        let scattered: Vec<(u64, u64)> = grid
            .iter()
            .zip(offs)
            .map(|(&(d, l), o)| (d + o, l))
            .collect();
        let r = StallReport::new(&scattered, 6);
        assert_eq!(r.on_host_grid, 0);
        assert!(!r.host_throttled());
        assert!(!r.line().unwrap().contains("host"), "{:?}", r.line());
        // A run's report names the grid only where it shows the host throttling.
        assert!(r.line().unwrap().contains("0 of 5 gaps"), "{:?}", r.line());
        assert!(
            !r.run_line().unwrap().contains("gaps"),
            "{:?}",
            r.run_line()
        );
        let throttled = StallReport::new(&grid, 6).run_line().unwrap();
        assert!(
            throttled.ends_with(
                "; 5 of 5 gaps between consecutive stalls' ends are a multiple of 100 ms: the \
                 host throttles this VM's CPU time (a CFS bandwidth limit), not the drive"
            ),
            "{throttled}"
        );
        // One pair on the grid of five is chance, and two stalls are too few to tell.
        let mut one = scattered.clone();
        one[1] = (grid[1].0 - grid[0].0 + scattered[0].0, grid[1].1);
        let r = StallReport::new(&one, 6);
        assert_eq!(r.on_host_grid, 1);
        assert!(!r.host_throttled());
        assert!(!StallReport::new(&grid[..2], 2).host_throttled());
        // Three stalls, one pair of the two on the grid: one report in 50 by chance.
        let r = StallReport::new(&[grid[0], grid[1], scattered[2]], 3);
        assert_eq!((r.pairs, r.on_host_grid), (2, 1));
        assert!(!r.host_throttled());
        // Both pairs of three: not by chance (one report in 10 000).
        let r = StallReport::new(&grid[..3], 3);
        assert_eq!((r.pairs, r.on_host_grid), (2, 2));
        assert!(r.host_throttled());
        // Stalls closer together than half a period are never on the grid, however close.
        let close = [
            (1_000_000_000, 600_000),
            (1_000_700_000, 600_000),
            (1_001_400_000, 600_000),
        ];
        assert_eq!(StallReport::new(&close, 3).on_host_grid, 0);
        // Rounds add up; the longest is the longest of any.
        let m = StallReport::new(&grid, 6).merged(&StallReport::new(&scattered, 6));
        assert_eq!((m.count, m.pairs, m.on_host_grid), (12, 10, 5));
        assert!(m.host_throttled());
        assert!((m.longest_ms - 24.67).abs() < 1e-9);
        assert_eq!(StallReport::new(&[], 0).line(), None);
    }

    #[test]
    fn recording_does_not_allocate() {
        // The histogram's counts array is sized at creation (auto-resize is off) and the
        // compact histogram is a fixed array: recording across the whole range, beyond it
        // (clamped) and below it (negative) must not allocate.
        let mut h = LatencyHist::new("x");
        let ((), allocations) = crate::alloc_count::allocations_during(|| {
            for e in 0..34 {
                h.record_ns(1i64 << e);
            }
            h.record_ns(-5);
            h.record_ns(i64::MAX);
        });
        assert_eq!(allocations, 0);
        assert_eq!((h.len(), h.clamped), (36, 1));
    }

    #[test]
    fn synthetic_clock_counts_misses_and_runs() {
        // Ts = 100 µs; commands arrive 30 µs after t_k, except a slow step (250 µs) at k = 5
        // and two missing commands at k = 7, 8.
        let ts = 100_000u64;
        let mut m = CycleMonitor::new(ts);
        for k in 0..10u64 {
            let t_k = k * ts;
            let avail = match k {
                5 => Some(t_k + 250_000),
                7 | 8 => None,
                _ => Some(t_k + 30_000),
            };
            m.at_deadline(t_k, avail);
        }
        assert_eq!(m.misses.misses, 3);
        assert_eq!(m.misses.longest_run, 2);
        assert_eq!(m.cycle.len(), 8);
        assert!((m.cycle.percentiles().max - 250.0).abs() < 0.5);
    }

    #[test]
    fn hgrm_and_v2_round_trip() {
        let mut h = LatencyHist::new("x");
        for v in [10_000i64, 20_000, 30_000, 1_000_000] {
            h.record_ns(v);
        }
        let p = std::env::temp_dir().join(format!("drivelab-hist-{}.hdr", std::process::id()));
        h.write_v2(&p).unwrap();
        let g = LatencyHist::read_v2("x", &p).unwrap();
        std::fs::remove_file(&p).unwrap();
        assert_eq!(g.percentiles(), h.percentiles());
        let text = h.hgrm();
        assert!(text.contains("Percentile") && text.contains("Total count"));
        assert!(!h.curve().is_empty());
    }
}

#[cfg(test)]
mod slow_step_tests {
    use super::*;
    use crate::rt::{now_ns, sleep_until_ns};

    /// A periodic loop on the real clock whose step deliberately takes 1.5 T_s every 5th
    /// sample: each such sample must be counted as a miss (the command is ready after
    /// t_{k+1}); the other samples are not asserted (the machine may be busy).
    #[test]
    fn a_deliberately_slow_step_is_counted_as_a_miss() {
        let ts = 2_000_000u64; // 2 ms, generous for a shared test machine
        let mut mon = CycleMonitor::new(ts);
        let t0 = now_ns() + ts;
        let mut slow_seen = 0;
        for k in 0..20u64 {
            let t_k = t0 + k * ts;
            sleep_until_ns(t_k);
            if k % 5 == 0 {
                while now_ns() < t_k + ts * 3 / 2 {
                    std::hint::spin_loop();
                }
                slow_seen += 1;
            }
            mon.at_deadline(t_k, Some(now_ns()));
        }
        assert!(
            mon.misses.misses >= slow_seen,
            "{} misses for {slow_seen} slow steps",
            mon.misses.misses
        );
        assert_eq!(mon.cycle.len(), 20);
        assert!(mon.cycle.percentiles().max >= 1.5 * ts as f64 / 1e3);
    }

    #[test]
    fn histograms_add_up() {
        let mut a = LatencyHist::new("a");
        let mut b = LatencyHist::new("b");
        for v in [1_000, 2_000, 3_000] {
            a.record_ns(v);
        }
        b.record_ns(400_000);
        a.add(&b).unwrap();
        assert_eq!(a.len(), 4);
        let max = a.percentiles().max;
        assert!((399.0..=401.0).contains(&max), "max {max} µs"); // 3 significant digits
        assert_eq!(a.compact.count, 4);
        assert_eq!(a.compact.max_ns, 400_000);
    }
}
