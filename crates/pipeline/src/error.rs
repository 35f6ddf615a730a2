//! The functions' error: every variant has the stable name the state machine's `ErrorEquals`
//! matches, and becomes a Lambda `Diagnostic` with that name as `errorType`.

use lb_aws::AwsError;
use lb_cluster::ClusterError;
use lb_domain::job::plan::PlanError;
use lb_domain::results::ResultsError;
use lb_domain::settings::SettingsError;
use lb_domain::submission::MessageError;
use lb_evalai::EvalAiError;
use lb_jobs::{ContextError, RenderError};

/// Result alias of the functions.
pub type Result<T, E = FnError> = std::result::Result<T, E>;

/// Why a function failed. Each adapter's error travels whole (its source kept) and under its
/// own stable name; the few failures that belong to a stage are variants here.
#[derive(Debug, thiserror::Error)]
pub enum FnError {
    /// The submission message is malformed.
    #[error(transparent)]
    Message(#[from] MessageError),
    /// The configuration does not cover this submission, or is broken.
    #[error(transparent)]
    Settings(#[from] SettingsError),
    /// EvalAI refused, failed or answered nonsense.
    #[error(transparent)]
    EvalAi(#[from] EvalAiError),
    /// An AWS call failed.
    #[error(transparent)]
    Aws(#[from] AwsError),
    /// The Job cluster refused or failed.
    #[error(transparent)]
    Cluster(#[from] ClusterError),
    /// The workers' results cannot be used.
    #[error(transparent)]
    Results(#[from] ResultsError),
    /// The routes cannot be planned over the workers.
    #[error(transparent)]
    Plan(#[from] PlanError),
    /// The leaderboard's settings cannot fill the Job template.
    #[error(transparent)]
    JobSettings(#[from] ContextError),
    /// The Job template cannot be rendered.
    #[error(transparent)]
    Render(#[from] RenderError),
    /// The function's input is not what the state machine sends.
    #[error("invalid {what} input")]
    Input {
        /// Which function's input.
        what: &'static str,
        /// Where and why it does not decode.
        #[source]
        source: serde_json::Error,
    },
    /// A run state carried from an earlier stage holds a value no stage writes.
    #[error("invalid run state: {0}")]
    RunState(String),
    /// The function's output cannot be serialised (a defect: every output is plain data).
    #[error("the {what} output cannot be serialized")]
    Output {
        /// Which function's output.
        what: &'static str,
        /// serde_json's reason.
        #[source]
        source: serde_json::Error,
    },
    /// The function's environment is incomplete.
    #[error("invalid function configuration: {0}")]
    Config(String),
    /// The invocation's time ran out before its calls ended (they were cut short on purpose,
    /// before Lambda's own timeout).
    #[error("the invocation's time ran out before its calls ended")]
    DeadlineExceeded,
    /// EvalAI has the submission in another phase than the message says.
    #[error("the message says phase `{message}` but EvalAI has submission `{submission}` in phase `{evalai}`")]
    PhaseMismatch {
        /// The message's phase.
        message: u64,
        /// The submission.
        submission: u64,
        /// EvalAI's phase.
        evalai: u64,
    },
    /// A sweep did what it could; these challenges or wake-ups failed (the next sweep retries).
    #[error("{}", .0.join("; "))]
    SweepIncomplete(Vec<String>),
    /// An event from EventBridge is not the one the rule delivers.
    #[error("invalid event: {0}")]
    Event(String),
    /// The reaper's pass over the held places did what it could; these failed (the next pass
    /// retries).
    #[error("{}", .0.join("; "))]
    ReconcileIncomplete(Vec<String>),
}

lb_domain::error_names!(FnError {
    Input | RunState | Event => "InvalidInput";
    Output => "OutputNotSerializable";
    Config => "InvalidConfiguration";
    DeadlineExceeded => "DeadlineExceeded" [transient];
    PhaseMismatch => "PhaseMismatch";
    // The next minute's sweep tries again: no state machine retries it.
    SweepIncomplete => "SweepIncomplete";
    ReconcileIncomplete => "ReconcileIncomplete";
} wraps {
    Message => MessageError;
    Settings => SettingsError;
    EvalAi => EvalAiError;
    Aws => AwsError;
    Cluster => ClusterError;
    Results => ResultsError;
    Plan => PlanError;
    JobSettings => ContextError;
    Render => RenderError;
});

impl FnError {
    /// The message with its causes, for EvalAI's stderr and the Lambda diagnostic.
    pub fn chain(&self) -> String {
        let mut text = self.to_string();
        let mut source = std::error::Error::source(self);
        while let Some(cause) = source {
            let cause_text = cause.to_string();
            if !text.contains(&cause_text) {
                text.push_str(": ");
                text.push_str(&cause_text);
            }
            source = cause.source();
        }
        text
    }

    /// A function's input decoded, or [`FnError::Input`] naming the function.
    pub fn decode<T: serde::de::DeserializeOwned>(
        what: &'static str,
        input: serde_json::Value,
    ) -> Result<T> {
        serde_json::from_value(input).map_err(|source| FnError::Input { what, source })
    }

    /// A function's output encoded, or [`FnError::Output`] naming the function.
    pub fn encode<T: serde::Serialize>(
        what: &'static str,
        output: &T,
    ) -> Result<serde_json::Value> {
        serde_json::to_value(output).map_err(|source| FnError::Output { what, source })
    }
}

/// The most of an error's message a function raises. The message becomes the Catch's `Cause`
/// in the state, and untrusted input (a results file, an EvalAI answer) can be quoted in it:
/// unbounded, it could push a payload past Step Functions' 256 KiB (`States.DataLimitExceeded`,
/// which no Catch handles).
pub const MAX_ERROR_MESSAGE_BYTES: usize = 4 * 1024;

impl From<FnError> for lambda_runtime::Diagnostic {
    fn from(error: FnError) -> Self {
        lambda_runtime::Diagnostic {
            error_type: error.name().to_string(),
            error_message: lb_domain::run::state::printable_bounded(
                &error.chain(),
                MAX_ERROR_MESSAGE_BYTES,
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_lists_hold_the_wrapped_errors_names_and_only_the_transient_ones_as_transient() {
        let (names, transient) = (FnError::names(), FnError::transient_names());
        for name in ResultsError::names()
            .into_iter()
            .chain(["InvalidBatch", "KubeTimeout"])
        {
            assert!(names.contains(&name), "{name}");
        }
        assert!(transient.contains(&"DeadlineExceeded") && transient.contains(&"EvalAiThrottled"));
        assert!(!transient.contains(&"InvalidResult") && !transient.contains(&"KubeForbidden"));
        assert!(transient.iter().all(|t| names.contains(t)));
    }

    #[test]
    fn undecodable_input_and_unencodable_output_are_named_apart() {
        let input = FnError::decode::<u64>("monitor", serde_json::json!("x")).unwrap_err();
        assert_eq!(input.name(), "InvalidInput");
        assert!(
            input
                .chain()
                .starts_with("invalid monitor input: invalid type"),
            "{}",
            input.chain()
        );
        let map: std::collections::HashMap<(u8, u8), u8> = [((1, 2), 3)].into();
        let output = FnError::encode("sweep", &map).unwrap_err();
        assert_eq!(output.name(), "OutputNotSerializable");
        assert!(output
            .chain()
            .starts_with("the sweep output cannot be serialized: "));
    }

    #[test]
    fn a_huge_message_is_cut_at_the_bound() {
        let error = FnError::from(MessageError::Field {
            field: "phase_pk",
            problem: "é".repeat(100_000),
        });
        let diagnostic = lambda_runtime::Diagnostic::from(error);
        assert!(diagnostic.error_message.len() <= MAX_ERROR_MESSAGE_BYTES);
        assert!(diagnostic.error_message.ends_with("[... cut]"));
        assert_eq!(diagnostic.error_type, "InvalidMessage");
    }

    #[test]
    fn the_diagnostic_carries_the_stable_name_and_the_causes() {
        let error = FnError::from(MessageError::Field {
            field: "phase_pk",
            problem: "is missing".into(),
        });
        let diagnostic = lambda_runtime::Diagnostic::from(error);
        assert_eq!(diagnostic.error_type, "InvalidMessage");
        assert_eq!(
            diagnostic.error_message,
            "submission message field `phase_pk` is missing"
        );
        assert!(FnError::names().contains(&"InvalidMessage"));
    }
}
