//! Where the microseconds of a cycle go: the critical path of one sample, from the source's
//! ideal release instant t_k to the command it waits for, cut into parts that tile it
//! (docs/architecture.md, "Where the microseconds go").
//!
//! For a sample, the parts are: the source's timer wake-up (lateness), its execution, then
//! for every stage on the path its trigger's publish (the sender's loan, copy and send, up to
//! its notify), its own wake-up (notify → running), and its execution. Per sample they add up
//! to the cycle latency except for the short stretches between a step's return and the
//! stamping of the message that the next stage waits for; the table shows what is left as
//! "rest" (cycle − sum of the parts' medians, which is not the median of a sum).

use drivelab_runtime::service::TopologyPlan;
use drivelab_runtime::stage::Role;
use drivelab_runtime::timing::Percentiles;
use serde::Serialize;
use std::collections::BTreeMap;

/// One part of the critical path.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Part {
    /// What it is, e.g. "observer wake-up".
    pub part: String,
    /// The histogram it comes from (`<stage>.<hist>` in the run folder).
    pub hist: String,
    /// Median, µs.
    pub p50_us: f64,
    /// 99th percentile, µs.
    pub p99_us: f64,
}

/// The budget of the cycle.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Budget {
    /// Stages on the critical path, source first.
    pub path: Vec<String>,
    /// The parts, in path order.
    pub parts: Vec<Part>,
    /// Sum of the parts' medians, µs.
    pub sum_p50_us: f64,
    /// The cycle latency's median and 99th percentile, µs.
    pub cycle_p50_us: f64,
    /// The cycle latency's 99th percentile, µs.
    pub cycle_p99_us: f64,
    /// cycle p50 − sum of the parts' p50, µs.
    pub rest_p50_us: f64,
}

/// The stages on the critical path, source first: from the stage that produces the
/// source's delayed command back along each stage's trigger to the source. None when the
/// topology has no such path (no delayed command, or a trigger nobody produces).
pub fn critical_path(t: &TopologyPlan) -> Option<Vec<String>> {
    let source = t.stages.first()?;
    let cmd = source
        .inputs
        .iter()
        .find(|i| i.delay > 0 && i.role == Role::Latest)?
        .topic;
    let producer = |topic| t.producers.iter().find(|p| p.topic == topic);
    let mut path = Vec::new();
    let mut stage = producer(cmd)?.stage.clone();
    // At most one visit per stage: a loop of triggers is not a path.
    for _ in 0..t.stages.len() {
        if stage == source.name {
            path.push(stage);
            path.reverse();
            return Some(path);
        }
        let info = t.stages.iter().find(|s| s.name == stage)?;
        let trigger = info.inputs.iter().find(|i| i.role == Role::Trigger)?.topic;
        path.push(stage);
        stage = producer(trigger)?.stage.clone();
    }
    None
}

/// The budget of a run from its topology and the percentiles of its histograms (keys
/// `<stage>.<hist>` and `cycle`, as in `summary.json → latency_us`). None when the run has
/// no cycle histogram (not a real-time run) or no critical path.
pub fn budget(t: &TopologyPlan, latency: &BTreeMap<String, Percentiles>) -> Option<Budget> {
    let path = critical_path(t)?;
    let cycle = latency.get("cycle")?;
    let mut parts = Vec::new();
    let mut add = |part: String, hist: String| {
        if let Some(p) = latency.get(&hist) {
            parts.push(Part {
                part,
                hist,
                p50_us: p.p50,
                p99_us: p.p99,
            });
        }
    };
    for (i, s) in path.iter().enumerate() {
        if i == 0 {
            add(format!("{s} timer wake-up"), format!("{s}.lateness"));
        } else if t.process_of(s) != t.process_of(&path[i - 1]) {
            let up = &path[i - 1];
            if latency.contains_key(&format!("{s}.send")) {
                add(format!("{up} publish"), format!("{s}.send"));
                add(format!("{s} wake-up"), format!("{s}.wakeup"));
            } else {
                // No stamped wake-ups (iceoryx2 events): publish and wake-up as one hop.
                add(
                    format!("{up} → {s} publish and wake-up"),
                    format!("{s}.wake"),
                );
            }
        }
        add(format!("{s} execution"), format!("{s}.exec"));
    }
    let sum_p50_us: f64 = parts.iter().map(|p| p.p50_us).sum();
    Some(Budget {
        path,
        parts,
        sum_p50_us,
        cycle_p50_us: cycle.p50,
        cycle_p99_us: cycle.p99,
        rest_p50_us: cycle.p50 - sum_p50_us,
    })
}

/// The budget as a Markdown table.
pub fn markdown(b: &Budget) -> String {
    let mut s = String::from("| part of the cycle | p50 µs | p99 µs |\n|---|---:|---:|\n");
    for p in &b.parts {
        s += &format!("| {} | {:.1} | {:.1} |\n", p.part, p.p50_us, p.p99_us);
    }
    s += &format!(
        "| **sum of the parts** | **{:.1}** | |\n| **cycle latency** | **{:.1}** | **{:.1}** |\n| rest (cycle − sum) | {:.1} | |\n",
        b.sum_p50_us, b.cycle_p50_us, b.cycle_p99_us, b.rest_p50_us
    );
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use drivelab_runtime::config::Scenario;

    fn plan(topology: &str) -> TopologyPlan {
        let (sc, _) = Scenario::load("kyslan-pi").unwrap();
        let (file, _) = drivelab_runtime::topology::load(topology).unwrap();
        let r = drivelab_runtime::topology::resolve(&file.process, &mut |_, stage| {
            drivelab_runtime::topology::builtin_info(&sc, stage).ok_or_else(|| stage.to_string())
        })
        .unwrap();
        TopologyPlan::from_resolved(&r)
    }

    fn pct(p50: f64, p99: f64) -> Percentiles {
        Percentiles {
            p50,
            p99,
            p999: p99,
            max: p99,
            count: 100,
        }
    }

    #[test]
    fn the_default_chain_runs_plant_observer_current_loop() {
        // The speed loop is not on it: its current reference is a delayed input.
        assert_eq!(
            critical_path(&plan("four-process")).unwrap(),
            ["plant", "observer", "current-loop"]
        );
        assert_eq!(
            critical_path(&plan("one-process")).unwrap(),
            ["plant", "observer", "current-loop"]
        );
    }

    #[test]
    fn parts_follow_the_path_and_the_rest_is_what_they_miss() {
        let mut lat = BTreeMap::new();
        for (k, v) in [
            ("cycle", pct(30.0, 50.0)),
            ("plant.lateness", pct(15.0, 30.0)),
            ("plant.exec", pct(1.0, 2.0)),
            ("observer.send", pct(0.5, 1.0)),
            ("observer.wakeup", pct(3.0, 5.0)),
            ("observer.exec", pct(2.0, 3.0)),
            // No stamps for the current loop: one hop part.
            ("current-loop.wake", pct(4.0, 6.0)),
            ("current-loop.exec", pct(1.5, 2.0)),
            ("speed-loop.exec", pct(9.0, 9.0)),
        ] {
            lat.insert(k.to_string(), v);
        }
        let b = budget(&plan("four-process"), &lat).unwrap();
        let names: Vec<&str> = b.parts.iter().map(|p| p.part.as_str()).collect();
        assert_eq!(
            names,
            [
                "plant timer wake-up",
                "plant execution",
                "plant publish",
                "observer wake-up",
                "observer execution",
                "observer → current-loop publish and wake-up",
                "current-loop execution"
            ]
        );
        assert_eq!(b.sum_p50_us, 27.0);
        assert_eq!(b.rest_p50_us, 3.0);
        assert!(markdown(&b).contains("| plant publish | 0.5 | 1.0 |"));
        // In one process there are no hops, only executions.
        let one = budget(&plan("one-process"), &lat).unwrap();
        assert_eq!(one.parts.len(), 4);
        // Not a real-time run: no cycle, no budget.
        lat.remove("cycle");
        assert!(budget(&plan("four-process"), &lat).is_none());
    }
}
