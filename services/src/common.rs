//! What the launcher shares with the stage hosts: the clock, signal handling and the rejoin
//! file of a restarted source. The host itself is `drivelab::service`.

pub use drivelab::service::{
    install_signal_handlers, measurement_from_json, measurement_to_json, stop_requested, BusClock,
};
