//! `drivelab run --zenoh-listen`: the launcher's handle on the Zenoh bridge process
//! (`drivelab bridge`, `drivelab_bridge::serve`; docs/architecture.md, "Across machines
//! (Zenoh)"). The bridge starts after the supervisor's telemetry and the recorder's
//! subscriptions exist and before the stage hosts, lets go of the bus before its files are
//! removed, and publishes the summary once it is written.

use super::spawn::die_with_launcher;
use anyhow::{anyhow, bail, Context, Result};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

/// What `drivelab run --zenoh-listen` asks for.
#[derive(Debug, Clone)]
pub struct ZenohListen {
    /// Endpoint to listen on.
    pub endpoint: String,
    /// Zenoh configuration file (TLS, access control).
    pub config: Option<PathBuf>,
    /// Pass fault requests from the network to the supervisor.
    pub allow_remote_faults: bool,
    /// Topics to forward (short names).
    pub topics: Vec<String>,
    /// Connect to `endpoint` instead of listening there (`--zenoh-connect`: the side of a
    /// split drive that joins the other).
    pub connect: bool,
    /// This machine of a split topology (`--machine`): only its processes run here.
    pub machine: Option<String>,
    /// A split drive: how long to wait for the other machine (`--zenoh-wait`).
    pub wait: Duration,
}

/// The running bridge.
pub(super) struct Bridge {
    child: Child,
    stdin: Option<ChildStdin>,
    lines: mpsc::Receiver<String>,
    /// The other machine has left (reported once by [`Bridge::lost`]).
    left: bool,
}

/// How long the bridge may take to answer the launcher.
const ANSWER: Duration = Duration::from_secs(10);

impl Bridge {
    /// Starts the bridge of bus `bus` for the run in `out` and waits until it listens.
    pub fn start(
        z: &ZenohListen,
        bus: &str,
        out: &Path,
        clock: &str,
        verbose: bool,
    ) -> Result<Self> {
        let exe = std::env::current_exe().context("cannot find the drivelab executable")?;
        let mut cmd = Command::new(exe);
        cmd.arg("bridge")
            .arg("--bus")
            .arg(bus)
            .arg("--listen")
            .arg(&z.endpoint)
            .arg("--run-dir")
            .arg(out)
            .arg("--topics")
            .arg(z.topics.join(","));
        if let Some(c) = &z.config {
            cmd.arg("--zenoh-config").arg(c);
        }
        if z.allow_remote_faults {
            cmd.arg("--allow-remote-faults");
        }
        if z.connect {
            cmd.arg("--connect");
        }
        if let Some(m) = &z.machine {
            cmd.arg("--machine")
                .arg(m)
                .arg("--clock")
                .arg(clock)
                .arg("--wait-s")
                .arg(z.wait.as_secs_f64().to_string());
        }
        cmd.stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        die_with_launcher(&mut cmd);
        let mut child = cmd.spawn().context("cannot start the zenoh bridge")?;
        let stdout = child.stdout.take().expect("piped");
        let stderr = child.stderr.take().expect("piped");
        // Its error lines: the last one explains a failed start; later ones (refused fault
        // requests) are passed on.
        let (etx, errors) = mpsc::channel::<String>();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if etx.send(line.clone()).is_err() {
                    crate::errln!("{line}");
                }
            }
        });
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let mut b = Self {
            stdin: child.stdin.take(),
            child,
            lines,
            left: false,
        };
        // The joining side of a split drive retries its connection and then asks the other
        // side for its scenario.
        let ready = b.answer_within(
            "ready",
            if z.connect {
                ANSWER + z.wait * 2
            } else {
                ANSWER
            },
        );
        let mut early: Vec<String> = errors.try_iter().collect();
        if ready.is_err() {
            b.kill();
            // Its stderr closes with it: take every line up to there.
            while let Ok(l) = errors.recv_timeout(Duration::from_secs(2)) {
                early.push(l);
            }
        }
        // From now on its error lines go straight to the launcher's stderr.
        drop(errors);
        match ready {
            Ok(placed) => {
                for line in early {
                    crate::errln!("{line}");
                }
                if verbose {
                    crate::errln!(
                        "drivelab: zenoh bridge {} {} ({placed}); remote faults {}",
                        if z.connect {
                            "connected to"
                        } else {
                            "listening on"
                        },
                        z.endpoint,
                        if z.allow_remote_faults {
                            "allowed"
                        } else {
                            "refused"
                        }
                    );
                }
                Ok(b)
            }
            Err(e) => {
                // The bridge's own one-line error says why (a port in use, a bad config).
                match early.last() {
                    Some(why) => Err(anyhow!(
                        "zenoh bridge: {}",
                        why.trim_start_matches("drivelab: error: ")
                    )),
                    None => Err(e),
                }
            }
        }
    }

    /// Waits for the line that starts with `word`; returns the rest of it.
    fn answer(&mut self, word: &str) -> Result<String> {
        self.answer_within(word, ANSWER)
    }

    fn answer_within(&mut self, word: &str, within: Duration) -> Result<String> {
        let line = loop {
            match self.lines.recv_timeout(within) {
                // A notice that the other machine left (see `lost`) is no answer.
                Ok(line) if line.starts_with("lost ") => continue,
                other => break other,
            }
        };
        match line {
            Ok(line) if line.split(' ').next() == Some(word) => {
                Ok(line[word.len()..].trim().to_string())
            }
            Ok(line) => bail!("zenoh bridge: expected '{word}', got '{line}'"),
            Err(_) => {
                let status = self.child.try_wait().ok().flatten();
                match status {
                    Some(s) => bail!("the zenoh bridge exited ({s})"),
                    None => bail!("the zenoh bridge did not answer '{word}' within {within:?}"),
                }
            }
        }
    }

    fn tell(&mut self, line: &str) -> Result<()> {
        let stdin = self
            .stdin
            .as_mut()
            .ok_or_else(|| anyhow!("zenoh bridge: input closed"))?;
        writeln!(stdin, "{line}")
            .and_then(|_| stdin.flush())
            .map_err(|e| anyhow!("zenoh bridge: {e}"))
    }

    /// A split drive: tells the other machine that this one's stage hosts are ready and
    /// waits until the other's are (the bridge gives up after `wait`).
    pub fn meet(&mut self, wait: Duration) -> Result<()> {
        self.tell("peer")?;
        self.answer_within("peer", wait + ANSWER).map(|_| ())
    }

    /// A split drive: `Some(why)` once the other machine has left the link (its bridge
    /// ended or the network failed); never blocks.
    pub fn lost(&mut self) -> Option<String> {
        let why = match self.lines.try_recv() {
            Ok(line) => line.strip_prefix("lost ").map(str::to_string),
            Err(_) => None,
        };
        self.left |= why.is_some();
        why
    }

    /// A split drive: whether the other machine has left, now or before.
    pub fn has_left(&mut self) -> bool {
        self.lost();
        self.left
    }

    /// Makes the bridge forward what is left and let go of the bus; returns its counters.
    pub fn detach(&mut self) -> Result<serde_json::Value> {
        self.tell("detach")?;
        let stats = self.answer("detached")?;
        serde_json::from_str(&stats).map_err(|e| anyhow!("zenoh bridge counters: {e}"))
    }

    /// Publishes the summary at `path` to remote recorders and ends the bridge.
    pub fn finish(mut self, path: &Path) -> Result<()> {
        self.tell(&format!("summary {}", path.display()))?;
        let r = self.answer("done");
        self.stdin = None;
        let _ = self.child.wait();
        r.map(|_| ())
    }

    /// Ends the bridge at once (a failed run).
    pub fn kill(&mut self) {
        self.stdin = None;
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Bridge {
    fn drop(&mut self) {
        if matches!(self.child.try_wait(), Ok(None)) {
            self.kill();
        }
    }
}
