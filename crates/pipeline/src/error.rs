//! The functions' error: every variant has the stable name the state machine's `ErrorEquals`
//! matches, and becomes a Lambda `Diagnostic` with that name as `errorType`.

use lb_aws::AwsError;
use lb_domain::settings::SettingsError;
use lb_domain::submission::MessageError;
use lb_evalai::EvalAiError;

/// Result alias of the functions.
pub type Result<T, E = FnError> = std::result::Result<T, E>;

/// Why a function failed.
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
    /// The function's input is not what the state machine sends.
    #[error("invalid input: {0}")]
    Input(String),
    /// The function's environment is incomplete.
    #[error("invalid function configuration: {0}")]
    Config(String),
    /// A stage-specific failure with its own stable name.
    #[error("{message}")]
    Stage {
        /// Stable PascalCase name.
        name: &'static str,
        /// Readable cause.
        message: String,
        /// Worth retrying.
        transient: bool,
    },
}

impl FnError {
    /// The stable name raised to the state machine.
    pub fn name(&self) -> &'static str {
        match self {
            FnError::Message(e) => e.name(),
            FnError::Settings(e) => e.name(),
            FnError::EvalAi(e) => e.name(),
            FnError::Aws(e) => e.name(),
            FnError::Input(_) => "InvalidInput",
            FnError::Config(_) => "InvalidConfiguration",
            FnError::Stage { name, .. } => name,
        }
    }

    /// Transient errors are retried by the state machine (and listed in its Retry).
    pub fn is_transient(&self) -> bool {
        match self {
            FnError::EvalAi(e) => e.is_transient(),
            FnError::Aws(e) => e.is_transient(),
            FnError::Stage { transient, .. } => *transient,
            _ => false,
        }
    }

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
            error_message: crate::payload::printable_bounded(
                &error.chain(),
                MAX_ERROR_MESSAGE_BYTES,
            ),
        }
    }
}

/// The names of the transient errors (`FnError::is_transient`): every Task retries them all
/// (the state machine test checks it).
pub const TRANSIENT_NAMES: &[&str] = &[
    "EvalAiThrottled",
    "EvalAiUnavailable",
    "EvalAiNotConfirmed",
    "AwsTransient",
    "KubeTransient",
    "KubeUnavailable",
    "KubeTimeout",
    "JobTerminating",
    "DeadlineExceeded",
];

/// Every name our functions raise; the state machine test checks `ErrorEquals` against it.
pub const ERROR_NAMES: &[&str] = &[
    "DeadlineExceeded",
    "InvalidMessage",
    "InvalidBatch",
    "InvalidSettings",
    "UnknownPhase",
    "EvalAiConfig",
    "EvalAiUnauthorized",
    "SubmissionNotFound",
    "EvalAiRejected",
    "EvalAiThrottled",
    "EvalAiUnavailable",
    "EvalAiInvalidResponse",
    "InvalidResult",
    "EvalAiNotConfirmed",
    "AwsTransient",
    "AwsServiceError",
    "InvalidSecret",
    "ObjectTooLarge",
    "MalformedRecord",
    "InvalidInput",
    "InvalidConfiguration",
    "PhaseMismatch",
    "KubeConfigInvalid",
    "InvalidSubmissionId",
    "InvalidJobSpec",
    "JobNameTaken",
    "JobTerminating",
    "KubeInvalid",
    "KubeForbidden",
    "KubeUnauthorized",
    "KubeTransient",
    "KubeUnavailable",
    "KubeTimeout",
    "KubeRequestFailed",
    "KubeResponseMalformed",
    "InvalidPlan",
    "InvalidJobTemplate",
    "InvalidImage",
    "InvalidJobSetting",
    "JobTemplateEvaluationFailed",
    "ResultsTooLarge",
    "ResultsNonFinite",
    "ResultsInvalid",
    "ResultsOutsideSubset",
    "SensorMismatch",
    "DuplicateRoute",
    "MissingRouteData",
    "UnexpectedRecords",
    "RepetitionMismatch",
];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_results_error_name_is_raised_to_the_state_machine() {
        for name in lb_domain::results::ResultsError::NAMES {
            assert!(ERROR_NAMES.contains(&name), "{name}");
        }
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
        assert!(ERROR_NAMES.contains(&"InvalidMessage"));
    }
}
