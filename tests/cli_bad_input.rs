//! Bad command-line input to every `drivelab` command: each case must fail with its exit code
//! (1 an error, 2 a usage error found by clap), exactly one stderr line that names the
//! problem, no panic, and nothing left behind (no process or file of its bus, no folder it
//! was asked to write).

mod common;

use common::{assert_clean, bus_id, drivelab, run_ok, scratch, serial, wait_for_services, Drive};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

fn stderr(o: &std::process::Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// One bad command line and what it must produce.
struct Case {
    args: Vec<String>,
    code: i32,
    /// In the one line of stderr.
    needle: &'static str,
    /// The bus the command names, checked clean afterwards.
    bus: Option<String>,
    /// Paths the command must not create.
    absent: Vec<PathBuf>,
}

/// A case whose arguments are `args` with `{bus}` replaced by a bus id of its own (made
/// from `name`) and `{dir}` by the test's scratch folder.
fn case(name: &str, dir: &Path, args: &[&str], code: i32, needle: &'static str) -> Case {
    let bus = args
        .iter()
        .any(|a| a.contains("{bus}"))
        .then(|| bus_id(name));
    let args = args
        .iter()
        .map(|a| {
            let a = a.replace("{dir}", dir.to_str().unwrap());
            match &bus {
                Some(b) => a.replace("{bus}", b),
                None => a,
            }
        })
        .collect();
    Case {
        args,
        code,
        needle,
        bus,
        absent: Vec::new(),
    }
}

impl Case {
    fn leaves_no(mut self, p: PathBuf) -> Self {
        self.absent.push(p);
        self
    }

    /// An export that must leave neither trace.mcap nor its partial file in `run`.
    fn leaves_no_mcap(self, run: &str) -> Self {
        let run = Path::new(run);
        self.leaves_no(run.join("trace.mcap"))
            .leaves_no(run.join("trace.mcap.part"))
    }

    fn check(&self) {
        let args: Vec<&str> = self.args.iter().map(String::as_str).collect();
        let o = drivelab(&args);
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(self.code), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{args:?}: {err}");
        assert_eq!(err.lines().count(), 1, "{args:?}: not one line: {err}");
        assert!(
            err.starts_with("drivelab: error: "),
            "{args:?}: not an error line: {err}"
        );
        assert!(
            err.contains(self.needle),
            "{args:?}: no '{}' in {err}",
            self.needle
        );
        if let Some(bus) = &self.bus {
            assert_clean(bus);
        }
        for p in &self.absent {
            assert!(!p.exists(), "{args:?}: {} was made", p.display());
        }
    }
}

#[test]
fn bad_input_is_one_line_with_its_exit_code_and_leaves_nothing() {
    let d = scratch("bad");
    let dir = d.as_path();
    let out = d.join("out");
    // A finished run to point plot, export and compare at, and plant input files.
    let (run, _) = run_ok("good", &["--clock", "lockstep", "--duration", "0.05"]);
    let run = run.to_str().unwrap().to_string();
    let csv = |name: &str, text: &str| {
        let p = d.join(name);
        std::fs::write(&p, text).unwrap();
        p.to_str().unwrap().to_string()
    };
    let volts = csv("volts.csv", "t,u_d,u_q,t_load\n0,0,10,0\n0.01,0,10,0\n");
    let huge = csv("huge.csv", "t,u_d,u_q,t_load\n0,1e300,10,0\n0.001,0,0,0\n");
    let no_t = csv("no-t.csv", "k,u_d,u_q\n0,1,2\n");
    let not_num = csv("not-num.csv", "t,u_d,u_q,t_load\n0,1,abc,0\n");
    let short = csv("short.csv", "t,u_d,u_q,t_load\n0,1,2,0\n0.1,1,2\n");
    // A run folder whose trace has a header and no sample.
    let empty = d.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    for f in ["scenario.toml", "summary.json"] {
        std::fs::copy(Path::new(&run).join(f), empty.join(f)).unwrap();
    }
    std::fs::write(empty.join("trace.csv"), "k,t,omega_ref\n").unwrap();
    let empty = empty.to_str().unwrap().to_string();
    // Two links that point at each other: not a missing file.
    let looped = d.join("loop1.toml");
    std::os::unix::fs::symlink(d.join("loop2.toml"), &looped).unwrap();
    std::os::unix::fs::symlink(&looped, d.join("loop2.toml")).unwrap();
    let looped = looped.to_str().unwrap().to_string();
    // A folder of other files: a run must not write into it.
    let foreign = d.join("foreign");
    std::fs::create_dir_all(&foreign).unwrap();
    std::fs::write(foreign.join("notes.txt"), "mine\n").unwrap();
    let foreign_s = foreign.to_str().unwrap().to_string();
    // Configuration files that are not: a FIFO (opening it would wait for a writer for
    // ever), a device without end, a regular file too large to be one.
    let fifo = d.join("fifo.toml");
    let made = Command::new("mkfifo").arg(&fifo).status().unwrap();
    assert!(made.success());
    let fifo = fifo.to_str().unwrap().to_string();
    let big = csv("big.toml", &"#\n".repeat(600_000));
    let tiny_j = common::variant(
        "tiny-j",
        "kyslan-nl",
        &[(
            "preset = \"kyslan2015\"",
            "preset = \"kyslan2015\"\nj_kgm2 = 1e-12",
        )],
    );
    let tiny_j = tiny_j.to_str().unwrap().to_string();
    let o = out.to_str().unwrap();
    let lockstep = ["--clock", "lockstep", "--no-plots"];
    let run_case = |name: &str, extra: &[&str], code: i32, needle: &'static str| {
        let mut a = vec!["run", "--bus", "{bus}", "--out", o];
        a.extend_from_slice(&lockstep);
        a.extend_from_slice(extra);
        case(name, dir, &a, code, needle).leaves_no(out.clone())
    };
    // A real-time run (the default clock), refused before anything starts.
    let rt_case = |name: &str, extra: &[&str], code: i32, needle: &'static str| {
        let mut a = vec!["run", "--bus", "{bus}", "--out", o, "--no-plots"];
        a.extend_from_slice(extra);
        case(name, dir, &a, code, needle).leaves_no(out.clone())
    };
    let mut cases = vec![
        // run
        run_case(
            "dur-nan",
            &["--duration", "NaN"],
            2,
            "invalid value 'NaN' for '--duration <SECONDS>': must be more than 0 and at most 3600 s",
        ),
        run_case("dur-neg", &["--duration", "-1"], 2, "'-1' for '--duration <SECONDS>'"),
        run_case("dur-huge", &["--duration", "1e300"], 2, "at most 3600 s"),
        run_case(
            "dur-int",
            &["--duration", "99999999999999999999"],
            2,
            "at most 3600 s",
        ),
        run_case("dur-empty", &["--duration", ""], 2, "not a number"),
        // Not an unknown flag '-i': the option's range names it.
        run_case(
            "dur-neg-inf",
            &["--duration", "-inf"],
            2,
            "invalid value '-inf' for '--duration <SECONDS>': must be more than 0",
        ),
        run_case("dur-neg-nan", &["--duration", "-NaN"], 2, "'-NaN' for '--duration <SECONDS>'"),
        run_case(
            "expect-below-number",
            &["--expect", "peak_current_a.x <= 1"],
            2,
            "'peak_current_a' is a number; no figure lies below it",
        ),
        run_case(
            "timing-lockstep",
            &["--timing-csv"],
            2,
            "--timing-csv needs the realtime clock: the lockstep clock has no sample instants to time against",
        ),
        case(
            "timing-inprocess",
            dir,
            &["run", "--bus", "{bus}", "--out", o, "--clock", "inprocess", "--timing-csv"],
            2,
            "--timing-csv needs the realtime clock: the inprocess clock has no sample instants",
        )
        .leaves_no(out.clone()),
        run_case("scenario", &["--scenario", "nosuch"], 1, "unknown scenario 'nosuch'"),
        run_case(
            "scenario-dir",
            &["--scenario", "/tmp"],
            1,
            "scenario /tmp is a folder, not a scenario file",
        ),
        run_case(
            "scenario-dev",
            &["--scenario", "/dev/null"],
            1,
            "scenario /dev/null is not a regular file",
        ),
        case(
            "bus-digits",
            dir,
            &["clean", "--bus", "1234567890123456789012345"],
            2,
            "bus id '1234567890123456789012345' must be 1-24 characters",
        ),
        // Above 0 s, below one sample.
        run_case(
            "dur-tiny",
            &["--duration", "1e-9"],
            1,
            "0.000000001 s × 10000 Hz = 0 samples must be in 1..=2e8",
        ),
        case(
            "clock",
            dir,
            &["run", "--bus", "{bus}", "--clock", "nosuch"],
            2,
            "[possible values: realtime, lockstep, inprocess]",
        ),
        run_case(
            "rt",
            &["--rt-strict", "--no-rt"],
            2,
            "'--rt-strict' cannot be used with '--no-rt'",
        ),
        run_case(
            "restart-ms",
            &["--lockstep-restart-ms", "-1"],
            2,
            "lasts 1 to 10000 ms",
        ),
        run_case(
            "restart-never-ms",
            &["--restart", "never", "--lockstep-restart-ms", "50"],
            2,
            "--lockstep-restart-ms with --restart never: a killed stage stays dead, there is no restart to time",
        ),
        // A delay whose spinning outlasts what the run may take.
        rt_case(
            "delay-outlasts-the-run",
            &[
                "--duration",
                "0.3",
                "--fault",
                "delay:current-loop@0.1:0.1:100ms",
            ],
            1,
            "fault delay:current-loop@0.1:0.1:100000us: its 1000 delayed steps would keep the stages' core busy for 100.0 s, which with the run's own 0.3 s is longer than this run may last (20.4 s, 10 s of it for the start and the end): shorten its window or latency",
        ),
        // Two delays that each fit, but not together (15 s each; 10.1 s of room).
        rt_case(
            "delays-outlast-the-run-together",
            &[
                "--duration",
                "0.3",
                "--fault",
                "delay:observer@0.1:0.1:15ms",
                "--fault",
                "delay:current-loop@0.1:0.1:15ms",
            ],
            1,
            "fault delay:observer@0.1:0.1:15000us, delay:current-loop@0.1:0.1:15000us: their 2000 delayed steps would keep the stages' core busy for 30.0 s",
        ),
        rt_case(
            "restart-ms-realtime",
            &["--lockstep-restart-ms", "50"],
            2,
            "--lockstep-restart-ms times a simulated restart (--clock lockstep or inprocess); in real time the supervisor restarts the process itself",
        ),
        run_case(
            "seed",
            &["--fault-seed", "-1"],
            2,
            "'--fault-seed <FAULT_SEED>': must be a whole number from 0 to",
        ),
        run_case("topology", &["--topology", "nosuch"], 1, "unknown topology 'nosuch'"),
        run_case(
            "topology-device",
            &["--topology", "/dev/zero"],
            1,
            "topology /dev/zero is not a regular file",
        ),
        run_case(
            "topology-fifo",
            &["--topology", &fifo],
            1,
            "fifo.toml is not a regular file",
        ),
        run_case(
            "scenario-big",
            &["--scenario", &big],
            1,
            "big.toml is larger than 1048576 bytes: not a scenario file",
        ),
        run_case(
            "fault",
            &["--fault", "kill:plant@nan"],
            2,
            "time must be a finite number",
        ),
        run_case(
            "fox",
            &["--foxglove", "127.0.0.1:99999"],
            2,
            "port '99999' is not a number from 0 to 65535",
        ),
        case(
            "out",
            dir,
            &["run", "--bus", "{bus}", "--clock", "lockstep", "--out", "/proc/x"],
            1,
            "cannot create run folder /proc/x",
        ),
        case("busid", dir, &["run", "--bus", "bad-id"], 2, "bus id 'bad-id'"),
        run_case(
            "fault-sample0",
            &["--fault", "kill:plant@0"],
            1,
            "fault 'kill:plant@0' falls on sample 0: a kill or stop must come after the drive's first sample",
        ),
        case(
            "foreign",
            dir,
            &["run", "--bus", "{bus}", "--clock", "lockstep", "--out", &foreign_s],
            1,
            "not empty and not a run folder (no scenario.toml)",
        )
        .leaves_no(foreign.join("scenario.toml")),
        // plant
        case(
            "plant-step",
            dir,
            &["plant", "--replay", &volts, "--out", o, "--max-step-s", "1"],
            2,
            "--max-step-s 1: must be more than 0 and at most the motor's electrical time constant",
        ),
        case(
            "plant-nan",
            dir,
            &["plant", "--replay", &volts, "--out", o, "--max-step-s", "NaN"],
            2,
            "--max-step-s NaN: must be more than 0",
        ),
        case(
            "plant-dir",
            dir,
            &["plant", "--replay", dir.to_str().unwrap(), "--out", o],
            1,
            "not a file",
        ),
        case(
            "plant-same",
            dir,
            &["plant", "--replay", &volts, "--out", &volts],
            1,
            "the same file as --replay",
        ),
        case(
            "plant-huge",
            dir,
            &["plant", "--replay", &huge, "--out", o],
            1,
            "the model's state is not a finite number from t = 0.001 s",
        ),
        case(
            "plant-columns",
            dir,
            &["plant", "--replay", &no_t, "--out", o],
            1,
            "no-t.csv: no column t, t_load in its first line (need columns t,u_d,u_q,t_load)",
        ),
        case(
            "plant-not-a-number",
            dir,
            &["plant", "--replay", &not_num, "--out", o],
            1,
            "not-num.csv row 2: column u_q: invalid float literal",
        ),
        case(
            "plant-short-row",
            dir,
            &["plant", "--replay", &short, "--out", o],
            1,
            "short.csv row 3: 3 fields, the first line has 4",
        ),
        case(
            "plant-motor",
            dir,
            &["plant", "--replay", &volts, "--out", o, "--motor", "nosuch"],
            1,
            "unknown motor 'nosuch'",
        ),
        // design
        case(
            "design-rise",
            dir,
            &["design", "--rise-time-ms", "0"],
            2,
            "'--rise-time-ms <MS>': must be more than 0 and at most 10000 ms",
        ),
        case(
            "design-motor",
            dir,
            &["design", "--motor", "nosuch"],
            1,
            "unknown motor 'nosuch'",
        ),
        // An inertia no motor has: the design's step response was not finite ("NaN").
        case(
            "design-tiny-j",
            dir,
            &["design", "--scenario", &tiny_j],
            1,
            "motor.j_kgm2 = 0.000000000001 must be in [0.0000000001, 1000000000] kg·m²",
        ),
        // monitor, fault, clean, bus-config on a bus with no drive
        case(
            "mon-none",
            dir,
            &["monitor", "--bus", "{bus}", "--print"],
            1,
            "no drive on bus",
        ),
        case(
            "mon-refresh",
            dir,
            &["monitor", "--bus", "{bus}", "--refresh-ms", "-1"],
            2,
            "'-1' for '--refresh-ms <MS>': must be a whole number from 10 to 10000 ms",
        ),
        case(
            "mon-size",
            dir,
            &["monitor", "--bus", "{bus}", "--print-size", "100x50"],
            2,
            "not provided: --print",
        ),
        case(
            "fault-kind",
            dir,
            &["fault", "nokind", "plant", "--bus", "{bus}"],
            2,
            "[possible values: kill, stop]",
        ),
        case(
            "fault-stop",
            dir,
            &["fault", "stop", "plant", "--bus", "{bus}", "--duration-s", "-1"],
            2,
            "invalid value '-1' for '--duration-s <SECONDS>': a stop lasts 0.001 to 60 s",
        ),
        case(
            "fault-kill-duration",
            dir,
            &["fault", "kill", "plant", "--bus", "{bus}", "--duration-s", "1"],
            2,
            "--duration-s 1: only a stop has a duration",
        ),
        case("clean", dir, &["clean", "--bus", ""], 2, "bus id ''"),
        case(
            "bus-config",
            dir,
            &["bus-config", "--bus", "x/y"],
            2,
            "bus id 'x/y'",
        ),
        // files and folders
        case(
            "scenario-link-loop",
            dir,
            &["run", "--bus", "{bus}", "--scenario", &looped],
            1,
            "Too many levels of symbolic links",
        ),
        case(
            "export",
            dir,
            &["export", "/nonexistent", "--mcap"],
            1,
            "/nonexistent does not exist",
        ),
        case("export-empty", dir, &["export", &empty, "--mcap"], 1, "has no samples")
            .leaves_no(Path::new(&empty).join("trace.mcap")),
        case(
            "compare",
            dir,
            &["compare", "/nonexistent", &run],
            1,
            "/nonexistent: no such run folder",
        ),
        case(
            "compare-file",
            dir,
            &["compare", &format!("{run}/trace.csv"), &run],
            1,
            "/trace.csv is not a folder (not a run folder)",
        ),
        case(
            "compare-out-file",
            dir,
            &["compare", &run, &run, "--out", &format!("{run}/trace.csv")],
            1,
            "/trace.csv: is a file, not a folder; give a folder with --out",
        ),
        case(
            "plot-out-file",
            dir,
            &["plot", &run, "--out", &format!("{run}/trace.csv")],
            1,
            "/trace.csv: is a file, not a folder; give a folder with --out",
        ),
        case(
            "plot-nan",
            dir,
            &["plot", &run, "--window", "nan:1", "--out", o],
            2,
            "--window 'nan:1': START and END must be finite numbers of seconds",
        ),
        case(
            "plot-outside",
            dir,
            &["plot", &run, "--window", "5:6", "--out", o],
            1,
            "--window '5:6': no sample inside",
        )
        .leaves_no(out.clone()),
        case(
            "campaign",
            dir,
            &["campaign", "/nonexistent.toml", "--out", o],
            1,
            "cannot read campaign /nonexistent.toml",
        ),
        case(
            "campaign-fifo",
            dir,
            &["campaign", &fifo, "--out", o],
            1,
            "fifo.toml is not a regular file (a campaign is a .toml file)",
        ),
        case(
            "campaign-device",
            dir,
            &["campaign", "/dev/zero", "--out", o],
            1,
            "campaign /dev/zero is not a regular file (a campaign is a .toml file)",
        ),
        case(
            "campaign-big",
            dir,
            &["campaign", &big, "--out", o],
            1,
            "is larger than 1048576 bytes: not a campaign file",
        ),
        // observer-error, cdm-design
        case(
            "oe-ts",
            dir,
            &["observer-error", "--no-plots", "--out", o, "--ts", "1e-300s"],
            2,
            "must be between 1 µs and 100 ms",
        ),
        case(
            "oe-step",
            dir,
            &["observer-error", "--no-plots", "--out", o, "--step-rpm", "1e300"],
            2,
            "--step-rpm 1e300: must be at most the sweep's highest speed",
        ),
        case(
            "oe-tau",
            dir,
            &["observer-error", "--no-plots", "--out", o, "--pole-tau-ms", "-1"],
            2,
            "--pole-tau-ms -1: must be more than 0 and at most 1000 ms",
        ),
        case(
            "cdm-tu",
            dir,
            &["cdm-design", "--v-ao-v", "5", "--tu-us", "1e300"],
            2,
            "--tu-us 1e300: must be between 1 and 100000 µs",
        ),
        case(
            "cdm-vao",
            dir,
            &["cdm-design", "--v-ao-v", "NaN"],
            2,
            "--v-ao-v NaN: must be a finite number of volts",
        ),
        case(
            "cdm-sigma",
            dir,
            &[
                "cdm-design",
                "--v-ao-v",
                "5",
                "--speed-rpm",
                "800",
                "--sigma-v-rad-s",
                "5",
            ],
            2,
            "--sigma-v-rad-s 5: must be negative",
        ),
        case(
            "cdm-iq",
            dir,
            &["cdm-design", "--v-ao-v", "5", "--i-q-a", "3"],
            2,
            "not provided: --speed-rpm",
        ),
        // bench: refused before anything is measured or written
        case(
            "bench-quick",
            dir,
            &["bench", "--quick", "--rates", "5000", "--out", o],
            2,
            "--rates cannot be used with --quick",
        )
        .leaves_no(out.clone()),
        case(
            "bench-rates",
            dir,
            &["bench", "--rates", "NaN", "--out", o],
            2,
            "--rates: NaN Hz must be in [100, 100000]",
        )
        .leaves_no(out.clone()),
        case(
            "bench-variant",
            dir,
            &["bench", "--variants", "nosuch", "--out", o],
            2,
            "--variants: unknown variant 'nosuch'",
        )
        .leaves_no(out.clone()),
        case(
            "bench-seconds",
            dir,
            &["bench", "--quick", "--seconds", "1e300", "--out", o],
            2,
            "--seconds must be in (0, 3600]",
        )
        .leaves_no(out.clone()),
        case(
            "bench-cyclictest",
            dir,
            &["bench", "--quick", "--cyclictest", "", "--out", o],
            2,
            "--cyclictest is empty",
        )
        .leaves_no(out.clone()),
        // usage
        case(
            "scenarios",
            dir,
            &["scenarios", "extra"],
            2,
            "unexpected argument 'extra'",
        ),
        case("doctor", dir, &["doctor", "--nosuch"], 2, "'--nosuch'"),
        case(
            "doctor-topology",
            dir,
            &["doctor", "--topology", "nosuch"],
            1,
            "--topology: unknown topology 'nosuch' (known: four-process",
        ),
        case(
            "command",
            dir,
            &["nosuch"],
            2,
            "unrecognized subcommand 'nosuch'; tip: a similar subcommand exists: 'bench'; the commands are run, ",
        ),
    ];
    if cfg!(feature = "zenoh") {
        cases.extend([
            run_case(
                "zenoh-config",
                &["--zenoh-listen", "--zenoh-config", "/nonexistent"],
                1,
                "--zenoh-config /nonexistent: cannot read it: No such file",
            ),
            run_case(
                "zenoh-wait",
                &["--machine", "a", "--zenoh-listen", "--zenoh-wait", "-1"],
                2,
                "--zenoh-wait -1: 1 to 3600 seconds",
            ),
            case(
                "rec-wait",
                dir,
                &[
                    "record",
                    "--connect",
                    "tcp/127.0.0.1:1",
                    "--out",
                    o,
                    "--wait",
                    "-1",
                ],
                2,
                "--wait -1: 0 to 3600 seconds",
            )
            .leaves_no(out.clone()),
            case(
                "rec-out",
                dir,
                &["record", "--connect", "tcp/127.0.0.1:1", "--out", "/proc/x"],
                1,
                "--out /proc/x: cannot create run folder /proc/x",
            ),
            // Nothing recorded: the folders made for it are gone.
            case(
                "rec-refused",
                dir,
                &[
                    "record",
                    "--connect",
                    "tcp/127.0.0.1:1",
                    "--out",
                    &format!("{o}/a/b"),
                ],
                1,
                "cannot connect to tcp/127.0.0.1:1",
            )
            .leaves_no(out.clone()),
            case(
                "rec-config",
                dir,
                &[
                    "record",
                    "--connect",
                    "tcp/127.0.0.1:1",
                    "--out",
                    o,
                    "--zenoh-config",
                    dir.to_str().unwrap(),
                ],
                1,
                "-bad: not a file",
            ),
        ]);
    }
    for c in &cases {
        c.check();
    }
    if cfg!(feature = "zenoh") {
        // An earlier run's folder as --out: a remote drive that does not answer leaves it
        // whole (its outputs are replaced only once there is something to record).
        let earlier = dir.join("earlier-run");
        std::fs::create_dir_all(&earlier).unwrap();
        for f in ["scenario.toml", "trace.csv", "summary.json"] {
            std::fs::write(earlier.join(f), format!("the earlier run's {f}")).unwrap();
        }
        let e = earlier.to_str().unwrap();
        let o = drivelab(&["record", "--connect", "tcp/127.0.0.1:1", "--out", e]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{err}");
        assert!(err.contains("cannot connect to tcp/127.0.0.1:1"), "{err}");
        for f in ["scenario.toml", "trace.csv", "summary.json"] {
            assert_eq!(
                std::fs::read_to_string(earlier.join(f)).ok(),
                Some(format!("the earlier run's {f}")),
                "a failed record removed the earlier run's {f}"
            );
        }
    }
    let left: Vec<_> = std::fs::read_dir(&foreign).unwrap().flatten().collect();
    assert_eq!(
        left.len(),
        1,
        "the refused run wrote into {}",
        foreign.display()
    );
}

#[test]
fn a_bus_in_use_is_refused_and_left_to_its_drive() {
    let _s = serial();
    let d = scratch("busy");
    let bus = bus_id("busy");
    let drive = Drive::start(&bus, &d.join("drive"), &["--duration", "2"]);
    wait_for_services(&bus);
    let second = d.join("second");
    for args in [
        vec![
            "run",
            "--bus",
            &bus,
            "--clock",
            "lockstep",
            "--out",
            second.to_str().unwrap(),
        ],
        vec!["clean", "--bus", &bus],
    ] {
        let o = drivelab(&args);
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(1), "{args:?}: {err}");
        assert_eq!(err.lines().count(), 1, "{args:?}: {err}");
        assert!(
            err.contains(&format!("bus {bus} is in use by pid")),
            "{err}"
        );
        assert!(!second.exists(), "the refused run made its folder");
    }
    // The drive itself was not disturbed.
    let o = drive.wait_for_exit(Duration::from_secs(60), "the drive");
    assert!(o.status.success(), "{}", stderr(&o));
    assert_clean(&bus);
}

#[test]
fn cdm_design_refuses_an_operating_point_beyond_its_physical_range() {
    let d = scratch("cdm-op");
    let dir = d.as_path();
    for c in [
        case(
            "cdm-vao-huge",
            dir,
            &["cdm-design", "--v-ao-v", "1e300"],
            2,
            "--v-ao-v 1e300: must be between -100000 and 100000 V",
        ),
        case(
            "cdm-vao-2e64",
            dir,
            &["cdm-design", "--v-ao-v", "18446744073709551616"],
            2,
            ": must be between -100000 and 100000 V",
        ),
        case(
            "cdm-vao-neg",
            dir,
            &["cdm-design", "--v-ao-v", "-100001"],
            2,
            "--v-ao-v -100001: must be between -100000 and 100000 V",
        ),
        case(
            "cdm-delta-huge",
            dir,
            &["cdm-design", "--v-ao-v", "5", "--delta-o-deg", "1e300"],
            2,
            "--delta-o-deg 1e300: must be between -90 and 90 degrees",
        ),
        case(
            "cdm-delta-neg",
            dir,
            &["cdm-design", "--v-ao-v", "5", "--delta-o-deg", "-90.5"],
            2,
            "--delta-o-deg -90.5: must be between -90 and 90 degrees",
        ),
    ] {
        c.check();
    }
    // The ends of the ranges are designed, clamped to the paper's limits as before.
    let o = drivelab(&["cdm-design", "--v-ao-v", "-100000", "--delta-o-deg", "90"]);
    let t = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(t.contains("V_ao = -271.355 V, δ_o = 81.000000°"), "{t}");
}

#[test]
fn plot_compare_and_export_refuse_a_summary_json_or_scenario_that_is_not_one() {
    let _s = serial();
    let d = scratch("badsum");
    let (run, _) = run_ok("badsum-run", &["--clock", "lockstep", "--duration", "0.05"]);
    // Copies of the run folder's trace and scenario, with summary.json as given.
    let folder = |name: &str, summary: Option<&str>| {
        let p = d.join(name);
        std::fs::create_dir_all(&p).unwrap();
        for f in ["trace.csv", "scenario.toml"] {
            std::fs::copy(run.join(f), p.join(f)).unwrap();
        }
        if let Some(text) = summary {
            std::fs::write(p.join("summary.json"), text).unwrap();
        }
        p.to_str().unwrap().to_string()
    };
    let corrupt = folder("corrupt-summary", Some("{not json"));
    let no_summary = folder("no-summary", None);
    // A scenario.toml that is not a scenario: the figures' limit lines come from it.
    let bad_scenario = folder("corrupt-scenario", None);
    std::fs::write(format!("{bad_scenario}/scenario.toml"), "name = [").unwrap();
    let array = folder("array-summary", Some("[1, 2]"));
    // Figures plot reads, of the wrong type or out of range.
    let typed = folder("typed-summary", Some(r#"{"rate_hz": "fast"}"#));
    let faults = folder("faults-summary", Some(r#"{"faults": {"kill": 1}}"#));
    let rate = folder("rate-summary", Some(r#"{"rate_hz": -10000}"#));
    // What export logs, of the wrong type; and a summary without the sample rate, which
    // export needs (the samples of the log entries).
    let events = folder(
        "events-summary",
        Some(r#"{"rate_hz": 10000, "supervisor_events": [{"k": "soon"}]}"#),
    );
    let no_rate = folder("norate-summary", Some(r#"{"clock": "lockstep"}"#));
    // A trace whose rows 2 and 3 are swapped: time runs backwards (the run's own summary).
    let summary_text = std::fs::read_to_string(run.join("summary.json")).unwrap();
    let backwards = folder("backwards", Some(&summary_text));
    let text = std::fs::read_to_string(run.join("trace.csv")).unwrap();
    let mut lines: Vec<&str> = text.lines().collect();
    lines.swap(2, 3);
    std::fs::write(format!("{backwards}/trace.csv"), lines.join("\n") + "\n").unwrap();
    let out = d.join("out");
    let o = out.to_str().unwrap();
    let good = run.to_str().unwrap();
    let dir = d.as_path();
    for c in [
        case(
            "plot-badsum",
            dir,
            &["plot", &corrupt, "--out", o],
            1,
            "corrupt-summary/summary.json: not JSON: key must be a string",
        )
        .leaves_no(out.clone()),
        case(
            "compare-badsum",
            dir,
            &["compare", good, &corrupt, "--out", o],
            1,
            "corrupt-summary/summary.json: not JSON: key must be a string",
        )
        .leaves_no(out.clone()),
        case(
            "plot-arraysum",
            dir,
            &["plot", &array, "--out", o],
            1,
            "array-summary/summary.json: not a run summary",
        )
        .leaves_no(out.clone()),
        case(
            "plot-typedsum",
            dir,
            &["plot", &typed, "--out", o],
            1,
            "typed-summary/summary.json: not a run summary: invalid type: string \"fast\", expected f64",
        )
        .leaves_no(out.clone()),
        case(
            "compare-faultssum",
            dir,
            &["compare", good, &faults, "--out", o],
            1,
            "faults-summary/summary.json: not a run summary: invalid type: map, expected a sequence",
        )
        .leaves_no(out.clone()),
        case(
            "plot-ratesum",
            dir,
            &["plot", &rate, "--out", o],
            1,
            "rate-summary/summary.json: not a run summary: rate_hz = -10000 is not a rate in Hz",
        )
        .leaves_no(out.clone()),
        case(
            "plot-backwards",
            dir,
            &["plot", &backwards, "--out", o],
            1,
            "backwards/trace.csv: row 3 (k = 1, t = 0.0001 s) does not come after the row before it (k = 2, t = 0.0002 s): a trace runs forward",
        )
        .leaves_no(out.clone()),
        case(
            "compare-backwards",
            dir,
            &["compare", good, &backwards, "--out", o],
            1,
            "a trace runs forward",
        )
        .leaves_no(out.clone()),
        case(
            "export-backwards",
            dir,
            &["export", &backwards, "--mcap"],
            1,
            "row 3 (k = 1, t = 0.0001 s) does not come after the row before it",
        )
        .leaves_no(Path::new(&backwards).join("trace.mcap")),
        case(
            "plot-badscenario",
            dir,
            &["plot", &bad_scenario, "--out", o],
            1,
            "corrupt-scenario/scenario.toml:1:",
        )
        .leaves_no(out.clone()),
        // export refuses each damaged folder as plot and compare do, before it writes.
        case(
            "export-badsum",
            dir,
            &["export", &corrupt, "--mcap"],
            1,
            "corrupt-summary/summary.json: not JSON: key must be a string",
        )
        .leaves_no_mcap(&corrupt),
        case(
            "export-arraysum",
            dir,
            &["export", &array, "--mcap"],
            1,
            "array-summary/summary.json: not a run summary",
        )
        .leaves_no_mcap(&array),
        case(
            "export-typedsum",
            dir,
            &["export", &typed, "--mcap"],
            1,
            "typed-summary/summary.json: not a run summary: invalid type: string \"fast\", expected f64",
        )
        .leaves_no_mcap(&typed),
        case(
            "export-faultssum",
            dir,
            &["export", &faults, "--mcap"],
            1,
            "faults-summary/summary.json: not a run summary: invalid type: map, expected a sequence",
        )
        .leaves_no_mcap(&faults),
        case(
            "export-ratesum",
            dir,
            &["export", &rate, "--mcap"],
            1,
            "rate-summary/summary.json: not a run summary: rate_hz = -10000 is not a rate in Hz",
        )
        .leaves_no_mcap(&rate),
        case(
            "export-eventssum",
            dir,
            &["export", &events, "--mcap"],
            1,
            "events-summary/summary.json: not a run summary: invalid type: string \"soon\", expected u64",
        )
        .leaves_no_mcap(&events),
        case(
            "export-noratesum",
            dir,
            &["export", &no_rate, "--mcap"],
            1,
            "norate-summary/summary.json: not a run summary: no rate_hz",
        )
        .leaves_no_mcap(&no_rate),
        case(
            "export-badscenario",
            dir,
            &["export", &bad_scenario, "--mcap"],
            1,
            "corrupt-scenario/scenario.toml:1:",
        )
        .leaves_no_mcap(&bad_scenario),
    ] {
        c.check();
    }
    // A run folder without summary.json (a killed launcher's) is still drawn, compared and
    // exported (with one warning), and one without scenario.toml is drawn (without limit
    // lines).
    let none = no_summary;
    let no_scenario = folder("no-scenario", None);
    std::fs::remove_file(format!("{no_scenario}/scenario.toml")).unwrap();
    for args in [
        vec!["plot", none.as_str(), "--out", o],
        vec!["compare", good, none.as_str(), "--out", o],
        vec!["export", none.as_str(), "--mcap"],
        vec!["plot", no_scenario.as_str(), "--out", o],
    ] {
        let r = drivelab(&args);
        assert!(r.status.success(), "{args:?}: {}", stderr(&r));
    }
}

#[test]
fn a_link_planted_where_a_command_writes_is_refused_and_its_target_kept() {
    // Whoever can write into a run folder could put a link there named like a file that a
    // command writes into it; the command must refuse it rather than write where it points.
    let _s = serial();
    let d = scratch("planted-link");
    let (run, _) = run_ok(
        "planted-link-run",
        &["--clock", "lockstep", "--duration", "0.05"],
    );
    let victim = d.join("victim");
    let r = run.to_str().unwrap();
    for (file, args) in [
        ("speed.png", vec!["plot", r]),
        ("latency.svg", vec!["plot", r]),
        ("trace.mcap.part", vec!["export", r, "--mcap", "--force"]),
    ] {
        std::fs::write(&victim, "keep me").unwrap();
        let link = run.join(file);
        let _ = std::fs::remove_file(&link);
        std::os::unix::fs::symlink(&victim, &link).unwrap();
        let o = drivelab(&args);
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(1), "{args:?}: {err}");
        assert_eq!(err.lines().count(), 1, "{args:?}: not one line: {err}");
        assert!(
            err.contains(&format!(
                "{} is a symbolic link: refused (drivelab never writes through one; remove it)",
                link.display()
            )),
            "{args:?}: {err}"
        );
        assert_eq!(
            std::fs::read_to_string(&victim).unwrap(),
            "keep me",
            "{args:?}"
        );
        assert!(link.symlink_metadata().unwrap().file_type().is_symlink());
        std::fs::remove_file(&link).unwrap();
    }
    // Without the links both commands write their files (the export over the run's own
    // trace.mcap: with --force).
    for args in [vec!["plot", r], vec!["export", r, "--mcap", "--force"]] {
        let o = drivelab(&args);
        assert!(o.status.success(), "{args:?}: {}", stderr(&o));
    }
    assert!(run.join("speed.png").is_file() && run.join("trace.mcap").is_file());
}
