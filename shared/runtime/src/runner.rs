//! A runner for the processes that drivelab starts: a command put in front of each one, as
//! cargo's `target.<triple>.runner` is. With `qemu-aarch64 -L /usr/aarch64-linux-gnu` a
//! launcher built for aarch64 starts its aarch64 stage hosts on an x86_64 machine without
//! any binfmt handler; with `strace -f -o trace.log` or a logging script it shows what is
//! started.
//!
//! The runner is given by `drivelab run --runner 'CMD'` or by the environment variable
//! [`ENV`] (the bench's nodes read only the variable). It is split at whitespace, with no
//! shell quoting, as cargo splits its runner. It must end by exec'ing the program it is
//! given (qemu-user and `exec "$@"` scripts do): drivelab signals the process it started,
//! and a runner that stays in front would take the signals of fault injection and shutdown.

use std::ffi::OsStr;
use std::process::Command;

/// The environment variable that holds a runner.
pub const ENV: &str = "DRIVELAB_RUNNER";

/// A command put in front of every process that drivelab starts.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Runner {
    program: String,
    args: Vec<String>,
}

impl Runner {
    /// Parses `CMD` (split at whitespace). An empty or blank `CMD` is an error.
    pub fn parse(cmd: &str) -> Result<Self, String> {
        let mut words = cmd.split_whitespace().map(String::from);
        let program = words.next().ok_or_else(|| {
            "the runner is empty: give a command, e.g. 'qemu-aarch64 -L /usr/aarch64-linux-gnu'"
                .to_string()
        })?;
        Ok(Self {
            program,
            args: words.collect(),
        })
    }

    /// The runner of [`ENV`], if it is set (an empty value counts as unset).
    pub fn from_env() -> Result<Option<Self>, String> {
        match std::env::var(ENV) {
            Ok(v) if !v.trim().is_empty() => {
                Self::parse(&v).map(Some).map_err(|e| format!("{ENV}: {e}"))
            }
            _ => Ok(None),
        }
    }

    /// Whether the runner's program can be started (see [`locate`]). A one-line error
    /// otherwise, so that a run can refuse it before it makes anything.
    pub fn check(&self) -> Result<(), String> {
        let missing = match locate(&self.program) {
            Ok(_) => return Ok(()),
            Err(Missing::NotExecutable) => "",
            Err(Missing::NotOnPath) => " on PATH",
        };
        Err(format!(
            "the runner '{}' cannot be started: {} is not an executable file{missing}",
            self.display(),
            self.program
        ))
    }

    /// The runner's words, to show in messages.
    pub fn display(&self) -> String {
        std::iter::once(self.program.as_str())
            .chain(self.args.iter().map(String::as_str))
            .collect::<Vec<_>>()
            .join(" ")
    }
}

/// Why [`locate`] found no program.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Missing {
    /// A path (it holds a `/`) that is not an executable file.
    NotExecutable,
    /// A name that no executable file on `PATH` has.
    NotOnPath,
}

/// The program `cmd` names: `cmd` itself when it holds a `/` and is an executable file, else
/// the first executable file of that name on `PATH`.
pub fn locate(cmd: &str) -> Result<std::path::PathBuf, Missing> {
    use std::os::unix::fs::PermissionsExt;
    let runnable = |p: &std::path::Path| {
        std::fs::metadata(p).is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
    };
    if cmd.contains('/') {
        let p = std::path::PathBuf::from(cmd);
        return if runnable(&p) {
            Ok(p)
        } else {
            Err(Missing::NotExecutable)
        };
    }
    std::env::var_os("PATH")
        .and_then(|path| {
            std::env::split_paths(&path)
                .map(|d| d.join(cmd))
                .find(|p| runnable(p))
        })
        .ok_or(Missing::NotOnPath)
}

/// A command that starts `program`, through `runner` when there is one.
pub fn command(runner: Option<&Runner>, program: impl AsRef<OsStr>) -> Command {
    match runner {
        Some(r) => {
            let mut c = Command::new(&r.program);
            c.args(&r.args).arg(program);
            c
        }
        None => Command::new(program),
    }
}

/// A command that starts `program` through the runner of [`ENV`], if set. A malformed
/// variable is an error (so that a typo does not silently start native binaries).
pub fn env_command(program: impl AsRef<OsStr>) -> Result<Command, String> {
    Ok(command(Runner::from_env()?.as_ref(), program))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_runner_that_cannot_be_started_is_named_before_the_run() {
        for ok in ["sh -c", "/bin/sh -c"] {
            assert_eq!(Runner::parse(ok).unwrap().check(), Ok(()), "{ok}");
        }
        let e = Runner::parse("/nonexistent/qemu -L x")
            .unwrap()
            .check()
            .unwrap_err();
        assert_eq!(
            e,
            "the runner '/nonexistent/qemu -L x' cannot be started: /nonexistent/qemu is not an executable file"
        );
        let e = Runner::parse("no-such-runner-xyz")
            .unwrap()
            .check()
            .unwrap_err();
        assert!(e.ends_with("is not an executable file on PATH"), "{e}");
        // A folder is not a program.
        assert!(Runner::parse("/tmp").unwrap().check().is_err());
    }

    #[test]
    fn a_runner_goes_in_front_of_the_program() {
        let r = Runner::parse("  qemu-aarch64  -L /usr/aarch64-linux-gnu ").unwrap();
        assert_eq!(r.display(), "qemu-aarch64 -L /usr/aarch64-linux-gnu");
        let c = command(Some(&r), "/x/drivelab-host");
        assert_eq!(c.get_program(), "qemu-aarch64");
        let args: Vec<_> = c.get_args().collect();
        assert_eq!(args, ["-L", "/usr/aarch64-linux-gnu", "/x/drivelab-host"]);
        let c = command(None, "/x/drivelab-host");
        assert_eq!(c.get_program(), "/x/drivelab-host");
        assert_eq!(c.get_args().count(), 0);
    }

    #[test]
    fn an_empty_runner_is_refused() {
        assert!(Runner::parse("").is_err());
        assert!(Runner::parse(" \t ")
            .unwrap_err()
            .contains("runner is empty"));
    }
}
