//! Every agent tampers with its pair's recordings as far as its container lets it: it stops
//! CARLA's recorder right after the evaluator started it, leaves 1-byte files of its routes'
//! names in its own logs, and its records claim 0 s of simulated time, which CARLA's header
//! alone would fit. The scores stand on EvalAI (FINISHED); the audit holds each route to the
//! time the organisers' route length takes at a top speed and fails every scoring route, the
//! participant reads why on EvalAI and operators read `FINISHED*`.

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
