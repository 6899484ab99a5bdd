//! drivelab shared library: message types, PMSM model, transforms, control laws,
//! observers, timing/RT setup, bus helpers and configuration types.
//!
//! Control maths are pure step functions (`fn step(&mut self, input) -> output`), unit-tested
//! without a bus; the services in `services/` only set up, loop and hand messages over.

pub mod bus;
pub mod config;
pub mod control;
pub mod doctor;
pub mod drive;
pub mod futex;
pub mod messages;
pub mod metrics;
pub mod motor;
pub mod observer;
pub mod observer_sensorless;
pub mod plot;
pub mod plot_polar;
pub mod rt;
pub mod telemetry;
pub mod timing;
pub mod trace;
pub mod transforms;
pub mod wiring;

#[cfg(test)]
mod scenario_tests;
