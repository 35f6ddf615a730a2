//! Whose a pod's disruption is: the control plane's (a reclaim: the pair's next pod resumes for
//! free and the time lost is given back) or the pod's own (counted as a crash), with the caps
//! on what reclaims may give.
//!
//! The Job's Pod failure policy cannot tell them apart: its `onPodConditions` pattern matches
//! a condition's type and status only, never its reason, so its `Ignore` rule lets every
//! `DisruptionTarget` pass uncounted. The Monitor reads the reason and counts the pod's own
//! against the pair's retries itself.

use serde::{Deserialize, Serialize};

/// Reasons the control plane writes for events outside the pod: a drain or a scale-down
/// through the Eviction API, a `NoExecute` taint, a deleted node's pods collected, the
/// scheduler preempting for a higher priority. A participant's code reaches none of them: its
/// pods have no service-account token.
pub const CONTROL_PLANE_REASONS: [&str; 4] = [
    "EvictionByEvictionAPI",
    "DeletionByTaintManager",
    "DeletionByPodGC",
    "PreemptionByScheduler",
];

/// The kubelet's own reason: node-pressure eviction (disk, inodes, PIDs, memory), graceful
/// node shutdown, or admitting a critical pod. Only the pressure case can be the pod's doing.
pub const BY_KUBELET: &str = "TerminationByKubelet";

/// The messages of the kubelet's terminations that are the platform's: graceful node shutdown
/// (`pkg/kubelet/nodeshutdown`) and admitting a critical pod (`pkg/kubelet/preemption`).
/// Pressure evictions say "The node was low on resource: ...".
pub const KUBELET_PLATFORM_MESSAGES: [&str; 2] = [
    "Pod was terminated in response to imminent node shutdown.",
    "Pod was preempted by Kubelet to accommodate a critical pod.",
];

/// How the kubelet begins a pressure eviction's message (`nodeLowMessageFmt`), and how it names
/// each container of the evicted pod that used more of the starved resource than it requested
/// (`containerMessageFmt`: "Container agent-1 was using 9Gi, request is 4Gi, has larger
/// consumption of ephemeral-storage."), in `pkg/kubelet/eviction/helpers.go`.
const PRESSURE_PREFIX: &str = "The node was low on resource: ";
const OVER_REQUEST: &str = "has larger consumption of";

/// The starved resources whose evictions the kubelet ranks by use above request and words per
/// container. Inodes and PIDs have no request: their evictions rank by use alone and name no
/// container, so the evicted pod is the top user, its own doing.
const RANKED_BY_REQUEST: [&str; 2] = ["ephemeral-storage", "memory"];

/// The taint (effect `NoSchedule`) on a node our consolidation drains
/// (`capacity::consolidation`). Ours alone: a node cordoned by anyone else (an upgrade, an
/// operator) is never moved from by the Monitor.
pub const CONSOLIDATING_TAINT: &str = "leaderboard.carla.org/consolidating";

/// Node taints that mean the node is going away: cordoned (drain), drained by our own
/// consolidation, chosen by the Cluster Autoscaler or Karpenter for removal, shut down, out of
/// service, unreachable.
const LEAVING_TAINTS: [&str; 8] = [
    "node.kubernetes.io/unschedulable",
    CONSOLIDATING_TAINT,
    "ToBeDeletedByClusterAutoscaler",
    "karpenter.sh/disrupted",
    "node.cloudprovider.kubernetes.io/shutdown",
    "node.kubernetes.io/out-of-service",
    "node.kubernetes.io/not-ready",
    "node.kubernetes.io/unreachable",
];

/// Replacements per pair that reclaims get free. A Spot GPU node is interrupted a few times a
/// month at worst, and a pair runs on one node at a time: three reclaims of one pair within an
/// evaluation's 72 hours is already rare. Beyond them a reclaim counts as a crash, against the
/// Job's `backoffLimit`, so no chain of disruptions runs a pair forever.
pub const FREE_RECLAIMS_PER_PAIR: u32 = 3;

/// Most seconds reclaims may take off the 72-hour limit (and add to the Jobs' deadlines): 12
/// hours, a sixth of the limit. Each reclaim costs the evaluation the interrupted route and a
/// new node's start (minutes to an hour); the free reclaims of every pair fit within it, and
/// an evaluation ends by 84 hours of wall time whatever its pods do.
pub const MAX_TIME_OFF: u64 = 12 * 3600;

/// How a pod's `DisruptionTarget` reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Disruption {
    /// The control plane's: a reclaim.
    Reclaim,
    /// The kubelet's for pressure: a reclaim only if its node is leaving (see [`judge`]).
    ByKubelet,
    /// The pod's own: counted as a crash.
    Own,
}

/// A `DisruptionTarget` condition's reason and message, read.
pub fn classify(reason: &str, message: Option<&str>) -> Disruption {
    let platform = |m: &str| KUBELET_PLATFORM_MESSAGES.contains(&m.trim());
    match reason {
        r if CONTROL_PLANE_REASONS.contains(&r) => Disruption::Reclaim,
        BY_KUBELET if message.is_some_and(platform) => Disruption::Reclaim,
        BY_KUBELET if message.is_some_and(crowded_out) => Disruption::Reclaim,
        BY_KUBELET => Disruption::ByKubelet,
        // A reason this code does not know is not taken as free: new free reasons are added
        // above once the control plane is seen writing them.
        _ => Disruption::Own,
    }
}

/// Whether a pressure eviction's message says the pod was within its share: disk or memory
/// ran short on the node, yet none of the pod's containers used more than it requested. The
/// kubelet evicts the pods above their requests first, and the Jobs request every volume's room
/// (`lb_domain::cluster::resources::Storage::logcopy`), so such a pod made room for a
/// co-tenant's use, a neighbour's or the node's own: free for it, as a reclaim.
pub fn crowded_out(message: &str) -> bool {
    let Some(rest) = message.trim_start().strip_prefix(PRESSURE_PREFIX) else {
        return false;
    };
    let resource = rest.split(['.', ' ']).next().unwrap_or_default();
    RANKED_BY_REQUEST.contains(&resource) && !message.contains(OVER_REQUEST)
}

/// What a node's object says.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct NodeFacts {
    /// `spec.unschedulable` (cordoned).
    pub unschedulable: bool,
    /// Its taints' keys.
    pub taints: Vec<String>,
    /// Its `Ready` condition is `True`.
    pub ready: bool,
}

/// Whether a node is leaving: cordoned, tainted for removal, or not ready. A node under disk,
/// inode or PID pressure stays `Ready` and untainted for removal: it is not leaving, and a
/// pressure eviction on it is a pod's doing. A node already gone (`None`) says nothing of why
/// the kubelet evicted: the Cluster Autoscaler removes a node a pressure eviction emptied, so
/// it is taken as staying, and a node that went with its pods gives them a reason of the
/// control plane's own (`DeletionByPodGC`, `DeletionByTaintManager`) or the kubelet's
/// shutdown message, each a reclaim without asking the node.
pub fn leaving(node: Option<&NodeFacts>) -> bool {
    node.is_some_and(|n| {
        n.unschedulable
            || !n.ready
            || n.taints
                .iter()
                .any(|t| LEAVING_TAINTS.contains(&t.as_str()))
    })
}

/// A kubelet's disruption judged by its node: a reclaim when the node is leaving, the pod's
/// own otherwise. Others pass unchanged.
pub fn judge(disruption: Disruption, node_leaving: bool) -> Disruption {
    match disruption {
        Disruption::ByKubelet if node_leaving => Disruption::Reclaim,
        Disruption::ByKubelet => Disruption::Own,
        other => other,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn node(unschedulable: bool, ready: bool, taints: &[&str]) -> NodeFacts {
        NodeFacts {
            unschedulable,
            ready,
            taints: taints.iter().map(|t| t.to_string()).collect(),
        }
    }

    #[test]
    fn only_the_control_plane_s_reasons_and_a_leaving_node_s_kubelet_are_reclaims() {
        let healthy = node(false, true, &["nvidia.com/gpu"]);
        let pressured = node(
            false,
            true,
            &["nvidia.com/gpu", "node.kubernetes.io/disk-pressure"],
        );
        let cordoned = node(true, true, &["node.kubernetes.io/unschedulable"]);
        let scaling_down = node(false, true, &["ToBeDeletedByClusterAutoscaler"]);
        let not_ready = node(false, false, &[]);
        // The kubelet's words: the pod named over its request, or the top user of inodes.
        let pressure = Some(
            "The node was low on resource: ephemeral-storage. Threshold quantity: 30Gi, \
             available: 29Gi. Container agent-1 was using 20Gi, request is 4Gi, has larger \
             consumption of ephemeral-storage. ",
        );
        let inodes = Some("The node was low on resource: inodes. ");
        // A co-tenant's victim: within its requests, evicted to make room.
        let crowded = Some(
            "The node was low on resource: ephemeral-storage. Threshold quantity: 30Gi, \
             available: 29Gi. ",
        );
        let crowded_memory = Some("The node was low on resource: memory. ");
        let cases: [(&str, Option<&str>, Option<&NodeFacts>, Disruption); 18] = [
            (
                "EvictionByEvictionAPI",
                None,
                Some(&healthy),
                Disruption::Reclaim,
            ),
            ("DeletionByTaintManager", None, None, Disruption::Reclaim),
            ("DeletionByPodGC", None, None, Disruption::Reclaim),
            (
                "PreemptionByScheduler",
                None,
                Some(&healthy),
                Disruption::Reclaim,
            ),
            // The participant filled the node's disk, or its inodes or PIDs.
            (BY_KUBELET, pressure, Some(&healthy), Disruption::Own),
            (BY_KUBELET, pressure, Some(&pressured), Disruption::Own),
            (BY_KUBELET, inodes, Some(&pressured), Disruption::Own),
            (
                BY_KUBELET,
                Some("The node was low on resource: pids."),
                None,
                Disruption::Own,
            ),
            // Its node gone before a round judged it: the emptied node scaled down.
            (BY_KUBELET, pressure, None, Disruption::Own),
            // Within its share: a neighbour's disk or memory use pushed it out, on a healthy
            // node, a pressured one or one gone since.
            (BY_KUBELET, crowded, Some(&pressured), Disruption::Reclaim),
            (BY_KUBELET, crowded, None, Disruption::Reclaim),
            (
                BY_KUBELET,
                crowded_memory,
                Some(&healthy),
                Disruption::Reclaim,
            ),
            // The node is going anyway.
            (BY_KUBELET, pressure, Some(&cordoned), Disruption::Reclaim),
            (
                BY_KUBELET,
                pressure,
                Some(&scaling_down),
                Disruption::Reclaim,
            ),
            (BY_KUBELET, pressure, Some(&not_ready), Disruption::Reclaim),
            (
                BY_KUBELET,
                Some(KUBELET_PLATFORM_MESSAGES[0]),
                Some(&healthy),
                Disruption::Reclaim,
            ),
            (
                BY_KUBELET,
                Some(KUBELET_PLATFORM_MESSAGES[1]),
                Some(&healthy),
                Disruption::Reclaim,
            ),
            ("SomethingNew", None, None, Disruption::Own),
        ];
        for (reason, message, node, expected) in cases {
            let judged = judge(classify(reason, message), leaving(node));
            assert_eq!(judged, expected, "{reason} {message:?} {node:?}");
        }
    }

    #[test]
    fn only_a_disk_or_memory_eviction_naming_none_of_the_pod_s_containers_crowded_it_out() {
        for (message, crowded) in [
            ("The node was low on resource: ephemeral-storage. ", true),
            ("The node was low on resource: memory. Threshold quantity: 100Mi, available: 90Mi. ", true),
            (
                "The node was low on resource: memory. Container agent-1 was using 17Gi, request \
                 is 16Gi, has larger consumption of memory. ",
                false,
            ),
            ("The node was low on resource: inodes. ", false),
            ("The node was low on resource: ephemeral-storagex. ", false),
            ("Pod ephemeral local storage usage exceeds the total limit of containers 26Gi. ", false),
            ("", false),
        ] {
            assert_eq!(crowded_out(message), crowded, "{message}");
        }
    }
}
