//! What a submission's evaluation cost: GPU-seconds from its pods' lifetimes, on Spot or
//! on-demand capacity, the part spent again on routes a reclaim interrupted, and an estimate
//! in dollars from the settings' price table.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// The capacity a pod's node was, from its `eks.amazonaws.com/capacityType` label.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum NodeCapacity {
    /// `SPOT`.
    Spot,
    /// `ON_DEMAND`.
    OnDemand,
    /// No label (a node outside a managed node group): priced as on-demand.
    Unknown,
}

impl NodeCapacity {
    /// From the node label's value.
    pub fn from_label(value: Option<&str>) -> NodeCapacity {
        match value {
            Some("SPOT") => NodeCapacity::Spot,
            Some("ON_DEMAND") => NodeCapacity::OnDemand,
            _ => NodeCapacity::Unknown,
        }
    }
}

/// One pod of a submission as the Monitor saw it, in epoch seconds.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct PodSpan {
    /// When it started running (the kubelet's `startTime`).
    pub started_at: u64,
    /// When it ended (its containers' last `finishedAt`), or when it was last seen running.
    pub ended_at: u64,
    /// GPUs it held.
    pub gpus: u32,
    /// Its node's instance type.
    pub instance_type: String,
    /// Its node's capacity type.
    pub capacity: NodeCapacity,
    /// Seconds it ran after its pairs' last finished route, when the control plane took it
    /// away (`DisruptionTarget`): that work is done again by the next pod.
    pub lost_seconds: Option<u64>,
}

impl PodSpan {
    /// Seconds it ran.
    pub fn seconds(&self) -> u64 {
        self.ended_at.saturating_sub(self.started_at)
    }
}

/// GPU-seconds of one instance type and capacity.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct GpuSeconds {
    /// Every second a GPU was held.
    pub held: u64,
    /// The part spent on routes a reclaim interrupted (run again by the next pod).
    pub run_again: u64,
}

/// What a submission's pods used, by instance type and capacity.
pub type Usage = BTreeMap<(String, NodeCapacity), GpuSeconds>;

/// Adds the pods' GPU-seconds up.
pub fn usage(pods: &[PodSpan]) -> Usage {
    let mut usage = Usage::new();
    for pod in pods {
        let gpus = u64::from(pod.gpus);
        let entry = usage
            .entry((pod.instance_type.clone(), pod.capacity))
            .or_default();
        entry.held += pod.seconds() * gpus;
        entry.run_again += pod.lost_seconds.unwrap_or(0).min(pod.seconds()) * gpus;
    }
    usage
}

/// Dollars per hour of one instance type (the settings' `prices`).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InstancePrice {
    /// On-demand, dollars per instance-hour.
    pub on_demand: f64,
    /// Spot, dollars per instance-hour (a recent average: Spot prices move).
    pub spot: f64,
}

/// An estimate in dollars, and the GPU-seconds no price was known for.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    /// Dollars.
    pub dollars: f64,
    /// GPU-seconds of instance types the table does not price.
    pub unpriced_gpu_seconds: u64,
}

/// Prices the usage: each GPU-second at its instance type's hourly price over its GPUs.
pub fn estimate(usage: &Usage, prices: &BTreeMap<String, InstancePrice>) -> Estimate {
    let mut out = Estimate::default();
    for ((instance_type, capacity), seconds) in usage {
        let gpus = crate::resources::capacity(instance_type).map(|c| c.gpus);
        match (prices.get(instance_type), gpus) {
            (Some(price), Some(gpus)) if gpus > 0 => {
                let hourly = match capacity {
                    NodeCapacity::Spot => price.spot,
                    NodeCapacity::OnDemand | NodeCapacity::Unknown => price.on_demand,
                };
                out.dollars += hourly / f64::from(gpus) * seconds.held as f64 / 3600.0;
            }
            _ => out.unpriced_gpu_seconds += seconds.held,
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pod(start: u64, end: u64, capacity: NodeCapacity, lost: Option<u64>) -> PodSpan {
        PodSpan {
            started_at: start,
            ended_at: end,
            gpus: 1,
            instance_type: "g5.12xlarge".into(),
            capacity,
            lost_seconds: lost,
        }
    }

    #[test]
    fn gpu_seconds_add_up_by_capacity_and_a_reclaim_counts_what_runs_again() {
        let pods = [
            pod(0, 3600, NodeCapacity::Spot, Some(600)),
            pod(3700, 7300, NodeCapacity::Spot, None),
            pod(0, 7200, NodeCapacity::OnDemand, None),
            pod(100, 50, NodeCapacity::OnDemand, Some(10)),
        ];
        let usage = usage(&pods);
        let spot = usage[&("g5.12xlarge".to_string(), NodeCapacity::Spot)];
        assert_eq!(
            spot,
            GpuSeconds {
                held: 7200,
                run_again: 600
            }
        );
        let on_demand = usage[&("g5.12xlarge".to_string(), NodeCapacity::OnDemand)];
        assert_eq!(
            on_demand,
            GpuSeconds {
                held: 7200,
                run_again: 0
            },
            "a clock gone back counts 0"
        );

        let prices = BTreeMap::from([(
            "g5.12xlarge".to_string(),
            InstancePrice {
                on_demand: 5.672,
                spot: 2.0,
            },
        )]);
        let e = estimate(&usage, &prices);
        // Two GPU-hours at a quarter of each hourly price.
        assert!(
            (e.dollars - (2.0 * 2.0 / 4.0 + 2.0 * 5.672 / 4.0)).abs() < 1e-9,
            "{e:?}"
        );
        assert_eq!(e.unpriced_gpu_seconds, 0);
        let unpriced = estimate(&usage, &BTreeMap::new());
        assert_eq!(unpriced.unpriced_gpu_seconds, 14_400);
    }

    #[test]
    fn the_capacity_comes_from_the_node_label() {
        assert_eq!(NodeCapacity::from_label(Some("SPOT")), NodeCapacity::Spot);
        assert_eq!(
            NodeCapacity::from_label(Some("ON_DEMAND")),
            NodeCapacity::OnDemand
        );
        assert_eq!(NodeCapacity::from_label(None), NodeCapacity::Unknown);
    }
}
