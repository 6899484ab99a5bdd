//! The data the figure functions take, the same in a build with figures and without.

/// Options for trace figures.
#[derive(Debug, Clone, Default)]
pub struct TraceFigureOptions {
    /// Only draw samples with t in [t0, t1] (seconds); None = all.
    pub window_s: Option<(f64, f64)>,
    /// The speed loop's limit of i_q*, drawn as dashed horizontal lines at ±value on the
    /// current plot and named i_q,max there, A.
    pub current_limit_a: Option<f64>,
    /// Voltage limit (max |u| available, V) drawn as dashed lines at ± on the voltage plot.
    pub voltage_limit_v: Option<f64>,
    /// Time windows to shade (e.g. faults), with a label each: (t_start_s, t_end_s, label).
    pub shaded_windows: Vec<(f64, f64, String)>,
    /// Title prefix, e.g. the scenario name.
    pub title: String,
}

/// One latency distribution for a percentile chart: (label, points) where each point is
/// (percentile in [0, 100), value in microseconds).
pub type PercentileSeries = (String, Vec<(f64, f64)>);
