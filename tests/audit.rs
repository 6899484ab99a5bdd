//! `drivelab run --audit-syscalls`: each stage host's loop counts the system calls it makes
//! from its first sample on beyond its waits and wakes (a seccomp filter on the loop's
//! thread; docs/architecture.md, "The system-call audit"). Nothing here asserts a time.

mod common;
use common::*;

/// The processes of a summary, with each one's counted calls (None: not counted).
fn strays(
    s: &serde_json::Value,
) -> Vec<(String, Option<serde_json::Map<String, serde_json::Value>>)> {
    s["processes"]
        .as_object()
        .unwrap()
        .iter()
        .map(|(p, v)| (p.clone(), v["stray_syscalls"].as_object().cloned()))
        .collect()
}

/// Each of a four-process drive's processes was audited and counted no call.
fn assert_four_audited_and_none_counted(s: &serde_json::Value) {
    assert_eq!(s["stray_syscalls"], 0, "{}", s["processes"]);
    let procs = strays(s);
    assert_eq!(procs.len(), 4, "{procs:?}");
    for (p, calls) in &procs {
        assert!(
            calls.as_ref().is_some_and(|c| c.is_empty()),
            "{p}: {calls:?}"
        );
    }
}

/// `drivelab run` on its own bus into a scratch folder with `extra`: its output, its run
/// folder (after checking that the bus is clean).
fn run(name: &str, extra: &[&str]) -> (std::process::Output, std::path::PathBuf) {
    let bus = bus_id(name);
    let out = scratch(name).join("run");
    let mut args = run_args(&bus, &out).to_vec();
    args.extend_from_slice(extra);
    let o = drivelab(&args);
    assert_clean(&bus);
    (o, out)
}

/// A clean real-time drive: none of its four loops makes a call beyond its waits, the summary
/// says so (and `--expect 'stray_syscalls == 0'` holds), and so does the run's line.
#[test]
fn the_loops_of_a_clean_real_time_drive_make_no_call_beyond_their_waits() {
    let _serial = serial();
    let (o, out) = run(
        "clean",
        &[
            "--duration",
            "0.3",
            "--audit-syscalls",
            "--expect",
            "stray_syscalls == 0",
        ],
    );
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let s = summary(&out);
    assert_four_audited_and_none_counted(&s);
    assert!(
        stdout.contains(
            "system-call audit: no call beyond the waits in the loops of 4 of 4 processes"
        ),
        "{stdout}"
    );
    // Without the flag, nothing is counted, and an expectation on the count fails (exit 3)
    // saying how to have it.
    let (o, out) = run(
        "unaudited",
        &["--duration", "0.05", "--expect", "stray_syscalls == 0"],
    );
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(3), "{stderr}");
    assert!(
        stderr.contains("stray_syscalls == 0 (the summary has no such figure: it is counted with --audit-syscalls)"),
        "{stderr}"
    );
    let s = summary(&out);
    assert!(s.get("stray_syscalls").is_none(), "{s}");
    assert!(strays(&s).iter().all(|(_, c)| c.is_none()));
}

/// A killed and restarted current loop: the loops that lived on make the calls with which
/// iceoryx2 drops the dead process's connections and maps the new one's (opening and
/// mapping its segments, unmapping and removing the old ones), once, inside their loops;
/// the audit counts them by name and the expectation fails on them.
#[test]
fn after_a_restart_the_survivors_loops_make_the_calls_that_reconnect_them() {
    let _serial = serial();
    let (o, out) = run(
        "restart",
        &[
            "--duration",
            "0.6",
            "--fault",
            "kill:current-loop@0.15",
            "--audit-syscalls",
            "--expect",
            "stray_syscalls == 0",
        ],
    );
    let stdout = String::from_utf8_lossy(&o.stdout);
    let stderr = String::from_utf8_lossy(&o.stderr);
    // Exit 3: the run went through and an expectation failed.
    assert_eq!(o.status.code(), Some(3), "{stdout}{stderr}");
    let s = summary(&out);
    assert_eq!(s["crashes"], 0, "{}", s["supervisor_events"]);
    assert!(
        s["stray_syscalls"].as_u64().is_some_and(|n| n > 0),
        "{}",
        s["processes"]
    );
    for (p, calls) in strays(&s) {
        let calls = calls.unwrap_or_else(|| panic!("{p}: not counted"));
        if p == "current-loop" {
            continue;
        }
        // Each survivor is connected to the current loop: it reads its commands or feeds it.
        for call in ["openat", "mmap", "munmap"] {
            assert!(
                calls
                    .get(call)
                    .and_then(|n| n.as_u64())
                    .is_some_and(|n| n > 0),
                "{p}: no {call} in {calls:?}"
            );
        }
    }
    assert!(
        stdout.contains("system-call audit: calls beyond the waits in the real-time loops: ")
            && stdout.contains("plant: "),
        "{stdout}"
    );
}

/// Ctrl-C: the stop signal interrupts each loop (its handler makes no call, and its return
/// is not the loop's), and what the hosts do once the drive is asked to stop (dropping
/// their peers' connections as they go) is the stop's: nothing counted.
#[test]
fn a_drive_stopped_by_sigint_counts_nothing_of_its_stop() {
    let _serial = serial();
    let bus = bus_id("sigint");
    let out = scratch("sigint").join("run");
    let child = Drive::start(&bus, &out, &["--duration", "5", "--audit-syscalls"]);
    wait_for_progress(&bus, 1);
    // SAFETY: signalling a child process we spawned.
    unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
    let o = child.wait_for_exit(std::time::Duration::from_secs(30), "drivelab after SIGINT");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("interrupted (SIGINT)"), "{err}");
    assert_clean(&bus);
    let s = summary(&out);
    assert_four_audited_and_none_counted(&s);
}

/// The inprocess clock starts no host: refused in one line before anything is made.
#[test]
fn the_audit_of_an_inprocess_run_is_refused() {
    assert_run_usage_error(
        &bus_id("inproc"),
        &["--clock", "inprocess", "--audit-syscalls"],
        "--audit-syscalls audits the stage hosts' loops",
    );
}
