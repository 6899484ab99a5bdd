//! What the launcher shares with the stage hosts: the clock, signal handling and the rejoin
//! file of a restarted source. The host itself is `drivelab_runtime::service`.

pub use drivelab_runtime::service::{
    install_signal_handlers, stop_requested, truth_to_json, BusClock,
};
