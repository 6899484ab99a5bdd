//! Topologies: which stages share a process, on which core, at which priority. Part of the
//! scenario (`[[process]]` tables) or given with `drivelab run --topology NAME|FILE`.
//! See docs/architecture.md, "Stages and topologies".
//!
//! [`resolve`] checks a topology against the stages' declarations and orders each process's
//! stages along the data graph; every error is one line that names the problem.

use crate::stage::{InputSpec, OnStale, Role, TopicId};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// One process of a topology.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProcessSpec {
    /// Process name (unique; 1-32 characters of a-z, 0-9, -).
    pub name: String,
    /// Stages it hosts. Their order is taken from the data graph.
    pub stages: Vec<String>,
    /// CPU core; None = not pinned.
    #[serde(default, deserialize_with = "cpu_field")]
    pub cpu: Option<usize>,
    /// SCHED_FIFO priority 1..=99; None = SCHED_OTHER.
    #[serde(default, deserialize_with = "priority_field")]
    pub priority: Option<u8>,
    /// Executable that hosts the stages (a user's stage crate), absolute or relative to the
    /// scenario file; default: the built-in host `drivelab-host`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub exec: Option<String>,
    /// Keep a warm twin of this process: started beside it on the same CPU one priority
    /// below, fed the same inputs, publishing nothing until the process dies; then it takes
    /// over within a sample or two (docs/architecture.md, "Liveness words and standby
    /// twins"). Not for the plant's process. Real-time clock only.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub standby: bool,
    /// The machine this process runs on, in a drive split across two machines joined by
    /// Zenoh bridges (docs/architecture.md, "The drive split across machines"). Either every
    /// process names one or none does; `drivelab run --machine NAME` starts that machine's
    /// processes. Without `--machine` the whole topology runs here.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub machine: Option<String>,
}

/// The largest CPU number a topology may name.
pub const CPU_MAX: usize = 1023;

/// A `cpu` (or `core`) field: any integer is read, and a negative one is one line that names
/// the value and the range (serde's own says "expected usize"); one above [`CPU_MAX`] is
/// refused with the process's name by [`check_specs`], a scenario's `[placement]` by its
/// validation.
pub(crate) fn cpu_field<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Option<usize>, D::Error> {
    // `null` (JSON: the resolved topology.json of an unpinned process) is no CPU.
    let Some(v) = Option::<i64>::deserialize(d)? else {
        return Ok(None);
    };
    usize::try_from(v)
        .map(Some)
        .map_err(|_| serde::de::Error::custom(format!("{v} is not a CPU number (0..={CPU_MAX})")))
}

/// A `priority` field: any integer is read, and one outside a `u8` is one line that names
/// the value and the SCHED_FIFO range (0 and 100..=255 are refused with the process's name
/// by [`check_specs`], a scenario's `[placement]` by its validation).
pub(crate) fn priority_field<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> Result<Option<u8>, D::Error> {
    // `null` (JSON: a SCHED_OTHER process in topology.json) is no priority.
    let Some(v) = Option::<i64>::deserialize(d)? else {
        return Ok(None);
    };
    u8::try_from(v).map(Some).map_err(|_| {
        serde::de::Error::custom(format!(
            "{v} is out of range: SCHED_FIFO priorities are 1..=99"
        ))
    })
}

/// A topology file: `[[process]]` tables.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TopologyFile {
    /// One-line purpose.
    #[serde(default)]
    pub purpose: String,
    /// The processes.
    pub process: Vec<ProcessSpec>,
}

/// What a stage declares, as the topology checks it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageInfo {
    /// Stage name.
    pub name: String,
    /// Declared inputs.
    pub inputs: Vec<InputSpec>,
    /// Published topics.
    pub outputs: Vec<TopicId>,
    /// Rate divider.
    pub divider: u64,
}

/// The producer of a topic in a resolved topology.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Producer {
    /// The topic.
    pub topic: TopicId,
    /// Producing stage.
    pub stage: String,
    /// Index of its process.
    pub process: usize,
    /// Its rate divider.
    pub divider: u64,
}

/// A checked topology.
#[derive(Debug, Clone, PartialEq)]
pub struct Resolved {
    /// Processes, each with its stages in chain order; the source's process first.
    pub processes: Vec<(ProcessSpec, Vec<StageInfo>)>,
    /// Every produced topic.
    pub producers: Vec<Producer>,
}

impl Resolved {
    /// Index of the process that hosts `stage`.
    pub fn process_of(&self, stage: &str) -> Option<usize> {
        self.processes
            .iter()
            .position(|(p, _)| p.stages.iter().any(|s| s == stage))
    }

    /// `(topic, producer divider, produced in process i)` for the host of process `i`.
    pub fn bindings(&self, i: usize) -> Vec<(TopicId, u64, bool)> {
        self.producers
            .iter()
            .map(|p| (p.topic, p.divider, p.process == i))
            .collect()
    }

    /// Every stage name, in process order then chain order.
    pub fn stage_names(&self) -> Vec<String> {
        self.processes
            .iter()
            .flat_map(|(_, s)| s.iter().map(|x| x.name.clone()))
            .collect()
    }
}

/// The folders a topology name is looked up in: `topologies/` in each of the scenario
/// folders ([`crate::config::scenario_dirs`]), in their order (the working folder's first).
pub fn topology_dirs() -> Vec<PathBuf> {
    crate::config::scenario_dirs()
        .into_iter()
        .map(|d| d.join("topologies"))
        .filter(|d| d.is_dir())
        .collect()
}

/// Names of the topologies found by name ([`topology_dirs`]), sorted.
pub fn list_topologies() -> Vec<String> {
    crate::config::list_named(&topology_dirs())
        .into_iter()
        .map(|(n, _)| n)
        .collect()
}

/// Loads a topology by shipped name or file path and checks what needs no stage declarations
/// ([`check_specs`]); an error names the file.
pub fn load(name_or_path: &str) -> Result<(TopologyFile, PathBuf), String> {
    let path = if crate::config::names_a_file(name_or_path) {
        PathBuf::from(name_or_path)
    } else {
        crate::config::find_named(&topology_dirs(), name_or_path).ok_or_else(|| {
            format!(
                "unknown topology '{name_or_path}' (known: {})",
                list_topologies().join(", ")
            )
        })?
    };
    let text = crate::config::read_config_file(&path, "topology")?;
    let origin = path.display().to_string();
    let t: TopologyFile = match toml::from_str(&text) {
        Ok(t) => t,
        Err(e) => match crate::config::Scenario::from_toml(&text, &origin) {
            // A scenario's processes are its topology (docs/architecture.md, "Stages and
            // topologies"): its `[[process]]` tables, else one process per stage as its
            // `[placement]` places them. A whole scenario is taken for them, only one that is
            // sound as a whole: a topology file with a misspelt key stays refused.
            Ok(sc) => TopologyFile {
                purpose: format!("the processes of the scenario {origin}"),
                process: sc.topology(),
            },
            Err(_) => return Err(crate::config::toml_error(&text, &origin, &e)),
        },
    };
    check_specs(&t.process).map_err(|e| format!("{origin}: {e}"))?;
    Ok((t, path))
}

/// Checks the parts of a topology that need no stage declarations.
pub fn check_specs(procs: &[ProcessSpec]) -> Result<(), String> {
    if procs.is_empty() {
        return Err("the topology has no [[process]]".into());
    }
    let mut names = BTreeMap::new();
    let mut hosted: BTreeMap<&str, &str> = BTreeMap::new();
    for p in procs {
        if p.name.is_empty()
            || p.name.len() > 32
            || !p
                .name
                .chars()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-')
        {
            return Err(format!(
                "process name '{}' must be 1-32 characters of a-z, 0-9 or -",
                p.name
            ));
        }
        if names.insert(p.name.as_str(), ()).is_some() {
            return Err(format!("process '{}' is defined twice", p.name));
        }
        if p.stages.is_empty() {
            return Err(format!("process '{}' hosts no stage", p.name));
        }
        if let Some(pr) = p.priority {
            if !(1..=99).contains(&pr) {
                return Err(format!(
                    "process '{}': priority = {pr} must be in 1..=99",
                    p.name
                ));
            }
        }
        if let Some(c) = p.cpu {
            if c > CPU_MAX {
                return Err(format!(
                    "process '{}': cpu = {c} is not a CPU number (0..={CPU_MAX})",
                    p.name
                ));
            }
        }
        if let Some(e) = p.exec.as_deref().filter(|e| e.trim().is_empty()) {
            // As written, quoted as TOML quotes it ("" or " " or "\t").
            return Err(format!(
                "process '{}': exec = {e:?} is {} and names no executable (leave exec out for the built-in host)",
                p.name,
                if e.is_empty() { "empty" } else { "blank" }
            ));
        }
        if p.standby && p.stages.iter().any(|s| s == "plant") {
            return Err(format!(
                "process '{}': standby = true is not for the plant's process (the plant is the drive's clock and its motor; a restarted plant rebuilds its downtime instead)",
                p.name
            ));
        }
        for s in &p.stages {
            if let Some(other) = hosted.insert(s.as_str(), p.name.as_str()) {
                return Err(if other == p.name {
                    format!("stage '{s}' is listed twice in process '{}'", p.name)
                } else {
                    format!(
                        "stage '{s}' is hosted twice: by process '{other}' and by process '{}'",
                        p.name
                    )
                });
            }
            if p.exec.is_none() && !crate::stages::BUILTIN.contains(&s.as_str()) {
                return Err(format!(
                    "unknown stage '{s}' in process '{}' (built-in: {}; a user's stage needs the process's `exec`)",
                    p.name,
                    crate::stages::BUILTIN.join(", ")
                ));
            }
        }
    }
    for b in crate::stages::BUILTIN {
        if !hosted.contains_key(b) {
            return Err(format!("stage '{b}' is not hosted by any process"));
        }
    }
    check_machines(procs)
}

/// The machines of a split topology: none, or exactly two, named by every process (1-32
/// characters of a-z, 0-9 or -).
fn check_machines(procs: &[ProcessSpec]) -> Result<(), String> {
    let named = procs.iter().filter(|p| p.machine.is_some()).count();
    if named == 0 {
        return Ok(());
    }
    if let Some(p) = procs.iter().find(|p| p.machine.is_none()) {
        return Err(format!(
            "process '{}' names no machine; in a split topology every process does",
            p.name
        ));
    }
    let mut machines: Vec<&str> = Vec::new();
    for p in procs {
        let m = p.machine.as_deref().unwrap_or_default();
        if m.is_empty()
            || m.len() > 32
            || !m
                .chars()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-')
        {
            return Err(format!(
                "process '{}': machine '{m}' must be 1-32 characters of a-z, 0-9 or -",
                p.name
            ));
        }
        if !machines.contains(&m) {
            machines.push(m);
        }
    }
    if machines.len() != 2 {
        return Err(format!(
            "a split topology places its processes on exactly two machines, found {}: {}",
            machines.len(),
            machines.join(", ")
        ));
    }
    Ok(())
}

/// The CPUs the processes are pinned to (bit i = CPU i, CPUs 0–63): the drive's real-time
/// cores, which tools keep off.
pub fn cores(procs: &[ProcessSpec]) -> u64 {
    procs
        .iter()
        .filter_map(|p| p.cpu)
        .filter(|&c| c < 64)
        .fold(0u64, |m, c| m | (1 << c))
}

/// One line for each CPU on which two or more processes (a standby twin counts, one
/// priority below its process) share a SCHED_FIFO priority: among equal priorities the
/// kernel runs them in the order they became ready, not along the data graph, so a stage
/// may wait for one that is not its input's producer. Processes of different machines do
/// not share a CPU. Real time only: lockstep runs its processes as normal tasks.
pub fn placement_warnings(procs: &[ProcessSpec]) -> Vec<String> {
    // (machine, cpu, priority) → the processes there.
    let mut at: BTreeMap<(Option<&str>, usize, u8), Vec<String>> = BTreeMap::new();
    for p in procs {
        let (Some(cpu), Some(pr)) = (p.cpu, p.priority) else {
            continue;
        };
        let m = p.machine.as_deref();
        at.entry((m, cpu, pr))
            .or_default()
            .push(format!("'{}'", p.name));
        if p.standby {
            at.entry((m, cpu, pr.saturating_sub(1).max(1)))
                .or_default()
                .push(format!("'{}' (its standby twin)", p.name));
        }
    }
    at.into_iter()
        .filter(|(_, who)| who.len() > 1)
        .map(|((m, cpu, pr), who)| {
            format!(
                "processes {} run on CPU {cpu}{} at the same SCHED_FIFO priority {pr}: the kernel runs them in the order they become ready, not along the data graph; give each its own priority, rising along the chain",
                who.join(", "),
                m.map(|m| format!(" of machine {m}")).unwrap_or_default()
            )
        })
        .collect()
}

/// The two machines of a split topology in order of appearance (the first hosts the first
/// process); empty when the topology is not split.
pub fn machines(procs: &[ProcessSpec]) -> Vec<String> {
    let mut v: Vec<String> = Vec::new();
    for m in procs.iter().filter_map(|p| p.machine.as_ref()) {
        if !v.contains(m) {
            v.push(m.clone());
        }
    }
    v
}

/// Why the kernel would refuse to start the script `exe` (a file that exists) with "No such
/// file or directory": the interpreter its first line names (`#!/path/to/interpreter`) is
/// not there. None when `exe` is no script, or its interpreter exists or is a relative path
/// (resolved in the starting process's folder, which only the start can tell).
pub fn missing_interpreter(exe: &Path) -> Option<String> {
    use std::io::Read;
    let mut head = [0u8; 256];
    let n = std::fs::File::open(exe).ok()?.read(&mut head).ok()?;
    let line = head[..n].strip_prefix(b"#!")?;
    let line = line.split(|&b| b == b'\n').next()?;
    let line = String::from_utf8_lossy(line);
    let interpreter = line.split_whitespace().next()?;
    let path = Path::new(interpreter);
    (path.is_absolute() && !path.exists()).then(|| {
        format!(
            "the interpreter named in its first line (#!{}) was not found: install it or correct that line",
            line.trim()
        )
    })
}

/// Checks a topology against the stages' declarations (`info(process, stage)`) and orders
/// each process's stages along the data graph.
pub fn resolve(
    procs: &[ProcessSpec],
    info: &mut dyn FnMut(&ProcessSpec, &str) -> Result<StageInfo, String>,
) -> Result<Resolved, String> {
    check_specs(procs)?;
    let mut processes: Vec<(ProcessSpec, Vec<StageInfo>)> = Vec::new();
    for p in procs {
        let mut v = Vec::new();
        for s in &p.stages {
            let i = info(p, s)?;
            if i.name != *s {
                return Err(format!(
                    "process '{}': its executable hosts no stage '{s}'",
                    p.name
                ));
            }
            v.push(i);
        }
        processes.push((p.clone(), v));
    }
    // One producer per topic.
    let mut producers: Vec<Producer> = Vec::new();
    for (pi, (_, stages)) in processes.iter().enumerate() {
        for st in stages {
            if st.divider == 0 {
                return Err(format!(
                    "stage '{}' declares a rate divider of 0 (it runs every N-th sample, N at least 1)",
                    st.name
                ));
            }
            for &t in &st.outputs {
                if let Some(other) = producers.iter().find(|p| p.topic == t) {
                    return Err(format!(
                        "two publishers on topic '{}': stages '{}' and '{}'",
                        t.name(),
                        other.stage,
                        st.name
                    ));
                }
                producers.push(Producer {
                    topic: t,
                    stage: st.name.clone(),
                    process: pi,
                    divider: st.divider,
                });
            }
        }
    }
    // Exactly one source (a stage without trigger).
    let sources: Vec<String> = processes
        .iter()
        .flat_map(|(_, s)| s.iter())
        .filter(|s| !s.inputs.iter().any(|i| i.role == Role::Trigger))
        .map(|s| s.name.clone())
        .collect();
    if sources.len() != 1 {
        return Err(format!(
            "a topology needs exactly one source stage (a stage without trigger), found {}: {}",
            sources.len(),
            sources.join(", ")
        ));
    }
    // A stage is triggered by a topic that someone produces.
    for (_, stages) in &processes {
        for st in stages {
            for i in &st.inputs {
                let produced = producers.iter().any(|p| p.topic == i.topic);
                if i.role == Role::Trigger && !produced {
                    return Err(format!(
                        "stage '{}' is triggered by topic '{}', which no stage publishes",
                        st.name,
                        i.topic.name()
                    ));
                }
                // A required input nobody makes would never be there: the stage could never
                // run, or would run without it.
                if i.on_stale == OnStale::Required && i.role != Role::Rejoin && !produced {
                    return Err(format!(
                        "stage '{}' requires topic '{}', which no stage publishes (declare it OnStale::Fallback to run without it)",
                        st.name,
                        i.topic.name()
                    ));
                }
                if i.delay > 1 {
                    return Err(format!(
                        "stage '{}': input '{}' has delay {} (0 or 1 sample)",
                        st.name,
                        i.topic.name(),
                        i.delay
                    ));
                }
            }
            let triggers: Vec<&str> = st
                .inputs
                .iter()
                .filter(|i| i.role == Role::Trigger)
                .map(|i| i.topic.name())
                .collect();
            if triggers.len() > 1 {
                return Err(format!(
                    "stage '{}' declares {} triggers ({}): a stage runs on one, and reads the others as latest values",
                    st.name,
                    triggers.len(),
                    triggers.join(", ")
                ));
            }
        }
    }
    // The same-sample graph (delay 0 edges) must have no loop: order all stages.
    let all: Vec<&StageInfo> = processes.iter().flat_map(|(_, s)| s.iter()).collect();
    let deps = |s: &StageInfo| -> Vec<String> {
        s.inputs
            .iter()
            .filter(|i| i.delay == 0 && i.role != Role::Rejoin)
            .filter_map(|i| producers.iter().find(|p| p.topic == i.topic))
            .map(|p| p.stage.clone())
            .collect()
    };
    let mut order: Vec<String> = Vec::new();
    let mut state: BTreeMap<String, u8> = BTreeMap::new();
    fn visit(
        name: &str,
        all: &[&StageInfo],
        deps: &dyn Fn(&StageInfo) -> Vec<String>,
        state: &mut BTreeMap<String, u8>,
        order: &mut Vec<String>,
        path: &mut Vec<String>,
    ) -> Result<(), String> {
        match state.get(name) {
            Some(2) => return Ok(()),
            Some(1) => {
                let start = path.iter().position(|p| p == name).unwrap_or(0);
                let mut cyc = path[start..].to_vec();
                cyc.push(name.to_string());
                return Err(format!(
                    "a loop in the data graph without a one-sample delay: {}",
                    cyc.join(" -> ")
                ));
            }
            _ => {}
        }
        state.insert(name.to_string(), 1);
        path.push(name.to_string());
        let s = all.iter().find(|s| s.name == name).expect("known stage");
        for d in deps(s) {
            visit(&d, all, deps, state, order, path)?;
        }
        path.pop();
        state.insert(name.to_string(), 2);
        order.push(name.to_string());
        Ok(())
    }
    for s in &all {
        let mut path = Vec::new();
        visit(&s.name, &all, &deps, &mut state, &mut order, &mut path)?;
    }
    let rank = |n: &str| order.iter().position(|o| o == n).unwrap_or(usize::MAX);
    for (p, stages) in processes.iter_mut() {
        stages.sort_by_key(|s| rank(&s.name));
        p.stages = stages.iter().map(|s| s.name.clone()).collect();
        // The source runs on the clock: it must come first in its process.
        if stages.iter().skip(1).any(|s| sources.contains(&s.name)) {
            return Err(format!(
                "process '{}': the source stage '{}' must not follow other stages",
                p.name, sources[0]
            ));
        }
    }
    // The source's process first, then the others in the order given.
    let src = processes
        .iter()
        .position(|(_, s)| s.iter().any(|x| x.name == sources[0]))
        .expect("source hosted");
    let sp = processes.remove(src);
    processes.insert(0, sp);
    for p in producers.iter_mut() {
        p.process = processes
            .iter()
            .position(|(_, s)| s.iter().any(|x| x.name == p.stage))
            .expect("hosted");
    }
    Ok(Resolved {
        processes,
        producers,
    })
}

/// The built-in stages' declarations for scenario `sc` (the launcher asks a user's
/// executable for its own with `--describe`).
pub fn builtin_info(sc: &crate::config::Scenario, name: &str) -> Option<StageInfo> {
    let (inputs, outputs, divider) = crate::stages::declaration(name, sc)?;
    Some(StageInfo {
        name: name.to_string(),
        inputs: inputs.to_vec(),
        outputs: outputs.to_vec(),
        divider,
    })
}

/// Checks a user's stage `user` that takes the name of built-in stage `builtin` (from the
/// executable `exe`): it must publish exactly the topics the built-in publishes, at its rate,
/// so that the drive's wiring, its trace, its fault reports and the built-in stages that read
/// it (which time their holds by that rate) stay as they are. Its inputs are its own.
pub fn check_replacement(user: &StageInfo, builtin: &StageInfo, exe: &str) -> Result<(), String> {
    let names = |t: &[TopicId]| {
        let mut v: Vec<&str> = t.iter().map(|t| t.name()).collect();
        v.sort_unstable();
        v
    };
    let (mine, theirs) = (names(&user.outputs), names(&builtin.outputs));
    if mine != theirs {
        return Err(format!(
            "stage '{}' of {exe} replaces the built-in {} and must publish what it publishes: {} (it declares: {})",
            user.name,
            user.name,
            theirs.join(", "),
            if mine.is_empty() { "nothing".to_string() } else { mine.join(", ") }
        ));
    }
    if user.divider != builtin.divider {
        let set_by = if user.name == "speed-loop" {
            " ([rates] speed_divider sets it)"
        } else {
            ""
        };
        return Err(format!(
            "stage '{}' of {exe} replaces the built-in {} and must run at its rate, every {} sample(s){set_by}, not every {}",
            user.name, user.name, builtin.divider, user.divider
        ));
    }
    Ok(())
}

/// The path of a process's executable, relative paths taken from `base` (the scenario's
/// folder).
pub fn exec_path(p: &ProcessSpec, base: &Path) -> Option<PathBuf> {
    p.exec.as_ref().map(|e| {
        let e = Path::new(e);
        if e.is_absolute() {
            e.to_path_buf()
        } else {
            base.join(e)
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Scenario;

    fn sc() -> Scenario {
        let path = format!(
            "{}/../../scenarios/kyslan-pi.toml",
            env!("CARGO_MANIFEST_DIR")
        );
        Scenario::from_toml(&std::fs::read_to_string(&path).unwrap(), &path).unwrap()
    }

    #[test]
    fn a_scenario_file_is_taken_for_its_processes() {
        let root = concat!(env!("CARGO_MANIFEST_DIR"), "/../..");
        let with = format!("{root}/examples/position-loop/position-step.toml");
        let (t, _) = load(&with).unwrap();
        let names: Vec<&str> = t.process.iter().map(|p| p.name.as_str()).collect();
        assert!(names.contains(&"position-loop"), "{names:?}");
        let text = std::fs::read_to_string(&with).unwrap();
        assert_eq!(
            t.process,
            Scenario::from_toml(&text, &with).unwrap().process
        );
        // Without them (kyslan-pi, as `sc()` reads it): one process per stage, where its
        // [placement] puts them.
        let (t, _) = load(&format!("{root}/scenarios/kyslan-pi.toml")).unwrap();
        let sc = sc();
        assert!(sc.process.is_empty());
        assert_eq!(t.process, sc.topology());
        assert_eq!(t.process.len(), 4);
        // A topology file with a misspelt key is neither: the topology's own error.
        let typo = std::env::temp_dir().join(format!("drivelab-typo-{}.toml", std::process::id()));
        std::fs::write(
            &typo,
            "[[process]]\nname = \"all\"\nstages = [\"plant\", \"observer\", \"current-loop\", \"speed-loop\"]\ncpuu = 1\n",
        )
        .unwrap();
        let e = load(typo.to_str().unwrap());
        let _ = std::fs::remove_file(&typo);
        let e = e.unwrap_err();
        assert!(e.contains("unknown field `cpuu`"), "{e}");
    }

    #[test]
    fn an_unpinned_sched_other_process_reads_back_from_its_json() {
        // topology.json, which every host reads, writes an unpinned SCHED_OTHER process's
        // cpu and priority as null.
        let mut p = procs(&[("speed-loop", &["speed-loop"])]).remove(0);
        p.cpu = None;
        p.priority = None;
        let json = serde_json::to_string(&p).unwrap();
        assert!(json.contains("\"cpu\":null"), "{json}");
        assert_eq!(serde_json::from_str::<ProcessSpec>(&json).unwrap(), p);
        p.cpu = Some(1);
        p.priority = Some(74);
        let json = serde_json::to_string(&p).unwrap();
        assert_eq!(serde_json::from_str::<ProcessSpec>(&json).unwrap(), p);
    }

    fn procs(spec: &[(&str, &[&str])]) -> Vec<ProcessSpec> {
        spec.iter()
            .map(|(n, s)| ProcessSpec {
                name: n.to_string(),
                stages: s.iter().map(|x| x.to_string()).collect(),
                cpu: Some(1),
                priority: Some(70),
                exec: None,
                standby: false,
                machine: None,
            })
            .collect()
    }

    fn resolve_builtin(p: &[ProcessSpec]) -> Result<Resolved, String> {
        let sc = sc();
        resolve(p, &mut |_, s| {
            builtin_info(&sc, s).ok_or_else(|| format!("unknown stage '{s}'"))
        })
    }

    #[test]
    fn a_script_whose_interpreter_is_missing_is_named_by_its_first_line() {
        let dir = std::env::temp_dir().join(format!("drivelab-shebang-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let script = |name: &str, text: &str| {
            let f = dir.join(name);
            std::fs::write(&f, text).unwrap();
            f
        };
        let missing = script("missing.py", "#!/nonexistent/python -u\nprint(1)\n");
        assert_eq!(
            missing_interpreter(&missing).as_deref(),
            Some("the interpreter named in its first line (#!/nonexistent/python -u) was not found: install it or correct that line")
        );
        assert_eq!(
            missing_interpreter(&script("sh.sh", "#!/bin/sh\nexit 0\n")),
            None
        );
        assert_eq!(missing_interpreter(&script("rel.sh", "#!python\n")), None);
        assert_eq!(missing_interpreter(&script("plain", "\x7fELF")), None);
        assert_eq!(missing_interpreter(&dir.join("absent")), None);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn processes_at_one_priority_on_one_cpu_are_warned_about_once_per_cpu_and_priority() {
        let mut p = procs(&[
            ("plant", &["plant"]),
            ("observer", &["observer"]),
            ("loops", &["current-loop", "speed-loop"]),
        ]);
        // plant and observer at 70 on CPU 1; the loops at 72 on CPU 1.
        p[2].priority = Some(72);
        let w = placement_warnings(&p);
        assert_eq!(
            w,
            ["processes 'plant', 'observer' run on CPU 1 at the same SCHED_FIFO priority 70: the kernel runs them in the order they become ready, not along the data graph; give each its own priority, rising along the chain"]
        );
        // Another CPU, or another priority: nothing to say.
        p[1].cpu = Some(2);
        assert!(placement_warnings(&p).is_empty());
        p[1].cpu = Some(1);
        p[1].priority = Some(71);
        assert!(placement_warnings(&p).is_empty());
        // A standby twin runs one priority below its process: the loops' twin at 71 shares
        // it with the observer.
        p[2].standby = true;
        let w = placement_warnings(&p);
        assert_eq!(w.len(), 1, "{w:?}");
        assert!(
            w[0].starts_with("processes 'observer', 'loops' (its standby twin) run on CPU 1 at the same SCHED_FIFO priority 71"),
            "{w:?}"
        );
        // Unpinned or not real-time: no shared core to speak of.
        p[2].standby = false;
        p[0].priority = None;
        p[1].cpu = None;
        assert!(placement_warnings(&p).is_empty());
        // The shipped topologies give every process its own priority on its core (5 ship: an
        // empty list, the folder not found, would check nothing).
        let shipped = list_topologies();
        assert!(shipped.len() >= 5, "{shipped:?}");
        for name in shipped {
            let (t, _) = load(&name).unwrap();
            assert_eq!(
                placement_warnings(&t.process),
                Vec::<String>::new(),
                "{name}"
            );
        }
    }

    #[test]
    fn a_replacement_publishes_exactly_what_the_built_in_publishes() {
        let sc = sc();
        let b = builtin_info(&sc, "current-loop").unwrap();
        let mine = |outputs: Vec<TopicId>| StageInfo {
            name: "current-loop".into(),
            // Its inputs are its own.
            inputs: vec![InputSpec::trigger(TopicId::Meas, 1, OnStale::Required)],
            outputs,
            divider: 1,
        };
        check_replacement(&mine(vec![TopicId::Cmd]), &b, "/x/mine").unwrap();
        // Its rate is the built-in's.
        let slow = StageInfo {
            divider: 2,
            ..mine(vec![TopicId::Cmd])
        };
        assert_eq!(
            check_replacement(&slow, &b, "/x/mine").unwrap_err(),
            "stage 'current-loop' of /x/mine replaces the built-in current-loop and must run at its rate, every 1 sample(s), not every 2"
        );
        assert_eq!(
            check_replacement(&mine(vec![TopicId::Cmd, TopicId::Wref]), &b, "/x/mine").unwrap_err(),
            "stage 'current-loop' of /x/mine replaces the built-in current-loop and must publish what it publishes: cmd (it declares: cmd, wref)"
        );
        assert_eq!(
            check_replacement(&mine(Vec::new()), &b, "/x/mine").unwrap_err(),
            "stage 'current-loop' of /x/mine replaces the built-in current-loop and must publish what it publishes: cmd (it declares: nothing)"
        );
    }

    #[test]
    fn shipped_topologies_resolve_with_the_stages_in_chain_order() {
        for name in ["four-process", "two-process", "one-process"] {
            let (t, _) = load(name).unwrap();
            let r = resolve_builtin(&t.process).unwrap();
            assert_eq!(r.processes[0].1[0].name, "plant", "{name}");
            let all = r.stage_names();
            let pos = |s: &str| all.iter().position(|x| x == s).unwrap();
            assert!(pos("plant") < pos("observer"), "{name}: {all:?}");
            assert!(pos("observer") < pos("current-loop"), "{name}: {all:?}");
            assert!(pos("observer") < pos("speed-loop"), "{name}: {all:?}");
        }
        let (one, _) = load("one-process").unwrap();
        assert_eq!(resolve_builtin(&one.process).unwrap().processes.len(), 1);
    }

    /// A stage that waits in real time, after its process's first stage, for a trigger from
    /// another process is named (its host waits with a timer every sample); no shipped
    /// topology has one.
    #[test]
    fn a_trigger_from_another_process_after_the_first_stage_is_named() {
        use crate::service::TopologyPlan;
        let r = resolve_builtin(&procs(&[
            ("p", &["plant", "current-loop"]),
            ("o", &["observer", "speed-loop"]),
        ]))
        .unwrap();
        assert_eq!(
            TopologyPlan::from_resolved(&r).timed_waits(),
            ["process 'p': stage 'current-loop' is triggered by 'est' from process 'o' after 'plant' has run: in real time it waits for it with a timer every sample; host it with 'observer' or first in a process of its own"]
        );
        for name in list_topologies() {
            let (t, _) = load(&name).unwrap();
            let Ok(r) = resolve_builtin(&t.process) else {
                continue;
            };
            assert!(
                TopologyPlan::from_resolved(&r).timed_waits().is_empty(),
                "{name}"
            );
        }
    }

    #[test]
    fn order_in_a_process_follows_the_data_graph() {
        let r = resolve_builtin(&procs(&[
            ("p", &["plant"]),
            ("c", &["speed-loop", "current-loop", "observer"]),
        ]))
        .unwrap();
        assert_eq!(r.processes[1].0.stages[0], "observer");
    }

    #[test]
    fn bad_topologies_fail_with_one_line_naming_the_problem() {
        let cases: Vec<(Vec<ProcessSpec>, &str)> = vec![
            (
                procs(&[
                    ("a", &["plant", "observer"]),
                    ("b", &["observer", "current-loop", "speed-loop"]),
                ]),
                "stage 'observer' is hosted twice",
            ),
            (
                procs(&[("a", &["plant", "observer", "current-loop"])]),
                "stage 'speed-loop' is not hosted",
            ),
            (
                procs(&[(
                    "a",
                    &[
                        "plant",
                        "observer",
                        "current-loop",
                        "speed-loop",
                        "torque-loop",
                    ],
                )]),
                "unknown stage 'torque-loop'",
            ),
            (
                procs(&[
                    ("a", &["plant", "observer"]),
                    ("a", &["current-loop", "speed-loop"]),
                ]),
                "process 'a' is defined twice",
            ),
            (
                procs(&[("A b", &["plant", "observer", "current-loop", "speed-loop"])]),
                "process name 'A b'",
            ),
            (
                procs(&[
                    ("a", &["plant", "observer", "current-loop", "speed-loop"]),
                    ("b", &[]),
                ]),
                "process 'b' hosts no stage",
            ),
        ];
        for (p, want) in cases {
            let e = resolve_builtin(&p).unwrap_err();
            assert!(e.contains(want), "{e} (want {want})");
            assert!(!e.contains('\n'), "{e}");
        }
    }

    #[test]
    fn an_input_nobody_publishes_is_refused_when_it_triggers_or_is_required() {
        let sc = sc();
        let mut topo = procs(&[
            ("a", &["plant", "observer", "current-loop", "speed-loop"]),
            ("b", &["mine"]),
        ]);
        topo[1].exec = Some("/usr/local/bin/my-host".into());
        // A user stage reading `wref`, which no stage of this topology publishes.
        let with = |input: InputSpec| {
            resolve(&topo, &mut |_, s| {
                if s == "mine" {
                    return Ok(StageInfo {
                        name: "mine".into(),
                        inputs: vec![
                            InputSpec::trigger(TopicId::Est, 1, OnStale::Fallback),
                            input,
                        ],
                        outputs: Vec::new(),
                        divider: 1,
                    });
                }
                builtin_info(&sc, s).ok_or_else(|| format!("unknown stage '{s}'"))
            })
        };
        let e = with(InputSpec::latest(TopicId::Wref, 1, 2, OnStale::Required)).unwrap_err();
        assert_eq!(
            e,
            "stage 'mine' requires topic 'wref', which no stage publishes (declare it OnStale::Fallback to run without it)"
        );
        let e = with(InputSpec::trigger(TopicId::Wref, 1, OnStale::Fallback)).unwrap_err();
        assert_eq!(
            e,
            "stage 'mine' is triggered by topic 'wref', which no stage publishes"
        );
        // A fallback input may be absent: the stage runs without it.
        with(InputSpec::latest(TopicId::Wref, 1, 2, OnStale::Fallback)).unwrap();
        // A rate divider of 0 is refused, not read as 1.
        let e = resolve(&topo, &mut |_, s| {
            if s == "mine" {
                return Ok(StageInfo {
                    name: "mine".into(),
                    inputs: vec![InputSpec::trigger(TopicId::Est, 1, OnStale::Fallback)],
                    outputs: vec![TopicId::Wref],
                    divider: 0,
                });
            }
            builtin_info(&sc, s).ok_or_else(|| format!("unknown stage '{s}'"))
        })
        .unwrap_err();
        assert_eq!(
            e,
            "stage 'mine' declares a rate divider of 0 (it runs every N-th sample, N at least 1)"
        );
        // One trigger a stage.
        let e = with(InputSpec::trigger(TopicId::Meas, 1, OnStale::Fallback)).unwrap_err();
        assert_eq!(
            e,
            "stage 'mine' declares 2 triggers (est, meas): a stage runs on one, and reads the others as latest values"
        );
    }

    #[test]
    fn a_stage_rate_must_divide_the_sample_rate_and_placement_is_given_once() {
        let base = "name = \"x\"\nduration_s = 0.01\n[motor]\npreset = \"kyslan2015\"\n";
        let e = Scenario::from_toml(
            &format!("{base}[stages.position-loop]\nrate_hz = 3000.0\n"),
            "x.toml",
        )
        .unwrap_err();
        assert!(
            e.contains(
                "stages.position-loop.rate_hz = 3000.0 must divide the sample rate 10000 Hz"
            ),
            "{e}"
        );
        let ok = Scenario::from_toml(
            &format!("{base}[stages.position-loop]\nrate_hz = 2000\n"),
            "x.toml",
        )
        .unwrap();
        assert_eq!(ok.stage_divider("position-loop"), Some(5));
        let e = Scenario::from_toml(
            &format!("{base}[placement.plant]\ncore = 0\npriority = 50\n[[process]]\nname = \"a\"\nstages = [\"plant\", \"observer\", \"current-loop\", \"speed-loop\"]\n"),
            "x.toml",
        )
        .unwrap_err();
        assert!(e.contains("either in [placement] or in [[process]]"), "{e}");
    }

    #[test]
    fn a_split_topology_names_exactly_two_machines_for_every_process() {
        let split = |machines: &[Option<&str>]| {
            let mut v = procs(&[
                ("plant", &["plant"]),
                ("observer", &["observer"]),
                ("loops", &["current-loop", "speed-loop"]),
            ]);
            for (p, m) in v.iter_mut().zip(machines) {
                p.machine = m.map(str::to_string);
            }
            v
        };
        let ok = split(&[Some("bench"), Some("board"), Some("board")]);
        assert!(resolve_builtin(&ok).is_ok());
        assert_eq!(machines(&ok), ["bench", "board"]);
        assert!(machines(&split(&[None, None, None])).is_empty());
        let cases = [
            (
                split(&[Some("bench"), None, Some("board")]),
                "process 'observer' names no machine; in a split topology every process does",
            ),
            (
                split(&[Some("bench"), Some("bench"), Some("bench")]),
                "exactly two machines, found 1: bench",
            ),
            (
                split(&[Some("a"), Some("b"), Some("c")]),
                "exactly two machines, found 3: a, b, c",
            ),
            (
                split(&[Some("Bench PC"), Some("board"), Some("board")]),
                "process 'plant': machine 'Bench PC' must be 1-32 characters of a-z, 0-9 or -",
            ),
        ];
        for (p, want) in cases {
            let e = resolve_builtin(&p).unwrap_err();
            assert!(e.contains(want), "{e} (want {want})");
        }
    }

    fn info(name: &str, inputs: Vec<InputSpec>, outputs: Vec<TopicId>) -> StageInfo {
        StageInfo {
            name: name.into(),
            inputs,
            outputs,
            divider: 1,
        }
    }

    #[test]
    fn two_publishers_and_undelayed_loops_are_rejected() {
        use crate::stage::OnStale;
        let sc = sc();
        let p = |extra: &'static str| {
            let mut v = procs(&[("a", &["plant", "observer", "current-loop", "speed-loop"])]);
            v.push(ProcessSpec {
                name: "x".into(),
                stages: vec![extra.into()],
                cpu: None,
                priority: None,
                exec: Some("/bin/true".into()),
                standby: false,
                machine: None,
            });
            v
        };
        // A second publisher of the estimate.
        let e = resolve(&p("twin"), &mut |_, s| {
            Ok(builtin_info(&sc, s).unwrap_or_else(|| {
                info(
                    s,
                    vec![InputSpec::trigger(TopicId::Meas, 1, OnStale::Required)],
                    vec![TopicId::Est],
                )
            }))
        })
        .unwrap_err();
        assert!(e.contains("two publishers on topic 'est'"), "{e}");
        // An outer loop that reads the speed loop's output in the same sample and feeds it
        // back without delay: speed-loop -> outer -> speed-loop.
        let e = resolve(&p("outer"), &mut |_, s| {
            let mut i = builtin_info(&sc, s).unwrap_or_else(|| {
                info(
                    s,
                    vec![InputSpec::trigger(TopicId::Iref, 1, OnStale::Required)],
                    vec![TopicId::Wref],
                )
            });
            if s == "speed-loop" {
                for x in i.inputs.iter_mut() {
                    if x.topic == TopicId::Wref {
                        x.delay = 0;
                    }
                }
            }
            Ok(i)
        })
        .unwrap_err();
        assert!(
            e.contains("a loop in the data graph without a one-sample delay"),
            "{e}"
        );
        assert!(e.contains("speed-loop") && e.contains("outer"), "{e}");
    }
}
