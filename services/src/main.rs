//! `drivelab`: the launcher and supervisor CLI.

use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};
use drivelab_services::expect::usage;
use drivelab_services::launcher::{self, Clock, RunOptions};
use std::path::PathBuf;
use std::process::ExitCode;

/// drivelab: a real-time PMSM drive of stages in processes on iceoryx2 shared memory.
///
/// Exit codes: 0 success, 1 error (a bad file or name, a service failed, interrupted), 2 usage
/// error (an option's value not of its kind, out of its range or not one of its choices,
/// options that cannot go together, a malformed expectation), 3 an expectation failed (the run
/// itself completed).
#[derive(Debug, Parser)]
#[command(name = "drivelab", version, long_about = None)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

/// Which running drive `monitor` and `fault` address.
#[derive(Debug, clap::Args)]
struct DriveArgs {
    /// Bus id of the running drive (printed by `drivelab run`, also in summary.json); with
    /// --connect, picks one of several drives behind the endpoint.
    #[arg(long, required_unless_present = "connect", value_parser = bus_id)]
    bus: Option<String>,
    /// A remote drive instead, through its Zenoh endpoint (tcp/HOST:PORT or tls/HOST:PORT;
    /// the drive runs with --zenoh-listen).
    #[arg(long, value_name = "ENDPOINT")]
    connect: Option<String>,
    /// With --connect: a Zenoh configuration file (JSON5) for TLS.
    #[arg(long, value_name = "FILE", requires = "connect")]
    zenoh_config: Option<PathBuf>,
}

#[derive(Debug, Subcommand)]
enum Cmd {
    /// Run a scenario: start the processes of its topology (plant, observer, current-loop and
    /// speed-loop stages, and any user stages), record every sample, stop them and write
    /// trace.csv, trace.mcap, summary.json and plots into the run folder.
    ///
    /// Examples:
    ///   drivelab run                                  # kyslan-pi, realtime, 10 kHz
    ///   drivelab run --clock lockstep --out runs/ls   # reproducible, as fast as possible
    ///   drivelab run --scenario my.toml --duration 2
    ///   drivelab run --topology two-process           # plant | observer + current + speed loop
    #[command(verbatim_doc_comment)]
    Run {
        /// Scenario name (see `drivelab scenarios`) or path to a TOML file.
        #[arg(long, default_value = "kyslan-pi")]
        scenario: String,
        /// Pacing: realtime (wall clock, deadlines), lockstep (wait for each command) or
        /// inprocess (one thread, no bus).
        #[arg(long, value_enum, default_value_t = Clock::Realtime)]
        clock: Clock,
        /// The run's length, s, instead of the scenario's. A shorter run leaves out the steps,
        /// injections and sensor faults that come at or after its end (one note line names them;
        /// summary.json → not_reached); what comes before is as in the full run.
        #[arg(long, value_name = "SECONDS", value_parser = duration_s)]
        duration: Option<f64>,
        /// Run folder (default: runs/<scenario>-<clock>-<unix time>, always a new one: -2,
        /// -3, … after it for another run in the same second).
        #[arg(long, value_name = "DIR")]
        out: Option<PathBuf>,
        /// Bus id isolating this drive's shared memory (default: the launcher's pid).
        #[arg(long, value_parser = bus_id)]
        bus: Option<String>,
        /// Fail when a core, SCHED_FIFO priority or mlock is refused (default: warn and run).
        #[arg(long, conflicts_with = "no_rt")]
        rt_strict: bool,
        /// Do not pin, raise priority or lock memory.
        #[arg(long)]
        no_rt: bool,
        /// Do not draw PNG/SVG plots.
        #[arg(long)]
        no_plots: bool,
        /// Also write timing.csv: per sample, when the plant, the observer, the speed loop and
        /// the current loop published their outputs for it, µs after the sample's instant t_k
        /// (realtime clock only).
        #[arg(long)]
        timing_csv: bool,
        /// Count every system call each stage host's loop makes from its first sample on beyond
        /// its wait and wakes (futex, clock_nanosleep, clock_gettime, restart_syscall,
        /// rt_sigreturn) up to a stop request, by name: summary.json → stray_syscalls (the
        /// total) and processes.<p>.stray_syscalls; check it with
        /// `--expect 'stray_syscalls == 0'`. A seccomp filter on each loop's thread; a
        /// counted call still runs, two thread switches slower.
        #[arg(long)]
        audit_syscalls: bool,
        /// Print the summary as JSON on stdout instead of the human summary.
        #[arg(long)]
        json: bool,
        /// Inject a fault (repeatable): kill:STAGE@SECONDS (SIGKILL),
        /// stop:STAGE@SECONDS:DURATION (SIGSTOP, then SIGCONT), random:N (N kills of random
        /// stages at random instants, seeded by --fault-seed): in real time the signal goes to
        /// the process that hosts the stage, and so to all its stages; lockstep and inprocess
        /// simulate them at their sample (see --lockstep-restart-ms).
        /// hog:CPU@SECONDS:DURATION:PRIO (a SCHED_FIFO busy loop pinned to CPU): realtime only.
        /// Applied by sample index in every clock: delay:STAGE@SECONDS:DURATION:LATENCY (the
        /// stage's every step in the window takes LATENCY longer, e.g. 200us or 0.3ms; felt in
        /// real time only, and a LATENCY above the sample time makes the stage fall behind), drop:TOPIC@SECONDS:N (N messages not published), corrupt:TOPIC@SECONDS:N (N
        /// messages with NaN and 1e30), encoder-stuck@SECONDS:DURATION (the encoder reading
        /// frozen), current-offset:PHASE@SECONDS:AMPS (phase a, b or c measured with an offset
        /// in A, to the end of the run). SECONDS and DURATION are seconds of simulated time (in real time the run's own clock).
        #[arg(long = "fault", value_name = "SPEC")]
        faults: Vec<String>,
        /// What the supervisor does when a process dies.
        #[arg(long, value_enum, default_value_t = launcher::Restart::OnFailure)]
        restart: launcher::Restart,
        /// Lockstep and inprocess: how long a killed stage stays dead before it rejoins
        /// (its simulated restart), milliseconds, 1 to 10000 [default: 40]. Not with
        /// --restart never, where a killed stage stays dead, nor in real time.
        #[arg(long, value_name = "MS", value_parser = drivelab_services::faults::restart_ms)]
        lockstep_restart_ms: Option<f64>,
        /// Seed of random:N fault plans.
        #[arg(long, default_value_t = 1, value_parser = seed)]
        fault_seed: u64,
        /// Topology: which stages share a process, on which core, at which priority. A
        /// shipped one (four-process, two-process, one-process, four-process-standby, split-hil) or a TOML file with
        /// [[process]] tables (or a scenario: its processes are taken); replaces the scenario's own.
        #[arg(long, value_name = "NAME|FILE")]
        topology: Option<String>,
        /// Check a summary figure after the run (repeatable; beside the scenario's [[expect]]
        /// tables): 'FIGURE OP LIMIT' with OP one of <= < >= > == or 'in A..B', FIGURE a
        /// path into summary.json (* for every key or element). The run exits with code 3
        /// when one fails. E.g. 'peak_current_a <= 8', 'faults.*.speed_recovered_ms <= 200',
        /// 'metrics.rise_time_ms in 7.2..8.8', 'deadline_misses_per_million <= 5000'.
        #[arg(long = "expect", value_name = "EXPR")]
        expect: Vec<String>,
        /// Put CMD in front of every process the launcher starts, as cargo's runner (split
        /// at whitespace; it must exec the program it is given). E.g. 'qemu-aarch64 -L
        /// /usr/aarch64-linux-gnu' runs an aarch64 build's stage hosts on x86_64. Default:
        /// the DRIVELAB_RUNNER environment variable.
        #[arg(long, value_name = "CMD")]
        runner: Option<String>,
        /// Make the drive reachable from other machines over Zenoh: a bridge process (on a
        /// core the drive does not use) listens on ENDPOINT, tcp/HOST:PORT or tls/HOST:PORT
        /// (default tcp/127.0.0.1:7447: this machine only; tcp/0.0.0.0:7447 for every
        /// interface). Off by default. See docs/remote.md.
        #[arg(long, value_name = "ENDPOINT", num_args = 0..=1, default_missing_value = "tcp/127.0.0.1:7447")]
        zenoh_listen: Option<String>,
        /// With --zenoh-listen: let `drivelab fault --connect` kill or freeze this drive's
        /// processes (refused otherwise).
        #[arg(long, requires = "zenoh_listen")]
        allow_remote_faults: bool,
        /// With --zenoh-listen: the bus topics to forward, comma-separated, from meas, truth,
        /// est, iref, cmd, wref, view, events (default truth,cmd,wref,view,events).
        #[arg(long, value_name = "LIST", requires = "zenoh_listen")]
        zenoh_topics: Option<String>,
        /// With --zenoh-listen or --zenoh-connect: a Zenoh configuration file (JSON5) for TLS
        /// and access control; its mode and endpoints are replaced by drivelab's.
        #[arg(long, value_name = "FILE")]
        zenoh_config: Option<PathBuf>,
        /// Run only machine NAME's processes of a split topology (one whose processes name
        /// a `machine`); the other machine runs the rest, joined over Zenoh: one side with
        /// --zenoh-listen, the other with --zenoh-connect. See docs/remote.md.
        #[arg(long, value_name = "NAME")]
        machine: Option<String>,
        /// With --machine: join the other machine's drive, started with --machine and
        /// --zenoh-listen, at ENDPOINT (tcp/HOST:PORT or tls/HOST:PORT).
        #[arg(
            long,
            value_name = "ENDPOINT",
            requires = "machine",
            conflicts_with = "zenoh_listen"
        )]
        zenoh_connect: Option<String>,
        /// With --machine: seconds to wait for the other machine to connect and be ready.
        #[arg(
            long,
            value_name = "SECONDS",
            default_value_t = 120.0,
            requires = "machine"
        )]
        zenoh_wait: f64,
        /// Serve the drive live over the Foxglove WebSocket protocol (subprotocol
        /// foxglove.websocket.v1) on ADDR, HOST:PORT or PORT (default 127.0.0.1:8765: this
        /// machine only; port 0: any free port, printed). Signals at 100 Hz of simulated
        /// time, per-stage rates, misses and latency percentiles once a second, the event log.
        /// Off by default. See docs/foxglove.md.
        #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = drivelab_services::foxglove::DEFAULT_ADDR)]
        foxglove: Option<String>,
    },
    /// Convert a run folder: write trace.mcap (every sample of trace.csv, the supervisor's
    /// events and fault reports, scenario and summary as metadata) for an older run that has
    /// none. Runs write trace.mcap themselves.
    ///
    /// Examples:
    ///   drivelab export runs/default --mcap
    #[command(verbatim_doc_comment)]
    Export {
        /// Run folder (with trace.csv, scenario.toml and summary.json).
        run: PathBuf,
        /// Write RUNDIR/trace.mcap (the only format so far, required).
        #[arg(long, required = true)]
        mcap: bool,
        /// Replace a trace.mcap that is there (a run's own has per-second latency and wall
        /// times that an export cannot rebuild).
        #[arg(long)]
        force: bool,
    },
    /// Record a remote drive (one started with --zenoh-listen) into a local run folder:
    /// scenario.toml, trace.csv, trace.mcap and summary.json with the missing samples and
    /// their causes, as a local run's.
    ///
    /// Example:
    ///   drivelab record --connect tcp/192.168.1.20:7447 --out runs/board --wait 30
    #[command(verbatim_doc_comment)]
    Record {
        /// The drive's Zenoh endpoint (tcp/HOST:PORT or tls/HOST:PORT).
        #[arg(long, value_name = "ENDPOINT")]
        connect: String,
        /// Run folder to write.
        #[arg(long, value_name = "DIR")]
        out: PathBuf,
        /// Bus id of the drive (only when the endpoint serves several).
        #[arg(long, value_parser = bus_id)]
        bus: Option<String>,
        /// Seconds to keep trying to connect while the drive is not up yet (0: one try).
        #[arg(long, default_value_t = 0.0, value_name = "SECONDS")]
        wait: f64,
        /// Zenoh configuration file (JSON5) for TLS.
        #[arg(long, value_name = "FILE")]
        zenoh_config: Option<PathBuf>,
    },
    /// Internal: the Zenoh bridge of a drive (started by `drivelab run --zenoh-listen`).
    #[command(hide = true)]
    Bridge {
        #[arg(long)]
        bus: String,
        #[arg(long)]
        listen: String,
        #[arg(long)]
        run_dir: PathBuf,
        #[arg(long)]
        topics: String,
        #[arg(long)]
        zenoh_config: Option<PathBuf>,
        #[arg(long)]
        allow_remote_faults: bool,
        #[arg(long)]
        connect: bool,
        #[arg(long)]
        machine: Option<String>,
        #[arg(long)]
        clock: Option<String>,
        #[arg(long, default_value_t = 120.0)]
        wait_s: f64,
    },
    /// Run a fault campaign: every scenario × fault set × seed of FILE.toml, each checked
    /// against the campaign's expectations and the scenarios' [[expect]] tables. Writes
    /// campaign.json, campaign.md and junit.xml (one test case per run). Exit code 3 when an
    /// expectation failed, 1 when a run did not complete.
    ///
    /// Examples:
    ///   drivelab campaign campaigns/smoke.toml --out runs/smoke
    ///   drivelab campaign campaigns/thorough.toml --out runs/thorough   # 123 runs, ~2.5 min
    #[command(verbatim_doc_comment)]
    Campaign(drivelab_services::campaign::CampaignArgs),
    /// Inject a fault into a drive that is already running (found by its bus id). The
    /// request goes to the drive's supervisor, which signals its own child process; the
    /// answer is printed (real-time drives only).
    ///
    /// Examples:
    ///   drivelab fault kill current-loop --bus 4242
    ///   drivelab fault stop observer --bus 4242 --duration-s 0.05
    ///   drivelab fault kill observer --connect tcp/192.168.1.20:7447
    #[command(verbatim_doc_comment)]
    Fault {
        /// kill (SIGKILL) or stop (SIGSTOP, then SIGCONT after --duration-s).
        #[arg(value_parser = ["kill", "stop"])]
        kind: String,
        /// The stage (plant, observer, current-loop, speed-loop or a user stage); its whole
        /// process is signalled.
        service: String,
        /// The drive (a remote one must run with --allow-remote-faults).
        #[command(flatten)]
        drive: DriveArgs,
        /// For stop: seconds before SIGCONT (0.001 to 60; default 0.05). A kill takes
        /// none: the stage stays dead until the supervisor restarts it.
        #[arg(long, alias = "duration", value_name = "SECONDS", value_parser = stop_s)]
        duration_s: Option<f64>,
    },
    /// Watch a running drive live in the terminal: per-stage state, rate, wake-up
    /// lateness, execution time and deadline misses; speed against its reference and i_d,
    /// i_q; the supervisor's event log. k / s kill or freeze the process of the selected
    /// stage after a confirmation (real-time drives only); q, Esc or Ctrl-C leave. The
    /// monitor reads the supervisor's telemetry, never the real-time processes' topics, so
    /// it does not disturb the drive.
    ///
    /// Examples:
    ///   drivelab run --bus 4242 --duration 60 &
    ///   drivelab monitor --bus 4242
    ///   drivelab monitor --bus 4242 --print        # one text frame on stdout, no terminal
    ///   drivelab monitor --connect tcp/192.168.1.20:7447   # a drive run with --zenoh-listen
    #[command(verbatim_doc_comment)]
    Monitor {
        /// The drive.
        #[command(flatten)]
        drive: DriveArgs,
        /// Screen refresh period, ms.
        #[arg(long, default_value_t = 100, value_name = "MS", value_parser = refresh_ms)]
        refresh_ms: u64,
        /// Freeze time of the `s` (stop) fault, ms (1..60000).
        #[arg(long, default_value_t = 200, value_name = "MS", value_parser = stop_ms)]
        stop_ms: u32,
        /// Print one frame as text on stdout and exit (for logs and scripts).
        #[arg(long)]
        print: bool,
        /// Size of the --print frame, COLUMNSxROWS (40-1000 columns, 20-1000 rows).
        #[arg(
            long,
            default_value = "140x40",
            value_name = "COLSxROWS",
            requires = "print",
            value_parser = print_size
        )]
        print_size: (u16, u16),
    },
    /// Remove the shared-memory files of a bus whose drive is gone (e.g. after the
    /// launcher itself was SIGKILLed). Refuses while any process still uses the bus.
    ///
    /// Example:
    ///   drivelab clean --bus 4242
    #[command(verbatim_doc_comment)]
    Clean {
        /// Bus id of the dead drive.
        #[arg(long, value_parser = bus_id)]
        bus: String,
    },
    /// Print the iceoryx2 configuration of a bus (TOML). Saved as config/iceoryx2.toml in
    /// a folder (every run folder has one), it lets iceoryx2's own `iox2` tool, started from
    /// that folder, see the drive's services.
    ///
    /// Example:
    ///   drivelab bus-config --bus 4242 > config/iceoryx2.toml && iox2 service list
    #[command(verbatim_doc_comment)]
    BusConfig {
        /// Bus id of the drive.
        #[arg(long, value_parser = bus_id)]
        bus: String,
    },
    /// Run the plant model alone, open loop, from rest, on recorded voltages.
    ///
    /// IN.csv has columns t,u_d,u_q,t_load (s, V, V, N·m), each row held from its t on.
    /// OUT.csv gets t,u_d,u_q,t_load,i_d,i_q,omega_m,theta_e at the input rows' times
    /// (i_d, i_q in A; omega_m in mechanical rad/s; theta_e in electrical rad).
    ///
    /// Example:
    ///   drivelab plant --replay volts.csv --out states.csv --motor kyslan2015
    #[command(verbatim_doc_comment)]
    Plant {
        /// Input CSV (t,u_d,u_q,t_load).
        #[arg(long, value_name = "IN.csv")]
        replay: PathBuf,
        /// Output CSV.
        #[arg(long, value_name = "OUT.csv")]
        out: PathBuf,
        /// Motor preset (kyslan2015, kyslan2015-sal618, low1998, miyajima) or TOML file.
        #[arg(long, default_value = "kyslan2015")]
        motor: String,
        /// Largest RK4 step, seconds.
        #[arg(
            long = "max-step-s",
            alias = "max-step",
            default_value_t = 1e-5,
            value_name = "SECONDS"
        )]
        max_step: f64,
    },
    /// List the shipped scenarios with their purpose and the paper figure they reproduce.
    ///
    /// Example:
    ///   drivelab scenarios
    #[command(verbatim_doc_comment)]
    Scenarios,
    /// Print the controller design of a scenario (current PI, speed PI by the symmetrical
    /// optimum) so it can be checked by hand.
    ///
    /// Examples:
    ///   drivelab design --scenario kyslan-pi
    ///   drivelab design --scenario kyslan-nl --motor kyslan2015-sal618 --rise-time-ms 8
    #[command(verbatim_doc_comment)]
    Design {
        /// Scenario name or file (rates, filters and current-loop settings come from it).
        #[arg(long, default_value = "kyslan-pi")]
        scenario: String,
        /// Use this motor instead of the scenario's: a preset (kyslan2015, kyslan2015-sal618,
        /// low1998, miyajima) or a TOML file with a [motor] table.
        #[arg(long)]
        motor: Option<String>,
        /// Target speed rise time (0 to 100 %, time to first reach the set-point), ms.
        #[arg(long, value_name = "MS", value_parser = rise_time_ms)]
        rise_time_ms: Option<f64>,
    },
    /// Plot several runs on one set of axes (speed, i_q, i_d) and print their metrics side
    /// by side, like Kyslan et al. Fig. 3 and 4.
    ///
    /// Example:
    ///   drivelab compare runs/kyslan-pi runs/kyslan-nl --out runs/compare
    #[command(verbatim_doc_comment)]
    Compare(drivelab_services::compare::CompareArgs),
    /// Measure the sample-time budget: a bare timer (the floor), the chain in one thread,
    /// the four processes over Unix sockets and over iceoryx2, at 5, 10 and 20 kHz and
    /// three placements; writes bench.json, bench.md, .hgrm files and percentile plots,
    /// with a verdict per configuration.
    ///
    /// Examples:
    ///   drivelab bench --quick                       # smoke run, ~10 s
    ///   drivelab bench --seconds 30 --rates 10000    # 30 s per variant at 10 kHz
    #[command(verbatim_doc_comment)]
    Bench(drivelab_services::bench::BenchArgs),
    /// Internal (tests): publish malformed estimates onto a running drive's bus.
    #[command(hide = true)]
    BusInject {
        /// Bus id of the running drive.
        #[arg(long)]
        bus: String,
        /// nan or backwards.
        #[arg(long)]
        kind: String,
        /// How many messages.
        #[arg(long, default_value_t = 10)]
        count: u32,
    },
    /// Internal: a hog fault's busy loop (started by the supervisor for `--fault hog:…`).
    #[command(hide = true)]
    Hog {
        /// CPU to pin to.
        #[arg(long)]
        cpu: usize,
        /// SCHED_FIFO priority, 1..=99.
        #[arg(long)]
        priority: u8,
        /// How long to spin, s (0: only check that the CPU and priority are granted).
        #[arg(long)]
        duration_s: f64,
        /// Bus id of the drive it disturbs (a label: the hog uses no bus).
        #[arg(long)]
        bus: Option<String>,
        /// Wait for one byte on stdin before spinning (end of file: exit unstarted).
        #[arg(long)]
        armed: bool,
    },
    /// Internal: one node of the Unix-socket chain (started by `drivelab bench`).
    #[command(hide = true)]
    BenchNode {
        #[command(subcommand)]
        kind: BenchNodeKind,
    },
    /// Print and plot the relative truncation error ζ of the observer's model I + A·T_s
    /// against speed (Low et al. 1998 eq. 14, Fig. 3) for given sample times, with the
    /// steady-state angle error it causes (truncated against exact discretisation).
    ///
    /// Examples:
    ///   drivelab observer-error --ts 0.2ms
    ///   drivelab observer-error --ts 0.1ms,0.2ms,0.5ms --motor low1998 --max-rpm 3000
    #[command(verbatim_doc_comment)]
    ObserverError(drivelab_services::observer_error::ObserverErrorArgs),
    /// Print the coefficient-diagram design of the polar current loops of Miyajima et al.
    /// (C_21: i_q through V_a, C_12: i_d through δ; eqs 26-37) at one operating point
    /// (V_ao, δ_o, and τ_12 from eq. 37 unless given), to check eqs (28)-(31) by hand.
    ///
    /// Examples:
    ///   drivelab cdm-design --v-ao-v 5 --delta-o-deg 0              # miyajima, T_u = 100 µs, V_dc = 470 V
    ///   drivelab cdm-design --tu-us 100 --v-amax-v 271.4 --v-ao-v 30 --delta-o-deg 20
    ///   drivelab cdm-design --v-ao-v 1 --delta-o-deg 0 --json       # τ_12 slowed by eq. (37)
    #[command(verbatim_doc_comment)]
    CdmDesign(drivelab_services::cdm_design::CdmArgs),
    /// Redraw every figure of a run as PNG and SVG (traces with references and limits,
    /// latency percentiles, fault windows), optionally for a time window.
    ///
    /// Examples:
    ///   drivelab plot runs/default
    ///   drivelab plot runs/default --window 0.035:0.07 --out runs/zoom
    #[command(verbatim_doc_comment)]
    Plot(drivelab_services::plotcmd::PlotArgs),
    /// Report how ready this machine is for real-time work. Reads only; changes nothing.
    ///
    /// Examples:
    ///   drivelab doctor
    ///   drivelab doctor --topology two-process   # isolation, irqs, kernel runs on its cores
    #[command(verbatim_doc_comment)]
    Doctor {
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
        /// Judge the per-core checks (isolated cpus, device irqs, kernel runs) for the cores
        /// this topology (a shipped name, a topology file, or a scenario file: its processes)
        /// pins its processes to, and add a
        /// "placement" line about it; without it they are judged for the isolated cpus, else
        /// every cpu but the first (the default placement uses cpu 1).
        #[arg(long, value_name = "NAME|FILE")]
        topology: Option<String>,
        /// With a --topology split across machines (its processes name a `machine`): this
        /// machine's name, as `drivelab run --machine` takes it. Only its processes' cores
        /// are judged, the other machine's named as not judged here; without it the whole
        /// topology is judged here, as `drivelab run` without --machine runs it.
        #[arg(long, value_name = "NAME", requires = "topology")]
        machine: Option<String>,
    },
}

#[derive(Debug, Subcommand)]
enum BenchNodeKind {
    /// A node of the Unix-domain-socket chain.
    Uds {
        /// plant, observer, current-loop or speed-loop.
        #[arg(long)]
        role: String,
        /// Socket folder.
        #[arg(long)]
        dir: PathBuf,
        /// Scenario file.
        #[arg(long)]
        scenario: PathBuf,
        /// Seconds to run.
        #[arg(long)]
        seconds: f64,
        /// CPU core.
        #[arg(long)]
        core: Option<usize>,
        /// SCHED_FIFO priority.
        #[arg(long)]
        priority: Option<u8>,
        /// Result file: the plant's measurements, another role's system-call count.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// The receiver of the hop floor.
    Hop {
        /// Bus id of the wake segment.
        #[arg(long)]
        bus: String,
        /// This receiver's place in the chain, 1-based.
        #[arg(long, default_value_t = 1)]
        position: usize,
        /// Receivers in the chain.
        #[arg(long, default_value_t = 1)]
        hops: usize,
        /// What the last receiver records: wakeup (notify → running) or cycle (deadline →
        /// running).
        #[arg(long, default_value = "wakeup")]
        measure: drivelab_bench::hop::Measure,
        /// Sample period, ns (to count a cycle's misses).
        #[arg(long, default_value_t = 0)]
        period_ns: u64,
        /// CPU core.
        #[arg(long)]
        core: Option<usize>,
        /// SCHED_FIFO priority.
        #[arg(long)]
        priority: Option<u8>,
        /// Histogram file (HdrHistogram V2).
        #[arg(long)]
        out: PathBuf,
    },
}

fn main() -> ExitCode {
    drivelab_runtime::bus::quiet_iceoryx2_log();
    drivelab_runtime::service::file_size_limit_as_error();
    let cli = match parse_cli() {
        Ok(cli) => cli,
        Err(code) => return code,
    };
    match real_main(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            if let Some(r) = e.downcast_ref::<drivelab_services::expect::Reported>() {
                // What failed was printed on its own lines.
                return ExitCode::from(r.0);
            }
            drivelab_services::errln!(
                "drivelab: error: {}",
                drivelab_runtime::text::error_text(&e)
            );
            // A value the command line itself gets wrong (out of range, a malformed
            // expectation, options that cannot go together) is a usage error, as clap's are.
            if e.downcast_ref::<drivelab_services::expect::UsageError>()
                .is_some()
            {
                ExitCode::from(2)
            } else {
                ExitCode::from(1)
            }
        }
    }
}

/// Parses the command line. Help and version are printed as clap prints them; any other
/// problem is one line on stderr, exit code 2.
fn parse_cli() -> Result<Cli, ExitCode> {
    negative_values(Cli::command())
        .try_get_matches_from(non_finite_values(std::env::args_os()))
        .and_then(|m| Cli::from_arg_matches(&m))
        .map_err(|e| {
            use clap::error::ErrorKind;
            match e.kind() {
                ErrorKind::DisplayHelp
                | ErrorKind::DisplayVersion
                | ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand => e.exit(),
                ErrorKind::InvalidSubcommand => {
                    // clap's tip alone can mislead ('nosuch' is "similar" to 'bench'): the
                    // commands there are, by name.
                    let commands: Vec<String> = Cli::command()
                        .get_subcommands()
                        .filter(|c| !c.is_hide_set())
                        .map(|c| c.get_name().to_string())
                        .collect();
                    drivelab_services::errln!(
                        "drivelab: error: {}; the commands are {}",
                        clap_line(&e),
                        commands.join(", ")
                    );
                    ExitCode::from(2)
                }
                _ => {
                    drivelab_services::errln!("drivelab: error: {}", clap_line(&e));
                    ExitCode::from(2)
                }
            }
        })
}

/// Lets every value start with '-' when it is a number, so that `--duration -1` is refused
/// by its range instead of being taken for a flag.
fn negative_values(c: clap::Command) -> clap::Command {
    c.mut_args(|a| {
        if a.get_action().takes_values() {
            a.allow_negative_numbers(true)
        } else {
            a
        }
    })
    .mut_subcommands(negative_values)
}

/// Joins `-inf`, `-infinity` and `-nan` to the long option before them (`--duration=-inf`),
/// so that the option's own range refuses them: clap takes only digits after a '-' for a
/// negative number and would call `-inf` an unknown flag '-i'.
fn non_finite_values(args: impl Iterator<Item = std::ffi::OsString>) -> Vec<std::ffi::OsString> {
    let mut out: Vec<std::ffi::OsString> = Vec::new();
    for a in args {
        let word = a.to_str().map(str::to_ascii_lowercase);
        let non_finite = matches!(word.as_deref(), Some("-inf" | "-infinity" | "-nan"));
        match out.last_mut() {
            Some(option)
                if non_finite
                    && option.to_str().is_some_and(|o| {
                        o.starts_with("--") && o.len() > 2 && !o.contains('=')
                    }) =>
            {
                option.push("=");
                option.push(&a);
            }
            _ => out.push(a),
        }
    }
    out
}

/// A clap error on one line: what is wrong, its possible values and tip, without the usage.
fn clap_line(e: &clap::Error) -> String {
    let text = e.render().to_string();
    let mut line = String::new();
    for l in text
        .lines()
        .map(str::trim)
        .take_while(|l| !l.starts_with("Usage:") && !l.starts_with("For more information"))
        .filter(|l| !l.is_empty())
    {
        if !line.is_empty() {
            line.push_str(if l.starts_with("tip:") { "; " } else { " " });
        }
        line.push_str(l);
    }
    line.strip_prefix("error: ").unwrap_or(&line).to_string()
}

/// A finite number above `min` and at most `max` of `unit`, or the reason, which clap
/// prints after the option and the value.
fn number_in(v: &str, min: f64, max: f64, unit: &str) -> Result<f64, String> {
    let range = format!("must be more than {min} and at most {max} {unit}");
    match v.trim().parse::<f64>() {
        Ok(x) if x.is_finite() && x > min && x <= max => Ok(x),
        Ok(_) => Err(range),
        Err(_) => Err(format!("not a number ({range})")),
    }
}

/// A whole number within `min..=max` of `unit`, or the reason.
fn whole_in(v: &str, min: u64, max: u64, unit: &str) -> Result<u64, String> {
    v.trim()
        .parse::<u64>()
        .ok()
        .filter(|x| (min..=max).contains(x))
        .ok_or_else(|| format!("must be a whole number from {min} to {max}{unit}"))
}

/// `run --fault-seed`: any 64-bit seed.
fn seed(v: &str) -> Result<u64, String> {
    whole_in(v, 0, u64::MAX, "")
}

/// `monitor --refresh-ms`.
fn refresh_ms(v: &str) -> Result<u64, String> {
    whole_in(v, 10, 10_000, " ms")
}

/// `monitor --stop-ms`: the bounds of a stop fault.
fn stop_ms(v: &str) -> Result<u32, String> {
    whole_in(v, 1, 60_000, " ms").map(|x| x as u32)
}

/// `monitor --print-size`: COLSxROWS with 40-1000 columns and 20-1000 rows.
fn print_size(v: &str) -> Result<(u16, u16), String> {
    v.split_once('x')
        .and_then(|(w, h)| Some((w.parse::<u16>().ok()?, h.parse::<u16>().ok()?)))
        .filter(|&(w, h)| (40..=1000).contains(&w) && (20..=1000).contains(&h))
        .ok_or_else(|| "must be COLSxROWS with 40-1000 columns and 20-1000 rows".to_string())
}

/// `fault stop --duration-s`: the bounds of a stop, both included.
fn stop_s(v: &str) -> Result<f64, String> {
    use drivelab_services::faults::{STOP_MAX_S, STOP_MIN_S};
    match v.trim().parse::<f64>() {
        Ok(x) if (STOP_MIN_S..=STOP_MAX_S).contains(&x) => Ok(x),
        _ => Err(format!("a stop lasts {STOP_MIN_S} to {STOP_MAX_S} s")),
    }
}

/// `run --duration`: the scenario's own bounds on its duration.
fn duration_s(v: &str) -> Result<f64, String> {
    number_in(v, 0.0, 3600.0, "s")
}

/// `design --rise-time-ms`: the scenario's own bounds on the speed rise time.
fn rise_time_ms(v: &str) -> Result<f64, String> {
    number_in(v, 0.0, 10_000.0, "ms")
}

/// A bus id (1-24 characters of A-Z, a-z, 0-9 or _).
fn bus_id(v: &str) -> Result<String, String> {
    drivelab_runtime::bus::check_bus_id(v)
        .map(|()| v.to_string())
        .map_err(|e| e.to_string())
}

/// `--zenoh-config FILE`, checked to be a file before anything starts. A bad file is an
/// error (exit code 1), as a bad scenario file is, not a usage error.
fn zenoh_config_file(file: Option<PathBuf>) -> anyhow::Result<Option<PathBuf>> {
    if let Some(p) = &file {
        match std::fs::metadata(p) {
            Ok(m) if m.is_file() => {}
            Ok(_) => anyhow::bail!("--zenoh-config {}: not a file", p.display()),
            Err(e) => anyhow::bail!("--zenoh-config {}: cannot read it: {e}", p.display()),
        }
    }
    Ok(file)
}

/// Metric `key` of `summary.json → metrics` as [`fmt_opt`] writes it; a null one whose window
/// a fault cut says so: `n/a (cut by the fault at 0.500 s (kill:current-loop@0.5))`.
fn fmt_metric(m: &serde_json::Value, key: &str, unit: &str) -> String {
    let text = fmt_opt(&m[key], unit);
    match m["cut_by_fault"][key].as_str() {
        Some(why) if m[key].is_null() => format!("{text} ({why})"),
        _ => text,
    }
}

fn fmt_opt(v: &serde_json::Value, unit: &str) -> String {
    v.as_f64()
        .map(|x| {
            // A value that rounds to zero is 0.000, not -0.000.
            let text = format!("{x:.3}");
            let text = text
                .strip_prefix('-')
                .filter(|t| t.trim_start_matches(['0', '.']).is_empty())
                .unwrap_or(&text);
            drivelab_runtime::text::readable_numbers(&format!("{text} {unit}")).into_owned()
        })
        .unwrap_or_else(|| "n/a".into())
}

/// Checks a Zenoh endpoint given to `flag` (a usage error names the problem).
#[cfg(feature = "zenoh")]
fn endpoint_arg(flag: &str, ep: &str, listen: bool) -> anyhow::Result<String> {
    drivelab_bridge::link::check_endpoint(ep, listen).map_err(|e| usage(format!("{flag}: {e}")))
}

/// `--zenoh-listen`'s endpoint, checked and found free before the drive makes anything (a
/// port in use leaves no run folder behind), with port 0 replaced by a free port.
#[cfg(feature = "zenoh")]
fn listen_arg(ep: &str) -> anyhow::Result<String> {
    let ep = endpoint_arg("--zenoh-listen", ep, true)?;
    drivelab_bridge::link::check_free(&ep).map_err(|e| anyhow::anyhow!("--zenoh-listen: {e}"))
}

/// `--zenoh-config` of a run, read before the drive makes anything: a bad file leaves no run
/// folder behind.
#[cfg(feature = "zenoh")]
fn zenoh_config_arg(file: Option<PathBuf>) -> anyhow::Result<Option<PathBuf>> {
    if let Some(f) = &file {
        drivelab_bridge::link::check_config(f)?;
    }
    Ok(file)
}

#[cfg(not(feature = "zenoh"))]
fn zenoh_config_arg(file: Option<PathBuf>) -> anyhow::Result<Option<PathBuf>> {
    Ok(file)
}

#[cfg(not(feature = "zenoh"))]
fn listen_arg(ep: &str) -> anyhow::Result<String> {
    endpoint_arg("--zenoh-listen", ep, true)
}

#[cfg(not(feature = "zenoh"))]
fn endpoint_arg(flag: &str, _: &str, _: bool) -> anyhow::Result<String> {
    Err(usage(format!(
        "{flag}: this drivelab was built without Zenoh (cargo feature `zenoh`)"
    )))
}

#[cfg(feature = "zenoh")]
fn zenoh_topics_arg(list: &str) -> anyhow::Result<Vec<String>> {
    drivelab_bridge::parse_topics(list).map_err(|e| usage(format!("--zenoh-topics: {e}")))
}

#[cfg(not(feature = "zenoh"))]
fn zenoh_topics_arg(_: &str) -> anyhow::Result<Vec<String>> {
    Ok(Vec::new())
}

#[cfg(feature = "zenoh")]
fn default_zenoh_topics() -> Vec<String> {
    drivelab_bridge::DEFAULT_TOPICS
        .iter()
        .map(|t| t.to_string())
        .collect()
}

#[cfg(not(feature = "zenoh"))]
fn default_zenoh_topics() -> Vec<String> {
    Vec::new()
}

/// The drive of `monitor` and `fault`: a local bus or a remote endpoint.
fn target(d: DriveArgs) -> anyhow::Result<drivelab_services::monitor::Target> {
    use drivelab_services::monitor::Target;
    let config = zenoh_config_file(d.zenoh_config)?;
    Ok(match (d.connect, d.bus) {
        (Some(ep), bus) => Target::Remote {
            endpoint: endpoint_arg("--connect", &ep, false)?,
            bus,
            config,
        },
        // The id was checked by `bus_id` when the command line was read.
        (None, Some(bus)) => Target::Bus(bus),
        (None, None) => return Err(usage("give --bus ID or --connect ENDPOINT".into())),
    })
}

#[cfg(feature = "zenoh")]
fn record(
    endpoint: String,
    out: PathBuf,
    bus: Option<String>,
    wait: f64,
    config: Option<PathBuf>,
) -> anyhow::Result<()> {
    let r = drivelab_services::record::record(&drivelab_services::record::RecordOptions {
        endpoint: endpoint.clone(),
        bus,
        config,
        out: out.clone(),
        wait: std::time::Duration::from_secs_f64(wait),
    })?;
    let s = &r.summary;
    drivelab_services::outln!(
        "run folder: {} (bus {} at {endpoint})",
        out.display(),
        r.bus
    );
    drivelab_services::outln!(
        "{} samples ({} expected), {} missing; deadline misses on the drive {}",
        s["samples"],
        s["samples_expected"],
        s["samples_missing"],
        s["deadline_misses"]
    );
    Ok(())
}

#[cfg(not(feature = "zenoh"))]
fn record(
    _: String,
    _: PathBuf,
    _: Option<String>,
    _: f64,
    _: Option<PathBuf>,
) -> anyhow::Result<()> {
    unreachable!("endpoint_arg refuses --connect without zenoh")
}

/// The internal `drivelab bridge` command's options, as the launcher passes them (read only
/// by a build with Zenoh).
#[cfg_attr(not(feature = "zenoh"), allow(dead_code))]
struct BridgeArgs {
    bus: String,
    listen: String,
    run_dir: PathBuf,
    topics: String,
    config: Option<PathBuf>,
    allow_remote_faults: bool,
    connect: bool,
    split: Option<(String, String)>,
    wait_s: f64,
}

#[cfg(feature = "zenoh")]
fn bridge(a: BridgeArgs) -> anyhow::Result<()> {
    drivelab_bridge::serve::serve(&drivelab_bridge::serve::ServeOptions {
        bus: a.bus,
        listen: a.listen,
        config: a.config,
        allow_remote_faults: a.allow_remote_faults,
        topics: drivelab_bridge::parse_topics(&a.topics).map_err(|e| anyhow::anyhow!(e))?,
        run_dir: a.run_dir,
        connect: a.connect,
        split: a.split,
        wait: std::time::Duration::from_secs_f64(a.wait_s),
    })
}

#[cfg(not(feature = "zenoh"))]
fn bridge(_: BridgeArgs) -> anyhow::Result<()> {
    anyhow::bail!("this drivelab was built without Zenoh (cargo feature `zenoh`)")
}

fn real_main(cli: Cli) -> anyhow::Result<()> {
    use drivelab_services::expect::{Reported, EXIT_EXPECTATION_FAILED};
    match cli.cmd {
        Cmd::Run {
            scenario,
            clock,
            duration,
            out,
            bus,
            rt_strict,
            no_rt,
            no_plots,
            timing_csv,
            audit_syscalls,
            json,
            faults,
            restart,
            fault_seed,
            lockstep_restart_ms,
            topology,
            expect,
            runner,
            zenoh_listen,
            allow_remote_faults,
            zenoh_topics,
            zenoh_config,
            machine,
            zenoh_connect,
            zenoh_wait,
            foxglove,
        } => {
            let foxglove = foxglove
                .map(|a| drivelab_services::foxglove::parse_addr(&a))
                .transpose()?;
            if zenoh_config.is_some() && zenoh_listen.is_none() && zenoh_connect.is_none() {
                return Err(usage(
                    "--zenoh-config needs --zenoh-listen or --zenoh-connect".into(),
                ));
            }
            if machine.is_some() && zenoh_listen.is_none() && zenoh_connect.is_none() {
                return Err(usage(
                    "--machine needs --zenoh-listen (this side listens) or --zenoh-connect ENDPOINT (this side joins the other)".into(),
                ));
            }
            if !(1.0..=3600.0).contains(&zenoh_wait) {
                return Err(usage(format!(
                    "--zenoh-wait {zenoh_wait}: 1 to 3600 seconds"
                )));
            }
            let endpoint = match (zenoh_listen, zenoh_connect) {
                (Some(ep), _) => Some((listen_arg(&ep)?, false)),
                (None, Some(ep)) => Some((endpoint_arg("--zenoh-connect", &ep, false)?, true)),
                (None, None) => None,
            };
            let zenoh = endpoint
                .map(
                    |(endpoint, connect)| -> anyhow::Result<launcher::ZenohListen> {
                        Ok(launcher::ZenohListen {
                            endpoint,
                            config: zenoh_config_arg(zenoh_config_file(zenoh_config)?)?,
                            allow_remote_faults,
                            topics: match zenoh_topics {
                                Some(t) => zenoh_topics_arg(&t)?,
                                None => default_zenoh_topics(),
                            },
                            connect,
                            machine,
                            wait: std::time::Duration::from_secs_f64(zenoh_wait),
                        })
                    },
                )
                .transpose()?;
            let runner = runner
                .map(|r| drivelab_runtime::runner::Runner::parse(&r))
                .transpose()
                .map_err(|e| usage(format!("--runner: {e}")))?;
            let faults = faults
                .iter()
                .map(|f| drivelab_services::faults::parse(f).map_err(|e| usage(format!("{e:#}"))))
                .collect::<anyhow::Result<Vec<_>>>()?;
            drivelab_services::faults::check_counts(&faults).map_err(usage)?;
            if restart == launcher::Restart::Never && lockstep_restart_ms.is_some() {
                return Err(usage(
                    "--lockstep-restart-ms with --restart never: a killed stage stays dead, there is no restart to time".into(),
                ));
            }
            if clock == Clock::Realtime && lockstep_restart_ms.is_some() {
                return Err(usage(
                    "--lockstep-restart-ms times a simulated restart (--clock lockstep or inprocess); in real time the supervisor restarts the process itself".into(),
                ));
            }
            let lockstep_restart_ms =
                lockstep_restart_ms.unwrap_or(drivelab_runtime::inject::RESTART_DEFAULT_MS);
            let o = RunOptions {
                scenario,
                clock,
                duration_s: duration,
                out,
                bus,
                rt_strict,
                no_rt,
                no_plots,
                verbose: !json,
                faults,
                restart,
                fault_seed,
                lockstep_restart_ms,
                topology,
                expect,
                runner,
                zenoh,
                foxglove,
                timing_csv,
                audit_syscalls,
                quiet_hosts: false,
                quiet_warnings: false,
            };
            let r = launcher::run(&o)?;
            let failed = drivelab_services::expect::failed(&r.summary);
            if json {
                drivelab_services::outln!("{}", serde_json::to_string_pretty(&r.summary)?);
            } else {
                let s = &r.summary;
                let m = &s["metrics"];
                drivelab_services::outln!("run folder: {}", r.out.display());
                if let Some(r) = s["replaced_stages"].as_object().filter(|r| !r.is_empty()) {
                    let by: Vec<String> = r
                        .iter()
                        .map(|(st, exe)| format!("{st} by {}", exe.as_str().unwrap_or("?")))
                        .collect();
                    drivelab_services::outln!("built-in stages replaced: {}", by.join(", "));
                }
                // Below 1× (a short or a networked lockstep run): two decimals, not "0.0×".
                let speed = s["simulated_s_per_wall_s"].as_f64().unwrap_or(0.0);
                let speed = if speed < 1.0 {
                    format!("{speed:.2}")
                } else {
                    format!("{speed:.1}")
                };
                drivelab_services::outln!(
                    "{} samples ({} expected), deadline misses {}, wall {:.2} s ({speed}× real time)",
                    s["samples"],
                    s["samples_expected"],
                    s["deadline_misses"],
                    s["wall_time_s"].as_f64().unwrap_or(0.0),
                );
                if let Some(l) = s["timing"]["stalls"]["line"].as_str() {
                    drivelab_services::outln!("{l}");
                }
                if let Some(l) = s["timing"]["tail_by_part"]["line"].as_str() {
                    drivelab_services::outln!("{l}");
                }
                if let Some(l) = launcher::stray_syscalls_line(s) {
                    drivelab_services::outln!("{l}");
                }
                if let Some(outer) = m["speed_reference_from"].as_str() {
                    drivelab_services::outln!(
                        "speed metrics left out: stage '{outer}' makes the speed reference, not the scenario's [reference]"
                    );
                } else if m["speed_prescribed_rad_s"].is_number() {
                    drivelab_services::outln!(
                        "speed metrics left out: a dynamometer held the speed at {} ([mechanics] prescribed_speed_rad_s)",
                        fmt_opt(&m["speed_prescribed_rad_s"], "rad/s")
                    );
                } else {
                    drivelab_services::outln!(
                        "rise {}, overshoot {}, load dip {}, load recovery {}, steady-state error {}",
                        fmt_metric(m, "rise_time_ms", "ms"),
                        fmt_metric(m, "overshoot_pct", "%"),
                        fmt_metric(m, "load_dip_rad_s", "rad/s"),
                        fmt_metric(m, "load_recovery_ms", "ms"),
                        fmt_metric(m, "steady_state_error_rad_s", "rad/s")
                    );
                }
                if m["angle_error_ss_deg"].as_f64().is_some() {
                    drivelab_services::outln!(
                        "observer: angle error θ̂ − θ in the last 10 % {}, within ±1° of it after {}",
                        fmt_opt(&m["angle_error_ss_deg"], "° electrical"),
                        fmt_opt(&m["observer_convergence_ms"], "ms")
                    );
                }
                if m["iq_rise_time_us"].as_f64().is_some() || m["id_max_a"].as_f64().is_some() {
                    drivelab_services::outln!(
                        "i_q rise (10-90 %) {}, i_q overshoot {}, max settled i_d {}",
                        fmt_metric(m, "iq_rise_time_us", "µs"),
                        fmt_metric(m, "iq_overshoot_pct", "%"),
                        fmt_metric(m, "id_max_a", "A")
                    );
                }
                if let Some(g) = s["missing_samples"].as_array().filter(|g| !g.is_empty()) {
                    let count = |part: &str| -> u64 {
                        g.iter()
                            .filter(|x| x["part"] == part)
                            .map(|x| {
                                x["to"].as_u64().unwrap_or(0) + 1 - x["from"].as_u64().unwrap_or(0)
                            })
                            .sum()
                    };
                    let parts: Vec<String> = [
                        ("measurement", "measurements"),
                        ("command", "commands"),
                        ("row", "rows not written"),
                    ]
                    .iter()
                    .map(|&(one, many)| (count(one), one, many))
                    .filter(|&(n, ..)| n > 0)
                    .map(|(n, one, many)| format!("{n} {}", if n == 1 { one } else { many }))
                    .collect();
                    drivelab_services::outln!(
                        "missing from the trace: {} ({} {}); each cause in summary.json → missing_samples",
                        parts.join(", "),
                        g.len(),
                        if g.len() == 1 { "range" } else { "ranges" }
                    );
                }
                if let Some(w) = launcher::rate_warning(s, o.clock == Clock::Realtime) {
                    drivelab_services::errln!("drivelab: warning: {w}");
                }
                // A process that died without an injected kill, even if restarted.
                if let Some(n) = s["crashes"].as_u64().filter(|&n| n > 0) {
                    let mut who: Vec<&str> = s["supervisor_events"]
                        .as_array()
                        .into_iter()
                        .flatten()
                        .filter(|e| {
                            e["event"] == "exited"
                                && e["detail"]
                                    .as_str()
                                    .is_some_and(|d| d.ends_with(launcher::NOT_INJECTED))
                        })
                        .filter_map(|e| e["process"].as_str())
                        .collect();
                    who.sort_unstable();
                    who.dedup();
                    drivelab_services::errln!(
                        "drivelab: warning: {n} process {} without an injected fault ({}); see summary.json → supervisor_events",
                        if n == 1 { "exit" } else { "exits" },
                        who.join(", ")
                    );
                }
                // A fault a monitor asked for and not made (refused, or its process was
                // down); a planned one not made fails the run.
                for e in s["supervisor_events"].as_array().into_iter().flatten() {
                    let detail = e["detail"].as_str().unwrap_or("");
                    if e["event"] == "inject-refused" {
                        drivelab_services::errln!("drivelab: warning: fault not made: {detail}");
                    } else if e["event"] == "inject-skipped" {
                        drivelab_services::errln!(
                            "drivelab: warning: fault not made: {}: {detail}",
                            e["service"].as_str().unwrap_or("")
                        );
                    }
                }
                if let Some(f) = s["faults"].as_array().filter(|f| !f.is_empty()) {
                    drivelab_services::outln!(
                        "faults: {} injected; report in summary.json → faults",
                        f.len()
                    );
                }
                // Checked and met says so: a CI log tells it from not checked.
                let n = s["expectations"].as_array().map_or(0, Vec::len);
                if n > 0 && failed.is_empty() {
                    drivelab_services::outln!(
                        "expectations: {n} of {n} met; each in summary.json → expectations"
                    );
                }
            }
            if !failed.is_empty() {
                for line in &failed {
                    drivelab_services::errln!("drivelab: {line}");
                }
                return Err(Reported(EXIT_EXPECTATION_FAILED).into());
            }
            Ok(())
        }
        Cmd::Plant {
            replay,
            out,
            motor,
            max_step,
        } => {
            let m = drivelab_services::replay::resolve_motor(&motor)?;
            // Longer RK4 steps than the electrical time constant give numbers, not the model.
            let tau = m.l_d_h.min(m.l_q_h) / m.r_ohm;
            if !(max_step.is_finite() && max_step > 0.0 && max_step <= tau) {
                return Err(usage(format!(
                    "--max-step-s {max_step}: must be more than 0 and at most the motor's electrical time constant min(L_d, L_q)/R = {tau:.3e} s"
                )));
            }
            let n = drivelab_services::replay::replay(&replay, &out, &m, max_step)?;
            drivelab_services::errln!("wrote {n} rows to {}", out.display());
            Ok(())
        }
        Cmd::Scenarios => {
            let list = drivelab_runtime::config::list_scenarios();
            if list.is_empty() {
                anyhow::bail!(
                    "no scenarios found in {}",
                    drivelab_runtime::config::scenarios_dir().display()
                );
            }
            // Name and reproduced figure on one line, the purpose indented below it: the
            // purposes are too long for a third column.
            let w = list.iter().map(|(n, _)| n.len()).max().unwrap_or(0);
            drivelab_services::outln!("{:<w$}  reproduces\n    purpose\n", "name");
            for (name, path) in list {
                let text = std::fs::read_to_string(&path)?;
                match drivelab_runtime::config::Scenario::from_toml(
                    &text,
                    &path.display().to_string(),
                ) {
                    Ok(s) => {
                        drivelab_services::outln!("{name:<w$}  {}\n    {}", s.reproduces, s.purpose)
                    }
                    Err(e) => drivelab_services::outln!("{name:<w$}  INVALID: {e}"),
                }
            }
            Ok(())
        }
        Cmd::Design {
            scenario,
            motor,
            rise_time_ms,
        } => {
            let (mut sc, src) = drivelab_runtime::config::Scenario::load(&scenario)
                .map_err(|e| anyhow::anyhow!(e))?;
            if let Some(m) = motor {
                let p = drivelab_services::replay::resolve_motor(&m)?;
                sc.motor = drivelab_runtime::config::MotorSpec {
                    preset: None,
                    r_ohm: Some(p.r_ohm),
                    l_d_h: Some(p.l_d_h),
                    l_q_h: Some(p.l_q_h),
                    pole_pairs: Some(p.pole_pairs),
                    psi_pm_wb: Some(p.psi_pm_wb),
                    j_kgm2: Some(p.j_kgm2),
                    b_nms: Some(p.b_nms),
                    i_max_a: Some(p.i_max_a),
                    omega_rated_rad_s: Some(p.omega_rated_rad_s),
                    t_rated_nm: Some(p.t_rated_nm),
                };
            }
            if let Some(r) = rise_time_ms {
                sc.speed_loop.rise_time_s = r * 1e-3;
            }
            sc.validate().map_err(|e| anyhow::anyhow!(e))?;
            // A built-in stage that a process's `exec` hosts a stage of the same name for (it is
            // asked, as `run` asks it) is the user's stage: the built-in's design is printed for
            // comparison and says "not run".
            let (replaced, notes) = drivelab_services::design::replacements(&mut sc, &src)?;
            drivelab_services::out!("{}", drivelab_services::design::render(&sc, &replaced));
            for line in notes {
                drivelab_services::outln!("note: {line}");
            }
            Ok(())
        }
        Cmd::Monitor {
            drive,
            refresh_ms,
            stop_ms,
            print,
            print_size,
        } => {
            let size = print.then_some(print_size);
            drivelab_services::monitor::run(&drivelab_services::monitor::MonitorOptions {
                target: target(drive)?,
                refresh: std::time::Duration::from_millis(refresh_ms),
                stop_ms,
                print: size,
            })?;
            Ok(())
        }
        Cmd::Record {
            connect,
            out,
            bus,
            wait,
            zenoh_config,
        } => {
            let endpoint = endpoint_arg("--connect", &connect, false)?;
            if !(0.0..=3600.0).contains(&wait) {
                return Err(usage(format!("--wait {wait}: 0 to 3600 seconds")));
            }
            record(endpoint, out, bus, wait, zenoh_config_file(zenoh_config)?)
        }
        Cmd::Bridge {
            bus,
            listen,
            run_dir,
            topics,
            zenoh_config,
            allow_remote_faults,
            connect,
            machine,
            clock,
            wait_s,
        } => bridge(BridgeArgs {
            bus,
            listen,
            run_dir,
            topics,
            config: zenoh_config,
            allow_remote_faults,
            connect,
            split: machine.zip(clock),
            wait_s,
        }),
        Cmd::Clean { bus } => {
            launcher::refuse_busy_bus(&bus, false)?;
            let files = drivelab_runtime::bus::leftovers(&bus);
            drivelab_runtime::bus::cleanup(&bus)?;
            if files.is_empty() {
                drivelab_services::outln!("bus {bus}: nothing to remove");
            } else {
                drivelab_services::outln!("bus {bus}: removed {} files and folders", files.len());
            }
            Ok(())
        }
        Cmd::BusConfig { bus } => {
            drivelab_services::out!("{}", drivelab_runtime::bus::config_toml(&bus)?);
            Ok(())
        }
        Cmd::Fault {
            kind,
            service,
            drive,
            duration_s,
        } => {
            let target = target(drive)?;
            // Bounded before anything is sent (`stop_s`), as in the monitor.
            if kind == "kill" {
                if let Some(d) = duration_s {
                    return Err(usage(format!(
                        "--duration-s {d}: only a stop has a duration; a kill lasts until the supervisor restarts the stage"
                    )));
                }
            }
            let duration_s = duration_s.unwrap_or(0.05);
            let kind = if kind == "kill" {
                drivelab_runtime::telemetry::FAULT_KILL
            } else {
                drivelab_runtime::telemetry::FAULT_STOP
            };
            let stop_ms = (duration_s * 1000.0).round() as u32;
            let done = drivelab_services::monitor::request_fault(&target, kind, &service, stop_ms)?;
            // The answer on stdout, for a script to read.
            drivelab_services::outln!("supervisor: {done}");
            Ok(())
        }
        Cmd::Hog {
            cpu,
            priority,
            duration_s,
            bus: _,
            armed,
        } => drivelab_services::faults::hog::run(cpu, priority, duration_s, armed),
        Cmd::BusInject { bus, kind, count } => {
            drivelab_services::faults::inject_bad_estimates(&bus, &kind, count)
        }
        Cmd::Export {
            run,
            mcap: _,
            force,
        } => {
            let f = drivelab_services::trace_mcap::export(&run, force)?;
            drivelab_services::outln!("{}", f.display());
            Ok(())
        }
        Cmd::Plot(args) => {
            for f in drivelab_services::plotcmd::run(&args)? {
                drivelab_services::outln!("{}", f.display());
            }
            Ok(())
        }
        Cmd::Campaign(args) => match drivelab_services::campaign::run(&args)? {
            0 => Ok(()),
            code => Err(Reported(code).into()),
        },
        Cmd::Compare(args) => drivelab_services::compare::run(&args),
        Cmd::Bench(args) => drivelab_services::bench::run(&args),
        Cmd::BenchNode {
            kind:
                BenchNodeKind::Uds {
                    role,
                    dir,
                    scenario,
                    seconds,
                    core,
                    priority,
                    out,
                },
        } => drivelab_bench::run_uds_node(&drivelab_bench::UdsNodeArgs {
            role,
            dir,
            scenario,
            seconds,
            core,
            priority,
            out,
        }),
        Cmd::BenchNode {
            kind:
                BenchNodeKind::Hop {
                    bus,
                    position,
                    hops,
                    measure,
                    period_ns,
                    core,
                    priority,
                    out,
                },
        } => drivelab_bench::hop::receive(
            &bus,
            position,
            hops,
            measure,
            period_ns,
            &drivelab_bench::NodeSpec { core, priority },
            &out,
        ),
        Cmd::ObserverError(args) => drivelab_services::observer_error::run(&args),
        Cmd::CdmDesign(args) => drivelab_services::cdm_design::run(&args),
        Cmd::Doctor {
            json,
            topology,
            machine,
        } => {
            let placement = topology
                .map(|t| {
                    let (f, _) = drivelab_runtime::topology::load(&t)
                        .map_err(|e| anyhow::anyhow!("--topology: {e}"))?;
                    drivelab_tools::doctor::Placement::new(&t, f.process, machine.as_deref())
                        .map_err(usage)
                })
                .transpose()?;
            let checks = drivelab_tools::doctor::run_checks_for(placement.as_ref());
            if json {
                drivelab_services::outln!("{}", serde_json::to_string_pretty(&checks)?);
            } else {
                drivelab_services::out!("{}", drivelab_tools::doctor::render_text(&checks));
            }
            Ok(())
        }
    }
}
