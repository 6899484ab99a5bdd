//! Messages exchanged on the bus. Every message is defined once, here: iceoryx2 identifies a
//! payload type by its name, size and alignment.
//!
//! Timestamps are CLOCK_MONOTONIC nanoseconds, comparable across processes. In lockstep
//! runs `t_sample_ns` is 0 (there is no wall-clock schedule).

use iceoryx2::prelude::ZeroCopySend;

/// Header flag: the plant has produced its last sample; consumers forward it and exit.
pub const FLAG_END: u32 = 1;
/// Header flag (measurement): the plant used a stale command this sample (deadline miss).
pub const FLAG_STALE_CMD: u32 = 2;
/// Header flag (measurement): the inverter is in its safe state.
pub const FLAG_SAFE_STATE: u32 = 4;
/// Header flag: the producer used a stale input this sample.
pub const FLAG_STALE_INPUT: u32 = 8;
/// Trace only: no command was recorded for this sample (the current loop produced none).
pub const FLAG_MISSING: u32 = 32;
/// Header flag: a warm-up message before sample 0. It travels the whole chain (so that every
/// port has connected and every page is touched) but no step function sees it.
pub const FLAG_WARMUP: u32 = 16;
/// Trace only: the plant's process was down at this sample; the motor was integrated
/// afterwards under the inverter's hold and safe state (no command reached it).
pub const FLAG_PLANT_DOWN: u32 = 64;
/// Header flag (measurement): the inverter's overcurrent trip has fired (at this sample or
/// before). The trip is latched: the inverter stays in its safe state until the run ends.
pub const FLAG_TRIPPED: u32 = 128;
/// Header flag, lockstep only: the producer has no message for this sample (a `drop` fault,
/// or a stage that could not step for want of an input). The marker carries no values;
/// consumers take the input as absent for that sample instead of waiting for it
/// (docs/architecture.md, "Fault model").
pub const FLAG_ABSENT: u32 = 256;
/// Largest magnitude a payload value may have: no current (A), voltage (V), speed (rad/s),
/// angle (rad) or torque (N·m) of a drive comes near it, so a larger value is corrupt.
pub const MAX_ABS_VALUE: f64 = 1e12;

/// Common header.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct Header {
    /// Sample index k.
    pub k: u64,
    /// Ideal sample instant t_k (plant's schedule), ns; 0 in lockstep.
    pub t_sample_ns: u64,
    /// When the producer published the sample's outputs, ns: the first one's publish (a
    /// stage's later outputs of the same sample carry the same instant).
    pub t_pub_ns: u64,
    /// `FLAG_*` bits.
    pub flags: u32,
    /// Padding (keeps the layout explicit).
    pub reserved: u32,
}

impl Header {
    /// True when the END flag is set.
    pub fn is_end(&self) -> bool {
        self.flags & FLAG_END != 0
    }

    /// True when the WARMUP flag is set.
    pub fn is_warmup(&self) -> bool {
        self.flags & FLAG_WARMUP != 0
    }

    /// True when the ABSENT flag is set (lockstep: no message for this sample).
    pub fn is_absent(&self) -> bool {
        self.flags & FLAG_ABSENT != 0
    }
}

/// Plant → controllers: what the sensors and the inverter report at t_k (nothing a real
/// controller could not know).
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct Measurement {
    /// Header.
    pub hdr: Header,
    /// Measured phase currents (a, b, c), A (with sensor noise if configured).
    pub i_abc: [f64; 3],
    /// Encoder mechanical angle, rad in [0, 2π) (quantised if configured).
    pub theta_m_enc: f64,
    /// αβ voltage applied by the inverter on [t_k, t_{k+1}), V.
    pub u_ab_applied: [f64; 2],
}

/// Plant → recorder only: the true state at t_k, for the trace (and for a restarted plant
/// to resume from). No stage reads it. Its header carries the measurement's flags.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct PlantTruth {
    /// Header (flags as in the measurement of the same sample).
    pub hdr: Header,
    /// True d/q current at t_k, A.
    pub i_dq: [f64; 2],
    /// True mechanical speed at t_k, rad/s.
    pub omega_m: f64,
    /// True electrical angle at t_k, rad in [0, 2π).
    pub theta_e: f64,
    /// True mechanical position at t_k, unwrapped (counted from 0 at the start), rad.
    pub theta_m: f64,
    /// d/q voltage applied on [t_k, t_{k+1}) in the true rotor frame, V.
    pub u_dq_applied: [f64; 2],
    /// αβ voltage applied on [t_k, t_{k+1}), V.
    pub u_ab_applied: [f64; 2],
    /// Load torque on [t_k, t_{k+1}), N·m.
    pub t_load: f64,
    /// Encoder reading at t_k, rad in [0, 2π).
    pub theta_m_enc: f64,
}

/// Observer → current and speed loop: position/speed estimate for sample k.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct Estimate {
    /// Header.
    pub hdr: Header,
    /// Estimated electrical angle, rad in [0, 2π).
    pub theta_e: f64,
    /// Estimated mechanical speed, rad/s.
    pub omega_m: f64,
}

/// Speed loop → current loop: current references computed at sample k (used from k+1 on).
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct CurrentRef {
    /// Header.
    pub hdr: Header,
    /// Speed reference the speed loop tracked, mechanical rad/s.
    pub omega_ref: f64,
    /// d-axis current reference, A.
    pub i_d_ref: f64,
    /// q-axis current reference, A.
    pub i_q_ref: f64,
}

/// Current loop → plant: voltage command k (applied from t_{k+1} on) and, for the trace, the
/// references and estimates it used.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct VoltageCommand {
    /// Header.
    pub hdr: Header,
    /// Commanded αβ voltage, V (what a real inverter receives).
    pub u_ab: [f64; 2],
    /// Commanded d/q voltage in the estimated frame, V.
    pub u_dq: [f64; 2],
    /// Current references used at k, A.
    pub i_dq_ref: [f64; 2],
    /// Speed reference carried by the current reference used at k, rad/s.
    pub omega_ref: f64,
    /// Estimate used at k: speed (rad/s) and electrical angle (rad).
    pub omega_hat: f64,
    /// Estimated electrical angle used at k, rad.
    pub theta_hat: f64,
}

/// Outer loop → speed loop: the speed reference computed at sample k (used from k+1 on), e.g.
/// by a position loop. When a topology has a producer of it, the speed loop follows it instead
/// of the scenario's speed profile.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct SpeedRef {
    /// Header.
    pub hdr: Header,
    /// Speed reference, mechanical rad/s.
    pub omega_ref: f64,
    /// Position reference the outer loop tracked, mechanical rad (unwrapped; 0 if none).
    pub theta_m_ref: f64,
    /// The unwrapped position the outer loop measured, mechanical rad (0 if none): what a
    /// restarted outer loop takes its turn count from (docs/architecture.md, "Bumpless
    /// rejoin").
    pub theta_m: f64,
}

/// Every payload must be finite and plausible; a NaN, an infinity or a value beyond
/// [`MAX_ABS_VALUE`] from a peer is rejected, never used.
pub trait Finite {
    /// True when every floating-point field is finite and at most [`MAX_ABS_VALUE`] in
    /// magnitude.
    fn is_finite(&self) -> bool;
}

fn all_finite(v: &[f64]) -> bool {
    v.iter().all(|x| x.is_finite() && x.abs() <= MAX_ABS_VALUE)
}

impl Finite for Measurement {
    fn is_finite(&self) -> bool {
        all_finite(&self.i_abc) && all_finite(&self.u_ab_applied) && all_finite(&[self.theta_m_enc])
    }
}

impl Finite for PlantTruth {
    fn is_finite(&self) -> bool {
        all_finite(&self.i_dq)
            && all_finite(&self.u_dq_applied)
            && all_finite(&self.u_ab_applied)
            && all_finite(&[
                self.omega_m,
                self.theta_e,
                self.theta_m,
                self.t_load,
                self.theta_m_enc,
            ])
    }
}

impl Finite for Estimate {
    fn is_finite(&self) -> bool {
        all_finite(&[self.theta_e, self.omega_m])
    }
}

impl Finite for CurrentRef {
    fn is_finite(&self) -> bool {
        all_finite(&[self.omega_ref, self.i_d_ref, self.i_q_ref])
    }
}

impl Finite for SpeedRef {
    fn is_finite(&self) -> bool {
        all_finite(&[self.omega_ref, self.theta_m_ref, self.theta_m])
    }
}

impl Finite for VoltageCommand {
    fn is_finite(&self) -> bool {
        all_finite(&self.u_ab)
            && all_finite(&self.u_dq)
            && all_finite(&self.i_dq_ref)
            && all_finite(&[self.omega_ref, self.omega_hat, self.theta_hat])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nan_is_detected() {
        let mut m = Measurement::default();
        assert!(m.is_finite());
        m.i_abc[1] = f64::NAN;
        assert!(!m.is_finite());
        let mut c = VoltageCommand::default();
        c.u_ab[0] = f64::INFINITY;
        assert!(!c.is_finite());
        // Finite but absurd: as unusable as NaN.
        c.u_ab[0] = 1e30;
        assert!(!c.is_finite());
        c.u_ab[0] = -MAX_ABS_VALUE;
        assert!(c.is_finite());
    }

    #[test]
    fn layouts_are_fixed_size() {
        assert_eq!(std::mem::size_of::<Header>(), 32);
        assert_eq!(std::mem::size_of::<Measurement>() % 8, 0);
    }
}
