//! The `speed-loop` process of the drive (normally started by `drivelab run`).

fn main() -> std::process::ExitCode {
    drivelab_services::common::service_main("speed-loop", drivelab_services::speed_loop::run)
}
