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
    let ms = match toml::from_str::<Wrapped>(&text) {
        Ok(w) => w.motor,
        Err(_) => {
            toml::from_str::<MotorSpec>(&text).map_err(|e| anyhow!("{spec}: {}", e.message()))?
        }
    };
    ms.resolve().map_err(|e| anyhow!("{spec}: {e}"))
}

/// Integrates the model through the input rows; each row's inputs are held from its t on.
/// Output rows are the state at each input row's time, before that row's input acts.
pub fn replay(input: &Path, output: &Path, m: &MotorParams, max_step_s: f64) -> Result<usize> {
    let mut rd = csv::Reader::from_path(input)
        .with_context(|| format!("cannot read {}", input.display()))?;
    let mut rows = Vec::new();
    for (i, r) in rd.deserialize::<InRow>().enumerate() {
        let r = r.map_err(|e| {
            anyhow!(
                "{} row {}: {e} (need columns t,u_d,u_q,t_load)",
                input.display(),
                i + 2
            )
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
    let mut w = csv::Writer::from_path(output)
        .with_context(|| format!("cannot write {}", output.display()))?;
    let mut x = MotorState::default();
    for i in 0..rows.len() {
        let r = &rows[i];
        w.serialize(OutRow {
            t: r.t,
            u_d: r.u_d,
            u_q: r.u_q,
            t_load: r.t_load,
            i_d: x.i_d,
            i_q: x.i_q,
            omega_m: x.omega_m,
            theta_e: x.theta_e(m),
        })?;
        if let Some(next) = rows.get(i + 1) {
            let dt = next.t - r.t;
            let substeps = (dt / max_step_s).ceil().max(1.0) as u32;
            let u = MotorInput {
                u_d: r.u_d,
                u_q: r.u_q,
                t_load: r.t_load,
            };
            x = Rk4 { substeps }.advance(m, Mechanics::Inertia, &x, &u, dt);
        }
    }
    w.flush()?;
    Ok(rows.len())
}
