//! `drivelab`: the launcher and supervisor CLI.

use clap::{Parser, Subcommand};
use drivelab_services::launcher::{self, Clock, RunOptions};
use std::path::PathBuf;
use std::process::ExitCode;

/// drivelab: a four-process real-time PMSM drive on iceoryx2 shared memory.
///
/// Exit codes: 0 success, 1 error (bad input, a service failed, interrupted), 2 usage error.
#[derive(Debug, Parser)]
#[command(name = "drivelab", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Debug, Subcommand)]
enum Cmd {
    /// Run a scenario: start plant, observer, current-loop and speed-loop, record every
    /// sample, stop them and write trace.csv, summary.json and plots into the run folder.
    ///
    /// Examples:
    ///   drivelab run                                  # kyslan-pi, realtime, 10 kHz
    ///   drivelab run --clock lockstep --out runs/ls   # reproducible, as fast as possible
    ///   drivelab run --scenario my.toml --duration 2
    #[command(verbatim_doc_comment)]
    Run {
        /// Scenario name (see `drivelab scenarios`) or path to a TOML file.
        #[arg(long, default_value = "kyslan-pi")]
        scenario: String,
        /// Pacing: realtime (wall clock, deadlines), lockstep (wait for each command) or
        /// inprocess (one thread, no bus).
        #[arg(long, value_enum, default_value_t = Clock::Realtime)]
        clock: Clock,
        /// Override the scenario's duration, seconds.
        #[arg(long, value_name = "SECONDS")]
        duration: Option<f64>,
        /// Run folder (default: runs/<scenario>-<clock>-<unix time>).
        #[arg(long, value_name = "DIR")]
        out: Option<PathBuf>,
        /// Bus id isolating this drive's shared memory (default: the launcher's pid).
        #[arg(long)]
        bus: Option<String>,
        /// Fail when a core, SCHED_FIFO priority or mlock is refused (default: warn and run).
        #[arg(long)]
        rt_strict: bool,
        /// Do not pin, raise priority or lock memory.
        #[arg(long)]
        no_rt: bool,
        /// Do not draw PNG/SVG plots.
        #[arg(long)]
        no_plots: bool,
        /// Print the summary as JSON on stdout instead of the human summary.
        #[arg(long)]
        json: bool,
    },
    /// Run the plant model alone, open loop, from rest, on recorded voltages.
    ///
    /// IN.csv has columns t,u_d,u_q,t_load (s, V, V, N·m), each row held from its t on.
    /// OUT.csv gets t,u_d,u_q,t_load,i_d,i_q,omega_m,theta_e at the input rows' times.
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
        #[arg(long, default_value_t = 1e-5, value_name = "SECONDS")]
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
    /// Example:
    ///   drivelab design --scenario kyslan-pi
    #[command(verbatim_doc_comment)]
    Design {
        /// Scenario name or file.
        #[arg(long, default_value = "kyslan-pi")]
        scenario: String,
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
    /// Internal: one node of the Unix-socket chain (started by `drivelab bench`).
    #[command(hide = true)]
    BenchNode {
        #[command(subcommand)]
        kind: BenchNodeKind,
    },
    /// Report how ready this machine is for real-time work. Reads only; changes nothing.
    ///
    /// Example:
    ///   drivelab doctor
    #[command(verbatim_doc_comment)]
    Doctor {
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
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
        /// Result file (plant).
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match real_main(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("drivelab: error: {e:#}");
            ExitCode::from(1)
        }
    }
}

fn fmt_opt(v: &serde_json::Value, unit: &str) -> String {
    v.as_f64()
        .map(|x| format!("{x:.3} {unit}"))
        .unwrap_or_else(|| "n/a".into())
}

fn real_main(cli: Cli) -> anyhow::Result<()> {
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
            json,
        } => {
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
            };
            let r = launcher::run(&o)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&r.summary)?);
            } else {
                let s = &r.summary;
                let m = &s["metrics"];
                println!("run folder: {}", r.out.display());
                println!(
                    "{} samples ({} expected), deadline misses {}, wall {:.2} s ({:.1}× real time)",
                    s["samples"],
                    s["samples_expected"],
                    s["deadline_misses"],
                    s["wall_time_s"].as_f64().unwrap_or(0.0),
                    s["simulated_s_per_wall_s"].as_f64().unwrap_or(0.0)
                );
                println!(
                    "rise {}, overshoot {}, load dip {}, load recovery {}, steady-state error {}",
                    fmt_opt(&m["rise_time_ms"], "ms"),
                    fmt_opt(&m["overshoot_pct"], "%"),
                    fmt_opt(&m["load_dip_rad_s"], "rad/s"),
                    fmt_opt(&m["load_recovery_ms"], "ms"),
                    fmt_opt(&m["steady_state_error"], "rad/s")
                );
                if let Some(g) = s["missing_samples"].as_array().filter(|g| !g.is_empty()) {
                    println!("missing samples: {}", serde_json::to_string(g)?);
                }
            }
            Ok(())
        }
        Cmd::Plant {
            replay,
            out,
            motor,
            max_step,
        } => {
            if !(max_step.is_finite() && max_step > 0.0) {
                anyhow::bail!("--max-step must be a positive number of seconds, got {max_step}");
            }
            let m = drivelab_services::replay::resolve_motor(&motor)?;
            let n = drivelab_services::replay::replay(&replay, &out, &m, max_step)?;
            eprintln!("wrote {n} rows to {}", out.display());
            Ok(())
        }
        Cmd::Scenarios => {
            let list = drivelab::config::list_scenarios();
            if list.is_empty() {
                anyhow::bail!(
                    "no scenarios found in {}",
                    drivelab::config::scenarios_dir().display()
                );
            }
            println!("{:<24} {:<40} purpose", "name", "reproduces");
            for (name, path) in list {
                let text = std::fs::read_to_string(&path)?;
                match drivelab::config::Scenario::from_toml(&text, &path.display().to_string()) {
                    Ok(s) => println!("{:<24} {:<40} {}", name, s.reproduces, s.purpose),
                    Err(e) => println!("{name:<24} INVALID: {e}"),
                }
            }
            Ok(())
        }
        Cmd::Design { scenario } => {
            let sc = launcher::load_scenario(&scenario, None)?;
            print!("{}", drivelab_services::design::render(&sc));
            Ok(())
        }
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
        Cmd::Doctor { json } => {
            let checks = drivelab::doctor::run_checks();
            if json {
                println!("{}", serde_json::to_string_pretty(&checks)?);
            } else {
                print!("{}", drivelab::doctor::render_text(&checks));
            }
            Ok(())
        }
    }
}
