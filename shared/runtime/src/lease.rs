//! The lease of a process with a standby twin: a robust, process-shared mutex in a small
//! shared-memory segment of the bus (`/dev/shm/iox2_dl<BUS>_lease-<PROCESS>`).
//!
//! The active instance of the process holds it for its whole life and never releases it.
//! When that instance dies, however it dies, the kernel walks its robust-futex list on the
//! way out and marks the mutex "owner died" (see set_robust_list(2)). The twin asks for the
//! lease with `pthread_mutex_trylock` at every output it would publish: while the owner
//! lives that is one failed compare-and-swap in user space (no system call), and the first
//! attempt after the owner's death succeeds with `EOWNERDEAD`. The twin then holds the
//! lease itself, so a new twin can watch it in turn. See docs/architecture.md, "Standby
//! twins".

use anyhow::{anyhow, bail, Result};

/// Bytes of the segment: one mutex, rounded up to a page.
const SEG_BYTES: usize = 4096;
const _: () = assert!(std::mem::size_of::<libc::pthread_mutex_t>() <= SEG_BYTES);

/// One process's lease, mapped. The mapping is never undone: the kernel reads the holder's
/// robust-list entry in it when the holder exits, so it stays until the process ends.
#[derive(Debug)]
pub struct Lease {
    mutex: *mut libc::pthread_mutex_t,
    /// This instance holds the lease.
    held: bool,
}

// SAFETY: the mapping is process-shared memory that only the pthread mutex functions
// touch; they are made for concurrent use from any thread or process.
unsafe impl Send for Lease {}

/// The shared-memory name of `process`'s lease on bus `id` (without the leading '/').
pub fn name(id: &str, process: &str) -> String {
    format!("{}lease-{process}", crate::bus::shm_prefix(id))
}

impl Lease {
    /// Creates the lease of `process` on bus `id` (the launcher, before it starts the
    /// process): a fresh robust, process-shared mutex that nobody holds.
    pub fn create(id: &str, process: &str) -> Result<Self> {
        let lease = Self::map(id, process, true)?;
        // SAFETY: `mutex` points to zeroed shared memory of the mutex's size that nobody
        // else uses yet (the file was just created empty); the attribute object lives on
        // this stack frame and is destroyed after use; every return code is checked.
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
                check(libc::pthread_mutex_init(lease.mutex, a), "mutex_init")
            })();
            libc::pthread_mutexattr_destroy(a);
            r?;
        }
        Ok(lease)
    }

    /// Opens the lease of `process` on bus `id` that the launcher created.
    pub fn open(id: &str, process: &str) -> Result<Self> {
        Self::map(id, process, false)
    }

    fn map(id: &str, process: &str, create: bool) -> Result<Self> {
        crate::bus::check_bus_id(id)?;
        let path = std::ffi::CString::new(format!("/{}", name(id, process)))?;
        let flags = if create {
            libc::O_CREAT | libc::O_EXCL | libc::O_RDWR
        } else {
            libc::O_RDWR
        };
        // SAFETY: plain libc calls with a valid NUL-terminated name; every return value is
        // checked and the fd is closed after mmap (the mapping keeps the object alive).
        unsafe {
            let fd = libc::shm_open(path.as_ptr(), flags, 0o600);
            if fd < 0 {
                bail!(
                    "lease of process {process}: shm_open {path:?}: {}",
                    std::io::Error::last_os_error()
                );
            }
            if create && libc::ftruncate(fd, SEG_BYTES as libc::off_t) != 0 {
                let e = std::io::Error::last_os_error();
                libc::close(fd);
                bail!("lease of process {process}: ftruncate: {e}");
            }
            let p = libc::mmap(
                std::ptr::null_mut(),
                SEG_BYTES,
                libc::PROT_READ | libc::PROT_WRITE,
                libc::MAP_SHARED,
                fd,
                0,
            );
            libc::close(fd);
            if p == libc::MAP_FAILED {
                bail!(
                    "lease of process {process}: mmap: {}",
                    std::io::Error::last_os_error()
                );
            }
            Ok(Self {
                mutex: p.cast(),
                held: false,
            })
        }
    }

    /// Takes the lease at the active instance's set-up: nobody holds it then, or a dead
    /// instance left it. A live holder (a twin that took over) is an error after 2 s.
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

    /// The twin's check: takes the lease if its holder has died (or nobody holds it).
    /// Returns true when this instance holds it now. No system call while the holder lives.
    #[inline]
    pub fn try_take(&mut self) -> bool {
        if self.held {
            return true;
        }
        // SAFETY: `mutex` is an initialised process-shared robust mutex in our mapping.
        let r = unsafe { libc::pthread_mutex_trylock(self.mutex) };
        r != libc::EBUSY && self.taken(r).is_ok()
    }

    /// This instance holds the lease.
    pub fn held(&self) -> bool {
        self.held
    }

    /// After a lock or trylock that returned `r`: the lease is ours (a dead holder's state
    /// made consistent again), or why not.
    fn taken(&mut self, r: i32) -> Result<()> {
        match r {
            0 => {}
            libc::EOWNERDEAD => {
                // SAFETY: we hold the mutex (EOWNERDEAD hands it over); marking it
                // consistent lets later holders lock it normally.
                check(
                    unsafe { libc::pthread_mutex_consistent(self.mutex) },
                    "consistent",
                )?;
            }
            e => return Err(anyhow!("lease: {}", std::io::Error::from_raw_os_error(e))),
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

    /// A child process takes the lease and is SIGKILLed: the twin, which could not take it
    /// while the child lived, takes it at its next attempt.
    #[test]
    fn the_twin_takes_the_lease_when_its_holder_is_killed_and_not_before() {
        let bus = format!("lease{}", std::process::id());
        let _creator = Lease::create(&bus, "p").unwrap();
        // Mapped before the fork: the child allocates nothing.
        let mut holder = Lease::open(&bus, "p").unwrap();
        let mut twin = Lease::open(&bus, "p").unwrap();
        let mut fds = [0; 2];
        // SAFETY: pipe(2) into a two-element array.
        assert_eq!(unsafe { libc::pipe(fds.as_mut_ptr()) }, 0);
        // SAFETY: fork in a test: the child takes the lease, writes one byte to the pipe
        // and pauses until it is killed; it allocates nothing and touches only the mapping.
        let pid = unsafe { libc::fork() };
        assert!(pid >= 0);
        if pid == 0 {
            let code = if holder.hold().is_ok() { 0 } else { 1u8 };
            // SAFETY: write(2) of one byte from a live buffer, then pause(2) until killed.
            unsafe {
                libc::write(fds[1], (&code as *const u8).cast(), 1);
                loop {
                    libc::pause();
                }
            }
        }
        let mut byte = 9u8;
        // SAFETY: read(2) of one byte into a live buffer (the child writes it at once).
        let n = unsafe { libc::read(fds[0], (&mut byte as *mut u8).cast(), 1) };
        assert_eq!((n, byte), (1, 0), "the child could not take the lease");
        for _ in 0..1000 {
            assert!(!twin.try_take(), "taken while its holder lives");
        }
        assert!(!twin.held());
        // SAFETY: kill and reap our own child; close our pipe.
        unsafe {
            libc::kill(pid, libc::SIGKILL);
            libc::waitpid(pid, std::ptr::null_mut(), 0);
            libc::close(fds[0]);
            libc::close(fds[1]);
        }
        assert!(twin.try_take(), "not taken after the holder's death");
        assert!(twin.held());
        // Nobody else takes it from the twin, which lives (here: the same thread, refused
        // as a non-recursive mutex refuses a second lock).
        assert!(!holder.try_take());
        drop((holder, twin));
        let name = std::ffi::CString::new(format!("/{}", name(&bus, "p"))).unwrap();
        // SAFETY: removes the test's own segment.
        unsafe { libc::shm_unlink(name.as_ptr()) };
    }
}
