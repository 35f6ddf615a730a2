//! Every agent tampers with its pair's recordings as far as its container lets it: it stops
//! CARLA's recorder right after the evaluator started it, and leaves 1-byte files of its
//! routes' names in its own logs. The scores stand on EvalAI (FINISHED); the audit fails
//! every scoring route, and operators read `FINISHED*` with why.

use std::path::Path;

use local_stack::workloads::Behaviour;

use super::Rehearsal;

/// Agents that tamper with their recordings.
pub struct ForgeRecordings;

impl Rehearsal for ForgeRecordings {
    fn expected(&self) -> &'static str {
        "finished"
    }

    fn audit_passes(&self) -> bool {
        false
    }

    fn set_up(&self, behaviour: &mut Behaviour, _once: &Path) {
        behaviour
            .evaluator_env
            .insert("FAKE_EVALUATOR_FORGE_RECORDINGS".into(), "1".into());
    }
}
