//! `drivelab plant --replay`: the plant model alone, open loop, from rest.

use anyhow::{anyhow, bail, Context, Result};
use drivelab_control::motor::{Mechanics, MotorInput, MotorParams, MotorState, Rk4};
use drivelab_runtime::config::MotorSpec;
use serde::{Deserialize, Serialize};
use std::path::Path;

#[derive(Debug, Deserialize)]
struct InRow {
    t: f64,
    u_d: f64,
    u_q: f64,
    t_load: f64,
}

#[derive(Debug, Serialize)]
struct OutRow {
    t: f64,
    u_d: f64,
    u_q: f64,
    t_load: f64,
    i_d: f64,
    i_q: f64,
    omega_m: f64,
    theta_e: f64,
}

/// Resolves `--motor`: a preset name or a TOML file holding a `[motor]` table (or its fields).
pub fn resolve_motor(spec: &str) -> Result<MotorParams> {
    if let Some(m) = MotorParams::preset(spec) {
        return Ok(m);
    }
    let p = Path::new(spec);
    if !p.is_file() {
        bail!(
            "unknown motor '{spec}': not a preset ({}) and not a file",
            MotorParams::PRESETS.join(", ")
        );
    }
    let text = std::fs::read_to_string(p).with_context(|| format!("cannot read {spec}"))?;
    #[derive(Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Wrapped {
        motor: MotorSpec,
    }
    // The error of the form the file is in: a `[motor]` table, or its fields alone.
    let wrapped = toml::from_str::<toml::Table>(&text).is_ok_and(|t| t.contains_key("motor"));
    let ms = if wrapped {
        toml::from_str::<Wrapped>(&text)
            .map(|w| w.motor)
            .map_err(|e| anyhow!("{spec}: {}", e.message()))?
    } else {
        toml::from_str::<MotorSpec>(&text).map_err(|e| anyhow!("{spec}: {}", e.message()))?
    };
    ms.resolve().map_err(|e| anyhow!("{spec}: {e}"))
}

/// Most RK4 steps one replay may take (about a minute of computing).
pub const MAX_STEPS: u64 = 1_000_000_000;

/// Integrates the model through the input rows; each row's inputs are held from its t on.
/// Output rows are the state at each input row's time, before that row's input acts.
pub fn replay(input: &Path, output: &Path, m: &MotorParams, max_step_s: f64) -> Result<usize> {
    replay_within(input, output, m, max_step_s, MAX_STEPS)
}

/// [`replay`], refusing an input that needs more than `max_steps` RK4 steps.
fn replay_within(
    input: &Path,
    output: &Path,
    m: &MotorParams,
    max_step_s: f64,
    max_steps: u64,
) -> Result<usize> {
    if !(max_step_s.is_finite() && max_step_s > 0.0) {
        bail!("the largest step must be a positive number of seconds, got {max_step_s}");
    }
    if !input.is_file() {
        bail!(
            "--replay {}: not a file (a CSV with columns t,u_d,u_q,t_load)",
            input.display()
        );
    }
    // The rows are read before the output is written, but the input would be lost.
    if output
        .canonicalize()
        .is_ok_and(|o| input.canonicalize().is_ok_and(|i| i == o))
    {
        bail!(
            "--out {}: the same file as --replay; give another",
            output.display()
        );
    }
    let mut rd = csv::Reader::from_path(input)
        .with_context(|| format!("cannot read {}", input.display()))?;
    let headers = rd
        .headers()
        .with_context(|| format!("cannot read {}", input.display()))?
        .clone();
    let missing: Vec<&str> = ["t", "u_d", "u_q", "t_load"]
        .into_iter()
        .filter(|c| !headers.iter().any(|h| h.trim() == *c))
        .collect();
    if !missing.is_empty() {
        bail!(
            "{}: no column {} in its first line (need columns t,u_d,u_q,t_load)",
            input.display(),
            missing.join(", ")
        );
    }
    let mut rows = Vec::new();
    for (i, r) in rd.deserialize::<InRow>().enumerate() {
        let r = r.map_err(|e| {
            // The column and what is wrong with it, not the CSV reader's byte positions.
            let what = match e.kind() {
                csv::ErrorKind::Deserialize { err, .. } => match err.field() {
                    Some(f) => format!(
                        "column {}: {}",
                        headers.get(f as usize).unwrap_or("?"),
                        err.kind()
                    ),
                    None => err.kind().to_string(),
                },
                csv::ErrorKind::UnequalLengths {
                    len, expected_len, ..
                } => {
                    format!("{len} fields, the first line has {expected_len}")
                }
                _ => e.to_string(),
            };
            anyhow!("{} row {}: {what}", input.display(), i + 2)
        })?;
        if ![r.t, r.u_d, r.u_q, r.t_load].iter().all(|v| v.is_finite()) {
            bail!(
                "{} row {}: values must be finite numbers",
                input.display(),
                i + 2
            );
        }
        if let Some(prev) = rows.last().map(|p: &InRow| p.t) {
            if r.t <= prev {
                bail!(
                    "{} row {}: t = {} must increase (previous {prev})",
                    input.display(),
                    i + 2,
                    r.t
                );
            }
        }
        rows.push(r);
    }
    if rows.is_empty() {
        bail!("{} has no rows", input.display());
    }
    // Every step count is known before the first: refuse what cannot be done.
    let mut total = 0f64;
    for w in rows.windows(2) {
        total += ((w[1].t - w[0].t) / max_step_s).ceil().max(1.0);
    }
    if total > max_steps as f64 {
        bail!(
            "{}: t from {} to {} s at steps of at most {max_step_s} s needs {total:.3e} RK4 steps, more than {max_steps}; raise --max-step-s or shorten the input",
            input.display(),
            rows[0].t,
            rows[rows.len() - 1].t
        );
    }
    let states = simulate(&rows, m, max_step_s);
    let finite = |r: &OutRow| {
        [r.i_d, r.i_q, r.omega_m, r.theta_e]
            .iter()
            .all(|v| v.is_finite())
    };
    if let Some(r) = states.iter().find(|r| !finite(r)) {
        bail!(
            "{}: the model's state is not a finite number from t = {} s on (inputs too large for the motor, or --max-step-s too long)",
            input.display(),
            r.t
        );
    }
    let mut w = csv::Writer::from_writer(
        drivelab_runtime::files::create(output)
            .with_context(|| format!("cannot write {}", output.display()))?,
    );
    for r in states {
        w.serialize(r)?;
    }
    w.flush()?;
    Ok(rows.len())
}

/// The model from rest through `rows` (checked: finite, t increasing): each row's inputs
/// held from its t to the next row's, in RK4 steps of at most `max_step_s`; one output row
/// per input row, the state at its t before its input acts.
fn simulate(rows: &[InRow], m: &MotorParams, max_step_s: f64) -> Vec<OutRow> {
    let mut out = Vec::with_capacity(rows.len());
    let mut x = MotorState::default();
    for (i, r) in rows.iter().enumerate() {
        out.push(OutRow {
            t: r.t,
            u_d: r.u_d,
            u_q: r.u_q,
            t_load: r.t_load,
            i_d: x.i_d,
            i_q: x.i_q,
            omega_m: x.omega_m,
            theta_e: x.theta_e(m),
        });
        if let Some(next) = rows.get(i + 1) {
            let dt = next.t - r.t;
            let substeps = (dt / max_step_s).ceil().max(1.0) as u32;
            let u = MotorInput {
                u_d: r.u_d,
                u_q: r.u_q,
                t_load: r.t_load,
                ..Default::default()
            };
            x = Rk4 { substeps }.advance(m, Mechanics::Inertia, &x, &u, dt);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn run(text: &str, max_step_s: f64, max_steps: u64) -> Result<usize> {
        // One folder per call: the tests run in parallel.
        static CALLS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let n = CALLS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!("drivelab-replay-{}-{n}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (i, o) = (dir.join("in.csv"), dir.join("out.csv"));
        std::fs::write(&i, text).unwrap();
        let m = MotorParams::preset("kyslan2015").unwrap();
        let r = replay_within(&i, &o, &m, max_step_s, max_steps);
        let _ = std::fs::remove_dir_all(&dir);
        r
    }

    #[test]
    fn a_replay_that_needs_too_many_steps_is_refused_before_it_starts() {
        let e = run("t,u_d,u_q,t_load\n0,0,0,0\n1e300,1,1,0\n", 1e-5, MAX_STEPS)
            .unwrap_err()
            .to_string();
        assert!(e.contains("RK4 steps, more than 1000000000"), "{e}");
        assert!(!e.contains('\n'), "{e}");
        // Within the limit it runs: 1 s at 1 ms steps is 1000 steps.
        assert_eq!(
            run("t,u_d,u_q,t_load\n0,0,0,0\n1,1,1,0\n", 1e-3, 1000).unwrap(),
            2
        );
        assert!(run("t,u_d,u_q,t_load\n0,0,0,0\n1,1,1,0\n", 1e-3, 999).is_err());
        assert!(run("t,u_d,u_q,t_load\n0,0,0,0\n", 0.0, 10).is_err());
    }

    fn row(t: f64, u_d: f64, u_q: f64, t_load: f64) -> InRow {
        InRow {
            t,
            u_d,
            u_q,
            t_load,
        }
    }

    #[test]
    fn each_rows_input_is_held_from_its_time_and_each_output_is_the_state_before_it() {
        // u_d alone on a motor at rest: no torque (i_q = 0), so it stays at rest and i_d
        // follows the RL circuit, i_d(t) = u/R·(1 − e^{−t/τ}) with τ = L_d/R, then decays
        // as e^{−t/τ} once u_d is 0.
        let m = MotorParams::preset("kyslan2015").unwrap();
        let tau = m.l_d_h / m.r_ohm;
        let (u, t1, t2) = (10.0, 0.5 * tau, 1.5 * tau);
        let rows = [
            row(0.0, u, 0.0, 0.0),
            row(t1, 0.0, 0.0, 0.0),
            row(t2, 0.0, 0.0, 0.0),
        ];
        let out = simulate(&rows, &m, tau / 1000.0);
        assert_eq!(out.len(), 3);
        let i1 = u / m.r_ohm * (1.0 - (-t1 / tau).exp());
        let i2 = i1 * (-(t2 - t1) / tau).exp();
        // RK4 at τ/1000: its global error, of order (h/τ)^4 = 1e-12 of the current, is far
        // below the 1e-9 A allowed.
        for (o, want) in out.iter().zip([0.0, i1, i2]) {
            assert!(
                (o.i_d - want).abs() < 1e-9,
                "t = {}: {} vs {want}",
                o.t,
                o.i_d
            );
            assert_eq!((o.i_q, o.omega_m), (0.0, 0.0));
        }
        // The row's own inputs are echoed beside the state they have not acted on yet.
        assert_eq!((out[0].u_d, out[1].u_d), (u, 0.0));
    }

    #[test]
    fn motors_are_presets_or_files_with_or_without_a_motor_table() {
        let low = MotorParams::preset("low1998").unwrap();
        assert_eq!(resolve_motor("low1998").unwrap(), low);
        let dir = std::env::temp_dir().join(format!("drivelab-motor-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = |name: &str, text: &str| {
            let p = dir.join(name);
            std::fs::write(&p, text).unwrap();
            p.to_string_lossy().into_owned()
        };
        let wrapped = f("w.toml", "[motor]\npreset = \"low1998\"\nr_ohm = 3.0\n");
        let bare = f("b.toml", "preset = \"low1998\"\nr_ohm = 3.0\n");
        let bad = f("x.toml", "[motor]\npreset = \"low1998\"\nr_ohms = 3.0\n");
        let want = MotorParams { r_ohm: 3.0, ..low };
        assert_eq!(resolve_motor(&wrapped).unwrap(), want);
        assert_eq!(resolve_motor(&bare).unwrap(), want);
        let e = resolve_motor(&bad).unwrap_err().to_string();
        // The unknown key is named, in a `[motor]` table and in a bare file alike.
        assert!(
            e.starts_with(&bad) && !e.contains('\n') && e.contains("`r_ohms`"),
            "{e}"
        );
        let bad_bare = f("y.toml", "preset = \"low1998\"\nr_ohms = 3.0\n");
        let e = resolve_motor(&bad_bare).unwrap_err().to_string();
        assert!(e.contains("`r_ohms`"), "{e}");
        let e = resolve_motor("no-such-motor").unwrap_err().to_string();
        assert!(
            e.contains("unknown motor 'no-such-motor': not a preset (") && e.contains("low1998"),
            "{e}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn rows_out_of_order_not_finite_or_absent_are_refused_naming_the_row() {
        for (text, want) in [
            (
                "t,u_d,u_q,t_load\n0,0,0,0\n0,1,1,0\n",
                "row 3: t = 0 must increase (previous 0)",
            ),
            (
                "t,u_d,u_q,t_load\n0,0,0,0\n1,NaN,1,0\n",
                "row 3: values must be finite numbers",
            ),
            ("t,u_d,u_q,t_load\n", "has no rows"),
            ("t,u_d,u_q\n0,0,0\n", ": no column t_load in its first line"),
            (
                "t,u_d,u_q,t_load\n0,0,x,0\n",
                "row 2: column u_q: invalid float literal",
            ),
        ] {
            let e = run(text, 1e-3, 1000).unwrap_err().to_string();
            assert!(e.contains(want), "{text:?}: {e}");
        }
    }

    /// A CSV cell: numbers of every size, the words f64 parsing knows, and junk.
    fn cell() -> impl Strategy<Value = String> {
        prop_oneof![
            any::<f64>().prop_map(|x| x.to_string()),
            (-10.0f64..10.0).prop_map(|x| x.to_string()),
            Just("NaN".to_string()),
            Just("inf".to_string()),
            Just("".to_string()),
            "[ -~]{0,8}",
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 256, failure_persistence: None, ..ProptestConfig::default() })]

        #[test]
        fn no_csv_input_panics_and_every_refusal_is_one_line(
            header in prop_oneof![Just("t,u_d,u_q,t_load".to_string()), "[ -~]{0,30}"],
            rows in prop::collection::vec(prop::collection::vec(cell(), 0..6), 0..6),
        ) {
            let mut text = header + "\n";
            for r in rows {
                text += &r.join(",");
                text += "\n";
            }
            // The small step limit keeps each case short; what it refuses is checked above.
            match run(&text, 1e-3, 100_000) {
                Ok(n) => prop_assert!(n >= 1),
                Err(e) => prop_assert!(!format!("{e:#}").contains('\n'), "{e:#}"),
            }
        }
    }
}
