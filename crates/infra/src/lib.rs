//! The deployment's templates read as data: `infra/app.yaml` and `infra/cluster.yaml`
//! evaluated, the Pipe's input transformation that `lbctl submit` and local mode apply, how
//! long EKS supports the clusters' Kubernetes minor, and what a versioned deploy ships and
//! rolls back to.

pub mod pipe;
pub mod release;
pub mod support;
pub mod template;

pub use template::{Statement, Template, TemplateError};
