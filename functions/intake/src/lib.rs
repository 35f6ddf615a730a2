//! Intake (stage 1): validate the message, read the submission on EvalAI, decide whether it is
//! ours to run, pin the image's tag to its digest, gate on the qualifier, choose the worker
//! count and claim it in DynamoDB.
//!
//! Nothing here touches the Job cluster: a skipped or rejected submission costs nothing.

use aws_config::SdkConfig;
use lb_aws::dynamo::{Claim, NewRecord, QualifierTable, SubmissionsTable};
use lb_aws::ecr::{Lookup, Registry};
use lb_domain::run::intake;
use lb_domain::run::metrics::{Metric, Signals};
use lb_domain::settings::{Settings, Target};
use lb_domain::submission::{SubmissionMessage, SubmissionStatus};
use lb_evalai::{EvalAiClient, Submission};
use lb_pipeline::payload::{Decision, IntakeInput, SubmissionInfo};
use lb_pipeline::serve::Function;
use lb_pipeline::{clients, FnError, FunctionConfig, Result};
use tracing::{info, warn};

/// What Intake needs: read access to EvalAI and the settings, the submissions and qualifier
/// tables, the participants' image registry.
#[derive(Debug, Clone)]
pub struct Deps {
    /// The operator's configuration.
    pub settings: Settings,
    /// EvalAI, as the host.
    pub evalai: EvalAiClient,
    /// DynamoDB.
    pub dynamo: aws_sdk_dynamodb::Client,
    /// ECR, where the participants' images are.
    pub registry: Registry,
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
            registry: Registry::new(sdk),
        })
    }
}

impl Function for Deps {
    const NAME: &'static str = "intake";
    type Input = IntakeInput;
    type Output = Decision;
    async fn handle(&self, input: IntakeInput) -> Result<Decision> {
        let decision = handle(input, self).await?;
        let arrival = match &decision {
            Decision::Run(info) => Some((info.leaderboard, Metric::Arrivals)),
            Decision::Reject { submission, .. } => Some((submission.leaderboard, Metric::Refusals)),
            Decision::Skip { .. } => None,
        };
        if let Some((leaderboard, metric)) = arrival {
            let mut signals = Signals::default();
            signals.add(metric, 1.0);
            lb_pipeline::metrics::record_for(leaderboard, signals);
        }
        Ok(decision)
    }
}

/// A refusal, said in the log.
fn rejected(reason: String, submission: SubmissionInfo) -> Decision {
    warn!(submission_id = submission.submission_id, reason = %reason, "rejected");
    Decision::Reject { reason, submission }
}

/// A skip, said in the log.
fn skipped(reason: String, submission: SubmissionInfo) -> Decision {
    info!(submission_id = submission.submission_id, reason = %reason, "skipped");
    Decision::Skip {
        reason,
        submission: Some(submission),
    }
}

/// Decides what to do with one submission message: each fact is read only when the rules
/// before it let the submission through (`lb_domain::run::intake` has the rules).
pub async fn handle(input: IntakeInput, deps: &Deps) -> Result<Decision> {
    let message = SubmissionMessage::from_pipe(&input.message)?;
    let target = deps.settings.target(message.phase_id)?;
    let submission = deps.evalai.submission(message.submission_id).await?;
    let mut info = described(&message, &target, &submission, input.execution)?;
    if let Some(reason) = intake::skip_reason(submission.status) {
        return Ok(skipped(reason, info));
    }
    let image = match message.image {
        Some(image) => image,
        None => match deps.evalai.submitted_image(&submission).await {
            Ok(image) => image,
            Err(e) => {
                let reason = intake::no_image(&e.to_string());
                return Ok(rejected(reason, info));
            }
        },
    };
    // Before anything is claimed: an image no cluster can pull would hold the claim for a run
    // that cannot start, and an oversized one would grow every state's payload.
    let reference = match lb_jobs::parse_image(&image) {
        Ok(reference) => reference,
        Err(problem) => {
            let reason = intake::invalid_image(&image, &problem);
            return Ok(rejected(reason, info));
        }
    };
    // The Jobs run the digest the tag names now: every pair and every replacement pod runs
    // the same code, whatever is pushed to the tag later.
    info.image = match pinned(deps, &reference).await? {
        Pinned::Digest(pinned) => pinned,
        Pinned::AsGiven => image.clone(),
        Pinned::NotFound => {
            let reason = intake::image_not_found(&image);
            return Ok(rejected(reason, info));
        }
    };
    if let Some(qualifier) = target.required_qualifier() {
        let table = QualifierTable::new(deps.dynamo.clone(), &target.deployment.qualifier_table);
        // The item `(team, track)` admits: a pass recorded by the original system counts.
        if !table.admitted(info.team_id, &info.track).await? {
            let reason = intake::not_qualified(&info.team_name, qualifier, &info.track);
            return Ok(rejected(reason, info));
        }
    }
    let table = SubmissionsTable::new(deps.dynamo.clone(), &target.deployment.submissions_table);
    let overridden = table
        .worker_override(info.team_id, info.submission_id)
        .await?;
    info.workers = intake::worker_count(overridden, target.track_settings.workers, info.routes);
    Ok(match table.claim(&new_record(&info, &image)).await? {
        Claim::Claimed => {
            info!(
                submission_id = info.submission_id,
                workers = info.workers,
                "claimed"
            );
            Decision::Run(info)
        }
        Claim::Duplicate { status, claimed_by } => {
            let reason = intake::duplicate(claimed_by.as_deref(), status);
            skipped(reason, info)
        }
    })
}

/// The submission as the message, the settings and EvalAI describe it (no image or worker
/// count yet); EvalAI must have it in the message's phase.
fn described(
    message: &SubmissionMessage,
    target: &Target<'_>,
    submission: &Submission,
    execution: String,
) -> Result<SubmissionInfo> {
    if submission.phase_id != message.phase_id {
        return Err(FnError::PhaseMismatch {
            message: message.phase_id,
            submission: submission.id,
            evalai: submission.phase_id,
        });
    }
    let resuming = submission.status == SubmissionStatus::Resuming;
    Ok(SubmissionInfo {
        challenge_id: message.challenge_id,
        phase_id: message.phase_id,
        submission_id: message.submission_id,
        team_id: submission.team_id,
        team_name: submission.team_name.clone(),
        leaderboard: target.leaderboard,
        track: target.track.to_string(),
        image: String::new(),
        routes: target.track_settings.routes,
        workers: 0,
        resuming,
        execution,
        // A resume arrives anew; a new submission's place is when EvalAI received it.
        arrived_ms: submission.submitted_ms.filter(|_| !resuming),
        submitted_at: submission.submitted_ms.map_or(0, |ms| ms / 1000),
    })
}

/// What the Jobs will name the participant's image by.
enum Pinned {
    /// Its digest (`repo@sha256:...`).
    Digest(String),
    /// The reference as given: not an ECR tag, or the registry would not say (the Monitor
    /// then holds the pods to the first digest they run).
    AsGiven,
    /// The registry has no such image.
    NotFound,
}

/// Resolves an ECR tag to the digest it names now (`lb_aws::ecr`).
async fn pinned(deps: &Deps, reference: &lb_jobs::ImageRef) -> Result<Pinned> {
    let Some(ecr) = reference.ecr_tagged() else {
        return Ok(Pinned::AsGiven);
    };
    let registry = (ecr.registry, ecr.region);
    Ok(
        match deps
            .registry
            .digest_of(registry, ecr.repository, ecr.tag)
            .await?
        {
            Lookup::Digest(digest) => {
                info!(%digest, "the image's tag resolved");
                Pinned::Digest(reference.pinned(&digest).to_string())
            }
            Lookup::NotFound => Pinned::NotFound,
            Lookup::Refused(why) => {
                warn!(%why, "the image's tag not resolved: the Jobs name the tag");
                Pinned::AsGiven
            }
        },
    )
}

/// The record the claim writes: the image as the participant submitted it.
fn new_record(info: &SubmissionInfo, submitted: &str) -> NewRecord {
    NewRecord {
        team_id: info.team_id,
        submission_id: info.submission_id,
        team_name: info.team_name.clone(),
        track_id: info.phase_id,
        track_name: info.track.clone(),
        image: submitted.to_owned(),
        workers: info.workers,
        submitted_time: clients::now_record_time(),
        claimed_by: info.execution.clone(),
        resuming: info.resuming,
    }
}
