//! The figure API of a build without the `plot` feature: the same types, and drawing
//! functions that fail with one line saying how to get the figures.

/// Why no figure is drawn.
const NOT_BUILT: &str = "this drivelab was built without figures (cargo feature `plot`, off in \
     the cross build); draw the run folder on a workstation with `drivelab plot RUNDIR`";

pub mod plot {
    //! Trace and percentile figures: not built (see the crate's documentation).
    use anyhow::{bail, Result};
    use drivelab_runtime::trace::TraceRow;
    use std::path::{Path, PathBuf};

    /// False: this build draws no figures.
    pub const AVAILABLE: bool = false;

    pub use crate::plot_options::{PercentileSeries, TraceFigureOptions};

    /// Fails: no figures in this build.
    pub fn plot_trace(_: &[TraceRow], _: &Path, _: &TraceFigureOptions) -> Result<Vec<PathBuf>> {
        bail!(super::NOT_BUILT)
    }

    /// Fails: no figures in this build.
    pub fn plot_percentiles(
        _: &[PercentileSeries],
        _: &str,
        _: Option<(f64, String)>,
        _: bool,
        _: &Path,
    ) -> Result<Vec<PathBuf>> {
        bail!(super::NOT_BUILT)
    }

    /// Fails: no figures in this build.
    pub fn plot_lines(
        _: &[(String, Vec<(f64, f64)>)],
        _: &str,
        _: &str,
        _: &str,
        _: &[(f64, String)],
        _: &Path,
    ) -> Result<Vec<PathBuf>> {
        bail!(super::NOT_BUILT)
    }
}

pub mod plot_polar {
    //! Polar panels: not built (see the crate's documentation).
    use anyhow::{bail, Result};
    use drivelab_runtime::config::Scenario;
    use drivelab_runtime::trace::TraceRow;
    use std::path::{Path, PathBuf};

    /// Fails: no figures in this build.
    pub fn plot_polar_panels(
        _: &Scenario,
        _: &[TraceRow],
        _: &Path,
        _: &str,
    ) -> Result<Vec<PathBuf>> {
        bail!(super::NOT_BUILT)
    }
}
