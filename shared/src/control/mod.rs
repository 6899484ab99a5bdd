//! Control laws as pure step functions.

pub mod current;
pub mod filter;
pub mod nonlinear;
pub mod pi;
pub mod speed;
