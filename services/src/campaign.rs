//! `drivelab campaign`: a matrix of runs (scenarios × fault sets × seeds), each checked
//! against the campaign's expectations, reported as `campaign.json`, `campaign.md` and
//! `junit.xml` (the test-report format CI systems read).

use crate::expect::{Outcome, UsageError, EXIT_EXPECTATION_FAILED};
use crate::launcher::{self, Clock, Restart, RunOptions};
use anyhow::{anyhow, bail, Context, Result};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Most runs one campaign may hold.
const MAX_RUNS: usize = 10_000;

/// Options of `drivelab campaign`.
#[derive(Debug, clap::Args)]
pub struct CampaignArgs {
    /// Campaign file (TOML): scenarios, fault sets, seeds, expectations.
    #[arg(value_name = "FILE.toml")]
    pub file: PathBuf,
    /// Report folder (default: runs/campaign-<name>-<unix time>); each run's folder goes
    /// into its runs/ subfolder.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Draw each run's plots (slower; off by default).
    #[arg(long)]
    pub plots: bool,
    /// Do not pin, raise priority or lock memory in the runs: for a machine without the
    /// privilege. Real-time runs then compete with every other task and can miss most of
    /// their deadlines, so expectations on currents or misses may fail; lockstep runs are
    /// unaffected.
    #[arg(long)]
    pub no_rt: bool,
    /// Print the campaign report as JSON on stdout instead of the table.
    #[arg(long)]
    pub json: bool,
}

/// A campaign file.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct CampaignFile {
    /// Short name, used in the report and as the JUnit suite's name.
    name: String,
    /// One-line purpose.
    #[serde(default)]
    purpose: String,
    /// Scenario names or files (relative to the campaign file).
    scenarios: Vec<String>,
    /// Pacing of every run.
    #[serde(default = "realtime")]
    clock: Clock,
    /// Override of every scenario's duration, s.
    duration_s: Option<f64>,
    /// Topology override for every run (a shipped name or a file relative to the campaign
    /// file).
    topology: Option<String>,
    /// Fault seeds; every run is repeated once per seed.
    #[serde(default = "one_seed")]
    seeds: Vec<u64>,
    /// What the supervisor does when a process dies.
    #[serde(default)]
    restart: Restart,
    /// Fault sets: each is a list of `--fault` specs; `[]` is a run without faults.
    #[serde(default)]
    faults: Vec<Vec<String>>,
    /// More fault sets, one per kind × stage × time.
    sweep: Option<Sweep>,
    /// Expectations checked in every run (beside the scenario's own `[[expect]]`).
    #[serde(default)]
    expect: Vec<String>,
    /// Every run counts its loops' system calls beyond their waits (`drivelab run
    /// --audit-syscalls`), for an expectation on `stray_syscalls`.
    #[serde(default)]
    audit_syscalls: bool,
}

fn realtime() -> Clock {
    Clock::Realtime
}

fn one_seed() -> Vec<u64> {
    vec![1]
}

/// `[sweep]`: one fault per kind × stage × injection time.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Sweep {
    /// `kill` and/or `stop`.
    kinds: Vec<String>,
    /// Target stages.
    stages: Vec<String>,
    /// Injection times, s.
    at_s: Vec<f64>,
    /// How long a `stop` lasts, s.
    #[serde(default = "stop_default")]
    stop_duration_s: f64,
}

fn stop_default() -> f64 {
    0.05
}

/// One run of the matrix.
#[derive(Debug, Clone, Serialize)]
pub struct Case {
    /// 1-based number.
    pub number: usize,
    /// Scenario name or file (a file's path resolved from the campaign file's folder).
    pub scenario: String,
    /// The scenario as the campaign file names it: the name in the reports, the same
    /// wherever the campaign is started from.
    #[serde(skip)]
    pub label: String,
    /// Its faults (`--fault` specs).
    pub faults: Vec<String>,
    /// Fault seed.
    pub seed: u64,
}

impl Case {
    /// `scenario [faults] seed N`, the JUnit test case's name.
    pub fn title(&self) -> String {
        format!(
            "{} [{}] seed {}",
            self.label,
            if self.faults.is_empty() {
                "no fault".to_string()
            } else {
                self.faults.join(" + ")
            },
            self.seed
        )
    }
}

/// What one run gave.
#[derive(Debug, Clone, Serialize)]
pub struct CaseResult {
    /// The run.
    #[serde(flatten)]
    pub case: Case,
    /// `pass`, `fail` (an expectation failed), `error` (the run did not complete) or
    /// `skipped` (the campaign was interrupted first).
    pub status: &'static str,
    /// The run folder.
    pub out: PathBuf,
    /// Why the run did not complete.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// The expectations' outcomes.
    pub expectations: Vec<Outcome>,
    /// Headline figures of the run (see [`FIGURES`]).
    pub figures: serde_json::Map<String, Value>,
    /// Wall time of the run, s.
    pub wall_s: f64,
}

/// The figures each run reports (JUnit properties, table columns): name and the summary
/// path, where `*` means the worst (largest) over all faults.
pub const FIGURES: &[(&str, &str)] = &[
    ("peak_current_a", "peak_current_a"),
    ("peak_speed_rad_s", "peak_speed_rad_s"),
    ("deadline_misses_per_million", "deadline_misses_per_million"),
    ("samples_missing", "samples_missing"),
    ("rise_time_ms", "metrics.rise_time_ms"),
    ("worst_republished_ms", "faults.*.republished_ms"),
    ("worst_speed_recovered_ms", "faults.*.speed_recovered_ms"),
    (
        "worst_detected_data_path_ms",
        "faults.*.detected_data_path_ms",
    ),
];

fn figures(summary: &Value) -> serde_json::Map<String, Value> {
    let mut m = serde_json::Map::new();
    for (name, path) in FIGURES {
        // The summary's own number, so that a count stays a whole number (`0`, not `0.0`).
        let v: Option<&Value> = match path.split_once(".*.") {
            Some((list, key)) => summary[list].as_array().and_then(|a| {
                let v: Option<Vec<&Value>> =
                    a.iter().map(|f| f[key].as_f64().map(|_| &f[key])).collect();
                v.and_then(|v| {
                    v.into_iter().max_by(|a, b| {
                        a.as_f64()
                            .unwrap_or(f64::MIN)
                            .total_cmp(&b.as_f64().unwrap_or(f64::MIN))
                    })
                })
            }),
            None => Some(path.split('.').fold(summary, |v, k| &v[k])).filter(|v| v.is_number()),
        };
        // A fault that never recovered has no figure: say so rather than leave it out.
        let never = path.contains(".*.")
            && summary[path.split_once(".*.").map_or("", |p| p.0)]
                .as_array()
                .is_some_and(|a| !a.is_empty());
        m.insert(
            name.to_string(),
            match v {
                Some(x) => x.clone(),
                None if never => json!("never"),
                None => Value::Null,
            },
        );
    }
    m
}

/// A campaign file read, its matrix expanded and every run checked ([`load`]).
struct Loaded {
    c: CampaignFile,
    cases: Vec<Case>,
    /// The runs that differ from one of `cases` only by a seed that nothing uses (simulated
    /// clocks, no `random:N`), which are not in `cases`.
    repeats: usize,
    /// The configuration warnings the runs give, each once, with the first run it applies to.
    warnings: Vec<(String, usize)>,
}

/// Reads the campaign file, expands its matrix and checks its runs.
fn load(file: &Path) -> Result<Loaded> {
    let text =
        drivelab_runtime::config::read_config_file(file, "campaign").map_err(|e| anyhow!(e))?;
    let mut c: CampaignFile = toml::from_str(&text).map_err(|e| {
        anyhow!(
            "campaign {}",
            drivelab_runtime::config::toml_error(&text, &file.display().to_string(), &e)
        )
    })?;
    let bad = |m: String| anyhow!("campaign {}: {m}", file.display());
    if !drivelab_runtime::config::name_ok(&c.name) {
        return Err(bad(format!(
            "name = {:?} must be 1..=64 characters of a-z, A-Z, 0-9, -, _ or . (it names the report folder), not starting with .",
            c.name
        )));
    }
    if c.scenarios.is_empty() {
        return Err(bad("scenarios = [] names no scenario to run".into()));
    }
    if c.seeds.is_empty() {
        return Err(bad(
            "seeds = [] gives no seed: every run needs one (leave seeds out for [1])".into(),
        ));
    }
    // The size of the matrix is known from the lengths of its lists alone: a file that
    // asks for too many runs is refused before anything whose time grows with the runs
    // (building the fault sets, looking for repeats, checking each run).
    let sweep_sets = c.sweep.as_ref().map_or(0, |s| {
        s.kinds
            .len()
            .saturating_mul(s.stages.len())
            .saturating_mul(s.at_s.len())
    });
    let n = c
        .scenarios
        .len()
        .saturating_mul(c.faults.len().saturating_add(sweep_sets).max(1))
        .saturating_mul(c.seeds.len());
    if n > MAX_RUNS {
        bail!(
            "campaign {}: {n} runs is more than {MAX_RUNS}; split it",
            file.display()
        );
    }
    // The same run twice is a copy-and-paste slip, not a repetition (seeds move random
    // kills; give another seed to repeat a run).
    if let Some(d) = duplicate(&c.scenarios) {
        return Err(bad(format!("scenarios: '{d}' is listed twice")));
    }
    if let Some(d) = duplicate(&c.seeds) {
        return Err(bad(format!("seeds: {d} is listed twice")));
    }
    if let Some(d) = duplicate(&c.expect) {
        return Err(bad(format!("expect: '{d}' is listed twice")));
    }
    let mut sets = c.faults.clone();
    if let Some(s) = &c.sweep {
        for (field, empty) in [
            ("kinds", s.kinds.is_empty()),
            ("stages", s.stages.is_empty()),
            ("at_s", s.at_s.is_empty()),
        ] {
            if empty {
                return Err(bad(format!(
                    "[sweep] {field} = [] makes no fault set (give at least one, or leave [sweep] out)"
                )));
            }
        }
        if !(s.stop_duration_s.is_finite() && s.stop_duration_s > 0.0) {
            bail!(
                "campaign {}: [sweep] stop_duration_s must be a positive number of seconds",
                file.display()
            );
        }
        for kind in &s.kinds {
            for stage in &s.stages {
                for at in &s.at_s {
                    sets.push(vec![match kind.as_str() {
                        "kill" => format!("kill:{stage}@{at}"),
                        "stop" => format!("stop:{stage}@{at}:{}", s.stop_duration_s),
                        other => bail!(
                            "campaign {}: [sweep] kind '{other}' is not kill or stop",
                            file.display()
                        ),
                    }]);
                }
            }
        }
    }
    if sets.is_empty() {
        sets.push(Vec::new());
    }
    // Every spec and expectation is checked before the first run starts.
    let mut parsed = Vec::with_capacity(sets.len());
    for set in &sets {
        let specs = set
            .iter()
            .map(|spec| {
                crate::faults::parse(spec).map_err(|e| anyhow!("campaign {}: {e}", file.display()))
            })
            .collect::<Result<Vec<_>>>()?;
        parsed.push(specs);
    }
    // Two sets are the same run when their faults are, however they are written
    // (`kill:plant@0.05` and `kill:plant@0.050s`).
    let keys: Vec<Vec<String>> = parsed.iter().map(|p| fault_set_key(p)).collect();
    if let Some(d) = duplicate(&keys) {
        let mut same = keys
            .iter()
            .zip(&sets)
            .filter(|(k, _)| **k == d)
            .map(|(_, s)| s);
        let (first, second) = (same.next(), same.next());
        let show = |s: Option<&Vec<String>>| s.map_or(String::new(), |s| s.join(", "));
        return Err(bad(if first == second {
            format!(
                "faults: the fault set [{}] is listed twice (in faults or made again by [sweep])",
                show(first)
            )
        } else {
            format!(
                "faults: the fault sets [{}] and [{}] are the same faults written two ways (in faults or made again by [sweep]); give one",
                show(first),
                show(second)
            )
        }));
    }
    // A malformed expectation here is an error in a file, exit code 1 like every other one
    // of the campaign: the message of expect::UsageError (exit code 2, for `run --expect`)
    // is kept, not its type.
    for e in &c.expect {
        crate::expect::parse(e)
            .map_err(|UsageError(m)| anyhow!("campaign {}: expect: {m}", file.display()))?;
    }
    // A file is taken relative to the campaign file (a name is a shipped one), so that a
    // campaign runs the same from any working folder.
    let base = file.parent().unwrap_or(Path::new("."));
    let beside = |s: &String| {
        if drivelab_runtime::config::names_a_file(s) {
            base.join(s).display().to_string()
        } else {
            s.clone()
        }
    };
    c.topology = c.topology.as_ref().map(beside);
    let mut scenarios = Vec::new();
    // The same file named two ways (`kyslan-pi` and `scenarios/kyslan-pi.toml`) is the same
    // scenario listed twice.
    let mut files: Vec<(PathBuf, String)> = Vec::new();
    for s in &c.scenarios {
        let (written, s) = (s.clone(), beside(s));
        let (mut sc, path) = drivelab_runtime::config::Scenario::load(&s)
            .map_err(|e| anyhow!("campaign {}: {e}", file.display()))?;
        let path = path.canonicalize().unwrap_or(path);
        if let Some((_, first)) = files.iter().find(|(p, _)| *p == path) {
            return Err(bad(format!(
                "scenarios: '{first}' and '{written}' are the same file ({}), listed twice",
                path.display()
            )));
        }
        files.push((path, written.clone()));
        if let Some(d) = c.duration_s {
            launcher::set_duration(&mut sc, d).map_err(|e| {
                anyhow!("campaign {}: duration_s = {d} for {s}: {e}", file.display())
            })?;
        }
        crate::expect::collect(&sc.expect, &s, &[])
            .map_err(|e| anyhow!("campaign {}: {e}", file.display()))?;
        scenarios.push((written, s));
    }
    // A seed moves only the kills of `random:N`. In real time a run is repeated once per
    // seed whatever its faults (each repetition meets the machine anew); a lockstep or
    // in-process run without random kills gives the same trace for every seed, so it runs
    // once, with the first seed.
    let simulated = c.clock != Clock::Realtime;
    let mut cases = Vec::with_capacity(n);
    let mut repeats = 0;
    let mut checks = Vec::with_capacity(scenarios.len() * sets.len());
    for (label, sc) in &scenarios {
        for (set, specs) in sets.iter().zip(&parsed) {
            let seeded = specs
                .iter()
                .any(|s| matches!(s, crate::faults::FaultSpec::Random(_)));
            let seeds = if simulated && !seeded {
                repeats += c.seeds.len() - 1;
                &c.seeds[..1]
            } else {
                &c.seeds[..]
            };
            checks.push(cases.len());
            for &seed in seeds {
                cases.push(Case {
                    number: cases.len() + 1,
                    scenario: sc.clone(),
                    label: label.clone(),
                    faults: set.clone(),
                    seed,
                });
            }
        }
    }
    // Each scenario × fault set is checked as its run would be (faults against the
    // scenario's stages and duration, topology, expectations); seeds only move random kills.
    // Ten thousand checks take about 0.6 s (no stage is built for them: see
    // `stages::declaration`); a stop signal still ends them.
    let total = cases.len();
    let mut warnings: Vec<(String, usize)> = Vec::new();
    for case in checks.iter().map(|&i| &cases[i]) {
        if drivelab_runtime::service::stop_requested() {
            bail!(
                "campaign {}: interrupted ({}) while checking run {} of {total}, before any run started",
                file.display(),
                drivelab_runtime::service::stop_signal_name(),
                case.number
            );
        }
        let said = launcher::check(&options(&c, case, true, false, None)?).map_err(|e| {
            anyhow!(
                "campaign {}: {}: {}",
                file.display(),
                case.title(),
                drivelab_runtime::text::error_text(&e)
            )
        })?;
        for w in said {
            if !warnings.iter().any(|(v, _)| *v == w) {
                warnings.push((w, case.number));
            }
        }
    }
    Ok(Loaded {
        c,
        cases,
        repeats,
        warnings,
    })
}

/// A fault set as the run sees it, whatever its spelling: each spec parsed (numbers in
/// their shortest form), in a fixed order unless two `random:N` share the set (they draw
/// from one generator in turn, so their order moves the kills).
fn fault_set_key(specs: &[crate::faults::FaultSpec]) -> Vec<String> {
    let mut key: Vec<String> = specs.iter().map(|s| format!("{s:?}")).collect();
    let randoms = specs
        .iter()
        .filter(|s| matches!(s, crate::faults::FaultSpec::Random(_)))
        .count();
    if randoms < 2 {
        key.sort();
    }
    key
}

/// The first value `items` holds twice, if any (the first one whose earlier copy exists).
/// One pass with a set of the values seen: a sweep can make thousands of fault sets, and
/// comparing every pair of them would take minutes.
fn duplicate<T: Eq + std::hash::Hash + Clone>(items: &[T]) -> Option<T> {
    let mut seen = std::collections::HashSet::with_capacity(items.len());
    items.iter().find(|x| !seen.insert(*x)).cloned()
}

/// The drive options of one case: its folder `dir` and bus (None: a check only, see
/// [`launcher::check`]).
fn options(
    c: &CampaignFile,
    case: &Case,
    no_rt: bool,
    plots: bool,
    dir: Option<PathBuf>,
) -> Result<RunOptions> {
    let faults = case
        .faults
        .iter()
        .map(|f| crate::faults::parse(f))
        .collect::<Result<Vec<_>>>()?;
    Ok(RunOptions {
        scenario: case.scenario.clone(),
        clock: c.clock,
        duration_s: c.duration_s,
        // Unique per campaign process and run, so that campaigns can run side by side.
        bus: dir
            .as_ref()
            .map(|_| format!("{}{}", bus_prefix(std::process::id()), case.number)),
        out: dir,
        rt_strict: false,
        no_rt,
        no_plots: !plots,
        verbose: false,
        faults,
        restart: c.restart,
        fault_seed: case.seed,
        lockstep_restart_ms: drivelab_runtime::inject::RESTART_DEFAULT_MS,
        topology: c.topology.clone(),
        expect: c.expect.clone(),
        runner: None,
        zenoh: None,
        foxglove: None,
        timing_csv: false,
        audit_syscalls: c.audit_syscalls,
        quiet_hosts: true,
        quiet_warnings: true,
    })
}

/// The real-time set-up refusals of the processes of a run's summary `s`
/// (`summary.json → processes → rt_warnings`) in one line, or None.
fn rt_refusals(s: &Value) -> Option<String> {
    let all: Vec<String> = s["processes"]
        .as_object()?
        .iter()
        .flat_map(|(p, v)| {
            v["rt_warnings"]
                .as_array()
                .into_iter()
                .flatten()
                .filter_map(|w| w.as_str())
                .map(move |w| format!("{p}: {w}"))
        })
        .collect();
    let first = all.first()?;
    Some(match all.len() {
        1 => first.clone(),
        n => format!("{first} (and {} more; see summary.json → processes)", n - 1),
    })
}

/// The summary in run folder `out`, if one was written at or after `since` (by this run: a
/// folder the run refused may hold another's).
fn run_summary(out: &Path, since: std::time::SystemTime) -> Option<Value> {
    let path = out.join("summary.json");
    if std::fs::metadata(&path).and_then(|m| m.modified()).ok()? < since {
        return None;
    }
    serde_json::from_slice(&std::fs::read(path).ok()?).ok()
}

/// Runs one case, started at `since`.
fn run_case(
    c: &CampaignFile,
    case: &Case,
    a: &CampaignArgs,
    out: &Path,
    since: std::time::SystemTime,
) -> CaseResult {
    let dir = out.join("runs").join(format!("{:03}", case.number));
    let started = Instant::now();
    let result = (|| -> Result<Value> {
        let o = options(c, case, a.no_rt, a.plots, Some(dir.clone()))?;
        Ok(launcher::run(&o)?.summary)
    })();
    let wall_s = started.elapsed().as_secs_f64();
    match result {
        Ok(summary) => {
            let expectations: Vec<Outcome> =
                serde_json::from_value(summary["expectations"].clone()).unwrap_or_default();
            CaseResult {
                case: case.clone(),
                status: if expectations.iter().all(|e| e.pass) {
                    "pass"
                } else {
                    "fail"
                },
                out: dir,
                error: None,
                figures: figures(&summary),
                expectations,
                wall_s,
            }
        }
        Err(e) => CaseResult {
            case: case.clone(),
            status: "error",
            // A run that failed after its drive ended (a planned fault not made, a file it
            // could not write) has written its summary: its figures are known.
            figures: run_summary(&dir, since)
                .map(|s| figures(&s))
                .unwrap_or_default(),
            out: dir,
            error: Some(drivelab_runtime::text::error_text(&e)),
            expectations: Vec::new(),
            wall_s,
        },
    }
}

fn cell(v: Option<&Value>) -> String {
    match v {
        Some(Value::Number(n)) => {
            let x = n.as_f64().unwrap_or(0.0);
            if x.fract() == 0.0 && x.abs() < 1e15 {
                format!("{x:.0}")
            } else {
                format!("{x:.1}")
            }
        }
        Some(Value::String(s)) => s.clone(),
        _ => "–".into(),
    }
}

/// `s` as the text of one cell of a Markdown table: a `|` would end the cell (and shift
/// every column after it), a line break the row.
fn md_cell(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '|' => out.push_str("\\|"),
            c if c.is_control() => out.push(' '),
            c => out.push(c),
        }
    }
    out
}

/// The Markdown table of a campaign.
/// `note`: a line under the counts (runs left out).
pub fn markdown(name: &str, purpose: &str, note: Option<&str>, results: &[CaseResult]) -> String {
    let count = |s: &str| results.iter().filter(|r| r.status == s).count();
    let purpose = if purpose.trim().is_empty() {
        String::new()
    } else {
        format!("{}\n\n", purpose.trim())
    };
    let mut md = format!(
        "# Campaign {name}\n\n{purpose}{} runs: {} passed, {} failed, {} errors, {} skipped.\n\n",
        results.len(),
        count("pass"),
        count("fail"),
        count("error"),
        count("skipped")
    );
    if let Some(n) = note {
        md.push_str(&format!("Note: {}.\n\n", md_cell(n)));
    }
    md.push_str("| # | scenario | faults | seed | result | peak \\|i\\| A | misses /M | worst republish ms | worst speed recovery ms | failed expectations |\n");
    md.push_str("|---|---|---|---|---|---|---|---|---|---|\n");
    let mut rows = results.iter().peekable();
    while let Some(r) = rows.next() {
        if r.status == "skipped" && rows.peek().is_some_and(|n| n.status == "skipped") {
            // Runs that never started follow one another to the end of an interrupted
            // campaign: one row for all of them (campaign.json and junit.xml list each).
            let (mut last, mut count) = (r, 1);
            while let Some(n) = rows.next_if(|n| n.status == "skipped") {
                (last, count) = (n, count + 1);
            }
            md.push_str(&format!(
                "| {}–{} | {count} runs | – | – | skipped | – | – | – | – | never started |\n",
                r.case.number, last.case.number
            ));
            continue;
        }
        let failed: Vec<String> = r
            .expectations
            .iter()
            .filter(|e| !e.pass)
            .map(|e| format!("`{}`", e.expect))
            .chain(r.error.iter().map(|e| format!("error: {e}")))
            .chain((r.status == "skipped").then(|| "never started".to_string()))
            .collect();
        md.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
            r.case.number,
            md_cell(&r.case.label),
            if r.case.faults.is_empty() {
                "–".to_string()
            } else {
                md_cell(&r.case.faults.join(" + "))
            },
            r.case.seed,
            r.status,
            cell(r.figures.get("peak_current_a")),
            cell(r.figures.get("deadline_misses_per_million")),
            cell(r.figures.get("worst_republished_ms")),
            cell(r.figures.get("worst_speed_recovered_ms")),
            md_cell(&failed.join("; "))
        ));
    }
    md
}

/// `s` with the characters XML 1.0 cannot carry (control characters other than tab, line
/// feed and carriage return; U+FFFE, U+FFFF) replaced by U+FFFD: a report that a CI reader
/// cannot parse would lose every case.
fn xml_safe(s: &str) -> std::borrow::Cow<'_, str> {
    let bad = |c: char| {
        (c.is_control() && !matches!(c, '\t' | '\n' | '\r') && c < ' ')
            || matches!(c, '\u{FFFE}' | '\u{FFFF}')
    };
    if s.chars().any(bad) {
        s.chars()
            .map(|c| if bad(c) { '\u{FFFD}' } else { c })
            .collect::<String>()
            .into()
    } else {
        s.into()
    }
}

/// A property's value: a number in full (the shortest form that reads back the same), so
/// that it can be set beside a failed limit.
fn property_value(v: &Value) -> String {
    match v {
        Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

/// The JUnit XML report: one test suite, one test case per run with its figures as
/// properties, one `<failure>` for the failed expectations (one element: several in one
/// case are shown, or even read, by few CI readers), an `<error>` for a run that did not
/// complete and `<skipped/>` for one that never started. A test case's class is the
/// campaign's name and the scenario as the campaign file names it, a `.toml` file by its
/// stem (a reader takes dots for package separators).
pub fn junit(name: &str, results: &[CaseResult]) -> Result<String> {
    use quick_xml::events::{BytesDecl, BytesEnd, BytesStart, BytesText, Event};
    let count = |s: &str| results.iter().filter(|r| r.status == s).count().to_string();
    let time: f64 = results.iter().map(|r| r.wall_s).sum();
    let mut w = quick_xml::Writer::new_with_indent(Vec::new(), b' ', 2);
    w.write_event(Event::Decl(BytesDecl::new("1.0", Some("UTF-8"), None)))?;
    let totals = |tag: &str| {
        let mut e = BytesStart::new(tag.to_string());
        e.push_attribute(("name", xml_safe(name).as_ref()));
        e.push_attribute(("tests", results.len().to_string().as_str()));
        e.push_attribute(("failures", count("fail").as_str()));
        e.push_attribute(("errors", count("error").as_str()));
        e.push_attribute(("skipped", count("skipped").as_str()));
        e.push_attribute(("time", format!("{time:.3}").as_str()));
        e
    };
    w.write_event(Event::Start(totals("testsuites")))?;
    w.write_event(Event::Start(totals("testsuite")))?;
    for r in results {
        let mut tc = BytesStart::new("testcase");
        let label = &r.case.label;
        let class = match Path::new(label).file_stem() {
            Some(stem) if label.ends_with(".toml") => stem.to_string_lossy().into_owned(),
            _ => label.clone(),
        };
        tc.push_attribute(("classname", xml_safe(&format!("{name}.{class}")).as_ref()));
        tc.push_attribute(("name", xml_safe(&r.case.title()).as_ref()));
        tc.push_attribute(("time", format!("{:.3}", r.wall_s).as_str()));
        w.write_event(Event::Start(tc))?;
        w.write_event(Event::Start(BytesStart::new("properties")))?;
        let mut props: Vec<(String, String)> = vec![("seed".into(), r.case.seed.to_string())];
        // A run that never made its folder has none to point to.
        if r.out.is_dir() {
            props.push(("run_folder".into(), r.out.display().to_string()));
        }
        // A figure the run does not have (no fault, no rise) is left out.
        for (k, v) in r.figures.iter().filter(|(_, v)| !v.is_null()) {
            props.push((k.clone(), property_value(v)));
        }
        for (k, v) in props {
            let mut p = BytesStart::new("property");
            p.push_attribute(("name", xml_safe(&k).as_ref()));
            p.push_attribute(("value", xml_safe(&v).as_ref()));
            w.write_event(Event::Empty(p))?;
        }
        w.write_event(Event::End(BytesEnd::new("properties")))?;
        let mut element = |tag: &str, kind: &str, message: &str, body: &str| -> Result<()> {
            let mut f = BytesStart::new(tag.to_string());
            f.push_attribute(("type", kind));
            f.push_attribute(("message", xml_safe(message).as_ref()));
            w.write_event(Event::Start(f))?;
            w.write_event(Event::Text(BytesText::new(&xml_safe(body))))?;
            w.write_event(Event::End(BytesEnd::new(tag.to_string())))?;
            Ok(())
        };
        let failed: Vec<&Outcome> = r.expectations.iter().filter(|e| !e.pass).collect();
        if !failed.is_empty() {
            // Each with why it matters, where the scenario's `[[expect]] note` says.
            let with_note = |e: &Outcome, text: String| {
                if e.note.trim().is_empty() {
                    text
                } else {
                    format!("{text} — {}", e.note.trim())
                }
            };
            let message: Vec<String> = failed.iter().map(|e| with_note(e, e.violation())).collect();
            let values: Vec<String> = failed
                .iter()
                .flat_map(|e| {
                    // A path that named no figure has no value to list: its violation says so.
                    (e.values.is_empty())
                        .then(|| e.violation())
                        .into_iter()
                        .chain(e.values.iter().map(|c| {
                            format!(
                                "{}: {} = {} ({})",
                                e.expect,
                                c.figure,
                                c.value_text(true),
                                if c.pass { "ok" } else { "violates" }
                            )
                        }))
                        .chain(
                            (!e.note.trim().is_empty())
                                .then(|| format!("{}: note: {}", e.expect, e.note.trim())),
                        )
                })
                .collect();
            element(
                "failure",
                "expectation",
                &message.join("; "),
                &values.join("\n"),
            )?;
        }
        if let Some(err) = &r.error {
            element("error", "run", err.lines().next().unwrap_or(""), err)?;
        }
        if r.status == "skipped" {
            w.write_event(Event::Empty(BytesStart::new("skipped")))?;
        }
        w.write_event(Event::End(BytesEnd::new("testcase")))?;
    }
    w.write_event(Event::End(BytesEnd::new("testsuite")))?;
    w.write_event(Event::End(BytesEnd::new("testsuites")))?;
    let mut s = String::from_utf8(w.into_inner())?;
    s.push('\n');
    Ok(s)
}

/// The reports a campaign writes at the top of its folder.
const REPORTS: [&str; 3] = ["campaign.json", "campaign.md", "junit.xml"];

/// The bus ids of a campaign's runs: this, then the run's number.
fn bus_prefix(pid: u32) -> String {
    format!("c{pid}_")
}

/// Writes `bytes` to `out/name`, the file named in its error.
fn write_report(out: &Path, name: &str, bytes: impl AsRef<[u8]>) -> Result<()> {
    let path = out.join(name);
    drivelab_runtime::files::write(&path, bytes)
        .with_context(|| format!("write {}", path.display()))
}

/// The files of the buses of an earlier campaign in `out` that did not finish (killed, e.g.
/// by a CI job's time limit): its `campaign.json` is still the one written at its start,
/// which names them. Each bus that no process uses any more is cleaned; one line says so.
fn clean_unfinished(out: &Path) {
    let Ok(text) = std::fs::read(out.join("campaign.json")) else {
        return;
    };
    let Ok(v) = serde_json::from_slice::<Value>(&text) else {
        return;
    };
    let (Some(prefix), Some(n)) = (
        v["unfinished"]["bus_prefix"].as_str(),
        v["unfinished"]["runs"].as_u64(),
    ) else {
        return;
    };
    let mut removed = 0;
    for number in 1..=n.min(MAX_RUNS as u64) {
        let bus = format!("{prefix}{number}");
        if drivelab_runtime::bus::leftovers(&bus).is_empty()
            || launcher::refuse_busy_bus(&bus, false).is_err()
        {
            continue;
        }
        if drivelab_runtime::bus::cleanup(&bus).is_ok() {
            removed += 1;
        }
    }
    if removed > 0 {
        crate::errln!(
            "drivelab: campaign folder {}: an earlier campaign here did not finish; removed the shared-memory files of {removed} of its buses ({prefix}N)",
            out.display()
        );
    }
}

/// Makes campaign folder `out`: new, empty or an earlier campaign's (it has
/// `campaign.json`), never a folder of other files nor one another campaign is writing
/// into (an advisory lock held until the returned file drops). An earlier campaign's
/// reports and its runs' outputs are removed first, so that none of them passes for this
/// campaign's (a run it does not repeat); other files are kept.
fn claim_campaign_folder(out: &Path) -> Result<std::fs::File> {
    let not_empty = std::fs::read_dir(out).is_ok_and(|mut d| d.next().is_some());
    if not_empty && !out.join("campaign.json").is_file() {
        bail!(
            "campaign folder {}: not empty and not a campaign's (no campaign.json): give a new or empty folder, or an earlier campaign's",
            out.display()
        );
    }
    let dir = crate::launcher::make_and_lock_folder(out, "campaign folder", "campaign")?;
    clean_unfinished(out);
    let runs = out.join("runs");
    if let Ok(entries) = std::fs::read_dir(&runs) {
        for e in entries.flatten() {
            let run = e.path();
            let numbered = e
                .file_name()
                .to_str()
                .is_some_and(|n| n.len() >= 3 && n.bytes().all(|b| b.is_ascii_digit()));
            // Only folders (not links to them) that an earlier run wrote.
            let folder = e.file_type().is_ok_and(|t| t.is_dir());
            if numbered && folder && run.join("scenario.toml").is_file() {
                drop(crate::launcher::claim_run_folder(&run)?);
                let _ = std::fs::remove_dir(&run);
            }
        }
        let _ = std::fs::remove_dir(&runs);
    }
    for name in REPORTS {
        let path = out.join(name);
        if path.symlink_metadata().is_ok_and(|m| !m.is_dir()) {
            std::fs::remove_file(&path).with_context(|| {
                format!(
                    "campaign folder {}: cannot remove the earlier campaign's {name}",
                    out.display()
                )
            })?;
        }
    }
    Ok(dir)
}

/// Runs a campaign and writes its reports; returns the exit code: 0 all passed,
/// [`EXIT_EXPECTATION_FAILED`] when an expectation failed, 1 when a run did not complete or
/// the campaign was interrupted.
pub fn run(a: &CampaignArgs) -> Result<u8> {
    drivelab_runtime::service::install_signal_handlers()?;
    let Loaded {
        c,
        cases,
        repeats,
        warnings,
    } = load(&a.file)?;
    // Said once, before the runs: the report has fewer runs than seeds × fault sets.
    let note = (repeats > 0).then(|| {
        format!(
            "the {} clock gives the same trace for every seed: {repeats} {} that would differ from another only by a seed (no random:N fault uses it) {} left out; each such run ran once, with seed {}",
            c.clock.name(),
            if repeats == 1 { "run" } else { "runs" },
            if repeats == 1 { "is" } else { "are" },
            c.seeds[0]
        )
    });
    if let Some(n) = &note {
        crate::errln!("drivelab: campaign {}: {n}", a.file.display());
    }
    // A configuration warning (standby twins in lockstep, say) is the same for many runs:
    // said once, before the runs; each run's summary.json keeps it (its launcher keeps it
    // off stderr: `RunOptions::quiet_warnings`).
    for (w, first) in &warnings {
        crate::errln!(
            "drivelab: warning: {w} (said once for the campaign; from run {first}, and in the summary.json of each run it applies to)"
        );
    }
    let out = match &a.out {
        Some(out) => out.clone(),
        None => crate::launcher::new_default_folder(&format!(
            "campaign-{}-{}",
            c.name,
            crate::launcher::unix_s()
        ))?,
    };
    let _lock = claim_campaign_folder(&out)?;
    // Marks the folder a campaign's from the start, so that one killed before its end
    // leaves a folder the next campaign takes (and whose buses it cleans), and finds a
    // folder it cannot write before the first run.
    let unfinished = json!({
        "name": c.name,
        "purpose": c.purpose,
        "file": a.file,
        "clock": c.clock,
        "unfinished": {
            "why": "written at the campaign's start; a campaign that ends replaces it with its report",
            "bus_prefix": bus_prefix(std::process::id()),
            "runs": cases.len(),
        },
        "runs": [],
    });
    write_report(
        &out,
        "campaign.json",
        serde_json::to_vec_pretty(&unfinished)?,
    )?;
    let bar = if a.json {
        indicatif::ProgressBar::hidden()
    } else {
        indicatif::ProgressBar::new(cases.len() as u64)
    };
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} runs {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let mut results = Vec::with_capacity(cases.len());
    let stop = drivelab_runtime::service::stop_flag();
    // Where a stop signal cut the campaign short, for its error line.
    let mut interrupted: Option<String> = None;
    // A line above the bar; a hidden bar (stderr not a terminal, as in CI; --json) prints
    // nothing, so the line goes to stderr then.
    let say = |line: String| {
        if bar.is_hidden() {
            crate::errln!("{line}");
        } else {
            bar.println(line);
        }
    };
    for case in &cases {
        if stop.load(std::sync::atomic::Ordering::Relaxed) {
            results.push(CaseResult {
                case: case.clone(),
                status: "skipped",
                out: PathBuf::new(),
                error: None,
                expectations: Vec::new(),
                figures: serde_json::Map::new(),
                wall_s: 0.0,
            });
            continue;
        }
        bar.set_message(case.title());
        let since = std::time::SystemTime::now();
        let r = run_case(&c, case, a, &out, since);
        if let Some(e) = r
            .error
            .as_ref()
            .filter(|_| interrupted.is_none() && stop.load(std::sync::atomic::Ordering::Relaxed))
        {
            // The signal came during this run and stopped it (its error says how).
            interrupted = Some(format!(
                "during run {} of {}: {}",
                case.number,
                cases.len(),
                e.lines().next().unwrap_or("")
            ));
        }
        // The hosts keep their set-up lines to themselves in a campaign; a refused part
        // (no privilege for SCHED_FIFO, a core not there) is still said, once per run.
        let summary = run_summary(&r.out, since).unwrap_or_default();
        if let Some(w) = rt_refusals(&summary) {
            say(format!(
                "run {}: real-time set-up incomplete: {w}",
                case.number
            ));
        }
        if r.status != "pass" {
            say(format!(
                "run {}: {} — {}",
                case.number,
                r.status,
                case.title()
            ));
        }
        results.push(r);
        bar.inc(1);
    }
    bar.finish_and_clear();
    let md = markdown(&c.name, &c.purpose, note.as_deref(), &results);
    write_report(&out, "campaign.md", &md)?;
    write_report(&out, "junit.xml", junit(&c.name, &results)?)?;
    let mut report = json!({
        "name": c.name,
        "purpose": c.purpose,
        "file": a.file,
        "clock": c.clock,
        "runs": results,
    });
    if let Some(n) = &note {
        report["seed_repeats_left_out"] = json!({ "runs": repeats, "why": n });
    }
    write_report(&out, "campaign.json", serde_json::to_vec_pretty(&report)?)?;
    if a.json {
        crate::outln!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        crate::out!("{md}");
        crate::outln!(
            "\nreports: {}/{{campaign.json,campaign.md,junit.xml}}",
            out.display()
        );
    }
    let any = |s: &str| results.iter().any(|r| r.status == s);
    // The reason is in the table and junit.xml; stderr says in one line that the campaign
    // did not finish, as `run` does for a drive stopped by a signal. A signal that came as
    // the last run ended cut nothing short: no line then.
    let skipped = results.iter().filter(|r| r.status == "skipped").count();
    let at = interrupted.or_else(|| {
        (skipped > 0).then(|| {
            format!(
                "before run {} of {}",
                cases.len() - skipped + 1,
                cases.len()
            )
        })
    });
    if let Some(at) = at {
        crate::errln!(
            "drivelab: error: campaign interrupted ({}) {at}; {skipped} of {} runs skipped (reports: {})",
            drivelab_runtime::service::stop_signal_name(),
            cases.len(),
            out.display()
        );
    }
    Ok(if any("error") || any("skipped") {
        1
    } else if any("fail") {
        EXIT_EXPECTATION_FAILED
    } else {
        0
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn case(label: &str, status: &'static str, out: PathBuf) -> CaseResult {
        CaseResult {
            case: Case {
                number: 1,
                scenario: format!("/somewhere/{label}"),
                label: label.into(),
                faults: Vec::new(),
                seed: 1,
            },
            status,
            out,
            error: None,
            expectations: Vec::new(),
            figures: serde_json::Map::new(),
            wall_s: 0.5,
        }
    }

    #[test]
    fn the_junit_report_reads_back_with_one_failure_per_case_and_figures_in_full() {
        let here = std::env::temp_dir();
        let mut failed = case("sub/my<&\"scenario\u{1}.toml", "fail", here.clone());
        let summary = json!({ "peak_current_a": 3.24, "samples_missing": 2 });
        failed.expectations = ["peak_current_a <= 3.2", "samples_missing == 0"]
            .iter()
            .map(|t| crate::expect::parse(t).unwrap().evaluate(&summary))
            .collect();
        failed.figures.insert("peak_current_a".into(), json!(3.24));
        let mut error = case("kyslan-pi", "error", here.join("no-such-run-folder-here"));
        error.error = Some("the drive did not start\u{7}".into());
        let xml = junit("night\u{1b}ly", &[failed, error]).unwrap();
        let doc = roxmltree::Document::parse(&xml).unwrap_or_else(|e| panic!("{e}: {xml}"));
        let cases: Vec<_> = doc
            .descendants()
            .filter(|n| n.has_tag_name("testcase"))
            .collect();
        assert_eq!(cases.len(), 2);
        // The class: the campaign and the scenario file's stem as the campaign names it,
        // the characters XML cannot carry replaced.
        assert_eq!(
            cases[0].attribute("classname"),
            Some("night\u{FFFD}ly.my<&\"scenario\u{FFFD}")
        );
        assert_eq!(
            cases[1].attribute("classname"),
            Some("night\u{FFFD}ly.kyslan-pi")
        );
        // Both failed expectations in one element.
        let failures: Vec<_> = cases[0]
            .children()
            .filter(|n| n.has_tag_name("failure"))
            .collect();
        assert_eq!(failures.len(), 1);
        let message = failures[0].attribute("message").unwrap();
        assert!(
            message.contains("peak_current_a <= 3.2") && message.contains("samples_missing == 0"),
            "{message}"
        );
        let body = failures[0].text().unwrap();
        assert_eq!(body.lines().count(), 2, "{body}");
        let prop = |tc: roxmltree::Node, name: &str| {
            tc.descendants()
                .find(|p| p.has_tag_name("property") && p.attribute("name") == Some(name))
                .and_then(|p| p.attribute("value"))
                .map(str::to_string)
        };
        // A figure in full beside its limit, not rounded to 3.2.
        assert_eq!(prop(cases[0], "peak_current_a").as_deref(), Some("3.24"));
        assert!(prop(cases[0], "run_folder").is_some());
        // A run that made no folder points to none.
        assert_eq!(prop(cases[1], "run_folder"), None);
        let err = cases[1]
            .children()
            .find(|n| n.has_tag_name("error"))
            .unwrap();
        assert_eq!(
            err.attribute("message"),
            Some("the drive did not start\u{FFFD}")
        );
    }

    #[test]
    fn an_empty_purpose_leaves_no_blank_paragraph() {
        let md = markdown("c", "  ", None, &[]);
        assert!(md.starts_with("# Campaign c\n\n0 runs:"), "{md}");
        let md = markdown("c", "why", None, &[]);
        assert!(md.starts_with("# Campaign c\n\nwhy\n\n0 runs:"), "{md}");
    }
}
