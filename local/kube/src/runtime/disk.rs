//! What a pod holds on its node's disk, counted as the kubelet's stats summary counts it for
//! eviction: each container's writable layer and logs, and the pod's disk-backed `emptyDir`
//! volumes.
//!
//! Sizes are apparent (a file's length, not its blocks), so a rehearsal can fill a node's disk
//! with sparse files that take none of the machine's; the kubelet counts blocks.

use std::path::Path;

use k8s_openapi::api::core::v1::Pod;

/// Entries a walk reads at most: a pod that made more files than this is counted as far as
/// the walk got (already far past any request), and a look stays bounded.
const MOST_ENTRIES: usize = 200_000;

/// Where a container's writable layer is mounted in its view: what it writes outside its
/// volumes, as a container runtime's overlay would hold it.
pub const LAYER_MOUNT: &str = "/var/tmp";

/// One pod's use of the node's disk, in bytes.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct PodDisk {
    /// Each container's writable layer and logs (the kubelet's `rootfs` plus `logs`), by name.
    pub containers: Vec<(String, u64)>,
    /// Its disk-backed `emptyDir` volumes together (memory-backed ones count as memory).
    pub volumes: u64,
}

impl PodDisk {
    /// All of it: what the kubelet ranks a pod by.
    pub fn total(&self) -> u64 {
        self.containers.iter().map(|(_, b)| b).sum::<u64>() + self.volumes
    }
}

/// `pod`'s use, its directory being `dir` (layers under `layers/<container>`, logs under
/// `logs/<container>`, volumes under `volumes/<name>`).
pub fn usage(pod: &Pod, dir: &Path) -> PodDisk {
    let Some(spec) = pod.spec.as_ref() else {
        return PodDisk::default();
    };
    let containers = spec
        .containers
        .iter()
        .map(|c| {
            let bytes = apparent(&dir.join("layers").join(&c.name))
                + apparent(&dir.join("logs").join(&c.name));
            (c.name.clone(), bytes)
        })
        .collect();
    let volumes = spec
        .volumes
        .iter()
        .flatten()
        .filter(|v| {
            v.empty_dir
                .as_ref()
                .is_some_and(|e| e.medium.as_deref() != Some("Memory"))
        })
        .map(|v| apparent(&dir.join("volumes").join(&v.name)))
        .sum();
    PodDisk {
        containers,
        volumes,
    }
}

/// The apparent size of the files under `root`, symbolic links not followed, at most
/// [`MOST_ENTRIES`] entries read; 0 when it does not exist.
fn apparent(root: &Path) -> u64 {
    let mut total = 0u64;
    let mut seen = 0usize;
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&dir) else {
            continue;
        };
        for entry in entries.flatten() {
            seen += 1;
            if seen > MOST_ENTRIES {
                return total;
            }
            let Ok(meta) = entry.metadata() else { continue };
            if meta.is_dir() {
                stack.push(entry.path());
            } else if meta.is_file() {
                total = total.saturating_add(meta.len());
            }
        }
    }
    total
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layers_logs_and_disk_volumes_count_and_memory_volumes_do_not() {
        let dir = tempfile::tempdir().unwrap();
        let pod: Pod = serde_json::from_value(serde_json::json!({
            "metadata": {"name": "p"},
            "spec": {
                "containers": [{"name": "agent"}, {"name": "quiet"}],
                "volumes": [{"name": "logs", "emptyDir": {}},
                            {"name": "shm", "emptyDir": {"medium": "Memory"}}],
            },
        }))
        .unwrap();
        let write = |rel: &str, len: u64| {
            let path = dir.path().join(rel);
            std::fs::create_dir_all(path.parent().unwrap()).unwrap();
            std::fs::File::create(&path).unwrap().set_len(len).unwrap();
        };
        write("layers/agent/deep/fill.bin", 12 << 30);
        write("logs/agent/0.log", 100);
        write("volumes/logs/x", 7);
        write("volumes/shm/y", 1 << 20);
        let disk = usage(&pod, dir.path());
        assert_eq!(
            disk.containers,
            [
                ("agent".to_owned(), (12 << 30) + 100),
                ("quiet".to_owned(), 0)
            ]
        );
        assert_eq!(disk.volumes, 7);
        assert_eq!(disk.total(), (12 << 30) + 107);
    }
}
