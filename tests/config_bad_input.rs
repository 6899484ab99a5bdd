//! Bad input files: scenario TOML, topology files, campaign files and expectations, each
//! mutated one field at a time. Every case must be refused before anything starts with its
//! exit code and one stderr line that names the file, the field and the problem: no panic,
//! no run folder, no process and no bus file left behind.

mod common;

use common::*;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

/// What a refused command printed and left, checked: exit code `code`, one line (after any
/// `warning:` line) containing every one of `needles`, no panic.
fn assert_refused(what: &str, o: &Output, code: i32, needles: &[&str]) {
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!err.contains("panicked"), "{what}: a panic: {err}");
    assert_eq!(o.status.code(), Some(code), "{what}: {err}");
    let lines: Vec<&str> = err.lines().filter(|l| !l.contains("warning:")).collect();
    assert_eq!(lines.len(), 1, "{what}: not one line: {err}");
    for n in needles {
        assert!(lines[0].contains(n), "{what}: '{n}' not in: {}", lines[0]);
    }
}

/// `drivelab run --clock lockstep` with its own bus and folder and `extra`; asserts it is
/// refused as [`assert_refused`] says and left nothing.
fn run_refused(name: &str, extra: &[&str], code: i32, needles: &[&str]) {
    let bus = bus_id(name);
    let out = scratch(name).join("run");
    let mut args = run_args(&bus, &out).to_vec();
    args.extend_from_slice(&["--clock", "lockstep"]);
    args.extend_from_slice(extra);
    let o = drivelab(&args);
    assert_refused(name, &o, code, needles);
    assert!(!out.exists(), "{name}: a refused run made its folder");
    assert_clean(&bus);
}

/// The shipped kyslan-pi scenario with text `edits`, written as `<scratch>/<tag>.toml`.
fn scenario(tag: &str, edits: &[(&str, &str)]) -> PathBuf {
    variant(tag, "kyslan-pi", edits)
}

#[test]
fn a_bad_scenario_field_is_one_line_naming_file_field_range_and_unit() {
    let motor = |line: &str| {
        (
            "preset = \"kyslan2015\"",
            format!("preset = \"kyslan2015\"\n{line}"),
        )
    };
    // (case, edit of kyslan-pi.toml, exit code, what the line says)
    let cases: Vec<(&str, (&str, String), i32, &str)> = vec![
        (
            "duration-nan",
            ("duration_s = 0.1", "duration_s = nan".into()),
            1,
            "duration_s = NaN must be in (0, 3600] s",
        ),
        (
            "r-negative",
            motor("r_ohm = -7.0"),
            1,
            "motor.r_ohm = -7 must be in [0.000001, 1000] Ω",
        ),
        (
            "r-huge",
            motor("r_ohm = 1e300"),
            1,
            "motor.r_ohm = 1e300 must be in [0.000001, 1000] Ω",
        ),
        (
            "l-negative",
            motor("l_d_h = -0.01"),
            1,
            "motor.l_d_h = -0.01 must be in [0.000000001, 10] H",
        ),
        (
            "j-zero",
            motor("j_kgm2 = 0.0"),
            1,
            "motor.j_kgm2 = 0 must be in [0.0000000001, 1000000000] kg·m²",
        ),
        (
            "j-tiny",
            motor("j_kgm2 = 1e-12"),
            1,
            "motor.j_kgm2 = 0.000000000001 must be in [0.0000000001, 1000000000] kg·m²",
        ),
        (
            "psi-tiny",
            motor("psi_pm_wb = 1e-100"),
            1,
            "motor.psi_pm_wb = 1e-100 must be in [0.000001, 100] Wb",
        ),
        (
            "imax-huge",
            motor("i_max_a = 1e300"),
            1,
            "motor.i_max_a = 1e300 must be in [0.001, 100000] A",
        ),
        (
            "l-string",
            motor("l_d_h = \"x\""),
            1,
            "motor.l_d_h: invalid type: string \"x\", expected f64",
        ),
        (
            "pole-pairs-table",
            motor("pole_pairs = { a = 1 }"),
            1,
            "motor.pole_pairs: invalid type: map",
        ),
        (
            "motor-unknown-key",
            motor("r_ohms = 7.0"),
            1,
            "motor.r_ohms: unknown field `r_ohms`",
        ),
        (
            "preset-unknown",
            ("preset = \"kyslan2015\"", "preset = \"kyslan2016\"".into()),
            1,
            "motor.preset: unknown motor 'kyslan2016'",
        ),
        (
            "motor-missing",
            ("[motor]\npreset = \"kyslan2015\"", String::new()),
            1,
            "missing field `motor`",
        ),
        (
            "rate-1hz",
            ("sample_hz = 10000.0", "sample_hz = 1.0".into()),
            1,
            "rates.sample_hz = 1 must be in [100, 100000] Hz",
        ),
        (
            "rate-1ghz",
            ("sample_hz = 10000.0", "sample_hz = 1e9".into()),
            1,
            "rates.sample_hz = 1000000000 must be in [100, 100000] Hz",
        ),
        (
            "divider-0",
            ("speed_divider = 10", "speed_divider = 0".into()),
            1,
            "rates.speed_divider = 0 must be in 1..=1000",
        ),
        (
            "divider-nan",
            ("speed_divider = 10", "speed_divider = nan".into()),
            1,
            "rates.speed_divider: invalid type: floating point `NaN`",
        ),
        (
            "hold-huge",
            (
                "hold_samples = 3",
                "hold_samples = 99999999999999999999".into(),
            ),
            1,
            "inverter.hold_samples: invalid type: integer",
        ),
        (
            "controller-unknown",
            (
                "controller = \"pi\"\ntau_c_s",
                "controller = \"pid\"\ntau_c_s".into(),
            ),
            1,
            "current_loop.controller: unknown variant `pid`",
        ),
        (
            "observer-unknown",
            ("[observer]\n", "[observer]\nmode = \"kalman\"\n".into()),
            1,
            "observer.mode: unknown variant `kalman`",
        ),
        (
            "step-negative-time",
            (
                "{ t_s = 0.0, value = 70.0 }",
                "{ t_s = -1.0, value = 70.0 }".into(),
            ),
            1,
            "reference.speed_rad_s[0].t_s = -1 must be within [0, duration_s = 0.1] s",
        ),
        (
            "step-nan-time",
            (
                "{ t_s = 0.0, value = 70.0 }",
                "{ t_s = nan, value = 70.0 }".into(),
            ),
            1,
            "reference.speed_rad_s[0].t_s = NaN must be within",
        ),
        (
            "step-table",
            (
                "[{ t_s = 0.0, value = 70.0 }]",
                "{ t_s = 0.0, value = 70.0 }".into(),
            ),
            1,
            "reference.speed_rad_s: invalid type: map, expected a sequence",
        ),
        (
            "step-huge",
            (
                "{ t_s = 0.0, value = 70.0 }",
                "{ t_s = 0.0, value = 1e300 }".into(),
            ),
            1,
            "reference.speed_rad_s[0].value = 1e300 must be finite and within ±3665.19 rad/s",
        ),
        (
            "iq-limit-huge",
            ("i_q_max_a = 1.6", "i_q_max_a = 1e300".into()),
            1,
            "speed_loop.i_q_max_a = 1e300 must be in (0, 10 × motor.i_max_a = 16] A",
        ),
        (
            "unknown-key",
            ("[rates]\n", "[rates]\nsample_hzz = 1.0\n".into()),
            1,
            "rates.sample_hzz: unknown field `sample_hzz`",
        ),
        (
            "name-escapes",
            ("name = \"kyslan-pi\"", "name = \"../escape\"".into()),
            1,
            "name = \"../escape\" must be 1..=64 characters",
        ),
        (
            "priority-100",
            (
                "[load]",
                "[placement.plant]\ncore = 1\npriority = 100\n\n[load]".into(),
            ),
            1,
            "placement.plant.priority = 100 must be in 1..=99",
        ),
        (
            "placement-priority-256",
            (
                "[load]",
                "[placement.plant]\ncore = 1\npriority = 256\n\n[load]".into(),
            ),
            1,
            "placement.plant.priority: 256 is out of range: SCHED_FIFO priorities are 1..=99",
        ),
        (
            "placement-core-minus-1",
            (
                "[load]",
                "[placement.plant]\ncore = -1\npriority = 70\n\n[load]".into(),
            ),
            1,
            "placement.plant.core: -1 is not a CPU number (0..=1023)",
        ),
        (
            "encoder-1-count",
            (
                "[load]",
                "[sensors]\nencoder_counts_per_rev = 1\n\n[load]".into(),
            ),
            1,
            "sensors.encoder_counts_per_rev = 1 must be 0",
        ),
        (
            "stage-table-unhosted",
            (
                "[load]",
                "[stages.bogus]\nrate_hz = 1000.0\n\n[load]".into(),
            ),
            1,
            "[stages.bogus]: no process hosts a stage 'bogus'",
        ),
        (
            "expect-bad-operator",
            (
                "[motor]",
                "[[expect]]\ncheck = \"peak_current_a =< 3\"\n\n[motor]".into(),
            ),
            1,
            "[[expect]] #1: expectation 'peak_current_a =< 3': unknown operator",
        ),
        (
            "plant-step-longer-than-l-over-r",
            motor("l_d_h = 1e-7"),
            1,
            "rates.plant_substeps = 4: the plant's RK4 step 1/(rates.sample_hz × plant_substeps) = 2.500e-5 s must be at most the motor's electrical time constant min(L_d, L_q)/R = 1.429e-8 s (it would take plant_substeps = 7.001e3, above the 1000 allowed",
        ),
        (
            "plant-step-fixed-by-substeps",
            motor("l_d_h = 1e-5"),
            1,
            "min(L_d, L_q)/R = 1.429e-6 s (plant_substeps = 70 would do)",
        ),
        (
            "inject-unknown-stage",
            (
                "[motor]",
                "[[inject]]\nkind = \"kill\"\ntarget = \"nosuch\"\nat_s = 0.01\nduration_s = 0.01\n\n[motor]".into(),
            ),
            1,
            "[[inject]] kill:nosuch@0.01: unknown stage 'nosuch' (this drive's stages: plant, observer, current-loop, speed-loop)",
        ),
        (
            "inject-delay-unknown-stage",
            (
                "[motor]",
                "[[inject]]\nkind = \"delay\"\ntarget = \"pump\"\nat_s = 0.01\nduration_s = 0.01\nlatency_us = 5.0\n\n[motor]".into(),
            ),
            1,
            "unknown stage 'pump'",
        ),
        (
            "inject-drop-unpublished-topic",
            (
                "[motor]",
                "[[inject]]\nkind = \"drop\"\ntarget = \"wref\"\nat_s = 0.01\ncount = 2\n\n[motor]".into(),
            ),
            1,
            "[[inject]] drop:wref@0.01:2: no stage of this drive publishes topic 'wref'",
        ),
        (
            "inject-kill-on-sample-0",
            (
                "[motor]",
                "[[inject]]\nkind = \"kill\"\ntarget = \"plant\"\nat_s = 0.0\nduration_s = 0.01\n\n[motor]".into(),
            ),
            1,
            "[[inject]] kill:plant@0 falls on sample 0: a kill or stop must come after the drive's first sample (at or after 0.0001 s at 10000 Hz)",
        ),
        (
            "expect-nan-limit",
            (
                "[motor]",
                "[[expect]]\ncheck = \"peak_current_a <= nan\"\n\n[motor]".into(),
            ),
            1,
            "limit 'nan' must be a finite number",
        ),
    ];
    for (case, (from, to), code, needle) in cases {
        let name = format!("sc-{case}");
        let f = scenario(&name, &[(from, &to)]);
        let path = f.to_str().unwrap();
        run_refused(&name, &["--scenario", path], code, &[path, needle]);
    }
}

/// A process table for a topology file.
fn process(name: &str, stages: &[&str], extra: &str) -> String {
    let list: Vec<String> = stages.iter().map(|s| format!("\"{s}\"")).collect();
    format!(
        "[[process]]\nname = \"{name}\"\nstages = [{}]\ncpu = 1\npriority = 70\n{extra}\n",
        list.join(", ")
    )
}

/// A script in `dir` with `body`, executable or not.
fn script(dir: &Path, name: &str, body: &str, executable: bool) -> String {
    use std::os::unix::fs::PermissionsExt;
    let p = dir.join(name);
    std::fs::write(&p, format!("#!/bin/sh\n{body}\n")).unwrap();
    let mode = if executable { 0o755 } else { 0o644 };
    std::fs::set_permissions(&p, std::fs::Permissions::from_mode(mode)).unwrap();
    p.display().to_string()
}

#[test]
fn a_bad_topology_file_is_one_line_naming_file_process_and_field() {
    let dir = scratch("topo-files");
    let all = ["plant", "observer", "current-loop", "speed-loop"];
    // A user process beside the built-in stages, hosted by `exec`.
    let user = |exec: &str| {
        process("p", &all, "") + &process("u", &["pos"], &format!("exec = \"{exec}\""))
    };
    // A describe that never answers, through a child of its own: both must be gone after.
    let marker = format!("86399.{}", std::process::id());
    let hang = script(&dir, "hang.sh", &format!("sleep {marker} &\nwait"), true);
    let two_lines = script(
        &dir,
        "fails.sh",
        "echo 'line one' >&2\necho 'line two' >&2\nexit 3",
        true,
    );
    let not_exec = script(&dir, "not-exec.sh", "exit 0", false);
    let floods = script(&dir, "floods.sh", "exec yes '[]'", true);
    let no_interpreter = {
        use std::os::unix::fs::PermissionsExt;
        let p = dir.join("stage.py");
        std::fs::write(&p, "#!/nonexistent/python\nprint('[]')\n").unwrap();
        std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o755)).unwrap();
        p.display().to_string()
    };
    let cases: Vec<(&str, String, &str)> = vec![
        (
            "twice",
            process("a", &["plant", "observer"], "")
                + &process("b", &["observer", "current-loop", "speed-loop"], ""),
            "stage 'observer' is hosted twice",
        ),
        (
            "not-hosted",
            process("a", &["plant", "observer", "current-loop"], ""),
            "stage 'speed-loop' is not hosted by any process",
        ),
        (
            "unknown-stage",
            process(
                "a",
                &["plant", "observer", "current_loop", "speed-loop"],
                "",
            ),
            "unknown stage 'current_loop'",
        ),
        (
            "cpu-9999",
            process("a", &all, "").replace("cpu = 1", "cpu = 9999"),
            "process 'a': cpu = 9999 is not a CPU number (0..=1023)",
        ),
        (
            "priority-0",
            process("a", &all, "").replace("priority = 70", "priority = 0"),
            "process 'a': priority = 0 must be in 1..=99",
        ),
        // Beyond what the field's type holds: the field, the value and the range, not
        // serde's "expected u8".
        (
            "priority-256",
            process("a", &all, "").replace("priority = 70", "priority = 256"),
            ":5: process[0].priority: 256 is out of range: SCHED_FIFO priorities are 1..=99",
        ),
        (
            "priority-minus-1",
            process("a", &all, "").replace("priority = 70", "priority = -1"),
            ":5: process[0].priority: -1 is out of range: SCHED_FIFO priorities are 1..=99",
        ),
        (
            "cpu-minus-1",
            process("a", &all, "").replace("cpu = 1", "cpu = -1"),
            ":4: process[0].cpu: -1 is not a CPU number (0..=1023)",
        ),
        (
            "cpu-nan",
            process("a", &all, "").replace("cpu = 1", "cpu = nan"),
            ":4: process[0].cpu: invalid type: floating point `NaN`",
        ),
        (
            "unknown-key",
            process("a", &all, "core = 1"),
            "process[0].core: unknown field `core`",
        ),
        (
            "no-process",
            "process = []\n".into(),
            "the topology has no [[process]]",
        ),
        (
            "exec-missing",
            user("/nonexistent/drivelab-stage"),
            "process 'u': exec /nonexistent/drivelab-stage not found",
        ),
        (
            "exec-empty",
            user(""),
            "process 'u': exec = \"\" is empty and names no executable",
        ),
        // Quoted as written, not as "".
        (
            "exec-blank",
            user(" "),
            "process 'u': exec = \" \" is blank and names no executable",
        ),
        // A script whose interpreter is missing: the kernel's "No such file or directory"
        // was about a file that exists.
        (
            "exec-interpreter-missing",
            user(&no_interpreter),
            "the interpreter named in its first line (#!/nonexistent/python) was not found",
        ),
        (
            "exec-directory",
            user("/tmp"),
            "process 'u': exec /tmp is not a file",
        ),
        // Not executable, hosting built-in stages only: refused before the start, not when
        // the launcher spawns it after the other processes.
        (
            "exec-not-executable",
            process("p", &["plant"], "")
                + &process(
                    "c",
                    &["observer", "current-loop", "speed-loop"],
                    &format!("exec = \"{not_exec}\""),
                ),
            "process 'c': exec",
        ),
        (
            "describe-two-lines",
            user(&two_lines),
            "--describe failed (exit status: 3): line one / line two",
        ),
        (
            "describe-floods",
            user(&floods),
            "--describe: more than 1048576 bytes of output, not a stage list",
        ),
        (
            "describe-hangs",
            user(&hang),
            "--describe did not answer within 10 s (killed)",
        ),
    ];
    for (case, text, needle) in cases {
        let f = dir.join(format!("{case}.toml"));
        std::fs::write(&f, text).unwrap();
        let path = f.to_str().unwrap();
        run_refused(
            &format!("topo-{case}"),
            &["--topology", path],
            1,
            &[path, needle],
        );
    }
    assert!(
        processes_with(&marker).is_empty(),
        "the describe's child was left running"
    );
}

/// `--rt-strict` asks each process's executable `--check-rt` before the drive: one that does not
/// answer is killed after 10 s, with what it started, and named in one line (it hung the
/// launcher before).
#[test]
fn an_executable_that_does_not_answer_the_real_time_check_is_named_after_10_s() {
    let dir = scratch("check-rt-hangs");
    let marker = format!("86398.{}", std::process::id());
    // The stage host for every other question (`--describe`), a hang for this one.
    let host = Path::new(DRIVELAB).with_file_name("drivelab-host");
    let hangs = script(
        &dir,
        "hangs.sh",
        &format!(
            "for a in \"$@\"; do [ \"$a\" = --check-rt ] && {{ sleep {marker} & wait; }}; done\nexec '{}' \"$@\"",
            host.display()
        ),
        true,
    );
    let topo = dir.join("hangs.toml");
    std::fs::write(
        &topo,
        process("p", &["plant"], "")
            + &process(
                "c",
                &["observer", "current-loop", "speed-loop"],
                &format!("exec = \"{hangs}\""),
            ),
    )
    .unwrap();
    run_refused(
        "check-rt-hangs-run",
        &["--rt-strict", "--topology", topo.to_str().unwrap()],
        1,
        &[&format!(
            "--rt-strict: process c: {hangs} --check-rt did not answer within 10 s (killed)"
        )],
    );
    assert!(
        processes_with(&marker).is_empty(),
        "the check's child was left running"
    );
}

/// The scenario a user's stage is asked `--describe` with goes into a folder of the temp folder
/// that nobody else can have made: not through a link another user planted there (as root, the
/// drive would write the scenario over whatever the link names).
#[test]
fn the_describe_scenario_is_not_written_through_a_link_planted_in_the_temp_folder() {
    let dir = scratch("describe-tmp");
    let tmp = dir.join("tmp");
    std::fs::create_dir_all(&tmp).unwrap();
    let victim = dir.join("victim.txt");
    std::fs::write(&victim, "a file of another user\n").unwrap();
    let all = ["plant", "observer", "current-loop", "speed-loop"];
    let fails = script(&dir, "fails.sh", "echo 'no stages here' >&2\nexit 3", true);
    let topo = dir.join("user.toml");
    std::fs::write(
        &topo,
        process("p", &all, "") + &process("u", &["pos"], &format!("exec = \"{fails}\"")),
    )
    .unwrap();
    let bus = bus_id("describe-tmp");
    let out = dir.join("run");
    // The shell plants the folder under the name the launcher's pid gives (its own pid, kept
    // by exec) with a link to the victim, as another user could before the drive starts.
    let plant = format!(
        "mkdir \"$TMPDIR/drivelab-describe-$$\" && ln -s '{}' \"$TMPDIR/drivelab-describe-$$/scenario.toml\" && exec \"$0\" \"$@\"",
        victim.display()
    );
    let o = output_within(
        Command::new("sh")
            .env("TMPDIR", &tmp)
            .args(["-c", &plant, DRIVELAB])
            .args(run_args(&bus, &out))
            .args(["--clock", "lockstep", "--topology", topo.to_str().unwrap()]),
        std::time::Duration::from_secs(120),
    );
    assert_refused(
        "describe-tmp",
        &o,
        1,
        &["--describe failed (exit status: 3): no stages here"],
    );
    assert_eq!(
        std::fs::read_to_string(&victim).unwrap(),
        "a file of another user\n",
        "the scenario was written through the planted link"
    );
    // The planted folder and its link are left as they were; the drive's own scratch folder
    // is gone.
    let left: Vec<String> = std::fs::read_dir(&tmp)
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(left.len(), 1, "{left:?}");
    assert!(left[0].starts_with("drivelab-describe-"), "{left:?}");
    assert!(tmp.join(&left[0]).join("scenario.toml").is_symlink());
    assert!(!out.exists(), "a refused run made its folder");
    assert_clean(&bus);
}

#[test]
fn a_bad_expectation_is_a_usage_error_of_one_line() {
    for (case, expr, needle) in [
        (
            "op",
            "peak_current_a =< 8",
            "unknown operator (the operators are <=, <, >=, >, == or in A..B)",
        ),
        ("ne", "peak_current_a != 8", "unknown operator"),
        (
            "nan",
            "peak_current_a <= nan",
            "limit 'nan' must be a finite number within ±1e12",
        ),
        (
            "huge",
            "peak_current_a <= 1e300",
            "limit '1e300' must be a finite number within ±1e12",
        ),
        (
            "figure",
            "peak_currnt_a <= 8",
            "unknown figure 'peak_currnt_a'",
        ),
        (
            "range",
            "metrics.rise_time_ms in 9..8",
            "the range 9..8 is empty",
        ),
    ] {
        run_refused(
            &format!("expect-{case}"),
            &["--expect", expr],
            2,
            &["--expect: expectation", needle],
        );
    }
}

#[test]
fn a_bad_campaign_is_one_line_naming_file_and_field_before_any_run() {
    let dir = scratch("campaigns");
    let head = "name = \"c\"\nclock = \"lockstep\"\nduration_s = 0.05\n";
    let one = "scenarios = [\"kyslan-pi\"]\n";
    let cases: Vec<(&str, String, i32, &str)> = vec![
        (
            "no-scenarios",
            format!("{head}scenarios = []\n"),
            1,
            "scenarios = [] names no scenario to run",
        ),
        (
            "dup-scenario",
            format!("{head}scenarios = [\"kyslan-pi\", \"kyslan-pi\"]\n"),
            1,
            "scenarios: 'kyslan-pi' is listed twice",
        ),
        (
            "dup-seed",
            format!("{head}{one}seeds = [1, 1]\n"),
            1,
            "seeds: 1 is listed twice",
        ),
        (
            "dup-fault-set",
            format!("{head}{one}faults = [[\"kill:observer@0.02\"], [\"kill:observer@0.02\"]]\n"),
            1,
            "the fault set [kill:observer@0.02] is listed twice",
        ),
        (
            "seeds-empty",
            format!("{head}{one}seeds = []\n"),
            1,
            "seeds = [] gives no seed",
        ),
        (
            "seeds-string",
            format!("{head}{one}seeds = [\"1\"]\n"),
            1,
            ":5: seeds: invalid type: string \"1\", expected u64",
        ),
        (
            "unknown-fault",
            format!("{head}{one}faults = [[\"explode:observer@0.02\"]]\n"),
            1,
            "unknown fault kind 'explode'",
        ),
        (
            "unknown-key",
            format!("{head}{one}seed = [1]\n"),
            1,
            ":5: seed: unknown field `seed`",
        ),
        (
            "name-escapes",
            format!("{head}{one}").replace("name = \"c\"", "name = \"../x\""),
            1,
            "name = \"../x\" must be 1..=64 characters",
        ),
        (
            "sweep-empty",
            format!("{head}{one}[sweep]\nkinds = []\nstages = [\"observer\"]\nat_s = [0.02]\n"),
            1,
            "[sweep] kinds = [] makes no fault set",
        ),
        (
            "duration-nan",
            format!("{head}{one}").replace("duration_s = 0.05", "duration_s = nan"),
            1,
            "duration_s = NaN must be in (0, 3600] s",
        ),
        (
            "expect-operator",
            format!("{head}{one}expect = [\"peak_current_a =< 3\"]\n"),
            1,
            "expect: expectation 'peak_current_a =< 3': unknown operator",
        ),
    ];
    for (case, text, code, needle) in cases {
        let f = dir.join(format!("{case}.toml"));
        std::fs::write(&f, text).unwrap();
        let out = dir.join(format!("out-{case}"));
        let o = drivelab(&[
            "campaign",
            f.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ]);
        assert_refused(case, &o, code, &[f.to_str().unwrap(), needle]);
        assert!(!out.exists(), "{case}: the campaign started");
    }
}

/// Starts `drivelab campaign` (stdout and stderr piped) on a campaign file `<tag>.toml` in
/// its own scratch folder: one kyslan-pi scenario and a `[sweep]` of `kinds` × `stages` ×
/// `at_s`. Returns the file, the report folder asked for and the process.
fn sweep_campaign(
    tag: &str,
    kinds: &str,
    stages: &str,
    at_s: &[String],
) -> (PathBuf, PathBuf, Drive) {
    let dir = scratch(tag);
    let f = dir.join(format!("{tag}.toml"));
    std::fs::write(
        &f,
        format!(
            "name = \"c\"\nclock = \"lockstep\"\nscenarios = [\"kyslan-pi\"]\n[sweep]\nkinds = [{kinds}]\nstages = [{stages}]\nat_s = [{}]\n",
            at_s.join(", ")
        ),
    )
    .unwrap();
    let out = dir.join("out");
    let child = Command::new(DRIVELAB)
        .args([
            "campaign",
            f.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Killed if the test fails before it ends.
    (f, out, Drive::from(child))
}

#[test]
fn a_campaign_of_too_many_runs_is_refused_before_its_runs_are_built() {
    // 30 000 injection times × 2 kinds × 4 stages: 240 000 fault sets from a 270 KB file,
    // far more runs than a campaign may hold. Comparing every pair of those sets took
    // minutes.
    let at_s: Vec<String> = (1..=30_000)
        .map(|i| format!("{}", i as f64 * 1e-5))
        .collect();
    let (f, out, child) = sweep_campaign(
        "campaign-huge",
        "\"kill\", \"stop\"",
        "\"plant\", \"observer\", \"current-loop\", \"speed-loop\"",
        &at_s,
    );
    // A watchdog against a hang only.
    let o = wait(child, std::time::Duration::from_secs(60), "campaign huge");
    assert_refused(
        "huge",
        &o,
        1,
        &[
            f.to_str().unwrap(),
            "240000 runs is more than 10000; split it",
        ],
    );
    assert!(!out.exists(), "the campaign started");
}

#[test]
fn a_campaign_being_checked_stops_on_sigint_with_one_line() {
    // 10 000 kills, each checked against the scenario before the first run (about 0.6 s on
    // an idle 2-vCPU VM). SIGINT is sent as soon as the campaign catches it (its handler is
    // installed just before it reads the file), so it arrives while the file is read or the
    // runs are checked, and the check loop must end the campaign before any run starts.
    let at_s: Vec<String> = (0..10_000)
        .map(|i| format!("{:.6}", 0.0002 + f64::from(i) * 0.9e-5))
        .collect();
    let (_, out, child) = sweep_campaign("campaign-checks", "\"kill\"", "\"observer\"", &at_s);
    let caught = format!("/proc/{}/status", child.id());
    let sigint_caught = || {
        std::fs::read_to_string(&caught)
            .unwrap_or_default()
            .lines()
            .find_map(|l| l.strip_prefix("SigCgt:"))
            .and_then(|m| u64::from_str_radix(m.trim(), 16).ok())
            .is_some_and(|m| m & (1 << (libc::SIGINT - 1)) != 0)
    };
    let t = std::time::Instant::now();
    while !sigint_caught() {
        assert!(
            t.elapsed() < std::time::Duration::from_secs(30),
            "watchdog: the campaign never caught SIGINT"
        );
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    // SAFETY: signalling a child process we spawned and have not reaped.
    unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
    // A watchdog against a hang only.
    let o = wait(child, std::time::Duration::from_secs(60), "campaign checks");
    assert_refused(
        "checks",
        &o,
        1,
        &[
            "campaign",
            "interrupted (SIGINT) while checking run",
            "before any run started",
        ],
    );
    assert!(!out.join("runs").exists(), "a run was started");
}
