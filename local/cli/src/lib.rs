//! `lbctl local`: the rehearsal room's commands, a separate executable (`lbctl-local`) that
//! the shipped `lbctl` runs for `lbctl local ...`, so nothing of the rehearsal ships.

mod emf;
mod latency;
mod queue_report;
mod reaper;
mod reclaim;
mod relay;
mod release;
mod report;
mod run;
pub mod scenario;
mod states;
pub mod wiring;

use clap::{Parser, Subcommand};

pub use run::LocalRun;
pub use scenario::Scenario;

/// Rehearse the CARLA Leaderboard evaluation backend on this machine: moto, the fake EvalAI
/// and the local Kubernetes API stand in for AWS, EvalAI and EKS (no AWS account needed).
#[derive(Debug, Parser)]
#[command(name = "lbctl local", bin_name = "lbctl local", version)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
    /// Logging.
    #[command(flatten)]
    pub global: cli::Global,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Run one submission from the SQS message to the final scores: moto, the fake EvalAI,
    /// the local Kubernetes API, the real state machine, handlers, Job templates and sidecar.
    Run(LocalRun),
}

/// Runs a parsed command line; returns the process exit code.
pub async fn run(cli: Cli) -> anyhow::Result<u8> {
    match cli.command {
        Command::Run(args) => run::run(args).await,
    }
}
