//! Snapshot tests of the help texts and the scenario catalogue: a change to what
//! users read must be deliberate. `UPDATE_SNAPSHOTS=1 cargo test --test cli` rewrites those that
//! changed and fails (review the diff, then run again); it is refused when `CI` is set.

mod common;

use std::path::PathBuf;
use std::process::Command;

/// Compares `drivelab ARGS` with snapshot `name`; with `UPDATE_SNAPSHOTS` rewrites it when it
/// differs and returns its path (the caller fails after all were rewritten).
fn snapshot(name: &str, args: &[&str]) -> Option<PathBuf> {
    let o = common::output_within(
        Command::new(env!("CARGO_BIN_EXE_drivelab")).args(args),
        std::time::Duration::from_secs(60),
    );
    assert!(
        o.status.success(),
        "drivelab {args:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let got = String::from_utf8(o.stdout).unwrap();
    let file = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/snapshots"))
        .join(format!("{name}.txt"));
    let want = std::fs::read_to_string(&file).ok();
    if std::env::var_os("UPDATE_SNAPSHOTS").is_some() {
        // CI checks the snapshots; it never rewrites them.
        assert!(
            std::env::var_os("CI").is_none(),
            "UPDATE_SNAPSHOTS is refused when CI is set"
        );
        if want.as_deref() != Some(got.as_str()) {
            std::fs::write(&file, &got).unwrap();
            return Some(file);
        }
        return None;
    }
    let want =
        want.unwrap_or_else(|| panic!("{} missing: run with UPDATE_SNAPSHOTS=1", file.display()));
    assert_eq!(
        got, want,
        "drivelab {args:?} changed; review and run with UPDATE_SNAPSHOTS=1"
    );
    None
}

/// A rewritten snapshot is never a pass: review the diff, then run again.
fn none_rewritten(rewritten: impl IntoIterator<Item = Option<PathBuf>>) {
    let files: Vec<PathBuf> = rewritten.into_iter().flatten().collect();
    assert!(
        files.is_empty(),
        "rewritten, review and run again: {files:?}"
    );
}

/// Every subcommand, as `drivelab --help` lists them.
const COMMANDS: [&str; 16] = [
    "run",
    "campaign",
    "bench",
    "fault",
    "clean",
    "monitor",
    "plot",
    "plant",
    "scenarios",
    "design",
    "compare",
    "doctor",
    "observer-error",
    "cdm-design",
    "record",
    "export",
];

#[test]
fn help_texts() {
    let mut rewritten = vec![snapshot("help", &["--help"])];
    for cmd in COMMANDS {
        rewritten.push(snapshot(&format!("help-{cmd}"), &[cmd, "--help"]));
    }
    none_rewritten(rewritten);
}

/// Option values that are not physical quantities (names, paths, counts, choices).
const NOT_A_QUANTITY: &[&str] = &[
    "DIR",
    "FILE",
    "BUS",
    "MOTOR",
    "ENDPOINT",
    "SCENARIO",
    "NAME",
    "NAME,...",
    "NAME|FILE",
    "NAME|FILE,...",
    "CMD",
    "SPEC",
    "RESTART",
    "IN.csv",
    "OUT.csv",
    "EXPR",
    "COLSxROWS",
    "CLOCK",
    "LIST",
    "FAULT_SEED",
    "N",
];
/// Option values whose name is their unit.
const A_UNIT: &[&str] = &[
    "SECONDS",
    "MS",
    "MICROSECONDS",
    "HZ,...",
    "VOLTS",
    "AMPERES",
    "RPM",
    "RAD_PER_S",
    "DEGREES",
];

#[test]
fn the_simulated_restart_default_that_run_help_states_is_the_one_used() {
    // --lockstep-restart-ms has no clap default (an explicit value is refused with --restart
    // never), so its help text states the default itself.
    let o = common::output_within(
        Command::new(env!("CARGO_BIN_EXE_drivelab")).args(["run", "--help"]),
        std::time::Duration::from_secs(60),
    );
    let help = String::from_utf8(o.stdout).unwrap();
    let default = drivelab_runtime::inject::RESTART_DEFAULT_MS;
    assert!(help.contains(&format!("[default: {default}]")), "{help}");
}

#[test]
fn every_help_has_an_example_and_every_quantity_a_unit() {
    // Any other value must name its unit in its help text.
    let names_a_unit = |help: &str| {
        help.split_whitespace()
            .map(|w| w.trim_matches(|c: char| ",;:()[].'\"`".contains(c)))
            .any(|w| {
                w.ends_with('%')
                    || [
                        "s", "ms", "us", "µs", "second", "seconds", "Hz", "A", "V", "rad/s", "rpm",
                        "degree", "degrees", "N·m",
                    ]
                    .contains(&w)
            })
    };
    // `  -x, --name <VALUE>` or `  --name <VALUE>`: the option and its value.
    let option = |line: &str| -> Option<(String, String)> {
        let l = line.trim_start();
        let l = l
            .strip_prefix('-')
            .and_then(|r| r.get(3..))
            .filter(|_| !l.starts_with("--"))
            .unwrap_or(l);
        let (name, rest) = l.strip_prefix("--")?.split_once(' ')?;
        let value = rest.strip_prefix('<')?.split_once('>')?.0;
        Some((format!("--{name}"), value.to_string()))
    };
    let mut without = Vec::new();
    let mut options = 0;
    for cmd in COMMANDS {
        let o = common::output_within(
            Command::new(env!("CARGO_BIN_EXE_drivelab")).args([cmd, "--help"]),
            std::time::Duration::from_secs(60),
        );
        assert!(o.status.success(), "drivelab {cmd} --help: {:?}", o.status);
        let t = String::from_utf8(o.stdout).unwrap();
        assert!(
            t.contains("Example"),
            "drivelab {cmd} --help has no example:\n{t}"
        );
        let lines: Vec<&str> = t.lines().collect();
        for (i, line) in lines.iter().enumerate() {
            let Some((name, value)) = option(line) else {
                continue;
            };
            options += 1;
            if NOT_A_QUANTITY.contains(&value.as_str()) || A_UNIT.contains(&value.as_str()) {
                continue;
            }
            // The option's help: the lines after it, up to the next blank one.
            let help: Vec<&str> = lines[i + 1..]
                .iter()
                .take_while(|l| !l.trim().is_empty())
                .copied()
                .collect();
            if !names_a_unit(&help.join(" ")) {
                without.push(format!("drivelab {cmd} {name} <{value}>"));
            }
        }
    }
    // The option lines were found at all (a changed help layout would otherwise pass).
    assert!(options >= 50, "only {options} options with a value found");
    assert!(
        without.is_empty(),
        "options whose value names no unit (name it, or list the value as not a quantity): {without:?}"
    );
}

#[test]
fn scenario_catalogue() {
    none_rewritten([snapshot("scenarios", &["scenarios"])]);
}

/// `drivelab ARGS` run in folder `cwd`: (exit code, stdout, stderr).
fn drivelab_in(cwd: &std::path::Path, args: &[&str]) -> (Option<i32>, String, String) {
    let o = common::output_within(
        Command::new(env!("CARGO_BIN_EXE_drivelab"))
            .args(args)
            .current_dir(cwd),
        std::time::Duration::from_secs(60),
    );
    (
        o.status.code(),
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

/// The shipped scenarios, from the source tree.
const SCENARIOS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../scenarios");

/// The deadbeat example's scenario in a fresh temp folder, its `exec` line replaced by
/// `exec` (the folder goes when the value drops).
fn deadbeat_with(exec: &str) -> (tempfile::TempDir, PathBuf) {
    let text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../examples/deadbeat-current-loop/deadbeat.toml"
    ))
    .unwrap();
    let line = "exec = \"../../target/release/drivelab-deadbeat\"";
    assert!(text.contains(line));
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("deadbeat.toml");
    std::fs::write(&file, text.replace(line, exec)).unwrap();
    (dir, file)
}

/// What `drivelab design --scenario FILE` prints (it succeeds).
fn design_of(file: &std::path::Path) -> String {
    let (code, out, err) = drivelab_in(
        std::path::Path::new("/"),
        &["design", "--scenario", file.to_str().unwrap()],
    );
    assert_eq!(code, Some(0), "{err}");
    out
}

/// An example's executable of this build (`cargo build --bins --examples`), beside drivelab.
fn example_exe(name: &str) -> String {
    let exe = std::path::Path::new(env!("CARGO_BIN_EXE_drivelab")).with_file_name(name);
    assert!(
        exe.is_file(),
        "{}: build it with cargo build --bins --examples",
        exe.display()
    );
    exe.display().to_string()
}

#[test]
fn design_says_what_runs_when_a_users_stage_replaces_a_loop() {
    // The deadbeat example replaces kyslan-pi's current loop (its executable, asked with
    // --describe, hosts a 'current-loop' stage): the PI current design is not what runs
    // (the run's summary names it in design.not_run).
    let exe = example_exe("drivelab-deadbeat");
    let (_dir, file) = deadbeat_with(&format!("exec = {exe:?}"));
    let out = design_of(&file);
    let runs = out.lines().nth(1).unwrap();
    assert!(
        runs.starts_with(&format!("runs: the user's current-loop stage (process 'current-loop', exec {exe}), pi speed loop")),
        "{out}"
    );
    let line = |what: &str| out.lines().find(|l| l.contains(what)).unwrap();
    assert!(line("current PI (").starts_with("not run: "), "{out}");
    assert!(line("speed PI (").starts_with("speed PI ("), "{out}");
}

#[test]
fn design_asks_an_exec_which_stages_it_hosts_as_run_does() {
    // The position-loop example's executable hosts no 'current-loop' stage: the built-in
    // current loop runs in its process (`run` asks it with --describe), and `design` says so.
    let exe = example_exe("drivelab-position-loop");
    let (dir, file) = deadbeat_with(&format!("exec = {exe:?}"));
    // The deadbeat loop's own table would be refused where the built-in runs.
    let text = std::fs::read_to_string(&file).unwrap();
    let (head, rest) = text.split_once("[stages.current-loop]").unwrap();
    let text = format!("{head}{}", &rest[rest.find("[[process]]").unwrap()..]);
    std::fs::write(&file, text).unwrap();
    let out = design_of(&file);
    let runs = out.lines().nth(1).unwrap();
    assert!(
        runs.starts_with("runs: pi current loop, pi speed loop"),
        "{out}"
    );
    assert!(!out.contains("user's"), "{out}");
    let line = |what: &str| out.lines().find(|l| l.contains(what)).unwrap();
    assert!(line("current PI (").starts_with("current PI ("), "{out}");
    let bus = common::bus_id("note");
    // ... in a note line, as run does (a registration left out of the executable's
    // host_main, or an exec on the wrong process, would otherwise go unseen).
    let note = format!(
        "note: process 'current-loop' runs the built-in current-loop: its exec {exe} declares no stage of that name (its own stages: position-loop)"
    );
    assert_eq!(out.lines().last(), Some(note.as_str()), "{out}");
    let (run_code, _, run_err) = drivelab_in(
        std::path::Path::new("/"),
        &[
            "run",
            "--clock",
            "lockstep",
            "--duration",
            "0.01",
            "--scenario",
            file.to_str().unwrap(),
            "--bus",
            &bus,
            "--out",
            dir.path().join("run").to_str().unwrap(),
            "--no-plots",
        ],
    );
    common::assert_clean(&bus);
    assert_eq!(run_code, Some(0), "{run_err}");
    assert_eq!(
        run_err.matches(&format!("drivelab: {note}\n")).count(),
        1,
        "{run_err}"
    );
    // With the replacement's table left in, the same is refused, naming the executable.
    let (_dir2, kept) = deadbeat_with(&format!("exec = {exe:?}"));
    let (code, _, err) = drivelab_in(
        std::path::Path::new("/"),
        &["design", "--scenario", kept.to_str().unwrap()],
    );
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains(&format!(
            "the built-in runs here (process 'current-loop' starts {exe}, which declares no stage 'current-loop')"
        )),
        "{err}"
    );
    // A bad exec: the run's one-line error, exit code 1, nothing printed.
    let (_dir, file) = deadbeat_with("exec = \"./no-such-host\"");
    let f = file.to_str().unwrap();
    let (code, out, err) = drivelab_in(std::path::Path::new("/"), &["design", "--scenario", f]);
    assert_eq!(code, Some(1), "{out}{err}");
    assert!(out.is_empty(), "{out}");
    let (run_code, _, run_err) = drivelab_in(
        std::path::Path::new("/"),
        &[
            "run",
            "--clock",
            "lockstep",
            "--scenario",
            f,
            "--out",
            "/nonexistent/drivelab-design-test",
        ],
    );
    assert_eq!(run_code, Some(1), "{run_err}");
    assert_eq!(err, run_err);
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(
        err.contains("process 'current-loop': exec ") && err.contains("no-such-host not found"),
        "{err}"
    );
}

#[test]
fn design_says_unstable_where_the_sampled_loop_is() {
    // low-rst-sensorless runs the RST loops; the nonlinear design printed for comparison is
    // unstable at its 500 Hz speed law: a pole outside the unit circle, and an overshoot far
    // beyond any designed one, that of a growing response.
    let (code, out, err) = drivelab_in(
        std::path::Path::new("/"),
        &["design", "--scenario", "low-rst-sensorless"],
    );
    assert_eq!(code, Some(0), "{err}");
    let l = out
        .lines()
        .find(|l| l.contains("design model (drive's discrete law"))
        .unwrap();
    // The figure that follows a label in the line, e.g. "overshoot 12.5 %" → 12.5.
    let after = |label: &str| -> f64 {
        let (_, rest) = l
            .split_once(label)
            .unwrap_or_else(|| panic!("no {label:?}: {l}"));
        let v = rest.split([' ', ',', ';']).next().unwrap();
        v.parse()
            .unwrap_or_else(|e| panic!("{label:?} {v:?}: {e}: {l}"))
    };
    assert!(
        l.contains("; UNSTABLE: the sampled loop has a pole at |z| = "),
        "{l}"
    );
    let rho = after("|z| = ");
    assert!(rho > 1.0, "|z| = {rho}: {l}");
    let overshoot = after("overshoot ");
    assert!(overshoot > 100.0, "overshoot {overshoot} %: {l}");
    assert!(
        l.contains("(this design is not run: for comparison only)"),
        "{l}"
    );
}

#[test]
fn a_scenario_or_topology_in_the_working_folder_wins_over_the_shipped_one() {
    let dir = common::scratch("cwd");
    std::fs::create_dir_all(dir.join("scenarios/topologies")).unwrap();
    // kyslan-pi, edited in the working folder's scenarios/.
    let shipped = std::fs::read_to_string(format!("{SCENARIOS}/kyslan-pi.toml")).unwrap();
    let edited = shipped.replacen("name = \"kyslan-pi\"", "name = \"kyslan-pi-edited\"", 1);
    assert_ne!(edited, shipped);
    std::fs::write(dir.join("scenarios/kyslan-pi.toml"), edited).unwrap();
    let (code, out, err) = drivelab_in(&dir, &["design", "--scenario", "kyslan-pi"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(
        out.starts_with("scenario kyslan-pi-edited: "),
        "the shipped kyslan-pi was used: {out}"
    );
    // A name the working folder does not have is the shipped one.
    let (code, out, err) = drivelab_in(&dir, &["design", "--scenario", "kyslan-nl"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.starts_with("scenario kyslan-nl: "), "{out}");
    // A topology of a shipped name, broken in the working folder: it is the one read.
    let topo = dir.join("scenarios/topologies/four-process.toml");
    std::fs::write(&topo, "process = []\n").unwrap();
    let (code, _, err) = drivelab_in(
        &dir,
        &[
            "run",
            "--clock",
            "lockstep",
            "--scenario",
            "kyslan-nl",
            "--topology",
            "four-process",
            "--out",
            dir.join("run").to_str().unwrap(),
        ],
    );
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains(&format!(
            "{}: the topology has no [[process]]",
            topo.display()
        )),
        "{err}"
    );
    assert!(!dir.join("run").exists());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn doctor_judges_the_cores_of_the_topology_it_is_given() {
    let dir = common::scratch("doctor");
    std::fs::create_dir_all(&dir).unwrap();
    // A core no machine here has: the placement line is BAD and the per-core checks speak
    // of that core, not of the default placement's cpu 1.
    let topo = dir.join("far.toml");
    std::fs::write(
        &topo,
        "[[process]]\nname = \"all\"\nstages = [\"plant\", \"observer\", \"current-loop\", \"speed-loop\"]\ncpu = 1000\npriority = 70\n",
    )
    .unwrap();
    let (code, out, err) = drivelab_in(
        &dir,
        &["doctor", "--json", "--topology", topo.to_str().unwrap()],
    );
    assert_eq!(code, Some(0), "{err}");
    let checks: serde_json::Value = serde_json::from_str(&out).unwrap();
    let check = |name: &str| {
        checks
            .as_array()
            .unwrap()
            .iter()
            .find(|c| c["name"] == name)
            .unwrap_or_else(|| panic!("no '{name}' in {out}"))
            .clone()
    };
    let p = check("placement");
    assert_eq!(p["status"], "Bad", "{p}");
    assert!(
        p["value"]
            .as_str()
            .unwrap()
            .starts_with(&format!("topology {}: cpu 1000: all", topo.display())),
        "{p}"
    );
    let k = check("kernel runs");
    let v = k["value"].as_str().unwrap();
    assert!(v.contains("cpu 1000") || k["status"] == "Unknown", "{k}");
    // A split topology: this machine's processes (--machine, as for run) are judged, the
    // other's named as not judged here; a machine it does not name is refused in one line.
    let (code, out, err) = drivelab_in(
        &dir,
        &[
            "doctor",
            "--json",
            "--topology",
            "split-hil",
            "--machine",
            "board",
        ],
    );
    assert_eq!(code, Some(0), "{err}");
    let p = serde_json::from_str::<serde_json::Value>(&out).unwrap();
    let p = p
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["name"] == "placement")
        .unwrap();
    assert_eq!(
        p["value"],
        "topology split-hil, machine board (--machine): cpu 1: observer, current-loop, speed-loop; not judged here (machine simulator): plant",
        "{p}"
    );
    let (code, out, err) = drivelab_in(
        &dir,
        &["doctor", "--topology", "split-hil", "--machine", "laptop"],
    );
    assert_eq!((code, out.as_str()), (Some(2), ""), "{err}");
    assert_eq!(
        err,
        "drivelab: error: --machine laptop: topology split-hil has no machine 'laptop' (its machines: simulator, board)\n"
    );
    // Without it, no placement line.
    let (code, out, err) = drivelab_in(&dir, &["doctor", "--json"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(!out.contains("\"placement\""), "{out}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A motor whose sampled speed loop is not a finite matrix (a magnet flux of 100 Wb): the
/// design says its poles cannot be computed and ends (nalgebra's eigenvalues looped for ever
/// on it, at full CPU).
#[test]
fn design_of_an_out_of_scale_motor_ends_and_says_its_poles_cannot_be_computed() {
    let dir = common::scratch("design-out-of-scale");
    let motor = dir.join("motor.toml");
    std::fs::write(
        &motor,
        "[motor]\npreset = \"kyslan2015\"\npsi_pm_wb = 100.0\n",
    )
    .unwrap();
    let o = common::drivelab_within(
        &["design", "--motor", motor.to_str().unwrap()],
        std::time::Duration::from_secs(60),
    );
    let out = String::from_utf8_lossy(&o.stdout);
    assert_eq!(
        o.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(
        out.contains(
            "its poles cannot be computed: the sampled loop's matrix is not a finite number"
        ),
        "{out}"
    );
}
