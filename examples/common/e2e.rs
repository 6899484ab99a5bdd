//! End to end, shared by the example stages' tests (each includes this file with `#[path]`):
//! `drivelab run` of an example's scenario, its `exec` pointed at this build's executable,
//! under a watchdog, and the checks that nothing is left behind.
//!
//! `drivelab` and `drivelab-host` live in another package, so cargo does not build them for
//! an example's tests: `cargo test --workspace` (or `cargo build -p drivelab-services` first)
//! does. They are looked for next to the example's executable, `target/<profile>/`.
//! Timeouts here are watchdogs against hangs, never performance assertions.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

#[path = "../../tests/common/clean.rs"]
mod clean;
pub use clean::{assert_clean, remove_bus};

/// One drive at a time: they all pin to the same core.
pub static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// An example: its stage host, its scenario and the `exec` line the scenario ships with.
pub struct Example {
    /// This build's executable (`env!("CARGO_BIN_EXE_…")`).
    pub exe: &'static str,
    /// The scenario file.
    pub scenario: &'static str,
    /// The scenario's `exec = "…"` line, replaced by this build's executable.
    pub exec_line: &'static str,
    /// Prefix of scratch folders and bus ids (one letter or a short word).
    pub tag: &'static str,
}

impl Example {
    /// `drivelab`, next to the example's executable (with `drivelab-host`).
    pub fn drivelab(&self) -> PathBuf {
        let d = Path::new(self.exe).with_file_name("drivelab");
        for exe in [d.clone(), d.with_file_name("drivelab-host")] {
            assert!(
                exe.is_file(),
                "{} is missing: build it first with `cargo build -p drivelab-services` (same profile), or run `cargo test --workspace`",
                exe.display()
            );
        }
        d
    }

    /// A new empty scratch folder for test `name`.
    pub fn scratch(&self, name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!(
            "drivelab-{}-{}-{name}",
            self.tag,
            std::process::id()
        ));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    /// The bus id of test `name`: its own, so that tests can run in parallel. Two names cut
    /// to the same id (24 characters at most) fail the test instead of sharing a bus.
    pub fn bus_id(&self, name: &str) -> String {
        static ISSUED: std::sync::Mutex<Vec<(String, String)>> = std::sync::Mutex::new(Vec::new());
        let id: String = format!("{}{}{name}", self.tag, std::process::id())
            .chars()
            .filter(|c| c.is_ascii_alphanumeric())
            .take(24)
            .collect();
        let mut issued = ISSUED.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((_, other)) = issued.iter().find(|(i, n)| *i == id && n != name) {
            panic!("bus id {id} of '{name}' is that of '{other}' too");
        }
        issued.push((id.clone(), name.to_string()));
        id
    }

    /// The scenario copied into `dir` with each `(from, to)` of `edits` replaced (each must
    /// be in the file), then `exec` pointed at this build's executable (unless an edit
    /// replaced the `exec` line).
    pub fn scenario_copy(&self, dir: &Path, edits: &[(&str, &str)]) -> PathBuf {
        let mut text = std::fs::read_to_string(self.scenario).unwrap();
        let exec = format!("exec = {:?}", self.exe);
        let exec_edited = edits.iter().any(|(from, _)| *from == self.exec_line);
        let own = (!exec_edited).then_some((self.exec_line, exec.as_str()));
        for (from, to) in edits.iter().copied().chain(own) {
            assert!(text.contains(from), "{} has no '{from}'", self.scenario);
            text = text.replace(from, to);
        }
        let p = dir.join(Path::new(self.scenario).file_name().unwrap());
        std::fs::write(&p, text).unwrap();
        p
    }

    /// `drivelab run` of the scenario (with `edits`) into `<scratch>/run` with `extra`
    /// arguments, under a watchdog; its output, the run folder and the bus id.
    pub fn launch(
        &self,
        name: &str,
        extra: &[&str],
        edits: &[(&str, &str)],
    ) -> (Output, PathBuf, String) {
        self.start(name, extra, edits).wait()
    }

    /// As [`Example::launch`], without waiting for it.
    pub fn start(&self, name: &str, extra: &[&str], edits: &[(&str, &str)]) -> Started {
        let exe = self.drivelab();
        let dir = self.scratch(name);
        let sc = self.scenario_copy(&dir, edits);
        let out = dir.join("run");
        let bus = self.bus_id(name);
        let args: Vec<String> = [
            "run",
            "--scenario",
            sc.to_str().unwrap(),
            "--bus",
            &bus,
            "--out",
            out.to_str().unwrap(),
            "--no-plots",
        ]
        .iter()
        .chain(extra)
        .map(|a| a.to_string())
        .collect();
        let child = Command::new(&exe)
            .args(&args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start drivelab");
        Started {
            child: Some(child),
            out,
            bus,
            args,
        }
    }

    /// As [`Example::launch`] without edits; checks exit 0 and that nothing is left behind,
    /// and returns the run folder.
    pub fn run_with(&self, name: &str, extra: &[&str]) -> PathBuf {
        let (o, out, bus) = self.launch(name, extra, &[]);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert!(
            o.status.success(),
            "drivelab run {extra:?} failed: {stderr}"
        );
        assert_clean(&bus);
        out
    }

    /// A 3 s real-time run with `stage`'s process killed at 0.1 s; checks that the fault
    /// report names the stage and returns the run folder and its summary.
    pub fn run_killed(&self, stage: &str) -> (PathBuf, serde_json::Value) {
        let kill = format!("kill:{stage}@0.1");
        // The restarted process must be ready (and the drive recovered) before the end:
        // 2.9 s leave room for a loaded machine (a start-up takes tens of ms when idle).
        let out = self.run_with(
            "kill",
            &["--clock", "realtime", "--duration", "3.0", "--fault", &kill],
        );
        let s = summary(&out);
        assert_eq!(s["faults"][0]["service"], stage, "{}", s["faults"]);
        (out, s)
    }
}

/// A drive that [`Example::start`] started. Dropped while it runs, or while its test fails,
/// it kills the launcher and removes what its bus left (processes and files).
pub struct Started {
    child: Option<std::process::Child>,
    out: PathBuf,
    bus: String,
    args: Vec<String>,
}

impl Started {
    /// Waits for the drive under a watchdog of 300 s (on expiry it kills the launcher, its
    /// stage hosts and removes its bus files, then fails); its output, the run folder and the
    /// bus id.
    pub fn wait(mut self) -> (Output, PathBuf, String) {
        let t = Instant::now();
        let mut child = self.child.take().expect("waited once");
        while child.try_wait().unwrap().is_none() {
            if t.elapsed() > Duration::from_secs(300) {
                let _ = child.kill();
                // What the killed launcher leaves: its stage hosts and its bus files.
                remove_bus(&self.bus);
                let o = child.wait_with_output().unwrap();
                panic!(
                    "watchdog: drivelab {:?} still running after 300 s\nstderr: {}",
                    self.args,
                    String::from_utf8_lossy(&o.stderr)
                );
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let o = child.wait_with_output().unwrap();
        (o, self.out.clone(), self.bus.clone())
    }
}

impl Drop for Started {
    fn drop(&mut self) {
        let running = self.child.as_mut().is_some_and(kill_if_running);
        if running || std::thread::panicking() {
            remove_bus(&self.bus);
        }
    }
}

/// A helper process of a test (a recorder, a second launcher): killed and reaped when
/// dropped while it still runs, so that a failing test does not leave it behind.
pub struct Guarded(pub std::process::Child);

impl Drop for Guarded {
    fn drop(&mut self) {
        kill_if_running(&mut self.0);
    }
}

/// Kills and reaps `c` if it still runs; whether it did.
fn kill_if_running(c: &mut std::process::Child) -> bool {
    let running = matches!(c.try_wait(), Ok(None));
    if running {
        let _ = c.kill();
        let _ = c.wait();
    }
    running
}

/// Removes the scratch folder of a run folder `out` (called last: a failed test keeps it).
pub fn remove_scratch(out: &Path) {
    if let Some(dir) = out.parent() {
        let _ = std::fs::remove_dir_all(dir);
    }
}

/// trace.csv as named columns.
pub fn columns(path: &Path) -> std::collections::BTreeMap<String, Vec<f64>> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let names: Vec<String> = lines.next().unwrap().split(',').map(String::from).collect();
    let mut cols: Vec<Vec<f64>> = vec![Vec::new(); names.len()];
    for l in lines {
        for (c, x) in cols.iter_mut().zip(l.split(',')) {
            c.push(x.parse().unwrap_or(f64::NAN));
        }
    }
    names.into_iter().zip(cols).collect()
}

/// A Zenoh endpoint on a free local port, for a drive's `--zenoh-listen`.
pub fn local_endpoint() -> String {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    format!("tcp/127.0.0.1:{port}")
}

/// The run's summary.json.
pub fn summary(out: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap()
}
