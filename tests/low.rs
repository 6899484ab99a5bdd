//! Low, Deng & Guo 1998 reproduced with the real processes: RST current and speed
//! loops designed by pole placement, the minimal-order αβ position observer, the sensorless
//! drive, and the ζ report of eq. (14). Each run uses its own bus id and run folder and checks
//! that no process and no bus file is left.

use drivelab_control::control::rst::{poly_add, poly_mul, roots};
use drivelab_control::observer_sensorless::{predicted_angle_error, Discretisation};
use drivelab_runtime::trace::TraceRow;
use drivelab_runtime::wiring::observer_sensorless::angle_error_deg;
use serde_json::Value;

mod common;
use common::*;

const RPM: f64 = std::f64::consts::PI / 30.0;

fn poly(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap_or_else(|| panic!("not a polynomial: {v}"))
        .iter()
        .map(|c| c.as_f64().unwrap())
        .collect()
}

/// Rows with t in [t0, t1).
fn window(rows: &[TraceRow], t0: f64, t1: f64) -> impl Iterator<Item = &TraceRow> {
    rows.iter()
        .filter(move |r| r.t >= t0 - 1e-9 && r.t < t1 - 1e-9)
}

fn max_abs(it: impl Iterator<Item = f64>) -> f64 {
    it.map(f64::abs).fold(0.0, f64::max)
}

fn mean(it: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = it.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    assert!(n > 0, "empty window");
    s / n as f64
}

/// The motor of the low1998 scenarios: p = 4, ψ = 0.6333/4 Wb, J = 2e-3, B = 1e-3.
fn k_t() -> f64 {
    1.5 * 0.6333
}

#[test]
fn rst_loops_have_exactly_the_designed_itae_poles() {
    // From the outside: the polynomials in summary.json give A·R + B·S = B+·A_m·A_o, and
    // A_m's roots are the ITAE poles (Graham-Lathrop table, typed in here independently)
    // mapped by z = e^{sT} for the configured ω_n.
    let _s = serial();
    let r = run("poles", "low-rst", "inprocess");
    let d = &r.summary["design"];
    assert_eq!(d["controller"], "rst");
    let itae: [(&str, &[f64], f64, f64); 3] = [
        ("i_d", &[1.0, 1.4, 1.0], 1500.0, 2e-4),
        ("i_q", &[1.0, 1.75, 2.15, 1.0], 1500.0, 2e-4),
        ("speed", &[1.0, 1.75, 2.15, 1.0], 100.0, 2e-3),
    ];
    for (name, proto, wn, ts) in itae {
        let l = &d["rst"][name];
        let (a, b, rr, s) = (poly(&l["a"]), poly(&l["b"]), poly(&l["r"]), poly(&l["s"]));
        let want = poly_mul(
            &poly(&l["b_plus"]),
            &poly_mul(&poly(&l["a_m"]), &poly(&l["a_o"])),
        );
        let got = poly_add(&poly_mul(&a, &rr), &poly_mul(&b, &s));
        assert_eq!(got.len(), want.len(), "{name}");
        for (x, y) in got.iter().zip(&want) {
            assert!(
                (x - y).abs() < 1e-9,
                "{name}: A·R + B·S = {got:?}, want {want:?}"
            );
        }
        // A_o is a power of z: the remaining poles sit at the origin.
        assert!(poly(&l["a_o"]).iter().skip(1).all(|c| *c == 0.0), "{name}");
        // Integrator in R.
        assert!(rr.iter().sum::<f64>().abs() < 1e-12, "{name}: R(1) = 0");
        let scaled: Vec<f64> = proto
            .iter()
            .enumerate()
            .map(|(i, c)| c * wn.powi(i as i32))
            .collect();
        let zs: Vec<_> = roots(&scaled).into_iter().map(|s| (s * ts).exp()).collect();
        let am = roots(&poly(&l["a_m"]));
        assert_eq!(zs.len(), am.len(), "{name}: order");
        for p in &zs {
            assert!(
                am.iter().any(|q| (p - q).norm() < 1e-9),
                "{name}: ITAE pole {p} not a root of A_m {am:?}"
            );
        }
        assert_eq!(l["omega_n_rad_s"].as_f64().unwrap(), wn, "{name}");
        eprintln!(
            "{name}: closed-loop poles {am:?} (+ B+ and z^k), margins {}",
            l["margins"]
        );
    }
    // The design printout says the same.
    let o = drivelab(&["design", "--scenario", "low-rst"]);
    let t = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(t.matches("A·R + B·S = B+·A_m·A_o to").count(), 3, "{t}");
    assert!(t.contains("this scenario runs the rst controller"), "{t}");
}

#[test]
fn low_rst_lockstep_currents_settle_without_error_and_i_d_stays_near_zero() {
    let _s = serial();
    let r = run("rst-ls", "low-rst", "lockstep");
    assert_eq!(r.summary["deadline_misses"], 0);
    assert_eq!(r.summary["samples"], 8000);
    let rows = r.trace();
    // Settled windows: 1200 rpm under 2 N·m, and back at 300 rpm under 2 N·m.
    for (t0, t1, w, load) in [(0.6, 1.2, 1200.0, 2.0), (1.5, 1.6, 300.0, 2.0)] {
        let win: Vec<&TraceRow> = window(&rows, t0, t1).collect();
        let e_q = max_abs(win.iter().map(|x| x.i_q - x.i_q_ref));
        let e_d = max_abs(win.iter().map(|x| x.i_d - x.i_d_ref));
        let e_w = max_abs(win.iter().map(|x| x.omega_m - w * RPM));
        let i_q = mean(win.iter().map(|x| x.i_q));
        eprintln!(
            "{t0}-{t1} s at {w} rpm: max |i_q − i_q*| = {e_q:.2e} A, max |i_d| = {e_d:.2e} A, max |ω − ω*| = {e_w:.2e} rad/s, i_q = {i_q:.4} A"
        );
        assert!(e_q < 2e-3, "i_q error {e_q} A in {t0}-{t1}");
        assert!(e_d < 1e-3, "i_d error {e_d} A in {t0}-{t1}");
        assert!(
            e_w < 0.05 * w * RPM / 10.0,
            "speed error {e_w} in {t0}-{t1}"
        );
        // The torque balance: k_t·i_q = T_L + B·ω.
        let want = (load + 1e-3 * w * RPM) / k_t();
        assert!((i_q - want).abs() < 5e-3, "i_q = {i_q}, load needs {want}");
    }
    // i_d stays near zero through the whole run, although i_q swings over ±4.2 A at up to
    // 1200 rpm (the couplings ±ω_e·L·i are rejected by S/R, no feed-forward).
    let id_peak = max_abs(rows.iter().map(|x| x.i_d));
    let id_rms = mean(rows.iter().map(|x| x.i_d * x.i_d)).sqrt();
    let iq_peak = max_abs(rows.iter().map(|x| x.i_q));
    eprintln!("i_d peak {id_peak:.3} A, RMS {id_rms:.4} A; i_q peak {iq_peak:.2} A");
    assert!(id_peak < 0.3, "i_d peak {id_peak}");
    assert!(id_rms < 0.03, "i_d RMS {id_rms}");
    assert!(
        (iq_peak - 4.2).abs() < 0.2,
        "the 300 → 1200 step saturates at 4.2 A: {iq_peak}"
    );
    // 300 → 1200 rpm: within 1 % after the current-limited acceleration, little overshoot.
    let reach = rows
        .iter()
        .find(|x| x.t >= 0.2 && x.omega_m >= 0.99 * 1200.0 * RPM)
        .map(|x| x.t - 0.2)
        .unwrap();
    let peak = window(&rows, 0.2, 1.2)
        .map(|x| x.omega_m)
        .fold(0.0, f64::max);
    eprintln!(
        "300 → 1200 rpm within 1 % after {:.1} ms, peak {:.1} rpm",
        reach * 1e3,
        peak / RPM
    );
    assert!(reach < 0.15, "{reach}");
    assert!(peak < 1.02 * 1200.0 * RPM, "{peak}");
}

#[test]
fn low_rst_lockstep_and_inprocess_traces_are_bit_identical() {
    let _s = serial();
    for name in ["low-rst", "low-rst-sensorless"] {
        let ls = run(&format!("det-{name}-ls"), name, "lockstep");
        let ip = run(&format!("det-{name}-ip"), name, "inprocess");
        assert_eq!(
            read(&ls.dir.join("trace.csv")),
            read(&ip.dir.join("trace.csv")),
            "lockstep and inprocess traces of {name} differ"
        );
    }
}

#[test]
fn load_step_at_800_rpm_is_rejected() {
    // Fig. 6: 1.5 N·m asserted at 0.5 s at 800 rpm and removed at 2.6 s.
    let _s = serial();
    let r = run("load", "low-load-step", "lockstep");
    let rows = r.trace();
    let w = 800.0 * RPM;
    let dip = window(&rows, 0.5, 2.6)
        .map(|x| w - x.omega_m)
        .fold(0.0, f64::max);
    let rise = window(&rows, 2.6, 3.0)
        .map(|x| x.omega_m - w)
        .fold(0.0, f64::max);
    // Time from t0 to the last sample outside ±1 % of 800 rpm within the next 0.4 s.
    let back = |t0: f64| {
        window(&rows, t0, t0 + 0.4)
            .filter(|x| (x.omega_m - w).abs() > 0.01 * w)
            .map(|x| x.t - t0)
            .fold(0.0, f64::max)
    };
    let (rec_on, rec_off) = (back(0.5), back(2.6));
    let i_q = mean(window(&rows, 2.0, 2.6).map(|x| x.i_q));
    let id_peak = max_abs(rows.iter().map(|x| x.i_d));
    eprintln!(
        "1.5 N·m at 800 rpm: dip {dip:.2} rad/s ({:.1} rpm), back within 1 % after {:.1} ms; removal: rise {rise:.2} rad/s, back after {:.1} ms; i_q = {i_q:.4} A; i_d peak {id_peak:.4} A",
        dip / RPM,
        rec_on * 1e3,
        rec_off * 1e3
    );
    assert!(dip > 1.0 && dip < 0.1 * w, "dip {dip}");
    assert!(rise > 1.0 && rise < 0.1 * w, "rise {rise}");
    assert!(rec_on < 0.1 && rec_off < 0.1, "{rec_on} {rec_off}");
    assert!((i_q - (1.5 + 1e-3 * w) / k_t()).abs() < 5e-3, "i_q {i_q}");
    assert!(id_peak < 0.1, "i_d peak {id_peak}");
    assert!(r.metric("load_dip_rad_s") > 1.0);
}

/// The steady-state i_d, i_q and angle error of the last 10 % of a monitor/sensorless run,
/// and the truncation's prediction for that operating point.
fn steady_state(r: &Run, disc: Discretisation) -> (f64, f64) {
    let rows = r.trace();
    let end = rows.last().unwrap().t;
    let tail: Vec<&TraceRow> = rows.iter().filter(|x| x.t >= 0.9 * end).collect();
    let ss = mean(tail.iter().map(|x| angle_error_deg(x)));
    let m = drivelab_control::motor::MotorParams::low1998();
    let pred = predicted_angle_error(
        &m,
        2e-4,
        mean(tail.iter().map(|x| x.omega_m)),
        mean(tail.iter().map(|x| x.i_d)),
        mean(tail.iter().map(|x| x.i_q)),
        1e-3,
        disc,
    )
    .to_degrees();
    (ss, pred)
}

#[test]
fn observer_converges_from_90_degrees_at_1200_rpm_to_the_truncation_bias() {
    let _s = serial();
    let r = run("obs", "low-observer-1200", "lockstep");
    let rows = r.trace();
    assert!(
        (angle_error_deg(&rows[0]) - 90.0).abs() < 1e-9,
        "starts 90° wrong"
    );
    let ss = r.metric("angle_error_ss_deg");
    let conv = r.metric("observer_convergence_ms");
    let (ss_trace, pred) = steady_state(&r, Discretisation::Truncated);
    eprintln!(
        "truncated model (eq. 13): steady-state error {ss:.4}° (truncation predicts {pred:.4}°), converged within ±1° after {conv:.1} ms"
    );
    assert!((ss - ss_trace).abs() < 1e-9);
    // The error is the truncation's: θ̂ leads by about half a sample of rotation.
    assert!((ss - pred).abs() < 0.02, "{ss} vs {pred}");
    let half_sample = (4.0 * 1200.0 * RPM * 2e-4 / 2.0).to_degrees();
    assert!(
        ss > 0.5 * half_sample && ss < 1.5 * half_sample,
        "{ss} vs {half_sample}"
    );
    assert!(conv > 1.0 && conv < 20.0, "convergence {conv} ms");
    // The speed is held by the dynamometer and the current control is sensored throughout.
    assert!(rows.iter().all(|x| (x.omega_m - 1200.0 * RPM).abs() < 1e-9));

    // The exact discretisation removes the bias (what is left is the inverter's hold in the
    // rotor frame, which no αβ model with a held u_αβ describes).
    let sc = variant(
        "obs-exact",
        "low-observer-1200",
        &[(
            "discretisation = \"truncated\"",
            "discretisation = \"exact\"",
        )],
    );
    let x = run("obs-exact", sc.to_str().unwrap(), "lockstep");
    let ssx = x.metric("angle_error_ss_deg");
    let (_, predx) = steady_state(&x, Discretisation::Exact);
    eprintln!(
        "exact model: steady-state error {ssx:.4}° (predicted {predx:.4}°), converged after {:.1} ms",
        x.metric("observer_convergence_ms")
    );
    assert!((ssx - predx).abs() < 0.02, "{ssx} vs {predx}");
    assert!(ssx.abs() < 0.1 * ss.abs(), "{ssx}");
}

#[test]
fn sensorless_drive_reaches_1200_rpm_and_holds_it_under_2_nm() {
    let _s = serial();
    let r = run("sl", "low-rst-sensorless", "lockstep");
    assert_eq!(r.summary["design"]["observer"]["mode"], "sensorless");
    let rows = r.trace();
    let w = 1200.0 * RPM;
    let reach = rows
        .iter()
        .find(|x| x.t >= 0.2 && x.omega_m >= 0.99 * w)
        .map(|x| x.t - 0.2)
        .expect("reaches 1200 rpm");
    let hold: Vec<&TraceRow> = window(&rows, 0.4, 1.2).collect();
    assert!(hold.iter().all(|x| x.t_load == 2.0), "loaded at 2 N·m");
    let e_w = max_abs(hold.iter().map(|x| x.omega_m - w));
    let e_hat = max_abs(hold.iter().map(|x| x.omega_hat - x.omega_m));
    let e_th = max_abs(hold.iter().map(|x| angle_error_deg(x)));
    let i_q = mean(hold.iter().map(|x| x.i_q));
    let (ss, pred) = steady_state(&r, Discretisation::Truncated);
    eprintln!(
        "sensorless: within 1 % of 1200 rpm {:.1} ms after the step; 0.4-1.2 s under 2 N·m: max |ω − ω*| = {e_w:.4} rad/s, max |ω̂ − ω| = {e_hat:.4} rad/s, max |θ̂ − θ| = {e_th:.3}°, i_q = {i_q:.4} A; at 300 rpm: {ss:.3}° (predicted {pred:.3}°)",
        reach * 1e3
    );
    assert!(reach < 0.15, "{reach}");
    assert!(e_w < 0.005 * w, "speed error {e_w}");
    assert!(e_hat < 0.005 * w, "speed estimate error {e_hat}");
    assert!(e_th < 3.0, "angle error {e_th}");
    // The whole load is carried: k_t·i_q·cos(θ̂ − θ) = T_L + B·ω.
    assert!((i_q - (2.0 + 1e-3 * w) / k_t()).abs() < 0.01, "i_q {i_q}");
    assert!((ss - pred).abs() < 0.02, "{ss} vs {pred}");
    assert!(r.metric("steady_state_error").abs() < 0.05);
}

#[test]
fn observer_error_reports_zeta_and_plots_it() {
    let out = scratch("zeta");
    let o = drivelab(&[
        "observer-error",
        "--ts",
        "0.1ms,0.2ms,500us",
        "--motor",
        "low1998",
        "--out",
        out.to_str().unwrap(),
    ]);
    let t = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // Low et al.: ζ below 2 % at 1200 rpm with T_s = 0.2 ms.
    let z = number_after(&t, "T_s = 200 µs: ζ(1200 rpm) = ");
    assert!(z > 1.0 && z < 2.0, "{z}\n{t}");
    let z1 = number_after(&t, "T_s = 100 µs: ζ(1200 rpm) = ");
    let z5 = number_after(&t, "T_s = 500 µs: ζ(1200 rpm) = ");
    assert!(z1 < z && z < z5, "{z1} {z} {z5}");
    let line = t
        .lines()
        .find(|l| l.trim_start().starts_with("1200 "))
        .unwrap_or_else(|| panic!("no 1200 rpm row in\n{t}"));
    assert!(line.contains(&format!("{z:.3}%")), "{line}");
    for stem in ["zeta", "angle_error"] {
        for ext in ["png", "svg"] {
            let f = out.join(format!("{stem}.{ext}"));
            assert!(read(&f).len() > 1000, "{}", f.display());
        }
    }
    let j: Value = serde_json::from_slice(&read(&out.join("observer_error.json"))).unwrap();
    assert_eq!(j["sweeps"].as_array().unwrap().len(), 3);
    // A sample time without a unit: one clear line, exit code 1.
    let o = drivelab(&[
        "observer-error",
        "--ts",
        "0.2",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(err.contains("give a unit"), "{err}");
}

#[test]
fn low_scenarios_are_listed_with_the_figure_they_reproduce() {
    let o = drivelab(&["scenarios"]);
    let t = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success());
    for (name, fig) in [
        ("low-rst ", "Fig. 4"),
        ("low-load-step", "Fig. 6"),
        ("low-rst-sensorless", "Low et al. 1998"),
        ("low-observer-1200", "Low et al. 1998"),
    ] {
        let line = t
            .lines()
            .find(|l| l.starts_with(name))
            .unwrap_or_else(|| panic!("{name} not listed:\n{t}"));
        assert!(line.contains(fig) && !line.contains("INVALID"), "{line}");
    }
}
