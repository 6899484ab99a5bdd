//! End to end: `drivelab run` with the position loop in its own process (this crate's
//! executable, `exec` in `[[process]]`) and the four built-in stages in theirs (helpers:
//! `examples/common/e2e.rs`).

#[allow(dead_code)] // each example's tests use a part of it
#[path = "../../common/e2e.rs"]
mod e2e;

use e2e::{assert_clean, columns, remove_scratch, summary, Example, SERIAL};
use std::path::PathBuf;

const EXAMPLE: Example = Example {
    exe: env!("CARGO_BIN_EXE_drivelab-position-loop"),
    scenario: concat!(env!("CARGO_MANIFEST_DIR"), "/position-step.toml"),
    exec_line: "exec = \"../../target/release/drivelab-position-loop\"",
    tag: "posloop",
};

/// Runs the scenario in lockstep into `<scratch>/run`, checks exit 0 and that nothing is
/// left behind; returns the run folder.
fn run(name: &str) -> PathBuf {
    EXAMPLE.run_with(name, &["--clock", "lockstep"])
}

#[test]
fn position_step_settles_within_one_percent() {
    let _s = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let out = run("settle");
    let c = columns(&out.join("trace.csv"));
    let t = &c["t"];
    let theta_m = &c["theta_m"];
    // The trace records the reference the position loop used: 0 before the step, 2π after.
    let theta_ref = &c["theta_m_ref"];
    let at = |ts: f64| t.iter().position(|&x| x >= ts).unwrap();
    assert_eq!(theta_ref[at(0.005)], 0.0, "θ* before the step");
    assert_eq!(
        theta_ref[at(0.02)],
        std::f64::consts::TAU,
        "θ* after the step"
    );
    let target = std::f64::consts::TAU;
    let (step_at, tol) = (0.01, 0.01 * target);
    let last_out = theta_m
        .iter()
        .rposition(|x| (x - target).abs() > tol)
        .expect("never within 1 %");
    assert!(
        last_out + 1 < t.len(),
        "not settled at the end: θ_m = {}",
        theta_m[last_out]
    );
    let settle = t[last_out + 1] - step_at;
    let peak = theta_m.iter().cloned().fold(f64::MIN, f64::max);
    let fin = *theta_m.last().unwrap();
    eprintln!(
        "position step 0 → 2π: settled within 1 % after {:.1} ms, overshoot {:.2} %, final error {:.2e} rad",
        settle * 1e3,
        (peak - target) / target * 100.0,
        fin - target
    );
    // Bound from the design: slewing at ω_max = 100 rad/s takes 2π/100 = 63 ms at most, then
    // the P loop decays as exp(−K_p·t) with K_p = 1/(4·8 ms) = 31.25 /s: from at most the
    // whole step to 1 % takes ln(100)/K_p = 147 ms; plus the speed loop's 8 ms rise: 218 ms.
    // No slack on top: the bound counts the whole step twice (the slewing ends once
    // K_p·error < ω_max, 3.2 rad before the target, and the decay starts from there), which
    // covers the chain's sample delays (the 1 kHz position and speed loops' 1 ms each).
    assert!(settle < 0.218, "settling time {settle} s");
    assert!((fin - target).abs() < tol, "final θ_m = {fin}");
    // The speed loop followed the position loop, not the scenario's speed reference: the
    // summary leaves out the metrics measured against that, and says why.
    let s = summary(&out);
    let m = &s["metrics"];
    assert_eq!(m["speed_reference_from"], "position-loop", "{m}");
    for f in [
        "rise_time_ms",
        "overshoot_pct",
        "steady_state_error_rad_s",
        "load_dip_rad_s",
        "load_recovery_ms",
    ] {
        assert!(m[f].is_null(), "{f}: {m}");
    }
    remove_scratch(&out);
}

#[test]
fn lockstep_runs_are_bit_identical() {
    let _s = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let (out_a, out_b) = (run("twice-a"), run("twice-b"));
    let a = std::fs::read(out_a.join("trace.csv")).unwrap();
    let b = std::fs::read(out_b.join("trace.csv")).unwrap();
    assert!(!a.is_empty());
    assert!(a == b, "the two lockstep traces differ");
    remove_scratch(&out_a);
    remove_scratch(&out_b);
}

/// The user stage is supervised like a built-in one: a kill names the stage, its process is
/// restarted, and while it is down the speed loop brings the drive to standstill instead of
/// following the last speed reference.
#[test]
fn a_killed_user_stage_is_restarted_and_the_speed_loop_stops_following_it() {
    let _s = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let (out, s) = EXAMPLE.run_killed("position-loop");
    let f = &s["faults"][0];
    assert_eq!(f["process"], "position-loop", "{f}");
    let events = supervisor_events(&s);
    for want in [
        "exited position-loop",
        "restarted position-loop",
        "ready position-loop",
    ] {
        assert!(
            events.iter().any(|e| e == want),
            "no '{want}' in {events:?}"
        );
    }
    // The restart is immediate, but a process start-up (node, ports, RT set-up) takes far
    // more than the 2 periods (2 ms) after which the speed loop replaces a lost reference
    // by 0.
    let lost = s["counters"]["speed-loop"]["diagnostics"]["wref_lost_samples"]
        .as_u64()
        .unwrap();
    assert!(lost > 0, "{}", s["counters"]["speed-loop"]);
    assert!(s["processes"]["position-loop"]["stages"] == serde_json::json!(["position-loop"]));
    // In the trace: mid-move at the kill (a speed reference other than 0), and 0 within 5
    // speed periods and a sample of it (10 samples each at 10 kHz): the kill's sample is the
    // one the supervisor saw, up to a period behind the drive; the next reference was due
    // within a period, it is lost 2 periods after that, the speed loop steps on the next
    // period's sample at the latest, and its reference shows in the command's row a sample
    // later. (A speed loop that followed the last reference would not go to 0 at all.)
    let k0 = f["injected_k"].as_u64().unwrap();
    let rows = drivelab_runtime::trace::read_csv(&out.join("trace.csv")).unwrap();
    let before = rows.iter().rfind(|r| r.k < k0).unwrap();
    assert!(
        before.omega_ref != 0.0,
        "standing still at the kill: {before:?}"
    );
    let zero = rows.iter().find(|r| r.k >= k0 && r.omega_ref == 0.0);
    assert!(
        zero.is_some_and(|r| r.k <= k0 + 51),
        "the speed reference did not go to 0 within 51 samples of the kill at {k0}: {zero:?}"
    );
    remove_scratch(&out);
}

/// A restarted position loop takes over from the position the drive had, not from the
/// encoder's angle within a turn: a 4π step, the loop killed mid-move above 2π (lockstep,
/// deterministic) still ends at 4π, not a revolution beyond it.
#[test]
fn a_restarted_position_loop_keeps_its_turn_count() {
    let _s = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let target = 2.0 * std::f64::consts::TAU;
    let (o, out, bus) = EXAMPLE.launch(
        "rejoin",
        &["--clock", "lockstep", "--fault", "kill:position-loop@0.1"],
        &[
            ("duration_s = 0.3", "duration_s = 0.6"),
            (
                "step_rad = 6.283185307179586",
                "step_rad = 12.566370614359172",
            ),
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert_clean(&bus);
    let c = columns(&out.join("trace.csv"));
    // Killed mid-move (slewing at ω_max = 100 rad/s from 10 ms on).
    let killed = c["t"].iter().position(|&x| x >= 0.1).unwrap();
    let s = summary(&out);
    assert_eq!(
        s["faults"][0]["process"], "position-loop",
        "{}",
        s["faults"]
    );
    assert_the_move_ends_where_it_was_going(&s, &c["theta_m"], killed, target);
    // While the loop is down (40 ms simulated from 0.1 s) its θ* is empty, not 0.
    let down = theta_ref_while_down(&c, killed, target);
    assert!(
        down.empty > 300 && down.zero == 0,
        "θ_m* in the downtime: {down:?}"
    );
    remove_scratch(&out);
}

/// The supervisor's events of a run, as "EVENT PROCESS".
fn supervisor_events(s: &serde_json::Value) -> Vec<String> {
    s["supervisor_events"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| {
            format!(
                "{} {}",
                e["event"].as_str().unwrap(),
                e["process"].as_str().unwrap()
            )
        })
        .collect()
}

/// A move to `target` (4π) whose position loop was killed at sample `killed`, past its first
/// turn, ends at the target: a fresh loop that counted its turns from the encoder angle
/// would end one turn beyond. The loop's rejoin found its turn count unambiguously.
fn assert_the_move_ends_where_it_was_going(
    s: &serde_json::Value,
    theta_m: &[f64],
    killed: usize,
    target: f64,
) {
    assert!(
        theta_m[killed] > std::f64::consts::TAU && theta_m[killed] < target - 1.0,
        "θ_m at the kill: {}",
        theta_m[killed]
    );
    let fin = *theta_m.last().unwrap();
    assert!(
        (fin - target).abs() < 0.01 * target,
        "final θ_m = {fin} (target {target}; one turn off: {})",
        fin - target - std::f64::consts::TAU
    );
    let d = &s["counters"]["position-loop"]["diagnostics"];
    assert_eq!(d["ambiguous_rejoins"], 0, "{d}");
}

/// The trace's θ_m* column after the step at sample `from` on: rows with the target, empty
/// rows, rows reading 0 and rows with anything else.
#[derive(Debug, Default)]
struct ThetaRefRows {
    target: usize,
    empty: usize,
    zero: usize,
    other: usize,
}

/// The trace's columns.
type Columns = std::collections::BTreeMap<String, Vec<f64>>;

fn theta_ref_while_down(c: &Columns, from: usize, target: f64) -> ThetaRefRows {
    let mut r = ThetaRefRows::default();
    for &x in &c["theta_m_ref"][from..] {
        match x {
            x if x.is_nan() => r.empty += 1,
            x if x == target => r.target += 1,
            0.0 => r.zero += 1,
            _ => r.other += 1,
        }
    }
    r
}

/// A 3 s real-time run of a step to `step_rad` (as the scenario's text writes it) with a
/// `--fault` per `faults` and the scenario's `edits`; checks exit 0 and a clean bus. The run
/// folder, its summary and its trace.
fn real_time_move(
    name: &str,
    step_rad: &str,
    faults: &[&str],
    edits: &[(&str, &str)],
) -> (PathBuf, serde_json::Value, Columns) {
    let mut args = vec!["--clock", "realtime", "--duration", "3.0"];
    for f in faults {
        args.extend(["--fault", f]);
    }
    let step = format!("step_rad = {step_rad}");
    let mut edits = edits.to_vec();
    edits.push(("step_rad = 6.283185307179586", &step));
    let (o, out, bus) = EXAMPLE.launch(name, &args, &edits);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert_clean(&bus);
    let s = summary(&out);
    let c = columns(&out.join("trace.csv"));
    (out, s, c)
}

/// The same in real time: the supervisor hands the restarted process its last output as the
/// recorder saw it (`--rejoin-from`), so a 4π step whose loop is killed mid-move above 2π
/// ends at 4π, not a revolution beyond (18.85 rad); while the loop is down its θ* is empty.
#[test]
fn a_restarted_position_loop_keeps_its_turn_count_in_real_time() {
    let _s = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let target = 2.0 * std::f64::consts::TAU;
    let (out, s, c) = real_time_move(
        "rtrejoin",
        "12.566370614359172",
        // θ_m ≈ 7.6 rad (slewing at 100 rad/s from 10 ms on): past the first turn, with 40 ms
        // of slack for a late signal on a loaded machine.
        &["kill:position-loop@0.09"],
        &[],
    );
    let f = &s["faults"][0];
    assert_eq!(f["process"], "position-loop", "{}", s["faults"]);
    let events = supervisor_events(&s);
    assert!(
        events.iter().any(|e| e == "ready position-loop"),
        "not restarted: {events:?}"
    );
    let theta_m = &c["theta_m"];
    let killed = f["injected_k"].as_u64().unwrap() as usize;
    let fin = *theta_m.last().unwrap();
    let down = theta_ref_while_down(&c, killed, target);
    eprintln!("real-time restart: θ_m at the kill {:.3} rad, final θ_m {fin:.4} rad (target {target:.4}); θ_m* from the kill on: {down:?}", theta_m[killed]);
    assert_the_move_ends_where_it_was_going(&s, theta_m, killed, target);
    // A process start-up takes far longer than the 2 ms after which the speed loop stops
    // following a lost reference: some rows are empty, none reads 0.
    assert!(
        down.empty > 0 && down.zero == 0,
        "θ_m* from the kill on: {down:?}"
    );
    remove_scratch(&out);
}

/// With a standby twin (`standby = true`) the position loop keeps its turn count through
/// two takeovers in real time: a 64π step (32 turns, slewing at ω_max = 100 rad/s for 2 s),
/// the process killed mid-move (its twin takes over, a new twin starts) and killed again
/// later mid-move (the new twin takes over). The move ends at its target, not whole turns
/// beyond: a twin started mid-move learns its turn count as a restarted process does.
#[test]
fn a_position_loop_with_a_standby_twin_keeps_its_turn_count_through_two_takeovers() {
    let _s = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let target = 32.0 * std::f64::consts::TAU;
    let (out, s, c) = real_time_move(
        "twin",
        "201.06192982974676",
        // θ_m ≈ 7.6 rad and ≈ 139 rad: both mid-move, both past the first turn. The new twin
        // has 1.3 s to be ready for the second (checked below; it was ready 25 ms after the takeover here).
        &["kill:position-loop@0.09", "kill:position-loop@1.4"],
        &[("priority = 71", "priority = 71\nstandby = true")],
    );
    let timeline: Vec<(String, f64)> = s["supervisor_events"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["process"] == "position-loop")
        .map(|e| {
            let t = e["t_wall_s"].as_f64().unwrap();
            (e["event"].as_str().unwrap().to_string(), t)
        })
        .collect();
    let at = |event: &str| -> Vec<f64> {
        timeline
            .iter()
            .filter(|(e, _)| e == event)
            .map(|(_, t)| *t)
            .collect()
    };
    let (kills, takeovers, ready) = (at("inject"), at("taken-over"), at("standby-ready"));
    // Both kills were taken over by a twin (no restart), and the second twin was ready
    // before the second kill, started after the first takeover.
    assert!(
        kills.len() == 2 && takeovers.len() == 2 && at("restarted").is_empty(),
        "{timeline:?}"
    );
    assert!(
        ready.iter().any(|&r| r > takeovers[0] && r < kills[1]),
        "the new twin was not ready before the second kill: {timeline:?}"
    );
    let theta_m = &c["theta_m"];
    let faults = s["faults"].as_array().unwrap();
    let killed: Vec<usize> = faults
        .iter()
        .map(|f| f["injected_k"].as_u64().unwrap() as usize)
        .collect();
    let fin = *theta_m.last().unwrap();
    eprintln!(
        "standby twin: θ_m at the kills {:.3} and {:.3} rad, final θ_m {fin:.4} rad (target {target:.4})",
        theta_m[killed[0]], theta_m[killed[1]]
    );
    assert!(
        theta_m[killed[1]] < target - 1.0,
        "θ_m at the second kill: {} (not mid-move)",
        theta_m[killed[1]]
    );
    assert_the_move_ends_where_it_was_going(&s, theta_m, killed[0], target);
    remove_scratch(&out);
}

/// `drivelab record` over Zenoh writes the drive's own rows, θ_m* included: empty while the
/// killed position loop is down, as in the drive's trace, not its last value held.
#[test]
fn a_remote_recording_leaves_theta_ref_empty_while_the_position_loop_is_down() {
    let _s = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let ep = e2e::local_endpoint();
    // The recorder first: it waits for the drive's bridge (and must hear its summary).
    let rec_dir = EXAMPLE.scratch("recorded").join("remote");
    let mut recorder = e2e::Guarded(
        std::process::Command::new(EXAMPLE.drivelab())
            .args(["record", "--connect", &ep, "--wait", "60", "--out"])
            .arg(&rec_dir)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let (o, out, bus) = EXAMPLE.launch(
        "recorddown",
        &[
            "--clock",
            "realtime",
            "--duration",
            "1.0",
            "--zenoh-listen",
            &ep,
            "--fault",
            "kill:position-loop@0.09",
        ],
        &[],
    );
    // Watchdog: the recorder ends once it has the drive's summary.
    let t = std::time::Instant::now();
    while recorder.0.try_wait().unwrap().is_none() && t.elapsed().as_secs() < 120 {
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    if recorder.0.try_wait().unwrap().is_none() {
        let _ = recorder.0.kill();
    }
    let r_status = recorder.0.wait().unwrap();
    let mut r_err = String::new();
    std::io::Read::read_to_string(&mut recorder.0.stderr.take().unwrap(), &mut r_err).unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(r_status.success(), "{r_err}");
    assert_clean(&bus);
    let killed = summary(&out)["faults"][0]["injected_k"].as_u64().unwrap() as usize;
    // Each row recorded is the drive's, bit for bit (a sample the bridge lost on a loaded
    // machine is listed, not written).
    let (local, remote) = (
        columns(&out.join("trace.csv")),
        columns(&rec_dir.join("trace.csv")),
    );
    for (i, k) in remote["k"].iter().enumerate() {
        let j = local["k"]
            .binary_search_by(|x| x.total_cmp(k))
            .unwrap_or_else(|_| panic!("sample {k} is not in the drive's trace"));
        for (name, col) in &remote {
            assert_eq!(
                col[i].to_bits(),
                local[name][j].to_bits(),
                "sample {k}, {name}: the drive's {} recorded as {}",
                local[name][j],
                col[i]
            );
        }
    }
    // The loop was down for a while: the remote trace has rows with θ_m* empty after the
    // kill.
    let down = theta_ref_while_down(&remote, killed, std::f64::consts::TAU);
    assert!(down.empty > 0, "θ_m* from the kill on: {down:?}");
    remove_scratch(&out);
    remove_scratch(&rec_dir);
}

/// A negative step is a move like any other: the loop drives the motor backwards, across
/// zero, to it.
#[test]
fn a_negative_step_settles_backwards() {
    let _s = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let target = -std::f64::consts::TAU;
    let (o, out, bus) = EXAMPLE.launch(
        "negative",
        &["--clock", "lockstep"],
        &[(
            "step_rad = 6.283185307179586",
            "step_rad = -6.283185307179586",
        )],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert_clean(&bus);
    let c = columns(&out.join("trace.csv"));
    let (theta_m, theta_ref) = (&c["theta_m"], &c["theta_m_ref"]);
    assert_eq!(*theta_ref.last().unwrap(), target);
    let fin = *theta_m.last().unwrap();
    let low = theta_m.iter().cloned().fold(f64::MAX, f64::min);
    assert!(
        (fin - target).abs() < 0.01 * target.abs(),
        "final θ_m = {fin}"
    );
    // The P loop does not overshoot (the bound of the positive step's test).
    assert!(low > target * 1.01, "lowest θ_m = {low}");
    remove_scratch(&out);
}

/// A run shorter than the step's instant says so once on stderr and keeps it in its summary
/// (`counters.position-loop.warnings`, where a campaign or a CI script reads it).
#[test]
fn a_step_after_the_run_s_end_is_warned_about_and_kept_in_the_summary() {
    let _s = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    // The scenario's step is at 10 ms: a 5 ms run ends before it.
    let (o, out, bus) = EXAMPLE.launch(
        "late-step",
        &["--clock", "lockstep", "--duration", "0.005"],
        &[],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert_clean(&bus);
    let want = "stages.position-loop.step_at_s = 0.01 s is at or after the run's end (0.005 s): the position step is not taken";
    assert_eq!(
        err.matches(&format!("position-loop: warning: {want}\n"))
            .count(),
        1,
        "{err}"
    );
    let s = summary(&out);
    assert_eq!(
        s["counters"]["position-loop"]["warnings"],
        serde_json::json!([want]),
        "{}",
        s["counters"]
    );
    // The built-in stages warned about nothing here: no empty lists either.
    for st in ["plant", "observer", "current-loop", "speed-loop"] {
        assert!(
            s["counters"][st].get("warnings").is_none(),
            "{st}: {}",
            s["counters"][st]
        );
    }
    let c = columns(&out.join("trace.csv"));
    // Row 0 has no reference (empty: the speed loop follows the loop's output from the next
    // sample on); every later one is the step's start, 0.
    let theta_ref = &c["theta_m_ref"];
    assert!(
        theta_ref.len() == 50 && theta_ref[1..].iter().all(|&r| r == 0.0),
        "{theta_ref:?}"
    );
    remove_scratch(&out);
}

/// A run with `args` of the scenario whose position loop is the test host's, which panics at
/// its first step at or after 0.1 s (`examples/panicking_position_loop.rs`); checks exit 1
/// and a clean bus. The run folder, its summary and its stderr.
fn run_panicking(name: &str, args: &[&str]) -> (PathBuf, serde_json::Value, String) {
    let panicking = std::path::Path::new(EXAMPLE.exe)
        .with_file_name("examples")
        .join("panicking_position_loop");
    assert!(
        panicking.is_file(),
        "{} is missing: `cargo test -p drivelab-position-loop` builds it",
        panicking.display()
    );
    let exec = format!("exec = {:?}", panicking.to_str().unwrap());
    let (o, out, bus) = EXAMPLE.launch(
        name,
        args,
        &[
            (EXAMPLE.exec_line, &exec),
            (
                "omega_max_rad_s = 100.0",
                "panic_at_s = 0.1\nomega_max_rad_s = 100.0",
            ),
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert_clean(&bus);
    assert_eq!(o.status.code(), Some(1), "{err}");
    let s = summary(&out);
    (out, s, err)
}

/// What names the test stage's panic in `text`: the stage, its call and the sample it was
/// stepping, k and t = k·T_s (T_s = 100 µs), then the panic's message, which says k as well
/// (in real time the stage may step a later sample than the one it was due to panic at, if
/// it fell behind; never an earlier one).
fn panic_naming(text: &str) -> String {
    let tail = text
        .split("a test panic at sample ")
        .nth(1)
        .unwrap_or_else(|| panic!("no test panic in {text}"));
    let k: u64 = tail
        .split(|c: char| !c.is_ascii_digit())
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert!(k >= 1000, "panicked at sample {k}, before 0.1 s: {text}");
    let t = k as f64 / 1e4;
    format!("stage position-loop, step at sample {k}, t = {t} s: position-loop: a test panic at sample {k}")
}

/// A stage that panics is a failure of the run: its process exits with status 101 after one
/// line naming the panic (the stage, the call and the sample), the supervisor restarts it
/// (the drive goes on), and the run fails with one line naming the process and the panic.
#[test]
fn a_panicking_stage_fails_the_run_in_one_line() {
    let _s = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    // With RUST_BACKTRACE set (as in CI) the panicking host symbolizes its backtrace before it
    // exits: 0.4 s in a debug build, over 0.9 s under load (a 1 s drive then ended before the
    // restarted host was ready). 3 s leaves its restart time to be ready.
    let (out, s, err) = run_panicking("panic", &["--clock", "realtime", "--duration", "3.0"]);
    let exited: Vec<&serde_json::Value> = s["supervisor_events"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["process"] == "position-loop" && e["event"] != "reaped")
        .collect();
    assert_eq!(
        exited[0]["detail"], "exit status: 101, not injected",
        "{exited:?}"
    );
    let detail = exited[1]["detail"].as_str().unwrap();
    let what = panic_naming(detail);
    assert!(
        exited[1]["event"] == "panicked" && detail.starts_with(&what),
        "{exited:?}"
    );
    assert!(exited.iter().any(|e| e["event"] == "ready"), "{exited:?}");
    let failure = s["failure"].as_str().unwrap_or("");
    assert!(
        failure.starts_with(&format!("process position-loop panicked: {what}"))
            && failure.ends_with("(it was restarted)"),
        "{failure}"
    );
    // One line on stderr says it, and the host's own line names the panic.
    let lines: Vec<&str> = err.lines().filter(|l| l.contains("panicked:")).collect();
    assert_eq!(lines.len(), 1, "{err}");
    assert!(
        lines[0].starts_with("drivelab: error: process position-loop panicked: "),
        "{err}"
    );
    let (head, msg) = what.split_once(": ").unwrap();
    assert!(
        err.lines().any(|l| l.starts_with(&format!(
            "position-loop: error: a stage panicked ({head}): {msg}"
        ))),
        "{err}"
    );
    // The drive went on to its end.
    assert_eq!(s["samples"], s["samples_expected"], "{s}");
    remove_scratch(&out);
}

/// In lockstep the panic is at its sample exactly, and the run ends on it: the host's line,
/// the supervisor's event and the run's error name the stage, the call and the sample.
#[test]
fn a_panicking_stage_is_named_with_its_sample_in_lockstep() {
    let _s = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let (out, s, err) = run_panicking("panic-lockstep", &["--clock", "lockstep"]);
    let what = "stage position-loop, step at sample 1000, t = 0.1 s: position-loop: a test panic at sample 1000 (at ";
    assert!(
        err.lines().any(|l| l.starts_with(
            "position-loop: error: a stage panicked (stage position-loop, step at sample 1000, t = 0.1 s): position-loop: a test panic at sample 1000 (at "
        )),
        "{err}"
    );
    let panicked: Vec<&serde_json::Value> = s["supervisor_events"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["process"] == "position-loop" && e["event"] == "panicked")
        .collect();
    assert!(
        panicked.len() == 1 && panicked[0]["detail"].as_str().unwrap().starts_with(what),
        "{panicked:?}"
    );
    let failure = s["failure"].as_str().unwrap_or("");
    assert!(
        failure.starts_with("process position-loop panicked: ") && failure.contains(what),
        "{failure}"
    );
    assert!(
        err.lines()
            .any(|l| l.starts_with("drivelab: error: ") && l.contains(what)),
        "{err}"
    );
    remove_scratch(&out);
}

#[test]
fn in_process_a_user_stage_is_refused_before_anything_is_made() {
    let (o, out, bus) = EXAMPLE.launch("inprocess", &["--clock", "inprocess"], &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert_eq!(
        err.trim_end(),
        "drivelab: error: --clock inprocess runs the built-in stages only, in this process; \
         process 'position-loop' is started from an executable of its own (exec): use --clock \
         lockstep"
    );
    assert!(!out.exists(), "a refused run left its folder");
    assert_clean(&bus);
    remove_scratch(&out);
}

/// An executable whose `--describe` answer gives its stage another rate than the stage runs
/// at (a wrapper that rewrote it, say): the drive, planned on the answer, would wait for
/// samples that never come; the host refuses to start instead, naming both rates.
#[test]
fn a_describe_answer_that_differs_from_the_stage_is_refused_at_start_up() {
    let dir = std::env::temp_dir().join(format!("drivelab-posloop-lying-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let wrapper = dir.join("lying.sh");
    std::fs::write(
        &wrapper,
        format!(
            "#!/bin/sh\nfor a in \"$@\"; do [ \"$a\" = --describe ] && {{ '{exe}' \"$@\" | sed 's/\"divider\":[0-9]*/\"divider\":7/'; exit 0; }}; done\nexec '{exe}' \"$@\"\n",
            exe = EXAMPLE.exe
        ),
    )
    .unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&wrapper, std::fs::Permissions::from_mode(0o755)).unwrap();
    let exec = format!("exec = {:?}", wrapper.to_str().unwrap());
    let (o, out, bus) = EXAMPLE.launch(
        "lying",
        &["--clock", "lockstep", "--duration", "0.05"],
        &[(EXAMPLE.exec_line, &exec)],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.lines().any(|l| l.starts_with("position-loop: error: stage 'position-loop' runs every ")
            && l.ends_with(
                " sample(s), but the drive was planned on every 7 (its executable's --describe answer): the answer and the stage differ"
            )),
        "{err}"
    );
    assert_clean(&bus);
    remove_scratch(&out);
    let _ = std::fs::remove_dir_all(&dir);
}
