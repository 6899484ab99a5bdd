//! Static sensor errors of the plant (`[sensors]`, docs/architecture.md, "Plant realism"):
//! per-phase current-sensor gain and offset, ADC quantisation and an encoder delay. They are
//! properties of the hardware for the whole run, unlike the scheduled `[[sensor_fault]]`s.
//! Deterministic (the Gaussian current noise is the only random part, seeded by
//! `sensors.seed`); no allocation, no system call.

use crate::config::Sensors;
use drivelab_control::motor::wrap_2pi;

/// Longest encoder delay, samples.
pub const MAX_ENCODER_DELAY_SAMPLES: usize = 16;

/// A bipolar ADC: code = round(i/LSB) within [−2^(b−1), 2^(b−1) − 1], LSB = range/2^(b−1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Adc {
    /// One code step, A.
    pub lsb_a: f64,
    lo: f64,
    hi: f64,
}

impl Adc {
    /// The ADC of `bits` over ±`range_a`.
    pub fn new(bits: u32, range_a: f64) -> Self {
        let half = f64::from(1u32 << (bits - 1));
        Self {
            lsb_a: range_a / half,
            lo: -half,
            hi: half - 1.0,
        }
    }

    /// The reading of current `i`, A.
    pub fn read(&self, i: f64) -> f64 {
        (i / self.lsb_a).round().clamp(self.lo, self.hi) * self.lsb_a
    }
}

/// The static errors of one plant's sensors.
#[derive(Debug, Clone)]
pub struct SensorErrors {
    gain: [f64; 3],
    offset: [f64; 3],
    /// Gain or offset not ideal (skipped otherwise, so that an ideal sensor leaves every
    /// bit, the sign of a zero included, as it was).
    scaled: bool,
    adc: Option<Adc>,
    /// Encoder delay in samples (whole and fraction).
    delay_samples: f64,
    /// The last positions θ_m (rad, wrapped), newest at `head`.
    history: [f64; MAX_ENCODER_DELAY_SAMPLES + 2],
    head: usize,
    filled: usize,
}

impl SensorErrors {
    /// The errors of `s` at sample time `ts`.
    pub fn new(s: &Sensors, ts: f64) -> Self {
        Self {
            gain: s.current_gain,
            offset: s.current_offset_a,
            scaled: s.current_gain != [1.0; 3] || s.current_offset_a != [0.0; 3],
            adc: s.adc_bits.zip(s.adc_range_a).map(|(b, r)| Adc::new(b, r)),
            delay_samples: s.encoder_delay_us * 1e-6 / ts,
            history: [0.0; MAX_ENCODER_DELAY_SAMPLES + 2],
            head: 0,
            filled: 0,
        }
    }

    /// Gain and offset of each phase's sensor (before noise and faults).
    #[inline]
    pub fn analog(&self, i: &mut [f64; 3]) {
        if self.scaled {
            for ((x, g), o) in i.iter_mut().zip(self.gain).zip(self.offset) {
                *x = g * *x + o;
            }
        }
    }

    /// The ADC's quantisation and saturation (last, after noise and faults).
    #[inline]
    pub fn digitise(&self, i: &mut [f64; 3]) {
        if let Some(adc) = self.adc {
            for x in i.iter_mut() {
                *x = adc.read(*x);
            }
        }
    }

    /// The encoder's position at t_k − delay, given the true θ_m(t_k) (rad, wrapped):
    /// linear between the two samples around that instant; before the first sample the
    /// first position.
    #[inline]
    pub fn encoder(&mut self, theta_m: f64) -> f64 {
        if self.delay_samples == 0.0 {
            return theta_m;
        }
        let n = self.history.len();
        self.head = (self.head + 1) % n;
        self.history[self.head] = theta_m;
        self.filled = (self.filled + 1).min(n);
        let back = |j: usize| {
            let j = j.min(self.filled - 1);
            self.history[(self.head + n - j) % n]
        };
        let whole = self.delay_samples.floor();
        let frac = self.delay_samples - whole;
        let (a, b) = (back(whole as usize), back(whole as usize + 1));
        // b is one sample older than a; the step between them is far below π.
        let step =
            (a - b + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
        wrap_2pi(a - frac * step)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn adc_rounds_to_its_code_and_saturates_at_its_range() {
        // 12 bits over ±10 A: LSB = 10/2048 A.
        let adc = Adc::new(12, 10.0);
        let lsb = 10.0 / 2048.0;
        assert_eq!(adc.lsb_a, lsb);
        assert_eq!(adc.read(0.4 * lsb), 0.0);
        assert_eq!(adc.read(0.6 * lsb), lsb);
        assert_eq!(adc.read(-3.0 * lsb), -3.0 * lsb);
        assert_eq!(adc.read(50.0), 10.0 - lsb);
        assert_eq!(adc.read(-50.0), -10.0);
        // One bit: the codes −1 and 0.
        let one = Adc::new(1, 2.0);
        assert_eq!(
            (one.read(-5.0), one.read(0.7), one.read(5.0)),
            (-2.0, 0.0, 0.0)
        );
        // Quantisation error within half an LSB inside the range.
        for k in 0..1000 {
            let i = -9.9 + 0.0198 * f64::from(k);
            assert!((adc.read(i) - i).abs() <= 0.5 * lsb + 1e-15, "{i}");
        }
    }

    #[test]
    fn gain_and_offset_act_per_phase() {
        let s = Sensors {
            current_gain: [1.02, 1.0, 0.97],
            current_offset_a: [0.05, -0.1, 0.0],
            ..Sensors::default()
        };
        let e = SensorErrors::new(&s, 1e-4);
        let mut i = [1.0, -2.0, 1.0];
        e.analog(&mut i);
        assert_eq!(i, [1.02 + 0.05, -2.0 - 0.1, 0.97]);
    }

    #[test]
    fn the_encoder_reports_the_position_of_delay_ago() {
        // 2.5 samples of delay at a constant 0.1 rad per sample, across the wrap at 2π.
        let ts = 1e-4;
        let s = Sensors {
            encoder_delay_us: 250.0,
            ..Sensors::default()
        };
        let mut e = SensorErrors::new(&s, ts);
        let theta = |k: u64| wrap_2pi(6.0 + 0.1 * k as f64);
        for k in 0..40u64 {
            let r = e.encoder(theta(k));
            // Before 2.5 samples of history exist: the oldest position it has.
            let expected = if k < 3 {
                theta(0)
            } else {
                wrap_2pi(6.0 + 0.1 * (k as f64 - 2.5))
            };
            let d = (r - expected + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
                - std::f64::consts::PI;
            assert!(d.abs() < 1e-12, "k {k}: {r} vs {expected}");
        }
        // Ideal: the true position.
        let mut ideal = SensorErrors::new(&Sensors::default(), ts);
        assert_eq!(ideal.encoder(1.234), 1.234);
    }
}
