//! End to end: `drivelab run` with this crate's deadbeat current loop in the place of the
//! built-in one (its executable, `exec` in `[[process]]`), the plant, the observer and the
//! speed loop built in (helpers: `examples/common/e2e.rs`).

#[allow(dead_code)] // each example's tests use a part of it
#[path = "../../common/e2e.rs"]
mod e2e;

use e2e::{assert_clean, columns, remove_scratch, summary, Example, SERIAL};
use std::path::{Path, PathBuf};

const EXEC_LINE: &str = "exec = \"../../target/release/drivelab-deadbeat\"";

const EXAMPLE: Example = Example {
    exe: env!("CARGO_BIN_EXE_drivelab-deadbeat"),
    scenario: concat!(env!("CARGO_MANIFEST_DIR"), "/deadbeat.toml"),
    exec_line: EXEC_LINE,
    tag: "deadbeat",
};

/// The deadbeat loop's table in the scenario, left out for a run of the built-in loop.
const TABLE: &str = "[stages.current-loop]   # the deadbeat loop's parameters ([current_loop] is the built-in's)\nlambda = 1.0";

/// The scenario's i_d* step: from 0 to −1.6 A (the speed loop passes it on).
const I_D_STEP_A: f64 = -1.6;

/// A lockstep run of the scenario with `edits`; the run folder.
fn lockstep(name: &str, extra: &[&str], edits: &[(&str, &str)]) -> PathBuf {
    let mut args = vec!["--clock", "lockstep"];
    args.extend_from_slice(extra);
    let (o, out, bus) = EXAMPLE.launch(name, &args, edits);
    assert!(
        o.status.success(),
        "drivelab run {args:?} failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert_clean(&bus);
    out
}

/// The first row whose command carries the i_d* step, and the i_d error (A) of the rows
/// after it, relative to the step.
fn i_d_step_errors(out: &Path) -> (usize, Vec<f64>) {
    let c = columns(&out.join("trace.csv"));
    let k0 = c["i_d_ref"]
        .iter()
        .position(|&x| x == I_D_STEP_A)
        .expect("no i_d* step in the trace");
    let err = c["i_d"][k0..k0 + 12]
        .iter()
        .map(|i| (i - I_D_STEP_A) / I_D_STEP_A.abs())
        .collect();
    (k0, err)
}

/// The scenario's edits that make it run the built-in current loop.
fn built_in() -> [(&'static str, &'static str); 2] {
    // The exec line goes (the built-in host runs the process); the table would then be refused.
    [(EXEC_LINE, ""), (TABLE, "")]
}

#[test]
fn the_deadbeat_loop_replaces_the_built_in_and_reaches_an_i_d_step_in_two_samples() {
    let _s = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let out = lockstep("replace", &[], &[]);
    let s = summary(&out);
    // The summary names the replacement and its executable; the current loop's counters are
    // the deadbeat loop's.
    let by = s["replaced_stages"]["current-loop"].as_str().unwrap();
    assert!(
        by.ends_with("/drivelab-deadbeat"),
        "{}",
        s["replaced_stages"]
    );
    assert_eq!(s["processes"]["current-loop"]["executable"], by);
    // The built-in PI current design did not run: it is not in the summary's design, which
    // names it; the speed loop's is.
    let design = &s["design"];
    assert!(design.get("current").is_none(), "{design}");
    assert_eq!(design["not_run"], serde_json::json!({ "current": by }));
    assert!(design["speed"]["k_p"].is_f64(), "{design}");
    let diag = &s["counters"]["current-loop"]["diagnostics"];
    assert!(diag["voltage_limited_samples"].is_u64(), "{diag}");
    assert!(diag.get("iq_ramp_samples").is_none(), "{diag}");
    // Command k acts from t_{k+1}: the step is reached at t_{k+2}, two rows after the row
    // whose command first carries it. The plant is not the loop's model (RK4 with the
    // rotor turning within a sample against a frozen coupling term): within 2 % there.
    let (k0, err) = i_d_step_errors(&out);
    eprintln!("deadbeat: i_d error after the step (fraction of it), rows k0..: {err:.4?}");
    assert!(err[1].abs() > 0.5, "the step acted early: {err:?}");
    for (n, e) in err.iter().enumerate().skip(2) {
        assert!(e.abs() < 0.02, "row k0+{n} (k0 = {k0}): {err:?}");
    }
    // The speed loop's integrator takes the load step at 0.04 s: at the end the drive runs
    // at its reference again.
    let m = &s["metrics"];
    let sse = m["steady_state_error_rad_s"].as_f64().unwrap();
    assert!(
        sse.abs() < 0.7,
        "steady-state error {sse} rad/s (1 % of 70): {m}"
    );
    // The built-in PI loop, designed for τ_c = 250 µs (2.5 samples), is still far from the
    // step there: what ran above was not it.
    let builtin = lockstep("builtin", &[], &built_in());
    let sb = summary(&builtin);
    assert_eq!(sb["replaced_stages"], serde_json::json!({}));
    assert!(
        sb["design"]["current"]["k_p_d"].is_f64(),
        "{}",
        sb["design"]
    );
    // `drivelab design` says so too, for the scenario and not for the built-in's.
    let design = |scenario: &Path| {
        let o = std::process::Command::new(EXAMPLE.drivelab())
            .args(["design", "--scenario"])
            .arg(scenario)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8(o.stdout).unwrap()
    };
    // (Of this build's executable: `design` asks it which stages it hosts, as `run` does.)
    let user = format!(
        "the user's current-loop stage (process 'current-loop', exec {})",
        EXAMPLE.exe
    );
    let copy = EXAMPLE.scenario_copy(&EXAMPLE.scratch("design"), &[]);
    let text = design(&copy);
    assert!(
        text.contains(&format!("runs: {user}, pi speed loop")),
        "{text}"
    );
    assert!(text.contains("not run: current PI"), "{text}");
    let copy = EXAMPLE.scenario_copy(&EXAMPLE.scratch("design"), &built_in());
    let text = design(&copy);
    assert!(text.contains("runs: pi current loop"), "{text}");
    assert!(
        !text.contains("user's") && !text.contains("not run: current"),
        "{text}"
    );
    remove_scratch(&copy);
    let (k1, err_pi) = i_d_step_errors(&builtin);
    assert_eq!(k0, k1);
    assert!(err_pi[2].abs() > 0.2, "{err_pi:?}");
    remove_scratch(&out);
    remove_scratch(&builtin);
}

#[test]
fn one_process_four_or_two_machines_the_trace_is_the_same_bit_for_bit() {
    let _s = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let four = lockstep("four", &[], &[]);
    // The deadbeat host runs every stage in one process: the built-in ones and its own.
    let dir = EXAMPLE.scratch("one-topology");
    let topo = dir.join("one.toml");
    std::fs::write(
        &topo,
        format!(
            "[[process]]\nname = \"drive\"\nstages = [\"plant\", \"observer\", \"current-loop\", \"speed-loop\"]\ncpu = 1\npriority = 70\nexec = {:?}\n",
            EXAMPLE.exe
        ),
    )
    .unwrap();
    let one = lockstep("one", &["--topology", topo.to_str().unwrap()], &[]);
    assert!(summary(&one)["replaced_stages"]["current-loop"].is_string());
    let (a, b) = (
        std::fs::read(four.join("trace.csv")).unwrap(),
        std::fs::read(one.join("trace.csv")).unwrap(),
    );
    assert!(a.len() > 1000);
    assert!(
        a == b,
        "the one-process trace differs from the four-process one"
    );
    // Split across two machines (here both over localhost, each with its own bus): the
    // plant on the simulator, the deadbeat loop with the observer and the speed loop on the
    // board. Both recorders write the same trace, and both summaries name the replacement.
    let split = dir.join("split.toml");
    std::fs::write(
        &split,
        ["plant", "observer", "current-loop", "speed-loop"]
            .iter()
            .map(|p| {
                let (machine, exec) = match *p {
                    "plant" => ("simulator", String::new()),
                    "current-loop" => ("board", format!("exec = {:?}\n", EXAMPLE.exe)),
                    _ => ("board", String::new()),
                };
                format!("[[process]]\nname = \"{p}\"\nstages = [\"{p}\"]\ncpu = 1\npriority = 70\nmachine = \"{machine}\"\n{exec}")
            })
            .collect::<String>(),
    )
    .unwrap();
    let ep = e2e::local_endpoint();
    let side = |name: &str, machine: &str, zenoh: &str| {
        let args = [
            "--clock",
            "lockstep",
            "--topology",
            split.to_str().unwrap(),
            "--machine",
            machine,
            zenoh,
            &ep,
        ];
        EXAMPLE.start(name, &args, &[])
    };
    let simulator = side("simulator", "simulator", "--zenoh-listen");
    let board = side("board", "board", "--zenoh-connect");
    for (o, out, bus) in [board.wait(), simulator.wait()] {
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        assert_clean(&bus);
        let s = summary(&out);
        assert!(
            s["replaced_stages"]["current-loop"]
                .as_str()
                .is_some_and(|e| e == EXAMPLE.exe),
            "{}",
            s["replaced_stages"]
        );
        assert!(
            std::fs::read(out.join("trace.csv")).unwrap() == a,
            "{}: the split drive's trace differs from the four-process one",
            out.display()
        );
        remove_scratch(&out);
    }
    remove_scratch(&four);
    remove_scratch(&one);
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn a_table_for_a_built_in_stage_that_runs_is_refused_before_anything_is_made() {
    let (o, out, bus) = EXAMPLE.launch("table", &["--clock", "lockstep"], &[(EXEC_LINE, "")]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.trim_end().ends_with(
            "deadbeat.toml: [stages.current-loop] is for a user's stage that replaces the built-in current-loop, and the built-in runs here (process 'current-loop' starts no executable that replaces it): it takes its settings from [current_loop]"
        ) && err.lines().count() == 1,
        "{err}"
    );
    assert!(!out.exists(), "a refused run left its folder");
    assert_clean(&bus);
    remove_scratch(&out);
}

/// A killed replacement is supervised as the built-in is: restarted, it takes over from the
/// voltage the plant is applying and the drive recovers its speed.
#[test]
fn a_killed_deadbeat_loop_is_restarted_and_the_drive_recovers() {
    let _s = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let (out, s) = EXAMPLE.run_killed("current-loop");
    let f = &s["faults"][0];
    assert!(f["detected_data_path_ms"].is_number(), "{f}");
    assert!(f["speed_recovered_ms"].is_number(), "not recovered: {f}");
    let restarted = s["supervisor_events"]
        .as_array()
        .unwrap()
        .iter()
        .any(|e| e["event"] == "restarted" && e["process"] == "current-loop");
    assert!(restarted, "{}", s["supervisor_events"]);
    remove_scratch(&out);
}
