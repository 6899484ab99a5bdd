//! `drivelab design`: the controller design of a scenario, printed so it can be checked by hand.

use drivelab::config::Scenario;
use drivelab::drive::DriveDesign;
use std::fmt::Write;

/// Renders the design printout of `sc`.
pub fn render(sc: &Scenario) -> String {
    let m = sc.motor_params();
    let d = DriveDesign::from_scenario(sc);
    let mut o = String::new();
    let _ = writeln!(
        o,
        "scenario {}: motor R = {} Ω, Ld = {} mH, Lq = {} mH, p = {}, ψ = {} Wb, J = {:e} kg·m², k_t = {:.4} N·m/A",
        sc.name, m.r_ohm, m.l_d_h * 1e3, m.l_q_h * 1e3, m.pole_pairs, m.psi_pm_wb, m.j_kgm2, m.k_t()
    );
    let c = &d.current;
    let _ = writeln!(
        o,
        "current PI (pole-zero cancellation, τ_c = {} ms): d: Kp = L_d/τ_c = {:.4} V/A, Ki = R/τ_c = {:.1} V/(A·s); q: Kp = L_q/τ_c = {:.4} V/A, Ki = {:.1} V/(A·s)",
        c.tau_c_s * 1e3, c.k_p_d, c.k_i_d, c.k_p_q, c.k_i_q
    );
    let s = &d.speed;
    let _ = writeln!(
        o,
        "speed PI (symmetrical optimum, every {} samples = {} Hz): T_sigma = {:.4} ms, a = {:.4}, T_eq = {:.4} ms",
        sc.rates.speed_divider,
        sc.rates.sample_hz / f64::from(sc.rates.speed_divider),
        s.t_sigma_s * 1e3,
        s.a,
        s.t_eq_s * 1e3
    );
    let _ = writeln!(
        o,
        "  Kp = J/(a·k_t·T_eq) = {:.6} A·s/rad, Ti = a²·T_eq = {:.4} ms, prefilter 1/(1 + Ti s)",
        s.k_p,
        s.t_i_s * 1e3
    );
    let _ = writeln!(
        o,
        "  design model (sampled cascade): rise time {:.2} ms (target {:.2} ms), overshoot {:.1} %",
        s.predicted_rise_time_s * 1e3,
        sc.speed_loop.rise_time_s * 1e3,
        s.predicted_overshoot_pct
    );
    if let Some(w) = &s.warning {
        let _ = writeln!(o, "  WARNING: {w}");
    }
    o
}
