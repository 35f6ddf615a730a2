//! The cluster as the pipeline sees it: Jobs, pods and nodes as views, whose a disruption is,
//! what the autoscaler's word means, and what each container may use.

pub mod autoscaler;
pub mod disruption;
pub mod resources;
pub mod view;
