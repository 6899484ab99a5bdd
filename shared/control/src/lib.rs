//! drivelab control maths: PMSM model, transforms, control laws and observers.
//!
//! Pure step functions (`fn step(&mut self, input) -> output`) configured by plain parameter
//! structs, unit-tested without a bus; no bus, RT or scenario types here (the runtime's
//! `wiring` maps a scenario to these structs).

pub mod control;
pub mod motor;
pub mod observer;
pub mod observer_sensorless;
pub mod transforms;
