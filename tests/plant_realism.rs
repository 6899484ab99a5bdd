//! The plant's realism with the real processes (docs/architecture.md, "Plant realism"): the
//! new scenarios give the same trace in lockstep (twice) and in process, they are listed,
//! and a bad `[inverter]` or `[sensors]` table is refused with one line. Each run uses its
//! own bus id and run folder and checks that no process and no bus file is left.

mod common;
use common::*;

/// The scenarios of the switching inverter and the sensor errors, each run with every
/// option it sets: the same bytes in two lockstep runs and one in-process run.
#[test]
fn new_scenarios_give_the_same_trace_in_lockstep_and_in_process() {
    let _s = serial();
    for name in ["kyslan-pi-pwm", "miyajima-polar-0rpm-noise"] {
        let (dir, summary) =
            same_trace_in_every_run(&format!("same-{name}"), &["--scenario", name]);
        assert_eq!(summary["scenario"], name);
        // And with every stage in one process (the plant is a stage like the others).
        let (one, _) = run_ok(
            &format!("one-{name}"),
            &[
                "--scenario",
                name,
                "--clock",
                "lockstep",
                "--topology",
                "one-process",
            ],
        );
        assert!(
            read(&dir.join("trace.csv")) == read(&one.join("trace.csv")),
            "{name}: one-process lockstep differs from four-process"
        );
    }
    // Every sensor error and the DC link at once, on a short kyslan-pi-pwm.
    let all = variant(
        "same-all",
        "kyslan-pi-pwm",
        &[
            ("duration_s = 0.1", "duration_s = 0.05"),
            (
                "dead_time_us = 2.0      # t_d·f_sw·V_dc = 6.5 V per phase\n",
                "dead_time_us = 2.0\nv_drop_v = 1.0\ndc_link_c_uf = 100.0\nr_source_ohm = 2.0\n",
            ),
            (
                "decoupling = true",
                "decoupling = true\ndead_time_comp = true",
            ),
            (
                "[observer]",
                "[sensors]\ncurrent_gain = [1.02, 1.0, 0.98]\ncurrent_offset_a = [0.01, 0.0, -0.02]\nadc_bits = 12\nadc_range_a = 5.0\nadc_lead_us = 10.0\nencoder_delay_us = 150.0\ncurrent_noise_a = 0.01\nseed = 3\n\n[observer]",
            ),
        ],
    );
    same_trace_in_every_run("same-all", &["--scenario", all.to_str().unwrap()]);
}

#[test]
fn new_scenarios_are_listed() {
    let o = drivelab(&["scenarios"]);
    assert!(o.status.success());
    let t = String::from_utf8_lossy(&o.stdout);
    for name in ["kyslan-pi-pwm", "miyajima-polar-0rpm-noise"] {
        let line = t
            .lines()
            .find(|l| l.contains(name))
            .unwrap_or_else(|| panic!("{name} not listed:\n{t}"));
        assert!(!line.contains("INVALID"), "{line}");
    }
}

#[test]
fn bad_inverter_and_sensor_tables_are_refused_in_one_line() {
    let bus = bus_id("refused");
    for (edit, needle) in [
        (
            ("f_sw_hz = 10000.0 ", "f_sw_hz = 7000.0 "),
            "inverter.f_sw_hz = 7000",
        ),
        (
            ("dead_time_us = 2.0 ", "dead_time_us = 60.0 "),
            "inverter.dead_time_us = 60",
        ),
        (
            ("dead_time_us = 2.0 ", "dead_time_us = -1.0 "),
            "inverter.dead_time_us = -1",
        ),
        (
            ("model = \"switching\"", "model = \"averaged\""),
            "inverter.f_sw_hz applies to model = \"switching\" only",
        ),
        (
            ("seed = 1\n", "seed = 1\nadc_bits = 0\nadc_range_a = 5.0\n"),
            "sensors.adc_bits = 0",
        ),
        (
            ("seed = 1\n", "seed = 1\nadc_bits = 12\n"),
            "sensors.adc_bits and sensors.adc_range_a",
        ),
        (
            ("seed = 1\n", "seed = 1\nadc_lead_us = 100.0\n"),
            "sensors.adc_lead_us = 100",
        ),
        (
            ("seed = 1\n", "seed = 1\nencoder_delay_us = 5000.0\n"),
            "sensors.encoder_delay_us = 5000",
        ),
    ] {
        let sc = variant(
            "refused",
            "kyslan-pi-pwm",
            &[("[observer]", "[sensors]\nseed = 1\n\n[observer]"), edit],
        );
        assert_run_refused(&bus, &["--scenario", sc.to_str().unwrap()], needle);
    }
}
