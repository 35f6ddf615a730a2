//! Finalize (stage 5 and the failure path): decide the final status, make the final merge,
//! record the qualifier outcome, post the final update to EvalAI (confirmed by a GET), write
//! the final DynamoDB record and delete the Jobs.
//!
//! It only ever acts on a submission this execution claimed (or rejected): an execution that
//! failed before its claim must not touch a submission another execution is evaluating.
//! Every step is idempotent, so the state machine can retry it.

use lb_pipeline::serve::{Function, Invocation};
use std::future::Future;
use std::time::Duration;

use aws_config::SdkConfig;
use lb_aws::admission::AdmissionTable;
use lb_aws::dynamo::{FinalRecord, QualifierTable, RecordStatus, SubmissionsTable};
use lb_aws::s3::{SubmissionStore, CANCEL_MARKER};
use lb_aws::tasks::{Callbacks, StepFunctions};
use lb_aws::wake::WakeTable;
use lb_domain::logtail::{participant_tail, MAX_TAIL_CHARS};
use lb_domain::protocol::{self, Marker, Role, LOGS_DIR};
use lb_domain::py::Num;
use lb_domain::submission::SubmissionStatus;
use lb_evalai::{FinalUpdate, SubmissionRef, WriteOutcome};
use lb_pipeline::clients::{self, RunClients};
use lb_pipeline::cluster::Clusters;
use lb_pipeline::payload::{Action, IntakeOutput, PairRoutes, RunPhase, RunState, SubmissionInfo};
use lb_pipeline::queue;
use lb_pipeline::results::{collect, Snapshot};
use lb_pipeline::{FnError, FunctionConfig, Result};
use serde::{Deserialize, Serialize};
use serde_json::Value;
use tracing::{info, warn};

/// How long Finalize waits for deleted Jobs' pods to go (their logcopy's last upload).
pub const DELETE_WAIT: Duration = Duration::from_secs(120);

/// What Finalize needs: everything the pipeline touches.
#[derive(Debug)]
pub struct Deps<C = StepFunctions> {
    /// Settings, EvalAI, clusters, S3, DynamoDB.
    pub clients: RunClients,
    /// How long to wait for deleted pods.
    pub delete_wait: Duration,
    /// The wake table, to wake the team's next submission when a place is given back.
    pub wakes: Option<WakeTable>,
    /// Where its token is reported (the embedded executor in local mode).
    pub callbacks: C,
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
        let wakes = config
            .wake_table
            .as_deref()
            .map(|t| WakeTable::new(clients.dynamo.clone(), t));
        Ok(Deps {
            clients,
            delete_wait: DELETE_WAIT,
            wakes,
            callbacks: StepFunctions::new(aws_sdk_sfn::Client::new(sdk)),
        })
    }
}

impl<C> Deps<C> {
    /// The same, reporting tokens to `callbacks`.
    pub fn with_callbacks<D: Callbacks>(self, callbacks: D) -> Deps<D> {
        Deps {
            clients: self.clients,
            delete_wait: self.delete_wait,
            wakes: self.wakes,
            callbacks,
        }
    }
}

/// Finalize's input: the whole execution state (`{"state.$": "$"}`).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FinalizeInput {
    /// The state as the failed or finished path left it.
    pub state: Value,
}

/// What Finalize did (`$.final`; the Choice after it reads `pipeline_error`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FinalizeOutput {
    /// The submission's final status on our side (`FINISHED`, `FAILED`, `CANCELLED`; for a
    /// repeated Finalize, the one that stands), `UNCLAIMED` when this execution never owned
    /// it, or `SUPERSEDED` when another execution (a resume) holds it now.
    pub status: String,
    /// A stage failed: the execution ends as failed so operators see it.
    pub pipeline_error: bool,
    /// Why, for failed submissions.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        serialize_with = "lb_pipeline::payload::bounded_reason"
    )]
    pub reason: Option<String>,
}

impl Invocation for FinalizeInput {
    fn submission_id(&self) -> Option<u64> {
        self.state
            .pointer("/intake/submission/submission_id")?
            .as_u64()
    }
    fn execution(&self) -> Option<&str> {
        self.state.pointer("/intake/submission/execution")?.as_str()
    }
}

impl<C: Callbacks> Function for Deps<C> {
    const NAME: &'static str = "finalize";
    type Input = FinalizeInput;
    type Output = FinalizeOutput;
    fn handle(&self, input: FinalizeInput) -> impl Future<Output = Result<FinalizeOutput>> {
        handle(input, self)
    }
}

/// The error a Catch put at `$.error`, in words: Lambda's `Cause` is a JSON text holding
/// `errorMessage`.
pub fn caught_error(state: &Value) -> Option<String> {
    let error = state.get("error")?;
    let name = error
        .get("Error")
        .and_then(Value::as_str)
        .unwrap_or("Error");
    let cause = error
        .get("Cause")
        .and_then(Value::as_str)
        .unwrap_or_default();
    let message = serde_json::from_str::<Value>(cause)
        .ok()
        .and_then(|c| {
            c.get("errorMessage")
                .and_then(Value::as_str)
                .map(str::to_owned)
        })
        .unwrap_or_else(|| cause.to_string());
    Some(if message.is_empty() {
        name.to_string()
    } else {
        format!("{name}: {message}")
    })
}

/// Which routes a failed run evaluated, when some pairs finished and some did not (a pair out
/// of retries, one Job per pair): `None` when none or all finished.
pub fn pairs_note(pairs: &[PairRoutes], finished: &[u32]) -> Option<String> {
    let (done, missing): (Vec<&PairRoutes>, Vec<&PairRoutes>) =
        pairs.iter().partition(|p| finished.contains(&p.id));
    if done.is_empty() || missing.is_empty() {
        return None;
    }
    let describe = |ps: &[&PairRoutes]| {
        let routes: Vec<&str> = ps.iter().map(|p| p.routes.as_str()).collect();
        let ids: Vec<String> = ps.iter().map(|p| p.id.to_string()).collect();
        let pairs = if ids.len() == 1 { "pair" } else { "pairs" };
        format!("routes {} ({pairs} {})", routes.join(", "), ids.join(", "))
    };
    Some(format!(
        "{} were not evaluated; {} are complete and kept: resuming this submission evaluates only the missing routes",
        describe(&missing),
        describe(&done)
    ))
}

/// What the participant reads for a caught error (`Name: message`, from [`caught_error`]): a
/// problem with their results in full; anything on our side as a plain sentence with the
/// error's stable name, its chain (ARNs, table names, endpoints) staying in our logs and in the
/// submission's record.
pub fn participant_reason(error: &str) -> String {
    let name = error.split_once(": ").map_or(error, |(name, _)| name);
    // The participant's own results: the message names the file, field or route to fix.
    if lb_domain::results::ResultsError::names().contains(&name) {
        format!("the evaluation failed: {error}")
    } else {
        format!(
            "the evaluation failed because of an error on the evaluation service's side \
             ({name}), not because of your agent; the organisers have been alerted"
        )
    }
}

/// Ends one execution.
pub async fn handle<C: Callbacks>(input: FinalizeInput, deps: &Deps<C>) -> Result<FinalizeOutput> {
    let state = input.state;
    let error = caught_error(&state);
    let intake: Option<IntakeOutput> = state
        .get("intake")
        .and_then(|v| serde_json::from_value(v.clone()).ok());
    let (action, submission) = match intake {
        Some(IntakeOutput {
            action,
            submission: Some(submission),
            reason,
        }) => ((action, reason), submission),
        _ => {
            // NB: not ours. Telling EvalAI or deleting Jobs here could end another
            // execution's evaluation of the same submission.
            warn!(
                error = error.as_deref().unwrap_or_default(),
                "failed before claiming a submission"
            );
            return Ok(FinalizeOutput {
                status: "UNCLAIMED".into(),
                pipeline_error: true,
                reason: error,
            });
        }
    };
    let at = SubmissionRef {
        challenge: submission.challenge_id,
        phase: submission.phase_id,
        submission: submission.submission_id,
    };
    if action.0 == Action::Reject {
        let reason = action
            .1
            .unwrap_or_else(|| "the submission was refused".into());
        post(
            deps,
            at,
            SubmissionStatus::Failed,
            None,
            String::new(),
            reason.clone(),
        )
        .await?;
        return Ok(FinalizeOutput {
            status: RecordStatus::Failed.as_str().into(),
            pipeline_error: false,
            reason: Some(reason),
        });
    }
    if action.0 != Action::Run {
        return Ok(FinalizeOutput {
            status: "UNCLAIMED".into(),
            pipeline_error: error.is_some(),
            reason: error,
        });
    }
    let run: Option<RunState> = state
        .get("run")
        .and_then(|v| serde_json::from_value(v.clone()).ok());
    finish_run(deps, &submission, run, error).await
}

async fn finish_run<C: Callbacks>(
    deps: &Deps<C>,
    submission: &SubmissionInfo,
    run: Option<RunState>,
    error: Option<String>,
) -> Result<FinalizeOutput> {
    let id = submission.submission_id;
    let target = deps.clients.settings.target(submission.phase_id)?;
    let store = SubmissionStore::new(deps.clients.s3.clone(), &target.deployment.bucket, id);
    let table = SubmissionsTable::new(
        deps.clients.dynamo.clone(),
        &target.deployment.submissions_table,
    );

    // Only the execution that holds the claim ends the run, once: a stale execution (one a
    // resume superseded) must not delete the new run's Jobs or post its own status, and a
    // repeated Finalize reports what stands instead of doing it again.
    let standing = table.standing(submission.team_id, id).await?;
    let holder = standing.as_ref().and_then(|s| s.claimed_by.clone());
    if holder.as_deref() != Some(submission.execution.as_str()) {
        warn!(
            submission_id = id,
            holder = holder.as_deref().unwrap_or("nobody"),
            "another execution holds the submission; nothing done"
        );
        return Ok(FinalizeOutput {
            status: "SUPERSEDED".into(),
            pipeline_error: error.is_some(),
            reason: Some(format!(
                "execution `{}` holds the submission now",
                holder.unwrap_or_default()
            )),
        });
    }
    if let Some(stored) = standing
        .as_ref()
        .and_then(|s| s.status.clone())
        .filter(|s| !RecordStatus::is_in_flight(s))
    {
        info!(submission_id = id, status = %stored, "already finalized; nothing done");
        // An earlier attempt may have ended before it gave the place back.
        leave_queue(deps, submission).await?;
        return Ok(FinalizeOutput {
            status: stored,
            pipeline_error: error.is_some(),
            reason: standing.and_then(|s| s.error),
        });
    }

    // Stop the Jobs first: GPUs cost money, and their logcopy makes its last upload on the way out.
    // Only this execution's Jobs (and unlabelled ones from before the label): a superseded
    // execution never reaches here (the claim check above), and this is the second guard.
    let execution = submission.execution.as_str();
    let cluster = deps.clients.clusters.connect(target.deployment).await?;
    let deleted = cluster.delete_all(&id.to_string(), Some(execution)).await?;
    info!(submission_id = id, ?deleted, "jobs deleted");
    if !cluster
        .wait_gone(
            &id.to_string(),
            Some(execution),
            deps.delete_wait,
            Duration::from_secs(2),
        )
        .await?
    {
        warn!(
            submission_id = id,
            "jobs still terminating; results as they are now"
        );
    }

    let markers = store.markers().await?;
    let cancelled = run
        .as_ref()
        .is_some_and(|r| r.monitor.state == RunPhase::Cancelled)
        || markers.iter().any(|m| m == CANCEL_MARKER);
    let snapshot: Option<std::result::Result<Snapshot, FnError>> = match &run {
        Some(run) => Some(collect(&store, target.leaderboard, &run.pairs, run.repetitions).await),
        None => None,
    };
    // The results could not be read for now: retried, unless the outcome does not need them.
    let snapshot = match snapshot {
        Some(Err(e)) if !cancelled && error.is_none() && e.is_transient() => return Err(e),
        other => other,
    };
    let (mut status, mut reason) = match (&error, &run, &snapshot) {
        _ if cancelled => (SubmissionStatus::Cancelled, None),
        (Some(error), _, _) => {
            warn!(submission_id = id, error = %error, "the run failed");
            (SubmissionStatus::Failed, Some(participant_reason(error)))
        }
        (None, _, Some(Err(e))) if !e.is_transient() => (
            SubmissionStatus::Failed,
            Some(format!("the results cannot be used: {}", e.chain())),
        ),
        (None, Some(run), Some(Ok(snapshot))) => match run.monitor.state {
            RunPhase::Finished if snapshot.complete => (SubmissionStatus::Finished, None),
            RunPhase::Finished => (
                SubmissionStatus::Failed,
                Some(format!(
                    "the evaluation ended with {} of {} routes evaluated",
                    snapshot.progress.0, snapshot.progress.1
                )),
            ),
            _ => (
                SubmissionStatus::Failed,
                Some(
                    run.monitor
                        .reason
                        .clone()
                        .unwrap_or_else(|| "the evaluation failed".into()),
                ),
            ),
        },
        _ => (
            SubmissionStatus::Failed,
            Some("the evaluation did not start".into()),
        ),
    };
    let snapshot = snapshot.and_then(|s| s.ok());
    // A pair that gave up leaves its routes missing; its neighbours' are complete and kept.
    let pairs_note = match (&run, &snapshot) {
        (Some(run), Some(snapshot)) if status == SubmissionStatus::Failed => {
            pairs_note(&run.pairs, &snapshot.finished_pairs)
        }
        _ => None,
    };
    if let Some(note) = &pairs_note {
        reason = reason.map(|r| format!("{r}. {note}"));
    }
    let metrics: Vec<(&'static str, Num)> = snapshot
        .as_ref()
        .map(|s| s.metrics.clone())
        .unwrap_or_default();

    let mut stdout = snapshot
        .as_ref()
        .map(|s| s.files.stdout.clone())
        .unwrap_or_default();
    if status == SubmissionStatus::Finished && target.track_settings.qualifier {
        // As the original: a pass admits the team to the qualifier's target track(s).
        let qualifier = &target.deployment.qualifier;
        let targets = qualifier.targets_of(&submission.track);
        if let Some(first) = targets.first() {
            let (passed, verdict) = qualifier.verdict(first, &metrics);
            if passed {
                let table = QualifierTable::new(
                    deps.clients.dynamo.clone(),
                    &target.deployment.qualifier_table,
                );
                for track in &targets {
                    table.admit(submission.team_id, track, id).await?;
                }
            }
            stdout = format!("{verdict}{stdout}");
        }
    }
    if let Some(note) = &pairs_note {
        stdout = format!("{note}\n\n{stdout}");
    }
    // The participant learns why: the reason, then the end of the agent's own output.
    let mut stderr = reason.clone().unwrap_or_default();
    if status == SubmissionStatus::Failed {
        if let Some((pair, tail)) = agent_log_tail(&store, &markers).await {
            stderr.push_str(&format!(
                "\n\nThe last lines of agent {pair}'s output:\n{tail}\n"
            ));
        }
    }
    let outcome = post(
        deps,
        SubmissionRef {
            challenge: submission.challenge_id,
            phase: submission.phase_id,
            submission: id,
        },
        status,
        snapshot.as_ref(),
        stdout,
        stderr,
    )
    .await?;
    match outcome {
        WriteOutcome::Cancelled => {
            status = SubmissionStatus::Cancelled;
            reason = None;
        }
        // EvalAI already holds a final status (an earlier attempt of this Finalize posted it
        // before failing): that is what stands, and what the record says.
        WriteOutcome::AlreadyFinal(stands) if stands != status => {
            warn!(submission_id = id, %stands, computed = %status, "EvalAI's final status stands");
            if stands == SubmissionStatus::Finished {
                reason = None;
            }
            status = stands;
        }
        _ => {}
    }
    let record_status = match status {
        SubmissionStatus::Finished => RecordStatus::Finished,
        SubmissionStatus::Cancelled => RecordStatus::Cancelled,
        _ => RecordStatus::Failed,
    };
    let written = table
        .finish(
            submission.team_id,
            id,
            &submission.execution,
            &FinalRecord {
                status: record_status,
                end_time: clients::now_record_time(),
                results: store.location(),
                // Every metric of the leaderboard, as EvalAI got it, `-` where it got none.
                metrics: target
                    .leaderboard
                    .metrics()
                    .iter()
                    .map(|m| {
                        let value = metrics.iter().find(|(a, _)| *a == m.attribute);
                        (m.attribute, value.map(|(_, v)| v.py_str()))
                    })
                    .collect(),
                progress: snapshot.as_ref().map_or((0, 0), |s| s.progress),
                // Operators get the whole chain; the participant got `reason`.
                error: error.clone().or_else(|| reason.clone()),
            },
        )
        .await?;
    if !written {
        // Lost the claim while this ran (a resume claimed it anew): EvalAI had the final word
        // before that; the new execution owns the record.
        warn!(
            submission_id = id,
            "the claim moved on; the record is the new execution's"
        );
    }
    info!(
        submission_id = id,
        status = record_status.as_str(),
        "finalized"
    );
    leave_queue(deps, submission).await?;
    Ok(FinalizeOutput {
        status: record_status.as_str().into(),
        pipeline_error: error.is_some(),
        reason,
    })
}

/// Gives the team its place back and takes the submission out of its leaderboard's queue,
/// last: EvalAI has its final status before the team's next submission is admitted, so the
/// team never shows more than its `team_limit` evaluations in progress. Repeating it is
/// harmless.
async fn leave_queue<C: Callbacks>(deps: &Deps<C>, submission: &SubmissionInfo) -> Result<()> {
    if let Some(table) = &deps.clients.admission {
        table
            .release(
                &submission.leaderboard,
                submission.submission_id,
                submission.team_id,
            )
            .await?;
        info!(submission_id = submission.submission_id, "left the queue");
        wake_next(deps, table, submission).await;
    }
    Ok(())
}

/// Wakes the team's next waiting submission, whose turn the place just given back is (see
/// [`queue::wake_team_next`]). Best effort: a failure is logged, and its poll still comes.
async fn wake_next<C: Callbacks>(
    deps: &Deps<C>,
    table: &AdmissionTable,
    submission: &SubmissionInfo,
) {
    let Some(wakes) = &deps.wakes else { return };
    let woken = queue::wake_team_next(
        table,
        wakes,
        &deps.callbacks,
        &submission.leaderboard,
        submission.team_id,
        clients::now_epoch_seconds(),
    )
    .await;
    match woken {
        Ok(woken) => info!(
            submission_id = submission.submission_id,
            ?woken,
            "the team's next submission"
        ),
        Err(e) => {
            warn!(submission_id = submission.submission_id, error = %e, "cannot wake the team's next; its poll comes")
        }
    }
}

/// Bytes read from the end of an agent's log: enough for [`MAX_TAIL_CHARS`] characters of
/// multi-byte text and the escapes that are stripped from it.
const TAIL_BYTES: u64 = 64 * 1024;

/// The agent that crashed most often (the lowest pair on a tie) and the end of its output,
/// cleaned for the participant's page. Its container holds no secret (no AWS credentials, no
/// token), so its own output has none of ours to leak. `None` when no agent crashed or its log
/// cannot be read (the reason alone is posted then).
async fn agent_log_tail(store: &SubmissionStore, markers: &[String]) -> Option<(u32, String)> {
    let mut crashes: std::collections::BTreeMap<u32, u32> = Default::default();
    for name in markers {
        if let Some(Marker::Crash {
            role: Role::Agent,
            pair,
            ..
        }) = Marker::parse(name)
        {
            *crashes.entry(pair).or_default() += 1;
        }
    }
    let pair = crashes
        .iter()
        .max_by_key(|(pair, n)| (**n, std::cmp::Reverse(**pair)))
        .map(|(pair, _)| *pair)?;
    let key = format!("{LOGS_DIR}/{}/agent.log", protocol::agent_logs_dir(pair));
    match store.get_tail(&key, TAIL_BYTES).await {
        Ok(Some(bytes)) => {
            let tail = participant_tail(&bytes, MAX_TAIL_CHARS);
            (!tail.is_empty()).then_some((pair, tail))
        }
        Ok(None) => None,
        Err(e) => {
            warn!(%key, error = %e, "the agent's log could not be read");
            None
        }
    }
}

/// The final EvalAI update: scores for a finished run; for a failed one, the partial summary
/// as stdout and the reason as stderr.
async fn post<C: Callbacks>(
    deps: &Deps<C>,
    at: SubmissionRef,
    status: SubmissionStatus,
    snapshot: Option<&Snapshot>,
    stdout: String,
    stderr: String,
) -> Result<WriteOutcome> {
    let update = FinalUpdate {
        status,
        result: snapshot.map_or_else(|| "[]".to_string(), |s| s.files.results_json()),
        stdout,
        stderr,
        metadata: snapshot
            .and_then(|s| s.files.metadata.clone())
            .unwrap_or_else(|| "{}".into()),
    };
    Ok(deps.clients.evalai.post_final(at, &update).await?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_failed_run_names_the_missing_routes_and_the_complete_ones() {
        let pairs: Vec<PairRoutes> = ["0-4", "5-9", "10-14", "15-19"]
            .iter()
            .zip(1..)
            .map(|(r, id)| PairRoutes {
                id,
                routes: (*r).into(),
            })
            .collect();
        assert_eq!(
            pairs_note(&pairs, &[2, 3, 4]).unwrap(),
            "routes 0-4 (pair 1) were not evaluated; routes 5-9, 10-14, 15-19 (pairs 2, 3, 4) are complete and kept: resuming this submission evaluates only the missing routes"
        );
        assert!(pairs_note(&pairs, &[]).is_none());
        assert!(pairs_note(&pairs, &[1, 2, 3, 4]).is_none());
        assert!(pairs_note(&pairs, &[9]).is_none());
    }
    use serde_json::json;

    #[test]
    fn a_caught_lambda_error_reads_as_its_name_and_message() {
        let state = json!({"error": {"Error": "KubeForbidden",
            "Cause": "{\"errorType\":\"KubeForbidden\",\"errorMessage\":\"jobs.batch is forbidden\"}"}});
        assert_eq!(
            caught_error(&state).unwrap(),
            "KubeForbidden: jobs.batch is forbidden"
        );
        let timeout = json!({"error": {"Error": "States.Timeout", "Cause": ""}});
        assert_eq!(caught_error(&timeout).unwrap(), "States.Timeout");
        assert_eq!(caught_error(&json!({})), None);
    }

    #[test]
    fn participants_read_their_results_problems_but_never_our_internals() {
        let ours = "AwsTransient: dynamodb UpdateItem on `leaderboard-20-submissions` \
                    (arn:aws:iam::123456789012:role/leaderboard-FinalizeRole-X): timed out";
        let reason = participant_reason(ours);
        assert!(reason.contains("(AwsTransient)"), "{reason}");
        for secret in ["arn:aws", "leaderboard-20-submissions", "UpdateItem"] {
            assert!(!reason.contains(secret), "{reason}");
        }
        assert_eq!(
            participant_reason("States.Timeout"),
            participant_reason("States.Timeout: ")
        );
        let theirs = "ResultsInvalid: `worker1.json` field `_checkpoint.records[3].scores.score_route` is negative";
        assert_eq!(
            participant_reason(theirs),
            format!("the evaluation failed: {theirs}")
        );
    }
}
