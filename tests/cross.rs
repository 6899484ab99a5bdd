//! The embedded target: the runner that prefixes every process the launcher starts, and the
//! aarch64 and armv7 builds (`scripts/cross.sh TRIPLE`) run under qemu-user, whose lockstep
//! traces must equal the x86_64 ones byte for byte, whose doctor must read this machine's
//! files without failing, and whose system-call audit fails in one line (qemu-user refuses a
//! guest's seccomp filter).
//!
//! Those tests need the target's Rust standard library, Debian's cross compiler and
//! qemu-user (`scripts/setup.sh` installs them where it can, through `scripts/cross.sh
//! --tools-only`). Without them each says in one line what is missing and does not run.
//! With them it builds the two binaries (release, `--no-default-features`, into
//! `target/TRIPLE/release`, as the script does; a no-op when they are up to date).

mod common;

use common::*;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::OnceLock;
use std::time::Duration;

/// A script that logs its arguments to the file named first and then execs the rest.
fn logging_runner(dir: &Path) -> (String, PathBuf) {
    let script = dir.join("log-runner.sh");
    std::fs::write(
        &script,
        "#!/bin/sh\nlog=$1\nshift\necho \"$*\" >> \"$log\"\nexec \"$@\"\n",
    )
    .unwrap();
    let log = dir.join("runner.log");
    (format!("sh {} {}", script.display(), log.display()), log)
}

fn lines(p: &Path) -> Vec<String> {
    std::fs::read_to_string(p)
        .unwrap_or_default()
        .lines()
        .map(String::from)
        .collect()
}

/// The processes the runner started (`lines` of its log), without the one question the
/// launcher asks the built-in host through it before the run (`--describe`), which must
/// come exactly once.
fn hosts_started(log: &Path) -> Vec<String> {
    let (asked, started): (Vec<String>, Vec<String>) = lines(log)
        .into_iter()
        .partition(|l| l.contains("--describe"));
    assert_eq!(asked.len(), 1, "{asked:?}");
    assert!(asked[0].contains("drivelab-host"), "{asked:?}");
    started
}

#[test]
fn the_runner_prefixes_every_stage_host_and_changes_no_sample() {
    let _g = serial();
    let dir = scratch("runner");
    let (runner, log) = logging_runner(&dir);
    let plain = run_ok("runner-plain", &["--clock", "lockstep", "--no-rt"]).0;
    let (through, summary) = run_ok(
        "runner-flag",
        &["--clock", "lockstep", "--no-rt", "--runner", &runner],
    );
    // One line per process of the default topology, each the stage host with its process.
    let started = hosts_started(&log);
    let procs: Vec<&str> = summary["processes"]
        .as_object()
        .expect("processes")
        .keys()
        .map(String::as_str)
        .collect();
    assert_eq!(started.len(), procs.len(), "{started:?}");
    for p in &procs {
        assert!(
            started
                .iter()
                .any(|l| l.contains("drivelab-host") && l.contains(&format!("--process {p} "))),
            "no process {p} in {started:?}"
        );
    }
    assert_eq!(
        std::fs::read(plain.join("trace.csv")).unwrap(),
        std::fs::read(through.join("trace.csv")).unwrap()
    );

    // DRIVELAB_RUNNER does the same when --runner is not given.
    std::fs::remove_file(&log).unwrap();
    let bus = bus_id("runner-env");
    let out = dir.join("env");
    let o = Command::new(DRIVELAB)
        .args(["run", "--clock", "lockstep", "--no-rt", "--no-plots"])
        .args(["--topology", "one-process", "--bus", &bus, "--out"])
        .arg(&out)
        .env("DRIVELAB_RUNNER", &runner)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let o = wait(
        Drive::on_bus(o, &bus),
        Duration::from_secs(120),
        "drivelab run with DRIVELAB_RUNNER",
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_clean(&bus);
    assert_eq!(hosts_started(&log).len(), 1, "{:?}", lines(&log));
}

#[test]
fn a_restarted_process_goes_through_the_runner_too() {
    let _g = serial();
    let dir = scratch("runner-restart-script");
    let (runner, log) = logging_runner(&dir);
    let (_, summary) = run_ok(
        "runner-restart",
        &[
            "--duration",
            "0.3",
            "--no-rt",
            "--fault",
            "kill:observer@0.1",
            "--runner",
            &runner,
        ],
    );
    let started = hosts_started(&log);
    let rejoined: Vec<_> = started.iter().filter(|l| l.contains("--rejoin")).collect();
    assert_eq!(rejoined.len(), 1, "{started:?}");
    assert!(rejoined[0].contains("--process observer "), "{started:?}");
    assert_eq!(started.len(), 5, "{started:?}");
    assert_eq!(summary["faults"].as_array().map(Vec::len), Some(1));
}

#[test]
fn a_bad_runner_is_one_line_and_leaves_nothing() {
    let dir = scratch("bad-runner");
    let bus = bus_id("bad-runner");
    let out = dir.join("run");
    let o = drivelab(
        &[
            &run_args(&bus, &out)[..],
            &["--runner", " ", "--clock", "lockstep"],
        ]
        .concat(),
    );
    // A command line wrong in itself: a usage error.
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("--runner: the runner is empty"), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(!out.exists(), "an empty runner's run made its folder");
    // In process there is no process to put a runner in front of: a usage error too.
    let o = drivelab(
        &[
            &run_args(&bus, &out)[..],
            &["--runner", "/usr/bin/env", "--clock", "inprocess"],
        ]
        .concat(),
    );
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("--runner needs a clock that starts processes (realtime or lockstep)")
            && err.trim().lines().count() == 1,
        "{err}"
    );
    assert!(
        !out.exists(),
        "an in-process run with a runner made its folder"
    );

    let with_runner = |runner: &str| {
        drivelab(&[
            "run",
            "--clock",
            "lockstep",
            "--no-rt",
            "--no-plots",
            "--bus",
            &bus,
            "--out",
            out.to_str().unwrap(),
            "--runner",
            runner,
        ])
    };
    let o = with_runner("/nonexistent/runner --flag");
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains(
            "the runner '/nonexistent/runner --flag' cannot be started: /nonexistent/runner is not an executable file"
        ) && err.trim().lines().count() == 1,
        "{err}"
    );
    // Refused before the run: no folder.
    assert!(!out.exists(), "the refused run made its folder");
    assert_clean(&bus);
    // A runner that starts but runs nothing (or not a stage host): the built-in host does
    // not answer through it when asked before the run, and the error says so in words,
    // in one line, with nothing made.
    for (runner, why) in [
        ("false", "--describe failed (exit status: 1)"),
        ("true", "--describe: not a stage list"),
    ] {
        let o = with_runner(runner);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{err}");
        assert!(
            err.contains(&format!(
                "process 'plant' (started through the runner '{runner}'): "
            )) && err.contains(why)
                && !err.contains("ExitStatus(")
                && err.trim().lines().count() == 1,
            "{err}"
        );
        assert!(!out.exists(), "{runner}: the refused run made its folder");
        assert_clean(&bus);
    }
}

/// An ARM target this test builds for and runs under qemu-user (no binfmt handler is
/// registered, so every process is started through its runner).
struct Arm {
    triple: &'static str,
    /// Debian's cross compiler (the linker in .cargo/config.toml).
    gcc: &'static str,
    qemu: &'static str,
    /// The target's C library tree, qemu's `-L`.
    root: &'static str,
    /// What the guest's uname says: the kernel line of its doctor.
    machine: &'static str,
    built: OnceLock<Result<PathBuf, String>>,
}

impl Arm {
    /// `qemu-… -L /usr/…`: the runner of every process the launcher starts.
    fn runner(&self) -> String {
        format!("{} -L {}", self.qemu, self.root)
    }

    /// The release binaries, built once per test binary; Err(why) when the toolchain is
    /// absent (then the reason says what is missing).
    fn build(&self) -> &Result<PathBuf, String> {
        self.built.get_or_init(|| {
            let on_path = |c: &str| {
                Command::new("sh")
                    .args(["-c", &format!("command -v {c}")])
                    .output()
                    .is_ok_and(|o| o.status.success())
            };
            let sysroot = Command::new("rustc")
                .args(["--print", "sysroot"])
                .output()
                .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
                .unwrap_or_default();
            let missing: Vec<&str> = [
                (
                    Path::new(&sysroot)
                        .join("lib/rustlib")
                        .join(self.triple)
                        .is_dir(),
                    "the Rust target",
                ),
                (on_path(self.gcc), self.gcc),
                (on_path(self.qemu), self.qemu),
                (Path::new(self.root).join("lib").is_dir(), self.root),
            ]
            .into_iter()
            .filter(|(ok, _)| !ok)
            .map(|(_, what)| what)
            .collect();
            if !missing.is_empty() {
                return Err(format!(
                    "not run: {} missing (scripts/cross.sh {} installs them)",
                    missing.join(", "),
                    self.triple
                ));
            }
            let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
            let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
            let o = Command::new(cargo)
                .current_dir(&root)
                .args([
                    "build",
                    "--release",
                    "--target",
                    self.triple,
                    "--no-default-features",
                ])
                .args(["-p", "drivelab-runtime", "--bin", "drivelab-host"])
                .args(["-p", "drivelab-services", "--bin", "drivelab"])
                .stdout(Stdio::null())
                .stderr(Stdio::piped())
                .output()
                .map_err(|e| format!("cannot run cargo: {e}"))?;
            if !o.status.success() {
                // A toolchain that is there but does not build is a failure, not a skip.
                panic!(
                    "the {} build failed:\n{}",
                    self.triple,
                    String::from_utf8_lossy(&o.stderr)
                );
            }
            Ok(root.join("target").join(self.triple).join("release"))
        })
    }

    /// The build's directory, or None after printing why the test does not run.
    fn build_or_skip(&self, test: &str) -> Option<PathBuf> {
        match self.build() {
            Ok(d) => Some(d.clone()),
            Err(why) => {
                not_checked(&format!("{test} ({})", self.triple), why);
                None
            }
        }
    }

    /// `drivelab` of this build under qemu-user, with a watchdog.
    fn drivelab(&self, bin: &Path, args: &[&str], watchdog: Duration) -> Output {
        let child = Command::new(self.qemu)
            .args(["-L", self.root])
            .arg(bin.join("drivelab"))
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("start {}: {e}", self.qemu));
        wait(
            child,
            watchdog,
            &format!("{} drivelab {args:?}", self.triple),
        )
    }
}

static AARCH64: Arm = Arm {
    triple: "aarch64-unknown-linux-gnu",
    gcc: "aarch64-linux-gnu-gcc",
    qemu: "qemu-aarch64",
    root: "/usr/aarch64-linux-gnu",
    machine: "aarch64",
    built: OnceLock::new(),
};

static ARMV7: Arm = Arm {
    triple: "armv7-unknown-linux-gnueabihf",
    gcc: "arm-linux-gnueabihf-gcc",
    qemu: "qemu-arm",
    root: "/usr/arm-linux-gnueabihf",
    machine: "armv7l",
    built: OnceLock::new(),
};

/// Where two traces first differ: "line N, column NAME: A vs B".
fn first_difference(a: &str, b: &str) -> String {
    let header: Vec<&str> = a.lines().next().unwrap_or("").split(',').collect();
    for (n, (la, lb)) in a.lines().zip(b.lines()).enumerate() {
        if la != lb {
            for (i, (x, y)) in la.split(',').zip(lb.split(',')).enumerate() {
                if x != y {
                    let col = header.get(i).copied().unwrap_or("?");
                    return format!("line {}, column {col}: {x} vs {y}", n + 1);
                }
            }
            return format!("line {}: {la} vs {lb}", n + 1);
        }
    }
    format!(
        "lengths {} vs {} lines",
        a.lines().count(),
        b.lines().count()
    )
}

/// Each shipped scenario of the three papers in lockstep on `arm` under qemu-user: its
/// trace must equal the x86_64 one byte for byte (the maths is IEEE-754 arithmetic and the
/// pure-Rust libm, not the platform's).
fn lockstep_traces_equal_the_x86_64_ones(arm: &Arm, test: &str) {
    let Some(bin) = arm.build_or_skip(test) else {
        return;
    };
    let _g = serial();
    let runner = arm.runner();
    for sc in ["kyslan-pi", "low-rst-sensorless", "miyajima-polar-400rpm"] {
        // Each ARM test runs its own x86_64 reference (its own bus and folder).
        let (x86, _) = run_ok(
            &format!("x86-{}-{sc}", arm.machine),
            &["--clock", "lockstep", "--scenario", sc],
        );
        let dir = scratch(&format!("{}-{sc}", arm.machine));
        let bus = bus_id(&format!("{}-{sc}", arm.machine));
        let out = dir.join("run");
        let o = arm.drivelab(
            &bin,
            &[
                "run",
                "--clock",
                "lockstep",
                "--scenario",
                sc,
                "--no-rt",
                "--bus",
                &bus,
                "--out",
                out.to_str().unwrap(),
                "--runner",
                &runner,
            ],
            Duration::from_secs(300),
        );
        assert!(
            o.status.success(),
            "{sc} under {}: {}",
            arm.qemu,
            String::from_utf8_lossy(&o.stderr)
        );
        assert_clean(&bus);
        let a = std::fs::read_to_string(x86.join("trace.csv")).unwrap();
        let b = std::fs::read_to_string(out.join("trace.csv")).unwrap();
        assert!(a.lines().count() > 100, "{sc}: a short trace");
        assert!(
            a == b,
            "{sc}: the {} trace differs from the x86_64 one at {}",
            arm.triple,
            first_difference(&a, &b)
        );
    }
}

#[test]
fn an_aarch64_lockstep_trace_equals_the_x86_64_one_byte_for_byte() {
    lockstep_traces_equal_the_x86_64_ones(
        &AARCH64,
        "an_aarch64_lockstep_trace_equals_the_x86_64_one_byte_for_byte",
    );
}

#[test]
fn an_armv7_lockstep_trace_equals_the_x86_64_one_byte_for_byte() {
    lockstep_traces_equal_the_x86_64_ones(
        &ARMV7,
        "an_armv7_lockstep_trace_equals_the_x86_64_one_byte_for_byte",
    );
}

/// `drivelab doctor` of the `arm` build under qemu-user reads this machine's files without
/// failing, lists the checks a board needs, and its kernel line is the guest's.
fn doctor_runs_under_qemu(arm: &Arm, test: &str) {
    let Some(bin) = arm.build_or_skip(test) else {
        return;
    };
    let o = arm.drivelab(&bin, &["doctor", "--json"], Duration::from_secs(60));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    let checks: serde_json::Value = serde_json::from_slice(&o.stdout).expect("doctor --json");
    let names: Vec<&str> = checks
        .as_array()
        .expect("a list of checks")
        .iter()
        .map(|c| c["name"].as_str().unwrap())
        .collect();
    for want in [
        "governor",
        "cpufreq limits",
        "cpuidle",
        "isolated cpus",
        "rt throttling",
        "clocksource",
    ] {
        assert!(names.contains(&want), "no '{want}' in {names:?}");
    }
    let kernel = checks
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["name"] == "kernel")
        .expect("kernel check");
    assert!(
        kernel["value"]
            .as_str()
            .unwrap_or("")
            .contains(&format!("({})", arm.machine)),
        "{kernel}"
    );
}

#[test]
fn doctor_runs_under_qemu_and_reads_the_arm_checks() {
    doctor_runs_under_qemu(&AARCH64, "doctor_runs_under_qemu_and_reads_the_arm_checks");
}

#[test]
fn the_armv7_doctor_runs_under_qemu_arm() {
    doctor_runs_under_qemu(&ARMV7, "the_armv7_doctor_runs_under_qemu_arm");
}

/// The system-call audit under qemu-user: the emulator refuses a guest's seccomp filter, so
/// the run fails with one line that names the audit and the emulator as a possible cause,
/// and leaves nothing behind.
#[test]
fn the_audit_under_qemu_user_is_refused_in_one_line() {
    let test = "the_audit_under_qemu_user_is_refused_in_one_line";
    let Some(bin) = AARCH64.build_or_skip(test) else {
        return;
    };
    let dir = scratch("qemu-audit");
    let bus = bus_id("qemu-audit");
    let out = dir.join("run");
    let o = AARCH64.drivelab(
        &bin,
        &[
            "run",
            "--clock",
            "lockstep",
            "--no-rt",
            "--duration",
            "0.2",
            "--audit-syscalls",
            "--bus",
            &bus,
            "--out",
            out.to_str().unwrap(),
            "--runner",
            &AARCH64.runner(),
        ],
        Duration::from_secs(120),
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    let refusals: Vec<&str> = err
        .lines()
        .filter(|l| l.contains("error: --audit-syscalls:"))
        .collect();
    assert!(!refusals.is_empty(), "no host refused the audit: {err}");
    for l in &refusals {
        assert!(
            l.contains("seccomp filter was refused") && l.contains("qemu-user"),
            "{l}"
        );
    }
    // The drive's own error: one line, the failed process's (each refusing host names
    // itself on its own line before it).
    let errors: Vec<&str> = err
        .lines()
        .filter(|l| l.starts_with("drivelab: error:"))
        .collect();
    assert_eq!(errors.len(), 1, "{err}");
    assert!(
        errors[0].starts_with("drivelab: error: process ") && errors[0].contains(" failed"),
        "{err}"
    );
    assert_clean(&bus);
}
