//! What the launcher shares with the stage hosts: the clock, signal handling and the rejoin
//! file of a restarted source. The host itself is `drivelab_runtime::service`.

pub use drivelab_runtime::service::{
    install_signal_handlers, measurement_from_json, measurement_to_json, stop_requested, BusClock,
};
