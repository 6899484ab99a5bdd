//! Re-joining a running drive after a restart: each step function is initialised
//! from the plant's current state before it takes over, so that its first output continues
//! what the drive was doing (no torque bump).

use super::{CurrentLaw, CurrentLoopStep, ObserverStep, Plant, SpeedLaw, SpeedLoopStep};
use crate::messages::{CurrentRef, Estimate, Measurement, PlantTruth};

use drivelab_control::control::current::{CurrentInput, VoltageDq};
use drivelab_control::transforms::{clarke, park, AlphaBeta};

impl Plant {
    /// A restarted plant resumes from its last published true state: currents, speed,
    /// position, and the voltage the inverter was applying. [`Plant::coast`] then brings it
    /// through its downtime.
    pub fn restore(&mut self, last: &PlantTruth) {
        self.x.i_d = last.i_dq[0];
        self.x.i_q = last.i_dq[1];
        self.x.omega_m = last.omega_m;
        self.x.theta_m = drivelab_control::motor::wrap_2pi(last.theta_m);
        self.theta_m_unwrapped = last.theta_m;
        // The ADC's instant before t_k is not in the record: the first reading is at t_k.
        self.x_adc = self.x;
        self.last_u_ab = last.u_ab_applied;
        self.stale_run = 0;
        // A tripped inverter stays tripped through a restart of the plant's process.
        self.tripped = last.hdr.flags & crate::messages::FLAG_TRIPPED != 0;
        // Inside an encoder freeze, the frozen reading it had published.
        self.sensor_faults.resume(last.hdr.k, last.theta_m_enc);
    }

    /// The motor through the plant's downtime: restored to `last` (its last recorded
    /// sample k0), it integrates from t_k0 up to t_k_to with no command reaching the
    /// inverter, which holds the last one for `inverter.hold_samples` and then applies its
    /// safe state, as a real inverter's watchdog would. `each` gets the true state of every
    /// sample k0 < k < k_to, flagged [`FLAG_PLANT_DOWN`]. Depends only on `last` and `k_to`:
    /// the launcher rebuilds the same samples for the trace.
    pub fn coast(&mut self, last: &PlantTruth, k_to: u64, mut each: impl FnMut(&PlantTruth)) {
        let k0 = last.hdr.k;
        self.restore(last);
        // Sample k0 as it was: its own command (the restored voltage) was fresh.
        self.sample(k0, None);
        self.stale_run = 0;
        self.advance();
        self.coast_on(k0 + 1, k_to, &mut each);
    }

    /// Coasts on from sample `k_from`, where an earlier [`Plant::coast`] (or this) left the
    /// model, to `k_to`: the same steps as one coast to `k_to`, so the model ends bit for bit
    /// where that one would.
    pub fn coast_on(&mut self, k_from: u64, k_to: u64, mut each: impl FnMut(&PlantTruth)) {
        use crate::messages::FLAG_PLANT_DOWN;
        for k in k_from..k_to {
            self.sample(k, None);
            self.truth.hdr.flags |= FLAG_PLANT_DOWN;
            each(&self.truth);
            self.advance();
        }
    }
}

impl ObserverStep {
    /// Starts the estimator at angle `theta_m` (encoder, rad) and speed `omega_m` (rad/s),
    /// e.g. from the backward difference of the first two measurements after a restart.
    pub fn preset(&mut self, theta_m: f64, omega_m: f64) {
        self.enc.preset(theta_m, omega_m);
    }
}

impl SpeedLoopStep {
    /// Takes over at speed `omega_m` with output `i_q_ref` (the last reference the drive
    /// used). Returns false when the selected law has no bumpless start (it then starts cold).
    pub fn preset(&mut self, omega_m: f64, i_q_ref: f64) -> bool {
        match &mut self.law {
            SpeedLaw::Pi(c) => {
                c.preset(omega_m, i_q_ref);
                true
            }
            SpeedLaw::Rst(c) => {
                c.preset(omega_m, i_q_ref);
                true
            }
            #[allow(unreachable_patterns)]
            _ => false,
        }
    }
}

impl CurrentLoopStep {
    /// Takes over from the voltage the plant is applying (`meas.u_ab_applied`), at the
    /// estimated angle and speed and with reference `iref`. Returns false when the selected
    /// law has no bumpless start.
    pub fn preset(&mut self, meas: &Measurement, est: &Estimate, iref: &CurrentRef) -> bool {
        let i = park(
            clarke(meas.i_abc[0], meas.i_abc[1], meas.i_abc[2]),
            est.theta_e,
        );
        let omega_e = self.pole_pairs * est.omega_m;
        // The applied vector is command k−1: the previous owner rotated it with its estimate
        // k−1 plus 1.5 samples of advance, i.e. with about θ̂_k + 0.5·ω_e·T_s.
        let u = park(
            AlphaBeta {
                alpha: meas.u_ab_applied[0],
                beta: meas.u_ab_applied[1],
            },
            est.theta_e + 0.5 * omega_e * self.ts,
        );
        let input = CurrentInput {
            i_d_ref: iref.i_d_ref,
            i_q_ref: iref.i_q_ref,
            i_d: i.d,
            i_q: i.q,
            omega_e,
        };
        match &mut self.law {
            CurrentLaw::Pi(c) => {
                c.preset(
                    VoltageDq {
                        u_d: u.d,
                        u_q: u.q,
                        saturated: false,
                    },
                    &input,
                );
                true
            }
            #[allow(unreachable_patterns)]
            _ => false,
        }
    }
}
