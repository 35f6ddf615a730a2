//! Typed configuration of a local-kube server.

use std::path::PathBuf;
use std::time::Duration;

use crate::imagemap::ImageMap;

/// How container processes are isolated from each other and from the host.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Isolation {
    /// A private mount namespace when one can be made (root, or an unprivileged user
    /// namespace), else none.
    #[default]
    Auto,
    /// Always a private mount namespace; `start` fails when none can be made.
    MountNamespace,
    /// Plain processes: containers that mount volumes or image files cannot start.
    None,
}

/// Delays of the process runtime, short by default so whole submissions rehearse in seconds.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Timing {
    /// First delay before restarting a failed container (doubles per restart).
    pub restart_backoff: Duration,
    /// Longest restart (and pod replacement) delay.
    pub max_backoff: Duration,
    /// First delay before the controller replaces a failed pod (`restartPolicy: Never`).
    pub pod_backoff: Duration,
    /// How long an unpullable image shows `ErrImagePull` before `ImagePullBackOff` (and back).
    pub image_pull_backoff: Duration,
    /// Cap on `terminationGracePeriodSeconds` between SIGTERM and SIGKILL. Long enough for
    /// what a pod does on SIGTERM (logcopy's final upload) on a loaded machine, as a kubelet
    /// gives it the whole grace; a process that ignores SIGTERM waits this long.
    pub max_grace_period: Duration,
}

impl Default for Timing {
    fn default() -> Self {
        Self {
            restart_backoff: Duration::from_millis(200),
            max_backoff: Duration::from_secs(2),
            pod_backoff: Duration::from_millis(200),
            image_pull_backoff: Duration::from_secs(1),
            max_grace_period: Duration::from_secs(30),
        }
    }
}

/// Server configuration.
#[derive(Clone, Debug, Default)]
pub struct Config {
    /// Image -> local command map.
    pub images: ImageMap,
    /// Where pod directories (volumes, logs) go; a fresh temporary directory when unset.
    pub state_dir: Option<PathBuf>,
    /// Bearer token every request must carry, when set.
    pub token: Option<String>,
    /// Namespaces the (single) user may not touch: 403 Forbidden.
    pub forbidden_namespaces: Vec<String>,
    /// Container isolation.
    pub isolation: Isolation,
    /// Runtime delays.
    pub timing: Timing,
    /// The node's `nvidia.com/gpu` capacity: pods wait `Pending` (`Unschedulable`) until
    /// their GPU request fits. `None`: GPUs are not modelled and every pod fits.
    pub gpus: Option<u32>,
    /// The node's `node.kubernetes.io/instance-type` label. When set, the scheduler honours
    /// a pod's `nodeSelector` against the node's labels (a pod asking for another instance
    /// type waits `Unschedulable`); `None`: node selectors are not modelled.
    pub instance_type: Option<String>,
    /// The node's further labels, as its node group sets them (a GPU model, EKS's
    /// `eks.amazonaws.com/capacityType`). Any label set here also makes the scheduler honour
    /// `nodeSelector`.
    pub labels: std::collections::BTreeMap<String, String>,
    /// Record the Cluster Autoscaler's events on pods that wait, as for a cluster whose only
    /// node group is this node at its maximum size: `NotTriggerScaleUp` with
    /// `max node group size reached` for a pod a free node would hold, and the rejection
    /// (`Insufficient nvidia.com/gpu`, `node(s) didn't match Pod's node affinity/selector`)
    /// for one no node of the group ever could.
    pub autoscaler: bool,
}

/// What the scheduler (and the autoscaler) know of the one node.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Node {
    /// `Config::gpus`.
    pub gpus: Option<u32>,
    /// `Config::instance_type`.
    pub instance_type: Option<String>,
    /// `Config::labels`.
    pub labels: std::collections::BTreeMap<String, String>,
    /// `Config::autoscaler`.
    pub autoscaler: bool,
}

impl Config {
    /// The node this configuration describes.
    pub fn node(&self) -> Node {
        Node {
            gpus: self.gpus,
            instance_type: self.instance_type.clone(),
            labels: self.labels.clone(),
            autoscaler: self.autoscaler,
        }
    }
}
