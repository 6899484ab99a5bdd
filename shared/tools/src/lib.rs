//! drivelab tools: figures (traces, latency percentiles, polar panels), run metrics and the
//! doctor's machine checks; used by the CLI, never by the real-time services.

pub mod doctor;
pub mod metrics;
pub mod plot;
pub mod plot_polar;

#[cfg(test)]
mod scenario_tests;
