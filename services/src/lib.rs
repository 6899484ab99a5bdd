//! The drive's processes. `drivelab-host` (in `src/bin/`) is the generic stage host of
//! `drivelab_runtime::service`; the control maths live in `drivelab-control`.

/// `println!` that does not panic when nobody reads stdout any more (`drivelab … | head`
/// closes the pipe): a drive must still stop cleanly, write its trace and remove its bus
/// files, so a failed write of a line for the person watching is ignored.
#[macro_export]
macro_rules! outln {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stdout(), $($t)*);
    }};
}

/// `print!` that does not panic on a closed stdout (see [`outln!`]).
#[macro_export]
macro_rules! out {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let _ = write!(std::io::stdout(), $($t)*);
    }};
}

/// `eprintln!` that does not panic on a closed stderr (see [`outln!`]).
#[macro_export]
macro_rules! errln {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stderr(), $($t)*);
    }};
}

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
pub mod hub;
pub mod launcher;
pub mod monitor;
pub mod observer_error;
pub mod plotcmd;
pub mod replay;
