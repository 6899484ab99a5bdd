//! Measurements of the plant's realism (docs/architecture.md, "Plant realism"), in process:
//! the dead time's voltage loss, the voltage-phase spread of Miyajima et al.'s polar current
//! control, and the angle shift of Low et al.'s observer under a resistance error. Used by
//! the tests and by the `plant_realism_figures` example that draws docs/img.

use drivelab_control::control::polar::dq_to_polar;
use drivelab_control::transforms::{park, AlphaBeta};
use drivelab_runtime::config::Scenario;
use drivelab_runtime::drive::{run_inprocess, InProcessDrive};
use drivelab_runtime::wiring::observer_sensorless::angle_error_deg;

/// A shipped scenario by name.
pub fn scenario(name: &str) -> Scenario {
    Scenario::load(name).unwrap_or_else(|e| panic!("{e}")).0
}

/// The TOML text of a shipped scenario.
pub fn scenario_text(name: &str) -> String {
    let (_, path) = Scenario::load(name).unwrap_or_else(|e| panic!("{e}"));
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The fundamental voltage the switching inverter loses against what the current loop asked
/// for, from `t_from_s` to the end of the run (whole electrical periods): (along the
/// current, across it), V. Per sample the loss is the law's dq voltage of the command
/// applied over the sample (before any dead-time compensation) minus the mean applied αβ
/// voltage turned into dq at the mid-sample angle (the angle the current loop aimed the
/// command at). Its mean in the rotor frame is the fundamental of the loss (the harmonics,
/// 6th and up in dq, average out over whole periods); it is split along and across the mean
/// dq current, the current's fundamental.
pub fn dead_time_loss(sc: &Scenario, t_from_s: f64) -> (f64, f64) {
    let mut d = InProcessDrive::new(sc);
    let (mut du, mut dq, mut id, mut iq, mut n) = (0.0, 0.0, 0.0, 0.0, 0.0);
    let ts = sc.rates.ts();
    let p = sc.motor_params().p();
    let mut asked = None;
    for k in 0..sc.samples() {
        let row = d.cycle(k);
        if let (Some(u), true) = (asked, row.t >= t_from_s) {
            let [ud, uq]: [f64; 2] = u;
            let [a, b] = d.plant.mean_u_ab;
            let mid = row.theta_e + 0.5 * p * row.omega_m * ts;
            let applied = park(AlphaBeta { alpha: a, beta: b }, mid);
            du += ud - applied.d;
            dq += uq - applied.q;
            id += row.i_d;
            iq += row.i_q;
            n += 1.0;
        }
        asked = d.command().map(|c| c.u_dq);
    }
    let (du, dq, id, iq) = (du / n, dq / n, id / n, iq / n);
    let mag = id.hypot(iq);
    ((du * id + dq * iq) / mag, (dq * id - du * iq) / mag)
}

/// The voltage phase δ of a run (degrees, against t in ms), from the applied u_d, u_q in
/// Miyajima et al.'s signed polar form (|δ| ≤ 90°).
pub fn voltage_phase_deg(sc: &Scenario) -> Vec<(f64, f64)> {
    run_inprocess(sc)
        .iter()
        .map(|r| (r.t * 1e3, dq_to_polar(r.u_d, r.u_q).1.to_degrees()))
        .collect()
}

/// Standard deviation of the values of `pts` whose x lies in [a, b).
pub fn spread(pts: &[(f64, f64)], a: f64, b: f64) -> f64 {
    let v: Vec<f64> = pts
        .iter()
        .filter(|(x, _)| *x >= a && *x < b)
        .map(|p| p.1)
        .collect();
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    (v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / n).sqrt()
}

/// The voltage phase's spread (standard deviation, degrees) of a run over [a_ms, b_ms).
pub fn phase_spread_deg(sc: &Scenario, a_ms: f64, b_ms: f64) -> f64 {
    spread(&voltage_phase_deg(sc), a_ms, b_ms)
}

/// `miyajima-polar-0rpm-noise` moved to 400 rpm (`miyajima-polar-400rpm`'s speed): the same
/// noise, i_q* = 0 for 10 ms, then 2 A.
pub fn miyajima_400rpm_noise() -> Scenario {
    let text = scenario_text("miyajima-polar-0rpm-noise").replace(
        "prescribed_speed_rad_s = 0.0 ",
        &format!(
            "prescribed_speed_rad_s = {} ",
            scenario("miyajima-polar-400rpm")
                .mechanics
                .prescribed_speed_rad_s
                .unwrap()
        ),
    );
    Scenario::from_toml(&text, "miyajima-polar-400rpm-noise").unwrap()
}

/// Low et al.'s observer beside a sensored drive on a dynamometer at `rpm`, i_d = −2 A,
/// i_q = 0 (as `tests/low.rs`): the steady angle error's shift when the plant's R is 30 %
/// above the observer's (degrees: with minus without the mismatch, the mean over the run's
/// last 10 %), and the first-order prediction from eq. (16) in steady state,
/// Δθ ≈ −ΔR·i_d/(ω_e·ψ).
pub fn low_angle_shift_deg(rpm: f64) -> (f64, f64) {
    let w = rpm * std::f64::consts::PI / 30.0;
    let base = scenario_text("low-observer-1200")
        .replace("125.66370614359172", &format!("{w}"))
        .replace("i_d_a = []", "i_d_a = [{ t_s = 0.0, value = -2.0 }]")
        .replace(
            "initial_angle_error_deg = 90.0",
            "initial_angle_error_deg = 0.0",
        );
    let hot = base.replace(
        "preset = \"low1998\"",
        "preset = \"low1998\"\nr_ohm = 3.25\n\n[model]\nr_ohm = 2.5\n",
    );
    let mean_error = |text: &str| {
        let rows = run_inprocess(&Scenario::from_toml(text, "low-angle-shift").unwrap());
        let end = rows.last().unwrap().t;
        let tail: Vec<f64> = rows
            .iter()
            .filter(|x| x.t >= 0.9 * end)
            .map(angle_error_deg)
            .collect();
        tail.iter().sum::<f64>() / tail.len() as f64
    };
    let shift = mean_error(&hot) - mean_error(&base);
    let (dr, i_d, psi) = (0.75, -2.0, 0.6333 / 4.0);
    (shift, (-dr * i_d / (4.0 * w * psi)).to_degrees())
}
