//! `lbctl`: the operators' tool. `invoke` runs one function in-process; `status`, `list`,
//! `cancel`, `submit`, `resume`, `rescore`, `logs` and `watch` work on a real deployment (AWS
//! configuration from the environment); `lbctl local ...` runs the rehearsal's own executable.

#[macro_use]
pub mod output;
mod aws;
mod deployment;
mod error;
mod executions;
mod invoke;
mod logs;
mod ops;
mod plan;
mod plugin;
mod rescore;
mod support;
mod versions;
mod watch;

use clap::{Parser, Subcommand};

pub use deployment::{clean, DeploymentArgs, MAX_SCAN_PAGES};
pub use error::CliError;
pub use executions::{execution_name, pipe_input, Resume, StateMachineArgs, Submit};
pub use invoke::{error_object, Function, Invoke};
pub use logs::Logs;
pub use ops::{Cancel, List, Release, Status};
pub use rescore::Rescore;
pub use watch::Watch;

const EXIT_CODES: &str = "\
Exit codes: 0 ok, 1 failure (a function error, an AWS error, a refused operation),
2 usage (bad arguments, or a required setting missing).

AWS credentials, region and endpoint (AWS_ENDPOINT_URL) come from the standard environment.";

/// Operate the CARLA Leaderboard evaluation backend: inspect, cancel, submit and resume
/// submissions of a deployment, run one function in-process, rehearse a submission locally.
#[derive(Debug, Parser)]
#[command(name = "lbctl", version, after_help = EXIT_CODES)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
    /// Logging.
    #[command(flatten)]
    pub global: Global,
}

/// The options every command takes (`lbctl local` too).
#[derive(Debug, Clone, Copy, clap::Args)]
pub struct Global {
    /// Log lines on stderr: `text` for people, `json` for machines.
    #[arg(
        long,
        global = true,
        value_enum,
        env = "LB_LOG_FORMAT",
        default_value = "text"
    )]
    pub log_format: LogFormat,
    /// More log lines: `-v` info, `-vv` debug (RUST_LOG, when set, decides instead).
    #[arg(short, long, global = true, action = clap::ArgAction::Count)]
    pub verbose: u8,
}

/// The whole of a `main`: logging as `global` says, the async runtime, `run`, and the exit
/// code (an error said once on stderr after `name: `).
pub fn main_with<F>(name: &str, global: Global, run: F) -> std::process::ExitCode
where
    F: std::future::Future<Output = anyhow::Result<u8>>,
{
    telemetry(global.log_format, global.verbose);
    let runtime = match tokio::runtime::Runtime::new() {
        Ok(runtime) => runtime,
        Err(e) => {
            errln!("{name}: cannot start the async runtime: {e}");
            return std::process::ExitCode::from(1);
        }
    };
    match runtime.block_on(run) {
        Ok(code) => std::process::ExitCode::from(code),
        Err(e) => {
            errln!("{name}: {}", describe(&e));
            std::process::ExitCode::from(exit_code(&e))
        }
    }
}

/// How log lines are written.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum LogFormat {
    /// `WARN message key=value`, one line each.
    Text,
    /// One JSON object per line.
    Json,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Rehearse on this machine (no AWS account needed): `lbctl local run --help`. Runs
    /// `lbctl-local` from beside lbctl or from PATH (`make local` builds it).
    #[command(disable_help_flag = true)]
    Local {
        /// The rehearsal's own arguments, e.g. `run --scenario crash`.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<std::ffi::OsString>,
    },
    /// Run one function's handler in this process, as its Lambda would: configured from
    /// LB_SETTINGS_SECRET, LB_EVALAI_TOKEN_SECRET, AWS_* and LB_KUBECONFIG; prints its JSON
    /// result, or `{"errorType", "errorMessage"}` and exits 1.
    Invoke(Invoke),
    /// Show a submission: its DynamoDB record(s) in every leaderboard and its S3 markers.
    Status(Status),
    /// List submissions from the DynamoDB tables, newest (highest id) first, one line each.
    List(List),
    /// Cancel a running submission: write the S3 cancel marker its Jobs mirror; Finalize then
    /// reports CANCELLED.
    Cancel(Cancel),
    /// Give back a submission's place in its team's share of a leaderboard's queue (a place
    /// whose run ended without giving it back); asks for the id to be typed back.
    Release(Release),
    /// Start a state machine execution for a submission, with the input the EventBridge Pipe
    /// gives it.
    Submit(Submit),
    /// Evaluate a FAILED or CANCELLED submission again: remove its cancel marker and start a
    /// new execution with its record's phase and image. EvalAI must report it `resuming`.
    Resume(Resume),
    /// Merge a submission's workers' results from S3 again, with the library the functions
    /// use; show the EvalAI files, write them with --out, send them with --post.
    Rescore(Rescore),
    /// Print a submission's logs from S3: each worker's agent and simulator output and the
    /// logcopy logs (recordings with --recorder); --follow until it ends.
    Logs(Logs),
    /// The fleet, live: each leaderboard's queue with waits and estimated starts, the runs
    /// with their progress, capacity and cost so far, the GPU nodes paid for and idle, today's
    /// cost and the recent failures; redrawn in place until `q`.
    Top(ops::Top),
    /// Follow one submission until it ends: stage and queue position, pods and restarts,
    /// routes per worker, the last partial scores, EvalAI's status; then a summary.
    Watch(Watch),
    /// Say where the clusters' Kubernetes minor stands in EKS's standard support (exit 1
    /// within 60 days of its end, past it, or when no date is known).
    KubernetesSupport(support::KubernetesSupport),
    /// Ship one function's new version: publish a state machine version naming it and move
    /// the `live` alias there (`make deploy-function` runs it). Running executions keep theirs.
    Ship(versions::Ship),
    /// Move the state machine's `live` alias back to an earlier version: new submissions start
    /// there, executions running on the later one finish on it.
    Rollback(versions::Rollback),
    /// What a deadline rush would cost on the GPU fleet as `infra/` deploys it (billed
    /// instance-hours, dollars, the idle share by cause, waits): the original's way, ours
    /// on-demand and ours Spot first, on the node model `make bench-scale` measures.
    Plan(plan::Plan),
}

/// Runs a parsed command line; returns the process exit code. Errors of the operator commands
/// are [`CliError`]s ([`exit_code`] tells their code).
pub async fn run(cli: Cli) -> anyhow::Result<u8> {
    let code = match cli.command {
        Command::Local { args } => {
            return Err(
                plugin::exec("local", &args, cli.global.log_format, cli.global.verbose).into(),
            )
        }
        Command::Invoke(args) => invoke::run(args).await?,
        Command::Status(args) => ops::status(args).await?,
        Command::List(args) => ops::list(args).await?,
        Command::Cancel(args) => ops::cancel(args).await?,
        Command::Release(args) => ops::release(args).await?,
        Command::Submit(args) => executions::submit(args).await?,
        Command::Resume(args) => executions::resume(args).await?,
        Command::Rescore(args) => rescore::rescore(args).await?,
        Command::Ship(args) => versions::ship(args).await?,
        Command::Rollback(args) => versions::rollback(args).await?,
        Command::Logs(args) => logs::logs(args).await?,
        Command::Watch(args) => watch::watch(args).await?,
        Command::Top(args) => ops::top(args).await?,
        Command::KubernetesSupport(args) => support::run(args)?,
        Command::Plan(args) => plan::run(args)?,
    };
    Ok(code)
}

/// The exit code of an error [`run`] returned: 2 for usage errors, else 1.
pub fn exit_code(error: &anyhow::Error) -> u8 {
    error
        .downcast_ref::<CliError>()
        .map_or(1, CliError::exit_code)
}

/// The error and its causes on one line, each said once (an SDK error repeats its message in
/// its sources).
pub fn describe(error: &anyhow::Error) -> String {
    let mut text = String::new();
    for cause in error.chain() {
        let part = cause.to_string();
        if part.is_empty() || text.contains(&part) {
            continue;
        }
        if !text.is_empty() {
            text.push_str(": ");
        }
        text.push_str(&part);
    }
    text
}

/// Log lines on stderr, warnings only unless asked (`-v`, `RUST_LOG`), so stdout stays the
/// command's output. The SDK's credential chain, which logs every provider it tries, stays
/// quiet unless `RUST_LOG` asks for it: a missing credential is one error line of our own.
pub fn telemetry(format: LogFormat, verbose: u8) {
    use std::io::IsTerminal;
    use tracing_subscriber::{fmt, EnvFilter};
    let level = match verbose {
        0 => "warn",
        1 => "info",
        _ => "debug",
    };
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| {
        EnvFilter::new(format!(
            "{level},aws_config=off,aws_smithy_runtime=error,aws_smithy_runtime_api=error"
        ))
    });
    let builder = fmt().with_writer(std::io::stderr).with_env_filter(filter);
    let _ = match format {
        LogFormat::Json => builder.json().try_init(),
        LogFormat::Text => builder
            .compact()
            .with_target(false)
            .without_time()
            .with_ansi(std::io::stderr().is_terminal())
            .try_init(),
    };
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cause_repeated_by_its_source_is_said_once() {
        let inner = std::io::Error::other("NotFound: no such secret");
        let error = anyhow::Error::new(inner)
            .context("service error: NotFound: no such secret")
            .context("reading `x`");
        assert_eq!(
            describe(&error),
            "reading `x`: service error: NotFound: no such secret"
        );
    }

    #[test]
    fn usage_errors_keep_their_exit_code_through_anyhow() {
        let error = anyhow::Error::from(CliError::Usage("bad".into()));
        assert_eq!(exit_code(&error), 2);
        assert_eq!(exit_code(&anyhow::anyhow!("other")), 1);
    }
}
