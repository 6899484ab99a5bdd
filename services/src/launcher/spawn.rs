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
    /// A standby twin that has not taken over.
    pub standby: bool,
}

/// The executable of process `p`: its `exec` (relative to `base`) or the built-in host next
/// to this executable.
pub(super) fn process_binary(p: &ProcessSpec, base: &Path) -> Result<PathBuf> {
    match drivelab_runtime::topology::exec_path(p, base) {
        Some(e) if e.is_file() => Ok(e),
        Some(e) => bail!(
            "process '{}': executable {} not found (build it first: cargo build --release --workspace)",
            p.name,
            e.display()
        ),
        None => service_binary("drivelab-host"),
    }
}

/// Asks `exe` for process `p`'s real-time placement as `--rt-strict` would
/// (`drivelab-host --check-rt`), in a process of its own that exits at once: a refusal is one
/// line before the drive starts instead of one per host after. It locks the memory of a
/// process without a bus; a host that opened its bus locks more (18-28 MiB in the default
/// drive), so a finite RLIMIT_MEMLOCK that lets the check pass may still refuse the host.
pub(super) fn check_rt(p: &ProcessSpec, exe: &Path) -> Result<()> {
    let mut cmd = Command::new(exe);
    cmd.arg("--check-rt");
    if let Some(c) = p.cpu {
        cmd.arg("--cpu").arg(c.to_string());
    }
    if let Some(pr) = p.priority {
        cmd.arg("--priority").arg(pr.to_string());
    }
    cmd.stdin(Stdio::null()).stdout(Stdio::null());
    die_with_launcher(&mut cmd);
    let out = cmd
        .output()
        .with_context(|| format!("cannot start process {} ({})", p.name, exe.display()))?;
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        let line = err.lines().rfind(|l| !l.trim().is_empty()).unwrap_or("");
        bail!(
            "--rt-strict: process {}: {}",
            p.name,
            if line.is_empty() {
                format!(
                    "the real-time check of {} failed ({})",
                    exe.display(),
                    out.status
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
}

/// Starts the stage host of process `p`; `source` when it hosts the plant; `rejoin_from`
/// when it is a restart (the plant resumes from the true state in that file).
pub(super) fn spawn_service(
    p: &ProcessSpec,
    exe: &Path,
    source: bool,
    sp: &Spawn,
    rejoin_from: Option<&Path>,
    standby: bool,
) -> Result<ChildProc> {
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
    if source {
        cmd.arg("--recorder");
    }
    if standby {
        cmd.arg("--standby");
    }
    if let Some(f) = rejoin_from {
        cmd.arg("--rejoin");
        if source {
            cmd.arg("--rejoin-from").arg(f);
        }
    }
    cmd.stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit());
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
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
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
        standby,
    })
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
    /// The same process started again with `--rejoin`.
    pub fn respawn(&self, sp: &Spawn, rejoin_from: &Path) -> Result<ChildProc> {
        spawn_service(
            &self.spec,
            &self.exe,
            self.source,
            sp,
            Some(rejoin_from),
            false,
        )
    }

    /// A standby twin of this process (`standby = true`), joining the running drive.
    pub fn respawn_standby(&self, sp: &Spawn) -> Result<ChildProc> {
        let rejoin = sp.out.join(format!("rejoin-{}.json", self.name));
        spawn_service(&self.spec, &self.exe, false, sp, Some(&rejoin), true)
    }

    /// Its pid.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Takes one line of its stdout: records an `RT` report; true for `READY`.
    fn take_line(&mut self, l: &str) -> bool {
        if l == "READY" {
            return true;
        }
        if let Some(j) = l.strip_prefix("RT ") {
            self.rt = serde_json::from_str(j).ok();
        }
        false
    }

    /// Reads what it has written so far without waiting; true once it said `READY`.
    pub fn poll_ready(&mut self) -> bool {
        let mut ready = false;
        while let Ok(l) = self.lines.try_recv() {
            ready |= self.take_line(&l);
        }
        ready
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

/// SIGTERM to every child still running, then SIGKILL to those not gone within 3 s.
pub(super) fn terminate(children: &mut [ChildProc]) {
    for c in children.iter_mut() {
        if let Ok(None) = c.child.try_wait() {
            // SAFETY: kill(2) on a pid we spawned and have not reaped; no memory is touched.
            unsafe {
                libc::kill(c.child.id() as libc::pid_t, libc::SIGTERM);
            }
        }
    }
    let t = Instant::now();
    for c in children.iter_mut() {
        loop {
            match c.child.try_wait() {
                Ok(Some(_)) | Err(_) => break,
                Ok(None) if t.elapsed() > Duration::from_secs(3) => {
                    let _ = c.child.kill();
                    let _ = c.child.wait();
                    break;
                }
                Ok(None) => std::thread::sleep(Duration::from_millis(5)),
            }
        }
    }
}
