//! End to end: `drivelab run` with the position loop in its own process (this crate's
//! executable, `exec` in `[[process]]`) and the four built-in stages in theirs.
//!
//! `drivelab` and `drivelab-host` live in another package, so cargo does not build them for
//! this test: `cargo test --workspace` (or `cargo build -p drivelab-services` first) does.
//! The test looks for them next to this crate's executable, `target/<profile>/`.
//! Timeouts here are watchdogs against hangs, never performance assertions.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const EXAMPLE: &str = env!("CARGO_BIN_EXE_drivelab-position-loop");
const SCENARIO: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/position-step.toml");

/// One drive at a time: they all pin to the same core.
static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn drivelab_exe() -> PathBuf {
    let d = Path::new(EXAMPLE).with_file_name("drivelab");
    for exe in [d.clone(), d.with_file_name("drivelab-host")] {
        assert!(
            exe.is_file(),
            "{} is missing: build it first with `cargo build -p drivelab-services` (same profile), or run `cargo test --workspace`",
            exe.display()
        );
    }
    d
}

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("drivelab-posloop-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Removes the scratch folder of a run folder `out` (called last: a failed test keeps it).
fn remove_scratch(out: &Path) {
    if let Some(dir) = out.parent() {
        let _ = std::fs::remove_dir_all(dir);
    }
}

fn bus_id(name: &str) -> String {
    format!("p{}{name}", std::process::id())
        .chars()
        .filter(|c| c.is_ascii_alphanumeric())
        .take(24)
        .collect()
}

/// Processes whose command line names this bus, as "PID ARGS".
fn processes_on_bus(bus: &str) -> Vec<String> {
    let mut v = Vec::new();
    for e in std::fs::read_dir("/proc").unwrap().flatten() {
        if let Ok(cmd) = std::fs::read(e.path().join("cmdline")) {
            let args: Vec<String> = cmd
                .split(|b| *b == 0)
                .map(|s| String::from_utf8_lossy(s).into_owned())
                .collect();
            if args.windows(2).any(|w| w[0] == "--bus" && w[1] == bus) {
                v.push(format!(
                    "{} {}",
                    e.file_name().to_string_lossy(),
                    args.join(" ")
                ));
            }
        }
    }
    v
}

/// The scenario copied into `dir` with `exec` pointing at this build's executable.
fn scenario_copy(dir: &Path) -> PathBuf {
    let text = std::fs::read_to_string(SCENARIO).unwrap();
    let from = "exec = \"../../target/release/drivelab-position-loop\"";
    assert!(text.contains(from), "position-step.toml has no '{from}'");
    let p = dir.join("position-step.toml");
    std::fs::write(&p, text.replace(from, &format!("exec = {EXAMPLE:?}"))).unwrap();
    p
}

/// Runs the scenario in lockstep into `<scratch>/run`, checks exit 0 and that nothing is
/// left behind; returns the run folder.
fn run(name: &str) -> PathBuf {
    run_with(name, &["--clock", "lockstep"])
}

/// As [`run`], with `extra` arguments.
fn run_with(name: &str, extra: &[&str]) -> PathBuf {
    let (o, out, bus) = launch(name, extra);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(
        o.status.success(),
        "drivelab run {extra:?} failed: {stderr}"
    );
    assert_clean(&bus);
    out
}

/// Asserts that no process and no file of `bus` is left.
fn assert_clean(bus: &str) {
    let procs = processes_on_bus(bus);
    assert!(procs.is_empty(), "processes left: {procs:?}");
    let files = drivelab_runtime::bus::leftovers(bus);
    assert!(files.is_empty(), "bus files left: {files:?}");
}

/// `drivelab run` of the scenario into `<scratch>/run` with `extra` arguments, under a
/// watchdog; its output, the run folder and the bus id.
fn launch(name: &str, extra: &[&str]) -> (std::process::Output, PathBuf, String) {
    let exe = drivelab_exe();
    let dir = scratch(name);
    let sc = scenario_copy(&dir);
    let out = dir.join("run");
    let bus = bus_id(name);
    let mut args = vec![
        "run",
        "--scenario",
        sc.to_str().unwrap(),
        "--bus",
        &bus,
        "--out",
        out.to_str().unwrap(),
        "--no-plots",
    ];
    args.extend_from_slice(extra);
    let mut child = Command::new(&exe)
        .args(&args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start drivelab");
    let t = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if t.elapsed() > Duration::from_secs(300) {
            let _ = child.kill();
            let o = child.wait_with_output().unwrap();
            panic!(
                "watchdog: drivelab {args:?} still running after 300 s\nstderr: {}",
                String::from_utf8_lossy(&o.stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    (child.wait_with_output().unwrap(), out, bus)
}

/// trace.csv as named columns.
fn columns(path: &Path) -> std::collections::BTreeMap<String, Vec<f64>> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let names: Vec<String> = lines.next().unwrap().split(',').map(String::from).collect();
    let mut cols: Vec<Vec<f64>> = vec![Vec::new(); names.len()];
    for l in lines {
        for (c, x) in cols.iter_mut().zip(l.split(',')) {
            c.push(x.parse().unwrap_or(f64::NAN));
        }
    }
    names.into_iter().zip(cols).collect()
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
    let s: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
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
    let out = run_with(
        "kill",
        &[
            "--clock",
            "realtime",
            // The restarted process must be ready before the end: 2.9 s leaves room for a
            // loaded machine (a start-up takes tens of ms when idle).
            "--duration",
            "3.0",
            "--fault",
            "kill:position-loop@0.1",
        ],
    );
    let s: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
    let f = &s["faults"][0];
    assert_eq!(f["service"], "position-loop", "{f}");
    assert_eq!(f["process"], "position-loop", "{f}");
    let events: Vec<String> = s["supervisor_events"]
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
        .collect();
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
    remove_scratch(&out);
}

#[test]
fn in_process_a_user_stage_is_refused_before_anything_is_made() {
    let (o, out, bus) = launch("inprocess", &["--clock", "inprocess"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert_eq!(
        err.trim_end(),
        "drivelab: error: --clock inprocess runs the built-in stages only; process \
         'position-loop' hosts user stages (position-loop): use --clock lockstep"
    );
    assert!(!out.exists(), "a refused run left its folder");
    assert_clean(&bus);
    remove_scratch(&out);
}
