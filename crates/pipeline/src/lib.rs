//! What the pipeline's functions share: the payloads that travel through the state machine,
//! the error names it matches, and the configuration every function reads once.

pub mod cluster;
pub mod config;
pub mod error;
pub mod metrics;
pub mod payload;
pub mod queue;
pub mod results;
pub mod serve;

pub use config::FunctionConfig;
pub use error::{FnError, Result};
pub mod clients;
