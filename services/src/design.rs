//! `drivelab design`: the controller design of a scenario, printed so it can be checked by hand.
//! Both controllers are designed for the scenario's motor and rise-time target: the PI cascade
//! (symmetrical optimum) and Kyslan's nonlinear controller (pole placement).

use drivelab_control::control::nonlinear::{KyslanModel, StepFigures};
use drivelab_runtime::config::Scenario;
use drivelab_runtime::drive::DriveDesign;
use std::collections::BTreeMap;
use std::fmt::Write;

/// A built-in stage that a user's stage runs in place of: the process that hosts it and the
/// executable (as the scenario writes it) that process starts.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Replacement {
    /// The process's name.
    pub process: String,
    /// Its `exec`.
    pub exec: String,
}

impl Replacement {
    /// "the user's current-loop stage (process 'p', exec ./x)".
    fn describe(&self, stage: &str) -> String {
        format!(
            "the user's {stage} stage (process '{}', exec {})",
            self.process, self.exec
        )
    }
}

/// The built-in stages of `sc` (loaded from `src`) that a user's stage replaces, as `drivelab
/// run` resolves them (`launcher::resolve_topology`): a process's `exec` is asked with
/// `--describe`, and replaces a built-in stage it hosts only if it declares a stage of that
/// name (docs/architecture.md, "Replacing a built-in stage"). A bad `exec` is the run's error.
/// `sc`'s processes are left resolved, as a run leaves them. Also the note lines `run` prints
/// about its topology (a built-in stage that runs in a process with an `exec`).
pub fn replacements(
    sc: &mut Scenario,
    src: &std::path::Path,
) -> anyhow::Result<(BTreeMap<String, Replacement>, Vec<String>)> {
    // The `exec` of each process as the scenario writes it (resolving makes it absolute).
    let written: BTreeMap<String, String> = sc
        .topology()
        .into_iter()
        .filter_map(|p| Some((p.name, p.exec?)))
        .collect();
    let plan = crate::launcher::resolve_topology(sc, src, &design_options(src))?;
    let replaced = plan
        .replaced
        .iter()
        .map(|(stage, exe)| {
            let p = plan
                .processes
                .iter()
                .find(|p| p.stages.contains(stage) && p.exec.as_ref() == Some(exe))
                .ok_or_else(|| anyhow::anyhow!("no process hosts the replaced stage '{stage}'"))?;
            let exec = written.get(&p.name).unwrap_or(exe).clone();
            let r = Replacement {
                process: p.name.clone(),
                exec,
            };
            Ok((stage.clone(), r))
        })
        .collect::<anyhow::Result<_>>()?;
    Ok((replaced, plan.notes))
}

/// The options of a `drivelab run` of `src` as far as resolving its topology reads them: the
/// scenario's own topology, on this machine, real time, the runner of `DRIVELAB_RUNNER`.
fn design_options(src: &std::path::Path) -> crate::launcher::RunOptions {
    crate::launcher::RunOptions {
        scenario: src.display().to_string(),
        no_plots: true,
        lockstep_restart_ms: drivelab_runtime::inject::RESTART_DEFAULT_MS,
        ..Default::default()
    }
}

/// Renders the design printout of `sc`, with the built-in stages in `replaced` run by a
/// user's stage (their built-in designs are printed for comparison and say "not run").
/// The controllers and observers are designed with the controller's view of the motor
/// (`[model]`); when it differs from the plant's, both sets are printed.
pub fn render(sc_true: &Scenario, replaced: &BTreeMap<String, Replacement>) -> String {
    let truth = sc_true.motor_params();
    let view = sc_true.controller_view();
    let sc = &view;
    let m = sc.motor_params();
    let d = DriveDesign::from_scenario(sc);
    let mut o = String::new();
    let motor_line = |o: &mut String, what: &str, m: &drivelab_control::motor::MotorParams| {
        let _ = writeln!(
            o,
            "{what}R = {} Ω, Ld = {} mH, Lq = {} mH, p = {}, ψ = {} Wb, J = {:e} kg·m², B = {:e} N·m·s/rad, k_t = {:.4} N·m/A",
            m.r_ohm, m.l_d_h * 1e3, m.l_q_h * 1e3, m.pole_pairs, m.psi_pm_wb, m.j_kgm2, m.b_nms, m.k_t()
        );
    };
    if truth == m {
        motor_line(&mut o, &format!("scenario {}: motor ", sc.name), &m);
    } else {
        motor_line(
            &mut o,
            &format!("scenario {}: plant (true) motor ", sc.name),
            &truth,
        );
        motor_line(
            &mut o,
            "  controller's model ([model], every design below): ",
            &m,
        );
    }
    for (what, pts) in [
        ("R", &sc_true.plant_drift.r_factor),
        ("ψ", &sc_true.plant_drift.psi_factor),
    ] {
        if !pts.is_empty() {
            let p: Vec<String> = pts
                .iter()
                .map(|p| format!("{} at {} s", p.value, p.t_s))
                .collect();
            let _ = writeln!(
                o,
                "  plant drift: true {what} × ({}), linear between the points",
                p.join(", ")
            );
        }
    }
    use drivelab_runtime::config::{CurrentController, SpeedController};
    // Every design is printed for comparison; the ones this scenario does not run say so
    // where they begin.
    let current_by = replaced.get("current-loop");
    let speed_by = replaced.get("speed-loop");
    let observer_by = replaced.get("observer");
    let loop_runs = |by: Option<&Replacement>, stage: &str, builtin: String| match by {
        Some(r) => r.describe(stage),
        None => builtin,
    };
    let _ = writeln!(
        o,
        "runs: {}, {}{} (the other designs below are for comparison and say \"not run\")",
        loop_runs(
            current_by,
            "current-loop",
            format!("{} current loop", name(&sc.current_loop.controller))
        ),
        loop_runs(
            speed_by,
            "speed-loop",
            format!("{} speed loop", name(&sc.speed_loop.controller))
        ),
        observer_by
            .map(|r| format!(", {}", r.describe("observer")))
            .unwrap_or_default()
    );
    let not_run = |runs: bool| if runs { "" } else { "not run: " };
    // As the scenario file names it.
    fn name(c: &impl serde::Serialize) -> String {
        serde_json::to_value(c)
            .ok()
            .and_then(|v| v.as_str().map(str::to_string))
            .unwrap_or_default()
    }
    let c = &d.current;
    let _ = writeln!(
        o,
        "{}current PI (pole-zero cancellation, τ_c = {} ms): d: Kp = L_d/τ_c = {:.4} V/A, Ki = R/τ_c = {:.1} V/(A·s); q: Kp = L_q/τ_c = {:.4} V/A, Ki = {:.1} V/(A·s)",
        not_run(sc.current_loop.controller == CurrentController::Pi && current_by.is_none()),
        c.tau_c_s * 1e3, c.k_p_d, c.k_i_d, c.k_p_q, c.k_i_q
    );
    let s = &d.speed;
    let _ = writeln!(
        o,
        "{}speed PI (symmetrical optimum, every {} samples = {} Hz): T_sigma = {:.4} ms, a = {:.4}, T_eq = {:.4} ms",
        not_run(sc.speed_loop.controller == SpeedController::Pi && speed_by.is_none()),
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
    let speed_pi_runs = sc.speed_loop.controller == SpeedController::Pi && speed_by.is_none();
    let _ = writeln!(
        o,
        "  design model (sampled cascade): rise time {:.2} ms (target {:.2} ms), overshoot {:.1} %{}",
        s.predicted_rise_time_s * 1e3,
        sc.speed_loop.rise_time_s * 1e3,
        s.predicted_overshoot_pct,
        unstable(
            s.spectral_radius,
            "",
            drivelab_runtime::drive::speed_loop_model(sc).response_window_s(s.a, s.t_eq_s),
            speed_pi_runs
        )
    );
    if let Some(w) = &s.warning {
        let _ = writeln!(o, "  WARNING: {w}");
    }
    render_nonlinear(&mut o, sc, &d, current_by.is_some(), speed_by.is_some());
    if let Some(r) = &d.rst {
        // Each loop's RST runs where its loop selects "rst" and no user's stage replaces it.
        let current = sc.current_loop.controller == CurrentController::Rst && current_by.is_none();
        let speed = sc.speed_loop.controller == SpeedController::Rst && speed_by.is_none();
        for line in r.render().lines() {
            let runs = match line.trim_start().split(' ').next() {
                Some("i_d" | "i_q") if line.starts_with("  i_") => current,
                Some("speed") if line.starts_with("  speed loop") => speed,
                _ => true,
            };
            let _ = match line.strip_prefix("  ").filter(|_| !runs) {
                Some(rest) => writeln!(o, "  not run: {rest}"),
                None => writeln!(o, "{line}"),
            };
        }
    }
    if let Some(ob) = &d.observer {
        o.push_str(not_run(observer_by.is_none()));
        o.push_str(&drivelab_control::observer_sensorless::render_design(
            ob,
            &m,
            sc.rates.ts(),
        ));
    }
    if let Some(p) = &d.polar {
        o.push_str(not_run(current_by.is_none()));
        o.push_str(&crate::cdm_design::render_polar_design(p));
    }
    let in_place: Vec<String> = replaced
        .iter()
        .map(|(st, r)| format!("{} in place of the built-in {st}", r.describe(st)))
        .collect();
    if in_place.is_empty() {
        let _ = writeln!(o, "this scenario runs the {} controller", d.controller);
    } else {
        let _ = writeln!(
            o,
            "this scenario runs the {} controller with {}",
            d.controller,
            in_place.join(", ")
        );
    }
    o
}

fn render_nonlinear(
    o: &mut String,
    sc: &Scenario,
    d: &DriveDesign,
    current_replaced: bool,
    speed_replaced: bool,
) {
    let m = sc.motor_params();
    let k = KyslanModel::new(&m);
    let n = &d.nonlinear;
    let g = &n.gains;
    let (z, wi, w0) = (n.zeta, n.omega_i_rad_s, n.omega_0_rad_s);
    let _ = writeln!(
        o,
        "{}nonlinear (Kyslan et al. 2015, two-step linearisation, x = [ω, i_q, i_d]):",
        match (sc.nonlinear(), current_replaced, speed_replaced) {
            (false, _, _) | (true, true, true) => "not run: ",
            (true, true, false) =>
                "not run as designed (the user's current-loop stage replaces its current law): ",
            (true, false, true) =>
                "not run as designed (the user's speed-loop stage replaces its speed law): ",
            (true, false, false) => "",
        }
    );
    let _ = writeln!(
        o,
        "  model (5)-(8): a1 = 3pψ/(2J) = {:.2}, a2 = 3p(Ld-Lq)/(2J) = {:.2}, a3 = R/Lq = {:.1}, a4 = pLd/Lq = {:.4}, a5 = pψ/Lq = {:.1}, a6 = R/Ld = {:.2}, a7 = pLq/Ld = {:.4}, b21 = 1/Lq = {:.1}, b32 = 1/Ld = {:.3}, e = 1/J = {:.1}",
        k.a1, k.a2, k.a3, k.a4, k.a5, k.a6, k.a7, k.b21, k.b32, k.e
    );
    match n.i_d_singular_a {
        Some(i) => {
            let _ = writeln!(
                o,
                "  eq. (15): uncontrollable at i_d = -ψ/(Ld-Lq) = {i:.3} A; warning below a1 + a2·i_d = {:.0} % of a1 (i_d = {:.3} A)",
                100.0 * drivelab_control::control::nonlinear::NEAR_SINGULAR,
                (drivelab_control::control::nonlinear::NEAR_SINGULAR - 1.0) * k.a1 / k.a2
            );
        }
        None => {
            let _ = writeln!(o, "  eq. (15): Ld = Lq, controllable everywhere");
        }
    }
    for w in &d.warnings {
        let _ = writeln!(o, "  WARNING: {w}");
    }
    if n.sampled.is_none() {
        let _ = writeln!(
            o,
            "  inner loops (27) i = 2, 3, damping ζ = {z}, ω_i = 1/(2·τ_c) = {wi:.1} rad/s: r2 = r3 = 2ζω_i = {:.2} 1/s, K2 = K3 = ω_i² = {:.6e} 1/s²",
            g.r2, g.k2
        );
    } else {
        let _ = writeln!(
            o,
            "  field loop (27) i = 3, damping ζ = {z}, ω_i = 1/(2·τ_c) = {wi:.1} rad/s: r3 = 2ζω_i = {:.2} 1/s, K3 = ω_i² = {:.6e} 1/s²; torque loop (27) i = 2 placed with the speed subsystem: r2 = {:.2} 1/s, K2 = {:.6e} 1/s²",
            g.r3, g.k3, g.r2, g.k2
        );
    }
    match &n.sampled {
        None => {
            let _ = writeln!(
                o,
                "  speed subsystem (27) i = 1, (31): poles (s² + 2ζω_0 s + ω_0²)(s² + 2ζω_i s + ω_i²), ω_0 = {w0:.3} rad/s (solved for the rise time)"
            );
            let _ = writeln!(
                o,
                "    K1 = ω_0² = {:.6e} 1/s², r11 = 2ζω_0(ω_0+ω_i)/ω_i = {:.4} 1/s, r12 = (ω_0/ω_i)² = {:.6}, d12 = 2ζω_0/ω_i² = {:.6e} s",
                g.k1, g.r11, g.r12, g.d12
            );
        }
        Some(sp) => {
            let _ = writeln!(
                o,
                "  speed subsystem (27) i = 1, (31) placed on the sampled loop as it runs (delay, speed law every {} samples, speed filter): dominant pair at (ζ, ω_0), ω_0 = {w0:.3} rad/s (the slowest that meets the rise time, else the fastest-rising); every other pole as fast as r12, d12, r2, K2 make it (slowest at {:.1} rad/s)",
                sc.rates.speed_divider, sp.others_slowest_rad_s
            );
            let _ = writeln!(
                o,
                "    K1 = {:.6e} 1/s², r11 = {:.4} 1/s (det(zI − Φ) = 0 at the pair, affine in both), r12 = {:.6}, d12 = {:.6e} s (the continuous closed forms no longer hold)",
                g.k1, g.r11, g.r12, g.d12
            );
            let poles: Vec<String> = sp
                .poles
                .iter()
                .take(8)
                .map(|(re, im)| format!("{re:.1}{im:+.1}j"))
                .collect();
            let _ = writeln!(
                o,
                "    poles of the sampled loop, ln(z)/T_w in rad/s, slowest first: {}",
                poles.join(", ")
            );
        }
    }
    let _ = writeln!(
        o,
        "    settled gain g = 1 + r12 + d12·r2 = {:.6} (bus i_q* = (v1 - r11·ω)/(g·(a1 + a2·i_d*)))",
        n.g_ss
    );
    // Whether the sampled loop is stable: a response that grows without bound has a "rise
    // time" and an "overshoot" only because its simulation stopped somewhere.
    let model = drivelab_control::control::nonlinear::NlLoopModel {
        ts: sc.rates.ts(),
        n: sc.rates.speed_divider,
        tau_f_s: sc.observer.speed_filter_tau_s,
    };
    let unstable = unstable(
        model.spectral_radius(&m, g),
        " (linearised at rest)",
        n.response_window_s,
        sc.nonlinear(),
    );
    let _ = writeln!(
        o,
        "  design model (drive's discrete law, sampled, 1-sample delay, speed law every {} samples): {}{unstable}",
        sc.rates.speed_divider,
        response(&n.predicted(), Some(sc.speed_loop.rise_time_s))
    );
    let _ = writeln!(
        o,
        "  {} on the continuous dummy system (26)-(27): {}",
        if n.sampled.is_some() {
            "the continuous placement at the same ω_0"
        } else {
            "same gains"
        },
        response(&n.continuous(), None)
    );
    if let Some(w) = &n.warning {
        let _ = writeln!(o, "  WARNING: {w}");
    }
}

/// The stability verdict of a design whose sampled design model's poles reach `rho` = max |z|
/// (`how` says of what model, e.g. " (linearised at rest)"), to follow its figures: empty when
/// the loop is stable, else "; UNSTABLE: …". The figures of an unstable loop are only those
/// of the `window_s` simulated: its response grows without bound.
fn unstable(rho: f64, how: &str, window_s: f64, runs: bool) -> String {
    if rho.is_nan() {
        return "; its poles cannot be computed: the sampled loop's matrix is not a finite number (the motor's values are out of scale for this rate)".into();
    }
    if rho <= 1.0 {
        return String::new();
    }
    format!(
        "; UNSTABLE: the sampled loop has a pole at |z| = {rho:.3} > 1{how}, so its response grows without bound and these figures are only those of the {:.2} ms simulated{}",
        window_s * 1e3,
        if runs { "" } else { " (this design is not run: for comparison only)" }
    )
}

/// "rise time 8.00 ms (target 8.00 ms), overshoot 12.3 %" of a design's step response, or
/// what it did instead: "did not reach the set-point within 20.00 ms (target 0.20 ms)",
/// "diverged: not finite within 2.00 ms".
fn response(f: &StepFigures, target_s: Option<f64>) -> String {
    let target = target_s.map_or(String::new(), |t| format!(" (target {:.2} ms)", t * 1e3));
    match (f.rise_s, f.overshoot_pct, f.failure()) {
        (Some(r), Some(os), _) => {
            format!("rise time {:.2} ms{target}, overshoot {os:.1} %", r * 1e3)
        }
        (Some(r), None, why) => format!(
            "rise time {:.2} ms{target}, then {}",
            r * 1e3,
            why.unwrap_or_default()
        ),
        (None, _, why) => format!("{}{target}", why.unwrap_or_default()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_rise_time_the_loops_cannot_meet_prints_what_they_give_not_nan() {
        // 0.2 ms: the nonlinear design's speed pair at ω_0 = ω_i rises well after 10 × the
        // target; its figures and the warning are read off the whole response.
        let mut sc = crate::launcher::load_scenario("kyslan-nl", None).unwrap();
        sc.speed_loop.rise_time_s = 0.2e-3;
        let t = render(&sc, &BTreeMap::new());
        assert!(!t.contains("NaN"), "{t}");
        let line = t
            .lines()
            .find(|l| l.contains("design model (drive's discrete law"))
            .unwrap();
        assert!(line.contains("(target 0.20 ms), overshoot "), "{line}");
        assert!(t.contains("(ω_0 = ω_i gives "), "{t}");
    }

    #[test]
    fn the_designs_a_scenario_does_not_run_say_so() {
        // (scenario, what runs, which of current PI, speed PI, nonlinear are not run)
        for (name, runs, not_run) in [
            (
                "kyslan-pi",
                "pi current loop, pi speed loop",
                [false, false, true],
            ),
            (
                "kyslan-nl",
                "nonlinear current loop, nonlinear speed loop",
                [true, true, false],
            ),
            (
                "low-rst",
                "rst current loop, rst speed loop",
                [true, true, true],
            ),
        ] {
            let t = render(
                &crate::launcher::load_scenario(name, None).unwrap(),
                &BTreeMap::new(),
            );
            assert!(
                t.lines()
                    .nth(1)
                    .unwrap()
                    .starts_with(&format!("runs: {runs} (")),
                "{t}"
            );
            for (section, not) in ["current PI (", "speed PI (", "nonlinear (Kyslan"]
                .iter()
                .zip(not_run)
            {
                let line = t.lines().find(|l| l.contains(section)).unwrap();
                assert_eq!(line.starts_with("not run: "), not, "{name}: {line}");
            }
        }
    }
    #[test]
    fn a_loop_a_users_stage_replaces_is_named_as_what_runs_and_its_design_not_run() {
        let mut sc = crate::launcher::load_scenario("kyslan-pi", None).unwrap();
        sc.process = drivelab_runtime::topology::load("four-process")
            .unwrap()
            .0
            .process;
        let cl = sc
            .process
            .iter_mut()
            .find(|p| p.stages.iter().any(|s| s == "current-loop"))
            .unwrap();
        cl.exec = Some("./my-loop".into());
        let process = cl.name.clone();
        let t = render(&sc, &replaced_by(&sc, "current-loop"));
        let runs = t.lines().nth(1).unwrap();
        assert!(
            runs.starts_with(&format!(
                "runs: the user's current-loop stage (process '{process}', exec ./my-loop), pi speed loop ("
            )),
            "{t}"
        );
        assert!(!runs.contains("pi current loop"), "{runs}");
        let line = |what: &str| t.lines().find(|l| l.contains(what)).unwrap();
        assert!(line("current PI (").starts_with("not run: "), "{t}");
        assert!(line("speed PI (").starts_with("speed PI ("), "{t}");
        assert!(
            t.trim_end().ends_with(&format!(
                "this scenario runs the pi controller with the user's current-loop stage (process '{process}', exec ./my-loop) in place of the built-in current-loop"
            )),
            "{t}"
        );
        // Low et al.'s RST: the replaced speed loop's RST design is not run, the current
        // loops' are.
        let mut sc = crate::launcher::load_scenario("low-rst", None).unwrap();
        sc.process = drivelab_runtime::topology::load("four-process")
            .unwrap()
            .0
            .process;
        for p in sc.process.iter_mut() {
            if p.stages.iter().any(|s| s == "speed-loop") {
                p.exec = Some("./my-speed".into());
            }
        }
        let t = render(&sc, &replaced_by(&sc, "speed-loop"));
        for (section, not) in [
            ("i_d loop (", false),
            ("i_q loop (", false),
            ("speed loop (T", true),
        ] {
            let l = line_of(&t, section);
            assert_eq!(l.starts_with("  not run: "), not, "{l}");
        }
    }

    /// `stage` replaced by the user's stage of the process of `sc` that hosts it (its `exec`).
    fn replaced_by(sc: &Scenario, stage: &str) -> BTreeMap<String, Replacement> {
        let p = sc
            .process
            .iter()
            .find(|p| p.stages.iter().any(|s| s == stage))
            .unwrap();
        BTreeMap::from([(
            stage.to_string(),
            Replacement {
                process: p.name.clone(),
                exec: p.exec.clone().unwrap(),
            },
        )])
    }

    fn line_of<'a>(t: &'a str, what: &str) -> &'a str {
        t.lines().find(|l| l.contains(what)).unwrap()
    }

    #[test]
    fn an_unstable_speed_pi_says_so_and_no_shipped_scenarios_does() {
        // A speed law every 1000 samples (10 Hz behind a 10 kHz current loop): the sampled
        // cascade's symmetrical optimum has a pole outside the unit circle, though its
        // figures (read off the simulated window) look like a design's.
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("slow-speed-law.toml");
        let text = std::fs::read_to_string(
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/kyslan-pi.toml"),
        )
        .unwrap()
        .replace("speed_divider = 10 ", "speed_divider = 1000 ");
        std::fs::write(&file, text).unwrap();
        let sc = crate::launcher::load_scenario(file.to_str().unwrap(), None).unwrap();
        assert_eq!(sc.rates.speed_divider, 1000);
        let t = render(&sc, &BTreeMap::new());
        let l = line_of(&t, "design model (sampled cascade)");
        assert!(l.contains(", overshoot "), "the figure stays: {l}");
        assert!(
            l.contains("; UNSTABLE: the sampled loop has a pole at |z| = "),
            "{l}"
        );
        assert!(!l.contains("not run"), "kyslan-pi runs its speed PI: {l}");
        let json = serde_json::to_value(DriveDesign::from_scenario(&sc.controller_view())).unwrap();
        assert!(
            json["speed"]["spectral_radius"].as_f64().unwrap() > 1.0,
            "{json}"
        );
        // Every shipped scenario: only the nonlinear designs flagged so far are unstable.
        for f in std::fs::read_dir(concat!(env!("CARGO_MANIFEST_DIR"), "/../scenarios")).unwrap() {
            let f = f.unwrap().path();
            if f.extension().is_none_or(|e| e != "toml") {
                continue;
            }
            let sc = crate::launcher::load_scenario(f.to_str().unwrap(), None).unwrap();
            let t = render(&sc, &BTreeMap::new());
            for l in t.lines().filter(|l| l.contains("UNSTABLE")) {
                assert!(
                    l.contains("design model (drive's discrete law")
                        && l.contains("(linearised at rest)"),
                    "{}: {l}",
                    f.display()
                );
            }
        }
    }

    #[test]
    fn an_unstable_design_says_so_beside_its_overshoot() {
        // low-rst-sensorless's nonlinear design (for comparison, not run): the sampled loop at
        // 5 kHz with a 500 Hz speed law is unstable, and its figures are those of a growing
        // response within the simulated window. Kyslan's own is stable.
        let sc = crate::launcher::load_scenario("low-rst-sensorless", None).unwrap();
        let t = render(&sc, &BTreeMap::new());
        // The pole tells the truth: simulated twice as long, the response overshoots more.
        let view = sc.controller_view();
        let n = DriveDesign::from_scenario(&view).nonlinear;
        let model = drivelab_control::control::nonlinear::NlLoopModel {
            ts: view.rates.ts(),
            n: view.rates.speed_divider,
            tau_f_s: view.observer.speed_filter_tau_s,
        };
        let longer = model
            .step_response(&view.motor_params(), &n.gains, 2.0 * n.response_window_s)
            .overshoot_pct
            .unwrap();
        assert!(
            longer > 10.0 * n.predicted_overshoot_pct.unwrap(),
            "{longer}"
        );
        let l = line_of(&t, "design model (drive's discrete law");
        assert!(l.contains(", overshoot "), "the figure stays: {l}");
        assert!(
            l.contains("; UNSTABLE: the sampled loop has a pole at |z| = "),
            "{l}"
        );
        assert!(
            l.contains("(this design is not run: for comparison only)"),
            "{l}"
        );
        let t = render(
            &crate::launcher::load_scenario("kyslan-nl", None).unwrap(),
            &BTreeMap::new(),
        );
        let l = line_of(&t, "design model (drive's discrete law");
        assert!(!l.contains("UNSTABLE"), "{l}");
    }
}
