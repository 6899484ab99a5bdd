//! What a run's slowest cycles were made of, from its `timing.csv`: the samples whose cycle
//! (t_k → command published) was above the cycle's 99th percentile, and how long each part
//! of the chain took in them against its median over every sample (docs/architecture.md,
//! "Where the microseconds go").

use anyhow::{anyhow, bail, Context, Result};
use drivelab_runtime::timing::LatencyHist;
use serde::Serialize;
use std::path::Path;

/// The three parts of a cycle that `timing.csv` separates, µs.
#[derive(Debug, Clone, Copy, Default, Serialize, PartialEq)]
pub struct Parts {
    /// t_k → the plant published sample k (its timer wake-up, step and publish).
    pub plant_us: f64,
    /// The plant's publish → the observer's estimate (a hop, the observer's step and publish).
    pub to_estimate_us: f64,
    /// The estimate → the current loop's command (a hop, its step and publish).
    pub to_command_us: f64,
}

/// `summary.json → timing → tail_by_part`.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct TailByPart {
    /// Samples with all three times (a sample superseded while the chain caught up, or whose
    /// command never came, has not).
    pub samples_timed: u64,
    /// The cycle's 99th percentile over them, µs (HdrHistogram, 3 significant digits).
    pub cycle_p99_us: f64,
    /// Samples whose cycle was above it: the tail.
    pub tail_samples: u64,
    /// Each part's median over every timed sample.
    pub median: Parts,
    /// Each part's median over the tail (a median: a stall's samples would make a mean of
    /// the stall).
    pub tail_median: Parts,
    /// Share of the tail whose plant part was above its own 99th percentile, %.
    pub tail_with_slow_plant_pct: f64,
    /// The same in one line, for the run's report.
    pub line: String,
}

/// One timed row: the three parts, ns.
type Row = [i64; 3];

/// Reads `timing.csv` once and calls `each` with every sample that has a plant, an estimate
/// and a command time.
fn rows(path: &Path, mut each: impl FnMut(Row)) -> Result<()> {
    let mut r =
        csv::Reader::from_path(path).with_context(|| format!("cannot read {}", path.display()))?;
    let ns = |s: &str| -> Result<Option<i64>> {
        if s.is_empty() {
            return Ok(None);
        }
        let us: f64 = s
            .parse()
            .map_err(|_| anyhow!("{}: '{s}' is not a time in µs", path.display()))?;
        Ok(Some((us * 1e3).round() as i64))
    };
    // The columns by their names in the header.
    let header = r
        .headers()
        .with_context(|| format!("cannot read {}", path.display()))?
        .clone();
    let [a_at, e_at, c_at] = [
        "plant_published_us",
        "estimate_published_us",
        "command_published_us",
    ]
    .map(|name| header.iter().position(|h| h == name));
    let (Some(a_at), Some(e_at), Some(c_at)) = (a_at, e_at, c_at) else {
        bail!(
            "{}: the header lacks plant_published_us, estimate_published_us or \
             command_published_us",
            path.display()
        );
    };
    for rec in r.records() {
        let rec = rec.with_context(|| format!("cannot read {}", path.display()))?;
        let col = |i: usize| rec.get(i).unwrap_or("");
        if let (Some(a), Some(e), Some(c)) = (ns(col(a_at))?, ns(col(e_at))?, ns(col(c_at))?) {
            each([a, e - a, c - e]);
        }
    }
    Ok(())
}

/// One histogram per part, in `Row`'s order.
fn part_hists() -> [LatencyHist; 3] {
    [
        LatencyHist::new("plant"),
        LatencyHist::new("to estimate"),
        LatencyHist::new("to command"),
    ]
}

/// Each part's median, µs.
fn medians(h: &[LatencyHist; 3]) -> Parts {
    let median = |h: &LatencyHist| h.quantile_ns(0.5) as f64 * 1e-3;
    Parts {
        plant_us: median(&h[0]),
        to_estimate_us: median(&h[1]),
        to_command_us: median(&h[2]),
    }
}

/// The tail of the run whose `timing.csv` is at `path` (two passes over the file: the
/// percentiles, then the tail's parts); None where no sample was timed whole.
pub fn of(path: &Path) -> Result<Option<TailByPart>> {
    let mut cycle = LatencyHist::new("cycle");
    let mut parts = part_hists();
    rows(path, |r| {
        cycle.record_ns(r.iter().sum());
        for (h, v) in parts.iter_mut().zip(r) {
            h.record_ns(v);
        }
    })?;
    if cycle.is_empty() {
        return Ok(None);
    }
    let p99 = cycle.quantile_ns(0.99) as i64;
    let plant_p99 = parts[0].quantile_ns(0.99) as i64;
    let mut tail = part_hists();
    let mut slow_plant = 0u64;
    rows(path, |r| {
        if r.iter().sum::<i64>() > p99 {
            for (h, v) in tail.iter_mut().zip(r) {
                h.record_ns(v);
            }
            slow_plant += u64::from(r[0] > plant_p99);
        }
    })?;
    let n = tail[0].len();
    let mut t = TailByPart {
        samples_timed: cycle.len(),
        cycle_p99_us: p99 as f64 * 1e-3,
        tail_samples: n,
        median: medians(&parts),
        tail_median: medians(&tail),
        tail_with_slow_plant_pct: if n == 0 {
            0.0
        } else {
            100.0 * slow_plant as f64 / n as f64
        },
        line: String::new(),
    };
    t.line = format!(
        "slowest 1 % of cycles (above {:.1} µs, {} samples), their medians (every \
             sample's): plant published at {:.1} µs ({:.1}), estimate {:.1} µs later ({:.1}), \
             command {:.1} µs later ({:.1}); {:.0} % of them had the plant above its own p99",
        t.cycle_p99_us,
        t.tail_samples,
        t.tail_median.plant_us,
        t.median.plant_us,
        t.tail_median.to_estimate_us,
        t.median.to_estimate_us,
        t.tail_median.to_command_us,
        t.median.to_command_us,
        t.tail_with_slow_plant_pct
    );
    Ok(Some(t))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(name: &str, body: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("drivelab-tail-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("timing.csv");
        std::fs::write(
            &p,
            format!(
                "k,plant_published_us,estimate_published_us,current_ref_published_us,\
                 command_published_us\n{body}"
            ),
        )
        .unwrap();
        p
    }

    #[test]
    fn the_tail_is_the_samples_above_the_cycles_p99_with_their_parts() {
        // 990 samples: plant 15, estimate at 17, command at 20 µs (a 20 µs cycle); 10 slow
        // ones: 6 with a slow plant (40, 42, 45: 45 µs), 4 with a slow last hop (15, 17, 37).
        // And rows that are not timed whole: no estimate, no command.
        let mut body = String::new();
        for k in 0..1000 {
            let (a, e, c) = match k {
                k if k % 100 == 7 && k < 600 => (40.0, 42.0, 45.0),
                k if k % 100 == 7 => (15.0, 17.0, 37.0),
                _ => (15.0, 17.0, 20.0),
            };
            let r = if k % 10 == 0 { "30.000" } else { "" };
            body += &format!("{k},{a:.3},{e:.3},{r},{c:.3}\n");
        }
        body += "1000,15.000,,,20.000\n1001,15.000,17.000,,\n";
        let p = write("tail", &body);
        let t = of(&p).unwrap().unwrap();
        std::fs::remove_dir_all(p.parent().unwrap()).unwrap();
        assert_eq!(t.samples_timed, 1000);
        // The 99th percentile is the 990th value, 20 µs (to 0.1 %): the 10 slow ones are
        // above it.
        assert!((t.cycle_p99_us - 20.0).abs() < 0.02, "{t:?}");
        assert_eq!(t.tail_samples, 10);
        // HdrHistogram reports the top of a value's bucket: up to 0.1 % above it.
        let close = |a: f64, b: f64| a >= b && a <= b * 1.001 + 1e-3;
        assert!(close(t.median.plant_us, 15.0), "{t:?}");
        assert!(close(t.median.to_estimate_us, 2.0), "{t:?}");
        assert!(close(t.median.to_command_us, 3.0), "{t:?}");
        // Tail medians (the 5th of 10): the plant's 40 µs (4 × 15, 6 × 40), the first hop's
        // 2, the last hop's 3 (6 × 3, 4 × 20).
        assert!(close(t.tail_median.plant_us, 40.0), "{t:?}");
        assert!(close(t.tail_median.to_estimate_us, 2.0), "{t:?}");
        assert!(close(t.tail_median.to_command_us, 3.0), "{t:?}");
        // The plant's own p99 is 15 µs: 6 of the 10 had it above.
        assert_eq!(t.tail_with_slow_plant_pct, 60.0);
        assert_eq!(
            t.line,
            "slowest 1 % of cycles (above 20.0 µs, 10 samples), their medians (every sample's): \
             plant published at 40.0 µs (15.0), estimate 2.0 µs later (2.0), command 3.0 µs \
             later (3.0); 60 % of them had the plant above its own p99"
        );
    }

    #[test]
    fn nothing_timed_is_none_and_a_bad_cell_is_an_error_that_names_it() {
        let p = write("none", "0,15.000,,,\n");
        assert_eq!(of(&p).unwrap(), None);
        std::fs::write(
            &p,
            "k,plant_published_us,estimate_published_us,current_ref_published_us,\
             command_published_us\n0,15.000,x,,20.000\n",
        )
        .unwrap();
        let e = format!("{:#}", of(&p).unwrap_err());
        assert!(e.ends_with("timing.csv: 'x' is not a time in µs"), "{e}");
        // An older file, without the estimate's column.
        std::fs::write(
            &p,
            "k,plant_published_us,command_published_us\n0,15.000,20.000\n",
        )
        .unwrap();
        let e = format!("{:#}", of(&p).unwrap_err());
        std::fs::remove_dir_all(p.parent().unwrap()).unwrap();
        assert!(
            e.ends_with(
                "timing.csv: the header lacks plant_published_us, estimate_published_us or \
                 command_published_us"
            ),
            "{e}"
        );
    }
}
