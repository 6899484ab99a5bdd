//! `drivelab monitor` driven through tmux: it attaches to a running drive, shows the
//! services, the traces and the event log, asks before it injects a fault, and leaves the
//! terminal as it found it. Each test has its own bus and tmux server and checks that nothing
//! is left behind. Times are watchdogs only: the drives are held (a lockstep drive by
//! freezing its plant) or ended (a real-time drive by SIGTERM) on the test's events, so
//! they last as long as the checks need, however fast or slow the machine.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

mod common;
use common::*;

/// A private tmux server (its own socket) holding one pane that runs the monitor.
struct Tmux {
    socket: String,
}

impl Tmux {
    fn start(socket: &str, cmd: &str) -> Self {
        let t = Self {
            socket: socket.to_string(),
        };
        let ok = Command::new("tmux")
            .args([
                "-L",
                socket,
                "-f",
                "/dev/null",
                "new-session",
                "-d",
                "-x",
                "150",
                "-y",
                "45",
            ])
            // The shell prints the monitor's exit status on the restored screen and keeps
            // the pane open so that it can be read.
            .arg(format!("{cmd}; echo \"monitor exit status $?\"; sleep 600"))
            .status()
            .unwrap_or_else(|e| {
                panic!("cannot run tmux ({e}): install it with `bash scripts/setup.sh`")
            });
        assert!(ok.success(), "tmux new-session failed");
        t
    }

    fn tmux(&self, args: &[&str]) -> String {
        let o = Command::new("tmux")
            .args(["-L", &self.socket])
            .args(args)
            .output()
            .expect("tmux");
        String::from_utf8_lossy(&o.stdout).into_owned()
    }

    fn screen(&self) -> String {
        self.tmux(&["capture-pane", "-p"])
    }

    fn keys(&self, keys: &str) {
        self.tmux(&["send-keys", keys]);
    }

    /// Waits until the screen contains every one of `words`; returns it.
    fn wait_for(&self, words: &[&str], watchdog: Duration) -> String {
        let t = Instant::now();
        loop {
            let s = self.screen();
            if words.iter().all(|w| s.contains(w)) {
                return s;
            }
            assert!(
                t.elapsed() < watchdog,
                "watchdog: screen never showed {words:?} within {watchdog:?}:\n{s}"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// The monitor's exit status, once the shell around it has printed it.
    fn wait_exit(&self, watchdog: Duration) -> i32 {
        let s = self.wait_for(&["monitor exit status "], watchdog);
        let rest = &s[s.find("monitor exit status ").unwrap() + 20..];
        rest.split_whitespace().next().unwrap().parse().unwrap()
    }
}

impl Drop for Tmux {
    fn drop(&mut self) {
        let _ = Command::new("tmux")
            .args(["-L", &self.socket, "kill-server"])
            .stderr(Stdio::null())
            .status();
    }
}

/// Waits until `drivelab monitor --print` can attach (the supervisor publishes its view).
fn wait_attachable(bus: &str) -> String {
    let t = Instant::now();
    loop {
        let o = drivelab(&["monitor", "--bus", bus, "--print"]);
        if o.status.success() {
            return String::from_utf8(o.stdout).unwrap();
        }
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "watchdog: monitor could not attach within 60 s: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn monitor_cmd(bus: &str) -> String {
    format!("{DRIVELAB} monitor --bus {bus}")
}

/// Sends `sig` to `pid`, a process of this test's own drive.
fn signal(pid: i32, sig: i32) {
    // SAFETY: a signal to a process of this test's own drive.
    assert_eq!(unsafe { libc::kill(pid, sig) }, 0, "kill({pid}, {sig})");
}

/// A lockstep drive held still: its plant (the source, which every other stage waits for)
/// is stopped; dropping this resumes it, also when the test fails.
struct Held(i32);

impl Held {
    /// Holds the drive on `bus` once every stage has published a status and is alive, as
    /// the supervisor's view shows (the first status comes with a stage's first sample).
    fn once_all_report(bus: &str) -> Self {
        use drivelab_runtime::telemetry::ProcState;
        wait_for_view(bus, "show four live stages with a status each", |v| {
            v.stages() == 4
                && v.services[..4]
                    .iter()
                    .all(|s| s.has_status == 1 && ProcState::from_u32(s.state) == ProcState::Alive)
        });
        let pid = process_pid(bus, "plant");
        signal(pid, libc::SIGSTOP);
        Self(pid)
    }
}

impl Drop for Held {
    fn drop(&mut self) {
        signal(self.0, libc::SIGCONT);
    }
}

#[test]
fn monitor_shows_a_lockstep_drive_refuses_faults_and_restores_the_terminal() {
    let _serial = serial();
    let bus = bus_id("lock");
    let out = scratch("lock").join("run");
    // 30 s of drive (3·10^5 samples, 10–15 s in lockstep on a 2-core VM) after the first
    // statuses: far more than the moment the test takes to hold it. (With 10 s, once in a
    // CI run, the drive had run to its end before the hold.)
    let drive = Drive::start(&bus, &out, &["--clock", "lockstep", "--duration", "30"]);
    let held = Held::once_all_report(&bus);
    let printed = wait_attachable(&bus);
    assert!(
        printed.contains("lockstep") && printed.contains("kyslan-pi"),
        "{printed}"
    );
    let tmux = Tmux::start(&bus, &monitor_cmd(&bus));
    // Every service reports: a state, a rate and its histograms.
    let s = tmux.wait_for(
        &[
            &format!("bus {bus}"),
            "kyslan-pi",
            "lockstep",
            "current-loop",
            "speed-loop",
            "speed ω",
            "currents i_d",
            "supervisor events",
        ],
        Duration::from_secs(30),
    );
    let rows: Vec<&str> = s
        .lines()
        .filter(|l| {
            ["plant ", "observer ", "current-loop ", "speed-loop "]
                .iter()
                .any(|n| l.contains(n))
                && l.contains("alive")
        })
        .collect();
    assert_eq!(rows.len(), 4, "four live services expected:\n{s}");
    // Each has its figures ("–" stands for each of them until a stage's first status).
    for r in &rows {
        assert!(
            !r.split_whitespace().any(|w| w == "–"),
            "a service published no status:\n{s}"
        );
    }
    assert!(s.contains("not measured in lockstep"), "{s}");
    // Selecting a service and asking for a fault in lockstep is refused with a reason.
    tmux.keys("2");
    tmux.wait_for(&["select (observer)"], Duration::from_secs(10));
    tmux.keys("k");
    tmux.wait_for(
        &["faults need a real-time drive (this one runs in lockstep)"],
        Duration::from_secs(10),
    );
    // q leaves, with exit status 0, and the terminal is back on its normal screen.
    tmux.keys("q");
    assert_eq!(tmux.wait_exit(Duration::from_secs(10)), 0);
    let after = tmux.screen();
    assert!(
        !after.contains("supervisor events"),
        "the monitor's screen is still shown after it exited:\n{after}"
    );
    drop(held);
    let o = wait(drive, Duration::from_secs(600), "drive");
    assert!(
        o.status.success(),
        "drive failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    drop(tmux);
    // kill-server hangs up the pane's shell; give it a moment to go.
    assert_clean_within(&bus, Duration::from_secs(5));
}

#[test]
fn a_fault_from_the_monitor_is_confirmed_injected_logged_and_reported() {
    let _serial = serial();
    let bus = bus_id("rt");
    let out = scratch("rt").join("run");
    // Longer than the test needs: it ends the drive itself (SIGTERM) once the fault is
    // through; the duration only bounds a test that hangs.
    let drive = Drive::start(&bus, &out, &["--duration", "60"]);
    wait_attachable(&bus);
    let tmux = Tmux::start(&bus, &monitor_cmd(&bus));
    tmux.wait_for(&["realtime", "speed-loop"], Duration::from_secs(30));
    tmux.keys("3");
    tmux.wait_for(&["select (current-loop)"], Duration::from_secs(10));
    // The first request is cancelled: nothing happens.
    tmux.keys("k");
    tmux.wait_for(
        &["kill current-loop (SIGKILL)? press y to confirm"],
        Duration::from_secs(10),
    );
    tmux.keys("n");
    tmux.wait_for(&["cancelled"], Duration::from_secs(10));
    // The second is confirmed: the supervisor kills, logs, restarts.
    tmux.keys("k");
    tmux.wait_for(&["press y to confirm"], Duration::from_secs(10));
    tmux.keys("y");
    let s = tmux.wait_for(
        &[
            "inject current-loop: kill (requested by pid",
            "exited current-loop",
            "restarted current-loop",
        ],
        Duration::from_secs(30),
    );
    assert!(
        s.contains("asked the supervisor to kill current-loop"),
        "{s}"
    );
    // The drive is stopped (SIGTERM: it writes its run folder, then exits 1); the monitor
    // says it has ended and lets go of the bus.
    signal(drive.id() as i32, libc::SIGTERM);
    tmux.wait_for(&["ENDED", "the drive has ended"], Duration::from_secs(60));
    let o = wait(drive, Duration::from_secs(60), "drive");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("interrupted (SIGTERM)"), "{err}");
    // Ctrl-C leaves too (the terminal is in raw mode: it arrives as a key).
    tmux.keys("C-c");
    assert_eq!(tmux.wait_exit(Duration::from_secs(10)), 0);
    let summary: serde_json::Value =
        serde_json::from_slice(&read(&out.join("summary.json"))).unwrap();
    let faults = summary["faults"]
        .as_array()
        .expect("faults in summary.json");
    assert_eq!(
        faults.len(),
        1,
        "exactly the one confirmed fault: {faults:?}"
    );
    assert_eq!(faults[0]["service"], "current-loop");
    assert!(
        faults[0]["fault"]
            .as_str()
            .unwrap()
            .starts_with("kill (requested by pid"),
        "{faults:?}"
    );
    assert!(
        faults[0]["detected_supervisor_ms"].as_f64().is_some(),
        "{faults:?}"
    );
    drop(tmux);
    // kill-server hangs up the pane's shell; give it a moment to go.
    assert_clean_within(&bus, Duration::from_secs(5));
}

#[test]
fn monitor_without_a_drive_is_a_one_line_error_and_leaves_nothing() {
    let bus = bus_id("none");
    let o = drivelab(&["monitor", "--bus", &bus]);
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(err.contains(&format!("no drive on bus '{bus}'")), "{err}");
    let o = drivelab(&["monitor", "--bus", "bad-id!"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("bus id 'bad-id!'"));
    let o = drivelab(&["monitor", "--bus", &bus, "--print", "--print-size", "10x5"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr)
        .contains("invalid value '10x5' for '--print-size <COLSxROWS>': must be COLSxROWS"));
    assert_clean(&bus);
}
