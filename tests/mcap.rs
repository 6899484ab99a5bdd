//! `trace.mcap`, read back by a reader drivelab did not write: the `mcap` package from PyPI
//! in the project's `.venv` (made by `scripts/setup.sh`) runs `tests/mcap_check.py`, which
//! compares every sample with `trace.csv` and the log and metadata with `summary.json`. In
//! CI (CI=true) a missing reader fails the test; elsewhere it is skipped with one line.

mod common;
use common::*;
use std::path::{Path, PathBuf};
use std::process::Command;

const REPO: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/..");

/// The venv's Python with the `mcap` package, or None (skipped, outside CI only).
fn python() -> Option<PathBuf> {
    let py = Path::new(REPO).join(".venv/bin/python");
    let ok = Command::new(&py)
        .args(["-c", "import mcap.reader"])
        .output()
        .is_ok_and(|o| o.status.success());
    if ok {
        return Some(py);
    }
    let why = format!(
        "{} cannot import the mcap package: run scripts/setup.sh",
        py.display()
    );
    assert!(std::env::var("CI").as_deref() != Ok("true"), "{why}");
    not_checked("mcap", &why);
    None
}

/// Runs the Python reader on run folder `dir` with `flags`; asserts that it found every
/// sample equal.
fn check(py: &Path, dir: &Path, flags: &[&str]) {
    let o = Command::new(py)
        .arg(Path::new(REPO).join("tests/mcap_check.py"))
        .arg(dir)
        .args(flags)
        .output()
        .expect("run mcap_check.py");
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{out}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(out.starts_with("mcap_check: OK"), "{out}");
    eprintln!("{}", out.trim());
}

#[test]
fn every_sample_of_trace_mcap_read_with_the_python_mcap_package_equals_trace_csv() {
    let Some(py) = python() else { return };
    let _g = serial();
    // A killed current loop: supervisor events and a fault report for the log.
    let (dir, summary) = run_ok(
        "lockstep",
        &[
            "--clock",
            "lockstep",
            "--duration",
            "2.5",
            "--fault",
            "kill:current-loop@1.2",
        ],
    );
    assert!(!summary["faults"].as_array().unwrap().is_empty());
    check(&py, &dir, &["--wall", "--services"]);
}

#[test]
fn a_real_time_run_has_wall_times_and_a_latency_message_per_second() {
    let Some(py) = python() else { return };
    let _g = serial();
    let (dir, _) = run_ok("realtime", &["--duration", "2.2"]);
    check(&py, &dir, &["--wall", "--services", "--cycle"]);
}

#[test]
fn export_writes_trace_mcap_for_an_older_run_folder() {
    let Some(py) = python() else { return };
    let _g = serial();
    let (dir, _) = run_ok("export", &["--clock", "lockstep", "--duration", "0.5"]);
    // The run's own trace.mcap is not replaced without --force: one line, the file as it was.
    let own = std::fs::read(dir.join("trace.mcap")).unwrap();
    let o = drivelab(&["export", dir.to_str().unwrap(), "--mcap"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(
        err.contains("trace.mcap exists") && err.contains("--force"),
        "{err}"
    );
    assert_eq!(std::fs::read(dir.join("trace.mcap")).unwrap(), own);
    let o = drivelab(&["export", dir.to_str().unwrap(), "--mcap", "--force"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    check(&py, &dir, &[]);
    // And a run without one (an older run's folder) gets one.
    std::fs::remove_file(dir.join("trace.mcap")).unwrap();
    let o = drivelab(&["export", dir.to_str().unwrap(), "--mcap"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    check(&py, &dir, &[]);
}

#[test]
fn export_of_a_folder_without_trace_csv_is_a_one_line_error() {
    let dir = scratch("empty");
    let o = drivelab(&["export", dir.to_str().unwrap(), "--mcap"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("has no trace.csv"), "{err}");
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(!dir.join("trace.mcap").exists());
}

/// A run folder `tag` with the scenario and summary of a short lockstep run and a synthetic
/// `trace.csv` of `rows` samples (its first row's values, k and t counting up), long enough
/// that reading it takes a while; its summary says `rows` samples.
fn big_run_folder(tag: &str, rows: u64) -> PathBuf {
    let (run, mut summary) = run_ok(tag, &["--clock", "lockstep", "--duration", "0.05"]);
    let dir = scratch(&format!("{tag}-big"));
    std::fs::copy(run.join("scenario.toml"), dir.join("scenario.toml")).unwrap();
    summary["samples"] = rows.into();
    std::fs::write(dir.join("summary.json"), summary.to_string()).unwrap();
    let text = std::fs::read_to_string(run.join("trace.csv")).unwrap();
    let mut lines = text.lines();
    let header = lines.next().unwrap();
    let first: Vec<&str> = lines.next().unwrap().split(',').collect();
    let cols: Vec<&str> = header.split(',').collect();
    let (ik, it) = (
        cols.iter().position(|c| *c == "k").unwrap(),
        cols.iter().position(|c| *c == "t").unwrap(),
    );
    let mut w = std::io::BufWriter::new(std::fs::File::create(dir.join("trace.csv")).unwrap());
    use std::io::Write;
    writeln!(w, "{header}").unwrap();
    let mut row = first.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    for k in 0..rows {
        row[ik] = k.to_string();
        row[it] = format!("{}", k as f64 * 1e-4);
        writeln!(w, "{}", row.join(",")).unwrap();
    }
    w.into_inner().unwrap().sync_all().unwrap();
    dir
}

/// Starts `drivelab ARGS`, waits until `ready` holds (watchdog 60 s; fails if it ends
/// first), sends it SIGINT and returns what it printed.
fn interrupted_when(args: &[&str], ready: impl Fn(u32) -> bool) -> std::process::Output {
    let mut child: Drive = Command::new(DRIVELAB)
        .args(args)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap()
        .into();
    let pid = child.id();
    let t = std::time::Instant::now();
    while !ready(pid) {
        assert!(
            child.try_wait().unwrap().is_none(),
            "drivelab {args:?} ended before it could be interrupted"
        );
        assert!(
            t.elapsed() < std::time::Duration::from_secs(60),
            "watchdog: drivelab {args:?} never got ready"
        );
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    // SAFETY: signalling a child process this test spawned (not yet reaped).
    unsafe { libc::kill(pid as i32, libc::SIGINT) };
    child.wait_for_exit(std::time::Duration::from_secs(60), "drivelab after SIGINT")
}

/// The one stderr line of an interrupted command: exit code 1, no panic.
fn one_error_line(o: &std::process::Output) -> String {
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert_eq!(o.status.code(), Some(1), "{:?}: {err}", o.status);
    assert!(!err.contains("panicked"), "{err}");
    assert_eq!(err.lines().count(), 1, "not one line: {err}");
    err
}

#[test]
fn an_export_stopped_by_sigint_says_how_far_it_got_and_leaves_no_file() {
    let _g = serial();
    let rows = 1_500_000;
    let dir = big_run_folder("export-sigint", rows);
    let part = dir.join("trace.mcap.part");
    let o = interrupted_when(&["export", dir.to_str().unwrap(), "--mcap"], |_| {
        part.exists()
    });
    let err = one_error_line(&o);
    assert!(
        err.starts_with("drivelab: error: export interrupted (SIGINT) after "),
        "{err}"
    );
    assert!(
        err.contains(&format!(" of {rows} rows of ")) && err.contains("; nothing written"),
        "{err}"
    );
    assert!(!part.exists(), "{} left", part.display());
    assert!(!dir.join("trace.mcap").exists(), "trace.mcap written");
}

#[test]
fn a_plot_stopped_by_sigint_says_so_in_one_line_and_draws_nothing() {
    let _g = serial();
    let dir = big_run_folder("plot-sigint", 1_500_000);
    let out = dir.join("figures");
    let trace = dir.join("trace.csv");
    // Once plot holds trace.csv open, it is reading it.
    let reading = |pid: u32| {
        std::fs::read_dir(format!("/proc/{pid}/fd"))
            .into_iter()
            .flatten()
            .flatten()
            .any(|fd| std::fs::read_link(fd.path()).is_ok_and(|p| p == trace))
    };
    let o = interrupted_when(
        &[
            "plot",
            dir.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        reading,
    );
    let err = one_error_line(&o);
    assert!(
        err.starts_with("drivelab: error: plot interrupted (SIGINT) after reading "),
        "{err}"
    );
    assert!(err.contains("; nothing written"), "{err}");
    assert!(!out.exists(), "{} made", out.display());
}
