//! The state machine's payloads: what each Task receives and returns (see
//! `statemachine/submission.asl.json` for where they sit in the state).
//!
//! No secret ever goes in here: payloads are visible in the execution history.

use serde::{Deserialize, Serialize};

pub use lb_domain::run::state::{
    bounded_reason, printable_bounded, MonitorState, PairRoutes, QueueState, RunPhase, RunState,
    MAX_REASON_BYTES,
};

/// The largest submission message the queue accepts (its `MaximumMessageSize` in
/// `infra/app.yaml`). The message stays in the execution's state to the end.
pub const MAX_MESSAGE_BYTES: usize = 16 * 1024;

/// Intake's input: the Pipe's message and the execution's name (who claims).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IntakeInput {
    /// The EventBridge Pipe's output, validated by Intake.
    pub message: serde_json::Value,
    /// `$$.Execution.Name`.
    pub execution: String,
}

impl crate::serve::Invocation for IntakeInput {
    fn execution(&self) -> Option<&str> {
        Some(&self.execution)
    }
}

/// What Intake decided (`$.intake`): a run carries a complete submission (its image pinned, its
/// pairs counted); a skip or a refusal carries its reason and the submission as far as it was
/// known. In the state it keeps the shape the Choice after Intake and earlier versions read
/// ([`IntakeOutput`]); a run or a refusal without its submission does not decode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "IntakeOutput", into = "IntakeOutput")]
pub enum Decision {
    /// Evaluate it.
    Run(SubmissionInfo),
    /// Not ours to run (its status, a duplicate): end without touching anything.
    Skip {
        reason: String,
        /// Absent when skipped before EvalAI was read.
        submission: Option<SubmissionInfo>,
    },
    /// Refuse it with a message to the participant (not qualified, no image).
    Reject {
        reason: String,
        submission: SubmissionInfo,
    },
}

impl Decision {
    /// The word the state machine's Choice branches on.
    pub fn action(&self) -> Action {
        match self {
            Decision::Run(_) => Action::Run,
            Decision::Skip { .. } => Action::Skip,
            Decision::Reject { .. } => Action::Reject,
        }
    }

    /// Why it is skipped or refused.
    pub fn reason(&self) -> Option<&str> {
        match self {
            Decision::Run(_) => None,
            Decision::Skip { reason, .. } | Decision::Reject { reason, .. } => Some(reason),
        }
    }

    /// The submission, where it is known.
    pub fn submission(&self) -> Option<&SubmissionInfo> {
        match self {
            Decision::Run(submission) | Decision::Reject { submission, .. } => Some(submission),
            Decision::Skip { submission, .. } => submission.as_ref(),
        }
    }
}

impl TryFrom<IntakeOutput> for Decision {
    type Error = String;

    fn try_from(wire: IntakeOutput) -> Result<Decision, String> {
        Ok(match (wire.action, wire.submission) {
            (Action::Run, Some(submission)) if submission.is_complete() => {
                Decision::Run(submission)
            }
            (Action::Run, _) => {
                return Err("a run decision needs the whole submission (image and pairs)".into())
            }
            (Action::Skip, submission) => Decision::Skip {
                reason: wire.reason.unwrap_or_else(|| "skipped".into()),
                submission,
            },
            (Action::Reject, Some(submission)) => Decision::Reject {
                reason: wire
                    .reason
                    .unwrap_or_else(|| "the submission was refused".into()),
                submission,
            },
            (Action::Reject, None) => return Err("a refusal needs the submission".into()),
        })
    }
}

impl From<Decision> for IntakeOutput {
    fn from(decision: Decision) -> IntakeOutput {
        let action = decision.action();
        let (reason, submission) = match decision {
            Decision::Run(submission) => (None, Some(submission)),
            Decision::Skip { reason, submission } => (Some(reason), submission),
            Decision::Reject { reason, submission } => (Some(reason), Some(submission)),
        };
        IntakeOutput {
            action,
            reason,
            submission,
        }
    }
}

/// [`Decision`]'s shape in the state (`{action, reason, submission}`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IntakeOutput {
    /// The Choice after Intake branches on it.
    pub action: Action,
    /// Why, in words (skip and reject).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        serialize_with = "bounded_reason"
    )]
    pub reason: Option<String>,
    /// The submission, once known (absent when skipped before the EvalAI read).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub submission: Option<SubmissionInfo>,
}

/// Intake's decision.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Action {
    /// Evaluate it.
    Run,
    /// Not ours to run (status, duplicate): end without touching anything.
    Skip,
    /// Refuse it with a message to the participant (not qualified, no image).
    Reject,
}

/// A continued execution's input, as `ContinueAsNew` starts it and `Resume` unpacks it: the run
/// crosses from one execution (and, through the alias, possibly one release) to the next here.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ContinuedInput {
    pub continued: Continued,
}

/// What a continued execution carries on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Continued {
    /// Intake's decision, as the first execution made it.
    pub intake: Decision,
    /// The run as the last round left it.
    pub run: RunState,
    /// The execution it continues (`$$.Execution.Name`).
    pub from: String,
}

/// The execution state as the finished or failed path hands it to Finalize (`{"state.$": "$"}`),
/// typed: what Intake decided, the run, and the error a Catch put there. The state's other keys
/// are not Finalize's. A part that does not decode is an invalid input, named, never read as
/// "absent": a run state dropped for a decode error would read as an evaluation that never
/// started.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ExecutionState {
    /// Intake's decision (`$.intake`); absent when the execution failed before it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub intake: Option<Decision>,
    /// The run (`$.run`); absent before Launch.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub run: Option<RunState>,
    /// The error a Catch put at `$.error` (`{"Error", "Cause"}`, as Step Functions writes it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<serde_json::Value>,
}

impl ExecutionState {
    /// The state from its JSON, or an `InvalidInput` error naming the part that is wrong.
    pub fn from_value(state: serde_json::Value) -> crate::Result<ExecutionState> {
        serde_path_to_error::deserialize(state).map_err(|e| {
            crate::FnError::RunState(format!(
                "the execution state at `{}`: {}",
                e.path(),
                e.inner()
            ))
        })
    }

    /// The caught error in words (`Name: message`), if a Catch put one there.
    pub fn caught_error(&self) -> Option<String> {
        self.error.as_ref().map(lb_domain::run::finalize::caught)
    }
}

pub use lb_domain::submission::SubmissionInfo;
