//! Reporting to a waiting Step Functions task: `SendTaskSuccess` with the token a wait stored.
//!
//! The wake and sweep functions take a [`Callbacks`] so that local mode can hand the token to
//! the embedded executor instead of the Step Functions API.

use std::future::Future;

use aws_sdk_sfn::operation::send_task_success::SendTaskSuccessError;

use crate::{AwsError, Result};

/// What became of a report.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reported {
    /// The waiting task took it: the execution moves on.
    Delivered,
    /// The token is no longer waiting (the task timed out, was answered, or its execution
    /// ended): harmless, the execution is already past that wait.
    Stale,
}

/// Where task tokens are reported.
pub trait Callbacks: Send + Sync {
    /// Ends the waiting task of `token` successfully with the JSON `output`. `Err` only for
    /// a failure worth retrying (the API unreachable, throttled, denied).
    fn succeed(&self, token: &str, output: &str) -> impl Future<Output = Result<Reported>> + Send;
}

/// The Step Functions API.
#[derive(Debug, Clone)]
pub struct StepFunctions {
    client: aws_sdk_sfn::Client,
}

impl StepFunctions {
    /// The API through `client`.
    pub fn new(client: aws_sdk_sfn::Client) -> Self {
        StepFunctions { client }
    }

    /// The client, for the other calls of this API.
    pub(crate) fn client(&self) -> &aws_sdk_sfn::Client {
        &self.client
    }
}

impl Callbacks for StepFunctions {
    async fn succeed(&self, token: &str, output: &str) -> Result<Reported> {
        let result = self
            .client
            .send_task_success()
            .task_token(token)
            .output(output)
            .send()
            .await;
        match result {
            Ok(_) => Ok(Reported::Delivered),
            // The API reference's errors for a token nobody waits on any more.
            Err(e)
                if matches!(
                    e.as_service_error(),
                    Some(
                        SendTaskSuccessError::TaskTimedOut(_)
                            | SendTaskSuccessError::TaskDoesNotExist(_)
                            | SendTaskSuccessError::InvalidToken(_)
                    )
                ) =>
            {
                Ok(Reported::Stale)
            }
            Err(e) => Err(AwsError::sdk("states", "SendTaskSuccess", e)),
        }
    }
}
