//! Every agent rewrites a file of its status directory and its results file several times a
//! second: only the protocol's files wake the execution, rounds come no sooner than the least
//! interval, and a history near its budget continues as a new execution. FINISHED.

use std::path::Path;

use local_stack::workloads::Behaviour;

use super::Rehearsal;

/// How often a flooding agent rewrites its files: the reproduction rewrote one four
/// times a second.
const FLOOD_HZ: u32 = 4;

/// Agents that flood the wake path.
pub struct WakeFlood;

impl Rehearsal for WakeFlood {
    fn expected(&self) -> &'static str {
        "finished"
    }

    fn set_up(&self, behaviour: &mut Behaviour, _once: &Path) {
        behaviour
            .evaluator_env
            .insert("FAKE_EVALUATOR_FLOOD_HZ".into(), FLOOD_HZ.to_string());
    }
}
