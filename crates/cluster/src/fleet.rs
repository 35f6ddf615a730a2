//! What a cluster's GPU nodes hold, for operators (`lbctl top`): each GPU node with its kind
//! and GPUs, and the GPUs the pods bound to it take. It lists the nodes and the namespace's
//! pods: an operator's access. Nothing of the pipeline calls it, and the pipeline's role does
//! not grant listing nodes.

use k8s_openapi::api::core::v1::{Node, Pod};
use kube::api::ListParams;
use lb_domain::capacity::cost::{CapacityType, NodeKind};

use crate::cluster::{is_ready, kind_of, Cluster};
use crate::error::{ClusterError, Result};

/// The resource a pair's pod asks GPUs by.
const GPU: &str = "nvidia.com/gpu";

/// One GPU node.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
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
}

/// The GPU nodes of a cluster: every one is paid for, from its launch to its termination,
/// whether its GPUs are held or not.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct GpuFleet {
    /// By name.
    pub nodes: Vec<GpuNode>,
}

impl GpuFleet {
    /// The fleet `nodes` and `pods` describe: the nodes with GPUs, each with the GPUs of the
    /// pods bound to it that have not ended.
    pub fn of(nodes: &[Node], pods: &[Pod]) -> GpuFleet {
        let mut out: Vec<GpuNode> = nodes
            .iter()
            .filter_map(|node| {
                let gpus = quantity(node.status.as_ref()?.allocatable.as_ref()?.get(GPU)?)?;
                Some(GpuNode {
                    name: node.metadata.name.clone()?,
                    kind: kind_of(node),
                    gpus,
                    held: 0,
                    ready: is_ready(node),
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
            let Some(node) = spec.node_name.as_deref() else {
                continue;
            };
            let gpus: u32 = spec
                .containers
                .iter()
                .filter_map(|c| {
                    let r = c.resources.as_ref()?;
                    let asked = r.limits.as_ref().and_then(|l| l.get(GPU));
                    quantity(asked.or(r.requests.as_ref().and_then(|q| q.get(GPU)))?)
                })
                .sum();
            if let Some(n) = out.iter_mut().find(|n| n.name == node) {
                n.held = n.held.saturating_add(gpus);
            }
        }
        out.sort_by(|a, b| a.name.cmp(&b.name));
        GpuFleet { nodes: out }
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
        assert_eq!(fleet.spot_nodes(), 1);
        assert!(fleet.nodes.iter().all(|n| n.ready));
    }
}
