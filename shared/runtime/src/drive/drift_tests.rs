//! The plant's R and ψ drift (`[plant_drift]`, docs/architecture.md "Model mismatch").

use super::Plant;
use crate::config::Scenario;
use crate::messages::{Header, VoltageCommand};

/// The low1998 motor locked (a dynamometer at 0 rad/s, rotor at θ_e = 0): u_α = U drives i_d
/// alone through R and L, di/dt = (U − R(t)·i)/L.
fn locked(drift: &str) -> Plant {
    let text = format!(
        "name = \"t\"\nduration_s = 0.2\n[motor]\npreset = \"low1998\"\n[mechanics]\nprescribed_speed_rad_s = 0.0\n[rates]\nsample_hz = 10000.0\nplant_substeps = 4\n{drift}"
    );
    Plant::new(&Scenario::from_toml(&text, "t.toml").unwrap())
}

/// Runs `n` samples at u_α = 10 V and returns i_d at each.
fn response(p: &mut Plant, n: u64) -> Vec<f64> {
    let cmd = VoltageCommand {
        hdr: Header::default(),
        u_ab: [10.0, 0.0],
        ..Default::default()
    };
    (0..n)
        .map(|k| {
            p.sample(k, Some(&cmd));
            let i = p.truth().i_dq[0];
            p.advance();
            i
        })
        .collect()
}

#[test]
fn locked_rotor_current_follows_the_drifted_resistance() {
    let (u, r, l, ts) = (10.0, 2.5, 30e-3, 1e-4);
    // No drift: i(t) = U/R·(1 − e^{−R t/L}); the 4-substep RK4 is within 1e-9 A of it.
    let plain = response(&mut locked(""), 2000);
    // R ×1.3 from t = 0: the same with 1.3·R.
    let hot = response(
        &mut locked("[plant_drift]\nr_factor = [{t_s = 0.0, value = 1.3}]\n"),
        2000,
    );
    for k in [100usize, 500, 1999] {
        let t = k as f64 * ts;
        for (rows, rr) in [(&plain, r), (&hot, 1.3 * r)] {
            let want = u / rr * (1.0 - libm::exp(-rr * t / l));
            assert!(
                (rows[k] - want).abs() < 1e-6,
                "k = {k}, R = {rr}: {} vs {want}",
                rows[k]
            );
        }
    }
    // A ramp 1.0 → 1.5 over [0.05, 0.15] s, slow against L/R = 12 ms: the current tracks
    // U/R(t) with the lag of a first-order system on a ramp, i ≈ U/R(t) + (U/R²)·R'·L/R.
    let mut p = locked(
        "[plant_drift]\nr_factor = [{t_s = 0.05, value = 1.0}, {t_s = 0.15, value = 1.5}]\n",
    );
    let ramp = response(&mut p, 2000);
    for k in [1000usize, 1400] {
        let t = k as f64 * ts;
        let rt = r * (1.0 + 0.5 * (t - 0.05) / 0.1);
        let lag = u / (rt * rt) * (r * 0.5 / 0.1) * l / rt;
        let want = u / rt + lag;
        // The quasi-static formula is first order in the slow ramp: within 2 %.
        assert!(
            (ramp[k] - want).abs() < 0.02 * want,
            "k = {k}: {} vs {want} (U/R(t) = {})",
            ramp[k],
            u / rt
        );
        // And clearly off the undrifted current.
        assert!(plain[k] - ramp[k] > 0.1 * plain[k], "k = {k}");
    }
    // Before the ramp the plant is the undrifted one, bit for bit.
    assert_eq!(&ramp[..500], &plain[..500]);
}
