//! Property tests of what comes from outside: scenario files, and the messages every stage
//! takes from the bus. No input may panic, and no finite garbage on the bus may steer the
//! plant past its limits (the voltage vector past V_dc/√3, i_q* past its limit).

use drivelab_runtime::config::Scenario;
use drivelab_runtime::messages::*;
use drivelab_runtime::stage::{Inbox, Msg, Outbox, TopicId};
use proptest::prelude::*;

const SCENARIOS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenarios");

/// The shipped scenario files, as (name, text).
fn shipped() -> Vec<(String, String)> {
    let mut v: Vec<(String, String)> = std::fs::read_dir(SCENARIOS)
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .map(|p| {
            (
                p.file_stem().unwrap().to_string_lossy().into_owned(),
                std::fs::read_to_string(&p).unwrap(),
            )
        })
        .collect();
    v.sort();
    assert!(v.len() >= 10, "shipped scenarios not found in {SCENARIOS}");
    v
}

/// Lines of the form `key = NUMBER` (comments allowed after), as line indices.
fn numeric_lines(text: &str) -> Vec<usize> {
    text.lines()
        .enumerate()
        .filter(|(_, l)| {
            l.split_once('=').is_some_and(|(k, v)| {
                !k.contains('[') && v.split('#').next().unwrap().trim().parse::<f64>().is_ok()
            })
        })
        .map(|(i, _)| i)
        .collect()
}

/// Values a user (or a fuzzer) might write where a number belongs.
fn odd_value() -> impl Strategy<Value = String> {
    prop_oneof![
        any::<f64>().prop_map(|x| format!("{x:e}")),
        any::<i64>().prop_map(|x| x.to_string()),
        (-1e3f64..1e3).prop_map(|x| format!("{x}")),
        Just("nan".to_string()),
        Just("inf".to_string()),
        Just("-inf".to_string()),
        Just("1e400".to_string()),
        Just("-0.0".to_string()),
        Just("0".to_string()),
        Just("\"text\"".to_string()),
        Just("[]".to_string()),
        Just("{}".to_string()),
    ]
}

/// A scenario that parsed is usable: its design, plant and stages can be made without a
/// panic.
fn use_it(sc: &Scenario) {
    let _ = drivelab_runtime::drive::DriveDesign::from_scenario(sc);
    let _ = drivelab_runtime::drive::Plant::new(sc);
    for name in drivelab_runtime::config::SERVICES {
        let _ = drivelab_runtime::stages::builtin(name, sc);
    }
    let _ = sc.samples();
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, failure_persistence: None, ..ProptestConfig::default() })]

    #[test]
    fn a_scenario_with_any_value_in_any_numeric_field_parses_or_is_refused(
        which in any::<prop::sample::Index>(),
        line in any::<prop::sample::Index>(),
        value in odd_value(),
    ) {
        let all = shipped();
        let (name, text) = &all[which.index(all.len())];
        let lines = numeric_lines(text);
        prop_assume!(!lines.is_empty());
        let target = lines[line.index(lines.len())];
        let edited: String = text
            .lines()
            .enumerate()
            .map(|(i, l)| {
                if i == target {
                    let (k, _) = l.split_once('=').unwrap();
                    format!("{k}= {value}\n")
                } else {
                    format!("{l}\n")
                }
            })
            .collect();
        match Scenario::from_toml(&edited, name) {
            Ok(sc) => use_it(&sc),
            Err(e) => {
                prop_assert!(!e.is_empty());
                prop_assert!(!e.contains('\n'), "not one line: {e}");
            }
        }
    }

    #[test]
    fn any_text_as_a_scenario_is_a_one_line_error_or_a_scenario(text in ".{0,400}") {
        match Scenario::from_toml(&text, "fuzz") {
            Ok(sc) => use_it(&sc),
            Err(e) => prop_assert!(!e.contains('\n'), "not one line: {e}"),
        }
    }
}

/// Finite garbage: ordinary values, huge ones and the extremes of f64.
fn garbage() -> impl Strategy<Value = f64> {
    prop_oneof![
        -1e3f64..1e3,
        -1e12f64..1e12,
        any::<f64>().prop_filter("finite", |x| x.is_finite()),
        Just(f64::MAX),
        Just(f64::MIN),
        Just(f64::MIN_POSITIVE),
    ]
}

/// One step's inputs: every topic's message with garbage fields and index, fresh or stale.
fn inbox() -> impl Strategy<Value = (Vec<f64>, Vec<u64>, Vec<bool>)> {
    (
        prop::collection::vec(garbage(), 24),
        prop::collection::vec(any::<u64>(), 5),
        prop::collection::vec(any::<bool>(), 5),
    )
}

fn header(k: u64) -> Header {
    Header {
        k,
        ..Default::default()
    }
}

fn fill(ib: &mut Inbox, v: &[f64], ks: &[u64], fresh: &[bool]) {
    let msgs = [
        Msg::Meas(Measurement {
            hdr: header(ks[0]),
            i_abc: [v[0], v[1], v[2]],
            theta_m_enc: v[3],
            u_ab_applied: [v[4], v[5]],
        }),
        Msg::Est(Estimate {
            hdr: header(ks[1]),
            theta_e: v[6],
            omega_m: v[7],
        }),
        Msg::Iref(CurrentRef {
            hdr: header(ks[2]),
            omega_ref: v[8],
            i_d_ref: v[9],
            i_q_ref: v[10],
        }),
        Msg::Cmd(VoltageCommand {
            hdr: header(ks[3]),
            u_ab: [v[11], v[12]],
            u_dq: [v[13], v[14]],
            i_dq_ref: [v[15], v[16]],
            omega_ref: v[17],
            omega_hat: v[18],
            theta_hat: v[19],
        }),
        Msg::Wref(SpeedRef {
            hdr: header(ks[4]),
            omega_ref: v[20],
            theta_m_ref: v[21],
            theta_m: v[22],
        }),
    ];
    for (i, m) in msgs.into_iter().enumerate() {
        ib.put(m);
        if !fresh[i] {
            ib.set_stale(m.topic(), 1 + (ks[i] % 1000));
        }
    }
}

/// Runs `stage` of `scenario` for the given steps of garbage and checks its outputs.
///
/// What each stage must publish (stages.rs): the plant a measurement at every step; the
/// observer an estimate and the current loop a command whenever the measurement is fresh;
/// the speed loop a current reference whenever the estimate is fresh and its index a speed
/// sample (k mod speed_divider = 0). On other steps the speed loop may hold its last output,
/// and the observer's estimate is only required to come without a panic. The first step of
/// every case has a fresh measurement and a fresh estimate of a speed sample, so each stage
/// publishes at least once and every case checks at least one output of its stage.
fn steer(
    scenario: &str,
    stage: &str,
    steps: &[(Vec<f64>, Vec<u64>, Vec<bool>)],
) -> Result<(), TestCaseError> {
    let (sc, _) = Scenario::load(&format!("{SCENARIOS}/{scenario}.toml")).unwrap();
    let mut s = drivelab_runtime::stages::builtin(stage, &sc).unwrap();
    let u_max = sc.u_max();
    let i_max = sc.i_q_max();
    let divider = u64::from(sc.rates.speed_divider);
    let (mut checked, mut published) = (0usize, 0usize);
    for (k, (v, ks, fresh)) in steps.iter().enumerate() {
        let (mut ks, mut fresh) = (ks.clone(), fresh.clone());
        if k == 0 {
            fresh[0] = true;
            fresh[1] = true;
            ks[1] -= ks[1] % divider;
        }
        let mut ib = Inbox::default();
        fill(&mut ib, v, &ks, &fresh);
        let mut out = Outbox::default();
        s.step(k as u64 + 1, &ib, &mut out);
        s.after_publish();
        let (topic, must) = match stage {
            "plant" => (TopicId::Meas, true),
            "observer" => (TopicId::Est, fresh[0]),
            "current-loop" => (TopicId::Cmd, fresh[0]),
            "speed-loop" => (TopicId::Iref, fresh[1] && ks[1] % divider == 0),
            _ => unreachable!("{stage}"),
        };
        prop_assert!(
            !must || out.get(topic).is_some(),
            "{stage} of {scenario} published no {topic:?} at step {k}"
        );
        published += usize::from(out.get(topic).is_some());
        if let Some(Msg::Cmd(c)) = out.get(TopicId::Cmd) {
            // The voltage a controller commands stays finite and within V_dc/√3.
            let u = c.u_ab[0].hypot(c.u_ab[1]);
            prop_assert!(
                u.is_finite() && u <= u_max * (1.0 + 1e-9),
                "{stage} of {scenario}: |u_ab| = {u} V > {u_max} V"
            );
            checked += 1;
        }
        if let Some(Msg::Iref(r)) = out.get(TopicId::Iref) {
            prop_assert!(
                r.i_q_ref.is_finite() && r.i_q_ref.abs() <= i_max * (1.0 + 1e-9),
                "{stage} of {scenario}: i_q* = {} A, limit {i_max} A",
                r.i_q_ref
            );
            checked += 1;
        }
        if let Some(Msg::Meas(m)) = out.get(TopicId::Meas) {
            let u = m.u_ab_applied[0].hypot(m.u_ab_applied[1]);
            prop_assert!(
                u.is_finite() && u <= u_max * (1.0 + 1e-9),
                "plant of {scenario}: applied |u_ab| = {u} V > {u_max} V"
            );
            checked += 1;
        }
    }
    // Every case published; the stages that steer the plant had a bound checked.
    prop_assert!(published > 0, "{stage} of {scenario} published nothing");
    if stage != "observer" {
        prop_assert!(checked > 0, "{stage} of {scenario}: no output checked");
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 128, failure_persistence: None, ..ProptestConfig::default() })]

    #[test]
    fn finite_garbage_never_steers_the_plant_past_its_limits(
        steps in prop::collection::vec(inbox(), 1..12),
        scenario in prop::sample::select(vec!["kyslan-pi", "kyslan-nl", "low-rst-sensorless", "miyajima-polar-400rpm"]),
        stage in prop::sample::select(vec!["plant", "observer", "current-loop", "speed-loop"]),
    ) {
        steer(scenario, stage, &steps)?;
    }
}
