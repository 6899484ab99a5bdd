//! The `plant` process of the drive (normally started by `drivelab run`).

fn main() -> std::process::ExitCode {
    drivelab_services::common::service_main("plant", drivelab_services::plant::run)
}
