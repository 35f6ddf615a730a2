//! Command-line interface of `lb-sidecar`.

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand};
use lb_domain::results::{Leaderboard, RouteSubset};

/// The in-Job sidecar of the CARLA Leaderboard evaluation backend.
#[derive(Debug, Parser)]
#[command(name = "lb-sidecar", version, about)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// Subcommands. Everything but `merge` is configured by environment variables (see the
/// README); a missing or malformed one is named in an `InvalidEnvironment` error.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Init container: copy the official code and this binary into the shared volumes,
    /// create the logs tree, clear stale markers, download partial results and logs.
    Init,
    /// Run CARLA (`-- CMD...`) as the simulator of a pair.
    Simulator(WrapArgs),
    /// Run the Leaderboard evaluator (`-- CMD...`) as the agent of a pair.
    Agent(WrapArgs),
    /// Upload the logs tree to S3 every period until the Job is over.
    Logcopy,
    /// Merge workers' results files and write the merged file and the EvalAI files.
    ///
    /// Writes DIR/agent_results.json and DIR/evalai/{results.json,stdout.txt,metadata.json},
    /// all or nothing: on an error nothing new is written and earlier outputs are removed, so
    /// a stale result can never be published.
    Merge(MergeArgs),
}

/// The wrapped command of `simulator` and `agent`.
#[derive(Debug, Args)]
pub struct WrapArgs {
    /// The command and its arguments, after `--`.
    #[arg(last = true, required = true, value_name = "CMD")]
    pub command: Vec<String>,
}

/// Arguments of `lb-sidecar merge`.
#[derive(Debug, Args)]
pub struct MergeArgs {
    /// Output directory (created if missing).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Routes the plan assigned over all workers; with fewer records the result is partial
    /// and never a final score.
    #[arg(long, value_name = "N")]
    pub expect_routes: Option<u64>,
    /// Repetitions of each route (Leaderboard 1.0 runs 5); multiplies --expect-routes.
    #[arg(long, value_name = "R", default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..=100))]
    pub repetitions: u64,
    /// Which evaluator wrote the files.
    #[arg(long, value_name = "1.0|2.0", default_value = "2.0")]
    pub leaderboard: Leaderboard,
    /// Each file's assigned route subset, in file order (e.g. 0-4,5-9,10-14,15-19); a record
    /// outside its subset is an error.
    #[arg(long, value_name = "a-b,...", value_delimiter = ',')]
    pub subsets: Vec<RouteSubset>,
    /// Workers' results files; a missing, empty or unreadable one counts as empty.
    #[arg(value_name = "FILE", required = true)]
    pub files: Vec<PathBuf>,
}
