//! The errors of `lbctl`'s operator commands, with stable names and the exit code each maps to.

use std::path::PathBuf;

type Source = Box<dyn std::error::Error + Send + Sync>;

/// Why an operator command failed.
#[derive(Debug, thiserror::Error)]
pub enum CliError {
    /// The command line (or the environment standing in for it) is incomplete or invalid.
    #[error("{0}")]
    Usage(String),
    /// The event file cannot be read.
    #[error("cannot read the event from `{path}`: {source}")]
    EventUnreadable {
        /// The file (`-` for stdin).
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The event is not JSON.
    #[error("the event in `{path}` is not valid JSON: {source}")]
    InvalidEvent {
        /// The file (`-` for stdin).
        path: PathBuf,
        /// Where and what.
        #[source]
        source: serde_json::Error,
    },
    /// An adapter call failed (settings secret, DynamoDB, S3).
    #[error("{context}")]
    Aws {
        /// What was being done.
        context: String,
        /// The adapter's error.
        #[source]
        source: lb_aws::AwsError,
    },
    /// A direct SDK call failed (Step Functions, DynamoDB Scan, S3 delete).
    #[error("{context} failed")]
    Sdk {
        /// The call and its target, e.g. ``dynamodb `Scan` of `table` ``.
        context: String,
        /// The SDK error.
        #[source]
        source: Source,
    },
    /// EvalAI could not be read (the token secret or the API).
    #[error("reading submission `{submission}` on EvalAI failed")]
    EvalAi {
        /// The submission.
        submission: u64,
        /// The pipeline's error (boxed: it carries every adapter's error whole).
        #[source]
        source: Box<lb_pipeline::FnError>,
    },
    /// Nothing is known about the submission.
    #[error("{0}")]
    NotFound(String),
    /// The operation would be wrong in the submission's current state.
    #[error("{0}")]
    Refused(String),
    /// No AWS region or no credentials: what was looked for and how to provide it.
    #[error("{0}")]
    AwsNotConfigured(String),
    /// The terminal could not be driven (`lbctl top`): raw mode, its screen, or a signal.
    #[error("the terminal could not be used: {0}")]
    Terminal(#[source] std::io::Error),
}

impl CliError {
    /// Stable PascalCase name (logs, scripts).
    pub fn name(&self) -> &'static str {
        match self {
            CliError::Usage(_) => "Usage",
            CliError::EventUnreadable { .. } => "EventUnreadable",
            CliError::InvalidEvent { .. } => "InvalidEvent",
            CliError::Aws { source, .. } => source.name(),
            CliError::Sdk { .. } => "AwsServiceError",
            CliError::EvalAi { source, .. } => source.name(),
            CliError::NotFound(_) => "NotFound",
            CliError::Refused(_) => "Refused",
            CliError::AwsNotConfigured(_) => "AwsNotConfigured",
            CliError::Terminal(_) => "Terminal",
        }
    }

    /// The process exit code: 2 for usage errors, 1 for every other failure.
    pub fn exit_code(&self) -> u8 {
        match self {
            CliError::Usage(_) => 2,
            _ => 1,
        }
    }

    /// Wraps an adapter error with what was being done.
    pub(crate) fn aws(context: impl Into<String>, source: lb_aws::AwsError) -> Self {
        CliError::Aws {
            context: context.into(),
            source,
        }
    }

    /// Wraps an SDK error with the call and its target.
    pub(crate) fn sdk<E>(context: impl Into<String>, source: E) -> Self
    where
        E: std::error::Error + Send + Sync + 'static,
    {
        CliError::Sdk {
            context: context.into(),
            source: Box::new(source),
        }
    }
}

/// Result alias of the operator commands.
pub type Result<T, E = CliError> = std::result::Result<T, E>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn usage_errors_exit_2_and_the_rest_exit_1() {
        assert_eq!(CliError::Usage("x".into()).exit_code(), 2);
        assert_eq!(CliError::Refused("x".into()).exit_code(), 1);
        assert_eq!(CliError::NotFound("x".into()).name(), "NotFound");
    }
}
