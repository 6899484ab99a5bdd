//! Sensor faults of the plant (docs/architecture.md, "Fault model"): the `[[sensor_fault]]`
//! tables of a scenario and the model that applies them to the measurement by sample index.
//!
//! Only what the controllers and the observer see is faulty (the `Measurement` topic); the
//! plant's true state (the `PlantTruth` topic, the trace's true columns) stays true. The
//! schedule is in samples, so it gives the same trace in every clock and a restarted plant
//! keeps applying it.

use serde::{Deserialize, Serialize};

/// Shortest encoder freeze, s.
pub const STUCK_MIN_S: f64 = 0.001;
/// Longest encoder freeze, s.
pub const STUCK_MAX_S: f64 = 60.0;
/// Largest |current offset|, A.
pub const OFFSET_MAX_A: f64 = 1000.0;
/// Most `[[sensor_fault]]` tables in one scenario.
pub const MAX_SENSOR_FAULTS: usize = 64;

/// A phase of the current sensors.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Phase {
    /// Phase a.
    A,
    /// Phase b.
    B,
    /// Phase c.
    C,
}

impl Phase {
    /// Index into `Measurement::i_abc`.
    pub fn index(self) -> usize {
        self as usize
    }

    /// `a`, `b` or `c`.
    pub fn name(self) -> &'static str {
        ["a", "b", "c"][self.index()]
    }
}

/// One `[[sensor_fault]]` table.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum SensorFault {
    /// The encoder's output freezes at its reading of sample round(at_s·f_s) for
    /// `duration_s`, then reads true again.
    EncoderStuck {
        /// Start, s of simulated time.
        at_s: f64,
        /// How long the reading stays frozen, s.
        duration_s: f64,
    },
    /// From sample round(at_s·f_s) to the end of the run, the measured current of `phase`
    /// carries the constant offset `amps`.
    CurrentOffset {
        /// The phase whose sensor is offset.
        phase: Phase,
        /// Start, s of simulated time.
        at_s: f64,
        /// Offset added to the measured current, A.
        amps: f64,
    },
}

impl SensorFault {
    /// `encoder-stuck` or `current-offset`.
    pub fn kind_name(&self) -> &'static str {
        match self {
            Self::EncoderStuck { .. } => "encoder-stuck",
            Self::CurrentOffset { .. } => "current-offset",
        }
    }

    /// Start, s.
    pub fn at_s(&self) -> f64 {
        match *self {
            Self::EncoderStuck { at_s, .. } | Self::CurrentOffset { at_s, .. } => at_s,
        }
    }

    /// The spec as `--fault` takes it, e.g. `encoder-stuck@0.3:0.05`.
    pub fn spec(&self) -> String {
        match *self {
            Self::EncoderStuck { at_s, duration_s } => format!("encoder-stuck@{at_s}:{duration_s}"),
            Self::CurrentOffset { phase, at_s, amps } => {
                format!("current-offset:{}@{at_s}:{amps}", phase.name())
            }
        }
    }

    /// The bounds that do not depend on the run: a one-line error naming the bad value.
    pub fn check(&self) -> Result<(), String> {
        let at = self.at_s();
        if !(at.is_finite() && at >= 0.0) {
            return Err(format!(
                "{}: at_s = {at} must be a finite number of seconds >= 0",
                self.kind_name()
            ));
        }
        match *self {
            Self::EncoderStuck { duration_s, .. } => {
                if !(STUCK_MIN_S..=STUCK_MAX_S).contains(&duration_s) {
                    return Err(format!(
                        "encoder-stuck: duration_s = {duration_s} must be in {STUCK_MIN_S}..={STUCK_MAX_S} s"
                    ));
                }
            }
            Self::CurrentOffset { amps, .. } => {
                if !(amps.is_finite() && amps.abs() <= OFFSET_MAX_A) {
                    return Err(format!(
                        "current-offset: amps = {amps} must be finite and within ±{OFFSET_MAX_A} A"
                    ));
                }
            }
        }
        Ok(())
    }

    /// First faulty sample and the first sample after the fault (`u64::MAX`: to the end of
    /// the run) at sample rate `sample_hz`. An encoder freeze lasts at least one sample.
    pub fn samples(&self, sample_hz: f64) -> (u64, u64) {
        let k0 = (self.at_s() * sample_hz).round() as u64;
        match *self {
            Self::EncoderStuck { duration_s, .. } => {
                (k0, k0 + ((duration_s * sample_hz).round() as u64).max(1))
            }
            Self::CurrentOffset { .. } => (k0, u64::MAX),
        }
    }
}

/// Checks a scenario's `[[sensor_fault]]` tables against its run length.
pub fn validate(faults: &[SensorFault], duration_s: f64) -> Result<(), String> {
    if faults.len() > MAX_SENSOR_FAULTS {
        return Err(format!(
            "{} [[sensor_fault]] tables: at most {MAX_SENSOR_FAULTS}",
            faults.len()
        ));
    }
    for (i, f) in faults.iter().enumerate() {
        f.check().map_err(|e| format!("sensor_fault[{i}] {e}"))?;
        if f.at_s() >= duration_s {
            return Err(format!(
                "sensor_fault[{i}] {} is at or after the end of the run ({duration_s} s)",
                f.spec()
            ));
        }
    }
    Ok(())
}

/// The sensor faults of one plant, by sample index. Built once; [`SensorModel::encoder`] and
/// [`SensorModel::currents`] neither allocate nor make a syscall (real-time safe).
#[derive(Debug, Clone, Default)]
pub struct SensorModel {
    /// Encoder freezes: [first, end) samples.
    stuck: Vec<(u64, u64)>,
    /// Current offsets: first sample, phase index, A.
    offsets: Vec<(u64, usize, f64)>,
    /// The frozen encoder reading while a freeze lasts.
    held: Option<f64>,
}

impl SensorModel {
    /// The model of `faults` at sample rate `sample_hz`.
    pub fn new(faults: &[SensorFault], sample_hz: f64) -> Self {
        let mut m = Self::default();
        for f in faults {
            let (k0, k1) = f.samples(sample_hz);
            match *f {
                SensorFault::EncoderStuck { .. } => m.stuck.push((k0, k1)),
                SensorFault::CurrentOffset { phase, amps, .. } => {
                    m.offsets.push((k0, phase.index(), amps))
                }
            }
        }
        m
    }

    /// The encoder's output at sample k, given its true `reading`: inside a freeze, the
    /// reading of the freeze's first sample.
    #[inline]
    pub fn encoder(&mut self, k: u64, reading: f64) -> f64 {
        match self.stuck.iter().find(|(a, b)| (*a..*b).contains(&k)) {
            Some(&(a, _)) => match self.held {
                Some(h) if k != a => h,
                _ => {
                    self.held = Some(reading);
                    reading
                }
            },
            None => {
                self.held = None;
                reading
            }
        }
    }

    /// Adds the offsets active at sample k to the measured phase currents `i_abc`, A.
    #[inline]
    pub fn currents(&self, k: u64, i_abc: &mut [f64; 3]) {
        for &(k0, ph, amps) in &self.offsets {
            if k >= k0 {
                i_abc[ph] += amps;
            }
        }
    }

    /// A restarted plant resumes after sample `k` whose published encoder output was
    /// `theta_m_enc`: inside a freeze, that is the frozen value it keeps.
    pub fn resume(&mut self, k: u64, theta_m_enc: f64) {
        self.held = self
            .stuck
            .iter()
            .any(|(a, b)| (*a..*b).contains(&k))
            .then_some(theta_m_enc);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_encoder_freeze_holds_its_first_reading_then_reads_true() {
        let f = SensorFault::EncoderStuck {
            at_s: 0.002,
            duration_s: 0.003,
        };
        assert_eq!(f.samples(1000.0), (2, 5));
        let mut m = SensorModel::new(&[f], 1000.0);
        let out: Vec<f64> = (0..7).map(|k| m.encoder(k, k as f64)).collect();
        assert_eq!(out, [0.0, 1.0, 2.0, 2.0, 2.0, 5.0, 6.0]);
        // A plant restarted inside the freeze keeps the value it had published.
        let mut r = SensorModel::new(&[f], 1000.0);
        r.resume(3, 0.2);
        assert_eq!(r.encoder(4, 0.4), 0.2);
        assert_eq!(r.encoder(5, 0.5), 0.5);
    }

    #[test]
    fn a_current_offset_adds_to_its_phase_from_its_sample_on() {
        let f = SensorFault::CurrentOffset {
            phase: Phase::B,
            at_s: 0.01,
            amps: -0.5,
        };
        let m = SensorModel::new(&[f], 1000.0);
        let mut i = [1.0, 1.0, 1.0];
        m.currents(9, &mut i);
        assert_eq!(i, [1.0, 1.0, 1.0]);
        for k in [10, 1_000_000] {
            let mut i = [1.0, 1.0, 1.0];
            m.currents(k, &mut i);
            assert_eq!(i, [1.0, 0.5, 1.0]);
        }
    }

    /// A turning plant (prescribed speed) with a freeze of samples 10..30.
    fn turning_plant() -> crate::drive::Plant {
        let text = std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../scenarios/kyslan-pi.toml"
        ))
        .unwrap();
        let mut sc = crate::config::Scenario::from_toml(&text, "kyslan-pi.toml").unwrap();
        sc.mechanics.prescribed_speed_rad_s = Some(70.0);
        sc.sensor_fault = vec![SensorFault::EncoderStuck {
            at_s: 0.001,
            duration_s: 0.002,
        }];
        sc.validate().unwrap();
        crate::drive::Plant::new(&sc)
    }

    #[test]
    fn the_plant_freezes_the_measurement_not_the_truth_and_a_restart_keeps_the_freeze() {
        let mut a = turning_plant();
        let (mut enc, mut truths) = (Vec::new(), Vec::new());
        for k in 0..40 {
            enc.push(a.sample(k, None).theta_m_enc);
            truths.push(*a.truth());
            a.advance();
        }
        assert!(enc[10..30].iter().all(|&e| e == enc[10]), "{enc:?}");
        assert!(enc[9] != enc[10] && enc[30] != enc[10], "{enc:?}");
        // The true position moves on through the freeze.
        assert!(truths[29].theta_m > truths[10].theta_m);
        // Restarted from its state of sample 15 (inside the freeze), resuming at 20: it
        // reads the frozen value up to 29, then true again.
        let mut b = turning_plant();
        b.coast(&truths[15], 20, |_| {});
        let seen: Vec<f64> = (20..40)
            .map(|k| {
                let e = b.sample(k, None).theta_m_enc;
                b.advance();
                e
            })
            .collect();
        assert!(seen[..10].iter().all(|&e| e == enc[10]), "{seen:?}");
        assert!(
            (seen[10] - enc[30]).abs() < 1e-9,
            "{} {}",
            seen[10],
            enc[30]
        );
    }

    #[test]
    fn bounds_are_one_line_errors() {
        let stuck = |d| SensorFault::EncoderStuck {
            at_s: 0.1,
            duration_s: d,
        };
        assert!(stuck(0.001).check().is_ok() && stuck(60.0).check().is_ok());
        for d in [0.0005, 61.0, f64::NAN] {
            let e = stuck(d).check().unwrap_err();
            assert!(e.contains("must be in 0.001..=60 s"), "{e}");
        }
        let off = |a| SensorFault::CurrentOffset {
            phase: Phase::A,
            at_s: 0.1,
            amps: a,
        };
        assert!(off(-1000.0).check().is_ok());
        for a in [1000.5, f64::INFINITY, f64::NAN] {
            let e = off(a).check().unwrap_err();
            assert!(e.contains("within ±1000 A"), "{e}");
        }
        let e = validate(&[stuck(0.1)], 0.1).unwrap_err();
        assert_eq!(
            e,
            "sensor_fault[0] encoder-stuck@0.1:0.1 is at or after the end of the run (0.1 s)"
        );
    }

    #[test]
    fn the_tables_read_and_write_as_toml() {
        #[derive(Serialize, Deserialize)]
        struct T {
            sensor_fault: Vec<SensorFault>,
        }
        let text = "[[sensor_fault]]\nkind = \"current-offset\"\nphase = \"c\"\nat_s = 0.5\namps = 2.0\n\n[[sensor_fault]]\nkind = \"encoder-stuck\"\nat_s = 0.2\nduration_s = 0.05\n";
        let t: T = toml::from_str(text).unwrap();
        assert_eq!(
            t.sensor_fault[0],
            SensorFault::CurrentOffset {
                phase: Phase::C,
                at_s: 0.5,
                amps: 2.0
            }
        );
        let back: T = toml::from_str(&toml::to_string(&t).unwrap()).unwrap();
        assert_eq!(back.sensor_fault, t.sensor_fault);
        let bad = "[[sensor_fault]]\nkind = \"encoder-stuck\"\nat_s = 0.2\nduration_s = 0.05\namps = 1.0\n";
        assert!(toml::from_str::<T>(bad).is_err());
    }
}
