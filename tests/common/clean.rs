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

/// What `bus` left, its processes ("PID ARGS") and its files, removed ([`remove_bus`]) once
/// they are named.
pub fn take_leftovers(bus: &str) -> (Vec<String>, Vec<String>) {
    let procs = processes_on_bus(bus);
    let files = drivelab_runtime::bus::leftovers(bus);
    if !procs.is_empty() || !files.is_empty() {
        remove_bus(bus);
    }
    (procs, files)
}

/// Asserts that no process and no bus file of `bus` is left. Whatever is left is removed
/// first, so that the failing test leaves nothing behind.
pub fn assert_clean(bus: &str) {
    let (procs, files) = take_leftovers(bus);
    assert!(procs.is_empty(), "processes left: {procs:?}");
    assert!(files.is_empty(), "bus files left: {files:?}");
}

/// SIGKILLs the processes of `bus` (waiting up to 5 s for them to go) and removes its files.
pub fn remove_bus(bus: &str) {
    let t = std::time::Instant::now();
    loop {
        let left = processes_on_bus(bus);
        if left.is_empty() || t.elapsed() > std::time::Duration::from_secs(5) {
            break;
        }
        for line in &left {
            if let Some(pid) = line.split(' ').next() {
                let _ = std::process::Command::new("kill")
                    .args(["-KILL", pid])
                    .stderr(std::process::Stdio::null())
                    .status();
            }
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    let _ = drivelab_runtime::bus::cleanup(bus);
}
