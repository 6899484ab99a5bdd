//! drivelab tools: figures (traces, latency percentiles, polar panels), run metrics and the
//! doctor's machine checks; used by the CLI, never by the real-time services.
//!
//! The figures need the cargo feature `plot` (on by default; plotters links fontconfig).
//! Without it, [`plot`] and [`plot_polar`] keep their types and every drawing function
//! returns an error that says so: a board's build writes its run folder and a workstation
//! draws it with `drivelab plot RUNDIR`.

pub mod doctor;
pub mod metrics;
#[cfg(not(feature = "plot"))]
mod no_plot;
pub mod plant_realism;
#[cfg(feature = "plot")]
pub mod plot;
mod plot_options;
#[cfg(feature = "plot")]
pub mod plot_polar;
#[cfg(not(feature = "plot"))]
pub use no_plot::{plot, plot_polar};

#[cfg(test)]
mod plant_realism_tests;
#[cfg(test)]
mod scenario_tests;
