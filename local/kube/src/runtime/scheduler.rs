//! The scheduler of the one node: pods are bound in creation order while the node's
//! `nvidia.com/gpu` has room; the others stay `Pending` with the real scheduler's
//! `PodScheduled=False`, reason `Unschedulable` condition and message until room frees. A
//! bound pod gets particular GPUs, as the NVIDIA device plugin allocates them: the kubelet
//! gives each container that requested GPUs their UUIDs in `NVIDIA_VISIBLE_DEVICES`.

use std::collections::{BTreeMap, HashMap};

use k8s_openapi::api::core::v1::{Pod, PodCondition, PodSpec};
use k8s_openapi::apimachinery::pkg::api::resource::Quantity;

use crate::config::Node;
use crate::store::time_now;

/// The extended resource the NVIDIA device plugin advertises.
pub const GPU: &str = "nvidia.com/gpu";

/// What the real scheduler writes on a pod no node has GPUs for (kube-scheduler's
/// `NodeResourcesFit` plugin, one node; then the dynamic resource allocation's word, no claim
/// to free, and the preemption it tries: none helps, no lower-priority pod holding one), as
/// `tests/e2e/tests/real_kube.rs` checks against the real one of the pinned release.
pub const INSUFFICIENT_GPU: &str = "0/1 nodes are available: 1 Insufficient nvidia.com/gpu. no new claims to deallocate, preemption: 0/1 nodes are available: 1 Preemption is not helpful for scheduling.";

/// What the real scheduler writes on a pod whose `nodeSelector` the node's labels do not
/// satisfy (kube-scheduler's `NodeAffinity` filter, one node; preemption cannot help).
pub const SELECTOR_MISMATCH: &str = "0/1 nodes are available: 1 node(s) didn't match Pod's node affinity/selector. no new claims to deallocate, preemption: 0/1 nodes are available: 1 Preemption is not helpful for scheduling.";

/// The component the Cluster Autoscaler's events name.
pub const AUTOSCALER: &str = "cluster-autoscaler";
/// The autoscaler's event reason for a pod it did not add a node for.
pub const NOT_TRIGGERED: &str = "NotTriggerScaleUp";

/// The well-known label of a node's instance type.
pub const INSTANCE_TYPE_LABEL: &str = "node.kubernetes.io/instance-type";

/// GPUs a node lists when GPUs are not modelled (every pod fits; beyond this many in use at
/// once, devices are shared).
pub const UNMODELLED_GPUS: u32 = 64;

/// GPUs in use: the device indexes of each pod, by pod uid.
#[derive(Debug, Default)]
pub struct Allocations {
    used: HashMap<String, Vec<u32>>,
}

impl Allocations {
    /// GPUs bound to pods now.
    pub fn in_use(&self) -> u32 {
        self.used.values().map(|d| d.len() as u32).sum()
    }

    /// Binds `gpus` free devices (the lowest indexes) of a node of `capacity` to pod `uid`.
    pub fn bind(&mut self, uid: &str, gpus: u32, capacity: Option<u32>) -> Vec<u32> {
        let total = capacity.unwrap_or(UNMODELLED_GPUS);
        let taken: std::collections::BTreeSet<u32> =
            self.used.values().flatten().copied().collect();
        let mut devices: Vec<u32> = (0..total)
            .filter(|i| !taken.contains(i))
            .take(gpus as usize)
            .collect();
        // NB: only when GPUs are not modelled can more be asked than are free: share.
        let mut next = 0;
        while devices.len() < gpus as usize {
            devices.push(next % total.max(1));
            next += 1;
        }
        self.used.insert(uid.to_owned(), devices.clone());
        devices
    }

    /// The devices of pod `uid`.
    pub fn devices(&self, uid: &str) -> Vec<u32> {
        self.used.get(uid).cloned().unwrap_or_default()
    }

    /// Frees pod `uid`'s GPUs (idempotent).
    pub fn release(&mut self, uid: &str) {
        self.used.remove(uid);
    }
}

/// The UUID of GPU `index` of this node, in the form the device plugin hands out.
pub fn gpu_uuid(index: u32) -> String {
    format!("GPU-6c6f6361-6c6b-4b75-8265-{index:012x}")
}

/// A container's own `nvidia.com/gpu` request (an extended resource's request defaults to
/// its limit).
pub fn container_gpus(c: &k8s_openapi::api::core::v1::Container) -> u32 {
    let r = c.resources.as_ref();
    let request = r.and_then(|r| r.requests.as_ref()).and_then(|m| m.get(GPU));
    let limit = r.and_then(|r| r.limits.as_ref()).and_then(|m| m.get(GPU));
    gpus_of(request.or(limit))
}

/// The `nvidia-smi` this node's containers see (what the NVIDIA container toolkit mounts
/// into a container with `NVIDIA_VISIBLE_DEVICES` set): it answers
/// `--query-gpu=index,uuid --format=csv[,noheader]` and `-L` for the GPUs that variable makes
/// visible (`all`, or a comma-separated list of UUIDs).
pub fn nvidia_smi_script(gpus: u32) -> String {
    let rows: String = (0..gpus)
        .map(|i| format!("{i}, {}\n", gpu_uuid(i)))
        .collect();
    format!(
        r#"#!/bin/sh
# local-kube's nvidia-smi: the node's {gpus} GPU(s), as the device plugin names them.
header=1; list=0
for arg in "$@"; do
  case "$arg" in
    --query-gpu=index,uuid) ;;
    --format=csv) ;;
    --format=csv,noheader) header=0 ;;
    -L|--list-gpus) list=1 ;;
    *) echo "nvidia-smi (local-kube): unsupported argument $arg" >&2; exit 2 ;;
  esac
done
visible="${{NVIDIA_VISIBLE_DEVICES:-}}"
if [ -z "$visible" ] || [ "$visible" = void ] || [ "$visible" = none ]; then
  echo "No devices were found" >&2; exit 6
fi
[ $list = 0 ] && [ $header = 1 ] && echo "index, uuid"
printf '{rows}' | while IFS=', ' read -r index uuid; do
  case ",$visible," in
    *,all,*|*,"$uuid",*) ;;
    *) continue ;;
  esac
  if [ $list = 1 ]; then echo "GPU $index: local-kube GPU (UUID: $uuid)"; else echo "$index, $uuid"; fi
done
"#
    )
}

fn gpus_of(q: Option<&Quantity>) -> u32 {
    q.and_then(|q| q.0.trim().parse::<u32>().ok()).unwrap_or(0)
}

/// The pod's `nvidia.com/gpu` request, as the scheduler counts it: the larger of the sum
/// over the app containers and the largest init container (an extended resource's request
/// defaults to its limit and must equal it).
pub fn gpu_request(spec: &PodSpec) -> u32 {
    let apps: u32 = spec.containers.iter().map(container_gpus).sum();
    let inits = spec
        .init_containers
        .iter()
        .flatten()
        .map(container_gpus)
        .max()
        .unwrap_or(0);
    apps.max(inits)
}

/// Whether a pod needing `need` GPUs fits a node of `capacity` (`None`: GPUs not modelled,
/// everything fits) with `in_use` bound.
pub fn fits(capacity: Option<u32>, in_use: u32, need: u32) -> bool {
    match capacity {
        None => true,
        Some(total) => in_use.saturating_add(need) <= total,
    }
}

/// Marks `pod` scheduled on `node`.
pub fn bind(pod: &mut Pod, node: &str) {
    pod.spec.get_or_insert_with(Default::default).node_name = Some(node.to_owned());
    set_scheduled(pod, None);
}

/// Marks `pod` unschedulable with the scheduler's `message` (keeping the transition time
/// while it stays so).
pub fn mark_unschedulable(pod: &mut Pod, message: &str) {
    set_scheduled(pod, Some(message));
}

/// The labels of node `name`: the well-known ones a kubelet sets, the instance type and the
/// node group's.
pub fn node_labels(name: &str, node: &Node) -> BTreeMap<String, String> {
    let mut labels = BTreeMap::from([
        ("kubernetes.io/hostname".to_owned(), name.to_owned()),
        ("kubernetes.io/os".to_owned(), "linux".to_owned()),
        ("kubernetes.io/arch".to_owned(), "amd64".to_owned()),
    ]);
    if let Some(t) = &node.instance_type {
        labels.insert(INSTANCE_TYPE_LABEL.to_owned(), t.clone());
    }
    labels.extend(node.labels.clone());
    labels
}

/// Whether the node's labels are modelled, so that `nodeSelector` is honoured.
pub fn labels_modelled(node: &Node) -> bool {
    node.instance_type.is_some() || !node.labels.is_empty()
}

/// Whether a node with `labels` satisfies the pod's `nodeSelector` (every pair present).
pub fn selects(spec: &PodSpec, labels: &BTreeMap<String, String>) -> bool {
    spec.node_selector
        .iter()
        .flatten()
        .all(|(k, v)| labels.get(k) == Some(v))
}

/// What the Cluster Autoscaler says of a pod that waits, when the cluster's one node group is
/// this node at its maximum size (kubernetes/autoscaler `eventing_scale_up_processor.go`:
/// `pod didn't trigger scale-up: ` and one counted reason per node group): *skipped* when a
/// new node of the group would hold the pod, *rejected* with the scheduler filter's reason
/// (the first that fails, as the framework stops there) when none would.
pub fn autoscaler_word(selected: bool, need: u32, capacity: Option<u32>) -> String {
    let reason = if !selected {
        "node(s) didn't match Pod's node affinity/selector"
    } else if capacity.is_some_and(|total| need > total) {
        "Insufficient nvidia.com/gpu"
    } else {
        "max node group size reached"
    };
    format!("pod didn't trigger scale-up: 1 {reason}")
}

fn set_scheduled(pod: &mut Pod, unschedulable: Option<&str>) {
    let status = pod.status.get_or_insert_with(Default::default);
    let conditions = status.conditions.get_or_insert_with(Vec::new);
    let value = if unschedulable.is_some() {
        "False"
    } else {
        "True"
    };
    if let Some(c) = conditions.iter().find(|c| c.type_ == "PodScheduled") {
        if c.status == value && c.message.as_deref() == unschedulable {
            return;
        }
    }
    conditions.retain(|c| c.type_ != "PodScheduled");
    conditions.push(PodCondition {
        type_: "PodScheduled".into(),
        status: value.into(),
        reason: unschedulable.map(|_| "Unschedulable".into()),
        message: unschedulable.map(Into::into),
        last_transition_time: Some(time_now()),
        ..Default::default()
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(yaml: &str) -> PodSpec {
        serde_yaml::from_str(yaml).unwrap()
    }

    #[test]
    fn the_request_sums_app_containers_and_takes_the_largest_init_container() {
        let s = spec(
            r#"{"containers": [
                 {"name": "a", "resources": {"limits": {"nvidia.com/gpu": 1}}},
                 {"name": "b", "resources": {"requests": {"nvidia.com/gpu": "2"},
                                             "limits": {"nvidia.com/gpu": "2"}}},
                 {"name": "c"}],
               "initContainers": [{"name": "i", "resources": {"limits": {"nvidia.com/gpu": 1}}}]}"#,
        );
        assert_eq!(gpu_request(&s), 3);
        let s = spec(
            r#"{"containers": [{"name": "a"}],
               "initContainers": [{"name": "i", "resources": {"limits": {"nvidia.com/gpu": 4}}}]}"#,
        );
        assert_eq!(gpu_request(&s), 4);
        assert_eq!(gpu_request(&spec("containers: [{name: a}]")), 0);
    }

    #[test]
    fn a_pod_fits_while_the_node_has_room() {
        assert!(fits(Some(4), 2, 2));
        assert!(!fits(Some(4), 3, 2));
        assert!(!fits(Some(1), 0, 2));
        assert!(fits(None, 100, 8));
        let mut a = Allocations::default();
        assert_eq!(a.bind("x", 2, Some(4)), [0, 1]);
        assert_eq!(a.bind("y", 1, Some(4)), [2]);
        a.release("x");
        a.release("x");
        assert_eq!(a.in_use(), 1);
        // Freed devices are handed out again, lowest first; no two pods share one.
        assert_eq!(a.bind("z", 2, Some(4)), [0, 1]);
        assert_eq!(a.devices("y"), [2]);
        assert_eq!(a.devices("gone"), Vec::<u32>::new());
    }

    #[test]
    fn node_selectors_and_the_autoscalers_word_follow_the_node() {
        let node = Node {
            gpus: Some(4),
            instance_type: Some("g5.12xlarge".into()),
            labels: Default::default(),
            autoscaler: true,
        };
        let labels = node_labels("local-kube", &node);
        let asks = |t: &str| {
            spec(&format!(
                r#"{{"containers": [{{"name": "a"}}], "nodeSelector": {{"{INSTANCE_TYPE_LABEL}": "{t}"}}}}"#
            ))
        };
        assert!(selects(&asks("g5.12xlarge"), &labels));
        assert!(!selects(&asks("g6.xlarge"), &labels));
        assert!(selects(&spec("containers: [{name: a}]"), &labels));
        assert_eq!(
            autoscaler_word(true, 1, Some(4)),
            "pod didn't trigger scale-up: 1 max node group size reached"
        );
        assert_eq!(
            autoscaler_word(true, 5, Some(4)),
            "pod didn't trigger scale-up: 1 Insufficient nvidia.com/gpu"
        );
        assert_eq!(
            autoscaler_word(false, 1, Some(4)),
            "pod didn't trigger scale-up: 1 node(s) didn't match Pod's node affinity/selector"
        );
    }

    #[test]
    fn the_conditions_are_the_real_schedulers() {
        let mut pod = Pod::default();
        mark_unschedulable(&mut pod, INSUFFICIENT_GPU);
        let c = &pod.status.as_ref().unwrap().conditions.as_ref().unwrap()[0];
        assert_eq!(
            (c.type_.as_str(), c.status.as_str(), c.reason.as_deref()),
            ("PodScheduled", "False", Some("Unschedulable"))
        );
        assert_eq!(c.message.as_deref(), Some(INSUFFICIENT_GPU));
        bind(&mut pod, "local-kube");
        assert_eq!(
            pod.spec.as_ref().unwrap().node_name.as_deref(),
            Some("local-kube")
        );
        let c = &pod.status.as_ref().unwrap().conditions.as_ref().unwrap()[0];
        assert_eq!((c.status.as_str(), c.reason.as_deref()), ("True", None));
    }
}
