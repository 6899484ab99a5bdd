//! The bus messages as datagrams on Unix domain sockets (`SOCK_DGRAM`), sent as their bytes.
//!
//! Every socket lives in a private directory; a receiver binds `<dir>/<name>`, a sender
//! connects an unbound socket to it. Sends never block (`MSG_DONTWAIT`): a full receive queue
//! drops the message and is counted, like iceoryx2's safe overflow on control data. Blocking
//! receives wake at least every [`RECV_SLICE`] so that a stop request is noticed.

use drivelab_runtime::messages::{CurrentRef, Estimate, Header, Measurement, VoltageCommand};
use std::io;
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
use std::os::unix::ffi::OsStrExt;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Longest a blocking receive waits before it returns [`Recv::Empty`] (to check for stop).
pub const RECV_SLICE: Duration = Duration::from_millis(50);

/// A message that may be sent as its bytes.
///
/// # Safety
/// Implementors must be `#[repr(C)]`, contain only integer and floating-point fields (every
/// bit pattern is a valid value) and have no padding bytes (checked below at compile time).
pub unsafe trait Wire: Copy + Default + 'static {}

// SAFETY: repr(C), fields u64/u64/u64/u32/u32 (32 bytes, no padding: asserted below).
unsafe impl Wire for Header {}
// SAFETY: repr(C), a Header then 6 f64 (no padding: asserted below).
unsafe impl Wire for Measurement {}
// SAFETY: repr(C), a Header then 2 f64 (no padding: asserted below).
unsafe impl Wire for Estimate {}
// SAFETY: repr(C), a Header then 3 f64 (no padding: asserted below).
unsafe impl Wire for CurrentRef {}
// SAFETY: repr(C), a Header then 9 f64 (no padding: asserted below).
unsafe impl Wire for VoltageCommand {}

// No padding anywhere: the sizes equal the sums of the field sizes.
const _: () = assert!(std::mem::size_of::<Header>() == 8 + 8 + 8 + 4 + 4);
const _: () = assert!(std::mem::size_of::<Measurement>() == 32 + 6 * 8);
const _: () = assert!(std::mem::size_of::<Estimate>() == 32 + 2 * 8);
const _: () = assert!(std::mem::size_of::<CurrentRef>() == 32 + 3 * 8);
const _: () = assert!(std::mem::size_of::<VoltageCommand>() == 32 + 9 * 8);

/// The bytes of a message.
pub fn as_bytes<T: Wire>(m: &T) -> &[u8] {
    // SAFETY: `T: Wire` has no padding, so all size_of::<T>() bytes behind `m` are initialised;
    // the slice borrows `m` and cannot outlive it.
    unsafe { std::slice::from_raw_parts((m as *const T).cast::<u8>(), std::mem::size_of::<T>()) }
}

/// A message from its bytes; None when the length is not exactly the message's size.
pub fn from_bytes<T: Wire>(b: &[u8]) -> Option<T> {
    if b.len() != std::mem::size_of::<T>() {
        return None;
    }
    // SAFETY: `b` holds exactly size_of::<T>() bytes; every bit pattern is a valid `T`
    // (`T: Wire`); read_unaligned copes with any alignment of `b`.
    Some(unsafe { std::ptr::read_unaligned(b.as_ptr().cast::<T>()) })
}

fn sockaddr(path: &Path) -> io::Result<(libc::sockaddr_un, libc::socklen_t)> {
    // SAFETY: sockaddr_un is a plain C struct for which all-zero bytes are a valid value.
    let mut addr: libc::sockaddr_un = unsafe { std::mem::zeroed() };
    let bytes = path.as_os_str().as_bytes();
    if bytes.len() >= addr.sun_path.len() || bytes.contains(&0) {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!(
                "socket path {} is too long ({} bytes, at most {})",
                path.display(),
                bytes.len(),
                addr.sun_path.len() - 1
            ),
        ));
    }
    addr.sun_family = libc::AF_UNIX as libc::sa_family_t;
    for (d, s) in addr.sun_path.iter_mut().zip(bytes) {
        *d = *s as libc::c_char;
    }
    let len = std::mem::offset_of!(libc::sockaddr_un, sun_path) + bytes.len() + 1;
    Ok((addr, len as libc::socklen_t))
}

fn dgram_socket() -> io::Result<OwnedFd> {
    // SAFETY: plain socket(2) call without pointers.
    let fd = unsafe { libc::socket(libc::AF_UNIX, libc::SOCK_DGRAM | libc::SOCK_CLOEXEC, 0) };
    if fd < 0 {
        return Err(io::Error::last_os_error());
    }
    // SAFETY: `fd` is a freshly created descriptor that nothing else owns.
    Ok(unsafe { OwnedFd::from_raw_fd(fd) })
}

fn errno() -> i32 {
    io::Error::last_os_error().raw_os_error().unwrap_or(0)
}

/// Outcome of one receive.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Recv<T> {
    /// A well-formed message.
    Msg(T),
    /// Nothing there (non-blocking), the wait slice expired, or a signal interrupted the wait.
    Empty,
    /// A datagram of the wrong size (dropped).
    Malformed,
    /// Any other error (errno).
    Err(i32),
}

/// A bound receiving socket; the socket file is removed on drop.
#[derive(Debug)]
pub struct Rx {
    fd: OwnedFd,
    path: PathBuf,
}

impl Rx {
    /// Binds `path` (removing a stale file first); blocking receives wait at most
    /// [`RECV_SLICE`].
    pub fn bind(path: &Path) -> io::Result<Self> {
        let (addr, len) = sockaddr(path)?;
        let fd = dgram_socket()?;
        let _ = std::fs::remove_file(path);
        // SAFETY: `addr` is a valid sockaddr_un of `len` bytes that outlives the call.
        let rc = unsafe {
            libc::bind(
                fd.as_raw_fd(),
                (&addr as *const libc::sockaddr_un).cast::<libc::sockaddr>(),
                len,
            )
        };
        if rc != 0 {
            let e = io::Error::last_os_error();
            return Err(io::Error::new(
                e.kind(),
                format!("bind {}: {e}", path.display()),
            ));
        }
        let tv = libc::timeval {
            tv_sec: RECV_SLICE.as_secs() as libc::time_t,
            tv_usec: RECV_SLICE.subsec_micros() as libc::suseconds_t,
        };
        // SAFETY: `tv` is a valid timeval whose size is passed; it outlives the call.
        let rc = unsafe {
            libc::setsockopt(
                fd.as_raw_fd(),
                libc::SOL_SOCKET,
                libc::SO_RCVTIMEO,
                (&tv as *const libc::timeval).cast::<libc::c_void>(),
                std::mem::size_of::<libc::timeval>() as libc::socklen_t,
            )
        };
        if rc != 0 {
            return Err(io::Error::last_os_error());
        }
        Ok(Self {
            fd,
            path: path.to_path_buf(),
        })
    }

    /// Receives one message: blocking (at most [`RECV_SLICE`]) or not. No allocation.
    #[inline]
    pub fn recv<T: Wire>(&self, block: bool) -> Recv<T> {
        /// Room for one byte more than `T`, so that an oversized datagram is seen as such.
        #[repr(C)]
        struct Buf<T> {
            msg: T,
            extra: [u8; 8],
        }
        let mut buf = Buf {
            msg: T::default(),
            extra: [0; 8],
        };
        let flags = if block { 0 } else { libc::MSG_DONTWAIT };
        drivelab_runtime::rt::count_syscall();
        // SAFETY: the buffer pointer and length describe `buf`, which is writable and lives
        // across the call; any bytes the kernel writes form a valid `T` (`T: Wire`).
        let n = unsafe {
            libc::recv(
                self.fd.as_raw_fd(),
                (&mut buf as *mut Buf<T>).cast::<libc::c_void>(),
                std::mem::size_of::<Buf<T>>(),
                flags,
            )
        };
        if n < 0 {
            return match errno() {
                libc::EAGAIN | libc::EINTR => Recv::Empty,
                e => Recv::Err(e),
            };
        }
        if n as usize == std::mem::size_of::<T>() {
            Recv::Msg(buf.msg)
        } else {
            Recv::Malformed
        }
    }

    /// Raw receive of one datagram into `buf` (non-blocking); the datagram's length.
    pub fn recv_raw(&self, buf: &mut [u8]) -> io::Result<usize> {
        // SAFETY: `buf` is a valid writable slice of the given length for the call.
        let n = unsafe {
            libc::recv(
                self.fd.as_raw_fd(),
                buf.as_mut_ptr().cast::<libc::c_void>(),
                buf.len(),
                libc::MSG_DONTWAIT,
            )
        };
        if n < 0 {
            Err(io::Error::last_os_error())
        } else {
            Ok(n as usize)
        }
    }
}

impl Drop for Rx {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

/// Outcome of one send.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sent {
    /// Delivered to the receiver's queue.
    Ok,
    /// The receiver's queue is full: dropped.
    Full,
    /// The receiver is gone (its socket was closed).
    PeerGone,
    /// Any other error (errno).
    Err(i32),
}

/// A sending socket connected to one receiver.
#[derive(Debug)]
pub struct Tx {
    fd: OwnedFd,
    /// The receiver's socket name, for messages.
    pub peer: &'static str,
}

impl Tx {
    /// Connects to the receiver bound at `path`, retrying every millisecond while the socket
    /// does not exist yet, until `timeout` or until `stop()` returns true.
    pub fn connect(
        path: &Path,
        peer: &'static str,
        timeout: Duration,
        stop: impl Fn() -> bool,
    ) -> anyhow::Result<Self> {
        let (addr, len) = sockaddr(path)?;
        let fd = dgram_socket()?;
        let started = Instant::now();
        loop {
            // SAFETY: `addr` is a valid sockaddr_un of `len` bytes that outlives the call.
            let rc = unsafe {
                libc::connect(
                    fd.as_raw_fd(),
                    (&addr as *const libc::sockaddr_un).cast::<libc::sockaddr>(),
                    len,
                )
            };
            if rc == 0 {
                return Ok(Self { fd, peer });
            }
            let e = io::Error::last_os_error();
            match e.raw_os_error() {
                Some(libc::ENOENT) | Some(libc::ECONNREFUSED) | Some(libc::EINTR) => {}
                _ => anyhow::bail!("connect to {peer} ({}): {e}", path.display()),
            }
            if stop() {
                anyhow::bail!("stopped while waiting for {peer}");
            }
            if started.elapsed() > timeout {
                anyhow::bail!(
                    "{peer} did not appear at {} within {timeout:?}",
                    path.display()
                );
            }
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    /// Sends one message without blocking. No allocation.
    #[inline]
    pub fn send<T: Wire>(&self, m: &T) -> Sent {
        let b = as_bytes(m);
        drivelab_runtime::rt::count_syscall();
        // SAFETY: `b` is a valid readable slice for the call; MSG_NOSIGNAL avoids SIGPIPE.
        let n = unsafe {
            libc::send(
                self.fd.as_raw_fd(),
                b.as_ptr().cast::<libc::c_void>(),
                b.len(),
                libc::MSG_DONTWAIT | libc::MSG_NOSIGNAL,
            )
        };
        if n >= 0 {
            return Sent::Ok;
        }
        match errno() {
            libc::EAGAIN | libc::ENOBUFS => Sent::Full,
            libc::ECONNREFUSED | libc::ENOTCONN | libc::ECONNRESET | libc::EPIPE | libc::ENOENT => {
                Sent::PeerGone
            }
            e => Sent::Err(e),
        }
    }

    /// Sends a control message (warm-up, end), retrying a full queue for up to `timeout`.
    pub fn send_patiently<T: Wire>(&self, m: &T, timeout: Duration) -> Sent {
        let started = Instant::now();
        loop {
            match self.send(m) {
                Sent::Full if started.elapsed() < timeout => {
                    std::thread::sleep(Duration::from_micros(100))
                }
                s => return s,
            }
        }
    }

    /// Raw send of arbitrary bytes (tests: malformed datagrams).
    pub fn send_raw(&self, b: &[u8]) -> io::Result<()> {
        // SAFETY: `b` is a valid readable slice for the call.
        let n = unsafe {
            libc::send(
                self.fd.as_raw_fd(),
                b.as_ptr().cast::<libc::c_void>(),
                b.len(),
                libc::MSG_DONTWAIT | libc::MSG_NOSIGNAL,
            )
        };
        if n < 0 {
            Err(io::Error::last_os_error())
        } else {
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use drivelab_runtime::messages::{FLAG_END, FLAG_WARMUP};

    fn dir(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("dlb-w-{tag}-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn hdr(k: u64, flags: u32) -> Header {
        Header {
            k,
            t_sample_ns: 123_456_789 + k,
            t_pub_ns: 987_654_321,
            flags,
            reserved: 7,
        }
    }

    #[test]
    fn message_bytes_round_trip() {
        let m = Measurement {
            hdr: hdr(42, FLAG_WARMUP),
            i_abc: [1.0, -2.5, 1.5],
            theta_m_enc: 3.25,
            u_ab_applied: [-0.0, 1e-300],
        };
        let b = as_bytes(&m);
        assert_eq!(b.len(), std::mem::size_of::<Measurement>());
        let back: Measurement = from_bytes(b).unwrap();
        assert_eq!(as_bytes(&back), b); // bit-identical, including -0.0
        assert!(from_bytes::<Measurement>(&b[1..]).is_none());
        assert!(from_bytes::<Estimate>(b).is_none());
    }

    #[test]
    fn messages_round_trip_through_a_socket() {
        let d = dir("rt");
        let rx = Rx::bind(&d.join("a.sock")).unwrap();
        let tx = Tx::connect(&d.join("a.sock"), "a", Duration::from_secs(1), || false).unwrap();
        let e = Estimate {
            hdr: hdr(1, 0),
            theta_e: 1.25,
            omega_m: -3.0,
        };
        let r = CurrentRef {
            hdr: hdr(10, 0),
            omega_ref: 70.0,
            i_d_ref: -1.6,
            i_q_ref: 0.8,
        };
        let c = VoltageCommand {
            hdr: hdr(3, FLAG_END),
            u_ab: [1.0, 2.0],
            u_dq: [3.0, 4.0],
            i_dq_ref: [5.0, 6.0],
            omega_ref: 7.0,
            omega_hat: 8.0,
            theta_hat: 9.0,
        };
        assert_eq!(rx.recv::<Estimate>(false), Recv::Empty);
        assert_eq!(tx.send(&e), Sent::Ok);
        assert_eq!(rx.recv::<Estimate>(true), Recv::Msg(e));
        assert_eq!(tx.send(&r), Sent::Ok);
        assert_eq!(rx.recv::<CurrentRef>(false), Recv::Msg(r));
        assert_eq!(tx.send(&c), Sent::Ok);
        assert_eq!(rx.recv::<VoltageCommand>(false), Recv::Msg(c));
        // Wrong sizes are rejected, in both directions.
        assert_eq!(tx.send(&c), Sent::Ok);
        assert_eq!(rx.recv::<Estimate>(false), Recv::Malformed);
        assert_eq!(tx.send(&e), Sent::Ok);
        assert_eq!(rx.recv::<VoltageCommand>(false), Recv::Malformed);
        tx.send_raw(&[0u8; 3]).unwrap();
        assert_eq!(rx.recv::<Estimate>(false), Recv::Malformed);
        // A blocking receive returns (empty) when nothing comes, instead of blocking for
        // ever; the bound is a watchdog, not a timing claim.
        let t = Instant::now();
        assert_eq!(rx.recv::<Estimate>(true), Recv::Empty);
        assert!(t.elapsed() < 100 * RECV_SLICE);
        // A full queue drops (never blocks); a closed receiver is reported as gone.
        let mut full = false;
        for _ in 0..10_000 {
            if tx.send(&e) == Sent::Full {
                full = true;
                break;
            }
        }
        assert!(full);
        drop(rx);
        // The socket closes once no process holds it: a child that another test thread is
        // spawning at this moment holds a copy of every descriptor until its exec (even a
        // close-on-exec one), and meanwhile the full queue still answers Full. Gone once
        // closed; the bound is a watchdog against a receiver that never goes.
        let t = Instant::now();
        let mut sent = tx.send(&e);
        while sent == Sent::Full && t.elapsed() < Duration::from_secs(10) {
            std::thread::sleep(Duration::from_millis(1));
            sent = tx.send(&e);
        }
        assert_eq!(sent, Sent::PeerGone);
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn long_socket_path_is_a_clear_error() {
        let p = PathBuf::from("/tmp").join("x".repeat(200));
        let e = Rx::bind(&p).unwrap_err().to_string();
        assert!(e.contains("too long"), "{e}");
    }
}
