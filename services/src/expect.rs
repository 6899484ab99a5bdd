//! Expectations: pass/fail checks of a run's summary figures, for CI.
//!
//! An expectation is `FIGURE OP LIMIT`, where FIGURE is a dotted path into `summary.json`
//! (`peak_current_a`, `metrics.rise_time_ms`, `faults.*.speed_recovered_ms`; `*` stands for
//! every key or element at its level) and OP is `<=`, `<`, `>=`, `>`, `==` or `in A..B`
//! (both ends included). Every figure the path names must hold; a path that names no figure,
//! or a figure that is not a number (a recovery that never happened is `null`), fails. A path
//! that goes on below a number or stops at a group is refused when it is read. A `*`
//! over an empty list (`faults.*.…` in a run without faults) holds: there is nothing to check.
//! A histogram's name may hold dots (`latency_us.current-loop.exec.p99`: the last name is the
//! figure). A `*` passes over the notes that say why a figure is null
//! (`metrics.cut_by_fault`, `faults.N.why_null`), which are text, not figures.

use anyhow::Result;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use std::fmt;

/// The figures of one entry of `summary.json → faults` (`faults.*.NAME`): checked when an
/// expectation is read, so that a misspelt one fails also in a run without faults, where
/// `faults.*` has nothing to check and holds.
pub const FAULT_FIGURES: &[&str] = &[
    "fault",
    "service",
    "process",
    "injected_k",
    "injected_t_s",
    "detected_data_path_ms",
    "detected_by",
    "detected_supervisor_ms",
    "safe_state_ms",
    "peak_current_a",
    "republished_ms",
    "speed_recovered_ms",
    "plant_down",
    "window_from_k",
    "window_to_k",
    "rejected_inputs",
    "rejected_by",
    "stale_command_samples",
    "safe_state_samples",
    "missing_command_samples",
    "stale_input_samples",
    "deadline_misses",
    "cycle_latency_max_us",
    "window",
    "why_null",
];

/// The fault figures that hold figures of their own (`faults.*.window.…`); every other one
/// is a number or a name, with nothing below it.
pub const FAULT_GROUPS: &[&str] = &["plant_down", "rejected_by", "window", "why_null"];

/// The groups of notes (why a figure is null, in words), as (parent, key): not figures, so
/// a `*` passes over them and a path into them is refused. A fault report's parent is
/// `faults.N`, written here `faults.#`.
const NOTES: &[(&str, &str)] = &[("metrics", "cut_by_fault"), ("faults.#", "why_null")];

/// True when `key` under the concrete path `parent` is a group of notes ([`NOTES`]).
fn is_notes(parent: &str, key: &str) -> bool {
    let general = match parent.split_once('.') {
        Some(("faults", i)) if i.parse::<usize>().is_ok() || i == "*" => "faults.#",
        _ => parent,
    };
    NOTES.iter().any(|&(p, k)| p == general && k == key)
}

/// The fault figures that are names (of the fault, its stage, its process, what saw it
/// first), not numbers.
pub const FAULT_NAMES: &[&str] = &["fault", "service", "process", "detected_by"];

/// The figures of each latency histogram (`latency_us.HISTOGRAM.FIGURE`).
pub const HISTOGRAM_FIGURES: &[&str] = &["count", "p50", "p99", "p999", "max"];

/// Exit code of `drivelab run` and `drivelab campaign` when an expectation failed.
pub const EXIT_EXPECTATION_FAILED: u8 = 3;

/// Top-level figures of `summary.json` that an expectation may start from.
pub const FIGURES: &[&str] = &[
    "peak_current_a",
    "peak_speed_rad_s",
    "deadline_misses",
    "deadline_misses_per_million",
    "longest_miss_run",
    "samples",
    "samples_expected",
    "samples_missing",
    "metrics",
    "faults",
    "crashes",
    "latency_us",
    "budget",
    "counters",
    "timing",
    "wall_time_s",
    "simulated_s_per_wall_s",
    "loop_simulated_s_per_wall_s",
    "rate_hz",
    "speed_loop_hz",
    "stray_syscalls",
    "plant_down_samples",
    "recorder_late",
    "recorder_rejected",
    "processes",
    "trace",
    "design",
];

/// The top-level figures that a run has only when asked for, each with the option that asks:
/// `stray_syscalls` (a number then, or null when a process was not counted).
pub const ON_REQUEST: &[(&str, &str)] = &[("stray_syscalls", "--audit-syscalls")];

/// The top-level figures that hold figures of their own; every other one is a number.
pub const GROUPS: &[&str] = &[
    "metrics",
    "faults",
    "latency_us",
    "budget",
    "counters",
    "timing",
    "processes",
    "trace",
    "design",
];

/// A command line that is wrong in itself: an option's value that is not of its kind, out
/// of its range or not one of its choices, options that cannot go together, an `--expect`
/// that cannot be read. `drivelab` exits with code 2 for it, as for an option clap refuses.
/// The same mistake in a scenario's or a campaign's file is a plain error (exit code 1), as
/// is a name looked up among files (a scenario, a topology) that is not there.
#[derive(Debug)]
pub struct UsageError(pub String);

/// A [`UsageError`] as an error to return: `drivelab` exits with code 2.
pub fn usage(text: String) -> anyhow::Error {
    UsageError(text).into()
}

impl fmt::Display for UsageError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for UsageError {}

/// An outcome already reported on its own lines (failed expectations, a campaign's
/// failed runs): `drivelab` prints nothing more and exits with this code.
#[derive(Debug)]
pub struct Reported(pub u8);

impl fmt::Display for Reported {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "exit code {}", self.0)
    }
}

impl std::error::Error for Reported {}

/// The one-line violations of a run's failed expectations (`summary.json → expectations`).
pub fn failed(summary: &Value) -> Vec<String> {
    let outcomes: Vec<Outcome> =
        serde_json::from_value(summary["expectations"].clone()).unwrap_or_default();
    outcomes
        .iter()
        .filter(|o| !o.pass)
        .map(Outcome::violation)
        .collect()
}

/// A comparison.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub enum Op {
    /// `<=`
    Le(f64),
    /// `<`
    Lt(f64),
    /// `>=`
    Ge(f64),
    /// `>`
    Gt(f64),
    /// `==`
    Eq(f64),
    /// `in A..B`, both ends included.
    In(f64, f64),
}

impl Op {
    fn holds(self, x: f64) -> bool {
        match self {
            Op::Le(l) => x <= l,
            Op::Lt(l) => x < l,
            Op::Ge(l) => x >= l,
            Op::Gt(l) => x > l,
            Op::Eq(l) => x == l,
            Op::In(a, b) => (a..=b).contains(&x),
        }
    }
}

impl fmt::Display for Op {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Op::Le(l) => write!(f, "<= {l}"),
            Op::Lt(l) => write!(f, "< {l}"),
            Op::Ge(l) => write!(f, ">= {l}"),
            Op::Gt(l) => write!(f, "> {l}"),
            Op::Eq(l) => write!(f, "== {l}"),
            Op::In(a, b) => write!(f, "in {a}..{b}"),
        }
    }
}

/// One parsed expectation.
#[derive(Debug, Clone, PartialEq)]
pub struct Expectation {
    /// As written.
    pub text: String,
    /// The figure's path, one entry per level (`*` for all).
    pub path: Vec<String>,
    /// The comparison.
    pub op: Op,
    /// Why it matters (from the scenario's `[[expect]] note`), may be empty.
    pub note: String,
}

/// The largest limit in magnitude: no figure of a run comes near it (every service rejects
/// values beyond 10^12), so a larger one is a typo.
pub const MAX_LIMIT: f64 = 1e12;

/// The operators, as the errors list them.
const OPERATORS: &str = "<=, <, >=, >, == or in A..B";

fn limit(v: &str, text: &str) -> Result<f64, UsageError> {
    let v = v.trim();
    if v.starts_with(['<', '>', '=', '!']) {
        return Err(bad_operator(text));
    }
    let x: f64 = v
        .parse()
        .map_err(|_| UsageError(format!("expectation '{text}': limit '{v}' is not a number")))?;
    if !(x.is_finite() && x.abs() <= MAX_LIMIT) {
        return Err(UsageError(format!(
            "expectation '{text}': limit '{v}' must be a finite number within ±1e12"
        )));
    }
    Ok(x)
}

fn bad_operator(text: &str) -> UsageError {
    UsageError(format!(
        "expectation '{text}': unknown operator (the operators are {OPERATORS})"
    ))
}

/// Parses `FIGURE OP LIMIT` (see the module documentation).
pub fn parse(text: &str) -> Result<Expectation, UsageError> {
    let form = "expected FIGURE OP LIMIT, e.g. 'peak_current_a <= 8' or 'metrics.rise_time_ms in 7.2..8.8'";
    // A control character (a form feed, an escape) has no place in a one-line check, and
    // would reach the reports.
    if let Some(c) = text.chars().find(|c| c.is_control()) {
        return Err(UsageError(format!(
            "expectation '{}': contains the control character U+{:04X}",
            text.escape_debug(),
            u32::from(c)
        )));
    }
    let t = text.trim();
    // An operator that is not one (`!=`, `=<`, `=>`, `≤`, `≥`, `≠`, `=`) is named as such,
    // not read as a figure path or a limit.
    if t.contains(['≤', '≥', '≠']) || t.contains("!=") || t.contains("=<") || t.contains("=>")
    {
        return Err(bad_operator(t));
    }
    // Two-character operators first, so that `<=` is not read as `<`.
    let ops = ["<=", ">=", "==", "<", ">", " in "];
    let Some((at, op)) = ops
        .iter()
        .filter_map(|op| t.find(op).map(|i| (i, *op)))
        .min_by_key(|&(i, op)| (i, std::cmp::Reverse(op.len())))
    else {
        return Err(if t.contains('=') {
            bad_operator(t)
        } else {
            UsageError(format!("expectation '{t}': {form}"))
        });
    };
    let (figure, rhs) = (t[..at].trim(), &t[at + op.len()..]);
    let op = match op {
        "<=" => Op::Le(limit(rhs, t)?),
        ">=" => Op::Ge(limit(rhs, t)?),
        "==" => Op::Eq(limit(rhs, t)?),
        "<" => Op::Lt(limit(rhs, t)?),
        ">" => Op::Gt(limit(rhs, t)?),
        _ => {
            if rhs.contains("...") {
                return Err(UsageError(format!(
                    "expectation '{t}': a range is A..B with two dots, e.g. in 7.2..8.8"
                )));
            }
            let (a, b) = rhs.split_once("..").ok_or_else(|| {
                UsageError(format!(
                    "expectation '{t}': 'in' needs a range A..B, e.g. in 7.2..8.8"
                ))
            })?;
            let (a, b) = (limit(a, t)?, limit(b, t)?);
            if a > b {
                return Err(UsageError(format!(
                    "expectation '{t}': the range {a}..{b} is empty"
                )));
            }
            Op::In(a, b)
        }
    };
    let mut path: Vec<String> = figure.split('.').map(str::to_string).collect();
    let good = |s: &String| {
        s == "*"
            || (!s.is_empty()
                && s.chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-'))
    };
    if figure.is_empty() || !path.iter().all(good) {
        return Err(UsageError(format!(
            "expectation '{t}': '{figure}' is not a figure path (names of letters, digits, _ and - joined by '.', or '*')"
        )));
    }
    if !FIGURES.contains(&path[0].as_str()) {
        return Err(UsageError(format!(
            "expectation '{t}': unknown figure '{}' (figures: {})",
            path[0],
            FIGURES.join(", ")
        )));
    }
    // A histogram's name holds dots (`current-loop.exec`): everything between `latency_us`
    // and the last name is the histogram, named whole or by a lone `*`.
    if path[0] == "latency_us" && path.len() > 3 {
        // A histogram's figure followed by more names: below a number.
        if let Some(i) =
            (2..path.len() - 1).find(|&i| HISTOGRAM_FIGURES.contains(&path[i].as_str()))
        {
            return Err(UsageError(format!(
                "expectation '{t}': '{}' is a number; no figure lies below it",
                path[..=i].join(".")
            )));
        }
        let name = path[1..path.len() - 1].join(".");
        if name.split('.').any(|p| p == "*") {
            return Err(UsageError(format!(
                "expectation '{t}': a histogram is named whole ('latency_us.current-loop.exec.p99') or by '*' ('latency_us.*.p99'), not by a part of its name"
            )));
        }
        let last = path.pop().unwrap_or_default();
        path = vec![path[0].clone(), name, last];
    }
    if let Some(i) = (1..path.len()).find(|&i| is_notes(&path[..i].join("."), &path[i])) {
        return Err(UsageError(format!(
            "expectation '{t}': '{}' holds notes on why figures are null, not figures",
            path[..=i].join(".")
        )));
    }
    // A path that stops at a group or goes on below a number names no number: refused
    // here, before the drive runs, not found out in its summary.
    let top = path[0].as_str();
    match path.len() {
        1 if GROUPS.contains(&top) => {
            return Err(UsageError(format!(
                "expectation '{t}': '{top}' is a group of figures, not a number; name one below it, e.g. '{top}.*'"
            )));
        }
        2.. if !GROUPS.contains(&top) => {
            return Err(UsageError(format!(
                "expectation '{t}': '{top}' is a number; no figure lies below it"
            )));
        }
        _ => {}
    }
    let refuse = |why: String| Err(UsageError(format!("expectation '{t}': {why}")));
    match path.as_slice() {
        [top, i] if top == "faults" => {
            return refuse(format!(
                "'faults.{i}' is a fault's report, not a number; name one of its figures, e.g. 'faults.{i}.speed_recovered_ms'"
            ));
        }
        [top, _, name, ..] if top == "faults" && FAULT_NAMES.contains(&name.as_str()) => {
            return refuse(format!("the fault figure '{name}' is a name, not a number"));
        }
        [top, name, _, ..] if top == "metrics" && name != "*" => {
            return refuse(format!(
                "'metrics.{name}' is a number; no figure lies below it"
            ));
        }
        [top, h] if top == "latency_us" => {
            return refuse(format!(
                "'latency_us.{h}' is a histogram, not a number; name one of its figures ({}), e.g. 'latency_us.{h}.p99'",
                HISTOGRAM_FIGURES.join(", ")
            ));
        }
        [top, _, f]
            if top == "latency_us" && f != "*" && !HISTOGRAM_FIGURES.contains(&f.as_str()) =>
        {
            return refuse(format!(
                "unknown histogram figure '{f}' (a histogram's figures: {})",
                HISTOGRAM_FIGURES.join(", ")
            ));
        }
        _ => {}
    }
    if let [top, _, name, rest @ ..] = path.as_slice() {
        if top == "faults" && name != "*" {
            if !FAULT_FIGURES.contains(&name.as_str()) {
                return Err(UsageError(format!(
                    "expectation '{t}': unknown fault figure '{name}' (a fault's figures: {})",
                    FAULT_FIGURES.join(", ")
                )));
            }
            let group = FAULT_GROUPS.contains(&name.as_str());
            if group == rest.is_empty() {
                return Err(UsageError(if group {
                    format!("expectation '{t}': the fault figure '{name}' is a group of figures, not a number; name one below it, e.g. 'faults.*.{name}.*'")
                } else {
                    format!("expectation '{t}': the fault figure '{name}' has no figure below it")
                }));
            }
        }
    }
    Ok(Expectation {
        text: t.to_string(),
        path,
        op,
        note: String::new(),
    })
}

/// One figure an expectation checked.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Checked {
    /// Its concrete path, e.g. `faults.3.speed_recovered_ms`.
    pub figure: String,
    /// Its value (None: null or not a number).
    pub value: Option<f64>,
    /// Why the figure is null (a recovery that never came, a window a fault cut), when it
    /// is; absent for a number.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub null: Option<String>,
    /// Whether it holds.
    pub pass: bool,
}

impl Checked {
    /// Its value as a report gives it: the number (`full`: as it reads back, else
    /// rounded for reading), `null (why)`, or `not a number`.
    pub fn value_text(&self, full: bool) -> String {
        match (self.value, &self.null) {
            (Some(v), _) if full => v.to_string(),
            (Some(v), _) => drivelab_runtime::text::readable_numbers(&v.to_string()).into_owned(),
            (None, Some(why)) => format!("null ({why})"),
            (None, None) => "not a number".into(),
        }
    }
}

/// Why figure `figure` (a concrete path, e.g. `faults.0.speed_recovered_ms`) of `summary` is
/// null: the summary's own reason where it gives one (`metrics.cut_by_fault`,
/// `faults.N.why_null`), else what a null means for that figure.
fn null_reason(summary: &Value, figure: &str) -> String {
    let parts: Vec<&str> = figure.split('.').collect();
    match parts.as_slice() {
        ["metrics", key] => summary["metrics"]["cut_by_fault"][*key]
            .as_str()
            .map_or("not measured in this run".into(), str::to_string),
        ["faults", i, key] => {
            let note = i
                .parse::<usize>()
                .ok()
                .and_then(|i| summary["faults"][i]["why_null"][*key].as_str());
            match (note, *key) {
                (Some(why), _) => why,
                (None, "speed_recovered_ms") => "never recovered",
                (None, "republished_ms") => "never published again",
                (None, "detected_data_path_ms") => "no consumer saw a stale input",
                (None, "detected_supervisor_ms") => "the supervisor did not see the process die",
                (None, "safe_state_ms") => "the inverter never reached its safe state",
                _ => "not measured for this fault",
            }
            .into()
        }
        _ => "not measured in this run".into(),
    }
}

/// The outcome of one expectation, as `summary.json → expectations` lists it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Outcome {
    /// As written.
    pub expect: String,
    /// The comparison and limit, e.g. `<= 8`.
    pub limit: String,
    /// Why it matters, may be empty.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub note: String,
    /// Every figure the path named, in order.
    pub values: Vec<Checked>,
    /// All hold, and the path named at least one figure.
    pub pass: bool,
}

impl Outcome {
    /// One line for a failed expectation: the figures that do not hold.
    pub fn violation(&self) -> String {
        let bad: Vec<&Checked> = self.values.iter().filter(|c| !c.pass).collect();
        let shown: Vec<String> = bad
            .iter()
            .take(3)
            .map(|c| match (c.value, &c.null) {
                (None, None) => format!("{} is not a number", c.figure),
                _ => format!("{} = {}", c.figure, c.value_text(false)),
            })
            .collect();
        let more = if bad.len() > 3 {
            format!(" and {} more", bad.len() - 3)
        } else {
            String::new()
        };
        if self.values.is_empty() {
            // The figure the path starts from, and the option that would have made it.
            let figure = self.expect.trim_start();
            let figure = figure
                .split(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
                .next()
                .unwrap_or("");
            let hint = ON_REQUEST
                .iter()
                .find(|(f, _)| *f == figure)
                .map(|(_, flag)| format!(": it is counted with {flag}"))
                .unwrap_or_default();
            format!(
                "expectation failed: {} (the summary has no such figure{hint})",
                self.expect
            )
        } else {
            format!(
                "expectation failed: {}: {}{more}",
                self.expect,
                shown.join(", ")
            )
        }
    }
}

/// What [`walk`] found along a path.
#[derive(Default)]
struct Found<'a> {
    /// The values at the path, with their concrete paths.
    values: Vec<(String, &'a Value)>,
    /// A branch ended at a name that is not there, or below a value that is no group.
    dead_end: bool,
}

/// Collects the values at `path` below `v` with their concrete paths. A `*` goes over every
/// key or element but the notes ([`NOTES`]); a `*` over an empty group ends its branch
/// without a dead end (nothing to check there).
fn walk<'a>(v: &'a Value, path: &[String], at: String, out: &mut Found<'a>) {
    let Some((head, rest)) = path.split_first() else {
        out.values.push((at, v));
        return;
    };
    let join = |k: &str| {
        if at.is_empty() {
            k.to_string()
        } else {
            format!("{at}.{k}")
        }
    };
    match (v, head.as_str()) {
        (Value::Object(m), "*") => {
            for (k, x) in m.iter().filter(|(k, _)| !is_notes(&at, k)) {
                walk(x, rest, join(k), out);
            }
        }
        (Value::Array(a), "*") => {
            for (i, x) in a.iter().enumerate() {
                walk(x, rest, join(&i.to_string()), out);
            }
        }
        (Value::Object(m), k) => match m.get(k) {
            Some(x) => walk(x, rest, join(k), out),
            None => out.dead_end = true,
        },
        (Value::Array(a), k) => match k.parse::<usize>().ok().and_then(|i| a.get(i)) {
            Some(x) => walk(x, rest, join(k), out),
            None => out.dead_end = true,
        },
        _ => out.dead_end = true,
    }
}

impl Expectation {
    /// Checks the expectation against a run's summary.
    pub fn evaluate(&self, summary: &Value) -> Outcome {
        let mut found = Found::default();
        walk(summary, &self.path, String::new(), &mut found);
        let dead_end = found.dead_end;
        let values: Vec<Checked> = found
            .values
            .into_iter()
            .map(|(figure, v)| {
                let value = v.as_f64().filter(|x| x.is_finite());
                Checked {
                    null: v.is_null().then(|| null_reason(summary, &figure)),
                    figure,
                    value,
                    pass: value.is_some_and(|x| self.op.holds(x)),
                }
            })
            .collect();
        // `faults.*.x` over a run without faults holds: there is nothing to check, as for
        // every `*` whose every branch ends at an empty group. A path that names nothing
        // anywhere else (a typo, a figure this run lacks) fails.
        let nothing_to_check = values.is_empty() && !dead_end;
        Outcome {
            expect: self.text.clone(),
            limit: self.op.to_string(),
            note: self.note.clone(),
            pass: nothing_to_check || (!values.is_empty() && values.iter().all(|c| c.pass)),
            values,
        }
    }
}

/// Parses the scenario's `[[expect]]` tables (of file `origin`) and the command line's
/// `--expect` values, in that order. A bad table is an error in the scenario file (exit code
/// 1, as for any other bad key); a bad `--expect` is a [`UsageError`] (exit code 2).
pub fn collect(
    scenario: &[drivelab_runtime::config::ExpectSpec],
    origin: &str,
    cli: &[String],
) -> anyhow::Result<Vec<Expectation>> {
    let mut v = Vec::new();
    for (i, e) in scenario.iter().enumerate() {
        let mut x = parse(&e.check)
            .map_err(|UsageError(m)| anyhow::anyhow!("{origin}: [[expect]] #{}: {m}", i + 1))?;
        x.note = e.note.clone();
        v.push(x);
    }
    for e in cli {
        v.push(parse(e).map_err(|UsageError(m)| UsageError(format!("--expect: {m}")))?);
    }
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn summary() -> Value {
        json!({
            "peak_current_a": 7.5,
            "deadline_misses_per_million": 6000.0,
            "metrics": { "rise_time_ms": 8.1, "overshoot_pct": null },
            "faults": [
                { "speed_recovered_ms": 120.0 },
                { "speed_recovered_ms": 350.0 },
                { "speed_recovered_ms": null },
            ],
            "latency_us": { "cycle": { "p99": 40.0 }, "plant.wake": { "p99": 30.0 } },
        })
    }

    fn check(text: &str) -> Outcome {
        parse(text).unwrap().evaluate(&summary())
    }

    /// Each expectation is refused with an error that contains its text.
    fn assert_refused(cases: &[(&str, &str)]) {
        for (text, says) in cases {
            let err = parse(text).unwrap_err().0;
            assert!(err.contains(says), "{text}: {err}");
        }
    }

    #[test]
    fn a_huge_figure_is_named_in_exponent_form() {
        let o = parse("peak_current_a <= 8")
            .unwrap()
            .evaluate(&json!({ "peak_current_a": 1e308 }));
        assert_eq!(
            o.violation(),
            "expectation failed: peak_current_a <= 8: peak_current_a = 1e308"
        );
    }

    #[test]
    fn each_operator_compares_at_its_limit() {
        assert!(check("peak_current_a <= 7.5").pass);
        assert!(!check("peak_current_a < 7.5").pass);
        assert!(check("peak_current_a >= 7.5").pass);
        assert!(!check("peak_current_a > 7.5").pass);
        assert!(check("peak_current_a == 7.5").pass);
        assert!(!check("peak_current_a == 7.4").pass);
        assert!(check("metrics.rise_time_ms in 7.2..8.8").pass);
        assert!(check("metrics.rise_time_ms in 8.1..8.1").pass);
        assert!(!check("metrics.rise_time_ms in 7.2..8.0").pass);
        assert!(!check("deadline_misses_per_million <= 5000").pass);
        assert_eq!(parse("peak_current_a<=8").unwrap().op, Op::Le(8.0));
        assert_eq!(
            parse(" peak_current_a >= -1e3 ").unwrap().op,
            Op::Ge(-1000.0)
        );
    }

    #[test]
    fn a_wildcard_checks_every_figure_and_names_the_ones_that_fail() {
        let o = check("faults.*.speed_recovered_ms <= 200");
        assert!(!o.pass);
        let figs: Vec<(&str, bool)> = o
            .values
            .iter()
            .map(|c| (c.figure.as_str(), c.pass))
            .collect();
        assert_eq!(
            figs,
            [
                ("faults.0.speed_recovered_ms", true),
                ("faults.1.speed_recovered_ms", false),
                ("faults.2.speed_recovered_ms", false)
            ]
        );
        assert_eq!(
            o.violation(),
            "expectation failed: faults.*.speed_recovered_ms <= 200: faults.1.speed_recovered_ms = 350, faults.2.speed_recovered_ms = null (never recovered)"
        );
        assert!(check("faults.*.speed_recovered_ms <= 400").values[2]
            .value
            .is_none());
        assert!(!check("faults.*.speed_recovered_ms <= 400").pass);
        assert!(check("faults.0.speed_recovered_ms <= 200").pass);
        assert!(check("latency_us.*.p99 <= 40").pass);
        assert!(!check("latency_us.*.p99 < 40").pass);
    }

    #[test]
    fn a_null_figure_is_named_null_with_the_summarys_reason() {
        let s = json!({
            "metrics": {
                "load_recovery_ms": null,
                "overshoot_pct": null,
                "cut_by_fault": { "load_recovery_ms": "cut by the fault at 0.055 s (kill:current-loop@0.055)" },
            },
            "faults": [{ "republished_ms": null }],
            "peak_current_a": "high",
        });
        let v = |t: &str| parse(t).unwrap().evaluate(&s).violation();
        assert_eq!(
            v("metrics.load_recovery_ms <= 5"),
            "expectation failed: metrics.load_recovery_ms <= 5: metrics.load_recovery_ms = null (cut by the fault at 0.055 s (kill:current-loop@0.055))"
        );
        assert_eq!(
            v("metrics.overshoot_pct <= 5"),
            "expectation failed: metrics.overshoot_pct <= 5: metrics.overshoot_pct = null (not measured in this run)"
        );
        assert_eq!(
            v("faults.*.republished_ms <= 5"),
            "expectation failed: faults.*.republished_ms <= 5: faults.0.republished_ms = null (never published again)"
        );
        // A value that is neither a number nor null is still named so.
        assert_eq!(
            v("peak_current_a <= 5"),
            "expectation failed: peak_current_a <= 5: peak_current_a is not a number"
        );
        // The reason reads back from summary.json → expectations.
        let o = parse("metrics.load_recovery_ms <= 5").unwrap().evaluate(&s);
        let back: Outcome = serde_json::from_value(serde_json::to_value(&o).unwrap()).unwrap();
        assert_eq!(back.violation(), o.violation());
    }

    /// The notes on why figures are null are passed over by a `*` and refused as a figure;
    /// a fault report's own note is the reason its null is named with.
    #[test]
    fn notes_are_not_figures_and_name_a_faults_null() {
        let s = json!({
            "metrics": {
                "rise_time_ms": 8.1,
                "load_recovery_ms": 19.6,
                "cut_by_fault": { "id_tracking_error_a": "measured up to the fault at 0.030 s" },
            },
            "faults": [{
                "speed_recovered_ms": null,
                "why_null": { "speed_recovered_ms": "the run ended 9 ms after the speed came back" },
            }],
        });
        let e = |t: &str| parse(t).unwrap().evaluate(&s);
        let o = e("metrics.* <= 1000");
        assert!(o.pass, "{}", o.violation());
        assert_eq!(o.values.len(), 2);
        assert_eq!(
            e("faults.*.* <= 1000").violation(),
            "expectation failed: faults.*.* <= 1000: faults.0.speed_recovered_ms = null (the run ended 9 ms after the speed came back)"
        );
        assert_refused(&[
            (
                "metrics.cut_by_fault.x <= 1",
                "'metrics.cut_by_fault' holds notes on why figures are null, not figures",
            ),
            (
                "faults.*.why_null.speed_recovered_ms <= 1",
                "'faults.*.why_null' holds notes",
            ),
            (
                "faults.0.why_null.* <= 1",
                "'faults.0.why_null' holds notes",
            ),
        ]);
    }

    /// A histogram's name holds dots: it is everything between `latency_us` and the figure,
    /// so a figure a `*` found can be named on its own.
    #[test]
    fn a_histogram_is_named_whole_with_its_dots() {
        let o = check("latency_us.plant.wake.p99 <= 30");
        assert!(o.pass, "{}", o.violation());
        assert_eq!(o.values[0].figure, "latency_us.plant.wake.p99");
        assert!(!check("latency_us.plant.wake.p99 < 30").pass);
        for c in check("latency_us.*.p99 <= 40").values {
            let again = check(&format!("{} <= 40", c.figure));
            assert!(again.pass && again.values.len() == 1, "{}", c.figure);
        }
        assert_refused(&[
            (
                "latency_us.plant.wake <= 1",
                "unknown histogram figure 'wake'",
            ),
            ("latency_us.*.wake.p99 <= 1", "a histogram is named whole"),
            (
                "latency_us.plant.wake.p98 <= 1",
                "unknown histogram figure 'p98'",
            ),
        ]);
    }

    /// Every `*` over an empty group holds, wherever it is in the path; a name that is not
    /// there still fails.
    #[test]
    fn an_empty_group_under_any_star_holds() {
        let s = json!({ "faults": [{ "rejected_by": {} }, { "rejected_by": {} }] });
        let e = |t: &str| parse(t).unwrap().evaluate(&s);
        assert!(e("faults.0.rejected_by.* == 0").pass);
        assert!(e("faults.*.rejected_by.* == 0").pass);
        let lacking = json!({ "faults": [{ "rejected_by": {} }, {}] });
        assert!(
            !parse("faults.*.rejected_by.* == 0")
                .unwrap()
                .evaluate(&lacking)
                .pass
        );
    }

    #[test]
    fn a_figure_the_summary_lacks_or_a_null_fails() {
        let o = check("metrics.settling_ms <= 5");
        assert!(!o.pass && o.values.is_empty());
        assert!(
            o.violation().contains("no such figure"),
            "{}",
            o.violation()
        );
        assert!(!check("metrics.overshoot_pct <= 5").pass);
        // No fault injected: nothing to check, so it holds; but a key after the `*` that no
        // fault has (a typo) fails.
        let e = parse("faults.*.speed_recovered_ms <= 200").unwrap();
        assert!(e.evaluate(&json!({ "faults": [] })).pass);
        assert!(
            !e.evaluate(&json!({ "faults": [{ "speed_recoverd_ms": 1.0 }] }))
                .pass
        );
        assert!(!e.evaluate(&json!({})).pass);
    }

    #[test]
    fn malformed_expectations_are_one_line_errors() {
        for (text, says) in [
            ("peak_current_a", "expected FIGURE OP LIMIT"),
            ("peak_current_a <= eight", "limit 'eight' is not a number"),
            ("peak_current_a <= NaN", "must be a finite number"),
            ("peak_current_a <= inf", "must be a finite number"),
            ("peak_curent_a <= 8", "unknown figure 'peak_curent_a'"),
            (
                "faults.*.speed_recoverd_ms <= 200",
                "unknown fault figure 'speed_recoverd_ms' (a fault's figures: fault, service,",
            ),
            (
                "faults.0.peak_current <= 8",
                "unknown fault figure 'peak_current'",
            ),
            ("metrics..rise <= 8", "is not a figure path"),
            ("<= 8", "is not a figure path"),
            ("metrics.rise_time_ms in 8", "needs a range A..B"),
            ("metrics.rise_time_ms in 9..8", "is empty"),
            ("peak_current_a in 1...2", "a range is A..B with two dots"),
            (
                "peak_current_a =< 8",
                "unknown operator (the operators are <=, <, >=, >, ==",
            ),
            ("peak_current_a => 8", "unknown operator"),
            ("peak_current_a != 8", "unknown operator"),
            ("peak_current_a = 8", "unknown operator"),
            ("peak_current_a <== 8", "unknown operator"),
            ("peak_current_a < = 8", "unknown operator"),
            ("peak_current_a ≤ 8", "unknown operator"),
            (
                "peak_current_a <= 1e13",
                "must be a finite number within ±1e12",
            ),
            (
                "peak_current_a >= -1e300",
                "must be a finite number within ±1e12",
            ),
            (
                "metrics.rise_time_ms in 1..nan",
                "limit 'nan' must be a finite number",
            ),
            (
                "peak_current_a.x <= 1",
                "'peak_current_a' is a number; no figure lies below it",
            ),
            ("samples.* <= 1", "'samples' is a number"),
            (
                "metrics <= 1",
                "'metrics' is a group of figures, not a number; name one below it, e.g. 'metrics.*'",
            ),
            ("faults == 0", "'faults' is a group of figures"),
            (
                "peak_current_a\x0c<=\x0c0.1",
                "expectation 'peak_current_a\\u{c}<=\\u{c}0.1': contains the control character U+000C",
            ),
            ("peak_current_a <= 8\n", "contains the control character U+000A"),
            (
                "faults.*.peak_current_a.max <= 8",
                "the fault figure 'peak_current_a' has no figure below it",
            ),
            (
                "faults.0.window <= 8",
                "the fault figure 'window' is a group of figures",
            ),
            (
                "faults.* <= 1",
                "'faults.*' is a fault's report, not a number; name one of its figures",
            ),
            (
                "faults.*.service == 1",
                "the fault figure 'service' is a name, not a number",
            ),
            (
                "faults.0.detected_by >= 0",
                "the fault figure 'detected_by' is a name",
            ),
            (
                "metrics.rise_time_ms.x <= 50",
                "'metrics.rise_time_ms' is a number; no figure lies below it",
            ),
            (
                "latency_us.cycle <= 50",
                "'latency_us.cycle' is a histogram, not a number; name one of its figures (count, p50, p99, p999, max), e.g. 'latency_us.cycle.p99'",
            ),
            (
                "latency_us.cycle.p95 <= 50",
                "unknown histogram figure 'p95'",
            ),
            (
                "latency_us.cycle.p99.x <= 50",
                "'latency_us.cycle.p99' is a number",
            ),
        ] {
            let e = parse(text).unwrap_err().to_string();
            assert!(e.contains(says), "{text}: {e}");
            assert!(!e.contains('\n'), "{e}");
        }
        assert_eq!(parse("samples <= 1e12").unwrap().op, Op::Le(1e12));
        // A fault's figure further down, or any under a `*`, is not checked by name.
        for text in [
            "faults.*.window.cycle_p99_us.during <= 50",
            "faults.*.* <= 1",
            "faults.*.rejected_by.observer >= 1",
            "latency_us.*.p99 <= 100",
            "latency_us.cycle.* <= 1e6",
            "metrics.* <= 1000",
        ] {
            parse(text).unwrap_or_else(|e| panic!("{text}: {e}"));
        }
    }

    #[test]
    fn the_fault_figures_are_the_keys_of_a_fault_report() {
        use crate::launcher::{FaultReport, PlantDown};
        // Every optional part present: the most keys a report can have.
        let r = FaultReport {
            plant_down: Some(PlantDown::default()),
            samples: Default::default(),
            bus: Some(crate::bus_faults::BusFigures::default()),
            window: Some(crate::faults::window::FaultWindow::default()),
            why_null: [("speed_recovered_ms", "a note".to_string())].into(),
            ..FaultReport::default()
        };
        let v = serde_json::to_value(&r).unwrap();
        let keys: std::collections::BTreeSet<&str> =
            v.as_object().unwrap().keys().map(String::as_str).collect();
        assert_eq!(keys, FAULT_FIGURES.iter().copied().collect());
        // The groups are the keys that hold objects; the rest are numbers, names or null.
        for (k, x) in v.as_object().unwrap() {
            assert_eq!(
                x.is_object(),
                FAULT_GROUPS.contains(&k.as_str()),
                "{k}: {x}"
            );
        }
    }

    #[test]
    fn a_scenarios_bad_expectation_names_its_file_and_table() {
        let spec = |c: &str| drivelab_runtime::config::ExpectSpec {
            check: c.into(),
            note: String::new(),
        };
        let e = collect(
            &[spec("peak_current_a <= 8"), spec("peak_current_a =< 8")],
            "s.toml",
            &[],
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.starts_with(
                "s.toml: [[expect]] #2: expectation 'peak_current_a =< 8': unknown operator"
            ),
            "{e}"
        );
        let e = collect(&[], "s.toml", &["bogus <= 1".into()])
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("--expect: expectation 'bogus <= 1': unknown figure"),
            "{e}"
        );
    }
}
