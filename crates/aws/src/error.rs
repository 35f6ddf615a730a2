//! One error type for the AWS adapters, keeping the SDK error as its source.

use aws_sdk_dynamodb::error::SdkError;

/// Result alias of this crate.
pub type Result<T, E = AwsError> = std::result::Result<T, E>;

type Source = Box<dyn std::error::Error + Send + Sync>;

/// What went wrong with AWS; `name()` is what the state machine matches.
#[derive(Debug, thiserror::Error)]
pub enum AwsError {
    /// Throttling, timeouts, 5xx, connection failures: retry later.
    #[error("{service} `{operation}` failed transiently")]
    Transient {
        /// e.g. `dynamodb`.
        service: &'static str,
        /// e.g. `PutItem`.
        operation: &'static str,
        /// The SDK error.
        #[source]
        source: Source,
    },
    /// Any other SDK failure (permissions, missing table or bucket, validation).
    #[error("{service} `{operation}` failed")]
    Service {
        /// e.g. `s3`.
        service: &'static str,
        /// e.g. `GetObject`.
        operation: &'static str,
        /// The SDK error.
        #[source]
        source: Source,
    },
    /// A secret is missing a value or is not the documented JSON.
    #[error("secret `{id}` is unusable: {problem}")]
    InvalidSecret {
        /// Secret id.
        id: String,
        /// What is wrong (never the value).
        problem: String,
    },
    /// An object is bigger than we agree to read.
    #[error("`s3://{bucket}/{key}` is {size} bytes, over the {limit}-byte limit")]
    TooLarge {
        /// Bucket.
        bucket: String,
        /// Key.
        key: String,
        /// Its size.
        size: u64,
        /// Our limit.
        limit: u64,
    },
    /// A stored record does not have the shape we write.
    #[error("record {what} is malformed: {problem}")]
    Malformed {
        /// Which record.
        what: String,
        /// What is wrong.
        problem: String,
    },
}

lb_domain::error_names!(AwsError {
    // Throttling, timeouts, 5xx: worth trying again later.
    Transient => "AwsTransient" [transient];
    Service => "AwsServiceError";
    InvalidSecret => "InvalidSecret";
    TooLarge => "ObjectTooLarge";
    Malformed => "MalformedRecord";
});

impl AwsError {
    /// Classifies an SDK error: throttling and transport problems are transient.
    pub(crate) fn sdk<E, R>(
        service: &'static str,
        operation: &'static str,
        err: SdkError<E, R>,
    ) -> Self
    where
        E: std::error::Error
            + aws_sdk_dynamodb::error::ProvideErrorMetadata
            + Send
            + Sync
            + 'static,
        R: std::fmt::Debug + Send + Sync + 'static,
    {
        let transient = match &err {
            SdkError::TimeoutError(_)
            | SdkError::DispatchFailure(_)
            | SdkError::ResponseError(_) => true,
            SdkError::ServiceError(e) => matches!(
                e.err().code(),
                Some(
                    "ThrottlingException"
                        | "Throttling"
                        | "ProvisionedThroughputExceededException"
                        | "RequestLimitExceeded"
                        | "SlowDown"
                        | "InternalServerError"
                        | "InternalError"
                        | "ServiceUnavailable"
                )
            ),
            _ => false,
        };
        let source: Source = Box::new(err);
        if transient {
            AwsError::Transient {
                service,
                operation,
                source,
            }
        } else {
            AwsError::Service {
                service,
                operation,
                source,
            }
        }
    }
}

/// Whether a DynamoDB write was refused by its condition: for a conditional write, the
/// answer "someone else got there first", not a failure.
pub(crate) fn condition_failed<E, R>(err: &SdkError<E, R>) -> bool
where
    E: aws_sdk_dynamodb::error::ProvideErrorMetadata,
{
    err.as_service_error().and_then(|e| e.code()) == Some("ConditionalCheckFailedException")
}
