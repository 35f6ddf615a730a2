//! Consolidation at route ends: which GPU nodes to drain so the fleet's empty GPUs go, and
//! which pod of a drained node moves now. The sweep takes the first decision each minute, the
//! Monitor the second each round; the fleet model takes both, so the bench measures the rule
//! production runs.
//!
//! A pair writes its results at each route's end and a new pod resumes from them (the reclaim
//! path), so a pod moved just after a write loses seconds, not a route. A node at most half
//! used whose pairs the other open nodes have room for is tainted [`TAINT`]: the scheduler
//! sends it no new pod, and each of its pods is evicted at its pair's next write. Once empty,
//! the Cluster Autoscaler removes it (its pods are not safe to evict, so it never does while
//! one runs). When pods wait with no room on the open nodes, every drained node opens again
//! before the autoscaler would start a new one.

use std::collections::{BTreeMap, BTreeSet};

use crate::cluster::disruption::{self, NodeFacts};
use crate::cluster::view::JobView;
use crate::status::PodPhase;

/// The taint (effect `NoSchedule`) on a node being drained.
pub const TAINT: &str = disruption::CONSOLIDATING_TAINT;

/// How long after its pair's results were written a pod on a drained node is still moved, by
/// default (the leaderboard's `move_window_seconds`): the route it began since is what runs
/// again. The write wakes the Monitor within seconds; a later round leaves the pod to the
/// next route's end.
pub const MOVE_WINDOW_SECONDS: u64 = 120;

/// Moves per pair over its evaluation. Each costs the pair a pod's start (its images and
/// CARLA's, minutes given back as time lost); beyond them it stays where it is, so no chain
/// of drains moves one pair over and over.
pub const MAX_MOVES_PER_PAIR: u32 = 3;

/// A GPU node as the rule sees it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NodeUse {
    /// Its name.
    pub name: String,
    /// GPUs it offers.
    pub gpus: u32,
    /// GPUs its pods hold.
    pub held: u32,
    /// It takes pods: ready, and neither cordoned nor leaving for anyone.
    pub open: bool,
    /// It carries [`TAINT`].
    pub draining: bool,
}

/// What to change on the nodes.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Plan {
    /// Nodes to taint.
    pub drain: Vec<String>,
    /// Drained nodes to open again.
    pub reopen: Vec<String>,
}

impl Plan {
    /// Nothing to change.
    pub fn is_empty(&self) -> bool {
        self.drain.is_empty() && self.reopen.is_empty()
    }
}

/// The plan for `nodes` while pods asking `pending` GPUs wait for a node. With pods waiting,
/// nothing new is drained, and the drained nodes open again when the open ones lack room for
/// them. With none, the least used open nodes are drained, each at most half used and only
/// while the nodes staying open have room for its pairs, less the pairs already sent to them.
pub fn plan(nodes: &[NodeUse], pending: u32) -> Plan {
    let mut out = Plan::default();
    let open: Vec<&NodeUse> = nodes.iter().filter(|n| n.open && !n.draining).collect();
    let free = |n: &NodeUse| n.gpus.saturating_sub(n.held);
    if pending > 0 {
        let room: u32 = open.iter().map(|n| free(n)).sum();
        if room < pending {
            let drained = nodes.iter().filter(|n| n.draining);
            out.reopen = drained.map(|n| n.name.clone()).collect();
        }
        return out;
    }
    let mut order = open;
    order.sort_by(|a, b| (a.held.min(a.gpus), &a.name).cmp(&(b.held.min(b.gpus), &b.name)));
    // Free GPUs on the nodes staying open, less the pairs already sent to them: negative
    // once a node's own free GPUs were counted for pairs sent its way.
    let mut room: i64 = order.iter().map(|n| i64::from(free(n))).sum();
    for node in order {
        let busy = i64::from(node.held.min(node.gpus));
        let elsewhere = room - i64::from(free(node));
        if busy == 0 || busy * 2 > i64::from(node.gpus) || elsewhere < busy {
            continue;
        }
        out.drain.push(node.name.clone());
        room = elsewhere - busy;
    }
    out
}

/// A running pod of the submission, as the Monitor sees it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Running {
    /// Its Job's index.
    pub job: u32,
    /// Its name.
    pub pod: String,
    /// Its node.
    pub node: String,
    /// When it started (epoch seconds).
    pub started_at: u64,
}

/// The submission's pods running on a node, not being deleted and not disrupted.
pub fn running(jobs: &[JobView]) -> Vec<Running> {
    let mut out = Vec::new();
    for job in jobs {
        let Some(index) = job.index else { continue };
        for pod in &job.pods {
            let (Some(node), Some(start)) = (&pod.node, pod.start_time) else {
                continue;
            };
            if pod.phase != PodPhase::Running || pod.terminating || pod.disruption.is_some() {
                continue;
            }
            out.push(Running {
                job: index,
                pod: pod.name.clone(),
                node: node.clone(),
                started_at: u64::try_from(start.as_second()).unwrap_or(0),
            });
        }
    }
    out
}

/// Whether a node read is one the sweep drains.
pub fn drained(node: &NodeFacts) -> bool {
    node.taints.iter().any(|t| t == TAINT)
}

/// The pods that may move at `now`: their pair wrote results since the pod started and at
/// most `window` seconds ago, and it has moves left (`moved`: its moves so far). Whether their
/// nodes are drained is read next, for these alone.
pub fn due(
    pods: &[Running],
    written: &BTreeMap<u32, u64>,
    moved: impl Fn(u32) -> u32,
    (now, window): (u64, u64),
) -> Vec<Running> {
    pods.iter()
        .filter(|p| moved(p.job) < MAX_MOVES_PER_PAIR)
        .filter(|p| {
            written
                .get(&p.job)
                .is_some_and(|&at| at > p.started_at && at <= now && now - at <= window)
        })
        .cloned()
        .collect()
}

/// Of the pods [`due`], those on a drained node: the ones to evict.
pub fn to_move(due: Vec<Running>, drained: &BTreeSet<String>) -> Vec<Running> {
    due.into_iter()
        .filter(|p| drained.contains(&p.node))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn node(name: &str, held: u32) -> NodeUse {
        NodeUse {
            name: name.into(),
            gpus: 4,
            held,
            open: true,
            draining: false,
        }
    }

    #[test]
    fn the_least_used_nodes_drain_while_the_others_have_room_for_their_pairs() {
        // a's pair goes to the others (9 free), then c's (6 free less a's pair); b's two
        // would need b's own free GPUs, already counted for a's and c's; d is past half.
        let nodes = [node("a", 1), node("b", 2), node("c", 1), node("d", 3)];
        let plan = plan(&nodes, 0);
        assert_eq!(plan.drain, ["a", "c"]);
        assert!(plan.reopen.is_empty());
    }

    #[test]
    fn a_node_more_than_half_used_or_empty_or_not_open_is_never_drained() {
        let mut closed = node("closed", 1);
        closed.open = false;
        let nodes = [node("busy", 3), node("empty", 0), closed, node("room", 0)];
        assert!(plan(&nodes, 0).is_empty(), "{:?}", plan(&nodes, 0));
    }

    #[test]
    fn pods_waiting_drain_nothing_and_open_the_drained_nodes_when_room_runs_short() {
        let mut drained = node("drained", 1);
        drained.draining = true;
        let nodes = [drained, node("open", 2)];
        assert_eq!(plan(&nodes, 2), Plan::default(), "room for two: wait");
        assert_eq!(plan(&nodes, 3).reopen, ["drained"]);
        assert!(plan(&nodes, 3).drain.is_empty());
    }

    #[test]
    fn a_drained_node_gives_no_room_to_another_drain() {
        let mut drained = node("drained", 2);
        drained.draining = true;
        // With "drained" not counted as room, "a"'s pair fits only in "b".
        let nodes = [drained, node("a", 1), node("b", 3)];
        assert_eq!(plan(&nodes, 0).drain, ["a"]);
        let nodes = [node("a", 1), node("b", 4)];
        assert!(plan(&nodes, 0).is_empty(), "no room elsewhere");
    }

    fn running(job: u32, node: &str, started_at: u64) -> Running {
        Running {
            job,
            pod: format!("p{job}"),
            node: node.into(),
            started_at,
        }
    }

    #[test]
    fn a_pod_moves_just_after_its_pair_wrote_and_only_from_a_drained_node() {
        let pods = [
            running(0, "drained", 100),
            running(1, "drained", 100),
            running(2, "drained", 500),
            running(3, "open", 100),
            running(4, "drained", 100),
        ];
        let now = 1_000;
        let written = BTreeMap::from([
            (0, now - 30),                      // just wrote: moves
            (1, now - MOVE_WINDOW_SECONDS - 1), // too long ago: its route is under way
            (2, 400),                           // before this pod started: not a route of its own
            (3, now - 5),                       // on an open node
            (4, now - 5),                       // out of moves
        ]);
        let moved = |job| if job == 4 { MAX_MOVES_PER_PAIR } else { 0 };
        let due = due(&pods, &written, moved, (now, MOVE_WINDOW_SECONDS));
        let jobs: Vec<u32> = due.iter().map(|p| p.job).collect();
        assert_eq!(jobs, [0, 3]);
        let drained = BTreeSet::from(["drained".to_string()]);
        assert_eq!(to_move(due, &drained), [running(0, "drained", 100)]);
    }
}
