//! The files drivelab writes into a run folder (or any folder a user names), created without
//! following a symbolic link.
//!
//! A run folder may be an earlier run's, and anyone who can write into it could put a link
//! there named like one of the run's files (`trace.csv` → a file of the user's, or of root's
//! when root runs the drive). The earlier run's outputs, links among them, are removed before
//! a run starts; every file is then created through [`create`], which refuses a link in place
//! of the file (symbolic or hard) instead of writing where it points (docs/architecture.md,
//! "Who can reach a drive").

use std::fs::File;
use std::io::Write;
use std::os::unix::fs::OpenOptionsExt;
use std::path::Path;

/// Opens `path` for writing, created (mode 0666 less the umask) or truncated. When `path`
/// is a symbolic link the error says so and names it, whatever the link points to (nothing
/// is opened, created or truncated). So it does when `path` is a file with more than one
/// name (a hard link to a file elsewhere, which anybody can make to another user's file
/// where `fs.protected_hardlinks` is off): it is opened, found shared, and closed untouched; and
/// when it is not a regular file (a FIFO would otherwise hold the command forever).
pub fn create(path: impl AsRef<Path>) -> std::io::Result<File> {
    use std::os::unix::fs::MetadataExt;
    let path = path.as_ref();
    let file = std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        // O_NONBLOCK: a FIFO planted in place of the file would block the open until
        // somebody reads it; this way it fails (ENXIO) or is refused below. A regular
        // file's reads and writes ignore the flag.
        .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC | libc::O_NONBLOCK)
        .open(path)
        .map_err(|e| refused(path, e))?;
    let meta = file.metadata()?;
    if !meta.is_file() {
        return Err(not_regular(path));
    }
    let links = meta.nlink();
    if links > 1 {
        return Err(std::io::Error::other(format!(
            "{} has {links} hard links: refused (drivelab never writes into a file that also \
             has another name; remove it)",
            path.display()
        )));
    }
    file.set_len(0)?;
    Ok(file)
}

/// [`create`], then writes all of `bytes`.
pub fn write(path: impl AsRef<Path>, bytes: impl AsRef<[u8]>) -> std::io::Result<()> {
    create(path)?.write_all(bytes.as_ref())
}

/// `e`, or an error that says why the path was refused: ELOOP on a path that is a link
/// (`O_NOFOLLOW` refused it), ENXIO on one that is a FIFO nobody reads (`O_NONBLOCK`).
fn refused(path: &Path, e: std::io::Error) -> std::io::Error {
    let kind = path.symlink_metadata().map(|m| m.file_type());
    match (e.raw_os_error(), kind) {
        (Some(libc::ELOOP), Ok(t)) if t.is_symlink() => std::io::Error::other(format!(
            "{} is a symbolic link: refused (drivelab never writes through one; remove it)",
            path.display()
        )),
        (Some(libc::ENXIO), Ok(t)) if !t.is_file() => not_regular(path),
        _ => e,
    }
}

fn not_regular(path: &Path) -> std::io::Error {
    std::io::Error::other(format!(
        "{} is not a regular file: refused (remove it)",
        path.display()
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(tag: &str) -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("drivelab-files-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn a_file_is_created_and_an_existing_one_replaced() {
        let d = scratch("plain");
        let p = d.join("summary.json");
        write(&p, b"first, longer").unwrap();
        write(&p, b"second").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"second");
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn a_link_in_place_of_the_file_is_refused_and_its_target_left_alone() {
        let d = scratch("link");
        let victim = d.join("victim");
        std::fs::write(&victim, b"keep me").unwrap();
        let p = d.join("trace.csv");
        std::os::unix::fs::symlink(&victim, &p).unwrap();
        let e = write(&p, b"overwritten").unwrap_err().to_string();
        assert_eq!(
            e,
            format!(
                "{} is a symbolic link: refused (drivelab never writes through one; remove it)",
                p.display()
            )
        );
        assert_eq!(std::fs::read(&victim).unwrap(), b"keep me");
        // A link to nowhere would otherwise make the file it names.
        let dangling = d.join("summary.json");
        std::os::unix::fs::symlink(d.join("made-through-the-link"), &dangling).unwrap();
        assert!(create(&dangling).is_err());
        assert!(!d.join("made-through-the-link").exists());
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn a_hard_link_in_place_of_the_file_is_refused_and_the_file_left_alone() {
        let d = scratch("hard");
        let victim = d.join("victim");
        std::fs::write(&victim, b"keep me").unwrap();
        let p = d.join("trace.csv");
        std::fs::hard_link(&victim, &p).unwrap();
        let e = write(&p, b"overwritten").unwrap_err().to_string();
        assert_eq!(
            e,
            format!(
                "{} has 2 hard links: refused (drivelab never writes into a file that also \
                 has another name; remove it)",
                p.display()
            )
        );
        assert_eq!(std::fs::read(&victim).unwrap(), b"keep me");
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn a_fifo_in_place_of_the_file_is_refused_without_waiting_for_a_reader() {
        let d = scratch("fifo");
        let p = d.join("summary.json");
        let c = std::ffi::CString::new(p.as_os_str().as_encoded_bytes()).unwrap();
        // SAFETY: `c` is a NUL-terminated path that outlives the call.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        // Nobody reads it: without O_NONBLOCK the open would wait for ever (the watchdog).
        let (tx, rx) = std::sync::mpsc::channel();
        let path = p.clone();
        std::thread::spawn(move || tx.send(create(&path).map(|_| ())));
        let e = rx
            .recv_timeout(std::time::Duration::from_secs(10))
            .expect("create waited for a reader of the FIFO")
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            format!("{} is not a regular file: refused (remove it)", p.display())
        );
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn other_errors_pass_through() {
        let d = scratch("other");
        let e = create(d.join("no-such-folder/x")).unwrap_err();
        assert_eq!(e.kind(), std::io::ErrorKind::NotFound);
        std::fs::remove_dir_all(&d).unwrap();
    }
}
