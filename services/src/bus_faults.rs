//! Bus faults on the command line (`delay:STAGE@S:DUR:LAT`, `drop:TOPIC@S:N`,
//! `corrupt:TOPIC@S:N`): parsing, checking against the run's topology, the schedule put into
//! the resolved scenario (`[[inject]]`, read by every stage host, restarted ones included),
//! and their reports in `summary.json → faults`. The hosts apply them by sample index
//! (`drivelab_runtime::inject`); see docs/architecture.md, "Fault model".

use crate::faults::FaultSpec;
use crate::launcher::{DriveEnd, FaultReport};
use anyhow::{anyhow, bail, Result};
use drivelab_runtime::config::Scenario;
use drivelab_runtime::inject::{
    self, Armed, Inject, InjectKind, COUNT_MAX, DELAY_MAX_S, DELAY_MIN_S, LATENCY_MAX_US,
    LATENCY_MIN_US,
};
use drivelab_runtime::messages::{FLAG_MISSING, FLAG_SAFE_STATE, FLAG_STALE_CMD, FLAG_STALE_INPUT};
use drivelab_runtime::service::TopologyPlan;
use drivelab_runtime::trace::TraceRow;
use serde::Serialize;
use std::collections::BTreeMap;

/// The forms, for error messages.
const FORMS: &str =
    "delay:STAGE@SECONDS:DURATION:LATENCY, drop:TOPIC@SECONDS:N or corrupt:TOPIC@SECONDS:N";

/// A latency with its unit: `200us`, `200µs` or `0.3ms`, 1 µs to 100 ms.
fn latency_us(v: &str, spec: &str) -> Result<f64> {
    let bad = || {
        anyhow!(
            "fault '{spec}': latency '{v}' must be a number with a unit: 200us, 200µs or 0.3ms (1 µs to 100 ms)"
        )
    };
    let (num, scale) = if let Some(n) = v.strip_suffix("ms") {
        (n, 1e3)
    } else if let Some(n) = v.strip_suffix("us").or_else(|| v.strip_suffix("µs")) {
        (n, 1.0)
    } else {
        return Err(bad());
    };
    let x: f64 = num.parse().map_err(|_| bad())?;
    let us = x * scale;
    if !(LATENCY_MIN_US..=LATENCY_MAX_US).contains(&us) {
        return Err(bad());
    }
    Ok(us)
}

/// Parses the part after `kind:` of a bus fault (`kind` is delay, drop or corrupt).
pub fn parse(kind: &str, rest: &str, spec: &str) -> Result<FaultSpec> {
    let form = if kind == "delay" {
        "delay:STAGE@SECONDS:DURATION:LATENCY".to_string()
    } else {
        format!("{kind}:TOPIC@SECONDS:N")
    };
    let (target, when) = rest
        .split_once('@')
        .ok_or_else(|| anyhow!("fault '{spec}': expected {form}"))?;
    let parts: Vec<&str> = when.split(':').collect();
    let inject = match (kind, parts.as_slice()) {
        ("delay", [at, dur, lat]) => {
            let duration_s = crate::faults::seconds(dur, "duration", spec)?;
            if !(DELAY_MIN_S..=DELAY_MAX_S).contains(&duration_s) {
                bail!("fault '{spec}': a delay lasts {DELAY_MIN_S} to {DELAY_MAX_S} s");
            }
            Inject {
                kind: InjectKind::Delay,
                target: crate::faults::service(target, spec)?,
                at_s: crate::faults::seconds(at, "time", spec)?,
                duration_s,
                latency_us: latency_us(lat, spec)?,
                count: 0,
            }
        }
        ("drop" | "corrupt", [at, n]) => {
            let count: u64 = n
                .parse()
                .ok()
                .filter(|c| (1..=COUNT_MAX).contains(c))
                .ok_or_else(|| {
                    anyhow!("fault '{spec}': N must be a whole number in 1..={COUNT_MAX}")
                })?;
            inject::topic(target).map_err(|e| anyhow!("fault '{spec}': {e}"))?;
            Inject {
                kind: if kind == "drop" {
                    InjectKind::Drop
                } else {
                    InjectKind::Corrupt
                },
                target: target.to_string(),
                at_s: crate::faults::seconds(at, "time", spec)?,
                duration_s: 0.0,
                latency_us: 0.0,
                count,
            }
        }
        ("delay" | "drop" | "corrupt", _) => bail!("fault '{spec}': expected {form}"),
        _ => bail!("fault '{spec}': not a bus fault (expected {FORMS})"),
    };
    Ok(FaultSpec::Bus(inject))
}

/// Checks the bus faults of `specs` against the run's topology (a delayed stage must be
/// hosted, a topic produced) and duration, and appends them to `sc.inject`.
pub fn schedule(specs: &[FaultSpec], sc: &mut Scenario, topo: &TopologyPlan) -> Result<()> {
    for s in specs {
        let FaultSpec::Bus(i) = s else { continue };
        check_target(i, topo, "fault")?;
        sc.inject.push(i.clone());
    }
    inject::validate(&sc.inject, sc.duration_s)
        .map_err(|e| anyhow!("--fault with the scenario's own [[inject]] tables: {e}"))
}

/// Checks a scenario's own `[[inject]]` tables as `--fault` is checked: a stage of this
/// drive, a topic one of its stages publishes, and a kill or stop after sample 0.
pub fn check_tables(sc: &Scenario, topo: &TopologyPlan) -> Result<()> {
    for i in &sc.inject {
        check_target(i, topo, "[[inject]]")?;
        if i.kind.downs_stage() {
            crate::faults::after_sample_0(
                &format!("[[inject]] {}", i.spec()),
                i.at_s,
                sc.rates.sample_hz,
            )?;
        }
    }
    Ok(())
}

/// The stage or topic that bus fault `i` names must be this drive's (`what`: how the
/// error names where it came from).
fn check_target(i: &Inject, topo: &TopologyPlan, what: &str) -> Result<()> {
    let spec = i.spec();
    match i.kind {
        InjectKind::Delay | InjectKind::Kill | InjectKind::Stop => {
            if !topo.stages.iter().any(|x| x.name == i.target) {
                let names: Vec<&str> = topo.stages.iter().map(|x| x.name.as_str()).collect();
                bail!(
                    "{what} {spec}: unknown stage '{}' (this drive's stages: {})",
                    i.target,
                    names.join(", ")
                );
            }
        }
        InjectKind::Drop | InjectKind::Corrupt => {
            let produced: Vec<&str> = inject::TOPICS
                .iter()
                .filter(|t| topo.producers.iter().any(|p| p.topic == **t))
                .map(|t| t.name())
                .collect();
            if !produced.contains(&i.target.as_str()) {
                bail!(
                    "{what} {spec}: no stage of this drive publishes topic '{}' (its topics: {})",
                    i.target,
                    produced.join(", ")
                );
            }
        }
    }
    Ok(())
}

/// The window of injection `i` of the run (its producer's samples for a topic's fault).
fn armed(i: &Inject, sc: &Scenario, topo: &TopologyPlan) -> Armed {
    let divider = |t| {
        topo.producers
            .iter()
            .find(|p| p.topic == t)
            .map_or(1, |p| p.divider)
    };
    Armed::bind(i, sc.rates.sample_hz, &[], divider)
}

/// True when `a` is due at or after the drive's `end`, which never reached it: a bus fault,
/// or a simulated kill or stop of a drive a stop signal interrupted (a drive that ended at a
/// plant's kill had its late kills and stops taken out of the scenario, and ended at that
/// kill's own sample).
fn after_the_end(a: &Armed, end: DriveEnd) -> bool {
    (!a.kind.downs_stage() || end.interrupted) && end.before(a.from_k)
}

/// The injections of `sc` (bus faults; simulated kills and stops when interrupted) that were
/// not made because the drive ended at `end` before their first sample (a killed plant with
/// `--restart never`, a stop signal), each as (the drive's end, why)
/// ([`DriveEnd::not_reached`]).
pub fn not_made(sc: &Scenario, topo: &TopologyPlan, end: DriveEnd) -> Vec<(u64, String)> {
    sc.inject
        .iter()
        .map(|i| (i, armed(i, sc, topo)))
        .filter(|(_, a)| after_the_end(a, end))
        .filter_map(|(i, a)| end.not_reached(&i.spec(), a.from_k))
        .collect()
}

/// What a bus fault caused, beside the common figures of a [`FaultReport`].
#[derive(Debug, Clone, Default, Serialize, PartialEq)]
pub struct BusFigures {
    /// The samples the fault covers: [window_from_k, window_to_k).
    pub window_from_k: u64,
    /// The first sample after them.
    pub window_to_k: u64,
    /// corrupt: messages of the window rejected, every receiving stage together (None: no
    /// per-stage counters, the in-process clock).
    pub rejected_inputs: Option<u64>,
    /// corrupt: the same per receiving stage.
    pub rejected_by: BTreeMap<String, u64>,
    /// delay, real time: commands of the window's samples not there at their deadline, as
    /// the plant counted them (None elsewhere).
    pub deadline_misses: Option<u64>,
    /// delay, real time: the longest cycle latency of the window's samples (t_k to command k
    /// published), µs.
    pub cycle_latency_max_us: Option<f64>,
}

/// The reports of the scenario's bus faults from the trace `rows` and the per-stage
/// `counters` (`summary.json → counters`; None in process), and the windows to shade on the
/// plots (from, to in s, label). The drive ended at `end`: an injection due after it was not
/// made ([`not_made`]) and gets none.
pub fn reports(
    sc: &Scenario,
    topo: &TopologyPlan,
    rows: &[TraceRow],
    counters: Option<&serde_json::Value>,
    end: DriveEnd,
) -> (Vec<FaultReport>, Vec<(f64, f64, String)>) {
    let fs = sc.rates.sample_hz;
    let ms = |dk: u64| dk as f64 * 1e3 / fs;
    let producer =
        |t: drivelab_runtime::stage::TopicId| topo.producers.iter().find(|p| p.topic == t);
    let slowest = topo.producers.iter().map(|p| p.divider).max().unwrap_or(1);
    let mut out = Vec::new();
    let mut windows = Vec::new();
    // `n` is the injection's index in every host's schedule (its counters), kept as is.
    for (n, i) in sc.inject.iter().enumerate() {
        let a = armed(i, sc, topo);
        if after_the_end(&a, end) {
            continue;
        }
        // The window within the run (a stage never restarted is down to the end).
        let to_k = a.to_k.min(sc.samples());
        // A topic's fault is its producer's; a stage's names the stage.
        let stage = match a.topic {
            Some(t) => producer(t).map_or_else(String::new, |p| p.stage.clone()),
            None => i.target.clone(),
        };
        let process = topo
            .process_of(&stage)
            .map_or_else(String::new, |p| topo.processes[p].name.clone());
        let from = rows.partition_point(|r| r.k < a.from_k);
        let after = &rows[from..];
        let disturbed = |r: &TraceRow| {
            r.plant_flags & (FLAG_STALE_CMD | FLAG_SAFE_STATE) != 0
                || r.ctrl_flags & (FLAG_STALE_INPUT | FLAG_MISSING) != 0
        };
        // A fault shows within its window, or within a slow producer's period or two after
        // it (a lost message of a stage that steps every N-th sample); a disturbance after
        // that belongs to something else.
        let shows_by = to_k + 2 * slowest + 2;
        let det = after
            .iter()
            .take_while(|r| r.k < shows_by)
            .find(|r| disturbed(r))
            .map(|r| {
                let by = if r.plant_flags & (FLAG_STALE_CMD | FLAG_SAFE_STATE) != 0 {
                    "plant"
                } else if r.ctrl_flags & FLAG_MISSING != 0 {
                    "recorder (no usable command)"
                } else {
                    "current-loop"
                };
                (r.k, by.to_string())
            });
        let obs = |field: &str| -> Vec<(String, u64)> {
            counters
                .and_then(|c| c.as_object())
                .map(|m| {
                    m.iter()
                        .filter_map(|(st, v)| {
                            Some((st.clone(), v["inject"].get(n)?[field].as_u64()?))
                        })
                        .collect()
                })
                .unwrap_or_default()
        };
        let plant = |field: &str| {
            obs(field)
                .into_iter()
                .find(|(st, _)| st == "plant")
                .map(|x| x.1)
        };
        // Only a real-time plant waits for commands at deadlines; it counts a late one as a
        // miss even when the command is there by the time it wakes (no trace row shows it).
        let realtime_delay = i.kind == InjectKind::Delay && plant("cycles").is_some_and(|c| c > 0);
        let late = realtime_delay && plant("misses").is_some_and(|m| m > 0);
        // Fresh again: the first undisturbed sample after the window and the detection; a
        // fault nothing saw (a delay in lockstep, a lost message a stage did not need) never
        // interrupted the outputs: fresh from its first sample (0 ms).
        let fresh = match &det {
            None if !late => after.first().map(|r| r.k),
            _ => {
                let k_det = det.as_ref().map_or(a.from_k, |d| d.0);
                after
                    .iter()
                    .find(|r| r.k >= to_k && r.k > k_det && !disturbed(r))
                    .map(|r| r.k)
            }
        };
        let tail: Vec<&TraceRow> = after
            .iter()
            .filter(|r| fresh.is_some_and(|f| r.k >= f))
            .collect();
        let rec = crate::launcher::speed_recovered(sc, &tail);
        let k_end = rec.or(fresh).unwrap_or(to_k + (0.2 * fs) as u64);
        windows.push((a.from_k as f64 / fs, k_end as f64 / fs, i.spec()));
        let span: Vec<&TraceRow> = after.iter().take_while(|r| r.k <= k_end).collect();
        let rejected: Vec<(String, u64)> = obs("rejected");
        out.push(FaultReport {
            fault: i.spec(),
            service: stage,
            process,
            injected_k: a.from_k,
            injected_t_s: a.from_k as f64 / fs,
            detected_data_path_ms: det.as_ref().map(|d| ms(d.0 - a.from_k)),
            detected_by: det.map(|d| d.1),
            detected_supervisor_ms: None,
            safe_state_ms: span
                .iter()
                .find(|r| r.plant_flags & FLAG_SAFE_STATE != 0)
                .map(|r| ms(r.k - a.from_k)),
            peak_current_a: span.iter().map(|r| r.i_d.hypot(r.i_q)).fold(0.0, f64::max),
            republished_ms: fresh.map(|f| ms(f - a.from_k)),
            speed_recovered_ms: rec.map(|r| ms(r - a.from_k)),
            plant_down: crate::launcher::PlantDown::of(span.iter().copied()),
            window: None,
            why_null: crate::launcher::recovery_notes(sc, &tail, rec),
            samples: crate::launcher::SampleCounts::of(span.iter().copied()),
            bus: Some(BusFigures {
                window_from_k: a.from_k,
                window_to_k: to_k,
                rejected_inputs: (i.kind == InjectKind::Corrupt && counters.is_some())
                    .then(|| rejected.iter().map(|x| x.1).sum()),
                rejected_by: rejected.into_iter().filter(|x| x.1 > 0).collect(),
                deadline_misses: if realtime_delay {
                    plant("misses")
                } else {
                    None
                },
                cycle_latency_max_us: if realtime_delay {
                    plant("cycle_max_ns").map(|ns| ns as f64 * 1e-3)
                } else {
                    None
                },
            }),
        });
    }
    (out, windows)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn one(spec: &str) -> Inject {
        match crate::faults::parse(spec).unwrap() {
            FaultSpec::Bus(i) => i,
            other => panic!("{other:?}"),
        }
    }

    fn err(spec: &str) -> String {
        let e = crate::faults::parse(spec).unwrap_err().to_string();
        assert!(!e.contains('\n'), "{e}");
        e
    }

    #[test]
    fn parses_every_kind_and_unit() {
        let d = one("delay:current-loop@0.5:0.2:200us");
        assert_eq!(
            (
                d.kind,
                d.target.as_str(),
                d.at_s,
                d.duration_s,
                d.latency_us
            ),
            (InjectKind::Delay, "current-loop", 0.5, 0.2, 200.0)
        );
        assert_eq!(one("delay:plant@1s:1s:0.3ms").latency_us, 300.0);
        assert_eq!(one("delay:plant@1:1:7µs").latency_us, 7.0);
        assert_eq!(one("delay:plant@1:0.001:1us").duration_s, 0.001);
        assert_eq!(one("delay:plant@1:60:100ms").latency_us, 100_000.0);
        let d = one("drop:cmd@0.25:3");
        assert_eq!(
            (d.kind, d.target.as_str(), d.at_s, d.count),
            (InjectKind::Drop, "cmd", 0.25, 3)
        );
        let c = one("corrupt:est@0:100000");
        assert_eq!((c.kind, c.count), (InjectKind::Corrupt, 100_000));
        // The spec round-trips.
        assert_eq!(one(&d.spec()), d);
    }

    #[test]
    fn every_bound_and_malformed_input_is_a_one_line_error() {
        for lat in [
            "0.5us", "100001us", "100.1ms", "200", "2s", "xus", "-5us", "NaNus",
        ] {
            let e = err(&format!("delay:plant@1:0.1:{lat}"));
            assert!(
                e.contains("must be a number with a unit: 200us, 200µs or 0.3ms (1 µs to 100 ms)"),
                "{lat}: {e}"
            );
        }
        for dur in ["0.0005", "61", "1e20"] {
            let e = err(&format!("delay:plant@1:{dur}:10us"));
            assert!(e.contains("a delay lasts 0.001 to 60 s"), "{dur}: {e}");
        }
        for n in ["0", "100001", "-1", "1.5", "x", ""] {
            let e = err(&format!("drop:cmd@1:{n}"));
            assert!(
                e.contains("N must be a whole number in 1..=100000"),
                "{n}: {e}"
            );
        }
        let e = err("corrupt:bogus@1:1");
        assert!(
            e.contains("unknown topic 'bogus' (topics a stage reads: meas, est, iref, cmd, wref)"),
            "{e}"
        );
        assert!(err("drop:truth@1:1").contains("unknown topic 'truth'"));
        assert!(err("drop:cmd@1").contains("expected drop:TOPIC@SECONDS:N"));
        assert!(err("corrupt:cmd").contains("expected corrupt:TOPIC@SECONDS:N"));
        assert!(err("delay:plant@1:0.1").contains("expected delay:STAGE@SECONDS:DURATION:LATENCY"));
        assert!(err("delay:plant@1:0.1:5us:9").contains("expected delay:"));
        assert!(err("delay:Pump@1:0.1:5us").contains("unknown stage 'Pump'"));
        assert!(err("drop:cmd@x:1").contains("not a number"));
        assert!(err("drop:cmd@-1:1").contains("finite number of seconds >= 0"));
        assert!(err("explode:cmd@1:1").contains("delay, drop, corrupt"));
    }

    /// kyslan-pi (1 s, 10 kHz) and its default topology.
    fn kyslan() -> (Scenario, TopologyPlan) {
        let mut sc = crate::launcher::load_scenario("kyslan-pi", Some(1.0)).unwrap();
        let o = crate::launcher::RunOptions {
            scenario: "kyslan-pi".into(),
            clock: crate::launcher::Clock::Lockstep,
            no_rt: true,
            no_plots: true,
            lockstep_restart_ms: drivelab_runtime::inject::RESTART_DEFAULT_MS,
            ..Default::default()
        };
        let topo = crate::launcher::resolve_topology(
            &mut sc,
            std::path::Path::new("./kyslan-pi.toml"),
            &o,
        )
        .unwrap();
        (sc, topo)
    }

    #[test]
    fn reports_count_the_window_from_the_trace_and_the_stages_counters() {
        let (mut sc, topo) = kyslan();
        let specs = [
            crate::faults::parse("corrupt:cmd@0.001:3").unwrap(),
            crate::faults::parse("delay:current-loop@0.001:0.001:150us").unwrap(),
        ];
        schedule(&specs, &mut sc, &topo).unwrap();
        // Commands 10..=12 unusable: no command in those rows, the plant holds 11..=13
        // (within hold_samples = 3: no safe state), fresh again at 14.
        let rows: Vec<TraceRow> = (0..100)
            .map(|k| TraceRow {
                k,
                t: k as f64 * 1e-4,
                omega_m: 70.0,
                i_q: if k == 12 { 3.0 } else { 1.0 },
                ctrl_flags: if (10..13).contains(&k) {
                    FLAG_MISSING
                } else {
                    0
                },
                plant_flags: if (11..14).contains(&k) {
                    FLAG_STALE_CMD
                } else {
                    0
                },
                ..Default::default()
            })
            .collect();
        let obs = |rejected: u64, cycles: u64, misses: u64| {
            serde_json::json!([
                { "rejected": rejected, "cycles": 0, "misses": 0, "cycle_max_ns": 0 },
                { "rejected": 0, "cycles": cycles, "misses": misses, "cycle_max_ns": 250_000 },
            ])
        };
        let counters = serde_json::json!({
            "plant": { "inject": obs(3, 10, 7) },
            "observer": { "inject": obs(0, 0, 0) },
        });
        let (r, windows) = reports(&sc, &topo, &rows, Some(&counters), DriveEnd::NEVER);
        assert_eq!(windows.len(), 2);
        let (c, d) = (&r[0], &r[1]);
        let b = c.bus.as_ref().unwrap();
        assert_eq!((c.service.as_str(), c.injected_k), ("current-loop", 10));
        assert_eq!((b.window_from_k, b.window_to_k), (10, 13));
        assert_eq!(b.rejected_inputs, Some(3));
        assert_eq!(b.rejected_by, BTreeMap::from([("plant".to_string(), 3)]));
        assert_eq!(
            (
                c.samples.stale_command_samples,
                c.samples.missing_command_samples
            ),
            (3, 3)
        );
        assert_eq!(
            c.detected_by.as_deref(),
            Some("recorder (no usable command)")
        );
        assert_eq!(c.republished_ms, Some(0.4));
        assert_eq!(c.peak_current_a, 3.0);
        assert_eq!((b.deadline_misses, b.cycle_latency_max_us), (None, None));
        let b = d.bus.as_ref().unwrap();
        assert_eq!((b.window_from_k, b.window_to_k), (10, 20));
        assert_eq!(
            (b.deadline_misses, b.cycle_latency_max_us),
            (Some(7), Some(250.0))
        );
        assert_eq!(b.rejected_inputs, None);
        // A fault nothing saw never interrupted the outputs (0 ms), and a disturbance well
        // after its window (here 100 samples later) is not its detection.
        let quiet: Vec<TraceRow> = (0..200)
            .map(|k| TraceRow {
                k,
                t: k as f64 * 1e-4,
                omega_m: 70.0,
                plant_flags: if (120..123).contains(&k) {
                    FLAG_STALE_CMD
                } else {
                    0
                },
                ..Default::default()
            })
            .collect();
        let (r, _) = reports(&sc, &topo, &quiet, None, DriveEnd::NEVER);
        assert!(!r.is_empty(), "no report of the faults");
        for f in &r {
            assert_eq!(f.detected_data_path_ms, None, "{f:?}");
            assert_eq!(f.republished_ms, Some(0.0), "{f:?}");
            assert_eq!(f.samples.stale_command_samples, 0, "{f:?}");
        }
        // In process: no counters, no counts from them.
        let (r, _) = reports(&sc, &topo, &rows, None, DriveEnd::NEVER);
        let b = r[0].bus.as_ref().unwrap();
        assert_eq!(
            (b.rejected_inputs, r[0].samples.stale_command_samples),
            (None, 3)
        );
    }

    #[test]
    fn the_schedule_is_checked_against_the_topology_and_the_run() {
        let (sc, topo) = kyslan();
        let specs = [
            crate::faults::parse("drop:cmd@0.5:3").unwrap(),
            crate::faults::parse("kill:plant@0.5").unwrap(),
        ];
        let mut a = sc.clone();
        schedule(&specs, &mut a, &topo).unwrap();
        assert_eq!(a.inject.len(), 1);
        let refused = |spec: &str| {
            let specs = [crate::faults::parse(spec).unwrap()];
            let e = schedule(&specs, &mut sc.clone(), &topo).unwrap_err();
            e.to_string()
        };
        for (spec, want) in [
            (
                "drop:wref@0.5:3",
                "no stage of this drive publishes topic 'wref' (its topics: meas, est, iref, cmd)",
            ),
            (
                "delay:pump@0.5:0.1:5us",
                "unknown stage 'pump' (this drive's stages: plant",
            ),
            ("drop:cmd@1.5:3", "at_s must be within [0, duration_s = 1)"),
        ] {
            let e = refused(spec);
            assert!(e.contains(want), "{spec}: {e}");
        }
    }
}
