//! Cost per sample of the plant's inverter models (docs/architecture.md, "Plant realism"):
//! the plant's `sample` + `advance` alone, and the whole in-process chain, per model.
//! Timing only, no verdict; run it in release on a quiet machine:
//! `cargo run --release -p drivelab-bench --example plant_cost`

use drivelab_runtime::config::Scenario;
use drivelab_runtime::drive::{InProcessDrive, Plant};
use drivelab_runtime::messages::VoltageCommand;
use std::time::Instant;

/// Samples per timed round, rounds per variant (the median round is reported).
const SAMPLES: u64 = 20_000;
const ROUNDS: usize = 15;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> Result<(), Box<dyn core::error::Error>> {
    let (base, _) = Scenario::load("kyslan-pi")?;
    let with = |edit: &dyn Fn(&mut Scenario)| {
        let mut s = base.clone();
        edit(&mut s);
        s.validate().map(|_| s)
    };
    use drivelab_runtime::config::InverterModel::Switching;
    let variants: Vec<(&str, Scenario)> = vec![
        ("averaged (RK4, 4 sub-steps)", base.clone()),
        (
            "switching 10 kHz, t_d 0",
            with(&|s| s.inverter.model = Switching)?,
        ),
        (
            "switching 10 kHz, t_d 2 µs (kyslan-pi-pwm)",
            Scenario::load("kyslan-pi-pwm")?.0,
        ),
        (
            "switching 10 kHz, t_d 2 µs, drop, DC link",
            with(&|s| {
                s.inverter.model = Switching;
                s.inverter.dead_time_us = 2.0;
                s.inverter.v_drop_v = 1.0;
                s.inverter.dc_link_c_uf = Some(100.0);
                s.inverter.r_source_ohm = Some(2.0);
            })?,
        ),
        (
            "switching 20 kHz, t_d 2 µs",
            with(&|s| {
                s.inverter.model = Switching;
                s.inverter.f_sw_hz = Some(20_000.0);
                s.inverter.dead_time_us = 2.0;
            })?,
        ),
    ];
    println!("per sample, median of {ROUNDS} rounds of {SAMPLES} samples:");
    for (name, sc) in &variants {
        // The plant alone, under a fixed command (a 100 V vector).
        let cmd = VoltageCommand {
            u_ab: [80.0, 60.0],
            ..Default::default()
        };
        let mut plant_ns = Vec::new();
        let mut chain_ns = Vec::new();
        for _ in 0..ROUNDS {
            let mut p = Plant::new(sc);
            let t = Instant::now();
            for k in 0..SAMPLES {
                std::hint::black_box(p.sample(k, Some(&cmd)));
                p.advance();
            }
            plant_ns.push(t.elapsed().as_nanos() as f64 / SAMPLES as f64);
            // The scenario's profiles end at 0.1 s; longer runs hold the last values.
            let mut long = sc.clone();
            long.duration_s = SAMPLES as f64 / long.rates.sample_hz;
            let mut d = InProcessDrive::new(&long);
            let n = SAMPLES;
            let t = Instant::now();
            for k in 0..n {
                std::hint::black_box(d.cycle(k));
            }
            chain_ns.push(t.elapsed().as_nanos() as f64 / n as f64);
        }
        println!(
            "  {name:44} plant {:7.0} ns   whole chain in process {:7.0} ns",
            median(plant_ns),
            median(chain_ns)
        );
    }
    Ok(())
}
