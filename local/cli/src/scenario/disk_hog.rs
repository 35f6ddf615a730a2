//! The first pair's agent fills its own disk at every attempt, on a node whose images leave
//! little room: the kubelet evicts its pod for disk pressure, naming the agent's container,
//! and reports the pod failed only seconds after the condition. Each eviction is charged once
//! as the pod's own, and the pair ends past its Job's `backoffLimit`: FAILED, the participant
//! told why, well before the run's time limit. Only the real control plane's nodes have a
//! disk.

use std::path::Path;

use local_stack::workloads::Behaviour;

use super::Rehearsal;

/// A GiB.
const GI: u64 = 1 << 30;

/// Routes long enough that the kubelet's pass (once a second) finds the agent still on the
/// route it filled its disk on, and the route is never done: each attempt runs it again.
const ROUTE_SECONDS: f64 = 4.0;

/// An agent that writes 12 GiB outside its volumes on route 1, at every attempt.
pub struct DiskHog;

impl Rehearsal for DiskHog {
    fn expected(&self) -> &'static str {
        "failed"
    }

    fn needs_real_kube(&self) -> bool {
        true
    }

    fn set_up(&self, behaviour: &mut Behaviour, _once: &Path) {
        behaviour.route_seconds = behaviour.route_seconds.max(ROUTE_SECONDS);
        behaviour
            .evaluator_env
            .insert("FAKE_EVALUATOR_FILL_AT_ROUTE".into(), "1".into());
        // 30 GiB left of 200, the threshold 20 GiB: the pods' own few MiB keep the node above
        // it, the agent's 12 GiB bring it below. The scheduler places 180 GiB of requests.
        behaviour.node_disk = node_agent::Disk {
            capacity: 200 * GI,
            images: 170 * GI,
        };
    }
}
