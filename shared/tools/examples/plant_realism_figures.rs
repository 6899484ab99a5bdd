//! The figures of docs/architecture.md, "Plant realism" (in process, a few seconds in
//! release): `cargo run --release -p drivelab-tools --example plant_realism_figures -- docs/img`
//!
//! - `low-angle-error-r30.png`: Low et al.'s observer, steady angle-error shift against speed
//!   with the plant's R 30 % above the observer's, measured and first-order prediction;
//! - `miyajima-0rpm-noise-phase.png`: the voltage phase of `miyajima-polar-0rpm-noise` with
//!   and without the current noise, and with the same noise at 400 rpm.

use drivelab_tools::plant_realism::{
    low_angle_shift_deg, miyajima_400rpm_noise, scenario, voltage_phase_deg,
};
use drivelab_tools::plot::plot_lines;
use std::path::PathBuf;

fn main() -> Result<(), Box<dyn core::error::Error>> {
    let out = PathBuf::from(std::env::args().nth(1).unwrap_or_else(|| "docs/img".into()));
    std::fs::create_dir_all(&out)?;

    let (mut measured, mut predicted) = (Vec::new(), Vec::new());
    for rpm in [150.0, 200.0, 300.0, 400.0, 600.0, 800.0, 1200.0, 1500.0] {
        let (m, p) = low_angle_shift_deg(rpm);
        println!("{rpm:6.0} rpm: shift {m:.4}°, first order {p:.4}°");
        measured.push((rpm, m));
        predicted.push((rpm, p));
    }
    plot_lines(
        &[
            ("measured (R +30 %, i_d = −2 A)".into(), measured),
            ("first order −ΔR·i_d/(ω_e·ψ)".into(), predicted),
        ],
        "Low et al. observer: steady angle-error shift from a 30 % resistance error",
        "speed, rpm",
        "angle-error shift, degrees",
        &[],
        &out.join("low-angle-error-r30"),
    )?;

    let noisy = scenario("miyajima-polar-0rpm-noise");
    let mut quiet = noisy.clone();
    quiet.sensors.current_noise_a = 0.0;
    plot_lines(
        &[
            (
                "δ, 20 mA rms current noise".into(),
                voltage_phase_deg(&noisy),
            ),
            ("δ, no noise".into(), voltage_phase_deg(&quiet)),
            (
                "δ at 400 rpm, the same noise".into(),
                voltage_phase_deg(&miyajima_400rpm_noise()),
            ),
        ],
        "Miyajima et al. polar current control: voltage phase, i_q* 0 → 2 A at 10 ms",
        "t, ms",
        "voltage phase δ, degrees",
        &[],
        &out.join("miyajima-0rpm-noise-phase"),
    )?;
    println!("figures in {}", out.display());
    Ok(())
}
