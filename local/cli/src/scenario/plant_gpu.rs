//! Every agent plants another GPU's UUID in its pair's handoff and crashes once: each
//! simulator renders on its own pair's GPU at every attempt, FINISHED (a node of 4 GPUs
//! unless --gpus says otherwise).

use std::path::Path;

use local_stack::workloads::Behaviour;

use super::Rehearsal;

/// Agents that try to move their simulator to another GPU.
pub struct PlantGpu;

impl Rehearsal for PlantGpu {
    fn expected(&self) -> &'static str {
        "finished"
    }

    fn set_up(&self, behaviour: &mut Behaviour, once: &Path) {
        // Two of the node's GPUs: at least one is another pair's.
        let planted = [0, 1].map(local_kube::gpu_uuid).join(",");
        behaviour.node_gpus.get_or_insert(4);
        behaviour.evaluator_env.extend([
            ("FAKE_EVALUATOR_PLANT_GPU".into(), planted),
            ("FAKE_EVALUATOR_ONCE_DIR".into(), once.display().to_string()),
        ]);
    }
}
