//! `drivelab cdm-design`: the coefficient-diagram design of the polar current loops of
//! Miyajima et al. (eqs 26–37) at one operating point, printed so that eqs (28)–(31) can be
//! checked by hand.

use crate::expect::usage;
use anyhow::Result;
use drivelab_control::control::cdm::{self, CdmDesign};
use drivelab_control::control::polar::{self, FwDesign, SpmsmModel};
use std::fmt::Write;

/// Arguments of `drivelab cdm-design`.
#[derive(Debug, clap::Args)]
pub struct CdmArgs {
    /// Motor preset (miyajima = low1998, kyslan2015, ...) or a TOML file with a [motor]
    /// table. The law is for surface motors: L = (L_d + L_q)/2.
    #[arg(long, default_value = "miyajima")]
    pub motor: String,
    /// Control period T_u, µs.
    #[arg(long = "tu-us", value_name = "MICROSECONDS", default_value_t = 100.0)]
    pub tu_us: f64,
    /// Voltage limit V_amax, V (default: V_dc/√3 of --v-dc-v).
    #[arg(long = "v-amax-v", value_name = "VOLTS")]
    pub v_amax_v: Option<f64>,
    /// DC bus voltage, V; sets V_amax = V_dc/√3 when --v-amax-v is not given.
    #[arg(long = "v-dc-v", value_name = "VOLTS", default_value_t = 470.0)]
    pub v_dc_v: f64,
    /// Operating point: voltage amplitude V_ao, V (signed).
    #[arg(long = "v-ao-v", value_name = "VOLTS", allow_hyphen_values = true)]
    pub v_ao_v: f64,
    /// Operating point: voltage phase δ_o, degrees.
    #[arg(
        long = "delta-o-deg",
        value_name = "DEGREES",
        default_value_t = 0.0,
        allow_hyphen_values = true
    )]
    pub delta_o_deg: f64,
    /// Use this τ_12 instead of eq. (37), µs.
    #[arg(long = "tau12-us", value_name = "MICROSECONDS")]
    pub tau12_us: Option<f64>,
    /// Also print the section III designs (phase controller C_δ on ΔP_22, amplitude
    /// controller C_v on ΔP_11, eq. 11) at this mechanical speed, rpm, with V_ao as the
    /// equilibrium amplitude and δ_o from eq. (9).
    #[arg(long = "speed-rpm", value_name = "RPM", allow_hyphen_values = true)]
    pub speed_rpm: Option<f64>,
    /// Section III: q-axis current reference of the equilibrium, A.
    #[arg(
        long = "i-q-a",
        value_name = "AMPERES",
        default_value_t = 0.0,
        allow_hyphen_values = true,
        requires = "speed_rpm"
    )]
    pub i_q_a: f64,
    /// Section III: real part of the phase loop's poles, rad/s.
    #[arg(long = "sigma-delta-rad-s", alias = "sigma-delta", value_name = "RAD_PER_S", default_value_t = polar::SIGMA_DELTA_RAD_S, allow_hyphen_values = true, requires = "speed_rpm")]
    pub sigma_delta: f64,
    /// Section III: real part of the amplitude loop's poles, rad/s.
    #[arg(long = "sigma-v-rad-s", alias = "sigma-v", value_name = "RAD_PER_S", default_value_t = polar::SIGMA_V_RAD_S, allow_hyphen_values = true, requires = "speed_rpm")]
    pub sigma_v: f64,
    /// Print the design as JSON (SI units) instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Runs the command.
pub fn run(a: &CdmArgs) -> Result<()> {
    check(a)?;
    let m = crate::replay::resolve_motor(&a.motor)?;
    let v_amax = match a.v_amax_v {
        Some(v) => v,
        None => a.v_dc_v / 3f64.sqrt(),
    };
    let l = 0.5 * (m.l_d_h + m.l_q_h);
    let d = CdmDesign::new(
        m.r_ohm,
        l,
        a.tu_us * 1e-6,
        v_amax,
        a.v_ao_v,
        a.delta_o_deg.to_radians(),
        a.tau12_us.map(|t| t * 1e-6),
    );
    let fw = match a.speed_rpm {
        Some(rpm) => {
            // The laws run mirrored to ω_e ≥ 0 (polar.rs, reading 7).
            let w = (m.p() * rpm * std::f64::consts::PI / 30.0).abs();
            Some(FwDesign::new(
                &SpmsmModel::from_motor(&m),
                a.v_ao_v.abs(),
                a.i_q_a * rpm.signum(),
                w,
                a.tu_us * 1e-6,
                v_amax,
                a.sigma_delta,
                a.sigma_v,
            ))
        }
        None => None,
    };
    if a.json {
        crate::outln!(
            "{}",
            serde_json::to_string_pretty(&json_of(&d, m.psi_pm_wb, fw.as_ref())?)?
        );
    } else {
        crate::out!("{}", render(&a.motor, &d, m.psi_pm_wb));
        if let Some(f) = &fw {
            crate::out!("{}", render_fw(f));
        }
    }
    Ok(())
}

/// The design as JSON (SI units): the section IV design with its sampled loop's poles for a
/// motor of flux `k_e_wb` (`sampled_both`, ln(z)/T_u as [re, im] in rad/s, as the text
/// prints them), and with `fw` the section III design beside it (`{"cdm": …,
/// "flux_weakening": …}`).
fn json_of(d: &CdmDesign, k_e_wb: f64, fw: Option<&FwDesign>) -> Result<serde_json::Value> {
    let mut cdm = serde_json::to_value(d)?;
    cdm["sampled_both"] = serde_json::json!(polar::cdm_sampled_poles(d, k_e_wb));
    Ok(match fw {
        Some(f) => serde_json::json!({ "cdm": cdm, "flux_weakening": f }),
        None => cdm,
    })
}

/// Checks every number given, one option at a time: a one-line error naming the option, its
/// value and the range with its unit. The operating point (--v-ao-v, --delta-o-deg) may lie
/// beyond the paper's limits, which the design clamps it to and shows beside it as typed,
/// but not beyond a physical range (below).
fn check(a: &CdmArgs) -> Result<()> {
    // (option, value, lowest, lowest allowed itself, highest, unit)
    let mut ranges = vec![
        ("--tu-us", a.tu_us, 1.0, true, 100_000.0, "µs"),
        ("--v-dc-v", a.v_dc_v, 0.0, false, 100_000.0, "V"),
        ("--i-q-a", a.i_q_a, -10_000.0, true, 10_000.0, "A"),
    ];
    if let Some(v) = a.v_amax_v {
        ranges.push(("--v-amax-v", v, 0.0, false, 100_000.0, "V"));
    }
    if let Some(t) = a.tau12_us {
        ranges.push(("--tau12-us", t, 1.0, true, 10_000_000.0, "µs"));
    }
    if let Some(r) = a.speed_rpm {
        ranges.push(("--speed-rpm", r, -100_000.0, true, 100_000.0, "rpm"));
    }
    for (flag, v, lo, closed, hi, unit) in ranges {
        let low_ok = if closed { v >= lo } else { v > lo };
        if !(v.is_finite() && low_ok && v <= hi) {
            return Err(usage(if closed {
                format!("{flag} {v}: must be between {lo} and {hi} {unit}")
            } else {
                format!("{flag} {v}: must be more than {lo} and at most {hi} {unit}")
            }));
        }
    }
    // The operating point: V_ao is a signed amplitude, so its range is symmetric, with the
    // bound of the other voltage options (--v-dc-v, --v-amax-v ≤ 100000 V); |V_ao| above
    // V_amax is clamped to V_amax (cdm::limit_operating_point) and shown so. δ_o is the
    // voltage phase from the q axis (v_q = V_a cos δ, eq. 1): the law's phase output is
    // limited to ±90° (polar::DELTA_MAX), eqs (28)–(31) divide by cos δ_o, and the design
    // clamps δ_o to ±0.9·90° = ±81° (cdm::DELTA_O_MAX). A δ_o in 81°..90° is a point the
    // drive can reach and is clamped visibly; beyond ±90° cos δ_o changes sign and the clamp
    // would design a point unlike the one asked, so it is refused.
    for (flag, v, lo, hi, unit, units) in [
        ("--v-ao-v", a.v_ao_v, -100_000.0, 100_000.0, "V", "volts"),
        (
            "--delta-o-deg",
            a.delta_o_deg,
            -90.0,
            90.0,
            "degrees",
            "degrees",
        ),
    ] {
        if !v.is_finite() {
            return Err(usage(format!(
                "{flag} {v}: must be a finite number of {units}"
            )));
        }
        if !(lo..=hi).contains(&v) {
            return Err(usage(format!(
                "{flag} {v}: must be between {lo} and {hi} {unit}"
            )));
        }
    }
    for (flag, v) in [
        ("--sigma-delta-rad-s", a.sigma_delta),
        ("--sigma-v-rad-s", a.sigma_v),
    ] {
        if !(v.is_finite() && (-1e6..0.0).contains(&v)) {
            return Err(usage(format!(
                "{flag} {v}: must be negative, from -1000000 rad/s up to (not including) 0"
            )));
        }
    }
    Ok(())
}

/// "" when every pole ln(z)/T_u (re, im) of a sampled loop has a negative real part (|z| < 1),
/// else "; UNSTABLE: …" with the largest real part: the loop grows without bound as it runs.
fn unstable(poles: &[(f64, f64)]) -> String {
    let re = poles.iter().map(|p| p.0).fold(f64::NEG_INFINITY, f64::max);
    if re < 0.0 {
        return String::new();
    }
    format!(
        "; UNSTABLE: the sampled loop has a pole with real part {re:.1} rad/s ≥ 0 (|z| ≥ 1), so it grows without bound as it runs"
    )
}

/// Poles (re, im) in rad/s as "re±imj, …"; "none …" when there are none.
fn poles(v: &[(f64, f64)]) -> String {
    if v.is_empty() {
        return "none (no controller to close the loop with)".to_string();
    }
    v.iter()
        .map(|(re, im)| format!("{re:.1}{:+.1}j", im))
        .collect::<Vec<_>>()
        .join(", ")
}

/// The text printout of the section III designs at one operating point.
pub fn render_fw(f: &FwDesign) -> String {
    let mut o = String::new();
    let gains = |g: &Option<polar::PidGains>| {
        match g {
        Some(g) => format!(
            "C(s) = (q2 s² + q1 s + q0)/(s(s + f)): q2 = {:.6}, q1 = {:.6}, q0 = {:.6}, f = {:.3} rad/s (K_P = {:.6}, K_I = {:.6}, B = {:.6})",
            g.q2,
            g.q1,
            g.q0,
            g.f,
            g.k_p(),
            g.k_i(),
            g.b()
        ),
        None => "not placeable (numerator and denominator share a root, or f ≤ 0)".into(),
    }
    };
    let _ = writeln!(
        o,
        "flux weakening (section III) at ω_e = {:.3} rad/s, V_ao = {:.4} V, i_q* = {} A: δ_o (eq. 9) = {:.4} °, i_d,o = {:.4} A; plant poles −R/L ± jω_e on the circle |s| = {:.3} rad/s (eq. 12)",
        f.omega_e,
        f.v_ao_v,
        f.i_q_ref_a,
        f.delta_o_rad.to_degrees(),
        f.i_d_o_a,
        f.rho_rad_s
    );
    let _ = writeln!(
        o,
        "C_δ (i_q through δ) on ΔP_22 = ({:.4} s + {:.4})/(s² + {:.4} s + {:.4}), zero at s = {:.3} rad/s: poles asked real part {} rad/s: {}",
        f.p22.b1, f.p22.b0, f.p22.a1, f.p22.a0, f.zero_22_rad_s, f.sigma_delta_rad_s, poles(&f.poles_delta)
    );
    let _ = writeln!(o, "  {}", gains(&f.g_delta));
    let _ = writeln!(
        o,
        "C_v (i_d through V_a, eq. 11) on ΔP_11 = ({:.4} s + {:.4})/(s² + {:.4} s + {:.4}), zero at s = {:.3} rad/s: poles asked real part {} rad/s: {}",
        f.p11.b1, f.p11.b0, f.p11.a1, f.p11.a0, f.zero_11_rad_s, f.sigma_v_rad_s, poles(&f.poles_v)
    );
    let _ = writeln!(o, "  {}", gains(&f.g_v));
    let _ = writeln!(
        o,
        "sampled loop as it runs (ZOH, one-sample delay), poles ln(z)/T_u in rad/s: C_δ alone (V_a = V_ao): {}{}",
        poles(&f.sampled_delta),
        unstable(&f.sampled_delta)
    );
    let _ = writeln!(
        o,
        "  C_δ and C_v together: {}{}",
        poles(&f.sampled_both),
        unstable(&f.sampled_both)
    );
    short_floats(&o)
}

/// `text` with every number written with 7 or more decimals (a float printed whole, such as
/// 150.01041666666669 or 9999.999999999998) cut to 6 significant digits (150.010, 10000).
/// The figures printed with a fixed number of decimals (6 at most) and numbers in exponent
/// form are left as they are.
fn short_floats(text: &str) -> String {
    drivelab_runtime::text::rewrite_numbers(text, |n| {
        if n.decimals < 7 || matches!(n.after, Some(b'e' | b'E')) {
            return None;
        }
        let v: f64 = n.written.parse().ok()?;
        // 6 significant digits, trailing zeros of the fraction dropped.
        let digits = 6 - (v.abs().log10().floor() as i32 + 1).clamp(-20, 6);
        let t = format!("{v:.*}", digits.max(0) as usize);
        Some(if t.contains('.') {
            t.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            t
        })
    })
    .into_owned()
}

/// The text printout of a design.
pub fn render(motor: &str, d: &CdmDesign, k_e_wb: f64) -> String {
    let mut o = String::new();
    let us = |s: f64| s * 1e6;
    let _ = writeln!(
        o,
        "CDM design of the polar current loops (Miyajima et al. eqs 26-37), motor {motor}: R = {} Ω, L = {} mH, T_u = {:.3} µs, V_amax = {:.4} V",
        d.r_ohm,
        d.l_h * 1e3,
        us(d.tu_s),
        d.v_amax_v
    );
    let _ = writeln!(
        o,
        "operating point asked: V_ao = {} V, δ_o = {:.6}°; after the limits {:.4} V ≤ |V_ao| ≤ {:.4} V and |δ_o| ≤ 0.9·90° = 81°: V_ao = {} V, δ_o = {:.6}°, cos δ_o = {:.6}",
        // A value beyond the limits is clamped to them and shown as typed beside it.
        drivelab_runtime::text::readable_numbers(&d.v_ao_in_v.to_string()),
        d.delta_o_in_rad.to_degrees(),
        cdm::V_AO_MIN_FRAC * d.v_amax_v,
        d.v_amax_v,
        d.v_ao_v,
        d.delta_o_rad.to_degrees(),
        d.delta_o_rad.cos()
    );
    let _ = writeln!(
        o,
        "C_21 (i_q through V_a, eq. 24): γ_1 = {}, τ_21 = 10·T_u = {:.3} µs (eq. 36): a_1 = γ_1/τ_21 = {} 1/s, a_0 = γ_1/τ_21² = {} 1/s²",
        d.gamma1,
        us(d.tau21_s),
        d.a1_21,
        d.a0_21
    );
    let _ = writeln!(
        o,
        "  K_P21 = (a_1·L − R)/cos δ_o = {} V/A   (eq. 28)",
        d.k_p21
    );
    let _ = writeln!(
        o,
        "  K_I21 = a_0·L/cos δ_o = {} V/(A·s)   (eq. 29)",
        d.k_i21
    );
    let rule = if d.tau12_given {
        "given with --tau12-us".to_string()
    } else if d.tau12_slowed {
        format!(
            "< 0.01·V_amax = {:.4} V: τ_12 = 0.1·V_amax/|V_ao cos δ_o|·T_u (eq. 37)",
            cdm::TAU12_SWITCH_FRAC * d.v_amax_v
        )
    } else {
        format!(
            "≥ 0.01·V_amax = {:.4} V: τ_12 = 10·T_u (eq. 37)",
            cdm::TAU12_SWITCH_FRAC * d.v_amax_v
        )
    };
    let _ = writeln!(
        o,
        "C_12 (i_d through δ, eq. 25): |V_ao cos δ_o| = {:.6} V {rule}, so τ_12 = {} µs, a_1 = γ_1/τ_12 = {} 1/s, a_0 = γ_1/τ_12² = {} 1/s²",
        d.v_cos_v,
        us(d.tau12_s),
        d.a1_12,
        d.a0_12
    );
    let _ = writeln!(
        o,
        "  K_P12 = (a_1·L − R)/(−V_ao·cos δ_o) = {} rad/A   (eq. 30)",
        d.k_p12
    );
    let _ = writeln!(
        o,
        "  K_I12 = a_0·L/(−V_ao·cos δ_o) = {} rad/(A·s)   (eq. 31)",
        d.k_i12
    );
    let sampled = polar::cdm_sampled_poles(d, k_e_wb);
    let _ = writeln!(
        o,
        "sampled loop at 0 rpm as it runs (ZOH, one-sample delay, measured currents, δ_d linearised at K_e = {k_e_wb} Wb), poles ln(z)/T_u in rad/s: C_21 and C_12 together: {}{}",
        poles(&sampled),
        unstable(&sampled)
    );
    render_delay(&mut o, d);
    short_floats(&o)
}

/// Section IV at standstill with the one-sample computation delay: the q loop's design
/// model (cdm::QLoop, δ_o = 0) for the paper's design and the delay options, against the
/// target overshoot < 10 % with a rise ≤ 1.5× the paper's.
fn render_delay(o: &mut String, d: &CdmDesign) {
    use cdm::{CdmDelay, DelayedPlantCdm, QLoop};
    let (r, l, tu) = (d.r_ohm, d.l_h, d.tu_s);
    let us = |s: f64| s * 1e6;
    let paper = QLoop::paper(r, l, tu, CdmDelay::Paper);
    let (rise0, os0) = paper.step();
    let _ = writeln!(
        o,
        "q loop at δ_o = 0 with the one-sample delay (design model, 10-90 % rise, overshoot); target < 10 % within {:.0} µs (1.5× the paper's rise):",
        us(1.5 * rise0)
    );
    let _ = writeln!(
        o,
        "  paper (γ_1 = 2.5, τ_21 = 10·T_u, measured currents): {:.0} µs, {os0:.1} %",
        us(rise0)
    );
    let (rp, osp) = QLoop::paper(r, l, tu, CdmDelay::Predict).step();
    let _ = writeln!(
        o,
        "  cdm_delay = predict (currents one sample ahead): {:.0} µs, {osp:.1} %",
        us(rp)
    );
    let dp = DelayedPlantCdm::new(r, l, tu, cdm::GAMMA1, 2.0);
    let q = QLoop::delayed_plant(r, l, tu);
    let (rd, osd) = q.step();
    let (rb, osb) = QLoop { beta: 0.0, ..q }.step();
    let _ = writeln!(
        o,
        "  CDM on the delayed plant 1/((L s + R)(T_u s + 1)), γ_1 = {}, γ_2 = {}: a_3..a_0 = {:.6e}, {:.6e}, {:.4}, {:.2}; K_P21 = {} V/A, K_I21 = {} V/(A·s), τ = a_1/a_0 = {:.2} µs: {:.0} µs, {osd:.1} % (reference through the integrator only, β = 0: {:.0} µs, {osb:.1} %)",
        dp.gamma1, dp.gamma2, dp.a[0], dp.a[1], dp.a[2], dp.a[3], dp.k_p, dp.k_i, us(dp.tau_s), us(rd), us(rb)
    );
    for delay in [CdmDelay::Paper, CdmDelay::Predict] {
        let best = QLoop::paper(r, l, tu, delay).least_overshoot_within(1.5 * rise0);
        if let Some((t, rr, os)) = best {
            let _ = writeln!(
                o,
                "  γ_1 = 2.5, any τ_21 from 2 to 40·T_u, {delay:?}: least overshoot within the rise: {os:.1} % (τ_21 = {t}·T_u, {:.0} µs)",
                us(rr)
            );
        }
    }
    let (rs, oss) = QLoop {
        tau_samples: 5.0,
        beta: 0.6,
        ..QLoop::paper(r, l, tu, CdmDelay::Predict)
    }
    .step();
    let _ = writeln!(
        o,
        "  predict, τ_21 = 5·T_u, β = 0.6 (scenario miyajima-polar-0rpm-predict): {:.0} µs, {oss:.1} %",
        us(rs)
    );
}

/// The polar law of a scenario (`drivelab design`): the CDM loops at δ_o = 0, the limits, and
/// for the flux-weakening laws the pole rule of the phase and amplitude controllers.
pub fn render_polar_design(p: &drivelab_control::control::polar::PolarDesign) -> String {
    use drivelab_control::control::polar::PolarMode;
    let mut o = String::new();
    let sp = &p.spec;
    let _ = writeln!(
        o,
        "polar current law \"{}\" (Miyajima et al.): R = {} Ω, L = {} mH, K_e = {} Wb, T_u = {:.3} µs, V_amax = V_dc/√3 = {:.4} V",
        sp.mode.name(),
        sp.model.r_ohm,
        sp.model.l_h * 1e3,
        sp.model.k_e_wb,
        sp.tu_s * 1e6,
        sp.v_amax_v
    );
    match sp.mode {
        PolarMode::Polar => {
            let _ = writeln!(
                o,
                "  C_21, C_12: CDM γ_1 = {}, τ_21 = {}·T_u = {:.3} µs (a_1 = {} 1/s, a_0 = {} 1/s²), τ_12 per eq. (37), gains rescheduled every sample from eqs (38)-(39); at δ_o = 0: K_P21 = {} V/A, K_I21 = {} V/(A·s) (drivelab cdm-design prints any operating point)",
                p.gamma1,
                sp.cdm_tau21_samples,
                p.tau21_s * 1e6,
                p.a1_21,
                p.a0_21,
                p.k_p21_at_0,
                p.k_i21_at_0
            );
            if !sp.cdm_delay.is_paper() || sp.cdm_setpoint_weight != 1.0 {
                let _ = writeln!(
                    o,
                    "  delay: {:?} (the loops see the current predicted one sample ahead when Predict); C_21's proportional term K_P21·(β·i_q* − i_q), β = {}",
                    sp.cdm_delay, sp.cdm_setpoint_weight
                );
            }
            let _ = writeln!(
                o,
                "  limits: {:.4} V ≤ |V_ao| ≤ V_amax, |δ_o| ≤ {:.4} rad; outputs |V_a| ≤ V_amax, |δ| ≤ {:.4} rad; integrators frozen while an output is limited",
                p.v_ao_min_v, p.delta_o_max_rad, p.delta_max_rad
            );
        }
        PolarMode::VoltagePhase | PolarMode::PolarFw => {
            let _ = writeln!(
                o,
                "  phase controller: filtered PID on ΔP_22 = Δi_q/Δδ of eq. (2) at (V_ao = V_a[k−1], δ_o of eq. 9), four poles with real part σ_δ = {} rad/s, pairs on the circle through the plant poles (eq. 12); |δ| ≤ π/2",
                p.sigma_delta_rad_s
            );
            if sp.mode == PolarMode::PolarFw {
                let _ = writeln!(
                    o,
                    "  amplitude controller C_v: filtered PID on ΔP_11 = Δi_d/ΔV_a (eq. 11), four poles with real part σ_v = {} rad/s, pairs on the circle through the plant poles; 0 ≤ V_a ≤ V_amax, states not renewed while V_a is limited",
                    p.sigma_v_rad_s
                );
            } else {
                let _ = writeln!(o, "  V_a = V_amax (no amplitude controller)");
            }
        }
    }
    short_floats(&o)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Section III at 800 rpm, V_dc = 100 V, the paper's σ_δ = −600 rad/s: the phase loop as
    /// it runs is unstable at i_q* = 3 A (its zero inside |σ|) and stable at 0.5 A, and the
    /// printout says so of exactly those lines.
    #[test]
    fn a_sampled_flux_weakening_loop_that_diverges_is_called_unstable() {
        let m = drivelab_control::motor::MotorParams::low1998();
        let md = SpmsmModel::from_motor(&m);
        let w = m.p() * 800.0 * std::f64::consts::PI / 30.0;
        let vmax = 100.0 / 3f64.sqrt();
        let lines = |iq: f64| {
            let f = FwDesign::new(&md, vmax, iq, w, 1e-4, vmax, -600.0, -300.0);
            render_fw(&f)
                .lines()
                .filter(|l| l.contains("UNSTABLE"))
                .map(str::to_string)
                .collect::<Vec<_>>()
        };
        let hi = lines(3.0);
        assert_eq!(hi.len(), 2, "{hi:?}");
        assert!(
            hi[0].starts_with("sampled loop as it runs")
                && hi[1].starts_with("  C_δ and C_v together"),
            "{hi:?}"
        );
        for l in &hi {
            assert!(
                l.ends_with("(|z| ≥ 1), so it grows without bound as it runs"),
                "{l}"
            );
        }
        assert!(lines(0.5).is_empty());
    }

    /// Section IV at 0 rpm (the printout's eqs 28–31 at V_ao = 100 V, δ_o = 0, V_dc = 470 V):
    /// the sampled loop of C_21 and C_12 as it runs, stable at the paper's T_u = 100 µs, and
    /// unstable at T_u = 400 µs with the τ_12 = 1000 µs of the paper's T_u kept.
    #[test]
    fn the_section_iv_sampled_loop_is_printed_and_called_unstable_when_it_diverges() {
        let m = drivelab_control::motor::MotorParams::low1998();
        let l = 0.5 * (m.l_d_h + m.l_q_h);
        let vmax = 470.0 / 3f64.sqrt();
        let sampled = |tu_s: f64, tau12_s: Option<f64>| {
            let d = CdmDesign::new(m.r_ohm, l, tu_s, vmax, 100.0, 0.0, tau12_s);
            render("miyajima", &d, m.psi_pm_wb)
                .lines()
                .filter(|l| l.starts_with("sampled loop at 0 rpm as it runs"))
                .map(str::to_string)
                .collect::<Vec<_>>()
        };
        let paper = sampled(1e-4, None);
        assert_eq!(paper.len(), 1, "{paper:?}");
        assert!(
            paper[0].contains("C_21 and C_12 together: -") && !paper[0].contains("UNSTABLE"),
            "{paper:?}"
        );
        let d = CdmDesign::new(m.r_ohm, l, 1e-4, vmax, 100.0, 0.0, None);
        let poles = &json_of(&d, m.psi_pm_wb, None).unwrap()["sampled_both"];
        assert_eq!(poles.as_array().map(Vec::len), Some(6), "{poles}");
        assert!(poles[0][0].as_f64().unwrap() < 0.0, "{poles}");
        let slow = sampled(4e-4, Some(1e-3));
        assert_eq!(slow.len(), 1, "{slow:?}");
        assert!(
            slow[0].contains("; UNSTABLE: the sampled loop has a pole with real part ")
                && slow[0].ends_with("(|z| ≥ 1), so it grows without bound as it runs"),
            "{slow:?}"
        );
    }

    #[test]
    fn floats_printed_whole_are_cut_to_six_digits_and_fixed_ones_kept() {
        assert_eq!(
            short_floats("τ_12 = 9999.999999999998 µs, a_1 = 250.00000000000003 1/s"),
            "τ_12 = 10000 µs, a_1 = 250 1/s"
        );
        assert_eq!(
            short_floats("K_P = 150.01041666666669, K_I = -307562.6736111112, x = 0.000123456789"),
            "K_P = 150.01, K_I = -307563, x = 0.000123457"
        );
        // Fixed decimals, exponents, whole numbers and names with digits: as they are.
        let kept =
            "cos δ_o = 1.000000, a_3 = 3.000000e-6, 2.1234567e-3, 2500000 1/s, eq. 37, K_P21";
        assert_eq!(short_floats(kept), kept);
    }
}
