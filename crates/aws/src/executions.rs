//! What the reaper reads of an execution: its status (`DescribeExecution`) and the last state
//! it carried (`GetExecutionHistory`, newest first). Local mode answers from the embedded
//! executor through the same [`Executions`] trait.

use std::future::Future;

use aws_sdk_sfn::operation::describe_execution::DescribeExecutionError;
use aws_sdk_sfn::operation::get_execution_history::GetExecutionHistoryError;
use lb_domain::status::ExecutionStatus;
use serde_json::Value;

use crate::tasks::StepFunctions;
use crate::{AwsError, Result};

/// The newest history events read looking for the last state (a page is at most 1,000
/// events; the last state is among the last few).
const HISTORY_PAGE: i32 = 100;

/// An execution's end as `DescribeExecution` tells it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Described {
    /// How it stands.
    pub status: ExecutionStatus,
    /// The error it failed with, if any.
    pub error: Option<String>,
    /// The execution its run continued as, when it ended to start one
    /// (`lb_domain::run::history::continued_as` of its output).
    pub continued_as: Option<String>,
}

/// The most continuations [`current`] follows: a run's chain is under 100 executions long,
/// and the queue entry names the newest within a round of its start.
const MAX_HOPS: usize = 8;

/// The execution a run is in now, from one of its executions `arn`: that one while it runs or
/// when it ended for good, else the one it continued as (followed a few hops at most). `None`
/// when Step Functions does not know `arn`.
pub async fn current<E: Executions>(
    executions: &E,
    arn: &str,
) -> Result<Option<(String, Described)>> {
    let mut arn = arn.to_string();
    for _ in 0..MAX_HOPS {
        let Some(described) = executions.describe(&arn).await? else {
            return Ok(None);
        };
        match described.continued_as.clone() {
            Some(next) if described.status == ExecutionStatus::Succeeded => arn = next,
            _ => return Ok(Some((arn, described))),
        }
    }
    Ok(executions.describe(&arn).await?.map(|d| (arn, d)))
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
            Ok(out) => {
                let output: Option<Value> = out.output().and_then(|t| serde_json::from_str(t).ok());
                let status = out.status().as_str().parse().map_err(
                    |e: lb_domain::status::UnknownStatus| AwsError::Malformed {
                        what: format!("execution `{arn}`"),
                        problem: e.to_string(),
                    },
                )?;
                Ok(Some(Described {
                    status,
                    error: out.error().map(str::to_owned),
                    continued_as: output
                        .as_ref()
                        .and_then(lb_domain::run::history::continued_as)
                        .map(str::to_owned),
                }))
            }
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
    use super::{current, execution_arn, Described, Executions};
    use std::collections::HashMap;

    /// Executions as a map from ARN to (status, continued as).
    struct Known(HashMap<String, (&'static str, Option<String>)>);

    impl Executions for Known {
        async fn describe(&self, arn: &str) -> crate::Result<Option<Described>> {
            Ok(self.0.get(arn).map(|(status, next)| Described {
                status: status.parse().unwrap(),
                error: None,
                continued_as: next.clone(),
            }))
        }
        async fn last_state(&self, _: &str) -> crate::Result<Option<serde_json::Value>> {
            Ok(None)
        }
    }

    #[tokio::test]
    async fn a_continued_run_is_followed_to_the_execution_it_runs_in() {
        let known = Known(HashMap::from([
            ("a".into(), ("SUCCEEDED", Some("a-c1".into()))),
            ("a-c1".into(), ("SUCCEEDED", Some("a-c2".into()))),
            ("a-c2".into(), ("RUNNING", None)),
            ("done".into(), ("SUCCEEDED", None)),
            ("failed".into(), ("FAILED", Some("never".into()))),
            ("lost".into(), ("SUCCEEDED", Some("gone".into()))),
        ]));
        let at = |arn: &'static str| {
            let known = &known;
            async move {
                current(known, arn)
                    .await
                    .unwrap()
                    .map(|(arn, d)| (arn, d.status.as_str()))
            }
        };
        assert_eq!(at("a").await, Some(("a-c2".into(), "RUNNING")));
        assert_eq!(at("done").await, Some(("done".into(), "SUCCEEDED")));
        // Only a success continues: a failure is judged as itself.
        assert_eq!(at("failed").await, Some(("failed".into(), "FAILED")));
        // A continuation Step Functions does not know: as for an unknown execution.
        assert_eq!(at("lost").await, None);
        assert_eq!(at("nobody").await, None);
    }

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
