//! drivelab shared library: message types, PMSM model, transforms, control laws,
//! observers, timing/RT setup, bus helpers and configuration types.

pub mod plot;
pub mod trace;
