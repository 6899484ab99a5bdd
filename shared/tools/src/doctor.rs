//! `drivelab doctor`: how ready this machine is for real-time work.
//!
//! Every check only **reads** (files under `/sys` and `/proc`, `uname`, `getrlimit`,
//! `statvfs`; "other load" reads every thread's CPU time twice, 300 ms apart; "kernel
//! runs" reads every task's run count and CPU time since it started). The one
//! active probe, "can this process use `SCHED_FIFO`", runs in a
//! short-lived thread of its own that switches to `SCHED_FIFO` priority 1 and straight back
//! to `SCHED_OTHER`, then exits; nothing persists. Advice strings describe what an operator
//! could do to improve timing; they are text only and are never executed.
//!
//! All file reads go through [`read_trimmed`] and a root directory (`/` for the real
//! machine, see [`run_checks_in`]), so a missing or unreadable file gives
//! [`Status::Unknown`], never a panic, and the checks can be tested on a fake tree.
//!
//! Nothing assumes an x86 machine: the checks read what ARM boards have and x86 VMs often do
//! not (cpufreq policies and their frequency limits, cpuidle states per CPU, the
//! architected timer `arch_sys_counter`), and a file that is not there is reported as such.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::io;
use std::path::{Path, PathBuf};

use serde::Serialize;

use drivelab_runtime::{rt, tick};

/// One line of the doctor report.
#[derive(Debug, Clone, Serialize)]
pub struct Check {
    /// Short name, e.g. `"rt throttling"`.
    pub name: String,
    /// What was found.
    pub value: String,
    /// How good that is for real-time work.
    pub status: Status,
    /// What would improve timing (never executed by drivelab).
    pub advice: Option<String>,
}

/// Verdict of one [`Check`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum Status {
    /// Fine for real-time work.
    Ok,
    /// Works, but timing will suffer (jitter, throttling, ...).
    Warn,
    /// Real-time operation is not possible or badly degraded.
    Bad,
    /// Could not be determined (file missing or unreadable).
    Unknown,
}

impl Status {
    /// Label used in the text table.
    pub fn label(self) -> &'static str {
        match self {
            Status::Ok => "OK",
            Status::Warn => "WARN",
            Status::Bad => "BAD",
            Status::Unknown => "UNKNOWN",
        }
    }
}

impl Check {
    fn new(name: &str, value: impl Into<String>, status: Status, advice: Option<String>) -> Self {
        Check {
            name: name.to_string(),
            value: value.into(),
            status,
            advice,
        }
    }
}

/// A topology's processes, for `drivelab doctor --topology`: the checks made per core
/// (isolation, device interrupts, kernel runs) are judged for the cores they are pinned to
/// instead of the default placement's. Of a topology split across machines (processes that
/// name a `machine`), only this machine's processes are judged ([`Placement::new`]).
#[derive(Debug, Clone, Default)]
pub struct Placement {
    /// What names it: a shipped topology's name or a file.
    pub name: String,
    /// The processes this machine runs (every one, unless the topology is split).
    pub processes: Vec<drivelab_runtime::topology::ProcessSpec>,
    /// Of a split topology: this machine's name, as `--machine` gives it.
    pub machine: Option<String>,
    /// Of a split topology: the other machines' processes, not judged here.
    pub away: Vec<drivelab_runtime::topology::ProcessSpec>,
}

impl Placement {
    /// The placement of topology `name`'s `processes` on this machine. The doctor cannot tell
    /// which machine of a split topology this is: as `drivelab run`, it is told with
    /// `machine` (`--machine`), whose processes are judged and the others' listed as not
    /// judged here; without it the whole topology is judged on this machine, as a run
    /// without `--machine` runs it. A `machine` the topology does not name, or one given
    /// for a topology that is not split, is refused in one line.
    pub fn new(
        name: &str,
        processes: Vec<drivelab_runtime::topology::ProcessSpec>,
        machine: Option<&str>,
    ) -> Result<Self, String> {
        let machines = drivelab_runtime::topology::machines(&processes);
        let name = name.to_string();
        match machine {
            None => Ok(Self {
                name,
                processes,
                ..Self::default()
            }),
            Some(m) if machines.is_empty() => Err(format!(
                "--machine {m}: topology {name} is not split across machines (no process names a machine)"
            )),
            Some(m) if !machines.iter().any(|x| x == m) => Err(format!(
                "--machine {m}: topology {name} has no machine '{m}' (its machines: {})",
                machines.join(", ")
            )),
            Some(m) => {
                let (here, away) = processes
                    .into_iter()
                    .partition(|p| p.machine.as_deref() == Some(m));
                Ok(Self {
                    name,
                    processes: here,
                    machine: Some(m.to_string()),
                    away,
                })
            }
        }
    }

    /// The CPUs its processes are pinned to, sorted.
    fn cpus(&self) -> Vec<usize> {
        let mut v: Vec<usize> = self.processes.iter().filter_map(|p| p.cpu).collect();
        v.sort_unstable();
        v.dedup();
        v
    }
}

/// Runs every check against the real machine.
pub fn run_checks() -> Vec<Check> {
    run_checks_for(None)
}

/// Runs every check against the real machine, the per-core ones for `placement`'s cores when
/// one is given.
pub fn run_checks_for(placement: Option<&Placement>) -> Vec<Check> {
    run_checks_in_for(Path::new("/"), placement)
}

/// Runs every check with all file paths taken relative to `root` (`/` for the real
/// machine; a fake tree in tests). Probes that are not files (`uname`, rlimits, the
/// `SCHED_FIFO` probe, the process's euid) always look at the live system.
pub fn run_checks_in(root: &Path) -> Vec<Check> {
    run_checks_in_for(root, None)
}

/// [`run_checks_in`], the per-core checks for `placement`'s cores when one is given (with a
/// "placement" line about the placement itself).
pub fn run_checks_in_for(root: &Path, placement: Option<&Placement>) -> Vec<Check> {
    let fs = Fs { root };
    let uts = uname();
    let online = online_cpu_list(&fs);
    let caps = Caps::read(&fs);
    let drive = match placement {
        Some(p) => p.cpus(),
        None => drive_cpus(&fs, &online),
    };
    let mut checks = vec![
        kernel_check(uts.as_ref()),
        preemption_check(
            &fs,
            uts.as_ref().map(|u| u.version.as_str()),
            uts.as_ref().map(|u| u.release.as_str()),
        ),
        rt_throttling_check(&fs),
        online_cpus_check(&online),
        match placement {
            Some(p) => isolated_cpus_check_for(&fs, &online, &p.cpus()),
            None => isolated_cpus_check(&fs, &online),
        },
        device_irq_check_on(&fs, &drive),
        governor_check(&fs),
        cpufreq_limits_check(&fs),
        smt_check(&fs),
        irqbalance_check(&fs),
        sched_fifo_check(&caps),
        mlock_check(&caps),
        timer_slack_check(&fs),
        clocksource_check(&fs),
        address_space_check(&fs),
        dev_shm_check(&fs),
        cpuidle_check(&fs),
        cpu_latency_request_check(&fs),
        tick_check(&fs, uts.as_ref().map(|u| u.release.as_str())),
        other_load_check(&fs, BUSY_WINDOW),
        kernel_runs_check_on(&fs, &drive),
    ];
    if let Some(p) = placement {
        checks.insert(4, placement_check(&online, p));
    }
    checks
}

/// What a topology's placement means on this machine: the cores it pins, one it pins that
/// the machine does not have (a real-time run refuses it), processes it leaves unpinned, and
/// processes that share a core at one SCHED_FIFO priority.
fn placement_check(online: &[usize], p: &Placement) -> Check {
    const NAME: &str = "placement";
    let mut by_cpu: BTreeMap<usize, Vec<&str>> = BTreeMap::new();
    let mut unpinned = Vec::new();
    for q in &p.processes {
        match q.cpu {
            Some(c) => by_cpu.entry(c).or_default().push(&q.name),
            None => unpinned.push(q.name.as_str()),
        }
    }
    let mut value = match &p.machine {
        Some(m) => format!("topology {}, machine {m} (--machine): ", p.name),
        None => format!("topology {}: ", p.name),
    };
    let pinned: Vec<String> = by_cpu
        .iter()
        .map(|(c, who)| format!("cpu {c}: {}", who.join(", ")))
        .collect();
    value.push_str(&if pinned.is_empty() {
        "no process pinned to a cpu".to_string()
    } else {
        pinned.join("; ")
    });
    if !unpinned.is_empty() {
        let _ = write!(value, "; not pinned: {}", unpinned.join(", "));
    }
    if p.machine.is_none() && !drivelab_runtime::topology::machines(&p.processes).is_empty() {
        value.push_str(
            " (split across machines: judged whole on this machine, as drivelab run without --machine runs it; --machine NAME judges one machine's share)",
        );
    }
    for m in drivelab_runtime::topology::machines(&p.away) {
        let who: Vec<&str> = p
            .away
            .iter()
            .filter(|q| q.machine.as_ref() == Some(&m))
            .map(|q| q.name.as_str())
            .collect();
        let _ = write!(value, "; not judged here (machine {m}): {}", who.join(", "));
    }
    let missing: Vec<String> = by_cpu
        .keys()
        .filter(|c| !online.contains(c))
        .map(|c| c.to_string())
        .collect();
    if !missing.is_empty() {
        return Check::new(
            NAME,
            value,
            Status::Bad,
            Some(format!(
                "cpu {} is not online here (online: {}): a real-time run refuses a process pinned to it; change its cpu",
                missing.join(", "),
                fmt_cpu_list(online)
            )),
        );
    }
    let mut advice = drivelab_runtime::topology::placement_warnings(&p.processes);
    if !unpinned.is_empty() {
        advice.push(
            "a process pinned to no cpu runs wherever the scheduler puts it, beside the OS; give it a cpu".into(),
        );
    }
    if advice.is_empty() {
        Check::new(NAME, value, Status::Ok, None)
    } else {
        Check::new(NAME, value, Status::Warn, Some(advice.join("; ")))
    }
}

/// The "kernel tick" check alone, on the real machine: what a drive's summary records of the
/// tick its schedule was aligned with.
pub fn kernel_tick() -> Check {
    tick_check(
        &Fs {
            root: Path::new("/"),
        },
        uname().as_ref().map(|u| u.release.as_str()),
    )
}

/// The idle driver and the states (exit latency, µs) of every CPU, grouped by CPUs with the
/// same states (the clusters of an ARM board may differ): an idle CPU that must leave a
/// state with a long exit latency wakes late.
fn cpuidle_check(fs: &Fs) -> Check {
    const NAME: &str = "cpuidle";
    let driver = fs.read("/sys/devices/system/cpu/cpuidle/current_driver");
    let governor = fs.read("/sys/devices/system/cpu/cpuidle/current_governor");
    let mut worst = 0u64;
    // (states of a CPU, the CPUs that have them), in CPU order.
    let mut groups: Vec<(Vec<String>, Vec<usize>)> = Vec::new();
    for cpu in fs.cpu_dirs().unwrap_or_default() {
        let base = format!("/sys/devices/system/cpu/cpu{cpu}/cpuidle");
        let mut states = Vec::new();
        for st in fs.list(&base).unwrap_or_default() {
            let dir = format!("{base}/{st}");
            let (Some(name), Some(lat)) = (
                fs.read(&format!("{dir}/name")),
                fs.read(&format!("{dir}/latency")),
            ) else {
                continue;
            };
            let lat: u64 = lat.parse().unwrap_or(0);
            let disabled = fs.read(&format!("{dir}/disable")).is_some_and(|d| d == "1");
            if !disabled {
                worst = worst.max(lat);
            }
            states.push(format!(
                "{name} {lat} µs{}",
                if disabled { " (disabled)" } else { "" }
            ));
        }
        if states.is_empty() {
            continue;
        }
        match groups.iter_mut().find(|(s, _)| *s == states) {
            Some((_, cpus)) => cpus.push(cpu),
            None => groups.push((states, vec![cpu])),
        }
    }
    let value = match (&driver, groups.is_empty()) {
        (None, true) => {
            return Check::new(
                NAME,
                "no cpuidle (idle CPUs halt)",
                Status::Ok,
                Some(LATENCY_ADVICE.into()),
            )
        }
        (d, _) => format!(
            "driver {}{}; {}",
            d.as_deref().unwrap_or("unknown"),
            governor
                .as_deref()
                .map_or(String::new(), |g| format!(", governor {g}")),
            if groups.is_empty() {
                "no states".to_string()
            } else {
                groups
                    .iter()
                    .map(|(s, cpus)| {
                        format!("states on cpu{}: {}", fmt_cpu_list(cpus), s.join(", "))
                    })
                    .collect::<Vec<_>>()
                    .join("; ")
            }
        ),
    };
    // Waking a halted vCPU costs about 11 µs on the measured VM even at exit latency 1 µs.
    let status = if worst > 0 { Status::Warn } else { Status::Ok };
    let advice = (status == Status::Warn).then(|| {
        if governor.as_deref() == Some("haltpoll") {
            format!("{LATENCY_ADVICE}; {HALTPOLL_ADVICE}")
        } else {
            LATENCY_ADVICE.into()
        }
    });
    Check::new(NAME, value, status, advice)
}

/// haltpoll sets a CPU's poll window when a request makes it poll and shrinks it only when the
/// CPU halts, so a periodic load keeps polling after the request is gone.
const HALTPOLL_ADVICE: &str = "the haltpoll governor keeps a CPU polling after a request is released until the CPU has halted a few times, so let the CPU idle before measuring without one (drivelab bench does)";

const LATENCY_ADVICE: &str = "drivelab run holds a CPU wake-up latency request while a real-time drive runs ([timing] cpu_latency_us, default 0 µs), which keeps idle CPUs out of these states";

/// The PM QoS CPU latency in force and who holds a request now.
fn cpu_latency_request_check(fs: &Fs) -> Check {
    const NAME: &str = "cpu latency request";
    let holders = latency_request_holders(fs);
    let held = if holders.is_empty() {
        "held by no process".to_string()
    } else {
        format!("held by {}", holders.join(", "))
    };
    match std::fs::read(fs.path(drivelab_runtime::rt::CPU_DMA_LATENCY)) {
        Ok(b) if b.len() >= 4 => {
            let v = i32::from_ne_bytes([b[0], b[1], b[2], b[3]]);
            // The kernel's default (no request) is 2000 s.
            let in_force = if v >= 2_000_000_000 {
                "none in force".to_string()
            } else {
                format!("{v} µs in force")
            };
            Check::new(NAME, format!("{in_force}; {held}"), Status::Ok, None)
        }
        Ok(_) => Check::new(NAME, format!("unreadable value; {held}"), Status::Unknown, None),
        Err(e) => Check::new(
            NAME,
            format!("{}: {e}; {held}", drivelab_runtime::rt::CPU_DMA_LATENCY),
            Status::Warn,
            Some("without this device (or as a user without access to it) a drive cannot hold a CPU wake-up latency request; idle CPUs may wake late".into()),
        ),
    }
}

/// The scheduler tick: its period (CONFIG_HZ) and where it falls within a millisecond on each
/// CPU (from `/proc/timer_list`, which only root can read). A tick-aligned schedule (`[timing]
/// tick_aligned`) starts on its own CPU's tick so that every tick there expires with a
/// deadline (docs/architecture.md, "The tick and the samples"); that holds only where the
/// tick's period is whole milliseconds, and for the stages on other CPUs only where their
/// ticks fall at the same point of a millisecond.
fn tick_check(fs: &Fs, release: Option<&str>) -> Check {
    const NAME: &str = "kernel tick";
    let hz = kernel_config(fs, release).and_then(|c| config_hz(&c));
    let period = match hz {
        Some(hz) => format!("CONFIG_HZ {hz}, every {}", fmt_ms(1_000_000_000 / hz)),
        None => "CONFIG_HZ unknown".to_string(),
    };
    let skew = if fs.cmdline_param("skew_tick").is_some_and(|v| v != "0") {
        " (skew_tick on the kernel command line offsets the tick per CPU)"
    } else {
        ""
    };
    let Some(text) = fs.read(tick::TIMER_LIST) else {
        return Check::new(
            NAME,
            format!("{period}; its phase unknown: /proc/timer_list unreadable (root reads it)"),
            Status::Unknown,
            None,
        );
    };
    let ticks = tick::parse(&text);
    let stopped: Vec<usize> = ticks
        .iter()
        .filter(|t| t.next_ns.is_none())
        .map(|t| t.cpu)
        .collect();
    // (phase past the millisecond in ns, the CPUs whose tick has it); a stopped tick restarts
    // on its grid, so its last expiry gives its phase.
    let mut phases: Vec<(u64, Vec<usize>)> = Vec::new();
    let mut unknown = Vec::new();
    for t in &ticks {
        match t.phase_ns() {
            Some(ph) => match phases.iter_mut().find(|(p, _)| *p == ph) {
                Some((_, cpus)) => cpus.push(t.cpu),
                None => phases.push((ph, vec![t.cpu])),
            },
            None => unknown.push(t.cpu),
        }
    }
    let mut where_ = phases
        .iter()
        .map(|(ph, cpus)| match ph {
            0 => format!("on whole milliseconds on cpu{}", fmt_cpu_list(cpus)),
            _ => format!(
                "{} past the millisecond on cpu{}",
                fmt_ms(*ph),
                fmt_cpu_list(cpus)
            ),
        })
        .collect::<Vec<_>>();
    if !stopped.is_empty() {
        where_.push(format!("stopped on idle cpu{}", fmt_cpu_list(&stopped)));
    }
    if !unknown.is_empty() {
        where_.push(format!("no phase shown for cpu{}", fmt_cpu_list(&unknown)));
    }
    if where_.is_empty() {
        where_.push("no tick timer found in /proc/timer_list".to_string());
    }
    let value = format!("{period}; {}{skew}", where_.join(", "));
    let whole_ms = hz.map(|hz| (1_000_000_000 / hz).is_multiple_of(tick::GRID_NS));
    if whole_ms == Some(false) {
        return Check::new(
            NAME,
            value,
            Status::Warn,
            Some("the tick's period is not whole milliseconds, so a tick-aligned schedule ([timing] tick_aligned) meets it at a deadline only now and then, and at other ticks the tick interrupts a sample part-way: compare runs with tick_aligned = false".into()),
        );
    }
    if phases.len() > 1 {
        return Check::new(
            NAME,
            value,
            Status::Warn,
            Some("the CPUs' ticks fall at different points of a millisecond: a tick-aligned schedule ([timing] tick_aligned, default true) starts on the plant's CPU's tick, so stages on another CPU meet theirs part-way through a sample; keep the chain on one core, or compare runs with tick_aligned = false".into()),
        );
    }
    let status = if phases.is_empty() || hz.is_none() {
        Status::Unknown
    } else {
        Status::Ok
    };
    Check::new(NAME, value, status, None)
}

/// `CONFIG_HZ=N` in a kernel configuration's text.
fn config_hz(config: &str) -> Option<u64> {
    config
        .lines()
        .find_map(|l| l.trim().strip_prefix("CONFIG_HZ="))
        .and_then(|v| v.parse().ok())
        .filter(|hz| *hz > 0)
}

/// `ns` as milliseconds with µs resolution, e.g. "4 ms", "3.333 ms", "0.500 ms".
fn fmt_ms(ns: u64) -> String {
    if ns.is_multiple_of(1_000_000) {
        format!("{} ms", ns / 1_000_000)
    } else {
        format!("{:.3} ms", ns as f64 / 1e6)
    }
}

/// Processes with /dev/cpu_dma_latency open, as "pid N (name)".
fn latency_request_holders(fs: &Fs) -> Vec<String> {
    let mut v = Vec::new();
    for pid in fs.numbered("/proc").unwrap_or_default() {
        let fds = fs.list(&format!("/proc/{pid}/fd")).unwrap_or_default();
        let holds = fds.iter().any(|fd| {
            std::fs::read_link(fs.path(&format!("/proc/{pid}/fd/{fd}")))
                .is_ok_and(|t| t == Path::new(drivelab_runtime::rt::CPU_DMA_LATENCY))
        });
        if holds {
            let comm = fs.read(&format!("/proc/{pid}/comm")).unwrap_or_default();
            v.push(format!("pid {pid} ({comm})"));
        }
    }
    v
}

/// Renders the checks as an aligned table, one line per check, each check's advice on
/// indented lines below it, and a one-line summary.
pub fn render_text(checks: &[Check]) -> String {
    let name_w = checks
        .iter()
        .map(|c| c.name.chars().count())
        .chain(std::iter::once("CHECK".len()))
        .max()
        .unwrap_or(5);
    let status_w = "UNKNOWN".len();
    let indent = " ".repeat(name_w + 2 + status_w + 2);
    let mut out = String::new();
    let _ = writeln!(out, "{:<name_w$}  {:<status_w$}  VALUE", "CHECK", "STATUS");
    for c in checks {
        let value = one_line(&c.value);
        let _ = writeln!(
            out,
            "{:<name_w$}  {:<status_w$}  {}",
            c.name,
            c.status.label(),
            value
        );
        if let Some(a) = &c.advice {
            let _ = writeln!(out, "{indent}-> {}", one_line(a));
        }
    }
    let count = |s: Status| checks.iter().filter(|c| c.status == s).count();
    let _ = writeln!(
        out,
        "{} ok, {} warn, {} bad, {} unknown (advice is informational; doctor changes nothing)",
        count(Status::Ok),
        count(Status::Warn),
        count(Status::Bad),
        count(Status::Unknown)
    );
    out
}

fn one_line(s: &str) -> String {
    s.split_whitespace().collect::<Vec<_>>().join(" ")
}

// ---------------------------------------------------------------------------------------
// file access

/// Reads `path` as text, trimmed; `None` if it is missing, unreadable or not UTF-8.
pub fn read_trimmed(path: &Path) -> Option<String> {
    std::fs::read_to_string(path)
        .ok()
        .map(|s| s.trim().to_string())
}

/// A check that depends on one file: `Unknown` naming the path if it cannot be read,
/// otherwise whatever `interpret` makes of the trimmed content.
pub fn file_check(
    name: &str,
    path: &Path,
    interpret: impl FnOnce(&str) -> (Status, String, Option<String>),
) -> Check {
    match read_trimmed(path) {
        Some(text) => {
            let (status, value, advice) = interpret(&text);
            Check::new(name, value, status, advice)
        }
        None => Check::new(
            name,
            format!("unknown ({} not readable)", path.display()),
            Status::Unknown,
            None,
        ),
    }
}

/// Absolute paths resolved under a root directory.
struct Fs<'a> {
    root: &'a Path,
}

impl Fs<'_> {
    fn path(&self, abs: &str) -> PathBuf {
        self.root.join(abs.trim_start_matches('/'))
    }

    fn read(&self, abs: &str) -> Option<String> {
        read_trimmed(&self.path(abs))
    }

    /// Names of the entries of directory `abs`, sorted; `None` if it cannot be listed.
    fn list(&self, abs: &str) -> Option<Vec<String>> {
        let rd = std::fs::read_dir(self.path(abs)).ok()?;
        let mut v: Vec<String> = rd
            .filter_map(|e| e.ok())
            .filter_map(|e| e.file_name().into_string().ok())
            .collect();
        v.sort();
        Some(v)
    }

    /// The numbered entries of directory `abs` (the processes of `/proc`, the threads of
    /// `/proc/PID/task`), in [`Fs::list`]'s order; `None` if it cannot be listed.
    fn numbered(&self, abs: &str) -> Option<Vec<u32>> {
        Some(
            self.list(abs)?
                .iter()
                .filter_map(|n| n.parse().ok())
                .collect(),
        )
    }

    /// CPU numbers that have a `/sys/devices/system/cpu/cpuN` directory.
    fn cpu_dirs(&self) -> Option<Vec<usize>> {
        let mut cpus: Vec<usize> = self
            .list("/sys/devices/system/cpu")?
            .iter()
            .filter_map(|n| n.strip_prefix("cpu"))
            .filter_map(|n| n.parse().ok())
            .collect();
        cpus.sort_unstable();
        Some(cpus)
    }

    fn cmdline_param(&self, key: &str) -> Option<String> {
        let cmdline = self.read("/proc/cmdline")?;
        cmdline_param(&cmdline, key)
    }
}

/// Value of `key=value` on a kernel command line (last occurrence wins, like the kernel).
fn cmdline_param(cmdline: &str, key: &str) -> Option<String> {
    cmdline
        .split_whitespace()
        .take_while(|t| *t != "--")
        .filter_map(|t| t.split_once('='))
        .filter(|(k, _)| *k == key)
        .map(|(_, v)| v.to_string())
        .last()
}

/// Parses a kernel CPU list like `"0-3,8,10-11"`; `None` on syntax errors. Empty → empty.
pub(crate) fn parse_cpu_list(s: &str) -> Option<Vec<usize>> {
    let mut out = Vec::new();
    for part in s.trim().split(',').filter(|p| !p.is_empty()) {
        // Skip isolcpus flags ("nohz", "domain", "managed_irq") and "a-b:n/stride" groups.
        let part = part.trim();
        if part.starts_with(|c: char| c.is_ascii_alphabetic()) {
            continue;
        }
        let part = part.split(':').next().unwrap_or(part);
        if let Some((a, b)) = part.split_once('-') {
            let (a, b): (usize, usize) = (a.trim().parse().ok()?, b.trim().parse().ok()?);
            if b < a || b - a > 65_536 {
                return None;
            }
            out.extend(a..=b);
        } else {
            out.push(part.trim().parse().ok()?);
        }
    }
    out.sort_unstable();
    out.dedup();
    Some(out)
}

/// Formats CPUs compactly: `[0,1,2,3,8]` → `"0-3,8"`.
pub(crate) fn fmt_cpu_list(cpus: &[usize]) -> String {
    let mut v = cpus.to_vec();
    v.sort_unstable();
    v.dedup();
    let mut parts = Vec::new();
    let mut i = 0;
    while i < v.len() {
        let start = v[i];
        let mut end = start;
        while i + 1 < v.len() && v[i + 1] == end + 1 {
            i += 1;
            end = v[i];
        }
        parts.push(if end == start {
            start.to_string()
        } else {
            format!("{start}-{end}")
        });
        i += 1;
    }
    parts.join(",")
}

// ---------------------------------------------------------------------------------------
// live probes

struct Uname {
    release: String,
    version: String,
    /// The architecture, e.g. `x86_64`, `aarch64`, `armv7l`.
    machine: String,
}

fn uname() -> Option<Uname> {
    // SAFETY: utsname is plain C char arrays; all-zero is a valid value for the out-param.
    let mut u: libc::utsname = unsafe { std::mem::zeroed() };
    // SAFETY: `u` is a valid, writable utsname; uname only fills it in.
    if unsafe { libc::uname(&mut u) } != 0 {
        return None;
    }
    // Fields are NUL-terminated C strings; stop at the NUL (or the array's end).
    let field = |f: &[libc::c_char]| {
        let bytes: Vec<u8> = f
            .iter()
            .take_while(|&&c| c != 0)
            .map(|&c| c as u8)
            .collect();
        String::from_utf8_lossy(&bytes).into_owned()
    };
    Some(Uname {
        release: field(&u.release),
        version: field(&u.version),
        machine: field(&u.machine),
    })
}

fn euid() -> u32 {
    // SAFETY: geteuid has no preconditions and cannot fail.
    unsafe { libc::geteuid() }
}

/// Effective capabilities of this process (from `/proc/self/status`).
struct Caps {
    euid: u32,
    eff: Option<u64>,
}

const CAP_IPC_LOCK: u32 = 14;
const CAP_SYS_NICE: u32 = 23;

impl Caps {
    fn read(fs: &Fs) -> Self {
        let eff = fs.read("/proc/self/status").and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("CapEff:"))
                .and_then(|v| u64::from_str_radix(v.trim(), 16).ok())
        });
        Caps { euid: euid(), eff }
    }

    /// `Some(has)` if the capability set is known; otherwise a guess from euid 0.
    fn has(&self, cap: u32) -> Option<bool> {
        match self.eff {
            Some(e) => Some(e & (1u64 << cap) != 0),
            None if self.euid == 0 => None,
            None => Some(false),
        }
    }

    fn describe(&self, cap: u32, cap_name: &str) -> String {
        match self.has(cap) {
            Some(true) => cap_name.to_string(),
            Some(false) => format!("no {cap_name}"),
            None => format!("{cap_name} unknown"),
        }
    }
}

// ---------------------------------------------------------------------------------------
// checks

fn kernel_check(uts: Option<&Uname>) -> Check {
    match uts {
        Some(u) => Check::new(
            "kernel",
            format!("{} {} ({})", u.release, u.version, u.machine),
            Status::Ok,
            None,
        ),
        None => Check::new("kernel", "unknown (uname failed)", Status::Unknown, None),
    }
}

const RT_KERNEL_ADVICE: &str =
    "use a PREEMPT_RT kernel (CONFIG_PREEMPT_RT=y, e.g. the distribution's \
     -rt kernel package); on a PREEMPT_DYNAMIC kernel at least boot with preempt=full";

/// Preemption model from `/sys/kernel/realtime`, `/sys/kernel/debug/sched/preempt`,
/// `preempt=` on the command line and the `PREEMPT*` words of `uname -v`.
fn preemption_check(fs: &Fs, uname_version: Option<&str>, release: Option<&str>) -> Check {
    let realtime = fs.read("/sys/kernel/realtime");
    let debug_mode = fs
        .read("/sys/kernel/debug/sched/preempt")
        .and_then(|s| current_preempt_mode(&s));
    let cmdline_mode = fs.cmdline_param("preempt");
    preemption_verdict(
        realtime.as_deref(),
        debug_mode.as_deref(),
        cmdline_mode.as_deref(),
        built_preempt_mode(fs, release),
        uname_version,
    )
}

/// The preemption model the kernel was built with (`none`, `voluntary`, `full` or `lazy`),
/// from `/proc/config.gz` or else `/boot/config-<release>`: the mode a PREEMPT_DYNAMIC
/// kernel starts in when no `preempt=` on its command line says otherwise.
fn built_preempt_mode(fs: &Fs, release: Option<&str>) -> Option<&'static str> {
    config_preempt_mode(&kernel_config(fs, release)?)
}

/// The running kernel's configuration: `/proc/config.gz`, or else `/boot/config-<release>`.
fn kernel_config(fs: &Fs, release: Option<&str>) -> Option<String> {
    let gz = std::fs::File::open(fs.path("/proc/config.gz"))
        .ok()
        .and_then(|f| {
            let mut text = String::new();
            std::io::Read::read_to_string(&mut flate2::read::GzDecoder::new(f), &mut text)
                .ok()
                .map(|_| text)
        });
    gz.or_else(|| release.and_then(|r| fs.read(&format!("/boot/config-{r}"))))
}

/// The preemption model chosen in a kernel configuration's text.
fn config_preempt_mode(config: &str) -> Option<&'static str> {
    const MODES: [(&str, &str); 4] = [
        ("CONFIG_PREEMPT_NONE=y", "none"),
        ("CONFIG_PREEMPT_VOLUNTARY=y", "voluntary"),
        ("CONFIG_PREEMPT=y", "full"),
        ("CONFIG_PREEMPT_LAZY=y", "lazy"),
    ];
    config.lines().find_map(|l| {
        MODES
            .iter()
            .find(|(line, _)| l.trim() == *line)
            .map(|(_, mode)| *mode)
    })
}

/// The mode in parentheses in `/sys/kernel/debug/sched/preempt`, e.g. `"full"` from
/// `"none voluntary (full) lazy"`.
fn current_preempt_mode(s: &str) -> Option<String> {
    s.split_whitespace()
        .find(|w| w.starts_with('(') && w.ends_with(')'))
        .map(|w| w.trim_matches(|c| c == '(' || c == ')').to_string())
}

fn preemption_verdict(
    realtime: Option<&str>,
    debug_mode: Option<&str>,
    cmdline_mode: Option<&str>,
    built_mode: Option<&str>,
    uname_version: Option<&str>,
) -> Check {
    const NAME: &str = "preemption";
    let words: Vec<&str> = uname_version
        .map(|v| v.split_whitespace().collect())
        .unwrap_or_default();
    let has = |w: &str| words.contains(&w);

    if realtime == Some("1") || has("PREEMPT_RT") {
        return Check::new(NAME, "PREEMPT_RT", Status::Ok, None);
    }
    let advice = Some(RT_KERNEL_ADVICE.to_string());
    let dynamic = has("PREEMPT_DYNAMIC");
    let mode_verdict = |mode: &str, source: &str| {
        let status = match mode {
            "full" | "lazy" => Status::Warn,
            "none" | "voluntary" => Status::Bad,
            _ => Status::Unknown,
        };
        let prefix = if dynamic { "PREEMPT_DYNAMIC, " } else { "" };
        // Without preemption of kernel code, a real-time task that wakes while any task on
        // its CPU is inside a system call waits until that call returns.
        let effect = if status == Status::Bad {
            ": a task's system call on a drive's core holds up the drive's wake-up until it returns"
        } else {
            ""
        };
        Check::new(
            NAME,
            format!("{prefix}mode {mode} ({source}){effect}; not PREEMPT_RT"),
            status,
            advice.clone(),
        )
    };
    if let Some(mode) = debug_mode {
        return mode_verdict(mode, "debugfs sched/preempt");
    }
    if dynamic {
        if let Some(mode) = cmdline_mode {
            return mode_verdict(mode, "preempt= on /proc/cmdline");
        }
        if let Some(mode) = built_mode {
            return mode_verdict(
                mode,
                "the kernel's built-in default, no preempt= on the command line",
            );
        }
        return Check::new(
            NAME,
            "PREEMPT_DYNAMIC, current mode unknown (debugfs sched/preempt not readable, \
             no preempt= on the command line); not PREEMPT_RT",
            Status::Warn,
            advice,
        );
    }
    if has("PREEMPT") {
        return Check::new(
            NAME,
            "PREEMPT (full preemption); not PREEMPT_RT",
            Status::Warn,
            advice,
        );
    }
    if uname_version.is_some() {
        return Check::new(
            NAME,
            "no PREEMPT in uname -v: voluntary or no kernel preemption",
            Status::Bad,
            advice,
        );
    }
    Check::new(
        NAME,
        "unknown (uname and /sys/kernel/realtime unavailable)",
        Status::Unknown,
        None,
    )
}

fn rt_throttling_check(fs: &Fs) -> Check {
    const NAME: &str = "rt throttling";
    let runtime = fs
        .read("/proc/sys/kernel/sched_rt_runtime_us")
        .and_then(|s| s.parse::<i64>().ok());
    let period = fs
        .read("/proc/sys/kernel/sched_rt_period_us")
        .and_then(|s| s.parse::<i64>().ok());
    rt_throttling_verdict(runtime, period, NAME)
}

fn rt_throttling_verdict(runtime: Option<i64>, period: Option<i64>, name: &str) -> Check {
    match (runtime, period) {
        (Some(-1), _) => Check::new(
            name,
            "disabled (sched_rt_runtime_us = -1): SCHED_FIFO tasks are never throttled \
             (a runaway FIFO loop can monopolise its CPU)",
            Status::Ok,
            None,
        ),
        (Some(rt), Some(p)) if p > 0 && rt >= p => Check::new(
            name,
            format!("{rt}/{p} us: RT tasks may use the whole period (not throttled)"),
            Status::Ok,
            None,
        ),
        (Some(rt), Some(p)) if p > 0 && rt >= 0 => {
            let idle_ms = (p - rt) as f64 / 1000.0;
            let period_ms = p as f64 / 1000.0;
            let pct = 100.0 * rt as f64 / p as f64;
            Check::new(
                name,
                format!(
                    "{rt}/{p} us: real-time tasks get at most {pct:.1}% of each CPU; a SCHED_FIFO \
                     task that spins without sleeping is stopped ~{idle_ms:.0} ms in every \
                     {period_ms:.0} ms"
                ),
                Status::Warn,
                Some(format!(
                    "loops that sleep every period (clock_nanosleep) are not affected; for a \
                     busy-polling FIFO loop disable throttling with \
                     sysctl kernel.sched_rt_runtime_us=-1 (then keep a watchdog: a runaway \
                     FIFO task would freeze its CPU), or raise it towards {p}"
                )),
            )
        }
        (Some(rt), Some(p)) => Check::new(
            name,
            format!("unexpected values {rt}/{p} us"),
            Status::Unknown,
            None,
        ),
        _ => Check::new(
            name,
            "unknown (/proc/sys/kernel/sched_rt_runtime_us or sched_rt_period_us not readable)",
            Status::Unknown,
            None,
        ),
    }
}

/// Online CPUs from `/sys/devices/system/cpu/online`, else `0..online_cpus()`.
fn online_cpu_list(fs: &Fs) -> Vec<usize> {
    fs.read("/sys/devices/system/cpu/online")
        .and_then(|s| parse_cpu_list(&s))
        .filter(|v| !v.is_empty())
        .unwrap_or_else(|| (0..rt::online_cpus()).collect())
}

fn online_cpus_check(online: &[usize]) -> Check {
    let n = online.len();
    let value = format!("{n} online ({})", fmt_cpu_list(online));
    if n >= 2 {
        Check::new("online cpus", value, Status::Ok, None)
    } else {
        Check::new(
            "online cpus",
            value,
            Status::Warn,
            Some(
                "all services and the OS share one CPU; give the machine/VM at least 2 CPUs \
                 (one for housekeeping, the rest for pinned real-time loops)"
                    .into(),
            ),
        )
    }
}

/// The isolated CPUs: `/sys/devices/system/cpu/isolated`, else `isolcpus=` of the command
/// line; empty when neither names any.
fn isolated_list(fs: &Fs) -> Vec<usize> {
    fs.read("/sys/devices/system/cpu/isolated")
        .as_deref()
        .and_then(parse_cpu_list)
        .or_else(|| {
            fs.cmdline_param("isolcpus")
                .as_deref()
                .and_then(parse_cpu_list)
        })
        .unwrap_or_default()
}

/// The CPUs a drive runs on by default: the isolated ones, else every online CPU but the
/// first (drivelab's default placement puts the stages on core 1 and leaves core 0 to the
/// OS, the supervisor and the recorder).
fn drive_cpus(fs: &Fs, online: &[usize]) -> Vec<usize> {
    let isolated = isolated_list(fs);
    if isolated.is_empty() {
        online.iter().skip(1).copied().collect()
    } else {
        isolated
    }
}

/// The drive's CPUs for a check's line: `-` when there are none.
fn drive_cpu_text(drive: &[usize]) -> String {
    if drive.is_empty() {
        "-".into()
    } else {
        fmt_cpu_list(drive)
    }
}

/// The first five of `items`, comma-separated, then how many more there are.
fn first_five(items: &[String]) -> String {
    let mut s = items[..items.len().min(5)].join(", ");
    if items.len() > 5 {
        let _ = write!(s, " and {} more", items.len() - 5);
    }
    s
}

/// One device interrupt line of `/proc/interrupts`.
#[derive(Debug, Clone, PartialEq)]
struct DeviceIrq {
    irq: u32,
    /// The device's name (the line's last field).
    name: String,
    /// Interrupts served since boot, all CPUs.
    count: u64,
    /// The CPUs that serve it now (`effective_affinity_list`, else `smp_affinity_list`).
    cpus: Vec<usize>,
}

/// The numbered (device) lines of `/proc/interrupts` that fired at least once, most first.
/// The per-CPU architecture lines (LOC, RES, ...) are the CPUs' own, and so is a numbered
/// line that fired on every CPU.
fn device_irqs(fs: &Fs) -> Option<Vec<DeviceIrq>> {
    let text = fs.read("/proc/interrupts")?;
    let mut lines = text.lines();
    let n_cpus = lines.next()?.split_whitespace().count();
    let mut v = Vec::new();
    for l in lines {
        let mut f = l.split_whitespace();
        let Some(irq) = f
            .next()
            .and_then(|t| t.strip_suffix(':')?.parse::<u32>().ok())
        else {
            continue;
        };
        let fields: Vec<&str> = f.collect();
        if fields.len() <= n_cpus {
            continue;
        }
        let counts: Vec<u64> = fields[..n_cpus]
            .iter()
            .map(|c| c.parse::<u64>().unwrap_or(0))
            .collect();
        let count: u64 = counts.iter().sum();
        // Never fired; or fired on every CPU: a per-CPU line (an ARM board's architected
        // timer or PMU is numbered like a device), each CPU's own, nothing to steer.
        if count == 0 || (n_cpus > 1 && counts.iter().all(|&c| c > 0)) {
            continue;
        }
        let cpus = ["effective_affinity_list", "smp_affinity_list"]
            .iter()
            .find_map(|f| {
                fs.read(&format!("/proc/irq/{irq}/{f}"))
                    .as_deref()
                    .and_then(parse_cpu_list)
            })
            .unwrap_or_default();
        v.push(DeviceIrq {
            irq,
            name: fields[fields.len() - 1].to_string(),
            count,
            cpus,
        });
    }
    v.sort_by(|a, b| b.count.cmp(&a.count).then(a.irq.cmp(&b.irq)));
    Some(v)
}

/// Device interrupts served by the CPUs a drive runs on: each interrupt, and the softirq and
/// kernel-thread work it starts, runs ahead of the drive's tasks on that CPU.
#[cfg(test)]
fn device_irq_check(fs: &Fs, online: &[usize]) -> Check {
    device_irq_check_on(fs, &drive_cpus(fs, online))
}

/// [`device_irq_check`] for the drive's CPUs `drive`.
fn device_irq_check_on(fs: &Fs, drive: &[usize]) -> Check {
    const NAME: &str = "device irqs";
    let Some(irqs) = device_irqs(fs) else {
        return Check::new(NAME, "/proc/interrupts not readable", Status::Unknown, None);
    };
    let on_drive: Vec<&DeviceIrq> = irqs
        .iter()
        .filter(|d| d.cpus.iter().any(|c| drive.contains(c)))
        .collect();
    let drive_list = drive_cpu_text(drive);
    if on_drive.is_empty() {
        return Check::new(
            NAME,
            format!(
                "{} device interrupt line(s), none served by the drive's cpu {}",
                irqs.len(),
                drive_list
            ),
            Status::Ok,
            None,
        );
    }
    let names: Vec<String> = on_drive
        .iter()
        .map(|d| {
            format!(
                "{} (irq {}, {} since boot, cpu {})",
                d.name,
                d.irq,
                d.count,
                fmt_cpu_list(&d.cpus)
            )
        })
        .collect();
    Check::new(
        NAME,
        format!(
            "{} of {} device interrupt line(s) served by the drive's cpu {drive_list}: {}",
            on_drive.len(),
            irqs.len(),
            first_five(&names)
        ),
        Status::Warn,
        Some(
            "each of these interrupts, and the softirq and kernel-thread work it starts, runs \
             ahead of the drive on its cpu; route them to the OS's cpu (boot with irqaffinity=0, \
             or as root write 0 to /proc/irq/N/smp_affinity_list; drivelab changes nothing)"
                .into(),
        ),
    )
}

fn isolated_cpus_check(fs: &Fs, online: &[usize]) -> Check {
    const NAME: &str = "isolated cpus";
    let isolated_file = fs.read("/sys/devices/system/cpu/isolated");
    let nohz_file = fs.read("/sys/devices/system/cpu/nohz_full");
    let cmdline = fs.read("/proc/cmdline");
    if isolated_file.is_none() && cmdline.is_none() {
        return Check::new(
            NAME,
            "unknown (/sys/devices/system/cpu/isolated and /proc/cmdline not readable)",
            Status::Unknown,
            None,
        );
    }
    let param = |k: &str| cmdline.as_deref().and_then(|c| cmdline_param(c, k));
    let isolated = isolated_list(fs);
    let nohz = nohz_file
        .as_deref()
        .filter(|s| !s.is_empty() && *s != "(null)")
        .map(str::to_string)
        .or_else(|| param("nohz_full"));
    let rcu = param("rcu_nocbs");
    let show = |o: &Option<String>| o.clone().unwrap_or_else(|| "-".into());
    let value = format!(
        "isolated: {}; nohz_full: {}; rcu_nocbs: {}",
        if isolated.is_empty() {
            "none".to_string()
        } else {
            fmt_cpu_list(&isolated)
        },
        show(&nohz),
        show(&rcu)
    );
    // Suggest everything but the first online CPU (kept for housekeeping).
    let suggest = if online.len() >= 2 {
        fmt_cpu_list(&online[1..])
    } else {
        String::new()
    };
    if !isolated.is_empty() {
        let advice = if nohz.is_none() || rcu.is_none() {
            let l = fmt_cpu_list(&isolated);
            Some(format!(
                "also boot with nohz_full={l} rcu_nocbs={l} so the tick and RCU callbacks \
                 leave the isolated CPUs"
            ))
        } else {
            None
        };
        return Check::new(NAME, value, Status::Ok, advice);
    }
    let advice = if suggest.is_empty() {
        "only one CPU: isolation is impossible; add CPUs".to_string()
    } else {
        format!(
            "boot with isolcpus={suggest} nohz_full={suggest} rcu_nocbs={suggest} \
             (irqaffinity=0) and pin the drive loops to those CPUs"
        )
    };
    Check::new(NAME, value, Status::Warn, Some(advice))
}

/// [`isolated_cpus_check`] for a topology that pins its processes to `cpus`: OK when every one
/// of them is isolated (with the same nohz_full/rcu_nocbs advice), else which are not, and
/// the boot parameters that would isolate them.
fn isolated_cpus_check_for(fs: &Fs, online: &[usize], cpus: &[usize]) -> Check {
    let c = isolated_cpus_check(fs, online);
    if c.status == Status::Unknown || cpus.is_empty() {
        return c;
    }
    let isolated = isolated_list(fs);
    let not: Vec<usize> = cpus
        .iter()
        .copied()
        .filter(|x| !isolated.contains(x))
        .collect();
    if not.is_empty() {
        return Check::new(&c.name, c.value, Status::Ok, c.advice);
    }
    let l = fmt_cpu_list(cpus);
    let advice = if not.contains(&online.first().copied().unwrap_or(0)) {
        format!(
            "the topology pins a process to cpu {}, the OS's first cpu, which cannot be isolated; move it to another",
            online.first().copied().unwrap_or(0)
        )
    } else {
        format!(
            "boot with isolcpus={l} nohz_full={l} rcu_nocbs={l} (irqaffinity=0) so that the topology's cpus are the drive's alone"
        )
    };
    Check::new(
        &c.name,
        format!(
            "{}; the topology's cpu {} not isolated",
            c.value,
            fmt_cpu_list(&not)
        ),
        Status::Warn,
        Some(advice),
    )
}

const GOVERNOR_ADVICE: &str = "set governor to performance: cpupower frequency-set -g performance \
     (or write performance to /sys/devices/system/cpu/cpu*/cpufreq/scaling_governor)";

fn governor_check(fs: &Fs) -> Check {
    const NAME: &str = "governor";
    let Some(cpus) = fs.cpu_dirs() else {
        return Check::new(
            NAME,
            "unknown (/sys/devices/system/cpu not readable)",
            Status::Unknown,
            None,
        );
    };
    let mut by_gov: BTreeMap<String, Vec<usize>> = BTreeMap::new();
    let mut missing = Vec::new();
    for c in &cpus {
        match fs.read(&format!(
            "/sys/devices/system/cpu/cpu{c}/cpufreq/scaling_governor"
        )) {
            Some(g) if !g.is_empty() => by_gov.entry(g).or_default().push(*c),
            _ => missing.push(*c),
        }
    }
    if by_gov.is_empty() {
        return Check::new(NAME, "no cpufreq (VM?)", Status::Unknown, None);
    }
    let mut parts: Vec<String> = by_gov
        .iter()
        .map(|(g, cs)| format!("{g}: cpu {}", fmt_cpu_list(cs)))
        .collect();
    if !missing.is_empty() {
        parts.push(format!("no cpufreq: cpu {}", fmt_cpu_list(&missing)));
    }
    let value = parts.join("; ");
    if by_gov.keys().all(|g| g == "performance") {
        Check::new(NAME, value, Status::Ok, None)
    } else {
        Check::new(NAME, value, Status::Warn, Some(GOVERNOR_ADVICE.into()))
    }
}

/// The frequency limits of each cpufreq policy (a cluster of CPUs that share a clock, e.g.
/// the little and the big cores of an ARM board): a loop's execution time follows the
/// clock, so a frequency that may move between `scaling_min_freq` and `scaling_max_freq`
/// moves it, and a `scaling_max_freq` below `cpuinfo_max_freq` caps it.
fn cpufreq_limits_check(fs: &Fs) -> Check {
    const NAME: &str = "cpufreq limits";
    const DIR: &str = "/sys/devices/system/cpu/cpufreq";
    let policies: Vec<String> = fs
        .list(DIR)
        .unwrap_or_default()
        .into_iter()
        .filter(|p| p.starts_with("policy"))
        .collect();
    let khz =
        |p: &str, f: &str| -> Option<u64> { fs.read(&format!("{DIR}/{p}/{f}"))?.parse().ok() };
    let mhz = |k: u64| format!("{}", k / 1000);
    let mut parts = Vec::new();
    let mut moves = false;
    let mut capped = false;
    for p in &policies {
        let cpus = fs
            .read(&format!("{DIR}/{p}/affected_cpus"))
            .and_then(|s| parse_cpu_list(&s.replace(' ', ",")))
            .map(|c| fmt_cpu_list(&c))
            .unwrap_or_else(|| "?".into());
        let (Some(lo), Some(hi)) = (khz(p, "scaling_min_freq"), khz(p, "scaling_max_freq")) else {
            parts.push(format!("cpu {cpus}: limits not readable"));
            continue;
        };
        let hw = khz(p, "cpuinfo_max_freq");
        moves |= lo < hi;
        capped |= hw.is_some_and(|h| hi < h);
        parts.push(format!(
            "cpu {cpus}: {}-{} MHz{}",
            mhz(lo),
            mhz(hi),
            hw.map(|h| format!(
                " of {}-{} MHz",
                khz(p, "cpuinfo_min_freq").map_or("?".into(), mhz),
                mhz(h)
            ))
            .unwrap_or_default()
        ));
    }
    if parts.is_empty() {
        return Check::new(
            NAME,
            "no cpufreq policy (a VM, or the firmware sets the clock)",
            Status::Unknown,
            None,
        );
    }
    let value = parts.join("; ");
    if !moves && !capped {
        return Check::new(NAME, format!("{value}: fixed"), Status::Ok, None);
    }
    let mut advice = Vec::new();
    if moves {
        advice.push(
            "fix each real-time cluster's clock: write its cpuinfo_max_freq to scaling_min_freq              (or use the performance governor), so execution times do not follow the load",
        );
    }
    if capped {
        advice.push(
            "scaling_max_freq is below the hardware's maximum (a thermal or power limit?): the              loops run slower than the CPU can",
        );
    }
    Check::new(NAME, value, Status::Warn, Some(advice.join("; ")))
}

fn smt_check(fs: &Fs) -> Check {
    const NAME: &str = "smt";
    let control = fs.read("/sys/devices/system/cpu/smt/control");
    let active = fs.read("/sys/devices/system/cpu/smt/active");
    let mut groups: Vec<Vec<usize>> = Vec::new();
    for c in fs.cpu_dirs().unwrap_or_default() {
        if let Some(g) = fs
            .read(&format!(
                "/sys/devices/system/cpu/cpu{c}/topology/thread_siblings_list"
            ))
            .and_then(|s| parse_cpu_list(&s))
        {
            if g.len() > 1 && !groups.contains(&g) {
                groups.push(g);
            }
        }
    }
    if control.is_none() && active.is_none() && groups.is_empty() {
        // ARM cores have one thread each; their kernels may have no smt directory at all.
        let topology_read = fs.cpu_dirs().unwrap_or_default().iter().any(|c| {
            fs.read(&format!(
                "/sys/devices/system/cpu/cpu{c}/topology/thread_siblings_list"
            ))
            .is_some()
        });
        if topology_read {
            return Check::new(NAME, "no sibling threads (one per core)", Status::Ok, None);
        }
        return Check::new(
            NAME,
            "unknown (/sys/devices/system/cpu/smt not readable)",
            Status::Unknown,
            None,
        );
    }
    let mut value = format!(
        "control {}, active {}",
        control.as_deref().unwrap_or("-"),
        active.as_deref().unwrap_or("-")
    );
    if groups.is_empty() {
        value.push_str("; no sibling threads");
    } else {
        let g: Vec<String> = groups.iter().map(|g| fmt_cpu_list(g)).collect();
        value.push_str(&format!("; siblings {}", g.join(" ")));
    }
    if active.as_deref() == Some("1") || !groups.is_empty() {
        Check::new(
            NAME,
            value,
            Status::Warn,
            Some(
                "hyperthread siblings share a core's execution units: keep the sibling of each \
                 real-time CPU idle (isolate both threads of the core) or boot with nosmt"
                    .into(),
            ),
        )
    } else {
        Check::new(NAME, value, Status::Ok, None)
    }
}

fn irqbalance_check(fs: &Fs) -> Check {
    const NAME: &str = "irqbalance";
    let Some(pids) = fs.numbered("/proc") else {
        return Check::new(NAME, "unknown (/proc not readable)", Status::Unknown, None);
    };
    if pids.is_empty() {
        return Check::new(
            NAME,
            "unknown (no processes in /proc)",
            Status::Unknown,
            None,
        );
    }
    let running: Vec<String> = pids
        .iter()
        .filter(|pid| fs.read(&format!("/proc/{pid}/comm")).as_deref() == Some("irqbalance"))
        .map(u32::to_string)
        .collect();
    if running.is_empty() {
        Check::new(NAME, "not running", Status::Ok, None)
    } else {
        Check::new(
            NAME,
            format!("running (pid {})", running.join(", ")),
            Status::Warn,
            Some(
                "irqbalance may move device interrupts onto the real-time CPUs: stop it \
                 (systemctl stop irqbalance) or ban those CPUs (IRQBALANCE_BANNED_CPULIST), \
                 and boot with irqaffinity=0"
                    .into(),
            ),
        )
    }
}

/// Tries `SCHED_FIFO` priority 1 in a throw-away thread, switching straight back to
/// `SCHED_OTHER`. `Ok(())` if allowed, else the error.
fn probe_sched_fifo() -> io::Result<()> {
    std::thread::Builder::new()
        .name("doctor-fifo-probe".into())
        .spawn(|| -> io::Result<()> {
            rt::set_scheduler(libc::SCHED_FIFO, 1)?;
            // Back to normal at once; the thread ends right after anyway.
            let _ = rt::set_scheduler(libc::SCHED_OTHER, 0);
            Ok(())
        })
        .map_err(|e| io::Error::other(format!("cannot spawn probe thread: {e}")))?
        .join()
        .unwrap_or_else(|_| Err(io::Error::other("probe thread panicked")))
}

fn sched_fifo_check(caps: &Caps) -> Check {
    const NAME: &str = "sched_fifo privilege";
    let (soft, hard) = rt::get_rlimit(libc::RLIMIT_RTPRIO);
    let who = format!(
        "euid {}, {}, RLIMIT_RTPRIO {}/{}",
        caps.euid,
        caps.describe(CAP_SYS_NICE, "CAP_SYS_NICE"),
        rt::fmt_rlimit_count(soft),
        rt::fmt_rlimit_count(hard)
    );
    match probe_sched_fifo() {
        Ok(()) => {
            let privileged = caps.euid == 0 || caps.has(CAP_SYS_NICE) == Some(true);
            if !privileged && soft != libc::RLIM_INFINITY && soft < 99 {
                Check::new(
                    NAME,
                    format!("allowed up to priority {soft} ({who})"),
                    Status::Ok,
                    None,
                )
            } else {
                Check::new(NAME, format!("allowed ({who})"), Status::Ok, None)
            }
        }
        Err(e) => {
            let root_hint = if caps.euid == 0 {
                "; as root this usually means a container without CAP_SYS_NICE or a cgroup \
                 with cpu.rt_runtime_us = 0"
            } else {
                ""
            };
            Check::new(
                NAME,
                format!("refused: {} ({who})", rt::os_error_text(&e)),
                Status::Bad,
                Some(format!(
                    "run as root, or grant CAP_SYS_NICE (setcap cap_sys_nice+ep <binary>, or \
                     AmbientCapabilities=CAP_SYS_NICE in a systemd unit), or raise \
                     RLIMIT_RTPRIO (LimitRTPRIO=99, or '@realtime - rtprio 99' in \
                     /etc/security/limits.conf){root_hint}"
                )),
            )
        }
    }
}

fn mlock_check(caps: &Caps) -> Check {
    let (soft, hard) = rt::get_rlimit(libc::RLIMIT_MEMLOCK);
    mlock_verdict(caps, soft, hard)
}

/// The memory lock a stage host gets with these capabilities and this `RLIMIT_MEMLOCK`
/// (soft, hard): a host locks up to about [`rt::HOST_LOCKED_BYTES`] once its bus is open.
fn mlock_verdict(caps: &Caps, soft: libc::rlim_t, hard: libc::rlim_t) -> Check {
    const NAME: &str = "mlock";
    let limit = format!(
        "RLIMIT_MEMLOCK {}/{}",
        rt::fmt_rlimit_bytes(soft),
        rt::fmt_rlimit_bytes(hard)
    );
    let cap = caps.has(CAP_IPC_LOCK);
    if cap == Some(true) || (cap.is_none() && caps.euid == 0) {
        let who = if caps.euid == 0 {
            "root"
        } else {
            "CAP_IPC_LOCK"
        };
        return Check::new(
            NAME,
            format!("unlimited ({who}; {limit})"),
            Status::Ok,
            None,
        );
    }
    if soft == libc::RLIM_INFINITY {
        return Check::new(NAME, format!("unlimited ({limit})"), Status::Ok, None);
    }
    let host_mib = rt::HOST_LOCKED_BYTES >> 20;
    if soft >= rt::HOST_LOCKED_BYTES as libc::rlim_t {
        return Check::new(
            NAME,
            format!(
                "{limit} (euid {}, no CAP_IPC_LOCK): enough for a stage host of the default \
                 drive, which locks up to about {host_mib} MiB once its bus is open",
                caps.euid
            ),
            Status::Ok,
            None,
        );
    }
    Check::new(
        NAME,
        format!(
            "{limit} (euid {}, no CAP_IPC_LOCK): below the about {host_mib} MiB a stage host \
             locks once its bus is open: the hosts run with memory not locked (page faults in \
             the loop) and --rt-strict refuses to start",
            caps.euid
        ),
        Status::Warn,
        Some(
            "raise the limit (ulimit -l unlimited, LimitMEMLOCK=infinity in a systemd unit, \
             '@realtime - memlock unlimited' in /etc/security/limits.conf) or grant CAP_IPC_LOCK"
                .into(),
        ),
    )
}

fn timer_slack_check(fs: &Fs) -> Check {
    file_check(
        "timer slack",
        &fs.path("/proc/self/timerslack_ns"),
        |s| match s.parse::<u64>() {
            Ok(ns) if ns <= 1_000 => (Status::Ok, format!("{ns} ns"), None),
            Ok(ns) => (
                Status::Warn,
                format!(
                    "{ns} ns: SCHED_OTHER sleeps may wake up to {:.0} us late (SCHED_FIFO \
                     ignores slack)",
                    ns as f64 / 1000.0
                ),
                Some(
                    "run the loops at SCHED_FIFO, or lower the slack with \
                     prctl(PR_SET_TIMERSLACK, 1) in the service"
                        .into(),
                ),
            ),
            Err(_) => (Status::Unknown, format!("unparsable: {s}"), None),
        },
    )
}

fn clocksource_check(fs: &Fs) -> Check {
    file_check(
        "clocksource",
        &fs.path("/sys/devices/system/clocksource/clocksource0/current_clocksource"),
        |s| match s {
            "tsc" | "kvm-clock" | "arch_sys_counter" | "hyperv_clocksource_tsc_page" => {
                (Status::Ok, s.to_string(), None)
            }
            "hpet" | "acpi_pm" | "jiffies" | "refined-jiffies" | "xen" => (
                Status::Warn,
                format!("{s}: slow clock reads (clock_gettime may enter the kernel)"),
                Some(
                    "use a clock read without entering the kernel: on x86 find out why the TSC is \
                     not used (dmesg | grep -i tsc); on ARM the architected timer \
                     (arch_sys_counter) should be the clocksource"
                        .into(),
                ),
            ),
            other => (Status::Ok, other.to_string(), None),
        },
    )
}

/// Whether a switch between two processes on a CPU keeps their TLB entries. x86 tags them
/// with a process-context ID when the CPU offers one (`pcid` in `/proc/cpuinfo`, which the
/// kernel clears when it does not use it); without it every switch to another address space
/// drops the user entries, and a stage woken in another process walks the page tables again
/// for every page it touches (docs/architecture.md, "Where the microseconds go"). ARM cores
/// tag them with address-space IDs.
fn address_space_check(fs: &Fs) -> Check {
    const NAME: &str = "address spaces";
    let Some(cpuinfo) = fs.read("/proc/cpuinfo") else {
        return Check::new(
            NAME,
            "unknown (/proc/cpuinfo not readable)",
            Status::Unknown,
            None,
        );
    };
    let field = |key: &str| {
        cpuinfo.lines().find_map(|l| {
            let (k, v) = l.split_once(':')?;
            (k.trim() == key).then(|| v.split_whitespace().collect::<Vec<_>>())
        })
    };
    if let Some(flags) = field("flags") {
        let vm = if flags.contains(&"hypervisor") {
            " (a VM: each walk also goes through the host's tables)"
        } else {
            ""
        };
        if flags.contains(&"pcid") {
            return Check::new(
                NAME,
                "PCID: a switch between processes keeps each one's TLB entries",
                Status::Ok,
                None,
            );
        }
        return Check::new(
            NAME,
            format!(
                "no PCID: every switch between two processes on a cpu empties the TLB of user \
                 pages{vm}"
            ),
            Status::Warn,
            Some(
                "a stage woken in another process walks the page tables again for every page \
                 it touches (bench/c/tlb_after_switch.c measures what a page costs here); fewer \
                 of the drive's processes on a cpu mean fewer such switches: the two-process \
                 and one-process topologies (drivelab run --topology)"
                    .into(),
            ),
        );
    }
    if field("Features").is_some() || field("CPU architecture").is_some() {
        return Check::new(
            NAME,
            "ARM address-space IDs: a switch between processes keeps each one's TLB entries",
            Status::Ok,
            None,
        );
    }
    Check::new(
        NAME,
        "unknown (no x86 flags or ARM features in /proc/cpuinfo)",
        Status::Unknown,
        None,
    )
}

/// How long [`other_load_check`] watches the machine.
const BUSY_WINDOW: std::time::Duration = std::time::Duration::from_millis(300);

/// A task that used more than this share of one CPU over the window is reported.
const BUSY_PERMILLE: u64 = 5;

/// One task (a thread of a process, or a kernel thread) as read from `/proc/PID/task/TID`.
#[derive(Debug, Clone, PartialEq)]
struct TaskSample {
    pid: u32,
    tid: u32,
    comm: String,
    /// The process's name (its main thread's).
    process: String,
    /// Time on a CPU so far (`schedstat`, ns).
    cpu_ns: u64,
    /// Times it was put on a CPU so far (`schedstat`).
    runs: u64,
    /// Clock ticks it ran in user mode and in the kernel (`stat`: utime, stime).
    user_ticks: u64,
    system_ticks: u64,
    /// A kernel thread (`PF_KTHREAD`).
    kthread: bool,
    /// User space may change its CPUs (no `PF_NO_SETAFFINITY`).
    movable: bool,
    /// The CPUs it may run on (`Cpus_allowed_list`).
    allowed: String,
}

impl TaskSample {
    /// Its time in the kernel per run on average since it started, ns: all of its time for
    /// a kernel thread, the system share of it (stime over utime + stime) for a user task.
    fn kernel_ns_per_run(&self) -> u64 {
        let ticks = self.user_ticks + self.system_ticks;
        let share = if self.kthread {
            1.0
        } else if ticks == 0 {
            0.0
        } else {
            self.system_ticks as f64 / ticks as f64
        };
        (self.cpu_ns as f64 * share / self.runs.max(1) as f64) as u64
    }
}

/// The name and the fields after it of a `/proc/.../stat` line ("pid (comm) state ppid pgrp
/// session tty tpgid flags ..."): the name may hold spaces and parentheses, so the fields
/// are counted after the last ')'. Field 0 is the state, field 6 the flags.
fn stat_fields(stat: &str) -> Option<(&str, Vec<&str>)> {
    let (open, close) = (stat.find('(')?, stat.rfind(')')?);
    let name = stat.get(open + 1..close)?;
    Some((name, stat[close + 1..].split_whitespace().collect()))
}

/// `PF_KTHREAD` in a task's flags: a kernel thread.
const PF_KTHREAD: u64 = 0x0020_0000;
/// `PF_NO_SETAFFINITY`: a kernel thread whose CPUs user space cannot change (per-CPU threads,
/// workqueue workers).
const PF_NO_SETAFFINITY: u64 = 0x0400_0000;

/// The `Cpus_allowed_list` of the task whose `/proc` directory is `dir`.
fn allowed_cpus(fs: &Fs, dir: &str) -> Option<String> {
    fs.read(&format!("{dir}/status"))?
        .lines()
        .find_map(|l| l.strip_prefix("Cpus_allowed_list:"))
        .map(|l| l.trim().to_string())
}

/// Every thread of every process but `skip_pid`, kernel threads included.
fn task_samples(fs: &Fs, skip_pid: u32) -> Vec<TaskSample> {
    let mut v = Vec::new();
    for pid in fs.numbered("/proc").unwrap_or_default() {
        if pid == skip_pid {
            continue;
        }
        let process = fs.read(&format!("/proc/{pid}/comm")).unwrap_or_default();
        for tid in fs
            .numbered(&format!("/proc/{pid}/task"))
            .unwrap_or_default()
        {
            let dir = format!("/proc/{pid}/task/{tid}");
            let Some(stat) = fs.read(&format!("{dir}/stat")) else {
                continue;
            };
            let Some((comm, fields)) = stat_fields(&stat) else {
                continue;
            };
            let field = |i: usize| fields.get(i).and_then(|f| f.parse::<u64>().ok());
            let Some(flags) = field(6) else {
                continue;
            };
            let sched: Vec<u64> = fs
                .read(&format!("{dir}/schedstat"))
                .map(|s| {
                    s.split_whitespace()
                        .filter_map(|f| f.parse().ok())
                        .collect()
                })
                .unwrap_or_default();
            let Some(&cpu_ns) = sched.first() else {
                continue;
            };
            v.push(TaskSample {
                pid,
                tid,
                comm: comm.to_string(),
                process: process.clone(),
                cpu_ns,
                runs: sched.get(2).copied().unwrap_or(0),
                user_ticks: field(11).unwrap_or(0),
                system_ticks: field(12).unwrap_or(0),
                kthread: flags & PF_KTHREAD != 0,
                movable: flags & PF_NO_SETAFFINITY == 0,
                allowed: allowed_cpus(fs, &dir).unwrap_or_else(|| "?".into()),
            });
        }
    }
    v
}

/// The tasks of `after` that used more than [`BUSY_PERMILLE`] of a CPU since `before`
/// (`window_ns` apart), busiest first, with their share in per mille. A thread that started
/// during the window counts from zero.
fn busy_tasks(
    before: &[TaskSample],
    after: &[TaskSample],
    window_ns: u64,
) -> Vec<(TaskSample, u64)> {
    let was: BTreeMap<(u32, u32), u64> =
        before.iter().map(|t| ((t.pid, t.tid), t.cpu_ns)).collect();
    let mut v: Vec<(TaskSample, u64)> = after
        .iter()
        .filter_map(|t| {
            let used = t
                .cpu_ns
                .saturating_sub(was.get(&(t.pid, t.tid)).copied().unwrap_or(0));
            let permille = used.saturating_mul(1000) / window_ns.max(1);
            (permille > BUSY_PERMILLE).then(|| (t.clone(), permille))
        })
        .collect();
    v.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.tid.cmp(&b.0.tid)));
    v
}

/// Other user-space tasks that used CPU time while doctor watched for `window`: each can
/// take a drive's core, and on a kernel without full preemption its system calls hold up
/// the drive's wake-ups until they return. A running drive's own tasks are counted apart.
fn other_load_check(fs: &Fs, window: std::time::Duration) -> Check {
    const NAME: &str = "other load";
    let me = std::process::id();
    let user_space = |mut v: Vec<TaskSample>| {
        v.retain(|t| !t.kthread);
        v
    };
    let before = user_space(task_samples(fs, me));
    let started = std::time::Instant::now();
    std::thread::sleep(window);
    let after = user_space(task_samples(fs, me));
    if after.is_empty() {
        return Check::new(NAME, "no /proc task could be read", Status::Unknown, None);
    }
    let window_ns = started.elapsed().as_nanos().min(u128::from(u64::MAX)) as u64;
    load_verdict(busy_tasks(&before, &after, window_ns), window.as_millis())
}

/// The "other load" line for the busy tasks seen in `ms` milliseconds.
fn load_verdict(busy: Vec<(TaskSample, u64)>, ms: u128) -> Check {
    const NAME: &str = "other load";
    let (drive, other): (Vec<_>, Vec<_>) = busy
        .into_iter()
        .partition(|(t, _)| t.process.starts_with("drivelab"));
    let list = |v: &[(TaskSample, u64)]| {
        let named: Vec<String> = v
            .iter()
            .map(|(t, pm)| {
                let thread = if t.tid == t.pid {
                    String::new()
                } else {
                    format!(" thread {}", t.tid)
                };
                format!(
                    "{} (pid {}{thread}, {}.{} % of a CPU, cpus {})",
                    t.comm,
                    t.pid,
                    pm / 10,
                    pm % 10,
                    t.allowed
                )
            })
            .collect();
        first_five(&named)
    };
    let drive_note = if drive.is_empty() {
        String::new()
    } else {
        format!("; a drive's own tasks: {} (not counted)", drive.len())
    };
    if other.is_empty() {
        return Check::new(
            NAME,
            format!(
                "no other user-space task used more than {}.{} % of a CPU in {ms} ms{drive_note}",
                BUSY_PERMILLE / 10,
                BUSY_PERMILLE % 10
            ),
            Status::Ok,
            None,
        );
    }
    Check::new(
        NAME,
        format!(
            "{} other user-space task(s) used CPU in {ms} ms: {}{drive_note}",
            other.len(),
            list(&other)
        ),
        Status::Warn,
        Some(
            "a task allowed on a drive's core competes with it (SCHED_FIFO preempts it, but on a \
             kernel without full preemption only when its system call returns): stop it during \
             measurements, or keep it off the drive's cores (taskset -a -p -c CPUS PID, a cpuset \
             cgroup, or isolcpus= at boot)"
                .into(),
        ),
    )
}

/// A task that spends this long in the kernel per run on average, µs, can hold a CPU for
/// a whole sample at 10 kHz on a kernel without full preemption.
const LONG_RUN_US: u64 = 100;

/// ... once it has run this many times (not a thread that ran a few times at boot).
const LONG_RUN_MIN_RUNS: u64 = 100;

/// The DAMON monitors that are on (`/sys/kernel/mm/damon/admin/kdamonds/N/state`), with
/// their thread's pid.
fn damon_on(fs: &Fs) -> Vec<(u32, Option<u32>)> {
    const DIR: &str = "/sys/kernel/mm/damon/admin/kdamonds";
    fs.numbered(DIR)
        .unwrap_or_default()
        .into_iter()
        .filter(|n| fs.read(&format!("{DIR}/{n}/state")).as_deref() == Some("on"))
        .map(|n| {
            let pid = fs
                .read(&format!("{DIR}/{n}/pid"))
                .and_then(|p| p.parse().ok());
            (n, pid)
        })
        .collect()
}

/// Tasks allowed on a drive's CPUs that spend long in the kernel at a time (on average
/// since they started): kernel threads, and user tasks by the kernel's share of their time.
/// On a kernel without full preemption a drive task that wakes while one of them is in the
/// kernel waits for its next preemption point (user code it preempts at once). A running
/// drive's own tasks are left out; DAMON's monitor thread is named as such.
#[cfg(test)]
fn kernel_runs_check(fs: &Fs, online: &[usize]) -> Check {
    kernel_runs_check_on(fs, &drive_cpus(fs, online))
}

/// [`kernel_runs_check`] for the drive's CPUs `drive`.
fn kernel_runs_check_on(fs: &Fs, drive: &[usize]) -> Check {
    const NAME: &str = "kernel runs";
    let tasks = task_samples(fs, std::process::id());
    if tasks.is_empty() {
        return Check::new(NAME, "no /proc task could be read", Status::Unknown, None);
    }
    let damon = damon_on(fs);
    let mut long: Vec<&TaskSample> = tasks
        .iter()
        .filter(|t| !t.process.starts_with("drivelab"))
        .filter(|t| t.runs >= LONG_RUN_MIN_RUNS && t.kernel_ns_per_run() >= LONG_RUN_US * 1000)
        .filter(|t| parse_cpu_list(&t.allowed).is_some_and(|a| a.iter().any(|c| drive.contains(c))))
        .collect();
    long.sort_by(|a, b| {
        b.kernel_ns_per_run()
            .cmp(&a.kernel_ns_per_run())
            .then(a.tid.cmp(&b.tid))
    });
    // The monitors whose thread is not named among the long ones.
    let other_damon: Vec<String> = damon
        .iter()
        .filter(|(_, pid)| pid.is_none_or(|p| long.iter().all(|t| t.tid != p)))
        .map(|(n, pid)| match pid {
            Some(p) => format!("kdamond {n} (pid {p})"),
            None => format!("kdamond {n}"),
        })
        .collect();
    let damon_note = if other_damon.is_empty() {
        String::new()
    } else {
        format!("; DAMON on: {}", other_damon.join(", "))
    };
    let drive_list = drive_cpu_text(drive);
    if long.is_empty() {
        return Check::new(
            NAME,
            format!(
                "no task allowed on the drive's cpu {drive_list} spends {LONG_RUN_US} µs or more \
                 in the kernel per run on average{damon_note}"
            ),
            Status::Ok,
            None,
        );
    }
    let names: Vec<String> = long
        .iter()
        .map(|t| {
            let who = if t.kthread {
                format!("kernel thread, pid {}", t.pid)
            } else if t.tid == t.pid {
                format!("pid {}", t.pid)
            } else {
                format!("pid {} thread {}", t.pid, t.tid)
            };
            let per_run = if t.kthread {
                format!("{} µs per run", t.kernel_ns_per_run() / 1000)
            } else {
                format!(
                    "{} µs in the kernel of {} µs per run",
                    t.kernel_ns_per_run() / 1000,
                    t.cpu_ns / t.runs.max(1) / 1000
                )
            };
            let damon = damon
                .iter()
                .find(|(_, p)| *p == Some(t.tid))
                .map_or(String::new(), |(n, _)| format!(", DAMON kdamond {n}"));
            format!(
                "{} ({who}, {per_run} over {} runs, cpus {}{}{damon})",
                t.comm,
                t.runs,
                t.allowed,
                if t.movable { "" } else { ", fixed" },
            )
        })
        .collect();
    Check::new(
        NAME,
        format!(
            "{} task(s) allowed on the drive's cpu {drive_list} spend {LONG_RUN_US} µs or more \
             in the kernel per run on average since they started: {}{damon_note}",
            long.len(),
            first_five(&names)
        ),
        Status::Warn,
        Some(
            "on a kernel without full preemption a drive task that wakes while one of them is in \
             the kernel waits for its next preemption point; keep them off the drive's cores \
             (taskset -a -p -c CPUS PID for a task not marked fixed, the OS's cpus in \
             /sys/devices/virtual/workqueue/cpumask for kworkers, isolcpus= at boot) and stop \
             DAMON while measuring (echo off > /sys/kernel/mm/damon/admin/kdamonds/N/state); \
             drivelab changes nothing"
                .into(),
        ),
    )
}

fn dev_shm_check(fs: &Fs) -> Check {
    const NAME: &str = "/dev/shm";
    let path = fs.path("/dev/shm");
    match statvfs(&path) {
        Ok((size, free)) => {
            let value = format!("size {}, free {}", fmt_bytes(size), fmt_bytes(free));
            const MIB: u64 = 1024 * 1024;
            if free < 64 * MIB {
                Check::new(
                    NAME,
                    value,
                    Status::Bad,
                    Some(
                        "iceoryx2 keeps its buses in /dev/shm: remove stale segments or remount \
                         it larger (mount -o remount,size=1G /dev/shm)"
                            .into(),
                    ),
                )
            } else if free < 256 * MIB {
                Check::new(
                    NAME,
                    value,
                    Status::Warn,
                    Some(
                        "little free shared memory for iceoryx2: remount /dev/shm larger \
                         (mount -o remount,size=1G /dev/shm)"
                            .into(),
                    ),
                )
            } else {
                Check::new(NAME, value, Status::Ok, None)
            }
        }
        Err(e) => Check::new(
            NAME,
            format!("not usable: {}", rt::os_error_text(&e)),
            Status::Bad,
            Some("iceoryx2 needs a tmpfs mounted on /dev/shm".into()),
        ),
    }
}

/// (total, available) bytes of the filesystem holding `path`.
fn statvfs(path: &Path) -> io::Result<(u64, u64)> {
    use std::os::unix::ffi::OsStrExt;
    let c = std::ffi::CString::new(path.as_os_str().as_bytes())
        .map_err(|_| io::Error::from_raw_os_error(libc::EINVAL))?;
    // SAFETY: statvfs is plain integers; all-zero is a valid value for the out-param.
    let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
    // SAFETY: `c` is a NUL-terminated path that outlives the call; `st` is valid and
    // writable.
    if unsafe { libc::statvfs(c.as_ptr(), &mut st) } != 0 {
        return Err(io::Error::last_os_error());
    }
    let frsize = if st.f_frsize > 0 {
        st.f_frsize
    } else {
        st.f_bsize
    } as u64;
    Ok((
        (st.f_blocks as u64).saturating_mul(frsize),
        (st.f_bavail as u64).saturating_mul(frsize),
    ))
}

fn fmt_bytes(b: u64) -> String {
    const UNITS: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut v = b as f64;
    let mut u = 0;
    while v >= 1024.0 && u + 1 < UNITS.len() {
        v /= 1024.0;
        u += 1;
    }
    if u == 0 {
        format!("{b} B")
    } else {
        format!("{v:.1} {}", UNITS[u])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};

    const REQUIRED: [&str; 10] = [
        "preemption",
        "rt throttling",
        "governor",
        "isolated cpus",
        "sched_fifo privilege",
        "mlock",
        "/dev/shm",
        "other load",
        "device irqs",
        "kernel runs",
    ];

    /// A fresh empty directory under the system temp dir, removed on drop.
    struct FakeRoot(PathBuf);

    impl FakeRoot {
        fn new() -> Self {
            static N: AtomicUsize = AtomicUsize::new(0);
            let p = std::env::temp_dir().join(format!(
                "drivelab-doctor-test-{}-{}",
                std::process::id(),
                N.fetch_add(1, Ordering::Relaxed)
            ));
            std::fs::create_dir_all(&p).unwrap();
            FakeRoot(p)
        }

        fn write(&self, abs: &str, content: &str) {
            let p = self.0.join(abs.trim_start_matches('/'));
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(p, content).unwrap();
        }

        fn fs(&self) -> Fs<'_> {
            Fs { root: &self.0 }
        }
    }

    impl Drop for FakeRoot {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    fn find<'a>(checks: &'a [Check], name: &str) -> &'a Check {
        checks
            .iter()
            .find(|c| c.name == name)
            .unwrap_or_else(|| panic!("no check named {name:?}"))
    }

    /// `/proc/timer_list` cut down to what the tick check reads (the full text is parsed in
    /// drivelab_runtime::tick's tests): CPU 0's tick armed at `cpu0`, CPU 1's at `cpu1` or
    /// stopped while idle (`None`), its last tick at `last1` (0: not shown).
    fn timer_list(cpu0: u64, cpu1: Option<u64>, last1: u64) -> String {
        let mut t = format!(
            "now at 98577976528 nsecs\n\ncpu: 0\nactive timers:\n \
             #0: <0c>, tick_nohz_handler, S:01\n # expires at {cpu0}-{cpu0} nsecs\n\
             \x20 .last_tick      : 98576000000 nsecs\n\ncpu: 1\nactive timers:\n"
        );
        if let Some(e) = cpu1 {
            t += &format!(" #0: <1b>, tick_nohz_handler, S:01\n # expires at {e}-{e} nsecs\n");
        }
        t + &format!("  .last_tick      : {last1} nsecs\n\nTick Device: mode:     1\n")
    }

    #[test]
    fn the_tick_period_is_read_from_the_kernels_configuration() {
        assert_eq!(config_hz("CONFIG_HZ_250=y\nCONFIG_HZ=250\n"), Some(250));
        assert_eq!(config_hz("# CONFIG_HZ is not set\n"), None);
        assert_eq!(config_hz("CONFIG_HZ=0\n"), None);
    }

    #[test]
    fn the_tick_is_judged_by_its_period_and_whether_the_cpus_share_its_phase() {
        let root = FakeRoot::new();
        let rel = Some("6.18.0");
        root.write("/boot/config-6.18.0", "CONFIG_HZ_250=y\nCONFIG_HZ=250\n");
        root.write("/proc/cmdline", "console=ttyS0 quiet\n");
        // Without the timer list (a user other than root cannot read it): the period only.
        let c = tick_check(&root.fs(), rel);
        assert_eq!(c.status, Status::Unknown);
        assert_eq!(
            c.value,
            "CONFIG_HZ 250, every 4 ms; its phase unknown: /proc/timer_list unreadable (root \
             reads it)"
        );
        // On whole milliseconds, as on the measured VMs, with CPU 1 idle: its last tick says
        // where its tick restarts.
        root.write(
            "/proc/timer_list",
            &timer_list(98_580_000_000, None, 98_000_000_000),
        );
        let c = tick_check(&root.fs(), rel);
        assert_eq!(c.status, Status::Ok, "{c:?}");
        assert_eq!(
            c.value,
            "CONFIG_HZ 250, every 4 ms; on whole milliseconds on cpu0-1, stopped on idle cpu1"
        );
        root.write("/proc/timer_list", &timer_list(98_580_000_000, None, 0));
        let c = tick_check(&root.fs(), rel);
        assert_eq!(
            c.value,
            "CONFIG_HZ 250, every 4 ms; on whole milliseconds on cpu0, stopped on idle cpu1, \
             no phase shown for cpu1"
        );
        root.write(
            "/proc/timer_list",
            &timer_list(98_580_000_000, Some(98_584_000_000), 0),
        );
        assert_eq!(tick_check(&root.fs(), rel).status, Status::Ok);
        // All CPUs at one phase off the millisecond: a tick-aligned schedule starts on it.
        root.write(
            "/proc/timer_list",
            &timer_list(98_580_250_000, Some(98_584_250_000), 0).replace(
                ".last_tick      : 98576000000",
                ".last_tick      : 98576250000",
            ),
        );
        let c = tick_check(&root.fs(), rel);
        assert_eq!(c.status, Status::Ok, "{c:?}");
        assert_eq!(
            c.value,
            "CONFIG_HZ 250, every 4 ms; 0.250 ms past the millisecond on cpu0-1"
        );
        // skew_tick=1 offsets each CPU's tick by half a period over the number of CPUs (0.5
        // ms for CPU 1 of 4 at 250 Hz): the stages on a CPU other than the plant's meet
        // their tick part-way through a sample.
        root.write("/proc/cmdline", "console=ttyS0 skew_tick=1 quiet\n");
        root.write(
            "/proc/timer_list",
            &timer_list(98_580_000_000, Some(98_582_500_000), 0),
        );
        let c = tick_check(&root.fs(), rel);
        assert_eq!(c.status, Status::Warn);
        assert_eq!(
            c.value,
            "CONFIG_HZ 250, every 4 ms; on whole milliseconds on cpu0, 0.500 ms past the \
             millisecond on cpu1 (skew_tick on the kernel command line offsets the tick per CPU)"
        );
        assert!(c.advice.unwrap().contains("keep the chain on one core"));
        // A period that is not whole milliseconds cannot be aligned with, wherever it is now.
        root.write("/proc/cmdline", "console=ttyS0\n");
        root.write("/boot/config-6.18.0", "CONFIG_HZ=300\n");
        root.write("/proc/timer_list", &timer_list(3_000_000_000, None, 0));
        let c = tick_check(&root.fs(), rel);
        assert_eq!(c.status, Status::Warn);
        assert!(
            c.value.starts_with("CONFIG_HZ 300, every 3.333 ms; "),
            "{}",
            c.value
        );
        assert!(c.advice.unwrap().contains("not whole milliseconds"));
        // No configuration: the phase is reported, the verdict is unknown.
        let bare = FakeRoot::new();
        bare.write("/proc/timer_list", &timer_list(98_580_000_000, None, 0));
        let c = tick_check(&bare.fs(), rel);
        assert_eq!(c.status, Status::Unknown);
        assert!(c
            .value
            .starts_with("CONFIG_HZ unknown; on whole milliseconds"));
    }

    #[test]
    fn mlock_is_judged_against_what_a_stage_host_locks() {
        let nobody = Caps {
            euid: 65534,
            eff: Some(0),
        };
        let mib = |n: libc::rlim_t| n << 20;
        let low = mlock_verdict(&nobody, mib(8), mib(8));
        assert_eq!(low.status, Status::Warn);
        assert_eq!(
            low.value,
            "RLIMIT_MEMLOCK 8 MiB/8 MiB (euid 65534, no CAP_IPC_LOCK): below the about 32 MiB \
             a stage host locks once its bus is open: the hosts run with memory not locked \
             (page faults in the loop) and --rt-strict refuses to start"
        );
        assert_eq!(mlock_verdict(&nobody, mib(32), mib(64)).status, Status::Ok);
        assert_eq!(
            mlock_verdict(&nobody, mib(31), mib(64)).status,
            Status::Warn
        );
        let inf = libc::RLIM_INFINITY;
        assert_eq!(mlock_verdict(&nobody, inf, inf).status, Status::Ok);
        let locker = Caps {
            euid: 1000,
            eff: Some(1 << CAP_IPC_LOCK),
        };
        let ok = mlock_verdict(&locker, mib(8), mib(8));
        assert_eq!(
            (ok.status, ok.value.as_str()),
            (
                Status::Ok,
                "unlimited (CAP_IPC_LOCK; RLIMIT_MEMLOCK 8 MiB/8 MiB)"
            )
        );
    }

    #[test]
    fn address_space_switches_are_judged_by_pcid_or_arm_asids() {
        let root = FakeRoot::new();
        let x86 = |flags: &str| {
            format!("processor\t: 0\nmodel name\t: AMD EPYC\nflags\t\t: fpu pse {flags} sse2\n\nprocessor\t: 1\n")
        };
        root.write("/proc/cpuinfo", &x86("pge hypervisor"));
        let c = address_space_check(&root.fs());
        assert_eq!(c.status, Status::Warn);
        assert_eq!(
            c.value,
            "no PCID: every switch between two processes on a cpu empties the TLB of user \
             pages (a VM: each walk also goes through the host's tables)"
        );
        assert!(c.advice.as_deref().unwrap().contains("--topology"));

        root.write("/proc/cpuinfo", &x86("pge"));
        let c = address_space_check(&root.fs());
        assert_eq!(c.status, Status::Warn);
        assert!(!c.value.contains("VM"), "{}", c.value);

        // "pcid" as a whole flag, not as a part of "invpcid" alone
        root.write("/proc/cpuinfo", &x86("invpcid hypervisor"));
        assert_eq!(address_space_check(&root.fs()).status, Status::Warn);
        root.write("/proc/cpuinfo", &x86("pcid invpcid hypervisor"));
        let c = address_space_check(&root.fs());
        assert_eq!(c.status, Status::Ok);
        assert!(c.value.starts_with("PCID"), "{}", c.value);

        root.write(
            "/proc/cpuinfo",
            "processor\t: 0\nBogoMIPS\t: 108.00\nFeatures\t: fp asimd evtstrm crc32\nCPU architecture: 8\n",
        );
        let c = address_space_check(&root.fs());
        assert_eq!(c.status, Status::Ok);
        assert!(c.value.starts_with("ARM address-space IDs"), "{}", c.value);

        root.write("/proc/cpuinfo", "processor\t: 0\n");
        assert_eq!(address_space_check(&root.fs()).status, Status::Unknown);
        let empty = FakeRoot::new();
        assert_eq!(address_space_check(&empty.fs()).status, Status::Unknown);
    }

    #[test]
    fn cpuidle_states_and_the_latency_request_are_reported() {
        let root = FakeRoot::new();
        root.write(
            "/sys/devices/system/cpu/cpuidle/current_driver",
            "haltpoll\n",
        );
        root.write("/sys/devices/system/cpu/cpu0/cpuidle/state0/name", "POLL\n");
        root.write("/sys/devices/system/cpu/cpu0/cpuidle/state0/latency", "0\n");
        root.write(
            "/sys/devices/system/cpu/cpu0/cpuidle/state1/name",
            "haltpoll idle\n",
        );
        root.write("/sys/devices/system/cpu/cpu0/cpuidle/state1/latency", "1\n");
        let c = cpuidle_check(&root.fs());
        assert_eq!(
            c.value,
            "driver haltpoll; states on cpu0: POLL 0 µs, haltpoll idle 1 µs"
        );
        root.write(
            "/sys/devices/system/cpu/cpuidle/current_governor",
            "haltpoll\n",
        );
        let c = cpuidle_check(&root.fs());
        assert_eq!(
            c.value,
            "driver haltpoll, governor haltpoll; states on cpu0: POLL 0 µs, haltpoll idle 1 µs"
        );
        assert_eq!(c.status, Status::Warn);
        let advice = c.advice.as_deref().unwrap();
        assert!(advice.contains("cpu_latency_us"), "{advice}");
        assert!(
            advice.contains("keeps a CPU polling after a request is released"),
            "{advice}"
        );
        root.write("/sys/devices/system/cpu/cpuidle/current_governor", "menu\n");
        let advice = cpuidle_check(&root.fs()).advice.unwrap();
        assert!(!advice.contains("haltpoll"), "{advice}");
        root.write("/sys/devices/system/cpu/cpu0/cpuidle/state1/disable", "1\n");
        assert_eq!(cpuidle_check(&root.fs()).status, Status::Ok);
        // The value in force (a binary s32) and a holder (a process with the device open).
        let dev = root.0.join("dev/cpu_dma_latency");
        root.write("/dev/cpu_dma_latency", "");
        std::fs::write(&dev, 2_000_000_000i32.to_ne_bytes()).unwrap();
        let c = cpu_latency_request_check(&root.fs());
        assert_eq!(c.value, "none in force; held by no process");
        std::fs::write(&dev, 0i32.to_ne_bytes()).unwrap();
        root.write("/proc/4242/comm", "drivelab\n");
        std::fs::create_dir_all(root.0.join("proc/4242/fd")).unwrap();
        std::os::unix::fs::symlink("/dev/cpu_dma_latency", root.0.join("proc/4242/fd/7")).unwrap();
        let c = cpu_latency_request_check(&root.fs());
        assert_eq!(c.value, "0 µs in force; held by pid 4242 (drivelab)");
        std::fs::remove_file(&dev).unwrap();
        assert_eq!(cpu_latency_request_check(&root.fs()).status, Status::Warn);
    }

    /// A Raspberry Pi 4 style tree: one cpufreq policy for four Cortex-A72 cores, PSCI idle
    /// states, the architected timer, no smt directory, CPU 3 isolated; no x86 file at all.
    #[test]
    fn an_arm_board_is_read_without_x86_files() {
        let root = FakeRoot::new();
        let cpu = "/sys/devices/system/cpu";
        root.write(&format!("{cpu}/online"), "0-3\n");
        for c in 0..4 {
            root.write(
                &format!("{cpu}/cpu{c}/topology/thread_siblings_list"),
                &format!("{c}\n"),
            );
            root.write(
                &format!("{cpu}/cpu{c}/cpufreq/scaling_governor"),
                "ondemand\n",
            );
            root.write(&format!("{cpu}/cpu{c}/cpuidle/state0/name"), "WFI\n");
            root.write(&format!("{cpu}/cpu{c}/cpuidle/state0/latency"), "1\n");
            if c < 2 {
                root.write(&format!("{cpu}/cpu{c}/cpuidle/state1/name"), "cpu-sleep\n");
                root.write(&format!("{cpu}/cpu{c}/cpuidle/state1/latency"), "150\n");
            }
        }
        root.write(&format!("{cpu}/cpuidle/current_driver"), "psci_idle\n");
        let pol = format!("{cpu}/cpufreq/policy0");
        root.write(&format!("{pol}/affected_cpus"), "0 1 2 3\n");
        root.write(&format!("{pol}/scaling_min_freq"), "600000\n");
        root.write(&format!("{pol}/scaling_max_freq"), "1500000\n");
        root.write(&format!("{pol}/cpuinfo_min_freq"), "600000\n");
        root.write(&format!("{pol}/cpuinfo_max_freq"), "1800000\n");
        root.write(
            "/sys/devices/system/clocksource/clocksource0/current_clocksource",
            "arch_sys_counter\n",
        );
        root.write(&format!("{cpu}/isolated"), "3\n");
        root.write(&format!("{cpu}/nohz_full"), "3\n");
        root.write(
            "/proc/cmdline",
            "console=ttyS0 isolcpus=3 nohz_full=3 rcu_nocbs=3\n",
        );
        root.write("/proc/sys/kernel/sched_rt_runtime_us", "950000\n");
        root.write("/proc/sys/kernel/sched_rt_period_us", "1000000\n");
        let checks = run_checks_in(&root.0);

        let g = find(&checks, "governor");
        assert_eq!(
            (g.status, g.value.as_str()),
            (Status::Warn, "ondemand: cpu 0-3")
        );
        let f = find(&checks, "cpufreq limits");
        assert_eq!(f.status, Status::Warn);
        assert_eq!(f.value, "cpu 0-3: 600-1500 MHz of 600-1800 MHz");
        let advice = f.advice.as_deref().unwrap();
        assert!(advice.contains("scaling_min_freq") && advice.contains("below the hardware"));
        let i = find(&checks, "cpuidle");
        assert_eq!(
            i.value,
            "driver psci_idle; states on cpu0-1: WFI 1 µs, cpu-sleep 150 µs; states on cpu2-3: WFI 1 µs"
        );
        assert_eq!(i.status, Status::Warn);
        let c = find(&checks, "clocksource");
        assert_eq!(
            (c.status, c.value.as_str()),
            (Status::Ok, "arch_sys_counter")
        );
        assert_eq!(find(&checks, "isolated cpus").status, Status::Ok);
        assert_eq!(find(&checks, "rt throttling").status, Status::Warn);
        let smt = find(&checks, "smt");
        assert_eq!(
            (smt.status, smt.value.as_str()),
            (Status::Ok, "no sibling threads (one per core)")
        );

        // A fixed clock at the top is fine.
        root.write(&format!("{pol}/scaling_min_freq"), "1800000\n");
        root.write(&format!("{pol}/scaling_max_freq"), "1800000\n");
        let f = cpufreq_limits_check(&root.fs());
        assert_eq!(
            (f.status, f.value.as_str()),
            (Status::Ok, "cpu 0-3: 1800-1800 MHz of 600-1800 MHz: fixed")
        );
        // No cpufreq at all (an x86 VM) is unknown, not an error.
        let empty = FakeRoot::new();
        assert_eq!(cpufreq_limits_check(&empty.fs()).status, Status::Unknown);
    }

    #[test]
    fn a_topology_has_its_own_cores_judged() {
        use drivelab_runtime::topology::ProcessSpec;
        let proc_on = |name: &str, cpu: Option<usize>, priority: u8| ProcessSpec {
            name: name.into(),
            stages: vec![name.into()],
            cpu,
            priority: Some(priority),
            exec: None,
            standby: false,
            machine: None,
        };
        let root = FakeRoot::new();
        root.write(
            "/proc/interrupts",
            "           CPU0       CPU1\n \
             26:         16          0   IO-APIC   4-edge      ttyS0\n \
             36:          0      43330   PCI-MSIX-0000:00:02.0   1-edge      virtio1-req.0\n",
        );
        root.write("/proc/irq/26/effective_affinity_list", "0\n");
        root.write("/proc/irq/36/effective_affinity_list", "1\n");
        root.write("/proc/cmdline", "ro quiet\n");
        let fs = root.fs();
        let online = [0, 1];
        // The default placement's cpu 1 serves virtio1; a topology on cpu 0 meets ttyS0.
        assert!(device_irq_check(&fs, &online)
            .value
            .contains("by the drive's cpu 1: virtio1-req.0"));
        let on0 = Placement {
            name: "mine.toml".into(),
            processes: vec![
                proc_on("plant", Some(0), 70),
                proc_on("observer", Some(0), 72),
            ],
            ..Placement::default()
        };
        let c = device_irq_check_on(&fs, &on0.cpus());
        assert!(c.value.contains("by the drive's cpu 0: ttyS0"), "{c:?}");
        let c = placement_check(&online, &on0);
        assert_eq!(
            (c.status, c.value.as_str()),
            (Status::Ok, "topology mine.toml: cpu 0: plant, observer")
        );
        let c = isolated_cpus_check_for(&fs, &online, &on0.cpus());
        assert_eq!(c.status, Status::Warn);
        assert!(
            c.value.ends_with("the topology's cpu 0 not isolated"),
            "{c:?}"
        );
        assert!(c
            .advice
            .unwrap()
            .contains("the OS's first cpu, which cannot be isolated"));
        // Isolated: fine.
        root.write("/sys/devices/system/cpu/isolated", "1\n");
        let on1 = Placement {
            name: "one".into(),
            processes: vec![proc_on("plant", Some(1), 70)],
            ..Placement::default()
        };
        assert_eq!(
            isolated_cpus_check_for(&fs, &online, &on1.cpus()).status,
            Status::Ok
        );
        // A cpu this machine does not have, one at a shared priority, one unpinned.
        let odd = Placement {
            name: "odd".into(),
            processes: vec![
                proc_on("plant", Some(1), 70),
                proc_on("observer", Some(1), 70),
                proc_on("current-loop", None, 76),
            ],
            ..Placement::default()
        };
        let c = placement_check(&online, &odd);
        assert_eq!(c.status, Status::Warn, "{c:?}");
        let a = c.advice.unwrap();
        assert!(
            a.contains(
                "processes 'plant', 'observer' run on CPU 1 at the same SCHED_FIFO priority 70"
            ),
            "{a}"
        );
        assert!(a.contains("a process pinned to no cpu"), "{a}");
        assert!(
            c.value.ends_with("; not pinned: current-loop"),
            "{}",
            c.value
        );
        let far = Placement {
            name: "far".into(),
            processes: vec![proc_on("plant", Some(7), 70)],
            ..Placement::default()
        };
        let c = placement_check(&online, &far);
        assert_eq!(c.status, Status::Bad, "{c:?}");
        assert!(c
            .advice
            .unwrap()
            .starts_with("cpu 7 is not online here (online: 0-1)"));
    }

    #[test]
    fn a_split_topology_has_this_machines_processes_judged_only() {
        let (file, _) = drivelab_runtime::topology::load("split-hil").unwrap();
        // Which machine this is the doctor cannot tell: without --machine the drive runs
        // whole here, and the line says so.
        let whole = Placement::new("split-hil", file.process.clone(), None).unwrap();
        let c = placement_check(&[0, 1], &whole);
        assert_eq!(
            c.value,
            "topology split-hil: cpu 1: plant, observer, current-loop, speed-loop (split across machines: judged whole on this machine, as drivelab run without --machine runs it; --machine NAME judges one machine's share)"
        );
        let e = Placement::new("split-hil", file.process.clone(), Some("laptop")).unwrap_err();
        assert_eq!(
            e,
            "--machine laptop: topology split-hil has no machine 'laptop' (its machines: simulator, board)"
        );
        let (one, _) = drivelab_runtime::topology::load("two-process").unwrap();
        let e = Placement::new("two-process", one.process, Some("board")).unwrap_err();
        assert!(e.contains("is not split across machines"), "{e}");
        // The board's three processes on its cpu 1; the simulator's plant (also on a cpu 1,
        // of its own machine) is not judged here.
        let board = Placement::new("split-hil", file.process.clone(), Some("board")).unwrap();
        assert_eq!(board.cpus(), [1]);
        let c = placement_check(&[0, 1], &board);
        assert_eq!(
            c.value,
            "topology split-hil, machine board (--machine): cpu 1: observer, current-loop, speed-loop; not judged here (machine simulator): plant"
        );
        let sim = Placement::new("split-hil", file.process, Some("simulator")).unwrap();
        let c = placement_check(&[0, 1], &sim);
        assert_eq!(
            (c.status, c.value.as_str()),
            (
                Status::Ok,
                "topology split-hil, machine simulator (--machine): cpu 1: plant; not judged here (machine board): observer, current-loop, speed-loop"
            )
        );
    }

    #[test]
    fn device_interrupts_on_the_drive_cpus_are_named() {
        let root = FakeRoot::new();
        root.write(
            "/proc/interrupts",
            "           CPU0       CPU1\n  \
             0:         40          0   IO-APIC   2-edge      timer\n \
             26:          0         16   IO-APIC   4-edge      ttyS0\n \
             31:          0        336   PCI-MSIX-0000:00:01.0   3-edge      virtio0-stats\n \
             36:          0      43330   PCI-MSIX-0000:00:02.0   1-edge      virtio1-req.0\n \
             37:          0          0   PCI-MSIX-0000:00:02.0   0-edge      virtio1-config\n \
             NMI:          0          0   Non-maskable interrupts\n \
             11:      12345      12345   GICv3  30 Level     arch_timer\n \
             LOC:     146000      80000   Local timer interrupts\n",
        );
        root.write("/proc/irq/0/effective_affinity_list", "0\n");
        root.write("/proc/irq/26/smp_affinity_list", "1\n");
        root.write("/proc/irq/31/effective_affinity_list", "1\n");
        root.write("/proc/irq/36/effective_affinity_list", "1\n");
        root.write("/proc/irq/36/smp_affinity_list", "0-1\n");
        // An ARM board's per-CPU timer: numbered, but every CPU's own.
        root.write("/proc/irq/11/effective_affinity_list", "0-1\n");
        let c = device_irq_check(&root.fs(), &[0, 1]);
        assert_eq!(
            (c.status, c.value.as_str()),
            (
                Status::Warn,
                "3 of 4 device interrupt line(s) served by the drive's cpu 1: virtio1-req.0 (irq \
                 36, 43330 since boot, cpu 1), virtio0-stats (irq 31, 336 since boot, cpu 1), \
                 ttyS0 (irq 26, 16 since boot, cpu 1)"
            )
        );
        assert!(c
            .advice
            .as_deref()
            .is_some_and(|a| a.contains("irqaffinity=0")));
        // With CPUs 2-3 isolated the drive runs there; nothing is served by them.
        let four = [0, 1, 2, 3];
        root.write("/sys/devices/system/cpu/isolated", "2-3\n");
        let c = device_irq_check(&root.fs(), &four);
        assert_eq!(
            (c.status, c.value.as_str()),
            (
                Status::Ok,
                "4 device interrupt line(s), none served by the drive's cpu 2-3"
            )
        );
        // No /proc/interrupts: unknown.
        let empty = FakeRoot::new();
        assert_eq!(
            device_irq_check(&empty.fs(), &[0, 1]).status,
            Status::Unknown
        );
    }

    fn task(pid: u32, tid: u32, cpu_ns: u64) -> TaskSample {
        TaskSample {
            pid,
            tid,
            comm: format!("t{tid}"),
            process: format!("p{pid}"),
            cpu_ns,
            runs: 1,
            user_ticks: 1,
            system_ticks: 0,
            kthread: false,
            movable: true,
            allowed: "0-1".into(),
        }
    }

    #[test]
    fn busy_tasks_are_those_above_the_threshold_busiest_first() {
        let window = 100_000_000; // 100 ms
        let before = [task(1, 1, 1_000), task(2, 2, 0), task(2, 3, 50)];
        let after = [
            // 0.5 % exactly: not more than the threshold.
            task(1, 1, 1_000 + 500_000),
            // 0.6 %.
            task(2, 2, 600_000),
            // 30 %.
            task(2, 3, 50 + 30_000_000),
            // Started during the window: counted from zero (2 %).
            task(4, 4, 2_000_000),
        ];
        let busy = busy_tasks(&before, &after, window);
        let got: Vec<(u32, u64)> = busy.iter().map(|(t, pm)| (t.tid, *pm)).collect();
        assert_eq!(got, vec![(3, 300), (4, 20), (2, 6)]);
        // A counter that went backwards (a reused tid) is not busy.
        assert!(busy_tasks(&[task(5, 5, 9_000_000)], &[task(5, 5, 10)], window).is_empty());
    }

    #[test]
    fn task_samples_read_every_thread_and_mark_kernel_threads() {
        let root = FakeRoot::new();
        // /proc/PID/task/TID of a process `comm` with stat flags `flags` and CPU time `ns`
        // (utime 3 and stime 1 ticks, 3 runs).
        let thread = |pid: u32, tid: u32, comm: &str, flags: u64, ns: u64| {
            root.write(&format!("/proc/{pid}/comm"), &format!("{comm}\n"));
            let dir = format!("/proc/{pid}/task/{tid}");
            root.write(
                &format!("{dir}/stat"),
                &format!(
                    "{tid} ({comm}) S 1 {pid} {pid} 0 -1 {flags} 100 0 0 0 3 1 0 0 20 0 2 0\n"
                ),
            );
            root.write(&format!("{dir}/schedstat"), &format!("{ns} 10 3\n"));
            root.write(
                &format!("{dir}/status"),
                "Name:\tx\nCpus_allowed:\t2\nCpus_allowed_list:\t1\n",
            );
        };
        // A user process whose name holds a space and a parenthesis, with two threads.
        thread(42, 42, "my (app) x", 4_194_560, 1_500);
        thread(42, 43, "my (app) x", 4_194_560, 7);
        // A kernel thread (PF_KTHREAD) whose CPUs cannot be changed (PF_NO_SETAFFINITY);
        // `/proc` lists by name, so pid 7 comes after 42.
        thread(7, 7, "kworker/1:1", 69_238_880, 99_999_999);
        // The doctor's own process: left out.
        thread(9, 9, "drivelab", 4_194_304, 5);
        let got = task_samples(&root.fs(), 9);
        assert_eq!(
            got.iter()
                .map(|t| (
                    t.pid,
                    t.tid,
                    t.comm.as_str(),
                    t.process.as_str(),
                    t.cpu_ns,
                    t.allowed.as_str(),
                    t.kthread,
                    t.movable
                ))
                .collect::<Vec<_>>(),
            vec![
                (42, 42, "my (app) x", "my (app) x", 1_500, "1", false, true),
                (42, 43, "my (app) x", "my (app) x", 7, "1", false, true),
                (
                    7,
                    7,
                    "kworker/1:1",
                    "kworker/1:1",
                    99_999_999,
                    "1",
                    true,
                    false
                ),
            ]
        );
        assert!(got
            .iter()
            .all(|t| (t.runs, t.user_ticks, t.system_ticks) == (3, 3, 1)));
        // Other load counts user-space tasks only: the kernel thread is not in it.
        // A quiet tree is OK; no /proc at all is unknown.
        let quiet = other_load_check(&root.fs(), std::time::Duration::from_millis(1));
        assert_eq!(quiet.status, Status::Ok, "{}", quiet.value);
        let empty = FakeRoot::new();
        let none = other_load_check(&empty.fs(), std::time::Duration::from_millis(1));
        assert_eq!(
            (none.status, none.value.as_str()),
            (Status::Unknown, "no /proc task could be read")
        );
    }

    /// Kills and reaps the child on drop, also when an assertion fails.
    struct Child(std::process::Child);

    impl Drop for Child {
        fn drop(&mut self) {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }

    #[test]
    fn a_busy_process_is_found() {
        let child = Child(
            std::process::Command::new("sh")
                .args(["-c", "while :; do :; done"])
                .spawn()
                .unwrap(),
        );
        let pid = child.0.id();
        let fs = Fs {
            root: Path::new("/"),
        };
        let me = std::process::id();
        let before = task_samples(&fs, me);
        assert!(before.iter().all(|t| t.pid != me));
        std::thread::sleep(BUSY_WINDOW);
        let after = task_samples(&fs, me);
        let busy = busy_tasks(&before, &after, BUSY_WINDOW.as_nanos() as u64);
        assert!(
            busy.iter()
                .any(|(t, _)| t.pid == pid && t.comm == "sh" && t.allowed != "?"),
            "{busy:?}"
        );
        // Other load makes the check warn (the child alone is enough).
        assert_eq!(other_load_check(&fs, BUSY_WINDOW).status, Status::Warn);
    }

    #[test]
    fn tasks_that_spend_long_in_the_kernel_on_the_drive_cpus_are_named() {
        let root = FakeRoot::new();
        // /proc/PID/task/PID of a single-threaded task `comm` with stat flags `flags`, `runs`
        // runs of `us` µs each (`user` and `sys` clock ticks) and allowed CPUs `cpus`.
        let task = |pid: u32,
                    comm: &str,
                    flags: u64,
                    us: u64,
                    runs: u64,
                    ticks: (u64, u64),
                    cpus: &str| {
            let dir = format!("/proc/{pid}/task/{pid}");
            root.write(&format!("/proc/{pid}/comm"), &format!("{comm}\n"));
            root.write(
                &format!("{dir}/stat"),
                &format!(
                    "{pid} ({comm}) S 2 0 0 0 -1 {flags} 0 0 0 0 {} {} 0 0 20 0 1 0\n",
                    ticks.0, ticks.1
                ),
            );
            root.write(
                &format!("{dir}/schedstat"),
                &format!("{} 1000 {runs}\n", us * 1000 * runs),
            );
            root.write(
                &format!("{dir}/status"),
                &format!("Name:\t{comm}\nCpus_allowed_list:\t{cpus}\n"),
            );
        };
        const KTHREAD: u64 = 0x0020_8040;
        const FIXED: u64 = KTHREAD | 0x0400_0000;
        const USER: u64 = 0x0040_0100;
        task(77, "kdamond.0", KTHREAD, 586, 65_000, (0, 4_713), "0-1");
        task(
            150,
            "kworker/u8:2-ipv6_addrconf",
            FIXED,
            235,
            10_000,
            (0, 241),
            "0-1",
        );
        // A user task that is in the kernel 90 % of its 640 µs runs: 576 µs.
        task(
            75,
            "tokio-rt-worker",
            USER,
            640,
            54_000,
            (317, 2_853),
            "0-1",
        );
        // Left out: only on the OS's cpu, a few long runs at boot, short runs, exactly under
        // the bound, long runs of user code (preempted at once), a running drive's own task.
        task(20, "kworker/0:1", FIXED, 900, 5_000, (0, 450), "0");
        task(24, "irq/24-ACPI:Ged", KTHREAD, 1_800, 4, (0, 1), "0-1");
        task(31, "ksoftirqd/1", FIXED, 36, 14_000, (0, 50), "1");
        task(32, "khugepaged", KTHREAD, 99, 1_000, (0, 10), "0-1");
        task(400, "make", USER, 5_000, 1_000, (495, 5), "0-1");
        task(500, "drivelab-host", USER, 5_000, 1_000, (0, 500), "1");
        let damon = "/sys/kernel/mm/damon/admin/kdamonds";
        root.write(&format!("{damon}/0/state"), "on\n");
        root.write(&format!("{damon}/0/pid"), "77\n");
        root.write(&format!("{damon}/1/state"), "off\n");
        root.write(&format!("{damon}/1/pid"), "-1\n");
        let c = kernel_runs_check(&root.fs(), &[0, 1]);
        assert_eq!(
            (c.status, c.value.as_str()),
            (
                Status::Warn,
                "3 task(s) allowed on the drive's cpu 1 spend 100 µs or more in the kernel per \
                 run on average since they started: kdamond.0 (kernel thread, pid 77, 586 µs \
                 per run over 65000 runs, cpus 0-1, DAMON kdamond 0), tokio-rt-worker (pid 75, \
                 576 µs in the kernel of 640 µs per run over 54000 runs, cpus 0-1), \
                 kworker/u8:2-ipv6_addrconf (kernel thread, pid 150, 235 µs per run over 10000 \
                 runs, cpus 0-1, fixed)"
            )
        );
        assert!(c.advice.unwrap().contains("kdamonds/N/state"));
        // With cpu 0 isolated, the drive's cpu is 0: the kworker bound to it is named too.
        root.write("/sys/devices/system/cpu/isolated", "0\n");
        let c = kernel_runs_check(&root.fs(), &[0, 1]);
        assert!(
            c.value
                .starts_with("4 task(s) allowed on the drive's cpu 0")
                && c.value
                    .contains("kworker/0:1 (kernel thread, pid 20, 900 µs"),
            "{}",
            c.value
        );
        // A monitor whose thread runs short is still reported as on.
        for (pid, comm, flags, cpus) in [
            (77, "kdamond.0", KTHREAD, "0-1"),
            (150, "kworker/u8:2-ipv6_addrconf", FIXED, "0-1"),
            (20, "kworker/0:1", FIXED, "0"),
            (75, "tokio-rt-worker", USER, "0-1"),
        ] {
            task(pid, comm, flags, 20, 5_000, (0, 10), cpus);
        }
        let c = kernel_runs_check(&root.fs(), &[0, 1]);
        assert_eq!(
            (c.status, c.value.as_str()),
            (
                Status::Ok,
                "no task allowed on the drive's cpu 0 spends 100 µs or more in the kernel per \
                 run on average; DAMON on: kdamond 0 (pid 77)"
            )
        );
        let empty = FakeRoot::new();
        assert_eq!(
            kernel_runs_check(&empty.fs(), &[0, 1]).status,
            Status::Unknown
        );
    }

    #[test]
    fn the_load_line_names_the_tasks_and_counts_a_drive_apart() {
        let t = |pid, tid, comm: &str, process: &str, pm| {
            let mut x = task(pid, tid, 0);
            x.comm = comm.into();
            x.process = process.into();
            (x, pm)
        };
        let c = load_verdict(
            vec![
                t(10, 10, "sh", "sh", 717),
                t(20, 22, "recorder", "drivelab", 119),
                t(1, 75, "tokio-rt-worker", "init", 14),
            ],
            300,
        );
        assert_eq!(
            (c.status, c.value.as_str()),
            (
                Status::Warn,
                "2 other user-space task(s) used CPU in 300 ms: sh (pid 10, 71.7 % of a CPU, \
                 cpus 0-1), tokio-rt-worker (pid 1 thread 75, 1.4 % of a CPU, cpus 0-1); a \
                 drive's own tasks: 1 (not counted)"
            )
        );
        assert!(c.advice.as_deref().is_some_and(|a| a.contains("taskset")));
        let many: Vec<_> = (0..7).map(|i| t(100 + i, 100 + i, "w", "w", 50)).collect();
        assert!(load_verdict(many, 300)
            .value
            .ends_with("cpus 0-1) and 2 more"));
        let drive_only = load_verdict(vec![t(20, 20, "drivelab-host", "drivelab-host", 90)], 300);
        assert_eq!(
            (drive_only.status, drive_only.value.as_str()),
            (
                Status::Ok,
                "no other user-space task used more than 0.5 % of a CPU in 300 ms; a drive's \
                 own tasks: 1 (not counted)"
            )
        );
    }

    #[test]
    fn run_checks_has_the_named_checks() {
        let checks = run_checks();
        for name in REQUIRED {
            find(&checks, name);
        }
        for c in &checks {
            assert!(!c.value.is_empty(), "{} has an empty value", c.name);
        }
        // sched_fifo probe ran and left this thread alone.
        assert_eq!(rt::current_policy_raw(), libc::SCHED_OTHER);
    }

    #[test]
    fn render_text_contains_every_check() {
        let checks = run_checks();
        let text = render_text(&checks);
        for c in &checks {
            assert!(text.contains(&c.name), "{} missing from\n{text}", c.name);
        }
        // Header + one line per check + advice lines + summary.
        let advice = checks.iter().filter(|c| c.advice.is_some()).count();
        assert_eq!(
            text.lines().count(),
            1 + checks.len() + advice + 1,
            "{text}"
        );
        // Rows are aligned: the status column starts at the same offset everywhere.
        let w = checks.iter().map(|c| c.name.len()).max().unwrap().max(5);
        for (line, c) in text
            .lines()
            .skip(1)
            .filter(|l| !l.starts_with(' '))
            .zip(&checks)
        {
            assert!(line[w + 2..].starts_with(c.status.label()), "{line}");
        }
        serde_json::to_string(&checks).unwrap();
    }

    #[test]
    fn render_text_advice_below_row() {
        let checks = vec![
            Check::new("a", "x", Status::Ok, None),
            Check::new("longer name", "y\nz", Status::Warn, Some("do this".into())),
        ];
        let text = render_text(&checks);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "CHECK        STATUS   VALUE");
        assert_eq!(lines[1], "a            OK       x");
        assert_eq!(lines[2], "longer name  WARN     y z");
        assert_eq!(lines[3], "                      -> do this");
        assert!(lines[4].starts_with("1 ok, 1 warn, 0 bad, 0 unknown"));
    }

    #[test]
    fn missing_file_is_unknown() {
        assert_eq!(read_trimmed(Path::new("/nonexistent/drivelab/file")), None);
        let c = file_check("x", Path::new("/nonexistent/drivelab/file"), |_| {
            unreachable!("must not interpret a missing file")
        });
        assert_eq!(c.status, Status::Unknown);
        assert!(c.value.contains("/nonexistent/drivelab/file"));
    }

    #[test]
    fn empty_root_gives_unknown_not_panics() {
        let root = FakeRoot::new();
        let checks = run_checks_in(&root.0);
        for name in REQUIRED {
            find(&checks, name);
        }
        for name in [
            "rt throttling",
            "governor",
            "isolated cpus",
            "smt",
            "irqbalance",
            "timer slack",
            "clocksource",
        ] {
            assert_eq!(find(&checks, name).status, Status::Unknown, "{name}");
        }
        // No /dev/shm under the fake root.
        assert_eq!(find(&checks, "/dev/shm").status, Status::Bad);
        render_text(&checks);
    }

    #[test]
    fn rt_throttling_values() {
        let root = FakeRoot::new();
        root.write("/proc/sys/kernel/sched_rt_runtime_us", "950000\n");
        root.write("/proc/sys/kernel/sched_rt_period_us", "1000000\n");
        let c = rt_throttling_check(&root.fs());
        assert_eq!(c.status, Status::Warn);
        assert!(c.value.contains("~50 ms in every 1000 ms"), "{}", c.value);
        assert!(c.advice.unwrap().contains("sched_rt_runtime_us=-1"));

        root.write("/proc/sys/kernel/sched_rt_runtime_us", "-1\n");
        let c = rt_throttling_check(&root.fs());
        assert_eq!(c.status, Status::Ok);
        assert!(c.value.contains("disabled"));

        assert_eq!(
            rt_throttling_verdict(Some(1_000_000), Some(1_000_000), "t").status,
            Status::Ok
        );
        assert_eq!(
            rt_throttling_verdict(None, None, "t").status,
            Status::Unknown
        );
    }

    #[test]
    fn governor_values() {
        let root = FakeRoot::new();
        root.write("/sys/devices/system/cpu/cpu0/uevent", "");
        root.write("/sys/devices/system/cpu/cpu1/uevent", "");
        let c = governor_check(&root.fs());
        assert_eq!(c.status, Status::Unknown);
        assert_eq!(c.value, "no cpufreq (VM?)");

        root.write(
            "/sys/devices/system/cpu/cpu0/cpufreq/scaling_governor",
            "performance\n",
        );
        root.write(
            "/sys/devices/system/cpu/cpu1/cpufreq/scaling_governor",
            "performance\n",
        );
        let c = governor_check(&root.fs());
        assert_eq!(c.status, Status::Ok);
        assert_eq!(c.value, "performance: cpu 0-1");

        root.write(
            "/sys/devices/system/cpu/cpu1/cpufreq/scaling_governor",
            "powersave\n",
        );
        let c = governor_check(&root.fs());
        assert_eq!(c.status, Status::Warn);
        assert!(c.value.contains("powersave: cpu 1"));
        assert!(c.advice.unwrap().contains("performance"));
    }

    #[test]
    fn isolated_values() {
        let root = FakeRoot::new();
        root.write("/sys/devices/system/cpu/isolated", "\n");
        root.write("/proc/cmdline", "quiet splash\n");
        let c = isolated_cpus_check(&root.fs(), &[0, 1, 2, 3]);
        assert_eq!(c.status, Status::Warn);
        assert!(c.value.starts_with("isolated: none"));
        let a = c.advice.unwrap();
        assert!(
            a.contains("isolcpus=1-3 nohz_full=1-3 rcu_nocbs=1-3"),
            "{a}"
        );
        let c = isolated_cpus_check(&root.fs(), &[0, 1]);
        assert!(c
            .advice
            .unwrap()
            .contains("boot with isolcpus=1 nohz_full=1 rcu_nocbs=1"));

        root.write("/sys/devices/system/cpu/isolated", "1\n");
        root.write(
            "/proc/cmdline",
            "quiet isolcpus=1 nohz_full=1 rcu_nocbs=1\n",
        );
        let c = isolated_cpus_check(&root.fs(), &[0, 1]);
        assert_eq!(c.status, Status::Ok);
        assert_eq!(c.value, "isolated: 1; nohz_full: 1; rcu_nocbs: 1");
        assert!(c.advice.is_none());
    }

    #[test]
    fn preemption_values() {
        let v = |rt, dbg, cmd, un| preemption_verdict(rt, dbg, cmd, None, un);
        assert_eq!(v(Some("1"), None, None, None).status, Status::Ok);
        assert_eq!(
            v(None, None, None, Some("#1 SMP PREEMPT_RT Mon")).status,
            Status::Ok
        );
        let c = v(None, None, None, Some("#1 SMP PREEMPT_DYNAMIC @0"));
        assert_eq!(c.status, Status::Warn);
        assert!(c.value.contains("PREEMPT_DYNAMIC"));
        assert!(c.advice.unwrap().contains("PREEMPT_RT"));
        let c = v(None, Some("full"), None, Some("#1 SMP PREEMPT_DYNAMIC"));
        assert_eq!(c.status, Status::Warn);
        assert!(c.value.contains("mode full"));
        let c = v(None, None, Some("none"), Some("#1 SMP PREEMPT_DYNAMIC"));
        assert_eq!(c.status, Status::Bad);
        assert_eq!(
            v(None, None, None, Some("#1 SMP PREEMPT")).status,
            Status::Warn
        );
        assert_eq!(v(None, None, None, Some("#1 SMP Tue")).status, Status::Bad);
        assert_eq!(v(None, None, None, None).status, Status::Unknown);
        assert_eq!(
            current_preempt_mode("none voluntary (full) lazy").as_deref(),
            Some("full")
        );

        let root = FakeRoot::new();
        root.write("/sys/kernel/realtime", "1\n");
        assert_eq!(preemption_check(&root.fs(), None, None).status, Status::Ok);
    }

    #[test]
    fn a_dynamic_kernel_without_preempt_on_its_command_line_runs_its_built_in_mode() {
        let dynamic = Some("#1 SMP PREEMPT_DYNAMIC @0");
        let root = FakeRoot::new();
        root.write("/proc/cmdline", "quiet\n");
        // Neither debugfs nor a configuration: unknown.
        let c = preemption_check(&root.fs(), dynamic, Some("6.18.0"));
        assert_eq!(c.status, Status::Warn);
        assert!(c.value.contains("current mode unknown"), "{}", c.value);
        // /boot/config-<release>, as distributions install it.
        root.write(
            "/boot/config-6.18.0",
            "CONFIG_PREEMPT_BUILD=y\n# CONFIG_PREEMPT_VOLUNTARY is not set\nCONFIG_PREEMPT_NONE=y\n",
        );
        let c = preemption_check(&root.fs(), dynamic, Some("6.18.0"));
        assert_eq!(c.status, Status::Bad);
        assert_eq!(
            c.value,
            "PREEMPT_DYNAMIC, mode none (the kernel's built-in default, no preempt= on the \
             command line): a task's system call on a drive's core holds up the drive's \
             wake-up until it returns; not PREEMPT_RT"
        );
        // /proc/config.gz comes first; preempt= on the command line overrides either.
        let gz = {
            use std::io::Write;
            let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
            e.write_all(b"CONFIG_PREEMPT_DYNAMIC=y\nCONFIG_PREEMPT=y\n")
                .unwrap();
            e.finish().unwrap()
        };
        std::fs::write(root.0.join("proc/config.gz"), gz).unwrap();
        let c = preemption_check(&root.fs(), dynamic, Some("6.18.0"));
        assert_eq!(c.status, Status::Warn);
        assert!(
            c.value.contains("mode full (the kernel's built-in default"),
            "{}",
            c.value
        );
        root.write("/proc/cmdline", "quiet preempt=voluntary\n");
        let c = preemption_check(&root.fs(), dynamic, Some("6.18.0"));
        assert_eq!(c.status, Status::Bad);
        assert!(
            c.value
                .contains("mode voluntary (preempt= on /proc/cmdline)"),
            "{}",
            c.value
        );
        assert_eq!(config_preempt_mode("CONFIG_PREEMPT_LAZY=y\n"), Some("lazy"));
        assert_eq!(config_preempt_mode("# CONFIG_PREEMPT is not set\n"), None);
    }

    #[test]
    fn irqbalance_values() {
        let root = FakeRoot::new();
        root.write("/proc/1/comm", "init\n");
        assert_eq!(irqbalance_check(&root.fs()).status, Status::Ok);
        root.write("/proc/42/comm", "irqbalance\n");
        let c = irqbalance_check(&root.fs());
        assert_eq!(c.status, Status::Warn);
        assert!(c.value.contains("42"));
    }

    #[test]
    fn smt_values() {
        let root = FakeRoot::new();
        root.write("/sys/devices/system/cpu/smt/control", "notsupported\n");
        root.write("/sys/devices/system/cpu/smt/active", "0\n");
        root.write(
            "/sys/devices/system/cpu/cpu0/topology/thread_siblings_list",
            "0\n",
        );
        assert_eq!(smt_check(&root.fs()).status, Status::Ok);
        root.write("/sys/devices/system/cpu/smt/control", "on\n");
        root.write("/sys/devices/system/cpu/smt/active", "1\n");
        root.write(
            "/sys/devices/system/cpu/cpu0/topology/thread_siblings_list",
            "0,2\n",
        );
        root.write(
            "/sys/devices/system/cpu/cpu2/topology/thread_siblings_list",
            "0,2\n",
        );
        let c = smt_check(&root.fs());
        assert_eq!(c.status, Status::Warn);
        assert!(c.value.contains("siblings 0,2"), "{}", c.value);
    }

    #[test]
    fn timer_slack_values() {
        let root = FakeRoot::new();
        root.write("/proc/self/timerslack_ns", "50000\n");
        let c = timer_slack_check(&root.fs());
        assert_eq!(c.status, Status::Warn);
        assert!(c.value.contains("50 us"));
        root.write("/proc/self/timerslack_ns", "1\n");
        assert_eq!(timer_slack_check(&root.fs()).status, Status::Ok);
    }

    #[test]
    fn cpu_lists() {
        assert_eq!(
            parse_cpu_list("0-3,8,10-11"),
            Some(vec![0, 1, 2, 3, 8, 10, 11])
        );
        assert_eq!(parse_cpu_list(""), Some(vec![]));
        assert_eq!(parse_cpu_list("x"), Some(vec![]));
        assert_eq!(parse_cpu_list("1-"), None);
        assert_eq!(parse_cpu_list("nohz,domain,1-2"), Some(vec![1, 2]));
        assert_eq!(fmt_cpu_list(&[0, 1, 2, 3, 8, 10, 11]), "0-3,8,10-11");
        assert_eq!(fmt_cpu_list(&[]), "");
        assert_eq!(
            cmdline_param("a isolcpus=2 b nohz_full=2-3 -- isolcpus=9", "isolcpus").as_deref(),
            Some("2")
        );
        assert_eq!(fmt_bytes(512), "512 B");
        assert_eq!(fmt_bytes(3 * 1024 * 1024), "3.0 MiB");
    }

    #[test]
    fn dev_shm_live_and_missing() {
        // The drive's buses live in /dev/shm (every test of the drive needs it): read.
        assert!(Path::new("/dev/shm").is_dir());
        let c = dev_shm_check(&Fs {
            root: Path::new("/"),
        });
        assert!(
            c.value.starts_with("size ") && c.value.contains(", free "),
            "{}",
            c.value
        );
        // A root without dev/shm: not usable, a Bad check with advice.
        let root =
            std::env::temp_dir().join(format!("drivelab-doctor-noshm-{}", std::process::id()));
        std::fs::create_dir_all(&root).unwrap();
        let c = dev_shm_check(&Fs { root: &root });
        std::fs::remove_dir_all(&root).unwrap();
        assert!(c.value.starts_with("not usable: "), "{}", c.value);
        assert_eq!(c.status, Status::Bad);
        assert_eq!(
            c.advice.as_deref(),
            Some("iceoryx2 needs a tmpfs mounted on /dev/shm")
        );
    }
}
