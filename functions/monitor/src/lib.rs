//! Monitor (stage 4): one round of the wait -> Monitor -> Choice loop, as read -> decide ->
//! apply: `lb_domain::run::round` decides every step and which rule wins; this shell performs each
//! step it asks for (`io`) and answers with what it found.
//!
//! A round runs when something changed (a results file or marker landed in S3, the cancel
//! sweep found a cancel: both wake the waiting execution) or when the safety net's timeout
//! ends the wait. EvalAI allows 60 requests a minute for every submission in flight together:
//! partial updates and the status fallback are routine for the shared budget, and wait for a
//! later round when it is short. Transient trouble with EvalAI, S3 or the cluster skips this
//! round's part instead of failing a run that may last three days.

mod io;

use std::future::Future;
use std::time::Duration;

use aws_config::SdkConfig;
use lb_aws::wake::{WakeTable, RETENTION_SECONDS};
use lb_cluster::VerdictPolicy;
use lb_domain::capacity::cost;
use lb_domain::run::round::{Context, Round, Step};
use lb_domain::run::{history, metrics};
use lb_pipeline::clients::{self, RunClients};
use lb_pipeline::cluster::Clusters;
use lb_pipeline::payload::{RunPhase, RunState, SubmissionInfo};
use lb_pipeline::queue::QUEUE_NOTE_INTERVAL;
use lb_pipeline::serve::{Function, Invocation};
use lb_pipeline::{FunctionConfig, Result};
use serde::{Deserialize, Serialize};
use tracing::info;

/// What the Monitor needs: settings, clusters, EvalAI, S3, the submissions table.
#[derive(Debug)]
pub struct Deps {
    /// Settings, EvalAI, clusters, S3, DynamoDB.
    pub clients: RunClients,
    /// How long an unschedulable pod is waited for.
    pub policy: VerdictPolicy,
    /// The wake table.
    pub wake: WakeTable,
    /// The events one execution may take before the run continues as a new one.
    pub history_budget: u64,
}

impl Deps {
    /// Cold start: environment, secrets, clients.
    pub async fn from_env() -> Result<Deps> {
        let (config, sdk) = clients::cold_start().await?;
        let clusters = Clusters::from_env(&sdk);
        Self::load(&sdk, &config, clusters).await
    }

    /// The same from an explicit SDK configuration and cluster access (local mode, tests).
    pub async fn load(
        sdk: &SdkConfig,
        config: &FunctionConfig,
        clusters: Clusters,
    ) -> Result<Deps> {
        let clients = RunClients::load(sdk, config, clusters).await?;
        let wake = WakeTable::new(clients.dynamo.clone(), config.wake_table()?);
        Ok(Deps {
            clients,
            policy: VerdictPolicy::default(),
            wake,
            history_budget: history::EXECUTION_BUDGET,
        })
    }
}

/// The Monitor's input.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MonitorInput {
    /// As Intake established it.
    pub submission: SubmissionInfo,
    /// As Launch or the previous round left it.
    pub run: RunState,
    /// `$$.Execution.Name`: the execution this round runs in (its history is counted).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub execution: Option<String>,
    /// `$$.State.RetryCount`: attempts of this round that failed before this one.
    #[serde(default)]
    pub retries: u64,
}

impl Invocation for MonitorInput {
    fn submission_id(&self) -> Option<u64> {
        Some(self.submission.submission_id)
    }
    fn execution(&self) -> Option<&str> {
        Some(&self.submission.execution)
    }
    fn leaderboard(&self) -> Option<lb_domain::results::Leaderboard> {
        Some(self.submission.leaderboard)
    }
}

impl Function for Deps {
    const NAME: &'static str = "monitor";
    type Input = MonitorInput;
    type Output = RunState;
    fn handle(&self, input: MonitorInput) -> impl Future<Output = Result<RunState>> {
        handle(input, self)
    }
}

/// One monitor round: the round asks, the shell performs and answers, until it is over;
/// then whether the run goes on in this execution (`lb_domain::run::history`).
pub async fn handle(input: MonitorInput, deps: &Deps) -> Result<RunState> {
    let MonitorInput {
        submission,
        run,
        execution,
        retries,
    } = input;
    let meter = clients::Meter::start(&deps.clients.dynamo_requests, deps.clients.memory_mb);
    let target = deps.clients.settings.target(submission.phase_id)?;
    let deployment = target.deployment;
    let before = run.clone();
    let mut round = Round::begin(
        run,
        Context {
            now: clients::now_epoch_seconds(),
            execution,
            retries,
            arrived_ms: submission.arrived_ms,
            partial_update_seconds: deployment.partial_update_seconds,
            move_window_seconds: deployment.move_window_seconds,
            max_queue_hours: deployment.max_queue_hours,
            max_cluster_outage_hours: deployment.max_cluster_outage_hours,
            team_limit: deployment.team_limit,
            note_interval: QUEUE_NOTE_INTERVAL.as_secs(),
            prices: deps.clients.settings.prices.clone(),
            wake_retention: RETENTION_SECONDS,
            policy: VerdictPolicy {
                queue_limit: Duration::from_secs(deployment.max_queue_hours * 3600),
                ..deps.policy
            },
        },
    );
    let mut shell = io::Shell::new(deps, &target, &submission);
    loop {
        match round.poll() {
            Step::Done => break,
            // Boxed: the steps' futures are large, and nested in the runtime's they overflow
            // the compiler's layout depth.
            step => round.answer(Box::pin(shell.perform(step)).await?),
        }
    }
    let mut run = round.finish(deps.history_budget, &submission.execution);
    let prices = &deps.clients.settings.prices;
    lb_pipeline::metrics::record(metrics::of_round(&before, &run, prices));
    let (id, monitor) = (submission.submission_id, &run.monitor);
    match monitor.state {
        RunPhase::Running | RunPhase::Admitted => {}
        RunPhase::Continued => {
            info!(submission_id = id, events = monitor.events, next = ?monitor.continue_as, "history budget reached: continuing as a new execution")
        }
        state => info!(submission_id = id, ?state, reason = ?monitor.reason, "the run ended"),
    }
    // This round's share of the orchestration, up to the next task.
    let round = meter.invocation(cost::task_transitions(retries, run.monitor.after()));
    run.monitor.orchestration = run.monitor.orchestration + round;
    Ok(run)
}
