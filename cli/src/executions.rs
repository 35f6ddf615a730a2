//! `lbctl submit` and `lbctl resume`: Step Functions executions started as the EventBridge
//! Pipe starts them: EvalAI's message through the Pipe's input template, as a one-element
//! batch `[{challenge_pk, phase_pk, submission_pk, submitted_image_uri}]`.

use std::time::{SystemTime, UNIX_EPOCH};

use clap::Args;
use lb_aws::dynamo::RecordStatus;
use lb_aws::s3::{CANCEL_MARKER, STATUS_DIR};
use lb_domain::submission::{SubmissionMessage, SubmissionStatus};
use lb_infra::pipe;
use serde_json::{json, Map, Value};

use crate::deployment::evalai_id;
use crate::deployment::{clean, Deployment, DeploymentArgs, EvalAiTokenArgs, Record, ScanFilter};
use crate::error::{CliError, Result};

/// Where the submission state machine is.
#[derive(Debug, Clone, Args)]
pub struct StateMachineArgs {
    /// ARN of the submission state machine (the one the EventBridge Pipe targets).
    #[arg(
        long = "state-machine",
        value_name = "ARN",
        env = "LB_STATE_MACHINE_ARN"
    )]
    pub state_machine: Option<String>,
}

impl StateMachineArgs {
    /// The ARN, checked before anything is called.
    pub fn arn(&self) -> Result<&str> {
        let arn = self
            .state_machine
            .as_deref()
            .map(str::trim)
            .filter(|a| !a.is_empty())
            .ok_or_else(|| {
                CliError::Usage(
                    "no state machine: pass --state-machine ARN or set LB_STATE_MACHINE_ARN".into(),
                )
            })?;
        if !arn.starts_with("arn:") || !arn.contains(":states:") || !arn.contains(":stateMachine:")
        {
            return Err(CliError::Usage(format!(
                "`{}` (--state-machine or LB_STATE_MACHINE_ARN) is not a state machine ARN \
                 (arn:aws:states:<region>:<account>:stateMachine:<name>)",
                arn.escape_debug()
            )));
        }
        Ok(arn)
    }
}

/// `lbctl submit` options.
#[derive(Debug, Clone, Args)]
pub struct Submit {
    /// EvalAI challenge id (`challenge_pk`).
    #[arg(long, value_parser = evalai_id())]
    pub challenge: u64,
    /// EvalAI phase id (`phase_pk`): it decides the leaderboard and the track.
    #[arg(long, value_parser = evalai_id())]
    pub phase: u64,
    /// EvalAI submission id (`submission_pk`).
    #[arg(long, value_parser = evalai_id())]
    pub submission: u64,
    /// The participant's image (`submitted_image_uri`). Omitted: the key is left out, as
    /// EvalAI does when it could not read it, and Intake reads it from EvalAI's input file.
    #[arg(long, value_name = "URI")]
    pub image: Option<String>,
    /// Print the execution input instead of starting one: what to paste into the Step
    /// Functions console's "Start execution" (needs no AWS access).
    #[arg(long)]
    pub print_input: bool,
    #[command(flatten)]
    pub machine: StateMachineArgs,
}

/// `lbctl resume` options.
#[derive(Debug, Clone, Args)]
pub struct Resume {
    /// EvalAI submission id.
    #[arg(value_parser = evalai_id())]
    pub submission: u64,
    /// EvalAI challenge id; by default read from the input of the execution that claimed the
    /// submission (its record's `claimed_by`).
    #[arg(long, value_parser = evalai_id())]
    pub challenge: Option<u64>,
    /// Skip the checks: resume a FINISHED record too, and do not ask EvalAI for `resuming`.
    #[arg(long)]
    pub force: bool,
    #[command(flatten)]
    pub token: EvalAiTokenArgs,
    #[command(flatten)]
    pub machine: StateMachineArgs,
    #[command(flatten)]
    pub deployment: DeploymentArgs,
}

/// What the EventBridge Pipe starts an execution with for this submission: EvalAI's message
/// (ids as numbers, as EvalAI sends them on resume; no image key when there is none) through
/// the deployed input template, as the Pipe's one-element batch.
pub fn pipe_input(challenge: u64, phase: u64, submission: u64, image: Option<&str>) -> Value {
    let mut body = Map::new();
    body.insert("challenge_pk".into(), json!(challenge));
    body.insert("phase_pk".into(), json!(phase));
    body.insert("submission_pk".into(), json!(submission));
    if let Some(image) = image {
        body.insert("submitted_image_uri".into(), json!(image));
    }
    let record = pipe::record_of_body(&Value::Object(body).to_string());
    // NB: the deployed template has only `<$.body.*>` placeholders; it cannot fail on a body
    // built here (a test holds it to that).
    pipe::batch(&pipe::INPUT_TEMPLATE, &[record]).unwrap_or_else(|_| json!([]))
}

/// A name unique per submission and second: `submission-<id>-<unix time>`.
pub fn execution_name(submission: u64) -> String {
    let now = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    format!("submission-{submission}-{now}")
}

pub use lb_aws::executions::execution_arn;

/// `image` named by the registry digest `digest` (`sha256:...`), when both are well formed.
fn pinned(image: &str, digest: &str) -> Option<String> {
    let reference = lb_jobs::parse_image(image).ok()?;
    let pinned = reference.pinned(digest).to_string();
    lb_jobs::parse_image(&pinned).ok().map(|_| pinned)
}

fn image_ok(image: &str) -> Result<()> {
    if image.trim().is_empty()
        || image.len() > 1000
        || image.chars().any(|c| c.is_whitespace() || c.is_control())
    {
        return Err(CliError::Usage(format!(
            "--image `{}` is not an image URI",
            image.escape_debug()
        )));
    }
    Ok(())
}

async fn start(
    sdk: &aws_config::SdkConfig,
    state_machine: &str,
    submission: u64,
    input: &Value,
) -> Result<(String, String)> {
    let sfn = aws_sdk_sfn::Client::new(sdk);
    let name = execution_name(submission);
    let out = sfn
        .start_execution()
        .state_machine_arn(state_machine)
        .name(&name)
        .input(input.to_string())
        .send()
        .await
        .map_err(|e| {
            CliError::sdk(
                format!("states `StartExecution` of `{state_machine}` named `{name}`"),
                e,
            )
        })?;
    Ok((name, out.execution_arn))
}

fn report(name: &str, arn: &str, input: &Value, state_machine: &str) {
    // Through the unqualified ARN an execution runs the latest revision, which neither `make
    // rollback` nor `make deploy-function` moves: not necessarily the version the Pipe runs.
    if state_machine.split(':').count() == 7 {
        errln!(
            "note: `{state_machine}` is the state machine itself: this execution runs its latest \
             revision, not the version its `live` alias names (the stack's StateMachineAliasArn)"
        );
    }
    outln!("execution started: {name}");
    outln!("  arn    {arn}");
    outln!("  input  {input}");
}

/// `lbctl submit`: one execution with the Pipe's input (or only that input, printed).
pub async fn submit(args: Submit) -> Result<u8> {
    if let Some(image) = &args.image {
        image_ok(image)?;
    }
    let input = pipe_input(
        args.challenge,
        args.phase,
        args.submission,
        args.image.as_deref(),
    );
    if args.print_input {
        outln!(
            "{}",
            serde_json::to_string_pretty(&input).unwrap_or_default()
        );
        return Ok(0);
    }
    let state_machine = args.machine.arn()?;
    let sdk = crate::aws::config().await?;
    let (name, arn) = start(&sdk, state_machine, args.submission, &input).await?;
    report(&name, &arn, &input, state_machine);
    Ok(0)
}

/// The challenge of the execution that claimed the submission.
async fn claimed_challenge(
    sdk: &aws_config::SdkConfig,
    state_machine: &str,
    claimed_by: Option<&str>,
) -> std::result::Result<u64, String> {
    let name = claimed_by
        .filter(|n| !n.is_empty())
        .ok_or("the record has no `claimed_by`")?;
    let arn = execution_arn(state_machine, name)
        .ok_or_else(|| format!("no execution ARN from `{state_machine}`"))?;
    let out = aws_sdk_sfn::Client::new(sdk)
        .describe_execution()
        .execution_arn(&arn)
        .send()
        .await
        .map_err(|e| {
            format!(
                "`DescribeExecution` of `{arn}`: {}",
                aws_sdk_sfn::error::DisplayErrorContext(&e)
            )
        })?;
    let input: Value = serde_json::from_str(out.input().unwrap_or_default())
        .map_err(|e| format!("the input of `{arn}` is not JSON: {e}"))?;
    SubmissionMessage::from_pipe(&input)
        .map(|m| m.challenge_id)
        .map_err(|e| format!("the input of `{arn}`: {e}"))
}

/// Why Intake would not run the submission, and what to do on EvalAI.
fn evalai_advice(id: u64, status: SubmissionStatus) -> String {
    let how = match status {
        SubmissionStatus::Failed => format!(
            "Resume it on EvalAI first (host: POST /api/jobs/submissions/{id}/resume/, failed \
             submissions of challenges that allow it; EvalAI then publishes a new message itself, \
             which starts an execution without lbctl)"
        ),
        _ => format!(
            "Set it to `resuming` on EvalAI first (host: PATCH \
             /api/jobs/challenges/<challenge>/submissions/{id}/update_submission_meta/ with \
             {{\"status\": \"resuming\"}}; this publishes no message), then run lbctl resume again"
        ),
    };
    format!(
        "EvalAI reports submission `{id}` as `{status}`: Intake claims an existing record only \
         while EvalAI says `resuming`, so the execution would be skipped. {how}; or pass --force"
    )
}

/// `lbctl resume`: clears the cancel marker and starts a new execution for a FAILED or
/// CANCELLED submission, with the phase and image of its record.
pub async fn resume(args: Resume) -> Result<u8> {
    let state_machine = args.machine.arn()?;
    let id = args.submission;
    let deployment = Deployment::load(&args.deployment).await?;
    let found = deployment.records(None, ScanFilter::Submission(id)).await?;
    let record = only_record(&found.records, id)?;
    if let Some(why) = resume_refusal(record.status, args.force, id) {
        return Err(CliError::Refused(format!(
            "submission `{id}` cannot be resumed: it is `{}`{why}",
            clean(record.status_word.as_str())
        )));
    }
    let phase = record.track_id.ok_or_else(|| {
        CliError::Refused(format!(
            "the record of submission `{id}` in `{}` has no numeric `track_id` (the phase)",
            record.table
        ))
    })?;
    // The digest the run ran (the routes kept were driven by it), else the tag as submitted.
    let pinned = record
        .image
        .as_deref()
        .and_then(|i| pinned(i, record.image_digest.as_deref()?));
    let image = pinned
        .as_deref()
        .or(record.image.as_deref())
        .filter(|i| image_ok(i).is_ok());
    let challenge = match args.challenge {
        Some(c) => c,
        None => claimed_challenge(&deployment.sdk, state_machine, record.claimed_by.as_deref())
            .await
            .map_err(|why| {
                CliError::Usage(format!(
                    "cannot tell the challenge of submission `{id}` ({why}): pass --challenge"
                ))
            })?,
    };

    if args.force {
        outln!("note: --force: EvalAI's status is not checked");
    } else {
        resuming_on_evalai(&deployment, &args.token, id).await?;
    }
    clear_cancel_marker(&deployment, &record.leaderboard, id).await?;

    let input = pipe_input(challenge, phase, id, image);
    let (name, arn) = start(&deployment.sdk, state_machine, id, &input).await?;
    report(&name, &arn, &input, state_machine);
    outln!(
        "note: Intake runs it only while EvalAI reports `resuming` (its claim takes a FAILED or \
         CANCELLED record back only then); otherwise the execution ends skipped. EvalAI's own \
         resume endpoint also publishes a message: if both arrive, the claim lets one run."
    );
    Ok(0)
}

/// The one record of submission `id`: none means nothing ran here, several need a person.
fn only_record(records: &[Record], id: u64) -> Result<&Record> {
    match records {
        [] => Err(CliError::NotFound(format!(
            "submission `{id}` has no record: it never ran here, so there is nothing to \
             resume (`lbctl submit` starts it)"
        ))),
        [record] => Ok(record),
        many => {
            let places: Vec<String> = many
                .iter()
                .map(|r| format!("team {:?} in `{}`", r.team_id, r.table))
                .collect();
            Err(CliError::Refused(format!(
                "submission `{id}` has {} records ({}): resolve that by hand",
                many.len(),
                places.join(", ")
            )))
        }
    }
}

/// Refuses unless EvalAI reports submission `id` as `resuming` (Intake would skip it).
async fn resuming_on_evalai(
    deployment: &Deployment,
    token: &EvalAiTokenArgs,
    id: u64,
) -> Result<()> {
    let evalai = deployment
        .evalai(token)
        .await
        .map_err(|source| CliError::EvalAi {
            submission: id,
            source: Box::new(source),
        })?;
    let on_evalai = evalai.submission(id).await.map_err(|e| CliError::EvalAi {
        submission: id,
        source: Box::new(e.into()),
    })?;
    if on_evalai.status != SubmissionStatus::Resuming {
        return Err(CliError::Refused(evalai_advice(id, on_evalai.status)));
    }
    Ok(())
}

/// Removes submission `id`'s cancel marker from its leaderboard's bucket, when there is one.
async fn clear_cancel_marker(deployment: &Deployment, leaderboard: &str, id: u64) -> Result<()> {
    let bucket = &deployment.leaderboard(leaderboard)?.bucket;
    let key = format!("{id}/{STATUS_DIR}/{CANCEL_MARKER}");
    let store = lb_aws::s3::SubmissionStore::new(deployment.s3.clone(), bucket, id);
    let markers = store.markers().await.map_err(|e| {
        CliError::aws(
            format!("listing the markers of submission `{id}` in `{bucket}`"),
            e,
        )
    })?;
    if markers.iter().any(|m| m == CANCEL_MARKER) {
        deployment
            .s3
            .delete_object()
            .bucket(bucket)
            .key(&key)
            .send()
            .await
            .map_err(|e| CliError::sdk(format!("s3 `DeleteObject` of `s3://{bucket}/{key}`"), e))?;
        outln!("cancel marker removed: s3://{bucket}/{key}");
    }
    Ok(())
}

/// Why a record in `status` must not be resumed (`None`: it may): only a failed or cancelled
/// submission is, a finished one with `--force`; one in flight is still held by an execution.
fn resume_refusal(status: Option<RecordStatus>, force: bool, id: u64) -> Option<String> {
    match status {
        Some(RecordStatus::Failed | RecordStatus::Cancelled) => None,
        Some(RecordStatus::Finished) if force => None,
        Some(status) if status.is_in_flight() => Some(format!(
            ": an execution still holds it and Intake would skip a new one as a duplicate; \
             `lbctl cancel {id}` first and wait for Finalize"
        )),
        _ => Some(
            "; only FAILED or CANCELLED submissions are resumed (FINISHED with --force)".into(),
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_resume_runs_the_digest_the_run_ran() {
        let digest = format!("sha256:{}", "c".repeat(64));
        let tag = "342236305043.dkr.ecr.us-west-2.amazonaws.com/team-one:agent-v1";
        assert_eq!(
            pinned(tag, &digest).as_deref(),
            Some(
                format!("342236305043.dkr.ecr.us-west-2.amazonaws.com/team-one@{digest}").as_str()
            )
        );
        assert_eq!(pinned(tag, "sha256:nothex"), None);
        assert_eq!(pinned("not an image", &digest), None);
    }

    #[test]
    fn the_input_is_the_pipes_one_element_batch_with_a_missing_image_null() {
        assert_eq!(
            pipe_input(1, 2, 3, Some("img:1")),
            json!([{"challenge_pk": 1, "phase_pk": 2, "submission_pk": 3, "submitted_image_uri": "img:1"}])
        );
        assert_eq!(
            pipe_input(1, 2, 3, None),
            json!([{"challenge_pk": 1, "phase_pk": 2, "submission_pk": 3, "submitted_image_uri": null}])
        );
        // What Intake accepts.
        let message = SubmissionMessage::from_pipe(&pipe_input(1, 2, 3, Some("i"))).unwrap();
        assert_eq!((message.challenge_id, message.submission_id), (1, 3));
    }

    #[test]
    fn execution_names_are_valid_step_functions_names() {
        let name = execution_name(2_147_483_647);
        assert!(name.starts_with("submission-2147483647-"), "{name}");
        assert!(name.len() <= 80);
        assert!(name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_'));
    }

    #[test]
    fn a_missing_or_wrong_state_machine_is_a_usage_error_naming_both_sources() {
        let err = StateMachineArgs {
            state_machine: None,
        }
        .arn()
        .unwrap_err();
        assert_eq!(err.exit_code(), 2);
        assert!(err.to_string().contains("--state-machine"), "{err}");
        assert!(err.to_string().contains("LB_STATE_MACHINE_ARN"), "{err}");
        let err = StateMachineArgs {
            state_machine: Some("arn:aws:lambda:us-east-1:1:function:intake".into()),
        }
        .arn()
        .unwrap_err();
        assert!(err.to_string().contains("not a state machine ARN"), "{err}");
    }

    #[test]
    fn evalai_advice_names_the_endpoint_that_fits_the_status() {
        assert!(evalai_advice(7, SubmissionStatus::Failed).contains("/submissions/7/resume/"));
        assert!(evalai_advice(7, SubmissionStatus::Cancelled).contains("update_submission_meta"));
    }
}
