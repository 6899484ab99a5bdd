//! Snapshot tests of the help texts and the scenario catalogue: a change to what
//! users read must be deliberate. `UPDATE_SNAPSHOTS=1 cargo test --test cli` rewrites them.

use std::path::PathBuf;
use std::process::Command;

fn snapshot(name: &str, args: &[&str]) {
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
    if std::env::var_os("UPDATE_SNAPSHOTS").is_some() {
        std::fs::write(&file, &got).unwrap();
        return;
    }
    let want = std::fs::read_to_string(&file)
        .unwrap_or_else(|_| panic!("{} missing: run with UPDATE_SNAPSHOTS=1", file.display()));
    assert_eq!(
        got, want,
        "drivelab {args:?} changed; review and run with UPDATE_SNAPSHOTS=1"
    );
}

#[test]
fn help_texts() {
    snapshot("help", &["--help"]);
    for cmd in [
        "run",
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
    ] {
        snapshot(&format!("help-{cmd}"), &[cmd, "--help"]);
    }
}

#[test]
fn every_help_has_an_example_and_units() {
    for cmd in [
        "run", "bench", "fault", "clean", "monitor", "plot", "plant", "design", "compare", "doctor",
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
    snapshot("scenarios", &["scenarios"]);
}
