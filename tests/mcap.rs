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
    eprintln!("skipped: {why}");
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
