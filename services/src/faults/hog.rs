//! `hog:CPU@S:DUR:PRIO`: a noisy neighbour. The supervisor starts a child process
//! (`drivelab hog`, hidden) when the drive starts; it pins itself to CPU, takes SCHED_FIFO
//! priority PRIO and waits, armed, on its stdin. At simulated second S the supervisor writes
//! it a byte, and it busy-loops for DUR seconds from then: above the drive's priorities on the
//! drive's core it is a priority inversion, below them a load the drive should shrug off.
//! Real-time clock only. The kernel's RT throttling (`sched_rt_runtime_us`) still leaves a
//! share of the CPU to others; it is read and reported, never changed
//! (docs/architecture.md, "Fault model").

use super::window::{window as figures, FaultWindow, Pair};
use super::{FaultSpec, STOP_MAX_S, STOP_MIN_S};
use crate::launcher::FaultReport;
use anyhow::{anyhow, bail, Context, Result};
use drivelab_runtime::trace::TraceRow;
use serde::Serialize;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// One hog.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Hog {
    /// The CPU it pins itself to.
    pub cpu: usize,
    /// Start, simulated s after sample 0.
    pub at_s: f64,
    /// How long it spins, s.
    pub duration_s: f64,
    /// Its SCHED_FIFO priority, 1..=99.
    pub priority: u8,
}

impl Hog {
    /// The spec as `--fault` takes it, e.g. `hog:1@0.5:0.3:99`.
    pub fn spec(&self) -> String {
        format!(
            "hog:{}@{}:{}:{}",
            self.cpu, self.at_s, self.duration_s, self.priority
        )
    }

    /// E.g. `hog cpu 1 SCHED_FIFO 99 for 0.3 s`.
    pub fn describe(&self) -> String {
        format!(
            "hog cpu {} SCHED_FIFO {} for {} s",
            self.cpu, self.priority, self.duration_s
        )
    }
}

/// Parses `hog:CPU@SECONDS:DURATION:PRIORITY`.
pub fn parse(spec: &str) -> Result<Hog> {
    let form = || anyhow!("fault '{spec}': expected hog:CPU@SECONDS:DURATION:PRIORITY");
    let rest = spec.strip_prefix("hog:").ok_or_else(form)?;
    let (cpu, when) = rest.split_once('@').ok_or_else(form)?;
    let mut parts = when.split(':');
    let (Some(at), Some(dur), Some(prio), None) =
        (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return Err(form());
    };
    let cpu: usize = cpu
        .parse()
        .ok()
        .filter(|&c| c < libc::CPU_SETSIZE as usize)
        .ok_or_else(|| anyhow!("fault '{spec}': CPU '{cpu}' is not a CPU number"))?;
    let duration_s = super::seconds(dur, "duration", spec)?;
    if !(STOP_MIN_S..=STOP_MAX_S).contains(&duration_s) {
        bail!("fault '{spec}': a hog lasts {STOP_MIN_S} to {STOP_MAX_S} s");
    }
    let priority = prio
        .parse::<u8>()
        .ok()
        .filter(|p| (1..=99).contains(p))
        .ok_or_else(|| {
            anyhow!("fault '{spec}': PRIORITY '{prio}' must be a SCHED_FIFO priority in 1..=99")
        })?;
    Ok(Hog {
        cpu,
        at_s: super::seconds(at, "time", spec)?,
        duration_s,
        priority,
    })
}

/// CPU numbers for a message: "0, 1".
pub fn cpu_list(cpus: &[usize]) -> String {
    cpus.iter()
        .map(|c| c.to_string())
        .collect::<Vec<_>>()
        .join(", ")
}

/// The CPUs this process may run on (its affinity mask; every online CPU when it cannot
/// be read).
pub fn allowed_cpus() -> Vec<usize> {
    drivelab_runtime::rt::affinity_cpus()
        .unwrap_or_else(|| (0..drivelab_runtime::rt::online_cpus()).collect())
}

/// The hogs among `specs`, in the order they start, checked against the run: the CPU
/// exists (`cpus`), the start is inside the run, and the clock is the real-time one.
pub fn plan(
    specs: &[FaultSpec],
    duration_s: f64,
    realtime: bool,
    cpus: &[usize],
) -> Result<Vec<Hog>> {
    let mut hogs: Vec<Hog> = specs
        .iter()
        .filter_map(|s| match s {
            FaultSpec::Hog(h) => Some(h.clone()),
            _ => None,
        })
        .collect();
    for h in &hogs {
        let spec = h.spec();
        if !realtime {
            bail!(
                "fault {spec}: a CPU hog needs --clock realtime (it loads a real core; the \
                 other faults work in every clock)"
            );
        }
        if !cpus.contains(&h.cpu) {
            bail!(
                "fault {spec}: there is no CPU {} here (CPUs: {})",
                h.cpu,
                cpu_list(cpus)
            );
        }
        if h.at_s >= duration_s {
            bail!("fault {spec} is at or after the end of the run ({duration_s} s)");
        }
    }
    hogs.sort_by(|a, b| a.at_s.total_cmp(&b.at_s));
    Ok(hogs)
}

/// Checks before the run that a hog can get its CPU and SCHED_FIFO priority: starts one
/// that spins for no time and reports its refusal in one line.
pub fn check_privilege(h: &Hog) -> Result<()> {
    let hog = Hog {
        duration_s: 0.0,
        ..h.clone()
    };
    let out = command(&hog, None, false)?
        .stderr(Stdio::piped())
        .output()
        .context("cannot start the hog process")?;
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        let line = err.lines().last().unwrap_or("").trim();
        bail!(
            "fault {}: {}",
            h.spec(),
            line.trim_start_matches("drivelab: error: ")
        );
    }
    Ok(())
}

/// `drivelab hog --cpu C --priority P --duration-s D [--bus ID] [--armed]`, ended by the
/// kernel if the launcher dies. `--bus` names the drive it disturbs, so that it is found like
/// the drive's own processes (`drivelab run` refuses a busy bus, tests check that none is
/// left). `--armed`: it waits for a byte on its stdin before it spins.
fn command(h: &Hog, bus: Option<&str>, armed: bool) -> Result<Command> {
    let exe = std::env::current_exe().context("cannot find the drivelab executable")?;
    let mut cmd = Command::new(exe);
    cmd.arg("hog")
        .arg("--cpu")
        .arg(h.cpu.to_string())
        .arg("--priority")
        .arg(h.priority.to_string())
        .arg("--duration-s")
        .arg(h.duration_s.to_string())
        .args(bus.map(|b| ["--bus", b]).into_iter().flatten())
        .args(armed.then_some("--armed"))
        .stdin(if armed { Stdio::piped() } else { Stdio::null() })
        .stdout(Stdio::null());
    crate::launcher::die_with_launcher(&mut cmd);
    Ok(cmd)
}

/// The hog process's body: pins itself to `cpu`, takes SCHED_FIFO `priority` (a one-line
/// error if refused) and spins for `duration_s` seconds. `armed`: it first waits for one
/// byte on stdin and spins from its arrival; at end of file (the supervisor ended before the
/// hog's time) it exits without spinning.
pub fn run(cpu: usize, priority: u8, duration_s: f64, armed: bool) -> Result<()> {
    if !(0.0..=STOP_MAX_S).contains(&duration_s) {
        bail!("hog: --duration-s {duration_s} must be in 0..={STOP_MAX_S}");
    }
    let req = drivelab_runtime::rt::RtRequest {
        core: Some(cpu),
        fifo_priority: Some(priority),
        lock_memory: false,
        prefault_stack_bytes: 0,
    };
    drivelab_runtime::rt::setup_rt(&req, drivelab_runtime::rt::RtPolicy::Strict)
        .map_err(|e| anyhow!("hog: {e:#}"))?;
    if armed {
        let mut go = [0u8; 1];
        match std::io::Read::read(&mut std::io::stdin().lock(), &mut go) {
            Ok(1) => {}
            Ok(_) => return Ok(()),
            Err(e) => bail!("hog: cannot read its start from stdin: {e}"),
        }
    }
    let end = Instant::now() + Duration::from_secs_f64(duration_s);
    while Instant::now() < end {
        std::hint::spin_loop();
    }
    Ok(())
}

/// A hog process's state under the supervisor.
enum State {
    /// Started, waiting on its stdin.
    Armed(Child, std::process::ChildStdin),
    /// Spinning; killed if it is still there at the instant.
    Started(Child, Instant),
    /// Ended (reaped), or never started: why.
    Gone(String),
}

/// Hogs under the supervisor, in the order of their plan: started ahead of their time and
/// armed, so that a hog spins from its planned sample on, not from whenever a process the
/// size of this one has been loaded (4 to 36 ms for a debug build on a loaded machine here,
/// 7 to 32 ms for a release build). Dropping it (however the supervisor returns) kills and
/// reaps every one still there; an armed hog whose start never came is killed unstarted.
pub struct Running {
    hogs: Vec<State>,
}

impl Running {
    /// Starts a process for each of `hogs` against the drive of bus `bus`, armed; a hog
    /// that could not be started keeps its error for [`Running::start`].
    pub fn arm(hogs: &[Hog], bus: &str) -> Self {
        let start = |h: &Hog| -> Result<State> {
            let mut child = command(h, Some(bus), true)?
                .stderr(Stdio::null())
                .spawn()
                .context("cannot start the hog process")?;
            let stdin = child.stdin.take().context("the hog process has no stdin")?;
            Ok(State::Armed(child, stdin))
        };
        Self {
            hogs: hogs
                .iter()
                .map(|h| start(h).unwrap_or_else(|e| State::Gone(format!("{e:#}"))))
                .collect(),
        }
    }

    /// Starts hog `i` of the plan (`h`) now; returns its pid.
    pub fn start(&mut self, i: usize, h: &Hog) -> Result<u32> {
        let slot = self
            .hogs
            .get_mut(i)
            .ok_or_else(|| anyhow!("it was not armed"))?;
        let (child, stdin) = match slot {
            State::Armed(child, stdin) => (child, stdin),
            State::Started(..) => bail!("it has started already"),
            State::Gone(why) => bail!("{why}"),
        };
        let pid = child.id();
        std::io::Write::write_all(stdin, b"!")
            .with_context(|| format!("cannot start its process (pid {pid})"))?;
        // It ends itself after DUR; it is killed if it is still there 100 ms later.
        let end = Instant::now() + Duration::from_secs_f64(h.duration_s + 0.1);
        // Its stdin is dropped: the hog reads one byte only.
        if let State::Armed(child, _) = std::mem::replace(slot, State::Gone(String::new())) {
            *slot = State::Started(child, end);
        }
        Ok(pid)
    }

    /// Reaps the hogs that ended and kills those past their end; returns the pids that
    /// failed (exited with an error, e.g. refused their priority) with their status.
    pub fn poll(&mut self, now: Instant) -> Vec<(u32, std::process::ExitStatus)> {
        let mut failed = Vec::new();
        for slot in &mut self.hogs {
            let (child, end) = match slot {
                State::Armed(c, _) => (c, None),
                State::Started(c, end) => (c, Some(*end)),
                State::Gone(_) => continue,
            };
            let pid = child.id();
            let gone = match child.try_wait() {
                Ok(Some(st)) => {
                    if !st.success() {
                        failed.push((pid, st));
                    }
                    format!("its process (pid {pid}) had ended before its start: {st}")
                }
                Ok(None) if end.is_some_and(|end| now >= end) => {
                    let _ = child.kill();
                    let _ = child.wait();
                    "killed after its end".into()
                }
                Ok(None) => continue,
                Err(e) => format!("its process (pid {pid}) cannot be waited for: {e}"),
            };
            *slot = State::Gone(gone);
        }
        failed
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        for slot in &mut self.hogs {
            if let State::Armed(c, _) | State::Started(c, _) = slot {
                let _ = c.kill();
                let _ = c.wait();
            }
        }
    }
}

/// The window figures of a hog that started at sample `k0`: its DUR against as long
/// before it.
pub fn window(h: &Hog, rows: &[TraceRow], k0: u64, fs: f64) -> FaultWindow {
    let len = ((h.duration_s * fs).round() as u64).max(1);
    figures(rows, k0.saturating_sub(len)..k0, k0..k0 + len)
}

/// Samples of margin around a hog's planned window for the supervisor's late start, s.
const MARGIN_S: f64 = 0.2;
/// The recorder keeps latencies for the drive's catching up after a hog: up to 5 × DUR,
/// at most this long, s.
const CATCH_UP_MAX_S: f64 = 10.0;

/// Cycle latencies (t_k → command k published) the recorder keeps around a hog's planned
/// window, one per sample, preallocated (`u32::MAX`: none, e.g. a lockstep command).
#[derive(Debug, Clone)]
pub struct WindowLatency {
    /// First sample kept.
    pub from_k: u64,
    /// Sample time T_s, ns.
    pub ts_ns: u64,
    /// Latency of sample from_k + i, ns (clamped).
    pub ns: Vec<u32>,
}

impl WindowLatency {
    /// The span for hog `h` at `fs` Hz: its DUR before its start to its end, with margins.
    pub fn new(h: &Hog, fs: f64) -> Self {
        let len = (h.duration_s * fs).round() as u64;
        let margin = (MARGIN_S * fs) as u64;
        let k0 = (h.at_s * fs).round() as u64;
        let from_k = k0.saturating_sub(len + margin);
        let end_k = k0 + len + margin + (5 * len).min((CATCH_UP_MAX_S * fs) as u64);
        Self {
            from_k,
            ts_ns: (1e9 / fs).round() as u64,
            ns: vec![u32::MAX; (end_k - from_k) as usize],
        }
    }

    /// The first sample from `k` on from which every command comes before its deadline
    /// for 10 ms (`hold` samples).
    fn on_schedule_from(&self, k: u64, hold: usize) -> Option<u64> {
        let i0 = k.checked_sub(self.from_k)? as usize;
        let ts = self.ts_ns.min(u64::from(u32::MAX - 1)) as u32;
        let v = self.ns.get(i0..)?;
        (0..v.len().saturating_sub(hold))
            .find(|&i| v[i..i + hold].iter().all(|&x| x <= ts))
            .map(|i| k + i as u64)
    }

    /// Records command k's latency.
    #[inline]
    pub fn record(&mut self, k: u64, latency_ns: i64) {
        if let Some(v) = k
            .checked_sub(self.from_k)
            .and_then(|i| self.ns.get_mut(i as usize))
        {
            *v = latency_ns.clamp(0, i64::from(u32::MAX - 1)) as u32;
        }
    }

    /// The latencies of samples `ks` = [first, end) (None when it does not cover them).
    fn of(&self, ks: [u64; 2]) -> Option<&[u32]> {
        let lo = ks[0].checked_sub(self.from_k)? as usize;
        let hi = ks[1].checked_sub(self.from_k)? as usize;
        self.ns.get(lo..hi)
    }

    /// Deadline misses among samples `ks`, as the plant counts them: command k published
    /// after t_{k+1} (cycle latency > T_s) or never.
    fn misses(&self, ks: [u64; 2]) -> Option<u64> {
        let ts = self.ts_ns.min(u64::from(u32::MAX - 1)) as u32;
        Some(self.of(ks)?.iter().filter(|&&x| x > ts).count() as u64)
    }

    /// p99 of the latencies of samples `ks`, µs (None when it holds none of them).
    fn p99_us(&self, ks: [u64; 2]) -> Option<f64> {
        let mut v: Vec<u32> = self
            .of(ks)?
            .iter()
            .copied()
            .filter(|&x| x != u32::MAX)
            .collect();
        if v.is_empty() {
            return None;
        }
        v.sort_unstable();
        let i = ((0.99 * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1;
        Some(f64::from(v[i]) / 1e3)
    }
}

/// Fills `cycle_p99_us` and `deadline_misses` of the hogs' reports from the recorder's
/// latencies. A starved plant catches up on its missed deadlines with the commands there
/// (the chain runs above it), so the trace's `miss` column does not show them: the
/// latencies do.
pub fn add_latency(faults: &mut [FaultReport], lat: &[WindowLatency]) {
    for f in faults.iter_mut().filter(|f| f.fault.starts_with("hog ")) {
        let Some(w) = f.window.as_mut() else { continue };
        let Some(l) = lat
            .iter()
            .find(|l| l.of([w.before_k[0], w.during_k[1]]).is_some())
        else {
            continue;
        };
        w.cycle_p99_us = l
            .p99_us(w.before_k)
            .zip(l.p99_us(w.during_k))
            .map(|(b, d)| Pair {
                before: b,
                during: d,
            });
        if let (Some(b), Some(d)) = (l.misses(w.before_k), l.misses(w.during_k)) {
            w.deadline_misses = Pair {
                before: b,
                during: d,
            };
        }
        let per_ms = 1e6 / l.ts_ns as f64;
        w.cycle_recovered_ms = l
            .on_schedule_from(w.during_k[1], per_ms.round().max(1.0) as usize * 10)
            .map(|k| (k - w.during_k[0]) as f64 / per_ms);
    }
}

/// The kernel's RT throttling: (sched_rt_runtime_us, sched_rt_period_us), read only.
pub fn rt_throttling() -> Option<(i64, i64)> {
    let read = |name: &str| -> Option<i64> {
        std::fs::read_to_string(format!("/proc/sys/kernel/{name}"))
            .ok()?
            .trim()
            .parse()
            .ok()
    };
    Some((read("sched_rt_runtime_us")?, read("sched_rt_period_us")?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_a_hog() {
        assert_eq!(
            parse("hog:1@0.5:0.3:99").unwrap(),
            Hog {
                cpu: 1,
                at_s: 0.5,
                duration_s: 0.3,
                priority: 99
            }
        );
        assert!(matches!(
            super::super::parse("hog:0@0:60:1").unwrap(),
            FaultSpec::Hog(_)
        ));
    }

    #[test]
    fn bad_hogs_are_one_line_errors() {
        for (spec, needle) in [
            (
                "hog:1@0.5:0.3",
                "expected hog:CPU@SECONDS:DURATION:PRIORITY",
            ),
            (
                "hog:1@0.5:0.3:99:7",
                "expected hog:CPU@SECONDS:DURATION:PRIORITY",
            ),
            ("hog:1", "expected hog:CPU@SECONDS:DURATION:PRIORITY"),
            (
                "hog@1:0.5:0.3",
                "expected hog:CPU@SECONDS:DURATION:PRIORITY",
            ),
            ("hog:x@0.5:0.3:99", "CPU 'x' is not a CPU number"),
            ("hog:-1@0.5:0.3:99", "CPU '-1' is not a CPU number"),
            ("hog:99999@0.5:0.3:99", "CPU '99999' is not a CPU number"),
            ("hog:1@soon:0.3:99", "'soon' is not a number of seconds"),
            ("hog:1@0.5:0.0005:99", "a hog lasts 0.001 to 60 s"),
            ("hog:1@0.5:61:99", "a hog lasts 0.001 to 60 s"),
            ("hog:1@0.5:nan:99", "finite number of seconds"),
            (
                "hog:1@0.5:0.3:0",
                "PRIORITY '0' must be a SCHED_FIFO priority in 1..=99",
            ),
            ("hog:1@0.5:0.3:100", "in 1..=99"),
            ("hog:1@0.5:0.3:high", "in 1..=99"),
        ] {
            let e = format!("{:#}", super::super::parse(spec).unwrap_err());
            assert!(e.contains(needle), "{spec}: {e}");
            assert_eq!(e.lines().count(), 1, "{spec}: {e}");
        }
    }

    #[test]
    fn the_plan_checks_cpu_run_length_and_clock() {
        let specs = [
            super::super::parse("hog:1@0.8:0.1:50").unwrap(),
            super::super::parse("hog:0@0.2:0.1:99").unwrap(),
        ];
        let p = plan(&specs, 1.0, true, &[0, 1]).unwrap();
        assert_eq!((p[0].cpu, p[1].cpu), (0, 1));
        let e = plan(&specs, 1.0, true, &[0]).unwrap_err().to_string();
        assert_eq!(
            e,
            "fault hog:1@0.8:0.1:50: there is no CPU 1 here (CPUs: 0)"
        );
        let e = plan(&specs, 0.5, true, &[0, 1]).unwrap_err().to_string();
        assert!(e.contains("at or after the end of the run (0.5 s)"), "{e}");
        let e = plan(&specs, 1.0, false, &[0, 1]).unwrap_err().to_string();
        assert!(e.contains("needs --clock realtime"), "{e}");
        assert!(plan(&[], 1.0, false, &[0]).unwrap().is_empty());
    }

    #[test]
    fn window_latency_p99_of_each_range() {
        let h = Hog {
            cpu: 0,
            at_s: 1.0,
            duration_s: 0.1,
            priority: 1,
        };
        let mut l = WindowLatency::new(&h, 1000.0);
        // 100 samples before at 10 µs, 100 during at 10..=1000 µs.
        for k in 900..1000 {
            l.record(k, 10_000);
        }
        for k in 1000..1100 {
            l.record(k, (k as i64 - 999) * 10_000);
        }
        l.record(5_000_000, 1);
        assert_eq!(l.p99_us([900, 1000]), Some(10.0));
        assert_eq!(l.p99_us([1000, 1100]), Some(990.0));
        assert_eq!(l.p99_us([0, 10]), None);
        // T_s = 1 ms: the samples above 1000 µs and the one without a command are misses.
        l.ns[0] = u32::MAX;
        assert_eq!(l.misses([1000, 1100]), Some(0));
        l.record(1050, 1_000_001);
        assert_eq!(l.misses([1000, 1100]), Some(1));
        assert_eq!(l.misses([700, 701]), Some(1));
        // Late up to 1150, on time from 1151 on (10 ms = 10 samples at 1 kHz).
        for k in 1100..1400 {
            l.record(k, if k <= 1150 { 2_000_000 } else { 500_000 });
        }
        l.record(1155, 2_000_000);
        assert_eq!(l.on_schedule_from(1100, 10), Some(1156));
        assert_eq!(l.on_schedule_from(1400, 10), None);
    }
}
