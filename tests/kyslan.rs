//! Kyslan et al. 2015 reproduced with the real processes: the PI cascade against the
//! two-step linearising controller, for saliency 2.18 and 6.18 (Figs 3-4). Each run uses its
//! own bus id and run folder and checks that no process and no bus file is left.

use serde_json::Value;

mod common;
use common::*;

const FOUR: [&str; 4] = [
    "kyslan-pi",
    "kyslan-nl",
    "kyslan-pi-sal618",
    "kyslan-nl-sal618",
];

/// The nonlinear controller with its poles placed on the sampled loop.
const SAMPLED: [&str; 2] = ["kyslan-nl-sampled", "kyslan-nl-sampled-sal618"];

#[test]
fn pi_and_nonlinear_designs_meet_the_rise_time_in_lockstep() {
    let _s = serial();
    for name in FOUR.iter().chain(&SAMPLED) {
        let r = run(&format!("rise-{name}"), name, "lockstep");
        let rise = r.metric("rise_time_ms");
        let nl = name.contains("-nl");
        // Both designs are solved for the 8 ms of Kyslan et al. on their sampled design
        // models (the drive's own discrete laws and timing); the run reaches 70 rad/s when
        // its model says, to one 0.1 ms sample of the trace.
        let design = &r.summary["design"][if nl { "nonlinear" } else { "speed" }];
        let predicted = design["predicted_rise_time_s"].as_f64().unwrap() * 1e3;
        assert!(
            (rise - predicted).abs() <= 0.1 + 1e-9,
            "{name}: rise time {rise} ms, design model {predicted} ms"
        );
        // ... and the design reached the paper's 8 ms on that model (else it says why).
        assert!(
            (predicted - 8.0).abs() <= 0.1,
            "{name}: design model {predicted} ms"
        );
        assert!(design["warning"].is_null(), "{name}: {design}");
        assert_eq!(r.summary["deadline_misses"], 0);
        assert_eq!(
            r.summary["design"]["controller"],
            if nl { "nonlinear" } else { "pi" }
        );
        for key in [
            "overshoot_pct",
            "load_dip_rad_s",
            "load_recovery_ms",
            "id_tracking_error_a",
        ] {
            assert!(r.metric(key).is_finite(), "{name}: {key}");
        }
        assert!(!r.stderr.contains("warning: i_d*"), "{name}: {}", r.stderr);
        eprintln!("{name}: {}", r.summary["metrics"]);
    }
}

#[test]
fn nonlinear_poles_placed_on_the_sampled_loop() {
    let _s = serial();
    let cont = run("pl-cont", "kyslan-nl", "lockstep");
    for name in SAMPLED {
        let r = run(&format!("pl-{name}"), name, "lockstep");
        let d = &r.summary["design"]["nonlinear"];
        let f = |k: &str| d[k].as_f64().unwrap();
        let zeta = f("zeta");
        assert_eq!(zeta, 0.6, "Kyslan §6: damping 0.6");
        assert!(d["warning"].is_null(), "{name}: {}", d["warning"]);
        // The dominant pair asked, (ζ, ω_0), is a pole pair of the sampled loop (placed to
        // 1e-12 of det(zI − Φ); checked against the loop's matrix derived by hand in the
        // unit test of control::nonlinear); every other pole is at least twice as fast.
        let poles: Vec<(f64, f64)> = d["sampled"]["poles"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| (p[0].as_f64().unwrap(), p[1].as_f64().unwrap()))
            .collect();
        let w0 = f("omega_0_rad_s");
        let want = (-zeta * w0, w0 * (1.0 - zeta * zeta).sqrt());
        let is_pair =
            |p: &(f64, f64)| (p.0 - want.0).abs() < 1e-2 && (p.1.abs() - want.1).abs() < 1e-2;
        assert_eq!(
            poles.iter().filter(|p| is_pair(p)).count(),
            2,
            "{name}: {want:?} not in {poles:?}"
        );
        assert!(
            poles
                .iter()
                .filter(|p| !is_pair(p))
                .all(|p| p.0 < 2.0 * want.0),
            "{name}: {poles:?}"
        );
        let (rise, os) = (r.metric("rise_time_ms"), r.metric("overshoot_pct"));
        let target = cont.summary["design"]["nonlinear"]["continuous_overshoot_pct"]
            .as_f64()
            .unwrap();
        eprintln!(
            "{name}: ω_0 = {w0:.0} rad/s, rise {rise} ms (asked 8), overshoot {os:.2} % (model {:.2} %, the continuous design on the paper's model {target:.2} %); today's continuous placement: overshoot {:.2} %",
            f("predicted_overshoot_pct"),
            cont.metric("overshoot_pct")
        );
        // The targets of this placement (docs/paper-departures.md, section 3): the 8 ms rise
        // of Kyslan et al. (to one 0.1 ms trace sample) and an overshoot within 3 percentage
        // points of the continuous design's on the paper's model.
        assert!((rise - 8.0).abs() <= 0.1 + 1e-9, "{name}: rise {rise} ms");
        assert!(
            (os - target).abs() <= 3.0,
            "{name}: overshoot {os} % vs {target} %"
        );
    }
}

#[test]
fn nonlinear_i_d_step_response_does_not_change_when_the_load_steps() {
    // The same i_d step at 20 ms, once with the nominal load stepping at the same instant,
    // once without load. The load changes speed and i_q a lot; the field loop must not see it.
    let _s = serial();
    let load = "torque_nm = [{ t_s = 0.04, value = 0.5457 }]";
    for base in [
        "kyslan-nl",
        "kyslan-nl-sal618",
        "kyslan-pi",
        "kyslan-pi-sal618",
    ] {
        let with = variant(
            &format!("{base}-load"),
            base,
            &[(load, "torque_nm = [{ t_s = 0.02, value = 0.5457 }]")],
        );
        let without = variant(&format!("{base}-noload"), base, &[(load, "torque_nm = []")]);
        let a = run(&format!("dec-{base}-a"), with.to_str().unwrap(), "lockstep").trace();
        let b = run(
            &format!("dec-{base}-b"),
            without.to_str().unwrap(),
            "lockstep",
        )
        .trace();
        let window = |r: &&drivelab_runtime::trace::TraceRow| r.t >= 0.02 && r.t < 0.04;
        let max_diff = |f: fn(&drivelab_runtime::trace::TraceRow) -> f64| {
            a.iter()
                .zip(&b)
                .filter(|(x, _)| window(x))
                .map(|(x, y)| (f(x) - f(y)).abs())
                .fold(0.0, f64::max)
        };
        let (d_id, d_iq, d_w) = (
            max_diff(|r| r.i_d),
            max_diff(|r| r.i_q),
            max_diff(|r| r.omega_m),
        );
        eprintln!(
            "{base}: load vs no load during the i_d step: max |Δi_d| = {d_id:.5} A, |Δi_q| = {d_iq:.3} A, |Δω| = {d_w:.2} rad/s"
        );
        // Not vacuous: the load really acted (its current T_L/k_t = 0.5457/0.78 = 0.70 A,
        // and the speed dips by tens of rad/s, load_dip_rad_s of the runs).
        assert!(
            d_iq > 0.5 && d_w > 10.0,
            "{base}: the load step did not act"
        );
        if base.contains("-nl") {
            // The decoupling claim: the i_d response moves by less than 1 % of the 1.6 A step.
            assert!(
                d_id < 0.016,
                "{base}: i_d changed by {d_id} A with the load"
            );
        }
    }
}

#[test]
fn nonlinear_load_recovery_depends_less_on_saliency_than_pi() {
    // Kyslan et al. §6-7: with saliency 6.18 instead of 2.18 the nonlinear controller keeps
    // its dynamics under load while the PI cascade's deteriorates (gains recomputed for both).
    // Checked for both placements of the nonlinear poles.
    let _s = serial();
    let names = [
        "kyslan-pi",
        "kyslan-pi-sal618",
        "kyslan-nl",
        "kyslan-nl-sal618",
        SAMPLED[0],
        SAMPLED[1],
    ];
    let m: Vec<(f64, f64)> = names
        .iter()
        .map(|n| {
            let r = run(&format!("sal-{n}"), n, "lockstep");
            (r.metric("load_recovery_ms"), r.metric("load_dip_rad_s"))
        })
        .collect();
    let (pi, pi6) = (m[0], m[1]);
    let d_pi = ((pi6.0 - pi.0).abs(), (pi6.1 - pi.1).abs());
    eprintln!(
        "PI: load recovery {:.1} → {:.1} ms, dip {:.2} → {:.2} rad/s",
        pi.0, pi6.0, pi.1, pi6.1
    );
    for (label, nl, nl6) in [("continuous", m[2], m[3]), ("sampled", m[4], m[5])] {
        let d_nl = ((nl6.0 - nl.0).abs(), (nl6.1 - nl.1).abs());
        eprintln!(
            "nonlinear ({label}): load recovery {:.1} → {:.1} ms, dip {:.2} → {:.2} rad/s",
            nl.0, nl6.0, nl.1, nl6.1
        );
        assert!(
            d_nl.0 < d_pi.0,
            "{label}: recovery change {d_nl:?}, PI {d_pi:?}"
        );
        assert!(d_nl.1 < d_pi.1, "{label}: dip change {d_nl:?}, PI {d_pi:?}");
    }
}

#[test]
fn kyslan_nl_lockstep_and_inprocess_traces_are_bit_identical() {
    let _s = serial();
    let ls = run("det-nl-ls", "kyslan-nl", "lockstep");
    let ip = run("det-nl-ip", "kyslan-nl", "inprocess");
    assert_eq!(
        read(&ls.dir.join("trace.csv")),
        read(&ip.dir.join("trace.csv")),
        "lockstep and inprocess traces of kyslan-nl differ"
    );
}

#[test]
fn compare_draws_the_runs_on_one_set_of_axes_and_tabulates_the_metrics() {
    let _s = serial();
    let a = run("cmp-pi", "kyslan-pi", "inprocess");
    let b = run("cmp-nl", "kyslan-nl", "inprocess");
    let out = scratch("cmp-out");
    let o = drivelab(&[
        "compare",
        a.dir.to_str().unwrap(),
        b.dir.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let header = text.lines().next().unwrap();
    assert!(
        header.contains("kyslan-pi") && header.contains("kyslan-nl"),
        "{text}"
    );
    for (row, key, digits) in [
        ("rise time (ms)", "rise_time_ms", 2),
        ("overshoot (%)", "overshoot_pct", 1),
        ("load dip (rad/s)", "load_dip_rad_s", 2),
        ("load recovery (ms)", "load_recovery_ms", 1),
        ("i_d tracking error (A)", "id_tracking_error_a", 5),
    ] {
        let line = text
            .lines()
            .find(|l| l.starts_with(row))
            .unwrap_or_else(|| panic!("no '{row}' row in\n{text}"));
        // Side by side, the same numbers as each run's summary.json.
        let want: Vec<String> = [&a, &b]
            .iter()
            .map(|r| format!("{:.digits$}", r.metric(key)))
            .collect();
        let got: Vec<&str> = line[row.len()..].split_whitespace().collect();
        assert_eq!(got, want, "{row}");
    }
    for stem in ["compare_speed", "compare_iq", "compare_id"] {
        assert!(
            read(&out.join(format!("{stem}.png"))).len() > 1000,
            "{stem}.png"
        );
        // One set of axes with both runs: the SVG's legend has a text of its own for each
        // (the title names both too, on one line of its own).
        let svg = String::from_utf8(read(&out.join(format!("{stem}.svg")))).unwrap();
        for run in ["kyslan-pi", "kyslan-nl"] {
            assert!(
                svg.lines().any(|l| l.trim() == run),
                "{stem}.svg has no legend entry {run}"
            );
        }
    }
    let j: Value = serde_json::from_slice(&read(&out.join("comparison.json"))).unwrap();
    assert_eq!(j["runs"].as_array().unwrap().len(), 2);

    // A folder that is not a run: one clear line, exit code 1.
    let empty = scratch("cmp-empty");
    let o = drivelab(&["compare", a.dir.to_str().unwrap(), empty.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(
        err.starts_with("drivelab: error: ") && err.contains("no trace.csv"),
        "{err}"
    );
}

#[test]
fn design_printout_gives_both_designs_checkable_by_hand() {
    let o = drivelab(&["design", "--scenario", "kyslan-nl-sal618"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let t = String::from_utf8_lossy(&o.stdout).into_owned();
    // Kyslan motor with L_d = 24.75 mH: J = 4.3e-5, k_t = 3/2·5·0.104 = 0.78.
    let (j, kt) = (4.3e-5, 1.5 * 5.0 * 0.104);
    // PI: symmetrical optimum.
    let a = number_after(&t, ", a = ");
    let t_eq = number_after(&t, "T_eq = ") * 1e-3;
    let kp = number_after(&t, "Kp = J/(a·k_t·T_eq) = ");
    assert!((kp - j / (a * kt * t_eq)).abs() < 1e-5, "{kp}");
    let ti = number_after(&t, "Ti = a²·T_eq = ") * 1e-3;
    assert!((ti - a * a * t_eq).abs() < 1e-6, "{ti}");
    // Nonlinear: model constants and the closed-form gains of the pole placement.
    let a1 = number_after(&t, "a1 = 3pψ/(2J) = ");
    assert!((a1 - 1.5 * 5.0 * 0.104 / j).abs() < 0.01, "{a1}");
    let a2 = number_after(&t, "a2 = 3p(Ld-Lq)/(2J) = ");
    assert!(
        (a2 - 1.5 * 5.0 * (24.75e-3 - 4e-3) / j).abs() < 0.01,
        "{a2}"
    );
    let sing = number_after(&t, "uncontrollable at i_d = -ψ/(Ld-Lq) = ");
    assert!((sing + 0.104 / 20.75e-3).abs() < 1e-3, "{sing}");
    let z = 0.6;
    let wi = number_after(&t, "ω_i = 1/(2·τ_c) = ");
    assert!((wi - 0.5 / 2.5e-4).abs() < 1e-6, "{wi}");
    assert!((number_after(&t, "r2 = r3 = 2ζω_i = ") - 2.0 * z * wi).abs() < 0.01);
    assert!((number_after(&t, "K2 = K3 = ω_i² = ") - wi * wi).abs() < 1.0);
    // ω_0 is solved for the rise time on the design model: the solve met its target (the
    // printout's two-decimal rounding), and the speed loop stays slower than the torque loop
    // it commands (the cascade's premise, eq. 31).
    let w0 = number_after(&t, "ω_0 = ");
    assert!(w0 < wi, "{w0}");
    let rise = number_after(
        &t,
        "sampled, 1-sample delay, speed law every 10 samples): rise time ",
    );
    assert!((rise - 8.0).abs() <= 0.005, "{rise}");
    assert!((number_after(&t, "K1 = ω_0² = ") - w0 * w0).abs() < 1e-5 * w0 * w0);
    let r11 = number_after(&t, "r11 = 2ζω_0(ω_0+ω_i)/ω_i = ");
    assert!((r11 - 2.0 * z * w0 * (w0 + wi) / wi).abs() < 1e-3, "{r11}");
    let r12 = number_after(&t, "r12 = (ω_0/ω_i)² = ");
    assert!((r12 - (w0 / wi).powi(2)).abs() < 1e-6, "{r12}");
    let d12 = number_after(&t, "d12 = 2ζω_0/ω_i² = ");
    assert!((d12 - 2.0 * z * w0 / (wi * wi)).abs() < 1e-10, "{d12}");
    // Both design models meet the 8 ms target.
    assert_eq!(
        t.matches("rise time 8.00 ms (target 8.00 ms)").count(),
        2,
        "{t}"
    );
    assert!(t.contains("this scenario runs the nonlinear controller"));
    assert!(!t.contains("WARNING"), "{t}");
}

#[test]
fn a_set_point_near_the_uncontrollable_i_d_is_warned_and_the_run_completes() {
    // L_d = 24.75 mH: a1 + a2·i_d = 0 at i_d = −5.01 A (eq. 15). −3 A is past half of it.
    let _s = serial();
    let sc = variant(
        "nearsing",
        "kyslan-nl-sal618",
        &[("value = -1.6 }", "value = -3.0 }")],
    );
    let o = drivelab(&["design", "--scenario", sc.to_str().unwrap()]);
    let t = String::from_utf8_lossy(&o.stdout);
    assert!(
        t.contains("WARNING: i_d* = -3 A") && t.contains("eq. (15)"),
        "{t}"
    );
    let r = run("nearsing-run", sc.to_str().unwrap(), "lockstep");
    assert!(
        r.stderr.contains("speed-loop: warning: i_d* = -3 A"),
        "{}",
        r.stderr
    );
    assert!(
        r.stderr.contains("speed samples had an i_d set-point near"),
        "{}",
        r.stderr
    );
    assert!(r
        .trace()
        .iter()
        .all(|x| x.u_d.is_finite() && x.u_q.is_finite()));
    assert_eq!(r.summary["samples"], 1000);
}
