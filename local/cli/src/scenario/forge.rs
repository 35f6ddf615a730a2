//! Every other pair's agent writes pair 2's results file and done marker in its own pod: none
//! of it leaves the pod, pair 2's honest results stand, FINISHED.

use std::path::Path;

use local_stack::workloads::Behaviour;

use super::Rehearsal;

/// Agents that forge another pair's results.
pub struct Forge;

impl Rehearsal for Forge {
    fn expected(&self) -> &'static str {
        "finished"
    }

    fn set_up(&self, behaviour: &mut Behaviour, _once: &Path) {
        behaviour
            .evaluator_env
            .insert("FAKE_EVALUATOR_FORGE_PAIR".into(), "2".into());
    }
}
