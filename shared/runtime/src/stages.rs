//! The drive's four stages (plant, observer, current loop, speed loop) on the stage API,
//! with their freshness policies. Each wraps the step function of [`crate::drive`]; the
//! policies live here, not in the host, and are tested here with synthetic inboxes.
//! See docs/architecture.md, "The cycle" and "Fault model".

use crate::config::Scenario;
use crate::drive::{CurrentLoopStep, ObserverStep, Plant, SpeedLoopStep};
use crate::messages::*;
use crate::stage::*;
use drivelab_control::motor::wrap_2pi;
use drivelab_control::observer_sensorless::ObserverMode;
use std::f64::consts::{PI, TAU};

/// Names of the built-in stages, in chain order.
pub const BUILTIN: [&str; 4] = ["plant", "observer", "current-loop", "speed-loop"];

/// The built-in stages a user's stage may replace by registering under the same name
/// (docs/architecture.md, "Replacing a built-in stage"). Not the plant: it is the drive's
/// clock and its motor, and the recorder, the fault reports and a restarted plant's rebuilt
/// samples all rest on it.
pub const REPLACEABLE: [&str; 3] = ["observer", "current-loop", "speed-loop"];

/// Builds built-in stage `name` for scenario `sc`.
/// The plant is built from the true scenario, every other stage from its
/// [`Scenario::controller_view`] (docs/architecture.md, "Model mismatch").
pub fn builtin(name: &str, sc: &Scenario) -> Option<Box<dyn Stage>> {
    if name == "plant" {
        return Some(Box::new(PlantStage::new(sc)));
    }
    let view = sc.controller_view();
    let sc = &view;
    Some(match name {
        "observer" => Box::new(ObserverStage::new(sc)),
        "current-loop" => Box::new(CurrentLoopStage::new(sc)),
        "speed-loop" => Box::new(SpeedLoopStage::new(sc)),
        _ => return None,
    })
}

/// What built-in stage `name` declares for scenario `sc` (its inputs, outputs and rate
/// divider) without building it: every run and every campaign case resolves its topology
/// first, and building the speed loop designs its controller (a search over step responses,
/// milliseconds). A unit test holds these equal to what the built stages declare.
pub fn declaration(
    name: &str,
    sc: &Scenario,
) -> Option<(&'static [InputSpec], &'static [TopicId], u64)> {
    Some(match name {
        "plant" => (PLANT_IN, PLANT_OUT, 1),
        "observer" => (OBSERVER_IN, OBSERVER_OUT, 1),
        "current-loop" => (CURRENT_IN, CURRENT_OUT, 1),
        "speed-loop" => (SPEED_IN, SPEED_OUT, u64::from(sc.rates.speed_divider)),
        _ => return None,
    })
}

// ------------------------------------------------------------------------------ plant

/// The plant: timing master. At k it applies command k−1 (held for `inverter.hold_samples`
/// when missing, then the safe state), publishes measurement k and, after publishing,
/// integrates to t_{k+1}.
pub struct PlantStage {
    /// The model.
    pub plant: Plant,
    /// The model as built (a copy made at set-up), for a rejoin after the model has moved.
    pristine: Plant,
    /// The model has stepped since it was built.
    stepped: bool,
    /// A rejoin coasted the model: from the last true state of this sample, up to that one.
    /// The host rejoins a restarted plant before its first step, and aims again at a later
    /// sample when coasting took it past the one aimed at: each aim coasts on from where
    /// the last stopped, so no aim copies the model or allocates at real-time priority.
    coasted: Option<(u64, u64)>,
}

const PLANT_IN: &[InputSpec] = &[InputSpec::latest(TopicId::Cmd, 1, 0, OnStale::Fallback)];
const PLANT_OUT: &[TopicId] = &[TopicId::Meas, TopicId::Truth];

impl PlantStage {
    /// The plant of `sc`.
    pub fn new(sc: &Scenario) -> Self {
        let plant = Plant::new(sc);
        Self {
            pristine: plant.clone(),
            plant,
            stepped: false,
            coasted: None,
        }
    }
}

impl Stage for PlantStage {
    fn name(&self) -> &'static str {
        "plant"
    }
    fn inputs(&self) -> &'static [InputSpec] {
        PLANT_IN
    }
    fn outputs(&self) -> &'static [TopicId] {
        PLANT_OUT
    }
    fn step(&mut self, k: u64, inputs: &Inbox, out: &mut Outbox) {
        self.stepped = true;
        // A missing command (None) is held, then replaced by the safe state (Plant::sample).
        out.push(Msg::Meas(self.plant.sample(k, inputs.cmd())));
        out.push(Msg::Truth(*self.plant.truth()));
    }
    fn after_publish(&mut self) {
        self.plant.advance();
    }
    fn rejoin(&mut self, k: u64, inputs: &Inbox) -> Rejoin {
        // A restarted plant resumes at sample k from its last true state as the recorder saw
        // it, the motor integrated through the downtime under the inverter's hold and safe
        // state (the launcher rebuilds those samples for the trace the same way).
        if let Some(t) = inputs.newest_truth() {
            let k0 = t.hdr.k;
            match self.coasted {
                // Aiming again, later, from the same state: on from where the last aim
                // stopped (bit for bit a coast from the start).
                Some((from, at)) if from == k0 && at <= k && !self.stepped => {
                    self.plant.coast_on(at, k, |_| {});
                }
                moved => {
                    if moved.is_some() || self.stepped {
                        self.plant = self.pristine.clone();
                        self.stepped = false;
                    }
                    self.plant.coast(t, k, |_| {});
                }
            }
            self.coasted = Some((k0, k.max(k0 + 1)));
        }
        Rejoin::Done
    }
}

// ------------------------------------------------------------------------------ observer

/// The estimate a stage falls back on without the observer's: the electrical angle of
/// `meas`'s encoder angle and `omega_m`, the last speed estimated, flagged `STALE_INPUT`.
fn encoder_fallback(meas: &Measurement, pole_pairs: f64, omega_m: f64) -> Estimate {
    Estimate {
        hdr: Header {
            k: meas.hdr.k,
            t_sample_ns: meas.hdr.t_sample_ns,
            flags: FLAG_STALE_INPUT,
            ..Default::default()
        },
        theta_e: wrap_2pi(pole_pairs * meas.theta_m_enc),
        omega_m,
    }
}

/// The observer: measurement k → estimate k. Its filter needs every sample, so when behind it
/// steps the older measurements without publishing them. Across a gap in the measurements
/// (a plant that restarted after its downtime, measurements lost) the filter cannot step:
/// the angle moved by an unknown number of turns. It seeds itself again as after a restart
/// (angle and speed from two consecutive measurements); until it has, it publishes what the
/// current loop falls back on without an estimate: the encoder angle and the last speed
/// estimate, flagged `FLAG_STALE_INPUT`.
pub struct ObserverStage {
    obs: ObserverStep,
    ts: f64,
    pole_pairs: f64,
    seed: Option<Measurement>,
    last_k: Option<u64>,
    last_omega_m: f64,
    /// Gaps in the measurements it seeded itself again after.
    pub measurement_gaps: u64,
}

const OBSERVER_IN: &[InputSpec] = &[InputSpec::trigger(TopicId::Meas, 1, OnStale::Required)];
const OBSERVER_OUT: &[TopicId] = &[TopicId::Est];

impl ObserverStage {
    /// The observer of `sc`.
    pub fn new(sc: &Scenario) -> Self {
        Self {
            obs: ObserverStep::new(sc),
            ts: sc.rates.ts(),
            pole_pairs: sc.motor_params().p(),
            seed: None,
            last_k: None,
            last_omega_m: 0.0,
            measurement_gaps: 0,
        }
    }

    /// Seeds the filter: the angle from the newest measurement, the speed from the backward
    /// difference to the next one; `NeedMore` until two consecutive ones came.
    fn seed(&mut self, m: &Measurement) -> Rejoin {
        self.last_k = Some(m.hdr.k);
        match self.seed {
            Some(s) if m.hdr.k == s.hdr.k + 1 => {
                let d = (m.theta_m_enc - s.theta_m_enc + PI).rem_euclid(TAU) - PI;
                self.obs.preset(s.theta_m_enc, d / self.ts);
                self.seed = None;
                Rejoin::Done
            }
            _ => {
                self.seed = Some(*m);
                Rejoin::NeedMore
            }
        }
    }
}

impl Stage for ObserverStage {
    fn name(&self) -> &'static str {
        "observer"
    }
    fn inputs(&self) -> &'static [InputSpec] {
        OBSERVER_IN
    }
    fn outputs(&self) -> &'static [TopicId] {
        OBSERVER_OUT
    }
    fn steps_every_sample(&self) -> bool {
        true
    }
    fn step(&mut self, _k: u64, inputs: &Inbox, out: &mut Outbox) {
        let Some(m) = inputs.meas() else { return };
        let gap = self.last_k.is_some_and(|l| m.hdr.k > l + 1);
        if gap {
            self.measurement_gaps += 1;
            self.seed = None;
        }
        if (gap || self.seed.is_some()) && self.seed(m) == Rejoin::NeedMore {
            out.push(Msg::Est(encoder_fallback(
                m,
                self.pole_pairs,
                self.last_omega_m,
            )));
            return;
        }
        self.last_k = Some(m.hdr.k);
        let e = self.obs.step(m);
        self.last_omega_m = e.omega_m;
        out.push(Msg::Est(e));
    }
    fn rejoin(&mut self, _k: u64, inputs: &Inbox) -> Rejoin {
        // After a restart: as after a gap in the measurements.
        match inputs.meas() {
            Some(m) => self.seed(m),
            None => Rejoin::NeedMore,
        }
    }
    fn diagnostic_names(&self) -> Diagnostics {
        &["measurement_gaps"]
    }
    fn diagnostics(&self, v: &mut [u64]) {
        v[0] = self.measurement_gaps;
    }
}

// ------------------------------------------------------------------------------ current loop

/// The current loop: measurement k + estimate k + the current reference of the last speed
/// sample before k → command k. Policies (real time):
/// - no estimate for 2 samples: the encoder angle of the measurement and the last speed
///   estimate; sensorless, zero voltage;
/// - no fresh current reference: the last one is held; after 2 speed periods i_q* ramps to
///   zero (full scale in 20 ms);
/// - a command made from any stale input (estimate, a held reference, or a reference the
///   speed loop held) carries `FLAG_STALE_INPUT`, so the trace shows every sample a stale
///   input reached;
/// - rejoin: its integrators are preset to the voltage the plant is applying.
pub struct CurrentLoopStage {
    ctrl: CurrentLoopStep,
    pole_pairs: f64,
    sensorless: bool,
    reference: ReferenceHold,
    last_est: Estimate,
    /// The sample of the last step: a sample the loop skipped (late, caught up) still counts
    /// toward the hold and the ramp, which are in time, not in steps.
    last_k: Option<u64>,
    /// Samples run on the encoder fallback.
    pub fallback_samples: u64,
}

/// The built-in current loop's policy for its current reference, public so that a user's
/// current loop can follow it (docs/architecture.md, "Replacing a built-in stage"): a fresh
/// reference is taken; a missing one is held and the command flagged `FLAG_STALE_INPUT`
/// (before the first came, the zero reference stands, flagged too); after two speed periods
/// without one, i_q* ramps to zero, full scale (the scenario's i_q limit) in 20 ms.
#[derive(Debug, Clone)]
pub struct ReferenceHold {
    hold_samples: u64,
    iq_ramp_per_sample: f64,
    active: CurrentRef,
    stale_samples: u64,
    /// Samples with the i_q* ramp active.
    pub ramp_samples: u64,
}

impl ReferenceHold {
    /// The policy at the rates and limits of `sc`.
    pub fn new(sc: &Scenario) -> Self {
        Self {
            hold_samples: 2 * u64::from(sc.rates.speed_divider),
            iq_ramp_per_sample: sc.i_q_max() * sc.rates.ts() / 0.02,
            active: CurrentRef::default(),
            stale_samples: 0,
            ramp_samples: 0,
        }
    }

    /// The reference in force.
    pub fn active(&self) -> &CurrentRef {
        &self.active
    }

    /// Puts `r` in force (a rejoin: the newest reference).
    pub fn set(&mut self, r: CurrentRef) {
        self.active = r;
    }

    /// Takes the fresh current reference of `inputs`, or holds the one in force and, when
    /// `ramp`, ramps its i_q* once it has been missing for two speed periods (without `ramp`,
    /// e.g. on the encoder fallback, it is held as it stands and the time does not count).
    /// `elapsed`: samples since the last step (1, or more after skipped samples: the hold
    /// and the ramp are in time, not in steps). The command's flags.
    pub fn take(&mut self, inputs: &Inbox, ramp: bool, elapsed: u64) -> u32 {
        let mut flags = 0;
        match (inputs.slot(TopicId::Iref).fresh, inputs.iref()) {
            (true, Some(r)) => {
                self.active = *r;
                self.stale_samples = 0;
                // A reference the speed loop made from a stale input (its held output) makes
                // this command one too.
                flags |= r.hdr.flags & FLAG_STALE_INPUT;
            }
            // Nothing expected yet (before the first speed sample): zero references.
            (true, None) => {}
            (false, _) => {
                flags |= FLAG_STALE_INPUT;
                if !ramp {
                    return flags;
                }
                // The ramp's samples among the ones elapsed: those past the hold.
                let before = self.stale_samples;
                self.stale_samples = before.saturating_add(elapsed);
                let steps = self
                    .stale_samples
                    .saturating_sub(before.max(self.hold_samples));
                if steps > 0 {
                    self.ramp_samples += steps;
                    let q = self.active.i_q_ref;
                    let down = self.iq_ramp_per_sample * steps as f64;
                    self.active.i_q_ref = q - q.signum() * down.min(q.abs());
                }
            }
        }
        flags
    }
}

/// Estimate stale after this many samples (one is the observer's normal lag).
pub const EST_MAX_AGE: u64 = 2;

const CURRENT_IN: &[InputSpec] = &[
    InputSpec::trigger(TopicId::Est, EST_MAX_AGE, OnStale::Fallback),
    InputSpec::latest(TopicId::Meas, 0, 0, OnStale::Required),
    InputSpec::latest(TopicId::Iref, 1, 0, OnStale::Fallback),
];
const CURRENT_OUT: &[TopicId] = &[TopicId::Cmd];

impl CurrentLoopStage {
    /// The current loop of `sc`.
    pub fn new(sc: &Scenario) -> Self {
        Self {
            ctrl: CurrentLoopStep::new(sc),
            pole_pairs: sc.motor_params().p(),
            sensorless: sc.observer.mode == ObserverMode::Sensorless,
            reference: ReferenceHold::new(sc),
            last_est: Estimate::default(),
            last_k: None,
            fallback_samples: 0,
        }
    }

    /// Samples with the i_q* ramp active.
    pub fn ramp_samples(&self) -> u64 {
        self.reference.ramp_samples
    }

    /// While the measurement says the inverter is in its safe state (no command of this
    /// loop reached it in time, or it tripped), the integrators follow the voltage it
    /// applies, as on a rejoin: the loop takes over from that voltage when its commands
    /// reach the inverter again, instead of from integrators that ran on against a motor
    /// the safe state was braking (a plant restarted after its downtime met a 5.2 A spike).
    fn track_safe_state(&mut self, meas: &Measurement, e: &Estimate) {
        if meas.hdr.flags & FLAG_SAFE_STATE != 0 {
            self.ctrl.preset(meas, e, self.reference.active());
        }
    }
}

impl Stage for CurrentLoopStage {
    fn name(&self) -> &'static str {
        "current-loop"
    }
    fn inputs(&self) -> &'static [InputSpec] {
        CURRENT_IN
    }
    fn outputs(&self) -> &'static [TopicId] {
        CURRENT_OUT
    }
    fn step(&mut self, k: u64, inputs: &Inbox, out: &mut Outbox) {
        let Some(meas) = inputs.meas() else { return };
        let elapsed = self.last_k.map_or(1, |last| k.saturating_sub(last).max(1));
        self.last_k = Some(k);
        // The reference first. On the encoder fallback (no estimate) a stale reference is
        // held as it stands, neither ramped (the speed loop, without estimates, holds its
        // output) nor reset to the last one received (which would undo a ramp under way).
        let mut flags = self.reference.take(inputs, inputs.est().is_some(), elapsed);
        let cmd = match inputs.est() {
            Some(e) => {
                self.last_est = *e;
                self.track_safe_state(meas, e);
                self.ctrl.step(meas, e, self.reference.active())
            }
            None => {
                // No estimate: the encoder angle of this measurement, the last speed estimate
                // and the reference as above.
                self.fallback_samples += 1;
                flags |= FLAG_STALE_INPUT;
                let e = encoder_fallback(meas, self.pole_pairs, self.last_est.omega_m);
                if self.sensorless {
                    // No position sensor to fall back on: command zero voltage.
                    let r = self.reference.active();
                    VoltageCommand {
                        hdr: e.hdr,
                        i_dq_ref: [r.i_d_ref, r.i_q_ref],
                        omega_ref: r.omega_ref,
                        omega_hat: self.last_est.omega_m,
                        theta_hat: self.last_est.theta_e,
                        ..Default::default()
                    }
                } else {
                    self.track_safe_state(meas, &e);
                    self.ctrl.step(meas, &e, self.reference.active())
                }
            }
        };
        let mut cmd = cmd;
        cmd.hdr.flags |= flags;
        out.push(Msg::Cmd(cmd));
    }
    fn rejoin(&mut self, _k: u64, inputs: &Inbox) -> Rejoin {
        let (Some(meas), Some(e)) = (inputs.meas(), inputs.est()) else {
            return Rejoin::NeedMore;
        };
        if let Some(r) = inputs.newest_iref() {
            self.reference.set(*r);
        }
        self.ctrl.preset(meas, e, self.reference.active());
        Rejoin::Done
    }
    fn diagnostic_names(&self) -> Diagnostics {
        &[
            "encoder_fallback_samples",
            "iq_ramp_samples",
            "kyslan_eq15_near_singular_samples",
            "kyslan_eq15_clamped_samples",
            "zeroed_commands",
        ]
    }
    fn diagnostics(&self, v: &mut [u64]) {
        let (near, clamped) = self.ctrl.singularity_counts();
        for (d, s) in v.iter_mut().zip([
            self.fallback_samples,
            self.reference.ramp_samples,
            near,
            clamped,
            self.ctrl.zeroed_commands,
        ]) {
            *d = s;
        }
    }
    fn exit_warnings(&self) -> Vec<String> {
        let (near, clamped) = self.ctrl.singularity_counts();
        if near == 0 {
            return Vec::new();
        }
        vec![format!(
            "for {near} samples the measured i_d approached the uncontrollable i_d of Kyslan eq. (15); a1 + a2*i_d was clamped in {clamped} of them"
        )]
    }
}

// ------------------------------------------------------------------------------ speed loop

/// The speed loop: every N-th estimate → current reference. Policies (real time): without
/// estimates it holds its output (integrator frozen), re-published at each speed sample the
/// drive reaches; after a restart it takes over from the last reference the current loop
/// used (the command topic's history) at the present speed estimate. A speed reference
/// from an outer stage (topic `wref`) replaces the scenario's speed profile.
pub struct SpeedLoopStage {
    ctrl: SpeedLoopStep,
    divider: u64,
    last_out: Option<CurrentRef>,
    design_warnings: Vec<String>,
    /// Speed samples whose output was held (no estimate).
    pub held_samples: u64,
    /// Speed samples run with ω* = 0 because the outer speed reference was lost.
    pub wref_lost_samples: u64,
}

/// Periods of the outer loop after which its lost speed reference is replaced by 0.
pub const WREF_MAX_AGE: u64 = 2;

/// True when an outer loop's reference computed at sample `w_k` is the one the speed loop
/// follows at sample k: computed before k and at most [`WREF_MAX_AGE`] of its producer's
/// periods (`divider` samples) older than the one expected at k. Beyond that the loop is
/// down as far as the drive is concerned (the speed loop has replaced ω* by 0), and the
/// trace's θ_m* column is empty, as before the loop's first output.
pub fn wref_followed(k: u64, w_k: u64, divider: u64) -> bool {
    crate::stage::expected_index(k, 1, divider)
        .is_some_and(|want| w_k < k && want.saturating_sub(w_k) <= WREF_MAX_AGE * divider.max(1))
}

const SPEED_IN: &[InputSpec] = &[
    InputSpec::trigger(TopicId::Est, 1, OnStale::Fallback),
    InputSpec::latest(TopicId::Wref, 1, 0, OnStale::Fallback),
    InputSpec::rejoin(TopicId::Cmd),
];
const SPEED_OUT: &[TopicId] = &[TopicId::Iref];

impl SpeedLoopStage {
    /// The speed loop of `sc`.
    pub fn new(sc: &Scenario) -> Self {
        Self {
            ctrl: SpeedLoopStep::new(sc),
            divider: u64::from(sc.rates.speed_divider),
            last_out: None,
            design_warnings: if sc.nonlinear() {
                crate::drive::set_point_warnings(sc)
            } else {
                Vec::new()
            },
            held_samples: 0,
            wref_lost_samples: 0,
        }
    }
}

impl Stage for SpeedLoopStage {
    fn name(&self) -> &'static str {
        "speed-loop"
    }
    fn inputs(&self) -> &'static [InputSpec] {
        SPEED_IN
    }
    fn outputs(&self) -> &'static [TopicId] {
        SPEED_OUT
    }
    fn divider(&self) -> u64 {
        self.divider
    }
    fn step(&mut self, k: u64, inputs: &Inbox, out: &mut Outbox) {
        match inputs.est() {
            Some(e) => {
                // An outer loop's speed reference replaces the profile. If it stops coming
                // for more than 2 of its periods, the drive is brought to standstill (ω* = 0,
                // shaped by the speed loop's prefilter) rather than left running on the last
                // value.
                let slot = inputs.slot(TopicId::Wref);
                let (w, stale) = match inputs.newest_wref() {
                    None => (None, false),
                    Some(_) if !slot.fresh && slot.age > WREF_MAX_AGE => (Some(0.0), true),
                    Some(w) => (Some(w.omega_ref), false),
                };
                if let Some(mut r) = self.ctrl.step_with(e, w) {
                    if stale {
                        r.hdr.flags |= FLAG_STALE_INPUT;
                        self.wref_lost_samples += 1;
                    }
                    self.last_out = Some(r);
                    out.push(Msg::Iref(r));
                }
            }
            None => {
                // Hold the output, integrator frozen; before the first one (a real-time
                // start or a restart whose first estimate is late) that is the zero
                // reference the current loop starts from. Either way the step publishes,
                // as every step must.
                let mut r = self.last_out.unwrap_or_default();
                r.hdr.k = k;
                r.hdr.flags |= FLAG_STALE_INPUT;
                self.held_samples += 1;
                self.last_out = Some(r);
                out.push(Msg::Iref(r));
            }
        }
    }
    fn rejoin(&mut self, _k: u64, inputs: &Inbox) -> Rejoin {
        if let Some(c) = inputs.newest_cmd() {
            if let Some(e) = inputs.est() {
                self.ctrl.preset(e.omega_m, c.i_dq_ref[1]);
            }
            // Held while no estimate comes: the reference in force, not the zero one.
            self.last_out = Some(CurrentRef {
                hdr: Header {
                    k: c.hdr.k,
                    t_sample_ns: c.hdr.t_sample_ns,
                    ..Default::default()
                },
                omega_ref: c.omega_ref,
                i_d_ref: c.i_dq_ref[0],
                i_q_ref: c.i_dq_ref[1],
            });
        }
        Rejoin::Done
    }
    fn diagnostic_names(&self) -> Diagnostics {
        &[
            "held_samples",
            "wref_lost_samples",
            "kyslan_eq15_near_singular_samples",
        ]
    }
    fn diagnostics(&self, v: &mut [u64]) {
        for (d, s) in v.iter_mut().zip([
            self.held_samples,
            self.wref_lost_samples,
            self.ctrl.near_singular_samples,
        ]) {
            *d = s;
        }
    }
    fn warnings(&self) -> Vec<String> {
        self.design_warnings.clone()
    }
    fn exit_warnings(&self) -> Vec<String> {
        if self.ctrl.near_singular_samples == 0 {
            return Vec::new();
        }
        vec![format!(
            "{} speed samples had an i_d set-point near the uncontrollable i_d of Kyslan eq. (15)",
            self.ctrl.near_singular_samples
        )]
    }
}

/// Runs every built-in stage of `sc` in one thread on the same host as the bus (the
/// `inprocess` clock) and returns the trace.
pub fn run_inprocess(sc: &Scenario) -> Vec<crate::trace::TraceRow> {
    try_run_inprocess(sc).expect("in-process chain")
}

/// [`run_inprocess`], with an error where the run cannot be done (no memory for its trace).
pub fn try_run_inprocess(sc: &Scenario) -> anyhow::Result<Vec<crate::trace::TraceRow>> {
    try_run_inprocess_until(sc, || false)
}

/// [`try_run_inprocess`] that ends early, with the samples done so far, once `stop` says so
/// (asked once per sample; the launcher passes its stop-signal flag).
pub fn try_run_inprocess_until(
    sc: &Scenario,
    stop: impl Fn() -> bool + Send + 'static,
) -> anyhow::Result<Vec<crate::trace::TraceRow>> {
    let stages: Vec<Box<dyn Stage>> = BUILTIN
        .iter()
        .map(|n| builtin(n, sc).ok_or_else(|| anyhow::anyhow!("no built-in stage {n}")))
        .collect::<anyhow::Result<_>>()?;
    run_stages_until(sc, stages, stop)
}

/// An empty vector with room for `n` entries, or an error naming `what` and the size when
/// the memory cannot be had (instead of an abort).
fn fallible_vec<T>(n: usize, what: &str) -> anyhow::Result<Vec<T>> {
    let mut v = Vec::new();
    v.try_reserve_exact(n).map_err(|_| {
        anyhow::anyhow!(
            "cannot allocate {what}: {n} entries of {} bytes ({:.1} GB); the in-process clock holds the whole run in memory, --clock lockstep streams it to disk",
            std::mem::size_of::<T>(),
            n as f64 * std::mem::size_of::<T>() as f64 / 1e9
        )
    })?;
    Ok(v)
}

/// Runs `stages` (chain order, the source first) in one thread and returns the trace.
pub fn run_stages_inprocess(
    sc: &Scenario,
    stages: Vec<Box<dyn Stage>>,
) -> anyhow::Result<Vec<crate::trace::TraceRow>> {
    run_stages_until(sc, stages, || false)
}

/// [`run_stages_inprocess`] until `stop` says so: the trace of the samples done.
fn run_stages_until(
    sc: &Scenario,
    stages: Vec<Box<dyn Stage>>,
    stop: impl Fn() -> bool + Send + 'static,
) -> anyhow::Result<Vec<crate::trace::TraceRow>> {
    use crate::host::{Host, HostConfig, Local, Pacing};
    let producers: Vec<(TopicId, u64, bool)> = stages
        .iter()
        .flat_map(|s| {
            s.outputs()
                .iter()
                .map(|t| (*t, s.divider(), true))
                .collect::<Vec<_>>()
        })
        .collect();
    let wref_divider = producers
        .iter()
        .find(|p| p.0 == TopicId::Wref)
        .map_or(1, |p| p.1);
    let n = sc.samples();
    // Every output of every stage, one per period of its stage, and each topic's end marker:
    // reserved whole, so that the loop's sends never reallocate.
    let messages: u64 = producers.iter().map(|p| n / p.1.max(1) + 2).sum();
    let mut host = Host::new(
        stages,
        &producers,
        Local {
            sent: fallible_vec(messages as usize + 16, "the in-process run's messages")?,
        },
        HostConfig {
            warm_up: false,
            // Up to a kill of the plant for good, where the drive ends.
            ..HostConfig::for_scenario(sc, Pacing::Lockstep, sc.samples_made())
        },
    );
    host.arm_spares(|name| builtin(name, sc))?;
    host.stop_when(stop);
    let reserved = host.transport.sent.capacity();
    host.run()?;
    debug_assert_eq!(
        host.transport.sent.capacity(),
        reserved,
        "the in-process run's sends outgrew what was reserved for them"
    );
    let ts = sc.rates.ts();
    let mut truth: Vec<Option<PlantTruth>> = fallible_vec(n as usize, "the in-process trace")?;
    truth.resize(n as usize, None);
    let mut rows = fallible_vec(n as usize, "the in-process trace")?;
    let mut wref: Option<SpeedRef> = None;
    for m in &host.transport.sent {
        match m {
            Msg::Truth(x) if !x.hdr.is_end() && x.hdr.k < n => truth[x.hdr.k as usize] = Some(*x),
            Msg::Wref(w) if !w.hdr.is_end() && !w.hdr.is_absent() && m.is_finite() => {
                wref = Some(*w)
            }
            Msg::Cmd(c) if !c.hdr.is_end() && c.hdr.k < n => {
                if let Some(x) = truth[c.hdr.k as usize] {
                    // An absent or unusable command (a drop or corrupt fault) leaves the row
                    // without one, as the recorder of a bus run does.
                    let c = if c.hdr.is_absent() || !m.is_finite() {
                        crate::drive::missing_command(c.hdr.k)
                    } else {
                        *c
                    };
                    let mut r = crate::drive::trace_row(ts, &x, &c);
                    // The outer reference in use at k: the newest computed before k, while
                    // the speed loop still follows it.
                    r.theta_m_ref = wref
                        .filter(|w| wref_followed(c.hdr.k, w.hdr.k, wref_divider))
                        .map(|w| w.theta_m_ref);
                    rows.push(r);
                }
            }
            _ => {}
        }
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::InProcessDrive;

    fn scenario(name: &str) -> Scenario {
        let path = format!("{}/../../scenarios/{name}.toml", env!("CARGO_MANIFEST_DIR"));
        Scenario::from_toml(&std::fs::read_to_string(&path).unwrap(), &path).unwrap()
    }

    fn short(name: &str, seconds: f64) -> Scenario {
        let mut sc = scenario(name);
        sc.duration_s = seconds;
        sc
    }

    /// The step functions called directly, in the cycle's order, with no host in between.
    fn direct(sc: &Scenario) -> Vec<crate::trace::TraceRow> {
        let mut d = InProcessDrive::new(sc);
        (0..sc.samples()).map(|k| d.cycle(k)).collect()
    }

    /// The host's loop and every built-in stage allocate nothing per sample: a run twice as
    /// long makes exactly as many allocations as the shorter one (its set-up's, and its
    /// trace's and messages' buffers, one allocation each whatever the length).
    #[test]
    fn the_in_process_chain_allocates_nothing_per_sample() {
        for name in [
            "kyslan-pi",
            "kyslan-nl",
            "low-rst-sensorless",
            "miyajima-polar-400rpm",
        ] {
            let count = |seconds: f64| {
                let sc = short(name, seconds);
                let (rows, n) =
                    crate::alloc_count::allocations_during(|| try_run_inprocess(&sc).unwrap());
                assert_eq!(rows.len() as u64, sc.samples(), "{name}");
                n
            };
            let (short_run, long_run) = (count(0.05), count(0.1));
            assert!(
                short_run > 0,
                "{name}: the set-up allocates, so the count works"
            );
            assert_eq!(
                long_run, short_run,
                "{name}: allocations in 0.1 s against 0.05 s"
            );
        }
    }

    #[test]
    fn a_declaration_is_what_the_built_stage_declares() {
        // Every shipped scenario, and one with another speed divider.
        let dir = format!("{}/../../scenarios", env!("CARGO_MANIFEST_DIR"));
        let mut scenarios: Vec<Scenario> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|x| x == "toml"))
            .map(|p| {
                let text = std::fs::read_to_string(&p).unwrap();
                Scenario::from_toml(&text, &p.display().to_string()).unwrap()
            })
            .collect();
        assert!(
            scenarios.len() >= 10,
            "{} scenarios in {dir}",
            scenarios.len()
        );
        let mut other = scenario("kyslan-pi");
        other.rates.speed_divider = 4;
        scenarios.push(other);
        for sc in &scenarios {
            for name in BUILTIN {
                let s = builtin(name, sc).unwrap();
                let (inputs, outputs, divider) = declaration(name, sc).unwrap();
                assert_eq!(s.name(), name);
                assert_eq!(s.inputs(), inputs, "{name} in {}", sc.name);
                assert_eq!(s.outputs(), outputs, "{name} in {}", sc.name);
                assert_eq!(s.divider(), divider, "{name} in {}", sc.name);
            }
        }
        let (_, _, divider) = declaration("speed-loop", scenarios.last().unwrap()).unwrap();
        assert_eq!(divider, 4);
        assert!(declaration("no-such-stage", &scenarios[0]).is_none());
    }

    /// `--duration` shorter than the scenario: what it schedules after the end is left out
    /// and named, and the samples that are run are the full run's first ones, bit for bit.
    #[test]
    fn a_shortened_run_is_the_start_of_the_full_one() {
        let path = format!(
            "{}/../../scenarios/kyslan-pi.toml",
            env!("CARGO_MANIFEST_DIR")
        );
        let text = std::fs::read_to_string(&path).unwrap()
            + "[plant_drift]\nr_factor = [{ t_s = 0.0, value = 1.0 }, { t_s = 0.08, value = 1.3 }]\n\n"
            + "[[sensor_fault]]\nkind = \"encoder-stuck\"\nat_s = 0.01\nduration_s = 0.005\n\n"
            + "[[sensor_fault]]\nkind = \"current-offset\"\nphase = \"a\"\nat_s = 0.05\namps = 0.5\n\n"
            + "[[inject]]\nkind = \"drop\"\ntarget = \"cmd\"\nat_s = 0.06\ncount = 2\n";
        let full = Scenario::from_toml(&text, &path).unwrap();
        assert_eq!(full.duration_s, 0.1);
        // Only the duration changed: the late items make the scenario invalid.
        let mut bare = full.clone();
        bare.duration_s = 0.03;
        assert!(bare.validate().is_err());
        let mut sc = full.clone();
        let cut = sc.set_duration(0.03);
        assert_eq!(
            cut,
            [
                "load.torque_nm[0] at 0.04 s",
                "inject[0] drop:cmd@0.06:2",
                "sensor_fault[1] current-offset:a@0.05:0.5",
            ]
        );
        sc.validate().unwrap();
        // Kept: the step at 0.02 s, the stuck encoder at 0.01 s, the drift profile whole.
        assert_eq!(sc.reference.i_d_a.len(), 1);
        assert_eq!(sc.sensor_fault.len(), 1);
        assert_eq!(sc.plant_drift, full.plant_drift);
        let (a, b) = (direct(&full), direct(&sc));
        assert_eq!(b.len(), 300);
        for (x, y) in a.iter().zip(&b) {
            assert_eq!(format!("{x:?}"), format!("{y:?}"), "k = {}", x.k);
        }
        // A step at the new end itself comes after the last sample (0.0399 s).
        let mut at_end = full.clone();
        assert_eq!(at_end.set_duration(0.04)[0], "load.torque_nm[0] at 0.04 s");
        // Longer than the scenario: nothing left out.
        let mut long = full.clone();
        assert!(long.set_duration(0.2).is_empty());
        assert_eq!((long.inject.len(), long.sensor_fault.len()), (1, 2));
        long.validate().unwrap();
    }

    #[test]
    fn the_host_gives_the_same_trace_as_direct_calls() {
        for (name, secs) in [
            ("kyslan-pi", 0.06),
            ("low-rst-sensorless", 0.3),
            ("miyajima-polar-400rpm", 0.02),
        ] {
            let sc = short(name, secs);
            let a = direct(&sc);
            let b = run_inprocess(&sc);
            assert_eq!(a.len(), b.len(), "{name}");
            for (x, y) in a.iter().zip(&b) {
                // Bit for bit: compare the CSV rows' bits, NaN included.
                assert_eq!(format!("{x:?}"), format!("{y:?}"), "{name} at k = {}", x.k);
            }
        }
    }

    fn meas(k: u64, theta_m_enc: f64) -> Measurement {
        Measurement {
            hdr: Header {
                k,
                ..Default::default()
            },
            theta_m_enc,
            ..Default::default()
        }
    }

    fn est(k: u64, omega_m: f64) -> Estimate {
        Estimate {
            hdr: Header {
                k,
                ..Default::default()
            },
            theta_e: 0.3,
            omega_m,
        }
    }

    fn iref(k: u64, i_q_ref: f64) -> CurrentRef {
        CurrentRef {
            hdr: Header {
                k,
                ..Default::default()
            },
            omega_ref: 50.0,
            i_d_ref: 0.0,
            i_q_ref,
        }
    }

    fn cmd_of(out: &Outbox) -> VoltageCommand {
        match out.get(TopicId::Cmd) {
            Some(Msg::Cmd(c)) => *c,
            other => panic!("no command: {other:?}"),
        }
    }

    #[test]
    fn current_loop_without_estimate_controls_on_the_encoder_angle() {
        let sc = scenario("kyslan-pi");
        let mut s = CurrentLoopStage::new(&sc);
        let mut ib = Inbox::default();
        ib.put(Msg::Meas(meas(10, 0.1)));
        ib.put(Msg::Est(est(10, 42.0)));
        ib.put(Msg::Iref(iref(0, 1.0)));
        let mut out = Outbox::default();
        s.step(10, &ib, &mut out);
        assert_eq!(cmd_of(&out).hdr.flags & FLAG_STALE_INPUT, 0);
        assert_eq!(cmd_of(&out).omega_hat, 42.0);
        // Sample 11: the estimate is stale. The command uses θ_e = p·θ_m,enc and the last ω̂.
        let mut ib = Inbox::default();
        ib.put(Msg::Meas(meas(11, 0.2)));
        ib.put(Msg::Est(est(10, 42.0)));
        ib.set_stale(TopicId::Est, 1);
        ib.put(Msg::Iref(iref(0, 1.0)));
        let mut out = Outbox::default();
        s.step(11, &ib, &mut out);
        let c = cmd_of(&out);
        assert_ne!(c.hdr.flags & FLAG_STALE_INPUT, 0);
        assert_eq!(c.omega_hat, 42.0);
        let p = sc.motor_params().p();
        assert!((c.theta_hat - wrap_2pi(p * 0.2)).abs() < 1e-12, "{c:?}");
        assert_eq!(s.fallback_samples, 1);
    }

    #[test]
    fn sensorless_current_loop_without_estimate_commands_zero_voltage() {
        let sc = scenario("low-rst-sensorless");
        let mut s = CurrentLoopStage::new(&sc);
        let mut ib = Inbox::default();
        ib.put(Msg::Meas(meas(5, 0.2)));
        ib.set_stale(TopicId::Est, 3);
        let mut out = Outbox::default();
        s.step(5, &ib, &mut out);
        let c = cmd_of(&out);
        assert_eq!(c.u_ab, [0.0, 0.0]);
        assert_ne!(c.hdr.flags & FLAG_STALE_INPUT, 0);
    }

    #[test]
    fn current_loop_ramps_i_q_ref_to_zero_after_two_speed_periods() {
        let sc = scenario("kyslan-pi");
        let n = u64::from(sc.rates.speed_divider);
        let ramp = sc.i_q_max() * sc.rates.ts() / 0.02;
        let mut s = CurrentLoopStage::new(&sc);
        let step = |s: &mut CurrentLoopStage, k: u64, fresh: bool| {
            let mut ib = Inbox::default();
            ib.put(Msg::Meas(meas(k, 0.0)));
            ib.put(Msg::Est(est(k, 0.0)));
            ib.put(Msg::Iref(iref(0, 1.0)));
            if !fresh {
                ib.set_stale(TopicId::Iref, 1);
            }
            let mut out = Outbox::default();
            s.step(k, &ib, &mut out);
            cmd_of(&out)
        };
        // A reference that was due and has not come, before any came: the zero reference
        // stands, flagged (the command differs from one made with the reference).
        let mut ib = Inbox::default();
        ib.put(Msg::Meas(meas(1, 0.0)));
        ib.put(Msg::Est(est(1, 0.0)));
        ib.set_stale(TopicId::Iref, 1);
        let mut out = Outbox::default();
        CurrentLoopStage::new(&sc).step(1, &ib, &mut out);
        assert_eq!(cmd_of(&out).i_dq_ref[1], 0.0);
        assert_ne!(cmd_of(&out).hdr.flags & FLAG_STALE_INPUT, 0);
        // Not yet due (before the speed loop's first sample): the zero reference, unflagged.
        let mut ib = Inbox::default();
        ib.put(Msg::Meas(meas(0, 0.0)));
        ib.put(Msg::Est(est(0, 0.0)));
        // (What the host gives when nothing is expected yet: fresh, with no value.)
        ib.slots[TopicId::Iref.index()].fresh = true;
        let mut out = Outbox::default();
        CurrentLoopStage::new(&sc).step(0, &ib, &mut out);
        assert_eq!(cmd_of(&out).i_dq_ref[1], 0.0);
        assert_eq!(cmd_of(&out).hdr.flags & FLAG_STALE_INPUT, 0);
        assert_eq!(step(&mut s, 1, true).i_dq_ref[1], 1.0);
        // Held for 2 speed periods (flagged: a stale input).
        for k in 2..2 + 2 * n {
            let c = step(&mut s, k, false);
            assert_eq!(c.i_dq_ref[1], 1.0, "k = {k}");
            assert_ne!(c.hdr.flags & FLAG_STALE_INPUT, 0, "k = {k}");
        }
        assert_eq!(s.ramp_samples(), 0);
        // Then a ramp of i_max·T_s/20 ms per sample, flagged.
        let c = step(&mut s, 2 + 2 * n, false);
        assert!((c.i_dq_ref[1] - (1.0 - ramp)).abs() < 1e-12, "{c:?}");
        assert_ne!(c.hdr.flags & FLAG_STALE_INPUT, 0);
        let c = step(&mut s, 3 + 2 * n, false);
        assert!((c.i_dq_ref[1] - (1.0 - 2.0 * ramp)).abs() < 1e-12, "{c:?}");
        assert_eq!(s.ramp_samples(), 2);
        // A sample on the encoder fallback (no estimate) during the ramp holds i_q* where
        // the ramp left it: neither ramped further nor put back to the last reference
        // received (the dead speed loop's 1.0).
        let mut ib = Inbox::default();
        ib.put(Msg::Meas(meas(4 + 2 * n, 0.0)));
        ib.put(Msg::Est(est(3 + 2 * n, 0.0)));
        ib.set_stale(TopicId::Est, 1);
        ib.put(Msg::Iref(iref(0, 1.0)));
        ib.set_stale(TopicId::Iref, 1);
        let mut out = Outbox::default();
        s.step(4 + 2 * n, &ib, &mut out);
        let c = cmd_of(&out);
        assert!((c.i_dq_ref[1] - (1.0 - 2.0 * ramp)).abs() < 1e-12, "{c:?}");
        assert_ne!(c.hdr.flags & FLAG_STALE_INPUT, 0);
        assert_eq!((s.ramp_samples(), s.fallback_samples), (2, 1));
        // With the estimate back the ramp goes on from there.
        let c = step(&mut s, 5 + 2 * n, false);
        assert!((c.i_dq_ref[1] - (1.0 - 3.0 * ramp)).abs() < 1e-12, "{c:?}");
        assert_eq!(s.ramp_samples(), 3);
        // Two samples the loop skipped (late, caught up) count: the ramp is in time.
        let c = step(&mut s, 8 + 2 * n, false);
        assert!((c.i_dq_ref[1] - (1.0 - 6.0 * ramp)).abs() < 1e-12, "{c:?}");
        assert_eq!(s.ramp_samples(), 6);
        // A fresh reference ends it, unflagged.
        let c = step(&mut s, 9 + 2 * n, true);
        assert_eq!(c.i_dq_ref[1], 1.0);
        assert_eq!(c.hdr.flags & FLAG_STALE_INPUT, 0);
        // A fresh reference the speed loop held (flagged) flags the command.
        let mut ib = Inbox::default();
        ib.put(Msg::Meas(meas(10 + 2 * n, 0.0)));
        ib.put(Msg::Est(est(10 + 2 * n, 0.0)));
        let mut held = iref(0, 1.0);
        held.hdr.flags = FLAG_STALE_INPUT;
        ib.put(Msg::Iref(held));
        let mut out = Outbox::default();
        s.step(10 + 2 * n, &ib, &mut out);
        assert_ne!(cmd_of(&out).hdr.flags & FLAG_STALE_INPUT, 0);
    }

    #[test]
    fn speed_loop_without_estimate_holds_its_output_flagged() {
        let sc = scenario("kyslan-pi");
        let n = u64::from(sc.rates.speed_divider);
        let mut s = SpeedLoopStage::new(&sc);
        let mut ib = Inbox::default();
        ib.put(Msg::Est(est(0, 0.0)));
        let mut out = Outbox::default();
        s.step(0, &ib, &mut out);
        let Some(Msg::Iref(first)) = out.get(TopicId::Iref).copied() else {
            panic!("no output")
        };
        let mut ib = Inbox::default();
        ib.put(Msg::Est(est(0, 0.0)));
        ib.set_stale(TopicId::Est, 1);
        let mut out = Outbox::default();
        s.step(n, &ib, &mut out);
        let Some(Msg::Iref(held)) = out.get(TopicId::Iref).copied() else {
            panic!("no held output")
        };
        assert_eq!(held.hdr.k, n);
        assert_ne!(held.hdr.flags & FLAG_STALE_INPUT, 0);
        assert_eq!(
            (held.i_q_ref, held.omega_ref),
            (first.i_q_ref, first.omega_ref)
        );
        assert_eq!(s.held_samples, 1);
    }

    /// In real time the first estimate may come late (a loaded machine, a restart): the
    /// step still publishes, the zero reference, flagged (a step that published nothing
    /// stopped its host).
    #[test]
    fn speed_loop_without_any_estimate_yet_publishes_the_zero_reference_flagged() {
        let sc = scenario("kyslan-pi");
        let mut s = SpeedLoopStage::new(&sc);
        let mut ib = Inbox::default();
        ib.set_stale(TopicId::Est, 3);
        let mut out = Outbox::default();
        s.step(70, &ib, &mut out);
        let Some(Msg::Iref(r)) = out.get(TopicId::Iref).copied() else {
            panic!("no output")
        };
        assert_eq!(r.hdr.k, 70);
        assert_eq!(r.hdr.flags, FLAG_STALE_INPUT);
        assert_eq!((r.omega_ref, r.i_d_ref, r.i_q_ref), (0.0, 0.0, 0.0));
        assert_eq!(s.held_samples, 1);
    }

    #[test]
    fn speed_loop_follows_an_outer_speed_reference() {
        let sc = scenario("kyslan-pi");
        let mut s = SpeedLoopStage::new(&sc);
        let mut ib = Inbox::default();
        ib.put(Msg::Est(est(0, 0.0)));
        ib.put(Msg::Wref(SpeedRef {
            omega_ref: 12.5,
            ..Default::default()
        }));
        let mut out = Outbox::default();
        s.step(0, &ib, &mut out);
        let Some(Msg::Iref(r)) = out.get(TopicId::Iref).copied() else {
            panic!("no output")
        };
        assert_eq!(r.omega_ref, 12.5);
    }

    #[test]
    fn speed_loop_stops_the_drive_when_the_outer_reference_is_lost() {
        let sc = scenario("kyslan-pi");
        let mut s = SpeedLoopStage::new(&sc);
        let w = SpeedRef {
            omega_ref: 12.5,
            ..Default::default()
        };
        let step = |s: &mut SpeedLoopStage, age: u64| {
            let mut ib = Inbox::default();
            ib.put(Msg::Est(est(0, 0.0)));
            ib.put(Msg::Wref(w));
            if age > 0 {
                ib.set_stale(TopicId::Wref, age);
            }
            let mut out = Outbox::default();
            s.step(0, &ib, &mut out);
            match out.get(TopicId::Iref) {
                Some(Msg::Iref(r)) => *r,
                other => panic!("{other:?}"),
            }
        };
        // Up to WREF_MAX_AGE periods late: the last value, unflagged.
        let r = step(&mut s, WREF_MAX_AGE);
        assert_eq!(r.omega_ref, 12.5);
        assert_eq!(r.hdr.flags & FLAG_STALE_INPUT, 0);
        // Beyond: ω* = 0, flagged and counted.
        let r = step(&mut s, WREF_MAX_AGE + 1);
        assert_eq!(r.omega_ref, 0.0);
        assert_ne!(r.hdr.flags & FLAG_STALE_INPUT, 0);
        assert_eq!(s.wref_lost_samples, 1);
    }

    #[test]
    fn plant_holds_a_missing_command_then_goes_to_the_safe_state() {
        let sc = scenario("kyslan-pi");
        let hold = u64::from(sc.inverter.hold_samples);
        let mut s = PlantStage::new(&sc);
        let mut ib = Inbox::default();
        let mut out = Outbox::default();
        s.step(0, &ib, &mut out);
        ib.put(Msg::Cmd(VoltageCommand {
            u_ab: [5.0, 0.0],
            ..Default::default()
        }));
        ib.set_stale(TopicId::Cmd, 1);
        for k in 1..=hold + 1 {
            let mut out = Outbox::default();
            s.step(k, &ib, &mut out);
            let Some(Msg::Meas(m)) = out.get(TopicId::Meas).copied() else {
                panic!()
            };
            assert_ne!(m.hdr.flags & FLAG_STALE_CMD, 0, "k = {k}");
            let safe = m.hdr.flags & FLAG_SAFE_STATE != 0;
            assert_eq!(safe, k > hold, "k = {k}");
            s.after_publish();
        }
    }

    /// Runs the four stages directly up to sample `k_end` (exclusive) and returns them with
    /// the last messages, as a running drive would have them.
    #[allow(clippy::type_complexity)]
    fn run_to(
        sc: &Scenario,
        k_end: u64,
    ) -> (
        PlantStage,
        CurrentLoopStage,
        Vec<(Measurement, Estimate, CurrentRef, VoltageCommand)>,
    ) {
        let mut plant = PlantStage::new(sc);
        let mut obs = ObserverStage::new(sc);
        let mut cur = CurrentLoopStage::new(sc);
        let mut spd = SpeedLoopStage::new(sc);
        let (mut cmd, mut iref) = (None::<VoltageCommand>, CurrentRef::default());
        let mut log = Vec::new();
        for k in 0..k_end {
            let mut ib = Inbox::default();
            if let Some(c) = cmd {
                ib.put(Msg::Cmd(c));
            }
            let mut out = Outbox::default();
            plant.step(k, &ib, &mut out);
            let Some(Msg::Meas(m)) = out.get(TopicId::Meas).copied() else {
                panic!()
            };
            let mut ib = Inbox::default();
            ib.put(Msg::Meas(m));
            let mut out = Outbox::default();
            obs.step(k, &ib, &mut out);
            let Some(Msg::Est(e)) = out.get(TopicId::Est).copied() else {
                panic!()
            };
            let mut ib = Inbox::default();
            ib.put(Msg::Meas(m));
            ib.put(Msg::Est(e));
            if k > 0 {
                ib.put(Msg::Iref(iref));
            }
            let mut out = Outbox::default();
            cur.step(k, &ib, &mut out);
            let c = cmd_of(&out);
            let used = iref;
            if k.is_multiple_of(spd.divider()) {
                let mut ib = Inbox::default();
                ib.put(Msg::Est(e));
                let mut out = Outbox::default();
                spd.step(k, &ib, &mut out);
                if let Some(Msg::Iref(r)) = out.get(TopicId::Iref).copied() {
                    iref = r;
                }
            }
            plant.after_publish();
            cmd = Some(c);
            log.push((m, e, used, c));
        }
        (plant, cur, log)
    }

    #[test]
    fn a_restored_plant_continues_from_the_last_true_state() {
        let sc = scenario("kyslan-pi");
        // 35 ms: on the 70 rad/s plateau, currents and voltage far from zero.
        let (running, _, _) = run_to(&sc, 351);
        let last = *running.plant.truth();
        assert_eq!(last.hdr.k, 350);
        let mut restarted = PlantStage::new(&sc);
        restarted.plant.restore(&last);
        // Its first sample (the command is missing after a restart: held) reproduces the
        // state and the voltage of the last one...
        let m = restarted.plant.sample(350, None);
        let t = *restarted.plant.truth();
        assert_eq!(
            (t.i_dq, t.omega_m, t.theta_m),
            (last.i_dq, last.omega_m, last.theta_m)
        );
        assert_eq!(t.u_ab_applied, last.u_ab_applied);
        assert_eq!(m.hdr.flags, FLAG_STALE_CMD);
        // ...and integrates to the state the running plant reached. Tolerance: the restored
        // angle is the unwrapped one wrapped again, equal to the model's up to rounding
        // (~1e-15 rad), which reaches the currents through sin/cos at the same relative size;
        // 1e-12 is a thousand times that.
        restarted.plant.advance();
        let (a, b) = (running.plant.x, restarted.plant.x);
        for (x, y) in [
            (a.i_d, b.i_d),
            (a.i_q, b.i_q),
            (a.omega_m, b.omega_m),
            (a.theta_m, b.theta_m),
        ] {
            assert!((x - y).abs() <= 1e-12 * x.abs().max(1.0), "{a:?} vs {b:?}");
        }
        // A plant that is not restored starts from rest.
        let mut cold = PlantStage::new(&sc);
        cold.plant.sample(350, None);
        assert_eq!(cold.plant.truth().omega_m, 0.0);
    }

    #[test]
    fn the_downtime_rebuilt_equals_a_plant_that_lost_its_commands_at_the_same_sample() {
        use crate::messages::FLAG_PLANT_DOWN;
        let sc = scenario("kyslan-pi");
        // Run A: the plant stays up, but no command reaches it after sample 350: it holds
        // the last one for hold_samples, then applies its safe state.
        let (mut up, _, _) = run_to(&sc, 351);
        // (run_to has integrated past sample 350 already.)
        let last = *up.plant.truth();
        let mut a = Vec::new();
        for k in 351..800 {
            up.plant.sample(k, None);
            a.push(*up.plant.truth());
            up.plant.advance();
        }
        // Run B: the plant died after sample 350; restarted at 800, it coasts from there.
        let mut restarted = PlantStage::new(&sc);
        let mut b = Vec::new();
        restarted.plant.coast(&last, 800, |t| b.push(*t));
        assert_eq!(b.len(), a.len());
        // Equal up to the rounding of the restored angle (see the test above: 1e-12).
        let close = |x: f64, y: f64| (x - y).abs() <= 1e-12 * x.abs().max(1.0);
        for (x, y) in a.iter().zip(&b) {
            assert_eq!(y.hdr.flags, x.hdr.flags | FLAG_PLANT_DOWN, "k {}", x.hdr.k);
            assert_eq!(x.hdr.k, y.hdr.k);
            for (p, q) in [
                (x.i_dq[0], y.i_dq[0]),
                (x.i_dq[1], y.i_dq[1]),
                (x.omega_m, y.omega_m),
                (x.theta_m, y.theta_m),
                (x.u_ab_applied[0], y.u_ab_applied[0]),
                (x.u_ab_applied[1], y.u_ab_applied[1]),
            ] {
                assert!(close(p, q), "k {}: {x:?} vs {y:?}", x.hdr.k);
            }
        }
        // The safe state came after the hold, as in a live inverter.
        let hold = u64::from(sc.inverter.hold_samples);
        assert_eq!(
            b[hold as usize].hdr.flags & FLAG_SAFE_STATE,
            FLAG_SAFE_STATE
        );
        assert_eq!(b[hold as usize - 1].hdr.flags & FLAG_SAFE_STATE, 0);
        // The plant stage's rejoin at 800 leaves the model where run A is at 800, however
        // often it has to aim again.
        let mut ib = Inbox::default();
        ib.put(Msg::Truth(last));
        let mut s = PlantStage::new(&sc);
        s.rejoin(790, &ib);
        s.rejoin(800, &ib);
        let (p, q) = (s.plant.x, up.plant.x);
        for (x, y) in [
            (p.i_d, q.i_d),
            (p.i_q, q.i_q),
            (p.omega_m, q.omega_m),
            (p.theta_m, q.theta_m),
        ] {
            assert!(close(x, y), "{p:?} vs {q:?}");
        }
        // Rebuilding from the same truth gives the same model bit for bit (what the
        // launcher relies on to fill the trace).
        let mut again = PlantStage::new(&sc);
        again.plant.coast(&last, 800, |_| {});
        assert_eq!(again.plant.x, s.plant.x);
    }

    /// A restarted plant's rejoin, before its first step and again at a later sample each
    /// time coasting took it past the one aimed at, runs at real-time priority: it allocates
    /// nothing (the scenario's load steps make a copy of the model allocate), and three aims
    /// leave the model where one coast of a fresh one to the last sample does, bit for bit.
    #[test]
    fn a_restarted_plants_rejoin_allocates_nothing() {
        let sc = scenario("kyslan-pi");
        let (up, _, _) = run_to(&sc, 351);
        let last = *up.plant.truth();
        let mut ib = Inbox::default();
        ib.put(Msg::Truth(last));
        let mut s = PlantStage::new(&sc);
        // The host aims again at later samples when coasting took it past one.
        let (r, allocations) = crate::alloc_count::allocations_during(|| {
            [s.rejoin(700, &ib), s.rejoin(760, &ib), s.rejoin(800, &ib)]
        });
        assert_eq!(
            (r, allocations),
            ([Rejoin::Done; 3], 0),
            "rejoin, allocations"
        );
        let mut by_hand = PlantStage::new(&sc);
        by_hand.plant.coast(&last, 800, |_| {});
        assert_eq!(s.plant.x, by_hand.plant.x, "three aims against one coast");
        assert_eq!(s.plant.truth(), by_hand.plant.truth());
    }

    #[test]
    fn a_restarted_current_loop_takes_over_without_a_voltage_bump() {
        let sc = scenario("kyslan-pi");
        // 35 ms: on the 70 rad/s plateau with i_d* = -1.6 A, before the load at 40 ms.
        let k = 350;
        let (_, _, log) = run_to(&sc, k + 1);
        let (m, e, r, running) = log[k as usize];
        let prev = log[k as usize - 1].3;
        let mut fresh = CurrentLoopStage::new(&sc);
        let mut ib = Inbox::default();
        ib.put(Msg::Meas(m));
        ib.put(Msg::Est(e));
        ib.put(Msg::Iref(r));
        assert_eq!(fresh.rejoin(k, &ib), Rejoin::Done);
        let mut out = Outbox::default();
        fresh.step(k, &ib, &mut out);
        let took_over = cmd_of(&out);
        let norm = |u: [f64; 2]| libm::hypot(u[0], u[1]);
        let bump = norm([
            took_over.u_dq[0] - running.u_dq[0],
            took_over.u_dq[1] - running.u_dq[1],
        ]);
        // The preset reproduces the voltage being applied (command k-1); the running
        // controller has moved on by one sample since. Bound: that one-sample change.
        let step = norm([
            running.u_dq[0] - prev.u_dq[0],
            running.u_dq[1] - prev.u_dq[1],
        ]);
        eprintln!(
            "bump {bump:.3e} V, one-sample change {step:.3e} V, |u| {:.2} V",
            norm(running.u_dq)
        );
        assert!(
            bump <= 2.0 * step + 1e-9 * norm(running.u_dq),
            "bump {bump} V > 2 × {step} V"
        );
        // A cold start instead (no rejoin) bumps by far more.
        let mut cold = CurrentLoopStage::new(&sc);
        let mut out = Outbox::default();
        cold.step(k, &ib, &mut out);
        let c = cmd_of(&out);
        let cold_bump = norm([c.u_dq[0] - running.u_dq[0], c.u_dq[1] - running.u_dq[1]]);
        assert!(
            cold_bump > 10.0 * bump.max(1e-6),
            "cold {cold_bump} V vs rejoin {bump} V"
        );
    }

    #[test]
    fn a_restarted_speed_loop_takes_over_from_the_reference_in_use() {
        let sc = scenario("kyslan-pi");
        let k = 350;
        let (_, _, log) = run_to(&sc, k + 1);
        let (_, e, r, c) = log[k as usize];
        let mut fresh = SpeedLoopStage::new(&sc);
        let mut ib = Inbox::default();
        ib.put(Msg::Est(e));
        ib.put(Msg::Cmd(c));
        assert_eq!(fresh.rejoin(k, &ib), Rejoin::Done);
        let mut out = Outbox::default();
        fresh.step(k, &ib, &mut out);
        let Some(Msg::Iref(out_r)) = out.get(TopicId::Iref).copied() else {
            panic!()
        };
        // On the plateau the running loop's i_q* hardly moves between speed samples: the
        // taken-over output continues it (within 1 % of the current limit).
        let lim = sc.i_q_max();
        assert!(
            (out_r.i_q_ref - r.i_q_ref).abs() < 0.01 * lim,
            "took over at {} A, running {} A",
            out_r.i_q_ref,
            r.i_q_ref
        );
    }

    /// Restarted with its first estimate late, the speed loop holds the reference in force
    /// (the current loop's last command's), not the zero one of a cold start.
    #[test]
    fn a_restarted_speed_loop_without_an_estimate_holds_the_reference_in_force() {
        let sc = scenario("kyslan-pi");
        // After the load step at 40 ms: a torque current to hold.
        let k = 450;
        let (_, _, log) = run_to(&sc, k + 1);
        let (_, _, _, c) = log[k as usize];
        assert!(c.i_dq_ref[1].abs() > 0.1, "{c:?}");
        let mut fresh = SpeedLoopStage::new(&sc);
        let mut ib = Inbox::default();
        ib.put(Msg::Cmd(c));
        ib.set_stale(TopicId::Est, 2);
        assert_eq!(fresh.rejoin(k, &ib), Rejoin::Done);
        let mut out = Outbox::default();
        fresh.step(k, &ib, &mut out);
        let Some(Msg::Iref(r)) = out.get(TopicId::Iref).copied() else {
            panic!("no output")
        };
        assert_eq!(
            (r.i_d_ref, r.i_q_ref, r.omega_ref),
            (c.i_dq_ref[0], c.i_dq_ref[1], c.omega_ref)
        );
        assert_eq!((r.hdr.k, r.hdr.flags), (k, FLAG_STALE_INPUT));
    }

    #[test]
    fn across_a_gap_in_the_measurements_the_observer_seeds_itself_again() {
        let sc = scenario("kyslan-pi");
        let mut s = ObserverStage::new(&sc);
        let w = 20.0;
        let dtheta = w * sc.rates.ts();
        let est = |s: &mut ObserverStage, k: u64, theta: f64| {
            let mut ib = Inbox::default();
            ib.put(Msg::Meas(meas(k, theta)));
            let mut out = Outbox::default();
            s.step(k, &ib, &mut out);
            let Some(Msg::Est(e)) = out.get(TopicId::Est).copied() else {
                panic!("no estimate at {k}")
            };
            e
        };
        for k in 0..200 {
            est(&mut s, k, 1.0 + dtheta * k as f64);
        }
        assert_eq!(s.measurement_gaps, 0);
        // 400 samples later the angle moved by an unknown number of turns: not stepped across
        // as one sample (that gave −1544 rad/s), but the encoder angle and the last speed,
        // flagged as a fallback, then a new seed from two consecutive measurements.
        let (k, theta) = (600, 2.5);
        let e = est(&mut s, k, theta);
        assert_eq!(s.measurement_gaps, 1);
        assert_eq!(e.hdr.flags, FLAG_STALE_INPUT);
        assert!((e.theta_e - wrap_2pi(sc.motor_params().p() * theta)).abs() < 1e-12);
        assert!((e.omega_m - w).abs() < 0.05 * w, "ω̂ {} held", e.omega_m);
        let e = est(&mut s, k + 1, theta + dtheta);
        assert_eq!(e.hdr.flags, 0);
        assert!((e.omega_m - w).abs() < 0.05 * w, "ω̂ {} vs {w}", e.omega_m);
        assert_eq!(s.measurement_gaps, 1);
    }

    #[test]
    fn observer_rejoins_from_two_consecutive_measurements() {
        let sc = scenario("kyslan-pi");
        let mut s = ObserverStage::new(&sc);
        let mut ib = Inbox::default();
        ib.put(Msg::Meas(meas(100, 1.0)));
        assert_eq!(s.rejoin(100, &ib), Rejoin::NeedMore);
        // Not consecutive: a new seed.
        ib.put(Msg::Meas(meas(102, 1.0)));
        assert_eq!(s.rejoin(102, &ib), Rejoin::NeedMore);
        let dtheta = 0.001;
        ib.put(Msg::Meas(meas(103, 1.0 + dtheta)));
        assert_eq!(s.rejoin(103, &ib), Rejoin::Done);
        let mut out = Outbox::default();
        ib.put(Msg::Meas(meas(104, 1.0 + 2.0 * dtheta)));
        s.step(104, &ib, &mut out);
        let Some(Msg::Est(e)) = out.get(TopicId::Est).copied() else {
            panic!()
        };
        let w = dtheta / sc.rates.ts();
        assert!((e.omega_m - w).abs() < 0.05 * w, "ω̂ {} vs {w}", e.omega_m);
    }
}
