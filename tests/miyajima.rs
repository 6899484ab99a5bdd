//! Miyajima, Fujimoto & Fujitsuna reproduced with the real processes: current
//! control with the inputs in polar coordinates (section IV, Figs 7-8), voltage-phase flux
//! weakening with and without the amplitude controller (section III, Figs 2-3), and the CDM
//! design printout (eqs 28-31). Each run uses its own bus id and run folder and checks that no
//! process and no bus file is left.

mod common;
use common::*;
use drivelab_control::control::cdm;
use drivelab_control::control::polar::{FwDesign, SpmsmModel};

fn load(p: &str) -> drivelab_runtime::config::Scenario {
    let path = if p.ends_with(".toml") {
        p.to_string()
    } else {
        format!("{SCENARIOS}/{p}.toml")
    };
    drivelab_runtime::config::Scenario::from_toml(&std::fs::read_to_string(&path).unwrap(), &path)
        .unwrap()
}

/// Integral action leaves no steady-state error: the largest |error| over the last 1 ms of
/// the run is below `tol` and below the one over the 1 ms before (a loop without an
/// integrator settles to a constant error, which does not shrink), unless it is a thousandth
/// of `tol` already (rounding). Returns both.
fn settling(
    rows: &[drivelab_runtime::trace::TraceRow],
    tol: f64,
    err: impl Fn(&drivelab_runtime::trace::TraceRow) -> f64,
) -> (f64, f64) {
    let end = rows.last().unwrap().t;
    let worst = |a: f64, b: f64| {
        rows.iter()
            .filter(|x| x.t > end - b && x.t <= end - a)
            .map(|x| err(x).abs())
            .fold(0.0, f64::max)
    };
    let (before, last) = (worst(1e-3, 2e-3), worst(0.0, 1e-3));
    assert!(
        last <= tol && (last < before || last <= tol * 1e-3),
        "error over the last ms {last} (at most {tol}), the ms before {before}"
    );
    (before, last)
}

/// A current error that the paper's figures would show: 1 % of the 2 A step. The runs end
/// 9 ms after the step, 9 of the design's 1 ms time constants (τ_21 = 10 T_u).
const CURRENT_TOL_A: f64 = 0.02;
/// The voltage phase's error from its steady state at standstill (0), rad: one degree.
const PHASE_TOL_RAD: f64 = std::f64::consts::PI / 180.0;

/// Equal to the printout's precision: `cdm-design` prints its figures to 6 significant
/// digits (a wrong equation is off by far more: a missing cos δ_o at 20° by 6 %).
fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-5 * b.abs().max(1e-9)
}

#[test]
fn cdm_printout_gives_the_gains_of_eqs_28_to_31() {
    // The miyajima motor (low1998 surface set): R = 2.5 Ω, L = 30 mH. T_u = 100 µs.
    let (r, l, tu) = (2.5, 30e-3, 100e-6);
    let vmax = 271.4;
    // (V_ao, δ_o in degrees) → after the paper's limits: |V_ao| ≥ 0.001·V_amax, |δ_o| ≤ 81°.
    for (v_ao, d_deg, v_used, d_used) in [
        (5.0, 0.0, 5.0, 0.0),
        (30.0, 20.0, 30.0, 20.0),
        (-12.0, -35.0, -12.0, -35.0),
        (1.0, 0.0, 1.0, 0.0), // |V_ao cos δ_o| < 0.01·V_amax: τ_12 slowed (eq. 37)
        (0.0, 0.0, 0.001 * vmax, 0.0), // V_ao limited to 0.001·V_amax
        (100.0, 85.0, 100.0, 81.0), // δ_o limited to 0.9·π/2
    ] {
        let (va, dd) = (format!("{v_ao}"), format!("{d_deg}"));
        let o = drivelab(&[
            "cdm-design",
            "--motor",
            "miyajima",
            "--tu-us",
            "100",
            "--v-amax-v",
            "271.4",
            "--v-ao-v",
            &va,
            "--delta-o-deg",
            &dd,
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let t = String::from_utf8_lossy(&o.stdout).into_owned();
        let c = f64::to_radians(d_used).cos();
        // Eq. (36): τ_21 = 10·T_u; CDM standard form γ_1 = a_1²/a_0 = 2.5, τ = a_1/a_0.
        let tau21 = 10.0 * tu;
        let (a1, a0) = (2.5 / tau21, 2.5 / (tau21 * tau21));
        assert!(close(number_after(&t, "a_1 = γ_1/τ_21 = "), a1), "{t}");
        assert!(close(number_after(&t, "a_0 = γ_1/τ_21² = "), a0), "{t}");
        let kp21 = number_after(&t, "K_P21 = (a_1·L − R)/cos δ_o = ");
        let ki21 = number_after(&t, "K_I21 = a_0·L/cos δ_o = ");
        assert!(
            close(kp21, (a1 * l - r) / c),
            "{v_ao} {d_deg}: K_P21 {kp21}"
        );
        assert!(close(ki21, a0 * l / c), "{v_ao} {d_deg}: K_I21 {ki21}");
        // Eq. (37).
        let g = (v_used * c).abs();
        let tau12 = if g >= 0.01 * vmax {
            10.0 * tu
        } else {
            0.1 * vmax / g * tu
        };
        assert!(
            close(number_after(&t, "so τ_12 = ") * 1e-6, tau12),
            "{v_ao} {d_deg}: {t}"
        );
        let (b1, b0) = (2.5 / tau12, 2.5 / (tau12 * tau12));
        let kp12 = number_after(&t, "K_P12 = (a_1·L − R)/(−V_ao·cos δ_o) = ");
        let ki12 = number_after(&t, "K_I12 = a_0·L/(−V_ao·cos δ_o) = ");
        assert!(
            close(kp12, (b1 * l - r) / (-v_used * c)),
            "{v_ao} {d_deg}: K_P12 {kp12}"
        );
        assert!(
            close(ki12, b0 * l / (-v_used * c)),
            "{v_ao} {d_deg}: K_I12 {ki12}"
        );
        eprintln!("V_ao = {v_ao} V, δ_o = {d_deg}°: K_P21 {kp21:.4}, K_I21 {ki21:.1}, τ_12 {:.1} µs, K_P12 {kp12:.4}, K_I12 {ki12:.3}", tau12 * 1e6);
        // C_21 designed on the delayed plant 1/((L s + R)(T_u s + 1)): the closed loop
        // L·T_u s³ + (L + R·T_u) s² + (R + K_P) s + K_I with γ_1 = 2.5 and γ_2 = 2.
        let dp = &t[t.find("CDM on the delayed plant").unwrap()..];
        let (a3, a2) = (l * tu, l + r * tu);
        let a1 = a2 * a2 / (2.0 * a3);
        let a0 = a1 * a1 / (2.5 * a2);
        assert!(close(number_after(dp, "K_P21 = "), a1 - r), "{dp}");
        assert!(close(number_after(dp, "K_I21 = "), a0), "{dp}");
    }
    // Section III (--speed-rpm): the flux-weakening scenarios' operating point at 3 A.
    let o = drivelab(&[
        "cdm-design",
        "--motor",
        "miyajima",
        "--v-dc-v",
        "100",
        "--v-ao-v",
        "57.735",
        "--speed-rpm",
        "800",
        "--i-q-a",
        "3",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let t = String::from_utf8_lossy(&o.stdout).into_owned();
    let w = 4.0 * 800.0 * std::f64::consts::PI / 30.0;
    assert!(close(
        number_after(&t, "at ω_e = "),
        (w * 1e3).round() / 1e3
    ));
    // Eq. (12): the circle through −R/L ± jω_e.
    let rho = number_after(&t, "on the circle |s| = ");
    assert!((rho - (r / l).hypot(w)).abs() < 1e-3, "{t}");
    // ΔP_22's zero of eq. (2): s = ω_e cot δ_o − R/L, with δ_o as printed (4 decimals in °).
    let d_o = number_after(&t, "δ_o (eq. 9) = ").to_radians();
    let z = number_after(&t, "zero at s = ");
    assert!(
        (z - (w / d_o.tan() - r / l)).abs() < 1e-3 * z.abs().max(1.0),
        "{z} {t}"
    );
    // The pole numbers of section III-C are the defaults.
    assert_eq!(number_after(&t, "poles asked real part "), -600.0);
    let cv = &t[t.find("C_v (i_d through V_a").unwrap()..];
    assert_eq!(number_after(cv, "poles asked real part "), -300.0);
    for line in [
        "C(s) = (q2 s² + q1 s + q0)/(s(s + f))",
        "sampled loop as it runs",
    ] {
        assert!(t.contains(line), "{line} not in {t}");
    }

    // An operating point above the inverter's limit is clamped to it, and shown as typed.
    let o = drivelab(&["cdm-design", "--v-ao-v", "1000"]);
    let t = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{t}");
    assert!(
        t.contains("operating point asked: V_ao = 1000 V") && t.contains("V_ao = 271.355 V"),
        "{t}"
    );
    // A value out of its range: one clear line, exit code 2 (a usage error).
    let o = drivelab(&["cdm-design", "--v-ao-v", "5", "--tu-us", "0"]);
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("--tu-us"), "{err}");
}

#[test]
fn polar_control_at_0_rpm_reaches_2_a_without_steady_state_error() {
    let _s = serial();
    let r = run("p0", "miyajima-polar-0rpm", "lockstep");
    assert_eq!(r.summary["design"]["controller"], "polar");
    assert_eq!(r.summary["deadline_misses"], 0);
    let rows = r.trace();
    // i_q* = 2 A since 1 ms: no steady-state error, i_d held at 0.
    settling(&rows, CURRENT_TOL_A, |x| 2.0 - x.i_q);
    settling(&rows, CURRENT_TOL_A, |x| x.i_d);
    // Noise-free simulation: V_a = 0 before the step (uncontrollable point), yet the phase
    // stays put (section IV-C: "the controller output (the voltage phase) is stable"). After
    // the step δ = δ_d + δ_fb moves (reading 1 of polar.rs) and returns to the steady state
    // of (1) at standstill with i_d = 0: v_d = 0, δ = 0.
    for x in rows.iter().filter(|x| x.t < 1e-3) {
        let (_, d) = drivelab_tools::plot_polar::modulation_and_phase(x, 470.0);
        assert!(d == 0.0, "δ = {d} at t = {}", x.t);
    }
    settling(&rows, PHASE_TOL_RAD, |x| {
        drivelab_tools::plot_polar::modulation_and_phase(x, 470.0).1
    });
    let (rise, over) = (r.metric("iq_rise_time_us"), r.metric("iq_overshoot_pct"));
    // The design model of the q loop with the drive's delay (cdm::QLoop::step): the rise on
    // the same 100 µs grid; the overshoot at most the model's, since at standstill δ_d turns
    // C_21's output off the q axis and lowers the loop gain by cos δ_d (reading 1).
    let (m_rise, m_over) = cdm::QLoop::paper(2.5, 30e-3, 1e-4, cdm::CdmDelay::Paper).step();
    assert!(
        (rise - m_rise * 1e6).abs() < 1.0,
        "rise {rise} µs, model {m_rise}"
    );
    assert!(
        over > 0.0 && over <= m_over,
        "overshoot {over} %, model {m_over}"
    );
    eprintln!("0 rpm: rise {rise:.0} µs, overshoot {over:.1} % (model {m_over:.1} %)");
}

#[test]
fn cdm_with_the_delay_predicted_at_0_rpm() {
    // Option cdm_delay = "predict": the loops see the current one sample ahead. Alone, and
    // with τ_21 = 5·T_u and a set-point weight of 0.6 (miyajima-polar-0rpm-predict).
    let _s = serial();
    let sc = variant(
        "p0pred",
        "miyajima-polar-0rpm",
        &[(
            "controller = \"polar\"",
            "controller = \"polar\"\ncdm_delay = \"predict\"",
        )],
    );
    let paper = run("p0paper", "miyajima-polar-0rpm", "lockstep");
    let pred = run("p0pred-run", sc.to_str().unwrap(), "lockstep");
    let both = run("p0both", "miyajima-polar-0rpm-predict", "lockstep");
    let m = |r: &Run| (r.metric("iq_rise_time_us"), r.metric("iq_overshoot_pct"));
    let (r0, o0) = m(&paper);
    for (name, r, tau, beta) in [
        ("predict", &pred, 10.0, 1.0),
        ("predict, τ_21 = 5·T_u, β = 0.6", &both, 5.0, 0.6),
    ] {
        let (r1, o1) = m(r);
        // The design model (cdm::QLoop::step): the rise on the 100 µs grid as the model's,
        // the overshoot at most the model's (the δ_d rotation only lowers the loop gain,
        // reading 1 of polar.rs), and below the paper design's.
        let (m_rise, m_over) = cdm::QLoop {
            tau_samples: tau,
            beta,
            ..cdm::QLoop::paper(2.5, 30e-3, 1e-4, cdm::CdmDelay::Predict)
        }
        .step();
        assert!(
            (r1 - m_rise * 1e6).abs() < 1.0,
            "{name}: rise {r1} µs, model {m_rise}"
        );
        assert!(
            o1 <= m_over && o1 < o0,
            "{name}: overshoot {o1} % (paper {o0} %, model {m_over} %)"
        );
        let rows = r.trace();
        settling(&rows, CURRENT_TOL_A, |x| 2.0 - x.i_q);
        settling(&rows, CURRENT_TOL_A, |x| x.i_d);
        eprintln!(
            "0 rpm, {name}: rise {r1:.0} µs ({:.2}× the paper's {r0:.0} µs), overshoot {o1:.1} % (paper {o0:.1} %, model {m_over:.1} %)",
            r1 / r0
        );
    }
    // The option's target (< 10 % overshoot with at most 1.5× the rise): the design model
    // says prediction alone cannot meet it (the PI zero keeps 20 %), τ_21 = 5·T_u with β = 0.6
    // can (8.4 %, 400 µs); the runs agree.
    let (rp, op) = m(&pred);
    let (rb, ob) = m(&both);
    assert!(op >= 10.0 && rp > 1.5 * r0);
    assert!(ob < 10.0 && rb <= 1.5 * r0, "{ob} % {rb} µs");
}

#[test]
fn polar_control_at_400_rpm_lockstep_and_inprocess_traces_are_bit_identical() {
    let _s = serial();
    let ls = run("p400ls", "miyajima-polar-400rpm", "lockstep");
    let ip = run("p400ip", "miyajima-polar-400rpm", "inprocess");
    assert_eq!(
        read(&ls.dir.join("trace.csv")),
        read(&ip.dir.join("trace.csv")),
        "lockstep and inprocess traces of miyajima-polar-400rpm differ"
    );
    let (rise, over) = (ls.metric("iq_rise_time_us"), ls.metric("iq_overshoot_pct"));
    let rows = ls.trace();
    settling(&rows, CURRENT_TOL_A, |x| x.i_q_ref - x.i_q);
    settling(&rows, CURRENT_TOL_A, |x| x.i_d);
    eprintln!("400 rpm: rise {rise:.0} µs, overshoot {over:.1} %");
}

#[test]
fn flux_weakening_with_the_papers_poles() {
    // Section III with the paper's numbers (σ_δ = −600 rad/s, σ_v = −300 rad/s) on our motor.
    let _s = serial();
    let conv = run("fwc", "miyajima-fw-800rpm-conventional", "lockstep");
    let prop = run("fwp", "miyajima-fw-800rpm-polar", "lockstep");
    assert_eq!(conv.summary["design"]["controller"], "voltage-phase");
    assert_eq!(prop.summary["design"]["controller"], "polar-fw");
    let sc = load("miyajima-fw-800rpm-polar");
    let v_dc = sc.inverter.v_dc_v;
    let vmax = v_dc / 3f64.sqrt();
    let md = SpmsmModel::from_motor(&sc.motor_params());
    let w = sc.motor_params().p() * sc.mechanics.prescribed_speed_rad_s.unwrap();
    // Section III-C: phase loop at −600 rad/s, amplitude loop at −300 rad/s, the defaults.
    let sigma = |k: &str| prop.summary["design"]["polar"][k].as_f64().unwrap();
    let (s_d, s_v) = (sigma("sigma_delta_rad_s"), sigma("sigma_v_rad_s"));
    assert_eq!((s_d, s_v), (-600.0, -300.0));
    let at = |iq: f64| FwDesign::new(&md, vmax, iq, w, sc.rates.ts(), vmax, s_d, s_v);
    let (hi, lo) = (at(3.0), at(0.5));
    // Fig. 2: the conventional method ends flux-strengthening at 0.5 A. The equilibrium of
    // (1) at V_amax, i_q = 0.5 A has i_d > 0; the run settles there within what the slowest
    // pole of the sampled loop (the design model) leaves of the 2.5 A step after 39 ms.
    let slowest = lo
        .sampled_delta
        .iter()
        .map(|p| p.0)
        .fold(f64::MIN, f64::max);
    assert!(lo.i_d_o_a > 0.0 && slowest < 0.0);
    let last = *conv.trace().last().unwrap();
    let left = 2.5 * (slowest * 0.039).exp();
    assert!(
        (last.i_d - lo.i_d_o_a).abs() < left,
        "i_d {} vs {}",
        last.i_d,
        lo.i_d_o_a
    );
    // The design model at 3 A: the phase loop at −600 rad/s is unstable once sampled with
    // the one-sample delay (the zero of ΔP_22 lies inside |σ|); at 0.5 A it is stable.
    assert!(hi.sampled_delta.iter().any(|p| p.0 > 0.0));
    // So in both runs δ reaches its limit ±π/2 while i_q* = 3 A.
    for (name, r) in [("conventional", &conv), ("proposed", &prop)] {
        let hit = r
            .trace()
            .iter()
            .filter(|x| x.t >= 0.03 && x.t < 0.06)
            .any(|x| {
                let (_, d) = drivelab_tools::plot_polar::modulation_and_phase(x, v_dc);
                (d.abs() - std::f64::consts::FRAC_PI_2).abs() < 1e-9
            });
        assert!(hit, "{name}: δ never at ±π/2");
    }
    // The paper's two claims, measured: the q-axis rise the same for both (±20 %), and no
    // flux strengthening by the proposed method (i_d ≤ 0.01 A over the whole run). With the
    // paper's design on our motor neither holds (README, docs/paper-departures.md).
    let (rc, rp) = (
        conv.metric("iq_rise_time_us"),
        prop.metric("iq_rise_time_us"),
    );
    let id_max = prop.trace().iter().map(|x| x.i_d).fold(f64::MIN, f64::max);
    eprintln!("q rise: conventional {rc:.0} µs, proposed {rp:.0} µs (ratio {:.2}); proposed max i_d {id_max:.3} A", rp / rc);
    // Claim 1 is not reproduced on the proposed side: docs/paper-departures.md gives 6.0 ms
    // against 7.5 ms (ratio 1.25), the proposed method slower than the ±20 % accepted.
    assert!(
        rp > 1.2 * rc,
        "docs/paper-departures.md says the proposed q rise is more than 1.2× the conventional one; now {rp} µs against {rc} µs (ratio {})",
        rp / rc
    );
    assert!(
        id_max > 0.01,
        "the README says the claim is not reproduced; it now is: {id_max} A"
    );
}

#[test]
fn near_the_uncontrollable_point_v_a_0_the_controller_stays_bounded() {
    // Standstill, zero references and noisy phase currents: V_a ≈ 0, where the
    // controllability matrix (13) loses rank and C_12's gains are scheduled to their limits.
    let _s = serial();
    let sc = variant(
        "nearzero",
        "miyajima-polar-0rpm",
        &[
            ("duration_s = 0.01", "duration_s = 0.2"),
            (
                "i_q_a = [{ t_s = 0.001, value = 2.0 }]",
                "i_q_a = [{ t_s = 0.001, value = 0.0 }]",
            ),
            (
                "[rates]",
                "[sensors]\nencoder_counts_per_rev = 0\ncurrent_noise_a = 0.02\nseed = 7\n\n[rates]",
            ),
        ],
    );
    let r = run("nearzero-run", sc.to_str().unwrap(), "lockstep");
    let rows = r.trace();
    assert_eq!(rows.len(), 2000);
    let v_dc = 470.0;
    // Bounded: no NaN, and the currents stay small. (δ and M of the applied voltage are
    // within ±90° and M_max whatever the law does: the plant folds and clamps them, so they
    // are reported, not asserted.) The phase itself is not quiet: with V_a ≈ 0 it does not
    // act on the currents and the noise moves it (the oscillation Miyajima et al. report
    // from their experiment at 0 rpm, Fig. 9).
    let (mut run_at_limit, mut longest, mut m_peak, mut i_peak) = (0usize, 0usize, 0.0f64, 0.0f64);
    let mut near_zero = 0usize;
    for x in &rows {
        assert!(
            x.u_d.is_finite() && x.u_q.is_finite() && x.i_d.is_finite() && x.i_q.is_finite(),
            "non-finite at t = {}",
            x.t
        );
        let (m, d) = drivelab_tools::plot_polar::modulation_and_phase(x, v_dc);
        if m.abs() < 0.01 {
            near_zero += 1;
        }
        m_peak = m_peak.max(m.abs());
        i_peak = i_peak.max(x.i_d.abs()).max(x.i_q.abs());
        if d.abs() > 0.99 * std::f64::consts::FRAC_PI_2 {
            run_at_limit += 1;
            longest = longest.max(run_at_limit);
        } else {
            run_at_limit = 0;
        }
    }
    // No runaway phase: a wound-up integrator would hold δ at its limit to the end of the
    // run; it must leave the limit in the last 100 ms.
    let late_at_limit = rows.iter().filter(|x| x.t >= 0.1).all(|x| {
        let d = drivelab_tools::plot_polar::modulation_and_phase(x, v_dc).1;
        d.abs() > 0.99 * std::f64::consts::FRAC_PI_2
    });
    assert!(!late_at_limit, "δ stuck at its limit");
    // The run is where the test says: V_a below 1 % of its range in most samples ...
    assert!(
        near_zero > rows.len() / 2,
        "V_a < 1 % in {near_zero} samples only"
    );
    // ... and no runaway: the noise alone moves the currents by a fraction of the 2 A step
    // this scenario commands otherwise (0.16 A measured with this seed); a loop that winds up
    // at V_a ≈ 0 drives them to that and beyond.
    assert!(i_peak < 0.5, "peak |i| {i_peak} A with zero references");
    eprintln!("V_a ≈ 0 with 20 mA noise: longest run of δ at its limit {longest} samples, peak M {m_peak:.3}, peak |i| {i_peak:.3} A");
}

#[test]
fn polar_panels_are_drawn_with_their_limits() {
    let _s = serial();
    let r = run("panels", "miyajima-fw-800rpm-polar", "inprocess");
    let sc = load("miyajima-fw-800rpm-polar");
    let out = scratch("panels-out");
    let files = drivelab_tools::plot_polar::plot_polar_panels(
        &sc,
        &r.trace(),
        &out,
        "miyajima-fw-800rpm-polar",
    )
    .unwrap();
    assert_eq!(files.len(), 2);
    for f in &files {
        assert!(read(f).len() > 10_000, "{}", f.display());
    }
    let svg = String::from_utf8(read(&out.join("polar_panels.svg"))).unwrap();
    for label in [
        "±M_max",
        "±δ_max",
        "±I_max",
        "modulation index",
        "voltage phase",
    ] {
        assert!(svg.contains(label), "{label} not drawn");
    }
}

#[test]
fn polar_laws_reject_salient_motors_and_i_q_profiles_need_current_reference() {
    let out = scratch("polar-refused").join("run");
    let salient = variant(
        "salient",
        "miyajima-polar-0rpm",
        &[("preset = \"miyajima\"", "preset = \"kyslan2015\"")],
    );
    let o = drivelab(&[
        "run",
        "--scenario",
        salient.to_str().unwrap(),
        "--clock",
        "inprocess",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(!out.exists(), "the refused run made its folder");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("L_d = L_q"), "{err}");
    let profile = variant(
        "iqpi",
        "miyajima-polar-0rpm",
        &[("controller = \"current-reference\"", "controller = \"pi\"")],
    );
    let o = drivelab(&[
        "run",
        "--scenario",
        profile.to_str().unwrap(),
        "--clock",
        "inprocess",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(!out.exists(), "the refused run made its folder");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("reference.i_q_a"), "{err}");
}
