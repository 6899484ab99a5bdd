//! The bus belongs to one drive: a second drive on a busy bus is refused and the first goes
//! on unharmed, of two started at once exactly one runs, a bus folder that is a symbolic link is refused by `run` and `clean`, and a
//! run folder's `config/iceoryx2.toml` lets iceoryx2's own tools see the drive.

mod common;

use common::*;
use serde_json::Value;
use std::time::Duration;

fn stderr(o: &std::process::Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[test]
fn a_second_drive_on_a_busy_bus_is_refused_and_the_first_is_unharmed() {
    let _one = serial();
    let dir = scratch("busy");
    let bus = bus_id("busy");
    let out = dir.join("first");
    let first = Drive::start(&bus, &out, &["--duration", "2"]);
    wait_for_services(&bus);
    let second = dir.join("second");
    let o = drivelab(&[
        "run",
        "--bus",
        &bus,
        "--duration",
        "0.1",
        "--out",
        second.to_str().unwrap(),
    ]);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(
        err.contains(&format!("bus {bus} is in use by pid")),
        "{err}"
    );
    assert!(!second.exists(), "the refused run made its folder");
    // `clean` refuses it too.
    let o = drivelab(&["clean", "--bus", &bus]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(stderr(&o).contains("is in use by pid"), "{}", stderr(&o));
    // The first drive did not notice: every sample, no fault, exit 0.
    let o = wait(first, Duration::from_secs(120), "the first drive");
    assert!(o.status.success(), "{}", stderr(&o));
    let s: Value = serde_json::from_slice(&read(&out.join("summary.json"))).unwrap();
    assert_eq!(s["samples"], s["samples_expected"]);
    assert_eq!(s["samples_missing"], 0);
    assert_eq!(s["supervisor_events"].as_array().map(Vec::len), Some(0));
    assert_clean(&bus);
}

#[test]
fn of_two_drives_started_at_once_on_one_bus_exactly_one_runs() {
    let _one = serial();
    // Each saw the other's command line in the busy-bus check, and both were refused in
    // about one try of three; the bus's claim lets one of them through.
    for attempt in 0..5 {
        let dir = scratch(&format!("race{attempt}"));
        let bus = bus_id(&format!("race{attempt}"));
        let outs = [dir.join("a"), dir.join("b")];
        let drives: Vec<Drive> = outs
            .iter()
            .map(|out| Drive::start(&bus, out, &["--duration", "1"]))
            .collect();
        let results: Vec<std::process::Output> = drives
            .into_iter()
            .map(|d| d.wait_for_exit(Duration::from_secs(120), "a racing drive"))
            .collect();
        let ran: Vec<usize> = (0..2).filter(|&i| results[i].status.success()).collect();
        assert_eq!(
            ran.len(),
            1,
            "attempt {attempt}: {:?} / {:?}",
            stderr(&results[0]),
            stderr(&results[1])
        );
        let refused = 1 - ran[0];
        let err = stderr(&results[refused]);
        assert_eq!(results[refused].status.code(), Some(1), "{err}");
        assert_eq!(err.trim().lines().count(), 1, "{err}");
        assert!(
            err.contains(&format!("bus {bus} is in use by pid")),
            "{err}"
        );
        assert!(!outs[refused].exists(), "the refused run made its folder");
        assert_clean(&bus);
    }
}

#[test]
fn a_bus_folder_that_is_a_symbolic_link_is_refused_and_its_target_kept() {
    let dir = scratch("symlink");
    let bus = bus_id("symlink");
    let target = dir.join("precious");
    std::fs::create_dir_all(&target).unwrap();
    std::fs::write(target.join("keep.txt"), "keep").unwrap();
    let root = drivelab_runtime::bus::root_path(&bus);
    let link = root.trim_end_matches('/');
    std::fs::create_dir_all(std::path::Path::new(link).parent().unwrap()).unwrap();
    let _ = std::fs::remove_file(link);
    std::os::unix::fs::symlink(&target, link).unwrap();
    let out = dir.join("run");
    let runs = [
        vec!["clean", "--bus", &bus],
        vec![
            "run",
            "--bus",
            &bus,
            "--clock",
            "lockstep",
            "--duration",
            "0.02",
            "--out",
            out.to_str().unwrap(),
        ],
    ];
    let mut outcomes = Vec::new();
    for args in &runs {
        let o = drivelab(args);
        outcomes.push((args, o.status.code(), stderr(&o)));
    }
    // Remove the link before asserting, so that a failure leaves nothing behind.
    std::fs::remove_file(link).unwrap();
    for (args, code, e) in &outcomes {
        assert_eq!(*code, Some(1), "{args:?}: {e}");
        assert_eq!(e.trim().lines().count(), 1, "{e}");
        assert!(e.contains("is a symbolic link"), "{e}");
    }
    assert!(
        target.join("keep.txt").is_file(),
        "the link's target was emptied"
    );
    assert_clean(&bus);
}

#[test]
fn a_run_folder_lets_iceoryx2_tools_list_the_drives_services() {
    use iceoryx2::prelude::*;
    let _one = serial();
    let dir = scratch("iox2cfg");
    let bus = bus_id("iox2cfg");
    let out = dir.join("run");
    let drive = Drive::start(&bus, &out, &["--clock", "lockstep", "--duration", "60"]);
    wait_for_services(&bus);
    let file = out.join("config/iceoryx2.toml");
    let printed = drivelab(&["bus-config", "--bus", &bus]);
    assert!(printed.status.success());
    assert_eq!(
        printed.stdout,
        read(&file),
        "bus-config differs from the run's file"
    );
    // iceoryx2's own loader, as `iox2` uses it, and its own service listing.
    let cfg = iceoryx2::config::Config::from_file(
        &iceoryx2::prelude::FilePath::new(file.to_str().unwrap().as_bytes()).unwrap(),
    )
    .expect("iceoryx2 reads the file");
    let mut names = Vec::new();
    ipc::Service::list(&cfg, |s| {
        names.push(s.static_details.name().to_string());
        CallbackProgression::Continue
    })
    .unwrap();
    // With the default configuration (another prefix and root) the running drive is
    // invisible: the file is what makes it visible.
    let mut default_names = Vec::new();
    ipc::Service::list(&iceoryx2::config::Config::default(), |s| {
        default_names.push(s.static_details.name().to_string());
        CallbackProgression::Continue
    })
    .unwrap();
    // Stop the drive (SIGINT: it cleans up after itself) before the checks of what was
    // listed. A failure before this point is cleaned up by the drive's guard.
    // SAFETY: SIGINT to the drive's launcher, this test's child (not yet reaped).
    assert_eq!(unsafe { libc::kill(drive.id() as i32, libc::SIGINT) }, 0);
    let o = wait(drive, Duration::from_secs(60), "the drive");
    // Its services are up; the signal may still find it starting.
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("interrupted (SIGINT): drive stopped")
            || stderr(&o).contains("interrupted during start-up"),
        "{}",
        stderr(&o)
    );
    assert_clean(&bus);
    for topic in [
        "drivelab/meas",
        "drivelab/est",
        "drivelab/iref",
        "drivelab/cmd",
    ] {
        assert!(names.iter().any(|n| n == topic), "{topic} not in {names:?}");
    }
    assert!(!default_names.iter().any(|n| n == "drivelab/meas"));
}

#[test]
fn drivelab_fault_goes_through_the_supervisor_and_cannot_hit_an_impostor() {
    let _one = serial();
    let dir = scratch("impostor");
    let bus = bus_id("impostor");
    let out = dir.join("run");
    let drive = Drive::start(&bus, &out, &["--duration", "3"]);
    wait_for_progress(&bus, 1000);
    // A process that looks like the observer's host to anyone reading command lines
    // (killed by its guard if the test fails before it kills it).
    let mut impostor: Drive = std::process::Command::new("python3")
        .args(["-c", "import time; time.sleep(60)"])
        .args([
            "--bus",
            &bus,
            "--process",
            "observer",
            "--hosts",
            "observer",
        ])
        .spawn()
        .expect("python3")
        .into();
    // Bad requests fail before anything is sent: an option out of its range is a usage
    // error (2), a stage the drive lacks an error (1).
    for (args, code, says) in [
        (
            vec!["stop", "observer", "--duration-s", "1e20"],
            2,
            "a stop lasts 0.001 to 60 s",
        ),
        (
            // The option's old name, kept as an alias.
            vec!["stop", "observer", "--duration", "NaN"],
            2,
            "a stop lasts 0.001 to 60 s",
        ),
        (vec!["kill", "pump"], 1, "no stage 'pump' in the drive"),
    ] {
        let mut a = vec!["fault"];
        a.extend(args.iter().copied());
        a.extend(["--bus", &bus]);
        let o = drivelab(&a);
        assert_eq!(o.status.code(), Some(code), "{a:?}: {}", stderr(&o));
        assert_eq!(stderr(&o).trim().lines().count(), 1, "{}", stderr(&o));
        assert!(stderr(&o).contains(says), "{a:?}: {}", stderr(&o));
    }
    let fault = std::process::Command::new(DRIVELAB)
        .args(["fault", "kill", "observer", "--bus", &bus])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("start drivelab fault");
    // The requester the supervisor must name: this process, not one it read from a message.
    let fault_pid = fault.id();
    let o = wait(fault, Duration::from_secs(60), "drivelab fault kill");
    let alive = impostor.try_wait().unwrap().is_none();
    let _ = impostor.kill();
    let _ = impostor.wait();
    let d = wait(drive, Duration::from_secs(60), "the drive");
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        String::from_utf8_lossy(&o.stdout).contains(&format!(
            "supervisor: inject observer: kill (requested by pid {fault_pid})"
        )),
        "{}",
        stderr(&o)
    );
    assert!(alive, "the impostor was signalled");
    assert!(d.status.success(), "{}", stderr(&d));
    assert_clean(&bus);
    // The drive's own report has the fault: its supervisor did it.
    let s: Value = serde_json::from_slice(&read(&out.join("summary.json"))).unwrap();
    let f = &s["faults"][0];
    assert_eq!(f["service"], "observer");
    assert_eq!(f["fault"], format!("kill (requested by pid {fault_pid})"));
}
