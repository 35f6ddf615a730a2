//! The kubelet's eviction manager for node disk pressure: when what is left of a node's disk
//! falls below the hard threshold (`nodefs.available<10%`, the kubelet's default), it evicts
//! one pod per pass, pods above their `ephemeral-storage` request first, then the largest
//! user, and words the eviction as `pkg/kubelet/eviction/helpers.go` does: the node was low on
//! the resource, and each container that used more than it requested, by name.

use k8s_openapi::api::core::v1::{Container, Pod};

/// What the kubelet calls the starved resource.
const RESOURCE: &str = "ephemeral-storage";

/// A node's disk, as its kubelet sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Disk {
    /// Its `ephemeral-storage` capacity, in bytes.
    pub capacity: u64,
    /// What is on it besides the pods (images, the system), in bytes.
    pub images: u64,
}

impl Default for Disk {
    /// As roomy as no pair fills: 1 TiB, empty.
    fn default() -> Self {
        Disk {
            capacity: 1 << 40,
            images: 0,
        }
    }
}

impl Disk {
    /// The hard eviction threshold: a tenth of the capacity.
    pub fn threshold(&self) -> u64 {
        self.capacity / 10
    }

    /// What the scheduler may place: the capacity less the threshold (no reserves modelled),
    /// so pods within their requests never bring the node below it by themselves.
    pub fn allocatable(&self) -> u64 {
        self.capacity - self.threshold()
    }
}

/// One container of a running pod: its use of the node's disk and its request, in bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ContainerUse {
    /// Its name.
    pub name: String,
    /// Its writable layer and logs.
    pub used: u64,
    /// Its `ephemeral-storage` request as the spec writes it (`None`: no request).
    pub request: Option<String>,
}

/// One running pod on the node.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PodUse {
    /// Its containers.
    pub containers: Vec<ContainerUse>,
    /// Its disk-backed volumes together.
    pub volumes: u64,
}

impl PodUse {
    /// What `pod`'s containers request, with what they and its volumes use (`used` by
    /// container name, as [`local_kube::PodDisk`] counts it).
    pub fn of(pod: &Pod, disk: &local_kube::PodDisk) -> PodUse {
        let used = |name: &str| {
            disk.containers
                .iter()
                .find(|(n, _)| n == name)
                .map_or(0, |(_, b)| *b)
        };
        let containers = pod
            .spec
            .iter()
            .flat_map(|s| &s.containers)
            .map(|c| ContainerUse {
                name: c.name.clone(),
                used: used(&c.name),
                request: request(c),
            })
            .collect();
        PodUse {
            containers,
            volumes: disk.volumes,
        }
    }

    fn used(&self) -> u64 {
        self.containers.iter().map(|c| c.used).sum::<u64>() + self.volumes
    }

    fn requested(&self) -> u64 {
        self.containers
            .iter()
            .filter_map(|c| c.request.as_deref().and_then(bytes))
            .sum()
    }
}

fn request(c: &Container) -> Option<String> {
    let requests = c.resources.as_ref()?.requests.as_ref()?;
    requests.get(RESOURCE).map(|q| q.0.clone())
}

/// The kubelet's choice: the pod to evict and the eviction's message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Eviction {
    /// The pod's place among the pods it was chosen from.
    pub pod: usize,
    /// The `DisruptionTarget` condition's message and the pod's status message.
    pub message: String,
}

/// Whether `pods` (every running pod of the node) bring `disk` below its threshold, and if so
/// which pod goes: those above their request before the others, then the largest user.
pub fn choose(disk: &Disk, pods: &[PodUse]) -> Option<Eviction> {
    let used = disk
        .images
        .saturating_add(pods.iter().map(PodUse::used).sum());
    let available = disk.capacity.saturating_sub(used);
    if available >= disk.threshold() {
        return None;
    }
    let (index, pod) = pods
        .iter()
        .enumerate()
        .max_by_key(|(_, p)| (p.used() > p.requested(), p.used()))?;
    let mut message = format!(
        "The node was low on resource: {RESOURCE}. Threshold quantity: {}, available: {}. ",
        quantity(disk.threshold()),
        quantity(available)
    );
    for c in &pod.containers {
        let request = c.request.as_deref().unwrap_or("0");
        if c.used > bytes(request).unwrap_or(0) {
            message.push_str(&format!(
                "Container {} was using {}, request is {request}, has larger consumption of {RESOURCE}. ",
                c.name,
                quantity(c.used)
            ));
        }
    }
    Some(Eviction {
        pod: index,
        message,
    })
}

/// Binary suffixes, largest first.
const BINARY: [(&str, u64); 6] = [
    ("Ei", 1 << 60),
    ("Pi", 1 << 50),
    ("Ti", 1 << 40),
    ("Gi", 1 << 30),
    ("Mi", 1 << 20),
    ("Ki", 1 << 10),
];

/// Decimal suffixes.
const DECIMAL: [(&str, u64); 6] = [
    ("E", 1_000_000_000_000_000_000),
    ("P", 1_000_000_000_000_000),
    ("T", 1_000_000_000_000),
    ("G", 1_000_000_000),
    ("M", 1_000_000),
    ("k", 1_000),
];

/// Bytes as a binary `Quantity` prints them: the largest suffix that divides them exactly.
pub fn quantity(bytes: u64) -> String {
    BINARY
        .iter()
        .find(|(_, unit)| bytes > 0 && bytes % unit == 0)
        .map_or_else(
            || bytes.to_string(),
            |(suffix, unit)| format!("{}{suffix}", bytes / unit),
        )
}

/// A `Quantity` of bytes (`4Gi`, `500M`, `1.5Gi`, `1024`); `None` when it is not one.
pub fn bytes(quantity: &str) -> Option<u64> {
    let q = quantity.trim();
    let (number, unit) = BINARY
        .iter()
        .chain(DECIMAL.iter())
        .find_map(|(suffix, unit)| q.strip_suffix(suffix).map(|n| (n, *unit)))
        .unwrap_or((q, 1));
    let value: f64 = number.parse().ok().filter(|v: &f64| *v >= 0.0)?;
    Some((value * unit as f64).round() as u64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use lb_domain::cluster::disruption::{classify, Disruption, BY_KUBELET};

    const GI: u64 = 1 << 30;

    fn container(name: &str, used: u64, request: &str) -> ContainerUse {
        ContainerUse {
            name: name.into(),
            used,
            request: Some(request.into()),
        }
    }

    fn pod(containers: Vec<ContainerUse>, volumes: u64) -> PodUse {
        PodUse {
            containers,
            volumes,
        }
    }

    /// A node of 200 GiB whose images leave 25 GiB before the threshold.
    const NEARLY_FULL: Disk = Disk {
        capacity: 200 * GI,
        images: 155 * GI,
    };

    #[test]
    fn nothing_is_evicted_while_the_node_is_above_its_threshold() {
        let pods = [pod(vec![container("agent", 3 * GI, "4Gi")], GI)];
        assert_eq!(choose(&NEARLY_FULL, &pods), None);
        assert_eq!(choose(&Disk::default(), &pods), None);
    }

    #[test]
    fn a_pod_over_its_request_goes_first_and_its_container_is_named() {
        let hog = pod(
            vec![
                container("agent", 12 * GI, "4Gi"),
                container("simulator", 0, "1Gi"),
            ],
            0,
        );
        // The neighbour uses more in all, within its request.
        let big = pod(vec![container("logcopy", 14 * GI, "15Gi")], 0);
        let eviction = choose(&NEARLY_FULL, &[big, hog]).unwrap();
        assert_eq!(eviction.pod, 1, "the hog, not the larger neighbour");
        assert_eq!(
            eviction.message,
            "The node was low on resource: ephemeral-storage. Threshold quantity: 20Gi, \
             available: 19Gi. Container agent was using 12Gi, request is 4Gi, has larger \
             consumption of ephemeral-storage. "
        );
        // The Monitor reads it as the kubelet's, the pod's own doing on a node that stays.
        assert_eq!(
            classify(BY_KUBELET, Some(&eviction.message)),
            Disruption::ByKubelet
        );
    }

    #[test]
    fn a_node_filled_by_its_images_evicts_the_largest_user_and_names_no_container() {
        let disk = Disk {
            images: 181 * GI,
            ..NEARLY_FULL
        };
        let pods = [
            pod(vec![container("agent", GI, "4Gi")], 0),
            pod(vec![container("agent", 3 * GI, "4Gi")], GI),
        ];
        let eviction = choose(&disk, &pods).unwrap();
        assert_eq!(eviction.pod, 1, "the larger user");
        assert!(
            !eviction.message.contains("Container"),
            "{}",
            eviction.message
        );
        // Within its share: crowded out, free for it.
        assert_eq!(
            classify(BY_KUBELET, Some(&eviction.message)),
            Disruption::Reclaim
        );
    }

    #[test]
    fn quantities_read_and_print_as_kubernetes_writes_them() {
        assert_eq!(bytes("4Gi"), Some(4 * GI));
        assert_eq!(bytes("1.5Gi"), Some(3 * GI / 2));
        assert_eq!(bytes("500M"), Some(500_000_000));
        assert_eq!(bytes("1024"), Some(1024));
        assert_eq!(bytes("lots"), None);
        assert_eq!(quantity(12 * GI), "12Gi");
        assert_eq!(quantity(3 * GI / 2), "1536Mi");
        assert_eq!(quantity(1000), "1000");
    }
}
