//! Launch (stages 2 and 3): take the submission's turn in its leaderboard's queue, then plan the
//! workers, render the leaderboard's Job template and create the Jobs on its cluster (adopting
//! those that already exist), and tell EvalAI the submission is `queued`: it runs (EvalAI's
//! `running`, the record's `RUNNING` and start time) when the Monitor sees its first pair start.
//!
//! A submission whose team already holds its `team_limit` evaluations gets no Jobs: it is
//! `queued` on EvalAI, and the Monitor asks for its turn again each round; once admitted, the
//! state machine comes back here (`LaunchAdmitted`) to create them.

use aws_config::SdkConfig;
use lb_domain::capacity::cost::{self, Orchestration};
use lb_domain::job::plan::{plan, Plan, PlanInput};
use lb_domain::run::history;
use lb_domain::run::schedule::queue_wait;
use lb_domain::run::schedule::FIRST_WAIT;
use lb_domain::settings::{Settings, Target};
use lb_evalai::{EvalAiClient, SubmissionRef, WriteOutcome};
use lb_jobs::{render_plan, JobSettings};
use lb_pipeline::cluster::Clusters;
use lb_pipeline::payload::{MonitorState, PairRoutes, QueueState, RunState, SubmissionInfo};
use lb_pipeline::serve::{Function, Invocation};
use lb_pipeline::{clients, queue, FunctionConfig, Result};
use std::future::Future;
use std::time::Duration;

use serde::{Deserialize, Serialize};
use tracing::{info, warn};

/// What Launch needs: the settings, the clusters, EvalAI (to say it is queued).
#[derive(Debug)]
pub struct Deps {
    /// The operator's configuration.
    pub settings: Settings,
    /// EvalAI, as the host.
    pub evalai: EvalAiClient,
    /// The Job clusters.
    pub clusters: Clusters,
    /// Region of the bucket (the Jobs' `AWS_REGION`).
    pub region: String,
    /// The sidecar's timers, when not the defaults (local runs poll faster).
    pub timers: Option<lb_jobs::Timers>,
    /// The leaderboards' queues.
    pub admission: queue::Admission,
    /// This function's memory, MB, and its DynamoDB requests: its share of the orchestration.
    pub memory_mb: u32,
    /// The DynamoDB requests of its clients.
    pub dynamo_requests: lb_aws::RequestCount,
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
        let settings = clients::settings(sdk, config).await?;
        let count = lb_aws::RequestCount::default();
        let evalai = clients::evalai_counted(sdk, config, &settings, &count).await?;
        Ok(Deps {
            settings,
            evalai,
            clusters,
            region: sdk.region().map(|r| r.to_string()).unwrap_or_default(),
            timers: None,
            admission: clients::admission_counted(sdk, config, &count),
            memory_mb: config.memory_mb,
            dynamo_requests: count,
        })
    }
}

/// Launch's input.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LaunchInput {
    /// As Intake established it.
    pub submission: SubmissionInfo,
    /// Its place in the queue, when it waited for its turn (`LaunchAdmitted`); none the first
    /// time.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub queue: Option<QueueState>,
    /// This execution's history so far, as the Monitor counted it (`LaunchAdmitted`): the
    /// count goes on from there (`lb_domain::run::history`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub events: Option<u64>,
    /// `$$.Execution.Name`: whose history `events` counts (a continued run's execution is not
    /// the one that claimed the submission).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub execution: Option<String>,
    /// What the orchestration did for the run while it waited for its turn
    /// (`LaunchAdmitted`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub orchestration: Option<Orchestration>,
}

impl Invocation for LaunchInput {
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
    const NAME: &'static str = "launch";
    type Input = LaunchInput;
    type Output = RunState;
    fn handle(&self, input: LaunchInput) -> impl Future<Output = Result<RunState>> {
        handle(input, self)
    }
}

/// Creates the submission's Jobs and starts its run state, or, when its team holds all its
/// places, starts the run state of a submission waiting for its turn; the run's orchestration
/// counted so far, this Launch's share added (and Intake's transitions the first time).
pub async fn handle(input: LaunchInput, deps: &Deps) -> Result<RunState> {
    let meter = clients::Meter::start(&deps.dynamo_requests, deps.memory_mb);
    let before = match input.orchestration {
        Some(counted) => counted,
        // Intake's invocation and the states before Launch.
        None => Orchestration {
            transitions: cost::OPENING_TRANSITIONS,
            invocations: 1,
            ..Orchestration::default()
        },
    };
    let mut run = launch(input, deps).await?;
    let this = meter.invocation(cost::task_transitions(0, run.monitor.after()));
    run.monitor.orchestration = before + this;
    Ok(run)
}

async fn launch(input: LaunchInput, deps: &Deps) -> Result<RunState> {
    let submission = input.submission;
    let target = deps.settings.target(submission.phase_id)?;
    let now = clients::now_epoch_seconds();
    // The first Launch tells EvalAI `queued` even when the team's cap holds it back.
    let first = input.queue.is_none();
    let arrived_ms = lb_domain::capacity::queue::arrival_ms(submission.arrived_ms, now);
    let mut place = input
        .queue
        .unwrap_or_else(|| QueueState::arriving(arrived_ms / 1000));
    let prepared = prepare(deps, &target, &submission)?;
    // This execution's events so far: the opening the first time, the Monitor's count and
    // this Launch after a wait for the turn.
    let events = match input.events {
        None => history::OPENING_EVENTS,
        Some(counted) => counted + history::ADMITTED_EVENTS,
    };
    let execution = input
        .execution
        .unwrap_or_else(|| submission.execution.clone());
    let history = (execution.as_str(), events);
    let at = SubmissionRef::from(&submission);
    let limit = target.deployment.team_limit;
    let standing = deps
        .admission
        .take_turn(&submission, arrived_ms, limit)
        .await?;
    if !standing.admitted {
        info!(
            submission_id = submission.submission_id,
            team_id = submission.team_id,
            ahead = standing.ahead,
            "the team holds all its places: waiting for its turn"
        );
        if first {
            mark_queued(deps, at, "").await?;
        }
        place.admitted = false;
        let mut run = prepared.run_state(0, now, place, history);
        run.monitor.wait_seconds = queue_wait(Duration::ZERO).as_secs();
        return Ok(run);
    }
    place.admitted = true;
    lb_pipeline::metrics::record(lb_domain::run::metrics::admitted(place.arrived_at, now));
    let names = launch_jobs(deps, &target, &submission, &prepared).await?;
    // Queued until a pair starts: the Monitor sends `running` then (EvalAI's `started_at`,
    // the record's start time), so time spent waiting for a GPU is not the participant's.
    mark_queued(deps, at, &names.join(",")).await?;
    let jobs = names.len() as u32;
    Ok(prepared.run_state(jobs, clients::now_epoch_seconds(), place, history))
}

/// What a submission's run is made of, decided before anything is created: the routes over
/// the pairs and the Jobs' settings.
struct Prepared {
    plan: Plan,
    settings: JobSettings,
    pairs: Vec<PairRoutes>,
    /// Records the run ends with: routes times repetitions.
    total: u64,
}

fn prepare(deps: &Deps, target: &Target<'_>, submission: &SubmissionInfo) -> Result<Prepared> {
    let plan = plan(PlanInput {
        submission_id: submission.submission_id,
        team_name: &submission.team_name,
        routes: submission.routes,
        workers: submission.workers,
    })?;
    let deployment = target.deployment;
    let mut settings = JobSettings::from_deployment(
        target.leaderboard,
        deployment,
        &deps.region,
        &deployment.job_role_arn,
    )?;
    settings.qualifier = target.track_settings.qualifier;
    if let Some(timers) = &deps.timers {
        settings.timers = timers.clone();
    }
    let pairs = plan
        .pairs()
        .map(|p| PairRoutes {
            id: p.id,
            routes: p.routes.to_string(),
        })
        .collect();
    let total = u64::from(submission.routes) * u64::from(settings.repetitions);
    Ok(Prepared {
        plan,
        settings,
        pairs,
        total,
    })
}

/// Renders the plan's Jobs and creates them (or adopts those a retry already created); their
/// names.
async fn launch_jobs(
    deps: &Deps,
    target: &Target<'_>,
    submission: &SubmissionInfo,
    prepared: &Prepared,
) -> Result<Vec<String>> {
    let jobs = render_plan(
        target.leaderboard,
        &prepared.plan,
        submission,
        &prepared.settings,
    )?;
    let cluster = deps.clusters.connect(target.deployment).await?;
    let mut names = Vec::with_capacity(jobs.len());
    for job in &jobs {
        let launched = cluster.create_or_adopt(job).await?;
        info!(submission_id = submission.submission_id, job = %launched.name, adopted = launched.adopted, "job launched");
        names.push(launched.name);
    }
    Ok(names)
}

/// Tells EvalAI the submission is queued (with its Jobs' names once it has Jobs).
async fn mark_queued(deps: &Deps, at: SubmissionRef, names: &str) -> Result<()> {
    match deps.evalai.mark_queued(at, names).await? {
        WriteOutcome::Written => {}
        other => warn!(
            submission_id = at.submission,
            ?other,
            "not marked queued; the monitor will see why"
        ),
    }
    Ok(())
}

impl Prepared {
    /// A run's first state: `jobs` Jobs launched (none while it waits for its turn) at `now`.
    fn run_state(self, jobs: u32, now: u64, queue: QueueState, history: (&str, u64)) -> RunState {
        let (execution, events) = history;
        RunState {
            jobs,
            pairs: self.pairs,
            repetitions: self.settings.repetitions,
            launched_at: now,
            recorder: true,
            queue,
            monitor: MonitorState::starting(
                FIRST_WAIT.as_secs(),
                now + lb_aws::wake::RETENTION_SECONDS,
                self.total,
                execution,
                events,
            ),
        }
    }
}
