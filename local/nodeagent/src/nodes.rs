//! The Node objects: registered as a node group's kubelet registers them, and cordoned as a
//! managed node group cordons a node it drains.

use k8s_openapi::api::core::v1::{Node, Taint};
use kube::api::{Api, Patch, PatchParams, PostParams};
use serde_json::json;

use crate::{Error, NodeSpec};

/// The taint of every GPU node group (`infra/cluster.yaml`): only pods that tolerate it land.
pub const GPU_TAINT: &str = "nvidia.com/gpu";

/// The taint the API server's admission puts on a new Node until it is Ready (the node
/// lifecycle controller would lift it; it does not run beside a node agent).
const NOT_READY: &str = "node.kubernetes.io/not-ready";

/// The taint a cordoned node carries (`kubectl cordon` sets `spec.unschedulable`; the node
/// lifecycle controller mirrors it as this taint).
const UNSCHEDULABLE: &str = "node.kubernetes.io/unschedulable";

/// Resources beyond the GPUs and the disk: more than any pair asks, so GPUs are what the
/// scheduler counts.
const ROOMY: [(&str, &str); 3] = [("cpu", "192"), ("memory", "768Gi"), ("pods", "110")];

/// Registers `node` (or takes over a Node of that name), Ready, with its capacity and the log
/// endpoint on `port`, carrying only its node group's taints.
pub async fn register(client: &kube::Client, node: &NodeSpec, port: u16) -> Result<(), Error> {
    let api: Api<Node> = Api::all(client.clone());
    let fail = |what: &str, e: kube::Error| Error::Api(format!("node {}: {what}: {e}", node.name));
    let mut labels = node.labels.clone();
    labels.insert("kubernetes.io/hostname".into(), node.name.clone());
    labels.insert("kubernetes.io/os".into(), "linux".into());
    labels.insert("kubernetes.io/arch".into(), "amd64".into());
    let object: Node = serde_json::from_value(json!({
        "metadata": {"name": node.name, "labels": labels},
        "spec": {"taints": node.taints},
    }))
    .map_err(|e| Error::Api(format!("node {}: {e}", node.name)))?;
    match api.create(&PostParams::default(), &object).await {
        Ok(_) => {}
        Err(kube::Error::Api(s)) if s.code == 409 => {}
        Err(e) => return Err(fail("create", e)),
    }
    let mut resources: serde_json::Map<String, serde_json::Value> = ROOMY
        .iter()
        .map(|(k, v)| ((*k).to_owned(), json!(v)))
        .collect();
    resources.insert("nvidia.com/gpu".into(), json!(node.gpus.to_string()));
    let (mut capacity, mut allocatable) = (resources.clone(), resources);
    capacity.insert(
        "ephemeral-storage".into(),
        json!(node.disk.capacity.to_string()),
    );
    allocatable.insert(
        "ephemeral-storage".into(),
        json!(node.disk.allocatable().to_string()),
    );
    let status = json!({"status": {
        "capacity": capacity, "allocatable": allocatable,
        "conditions": [{"type": "Ready", "status": "True", "reason": "KubeletReady",
                        "message": "kubelet is posting ready status"}],
        "addresses": [{"type": "InternalIP", "address": "127.0.0.1"},
                      {"type": "Hostname", "address": node.name}],
        "daemonEndpoints": {"kubeletEndpoint": {"Port": port}},
    }});
    let params = PatchParams::default();
    api.patch_status(&node.name, &params, &Patch::Merge(&status))
        .await
        .map_err(|e| fail("status", e))?;
    set_taints(&api, &node.name, |taints| {
        taints.retain(|t| t.key != NOT_READY);
    })
    .await
    .map_err(|e| fail("taints", e))?;
    if node.unschedulable {
        cordon(client, &node.name)
            .await
            .map_err(|e| fail("cordon", e))?;
    }
    Ok(())
}

/// Cordons `node` as a managed node group does before draining it: unschedulable, with the
/// taint that says so.
pub async fn cordon(client: &kube::Client, node: &str) -> Result<(), kube::Error> {
    let api: Api<Node> = Api::all(client.clone());
    let unschedulable = json!({"spec": {"unschedulable": true}});
    api.patch(node, &PatchParams::default(), &Patch::Merge(&unschedulable))
        .await?;
    set_taints(&api, node, |taints| {
        if !taints.iter().any(|t| t.key == UNSCHEDULABLE) {
            taints.push(Taint {
                key: UNSCHEDULABLE.into(),
                effect: "NoSchedule".into(),
                ..Taint::default()
            });
        }
    })
    .await
}

/// Makes `node` schedulable again: what a node that joins its group looks like to the
/// scheduler.
pub async fn uncordon(client: &kube::Client, node: &str) -> Result<(), kube::Error> {
    let api: Api<Node> = Api::all(client.clone());
    let schedulable = json!({"spec": {"unschedulable": false}});
    api.patch(node, &PatchParams::default(), &Patch::Merge(&schedulable))
        .await?;
    set_taints(&api, node, |taints| {
        taints.retain(|t| t.key != UNSCHEDULABLE)
    })
    .await
}

/// How often a taint change is tried when others change the Node meanwhile (the TTL
/// controller annotates new nodes).
const TAINT_TRIES: u32 = 5;

/// Rewrites a node's taints: a merge patch replaces the list, guarded by the resourceVersion
/// read, read again and retried (a few times, with backoff) when the Node changed meanwhile.
async fn set_taints(
    api: &Api<Node>,
    name: &str,
    change: impl Fn(&mut Vec<Taint>),
) -> Result<(), kube::Error> {
    let mut wait = std::time::Duration::from_millis(50);
    for attempt in 1..=TAINT_TRIES {
        let current = api.get(name).await?;
        let mut taints = current
            .spec
            .as_ref()
            .and_then(|s| s.taints.clone())
            .unwrap_or_default();
        change(&mut taints);
        let patch = json!({
            "metadata": {"resourceVersion": current.metadata.resource_version},
            "spec": {"taints": taints},
        });
        match api
            .patch(name, &PatchParams::default(), &Patch::Merge(&patch))
            .await
        {
            Err(kube::Error::Api(s)) if s.code == 409 && attempt < TAINT_TRIES => {
                tokio::time::sleep(wait).await;
                wait *= 2;
            }
            other => return other.map(|_| ()),
        }
    }
    Ok(())
}
