//! The first pair's evaluator crashes at every attempt: out of retries, FAILED, and the
//! participant's stderr shows the reason and the end of that agent's output.

use std::path::Path;

use local_stack::workloads::Behaviour;

use super::Rehearsal;

/// An evaluator that always crashes on one route.
pub struct CrashLoop;

impl Rehearsal for CrashLoop {
    fn expected(&self) -> &'static str {
        "failed"
    }

    fn set_up(&self, behaviour: &mut Behaviour, _once: &Path) {
        // No once-dir: every attempt of the pair that runs route 1 crashes there.
        behaviour
            .evaluator_env
            .insert("FAKE_EVALUATOR_CRASH_AT_ROUTE".into(), "1".into());
    }
}
