//! `drivelab run`: starts the topology's stage hosts on a private bus, records every sample,
//! stops them cleanly, removes the bus files and writes the run folder.
//!
//! [`spawn`] starts and stops the stage hosts, [`recorder`] records the drive and assembles
//! the trace, [`supervisor`] injects faults and keeps the processes alive per [`policy`];
//! this module resolves the topology, runs the whole and writes the summary.

mod bridge;
mod policy;
mod recorder;
pub mod sinks;
mod spawn;
pub(crate) mod stream;
mod supervisor;
pub mod tail;
mod trip;

pub use bridge::ZenohListen;
pub use recorder::{samples_missing, Gap};
pub(crate) use spawn::die_with_launcher;
pub use supervisor::{
    fault_reports, recovery_notes, speed_recovered, EventKind, FaultReport, PlantDown,
    SampleCounts, SupEvent, NOT_INJECTED,
};

use crate::common::BusClock;
use crate::expect::usage;
use anyhow::{anyhow, bail, Context, Result};
use drivelab_runtime::bus;
use drivelab_runtime::config::Scenario;
use drivelab_runtime::drive::DriveDesign;
use drivelab_runtime::service::TopologyPlan;
use drivelab_runtime::tick;
use drivelab_runtime::topology::StageInfo;
use drivelab_runtime::trace::TraceRow;
use drivelab_tools::metrics::{speed_metrics_with_faults, FaultStart};
use recorder::{run_recorder, Progress};
use serde::Serialize;
use serde_json::json;
use spawn::{process_binary, runner_of, spawn_service, terminate, ChildProc, Spawn};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::sync::Arc;
use std::time::{Duration, Instant};
use stream::{TraceStats, TraceStream};
use supervisor::{supervise, Supervised};

/// Which clock paces the run.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize, serde::Deserialize, Default,
)]
#[serde(rename_all = "lowercase")]
pub enum Clock {
    /// The topology's processes; the plant sleeps to absolute deadlines.
    #[default]
    Realtime,
    /// The topology's processes; the plant waits for each command; as fast as possible.
    Lockstep,
    /// The same stages on the same host in one thread, no bus.
    Inprocess,
}

impl Clock {
    /// Its name on the command line and in run folders.
    pub fn name(self) -> &'static str {
        match self {
            Clock::Realtime => "realtime",
            Clock::Lockstep => "lockstep",
            Clock::Inprocess => "inprocess",
        }
    }
}

/// Options of one run (`Default`: a real-time run of no scenario with no option given, but
/// `lockstep_restart_ms` 0, where the command line's default is `inject::RESTART_DEFAULT_MS`).
#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    /// Scenario name or file.
    pub scenario: String,
    /// Clock.
    pub clock: Clock,
    /// Override of the scenario's duration, s.
    pub duration_s: Option<f64>,
    /// Output folder.
    pub out: Option<PathBuf>,
    /// Bus id (default: derived from the process id).
    pub bus: Option<String>,
    /// Strict RT setup.
    pub rt_strict: bool,
    /// No pinning / FIFO / mlock.
    pub no_rt: bool,
    /// Skip the PNG plots.
    pub no_plots: bool,
    /// Print progress lines.
    pub verbose: bool,
    /// Faults to inject.
    pub faults: Vec<crate::faults::FaultSpec>,
    /// Lockstep and in process: the simulated restart of a killed stage, ms (see
    /// docs/architecture.md, "Fault model").
    pub lockstep_restart_ms: f64,
    /// Restart policy of the supervisor.
    pub restart: Restart,
    /// Seed of `random:N` fault plans.
    pub fault_seed: u64,
    /// Topology override: a shipped name or a file with `[[process]]` tables.
    pub topology: Option<String>,
    /// Expectations from the command line (`--expect`), checked after the scenario's own.
    pub expect: Vec<String>,
    /// A command put in front of every process the launcher starts (`--runner`); None: the
    /// `DRIVELAB_RUNNER` variable, if set (see `drivelab_runtime::runner`).
    pub runner: Option<drivelab_runtime::runner::Runner>,
    /// Make the drive reachable over Zenoh (`--zenoh-listen`; docs/architecture.md,
    /// "Across machines (Zenoh)").
    pub zenoh: Option<ZenohListen>,
    /// Serve the Foxglove WebSocket protocol on this address while the drive runs
    /// (`--foxglove`; docs/foxglove.md).
    pub foxglove: Option<std::net::SocketAddr>,
    /// Also write `timing.csv`, each sample's publish times (`--timing-csv`; real time only).
    pub timing_csv: bool,
    /// Each stage host counts the system calls its loop makes beyond its wait and wakes
    /// (`--audit-syscalls`; summary.json → stray_syscalls).
    pub audit_syscalls: bool,
    /// The stage hosts keep their real-time set-up line off stderr (it is in summary.json →
    /// processes): a campaign's runs, where four such lines a run would bury the failures.
    pub quiet_hosts: bool,
    /// The launcher keeps its configuration warnings off stderr (they are in summary.json →
    /// warnings): a campaign's runs, whose campaign says each such line once, not once a run.
    pub quiet_warnings: bool,
}

/// What the supervisor does when a service dies.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize, serde::Deserialize, Default,
)]
#[serde(rename_all = "kebab-case")]
pub enum Restart {
    /// Leave it dead; the rest of the drive goes on in its degraded mode.
    Never,
    /// Restart it (with --rejoin) at once; in a crash loop (more than 5 crashes of one
    /// process within 10 s, injected kills not counted) after a back-off of 100 ms, doubling
    /// up to 1 s. In lockstep a process that dies without an injected fault ends the run.
    #[default]
    OnFailure,
}

/// What a run produced.
#[derive(Debug)]
pub struct RunResult {
    /// The run folder.
    pub out: PathBuf,
    /// The summary as written to `summary.json`.
    pub summary: serde_json::Value,
}

/// Loads the scenario and applies the duration override ([`set_duration`]), with a
/// one-line error.
pub fn load_scenario(name: &str, duration_s: Option<f64>) -> Result<Scenario> {
    let (mut sc, _) = Scenario::load(name).map_err(|e| anyhow!(e))?;
    if let Some(d) = duration_s {
        set_duration(&mut sc, d).map_err(|e| anyhow!("--duration {d}: {e}"))?;
    }
    Ok(sc)
}

/// Gives the run `duration_s` seconds ([`Scenario::set_duration`]) and checks the result;
/// returns what a shorter run than the scenario's leaves out, one item each.
pub fn set_duration(sc: &mut Scenario, duration_s: f64) -> Result<Vec<String>, String> {
    let cut = sc.set_duration(duration_s);
    sc.validate()?;
    Ok(cut)
}

/// The resolved scenario as `scenario.toml` holds it; a run shortened by `--duration`
/// starts with comment lines naming what it left out, so that a longer run of the file is
/// not taken for the scenario's own.
fn resolved_toml(sc: &Scenario, not_reached: &[String]) -> Result<String> {
    let mut text = String::new();
    if !not_reached.is_empty() {
        text.push_str(&format!(
            "# Shortened to {} s by --duration: left out (after its end)\n",
            sc.duration_s
        ));
        for item in not_reached {
            text.push_str(&format!("#   {item}\n"));
        }
    }
    text.push_str(&toml::to_string(sc)?);
    Ok(text)
}

/// The one line that says what a shortened run leaves out (None: nothing).
pub fn not_reached_line(duration_s: f64, cut: &[String]) -> Option<String> {
    (!cut.is_empty()).then(|| {
        format!(
            "the run ends at {duration_s} s, before what the scenario schedules later; left out: {}",
            cut.join(", ")
        )
    })
}

/// The name of a run's folder where none is given: `<scenario>-<clock>-<unix seconds>`.
fn default_stem(sc: &Scenario, clock: Clock) -> String {
    format!("{}-{}-{}", sc.name, clock.name(), unix_s()).to_lowercase()
}

/// Seconds since the Unix epoch, now (0 before it).
pub(crate) fn unix_s() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0)
}

/// The folder for a command's outputs where none was given (no `--out`): `runs/STEM`, made
/// here, or `runs/STEM-2`, `-3`, … where that one exists (a run in the same second, one that
/// goes on now): two commands started together never share a folder, and one never
/// replaces another's outputs.
pub(crate) fn new_default_folder(stem: &str) -> Result<PathBuf> {
    new_folder_in(Path::new("runs"), stem)
}

fn new_folder_in(parent: &Path, stem: &str) -> Result<PathBuf> {
    std::fs::create_dir_all(parent)
        .with_context(|| format!("cannot create {}", parent.display()))?;
    for n in 1..=1000u32 {
        let p = match n {
            1 => parent.join(stem),
            _ => parent.join(format!("{stem}-{n}")),
        };
        // Made or found there: `create_dir` is the one that decides, so two commands cannot
        // both take one.
        match std::fs::create_dir(&p) {
            Ok(()) => return Ok(p),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
            Err(e) => return Err(e).with_context(|| format!("cannot create {}", p.display())),
        }
    }
    bail!(
        "no new folder {}/{stem}-N: the first 1000 exist; give --out",
        parent.display()
    )
}

/// A run folder this process writes into: an advisory `flock` on the folder, which the kernel
/// drops when this value drops or the process ends, so that two drives never write into one
/// folder at the same time (the later one is refused).
pub(crate) struct RunFolderLock {
    _dir: std::fs::File,
    out: PathBuf,
}

/// Makes run folder `out` for a run: it may be new, empty or an earlier run's (it has
/// `scenario.toml`), never a folder of other files (`--out /`, `--out ~`) nor one another
/// drive is writing into. An earlier run's outputs are removed first, so that none of them
/// (plots after `--no-plots`, a stage the new topology lacks) passes for the new run's; other
/// files in it are kept. Nothing is removed unless all of them can be.
pub(crate) fn claim_run_folder(out: &Path) -> Result<RunFolderLock> {
    let lock = lock_run_folder(out)?;
    lock.remove_earlier_outputs()?;
    Ok(lock)
}

/// The checks and the lock of [`claim_run_folder`], with the earlier run's outputs still in
/// place: for a command that may yet fail before it has anything to write (`record`, whose
/// remote drive may not answer), so that a failure leaves the earlier run whole.
pub(crate) fn lock_run_folder(out: &Path) -> Result<RunFolderLock> {
    earlier_outputs(out)?;
    let dir = make_and_lock_folder(out, "run folder", "drive")?;
    let earlier = earlier_outputs(out)?;
    // Every folder a removal changes must be writable, or nothing is removed.
    for folder in [out.to_path_buf(), out.join("config")] {
        if earlier.iter().any(|p| p.parent() == Some(folder.as_path())) && !writable(&folder) {
            bail!(
                "run folder {}: cannot replace the earlier run's files in {} (not writable by this user)",
                out.display(),
                folder.display()
            );
        }
    }
    Ok(RunFolderLock {
        _dir: dir,
        out: out.to_path_buf(),
    })
}

/// Makes folder `out` (a "run folder", …) and takes its advisory lock (`flock(LOCK_EX |
/// LOCK_NB)`), held until the returned file drops; refused when another `who` (a drive, …)
/// holds it.
pub(crate) fn make_and_lock_folder(out: &Path, what: &str, who: &str) -> Result<std::fs::File> {
    make_folder(out, what)?;
    let dir = std::fs::File::open(out)
        .with_context(|| format!("cannot open {what} {}", out.display()))?;
    match dir.try_lock() {
        Ok(()) => Ok(dir),
        Err(std::fs::TryLockError::WouldBlock) => bail!(
            "{what} {}: another {who} is writing into it now; give another --out",
            out.display()
        ),
        Err(std::fs::TryLockError::Error(e)) => {
            bail!("{what} {}: cannot lock it: {e}", out.display())
        }
    }
}

/// Makes folder `out` (a "run folder", "output folder", …) with its missing parents.
pub(crate) fn make_folder(out: &Path, what: &str) -> Result<()> {
    // A file where the folder (or one above it) would be: said as such, not as the system's
    // "File exists" or "Not a directory".
    if let Some(file) = out
        .ancestors()
        .filter(|p| !p.as_os_str().is_empty())
        .find(|p| std::fs::metadata(p).is_ok_and(|m| !m.is_dir()))
    {
        if file == out {
            bail!(
                "{what} {}: is a file, not a folder; give a folder with --out",
                out.display()
            );
        }
        bail!(
            "{what} {}: {} is a file, not a folder; give a folder with --out",
            out.display(),
            file.display()
        );
    }
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {what} {}", out.display()))
}

impl RunFolderLock {
    /// Removes the earlier run's outputs from the locked folder (see [`claim_run_folder`]).
    pub(crate) fn remove_earlier_outputs(&self) -> Result<()> {
        let out = &self.out;
        for path in &earlier_outputs(out)? {
            std::fs::remove_file(path).with_context(|| {
                format!(
                    "run folder {}: cannot remove the earlier run's {}",
                    out.display(),
                    path.display()
                )
            })?;
        }
        // Its bus configuration's folder, when that leaves it empty (a run on the bus makes it).
        let _ = std::fs::remove_dir(out.join("config"));
        Ok(())
    }
}

/// The earlier run's outputs in `out` (none when it is absent or empty); an error when it is
/// a folder of other files.
fn earlier_outputs(out: &Path) -> Result<Vec<PathBuf>> {
    let Ok(entries) = std::fs::read_dir(out) else {
        return Ok(Vec::new()); // absent (made next), or not a folder (refused when made)
    };
    let names: Vec<std::ffi::OsString> = entries.flatten().map(|e| e.file_name()).collect();
    if names.is_empty() {
        return Ok(Vec::new());
    }
    if !out.join("scenario.toml").is_file() {
        bail!(
            "run folder {}: not empty and not a run folder (no scenario.toml): give a new or empty folder, or an earlier run's",
            out.display()
        );
    }
    Ok(names
        .iter()
        .filter_map(|n| n.to_str())
        .filter(|n| is_run_output(n))
        .map(|n| out.join(n))
        .chain([out.join("config").join("iceoryx2.toml")])
        // A symbolic link is removed, not followed: a trace written through one planted in
        // the folder would land wherever it points.
        .filter(|p| p.symlink_metadata().is_ok_and(|m| !m.is_dir()))
        .collect())
}

/// Whether this process may add and remove entries of folder `p`.
fn writable(p: &Path) -> bool {
    use std::os::unix::ffi::OsStrExt;
    let Ok(c) = std::ffi::CString::new(p.as_os_str().as_bytes()) else {
        return false;
    };
    // SAFETY: `c` is a valid NUL-terminated path that outlives the call.
    unsafe { libc::access(c.as_ptr(), libc::W_OK | libc::X_OK) == 0 }
}

/// Whether `name` is a file a run writes at the top of its folder.
fn is_run_output(name: &str) -> bool {
    const NAMES: &[&str] = &[
        "scenario.toml",
        "topology.json",
        "summary.json",
        "trace.csv",
        "trace.mcap",
        "trace.mcap.part",
        "timing.csv",
    ];
    const ENDINGS: &[&str] = &[".hdr", ".hgrm", ".stats.json", ".png", ".svg"];
    NAMES.contains(&name)
        || ENDINGS.iter().any(|e| name.ends_with(e))
        || (name.starts_with("rejoin-") && name.ends_with(".json"))
}

/// What a run on the bus produced.
struct BusRun {
    /// The trace's rows kept for the analyses (every row unless `stats` says otherwise).
    rows: Vec<TraceRow>,
    /// When the trace was written as it went: its figures.
    stats: Option<TraceStats>,
    /// Samples missing from it.
    gaps: Vec<Gap>,
    /// `summary.json` → `processes`.
    processes: serde_json::Value,
    /// Bus id, counters, deadline misses, the fault plan.
    info: serde_json::Value,
    /// The supervisor's log.
    events: Vec<SupEvent>,
    /// Why the run ended early (a failed service, Ctrl-C), if it did: what was recorded up
    /// to then is still written, then the run fails.
    failure: Option<String>,
    /// Cycle latencies around each hog's window.
    hog_latency: Vec<crate::faults::hog::WindowLatency>,
    /// The Zenoh bridge, detached from the bus: it publishes the summary once written.
    bridge: Option<bridge::Bridge>,
}

/// SCHED_FIFO priority of the recorder thread of a real-time drive: below the stages (70 and
/// up in the shipped topologies), above a split drive's link (60).
const RECORDER_PRIORITY: i32 = 65;

/// Runs the topology's processes on a bus and returns the recorder's data, the process info
/// and the supervisor's events.
fn run_bus(
    sc: &Scenario,
    sc_path: &Path,
    plan_topo: &TopologyPlan,
    plan: &[crate::faults::Fault],
    hogs: &[crate::faults::hog::Hog],
    o: &RunOptions,
    out: &Path,
    clock: BusClock,
    sinks: &sinks::Sinks,
) -> Result<BusRun> {
    // In real time the launcher's own threads (the supervisor, the readers of the hosts'
    // output, the hub) keep off the stages' cores until the drive ends; the hosts start with
    // the mask the launcher had (docs/architecture.md, "Real-time rules").
    let off = (clock == BusClock::Realtime && !o.no_rt).then(|| {
        drivelab_runtime::rt::off_rt_cores(drivelab_runtime::topology::cores(&plan_topo.processes))
    });
    let bus_id = bus_id_of(o);
    bus::check_bus_id(&bus_id)?;
    spawn::adopt_orphans();
    // Another drive (or any process) on this bus would be wrecked by the clean-up below:
    // `run` holds the bus (claim_bus) from before the run folder is made.
    // Leftovers of an earlier crashed run with the same id would confuse this one.
    bus::cleanup(&bus_id)?;
    // iceoryx2's own tools (`iox2`) find the drive from the run folder with this file.
    std::fs::create_dir_all(out.join("config"))?;
    drivelab_runtime::files::write(out.join("config/iceoryx2.toml"), bus::config_toml(&bus_id)?)?;
    let n = sc.samples();
    let stop = Arc::new(AtomicBool::new(false));
    let progress = Arc::new(Progress {
        tail: crate::hub::TraceTail::new(sc.rates.sample_hz),
        hog_latency: std::sync::Mutex::new(
            hogs.iter()
                .map(|h| crate::faults::hog::WindowLatency::new(h, sc.rates.sample_hz))
                .collect(),
        ),
        ..Default::default()
    });
    let (ready_tx, ready_rx) = mpsc::channel();
    // The trace goes to disk as the drive runs.
    let trace = TraceStream::new(
        sc,
        Some(drivelab_runtime::trace::CsvTrace::create(
            &out.join("trace.csv"),
        )?),
    )?
    .with_sinks(sinks.clone())
    .with_outer_divider(TraceStream::outer_divider(plan_topo))
    .with_plant_gone_at(sc.plant_gone_at())
    .with_timing(if o.timing_csv {
        Some(stream::TimingCsv::create(&out.join("timing.csv"))?)
    } else {
        None
    });
    // Real time: the liveness segment (every process's lease, and its twin's), made before
    // anyone starts; the processes with a standby twin.
    let lockstep = clock == BusClock::Lockstep;
    if !lockstep {
        drivelab_runtime::lease::Life::create(&bus_id, plan_topo.processes.len())?;
    }
    let standby: Vec<String> = plan_topo
        .processes
        .iter()
        .filter(|p| p.standby && !lockstep)
        .map(|p| p.name.clone())
        .collect();
    let publishers = drivelab_runtime::service::publishers_per_topic(plan_topo, lockstep);
    // In real time the recorder thread runs off the drive's cores at SCHED_FIFO, below every
    // stage and above a split drive's link, so that no normal task on its core (a build, the
    // OS) can keep it from draining its buffers (4096 samples) for long enough to lose one.
    // Refused without the privilege: it runs as before.
    let realtime = clock == BusClock::Realtime;
    let recorder_fifo = realtime && !o.no_rt;
    let rt_cores = drivelab_runtime::topology::cores(&plan_topo.processes);
    let rec = {
        let (b, s, sc, pr) = (bus_id.clone(), stop.clone(), sc.clone(), progress.clone());
        std::thread::Builder::new()
            .name("recorder".into())
            .spawn(move || {
                if recorder_fifo {
                    // Off the drive's cores first (where it could only wait below the
                    // stages), then above every normal task there.
                    let _ = drivelab_runtime::rt::keep_off(rt_cores, "recorder");
                    let _ =
                        drivelab_runtime::rt::set_scheduler(libc::SCHED_FIFO, RECORDER_PRIORITY);
                }
                let r = run_recorder(b, sc, trace, s, pr.clone(), ready_tx, publishers, realtime);
                let failed = r.as_ref().map_or(true, |t| !t.write_errors.is_empty());
                pr.failed.store(failed, Ordering::SeqCst);
                r
            })?
    };
    let topo_path = out.join("topology.json");
    let sp = Spawn {
        sc_path,
        topo_path: &topo_path,
        bus_id: &bus_id,
        clock,
        o,
        out,
        cpus: off.as_ref().and_then(|g| g.previous()),
        plan: plan_topo,
    };
    let mut events: Vec<SupEvent> = Vec::new();
    let mut bridge: Option<bridge::Bridge> = None;
    let result = (|| -> Result<(Vec<ChildProc>, Option<String>)> {
        ready_rx
            .recv()
            .map_err(|_| anyhow!("recorder thread died"))??;
        // The telemetry hub subscribes to the services' statuses before they start.
        let stage_names: Vec<String> = plan_topo.stages.iter().map(|s| s.name.clone()).collect();
        let mut hub = crate::hub::Hub::new(&bus_id, sc, clock == BusClock::Lockstep, &stage_names)?;
        hub.set_sinks(sinks.clone());
        // The bridge subscribes (polled) before the stage hosts start, like the recorder.
        if let Some(z) = &o.zenoh {
            let clock_name = match clock {
                BusClock::Realtime => "realtime",
                BusClock::Lockstep => "lockstep",
            };
            bridge = Some(bridge::Bridge::start(
                z, &bus_id, out, clock_name, o.verbose,
            )?);
        }
        let mut children = Vec::new();
        for (i, p) in plan_topo.processes.iter().enumerate() {
            if plan_topo.away.contains(&i) {
                continue;
            }
            // `exec` paths were made absolute when the topology was resolved.
            let spawned = process_binary(p, Path::new("/"))
                .and_then(|exe| spawn_service(p, &exe, i == 0, &sp, spawn::Start::Fresh));
            match spawned {
                Ok(c) => children.push(c),
                Err(e) => return Ok((children, Some(format!("{e:#}")))),
            }
        }
        // Handshake: each service reports its RT setup and READY (the processes with a twin
        // hold their lease by then); then their twins start and report; then the source goes.
        if let Some(failure) = spawn::wait_ready(&mut children)? {
            return Ok((children, Some(failure)));
        }
        let mut twins: Vec<Option<ChildProc>> = Vec::with_capacity(children.len());
        for c in &children {
            let twin = standby
                .contains(&c.name)
                .then(|| c.respawn_standby(&sp))
                .transpose();
            match twin {
                Ok(t) => twins.push(t),
                Err(e) => {
                    children.extend(twins.into_iter().flatten());
                    return Ok((children, Some(format!("{e:#}"))));
                }
            }
        }
        let mut started: Vec<ChildProc> = twins.iter_mut().filter_map(Option::take).collect();
        let failure = spawn::wait_ready(&mut started)?;
        let mut started = started.into_iter();
        for (t, c) in twins.iter_mut().zip(&children) {
            if standby.contains(&c.name) {
                *t = started.next();
            }
        }
        if let Some(failure) = failure {
            children.extend(twins.into_iter().flatten());
            return Ok((children, Some(failure)));
        }
        // A split drive starts when both machines' hosts are ready.
        if let (Some(b), Some(z)) = (bridge.as_mut(), o.zenoh.as_ref()) {
            if z.machine.is_some() {
                if let Err(e) = b.meet(z.wait) {
                    return Ok((children, Some(format!("{e:#}"))));
                }
            }
        }
        // The hogs start armed before sample 0, so that each spins from its own sample on.
        let running = crate::faults::hog::Running::arm(hogs, &bus_id);
        spawn::go(&mut children)?;
        if o.verbose {
            crate::errln!(
                "drivelab: {} samples at {} Hz, clock {}, bus {bus_id}",
                n,
                sc.rates.sample_hz,
                o.clock.name()
            );
        }
        // Supervise until the services finish.
        let started = Instant::now();
        let limit = match clock {
            // A stopped plant stops the clock: the run lasts the stops longer.
            BusClock::Realtime => realtime_limit(sc, &o.faults),
            BusClock::Lockstep => Duration::from_secs_f64(sc.duration_s * 2000.0 + 120.0),
        };
        // Progress on a terminal only (indicatif draws nothing when stderr is not a tty).
        let bar = if o.verbose {
            indicatif::ProgressBar::new(n)
        } else {
            indicatif::ProgressBar::hidden()
        };
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} samples {msg}",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        let mut supervised: Vec<_> = children
            .into_iter()
            .zip(twins)
            .map(|(c, t)| Supervised::new(c, t))
            .collect();
        // A split drive goes on when the controllers' machine leaves (the plant holds, then
        // goes safe: the drive's reaction is the point of the test) and stops when the
        // plant's machine does (nothing comes any more).
        let plant_here = !plan_topo.away.contains(&0);
        let mut link = || -> Option<String> {
            if progress.failed.load(Ordering::SeqCst) {
                return Some(RECORDER_FAILED.into());
            }
            let why = bridge.as_mut()?.lost()?;
            // At the end the machines leave one after the other: that is no news.
            if progress.next_k.load(Ordering::Relaxed) >= n {
                return None;
            }
            if plant_here {
                crate::errln!(
                    "drivelab: {why}; the plant goes on without its commands (hold, then safe state)"
                );
                None
            } else {
                Some(format!("{why}: no measurement comes any more"))
            }
        };
        let failure = supervise(
            &mut hub,
            &bar,
            &mut supervised,
            plan,
            hogs,
            running,
            &mut events,
            &progress,
            sc,
            &sp,
            started,
            limit,
            &mut link,
        )?;
        bar.finish_and_clear();
        // Let attached monitors see the end and detach before the bus goes away.
        hub.finish(
            progress.next_k.load(Ordering::Relaxed),
            &progress.tail,
            Duration::from_secs(1),
        )?;
        Ok((
            supervised
                .into_iter()
                .flat_map(|c| std::iter::once(c.proc).chain(c.standby))
                .collect(),
            failure,
        ))
    })();
    let (mut children, mut failure) = match result {
        Ok(v) => v,
        Err(e) => (Vec::new(), Some(format!("{e:#}"))),
    };
    terminate(&mut children);
    let strays = spawn::end_strays(&bus_id);
    if !strays.is_empty() {
        crate::errln!(
            "drivelab: warning: killed what the stage hosts left running after the drive: {}",
            strays.join(", ")
        );
    }
    // After a split drive that ended well the recorder is given time to end by itself, on
    // the end markers: the other machine's last samples may still be on the link when the
    // hosts here have ended. (Here, every host has ended: what they published is on the
    // bus, and the recorder takes it all when it stops.)
    let recorder_ended = !plan_topo.away.is_empty()
        && failure.is_none()
        && recorder_ends_alone(&rec, bridge.as_mut());
    stop.store(true, Ordering::SeqCst);
    let rec = rec
        .join()
        .map_err(|_| anyhow!("recorder thread panicked"))?;
    // The bridge forwards what is left and lets go of the bus before its files go.
    let bridge_stats = match bridge.as_mut().map(|b| b.detach()) {
        Some(Ok(s)) => Some(s),
        Some(Err(e)) => {
            // Killed, its bus files go with the rest; the run fails with the reason.
            if let Some(mut b) = bridge.take() {
                b.kill();
            }
            failure.get_or_insert(format!("{e:#}"));
            None
        }
        None => None,
    };
    let cleaned = bus::cleanup(&bus_id);
    // Whatever ended the run, what the recorder holds is written (the failure goes into the
    // summary and the exit code); only a recorder that failed itself has nothing to give.
    let rec = match (rec, &failure) {
        (Ok(r), _) => r,
        // The recorder's own error is the whole story.
        (Err(e), Some(f)) if f == RECORDER_FAILED || *f == format!("{e:#}") => return Err(e),
        (Err(e), Some(f)) => bail!("{f}; and the recorder failed: {e:#}"),
        (Err(e), None) => return Err(e),
    };
    // An output that could not be written stopped the run, with what it holds and the
    // summary written (the rows missing from trace.csv are listed).
    if !rec.write_errors.is_empty() {
        add_failure(&mut failure, rec.write_errors.join("; "));
    }
    // Bus files that would not go fail the run, with its trace and summary written.
    if let Err(e) = cleaned {
        failure.get_or_insert(format!("cannot remove this drive's bus files: {e:#}"));
    }
    let left = bus::leftovers(&bus_id);
    if !left.is_empty() {
        failure.get_or_insert(format!("bus files left behind: {}", left.join(", ")));
    }
    let mut processes = serde_json::Map::new();
    let mut counters = serde_json::Map::new();
    // Stages whose `<stage>.stats.json` could not be read, with why: their counters are not
    // in the summary.
    let mut stats_missing = serde_json::Map::new();
    for c in &children {
        let rt = c.rt.clone().unwrap_or(serde_json::Value::Null);
        if c.standby {
            // A twin that never took over: beside its process, no statistics of its own.
            if let Some(p) = processes.get_mut(&c.name) {
                p["standby"] = json!({ "pid": c.child.id(), "cpu": rt.get("cpu"), "priority": rt.get("priority") });
            }
            continue;
        }
        let mut entry = json!({ "stages": c.stages, "executable": c.exe, "pid": c.host_pid(), "cpu": rt.get("cpu"), "policy": rt.get("policy"), "priority": rt.get("priority"), "memory_locked": rt.get("memory_locked") });
        if let Some(w) = rt
            .get("warnings")
            .filter(|w| w.as_array().is_some_and(|a| !a.is_empty()))
        {
            // What the host's real-time set-up line says beyond its placement.
            entry["rt_warnings"] = w.clone();
        }
        for st in &c.stages {
            let stats_path = out.join(format!("{st}.stats.json"));
            let read = std::fs::read_to_string(&stats_path)
                .map_err(|e| match e.kind() {
                    std::io::ErrorKind::NotFound => not_written(&events, &c.name),
                    _ => format!("unreadable: {e}"),
                })
                .and_then(|text| {
                    serde_json::from_str::<serde_json::Value>(&text)
                        .map_err(|e| format!("unreadable: {e}"))
                });
            match read {
                Ok(v) => {
                    // What the process cost (its last incarnation's; every stage of a process
                    // carries the same figures, taken from the first that has them).
                    if entry.get("cpu_s").is_none() && v.is_object() {
                        entry["cpu_s"] = v["process_cpu_s"].clone();
                        entry["context_switches"] = v["process_context_switches"].clone();
                        entry["syscalls"] = v["process_syscalls"].clone();
                        if let Some(s) = v.get("stray_syscalls") {
                            entry["stray_syscalls"] = s.clone();
                        }
                    }
                    let mut cv = v.get("counters").cloned().unwrap_or_default();
                    if let Some(d) = v.get("diagnostics") {
                        cv["diagnostics"] = d.clone();
                    }
                    if let Some(d) = v.get("stalls") {
                        cv["stalls"] = d.clone();
                    }
                    if let Some(d) = v.get("inject") {
                        cv["inject"] = d.clone();
                    }
                    if let Some(w) = v.get("warnings") {
                        cv["warnings"] = w.clone();
                    }
                    counters.insert(st.clone(), cv);
                }
                Err(why) => {
                    stats_missing.insert(st.clone(), json!(why));
                }
            }
        }
        processes.insert(c.name.clone(), entry);
    }
    let not_made = progress
        .not_made
        .lock()
        .map(|mut v| std::mem::take(&mut *v))
        .unwrap_or_default();
    // The first sample the drive did not make: the plant's end marker's (the run's end, or
    // where it stopped), else the one after the newest measurement (a plant that died).
    let end_k = progress
        .plant_end
        .get()
        .copied()
        .unwrap_or_else(|| progress.next_k.load(Ordering::Relaxed));
    let mut info = json!({ "end_k": end_k, "faults_not_made": not_made, "bus": bus_id, "counters": counters, "statistics_missing": stats_missing, "recorder_rejected": rec.rejected, "recorder_late": rec.late, "plan": plan, "plant_down_samples": rec.rebuilt, "plant_down_ranges": rec.rebuilt_ranges, "schedule_start_ns": rec.t0_ns });
    if let Some(b) = bridge_stats {
        info["bridge"] = b;
    }
    // The CPUs the launcher's threads ran on (null: it was left on its own mask).
    info["launcher_cpus"] = match off.as_ref().map(|g| g.cpus()) {
        Some(c) if !c.is_empty() => json!(c),
        _ => serde_json::Value::Null,
    };
    if let Some(p) = counters.get("plant") {
        info["deadline_misses"] = p["deadline_misses"].clone();
        info["longest_miss_run"] = p["longest_miss_run"].clone();
        if let Some(st) = p.get("stalls") {
            info["stalls"] = stall_report(st);
        }
    }
    let mut gaps = rec.gaps;
    let produced = counters
        .get("plant")
        .and_then(|p| p["samples"].as_u64())
        .unwrap_or(0);
    // A plant killed for good in lockstep ended the drive at its kill
    // (`Scenario::samples_made`).
    let published = sc.samples_made();
    if let Some(f) = unreceived(&mut gaps, produced, published, rec.stats.rows) {
        failure.get_or_insert(f);
    }
    if plan_topo.away.contains(&0) && failure.is_none() {
        let end = progress.plant_end.get().copied();
        if let Some(f) = remote_tail(&mut gaps, end, recorder_ended, sc.samples()) {
            failure = Some(f);
        }
    }
    let hog_latency = progress
        .hog_latency
        .lock()
        .map(|mut l| std::mem::take(&mut *l))
        .map_err(|_| anyhow!("recorder thread panicked"))?;
    Ok(BusRun {
        rows: rec.kept,
        gaps,
        stats: Some(rec.stats),
        processes: serde_json::Value::Object(processes),
        info,
        events,
        failure,
        hog_latency,
        bridge,
    })
}

/// How [`not_written`] ends for a process the supervisor left dead: the summary's events
/// explain it, and no warning is needed.
const LEFT_DEAD: &str = " and was not restarted";

/// Why the process `process` left no `<stage>.stats.json` (a host writes it as it exits): it
/// exited for the last time during the run and was not restarted, or it did not write it.
fn not_written(events: &[SupEvent], process: &str) -> String {
    let last = events.iter().rev().find(|e| {
        e.process == process
            && matches!(
                e.kind,
                supervisor::EventKind::Exited { .. } | supervisor::EventKind::Restarted { .. }
            )
    });
    match last {
        Some(SupEvent {
            kind: supervisor::EventKind::Exited { status, .. },
            t_wall_s,
            ..
        }) => format!("not written: its process exited ({status}) at {t_wall_s:.3} s{LEFT_DEAD}"),
        _ => "not written by its process (it writes it as it exits)".to_string(),
    }
}

/// The cause of a measurement the plant published and the recorder never received.
const UNRECEIVED: &str = "the plant published it; it never reached the recorder";

/// A plant process that stepped through every one of the `samples` it published (its
/// `produced` counter: it never restarted) published each of them, so a measurement before
/// `samples` missing from a trace of `recorded` rows never reached the recorder: its gap says
/// so instead of "the plant stopped", and the run fails with the count. None when nothing is
/// amiss.
fn unreceived(gaps: &mut [Gap], produced: u64, samples: u64, recorded: u64) -> Option<String> {
    if produced < samples || recorded >= samples {
        return None;
    }
    let mut any = false;
    for g in gaps
        .iter_mut()
        .filter(|g| g.part == "measurement" && g.from < samples)
    {
        g.cause = UNRECEIVED.into();
        any = true;
    }
    any.then(|| {
        format!("the recorder received {recorded} of the {samples} samples the plant published")
    })
}

/// The start of the cause of a split drive's last measurements that never came and may not
/// have been published.
const NOT_FROM_PLANT_MACHINE: &str = "not received from the plant's machine";

/// How long the recorder of a run that ended well may take to get the end markers.
const END_WAIT: Duration = Duration::from_secs(5);

/// How long it may still take once the other machine of a split drive has left.
const END_GRACE: Duration = Duration::from_secs(1);

/// Waits for the recorder thread `rec` to end by itself (it has both end markers), at most
/// [`END_WAIT`], or [`END_GRACE`] once the split drive's `bridge` says the other machine
/// has left. Whether it ended.
fn recorder_ends_alone<T>(
    rec: &std::thread::JoinHandle<T>,
    mut bridge: Option<&mut bridge::Bridge>,
) -> bool {
    let start = Instant::now();
    let mut limit = END_WAIT;
    while !rec.is_finished() {
        if bridge.as_mut().is_some_and(|b| b.has_left()) {
            limit = limit.min(start.elapsed() + END_GRACE);
        }
        if start.elapsed() >= limit {
            return false;
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    true
}

/// The measurements missing at the end of a run whose plant is on another machine, which
/// the recorder could only label "the plant stopped" (there are no plant counters here).
/// With the plant's end marker at the run's last sample (`end`), the plant published them
/// and they never came: [`UNRECEIVED`]. Without an end marker, after a recorder that had
/// to be stopped (`recorder_ended` false), it is not known whether the plant published them:
/// the gap says that. Either fails the run with the count; None when nothing is missing at
/// the end, or when the plant's end marker came before the end (it stopped there).
fn remote_tail(
    gaps: &mut [Gap],
    end: Option<u64>,
    recorder_ended: bool,
    samples: u64,
) -> Option<String> {
    let tail = gaps.iter_mut().find(|g| {
        g.part == "measurement" && g.to + 1 == samples && g.cause == recorder::PLANT_STOPPED
    })?;
    let count = tail.to + 1 - tail.from;
    match end {
        Some(k) if k >= samples => {
            tail.cause = UNRECEIVED.into();
            Some(format!(
                "the plant's machine published samples {} to {} and they never reached the recorder",
                tail.from, tail.to
            ))
        }
        None if !recorder_ended => {
            tail.cause = format!(
                "{NOT_FROM_PLANT_MACHINE}, which sent no end of the run within {} s of the run's end here",
                END_WAIT.as_secs()
            );
            Some(format!(
                "the last {count} samples did not come from the plant's machine (no end of the run from it)"
            ))
        }
        _ => None,
    }
}

/// The run's bus: `--bus`, or this process's id.
fn bus_id_of(o: &RunOptions) -> String {
    o.bus
        .clone()
        .unwrap_or_else(|| format!("{}", std::process::id()))
}

/// A launcher's hold on its bus for as long as it runs: an abstract Unix socket named after
/// the bus, which only one process can bind and which the kernel releases when that process
/// ends, however it ends (no file). Two drives started at the same instant on one bus: one
/// gets it, the other is refused (each saw the other's command line before).
#[derive(Debug)]
pub struct BusClaim {
    _socket: std::os::unix::net::UnixListener,
}

fn claim_address(id: &str) -> Result<std::os::unix::net::SocketAddr> {
    use std::os::linux::net::SocketAddrExt;
    std::os::unix::net::SocketAddr::from_abstract_name(format!("drivelab-bus-{id}"))
        .map_err(|e| anyhow!("bus {id}: {e}"))
}

/// Takes bus `id` for this launcher, or fails in one line naming who has it; then checks
/// the bus as [`refuse_busy_bus`] does.
pub fn claim_bus(id: &str) -> Result<BusClaim> {
    match std::os::unix::net::UnixListener::bind_addr(&claim_address(id)?) {
        Ok(l) => {
            let claim = BusClaim { _socket: l };
            refuse_busy_bus(id, true)?;
            Ok(claim)
        }
        Err(e) if e.kind() == std::io::ErrorKind::AddrInUse => Err(held_by(id)),
        Err(e) => bail!("bus {id}: cannot claim it for this drive: {e}"),
    }
}

/// The error for a bus another launcher holds, naming it when it can be found.
fn held_by(id: &str) -> anyhow::Error {
    let me = std::process::id();
    let by = crate::faults::bus_users(id)
        .into_iter()
        .find(|(pid, what)| *pid != me && what.ends_with(" run"))
        .map(|(pid, what)| format!("pid {pid} ({what})"))
        .unwrap_or_else(|| "another drive".into());
    anyhow!("bus {id} is in use by {by}; choose another --bus or stop it first")
}

/// Fails with a one-line error naming a process when bus `id` is in use: a drive's launcher
/// holds it (unless `claimed`: this process does), a drive's stage host runs on it, or it has
/// a live iceoryx2 node (an attached monitor has one; a monitor still waiting for its drive
/// does not count).
pub fn refuse_busy_bus(id: &str, claimed: bool) -> Result<()> {
    if !claimed
        && std::os::unix::net::UnixListener::bind_addr(&claim_address(id)?)
            .is_err_and(|e| e.kind() == std::io::ErrorKind::AddrInUse)
    {
        return Err(held_by(id));
    }
    let me = std::process::id();
    let users: Vec<(u32, String)> = crate::faults::find_services(id)
        .into_iter()
        .filter(|h| h.2 != me)
        .map(|(_, process, pid)| (pid, format!("the stage host of process {process}")))
        .collect();
    if let Some((pid, what)) = users.first() {
        bail!(
            "bus {id} is in use by pid {pid} ({what}){}; choose another --bus or stop it first",
            if users.len() > 1 {
                format!(" and {} more", users.len() - 1)
            } else {
                String::new()
            }
        );
    }
    let nodes = bus::live_nodes(id)?;
    if !nodes.is_empty() {
        bail!(
            "bus {id} has {} live iceoryx2 node(s) ({}); choose another --bus or stop them first",
            nodes.len(),
            nodes.join(", ")
        );
    }
    Ok(())
}

/// The CPU wake-up latency request of a real-time drive, or why there is none (the caller's
/// one-line warning; an error with `--rt-strict`).
fn cpu_latency_request(
    sc: &Scenario,
    o: &RunOptions,
) -> Result<(
    Option<drivelab_runtime::rt::CpuLatencyRequest>,
    Option<String>,
)> {
    use drivelab_runtime::config::CpuLatency;
    use drivelab_runtime::rt::{CpuLatencyRequest, CPU_DMA_LATENCY};
    let CpuLatency::Us(v) = sc.timing.cpu_latency_us else {
        return Ok((None, None));
    };
    if o.clock != Clock::Realtime || o.no_rt {
        return Ok((None, None));
    }
    match CpuLatencyRequest::hold(v) {
        Ok(r) => Ok((Some(r), None)),
        Err(e) => {
            let why = format!(
                "cannot hold a CPU wake-up latency request of {v} µs ({CPU_DMA_LATENCY}: {e})"
            );
            if o.rt_strict {
                bail!("--rt-strict: {why}");
            }
            Ok((None, Some(why)))
        }
    }
}

/// With `--rt-strict`, each of this machine's processes has its executable ask for its
/// placement (memory lock, CPU, SCHED_FIFO priority) and exit: a missing privilege is one
/// line, before the run folder is made. Through a runner the executable may not run here as
/// it is; its hosts report then.
fn check_placements(o: &RunOptions, topo: &TopologyPlan) -> Result<()> {
    if !o.rt_strict || o.no_rt || o.clock == Clock::Inprocess || runner_of(o)?.is_some() {
        return Ok(());
    }
    let here = (0..topo.processes.len()).filter(|i| !topo.away.contains(i));
    for p in here.map(|i| &topo.processes[i]) {
        // Lockstep keeps the cores and the locked memory but not the priorities.
        let mut p = p.clone();
        if o.clock == Clock::Lockstep {
            p.priority = None;
        }
        spawn::check_rt(&p, &process_binary(&p, Path::new("/"))?)?;
    }
    Ok(())
}

/// Applies `--topology`, resolves the scenario's topology against the stages' declarations
/// (a user's executable is asked with `--describe`) and makes `exec` paths absolute. An error
/// names the file that gives the topology (the `--topology` file or the scenario).
pub fn resolve_topology(sc: &mut Scenario, sc_src: &Path, o: &RunOptions) -> Result<TopologyPlan> {
    let mut origin = sc_src.display().to_string();
    if let Some(t) = &o.topology {
        let (file, path) =
            drivelab_runtime::topology::load(t).map_err(|e| anyhow!("--topology: {e}"))?;
        sc.process = file.process;
        absolute_execs(&mut sc.process, &path)?;
        sc.placement = drivelab_runtime::config::Placement::default();
        sc.validate().map_err(|e| anyhow!("--topology {t}: {e}"))?;
        origin = format!("--topology: {}", path.display());
    }
    let mut procs = sc.topology();
    absolute_execs(&mut procs, sc_src)?;
    let runner = runner_of(o)?;
    // Every `exec` of this machine's processes is checked before anything starts, also one
    // that hosts built-in stages only (it is asked nothing, but it is started).
    let here = o.zenoh.as_ref().and_then(|z| z.machine.as_deref());
    // A process this machine runs (every one, unless the drive is split).
    let on_this_machine = |p: &drivelab_runtime::topology::ProcessSpec| {
        here.is_none() || p.machine.as_deref() == here
    };
    for p in &procs {
        if let (Some(exe), true) = (&p.exec, on_this_machine(p)) {
            check_exec(exe, runner.is_some())
                .map_err(|e| anyhow!("{origin}: process '{}': {e}", p.name))?;
        }
    }
    let mut described: BTreeMap<String, Vec<StageInfo>> = BTreeMap::new();
    let mut replaced: BTreeMap<String, String> = BTreeMap::new();
    let scr: &Scenario = sc;
    let sc_text = toml::to_string(scr)?;
    let resolved = drivelab_runtime::topology::resolve(&procs, &mut |p, stage| {
        let builtin = drivelab_runtime::topology::builtin_info(scr, stage);
        // A user's executable runs its own stage of a built-in's name in the built-in's place
        // (the plant's name it may not take). Asked for every process, also those of the
        // other machine of a split drive (as for any user stage): both machines then build
        // the same plan, and send each other what the replacement reads.
        let ask = match (&p.exec, &builtin) {
            (None, _) => false,
            (Some(_), None) => true,
            (Some(_), Some(_)) => drivelab_runtime::stages::REPLACEABLE.contains(&stage),
        };
        let Some(exe) = p.exec.clone().filter(|_| ask) else {
            return builtin.ok_or_else(|| format!("unknown stage '{stage}'"));
        };
        if !described.contains_key(&exe) {
            described.insert(
                exe.clone(),
                describe(&exe, &sc_text, runner.as_ref())
                    .map_err(|e| format!("process '{}': {e:#}", p.name))?,
            );
        }
        match (described[&exe].iter().find(|i| i.name == stage), builtin) {
            (Some(mine), Some(b)) => {
                drivelab_runtime::topology::check_replacement(mine, &b, &exe)
                    .map_err(|e| format!("process '{}': {e}", p.name))?;
                replaced.insert(stage.to_string(), exe.clone());
                Ok(mine.clone())
            }
            (Some(mine), None) => Ok(mine.clone()),
            (None, Some(b)) => Ok(b),
            (None, None) => {
                let hosted: Vec<&str> = described[&exe].iter().map(|i| i.name.as_str()).collect();
                Err(format!(
                    "process '{}': its executable {exe} hosts no stage '{stage}' (its own stages: {}; and the built-in ones)",
                    p.name,
                    if hosted.is_empty() { "none".to_string() } else { hosted.join(", ") }
                ))
            }
        }
    })
    .map_err(|e| anyhow!("{origin}: {e}"))?;
    // An `exec` that hosts built-in stages only was asked nothing above, nor was the built-in
    // host under a `--runner`: each must still answer as a stage host (`/bin/true` would
    // fail its start after the run folder exists).
    // A runner that cannot start anything fails every process: refused before the run.
    let runner = runner.filter(|_| o.clock != Clock::Inprocess);
    if let Some(r) = &runner {
        r.check().map_err(|e| anyhow!(e))?;
    }
    for p in procs.iter().filter(|p| on_this_machine(p)) {
        let exe = match (&p.exec, &runner) {
            (Some(exe), _) => exe.clone(),
            (None, Some(_)) => spawn::process_binary(p, Path::new("/"))?
                .display()
                .to_string(),
            (None, None) => continue,
        };
        if let std::collections::btree_map::Entry::Vacant(slot) = described.entry(exe) {
            let info = describe(slot.key(), &sc_text, runner.as_ref()).map_err(|e| {
                let through = runner
                    .as_ref()
                    .map(|r| format!(" (started through the runner '{}')", r.display()))
                    .unwrap_or_default();
                anyhow!("{origin}: process '{}'{through}: {e:#}", p.name)
            })?;
            slot.insert(info);
        }
    }
    // A `[stages.NAME]` table for a stage no process hosts is a typo or a leftover: its
    // parameters would be ignored.
    let hosted = resolved.stage_names();
    if let Some(name) = sc.stages.keys().find(|n| !hosted.contains(n)) {
        bail!(
            "{}: [stages.{name}]: no process hosts a stage '{name}' (the topology's stages: {})",
            sc_src.display(),
            hosted.join(", ")
        );
    }
    // A built-in stage's name is a user's replacement's table; where the built-in runs (on
    // this machine) its settings would be ignored.
    if let Some((name, p)) = sc
        .stages
        .keys()
        .filter(|n| drivelab_runtime::stages::BUILTIN.contains(&n.as_str()))
        .filter(|n| !replaced.contains_key(*n))
        .find_map(|n| {
            procs
                .iter()
                .find(|p| p.stages.contains(n) && on_this_machine(p))
                .map(|p| (n, p))
        })
    {
        // The topology that makes the built-in run, when it is not the scenario's.
        let of = match &o.topology {
            Some(t) => format!(" of the topology {t}"),
            None => String::new(),
        };
        let tables = match name.as_str() {
            "observer" => "[observer]",
            "current-loop" => "[current_loop]",
            _ => "[speed_loop] and [rates]",
        };
        bail!(
            "{}: [stages.{name}] is for a user's stage that replaces the built-in {name}, and the built-in runs here (process '{}'{of} {}): it takes its settings from {tables}",
            sc_src.display(),
            p.name,
            match &p.exec {
                Some(exe) => format!("starts {exe}, which declares no stage '{name}'"),
                None => "starts no executable that replaces it".to_string(),
            }
        );
    }
    // A process with an `exec` that runs none of that executable's own stages runs built-in
    // ones only: what a wrapper of drivelab-host means, and what a registration left out of
    // `host_main` or an `exec` on the wrong process does without a word. Said in one note
    // line where a built-in it runs could have been replaced (a process that also hosts one
    // of the executable's stages, as the examples' one-process drives do, gets none).
    let notes = procs
        .iter()
        .filter(|p| on_this_machine(p))
        .filter_map(|p| {
            let exe = p.exec.as_ref()?;
            let declared = described.get(exe)?;
            let builtin: Vec<&str> = p
                .stages
                .iter()
                .map(String::as_str)
                .filter(|s| drivelab_runtime::stages::REPLACEABLE.contains(s))
                .filter(|s| !replaced.contains_key(*s))
                .collect();
            let own: Vec<&str> = declared.iter().map(|i| i.name.as_str()).collect();
            let runs_its_own = p.stages.iter().any(|s| own.contains(&s.as_str()));
            (!builtin.is_empty() && !runs_its_own).then(|| {
                format!(
                    "process '{}' runs the built-in {}: its exec {exe} declares no stage of {} (its own stages: {})",
                    p.name,
                    builtin.join(", the built-in "),
                    if builtin.len() == 1 { "that name" } else { "those names" },
                    if own.is_empty() { "none".to_string() } else { own.join(", ") }
                )
            })
        })
        .collect();
    sc.process = resolved.processes.iter().map(|(p, _)| p.clone()).collect();
    sc.placement = drivelab_runtime::config::Placement::default();
    let mut plan = TopologyPlan::from_resolved(&resolved);
    plan.replaced = replaced;
    plan.notes = notes;
    Ok(plan)
}

/// Checks that `exe` (absolute) is a file that can be run: it exists, is a regular file and,
/// unless a runner starts it (qemu-user reads it), has an execute permission. Returns its
/// metadata.
fn check_exec(exe: &str, through_runner: bool) -> Result<std::fs::Metadata> {
    use std::os::unix::fs::PermissionsExt;
    let md = match std::fs::metadata(exe) {
        Ok(m) => m,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            bail!("exec {exe} not found (a wrong path, or not built yet: cargo build --release in its crate)")
        }
        Err(e) => bail!("exec {exe}: {e}"),
    };
    if !md.is_file() {
        bail!("exec {exe} is not a file (it must name the executable that hosts the process's stages)");
    }
    if !through_runner && md.permissions().mode() & 0o111 == 0 {
        bail!("exec {exe} is not executable (no execute permission: chmod +x it)");
    }
    // A script whose interpreter is missing: its start would say "No such file or directory"
    // of a file that exists.
    if let Some(why) =
        drivelab_runtime::topology::missing_interpreter(Path::new(exe)).filter(|_| !through_runner)
    {
        bail!("exec {exe}: {why}");
    }
    Ok(md)
}

/// Makes every `exec` of `procs` absolute, relative paths taken from the folder of `file`
/// (the scenario or topology file that names them), so that the hosts find them whatever
/// their working folder.
fn absolute_execs(
    procs: &mut [drivelab_runtime::topology::ProcessSpec],
    file: &Path,
) -> Result<()> {
    // `Path::new("topology.toml").parent()` is `Some("")`: the working folder.
    let dir = file.parent().filter(|d| !d.as_os_str().is_empty());
    let base = std::path::absolute(dir.unwrap_or(Path::new(".")))
        .with_context(|| format!("the folder of {}", file.display()))?;
    for p in procs.iter_mut() {
        let relative = p
            .exec
            .as_deref()
            .is_some_and(|e| Path::new(e).is_relative());
        if let Some(e) = drivelab_runtime::topology::exec_path(p, &base) {
            // A relative path's folder as the kernel resolves it
            // (`…/examples/x/../../target/release/h` is `…/target/release/h`), the file's own
            // name as given; an absolute path stays as written, and a folder that does not
            // exist is left for the exec check to name.
            let e = match (e.parent().map(std::fs::canonicalize), e.file_name()) {
                (Some(Ok(dir)), Some(name)) if relative => dir.join(name),
                _ => e,
            };
            p.exec = Some(e.display().to_string());
        }
    }
    Ok(())
}

/// How long a user's stage executable may take to answer `--describe`.
const DESCRIBE_TIMEOUT: Duration = Duration::from_secs(10);
/// The most output of `--describe` read (a stage list is a few kB).
const DESCRIBE_MAX_BYTES: u64 = 1 << 20;

/// What an executable's answer to `--describe` depends on: its path, modification time and
/// size, the runner it is started through, and the scenario's text.
type DescribeKey = (String, Option<std::time::SystemTime>, u64, String, String);

/// The answers given so far in this process: a campaign checks thousands of cases against one
/// topology, and each answer costs a process start (about 6 ms). A rebuilt executable (another
/// modification time or size) is asked again.
static DESCRIBED: std::sync::Mutex<BTreeMap<DescribeKey, Vec<StageInfo>>> =
    std::sync::Mutex::new(BTreeMap::new());

/// Asks a user's stage executable which stages it hosts ([`spawn::ask`]): it must exit within
/// [`DESCRIBE_TIMEOUT`] with at most [`DESCRIBE_MAX_BYTES`] of output. An answer is asked for
/// once per [`DescribeKey`].
fn describe(
    exe: &str,
    sc_text: &str,
    runner: Option<&drivelab_runtime::runner::Runner>,
) -> Result<Vec<StageInfo>> {
    let md = check_exec(exe, runner.is_some())?;
    let key = (
        exe.to_string(),
        md.modified().ok(),
        md.len(),
        format!("{runner:?}"),
        sc_text.to_string(),
    );
    // A panic elsewhere while the lock was held leaves the map as it was: still usable.
    let answers = || DESCRIBED.lock().unwrap_or_else(|e| e.into_inner());
    if let Some(info) = answers().get(&key) {
        return Ok(info.clone());
    }
    let info = ask_describe(exe, sc_text, runner)?;
    answers().insert(key, info.clone());
    Ok(info)
}

/// [`describe`] without the memory of earlier answers.
fn ask_describe(
    exe: &str,
    sc_text: &str,
    runner: Option<&drivelab_runtime::runner::Runner>,
) -> Result<Vec<StageInfo>> {
    // A folder of a fresh random name that only this user can enter, gone when `dir` drops:
    // in a temp folder that anyone can write, a name known in advance could be made first by
    // another user, with a link in it that the scenario would be written through.
    let dir = tempfile::Builder::new()
        .prefix("drivelab-describe-")
        .tempdir()
        .context("cannot make a scratch folder in the temp folder for --describe")?;
    let f = dir.path().join("scenario.toml");
    drivelab_runtime::files::write(&f, sc_text)?;
    let mut cmd = drivelab_runtime::runner::command(runner, exe);
    cmd.arg("--describe").arg("--scenario").arg(&f);
    let answer = spawn::ask(cmd, DESCRIBE_TIMEOUT, DESCRIBE_MAX_BYTES)
        .with_context(|| format!("cannot run {exe} --describe"))?;
    let _ = dir.close();
    let spawn::Answer {
        status,
        stdout,
        stderr,
        in_time,
    } = answer;
    if !in_time {
        bail!(
            "{exe} --describe did not answer within {} s (killed)",
            DESCRIBE_TIMEOUT.as_secs()
        );
    }
    // Before the exit status: past the limit its output pipe was closed, so a program that
    // kept writing died of SIGPIPE, which is not what went wrong.
    if stdout.len() as u64 > DESCRIBE_MAX_BYTES {
        bail!("{exe} --describe: more than {DESCRIBE_MAX_BYTES} bytes of output, not a stage list");
    }
    let status = status.with_context(|| format!("{exe} --describe"))?;
    if !status.success() {
        let said = drivelab_runtime::text::join_lines(&String::from_utf8_lossy(&stderr), " / ");
        bail!(
            "{exe} --describe failed ({status}){}{said}",
            if said.is_empty() { "" } else { ": " },
        );
    }
    let info: Vec<StageInfo> = serde_json::from_slice(&stdout)
        .map_err(|e| anyhow!("{exe} --describe: not a stage list ({e})"))?;
    // Which declaration would a process hosting it get? Neither: the answer is refused.
    for (i, st) in info.iter().enumerate() {
        if info[..i].iter().any(|o| o.name == st.name) {
            bail!("{exe} --describe: stage '{}' is declared twice", st.name);
        }
    }
    Ok(info)
}

/// The warning for a real-time run that missed most of its deadlines without a fault: the
/// chain does not hold its rate on this machine (a drive split over a network whose round
/// trip is longer than a sample, a rate too high for the CPU). Faults miss deadlines by
/// design, so a run with faults gets none.
pub fn rate_warning(summary: &serde_json::Value, realtime: bool) -> Option<String> {
    let misses = summary["deadline_misses"].as_u64()?;
    let samples = summary["samples"].as_u64()?;
    let faulted = summary["faults"].as_array().is_some_and(|f| !f.is_empty());
    (realtime && !faulted && samples > 0 && misses * 2 > samples).then(|| {
        format!(
            "{misses} of {samples} deadlines missed: this chain does not hold {} kHz here (cycle latency in summary.json → latency_us.cycle)",
            summary["rate_hz"].as_f64().unwrap_or(0.0) / 1000.0
        )
    })
}

/// A run's options checked and resolved, before anything is created.
struct Prepared {
    sc: Scenario,
    topo: TopologyPlan,
    plan: Vec<crate::faults::Fault>,
    hogs: Vec<crate::faults::hog::Hog>,
    expectations: Vec<crate::expect::Expectation>,
    /// Simulated kills and stops not made, each with why ([`after_the_plant`]).
    not_made: Vec<(u64, String)>,
    /// Configuration that this clock does not apply, each in one line: said, not dropped in
    /// silence (and kept in summary.json → warnings).
    warnings: Vec<String>,
    /// What the scenario schedules after a `--duration` shorter than its own, left out
    /// ([`Scenario::set_duration`]; summary.json → not_reached).
    not_reached: Vec<String>,
}

/// A simulated run whose plant is killed for good ([`Scenario::plant_gone_at`]) ends at
/// that kill, as a real-time drive stops when its plant dies: the kills and stops planned
/// after it are taken out of `sc` and returned, each as (the drive's end, why it was not
/// made), worded as the real-time supervisor words them.
fn after_the_plant(sc: &mut Scenario) -> Vec<(u64, String)> {
    let Some(gone) = sc.plant_gone_at() else {
        return Vec::new();
    };
    let fs = sc.rates.sample_hz;
    let mut late = Vec::new();
    sc.inject.retain(|i| {
        let k = (i.at_s * fs).round() as u64;
        let the_kill = i.target == "plant" && k == gone;
        if !i.kind.downs_stage() || k < gone || the_kill {
            return true;
        }
        late.push((gone, ended_before(&i.spec(), gone, k)));
        false
    });
    late
}

/// Why a planned fault was not made when the drive ended at sample `end`, before the fault's
/// sample `k`, worded as the real-time supervisor words it.
pub(crate) fn ended_before(spec: &str, end: u64, k: u64) -> String {
    format!("{spec}: not injected: the drive ended at sample {end}, before the fault's sample {k}")
}

/// The kills, stops and hogs of a real-time plan due at or after the interrupted drive's
/// `end` that were not made (no `inject` event of their service from their sample on, no
/// `hog` event of theirs), each as (the drive's end, why) ([`DriveEnd::not_reached`]).
fn interrupted_kills(
    plan: &[crate::faults::Fault],
    hogs: &[crate::faults::hog::Hog],
    events: &[supervisor::SupEvent],
    end: DriveEnd,
    fs: f64,
) -> Vec<(u64, String)> {
    let kills = plan.iter().filter_map(|f| {
        let k = (f.at_s * fs).round() as u64;
        let sent = events.iter().any(|e| {
            matches!(
                e.kind,
                supervisor::EventKind::Inject {
                    monitor_pid: None,
                    ..
                }
            ) && e.service == f.service
                && e.k >= k
        });
        (!sent).then(|| end.not_reached(&f.spec(), k)).flatten()
    });
    let hogs = hogs.iter().filter_map(|h| {
        let started = events
            .iter()
            .any(|e| matches!(&e.kind, supervisor::EventKind::Hog { hog, .. } if hog == h));
        let k = (h.at_s * fs).round() as u64;
        (!started).then(|| end.not_reached(&h.spec(), k)).flatten()
    });
    kills.chain(hogs).collect()
}

/// Where a drive ended: the first sample it did not make, and whether a stop signal ended it
/// there (docs/architecture.md, "Fault model").
#[derive(Debug, Clone, Copy)]
pub struct DriveEnd {
    /// The first sample the drive did not make.
    pub k: u64,
    /// A stop signal ended it before the run's samples were made.
    pub interrupted: bool,
}

impl DriveEnd {
    /// A drive that made every sample there is (unit tests).
    #[cfg(test)]
    pub(crate) const NEVER: DriveEnd = DriveEnd {
        k: u64::MAX,
        interrupted: false,
    };

    /// Whether a fault whose first sample is `k` came after the drive's end.
    pub fn before(&self, k: u64) -> bool {
        k >= self.k
    }

    /// The planned fault `spec` whose first sample is `k`, when the drive never reached it:
    /// (the drive's end, why it was not made), worded as [`ended_before`], or as interrupted.
    pub fn not_reached(&self, spec: &str, k: u64) -> Option<(u64, String)> {
        let end = self.k;
        self.before(k).then(|| {
            let why = if self.interrupted {
                format!("{spec}: not injected: the drive was interrupted at sample {end}, before the fault's sample {k}")
            } else {
                ended_before(spec, end, k)
            };
            (end, why)
        })
    }
}

/// Checks a run's options the way [`run`] does before it creates anything (scenario,
/// duration, topology, faults against the run's stages and duration, expectations), without
/// creating anything or touching a bus, and returns the configuration warnings the run would
/// give, with the line saying what a shorter run leaves out ([`not_reached_line`]). A
/// campaign checks every run with it before the first one starts.
pub fn check(o: &RunOptions) -> Result<Vec<String>> {
    prepare(o).map(|p| {
        let note = not_reached_line(p.sc.duration_s, &p.not_reached);
        p.warnings.into_iter().chain(note).collect()
    })
}

/// Everything [`run`] checks and resolves before the run folder is made.
fn prepare(o: &RunOptions) -> Result<Prepared> {
    if o.audit_syscalls && o.clock == Clock::Inprocess {
        return Err(usage(
            "--audit-syscalls audits the stage hosts' loops: use --clock realtime or lockstep \
             (the inprocess clock starts no host)"
                .into(),
        ));
    }
    if o.zenoh.is_some() && o.clock == Clock::Inprocess {
        let flag = if o.zenoh.as_ref().is_some_and(|z| z.connect) {
            "--zenoh-connect"
        } else {
            "--zenoh-listen"
        };
        return Err(usage(format!(
            "{flag} needs a drive on a bus: use --clock realtime or lockstep"
        )));
    }
    if o.foxglove.is_some() {
        crate::foxglove::check_clock(o.clock == Clock::Inprocess)?;
    }
    if let Some(b) = &o.bus {
        bus::check_bus_id(b)?;
        // Before the run folder is made: a busy bus leaves nothing behind.
        refuse_busy_bus(b, false)?;
    }
    let (mut sc, sc_src) = Scenario::load(&o.scenario).map_err(|e| anyhow!(e))?;
    let not_reached = match o.duration_s {
        Some(d) => set_duration(&mut sc, d).map_err(|e| anyhow!("--duration {d}: {e}"))?,
        None => Vec::new(),
    };
    let expectations =
        crate::expect::collect(&sc.expect, &sc_src.display().to_string(), &o.expect)?;
    // Sensor faults go into the resolved scenario: every plant applies them.
    crate::faults::sensor::add_to_scenario(&o.faults, &mut sc)?;
    let mut topo = resolve_topology(&mut sc, &sc_src, o)?;
    // A drive split across two machines: the processes of the other one are away.
    if let Some(m) = o.zenoh.as_ref().and_then(|z| z.machine.as_deref()) {
        let machines = drivelab_runtime::topology::machines(&topo.processes);
        if !machines.iter().any(|x| x == m) {
            bail!(
                "--machine {m}: {}",
                if machines.is_empty() {
                    "the topology names no machines (give its processes `machine = \"...\"`, e.g. --topology split-hil)".to_string()
                } else {
                    format!("the topology's machines are {}", machines.join(", "))
                }
            );
        }
        topo.away = (0..topo.processes.len())
            .filter(|&i| topo.processes[i].machine.as_deref() != Some(m))
            .collect();
    }
    // The CPUs this machine's processes are pinned to, refused before anything is created.
    // With --rt-strict, one this launcher may not use (its process would fail its start;
    // without it, it warns and runs unpinned). In real time, also without it, one the
    // machine does not have (`cpuN` missing from the kernel's list): the placement is the
    // experiment, and one the machine has but the drive may not use only warns, as a missing
    // privilege does. Lockstep's processes keep their cores but not their timing: there a
    // missing CPU warns and runs unpinned, so that a target's topology still runs on a
    // smaller machine.
    const CPU_SYSFS: &str = "/sys/devices/system/cpu";
    let strict = o.rt_strict && o.clock != Clock::Inprocess;
    let check_present = o.clock == Clock::Realtime && Path::new(CPU_SYSFS).is_dir();
    if strict || check_present {
        let cpus = crate::faults::hog::allowed_cpus();
        let here = (0..topo.processes.len()).filter(|i| !topo.away.contains(i));
        for (p, c) in here.filter_map(|i| topo.processes[i].cpu.map(|c| (&topo.processes[i], c))) {
            if strict && !cpus.contains(&c) {
                bail!(
                    "--rt-strict: process {} is pinned to CPU {c}, which this drive may not use (CPUs: {})",
                    p.name,
                    crate::faults::hog::cpu_list(&cpus)
                );
            }
            if check_present && !Path::new(&format!("{CPU_SYSFS}/cpu{c}")).exists() {
                bail!(
                    "process {} is pinned to CPU {c}, which this machine does not have (this \
                     drive may use CPUs {}): change its `cpu`",
                    p.name,
                    crate::faults::hog::cpu_list(&cpus)
                );
            }
        }
    }
    // Faults are checked before anything is created: a bad plan leaves nothing behind.
    // Lockstep and in process simulate kills and stops at their sample.
    let simulated = o.clock != Clock::Realtime;
    // The scenario's own [[inject]] tables, before the command line's faults join them.
    crate::bus_faults::check_tables(&sc, &topo)
        .map_err(|e| anyhow!("{}: {e:#}", sc_src.display()))?;
    // Faults reach the stages of this machine only.
    let stage_names: Vec<String> = topo
        .stages
        .iter()
        .filter(|s| {
            topo.process_of(&s.name)
                .is_some_and(|i| !topo.away.contains(&i))
        })
        .map(|s| s.name.clone())
        .collect();
    let mut plan = crate::faults::plan(
        &o.faults,
        sc.duration_s,
        sc.rates.sample_hz,
        o.fault_seed,
        0.3,
        &stage_names,
    )?;
    if simulated {
        // The restart policy holds as in real time: with `never` a killed stage stays dead.
        let restart_ms = (o.restart != Restart::Never).then_some(o.lockstep_restart_ms);
        crate::faults::schedule_simulated(&plan, restart_ms, &mut sc)?;
        plan.clear();
    }
    let not_made = after_the_plant(&mut sc);
    // Bus faults (delay, drop, corrupt) go to every stage host in the resolved scenario.
    crate::bus_faults::schedule(&o.faults, &mut sc, &topo)?;
    if o.clock == Clock::Realtime {
        check_delays(&sc, &topo, realtime_limit(&sc, &o.faults))?;
    }
    let hogs = crate::faults::hog::plan(
        &o.faults,
        sc.duration_s,
        o.clock == Clock::Realtime,
        &crate::faults::hog::allowed_cpus(),
    )?;
    for h in &hogs {
        crate::faults::hog::check_privilege(h)?;
    }
    if let (true, Some((runtime, period))) = (
        o.verbose && !hogs.is_empty(),
        crate::faults::hog::rt_throttling(),
    ) {
        crate::errln!(
            "drivelab: RT throttling (read, not changed): sched_rt_runtime_us = {runtime} of sched_rt_period_us = {period}; a hog leaves the rest to tasks that are not real-time"
        );
    }
    // Simulated kills and stops, from the plan or a scenario's own [[inject]] tables.
    crate::faults::check_simulated(&sc.inject, simulated)?;
    if o.clock == Clock::Inprocess {
        if let Some(p) = topo.processes.iter().find(|p| p.exec.is_some()) {
            bail!(
                "--clock inprocess runs the built-in stages only, in this process; process '{}' is started from an executable of its own (exec): use --clock lockstep",
                p.name
            );
        }
    }
    let twins: Vec<&str> = topo
        .processes
        .iter()
        .filter(|p| p.standby)
        .map(|p| p.name.as_str())
        .collect();
    let warnings: Vec<String> = (o.clock != Clock::Realtime && !twins.is_empty())
        .then(|| {
            format!(
                "standby = true (process {}) applies in real time only: the {} clock starts no standby twin",
                twins.join(", "),
                o.clock.name()
            )
        })
        .into_iter()
        .collect();
    Ok(Prepared {
        sc,
        topo,
        plan,
        hogs,
        expectations,
        not_made,
        warnings,
        not_reached,
    })
}

/// Why a drive stopped when its recorder failed (its error follows).
const RECORDER_FAILED: &str = "the recorder failed";

/// Why a run that a stop signal (SIGINT, SIGTERM, SIGHUP …) stopped ended early.
pub(super) fn interrupted() -> String {
    format!(
        "interrupted ({}): drive stopped",
        drivelab_runtime::service::stop_signal_name()
    )
}

/// With `--audit-syscalls`: the system calls beyond the waits that every process's loop made,
/// summed (`summary.json → stray_syscalls`); None when a process has no count (its
/// statistics are missing), so that `--expect 'stray_syscalls == 0'` cannot pass on a loop
/// nobody counted.
fn stray_syscalls_total(processes: &serde_json::Value) -> Option<u64> {
    let procs = processes.as_object()?;
    procs.values().try_fold(0, |sum, p| {
        let calls = p.get("stray_syscalls")?.as_object()?;
        Some(sum + calls.values().filter_map(|n| n.as_u64()).sum::<u64>())
    })
}

/// With `--audit-syscalls`: one line saying which loops made which calls beyond their waits
/// (or that none did, or which process was not counted).
pub fn stray_syscalls_line(summary: &serde_json::Value) -> Option<String> {
    summary.get("stray_syscalls")?;
    let procs = summary["processes"].as_object()?;
    let mut found = Vec::new();
    let mut uncounted = Vec::new();
    for (name, p) in procs {
        match p.get("stray_syscalls").and_then(|s| s.as_object()) {
            None => uncounted.push(name.as_str()),
            Some(calls) if !calls.is_empty() => {
                let each: Vec<String> = calls
                    .iter()
                    .map(|(call, n)| format!("{call} ×{}", n.as_u64().unwrap_or(0)))
                    .collect();
                found.push(format!("{name}: {}", each.join(", ")));
            }
            Some(_) => {}
        }
    }
    let mut line = if found.is_empty() {
        format!(
            "system-call audit: no call beyond the waits in the loops of {} of {} processes",
            procs.len() - uncounted.len(),
            procs.len()
        )
    } else {
        format!(
            "system-call audit: calls beyond the waits in the real-time loops: {}",
            found.join("; ")
        )
    };
    if !uncounted.is_empty() {
        line.push_str(&format!(
            " (not counted: {}, no statistics)",
            uncounted.join(", ")
        ));
    }
    Some(line)
}

/// Runs a scenario end to end and writes the run folder.
pub fn run(o: &RunOptions) -> Result<RunResult> {
    // The launcher stops on a stop signal (SIGINT, SIGTERM, SIGHUP …) the same way the
    // services do.
    crate::common::install_signal_handlers()?;
    if o.timing_csv && o.clock != Clock::Realtime {
        return Err(usage(format!(
            "--timing-csv needs the realtime clock: the {} clock has no sample instants to time against",
            o.clock.name()
        )));
    }
    if o.runner.is_some() && o.clock == Clock::Inprocess {
        return Err(usage(
            "--runner needs a clock that starts processes (realtime or lockstep): the inprocess \
             clock runs every stage in this process"
                .into(),
        ));
    }
    let Prepared {
        sc,
        topo,
        plan,
        hogs,
        expectations,
        not_made,
        warnings,
        not_reached,
    } = prepare(o)?;
    if !o.quiet_warnings {
        for w in &warnings {
            crate::errln!("drivelab: warning: {w}");
        }
        if let Some(line) = not_reached_line(sc.duration_s, &not_reached) {
            crate::errln!("drivelab: note: {line}");
        }
    }
    // The bus is this drive's until it returns (two launchers that passed the check above at
    // the same time: one of them gets it).
    let _claim = match o.clock {
        Clock::Inprocess => None,
        Clock::Lockstep | Clock::Realtime => Some(claim_bus(&bus_id_of(o))?),
    };
    // The live stream's address is taken before anything is created: an address in use
    // leaves nothing behind.
    let live = match o.foxglove {
        Some(addr) => {
            let l = crate::foxglove::Live::start(
                addr,
                sc.rates.sample_hz,
                crate::hub::rt_cores(&sc),
                &[("scenario", sc.name.clone())],
            )?;
            crate::errln!(
                "drivelab: Foxglove WebSocket server on ws://{} (subprotocol {})",
                l.addr(),
                crate::foxglove::SUBPROTOCOL
            );
            Some(Arc::new(l))
        }
        None => None,
    };
    // A real-time drive holds the CPU wake-up latency request while it runs (released when
    // this value drops, or by the kernel if the launcher dies).
    let (latency_request, latency_error) = cpu_latency_request(&sc, o)?;
    check_placements(o, &topo)?;
    let out = match &o.out {
        Some(out) => out.clone(),
        None => new_default_folder(&default_stem(&sc, o.clock))?,
    };
    let _folder = claim_run_folder(&out)?;
    // Said once the folder is taken, so that a refused folder is the one line.
    match (&latency_request, &latency_error) {
        (Some(r), _) if o.verbose => crate::errln!(
            "drivelab: holding a CPU wake-up latency request of {} µs ({}) while the drive runs",
            r.value_us,
            drivelab_runtime::rt::CPU_DMA_LATENCY
        ),
        (_, Some(why)) => crate::errln!(
            "drivelab: warning: {why}; idle CPUs may wake late ([timing] cpu_latency_us = \"none\" silences this)"
        ),
        _ => {}
    }
    if !o.quiet_warnings {
        for line in &topo.notes {
            crate::errln!("drivelab: note: {line}");
        }
    }
    // Processes that share a core and a SCHED_FIFO priority (real time only: lockstep does
    // not use the priorities).
    if o.clock == Clock::Realtime && !o.no_rt {
        let here: Vec<_> = (0..topo.processes.len())
            .filter(|i| !topo.away.contains(i))
            .map(|i| topo.processes[i].clone())
            .collect();
        for w in drivelab_runtime::topology::placement_warnings(&here) {
            crate::errln!("drivelab: warning: {w}");
        }
        for w in topo.timed_waits() {
            crate::errln!("drivelab: warning: {w}");
        }
    }
    let out = out.canonicalize()?;
    let sc_path = out.join("scenario.toml");
    drivelab_runtime::files::write(&sc_path, resolved_toml(&sc, &not_reached)?)
        .with_context(|| format!("write {}", sc_path.display()))?;
    drivelab_runtime::files::write(out.join("topology.json"), serde_json::to_vec_pretty(&topo)?)?;
    let sinks = sinks::Sinks::new(
        Some(crate::trace_mcap::McapTrace::create(
            &out.join("trace.mcap"),
        )?),
        live.clone(),
    );
    let wall = Instant::now();
    let BusRun {
        rows,
        gaps,
        stats,
        processes,
        info,
        events,
        failure,
        hog_latency,
        bridge,
    } = match o.clock {
        Clock::Inprocess => {
            // A plant killed for good ends the drive at its kill (`Scenario::samples_made`).
            let rows = drivelab_runtime::stages::try_run_inprocess_until(
                &sc,
                drivelab_runtime::service::stop_requested,
            )?;
            let interrupted_here = (rows.len() as u64) < sc.samples_made();
            // Rows without a command are listed as the recorder lists them in the other
            // clocks; the samples not done (interrupted, or no plant) are one gap to the end
            // (named below).
            let mut gaps = recorder::command_gaps(&rows);
            let done = rows.len() as u64;
            if done < sc.samples() {
                gaps.push(Gap {
                    from: done,
                    to: sc.samples() - 1,
                    part: "measurement",
                    cause: String::new(),
                });
            }
            BusRun {
                rows,
                gaps,
                stats: None,
                processes: json!({}),
                info: json!({ "deadline_misses": 0, "end_k": done }),
                events: Vec::new(),
                failure: interrupted_here.then(interrupted),
                hog_latency: Vec::new(),
                bridge: None,
            }
        }
        Clock::Lockstep | Clock::Realtime => {
            let clock = if o.clock == Clock::Lockstep {
                BusClock::Lockstep
            } else {
                BusClock::Realtime
            };
            run_bus(&sc, &sc_path, &topo, &plan, &hogs, o, &out, clock, &sinks)?
        }
    };
    let wall_s = wall.elapsed().as_secs_f64();
    let (mut faults, mut windows) = fault_reports(&sc, &rows, &events);
    // A bus or sensor fault whose first sample the drive never reached (it stopped first: a
    // killed plant with `--restart never`, a stop signal) was not made: named with why, as a
    // late kill is, and no report. So is a kill or stop a stop signal came before.
    let end_k = info["end_k"].as_u64().unwrap_or(sc.samples());
    let end = DriveEnd {
        k: end_k,
        interrupted: crate::common::stop_requested() && end_k < sc.samples_made(),
    };
    let made_s = end_k.min(sc.samples()) as f64 / sc.rates.sample_hz;
    let mut not_made = not_made;
    not_made.extend(crate::bus_faults::not_made(&sc, &topo, end));
    not_made.extend(crate::faults::sensor::not_made(&sc, end));
    if end.interrupted && o.clock == Clock::Realtime {
        // The supervisor stopped on the signal with the rest of the plan not sent.
        not_made.extend(interrupted_kills(
            &plan,
            &hogs,
            &events,
            end,
            sc.rates.sample_hz,
        ));
    }
    let (bus_faults, bus_windows) =
        crate::bus_faults::reports(&sc, &topo, &rows, info.get("counters"), end);
    faults.extend(bus_faults);
    windows.extend(bus_windows);
    crate::faults::hog::add_latency(&mut faults, &hog_latency);
    for r in crate::faults::sensor::reports(&sc, &rows, end) {
        // Shaded on the plots like the other faults.
        if let Some(w) = &r.window {
            let t = |k: u64| k as f64 / sc.rates.sample_hz;
            windows.push((t(w.during_k[0]), t(w.during_k[1]), r.fault.clone()));
        }
        faults.push(r);
    }
    // After the reports: these are no signals, the reports above already cover them.
    let mut events = events;
    // (Not those a stop signal came before: they are not made, below.)
    events.extend(
        supervisor::simulated_events(&sc, &topo)
            .into_iter()
            .filter(|e| !(end.interrupted && end.before(e.k))),
    );
    let mut info = info;
    for (k, reason) in not_made {
        if let Some(list) = info["faults_not_made"].as_array_mut() {
            list.push(json!(reason));
        } else {
            info["faults_not_made"] = json!([reason]);
        }
        events.push(supervisor::SupEvent {
            t_wall_s: 0.0,
            k,
            kind: supervisor::EventKind::InjectRefused { reason },
            service: "-".into(),
            process: "-".into(),
        });
    }
    if let Some(t) = trip::trip_report(&sc, &rows) {
        crate::errln!(
            "drivelab: the inverter tripped on overcurrent at t = {:.4} s (sample {}); it stayed in its safe state",
            t.injected_t_s, t.injected_k
        );
        faults.push(t);
    }
    let mut gaps = gaps;
    recorder::attribute_gaps(&mut gaps, &faults, sc.rates.sample_hz);
    if let Some(p) = topo.process_of("plant") {
        recorder::attribute_crash_gaps(&mut gaps, &events, &topo.processes[p].name);
    }
    if let Some(f) = &failure {
        ended_early(&mut gaps, sc.samples(), f);
    }
    // A bus run wrote its trace as it went; an in-process one holds it whole.
    let mut failure = failure;
    let stats = match stats {
        Some(s) => s,
        None => {
            let (stats, lost) =
                stream::write_whole(&out.join("trace.csv"), &rows, &sinks, &mut gaps)?;
            if let Some(e) = lost {
                add_failure(&mut failure, e);
            }
            stats
        }
    };
    // Every fault of the summary (kills, stops, bus and sensor faults, hogs, a trip) ends
    // the metrics windows its start falls into.
    let fault_starts: Vec<FaultStart> = faults
        .iter()
        .map(|f| FaultStart {
            t_s: f.injected_k as f64 / sc.rates.sample_hz,
            fault: f.fault.clone(),
        })
        .collect();
    let mut metrics = speed_metrics_with_faults(&sc, &rows, &fault_starts);
    // A stage that makes the speed reference (an outer loop): the scenario's speed steps are
    // not what the speed loop followed.
    if let Some(outer) = topo
        .stages
        .iter()
        .find(|s| s.outputs.contains(&drivelab_runtime::stage::TopicId::Wref))
    {
        metrics.speed_reference_from = Some(outer.name.clone());
        metrics.leave_out_speed_response();
    }
    // The design that runs ([model]), without the built-in designs that a user's stage
    // replaced.
    let design = design_that_ran(
        &DriveDesign::from_scenario(&sc.controller_view()),
        &topo.replaced,
    );

    // An analysis of a file the run wrote: where it fails, the run's summary is still written,
    // with the reason in one line.
    let tail_by_part = if o.timing_csv {
        tail::of(&out.join("timing.csv")).unwrap_or_else(|e| {
            crate::errln!("drivelab: warning: no tail by part in summary.json: {e:#}");
            None
        })
    } else {
        None
    };
    let schedule_start = info.get("schedule_start_ns").and_then(|v| v.as_u64());
    // The plant is the first process (the topology's order starts at the source).
    let plant_tick_phase = topo
        .processes
        .first()
        .and_then(|p| p.cpu)
        .filter(|_| o.clock == Clock::Realtime)
        .and_then(|cpu| tick::phase_of(cpu).ok());
    let timing = json!({
        "cpu_latency_us_requested": match sc.timing.cpu_latency_us {
            drivelab_runtime::config::CpuLatency::Us(v) if o.clock == Clock::Realtime && !o.no_rt => Some(v),
            _ => None,
        },
        "cpu_latency_request_held": latency_request.as_ref().map(|r| r.value_us),
        "cpu_latency_request_error": latency_error,
        "plant_spin_us": sc.timing.plant_spin_us,
        "wake": sc.timing.wake,
        "tick_aligned": sc.timing.tick_aligned,
        // Where the plant's schedule started past a whole millisecond, µs (0: on the tick's
        // grid; docs/architecture.md, "The tick and the samples"); real time only.
        "schedule_start_us_past_ms": schedule_start.map(|t| (t % tick::GRID_NS) as f64 * 1e-3),
        // And past the last tick of the plant's core (0: on it, as a tick-aligned schedule
        // starts), µs; null where the plant is not pinned or the tick cannot be read.
        "schedule_start_us_past_tick": schedule_start.zip(plant_tick_phase).map(|(t, ph)| {
            ((t % tick::GRID_NS + tick::GRID_NS - ph) % tick::GRID_NS) as f64 * 1e-3
        }),
        // The kernel's tick as `drivelab doctor` reads it (its period and where it falls
        // within a millisecond on each CPU), so that a run says whether its tick-aligned
        // schedule could meet the tick; real time only.
        "kernel_tick": (o.clock == Clock::Realtime).then(drivelab_tools::doctor::kernel_tick),
        // What the slowest 1 % of cycles were made of, part by part (with --timing-csv).
        "tail_by_part": tail_by_part,
    });
    drop(latency_request);
    let deadline_misses = info
        .get("deadline_misses")
        .and_then(|v| v.as_u64())
        .unwrap_or(0);
    let h = headline(&stats, &gaps, deadline_misses, sc.samples());
    let mut summary = json!({
        "timing": timing,
        "scenario": sc.name,
        "clock": o.clock,
        "rate_hz": sc.rates.sample_hz,
        "speed_loop_hz": sc.rates.sample_hz / f64::from(sc.rates.speed_divider),
        "samples": stats.rows_written(),
        "trace": stats,
        "samples_expected": sc.samples(),
        "deadline_misses": deadline_misses,
        "deadline_misses_per_million": h.deadline_misses_per_million,
        "samples_missing": h.samples_missing,
        "peak_current_a": h.peak_current_a,
        "peak_speed_rad_s": h.peak_speed_rad_s,
        "longest_miss_run": info.get("longest_miss_run").cloned().unwrap_or(json!(0)),
        "processes": processes,
        "metrics": metrics,
        "missing_samples": gaps,
        "faults": faults,
        // Process exits that were not an injected kill's: zero in a sound drive, whatever the
        // restarts made of them (`--expect "crashes == 0"`).
        "crashes": supervisor::crashes(&events),
        "supervisor_events": events,
        "design": design,
        // Built-in stages a user's stage replaced, with the executable that ran it (their
        // built-in designs are not in `design`).
        "replaced_stages": topo.replaced,
        "wall_time_s": wall_s,
        // Of the samples made (a drive that ended early made fewer than the run's).
        "simulated_s_per_wall_s": made_s / wall_s.max(1e-9),
    });
    if !warnings.is_empty() {
        summary["warnings"] = json!(warnings);
    }
    if !not_reached.is_empty() {
        summary["not_reached"] = json!(not_reached);
    }
    if o.audit_syscalls {
        summary["stray_syscalls"] = json!(stray_syscalls_total(&summary["processes"]));
    }
    if !hogs.is_empty() {
        // Read, never changed: the kernel leaves (period − runtime) of each period to
        // non-real-time tasks, so a hog cannot take its CPU whole.
        summary["timing"]["rt_throttling"] = match crate::faults::hog::rt_throttling() {
            Some((runtime, period)) => {
                json!({ "sched_rt_runtime_us": runtime, "sched_rt_period_us": period })
            }
            None => serde_json::Value::Null,
        };
    }
    // A stage without its statistics: named, with why; a warning unless its process died
    // during the run and was left dead (the supervisor's events say so already), or the
    // drive made no sample (stopped during its start-up: its one line says so).
    if let Some(m) = info["statistics_missing"]
        .as_object()
        .filter(|m| !m.is_empty())
    {
        summary["statistics_missing"] = json!(m);
        let unexplained: Vec<String> = m
            .iter()
            .filter(|(_, why)| !why.as_str().is_some_and(|w| w.ends_with(LEFT_DEAD)))
            .map(|(st, why)| format!("{st} ({})", why.as_str().unwrap_or("")))
            .collect();
        if !unexplained.is_empty() && stats.rows > 0 {
            crate::errln!(
                "drivelab: warning: no statistics from {}: their counters are not in summary.json",
                unexplained.join(", ")
            );
        }
    }
    if let Some(c) = info.get("counters") {
        summary["counters"] = c.clone();
        if let Some(ns) = c["plant"]["loop_wall_ns"].as_u64().filter(|&n| n > 0) {
            summary["loop_simulated_s_per_wall_s"] = json!(made_s / (ns as f64 * 1e-9));
        }
    } else {
        summary["loop_simulated_s_per_wall_s"] = summary["simulated_s_per_wall_s"].clone();
    }
    if let Some(b) = info.get("bus") {
        summary["bus"] = b.clone();
    }
    if let Some(r) = info.get("plant_down_samples") {
        // Samples of the plant's downtimes, rebuilt (plant_flags bit 64), and where: [first,
        // last] of each downtime.
        summary["plant_down_samples"] = r.clone();
        summary["plant_down_ranges"] = info["plant_down_ranges"].clone();
    }
    if let Some(b) = info.get("bridge") {
        // What the Zenoh bridge forwarded, refused and rejected.
        summary["bridge"] = b.clone();
    }
    if let Some(c) = info.get("launcher_cpus") {
        summary["timing"]["launcher_cpus"] = c.clone();
    }
    if let Some(st) = info.get("stalls") {
        summary["timing"]["stalls"] = st.clone();
    }
    if let Some(r) = info.get("recorder_rejected") {
        // Messages the recorder could not place (an index beyond the run's samples).
        summary["recorder_rejected"] = r.clone();
    }
    if let Some(r) = info.get("recorder_late") {
        // Messages that came after their sample had left the window (as a row or a gap).
        summary["recorder_late"] = r.clone();
    }
    // A plant whose state blew up (parameters or a load the validation could not judge):
    // every figure after it is read off NaN.
    if let Some(k) = stats.first_not_finite {
        add_failure(
            &mut failure,
            format!(
                "the plant's state is not a finite number from sample {k} (t = {} s) on: the motor, its load or the inverter give no stable simulation at rates.plant_substeps = {}",
                k as f64 / sc.rates.sample_hz,
                sc.rates.plant_substeps
            ),
        );
    }
    // A planned fault that was not made (its process was down, the drive ended first): the
    // run did not test what it was asked to, and fails with them (after the gaps were named:
    // the drive itself ran to its end).
    if let Some(list) = info["faults_not_made"].as_array().filter(|l| !l.is_empty()) {
        summary["faults_not_made"] = json!(list);
        let first = list[0].as_str().unwrap_or("");
        failure.get_or_insert(match list.len() {
            1 => format!("a planned fault was not made: {first}"),
            n => format!("{n} planned faults were not made, the first: {first}"),
        });
    }
    // A stage that panicked (a bug of the stage): the run fails, even when its process was
    // restarted and the drive ran to its end.
    let panicked = events
        .iter()
        .find(|e| matches!(e.kind, supervisor::EventKind::Panicked { .. }));
    // (A run that failed on it already names it.)
    if let Some(e) =
        panicked.filter(|e| !failure.as_deref().is_some_and(|f| f.contains(&e.detail())))
    {
        let restarted = events
            .iter()
            .any(|r| r.process == e.process && r.name() == "restarted" && r.t_wall_s >= e.t_wall_s);
        add_failure(
            &mut failure,
            format!(
                "process {} panicked: {}{}",
                e.process,
                e.detail(),
                if restarted { " (it was restarted)" } else { "" }
            ),
        );
    }
    summary["failure"] = json!(failure);
    let Histograms {
        latency,
        curves,
        unreadable,
        not_written,
    } = collect_histograms(&out)?;
    if !not_written.is_empty() {
        add_failure(&mut failure, not_written.join("; "));
        summary["failure"] = json!(failure);
    }
    // A histogram a host could not finish (killed while it wrote it at its exit) is left
    // out and named: the trace and the rest of the summary are still written.
    if !unreadable.is_empty() {
        crate::errln!(
            "drivelab: warning: histograms left out, unreadable: {}",
            unreadable.join("; ")
        );
        summary["histograms_unreadable"] = json!(unreadable);
    }
    if !latency.is_empty() {
        summary["latency_us"] = serde_json::to_value(&latency)?;
        if let Some(b) = crate::budget::budget(&topo, &latency) {
            summary["budget"] = serde_json::to_value(&b)?;
        }
    }
    // A build without figures (the cross build) leaves them to `drivelab plot RUNDIR`.
    let plots = !o.no_plots && drivelab_tools::plot::AVAILABLE;
    // Figures are drawn from what was written: where drawing fails, the summary is still
    // written, with the reason (`drivelab plot RUNDIR` draws them again), and the figures
    // drawn before the failure are removed: on a full disk they would take the summary's
    // place.
    let before_plots = file_names(&out);
    let drawn = (|| -> Result<Vec<PathBuf>> {
        let mut files = Vec::new();
        if plots && !curves.is_empty() {
            let budget = Some((
                1e6 / sc.rates.sample_hz,
                format!("T_s = {:.0} µs", 1e6 / sc.rates.sample_hz),
            ));
            files.extend(drivelab_tools::plot::plot_percentiles(
                &curves,
                &format!("{}: latency percentiles", sc.name),
                budget,
                true,
                &out.join("latency"),
            )?);
        }
        if plots && !rows.is_empty() {
            let opts = drivelab_tools::plot::TraceFigureOptions {
                current_limit_a: Some(sc.i_q_max()),
                voltage_limit_v: Some(sc.u_max()),
                title: format!("{} ({})", sc.name, o.clock.name()).to_lowercase(),
                shaded_windows: windows.clone(),
                ..Default::default()
            };
            files.extend(drivelab_tools::plot::plot_trace(&rows, &out, &opts)?);
            if drivelab_runtime::wiring::polar::mode_of(&sc).is_some()
                || !sc.reference.i_q_a.is_empty()
            {
                files.extend(drivelab_tools::plot_polar::plot_polar_panels(
                    &sc,
                    &rows,
                    &out,
                    &opts.title,
                )?);
            }
        }
        Ok(files)
    })();
    match drawn {
        Ok(files) if !files.is_empty() => {
            summary["plots"] = json!(files
                .iter()
                .map(|f| f
                    .file_name()
                    .unwrap_or_default()
                    .to_string_lossy()
                    .into_owned())
                .collect::<Vec<_>>());
        }
        Ok(_) => {}
        Err(e) => {
            for name in file_names(&out).difference(&before_plots) {
                let _ = std::fs::remove_file(out.join(name));
            }
            crate::errln!(
                "drivelab: warning: the plots were not drawn ({e:#}); `drivelab plot {}` draws them",
                out.display()
            );
            summary["plots_error"] = json!(format!("{e:#}"));
        }
    }
    let outcomes: Vec<_> = expectations.iter().map(|e| e.evaluate(&summary)).collect();
    summary["expectations"] = serde_json::to_value(&outcomes)?;
    let recorded = format!(
        "what was recorded is in {}: {} of {} samples",
        out.display(),
        summary["samples"],
        sc.samples()
    );
    write_summary(
        &out,
        &mut summary,
        (&mut failure, "/failure"),
        sinks.take_mcap(),
        (&std::fs::read_to_string(&sc_path)?, sc.rates.sample_hz),
        &recorded,
    )?;
    if let Some(l) = &live {
        // Connected clients get what is queued for them, then a close.
        let dropped = l.stop();
        if dropped > 0 {
            crate::errln!(
                "drivelab: Foxglove: {dropped} messages dropped for clients that did not keep up"
            );
        }
    }
    if let Some(b) = bridge {
        // Remote recorders get the summary, then the bridge ends.
        b.finish(&out.join("summary.json"))?;
    }
    if let Some(f) = failure {
        bail!("{f} ({recorded})");
    }
    Ok(RunResult { out, summary })
}

/// The names of the files in `dir` (none where it cannot be read).
fn file_names(dir: &Path) -> std::collections::BTreeSet<std::ffi::OsString> {
    std::fs::read_dir(dir)
        .map(|d| {
            d.flatten()
                .filter(|e| e.file_type().is_ok_and(|t| t.is_file()))
                .map(|e| e.file_name())
                .collect()
        })
        .unwrap_or_default()
}

/// How long a real-time drive of `sc` may take before the supervisor gives up on it: its
/// duration and a half, 20 s for the start and the end, and the time its stops hold it (a
/// stopped plant stops the drive's clock).
fn realtime_limit(sc: &Scenario, faults: &[crate::faults::FaultSpec]) -> Duration {
    Duration::from_secs_f64(sc.duration_s * 1.5 + 20.0 + crate::faults::stopped_s(faults))
}

/// What a real-time drive's start and end may take of [`realtime_limit`], s.
const START_AND_END_S: f64 = 10.0;

/// A delay fault's stage spins on its core for every step in the window, above the stages
/// below it, and the drive's clock waits for it: delays whose spinning, added to the run
/// itself, would take longer than the run may last (leaving [`START_AND_END_S`] for its
/// start and end) could only end in the supervisor's time limit, so they are refused, all
/// of them together (they share the chain's core in the default topology).
fn check_delays(sc: &Scenario, topo: &TopologyPlan, limit: Duration) -> Result<()> {
    use drivelab_runtime::inject::InjectKind;
    let (mut steps, mut busy_s, mut specs) = (0.0, 0.0, Vec::new());
    for i in sc.inject.iter().filter(|i| i.kind == InjectKind::Delay) {
        let divider = topo
            .stages
            .iter()
            .find(|s| s.name == i.target)
            .map_or(1, |s| s.divider.max(1));
        let window_s = i.duration_s.min(sc.duration_s - i.at_s).max(0.0);
        let n = (window_s * sc.rates.sample_hz / divider as f64).ceil();
        steps += n;
        busy_s += n * i.latency_us * 1e-6;
        specs.push(i.spec());
    }
    let room_s = limit.as_secs_f64() - START_AND_END_S - sc.duration_s;
    if busy_s > room_s {
        let whose = if specs.len() == 1 { "its" } else { "their" };
        bail!(
            "fault {}: {whose} {steps} delayed steps would keep the stages' core busy for {busy_s:.1} s, which with the run's own {} s is longer than this run may last ({:.1} s, {START_AND_END_S} s of it for the start and the end): shorten {whose} window or latency",
            specs.join(", "),
            sc.duration_s,
            limit.as_secs_f64(),
        );
    }
    Ok(())
}

/// Adds `why` to a run's `failure`: the first, or after the ones before it (a write error
/// that came with a stop signal is named beside it), or in the place of the bare
/// [`RECORDER_FAILED`] (the recorder's own error says more).
pub(crate) fn add_failure(failure: &mut Option<String>, why: String) {
    *failure = Some(match failure.take() {
        Some(f) if f != RECORDER_FAILED => format!("{f}; {why}"),
        _ => why,
    });
}

/// Writes `summary` to `out/summary.json`, then finishes `mcap` (`trace.mcap`, which holds the
/// summary and the scenario's text `scenario`; `fs`: the sample rate, Hz). An MCAP that cannot
/// be finished is added to `failure` and to the summary (at JSON pointer `failure_at`), written
/// again. A `summary.json` that cannot be written is removed (cut short, it would not read as
/// JSON) and is the error, after the failure that came first (a full disk fails the trace
/// before the summary) and with `recorded` (what the run folder holds).
pub(crate) fn write_summary(
    out: &Path,
    summary: &mut serde_json::Value,
    (failure, failure_at): (&mut Option<String>, &str),
    mcap: Option<crate::trace_mcap::McapTrace>,
    (scenario, fs): (&str, f64),
    recorded: &str,
) -> Result<()> {
    let path = out.join("summary.json");
    let write = |summary: &serde_json::Value, failure: &Option<String>| -> Result<()> {
        let e = match drivelab_runtime::files::write(&path, serde_json::to_vec_pretty(summary)?) {
            Ok(()) => return Ok(()),
            Err(e) => e,
        };
        let _ = std::fs::remove_file(&path);
        let e = format!("cannot write {}: {e}", path.display());
        match failure {
            Some(f) => bail!("{f}; and {e} ({recorded})"),
            None => bail!("{e}"),
        }
    };
    write(summary, failure)?;
    if let Some(Err(e)) = mcap.map(|m| m.finish(scenario, summary, fs)) {
        add_failure(
            failure,
            format!("{e:#}; trace.mcap is left without its index"),
        );
        if let Some(f) = summary.pointer_mut(failure_at) {
            *f = json!(failure);
        }
        write(summary, failure)?;
    }
    Ok(())
}

/// The samples after the recording stopped were never produced: the gap that reaches the
/// run's last sample (of `samples`) says the run ended early, and why (`failure`). Not one
/// the plant is known to have published ([`unreceived`]), nor rows made and not written
/// ([`recorder::ROW`]): the run reached its end there.
fn ended_early(gaps: &mut [Gap], samples: u64, failure: &str) {
    for g in gaps.iter_mut().filter(|g| {
        g.to + 1 == samples
            && g.part != recorder::ROW
            && g.cause != UNRECEIVED
            && !g.cause.starts_with(NOT_FROM_PLANT_MACHINE)
    }) {
        g.cause = format!("the run ended early: {failure}");
    }
}

/// Headline figures of `summary.json`, which `[[expect]]` checks read.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Headline {
    /// Plant deadline misses per million expected samples.
    deadline_misses_per_million: f64,
    /// Samples with no measurement (gaps of the "measurement" part, both ends included).
    samples_missing: u64,
    /// Largest |i_dq| of the trace, A.
    peak_current_a: f64,
    /// Largest |ω_m| of the trace, mechanical rad/s.
    peak_speed_rad_s: f64,
}

/// The headline figures of a run of `samples` expected samples from its trace's figures,
/// its gaps and the plant's deadline misses.
fn headline(trace: &TraceStats, gaps: &[Gap], deadline_misses: u64, samples: u64) -> Headline {
    // A state that blew up has no peak: null in the summary, so no expectation on it passes
    // (the peaks of the rows before it are in `trace`).
    let peak = |p: f64| {
        if trace.first_not_finite.is_some() {
            f64::NAN
        } else {
            p
        }
    };
    Headline {
        deadline_misses_per_million: deadline_misses as f64 * 1e6 / samples.max(1) as f64,
        samples_missing: recorder::samples_missing(gaps),
        peak_current_a: peak(trace.peak_current_a),
        peak_speed_rad_s: peak(trace.peak_speed_rad_s),
    }
}

/// `summary.json → timing.stalls` from the source's `stats.json → stalls` (its last
/// incarnation's, after a restart): how many wake-ups came half a millisecond late or later,
/// and whether their ends fall on a host's 100 ms throttling grid
/// (docs/architecture.md, "Stalls that are the host's").
fn stall_report(st: &serde_json::Value) -> serde_json::Value {
    let log: Vec<(u64, u64)> = serde_json::from_value(st["log"].clone()).unwrap_or_default();
    let count = st["count"].as_u64().unwrap_or(log.len() as u64);
    let mut r = drivelab_runtime::timing::StallReport::new(&log, count);
    r.misses = st["misses"].as_u64().unwrap_or(0);
    let mut v = serde_json::to_value(&r).unwrap_or_default();
    v["host_throttled"] = json!(r.host_throttled());
    v["line"] = json!(r.run_line());
    v
}

/// Reads every `<key>.hdr` histogram the services wrote, writes `<key>.hgrm` beside it and
/// returns the percentiles by key and the percentile curves for the plot; a file it cannot
/// read is named, not an error.
fn collect_histograms(out: &Path) -> Result<Histograms> {
    let mut lat = BTreeMap::new();
    let mut curves = Vec::new();
    let mut unreadable = Vec::new();
    let mut not_written = Vec::new();
    let mut files: Vec<PathBuf> = std::fs::read_dir(out)?
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "hdr"))
        .collect();
    files.sort();
    for f in files {
        let key = f
            .file_stem()
            .unwrap_or_default()
            .to_string_lossy()
            .into_owned();
        let h = match drivelab_runtime::timing::LatencyHist::read_v2("hist", &f) {
            Ok(h) => h,
            Err(e) => {
                unreadable.push(format!("{e:#}"));
                continue;
            }
        };
        let hgrm = f.with_extension("hgrm");
        if let Err(e) = drivelab_runtime::files::write(&hgrm, h.hgrm()) {
            not_written.push(format!("cannot write {}: {e}", hgrm.display()));
        }
        lat.insert(key.clone(), h.percentiles());
        if key == "cycle" || key.ends_with(".wake") || key.ends_with(".lateness") {
            curves.push((key, h.curve()));
        }
    }
    Ok(Histograms {
        latency: lat,
        curves,
        unreadable,
        not_written,
    })
}

/// What [`collect_histograms`] read from a run folder's `.hdr` files.
struct Histograms {
    /// Percentiles by histogram name.
    latency: BTreeMap<String, drivelab_runtime::timing::Percentiles>,
    /// The curves of the cycle, the wake-ups and the lateness, for the latency plot.
    curves: Vec<drivelab_tools::plot::PercentileSeries>,
    /// The files that could not be read, each with why.
    unreadable: Vec<String>,
    /// The `.hgrm` files that could not be written, each with why.
    not_written: Vec<String>,
}

/// Per-service statistics keyed by service name (for tests and reports).
pub fn counters(summary: &serde_json::Value) -> BTreeMap<String, serde_json::Value> {
    summary["counters"]
        .as_object()
        .map(|m| m.clone().into_iter().collect())
        .unwrap_or_default()
}

/// The parts of a built-in design that each replaceable stage runs: keys of `design`, and of
/// `design.rst` (the Low et al. RST loops).
const DESIGN_PARTS: [(&str, &[&str], &[&str]); 3] = [
    ("observer", &["observer"], &[]),
    ("current-loop", &["current", "polar"], &["i_d", "i_q"]),
    ("speed-loop", &["speed"], &["speed"]),
];

/// `design` as `summary.json` gives it: the built-in designs of the stages in `replaced`
/// (stage → executable) left out, since none of them ran, and `not_run` naming each part left
/// out and the executable that ran in its place. Kyslan's nonlinear design spans both loops:
/// it goes only when both are replaced.
fn design_that_ran(design: &DriveDesign, replaced: &BTreeMap<String, String>) -> serde_json::Value {
    let mut v = json!(design);
    if replaced.is_empty() {
        return v;
    }
    let remove = |obj: Option<&mut serde_json::Value>, key: &str| {
        obj.and_then(|o| o.as_object_mut())
            .and_then(|m| m.remove(key))
            .is_some()
    };
    let mut not_run = serde_json::Map::new();
    for (stage, parts, rst) in DESIGN_PARTS {
        let Some(exe) = replaced.get(stage) else {
            continue;
        };
        for p in parts {
            if remove(Some(&mut v), p) {
                not_run.insert(p.to_string(), json!(exe));
            }
        }
        for p in rst {
            if remove(v.get_mut("rst"), p) {
                not_run.insert(format!("rst.{p}"), json!(exe));
            }
        }
    }
    if let (Some(c), Some(s)) = (replaced.get("current-loop"), replaced.get("speed-loop")) {
        if remove(Some(&mut v), "nonlinear") {
            not_run.insert("nonlinear".into(), json!(format!("{c}, {s}")));
        }
    }
    v["not_run"] = serde_json::Value::Object(not_run);
    v
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stage_without_statistics_is_explained_by_its_processs_last_exit() {
        use std::os::unix::process::ExitStatusExt;
        let ev = |t: f64, process: &str, kind: supervisor::EventKind| SupEvent {
            t_wall_s: t,
            k: 0,
            kind,
            service: process.to_string(),
            process: process.to_string(),
        };
        let exited = |t, p| {
            ev(
                t,
                p,
                supervisor::EventKind::Exited {
                    status: std::process::ExitStatus::from_raw(9),
                    crash: false,
                },
            )
        };
        let restarted = |t, p| {
            ev(
                t,
                p,
                supervisor::EventKind::Restarted { restart: 1, pid: 7 },
            )
        };
        let left_dead =
            "not written: its process exited (signal: 9 (SIGKILL)) at 0.300 s and was not restarted";
        let unexplained = "not written by its process (it writes it as it exits)";
        assert_eq!(not_written(&[], "observer"), unexplained);
        assert_eq!(
            not_written(&[exited(0.3, "observer")], "observer"),
            left_dead
        );
        // Restarted after it: the new process should have written it.
        assert_eq!(
            not_written(
                &[exited(0.1, "observer"), restarted(0.2, "observer")],
                "observer"
            ),
            unexplained
        );
        // Its last exit counts, another process's not.
        assert_eq!(
            not_written(
                &[
                    exited(0.1, "observer"),
                    restarted(0.2, "observer"),
                    exited(0.3, "observer"),
                    exited(0.4, "plant"),
                ],
                "observer"
            ),
            left_dead
        );
        assert_eq!(
            not_written(&[exited(0.3, "plant")], "observer"),
            unexplained
        );
    }

    #[test]
    fn a_replaced_stages_built_in_design_is_left_out_of_the_summary_and_named() {
        let design = |name: &str| {
            let sc = load_scenario(name, None).unwrap();
            DriveDesign::from_scenario(&sc.controller_view())
        };
        let of = |pairs: &[(&str, &str)]| -> BTreeMap<String, String> {
            pairs
                .iter()
                .map(|(s, e)| (s.to_string(), e.to_string()))
                .collect()
        };
        let keys = |v: &serde_json::Value| -> Vec<String> {
            v.as_object().unwrap().keys().cloned().collect()
        };
        // Nothing replaced: the design as it is, without a not_run.
        let pi = design("kyslan-pi");
        assert_eq!(design_that_ran(&pi, &of(&[])), json!(pi));
        // The current loop: its PI design goes, the speed loop's and the nonlinear one stay.
        let v = design_that_ran(&pi, &of(&[("current-loop", "/x/deadbeat")]));
        assert!(v.get("current").is_none(), "{v}");
        assert_eq!(v["speed"], json!(pi)["speed"]);
        assert!(v["nonlinear"].is_object());
        assert_eq!(v["not_run"], json!({ "current": "/x/deadbeat" }));
        // Both loops: the nonlinear design, which spans both, goes too.
        let v = design_that_ran(&pi, &of(&[("current-loop", "/c"), ("speed-loop", "/s")]));
        assert_eq!(keys(&v), ["controller", "not_run", "warnings"], "{v}");
        assert_eq!(
            v["not_run"],
            json!({ "current": "/c", "speed": "/s", "nonlinear": "/c, /s" })
        );
        // Low et al.'s RST: the speed loop's RST design goes, the current loops' stay; the
        // sensorless observer's design goes with the observer.
        let rst = design("low-rst-sensorless");
        let full = json!(rst);
        assert!(full["rst"]["speed"].is_object() && full["observer"].is_object());
        let v = design_that_ran(&rst, &of(&[("speed-loop", "/s"), ("observer", "/o")]));
        assert_eq!(keys(&v["rst"]), ["i_d", "i_q"], "{v}");
        assert!(v.get("observer").is_none() && v.get("speed").is_none());
        assert_eq!(v["current"], full["current"]);
        assert_eq!(
            v["not_run"],
            json!({ "observer": "/o", "speed": "/s", "rst.speed": "/s" })
        );
    }

    #[test]
    fn a_histogram_cut_short_is_left_out_and_named_the_others_are_read_and_written() {
        let dir = std::env::temp_dir().join(format!("drivelab-hists-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let mut h = drivelab_runtime::timing::LatencyHist::new("cycle");
        for ns in [20_000, 25_000, 40_000] {
            h.record_ns(ns);
        }
        h.write_v2(&dir.join("cycle.hdr")).unwrap();
        // What a host killed while it wrote its histogram leaves: the start of one.
        let whole = std::fs::read(dir.join("cycle.hdr")).unwrap();
        std::fs::write(dir.join("observer.exec.hdr"), &whole[..whole.len() / 2]).unwrap();
        // And an empty one (its host found the disk full).
        std::fs::write(dir.join("observer.wake.hdr"), b"").unwrap();
        // And one whose table cannot be written (a folder in its place): read, and named.
        std::fs::write(dir.join("plant.exec.hdr"), &whole).unwrap();
        std::fs::create_dir(dir.join("plant.exec.hgrm")).unwrap();
        let Histograms {
            latency: lat,
            curves,
            unreadable,
            not_written,
        } = collect_histograms(&dir).unwrap();
        assert_eq!(lat.keys().collect::<Vec<_>>(), ["cycle", "plant.exec"]);
        assert_eq!(not_written.len(), 1, "{not_written:?}");
        assert!(
            not_written[0].starts_with(&format!(
                "cannot write {}: ",
                dir.join("plant.exec.hgrm").display()
            )),
            "{not_written:?}"
        );
        assert_eq!(curves.len(), 1);
        assert_eq!(unreadable.len(), 2, "{unreadable:?}");
        assert!(
            unreadable[0].ends_with(&format!(
                "observer.exec.hdr: not an HdrHistogram V2 file: cut short ({} bytes)",
                whole.len() / 2
            )),
            "{unreadable:?}"
        );
        assert!(
            unreadable[1].ends_with("observer.wake.hdr: not an HdrHistogram V2 file: empty"),
            "{unreadable:?}"
        );
        assert!(dir.join("cycle.hgrm").is_file());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn an_executable_is_asked_to_describe_once_per_scenario_until_it_changes() {
        let dir = tempfile::tempdir().unwrap();
        let exe = dir.path().join("stages.sh");
        let asked = dir.path().join("asked");
        // A script that counts its questions in `asked` and hosts no stage, run through `sh`
        // (executing a file just written can fail with ETXTBSY while another test forks).
        let sh = drivelab_runtime::runner::Runner::parse("sh").unwrap();
        let write = |extra: &str| {
            let text = format!("echo x >> {}\n{extra}echo '[]'\n", asked.display());
            std::fs::write(&exe, text).unwrap();
        };
        let questions = || {
            std::fs::read_to_string(&asked)
                .unwrap_or_default()
                .lines()
                .count()
        };
        let e = exe.to_str().unwrap();
        write("");
        assert!(describe(e, "a = 1", Some(&sh)).unwrap().is_empty());
        assert!(describe(e, "a = 1", Some(&sh)).unwrap().is_empty());
        assert_eq!(questions(), 1);
        // Another scenario is another question.
        describe(e, "a = 2", Some(&sh)).unwrap();
        assert_eq!(questions(), 2);
        // A rebuilt executable (here: another size) is asked again.
        write(": rebuilt\n");
        describe(e, "a = 1", Some(&sh)).unwrap();
        assert_eq!(questions(), 3);
        // A failing answer is not kept: asked again, failing again.
        write("exit 3\n");
        assert!(describe(e, "a = 1", Some(&sh)).is_err());
        assert!(describe(e, "a = 1", Some(&sh)).is_err());
        assert_eq!(questions(), 5);
    }

    fn gap(from: u64, to: u64, part: &'static str) -> Gap {
        Gap {
            from,
            to,
            part,
            cause: "fault".into(),
        }
    }

    #[test]
    fn only_a_real_time_run_missing_most_deadlines_without_a_fault_is_warned_about() {
        let run = |misses: u64, faults: serde_json::Value| json!({ "deadline_misses": misses, "samples": 1000, "rate_hz": 10000.0, "faults": faults });
        assert_eq!(
            rate_warning(&run(1000, json!([])), true).as_deref(),
            Some("1000 of 1000 deadlines missed: this chain does not hold 10 kHz here (cycle latency in summary.json → latency_us.cycle)")
        );
        assert!(rate_warning(&run(501, json!([])), true).is_some());
        // Half or fewer, lockstep (no deadlines), or misses that faults caused: no warning.
        assert_eq!(rate_warning(&run(500, json!([])), true), None);
        assert_eq!(rate_warning(&run(1000, json!([])), false), None);
        assert_eq!(
            rate_warning(&run(1000, json!([{ "fault": "kill:plant@0.1" }])), true),
            None
        );
        assert_eq!(
            rate_warning(&json!({ "samples": 0, "deadline_misses": 0 }), true),
            None
        );
    }

    #[test]
    fn headline_figures_count_missing_measurements_with_both_ends_and_take_magnitudes() {
        let rows = [
            TraceRow {
                i_d: -3.0,
                i_q: 4.0,
                omega_m: 10.0,
                ..Default::default()
            },
            TraceRow {
                i_q: 4.5,
                omega_m: -12.0,
                ..Default::default()
            },
        ];
        // A one-sample gap counts 1; a missing command is not a missing sample.
        let gaps = [
            gap(5, 5, "measurement"),
            gap(10, 19, "measurement"),
            gap(30, 39, "command"),
        ];
        let h = headline(&TraceStats::of(&rows), &gaps, 3, 2_000_000);
        assert_eq!(
            h,
            Headline {
                deadline_misses_per_million: 1.5,
                samples_missing: 11,
                peak_current_a: 5.0,
                peak_speed_rad_s: 12.0,
            }
        );
        // Nothing expected, nothing recorded: no division by zero.
        let h = headline(&TraceStats::of(&[]), &[], 0, 0);
        assert_eq!(
            (h.deadline_misses_per_million, h.peak_current_a),
            (0.0, 0.0)
        );
    }

    #[test]
    fn samples_the_plant_published_but_the_recorder_lacks_fail_the_run() {
        // A plant that stepped every sample: the recorder's missing ones are its own loss.
        let mut gaps = vec![gap(0, 999, "measurement"), gap(5, 5, "command")];
        let f = unreceived(&mut gaps, 1000, 1000, 0).unwrap();
        assert_eq!(
            f,
            "the recorder received 0 of the 1000 samples the plant published"
        );
        assert!(gaps[0].cause.contains("never reached the recorder"));
        assert_eq!(gaps[1].cause, "fault");
        // A restarted plant (fewer samples of its own), or a complete trace: nothing said.
        let mut gaps = vec![gap(0, 9, "measurement")];
        assert_eq!(unreceived(&mut gaps, 990, 1000, 990), None);
        assert_eq!(gaps[0].cause, "fault");
        assert_eq!(unreceived(&mut [], 1000, 1000, 1000), None);
    }

    #[test]
    fn the_missing_end_of_a_remote_plant_says_whether_it_was_published() {
        let stopped = |from, to| Gap {
            cause: recorder::PLANT_STOPPED.into(),
            ..gap(from, to, "measurement")
        };
        // The plant's end marker at the run's end: the samples after the newest one
        // received were published and never came.
        let mut gaps = vec![gap(10, 19, "measurement"), stopped(990, 999)];
        let f = remote_tail(&mut gaps, Some(1000), true, 1000).unwrap();
        assert_eq!(
            f,
            "the plant's machine published samples 990 to 999 and they never reached the recorder"
        );
        assert_eq!(gaps[1].cause, UNRECEIVED);
        assert_eq!(
            gaps[0].cause, "fault",
            "a gap before the end keeps its cause"
        );
        // No end marker, and the recorder had to be stopped: not known.
        let mut gaps = vec![stopped(990, 999)];
        let f = remote_tail(&mut gaps, None, false, 1000).unwrap();
        assert_eq!(
            f,
            "the last 10 samples did not come from the plant's machine (no end of the run from it)"
        );
        assert_eq!(
            gaps[0].cause,
            "not received from the plant's machine, which sent no end of the run within 5 s of the run's end here"
        );
        // The plant ended before the run's end (its end marker says where): it stopped.
        let mut gaps = vec![stopped(990, 999)];
        assert_eq!(remote_tail(&mut gaps, Some(990), true, 1000), None);
        assert_eq!(gaps[0].cause, recorder::PLANT_STOPPED);
        // Nothing missing at the end, or a tail another cause already explains.
        assert_eq!(
            remote_tail(&mut [gap(5, 6, "measurement")], None, false, 1000),
            None
        );
        assert_eq!(
            remote_tail(&mut [gap(990, 999, "measurement")], None, false, 1000),
            None
        );
        assert_eq!(remote_tail(&mut [], Some(1000), true, 1000), None);
    }

    #[test]
    fn the_recorder_is_waited_for_until_it_ends_or_the_wait_is_over() {
        let quick = std::thread::spawn(|| std::thread::sleep(Duration::from_millis(50)));
        assert!(recorder_ends_alone(&quick, None));
        // A recorder that never gets its end markers is given END_WAIT, not forever.
        let (tx, rx) = mpsc::channel::<()>();
        let stuck = std::thread::spawn(move || {
            let _ = rx.recv();
        });
        let t = Instant::now();
        assert!(!recorder_ends_alone(&stuck, None));
        let waited = t.elapsed();
        assert!(waited >= END_WAIT, "{waited:?}");
        drop(tx);
        stuck.join().unwrap();
        quick.join().unwrap();
    }

    #[test]
    fn only_the_gap_that_reaches_the_last_sample_ended_early() {
        let mut gaps = [
            gap(10, 19, "measurement"),
            gap(50, 99, "measurement"),
            gap(98, 98, "command"),
        ];
        ended_early(&mut gaps, 100, "interrupted (SIGTERM): drive stopped");
        let causes: Vec<&str> = gaps.iter().map(|g| g.cause.as_str()).collect();
        assert_eq!(
            causes,
            [
                "fault",
                "the run ended early: interrupted (SIGTERM): drive stopped",
                "fault"
            ]
        );
        // The plant published every sample: the run failed because the recorder lacks some,
        // and the tail gap keeps saying that, not that the run ended early.
        let mut gaps = vec![gap(900, 999, "measurement")];
        let f = unreceived(&mut gaps, 1000, 1000, 900).unwrap();
        ended_early(&mut gaps, 1000, &f);
        assert_eq!(gaps[0].cause, UNRECEIVED);
        // Nor does a split drive's tail that never came from the plant's machine.
        let mut gaps = vec![Gap {
            cause: recorder::PLANT_STOPPED.into(),
            ..gap(900, 999, "measurement")
        }];
        let f = remote_tail(&mut gaps, None, false, 1000).unwrap();
        ended_early(&mut gaps, 1000, &f);
        assert!(
            gaps[0].cause.starts_with(NOT_FROM_PLANT_MACHINE),
            "{}",
            gaps[0].cause
        );
    }

    #[test]
    fn a_duration_override_is_validated_with_a_one_line_error() {
        let sc = load_scenario("kyslan-pi", Some(0.25)).unwrap();
        assert_eq!(sc.duration_s, 0.25);
        for bad in [-1.0, 0.0] {
            let e = load_scenario("kyslan-pi", Some(bad))
                .unwrap_err()
                .to_string();
            assert!(e.starts_with(&format!("--duration {bad}: ")), "{e}");
            assert!(!e.contains('\n'), "{e}");
        }
        assert!(load_scenario("no-such-scenario", None).is_err());
    }

    #[test]
    fn default_run_folders_and_exec_paths() {
        let sc = load_scenario("kyslan-pi", None).unwrap();
        let stem = default_stem(&sc, Clock::Lockstep);
        let secs = stem.strip_prefix("kyslan-pi-lockstep-").expect(&stem);
        assert!(secs.parse::<u64>().is_ok(), "{stem}");
        // Runs in the same second get folders of their own, each made new.
        let parent = std::env::temp_dir().join(format!("drivelab-runs-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&parent);
        let made: Vec<PathBuf> = (0..3)
            .map(|_| new_folder_in(&parent, &stem).unwrap())
            .collect();
        assert_eq!(
            made,
            [
                parent.join(&stem),
                parent.join(format!("{stem}-2")),
                parent.join(format!("{stem}-3"))
            ]
        );
        assert!(made.iter().all(|d| d.is_dir()));
        std::fs::remove_dir_all(&parent).unwrap();
        // A relative exec is taken from the naming file's folder; an absolute one stays.
        let mut procs = sc.topology();
        procs[0].exec = Some("bin/stage".into());
        procs[1].exec = Some("/opt/stage".into());
        absolute_execs(&mut procs, Path::new("/etc/drivelab/topology.toml")).unwrap();
        assert_eq!(procs[0].exec.as_deref(), Some("/etc/drivelab/bin/stage"));
        assert_eq!(procs[1].exec.as_deref(), Some("/opt/stage"));
        assert_eq!(procs[2].exec, None);
        // A file named without a folder (`--topology my.toml`): the working folder.
        let mut procs = sc.topology();
        procs[0].exec = Some("bin/stage".into());
        absolute_execs(&mut procs, Path::new("topology.toml")).unwrap();
        let cwd = std::env::current_dir().unwrap();
        assert_eq!(
            procs[0].exec,
            Some(cwd.join("bin/stage").display().to_string())
        );
    }

    #[test]
    fn counters_are_read_by_service() {
        let s = json!({ "counters": { "plant": { "samples": 5 }, "observer": {} } });
        let c = counters(&s);
        assert_eq!(c.keys().collect::<Vec<_>>(), ["observer", "plant"]);
        assert_eq!(c["plant"]["samples"], 5);
        assert!(counters(&json!({})).is_empty());
    }
}
