//! `drivelab-host`: runs the stages of one process of a drive's topology (normally started
//! by `drivelab run`, one per `[[process]]`).

fn main() -> std::process::ExitCode {
    drivelab_runtime::service::host_main(&[])
}
