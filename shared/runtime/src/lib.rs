//! drivelab runtime: message types, timing/RT setup, bus helpers, telemetry, configuration
//! types, the four services' step functions and the wiring from a scenario to the control
//! laws of `drivelab_control`.
//!
//! Control maths are pure step functions (`fn step(&mut self, input) -> output`), unit-tested
//! without a bus; the services in `services/` only set up, loop and hand messages over.
//!
//! As in `drivelab_control`, elementary functions come from the pure-Rust `libm` crate
//! (the workspace's `clippy.toml` forbids std's `f64::sin`, `exp`, ... here): the trace is
//! the same bit for bit on every architecture.
#![warn(clippy::disallowed_methods)]

/// `println!` that does not panic when nobody reads stdout any more (`drivelab … | head`
/// closes the pipe): a drive (launcher or stage host) must still stop cleanly, write its trace and remove its
/// bus files, so a failed write of a line for the person watching is ignored.
#[macro_export]
macro_rules! outln {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stdout(), $($t)*);
    }};
}

/// `print!` that does not panic on a closed stdout (see [`outln!`]).
#[macro_export]
macro_rules! out {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let _ = write!(std::io::stdout(), $($t)*);
    }};
}

/// `eprintln!` that does not panic on a closed stderr (see [`outln!`]), and writes the line
/// whole: stderr is not buffered, so the pieces of a formatted line would each be a write of
/// their own, and the stage hosts of a drive share the launcher's stderr (a pipe writes up
/// to 4 KiB at once without another writer's bytes in between). Never in a real-time loop:
/// it allocates.
#[macro_export]
macro_rules! errln {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let mut line = format!($($t)*);
        line.push('\n');
        let _ = std::io::stderr().write_all(line.as_bytes());
    }};
}

#[cfg(test)]
mod alloc_count;
pub mod audit;
pub mod bus;
pub mod config;
pub mod drive;
pub mod files;
pub mod futex;
pub mod host;
pub mod inject;
pub mod lease;
pub mod messages;
pub mod rt;
pub mod runner;
pub mod sensor_errors;
pub mod sensor_faults;
pub mod service;
pub mod stage;
pub mod stages;
pub mod telemetry;
pub mod text;
pub mod tick;
pub mod timing;
pub mod topology;
pub mod trace;
pub mod wiring;
