//! The deployment's templates read as data: `infra/app.yaml` and `infra/cluster.yaml`
//! evaluated, and the Pipe's input transformation that `lbctl submit` and local mode apply.

pub mod pipe;
pub mod template;

pub use template::{Statement, Template, TemplateError};
