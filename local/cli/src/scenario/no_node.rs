//! The cluster's node has another GPU model than the leaderboard's: the autoscaler says no
//! node group could hold the pods, FAILED at once naming the labels the pods need.

use std::path::Path;

use local_stack::workloads::Behaviour;

use super::Rehearsal;

/// The node type of the scenario: not of the GPU model the local settings name.
const OTHER_INSTANCE_TYPE: &str = "g6.xlarge";

/// A cluster without the leaderboard's nodes.
pub struct NoNode;

impl Rehearsal for NoNode {
    fn expected(&self) -> &'static str {
        "failed"
    }

    fn set_up(&self, behaviour: &mut Behaviour, _once: &Path) {
        behaviour.node_instance_type = Some(OTHER_INSTANCE_TYPE.into());
    }
}
