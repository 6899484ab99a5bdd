//! Who is alive on the bus: one robust, process-shared mutex per process of a real-time
//! drive, and one per standby twin, in a small shared-memory segment of the bus
//! (`/dev/shm/iox2_dl<BUS>_life`). See docs/architecture.md, "Liveness words and standby
//! twins".
//!
//! Each stage host holds its process's mutex (its *lease*) for its whole life and never
//! releases it. When the holder dies, however it dies, the kernel walks its robust-futex
//! list on the way out and sets the owner-died bit in the mutex's futex word (see
//! set_robust_list(2) and the "Robust futexes" section of futex(2)). So every other process
//! can tell, with one atomic load per sample and no system call, whether the producer of an
//! input is alive: a stopped (SIGSTOP) process is alive, a killed one is dead from the
//! moment the kernel has torn it down.
//!
//! A standby twin holds its own mutex while it waits, and asks for its process's lease with
//! `pthread_mutex_trylock` at every output it would publish: while the owner lives that is
//! one failed compare-and-swap in user space, and the first attempt after the owner's death
//! succeeds with `EOWNERDEAD`. The twin then holds the lease and gives up its standby mutex,
//! so a new twin can take that one.

use anyhow::{anyhow, bail, Result};
use std::sync::atomic::{AtomicU32, Ordering};

/// Bytes per mutex slot (a `pthread_mutex_t` is 40 bytes on x86_64 and aarch64, 24 on
/// armv7); a cache line each, so that one process's lock does not share a line with another's.
const SLOT_BYTES: usize = 64;
const _: () = assert!(std::mem::size_of::<libc::pthread_mutex_t>() <= SLOT_BYTES);
/// The kernel's bits in a robust futex word (linux/futex.h): the owner's thread id, and the
/// flag it sets when that owner died holding it.
const FUTEX_TID_MASK: u32 = 0x3fff_ffff;
const FUTEX_OWNER_DIED: u32 = 0x4000_0000;

/// The slots of `processes` processes: the process's lease and its twin's.
fn seg_bytes(processes: usize) -> usize {
    (2 * processes * SLOT_BYTES).next_multiple_of(4096)
}

/// The shared-memory name of bus `id`'s segment (without the leading '/').
pub fn name(id: &str) -> String {
    format!("{}life", crate::bus::shm_prefix(id))
}

/// The segment of a real-time drive, mapped. The mapping is never undone while a lease in it
/// is held: the kernel reads the holder's robust-list entry there when the holder exits.
#[derive(Debug)]
pub struct Life {
    base: *mut u8,
    processes: usize,
}

// SAFETY: the mapping is process-shared memory that only the pthread mutex functions and
// atomic loads touch; both are made for concurrent use from any thread or process.
unsafe impl Send for Life {}
// SAFETY: as above; `&Life` only reads words atomically or calls the mutex functions.
unsafe impl Sync for Life {}

/// Which mutex of a process.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// The process's lease: held by the instance that publishes.
    Active,
    /// Held by its standby twin while it waits.
    Standby,
}

impl Life {
    /// Creates bus `id`'s segment for `processes` processes (the launcher, before it starts
    /// any): fresh robust, process-shared mutexes that nobody holds.
    pub fn create(id: &str, processes: usize) -> Result<Self> {
        let life = Self::map(id, processes, true)?;
        for i in 0..2 * processes {
            // SAFETY: each slot is zeroed shared memory of at least a mutex's size that
            // nobody else uses yet (the file was just created); the attribute object lives
            // on this stack frame and is destroyed after use; every return code is checked.
            unsafe {
                let mut attr = std::mem::MaybeUninit::<libc::pthread_mutexattr_t>::uninit();
                check(
                    libc::pthread_mutexattr_init(attr.as_mut_ptr()),
                    "mutexattr_init",
                )?;
                let a = attr.as_mut_ptr();
                let r = (|| {
                    check(
                        libc::pthread_mutexattr_setpshared(a, libc::PTHREAD_PROCESS_SHARED),
                        "setpshared",
                    )?;
                    check(
                        libc::pthread_mutexattr_setrobust(a, libc::PTHREAD_MUTEX_ROBUST),
                        "setrobust",
                    )?;
                    check(libc::pthread_mutex_init(life.mutex(i), a), "mutex_init")
                })();
                libc::pthread_mutexattr_destroy(a);
                r?;
            }
        }
        Ok(life)
    }

    /// Opens the segment the launcher created for `processes` processes.
    pub fn open(id: &str, processes: usize) -> Result<Self> {
        Self::map(id, processes, false)
    }

    fn map(id: &str, processes: usize, create: bool) -> Result<Self> {
        crate::bus::check_bus_id(id)?;
        let path = std::ffi::CString::new(format!("/{}", name(id)))?;
        let flags = if create {
            libc::O_CREAT | libc::O_EXCL | libc::O_RDWR
        } else {
            libc::O_RDWR
        };
        let bytes = seg_bytes(processes);
        // SAFETY: plain libc calls with a valid NUL-terminated name; every return value is
        // checked, the size of an opened segment is checked before it is mapped, and the fd
        // is closed after mmap (the mapping keeps the object alive).
        unsafe {
            let fd = libc::shm_open(path.as_ptr(), flags, 0o600);
            if fd < 0 {
                bail!(
                    "liveness segment {path:?}: shm_open: {}",
                    std::io::Error::last_os_error()
                );
            }
            let fail = |what: &str| {
                let e = std::io::Error::last_os_error();
                libc::close(fd);
                anyhow!("liveness segment {path:?}: {what}: {e}")
            };
            if create {
                if libc::ftruncate(fd, bytes as libc::off_t) != 0 {
                    return Err(fail("ftruncate"));
                }
            } else {
                let mut st = std::mem::zeroed::<libc::stat>();
                if libc::fstat(fd, &mut st) != 0 {
                    return Err(fail("fstat"));
                }
                if (st.st_size as usize) < bytes {
                    libc::close(fd);
                    bail!(
                        "liveness segment {path:?} has {} bytes, {bytes} expected for {processes} processes",
                        st.st_size
                    );
                }
            }
            let p = libc::mmap(
                std::ptr::null_mut(),
                bytes,
                libc::PROT_READ | libc::PROT_WRITE,
                libc::MAP_SHARED,
                fd,
                0,
            );
            if p == libc::MAP_FAILED {
                return Err(fail("mmap"));
            }
            libc::close(fd);
            Ok(Self {
                base: p.cast(),
                processes,
            })
        }
    }

    fn slot(process: usize, role: Role) -> usize {
        2 * process + usize::from(role == Role::Standby)
    }

    fn mutex(&self, slot: usize) -> *mut libc::pthread_mutex_t {
        debug_assert!(slot < 2 * self.processes);
        // SAFETY: `slot` is within the mapping (checked by the callers' process index).
        unsafe { self.base.add(slot * SLOT_BYTES).cast() }
    }

    /// The mutex of `process` in `role`, to hold or to take.
    pub fn lease(&self, process: usize, role: Role) -> Result<Lease> {
        if process >= self.processes {
            bail!("liveness: process {process} of {}", self.processes);
        }
        Ok(Lease {
            mutex: self.mutex(Self::slot(process, role)),
            held: false,
        })
    }

    /// Whether a live process holds the mutex of `process` in `role`: the futex word holds
    /// its thread id, without the owner-died bit. One atomic load, no system call.
    #[inline]
    pub fn held_by_live(&self, process: usize, role: Role) -> bool {
        if process >= self.processes {
            return false;
        }
        // SAFETY: glibc's `pthread_mutex_t` begins with its futex word (`__data.__lock`, an
        // int, on every Linux architecture: the layout is ABI, fixed by the static
        // initialisers); for a robust mutex the kernel's robust-futex protocol defines its
        // bits. The word is 4-aligned within a 64-byte slot of a page-aligned mapping, and
        // is only read here. The test below checks the reading against a killed holder.
        let word = unsafe { &*self.mutex(Self::slot(process, role)).cast::<AtomicU32>() }
            .load(Ordering::Acquire);
        word & FUTEX_TID_MASK != 0 && word & FUTEX_OWNER_DIED == 0
    }

    /// Whether `process` is up: its lease or its twin's mutex is held by a live process. A
    /// process that was never started, or whose instance and twin are both dead, is down.
    #[inline]
    pub fn up(&self, process: usize) -> bool {
        self.held_by_live(process, Role::Active) || self.held_by_live(process, Role::Standby)
    }
}

/// One mutex of the segment, to hold (a process's instance, a twin) or to take over (a twin).
#[derive(Debug)]
pub struct Lease {
    mutex: *mut libc::pthread_mutex_t,
    /// This instance holds it.
    held: bool,
}

// SAFETY: see `Life`; a lease is used by the one thread that took it (robust mutexes
// belong to a thread).
unsafe impl Send for Lease {}

impl Lease {
    /// Takes the mutex at set-up: nobody holds it then, or a dead instance left it. A live
    /// holder (a twin that took over) is an error after 2 s.
    pub fn hold(&mut self) -> Result<()> {
        let t0 = std::time::Instant::now();
        while !self.try_take() {
            if t0.elapsed() > std::time::Duration::from_secs(2) {
                bail!("the lease is held by another live instance of this process");
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        Ok(())
    }

    /// Takes the mutex if its holder has died (or nobody holds it). Returns true when this
    /// instance holds it now. No system call while the holder lives.
    #[inline]
    pub fn try_take(&mut self) -> bool {
        if self.held {
            return true;
        }
        // SAFETY: `mutex` is an initialised process-shared robust mutex in our mapping.
        let r = unsafe { libc::pthread_mutex_trylock(self.mutex) };
        // Called every sample by a standing-by twin: an error is only a `false`, with no
        // message built (that would allocate).
        r != libc::EBUSY && self.take_after(r).is_ok()
    }

    /// This instance holds it.
    pub fn held(&self) -> bool {
        self.held
    }

    /// Gives it up (a twin that took over its process's lease frees its standby mutex for
    /// the next twin). No system call: nobody waits on these mutexes, they only try them.
    pub fn release(&mut self) {
        if std::mem::take(&mut self.held) {
            // SAFETY: this thread holds the mutex (`held`), so it may unlock it.
            unsafe { libc::pthread_mutex_unlock(self.mutex) };
        }
    }

    /// After a trylock that returned `r`: the mutex is ours (a dead holder's state made
    /// consistent again), or the failing call and its error number. No allocation.
    fn take_after(&mut self, r: i32) -> std::result::Result<(), (&'static str, i32)> {
        match r {
            0 => {}
            libc::EOWNERDEAD => {
                // SAFETY: we hold the mutex (EOWNERDEAD hands it over); marking it
                // consistent lets later holders lock it normally.
                let r = unsafe { libc::pthread_mutex_consistent(self.mutex) };
                if r != 0 {
                    return Err(("mutex_consistent", r));
                }
            }
            e => return Err(("mutex_trylock", e)),
        }
        self.held = true;
        Ok(())
    }
}

fn check(r: i32, what: &str) -> Result<()> {
    if r == 0 {
        Ok(())
    } else {
        Err(anyhow!(
            "lease: pthread_{what}: {}",
            std::io::Error::from_raw_os_error(r)
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Unlinks the test's segment of bus `id` when dropped, also when an assertion fails.
    /// Only in the process that made the guard: a forked child shares the memory and never
    /// returns from its loop, but must not remove the segment whatever happens to it.
    struct Segment {
        name: std::ffi::CString,
        owner: libc::pid_t,
    }

    impl Segment {
        fn of(id: &str) -> Self {
            Self {
                name: std::ffi::CString::new(format!("/{}", name(id))).unwrap(),
                // SAFETY: getpid(2) only reads the caller's pid.
                owner: unsafe { libc::getpid() },
            }
        }
    }

    impl Drop for Segment {
        fn drop(&mut self) {
            // SAFETY: getpid(2) only reads the caller's pid.
            if unsafe { libc::getpid() } == self.owner {
                // SAFETY: shm_unlink(3) of the test's own segment by its NUL-terminated name;
                // an error (not made yet, or already removed) changes nothing.
                unsafe { libc::shm_unlink(self.name.as_ptr()) };
            }
        }
    }

    /// A forked child of the test, SIGKILLed and reaped when dropped (also when an assertion
    /// fails) unless [`Forked::kill`] did that already.
    struct Forked(Option<libc::pid_t>);

    impl Forked {
        fn kill(&mut self) {
            if let Some(pid) = self.0.take() {
                // SAFETY: kill(2) and waitpid(2) on our own child, not reaped before (its pid
                // still names it); waitpid writes no status (null pointer).
                unsafe {
                    libc::kill(pid, libc::SIGKILL);
                    libc::waitpid(pid, std::ptr::null_mut(), 0);
                }
            }
        }
    }

    impl Drop for Forked {
        fn drop(&mut self) {
            self.kill();
        }
    }

    /// A child process takes process 1's lease and is SIGKILLed: process 1 reads up while
    /// the child lives and down after its death, and the twin, which could not take the lease
    /// while the child lived, takes it at its next attempt.
    #[test]
    fn a_killed_holder_reads_down_and_its_twin_takes_the_lease_then_and_not_before() {
        let bus = format!("life{}", std::process::id());
        let _segment = Segment::of(&bus);
        let creator = Life::create(&bus, 2).unwrap();
        let life = Life::open(&bus, 2).unwrap();
        assert!(!life.up(0) && !life.up(1), "up before anyone took a lease");
        // Made before the fork: the child allocates nothing.
        let mut holder = life.lease(1, Role::Active).unwrap();
        let mut twin = life.lease(1, Role::Active).unwrap();
        let mut fds = [0; 2];
        // SAFETY: pipe(2) into a two-element array.
        assert_eq!(unsafe { libc::pipe(fds.as_mut_ptr()) }, 0);
        use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
        // SAFETY: pipe(2) just made these two descriptors; nothing else owns or closes them.
        let (rx, tx) = unsafe { (OwnedFd::from_raw_fd(fds[0]), OwnedFd::from_raw_fd(fds[1])) };
        // SAFETY: fork in a test: the child takes the lease, writes one byte to the pipe
        // and pauses until it is killed; it allocates nothing and touches only the mapping.
        let pid = unsafe { libc::fork() };
        assert!(pid >= 0);
        if pid == 0 {
            let code = if holder.try_take() { 0 } else { 1u8 };
            // SAFETY: write(2) of one byte from a live buffer, then pause(2) until killed.
            unsafe {
                libc::write(tx.as_raw_fd(), (&code as *const u8).cast(), 1);
                loop {
                    libc::pause();
                }
            }
        }
        let mut child = Forked(Some(pid));
        let mut byte = 9u8;
        // SAFETY: read(2) of one byte into a live buffer (the child writes it at once).
        let n = unsafe { libc::read(rx.as_raw_fd(), (&mut byte as *mut u8).cast(), 1) };
        assert_eq!((n, byte), (1, 0), "the child could not take the lease");
        assert!(life.up(1) && !life.up(0), "process 1 up, process 0 down");
        for _ in 0..1000 {
            assert!(!twin.try_take(), "taken while its holder lives");
        }
        assert!(!twin.held());
        child.kill();
        drop((rx, tx));
        assert!(!life.up(1), "a dead holder reads up");
        // A live standby keeps the process up.
        let mut standby = life.lease(1, Role::Standby).unwrap();
        assert!(standby.try_take());
        assert!(life.up(1), "a live twin does not keep its process up");
        assert!(twin.try_take(), "not taken after the holder's death");
        assert!(twin.held() && life.held_by_live(1, Role::Active));
        standby.release();
        assert!(!standby.held() && !life.held_by_live(1, Role::Standby));
        assert!(life.up(1));
        let _ = (holder, twin, life, creator);
    }

    #[test]
    fn opening_a_segment_made_for_fewer_processes_is_an_error() {
        let bus = format!("lifesz{}", std::process::id());
        let _segment = Segment::of(&bus);
        let _creator = Life::create(&bus, 2).unwrap();
        // 2 processes need 256 bytes, rounded to a page: 64 processes do not fit.
        let e = Life::open(&bus, 64).unwrap_err().to_string();
        assert!(e.contains("expected for 64 processes"), "{e}");
        assert!(Life::open(&bus, 2).unwrap().lease(2, Role::Active).is_err());
    }
}
