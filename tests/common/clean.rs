//! What a drive leaves behind: its processes and its bus files. Shared by the workspace's
//! integration tests (`tests/common/mod.rs`) and the example stages' end-to-end tests
//! (`examples/common/e2e.rs`, which includes this file with `#[path]`).

/// Processes whose command line names this bus, as "PID ARGS".
pub fn processes_on_bus(bus: &str) -> Vec<String> {
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

/// Asserts that no process and no bus file of `bus` is left.
pub fn assert_clean(bus: &str) {
    let procs = processes_on_bus(bus);
    assert!(procs.is_empty(), "processes left: {procs:?}");
    let files = drivelab_runtime::bus::leftovers(bus);
    assert!(files.is_empty(), "bus files left: {files:?}");
}
