//! The drive split across two machines (docs/architecture.md, "The drive split across
//! machines"): the plant on one, the observer and both loops on the other, each with its
//! own bus, joined by their Zenoh bridges. The machines are two network namespaces joined
//! by a veth pair that the test makes and removes; where namespaces cannot be made (no
//! root, no `ip`), the test says so in one line and joins the sides over localhost. Each
//! side has its own bus; no process, namespace or bus file is left. Times are watchdogs.

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::Duration;

mod common;
use common::*;

/// Two network namespaces joined by a veth pair (10.200.N.1 and .2), removed on drop (the
/// veth pair goes with them).
struct Wire {
    names: [String; 2],
    addrs: [String; 2],
}

impl Wire {
    /// Makes the pair, or says why not.
    fn make(tag: &str) -> Result<Self, String> {
        let id = std::process::id() % 100_000;
        let n = id % 250 + 1;
        let w = Self {
            names: [format!("dl{id}{tag}a"), format!("dl{id}{tag}b")],
            addrs: [format!("10.200.{n}.1"), format!("10.200.{n}.2")],
        };
        let veth = [format!("dv{id}{tag}a"), format!("dv{id}{tag}b")];
        let ip = |args: &[&str]| -> Result<(), String> {
            match Command::new("ip").args(args).output() {
                Ok(o) if o.status.success() => Ok(()),
                Ok(o) => Err(format!(
                    "ip {}: {}",
                    args.join(" "),
                    String::from_utf8_lossy(&o.stderr).trim()
                )),
                Err(e) => Err(format!("ip: {e}")),
            }
        };
        // Made one by one: a failure leaves the namespaces made so far to `drop`.
        ip(&["netns", "add", &w.names[0]])?;
        ip(&["netns", "add", &w.names[1]])?;
        ip(&[
            "link", "add", &veth[0], "type", "veth", "peer", "name", &veth[1],
        ])?;
        let wired = (|| {
            for ((ns, v), addr) in w.names.iter().zip(&veth).zip(&w.addrs) {
                ip(&["link", "set", v, "netns", ns])?;
                ip(&["-n", ns, "addr", "add", &format!("{addr}/30"), "dev", v])?;
                ip(&["-n", ns, "link", "set", v, "up"])?;
                ip(&["-n", ns, "link", "set", "lo", "up"])?;
            }
            Ok(())
        })();
        if wired.is_err() {
            // A veth end still outside its namespace would outlive them.
            let _ = ip(&["link", "del", &veth[0]]);
        }
        wired.map(|()| w)
    }

    fn exists(name: &str) -> bool {
        Path::new("/run/netns").join(name).exists()
    }
}

impl Drop for Wire {
    fn drop(&mut self) {
        for n in &self.names {
            let _ = Command::new("ip").args(["netns", "del", n]).output();
        }
    }
}

/// Where the two sides run: in the namespaces of `wire`, or here over localhost.
struct Sides {
    wire: Option<Wire>,
    port: u16,
}

impl Sides {
    fn new(tag: &str) -> Self {
        let wire = match Wire::make(tag) {
            Ok(w) => Some(w),
            Err(why) => {
                not_checked(
                    &format!("split {tag}"),
                    &format!("no network namespaces here ({why}): the two sides join over localhost instead"),
                );
                None
            }
        };
        let port = free_port();
        Self { wire, port }
    }

    /// The listening side's endpoint: its veth address, or localhost.
    fn endpoint(&self) -> String {
        match &self.wire {
            Some(w) => format!("tcp/{}:{}", w.addrs[0], self.port),
            None => format!("tcp/127.0.0.1:{}", self.port),
        }
    }

    /// `drivelab ARGS` on side `i` (0 listens, 1 joins), a drive on `bus`, output piped.
    fn start(&self, i: usize, bus: &str, args: &[&str]) -> Drive {
        let mut cmd = match &self.wire {
            Some(w) => {
                let mut c = Command::new("ip");
                c.args(["netns", "exec", &w.names[i], DRIVELAB]);
                c
            }
            None => Command::new(DRIVELAB),
        };
        // `ip netns exec` execs drivelab in place: the child is the launcher.
        let child = cmd
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start drivelab");
        Drive::on_bus(child, bus)
    }
}

/// `run --bus BUS --out OUT --no-plots --topology split-hil --machine M` and `extra`.
fn side_args<'a>(bus: &'a str, out: &'a Path, machine: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
    let mut v = run_args(bus, out).to_vec();
    v.extend_from_slice(&["--topology", "split-hil", "--machine", machine]);
    v.extend_from_slice(extra);
    v
}

fn ok(o: &Output, what: &str) {
    assert!(
        o.status.success(),
        "{what} failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
}

/// Runs kyslan-pi for 0.5 s split across the two sides (the simulator listens, the board
/// joins), with `extra` on both; asserts that both succeed and leave nothing on their buses.
/// Returns both run folders and the sides (their namespaces go when it is dropped).
fn run_split(tag: &str, name: &str, extra: &[&str]) -> (PathBuf, PathBuf, Sides) {
    let dir = scratch(name);
    let (bus_a, bus_b) = (
        bus_id(&format!("{name}-simulator")),
        bus_id(&format!("{name}-board")),
    );
    let sides = Sides::new(tag);
    let ep = sides.endpoint();
    let (out_a, out_b) = (dir.join("simulator"), dir.join("board"));
    let mut common = vec!["--scenario", "kyslan-pi", "--duration", "0.5"];
    common.extend_from_slice(extra);
    let mut a = common.clone();
    a.extend(["--zenoh-listen", &ep]);
    let mut b = common;
    b.extend(["--zenoh-connect", &ep]);
    let sim = sides.start(0, &bus_a, &side_args(&bus_a, &out_a, "simulator", &a));
    let board = sides.start(1, &bus_b, &side_args(&bus_b, &out_b, "board", &b));
    let ob = wait(board, Duration::from_secs(240), "the board's side");
    let oa = wait(sim, Duration::from_secs(240), "the simulator's side");
    ok(&oa, "the simulator's side");
    ok(&ob, "the board's side");
    assert_clean(&bus_a);
    assert_clean(&bus_b);
    (out_a, out_b, sides)
}

#[test]
fn a_split_drive_in_lockstep_gives_the_in_process_trace_on_both_machines() {
    let _g = serial();
    // 0.5 s: the speed step, the load step and the recovery.
    let (out_a, out_b, sides) = run_split("l", "lockstep", &["--clock", "lockstep"]);
    let (ref_dir, _) = run_ok(
        "lockstep-inprocess",
        &[
            "--scenario",
            "kyslan-pi",
            "--clock",
            "inprocess",
            "--duration",
            "0.5",
        ],
    );
    let ref_trace = read(&ref_dir.join("trace.csv"));
    // Both machines' recorders wrote the whole trace, each the in-process one byte for byte.
    assert_eq!(ref_trace.iter().filter(|&&b| b == b'\n').count(), 5001);
    assert!(
        read(&out_a.join("trace.csv")) == ref_trace,
        "the simulator's trace differs from the in-process trace"
    );
    assert!(
        read(&out_b.join("trace.csv")) == ref_trace,
        "the board's trace differs from the in-process trace"
    );
    // The link carried every message once, and each side ran only its own processes.
    let (sa, sb) = (summary(&out_a), summary(&out_b));
    // Lockstep holds no core at real-time priority, the bridges' threads (their own and
    // Zenoh's) included.
    for s in [&sa, &sb] {
        let p = s["bridge"]["thread_policies"]
            .as_object()
            .unwrap_or_else(|| panic!("no thread policies: {}", s["bridge"]));
        assert!(
            p.contains_key("SCHED_OTHER") && p.keys().all(|k| k == "SCHED_OTHER"),
            "{p:?}"
        );
    }
    let (la, lb) = (&sa["bridge"]["split"], &sb["bridge"]["split"]);
    assert_eq!(
        (la["here"].as_str(), la["there"].as_str()),
        (Some("simulator"), Some("board"))
    );
    for t in ["meas", "truth"] {
        assert_eq!(la["sent"][t], lb["taken"][t], "{t}: {la} / {lb}");
    }
    assert_eq!(lb["sent"]["cmd"], la["taken"]["cmd"], "{la} / {lb}");
    // 5000 samples, 50 warm-up messages and the end marker.
    assert_eq!(la["sent"]["meas"], 5051, "{la}");
    assert_eq!(lb["sent"]["cmd"], 5051, "{lb}");
    for l in [la, lb] {
        assert_eq!(
            (l["rejected"].as_u64(), l["implausible"].as_u64()),
            (Some(0), Some(0)),
            "{l}"
        );
    }
    let procs = |s: &Value| -> Vec<String> {
        s["processes"]
            .as_object()
            .unwrap()
            .keys()
            .cloned()
            .collect()
    };
    assert_eq!(procs(&sa), ["plant"]);
    assert_eq!(procs(&sb), ["current-loop", "observer", "speed-loop"]);
    if let Some(w) = &sides.wire {
        let names = w.names.clone();
        drop(sides);
        for n in names {
            assert!(!Wire::exists(&n), "namespace {n} left behind");
        }
    }
}

#[test]
fn a_real_time_split_drive_keeps_every_sample_on_both_machines() {
    let _g = serial();
    let (out_a, out_b, _sides) = run_split("r", "realtime", &[]);
    // The plant kept its schedule whatever the network did (late commands are misses, not
    // lost samples), and both recorders saw the same messages: the same rows, misses
    // included.
    let (ta, tb) = (
        read(&out_a.join("trace.csv")),
        read(&out_b.join("trace.csv")),
    );
    assert_eq!(ta.iter().filter(|&&c| c == b'\n').count(), 5001);
    assert!(ta == tb, "the two machines' traces differ");
    let (sa, sb) = (summary(&out_a), summary(&out_b));
    assert_eq!(sa["samples"], 5000);
    assert_eq!(sa["samples_missing"], 0, "{}", sa["missing_samples"]);
    let (la, lb) = (&sa["bridge"]["split"], &sb["bridge"]["split"]);
    assert_eq!(la["sent"]["meas"], lb["taken"]["meas"], "{la} / {lb}");
    assert_eq!(lb["sent"]["cmd"], la["taken"]["cmd"], "{la} / {lb}");
    // In real time the link is on the data path: where the plant got SCHED_FIFO, the
    // bridge's threads did too (below the stages).
    if sa["processes"]["plant"]["policy"] == "SCHED_FIFO" {
        let p = &sa["bridge"]["thread_policies"];
        assert!(p["SCHED_FIFO"].as_u64() > Some(0), "{p}");
    }
}

/// The two sides of a real-time split drive, started: their launchers, buses and run folders.
struct Running {
    sim: Drive,
    board: Drive,
    buses: (String, String),
    outs: (PathBuf, PathBuf),
}

fn start_real_time(sides: &Sides, name: &str, seconds: &str) -> Running {
    let dir = scratch(name);
    let buses = (
        bus_id(&format!("{name}-simulator")),
        bus_id(&format!("{name}-board")),
    );
    let outs = (dir.join("simulator"), dir.join("board"));
    let ep = sides.endpoint();
    let a = [
        "--scenario",
        "kyslan-pi",
        "--duration",
        seconds,
        "--zenoh-listen",
        &ep,
    ];
    let b = [
        "--scenario",
        "kyslan-pi",
        "--duration",
        seconds,
        "--zenoh-connect",
        &ep,
    ];
    Running {
        sim: sides.start(0, &buses.0, &side_args(&buses.0, &outs.0, "simulator", &a)),
        board: sides.start(1, &buses.1, &side_args(&buses.1, &outs.1, "board", &b)),
        buses,
        outs,
    }
}

/// Removes the bus files a SIGKILLed launcher left, then checks that nothing is left.
fn clean_after_kill(bus: &str) {
    let o = drivelab(&["clean", "--bus", bus]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_clean(bus);
}

#[test]
fn when_a_machine_leaves_the_board_stops_at_once_and_the_simulator_goes_on_safe() {
    let _g = serial();
    let sides = Sides::new("k");
    // The simulator's machine goes: the board has nothing to control and stops in one line
    // (not at its watchdog, long after).
    let mut r = start_real_time(&sides, "sim-leaves", "60");
    wait_for_progress(&r.buses.1, 5000);
    r.sim.kill_and_assert_no_orphans();
    let o = wait(r.board, Duration::from_secs(30), "the board's side");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("drivelab: error: machine 'simulator' left the split link: no measurement comes any more"),
        "{err}"
    );
    assert_clean(&r.buses.1);
    clean_after_kill(&r.buses.0);
    // The board's machine goes: the plant keeps its schedule without commands, holds, then
    // applies its safe state to the end, and every sample is in the trace.
    let mut r = start_real_time(&sides, "board-leaves", "3");
    wait_for_progress(&r.buses.0, 5000);
    r.board.kill_and_assert_no_orphans();
    let o = wait(r.sim, Duration::from_secs(60), "the simulator's side");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("drivelab: machine 'board' left the split link; the plant goes on without its commands (hold, then safe state)"),
        "{err}"
    );
    let s = summary(&r.outs.0);
    assert_eq!(s["samples"], 30_000);
    let lost: Vec<&Value> = s["missing_samples"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|g| g["part"] == "measurement")
        .collect();
    assert!(lost.is_empty(), "{lost:?}");
    let trace = std::fs::read_to_string(r.outs.0.join("trace.csv")).unwrap();
    let header: Vec<&str> = trace.lines().next().unwrap().split(',').collect();
    let flags = header.iter().position(|c| *c == "plant_flags").unwrap();
    let last: Vec<&str> = trace.lines().last().unwrap().split(',').collect();
    let f: u32 = last[flags].parse().unwrap();
    assert!(
        f & 4 != 0,
        "the last sample is not in the safe state: {}",
        last.join(",")
    );
    assert_clean(&r.buses.0);
    clean_after_kill(&r.buses.1);
}

#[test]
fn the_two_sides_must_run_the_same_scenario_and_clock_and_a_side_alone_gives_up() {
    let _g = serial();
    let dir = scratch("mismatch");
    let sides = Sides {
        wire: None,
        port: free_port(),
    };
    let ep = sides.endpoint();
    let bus_a = bus_id("mismatch-simulator");
    let out_a = dir.join("simulator");
    // The simulator waits 20 s for a board that matches it; none does, so it gives up.
    let a = [
        "--scenario",
        "kyslan-pi",
        "--clock",
        "lockstep",
        "--duration",
        "0.2",
        "--zenoh-listen",
        &ep,
        "--zenoh-wait",
        "20",
    ];
    let sim = sides.start(0, &bus_a, &side_args(&bus_a, &out_a, "simulator", &a));
    for (n, (extra, needle)) in [
        (
            vec!["--clock", "lockstep", "--duration", "0.3"],
            "machine 'simulator' runs another scenario (line ",
        ),
        (
            vec!["--clock", "realtime", "--duration", "0.2"],
            "machine 'simulator' runs the lockstep clock and this one realtime: start both with the same --clock",
        ),
    ]
    .into_iter()
    .enumerate()
    {
        let bus_b = bus_id(&format!("mismatch-board-{n}"));
        let out_b = dir.join(format!("board-{n}"));
        let mut b = vec!["--scenario", "kyslan-pi", "--zenoh-connect", &ep, "--zenoh-wait", "30"];
        b.extend(extra);
        let o = drivelab(&side_args(&bus_b, &out_b, "board", &b));
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{err}");
        assert!(err.contains(needle), "want '{needle}' in: {err}");
        assert!(!err.contains("panicked"), "{err}");
        assert_clean(&bus_b);
    }
    let oa = wait(sim, Duration::from_secs(90), "the simulator's side");
    let err = String::from_utf8_lossy(&oa.stderr);
    assert_eq!(oa.status.code(), Some(1), "{err}");
    assert!(
        err.contains("machine 'board' did not join within 20 s (start its side with --machine board --zenoh-connect ENDPOINT)"),
        "{err}"
    );
    assert_clean(&bus_a);
}

#[test]
fn a_joining_side_that_cannot_connect_says_why_in_one_line_and_leaves_a_trace_with_its_header() {
    let dir = scratch("noconnect");
    let bus = bus_id("noconnect-board");
    let out = dir.join("board");
    // A port nothing listens on (bound, then let go).
    let port = free_port();
    let ep = format!("tcp/127.0.0.1:{port}");
    let b = [
        "--scenario",
        "kyslan-pi",
        "--clock",
        "lockstep",
        "--duration",
        "0.2",
        "--zenoh-connect",
        &ep,
        "--zenoh-wait",
        "1",
    ];
    let o = drivelab_within(
        &side_args(&bus, &out, "board", &b),
        Duration::from_secs(120),
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    let errors: Vec<&str> = err.lines().filter(|l| l.contains("error")).collect();
    assert_eq!(errors.len(), 1, "{err}");
    assert!(
        errors[0].starts_with(&format!(
            "drivelab: error: zenoh bridge: cannot connect to {ep}"
        )),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    assert_clean(&bus);
    // No sample, and the summary says why; the trace has its columns, no row.
    let s = summary(&out);
    assert_eq!(s["samples"], 0, "{s}");
    assert!(
        s["failure"]
            .as_str()
            .is_some_and(|f| f.starts_with("zenoh bridge: cannot connect")),
        "{}",
        s["failure"]
    );
    let trace = String::from_utf8(read(&out.join("trace.csv"))).unwrap();
    assert_eq!(trace.lines().count(), 1, "{trace}");
    assert!(trace.starts_with("k,"), "{trace}");
    assert!(drivelab_runtime::trace::read_csv(&out.join("trace.csv"))
        .unwrap()
        .is_empty());
}

#[test]
fn machines_are_checked_before_anything_starts() {
    let bus = bus_id("refused");
    // A machine the topology does not name, and a topology without machines.
    assert_run_refused(
        &bus,
        &[
            "--topology",
            "split-hil",
            "--machine",
            "desk",
            "--zenoh-listen",
            "tcp/127.0.0.1:0",
        ],
        "--machine desk: the topology's machines are simulator, board",
    );
    assert_run_refused(
        &bus,
        &["--machine", "board", "--zenoh-listen", "tcp/127.0.0.1:0"],
        "--machine board: the topology names no machines",
    );
    // --machine needs a link; --zenoh-connect needs --machine.
    for (args, needle) in [
        (
            vec!["run", "--topology", "split-hil", "--machine", "board"],
            "--machine needs --zenoh-listen",
        ),
        (
            vec!["run", "--zenoh-connect", "tcp/127.0.0.1:7447"],
            "--machine <NAME>",
        ),
    ] {
        let o = drivelab(&args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains(needle), "{args:?}: {err}");
    }
    assert_clean(&bus);
}
