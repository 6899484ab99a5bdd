//! Control laws as pure step functions.

pub mod cdm;
pub mod current;
pub mod filter;
pub mod nonlinear;
pub mod pi;
pub mod polar;
pub mod rst;
pub mod speed;
