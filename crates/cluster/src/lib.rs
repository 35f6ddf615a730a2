//! Kubernetes adapter of the submission pipeline: creates (or adopts) a submission's Jobs,
//! observes them as a verdict the Monitor acts on, and deletes them.
//!
//! The client side lives in [`Cluster`]; the mapping from API objects to a [`Verdict`] is pure
//! and lives in [`observe`](mod@observe), so it is tested without a server.

pub mod autoscaler;
mod cluster;
mod error;
pub mod fleet;
pub mod labels;
pub mod observe;

pub use cluster::{eks_config, Cluster, Deleted, Launched, Timeouts};
pub use error::{ClusterError, Result};
pub use labels::Whose;
pub use observe::{
    ContainerState, ContainerView, Exit, FailureKind, JobState, JobView, Observation, PodView,
    Unschedulable, Verdict, VerdictPolicy,
};

/// The API object types this crate takes and returns, so callers need not pin k8s-openapi.
pub use k8s_openapi::api::batch::v1::Job;
pub use k8s_openapi::api::core::v1::Pod;
