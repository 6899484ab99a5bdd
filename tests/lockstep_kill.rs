//! Kill and stop faults in lockstep and in process: simulated by the stage hosts at the
//! fault's sample (docs/architecture.md, "Fault model"), so the trace is the same bytes on
//! every run and in both clocks. Each test has its own bus id and run folder and checks that
//! nothing is left behind. Times are watchdogs only.

use drivelab_runtime::messages::{
    FLAG_MISSING, FLAG_PLANT_DOWN, FLAG_SAFE_STATE, FLAG_STALE_CMD, FLAG_STALE_INPUT,
};
use drivelab_runtime::trace::TraceRow;
use std::collections::BTreeSet;

mod common;
use common::*;

/// The samples with no command recorded, with the plant holding a stale command, and with
/// the inverter in its safe state.
fn command_loss(rows: &[TraceRow]) -> [BTreeSet<u64>; 3] {
    [
        samples(rows, |r| r.ctrl_flags & FLAG_MISSING != 0),
        samples(rows, |r| r.plant_flags & FLAG_STALE_CMD != 0),
        samples(rows, |r| r.plant_flags & FLAG_SAFE_STATE != 0),
    ]
}

/// Runs `extra` for `duration` s twice in lockstep and once in process, checks that the
/// three traces are the same bytes and returns the first run's trace and summary.
fn deterministic(tag: &str, duration: &str, extra: &[&str]) -> (Vec<TraceRow>, serde_json::Value) {
    let mut args = vec!["--duration", duration];
    args.extend_from_slice(extra);
    let (a, s) = same_trace_in_every_run(tag, &args);
    let rows = drivelab_runtime::trace::read_csv(&a.join("trace.csv")).unwrap();
    (rows, s)
}

#[test]
fn a_killed_current_loop_is_absent_for_the_restart_then_rejoins_the_same_every_time() {
    let _serial = serial();
    // kyslan-pi at 10 kHz: k0 = 500, default restart 40 ms = 400 samples.
    let (rows, s) = deterministic("killcl", "0.2", &["--fault", "kill:current-loop@0.05"]);
    assert_eq!(rows.len(), 2000);
    // No command for 500..900; the plant applies command k−1, so it holds from 501 for
    // hold_samples (3) and is in its safe state from 504 until the rejoined loop's first
    // command (900) takes effect at 901.
    assert_eq!(
        command_loss(&rows),
        [ks(500..900), ks(501..901), ks(504..901)]
    );
    // The commands the trace lacks are listed, with the fault as their cause.
    let gaps = s["missing_samples"].as_array().unwrap();
    assert_eq!(gaps.len(), 1, "{gaps:?}");
    assert_eq!(
        (gaps[0]["from"].as_u64(), gaps[0]["to"].as_u64()),
        (Some(500), Some(899))
    );
    assert_eq!(gaps[0]["part"], "command");
    let cause = gaps[0]["cause"].as_str().unwrap();
    assert!(cause.contains("kill:current-loop@0.05"), "{cause}");
    let f = &s["faults"][0];
    assert_eq!(f["fault"], "kill:current-loop@0.05", "{f}");
    assert_eq!(f["service"], "current-loop", "{f}");
    assert_eq!(
        (f["injected_k"].as_u64(), f["window_to_k"].as_u64()),
        (Some(500), Some(900))
    );
    assert_eq!(
        f["safe_state_ms"].as_f64().map(|x| (x * 10.0).round()),
        Some(4.0),
        "{f}"
    );
    assert!(
        f["republished_ms"].as_f64().is_some_and(|x| x > 40.0),
        "{f}"
    );
    assert!(f["speed_recovered_ms"].as_f64().is_some(), "{f}");
    // The kill (50 ms) falls into the load step's response (40 ms, recovered at about 60 ms
    // without a fault): the dip and the recovery are not measured over the kill, and the
    // metrics say why. The rise and overshoot (over by the load step) stand.
    let m = &s["metrics"];
    for metric in ["load_dip_rad_s", "load_recovery_ms"] {
        assert!(m[metric].is_null(), "{metric}: {m}");
        assert_eq!(
            m["cut_by_fault"][metric], "cut by the fault at 0.050 s (kill:current-loop@0.05)",
            "{m}"
        );
    }
    assert!(m["rise_time_ms"].as_f64().is_some(), "{m}");
    assert!(m["overshoot_pct"].as_f64().is_some(), "{m}");
    // One supervisor event, at the fault's sample, and no signal.
    let ev = s["supervisor_events"].as_array().unwrap();
    assert_eq!(ev.len(), 1, "{ev:?}");
    assert_eq!(ev[0]["event"], "inject-simulated", "{ev:?}");
    assert_eq!(
        (ev[0]["k"].as_u64(), ev[0]["service"].as_str()),
        (Some(500), Some("current-loop"))
    );
}

#[test]
fn killed_observer_and_speed_loop_fall_back_downstream_deterministically() {
    let _serial = serial();
    let (rows, s) = deterministic(
        "killos",
        "0.3",
        &[
            "--fault",
            "kill:observer@0.05",
            "--fault",
            "kill:speed-loop@0.15",
            "--lockstep-restart-ms",
            "20",
        ],
    );
    // Every command is made (no plant hold), but from a stale input while either is down:
    // the current loop on the encoder angle (observer), then on its held reference.
    assert!(command_loss(&rows).iter().all(|s| s.is_empty()));
    let stale = samples(&rows, |r| r.ctrl_flags & FLAG_STALE_INPUT != 0);
    assert!(
        ks(500..700).is_subset(&stale),
        "observer window not flagged"
    );
    assert!(
        ks(1501..1700).is_subset(&stale),
        "speed-loop window not flagged"
    );
    let faults: Vec<(String, u64, u64)> = s["faults"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| {
            (
                f["fault"].as_str().unwrap().to_string(),
                f["window_from_k"].as_u64().unwrap(),
                f["window_to_k"].as_u64().unwrap(),
            )
        })
        .collect();
    assert_eq!(
        faults,
        [
            ("kill:observer@0.05".to_string(), 500, 700),
            ("kill:speed-loop@0.15".to_string(), 1500, 1700)
        ]
    );
    for f in s["faults"].as_array().unwrap() {
        assert_eq!(f["detected_by"], "current-loop", "{f}");
        assert!(f["republished_ms"].as_f64().is_some(), "{f}");
    }
}

#[test]
fn a_killed_plant_coasts_flagged_plant_down_with_no_measurement_then_resumes() {
    let _serial = serial();
    let (rows, s) = deterministic("killpl", "0.2", &["--fault", "kill:plant@0.05"]);
    assert_eq!(rows.len(), 2000);
    // Down for 500..900: every row there is the motor integrated with no command reaching
    // the inverter (command 499 lost with the plant: held 500..503, safe state from 503),
    // the controllers have no measurement (no command recorded). The first measurement
    // after it is 900, its command takes effect at 901.
    assert_eq!(
        samples(&rows, |r| r.plant_flags & FLAG_PLANT_DOWN != 0),
        ks(500..900)
    );
    assert_eq!(
        command_loss(&rows),
        [ks(500..900), ks(500..901), ks(503..901)]
    );
    let f = &s["faults"][0];
    assert_eq!(f["fault"], "kill:plant@0.05", "{f}");
    assert_eq!(f["plant_down"]["samples"], 400, "{f}");
    assert!(f["speed_recovered_ms"].as_f64().is_some(), "{f}");
}

/// A plant killed so late that its simulated restart would come after the end is down to
/// the end, as under a real-time supervisor: every sample is made, the ones after the kill
/// rebuilt and flagged `plant_down` (the drive ends at the kill only with `--restart never`).
#[test]
fn a_plant_whose_restart_comes_after_the_end_is_down_to_the_end() {
    let _serial = serial();
    // Kill at 0.17 s (sample 1700), restart 40 ms later: 0.21 s, after the 0.2 s run.
    let (rows, s) = deterministic("killpllate", "0.2", &["--fault", "kill:plant@0.17"]);
    assert_eq!(rows.len(), 2000);
    assert_eq!(
        samples(&rows, |r| r.plant_flags & FLAG_PLANT_DOWN != 0),
        ks(1700..2000)
    );
    assert!(s["failure"].is_null(), "{}", s["failure"]);
    let f = &s["faults"][0];
    assert_eq!(f["plant_down"]["samples"], 300, "{f}");
}

#[test]
fn a_stopped_current_loop_is_absent_for_exactly_its_duration() {
    let _serial = serial();
    let (rows, s) = deterministic("stopcl", "0.2", &["--fault", "stop:current-loop@0.05:0.01"]);
    // 0.01 s · 10 kHz = 100 samples with no command, then the old state resumes.
    assert_eq!(
        command_loss(&rows),
        [ks(500..600), ks(501..601), ks(504..601)]
    );
    assert_eq!(s["faults"][0]["fault"], "stop:current-loop@0.05:0.01");
}

/// After a gap in the measurements or in the commands reaching the inverter, the drive
/// takes over from where the motor is: the current stays below twice the 1.6 A limit (the
/// safe state's own short-circuit current, 2.7 A, is the largest), and the speed estimate
/// stays near the motor's speed. Before, the observer stepped across a restarted plant's
/// downtime as across one sample (ω̂ −1544 rad/s, 5.2 A), a simulated observer stop resumed
/// without the catch-up a real one makes (4.5 A), and the current loop's integrators ran on
/// while its dropped commands left the inverter in its safe state (9.4 A).
#[test]
fn after_a_gap_in_measurements_or_commands_the_drive_takes_over_without_a_current_spike() {
    let _serial = serial();
    for (i, (fault, gaps)) in [
        ("kill:plant@0.4", 1),
        ("stop:plant@0.4:0.05", 1),
        ("stop:observer@0.3:0.02", 0),
        // 500 samples: past the topic's history of 256, the oldest are lost to the observer
        // (as to a real stopped one) and it seeds itself again.
        ("stop:observer@0.3:0.05", 1),
        ("drop:cmd@0.4:200", 0),
        ("stop:current-loop@0.4:0.05", 0),
    ]
    .into_iter()
    .enumerate()
    {
        let (out, s) = run_ok(
            &format!("gap{i}"),
            &["--clock", "lockstep", "--duration", "0.6", "--fault", fault],
        );
        let peak = s["peak_current_a"].as_f64().unwrap();
        assert!(peak <= 3.2, "{fault}: peak |i_dq| {peak} A");
        assert_eq!(
            s["counters"]["observer"]["diagnostics"]["measurement_gaps"], gaps,
            "{fault}"
        );
        let rows = drivelab_runtime::trace::read_csv(&out.join("trace.csv")).unwrap();
        let k0 = s["faults"][0]["injected_k"]
            .as_u64()
            .unwrap_or_else(|| panic!("{fault}: no injected_k: {}", s["faults"]));
        let error = |from: u64, to: u64| {
            rows.iter()
                .filter(|r| r.k >= from && r.k < to && r.omega_hat.is_finite())
                .map(|r| (r.omega_hat - r.omega_m).abs())
                .fold(0.0, f64::max)
        };
        let (before, after) = (error(0, k0), error(k0, u64::MAX));
        let speeds = rows.iter().filter(|r| r.k + 1 >= k0).map(|r| r.omega_m);
        let swing = speeds.clone().fold(f64::MIN, f64::max) - speeds.fold(f64::MAX, f64::min);
        // At most the speed's swing from the fault on (the one sample before the new seed
        // holds the speed estimated before the gap: 70 rad/s after a plant kill, the motor at
        // −9.4), on top of the estimate's own error before the fault.
        assert!(
            after <= swing + before,
            "{fault}: ω̂ off by {after} rad/s after the fault, the speed's swing {swing}, \
             the error before {before}"
        );
    }
}

/// While a stage is down the chain keeps its pace: the speed loop, held back by the machine
/// (SIGSTOP for 0.5 s of wall time) while the current loop is down, is waited for and loses
/// no estimate. (The plant ran on without it; the speed loop lost the estimates its buffer
/// could not keep and waited for them until the watchdog.) The trace is the one without the
/// freeze.
#[test]
fn a_speed_loop_held_back_while_the_current_loop_is_down_is_waited_for() {
    let _serial = serial();
    // The current loop is down from sample 500 to 100 500 (a 10 s restart, the longest).
    let args = [
        "--clock",
        "lockstep",
        "--duration",
        "12",
        "--fault",
        "kill:current-loop@0.05",
        "--lockstep-restart-ms",
        "10000",
    ];
    let (plain, _) = run_ok("heldplain", &args);
    let bus = bus_id("held");
    let out = scratch("held").join("run");
    let drive = Drive::start(&bus, &out, &args);
    wait_for_progress(&bus, 2_000);
    let pid = process_pid(&bus, "speed-loop");
    // SAFETY: kill(2) with a pid of this test's own drive, read from /proc just now; it
    // touches no memory of this process.
    assert_eq!(unsafe { libc::kill(pid, libc::SIGSTOP) }, 0);
    std::thread::sleep(std::time::Duration::from_millis(500));
    // SAFETY: as above.
    assert_eq!(unsafe { libc::kill(pid, libc::SIGCONT) }, 0);
    let o = drive.wait_for_exit(std::time::Duration::from_secs(120), "the held-back run");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_clean(&bus);
    assert!(
        read(&plain.join("trace.csv")) == read(&out.join("trace.csv")),
        "the held-back run's trace differs from the plain run's"
    );
}

#[test]
fn random_kills_in_lockstep_are_the_same_every_time() {
    let _serial = serial();
    let (rows, s) = deterministic(
        "rndkill",
        "2",
        &["--fault", "random:5", "--fault-seed", "3"],
    );
    assert_eq!(rows.len(), 20_000);
    let faults = s["faults"].as_array().unwrap();
    assert_eq!(faults.len(), 5, "{faults:?}");
    for f in faults {
        assert!(f["fault"].as_str().unwrap().starts_with("kill:"), "{f}");
        assert_eq!(
            f["window_to_k"].as_u64().unwrap() - f["window_from_k"].as_u64().unwrap(),
            400
        );
    }
}

#[test]
fn bad_restart_times_are_refused_before_anything_starts() {
    let _serial = serial();
    let dir = scratch("badrestart");
    let out = dir.join("run");
    let run = |extra: &[&str]| {
        let mut a = vec![
            "run",
            "--clock",
            "lockstep",
            "--duration",
            "0.1",
            "--out",
            out.to_str().unwrap(),
            "--no-plots",
        ];
        a.extend_from_slice(extra);
        drivelab(&a)
    };
    for bad in ["0", "10001", "NaN", "soon"] {
        let o = run(&[
            "--fault",
            "kill:observer@0.05",
            "--lockstep-restart-ms",
            bad,
        ]);
        let e = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{bad}: {e}");
        let first = e.lines().next().unwrap_or("");
        assert!(
            first.contains("--lockstep-restart-ms")
                && (first.contains("lasts 1 to 10000 ms") || first.contains("not a number")),
            "{bad}: {e}"
        );
        assert!(!out.exists(), "{bad}: a run folder was made");
    }
}

#[test]
fn with_restart_never_a_killed_stage_stays_dead_in_lockstep_as_in_real_time() {
    // kyslan-pi at 10 kHz: a kill at 0.05 s is sample 500; the run ends at sample 2000.
    let (rows, s) = deterministic(
        "killnever",
        "0.2",
        &["--fault", "kill:current-loop@0.05", "--restart", "never"],
    );
    assert_eq!(rows.len(), 2000);
    // No command from the kill to the end: the inverter holds, then stays in its safe state.
    assert_eq!(
        command_loss(&rows),
        [ks(500..2000), ks(501..2000), ks(504..2000)]
    );
    let f = &s["faults"][0];
    assert_eq!(f["fault"], "kill:current-loop@0.05", "{f}");
    assert!(f["republished_ms"].is_null(), "{f}");
    assert!(f["speed_recovered_ms"].is_null(), "{f}");
}

#[test]
fn with_restart_never_a_killed_plant_ends_the_trace_at_its_kill_as_in_real_time() {
    let _serial = serial();
    // kyslan-pi at 10 kHz: a kill at 0.05 s is sample 500; the run would end at 5000. No
    // plant produced the samples from the kill on: none is in the trace (no rebuilt
    // `plant_down` rows), each is listed missing with the kill as its cause, and the run
    // exits 0 as a real-time one does (checked by `deterministic`).
    let (rows, s) = deterministic(
        "plantnever",
        "0.5",
        &["--fault", "kill:plant@0.05", "--restart", "never"],
    );
    assert_eq!(rows.len(), 500);
    assert_eq!(rows.last().map(|r| r.k), Some(499));
    assert!(samples(&rows, |r| r.plant_flags & FLAG_PLANT_DOWN != 0).is_empty());
    assert!(s["failure"].is_null(), "{}", s["failure"]);
    assert_eq!(
        (s["samples"].as_u64(), s["samples_missing"].as_u64()),
        (Some(500), Some(4500))
    );
    let gaps = s["missing_samples"].as_array().unwrap();
    assert_eq!(gaps.len(), 1, "{gaps:?}");
    assert_eq!(
        (
            gaps[0]["from"].as_u64(),
            gaps[0]["to"].as_u64(),
            gaps[0]["part"].as_str()
        ),
        (Some(500), Some(4999), Some("measurement"))
    );
    // The drive ended at the kill, as a real-time one stops: every host stepped the samples
    // before it only (the speed loop every 10th), with no stale input. Before, they stepped
    // on to the end (the plant 5000 samples, its measurements absent), and a plant more
    // than half a recorder buffer past its kill waited for the recorder and failed the run
    // ("recorder stopped reading at sample 500").
    let c = &s["counters"];
    let stepped = |host: &str| {
        (
            c[host]["samples"].as_u64(),
            c[host]["stale_inputs"].as_u64(),
        )
    };
    assert_eq!(stepped("plant"), (Some(500), Some(0)), "{c}");
    assert_eq!(stepped("observer"), (Some(500), Some(0)), "{c}");
    assert_eq!(stepped("current-loop"), (Some(500), Some(0)), "{c}");
    assert_eq!(stepped("speed-loop"), (Some(50), Some(0)), "{c}");
    assert_eq!(
        gaps[0]["cause"],
        "plant kill:plant@0.05 at sample 500 (fault); the plant had not come back yet"
    );
    let f = &s["faults"][0];
    assert_eq!(f["fault"], "kill:plant@0.05", "{f}");
    assert!(f["plant_down"].is_null(), "{f}");
}

/// Runs kyslan-pi for 0.2 s in lockstep and in process with `--restart never`, the plant
/// killed at 0.05 s (sample 500: the drive ends there) and `late` planned after it: the run
/// fails (exit 1) with its trace and summary written, in one line naming `late` as not made
/// (`why`), as a real-time run does. Returns each clock's summary.
fn not_made_after_the_plants_kill(tag: &str, late: &[&str], why: &str) -> Vec<serde_json::Value> {
    let mut summaries = Vec::new();
    for clock in ["lockstep", "inprocess"] {
        let name = format!("{tag}{clock}");
        let (dir, bus) = (scratch(&name), bus_id(&name));
        let out = dir.join("run");
        let mut args = run_args(&bus, &out).to_vec();
        args.extend_from_slice(&[
            "--clock",
            clock,
            "--duration",
            "0.2",
            "--restart",
            "never",
            "--fault",
            "kill:plant@0.05",
        ]);
        args.extend_from_slice(late);
        let o = drivelab(&args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{clock}: {err}");
        assert_clean(&bus);
        assert!(
            err.lines().last().unwrap_or("").starts_with(&format!(
                "drivelab: error: a planned fault was not made: {why} (what was recorded is in "
            )),
            "{clock}: {err}"
        );
        let s = summary(&out);
        assert_eq!(
            s["faults_not_made"],
            serde_json::json!([why]),
            "{clock}: {s}"
        );
        let refused = events(&s, "inject-refused");
        assert_eq!(refused.len(), 1, "{clock}: {s}");
        assert_eq!(
            (refused[0]["detail"].as_str(), refused[0]["k"].as_u64()),
            (Some(why), Some(500)),
            "{clock}: {s}"
        );
        summaries.push(s);
    }
    summaries
}

#[test]
fn with_restart_never_a_fault_planned_after_the_plants_kill_is_not_made_as_in_real_time() {
    let _serial = serial();
    // The observer's kill at sample 1000 is named, not simulated.
    let why = "kill:observer@0.1: not injected: the drive ended at sample 500, before the fault's sample 1000";
    for s in not_made_after_the_plants_kill("latefault", &["--fault", "kill:observer@0.1"], why) {
        assert_eq!(s["faults"].as_array().unwrap().len(), 1, "{s}");
    }
}

/// Before, a sensor fault planned after the plant's kill was reported as made (a report in
/// `faults`, its window past the trace's end) and the run exited 0.
#[test]
fn with_restart_never_a_sensor_fault_planned_after_the_plants_kill_is_not_made() {
    let _serial = serial();
    // The encoder freeze at sample 1000 never came; the current offset from 300, before the
    // kill, did.
    late_not_made_early_made(
        "latesensor",
        "encoder-stuck@0.1:0.01",
        "current-offset:a@0.03:0.5",
    );
}

/// Before, a bus fault planned after the plant's kill was reported as made (a report in
/// `faults` with no window the drive reached) and the run exited 0.
#[test]
fn with_restart_never_a_bus_fault_planned_after_the_plants_kill_is_not_made() {
    let _serial = serial();
    // The drop at sample 1000 never came; the delay from 300 to 400, before the kill, did.
    late_not_made_early_made(
        "latebus",
        "drop:cmd@0.1:5",
        "delay:current-loop@0.03:0.01:100us",
    );
}

/// [`not_made_after_the_plants_kill`] with `late` due at sample 1000 and `early` before the
/// kill: `late` is the fault not made, and the plant's kill and `early` are reported.
fn late_not_made_early_made(tag: &str, late: &str, early: &str) {
    let why = format!(
        "{late}: not injected: the drive ended at sample 500, before the fault's sample 1000"
    );
    let args = ["--fault", late, "--fault", early];
    for s in not_made_after_the_plants_kill(tag, &args, &why) {
        let made: Vec<&str> = s["faults"]
            .as_array()
            .unwrap()
            .iter()
            .map(|f| f["fault"].as_str().unwrap())
            .collect();
        assert_eq!(made, ["kill:plant@0.05", early], "{s}");
    }
}

#[test]
fn a_standby_topology_in_lockstep_says_in_one_line_that_its_twins_do_not_run() {
    let dir = scratch("standbyls");
    let bus = bus_id("standbyls");
    let out = dir.join("run");
    let mut args = run_args(&bus, &out).to_vec();
    args.extend_from_slice(&[
        "--clock",
        "lockstep",
        "--duration",
        "0.05",
        "--topology",
        "four-process-standby",
    ]);
    let o = drivelab(&args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert_clean(&bus);
    let said: Vec<&str> = err.lines().filter(|l| l.contains("standby")).collect();
    assert_eq!(said.len(), 1, "{err}");
    assert!(
        said[0].starts_with("drivelab: warning: standby = true (process ")
            && said[0]
                .ends_with("applies in real time only: the lockstep clock starts no standby twin"),
        "{}",
        said[0]
    );
    let s = summary(&out);
    assert_eq!(
        s["warnings"][0].as_str(),
        Some(&said[0]["drivelab: warning: ".len()..]),
        "{s}"
    );
}
