//! The run trace: one row per plant sample, in SI units.
//!
//! Column meaning (docs/architecture.md, "The cycle"): `u_d, u_q` in row k are the voltages the plant applied on
//! `[t_k, t_{k+1})`; speeds are mechanical rad/s, angles electrical rad.

use serde::{Deserialize, Serialize};

/// One row of `trace.csv`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct TraceRow {
    /// Sample index k.
    pub k: u64,
    /// Ideal sample instant t_k = k * Ts, s.
    pub t: f64,
    /// Speed reference (after the speed loop's input, before the prefilter), mechanical rad/s.
    pub omega_ref: f64,
    /// True rotor speed, mechanical rad/s.
    pub omega_m: f64,
    /// Estimated rotor speed (observer), mechanical rad/s.
    pub omega_hat: f64,
    /// True electrical angle, rad, wrapped to [0, 2π).
    pub theta_e: f64,
    /// Estimated electrical angle, rad, wrapped to [0, 2π).
    pub theta_hat: f64,
    /// d-axis current reference used by the current loop at k, A.
    pub i_d_ref: f64,
    /// q-axis current reference used by the current loop at k, A.
    pub i_q_ref: f64,
    /// True d-axis current, A.
    pub i_d: f64,
    /// True q-axis current, A.
    pub i_q: f64,
    /// d-axis voltage applied on [t_k, t_{k+1}), V.
    pub u_d: f64,
    /// q-axis voltage applied on [t_k, t_{k+1}), V.
    pub u_q: f64,
    /// Load torque applied on [t_k, t_{k+1}), N·m.
    pub t_load: f64,
    /// True mechanical position at t_k, unwrapped (from 0 at the start), rad.
    #[serde(default)]
    pub theta_m: f64,
    /// Position reference of an outer (position) loop in use at k, rad; empty when the
    /// drive has none.
    #[serde(default)]
    pub theta_m_ref: Option<f64>,
    /// Plant's header flags of sample k (`messages::FLAG_*`: 2 stale command held, 4 safe state).
    pub plant_flags: u32,
    /// Current loop's header flags of command k (8 = it used a stale or fallback input).
    pub ctrl_flags: u32,
    /// 1 if the plant held a stale command or went to its safe state at k (deadline miss), else 0.
    pub miss: u8,
}

/// Writes rows to a CSV file with a header line.
pub fn write_csv(path: &std::path::Path, rows: &[TraceRow]) -> anyhow::Result<()> {
    let mut w = CsvTrace::create(path)?;
    for r in rows {
        w.push(r)?;
    }
    w.finish()
}

/// `trace.csv` written row by row as a run goes (buffered), so that a long run needs no
/// memory for its trace and what was recorded is on disk.
pub struct CsvTrace {
    w: csv::Writer<std::fs::File>,
    path: std::path::PathBuf,
}

impl CsvTrace {
    /// Creates (truncates) the file.
    pub fn create(path: &std::path::Path) -> anyhow::Result<Self> {
        let w = csv::Writer::from_path(path)
            .map_err(|e| anyhow::anyhow!("cannot create {}: {e}", path.display()))?;
        Ok(Self {
            w,
            path: path.to_path_buf(),
        })
    }

    /// Appends one row.
    pub fn push(&mut self, r: &TraceRow) -> anyhow::Result<()> {
        self.w
            .serialize(r)
            .map_err(|e| anyhow::anyhow!("cannot write {}: {e}", self.path.display()))
    }

    /// Flushes what is buffered to the file.
    pub fn finish(mut self) -> anyhow::Result<()> {
        self.w
            .flush()
            .map_err(|e| anyhow::anyhow!("cannot write {}: {e}", self.path.display()))
    }
}

/// Reads a trace written by [`write_csv`].
pub fn read_csv(path: &std::path::Path) -> anyhow::Result<Vec<TraceRow>> {
    let mut rows: Vec<TraceRow> = Vec::new();
    for_each_csv_row(path, |row| {
        rows.push(row);
        Ok(())
    })?;
    Ok(rows)
}

/// Reads `trace.csv` at `path` row by row into `each`, checked as [`read_csv`] checks it,
/// without keeping the rows; the number of rows.
pub fn for_each_csv_row(
    path: &std::path::Path,
    mut each: impl FnMut(TraceRow) -> anyhow::Result<()>,
) -> anyhow::Result<usize> {
    let mut r = csv::Reader::from_path(path)
        .map_err(|e| anyhow::anyhow!("cannot read {}: {e}", path.display()))?;
    let mut prev: Option<TraceRow> = None;
    let mut n = 0;
    for (i, rec) in r.deserialize().enumerate() {
        let row: TraceRow = rec.map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        // A trace runs forward: each row a later sample at a later time (gaps allowed).
        if !row.t.is_finite() {
            anyhow::bail!(
                "{}: row {} (k = {}): time t = {} is not a number of seconds",
                path.display(),
                i + 1,
                row.k,
                row.t
            );
        }
        if let Some(p) = prev.filter(|p| row.k <= p.k || row.t <= p.t) {
            anyhow::bail!(
                "{}: row {} (k = {}, t = {} s) does not come after the row before it (k = {}, t = {} s): a trace runs forward",
                path.display(),
                i + 1,
                row.k,
                row.t,
                p.k,
                p.t
            );
        }
        prev = Some(row);
        n += 1;
        each(row)?;
    }
    Ok(n)
}
