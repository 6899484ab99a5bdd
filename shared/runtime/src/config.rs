//! Scenario files (TOML): motor, rates, controllers, references, load, placement.
//!
//! Every field has a unit in its name and a validation rule in [`Scenario::validate`]; unknown
//! keys are rejected so that a typo never silently falls back to a default.

use drivelab_control::motor::MotorParams;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// A complete scenario.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    /// Short name, e.g. `kyslan-pi`.
    pub name: String,
    /// One-line purpose.
    #[serde(default)]
    pub purpose: String,
    /// Paper figure it reproduces, if any.
    #[serde(default)]
    pub reproduces: String,
    /// Pass/fail checks of the run's summary figures (`[[expect]]` tables), checked by the
    /// launcher after the run.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub expect: Vec<ExpectSpec>,
    /// Run length, s.
    pub duration_s: f64,
    /// Motor: a preset name plus optional overrides.
    pub motor: MotorSpec,
    /// Inverter model.
    #[serde(default)]
    pub inverter: InverterSpec,
    /// Mechanics model.
    #[serde(default)]
    pub mechanics: MechanicsSpec,
    /// Sample rates.
    #[serde(default)]
    pub rates: Rates,
    /// Sensor models.
    #[serde(default)]
    pub sensors: Sensors,
    /// Sensor faults applied by the plant by sample index (`[[sensor_fault]]` tables, or
    /// `--fault encoder-stuck@…` / `current-offset:…`); none by default.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub sensor_fault: Vec<crate::sensor_faults::SensorFault>,
    /// Observer settings.
    #[serde(default)]
    pub observer: ObserverSpec,
    /// Current-loop settings.
    #[serde(default)]
    pub current_loop: CurrentLoopSpec,
    /// Speed-loop settings.
    #[serde(default)]
    pub speed_loop: SpeedLoopSpec,
    /// Reference profiles.
    #[serde(default)]
    pub reference: References,
    /// Load-torque profile.
    #[serde(default)]
    pub load: Load,
    /// Core and priority per service.
    #[serde(default)]
    pub placement: Placement,
    /// How the plant waits for its deadlines.
    #[serde(default)]
    pub timing: Timing,
    /// Parameters of user-written stages, one table per stage name (`[stages.NAME]`); a
    /// stage's `rate_hz` sets its rate (it must divide the sample rate).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub stages: BTreeMap<String, toml::Table>,
    /// The topology: which stages each process hosts, its core and priority. Empty: the
    /// four-process layout with `[placement]`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub process: Vec<crate::topology::ProcessSpec>,
    /// Bus faults the stage hosts inject by sample index (`[[inject]]` tables, written by the
    /// launcher from `--fault delay:…`, `drop:…`, `corrupt:…`; see [`crate::inject`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub inject: Vec<crate::inject::Inject>,
    /// The motor parameters the controllers and observers design with, when they differ from
    /// the plant's (`[model]`); none: the true ones. See docs/architecture.md, "Model
    /// mismatch".
    #[serde(default, skip_serializing_if = "ModelSpec::is_nominal")]
    pub model: ModelSpec,
    /// Drift of the plant's true R and ψ over the run (`[plant_drift]`); none by default.
    #[serde(default, skip_serializing_if = "PlantDrift::is_none")]
    pub plant_drift: PlantDrift,
}

/// `[model]`: the controller's view of the motor, each parameter as a value (SI unit in the
/// name) or as a factor of the true one, never both; absent ones are the true values.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelSpec {
    /// Stator resistance, Ω.
    pub r_ohm: Option<f64>,
    /// Stator resistance as a factor of the true one.
    pub r_factor: Option<f64>,
    /// d-axis inductance, H.
    pub l_d_h: Option<f64>,
    /// d-axis inductance as a factor of the true one.
    pub ld_factor: Option<f64>,
    /// q-axis inductance, H.
    pub l_q_h: Option<f64>,
    /// q-axis inductance as a factor of the true one.
    pub lq_factor: Option<f64>,
    /// PM flux, Wb.
    pub psi_pm_wb: Option<f64>,
    /// PM flux as a factor of the true one.
    pub psi_factor: Option<f64>,
    /// Inertia, kg·m².
    pub j_kgm2: Option<f64>,
    /// Inertia as a factor of the true one.
    pub j_factor: Option<f64>,
    /// Viscous friction, N·m·s/rad.
    pub b_nms: Option<f64>,
    /// Viscous friction as a factor of the true one.
    pub b_factor: Option<f64>,
}

/// Bounds of a `[model]` factor, and of a value as a multiple of the true one.
pub const MODEL_FACTOR_RANGE: (f64, f64) = (0.1, 10.0);

impl ModelSpec {
    /// True when no parameter is given: the controllers design with the plant's own.
    pub fn is_nominal(&self) -> bool {
        *self == Self::default()
    }

    /// The controller's parameters from the true ones `m`; the error names the field.
    pub fn apply(&self, m: &MotorParams) -> Result<MotorParams, String> {
        let (lo, hi) = MODEL_FACTOR_RANGE;
        let one = |name: &str, fname: &str, truth: f64, v: Option<f64>, f: Option<f64>| match (v, f)
        {
            (Some(_), Some(_)) => Err(format!("model: give {name} or {fname}, not both")),
            (Some(v), None) => {
                if v.is_finite() && v > 0.0 && v >= lo * truth && v <= hi * truth.max(1e-3) {
                    Ok(v)
                } else {
                    Err(format!(
                            "model.{name} = {v} must be finite, > 0 and within [{lo}, {hi}] × the true {truth}"
                        ))
                }
            }
            (None, Some(f)) => {
                if f.is_finite() && (lo..=hi).contains(&f) {
                    Ok(f * truth)
                } else {
                    Err(format!(
                        "model.{fname} = {f} must be finite and within [{lo}, {hi}]"
                    ))
                }
            }
            (None, None) => Ok(truth),
        };
        Ok(MotorParams {
            r_ohm: one("r_ohm", "r_factor", m.r_ohm, self.r_ohm, self.r_factor)?,
            l_d_h: one("l_d_h", "ld_factor", m.l_d_h, self.l_d_h, self.ld_factor)?,
            l_q_h: one("l_q_h", "lq_factor", m.l_q_h, self.l_q_h, self.lq_factor)?,
            psi_pm_wb: one(
                "psi_pm_wb",
                "psi_factor",
                m.psi_pm_wb,
                self.psi_pm_wb,
                self.psi_factor,
            )?,
            j_kgm2: one("j_kgm2", "j_factor", m.j_kgm2, self.j_kgm2, self.j_factor)?,
            b_nms: one("b_nms", "b_factor", m.b_nms, self.b_nms, self.b_factor)?,
            ..*m
        })
    }
}

/// One point of a drift profile: from `t_s` on the factor moves linearly to the next point's.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DriftPoint {
    /// Time, s.
    pub t_s: f64,
    /// Factor of the true (nominal) parameter.
    pub value: f64,
}

/// `[plant_drift]`: the plant's true R and ψ as factors of the motor's, piecewise linear in
/// time (held at the first point's value before it and at the last one's after it).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlantDrift {
    /// Resistance factor profile (a temperature rise).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub r_factor: Vec<DriftPoint>,
    /// PM flux factor profile.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub psi_factor: Vec<DriftPoint>,
}

impl PlantDrift {
    /// True when nothing drifts.
    pub fn is_none(&self) -> bool {
        self.r_factor.is_empty() && self.psi_factor.is_empty()
    }
}

/// Value of a piecewise-linear drift profile at time t (1 when empty). No allocation.
pub fn drift_at(points: &[DriftPoint], t: f64) -> f64 {
    let Some(first) = points.first() else {
        return 1.0;
    };
    if t <= first.t_s {
        return first.value;
    }
    for w in points.windows(2) {
        let (a, b) = (w[0], w[1]);
        if t < b.t_s {
            return a.value + (b.value - a.value) * (t - a.t_s) / (b.t_s - a.t_s);
        }
    }
    points[points.len() - 1].value
}

/// The longest run, s.
pub const MAX_DURATION_S: f64 = 3600.0;

/// A drift point may lie after the run's end: it sets the slope up to the end (a run
/// shortened with `--duration` keeps the profile it had).
fn check_drift(name: &str, points: &[DriftPoint]) -> Result<(), String> {
    let (lo, hi) = MODEL_FACTOR_RANGE;
    let mut last = f64::NEG_INFINITY;
    for (i, s) in points.iter().enumerate() {
        check(
            s.t_s.is_finite() && s.t_s >= 0.0 && s.t_s <= MAX_DURATION_S,
            || {
                format!(
                    "{name}[{i}].t_s = {} must be within [0, {MAX_DURATION_S}] s",
                    s.t_s
                )
            },
        )?;
        check(s.t_s > last, || {
            format!(
                "{name}[{i}].t_s = {} must be later than the point before",
                s.t_s
            )
        })?;
        check(s.value.is_finite() && (lo..=hi).contains(&s.value), || {
            format!(
                "{name}[{i}].value = {} must be finite and within [{lo}, {hi}]",
                s.value
            )
        })?;
        last = s.t_s;
    }
    check(points.len() <= 1000, || {
        format!("{name} has more than 1000 points")
    })
}

/// One `[[expect]]` table: `check = "FIGURE OP LIMIT"`, e.g. `"peak_current_a <= 8"` or
/// `"faults.*.speed_recovered_ms <= 200"`, and why it matters. The launcher parses and
/// checks it against `summary.json`; a failed one makes `drivelab run` exit with code 3.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExpectSpec {
    /// `FIGURE OP LIMIT`.
    pub check: String,
    /// Why it matters (shown in the reports).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub note: String,
}

/// How the plant (timing master) waits for each sample instant in real time.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Timing {
    /// Sleep with clock_nanosleep until this long before the deadline, then spin on the clock
    /// to the deadline, µs (0 = sleep all the way). Spinning trades CPU for wake-up jitter.
    pub plant_spin_us: f64,
    /// Wake-up mechanism between the services: "futex" (default: a futex word per topic in a
    /// shared segment of the bus, ~3 µs per hop here) or "iceoryx2" (the event service, a
    /// Unix datagram socket underneath, ~6-8 µs per hop here).
    pub wake: crate::bus::WakeKind,
    /// CPU wake-up latency request held while a real-time drive runs, µs (a PM QoS request
    /// on /dev/cpu_dma_latency, as cyclictest makes; the kernel drops it when the launcher
    /// exits), or "none". Default 0: idle CPUs do not enter deep idle states.
    pub cpu_latency_us: CpuLatency,
    /// Start the real-time schedule on the plant's CPU's scheduler tick: as far past a whole
    /// millisecond of CLOCK_MONOTONIC as that tick (read from /proc/timer_list; on a whole
    /// millisecond where it cannot be read, where the tick falls on most kernels). At a rate
    /// whose period divides a millisecond and a tick period of whole milliseconds (CONFIG_HZ
    /// 100, 250 or 1000), every tick then expires with a deadline and is served in the
    /// plant's own timer interrupt, instead of interrupting a sample on its own (on the
    /// measured VM that cost the sample 16 µs). Default true; false starts anywhere, as
    /// cyclictest does (docs/architecture.md, "The tick and the samples").
    pub tick_aligned: bool,
}

impl Default for Timing {
    fn default() -> Self {
        Self {
            plant_spin_us: 0.0,
            wake: crate::bus::WakeKind::Futex,
            cpu_latency_us: CpuLatency::Us(0),
            tick_aligned: true,
        }
    }
}

/// `[timing] cpu_latency_us`: a request in µs, or none.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CpuLatency {
    /// Hold a request of this many µs.
    Us(u32),
    /// Make no request.
    None,
}

impl Serialize for CpuLatency {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            CpuLatency::Us(v) => s.serialize_u32(*v),
            CpuLatency::None => s.serialize_str("none"),
        }
    }
}

impl<'de> Deserialize<'de> for CpuLatency {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Raw {
            N(i64),
            S(String),
        }
        let bad = || {
            serde::de::Error::custom(
                "cpu_latency_us must be a whole number of µs in 0..=1000000 or \"none\"",
            )
        };
        match Raw::deserialize(d).map_err(|_| bad())? {
            Raw::N(n) if (0..=1_000_000).contains(&n) => Ok(CpuLatency::Us(n as u32)),
            Raw::S(s) if s == "none" => Ok(CpuLatency::None),
            _ => Err(bad()),
        }
    }
}

/// Motor selection.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MotorSpec {
    /// Preset name (see [`MotorParams::PRESETS`]).
    pub preset: Option<String>,
    /// Overrides (SI units, names as in [`MotorParams`]).
    pub r_ohm: Option<f64>,
    /// d-axis inductance override, H.
    pub l_d_h: Option<f64>,
    /// q-axis inductance override, H.
    pub l_q_h: Option<f64>,
    /// Pole pairs override.
    pub pole_pairs: Option<u32>,
    /// PM flux override, Wb.
    pub psi_pm_wb: Option<f64>,
    /// Inertia override, kg·m².
    pub j_kgm2: Option<f64>,
    /// Viscous friction override, N·m·s/rad.
    pub b_nms: Option<f64>,
    /// Current limit override, A.
    pub i_max_a: Option<f64>,
    /// Rated speed override, rad/s.
    pub omega_rated_rad_s: Option<f64>,
    /// Rated torque override, N·m.
    pub t_rated_nm: Option<f64>,
}

impl MotorSpec {
    /// Resolves the preset and overrides into parameters.
    pub fn resolve(&self) -> Result<MotorParams, String> {
        let base = match &self.preset {
            Some(n) => MotorParams::preset(n).ok_or_else(|| {
                format!(
                    "motor.preset: unknown motor '{n}' (known: {})",
                    MotorParams::PRESETS.join(", ")
                )
            })?,
            None => {
                let need = |v: Option<f64>, n: &str| {
                    v.ok_or_else(|| format!("motor.{n} is required when motor.preset is not given"))
                };
                MotorParams {
                    r_ohm: need(self.r_ohm, "r_ohm")?,
                    l_d_h: need(self.l_d_h, "l_d_h")?,
                    l_q_h: need(self.l_q_h, "l_q_h")?,
                    pole_pairs: self
                        .pole_pairs
                        .ok_or("motor.pole_pairs is required when motor.preset is not given")?,
                    psi_pm_wb: need(self.psi_pm_wb, "psi_pm_wb")?,
                    j_kgm2: need(self.j_kgm2, "j_kgm2")?,
                    b_nms: self.b_nms.unwrap_or(0.0),
                    i_max_a: need(self.i_max_a, "i_max_a")?,
                    omega_rated_rad_s: need(self.omega_rated_rad_s, "omega_rated_rad_s")?,
                    t_rated_nm: need(self.t_rated_nm, "t_rated_nm")?,
                }
            }
        };
        let m = MotorParams {
            r_ohm: self.r_ohm.unwrap_or(base.r_ohm),
            l_d_h: self.l_d_h.unwrap_or(base.l_d_h),
            l_q_h: self.l_q_h.unwrap_or(base.l_q_h),
            pole_pairs: self.pole_pairs.unwrap_or(base.pole_pairs),
            psi_pm_wb: self.psi_pm_wb.unwrap_or(base.psi_pm_wb),
            j_kgm2: self.j_kgm2.unwrap_or(base.j_kgm2),
            b_nms: self.b_nms.unwrap_or(base.b_nms),
            i_max_a: self.i_max_a.unwrap_or(base.i_max_a),
            omega_rated_rad_s: self.omega_rated_rad_s.unwrap_or(base.omega_rated_rad_s),
            t_rated_nm: self.t_rated_nm.unwrap_or(base.t_rated_nm),
        };
        check_motor(&m)?;
        m.validate()?;
        Ok(m)
    }
}

/// The range of each motor parameter, with its unit: `(name, value, lowest allowed (None:
/// above 0), highest, unit)`. Far beyond any motor a drive of this kind runs, so that only
/// nonsense (a typo, a unit slip, a huge number) is refused.
fn motor_ranges(m: &MotorParams) -> [(&'static str, f64, Option<f64>, f64, &'static str); 9] {
    [
        // Each floor lies far below any real machine's figure (a micro-motor's flux linkage
        // is about 1e-4 Wb, a large machine's resistance milliohms): what is below is a slip
        // (a unit, an exponent) that would divide the designs by nearly zero.
        ("r_ohm", m.r_ohm, Some(1e-6), 1e3, "Ω"),
        ("l_d_h", m.l_d_h, Some(1e-9), 10.0, "H"),
        ("l_q_h", m.l_q_h, Some(1e-9), 10.0, "H"),
        ("psi_pm_wb", m.psi_pm_wb, Some(1e-6), 100.0, "Wb"),
        // Generous: a rotor held still (a locked-rotor test) is modelled by a huge inertia;
        // 1e-10 kg·m² (0.001 g·cm²) is about the rotor of the smallest micro-motors, so
        // what is below is a slip (a unit, an exponent), not a motor.
        ("j_kgm2", m.j_kgm2, Some(1e-10), 1e9, "kg·m²"),
        ("b_nms", m.b_nms, Some(0.0), 1e3, "N·m·s/rad"),
        ("i_max_a", m.i_max_a, Some(1e-3), 1e5, "A"),
        (
            "omega_rated_rad_s",
            m.omega_rated_rad_s,
            Some(1e-3),
            1e5,
            "rad/s",
        ),
        ("t_rated_nm", m.t_rated_nm, Some(1e-6), 1e6, "N·m"),
    ]
}

/// Checks the resolved motor parameters against [`motor_ranges`]: a one-line error naming the
/// field, its range and unit.
fn check_motor(m: &MotorParams) -> Result<(), String> {
    for (name, v, lo, hi, unit) in motor_ranges(m) {
        let ok = v.is_finite() && v <= hi && lo.map_or(v > 0.0, |lo| v >= lo);
        check(ok, || {
            let open = lo.map_or("(0".to_string(), |lo| format!("[{lo}"));
            format!("motor.{name} = {v} must be in {open}, {hi}] {unit}")
        })?;
    }
    check((1..=64).contains(&m.pole_pairs), || {
        format!("motor.pole_pairs = {} must be in 1..=64", m.pole_pairs)
    })
}

/// What the inverter does once a stale command has been held for `hold_samples`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SafeState {
    /// All lower (or upper) switches on: zero voltage vector, active short circuit.
    ZeroVector,
    /// All switches off (coast): current flows only through the free-wheeling diodes. Model:
    /// the terminal voltage is whatever extinguishes the current within one sample, limited
    /// to the DC link's V_dc/√3 (above that the diodes conduct into the link and the current
    /// decays more slowly).
    PulseBlock,
}

/// Inverter model.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct InverterSpec {
    /// DC-bus voltage, V. The voltage vector is limited to V_dc/√3 (linear SVPWM range).
    pub v_dc_v: f64,
    /// Samples a missing command is held before the safe state.
    pub hold_samples: u32,
    /// Safe state after the hold time.
    pub safe_state: SafeState,
    /// Overcurrent trip, A: when any true phase current exceeds this in magnitude at a
    /// sample, the inverter applies its safe state from that sample on and stays there
    /// (latched, as a real inverter's hardware trip). None (the default): no trip.
    pub i_trip_a: Option<f64>,
    /// "averaged" (the default: the commanded voltage, exactly) or "switching" (carrier PWM,
    /// dead time, device drop, DC link; docs/architecture.md, "Plant realism").
    #[serde(skip_serializing_if = "InverterModel::is_averaged")]
    pub model: InverterModel,
    /// Switching only: carrier frequency, Hz; 2·f_sw/f_s must be a whole number (the samples
    /// fall on the carrier's peaks and valleys). Default: the sample rate.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub f_sw_hz: Option<f64>,
    /// Switching only: dead time, µs (>= 0, below half the switching period).
    #[serde(skip_serializing_if = "is_zero")]
    pub dead_time_us: f64,
    /// Switching only: forward drop of a conducting transistor or diode, V.
    #[serde(skip_serializing_if = "is_zero")]
    pub v_drop_v: f64,
    /// Switching only: DC-link capacitance, µF (with `r_source_ohm`; none: a stiff bus).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dc_link_c_uf: Option<f64>,
    /// Switching only: resistance of the source feeding the DC link, Ω.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub r_source_ohm: Option<f64>,
}

/// `[inverter] model`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum InverterModel {
    /// The commanded voltage vector, limited to V_dc/√3, held over the sample.
    #[default]
    Averaged,
    /// Carrier-comparison PWM with dead time, device drop and an optional DC link.
    Switching,
}

impl InverterModel {
    /// True for the default.
    pub fn is_averaged(&self) -> bool {
        *self == Self::Averaged
    }
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

impl InverterSpec {
    /// The switching inverter's parameters at sample rate `sample_hz`, when
    /// `model = "switching"`.
    pub fn pwm(&self, sample_hz: f64) -> Option<drivelab_control::inverter::PwmSpec> {
        (self.model == InverterModel::Switching).then(|| drivelab_control::inverter::PwmSpec {
            v_dc_v: self.v_dc_v,
            f_sw_hz: self.f_sw_hz.unwrap_or(sample_hz),
            dead_time_s: self.dead_time_us * 1e-6,
            v_drop_v: self.v_drop_v,
            dc_link: self.dc_link_c_uf.zip(self.r_source_ohm).map(|(c, r)| {
                drivelab_control::inverter::DcLink {
                    c_f: c * 1e-6,
                    r_source_ohm: r,
                }
            }),
        })
    }

    /// Checks the model's fields at sample rate `sample_hz`: a one-line error naming the field.
    fn check_model(&self, sample_hz: f64) -> Result<(), String> {
        match self.pwm(sample_hz) {
            None => {
                let given = [
                    ("f_sw_hz", self.f_sw_hz.is_some()),
                    ("dead_time_us", self.dead_time_us != 0.0),
                    ("v_drop_v", self.v_drop_v != 0.0),
                    ("dc_link_c_uf", self.dc_link_c_uf.is_some()),
                    ("r_source_ohm", self.r_source_ohm.is_some()),
                ];
                match given.iter().find(|(_, g)| *g) {
                    Some((f, _)) => Err(format!(
                        "inverter.{f} applies to model = \"switching\" only (the averaged inverter applies the command exactly)"
                    )),
                    None => Ok(()),
                }
            }
            Some(p) => {
                // The fields in the units given (the model's check works in seconds and farads).
                let (td, half_us) = (self.dead_time_us, 0.5e6 / p.f_sw_hz);
                if p.f_sw_hz.is_finite() && p.f_sw_hz > 0.0 {
                    check(td.is_finite() && td >= 0.0 && td < half_us, || {
                        format!("inverter.dead_time_us = {td} must be >= 0 and below half the switching period ({half_us} µs)")
                    })?;
                }
                if let Some(c) = self.dc_link_c_uf {
                    check(c.is_finite() && c > 0.0 && c <= 1e6, || {
                        format!("inverter.dc_link_c_uf = {c} must be in (0, 1e6] µF")
                    })?;
                }
                check(
                    self.dc_link_c_uf.is_some() == self.r_source_ohm.is_some(),
                    || {
                        "inverter.dc_link_c_uf and inverter.r_source_ohm go together (a DC link is a capacitor fed through a resistance)".into()
                    },
                )?;
                drivelab_control::inverter::SwitchingInverter::check(&p, 1.0 / sample_hz)
            }
        }
    }
}

impl Default for InverterSpec {
    fn default() -> Self {
        // 325 V: a rectified 230 V mains; the Kyslan paper gives no DC-bus voltage.
        Self {
            v_dc_v: 325.0,
            hold_samples: 3,
            safe_state: SafeState::ZeroVector,
            i_trip_a: None,
            model: InverterModel::Averaged,
            f_sw_hz: None,
            dead_time_us: 0.0,
            v_drop_v: 0.0,
            dc_link_c_uf: None,
            r_source_ohm: None,
        }
    }
}

/// Mechanics model.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MechanicsSpec {
    /// If set, a dynamometer holds this speed (mechanical rad/s) and eq. (3) is not integrated.
    pub prescribed_speed_rad_s: Option<f64>,
    /// Speed of the free rotor at t = 0 (mechanical rad/s, default 0): the drive catches a
    /// spinning motor (flying start), e.g. for a back-EMF observer, blind at standstill.
    pub initial_speed_rad_s: Option<f64>,
}

/// Sample rates.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Rates {
    /// Plant/current-loop sample rate, Hz (5–20 kHz for real-time runs).
    pub sample_hz: f64,
    /// The speed loop runs every `speed_divider`-th sample.
    pub speed_divider: u32,
    /// RK4 sub-steps per sample in the plant.
    pub plant_substeps: u32,
}

impl Default for Rates {
    fn default() -> Self {
        Self {
            sample_hz: 10_000.0,
            speed_divider: 10,
            plant_substeps: 4,
        }
    }
}

impl Rates {
    /// Sample time T_s, s.
    pub fn ts(&self) -> f64 {
        1.0 / self.sample_hz
    }

    /// Sample time T_s, ns (rounded).
    pub fn ts_ns(&self) -> u64 {
        (1e9 / self.sample_hz).round() as u64
    }
}

/// Sensor models (ideal by default; docs/architecture.md, "Plant realism").
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Sensors {
    /// Encoder counts per mechanical revolution; 0 = ideal (no quantisation).
    pub encoder_counts_per_rev: u32,
    /// Standard deviation of additive Gaussian noise on each phase current, A.
    pub current_noise_a: f64,
    /// Seed of the noise generator (runs are reproducible).
    pub seed: u64,
    /// Gain of each phase's current sensor (a, b, c): measured = gain·i + offset.
    #[serde(
        skip_serializing_if = "is_unit_gain",
        deserialize_with = "one_per_phase"
    )]
    pub current_gain: [f64; 3],
    /// Offset of each phase's current sensor (a, b, c), A.
    #[serde(skip_serializing_if = "is_zero3", deserialize_with = "one_per_phase")]
    pub current_offset_a: [f64; 3],
    /// ADC resolution, bits (1–24), with `adc_range_a`; none: no quantisation.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub adc_bits: Option<u32>,
    /// ADC full scale, ±A (the reading saturates there).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub adc_range_a: Option<f64>,
    /// The ADC samples the currents this long before the sample instant t_k (the carrier's
    /// peak or valley), µs, in [0, T_s).
    #[serde(skip_serializing_if = "is_zero")]
    pub adc_lead_us: f64,
    /// The encoder reports the position of this long ago, µs (0 to 16·T_s).
    #[serde(skip_serializing_if = "is_zero")]
    pub encoder_delay_us: f64,
}

impl Default for Sensors {
    fn default() -> Self {
        Self {
            encoder_counts_per_rev: 0,
            current_noise_a: 0.0,
            seed: 0,
            current_gain: [1.0; 3],
            current_offset_a: [0.0; 3],
            adc_bits: None,
            adc_range_a: None,
            adc_lead_us: 0.0,
            encoder_delay_us: 0.0,
        }
    }
}

/// Exactly three values, one per phase: the `toml` crate gives serde's fixed-size arrays the
/// first three elements of a longer array and drops the rest without a word.
fn one_per_phase<'de, D: serde::Deserializer<'de>>(d: D) -> Result<[f64; 3], D::Error> {
    let v = Vec::<f64>::deserialize(d)?;
    <[f64; 3]>::try_from(v.as_slice()).map_err(|_| {
        serde::de::Error::invalid_length(v.len(), &"three values, one per phase (a, b, c)")
    })
}

fn is_unit_gain(g: &[f64; 3]) -> bool {
    *g == [1.0; 3]
}

fn is_zero3(v: &[f64; 3]) -> bool {
    *v == [0.0; 3]
}

impl Sensors {
    /// Checks the static sensor errors at sample time `ts` against the motor's rated current
    /// `i_max`: a one-line error naming the field.
    fn check_errors(&self, ts: f64, i_max: f64) -> Result<(), String> {
        for (p, g) in self.current_gain.iter().enumerate() {
            check(g.is_finite() && (0.5..=2.0).contains(g), || {
                format!("sensors.current_gain[{p}] = {g} must be in [0.5, 2]")
            })?;
        }
        for (p, o) in self.current_offset_a.iter().enumerate() {
            check(o.is_finite() && o.abs() <= i_max, || {
                format!(
                    "sensors.current_offset_a[{p}] = {o} must be within ±motor.i_max_a = {i_max} A"
                )
            })?;
        }
        check(
            self.adc_bits.is_some() == self.adc_range_a.is_some(),
            || "sensors.adc_bits and sensors.adc_range_a go together".into(),
        )?;
        if let Some(b) = self.adc_bits {
            check((1..=24).contains(&b), || {
                format!("sensors.adc_bits = {b} must be in 1..=24")
            })?;
        }
        if let Some(r) = self.adc_range_a {
            check(r.is_finite() && r > 0.0 && r <= 1e4, || {
                format!("sensors.adc_range_a = {r} must be in (0, 10000] A")
            })?;
        }
        let lead = self.adc_lead_us;
        check(lead.is_finite() && lead >= 0.0 && lead < ts * 1e6, || {
            format!(
                "sensors.adc_lead_us = {lead} must be in [0, T_s = {} µs)",
                ts * 1e6
            )
        })?;
        let d = self.encoder_delay_us;
        check(
            d.is_finite()
                && d >= 0.0
                && d <= crate::sensor_errors::MAX_ENCODER_DELAY_SAMPLES as f64 * ts * 1e6,
            || {
                format!(
                    "sensors.encoder_delay_us = {d} must be in [0, {}·T_s = {} µs]",
                    crate::sensor_errors::MAX_ENCODER_DELAY_SAMPLES,
                    crate::sensor_errors::MAX_ENCODER_DELAY_SAMPLES as f64 * ts * 1e6
                )
            },
        )?;
        Ok(())
    }
}

/// Observer settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ObserverSpec {
    /// Group delay of the 2nd-order Bessel speed filter (Low eq. 10), s.
    pub speed_filter_tau_s: f64,
    /// Position source: "encoder" (default), "sensorless" (the minimal-order αβ observer of
    /// Low eqs 11-17 closes the drive) or "monitor" (encoder for control, the observer runs
    /// beside it and is the trace's theta_hat). See `observer_sensorless`.
    pub mode: drivelab_control::observer_sensorless::ObserverMode,
    /// Time constant τ_o of the sensorless observer's pole λ = e^{-T_s/τ_o}, s.
    pub pole_tau_s: f64,
    /// Sensorless observer model: "truncated" (Low eq. 13, default) or "exact".
    pub discretisation: drivelab_control::observer_sensorless::Discretisation,
    /// Initial estimate of the sensorless observer, degrees electrical (the rotor starts at
    /// θ_e = 0, so this is the initial angle error).
    pub initial_angle_error_deg: f64,
}

impl Default for ObserverSpec {
    fn default() -> Self {
        Self {
            speed_filter_tau_s: 1e-4,
            mode: drivelab_control::observer_sensorless::ObserverMode::Encoder,
            pole_tau_s: 1e-3,
            discretisation: drivelab_control::observer_sensorless::Discretisation::Truncated,
            initial_angle_error_deg: 0.0,
        }
    }
}

/// Current-loop controller selection.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CurrentController {
    /// d/q PI with decoupling and back-EMF feed-forward.
    Pi,
    /// Kyslan et al. 2015: eqs (28)–(29) with the compensation (9)–(10); needs
    /// `speed_loop.controller = "nonlinear"`.
    Nonlinear,
    /// Low et al. 1998: RST per axis by pole placement (3rd-order ITAE for i_q, 2nd-order
    /// for i_d, `itae_omega_rad_s`), see `control::rst`.
    Rst,
    /// Miyajima et al. section IV: polar inputs (V_a, δ), C_21 (i_q via V_a) and C_12 (i_d
    /// via δ) with CDM gains rescheduled every sample, see `control::polar`. SPMSM only.
    Polar,
    /// Miyajima et al. section III, conventional: V_a held at V_amax, i_q via the voltage
    /// phase only (flux weakening). SPMSM only.
    VoltagePhase,
    /// Miyajima et al. section III, proposed: the phase controller plus the voltage-amplitude
    /// controller that stops flux strengthening (i_d > 0) without a mode switch. SPMSM only.
    PolarFw,
}

/// Current-loop settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CurrentLoopSpec {
    /// Controller.
    pub controller: CurrentController,
    /// Closed-loop time constant τ_c of the PI design, s.
    pub tau_c_s: f64,
    /// Decoupling and back-EMF feed-forward.
    pub decoupling: bool,
    /// RST only: ITAE natural frequency ω_n of the current loops, rad/s (default 0.3/T_s).
    pub itae_omega_rad_s: Option<f64>,
    /// voltage-phase and polar-fw only: real part of the phase loop's poles, rad/s
    /// (default −600, Miyajima et al. section III-C).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub polar_sigma_delta_rad_s: Option<f64>,
    /// polar-fw only: real part of the amplitude loop's poles, rad/s (default −300).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub polar_sigma_v_rad_s: Option<f64>,
    /// polar only: "paper" (CDM on the delay-free plant, default) or "predict" (the same
    /// CDM polynomials, with the current one sample ahead predicted by the model).
    #[serde(skip_serializing_if = "drivelab_control::control::cdm::CdmDelay::is_paper")]
    pub cdm_delay: drivelab_control::control::cdm::CdmDelay,
    /// polar only: τ_21 in samples (default 10, eq. 36).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cdm_tau21_samples: Option<f64>,
    /// polar only: weight β of i_q* in C_21's proportional term (default 1: a PI on the error).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cdm_setpoint_weight: Option<f64>,
    /// Dead-time compensation: each phase's reference gets sign(i_x)·(t_d·f_sw·V_dc + v_drop)
    /// from the measured current's sign (needs `inverter.model = "switching"`).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub dead_time_comp: bool,
}

impl Default for CurrentLoopSpec {
    fn default() -> Self {
        Self {
            controller: CurrentController::Pi,
            tau_c_s: 2.5e-4,
            decoupling: true,
            itae_omega_rad_s: None,
            polar_sigma_delta_rad_s: None,
            polar_sigma_v_rad_s: None,
            cdm_delay: drivelab_control::control::cdm::CdmDelay::Paper,
            cdm_tau21_samples: None,
            cdm_setpoint_weight: None,
            dead_time_comp: false,
        }
    }
}

/// Speed-loop controller selection.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SpeedController {
    /// PI by the symmetrical optimum with prefilter.
    Pi,
    /// Kyslan et al. 2015: the outer law of eqs (27), (30)–(31); needs
    /// `current_loop.controller = "nonlinear"`.
    Nonlinear,
    /// Low et al. 1998: RST by pole placement, 3rd-order ITAE including the speed filter
    /// (`itae_omega_rad_s`), see `control::rst`.
    Rst,
    /// No speed control: forwards i_d* and i_q* from `reference.i_d_a` and
    /// `reference.i_q_a` (current-loop studies at a prescribed speed).
    CurrentReference,
}

/// Speed-loop settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SpeedLoopSpec {
    /// Controller.
    pub controller: SpeedController,
    /// Design target: time to first reach the set-point after a step, s.
    pub rise_time_s: f64,
    /// Limit on i_q*, A; defaults to the motor's i_max_a.
    pub i_q_max_a: Option<f64>,
    /// RST only: ITAE natural frequency ω_n of the speed loop, rad/s (default: a tenth of
    /// the current loops', at most 0.2/T_w).
    pub itae_omega_rad_s: Option<f64>,
    /// Nonlinear only: "continuous" (the paper's dummy system, default) or "sampled" (the
    /// poles placed on the sampled loop as it runs, see `control::nonlinear`).
    #[serde(
        skip_serializing_if = "drivelab_control::control::nonlinear::NlPlacement::is_continuous"
    )]
    pub nl_poles: drivelab_control::control::nonlinear::NlPlacement,
}

impl Default for SpeedLoopSpec {
    fn default() -> Self {
        Self {
            controller: SpeedController::Pi,
            rise_time_s: 8e-3,
            i_q_max_a: None,
            itae_omega_rad_s: None,
            nl_poles: drivelab_control::control::nonlinear::NlPlacement::Continuous,
        }
    }
}

/// A step of a piecewise-constant profile.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Step {
    /// From this time on, s.
    pub t_s: f64,
    /// The value (unit given by the profile).
    pub value: f64,
}

/// Reference profiles (piecewise constant; value 0 before the first step).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct References {
    /// Speed reference steps, mechanical rad/s.
    #[serde(default)]
    pub speed_rad_s: Vec<Step>,
    /// d-axis current reference steps, A.
    #[serde(default)]
    pub i_d_a: Vec<Step>,
    /// q-axis current reference steps, A (only with `speed_loop.controller =
    /// "current-reference"`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub i_q_a: Vec<Step>,
}

/// Load-torque profile and what kind of machine the motor drives.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Load {
    /// Load torque steps, N·m (for `fan`: the torque at `fan_speed_rad_s`).
    #[serde(default)]
    pub torque_nm: Vec<Step>,
    /// How the torque follows the speed: `active` (the default: the profile's torque at any
    /// speed, as a hoist), `passive` (opposes the rotation, never drives it: a conveyor,
    /// friction) or `fan` (∝ ω², a fan or a centrifugal pump).
    #[serde(default)]
    pub kind: LoadKind,
    /// `passive`: the load's sign goes smoothly through zero as tanh(ω/ω_ε) with this ω_ε,
    /// mechanical rad/s (default 1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub smooth_sign_rad_s: Option<f64>,
    /// `fan`: the speed at which the load equals `torque_nm`, mechanical rad/s (default: the
    /// motor's rated speed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fan_speed_rad_s: Option<f64>,
}

/// What kind of machine the motor drives (see [`Load::kind`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LoadKind {
    /// The profile's torque whatever the speed.
    #[default]
    Active,
    /// Opposes the rotation, never drives it.
    Passive,
    /// ∝ ω².
    Fan,
}

impl Scenario {
    /// The load model of the motor's equation of motion.
    pub fn load_model(&self) -> drivelab_control::motor::LoadModel {
        use drivelab_control::motor::LoadModel;
        match self.load.kind {
            LoadKind::Active => LoadModel::Active,
            LoadKind::Passive => LoadModel::Passive {
                smooth_sign_rad_s: self.load.smooth_sign_rad_s.unwrap_or(1.0),
            },
            LoadKind::Fan => LoadModel::Fan {
                at_rad_s: self
                    .load
                    .fan_speed_rad_s
                    .unwrap_or_else(|| self.motor_params().omega_rated_rad_s),
            },
        }
    }
}

/// Value of a piecewise-constant profile at time t (0 before the first step). No allocation.
pub fn profile_at(steps: &[Step], t: f64) -> f64 {
    let mut v = 0.0;
    for s in steps {
        if t + 1e-12 >= s.t_s {
            v = s.value;
        } else {
            break;
        }
    }
    v
}

/// Placement of one service.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServicePlacement {
    /// CPU core; None = not pinned.
    #[serde(default, deserialize_with = "crate::topology::cpu_field")]
    pub core: Option<usize>,
    /// SCHED_FIFO priority 1..=99; None = SCHED_OTHER.
    #[serde(default, deserialize_with = "crate::topology::priority_field")]
    pub priority: Option<u8>,
}

/// Placement of the four services.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Placement {
    /// Plant (timing master).
    pub plant: ServicePlacement,
    /// Observer.
    pub observer: ServicePlacement,
    /// Current loop.
    pub current_loop: ServicePlacement,
    /// Speed loop.
    pub speed_loop: ServicePlacement,
}

impl Default for Placement {
    /// All four services on core 1 (a wake-up on another core costs 12-15 µs here, on the
    /// same core 2-6 µs), priorities rising along the chain so that each notify hands the CPU
    /// straight to the next stage (plant 70 < observer 72 < speed loop 74 < current loop 76);
    /// core 0 keeps the OS, the supervisor and the recorder. See the README's measurements.
    fn default() -> Self {
        let on1 = |p| ServicePlacement {
            core: Some(1),
            priority: Some(p),
        };
        Self {
            plant: on1(70),
            observer: on1(72),
            current_loop: on1(76),
            speed_loop: on1(74),
        }
    }
}

impl Placement {
    /// Placement for a service by name.
    pub fn get(&self, service: &str) -> Option<ServicePlacement> {
        match service {
            "plant" => Some(self.plant),
            "observer" => Some(self.observer),
            "current-loop" => Some(self.current_loop),
            "speed-loop" => Some(self.speed_loop),
            _ => None,
        }
    }
}

/// A name that may name a folder: 1..=64 characters of a-z, A-Z, 0-9, `-`, `_` or `.`, not
/// starting with `.` (scenario and campaign names make the default run folders' names).
pub fn name_ok(name: &str) -> bool {
    (1..=64).contains(&name.len())
        && !name.starts_with('.')
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
}

/// Most RK4 sub-steps of the plant per sample (`rates.plant_substeps`).
const MAX_PLANT_SUBSTEPS: u32 = 1000;

/// The four service names, in chain order.
pub const SERVICES: [&str; 4] = ["plant", "observer", "current-loop", "speed-loop"];

/// One line for a TOML error of file `origin` with text `text`: `ORIGIN:LINE: FIELD: MESSAGE`,
/// where FIELD is the dotted path of the key or table the error is at (`motor.r_ohm`,
/// `process[1].cpu`), left out when the error is at none (a syntax error, a missing field
/// of the top level, which names itself).
pub fn toml_error(text: &str, origin: &str, e: &toml::de::Error) -> String {
    let msg = e.message().trim().replace('\n', " ");
    let Some(span) = e.span() else {
        return format!("{origin}: {msg}");
    };
    let at = span.start.min(text.len());
    let line = text[..at].matches('\n').count() + 1;
    match toml_field_at(text, at) {
        Some(f) => format!("{origin}:{line}: {f}: {msg}"),
        None => format!("{origin}:{line}: {msg}"),
    }
}

/// A `[table]` or `[[array]]` header line of TOML: its name and whether it is an array's.
fn toml_header(l: &str) -> Option<(String, bool)> {
    let t = l.split('#').next().unwrap_or_default().trim();
    let (inner, array) = match t.strip_prefix("[[").and_then(|x| x.strip_suffix("]]")) {
        Some(x) => (x, true),
        None => (t.strip_prefix('[')?.strip_suffix(']')?, false),
    };
    let inner = inner.trim();
    (!inner.is_empty()
        && inner
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "_-. ".contains(c)))
    .then(|| (inner.replace(' ', ""), array))
}

/// The dotted path of the key or table header at byte offset `at` of TOML `text`: the key
/// of that line, or of the multi-line value (an array) the line is inside, with its table
/// (`name[i]` for the i-th `[[name]]`). A light scan of the text (bare, dotted and
/// double-quoted keys), enough to name the field of a type or range error.
fn toml_field_at(text: &str, at: usize) -> Option<String> {
    // An error at offset 0 is about the whole file (a missing field of the top level), not
    // about the table or key the first line happens to hold.
    if at == 0 {
        return None;
    }
    let lines: Vec<&str> = text.lines().collect();
    let n = text[..at].matches('\n').count();
    let here = *lines.get(n)?;
    // The table a line belongs to: the nearest header at or above it.
    let table = |from: usize| -> Option<String> {
        let i = (0..=from)
            .rev()
            .find(|&i| toml_header(lines[i]).is_some())?;
        let (name, array) = toml_header(lines[i])?;
        Some(if array {
            let k = lines[..=i]
                .iter()
                .filter(|x| toml_header(x).is_some_and(|(h, a)| a && h == name))
                .count();
            format!("{name}[{}]", k - 1)
        } else {
            name
        })
    };
    if toml_header(here).is_some() {
        return table(n);
    }
    let key = match toml_key(here.trim_start()) {
        Some(k) => Some((k, n)),
        None => (0..n).rev().find_map(|j| {
            if toml_header(lines[j]).is_some() {
                return Some(None);
            }
            let k = toml_key(lines[j].trim_start())?;
            let first = lines[j].split_once('=').map_or("", |(_, v)| v);
            let depth = bracket_depth(first)
                + lines[j + 1..n]
                    .iter()
                    .map(|l| bracket_depth(l))
                    .sum::<i64>();
            Some((depth > 0).then_some((k, j)))
        })?,
    };
    let (k, j) = key?;
    Some(match table(j) {
        Some(t) => format!("{t}.{k}"),
        None => k,
    })
}

/// `[` and `{` opened minus closed on a line of TOML, outside strings and comments.
fn bracket_depth(l: &str) -> i64 {
    let (mut depth, mut quote) = (0, None);
    for c in l.chars() {
        match (quote, c) {
            (Some(q), c) if c == q => quote = None,
            (Some(_), _) => {}
            (None, '"' | '\'') => quote = Some(c),
            (None, '#') => break,
            (None, '[' | '{') => depth += 1,
            (None, ']' | '}') => depth -= 1,
            _ => {}
        }
    }
    depth
}

/// The key of a `key = value` line (bare, dotted or double-quoted), if it is one.
fn toml_key(t: &str) -> Option<String> {
    let (k, rest) = if let Some(q) = t.strip_prefix('"') {
        let end = q.find('"')?;
        (q[..end].to_string(), &q[end + 1..])
    } else {
        let end = t
            .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_' || c == '-' || c == '.'))
            .unwrap_or(t.len());
        (t[..end].to_string(), &t[end..])
    };
    (!k.is_empty() && rest.trim_start().starts_with('=')).then_some(k)
}

/// `x` to 6 significant digits, for limits computed from other fields (`3665.19`, not
/// `3665.1914291880917`).
fn sig(x: f64) -> f64 {
    format!("{x:.5e}").parse().unwrap_or(x)
}

fn check(cond: bool, msg: impl FnOnce() -> String) -> Result<(), String> {
    if cond {
        Ok(())
    } else {
        Err(msg())
    }
}

fn check_steps(
    name: &str,
    steps: &[Step],
    dur: f64,
    abs_max: f64,
    unit: &str,
) -> Result<(), String> {
    let mut last = f64::NEG_INFINITY;
    for (i, s) in steps.iter().enumerate() {
        check(s.t_s.is_finite() && s.t_s >= 0.0 && s.t_s <= dur, || {
            format!(
                "{name}[{i}].t_s = {} must be within [0, duration_s = {dur}] s",
                s.t_s
            )
        })?;
        check(s.t_s > last, || {
            format!(
                "{name}[{i}].t_s = {} must be later than the step before",
                s.t_s
            )
        })?;
        check(s.value.is_finite() && s.value.abs() <= abs_max, || {
            format!(
                "{name}[{i}].value = {} must be finite and within ±{} {unit}",
                s.value,
                sig(abs_max)
            )
        })?;
        last = s.t_s;
    }
    Ok(())
}

impl Scenario {
    /// Parses and validates a scenario from TOML text; `origin` names the source in errors.
    pub fn from_toml(text: &str, origin: &str) -> Result<Self, String> {
        let s: Scenario = toml::from_str(text).map_err(|e| toml_error(text, origin, &e))?;
        s.validate().map_err(|e| format!("{origin}: {e}"))?;
        Ok(s)
    }

    /// Loads a scenario by name (from the scenarios folder) or by file path.
    pub fn load(name_or_path: &str) -> Result<(Self, PathBuf), String> {
        let path = resolve_scenario_path(name_or_path)?;
        let text = read_config_file(&path, "scenario")?;
        Ok((Self::from_toml(&text, &path.display().to_string())?, path))
    }

    /// Resolved motor parameters (the plant's true ones).
    pub fn motor_params(&self) -> MotorParams {
        self.motor.resolve().expect("validated scenario")
    }

    /// The motor parameters the controllers and observers design with (`[model]`).
    pub fn controller_motor_params(&self) -> MotorParams {
        self.model
            .apply(&self.motor_params())
            .expect("validated scenario")
    }

    /// The scenario as the controllers and observers see it: the motor of `[model]`, no
    /// `[model]` and no `[plant_drift]`. Every stage but the plant is built from it. Without
    /// a `[model]` it is the scenario itself. See docs/architecture.md, "Model mismatch".
    pub fn controller_view(&self) -> Scenario {
        let mut v = self.clone();
        v.plant_drift = PlantDrift::default();
        if self.model.is_nominal() {
            return v;
        }
        let c = self.controller_motor_params();
        v.motor.r_ohm = Some(c.r_ohm);
        v.motor.l_d_h = Some(c.l_d_h);
        v.motor.l_q_h = Some(c.l_q_h);
        v.motor.psi_pm_wb = Some(c.psi_pm_wb);
        v.motor.j_kgm2 = Some(c.j_kgm2);
        v.motor.b_nms = Some(c.b_nms);
        v.model = ModelSpec::default();
        v
    }

    /// The topology: the `[[process]]` tables, or one process per built-in stage placed by
    /// `[placement]`.
    pub fn topology(&self) -> Vec<crate::topology::ProcessSpec> {
        if !self.process.is_empty() {
            return self.process.clone();
        }
        SERVICES
            .iter()
            .map(|s| {
                let p = self.placement.get(s).expect("known service");
                crate::topology::ProcessSpec {
                    name: s.to_string(),
                    stages: vec![s.to_string()],
                    cpu: p.core,
                    priority: p.priority,
                    exec: None,
                    standby: false,
                    machine: None,
                }
            })
            .collect()
    }

    /// The rate divider of user stage `name` (`[stages.NAME] rate_hz`), if set.
    pub fn stage_divider(&self, name: &str) -> Option<u64> {
        let hz = self
            .stages
            .get(name)?
            .get("rate_hz")?
            .as_float()
            .or_else(|| {
                self.stages
                    .get(name)?
                    .get("rate_hz")?
                    .as_integer()
                    .map(|i| i as f64)
            })?;
        Some((self.rates.sample_hz / hz).round() as u64)
    }

    /// Sets the run's length, as `--duration` and a campaign's `duration_s` do. What the
    /// scenario schedules at or after a shorter end is never reached, so it is taken out: a
    /// reference or load step, an `[[inject]]` or `[[sensor_fault]]` table. Nothing before
    /// the end changes: the shortened run's samples are the first ones of the full run, bit
    /// for bit (a drift profile stays whole; its points may lie after the end; a kill keeps
    /// its meaning: never restarted, or restarted after the end). Returns what was taken
    /// out, one item each, e.g. `load.torque_nm[0] at 0.04 s`; the caller validates the
    /// result.
    pub fn set_duration(&mut self, duration_s: f64) -> Vec<String> {
        let mut out = Vec::new();
        if duration_s < self.duration_s {
            let end = duration_s;
            for (name, steps) in [
                ("reference.speed_rad_s", &mut self.reference.speed_rad_s),
                ("reference.i_d_a", &mut self.reference.i_d_a),
                ("reference.i_q_a", &mut self.reference.i_q_a),
                ("load.torque_nm", &mut self.load.torque_nm),
            ] {
                // Steps are in time order (validated): the late ones are a tail. A step at
                // the end itself comes after the last sample.
                let keep = steps.iter().take_while(|s| s.t_s < end).count();
                for (i, s) in steps.iter().enumerate().skip(keep) {
                    out.push(format!("{name}[{i}] at {} s", s.t_s));
                }
                steps.truncate(keep);
            }
            let mut i = 0;
            self.inject.retain_mut(|j| {
                let keep = j.at_s < end;
                if !keep {
                    out.push(format!("inject[{i}] {}", j.spec()));
                } else if j.kind == crate::inject::InjectKind::Kill {
                    // A restart after the old end is after the new one too (0: never).
                    j.duration_s = j.duration_s.min(crate::inject::restart_max_s(end));
                }
                i += 1;
                keep
            });
            let mut i = 0;
            self.sensor_fault.retain(|f| {
                let keep = f.at_s() < end;
                if !keep {
                    out.push(format!("sensor_fault[{i}] {}", f.spec()));
                }
                i += 1;
                keep
            });
        }
        self.duration_s = duration_s;
        out
    }

    /// Number of samples in the run.
    pub fn samples(&self) -> u64 {
        (self.duration_s * self.rates.sample_hz).round() as u64
    }

    /// Lockstep and in process: the first sample that no plant produces (None: every sample
    /// has one), that of a kill of the plant in `[[inject]]` that is never restarted
    /// (`--restart never`). The drive ends there, as a real-time drive stops when its plant
    /// dies for good (docs/architecture.md, "Kill and stop in lockstep"). A plant whose
    /// restart would come after the end is down to the end instead: its samples are made, as
    /// a real-time supervisor's restart rebuilds them.
    pub fn plant_gone_at(&self) -> Option<u64> {
        use crate::inject::Armed;
        self.inject
            .iter()
            .filter(|i| i.target == "plant" && i.never_restarted())
            .map(|i| Armed::bind(i, self.rates.sample_hz, &["plant"], |_| 1).from_k)
            .min()
    }

    /// The samples a lockstep or in-process drive makes: the run's, or up to the plant's
    /// kill for good ([`Scenario::plant_gone_at`]).
    pub fn samples_made(&self) -> u64 {
        self.plant_gone_at().unwrap_or(self.samples())
    }

    /// Voltage-vector limit V_dc/√3, V.
    pub fn u_max(&self) -> f64 {
        self.inverter.v_dc_v / 3f64.sqrt()
    }

    /// True when the scenario selects Kyslan's nonlinear controller (both loops).
    pub fn nonlinear(&self) -> bool {
        self.speed_loop.controller == SpeedController::Nonlinear
    }

    /// i_q* limit, A.
    pub fn i_q_max(&self) -> f64 {
        self.speed_loop
            .i_q_max_a
            .unwrap_or_else(|| self.motor_params().i_max_a)
    }

    /// Checks ranges; the error names the field and the rule.
    pub fn validate(&self) -> Result<(), String> {
        check(name_ok(&self.name), || {
            format!(
                "name = {:?} must be 1..=64 characters of a-z, A-Z, 0-9, -, _ or . (it names the run folder), not starting with .",
                self.name
            )
        })?;
        check(
            self.duration_s.is_finite()
                && self.duration_s > 0.0
                && self.duration_s <= MAX_DURATION_S,
            || {
                format!(
                    "duration_s = {} must be in (0, {MAX_DURATION_S}] s",
                    self.duration_s
                )
            },
        )?;
        let m = self.motor.resolve()?;
        self.model.apply(&m)?;
        check_drift("plant_drift.r_factor", &self.plant_drift.r_factor)?;
        check_drift("plant_drift.psi_factor", &self.plant_drift.psi_factor)?;
        let r = &self.rates;
        check(
            r.sample_hz.is_finite() && (100.0..=100_000.0).contains(&r.sample_hz),
            || {
                format!(
                    "rates.sample_hz = {} must be in [100, 100000] Hz",
                    r.sample_hz
                )
            },
        )?;
        check((1..=1000).contains(&r.speed_divider), || {
            format!(
                "rates.speed_divider = {} must be in 1..=1000",
                r.speed_divider
            )
        })?;
        check((1..=MAX_PLANT_SUBSTEPS).contains(&r.plant_substeps), || {
            format!(
                "rates.plant_substeps = {} must be in 1..={MAX_PLANT_SUBSTEPS}",
                r.plant_substeps
            )
        })?;
        // RK4 steps longer than the electrical time constant give numbers, not the motor
        // (the same bound as `drivelab plant --max-step-s`).
        let tau = m.l_d_h.min(m.l_q_h) / m.r_ohm;
        let h = 1.0 / (r.sample_hz * f64::from(r.plant_substeps));
        check(h <= tau, || {
            let need = (1.0 / (r.sample_hz * tau)).ceil();
            format!(
                "rates.plant_substeps = {}: the plant's RK4 step 1/(rates.sample_hz × plant_substeps) = {h:.3e} s must be at most the motor's electrical time constant min(L_d, L_q)/R = {tau:.3e} s ({})",
                r.plant_substeps,
                if need <= f64::from(MAX_PLANT_SUBSTEPS) {
                    format!("plant_substeps = {need} would do")
                } else {
                    format!("it would take plant_substeps = {need:e}, above the {MAX_PLANT_SUBSTEPS} allowed: check the motor's inductances and resistance")
                }
            )
        })?;
        check(self.samples() >= 1 && self.samples() <= 200_000_000, || {
            format!(
                "duration_s × rates.sample_hz = {} s × {} Hz = {} samples must be in 1..=2e8",
                self.duration_s,
                self.rates.sample_hz,
                self.samples()
            )
        })?;
        let inv = &self.inverter;
        check(
            inv.v_dc_v.is_finite() && inv.v_dc_v > 0.0 && inv.v_dc_v <= 2000.0,
            || format!("inverter.v_dc_v = {} must be in (0, 2000] V", inv.v_dc_v),
        )?;
        if let Some(i) = inv.i_trip_a {
            check(i.is_finite() && i > 0.0 && i <= 1e5, || {
                format!("inverter.i_trip_a = {i} must be in (0, 100000] A")
            })?;
        }
        check(inv.hold_samples <= 100_000, || {
            format!(
                "inverter.hold_samples = {} must be <= 100000",
                inv.hold_samples
            )
        })?;
        if let Some(w) = self.mechanics.prescribed_speed_rad_s {
            check(
                w.is_finite() && w.abs() <= 10.0 * m.omega_rated_rad_s,
                || {
                    format!(
                        "mechanics.prescribed_speed_rad_s = {w} must be finite and within ±10 × motor.omega_rated_rad_s = ±{} rad/s",
                        sig(10.0 * m.omega_rated_rad_s)
                    )
                },
            )?;
        }
        if let Some(w) = self.mechanics.initial_speed_rad_s {
            check(
                w.is_finite()
                    && w.abs() <= 10.0 * m.omega_rated_rad_s
                    && self.mechanics.prescribed_speed_rad_s.is_none(),
                || {
                    format!(
                        "mechanics.initial_speed_rad_s = {w} must be finite, within ±10 × motor.omega_rated_rad_s = ±{} rad/s, and not set together with prescribed_speed_rad_s",
                        sig(10.0 * m.omega_rated_rad_s)
                    )
                },
            )?;
        }
        crate::sensor_faults::validate(&self.sensor_fault, self.duration_s)?;
        inv.check_model(r.sample_hz)?;
        check(
            !self.current_loop.dead_time_comp || inv.model == InverterModel::Switching,
            || {
                "current_loop.dead_time_comp needs inverter.model = \"switching\" (the averaged inverter has no dead time)".into()
            },
        )?;
        let s = &self.sensors;
        s.check_errors(r.ts(), m.i_max_a)?;
        check(
            s.encoder_counts_per_rev == 0 || s.encoder_counts_per_rev >= 4,
            || {
                format!(
                    "sensors.encoder_counts_per_rev = {} must be 0 (an ideal encoder) or at least 4 counts per revolution",
                    s.encoder_counts_per_rev
                )
            },
        )?;
        check(
            s.current_noise_a.is_finite()
                && s.current_noise_a >= 0.0
                && s.current_noise_a <= m.i_max_a,
            || {
                format!(
                    "sensors.current_noise_a = {} must be in [0, motor.i_max_a = {}] A",
                    s.current_noise_a, m.i_max_a
                )
            },
        )?;
        let ts = r.ts();
        let o = &self.observer;
        check(
            o.speed_filter_tau_s.is_finite()
                && o.speed_filter_tau_s >= ts
                && o.speed_filter_tau_s <= 1.0,
            || {
                format!(
                    "observer.speed_filter_tau_s = {} must be in [T_s = {ts}, 1] s",
                    o.speed_filter_tau_s
                )
            },
        )?;
        if !self.process.is_empty() {
            check(self.placement == Placement::default(), || {
                "give the placement either in [placement] or in [[process]] tables, not both"
                    .to_string()
            })?;
            crate::topology::check_specs(&self.process)?;
        }
        for (name, t) in &self.stages {
            // The plant reads its own tables; here its settings would be ignored. (A table of
            // another built-in stage's name is for a user's stage that replaces it: the
            // launcher refuses it where the built-in runs.)
            check(name != "plant", || {
                "[stages.plant] is for user stages, and the plant cannot be replaced: it takes its settings from [motor], [inverter], [rates] and the plant's other tables".to_string()
            })?;
            if let Some(v) = t.get("rate_hz") {
                let hz = v.as_float().or_else(|| v.as_integer().map(|i| i as f64));
                // A rate that divides the sample rate can still be one step in the run, or
                // none after the first (1e-20 Hz: a divider of 2^64 − 1, accepted before).
                check(!hz.is_some_and(|hz| hz > 0.0 && hz < 1.0), || {
                    format!("stages.{name}.rate_hz = {v} is below 1 Hz, the slowest rate a stage may run at")
                })?;
                let ok = hz.is_some_and(|hz| {
                    hz.is_finite()
                        && hz > 0.0
                        && hz <= r.sample_hz
                        && ((r.sample_hz / hz) - (r.sample_hz / hz).round()).abs() < 1e-9
                });
                check(ok, || {
                    format!(
                        "stages.{name}.rate_hz = {v} must divide the sample rate {} Hz",
                        r.sample_hz
                    )
                })?;
            }
        }
        crate::wiring::observer_sensorless::validate(self)?;
        crate::wiring::rst::validate(self)?;
        crate::wiring::polar::validate(self)?;
        let c = &self.current_loop;
        check(
            c.tau_c_s.is_finite() && c.tau_c_s >= 2.0 * ts && c.tau_c_s <= 1.0,
            || {
                format!(
                    "current_loop.tau_c_s = {} must be in [2·T_s = {}, 1] s",
                    c.tau_c_s,
                    2.0 * ts
                )
            },
        )?;
        let sl = &self.speed_loop;
        let nl_speed = sl.controller == SpeedController::Nonlinear;
        let nl_current = c.controller == CurrentController::Nonlinear;
        check(nl_speed == nl_current, || {
            format!(
                "speed_loop.controller = {:?} and current_loop.controller = {:?} must both be \"pi\" or both \"nonlinear\" (the nonlinear law is split across the two loops)",
                sl.controller, c.controller
            )
            .to_lowercase()
        })?;
        check(
            sl.rise_time_s.is_finite() && sl.rise_time_s > 0.0 && sl.rise_time_s <= 10.0,
            || {
                format!(
                    "speed_loop.rise_time_s = {} must be in (0, 10] s",
                    sl.rise_time_s
                )
            },
        )?;
        if let Some(i) = sl.i_q_max_a {
            check(i.is_finite() && i > 0.0 && i <= 10.0 * m.i_max_a, || {
                format!(
                    "speed_loop.i_q_max_a = {i} must be in (0, 10 × motor.i_max_a = {}] A",
                    sig(10.0 * m.i_max_a)
                )
            })?;
        }
        check_steps(
            "reference.speed_rad_s",
            &self.reference.speed_rad_s,
            self.duration_s,
            10.0 * m.omega_rated_rad_s,
            "rad/s (10 × motor.omega_rated_rad_s)",
        )?;
        check_steps(
            "reference.i_d_a",
            &self.reference.i_d_a,
            self.duration_s,
            10.0 * m.i_max_a,
            "A (10 × motor.i_max_a)",
        )?;
        check_steps(
            "reference.i_q_a",
            &self.reference.i_q_a,
            self.duration_s,
            10.0 * m.i_max_a,
            "A (10 × motor.i_max_a)",
        )?;
        check_steps(
            "load.torque_nm",
            &self.load.torque_nm,
            self.duration_s,
            100.0 * m.t_rated_nm,
            "N·m (100 × motor.t_rated_nm)",
        )?;
        for (name, v) in [
            ("load.smooth_sign_rad_s", self.load.smooth_sign_rad_s),
            ("load.fan_speed_rad_s", self.load.fan_speed_rad_s),
        ] {
            if let Some(v) = v {
                check(v.is_finite() && v > 0.0 && v <= 1e5, || {
                    format!("{name} = {v} must be a speed in (0, 1e5] rad/s")
                })?;
            }
        }
        let spin = self.timing.plant_spin_us;
        check(
            spin.is_finite() && spin >= 0.0 && spin < 0.5e6 / r.sample_hz,
            || {
                format!(
                    "timing.plant_spin_us = {spin} must be in [0, T_s/2 = {:.1}) µs (the plant spins on the chain's core; the chain needs the rest of the period)",
                    0.5e6 / r.sample_hz
                )
            },
        )?;
        let cpus = std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1);
        for svc in SERVICES {
            let p = self.placement.get(svc).expect("known service");
            if let Some(core) = p.core {
                check(core < 1024, || {
                    format!(
                        "placement.{}.core = {core} is not a CPU number (0..=1023)",
                        svc.replace('-', "_")
                    )
                })?;
                let _ = cpus; // a core beyond this machine is reported by the RT setup, not here
            }
            if let Some(pr) = p.priority {
                check((1..=99).contains(&pr), || {
                    format!(
                        "placement.{}.priority = {pr} must be in 1..=99",
                        svc.replace('-', "_")
                    )
                })?;
            }
        }
        crate::inject::validate(&self.inject, self.duration_s)?;
        Ok(())
    }
}

/// The folders a scenario name is looked up in, the first that holds `NAME.toml` winning:
/// `scenarios/` in the working folder (a checkout's, edited), then the shipped ones:
/// `$DRIVELAB_SCENARIOS` when it is set, else `scenarios/` next to the executable or a folder
/// above it (a checkout's `target/release/drivelab`), then the source tree it was built from.
/// Only folders that exist; a file path is never looked up (`names_a_file`).
pub fn scenario_dirs() -> Vec<PathBuf> {
    let mut candidates = Vec::new();
    if let Ok(cwd) = std::env::current_dir() {
        candidates.push(cwd.join("scenarios"));
    }
    if let Ok(d) = std::env::var("DRIVELAB_SCENARIOS") {
        candidates.push(PathBuf::from(d));
    } else {
        if let Ok(exe) = std::env::current_exe() {
            for a in exe.ancestors().skip(1) {
                candidates.push(a.join("scenarios"));
            }
        }
        candidates.push(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../scenarios"));
    }
    let mut dirs: Vec<PathBuf> = Vec::new();
    for c in candidates.into_iter().filter(|p| p.is_dir()) {
        // The same folder reached twice (the working folder is the checkout) is one.
        let same = |d: &PathBuf| match (d.canonicalize(), c.canonicalize()) {
            (Ok(a), Ok(b)) => a == b,
            _ => *d == c,
        };
        if !dirs.iter().any(same) {
            dirs.push(c);
        }
    }
    dirs
}

/// The first of [`scenario_dirs`] (where `drivelab scenarios` looked when it found none).
pub fn scenarios_dir() -> PathBuf {
    scenario_dirs()
        .into_iter()
        .next()
        .unwrap_or_else(|| PathBuf::from("scenarios"))
}

/// `NAME.toml` in the first folder of `dirs` that holds it.
pub fn find_named(dirs: &[PathBuf], name: &str) -> Option<PathBuf> {
    dirs.iter()
        .map(|d| d.join(format!("{name}.toml")))
        .find(|f| f.is_file())
}

/// The `NAME.toml` files of `dirs`, each name once with the file that [`find_named`] takes
/// for it, sorted by name.
pub fn list_named(dirs: &[PathBuf]) -> Vec<(String, PathBuf)> {
    let mut v: BTreeMap<String, PathBuf> = BTreeMap::new();
    for d in dirs {
        for p in std::fs::read_dir(d)
            .into_iter()
            .flatten()
            .flatten()
            .map(|e| e.path())
            .filter(|p| p.extension().is_some_and(|e| e == "toml") && p.is_file())
        {
            if let Some(stem) = p.file_stem() {
                v.entry(stem.to_string_lossy().into_owned()).or_insert(p);
            }
        }
    }
    v.into_iter().collect()
}

/// The scenarios found by name (file stems, [`scenario_dirs`]), sorted, each with the file a
/// run of that name reads.
pub fn list_scenarios() -> Vec<(String, PathBuf)> {
    list_named(&scenario_dirs())
}

/// Whether a scenario or topology argument names a file (it ends in `.toml` or holds a `/`)
/// rather than a shipped one.
pub fn names_a_file(name_or_path: &str) -> bool {
    name_or_path.ends_with(".toml") || name_or_path.contains('/')
}

/// The largest configuration file drivelab reads (a scenario, a topology, a campaign), bytes.
pub const MAX_CONFIG_BYTES: u64 = 1 << 20;

/// Reads configuration file `path` (`what`: "scenario", "topology", "campaign"). It must be a
/// regular file of at most [`MAX_CONFIG_BYTES`]: a device, a FIFO or a huge file is one line
/// instead of a read without end or without a bound.
pub fn read_config_file(path: &Path, what: &str) -> Result<String, String> {
    use std::io::Read;
    let shown = path.display();
    let meta = std::fs::metadata(path).map_err(|e| format!("cannot read {what} {shown}: {e}"))?;
    if meta.is_dir() {
        return Err(format!("{what} {shown} is a folder, not a {what} file"));
    }
    if !meta.is_file() {
        return Err(format!(
            "{what} {shown} is not a regular file (a {what} is a .toml file)"
        ));
    }
    let too_large =
        || format!("{what} {shown} is larger than {MAX_CONFIG_BYTES} bytes: not a {what} file");
    if meta.len() > MAX_CONFIG_BYTES {
        return Err(too_large());
    }
    let mut text = String::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(MAX_CONFIG_BYTES + 1).read_to_string(&mut text))
        .map_err(|e| format!("cannot read {what} {shown}: {e}"))?;
    if text.len() as u64 > MAX_CONFIG_BYTES {
        return Err(too_large());
    }
    Ok(text)
}

fn resolve_scenario_path(name_or_path: &str) -> Result<PathBuf, String> {
    let p = Path::new(name_or_path);
    if names_a_file(name_or_path) {
        return if p.is_file() {
            Ok(p.to_path_buf())
        } else if p.is_dir() {
            Err(format!(
                "scenario {name_or_path} is a folder, not a scenario file (a run folder's scenario is RUNDIR/scenario.toml)"
            ))
        } else if p.exists() {
            Err(format!(
                "scenario {name_or_path} is not a regular file (a scenario is a .toml file)"
            ))
        } else {
            // A dangling link or a loop of links "does not exist" to `exists`: say which.
            match std::fs::metadata(p) {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                    Err(format!("scenario file {name_or_path}: {e}"))
                }
                _ => Err(format!("scenario file {name_or_path} does not exist")),
            }
        };
    }
    if let Some(f) = find_named(&scenario_dirs(), name_or_path) {
        Ok(f)
    } else {
        let known: Vec<String> = list_scenarios().into_iter().map(|(n, _)| n).collect();
        Err(format!(
            "unknown scenario '{name_or_path}' (known: {})",
            known.join(", ")
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIN: &str = r#"
name = "t"
duration_s = 0.01
[motor]
preset = "kyslan2015"
"#;

    /// A plant killed for good (a restart time of 0) ends a simulated drive at its kill; one
    /// whose restart comes after the end does not. A shorter run keeps what each kill meant.
    #[test]
    fn kills_never_restarted_and_restarted_after_the_end_stay_so_in_a_shorter_run() {
        let kill = |target: &str, at: f64, restart: f64| {
            format!("[[inject]]\nkind = \"kill\"\ntarget = \"{target}\"\nat_s = {at}\nduration_s = {restart}\n")
        };
        let sc = |dur: f64, injects: &str| {
            Scenario::from_toml(
                &format!(
                    "name = \"t\"\nduration_s = {dur}\n{injects}[motor]\npreset = \"kyslan2015\"\n"
                ),
                "t.toml",
            )
        };
        // Never restarted: 0; a restart after the end (even as long as the run): not gone.
        let never = sc(
            12.0,
            &(kill("plant", 1.0, 0.0) + &kill("observer", 1.0, 12.0)),
        )
        .unwrap();
        assert_eq!(never.plant_gone_at(), Some(10_000));
        assert_eq!(
            sc(12.0, &kill("plant", 1.0, 12.0)).unwrap().plant_gone_at(),
            None
        );
        let late = sc(12.0, &kill("plant", 11.0, 5.0)).unwrap();
        assert_eq!(late.plant_gone_at(), None);
        // A restart of 0 is "never" for a kill only; above 10 s only in a longer run.
        let e = sc(
            12.0,
            "[[inject]]\nkind = \"stop\"\ntarget = \"plant\"\nat_s = 1.0\nduration_s = 0.0\n",
        )
        .unwrap_err();
        assert!(e.contains("a stop lasts 0.001 to 60 s"), "{e}");
        let e = sc(2.0, &kill("observer", 1.0, 11.0)).unwrap_err();
        assert!(
            e.contains("the simulated restart lasts 0.001 to 10 s (0: never restarted)"),
            "{e}"
        );
        // Shortened to 2 s: "never" stays 0, a restart after the end stays after it.
        let mut short = never.clone();
        assert!(short.set_duration(2.0).is_empty());
        short.validate().unwrap();
        assert_eq!(
            short
                .inject
                .iter()
                .map(|i| i.duration_s)
                .collect::<Vec<_>>(),
            [0.0, 10.0]
        );
        assert_eq!(short.plant_gone_at(), Some(10_000));
        let mut later = sc(12.0, &kill("plant", 1.5, 11.0)).unwrap();
        later.set_duration(2.0);
        later.validate().unwrap();
        assert_eq!(later.inject[0].duration_s, 10.0);
        assert_eq!(later.plant_gone_at(), None);
    }

    #[test]
    fn cpu_latency_request_is_microseconds_or_none() {
        let with = |v: &str| {
            Scenario::from_toml(&format!("{MIN}[timing]\ncpu_latency_us = {v}\n"), "t.toml")
        };
        assert_eq!(
            Scenario::from_toml(MIN, "t.toml")
                .unwrap()
                .timing
                .cpu_latency_us,
            CpuLatency::Us(0)
        );
        assert_eq!(
            with("20").unwrap().timing.cpu_latency_us,
            CpuLatency::Us(20)
        );
        assert_eq!(
            with("\"none\"").unwrap().timing.cpu_latency_us,
            CpuLatency::None
        );
        for bad in ["-1", "\"off\"", "1.5", "2000000"] {
            let e = with(bad).unwrap_err();
            assert!(
                e.contains("cpu_latency_us must be a whole number"),
                "{bad}: {e}"
            );
        }
        // It survives the run folder's TOML round trip.
        let sc = with("\"none\"").unwrap();
        let back = Scenario::from_toml(&toml::to_string(&sc).unwrap(), "x").unwrap();
        assert_eq!(back.timing.cpu_latency_us, CpuLatency::None);
    }

    #[test]
    fn the_schedule_starts_on_the_tick_grid_unless_told_not_to() {
        let with = |v: &str| {
            Scenario::from_toml(&format!("{MIN}[timing]\ntick_aligned = {v}\n"), "t.toml")
        };
        assert!(
            Scenario::from_toml(MIN, "t.toml")
                .unwrap()
                .timing
                .tick_aligned
        );
        assert!(!with("false").unwrap().timing.tick_aligned);
        let e = with("\"no\"").unwrap_err();
        assert!(e.contains("tick_aligned"), "{e}");
        let sc = with("false").unwrap();
        let back = Scenario::from_toml(&toml::to_string(&sc).unwrap(), "x").unwrap();
        assert!(!back.timing.tick_aligned);
    }

    #[test]
    fn minimal_scenario_gets_defaults() {
        let s = Scenario::from_toml(MIN, "t.toml").unwrap();
        assert_eq!(s.rates.sample_hz, 10_000.0);
        assert_eq!(s.samples(), 100);
        assert_eq!(s.motor_params(), MotorParams::kyslan2015());
    }

    #[test]
    fn unknown_key_is_named_with_its_line() {
        let e = Scenario::from_toml(&format!("{MIN}\n[rates]\nsample_hzz = 5\n"), "bad.toml")
            .unwrap_err();
        assert!(e.starts_with("bad.toml:"), "{e}");
        assert!(e.contains("sample_hzz"), "{e}");
    }

    #[test]
    fn out_of_range_values_are_named() {
        let e =
            Scenario::from_toml(&format!("{MIN}\n[rates]\nsample_hz = -5.0\n"), "x").unwrap_err();
        assert!(e.contains("rates.sample_hz"), "{e}");
        let e = Scenario::from_toml(&MIN.replace("kyslan2015", "nope"), "x").unwrap_err();
        assert!(e.contains("unknown motor 'nope'"), "{e}");
        let e = Scenario::from_toml(
            &format!("{MIN}\n[placement.plant]\ncore = 1\npriority = 120\n"),
            "x",
        )
        .unwrap_err();
        assert!(e.contains("placement.plant.priority = 120"), "{e}");
        let e = Scenario::from_toml(
            &format!("{MIN}\n[load]\ntorque_nm = [{{t_s = 5.0, value = 1.0}}]\n"),
            "x",
        )
        .unwrap_err();
        assert!(e.contains("load.torque_nm[0].t_s"), "{e}");
    }

    /// One bad value per validation rule; the message names the field (or the rule) it
    /// breaks. Each case is the minimal scenario with `edit` applied: a TOML tail appended,
    /// or a (from, to) replacement.
    #[test]
    fn every_rule_names_its_field() {
        let tail = |t: &str| format!("{MIN}{t}\n");
        let swap = |from: &str, to: &str| {
            assert!(MIN.contains(from), "{from}");
            MIN.replace(from, to)
        };
        let steps = |field: &str, v: &str| format!("[reference]\n{field} = [{v}]");
        let cases: Vec<(String, &str)> = vec![
            (swap("name = \"t\"", "name = \"\""), "name = \"\" must be 1..=64"),
            (
                swap("name = \"t\"", "name = \"../../etc\""),
                "name = \"../../etc\" must be 1..=64 characters of a-z",
            ),
            (swap("name = \"t\"", "name = \"a\\nb\""), "name = \"a\\nb\" must"),
            (swap("duration_s = 0.01", "duration_s = 0.0"), "duration_s = 0 must"),
            (tail("[rates]\nsample_hz = 50.0"), "rates.sample_hz = 50 must"),
            (tail("[rates]\nspeed_divider = 0"), "rates.speed_divider = 0 must"),
            (tail("[rates]\nplant_substeps = 0"), "rates.plant_substeps = 0 must"),
            (
                format!(
                    "{}[rates]\nsample_hz = 100000.0\n",
                    swap("duration_s = 0.01", "duration_s = 3600.0")
                ),
                "duration_s × rates.sample_hz = 3600 s × 100000 Hz = 360000000 samples",
            ),
            (tail("[inverter]\nv_dc_v = 0.0"), "inverter.v_dc_v = 0 must"),
            (tail("[inverter]\nhold_samples = 100001"), "inverter.hold_samples = 100001"),
            (tail("[inverter]\ni_trip_a = 0"), "inverter.i_trip_a = 0"),
            (tail("[inverter]\ni_trip_a = 1e9"), "inverter.i_trip_a = 1000000000"),
            (
                tail("[mechanics]\nprescribed_speed_rad_s = 1e9"),
                "mechanics.prescribed_speed_rad_s = 1000000000 must",
            ),
            (
                tail("[mechanics]\ninitial_speed_rad_s = 1e9"),
                "mechanics.initial_speed_rad_s = 1000000000 must",
            ),
            (
                tail("[mechanics]\nprescribed_speed_rad_s = 1.0\ninitial_speed_rad_s = 1.0"),
                "not set together with prescribed_speed_rad_s",
            ),
            (
                tail("[sensors]\nencoder_counts_per_rev = 0\ncurrent_noise_a = -1.0\nseed = 1"),
                "sensors.current_noise_a = -1 must",
            ),
            (
                tail("[observer]\nspeed_filter_tau_s = 0.0"),
                "observer.speed_filter_tau_s = 0 must",
            ),
            (tail("[observer]\npole_tau_s = 0.0"), "observer.pole_tau_s = 0 must"),
            (
                tail("[observer]\ninitial_angle_error_deg = 400.0"),
                "observer.initial_angle_error_deg = 400 must",
            ),
            (
                tail("[observer]\nmode = \"sensorless\""),
                "observer.mode = \"sensorless\" needs a surface PMSM",
            ),
            (
                tail("[placement.plant]\ncore = 0\n[[process]]\nname = \"all\"\nstages = [\"plant\", \"observer\", \"current-loop\", \"speed-loop\"]"),
                "either in [placement] or in [[process]]",
            ),
            (tail("[stages.pos]\nrate_hz = 3.0"), "stages.pos.rate_hz = 3.0 must divide"),
            (
                tail("[stages.pos]\nrate_hz = 1e-20"),
                "is below 1 Hz, the slowest rate a stage may run at",
            ),
            (tail("[stages.pos]\nrate_hz = 0.5"), "stages.pos.rate_hz = 0.5 is below 1 Hz"),
            (
                tail("[stages.plant]\nfoo = 1"),
                "[stages.plant] is for user stages, and the plant cannot be replaced: it takes its settings from",
            ),
            (
                tail("[current_loop]\nitae_omega_rad_s = 100.0"),
                "current_loop.itae_omega_rad_s is set but current_loop.controller is not",
            ),
            (
                tail("[speed_loop]\nitae_omega_rad_s = 100.0"),
                "speed_loop.itae_omega_rad_s is set but speed_loop.controller is not",
            ),
            (
                tail("[current_loop]\ncontroller = \"rst\"\nitae_omega_rad_s = 1e9"),
                "current_loop.itae_omega_rad_s = 1000000000 must",
            ),
            (
                tail("[speed_loop]\ncontroller = \"rst\"\nitae_omega_rad_s = 1e9"),
                "speed_loop.itae_omega_rad_s = 1000000000 must",
            ),
            (
                tail(&steps("i_q_a", "{t_s = 0.0, value = 1.0}")),
                "reference.i_q_a is set but speed_loop.controller is not",
            ),
            (
                tail("[current_loop]\ncontroller = \"polar\""),
                "current_loop.controller = \"polar\" is the surface-PMSM law",
            ),
            (
                tail("[current_loop]\ncontroller = \"polar\"\ncdm_setpoint_weight = nan"),
                "current_loop.cdm_setpoint_weight = NaN must be in [0, 1]",
            ),
            (
                tail("[current_loop]\ncontroller = \"polar\"\ncdm_tau21_samples = -5.0"),
                "current_loop.cdm_tau21_samples = -5 must be in [1, 10000] samples",
            ),
            (
                tail("[current_loop]\ncontroller = \"polar-fw\"\npolar_sigma_v_rad_s = 5.0"),
                "current_loop.polar_sigma_v_rad_s = 5 must be negative",
            ),
            (
                tail("[current_loop]\ncontroller = \"voltage-phase\"\npolar_sigma_delta_rad_s = -1e300"),
                "current_loop.polar_sigma_delta_rad_s = -1e300 must be negative",
            ),
            (
                tail("[current_loop]\ncdm_setpoint_weight = 0.5"),
                "current_loop.cdm_setpoint_weight is set but current_loop.controller is not \"polar\"",
            ),
            (
                tail("[current_loop]\ncontroller = \"polar\"\npolar_sigma_v_rad_s = -300.0"),
                "current_loop.polar_sigma_v_rad_s is set but current_loop.controller is not \"polar-fw\"",
            ),
            (
                tail("[sensors]\ncurrent_gain = [1.0, 1.0, 1.0, 1.0]"),
                "invalid length 4, expected three values, one per phase (a, b, c)",
            ),
            (
                tail("[sensors]\ncurrent_offset_a = [0.0, 0.0]"),
                "invalid length 2, expected three values, one per phase (a, b, c)",
            ),
            (
                tail("[current_loop]\ncdm_delay = \"predict\""),
                "current_loop.cdm_delay is set but current_loop.controller is not \"polar\"",
            ),
            (tail("[current_loop]\ntau_c_s = 0.0"), "current_loop.tau_c_s = 0 must"),
            (
                tail("[speed_loop]\ncontroller = \"nonlinear\""),
                "speed_loop.controller = nonlinear and current_loop.controller = pi",
            ),
            (tail("[speed_loop]\nrise_time_s = 0.0"), "speed_loop.rise_time_s = 0 must"),
            (tail("[speed_loop]\ni_q_max_a = 0.0"), "speed_loop.i_q_max_a = 0 must"),
            (tail("[load]\nkind = \"pump\""), "unknown variant `pump`"),
            (
                tail("[load]\nkind = \"passive\"\nsmooth_sign_rad_s = 0.0"),
                "load.smooth_sign_rad_s = 0 must be a speed",
            ),
            (
                tail("[load]\nkind = \"fan\"\nfan_speed_rad_s = nan"),
                "load.fan_speed_rad_s = NaN must be a speed",
            ),
            (
                tail(&steps("speed_rad_s", "{t_s = 1.0, value = 1.0}")),
                "reference.speed_rad_s[0].t_s = 1 must be within",
            ),
            (
                tail(&steps(
                    "speed_rad_s",
                    "{t_s = 0.005, value = 1.0}, {t_s = 0.001, value = 2.0}",
                )),
                "reference.speed_rad_s[1].t_s = 0.001 must be later",
            ),
            (
                tail(&steps("speed_rad_s", "{t_s = 0.0, value = 1e9}")),
                "reference.speed_rad_s[0].value = 1000000000 must",
            ),
            (
                tail(&steps("i_d_a", "{t_s = 0.0, value = 1e9}")),
                "reference.i_d_a[0].value = 1000000000 must",
            ),
            (
                tail(&format!(
                    "[speed_loop]\ncontroller = \"current-reference\"\n{}",
                    steps("i_q_a", "{t_s = 0.0, value = 1e9}")
                )),
                "reference.i_q_a[0].value = 1000000000 must",
            ),
            (
                tail("[load]\ntorque_nm = [{t_s = 0.0, value = 1e9}]"),
                "load.torque_nm[0].value = 1000000000 must",
            ),
            (tail("[timing]\nplant_spin_us = 1e9"), "timing.plant_spin_us = 1000000000 must"),
            (tail("[placement.plant]\ncore = 5000"), "placement.plant.core = 5000"),
            (
                tail("[placement.current_loop]\npriority = 0"),
                "placement.current_loop.priority = 0 must",
            ),
            (swap("kyslan2015", "nope"), "motor.preset: unknown motor 'nope'"),
            (
                swap("preset = \"kyslan2015\"", "r_ohm = 1.0"),
                "motor.l_d_h is required",
            ),
            (tail("r_ohm = -1.0"), "motor.r_ohm = -1 must be in [0.000001, 1000] Ω"),
            (tail("b_nms = -1.0"), "motor.b_nms = -1 must be in [0, 1000] N·m·s/rad"),
            (tail("pole_pairs = 0"), "motor.pole_pairs = 0 must be in 1..=64"),
            // Physically nonsense values, each the only change.
            (tail("r_ohm = 1e300"), "motor.r_ohm = 1e300 must be in [0.000001, 1000] Ω"),
            (tail("l_d_h = nan"), "motor.l_d_h = NaN must be in [0.000000001, 10] H"),
            (tail("l_q_h = -0.004"), "motor.l_q_h = -0.004 must be in [0.000000001, 10] H"),
            (tail("psi_pm_wb = inf"), "motor.psi_pm_wb = inf must be in [0.000001, 100] Wb"),
            (tail("j_kgm2 = 0.0"), "motor.j_kgm2 = 0 must be in [0.0000000001, 1000000000] kg·m²"),
            (
                tail("j_kgm2 = 1e-12"),
                "motor.j_kgm2 = 0.000000000001 must be in [0.0000000001, 1000000000] kg·m²",
            ),
            (tail("b_nms = 1e300"), "motor.b_nms = 1e300 must be in [0, 1000] N·m·s/rad"),
            (tail("i_max_a = 1e300"), "motor.i_max_a = 1e300 must be in [0.001, 100000] A"),
            (
                tail("omega_rated_rad_s = 1e300"),
                "motor.omega_rated_rad_s = 1e300 must be in [0.001, 100000] rad/s",
            ),
            (tail("t_rated_nm = -1.0"), "motor.t_rated_nm = -1 must be in [0.000001, 1000000] N·m"),
            (
                tail("[sensors]\nencoder_counts_per_rev = 1"),
                "sensors.encoder_counts_per_rev = 1 must be 0 (an ideal encoder) or at least 4",
            ),
            (
                tail(&steps("speed_rad_s", "{t_s = -0.001, value = 1.0}")),
                "reference.speed_rad_s[0].t_s = -0.001 must be within [0, duration_s = 0.01] s",
            ),
            (
                tail(&steps("i_d_a", "{t_s = nan, value = 1.0}")),
                "reference.i_d_a[0].t_s = NaN must be within",
            ),
            (
                tail("[speed_loop]\ni_q_max_a = 1e300"),
                "speed_loop.i_q_max_a = 1e300 must be in (0, 10 × motor.i_max_a = 16] A",
            ),
            // Type errors name the field by its path (and its line).
            (tail("[rates]\nsample_hz = \"fast\""), "x:7: rates.sample_hz: invalid type"),
            (tail("[rates]\nspeed_divider = nan"), "x:7: rates.speed_divider: invalid type"),
            (
                tail("[inverter]\nv_dc_v = { a = 1 }"),
                "x:7: inverter.v_dc_v: invalid type: map",
            ),
            (
                tail("[[process]]\nname = \"a\"\nstages = [\"plant\"]\ncpu = -1"),
                "x:9: process[0].cpu: -1 is not a CPU number (0..=1023)",
            ),
            (
                tail("[reference]\nspeed_rad_s = [\n  { t_s = 0.0, value = 1.0 },\n  { t_s = \"x\", value = 2.0 },\n]"),
                "x:9: reference.speed_rad_s: invalid type: string",
            ),
        ];
        for (text, needle) in cases {
            match Scenario::from_toml(&text, "x") {
                Ok(_) => panic!("accepted:\n{text}"),
                Err(e) => {
                    // As drivelab prints it (1e300 in exponent form).
                    let e = crate::text::readable_numbers(&e);
                    assert!(e.contains(needle), "'{needle}' not in '{e}' for\n{text}");
                    assert!(e.starts_with("x:"), "the file is not named: {e}");
                    assert!(!e.contains('\n'), "not one line: {e}");
                }
            }
        }
    }

    #[test]
    fn toml_errors_name_the_line_and_the_field_path() {
        let err = |text: &str| Scenario::from_toml(text, "f.toml").unwrap_err();
        // The line of a key at the start of its line is that line (not the one before).
        let e = err(&format!("{MIN}[rates]\nsample_hzz = 5\n"));
        assert!(
            e.starts_with("f.toml:7: rates.sample_hzz: unknown field"),
            "{e}"
        );
        // A missing field of the top level names no key; one of a table names the table.
        let e = err("duration_s = 0.1\n[motor]\npreset = \"kyslan2015\"\n");
        assert!(e.starts_with("f.toml:1: missing field `name`"), "{e}");
        let e = err("[rates]\nsample_hz = 1e4\n");
        assert!(e.starts_with("f.toml:1: missing field `name`"), "{e}");
        let e = err(&format!("{MIN}[[expect]]\nnote = \"x\"\n"));
        assert!(
            e.starts_with("f.toml:6: expect[0]: missing field `check`"),
            "{e}"
        );
        // A syntax error is not pinned on the key above it.
        let e = err(&format!("{MIN}[rates\n"));
        assert!(e.starts_with("f.toml:6: unclosed table"), "{e}");
        // The n-th array table is counted.
        let two = "[[process]]\nname = \"a\"\nstages = [\"plant\"]\n";
        let e = err(&format!("{MIN}{two}{two}priority = 1000\n"));
        assert!(
            e.starts_with(
                "f.toml:12: process[1].priority: 1000 is out of range: SCHED_FIFO priorities are 1..=99"
            ),
            "{e}"
        );
        // Brackets inside strings and comments do not count.
        let e = err(&format!(
            "{MIN}[reference]\nspeed_rad_s = [ # ] [\n {{ t_s = 0.0, value = \"]\" }},\n]\n"
        ));
        assert!(
            e.starts_with("f.toml:8: reference.speed_rad_s: invalid type"),
            "{e}"
        );
    }

    #[test]
    fn the_shipped_scenarios_and_presets_are_within_the_ranges() {
        let shipped = list_scenarios();
        // The scenarios folder was found (18 scenarios ship): an empty list checks nothing.
        assert!(shipped.len() >= 18, "{shipped:?}");
        for (name, path) in shipped {
            let text = std::fs::read_to_string(&path).unwrap();
            Scenario::from_toml(&text, &name).unwrap_or_else(|e| panic!("{e}"));
        }
        for preset in MotorParams::PRESETS {
            check_motor(&MotorParams::preset(preset).unwrap()).unwrap();
        }
    }

    #[test]
    fn profiles_are_piecewise_constant() {
        let st = [
            Step {
                t_s: 0.0,
                value: 70.0,
            },
            Step {
                t_s: 0.02,
                value: 10.0,
            },
        ];
        assert_eq!(profile_at(&st, 0.0), 70.0);
        assert_eq!(profile_at(&st, 0.019_999), 70.0);
        assert_eq!(profile_at(&st, 0.02), 10.0);
        assert_eq!(profile_at(&[], 1.0), 0.0);
    }

    #[test]
    fn no_model_table_is_the_scenario_itself() {
        let s = Scenario::from_toml(MIN, "t.toml").unwrap();
        assert!(s.model.is_nominal());
        assert_eq!(s.controller_view(), s);
        assert_eq!(s.controller_motor_params(), s.motor_params());
        // Nothing new is written back for a scenario without the tables.
        let text = toml::to_string(&s).unwrap();
        assert!(
            !text.contains("model") && !text.contains("plant_drift"),
            "{text}"
        );
    }

    #[test]
    fn model_values_and_factors_give_the_controllers_motor() {
        let s = Scenario::from_toml(
            &format!(
                "{MIN}[model]\nr_factor = 0.5\nl_q_h = 0.02\npsi_factor = 1.1\nj_factor = 2.0\n"
            ),
            "t.toml",
        )
        .unwrap();
        let (t, c) = (s.motor_params(), s.controller_motor_params());
        assert_eq!(c.r_ohm, 0.5 * t.r_ohm);
        assert_eq!(c.l_q_h, 0.02);
        assert_eq!(c.psi_pm_wb, 1.1 * t.psi_pm_wb);
        assert_eq!(c.j_kgm2, 2.0 * t.j_kgm2);
        assert_eq!(
            (c.l_d_h, c.b_nms, c.pole_pairs),
            (t.l_d_h, t.b_nms, t.pole_pairs)
        );
        let v = s.controller_view();
        assert_eq!(v.motor_params(), c);
        assert!(v.model.is_nominal());
        // The plant keeps the true motor.
        assert_eq!(s.motor_params(), MotorParams::kyslan2015());
    }

    #[test]
    fn model_errors_are_one_line_and_name_the_field() {
        for (table, want) in [
            (
                "r_ohm = 1.0\nr_factor = 0.8",
                "model: give r_ohm or r_factor, not both",
            ),
            (
                "psi_pm_wb = 0.1\npsi_factor = 0.8",
                "model: give psi_pm_wb or psi_factor, not both",
            ),
            (
                "r_factor = 0.0",
                "model.r_factor = 0 must be finite and within [0.1, 10]",
            ),
            (
                "lq_factor = 11.0",
                "model.lq_factor = 11 must be finite and within [0.1, 10]",
            ),
            ("j_factor = nan", "model.j_factor = NaN must be finite"),
            ("l_d_h = -0.01", "model.l_d_h = -0.01 must be finite, > 0"),
            ("b_factor = inf", "model.b_factor = inf must be finite"),
            (
                "r_ohm = 1e9",
                "model.r_ohm = 1000000000 must be finite, > 0 and within [0.1, 10]",
            ),
            ("x_factor = 1.0", "unknown field `x_factor`"),
        ] {
            let e = Scenario::from_toml(&format!("{MIN}[model]\n{table}\n"), "t.toml").unwrap_err();
            assert!(e.contains(want), "{table}: {e}");
            assert!(!e.contains('\n'), "{table}: not one line: {e}");
        }
    }

    #[test]
    fn drift_profiles_are_piecewise_linear_and_validated() {
        let p = |t, v| DriftPoint { t_s: t, value: v };
        let pts = [p(0.1, 1.0), p(0.3, 1.4)];
        assert_eq!(drift_at(&pts, 0.0), 1.0);
        assert_eq!(drift_at(&pts, 0.1), 1.0);
        assert!((drift_at(&pts, 0.2) - 1.2).abs() < 1e-12);
        assert_eq!(drift_at(&pts, 0.3), 1.4);
        assert_eq!(drift_at(&pts, 5.0), 1.4);
        assert_eq!(drift_at(&[], 1.0), 1.0);
        let ok = format!(
            "{MIN}[plant_drift]\nr_factor = [{{t_s = 0.0, value = 1.0}}, {{t_s = 0.01, value = 1.3}}]\n"
        );
        Scenario::from_toml(&ok, "t.toml").unwrap();
        // A point after the run's end (0.01 s) sets the slope up to it.
        let past_end = format!(
            "{MIN}[plant_drift]\npsi_factor = [{{t_s = 0.0, value = 1.0}}, {{t_s = 0.02, value = 0.9}}]\n"
        );
        Scenario::from_toml(&past_end, "t.toml").unwrap();
        for (prof, want) in [
            (
                "r_factor = [{t_s = 0.0, value = 0.0}]",
                "plant_drift.r_factor[0].value = 0 must be finite and within [0.1, 10]",
            ),
            (
                "psi_factor = [{t_s = 3600.5, value = 1.0}]",
                "plant_drift.psi_factor[0].t_s = 3600.5 must be within [0, 3600] s",
            ),
            (
                "r_factor = [{t_s = 0.005, value = 1.0}, {t_s = 0.005, value = 1.1}]",
                "plant_drift.r_factor[1].t_s = 0.005 must be later than the point before",
            ),
        ] {
            let e = Scenario::from_toml(&format!("{MIN}[plant_drift]\n{prof}\n"), "t.toml")
                .unwrap_err();
            assert!(e.contains(want), "{prof}: {e}");
        }
    }
}
