//! Real-time setup done once before a service's loop, and the monotonic clock helpers the
//! loops use.
//!
//! [`setup_rt`] applies an [`RtRequest`] (core pinning, `SCHED_FIFO` priority, `mlockall`,
//! stack prefault) to the calling thread/process and returns an [`RtReport`] of what the
//! kernel actually granted, read back after the fact. Like copper-rs' thread pool, a refusal
//! is either a warning in the report ([`RtPolicy::Warn`], the default for development
//! machines) or an error that stops the service ([`RtPolicy::Strict`], for a real rig where
//! running without real-time guarantees would be worse than not running).
//!
//! Scope of each part:
//! * core pinning and the scheduling policy apply to the **calling thread** (Linux
//!   `sched_setaffinity(0, ..)` / `sched_setscheduler(0, ..)` act on the caller's thread id);
//!   threads spawned afterwards inherit them;
//! * `mlockall` applies to the whole **process**;
//! * the stack prefault touches the calling thread's stack.
//!
//! In [`RtPolicy::Strict`] the request is validated (priority range, core index, stack
//! headroom) before anything is changed, so an invalid request changes nothing. A refusal
//! from the kernel later in the sequence returns `Err` immediately; the parts applied before
//! it stay applied (the service is expected to exit).

use std::cell::Cell;
use std::io;

use anyhow::bail;
use serde::{Deserialize, Serialize};

/// What to do when part of an [`RtRequest`] cannot be granted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum RtPolicy {
    /// Record the refusal as a warning in the [`RtReport`], skip that part, carry on.
    Warn,
    /// Return an error naming what was refused and why.
    Strict,
}

/// Real-time settings a service asks for.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RtRequest {
    /// Pin the calling thread to this CPU (index as in `/sys/devices/system/cpu/cpuN`).
    /// `None` leaves the affinity mask unchanged.
    pub core: Option<usize>,
    /// `SCHED_FIFO` priority, 1..=99. `None` = `SCHED_OTHER` (a thread currently running
    /// under a real-time policy is moved back to `SCHED_OTHER`).
    pub fifo_priority: Option<u8>,
    /// Lock all current and future pages of the process in RAM (`mlockall`).
    pub lock_memory: bool,
    /// Touch this many bytes of the calling thread's stack so the pages are resident
    /// (and, with `lock_memory`, locked) before the loop starts. 0 = skip.
    pub prefault_stack_bytes: usize,
}

/// What [`setup_rt`] obtained, read back from the kernel where possible.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RtReport {
    /// The CPU the calling thread is pinned to (its affinity mask holds exactly this CPU),
    /// `None` when the thread may run on several CPUs.
    pub cpu: Option<usize>,
    /// Scheduling policy read back with `sched_getscheduler`: `"SCHED_FIFO"`,
    /// `"SCHED_OTHER"`, ...
    pub policy: String,
    /// Static priority read back with `sched_getparam` (0 for non-real-time policies).
    pub priority: i32,
    /// `mlockall` succeeded (or the process already has locked memory).
    pub memory_locked: bool,
    /// One entry per refused/skipped part (only under [`RtPolicy::Warn`]).
    pub warnings: Vec<String>,
}

impl RtReport {
    /// One line for a service's start-up log, e.g.
    /// `"plant: cpu 1, SCHED_FIFO 80, memory locked"` or
    /// `"plant: cpu unpinned, SCHED_OTHER, memory not locked; WARNING: ..."`.
    pub fn one_line(&self, service: &str) -> String {
        let cpu = match self.cpu {
            Some(c) => format!("cpu {c}"),
            None => "cpu unpinned".to_string(),
        };
        let sched = if self.policy == "SCHED_FIFO" || self.policy == "SCHED_RR" {
            format!("{} {}", self.policy, self.priority)
        } else {
            self.policy.clone()
        };
        let mem = if self.memory_locked {
            "memory locked"
        } else {
            "memory not locked"
        };
        let mut line = format!("{service}: {cpu}, {sched}, {mem}");
        for w in &self.warnings {
            line.push_str("; WARNING: ");
            line.push_str(w);
        }
        line
    }
}

/// Collects refusals according to the policy.
struct Refusals {
    policy: RtPolicy,
    warnings: Vec<String>,
}

impl Refusals {
    /// Under `Warn` records `msg` and returns `Ok`; under `Strict` returns `Err(msg)`.
    fn refuse(&mut self, msg: String) -> anyhow::Result<()> {
        match self.policy {
            RtPolicy::Warn => {
                self.warnings.push(msg);
                Ok(())
            }
            RtPolicy::Strict => bail!(msg),
        }
    }
}

/// `MCL_ONFAULT` (Linux ≥ 4.4, all the architectures drivelab builds for; the libc crate
/// defines it for musl only).
const MCL_ONFAULT: libc::c_int = 4;

/// Applies `req` to the calling thread/process and reports what was granted.
///
/// Order: validate, `mlockall`, stack prefault, CPU affinity, scheduling policy (the policy
/// goes last so the set-up work itself does not run at real-time priority).
///
/// Each refusal (invalid priority or core, `EPERM`, `EINVAL`, `ENOMEM`, too little stack)
/// becomes a warning in the report under [`RtPolicy::Warn`] (that part is skipped), and an
/// `Err` with a one-line message naming what was refused and why under
/// [`RtPolicy::Strict`].
pub fn setup_rt(req: &RtRequest, policy: RtPolicy) -> anyhow::Result<RtReport> {
    let mut r = Refusals {
        policy,
        warnings: Vec::new(),
    };

    // ---- validation (nothing changed yet) ----
    let n_cpus = online_cpus();
    let mut core = req.core;
    if let Some(c) = core {
        if c >= n_cpus || c >= libc::CPU_SETSIZE as usize {
            core = None;
            r.refuse(format!(
                "pinning to cpu {c} refused: invalid core ({n_cpus} CPUs online, valid 0..={})",
                n_cpus.saturating_sub(1)
            ))?;
        }
    }
    let mut fifo = req.fifo_priority;
    if let Some(p) = fifo {
        if !(1..=99).contains(&p) {
            fifo = None;
            r.refuse(format!(
                "SCHED_FIFO priority {p} refused: out of range (valid 1..=99)"
            ))?;
        }
    }
    let mut prefault = req.prefault_stack_bytes;
    if prefault > 0 {
        if let Some(headroom) = stack_headroom() {
            // Keep a margin for this function's own frames and whatever runs after, and
            // count each recursion level's frame overhead on top of its buffer.
            let chunks = headroom.saturating_sub(PREFAULT_MARGIN) / (PREFAULT_CHUNK + 1024);
            let usable = chunks * PREFAULT_CHUNK;
            if prefault > usable {
                r.refuse(format!(
                    "stack prefault of {prefault} bytes refused: only {usable} bytes of stack \
                     headroom left in this thread (prefaulting {usable} instead)"
                ))?;
                prefault = usable;
            }
        }
    }

    // ---- memory locking (process-wide) ----
    let mut memory_locked = false;
    if req.lock_memory {
        // SAFETY: mlockall takes only flag bits and touches no memory of ours; it cannot
        // violate Rust invariants, it only changes how the kernel pages this process.
        let rc = unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE) };
        if rc == 0 {
            memory_locked = true;
            // Everything mapped so far is resident and locked now. Mappings made later (a
            // restarted peer's publisher segment, 8-25 MB, mapped by its subscribers at the
            // first receive) are locked page by page as they are touched instead of being
            // populated whole inside a real-time loop: populating them stalled the plant for
            // up to 17 ms at every restart. Kernels before 4.4 refuse the flag: keep the
            // first call's behaviour then.
            // SAFETY: as above, only flag bits.
            let _ = unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE | MCL_ONFAULT) };
        } else {
            let e = io::Error::last_os_error();
            let why = match e.raw_os_error() {
                Some(libc::ENOMEM) | Some(libc::EPERM) => format!(
                    " (needs root or CAP_IPC_LOCK, or RLIMIT_MEMLOCK above the process size; \
                     RLIMIT_MEMLOCK is {})",
                    fmt_rlimit_bytes(get_rlimit(libc::RLIMIT_MEMLOCK).0)
                ),
                _ => String::new(),
            };
            r.refuse(format!(
                "mlockall(MCL_CURRENT|MCL_FUTURE) refused: {}{why}",
                os_error_text(&e)
            ))?;
        }
    }
    if !memory_locked {
        // Already locked by an earlier call (e.g. another thread's setup).
        memory_locked = locked_memory_kib().is_some_and(|kib| kib > 0);
    }

    // ---- stack prefault (calling thread) ----
    if prefault > 0 {
        prefault_stack(prefault);
    }

    // ---- CPU affinity (calling thread) ----
    if let Some(c) = core {
        if let Err(e) = set_affinity_single(c) {
            r.refuse(format!(
                "pinning to cpu {c} refused: {}{}",
                os_error_text(&e),
                if e.raw_os_error() == Some(libc::EINVAL) {
                    " (cpu offline or outside this process's cpuset)"
                } else {
                    ""
                }
            ))?;
        }
    }

    // ---- scheduling policy (calling thread) ----
    match fifo {
        Some(p) => {
            if let Err(e) = set_scheduler(libc::SCHED_FIFO, i32::from(p)) {
                r.refuse(fifo_refusal_message(p, &e))?;
            }
        }
        None => {
            // None = SCHED_OTHER: undo a real-time policy inherited or set earlier.
            let current = current_policy_raw();
            if current == libc::SCHED_FIFO || current == libc::SCHED_RR {
                if let Err(e) = set_scheduler(libc::SCHED_OTHER, 0) {
                    r.refuse(format!(
                        "return to SCHED_OTHER refused: {}",
                        os_error_text(&e)
                    ))?;
                }
            }
        }
    }

    // ---- read back ----
    let (policy_name, priority) = current_sched();
    Ok(RtReport {
        cpu: pinned_cpu(),
        policy: policy_name,
        priority,
        memory_locked,
        warnings: r.warnings,
    })
}

/// The one-line message for a refused `SCHED_FIFO` request.
fn fifo_refusal_message(p: u8, e: &io::Error) -> String {
    let mut msg = format!("SCHED_FIFO priority {p} refused: {}", os_error_text(e));
    if e.raw_os_error() == Some(libc::EPERM) {
        let (soft, _) = get_rlimit(libc::RLIMIT_RTPRIO);
        msg.push_str(&format!(
            " (needs root or CAP_SYS_NICE / RLIMIT_RTPRIO; RLIMIT_RTPRIO is {}",
            fmt_rlimit_count(soft)
        ));
        // SAFETY: geteuid has no preconditions and cannot fail.
        if unsafe { libc::geteuid() } == 0 {
            msg.push_str(
                "; running as root, so probably a container without CAP_SYS_NICE \
                 or a cgroup with no real-time budget (cpu.rt_runtime_us = 0)",
            );
        }
        msg.push(')');
    }
    msg
}

/// Bytes kept free below the prefaulted region of the stack.
const PREFAULT_MARGIN: usize = 128 * 1024;

/// Bytes touched per recursion level of [`prefault_chunk`].
const PREFAULT_CHUNK: usize = 16 * 1024;

/// Touches `bytes` bytes of the calling thread's stack, below the current frame.
fn prefault_stack(bytes: usize) {
    prefault_chunk(bytes.div_ceil(PREFAULT_CHUNK));
}

/// One frame of [`PREFAULT_CHUNK`] bytes, written page by page, then recursion for the
/// remaining `chunks - 1`. Not inlined and the buffer is observed after the recursive call
/// (no tail call), so each level really occupies its own stack frame.
#[inline(never)]
fn prefault_chunk(chunks: usize) {
    if chunks == 0 {
        return;
    }
    let mut buf = [0u8; PREFAULT_CHUNK];
    let p = buf.as_mut_ptr();
    let mut i = 0;
    while i < PREFAULT_CHUNK {
        // SAFETY: `p.add(i)` with i < PREFAULT_CHUNK stays inside `buf`, a live local array we
        // exclusively borrow; a volatile write of a u8 to it is always valid.
        unsafe { std::ptr::write_volatile(p.add(i), 1) };
        i += 512;
    }
    prefault_chunk(chunks - 1);
    std::hint::black_box(&mut buf);
}

/// Bytes between the current stack pointer (approximately: the address of a local) and
/// the lowest usable address of the calling thread's stack, if the C library can tell.
fn stack_headroom() -> Option<usize> {
    let marker = 0u8;
    let here = std::hint::black_box(&marker) as *const u8 as usize;
    // SAFETY: an all-zero pthread_attr_t is a valid bit pattern for the out-parameter;
    // pthread_getattr_np initialises it before we read it.
    let mut attr: libc::pthread_attr_t = unsafe { std::mem::zeroed() };
    // SAFETY: pthread_self() is the calling (live) thread and `attr` is a valid, writable
    // pthread_attr_t; on success it must be destroyed, which we do below.
    let rc = unsafe { libc::pthread_getattr_np(libc::pthread_self(), &mut attr) };
    if rc != 0 {
        return None;
    }
    let mut addr: *mut libc::c_void = std::ptr::null_mut();
    let mut size: libc::size_t = 0;
    // SAFETY: `attr` was initialised by pthread_getattr_np above; `addr` and `size` are valid
    // out-pointers.
    let rc2 = unsafe { libc::pthread_attr_getstack(&attr, &mut addr, &mut size) };
    // SAFETY: `attr` was initialised by a successful pthread_getattr_np and is destroyed once.
    unsafe { libc::pthread_attr_destroy(&mut attr) };
    if rc2 != 0 || addr.is_null() {
        return None;
    }
    let low = addr as usize;
    // The guard page(s) are included in the reported range on some libcs; they are
    // covered by PREFAULT_MARGIN.
    if here > low && here - low <= size {
        Some(here - low)
    } else {
        None
    }
}

/// Pins the calling thread to exactly `cpu`.
fn set_affinity_single(cpu: usize) -> io::Result<()> {
    // SAFETY: cpu_set_t is a plain bit array; all-zero is a valid (empty) set.
    let mut set: libc::cpu_set_t = unsafe { std::mem::zeroed() };
    // SAFETY: the caller checked `cpu < CPU_SETSIZE`, so CPU_SET's index into the bit array
    // is in range; `set` is a valid, exclusively borrowed cpu_set_t.
    unsafe { libc::CPU_SET(cpu, &mut set) };
    // SAFETY: pid 0 = the calling thread; `set` is a valid cpu_set_t of the size passed.
    let rc = unsafe { libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set) };
    if rc == 0 {
        Ok(())
    } else {
        Err(io::Error::last_os_error())
    }
}

/// The calling thread's affinity mask; None when it cannot be read.
fn thread_cpu_set() -> Option<libc::cpu_set_t> {
    // SAFETY: cpu_set_t is a plain bit array; all-zero is a valid (empty) set.
    let mut set: libc::cpu_set_t = unsafe { std::mem::zeroed() };
    // SAFETY: pid 0 = the calling thread; `set` is a valid, writable cpu_set_t of the size
    // passed.
    let rc =
        unsafe { libc::sched_getaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &mut set) };
    (rc == 0).then_some(set)
}

/// The CPUs the calling thread's affinity mask allows, in order; None when it cannot be read.
pub fn affinity_cpus() -> Option<Vec<usize>> {
    let set = thread_cpu_set()?;
    // SAFETY: every `c` is below CPU_SETSIZE, so CPU_ISSET reads inside `set`'s bit array.
    Some(
        (0..libc::CPU_SETSIZE as usize)
            .filter(|&c| unsafe { libc::CPU_ISSET(c, &set) })
            .collect(),
    )
}

/// The single CPU the calling thread's affinity mask allows, if exactly one.
fn pinned_cpu() -> Option<usize> {
    match affinity_cpus()?.as_slice() {
        [c] => Some(*c),
        _ => None,
    }
}

/// `sched_setscheduler(0, policy, prio)` for the calling thread.
pub fn set_scheduler(policy: libc::c_int, priority: i32) -> io::Result<()> {
    let param = libc::sched_param {
        sched_priority: priority,
    };
    // SAFETY: pid 0 = the calling thread; `param` is a valid sched_param that outlives the
    // call. Changing the policy has no memory-safety implications.
    let rc = unsafe { libc::sched_setscheduler(0, policy, &param) };
    if rc == 0 {
        Ok(())
    } else {
        Err(io::Error::last_os_error())
    }
}

/// Raw policy of the calling thread (without `SCHED_RESET_ON_FORK`), or -1 on error.
pub fn current_policy_raw() -> libc::c_int {
    // SAFETY: pid 0 = the calling thread; no pointers involved.
    let p = unsafe { libc::sched_getscheduler(0) };
    if p < 0 {
        p
    } else {
        p & !libc::SCHED_RESET_ON_FORK
    }
}

/// (policy name, priority) of the calling thread, read back from the kernel.
fn current_sched() -> (String, i32) {
    let name = policy_name(current_policy_raw());
    let mut param = libc::sched_param { sched_priority: 0 };
    // SAFETY: pid 0 = the calling thread; `param` is a valid, writable sched_param.
    let rc = unsafe { libc::sched_getparam(0, &mut param) };
    let prio = if rc == 0 { param.sched_priority } else { 0 };
    (name, prio)
}

/// Name of a Linux scheduling policy number.
pub(crate) fn policy_name(p: libc::c_int) -> String {
    match p {
        libc::SCHED_OTHER => "SCHED_OTHER".into(),
        libc::SCHED_FIFO => "SCHED_FIFO".into(),
        libc::SCHED_RR => "SCHED_RR".into(),
        libc::SCHED_BATCH => "SCHED_BATCH".into(),
        libc::SCHED_IDLE => "SCHED_IDLE".into(),
        6 => "SCHED_DEADLINE".into(),
        p if p < 0 => "unknown".into(),
        p => format!("policy {p}"),
    }
}

/// `strerror`-style text without std's " (os error N)" suffix.
pub fn os_error_text(e: &io::Error) -> String {
    let s = e.to_string();
    match s.rfind(" (os error ") {
        Some(i) => s[..i].to_string(),
        None => s,
    }
}

/// The C type of `getrlimit`'s resource argument (an enum in glibc, `int` elsewhere).
#[cfg(target_env = "gnu")]
pub type RlimitResource = libc::__rlimit_resource_t;
/// The C type of `getrlimit`'s resource argument (an enum in glibc, `int` elsewhere).
#[cfg(not(target_env = "gnu"))]
pub type RlimitResource = libc::c_int;

/// (soft, hard) limit of `resource`; `RLIM_INFINITY` for unlimited, (0, 0) on error.
pub fn get_rlimit(resource: RlimitResource) -> (libc::rlim_t, libc::rlim_t) {
    let mut lim = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: `lim` is a valid, writable rlimit; getrlimit only writes into it.
    let rc = unsafe { libc::getrlimit(resource, &mut lim) };
    if rc == 0 {
        (lim.rlim_cur, lim.rlim_max)
    } else {
        (0, 0)
    }
}

/// A byte limit for humans: "unlimited", "8 MiB", "65536 bytes".
pub fn fmt_rlimit_bytes(v: libc::rlim_t) -> String {
    if v == libc::RLIM_INFINITY {
        "unlimited".into()
    } else if v >= 1024 * 1024 && v.is_multiple_of(1024 * 1024) {
        format!("{} MiB", v / (1024 * 1024))
    } else if v >= 1024 && v.is_multiple_of(1024) {
        format!("{} KiB", v / 1024)
    } else {
        format!("{v} bytes")
    }
}

/// A count limit for humans: "unlimited" or the number.
pub fn fmt_rlimit_count(v: libc::rlim_t) -> String {
    if v == libc::RLIM_INFINITY {
        "unlimited".into()
    } else {
        v.to_string()
    }
}

/// `VmLck` of this process from `/proc/self/status`, KiB.
fn locked_memory_kib() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmLck:"))
        .and_then(|rest| rest.split_whitespace().next())
        .and_then(|v| v.parse().ok())
}

/// How much memory a one-stage host may hold locked once its bus is open (its code, heap
/// and histograms, its own and its peers' bus segments: 18–28 MiB measured in the default
/// drive), which `--check-rt` makes sure this process could lock.
pub const HOST_LOCKED_BYTES: usize = 32 << 20;

/// What a host of `stages` stages may hold locked: [`HOST_LOCKED_BYTES`] and 8 MiB for each
/// stage after the first (the one-process topology's host, four stages, locked 35.2 MiB:
/// 8.7 MiB more than the largest one-stage host, about 3 MiB a stage).
pub fn host_locked_bytes(stages: usize) -> usize {
    HOST_LOCKED_BYTES.saturating_add(stages.saturating_sub(1).saturating_mul(8 << 20))
}

/// `mlock2`'s flag that locks pages as they are first touched instead of populating them
/// (Linux ≥ 4.4, the same value on every architecture; the libc crate does not export it).
const MLOCK_ONFAULT: libc::c_uint = 1;

/// Whether this process, with nothing locked yet, may lock `total` bytes: it maps that
/// much (anonymous, never touched), locks it on fault (`mlock2(MLOCK_ONFAULT)`, so nothing
/// is populated) and unmaps it again. The kernel checks `RLIMIT_MEMLOCK` against the whole
/// length when the lock is asked for, so a limit that a host would run into once it maps
/// its bus is refused here, while nothing has started, and whatever this executable's own
/// size.
pub fn check_lock_headroom(total: usize) -> anyhow::Result<()> {
    // SAFETY: a fresh anonymous private mapping that nothing else refers to; the result is
    // checked, and the memory is never accessed.
    let p = unsafe {
        libc::mmap(
            std::ptr::null_mut(),
            total,
            libc::PROT_READ | libc::PROT_WRITE,
            libc::MAP_PRIVATE | libc::MAP_ANONYMOUS | libc::MAP_NORESERVE,
            -1,
            0,
        )
    };
    if p == libc::MAP_FAILED {
        let e = io::Error::last_os_error();
        bail!(
            "memory lock: cannot map {} MiB to try locking it: {}",
            total >> 20,
            os_error_text(&e)
        );
    }
    // SAFETY: `p` is the mapping of `total` bytes made above; mlock2 only changes its
    // locking, and with MLOCK_ONFAULT touches none of it.
    let rc = unsafe { libc::mlock2(p, total, MLOCK_ONFAULT) };
    let e = io::Error::last_os_error();
    // SAFETY: `p` is the mapping of `total` bytes made above, referred to nowhere else;
    // unmapping it also drops its lock.
    unsafe { libc::munmap(p, total) };
    if rc != 0 {
        bail!(
            "memory lock: a stage host holds up to about {} MiB locked once its bus is open, \
             and this process could not lock that much: {} (needs root or CAP_IPC_LOCK, or \
             RLIMIT_MEMLOCK of at least {} MiB; RLIMIT_MEMLOCK is {})",
            total >> 20,
            os_error_text(&e),
            total >> 20,
            fmt_rlimit_bytes(get_rlimit(libc::RLIMIT_MEMLOCK).0)
        );
    }
    Ok(())
}

/// The PM QoS CPU latency device.
pub const CPU_DMA_LATENCY: &str = "/dev/cpu_dma_latency";

/// A held PM QoS CPU wake-up latency request: while the file stays open the kernel keeps
/// idle CPUs out of states whose exit latency exceeds the value. A per-process request, not a
/// kernel setting: it is released when this value is dropped or the process dies.
#[derive(Debug)]
pub struct CpuLatencyRequest {
    _file: std::fs::File,
    /// The requested latency, µs.
    pub value_us: u32,
}

impl CpuLatencyRequest {
    /// Holds a request of `value_us` on [`CPU_DMA_LATENCY`].
    pub fn hold(value_us: u32) -> std::io::Result<Self> {
        Self::hold_at(std::path::Path::new(CPU_DMA_LATENCY), value_us)
    }

    /// Holds a request of `value_us` on the device (or, in tests, file) at `path`: opens it,
    /// writes the value as a native-endian 32-bit integer and keeps it open.
    pub fn hold_at(path: &std::path::Path, value_us: u32) -> std::io::Result<Self> {
        use std::io::Write;
        let mut f = std::fs::OpenOptions::new().write(true).open(path)?;
        let v = i32::try_from(value_us).unwrap_or(i32::MAX);
        f.write_all(&v.to_ne_bytes())?;
        Ok(Self { _file: f, value_us })
    }
}

/// `CLOCK_MONOTONIC` now, nanoseconds.
pub fn now_ns() -> u64 {
    clock_ns(libc::CLOCK_MONOTONIC)
}

/// The calling thread's time on the CPU so far (`CLOCK_THREAD_CPUTIME_ID`), nanoseconds. A
/// system call (no vDSO path): not for a real-time loop.
pub fn thread_cpu_ns() -> u64 {
    clock_ns(libc::CLOCK_THREAD_CPUTIME_ID)
}

fn clock_ns(clock: libc::clockid_t) -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec; both clocks used here always exist on
    // Linux, so the call cannot fail.
    unsafe { libc::clock_gettime(clock, &mut ts) };
    (ts.tv_sec as u64) * 1_000_000_000 + ts.tv_nsec as u64
}

/// Where a real-time schedule starts: 2 ms from now, and when `tick_aligned` on the tick of
/// the CPU the caller runs on (its own, once pinned): the first instant from there that is
/// as far past a whole millisecond as that CPU's tick ([`crate::tick::on_grid`]). Where the
/// tick cannot be read (`/proc/timer_list` is root's) the schedule starts on a whole
/// millisecond, where the tick falls on most kernels (docs/architecture.md, "The tick and
/// the samples"). Called once, before a loop: it reads a file.
pub fn schedule_start_ns(tick_aligned: bool) -> u64 {
    let start = now_ns() + 2_000_000;
    if tick_aligned {
        let phase = crate::tick::this_cpu()
            .and_then(|cpu| crate::tick::phase_of(cpu).ok())
            .unwrap_or(0);
        crate::tick::on_grid(start, phase)
    } else {
        start
    }
}

/// Sleeps until the absolute `CLOCK_MONOTONIC` deadline `deadline_ns` (ns), with
/// `clock_nanosleep(TIMER_ABSTIME)`; restarts after signals (`EINTR`) — with an absolute
/// deadline a restart never accumulates drift. A deadline that has passed returns at once,
/// without the system call: `clock_nanosleep` to a past deadline still arms the timer and takes
/// its interrupt (15–21 µs on a 2-vCPU VM, where programming the timer traps into the
/// hypervisor), which a loop catching up after a stall would pay on every late sample
/// (docs/architecture.md, "Falling behind and catching up").
pub fn sleep_until_ns(deadline_ns: u64) {
    sleep_until_with(deadline_ns, now_ns, |ts| {
        // SAFETY: `ts` is a valid timespec; the remaining-time pointer may be null (and is
        // unused with TIMER_ABSTIME).
        unsafe {
            libc::clock_nanosleep(
                libc::CLOCK_MONOTONIC,
                libc::TIMER_ABSTIME,
                ts,
                std::ptr::null_mut(),
            )
        }
    })
}

thread_local! {
    /// See [`syscalls`]. Per thread, so that a count belongs to one loop (a test's threads
    /// do not add to each other's).
    static SYSCALLS: Cell<u64> = const { Cell::new(0) };
}

/// Counts one system call made at a call site named in [`syscalls`]: a thread-local add, no
/// lock, no allocation, no system call.
#[inline]
pub fn count_syscall() {
    SYSCALLS.with(|c| c.set(c.get() + 1));
}

/// The system calls the calling thread has made so far at drivelab's own blocking and waking
/// call sites: `clock_nanosleep` in [`sleep_until_ns`], `FUTEX_WAIT` and `FUTEX_WAKE` on the
/// bus's wake words, and the bench's Unix-socket sends and receives. Not counted: what
/// iceoryx2 calls itself (its event service, set-up) and everything outside these sites.
pub fn syscalls() -> u64 {
    SYSCALLS.with(Cell::get)
}

/// [`sleep_until_ns`] with its clock and its `clock_nanosleep` passed in (`nanosleep` returns
/// the error number, as `clock_nanosleep` does).
fn sleep_until_with(
    deadline_ns: u64,
    now: impl Fn() -> u64,
    mut nanosleep: impl FnMut(&libc::timespec) -> libc::c_int,
) {
    if now() >= deadline_ns {
        return;
    }
    let ts = libc::timespec {
        tv_sec: (deadline_ns / 1_000_000_000) as libc::time_t,
        tv_nsec: (deadline_ns % 1_000_000_000) as libc::c_long,
    };
    // clock_nanosleep returns the error number directly (it does not set errno).
    loop {
        count_syscall();
        if nanosleep(&ts) != libc::EINTR {
            break;
        }
    }
}

/// Number of online CPUs (`sysconf(_SC_NPROCESSORS_ONLN)`, at least 1).
pub fn online_cpus() -> usize {
    // SAFETY: sysconf takes a constant name and has no memory effects.
    let n = unsafe { libc::sysconf(libc::_SC_NPROCESSORS_ONLN) };
    if n >= 1 {
        n as usize
    } else {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    }
}

/// Moves this process off the drive's real-time cores `rt_cores` (bit i = CPU i; when
/// another core is left) and lowers its priority to nice 10, so that a tool beside the drive
/// (the monitor, the Zenoh bridge) competes with nothing the drive needs. Call it before
/// starting threads: they inherit both. Returns a note naming `who`.
pub fn keep_off(rt_cores: u64, who: &str) -> String {
    // SAFETY: setpriority on our own process (who = 0) only changes our nice value.
    unsafe {
        libc::setpriority(libc::PRIO_PROCESS, 0, 10);
    }
    let free = cpus_besides(rt_cores);
    if free.is_empty() {
        return format!("every core runs the drive: the {who} shares them at nice 10");
    }
    if set_affinity(&cpu_set(&free)) {
        format!("{who} on CPU {free:?}, nice 10")
    } else {
        format!("could not move the {who} off the drive's cores")
    }
}

/// The online CPUs (the first 64) that are not in `rt_cores` (bit i = CPU i).
fn cpus_besides(rt_cores: u64) -> Vec<usize> {
    let n = online_cpus().min(64);
    (0..n).filter(|c| rt_cores & (1 << c) == 0).collect()
}

/// A CPU mask of `cpus` (each below 64).
fn cpu_set(cpus: &[usize]) -> libc::cpu_set_t {
    // SAFETY: cpu_set_t is a plain bit array; all-zero is a valid (empty) set.
    let mut set: libc::cpu_set_t = unsafe { std::mem::zeroed() };
    for &c in cpus {
        // SAFETY: the index is below 64, within the set's 1024 bits.
        unsafe { libc::CPU_SET(c, &mut set) };
    }
    set
}

/// Sets the calling thread's CPU mask; false when the kernel refuses it.
fn set_affinity(set: &libc::cpu_set_t) -> bool {
    // SAFETY: `set` is a valid cpu_set_t of the size passed; pid 0 = the calling thread.
    unsafe { libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), set) == 0 }
}

/// The calling thread kept off the drive's real-time cores while this lives
/// ([`off_rt_cores`]); dropping it gives the thread its previous CPU mask back.
#[derive(Debug)]
pub struct OffRtCores {
    previous: Option<libc::cpu_set_t>,
    cpus: Vec<usize>,
}

impl OffRtCores {
    /// The CPUs the thread may run on now; empty when it was left as it was.
    pub fn cpus(&self) -> &[usize] {
        &self.cpus
    }

    /// The mask the thread had before, for a child process to start with again (`None` when
    /// the thread was left as it was).
    pub fn previous(&self) -> Option<libc::cpu_set_t> {
        self.previous
    }
}

impl Drop for OffRtCores {
    fn drop(&mut self) {
        if let Some(set) = &self.previous {
            set_affinity(set);
        }
    }
}

/// Keeps the calling thread, and the threads it starts from now on, off the drive's
/// real-time cores `rt_cores` (bit i = CPU i) for as long as the guard lives: on a kernel
/// without full preemption, a normal task inside a system call on a stage's core holds up
/// the stage's wake-up until the call returns. Its priority is not changed. When no other
/// core is online, or the mask cannot be read or set, the thread is left as it was.
pub fn off_rt_cores(rt_cores: u64) -> OffRtCores {
    let left = OffRtCores {
        previous: None,
        cpus: Vec::new(),
    };
    let free = cpus_besides(rt_cores);
    if free.is_empty() {
        return left;
    }
    let Some(previous) = thread_cpu_set() else {
        return left;
    };
    if !set_affinity(&cpu_set(&free)) {
        return left;
    }
    OffRtCores {
        previous: Some(previous),
        cpus: free,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn req() -> RtRequest {
        RtRequest {
            core: None,
            fifo_priority: None,
            lock_memory: false,
            prefault_stack_bytes: 0,
        }
    }

    /// Runs `f` in a fresh thread so affinity/policy changes never leak into the test
    /// harness threads.
    fn in_thread<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> T {
        std::thread::spawn(f).join().expect("test thread panicked")
    }

    #[test]
    fn a_thread_kept_off_the_drive_cores_gets_its_mask_back() {
        in_thread(|| {
            let before = affinity_cpus().unwrap();
            let n = online_cpus().min(64);
            // The last online CPU runs the drive.
            let drive = n - 1;
            let off = off_rt_cores(1 << drive);
            if n == 1 {
                // Nothing else to run on: left as it was.
                assert!(off.cpus().is_empty() && off.previous().is_none());
                assert_eq!(affinity_cpus().unwrap(), before);
                return;
            }
            let expect: Vec<usize> = (0..drive).collect();
            assert_eq!(off.cpus(), expect.as_slice());
            assert_eq!(affinity_cpus().unwrap(), expect);
            // A thread started meanwhile inherits the narrower mask.
            let child = std::thread::spawn(affinity_cpus).join().unwrap().unwrap();
            assert_eq!(child, expect);
            drop(off);
            assert_eq!(affinity_cpus().unwrap(), before);
        });
    }

    #[test]
    fn every_core_running_the_drive_leaves_the_thread_as_it_was() {
        in_thread(|| {
            let before = affinity_cpus().unwrap();
            let off = off_rt_cores(u64::MAX);
            assert!(off.cpus().is_empty() && off.previous().is_none());
            assert_eq!(affinity_cpus().unwrap(), before);
        });
    }

    #[test]
    fn one_line_granted() {
        let r = RtReport {
            cpu: Some(1),
            policy: "SCHED_FIFO".into(),
            priority: 80,
            memory_locked: true,
            warnings: vec![],
        };
        assert_eq!(
            r.one_line("plant"),
            "plant: cpu 1, SCHED_FIFO 80, memory locked"
        );
    }

    #[test]
    fn one_line_with_warnings() {
        let r = RtReport {
            cpu: None,
            policy: "SCHED_OTHER".into(),
            priority: 0,
            memory_locked: false,
            warnings: vec!["a refused: x".into(), "b refused: y".into()],
        };
        assert_eq!(
            r.one_line("ctrl"),
            "ctrl: cpu unpinned, SCHED_OTHER, memory not locked; WARNING: a refused: x; \
             WARNING: b refused: y"
        );
    }

    #[test]
    fn report_serde_roundtrip() {
        let r = RtReport {
            cpu: Some(0),
            policy: "SCHED_FIFO".into(),
            priority: 10,
            memory_locked: false,
            warnings: vec!["w".into()],
        };
        let s = serde_json::to_string(&r).unwrap();
        let back: RtReport = serde_json::from_str(&s).unwrap();
        assert_eq!(back.one_line("x"), r.one_line("x"));
        let p: RtPolicy = serde_json::from_str("\"Strict\"").unwrap();
        assert_eq!(p, RtPolicy::Strict);
    }

    #[test]
    fn invalid_core_warns_or_errs() {
        let (warn, strict) = in_thread(|| {
            let mut q = req();
            q.core = Some(10_000);
            (setup_rt(&q, RtPolicy::Warn), setup_rt(&q, RtPolicy::Strict))
        });
        let rep = warn.expect("Warn must not fail");
        assert_eq!(rep.warnings.len(), 1, "{:?}", rep.warnings);
        assert!(rep.warnings[0].contains("cpu 10000"), "{}", rep.warnings[0]);
        assert!(rep.one_line("t").contains("WARNING: pinning to cpu 10000"));
        let err = strict.expect_err("Strict must fail").to_string();
        assert!(
            err.contains("cpu 10000") && err.contains("invalid core"),
            "{err}"
        );
    }

    #[test]
    fn invalid_priority_warns_or_errs() {
        for p in [0u8, 100, 255] {
            let (warn, strict) = in_thread(move || {
                let mut q = req();
                q.fifo_priority = Some(p);
                (setup_rt(&q, RtPolicy::Warn), setup_rt(&q, RtPolicy::Strict))
            });
            let rep = warn.expect("Warn must not fail");
            assert_eq!(rep.warnings.len(), 1);
            assert!(rep.warnings[0].contains(&format!("priority {p}")));
            // The invalid priority was skipped: still SCHED_OTHER.
            assert_eq!(rep.policy, "SCHED_OTHER");
            let err = strict.expect_err("Strict must fail").to_string();
            assert!(err.contains("out of range"), "{err}");
        }
    }

    #[test]
    fn strict_validation_changes_nothing() {
        // Valid core 0 + invalid priority: Strict must fail before pinning.
        let (before, after, res) = in_thread(|| {
            let before = pinned_cpu();
            let mut q = req();
            q.core = Some(0);
            q.fifo_priority = Some(0);
            let res = setup_rt(&q, RtPolicy::Strict);
            (before, pinned_cpu(), res.is_err())
        });
        assert!(res);
        assert_eq!(before, after);
    }

    #[test]
    fn empty_request_is_clean() {
        let rep = in_thread(|| setup_rt(&req(), RtPolicy::Strict)).unwrap();
        assert!(rep.warnings.is_empty());
        assert_eq!(rep.policy, "SCHED_OTHER");
        assert_eq!(rep.priority, 0);
    }

    /// Root: the kernel grants SCHED_FIFO and mlock whatever the limits.
    fn root() -> bool {
        // SAFETY: geteuid takes no arguments and cannot fail.
        unsafe { libc::geteuid() == 0 }
    }

    #[test]
    fn pin_to_a_core_of_the_affinity_mask_is_granted() {
        let core = *affinity_cpus().unwrap().last().unwrap();
        let rep = in_thread(move || {
            let mut q = req();
            q.core = Some(core);
            setup_rt(&q, RtPolicy::Warn).unwrap()
        });
        assert!(rep.warnings.is_empty(), "{:?}", rep.warnings);
        assert_eq!(rep.cpu, Some(core));
        assert!(rep.one_line("t").starts_with(&format!("t: cpu {core}, ")));
    }

    #[test]
    fn fifo_granted_or_refused_then_restored() {
        // Granted to root or under an RLIMIT_RTPRIO of 10 or more; refused (EPERM: a
        // warning, or an error when strict) otherwise.
        let may = root() || get_rlimit(libc::RLIMIT_RTPRIO).0 >= 10;
        let (warn, strict, restored) = in_thread(|| {
            let mut q = req();
            q.fifo_priority = Some(10);
            let warn = setup_rt(&q, RtPolicy::Warn).unwrap();
            let strict = setup_rt(&q, RtPolicy::Strict).map_err(|e| e.to_string());
            // Back to SCHED_OTHER before the thread ends.
            let restored = setup_rt(&req(), RtPolicy::Strict).unwrap();
            (warn, strict, restored)
        });
        assert_eq!(warn.warnings.is_empty(), may, "{:?}", warn.warnings);
        if may {
            assert_eq!(warn.policy, "SCHED_FIFO");
            assert_eq!(warn.priority, 10);
            assert!(warn.one_line("p").contains("SCHED_FIFO 10"));
            assert!(strict.is_ok());
        } else {
            assert_eq!(warn.policy, "SCHED_OTHER");
            let w = &warn.warnings[0];
            assert!(w.starts_with("SCHED_FIFO priority 10 refused: "), "{w}");
            let e = strict.expect_err("Strict must fail when Warn warned");
            assert!(e.starts_with("SCHED_FIFO priority 10 refused: "), "{e}");
            assert!(!e.contains('\n'));
        }
        assert_eq!(restored.policy, "SCHED_OTHER");
        assert_eq!(restored.priority, 0);
    }

    #[test]
    fn eperm_message_names_the_fix() {
        let msg = fifo_refusal_message(80, &io::Error::from_raw_os_error(libc::EPERM));
        assert!(
            msg.starts_with(
                "SCHED_FIFO priority 80 refused: Operation not permitted (needs root or \
                 CAP_SYS_NICE / RLIMIT_RTPRIO"
            ),
            "{msg}"
        );
        assert!(msg.ends_with(')'));
    }

    #[test]
    fn prefault_stack_small_and_oversized() {
        let rep = in_thread(|| {
            let mut q = req();
            q.prefault_stack_bytes = 256 * 1024;
            setup_rt(&q, RtPolicy::Strict)
        })
        .expect("256 KiB fits in a default 2 MiB thread stack");
        assert!(rep.warnings.is_empty());

        // Far more than the thread's stack: clamped with a warning, no crash.
        let (warn, strict) = std::thread::Builder::new()
            .stack_size(512 * 1024)
            .spawn(|| {
                let mut q = req();
                q.prefault_stack_bytes = 64 * 1024 * 1024;
                (setup_rt(&q, RtPolicy::Warn), setup_rt(&q, RtPolicy::Strict))
            })
            .unwrap()
            .join()
            .unwrap();
        let warn = warn.unwrap();
        assert_eq!(warn.warnings.len(), 1);
        assert!(warn.warnings[0].starts_with("stack prefault of 67108864 bytes refused"));
        assert!(strict.is_err());
    }

    #[test]
    fn lock_memory_granted_or_warned() {
        let rep = in_thread(|| {
            let mut q = req();
            q.lock_memory = true;
            setup_rt(&q, RtPolicy::Warn).unwrap()
        });
        // Root and an unlimited RLIMIT_MEMLOCK always lock; a finite limit may fit or not.
        if root() || get_rlimit(libc::RLIMIT_MEMLOCK).0 == libc::RLIM_INFINITY {
            assert!(rep.warnings.is_empty(), "{:?}", rep.warnings);
        }
        if rep.warnings.is_empty() {
            assert!(rep.memory_locked);
            assert!(rep.one_line("m").ends_with("memory locked"));
        } else {
            assert!(rep.warnings[0].starts_with("mlockall(MCL_CURRENT|MCL_FUTURE) refused: "));
        }
        // Do not leave the test process locked.
        // SAFETY: munlockall takes no arguments and only changes paging of this process.
        unsafe { libc::munlockall() };
    }

    #[test]
    fn now_ns_is_monotonic() {
        let mut prev = now_ns();
        assert!(prev > 0);
        for _ in 0..10_000 {
            let t = now_ns();
            assert!(t >= prev);
            prev = t;
        }
    }

    /// The real clock and call: a deadline that has passed makes no system call.
    #[test]
    fn sleep_until_a_past_deadline_makes_no_system_call() {
        let t0 = now_ns();
        let counted = syscalls();
        sleep_until_ns(0);
        sleep_until_ns(t0.saturating_sub(1_000_000_000));
        sleep_until_ns(t0);
        assert_eq!(
            syscalls(),
            counted,
            "a past deadline reached clock_nanosleep"
        );
    }

    /// A late loop (a plant catching up after a stall) makes no system call for a deadline
    /// that has passed or is now; a future one is slept to, restarted after each signal.
    #[test]
    fn only_a_future_deadline_reaches_clock_nanosleep() {
        let counted = syscalls();
        let mut calls = Vec::new();
        for deadline in [0, 4_999_999_999, 5_000_000_000] {
            sleep_until_with(
                deadline,
                || 5_000_000_000,
                |_| {
                    calls.push(deadline);
                    0
                },
            );
        }
        assert!(
            calls.is_empty(),
            "past deadlines reached clock_nanosleep: {calls:?}"
        );
        assert_eq!(syscalls(), counted, "a past deadline counted a system call");
        let mut seen = Vec::new();
        let mut rc = [libc::EINTR, libc::EINTR, 0].into_iter();
        sleep_until_with(
            6_250_000_001,
            || 5_000_000_000,
            |ts| {
                seen.push((ts.tv_sec, ts.tv_nsec));
                rc.next().expect("called after it returned 0")
            },
        );
        assert_eq!(seen, vec![(6, 250_000_001); 3]);
        // Each restart after a signal is a system call of its own.
        assert_eq!(syscalls() - counted, 3);
    }

    #[test]
    fn sleep_until_future_deadline_waits() {
        let t0 = now_ns();
        let deadline = t0 + 2_000_000;
        sleep_until_ns(deadline);
        assert!(now_ns() >= deadline);
    }

    #[test]
    fn online_cpus_at_least_one() {
        assert!(online_cpus() >= 1);
    }

    #[test]
    fn policy_names() {
        assert_eq!(policy_name(libc::SCHED_FIFO), "SCHED_FIFO");
        assert_eq!(policy_name(libc::SCHED_OTHER), "SCHED_OTHER");
        assert_eq!(policy_name(-1), "unknown");
    }
}

#[cfg(test)]
mod latency_request_tests {
    use super::*;

    #[test]
    fn a_tick_aligned_schedule_starts_on_this_cpus_tick() {
        // Pinned, so that the CPU whose tick is read is the one the schedule runs on.
        let cpu = crate::tick::this_cpu().unwrap();
        set_affinity_single(cpu).unwrap();
        let before = now_ns();
        let t0 = schedule_start_ns(true);
        let after = now_ns();
        // 2 ms from the call, moved on by less than a millisecond to the grid.
        assert!(
            t0 >= before + 2_000_000 && t0 < after + 3_000_000,
            "{t0} from {before}"
        );
        // Where root can read the tick, on it; elsewhere on a whole millisecond.
        let phase = crate::tick::phase_of(cpu).unwrap_or(0);
        assert_eq!(t0 % crate::tick::GRID_NS, phase, "cpu{cpu}");
        let t1 = schedule_start_ns(false);
        assert!(t1 >= before + 2_000_000 && t1 < now_ns() + 2_000_000);
    }

    fn open_fds_to(path: &std::path::Path) -> usize {
        std::fs::read_dir("/proc/self/fd")
            .unwrap()
            .flatten()
            .filter(|e| std::fs::read_link(e.path()).is_ok_and(|t| t == path))
            .count()
    }

    #[test]
    fn the_request_is_written_held_and_released_on_drop() {
        let path = std::env::temp_dir().join(format!("drivelab-pmqos-{}", std::process::id()));
        std::fs::write(&path, b"").unwrap();
        let r = CpuLatencyRequest::hold_at(&path, 0).unwrap();
        assert_eq!(r.value_us, 0);
        assert_eq!(std::fs::read(&path).unwrap(), 0i32.to_ne_bytes());
        assert_eq!(open_fds_to(&path), 1, "held: the file stays open");
        drop(r);
        assert_eq!(open_fds_to(&path), 0, "released on drop");
        let r = CpuLatencyRequest::hold_at(&path, 75).unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), 75i32.to_ne_bytes());
        drop(r);
        let _ = std::fs::remove_file(&path);
        assert!(
            CpuLatencyRequest::hold_at(&path, 0).is_err(),
            "no device: an error"
        );
    }
}
