//! `drivelab bench --quick` end to end. It checks the report's structure and verdict logic,
//! never a latency figure (those belong to the bench's own output).

mod common;

use common::{assert_clean, not_checked, processes_with, scratch, wait};
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

/// Runs `drivelab bench ARGS --out OUT` with a watchdog against hangs.
fn bench(args: &[&str], out: &std::path::Path) -> std::process::Output {
    let child = Command::new(env!("CARGO_BIN_EXE_drivelab"))
        .arg("bench")
        .args(args)
        .args(["--out", out.to_str().unwrap()])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // Killed if it hangs; its chains end with it (their parent-death signal).
    let o = wait(child, Duration::from_secs(300), &format!("bench {args:?}"));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    o
}

/// Whether `cmd` is an executable file on PATH (found independently of the bench).
fn on_path(cmd: &str) -> bool {
    use std::os::unix::fs::PermissionsExt;
    std::env::var_os("PATH").is_some_and(|p| {
        std::env::split_paths(&p).any(|d| {
            std::fs::metadata(d.join(cmd))
                .is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
        })
    })
}

#[test]
fn a_missing_cyclictest_is_skipped_with_one_line_that_says_why() {
    let out = scratch("no-cyclictest");
    let o = bench(
        &[
            "--quick",
            "--json",
            "--variants",
            "cyclictest",
            "--cyclictest",
            "/nonexistent/cyclictest",
        ],
        &out,
    );
    let err = String::from_utf8_lossy(&o.stderr);
    let lines: Vec<&str> = err.lines().filter(|l| l.contains("cyclictest")).collect();
    assert_eq!(
        lines,
        ["drivelab: bench: cyclictest cross-check skipped: /nonexistent/cyclictest is not an executable file"]
    );
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    // Only cyclictest was asked for (and the floor, which always runs): the floor is left.
    let variants: Vec<&str> = report["rows"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["variant"].as_str().unwrap())
        .collect();
    assert_eq!(variants, ["floor", "floor"]);
    assert_eq!(report["floor_vs_cyclictest"], serde_json::json!([]));
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn bench_quick_runs_end_to_end_and_writes_its_report() {
    let out = scratch("quick");
    let o = bench(&["--quick", "--json"], &out);
    let report: serde_json::Value =
        serde_json::from_slice(&o.stdout).expect("bench --json prints JSON");
    let rows = report["rows"].as_array().unwrap();
    let md = std::fs::read_to_string(out.join("bench.md")).unwrap();
    let variants: Vec<(&str, bool)> = rows
        .iter()
        .map(|r| {
            (
                r["variant"].as_str().unwrap(),
                r["cpu_latency_request"].as_bool().unwrap(),
            )
        })
        .collect();
    // The request is held when this user may make one; the floor, cyclictest (when it is
    // installed) and the one-core chain are measured without it too.
    let can_request = std::fs::OpenOptions::new()
        .write(true)
        .open("/dev/cpu_dma_latency")
        .is_ok();
    let held = &report["cpu_latency_request_us"];
    assert_eq!(held.as_u64(), Some(0), "{held}");
    assert_eq!(report["cpu_latency_request_failed"], !can_request);
    let r = can_request;
    let mut expect = vec![("floor", r), ("floor", false)];
    let cyclictest = on_path("cyclictest");
    if cyclictest {
        expect.extend([("cyclictest", r), ("cyclictest", false)]);
    } else {
        assert!(
            String::from_utf8_lossy(&o.stderr).contains("cyclictest cross-check skipped"),
            "no line says why cyclictest did not run"
        );
    }
    expect.extend([
        ("floor-repeat", r),
        ("hop", r),
        ("bare-chain", r),
        ("inprocess", r),
        ("uds", r),
        ("iceoryx2", r),
        ("iceoryx2", false),
        ("iceoryx2+spin", r),
    ]);
    assert_eq!(variants, expect);
    // What the spin buys, from the two chains' rows (same request, one round: no median).
    let chain_of = |v: &str| {
        rows.iter()
            .find(|x| x["variant"] == v && x["cpu_latency_request"] == r)
            .unwrap()
    };
    // Both transports' chains say what they cost the machine: CPU time, waits and system
    // calls. A socket chain makes one call per message sent or received; the futex chain
    // one per sleep and one per wake of a sleeping receiver, so fewer.
    let calls = |row: &serde_json::Value| row["syscalls_per_sample"].as_f64();
    for v in ["uds", "iceoryx2"] {
        let c = chain_of(v);
        assert!(c["cpu_s_per_s"].as_f64().is_some_and(|c| c > 0.0), "{c}");
        assert!(
            c["waits_per_sample"].as_f64().is_some_and(|w| w > 0.0),
            "{c}"
        );
        assert!(calls(c).is_some_and(|n| n > 1.0), "{c}");
    }
    assert!(
        calls(chain_of("uds")) > calls(chain_of("iceoryx2")),
        "syscalls per sample: uds {:?}, iceoryx2 {:?}",
        calls(chain_of("uds")),
        calls(chain_of("iceoryx2"))
    );
    // The iceoryx2 chain says what each of its four processes costs the CPU per sample over
    // its run; the parts add up to no more than its CPU per simulated second with the set-up
    // (a short run's is most of it), and each stage's wake-up preempts the one that woke it
    // (all on one core, priorities rising along the chain).
    let c = chain_of("iceoryx2");
    let by = c["cpu_us_per_sample_by_process"].as_object().unwrap();
    let names: Vec<&str> = by.keys().map(String::as_str).collect();
    assert_eq!(
        names,
        ["current-loop", "observer", "plant", "speed-loop"],
        "{c}"
    );
    assert!(
        by.values().all(|us| us.as_f64().is_some_and(|u| u > 0.0)),
        "{c}"
    );
    // µs per sample × samples per simulated second (10 kHz) = s per simulated second.
    let sum = by.values().filter_map(|v| v.as_f64()).sum::<f64>() * 1e-6 * 10_000.0;
    let whole = c["cpu_s_per_s"].as_f64().unwrap();
    assert!(
        sum <= whole,
        "{sum} s/s by process over the runs, {whole} in all: {c}"
    );
    assert!(
        c["preemptions_per_sample"]
            .as_f64()
            .is_some_and(|p| p > 0.5),
        "{c}"
    );
    assert!(
        md.contains("CPU per sample, iceoryx2 one-core at 10 kHz: current-loop "),
        "bench.md has no CPU-per-sample line: {md}"
    );
    let (spin, plain) = (chain_of("iceoryx2+spin"), chain_of("iceoryx2"));
    let spins = report["spin"].as_array().unwrap();
    assert_eq!(spins.len(), 1, "{spins:?}");
    let e = &spins[0];
    let f = |row: &serde_json::Value, k: &str, q: &str| row[k][q].as_f64().unwrap();
    assert_eq!(
        e["spin_us"].as_f64(),
        Some(25.0),
        "30 µs capped at T_s/4: {e}"
    );
    for q in ["p50", "p99"] {
        let want = f(spin, "cycle_us", q) - f(plain, "cycle_us", q);
        assert_eq!(e[format!("{q}_change_us")].as_f64(), Some(want), "{q}: {e}");
    }
    assert_eq!(e["misses_per_million"], spin["misses_per_million"]);
    assert_eq!(e["misses_per_million_without"], plain["misses_per_million"]);
    let cpu = spin["cpu_s_per_s"].as_f64().unwrap() - plain["cpu_s_per_s"].as_f64().unwrap();
    assert_eq!(e["cpu_change_s_per_s"].as_f64(), Some(cpu));
    assert!(e["p99_median_change_us"].is_null(), "{e}");
    assert_eq!(
        e["p99_change_by_round_us"].as_array().map(Vec::len),
        Some(0),
        "{e}"
    );
    let floor_of = |req: bool| {
        rows.iter()
            .find(|x| x["variant"] == "floor" && x["cpu_latency_request"] == req)
            .unwrap()
    };
    // The floor sleeps at most once per deadline (a passed one costs no call).
    let floor_calls = calls(floor_of(r));
    assert!(
        floor_calls.is_some_and(|n| n > 0.0 && n <= 1.0),
        "{floor_calls:?}"
    );
    for r in rows {
        assert!(r["samples"].as_u64().unwrap() > 0, "{r}");
        for q in ["p50", "p99", "p999", "max"] {
            assert!(r["cycle_us"][q].as_f64().is_some(), "{r}");
        }
        let floor = floor_of(r["cpu_latency_request"].as_bool().unwrap());
        // The verdict follows its definition: cycle p99.9 < Ts and misses/M ≤ 2 × floor + 10,
        // against the floor measured under the same request.
        if ["floor", "floor-repeat", "cyclictest", "hop"].contains(&r["variant"].as_str().unwrap())
        {
            assert!(r["holds_budget"].is_null(), "not a chain: {r}");
        } else {
            let floor_pm = floor["misses_per_million"].as_f64().unwrap();
            let expect = r["cycle_us"]["p999"].as_f64().unwrap() < 100.0
                && r["misses_per_million"].as_f64().unwrap() <= 2.0 * floor_pm + 10.0;
            assert_eq!(r["holds_budget"].as_bool(), Some(expect), "{r}");
            let d50 =
                r["cycle_us"]["p50"].as_f64().unwrap() - floor["cycle_us"]["p50"].as_f64().unwrap();
            // The report rounds to the ns.
            assert!(
                (r["p50_minus_floor_us"].as_f64().unwrap() - d50).abs() < 2e-3,
                "{r}"
            );
        }
    }
    // Before each round without the request the core's idle governor is let settle; a round
    // whose core still polled (another test's drive may hold a request meanwhile) is counted
    // in its row and named in one warning line each, and a row with the request has none.
    let still_polling: u64 = rows
        .iter()
        .map(|r| {
            let n = r["idle_still_polling_rounds"].as_u64().unwrap();
            assert!(n == 0 || r["cpu_latency_request"] == false, "{r}");
            n
        })
        .sum();
    let warned = String::from_utf8_lossy(&o.stderr)
        .lines()
        .filter(|l| l.contains("still polls when idle"))
        .count();
    assert_eq!(still_polling, warned as u64);
    // The hop floor: one wake-up per sample, each either recorded or counted as unseen.
    let hop = rows.iter().find(|x| x["variant"] == "hop").unwrap();
    assert_eq!(hop["samples"], 2000, "{hop}");
    assert_eq!(
        hop["cycle_us"]["count"].as_u64().unwrap() + hop["misses"].as_u64().unwrap(),
        2000,
        "{hop}"
    );
    assert!(hop["holds_budget"].is_null(), "{hop}");
    // The bare chain: every sample that reached its last receiver is in the histogram, and
    // every sample that did not is a miss (late arrivals are misses too).
    let bare = rows.iter().find(|x| x["variant"] == "bare-chain").unwrap();
    assert_eq!(bare["samples"], 2000, "{bare}");
    let arrived = bare["cycle_us"]["count"].as_u64().unwrap();
    let missed = bare["misses"].as_u64().unwrap();
    assert!(arrived <= 2000 && missed >= 2000 - arrived, "{bare}");
    // The floor against cyclictest, under each request state, with the agreement verdict: on
    // the wake-ups' lateness (cyclictest skips the periods that pass while it is late, and so
    // do the floor's wake-ups), not on the floor's every deadline that the chains compare with.
    let checks = report["floor_vs_cyclictest"].as_array().unwrap();
    assert_eq!(checks.len(), if cyclictest { 2 } else { 0 });
    for c in checks {
        let req = c["cpu_latency_request"].as_bool().unwrap();
        let ct = rows
            .iter()
            .find(|x| x["variant"] == "cyclictest" && x["cpu_latency_request"] == req)
            .unwrap();
        assert_eq!(ct["samples"], 2000, "{ct}");
        let d = |q: &str| {
            floor_of(req)["lateness_us"][q].as_f64().unwrap() - ct["cycle_us"][q].as_f64().unwrap()
        };
        assert!(
            (c["p50_diff_us"].as_f64().unwrap() - d("p50")).abs() < 2e-3,
            "{c}"
        );
        assert!(
            (c["p99_diff_us"].as_f64().unwrap() - d("p99")).abs() < 2e-3,
            "{c}"
        );
        assert_eq!(
            c["agrees"].as_bool(),
            Some(d("p50").abs() <= 3.0 && d("p99").abs() <= 3.0),
            "{c}"
        );
        assert!(c["by_round"].is_null(), "one round, nothing to pair: {c}");
        // Its bench.md line ends with the floor against its own repeat when the repeat ran
        // under the same request (it runs under the request the bench holds).
        let label = if req { "request held" } else { "no request" };
        let line = md
            .lines()
            .find(|l| l.starts_with(&format!("Floor − cyclictest at 10 kHz ({label})")))
            .unwrap_or_else(|| panic!("no cross-check line for {label}: {md}"));
        let repeat = &report["floor_vs_repeat"][0];
        let tail = (repeat["cpu_latency_request"] == req).then(|| {
            format!(
                " The floor against its own repeat in the same rounds: p50 {:+.1} µs, p99 {:+.1} µs.",
                repeat["p50_diff_us"].as_f64().unwrap(),
                repeat["p99_diff_us"].as_f64().unwrap()
            )
        });
        match tail {
            Some(t) => assert!(line.ends_with(&t), "{line}"),
            None => assert!(!line.contains("its own repeat"), "{line}"),
        }
        // cyclictest's main thread runs off the measured core (1), as the floor's process does,
        // when this cyclictest can place it (rt-tests 2.0 and later).
        let help = std::process::Command::new("cyclictest")
            .arg("--help")
            .output()
            .unwrap();
        let can = String::from_utf8_lossy(&[help.stdout, help.stderr].concat())
            .contains("--mainaffinity");
        let main = c["cyclictest_main_thread_core"].as_u64();
        assert_eq!(main.is_some(), can, "{c}");
        assert_ne!(main, Some(1), "{c}");
    }
    // The floor against its own repeat: the same figures as against cyclictest, on the
    // wake-ups' lateness, and each one's misses; one line of bench.md says it.
    let repeats = report["floor_vs_repeat"].as_array().unwrap();
    assert_eq!(repeats.len(), 1, "{repeats:?}");
    let f = &repeats[0];
    let repeat = rows
        .iter()
        .find(|x| x["variant"] == "floor-repeat")
        .unwrap();
    assert_eq!(repeat["samples"], 2000, "{repeat}");
    assert_eq!(f["cpu_latency_request"], r);
    let late = |row: &serde_json::Value, q: &str| row["lateness_us"][q].as_f64().unwrap();
    let (d50, d99) = (
        late(floor_of(r), "p50") - late(repeat, "p50"),
        late(floor_of(r), "p99") - late(repeat, "p99"),
    );
    assert!(
        (f["p50_diff_us"].as_f64().unwrap() - d50).abs() < 2e-3,
        "{f}"
    );
    assert!(
        (f["p99_diff_us"].as_f64().unwrap() - d99).abs() < 2e-3,
        "{f}"
    );
    assert_eq!(
        f["within_agreement"].as_bool(),
        Some(d50.abs() <= 3.0 && d99.abs() <= 3.0),
        "{f}"
    );
    assert_eq!(f["misses_per_million"], floor_of(r)["misses_per_million"]);
    assert_eq!(f["repeat_misses_per_million"], repeat["misses_per_million"]);
    assert!(f["by_round"].is_null(), "one round, nothing to pair: {f}");
    // And at every deadline, which the chains' targets compare with.
    let cycle = |row: &serde_json::Value, q: &str| row["cycle_us"][q].as_f64().unwrap();
    for q in ["p50", "p99"] {
        let d = cycle(floor_of(r), q) - cycle(repeat, q);
        let got = f[format!("deadline_{q}_diff_us")].as_f64().unwrap();
        assert!((got - d).abs() < 2e-3, "{q}: {f}");
    }
    assert!(f["deadline_p99_median_round_diff_us"].is_null(), "{f}");
    let line = format!(
        "Floor − floor-repeat at 10 kHz ({}), wake-up lateness: p50 {:+.1} µs, p99 {:+.1} µs",
        if r { "request held" } else { "no request" },
        f["p50_diff_us"].as_f64().unwrap(),
        f["p99_diff_us"].as_f64().unwrap()
    );
    assert!(md.contains(&line), "bench.md lacks {line:?}: {md}");
    let line = format!(
        "; at every deadline (what the chains' targets compare with): p50 {:+.1} µs, p99 {:+.1} µs; misses per million {:.0} (floor) against {:.0} (repeat).",
        f["deadline_p50_diff_us"].as_f64().unwrap(),
        f["deadline_p99_diff_us"].as_f64().unwrap(),
        f["misses_per_million"].as_f64().unwrap(),
        f["repeat_misses_per_million"].as_f64().unwrap()
    );
    assert!(md.contains(&line), "bench.md lacks {line:?}: {md}");
    let ice: Vec<&serde_json::Value> = rows.iter().filter(|x| x["variant"] == "iceoryx2").collect();
    assert!(
        ice.iter().any(|r| r["p99_ratio_to_uds"].is_f64()),
        "no iceoryx2 row compared with the Unix-socket chain"
    );
    for r in &ice {
        // Against the Unix-socket chain measured under the same request, and only that one
        // (it is measured with the request held only).
        let uds = rows.iter().find(|x| {
            x["variant"] == "uds"
                && x["placement"] == r["placement"]
                && x["cpu_latency_request"] == r["cpu_latency_request"]
        });
        match uds {
            Some(u) => {
                let want =
                    r["cycle_us"]["p99"].as_f64().unwrap() / u["cycle_us"]["p99"].as_f64().unwrap();
                let got = r["p99_ratio_to_uds"].as_f64().unwrap();
                assert!((got - want).abs() < 1e-9, "{got} against {want}");
            }
            None => assert!(r["p99_ratio_to_uds"].is_null(), "{r}"),
        }
        // The cycle's budget: the default chain's critical path, cut at its hops.
        let b = &r["budget"];
        assert_eq!(
            b["path"],
            serde_json::json!(["plant", "observer", "current-loop"])
        );
        let parts: Vec<&str> = b["parts"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p["part"].as_str().unwrap())
            .collect();
        assert_eq!(
            parts,
            [
                "plant timer wake-up",
                "plant execution",
                "plant publish",
                "observer wake-up",
                "observer execution",
                "observer publish",
                "current-loop wake-up",
                "current-loop execution"
            ]
        );
    }
    // The default chain's targets, from its row (one core, under the request when it could
    // be held) and the floor's under the same request; then the control's, the floor's
    // repeat held to the same targets.
    let targets = report["targets"].as_array().unwrap();
    assert_eq!(targets.len(), 2, "{targets:?}");
    let t = &targets[0];
    let chain = rows
        .iter()
        .find(|x| x["variant"] == "iceoryx2" && x["cpu_latency_request"] == can_request)
        .unwrap();
    assert_eq!(t["chain"], "iceoryx2 one-core");
    assert_eq!(t["rate_hz"], 10000.0);
    assert_eq!(t["cpu_latency_request"], can_request);
    // One round: nothing to compare round by round.
    assert!(t["by_round"].is_null(), "{t}");
    assert!(t["uds_by_round"].is_null(), "{t}");
    let bound = 2.0
        * floor_of(can_request)["misses_per_million"]
            .as_f64()
            .unwrap()
        + 10.0;
    let control = &targets[1];
    for (t, row) in [(t, chain), (control, repeat)] {
        let cycle = |q: &str| row["cycle_us"][q].as_f64().unwrap();
        let floor_cycle = |q: &str| floor_of(can_request)["cycle_us"][q].as_f64().unwrap();
        for (q, limit) in [("p50", 10.0), ("p99", 15.0)] {
            let k = format!("{q}_minus_floor_us");
            let d = row[&k].as_f64().unwrap();
            assert!((d - (cycle(q) - floor_cycle(q))).abs() < 2e-3, "{k}: {row}");
            assert_eq!(t[&k].as_f64(), Some(d), "{k}");
            assert_eq!(
                t[format!("{q}_met")].as_bool(),
                Some(d <= limit),
                "{q}: {t}"
            );
        }
        assert_eq!(t["misses_bound"].as_f64(), Some(bound));
        let pm = row["misses_per_million"].as_f64().unwrap();
        assert_eq!(t["misses_met"].as_bool(), Some(pm <= bound));
    }
    assert_eq!(control["chain"], "floor-repeat (control)");
    assert_eq!(control["cpu_latency_request"], can_request);
    for k in [
        "p99_ratio_to_uds",
        "misses_floor_predicts_catching_up",
        "bare_chain",
    ] {
        assert!(
            control[k].is_null(),
            "the control is the floor: no {k}: {control}"
        );
    }
    let line = md
        .lines()
        .find(|l| l.starts_with("Targets at 10 kHz (floor-repeat (control) against the floor"))
        .unwrap_or_else(|| panic!("no control targets line: {md}"));
    assert!(
        line.ends_with(
            " A control: the floor measured again, so what it misses this run's noise decides, for the chains too."
        ) && !line.contains("Unix-socket"),
        "{line}"
    );
    let uds = chain["p99_ratio_to_uds"].as_f64().unwrap();
    assert_eq!(t["p99_ratio_to_uds"].as_f64(), Some(uds));
    assert_eq!(t["uds_met"].as_bool(), Some(uds <= 0.8));
    // What each chain adds to the floor's p99, one against the other.
    let p99 = |row: &serde_json::Value| row["cycle_us"]["p99"].as_f64().unwrap();
    let uds_row = rows
        .iter()
        .find(|x| x["variant"] == "uds" && x["placement"] == "one-core")
        .unwrap();
    let f99 = p99(floor_of(can_request));
    let above = (p99(uds_row) > f99).then(|| (p99(chain) - f99) / (p99(uds_row) - f99));
    assert_eq!(t["p99_above_floor_ratio_to_uds"].as_f64(), above, "{t}");
    // The floor's misses had its deadlines been due sooner: one figure per µs from 0 (its
    // own misses, to the histogram's resolution), never fewer the sooner; the target reads
    // it at the chain's p50 above the floor.
    let curve: Vec<f64> = floor_of(can_request)["misses_pm_if_sooner_us"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    assert_eq!(curve.len(), 41);
    assert!(curve.windows(2).all(|w| w[0] <= w[1]), "{curve:?}");
    let floor_pm = floor_of(can_request)["misses_per_million"]
        .as_f64()
        .unwrap();
    assert!(curve[0] <= floor_pm, "{curve:?} vs {floor_pm}");
    let predicted = t["misses_floor_predicts"].as_f64().unwrap();
    let d50 = t["p50_minus_floor_us"].as_f64().unwrap().clamp(0.0, 40.0);
    let (lo, hi) = (curve[d50.floor() as usize], curve[d50.ceil() as usize]);
    assert!(
        lo <= predicted && predicted <= hi,
        "{predicted} not in {lo}..{hi}"
    );
    // Only the floor carries the curve.
    assert!(chain["misses_pm_if_sooner_us"].is_null());
    // The bare chain of the same request against the floor, and the chain against it.
    let b = &t["bare_chain"];
    let bare = rows
        .iter()
        .find(|x| x["variant"] == "bare-chain" && x["cpu_latency_request"] == can_request)
        .unwrap();
    let q = |row: &serde_json::Value, p: &str| row["cycle_us"][p].as_f64().unwrap();
    let floor = floor_of(can_request);
    for p in ["p50", "p99"] {
        assert_eq!(
            b[format!("{p}_minus_floor_us")].as_f64(),
            Some(q(bare, p) - q(floor, p)),
            "{p}: {b}"
        );
        assert_eq!(
            b[format!("chain_{p}_minus_bare_us")].as_f64(),
            Some(q(chain, p) - q(bare, p)),
            "{p}: {b}"
        );
    }
    assert!(b["p99_minus_floor_median_us"].is_null(), "one round: {b}");
    // The Unix-socket target's bound against the bare critical path's p99.
    let ub = &t["uds_bound_against_bare"];
    let uds_bound = 0.8 * p99(uds_row);
    let bound_minus_bare = uds_bound - p99(bare);
    assert_eq!(ub["bound_us"].as_f64(), Some(uds_bound), "{ub}");
    assert_eq!(
        ub["minus_bare_p99_us"].as_f64(),
        Some(bound_minus_bare),
        "{ub}"
    );
    assert!(
        b["chain_p99_minus_bare_median_us"].is_null(),
        "one round: {b}"
    );
    assert!(
        report["speed"]["lockstep_simulated_s_per_wall_s"]
            .as_f64()
            .unwrap()
            > 0.0
    );
    assert!(
        report["speed"]["inprocess_simulated_s_per_wall_s"]
            .as_f64()
            .unwrap()
            > 0.0
    );
    for f in [
        "bench.json",
        "bench.md",
        "percentiles-10000hz.png",
        "percentiles-10000hz.svg",
        "floor-core1-10000hz.hgrm",
        "floor-core1-10000hz-norequest.hgrm",
        "iceoryx2-one-core-10000hz.hgrm",
        "iceoryx2-one-core-10000hz-norequest.hgrm",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    assert!(md.contains("| 10 kHz | iceoryx2 | one-core |"), "{md}");
    assert!(
        md.contains("Where the microseconds go, iceoryx2 one-core at 10 kHz"),
        "{md}"
    );
    assert!(
        md.contains("Targets at 10 kHz (iceoryx2 one-core against the floor"),
        "bench.md has no targets line"
    );
    assert!(
        md.contains(&format!(
            "; the floor's own tail gives {predicted:.0}/M to a chain that costs its {:+.1} µs at every deadline",
            t["p50_minus_floor_us"].as_f64().unwrap()
        )),
        "bench.md does not give the floor's prediction: {md}"
    );
    assert!(
        md.contains(&format!(
            "; p99 {uds:.3} × the Unix-socket chain's (≤ 0.8: {}",
            if uds <= 0.8 { "met" } else { "missed" }
        )),
        "{md}"
    );
    if let Some(a) = above {
        assert!(
            md.contains(&format!(
                "; above the floor's p99, {a:.2} × what the Unix-socket chain adds; the bound, "
            )),
            "{md}"
        );
    }
    assert!(
        md.contains(&format!(
            "; the bound, {uds_bound:.1} µs, lies {:.1} µs {} the bare critical path's p99 (timer and two futex wake-ups, no work))",
            bound_minus_bare.abs(),
            if bound_minus_bare < 0.0 { "below" } else { "above" }
        )),
        "{md}"
    );
    assert!(
        md.contains("The same critical path bare (timer and two futex wake-ups"),
        "bench.md does not compare with the bare chain"
    );
    assert!(
        md.contains("Sleep-then-spin at 10 kHz (25 µs) against the same chain without it: p50 "),
        "bench.md has no spin line"
    );
    // The cache probes before and after the rounds, on the plant's core, and their sentence.
    let probes = &report["machine"]["cache_after_sleep"];
    let clause = |p: &serde_json::Value| {
        assert_eq!(p["cpu"].as_u64(), Some(1), "{p}");
        assert_eq!(p["lines"].as_u64(), Some(64), "{p}");
        assert_eq!(p["wakeups"].as_u64(), Some(2000), "{p}");
        let (a, w) = (
            p["after_sleep_ns"].as_u64().unwrap(),
            p["warm_ns"].as_u64().unwrap(),
        );
        let extra = (a as f64 - w as f64) / 64.0;
        // Its verdict: held under 1.5 ns a line, cleared from 5 (cache::CacheState).
        let verdict = if extra < 1.5 {
            "the caches held while the core slept"
        } else if extra < 5.0 {
            "some lines came from memory: the caches were partly cleared while the core slept"
        } else {
            "the lines came from memory: the host cleared the core's caches while it slept, and \
             each stage then reads its own memory from there after its wake-up"
        };
        format!("{a} ns against {w} ns warm ({extra:+.1} ns a line): {verdict}")
    };
    let line = format!(
        "Caches after a sleep: a timer on core 1 woke every 100 µs and read 64 lines on as many \
         pages, then read them again (p50 of 2000 wake-ups): before the rounds {}; after them {} \
         (docs/measurements.md, \"The same VM three hours later\").",
        clause(&probes["before"]),
        clause(&probes["after"])
    );
    assert!(md.contains(&line), "bench.md lacks {line:?}: {md}");
    let _ = std::fs::remove_dir_all(&out);
}

/// `figure` of each round of the row of `variant` measured with `request` held or not.
fn by_round(
    rows: &[serde_json::Value],
    variant: &str,
    request: &serde_json::Value,
    figure: &str,
) -> Vec<f64> {
    let row = rows
        .iter()
        .find(|x| x["variant"] == variant && &x["cpu_latency_request"] == request)
        .unwrap();
    row["rounds"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r[figure].as_f64().unwrap())
        .collect()
}

/// A JSON array of numbers.
fn floats(v: &serde_json::Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|d| d.as_f64().unwrap())
        .collect()
}

#[test]
fn bench_rounds_interleave_the_variants_and_merge_their_samples() {
    let out = scratch("rounds");
    let o = bench(&["--quick", "--rounds", "2", "--json"], &out);
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(report["rounds"], 2);
    let rows = report["rows"].as_array().unwrap();
    // 0.2 s at 10 kHz in two slices of 0.1 s: both slices count.
    let floor = rows[0]["samples"].as_u64().unwrap();
    assert!((1990..=2010).contains(&floor), "floor samples {floor}");
    // What the spin bought, round by round: each round of the spin chain against the same
    // round of the chain without it; with two rounds the median is their mean.
    let req0 = &rows[0]["cpu_latency_request"];
    let (spin, plain) = (
        by_round(rows, "iceoryx2+spin", req0, "p99_us"),
        by_round(rows, "iceoryx2", req0, "p99_us"),
    );
    assert_eq!((spin.len(), plain.len()), (2, 2));
    let e = &report["spin"][0];
    let change = floats(&e["p99_change_by_round_us"]);
    assert_eq!(change, [spin[0] - plain[0], spin[1] - plain[1]], "{e}");
    let median = e["p99_median_change_us"].as_f64().unwrap();
    assert!((median - (change[0] + change[1]) / 2.0).abs() < 1e-9, "{e}");
    // The floor against cyclictest and against its own repeat, round by round on the
    // wake-ups: round i of each.
    let checks = report["floor_vs_cyclictest"].as_array().unwrap();
    assert_eq!(checks.len(), if on_path("cyclictest") { 2 } else { 0 });
    let repeats = report["floor_vs_repeat"].as_array().unwrap();
    assert_eq!(repeats.len(), 1, "{repeats:?}");
    let pairs = checks.iter().map(|c| (c, "cyclictest"));
    for (c, other) in pairs.chain(repeats.iter().map(|c| (c, "floor-repeat"))) {
        let req = &c["cpu_latency_request"];
        for (q, field) in [
            ("wake_p50_us", "p50_diff_us"),
            ("wake_p99_us", "p99_diff_us"),
        ] {
            let (f, o) = (
                by_round(rows, "floor", req, q),
                by_round(rows, other, req, q),
            );
            assert_eq!(
                floats(&c["by_round"][field]),
                [f[0] - o[0], f[1] - o[1]],
                "{other} {field}: {c}"
            );
        }
    }
    // At every deadline the repeat's p99 median round is the mean of the two rounds' diffs.
    let f = &repeats[0];
    let (a, b) = (
        by_round(rows, "floor", &f["cpu_latency_request"], "p99_us"),
        by_round(rows, "floor-repeat", &f["cpu_latency_request"], "p99_us"),
    );
    let got = f["deadline_p99_median_round_diff_us"].as_f64().unwrap();
    assert!(
        (got - ((a[0] - b[0]) + (a[1] - b[1])) / 2.0).abs() < 1e-9,
        "{f}"
    );
    // The bare chain round by round: round i of it against round i of the floor, and round
    // i of the default chain against round i of it (two rounds: the median is the mean).
    let t = &report["targets"][0];
    let treq = &t["cpu_latency_request"];
    let (floor, bare, chain) = (
        by_round(rows, "floor", treq, "p99_us"),
        by_round(rows, "bare-chain", treq, "p99_us"),
        by_round(rows, "iceoryx2", treq, "p99_us"),
    );
    let mean = |a: &[f64], b: &[f64]| ((a[0] - b[0]) + (a[1] - b[1])) / 2.0;
    let b = &t["bare_chain"];
    for (field, want) in [
        ("p99_minus_floor_median_us", mean(&bare, &floor)),
        ("chain_p99_minus_bare_median_us", mean(&chain, &bare)),
    ] {
        let got = b[field].as_f64().unwrap();
        assert!((got - want).abs() < 1e-9, "{field}: {b}");
    }
    // The Unix-socket target round by round: round i of the chain over round i of the
    // Unix-socket chain (same placement), which ran in the same pass.
    let uds: Vec<f64> = rows
        .iter()
        .find(|x| x["variant"] == "uds" && x["placement"] == "one-core")
        .unwrap()["rounds"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["p99_us"].as_f64().unwrap())
        .collect();
    let u = &t["uds_by_round"];
    let ratios = floats(&u["p99_ratio"]);
    assert_eq!(ratios, [chain[0] / uds[0], chain[1] / uds[1]], "{u}");
    let met = ratios.iter().filter(|r| **r <= 0.8).count() as u64;
    assert_eq!(u["met"].as_u64(), Some(met), "{u}");
    let median = u["p99_ratio_median"].as_f64().unwrap();
    assert!(
        (median - (ratios[0] + ratios[1]) / 2.0).abs() < 1e-12,
        "{u}"
    );
    let md = std::fs::read_to_string(out.join("bench.md")).unwrap();
    assert!(
        md.contains(&format!(
            " Against the Unix-socket chain round by round (2): p99 ratio median {median:.3}, met in {met}."
        )),
        "{md}"
    );
    // Each chain ran once per round, in its own folder.
    for v in ["iceoryx2-one-core-10000hz", "uds-one-core-10000hz"] {
        for r in ["round1", "round2"] {
            assert!(out.join(v).join(r).is_dir(), "{v}/{r} missing");
        }
    }
    let md = std::fs::read_to_string(out.join("bench.md")).unwrap();
    assert!(md.contains("in 2 interleaved round(s)"), "{md}");
    let o = Command::new(env!("CARGO_BIN_EXE_drivelab"))
        .args(["bench", "--rounds", "0"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--rounds must be in 1..=100"));
    let o = Command::new(env!("CARGO_BIN_EXE_drivelab"))
        .args(["bench", "--variants", "floor,ice"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--variants: unknown variant 'ice'"));
    for bad in ["NaN", "-1", "inf"] {
        let o = Command::new(env!("CARGO_BIN_EXE_drivelab"))
            .args(["bench", &format!("--spin-us={bad}")])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{bad}: {err}");
        assert!(
            err.contains("--spin-us must be a number of µs >= 0") && err.lines().count() == 1,
            "{bad}: {err}"
        );
    }
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn bench_compares_topologies_with_their_cpu_time() {
    let out = scratch("topologies");
    let o = bench(
        &[
            "--quick",
            "--topologies",
            "four-process,two-process,one-process",
            "--rounds",
            "2",
            "--json",
        ],
        &out,
    );
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let rows = report["rows"].as_array().unwrap();
    let got: Vec<(String, String)> = rows
        .iter()
        .map(|r| {
            (
                r["variant"].as_str().unwrap().to_string(),
                r["placement"].as_str().unwrap().to_string(),
            )
        })
        .collect();
    let want: Vec<(String, String)> = [
        ("floor", "-"),
        ("topology", "four-process"),
        ("topology", "two-process"),
        ("topology", "one-process"),
        ("floor-repeat", "-"),
    ]
    .iter()
    .map(|(a, b)| (a.to_string(), b.to_string()))
    .collect();
    assert_eq!(got, want);
    for r in &rows[1..4] {
        // Both rounds of 0.1 s at 10 kHz count: 2000 samples (the plant's own count).
        assert_eq!(r["samples"].as_u64(), Some(2000), "{r}");
        assert!(r["cpu_s_per_s"].as_f64().is_some_and(|c| c > 0.0), "{r}");
        assert!(r["p99_ratio_to_floor"].as_f64().is_some(), "{r}");
    }
    // Every topology gets the targets against the floor, overall and round by round: round
    // i of the topology against round i of the floor; and so does the control, the floor's
    // repeat.
    let num = |v: &serde_json::Value| v.as_f64().unwrap();
    let floor_rounds = rows[0]["rounds"].as_array().unwrap();
    assert_eq!(floor_rounds.len(), 2, "{}", rows[0]);
    let targets = report["targets"].as_array().unwrap();
    assert_eq!(targets.len(), 4, "{targets:?}");
    let md = std::fs::read_to_string(out.join("bench.md")).unwrap();
    for (t, r) in targets.iter().zip(&rows[1..]) {
        let name = match r["variant"].as_str().unwrap() {
            "topology" => format!("topology {}", r["placement"].as_str().unwrap()),
            _ => "floor-repeat (control)".to_string(),
        };
        assert_eq!(t["chain"], name);
        assert_eq!(t["p99_minus_floor_us"], r["p99_minus_floor_us"], "{name}");
        assert!(t["p99_ratio_to_uds"].is_null(), "{t}");
        // The bare chain mirrors the default chain's critical path, not a topology's.
        assert!(t["bare_chain"].is_null(), "{t}");
        let rounds = r["rounds"].as_array().unwrap();
        assert_eq!(rounds.len(), 2, "{r}");
        let by = &t["by_round"];
        for (key, field, limit) in [
            ("p50_minus_floor_us", "p50_us", 10.0),
            ("p99_minus_floor_us", "p99_us", 15.0),
        ] {
            let want: Vec<f64> = rounds
                .iter()
                .zip(floor_rounds)
                .map(|(c, f)| num(&c[field]) - num(&f[field]))
                .collect();
            let got: Vec<f64> = by[key].as_array().unwrap().iter().map(num).collect();
            assert_eq!(got, want, "{name} {key}");
            // Two rounds: the median is their mean.
            let median = by[key.replace("minus_floor_us", "median_us")]
                .as_f64()
                .unwrap();
            assert!(
                (median - (want[0] + want[1]) / 2.0).abs() < 1e-9,
                "{name} {key}"
            );
            let met = want.iter().filter(|d| **d <= limit).count();
            assert_eq!(
                by[key.replace("minus_floor_us", "met")],
                met,
                "{name} {key}"
            );
        }
        let misses_met = rounds
            .iter()
            .zip(floor_rounds)
            .filter(|(c, f)| {
                num(&c["misses_per_million"]) <= 2.0 * num(&f["misses_per_million"]) + 10.0
            })
            .count();
        assert_eq!(by["misses_met"], misses_met, "{name}");
        let line = md
            .lines()
            .find(|l| l.starts_with(&format!("Targets at 10 kHz ({name} against the floor")))
            .unwrap_or_else(|| panic!("bench.md has no targets line for {name}"));
        assert!(
            line.contains("Round by round (2, each against its own floor): p50 median "),
            "{line}"
        );
    }
    // Each topology ran once per round in its own folder, with its processes.
    let s: serde_json::Value = serde_json::from_slice(
        &std::fs::read(out.join("topology-two-process-10000hz/round2/summary.json")).unwrap(),
    )
    .unwrap();
    let mut procs: Vec<&String> = s["processes"].as_object().unwrap().keys().collect();
    procs.sort();
    assert_eq!(procs, ["controller", "plant"]);
    let o = Command::new(env!("CARGO_BIN_EXE_drivelab"))
        .args(["bench", "--topologies", "nine-process"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("unknown topology 'nine-process'"));
    let _ = std::fs::remove_dir_all(&out);
}

/// The files in /dev/shm and /tmp/iceoryx2 of every bus that the bench with pid `pid` made
/// (its bus ids are `b<pid>` and a letter: `b<pid>r0j2`, `b<pid>ls`).
fn bench_bus_files(pid: u32) -> Vec<String> {
    let mine = |dir: &str, prefix: String| -> Vec<String> {
        std::fs::read_dir(dir)
            .into_iter()
            .flatten()
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| {
                n.strip_prefix(&prefix)
                    .is_some_and(|rest| rest.starts_with(|c: char| c.is_ascii_alphabetic()))
            })
            .map(|n| format!("{dir}/{n}"))
            .collect()
    };
    let mut v = mine("/dev/shm", format!("iox2_dlb{pid}"));
    v.extend(mine("/tmp/iceoryx2", format!("dlb{pid}")));
    v
}

/// The `--bus` argument of a command line ("PROGRAM ARG ARG ...").
fn bus_of(cmdline: &str) -> Option<String> {
    let args: Vec<&str> = cmdline.split(' ').collect();
    args.windows(2)
        .find(|w| w[0] == "--bus")
        .map(|w| w[1].to_string())
}

/// Whether a thread named `name` runs in process `pid`.
fn has_thread(pid: u32, name: &str) -> bool {
    std::fs::read_dir(format!("/proc/{pid}/task"))
        .into_iter()
        .flatten()
        .flatten()
        .any(|t| std::fs::read_to_string(t.path().join("comm")).is_ok_and(|c| c.trim() == name))
}

/// Starts `drivelab bench` measuring only `variant` (and the floor, which always runs first)
/// in 3 s slices, waits until `running` (given the bench's pid and its output folder) says
/// the phase is under way, sends `sig` and checks that the bench says in one line where it
/// was stopped, exits with 1 and leaves no process, bus file or socket folder behind.
/// Returns that line.
fn interrupt_bench(
    name: &str,
    variant: &str,
    sig: libc::c_int,
    running: impl Fn(u32, &Path) -> bool,
) -> String {
    let out = scratch(name).join("bench");
    let child = Command::new(env!("CARGO_BIN_EXE_drivelab"))
        .args(["bench", "--quick", "--seconds", "300", "--rounds", "100"])
        .args(["--no-cpu-latency-request", "--variants", variant, "--out"])
        .arg(&out)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let pid = child.id();
    // In a guard from here on: killed if the test fails before it exits.
    let child = common::Drive::from(child);
    let t = Instant::now();
    while !running(pid, &out) {
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "watchdog: the {variant} phase did not start within 60 s"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    // The buses the phase uses, while it runs.
    let buses: Vec<String> = processes_with(out.to_str().unwrap())
        .iter()
        .filter_map(|c| bus_of(c))
        .collect();
    // SAFETY: a signal to the bench this test started, not yet reaped.
    unsafe { libc::kill(pid as i32, sig) };
    let o = wait(child, Duration::from_secs(60), "the bench after its signal");
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert_eq!(o.status.code(), Some(1), "{variant}: {err}");
    let lines: Vec<&str> = err
        .lines()
        .filter(|l| l.starts_with("drivelab: error:"))
        .collect();
    assert_eq!(lines.len(), 1, "{variant}: {err}");
    let left = processes_with(out.to_str().unwrap());
    assert!(left.is_empty(), "{variant}: processes left: {left:?}");
    for bus in &buses {
        assert_clean(bus);
    }
    let files = bench_bus_files(pid);
    assert!(files.is_empty(), "{variant}: bus files left: {files:?}");
    let socks: Vec<String> = [std::env::temp_dir(), "/tmp".into()]
        .iter()
        .flat_map(|d| std::fs::read_dir(d).into_iter().flatten().flatten())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(&format!("drivelab-uds-{pid}-")))
        .collect();
    assert!(
        socks.is_empty(),
        "{variant}: socket folders left: {socks:?}"
    );
    assert!(
        !out.join("bench.json").exists(),
        "{variant}: a report was written"
    );
    lines[0].to_string()
}

#[test]
fn a_bench_stopped_by_a_signal_says_where_in_one_line_and_leaves_nothing_behind() {
    // A process of the phase, with the bench's output folder on its command line.
    let child_with = |marker: &'static str| {
        move |_: u32, out: &Path| {
            processes_with(out.to_str().unwrap())
                .iter()
                .any(|c| c.contains(marker))
        }
    };
    // The hop and the bare chain: their receivers were left running and their wake segment
    // in /dev/shm before.
    for (variant, sig, signal) in [
        ("hop", libc::SIGINT, "SIGINT"),
        ("bare-chain", libc::SIGTERM, "SIGTERM"),
    ] {
        let line = interrupt_bench(
            &format!("stop-{variant}"),
            variant,
            sig,
            child_with("bench-node hop"),
        );
        let want = format!(
            "drivelab: error: bench interrupted ({signal}) during {variant} without request at 10000 Hz, round 1 of 100; no report written (bench.json, bench.md); the measurements so far are in "
        );
        assert!(line.starts_with(&want), "{line}");
    }
    // The Unix-socket chain's four nodes.
    let line = interrupt_bench(
        "stop-uds",
        "uds",
        libc::SIGHUP,
        child_with("bench-node uds"),
    );
    assert!(
        line.contains("bench interrupted (SIGHUP) during uds one-core without request at 10000 Hz, round 1 of 100; no report written"),
        "{line}"
    );
    // cyclictest, where it is installed.
    if on_path("cyclictest") {
        let line = interrupt_bench(
            "stop-cyclictest",
            "cyclictest",
            libc::SIGINT,
            child_with("--histfile="),
        );
        assert!(
            line.contains("bench interrupted (SIGINT) during cyclictest without request at 10000 Hz, round 1 of 100; no report written"),
            "{line}"
        );
    } else {
        not_checked(
            "a_bench_stopped_by_a_signal_says_where_in_one_line_and_leaves_nothing_behind",
            "cyclictest is not installed (scripts/setup.sh installs rt-tests): its interruption",
        );
    }
    // The floor, in the bench's own thread: nothing was written, and the output folder the
    // bench made is gone.
    let line = interrupt_bench("stop-floor", "floor", libc::SIGINT, |pid, _| {
        has_thread(pid, "bench-floor")
    });
    assert!(
        line.ends_with(
            "bench interrupted (SIGINT) during floor without request at 10000 Hz, round 1 of 100; nothing written"
        ),
        "{line}"
    );
    // A drive, once it samples: the launcher stops it and says what it recorded.
    let line = interrupt_bench("stop-iceoryx2", "iceoryx2", libc::SIGTERM, |_, out| {
        let plant = processes_with(out.to_str().unwrap())
            .into_iter()
            .find(|c| c.contains("--process plant"));
        match plant.as_deref().and_then(bus_of) {
            Some(bus) => {
                common::wait_for_progress(&bus, 1);
                true
            }
            None => false,
        }
    });
    for says in [
        "bench interrupted (SIGTERM) during iceoryx2 one-core without request at 10000 Hz, round 1 of 100: interrupted (SIGTERM): drive stopped",
        "; no report written",
    ] {
        assert!(line.contains(says), "'{says}' not in: {line}");
    }
}

#[test]
fn the_hop_receivers_of_a_sigkilled_bench_end_and_remove_its_wake_segment() {
    // SIGKILL leaves the bench no chance to clean up: its hop receivers must notice that it
    // is gone, end, and take the wake segment with them.
    let out = scratch("kill-hop").join("bench");
    let child = Command::new(env!("CARGO_BIN_EXE_drivelab"))
        .args(["bench", "--quick", "--seconds", "300", "--rounds", "100"])
        .args(["--no-cpu-latency-request", "--variants", "hop", "--out"])
        .arg(&out)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let pid = child.id();
    let child = common::Drive::from(child);
    let receivers = || {
        processes_with(out.to_str().unwrap())
            .into_iter()
            .filter(|c| c.contains("bench-node hop"))
            .collect::<Vec<_>>()
    };
    let t = Instant::now();
    // Killed as soon as the wake segment exists, polled often: the kill then often comes
    // right after the segment was made, or right after a receiver started, before its
    // handlers are in place (it starts with SIGTERM blocked for that). A bench that made the
    // segment before starting its receivers leaves it here in most runs.
    while bench_bus_files(pid).is_empty() {
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "watchdog: the hop phase did not start within 60 s"
        );
        std::thread::sleep(Duration::from_micros(200));
    }
    // SAFETY: a signal to the bench this test started, not yet reaped.
    unsafe { libc::kill(pid as i32, libc::SIGKILL) };
    let o = wait(child, Duration::from_secs(10), "the bench after SIGKILL");
    assert_eq!(o.status.code(), None, "the bench was not killed");
    // The kernel's parent-death signal ends them (and without it they give up after 5 s
    // without a notify); 30 s is a watchdog against hangs.
    let t = Instant::now();
    while !receivers().is_empty() {
        assert!(
            t.elapsed() < Duration::from_secs(30),
            "watchdog: hop receivers still run 30 s after their bench was killed: {:?}",
            receivers()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let files = bench_bus_files(pid);
    assert!(files.is_empty(), "bus files left: {files:?}");
}

/// `scripts/under-stalls.sh` (the tests under simulated host stalls): its command runs beside
/// one stall task per CPU, its exit status is the command's, and neither a stall task nor a
/// process that the command left behind outlives it, also when the command fails. Without
/// SCHED_FIFO it refuses in one line instead.
#[test]
fn under_stalls_runs_the_command_beside_two_stall_tasks_and_leaves_none() {
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/../scripts/under-stalls.sh");
    let dir = scratch("under-stalls");
    let (pids_file, err_file) = (dir.join("pids"), dir.join("stderr"));
    let leak_file = dir.join("leaked");
    // The command leaves a sleep behind, then lists its siblings named `stalls` (the script
    // is their parent and its). Files, not pipes: a process that outlived the script would
    // hold a pipe open.
    let cmd = format!(
        "sleep 600 & echo $! > {}; pgrep -P $PPID -x stalls > {}; exit 7",
        leak_file.display(),
        pids_file.display()
    );
    let read_pids = |f: &Path| -> Vec<String> {
        std::fs::read_to_string(f)
            .unwrap_or_default()
            .split_whitespace()
            .map(String::from)
            .collect()
    };
    let alive = |pids: &[String]| -> Vec<String> {
        pids.iter()
            .filter(|p| Path::new(&format!("/proc/{p}")).exists())
            .cloned()
            .collect()
    };
    let kill_all = |pids: &[String]| {
        for p in pids {
            let _ = Command::new("kill").args(["-9", p.as_str()]).status();
        }
    };
    let mut child = Command::new("bash")
        .args([script, "sh", "-c", &cmd])
        .stdout(std::process::Stdio::null())
        .stderr(std::fs::File::create(&err_file).unwrap())
        .spawn()
        .unwrap();
    let t = Instant::now();
    let status = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break st;
        }
        if t.elapsed() > Duration::from_secs(60) {
            // The script's children first (its stall tasks), what the command left, then
            // the script.
            let _ = Command::new("pkill")
                .args(["-P", &child.id().to_string()])
                .status();
            kill_all(&read_pids(&leak_file));
            let _ = child.kill();
            panic!("watchdog: scripts/under-stalls.sh hangs");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let err = std::fs::read_to_string(&err_file).unwrap();
    let root = Command::new("id").arg("-u").output().unwrap().stdout == b"0\n";
    if !root {
        assert_eq!(status.code(), Some(1), "{err}");
        assert!(err.contains("a stall task did not start"), "{err}");
        not_checked(
            "bench under stalls",
            "not root: the stall tasks and what they leave",
        );
        return;
    }
    let (pids, leaked) = (read_pids(&pids_file), read_pids(&leak_file));
    // A process killed by the script may take a moment to be reaped by its new parent.
    let t = Instant::now();
    while !alive(&leaked).is_empty() && t.elapsed() < Duration::from_secs(2) {
        std::thread::sleep(Duration::from_millis(20));
    }
    let (stalls_alive, leaked_alive) = (alive(&pids), alive(&leaked));
    kill_all(&stalls_alive);
    kill_all(&leaked_alive);
    assert_eq!(status.code(), Some(7), "{err}");
    assert_eq!(
        pids.len(),
        2,
        "stall tasks beside the command: {pids:?}; {err}"
    );
    assert!(
        stalls_alive.is_empty(),
        "stall tasks {stalls_alive:?} outlived the script"
    );
    assert_eq!(leaked.len(), 1, "{err}");
    assert!(
        leaked_alive.is_empty(),
        "the command's leftover {leaked_alive:?} outlived the script"
    );
    assert!(
        err.contains(&format!("still running: {}", leaked[0])),
        "the script does not name what it stopped: {err}"
    );
}
