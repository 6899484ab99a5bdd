//! Expectations and campaigns, as a CI job uses them: exit codes, summary.json →
//! expectations, and the shipped smoke campaign end to end with its junit.xml read back by
//! an independent XML parser.

mod common;

use common::*;
use serde_json::Value;
use std::path::{Path, PathBuf};

const CAMPAIGNS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../campaigns");

fn stderr(o: &std::process::Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// `drivelab run --clock inprocess --no-plots --duration 0.05 --out OUT EXTRA`: the same
/// maths as the drive, deterministic and fast.
fn inprocess(out: &Path, extra: &[&str]) -> std::process::Output {
    inprocess_for("0.05", out, extra)
}

/// [`inprocess`] for `seconds`.
fn inprocess_for(seconds: &str, out: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec![
        "run",
        "--clock",
        "inprocess",
        "--duration",
        seconds,
        "--no-plots",
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    drivelab(&args)
}

#[test]
fn a_failed_expectation_exits_3_with_one_line_and_the_run_is_kept() {
    let dir = scratch("expect3");
    let out = dir.join("run");
    // Kyslan et al. design for an 8 ms rise; the peak |i_dq| is at least the 1.6 A of the
    // i_d step, so `< 0` must fail.
    let o = inprocess(
        &out,
        &[
            "--expect",
            "metrics.rise_time_ms in 7.2..8.8",
            "--expect",
            "peak_current_a < 0",
            "--expect",
            "faults.*.speed_recovered_ms <= 200",
        ],
    );
    assert_eq!(o.status.code(), Some(3), "{}", stderr(&o));
    let err = stderr(&o);
    let lines: Vec<&str> = err
        .lines()
        .filter(|l| l.contains("expectation failed"))
        .map(str::trim)
        .collect();
    assert_eq!(lines.len(), 1, "{}", stderr(&o));
    assert!(
        lines[0].starts_with("drivelab: expectation failed: peak_current_a < 0: peak_current_a = "),
        "{}",
        lines[0]
    );
    let s = summary(&out);
    let e = s["expectations"].as_array().unwrap();
    assert_eq!(e.len(), 3);
    let peak = s["peak_current_a"].as_f64().unwrap();
    assert!(peak >= 1.6, "peak |i_dq| {peak} A below the 1.6 A i_d step");
    assert_eq!(e[1]["values"][0]["value"].as_f64(), Some(peak));
    assert_eq!(
        e.iter()
            .map(|x| x["pass"].as_bool().unwrap())
            .collect::<Vec<_>>(),
        [true, false, true],
        "{e:?}"
    );
    // The figure the rise-time expectation checked is the run's metric.
    assert_eq!(e[0]["values"][0]["value"], s["metrics"]["rise_time_ms"]);
    assert!(out.join("trace.csv").is_file());
}

/// A speed recovery that the run's end cut short (the speed back in its band for less than
/// the 10 ms it must stay there) is null with that reason, not "never recovered"; a time
/// counted in samples is its exact decimal, so an inclusive limit at it holds.
#[test]
fn a_recovery_the_runs_end_cut_says_so_and_sample_times_are_their_decimals() {
    let dir = scratch("cutbyend");
    let out = dir.join("run");
    let o = inprocess_for(
        "0.2",
        &out,
        &[
            "--fault",
            "stop:observer@0.19:0.001",
            "--expect",
            "faults.*.speed_recovered_ms <= 200",
        ],
    );
    assert_eq!(o.status.code(), Some(3), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("faults.0.speed_recovered_ms = null (the run ended ")
            && stderr(&o).contains("before the 10 ms it must stay there)"),
        "{}",
        stderr(&o)
    );
    let s = summary(&out);
    let rec = s["metrics"]["load_recovery_ms"]
        .as_f64()
        .expect("load recovery");
    // 10 kHz: a whole number of 0.1 ms samples after the load step, as that decimal.
    assert_eq!(rec.to_string(), format!("{rec:.1}"));
    let exact = format!("metrics.load_recovery_ms in {rec}..{rec}");
    let o = inprocess_for("0.2", &dir.join("again"), &["--expect", &exact]);
    assert!(o.status.success(), "{}", stderr(&o));
}

#[test]
fn all_expectations_met_exit_0_and_a_scenarios_own_are_checked_first() {
    let dir = scratch("expect0");
    let sc = variant(
        "expect0",
        "kyslan-pi",
        &[(
            "[motor]",
            "[[expect]]\ncheck = \"peak_current_a <= 100\"\nnote = \"far above the 1.6 A limit\"\n\n[motor]",
        )],
    );
    let out = dir.join("run");
    let o = inprocess(
        &out,
        &[
            "--scenario",
            sc.to_str().unwrap(),
            "--expect",
            "samples_missing == 0",
        ],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let e = summary(&out)["expectations"].clone();
    assert_eq!(e[0]["expect"], "peak_current_a <= 100");
    assert_eq!(e[0]["note"], "far above the 1.6 A limit");
    assert_eq!(e[1]["expect"], "samples_missing == 0");
    assert!(e.as_array().unwrap().iter().all(|x| x["pass"] == true));
    // Said on stdout, so that a CI log tells "checked and met" from "not checked".
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout
            .lines()
            .any(|l| l == "expectations: 2 of 2 met; each in summary.json → expectations"),
        "{stdout}"
    );
}

#[test]
fn malformed_expectations_are_refused_before_anything_runs() {
    let dir = scratch("expect2");
    let out = dir.join("run");
    for (expr, says) in [
        ("peak_curent_a <= 8", "unknown figure 'peak_curent_a'"),
        // A run without faults would hold it (nothing to check): refused by name instead.
        (
            "faults.*.speed_recoverd_ms <= 200",
            "unknown fault figure 'speed_recoverd_ms'",
        ),
        ("peak_current_a <= NaN", "must be a finite number"),
        ("peak_current_a", "expected FIGURE OP LIMIT"),
    ] {
        let o = inprocess(&out, &["--expect", expr]);
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{expr}: {err}");
        assert_eq!(err.trim().lines().count(), 1, "{err}");
        assert!(err.contains(says), "{expr}: {err}");
        assert!(!out.exists(), "a run folder was made for a bad expectation");
    }
    // In a scenario's [[expect]] table it is a mistake in the file: exit code 1, as for
    // any other bad key of a scenario (and as in a campaign).
    let sc = variant(
        "expect2",
        "kyslan-pi",
        &[(
            "[motor]",
            "[[expect]]\ncheck = \"peak_current_a =< 8\"\n\n[motor]",
        )],
    );
    let out = dir.join("out-table");
    let o = drivelab(&[
        "run",
        "--clock",
        "inprocess",
        "--scenario",
        sc.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert_eq!(stderr(&o).trim().lines().count(), 1, "{}", stderr(&o));
    assert!(stderr(&o).contains("[[expect]] #1"), "{}", stderr(&o));
    assert!(
        !out.exists(),
        "a run folder was made for a bad [[expect]] table"
    );
}

/// Writes a campaign file into `dir`.
fn campaign_file(dir: &Path, text: &str) -> PathBuf {
    let f = dir.join("c.toml");
    std::fs::write(&f, text).unwrap();
    f
}

/// A lockstep campaign file named `name` of three 0.05 s kyslan-pi runs: no fault, a kill of
/// the observer, and `third`; `extra` adds lines.
fn three_lockstep_runs(dir: &Path, name: &str, third: &str, extra: &str) -> PathBuf {
    campaign_file(
        dir,
        &format!(
            "name = \"{name}\"\nscenarios = [\"kyslan-pi\"]\nclock = \"lockstep\"\nduration_s = 0.05\n\
             {extra}faults = [[], [\"kill:observer@0.02\"], [\"{third}\"]]\n"
        ),
    )
}

/// `drivelab campaign FILE --out OUT`.
fn campaign(file: &Path, out: &Path) -> std::process::Output {
    drivelab(&[
        "campaign",
        file.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ])
}

/// The testcase elements of a junit.xml, as (name, failures, errors, properties).
type Case = (String, usize, usize, Vec<(String, String)>);

/// Reads junit.xml with roxmltree (not the writer's library) and checks that the suite's
/// counts are those of its test cases.
fn junit(path: &Path) -> (roxmltree::Node<'static, 'static>, Vec<Case>) {
    let text: &'static str = Box::leak(String::from_utf8(read(path)).unwrap().into_boxed_str());
    let doc: &'static roxmltree::Document = Box::leak(Box::new(
        roxmltree::Document::parse(text).expect("well-formed XML"),
    ));
    let suites = doc.root_element();
    assert_eq!(suites.tag_name().name(), "testsuites");
    let suite = suites
        .children()
        .find(|n| n.has_tag_name("testsuite"))
        .expect("a testsuite");
    let cases: Vec<Case> = suite
        .children()
        .filter(|n| n.has_tag_name("testcase"))
        .map(|tc| {
            let props = tc
                .descendants()
                .filter(|n| n.has_tag_name("property"))
                .map(|p| {
                    (
                        p.attribute("name").unwrap().to_string(),
                        p.attribute("value").unwrap().to_string(),
                    )
                })
                .collect();
            (
                tc.attribute("name").unwrap().to_string(),
                tc.children().filter(|n| n.has_tag_name("failure")).count(),
                tc.children().filter(|n| n.has_tag_name("error")).count(),
                props,
            )
        })
        .collect();
    let attr = |n: roxmltree::Node, a: &str| n.attribute(a).unwrap().parse::<usize>().unwrap();
    for n in [suites, suite] {
        assert_eq!(attr(n, "tests"), cases.len());
        assert_eq!(
            attr(n, "failures"),
            cases.iter().filter(|c| c.1 > 0).count()
        );
        assert_eq!(attr(n, "errors"), cases.iter().filter(|c| c.2 > 0).count());
    }
    (suite, cases)
}

#[test]
fn the_smoke_campaign_reports_every_run_in_json_markdown_and_junit() {
    let _one = serial();
    let dir = scratch("smoke");
    let out = dir.join("c");
    let file = Path::new(CAMPAIGNS).join("smoke.toml");
    let o = campaign(&file, &out);
    let report: Value = serde_json::from_slice(&read(&out.join("campaign.json"))).unwrap();
    let runs = report["runs"].as_array().unwrap();
    // kyslan-pi × four fault sets × one seed.
    assert_eq!(runs.len(), 4, "{}", stderr(&o));
    let status: Vec<&str> = runs.iter().map(|r| r["status"].as_str().unwrap()).collect();
    assert!(!status.contains(&"error"), "{status:?}: {}", stderr(&o));
    // The exit code follows the runs: 3 when an expectation failed, 0 when all passed.
    let expected = if status.contains(&"fail") { 3 } else { 0 };
    assert_eq!(o.status.code(), Some(expected), "{status:?}");
    // What must pass whatever the machine's load: the run without a fault (it has no fault
    // figure, and its current is the drive's own), and in every run the current bound, which
    // the restart's duration does not move (kill:current-loop 2.73 A, kill:speed-loop
    // 2.26-2.36 A, kill:observer 1.93 A with a simulated restart of 40 ms to 2 s, lockstep).
    // Tolerated: the `faults.*` expectations of the faulted runs, which are wall-clock
    // figures of this real-time campaign (the speed recovery includes the killed process's
    // restart, 0.8 s seen on a loaded machine; the detection is a scheduling latency); a
    // failure there must still be counted and reported consistently (checked below), and it
    // is named in a NOT CHECKED line. That each real-time kill is detected, made safe and
    // recovered is checked in tests/faults.rs (`sigkill_of_each_service_…`, 1.7 s after it).
    assert_eq!(runs[0]["faults"], serde_json::json!([]), "{}", runs[0]);
    for r in runs {
        for x in r["expectations"].as_array().unwrap() {
            if x["pass"] == false {
                let what = x["expect"].as_str().unwrap();
                assert!(
                    what.starts_with("faults.*."),
                    "only the wall-clock fault figures may fail: {x}"
                );
                not_checked(
                    "the_smoke_campaign_reports_every_run_in_json_markdown_and_junit",
                    &format!(
                        "the run with {} missed '{what}' ({}): a wall-clock figure, tolerated here",
                        r["faults"], x["values"]
                    ),
                );
            }
        }
    }
    assert_eq!(runs[0]["status"], "pass", "{}", runs[0]);
    for r in runs {
        let e = r["expectations"].as_array().unwrap();
        let current = e
            .iter()
            .find(|x| x["expect"] == "peak_current_a <= 3.2")
            .unwrap_or_else(|| panic!("no current expectation: {r}"));
        assert_eq!(current["pass"], true, "{r}");
        // No process died but by the injected kill, whatever the load.
        let crashes = e.iter().find(|x| x["expect"] == "crashes == 0");
        assert_eq!(crashes.map(|x| &x["pass"]), Some(&Value::Bool(true)), "{r}");
        // Each fault expectation was evaluated on the run's one fault, not on nothing.
        let n_faults = r["faults"].as_array().unwrap().len();
        for x in e.iter().filter(|x| {
            x["expect"]
                .as_str()
                .is_some_and(|s| s.starts_with("faults.*."))
        }) {
            assert_eq!(x["values"].as_array().unwrap().len(), n_faults, "{x}");
        }
    }
    let (_, cases) = junit(&out.join("junit.xml"));
    assert_eq!(cases.len(), 4);
    for (r, case) in runs.iter().zip(&cases) {
        let run = PathBuf::from(r["out"].as_str().unwrap());
        let s = summary(&run);
        assert_clean(s["bus"].as_str().unwrap());
        // The run's own summary says the same as the campaign: each expectation's verdict,
        // re-counted here from its values.
        let e = s["expectations"].as_array().unwrap();
        assert_eq!(e.len(), 4, "the campaign's four expectations");
        let failed = e.iter().filter(|x| x["pass"] == false).count();
        for x in e {
            let values = x["values"].as_array().unwrap();
            let all = values.iter().all(|v| v["pass"] == true);
            let empty_list = values.is_empty() && s["faults"].as_array().unwrap().is_empty();
            assert_eq!(
                x["pass"] == true,
                (all && !values.is_empty()) || empty_list,
                "{x}"
            );
        }
        assert_eq!(case.1, failed, "junit failures of {}", case.0);
        assert_eq!(r["status"] == "fail", failed > 0);
        // Figures as properties, equal to the summary's (to the table's rounding).
        let prop = |k: &str| case.3.iter().find(|p| p.0 == k).map(|p| p.1.clone());
        let peak: f64 = prop("peak_current_a").unwrap().parse().unwrap();
        assert!((peak - s["peak_current_a"].as_f64().unwrap()).abs() <= 0.05);
        assert_eq!(prop("run_folder").unwrap(), run.display().to_string());
        // The faulted runs injected what the campaign asked for.
        let faults = r["faults"].as_array().unwrap();
        assert_eq!(s["faults"].as_array().unwrap().len(), faults.len());
        assert!(case.0.starts_with("kyslan-pi ["), "{}", case.0);
    }
    let md = String::from_utf8(read(&out.join("campaign.md"))).unwrap();
    assert_eq!(
        md.lines()
            .filter(|l| l.starts_with("| ") && !l.starts_with("| #"))
            .count(),
        4
    );
    assert!(
        md.contains("| 2 | kyslan-pi | kill:current-loop@0.3 | 1 |"),
        "{md}"
    );
}

#[test]
fn a_campaign_whose_expectations_fail_exits_3_and_junit_counts_each_failure() {
    let dir = scratch("fail3");
    let f = campaign_file(
        &dir,
        "name = \"always-fails\"\nscenarios = [\"kyslan-pi\"]\nclock = \"lockstep\"\n\
         duration_s = 0.05\nfaults = [[], [\"stop:observer@0.02:0.005\"]]\n\
         expect = [\"peak_current_a < 0\", \"samples_missing == 0\"]\n",
    );
    let out = dir.join("c");
    let o = campaign(&f, &out);
    assert_eq!(o.status.code(), Some(3), "{}", stderr(&o));
    // Each failed run has its line on stderr also where it is not a terminal (as in CI,
    // and here), where the progress bar is hidden.
    let err = stderr(&o);
    for line in [
        "run 1: fail — kyslan-pi [no fault] seed 1",
        "run 2: fail — kyslan-pi [stop:observer@0.02:0.005] seed 1",
    ] {
        assert!(err.lines().any(|l| l == line), "'{line}' not in: {err}");
    }
    let (suite, cases) = junit(&out.join("junit.xml"));
    assert_eq!(suite.attribute("name"), Some("always-fails"));
    assert_eq!(cases.len(), 2);
    assert!(cases.iter().all(|c| c.1 == 1 && c.2 == 0), "{cases:?}");
    let failure = suite
        .descendants()
        .find(|n| n.has_tag_name("failure"))
        .unwrap();
    assert!(
        failure
            .attribute("message")
            .unwrap()
            .starts_with("expectation failed: peak_current_a < 0: peak_current_a = "),
        "{:?}",
        failure.attribute("message")
    );
    for c in &cases {
        let run = PathBuf::from(&c.3.iter().find(|p| p.0 == "run_folder").unwrap().1);
        assert_clean(summary(&run)["bus"].as_str().unwrap());
    }
}

#[test]
fn a_campaigns_topology_file_is_read_beside_the_campaign_not_from_the_working_folder() {
    let dir = scratch("topobeside");
    let shipped = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../scenarios/topologies/two-process.toml"
    );
    let text = std::fs::read_to_string(shipped).unwrap();
    assert!(text.contains("name = \"controller\""));
    // A process name that only this copy has, so that the run shows which file it used.
    std::fs::write(
        dir.join("beside.toml"),
        text.replace("name = \"controller\"", "name = \"beside-controller\""),
    )
    .unwrap();
    let f = campaign_file(
        &dir,
        "name = \"beside\"\nscenarios = [\"kyslan-pi\"]\nclock = \"lockstep\"\n\
         duration_s = 0.05\ntopology = \"beside.toml\"\n",
    );
    let out = dir.join("c");
    // The test's working folder is the crate's, which has no beside.toml.
    assert!(!Path::new("beside.toml").exists());
    let o = campaign(&f, &out);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let report: Value = serde_json::from_slice(&read(&out.join("campaign.json"))).unwrap();
    let run = PathBuf::from(report["runs"][0]["out"].as_str().unwrap());
    let s = summary(&run);
    let mut procs: Vec<&String> = s["processes"].as_object().unwrap().keys().collect();
    procs.sort();
    assert_eq!(procs, ["beside-controller", "plant"]);
    assert_clean(s["bus"].as_str().unwrap());
}

/// `audit_syscalls = true`: every run counts its loops' calls beyond their waits, and an
/// expectation on the count decides the run (a lockstep drive's loops make none).
#[test]
fn an_audited_campaign_holds_each_run_to_its_loops_system_calls() {
    let dir = scratch("audited");
    let f = campaign_file(
        &dir,
        "name = \"audited\"\nscenarios = [\"kyslan-pi\"]\nclock = \"lockstep\"\n\
         duration_s = 0.05\naudit_syscalls = true\nexpect = [\"stray_syscalls == 0\"]\n",
    );
    let out = dir.join("c");
    let o = campaign(&f, &out);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let (_, cases) = junit(&out.join("junit.xml"));
    assert_eq!(cases.len(), 1);
    let run = PathBuf::from(&cases[0].3.iter().find(|p| p.0 == "run_folder").unwrap().1);
    let s = summary(&run);
    assert_eq!(s["stray_syscalls"], 0, "{}", s["processes"]);
    assert_clean(s["bus"].as_str().unwrap());
}

#[test]
fn a_bad_campaign_is_a_one_line_error_before_any_run() {
    let dir = scratch("badcampaign");
    for (text, code, says) in [
        ("name = \"x\"\nscenarios = [\"kyslan-pi\"]\nsed = [1]\n", 1, "unknown field `sed`"),
        ("name = \"x\"\nscenarios = [\"nope\"]\n", 1, "nope"),
        (
            "name = \"x\"\nscenarios = [\"kyslan-pi\"]\nfaults = [[\"explode:plant@1\"]]\n",
            1,
            "unknown fault kind 'explode'",
        ),
        (
            "name = \"x\"\nscenarios = [\"kyslan-pi\"]\nexpect = [\"peak <= 1\"]\n",
            1,
            "c.toml: expect: expectation 'peak <= 1': unknown figure 'peak'",
        ),
        // Checked against each scenario before the first run, not as a failed run.
        (
            "name = \"x\"\nscenarios = [\"kyslan-pi\"]\nfaults = [[], [\"kill:plant@500\"]]\n",
            1,
            "kyslan-pi [kill:plant@500] seed 1: fault 'kill:plant@500' is at or after the end of the run (0.1 s)",
        ),
        (
            "name = \"x\"\nscenarios = [\"kyslan-pi\"]\nseeds = [1, 2]\nfaults = [[\"stop:nobody@0.05:0.01\"]]\n",
            1,
            "unknown stage 'nobody' (this drive's stages: plant, observer, current-loop, speed-loop)",
        ),
        (
            "name = \"x\"\nscenarios = [\"kyslan-pi\"]\n[sweep]\nkinds = [\"melt\"]\nstages = [\"plant\"]\nat_s = [0.1]\n",
            1,
            "kind 'melt'",
        ),
        // The same fault written two ways is the same run: both spellings named.
        (
            "name = \"x\"\nscenarios = [\"kyslan-pi\"]\nfaults = [[\"kill:plant@0.05\"], [\"kill:plant@0.050\"]]\n",
            1,
            "the fault sets [kill:plant@0.05] and [kill:plant@0.050] are the same faults written two ways",
        ),
        (
            "name = \"x\"\nscenarios = [\"kyslan-pi\"]\nfaults = [[\"kill:plant@0.05\", \"stop:observer@0.07:0.01s\"], [\"stop:observer@0.07:0.010\", \"kill:plant@0.05s\"]]\n",
            1,
            "the fault sets [kill:plant@0.05, stop:observer@0.07:0.01s] and [stop:observer@0.07:0.010, kill:plant@0.05s] are the same faults",
        ),
        // The inprocess clock starts no host whose loop could be audited.
        (
            "name = \"x\"\nscenarios = [\"kyslan-pi\"]\nclock = \"inprocess\"\naudit_syscalls = true\n",
            1,
            "--audit-syscalls audits the stage hosts' loops",
        ),
        // One scenario file named two ways.
        (
            &format!("name = \"x\"\nscenarios = [\"kyslan-pi\", \"{SCENARIOS}/kyslan-pi.toml\"]\n"),
            1,
            "scenarios: 'kyslan-pi' and ",
        ),
        // A [sweep] makes `kill:plant@0.1`.
        (
            "name = \"x\"\nscenarios = [\"kyslan-pi\"]\nfaults = [[\"kill:plant@0.10\"]]\n[sweep]\nkinds = [\"kill\"]\nstages = [\"plant\"]\nat_s = [0.1]\n",
            1,
            "the fault sets [kill:plant@0.10] and [kill:plant@0.1] are the same faults",
        ),
    ] {
        let f = campaign_file(&dir, text);
        let out = dir.join("c");
        let o = drivelab(&["campaign", f.to_str().unwrap(), "--out", out.to_str().unwrap()]);
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(code), "{text}: {err}");
        assert_eq!(err.trim().lines().count(), 1, "{err}");
        assert!(err.contains(says), "{text}: {err}");
        assert!(!out.exists(), "{text}: the campaign started");
    }
}

#[test]
fn a_malformed_expectation_in_a_campaign_is_a_file_error_with_exit_code_1() {
    let dir = scratch("campexpect");
    // A scenario file of the campaign with a malformed [[expect]] table.
    let sc = variant(
        "campexpect",
        "kyslan-pi",
        &[(
            "[motor]",
            "[[expect]]\ncheck = \"peak_current_a =< 8\"\n\n[motor]",
        )],
    );
    let sc_line = format!("name = \"x\"\nscenarios = [{:?}]\n", sc.to_str().unwrap());
    for (text, says) in [
        (
            "name = \"x\"\nscenarios = [\"kyslan-pi\"]\nexpect = [\"garbage\"]\n",
            "c.toml: expect: expectation 'garbage': expected FIGURE OP LIMIT",
        ),
        (
            "name = \"x\"\nscenarios = [\"kyslan-pi\"]\nexpect = [\"peak_current_a <= NaN\"]\n",
            "c.toml: expect: expectation 'peak_current_a <= NaN': limit 'NaN' must be a finite number",
        ),
        (
            sc_line.as_str(),
            "[[expect]] #1: expectation 'peak_current_a =< 8': unknown operator",
        ),
    ] {
        let f = campaign_file(&dir, text);
        let out = dir.join("c");
        let o = drivelab(&["campaign", f.to_str().unwrap(), "--out", out.to_str().unwrap()]);
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(1), "{text}: {err}");
        assert_eq!(err.trim().lines().count(), 1, "{err}");
        assert!(err.starts_with("drivelab: error: campaign "), "{text}: {err}");
        assert!(err.contains(says), "{text}: {err}");
        assert!(!out.exists(), "{text}: the campaign started");
    }
    // The same expectation on the command line stays a usage error.
    let out = dir.join("run");
    let o = inprocess(&out, &["--expect", "garbage"]);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(!out.exists(), "a run folder was made for a bad expectation");
}

/// Starts a campaign of `runs` real-time runs of 30 s each (`--no-rt`) in scratch folder
/// `tag`, its output piped; returns it and its report folder.
fn long_campaign(tag: &str, runs: usize) -> (std::process::Child, PathBuf) {
    let dir = scratch(tag);
    let seeds: Vec<String> = (1..=runs).map(|s| s.to_string()).collect();
    let f = campaign_file(
        &dir,
        &format!(
            "name = \"x\"\nscenarios = [\"kyslan-pi\"]\nduration_s = 30\nseeds = [{}]\n",
            seeds.join(", ")
        ),
    );
    let out = dir.join("c");
    let child = std::process::Command::new(DRIVELAB)
        .args(["campaign", f.to_str().unwrap(), "--out"])
        .arg(&out)
        .arg("--no-rt")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    (child, out)
}

#[test]
fn a_campaign_stopped_by_sigint_says_so_in_one_line_and_reports_the_rest_skipped() {
    let _one = serial();
    let (child, out) = long_campaign("campsigint", 3);
    // The bus of the campaign's first run (see campaign::options).
    let bus = format!("c{}_1", child.id());
    let pid = child.id() as i32;
    let drive = Drive::on_bus(child, &bus);
    wait_for_progress(&bus, 1);
    // SAFETY: signalling a child process we spawned.
    unsafe { libc::kill(pid, libc::SIGINT) };
    let o = drive.wait_for_exit(std::time::Duration::from_secs(60), "campaign after SIGINT");
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{err}");
    let lines: Vec<&str> = err.lines().filter(|l| l.starts_with("drivelab:")).collect();
    assert_eq!(lines.len(), 1, "{err}");
    for says in [
        "drivelab: error: campaign interrupted (SIGINT) during run 1 of 3: ",
        "interrupted (SIGINT): drive stopped",
        "2 of 3 runs skipped",
    ] {
        assert!(lines[0].contains(says), "'{says}' not in: {}", lines[0]);
    }
    assert_clean(&bus);
    // The table on stdout gives the runs that never started one row.
    let table = String::from_utf8_lossy(&o.stdout);
    let skipped: Vec<&str> = table.lines().filter(|l| l.contains("skipped")).collect();
    assert_eq!(
        skipped,
        [
            "3 runs: 0 passed, 0 failed, 1 errors, 2 skipped.",
            "| 2–3 | 2 runs | – | – | skipped | – | – | – | – | never started |"
        ],
        "{table}"
    );
    // The reports are still written: the stopped run is an error, the others skipped.
    let (suite, cases) = junit(&out.join("junit.xml"));
    assert_eq!(cases.len(), 3);
    assert_eq!(cases[0].2, 1, "run 1 is not an error");
    assert_eq!(suite.attribute("skipped"), Some("2"));
}

/// A campaign SIGKILLed mid-run (a CI job's time limit) leaves its folder marked as a
/// campaign's from its start, so a second campaign takes it, and that one removes the files
/// the dead campaign's bus left (the killed launcher could not).
#[test]
fn a_campaign_killed_mid_run_leaves_a_folder_the_next_one_takes_and_cleans_up_after() {
    let _one = serial();
    let (child, out) = long_campaign("campkill", 2);
    let dir = out.parent().unwrap();
    let bus = format!("c{}_1", child.id());
    // Guarded from here: a watchdog that fires kills the campaign and cleans its bus.
    let drive = Drive::on_bus(child, &bus);
    wait_for_progress(&bus, 1);
    kill_launcher_and_assert_no_orphans(drive, &bus);
    assert!(
        !drivelab_runtime::bus::leftovers(&bus).is_empty(),
        "the killed campaign's bus left no file: nothing to check"
    );
    let report: Value = serde_json::from_slice(&read(&out.join("campaign.json"))).unwrap();
    assert_eq!(report["unfinished"]["runs"], 2, "{report}");
    let short = dir.join("short.toml");
    std::fs::write(
        &short,
        "name = \"y\"\nscenarios = [\"kyslan-pi\"]\nclock = \"lockstep\"\nduration_s = 0.05\n",
    )
    .unwrap();
    let o = campaign(&short, &out);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(0), "{err}");
    assert!(
        err.contains(&format!(
            "an earlier campaign here did not finish; removed the shared-memory files of 1 of its buses (c{}_N)",
            bus.trim_start_matches('c').split('_').next().unwrap()
        )),
        "{err}"
    );
    assert_clean(&bus);
    let report: Value = serde_json::from_slice(&read(&out.join("campaign.json"))).unwrap();
    assert!(report.get("unfinished").is_none(), "{report}");
    assert_eq!(report["name"], "y");
}

#[test]
fn a_campaign_writes_only_into_a_new_empty_or_earlier_campaign_folder_and_replaces_its_runs() {
    let dir = scratch("campout");
    let three = three_lockstep_runs(&dir, "x", "stop:observer@0.02:0.005", "");
    // A folder of other files (a home folder, a source tree) is refused, untouched.
    let other = dir.join("other");
    std::fs::create_dir_all(&other).unwrap();
    std::fs::write(other.join("keep.txt"), "mine").unwrap();
    let o = campaign(&three, &other);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(
        err.contains("not empty and not a campaign's (no campaign.json)"),
        "{err}"
    );
    let names: Vec<_> = std::fs::read_dir(&other)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(names, ["keep.txt"]);
    // An earlier campaign's folder is reused: its runs that the new campaign does not repeat
    // are gone, a file of the user's stays.
    let out = dir.join("c");
    let o = campaign(&three, &out);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    for n in ["001", "002", "003"] {
        assert!(out.join("runs").join(n).join("trace.csv").is_file(), "{n}");
    }
    std::fs::write(out.join("notes.txt"), "mine").unwrap();
    let one = dir.join("one.toml");
    std::fs::write(
        &one,
        "name = \"y\"\nscenarios = [\"kyslan-pi\"]\nclock = \"lockstep\"\nduration_s = 0.05\nseeds = [1]\n",
    )
    .unwrap();
    let o = campaign(&one, &out);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let runs: Vec<_> = std::fs::read_dir(out.join("runs"))
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(runs, ["001"]);
    let report: Value =
        serde_json::from_slice(&std::fs::read(out.join("campaign.json")).unwrap()).unwrap();
    assert_eq!(report["name"], "y");
    assert_eq!(
        std::fs::read_to_string(out.join("notes.txt")).unwrap(),
        "mine"
    );
}

#[test]
fn a_campaign_in_process_simulates_its_kills_and_stops_at_their_samples() {
    // The in-process clock has no processes to signal: it simulates a kill or a stop at its
    // sample, as lockstep does, so a campaign runs it as it runs the others.
    let dir = scratch("inprocess");
    let f = campaign_file(
        &dir,
        "name = \"in-process\"\nscenarios = [\"kyslan-pi\"]\nclock = \"inprocess\"\n\
         duration_s = 0.05\nseeds = [1]\n\
         faults = [[], [\"kill:observer@0.02\"], [\"stop:current-loop@0.02:0.005\"]]\n\
         expect = [\"samples_missing == 0\"]\n",
    );
    let out = dir.join("c");
    let o = campaign(&f, &out);
    assert!(o.status.success(), "{}", stderr(&o));
    let (_, cases) = junit(&out.join("junit.xml"));
    assert_eq!(cases.len(), 3);
    assert!(cases.iter().all(|c| c.1 == 0 && c.2 == 0), "{cases:?}");
    for (case, fault) in cases.iter().zip([None, Some("kill"), Some("stop")]) {
        let run = PathBuf::from(&case.3.iter().find(|p| p.0 == "run_folder").unwrap().1);
        let s = summary(&run);
        assert_eq!(s["clock"], "inprocess");
        let events: Vec<&str> = s["supervisor_events"]
            .as_array()
            .unwrap()
            .iter()
            .map(|e| e["event"].as_str().unwrap())
            .collect();
        match fault {
            None => assert!(events.is_empty(), "{events:?}"),
            Some(kind) => {
                assert_eq!(events, ["inject-simulated"], "{}", case.0);
                let f = s["faults"][0]["fault"].as_str().unwrap();
                assert!(f.starts_with(&format!("{kind}:")), "{f}");
                // At its sample: 0.02 s at 10 kHz.
                assert_eq!(s["faults"][0]["injected_k"], 200, "{}", s["faults"][0]);
            }
        }
    }
}

#[test]
fn a_lockstep_campaign_runs_a_fault_set_without_random_kills_once_not_once_per_seed() {
    let dir = scratch("seedrepeats");
    // Seeds move only random:N kills, and lockstep gives the same trace bytes every time:
    // [] and the kill would be the same run three times each.
    let f = campaign_file(
        &dir,
        "name = \"seeds\"\nscenarios = [\"kyslan-pi\"]\nclock = \"lockstep\"\nduration_s = 0.4\n\
         seeds = [1, 2, 3]\nfaults = [[], [\"kill:observer@0.2\"], [\"random:1\"]]\n",
    );
    let out = dir.join("c");
    let o = campaign(&f, &out);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(0), "{err}");
    let report: Value = serde_json::from_slice(&read(&out.join("campaign.json"))).unwrap();
    let runs: Vec<(String, u64)> = report["runs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            (
                r["faults"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|f| f.as_str().unwrap())
                    .collect::<Vec<_>>()
                    .join("+"),
                r["seed"].as_u64().unwrap(),
            )
        })
        .collect();
    assert_eq!(
        runs,
        [
            ("".to_string(), 1),
            ("kill:observer@0.2".to_string(), 1),
            ("random:1".to_string(), 1),
            ("random:1".to_string(), 2),
            ("random:1".to_string(), 3),
        ],
        "{err}"
    );
    // Said in one line, and in the reports.
    let said: Vec<&str> = err.lines().filter(|l| l.contains("left out")).collect();
    assert_eq!(said.len(), 1, "{err}");
    assert!(
        said[0].contains("4 runs that would differ from another only by a seed"),
        "{err}"
    );
    assert_eq!(report["seed_repeats_left_out"]["runs"], 4, "{report}");
    let md = String::from_utf8(read(&out.join("campaign.md"))).unwrap();
    assert!(md.contains("4 runs that would differ"), "{md}");
    // The seeds of the random kills do move them: the runs kept are not repeats.
    let at: Vec<f64> = report["runs"].as_array().unwrap()[2..]
        .iter()
        .map(|r| {
            summary(Path::new(r["out"].as_str().unwrap()))["faults"][0]["injected_t_s"]
                .as_f64()
                .unwrap()
        })
        .collect();
    assert!(at[0] != at[1] && at[1] != at[2] && at[0] != at[2], "{at:?}");
}

#[test]
fn a_lockstep_campaign_with_standby_twins_says_their_warning_once_before_its_runs_and_each_run_keeps_it(
) {
    let dir = scratch("standbyonce");
    // Three runs of a topology with standby twins, which the lockstep clock does not start.
    let f = three_lockstep_runs(
        &dir,
        "twins",
        "kill:speed-loop@0.02",
        "topology = \"four-process-standby\"\n",
    );
    let out = dir.join("c");
    let o = campaign(&f, &out);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(0), "{err}");
    let said: Vec<&str> = err
        .lines()
        .filter(|l| l.contains("starts no standby twin"))
        .collect();
    assert_eq!(said.len(), 1, "{err}");
    assert!(said[0].starts_with("drivelab: warning: "), "{err}");
    let report: Value = serde_json::from_slice(&read(&out.join("campaign.json"))).unwrap();
    let runs = report["runs"].as_array().unwrap();
    assert_eq!(runs.len(), 3, "{report}");
    for r in runs {
        let s = summary(Path::new(r["out"].as_str().unwrap()));
        let w = s["warnings"].as_array().unwrap();
        assert_eq!(w.len(), 1, "{s}");
        assert!(
            w[0].as_str().unwrap().contains("starts no standby twin"),
            "{s}"
        );
        assert_clean(s["bus"].as_str().unwrap());
    }
    // A campaign whose second scenario has the twins and whose runs all fail an expectation:
    // the warning comes before the first run's line, from the check of every run before
    // the first one starts, not after the first run that has it.
    let plain = std::fs::read_to_string(Path::new(SCENARIOS).join("kyslan-pi.toml")).unwrap();
    let twins =
        std::fs::read_to_string(Path::new(SCENARIOS).join("topologies/four-process-standby.toml"))
            .unwrap();
    let sc = dir.join("twins.toml");
    let body = plain.replacen("name = \"kyslan-pi\"", "name = \"kyslan-pi-twins\"", 1);
    let tables = twins.split_once("[[process]]").unwrap().1;
    std::fs::write(&sc, format!("{body}\n[[process]]{tables}")).unwrap();
    let f = campaign_file(
        &dir,
        &format!(
            "name = \"late-twins\"\nscenarios = [\"kyslan-pi\", {:?}]\nclock = \"lockstep\"\n\
             duration_s = 0.05\nexpect = [\"crashes == 1\"]\n",
            sc.to_str().unwrap()
        ),
    );
    let out = dir.join("late");
    let o = campaign(&f, &out);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(3), "{err}");
    let lines: Vec<&str> = err.lines().collect();
    let warned = lines
        .iter()
        .position(|l| l.contains("starts no standby twin"))
        .unwrap_or_else(|| panic!("no warning: {err}"));
    let run1 = lines
        .iter()
        .position(|l| l.starts_with("run 1: "))
        .unwrap_or_else(|| panic!("no line for run 1: {err}"));
    assert!(warned < run1, "{err}");
    assert!(lines[warned].contains("from run 2"), "{err}");
}

#[test]
fn junit_gives_nulls_with_their_reason_the_scenarios_note_and_whole_counts() {
    let dir = scratch("junitnull");
    // A scenario named with a `|`, which a Markdown table must escape, and an [[expect]]
    // table with a note. A stop of the observer 10 ms before the end: the speed has no time
    // to recover, so its recovery is null.
    let sc = variant(
        "junitnull",
        "kyslan-pi",
        &[(
            "[motor]",
            "[[expect]]\ncheck = \"faults.*.speed_recovered_ms <= 200\"\nnote = \"the drive must be back within 200 ms\"\n\n[motor]",
        )],
    );
    std::fs::copy(&sc, dir.join("pipe|name.toml")).unwrap();
    let f = campaign_file(
        &dir,
        "name = \"nulls\"\nscenarios = [\"pipe|name.toml\"]\nclock = \"lockstep\"\nduration_s = 0.05\n\
         faults = [[\"stop:observer@0.04:0.005\"]]\n",
    );
    let out = dir.join("c");
    let o = campaign(&f, &out);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(3), "{err}");
    // No real-time set-up line of the hosts on the campaign's stderr: they are in each
    // run's summary.json.
    assert!(!err.contains("SCHED_OTHER"), "{err}");
    let (suite, cases) = junit(&out.join("junit.xml"));
    assert_eq!(cases.len(), 1);
    let failure = suite
        .descendants()
        .find(|n| n.has_tag_name("failure"))
        .unwrap();
    let message = failure.attribute("message").unwrap();
    assert!(
        message.contains("faults.0.speed_recovered_ms = null (never recovered)"),
        "{message}"
    );
    assert!(!message.contains("not a number"), "{message}");
    assert!(
        message.ends_with("— the drive must be back within 200 ms"),
        "{message}"
    );
    let body = failure.text().unwrap();
    assert!(
        body.contains("= null (never recovered) (violates)"),
        "{body}"
    );
    assert!(
        body.contains("note: the drive must be back within 200 ms"),
        "{body}"
    );
    // A count is a whole number, as in the summary.
    let prop = |k: &str| cases[0].3.iter().find(|p| p.0 == k).map(|p| p.1.clone());
    assert_eq!(
        prop("samples_missing").as_deref(),
        Some("0"),
        "{:?}",
        cases[0].3
    );
    let run = PathBuf::from(prop("run_folder").unwrap());
    let s = summary(&run);
    assert_eq!(s["processes"]["plant"]["policy"], "SCHED_OTHER", "{s}");
    let md = String::from_utf8(read(&out.join("campaign.md"))).unwrap();
    let row = md
        .lines()
        .find(|l| l.starts_with("| 1 |"))
        .unwrap_or_else(|| panic!("{md}"));
    assert!(row.starts_with("| 1 | pipe\\|name.toml | "), "{row}");
    // As many cells as the header has.
    let cells = |l: &str| l.replace("\\|", "").matches('|').count();
    let header = md.lines().find(|l| l.starts_with("| # |")).unwrap();
    assert_eq!(cells(row), cells(header), "{row}");
}

#[test]
fn a_run_that_ends_in_an_error_keeps_its_figures_as_junit_properties() {
    let dir = scratch("errorprops");
    // In real time with restart = "never", the second kill finds its process dead: the
    // fault is not made and the run is an error, with its trace and summary written.
    let f = campaign_file(
        &dir,
        "name = \"errors\"\nscenarios = [\"kyslan-pi\"]\nduration_s = 0.5\nrestart = \"never\"\n\
         faults = [[\"kill:speed-loop@0.1\", \"kill:speed-loop@0.3\"]]\n",
    );
    let out = dir.join("c");
    let o = drivelab(&[
        "campaign",
        f.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--no-rt",
    ]);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{err}");
    let (_, cases) = junit(&out.join("junit.xml"));
    assert_eq!(cases.len(), 1);
    assert_eq!(cases[0].2, 1, "not an error: {cases:?}");
    let prop = |k: &str| cases[0].3.iter().find(|p| p.0 == k).map(|p| p.1.clone());
    let run = PathBuf::from(prop("run_folder").expect("run_folder"));
    let s = summary(&run);
    assert_clean(s["bus"].as_str().unwrap());
    let peak: f64 = prop("peak_current_a")
        .unwrap_or_else(|| panic!("no figures: {:?}", cases[0].3))
        .parse()
        .unwrap();
    assert_eq!(peak, s["peak_current_a"].as_f64().unwrap());
    assert_eq!(
        prop("samples_missing"),
        Some(s["samples_missing"].to_string())
    );
    assert_eq!(prop("seed").as_deref(), Some("1"));
}

#[test]
fn a_campaign_folder_that_is_a_file_is_refused_in_one_line() {
    let dir = scratch("outfile");
    let f = campaign_file(
        &dir,
        "name = \"x\"\nscenarios = [\"kyslan-pi\"]\nclock = \"lockstep\"\nduration_s = 0.05\n",
    );
    let file = dir.join("a-file");
    std::fs::write(&file, "mine").unwrap();
    for out in [file.clone(), file.join("below")] {
        let o = campaign(&f, &out);
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(1), "{err}");
        assert_eq!(err.trim().lines().count(), 1, "{err}");
        assert!(
            err.contains(&format!("{} is a file, not a folder", file.display()))
                || err.contains(": is a file, not a folder"),
            "{err}"
        );
        assert!(!err.contains("os error"), "{err}");
    }
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "mine");
}
