//! `lbctl local run`: one submission from the SQS message to the final scores on this machine,
//! through the deployed state machine definition, the real handlers, Job templates and sidecar.
//! What differs per scenario is in `crate::scenario`; the handlers' wiring in `crate::wiring`.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;

use anyhow::bail;
use clap::Args;
use lb_domain::results::Leaderboard;
use local_stack::events::LateCallbacks;

use crate::release::Release;
use crate::scenario::{Rehearsal, Scenario};
use crate::wiring::Handlers;
use cli::outln;

mod drive;
mod inspect;
mod outcome;
mod setup;

use drive::*;
use inspect::*;
use outcome::*;
use setup::*;

pub(crate) use setup::machine;

/// The deployed definition, embedded so `lbctl` runs from anywhere.
const DEFINITION: &str = include_str!("../../../../statemachine/submission.asl.json");

/// `lbctl local run` options.
#[derive(Debug, Clone, Args)]
pub struct LocalRun {
    /// What to rehearse.
    #[arg(long, value_enum, default_value = "happy")]
    pub scenario: Scenario,
    /// Simulator-agent pairs.
    #[arg(long, default_value_t = 4)]
    pub workers: u32,
    /// The Kubernetes the Jobs run on: local-kube (embedded, fast), or the real control plane
    /// of the pinned release (`make real-kube` builds it) with local-kube's process runner as
    /// the kubelet of its GPU nodes.
    #[arg(long, value_enum, default_value = "local")]
    pub kube: KubeKind,
    /// GPUs of the local node (`nvidia.com/gpu`; each pair's agent requests one): pairs
    /// beyond them wait Pending, Unschedulable, until a GPU frees. Default: not modelled.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub gpus: Option<u32>,
    /// Submissions run together, from the teams of --teams, arriving on EvalAI in that order.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=50))]
    pub submissions: u32,
    /// How many of the submissions each team sends, e.g. `6,2,2,2` (summing to
    /// --submissions; the first team's go first). Default: one team for all.
    #[arg(long, value_delimiter = ',', value_parser = clap::value_parser!(u32).range(1..=50))]
    pub teams: Vec<u32>,
    /// The leaderboard's `team_limit`: evaluations one team may hold at once.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=100))]
    pub team_limit: Option<u32>,
    /// Write what the fake EvalAI saw of each submission (statuses in order, queue places
    /// shown, admission order, requests a minute) to this JSON file.
    #[arg(long, value_name = "FILE")]
    pub report: Option<std::path::PathBuf>,
    /// Write the metrics documents the functions print (CloudWatch's embedded metric format,
    /// one a line) to this file instead of the run's working folder, so they outlive it.
    #[arg(long, value_name = "FILE")]
    pub metrics: Option<std::path::PathBuf>,
    /// Routes of the track.
    #[arg(long, default_value_t = 20)]
    pub routes: u32,
    /// Seconds the fake evaluator spends per route.
    #[arg(long, default_value_t = 0.2)]
    pub route_seconds: f64,
    /// Leaderboard of the submission's phase (`1.0` or `2.0`).
    #[arg(long, default_value = "2.0", value_parser = |s: &str| s.parse::<Leaderboard>())]
    pub leaderboard: Leaderboard,
    /// Multiplies the state machine's waits and retry intervals (0.05: a 60 s Wait lasts 3 s).
    #[arg(long, default_value_t = 0.05)]
    pub time_scale: f64,
    /// From the first Monitor round, the local cluster's API answers every request with 500
    /// `InternalError` for this many minutes (scaled by --time-scale); the Jobs run on.
    #[arg(long, default_value_t = 0.0)]
    pub kube_outage_minutes: f64,
    /// The cancel scenario: the participant cancels when this Monitor round ends.
    #[arg(long, default_value_t = 1)]
    pub cancel_after_round: u64,
    /// The events one execution may take before the run continues as a new execution (the
    /// deployment's is 10,000; a small one rehearses continuations in a short run).
    #[arg(long, default_value_t = lb_domain::run::history::EXECUTION_BUDGET, value_parser = clap::value_parser!(u64).range(lb_domain::run::history::MIN_BUDGET..=lb_domain::run::history::EXECUTION_BUDGET))]
    pub history_budget: u64,
    /// Wall-clock limit of the whole run, in seconds.
    #[arg(long, default_value_t = 600)]
    pub timeout: u64,
    /// An EvalAI to use instead of the fake (needs --evalai-token, --challenge, --phase, --submission).
    #[arg(long, requires_all = ["evalai_token", "challenge", "phase", "submission"])]
    pub evalai_url: Option<String>,
    /// Host token of that EvalAI (better from the environment: a flag shows in `ps`).
    #[arg(long, env = "LB_EVALAI_TOKEN", hide_env_values = true)]
    pub evalai_token: Option<String>,
    /// Challenge id on that EvalAI.
    #[arg(long)]
    pub challenge: Option<u64>,
    /// Phase id on that EvalAI.
    #[arg(long)]
    pub phase: Option<u64>,
    /// Submission id on that EvalAI.
    #[arg(long)]
    pub submission: Option<u64>,
    /// The leaderboard's `partial_update_seconds` (default: 20 s scaled by --time-scale).
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..=3600))]
    pub partial_update_seconds: Option<u64>,
    /// Measure how long results take to reach EvalAI (record -> partial update, last write ->
    /// final status; `make bench-latency`).
    #[arg(long)]
    pub latency: bool,
    /// Leave S3's events undelivered (no wake function): rounds come only from the safety
    /// net, holds and the sweep, as in a deployment whose buckets send no events.
    #[arg(long)]
    pub no_wake: bool,
    /// Write what the run's executions handed on (each function's first input of a kind, a
    /// continued execution's input) into this folder, one JSON file each: the state fixtures
    /// of `statemachine/states/`.
    #[arg(long, value_name = "DIR")]
    pub record_states: Option<std::path::PathBuf>,
    /// Keep the stack running after the summary (until Ctrl-C) to look at S3, EvalAI, logs.
    #[arg(long)]
    pub keep: bool,
}

/// The Kubernetes of a local run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum KubeKind {
    /// local-kube: one node, its own API server, job controller and scheduler.
    Local,
    /// The real kube-apiserver, Job controller and scheduler; local-kube runs the pods.
    Real,
}

fn say(started: Instant, text: impl AsRef<str>) {
    outln!(
        "[{:>6.1}s] {}",
        started.elapsed().as_secs_f64(),
        text.as_ref()
    );
}

/// Runs one local submission; the exit code is 0 only when it ended as the scenario expects.
/// SIGTERM (what `timeout`, make and CI send) or SIGINT ends it early: the run is dropped, and
/// with it everything it started (moto, the fake EvalAI, the Kubernetes API or the real
/// control plane, the node agent and the pods' process groups), before it exits 143 or 130.
pub async fn run(args: LocalRun) -> anyhow::Result<u8> {
    use tokio::signal::unix::{signal, SignalKind};
    let mut term = signal(SignalKind::terminate())?;
    let mut interrupt = signal(SignalKind::interrupt())?;
    let stopped_by = tokio::select! {
        code = run_to_end(args) => return code,
        _ = term.recv() => ("SIGTERM", 143),
        _ = interrupt.recv() => ("SIGINT", 130),
    };
    outln!(
        "stopped by {}: everything the run started is stopped",
        stopped_by.0
    );
    Ok(stopped_by.1)
}

async fn run_to_end(mut args: LocalRun) -> anyhow::Result<u8> {
    let scenario: Arc<dyn Rehearsal> = Arc::from(args.scenario.rehearsal());
    // A release needs a submission on each side of the move.
    if scenario.release().is_some() && args.teams.is_empty() {
        args.submissions = args.submissions.max(2);
    }
    check(&args)?;
    let teams = team_sizes(&args)?;
    let started = Instant::now();
    let (stack, settings, kubeconfig, metrics) = set_up(&args, &*scenario, &teams, started).await?;
    let arrivals = submissions(&args, &stack, &teams, scenario.image())?;
    // The first is the one the summary describes in detail (and the scenarios act on).
    let submission = arrivals.each[0].0;
    let handlers = Handlers::load(&stack.sdk, kubeconfig.clone(), &pace(&args)).await?;
    // The summary reads the outcome from EvalAI with the functions' own client.
    let evalai = handlers.intake.evalai.clone();
    let late = LateCallbacks::default();
    let (tasks, reaper_deps) = handlers.task_map(&late);
    // The wake table's wait, on moto's DynamoDB; a continuation, on the executor.
    let tasks = local_stack::integrations::with_services(tasks, &stack.sdk, late.clone());
    let acted = Arc::new(AtomicBool::new(!scenario.acts()));
    let reaper_failures = Arc::new(AtomicU64::new(0));
    scenario.begin(&begin(
        &args,
        &stack,
        &settings,
        kubeconfig.clone(),
        submission,
        &acted,
        &reaper_failures,
    ));
    let many = arrivals.each.len() > 1;
    let watch = Watch::default();
    // Many executions: the per-round lines of each would drown the summary.
    let on_event = (!many).then(|| watch.on_event(&args, &stack, &scenario, &acted, started));
    let executor = executor(&args, tasks, on_event)?;
    late.bind(executor.clone());
    let template = local_stack::stack::app_template(&settings);
    let scaled = (&template, args.time_scale);
    let reaper = (reaper_deps, reaper_failures);
    let executor_and = (&executor, kubeconfig.as_path());
    let (mut reaper, relays) = deliveries(&args, &stack, scaled, executor_and, reaper).await?;
    let release = Release::publish(&executor, scenario.release())?;
    let hooks = (&*scenario, &watch, &acted, &mut reaper, scaled);
    let (executions, moved) = start_through(
        &args, &stack, &executor, &arrivals, &release, hooks, started,
    )
    .await?;
    let record = args.record_states.as_deref();
    let (mut results, chains) = wait_all(&executor, executions, record, started).await?;
    let release = release.check(&results, moved);
    let reaped = reaper.collect(ended_without_finalize(&results)).await;
    let ended = Instant::now();
    let bucket = settings_bucket(&settings, args.leaderboard);
    let logs = agent_logs(&stack.sdk, &bucket, submission, args.workers).await;
    let findings = scenario.finish(&logs).await;
    let wakes = relays.stop();
    let ran = Ran {
        args: &args,
        stack: &stack,
        settings: &settings,
        kubeconfig: &kubeconfig,
        arrivals: &arrivals.each,
        result: results.remove(0),
        chains: &chains,
        reaped,
        logs: &logs,
        findings,
        watch: &watch,
        acted: acted.load(Ordering::SeqCst),
        wakes,
        times: (started, ended),
        expected: scenario.expected(),
        audit_passes: scenario.audit_passes(),
        release,
    };
    let (mut report, latency) = ran.report(&evalai).await;
    report.metrics = metrics.report();
    finish(&args, &stack, &report, latency.as_ref(), many, &kubeconfig).await
}

/// The options no parser checks alone.
fn check(args: &LocalRun) -> anyhow::Result<()> {
    if !(args.time_scale > 0.0 && args.time_scale <= 1.0) {
        bail!("--time-scale must be in (0, 1], got {}", args.time_scale);
    }
    if args.routes == 0 || args.workers == 0 {
        bail!("--routes and --workers must be at least 1");
    }
    if !(args.kube_outage_minutes >= 0.0 && args.kube_outage_minutes <= 7.0 * 24.0 * 60.0) {
        bail!(
            "--kube-outage-minutes must be between 0 and a week, got {}",
            args.kube_outage_minutes
        );
    }
    use clap::ValueEnum as _;
    if args.kube != KubeKind::Real && args.scenario.rehearsal().needs_real_kube() {
        bail!(
            "--scenario {} needs --kube real: only the real control plane's nodes have a disk \
             their kubelet evicts from",
            args.scenario
                .to_possible_value()
                .map_or_else(String::new, |v| v.get_name().to_owned())
        );
    }
    if args.teams.len() > 1 && args.evalai_url.is_some() {
        bail!("--teams needs the fake EvalAI (an external one has its own teams)");
    }
    Ok(())
}
