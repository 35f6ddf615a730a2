//! What the Cluster Autoscaler says about a pending pod: its `NotTriggerScaleUp` and
//! `TriggeredScaleUp` events, and whether adding nodes could ever place the pod.
//!
//! The scheduler's message cannot tell a full cluster from a pod no node will ever hold: both
//! read `Insufficient nvidia.com/gpu`. The autoscaler can, because it simulates the pod on a
//! new node of every node group. Its event (kubernetes/autoscaler,
//! `processors/status/eventing_scale_up_processor.go`) reads `pod didn't trigger scale-up: `
//! followed by `<count> <reason>` per reason, joined by `, `, counting node groups. A node
//! group is either *skipped* (it could hold the pod but cannot grow now: the fixed phrases
//! of `core/scaleup/orchestrator/skippedreasons.go`) or *rejected* (the simulated new node
//! fails the scheduler's filters: `Insufficient <resource>`, `node(s) didn't match Pod's
//! node affinity/selector`, `node(s) had untolerated taint ...`). A pod every existing node
//! group rejects can never run here, however long it waits.

use jiff::Timestamp;
use serde::{Deserialize, Serialize};

/// The event reason of a pod the autoscaler did not scale up for.
pub const NOT_TRIGGERED: &str = "NotTriggerScaleUp";
/// The event reason of a pod the autoscaler added nodes for.
pub const TRIGGERED: &str = "TriggeredScaleUp";
/// The component the autoscaler's events name as their source.
pub const COMPONENT: &str = "cluster-autoscaler";

/// Phrases of node groups (or of the whole cluster) that could hold the pod but cannot grow
/// now; each goes away by itself or when the operator raises a limit, so the pod waits.
const CANNOT_GROW_NOW: [&str; 9] = [
    "max node group size reached",
    "max total nodes in cluster reached",
    "max cluster size reached",
    "in backoff after failed scale-up",
    "not ready for scale-up",
    // `max cluster <cpu, memory, ...> limit reached`
    "limit reached",
    "exceeds cluster node count limit",
    "at least one node can be vertically scaled",
    "not handling queued nodes",
];

/// The autoscaler's latest word on one pod.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ScaleUpWord {
    /// [`NOT_TRIGGERED`] or [`TRIGGERED`].
    pub reason: String,
    /// The event's message.
    pub message: String,
    /// When it was last said.
    pub at: Option<Timestamp>,
}

/// What the word means for the pod.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Outlook {
    /// Nodes are coming, or a node group could hold the pod once it may grow: wait.
    Waits,
    /// Every node group was rejected: no new node could ever hold the pod.
    Never {
        /// The rejections, as the autoscaler counted them (`2 Insufficient nvidia.com/gpu`).
        reasons: Vec<String>,
    },
    /// Nothing to go by (no node group at all, or a message in another form).
    Unclear,
}

impl ScaleUpWord {
    /// Classifies the word (see the module documentation).
    pub fn outlook(&self) -> Outlook {
        if self.reason == TRIGGERED {
            return Outlook::Waits;
        }
        if self.reason != NOT_TRIGGERED {
            return Outlook::Unclear;
        }
        // Older autoscalers, a pod that fits no template node.
        if self
            .message
            .contains("it wouldn't fit if a new node is added")
        {
            return Outlook::Never {
                reasons: vec!["it wouldn't fit if a new node is added".into()],
            };
        }
        let Some((_, reasons)) = self.message.split_once("scale-up:") else {
            return Outlook::Unclear;
        };
        let reasons = reasons.trim();
        if reasons.is_empty() {
            // No node group exists (or auto-discovery found none): the operator's setup,
            // which the scheduler's own limit reports after its wait.
            return Outlook::Unclear;
        }
        if CANNOT_GROW_NOW.iter().any(|p| reasons.contains(p)) {
            return Outlook::Waits;
        }
        Outlook::Never {
            reasons: split_reasons(reasons),
        }
    }
}

/// `2 Insufficient nvidia.com/gpu, 1 node(s) didn't match ...` -> its counted reasons.
/// A comma inside a reason (`untolerated taint(s)` lists, resource names) never precedes a
/// count, so only `, <digits> ` separates.
fn split_reasons(reasons: &str) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for piece in reasons.split(", ") {
        let counted = piece
            .split_once(' ')
            .is_some_and(|(n, _)| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()));
        match out.last_mut() {
            Some(last) if !counted => {
                last.push_str(", ");
                last.push_str(piece);
            }
            _ => out.push(piece.to_string()),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn word(reason: &str, message: &str) -> ScaleUpWord {
        ScaleUpWord {
            reason: reason.into(),
            message: message.into(),
            at: None,
        }
    }

    fn never(message: &str) -> Vec<String> {
        match word(NOT_TRIGGERED, message).outlook() {
            Outlook::Never { reasons } => reasons,
            other => panic!("{message}: {other:?}"),
        }
    }

    #[test]
    fn every_node_group_rejected_means_never() {
        assert_eq!(
            never("pod didn't trigger scale-up: 2 Insufficient nvidia.com/gpu"),
            vec!["2 Insufficient nvidia.com/gpu"]
        );
        assert_eq!(
            never("pod didn't trigger scale-up: 3 node(s) didn't match Pod's node affinity/selector, 1 Insufficient memory"),
            vec![
                "3 node(s) didn't match Pod's node affinity/selector",
                "1 Insufficient memory"
            ]
        );
        assert_eq!(
            never("pod didn't trigger scale-up: 1 node(s) had untolerated taint {dedicated: a, b}, 1 Insufficient cpu"),
            vec![
                "1 node(s) had untolerated taint {dedicated: a, b}",
                "1 Insufficient cpu"
            ]
        );
        assert_eq!(
            never("pod didn't trigger scale-up (it wouldn't fit if a new node is added)").len(),
            1
        );
    }

    #[test]
    fn a_node_group_that_cannot_grow_now_means_wait() {
        for message in [
            "pod didn't trigger scale-up: 2 max node group size reached",
            "pod didn't trigger scale-up: 1 node(s) had untolerated taint(s), 3 max node group size reached",
            "pod didn't trigger scale-up: 1 in backoff after failed scale-up",
            "pod didn't trigger scale-up: max total nodes in cluster reached",
            "pod didn't trigger scale-up: 1 max cluster cpu, memory limit reached, 2 Insufficient nvidia.com/gpu",
            "pod didn't trigger scale-up: 1 not ready for scale-up",
        ] {
            assert_eq!(word(NOT_TRIGGERED, message).outlook(), Outlook::Waits, "{message}");
        }
        assert_eq!(
            word(TRIGGERED, "pod triggered scale-up: [{gpu 1->2 (max: 4)}]").outlook(),
            Outlook::Waits
        );
    }

    #[test]
    fn no_reasons_or_another_form_is_unclear() {
        assert_eq!(
            word(NOT_TRIGGERED, "pod didn't trigger scale-up: ").outlook(),
            Outlook::Unclear
        );
        assert_eq!(
            word(NOT_TRIGGERED, "something else").outlook(),
            Outlook::Unclear
        );
        assert_eq!(
            word("FailedScheduling", "0/1 nodes are available").outlook(),
            Outlook::Unclear
        );
    }
}
