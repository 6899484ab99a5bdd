//! `drivelab bench`: the sample-time budget of the chain against the floor (a bare timer),
//! the same chain in one thread, the same four processes over Unix sockets, and the product
//! (iceoryx2), at several rates and placements, under identical conditions in one invocation.

use crate::launcher::{self, Clock, RunOptions};
use anyhow::{anyhow, Context, Result};
use drivelab_bench::{ChainSpec, NodeSpec, VariantResult};
use drivelab_runtime::config::{Placement, Scenario, ServicePlacement};
use drivelab_runtime::timing::{LatencyHist, Percentiles};
use serde::Serialize;
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
    /// Sample rates to measure, Hz (comma-separated).
    #[arg(long, value_delimiter = ',', default_values_t = vec![5000.0, 10000.0, 20000.0])]
    pub rates: Vec<f64>,
    /// Placements to measure (comma-separated): one-core, two-plus-two, alternating.
    #[arg(long, value_delimiter = ',', default_values_t = vec!["one-core".to_string(), "two-plus-two".to_string(), "alternating".to_string()])]
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
    /// (default 5; with --quick 1).
    #[arg(long, value_name = "N")]
    pub rounds: Option<usize>,
    /// Compare topologies instead of placements (comma-separated shipped names or files):
    /// the iceoryx2 chain in each topology, interleaved with the floor, e.g.
    /// `--topologies four-process,two-process,one-process --rates 10000`. Reports each
    /// topology's cycle latency, misses and the CPU time its processes used.
    #[arg(long, value_delimiter = ',', value_name = "NAME|FILE,...")]
    pub topologies: Vec<String>,
    /// Measure without a CPU wake-up latency request. By default the bench holds one of 0 µs
    /// (as cyclictest does, and as a real-time drive does) for every variant.
    #[arg(long)]
    pub no_cpu_latency_request: bool,
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
    /// floor, inprocess, uds, iceoryx2.
    pub variant: String,
    /// Placement name ("-" for the single-thread variants, which run on the plant's core).
    pub placement: String,
    /// Sample rate, Hz.
    pub rate_hz: f64,
    /// Samples measured.
    pub samples: u64,
    /// Cycle latency (floor: wake-up lateness), µs.
    pub cycle_us: Percentiles,
    /// Plant wake-up lateness, µs.
    pub lateness_us: Percentiles,
    /// Deadline misses (floor: wake-ups later than Ts).
    pub misses: u64,
    /// Longest run of consecutive misses.
    pub longest_miss_run: u64,
    /// Misses per million samples.
    pub misses_per_million: f64,
    /// Budget verdict (chains only): cycle p99.9 < Ts and misses/M ≤ 2 × floor/M + 10.
    pub holds_budget: Option<bool>,
    /// cycle p99 / floor p99.
    pub p99_ratio_to_floor: Option<f64>,
    /// cycle p99 − floor p99, µs.
    pub p99_minus_floor_us: Option<f64>,
    /// cycle p99 / Unix-socket chain p99 (same placement).
    pub p99_ratio_to_uds: Option<f64>,
    /// Histogram file (.hgrm) of the cycle latency.
    pub hgrm: String,
    /// CPU time (user + system) of the drive's processes per simulated second, s/s
    /// (iceoryx2 variants).
    pub cpu_s_per_s: Option<f64>,
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

struct Measured {
    result: VariantResult,
    curve_label: String,
}

fn row(variant: &str, placement: &str, hz: f64, m: &VariantResult, hgrm: &Path) -> Row {
    Row {
        variant: variant.into(),
        placement: placement.into(),
        rate_hz: hz,
        samples: m.samples,
        cycle_us: m.cycle.percentiles(),
        lateness_us: m.lateness.percentiles(),
        misses: m.misses.misses,
        longest_miss_run: m.misses.longest_run,
        misses_per_million: per_million(m.misses.misses, m.samples),
        holds_budget: None,
        p99_ratio_to_floor: None,
        p99_minus_floor_us: None,
        p99_ratio_to_uds: None,
        hgrm: hgrm
            .file_name()
            .unwrap_or_default()
            .to_string_lossy()
            .into_owned(),
        cpu_s_per_s: None,
    }
}

/// Runs the iceoryx2 chain through the real launcher (in `topology`, if given) and reads
/// its histograms and its processes' CPU time back.
fn run_iceoryx2(
    sc: &Scenario,
    out: &Path,
    bus: &str,
    topology: Option<&str>,
) -> Result<(VariantResult, f64)> {
    std::fs::create_dir_all(out)?;
    let file = out.join("scenario.in.toml");
    std::fs::write(&file, toml::to_string(sc)?)?;
    let o = RunOptions {
        scenario: file.display().to_string(),
        clock: Clock::Realtime,
        duration_s: None,
        out: Some(out.to_path_buf()),
        bus: Some(bus.into()),
        rt_strict: false,
        no_rt: false,
        no_plots: true,
        verbose: false,
        faults: Vec::new(),
        restart: launcher::Restart::Never,
        fault_seed: 0,
        topology: topology.map(String::from),
    };
    let r = launcher::run(&o)?;
    // CPU time: every stage's statistics carry its process's total; count each process once.
    let mut cpu = std::collections::BTreeMap::new();
    for e in std::fs::read_dir(out)?.flatten() {
        let p = e.path();
        if p.to_string_lossy().ends_with(".stats.json") {
            let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&p)?)?;
            if let (Some(pr), Some(c)) = (v["process"].as_str(), v["process_cpu_s"].as_f64()) {
                cpu.insert(pr.to_string(), c);
            }
        }
    }
    let cpu_s: f64 = cpu.values().sum();
    let cycle = LatencyHist::read_v2("cycle", &out.join("cycle.hdr"))?;
    let lateness = LatencyHist::read_v2("lateness", &out.join("plant.lateness.hdr"))?;
    let plant = &r.summary["counters"]["plant"];
    let mut misses = drivelab_runtime::timing::MissCounter::default();
    misses.misses = plant["deadline_misses"].as_u64().unwrap_or(0);
    misses.longest_run = plant["longest_miss_run"].as_u64().unwrap_or(0);
    Ok((
        VariantResult {
            cycle,
            lateness,
            samples: r.summary["samples"].as_u64().unwrap_or(0),
            misses,
        },
        cpu_s,
    ))
}

/// Runs the whole bench and writes bench.json, bench.md, .hgrm files and percentile plots.
pub fn run(a: &BenchArgs) -> Result<()> {
    let seconds = a.seconds.unwrap_or(if a.quick { 0.2 } else { 10.0 });
    if !(seconds.is_finite() && seconds > 0.0 && seconds <= 3600.0) {
        return Err(anyhow!("--seconds must be in (0, 3600], got {seconds}"));
    }
    let rates: Vec<f64> = if a.quick {
        vec![10_000.0]
    } else {
        a.rates.clone()
    };
    for &r in &rates {
        if !(r.is_finite() && (100.0..=100_000.0).contains(&r)) {
            return Err(anyhow!("--rates: {r} Hz must be in [100, 100000]"));
        }
    }
    let placements: Vec<String> = if a.quick {
        vec!["one-core".into()]
    } else {
        a.placements.clone()
    };
    for p in &placements {
        placement(p)?;
    }
    let out = a.out.clone().unwrap_or_else(|| {
        let secs = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_secs())
            .unwrap_or(0);
        PathBuf::from("runs").join(format!("bench-{secs}"))
    });
    std::fs::create_dir_all(&out).with_context(|| format!("cannot create {}", out.display()))?;
    let out = out.canonicalize()?;
    let exe = std::env::current_exe()?;
    let (base, _) = Scenario::load("kyslan-pi").map_err(|e| anyhow!(e))?;

    // Every variant runs under the same CPU wake-up latency request, the one a real-time drive
    // holds (the floor thus measures like cyclictest).
    let latency_request = if a.no_cpu_latency_request {
        None
    } else {
        match drivelab_runtime::rt::CpuLatencyRequest::hold(0) {
            Ok(r) => Some(r),
            Err(e) => {
                eprintln!(
                    "drivelab: warning: bench without a CPU wake-up latency request ({}: {e})",
                    drivelab_runtime::rt::CPU_DMA_LATENCY
                );
                None
            }
        }
    };
    let rounds = a.rounds.unwrap_or(if a.quick { 1 } else { 5 });
    if !(1..=100).contains(&rounds) {
        return Err(anyhow!("--rounds must be in 1..=100, got {rounds}"));
    }
    // The variants of every rate, each measured in `rounds` interleaved slices so that the
    // machine's slow changes (a VM's noisy minutes) reach all of them alike.
    let mut jobs: Vec<(&str, String)> = vec![("floor", "-".into())];
    let mut topo_paths: std::collections::BTreeMap<String, String> = Default::default();
    if a.topologies.is_empty() {
        jobs.push(("inprocess", "-".into()));
        for p in &placements {
            jobs.push(("uds", p.clone()));
            jobs.push(("iceoryx2", p.clone()));
            if a.spin_us > 0.0 && p == "one-core" {
                jobs.push(("iceoryx2+spin", p.clone()));
            }
        }
    } else {
        for t in &a.topologies {
            drivelab_runtime::topology::load(t).map_err(|e| anyhow!("--topologies: {e}"))?;
            // Shown (and filed) by its name: a file's stem.
            let name = Path::new(t.as_str())
                .file_stem()
                .map_or(t.clone(), |s| s.to_string_lossy().into_owned());
            if topo_paths.insert(name.clone(), t.clone()).is_some() {
                return Err(anyhow!("--topologies: '{name}' is listed twice"));
            }
            jobs.push(("topology", name));
        }
    }
    let total = rates.len() * jobs.len() * rounds + 2;
    let bar = indicatif::ProgressBar::new(total as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let mut rows: Vec<Row> = Vec::new();
    let mut curves_by_rate: Vec<(f64, Vec<drivelab_tools::plot::PercentileSeries>)> = Vec::new();
    for &hz in &rates {
        let mut measured: Vec<(Row, Measured)> = Vec::new();
        let one = placement("one-core")?;
        let tag = |v: &str, p: &str| format!("{v}-{p}-{}hz", hz as u64);
        let slice = seconds / rounds as f64;
        let mut acc: Vec<Option<VariantResult>> = jobs.iter().map(|_| None).collect();
        let mut cpu: Vec<f64> = vec![0.0; jobs.len()];
        for round in 0..rounds {
            for (i, (name, p)) in jobs.iter().enumerate() {
                let round_tag = if rounds > 1 {
                    format!(", round {}/{rounds}", round + 1)
                } else {
                    String::new()
                };
                bar.set_message(format!("{hz} Hz {name} {p}{round_tag}"));
                let dir = |v: &str| {
                    let d = out.join(tag(v, p));
                    if rounds > 1 {
                        d.join(format!("round{}", round + 1))
                    } else {
                        d
                    }
                };
                let m = match *name {
                    // The floor and the in-process chain run on the plant's core at its priority.
                    "floor" => drivelab_bench::run_floor(hz, slice, &node(one.plant))?,
                    "inprocess" => drivelab_bench::run_inprocess(&ChainSpec {
                        scenario: scenario_at(&base, hz, slice, one)?,
                        seconds: slice,
                        plant: node(one.plant),
                        observer: node(one.observer),
                        current_loop: node(one.current_loop),
                        speed_loop: node(one.speed_loop),
                    })?,
                    "uds" => {
                        let pl = placement(p)?;
                        let work = dir("uds");
                        std::fs::create_dir_all(&work)?;
                        drivelab_bench::run_uds_chain(
                            &ChainSpec {
                                scenario: scenario_at(&base, hz, slice, pl)?,
                                seconds: slice,
                                plant: node(pl.plant),
                                observer: node(pl.observer),
                                current_loop: node(pl.current_loop),
                                speed_loop: node(pl.speed_loop),
                            },
                            &exe,
                            &work,
                        )?
                    }
                    "iceoryx2" => {
                        let sc = scenario_at(&base, hz, slice, placement(p)?)?;
                        let bus = format!("b{}r{}j{i}", std::process::id(), round);
                        let (m, c) = run_iceoryx2(&sc, &dir("iceoryx2"), &bus, None)?;
                        cpu[i] += c;
                        m
                    }
                    "topology" => {
                        let sc = scenario_at(&base, hz, slice, one)?;
                        let bus = format!("b{}r{}j{i}t", std::process::id(), round);
                        let t = topo_paths.get(p).map(String::as_str);
                        let (m, c) = run_iceoryx2(&sc, &dir("topology"), &bus, t)?;
                        cpu[i] += c;
                        m
                    }
                    _ => {
                        // The same chain with the plant sleeping to spin_us before each
                        // deadline and spinning the rest (docs/architecture.md,
                        // "Real-time rules": sleep-then-short-spin).
                        let mut sc = scenario_at(&base, hz, slice, placement(p)?)?;
                        sc.timing.plant_spin_us = spin_us(a.spin_us, hz);
                        sc.validate().map_err(|e| anyhow!("--spin-us: {e}"))?;
                        let bus = format!("b{}r{}j{i}s", std::process::id(), round);
                        let (m, c) = run_iceoryx2(&sc, &dir("iceoryx2-spin"), &bus, None)?;
                        cpu[i] += c;
                        m
                    }
                };
                match &mut acc[i] {
                    Some(total) => total.merge(&m)?,
                    slot => *slot = Some(m),
                }
                bar.inc(1);
            }
        }
        for (((name, p), m), cpu_s) in jobs.iter().zip(acc).zip(cpu) {
            let m = m.ok_or_else(|| anyhow!("{name} {p}: no measurement"))?;
            let file_tag = if *name == "floor" || *name == "inprocess" {
                tag(name, "core1")
            } else {
                tag(name, p)
            };
            let h = out.join(format!("{file_tag}.hgrm"));
            std::fs::write(&h, m.cycle.hgrm())?;
            let mut r = row(name, p, hz, &m, &h);
            if cpu_s > 0.0 {
                // Per simulated second: the rounds add up to `seconds` of drive.
                r.cpu_s_per_s = Some(cpu_s / seconds);
            }
            measured.push((
                r,
                Measured {
                    result: m,
                    curve_label: if p == "-" {
                        name.to_string()
                    } else {
                        format!("{name} {p}")
                    },
                },
            ));
        }
        // Verdicts and ratios against the floor and the Unix-socket chain of the same run.
        let floor_row = measured[0].0.clone();
        let floor_late_pm = floor_row.misses_per_million;
        let ts_us = 1e6 / hz;
        let uds_p99: Vec<(String, f64)> = measured
            .iter()
            .filter(|(r, _)| r.variant == "uds")
            .map(|(r, _)| (r.placement.clone(), r.cycle_us.p99))
            .collect();
        for (r, _) in measured.iter_mut() {
            if r.variant == "floor" {
                continue;
            }
            r.holds_budget =
                Some(r.cycle_us.p999 < ts_us && r.misses_per_million <= 2.0 * floor_late_pm + 10.0);
            r.p99_ratio_to_floor = Some(r.cycle_us.p99 / floor_row.cycle_us.p99.max(1e-3));
            r.p99_minus_floor_us = Some(r.cycle_us.p99 - floor_row.cycle_us.p99);
            if r.variant.starts_with("iceoryx2") {
                r.p99_ratio_to_uds = uds_p99
                    .iter()
                    .find(|(p, _)| *p == r.placement)
                    .map(|(_, u)| r.cycle_us.p99 / u.max(1e-3));
            }
        }
        let curves = measured
            .iter()
            .map(|(_, m)| (m.curve_label.clone(), m.result.cycle.curve()))
            .collect();
        curves_by_rate.push((hz, curves));
        rows.extend(measured.into_iter().map(|(r, _)| r));
    }
    // Simulation speed: lockstep (four processes) and in-process, kyslan-pi.
    bar.set_message("lockstep speed");
    let sim_s = if a.quick { 0.2 } else { 2.0 };
    let ls_out = out.join("lockstep-speed");
    let ls = launcher::run(&RunOptions {
        scenario: "kyslan-pi".into(),
        clock: Clock::Lockstep,
        duration_s: Some(sim_s),
        out: Some(ls_out),
        bus: Some(format!("b{}ls", std::process::id())),
        rt_strict: false,
        no_rt: false,
        no_plots: true,
        verbose: false,
        faults: Vec::new(),
        restart: launcher::Restart::Never,
        fault_seed: 0,
        topology: None,
    })?;
    bar.inc(1);
    bar.set_message("in-process speed");
    let mut ip_sc = base.clone();
    ip_sc.duration_s = if a.quick { 1.0 } else { 20.0 };
    // Time the cycles only (the controller design at construction is set-up, not simulation).
    let mut drive = drivelab_runtime::drive::InProcessDrive::new(&ip_sc);
    let n = ip_sc.samples();
    let mut rows_ip = Vec::with_capacity(n as usize);
    let t = Instant::now();
    for k in 0..n {
        rows_ip.push(drive.cycle(k));
    }
    let ip_speed = ip_sc.duration_s / t.elapsed().as_secs_f64();
    std::hint::black_box(rows_ip.len());
    bar.inc(1);
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
    let report = serde_json::json!({
        "seconds_per_variant": seconds,
        "rounds": rounds,
        "quick": a.quick,
        "cpu_latency_request_us": latency_request.as_ref().map(|r| r.value_us),
        "machine": { "cpus": drivelab_runtime::rt::online_cpus(), "doctor": doctor },
        "rows": rows,
        "speed": speed,
    });
    std::fs::write(out.join("bench.json"), serde_json::to_vec_pretty(&report)?)?;
    let md = markdown(&rows, &speed, seconds, rounds, a.spin_us);
    std::fs::write(out.join("bench.md"), &md)?;
    for (hz, curves) in &curves_by_rate {
        let ts_us = 1e6 / hz;
        drivelab_tools::plot::plot_percentiles(
            curves,
            &format!(
                "cycle latency at {} kHz (floor: timer wake-up lateness)",
                hz / 1000.0
            ),
            Some((ts_us, format!("T_s = {ts_us:.0} µs"))),
            true,
            &out.join(format!("percentiles-{}hz", *hz as u64)),
        )?;
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{md}");
        println!("\nwritten: {}", out.display());
    }
    Ok(())
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

/// The Markdown table of the report.
pub fn markdown(
    rows: &[Row],
    speed: &serde_json::Value,
    seconds: f64,
    rounds: usize,
    spin_arg: f64,
) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "Cycle latency from t_k to command k available at the plant, µs ({seconds} s per variant in {rounds} interleaved round(s); floor = bare timer wake-up lateness).\n");
    let _ = writeln!(s, "| rate | variant | placement | p50 | p99 | p99.9 | max | misses/M | longest run | p99 − floor | p99 / floor | p99 / uds | CPU s/s | budget |");
    let _ = writeln!(
        s,
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for r in rows {
        let verdict = match r.holds_budget {
            Some(true) => "HOLDS",
            Some(false) => "MISSED",
            None => "-",
        };
        let _ = writeln!(
            s,
            "| {} kHz | {} | {} | {:.1} | {:.1} | {:.1} | {:.0} | {:.0} | {} | {} | {} | {} | {} | {} |",
            r.rate_hz / 1000.0,
            r.variant,
            r.placement,
            r.cycle_us.p50,
            r.cycle_us.p99,
            r.cycle_us.p999,
            r.cycle_us.max,
            r.misses_per_million,
            r.longest_miss_run,
            fmt_opt(r.p99_minus_floor_us, 1),
            fmt_opt(r.p99_ratio_to_floor, 2),
            fmt_opt(r.p99_ratio_to_uds, 2),
            fmt_opt(r.cpu_s_per_s, 3),
            verdict
        );
    }
    if rows.iter().any(|r| r.variant == "iceoryx2+spin") {
        let spins: Vec<String> = rows
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
            spins.join(", ")
        );
    }
    let _ = writeln!(
        s,
        "\nSimulation speed (kyslan-pi): lockstep (4 processes) {:.1}× real time, in-process {:.0}× real time.",
        speed["lockstep_simulated_s_per_wall_s"].as_f64().unwrap_or(f64::NAN),
        speed["inprocess_simulated_s_per_wall_s"].as_f64().unwrap_or(f64::NAN)
    );
    s
}
