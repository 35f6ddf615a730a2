//! What a cluster's GPU nodes hold, for the sweep and operators (`lbctl top`): each GPU node
//! with its kind, its GPUs and the GPUs the pods bound to it take, and the GPUs pods wait for;
//! and the sweep's one change, a node's consolidation taint set or taken off. It lists the
//! nodes and the namespace's pods and patches nodes: the fleet group's access. Nothing of the
//! pipeline calls it, and the pipeline's role grants none of it.

use k8s_openapi::api::core::v1::{Node, Pod, Taint};
use kube::api::{ListParams, Patch, PatchParams};
use lb_domain::capacity::consolidation::{self, NodeUse};
use lb_domain::capacity::cost::{CapacityType, NodeKind};
use lb_domain::capacity::forecast::Capacity;
use lb_domain::cluster::disruption;
use lb_domain::cluster::resources;
use tracing::info;

use crate::cluster::{facts_of, kind_of, Cluster};
use crate::error::{ClusterError, Result};

/// The resource a pair's pod asks GPUs by.
const GPU: &str = "nvidia.com/gpu";

/// One GPU node.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct GpuNode {
    /// Its name.
    pub name: String,
    /// Its instance type and capacity type (what it costs).
    pub kind: NodeKind,
    /// GPUs it offers (allocatable).
    pub gpus: u32,
    /// GPUs the pods bound to it and not ended take.
    pub held: u32,
    /// It reports `Ready`.
    pub ready: bool,
    /// It takes pods: ready, neither cordoned nor leaving for anyone but us.
    pub open: bool,
    /// It carries the consolidation taint.
    pub draining: bool,
    /// Its taints and object version, for a patch that changes only ours.
    #[serde(skip)]
    taints: Vec<Taint>,
    #[serde(skip)]
    version: Option<String>,
}

/// The GPU nodes of a cluster: every one is paid for, from its launch to its termination,
/// whether its GPUs are held or not.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct GpuFleet {
    /// By name.
    pub nodes: Vec<GpuNode>,
    /// GPUs the namespace's pods ask for and no node holds yet (not bound, not ended).
    pub pending: u32,
    /// GPU nodes (labelled with a GPU model) not ready yet or not yet advertising their GPUs.
    pub booting: u32,
}

impl GpuFleet {
    /// The fleet `nodes` and `pods` describe: the nodes with GPUs, each with the GPUs of the
    /// pods bound to it that have not ended.
    pub fn of(nodes: &[Node], pods: &[Pod]) -> GpuFleet {
        let mut pending = 0u32;
        let booting = (nodes.iter())
            .filter(|n| {
                let labels = n.metadata.labels.as_ref();
                labels.is_some_and(|l| l.contains_key(resources::GPU_MODEL_LABEL))
            })
            .filter(|n| {
                let gpus = n
                    .status
                    .as_ref()
                    .and_then(|s| s.allocatable.as_ref()?.get(GPU));
                !facts_of(n).ready || gpus.and_then(quantity).unwrap_or(0) == 0
            })
            .count() as u32;
        let mut out: Vec<GpuNode> = nodes
            .iter()
            .filter_map(|node| {
                let gpus = quantity(node.status.as_ref()?.allocatable.as_ref()?.get(GPU)?)?;
                let mut facts = facts_of(node);
                let draining = consolidation::drained(&facts);
                facts.taints.retain(|t| t != consolidation::TAINT);
                Some(GpuNode {
                    name: node.metadata.name.clone()?,
                    kind: kind_of(node),
                    gpus,
                    held: 0,
                    ready: facts.ready,
                    open: !disruption::leaving(Some(&facts)),
                    draining,
                    taints: (node.spec.as_ref().and_then(|s| s.taints.clone())).unwrap_or_default(),
                    version: node.metadata.resource_version.clone(),
                })
            })
            .filter(|n| n.gpus > 0)
            .collect();
        for pod in pods {
            let phase = pod.status.as_ref().and_then(|s| s.phase.as_deref());
            if lb_domain::status::PodPhase::reported(phase).has_ended() {
                continue;
            }
            let Some(spec) = &pod.spec else { continue };
            let gpus: u32 = spec
                .containers
                .iter()
                .filter_map(|c| {
                    let r = c.resources.as_ref()?;
                    let asked = r.limits.as_ref().and_then(|l| l.get(GPU));
                    quantity(asked.or(r.requests.as_ref().and_then(|q| q.get(GPU)))?)
                })
                .sum();
            let Some(node) = spec.node_name.as_deref() else {
                pending = pending.saturating_add(gpus);
                continue;
            };
            if let Some(n) = out.iter_mut().find(|n| n.name == node) {
                n.held = n.held.saturating_add(gpus);
            }
        }
        out.sort_by(|a, b| a.name.cmp(&b.name));
        GpuFleet {
            nodes: out,
            pending,
            booting,
        }
    }

    /// What a forecast of the queue waits for (`forecast::Capacity`): GPUs free on the nodes
    /// taking pods and not drained, those of the nodes booting (`gpus_per_node` each), and
    /// those of the nodes the node groups' maxima (`max_nodes`, none when unknown) leave room
    /// for.
    pub fn capacity(&self, gpus_per_node: u32, max_nodes: Option<u32>) -> Capacity {
        let free = (self.nodes.iter())
            .filter(|n| n.open && n.ready && !n.draining)
            .map(|n| n.gpus.saturating_sub(n.held))
            .sum();
        let nodes = (self.nodes.len() as u32).saturating_add(self.booting);
        let addable = max_nodes.map_or(0, |max| max.saturating_sub(nodes));
        Capacity {
            free,
            booting: self.booting.saturating_mul(gpus_per_node),
            addable: addable.saturating_mul(gpus_per_node),
        }
    }

    /// The nodes as the consolidation rule sees them.
    pub fn uses(&self) -> Vec<NodeUse> {
        (self.nodes.iter())
            .map(|n| NodeUse {
                name: n.name.clone(),
                gpus: n.gpus,
                held: n.held,
                open: n.open,
                draining: n.draining,
            })
            .collect()
    }

    /// GPUs paid for.
    pub fn gpus(&self) -> u32 {
        self.nodes.iter().map(|n| n.gpus).sum()
    }

    /// GPUs held by pods (at most each node's own).
    pub fn held(&self) -> u32 {
        self.nodes.iter().map(|n| n.held.min(n.gpus)).sum()
    }

    /// Nodes on Spot capacity.
    pub fn spot_nodes(&self) -> usize {
        let spot = |n: &&GpuNode| n.kind.capacity == CapacityType::Spot;
        self.nodes.iter().filter(spot).count()
    }
}

/// A whole count from a quantity (`"4"`); none for another form.
fn quantity(q: &k8s_openapi::apimachinery::pkg::api::resource::Quantity) -> Option<u32> {
    q.0.trim().parse().ok()
}

impl Cluster {
    /// The cluster's GPU nodes and what the namespace's pods take of them (one list of each).
    pub async fn gpu_fleet(&self) -> Result<GpuFleet> {
        let params = ListParams::default();
        let nodes = self.nodes();
        let pods = self.pods();
        let (nodes, pods) = tokio::join!(
            self.call("list nodes", nodes.list(&params)),
            self.call("list pods", pods.list(&params)),
        );
        let nodes = nodes?.map_err(|e| ClusterError::from_kube("list nodes", "", e))?;
        let pods = pods?.map_err(|e| ClusterError::from_kube("list pods", "", e))?;
        Ok(GpuFleet::of(&nodes.items, &pods.items))
    }

    /// Sets or takes off `node`'s consolidation taint (`NoSchedule`), its other taints kept. The
    /// patch carries the version the fleet read, so a node changed since (a taint of the
    /// autoscaler's, a cordon) is left for the next sweep: `Ok(false)`, as for a node gone.
    pub async fn set_draining(&self, node: &GpuNode, draining: bool) -> Result<bool> {
        let mut taints: Vec<Taint> = (node.taints.iter())
            .filter(|t| t.key != consolidation::TAINT)
            .cloned()
            .collect();
        if draining {
            taints.push(Taint {
                key: consolidation::TAINT.into(),
                effect: "NoSchedule".into(),
                ..Taint::default()
            });
        }
        let patch = Patch::Merge(serde_json::json!({
            "metadata": {"resourceVersion": node.version},
            "spec": {"taints": taints},
        }));
        let nodes = self.nodes();
        let patched = self
            .call(
                "patch node",
                nodes.patch(&node.name, &PatchParams::default(), &patch),
            )
            .await?;
        match patched {
            Ok(_) => {
                info!(node = node.name, draining, "consolidation taint set");
                Ok(true)
            }
            Err(kube::Error::Api(s)) if s.is_not_found() || s.code == 409 => Ok(false),
            Err(e) => Err(ClusterError::from_kube(
                "patch node",
                &format!("Node `{}`", node.name),
                e,
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn node(name: &str, gpus: &str, capacity: &str) -> Node {
        serde_json::from_value(json!({
            "metadata": {"name": name, "labels": {
                "node.kubernetes.io/instance-type": "g5.12xlarge",
                "eks.amazonaws.com/capacityType": capacity}},
            "status": {"allocatable": {"nvidia.com/gpu": gpus, "cpu": "48"},
                       "conditions": [{"type": "Ready", "status": "True"}]}
        }))
        .unwrap()
    }

    fn pod(node: Option<&str>, gpus: &str, phase: &str) -> Pod {
        serde_json::from_value(json!({
            "metadata": {"name": "p"},
            "spec": {"nodeName": node, "containers": [
                {"name": "agent", "resources": {"limits": {"nvidia.com/gpu": gpus}}},
                {"name": "sidecar"}]},
            "status": {"phase": phase}
        }))
        .unwrap()
    }

    #[test]
    fn a_fleet_counts_the_gpus_of_the_pods_bound_and_not_ended() {
        let nodes = [
            node("a", "4", "SPOT"),
            node("b", "4", "ON_DEMAND"),
            node("cpu", "0", "ON_DEMAND"),
        ];
        let pods = [
            pod(Some("a"), "1", "Running"),
            pod(Some("a"), "1", "Pending"),
            pod(Some("a"), "1", "Succeeded"),
            pod(None, "1", "Pending"),
            pod(Some("b"), "1", "Failed"),
        ];
        let fleet = GpuFleet::of(&nodes, &pods);
        assert_eq!(fleet.nodes.len(), 2, "the CPU node is not a GPU node");
        assert_eq!((fleet.gpus(), fleet.held()), (8, 2));
        assert_eq!(fleet.pending, 1, "the pod no node holds yet");
        assert_eq!(fleet.spot_nodes(), 1);
        assert!(fleet.nodes.iter().all(|n| n.ready));
    }

    #[test]
    fn a_node_with_our_taint_is_draining_and_open_and_one_cordoned_by_another_is_not_open() {
        let taint = |n: &mut Node, key: &str| {
            let spec = n.spec.get_or_insert_with(Default::default);
            spec.taints.get_or_insert_with(Vec::new).push(Taint {
                key: key.into(),
                effect: "NoSchedule".into(),
                ..Taint::default()
            });
        };
        let mut ours = node("ours", "4", "SPOT");
        taint(&mut ours, consolidation::TAINT);
        let mut cordoned = node("cordoned", "4", "SPOT");
        taint(&mut cordoned, "node.kubernetes.io/unschedulable");
        let fleet = GpuFleet::of(&[ours, cordoned], &[pod(Some("ours"), "1", "Running")]);
        let uses = fleet.uses();
        let by = |name: &str| uses.iter().find(|u| u.name == name).unwrap().clone();
        assert!(by("ours").open && by("ours").draining);
        assert_eq!(by("ours").held, 1);
        assert!(!by("cordoned").open && !by("cordoned").draining);
    }

    #[test]
    fn the_capacity_a_forecast_waits_for_counts_free_booting_and_addable_gpus() {
        let mut drained = node("drained", "4", "SPOT");
        drained.spec = Some(k8s_openapi::api::core::v1::NodeSpec {
            taints: Some(vec![Taint {
                key: consolidation::TAINT.into(),
                effect: "NoSchedule".into(),
                ..Taint::default()
            }]),
            ..Default::default()
        });
        let booting: Node = serde_json::from_value(json!({
            "metadata": {"name": "new", "labels": {resources::GPU_MODEL_LABEL: "nvidia-a10g-24gb"}},
            "status": {"conditions": [{"type": "Ready", "status": "False"}]}
        }))
        .unwrap();
        let pods = [
            pod(Some("a"), "1", "Running"),
            pod(Some("drained"), "1", "Running"),
        ];
        let fleet = GpuFleet::of(&[node("a", "4", "SPOT"), drained, booting], &pods);
        assert_eq!(fleet.booting, 1);
        let counted = fleet.capacity(4, Some(5));
        // 3 free on "a" (none on the drained node), one node of 4 booting, room for 2 more.
        assert_eq!((counted.free, counted.booting, counted.addable), (3, 4, 8));
        assert_eq!(fleet.capacity(4, None).addable, 0, "maxima unknown");
    }
}
