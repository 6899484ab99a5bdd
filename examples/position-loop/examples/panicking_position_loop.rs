//! A stage host for the tests: the position loop, made to panic once. Its
//! `[stages.position-loop]` table takes one more parameter, `panic_at_s`: the first instance
//! of the stage panics at its first step at or after that time; an instance that rejoined
//! (a restart) never does. `cargo test -p drivelab-position-loop` builds it
//! (`target/<profile>/examples/panicking_position_loop`).

use drivelab_position_loop::{ParamError, PositionLoop, NAME};
use drivelab_runtime::stage::{Diagnostics, Inbox, InputSpec, Outbox, Rejoin, Stage, TopicId};

struct Panicking {
    inner: PositionLoop,
    /// The sample it panics at; None once it rejoined.
    at_k: Option<u64>,
}

impl Stage for Panicking {
    fn name(&self) -> &'static str {
        NAME
    }
    fn inputs(&self) -> &'static [InputSpec] {
        self.inner.inputs()
    }
    fn outputs(&self) -> &'static [TopicId] {
        self.inner.outputs()
    }
    fn divider(&self) -> u64 {
        self.inner.divider()
    }
    fn step(&mut self, k: u64, inputs: &Inbox, out: &mut Outbox) {
        if self.at_k.is_some_and(|at| k >= at) {
            panic!("position-loop: a test panic at sample {k}");
        }
        self.inner.step(k, inputs, out);
    }
    fn rejoin(&mut self, k: u64, inputs: &Inbox) -> Rejoin {
        self.at_k = None;
        self.inner.rejoin(k, inputs)
    }
    fn diagnostic_names(&self) -> Diagnostics {
        self.inner.diagnostic_names()
    }
    fn diagnostics(&self, values: &mut [u64]) {
        self.inner.diagnostics(values);
    }
}

fn main() -> std::process::ExitCode {
    drivelab_runtime::service::host_main(&[(NAME, |sc| {
        let mut sc = sc.clone();
        let at_s = sc
            .stages
            .get_mut(NAME)
            .and_then(|t| t.remove("panic_at_s"))
            .and_then(|v| v.as_float())
            .ok_or_else(|| ParamError(format!("stages.{NAME}.panic_at_s: missing (s)")))?;
        Ok(Box::new(Panicking {
            inner: PositionLoop::new(&sc)?,
            at_k: Some((at_s * sc.rates.sample_hz).round() as u64),
        }))
    })])
}
