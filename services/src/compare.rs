//! `drivelab compare`: several runs on one set of axes, metrics side by side.
//! NOT IMPLEMENTED YET (issue 5): this stub only reports that.

use anyhow::{bail, Result};
use std::path::PathBuf;

/// Arguments of `drivelab compare`.
#[derive(Debug, clap::Args)]
pub struct CompareArgs {
    /// Run folders (each with trace.csv and summary.json).
    #[arg(required = true, num_args = 1..)]
    pub runs: Vec<PathBuf>,
    /// Output folder for the comparison plots.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
}

/// Runs the comparison.
pub fn run(_args: &CompareArgs) -> Result<()> {
    bail!("drivelab compare is not implemented yet (issue 5)")
}
