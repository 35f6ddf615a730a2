//! The rehearsal's workloads on the real Kubernetes control plane: the pinned kube-apiserver,
//! controller-manager and scheduler (`real_kube`), `infra/k8s` applied as an operator applies
//! it, and GPU nodes as the node groups of `infra/cluster.yaml` make them, whose kubelet is
//! local-kube's process runner (`node_agent`).

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::{Arc, Weak};

use k8s_openapi::api::core::v1::Taint;
use lb_domain::settings::Settings;
use node_agent::{NodeAgent, NodeSpec};
use real_kube::{ControlPlane, Identity};

use crate::stack::StackError;
use crate::workloads::Behaviour;

/// What the cluster's manifests are (the repository's, applied as `make cluster` applies them).
const INFRA_K8S: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../infra/k8s");

/// The node group's label of the pool GPU nodes belong to (`infra/cluster.yaml`).
const POOL_LABEL: &str = "leaderboard.carla.org/pool";

/// GPUs of a node when neither the run nor the settings say.
const DEFAULT_GPUS: u32 = 4;

/// How long the node agent holds an evicted pod's `Failed` after its `DisruptionTarget`
/// condition: longer than the Monitor's rounds are apart in a local run, so a round sees the
/// pod stopped with the condition while its phase still says `Running`, as it can on EKS.
const EVICTIONS_REPORTED_LATE: std::time::Duration = std::time::Duration::from_secs(5);

/// The node a run's pods are placed on: its instance type and its node group's labels.
pub struct NodeOf {
    /// `node.kubernetes.io/instance-type`, when one is modelled.
    pub instance_type: Option<String>,
    /// The GPU model and capacity type labels.
    pub labels: BTreeMap<String, String>,
}

/// One node, of the instance type the leaderboards run on (the run's own when it names one),
/// labelled as its node group labels it: the GPU model of that type, and the capacity type EKS
/// adds.
pub fn node_of(settings: &Settings, behaviour: &Behaviour) -> NodeOf {
    let mut types = settings.leaderboards.values().map(|l| &l.instance_type);
    let shared = types
        .next()
        .filter(|first| types.all(|t| t == *first))
        .cloned();
    let instance_type = behaviour.node_instance_type.clone().or(shared);
    let labels = instance_type
        .as_deref()
        .and_then(lb_domain::cluster::resources::gpu_model)
        .map(|model| {
            BTreeMap::from([
                (
                    lb_domain::cluster::resources::GPU_MODEL_LABEL.to_owned(),
                    model.to_owned(),
                ),
                (
                    lb_domain::settings::Capacity::LABEL.to_owned(),
                    behaviour
                        .node_capacity
                        .node_label()
                        .unwrap_or("ON_DEMAND")
                        .to_owned(),
                ),
            ])
        })
        .unwrap_or_default();
    NodeOf {
        instance_type,
        labels,
    }
}

/// What an in-place upgrade of the control plane did.
#[derive(Debug, Clone)]
pub struct Upgraded {
    /// The API server's release before.
    pub from: String,
    /// And after.
    pub to: String,
    /// How long the API answered nothing.
    pub unavailable_seconds: f64,
}

/// Upgrades a running control plane to the release one minor up (`build.sh --upgrade`),
/// as EKS upgrades a cluster's: the pods on the nodes run on meanwhile. It does not keep the
/// control plane alive: whoever holds it (a scenario the executor's hooks outlive) must not
/// keep the servers running past the cluster's own drop.
#[derive(Clone)]
pub struct Upgrader(Weak<ControlPlane>);

fn upgrade_failed(e: real_kube::Error) -> StackError {
    StackError::Kube(format!("upgrading the control plane: {e}"))
}

impl Upgrader {
    /// The new release's binaries (blocking: built the first time, in minutes; found after).
    pub fn binaries(&self) -> Result<std::path::PathBuf, StackError> {
        real_kube::upgrade_binaries().map_err(upgrade_failed)
    }

    /// Replaces the servers by `bin`'s (blocking: seconds).
    pub fn upgrade(&self, bin: &Path) -> Result<Upgraded, StackError> {
        let fail = upgrade_failed;
        let plane = self
            .0
            .upgrade()
            .ok_or_else(|| StackError::Kube("the control plane is gone".into()))?;
        let from = plane.version().map_err(fail)?;
        let unavailable = plane.upgrade(bin).map_err(fail)?;
        let to = plane.version().map_err(fail)?;
        Ok(Upgraded {
            from,
            to,
            unavailable_seconds: unavailable.as_secs_f64(),
        })
    }
}

/// The real control plane and the agent serving its nodes; dropping it stops both.
pub struct RealCluster {
    // NB: the agent goes first: it ends its pods while the API server still answers.
    /// The node agent.
    pub agent: NodeAgent,
    /// The control plane (shared: the upgrade rehearsal replaces its servers mid-run).
    pub plane: Arc<ControlPlane>,
}

impl RealCluster {
    /// What upgrades its control plane in place.
    pub fn upgrader(&self) -> Upgrader {
        Upgrader(Arc::downgrade(&self.plane))
    }

    /// Builds (once per machine) and starts the control plane, applies `infra/k8s`, and
    /// registers the run's GPU nodes (two when the scenario drains one).
    pub fn start(
        settings: &Settings,
        behaviour: &Behaviour,
        images: local_kube::ImageMap,
        workdir: &Path,
    ) -> Result<RealCluster, StackError> {
        let fail = |e: real_kube::Error| StackError::Kube(format!("real control plane: {e}"));
        let bin = real_kube::binaries().map_err(fail)?;
        let plane = Arc::new(ControlPlane::start(&bin).map_err(fail)?);
        plane.apply(Path::new(INFRA_K8S)).map_err(fail)?;
        let node = node_of(settings, behaviour);
        let gpus = behaviour
            .node_gpus
            .or_else(|| {
                settings
                    .leaderboards
                    .values()
                    .map(|l| l.gpus_per_node)
                    .max()
            })
            .unwrap_or(DEFAULT_GPUS);
        let mut labels = node.labels;
        labels.insert(POOL_LABEL.into(), "gpu".into());
        if let Some(t) = node.instance_type {
            labels.insert("node.kubernetes.io/instance-type".into(), t);
        }
        let taint = Taint {
            key: node_agent::GPU_TAINT.into(),
            value: Some("true".into()),
            effect: "NoSchedule".into(),
            ..Taint::default()
        };
        let count = if behaviour.spare_node { 2 } else { 1 };
        let nodes = (1..=count)
            .map(|i| NodeSpec {
                name: format!("gpu-node-{i}"),
                gpus,
                labels: labels.clone(),
                taints: vec![taint.clone()],
                disk: behaviour.node_disk,
                unschedulable: i > 1 && behaviour.spare_node_joins_later,
            })
            .collect();
        let agent = NodeAgent::spawn(node_agent::Config {
            kubeconfig: plane.kubeconfig(Identity::Admin),
            nodes,
            runtime: local_kube::Config {
                images,
                state_dir: Some(workdir.join("pods")),
                ..local_kube::Config::default()
            },
            tls: plane.kubelet_tls(),
            autoscaler: true,
            evictions_reported_late: EVICTIONS_REPORTED_LATE,
        })
        .map_err(|e| StackError::Kube(format!("node agent: {e}")))?;
        Ok(RealCluster { agent, plane })
    }
}
