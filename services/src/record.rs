//! `drivelab record --connect ENDPOINT --out DIR`: records a remote drive (one started with
//! `drivelab run --zenoh-listen`) into a local run folder: its scenario, `trace.csv` built
//! by the same [`TraceStream`] as a local run's, and `summary.json`, the drive's own summary
//! with this recording's trace figures and missing samples (docs/architecture.md, "Across
//! machines (Zenoh)").
//!
//! It subscribes first, then fetches the bridge's history (the last 6.5 s at 10 kHz), so a
//! recorder that joins early in a run misses nothing; samples older than that history, or
//! lost on the way, are listed in `missing_samples` with their cause.

use crate::launcher::stream::TraceStream;
use crate::launcher::Gap;
use anyhow::{anyhow, bail, Context, Result};
use drivelab_bridge::codec::Wire;
use drivelab_bridge::remote::{Feed, Remote};
use drivelab_runtime::config::Scenario;
use drivelab_runtime::messages::{PlantTruth, SpeedRef, VoltageCommand};
use serde_json::json;
use std::path::PathBuf;
use std::time::{Duration, Instant};

/// Options of `drivelab record`.
#[derive(Debug, Clone)]
pub struct RecordOptions {
    /// The drive's bridge.
    pub endpoint: String,
    /// Its bus id (needed only when the bridge serves several drives).
    pub bus: Option<String>,
    /// Zenoh configuration file (TLS, access control).
    pub config: Option<PathBuf>,
    /// The local run folder.
    pub out: PathBuf,
    /// How long to retry a refused connection (the drive not started yet).
    pub wait: Duration,
}

/// What a recording produced.
#[derive(Debug)]
pub struct Recorded {
    /// The bus id of the drive.
    pub bus: String,
    /// The summary as written.
    pub summary: serde_json::Value,
}

/// After the drive's last sample, how long to wait for its summary (it draws its plots
/// first).
const SUMMARY_WAIT: Duration = Duration::from_secs(120);
/// With no message for this long and no end seen, the drive is taken as gone.
const SILENCE: Duration = Duration::from_secs(30);

/// Feeds the messages of `feed` newer than `*last` to `take`; true when one ended the run.
fn drain<T: Wire>(
    remote: &Remote,
    feed: &Feed<T>,
    last: &mut Option<u64>,
    mut take: impl FnMut(T) -> Result<()>,
    hdr: impl Fn(&T) -> drivelab_runtime::messages::Header,
) -> Result<(bool, usize)> {
    let (mut ended, mut n) = (false, 0);
    while let Some(m) = remote.next(feed)? {
        n += 1;
        let h = hdr(&m);
        if h.is_warmup() {
            continue;
        }
        if h.is_end() {
            ended = true;
            continue;
        }
        // The history and the live feed overlap: each sample once.
        if last.is_some_and(|l| h.k <= l) {
            continue;
        }
        *last = Some(h.k);
        take(m)?;
    }
    Ok((ended, n))
}

/// Creates folder `out` with its missing parents and locks it
/// ([`crate::launcher::lock_run_folder`]: an earlier run's outputs stay until the remote
/// drive answers); returns the folders it made, outermost first, and the folder's lock.
fn make_folder(out: &std::path::Path) -> Result<(Vec<PathBuf>, crate::launcher::RunFolderLock)> {
    let mut made = Vec::new();
    let mut d = Some(out);
    while let Some(p) = d.filter(|p| !p.as_os_str().is_empty() && !p.exists()) {
        made.push(p.to_path_buf());
        d = p.parent();
    }
    made.reverse();
    let lock = crate::launcher::lock_run_folder(out)
        .with_context(|| format!("--out {}", out.display()))?;
    Ok((made, lock))
}

/// Records the remote drive into `o.out`.
pub fn record(o: &RecordOptions) -> Result<Recorded> {
    crate::common::install_signal_handlers()?;
    // The run folder first: a bad --out fails at once, not after connecting (which may
    // wait for --wait seconds); when nothing is recorded, the folders made are removed and
    // an earlier run in it is left as it was.
    let (made, folder) = make_folder(&o.out)?;
    let connected = (|| -> Result<_> {
        let remote = Remote::connect(&o.endpoint, o.bus.as_deref(), o.config.as_deref(), o.wait)?;
        let toml_text = remote.scenario_toml()?;
        let sc = Scenario::from_toml(&toml_text, "the remote drive's scenario")
            .map_err(|e| anyhow!("the remote drive's scenario: {e}"))?;
        // Its outer loop's rate divider: θ_m* is left empty while the speed loop does not
        // follow that loop, as in the drive's own trace (docs/architecture.md). A drive of
        // an older drivelab has no topology to send: its trace is still recorded, with the
        // last θ_m* held while an outer loop is down, and one line says so.
        let outer_divider = match remote.topology_json() {
            Ok(text) => {
                let plan: drivelab_runtime::service::TopologyPlan = serde_json::from_str(&text)
                    .map_err(|e| anyhow!("the remote drive's topology: {e}"))?;
                TraceStream::outer_divider(&plan)
            }
            Err(e) => {
                eprintln!(
                    "drivelab: warning: {e:#} (a drive of an older drivelab?): while an outer loop is down, the recorded θ_m* holds its last value where the drive's own trace leaves it empty"
                );
                None
            }
        };
        Ok((remote, toml_text, sc, outer_divider))
    })();
    let (remote, toml_text, sc, outer_divider) = match connected {
        Ok(c) => c,
        Err(e) => {
            for d in made.iter().rev() {
                let _ = std::fs::remove_dir(d);
            }
            return Err(e);
        }
    };
    folder.remove_earlier_outputs()?;
    drivelab_runtime::files::write(o.out.join("scenario.toml"), &toml_text)?;
    // Subscribe, then fetch the history: nothing falls in between.
    let truth = remote.feed::<PlantTruth>()?;
    let cmd = remote.feed::<VoltageCommand>()?;
    let wref = remote.feed::<SpeedRef>()?;
    let summary_feed = remote.summary_feed()?;
    let trace = TraceStream::new(
        &sc,
        Some(drivelab_runtime::trace::CsvTrace::create(
            &o.out.join("trace.csv"),
        )?),
    )?;
    // trace.mcap beside it, as a local run's (the drive's clock is not this machine's).
    let sinks = crate::launcher::sinks::Sinks::new(
        Some(crate::trace_mcap::McapTrace::create(
            &o.out.join("trace.mcap"),
        )?),
        None,
    )
    .without_wall_time();
    let mut trace = trace
        .with_sinks(sinks.clone())
        .with_outer_divider(outer_divider);
    let (mut last_truth, mut last_cmd) = (None, None);
    let mut first_k = None;
    for m in remote.history::<PlantTruth>()? {
        if !m.hdr.is_warmup() && !m.hdr.is_end() && last_truth.is_none_or(|l| m.hdr.k > l) {
            first_k.get_or_insert(m.hdr.k);
            last_truth = Some(m.hdr.k);
            trace.meas(m, Vec::new)?;
        }
    }
    for c in remote.history::<VoltageCommand>()? {
        if !c.hdr.is_warmup() && !c.hdr.is_end() && last_cmd.is_none_or(|l| c.hdr.k > l) {
            last_cmd = Some(c.hdr.k);
            trace.cmd(c)?;
        }
    }
    for w in remote.history::<SpeedRef>()? {
        if !w.hdr.is_warmup() && !w.hdr.is_end() && !w.hdr.is_absent() {
            trace.wref(w.hdr.k, w.theta_m_ref);
        }
    }
    // Live samples only (not the history): published by the plant → decoded here, ns.
    // CLOCK_MONOTONIC is one clock on one machine only: meaningful over localhost.
    let mut hop_ns: Vec<u64> = Vec::new();
    let (mut truth_end, mut cmd_end) = (false, false);
    let mut last_wref = None;
    let mut heard = Instant::now();
    let mut ended_at: Option<Instant> = None;
    let mut failure = None;
    let summary = loop {
        let (e1, n1) = drain(
            &remote,
            &truth,
            &mut last_truth,
            |m| {
                first_k.get_or_insert(m.hdr.k);
                if m.hdr.t_pub_ns > 0 {
                    hop_ns.push(drivelab_runtime::rt::now_ns().saturating_sub(m.hdr.t_pub_ns));
                }
                trace.meas(m, Vec::new)
            },
            |m| m.hdr,
        )?;
        let (e2, n2) = drain(&remote, &cmd, &mut last_cmd, |c| trace.cmd(c), |c| c.hdr)?;
        let (_, n3) = drain(
            &remote,
            &wref,
            &mut last_wref,
            |w| {
                // An absent marker (lockstep: the loop is down) is no reference.
                if !w.hdr.is_absent() {
                    trace.wref(w.hdr.k, w.theta_m_ref);
                }
                Ok(())
            },
            |w| w.hdr,
        )?;
        truth_end |= e1;
        cmd_end |= e2;
        trace.advance()?;
        // An output that cannot be written ends the recording (the failure is its first
        // error; the rows not written are listed).
        if !trace.write_errors.is_empty() {
            break None;
        }
        if let Some(s) = Remote::take_summary(&summary_feed) {
            break Some(s);
        }
        if n1 + n2 + n3 > 0 {
            heard = Instant::now();
        } else {
            std::thread::sleep(Duration::from_millis(1));
        }
        if truth_end && cmd_end {
            let t = *ended_at.get_or_insert_with(Instant::now);
            if t.elapsed() > SUMMARY_WAIT {
                failure = Some(format!(
                    "the drive ended but sent no summary within {SUMMARY_WAIT:?}"
                ));
                break None;
            }
        } else if heard.elapsed() > SILENCE {
            failure = Some(format!(
                "no data from the drive for {SILENCE:?} and no end: the drive or the link is gone"
            ));
            break None;
        }
        if crate::common::stop_requested() {
            failure = Some("interrupted".into());
            break None;
        }
    };
    let t = trace.finish()?;
    if !t.write_errors.is_empty() {
        crate::launcher::add_failure(&mut failure, t.write_errors.join("; "));
    }
    let mut s: serde_json::Value = match &summary {
        Some(text) => serde_json::from_str(text)
            .map_err(|e| anyhow!("the drive's summary is not JSON: {e}"))?,
        None => json!({ "scenario": sc.name, "rate_hz": sc.rates.sample_hz }),
    };
    let mut gaps = remote_gaps(t.gaps, first_k, &drive_gaps(&s), summary.is_some());
    // Without the drive's word, the last samples are missing because the recording ended.
    if let (Some(f), None) = (&failure, &summary) {
        for g in gaps
            .iter_mut()
            .filter(|g| g.part == "measurement" && g.to + 1 == sc.samples())
        {
            g.cause = format!("not recorded: the recording ended early: {f}");
        }
    }
    if let Some(m) = s.as_object_mut() {
        // Its plots stay in the drive's own run folder.
        m.remove("plots");
        let drive_gaps = m.remove("missing_samples").unwrap_or(json!([]));
        m.insert("drive_missing_samples".into(), drive_gaps);
    }
    let missing = crate::launcher::samples_missing(&gaps);
    s["samples"] = json!(t.stats.rows_written());
    s["samples_expected"] = json!(sc.samples());
    s["samples_missing"] = json!(missing);
    s["trace"] = serde_json::to_value(t.stats)?;
    s["missing_samples"] = serde_json::to_value(&gaps)?;
    s["record"] = json!({
        "endpoint": remote.endpoint(),
        "bus": remote.bus(),
        "first_sample": first_k,
        "rejected_frames": remote.rejected(),
        "late_messages": t.late,
        "drive_summary": summary.is_some(),
        "failure": failure,
        "live_samples": hop_ns.len(),
        "published_to_recorded_us": percentiles_us(&mut hop_ns),
    });
    let recorded = format!(
        "what was recorded is in {}: {} of {} samples",
        o.out.display(),
        t.stats.rows_written(),
        sc.samples()
    );
    crate::launcher::write_summary(
        &o.out,
        &mut s,
        (&mut failure, "/record/failure"),
        sinks.take_mcap(),
        (&toml_text, sc.rates.sample_hz),
        &recorded,
    )?;
    let bus = remote.bus().to_string();
    remote.close()?;
    if let Some(f) = failure {
        bail!("{f} ({recorded})");
    }
    Ok(Recorded { bus, summary: s })
}

/// p50, p99, p99.9 and max of `v` (ns) in µs; null when empty.
fn percentiles_us(v: &mut [u64]) -> serde_json::Value {
    if v.is_empty() {
        return serde_json::Value::Null;
    }
    v.sort_unstable();
    let at = |q: f64| v[((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1] as f64 / 1e3;
    json!({ "p50": at(0.5), "p99": at(0.99), "p999": at(0.999), "max": at(1.0) })
}

/// Why a remote recording lacks the samples of a plant downtime the drive rebuilt.
const REBUILT_THERE: &str = "the plant was down: the drive's trace has these samples rebuilt, which were never published to send (not rebuilt here)";

/// What the drive's summary says of its samples that no plant published: its own missing
/// samples, and its rebuilt downtimes (`plant_down_ranges`, measurements): (from, to, part,
/// cause).
fn drive_gaps(summary: &serde_json::Value) -> Vec<(u64, u64, String, String)> {
    let missing = summary["missing_samples"].as_array().into_iter().flatten();
    let missing = missing.filter_map(|g| {
        Some((
            g["from"].as_u64()?,
            g["to"].as_u64()?,
            g["part"].as_str()?.to_string(),
            g["cause"].as_str()?.to_string(),
        ))
    });
    let rebuilt = summary["plant_down_ranges"]
        .as_array()
        .into_iter()
        .flatten();
    let rebuilt = rebuilt.filter_map(|r| {
        Some((
            r[0].as_u64()?,
            r[1].as_u64()?,
            "measurement".to_string(),
            REBUILT_THERE.to_string(),
        ))
    });
    missing.chain(rebuilt).collect()
}

/// The causes of a remote recording's gaps: before its first sample, the samples were never
/// offered to it (older than the bridge's history); the samples of a gap that the drive
/// lacks too, or rebuilt, keep the drive's cause (a gap is split where the drive's causes
/// change); any other was lost between the drive and this recorder (only known when the
/// drive's summary, `have_drive`, arrived).
fn remote_gaps(
    gaps: Vec<Gap>,
    first_k: Option<u64>,
    drive: &[(u64, u64, String, String)],
    have_drive: bool,
) -> Vec<Gap> {
    let lost = "lost between the drive and the remote recorder (the bridge's bus buffer overflowed or the link dropped it)";
    let mut out = Vec::new();
    for g in gaps {
        if first_k.is_none_or(|f| g.to < f) {
            out.push(Gap {
                cause:
                    "before the remote recorder's first sample (older than the bridge's history)"
                        .into(),
                ..g
            });
            continue;
        }
        if !have_drive {
            out.push(g);
            continue;
        }
        // The drive's ranges of this part that overlap the gap, in order.
        let mut theirs: Vec<_> = drive
            .iter()
            .filter(|(from, to, part, _)| part == g.part && *from <= g.to && g.from <= *to)
            .collect();
        theirs.sort_by_key(|(from, ..)| *from);
        let mut next = g.from;
        let mut piece = |from: u64, to: u64, cause: &str| {
            if from <= to {
                out.push(Gap {
                    from,
                    to,
                    part: g.part,
                    cause: cause.to_string(),
                });
            }
        };
        for (from, to, _, cause) in theirs {
            let (a, b) = ((*from).max(next), (*to).min(g.to));
            if a > b {
                continue;
            }
            piece(next, a - 1, lost);
            piece(a, b, cause);
            next = b + 1;
        }
        if next <= g.to {
            piece(next, g.to, lost);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaps_before_the_first_sample_were_never_offered_and_later_ones_were_lost() {
        let g = |from, to, cause: &str| Gap {
            from,
            to,
            part: "measurement",
            cause: cause.into(),
        };
        let lost = "measurement lost between plant and recorder (recorder buffer overflow)";
        let stopped = "the plant stopped before this sample";
        // The drive itself lacks 900..999 (its plant stopped), not 150..151.
        let drive = [(
            900,
            999,
            "measurement".to_string(),
            "plant kill at sample 900".to_string(),
        )];
        let out = remote_gaps(
            vec![g(0, 99, lost), g(150, 151, lost), g(900, 999, stopped)],
            Some(100),
            &drive,
            true,
        );
        assert!(out[0]
            .cause
            .starts_with("before the remote recorder's first sample"));
        assert!(out[1]
            .cause
            .starts_with("lost between the drive and the remote recorder"));
        assert_eq!(out[2].cause, "plant kill at sample 900");
        // Without the drive's summary, nothing is known beyond the recorder's own view.
        let out = remote_gaps(vec![g(150, 151, lost)], Some(100), &[], false);
        assert_eq!(out[0].cause, lost);
        let none = remote_gaps(vec![g(0, 9, stopped)], None, &[], true);
        assert!(none[0]
            .cause
            .starts_with("before the remote recorder's first sample"));
    }

    #[test]
    fn a_gap_is_split_where_the_drives_causes_change() {
        let lost = "measurement lost between plant and recorder (recorder buffer overflow)";
        let g = |from, to| Gap {
            from,
            to,
            part: "measurement",
            cause: lost.into(),
        };
        // The drive: its plant down and rebuilt at 500..519, then missing 520..529 (a kill
        // it could not rebuild), a command gap that is no measurement's business.
        let summary = json!({
            "missing_samples": [
                { "from": 520, "to": 529, "part": "measurement", "cause": "plant kill at sample 520" },
                { "from": 495, "to": 540, "part": "command", "cause": "the current loop was down" },
            ],
            "plant_down_ranges": [[500, 519]],
        });
        let drive = drive_gaps(&summary);
        assert_eq!(drive.len(), 3);
        // The remote recording lacks 490..534: lost, rebuilt there, the drive's kill, lost.
        let out = remote_gaps(vec![g(490, 534)], Some(0), &drive, true);
        let pieces: Vec<_> = out
            .iter()
            .map(|g| (g.from, g.to, g.cause.as_str()))
            .collect();
        let lost_here = "lost between the drive and the remote recorder (the bridge's bus buffer overflowed or the link dropped it)";
        assert_eq!(
            pieces,
            [
                (490, 499, lost_here),
                (500, 519, REBUILT_THERE),
                (520, 529, "plant kill at sample 520"),
                (530, 534, lost_here),
            ]
        );
        // A gap inside one of the drive's: one piece, its cause.
        let out = remote_gaps(vec![g(505, 510)], Some(0), &drive, true);
        assert_eq!(out.len(), 1);
        assert_eq!((out[0].from, out[0].to), (505, 510));
        assert_eq!(out[0].cause, REBUILT_THERE);
        // A summary without the ranges (an older drive): the gaps as before.
        assert_eq!(drive_gaps(&json!({})), []);
    }
}
