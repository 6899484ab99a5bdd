//! Helpers shared by the integration tests that spawn the real processes: a scratch folder
//! and a bus id per test, a watchdog around `drivelab`, and the check that a run left no
//! process and no bus file behind. Timeouts here are watchdogs against hangs only.
#![allow(dead_code)]

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

mod clean;
pub use clean::{assert_clean, processes_on_bus, take_leftovers};

/// A TCP port of 127.0.0.1 that was free a moment ago (the kernel's pick).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// The CLI under test.
pub const DRIVELAB: &str = env!("CARGO_BIN_EXE_drivelab");
/// The shipped scenarios.
pub const SCENARIOS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../scenarios");
/// The test binary's name (kyslan, low, ...), used to keep scratch folders and bus ids apart.
const TAG: &str = env!("CARGO_CRATE_NAME");

/// One drive at a time: they all pin to the same core.
static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Serialises the drive tests of one test binary.
pub fn serial() -> std::sync::MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}

/// Says, past the test harness's capture of `eprintln!` (which a passing test's output never
/// leaves), that `test` did not check part of what it promises and why, so that a run that
/// passed without checking it shows so in its log.
pub fn not_checked(test: &str, why: &str) {
    use std::io::Write;
    let _ = writeln!(std::io::stderr(), "NOT CHECKED: {test}: {why}");
}

/// A fresh scratch folder for test `name`. The test binary removes its scratch folders when
/// it exits with no test failed; after a failure it keeps them and names them on stderr.
pub fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("drivelab-{TAG}-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    remove_at_exit(&d);
    d
}

/// Bus ids issued by [`bus_id`], with their tests' names.
static ISSUED: std::sync::Mutex<Vec<(String, String)>> = std::sync::Mutex::new(Vec::new());
/// Scratch folders made by this test binary.
static MADE: std::sync::Mutex<Vec<PathBuf>> = std::sync::Mutex::new(Vec::new());
/// Set by the first panic of any test thread (a failed assertion).
static FAILED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

fn remove_at_exit(d: &Path) {
    exit_hooks();
    MADE.lock()
        .unwrap_or_else(|e| e.into_inner())
        .push(d.to_path_buf());
}

/// Installs, once per test binary, the panic hook that notes a failure and the function that
/// runs at exit: [`at_exit`].
fn exit_hooks() {
    static HOOKS: std::sync::Once = std::sync::Once::new();
    HOOKS.call_once(|| {
        let report = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            FAILED.store(true, std::sync::atomic::Ordering::SeqCst);
            report(info);
        }));
        // SAFETY: registers a function without arguments that runs once when the process
        // exits (the test harness returns from main or calls exit).
        unsafe { libc::atexit(at_exit) };
    });
}

/// At the test binary's exit, every test done: the processes and files of every bus id it
/// issued are removed (what a failed test left behind). When no test failed, anything left
/// is a leak that no test caught: it is named and the binary exits with code 1.
extern "C" fn at_exit() {
    let issued = std::mem::take(&mut *ISSUED.lock().unwrap_or_else(|e| e.into_inner()));
    let mut leaks = Vec::new();
    for (bus, name) in issued {
        let (procs, files) = take_leftovers(&bus);
        if !procs.is_empty() || !files.is_empty() {
            leaks.push(format!(
                "bus {bus} of '{name}': processes {procs:?}, files {files:?}"
            ));
        }
    }
    remove_scratch();
    if !leaks.is_empty() && !FAILED.load(std::sync::atomic::Ordering::SeqCst) {
        eprintln!("left behind by tests that passed (now removed):");
        for l in &leaks {
            eprintln!("  {l}");
        }
        // SAFETY: ends this process at once with a failure code; every test has finished.
        unsafe { libc::_exit(1) };
    }
}

fn remove_scratch() {
    let made = std::mem::take(&mut *MADE.lock().unwrap_or_else(|e| e.into_inner()));
    if FAILED.load(std::sync::atomic::Ordering::SeqCst) {
        eprintln!(
            "scratch folders kept after a failure: {}",
            made.iter()
                .map(|d| d.display().to_string())
                .collect::<Vec<_>>()
                .join(" ")
        );
        return;
    }
    for d in made {
        let _ = std::fs::remove_dir_all(d);
    }
}

/// A bus id unique to this test binary, process and test: the binary's initial, the pid and
/// a 64-bit FNV-1a hash of binary and test name, in base 36 (at most 1 + 5 + 1 + 13 = 20 of
/// the 24 characters a bus id may have). Two names of one process that hash alike fail the
/// test instead of sharing a bus.
pub fn bus_id(name: &str) -> String {
    let base36 = |mut v: u64| {
        let mut s = Vec::new();
        loop {
            s.push(b"0123456789abcdefghijklmnopqrstuvwxyz"[(v % 36) as usize]);
            v /= 36;
            if v == 0 {
                break;
            }
        }
        s.reverse();
        String::from_utf8(s).unwrap()
    };
    let hash = format!("{TAG}/{name}")
        .bytes()
        .fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
            (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
        });
    let id = format!(
        "{}{}_{}",
        &TAG[..1],
        base36(u64::from(std::process::id())),
        base36(hash)
    );
    exit_hooks();
    let mut issued = ISSUED.lock().unwrap_or_else(|e| e.into_inner());
    if let Some((_, other)) = issued.iter().find(|(i, n)| *i == id && n != name) {
        panic!("bus id {id} of '{name}' collides with that of '{other}'");
    }
    issued.push((id.clone(), name.to_string()));
    id
}

/// Runs `cmd` (its output piped) with a watchdog against hangs behind a [`Drive`] guard: on
/// expiry the test fails and the process is killed.
pub fn output_within(cmd: &mut Command, watchdog: Duration) -> Output {
    let what = format!("{cmd:?}");
    let child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("start {what}: {e}"));
    Drive::from(child).wait_for_exit(watchdog, &what)
}

/// Runs drivelab with a watchdog of 300 s; kills it (and fails) if it hangs.
pub fn drivelab(args: &[&str]) -> Output {
    drivelab_within(args, Duration::from_secs(300))
}

/// Runs drivelab with a watchdog against hangs, behind a [`Drive`] guard: on expiry the test
/// fails, the process is killed and, when the command line names a `--bus`, that bus's
/// processes and files are removed too.
pub fn drivelab_within(args: &[&str], watchdog: Duration) -> Output {
    let child = Command::new(DRIVELAB)
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start drivelab");
    let guard = match args.windows(2).find(|w| w[0] == "--bus") {
        Some(w) => Drive::on_bus(child, w[1]),
        None => Drive::from(child),
    };
    guard.wait_for_exit(watchdog, &format!("drivelab {args:?}"))
}

/// Runs `drivelab run --bus BUS --no-plots EXTRA` and asserts that it fails before the start
/// with exit code 1 and a one-line error containing `needle`.
pub fn assert_run_refused(bus: &str, extra: &[&str], needle: &str) {
    assert_run_fails(bus, extra, 1, needle);
}

/// As [`assert_run_refused`], for a command line wrong in itself: exit code 2.
pub fn assert_run_usage_error(bus: &str, extra: &[&str], needle: &str) {
    assert_run_fails(bus, extra, 2, needle);
}

fn assert_run_fails(bus: &str, extra: &[&str], code: i32, needle: &str) {
    assert!(
        !extra.contains(&"--out"),
        "the refused run's folder is this helper's"
    );
    // A run folder of its own, so that a run that is not refused after all writes nothing
    // into the repository's runs/.
    let out = scratch(&format!("refused-{bus}")).join("run");
    let mut args = run_args(bus, &out).to_vec();
    args.extend_from_slice(extra);
    let o = drivelab(&args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(code), "{extra:?}: {err}");
    assert!(err.contains(needle), "{extra:?}: {err}");
    assert_eq!(err.lines().count(), 1, "{extra:?}: {err}");
    assert!(!out.exists(), "{extra:?}: a refused run made its folder");
}

/// Runs `drivelab run --bus <own id> --out <scratch>/run --no-plots EXTRA`, asserts success
/// and a clean bus, and returns the run folder and its summary.
pub fn run_ok(name: &str, extra: &[&str]) -> (PathBuf, Value) {
    let dir = scratch(name);
    let bus = bus_id(name);
    let out = dir.join("run");
    let mut args = run_args(&bus, &out).to_vec();
    args.extend_from_slice(extra);
    let o = drivelab(&args);
    assert!(
        o.status.success(),
        "drivelab {args:?} failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert_clean(&bus);
    let s = summary(&out);
    (out, s)
}

/// Waits for a spawned child (a bare [`Child`] or a [`Drive`]) with a watchdog against
/// hangs; kills it (and fails) on expiry.
pub fn wait(child: impl Into<Drive>, watchdog: Duration, what: &str) -> Output {
    child.into().wait_for_exit(watchdog, what)
}

/// Gives the process `cmd` starts a file size limit of `bytes` (`ulimit -f`).
pub fn limit_file_size(cmd: &mut Command, bytes: libc::rlim_t) {
    // SAFETY: the closure runs in the forked child before exec and calls only setrlimit(2)
    // with a limit on its own stack (lowering a limit needs no privilege).
    unsafe {
        use std::os::unix::process::CommandExt;
        cmd.pre_exec(move || {
            let limit = libc::rlimit {
                rlim_cur: bytes,
                rlim_max: bytes,
            };
            if libc::setrlimit(libc::RLIMIT_FSIZE, &limit) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
}

/// `run --bus BUS --out OUT --no-plots`: the start of every test drive's command line.
pub fn run_args<'a>(bus: &'a str, out: &'a Path) -> [&'a str; 6] {
    [
        "run",
        "--bus",
        bus,
        "--out",
        out.to_str().unwrap(),
        "--no-plots",
    ]
}

/// A run folder's `summary.json`.
pub fn summary(dir: &Path) -> Value {
    serde_json::from_slice(&read(&dir.join("summary.json"))).unwrap()
}

/// The `supervisor_events` of summary `s` of kind `event` (e.g. "inject-refused").
pub fn events<'a>(s: &'a Value, event: &str) -> Vec<&'a Value> {
    s["supervisor_events"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["event"] == event)
        .collect()
}

/// A process this test started, stopped however the test ends: a drive's launcher (with its
/// bus), or a helper process (no bus). It gives access to its [`Child`] (to signal it, take
/// its pipes, poll it); [`Drive::wait_for_exit`] waits for it.
///
/// When dropped while the process still runs (the test failed before stopping it, or left
/// it running), the process is SIGKILLed and reaped. For a drive, the stage hosts then die
/// with their launcher (the launcher spawns each with SIGKILL as its parent-death signal),
/// so none is left; any process of the bus still there after 10 s is SIGKILLed. After such
/// a kill, or when the test is failing, the bus's files are removed too, so that a failed
/// test leaves nothing behind. A test that passes with its drive ended keeps its own
/// checks: its bus is left as the drive left it (see [`assert_clean`]).
pub struct Drive {
    child: Option<Child>,
    bus: Option<String>,
}

impl Drive {
    /// Starts `drivelab run --bus BUS --out OUT --no-plots EXTRA` (stdout and stderr piped)
    /// behind a guard.
    pub fn start(bus: &str, out: &Path, extra: &[&str]) -> Self {
        let child = Command::new(DRIVELAB)
            .args(run_args(bus, out))
            .args(extra)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start drivelab run");
        Self::on_bus(child, bus)
    }

    /// Guards `child`, the launcher of a drive on `bus` started otherwise.
    pub fn on_bus(child: Child, bus: &str) -> Self {
        Self {
            child: Some(child),
            bus: Some(bus.to_string()),
        }
    }

    /// Waits for the process to exit with a watchdog against hangs (on expiry the test
    /// fails, and the guard kills it); returns its status and what it printed. Its piped
    /// output is read while it runs: a process that prints more than a pipe holds (64 KiB)
    /// would otherwise block in its write and never exit.
    pub fn wait_for_exit(mut self, watchdog: Duration, what: &str) -> Output {
        let drain = |pipe: Option<Box<dyn std::io::Read + Send>>| {
            std::thread::spawn(move || {
                let mut v = Vec::new();
                if let Some(mut p) = pipe {
                    let _ = p.read_to_end(&mut v);
                }
                v
            })
        };
        let out = drain(self.stdout.take().map(|p| Box::new(p) as _));
        let err = drain(self.stderr.take().map(|p| Box::new(p) as _));
        let t = Instant::now();
        while self.try_wait().unwrap().is_none() {
            assert!(
                t.elapsed() <= watchdog,
                "watchdog: {what} still running after {watchdog:?}"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        // It has exited and is reaped: the guard has nothing left to stop. Its pipes end
        // when the last process holding them (it, or a child it left) closes them.
        let status = self.child.take().unwrap().wait().unwrap();
        Output {
            status,
            stdout: out.join().unwrap(),
            stderr: err.join().unwrap(),
        }
    }

    /// SIGKILLs the launcher (nobody cleans up) and asserts that the kernel ends every other
    /// process of the drive's bus with it within 10 s; those left are killed before the
    /// assertion fails. The bus's files stay (the test may check them) unless the test
    /// fails later.
    pub fn kill_and_assert_no_orphans(&mut self) {
        let bus = self.bus.clone().expect("a drive on a bus");
        let child = self.child.as_mut().expect("a running launcher");
        // SAFETY: SIGKILL to this test's own launcher, not reaped yet (its pid is its own).
        unsafe { libc::kill(child.id() as i32, libc::SIGKILL) };
        let _ = child.wait();
        let orphans = end_processes_on_bus(&bus, Duration::from_secs(10));
        assert!(
            orphans.is_empty(),
            "processes outlived their launcher by 10 s: {orphans:?}"
        );
    }
}

/// A helper process of a test (no bus): killed and reaped on drop if it still runs.
impl From<Child> for Drive {
    fn from(child: Child) -> Self {
        Self {
            child: Some(child),
            bus: None,
        }
    }
}

impl std::ops::Deref for Drive {
    type Target = Child;
    fn deref(&self) -> &Child {
        self.child.as_ref().expect("the process was waited for")
    }
}

impl std::ops::DerefMut for Drive {
    fn deref_mut(&mut self) -> &mut Child {
        self.child.as_mut().expect("the process was waited for")
    }
}

impl Drop for Drive {
    fn drop(&mut self) {
        let mut killed = false;
        if let Some(child) = self.child.as_mut() {
            if matches!(child.try_wait(), Ok(None)) {
                let _ = child.kill();
                let _ = child.wait();
                killed = true;
            }
        }
        if let Some(bus) = &self.bus {
            if killed || std::thread::panicking() {
                end_processes_on_bus(bus, Duration::from_secs(10));
                if let Err(e) = drivelab_runtime::bus::cleanup(bus) {
                    eprintln!("bus {bus}: files not removed: {e:#}");
                }
            }
        }
    }
}

/// Waits up to `grace` for the processes of `bus` to end (a drive's stage hosts after their
/// launcher died), then SIGKILLs those left; returns them.
fn end_processes_on_bus(bus: &str, grace: Duration) -> Vec<String> {
    let t = Instant::now();
    while !processes_on_bus(bus).is_empty() && t.elapsed() < grace {
        std::thread::sleep(Duration::from_millis(20));
    }
    let left = processes_on_bus(bus);
    for line in &left {
        let pid: i32 = line.split(' ').next().unwrap().parse().unwrap();
        // SAFETY: SIGKILL to a process of this test's own bus.
        unsafe { libc::kill(pid, libc::SIGKILL) };
    }
    left
}

/// Waits until the launcher and its four services are running on `bus` (watchdog 60 s).
pub fn wait_for_services(bus: &str) {
    let t = Instant::now();
    while processes_on_bus(bus).len() < 5 {
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "services did not start"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Waits until the drive on `bus` has recorded `k` samples (watchdog 60 s), as its supervisor
/// publishes its progress for `drivelab monitor`: the chain is past its start-up handshake
/// and running.
pub fn wait_for_progress(bus: &str, k: u64) {
    wait_for_view(bus, &format!("reach sample {k}"), |v| v.hdr.k >= k);
}

/// Waits until a view the supervisor of the drive on `bus` publishes for `drivelab monitor`
/// satisfies `done` (watchdog 60 s, naming `what`), and returns it.
pub fn wait_for_view(
    bus: &str,
    what: &str,
    done: impl Fn(&drivelab_runtime::telemetry::DriveView) -> bool,
) -> drivelab_runtime::telemetry::DriveView {
    use drivelab_runtime::telemetry::{open_existing, DriveView, PlainReceiver, TOPIC_VIEW};
    let t = Instant::now();
    let watchdog = || {
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "watchdog: the drive on {bus} did not {what} within 60 s"
        )
    };
    // The launcher refuses a bus with a live node on it: join only once it has started its
    // first stage host, past that check. A child it has forked and not yet exec'd (a hog's
    // privilege check, an executable asked to describe itself) shows the launcher's own
    // command line, so a `drivelab run` line does not count: counting it, the test joined
    // before the check and the drive refused the bus. The launcher may be started through a
    // wrapper (`ip netns exec NS drivelab run …`).
    let launcher = |p: &String| {
        let args: Vec<&str> = p.split_whitespace().collect();
        args.windows(2)
            .any(|w| (w[0] == "drivelab" || w[0].ends_with("/drivelab")) && w[1] == "run")
    };
    while processes_on_bus(bus).iter().all(launcher) {
        watchdog();
        std::thread::sleep(Duration::from_millis(5));
    }
    let node = drivelab_runtime::bus::node(bus, "test").unwrap();
    let view = loop {
        // The topic exists once the supervisor's hub is up.
        if let Ok(v) = open_existing::<DriveView>(&node, TOPIC_VIEW) {
            break v;
        }
        watchdog();
        std::thread::sleep(Duration::from_millis(5));
    };
    let rx = PlainReceiver::new(&view, 4).unwrap();
    loop {
        while let Some(v) = rx.try_recv().unwrap() {
            if done(&v) {
                return v;
            }
        }
        watchdog();
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// The pid of the stage host `process` (its `--process` argument) of the drive on `bus`.
pub fn process_pid(bus: &str, process: &str) -> i32 {
    processes_on_bus(bus)
        .iter()
        .find(|l| {
            let args: Vec<&str> = l.split(' ').collect();
            args.windows(2).any(|w| w == ["--process", process])
        })
        .unwrap_or_else(|| panic!("no process {process} on bus {bus}"))
        .split(' ')
        .next()
        .unwrap()
        .parse()
        .unwrap()
}

/// SIGKILLs the launcher `child` (a bare [`Child`] or a [`Drive`]; nobody cleans up) and
/// asserts that the kernel ends every other process of `bus` with it (their parent-death
/// signal) within 10 s; those left are killed before the assertion fails.
/// [`Drive::kill_and_assert_no_orphans`] does the same and keeps the guard.
pub fn kill_launcher_and_assert_no_orphans(child: impl Into<Drive>, bus: &str) {
    let mut drive = child.into();
    let on = drive.bus.get_or_insert_with(|| bus.to_string());
    assert_eq!(on, bus, "the drive runs on another bus");
    drive.kill_and_assert_no_orphans();
}

/// Like [`assert_clean`], but gives the processes up to `grace` to exit first (after a
/// signal was sent to them from outside the launcher).
pub fn assert_clean_within(bus: &str, grace: Duration) {
    let t = Instant::now();
    while !processes_on_bus(bus).is_empty() && t.elapsed() < grace {
        std::thread::sleep(Duration::from_millis(20));
    }
    assert_clean(bus);
}

/// A finished run: folder, summary.json and stderr.
pub struct Run {
    /// Run folder.
    pub dir: PathBuf,
    /// summary.json.
    pub summary: Value,
    /// What drivelab printed on stderr.
    pub stderr: String,
}

impl Run {
    /// A metric of summary.json, which must exist.
    pub fn metric(&self, key: &str) -> f64 {
        self.summary["metrics"][key]
            .as_f64()
            .unwrap_or_else(|| panic!("{key} missing: {}", self.summary["metrics"]))
    }

    /// The trace.
    pub fn trace(&self) -> Vec<drivelab_runtime::trace::TraceRow> {
        drivelab_runtime::trace::read_csv(&self.dir.join("trace.csv")).unwrap()
    }
}

/// Runs `scenario` (a name or a file) with `clock` into a fresh folder named `tag`, checks it
/// succeeded and left nothing behind.
pub fn run(tag: &str, scenario: &str, clock: &str) -> Run {
    let dir = scratch(tag).join("run");
    let bus = bus_id(tag);
    let args = [
        "run",
        "--scenario",
        scenario,
        "--clock",
        clock,
        "--bus",
        &bus,
        "--out",
        dir.to_str().unwrap(),
        "--no-plots",
    ];
    let o = drivelab(&args);
    let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(o.status.success(), "drivelab {args:?} failed: {stderr}");
    assert_clean(&bus);
    let summary =
        serde_json::from_slice(&std::fs::read(dir.join("summary.json")).unwrap()).unwrap();
    Run {
        dir,
        summary,
        stderr,
    }
}

/// Reads a file or fails with its name.
pub fn read(p: &Path) -> Vec<u8> {
    std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// A variant of a shipped scenario with text `edits`, written to the scratch folder of `tag`.
pub fn variant(tag: &str, base: &str, edits: &[(&str, &str)]) -> PathBuf {
    let mut text = std::fs::read_to_string(format!("{SCENARIOS}/{base}.toml")).unwrap();
    for (from, to) in edits {
        assert!(text.contains(from), "{base}.toml has no '{from}'");
        text = text.replace(from, to);
    }
    let p = scratch(&format!("{tag}-sc")).join(format!("{tag}.toml"));
    std::fs::write(&p, text).unwrap();
    p
}

/// The number after `label` in `text` (up to the next space, comma or line end).
pub fn number_after(text: &str, label: &str) -> f64 {
    let i = text
        .find(label)
        .unwrap_or_else(|| panic!("'{label}' not in\n{text}"));
    let rest = &text[i + label.len()..];
    let end = rest.find([' ', ',', '\n']).unwrap_or(rest.len());
    rest[..end]
        .parse()
        .unwrap_or_else(|e| panic!("'{}' after '{label}': {e}", &rest[..end]))
}

/// Compares the trace of a real-time run with the lockstep trace of the same scenario: they
/// agree bit for bit on every row before the first one that a stale input reached (the
/// plant held a command or went safe: `plant_flags`, `miss`; the current loop used a stale
/// input: `ctrl_flags`) or that follows a missing sample, and entirely when there is no such
/// row. Returns the rows compared and whether such a row ended the comparison.
pub fn assert_identical_until_disturbed(lockstep: &Path, realtime: &Path) -> (usize, bool) {
    let (a, b) = (
        read(&lockstep.join("trace.csv")),
        read(&realtime.join("trace.csv")),
    );
    let la: Vec<&[u8]> = a.split(|c| *c == b'\n').filter(|l| !l.is_empty()).collect();
    let lb: Vec<&[u8]> = b.split(|c| *c == b'\n').filter(|l| !l.is_empty()).collect();
    assert_eq!(la[0], lb[0], "headers differ");
    let header: Vec<&str> = std::str::from_utf8(lb[0]).unwrap().split(',').collect();
    let flag_cols: Vec<usize> = ["plant_flags", "ctrl_flags", "miss"]
        .iter()
        .map(|n| header.iter().position(|c| c == n).unwrap())
        .collect();
    for (i, line) in lb.iter().enumerate().skip(1) {
        let f: Vec<&str> = std::str::from_utf8(line).unwrap().split(',').collect();
        let in_order = f[0].parse::<usize>().unwrap() == i - 1;
        if !in_order || flag_cols.iter().any(|&c| f[c] != "0") {
            return (i - 1, true);
        }
        assert_eq!(
            la.get(i).copied(),
            Some(*line),
            "{} differs from lockstep at sample {} before any stale input or gap",
            realtime.display(),
            i - 1
        );
    }
    assert_eq!(
        la.len(),
        lb.len(),
        "{}: rows missing at the end",
        realtime.display()
    );
    (lb.len() - 1, false)
}

/// Samples of `rows` whose row satisfies `f`.
pub fn samples(
    rows: &[drivelab_runtime::trace::TraceRow],
    f: impl Fn(&drivelab_runtime::trace::TraceRow) -> bool,
) -> std::collections::BTreeSet<u64> {
    rows.iter().filter(|r| f(r)).map(|r| r.k).collect()
}

/// The samples of range `r`, to compare with [`samples`].
pub fn ks(r: std::ops::Range<u64>) -> std::collections::BTreeSet<u64> {
    r.collect()
}

/// Runs `drivelab run EXTRA` twice in lockstep and once in process (runs `TAGa`, `TAGb`,
/// `TAGp`), checks that the three traces are the same bytes and returns the first run's
/// folder and summary.
pub fn same_trace_in_every_run(tag: &str, extra: &[&str]) -> (PathBuf, Value) {
    let args = |clock: &'static str| {
        let mut a = vec!["--clock", clock];
        a.extend_from_slice(extra);
        a
    };
    let (a, sa) = run_ok(&format!("{tag}a"), &args("lockstep"));
    let (b, _) = run_ok(&format!("{tag}b"), &args("lockstep"));
    let (p, sp) = run_ok(&format!("{tag}p"), &args("inprocess"));
    let ta = read(&a.join("trace.csv"));
    assert!(
        ta == read(&b.join("trace.csv")),
        "{extra:?}: two lockstep runs differ"
    );
    assert!(
        ta == read(&p.join("trace.csv")),
        "{extra:?}: lockstep and in-process differ"
    );
    // The same rows are missing the same parts for the same reasons in both clocks.
    assert_eq!(
        sa["missing_samples"], sp["missing_samples"],
        "{extra:?}: lockstep and in-process list different missing samples"
    );
    (a, sa)
}

/// The processes whose command line holds `marker`.
pub fn processes_with(marker: &str) -> Vec<String> {
    std::fs::read_dir("/proc")
        .unwrap()
        .flatten()
        .filter_map(|e| std::fs::read(e.path().join("cmdline")).ok())
        .map(|c| String::from_utf8_lossy(&c).replace('\0', " "))
        .filter(|c| c.contains(marker))
        .collect()
}
