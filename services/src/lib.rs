//! The drive's processes. `drivelab-host` (in `src/bin/`) is the generic stage host of
//! `drivelab_runtime::service`; the control maths live in `drivelab-control`.

// The closed-pipe-safe printing macros of the runtime, as `crate::outln!` etc. here.
pub use drivelab_runtime::{errln, out, outln};

pub mod bench;
pub mod budget;
pub mod bus_faults;
pub mod campaign;
pub mod cdm_design;
pub mod common;
pub mod compare;
pub mod design;
pub mod expect;
pub mod faults;
pub mod foxglove;
pub mod hub;
pub mod launcher;
pub mod monitor;
pub mod observer_error;
pub mod per_second;
pub mod plotcmd;
#[cfg(feature = "zenoh")]
pub mod record;
pub mod replay;
pub mod trace_mcap;
