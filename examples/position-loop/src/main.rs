//! `drivelab-position-loop`: a stage host with the built-in stages plus `position-loop`.

fn main() -> std::process::ExitCode {
    drivelab_runtime::service::host_main(&[("position-loop", |sc| {
        Ok(Box::new(drivelab_position_loop::PositionLoop::new(sc)?))
    })])
}
