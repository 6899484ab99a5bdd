//! Standby twins (`standby = true` in the topology): a killed process's twin takes over
//! without the drive noticing, a new twin is started and takes over at the next kill; a
//! frozen process keeps its lease, so its twin stays silent and the plant goes to its safe
//! state as without a twin; a twin that shadows publishes nothing. Timeouts are watchdogs
//! only.

mod common;
use common::*;
use drivelab_runtime::messages::{FLAG_SAFE_STATE, FLAG_STALE_CMD, FLAG_STALE_INPUT};
use serde_json::Value;

const TOPOLOGY: &str = "four-process-standby";

fn events(s: &Value, process: &str) -> Vec<String> {
    timeline(s, process).into_iter().map(|(e, _)| e).collect()
}

/// `process`'s supervisor events with their wall times, s: what a failure message shows.
fn timeline(s: &Value, process: &str) -> Vec<(String, f64)> {
    s["supervisor_events"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["process"] == process)
        .map(|e| {
            let t = e["t_wall_s"].as_f64().unwrap();
            (e["event"].as_str().unwrap().to_string(), t)
        })
        .collect()
}

/// Samples of `rows` in [k0, k0 + n) that a consumer saw stale: a held command at the plant
/// or a command made from a stale input.
fn disturbed(rows: &[drivelab_runtime::trace::TraceRow], k0: u64, n: u64) -> Vec<u64> {
    rows.iter()
        .filter(|r| r.k >= k0 && r.k < k0 + n)
        .filter(|r| r.plant_flags & FLAG_STALE_CMD != 0 || r.ctrl_flags & FLAG_STALE_INPUT != 0)
        .map(|r| r.k)
        .collect()
}

fn rows(out: &std::path::Path) -> Vec<drivelab_runtime::trace::TraceRow> {
    drivelab_runtime::trace::read_csv(&out.join("trace.csv")).unwrap()
}

#[test]
fn a_killed_process_is_replaced_by_its_twin_without_a_restart_and_again_by_the_next_twin() {
    let _serial = serial();
    let (out, s) = run_ok(
        "kills",
        &[
            "--scenario",
            "kyslan-pi",
            "--duration",
            "1.6",
            "--topology",
            TOPOLOGY,
            "--fault",
            "kill:current-loop@0.3",
            "--fault",
            "kill:speed-loop@0.45",
            "--fault",
            "kill:observer@0.6",
            // The current loop's first twin, now the process, is killed in turn: the twin
            // started after the first takeover takes over from it. That twin must be ready
            // by then (checked below); a second is ample: it was ready 50–80 ms after the
            // takeover on the development VM, 90–140 ms with both cores saturated.
            "--fault",
            "kill:current-loop@1.4",
        ],
    );
    assert_eq!(s["samples_missing"], 0, "{}", s["missing_samples"]);
    let rows = rows(&out);
    let faults = s["faults"].as_array().unwrap();
    assert_eq!(faults.len(), 4, "{faults:?}");
    // The precondition of the second kill: the new twin was ready before it. A drive whose
    // twin is still starting restarts the process instead, as it would without a twin.
    let cl = timeline(&s, "current-loop");
    let second_kill = cl
        .iter()
        .filter(|(e, _)| e == "inject")
        .nth(1)
        .map(|(_, t)| *t);
    let ready = cl
        .iter()
        .find(|(e, _)| e == "standby-ready")
        .map(|(_, t)| *t);
    assert!(
        matches!((ready, second_kill), (Some(r), Some(k)) if r < k),
        "the current loop's new twin was not ready before the second kill: {cl:?}"
    );
    for f in faults {
        let (svc, k0) = (
            f["service"].as_str().unwrap(),
            f["injected_k"].as_u64().unwrap(),
        );
        // How many samples the takeover cost (1–3 on the development VMs) is how soon the
        // kernel ends the process: a real-time figure, printed, not asserted. What is
        // asserted: no sample went into the safe state (the plant holds a stale command for
        // 3 samples before it goes safe), the speed recovered, a twin took over and nothing
        // was restarted (below).
        let d = disturbed(&rows, k0, 1000);
        eprintln!(
            "{svc} killed at {k0}: {} stale samples {:?}..{:?}",
            d.len(),
            d.first(),
            d.last()
        );
        assert!(f["safe_state_ms"].is_null(), "{svc}: {f}");
        assert!(
            rows.iter()
                .filter(|r| r.k >= k0 && r.k < k0 + 1000)
                .all(|r| r.plant_flags & FLAG_SAFE_STATE == 0),
            "{svc}: safe state after the kill at {k0}"
        );
        assert!(f["speed_recovered_ms"].as_f64().is_some(), "{svc}: {f}");
    }
    let take_overs = |p: &str| events(&s, p).iter().filter(|e| *e == "taken-over").count();
    assert_eq!(
        take_overs("current-loop"),
        2,
        "{:?}",
        events(&s, "current-loop")
    );
    assert_eq!(
        take_overs("speed-loop"),
        1,
        "{:?}",
        events(&s, "speed-loop")
    );
    assert_eq!(take_overs("observer"), 1, "{:?}", events(&s, "observer"));
    for p in ["current-loop", "speed-loop", "observer"] {
        let ev = events(&s, p);
        // A twin replaces the process: nothing is restarted, and each takeover is followed
        // by a new twin that becomes ready.
        assert!(!ev.iter().any(|e| e == "restarted"), "{p}: {ev:?}");
        let after = ev
            .iter()
            .skip_while(|e| *e != "taken-over")
            .map(String::as_str)
            .collect::<Vec<_>>();
        assert!(
            after
                .windows(2)
                .any(|w| w == ["standby-started", "standby-ready"]),
            "{p}: {ev:?}"
        );
    }
    // The process that runs at the end is the last twin: its pid is the last takeover's.
    let last_twin = s["supervisor_events"]
        .as_array()
        .unwrap()
        .iter()
        .rfind(|e| e["process"] == "current-loop" && e["event"] == "taken-over")
        .map(|e| e["detail"].as_str().unwrap().to_string())
        .unwrap();
    let pid = s["processes"]["current-loop"]["pid"].as_u64().unwrap();
    assert!(
        last_twin.contains(&format!("(pid {pid})")),
        "{last_twin} vs {pid}"
    );
}

#[test]
fn a_frozen_process_keeps_its_lease_so_its_twin_stays_silent_and_the_plant_goes_safe() {
    let _serial = serial();
    // 20 ms frozen, far beyond the 3-sample hold: only the twin could keep commands coming,
    // and it must not (the process is alive).
    let (out, s) = run_ok(
        "freeze",
        &[
            "--scenario",
            "kyslan-pi",
            "--duration",
            "0.6",
            "--topology",
            TOPOLOGY,
            "--fault",
            "stop:current-loop@0.2:0.02",
        ],
    );
    let f = &s["faults"][0];
    assert!(f["safe_state_ms"].as_f64().is_some(), "{f}");
    let ev = events(&s, "current-loop");
    assert!(!ev.iter().any(|e| e == "taken-over"), "{ev:?}");
    let k0 = f["injected_k"].as_u64().unwrap();
    let held = disturbed(&rows(&out), k0, 300);
    // The freeze spans 200 deadlines at 10 kHz (SIGCONT comes 20 ms after SIGSTOP at the
    // earliest). The first of them may still have its command (the loop stopped after
    // publishing it), and the thawed loop's first command lands one sample late at most:
    // at least 197 samples without a fresh command, one after another. A command in the
    // middle would be the twin's, speaking while the process holds its lease.
    let longest = held
        .windows(2)
        .fold((1u64, 1u64), |(run, best), w| {
            let run = if w[1] == w[0] + 1 { run + 1 } else { 1 };
            (run, best.max(run))
        })
        .1;
    assert!(
        !held.is_empty() && longest >= 197,
        "longest run of stale samples {longest} of {}: {held:?}",
        held.len()
    );
}

#[test]
fn twins_that_shadow_publish_nothing() {
    let _serial = serial();
    let (_, s) = run_ok(
        "quiet",
        &[
            "--scenario",
            "kyslan-pi",
            "--duration",
            "0.3",
            "--topology",
            TOPOLOGY,
        ],
    );
    // A twin's command, estimate or reference would reach its consumers a second time with
    // an index they have had: counted late or rejected.
    let counters = s["counters"].as_object().unwrap();
    assert_eq!(counters.len(), 4, "{counters:?}");
    for (stage, c) in counters {
        assert_eq!(c["late_inputs"], 0, "{stage}: {c}");
        assert_eq!(c["rejected_inputs"], 0, "{stage}: {c}");
        assert_eq!(c["late_commands"], 0, "{stage}: {c}");
    }
    // The twins were there, one priority below their processes, and ended with the drive.
    for (p, prio) in [("current-loop", 76), ("speed-loop", 74), ("observer", 72)] {
        assert_eq!(events(&s, p), Vec::<String>::new(), "{p}");
        let proc = &s["processes"][p];
        assert_eq!(proc["priority"], prio, "{p}: {proc}");
        assert_eq!(proc["standby"]["priority"], prio - 1, "{p}: {proc}");
        assert_ne!(proc["standby"]["pid"], proc["pid"], "{p}: {proc}");
    }
    assert!(s["processes"]["plant"]["standby"].is_null());
}
