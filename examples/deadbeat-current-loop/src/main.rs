//! `drivelab-deadbeat`: a stage host with the built-in stages, its `current-loop` replaced by
//! the deadbeat predictive current loop.

fn main() -> std::process::ExitCode {
    drivelab_runtime::service::host_main(&[(drivelab_deadbeat::NAME, |sc| {
        Ok(Box::new(drivelab_deadbeat::Deadbeat::new(sc)?))
    })])
}
