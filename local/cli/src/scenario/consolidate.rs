//! Consolidation at route ends rehearsed: the pairs run on a node of 8 GPUs, half used; once a
//! route is done a second node joins with room for them all, the sweep drains the first (its
//! rule, its taint), and the Monitor moves each pair at its next results write. Every move is
//! free (no retry used, none of the pair's free reclaims taken), the pairs end on the second
//! node, and the run scores as the happy one. FINISHED (`--kube real` only: local-kube has one
//! node).

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use local_stack::workloads::Behaviour;
use serde::Serialize;
use serde_json::Value;
use tokio::sync::watch;
use tokio::task::JoinHandle;

use lb_domain::capacity::cost::Ledger;
use lb_domain::status::PodPhase;

use super::{held, Begin, Findings, Rehearsal};
use crate::reclaim::{count_route_runs, note_disruptions, ReclaimReport};

/// The least seconds per route: a move lands within the leaderboard's window after a write
/// (120 s scaled by the run's time scale), well before the next route's end.
const CONSOLIDATE_ROUTE_SECONDS: f64 = 8.0;

/// GPUs of each node: the pairs (4) hold half of the first.
const NODE_GPUS: u32 = 8;

/// The node the pairs start on, and the one that joins (`local_stack::real`'s two nodes).
const FIRST: &str = "gpu-node-1";
const JOINS: &str = "gpu-node-2";

/// How often the pods and nodes are looked at.
const LOOK_EVERY: Duration = Duration::from_millis(200);

/// What the consolidation did and what followed.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ConsolidationReport {
    /// The pods moved (`evicted`: those seen with `DisruptionTarget`), retries used and the
    /// routes run again, as for a reclaim.
    #[serde(flatten)]
    pub reclaim: ReclaimReport,
    /// Nodes seen carrying the consolidation taint.
    pub drained: BTreeSet<String>,
    /// The moves the Monitor counted in the run's ledger.
    pub moves: u32,
    /// The nodes the submission's running pods were last seen on.
    pub ended_on: BTreeSet<String>,
}

impl ConsolidationReport {
    /// What consolidation should come to: the first node drained and no other, each pod taken
    /// off it a move the Monitor counted (nobody else evicted), the moves as free as a
    /// reclaim, and the pairs ending on the node that joined.
    pub fn as_expected(&self) -> bool {
        self.reclaim.as_expected()
            && self.drained == BTreeSet::from([FIRST.to_string()])
            && self.moves as usize == self.reclaim.evicted.len()
            && self.ended_on.iter().all(|n| n == JOINS)
    }
}

/// The consolidation rehearsal.
#[derive(Default)]
pub struct Consolidate {
    watcher: Mutex<Option<(JoinHandle<ConsolidationReport>, watch::Sender<bool>)>>,
    kubeconfig: Mutex<Option<PathBuf>>,
    joined: AtomicBool,
    /// The moves in the latest run state a round left.
    moves: Arc<AtomicU32>,
}

impl Rehearsal for Consolidate {
    fn expected(&self) -> &'static str {
        "finished"
    }

    fn needs_real_kube(&self) -> bool {
        true
    }

    fn set_up(&self, behaviour: &mut Behaviour, _once: &Path) {
        behaviour.route_seconds = behaviour.route_seconds.max(CONSOLIDATE_ROUTE_SECONDS);
        behaviour.node_gpus = Some(NODE_GPUS);
        behaviour.spare_node = true;
        behaviour.spare_node_joins_later = true;
    }

    fn acts(&self) -> bool {
        true
    }

    fn begin(&self, run: &Begin) {
        let (stop, stopped) = watch::channel(false);
        let task = tokio::spawn(watch_pods_and_nodes(
            (run.kubeconfig.clone(), run.namespace.clone()),
            run.submission,
            stopped,
            run.acted.clone(),
        ));
        *held(&self.watcher) = Some((task, stop));
        *held(&self.kubeconfig) = Some(run.kubeconfig.clone());
    }

    /// A route is done: the second node joins (once); the moves counted so far are kept.
    fn round_ended(&self, monitor: &Value) {
        self.moves.store(moves_in(monitor), Ordering::SeqCst);
        if monitor["progress"][0].as_u64() < Some(1) || self.joined.swap(true, Ordering::SeqCst) {
            return;
        }
        let Some(kubeconfig) = held(&self.kubeconfig).clone() else {
            return;
        };
        tokio::spawn(async move {
            let joined = super::node_joins(&kubeconfig, JOINS).await;
            cli::outln!(
                "           scenario: node {JOINS} joined with room for every pair: {joined}"
            );
        });
    }

    fn finish<'a>(
        &'a self,
        logs: &'a [String],
    ) -> Pin<Box<dyn std::future::Future<Output = Findings> + Send + 'a>> {
        let watcher = held(&self.watcher).take();
        Box::pin(async move {
            let Some((task, stop)) = watcher else {
                return Findings::default();
            };
            let _ = stop.send(true);
            let mut report = task.await.unwrap_or_default();
            count_route_runs(logs, &mut report.reclaim);
            report.moves = self.moves.load(Ordering::SeqCst);
            Findings {
                consolidation: Some(report),
                ..Findings::default()
            }
        })
    }
}

/// The moves the run state's ledger counts, over its Jobs.
fn moves_in(monitor: &Value) -> u32 {
    let ledger = serde_json::from_value::<Ledger>(monitor["usage"].clone());
    ledger.map_or(0, |l| l.jobs.iter().map(|j| j.moves).sum())
}

/// Watches the submission's pods (those taken away, the Jobs' retries, the nodes the running
/// ones are on) and the nodes tainted, until stopped; `acted` once a pod was moved.
async fn watch_pods_and_nodes(
    (kubeconfig, namespace): (PathBuf, String),
    submission: u64,
    mut stopped: watch::Receiver<bool>,
    acted: Arc<AtomicBool>,
) -> ConsolidationReport {
    let mut report = ConsolidationReport::default();
    let Ok(cluster) = lb_cluster::Cluster::from_kubeconfig(&kubeconfig, None).await else {
        return report;
    };
    let cluster = cluster.with_namespace(namespace);
    loop {
        tokio::select! {
            _ = stopped.changed() => return report,
            () = tokio::time::sleep(LOOK_EVERY) => {}
        }
        if let Ok(fleet) = cluster.gpu_fleet().await {
            let drained = fleet.nodes.into_iter().filter(|n| n.draining);
            report.drained.extend(drained.map(|n| n.name));
        }
        let Ok(seen) = cluster.observe(&submission.to_string()).await else {
            continue;
        };
        note_disruptions(&seen, &mut report.reclaim);
        // Every pod taken away here is one the Monitor moved (nothing else evicts).
        let reclaim = &mut report.reclaim;
        for pod in reclaim.disrupted.keys() {
            if !reclaim.evicted.contains(pod) {
                reclaim.evicted.push(pod.clone());
                acted.store(true, Ordering::SeqCst);
            }
        }
        let on: BTreeSet<String> = (seen.jobs.iter().flat_map(|j| &j.pods))
            .filter(|p| p.phase == PodPhase::Running && !p.terminating)
            .filter_map(|p| p.node.clone())
            .collect();
        if !on.is_empty() {
            report.ended_on = on;
        }
    }
}
