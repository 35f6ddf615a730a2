//! `lbctl`: the operators' tool. `lbctl local run` rehearses a whole submission on one machine.

mod local;

use clap::{Parser, Subcommand};

pub use local::{LocalRun, Scenario};

/// Operate the CARLA Leaderboard evaluation backend.
#[derive(Debug, Parser)]
#[command(name = "lbctl", version, about)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Work with the local stack (no AWS account needed).
    #[command(subcommand)]
    Local(LocalCommand),
}

/// `lbctl local ...`.
#[derive(Debug, Subcommand)]
pub enum LocalCommand {
    /// Run one submission from the SQS message to the final scores: moto, the fake EvalAI,
    /// the local Kubernetes API, the real state machine, handlers, Job templates and sidecar.
    Run(LocalRun),
}

/// Runs a parsed command line; returns the process exit code.
pub async fn run(cli: Cli) -> anyhow::Result<u8> {
    match cli.command {
        Command::Local(LocalCommand::Run(args)) => local::run(args).await,
    }
}

/// JSON logs on stderr at `RUST_LOG` (default: warnings), so the progress on stdout stays readable.
pub fn telemetry() {
    use tracing_subscriber::{fmt, EnvFilter};
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("warn"));
    let _ = fmt()
        .json()
        .with_writer(std::io::stderr)
        .with_env_filter(filter)
        .try_init();
}
