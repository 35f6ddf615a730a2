//! Launch (stages 2 and 3): plan the workers, render the leaderboard's Job template and create
//! the Jobs on its cluster (adopting those that already exist), then tell EvalAI the
//! submission is `queued`: it runs (EvalAI's `running`, the record's `RUNNING` and start time)
//! when the Monitor sees its first pair start.

use aws_config::SdkConfig;
use lb_domain::plan::{plan, PlanInput};
use lb_domain::schedule::FIRST_WAIT;
use lb_domain::settings::Settings;
use lb_evalai::{EvalAiClient, SubmissionRef, WriteOutcome};
use lb_jobs::{render_plan, JobSettings};
use lb_pipeline::cluster::{cluster_error, Clusters};
use lb_pipeline::payload::{MonitorState, PairRoutes, RunPhase, RunState, SubmissionInfo};
use lb_pipeline::{clients, FnError, FunctionConfig, Result};
use serde::Deserialize;
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
        let evalai = clients::evalai(sdk, config, &settings).await?;
        Ok(Deps {
            settings,
            evalai,
            clusters,
            region: sdk.region().map(|r| r.to_string()).unwrap_or_default(),
            timers: None,
        })
    }
}

/// Launch's input.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LaunchInput {
    /// As Intake established it.
    pub submission: SubmissionInfo,
}

/// The Lambda entry: JSON in, JSON out.
pub async fn handle_json(input: serde_json::Value, deps: &Deps) -> Result<serde_json::Value> {
    let input: LaunchInput =
        serde_json::from_value(input).map_err(|e| FnError::Input(format!("launch input: {e}")))?;
    let output = handle(input, deps).await?;
    serde_json::to_value(output).map_err(|e| FnError::Input(e.to_string()))
}

fn stage(name: &'static str, message: String) -> FnError {
    FnError::Stage {
        name,
        message,
        transient: false,
    }
}

/// Creates the submission's Jobs and starts its run state.
pub async fn handle(input: LaunchInput, deps: &Deps) -> Result<RunState> {
    let submission = input.submission;
    let target = deps.settings.target(submission.phase_id)?;
    let plan = plan(PlanInput {
        submission_id: submission.submission_id,
        team_name: &submission.team_name,
        routes: submission.routes,
        workers: submission.workers,
    })
    .map_err(|e| stage(e.name(), e.to_string()))?;
    let mut job_settings = JobSettings::from_deployment(
        target.leaderboard,
        target.deployment,
        &deps.region,
        &target.deployment.job_role_arn,
    )
    .map_err(|e| stage(e.name(), e.to_string()))?;
    if let Some(timers) = &deps.timers {
        job_settings.timers = timers.clone();
    }
    let jobs = render_plan(
        target.leaderboard,
        &plan,
        &lb_jobs::SubmissionInfo {
            submission_id: submission.submission_id,
            challenge_id: submission.challenge_id,
            phase_id: submission.phase_id,
            team_id: submission.team_id,
            team_name: submission.team_name.clone(),
            track: submission.track.clone(),
            qualifier: target.track_settings.qualifier,
            participant_image: submission.image.clone(),
            participant_resume: submission.resuming,
            execution: submission.execution.clone(),
        },
        &job_settings,
    )
    .map_err(|e| stage(e.name(), e.to_string()))?;

    let cluster = deps.clusters.connect(target.deployment).await?;
    let mut names = Vec::with_capacity(jobs.len());
    for job in &jobs {
        let launched = cluster.create_or_adopt(job).await.map_err(cluster_error)?;
        info!(submission_id = submission.submission_id, job = %launched.name, adopted = launched.adopted, "job launched");
        names.push(launched.name);
    }

    let at = SubmissionRef {
        challenge: submission.challenge_id,
        phase: submission.phase_id,
        submission: submission.submission_id,
    };
    // Queued until a pair starts: the Monitor sends `running` then (EvalAI's `started_at`,
    // the record's start time), so time spent waiting for a GPU is not the participant's.
    match deps.evalai.mark_queued(at, &names.join(",")).await? {
        WriteOutcome::Written => {}
        other => warn!(
            submission_id = submission.submission_id,
            ?other,
            "not marked queued; the monitor will see why"
        ),
    }
    let total = u64::from(submission.routes) * u64::from(job_settings.repetitions);

    let now = clients::now_epoch_seconds();
    Ok(RunState {
        jobs: names.len() as u32,
        pairs: plan
            .pairs()
            .map(|p| PairRoutes {
                id: p.id,
                routes: p.routes.to_string(),
            })
            .collect(),
        repetitions: job_settings.repetitions,
        launched_at: now,
        monitor: MonitorState {
            state: RunPhase::Running,
            wait_seconds: FIRST_WAIT.as_secs(),
            hold_seconds: 0,
            seen: 0,
            poll: false,
            expires_at: now + lb_aws::wake::RETENTION_SECONDS,
            updated_at: None,
            status_read_at: None,
            rounds: 0,
            fingerprint: None,
            progress: (0, total),
            reason: None,
            unreachable_since: None,
            started_at: None,
        },
    })
}
