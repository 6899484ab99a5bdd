//! drivelab control maths: PMSM model, transforms, control laws and observers.
//!
//! Pure step functions (`fn step(&mut self, input) -> output`) configured by plain parameter
//! structs, unit-tested without a bus; no bus, RT or scenario types here (the runtime's
//! `wiring` maps a scenario to these structs).
//!
//! Elementary functions (sin, cos, atan2, exp, ln, ...) come from the pure-Rust `libm`
//! crate, never from std's `f64` methods, which call the platform's libm and differ between
//! x86_64 and aarch64 in the last bits: a trace must be the same bit for bit on every
//! architecture. The workspace's `clippy.toml` lists the forbidden methods; [`math`] has the
//! complex-number functions.
#![warn(clippy::disallowed_methods)]

pub mod control;
pub mod inverter;
pub mod math;
pub mod motor;
pub mod observer;
pub mod observer_sensorless;
pub mod transforms;
