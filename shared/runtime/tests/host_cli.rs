//! The stage host's command line (`drivelab-host`), without a bus: what it hosts
//! (`--describe`) and its one-line errors. (This test also makes `cargo test` build the
//! executable that `drivelab run` starts.)

use std::process::Command;

const HOST: &str = env!("CARGO_BIN_EXE_drivelab-host");
const SCENARIO: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../scenarios/kyslan-pi.toml"
);

#[test]
fn describe_lists_no_user_stage_for_the_built_in_host() {
    let o = Command::new(HOST)
        .args(["--describe", "--scenario", SCENARIO])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(String::from_utf8_lossy(&o.stdout).trim(), "[]");
}

#[test]
fn bad_arguments_are_one_line_errors() {
    // A process the topology does not have.
    let dir = std::env::temp_dir().join(format!("drivelab-host-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let topo = dir.join("topology.json");
    std::fs::write(&topo, r#"{"processes": [], "producers": [], "stages": []}"#).unwrap();
    let o = Command::new(HOST)
        .args(["--scenario", SCENARIO, "--topology"])
        .arg(&topo)
        .args(["--process", "nope", "--bus", "hostcli1"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert_eq!(
        err.trim(),
        "nope: error: the topology has no process 'nope'"
    );
    // A malformed topology file.
    std::fs::write(&topo, "{").unwrap();
    let o = Command::new(HOST)
        .args(["--scenario", SCENARIO, "--topology"])
        .arg(&topo)
        .args(["--process", "p", "--bus", "hostcli2"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(
        err.contains("topology") && err.contains("topology.json"),
        "{err}"
    );
    // Without a process (and not --describe): a usage error.
    let o = Command::new(HOST)
        .args(["--scenario", SCENARIO])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    let _ = std::fs::remove_dir_all(&dir);
}
