//! Scenario → control wiring: everything that reads a [`Scenario`] to build, select or check
//! a control law or observer lives here, so the control maths take plain parameter structs
//! and never see the configuration types.
//!
//! One submodule per control module, with the functions that used to sit next to the law
//! (`rst::validate` was `control::rst::validate`, and so on); methods that took a scenario
//! became free functions: `RstDriveDesign::from_scenario` → [`rst::design_from_scenario`],
//! `PolarCurrentController::from_scenario` → [`polar::controller_from_scenario`],
//! `ObserverDesign::from_scenario` → [`observer_sensorless::design_from_scenario`].

use crate::config::Scenario;

/// Wiring of the RST laws ([`drivelab_control::control::rst`]).
pub mod rst {
    use super::Scenario;
    use crate::config::{CurrentController, SpeedController};
    use drivelab_control::control::rst::{
        default_current_omega, default_speed_omega, RstDriveDesign,
    };

    /// True when the current or the speed loop of `sc` selects "rst".
    pub fn uses_rst(sc: &Scenario) -> bool {
        sc.current_loop.controller == CurrentController::Rst
            || sc.speed_loop.controller == SpeedController::Rst
    }

    /// ITAE ω_n of the current and speed loops of a scenario (rad/s), defaults applied.
    pub fn bandwidths(sc: &Scenario) -> (f64, f64) {
        let ts = sc.rates.ts();
        let tw = ts * f64::from(sc.rates.speed_divider);
        let wc = sc
            .current_loop
            .itae_omega_rad_s
            .unwrap_or_else(|| default_current_omega(ts));
        let ws = sc
            .speed_loop
            .itae_omega_rad_s
            .unwrap_or_else(|| default_speed_omega(wc, tw));
        (wc, ws)
    }

    /// The RST designs of a scenario's motor, rates and bandwidths.
    pub fn design_from_scenario(sc: &Scenario) -> Result<RstDriveDesign, String> {
        let (wc, ws) = bandwidths(sc);
        RstDriveDesign::new(
            &sc.motor_params(),
            sc.rates.ts(),
            sc.rates.speed_divider,
            wc,
            ws,
            sc.observer.speed_filter_tau_s,
        )
    }

    /// Checks the RST fields of a scenario (and that the design exists); the error names the
    /// field and the rule.
    pub fn validate(sc: &Scenario) -> Result<(), String> {
        let cur = sc.current_loop.controller == CurrentController::Rst;
        let spd = sc.speed_loop.controller == SpeedController::Rst;
        if sc.current_loop.itae_omega_rad_s.is_some() && !cur {
            return Err(
                "current_loop.itae_omega_rad_s is set but current_loop.controller is not \"rst\""
                    .into(),
            );
        }
        if sc.speed_loop.itae_omega_rad_s.is_some() && !spd {
            return Err(
                "speed_loop.itae_omega_rad_s is set but speed_loop.controller is not \"rst\""
                    .into(),
            );
        }
        if !(cur || spd) {
            return Ok(());
        }
        let ts = sc.rates.ts();
        let tw = ts * f64::from(sc.rates.speed_divider);
        let (wc, ws) = bandwidths(sc);
        if !(wc.is_finite() && wc > 0.0 && wc * ts <= 1.0) {
            return Err(format!(
                "current_loop.itae_omega_rad_s = {wc} must be in (0, 1/T_s = {:.0}] rad/s",
                1.0 / ts
            ));
        }
        if !(ws.is_finite() && ws > 0.0 && ws * tw <= 1.0) {
            return Err(format!(
                "speed_loop.itae_omega_rad_s = {ws} must be in (0, 1/T_w = {:.0}] rad/s (T_w = speed_divider·T_s)",
                1.0 / tw
            ));
        }
        design_from_scenario(sc)
            .map(|_| ())
            .map_err(|e| format!("RST design failed: {e}"))
    }
}

/// Wiring of the polar current laws ([`drivelab_control::control::polar`]).
pub mod polar {
    use super::Scenario;
    use crate::config::{CurrentController, SpeedController};
    use drivelab_control::control::cdm::CdmDelay;
    use drivelab_control::control::polar::{
        PolarCurrentController, PolarMode, PolarSpec, SpmsmModel,
    };

    /// The polar law a scenario selects, if any.
    pub fn mode_of(sc: &Scenario) -> Option<PolarMode> {
        match sc.current_loop.controller {
            CurrentController::Polar => Some(PolarMode::Polar),
            CurrentController::VoltagePhase => Some(PolarMode::VoltagePhase),
            CurrentController::PolarFw => Some(PolarMode::PolarFw),
            _ => None,
        }
    }

    /// The polar law's settings for a scenario (T_u = T_s, V_amax = V_dc/√3), if it selects one.
    pub fn spec_from_scenario(sc: &Scenario) -> Option<PolarSpec> {
        let cl = &sc.current_loop;
        mode_of(sc).map(|mode| {
            let mut sp = PolarSpec::paper(
                mode,
                SpmsmModel::from_motor(&sc.motor_params()),
                sc.rates.ts(),
                sc.u_max(),
            );
            if let Some(v) = cl.polar_sigma_delta_rad_s {
                sp.sigma_delta_rad_s = v;
            }
            if let Some(v) = cl.polar_sigma_v_rad_s {
                sp.sigma_v_rad_s = v;
            }
            sp.cdm_delay = cl.cdm_delay;
            if let Some(v) = cl.cdm_tau21_samples {
                sp.cdm_tau21_samples = v;
            }
            if let Some(v) = cl.cdm_setpoint_weight {
                sp.cdm_setpoint_weight = v;
            }
            sp
        })
    }

    /// The controller a scenario selects, if it selects a polar law.
    pub fn controller_from_scenario(sc: &Scenario) -> Option<PolarCurrentController> {
        spec_from_scenario(sc).map(|sp| PolarCurrentController::new(&sp))
    }

    /// Scenario rules of the polar laws and of the current-reference profile; the error names
    /// the field and the rule.
    pub fn validate(sc: &Scenario) -> Result<(), String> {
        if !sc.reference.i_q_a.is_empty()
            && sc.speed_loop.controller != SpeedController::CurrentReference
        {
            return Err(
                "reference.i_q_a is set but speed_loop.controller is not \"current-reference\" (a speed controller computes i_q*)"
                    .into(),
            );
        }
        let cl = &sc.current_loop;
        let mode = mode_of(sc);
        // Each setting belongs to the laws that read it: set for another law it would be
        // ignored, so it is refused, as are values no sampled design can use.
        let sigma_laws = [PolarMode::VoltagePhase, PolarMode::PolarFw];
        let settings = [
            (
                "polar_sigma_delta_rad_s",
                cl.polar_sigma_delta_rad_s,
                &sigma_laws[..],
                "\"voltage-phase\" or \"polar-fw\"",
            ),
            (
                "polar_sigma_v_rad_s",
                cl.polar_sigma_v_rad_s,
                &[PolarMode::PolarFw][..],
                "\"polar-fw\"",
            ),
            (
                "cdm_tau21_samples",
                cl.cdm_tau21_samples,
                &[PolarMode::Polar][..],
                "\"polar\"",
            ),
            (
                "cdm_setpoint_weight",
                cl.cdm_setpoint_weight,
                &[PolarMode::Polar][..],
                "\"polar\"",
            ),
        ];
        for (field, value, laws, names) in settings {
            if value.is_some() && !mode.is_some_and(|m| laws.contains(&m)) {
                return Err(format!(
                    "current_loop.{field} is set but current_loop.controller is not {names}"
                ));
            }
        }
        if cl.cdm_delay != CdmDelay::Paper && mode != Some(PolarMode::Polar) {
            return Err(
                "current_loop.cdm_delay is set but current_loop.controller is not \"polar\"".into(),
            );
        }
        for (field, value) in [
            ("polar_sigma_delta_rad_s", cl.polar_sigma_delta_rad_s),
            ("polar_sigma_v_rad_s", cl.polar_sigma_v_rad_s),
        ] {
            if let Some(v) = value.filter(|v| !(v.is_finite() && (-1e6..0.0).contains(v))) {
                return Err(format!(
                    "current_loop.{field} = {v} must be negative, from -1000000 rad/s up to (not including) 0"
                ));
            }
        }
        if let Some(v) = cl
            .cdm_tau21_samples
            .filter(|v| !(v.is_finite() && (1.0..=10_000.0).contains(v)))
        {
            return Err(format!(
                "current_loop.cdm_tau21_samples = {v} must be in [1, 10000] samples (τ_21 of eq. 36; the paper's is 10)"
            ));
        }
        if let Some(v) = cl
            .cdm_setpoint_weight
            .filter(|v| !(v.is_finite() && (0.0..=1.0).contains(v)))
        {
            return Err(format!(
                "current_loop.cdm_setpoint_weight = {v} must be in [0, 1] (the weight of i_q* in C_21's proportional term)"
            ));
        }
        if let Some(mode) = mode {
            let m = sc.motor.resolve()?;
            if (m.l_d_h - m.l_q_h).abs() > 0.01 * m.l_d_h.max(m.l_q_h) {
                return Err(format!(
                    "current_loop.controller = \"{}\" is the surface-PMSM law of Miyajima et al.: it needs L_d = L_q (within 1 %), got L_d = {} H, L_q = {} H",
                    mode.name(),
                    m.l_d_h,
                    m.l_q_h
                ));
            }
        }
        Ok(())
    }
}

/// Wiring of the minimal-order αβ observer ([`drivelab_control::observer_sensorless`]), and
/// its metrics on a trace.
pub mod observer_sensorless {
    use super::Scenario;
    use crate::trace::TraceRow;
    use drivelab_control::observer_sensorless::{
        truncation_error, ObserverDesign, ObserverMode, SensorlessObserver, SensorlessSettings,
        OMEGA_MIN_FRACTION,
    };
    use std::f64::consts::{PI, TAU};

    /// The observer design of a scenario (None in encoder mode).
    pub fn design_from_scenario(sc: &Scenario) -> Option<ObserverDesign> {
        let o = &sc.observer;
        (o.mode != ObserverMode::Encoder).then(|| {
            let m = sc.motor_params();
            let ts = sc.rates.ts();
            ObserverDesign {
                mode: o.mode,
                discretisation: o.discretisation,
                pole_tau_s: o.pole_tau_s,
                lambda: libm::exp(-ts / o.pole_tau_s),
                omega_min_rad_s: OMEGA_MIN_FRACTION * m.omega_rated_rad_s,
                initial_angle_error_deg: o.initial_angle_error_deg,
                zeta_at_rated_speed: truncation_error(&m, ts, m.omega_rated_rad_s),
            }
        })
    }

    /// Angle error θ̂_e − θ_e of a trace row, degrees in [−180, 180).
    pub fn angle_error_deg(r: &TraceRow) -> f64 {
        ((r.theta_hat - r.theta_e + PI).rem_euclid(TAU) - PI).to_degrees()
    }

    /// Band around the steady-state angle error that counts as converged, degrees.
    pub const CONVERGED_BAND_DEG: f64 = 1.0;
    /// How long the error must stay in the band, s.
    pub const CONVERGED_HOLD_S: f64 = 0.02;

    /// Observer metrics of a trace (None in encoder mode): (steady-state angle error in
    /// degrees, the mean over the last 10 % of the run; convergence time in ms, from t = 0
    /// until the error stays within ±[`CONVERGED_BAND_DEG`] of the steady state for
    /// [`CONVERGED_HOLD_S`] or to the end of the run).
    pub fn angle_metrics(sc: &Scenario, rows: &[TraceRow]) -> Option<(f64, Option<f64>)> {
        if sc.observer.mode == ObserverMode::Encoder || rows.is_empty() {
            return None;
        }
        let end = rows.last().map(|r| r.t).unwrap_or(0.0);
        let tail: Vec<f64> = rows
            .iter()
            .filter(|r| r.t >= 0.9 * end)
            .map(angle_error_deg)
            .collect();
        let ss = tail.iter().sum::<f64>() / tail.len() as f64;
        let inside = |r: &TraceRow| (angle_error_deg(r) - ss).abs() <= CONVERGED_BAND_DEG;
        let mut conv = None;
        let mut start: Option<usize> = None;
        for (i, r) in rows.iter().enumerate() {
            if inside(r) {
                let s = *start.get_or_insert(i);
                if r.t - rows[s].t >= CONVERGED_HOLD_S - 1e-12 || i + 1 == rows.len() {
                    conv = Some(rows[s].t * 1e3);
                    break;
                }
            } else {
                start = None;
            }
        }
        Some((ss, conv))
    }

    /// Checks the `[observer]` fields of the observer; the error names the field and the rule.
    pub fn validate(sc: &Scenario) -> Result<(), String> {
        let o = &sc.observer;
        let ts = sc.rates.ts();
        if !(o.pole_tau_s.is_finite() && o.pole_tau_s >= ts && o.pole_tau_s <= 1.0) {
            return Err(format!(
                "observer.pole_tau_s = {} must be in [T_s = {ts}, 1] s",
                o.pole_tau_s
            ));
        }
        if !(o.initial_angle_error_deg.is_finite() && o.initial_angle_error_deg.abs() <= 360.0) {
            return Err(format!(
                "observer.initial_angle_error_deg = {} must be within ±360",
                o.initial_angle_error_deg
            ));
        }
        if o.mode != ObserverMode::Encoder {
            let m = sc.motor.resolve()?;
            if (m.l_d_h - m.l_q_h).abs() > 1e-6 * m.l_d_h.max(m.l_q_h) {
                return Err(format!(
                    "observer.mode = {:?} needs a surface PMSM (L_d = L_q, Low eq. 11); this motor has L_d = {} H, L_q = {} H",
                    o.mode, m.l_d_h, m.l_q_h
                )
                .replace("Sensorless", "\"sensorless\"")
                .replace("Monitor", "\"monitor\""));
            }
        }
        Ok(())
    }

    /// The observer of a scenario (None in encoder mode).
    pub fn from_scenario(sc: &Scenario) -> Option<SensorlessObserver> {
        (sc.observer.mode != ObserverMode::Encoder).then(|| {
            SensorlessObserver::new(
                &sc.motor_params(),
                SensorlessSettings {
                    ts: sc.rates.ts(),
                    pole_tau_s: sc.observer.pole_tau_s,
                    discretisation: sc.observer.discretisation,
                    speed_filter_tau_s: sc.observer.speed_filter_tau_s,
                    initial_angle_rad: sc.observer.initial_angle_error_deg.to_radians(),
                },
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::observer_sensorless::angle_error_deg;
    use super::Scenario;

    fn scenario(name: &str, edits: &[(&str, &str)]) -> Scenario {
        let path = format!("{}/../../scenarios/{name}.toml", env!("CARGO_MANIFEST_DIR"));
        let mut text = std::fs::read_to_string(&path).unwrap();
        for (a, b) in edits {
            assert!(text.contains(a), "{name}.toml has no '{a}'");
            text = text.replace(a, b);
        }
        Scenario::from_toml(&text, &path).unwrap()
    }

    /// (From `observer_sensorless.rs`.)
    #[test]
    fn sensorless_flying_start_converges_from_any_angle() {
        // The sensorless drive catches the motor turning at 300 rpm with the estimate 0°, 90°
        // or 180° off, then runs the low-rst profile: the back-EMF based speed estimate does
        // not depend on the angle estimate, so the observer converges in a few τ_o.
        for err in ["0.0", "90.0", "180.0"] {
            let sc = scenario(
                "low-rst-sensorless",
                &[
                    (
                        "initial_angle_error_deg = 0.0",
                        &format!("initial_angle_error_deg = {err}"),
                    ),
                    (
                        "[rates]",
                        "[mechanics]\ninitial_speed_rad_s = 31.415926535897931\n\n[rates]",
                    ),
                ],
            );
            let rows = crate::drive::run_inprocess(&sc);
            let conv = rows
                .iter()
                .position(|r| r.t > 0.003 && angle_error_deg(r).abs() < 5.0)
                .map(|i| rows[i].t)
                .unwrap();
            let worst_after = rows
                .iter()
                .filter(|r| r.t >= 0.05)
                .map(|r| angle_error_deg(r).abs())
                .fold(0.0, f64::max);
            let w_end = rows.iter().rev().find(|r| r.t <= 1.2).unwrap().omega_m;
            eprintln!(
                "initial error {err}°: within 5° after {:.1} ms, worst |error| after 50 ms {worst_after:.2}°, ω(1.2 s) = {w_end:.2} rad/s",
                conv * 1e3
            );
            assert!(conv < 0.015, "{err}: {conv}");
            assert!(worst_after < 5.0, "{err}: {worst_after}");
            assert!((w_end - 125.66).abs() < 0.5, "{err}: {w_end}");
        }
    }

    /// (From `control/rst.rs`.) The speed loop in the whole drive (real current loops instead
    /// of the design model's one-sample delay, encoder speed through the Bessel filter at T_s):
    /// a small step that does not saturate follows the designed response t0·B⁻/(z·A_m) within
    /// 5 % of the step.
    #[test]
    fn speed_loop_in_the_drive_follows_the_design_model() {
        let path = format!(
            "{}/../../scenarios/low-rst.toml",
            env!("CARGO_MANIFEST_DIR")
        );
        let text = std::fs::read_to_string(&path)
            .unwrap()
            // 300 → 330 rpm without load: i_q* stays far from its limit.
            .replace(
                "{ t_s = 0.2, value = 125.66370614359172 }",
                "{ t_s = 0.2, value = 34.557519189487724 }",
            )
            .replace("torque_nm = [{ t_s = 0.1, value = 2.0 }]", "torque_nm = []");
        let sc = Scenario::from_toml(&text, "low-rst-small-step").unwrap();
        let d = crate::drive::DriveDesign::from_scenario(&sc).rst.unwrap();
        let rows = crate::drive::run_inprocess(&sc);
        let n = sc.rates.speed_divider as usize;
        let k0 = (0.2 * sc.rates.sample_hz).round() as usize;
        let (w0, dw) = (rows[k0].omega_hat, 34.55751918948773 - 31.41592653589793);
        let want = d.speed.step_response(100);
        let mut worst: f64 = 0.0;
        for (j, wj) in want.iter().enumerate() {
            let got = (rows[k0 + n * j].omega_hat - w0) / dw;
            assert!(rows[k0 + n * j].i_q_ref.abs() < 4.0);
            worst = worst.max((got - wj).abs());
        }
        eprintln!(
            "speed loop in the drive vs design model: worst deviation {worst:.4} of the step"
        );
        assert!(worst < 0.05, "{worst}");
    }
}
