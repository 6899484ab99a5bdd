//! Bus faults (delay, drop, corrupt) with real processes: the stage hosts apply them by
//! sample index from the resolved scenario. Each test has its own bus id and run folder and
//! checks that nothing is left behind. Times are watchdogs only.

use drivelab_runtime::messages::{FLAG_MISSING, FLAG_SAFE_STATE, FLAG_STALE_CMD};

mod common;
use common::*;

/// Runs `fault` for `duration` s twice in lockstep and once in process and checks that the
/// three traces are the same bytes (see [`same_trace_in_every_run`]).
fn deterministic(
    tag: &str,
    fault: &str,
    duration: &str,
) -> (std::path::PathBuf, serde_json::Value) {
    same_trace_in_every_run(tag, &["--duration", duration, "--fault", fault])
}

#[test]
fn corrupt_commands_in_lockstep_are_rejected_held_and_never_applied() {
    let _serial = serial();
    // kyslan-pi at 10 kHz: messages 2000..=2004 of cmd carry NaN, 1e30, NaN, 1e30, NaN.
    let (out, s) = run_ok(
        "corruptcmd",
        &[
            "--clock",
            "lockstep",
            "--duration",
            "0.5",
            "--fault",
            "corrupt:cmd@0.2:5",
            "--expect",
            "faults.*.rejected_inputs == 5",
        ],
    );
    let f = &s["faults"][0];
    assert_eq!(f["fault"], "corrupt:cmd@0.2:5", "{f}");
    assert_eq!(f["service"], "current-loop", "{f}");
    assert_eq!(
        (f["window_from_k"].as_u64(), f["window_to_k"].as_u64()),
        (Some(2000), Some(2005)),
        "{f}"
    );
    // The one receiving stage rejected exactly the five, and nothing else in the run.
    assert_eq!(f["rejected_inputs"], 5, "{f}");
    assert_eq!(f["rejected_by"], serde_json::json!({ "plant": 5 }), "{f}");
    assert_eq!(s["counters"]["plant"]["rejected_inputs"], 5);
    let rows = drivelab_runtime::trace::read_csv(&out.join("trace.csv")).unwrap();
    assert_eq!(rows.len(), 5000);
    // No corrupt command reached the trace or the inverter: the five samples have no
    // command, the plant held the last good one for hold_samples (3) and then went to its
    // safe state until the next good command (2005) took effect at 2006.
    assert_eq!(
        samples(&rows, |r| r.ctrl_flags & FLAG_MISSING != 0),
        ks(2000..2005)
    );
    assert_eq!(
        samples(&rows, |r| r.plant_flags & FLAG_STALE_CMD != 0),
        ks(2001..2006)
    );
    assert_eq!(samples(&rows, |r| r.miss == 1), ks(2001..2006));
    assert_eq!(
        samples(&rows, |r| r.plant_flags & FLAG_SAFE_STATE != 0),
        ks(2004..2006)
    );
    assert_eq!(f["stale_command_samples"], 5, "{f}");
    assert_eq!(f["safe_state_samples"], 2, "{f}");
    assert!(f["safe_state_ms"].as_f64().is_some(), "{f}");
    let (sc, _) = drivelab_runtime::config::Scenario::load("kyslan-pi").unwrap();
    for r in &rows {
        assert!(r.u_d.is_finite() && r.u_q.is_finite(), "k = {}", r.k);
        assert!(
            r.u_d.hypot(r.u_q) <= sc.u_max() * (1.0 + 1e-9),
            "k = {}",
            r.k
        );
    }
    assert!(f["peak_current_a"].as_f64().unwrap() > 0.0, "{f}");
}

#[test]
fn dropped_commands_in_lockstep_are_deterministic_and_held_exactly_there() {
    let _serial = serial();
    let (a, sa) = deterministic("dropcmd", "drop:cmd@0.1:4", "0.4");
    let rows = drivelab_runtime::trace::read_csv(&a.join("trace.csv")).unwrap();
    // Commands 1000..=1003 were never published: those rows have none, and the plant held
    // (then applied its safe state) at exactly the four samples that needed them.
    assert_eq!(
        samples(&rows, |r| r.ctrl_flags & FLAG_MISSING != 0),
        ks(1000..1004)
    );
    assert_eq!(samples(&rows, |r| r.miss == 1), ks(1001..1005));
    assert_eq!(
        samples(&rows, |r| r.plant_flags & FLAG_STALE_CMD != 0),
        ks(1001..1005)
    );
    let f = &sa["faults"][0];
    assert_eq!(f["fault"], "drop:cmd@0.1:4", "{f}");
    assert_eq!(f["stale_command_samples"], 4, "{f}");
    assert_eq!(f["missing_command_samples"], 4, "{f}");
    assert_eq!(f["detected_by"], "recorder (no usable command)", "{f}");
    assert_eq!(f["rejected_inputs"], serde_json::Value::Null, "{f}");
    assert_eq!(sa["counters"]["plant"]["rejected_inputs"], 0);
    // The missing commands are listed, with the fault as their cause.
    let gaps = sa["missing_samples"].as_array().unwrap();
    assert!(
        gaps.iter().any(|g| g["part"] == "command"
            && g["from"] == 1000
            && g["cause"].as_str().unwrap().contains("drop:cmd@0.1:4")),
        "{gaps:?}"
    );
}

#[test]
fn a_dropped_measurement_in_lockstep_is_absent_along_the_chain() {
    let _serial = serial();
    // Measurement 1500 never leaves the plant: the observer has nothing to estimate, the
    // current loop no measurement, so command 1500 is absent and the plant holds at 1501.
    let (a, _) = deterministic("dropmeas", "drop:meas@0.15:1", "0.3");
    let rows = drivelab_runtime::trace::read_csv(&a.join("trace.csv")).unwrap();
    assert_eq!(rows.len(), 3000);
    assert_eq!(
        samples(&rows, |r| r.ctrl_flags & FLAG_MISSING != 0),
        ks(1500..1501)
    );
    assert_eq!(samples(&rows, |r| r.miss == 1), ks(1501..1502));
}

#[test]
fn a_delayed_current_loop_in_real_time_misses_deadlines_and_recovers() {
    let _serial = serial();
    // 150 µs added to every command of 0.1 s, at a sample time of 100 µs.
    let (out, s) = run_ok(
        "delaycl",
        &[
            "--duration",
            "1.5",
            "--fault",
            "delay:current-loop@0.4:0.1:150us",
        ],
    );
    let f = &s["faults"][0];
    eprintln!("{f}");
    assert_eq!(f["fault"], "delay:current-loop@0.4:0.1:150us", "{f}");
    assert_eq!(
        (f["window_from_k"].as_u64(), f["window_to_k"].as_u64()),
        (Some(4000), Some(5000)),
        "{f}"
    );
    let misses = f["deadline_misses"]
        .as_u64()
        .expect("deadline misses counted");
    assert!(misses > 0, "{f}");
    assert!(f["cycle_latency_max_us"].as_f64().unwrap() > 100.0, "{f}");
    // (Whether the plant also had to hold commands depends on the scheduler: with every
    // stage on one core at rising SCHED_FIFO priorities the spinning current loop starves
    // the plant, which then wakes late and finds each late command there.)
    // The drive came back after the window.
    assert!(f["republished_ms"].as_f64().unwrap() >= 100.0, "{f}");
    assert!(f["speed_recovered_ms"].as_f64().is_some(), "{f}");
    let rows = drivelab_runtime::trace::read_csv(&out.join("trace.csv")).unwrap();
    let last = rows.last().unwrap();
    assert!((last.omega_m - 70.0).abs() <= 0.02 * 70.0, "{last:?}");
}

#[test]
fn bad_bus_faults_are_one_line_errors_before_anything_starts() {
    let _serial = serial();
    let dir = scratch("badbus");
    let out = dir.join("run");
    for (fault, want) in [
        (
            "drop:wref@0.1:1",
            "no stage of this drive publishes topic 'wref' (its topics: meas, est, iref, cmd)",
        ),
        ("corrupt:volts@0.1:1", "unknown topic 'volts'"),
        ("delay:pump@0.1:0.1:10us", "unknown stage 'pump'"),
        ("delay:plant@0.1:0.1:10", "200us, 200µs or 0.3ms"),
        ("drop:cmd@0.1:0", "1..=100000"),
    ] {
        let o = drivelab(&[
            "run",
            "--clock",
            "lockstep",
            "--duration",
            "0.2",
            "--fault",
            fault,
            "--out",
            out.to_str().unwrap(),
            "--no-plots",
        ]);
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{fault}");
        assert!(e.contains(want), "{fault}: {e}");
        assert_eq!(e.trim().lines().count(), 1, "{fault}: {e}");
        assert!(!out.exists(), "{fault}: a run folder was made");
    }
}

#[test]
fn corrupt_estimates_in_lockstep_are_rejected_by_each_reader_and_deterministic() {
    use drivelab_runtime::messages::FLAG_STALE_INPUT;
    let _serial = serial();
    // Estimates 2000..=2002 are spoilt: the current loop (and the speed loop, which reads
    // every estimate) reject them; the current loop steps on its fallback instead.
    let (a, s) = deterministic("corruptest", "corrupt:est@0.2:3", "0.3");
    let f = &s["faults"][0];
    assert_eq!(f["service"], "observer", "{f}");
    assert_eq!(
        f["rejected_by"],
        serde_json::json!({ "current-loop": 3, "speed-loop": 3 }),
        "{f}"
    );
    assert_eq!(f["rejected_inputs"], 6, "{f}");
    let rows = drivelab_runtime::trace::read_csv(&a.join("trace.csv")).unwrap();
    assert_eq!(rows.len(), 3000);
    assert!(samples(&rows, |r| r.ctrl_flags & FLAG_MISSING != 0).is_empty());
    let stale = samples(&rows, |r| r.ctrl_flags & FLAG_STALE_INPUT != 0);
    assert_eq!(f["stale_input_samples"], stale.len(), "{f}");
    assert!(
        stale.contains(&2000) && stale.iter().all(|k| (2000..2013).contains(k)),
        "{stale:?}"
    );
    for r in &rows {
        assert!(
            r.theta_hat.is_finite() && r.omega_hat.abs() < 1e6,
            "k = {}",
            r.k
        );
    }
}

#[test]
fn every_shipped_topology_gives_the_inprocess_trace_under_drop_and_corrupt() {
    let _serial = serial();
    let faults = [
        "--fault",
        "drop:meas@0.1:2",
        "--fault",
        "corrupt:est@0.15:3",
        "--fault",
        "drop:iref@0.2:1",
        "--fault",
        "corrupt:cmd@0.25:2",
    ];
    let with = |head: &[&'static str]| [head, &faults[..]].concat();
    let (p, _) = run_ok(
        "topoinproc",
        &with(&["--clock", "inprocess", "--duration", "0.3"]),
    );
    let tp = read(&p.join("trace.csv"));
    let rows = drivelab_runtime::trace::read_csv(&p.join("trace.csv")).unwrap();
    let missing = samples(&rows, |r| r.ctrl_flags & FLAG_MISSING != 0);
    assert_eq!(missing, [1000, 1001, 2500, 2501].into(), "{missing:?}");
    for topo in ["four-process", "two-process", "one-process"] {
        let (a, s) = run_ok(
            &format!("topo{topo}"),
            &with(&[
                "--clock",
                "lockstep",
                "--duration",
                "0.3",
                "--topology",
                topo,
            ]),
        );
        assert!(
            read(&a.join("trace.csv")) == tp,
            "{topo}: not the in-process trace"
        );
        assert_eq!(s["faults"].as_array().unwrap().len(), 4, "{topo}");
    }
}

#[test]
fn a_restarted_stage_keeps_applying_the_schedule() {
    let _serial = serial();
    // The current loop is killed at 0.1 s and restarted: the corrupt commands at 1.5 s come
    // from the restarted process, which read the schedule from the same resolved scenario.
    let (out, s) = run_ok(
        "restartcorrupt",
        &[
            "--duration",
            "2.0",
            "--fault",
            "kill:current-loop@0.1",
            "--fault",
            "corrupt:cmd@1.5:5",
        ],
    );
    let events = s["supervisor_events"].as_array().unwrap();
    let ready = events
        .iter()
        .find(|e| e["event"] == "ready" && e["process"] == "current-loop")
        .unwrap_or_else(|| panic!("no restart: {events:?}"));
    // The test's premise, not a time budget: the corrupt window must come after the restart.
    assert!(
        ready["k"].as_u64().unwrap() < 15_000,
        "the current loop restarted after the corrupt window began (sample 15 000), so the \
         window did not test the restarted process: {ready}"
    );
    let f = s["faults"]
        .as_array()
        .unwrap()
        .iter()
        .find(|f| f["fault"] == "corrupt:cmd@1.5:5")
        .unwrap();
    // Every corrupt command the restarted loop published was rejected by the plant (a loop
    // that fell behind on a loaded machine publishes only its newest command, so up to 5).
    let n = f["rejected_inputs"].as_u64().unwrap();
    assert!((1..=5).contains(&n), "{f}");
    assert_eq!(f["rejected_by"], serde_json::json!({ "plant": n }), "{f}");
    let rows = drivelab_runtime::trace::read_csv(&out.join("trace.csv")).unwrap();
    let corrupt_rows = samples(&rows, |r| {
        (15_000..15_005).contains(&r.k) && r.ctrl_flags & FLAG_MISSING != 0
    });
    assert!(corrupt_rows.len() as u64 >= n, "{corrupt_rows:?}");
    for r in &rows {
        assert!(r.u_d.is_finite() && r.u_q.is_finite(), "k = {}", r.k);
    }
}

#[test]
fn a_delay_is_accepted_in_lockstep_and_changes_nothing_in_the_trace() {
    let _serial = serial();
    let (plain, _) = run_ok("delayplain", &["--clock", "inprocess", "--duration", "0.2"]);
    let (ls, s) = run_ok(
        "delayls",
        &[
            "--clock",
            "lockstep",
            "--duration",
            "0.2",
            "--fault",
            "delay:observer@0.05:0.1:300us",
        ],
    );
    assert!(
        read(&ls.join("trace.csv")) == read(&plain.join("trace.csv")),
        "a delay changed the lockstep trace"
    );
    let f = &s["faults"][0];
    assert_eq!(f["fault"], "delay:observer@0.05:0.1:300us", "{f}");
    // No deadline in lockstep: no misses, no cycle latency to report.
    assert!(
        f["deadline_misses"].is_null() && f["cycle_latency_max_us"].is_null(),
        "{f}"
    );
    // Nothing saw it: no detection, and the outputs were never interrupted.
    assert!(f["detected_data_path_ms"].is_null(), "{f}");
    assert_eq!(f["republished_ms"], 0.0, "{f}");
    assert_eq!(f["stale_command_samples"], 0, "{f}");
}
