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

#[cfg(test)]
mod alloc_count;
pub mod bus;
pub mod config;
pub mod drive;
pub mod futex;
pub mod host;
pub mod inject;
pub mod messages;
pub mod rt;
pub mod runner;
pub mod sensor_faults;
pub mod service;
pub mod stage;
pub mod stages;
pub mod telemetry;
pub mod timing;
pub mod topology;
pub mod trace;
pub mod wiring;
