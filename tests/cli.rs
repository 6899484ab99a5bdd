//! Snapshot tests of the help texts and the scenario catalogue: a change to what
//! users read must be deliberate. `UPDATE_SNAPSHOTS=1 cargo test --test cli` rewrites those that
//! changed and fails (review the diff, then run again); it is refused when `CI` is set.

use std::path::PathBuf;
use std::process::Command;

/// Compares `drivelab ARGS` with snapshot `name`; with `UPDATE_SNAPSHOTS` rewrites it when it
/// differs and returns its path (the caller fails after all were rewritten).
fn snapshot(name: &str, args: &[&str]) -> Option<PathBuf> {
    let o = Command::new(env!("CARGO_BIN_EXE_drivelab"))
        .args(args)
        .output()
        .unwrap();
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

#[test]
fn help_texts() {
    let mut rewritten = vec![snapshot("help", &["--help"])];
    for cmd in [
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
    ] {
        rewritten.push(snapshot(&format!("help-{cmd}"), &[cmd, "--help"]));
    }
    none_rewritten(rewritten);
}

#[test]
fn every_help_has_an_example_and_units() {
    for cmd in [
        "run", "bench", "fault", "clean", "monitor", "plot", "plant", "design", "compare",
        "doctor", "record",
    ] {
        let o = Command::new(env!("CARGO_BIN_EXE_drivelab"))
            .args([cmd, "--help"])
            .output()
            .unwrap();
        let t = String::from_utf8(o.stdout).unwrap();
        assert!(
            t.contains("Example"),
            "drivelab {cmd} --help has no example:\n{t}"
        );
    }
}

#[test]
fn scenario_catalogue() {
    none_rewritten([snapshot("scenarios", &["scenarios"])]);
}
