//! Remote operation over Zenoh on localhost (docs/architecture.md, "Across machines
//! (Zenoh)"): a drive run with `--zenoh-listen` is watched, recorded and faulted from
//! `--connect` clients; bad endpoints, a busy port and a fault the drive does not allow are
//! refused with one line. Each test has its own bus and its own free port, and checks that
//! no process and no bus file is left. Times are watchdogs only.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

mod common;
use common::*;

fn endpoint(port: u16) -> String {
    format!("tcp/127.0.0.1:{port}")
}

/// Runs `drivelab ARGS` until it succeeds (the drive's bridge may not listen yet), with a
/// watchdog; returns its output.
fn until_ok(args: &[&str]) -> std::process::Output {
    let t = Instant::now();
    loop {
        let o = drivelab(args);
        if o.status.success() {
            return o;
        }
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "watchdog: drivelab {args:?} kept failing: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn a_remote_monitor_sees_the_drive_and_a_remote_recorder_writes_its_trace() {
    let _g = serial();
    let dir = scratch("monitor-record");
    let bus = bus_id("monitor-record");
    let ep = endpoint(free_port());
    // The recorder first: it waits for the drive's bridge.
    let rec_dir = dir.join("remote");
    let recorder: Drive = Command::new(DRIVELAB)
        .args(["record", "--connect", &ep, "--wait", "60", "--out"])
        .arg(&rec_dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
        .into();
    let local = dir.join("run");
    let drive = Drive::start(&bus, &local, &["--duration", "1.5", "--zenoh-listen", &ep]);
    wait_for_progress(&bus, 2000);
    // The monitor's screen over the network, as a local one shows it.
    let o = until_ok(&["monitor", "--connect", &ep, "--print"]);
    let screen = String::from_utf8(o.stdout).unwrap();
    for want in [
        format!("bus {bus} at {ep}"),
        "kyslan-pi".to_string(),
        "realtime 10000 Hz".to_string(),
        "current-loop".to_string(),
    ] {
        assert!(screen.contains(&want), "{want}\n{screen}");
    }
    let d = wait(drive, Duration::from_secs(120), "the drive");
    assert!(d.status.success(), "{}", String::from_utf8_lossy(&d.stderr));
    let r = wait(recorder, Duration::from_secs(60), "the recorder");
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    assert_clean(&bus);
    // Each row the remote recorder wrote is the drive's row of that sample, bit for bit;
    // a sample it lacks (a starved bridge's buffer overflowed: a loaded machine) is listed
    // with its cause. On a quiet machine that is none: the traces are then identical.
    let rows = |d: &std::path::Path| -> std::collections::BTreeMap<u64, String> {
        std::fs::read_to_string(d.join("trace.csv"))
            .unwrap()
            .lines()
            .skip(1)
            .map(|l| (l.split(',').next().unwrap().parse().unwrap(), l.to_string()))
            .collect()
    };
    let (l, rm) = (rows(&local), rows(&rec_dir));
    assert_eq!(l.len(), 15_000);
    // It recorded to the run's end: the plant's last sample carries the end of the run,
    // which ended the recorder.
    assert!(rm.contains_key(&14_999), "the last sample not recorded");
    for (k, row) in &rm {
        assert_eq!(Some(row), l.get(k), "sample {k} differs from the drive's");
    }
    let (ls, rs) = (summary(&local), summary(&rec_dir));
    let listed: u64 = rs["missing_samples"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|g| g["part"] == "measurement")
        .map(|g| {
            assert!(
                g["cause"].as_str().unwrap().contains("remote recorder"),
                "{g}"
            );
            g["to"].as_u64().unwrap() + 1 - g["from"].as_u64().unwrap()
        })
        .sum();
    assert_eq!(
        rm.len() as u64 + listed,
        15_000,
        "{}",
        rs["missing_samples"]
    );
    assert_eq!(rs["samples"], rm.len());
    if listed > 0 {
        not_checked(
            "a_remote_monitor_sees_the_drive_and_a_remote_recorder_writes_its_trace",
            &format!(
                "the remote recorder lost {listed} of 15000 samples (listed with their cause): \
                 the traces were compared where both have the sample"
            ),
        );
    }
    assert_eq!(rs["drive_missing_samples"], ls["missing_samples"]);
    for same in ["scenario", "deadline_misses", "metrics", "faults"] {
        assert_eq!(rs[same], ls[same], "{same}");
    }
    assert_eq!(rs["record"]["bus"], bus.as_str());
    assert_eq!(rs["record"]["rejected_frames"], 0);
    assert_eq!(rs["record"]["drive_summary"], true);
    // The drive's bridge forwarded at least what arrived (and the warm-up and end markers)
    // and refused nothing.
    let b = &ls["bridge"];
    assert_eq!(b["listen"], ep.as_str());
    for t in ["truth", "cmd"] {
        assert!(b["forwarded"][t].as_u64().unwrap() > rm.len() as u64, "{b}");
    }
    assert_eq!(
        (b["faults_refused"].as_u64(), b["rejected"].as_u64()),
        (Some(0), Some(0))
    );
}

#[test]
fn a_remote_recording_that_cannot_be_written_ends_with_its_summary_and_its_gaps() {
    let _g = serial();
    let dir = scratch("record-limited");
    let bus = bus_id("record-limited");
    let ep = endpoint(free_port());
    let rec_dir = dir.join("remote");
    // trace.csv takes about 2.3 MB a second at 10 kHz: a 2 MiB file size limit stops the
    // recording within the first second of the drive's 3.
    let mut cmd = Command::new(DRIVELAB);
    cmd.args(["record", "--connect", &ep, "--wait", "60", "--out"])
        .arg(&rec_dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    limit_file_size(&mut cmd, 2 << 20);
    let recorder: Drive = cmd.spawn().unwrap().into();
    let local = dir.join("run");
    let drive = Drive::start(&bus, &local, &["--duration", "3", "--zenoh-listen", &ep]);
    let r = wait(recorder, Duration::from_secs(60), "the recorder");
    let err = String::from_utf8_lossy(&r.stderr).into_owned();
    // The drive does not depend on its remote recorder.
    let d = wait(drive, Duration::from_secs(120), "the drive");
    assert!(d.status.success(), "{}", String::from_utf8_lossy(&d.stderr));
    assert_clean(&bus);
    assert_eq!(r.status.code(), Some(1), "{err}");
    let trace = rec_dir.join("trace.csv");
    let why = format!(
        "cannot write {}: File too large (os error 27)",
        trace.display()
    );
    let rows = drivelab_runtime::trace::read_csv(&trace).unwrap();
    let (first, last) = (rows[0].k, rows[rows.len() - 1].k);
    let errors: Vec<&str> = err.lines().filter(|l| l.contains("error")).collect();
    assert_eq!(
        errors,
        [format!(
            "drivelab: error: {why}; trace.csv ends before sample {} (what was recorded is in {}: {} of 30000 samples)",
            last + 1,
            rec_dir.display(),
            rows.len()
        )]
    );
    // Its summary lists the rows received and not written, then the samples the recording
    // ended before.
    let s = summary(&rec_dir);
    assert_eq!(s["samples"], rows.len());
    let gaps: Vec<&serde_json::Value> = s["missing_samples"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|g| g["to"].as_u64().unwrap() > last)
        .collect();
    // One after the other from the trace's end to the run's: rows not written (between
    // them, on a loaded machine, measurements the link lost), then the end.
    let mut next = last + 1;
    for (i, g) in gaps.iter().enumerate() {
        assert_eq!(g["from"], next, "{}", s["missing_samples"]);
        next = g["to"].as_u64().unwrap() + 1;
        let cause = g["cause"].as_str().unwrap();
        if i + 1 == gaps.len() {
            assert_eq!(g["part"], "measurement");
            assert_eq!(
                cause,
                format!(
                    "not recorded: the recording ended early: {why}; trace.csv ends before sample {}",
                    last + 1
                )
            );
        } else if g["part"] == "row" {
            assert_eq!(cause, format!("not in trace.csv: {why}"));
        } else {
            assert!(cause.contains("remote recorder"), "{g}");
        }
    }
    assert_eq!(next, 30_000);
    assert_eq!(gaps[0]["part"], "row", "{}", s["missing_samples"]);
    assert!(first < last, "{first} {last}");
}

#[test]
fn a_remote_fault_needs_allow_remote_faults_on_the_drive() {
    let _g = serial();
    let dir = scratch("fault");
    for allow in [false, true] {
        let name = format!("fault-{allow}");
        let bus = bus_id(&name);
        let ep = endpoint(free_port());
        let mut extra = vec!["--duration", "3", "--zenoh-listen", ep.as_str()];
        if allow {
            extra.push("--allow-remote-faults");
        }
        let out = dir.join(&name);
        let drive = Drive::start(&bus, &out, &extra);
        wait_for_progress(&bus, 3000);
        let o = drivelab(&["fault", "kill", "observer", "--connect", &ep]);
        let err = String::from_utf8_lossy(&o.stderr).into_owned();
        if allow {
            assert!(o.status.success(), "{err}");
            let answer = String::from_utf8_lossy(&o.stdout);
            assert!(
                answer.contains("supervisor: inject observer: kill"),
                "{answer}"
            );
        } else {
            assert_eq!(o.status.code(), Some(1), "{err}");
            assert_eq!(
                err.trim(),
                "drivelab: error: the drive refused: remote faults are not allowed on this drive (start it with --allow-remote-faults)"
            );
        }
        let d = wait(drive, Duration::from_secs(120), "the drive");
        let derr = String::from_utf8_lossy(&d.stderr);
        assert!(d.status.success(), "{derr}");
        assert_clean(&bus);
        let s = summary(&out);
        let kills = s["faults"].as_array().unwrap().len();
        assert_eq!(kills, usize::from(allow), "{}", s["faults"]);
        assert_eq!(s["bridge"]["faults_forwarded"], u64::from(allow));
        assert_eq!(s["bridge"]["faults_refused"], u64::from(!allow));
        if !allow {
            // The drive's operator is told too.
            assert!(derr.contains("refused a fault request"), "{derr}");
        }
    }
}

#[test]
fn bad_endpoints_a_busy_port_and_no_drive_are_one_line_errors() {
    let dir = scratch("errors");
    let one_line = |o: &std::process::Output, code: i32, needle: &str| {
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(code), "{err}");
        assert_eq!(err.trim().lines().count(), 1, "{err}");
        assert!(err.contains(needle), "{needle}: {err}");
    };
    let bus = bus_id("errors");
    let out = dir.join("run");
    let o = drivelab(&[
        "run",
        "--bus",
        &bus,
        "--out",
        out.to_str().unwrap(),
        "--zenoh-listen",
        "udp/127.0.0.1:7447",
    ]);
    one_line(
        &o,
        2,
        "--zenoh-listen: endpoint 'udp/127.0.0.1:7447': protocol 'udp' is not built in",
    );
    assert!(!out.exists(), "a refused run makes no folder");
    let o = drivelab(&[
        "run",
        "--bus",
        &bus,
        "--out",
        out.to_str().unwrap(),
        "--clock",
        "inprocess",
        "--zenoh-listen",
    ]);
    one_line(&o, 2, "--zenoh-listen needs a drive on a bus");
    assert!(!out.exists());
    let o = drivelab(&["monitor", "--connect", "127.0.0.1:7447", "--print"]);
    one_line(
        &o,
        2,
        "--connect: endpoint '127.0.0.1:7447' must be PROTOCOL/HOST:PORT",
    );
    let o = drivelab(&["fault", "kill", "plant", "--connect", "tcp/localhost:http"]);
    one_line(&o, 2, "port 'http' is not a number");
    // Nobody listens there.
    let ep = endpoint(free_port());
    let o = drivelab(&["record", "--connect", &ep, "--out", out.to_str().unwrap()]);
    one_line(&o, 1, &format!("cannot connect to {ep}"));
    // A port in use: the drive does not start, and leaves nothing behind.
    let holder = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let busy = endpoint(holder.local_addr().unwrap().port());
    let _g = serial();
    let o = drivelab(&[
        "run",
        "--bus",
        &bus,
        "--out",
        out.to_str().unwrap(),
        "--no-plots",
        "--json",
        "--zenoh-listen",
        &busy,
    ]);
    one_line(
        &o,
        1,
        &format!("--zenoh-listen: endpoint '{busy}': 127.0.0.1:"),
    );
    assert!(String::from_utf8_lossy(&o.stderr).contains("is in use"));
    assert!(!out.exists(), "a refused run makes no folder");
    assert_clean(&bus);
    // A configuration file that is not JSON5: refused before the run, with Zenoh's reason
    // and without the source location its error carries.
    let bad = dir.join("bad.json5");
    std::fs::write(&bad, "this is {{{ not json5").unwrap();
    let o = drivelab(&[
        "run",
        "--bus",
        &bus,
        "--out",
        out.to_str().unwrap(),
        "--no-plots",
        "--zenoh-listen",
        &endpoint(free_port()),
        "--zenoh-config",
        bad.to_str().unwrap(),
    ]);
    one_line(&o, 1, &format!("zenoh config {}: ", bad.display()));
    assert!(
        !String::from_utf8_lossy(&o.stderr).contains(".rs:"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(!out.exists(), "a refused run makes no folder");
    assert_clean(&bus);
}

/// The documented secure set-up, as docs/remote.md gives it: certificates from
/// scripts/zenoh-certs.sh, the drive on TLS with client certificates and access control
/// (docs/zenoh/drive-tls-acl.json5) and --allow-remote-faults. The viewer watches but its
/// fault request is dropped by the access control; the operator's is injected; a client
/// without a certificate, or on plain TCP, cannot connect.
#[test]
fn tls_with_access_control_lets_the_operator_fault_and_the_viewer_only_watch() {
    let _g = serial();
    let dir = scratch("tls");
    let repo = concat!(env!("CARGO_MANIFEST_DIR"), "/..");
    let made = Command::new("bash")
        .arg(format!("{repo}/scripts/zenoh-certs.sh"))
        .arg(dir.join("certs"))
        .output()
        .expect("bash");
    assert!(
        made.status.success(),
        "scripts/zenoh-certs.sh (openssl: bash scripts/setup.sh): {}",
        String::from_utf8_lossy(&made.stderr)
    );
    // The example configs name certs/... relative to where drivelab starts.
    let cfg = |f: &str| format!("{repo}/docs/zenoh/{f}");
    let bus = bus_id("tls");
    let port = free_port();
    let (tls, tcp) = (format!("tls/127.0.0.1:{port}"), endpoint(port));
    let drive = Command::new(DRIVELAB)
        .current_dir(&dir)
        .args([
            "run",
            "--bus",
            &bus,
            "--out",
            "run",
            "--no-plots",
            "--duration",
            "4",
        ])
        .args([
            "--zenoh-listen",
            &tls,
            "--zenoh-config",
            &cfg("drive-tls-acl.json5"),
        ])
        .arg("--allow-remote-faults")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let drive = Drive::on_bus(drive, &bus);
    wait_for_progress(&bus, 3000);
    let at = |args: &[&str], who: &str| {
        let mut c = Command::new(DRIVELAB);
        c.current_dir(&dir).args(args);
        if !who.is_empty() {
            c.args(["--zenoh-config", &cfg(who)]);
        }
        output_within(&mut c, Duration::from_secs(120))
    };
    let o = at(
        &["monitor", "--connect", &tls, "--print"],
        "viewer-tls.json5",
    );
    let screen = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(screen.contains(&format!("bus {bus} at {tls}")), "{screen}");
    let o = at(
        &["fault", "kill", "observer", "--connect", &tls],
        "viewer-tls.json5",
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("denied by its access control?"), "{err}");
    let o = at(
        &["fault", "kill", "observer", "--connect", &tls],
        "operator-tls.json5",
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    let answer = String::from_utf8_lossy(&o.stdout);
    assert!(
        answer.contains("supervisor: inject observer: kill"),
        "{answer}"
    );
    // Plain TCP to the TLS port: refused with the one-line error of a failed connection.
    let o = at(&["monitor", "--connect", &tcp, "--print"], "");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(
        err.starts_with(&format!("drivelab: error: cannot connect to {tcp}")),
        "{err}"
    );
    std::fs::write(
        dir.join("nocert.json5"),
        r#"{transport:{link:{tls:{root_ca_certificate:"certs/ca.pem"}}}}"#,
    )
    .unwrap();
    let o = at(
        &[
            "monitor",
            "--connect",
            &tls,
            "--print",
            "--zenoh-config",
            "nocert.json5",
        ],
        "",
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains(&format!("cannot connect to {tls}")), "{err}");
    let d = wait(drive, Duration::from_secs(120), "the drive");
    assert!(d.status.success(), "{}", String::from_utf8_lossy(&d.stderr));
    assert_clean(&bus);
    let s = summary(&dir.join("run"));
    assert_eq!(s["faults"].as_array().unwrap().len(), 1, "{}", s["faults"]);
    assert_eq!(s["bridge"]["faults_forwarded"], 1);
}
