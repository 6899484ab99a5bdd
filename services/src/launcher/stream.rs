//! The trace as the drive runs: measurements and commands meet in a bounded window of
//! samples, each sample leaves it as a row of `trace.csv` (or a listed gap) once its command
//! had time to arrive, and the plant's downtimes are rebuilt on the way. Memory does not
//! grow with the run's length: a long run keeps for its analyses (metrics, fault reports,
//! plots) every row around each disturbance and reference step and every d-th row between
//! them, and says so in its summary.

use super::recorder::{missing_command_cause, push_gap, Gap, LOST_IN_BUFFER, PLANT_STOPPED, ROW};
use anyhow::Result;
use drivelab_runtime::config::Scenario;
use drivelab_runtime::drive::trace_row;
use drivelab_runtime::messages::{
    Header, PlantTruth, VoltageCommand, FLAG_PLANT_DOWN, FLAG_SAFE_STATE, FLAG_TRIPPED,
};
use drivelab_runtime::trace::{CsvTrace, TraceRow};
use serde::Serialize;

/// Samples held in the window (a power of two above any lag below).
const WINDOW: u64 = 1 << 16;
/// How long a sample waits for its command before it leaves the window, s.
const LAG_S: f64 = 0.2;
/// A plant downtime longer than this is not rebuilt (left missing), s.
const MAX_DOWNTIME_S: f64 = 10.0;
/// Runs up to this many samples keep every row for their analyses.
pub const FULL_ROWS: u64 = 1 << 20;
/// Longer runs keep about this many evenly spaced rows, plus the windows below.
const SPACED_ROWS: u64 = 200_000;
/// At most this many rows are kept for the windows below, in all (a run disturbed
/// throughout would otherwise keep every row).
const WINDOW_ROWS: u64 = 200_000;
/// Every row is kept from this long before a disturbance or a reference step, s …
const KEEP_BEFORE_S: f64 = 0.1;
/// … to this long after it, s.
const KEEP_AFTER_S: f64 = 1.0;

/// `timing.csv` (`drivelab run --timing-csv`): per sample, when each stage of the chain
/// published its output for it, µs after the sample's instant t_k: the plant, the observer's
/// estimate, the speed loop's current reference (on its samples only) and the current loop's
/// command. The cycle latency sample by sample, split at each hop: what the `cycle`
/// histogram merges, so that a slow sample's parts can be seen together. Written as the
/// trace is; the estimates and references are read as they come and held by sample until
/// their row leaves the window.
pub struct TimingCsv {
    w: csv::Writer<std::fs::File>,
    path: std::path::PathBuf,
    /// Publish instants of the chain's middle outputs by slot: (k, t_pub_ns) of the
    /// estimate and of the current reference.
    mid: Vec<[(u64, u64); 2]>,
}

/// The header of `timing.csv`.
pub const TIMING_COLUMNS: [&str; 5] = [
    "k",
    "plant_published_us",
    "estimate_published_us",
    "current_ref_published_us",
    "command_published_us",
];

/// An output of the chain between the plant's and the command, as `timing.csv` times it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Middle {
    /// The observer's estimate.
    Estimate = 0,
    /// The speed loop's current reference.
    CurrentRef = 1,
}

impl TimingCsv {
    /// Creates (truncates) the file and writes its header.
    pub fn create(path: &std::path::Path) -> Result<Self> {
        let file = drivelab_runtime::files::create(path)
            .map_err(|e| anyhow::anyhow!("cannot create {}: {e}", path.display()))?;
        let mut t = Self {
            w: csv::Writer::from_writer(file),
            path: path.to_path_buf(),
            // (u64::MAX, _): nothing yet.
            mid: vec![[(u64::MAX, 0); 2]; WINDOW as usize],
        };
        t.record(TIMING_COLUMNS.map(String::from))?;
        Ok(t)
    }

    fn record(&mut self, fields: [String; 5]) -> Result<()> {
        self.w
            .write_record(&fields)
            .map_err(|e| anyhow::anyhow!("cannot write {}: {e}", self.path.display()))
    }

    /// Output `which` of sample k was published at `t_pub_ns`.
    fn middle(&mut self, which: Middle, k: u64, t_pub_ns: u64) {
        self.mid[(k % WINDOW) as usize][which as usize] = (k, t_pub_ns);
    }

    /// Sample k's row: each time after t_k, µs, empty where there is none (a command that
    /// never came; a sample rebuilt while the plant was down, which nobody published; a
    /// sample without a speed-loop step).
    fn row(&mut self, m: &PlantTruth, c: Option<&VoltageCommand>) -> Result<()> {
        let (k, t_k) = (m.hdr.k, m.hdr.t_sample_ns);
        let after = |t_ns: u64| {
            if t_k == 0 || t_ns == 0 {
                String::new()
            } else {
                format!("{:.3}", (t_ns as i64 - t_k as i64) as f64 * 1e-3)
            }
        };
        let [est, iref] =
            self.mid[(k % WINDOW) as usize]
                .map(|(mk, t)| if mk == k { after(t) } else { String::new() });
        let cmd = c.map_or_else(String::new, |c| after(c.hdr.t_pub_ns));
        self.record([k.to_string(), after(m.hdr.t_pub_ns), est, iref, cmd])
    }

    fn finish(mut self) -> Result<()> {
        self.w
            .flush()
            .map_err(|e| anyhow::anyhow!("cannot write {}: {e}", self.path.display()))
    }
}

/// What a run's trace holds and what its analyses saw.
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct TraceStats {
    /// Rows made: in `trace.csv` but for the `rows_not_written`.
    pub rows: u64,
    /// Largest |i_dq| over every row, A.
    pub peak_current_a: f64,
    /// Largest |ω_m| over every row, mechanical rad/s.
    pub peak_speed_rad_s: f64,
    /// The first row whose plant state (currents, speed, angles) is not a finite number: the
    /// simulation blew up (the run fails; the peaks above cover the rows before it).
    pub first_not_finite: Option<u64>,
    /// Rows kept for the analyses (metrics, fault reports, plots).
    pub rows_analysed: u64,
    /// Between the kept windows, one row in this many was kept (1: every row).
    pub spacing: u64,
    /// Rows of windows not kept because the windows' budget was spent.
    pub window_rows_dropped: u64,
    /// Rows made but not in `trace.csv`: it could not be written from the first of them on
    /// (`missing_samples`, part "row"). They are still analysed.
    pub rows_not_written: u64,
}

impl TraceStats {
    /// The figures of rows all held in memory.
    pub fn of(rows: &[TraceRow]) -> Self {
        let mut s = Self {
            rows: 0,
            peak_current_a: 0.0,
            peak_speed_rad_s: 0.0,
            first_not_finite: None,
            rows_analysed: rows.len() as u64,
            spacing: 1,
            window_rows_dropped: 0,
            rows_not_written: 0,
        };
        for r in rows {
            s.count(r);
        }
        s
    }

    /// Rows in `trace.csv`.
    pub fn rows_written(&self) -> u64 {
        self.rows - self.rows_not_written
    }

    fn count(&mut self, r: &TraceRow) {
        self.rows += 1;
        let state = [r.i_d, r.i_q, r.omega_m, r.theta_e, r.theta_m];
        if self.first_not_finite.is_none() && !state.iter().all(|v| v.is_finite()) {
            self.first_not_finite = Some(r.k);
        }
        self.peak_current_a = self.peak_current_a.max(r.i_d.hypot(r.i_q));
        self.peak_speed_rad_s = self.peak_speed_rad_s.max(r.omega_m.abs());
    }
}

/// Which rows the analyses keep.
struct Keep {
    spacing: u64,
    /// Sample windows [from, to] kept whole: reference and load steps, then disturbances.
    windows: Vec<(u64, u64)>,
    before: u64,
    after: u64,
    /// Window rows that may still be kept.
    budget: u64,
    /// Window rows not kept for want of budget.
    dropped: u64,
}

impl Keep {
    fn new(sc: &Scenario) -> Self {
        let n = sc.samples();
        let fs = sc.rates.sample_hz;
        let before = (KEEP_BEFORE_S * fs).ceil() as u64;
        let after = (KEEP_AFTER_S * fs).ceil() as u64;
        let mut k = Self {
            spacing: if n <= FULL_ROWS {
                1
            } else {
                n.div_ceil(SPACED_ROWS)
            },
            windows: Vec::new(),
            before,
            after,
            budget: WINDOW_ROWS,
            dropped: 0,
        };
        if k.spacing > 1 {
            let steps = sc
                .reference
                .speed_rad_s
                .iter()
                .chain(&sc.reference.i_d_a)
                .chain(&sc.load.torque_nm);
            for s in steps {
                k.mark((s.t_s.max(0.0) * fs) as u64);
            }
        }
        k
    }

    /// Keeps every row around sample k.
    fn mark(&mut self, k: u64) {
        if self.spacing == 1 {
            return;
        }
        let w = (k.saturating_sub(self.before), k.saturating_add(self.after));
        match self.windows.last_mut() {
            // Disturbances come in order: extend the newest window while they overlap.
            Some(last) if w.0 <= last.1 && w.0 >= last.0 => last.1 = last.1.max(w.1),
            _ => self.windows.push(w),
        }
    }

    fn keeps(&mut self, k: u64) -> bool {
        // Windows that ended before k are done with (rows leave in order).
        self.windows.retain(|w| w.1 >= k);
        if k.is_multiple_of(self.spacing) {
            return true;
        }
        if !self.windows.iter().any(|w| w.0 <= k) {
            return false;
        }
        if self.budget == 0 {
            self.dropped += 1;
            return false;
        }
        self.budget -= 1;
        true
    }
}

/// The trace of a run being recorded (see the module's comment).
pub struct TraceStream {
    ts: f64,
    n: u64,
    lag: u64,
    sc: Scenario,
    meas: Vec<Option<PlantTruth>>,
    cmd: Vec<Option<VoltageCommand>>,
    /// Next sample to leave the window.
    next: u64,
    /// Newest measurement taken.
    newest: Option<u64>,
    /// Position references of an outer loop, (k, θ_m*), by k.
    wref: std::collections::VecDeque<(u64, f64)>,
    /// The newest of them before the row being made, (k, θ_m*).
    theta_ref: Option<(u64, f64)>,
    /// The outer loop's rate divider, when the topology has one: a row's θ_m* is empty once
    /// the speed loop no longer follows the loop's newest reference (it is down).
    outer_divider: Option<u64>,
    /// The first sample no plant produced ([`Scenario::plant_gone_at`]).
    plant_gone_at: Option<u64>,
    out: Option<CsvTrace>,
    /// `timing.csv`, when asked for.
    timing: Option<TimingCsv>,
    /// `trace.mcap` and the live stream.
    sinks: super::sinks::Sinks,
    keep: Keep,
    /// Rows kept for the analyses.
    pub kept: Vec<TraceRow>,
    /// Samples missing from the trace, with their causes.
    pub gaps: Vec<Gap>,
    /// The trace's figures.
    pub stats: TraceStats,
    /// Samples of the plant's downtimes rebuilt.
    pub rebuilt: u64,
    /// The rebuilt downtimes, first and last sample of each.
    pub rebuilt_ranges: Vec<(u64, u64)>,
    /// Messages that arrived after their sample had left the window (too late to be used).
    pub late: u64,
    /// Messages with an index beyond the run (malformed).
    pub rejected: u64,
    /// Real time: the instant of the plant's sample 0 on its schedule (CLOCK_MONOTONIC ns),
    /// from the first measurement that carried one.
    pub t0_ns: Option<u64>,
    /// Newest row made.
    last_row: Option<u64>,
    /// Once `trace.csv` could not be written: why its later rows are not in it.
    unwritten: Option<String>,
    /// Each output that could not be written (`trace.csv`, `timing.csv`, `trace.mcap`): its
    /// error and where the file ends. The stream goes on without that output; the recorders
    /// stop the recording at the first one.
    pub write_errors: Vec<String>,
}

impl TraceStream {
    /// A trace of scenario `sc` written to `out` (None: kept in memory only, for tests). The
    /// rows kept for the analyses get their room now, exactly (a vector that doubles as it
    /// grows would hold up to twice that), or the run is refused with the size it needs.
    pub fn new(sc: &Scenario, out: Option<CsvTrace>) -> Result<Self> {
        let keep = Keep::new(sc);
        let n = sc.samples();
        let rows = if keep.spacing == 1 {
            n
        } else {
            n.div_ceil(keep.spacing) + WINDOW_ROWS
        };
        let mut kept = Vec::new();
        kept.try_reserve_exact(rows as usize).map_err(|_| {
            anyhow::anyhow!(
                "cannot allocate the trace's analysis rows: {rows} rows of {} bytes",
                std::mem::size_of::<TraceRow>()
            )
        })?;
        if keep.spacing > 1 {
            // A long run: its analysis rows are bounded, so they are made resident now (each
            // page written once), and the drive's memory is the same from its first minute
            // to its last instead of rising as they fill.
            kept.resize(rows as usize, TraceRow::default());
            kept.clear();
        }
        Ok(Self {
            ts: sc.rates.ts(),
            n: sc.samples(),
            lag: ((LAG_S * sc.rates.sample_hz).ceil() as u64).clamp(1, WINDOW / 4),
            sc: sc.clone(),
            meas: vec![None; WINDOW as usize],
            cmd: vec![None; WINDOW as usize],
            next: 0,
            newest: None,
            wref: Default::default(),
            theta_ref: None,
            outer_divider: None,
            plant_gone_at: None,
            out,
            timing: None,
            sinks: super::sinks::Sinks::none(),
            kept,
            gaps: Vec::new(),
            stats: TraceStats {
                rows: 0,
                peak_current_a: 0.0,
                peak_speed_rad_s: 0.0,
                first_not_finite: None,
                rows_analysed: 0,
                spacing: keep.spacing,
                window_rows_dropped: 0,
                rows_not_written: 0,
            },
            keep,
            rebuilt: 0,
            rebuilt_ranges: Vec::new(),
            late: 0,
            rejected: 0,
            t0_ns: None,
            last_row: None,
            unwritten: None,
            write_errors: Vec::new(),
        })
    }

    /// Writes every row's timing to `timing` too.
    pub fn with_timing(mut self, timing: Option<TimingCsv>) -> Self {
        self.timing = timing;
        self
    }

    /// True when it writes `timing.csv`, which wants the chain's middle outputs too.
    pub fn times_the_chain(&self) -> bool {
        self.timing.is_some()
    }

    /// Output `which` of sample k was published at `t_pub_ns` (for `timing.csv`; one that
    /// comes after its sample left the window is not timed).
    pub fn middle(&mut self, which: Middle, k: u64, t_pub_ns: u64) {
        if let Some(t) = self.timing.as_mut() {
            if k >= self.next && k < self.n && k < self.next + WINDOW {
                t.middle(which, k, t_pub_ns);
            }
        }
    }

    /// Takes no measurement from sample `gone` on ([`Scenario::plant_gone_at`]): the
    /// trace ends before it and the samples after are listed missing.
    pub fn with_plant_gone_at(mut self, gone: Option<u64>) -> Self {
        self.plant_gone_at = gone;
        self
    }

    /// The rate divider of the stage of `plan` that publishes `wref` (an outer loop), if one
    /// does: what [`TraceStream::with_outer_divider`] takes.
    pub fn outer_divider(plan: &drivelab_runtime::service::TopologyPlan) -> Option<u64> {
        plan.producers
            .iter()
            .find(|p| p.topic == drivelab_runtime::stage::TopicId::Wref)
            .map(|p| p.divider)
    }

    /// The rate divider of the stage that publishes `wref` (an outer loop), if one does: a
    /// row's θ_m* is then empty while the speed loop no longer follows the loop's newest
    /// reference (`stages::wref_followed`), as before its first output.
    pub fn with_outer_divider(mut self, divider: Option<u64>) -> Self {
        self.outer_divider = divider;
        self
    }

    /// Sends every row to `sinks` too (`trace.mcap`, the live stream).
    pub fn with_sinks(mut self, sinks: super::sinks::Sinks) -> Self {
        self.sinks = sinks;
        self
    }

    fn slot(k: u64) -> usize {
        (k % WINDOW) as usize
    }

    /// True when sample k can be taken now; makes room for it.
    fn admit(&mut self, hdr: &Header) -> Result<bool> {
        let k = hdr.k;
        if k >= self.n {
            self.rejected += 1;
            return Ok(false);
        }
        if k < self.next {
            self.late += 1;
            return Ok(false);
        }
        if k >= self.next + WINDOW {
            self.emit_until(k + 1 - WINDOW)?;
        }
        Ok(true)
    }

    /// Takes the plant's true state at its sample. A measurement after missing ones may end
    /// a downtime of the plant: `rejoins` then gives the states restarted plants were given.
    pub fn meas(&mut self, m: PlantTruth, rejoins: impl FnOnce() -> Vec<PlantTruth>) -> Result<()> {
        if self.plant_gone_at.is_some_and(|g| m.hdr.k >= g) || !self.admit(&m.hdr)? {
            return Ok(());
        }
        let k = m.hdr.k;
        // Disturbances worth every row: the safe state, a rebuilt downtime, a trip (a held
        // command alone is a deadline miss, which a loaded machine has every few samples).
        if m.hdr.flags & (FLAG_SAFE_STATE | FLAG_PLANT_DOWN | FLAG_TRIPPED) != 0 {
            self.keep.mark(k);
        }
        self.meas[Self::slot(k)] = Some(m);
        match self.newest {
            Some(l) if k > l + 1 => {
                self.keep.mark(l + 1);
                self.rebuild_downtime(l, &m, &rejoins())?;
            }
            _ => {}
        }
        self.newest = Some(self.newest.map_or(k, |l| l.max(k)));
        Ok(())
    }

    /// Takes command k.
    pub fn cmd(&mut self, c: VoltageCommand) -> Result<()> {
        if !self.admit(&c.hdr)? {
            return Ok(());
        }
        self.cmd[Self::slot(c.hdr.k)] = Some(c);
        Ok(())
    }

    /// Takes an outer loop's position reference computed at sample k.
    pub fn wref(&mut self, k: u64, theta_m_ref: f64) {
        let at = self.wref.partition_point(|w| w.0 <= k);
        self.wref.insert(at, (k, theta_m_ref));
    }

    /// True when sample k has a measurement and a command in the window.
    pub fn complete(&self, k: u64) -> bool {
        k < self.next
            || (self.meas[Self::slot(k)].is_some_and(|m| m.hdr.k == k)
                && self.cmd[Self::slot(k)].is_some_and(|c| c.hdr.k == k))
    }

    /// Lets every sample whose command had its time leave the window.
    pub fn advance(&mut self) -> Result<()> {
        if let Some(l) = self.newest {
            self.emit_until((l + 1).saturating_sub(self.lag))?;
        }
        Ok(())
    }

    /// Lets every sample leave; returns the rows kept. The samples never measured are
    /// listed as stopped (after the newest measurement) or lost (before it).
    pub fn finish(mut self) -> Result<Self> {
        self.emit_until(self.n)?;
        if let Some(mut out) = self.out.take() {
            if let Err(e) = out.flush() {
                self.out = Some(out);
                if let Some(k) = self.last_row {
                    self.lose_trace(e, k);
                }
            }
        }
        if let Some(t) = self.timing.take() {
            if let Err(e) = t.finish() {
                self.write_errors
                    .push(format!("{e:#}; timing.csv may lack its last rows"));
            }
        }
        self.stats.rows_not_written = rows_not_written(&self.gaps);
        self.stats.rows_analysed = self.kept.len() as u64;
        self.stats.window_rows_dropped = self.keep.dropped;
        Ok(self)
    }

    /// A run of missing measurements after sample `l` that ends at `m`, a restarted plant's
    /// first: filled with the motor integrated from the state that plant was given, exactly
    /// as it did before it resumed ([`Plant::coast`](drivelab_runtime::drive::Plant::coast)).
    /// The rebuilt state at the resumed sample must equal the recorded one bit for bit, else
    /// the run is left missing (it was no restart of the plant). The restarted plant was given
    /// the newest sample the recorder had read, which lags `l` by less than the window's lag:
    /// only those states are tried, and a downtime longer than [`MAX_DOWNTIME_S`] is not
    /// rebuilt (the recorder must keep reading while the drive runs).
    fn rebuild_downtime(&mut self, l: u64, m: &PlantTruth, rejoins: &[PlantTruth]) -> Result<()> {
        use drivelab_runtime::drive::Plant;
        let (a, b) = (l + 1, m.hdr.k);
        let max_down = (MAX_DOWNTIME_S * self.sc.rates.sample_hz) as u64;
        let candidates = rejoins
            .iter()
            .rev()
            .filter(|t| t.hdr.k <= l && t.hdr.k + self.lag >= l && b - t.hdr.k <= max_down);
        for last in candidates {
            let mut rebuilt = Vec::new();
            let mut plant = Plant::new(&self.sc);
            plant.coast(last, b, |t| {
                if t.hdr.k >= a {
                    rebuilt.push(*t);
                }
            });
            plant.sample(b, None);
            let next = plant.truth();
            if (next.i_dq, next.omega_m, next.theta_m) == (m.i_dq, m.omega_m, m.theta_m) {
                // The samples before the downtime are complete (the plant was down for
                // longer than any command takes): they leave first, then the rebuilt ones.
                self.emit_until(a)?;
                // (A downtime longer than the window has already left it as missing.)
                let from = self.next;
                for t in rebuilt.iter().filter(|t| t.hdr.k >= from) {
                    self.row(t, None)?;
                    self.rebuilt += 1;
                }
                if from < b {
                    self.rebuilt_ranges.push((from, b - 1));
                }
                self.next = self.next.max(b);
                return Ok(());
            }
        }
        Ok(())
    }

    fn emit_until(&mut self, to: u64) -> Result<()> {
        while self.next < to.min(self.n) {
            let k = self.next;
            let s = Self::slot(k);
            let m = self.meas[s].take().filter(|m| m.hdr.k == k);
            // An absent marker (lockstep: no usable command will come) completes the sample
            // without a command.
            let c = self.cmd[s]
                .take()
                .filter(|c| c.hdr.k == k && !c.hdr.is_absent());
            match m {
                Some(m) => self.row(&m, c.as_ref())?,
                None => {
                    let cause = if self.newest.is_some_and(|l| k < l) {
                        LOST_IN_BUFFER
                    } else {
                        PLANT_STOPPED
                    };
                    self.gap(k, "measurement", cause);
                }
            }
            self.next += 1;
        }
        Ok(())
    }

    /// Sample k's row from its true state and command (None: no command, NaN in its
    /// columns).
    fn row(&mut self, m: &PlantTruth, c: Option<&VoltageCommand>) -> Result<()> {
        let k = m.hdr.k;
        if self.t0_ns.is_none() && m.hdr.t_sample_ns != 0 {
            self.t0_ns = m.hdr.t_sample_ns.checked_sub(k * self.sc.rates.ts_ns());
        }
        while self.wref.front().is_some_and(|w| w.0 < k) {
            self.theta_ref = self.wref.pop_front();
        }
        let followed = |&(wk, _): &(u64, f64)| {
            self.outer_divider
                .is_none_or(|d| drivelab_runtime::stages::wref_followed(k, wk, d))
        };
        let theta_ref = self.theta_ref.filter(followed).map(|w| w.1);
        let mut row = match c {
            Some(c) => trace_row(self.ts, m, c),
            None => trace_row(self.ts, m, &drivelab_runtime::drive::missing_command(k)),
        };
        row.theta_m_ref = theta_ref;
        self.last_row = Some(k);
        if let Some(e) = self.out.as_mut().and_then(|out| out.push(&row).err()) {
            self.lose_trace(e, k);
        } else if let Some(cause) = self.unwritten.clone() {
            self.gap(k, ROW, &cause);
        } else if c.is_none() {
            let cause = missing_command_cause(m.hdr.flags & FLAG_PLANT_DOWN != 0);
            self.gap(k, "command", cause);
        }
        if let Some(e) = self.timing.as_mut().and_then(|t| t.row(m, c).err()) {
            self.timing = None;
            self.write_errors
                .push(format!("{e:#}; timing.csv ends before sample {k} or in it"));
        }
        if let Err(e) = self.sinks.row(&row, m.hdr.t_pub_ns) {
            drop(self.sinks.take_mcap());
            self.write_errors.push(mcap_cut(&e, k));
        }
        self.stats.count(&row);
        if self.keep.keeps(k) {
            self.kept.push(row);
        }
        Ok(())
    }

    fn gap(&mut self, k: u64, part: &'static str, cause: &str) {
        push_gap(&mut self.gaps, k, part, cause);
    }

    /// `trace.csv` failed (`e`) while row k was written: it is cut after its last whole row,
    /// which it ends with, and each row after that one, up to k and from now on, is listed
    /// missing (part "row"; a command gap among them becomes part of it).
    fn lose_trace(&mut self, e: anyhow::Error, k: u64) {
        let Some(out) = self.out.take() else {
            return;
        };
        let (error, cause) = abandon_trace(out, &e, k, &mut self.gaps);
        self.write_errors.push(error);
        self.unwritten = Some(cause);
    }
}

/// `trace.csv` (`out`) failed (`e`) while row k, the newest made, was written: it is cut after
/// its last whole row, and the rows after that one up to k are listed in `gaps`. The error as
/// the run's failure gives it and the rows' cause.
fn abandon_trace(
    out: CsvTrace,
    e: &anyhow::Error,
    k: u64,
    gaps: &mut Vec<Gap>,
) -> (String, String) {
    let (from, cut) = match out.abandon() {
        Ok(last) => (last.map_or(0, |l| l + 1), String::new()),
        // Where it ends is not known: every row is listed.
        Err(c) => (0, format!(" ({c:#})")),
    };
    let cause = format!("not in trace.csv: {e:#}{cut}");
    list_unwritten(gaps, from, k, &cause);
    (
        format!("{e:#}; trace.csv ends before sample {from}{cut}"),
        cause,
    )
}

/// Rows not in `trace.csv` by `gaps`.
fn rows_not_written(gaps: &[Gap]) -> u64 {
    gaps.iter()
        .filter(|g| g.part == ROW)
        .map(|g| g.to + 1 - g.from)
        .sum()
}

/// Writes the rows of a run held whole (every sample from 0, in order: the in-process clock)
/// to `trace.csv` at `path` and to `sinks`. An output that fails is left as a recording leaves
/// it ([`TraceStream`]): `trace.csv` cut after its last whole row and the rows after it listed
/// in `gaps`. The trace's figures, and the failures joined (None: all written).
pub fn write_whole(
    path: &std::path::Path,
    rows: &[TraceRow],
    sinks: &super::sinks::Sinks,
    gaps: &mut Vec<Gap>,
) -> Result<(TraceStats, Option<String>)> {
    let mut stats = TraceStats::of(rows);
    let mut errors = Vec::new();
    let mut csv = CsvTrace::create(path)?;
    if let Err(e) = rows
        .iter()
        .try_for_each(|r| csv.push(r))
        .and_then(|()| csv.flush())
    {
        let last = rows.last().map_or(0, |r| r.k);
        errors.push(abandon_trace(csv, &e, last, gaps).0);
        stats.rows_not_written = rows_not_written(gaps);
    }
    for r in rows {
        if let Err(e) = sinks.row(r, 0) {
            drop(sinks.take_mcap());
            errors.push(mcap_cut(&e, r.k));
            break;
        }
    }
    Ok((stats, (!errors.is_empty()).then(|| errors.join("; "))))
}

/// Why trace.mcap stops at sample `k`: write error `e`. The rows of the chunk it was filling
/// were never written, so it ends before `k`, and perhaps well before it.
fn mcap_cut(e: &anyhow::Error, k: u64) -> String {
    format!(
        "{e:#}; trace.mcap ends before sample {k} (the samples of its unfinished chunk, up to {} MiB of rows before it, are lost with it), without its index",
        crate::trace_mcap::CHUNK_BYTES >> 20
    )
}

/// Lists samples `from..=to` of `gaps` (in order, each up to `to`) again: their measurement
/// gaps stay (no row was made), each other sample is a row not written (part [`ROW`], for
/// `cause`), a command gap among them included.
fn list_unwritten(gaps: &mut Vec<Gap>, from: u64, to: u64, cause: &str) {
    let at = gaps.partition_point(|g| g.to < from);
    let mut tail = gaps.split_off(at);
    if let Some(g) = tail.first_mut().filter(|g| g.from < from) {
        gaps.push(Gap {
            to: from - 1,
            ..g.clone()
        });
        g.from = from;
    }
    let mut next = from;
    for g in tail.into_iter().filter(|g| g.part == "measurement") {
        (next..g.from).for_each(|r| push_gap(gaps, r, ROW, cause));
        next = g.to + 1;
        gaps.push(g);
    }
    (next..=to).for_each(|r| push_gap(gaps, r, ROW, cause));
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Kyslan's scenario with `n` samples at 10 kHz; its reference and load steps at 0,
    /// 20 and 40 ms.
    fn scenario(n: u64) -> Scenario {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../scenarios/kyslan-pi.toml");
        let mut sc =
            Scenario::from_toml(&std::fs::read_to_string(path).unwrap(), "kyslan-pi.toml").unwrap();
        sc.duration_s = n as f64 / sc.rates.sample_hz;
        assert_eq!(sc.samples(), n);
        sc
    }

    fn truth(k: u64, flags: u32) -> PlantTruth {
        PlantTruth {
            hdr: Header {
                k,
                flags,
                ..Default::default()
            },
            omega_m: k as f64,
            ..Default::default()
        }
    }

    fn cmd(k: u64) -> VoltageCommand {
        VoltageCommand {
            hdr: Header {
                k,
                ..Default::default()
            },
            ..Default::default()
        }
    }

    /// Feeds samples `ks` (measurement then command) and lets them leave as they would.
    fn feed(t: &mut TraceStream, ks: impl Iterator<Item = u64>, flags_at: &[u64]) {
        for k in ks {
            let f = if flags_at.contains(&k) {
                FLAG_SAFE_STATE
            } else {
                0
            };
            t.meas(truth(k, f), Vec::new).unwrap();
            t.cmd(cmd(k)).unwrap();
            t.advance().unwrap();
        }
    }

    #[test]
    fn rows_not_written_are_listed_around_the_measurements_never_made() {
        let g = |from, to, part, cause: &str| Gap {
            from,
            to,
            part,
            cause: cause.into(),
        };
        // Rows 0..=20 made; measurements 8..=9 and 15 never came; rows 4..=11 and 13 have no
        // command; the file ends after row 5.
        let mut gaps = vec![
            g(4, 7, "command", "c"),
            g(8, 9, "measurement", "m"),
            g(10, 11, "command", "c"),
            g(13, 13, "command", "c"),
            g(15, 15, "measurement", "m"),
        ];
        list_unwritten(&mut gaps, 6, 20, "w");
        assert_eq!(
            gaps,
            [
                g(4, 5, "command", "c"),
                g(6, 7, ROW, "w"),
                g(8, 9, "measurement", "m"),
                g(10, 14, ROW, "w"),
                g(15, 15, "measurement", "m"),
                g(16, 20, ROW, "w"),
            ]
        );
        // Nothing after the file's end but rows: one range; from the first row: all of it.
        let mut gaps = vec![g(0, 2, "measurement", "m")];
        list_unwritten(&mut gaps, 3, 9, "w");
        assert_eq!(gaps, [g(0, 2, "measurement", "m"), g(3, 9, ROW, "w")]);
        let mut gaps = vec![g(0, 2, "command", "c")];
        list_unwritten(&mut gaps, 0, 4, "w");
        assert_eq!(gaps, [g(0, 4, ROW, "w")]);
    }

    #[test]
    fn a_long_run_keeps_spaced_rows_and_every_row_around_steps_and_disturbances() {
        // 2^21 samples (3.5 min at 10 kHz): above FULL_ROWS, so one row in
        // ceil(2^21 / 200 000) = 11 is kept between the windows.
        let n = 1 << 21;
        let mut t = TraceStream::new(&scenario(n), None).unwrap();
        let disturbed = 1_500_000;
        feed(&mut t, 0..n, &[disturbed]);
        let t = t.finish().unwrap();
        assert_eq!(t.stats.rows, n);
        assert_eq!(t.stats.spacing, 11);
        assert!(t.gaps.is_empty());
        let kept: std::collections::BTreeSet<u64> = t.kept.iter().map(|r| r.k).collect();
        assert_eq!(t.stats.rows_analysed, kept.len() as u64);
        // Every row from 0.1 s before to 1 s after the load step at 40 ms (sample 400) and
        // the disturbed sample; spaced rows elsewhere, and nothing else.
        let whole = |a: u64, b: u64| (a..=b).all(|k| kept.contains(&k));
        assert!(whole(0, 400 + 10_000));
        assert!(whole(disturbed - 1_000, disturbed + 10_000));
        assert!(!kept.contains(&(disturbed - 1_001)) || (disturbed - 1_001) % 11 == 0);
        assert!(!kept.contains(&(disturbed + 10_001)) || (disturbed + 10_001) % 11 == 0);
        let expected = (0..n)
            .filter(|&k| {
                k % 11 == 0 || k <= 10_400 || (disturbed - 1_000..=disturbed + 10_000).contains(&k)
            })
            .count();
        assert_eq!(kept.len(), expected);
        // Memory: the kept rows stay near SPACED_ROWS plus the windows.
        assert!(kept.len() < (SPACED_ROWS + 30_000) as usize);
        assert_eq!(t.stats.window_rows_dropped, 0);
    }

    #[test]
    fn a_run_disturbed_throughout_keeps_no_more_window_rows_than_the_budget() {
        let n = 1 << 21;
        let mut t = TraceStream::new(&scenario(n), None).unwrap();
        // The safe state every 0.5 s: windows would cover every row.
        let marks: Vec<u64> = (0..n).step_by(5_000).collect();
        feed(&mut t, 0..n, &marks);
        let t = t.finish().unwrap();
        assert_eq!(t.stats.rows, n);
        let spaced = n.div_ceil(11);
        let kept = t.kept.len() as u64;
        // Every spaced row, plus exactly the budget of window rows (not spaced ones); every
        // other row was in a window and is counted as dropped.
        assert_eq!(kept, spaced + WINDOW_ROWS);
        assert_eq!(kept + t.stats.window_rows_dropped, n);
    }

    #[test]
    fn a_short_run_keeps_every_row_and_the_file_holds_the_same() {
        let dir = std::env::temp_dir().join(format!("drivelab-stream-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("trace.csv");
        let n = 5_000;
        let mut t = TraceStream::new(&scenario(n), Some(CsvTrace::create(&path).unwrap())).unwrap();
        feed(&mut t, 0..n, &[]);
        let t = t.finish().unwrap();
        assert_eq!(t.stats.spacing, 1);
        assert_eq!(t.kept.len() as u64, n);
        let back = drivelab_runtime::trace::read_csv(&path).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        assert_eq!(back, t.kept);
        assert_eq!(t.stats.peak_speed_rad_s, (n - 1) as f64);
    }

    #[test]
    fn timing_csv_times_the_middle_outputs_of_their_own_sample_while_it_is_in_the_window() {
        let dir = std::env::temp_dir().join(format!("drivelab-timing-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("timing.csv");
        let n = 3 * WINDOW;
        let mut t = TraceStream::new(&scenario(n), None)
            .unwrap()
            .with_timing(Some(TimingCsv::create(&path).unwrap()));
        assert!(t.times_the_chain());
        // Sample k at t_k = 1 ms + k × 100 µs, published 10 µs after it; its estimate 3 µs
        // later, its command 6 µs later; a current reference at 0 and 10.
        let t_k = |k: u64| 1_000_000 + k * 100_000;
        let stamped = |mut h: Header, after_ns: u64| {
            h.t_sample_ns = t_k(h.k);
            h.t_pub_ns = t_k(h.k) + after_ns;
            h
        };
        for k in 0..=WINDOW + 3 {
            let mut m = truth(k, 0);
            m.hdr = stamped(m.hdr, 10_000);
            t.meas(m, Vec::new).unwrap();
            // None for the sample a window after sample 2, in sample 2's slot.
            if k != WINDOW + 2 {
                t.middle(Middle::Estimate, k, t_k(k) + 13_000);
            }
            if k % 10 == 0 {
                t.middle(Middle::CurrentRef, k, t_k(k) + 20_000);
            }
            let mut c = cmd(k);
            c.hdr = stamped(c.hdr, 16_000);
            t.cmd(c).unwrap();
            t.advance().unwrap();
        }
        // Sample 1 has left the window: an estimate for it now is not timed (it would be
        // sample 1 + WINDOW's slot's, and that sample is not in the run's window yet).
        t.middle(Middle::Estimate, 1, t_k(1));
        t.finish().unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], TIMING_COLUMNS.join(","));
        assert_eq!(lines[1], "0,10.000,13.000,20.000,16.000");
        assert_eq!(lines[2], "1,10.000,13.000,,16.000");
        assert_eq!(lines[3], "2,10.000,13.000,,16.000");
        assert_eq!(lines[11], "10,10.000,13.000,20.000,16.000");
        // Sample WINDOW + 1's slot is sample 1's: it holds sample WINDOW + 1's estimate, not
        // the late one for sample 1; WINDOW + 2's holds sample 2's, which is not its own.
        let row = |k: u64| lines[k as usize + 1];
        assert_eq!(
            row(WINDOW + 1),
            format!("{},10.000,13.000,,16.000", WINDOW + 1)
        );
        assert_eq!(row(WINDOW + 2), format!("{},10.000,,,16.000", WINDOW + 2));
        assert_eq!(
            row(WINDOW + 3),
            format!("{},10.000,13.000,,16.000", WINDOW + 3)
        );
        assert_eq!(lines.len() as u64, WINDOW + 5);
    }

    #[test]
    fn messages_too_late_or_beyond_the_run_are_counted_apart_and_not_used() {
        let n = 10_000;
        let mut t = TraceStream::new(&scenario(n), None).unwrap();
        feed(&mut t, 0..5_000, &[]);
        // The lag is 0.2 s = 2 000 samples: sample 2 999 has left, 3 000 has not.
        assert!(t.complete(2_999));
        t.cmd(cmd(2_999)).unwrap();
        assert_eq!((t.late, t.rejected), (1, 0));
        t.meas(truth(n, 0), Vec::new).unwrap();
        t.cmd(cmd(u64::MAX)).unwrap();
        assert_eq!((t.late, t.rejected), (1, 2));
        feed(&mut t, 5_000..n, &[]);
        let t = t.finish().unwrap();
        assert_eq!(t.stats.rows, n);
        assert!(t.gaps.is_empty());
    }

    #[test]
    fn a_sample_pushed_out_of_the_window_before_its_command_came_is_listed() {
        let n = 3 * WINDOW;
        let mut t = TraceStream::new(&scenario(n), None).unwrap();
        // Sample 0's command never comes; sample WINDOW needs its slot: 0 leaves without.
        t.meas(truth(0, 0), Vec::new).unwrap();
        t.meas(truth(WINDOW, 0), Vec::new).unwrap();
        assert_eq!(t.next, 1);
        let t = t.finish().unwrap();
        assert_eq!(t.gaps[0].part, "command");
        assert_eq!((t.gaps[0].from, t.gaps[0].to), (0, 0));
        assert_eq!(t.gaps[1].part, "measurement");
        assert_eq!((t.gaps[1].from, t.gaps[1].to), (1, WINDOW - 1));
        assert!(t.gaps[1].cause.contains("lost"), "{}", t.gaps[1].cause);
        assert_eq!(t.gaps[3].part, "measurement");
        assert_eq!((t.gaps[3].from, t.gaps[3].to), (WINDOW + 1, n - 1));
        assert!(t.gaps[3].cause.contains("stopped"), "{}", t.gaps[3].cause);
    }
}
