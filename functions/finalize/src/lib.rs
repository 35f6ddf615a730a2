//! Finalize (stage 5 and the failure path): end a claimed run in the order
//! `lb_domain::run::closing` decides: read the claim while this execution's Jobs stop, read what
//! the run left and decide the final status, post the final update to EvalAI (confirmed by a
//! GET), then write the final DynamoDB record and give the team's place back.
//!
//! It only ever acts on a submission this execution claimed (or rejected): an execution that
//! failed before its claim must not touch a submission another execution is evaluating.
//! Every step is idempotent, so the state machine can retry it.

mod io;
pub mod reaper;

use std::time::Duration;

use aws_config::SdkConfig;
use aws_lambda_events::event::eventbridge::EventBridgeEvent;
use lb_aws::dynamo::RecordStatus;
use lb_aws::executions::Executions;
use lb_aws::tasks::{Callbacks, StepFunctions};
use lb_aws::wake::WakeTable;
use lb_domain::run::closing::{Closing, Context, Settlement};
use lb_domain::run::metrics::{self, Signals};
use lb_domain::status::Settled;
use lb_domain::submission::SubmissionStatus;
use lb_pipeline::clients::{self, RunClients};
use lb_pipeline::cluster::Clusters;
use lb_pipeline::payload::{Decision, ExecutionState, RunState, SubmissionInfo};
use lb_pipeline::serve::{Function, Invocation};
use lb_pipeline::{FunctionConfig, Result};
use serde::{Deserialize, Serialize};
use serde_json::Value;
use tracing::warn;

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
    pub wakes: WakeTable,
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
        let wakes = WakeTable::new(clients.dynamo.clone(), config.wake_table()?);
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
#[derive(Debug, Clone, Serialize, Deserialize)]
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
    /// The submission failed for the platform's own failure (its reclaims past a pair's free
    /// ones), not the participant's: the execution ends as failed too, apart.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub platform_failure: bool,
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
        self.state.intake.as_ref()?.submission()
    }
}

impl Invocation for FinalizeInput {
    fn submission_id(&self) -> Option<u64> {
        Some(self.submission()?.submission_id)
    }
    fn execution(&self) -> Option<&str> {
        Some(&self.submission()?.execution)
    }
    fn leaderboard(&self) -> Option<lb_domain::results::Leaderboard> {
        Some(self.submission()?.leaderboard)
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
    fn leaderboard(&self) -> Option<lb_domain::results::Leaderboard> {
        match self {
            Request::State(input) => input.leaderboard(),
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

/// Ends one execution, as Intake decided: a claimed run is closed, a refusal told to EvalAI, a
/// skip left alone.
pub async fn handle<C: Callbacks>(input: FinalizeInput, deps: &Deps<C>) -> Result<FinalizeOutput> {
    let state = input.state;
    let error = state.caught_error();
    match state.intake {
        Some(Decision::Run(submission)) => finish_run(deps, &submission, state.run, error).await,
        Some(Decision::Reject { reason, submission }) => refuse(deps, &submission, reason).await,
        Some(Decision::Skip {
            submission: Some(_),
            ..
        }) => Ok(FinalizeOutput {
            status: Settled::Unclaimed,
            pipeline_error: error.is_some(),
            platform_failure: false,
            reason: error,
        }),
        Some(Decision::Skip {
            submission: None, ..
        })
        | None => {
            // NB: not ours. Telling EvalAI or deleting Jobs here could end another
            // execution's evaluation of the same submission.
            warn!(
                error = error.as_deref().unwrap_or_default(),
                "failed before claiming a submission"
            );
            Ok(FinalizeOutput {
                status: Settled::Unclaimed,
                pipeline_error: true,
                platform_failure: false,
                reason: error,
            })
        }
    }
}

/// Tells EvalAI that Intake refused the submission, and why.
async fn refuse<C>(
    deps: &Deps<C>,
    submission: &SubmissionInfo,
    reason: String,
) -> Result<FinalizeOutput> {
    let failed = io::FinalWord {
        status: SubmissionStatus::Failed,
        stdout: String::new(),
        stderr: reason.clone(),
    };
    io::post_final(deps, submission, failed).await?;
    let mut end = Signals::default();
    end.ended(
        RecordStatus::Failed.as_str(),
        Some(metrics::reason::REFUSED),
    );
    lb_pipeline::metrics::record(end);
    Ok(FinalizeOutput {
        status: Settled::Ended(RecordStatus::Failed),
        pipeline_error: false,
        platform_failure: false,
        reason: Some(reason),
    })
}

/// Ends a claimed run: `lb_domain::run::closing` decides each step and its order, the shell
/// performs it and answers.
async fn finish_run<C: Callbacks>(
    deps: &Deps<C>,
    submission: &SubmissionInfo,
    run: Option<RunState>,
    error: Option<String>,
) -> Result<FinalizeOutput> {
    if let Some(caught) = &error {
        warn!(error = %caught, "the run failed");
    }
    let meter = clients::Meter::start(&deps.clients.dynamo_requests, deps.clients.memory_mb);
    let target = deps.clients.settings.target(submission.phase_id)?;
    let mut closing = Closing::begin(Context {
        execution: &submission.execution,
        caught: error.as_deref(),
        run: run.as_ref(),
        track: &submission.track,
        qualifier: (target.track_settings.qualifier).then_some(&target.deployment.qualifier),
        route_lengths: &target.track_settings.route_lengths,
        now: clients::now_epoch_seconds(),
        prices: &deps.clients.settings.prices,
    });
    let mut shell = io::Shell::new(deps, &target, submission, &meter);
    loop {
        let batch = closing.poll();
        if batch.is_empty() {
            break;
        }
        closing.answer(Box::pin(shell.perform(batch)).await?);
    }
    let id = submission.submission_id;
    let Some(Settlement {
        status,
        reason,
        by_platform,
    }) = closing.finish()
    else {
        // Only a shell that answered out of turn gets here: operators must see it.
        let why = "Finalize ended before it decided the final status";
        warn!(submission_id = id, why, "a bug in Finalize's shell");
        return Ok(FinalizeOutput {
            status: Settled::Unclaimed,
            pipeline_error: true,
            platform_failure: false,
            reason: Some(why.into()),
        });
    };
    if status == Settled::Superseded {
        warn!(submission_id = id, why = reason.as_deref(), "nothing done");
    }
    if let Settled::Ended(ended) = status {
        let failure = run.as_ref().and_then(|r| r.monitor.failure);
        lb_pipeline::metrics::record(metrics::ending(ended, failure, error.is_some()));
    }
    Ok(FinalizeOutput {
        status,
        pipeline_error: error.is_some(),
        platform_failure: by_platform,
        reason,
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
