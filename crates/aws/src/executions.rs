//! What the reaper reads of an execution: its status (`DescribeExecution`) and the last state
//! it carried (`GetExecutionHistory`, newest first). Local mode answers from the embedded
//! executor through the same [`Executions`] trait.

use std::future::Future;

use aws_sdk_sfn::operation::describe_execution::DescribeExecutionError;
use aws_sdk_sfn::operation::get_execution_history::GetExecutionHistoryError;
use serde_json::Value;

use crate::tasks::StepFunctions;
use crate::{AwsError, Result};

/// The newest history events read looking for the last state (a page is at most 1,000
/// events; the last state is among the last few).
const HISTORY_PAGE: i32 = 100;

/// An execution's end as `DescribeExecution` tells it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Described {
    /// `RUNNING`, `SUCCEEDED`, `FAILED`, `TIMED_OUT`, `ABORTED`, `PENDING_REDRIVE`.
    pub status: String,
    /// The error it failed with, if any.
    pub error: Option<String>,
}

/// Where executions are read.
pub trait Executions: Send + Sync {
    /// The execution of `arn`; `None` when Step Functions has no such execution.
    fn describe(&self, arn: &str) -> impl Future<Output = Result<Option<Described>>> + Send;
    /// The last state the execution carried: the input of the state it last entered or the
    /// output of the state it last left, whichever came later (`None`: nothing recorded).
    fn last_state(&self, arn: &str) -> impl Future<Output = Result<Option<Value>>> + Send;
}

/// The ARN of execution `name` of the state machine `arn` (the documented layout:
/// `arn:<partition>:states:<region>:<account>:execution:<machine>:<name>`).
pub fn execution_arn(state_machine: &str, name: &str) -> Option<String> {
    let (head, machine) = state_machine.split_once(":stateMachine:")?;
    // NB: a version or alias ARN (`name:1`) has executions under the plain name.
    let machine = machine.split(':').next()?;
    Some(format!("{head}:execution:{machine}:{name}"))
}

impl Executions for StepFunctions {
    async fn describe(&self, arn: &str) -> Result<Option<Described>> {
        let out = self
            .client()
            .describe_execution()
            .execution_arn(arn)
            .send()
            .await;
        match out {
            Ok(out) => Ok(Some(Described {
                status: out.status().as_str().to_string(),
                error: out.error().map(str::to_owned),
            })),
            Err(e)
                if matches!(
                    e.as_service_error(),
                    Some(DescribeExecutionError::ExecutionDoesNotExist(_))
                ) =>
            {
                Ok(None)
            }
            Err(e) => Err(AwsError::sdk("states", "DescribeExecution", e)),
        }
    }

    async fn last_state(&self, arn: &str) -> Result<Option<Value>> {
        let out = self
            .client()
            .get_execution_history()
            .execution_arn(arn)
            .reverse_order(true)
            .include_execution_data(true)
            .max_results(HISTORY_PAGE)
            .send()
            .await;
        let out = match out {
            Ok(out) => out,
            Err(e)
                if matches!(
                    e.as_service_error(),
                    Some(GetExecutionHistoryError::ExecutionDoesNotExist(_))
                ) =>
            {
                return Ok(None)
            }
            Err(e) => return Err(AwsError::sdk("states", "GetExecutionHistory", e)),
        };
        let text = out.events().iter().find_map(|event| {
            event
                .state_entered_event_details()
                .and_then(|d| d.input())
                .or_else(|| event.state_exited_event_details().and_then(|d| d.output()))
        });
        Ok(text.and_then(|t| serde_json::from_str(t).ok()))
    }
}

#[cfg(test)]
mod tests {
    use super::execution_arn;

    #[test]
    fn the_execution_arn_follows_the_state_machine_arn() {
        assert_eq!(
            execution_arn("arn:aws:states:us-east-1:1:stateMachine:submission", "x").as_deref(),
            Some("arn:aws:states:us-east-1:1:execution:submission:x")
        );
        assert_eq!(
            execution_arn("arn:aws:states:us-east-1:1:stateMachine:submission:3", "x").as_deref(),
            Some("arn:aws:states:us-east-1:1:execution:submission:x")
        );
        assert_eq!(
            execution_arn("arn:aws:lambda:us-east-1:1:function:f", "x"),
            None
        );
    }
}
