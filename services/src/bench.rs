//! `drivelab bench`: the sample-time budget of the chain against the floor (a bare timer),
//! the same chain in one thread, the same four processes over Unix sockets, and the product
//! (iceoryx2), at several rates and placements, under identical conditions in one invocation.

use crate::expect::usage;
use crate::launcher::{self, Clock, RunOptions};
use anyhow::{anyhow, Context, Result};
use drivelab_bench::cache::CacheProbe;
use drivelab_bench::hop::Measure;
use drivelab_bench::idle::Settle;
use drivelab_bench::{ChainSpec, NodeSpec, VariantResult};
use drivelab_runtime::config::{CpuLatency, Placement, Scenario, ServicePlacement};
use drivelab_runtime::service::TopologyPlan;
use drivelab_runtime::timing::{LatencyHist, Percentiles};
use serde::Serialize;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Arguments of `drivelab bench`.
#[derive(Debug, clap::Args)]
pub struct BenchArgs {
    /// Smoke mode: 0.2 s per variant, 10 kHz only, one-core placement only.
    #[arg(long)]
    pub quick: bool,
    /// Seconds of measurement per variant (default 10; with --quick 0.2).
    #[arg(long, value_name = "SECONDS")]
    pub seconds: Option<f64>,
    /// Sample rates to measure, Hz (comma-separated; default 5000,10000,20000).
    #[arg(long, value_delimiter = ',', value_name = "HZ,...")]
    pub rates: Vec<f64>,
    /// Placements to measure (comma-separated; default all three): one-core, two-plus-two,
    /// alternating.
    #[arg(long, value_delimiter = ',', value_name = "NAME,...")]
    pub placements: Vec<String>,
    /// Output folder (default runs/bench-<unix time>).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Also measure the one-core iceoryx2 chain with the plant sleeping to this many µs
    /// before each deadline and spinning the rest, capped at T_s/4 (12.5 µs at 20 kHz) so
    /// that the spin leaves the chain its time on the core (0 = skip that variant).
    #[arg(long, default_value_t = 30.0, value_name = "MICROSECONDS")]
    pub spin_us: f64,
    /// Split each variant's measurement into this many interleaved rounds (every variant
    /// runs once per round), so that slow changes of the machine reach all variants alike
    /// (default 5; with --quick 1). With two or more, the targets are also judged round by
    /// round, each round's chain against that round's floor.
    #[arg(long, value_name = "N")]
    pub rounds: Option<usize>,
    /// Compare topologies instead of placements (comma-separated shipped names or files):
    /// the iceoryx2 chain in each topology, interleaved with the floor and its repeat (the
    /// control), e.g.
    /// `--topologies four-process,two-process,one-process --rates 10000`. Reports each
    /// topology's cycle latency, misses, the CPU time its processes used, where its
    /// microseconds go and its targets against the floor.
    #[arg(long, value_delimiter = ',', value_name = "NAME|FILE,...")]
    pub topologies: Vec<String>,
    /// Measure without a CPU wake-up latency request. By default the bench holds one of 0 µs
    /// (as cyclictest does, and as a real-time drive does) for every variant, and measures
    /// the floor, cyclictest and the one-core iceoryx2 chain also without one, to show what
    /// the request buys on this machine.
    #[arg(long)]
    pub no_cpu_latency_request: bool,
    /// The cyclictest (rt-tests) to run as a cross-check of the floor: a name on PATH or a
    /// path. When it is missing, that variant is skipped with one line saying why.
    #[arg(long, default_value = "cyclictest", value_name = "CMD")]
    pub cyclictest: String,
    /// Measure only these variants (comma-separated: floor, floor-repeat, cyclictest, hop,
    /// bare-chain, inprocess, uds, iceoryx2, iceoryx2+spin, topology); default all. The floor
    /// always runs: every comparison is against it. floor-repeat is the same timer measured
    /// a second time in every round: how far two measurements of one thing differ here.
    #[arg(long, value_delimiter = ',', value_name = "NAME,...")]
    pub variants: Vec<String>,
    /// Print bench.json on stdout instead of the Markdown table.
    #[arg(long)]
    pub json: bool,
}

/// A named placement of the four services on this 2-core machine.
pub fn placement(name: &str) -> Result<Placement> {
    let at = |core: usize, priority: u8| ServicePlacement {
        core: Some(core),
        priority: Some(priority),
    };
    // Priorities rise along the chain (see config::Placement::default).
    let (p, o, c, s) = match name {
        "one-core" => (1, 1, 1, 1),
        // Plant and observer share core 0, the controllers core 1: one crossing each way.
        "two-plus-two" => (0, 0, 1, 1),
        // Every hop crosses cores.
        "alternating" => (0, 1, 0, 1),
        other => {
            return Err(anyhow!(
                "unknown placement '{other}' (known: one-core, two-plus-two, alternating)"
            ))
        }
    };
    Ok(Placement {
        plant: at(p, 70),
        observer: at(o, 72),
        current_loop: at(c, 76),
        speed_loop: at(s, 74),
    })
}

fn node(p: ServicePlacement) -> NodeSpec {
    NodeSpec {
        core: p.core,
        priority: p.priority,
    }
}

/// One row of the report.
#[derive(Debug, Clone, Serialize)]
pub struct Row {
    /// floor, floor-repeat, cyclictest, hop, bare-chain, inprocess, uds, iceoryx2, iceoryx2+spin,
    /// topology.
    pub variant: String,
    /// Placement name ("-" for the single-thread variants, which run on the plant's core).
    pub placement: String,
    /// Whether a CPU wake-up latency request of 0 µs was held while it was measured.
    pub cpu_latency_request: bool,
    /// Without the request: the rounds whose core still polled when idle after the bench had
    /// let its idle governor settle (another process holds a request; see
    /// `drivelab_bench::idle`), so that they measured a request after all. 0 when fine.
    pub idle_still_polling_rounds: u32,
    /// Sample rate, Hz.
    pub rate_hz: f64,
    /// Samples measured.
    pub samples: u64,
    /// Cycle latency (floor: wake-up lateness; hop: notify → running; bare-chain: deadline →
    /// the last receiver running), µs.
    pub cycle_us: Percentiles,
    /// Plant wake-up lateness, µs.
    pub lateness_us: Percentiles,
    /// Deadline misses (floor: wake-ups later than Ts).
    pub misses: u64,
    /// Longest run of consecutive misses.
    pub longest_miss_run: u64,
    /// Misses per million samples.
    pub misses_per_million: f64,
    /// Misses per million that were not decided inside a stall (see [`Row::stalls`]): the
    /// misses of the machine running, a frozen one's left out. The floor and the iceoryx2
    /// variants; `None` for the others.
    pub misses_outside_stalls_per_million: Option<f64>,
    /// Budget verdict (chains only): cycle p99.9 < Ts and misses/M ≤ 2 × floor/M + 10.
    pub holds_budget: Option<bool>,
    /// cycle p99 / floor p99.
    pub p99_ratio_to_floor: Option<f64>,
    /// cycle p99 − floor p99, µs.
    pub p99_minus_floor_us: Option<f64>,
    /// cycle p50 − floor p50, µs.
    pub p50_minus_floor_us: Option<f64>,
    /// cycle p99 / Unix-socket chain p99 (same placement).
    pub p99_ratio_to_uds: Option<f64>,
    /// Histogram file (.hgrm) of the cycle latency.
    pub hgrm: String,
    /// CPU time (user + system) of the drive's processes per simulated second, s/s, set-up
    /// and shutdown included (iceoryx2 variants and the Unix-socket chain).
    pub cpu_s_per_s: Option<f64>,
    /// Voluntary context switches (waits, so wake-ups) of the drive's processes per sample,
    /// set-up and shutdown included (iceoryx2 variants and the Unix-socket chain).
    pub waits_per_sample: Option<f64>,
    /// Each process's CPU time (user + system) per sample over its run, µs, by process name
    /// (iceoryx2 variants; set-up left out, warm-up included): beside the stages' own
    /// execution, what the kernel's wake-ups and context switches cost it on this machine.
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub cpu_us_per_sample_by_process: BTreeMap<String, f64>,
    /// Involuntary context switches (preemptions) of the drive's processes per sample over
    /// their runs (iceoryx2 variants): a stage preempted by the next one it woke is switched
    /// back in.
    pub preemptions_per_sample: Option<f64>,
    /// System calls per sample that the variant's loops made at drivelab's own call sites:
    /// sleeps, futex waits and wakes, socket sends and receives (not the calls iceoryx2
    /// makes itself; none counted for cyclictest and the hop), set-up and shutdown included.
    pub syscalls_per_sample: Option<f64>,
    /// The floor: its thread's time on the CPU per wake-up, µs (the kernel's timer path
    /// included): what the timer alone costs the chain's core every sample.
    pub cpu_per_wakeup_us: Option<f64>,
    /// Where the cycle's microseconds go (iceoryx2 variants, all rounds merged).
    pub budget: Option<crate::budget::Budget>,
    /// The stalls of the floor's or the plant's wake-ups, half a millisecond late or later,
    /// over all rounds (the floor and the iceoryx2 variants), and how many consecutive ones (within a round) end on a host's
    /// 100 ms throttling grid (docs/architecture.md, "Stalls that are the host's").
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stalls: Option<drivelab_runtime::timing::StallReport>,
    /// Each interleaved round's own figures, in the order the rounds ran (the percentiles
    /// above are of all rounds merged).
    pub rounds: Vec<RoundFigures>,
    /// The floor: its misses per million had every deadline been due d µs sooner, for d = 0,
    /// 1, ... [`SOONER_MAX_US`] (index d; entry 0 is the floor's own misses, to the
    /// histogram's resolution). What this machine's timer tail alone gives a chain that
    /// costs d µs per sample and has no tail of its own.
    pub misses_pm_if_sooner_us: Option<Vec<f64>>,
    /// The floor: its lateness at every deadline, per round (not written to bench.json), for
    /// [`Targets::misses_floor_predicts_catching_up`].
    #[serde(skip)]
    pub deadline_lateness: Vec<drivelab_bench::catch_up::DeadlineLateness>,
}

/// The largest shift of [`Row::misses_pm_if_sooner_us`], µs.
pub const SOONER_MAX_US: u32 = 40;

/// [`Row::misses_pm_if_sooner_us`] of a floor whose deadline lateness is `cycle`, at a
/// period of `ts_ns`.
fn misses_pm_if_sooner(cycle: &LatencyHist, ts_ns: u64) -> Vec<f64> {
    (0..=SOONER_MAX_US)
        .map(|d| {
            let above = cycle.count_above_ns(ts_ns.saturating_sub(u64::from(d) * 1000));
            per_million(above, cycle.len())
        })
        .collect()
}

/// `curve` (per-µs values from 0) at `d` µs, linear between the whole µs, clamped to its ends.
fn at_shift(curve: &[f64], d: f64) -> Option<f64> {
    let last = curve.len().checked_sub(1)?;
    let d = d.clamp(0.0, last as f64);
    let i = d.floor() as usize;
    let j = (i + 1).min(last);
    Some(curve[i] + (curve[j] - curve[i]) * (d - i as f64))
}

/// One interleaved round of one variant.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct RoundFigures {
    /// Cycle latency (floor: wake-up lateness) p50, µs.
    pub p50_us: f64,
    /// Cycle latency p99, µs.
    pub p99_us: f64,
    /// Misses per million samples of this round.
    pub misses_per_million: f64,
    /// Of them, those not decided inside a stall (the floor and the iceoryx2 variants).
    pub misses_outside_stalls_per_million: Option<f64>,
    /// The plant's (floor: the timer thread's) wake-up lateness p50, µs.
    pub wake_p50_us: f64,
    /// Its p99, µs.
    pub wake_p99_us: f64,
}

impl RoundFigures {
    fn of(m: &VariantResult) -> Self {
        let (p, w) = (m.cycle.percentiles(), m.lateness.percentiles());
        Self {
            p50_us: p.p50,
            p99_us: p.p99,
            misses_per_million: per_million(m.misses.misses, m.samples),
            misses_outside_stalls_per_million: outside_stalls_pm(m),
            wake_p50_us: w.p50,
            wake_p99_us: w.p99,
        }
    }
}

/// Misses per million of `m` not decided inside a stall; `None` where stalls are not logged.
fn outside_stalls_pm(m: &VariantResult) -> Option<f64> {
    let st = m.stalls.as_ref()?;
    Some(per_million(
        m.misses.misses.saturating_sub(st.misses),
        m.samples,
    ))
}

fn per_million(n: u64, of: u64) -> f64 {
    if of == 0 {
        0.0
    } else {
        n as f64 * 1e6 / of as f64
    }
}

fn scenario_at(base: &Scenario, hz: f64, seconds: f64, pl: Placement) -> Result<Scenario> {
    let mut sc = base.clone();
    sc.rates.sample_hz = hz;
    // Keep the speed loop at 1 kHz and the controller timing legal at every rate; the bench
    // measures timing, not control quality.
    sc.rates.speed_divider = ((hz / 1000.0).round() as u32).max(1);
    let ts = 1.0 / hz;
    sc.observer.speed_filter_tau_s = sc.observer.speed_filter_tau_s.max(ts);
    sc.current_loop.tau_c_s = sc.current_loop.tau_c_s.max(2.0 * ts);
    sc.duration_s = seconds;
    sc.placement = pl;
    sc.validate()
        .map_err(|e| anyhow!("bench scenario at {hz} Hz: {e}"))?;
    Ok(sc)
}

fn row(job: &Job, hz: f64, m: &VariantResult, hgrm: &Path) -> Row {
    Row {
        variant: job.variant.into(),
        placement: job.placement.clone(),
        cpu_latency_request: job.request,
        idle_still_polling_rounds: 0,
        rate_hz: hz,
        samples: m.samples,
        cycle_us: m.cycle.percentiles(),
        lateness_us: m.lateness.percentiles(),
        misses: m.misses.misses,
        longest_miss_run: m.misses.longest_run,
        misses_per_million: per_million(m.misses.misses, m.samples),
        misses_outside_stalls_per_million: outside_stalls_pm(m),
        holds_budget: None,
        p99_ratio_to_floor: None,
        p99_minus_floor_us: None,
        p50_minus_floor_us: None,
        p99_ratio_to_uds: None,
        hgrm: hgrm
            .file_name()
            .unwrap_or_default()
            .to_string_lossy()
            .into_owned(),
        cpu_s_per_s: None,
        budget: None,
        stalls: m.stalls.clone(),
        rounds: Vec::new(),
        waits_per_sample: None,
        cpu_us_per_sample_by_process: BTreeMap::new(),
        preemptions_per_sample: None,
        syscalls_per_sample: m.syscalls.map(|c| c as f64 / m.samples.max(1) as f64),
        cpu_per_wakeup_us: m
            .cpu_run_ns
            .map(|ns| ns as f64 * 1e-3 / m.lateness.len().max(1) as f64),
        misses_pm_if_sooner_us: (job.variant == "floor")
            .then(|| misses_pm_if_sooner(&m.cycle, (1e9 / hz).round() as u64)),
        deadline_lateness: m.deadline_lateness.clone(),
    }
}

/// What each process of a chain costs the CPU per sample, against the sample period: the
/// data that says why a chain that needs most of its core cannot catch up after a stall.
fn cpu_per_sample_line(r: &Row) -> Option<String> {
    if r.cpu_us_per_sample_by_process.is_empty() {
        return None;
    }
    let parts: Vec<String> = r
        .cpu_us_per_sample_by_process
        .iter()
        .map(|(p, us)| format!("{p} {us:.1} µs"))
        .collect();
    let total: f64 = r.cpu_us_per_sample_by_process.values().sum();
    let ts_us = 1e6 / r.rate_hz;
    Some(format!(
        "CPU per sample, {} {} at {} kHz: {}; {:.1} µs of the {:.1} µs sample period ({:.0} %), with {:.2} preemptions a sample (user and kernel time from each process's run start, set-up left out, warm-up in: beside the stages' execution, each wake-up and context switch costs kernel time; what is left of the core is what the chain has to catch up after a stall).",
        r.variant,
        r.placement,
        r.rate_hz / 1000.0,
        parts.join(", "),
        total,
        ts_us,
        100.0 * total / ts_us,
        r.preemptions_per_sample.unwrap_or(0.0),
    ))
}

/// One variant of the bench.
#[derive(Debug, Clone)]
struct Job {
    /// floor, cyclictest, inprocess, uds, iceoryx2, iceoryx2+spin, topology.
    variant: &'static str,
    /// Placement or topology name ("-" for none).
    placement: String,
    /// Measured under a CPU wake-up latency request of 0 µs.
    request: bool,
}

impl Job {
    fn new(variant: &'static str, placement: &str, request: bool) -> Self {
        Self {
            variant,
            placement: placement.into(),
            request,
        }
    }

    /// File and folder tag at `hz`.
    fn tag(&self, hz: f64) -> String {
        let p = match self.variant {
            "floor" | "floor-repeat" | "cyclictest" | "inprocess" | "hop" | "bare-chain" => "core1",
            _ => &self.placement,
        };
        let req = if self.request { "" } else { "-norequest" };
        format!(
            "{}-{p}-{}hz{req}",
            self.variant.replace('+', "-"),
            hz as u64
        )
    }
}

/// What an iceoryx2 run adds to its variant: every histogram the drive wrote (by key, as in
/// `summary.json → latency_us`), its processes' CPU time and its topology.
struct DriveRun {
    result: VariantResult,
    cpu_s: f64,
    /// Voluntary context switches (waits) of the drive's processes.
    switches: u64,
    /// Each process's CPU time, s, and involuntary context switches over its run (set-up
    /// left out), by process name.
    by_process: BTreeMap<String, RunUsage>,
    hists: BTreeMap<String, LatencyHist>,
    topology: TopologyPlan,
}

/// A process's CPU time, s, and its preemptions over its run (`run_*` in its stats.json).
#[derive(Debug, Clone, Copy, Default)]
struct RunUsage {
    cpu_s: f64,
    preemptions: u64,
}

/// What a process's stats.json says of its cost (each process counted once).
struct ProcessUsage {
    /// CPU time from its start, s.
    cpu_s: f64,
    /// Voluntary context switches (waits) from its start.
    waits: u64,
    /// System calls at drivelab's own call sites, if it counted them.
    syscalls: Option<u64>,
    run: RunUsage,
}

/// Runs the iceoryx2 chain through the real launcher (in `topology`, if given) and reads
/// its histograms and its processes' CPU time back.
fn run_iceoryx2(sc: &Scenario, out: &Path, bus: &str, topology: Option<&str>) -> Result<DriveRun> {
    // The scenario goes beside the run folder: a run refuses a folder of other files.
    let name = out
        .file_name()
        .ok_or_else(|| anyhow!("{}: not a folder name", out.display()))?;
    let dir = out.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir)?;
    let file = dir.join(format!("{}.scenario.in.toml", name.to_string_lossy()));
    drivelab_runtime::files::write(&file, toml::to_string(sc)?)?;
    let o = RunOptions {
        scenario: file.display().to_string(),
        clock: Clock::Realtime,
        duration_s: None,
        out: Some(out.to_path_buf()),
        bus: Some(bus.into()),
        no_plots: true,
        restart: launcher::Restart::Never,
        lockstep_restart_ms: drivelab_runtime::inject::RESTART_DEFAULT_MS,
        topology: topology.map(String::from),
        ..RunOptions::default()
    };
    let r = launcher::run(&o)?;
    // CPU time: every stage's statistics carry its process's total; count each process once.
    let mut cpu = BTreeMap::new();
    let mut hists = BTreeMap::new();
    for e in std::fs::read_dir(out)?.flatten() {
        let p = e.path();
        let name = p
            .file_name()
            .unwrap_or_default()
            .to_string_lossy()
            .into_owned();
        if name.ends_with(".stats.json") {
            let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&p)?)?;
            if let (Some(pr), Some(c)) = (v["process"].as_str(), v["process_cpu_s"].as_f64()) {
                cpu.insert(
                    pr.to_string(),
                    ProcessUsage {
                        cpu_s: c,
                        waits: v["process_context_switches"]["voluntary"]
                            .as_u64()
                            .unwrap_or(0),
                        syscalls: v["process_syscalls"].as_u64(),
                        run: RunUsage {
                            cpu_s: v["run_cpu_s"].as_f64().unwrap_or(0.0),
                            preemptions: v["run_context_switches"]["involuntary"]
                                .as_u64()
                                .unwrap_or(0),
                        },
                    },
                );
            }
        } else if let Some(key) = name.strip_suffix(".hdr") {
            hists.insert(key.to_string(), LatencyHist::read_v2("hist", &p)?);
        }
    }
    let topology: TopologyPlan = serde_json::from_slice(&std::fs::read(out.join("topology.json"))?)
        .context("the run's topology.json")?;
    let cycle = LatencyHist::read_v2("cycle", &out.join("cycle.hdr"))?;
    let lateness = LatencyHist::read_v2("lateness", &out.join("plant.lateness.hdr"))?;
    let plant = &r.summary["counters"]["plant"];
    let mut misses = drivelab_runtime::timing::MissCounter::default();
    misses.misses = plant["deadline_misses"].as_u64().unwrap_or(0);
    misses.longest_run = plant["longest_miss_run"].as_u64().unwrap_or(0);
    Ok(DriveRun {
        result: VariantResult {
            cycle,
            lateness,
            samples: r.summary["samples"].as_u64().unwrap_or(0),
            misses,
            cpu_run_ns: None,
            deadline_lateness: Vec::new(),
            // Every process's, or none when one did not say.
            syscalls: cpu.values().map(|c| c.syscalls).sum(),
            stalls: serde_json::from_value(r.summary["timing"]["stalls"].clone()).ok(),
        },
        cpu_s: cpu.values().map(|c| c.cpu_s).sum(),
        switches: cpu.values().map(|c| c.waits).sum(),
        by_process: cpu.into_iter().map(|(p, c)| (p, c.run)).collect(),
        hists,
        topology,
    })
}

/// Holds or releases the bench's own CPU wake-up latency request so that it matches what
/// the next variant needs. The request is system-wide while held, so a variant measured
/// without one must not run while the bench holds it. A request that cannot be made is
/// reported once; the variants then run without it (and say so in their rows).
struct RequestHolder {
    held: Option<drivelab_runtime::rt::CpuLatencyRequest>,
    failed: bool,
}

impl RequestHolder {
    /// Whether a request is held after setting it to `want`.
    fn set(&mut self, want: bool) -> bool {
        if !want {
            self.held = None;
        } else if self.held.is_none() && !self.failed {
            match drivelab_runtime::rt::CpuLatencyRequest::hold(0) {
                Ok(r) => self.held = Some(r),
                Err(e) => {
                    self.failed = true;
                    crate::errln!(
                        "drivelab: warning: bench without a CPU wake-up latency request ({}: {e})",
                        drivelab_runtime::rt::CPU_DMA_LATENCY
                    );
                }
            }
        }
        self.held.is_some()
    }
}

/// Lets the idle governor of `node`'s core settle before a variant measured without the CPU
/// wake-up latency request ([`drivelab_bench::idle`]). True when the core still polls (a
/// one-line warning says so).
fn settle_idle(node: &NodeSpec) -> Result<bool> {
    let Some(cpu) = node.core else {
        return Ok(false);
    };
    match drivelab_bench::idle::settle(cpu)? {
        Settle::StillPolling => {
            crate::errln!(
                "drivelab: warning: bench: cpu {cpu} still polls when idle after {} sleeps of {} ms: another process holds a CPU wake-up latency request, so this round without one measures a request",
                drivelab_bench::idle::MAX_SLEEPS,
                drivelab_bench::idle::SLEEP.as_millis()
            );
            Ok(true)
        }
        Settle::NoPollState | Settle::Settled { .. } => Ok(false),
    }
}

/// The variants of one rate, in the order each round runs them.
fn jobs(a: &BenchArgs, placements: &[String], cyclictest: bool) -> Vec<Job> {
    let req = !a.no_cpu_latency_request;
    // Without the request too: the floor, cyclictest and the default chain (one core).
    let both = |v: &'static str, p: &str| -> Vec<Job> {
        let mut j = vec![Job::new(v, p, req)];
        if req {
            j.push(Job::new(v, p, false));
        }
        j
    };
    if !a.topologies.is_empty() {
        // Topologies compare with each other and the floor, all under the same request; the
        // floor's repeat last, the control of their targets.
        let mut jobs = vec![Job::new("floor", "-", req)];
        jobs.extend(
            a.topologies
                .iter()
                .map(|t| Job::new("topology", &topology_name(t), req)),
        );
        jobs.push(Job::new("floor-repeat", "-", req));
        return jobs;
    }
    let mut jobs = both("floor", "-");
    if cyclictest {
        jobs.extend(both("cyclictest", "-"));
    }
    // The floor again, after a variant without the request as cyclictest is: the same
    // timer twice in the same rounds, the run's resolution (FloorRepeat).
    jobs.push(Job::new("floor-repeat", "-", req));
    jobs.push(Job::new("hop", "-", req));
    jobs.push(Job::new("bare-chain", "-", req));
    jobs.push(Job::new("inprocess", "-", req));
    for p in placements {
        jobs.push(Job::new("uds", p, req));
        if p == "one-core" {
            jobs.extend(both("iceoryx2", p));
        } else {
            jobs.push(Job::new("iceoryx2", p, req));
        }
        if a.spin_us > 0.0 && p == "one-core" {
            jobs.push(Job::new("iceoryx2+spin", p, req));
        }
    }
    jobs
}

/// A topology is shown (and filed) by its name: a file's stem.
fn topology_name(t: &str) -> String {
    Path::new(t)
        .file_stem()
        .map_or(t.to_string(), |s| s.to_string_lossy().into_owned())
}

/// The floor against cyclictest in the same run: both measure a timer thread's wake-up
/// lateness on the same core, so they should agree (within [`CYCLICTEST_AGREEMENT_US`]).
#[derive(Debug, Clone, Serialize)]
pub struct CrossCheck {
    /// Sample rate, Hz.
    pub rate_hz: f64,
    /// Both measured under the CPU wake-up latency request.
    pub cpu_latency_request: bool,
    /// floor p50 − cyclictest p50 of the wake-ups' lateness, µs.
    pub p50_diff_us: f64,
    /// floor p99 − cyclictest p99 of the wake-ups' lateness, µs.
    pub p99_diff_us: f64,
    /// Both differences within the agreement.
    pub agrees: bool,
    /// The same differences round by round (each round's floor against the same round's
    /// cyclictest; at least two rounds).
    pub by_round: Option<CrossRounds>,
    /// The core cyclictest's main thread ran on, off the measured core (None: cyclictest's
    /// default layout, its main thread on the measured core; drivelab_bench::cyclictest).
    pub cyclictest_main_thread_core: Option<usize>,
    /// floor − cyclictest at p50 in the slots where each woke at its fastest (see
    /// [`FastestSlots`]): on a timer with two speeds the merged p50s differ by the slots'
    /// draw. `None` with a single round.
    pub fastest_slots: Option<CrossFastest>,
}

/// [`CrossCheck::fastest_slots`]: the floor's slots and cyclictest's, each picked by its own
/// wake-up p50 within [`FASTEST_SLOT_WITHIN_US`] of its fastest slot's.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CrossFastest {
    /// Slots picked of the floor's.
    pub floor_slots: usize,
    /// Slots picked of cyclictest's.
    pub cyclictest_slots: usize,
    /// Slots of each.
    pub rounds: usize,
    /// Median of the floor's picked slots' wake-up p50 − median of cyclictest's, µs.
    pub p50_diff_us: f64,
    /// Within ±[`CYCLICTEST_AGREEMENT_US`]; None (not judged) when fewer than
    /// [`FASTEST_SLOTS_MIN`] slots were picked on either side.
    pub agrees: Option<bool>,
}

impl CrossFastest {
    fn of(floor: &[RoundFigures], cyclictest: &[RoundFigures]) -> Option<Self> {
        let picks = FastestPicks::of(floor, cyclictest, |r| r.wake_p50_us)?;
        Some(Self {
            floor_slots: picks.a_slots,
            cyclictest_slots: picks.b_slots,
            rounds: picks.rounds,
            p50_diff_us: picks.diff,
            agrees: picks.judge(|d| d.abs() <= CYCLICTEST_AGREEMENT_US),
        })
    }

    /// The report's clause, given only when some slot was left out (otherwise it would
    /// repeat the rounds' medians).
    fn clause(&self) -> String {
        if !picked_some([self.floor_slots, self.cyclictest_slots], self.rounds) {
            return String::new();
        }
        format!(
            "; in the slots where each woke at its fastest (the floor's {} and cyclictest's {} of {}): p50 {:+.1} µs ({})",
            self.floor_slots,
            self.cyclictest_slots,
            self.rounds,
            self.p50_diff_us,
            judged_words(self.agrees, "agrees", "disagrees")
        )
    }
}

/// [`CrossCheck`] per interleaved round.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CrossRounds {
    /// floor p50 − cyclictest p50 of each round's wake-ups, µs.
    pub p50_diff_us: Vec<f64>,
    /// floor p99 − cyclictest p99 of each round's wake-ups, µs.
    pub p99_diff_us: Vec<f64>,
    /// Median over the rounds of `p50_diff_us`, µs.
    pub p50_median_us: f64,
    /// Median over the rounds of `p99_diff_us`, µs.
    pub p99_median_us: f64,
    /// Rounds in which both differences are within the agreement.
    pub rounds_agreeing: usize,
}

impl CrossRounds {
    /// The report's clause for these rounds, after a floor − other comparison.
    fn clause(&self) -> String {
        format!(
            "; round by round ({}): p50 median {:+.1} µs, p99 median {:+.1} µs, both within ±{CYCLICTEST_AGREEMENT_US} µs in {} of them",
            self.p50_diff_us.len(),
            self.p50_median_us,
            self.p99_median_us,
            self.rounds_agreeing
        )
    }

    fn of(floor: &[RoundFigures], cyclictest: &[RoundFigures]) -> Option<Self> {
        let p50 = round_diffs(floor, cyclictest, |r| r.wake_p50_us)?;
        let p99 = round_diffs(floor, cyclictest, |r| r.wake_p99_us)?;
        let within = |d: f64| d.abs() <= CYCLICTEST_AGREEMENT_US;
        Some(Self {
            p50_median_us: median(&p50),
            p99_median_us: median(&p99),
            rounds_agreeing: p50
                .iter()
                .zip(&p99)
                .filter(|&(&a, &b)| within(a) && within(b))
                .count(),
            p50_diff_us: p50,
            p99_diff_us: p99,
        })
    }
}

/// How close the floor must be to cyclictest at p50 and p99, µs.
pub const CYCLICTEST_AGREEMENT_US: f64 = 3.0;

/// The floor against its own repeat (`floor-repeat`: the same timer, the same core, the same
/// request, measured again in every round): two measurements of one thing, so whatever they
/// differ by is this machine's noise in this run. A difference between two variants (the
/// floor and cyclictest, a chain and its target) no larger than this one cannot be told
/// from that noise.
#[derive(Debug, Clone, Serialize)]
pub struct FloorRepeat {
    /// Sample rate, Hz.
    pub rate_hz: f64,
    /// Both measured under the CPU wake-up latency request.
    pub cpu_latency_request: bool,
    /// floor p50 − repeat p50 of the wake-ups' lateness, µs.
    pub p50_diff_us: f64,
    /// floor p99 − repeat p99 of the wake-ups' lateness, µs.
    pub p99_diff_us: f64,
    /// floor p50 − repeat p50 of the lateness at every deadline (what the chains' targets
    /// compare with), µs.
    pub deadline_p50_diff_us: f64,
    /// floor p99 − repeat p99 of the lateness at every deadline, µs.
    pub deadline_p99_diff_us: f64,
    /// Median over the rounds of floor p99 − repeat p99 at every deadline, µs (at least two
    /// rounds): what the chains' round-by-round p99 targets compare with.
    pub deadline_p99_median_round_diff_us: Option<f64>,
    /// The floor's deadline misses per million.
    pub misses_per_million: f64,
    /// The repeat's deadline misses per million.
    pub repeat_misses_per_million: f64,
    /// Both differences within [`CYCLICTEST_AGREEMENT_US`]: whether this run could resolve
    /// the floor's agreement with cyclictest at all.
    pub within_agreement: bool,
    /// The same differences round by round (at least two rounds).
    pub by_round: Option<CrossRounds>,
}

/// [`FloorRepeat`] for every rate and request at which both were measured.
fn floor_repeats(rows: &[Row]) -> Vec<FloorRepeat> {
    rows.iter()
        .filter(|r| r.variant == "floor-repeat")
        .filter_map(|rep| {
            let floor = rows.iter().find(|f| {
                f.variant == "floor"
                    && f.rate_hz == rep.rate_hz
                    && f.cpu_latency_request == rep.cpu_latency_request
            })?;
            let (d50, d99) = (
                floor.lateness_us.p50 - rep.lateness_us.p50,
                floor.lateness_us.p99 - rep.lateness_us.p99,
            );
            Some(FloorRepeat {
                rate_hz: rep.rate_hz,
                cpu_latency_request: rep.cpu_latency_request,
                p50_diff_us: d50,
                p99_diff_us: d99,
                deadline_p50_diff_us: floor.cycle_us.p50 - rep.cycle_us.p50,
                deadline_p99_diff_us: floor.cycle_us.p99 - rep.cycle_us.p99,
                deadline_p99_median_round_diff_us: round_diffs(&floor.rounds, &rep.rounds, |r| {
                    r.p99_us
                })
                .map(|d| median(&d)),
                misses_per_million: floor.misses_per_million,
                repeat_misses_per_million: rep.misses_per_million,
                within_agreement: d50.abs() <= CYCLICTEST_AGREEMENT_US
                    && d99.abs() <= CYCLICTEST_AGREEMENT_US,
                by_round: CrossRounds::of(&floor.rounds, &rep.rounds),
            })
        })
        .collect()
}

/// One line of the report: the floor against its repeat.
fn floor_repeat_line(f: &FloorRepeat) -> String {
    format!(
        "Floor − floor-repeat at {} kHz ({}), wake-up lateness: p50 {:+.1} µs, p99 {:+.1} µs ({} ±{CYCLICTEST_AGREEMENT_US} µs){}; at every deadline (what the chains' targets compare with): p50 {:+.1} µs, p99 {:+.1} µs{}; misses per million {:.0} (floor) against {:.0} (repeat). The same timer measured twice in the same rounds: differences between variants of this size are this run's noise.",
        f.rate_hz / 1000.0,
        request_words(f.cpu_latency_request),
        f.p50_diff_us,
        f.p99_diff_us,
        if f.within_agreement { "within" } else { "NOT within" },
        f.by_round.as_ref().map_or(String::new(), CrossRounds::clause),
        f.deadline_p50_diff_us,
        f.deadline_p99_diff_us,
        f.deadline_p99_median_round_diff_us
            .map_or(String::new(), |d| format!(" (median round {d:+.1})")),
        f.misses_per_million,
        f.repeat_misses_per_million,
    )
}

/// Verdicts and ratios of one rate's rows against the floor (measured under the same CPU
/// latency request) and the Unix-socket chain (same placement) of the same run; the floor
/// against cyclictest.
/// `cyclictest_main_core`: where cyclictest's main thread ran (reported with the check).
fn compare(rows: &mut [Row], hz: f64, cyclictest_main_core: Option<usize>) -> Vec<CrossCheck> {
    let ts_us = 1e6 / hz;
    // The chains compare with the floor's every deadline (`cycle_us`), cyclictest with its
    // wake-ups (`lateness_us`: after a late one the passed deadlines are skipped, as
    // cyclictest skips them).
    let floor_of = |rows: &[Row], req: bool| {
        rows.iter()
            .find(|r| r.variant == "floor" && r.cpu_latency_request == req)
            .or_else(|| rows.iter().find(|r| r.variant == "floor"))
            .map(|r| {
                (
                    r.cycle_us.p50,
                    r.cycle_us.p99,
                    r.misses_per_million,
                    r.lateness_us,
                    r.rounds.clone(),
                )
            })
    };
    // The Unix-socket chains' rows, taken out before the loop that changes `rows`.
    let uds_rows: Vec<Row> = rows
        .iter()
        .filter(|r| r.variant == "uds")
        .cloned()
        .collect();
    let mut checks = Vec::new();
    for i in 0..rows.len() {
        let Some((f50, f99, f_pm, wake, floor_rounds)) =
            floor_of(rows, rows[i].cpu_latency_request)
        else {
            continue;
        };
        let r = &mut rows[i];
        if matches!(r.variant.as_str(), "floor" | "hop") {
            continue;
        }
        if r.variant == "cyclictest" {
            let (d50, d99) = (wake.p50 - r.cycle_us.p50, wake.p99 - r.cycle_us.p99);
            checks.push(CrossCheck {
                rate_hz: hz,
                cpu_latency_request: r.cpu_latency_request,
                p50_diff_us: d50,
                p99_diff_us: d99,
                agrees: d50.abs() <= CYCLICTEST_AGREEMENT_US
                    && d99.abs() <= CYCLICTEST_AGREEMENT_US,
                by_round: CrossRounds::of(&floor_rounds, &r.rounds),
                fastest_slots: CrossFastest::of(&floor_rounds, &r.rounds),
                cyclictest_main_thread_core: cyclictest_main_core,
            });
            continue;
        }
        // The floor's repeat is measured against the floor as the chains are (the control of
        // their targets), but it is no chain: no budget verdict.
        if r.variant != "floor-repeat" {
            r.holds_budget =
                Some(r.cycle_us.p999 < ts_us && r.misses_per_million <= misses_bound(f_pm));
        }
        r.p99_ratio_to_floor = Some(r.cycle_us.p99 / f99.max(1e-3));
        r.p99_minus_floor_us = Some(r.cycle_us.p99 - f99);
        r.p50_minus_floor_us = Some(r.cycle_us.p50 - f50);
        if r.variant.starts_with("iceoryx2") {
            r.p99_ratio_to_uds = uds_rows
                .iter()
                .find(|u| is_uds_of(u, r))
                .map(|u| r.cycle_us.p99 / u.cycle_us.p99.max(1e-3));
        }
    }
    checks
}

/// A chain's latency targets against the bare timer of the same run: p50 at most
/// [`TARGET_P50_US`] and p99 at most [`TARGET_P99_US`] above the floor's, misses per million
/// at most twice the floor's + 10, and p99 at most [`TARGET_UDS_RATIO`] × the Unix-socket
/// chain's (the same four processes over sockets). `None` fields: not measured in this run.
#[derive(Debug, Clone, Serialize)]
pub struct Targets {
    /// The chain: "iceoryx2 one-core" (the default chain), or "topology NAME" when the bench
    /// compared topologies; or [`CONTROL`], the floor's repeat held to the same targets.
    pub chain: String,
    /// Sample rate, Hz.
    pub rate_hz: f64,
    /// Measured under the CPU wake-up latency request (the chain and its floor).
    pub cpu_latency_request: bool,
    /// Cycle p50 − floor p50, µs.
    pub p50_minus_floor_us: f64,
    /// Within [`TARGET_P50_US`].
    pub p50_met: bool,
    /// Cycle p99 − floor p99, µs.
    pub p99_minus_floor_us: f64,
    /// Within [`TARGET_P99_US`].
    pub p99_met: bool,
    /// The chain's misses per million.
    pub misses_per_million: f64,
    /// Twice the floor's misses per million + 10.
    pub misses_bound: f64,
    /// Within the bound.
    pub misses_met: bool,
    /// Cycle p99 / the Unix-socket chain's (same placement).
    pub p99_ratio_to_uds: Option<f64>,
    /// Within [`TARGET_UDS_RATIO`].
    pub uds_met: Option<bool>,
    /// What each chain adds to the floor's p99, the iceoryx2 chain's over the Unix-socket
    /// chain's: (cycle p99 − floor p99) / (Unix-socket p99 − floor p99). The machine's own
    /// timer tail, which both chains share, left out of the ratio; `None` without the
    /// Unix-socket chain, or when it is not above the floor.
    pub p99_above_floor_ratio_to_uds: Option<f64>,
    /// The Unix-socket target's bound ([`TARGET_UDS_RATIO`] × the Unix-socket chain's p99)
    /// against the bare critical path's p99 of the same run (the timer and two futex
    /// wake-ups, no work), µs: where it is below, the target asks of the chain less than
    /// this machine's wake-ups alone took. `None` without both.
    pub uds_bound_against_bare: Option<UdsBound>,
    /// The misses per million the floor of the same run gives a chain that costs its p50
    /// above the floor's at every deadline and has no tail of its own (the floor's deadline
    /// lateness above T_s − that cost): how many of the chain's misses this machine's timer
    /// tail accounts for. `None` when the floor's curve was not measured.
    pub misses_floor_predicts: Option<f64>,
    /// The same, with the chain catching up after each late wake-up: the floor's own
    /// wake-ups replayed with a chain that publishes its command its p50 above the floor's
    /// after each wake-up and, when it is behind, runs its samples back to back at its CPU
    /// time per sample less the timer's (`drivelab_bench::catch_up`). `None` without the
    /// chain's CPU time or the floor's lateness per deadline.
    pub misses_floor_predicts_catching_up: Option<CatchUp>,
    /// The same targets round by round, each round's chain against that round's floor (two
    /// or more rounds): how much of a verdict the machine's noise decides.
    pub by_round: Option<TargetRounds>,
    /// The Unix-socket target round by round, each round's chain against that round's
    /// Unix-socket chain. `None` without the Unix-socket chain or with a single round.
    pub uds_by_round: Option<UdsRounds>,
    /// The default chain's critical path bare, measured in the same run (the `bare-chain`
    /// variant: the timer and the same two futex wake-ups, no bus, no messages, no stage
    /// work): what this machine's wake-ups take of the distance to the floor, and what the
    /// chain adds to them. `None` when it was not measured, and for topologies.
    pub bare_chain: Option<BareChain>,
    /// The misses target with the stalls left out, the chain's and the floor's (see
    /// [`Row::misses_outside_stalls_per_million`]): whether the drive keeps its deadlines
    /// while the machine runs. Reported beside the target, which counts every miss. `None`
    /// where either was measured without a stall log.
    pub outside_stalls: Option<OutsideStalls>,
    /// The p50 target in the slots where the timer woke at its fastest, the chain's and the
    /// floor's each picked by their own timer wake-ups: on a machine whose timer changes
    /// speed from second to second, the slots' draw moves the merged p50s. `None` with a
    /// single round.
    pub fastest_slots: Option<FastestSlots>,
}

/// A slot (one variant's part of one round) is among a variant's fastest when its timer
/// wake-up p50 lies within this of the variant's fastest slot's, µs.
pub const FASTEST_SLOT_WITHIN_US: f64 = 2.0;

/// The fewest slots picked on each side for [`FastestSlots`] to judge the p50 target: the
/// median of one or two slots is those slots' own draw (a timer that drifted rather than
/// switched speed, or one quiet slot), not the speed's.
pub const FASTEST_SLOTS_MIN: usize = 3;

/// Whether `uds` is the Unix-socket chain that `chain` is compared with: the same placement
/// and CPU latency request (the socket chain is measured with the request held only, so a
/// chain without it has none).
fn is_uds_of(uds: &Row, chain: &Row) -> bool {
    uds.variant == "uds"
        && uds.placement == chain.placement
        && uds.cpu_latency_request == chain.cpu_latency_request
}

/// Two variants' fastest slots, each side's picked by its own timer wake-up p50 (within
/// [`FASTEST_SLOT_WITHIN_US`] of its fastest slot's): what [`FastestSlots`] and
/// [`CrossFastest`] compare.
struct FastestPicks {
    /// Slots picked of `a`'s.
    a_slots: usize,
    /// Slots picked of `b`'s.
    b_slots: usize,
    /// Slots of each.
    rounds: usize,
    /// Median of `value` over `a`'s picked slots − the same over `b`'s.
    diff: f64,
}

impl FastestPicks {
    /// `None` with fewer than two rounds on a side.
    fn of(
        a: &[RoundFigures],
        b: &[RoundFigures],
        value: impl Fn(&RoundFigures) -> f64,
    ) -> Option<Self> {
        if a.len() < 2 || b.len() < 2 {
            return None;
        }
        let picks = |v: &[RoundFigures]| -> Vec<f64> {
            let best = v
                .iter()
                .map(|r| r.wake_p50_us)
                .fold(f64::INFINITY, f64::min);
            v.iter()
                .filter(|r| r.wake_p50_us <= best + FASTEST_SLOT_WITHIN_US)
                .map(&value)
                .collect()
        };
        let (pa, pb) = (picks(a), picks(b));
        Some(Self {
            a_slots: pa.len(),
            b_slots: pb.len(),
            rounds: a.len().min(b.len()),
            diff: median(&pa) - median(&pb),
        })
    }

    /// `ok(diff)`, or None (not judged) with fewer than [`FASTEST_SLOTS_MIN`] slots on a side.
    fn judge(&self, ok: impl FnOnce(f64) -> bool) -> Option<bool> {
        (self.a_slots.min(self.b_slots) >= FASTEST_SLOTS_MIN).then(|| ok(self.diff))
    }
}

/// Whether some slot was left out of `slots` picks of `rounds` (otherwise a fastest-slot figure
/// is the rounds' median).
fn picked_some(slots: [usize; 2], rounds: usize) -> bool {
    slots.iter().any(|&n| n < rounds)
}

/// A fastest-slot verdict in words: `yes`, `no`, or why it was not judged.
fn judged_words(v: Option<bool>, yes: &str, no: &str) -> String {
    match v {
        Some(true) => yes.to_string(),
        Some(false) => no.to_string(),
        None => format!("not judged: fewer than {FASTEST_SLOTS_MIN} slots on a side"),
    }
}

/// [`Targets::fastest_slots`]. Some VMs' timers wake in one of two speeds that last seconds
/// each (the eleventh VM of docs/measurements.md: 7.3 or 14–20 µs at p50, switching within
/// one cyclictest run, with nothing in the guest to tell them apart), so each few-second slot
/// of the interleaved rounds gets one or the other, and "chain − floor" at p50 moves by the
/// difference with the draw. Here the chain's slots are picked by its plant's timer wake-up,
/// the floor's by its own, each within [`FASTEST_SLOT_WITHIN_US`] of the variant's fastest
/// slot; the medians of the picked slots' p50s are compared, and judged with at least
/// [`FASTEST_SLOTS_MIN`] on each side. On a steady machine every slot is picked and the figure
/// is the rounds' median.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FastestSlots {
    /// Slots picked of the chain's.
    pub chain_slots: usize,
    /// Slots picked of the floor's.
    pub floor_slots: usize,
    /// Slots of each.
    pub rounds: usize,
    /// The floor's slots' p50s, lowest and highest, µs.
    pub floor_p50_span_us: [f64; 2],
    /// Median of the picked chain slots' p50 − median of the picked floor slots' p50, µs.
    pub p50_minus_floor_us: f64,
    /// Within [`TARGET_P50_US`]; None (not judged) when fewer than [`FASTEST_SLOTS_MIN`]
    /// slots were picked on either side.
    pub p50_met: Option<bool>,
}

impl FastestSlots {
    fn of(chain: &[RoundFigures], floor: &[RoundFigures]) -> Option<Self> {
        let picks = FastestPicks::of(chain, floor, |r| r.p50_us)?;
        let lo = floor.iter().map(|r| r.p50_us).fold(f64::INFINITY, f64::min);
        let hi = floor
            .iter()
            .map(|r| r.p50_us)
            .fold(f64::NEG_INFINITY, f64::max);
        Some(Self {
            chain_slots: picks.a_slots,
            floor_slots: picks.b_slots,
            rounds: picks.rounds,
            floor_p50_span_us: [lo, hi],
            p50_minus_floor_us: picks.diff,
            p50_met: picks.judge(|d| d <= TARGET_P50_US),
        })
    }

    /// Whether some slot was left out (otherwise the figure is the rounds' median).
    fn picked_some(&self) -> bool {
        picked_some([self.chain_slots, self.floor_slots], self.rounds)
    }

    fn clause(&self) -> String {
        format!(
            " In the slots where the timer woke at its fastest (timer wake-up p50 within {FASTEST_SLOT_WITHIN_US} µs of the variant's fastest slot: the chain's {} and the floor's {} of {}; the floor's slots' p50s span {:.1} … {:.1} µs): p50 {:+.1} µs ({}).",
            self.chain_slots,
            self.floor_slots,
            self.rounds,
            self.floor_p50_span_us[0],
            self.floor_p50_span_us[1],
            self.p50_minus_floor_us,
            judged_words(self.p50_met, "met", "missed")
        )
    }
}

/// [`Targets::uds_bound_against_bare`].
#[derive(Debug, Clone, Serialize)]
pub struct UdsBound {
    /// [`TARGET_UDS_RATIO`] × the Unix-socket chain's p99, µs.
    pub bound_us: f64,
    /// The bound − the bare critical path's p99, µs.
    pub minus_bare_p99_us: f64,
}

/// [`Targets::outside_stalls`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct OutsideStalls {
    /// The chain's misses per million outside its stalls.
    pub misses_per_million: f64,
    /// Twice the floor's outside its own stalls + 10.
    pub misses_bound: f64,
    /// Within the bound.
    pub misses_met: bool,
    /// Rounds within their own floor's bound (two or more rounds that pair up).
    pub rounds_met: Option<usize>,
    /// Rounds in all.
    pub rounds: usize,
}

impl OutsideStalls {
    /// The chain's and the floor's misses per million outside their stalls, each with its
    /// rounds.
    fn of(
        (chain_pm, c): (Option<f64>, &[RoundFigures]),
        (floor_pm, f): (Option<f64>, &[RoundFigures]),
    ) -> Option<Self> {
        let pm = chain_pm?;
        let bound = misses_bound(floor_pm?);
        let rounds_met = (c.len() >= 2 && c.len() == f.len()).then(|| {
            c.iter()
                .zip(f)
                .filter(|(c, f)| {
                    match (
                        c.misses_outside_stalls_per_million,
                        f.misses_outside_stalls_per_million,
                    ) {
                        (Some(c), Some(f)) => c <= misses_bound(f),
                        _ => false,
                    }
                })
                .count()
        });
        Some(Self {
            misses_per_million: pm,
            misses_bound: bound,
            misses_met: pm <= bound,
            rounds_met,
            rounds: c.len(),
        })
    }
}

/// [`Targets::misses_floor_predicts_catching_up`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CatchUp {
    /// The chain's command after the plant's wake-up (its p50 − the floor's), µs.
    pub after_wake_up_us: f64,
    /// The chain's time per sample when it runs samples back to back: the CPU time of its
    /// processes per sample less the floor's per wake-up, µs.
    pub per_sample_us: f64,
    /// The modelled chain's misses per million.
    pub misses_per_million: f64,
}

impl CatchUp {
    /// `chain` (with its CPU time) modelled on `floor`'s deadlines; `None` when either
    /// figure is missing.
    fn of(chain: &Row, floor: &Row) -> Option<Self> {
        let ts_us = 1e6 / chain.rate_hz;
        Self::model(
            &floor.deadline_lateness,
            ts_us,
            chain.p50_minus_floor_us?,
            chain.cpu_s_per_s? * ts_us - floor.cpu_per_wakeup_us?,
        )
    }

    /// The chain's command `after_us` after each of the floor's wake-ups and `per_us` a
    /// sample when behind (both at least 0), over the floor's `rounds` (each its own
    /// start), at a sample time of `ts_us`; `None` without rounds.
    fn model(
        rounds: &[drivelab_bench::catch_up::DeadlineLateness],
        ts_us: f64,
        after_us: f64,
        per_us: f64,
    ) -> Option<Self> {
        if rounds.is_empty() {
            return None;
        }
        let (after_us, per_us) = (after_us.max(0.0), per_us.max(0.0));
        let ns = |us: f64| (us * 1e3).round() as u64;
        let (mut misses, mut n) = (0, 0);
        for round in rounds {
            misses += drivelab_bench::catch_up::misses(round, ns(ts_us), ns(after_us), ns(per_us));
            n += round.len() as u64;
        }
        Some(Self {
            after_wake_up_us: after_us,
            per_sample_us: per_us,
            misses_per_million: per_million(misses, n),
        })
    }
}

/// The bare chain against the floor, and the chain against the bare chain.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BareChain {
    /// Bare chain p50 − floor p50, µs.
    pub p50_minus_floor_us: f64,
    /// Bare chain p99 − floor p99, µs.
    pub p99_minus_floor_us: f64,
    /// Chain p50 − bare chain p50: what the bus, the messages and the stages add, µs.
    pub chain_p50_minus_bare_us: f64,
    /// Chain p99 − bare chain p99, µs.
    pub chain_p99_minus_bare_us: f64,
    /// Median over the rounds of the bare chain's p99 − that round's floor p99, µs (two or
    /// more rounds).
    pub p99_minus_floor_median_us: Option<f64>,
    /// Median over the rounds of the chain's p99 − that round's bare chain p99, µs.
    pub chain_p99_minus_bare_median_us: Option<f64>,
}

impl BareChain {
    /// `bare` against `floor`, and `chain` against `bare` (same rate and request).
    fn of(chain: &Row, bare: &Row, floor: &Row) -> Self {
        let p99 = |r: &RoundFigures| r.p99_us;
        let median_of =
            |a: &[RoundFigures], b: &[RoundFigures]| round_diffs(a, b, p99).map(|d| median(&d));
        Self {
            p50_minus_floor_us: bare.cycle_us.p50 - floor.cycle_us.p50,
            p99_minus_floor_us: bare.cycle_us.p99 - floor.cycle_us.p99,
            chain_p50_minus_bare_us: chain.cycle_us.p50 - bare.cycle_us.p50,
            chain_p99_minus_bare_us: chain.cycle_us.p99 - bare.cycle_us.p99,
            p99_minus_floor_median_us: median_of(&bare.rounds, &floor.rounds),
            chain_p99_minus_bare_median_us: median_of(&chain.rounds, &bare.rounds),
        }
    }
}

/// [`Targets`] per interleaved round.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TargetRounds {
    /// Cycle p50 − floor p50 of each round, µs.
    pub p50_minus_floor_us: Vec<f64>,
    /// Cycle p99 − floor p99 of each round, µs.
    pub p99_minus_floor_us: Vec<f64>,
    /// Median over the rounds of `p50_minus_floor_us`, µs: unlike the merged figure, not
    /// moved by a stall that hit one variant in one round.
    pub p50_median_us: f64,
    /// Median over the rounds of `p99_minus_floor_us`, µs.
    pub p99_median_us: f64,
    /// Whether `p99_median_us` is within [`TARGET_P99_US`]: the p99 target judged round by
    /// round, as the README's and docs/measurements.md's totals count it.
    pub p99_median_met: bool,
    /// Rounds that met the p50 target.
    pub p50_met: usize,
    /// Rounds that met the p99 target.
    pub p99_met: usize,
    /// Rounds whose misses were within twice that round's floor's + 10 per million.
    pub misses_met: usize,
}

/// [`Targets::uds_by_round`]: round i's chain against round i's Unix-socket chain, which ran
/// in the same interleaved pass.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct UdsRounds {
    /// Cycle p99 / the Unix-socket chain's cycle p99, of each round.
    pub p99_ratio: Vec<f64>,
    /// Median over the rounds of `p99_ratio`: unlike the merged figure, not decided by the
    /// one or two rounds that met a stall.
    pub p99_ratio_median: f64,
    /// Rounds within [`TARGET_UDS_RATIO`].
    pub met: usize,
}

impl UdsRounds {
    fn of(chain: &[RoundFigures], uds: &[RoundFigures]) -> Option<Self> {
        let r = round_pairs(chain, uds, |c, u| c.p99_us / u.p99_us)?;
        Some(Self {
            met: r.iter().filter(|x| **x <= TARGET_UDS_RATIO).count(),
            p99_ratio_median: median(&r),
            p99_ratio: r,
        })
    }
}

/// [`Targets::chain`] of the control: the floor's repeat, a "chain" that is the floor itself,
/// held to the chains' targets against the floor. It should meet every one; what it misses
/// in a run, that run's noise decides for the chains too.
pub const CONTROL: &str = "floor-repeat (control)";

/// Largest cycle p50 above the floor's that meets the target, µs.
pub const TARGET_P50_US: f64 = 10.0;
/// Largest cycle p99 above the floor's that meets the target, µs.
pub const TARGET_P99_US: f64 = 15.0;
/// Largest ratio of the iceoryx2 chain's p99 to the Unix-socket chain's that meets the target.
pub const TARGET_UDS_RATIO: f64 = 0.8;

/// The targets at each rate of `rows`, after [`compare`] filled in the differences: of the
/// default chain (iceoryx2 at its best placement, [`best_placement`]; under the request when it was measured both ways), and
/// of every topology when the bench compared topologies.
fn targets(rows: &[Row]) -> Vec<Targets> {
    let mut rates: Vec<f64> = Vec::new();
    for r in rows {
        if !rates.contains(&r.rate_hz) {
            rates.push(r.rate_hz);
        }
    }
    let mut goals = Vec::new();
    for hz in rates {
        let at_rate = || rows.iter().filter(move |r| r.rate_hz == hz);
        let default_chain = {
            let m: Vec<&Row> = at_rate().filter(|r| r.variant == "iceoryx2").collect();
            best_placement(&m, |r| r.cpu_latency_request, |r| r.cycle_us.p50)
                .map(|r| (format!("iceoryx2 {}", r.placement), *r))
        };
        let same_request = |variant: &'static str, chain: &Row| {
            at_rate().find(move |r| {
                r.variant == variant && r.cpu_latency_request == chain.cpu_latency_request
            })
        };
        let uds_of = |chain: &Row| at_rate().find(|r| is_uds_of(r, chain));
        let default_chain = default_chain.map(|(l, c)| {
            let others = Others {
                bare: same_request("bare-chain", c),
                uds: uds_of(c),
            };
            (l, c, others)
        });
        let chains = default_chain
            .into_iter()
            .chain(
                at_rate()
                    .filter(|r| r.variant == "topology")
                    .map(|r| (format!("topology {}", r.placement), r, Others::default())),
            )
            .chain(
                at_rate()
                    .filter(|r| r.variant == "floor-repeat")
                    .map(|r| (CONTROL.to_string(), r, Others::default())),
            );
        for (label, chain, others) in chains {
            if let Some(t) =
                same_request("floor", chain).and_then(|f| goal(label, chain, f, others))
            {
                goals.push(t);
            }
        }
    }
    goals
}

/// The default chain's row among `rows` (the iceoryx2 chain's rows of one rate, one per
/// placement and request): the best placement, the one with the lowest cycle p50, among
/// those measured under the request when it was measured both ways. Where the shipped
/// placements were all measured, that was one-core (docs/measurements.md).
fn best_placement<T>(
    rows: &[T],
    request: impl Fn(&T) -> bool,
    p50: impl Fn(&T) -> f64,
) -> Option<&T> {
    let held = rows.iter().any(&request);
    rows.iter()
        .filter(|r| !held || request(r))
        .min_by(|a, b| p50(a).total_cmp(&p50(b)))
}

/// The rows a chain's targets also look at, when they were measured in the same run.
#[derive(Default, Clone, Copy)]
struct Others<'a> {
    /// The bare chain (same rate and request).
    bare: Option<&'a Row>,
    /// The Unix-socket chain (same rate and placement).
    uds: Option<&'a Row>,
}

/// (chain − floor) / (other − floor): what one chain adds to the floor against what another
/// adds; `None` unless the other is above the floor.
fn above_floor_ratio(chain: f64, other: f64, floor: f64) -> Option<f64> {
    (other > floor).then(|| (chain - floor) / (other - floor))
}

/// `chain`'s targets against `floor` (same rate, same request), with the bare and the
/// Unix-socket chains of the same run when they were measured; `None` before [`compare`].
fn goal(chain_label: String, chain: &Row, floor: &Row, others: Others) -> Option<Targets> {
    let (d50, d99) = (chain.p50_minus_floor_us?, chain.p99_minus_floor_us?);
    let bound = misses_bound(floor.misses_per_million);
    Some(Targets {
        chain: chain_label,
        rate_hz: chain.rate_hz,
        cpu_latency_request: chain.cpu_latency_request,
        p50_minus_floor_us: d50,
        p50_met: d50 <= TARGET_P50_US,
        p99_minus_floor_us: d99,
        p99_met: d99 <= TARGET_P99_US,
        misses_per_million: chain.misses_per_million,
        misses_bound: bound,
        misses_met: chain.misses_per_million <= bound,
        p99_ratio_to_uds: chain.p99_ratio_to_uds,
        uds_met: chain.p99_ratio_to_uds.map(|u| u <= TARGET_UDS_RATIO),
        p99_above_floor_ratio_to_uds: others.uds.and_then(|u| {
            above_floor_ratio(chain.cycle_us.p99, u.cycle_us.p99, floor.cycle_us.p99)
        }),
        uds_bound_against_bare: others.uds.zip(others.bare).map(|(u, b)| {
            let bound_us = TARGET_UDS_RATIO * u.cycle_us.p99;
            UdsBound {
                bound_us,
                minus_bare_p99_us: bound_us - b.cycle_us.p99,
            }
        }),
        misses_floor_predicts: floor
            .misses_pm_if_sooner_us
            .as_deref()
            .and_then(|c| at_shift(c, d50)),
        misses_floor_predicts_catching_up: CatchUp::of(chain, floor),
        by_round: target_rounds(&chain.rounds, &floor.rounds),
        uds_by_round: others
            .uds
            .and_then(|u| UdsRounds::of(&chain.rounds, &u.rounds)),
        bare_chain: others.bare.map(|b| BareChain::of(chain, b, floor)),
        outside_stalls: OutsideStalls::of(
            (chain.misses_outside_stalls_per_million, &chain.rounds),
            (floor.misses_outside_stalls_per_million, &floor.rounds),
        ),
        fastest_slots: FastestSlots::of(&chain.rounds, &floor.rounds),
    })
}

/// The targets of each round: round i of the chain against round i of its floor, which ran
/// in the same interleaved pass. `None` for a single round or rounds that do not pair up.
fn target_rounds(chain: &[RoundFigures], floor: &[RoundFigures]) -> Option<TargetRounds> {
    let d50 = round_diffs(chain, floor, |r| r.p50_us)?;
    let d99 = round_diffs(chain, floor, |r| r.p99_us)?;
    Some(TargetRounds {
        p50_met: d50.iter().filter(|d| **d <= TARGET_P50_US).count(),
        p99_met: d99.iter().filter(|d| **d <= TARGET_P99_US).count(),
        misses_met: chain
            .iter()
            .zip(floor)
            .filter(|(c, f)| c.misses_per_million <= misses_bound(f.misses_per_million))
            .count(),
        p50_median_us: median(&d50),
        p99_median_us: median(&d99),
        p99_median_met: median(&d99) <= TARGET_P99_US,
        p50_minus_floor_us: d50,
        p99_minus_floor_us: d99,
    })
}

/// Round i of `a` minus round i of `b` in `figure`, for two or more rounds that pair up
/// (they ran in the same interleaved passes); `None` otherwise.
fn round_diffs(
    a: &[RoundFigures],
    b: &[RoundFigures],
    figure: fn(&RoundFigures) -> f64,
) -> Option<Vec<f64>> {
    round_pairs(a, b, |x, y| figure(x) - figure(y))
}

/// `op` of round i of `a` and round i of `b`, for two or more rounds that pair up; `None`
/// otherwise.
fn round_pairs(
    a: &[RoundFigures],
    b: &[RoundFigures],
    op: impl Fn(&RoundFigures, &RoundFigures) -> f64,
) -> Option<Vec<f64>> {
    (a.len() >= 2 && a.len() == b.len()).then(|| a.iter().zip(b).map(|(x, y)| op(x, y)).collect())
}

/// The most misses per million a chain may have against a floor with `floor_pm`: twice the
/// floor's + 10.
fn misses_bound(floor_pm: f64) -> f64 {
    2.0 * floor_pm + 10.0
}

/// The median of `v` (the mean of the middle two for an even count); NaN when empty.
fn median(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    match s.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => s[n / 2],
        n => (s[n / 2 - 1] + s[n / 2]) / 2.0,
    }
}

/// A target's verdict.
fn met(ok: bool) -> &'static str {
    if ok {
        "met"
    } else {
        "missed"
    }
}

/// The targets of every chain and rate as one table, before their lines: what a reader
/// looks for first (each line below gives the same verdicts with their figures and the
/// round-by-round detail).
fn targets_table(goals: &[Targets]) -> String {
    let mut s = format!(
        "| rate | chain | p50 − floor (≤ +{TARGET_P50_US} µs) | p99 − floor (≤ +{TARGET_P99_US} µs); median round | misses/M (≤ 2 × floor's + 10) | p99 / Unix socket's (≤ {TARGET_UDS_RATIO}) | in the fastest slots: p50 − floor |\n|---|---|---|---|---|---|---|\n"
    );
    for t in goals {
        let median_round = t.by_round.as_ref().map_or(String::new(), |r| {
            format!("; {:+.1} {}", r.p99_median_us, met(r.p99_median_met))
        });
        let uds = match (t.p99_ratio_to_uds, t.uds_met) {
            (Some(r), Some(ok)) => format!("{r:.3} {}", met(ok)),
            _ => "-".to_string(),
        };
        let fastest = t.fastest_slots.as_ref().map_or("-".to_string(), |f| {
            format!(
                "{:+.1} {} ({} and {} of {} slots)",
                f.p50_minus_floor_us,
                f.p50_met.map_or("not judged", met),
                f.chain_slots,
                f.floor_slots,
                f.rounds
            )
        });
        let _ = writeln!(
            s,
            "| {} kHz | {} | {:+.1} {} | {:+.1} {}{median_round} | {:.0} (bound {:.0}) {} | {uds} | {fastest} |",
            t.rate_hz / 1000.0,
            t.chain,
            t.p50_minus_floor_us,
            met(t.p50_met),
            t.p99_minus_floor_us,
            met(t.p99_met),
            t.misses_per_million,
            t.misses_bound,
            met(t.misses_met),
        );
    }
    s
}

/// One line of the report per chain and rate: the targets and whether each is met.
fn targets_line(t: &Targets) -> String {
    let above_floor = match t.p99_above_floor_ratio_to_uds {
        Some(r) => format!("; above the floor's p99, {r:.2} × what the Unix-socket chain adds"),
        None => String::new(),
    };
    let against_bare = match &t.uds_bound_against_bare {
        Some(b) => format!(
            "; the bound, {:.1} µs, lies {:.1} µs {} the bare critical path's p99 (timer and two futex wake-ups, no work)",
            b.bound_us,
            b.minus_bare_p99_us.abs(),
            if b.minus_bare_p99_us < 0.0 { "below" } else { "above" }
        ),
        None => String::new(),
    };
    let uds = match (t.p99_ratio_to_uds, t.uds_met) {
        (Some(r), Some(ok)) => format!(
            // Three decimals: 0.803 reads as missed, where "0.80" would not.
            "; p99 {r:.3} × the Unix-socket chain's (≤ {TARGET_UDS_RATIO}: {}{above_floor}{against_bare})",
            met(ok)
        ),
        // The control is the floor: no transport to compare.
        _ if t.chain == CONTROL => String::new(),
        _ => "; the Unix-socket chain was not measured".into(),
    };
    let uds_rounds = match &t.uds_by_round {
        Some(r) => format!(
            " Against the Unix-socket chain round by round ({}): p99 ratio median {:.3}, met in {}.",
            r.p99_ratio.len(),
            r.p99_ratio_median,
            r.met
        ),
        None => String::new(),
    };
    let predicted = match t.misses_floor_predicts {
        Some(p) => format!(
            "; the floor's own tail gives {p:.0}/M to a chain that costs its {:+.1} µs at every deadline",
            t.p50_minus_floor_us
        ),
        None => String::new(),
    };
    let catching_up = match &t.misses_floor_predicts_catching_up {
        Some(c) => format!(
            ", {:.0}/M when it also catches up after each late wake-up at {:.1} µs a sample (its CPU per sample less the timer's)",
            c.misses_per_million, c.per_sample_us
        ),
        None => String::new(),
    };
    let by_round = match &t.by_round {
        Some(r) => {
            let n = r.p50_minus_floor_us.len();
            let span = |d: &[f64]| {
                let lo = d.iter().copied().fold(f64::INFINITY, f64::min);
                let hi = d.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                format!("{lo:+.1} … {hi:+.1}")
            };
            format!(
                " Round by round ({n}, each against its own floor): p50 median {:+.1} µs ({}), met in {}; p99 median {:+.1} µs ({}), met in {}; misses met in {}.",
                r.p50_median_us,
                span(&r.p50_minus_floor_us),
                r.p50_met,
                r.p99_median_us,
                span(&r.p99_minus_floor_us),
                r.p99_met,
                r.misses_met
            )
        }
        None => String::new(),
    };
    let bare = match &t.bare_chain {
        Some(b) => {
            let median = |m: Option<f64>| match m {
                Some(v) => format!(" (median round {v:+.1})"),
                None => String::new(),
            };
            format!(
                " The same critical path bare (timer and two futex wake-ups; no bus, messages or stage work): p50 {:+.1} µs, p99 {:+.1} µs{} above the floor; the chain adds p50 {:+.1} µs, p99 {:+.1} µs{} to it.",
                b.p50_minus_floor_us,
                b.p99_minus_floor_us,
                median(b.p99_minus_floor_median_us),
                b.chain_p50_minus_bare_us,
                b.chain_p99_minus_bare_us,
                median(b.chain_p99_minus_bare_median_us),
            )
        }
        None => String::new(),
    };
    let outside = match &t.outside_stalls {
        Some(o) => format!(
            " Outside the stalls of {} ms or more (the machine frozen; see the stalls lines): misses {:.0}/M (≤ 2 × the floor's outside its stalls + 10 = {:.0}: {}{}).",
            drivelab_runtime::timing::STALL_NS as f64 / 1e6,
            o.misses_per_million,
            o.misses_bound,
            met(o.misses_met),
            match o.rounds_met {
                Some(n) => format!("; met in {n} of {} rounds", o.rounds),
                None => String::new(),
            }
        ),
        None => String::new(),
    };
    let fastest = match &t.fastest_slots {
        Some(f) if f.picked_some() => f.clause(),
        _ => String::new(),
    };
    let control = if t.chain == CONTROL {
        " A control: the floor measured again, so what it misses this run's noise decides, for the chains too."
    } else {
        ""
    };
    format!(
        "Targets at {} kHz ({} against the floor, {}): p50 {:+.1} µs (≤ +{TARGET_P50_US}: {}); p99 {:+.1} µs (≤ +{TARGET_P99_US}: {}); misses {:.0}/M (≤ 2 × floor + 10 = {:.0}: {}{predicted}{catching_up}){uds}.{by_round}{fastest}{uds_rounds}{outside}{bare}{control}",
        t.rate_hz / 1000.0,
        t.chain,
        request_words(t.cpu_latency_request),
        t.p50_minus_floor_us,
        met(t.p50_met),
        t.p99_minus_floor_us,
        met(t.p99_met),
        t.misses_per_million,
        t.misses_bound,
        met(t.misses_met),
    )
}

/// What sleep-then-spin buys at one rate: the `iceoryx2+spin` chain against the same chain
/// without it (one core, the same request, the same rounds). Negative changes are gains.
#[derive(Debug, Clone, Serialize)]
pub struct SpinEffect {
    /// Sample rate, Hz.
    pub rate_hz: f64,
    /// The plant's spin before each deadline, µs.
    pub spin_us: f64,
    /// Cycle p50 with the spin − without, µs.
    pub p50_change_us: f64,
    /// Cycle p99 with the spin − without, µs.
    pub p99_change_us: f64,
    /// Each round's p99 change, round i with the spin against round i without it, µs (empty
    /// for a single round).
    pub p99_change_by_round_us: Vec<f64>,
    /// Median of `p99_change_by_round_us`, µs.
    pub p99_median_change_us: Option<f64>,
    /// Misses per million with the spin.
    pub misses_per_million: f64,
    /// Misses per million without it.
    pub misses_per_million_without: f64,
    /// CPU time of the drive's processes with the spin − without, s per simulated second.
    pub cpu_change_s_per_s: Option<f64>,
}

/// The spin's effect at each rate where both chains were measured under the same request.
fn spin_effects(rows: &[Row], spin_arg: f64) -> Vec<SpinEffect> {
    rows.iter()
        .filter(|r| r.variant == "iceoryx2+spin")
        .filter_map(|spin| {
            let plain = rows.iter().find(|r| {
                r.variant == "iceoryx2"
                    && r.placement == spin.placement
                    && r.rate_hz == spin.rate_hz
                    && r.cpu_latency_request == spin.cpu_latency_request
            })?;
            let by_round =
                round_diffs(&spin.rounds, &plain.rounds, |r| r.p99_us).unwrap_or_default();
            Some(SpinEffect {
                rate_hz: spin.rate_hz,
                spin_us: spin_us(spin_arg, spin.rate_hz),
                p50_change_us: spin.cycle_us.p50 - plain.cycle_us.p50,
                p99_change_us: spin.cycle_us.p99 - plain.cycle_us.p99,
                p99_median_change_us: (!by_round.is_empty()).then(|| median(&by_round)),
                p99_change_by_round_us: by_round,
                misses_per_million: spin.misses_per_million,
                misses_per_million_without: plain.misses_per_million,
                cpu_change_s_per_s: spin.cpu_s_per_s.zip(plain.cpu_s_per_s).map(|(a, b)| a - b),
            })
        })
        .collect()
}

/// One line of the report per rate: what the spin bought and cost.
fn spin_line(e: &SpinEffect) -> String {
    let rounds = e
        .p99_median_change_us
        .map(|m| format!(" (median round {m:+.1} µs)"))
        .unwrap_or_default();
    let cpu = e
        .cpu_change_s_per_s
        .map(|c| format!("; CPU {c:+.3} s per simulated second"))
        .unwrap_or_default();
    format!(
        "Sleep-then-spin at {} kHz ({} µs) against the same chain without it: p50 {:+.1} µs, p99 {:+.1} µs{rounds}; misses {:.0}/M against {:.0}/M{cpu}.",
        e.rate_hz / 1000.0,
        e.spin_us,
        e.p50_change_us,
        e.p99_change_us,
        e.misses_per_million,
        e.misses_per_million_without,
    )
}

/// A variant's measurement so far: its rounds merged, and each round's own figures.
#[derive(Default)]
struct Acc {
    total: Option<VariantResult>,
    rounds: Vec<RoundFigures>,
}

/// Adds a round's measurement to its variant's total.
fn absorb(acc: &mut Acc, m: VariantResult) -> Result<()> {
    acc.rounds.push(RoundFigures::of(&m));
    match &mut acc.total {
        Some(t) => t.merge(&m),
        slot => {
            *slot = Some(m);
            Ok(())
        }
    }
}

/// Where the bench is, for the one line that says where a stop signal cut it short.
#[derive(Default)]
struct Place {
    /// What it is doing, e.g. "hop at 10000 Hz, round 1 of 5".
    step: String,
    /// The output folder once it exists, and whether the bench made it.
    out: Option<(PathBuf, bool)>,
    /// The progress bar, cleared before an error line.
    bar: Option<indicatif::ProgressBar>,
}

impl Place {
    /// Ends the current step and starts `step`; Err([`Interrupted`](drivelab_bench::Interrupted))
    /// instead when a stop signal arrived during the current one.
    fn enter(&mut self, step: impl Into<String>) -> Result<()> {
        drivelab_bench::check_stop()?;
        self.step = step.into();
        Ok(())
    }

    /// The error of a bench that a stop signal cut short during the current step, `e` being
    /// what that step returned: it says where and what was written. An output folder that
    /// the bench made and left empty is removed.
    fn interrupted(&self, e: &anyhow::Error) -> anyhow::Error {
        // A measurement's own stop needs no words; a drive's says what it recorded.
        let how = if e.downcast_ref::<drivelab_bench::Interrupted>().is_some() {
            String::new()
        } else {
            format!(": {}", drivelab_runtime::text::error_text(e))
        };
        let written = match &self.out {
            Some((dir, made)) if dir.read_dir().is_ok_and(|mut d| d.next().is_none()) => {
                if *made {
                    let _ = std::fs::remove_dir(dir);
                }
                "nothing written".to_string()
            }
            Some((dir, _)) => format!(
                "no report written (bench.json, bench.md); the measurements so far are in {}",
                dir.display()
            ),
            None => "nothing written".to_string(),
        };
        anyhow!(
            "bench interrupted ({}) during {}{how}; {written}",
            drivelab_runtime::service::stop_signal_name(),
            self.step
        )
    }
}

/// Runs the whole bench and writes bench.json, bench.md, .hgrm files and percentile plots.
/// A stop signal (SIGINT, SIGTERM, SIGHUP …) ends it at once with one error that says where:
/// every process it started is stopped and every bus it made is removed.
pub fn run(a: &BenchArgs) -> Result<()> {
    drivelab_runtime::service::install_signal_handlers()?;
    let mut at = Place {
        step: "the set-up".into(),
        ..Place::default()
    };
    measure_and_report(a, &mut at).map_err(|e| {
        if let Some(b) = &at.bar {
            b.finish_and_clear();
        }
        if drivelab_runtime::service::stop_requested() {
            at.interrupted(&e)
        } else {
            e
        }
    })
}

/// [`run`], keeping `at` up to date.
fn measure_and_report(a: &BenchArgs, at: &mut Place) -> Result<()> {
    let seconds = a.seconds.unwrap_or(if a.quick { 0.2 } else { 10.0 });
    if !(seconds.is_finite() && seconds > 0.0 && seconds <= 3600.0) {
        return Err(usage(format!(
            "--seconds must be in (0, 3600], got {seconds}"
        )));
    }
    if a.cyclictest.trim().is_empty() {
        return Err(usage(
            "--cyclictest is empty: give a name on PATH or a path (default: cyclictest)".into(),
        ));
    }
    for &r in &a.rates {
        if !(r.is_finite() && (100.0..=100_000.0).contains(&r)) {
            return Err(usage(format!("--rates: {r} Hz must be in [100, 100000]")));
        }
    }
    for p in &a.placements {
        placement(p).map_err(|e| usage(format!("--placements: {e}")))?;
    }
    // --quick fixes both; one given beside it would be ignored.
    for (given, flag) in [
        (!a.rates.is_empty(), "--rates"),
        (!a.placements.is_empty(), "--placements"),
    ] {
        if a.quick && given {
            return Err(usage(format!(
                "{flag} cannot be used with --quick (10000 Hz, one-core placement only)"
            )));
        }
    }
    let rates: Vec<f64> = if a.quick {
        vec![10_000.0]
    } else if a.rates.is_empty() {
        vec![5_000.0, 10_000.0, 20_000.0]
    } else {
        a.rates.clone()
    };
    let placements: Vec<String> = if a.quick {
        vec!["one-core".into()]
    } else if a.placements.is_empty() {
        ["one-core", "two-plus-two", "alternating"]
            .map(String::from)
            .to_vec()
    } else {
        a.placements.clone()
    };
    let mut topo_paths: BTreeMap<String, String> = Default::default();
    for t in &a.topologies {
        drivelab_runtime::topology::load(t).map_err(|e| anyhow!("--topologies: {e}"))?;
        let name = topology_name(t);
        if topo_paths.insert(name.clone(), t.clone()).is_some() {
            return Err(usage(format!("--topologies: '{name}' is listed twice")));
        }
    }
    let rounds = a.rounds.unwrap_or(if a.quick { 1 } else { 5 });
    if !(1..=100).contains(&rounds) {
        return Err(usage(format!("--rounds must be in 1..=100, got {rounds}")));
    }
    // Capped at T_s/4 per rate later; 0 skips the variant.
    if !(a.spin_us.is_finite() && a.spin_us >= 0.0) {
        return Err(usage(format!(
            "--spin-us must be a number of µs >= 0 (0 skips the spin variant), got {}",
            a.spin_us
        )));
    }
    // The variants of every rate, each measured in `rounds` interleaved slices so that the
    // machine's slow changes (a VM's noisy minutes) reach all of them alike.
    const VARIANTS: [&str; 10] = [
        "floor",
        "floor-repeat",
        "cyclictest",
        "hop",
        "bare-chain",
        "inprocess",
        "uds",
        "iceoryx2",
        "iceoryx2+spin",
        "topology",
    ];
    if let Some(v) = a.variants.iter().find(|v| !VARIANTS.contains(&v.as_str())) {
        return Err(usage(format!(
            "--variants: unknown variant '{v}' (known: {})",
            VARIANTS.join(", ")
        )));
    }
    let cyclictest = match drivelab_bench::cyclictest::locate(&a.cyclictest) {
        Ok(p) => Some(p),
        Err(why) => {
            crate::errln!("drivelab: bench: cyclictest cross-check skipped: {why}");
            None
        }
    };
    let (out, made) = match &a.out {
        Some(out) => (out.clone(), !out.exists()),
        None => (
            crate::launcher::new_default_folder(&format!("bench-{}", crate::launcher::unix_s()))?,
            true,
        ),
    };
    std::fs::create_dir_all(&out).with_context(|| format!("cannot create {}", out.display()))?;
    let out = out.canonicalize()?;
    at.out = Some((out.clone(), made));
    let exe = std::env::current_exe()?;
    let (base, _) = Scenario::load("kyslan-pi").map_err(|e| anyhow!(e))?;
    let mut request = RequestHolder {
        held: None,
        failed: false,
    };
    let mut jobs = jobs(a, &placements, cyclictest.is_some());
    if !a.variants.is_empty() {
        jobs.retain(|j| j.variant == "floor" || a.variants.iter().any(|v| v == j.variant));
    }
    let total = rates.len() * jobs.len() * rounds + 2;
    let bar = indicatif::ProgressBar::new(total as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    at.bar = Some(bar.clone());
    let mut rows: Vec<Row> = Vec::new();
    let mut checks: Vec<CrossCheck> = Vec::new();
    let mut curves_by_rate: Vec<(f64, Vec<drivelab_tools::plot::PercentileSeries>)> = Vec::new();
    // cyclictest runs on the plant's core of the one-core placement; its main thread goes to
    // another core, decided once for every run of it.
    let cyclictest_main_core = cyclictest.as_deref().and_then(|exe| {
        node(placement("one-core").ok()?.plant)
            .core
            .and_then(|c| drivelab_bench::cyclictest::main_thread_core(exe, c))
    });
    // How cold the plant's core leaves a task's memory over a sleep, before and after the
    // rounds, under the request the chains run with: says which state of the host the rows
    // were measured in.
    let probe_node = node(placement("one-core")?.plant);
    request.set(!a.no_cpu_latency_request);
    at.enter("the cache probe before the rounds")?;
    let cache_before = drivelab_bench::cache::after_sleep(&probe_node)?;
    for &hz in &rates {
        let one = placement("one-core")?;
        let slice = seconds / rounds as f64;
        let mut acc: Vec<Acc> = jobs.iter().map(|_| Acc::default()).collect();
        let mut cpu: Vec<f64> = vec![0.0; jobs.len()];
        let mut switches: Vec<u64> = vec![0; jobs.len()];
        let mut by_process: Vec<BTreeMap<String, RunUsage>> =
            jobs.iter().map(|_| BTreeMap::new()).collect();
        let mut stage_hists: Vec<BTreeMap<String, LatencyHist>> =
            jobs.iter().map(|_| BTreeMap::new()).collect();
        let mut topologies: Vec<Option<TopologyPlan>> = jobs.iter().map(|_| None).collect();
        let mut held: Vec<bool> = jobs.iter().map(|j| j.request).collect();
        let mut still_polling: Vec<u32> = vec![0; jobs.len()];
        for round in 0..rounds {
            for (i, job) in jobs.iter().enumerate() {
                let round_tag = if rounds > 1 {
                    format!(", round {}/{rounds}", round + 1)
                } else {
                    String::new()
                };
                let req_tag = if job.request { "" } else { " without request" };
                bar.set_message(format!(
                    "{hz} Hz {} {}{req_tag}{round_tag}",
                    job.variant, job.placement
                ));
                let place = match job.placement.as_str() {
                    "-" => String::new(),
                    p => format!(" {p}"),
                };
                at.enter(format!(
                    "{}{place}{req_tag} at {hz} Hz, round {} of {rounds}",
                    job.variant,
                    round + 1
                ))?;
                held[i] = request.set(job.request);
                if !held[i] {
                    // The request just released may leave the core polling when idle
                    // (drivelab_bench::idle): let it settle, or the row measures a request.
                    still_polling[i] += u32::from(settle_idle(&node(one.plant))?);
                }
                let dir = {
                    let d = out.join(job.tag(hz));
                    if rounds > 1 {
                        d.join(format!("round{}", round + 1))
                    } else {
                        d
                    }
                };
                let bus = format!("b{}r{round}j{i}", std::process::id());
                let chain = |pl: Placement| -> Result<ChainSpec> {
                    Ok(ChainSpec {
                        scenario: scenario_at(&base, hz, slice, pl)?,
                        seconds: slice,
                        plant: node(pl.plant),
                        observer: node(pl.observer),
                        current_loop: node(pl.current_loop),
                        speed_loop: node(pl.speed_loop),
                    })
                };
                let drive = match job.variant {
                    // The floor, cyclictest and the in-process chain run on the plant's core
                    // at its priority.
                    "floor" | "floor-repeat" => {
                        absorb(
                            &mut acc[i],
                            drivelab_bench::run_floor(
                                hz,
                                slice,
                                &node(one.plant),
                                base.timing.tick_aligned,
                            )?,
                        )?;
                        None
                    }
                    "cyclictest" => {
                        let exe = cyclictest
                            .as_deref()
                            .ok_or_else(|| anyhow!("no cyclictest"))?;
                        let m = drivelab_bench::cyclictest::run(
                            exe,
                            hz,
                            slice,
                            &node(one.plant),
                            cyclictest_main_core,
                            job.request,
                            base.timing.tick_aligned,
                            &dir,
                        )?;
                        absorb(&mut acc[i], m)?;
                        None
                    }
                    "inprocess" => {
                        absorb(&mut acc[i], drivelab_bench::run_inprocess(&chain(one)?)?)?;
                        None
                    }
                    // "hop": from the plant's place to the observer's, as the chain's first
                    // hop. "bare-chain": the default chain's critical path (plant →
                    // observer → current loop) with nothing but the timer and the wake-ups.
                    "hop" | "bare-chain" => {
                        let (receivers, measure) = if job.variant == "hop" {
                            (vec![node(one.observer)], Measure::Wakeup)
                        } else {
                            (
                                vec![node(one.observer), node(one.current_loop)],
                                Measure::Cycle,
                            )
                        };
                        let m = drivelab_bench::hop::run(
                            &exe,
                            hz,
                            slice,
                            base.timing.tick_aligned,
                            &node(one.plant),
                            &receivers,
                            measure,
                            &bus,
                            &dir,
                        )?;
                        absorb(&mut acc[i], m)?;
                        None
                    }
                    "uds" => {
                        std::fs::create_dir_all(&dir)?;
                        // Its four processes are the only children that end meanwhile.
                        let (cpu0, sw0) = drivelab_runtime::service::usage(libc::RUSAGE_CHILDREN);
                        let m = drivelab_bench::run_uds_chain(
                            &chain(placement(&job.placement)?)?,
                            &exe,
                            &dir,
                        )?;
                        let (cpu1, sw1) = drivelab_runtime::service::usage(libc::RUSAGE_CHILDREN);
                        cpu[i] += cpu1 - cpu0;
                        switches[i] += sw1.voluntary.saturating_sub(sw0.voluntary);
                        absorb(&mut acc[i], m)?;
                        None
                    }
                    "topology" => {
                        let sc = scenario_at(&base, hz, slice, one)?;
                        let t = topo_paths.get(&job.placement).map(String::as_str);
                        Some(run_iceoryx2(&sc, &dir, &bus, t)?)
                    }
                    _ => {
                        let mut sc = scenario_at(&base, hz, slice, placement(&job.placement)?)?;
                        if !job.request {
                            sc.timing.cpu_latency_us = CpuLatency::None;
                        }
                        if job.variant == "iceoryx2+spin" {
                            // The plant sleeps to spin_us before each deadline and spins the
                            // rest (docs/architecture.md, "Real-time rules").
                            sc.timing.plant_spin_us = spin_us(a.spin_us, hz);
                            sc.validate().map_err(|e| anyhow!("--spin-us: {e}"))?;
                        }
                        Some(run_iceoryx2(&sc, &dir, &bus, None)?)
                    }
                };
                if let Some(d) = drive {
                    absorb(&mut acc[i], d.result)?;
                    cpu[i] += d.cpu_s;
                    switches[i] += d.switches;
                    for (p, u) in d.by_process {
                        let e = by_process[i].entry(p).or_default();
                        e.cpu_s += u.cpu_s;
                        e.preemptions += u.preemptions;
                    }
                    for (k, h) in d.hists {
                        match stage_hists[i].get_mut(&k) {
                            Some(total) => total.add(&h)?,
                            None => {
                                stage_hists[i].insert(k, h);
                            }
                        }
                    }
                    topologies[i] = Some(d.topology);
                }
                bar.inc(1);
            }
        }
        let mut measured: Vec<Row> = Vec::new();
        let mut curves = Vec::new();
        for (i, job) in jobs.iter().enumerate() {
            let Acc {
                total,
                rounds: by_round,
            } = std::mem::take(&mut acc[i]);
            let m = total
                .ok_or_else(|| anyhow!("{} {}: no measurement", job.variant, job.placement))?;
            let h = out.join(format!("{}.hgrm", job.tag(hz)));
            drivelab_runtime::files::write(&h, m.cycle.hgrm())?;
            let mut r = row(job, hz, &m, &h);
            r.rounds = by_round;
            // What was held, not what was wanted (a refused request leaves it off).
            r.cpu_latency_request = held[i];
            r.idle_still_polling_rounds = still_polling[i];
            if cpu[i] > 0.0 {
                // Per simulated second: the rounds add up to `seconds` of drive.
                r.cpu_s_per_s = Some(cpu[i] / seconds);
                r.waits_per_sample = Some(switches[i] as f64 / r.samples.max(1) as f64);
            }
            if !by_process[i].is_empty() {
                let n = r.samples.max(1) as f64;
                r.cpu_us_per_sample_by_process = by_process[i]
                    .iter()
                    .map(|(p, u)| (p.clone(), u.cpu_s * 1e6 / n))
                    .collect();
                r.preemptions_per_sample =
                    Some(by_process[i].values().map(|u| u.preemptions).sum::<u64>() as f64 / n);
            }
            if let Some(t) = &topologies[i] {
                let lat = stage_hists[i]
                    .iter()
                    .map(|(k, h)| (k.clone(), h.percentiles()))
                    .collect();
                r.budget = crate::budget::budget(t, &lat);
            }
            let mut label = job.variant.to_string();
            if job.placement != "-" {
                label += &format!(" {}", job.placement);
            }
            if !held[i] {
                label += " (no request)";
            }
            curves.push((label, m.cycle.curve()));
            measured.push(r);
        }
        checks.extend(compare(&mut measured, hz, cyclictest_main_core));
        curves_by_rate.push((hz, curves));
        rows.extend(measured);
    }
    request.set(!a.no_cpu_latency_request);
    at.enter("the cache probe after the rounds")?;
    let cache_after = drivelab_bench::cache::after_sleep(&probe_node)?;
    // The speed measurements below are not real time: no request.
    request.set(false);
    // Simulation speed: lockstep (four processes) and in-process, kyslan-pi.
    bar.set_message("lockstep speed");
    at.enter("the lockstep speed run")?;
    let sim_s = if a.quick { 0.2 } else { 2.0 };
    let ls_out = out.join("lockstep-speed");
    let ls = launcher::run(&RunOptions {
        scenario: "kyslan-pi".into(),
        clock: Clock::Lockstep,
        duration_s: Some(sim_s),
        out: Some(ls_out),
        bus: Some(format!("b{}ls", std::process::id())),
        no_plots: true,
        restart: launcher::Restart::Never,
        lockstep_restart_ms: drivelab_runtime::inject::RESTART_DEFAULT_MS,
        ..RunOptions::default()
    })?;
    bar.inc(1);
    bar.set_message("in-process speed");
    at.enter("the in-process speed run")?;
    let mut ip_sc = base.clone();
    ip_sc.duration_s = if a.quick { 1.0 } else { 20.0 };
    // Time the cycles only (the controller design at construction is set-up, not simulation).
    let mut drive = drivelab_runtime::drive::InProcessDrive::new(&ip_sc);
    let n = ip_sc.samples();
    let mut rows_ip = Vec::with_capacity(n as usize);
    let t = Instant::now();
    for k in 0..n {
        if drivelab_runtime::service::stop_requested() {
            break;
        }
        rows_ip.push(drive.cycle(k));
    }
    let ip_speed = ip_sc.duration_s / t.elapsed().as_secs_f64();
    std::hint::black_box(rows_ip.len());
    bar.inc(1);
    // The measurements are done: a stop signal from here on cuts nothing short.
    at.enter("writing the report")?;
    bar.finish_and_clear();

    let speed = serde_json::json!({
        "scenario": "kyslan-pi",
        "lockstep_simulated_s_per_wall_s": ls.summary["loop_simulated_s_per_wall_s"],
        "lockstep_including_startup_simulated_s_per_wall_s": ls.summary["simulated_s_per_wall_s"],
        "lockstep_wall_s": ls.summary["wall_time_s"],
        "lockstep_simulated_s": sim_s,
        "inprocess_simulated_s_per_wall_s": ip_speed,
        "inprocess_simulated_s": ip_sc.duration_s,
    });
    let doctor = drivelab_tools::doctor::run_checks();
    let goals = targets(&rows);
    let spins = spin_effects(&rows, a.spin_us);
    let repeats = floor_repeats(&rows);
    let report = serde_json::json!({
        "seconds_per_variant": seconds,
        "rounds": rounds,
        "quick": a.quick,
        "cpu_latency_request_us": if a.no_cpu_latency_request { None } else { Some(0) },
        "cpu_latency_request_failed": request.failed,
        "floor_vs_cyclictest": checks,
        "floor_vs_repeat": repeats,
        "targets": goals,
        "spin": spins,
        "machine": {
            "cpus": drivelab_runtime::rt::online_cpus(),
            "cache_after_sleep": { "before": cache_before, "after": cache_after },
            "doctor": doctor,
        },
        "rows": rows,
        "speed": speed,
    });
    drivelab_runtime::files::write(out.join("bench.json"), serde_json::to_vec_pretty(&report)?)?;
    let mut md = markdown(
        &rows,
        &checks,
        &repeats,
        &goals,
        &spins,
        &speed,
        (seconds, rounds, a.spin_us),
    );
    md.push_str(&cache_paragraph(&cache_before, &cache_after));
    drivelab_runtime::files::write(out.join("bench.md"), &md)?;
    // A build without figures (the cross build) writes the tables and .hgrm files only.
    for (hz, curves) in curves_by_rate
        .iter()
        .filter(|_| drivelab_tools::plot::AVAILABLE)
    {
        let ts_us = 1e6 / hz;
        drivelab_tools::plot::plot_percentiles(
            curves,
            &format!(
                "cycle latency at {} kHz (floor: a bare timer's lateness at every deadline)",
                hz / 1000.0
            ),
            Some((ts_us, format!("T_s = {ts_us:.0} µs"))),
            true,
            &out.join(format!("percentiles-{}hz", *hz as u64)),
        )?;
    }
    if a.json {
        crate::outln!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        crate::out!("{md}");
        crate::outln!("\nwritten: {}", out.display());
    }
    Ok(())
}

/// The bench.md paragraph of the cache probes before and after the rounds.
fn cache_paragraph(before: &CacheProbe, after: &CacheProbe) -> String {
    let core = before
        .cpu
        .map_or_else(|| "the plant's core".to_string(), |c| format!("core {c}"));
    format!(
        "\nCaches after a sleep: a timer on {core} woke every {} µs and read {} lines on as \
         many pages, then read them again (p50 of {} wake-ups): before the rounds {}: {}; after \
         them {}: {} (docs/measurements.md, \"The same VM three hours later\").\n",
        drivelab_bench::cache::PERIOD_NS / 1000,
        before.lines,
        before.wakeups,
        before.clause(),
        before.state().words(),
        after.clause(),
        after.state().words()
    )
}

fn fmt_opt(v: Option<f64>, prec: usize) -> String {
    v.map(|x| format!("{x:.prec$}"))
        .unwrap_or_else(|| "-".into())
}

/// The plant's spin before each deadline in the `iceoryx2+spin` variant at `hz`: the
/// requested µs, capped at T_s/4.
pub fn spin_us(requested_us: f64, hz: f64) -> f64 {
    requested_us.min(0.25e6 / hz)
}

/// How the report's lines say whether the CPU wake-up latency request was held.
fn request_words(held: bool) -> &'static str {
    if held {
        "request held"
    } else {
        "no request"
    }
}

/// The report's request column: what was held, and a round that measured a request after all.
fn request_cell(r: &Row) -> String {
    match (r.cpu_latency_request, r.idle_still_polling_rounds) {
        (true, _) => "0 µs".into(),
        (false, 0) => "none".into(),
        (false, n) => format!("none (core polled in {n} round(s))"),
    }
}

/// The Markdown table of the report.
pub fn markdown(
    rows: &[Row],
    checks: &[CrossCheck],
    repeats: &[FloorRepeat],
    goals: &[Targets],
    spins: &[SpinEffect],
    speed: &serde_json::Value,
    (seconds, rounds, spin_arg): (f64, usize, f64),
) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "Cycle latency from t_k to command k available at the plant, µs ({seconds} s per variant in {rounds} interleaved round(s), the rounds' histograms added before any percentile is taken; floor = a bare timer loop's lateness at every deadline (deadlines that passed while it was late are handled by its next wake-up, as a chain that cost nothing would handle them), floor-repeat = the same floor measured again in every round; cyclictest = its wake-ups' lateness; request = CPU wake-up latency request of 0 µs held (none: before each such round the core idled in 2 ms sleeps until its idle governor stopped the polling a released request leaves behind); each chain is compared with the floor measured under the same request).\n");
    let _ = writeln!(s, "| rate | variant | placement | request | p50 | p99 | p99.9 | max | misses/M | longest run | p50 − floor | p99 − floor | p99 / floor | p99 / uds | CPU s/s | waits/sample | syscalls/sample | budget |");
    let _ = writeln!(
        s,
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for r in rows {
        let verdict = match r.holds_budget {
            Some(true) => "HOLDS",
            Some(false) => "MISSED",
            None => "-",
        };
        let _ = writeln!(
            s,
            "| {} kHz | {} | {} | {} | {:.1} | {:.1} | {:.1} | {:.0} | {:.0} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
            r.rate_hz / 1000.0,
            r.variant,
            r.placement,
            request_cell(r),
            r.cycle_us.p50,
            r.cycle_us.p99,
            r.cycle_us.p999,
            r.cycle_us.max,
            r.misses_per_million,
            r.longest_miss_run,
            fmt_opt(r.p50_minus_floor_us, 1),
            fmt_opt(r.p99_minus_floor_us, 1),
            fmt_opt(r.p99_ratio_to_floor, 2),
            fmt_opt(r.p99_ratio_to_uds, 2),
            fmt_opt(r.cpu_s_per_s, 3),
            fmt_opt(r.waits_per_sample, 2),
            fmt_opt(r.syscalls_per_sample, 2),
            verdict
        );
    }
    if !goals.is_empty() {
        let _ = write!(
            s,
            "\nThe targets, each chain against the floor of the same run:\n\n{}",
            targets_table(goals)
        );
    }
    for t in goals {
        let _ = writeln!(s, "\n{}", targets_line(t));
    }
    for c in checks {
        let _ = writeln!(
            s,
            "\nFloor − cyclictest at {} kHz ({}), wake-up lateness: p50 {:+.1} µs, p99 {:+.1} µs: {} (target: both within ±{CYCLICTEST_AGREEMENT_US} µs){} ({}).{}",
            c.rate_hz / 1000.0,
            request_words(c.cpu_latency_request),
            c.p50_diff_us,
            c.p99_diff_us,
            if c.agrees { "agrees" } else { "DISAGREES" },
            c.by_round.as_ref().map_or(String::new(), CrossRounds::clause)
                + &c.fastest_slots.as_ref().map_or(String::new(), CrossFastest::clause),
            match c.cyclictest_main_thread_core {
                Some(core) => format!("cyclictest's main thread on CPU {core}"),
                None => "cyclictest's main thread on the measured core".to_string(),
            },
            // The same comparison of the floor with itself, the scale to read this one by.
            repeats
                .iter()
                .find(|f| f.rate_hz == c.rate_hz && f.cpu_latency_request == c.cpu_latency_request)
                .map_or(String::new(), |f| format!(
                    " The floor against its own repeat in the same rounds: p50 {:+.1} µs, p99 {:+.1} µs.",
                    f.p50_diff_us, f.p99_diff_us
                ))
        );
    }
    for f in repeats {
        let _ = writeln!(s, "\n{}", floor_repeat_line(f));
    }
    for r in rows.iter().filter(|r| r.variant == "floor") {
        if let Some(line) = r.stalls.as_ref().and_then(|st| st.line_of("the floor's")) {
            let _ = writeln!(
                s,
                "\nfloor at {} kHz ({}), over its rounds: {line}.",
                r.rate_hz / 1000.0,
                request_words(r.cpu_latency_request)
            );
        }
        if let Some(c) = r.cpu_per_wakeup_us {
            let _ = writeln!(
                s,
                "\nfloor at {} kHz ({}): each timer wake-up costs its thread {c:.1} µs on the CPU, {:.0} % of the core at this rate before any stage runs.",
                r.rate_hz / 1000.0,
                request_words(r.cpu_latency_request),
                c * r.rate_hz * 1e-4
            );
        }
    }
    for r in rows.iter().filter(|r| r.variant == "hop") {
        let _ = writeln!(
            s,
            "\nhop at {} kHz: one process-to-process futex wake-up on the plant's core with nothing else in it, notify → running: p50 {:.1} µs, p99 {:.1} µs (the kernel's part of every hop; the default chain has two on its critical path).",
            r.rate_hz / 1000.0,
            r.cycle_us.p50,
            r.cycle_us.p99
        );
    }
    for r in rows
        .iter()
        .filter(|r| (r.variant == "iceoryx2" || r.variant == "topology") && r.cpu_latency_request)
    {
        if let Some(b) = &r.budget {
            let _ = writeln!(
                s,
                "\nWhere the microseconds go, {} {} at {} kHz (path {}):\n\n{}",
                r.variant,
                r.placement,
                r.rate_hz / 1000.0,
                b.path.join(" → "),
                crate::budget::markdown(b)
            );
        }
        if let Some(line) = cpu_per_sample_line(r) {
            let _ = writeln!(s, "\n{line}");
        }
        if let Some(line) = r.stalls.as_ref().and_then(|st| st.line()) {
            let _ = writeln!(
                s,
                "\n{} {} at {} kHz, over its rounds: {line}.",
                r.variant,
                r.placement,
                r.rate_hz / 1000.0
            );
        }
    }
    if rows.iter().any(|r| r.variant == "iceoryx2+spin") {
        let spin_at: Vec<String> = rows
            .iter()
            .filter(|r| r.variant == "iceoryx2+spin")
            .map(|r| {
                format!(
                    "{} µs at {} kHz",
                    spin_us(spin_arg, r.rate_hz),
                    r.rate_hz / 1000.0
                )
            })
            .collect();
        let _ = writeln!(
            s,
            "\niceoryx2+spin: the plant sleeps to {} before each deadline and spins the rest (--spin-us, capped at T_s/4).",
            spin_at.join(", ")
        );
    }
    for e in spins {
        let _ = writeln!(s, "\n{}", spin_line(e));
    }
    let _ = writeln!(
        s,
        "\nSimulation speed (kyslan-pi): lockstep (4 processes) {:.1}× real time, in-process {:.0}× real time.",
        speed["lockstep_simulated_s_per_wall_s"].as_f64().unwrap_or(f64::NAN),
        speed["inprocess_simulated_s_per_wall_s"].as_f64().unwrap_or(f64::NAN)
    );
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round(p50_us: f64, p99_us: f64, misses_per_million: f64) -> RoundFigures {
        RoundFigures {
            p50_us,
            p99_us,
            misses_per_million,
            misses_outside_stalls_per_million: None,
            wake_p50_us: p50_us,
            wake_p99_us: p99_us,
        }
    }

    #[test]
    fn each_round_of_a_chain_is_judged_against_the_floor_of_the_same_round() {
        let floor = [round(13.0, 30.0, 100.0), round(20.0, 60.0, 1000.0)];
        // Round 1 misses every target against its own floor (p50 +11, p99 +16, 220 > 210);
        // round 2 meets them all against its floor, though it is worse than round 1 in every
        // figure: judged against round 1's floor instead, it would miss them all.
        let chain = [round(24.0, 46.0, 220.0), round(29.0, 74.0, 2000.0)];
        let r = target_rounds(&chain, &floor).unwrap();
        assert_eq!(r.p50_minus_floor_us, [11.0, 9.0]);
        assert_eq!(r.p99_minus_floor_us, [16.0, 14.0]);
        assert_eq!((r.p50_met, r.p99_met, r.misses_met), (1, 1, 1));
        assert_eq!((r.p50_median_us, r.p99_median_us), (10.0, 15.0));
        // The median round's p99, +15.0, is within the target (at its bound); +16 and +15 are
        // not (median +15.5).
        assert!(r.p99_median_met);
        let worse = [round(24.0, 46.0, 220.0), round(29.0, 75.0, 2000.0)];
        assert!(!target_rounds(&worse, &floor).unwrap().p99_median_met);
        // At the limits: met.
        let r = target_rounds(&[round(23.0, 45.0, 210.0)].repeat(2), &[floor[0]; 2]).unwrap();
        assert_eq!((r.p50_met, r.p99_met, r.misses_met), (2, 2, 2));
        // One round, or rounds that do not pair up: nothing to say round by round.
        assert_eq!(target_rounds(&chain[..1], &floor[..1]), None);
        assert_eq!(target_rounds(&chain, &floor[..1]), None);
    }

    #[test]
    fn the_targets_table_gives_each_chain_and_rate_its_verdicts_in_one_row() {
        // Bench run 65 at 10 kHz (docs/measurements.md): the default chain and the control.
        let chain = Targets {
            chain: "iceoryx2 one-core".into(),
            rate_hz: 10_000.0,
            cpu_latency_request: true,
            p50_minus_floor_us: 12.896,
            p50_met: false,
            p99_minus_floor_us: -388.0,
            p99_met: true,
            misses_per_million: 5370.0,
            misses_bound: 27650.0,
            misses_met: true,
            p99_ratio_to_uds: Some(0.8003),
            uds_met: Some(false),
            p99_above_floor_ratio_to_uds: None,
            uds_bound_against_bare: None,
            misses_floor_predicts: None,
            misses_floor_predicts_catching_up: None,
            by_round: Some(TargetRounds {
                p50_minus_floor_us: vec![],
                p99_minus_floor_us: vec![],
                p50_median_us: 13.2,
                p99_median_us: 13.9,
                p99_median_met: true,
                p50_met: 1,
                p99_met: 5,
                misses_met: 4,
            }),
            uds_by_round: None,
            bare_chain: None,
            outside_stalls: None,
            fastest_slots: Some(FastestSlots {
                chain_slots: 1,
                floor_slots: 2,
                rounds: 10,
                floor_p50_span_us: [13.2, 18.7],
                p50_minus_floor_us: 5.516,
                p50_met: None,
            }),
        };
        let control = Targets {
            chain: CONTROL.into(),
            p50_minus_floor_us: 0.8,
            p50_met: true,
            p99_minus_floor_us: 1195.8,
            p99_met: false,
            misses_per_million: 25017.0,
            by_round: Some(TargetRounds {
                p99_median_us: 29.0,
                p99_median_met: false,
                ..chain.by_round.clone().unwrap()
            }),
            p99_ratio_to_uds: None,
            uds_met: None,
            fastest_slots: None,
            ..chain.clone()
        };
        let table = targets_table(&[chain, control]);
        let lines: Vec<&str> = table.lines().collect();
        assert_eq!(lines.len(), 4, "{table}");
        assert!(
            lines[0].starts_with(
                "| rate | chain | p50 − floor (≤ +10 µs) | p99 − floor (≤ +15 µs); median round |"
            ),
            "{}",
            lines[0]
        );
        assert_eq!(
            lines[2],
            "| 10 kHz | iceoryx2 one-core | +12.9 missed | -388.0 met; +13.9 met | 5370 (bound 27650) met | 0.800 missed | +5.5 not judged (1 and 2 of 10 slots) |"
        );
        assert_eq!(
            lines[3],
            format!("| 10 kHz | {CONTROL} | +0.8 met | +1195.8 missed; +29.0 missed | 25017 (bound 27650) met | - | - |")
        );
        // No chain measured: no table.
        let md = markdown(
            &[],
            &[],
            &[],
            &[],
            &[],
            &serde_json::json!({}),
            (1.0, 1, 0.0),
        );
        assert!(!md.contains("The targets, each chain"), "{md}");
    }

    #[test]
    fn the_p50_target_is_also_judged_in_the_slots_where_the_timer_woke_at_its_fastest() {
        // Bench run 60 at 10 kHz (docs/measurements.md): the timer woke in about 7.3 µs or
        // in 14–19 µs at p50, slot by slot. The floor drew its slow speed in 6 of 10 slots,
        // so its merged p50 (14.9 µs) met the chain's fast slots, and the target read +4.6.
        let floor: Vec<RoundFigures> = [17.2, 7.3, 7.3, 8.3, 18.3, 14.6, 16.1, 16.1, 18.8, 7.6]
            .map(|p50| round(p50, 30.0, 0.0))
            .to_vec();
        // The chain's slots: (cycle p50, its plant's timer wake-up p50).
        let chain: Vec<RoundFigures> = [
            (28.5, 18.2),
            (18.9, 11.9),
            (19.3, 12.0),
            (20.4, 12.8),
            (19.0, 11.8),
            (24.0, 15.1),
            (20.3, 12.8),
            (20.1, 12.6),
            (24.5, 15.3),
            (19.4, 12.2),
        ]
        .map(|(p50, wake)| RoundFigures {
            wake_p50_us: wake,
            ..round(p50, 45.0, 0.0)
        })
        .to_vec();
        let f = FastestSlots::of(&chain, &floor).unwrap();
        // Picked: the chain's slots woken within 11.8 + 2 µs, the floor's within 7.3 + 2.
        assert_eq!((f.chain_slots, f.floor_slots, f.rounds), (7, 4, 10));
        assert_eq!(f.floor_p50_span_us, [7.3, 18.8]);
        // Median 19.4 against median 7.45 (the mean of the middle two of four).
        assert!((f.p50_minus_floor_us - 11.95).abs() < 1e-9, "{f:?}");
        assert_eq!(f.p50_met, Some(false));
        assert!(f.picked_some());
        assert!(
            f.clause().contains("p50 +11.9 µs (missed)"),
            "{}",
            f.clause()
        );
        // Run 65 at 10 kHz: the timer drifted within its slow speed; the chain's fastest
        // slot stood alone and the floor's two: the medians are those slots' draw, not judged.
        let drift: Vec<RoundFigures> = [13.2, 18.7, 16.0, 17.1, 15.9, 16.5, 17.9, 14.6, 16.8, 15.7]
            .map(|p50| round(p50, 30.0, 0.0))
            .to_vec();
        let lone = chain
            .iter()
            .enumerate()
            .map(|(i, r)| RoundFigures {
                wake_p50_us: if i == 3 { 9.0 } else { r.wake_p50_us },
                ..*r
            })
            .collect::<Vec<_>>();
        let f = FastestSlots::of(&lone, &drift).unwrap();
        assert_eq!((f.chain_slots, f.floor_slots), (1, 2));
        assert_eq!(f.p50_met, None);
        assert!(
            f.clause()
                .ends_with("(not judged: fewer than 3 slots on a side)."),
            "{}",
            f.clause()
        );
        // A steady timer: every slot picked, the medians' difference (21 − 12); met at +10.
        let steady = |p50s: [f64; 3]| p50s.map(|p| round(p, 30.0, 0.0)).to_vec();
        let f = FastestSlots::of(&steady([20.0, 21.0, 22.0]), &steady([12.0, 13.0, 11.0])).unwrap();
        assert_eq!(
            (f.chain_slots, f.floor_slots, f.p50_minus_floor_us),
            (3, 3, 9.0)
        );
        assert!(f.p50_met == Some(true) && !f.picked_some());
        let f = FastestSlots::of(&steady([22.0, 22.0, 22.0]), &steady([12.0, 12.0, 12.0])).unwrap();
        assert_eq!(f.p50_met, Some(true), "at the limit: met");
        // One round: nothing to pick from.
        assert_eq!(FastestSlots::of(&chain[..1], &floor[..1]), None);
    }

    #[test]
    fn the_default_chain_is_judged_at_its_best_placement_under_the_request() {
        // (placement, request held, cycle p50 µs)
        let rows = [
            ("one-core", true, 21.0),
            ("two-plus-two", true, 19.5),
            ("spread", false, 12.0),
            ("one-core", false, 30.0),
        ];
        let best = |rows: &[(&'static str, bool, f64)]| {
            best_placement(rows, |r| r.1, |r| r.2).map(|r| (r.0, r.1))
        };
        assert_eq!(best(&rows), Some(("two-plus-two", true)));
        // Without the request anywhere: the lowest p50 of all.
        assert_eq!(best(&rows[2..]), Some(("spread", false)));
        assert_eq!(best(&rows[..1]), Some(("one-core", true)));
        assert_eq!(best(&[]), None);
    }

    #[test]
    fn each_round_of_a_chain_is_judged_against_the_unix_socket_chain_of_the_same_round() {
        // Round 2 met a stall in the iceoryx2 chain only: the merged p99 would be decided
        // by it, the median of the rounds is not.
        let uds = [
            round(30.0, 50.0, 0.0),
            round(30.0, 40.0, 0.0),
            round(30.0, 60.0, 0.0),
        ];
        let chain = [
            round(28.0, 40.0, 0.0),
            round(28.0, 80.0, 0.0),
            round(28.0, 45.0, 0.0),
        ];
        let r = UdsRounds::of(&chain, &uds).unwrap();
        assert_eq!(r.p99_ratio, [0.8, 2.0, 0.75]);
        assert_eq!(r.p99_ratio_median, 0.8);
        // At the limit (0.8): met.
        assert_eq!(r.met, 2);
        assert_eq!(UdsRounds::of(&chain[..1], &uds[..1]), None);
        assert_eq!(UdsRounds::of(&chain, &uds[..2]), None);
    }

    #[test]
    fn the_floor_is_checked_against_cyclictest_round_by_round_on_the_wake_ups() {
        // The wake-up figures, not the cycle's, are compared.
        let wake = |p50: f64, p99: f64| RoundFigures {
            wake_p50_us: p50,
            wake_p99_us: p99,
            ..round(500.0, 900.0, 0.0)
        };
        let floor = [wake(15.0, 30.0), wake(25.0, 80.0), wake(16.0, 31.0)];
        // Round 2 was a noisy minute for both: it agrees with its own round (+1, +2), though
        // its floor is 10 µs and 50 µs above round 1's cyclictest. Round 3 disagrees at p99.
        let ct = [wake(14.0, 28.0), wake(24.0, 78.0), wake(15.0, 20.0)];
        let r = CrossRounds::of(&floor, &ct).unwrap();
        assert_eq!(r.p50_diff_us, [1.0, 1.0, 1.0]);
        assert_eq!(r.p99_diff_us, [2.0, 2.0, 11.0]);
        assert_eq!((r.p50_median_us, r.p99_median_us), (1.0, 2.0));
        assert_eq!(r.rounds_agreeing, 2);
        // At the limit (±3 µs): agrees.
        let r = CrossRounds::of(&[wake(15.0, 30.0); 2], &[wake(18.0, 27.0); 2]).unwrap();
        assert_eq!(r.rounds_agreeing, 2);
        assert_eq!(CrossRounds::of(&floor[..1], &ct[..1]), None);
    }

    #[test]
    fn the_floor_is_also_checked_against_cyclictest_in_the_slots_where_each_woke_at_its_fastest() {
        // A timer with two speeds, as in bench run 66: the floor drew its fast one (7.3–7.6
        // µs) in 4 slots of 10, cyclictest in 6, so the merged p50s sit in different speeds
        // and differ by the draw; the fastest slots agree.
        let wake = |p50: f64| RoundFigures {
            wake_p50_us: p50,
            ..round(500.0, 900.0, 0.0)
        };
        let floor = [7.3, 16.0, 7.4, 17.0, 15.5, 7.6, 18.0, 16.5, 7.5, 19.0].map(wake);
        let ct = [7.0, 7.2, 15.0, 7.1, 16.0, 7.3, 7.2, 17.0, 16.5, 7.4].map(wake);
        let f = CrossFastest::of(&floor, &ct).unwrap();
        assert_eq!((f.floor_slots, f.cyclictest_slots, f.rounds), (4, 6, 10));
        // Medians 7.45 and 7.2.
        assert!((f.p50_diff_us - 0.25).abs() < 1e-9, "{f:?}");
        assert_eq!(f.agrees, Some(true));
        assert_eq!(
            f.clause(),
            "; in the slots where each woke at its fastest (the floor's 4 and cyclictest's 6 of 10): p50 +0.2 µs (agrees)"
        );
        // The floor 5 µs slower in its fast speed: disagrees.
        let slow = floor.map(|r| wake(r.wake_p50_us + 5.0));
        assert_eq!(CrossFastest::of(&slow, &ct).unwrap().agrees, Some(false));
        // Two fast floor slots: not judged.
        let mut two = floor;
        two[0] = wake(16.2);
        two[2] = wake(17.5);
        let f = CrossFastest::of(&two, &ct).unwrap();
        assert_eq!((f.floor_slots, f.agrees), (2, None));
        assert!(f
            .clause()
            .ends_with("(not judged: fewer than 3 slots on a side)"));
        // A steady timer: every slot picked, nothing beyond the rounds' medians to say.
        let steady = CrossFastest::of(&[wake(12.0); 3], &[wake(11.0); 3]).unwrap();
        assert_eq!(steady.clause(), "");
        assert_eq!(CrossFastest::of(&floor[..1], &ct[..1]), None);
    }

    #[test]
    fn the_floor_predicts_the_misses_of_a_chain_that_costs_only_its_median() {
        // 10 kHz: 990 deadlines 12 µs late, 5 at 95 µs and 5 at 150 µs.
        let mut h = LatencyHist::new("cycle");
        for _ in 0..990 {
            h.record_ns(12_000);
        }
        for _ in 0..5 {
            h.record_ns(95_000);
            h.record_ns(150_000);
        }
        let c = misses_pm_if_sooner(&h, 100_000);
        assert_eq!(c.len(), SOONER_MAX_US as usize + 1);
        // Due on time, only the 150 µs ones miss; due 5 µs sooner, 95 µs is not yet a miss;
        // 6 µs sooner it is; none of the 12 µs ones ever is.
        assert_eq!(
            (c[0], c[5], c[6], c[40]),
            (5_000.0, 5_000.0, 10_000.0, 10_000.0)
        );
        assert_eq!(at_shift(&c, 5.5), Some(7_500.0));
        // A chain faster than the floor (sleep-then-spin) is read at 0, a slow one at the end.
        assert_eq!(at_shift(&c, -3.0), Some(5_000.0));
        assert_eq!(at_shift(&c, 99.0), Some(10_000.0));
        assert_eq!(at_shift(&[], 1.0), None);
    }

    #[test]
    fn the_catch_up_model_runs_each_round_of_the_floor_on_its_own() {
        // Two rounds of 10 deadlines at 10 kHz (lateness in ns); the first ends inside a 250
        // µs stall, the second starts on time: no lag carries over from one to the other.
        let stall = vec![
            10_000, 10_000, 10_000, 10_000, 10_000, 10_000, 10_000, 250_000, 150_000, 50_000,
        ];
        let calm = vec![10_000; 10];
        let rounds = [stall, calm];
        // Without cost: the floor's own two misses (250 and 150 µs) in 20 deadlines.
        let m = CatchUp::model(&rounds, 100.0, 0.0, 0.0).unwrap();
        assert_eq!(m.misses_per_million, 100_000.0);
        // 10 µs after each wake-up and 50 µs a sample when behind: 260, 210, 160 µs late:
        // three misses, and the calm round none although it follows a late end.
        let m = CatchUp::model(&rounds, 100.0, 10.0, 50.0).unwrap();
        assert_eq!(m.misses_per_million, 150_000.0);
        assert_eq!((m.after_wake_up_us, m.per_sample_us), (10.0, 50.0));
        // A chain faster than the floor (sleep-then-spin) costs nothing after the wake-up.
        let m = CatchUp::model(&rounds, 100.0, -5.0, 0.0).unwrap();
        assert_eq!((m.after_wake_up_us, m.misses_per_million), (0.0, 100_000.0));
        assert_eq!(CatchUp::model(&[], 100.0, 10.0, 50.0), None);
    }

    #[test]
    fn what_a_chain_adds_to_the_floor_is_compared_with_what_another_adds() {
        let r = above_floor_ratio(32.0, 39.0, 20.0).unwrap();
        assert!((r - 12.0 / 19.0).abs() < 1e-12, "{r}");
        // (The raw ratio of the same p99s, 32 / 39, is 0.82: the shared floor hides the
        // difference.)
        assert_eq!(above_floor_ratio(32.0, 20.0, 20.0), None);
        assert_eq!(above_floor_ratio(32.0, 18.0, 20.0), None);
    }

    #[test]
    fn the_misses_outside_the_stalls_are_judged_against_the_floors_outside_its_own() {
        let outside = |total: f64, outside: f64| RoundFigures {
            misses_outside_stalls_per_million: Some(outside),
            ..round(20.0, 40.0, total)
        };
        // Round 1: a stall gave the chain 3 000/M, 40 of them outside it, against the
        // floor's 20 outside its own (bound 50): met. Round 2: 90 outside, bound 30: missed.
        let chain = [outside(3_040.0, 40.0), outside(90.0, 90.0)];
        let floor = [outside(20.0, 20.0), outside(10.0, 10.0)];
        let o = OutsideStalls::of((Some(65.0), &chain), (Some(15.0), &floor)).unwrap();
        assert_eq!((o.misses_bound, o.misses_met), (40.0, false));
        assert_eq!((o.rounds_met, o.rounds), (Some(1), 2));
        let o = OutsideStalls::of((Some(40.0), &chain), (Some(15.0), &floor)).unwrap();
        assert!(o.misses_met, "at the bound: met");
        // A round without a stall log counts as not met; one round has no round verdict.
        let bare = [round(20.0, 40.0, 0.0), outside(0.0, 0.0)];
        let o = OutsideStalls::of((Some(0.0), &bare), (Some(15.0), &floor)).unwrap();
        assert_eq!(o.rounds_met, Some(1));
        let o = OutsideStalls::of((Some(0.0), &chain[..1]), (Some(15.0), &floor[..1])).unwrap();
        assert_eq!(o.rounds_met, None);
        // Either side without a stall log: nothing to say.
        assert_eq!(
            OutsideStalls::of((None, &chain), (Some(15.0), &floor)),
            None
        );
        assert_eq!(OutsideStalls::of((Some(0.0), &chain), (None, &floor)), None);
    }

    #[test]
    fn the_median_is_the_middle_value_or_the_mean_of_the_middle_two() {
        assert_eq!(median(&[9.0, -40.0, 3.0]), 3.0);
        assert_eq!(median(&[9.0, -40.0, 3.0, 5.0]), 4.0);
        assert!(median(&[]).is_nan());
    }
}
