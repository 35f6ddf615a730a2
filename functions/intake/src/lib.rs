//! Intake (stage 1): validate the message, read the submission on EvalAI, decide whether it is
//! ours to run, gate on the qualifier, choose the worker count and claim it in DynamoDB.
//!
//! Nothing here touches the Job cluster: a skipped or rejected submission costs nothing.

use aws_config::SdkConfig;
use lb_aws::dynamo::{Claim, NewRecord, QualifierTable, SubmissionsTable};
use lb_domain::settings::Settings;
use lb_domain::submission::{SubmissionMessage, SubmissionStatus};
use lb_evalai::EvalAiClient;
use lb_pipeline::payload::{Action, IntakeInput, IntakeOutput, SubmissionInfo};
use lb_pipeline::serve::Function;
use lb_pipeline::{clients, FnError, FunctionConfig, Result};
use std::future::Future;
use tracing::{info, warn};

/// What Intake needs: read access to EvalAI and the settings, the submissions and qualifier
/// tables.
#[derive(Debug, Clone)]
pub struct Deps {
    /// The operator's configuration.
    pub settings: Settings,
    /// EvalAI, as the host.
    pub evalai: EvalAiClient,
    /// DynamoDB.
    pub dynamo: aws_sdk_dynamodb::Client,
}

impl Deps {
    /// Cold start: environment, secrets, clients.
    pub async fn from_env() -> Result<Deps> {
        let (config, sdk) = clients::cold_start().await?;
        Self::load(&sdk, &config).await
    }

    /// The same from an explicit SDK configuration (local mode, tests).
    pub async fn load(sdk: &SdkConfig, config: &FunctionConfig) -> Result<Deps> {
        let settings = clients::settings(sdk, config).await?;
        let evalai = clients::evalai(sdk, config, &settings).await?;
        Ok(Deps {
            settings,
            evalai,
            dynamo: aws_sdk_dynamodb::Client::new(sdk),
        })
    }
}

impl Function for Deps {
    const NAME: &'static str = "intake";
    type Input = IntakeInput;
    type Output = IntakeOutput;
    fn handle(&self, input: IntakeInput) -> impl Future<Output = Result<IntakeOutput>> {
        handle(input, self)
    }
}

fn skip(reason: String, submission: Option<SubmissionInfo>) -> IntakeOutput {
    IntakeOutput {
        action: Action::Skip,
        reason: Some(reason),
        submission,
    }
}

/// Decides what to do with one submission message.
pub async fn handle(input: IntakeInput, deps: &Deps) -> Result<IntakeOutput> {
    let message = SubmissionMessage::from_pipe(&input.message)?;
    let target = deps.settings.target(message.phase_id)?;
    let submission = deps.evalai.submission(message.submission_id).await?;
    if submission.phase_id != message.phase_id {
        return Err(FnError::PhaseMismatch {
            message: message.phase_id,
            submission: submission.id,
            evalai: submission.phase_id,
        });
    }
    let mut info = SubmissionInfo {
        challenge_id: message.challenge_id,
        phase_id: message.phase_id,
        submission_id: message.submission_id,
        team_id: submission.team_id,
        team_name: submission.team_name.clone(),
        leaderboard: target.leaderboard.as_str().to_string(),
        track: target.track.to_string(),
        image: String::new(),
        routes: target.track_settings.routes,
        workers: 0,
        resuming: submission.status == SubmissionStatus::Resuming,
        execution: input.execution.clone(),
        // A resume arrives anew; a new submission's place is when EvalAI received it.
        arrived_ms: submission
            .submitted_ms
            .filter(|_| submission.status != SubmissionStatus::Resuming),
    };
    if !submission.status.starts_evaluation() {
        info!(submission_id = info.submission_id, status = %submission.status, "not ours to run");
        return Ok(skip(
            format!(
                "EvalAI status is `{}`; only submitted or resuming submissions start",
                submission.status
            ),
            Some(info),
        ));
    }

    let reject = |reason: String, info: SubmissionInfo| {
        warn!(submission_id = info.submission_id, %reason, "rejected");
        Ok(IntakeOutput {
            action: Action::Reject,
            reason: Some(reason),
            submission: Some(info),
        })
    };

    info.image = match message.image {
        Some(image) => image,
        None => match deps.evalai.submitted_image(&submission).await {
            Ok(image) => image,
            Err(e) => {
                return reject(
                    format!("the submission has no docker image URI ({e}); push the image again with `evalai push`"),
                    info,
                )
            }
        },
    };

    // Before anything is claimed: an image no cluster can pull would hold the claim for a run
    // that cannot start, and an oversized one would grow every state's payload.
    if let Err(problem) = lb_jobs::parse_image(&info.image) {
        let shown: String = info.image.chars().take(120).collect();
        let cut = if shown.len() < info.image.len() {
            "..."
        } else {
            ""
        };
        info.image = String::new();
        return reject(
            format!(
                "the docker image URI `{}{cut}` is not a valid image reference: {problem}; push \
                 the image again with `evalai push`",
                shown.escape_debug()
            ),
            info,
        );
    }

    if let Some(qualifier) = target.required_qualifier() {
        let table = QualifierTable::new(deps.dynamo.clone(), &target.deployment.qualifier_table);
        // The item `(team, track)` admits: a pass recorded by the original system counts.
        if !table.admitted(info.team_id, &info.track).await? {
            return reject(
                format!(
                    "team `{}` has not passed the qualifier track `{qualifier}` yet, which `{}` requires",
                    info.team_name, info.track
                ),
                info,
            );
        }
    }

    let table = SubmissionsTable::new(deps.dynamo.clone(), &target.deployment.submissions_table);
    let workers = table
        .worker_override(info.team_id, info.submission_id)
        .await?
        .unwrap_or(target.track_settings.workers);
    info.workers = workers.min(info.routes).max(1);

    let claim = table
        .claim(&NewRecord {
            team_id: info.team_id,
            submission_id: info.submission_id,
            team_name: info.team_name.clone(),
            track_id: info.phase_id,
            track_name: info.track.clone(),
            image: info.image.clone(),
            workers: info.workers,
            submitted_time: clients::now_record_time(),
            claimed_by: info.execution.clone(),
            resuming: info.resuming,
        })
        .await?;
    match claim {
        Claim::Claimed => {
            info!(
                submission_id = info.submission_id,
                workers = info.workers,
                "claimed"
            );
            Ok(IntakeOutput {
                action: Action::Run,
                reason: None,
                submission: Some(info),
            })
        }
        Claim::Duplicate { status, claimed_by } => Ok(skip(
            format!(
                "already claimed by `{}` (record status `{}`): a duplicate delivery",
                claimed_by.unwrap_or_default(),
                status.unwrap_or_default()
            ),
            Some(info),
        )),
    }
}
