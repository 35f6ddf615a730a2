//! `lb-sidecar`: the one static binary that runs inside every evaluation Job.

pub mod cli;
pub mod merge;
pub mod telemetry;
