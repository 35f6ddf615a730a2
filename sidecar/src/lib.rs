//! `lb-sidecar`: the one self-contained binary that runs inside every evaluation Job.
//!
//! One module per subcommand (`init`, `simulator`, `agent`, `logcopy`, `merge`); the rest is
//! what they share.

pub mod agent;
pub mod cli;
pub mod config;
pub mod handoff;
pub mod init;
pub mod logcopy;
pub mod merge;
pub mod pair;
pub mod s3;
pub mod signals;
pub mod simulator;
pub mod status;
pub mod supervise;
pub mod telemetry;
pub mod tree;
