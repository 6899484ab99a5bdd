//! The files drivelab writes into a run folder (or any folder a user names), created without
//! following a symbolic link.
//!
//! A run folder may be an earlier run's, and anyone who can write into it could put a link
//! there named like one of the run's files (`trace.csv` → a file of the user's, or of root's
//! when root runs the drive). The earlier run's outputs, links among them, are removed before
//! a run starts; every file is then created through [`create`], which refuses a link in place
//! of the file instead of writing where it points (docs/architecture.md, "Who can reach a
//! drive").

use std::fs::File;
use std::io::Write;
use std::os::unix::fs::OpenOptionsExt;
use std::path::Path;

/// Opens `path` for writing, created (mode 0666 less the umask) or truncated. When `path`
/// is a symbolic link the error says so and names it, whatever the link points to (nothing
/// is opened, created or truncated).
pub fn create(path: impl AsRef<Path>) -> std::io::Result<File> {
    let path = path.as_ref();
    std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
        .open(path)
        .map_err(|e| refused_link(path, e))
}

/// [`create`], then writes all of `bytes`.
pub fn write(path: impl AsRef<Path>, bytes: impl AsRef<[u8]>) -> std::io::Result<()> {
    create(path)?.write_all(bytes.as_ref())
}

/// `e`, or (ELOOP on a path that is a link: `O_NOFOLLOW` refused it) an error that says why.
fn refused_link(path: &Path, e: std::io::Error) -> std::io::Error {
    let is_link = path
        .symlink_metadata()
        .is_ok_and(|m| m.file_type().is_symlink());
    if e.raw_os_error() == Some(libc::ELOOP) && is_link {
        std::io::Error::other(format!(
            "{} is a symbolic link: refused (drivelab never writes through one; remove it)",
            path.display()
        ))
    } else {
        e
    }
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
    fn other_errors_pass_through() {
        let d = scratch("other");
        let e = create(d.join("no-such-folder/x")).unwrap_err();
        assert_eq!(e.kind(), std::io::ErrorKind::NotFound);
        std::fs::remove_dir_all(&d).unwrap();
    }
}
