//! The `observer` process of the drive (normally started by `drivelab run`).

fn main() -> std::process::ExitCode {
    drivelab_services::common::service_main("observer", drivelab_services::observer::run)
}
