//! The `current-loop` process of the drive (normally started by `drivelab run`).

fn main() -> std::process::ExitCode {
    drivelab_services::common::service_main("current-loop", drivelab_services::current_loop::run)
}
