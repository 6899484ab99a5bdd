//! Fault injection: parsing of `--fault` specs, the seeded random plan, and signals.

use anyhow::{anyhow, bail, Result};
use drivelab_runtime::config::{Scenario, SERVICES};
use serde::Serialize;

pub mod hog;
pub mod sensor;
pub mod window;

/// One injected fault.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Fault {
    /// `kill` (SIGKILL) or `stop` (SIGSTOP, then SIGCONT after `duration_s`).
    pub kind: FaultKind,
    /// Target stage (the process that hosts it is signalled).
    pub service: String,
    /// When, seconds after sample 0.
    pub at_s: f64,
    /// For `stop`: how long the process stays stopped, s.
    pub duration_s: f64,
}

impl Fault {
    /// The fault as `--fault` gives it.
    pub fn spec(&self) -> String {
        match self.kind {
            FaultKind::Kill => format!("kill:{}@{}", self.service, self.at_s),
            FaultKind::Stop => format!("stop:{}@{}:{}", self.service, self.at_s, self.duration_s),
        }
    }
}

/// Kinds of fault.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum FaultKind {
    /// SIGKILL.
    Kill,
    /// SIGSTOP then SIGCONT.
    Stop,
}

/// A stage name as the target of fault `spec`: checked for its form here, against the run's
/// topology by [`plan`].
pub(crate) fn service(name: &str, spec: &str) -> Result<String> {
    if name.is_empty()
        || !name
            .chars()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-')
    {
        bail!(
            "fault '{spec}': unknown stage '{name}' (built-in: {})",
            SERVICES.join(", ")
        );
    }
    Ok(name.to_string())
}

pub(crate) fn seconds(v: &str, what: &str, spec: &str) -> Result<f64> {
    // One unit at most: `0.5s`, not `0.5sss`.
    let x: f64 = v
        .strip_suffix('s')
        .unwrap_or(v)
        .parse()
        .map_err(|_| anyhow!("fault '{spec}': {what} '{v}' is not a number of seconds"))?;
    if !(x.is_finite() && x >= 0.0) {
        bail!("fault '{spec}': {what} must be a finite number of seconds >= 0");
    }
    Ok(x)
}

/// Shortest stop, s.
pub const STOP_MIN_S: f64 = 0.001;
/// Longest stop, s.
pub const STOP_MAX_S: f64 = 60.0;

/// The command line's `--fault` specs against the limits of one run: at most
/// [`MAX_INJECT`](drivelab_runtime::inject::MAX_INJECT) bus faults (drop, corrupt, delay)
/// and
/// [`MAX_SENSOR_FAULTS`](drivelab_runtime::sensor_faults::MAX_SENSOR_FAULTS) sensor faults. Too
/// many is a command line wrong in itself; with a scenario's own tables the run checks the
/// sum again.
pub fn check_counts(specs: &[FaultSpec]) -> Result<(), String> {
    use drivelab_runtime::{inject::MAX_INJECT, sensor_faults::MAX_SENSOR_FAULTS};
    let bus = specs
        .iter()
        .filter(|s| matches!(s, FaultSpec::Bus(_)))
        .count();
    let sensor = specs
        .iter()
        .filter(|s| matches!(s, FaultSpec::Sensor(_)))
        .count();
    if bus > MAX_INJECT {
        return Err(format!(
            "--fault: {bus} bus faults (drop, corrupt, delay): at most {MAX_INJECT} in one run"
        ));
    }
    if sensor > MAX_SENSOR_FAULTS {
        return Err(format!(
            "--fault: {sensor} sensor faults: at most {MAX_SENSOR_FAULTS} in one run"
        ));
    }
    Ok(())
}

/// Parses one `--fault` value: `kill:STAGE@SECONDS`, `stop:STAGE@SECONDS:DURATION`,
/// `random:N` (expanded later with the run's seed and duration), a bus fault (`delay:…`,
/// `drop:…`, `corrupt:…`, see [`crate::bus_faults`]), `hog:CPU@S:DUR:PRIO` ([`hog`]),
/// `encoder-stuck@S:DUR` or `current-offset:PHASE@S:AMPS` ([`sensor`]).
pub fn parse(spec: &str) -> Result<FaultSpec> {
    let kind = spec.split([':', '@']).next().unwrap_or_default();
    let rest = spec.split_once(':').map_or("", |(_, r)| r);
    match kind {
        "hog" => hog::parse(spec).map(FaultSpec::Hog),
        "encoder-stuck" | "current-offset" => sensor::parse(spec).map(FaultSpec::Sensor),
        "random" => {
            match rest.parse::<u32>() {
                Ok(n @ 1..=10_000) => Ok(FaultSpec::Random(n)),
                _ => bail!("fault '{spec}': N must be a whole number in 1..=10000"),
            }
        }
        "kill" | "stop" => {
            let (svc, when) = rest.split_once('@').ok_or_else(|| {
                anyhow!(
                    "fault '{spec}': expected {kind}:STAGE@SECONDS{}",
                    if kind == "stop" { ":DURATION" } else { "" }
                )
            })?;
            let service = service(svc, spec)?;
            if kind == "kill" {
                Ok(FaultSpec::One(Fault {
                    kind: FaultKind::Kill,
                    service,
                    at_s: seconds(when, "time", spec)?,
                    duration_s: 0.0,
                }))
            } else {
                let (at, dur) = when.split_once(':').ok_or_else(|| {
                    anyhow!("fault '{spec}': expected stop:STAGE@SECONDS:DURATION")
                })?;
                let duration_s = seconds(dur, "duration", spec)?;
                // The same bounds as `drivelab fault stop` and the monitor: a frozen stage
                // for longer is a dead one (use kill).
                if !(STOP_MIN_S..=STOP_MAX_S).contains(&duration_s) {
                    bail!("fault '{spec}': a stop lasts {STOP_MIN_S} to {STOP_MAX_S} s");
                }
                Ok(FaultSpec::One(Fault {
                    kind: FaultKind::Stop,
                    service,
                    at_s: seconds(at, "time", spec)?,
                    duration_s,
                }))
            }
        }
        "delay" | "drop" | "corrupt" => crate::bus_faults::parse(kind, rest, spec),
        other => bail!(
            "fault '{spec}': unknown fault kind '{other}' (kill, stop, random, delay, drop, corrupt, hog, encoder-stuck, current-offset)"
        ),
    }
}

/// A parsed `--fault`.
#[derive(Debug, Clone, PartialEq)]
pub enum FaultSpec {
    /// A single fault.
    One(Fault),
    /// N kills of random services at random instants.
    Random(u32),
    /// A bus fault, injected by the stage hosts by sample index (not part of the plan).
    Bus(drivelab_runtime::inject::Inject),
    /// A competing SCHED_FIFO busy loop, started by the supervisor ([`hog`]).
    Hog(hog::Hog),
    /// A sensor fault, applied by the plant from the resolved scenario ([`sensor`]).
    Sensor(drivelab_runtime::sensor_faults::SensorFault),
}

/// Expands the specs into a time-ordered plan against the run's `stages` at `sample_hz`.
/// Random kills of one of `stages` are spread over [10 %, 90 %] of the run with a seeded
/// generator, at least `min_gap_s` apart so that each fault's recovery can be measured.
pub fn plan(
    specs: &[FaultSpec],
    duration_s: f64,
    sample_hz: f64,
    seed: u64,
    min_gap_s: f64,
    stages: &[String],
) -> Result<Vec<Fault>> {
    use rand::{RngExt, SeedableRng};
    let mut out = Vec::new();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    for s in specs {
        match s {
            FaultSpec::One(f) => {
                if !stages.contains(&f.service) {
                    bail!(
                        "fault '{}': unknown stage '{}' (this drive's stages: {})",
                        f.spec(),
                        f.service,
                        stages.join(", ")
                    );
                }
                if f.at_s >= duration_s {
                    bail!(
                        "fault '{}' is at or after the end of the run ({duration_s} s)",
                        f.spec()
                    );
                }
                after_sample_0(&format!("fault '{}'", f.spec()), f.at_s, sample_hz)?;
                out.push(f.clone());
            }
            // Not signals: the launcher plans them (`hog::plan`, `sensor::add_to_scenario`).
            FaultSpec::Hog(_) | FaultSpec::Sensor(_) => {}
            FaultSpec::Random(n) => {
                let span = 0.8 * duration_s;
                let slot = span / f64::from(*n);
                if slot < min_gap_s {
                    bail!(
                        "random:{n} needs at least {:.2} s of run ({min_gap_s} s per fault, spread over 80 % of the run); the run is {duration_s} s (give a longer --duration, or duration_s in a campaign)",
                        f64::from(*n) * min_gap_s / 0.8
                    );
                }
                for i in 0..*n {
                    // One fault per slot, at a random instant in the slot's first half.
                    let at = 0.1 * duration_s + slot * (f64::from(i) + 0.5 * rng.random::<f64>());
                    let service = stages[rng.random_range(0..stages.len())].clone();
                    out.push(Fault {
                        kind: FaultKind::Kill,
                        service,
                        at_s: at,
                        duration_s: 0.0,
                    });
                }
            }
            // Carried in the scenario instead (`crate::bus_faults::schedule`).
            FaultSpec::Bus(_) => {}
        }
    }
    out.sort_by(|a, b| a.at_s.total_cmp(&b.at_s));
    Ok(out)
}

/// A kill or stop (`what`, as the error names it) at `at_s` s lands on sample round(t·f_s), as
/// `[[inject]]` does: on sample 0 it would hit a drive that has no sample yet to resume from
/// or to hold, and is refused.
pub fn after_sample_0(what: &str, at_s: f64, sample_hz: f64) -> Result<()> {
    if (at_s * sample_hz).round() < 1.0 {
        bail!(
            "{what} falls on sample 0: a kill or stop must come after the drive's first sample (at or after {} s at {sample_hz} Hz)",
            1.0 / sample_hz
        );
    }
    Ok(())
}

/// How long the stops among `specs` hold their processes in total, s: a stopped plant
/// stops the drive's clock, so a real-time run lasts that much longer.
pub fn stopped_s(specs: &[FaultSpec]) -> f64 {
    specs
        .iter()
        .map(|s| match s {
            FaultSpec::One(f) if f.kind == FaultKind::Stop => f.duration_s,
            _ => 0.0,
        })
        .sum()
}

/// Lockstep and in process (docs/architecture.md, "Fault model"): the kills and stops of
/// `plan` become `[[inject]]` entries of `sc`, simulated by the stage hosts at their sample;
/// a kill's outputs are absent for `restart_ms`, the simulated restart, or (None: the
/// supervisor restarts nothing, `--restart never`) to the end of the run.
pub fn schedule_simulated(
    plan: &[Fault],
    restart_ms: Option<f64>,
    sc: &mut Scenario,
) -> Result<()> {
    use drivelab_runtime::inject::{Inject, InjectKind};
    for f in plan {
        sc.inject.push(Inject {
            kind: match f.kind {
                FaultKind::Kill => InjectKind::Kill,
                FaultKind::Stop => InjectKind::Stop,
            },
            target: f.service.clone(),
            at_s: f.at_s,
            duration_s: match (f.kind, restart_ms) {
                (FaultKind::Kill, Some(ms)) => ms * 1e-3,
                // The stage never comes back.
                (FaultKind::Kill, None) => 0.0,
                (FaultKind::Stop, _) => f.duration_s,
            },
            latency_us: 0.0,
            count: 0,
        });
    }
    Ok(())
}

/// Refuses `[[inject]]` kills and stops (a scenario may carry its own) in real time, where
/// the supervisor signals processes instead.
pub fn check_simulated(inject: &[drivelab_runtime::inject::Inject], simulated: bool) -> Result<()> {
    for i in inject.iter().filter(|i| i.kind.downs_stage()) {
        if !simulated {
            bail!(
                "[[inject]] {}: kill and stop tables are simulated in --clock lockstep and inprocess only (in real time use --fault)",
                i.spec()
            );
        }
    }
    Ok(())
}

/// `--lockstep-restart-ms`: a number of milliseconds within the bounds of a simulated
/// restart, or a one-line error.
pub fn restart_ms(v: &str) -> std::result::Result<f64, String> {
    use drivelab_runtime::inject::{RESTART_MAX_S, RESTART_MIN_S};
    let x: f64 = v
        .trim_end_matches("ms")
        .parse()
        .map_err(|_| format!("'{v}' is not a number of milliseconds"))?;
    if !(RESTART_MIN_S * 1e3..=RESTART_MAX_S * 1e3).contains(&x) {
        return Err(format!(
            "the simulated restart lasts {} to {} ms",
            RESTART_MIN_S * 1e3,
            RESTART_MAX_S * 1e3
        ));
    }
    Ok(x)
}

/// `kill` or `stop`.
pub fn kind_name(k: FaultKind) -> &'static str {
    match k {
        FaultKind::Kill => "kill",
        FaultKind::Stop => "stop",
    }
}

/// Sends `sig` to `pid`.
pub fn signal(pid: u32, sig: libc::c_int) -> Result<()> {
    // SAFETY: kill(2) with a pid and a signal number; no memory is involved.
    let rc = unsafe { libc::kill(pid as libc::pid_t, sig) };
    if rc != 0 {
        bail!(
            "cannot signal pid {pid}: {}",
            std::io::Error::last_os_error()
        );
    }
    Ok(())
}

/// Processes (other than this one) whose command line has `--bus ID`, as (pid, argv).
fn processes_with_bus(bus: &str) -> Vec<(u32, Vec<String>)> {
    let me = std::process::id();
    let mut v = Vec::new();
    for e in std::fs::read_dir("/proc").into_iter().flatten().flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<u32>() else {
            continue;
        };
        let Ok(cmd) = std::fs::read(e.path().join("cmdline")) else {
            continue;
        };
        let args: Vec<String> = cmd
            .split(|b| *b == 0)
            .map(|s| String::from_utf8_lossy(s).into_owned())
            .collect();
        if pid != me && args.windows(2).any(|w| w[0] == "--bus" && w[1] == bus) {
            v.push((pid, args));
        }
    }
    v
}

/// Every process using bus `bus` (launcher, services, monitors), as (pid, program and first
/// argument); this process excluded.
pub fn bus_users(bus: &str) -> Vec<(u32, String)> {
    processes_with_bus(bus)
        .into_iter()
        .map(|(pid, args)| (pid, args[..args.len().min(2)].join(" ")))
        .collect()
}

/// Stage hosts of a running drive: (stage, process, pid) for every stage each hosts, found
/// by their `--bus ID`, `--process NAME` and `--hosts STAGES` arguments.
pub fn find_services(bus: &str) -> Vec<(String, String, u32)> {
    let arg = |args: &[String], name: &str| -> Option<String> {
        args.windows(2).find(|w| w[0] == name).map(|w| w[1].clone())
    };
    processes_with_bus(bus)
        .into_iter()
        .filter_map(|(pid, args)| {
            let process = arg(&args, "--process")?;
            let hosts = arg(&args, "--hosts")?;
            Some(
                hosts
                    .split(',')
                    .map(|s| (s.to_string(), process.clone(), pid))
                    .collect::<Vec<_>>(),
            )
        })
        .flatten()
        .collect()
}

/// The estimate topic's word in the bus's wake segment (as `DriveTopics::open_with` numbers
/// the topics).
const EST_WAKE_WORD: usize = 1;

/// Tries to publish `count` malformed estimates onto a running drive's estimate topic, as a
/// foreign process on the same account would: `nan` puts NaN in the speed, `backwards` uses
/// sample index 0 (behind the drive). Every drive topic takes one publisher, its stage, so
/// this fails with the bus's one-line refusal while the drive runs. For the tests of that
/// refusal.
pub fn inject_bad_estimates(bus: &str, kind: &str, count: u32) -> Result<()> {
    use drivelab_runtime::messages::{Estimate, Header};
    drivelab_runtime::bus::check_bus_id(bus)?;
    let bad = |i: u32| -> Result<Estimate> {
        Ok(match kind {
            "nan" => Estimate {
                hdr: Header {
                    k: u64::MAX / 2 + u64::from(i),
                    ..Default::default()
                },
                theta_e: 0.0,
                omega_m: f64::NAN,
            },
            "backwards" => Estimate {
                hdr: Header {
                    k: 0,
                    ..Default::default()
                },
                theta_e: 0.0,
                omega_m: 0.0,
            },
            other => bail!("unknown bad-input kind '{other}' (nan, backwards)"),
        })
    };
    bad(0)?;
    if find_services(bus).is_empty() {
        bail!("no drive is running on bus {bus}");
    }
    let node = drivelab_runtime::bus::node(bus, "injector")?;
    // The estimate topic alone, which the drive has created. Opening every drive topic
    // would create those this drive does not use (an outer loop's speed references), to be
    // removed again as this process ends: a second injector opening them meanwhile found
    // one half gone (iceoryx2's HangsInCreation).
    let wake = std::sync::Arc::new(drivelab_runtime::futex::WakeSegment::open(bus)?);
    let est = drivelab_runtime::bus::Topic::<Estimate>::open_with(
        &node,
        drivelab_runtime::bus::TOPIC_EST,
        Some((wake, EST_WAKE_WORD)),
    )?;
    let tx = est.sender()?;
    tx.connect()?;
    for i in 0..count {
        tx.send(bad(i)?)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn too_many_faults_of_a_kind_on_one_command_line_are_refused() {
        use drivelab_runtime::{inject::MAX_INJECT, sensor_faults::MAX_SENSOR_FAULTS};
        let bus = parse("drop:cmd@0.01:1").unwrap();
        let sensor = parse("encoder-stuck@0.01:0.001").unwrap();
        assert_eq!(check_counts(&vec![bus.clone(); MAX_INJECT]), Ok(()));
        assert_eq!(
            check_counts(&vec![bus; MAX_INJECT + 1]),
            Err("--fault: 17 bus faults (drop, corrupt, delay): at most 16 in one run".into())
        );
        assert_eq!(
            check_counts(&vec![sensor.clone(); MAX_SENSOR_FAULTS]),
            Ok(())
        );
        assert_eq!(
            check_counts(&vec![sensor; MAX_SENSOR_FAULTS + 1]),
            Err("--fault: 65 sensor faults: at most 64 in one run".into())
        );
        // Kills and stops are not counted against either limit.
        assert_eq!(
            check_counts(&vec![parse("kill:plant@0.5").unwrap(); 100]),
            Ok(())
        );
    }

    #[test]
    fn a_fault_without_a_stage_names_its_spec() {
        for spec in ["kill:@0.01", "stop:@0.01:0.02", "delay:@0.1:0.1:10us"] {
            let e = format!("{:#}", parse(spec).unwrap_err());
            assert!(
                e.starts_with(&format!("fault '{spec}': unknown stage ''")),
                "{e}"
            );
        }
    }

    #[test]
    fn parses_the_three_forms() {
        assert_eq!(
            parse("kill:plant@0.5").unwrap(),
            FaultSpec::One(Fault {
                kind: FaultKind::Kill,
                service: "plant".into(),
                at_s: 0.5,
                duration_s: 0.0
            })
        );
        assert_eq!(
            parse("stop:current-loop@1:0.02").unwrap(),
            FaultSpec::One(Fault {
                kind: FaultKind::Stop,
                service: "current-loop".into(),
                at_s: 1.0,
                duration_s: 0.02
            })
        );
        assert_eq!(parse("random:100").unwrap(), FaultSpec::Random(100));
    }

    #[test]
    fn a_kill_or_stop_on_sample_0_is_refused_and_one_on_sample_1_planned() {
        let stages: Vec<String> = SERVICES.iter().map(|s| s.to_string()).collect();
        // At 10 kHz, t rounds to sample 0 below 50 µs.
        for at in ["0", "-0", "1e-320", "0.0000499"] {
            for spec in [
                format!("kill:plant@{at}"),
                format!("stop:observer@{at}:0.01"),
            ] {
                let e = plan(&[parse(&spec).unwrap()], 1.0, 1e4, 1, 0.3, &stages)
                    .unwrap_err()
                    .to_string();
                assert!(e.contains("falls on sample 0"), "{spec}: {e}");
                assert!(
                    e.contains("at or after 0.0001 s at 10000 Hz"),
                    "{spec}: {e}"
                );
            }
        }
        let p = plan(
            &[parse("kill:plant@0.00005").unwrap()],
            1.0,
            1e4,
            1,
            0.3,
            &stages,
        );
        assert_eq!(p.unwrap().len(), 1);
        // Two stops hold 0.3 s in all; kills and random kills hold nothing.
        let specs: Vec<FaultSpec> = [
            "stop:plant@0.1:0.2",
            "kill:observer@0.2",
            "stop:observer@0.5:0.1",
            "random:2",
        ]
        .iter()
        .map(|s| parse(s).unwrap())
        .collect();
        assert!((stopped_s(&specs) - 0.3).abs() < 1e-12);
    }

    #[test]
    fn bad_specs_are_clear_errors() {
        assert!(parse("kill:Pump@1")
            .unwrap_err()
            .to_string()
            .contains("unknown stage 'Pump'"));
        let stages: Vec<String> = SERVICES.iter().map(|s| s.to_string()).collect();
        let e = plan(&[parse("kill:pump@1").unwrap()], 2.0, 1e4, 1, 0.3, &stages).unwrap_err();
        assert!(e.to_string().contains("unknown stage 'pump'"), "{e}");
        assert!(parse("kill:plant")
            .unwrap_err()
            .to_string()
            .contains("kill:STAGE@SECONDS"));
        assert!(parse("stop:plant@1")
            .unwrap_err()
            .to_string()
            .contains("stop:STAGE@SECONDS:DURATION"));
        assert!(parse("kill:plant@x")
            .unwrap_err()
            .to_string()
            .contains("not a number"));
        // One unit at most.
        assert!(parse("kill:plant@0.01s").is_ok());
        assert!(parse("kill:plant@0.01sss")
            .unwrap_err()
            .to_string()
            .contains("'0.01sss' is not a number of seconds"));
        assert!(parse("explode:plant@1")
            .unwrap_err()
            .to_string()
            .contains("unknown fault kind"));
        for bad in ["0", "10001", "99999999999999999999999", "abc", "1e3"] {
            let e = parse(&format!("random:{bad}")).unwrap_err().to_string();
            assert_eq!(
                e,
                format!("fault 'random:{bad}': N must be a whole number in 1..=10000")
            );
        }
        for huge in ["1e20", "61", "0.0005"] {
            let e = parse(&format!("stop:observer@0.05:{huge}")).unwrap_err();
            assert!(
                e.to_string().contains("a stop lasts 0.001 to 60 s"),
                "{huge}: {e}"
            );
        }
        assert!(parse("stop:observer@0.05:60").is_ok());
    }

    #[test]
    fn simulated_kills_and_stops_become_inject_tables_refused_in_real_time() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../scenarios/kyslan-pi.toml");
        let (mut sc, _) = Scenario::load(path).unwrap();
        let specs = [
            parse("kill:observer@0.05").unwrap(),
            parse("stop:speed-loop@0.06:0.02").unwrap(),
        ];
        let stages: Vec<String> = SERVICES.iter().map(|s| s.to_string()).collect();
        let p = plan(&specs, 0.1, 1e4, 1, 0.3, &stages).unwrap();
        schedule_simulated(&p, Some(25.0), &mut sc).unwrap();
        let specs: Vec<(String, f64)> =
            sc.inject.iter().map(|i| (i.spec(), i.duration_s)).collect();
        assert_eq!(
            specs,
            [
                ("kill:observer@0.05".to_string(), 0.025),
                ("stop:speed-loop@0.06:0.02".to_string(), 0.02)
            ]
        );
        check_simulated(&sc.inject, true).unwrap();
        let e = check_simulated(&sc.inject, false).unwrap_err().to_string();
        assert!(e.contains("kill:observer@0.05: kill and stop tables are simulated in --clock lockstep and inprocess only"), "{e}");
        assert_eq!(restart_ms("40"), Ok(40.0));
        assert_eq!(restart_ms("2.5ms"), Ok(2.5));
        for bad in ["0", "0.5", "10001", "NaN", "inf", "-3"] {
            assert_eq!(
                restart_ms(bad).unwrap_err(),
                "the simulated restart lasts 1 to 10000 ms",
                "{bad}"
            );
        }
        assert!(restart_ms("soon").unwrap_err().contains("not a number"));
    }

    #[test]
    fn random_plan_is_seeded_sorted_and_spaced() {
        let stages: Vec<String> = SERVICES.iter().map(|s| s.to_string()).collect();
        let a = plan(&[FaultSpec::Random(10)], 20.0, 1e4, 7, 1.0, &stages).unwrap();
        let b = plan(&[FaultSpec::Random(10)], 20.0, 1e4, 7, 1.0, &stages).unwrap();
        assert_eq!(a, b);
        assert_eq!(a.len(), 10);
        for w in a.windows(2) {
            assert!(w[1].at_s - w[0].at_s >= 0.79, "{w:?}");
        }
        assert!(plan(&[FaultSpec::Random(10)], 2.0, 1e4, 7, 1.0, &stages)
            .unwrap_err()
            .to_string()
            .contains("--duration"));
    }
}
