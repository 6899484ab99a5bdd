//! `drivelab bench --quick` end to end. It checks the report's structure and verdict logic,
//! never a latency figure (those belong to the bench's own output).

use std::process::Command;
use std::time::{Duration, Instant};

/// Runs `drivelab bench ARGS --out OUT` with a watchdog against hangs.
fn bench(args: &[&str], out: &std::path::Path) -> std::process::Output {
    let mut child = Command::new(env!("CARGO_BIN_EXE_drivelab"))
        .arg("bench")
        .args(args)
        .args(["--out", out.to_str().unwrap()])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let t = Instant::now();
    while child.try_wait().unwrap().is_none() {
        assert!(
            t.elapsed() < Duration::from_secs(300),
            "watchdog: bench {args:?} hangs"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let o = child.wait_with_output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    o
}

#[test]
fn bench_quick_runs_end_to_end_and_writes_its_report() {
    let out = std::env::temp_dir().join(format!("drivelab-bench-test-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let o = bench(&["--quick", "--json"], &out);
    let report: serde_json::Value =
        serde_json::from_slice(&o.stdout).expect("bench --json prints JSON");
    let rows = report["rows"].as_array().unwrap();
    let variants: Vec<&str> = rows
        .iter()
        .map(|r| r["variant"].as_str().unwrap())
        .collect();
    assert_eq!(
        variants,
        ["floor", "inprocess", "uds", "iceoryx2", "iceoryx2+spin"]
    );
    for r in rows {
        assert!(r["samples"].as_u64().unwrap() > 0, "{r}");
        for q in ["p50", "p99", "p999", "max"] {
            assert!(r["cycle_us"][q].as_f64().is_some(), "{r}");
        }
        // The verdict follows its definition: cycle p99.9 < Ts and misses/M ≤ 2 × floor + 10.
        if r["variant"] != "floor" {
            let floor_pm = rows[0]["misses_per_million"].as_f64().unwrap();
            let expect = r["cycle_us"]["p999"].as_f64().unwrap() < 100.0
                && r["misses_per_million"].as_f64().unwrap() <= 2.0 * floor_pm + 10.0;
            assert_eq!(r["holds_budget"].as_bool(), Some(expect), "{r}");
            assert!(r["p99_ratio_to_floor"].as_f64().is_some());
        }
    }
    assert!(rows[3]["p99_ratio_to_uds"].as_f64().is_some());
    // Every variant ran under the CPU wake-up latency request when this user may make one.
    let can_request = std::fs::OpenOptions::new()
        .write(true)
        .open("/dev/cpu_dma_latency")
        .is_ok();
    let held = &report["cpu_latency_request_us"];
    assert_eq!(held.as_u64(), can_request.then_some(0), "{held}");
    assert!(rows[4]["p99_ratio_to_uds"].as_f64().is_some());
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
        "iceoryx2-one-core-10000hz.hgrm",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    let md = std::fs::read_to_string(out.join("bench.md")).unwrap();
    assert!(md.contains("| 10 kHz | iceoryx2 | one-core |"), "{md}");
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn bench_rounds_interleave_the_variants_and_merge_their_samples() {
    let out = std::env::temp_dir().join(format!("drivelab-bench-rounds-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let o = bench(
        &["--quick", "--rounds", "2", "--spin-us", "0", "--json"],
        &out,
    );
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(report["rounds"], 2);
    let rows = report["rows"].as_array().unwrap();
    // 0.2 s at 10 kHz in two slices of 0.1 s: both slices count.
    let floor = rows[0]["samples"].as_u64().unwrap();
    assert!((1990..=2010).contains(&floor), "floor samples {floor}");
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
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--rounds must be in 1..=100"));
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn bench_compares_topologies_with_their_cpu_time() {
    let out = std::env::temp_dir().join(format!("drivelab-bench-topo-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
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
    ]
    .iter()
    .map(|(a, b)| (a.to_string(), b.to_string()))
    .collect();
    assert_eq!(got, want);
    for r in &rows[1..] {
        // Both rounds of 0.1 s at 10 kHz count: 2000 samples (the plant's own count).
        assert_eq!(r["samples"].as_u64(), Some(2000), "{r}");
        assert!(r["cpu_s_per_s"].as_f64().is_some_and(|c| c > 0.0), "{r}");
        assert!(r["p99_ratio_to_floor"].as_f64().is_some(), "{r}");
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
