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

/// The column names of `trace.csv`: [`TraceRow`]'s fields, as serde names them.
fn header() -> anyhow::Result<csv::StringRecord> {
    let mut w = csv::Writer::from_writer(Vec::new());
    w.serialize(TraceRow::default())?;
    let bytes = w.into_inner().map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut r = csv::ReaderBuilder::new()
        .has_headers(false)
        .from_reader(bytes.as_slice());
    r.records()
        .next()
        .ok_or_else(|| anyhow::anyhow!("no trace header"))?
        .map_err(Into::into)
}

/// `trace.csv` written row by row as a run goes (buffered), so that a long run needs no
/// memory for its trace and what was recorded is on disk.
pub struct CsvTrace {
    w: csv::Writer<std::fs::File>,
    path: std::path::PathBuf,
}

impl CsvTrace {
    /// Creates (truncates) the file and writes its header, so that a run that records no
    /// sample (a drive that never started) leaves a trace with its columns, not an empty file.
    pub fn create(path: &std::path::Path) -> anyhow::Result<Self> {
        let file = crate::files::create(path)
            .map_err(|e| anyhow::anyhow!("cannot create {}: {e}", path.display()))?;
        let mut w = csv::WriterBuilder::new()
            .has_headers(false)
            .from_writer(file);
        let fail = |e: csv::Error| anyhow::anyhow!("cannot write {}: {e}", path.display());
        w.write_record(header()?.iter()).map_err(fail)?;
        w.flush()
            .map_err(|e| anyhow::anyhow!("cannot write {}: {e}", path.display()))?;
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

    /// Writes what is buffered to the file.
    pub fn flush(&mut self) -> anyhow::Result<()> {
        self.w
            .flush()
            .map_err(|e| anyhow::anyhow!("cannot write {}: {e}", self.path.display()))
    }

    /// Writes what is buffered to the file and closes it.
    pub fn finish(mut self) -> anyhow::Result<()> {
        self.flush()
    }

    /// After a write failed (a full disk, the file size limit): lets go of the file, writing
    /// what it still takes of the buffer, then cuts it after its last whole row, so that it
    /// reads as a trace without a cut line. The sample index of that row (None: no row is
    /// whole).
    pub fn abandon(self) -> anyhow::Result<Option<u64>> {
        let path = self.path;
        // Dropping the writer writes what is buffered, ignoring a failure again.
        drop(self.w);
        cut_after_last_row(&path)
    }
}

/// Cuts the trace at `path` after its last newline and reads the sample index of the row that
/// line ends (None: only the header, or not even that, is whole).
pub fn cut_after_last_row(path: &std::path::Path) -> anyhow::Result<Option<u64>> {
    use std::io::{Read, Seek, SeekFrom};
    let fail = |e: std::io::Error| anyhow::anyhow!("cannot cut {}: {e}", path.display());
    let mut f = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(path)
        .map_err(fail)?;
    let len = f.metadata().map_err(fail)?.len();
    // A row is a few hundred bytes: the last two rows are within this.
    let from = len.saturating_sub(8192);
    let mut tail = Vec::new();
    f.seek(SeekFrom::Start(from)).map_err(fail)?;
    f.read_to_end(&mut tail).map_err(fail)?;
    let Some(end) = tail.iter().rposition(|&b| b == b'\n') else {
        // Without a newline in its last 8 KiB, the file holds at most a cut header.
        f.set_len(0).map_err(fail)?;
        return Ok(None);
    };
    f.set_len(from + end as u64 + 1).map_err(fail)?;
    let start = tail[..end]
        .iter()
        .rposition(|&b| b == b'\n')
        .map_or(0, |i| i + 1);
    let line = &tail[start..end];
    let first = line.split(|&b| b == b',').next().unwrap_or_default();
    Ok(std::str::from_utf8(first)
        .ok()
        .and_then(|k| k.parse::<u64>().ok()))
}

/// True when the file at `path` is not empty and its last byte is not a newline.
fn ends_without_newline(path: &std::path::Path) -> anyhow::Result<bool> {
    use std::io::{Read, Seek, SeekFrom};
    let mut f = std::fs::File::open(path)
        .map_err(|e| anyhow::anyhow!("cannot read {}: {e}", path.display()))?;
    if f.metadata().map(|m| m.len()).unwrap_or(0) == 0 {
        return Ok(false);
    }
    let mut last = [0u8; 1];
    f.seek(SeekFrom::End(-1))
        .and_then(|_| f.read_exact(&mut last))
        .map_err(|e| anyhow::anyhow!("cannot read {}: {e}", path.display()))?;
    Ok(last[0] != b'\n')
}

/// Reads a trace written by [`write_csv`]. A last line cut short (a writer killed in the
/// middle of it) is left out with a warning on stderr; any other bad row is an error.
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
    // A launcher killed with SIGKILL (or a machine that lost power) leaves the file cut
    // wherever its last buffered write ended: the rows before the cut are whole.
    let cut = ends_without_newline(path)?;
    let mut prev: Option<TraceRow> = None;
    let mut n = 0;
    let mut records = r.deserialize().enumerate().peekable();
    while let Some((i, rec)) = records.next() {
        let row: TraceRow = match rec {
            Ok(row) => row,
            Err(e) if cut && records.peek().is_none() => {
                crate::errln!(
                    "drivelab: warning: {}: its last line (row {}) is cut short, as a killed writer leaves it, and is left out ({e}); {n} rows read",
                    path.display(),
                    i + 1
                );
                break;
            }
            Err(e) => anyhow::bail!("{}: {e}", path.display()),
        };
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_trace_without_rows_has_the_header_of_one_with_rows() {
        let dir = std::env::temp_dir().join(format!("dl-trace-header-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (empty, full) = (dir.join("empty.csv"), dir.join("full.csv"));
        CsvTrace::create(&empty).unwrap().finish().unwrap();
        let row = |k: u64| TraceRow {
            k,
            t: k as f64 * 1e-4,
            ..Default::default()
        };
        write_csv(&full, &[row(0), row(1)]).unwrap();
        let empty_text = std::fs::read_to_string(&empty).unwrap();
        let full_text = std::fs::read_to_string(&full).unwrap();
        assert_eq!(empty_text.lines().count(), 1, "{empty_text}");
        assert_eq!(full_text.lines().next(), empty_text.lines().next());
        assert_eq!(full_text.lines().count(), 3, "{full_text}");
        assert!(read_csv(&empty).unwrap().is_empty());
        assert_eq!(read_csv(&full).unwrap().len(), 2);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_trace_cut_after_a_failed_write_ends_on_its_last_whole_row() {
        let dir = std::env::temp_dir().join(format!("drivelab-cut-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("trace.csv");
        write_csv(&path, &rows(40)).unwrap();
        let whole = std::fs::read(&path).unwrap();
        // Cut in the middle of row 37: rows 0..=36 are whole.
        let row_37 = whole
            .split(|&b| b == b'\n')
            .take(38)
            .map(|l| l.len() + 1)
            .sum::<usize>();
        std::fs::write(&path, &whole[..row_37 + 5]).unwrap();
        assert_eq!(cut_after_last_row(&path).unwrap(), Some(36));
        let read = read_csv(&path).unwrap();
        assert_eq!(read, rows(37));
        // Whole already: nothing is cut.
        assert_eq!(cut_after_last_row(&path).unwrap(), Some(36));
        assert_eq!(std::fs::read(&path).unwrap(), whole[..row_37]);
        // Only the header is whole; a cut header goes.
        let header = whole.iter().position(|&b| b == b'\n').unwrap() + 1;
        std::fs::write(&path, &whole[..header + 3]).unwrap();
        assert_eq!(cut_after_last_row(&path).unwrap(), None);
        assert_eq!(std::fs::read(&path).unwrap(), whole[..header]);
        std::fs::write(&path, &whole[..header - 3]).unwrap();
        assert_eq!(cut_after_last_row(&path).unwrap(), None);
        assert_eq!(std::fs::read(&path).unwrap(), b"");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    fn rows(n: u64) -> Vec<TraceRow> {
        (0..n)
            .map(|k| TraceRow {
                k,
                t: k as f64 * 1e-4,
                omega_m: 0.123_456_789 * k as f64,
                ..TraceRow::default()
            })
            .collect()
    }

    /// A trace of 5 rows whose text `edit` then changes (cuts it short, adds a bad row …).
    fn damaged(name: &str, edit: impl FnOnce(Vec<u8>) -> Vec<u8>) -> std::path::PathBuf {
        let path =
            std::env::temp_dir().join(format!("drivelab-trace-{}-{name}.csv", std::process::id()));
        write_csv(&path, &rows(5)).unwrap();
        let text = std::fs::read(&path).unwrap();
        std::fs::write(&path, edit(text)).unwrap();
        path
    }

    #[test]
    fn a_last_row_cut_short_is_left_out_and_the_rows_before_it_are_read() {
        // Cut in the middle of the last row's numbers, as a killed writer leaves the file.
        let path = damaged("cut", |mut t| {
            let last_row = t[..t.len() - 1].iter().rposition(|&b| b == b'\n').unwrap();
            t.truncate(last_row + 9);
            t
        });
        let read = read_csv(&path);
        std::fs::remove_file(&path).unwrap();
        assert_eq!(read.unwrap(), rows(4));
    }

    #[test]
    fn a_bad_last_row_that_ends_with_a_newline_is_an_error() {
        // Whole lines: nothing was cut, the row is wrong.
        let path = damaged("bad-last", |mut t| {
            t.extend_from_slice(b"5,0.0005,oops\n");
            t
        });
        let read = read_csv(&path);
        std::fs::remove_file(&path).unwrap();
        let e = read.unwrap_err().to_string();
        assert!(e.contains("bad-last.csv"), "{e}");
    }

    #[test]
    fn a_bad_row_before_the_cut_one_is_an_error() {
        let path = damaged("bad-middle", |t| {
            let text = String::from_utf8(t).unwrap();
            let mut lines: Vec<&str> = text.lines().collect();
            lines[2] = "1,0.0001,broken";
            let mut out = lines.join("\n");
            out.truncate(out.len() - 3);
            out.into_bytes()
        });
        let read = read_csv(&path);
        std::fs::remove_file(&path).unwrap();
        assert!(read.is_err());
    }
}
