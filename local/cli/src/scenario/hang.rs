//! The first pair's evaluator hangs: the idle watchdog ends it, it resumes, FINISHED.

use std::path::Path;

use local_stack::workloads::Behaviour;

use super::Rehearsal;

/// An evaluator that goes silent.
pub struct Hang;

impl Rehearsal for Hang {
    fn expected(&self) -> &'static str {
        "finished"
    }

    fn set_up(&self, behaviour: &mut Behaviour, once: &Path) {
        behaviour.evaluator_env.extend([
            ("FAKE_EVALUATOR_HANG_AT_ROUTE".into(), "1".into()),
            ("FAKE_EVALUATOR_ONCE_DIR".into(), once.display().to_string()),
        ]);
    }
}
