//! Wake-up words in a shared-memory segment of the bus, woken with futex(2).
//!
//! The alternative to iceoryx2's event (which goes through a Unix datagram socket): a sender
//! bumps a 32-bit sequence word and calls FUTEX_WAKE only when a receiver sleeps on it; a
//! receiver sleeps with FUTEX_WAIT on the value it last saw. Data still travels through
//! iceoryx2 publish-subscribe; only the wake-up changes. The segment is
//! `/dev/shm/iox2_dl<BUS>_wake`, so `bus::cleanup` removes it with the rest of the bus.

use anyhow::{anyhow, Result};
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::time::Duration;

/// Number of wake words in a segment (one per topic).
pub const WORDS: usize = 16;
const SEG_BYTES: usize = 4096;
/// Offset of the notify stamps (one `AtomicU64` per word, CLOCK_MONOTONIC ns of the last
/// stamped notify), after the words.
const STAMPS_AT: usize = 2048;
const _: () =
    assert!(WORDS * std::mem::size_of::<Word>() <= STAMPS_AT && STAMPS_AT + WORDS * 8 <= SEG_BYTES);

/// One wake word: a sequence counter and a count of sleepers.
#[repr(C)]
struct Word {
    seq: AtomicU32,
    sleepers: AtomicU32,
}

/// The mapped segment of one bus.
#[derive(Debug)]
pub struct WakeSegment {
    base: *mut u8,
}

// SAFETY: the segment is a fixed mapping of atomics only; all access goes through atomic
// operations, which are safe to share between threads (and processes).
unsafe impl Send for WakeSegment {}
// SAFETY: see `Send`: only atomics are reached through `base`.
unsafe impl Sync for WakeSegment {}

impl WakeSegment {
    /// The shared-memory name of bus `id`'s wake segment.
    fn name(id: &str) -> Result<std::ffi::CString> {
        crate::bus::check_bus_id(id)?;
        Ok(std::ffi::CString::new(format!(
            "/{}wake",
            crate::bus::shm_prefix(id)
        ))?)
    }

    /// Opens (creating if needed) the wake segment of bus `id`.
    pub fn open(id: &str) -> Result<Self> {
        let name = Self::name(id)?;
        // SAFETY: plain libc calls with a valid NUL-terminated name; every return value is
        // checked and the fd is closed after mmap (the mapping keeps the object alive).
        unsafe {
            let fd = libc::shm_open(name.as_ptr(), libc::O_CREAT | libc::O_RDWR, 0o600);
            if fd < 0 {
                return Err(anyhow!(
                    "shm_open {:?}: {}",
                    name,
                    std::io::Error::last_os_error()
                ));
            }
            if libc::ftruncate(fd, SEG_BYTES as libc::off_t) != 0 {
                let e = std::io::Error::last_os_error();
                libc::close(fd);
                return Err(anyhow!("ftruncate wake segment: {e}"));
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
                return Err(anyhow!(
                    "mmap wake segment: {}",
                    std::io::Error::last_os_error()
                ));
            }
            Ok(Self { base: p.cast() })
        }
    }

    /// Removes the wake segment of bus `id` from `/dev/shm` (the mappings that are open stay
    /// valid). Returns whether there was one. For a process that outlived the one that made
    /// the segment and would otherwise leave it behind.
    pub fn remove(id: &str) -> Result<bool> {
        let name = Self::name(id)?;
        // SAFETY: shm_unlink(3) with a valid NUL-terminated name; it touches no memory of ours.
        if unsafe { libc::shm_unlink(name.as_ptr()) } == 0 {
            return Ok(true);
        }
        match std::io::Error::last_os_error() {
            e if e.kind() == std::io::ErrorKind::NotFound => Ok(false),
            e => Err(anyhow!("shm_unlink {name:?}: {e}")),
        }
    }

    fn word(&self, i: usize) -> &Word {
        assert!(i < WORDS, "wake word {i} out of range");
        // SAFETY: the mapping is SEG_BYTES long, zero-filled by ftruncate, page aligned, and
        // WORDS * size_of::<Word>() < SEG_BYTES; Word is two AtomicU32 (valid for any bits).
        unsafe { &*(self.base.add(i * std::mem::size_of::<Word>()) as *const Word) }
    }

    fn stamp_cell(&self, i: usize) -> &AtomicU64 {
        assert!(i < WORDS, "wake word {i} out of range");
        // SAFETY: STAMPS_AT + WORDS * 8 <= SEG_BYTES, the offset is 8-byte aligned in a page
        // aligned, zero-filled mapping, and AtomicU64 is valid for any bits.
        unsafe { &*(self.base.add(STAMPS_AT + i * 8) as *const AtomicU64) }
    }

    /// Like [`notify`](Self::notify), after storing `t_ns` (the moment the notify starts,
    /// CLOCK_MONOTONIC) in word `i`'s stamp: a woken receiver splits its hop into the
    /// sender's publish (message stamp → notify) and its own wake-up (notify → running).
    #[inline]
    pub fn notify_stamped(&self, i: usize, t_ns: u64) {
        self.stamp_cell(i).store(t_ns, Ordering::Release);
        self.notify(i);
    }

    /// The stamp of the last [`notify_stamped`](Self::notify_stamped) on word `i` (0: none).
    #[inline]
    pub fn stamp(&self, i: usize) -> u64 {
        self.stamp_cell(i).load(Ordering::Acquire)
    }

    /// Bumps word `i` and wakes its sleepers (a syscall only if someone sleeps).
    #[inline]
    pub fn notify(&self, i: usize) {
        let w = self.word(i);
        w.seq.fetch_add(1, Ordering::SeqCst);
        if w.sleepers.load(Ordering::SeqCst) > 0 {
            crate::rt::count_syscall();
            // SAFETY: FUTEX_WAKE on a valid, aligned u32 in a shared mapping.
            unsafe {
                libc::syscall(
                    libc::SYS_futex,
                    w.seq.as_ptr(),
                    libc::FUTEX_WAKE,
                    i32::MAX,
                    0,
                    0,
                    0,
                );
            }
        }
    }

    /// Current sequence value of word `i`.
    #[inline]
    pub fn seq(&self, i: usize) -> u32 {
        self.word(i).seq.load(Ordering::SeqCst)
    }

    /// Sleeps while word `i` still equals `seen`, at most `timeout`. Returns the value now
    /// (different from `seen` when woken by a notify; equal after a timeout or signal).
    #[inline]
    pub fn wait(&self, i: usize, seen: u32, timeout: Duration) -> u32 {
        let w = self.word(i);
        w.sleepers.fetch_add(1, Ordering::SeqCst);
        if w.seq.load(Ordering::SeqCst) == seen {
            crate::rt::count_syscall();
            let ts = libc::timespec {
                tv_sec: timeout.as_secs() as libc::time_t,
                tv_nsec: timeout.subsec_nanos() as libc::c_long,
            };
            // SAFETY: FUTEX_WAIT (shared) on a valid aligned u32 with a relative timeout on
            // the stack; EAGAIN/ETIMEDOUT/EINTR are all handled by re-reading the word.
            unsafe {
                libc::syscall(
                    libc::SYS_futex,
                    w.seq.as_ptr(),
                    libc::FUTEX_WAIT,
                    seen,
                    &ts as *const libc::timespec,
                    0,
                    0,
                );
            }
        }
        w.sleepers.fetch_sub(1, Ordering::SeqCst);
        w.seq.load(Ordering::SeqCst)
    }
}

impl Drop for WakeSegment {
    fn drop(&mut self) {
        // SAFETY: unmapping exactly the mapping created in `open`; no reference into it
        // outlives `self` (all accessors borrow `self`).
        unsafe {
            libc::munmap(self.base.cast(), SEG_BYTES);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn notify_wakes_a_sleeper_and_timeouts_return() {
        let id = format!("fx{}", std::process::id());
        // Removes the segment also when an assertion below fails (dropped last).
        let _cleanup = crate::bus::CleanupOnDrop(id.clone());
        let seg = Arc::new(WakeSegment::open(&id).unwrap());
        let s0 = seg.seq(3);
        let counted = crate::rt::syscalls();
        // Timeout path: nothing notifies.
        assert_eq!(seg.wait(3, s0, Duration::from_millis(5)), s0);
        assert_eq!(
            crate::rt::syscalls() - counted,
            1,
            "a wait is one FUTEX_WAIT"
        );
        // Nobody sleeps on the word: a notify is an atomic add, no system call.
        seg.notify(5);
        assert_eq!(
            crate::rt::syscalls() - counted,
            1,
            "a notify nobody waits for"
        );
        // A wait on a value that is already stale returns without sleeping.
        let s5 = seg.seq(5);
        assert_eq!(seg.wait(5, s5.wrapping_sub(1), Duration::from_secs(10)), s5);
        assert_eq!(
            crate::rt::syscalls() - counted,
            1,
            "a wait on a stale value"
        );
        let s2 = seg.clone();
        let (tid_tx, tid_rx) = std::sync::mpsc::channel();
        let t = std::thread::spawn(move || {
            // SAFETY: gettid(2) has no arguments and cannot fail.
            tid_tx.send(unsafe { libc::gettid() }).unwrap();
            let got = s2.wait(3, s0, Duration::from_secs(10));
            (got, crate::rt::syscalls())
        });
        // Notify once the thread sleeps in futex(2) (the kernel's view of it), not merely
        // once it counts as a sleeper: then both sides make their call.
        let tid = tid_rx.recv().unwrap();
        let in_futex = || {
            std::fs::read_to_string(format!("/proc/self/task/{tid}/syscall"))
                .is_ok_and(|s| s.split(' ').next() == Some(&libc::SYS_futex.to_string()))
        };
        let t0 = std::time::Instant::now();
        while !in_futex() {
            assert!(
                t0.elapsed() < Duration::from_secs(10),
                "watchdog: the thread never slept in futex(2)"
            );
            std::thread::sleep(Duration::from_millis(1));
        }
        seg.notify(3);
        let (got, waits) = t.join().unwrap();
        assert_eq!(got, s0.wrapping_add(1));
        assert_eq!(waits, 1, "the woken thread made one FUTEX_WAIT");
        assert_eq!(
            crate::rt::syscalls() - counted,
            2,
            "a notify with a sleeper"
        );
        // A stamped notify wakes like a plain one and leaves its stamp on its own word only.
        assert_eq!(seg.stamp(4), 0);
        seg.notify_stamped(4, 123_456);
        assert_eq!(seg.seq(4), 1);
        assert_eq!(seg.stamp(4), 123_456);
        assert_eq!(seg.stamp(3), 0);
        drop(seg);
        crate::bus::cleanup(&id).unwrap();
        assert!(crate::bus::leftovers(&id).is_empty());
    }
}
