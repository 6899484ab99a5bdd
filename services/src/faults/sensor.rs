//! Sensor faults from `--fault`: `encoder-stuck@S:DUR` and `current-offset:PHASE@S:AMPS`.
//! They are not signals: the launcher adds them to the resolved scenario's
//! `[[sensor_fault]]` tables, which every plant (restarted ones and the in-process clock
//! included) applies by sample index (docs/architecture.md, "Fault model").

use super::window::{window, FaultWindow};
use super::FaultSpec;
use crate::launcher::{DriveEnd, FaultReport};
use anyhow::{anyhow, bail, Result};
use drivelab_runtime::config::Scenario;
use drivelab_runtime::sensor_faults::{Phase, SensorFault};
use drivelab_runtime::trace::TraceRow;

/// Parses `encoder-stuck@SECONDS:DURATION` or `current-offset:PHASE@SECONDS:AMPS`.
pub fn parse(spec: &str) -> Result<SensorFault> {
    let f = if let Some(rest) = spec.strip_prefix("encoder-stuck@") {
        let (at, dur) = rest
            .split_once(':')
            .ok_or_else(|| anyhow!("fault '{spec}': expected encoder-stuck@SECONDS:DURATION"))?;
        SensorFault::EncoderStuck {
            at_s: super::seconds(at, "time", spec)?,
            duration_s: super::seconds(dur, "duration", spec)?,
        }
    } else if let Some(rest) = spec.strip_prefix("current-offset:") {
        let form = || anyhow!("fault '{spec}': expected current-offset:PHASE@SECONDS:AMPS");
        let (ph, when) = rest.split_once('@').ok_or_else(form)?;
        let (at, amps) = when.split_once(':').ok_or_else(form)?;
        let phase = match ph {
            "a" => Phase::A,
            "b" => Phase::B,
            "c" => Phase::C,
            other => bail!("fault '{spec}': unknown phase '{other}' (a, b, c)"),
        };
        let amps = amps
            .trim_end_matches('A')
            .parse::<f64>()
            .map_err(|_| anyhow!("fault '{spec}': offset '{amps}' is not a number of amperes"))?;
        SensorFault::CurrentOffset {
            phase,
            at_s: super::seconds(at, "time", spec)?,
            amps,
        }
    } else {
        bail!("fault '{spec}': expected encoder-stuck@SECONDS:DURATION or current-offset:PHASE@SECONDS:AMPS");
    };
    f.check().map_err(|e| anyhow!("fault '{spec}': {e}"))?;
    Ok(f)
}

/// Appends the sensor faults among `specs` to the scenario's `[[sensor_fault]]` tables and
/// validates the result against the run's length (one-line error).
pub fn add_to_scenario(specs: &[FaultSpec], sc: &mut Scenario) -> Result<()> {
    for s in specs {
        if let FaultSpec::Sensor(f) = s {
            if f.at_s() >= sc.duration_s {
                bail!(
                    "fault '{}' is at or after the end of the run ({} s)",
                    f.spec(),
                    sc.duration_s
                );
            }
            sc.sensor_fault.push(*f);
        }
    }
    drivelab_runtime::sensor_faults::validate(&sc.sensor_fault, sc.duration_s)
        .map_err(|e| anyhow!("fault {e}"))
}

/// Samples compared after a lasting fault (a current offset) and before it: 0.1 s.
const COMPARE_S: f64 = 0.1;

/// The `[[sensor_fault]]`s of `sc` that were not made because the drive ended at `end`
/// before their first sample (a killed plant with `--restart never`, a stop signal), each as
/// (the drive's end, why), as a bus fault's ([`DriveEnd::not_reached`]).
pub fn not_made(sc: &Scenario, end: DriveEnd) -> Vec<(u64, String)> {
    let fs = sc.rates.sample_hz;
    sc.sensor_fault
        .iter()
        .filter_map(|f| end.not_reached(&f.spec(), f.samples(fs).0))
        .collect()
}

/// One report per `[[sensor_fault]]` of `sc` that the drive, which ended at `end`, reached
/// (the others were not made: [`not_made`]): the trace before the fault against the trace
/// during it (an encoder freeze) or just after it (an offset, which lasts to the end).
pub fn reports(sc: &Scenario, rows: &[TraceRow], end: DriveEnd) -> Vec<FaultReport> {
    let fs = sc.rates.sample_hz;
    let n = sc.samples();
    sc.sensor_fault
        .iter()
        .filter(|f| !end.before(f.samples(fs).0))
        .map(|f| {
            let (k0, k1) = f.samples(fs);
            let k1 = k1.min(n).min(if k1 == u64::MAX {
                k0 + (COMPARE_S * fs) as u64
            } else {
                u64::MAX
            });
            let k1 = k1.max(k0);
            let len = (k1 - k0).min(k0);
            let w: FaultWindow = window(rows, k0 - len..k0, k0..k1);
            let mut r = super::window::report(sc, rows, f.spec(), k0, k1, w);
            r.service = "plant".into();
            r.process = "plant".into();
            r
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_both_sensor_faults() {
        assert_eq!(
            parse("encoder-stuck@0.3:0.05").unwrap(),
            SensorFault::EncoderStuck {
                at_s: 0.3,
                duration_s: 0.05
            }
        );
        assert_eq!(
            parse("current-offset:c@1:-2.5").unwrap(),
            SensorFault::CurrentOffset {
                phase: Phase::C,
                at_s: 1.0,
                amps: -2.5
            }
        );
        assert!(matches!(
            super::super::parse("current-offset:a@0.2:1").unwrap(),
            FaultSpec::Sensor(SensorFault::CurrentOffset { .. })
        ));
    }

    #[test]
    fn bad_sensor_specs_are_one_line_errors() {
        for (spec, needle) in [
            (
                "encoder-stuck@0.3",
                "expected encoder-stuck@SECONDS:DURATION",
            ),
            (
                "encoder-stuck:0.3:0.1",
                "expected encoder-stuck@SECONDS:DURATION",
            ),
            ("encoder-stuck@x:0.1", "'x' is not a number of seconds"),
            ("encoder-stuck@-1:0.1", "finite number of seconds >= 0"),
            ("encoder-stuck@0.3:0.0005", "must be in 0.001..=60 s"),
            ("encoder-stuck@0.3:61", "must be in 0.001..=60 s"),
            ("encoder-stuck@0.3:inf", "finite number of seconds"),
            (
                "current-offset:a@0.3",
                "expected current-offset:PHASE@SECONDS:AMPS",
            ),
            (
                "current-offset:0.3:1",
                "expected current-offset:PHASE@SECONDS:AMPS",
            ),
            ("current-offset:d@0.3:1", "unknown phase 'd' (a, b, c)"),
            (
                "current-offset:a@0.3:lots",
                "'lots' is not a number of amperes",
            ),
            ("current-offset:a@0.3:1000.1", "within ±1000 A"),
            ("current-offset:a@0.3:NaN", "within ±1000 A"),
            ("current-offset:a@0.3:-inf", "within ±1000 A"),
        ] {
            let e = format!("{:#}", super::super::parse(spec).unwrap_err());
            assert!(e.contains(needle), "{spec}: {e}");
            assert!(e.starts_with(&format!("fault '{spec}'")), "{spec}: {e}");
            assert_eq!(e.lines().count(), 1, "{spec}: {e}");
        }
        assert!(parse("current-offset:b@0:1000").is_ok());
    }

    #[test]
    fn a_fault_after_the_end_of_the_run_is_refused() {
        let (mut sc, _) = Scenario::load("kyslan-pi").unwrap();
        sc.duration_s = 0.5;
        let specs = [super::super::parse("encoder-stuck@0.5:0.1").unwrap()];
        let e = add_to_scenario(&specs, &mut sc).unwrap_err().to_string();
        assert!(e.contains("at or after the end of the run (0.5 s)"), "{e}");
    }
}
