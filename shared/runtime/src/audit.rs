//! The system-call audit of a real-time loop (`drivelab run --audit-syscalls`;
//! docs/architecture.md, "Real-time rules").
//!
//! A loop may make its wait and its wakes and nothing else: `futex` (the bus's wake words),
//! `clock_nanosleep` (the source's deadline), `clock_gettime` (the clock, when the vDSO
//! falls back to the kernel), `restart_syscall` (the kernel resuming one of these after a
//! SIGSTOP and SIGCONT) and `rt_sigreturn` (the return from a signal handler that
//! interrupted the loop). Counting ends with the loop or when the drive is asked to stop
//! (its peers' going away is then the stop's, not the loop's). The loop's thread installs a
//! seccomp filter on itself that lets these through untouched and hands every other call to
//! a supervisor thread of the same process (a seccomp user notification). While the audit is armed, the supervisor counts
//! the call by name; then it lets the call run as it would have (`CONTINUE`), so an audited
//! loop behaves as an unaudited one, a stray call costing it two thread switches more.
//!
//! A seccomp filter cannot be removed. After the loop the audit is disarmed: the thread's
//! calls still go through the supervisor, uncounted, until the process ends.

use anyhow::{bail, Result};
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};
use std::sync::{Arc, Mutex};
use syscalls::Sysno;

/// The calls a real-time loop may make (see the module's comment).
fn allowed() -> Vec<Sysno> {
    let waits = [
        Sysno::futex,
        Sysno::clock_nanosleep,
        Sysno::clock_gettime,
        Sysno::restart_syscall,
        Sysno::rt_sigreturn,
    ];
    // 32-bit ARM's C library makes the 64-bit-time forms of the same calls, and its kernel
    // has the older return from a handler too.
    #[cfg(target_arch = "arm")]
    let time64 = [
        Sysno::futex_time64,
        Sysno::clock_nanosleep_time64,
        Sysno::clock_gettime64,
        Sysno::sigreturn,
    ];
    #[cfg(not(target_arch = "arm"))]
    let time64: [Sysno; 0] = [];
    waits.into_iter().chain(time64).collect()
}

/// The system-call ABI of this build, as seccomp names it (`AUDIT_ARCH_*` of
/// `linux/audit.h`). A call through another ABI (a 32-bit call on x86_64) is never allowed.
const fn audit_arch() -> u32 {
    if cfg!(target_arch = "x86_64") {
        0xC000_003E
    } else if cfg!(target_arch = "aarch64") {
        0xC000_00B7
    } else if cfg!(target_arch = "arm") {
        0x4000_0028
    } else {
        // No call passes the arch check: every call is counted.
        0
    }
}

/// What the supervisor and the audited thread share.
#[derive(Debug)]
struct Shared {
    /// The filter's listener, -1 until the audited thread has installed it (once).
    fd: AtomicI32,
    /// Count the calls that reach the supervisor.
    armed: AtomicBool,
    /// The calls counted, by name (the supervisor's; the audited thread reads it once
    /// disarmed).
    found: Mutex<BTreeMap<String, u64>>,
    /// True once the drive is asked to stop: counting ends.
    stopping: fn() -> bool,
}

/// One loop's audit: started at set-up, armed by the loop's thread as its first sample
/// begins, disarmed after the loop. Its clones are the same audit.
#[derive(Debug, Clone)]
pub struct Audit {
    shared: Arc<Shared>,
    supervisor: std::thread::Thread,
}

impl Audit {
    /// Starts the supervisor thread. Call it before the real-time placement, so that the
    /// supervisor runs as a normal task wherever the kernel puts it (it inherits the
    /// calling thread's policy and CPUs). Counting ends once `stopping` says true.
    pub fn start(stopping: fn() -> bool) -> Result<Self> {
        let shared = Arc::new(Shared {
            fd: AtomicI32::new(-1),
            armed: AtomicBool::new(false),
            found: Mutex::new(BTreeMap::new()),
            stopping,
        });
        let s = shared.clone();
        let handle = std::thread::Builder::new()
            .name("syscall-audit".into())
            .spawn(move || supervise(&s))?;
        Ok(Self {
            shared,
            supervisor: handle.thread().clone(),
        })
    }

    /// Installs the filter on the calling thread and arms the audit: from here every call of
    /// this thread but its wait and wakes is counted. Its own calls (prctl, seccomp) come
    /// before the filter. Errors when the kernel has no seccomp user notification (before
    /// Linux 5.5), an emulator refuses seccomp, or the thread has a listening filter already.
    pub fn arm(&self) -> Result<()> {
        if self.shared.fd.load(Ordering::SeqCst) >= 0 {
            bail!("--audit-syscalls: this loop's audit was armed once already");
        }
        let arch = audit_arch();
        let allow = allowed();
        // seccomp_data: nr (offset 0), arch (offset 4).
        let ld = |off: u32| libc::sock_filter {
            code: (libc::BPF_LD | libc::BPF_W | libc::BPF_ABS) as u16,
            jt: 0,
            jf: 0,
            k: off,
        };
        let ret = |k: u32| libc::sock_filter {
            code: (libc::BPF_RET | libc::BPF_K) as u16,
            jt: 0,
            jf: 0,
            k,
        };
        let jeq = |k: u32, jt: u8, jf: u8| libc::sock_filter {
            code: (libc::BPF_JMP | libc::BPF_JEQ | libc::BPF_K) as u16,
            jt,
            jf,
            k,
        };
        let n = allow.len() as u8;
        // [arch?] → [nr = a0?] … [nr = an?] → notify; allow.
        let mut prog = vec![ld(4), jeq(arch, 0, n + 1), ld(0)];
        for (i, s) in allow.iter().enumerate() {
            // Equal: jump past the rest of the list and the notify to the allow.
            prog.push(jeq(s.id() as u32, n - i as u8, 0));
        }
        prog.push(ret(libc::SECCOMP_RET_USER_NOTIF));
        prog.push(ret(libc::SECCOMP_RET_ALLOW));
        let fprog = libc::sock_fprog {
            len: prog.len() as u16,
            filter: prog.as_mut_ptr(),
        };
        // SAFETY: PR_SET_NO_NEW_PRIVS takes plain integers; it lets an unprivileged thread
        // install a filter and only stops a later exec from gaining privileges.
        if unsafe { libc::prctl(libc::PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) } != 0 {
            bail!(
                "--audit-syscalls: prctl(PR_SET_NO_NEW_PRIVS): {}",
                std::io::Error::last_os_error()
            );
        }
        // SAFETY: `fprog` points at `prog`, which lives to the end of this function; the
        // kernel copies the program before the call returns.
        let fd = unsafe {
            libc::syscall(
                libc::SYS_seccomp,
                libc::SECCOMP_SET_MODE_FILTER,
                libc::SECCOMP_FILTER_FLAG_NEW_LISTENER,
                &fprog as *const libc::sock_fprog,
            )
        };
        if fd < 0 {
            let e = std::io::Error::last_os_error();
            bail!(
                "--audit-syscalls: the audit's seccomp filter was refused ({e}); it needs seccomp \
                 user notification (Linux 5.5 or later, and no emulator such as qemu-user between \
                 the host and the kernel)"
            );
        }
        self.shared.armed.store(true, Ordering::SeqCst);
        self.shared.fd.store(fd as i32, Ordering::SeqCst);
        // A futex wake at most: a call the filter lets through.
        self.supervisor.unpark();
        Ok(())
    }

    /// Stops counting and returns the calls counted, by name (empty when the loop made none).
    pub fn disarm(&self) -> BTreeMap<String, u64> {
        self.shared.armed.store(false, Ordering::SeqCst);
        self.shared
            .found
            .lock()
            .map(|m| m.clone())
            .unwrap_or_default()
    }
}

/// A call's name: its name in this build's ABI, or its number.
fn call_name(arch: u32, nr: i32) -> String {
    match usize::try_from(nr).ok().and_then(Sysno::new) {
        Some(s) if arch == audit_arch() => s.name().to_string(),
        _ => format!("#{nr} (ABI {arch:#x})"),
    }
}

/// The supervisor: waits for the listener, then counts each call it is handed while armed
/// and lets it run. Ends when the listener fails (every audited thread has ended).
fn supervise(s: &Shared) {
    let fd = loop {
        let fd = s.fd.load(Ordering::SeqCst);
        if fd >= 0 {
            break fd;
        }
        std::thread::park();
    };
    loop {
        // SAFETY: seccomp_notif is plain data; the kernel wants it zeroed before a receive.
        let mut req: libc::seccomp_notif = unsafe { std::mem::zeroed() };
        // SAFETY: `req` is a seccomp_notif the kernel fills; `fd` is the filter's listener.
        let r = unsafe { libc::ioctl(fd, libc::SECCOMP_IOCTL_NOTIF_RECV, &mut req) };
        if r != 0 {
            match std::io::Error::last_os_error().raw_os_error() {
                // Interrupted, or the caller was gone before its call was read.
                Some(libc::EINTR) | Some(libc::ENOENT) => continue,
                _ => return,
            }
        }
        if s.armed.load(Ordering::SeqCst) && !(s.stopping)() {
            if let Ok(mut m) = s.found.lock() {
                *m.entry(call_name(req.data.arch, req.data.nr)).or_insert(0) += 1;
            }
        }
        let mut resp = libc::seccomp_notif_resp {
            id: req.id,
            val: 0,
            error: 0,
            flags: libc::SECCOMP_USER_NOTIF_FLAG_CONTINUE as u32,
        };
        // SAFETY: `resp` answers the call `req` named; a caller gone since (ENOENT) is fine.
        unsafe { libc::ioctl(fd, libc::SECCOMP_IOCTL_NOTIF_SEND, &mut resp) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The audit counts each call of the audited thread by name while armed, lets it run
    /// (its results are the real ones), passes the wait calls uncounted, and counts nothing
    /// once disarmed.
    #[test]
    fn an_armed_audit_counts_stray_calls_and_lets_them_run() {
        let found = std::thread::spawn(|| {
            let audit = Audit::start(|| false).unwrap();
            audit.arm().unwrap();
            let pid = std::process::id();
            for _ in 0..3 {
                // SAFETY: getppid takes no argument and cannot fail.
                assert!(unsafe { libc::getppid() } > 0);
            }
            // The file is really read: the call ran.
            let status = std::fs::read_to_string("/proc/self/status").unwrap();
            assert!(status.contains(&format!("Tgid:\t{pid}")), "{status}");
            // Waits: a futex (park with a timeout) and a sleep are not counted.
            std::thread::park_timeout(std::time::Duration::from_micros(50));
            let mut ts = libc::timespec {
                tv_sec: 0,
                tv_nsec: 0,
            };
            // SAFETY: a valid timespec to fill.
            unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
            crate::rt::sleep_until_ns(crate::rt::now_ns() + 20_000);
            let found = audit.disarm();
            // SAFETY: as above; after the disarm, not counted.
            unsafe { libc::getppid() };
            assert_eq!(audit.disarm(), found);
            found
        })
        .join()
        .unwrap();
        assert_eq!(found.get("getppid"), Some(&3), "{found:?}");
        assert!(found.contains_key("openat"), "{found:?}");
        assert!(found.contains_key("read"), "{found:?}");
        for wait in ["futex", "clock_nanosleep", "clock_gettime"] {
            assert!(!found.contains_key(wait), "{wait} counted: {found:?}");
        }
    }

    /// A loop with no stray call: nothing counted, however long it waits.
    #[test]
    fn a_loop_of_waits_only_counts_nothing() {
        let found = std::thread::spawn(|| {
            let audit = Audit::start(|| false).unwrap();
            audit.arm().unwrap();
            for _ in 0..100 {
                crate::rt::sleep_until_ns(crate::rt::now_ns() + 10_000);
            }
            audit.disarm()
        })
        .join()
        .unwrap();
        assert!(found.is_empty(), "{found:?}");
    }

    /// Set by the next test: its drive is asked to stop.
    static STOPPING: AtomicBool = AtomicBool::new(false);

    extern "C" fn on_usr1(_: libc::c_int) {}

    /// Calls once the drive is asked to stop are not counted; the return from a signal
    /// handler that interrupted the loop is not counted (sending the signal is).
    #[test]
    fn counting_ends_at_a_stop_and_a_handlers_return_is_not_counted() {
        let found = std::thread::spawn(|| {
            let audit = Audit::start(|| STOPPING.load(Ordering::SeqCst)).unwrap();
            // SAFETY: a handler that does nothing, for a signal no other test uses.
            unsafe { libc::signal(libc::SIGUSR1, on_usr1 as *const () as libc::sighandler_t) };
            audit.arm().unwrap();
            // SAFETY: raise sends the signal to this thread; its handler returns at once.
            unsafe { libc::raise(libc::SIGUSR1) };
            for _ in 0..2 {
                // SAFETY: getppid takes no argument and cannot fail.
                unsafe { libc::getppid() };
            }
            STOPPING.store(true, Ordering::SeqCst);
            for _ in 0..3 {
                // SAFETY: as above.
                unsafe { libc::getppid() };
            }
            audit.disarm()
        })
        .join()
        .unwrap();
        assert_eq!(found.get("getppid"), Some(&2), "{found:?}");
        assert!(found.contains_key("tgkill"), "{found:?}");
        assert!(!found.contains_key("rt_sigreturn"), "{found:?}");
    }

    /// A second arm of the same audit is refused in one line.
    #[test]
    fn an_audit_is_armed_once() {
        let e = std::thread::spawn(|| {
            let audit = Audit::start(|| false).unwrap();
            audit.arm().unwrap();
            let e = audit.arm().unwrap_err().to_string();
            audit.disarm();
            e
        })
        .join()
        .unwrap();
        assert!(e.contains("armed once already") && !e.contains('\n'), "{e}");
    }
}
