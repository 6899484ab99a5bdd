//! Stage-host processes: finding their executables, spawning one per process of the
//! topology, the READY/RT handshake on their stdout, and stopping them.

use super::RunOptions;
use crate::common::BusClock;
use anyhow::{anyhow, bail, Context, Result};
use drivelab_runtime::runner::Runner;
use drivelab_runtime::topology::ProcessSpec;
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// One running stage host.
pub(super) struct ChildProc {
    /// Process name in the topology.
    pub name: String,
    /// Stages it hosts.
    pub stages: Vec<String>,
    /// It hosts the source (the plant).
    pub source: bool,
    spec: ProcessSpec,
    pub exe: PathBuf,
    pub child: Child,
    stdin: Option<ChildStdin>,
    lines: mpsc::Receiver<String>,
    /// Its RT setup as it reported it (`RT {json}`).
    pub rt: Option<serde_json::Value>,
    /// The stage host's own pid as it reported it (`PID n`): the child's, unless the
    /// topology's `exec` is a wrapper that started the host without `exec`ing it.
    host_pid: Option<u32>,
    /// A standby twin that has not taken over.
    pub standby: bool,
    /// What its stage's panic was, as the host said it (`PANIC <what>`).
    pub panic: Option<String>,
}

/// The executable of process `p`: its `exec` (relative to `base`) or the built-in host next
/// to this executable.
pub(super) fn process_binary(p: &ProcessSpec, base: &Path) -> Result<PathBuf> {
    match drivelab_runtime::topology::exec_path(p, base) {
        Some(e) if e.is_file() => Ok(e),
        Some(e) => bail!(
            "process '{}': executable {} not found (a wrong path, or not built yet: cargo build --release in its crate)",
            p.name,
            e.display()
        ),
        None => service_binary("drivelab-host"),
    }
}

/// What a program asked a question ([`ask`]) answered.
pub(super) struct Answer {
    /// Its exit status (SIGKILL when it did not answer in time).
    pub status: std::io::Result<std::process::ExitStatus>,
    /// Its stdout, cut one byte past the limit.
    pub stdout: Vec<u8>,
    /// Its stderr, cut one byte past the limit.
    pub stderr: Vec<u8>,
    /// Whether it exited within the time given.
    pub in_time: bool,
}

/// Runs `cmd` (a question such as `--describe`, answered on stdout, or `--check-rt`) in a
/// process group of its own and reads up to `max_bytes` of each of its outputs; after
/// `timeout`, or as soon as it exits, its whole group is killed, so that nothing it started
/// is left behind.
pub(super) fn ask(mut cmd: Command, timeout: Duration, max_bytes: u64) -> Result<Answer> {
    use std::io::Read;
    use std::os::unix::process::CommandExt;
    // Gone with the launcher, however it ends (a Ctrl-C reaches our process group only).
    die_with_launcher(&mut cmd);
    let mut child = cmd
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .process_group(0)
        .spawn()?;
    let pid = child.id() as libc::pid_t;
    let read = |pipe: Option<Box<dyn Read + Send>>| {
        std::thread::spawn(move || {
            let mut buf = Vec::new();
            if let Some(p) = pipe {
                let _ = p.take(max_bytes + 1).read_to_end(&mut buf);
            }
            buf
        })
    };
    let out = read(
        child
            .stdout
            .take()
            .map(|p| Box::new(p) as Box<dyn Read + Send>),
    );
    let err = read(
        child
            .stderr
            .take()
            .map(|p| Box::new(p) as Box<dyn Read + Send>),
    );
    // Whether the child has exited, without reaping it: until it is reaped its pid, the
    // group's id, cannot be reused, so the group kill below hits only what it started.
    let exited = || {
        // SAFETY: siginfo_t is plain data; all zeroes is a valid value.
        let mut info: libc::siginfo_t = unsafe { std::mem::zeroed() };
        // SAFETY: waitid on our own unreaped child with a valid siginfo_t pointer; WNOWAIT
        // leaves it waitable, WNOHANG returns at once.
        let r = unsafe {
            libc::waitid(
                libc::P_PID,
                pid as libc::id_t,
                &mut info,
                libc::WEXITED | libc::WNOHANG | libc::WNOWAIT,
            )
        };
        // SAFETY: waitid filled in (or left zero) the si_pid field of a child's state change.
        r != 0 || unsafe { info.si_pid() } != 0
    };
    let started = Instant::now();
    let mut in_time = true;
    while !exited() {
        if started.elapsed() >= timeout {
            in_time = false;
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    // SAFETY: signals the process group of our own child, which is not reaped yet (its id
    // is still taken); ESRCH when the group is empty is ignored.
    unsafe { libc::kill(-pid, libc::SIGKILL) };
    let status = child.wait();
    Ok(Answer {
        status,
        stdout: out.join().unwrap_or_default(),
        stderr: err.join().unwrap_or_default(),
        in_time,
    })
}

/// How long a process's executable may take to answer `--check-rt`.
const CHECK_RT_TIMEOUT: Duration = Duration::from_secs(10);
/// The most of its output read (its answer is one line).
const CHECK_RT_MAX_BYTES: u64 = 64 << 10;

/// Asks `exe` for process `p`'s real-time placement as `--rt-strict` would
/// (`drivelab-host --check-rt`), in a process of its own that exits at once: a refusal is one
/// line before the drive starts instead of one per host after. A host that opened its bus
/// locks more than the check's process (18-28 MiB in the default drive), so the check also
/// makes sure that RLIMIT_MEMLOCK leaves room for what a host of the process's stages
/// locks (`rt::host_locked_bytes`).
pub(super) fn check_rt(p: &ProcessSpec, exe: &Path) -> Result<()> {
    let mut cmd = Command::new(exe);
    cmd.arg("--check-rt")
        .arg("--stages")
        .arg(p.stages.len().clamp(1, 1024).to_string());
    if let Some(c) = p.cpu {
        cmd.arg("--cpu").arg(c.to_string());
    }
    if let Some(pr) = p.priority {
        cmd.arg("--priority").arg(pr.to_string());
    }
    let out = ask(cmd, CHECK_RT_TIMEOUT, CHECK_RT_MAX_BYTES)
        .with_context(|| format!("cannot start process {} ({})", p.name, exe.display()))?;
    if !out.in_time {
        bail!(
            "--rt-strict: process {}: {} --check-rt did not answer within {} s (killed)",
            p.name,
            exe.display(),
            CHECK_RT_TIMEOUT.as_secs()
        );
    }
    let status = out
        .status
        .with_context(|| format!("{} --check-rt", exe.display()))?;
    if !status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        let line = err.lines().rfind(|l| !l.trim().is_empty()).unwrap_or("");
        bail!(
            "--rt-strict: process {}: {}",
            p.name,
            if line.is_empty() {
                format!(
                    "the real-time check of {} failed ({})",
                    exe.display(),
                    status
                )
            } else {
                line.trim().trim_start_matches("error: ").to_string()
            }
        );
    }
    Ok(())
}

fn service_binary(name: &str) -> Result<PathBuf> {
    let exe = std::env::current_exe().context("cannot locate the drivelab executable")?;
    let p = exe
        .parent()
        .ok_or_else(|| anyhow!("executable has no folder"))?
        .join(name);
    if !p.is_file() {
        bail!(
            "service binary {} not found next to drivelab (build the workspace first)",
            p.display()
        );
    }
    Ok(p)
}

/// The runner of a run's processes: `--runner`, else the `DRIVELAB_RUNNER` variable.
pub(super) fn runner_of(o: &RunOptions) -> Result<Option<Runner>> {
    match &o.runner {
        Some(r) => Ok(Some(r.clone())),
        None => Runner::from_env().map_err(|e| anyhow!(e)),
    }
}

/// What every stage host of one run is started with.
pub(super) struct Spawn<'a> {
    pub sc_path: &'a Path,
    pub topo_path: &'a Path,
    pub bus_id: &'a str,
    pub clock: BusClock,
    pub o: &'a RunOptions,
    pub out: &'a Path,
    /// The CPU mask every host starts with (the launcher's before it moved off the stages'
    /// cores); `None`: the launcher's own.
    pub cpus: Option<libc::cpu_set_t>,
    /// The resolved topology (what each process's stages declare).
    pub plan: &'a drivelab_runtime::service::TopologyPlan,
}

/// How a stage host starts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Start<'a> {
    /// With the drive.
    Fresh,
    /// Restarted into the running drive (`--rejoin`), with the file the supervisor wrote for
    /// it (`--rejoin-from`: the plant's true state, the own last output of a stage that reads
    /// its output back; docs/architecture.md, "Bumpless rejoin"), if it wrote one.
    Restart(Option<&'a Path>),
    /// As the process's standby twin (`--standby --rejoin`: it joins the running drive and
    /// steps beside the process, so it needs no file: a stage that reads its own output back
    /// rejoins from the active instance's newest one on the bus).
    Standby,
}

/// Starts the stage host of process `p`; `source` when it hosts the plant.
pub(super) fn spawn_service(
    p: &ProcessSpec,
    exe: &Path,
    source: bool,
    sp: &Spawn,
    start: Start,
) -> Result<ChildProc> {
    let standby = start == Start::Standby;
    let runner = runner_of(sp.o)?;
    let mut cmd = drivelab_runtime::runner::command(runner.as_ref(), exe);
    cmd.arg("--scenario").arg(sp.sc_path);
    cmd.arg("--topology").arg(sp.topo_path);
    cmd.arg("--process").arg(&p.name);
    cmd.arg("--hosts").arg(p.stages.join(","));
    cmd.arg("--bus").arg(sp.bus_id);
    cmd.arg("--clock").arg(match sp.clock {
        BusClock::Realtime => "realtime",
        BusClock::Lockstep => "lockstep",
    });
    cmd.arg("--out").arg(sp.out);
    if sp.o.rt_strict {
        cmd.arg("--rt-strict");
    }
    if sp.o.no_rt {
        cmd.arg("--no-rt");
    }
    if sp.o.audit_syscalls {
        cmd.arg("--audit-syscalls");
    }
    if source {
        cmd.arg("--recorder");
    }
    if standby {
        cmd.arg("--standby");
    }
    match start {
        Start::Fresh => {}
        Start::Standby => {
            cmd.arg("--rejoin");
        }
        Start::Restart(file) => {
            cmd.arg("--rejoin");
            if let Some(f) = file {
                cmd.arg("--rejoin-from").arg(f);
            }
        }
    }
    cmd.stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit());
    // Inherited by whatever the host starts: how [`end_strays`] knows its leftovers.
    cmd.env(HOST_OF_BUS, sp.bus_id);
    if sp.o.quiet_hosts {
        cmd.env(drivelab_runtime::service::QUIET_RT_LINE, "1");
    }
    die_with_launcher(&mut cmd);
    if let Some(set) = sp.cpus {
        start_on(&mut cmd, set);
    }
    if sp.clock == BusClock::Realtime && !sp.o.no_rt && p.priority.is_some() {
        set_up_above_normal_tasks(&mut cmd);
    }
    let name = p.name.clone();
    let mut child = cmd.spawn().with_context(|| match &runner {
        Some(r) => format!(
            "cannot start process {name} ({} through the runner '{}')",
            exe.display(),
            r.display()
        ),
        None => format!("cannot start process {name} ({})", exe.display()),
    })?;
    let stdout = child.stdout.take().expect("piped");
    let stdin = child.stdin.take();
    // Its stdout says RT and READY; nobody reads what a host writes there afterwards (a
    // user's stage printing as it steps): lines that find the queue full are dropped, so
    // that such a stage neither grows the launcher's memory nor blocks on a full pipe.
    let (tx, rx) = mpsc::sync_channel(STDOUT_LINES_KEPT);
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if let Err(mpsc::TrySendError::Disconnected(_)) = tx.try_send(line) {
                break;
            }
        }
    });
    Ok(ChildProc {
        name,
        stages: p.stages.clone(),
        source,
        spec: p.clone(),
        exe: exe.to_path_buf(),
        child,
        stdin,
        lines: rx,
        rt: None,
        host_pid: None,
        standby,
        panic: None,
    })
}

/// The lines of a stage host's stdout that wait for the launcher to read them.
const STDOUT_LINES_KEPT: usize = 1024;

/// The environment variable that marks a stage host of a bus, and every process it starts.
const HOST_OF_BUS: &str = "DRIVELAB_HOST_OF_BUS";

/// Makes this launcher the reaper of its stage hosts' orphans: a process that a host started
/// and left running (a helper, or the real host under a wrapper script that did not `exec`
/// it) becomes the launcher's child when its parent ends, instead of init's, so that
/// [`end_strays`] finds it after the drive.
pub(super) fn adopt_orphans() {
    // SAFETY: prctl(2) with integer arguments only; no memory is involved.
    unsafe { libc::prctl(libc::PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) };
}

/// Kills and reaps the processes that the stage hosts of bus `bus_id` started and left
/// behind (children of this launcher through [`adopt_orphans`], marked by [`HOST_OF_BUS`]);
/// the hosts themselves must have been reaped. Returns them as `pid (name)`.
pub(super) fn end_strays(bus_id: &str) -> Vec<String> {
    let me = std::process::id();
    let mark = format!("{HOST_OF_BUS}={bus_id}");
    let mut ended = Vec::new();
    for e in std::fs::read_dir("/proc").into_iter().flatten().flatten() {
        let Some(pid) = e.file_name().to_str().and_then(|s| s.parse::<u32>().ok()) else {
            continue;
        };
        let Ok(stat) = std::fs::read_to_string(e.path().join("stat")) else {
            continue;
        };
        // "pid (comm) state ppid …", where comm may hold spaces and parentheses.
        let Some((head, tail)) = stat.rsplit_once(')') else {
            continue;
        };
        if tail.split_whitespace().nth(1) != Some(me.to_string().as_str()) {
            continue;
        }
        let marked = std::fs::read(e.path().join("environ"))
            .is_ok_and(|env| env.split(|b| *b == 0).any(|v| v == mark.as_bytes()));
        if !marked {
            continue;
        }
        // SAFETY: kill(2) and waitpid(2) on a child of this process that no `Child` handle
        // owns (it was adopted); unreaped, its pid cannot be reused. No memory is passed but
        // a null status pointer, which waitpid accepts.
        unsafe {
            libc::kill(pid as libc::pid_t, libc::SIGKILL);
            libc::waitpid(pid as libc::pid_t, std::ptr::null_mut(), 0);
        }
        let name = head.split_once('(').map_or("?", |(_, c)| c);
        ended.push(format!("{pid} ({name})"));
    }
    ended
}

/// The child gets SIGKILL when the launcher dies, however it dies (a SIGKILLed launcher
/// cannot stop its children, and a real-time stage host left behind would hold its core).
/// The signal follows the death of the thread that spawned the child: the launcher spawns
/// and respawns from the thread that runs the whole drive.
pub(crate) fn die_with_launcher(cmd: &mut Command) {
    use std::os::unix::process::CommandExt;
    // SAFETY: getpid(2) only reads the caller's pid.
    let launcher = unsafe { libc::getpid() };
    // SAFETY: the closure runs in the forked child before exec and calls only the
    // async-signal-safe prctl(2), getppid(2) and _exit(2); the io::Error it may return
    // holds the errno code (no allocation). It touches no memory shared with the parent.
    unsafe {
        cmd.pre_exec(move || {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            // The launcher may have died before the prctl: then nobody would signal us.
            if libc::getppid() != launcher {
                libc::_exit(1);
            }
            Ok(())
        });
    }
}

/// The child starts with CPU mask `set` instead of the launcher's (which keeps off the
/// stages' cores); its placement then pins it.
fn start_on(cmd: &mut Command, set: libc::cpu_set_t) {
    use std::os::unix::process::CommandExt;
    // SAFETY: the closure runs in the forked child before exec and calls only the
    // async-signal-safe sched_setaffinity(2) with a mask copied into the closure; it
    // allocates nothing and ignores the result (the host reports where it runs).
    unsafe {
        cmd.pre_exec(move || {
            libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set);
            Ok(())
        });
    }
}

/// A real-time drive's stage host runs its set-up (loading, the bus's ports, its design,
/// mlock) at SCHED_FIFO 1, above every normal task and below every real-time stage, until
/// its placement gives it its own priority (only a process that has one): a restart then does not wait for the CPU behind
/// a busy machine's normal work (compilers beside a drive made restarts 3–5 × slower). A
/// refusal (no privilege) is ignored here: the host's real-time report says what it got.
fn set_up_above_normal_tasks(cmd: &mut Command) {
    use std::os::unix::process::CommandExt;
    // SAFETY: the closure runs in the forked child before exec and calls only the
    // async-signal-safe sched_setscheduler(2) with a parameter on its own stack; it
    // allocates nothing and ignores the result.
    unsafe {
        cmd.pre_exec(|| {
            let param = libc::sched_param { sched_priority: 1 };
            libc::sched_setscheduler(0, libc::SCHED_FIFO, &param);
            Ok(())
        });
    }
}

impl ChildProc {
    /// The same process started again with `--rejoin`, and `--rejoin-from` when the
    /// supervisor wrote it a file.
    pub fn respawn(&self, sp: &Spawn, rejoin_from: Option<&Path>) -> Result<ChildProc> {
        spawn_service(
            &self.spec,
            &self.exe,
            self.source,
            sp,
            Start::Restart(rejoin_from),
        )
    }

    /// A standby twin of this process (`standby = true`), joining the running drive.
    pub fn respawn_standby(&self, sp: &Spawn) -> Result<ChildProc> {
        spawn_service(&self.spec, &self.exe, false, sp, Start::Standby)
    }

    /// Its pid.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// The pid that signals meant for its stage host go to (faults, SIGCONT): the host's
    /// own once it said it, else the child's.
    pub fn host_pid(&self) -> u32 {
        self.host_pid.unwrap_or_else(|| self.child.id())
    }

    /// Takes one line of its stdout: records an `RT` report and the host's `PID`; true for
    /// `READY`.
    fn take_line(&mut self, l: &str) -> bool {
        if l == "READY" {
            return true;
        }
        if let Some(j) = l.strip_prefix("RT ") {
            self.rt = serde_json::from_str(j).ok();
        } else if let Some(what) = l.strip_prefix("PANIC ") {
            self.panic.get_or_insert_with(|| what.to_string());
        } else if let Some(pid) = l.strip_prefix("PID ") {
            self.host_pid = pid.parse().ok();
        }
        false
    }

    /// One line when its `exec` did not become the stage host but started it as a child:
    /// signals then go to the host, but the launcher can only wait for the wrapper.
    fn wrapper_warning(&self) -> Option<String> {
        let (child, host) = (self.child.id(), self.host_pid?);
        (host != child).then(|| {
            format!(
                "drivelab: warning: process {}: {} started its stage host as a child (pid {host} under pid {child}) instead of becoming it; faults are sent to the host, but end the script with `exec` so that the process the launcher started is the host",
                self.name,
                self.exe.display()
            )
        })
    }

    /// Reads what it has written so far without waiting; true once it said `READY`.
    pub fn poll_ready(&mut self) -> bool {
        let mut ready = false;
        while let Ok(l) = self.lines.try_recv() {
            ready |= self.take_line(&l);
        }
        ready
    }

    /// After it exited with `status`: the panic its host reported, if it says it panicked
    /// (the rest of its stdout is read, for at most 1 s: the host wrote the line before it
    /// exited).
    pub fn panic_after_exit(&mut self, status: std::process::ExitStatus) -> Option<String> {
        if status.code() != Some(i32::from(drivelab_runtime::service::PANIC_STATUS)) {
            return None;
        }
        let t = Instant::now();
        while self.panic.is_none() && t.elapsed() < Duration::from_secs(1) {
            match self.lines.recv_timeout(Duration::from_millis(20)) {
                Ok(l) => {
                    self.take_line(&l);
                }
                Err(mpsc::RecvTimeoutError::Timeout) => {}
                Err(mpsc::RecvTimeoutError::Disconnected) => break,
            }
        }
        self.panic.clone()
    }

    /// Tells the source to start the drive.
    fn go(&mut self) -> Result<()> {
        if let Some(stdin) = self.stdin.as_mut() {
            stdin.write_all(b"GO\n")?;
            stdin.flush()?;
        }
        Ok(())
    }
}

/// Tells the first process (the source) to start the drive.
pub(super) fn go(children: &mut [ChildProc]) -> Result<Option<String>> {
    if let Some(c) = children.first_mut() {
        c.go()?;
    }
    Ok(None)
}

/// Waits for each process to report its RT setup and READY (20 s in all). Returns why the
/// start failed, if it did.
pub(super) fn wait_ready(children: &mut [ChildProc]) -> Result<Option<String>> {
    let t = Instant::now();
    for c in children.iter_mut() {
        loop {
            if crate::common::stop_requested() {
                return Ok(Some("interrupted during start-up".into()));
            }
            match c.lines.recv_timeout(Duration::from_millis(50)) {
                Ok(l) => {
                    if c.take_line(&l) {
                        if let Some(w) = c.wrapper_warning() {
                            crate::errln!("{w}");
                        }
                        break;
                    }
                }
                Err(mpsc::RecvTimeoutError::Timeout) => {
                    if let Ok(Some(st)) = c.child.try_wait() {
                        return Ok(Some(format!("{} exited during start-up ({st})", c.name)));
                    }
                    if t.elapsed() > Duration::from_secs(20) {
                        return Ok(Some(format!("{} did not become ready within 20 s", c.name)));
                    }
                }
                Err(mpsc::RecvTimeoutError::Disconnected) => {
                    return Ok(Some(match c.child.wait() {
                        Ok(st) => format!("{} exited during start-up ({st})", c.name),
                        Err(_) => format!("{} exited during start-up", c.name),
                    }));
                }
            }
        }
    }
    Ok(None)
}

/// SIGTERM (and SIGCONT) to a child still running: its stop request.
pub(super) fn ask_to_stop(c: &mut ChildProc) {
    if let Ok(None) = c.child.try_wait() {
        // A process a stop fault froze takes the signal once it is resumed (SIGCONT).
        // SAFETY: kill(2) on a pid we spawned and have not reaped (and on the host under
        // it, which a wrapper that ends first leaves to this launcher, its subreaper, to
        // reap); no memory is touched.
        unsafe {
            libc::kill(c.child.id() as libc::pid_t, libc::SIGTERM);
            libc::kill(c.child.id() as libc::pid_t, libc::SIGCONT);
            if c.host_pid() != c.child.id() {
                libc::kill(c.host_pid() as libc::pid_t, libc::SIGTERM);
                libc::kill(c.host_pid() as libc::pid_t, libc::SIGCONT);
            }
        }
    }
}

/// SIGTERM to every child still running, then SIGKILL (named in a warning) to those not
/// gone within 3 s. The source's stdin is closed after the signal: a source stopped before
/// its `GO` is waiting for that line, and ends at once when it reads the end of its input
/// instead.
pub(super) fn terminate(children: &mut [ChildProc]) {
    for c in children.iter_mut() {
        ask_to_stop(c);
        c.stdin = None;
    }
    let t = Instant::now();
    for c in children.iter_mut() {
        loop {
            match c.child.try_wait() {
                Ok(Some(_)) | Err(_) => break,
                Ok(None) if t.elapsed() > Duration::from_secs(3) => {
                    let _ = c.child.kill();
                    let _ = c.child.wait();
                    crate::errln!(
                        "drivelab: warning: process {} did not end within 3 s of SIGTERM; killed (SIGKILL)",
                        c.name
                    );
                    break;
                }
                Ok(None) => std::thread::sleep(Duration::from_millis(5)),
            }
        }
    }
}
