//! What each container of a submission may use on a node: CPU and memory per simulator and
//! agent, the size of `/dev/shm`, derived from the instance type or set by the operator.
//!
//! Requests equal limits (Kubernetes' `Guaranteed` class): a participant's agent cannot take
//! a neighbour's CPU or memory, and its pods are the last the kubelet evicts.

use serde::{Deserialize, Serialize};

/// Capacity of one node of an instance type, as EC2 lists it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NodeCapacity {
    /// vCPUs.
    pub vcpus: u32,
    /// Memory, GiB.
    pub memory_gib: u32,
    /// NVIDIA GPUs.
    pub gpus: u32,
}

/// GPU instance types a leaderboard is likely to run on (EC2 instance type specifications,
/// accelerated computing): name, vCPUs, GiB, GPUs.
const KNOWN: [(&str, u32, u32, u32); 32] = [
    ("g4dn.xlarge", 4, 16, 1),
    ("g4dn.2xlarge", 8, 32, 1),
    ("g4dn.4xlarge", 16, 64, 1),
    ("g4dn.8xlarge", 32, 128, 1),
    ("g4dn.12xlarge", 48, 192, 4),
    ("g4dn.16xlarge", 64, 256, 1),
    ("g4dn.metal", 96, 384, 8),
    ("g5.xlarge", 4, 16, 1),
    ("g5.2xlarge", 8, 32, 1),
    ("g5.4xlarge", 16, 64, 1),
    ("g5.8xlarge", 32, 128, 1),
    ("g5.12xlarge", 48, 192, 4),
    ("g5.16xlarge", 64, 256, 1),
    ("g5.24xlarge", 96, 384, 4),
    ("g5.48xlarge", 192, 768, 8),
    ("g6.xlarge", 4, 16, 1),
    ("g6.2xlarge", 8, 32, 1),
    ("g6.4xlarge", 16, 64, 1),
    ("g6.8xlarge", 32, 128, 1),
    ("g6.12xlarge", 48, 192, 4),
    ("g6.16xlarge", 64, 256, 1),
    ("g6.24xlarge", 96, 384, 4),
    ("g6.48xlarge", 192, 768, 8),
    ("g6e.xlarge", 4, 32, 1),
    ("g6e.2xlarge", 8, 64, 1),
    ("g6e.4xlarge", 16, 128, 1),
    ("g6e.8xlarge", 32, 256, 1),
    ("g6e.12xlarge", 48, 384, 2),
    ("g6e.24xlarge", 96, 768, 4),
    ("g6e.48xlarge", 192, 1536, 8),
    ("p3.8xlarge", 32, 244, 4),
    ("p3.16xlarge", 64, 488, 8),
];

/// The capacity of a known instance type.
pub fn capacity(instance_type: &str) -> Option<NodeCapacity> {
    KNOWN
        .iter()
        .find(|(name, ..)| *name == instance_type)
        .map(|&(_, vcpus, memory_gib, gpus)| NodeCapacity {
            vcpus,
            memory_gib,
            gpus,
        })
}

/// The node label every GPU node carries with its GPU model (`infra/cluster.yaml` sets it on
/// the node groups): the Jobs select nodes by it, so a pair runs on any instance type of that
/// GPU model, on Spot or on-demand capacity alike.
pub const GPU_MODEL_LABEL: &str = "leaderboard.carla.org/gpu-model";

/// The GPU model of an instance family, as the node label names it (EC2 instance type
/// specifications, accelerated computing: G4dn NVIDIA T4, G5 A10G, G6 L4, G6e L40S, P3 V100).
pub fn gpu_model(instance_type: &str) -> Option<&'static str> {
    let family = instance_type.split('.').next()?;
    match family {
        "g4dn" => Some("nvidia-t4"),
        "g5" => Some("nvidia-a10g"),
        "g6" => Some("nvidia-l4"),
        "g6e" => Some("nvidia-l40s"),
        "p3" => Some("nvidia-v100"),
        _ => None,
    }
}

/// Local disk (`ephemeral-storage`) one container may fill besides its volumes: its writable
/// layer and its logs, GiB. The request is what it normally takes, so the scheduler keeps
/// that much room on the node; the limit is where the kubelet evicts the pod as a failure of
/// its own (no `DisruptionTarget`), so a pod that fills its space spends one of its retries
/// instead of pushing the node into disk pressure, whose evictions hit every team's pods on
/// it. A GPU node's disk (`GpuNodeDiskGiB`, 300 GiB) holds the images (tens of GiB each),
/// then a few pods at their limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Storage {
    /// What the scheduler reserves, GiB.
    pub request_gib: u32,
    /// What the kubelet allows, GiB.
    pub limit_gib: u32,
}

impl Storage {
    /// CARLA: its `Saved/` logs and shader cache.
    pub const SIMULATOR: Storage = Storage {
        request_gib: 1,
        limit_gib: 4,
    };
    /// The participant's agent: caches and temporary files in its image's file system.
    pub const AGENT: Storage = Storage {
        request_gib: 4,
        limit_gib: 16,
    };
    /// Init and logcopy: they write into the volumes, not their own layers (logcopy also
    /// requests the volumes' room: [`Storage::logcopy`]).
    pub const SIDECAR: Storage = Storage {
        request_gib: 1,
        limit_gib: 1,
    };
}

/// `sizeLimit`s of a pod's disk-backed volumes: every `emptyDir` is bounded, so no volume can
/// outgrow the pod's own share of the node's disk.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct VolumeSizes {
    /// `logs` per pair, GiB: results, the agent's logs and the CARLA recordings of its routes.
    pub logs_per_pair_gib: u32,
    /// `lb-bin` (the sidecar binary), MiB.
    pub bin_mib: u32,
    /// Each of `leaderboard`, `scenario-runner` and `carla-api` (the evaluation's code), MiB.
    pub sources_mib: u32,
}

impl VolumeSizes {
    /// The sizes every Job gets.
    pub const JOB: VolumeSizes = VolumeSizes {
        logs_per_pair_gib: 8,
        bin_mib: 256,
        sources_mib: 2048,
    };

    /// What the volumes of a Job of `pairs` may hold together, GiB, rounded up.
    pub fn total_gib(self, pairs: u32) -> u32 {
        let mib = self.bin_mib + 3 * self.sources_mib;
        self.logs_per_pair_gib * pairs + mib.div_ceil(1024)
    }
}

impl Storage {
    /// logcopy's share: its own, plus room for every disk-backed volume at its `sizeLimit`.
    /// The scheduler then keeps on the node all the disk the pod may fill without passing a
    /// limit, and a pod the kubelet evicts for disk pressure without naming one of its
    /// containers as over its request was within its share: a co-tenant's victim
    /// (`lb_domain::cluster::disruption::crowded_out`), not the cause.
    pub fn logcopy(volumes: VolumeSizes, pairs: u32) -> Storage {
        let room = volumes.total_gib(pairs);
        Storage {
            request_gib: Storage::SIDECAR.request_gib + room,
            limit_gib: Storage::SIDECAR.limit_gib + room,
        }
    }
}

/// CPU (millicores) and memory (MiB) of one container, requested and limited alike.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Allotment {
    /// Millicores.
    pub cpu_millis: u32,
    /// MiB.
    pub memory_mib: u32,
}

impl Allotment {
    /// What init and logcopy get: they copy files and upload them, in constant memory.
    pub const SIDECAR: Allotment = Allotment {
        cpu_millis: 500,
        memory_mib: 512,
    };
}

/// One container's share as the operator writes it (cores and GiB, fractions allowed).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ContainerShare {
    /// CPU cores.
    pub cpu: f64,
    /// Memory, GiB.
    pub memory_gib: f64,
}

/// What one simulator-agent pair gets (`pair_resources` in the settings).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct PairShare {
    /// The CARLA server.
    pub simulator: ContainerShare,
    /// The participant's agent.
    pub agent: ContainerShare,
    /// Memory-backed `/dev/shm` per pair, GiB. Its pages count against the memory of the
    /// container that writes them, so it is no extra memory, only a bound.
    pub shm_gib: f64,
}

/// A [`PairShare`] in the units Kubernetes is given.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct PairAllotment {
    /// The CARLA server.
    pub simulator: Allotment,
    /// The participant's agent.
    pub agent: Allotment,
    /// `/dev/shm` per pair, MiB.
    pub shm_mib: u32,
}

/// Part of a node kept for the kubelet, the system daemons and init/logcopy of each pod:
/// 10% of the CPUs plus one, 15% of the memory plus 2 GiB (EKS reserves about 6% of memory
/// and 0.1-0.4 vCPU for the kubelet alone; daemon sets take the rest).
fn usable(capacity: NodeCapacity) -> (f64, f64) {
    let cpu = f64::from(capacity.vcpus) * 0.9 - 1.0;
    let memory = f64::from(capacity.memory_gib) * 0.85 - 2.0;
    (cpu.max(0.0), memory.max(0.0))
}

impl PairShare {
    /// The default share of a node running `pairs` pairs: what is usable, split evenly, 40%
    /// to the simulator and 60% to the agent (the evaluator, the agent's model and its data
    /// loaders), `/dev/shm` a quarter of the agent's memory; rounded down to half cores and
    /// whole GiB.
    pub fn derive(capacity: NodeCapacity, pairs: u32) -> PairShare {
        let (cpu, memory) = usable(capacity);
        let pairs = f64::from(pairs.max(1));
        let (cpu, memory) = (cpu / pairs, memory / pairs);
        let half_cores = |x: f64| (x * 2.0).floor() / 2.0;
        let agent_memory = (memory * 0.6).floor();
        PairShare {
            simulator: ContainerShare {
                cpu: half_cores(cpu * 0.4),
                memory_gib: (memory * 0.4).floor(),
            },
            agent: ContainerShare {
                cpu: half_cores(cpu * 0.6),
                memory_gib: agent_memory,
            },
            shm_gib: (agent_memory / 4.0).floor(),
        }
    }

    /// Checks the share's ranges and, if the instance type is known, that `pairs` of them fit
    /// a node with what is kept for the system.
    pub fn check(&self, pairs: u32, capacity: Option<NodeCapacity>) -> Result<(), String> {
        for (name, share) in [("simulator", self.simulator), ("agent", self.agent)] {
            if !(share.cpu >= 0.1 && share.cpu <= 512.0) {
                return Err(format!("{name}.cpu must be between 0.1 and 512 cores"));
            }
            if !(share.memory_gib >= 0.5 && share.memory_gib <= 4096.0) {
                return Err(format!("{name}.memory_gib must be between 0.5 and 4096"));
            }
        }
        if !(self.shm_gib >= 0.0625 && self.shm_gib <= self.agent.memory_gib) {
            return Err("shm_gib must be between 1/16 and the agent's memory_gib".into());
        }
        if let Some(capacity) = capacity {
            let (cpu, memory) = usable(capacity);
            let pairs = f64::from(pairs);
            let need_cpu = (self.simulator.cpu + self.agent.cpu) * pairs;
            let need_memory = (self.simulator.memory_gib + self.agent.memory_gib) * pairs;
            if need_cpu > cpu || need_memory > memory {
                return Err(format!(
                    "{pairs} pairs need {need_cpu} cores and {need_memory} GiB; a node keeps \
                     {cpu:.1} cores and {memory:.1} GiB of its {} vCPUs and {} GiB after the \
                     system's part",
                    capacity.vcpus, capacity.memory_gib
                ));
            }
        }
        Ok(())
    }

    /// In Kubernetes' units.
    pub fn allotment(&self) -> PairAllotment {
        let allot = |s: ContainerShare| Allotment {
            cpu_millis: (s.cpu * 1000.0).round() as u32,
            memory_mib: (s.memory_gib * 1024.0).round() as u32,
        };
        PairAllotment {
            simulator: allot(self.simulator),
            agent: allot(self.agent),
            shm_mib: (self.shm_gib * 1024.0).round() as u32,
        }
    }
}

#[cfg(test)]
mod gpu_model_tests {
    use super::*;

    #[test]
    fn every_known_instance_type_has_a_gpu_model_by_its_family() {
        for (name, ..) in KNOWN {
            assert!(gpu_model(name).is_some(), "{name}");
        }
        assert_eq!(gpu_model("g5.48xlarge"), gpu_model("g5.12xlarge"));
        assert_ne!(gpu_model("g6.12xlarge"), gpu_model("g6e.12xlarge"));
        assert_eq!(gpu_model("m6i.large"), None);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_share_of_a_g5_12xlarge_fits_four_pairs() {
        let node = capacity("g5.12xlarge").unwrap();
        assert_eq!(node.gpus, 4);
        let share = PairShare::derive(node, 4);
        // 48 * 0.9 - 1 = 42.2 cores, 192 * 0.85 - 2 = 161.2 GiB; per pair 10.55 and 40.3.
        assert_eq!(share.simulator.cpu, 4.0);
        assert_eq!(share.agent.cpu, 6.0);
        assert_eq!(share.simulator.memory_gib, 16.0);
        assert_eq!(share.agent.memory_gib, 24.0);
        assert_eq!(share.shm_gib, 6.0);
        share.check(4, Some(node)).unwrap();
        assert_eq!(
            share.allotment().agent,
            Allotment {
                cpu_millis: 6000,
                memory_mib: 24576
            }
        );
    }

    #[test]
    fn every_known_type_derives_a_share_that_fits_it() {
        for (name, ..) in KNOWN {
            let node = capacity(name).unwrap();
            let share = PairShare::derive(node, node.gpus);
            share
                .check(node.gpus, Some(node))
                .unwrap_or_else(|e| panic!("{name}: {e}"));
        }
    }

    #[test]
    fn a_share_too_large_for_the_node_or_out_of_range_is_refused() {
        let node = capacity("g5.12xlarge").unwrap();
        let mut share = PairShare::derive(node, 4);
        share.agent.memory_gib = 40.0;
        let why = share.check(4, Some(node)).unwrap_err();
        assert!(why.contains("4 pairs need"), "{why}");
        // Unknown types are not checked against a capacity.
        share.check(4, None).unwrap();
        share.shm_gib = 41.0;
        assert!(share.check(4, None).unwrap_err().starts_with("shm_gib"));
        let mut share = PairShare::derive(node, 4);
        share.simulator.cpu = f64::NAN;
        assert!(share
            .check(4, None)
            .unwrap_err()
            .starts_with("simulator.cpu"));
    }
}
