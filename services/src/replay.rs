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
    // Names trimmed as the check below trims them: rows are read by the trimmed names.
    let mut rd = csv::ReaderBuilder::new()
        .trim(csv::Trim::Headers)
        .from_path(input)
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

    /// `f(input, folder)` with `text` (any bytes) written to `input` in a folder of its own
    /// (the tests run in parallel), removed afterwards.
    fn with_input<R>(text: impl AsRef<[u8]>, f: impl FnOnce(&Path, &Path) -> R) -> R {
        static CALLS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let n = CALLS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!("drivelab-replay-{}-{n}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let i = dir.join("in.csv");
        std::fs::write(&i, text).unwrap();
        let r = f(&i, &dir);
        let _ = std::fs::remove_dir_all(&dir);
        r
    }

    /// [`replay_within`] on a file holding `text` (any bytes), kyslan2015's model.
    fn run(text: impl AsRef<[u8]>, max_step_s: f64, max_steps: u64) -> Result<usize> {
        let m = MotorParams::preset("kyslan2015").unwrap();
        with_input(text, |i, dir| {
            replay_within(i, &dir.join("out.csv"), &m, max_step_s, max_steps)
        })
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

    /// A header whose names have spaces or tabs around them is read by the names: the
    /// column check trims them, and so must the reading of the rows (it did not, and every
    /// row was refused for a missing field).
    #[test]
    fn names_in_the_header_may_have_spaces_around_them() {
        assert_eq!(
            run("t, u_d , u_q,\tt_load\n0,0,0,0\n0.001,1,1,0\n", 1e-4, 100).unwrap(),
            2
        );
    }

    /// An input that drives the model's state past the largest f64 is refused, naming the
    /// first time at which it is not finite.
    #[test]
    fn inputs_the_model_cannot_follow_are_refused_naming_the_time() {
        // 1e300 V on the d axis for 1 ms: the current, then the torque and the speed it
        // couples into, overflow within the ten 0.1 ms steps; the state at t = 0 is rest.
        let e = run("t,u_d,u_q,t_load\n0,1e300,10,0\n0.001,0,0,0\n", 1e-4, 1000)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("the model's state is not a finite number from t = 0.001 s on"),
            "{e}"
        );
        assert!(!e.contains(['\n', '\r']), "{e}");
    }

    /// A good input whose output file cannot be created is refused, naming the output.
    #[test]
    fn an_output_that_cannot_be_written_is_refused_naming_it() {
        let m = MotorParams::preset("kyslan2015").unwrap();
        // The folder itself as the output: the input is good, the file cannot be opened.
        let (e, dir) = with_input("t,u_d,u_q,t_load\n0,0,0,0\n", |i, dir| {
            let e = replay_within(i, dir, &m, 1e-3, 10).unwrap_err();
            (format!("{e:#}"), dir.to_path_buf())
        });
        assert!(
            e.starts_with(&format!("cannot write {}: ", dir.display())),
            "{e}"
        );
        assert!(!e.contains(['\n', '\r']), "{e}");
    }

    /// The columns a replay reads, in the order of [`InRow`]'s fields.
    const COLUMNS: [&str; 4] = ["t", "u_d", "u_q", "t_load"];

    /// The property test's largest RK4 step: 0.1 ms, under both electrical time constants
    /// of kyslan2015 (L_q/R = 0.57 ms, L_d/R = 1.25 ms), as `drivelab plant` requires.
    const STEP_S: f64 = 1e-4;

    /// Most rows in a generated input.
    const MAX_ROWS: usize = 8;

    /// Longest interval between two rows of an ordinary input: 10 ms, 100 steps.
    const ORDINARY_DT_S: f64 = 1e-2;

    /// The property test's step budget: an ordinary input needs at most
    /// (`MAX_ROWS` − 1) · 100 = 700 steps, so only wide inputs run into it; it keeps each
    /// case to milliseconds.
    const BUDGET: u64 = 10_000;

    /// Largest voltage of an ordinary input: 50 V drives at most about 7 A through
    /// kyslan2015's 7 Ω windings.
    const ORDINARY_V: f64 = 50.0;

    /// Largest load torque of an ordinary input: under kyslan2015's rated 0.55 N·m, so the
    /// speed stays where 0.1 ms steps follow the model.
    const ORDINARY_NM: f64 = 0.5;

    /// A well-formed replay input, and the ways of writing it that must not matter.
    #[derive(Debug, Clone)]
    struct Input {
        /// Each row's t, u_d, u_q, t_load: finite, t increasing.
        rows: Vec<[f64; 4]>,
        /// Within the `ORDINARY_*` bounds, where the model stays finite: it must be
        /// accepted. Otherwise values and intervals of any size.
        ordinary: bool,
        /// The order the header names the columns in: its k-th is `COLUMNS[order[k]]`.
        order: Vec<usize>,
        /// A column of text after the four (any characters, quoted where CSV needs it),
        /// which the replay ignores, one cell per row.
        note: Option<Vec<String>>,
        /// Spaces around the header's names.
        padded: bool,
        /// Numbers in exponent notation (`1e-5`) rather than positional (`0.00001`).
        exponent: bool,
        /// Lines end in CR LF rather than LF.
        crlf: bool,
    }

    impl Input {
        /// A number as this input writes it (either way, the same f64 is read back).
        fn number(&self, x: f64) -> String {
            if self.exponent {
                format!("{x:e}")
            } else {
                x.to_string()
            }
        }

        /// Where the header puts `COLUMNS[c]`.
        fn at(&self, c: usize) -> usize {
            self.order.iter().position(|&k| k == c).unwrap()
        }

        /// The header's cells and each row's, unquoted.
        fn cells(&self) -> (Vec<String>, Vec<Vec<String>>) {
            let name = |s: &str| {
                if self.padded {
                    format!("  {s} ")
                } else {
                    s.to_string()
                }
            };
            let mut header: Vec<String> = self.order.iter().map(|&c| name(COLUMNS[c])).collect();
            let mut rows: Vec<Vec<String>> = self
                .rows
                .iter()
                .map(|r| self.order.iter().map(|&c| self.number(r[c])).collect())
                .collect();
            if let Some(note) = &self.note {
                header.push(name("note"));
                for (r, n) in rows.iter_mut().zip(note) {
                    r.push(n.clone());
                }
            }
            (header, rows)
        }
    }

    /// A CSV field: quoted, its quotes doubled, when it holds a comma, a quote or a line
    /// break.
    fn field(s: &str) -> String {
        if s.contains([',', '"', '\n', '\r']) {
            format!("\"{}\"", s.replace('"', "\"\""))
        } else {
            s.to_string()
        }
    }

    /// The CSV text of a header and rows, each line ending in `eol`.
    fn csv_text(header: &[String], rows: &[Vec<String>], eol: &str) -> String {
        std::iter::once(header)
            .chain(rows.iter().map(Vec::as_slice))
            .map(|cells| cells.iter().map(|s| field(s)).collect::<Vec<_>>().join(",") + eol)
            .collect()
    }

    /// Text of up to 8 characters, among them those that break lines, tabs, quotes, commas,
    /// a no-break space and characters beyond ASCII.
    fn text() -> impl Strategy<Value = String> {
        r#"[ -~\t\n\r"\x{a0}é€😀]{0,8}"#
    }

    /// A magnitude from 10^lo to 10^hi, about uniform in its exponent.
    fn magnitude(lo: i32, hi: i32) -> impl Strategy<Value = f64> + Clone {
        (1.0f64..10.0, lo..hi).prop_map(|(m, e)| m * 10f64.powi(e))
    }

    /// Any finite f64, from subnormal to the largest, half the time an ordinary voltage.
    fn wide() -> impl Strategy<Value = f64> + Clone {
        use prop::num::f64::{NEGATIVE, NORMAL, POSITIVE, SUBNORMAL, ZERO};
        prop_oneof![
            POSITIVE | NEGATIVE | NORMAL | SUBNORMAL | ZERO,
            -ORDINARY_V..ORDINARY_V
        ]
    }

    /// The first time after `t` by `dt`, or the next f64 when `dt` is too small to move it.
    fn later(t: f64, dt: f64) -> f64 {
        Some(t + dt).filter(|&s| s > t).unwrap_or(t.next_up())
    }

    /// Rows with t increasing, ordinary (see [`Input`]) or wide: t from ±1e-300 to ±1e300,
    /// intervals from 1e-300 to 1e300 s, values of any finite size.
    fn rows(ordinary: bool) -> BoxedStrategy<(Vec<[f64; 4]>, bool)> {
        let (t0, dt, volts, load) = if ordinary {
            (
                prop_oneof![Just(0.0), -1e3..1e3].boxed(),
                prop_oneof![3 => 1e-6..ORDINARY_DT_S, 1 => magnitude(-300, -6)].boxed(),
                (-ORDINARY_V..ORDINARY_V).boxed(),
                (-ORDINARY_NM..ORDINARY_NM).boxed(),
            )
        } else {
            let signed =
                (magnitude(-300, 300), any::<bool>()).prop_map(|(x, neg)| if neg { -x } else { x });
            (
                prop_oneof![Just(0.0), signed].boxed(),
                // Half of them ordinary, so that large values have time to act.
                prop_oneof![magnitude(-300, 300), 1e-6..ORDINARY_DT_S].boxed(),
                wide().boxed(),
                wide().boxed(),
            )
        };
        (
            t0,
            prop::collection::vec((dt, volts.clone(), volts, load), 1..=MAX_ROWS),
        )
            .prop_map(move |(t0, values)| {
                let mut t = t0;
                let rows = values
                    .iter()
                    .enumerate()
                    .map(|(k, &(dt, u_d, u_q, t_load))| {
                        if k > 0 {
                            t = later(t, dt);
                        }
                        [t, u_d, u_q, t_load]
                    })
                    .collect();
                (rows, ordinary)
            })
            .boxed()
    }

    /// Well-formed inputs, three in four of them ordinary.
    fn input() -> impl Strategy<Value = Input> {
        prop_oneof![3 => rows(true), 1 => rows(false)]
            .prop_flat_map(|(rows, ordinary)| {
                let n = rows.len();
                (
                    Just(rows),
                    Just(ordinary),
                    Just((0..COLUMNS.len()).collect::<Vec<_>>()).prop_shuffle(),
                    prop::option::of(prop::collection::vec(text(), n)),
                    any::<(bool, bool, bool)>(),
                )
            })
            .prop_map(
                |(rows, ordinary, order, note, (padded, exponent, crlf))| Input {
                    rows,
                    ordinary,
                    order,
                    note,
                    padded,
                    exponent,
                    crlf,
                },
            )
    }

    /// One thing wrong with a well-formed input, or nothing. Rows and columns are picked
    /// by index among those the input has.
    #[derive(Debug, Clone)]
    enum Break {
        /// Nothing: the input as generated.
        Nothing,
        /// A row's number written as this text instead: junk, a word f64 parsing takes for
        /// infinity or NaN, a number too large for an f64, or empty.
        Cell(prop::sample::Index, prop::sample::Index, String),
        /// A row's last cell left out.
        Short(prop::sample::Index),
        /// A row with a cell more.
        Long(prop::sample::Index, String),
        /// A row's t the previous row's less this much (0 or more).
        Backwards(prop::sample::Index, f64),
        /// A column's name in the header written as this text instead.
        Header(prop::sample::Index, String),
        /// A byte that is not UTF-8 put anywhere in the file.
        NotUtf8(prop::sample::Index),
        /// No bytes at all.
        Empty,
        /// The header and no rows.
        HeaderOnly,
    }

    /// Mostly nothing, so that most inputs are well-formed; else one break of each kind.
    fn broken() -> impl Strategy<Value = Break> {
        use prop::sample::Index;
        let cell = prop_oneof![
            text(),
            prop::sample::select(vec!["NaN", "inf", "-inf", "infinity", "1e999", ""])
                .prop_map(String::from),
        ];
        prop_oneof![
            12 => Just(Break::Nothing),
            1 => (any::<Index>(), any::<Index>(), cell).prop_map(|(r, c, s)| Break::Cell(r, c, s)),
            1 => any::<Index>().prop_map(Break::Short),
            1 => (any::<Index>(), text()).prop_map(|(r, s)| Break::Long(r, s)),
            1 => (any::<Index>(), prop_oneof![Just(0.0), magnitude(-300, 300)])
                .prop_map(|(r, by)| Break::Backwards(r, by)),
            1 => (any::<Index>(), text()).prop_map(|(c, s)| Break::Header(c, s)),
            1 => any::<Index>().prop_map(Break::NotUtf8),
            1 => Just(Break::Empty),
            1 => Just(Break::HeaderOnly),
        ]
    }

    /// What [`replay_within`] must make of an input.
    #[derive(Debug)]
    enum Want {
        /// Accept it, counting this many rows.
        Rows(usize),
        /// Refuse it, the message holding this.
        Refusal(String),
        /// Refuse it, with any message.
        AnyRefusal,
        /// Refuse a well-formed input of this many rows for the step budget when it needs
        /// more steps than that (the bool), else accept it or refuse it for a model state
        /// that is not finite.
        Model(usize, bool),
        /// Anything: a cell rewritten as another finite number.
        Anything,
    }

    /// The RK4 steps `rows` need at steps of at most [`STEP_S`], counted as
    /// [`replay_within`] does.
    fn steps(rows: &[[f64; 4]]) -> f64 {
        rows.windows(2)
            .map(|w| ((w[1][0] - w[0][0]) / STEP_S).ceil().max(1.0))
            .sum()
    }

    /// The bytes of `input` with `b` done to it, and what the replay must make of them.
    fn case(input: &Input, b: &Break) -> (Vec<u8>, Want) {
        let (mut header, mut rows) = input.cells();
        let eol = if input.crlf { "\r\n" } else { "\n" };
        let n = input.rows.len();
        let well_formed = if input.ordinary {
            Want::Rows(n)
        } else {
            Want::Model(n, steps(&input.rows) > BUDGET as f64)
        };
        // Row r of the input is the file's row r + 2: the header is row 1.
        let want = match b {
            Break::Nothing => well_formed,
            Break::Cell(r, c, s) => {
                let (r, c) = (r.index(n), c.index(COLUMNS.len()));
                rows[r][input.at(c)] = s.clone();
                match s.parse::<f64>() {
                    Err(_) => Want::Refusal(format!("row {}: column {}: ", r + 2, COLUMNS[c])),
                    Ok(x) if !x.is_finite() => {
                        Want::Refusal(format!("row {}: values must be finite numbers", r + 2))
                    }
                    Ok(_) => Want::Anything,
                }
            }
            Break::Short(r) => {
                let r = r.index(n);
                rows[r].pop();
                let len = header.len();
                Want::Refusal(format!(
                    "row {}: {} fields, the first line has {len}",
                    r + 2,
                    len - 1
                ))
            }
            Break::Long(r, s) => {
                let r = r.index(n);
                rows[r].push(s.clone());
                let len = header.len();
                Want::Refusal(format!(
                    "row {}: {} fields, the first line has {len}",
                    r + 2,
                    len + 1
                ))
            }
            Break::Backwards(_, _) if n < 2 => well_formed,
            Break::Backwards(r, by) => {
                let r = 1 + r.index(n - 1);
                let prev = input.rows[r - 1][0];
                let t = Some(prev - by).filter(|t| t.is_finite()).unwrap_or(prev);
                rows[r][input.at(0)] = input.number(t);
                Want::Refusal(format!(
                    "row {}: t = {t} must increase (previous {prev})",
                    r + 2
                ))
            }
            Break::Header(c, s) => {
                let c = c.index(COLUMNS.len());
                header[input.at(c)] = s.clone();
                if s.trim() == COLUMNS[c] {
                    well_formed
                } else {
                    Want::Refusal(format!("no column {} in its first line", COLUMNS[c]))
                }
            }
            Break::NotUtf8(at) => {
                let mut bytes = csv_text(&header, &rows, eol).into_bytes();
                bytes.insert(at.index(bytes.len() + 1), 0xff);
                return (bytes, Want::AnyRefusal);
            }
            Break::Empty => {
                let all = COLUMNS.join(", ");
                return (
                    Vec::new(),
                    Want::Refusal(format!("no column {all} in its first line")),
                );
            }
            Break::HeaderOnly => {
                rows.clear();
                Want::Refusal("has no rows".to_string())
            }
        };
        (csv_text(&header, &rows, eol).into_bytes(), want)
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 256, failure_persistence: None, ..ProptestConfig::default() })]

        /// Well-formed inputs (the four columns in any order, a free-text column, padded
        /// names, CR LF, numbers of every size, intervals from 1e-300 to 1e300 s) and the
        /// same with one thing broken: none panics; every refusal is one non-empty line;
        /// an accepted input returns its number of rows; and each break is refused for
        /// what it broke, naming the row and column.
        #[test]
        fn no_csv_input_panics_and_every_refusal_is_one_line(input in input(), b in broken()) {
            let (bytes, want) = case(&input, &b);
            let got = run(&bytes, STEP_S, BUDGET).map_err(|e| format!("{e:#}"));
            match &got {
                Ok(n) => prop_assert!(*n >= 1),
                Err(e) => prop_assert!(!e.is_empty() && !e.contains(['\n', '\r']), "{e:?}"),
            }
            let budget = format!("RK4 steps, more than {BUDGET}");
            let as_wanted = match (&want, &got) {
                (Want::Rows(k) | Want::Model(k, false), Ok(n)) => n == k,
                (Want::Refusal(s), Err(e)) => e.contains(s.as_str()),
                (Want::AnyRefusal, Err(_)) | (Want::Anything, _) => true,
                (Want::Model(_, false), Err(e)) => e.contains("the model's state is not a finite number"),
                (Want::Model(_, true), Err(e)) => e.contains(&budget),
                _ => false,
            };
            prop_assert!(as_wanted, "wanted {want:?}, got {got:?}");
        }
    }
}
