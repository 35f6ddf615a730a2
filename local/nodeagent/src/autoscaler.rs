//! The Cluster Autoscaler's word on a pod no node holds, as its node groups would answer:
//! one group per distinct node the agent serves, each able to add a node like it. Not the
//! autoscaler (which the contract does not cover), only the event it writes.

use std::collections::{BTreeMap, HashSet};

use k8s_openapi::api::core::v1::{Event, Pod};
use kube::api::{Api, PostParams};
use serde_json::json;
use tracing::debug;

use crate::NodeSpec;

/// Writes `NotTriggerScaleUp` events, once per pod and message.
pub struct StandIn {
    client: kube::Client,
    groups: Vec<(BTreeMap<String, String>, u32)>,
    said: HashSet<(String, String)>,
}

impl StandIn {
    /// The stand-in of node groups that make nodes like `nodes`.
    pub fn new(client: kube::Client, nodes: &[NodeSpec]) -> StandIn {
        let mut groups: Vec<(BTreeMap<String, String>, u32)> = Vec::new();
        for n in nodes {
            let group = (n.labels.clone(), n.gpus);
            if !groups.contains(&group) {
                groups.push(group);
            }
        }
        StandIn {
            client,
            groups,
            said: HashSet::new(),
        }
    }

    /// Speaks of every pod the scheduler found unschedulable and no node holds.
    pub async fn speak(&mut self, unbound: &[Pod]) {
        for pod in unbound.iter().filter(|p| unschedulable(p)) {
            let Some(spec) = pod.spec.as_ref() else {
                continue;
            };
            let need = local_kube::gpu_request(spec);
            // The first group that could hold the pod decides; else the first rejection.
            let word = self
                .groups
                .iter()
                .map(|(labels, gpus)| {
                    local_kube::autoscaler_word(
                        local_kube::selects(spec, labels),
                        need,
                        Some(*gpus),
                    )
                })
                .min_by_key(|w| !w.contains("max node group size"))
                .unwrap_or_else(|| local_kube::autoscaler_word(false, need, None));
            let uid = pod.metadata.uid.clone().unwrap_or_default();
            if self.said.insert((uid, word.clone())) {
                self.record(pod, &word).await;
            }
        }
    }

    async fn record(&self, pod: &Pod, message: &str) {
        let ns = pod.metadata.namespace.clone().unwrap_or_default();
        let name = pod.metadata.name.clone().unwrap_or_default();
        let now = k8s_openapi::jiff::Timestamp::now();
        let event: Result<Event, _> = serde_json::from_value(json!({
            "metadata": {"name": format!("{name}.{:x}", now.as_nanosecond()), "namespace": ns},
            "involvedObject": {"kind": "Pod", "namespace": ns, "name": name,
                               "uid": pod.metadata.uid, "apiVersion": "v1"},
            "reason": local_kube::NOT_TRIGGERED, "message": message, "type": "Normal",
            "source": {"component": local_kube::AUTOSCALER},
            "count": 1, "firstTimestamp": now, "lastTimestamp": now,
        }));
        let Ok(event) = event else { return };
        let api: Api<Event> = Api::namespaced(self.client.clone(), &ns);
        if let Err(e) = api.create(&PostParams::default(), &event).await {
            debug!(pod = %name, error = %e, "autoscaler event not written");
        }
    }
}

fn unschedulable(pod: &Pod) -> bool {
    pod.metadata.deletion_timestamp.is_none()
        && pod
            .status
            .iter()
            .flat_map(|s| s.conditions.iter().flatten())
            .any(|c| c.type_ == "PodScheduled" && c.reason.as_deref() == Some("Unschedulable"))
}
