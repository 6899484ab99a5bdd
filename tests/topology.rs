//! Topologies: every shipped partition of the stages into processes gives the in-process
//! trace bit for bit in lockstep; bad topologies fail with one line and leave nothing; a
//! fault on a stage takes down the process that hosts it, with all its stages, and the
//! supervisor restarts that process. Timeouts are watchdogs only.

mod common;
use common::*;
use std::process::{Command, Stdio};
use std::time::Duration;

/// The shipped topologies. In lockstep `four-process-standby` starts no twin (a simulated
/// kill rejoins), so it gives the trace of the others; `split-hil` without `--machine`
/// runs both of its machines' processes here (tests/split.rs splits it).
const TOPOLOGIES: [&str; 5] = [
    "four-process",
    "two-process",
    "one-process",
    "four-process-standby",
    "split-hil",
];

#[test]
fn every_shipped_topology_gives_the_inprocess_trace_in_lockstep() {
    let _serial = serial();
    for (scenario, seconds) in [
        ("kyslan-pi", "0.06"),
        ("low-rst-sensorless", "1.3"),
        ("miyajima-polar-400rpm", "0.02"),
    ] {
        let (ip, _) = run_ok(
            &format!("ip{}", &scenario[..3]),
            &[
                "--scenario",
                scenario,
                "--duration",
                seconds,
                "--clock",
                "inprocess",
            ],
        );
        let want = read(&ip.join("trace.csv"));
        assert!(want.len() > 1000, "{scenario}: trace too short");
        for (i, t) in TOPOLOGIES.into_iter().enumerate() {
            let tag = format!("{}{i}", &scenario[..3]);
            let lockstep = |tag: &str, extra: &[&str]| {
                let mut args = vec![
                    "--scenario",
                    scenario,
                    "--duration",
                    seconds,
                    "--clock",
                    "lockstep",
                    "--topology",
                    t,
                ];
                args.extend_from_slice(extra);
                run_ok(tag, &args)
            };
            let (ls, s) = lockstep(&tag, &[]);
            assert!(
                read(&ls.join("trace.csv")) == want,
                "{scenario} with topology {t}: the lockstep trace differs from inprocess"
            );
            // Without real-time set-up the processes run side by side on both cores, so a
            // producer can be a sample ahead while a consumer still works (on one core at
            // rising priorities it never is): the same trace, and no stall.
            let (free, _) = lockstep(&format!("{tag}free"), &["--no-rt"]);
            assert!(
                read(&free.join("trace.csv")) == want,
                "{scenario} with topology {t}, --no-rt: the lockstep trace differs from inprocess"
            );
            // summary.json → processes is keyed by process, each with its stages; together
            // they host every stage once.
            let procs = s["processes"].as_object().unwrap();
            let mut stages: Vec<String> = procs
                .values()
                .flat_map(|p| p["stages"].as_array().unwrap().iter())
                .map(|v| v.as_str().unwrap().to_string())
                .collect();
            stages.sort();
            assert_eq!(
                stages,
                ["current-loop", "observer", "plant", "speed-loop"],
                "{t}: {procs:?}"
            );
            let expected = match t {
                "four-process" | "four-process-standby" | "split-hil" => 4,
                "two-process" => 2,
                _ => 1,
            };
            assert_eq!(procs.len(), expected, "{t}: {procs:?}");
        }
    }
}

#[test]
fn iceoryx2_event_wake_ups_give_the_same_trace() {
    let _serial = serial();
    // The futex words are the default; the iceoryx2 event service is the other transport
    // of wake-ups. Same trace bit for bit, in a split topology (hops on the bus).
    let sc = variant(
        "evwake",
        "kyslan-pi",
        &[(
            "# 200 W at 3500 rpm",
            "# 200 W at 3500 rpm\n\n[timing]\nwake = \"iceoryx2\"",
        )],
    );
    let sc = sc.to_str().unwrap();
    let (ip, _) = run_ok(
        "evip",
        &[
            "--scenario",
            sc,
            "--duration",
            "0.06",
            "--clock",
            "inprocess",
        ],
    );
    let (ls, _) = run_ok(
        "evls",
        &[
            "--scenario",
            sc,
            "--duration",
            "0.06",
            "--clock",
            "lockstep",
            "--topology",
            "two-process",
        ],
    );
    assert!(read(&ls.join("trace.csv")) == read(&ip.join("trace.csv")));
    let used = std::fs::read_to_string(ls.join("scenario.toml")).unwrap();
    assert!(used.contains("wake = \"iceoryx2\""), "{used}");
}

#[test]
fn bad_topologies_fail_with_one_line_naming_the_problem_and_leave_nothing() {
    let _serial = serial();
    let dir = scratch("badtopo");
    let bus = bus_id("badtopo");
    let p = |name: &str, stages: &str| {
        format!("[[process]]\nname = \"{name}\"\nstages = [{stages}]\ncpu = 1\npriority = 70\n")
    };
    // The built-in host, as the `exec` of a stage it does not host.
    let host = std::path::Path::new(DRIVELAB)
        .with_file_name("drivelab-host")
        .display()
        .to_string();
    // An executable whose --describe answer declares one stage twice.
    let twice = dir.join("twice.sh");
    let mine = r#"{"name":"mine","inputs":[{"topic":"est","role":"trigger","delay":0,"max_age":1,"on_stale":"fallback"}],"outputs":[],"divider":1}"#;
    std::fs::write(&twice, format!("#!/bin/sh\necho '[{mine},{mine}]'\n")).unwrap();
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&twice, std::fs::Permissions::from_mode(0o755)).unwrap();
    }
    let cases = [
        (
            "twice.toml",
            p("a", "\"plant\", \"observer\"")
                + &p("b", "\"observer\", \"current-loop\", \"speed-loop\""),
            "stage 'observer' is hosted twice",
        ),
        (
            "missing.toml",
            p("a", "\"plant\", \"observer\", \"current-loop\""),
            "stage 'speed-loop' is not hosted by any process",
        ),
        (
            "unknown.toml",
            p(
                "a",
                "\"plant\", \"observer\", \"current-loop\", \"speed-loop\", \"torque-loop\"",
            ),
            "unknown stage 'torque-loop'",
        ),
        (
            "prio.toml",
            p(
                "a",
                "\"plant\", \"observer\", \"current-loop\", \"speed-loop\"",
            )
            .replace("70", "120"),
            "priority = 120 must be in 1..=99",
        ),
        (
            "exec.toml",
            p(
                "a",
                "\"plant\", \"observer\", \"current-loop\", \"speed-loop\"",
            ) + &p("b", "\"position-loop\"")
                + "exec = \"no-such-binary\"\n",
            "no-such-binary not found",
        ),
        (
            "notitsstage.toml",
            p(
                "a",
                "\"plant\", \"observer\", \"current-loop\", \"speed-loop\"",
            ) + &p("b", "\"torque-loop\"")
                + &format!("exec = \"{host}\"\n"),
            "hosts no stage 'torque-loop' (its own stages: none; and the built-in ones)",
        ),
        (
            "notahost.toml",
            p(
                "a",
                "\"plant\", \"observer\", \"current-loop\", \"speed-loop\"",
            ) + "exec = \"/bin/true\"\n",
            "process 'a': /bin/true --describe: not a stage list",
        ),
        (
            "twice.toml",
            p(
                "a",
                "\"plant\", \"observer\", \"current-loop\", \"speed-loop\"",
            ) + &p("b", "\"mine\"")
                + &format!("exec = \"{}\"\n", twice.display()),
            "--describe: stage 'mine' is declared twice",
        ),
        (
            "standby.toml",
            p("a", "\"plant\", \"observer\"")
                + "standby = true\n"
                + &p("b", "\"current-loop\", \"speed-loop\""),
            "process 'a': standby = true is not for the plant's process",
        ),
    ];
    for (file, text, needle) in cases {
        let f = dir.join(file);
        std::fs::write(&f, text).unwrap();
        let out = dir.join(format!("out-{file}"));
        let o = drivelab(&[
            "run",
            "--clock",
            "lockstep",
            "--bus",
            &bus,
            "--out",
            out.to_str().unwrap(),
            "--topology",
            f.to_str().unwrap(),
        ]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{file}: {err}");
        assert_eq!(
            err.lines().count(),
            1,
            "{file}: expected one line, got {err}"
        );
        assert!(err.contains(needle), "{file}: '{needle}' not in {err}");
        assert!(!out.exists(), "{file}: a failed run left its folder");
        assert_clean(&bus);
    }
    // A file named from the working folder, without a folder in its name.
    let out = dir.join("out-relative");
    let child = std::process::Command::new(DRIVELAB)
        .current_dir(&dir)
        .args(["run", "--clock", "lockstep", "--bus", &bus, "--out"])
        .arg(&out)
        .args(["--topology", "prio.toml"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let o = wait(
        Drive::on_bus(child, &bus),
        std::time::Duration::from_secs(300),
        "drivelab run",
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("priority = 120 must be in 1..=99") && err.lines().count() == 1,
        "{err}"
    );
    assert!(!out.exists());
    assert_clean(&bus);
    let out = dir.join("out-unknown");
    let o = drivelab(&[&run_args(&bus, &out)[..], &["--topology", "three-process"]].concat());
    assert_eq!(o.status.code(), Some(1));
    assert!(!out.exists(), "an unknown topology's run made its folder");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains(
            "unknown topology 'three-process' (known: four-process, four-process-standby, one-process, split-hil, two-process)"
        ),
        "{err}"
    );
    // With --rt-strict, a process pinned to a CPU the drive may not use fails its start: it
    // is refused before the run, in one line. (Without it, the process warns and runs.)
    let f = dir.join("cpu99.toml");
    std::fs::write(
        &f,
        p(
            "a",
            "\"plant\", \"observer\", \"current-loop\", \"speed-loop\"",
        )
        .replace("cpu = 1", "cpu = 99"),
    )
    .unwrap();
    let out = dir.join("out-cpu99");
    // Lockstep keeps the cores (not the priorities): refused the same way.
    for clock in ["realtime", "lockstep"] {
        let o = drivelab(&[
            "run",
            "--rt-strict",
            "--clock",
            clock,
            "--bus",
            &bus,
            "--out",
            out.to_str().unwrap(),
            "--topology",
            f.to_str().unwrap(),
        ]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{clock}: {err}");
        assert!(
            err.contains(
                "--rt-strict: process a is pinned to CPU 99, which this drive may not use (CPUs: "
            ) && err.trim().lines().count() == 1,
            "{clock}: {err}"
        );
        assert!(!out.exists(), "{clock}: the refused run made its folder");
        assert_clean(&bus);
    }
    // Without --rt-strict a real-time drive refuses a CPU the machine does not have (a
    // placement it cannot measure), also in one line and before the run.
    let o = drivelab(
        &[
            &run_args(&bus, &out)[..],
            &["--topology", f.to_str().unwrap()],
        ]
        .concat(),
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("process a is pinned to CPU 99, which this machine does not have (this drive may use CPUs ")
            && err.trim().lines().count() == 1,
        "{err}"
    );
    assert!(!out.exists(), "the refused run made its folder");
    assert_clean(&bus);
    // A scenario that places its services in [placement] and in [[process]] tables.
    let both = dir.join("both.toml");
    std::fs::write(
        &both,
        "name = \"x\"\nduration_s = 0.01\n[motor]\npreset = \"kyslan2015\"\n[placement.plant]\ncore = 0\npriority = 50\n"
            .to_string()
            + &p("a", "\"plant\", \"observer\", \"current-loop\", \"speed-loop\""),
    )
    .unwrap();
    let out = dir.join("out-both");
    let o = drivelab(
        &[
            &run_args(&bus, &out)[..],
            &["--scenario", both.to_str().unwrap()],
        ]
        .concat(),
    );
    assert_eq!(o.status.code(), Some(1));
    assert!(!out.exists(), "the refused run made its folder");
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("either in [placement] or in [[process]]"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert_clean(&bus);
}

#[test]
fn a_fault_on_a_stage_takes_down_its_whole_process_which_is_restarted() {
    let _serial = serial();
    let (out, s) = run_ok(
        "procfault",
        &[
            "--duration",
            "1.2",
            "--topology",
            "two-process",
            "--fault",
            "kill:speed-loop@0.4",
        ],
    );
    let f = &s["faults"][0];
    assert_eq!(f["service"], "speed-loop");
    assert_eq!(f["process"], "controller", "{f}");
    let ev: Vec<(String, String)> = s["supervisor_events"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| {
            (
                e["event"].as_str().unwrap().to_string(),
                e["process"].as_str().unwrap().to_string(),
            )
        })
        .collect();
    for want in ["exited", "restarted", "ready"] {
        assert!(
            ev.contains(&(want.to_string(), "controller".to_string())),
            "no '{want}' of process controller in {ev:?}"
        );
    }
    // The observer and the current loop went down with it: the plant saw its commands stop
    // (it had to hold or go safe), which killing the speed loop alone never causes.
    assert_eq!(f["detected_by"], "plant", "{f}");
    assert!(f["republished_ms"].is_number(), "{f}");
    // After the restart every stage of the process ran again: the current loop produced
    // commands to the end of the run.
    let trace = std::fs::read_to_string(out.join("trace.csv")).unwrap();
    let last = trace.lines().last().unwrap();
    assert!(!last.contains("NaN"), "no command at the end: {last}");
}

/// Two processes on one core at one SCHED_FIFO priority: the kernel runs them in the order
/// they become ready, not along the data graph; a real-time run says so in one warning line
/// (lockstep, which does not use the priorities, does not).
#[test]
fn processes_sharing_a_core_and_a_priority_are_warned_about() {
    let _serial = serial();
    let dir = scratch("same-prio");
    let topo = dir.join("same.toml");
    std::fs::write(
        &topo,
        "[[process]]\nname = \"plant\"\nstages = [\"plant\"]\ncpu = 1\npriority = 70\n\
         [[process]]\nname = \"controller\"\nstages = [\"observer\", \"current-loop\", \"speed-loop\"]\ncpu = 1\npriority = 70\n",
    )
    .unwrap();
    let want = "drivelab: warning: processes 'plant', 'controller' run on CPU 1 at the same SCHED_FIFO priority 70";
    for (tag, clock, warned) in [
        ("same-prio-rt", "realtime", true),
        ("same-prio-ls", "lockstep", false),
    ] {
        let bus = bus_id(tag);
        let out = dir.join(tag);
        let mut args = run_args(&bus, &out).to_vec();
        args.extend_from_slice(&[
            "--duration",
            "0.05",
            "--clock",
            clock,
            "--topology",
            topo.to_str().unwrap(),
        ]);
        let o = drivelab(&args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(o.status.success(), "{clock}: {err}");
        assert_eq!(
            err.lines().filter(|l| l.starts_with(want)).count(),
            usize::from(warned),
            "{clock}: {err}"
        );
        assert_clean(&bus);
    }
}

/// A process whose `exec` is a script that starts a helper and then the host: the helper is
/// killed when the drive ends (named in one warning line), not left running. The same
/// script floods stdout, which the launcher reads only up to READY: the launcher's memory
/// stays bounded (it kept every line before).
#[test]
fn what_a_stage_process_leaves_running_is_killed_and_its_chatter_is_not_kept() {
    let _serial = serial();
    let dir = scratch("strays");
    let marker = format!("86399.{}", std::process::id());
    // Whatever the outcome, no helper outlives the test (it would sleep for a day).
    struct KillHelpers(String);
    impl Drop for KillHelpers {
        fn drop(&mut self) {
            let _ = std::process::Command::new("pkill")
                .args(["-KILL", "-f", &self.0])
                .status();
        }
    }
    let _helpers = KillHelpers(format!("sleep {marker}"));
    let host = std::path::Path::new(DRIVELAB).with_file_name("drivelab-host");
    let wrapper = dir.join("wrapper.sh");
    std::fs::write(
        &wrapper,
        format!(
            "#!/bin/sh\nsleep {marker} >/dev/null 2>&1 </dev/null &\n\
             (sleep 0.3; yes 'a chatty stage prints this line at every sample' | head -c 300000000) &\n\
             exec '{}' \"$@\"\n",
            host.display()
        ),
    )
    .unwrap();
    let topo = plant_and_controller(&dir, &wrapper);
    let bus = bus_id("strays");
    let out = dir.join("run");
    let mut child = start_without_stdout(
        &bus,
        &out,
        &["--duration", "2", "--topology", topo.to_str().unwrap()],
    );
    // The launcher's peak memory, read until it exits.
    let pid = child.id();
    let mut peak_kib = 0u64;
    let t = std::time::Instant::now();
    while child.try_wait().unwrap().is_none() {
        assert!(
            t.elapsed() < Duration::from_secs(120),
            "watchdog: the drive hangs"
        );
        if let Ok(status) = std::fs::read_to_string(format!("/proc/{pid}/status")) {
            if let Some(kib) = status
                .lines()
                .find_map(|l| l.strip_prefix("VmHWM:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
            {
                peak_kib = kib;
            }
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let o = wait(child, Duration::from_secs(10), "the drive");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(0), "{err}");
    let warning = err
        .lines()
        .find(|l| l.contains("left running"))
        .unwrap_or_else(|| panic!("no warning about the helper: {err}"));
    // The helper, and, on a busy machine, the flood that has not ended yet.
    assert!(
        warning.starts_with(
            "drivelab: warning: killed what the stage hosts left running after the drive: "
        ) && warning.contains(" (sleep)"),
        "{warning}"
    );
    assert!(
        processes_with(&marker).is_empty(),
        "the stage's helper was left running"
    );
    // 300 MB went through the host's stdout; the launcher keeps a bounded queue of lines.
    assert!(peak_kib > 0, "never read the launcher's memory");
    assert!(
        peak_kib < 150 * 1024,
        "the launcher's peak memory {peak_kib} kB: it kept the stage's stdout"
    );
    assert_eq!(summary(&out)["samples_missing"], 0);
    assert_clean(&bus);
}

/// A process whose `exec` is a wrapper script that runs the stage host as its child instead
/// of `exec`ing it: the launcher names that in one warning line, an injected kill reaches
/// the host (it reached only the shell before, and the restart then found the old host still
/// holding its topics), and the process is restarted and the drive recovers.
#[test]
fn a_kill_reaches_a_stage_host_that_a_wrapper_script_started_without_exec() {
    let _serial = serial();
    let dir = scratch("nowrapexec");
    let host = std::path::Path::new(DRIVELAB).with_file_name("drivelab-host");
    let wrapper = dir.join("wrapper.sh");
    std::fs::write(
        &wrapper,
        format!("#!/bin/sh\n'{}' \"$@\"\n", host.display()),
    )
    .unwrap();
    let topo = plant_and_controller(&dir, &wrapper);
    let bus = bus_id("nowrapexec");
    let out = dir.join("run");
    let child = start_without_stdout(
        &bus,
        &out,
        &[
            "--duration",
            "2",
            "--topology",
            topo.to_str().unwrap(),
            "--fault",
            "kill:current-loop@0.5",
        ],
    );
    let o = wait(child, Duration::from_secs(120), "the drive");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(0), "{err}");
    let warnings: Vec<&str> = err
        .lines()
        .filter(|l| l.contains("instead of becoming it"))
        .collect();
    assert_eq!(warnings.len(), 1, "{err}");
    assert!(
        warnings[0].starts_with("drivelab: warning: process c: ")
            && warnings[0].contains("wrapper.sh started its stage host as a child (pid "),
        "{}",
        warnings[0]
    );
    let s = summary(&out);
    let f = &s["faults"][0];
    assert_eq!(f["service"], "current-loop", "{f}");
    assert!(f["speed_recovered_ms"].is_number(), "{f}");
    let ev: Vec<String> = s["supervisor_events"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["service"] == "c" || e["process"] == "c")
        .map(|e| e["event"].as_str().unwrap().to_string())
        .collect();
    for want in ["inject", "exited", "restarted", "ready"] {
        assert!(ev.iter().any(|e| e == want), "no '{want}' in {ev:?}: {err}");
    }
    // The killed host went with its fault, not after the drive.
    assert!(!err.contains("left running"), "{err}");
    assert_clean(&bus);
}

/// Ctrl-C while the drive starts (the plant is READY and waits for its GO, another process
/// is still starting): the launcher stops, and the plant ends on its own when the launcher
/// closes its stdin, instead of being killed with SIGKILL after 3 s of waiting for a GO that
/// never comes.
#[test]
fn a_drive_stopped_during_its_start_up_ends_every_process_without_sigkill() {
    let _serial = serial();
    let dir = scratch("stopstart");
    let marker = format!("86397.{}", std::process::id());
    let host = std::path::Path::new(DRIVELAB).with_file_name("drivelab-host");
    let slow = dir.join("slow.sh");
    std::fs::write(
        &slow,
        format!(
            // The questions before the start (`--describe`) are answered at once.
            "#!/bin/sh\ncase \"$1\" in --describe|--check-rt) exec '{host}' \"$@\";; esac\n\
             sleep {marker} </dev/null\nexec '{host}' \"$@\"\n",
            host = host.display()
        ),
    )
    .unwrap();
    let topo = plant_and_controller(&dir, &slow);
    let bus = bus_id("stopstart");
    let out = dir.join("run");
    let child = start_without_stdout(
        &bus,
        &out,
        &["--duration", "2", "--topology", topo.to_str().unwrap()],
    );
    // The plant waits for its GO: blocked in read(2) on its stdin (fd 0).
    let t = std::time::Instant::now();
    let waiting_for_go = || {
        std::fs::read_dir("/proc").unwrap().flatten().any(|e| {
            let cmd = std::fs::read(e.path().join("cmdline")).unwrap_or_default();
            let cmd = String::from_utf8_lossy(&cmd).replace('\0', " ");
            let syscall = std::fs::read_to_string(e.path().join("syscall")).unwrap_or_default();
            // The slow process is still in its `sleep`: the only host of the bus is the plant's.
            cmd.contains("drivelab-host") && cmd.contains(&bus) && syscall.starts_with("0 0x0 ")
        })
    };
    while !waiting_for_go() {
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "watchdog: the plant never waited for its GO"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(
        !processes_with(&marker).is_empty(),
        "the slow process already started"
    );
    // SAFETY: signalling a child process we spawned.
    unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
    let o = wait(child, Duration::from_secs(60), "the drive after SIGINT");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("interrupted during start-up"), "{err}");
    assert!(!err.contains("did not end within 3 s"), "{err}");
    assert!(
        processes_with(&marker).is_empty(),
        "the slow start was left running"
    );
    assert_clean(&bus);
}

/// Starts `drivelab run --bus BUS --out OUT --no-plots EXTRA` behind a guard, its stdout
/// dropped and its stderr piped.
fn start_without_stdout(bus: &str, out: &std::path::Path, extra: &[&str]) -> Drive {
    let child = Command::new(DRIVELAB)
        .args(run_args(bus, out))
        .args(extra)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    Drive::on_bus(child, bus)
}

/// A topology of two processes on core 1: `p` (the plant) and `c` (observer, current loop,
/// speed loop) run by executable script `exec`, which is made executable.
fn plant_and_controller(dir: &std::path::Path, exec: &std::path::Path) -> std::path::PathBuf {
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(exec, std::fs::Permissions::from_mode(0o755)).unwrap();
    let topo = dir.join("topology.toml");
    std::fs::write(
        &topo,
        format!(
            "[[process]]\nname = \"p\"\nstages = [\"plant\"]\ncpu = 1\npriority = 70\n\n\
             [[process]]\nname = \"c\"\nstages = [\"observer\", \"current-loop\", \"speed-loop\"]\n\
             cpu = 1\npriority = 72\nexec = \"{}\"\n",
            exec.display()
        ),
    )
    .unwrap();
    topo
}
