//! The processes a measurement starts (the Unix-socket chain's nodes, the hop receivers,
//! cyclictest), held in a guard that stops and reaps every one still running on every way
//! out of the measurement: its end, an error, a stop signal ([`crate::Interrupted`]) or a
//! panic. None is left behind for init to adopt.

use anyhow::{Context, Result};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

/// How long a process gets to exit after SIGTERM before SIGKILL.
const TERM_GRACE: Duration = Duration::from_secs(2);

/// One process, `what` it is to its measurement, and its log (stdout and stderr).
pub(crate) struct Kid<T> {
    pub what: T,
    pub child: Child,
    pub log: PathBuf,
    /// Set once it has exited and been reaped.
    pub status: Option<ExitStatus>,
}

/// The processes of one measurement; on drop every one still running gets SIGTERM, then
/// SIGKILL after [`TERM_GRACE`], and is reaped.
pub(crate) struct Kids<T>(pub Vec<Kid<T>>);

impl<T> Default for Kids<T> {
    fn default() -> Self {
        Self(Vec::new())
    }
}

impl<T> Kids<T> {
    /// Starts `cmd` (`name` says what for, in the error) with no stdin and its stdout and
    /// stderr in a new file `log`, and keeps it as `what`. The process gets SIGTERM from the
    /// kernel when the thread that started it ends (a bench killed with SIGKILL can stop
    /// nobody itself); every measurement starts its processes from the bench's main thread.
    pub fn spawn(&mut self, what: T, cmd: &mut Command, log: PathBuf, name: &str) -> Result<()> {
        self.start(what, cmd, log, name, false)
    }

    /// [`Kids::spawn`] for a drivelab process that installs its stop-signal handlers first
    /// (`drivelab_runtime::service::install_signal_handlers`, which unblocks them) and
    /// cleans up when one arrives: it starts with SIGTERM blocked, so a parent-death SIGTERM
    /// sent before its handlers are in place waits for them instead of killing it first.
    pub fn spawn_holding_term(
        &mut self,
        what: T,
        cmd: &mut Command,
        log: PathBuf,
        name: &str,
    ) -> Result<()> {
        self.start(what, cmd, log, name, true)
    }

    fn start(
        &mut self,
        what: T,
        cmd: &mut Command,
        log: PathBuf,
        name: &str,
        hold_term: bool,
    ) -> Result<()> {
        let f = drivelab_runtime::files::create(&log)
            .with_context(|| format!("cannot create {}", log.display()))?;
        let parent = std::process::id();
        // SAFETY: the closure runs in the child between fork and exec; it calls only
        // sigemptyset(3), sigaddset(3), sigprocmask(2), prctl(2) and getppid(2), which are
        // async-signal-safe, on a sigset_t on its own stack, and allocates nothing. The
        // blocked mask is kept across exec (std resets the mask before the closure runs).
        unsafe {
            std::os::unix::process::CommandExt::pre_exec(cmd, move || {
                if hold_term {
                    let mut set: libc::sigset_t = std::mem::zeroed();
                    libc::sigemptyset(&mut set);
                    libc::sigaddset(&mut set, libc::SIGTERM);
                    if libc::sigprocmask(libc::SIG_BLOCK, &set, std::ptr::null_mut()) != 0 {
                        return Err(std::io::Error::last_os_error());
                    }
                }
                if libc::prctl(
                    libc::PR_SET_PDEATHSIG,
                    libc::SIGTERM as libc::c_ulong,
                    0,
                    0,
                    0,
                ) != 0
                {
                    return Err(std::io::Error::last_os_error());
                }
                // The bench died before the request was made: do not start at all.
                if u32::try_from(libc::getppid()).ok() != Some(parent) {
                    return Err(std::io::Error::from_raw_os_error(libc::ESRCH));
                }
                Ok(())
            });
        }
        let child = cmd
            .stdin(Stdio::null())
            .stdout(f.try_clone()?)
            .stderr(f)
            .spawn()
            .with_context(|| {
                format!(
                    "cannot start {} for {name}",
                    cmd.get_program().to_string_lossy()
                )
            })?;
        self.0.push(Kid {
            what,
            child,
            log,
            status: None,
        });
        Ok(())
    }

    /// Reaps whatever has exited; true when all have.
    pub fn poll(&mut self) -> bool {
        let mut all = true;
        for k in &mut self.0 {
            if k.status.is_none() {
                k.status = k.child.try_wait().ok().flatten();
            }
            all &= k.status.is_some();
        }
        all
    }

    /// SIGTERM to every process still running, SIGKILL to those still running
    /// [`TERM_GRACE`] later; all reaped.
    pub fn terminate(&mut self) {
        for k in &mut self.0 {
            if k.status.is_none() {
                // The child has not been reaped, so its pid still names it (at worst a zombie).
                if let Ok(pid) = libc::pid_t::try_from(k.child.id()) {
                    // SAFETY: kill(2) on our own unreaped child; no pointers.
                    unsafe { libc::kill(pid, libc::SIGTERM) };
                }
            }
        }
        let started = Instant::now();
        while !self.poll() && started.elapsed() < TERM_GRACE {
            std::thread::sleep(Duration::from_millis(10));
        }
        for k in &mut self.0 {
            if k.status.is_none() {
                let _ = k.child.kill();
                k.status = k.child.wait().ok();
            }
        }
    }
}

impl<T> Drop for Kids<T> {
    fn drop(&mut self) {
        self.terminate();
    }
}

/// The last few lines of a process's log, for error messages.
pub(crate) fn log_tail(log: &Path) -> String {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    let lines: Vec<&str> = text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && *l != "READY")
        .collect();
    let tail = &lines[lines.len().saturating_sub(3)..];
    if tail.is_empty() {
        format!("(no output; log {})", log.display())
    } else {
        format!("{} (log {})", tail.join(" | "), log.display())
    }
}
