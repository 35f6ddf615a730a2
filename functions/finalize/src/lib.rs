//! Finalize (stage 5 and the failure path): decide the final status, make the final merge,
//! record the qualifier outcome, post the final update to EvalAI (confirmed by a GET), write
//! the final DynamoDB record and delete the Jobs.
//!
//! It only ever acts on a submission this execution claimed (or rejected): an execution that
//! failed before its claim must not touch a submission another execution is evaluating.
//! Every step is idempotent, so the state machine can retry it.

pub mod reaper;

use aws_lambda_events::event::eventbridge::EventBridgeEvent;
use lb_aws::executions::Executions;
use lb_pipeline::serve::{Function, Invocation};
use std::time::Duration;

use aws_config::SdkConfig;
use lb_aws::dynamo::{FinalRecord, QualifierTable, RecordStatus, SubmissionsTable};
use lb_aws::s3::{SubmissionStore, CANCEL_MARKER};
use lb_aws::tasks::{Callbacks, StepFunctions};
use lb_aws::wake::WakeTable;
use lb_domain::cost::{self, Totals};
use std::collections::HashSet;

use lb_domain::audit;
use lb_domain::finalize::{self, Outcome, Posted};
use lb_domain::logtail::{participant_tail, MAX_TAIL_CHARS};
use lb_domain::protocol::{self, LOGS_DIR};
use lb_domain::settings::Target;
use lb_domain::status::Settled;
use lb_domain::submission::SubmissionStatus;
use lb_evalai::{FinalUpdate, SubmissionRef, WriteOutcome};
use lb_pipeline::clients::{self, RunClients};
use lb_pipeline::cluster::Clusters;
use lb_pipeline::payload::{
    Action, ExecutionState, IntakeOutput, RunPhase, RunState, SubmissionInfo,
};
use lb_pipeline::queue;
use lb_pipeline::results::{collect, Snapshot};
use lb_pipeline::{FunctionConfig, Result};
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
    pub state: ExecutionState,
}

/// What Finalize did (`$.final`; the Choice after it reads `pipeline_error`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FinalizeOutput {
    /// The submission's final status on our side (for a repeated Finalize, the one that
    /// stands), or why this execution touched nothing of it.
    pub status: Settled,
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

impl FinalizeInput {
    /// The state's submission, once Intake knew it.
    fn submission(&self) -> Option<&SubmissionInfo> {
        self.state.intake.as_ref()?.submission.as_ref()
    }
}

impl Invocation for FinalizeInput {
    fn submission_id(&self) -> Option<u64> {
        Some(self.submission()?.submission_id)
    }
    fn execution(&self) -> Option<&str> {
        Some(&self.submission()?.execution)
    }
}

/// What Finalize is asked: by the state machine, or as the reaper (`reaper`). Told apart by
/// their one distinguishing key, so a malformed one is refused with its own field's error
/// (an untagged enum would only say that nothing matched).
#[derive(Debug, Clone)]
pub enum Request {
    /// The state machine's Finalize task (boxed: the typed state is large).
    State(Box<FinalizeInput>),
    /// The scheduled pass over held places.
    Reconcile(reaper::ReconcileInput),
    /// Step Functions' "Execution Status Change", through EventBridge (boxed: large too).
    Event(Box<EventBridgeEvent<Value>>),
}

impl<'de> Deserialize<'de> for Request {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        use serde::de::Error;
        let value = Value::deserialize(d)?;
        let has = |key: &str| value.get(key).is_some();
        if has("state") {
            FinalizeInput::deserialize(value).map(|input| Request::State(Box::new(input)))
        } else if has("reconcile") {
            reaper::ReconcileInput::deserialize(value).map(Request::Reconcile)
        } else if has("detail-type") {
            EventBridgeEvent::deserialize(value).map(|event| Request::Event(Box::new(event)))
        } else {
            return Err(D::Error::custom(
                "expected the state machine's `{\"state\": ...}`, the schedule's \
                 `{\"reconcile\": ...}` or an EventBridge event with a `detail-type`",
            ));
        }
        .map_err(D::Error::custom)
    }
}

impl Invocation for Request {
    fn submission_id(&self) -> Option<u64> {
        match self {
            Request::State(input) => input.submission_id(),
            _ => None,
        }
    }
    fn execution(&self) -> Option<&str> {
        match self {
            Request::State(input) => input.execution(),
            _ => None,
        }
    }
}

/// What Finalize answers each [`Request`].
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Response {
    /// To the state machine.
    Finalized(FinalizeOutput),
    /// What the reaper did, execution by execution.
    Reaped(Vec<reaper::Reaped>),
}

impl<C: Callbacks + Executions> Function for Deps<C> {
    const NAME: &'static str = "finalize";
    type Input = Request;
    type Output = Response;
    async fn handle(&self, input: Request) -> Result<Response> {
        Ok(match input {
            Request::State(input) => Response::Finalized(handle(*input, self).await?),
            Request::Reconcile(input) => Response::Reaped(reaper::reconcile(input, self).await?),
            Request::Event(event) => Response::Reaped(vec![reaper::on_event(*event, self).await?]),
        })
    }
}

/// Ends one execution.
pub async fn handle<C: Callbacks>(input: FinalizeInput, deps: &Deps<C>) -> Result<FinalizeOutput> {
    let state = input.state;
    let error = state.caught_error();
    let (action, submission) = match state.intake {
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
                status: Settled::Unclaimed,
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
            status: Settled::Ended(RecordStatus::Failed),
            pipeline_error: false,
            reason: Some(reason),
        });
    }
    if action.0 != Action::Run {
        return Ok(FinalizeOutput {
            status: Settled::Unclaimed,
            pipeline_error: error.is_some(),
            reason: error,
        });
    }
    finish_run(deps, &submission, state.run, error).await
}

async fn finish_run<C: Callbacks>(
    deps: &Deps<C>,
    submission: &SubmissionInfo,
    run: Option<RunState>,
    error: Option<String>,
) -> Result<FinalizeOutput> {
    let id = submission.submission_id;
    let meter = clients::Meter::start(&deps.clients.dynamo_requests, deps.clients.memory_mb);
    let target = deps.clients.settings.target(submission.phase_id)?;
    let store = SubmissionStore::new(deps.clients.s3.clone(), &target.deployment.bucket, id);
    let submissions = &target.deployment.submissions_table;
    let table = SubmissionsTable::new(deps.clients.dynamo.clone(), submissions);
    let ended = |status: Settled, reason| FinalizeOutput {
        status,
        pipeline_error: error.is_some(),
        reason,
    };
    if let Some((status, reason)) = already_ended(deps, &table, submission).await? {
        return Ok(ended(status, reason));
    }
    stop_jobs(deps, &target, submission).await?;
    let (markers, snapshot) = read_left(&store, &target, run.as_ref()).await;
    let markers = markers?;
    let cancelled = run
        .as_ref()
        .is_some_and(|r| r.monitor.state == RunPhase::Cancelled)
        || markers.iter().any(|m| m == CANCEL_MARKER);
    // The results could not be read for now: retried, unless the outcome does not need them.
    let snapshot = match snapshot {
        Some(Err(e)) if !cancelled && error.is_none() && e.is_transient() => return Err(e),
        other => other,
    };
    let (outcome, snapshot) = decide(cancelled, error.as_deref(), run.as_ref(), snapshot);
    let summary = snapshot.as_ref().map_or("", |s| s.files.stdout.as_str());
    let tail = async {
        match outcome.status {
            SubmissionStatus::Failed => agent_log_tail(&store, &markers).await,
            _ => None,
        }
    };
    let qualified = qualify(deps, &target, submission, &outcome, snapshot.as_ref());
    let (verdict, tail) = tokio::join!(qualified, tail);
    let verdict = verdict?;
    let stdout = finalize::stdout(outcome.pairs_note.as_deref(), verdict.as_deref(), summary);
    let stderr = finalize::stderr(&outcome, tail.as_ref().map(|(p, t)| (*p, t.as_str())));
    let at = SubmissionRef {
        challenge: submission.challenge_id,
        phase: submission.phase_id,
        submission: id,
    };
    let posted = post(deps, at, outcome.status, snapshot.as_ref(), stdout, stderr).await?;
    let outcome = finalize::settle(outcome, posted);
    let mut record = final_record(&target, &store, &outcome, snapshot.as_ref(), error.clone());
    record.recordings = recordings(&store, &outcome, snapshot.as_ref()).await;
    record.usage = run.as_ref().map(|run| usage(deps, run, &meter));
    if !table
        .finish(submission.team_id, id, &submission.execution, &record)
        .await?
    {
        // Lost the claim while this ran (a resume claimed it anew): EvalAI had the final word
        // before that; the new execution owns the record.
        warn!(
            submission_id = id,
            "the claim moved on; the record is the new execution's"
        );
    }
    info!(
        submission_id = id,
        status = record.status.as_str(),
        "finalized"
    );
    if record.status == RecordStatus::Finished {
        record_pace(deps, submission, run.as_ref()).await;
    }
    leave_queue(deps, submission).await?;
    Ok(ended(Settled::Ended(record.status), outcome.reason))
}

/// What the run left, read at once (the reads are independent): its markers, and its results
/// when it had a run.
async fn read_left(
    store: &SubmissionStore,
    target: &Target<'_>,
    run: Option<&RunState>,
) -> (Result<Vec<String>>, Option<Result<Snapshot>>) {
    let results = async {
        match run {
            Some(run) => {
                Some(collect(store, target.leaderboard, &run.pairs, run.repetitions).await)
            }
            None => None,
        }
    };
    let (markers, snapshot) = tokio::join!(store.markers(), results);
    (markers.map_err(Into::into), snapshot)
}

/// What stands when this execution must not end the run: another holds the claim, or an
/// earlier attempt of this Finalize already ended it (`None`: end it now). Only the execution
/// that holds the claim ends the run, once: a stale one (a resume superseded it) must not
/// delete the new run's Jobs or post its own status, and a repeated one reports what stands.
async fn already_ended<C: Callbacks>(
    deps: &Deps<C>,
    table: &SubmissionsTable,
    submission: &SubmissionInfo,
) -> Result<Option<(Settled, Option<String>)>> {
    let id = submission.submission_id;
    let standing = table.standing(submission.team_id, id).await?;
    let holder = standing.as_ref().and_then(|s| s.claimed_by.as_deref());
    if let Some(why) = finalize::superseded(holder, &submission.execution) {
        warn!(submission_id = id, %why, "nothing done");
        return Ok(Some((Settled::Superseded, Some(why))));
    }
    let Some((status, error)) =
        standing.and_then(|s| Some((s.status.filter(|status| !status.is_in_flight())?, s.error)))
    else {
        return Ok(None);
    };
    info!(submission_id = id, %status, "already finalized; nothing done");
    // An earlier attempt may have ended before it gave the place back.
    leave_queue(deps, submission).await?;
    Ok(Some((Settled::Ended(status), error)))
}

/// The final status from what the run left (`lb_domain::finalize::outcome`), and the
/// results when they could be read.
fn decide(
    cancelled: bool,
    caught: Option<&str>,
    run: Option<&RunState>,
    snapshot: Option<Result<Snapshot>>,
) -> (Outcome, Option<Snapshot>) {
    if let Some(caught) = caught {
        warn!(error = %caught, "the run failed");
    }
    let problem = match &snapshot {
        Some(Err(e)) => e.chain(),
        _ => String::new(),
    };
    let pairs: Vec<(u32, &str)> = run
        .map(|r| r.pairs.iter().map(|p| (p.id, p.routes.as_str())).collect())
        .unwrap_or_default();
    let outcome = {
        let run = match (run, &snapshot) {
            (Some(run), Some(read)) => Some(finalize::Run {
                finished: run.monitor.state == RunPhase::Finished,
                reason: run.monitor.reason.as_deref(),
                pairs: &pairs,
                results: match read {
                    Ok(s) => Ok(finalize::Results {
                        complete: s.complete,
                        progress: s.progress,
                        finished_pairs: &s.finished_pairs,
                    }),
                    Err(_) => Err(problem.as_str()),
                },
            }),
            _ => None,
        };
        finalize::outcome(&finalize::Facts {
            cancelled,
            caught,
            run,
        })
    };
    (outcome, snapshot.and_then(|s| s.ok()))
}

/// Stops the Jobs first: GPUs cost money, and their logcopy makes its last upload on the way
/// out. Only this execution's Jobs (and unlabelled ones from before the label): a superseded
/// execution never gets here (the claim check), and this is the second guard.
async fn stop_jobs<C: Callbacks>(
    deps: &Deps<C>,
    target: &Target<'_>,
    submission: &SubmissionInfo,
) -> Result<()> {
    let (id, execution) = (
        submission.submission_id,
        Some(submission.execution.as_str()),
    );
    let cluster = deps.clients.clusters.connect(target.deployment).await?;
    let deleted = cluster.delete_all(&id.to_string(), execution).await?;
    info!(submission_id = id, ?deleted, "jobs deleted");
    let poll = Duration::from_secs(2);
    if !cluster
        .wait_gone(&id.to_string(), execution, deps.delete_wait, poll)
        .await?
    {
        warn!(
            submission_id = id,
            "jobs still terminating; results as they are now"
        );
    }
    Ok(())
}

/// A finished qualifier run: as the original, a pass admits the team to the qualifier's target
/// track(s); the verdict heads the participant's stdout either way.
async fn qualify<C: Callbacks>(
    deps: &Deps<C>,
    target: &Target<'_>,
    submission: &SubmissionInfo,
    outcome: &Outcome,
    snapshot: Option<&Snapshot>,
) -> Result<Option<String>> {
    if outcome.status != SubmissionStatus::Finished || !target.track_settings.qualifier {
        return Ok(None);
    }
    let qualifier = &target.deployment.qualifier;
    let targets = qualifier.targets_of(&submission.track);
    let Some(first) = targets.first() else {
        return Ok(None);
    };
    let metrics = snapshot.map(|s| s.metrics.as_slice()).unwrap_or_default();
    let (passed, verdict) = qualifier.verdict(first, metrics);
    if passed {
        let table = &target.deployment.qualifier_table;
        let table = QualifierTable::new(deps.clients.dynamo.clone(), table);
        for track in &targets {
            table
                .admit(submission.team_id, track, submission.submission_id)
                .await?;
        }
    }
    Ok(Some(verdict))
}

/// The record Finalize writes: every metric of the leaderboard as EvalAI got it (`-` where it
/// got none); operators get the whole error chain, the participant got the outcome's reason.
fn final_record(
    target: &Target<'_>,
    store: &SubmissionStore,
    outcome: &Outcome,
    snapshot: Option<&Snapshot>,
    error: Option<String>,
) -> FinalRecord {
    let metrics = snapshot.map(|s| s.metrics.as_slice()).unwrap_or_default();
    FinalRecord {
        status: match outcome.status {
            SubmissionStatus::Finished => RecordStatus::Finished,
            SubmissionStatus::Cancelled => RecordStatus::Cancelled,
            _ => RecordStatus::Failed,
        },
        end_time: clients::now_record_time(),
        results: store.location(),
        metrics: target
            .leaderboard
            .metrics()
            .iter()
            .map(|m| {
                let value = metrics.iter().find(|(a, _)| *a == m.attribute);
                (m.attribute, value.map(|(_, v)| v.py_str()))
            })
            .collect(),
        progress: snapshot.map_or((0, 0), |s| s.progress),
        error: error.or_else(|| outcome.reason.clone()),
        recordings: None,
        usage: None,
    }
}

/// What the run's GPUs came to: the Monitor's count, with the pods still running at its last
/// round charged until now (their Jobs were just deleted); and the orchestration's, this
/// Finalize so far and the states after it included.
fn usage<C: Callbacks>(deps: &Deps<C>, run: &RunState, meter: &clients::Meter<'_>) -> Totals {
    let mut ledger = run.monitor.usage.clone();
    ledger.close_all(clients::now_epoch_seconds());
    let this = meter.invocation(cost::CLOSING_TRANSITIONS);
    Totals {
        orchestration: Some(run.monitor.orchestration + this),
        ..ledger.summary(&deps.clients.settings.prices)
    }
}

/// What operators can audit of a FINISHED result: how many of its routes have their CARLA
/// recording in S3 (`lb_domain::audit`). `None` for another outcome, or when the logs could
/// not be listed (the record then says nothing rather than something wrong).
async fn recordings(
    store: &SubmissionStore,
    outcome: &Outcome,
    snapshot: Option<&Snapshot>,
) -> Option<(u64, u64)> {
    if outcome.status != SubmissionStatus::Finished {
        return None;
    }
    let snapshot = snapshot?;
    let logs = match store.logs().await {
        Ok(logs) => logs,
        Err(e) => {
            warn!(error = %e, "logs not listed: the recordings are not counted");
            return None;
        }
    };
    let present: HashSet<&str> = logs
        .iter()
        .filter(|(_, size)| *size > 0)
        .filter_map(|(key, _)| audit::recording_of(key))
        .collect();
    let expected = audit::expected_recordings(snapshot.route_ids.iter().map(String::as_str));
    let counted = audit::audit(&expected, &present);
    if !counted.complete() {
        warn!(
            found = counted.found,
            expected = counted.expected,
            missing = ?counted.missing,
            "FINISHED without every route's CARLA recording: these scores cannot be audited"
        );
    }
    Some((counted.found, counted.expected))
}

/// Gives the team its place back and takes the submission out of its leaderboard's queue,
/// last: EvalAI has its final status before the team's next submission is admitted, so the
/// team never shows more than its `team_limit` evaluations in progress. Repeating it is
/// harmless.
async fn leave_queue<C: Callbacks>(deps: &Deps<C>, submission: &SubmissionInfo) -> Result<()> {
    let admission = &deps.clients.admission;
    if admission.release(submission).await? {
        info!(submission_id = submission.submission_id, "left the queue");
        wake_next(deps, submission).await;
    }
    Ok(())
}

/// A finished evaluation's duration, from its first pair's start, joins its track's pace (the
/// queue note's estimate). Best effort: a failure is logged.
async fn record_pace<C: Callbacks>(
    deps: &Deps<C>,
    submission: &SubmissionInfo,
    run: Option<&RunState>,
) {
    let Some(started) = run.and_then(|r| r.monitor.started_at) else {
        return;
    };
    let seconds = clients::now_epoch_seconds().saturating_sub(started);
    let recorded = deps
        .clients
        .admission
        .record_pace(submission, seconds)
        .await;
    if let Err(e) = recorded {
        warn!(submission_id = submission.submission_id, error = %e, "pace not recorded");
    }
}

/// Wakes the team's next waiting submissions, one per open place (see
/// [`queue::wake_team_next`]). Best effort: a failure is logged, and its poll still comes.
async fn wake_next<C: Callbacks>(deps: &Deps<C>, submission: &SubmissionInfo) {
    let (Some(table), Some(wakes)) = (deps.clients.admission.table(), &deps.wakes) else {
        return;
    };
    let limit = match deps.clients.settings.target(submission.phase_id) {
        Ok(target) => target.deployment.team_limit,
        Err(e) => {
            warn!(submission_id = submission.submission_id, error = %e, "cannot wake the team's next; its poll comes");
            return;
        }
    };
    let woken = queue::wake_team_next(
        table,
        wakes,
        &deps.callbacks,
        (submission.leaderboard.as_str(), submission.team_id, limit),
        clients::now_epoch_seconds(),
    )
    .await;
    match woken {
        Ok(woken) => info!(
            submission_id = submission.submission_id,
            ?woken,
            "the team's next submissions"
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
    let pair = finalize::most_crashed_agent(markers.iter().map(String::as_str))?;
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
) -> Result<Posted> {
    let update = FinalUpdate {
        status,
        result: snapshot.map_or_else(|| "[]".to_string(), |s| s.files.results_json()),
        stdout,
        stderr,
        metadata: snapshot
            .and_then(|s| s.files.metadata.clone())
            .unwrap_or_else(|| "{}".into()),
    };
    Ok(match deps.clients.evalai.post_final(at, &update).await? {
        WriteOutcome::Written => Posted::Written,
        WriteOutcome::Cancelled => Posted::Cancelled,
        WriteOutcome::AlreadyFinal(stands) => Posted::AlreadyFinal(stands),
    })
}

#[cfg(test)]
mod tests {
    use super::Request;
    use serde_json::json;

    #[test]
    fn each_request_is_told_apart_by_its_key_and_a_bad_one_names_its_field() {
        let state = serde_json::from_value::<Request>(json!({"state": {"message": {}}}));
        assert!(matches!(state, Ok(Request::State(_))));
        // A part of the state that does not decode is refused, not read as absent: a run
        // state dropped here would read as an evaluation that never started.
        let bad_run = json!({"state": {"run": {"jobs": 1, "monitor": {}}}});
        let err = lb_pipeline::FnError::decode::<Request>("finalize", bad_run).unwrap_err();
        assert_eq!(err.name(), "InvalidInput");
        assert!(err.chain().contains("missing field"), "{}", err.chain());
        let err = lb_pipeline::payload::ExecutionState::from_value(
            json!({"intake": {"action": "maybe"}}),
        )
        .unwrap_err();
        assert_eq!(err.name(), "InvalidInput");
        assert!(err.to_string().contains("`intake.action`"), "{err}");
        let reconcile =
            json!({"reconcile": {"state_machine": "arn:aws:states:us-east-1:1:stateMachine:s"}});
        assert!(matches!(
            serde_json::from_value::<Request>(reconcile),
            Ok(Request::Reconcile(_))
        ));
        let extra = serde_json::from_value::<Request>(json!({"state": {}, "extra": 1}));
        assert!(extra.unwrap_err().to_string().contains("extra"));
        let none = serde_json::from_value::<Request>(json!({"nothing": 1}));
        assert!(none.unwrap_err().to_string().contains("detail-type"));
    }
}
