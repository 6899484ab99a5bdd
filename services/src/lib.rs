//! The drive's processes. Each binary in `src/bin/` is a thin `main` that calls one of the
//! service loops here; the control maths live in `drivelab-control`.

pub mod bench;
pub mod cdm_design;
pub mod common;
pub mod compare;
pub mod current_loop;
pub mod design;
pub mod faults;
pub mod hub;
pub mod launcher;
pub mod monitor;
pub mod observer;
pub mod observer_error;
pub mod plant;
pub mod plotcmd;
pub mod replay;
pub mod speed_loop;
