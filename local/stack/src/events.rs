//! What carries events to the functions in local mode as the deployment does: Lambda's SQS
//! event source mapping (the wake queue to the wake function), a scheduled rule's period (the
//! cancel sweep), and task reports to the embedded executor instead of the Step Functions API.
//!
//! Followed (Lambda developer guide, "Using Lambda with Amazon SQS"): the mapping polls the
//! queue and gathers messages until the batch is full or `MaximumBatchingWindowInSeconds` has
//! passed; the function gets `{"Records": [...]}`, each record as the Pipe sees it
//! ([`crate::pipe::sqs_record`]). With `ReportBatchItemFailures`, the messages named in the
//! response's `batchItemFailures` stay on the queue and come back after the visibility
//! timeout; the others are deleted. A function error, or a response naming a message that
//! is not in the batch, fails the whole batch: nothing is deleted.

use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

use aws_config::SdkConfig;
use aws_sdk_sqs::types::MessageSystemAttributeName;
use lb_aws::executions::{Described, Executions};
use lb_aws::tasks::{Callbacks, Reported};
use lb_domain::status::ExecutionStatus;
use local_stepfunctions::{CallbackError, Executor, Status};
use serde_json::Value;

use crate::pipe::{queue_arn, region_of, sqs_error, sqs_record, PipeError};
use lb_infra::template::{Template, TemplateError};

/// An SQS event source mapping of the template.
#[derive(Debug, Clone)]
pub struct SqsEventSource {
    sqs: aws_sdk_sqs::Client,
    url: String,
    arn: String,
    region: String,
    batch_size: usize,
    window: Duration,
}

/// One batch handed to the function.
#[derive(Debug, Clone)]
pub struct Batch {
    /// The event, `{"Records": [...]}`.
    pub event: Value,
    receipts: Vec<(String, String)>,
}

impl Batch {
    /// How many messages it holds.
    pub fn len(&self) -> usize {
        self.receipts.len()
    }

    /// Whether it holds none.
    pub fn is_empty(&self) -> bool {
        self.receipts.is_empty()
    }
}

impl SqsEventSource {
    /// The mapping `id` of `template` (its queue must exist on `sdk`'s endpoint).
    pub async fn from_template(
        sdk: &SdkConfig,
        template: &Template,
        id: &str,
    ) -> Result<SqsEventSource, TemplateError> {
        let queue = template.text(id, &["EventSourceArn"])?;
        let queue_id = queue
            .strip_prefix('<')
            .and_then(|q| q.strip_suffix(".Arn>"))
            .ok_or_else(|| {
                TemplateError::Invalid(format!(
                    "`{id}` reads `{queue}`, not a queue of the template"
                ))
            })?;
        let name = template.physical_name(queue_id)?;
        let number = |key: &str, default: usize| {
            template
                .text(id, &[key])
                .ok()
                .and_then(|v| v.parse().ok())
                .unwrap_or(default)
        };
        // The API's defaults for SQS: 10 messages, no window.
        let batch_size = number("BatchSize", 10);
        let window = Duration::from_secs(number("MaximumBatchingWindowInSeconds", 0) as u64);
        let sqs = aws_sdk_sqs::Client::new(sdk);
        let invalid = |e: PipeError| TemplateError::Invalid(format!("queue `{name}`: {e}"));
        let url = sqs
            .get_queue_url()
            .queue_name(&name)
            .send()
            .await
            .map_err(|e| invalid(sqs_error("GetQueueUrl", e)))?
            .queue_url
            .unwrap_or_default();
        let arn = queue_arn(&sqs, &url).await.map_err(invalid)?;
        let region = region_of(&arn);
        Ok(SqsEventSource {
            sqs,
            url,
            arn,
            region,
            batch_size,
            window,
        })
    }

    /// One batch: waits up to `wait` for a first message, then gathers more until the batch
    /// is full or the batching window has passed. `None` when nothing came.
    pub async fn poll(&self, wait: Duration) -> Result<Option<Batch>, PipeError> {
        let mut records = Vec::new();
        let mut receipts = Vec::new();
        let mut window_ends: Option<Instant> = None;
        while records.len() < self.batch_size {
            let wait_seconds = match window_ends {
                None => wait.as_secs().min(20) as i32,
                Some(end) if Instant::now() >= end => break,
                Some(end) => end
                    .saturating_duration_since(Instant::now())
                    .as_secs()
                    .min(20) as i32,
            };
            let received = self
                .sqs
                .receive_message()
                .queue_url(&self.url)
                .max_number_of_messages((self.batch_size - records.len()).min(10) as i32)
                .wait_time_seconds(wait_seconds)
                .message_system_attribute_names(MessageSystemAttributeName::All)
                .send()
                .await
                .map_err(|e| sqs_error("ReceiveMessage", e))?;
            let messages = received.messages();
            if messages.is_empty() && window_ends.is_none() {
                return Ok(None);
            }
            for m in messages {
                records.push(sqs_record(m, &self.arn, &self.region));
                receipts.push((
                    m.message_id().unwrap_or_default().to_owned(),
                    m.receipt_handle().unwrap_or_default().to_owned(),
                ));
            }
            if messages.is_empty() && wait_seconds == 0 {
                // Nothing more within the window's last second.
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            window_ends.get_or_insert_with(|| Instant::now() + self.window);
        }
        Ok(Some(Batch {
            event: serde_json::json!({ "Records": records }),
            receipts,
        }))
    }

    /// Settles a batch after the function ran: `response` is what it returned (`None` for a
    /// function error). Returns how many messages were deleted.
    pub async fn settle(&self, batch: Batch, response: Option<&Value>) -> Result<usize, PipeError> {
        let Some(response) = response else {
            return Ok(0);
        };
        let mut failed = Vec::new();
        if let Some(items) = response.get("batchItemFailures") {
            let Some(items) = items.as_array() else {
                return Ok(0);
            };
            for item in items {
                match item["itemIdentifier"].as_str() {
                    Some(id) if batch.receipts.iter().any(|(m, _)| m == id) => failed.push(id),
                    // Not a message of the batch: Lambda fails the whole batch.
                    _ => return Ok(0),
                }
            }
        }
        let mut deleted = 0;
        for (id, handle) in &batch.receipts {
            if failed.contains(&id.as_str()) {
                continue;
            }
            self.sqs
                .delete_message()
                .queue_url(&self.url)
                .receipt_handle(handle)
                .send()
                .await
                .map_err(|e| sqs_error("DeleteMessage", e))?;
            deleted += 1;
        }
        Ok(deleted)
    }
}

/// How Lambda runs again an asynchronous invocation (what EventBridge makes of its Lambda
/// targets) whose function returned an error: Lambda's documented waits, one minute before
/// the second attempt and two before the third, as many as the function's
/// `EventInvokeConfig.MaximumRetryAttempts` allows (Lambda's default, 2, without one); after
/// the last, the event is dropped. (EventBridge's own `RetryPolicy` covers only handing the
/// event to Lambda, which local mode does not fail.)
pub fn async_retry_waits(
    template: &Template,
    function: &str,
) -> Result<Vec<Duration>, TemplateError> {
    const WAITS: [Duration; 2] = [Duration::from_secs(60), Duration::from_secs(120)];
    template.property(function, &[])?;
    let retries = match template.property(function, &["EventInvokeConfig", "MaximumRetryAttempts"])
    {
        Ok(v) => v.as_u64().filter(|n| *n <= 2).ok_or_else(|| {
            TemplateError::Invalid(format!(
                "`{function}`: `EventInvokeConfig.MaximumRetryAttempts` is not 0, 1 or 2"
            ))
        })?,
        Err(_) => 2,
    };
    Ok(WAITS[..retries as usize].to_vec())
}

/// The period of the scheduled rule `id` (`ScheduleExpression: rate(<n> <unit>)`, units as
/// EventBridge spells them).
pub fn schedule_period(template: &Template, id: &str) -> Result<Duration, TemplateError> {
    let expression = template.text(id, &["ScheduleExpression"])?;
    let invalid =
        || TemplateError::Invalid(format!("`{id}`: `{expression}` is not rate(<n> <unit>)"));
    let inner = expression
        .strip_prefix("rate(")
        .and_then(|r| r.strip_suffix(')'))
        .ok_or_else(invalid)?;
    let (n, unit) = inner.split_once(' ').ok_or_else(invalid)?;
    let n: u64 = n.parse().map_err(|_| invalid())?;
    let seconds = match unit {
        "minute" | "minutes" => 60,
        "hour" | "hours" => 3600,
        "day" | "days" => 86_400,
        _ => return Err(invalid()),
    };
    Ok(Duration::from_secs(n * seconds))
}

/// The embedded executor where the deployment has the Step Functions API.
#[derive(Clone)]
pub struct ExecutorCallbacks(pub Executor);

impl Callbacks for ExecutorCallbacks {
    async fn succeed(&self, token: &str, output: &str) -> lb_aws::Result<Reported> {
        let output: Value =
            serde_json::from_str(output).map_err(|e| lb_aws::AwsError::Malformed {
                what: "SendTaskSuccess output".into(),
                problem: e.to_string(),
            })?;
        match self.0.send_task_success(token, output) {
            Ok(()) => Ok(Reported::Delivered),
            Err(
                CallbackError::TaskTimedOut
                | CallbackError::TaskDoesNotExist
                | CallbackError::InvalidToken(_),
            ) => Ok(Reported::Stale),
            Err(e) => Err(lb_aws::AwsError::Malformed {
                what: "SendTaskSuccess".into(),
                problem: e.to_string(),
            }),
        }
    }
}

/// The embedded executor's status as Step Functions words it (`None`: still running).
pub fn execution_status(status: Option<Status>) -> ExecutionStatus {
    match status {
        None => ExecutionStatus::Running,
        Some(Status::Succeeded) => ExecutionStatus::Succeeded,
        Some(Status::Failed) => ExecutionStatus::Failed,
        Some(Status::TimedOut) => ExecutionStatus::TimedOut,
        Some(Status::Aborted) => ExecutionStatus::Aborted,
    }
}

impl Executions for ExecutorCallbacks {
    async fn describe(&self, arn: &str) -> lb_aws::Result<Option<Described>> {
        Ok(self.0.describe(arn).map(|d| Described {
            status: execution_status(d.status),
            error: d.error,
            continued_as: d
                .output
                .as_ref()
                .and_then(lb_domain::run::history::continued_as)
                .map(str::to_owned),
        }))
    }

    async fn last_state(&self, arn: &str) -> lb_aws::Result<Option<Value>> {
        // What GetExecutionHistory in reverse order shows first of a state entered or left.
        Ok(self.0.history_of(arn).and_then(|history| {
            history.iter().rev().find_map(|event| {
                let key = if event.event_type.is_state_entered() {
                    "input"
                } else if event.event_type.is_state_exited() {
                    "output"
                } else {
                    return None;
                };
                event.details.get(key).cloned()
            })
        }))
    }
}

/// [`ExecutorCallbacks`] for a handler made before its executor (the task map the executor
/// runs holds the handlers): tokens reported before [`LateCallbacks::bind`] are stale (no
/// execution can be waiting on a token of an executor that does not exist yet).
#[derive(Clone, Default)]
pub struct LateCallbacks(Arc<OnceLock<Executor>>);

impl LateCallbacks {
    /// Reports from now on go to `executor`.
    pub fn bind(&self, executor: Executor) {
        let _ = self.0.set(executor);
    }

    /// The executor, once bound.
    pub fn executor(&self) -> Option<&Executor> {
        self.0.get()
    }
}

impl Callbacks for LateCallbacks {
    async fn succeed(&self, token: &str, output: &str) -> lb_aws::Result<Reported> {
        match self.0.get() {
            Some(executor) => {
                ExecutorCallbacks(executor.clone())
                    .succeed(token, output)
                    .await
            }
            None => Ok(Reported::Stale),
        }
    }
}

impl Executions for LateCallbacks {
    async fn describe(&self, arn: &str) -> lb_aws::Result<Option<Described>> {
        match self.0.get() {
            Some(executor) => ExecutorCallbacks(executor.clone()).describe(arn).await,
            None => Ok(None),
        }
    }

    async fn last_state(&self, arn: &str) -> lb_aws::Result<Option<Value>> {
        match self.0.get() {
            Some(executor) => ExecutorCallbacks(executor.clone()).last_state(arn).await,
            None => Ok(None),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sweep_runs_once_a_minute_and_other_expressions_are_named() {
        assert_eq!(
            schedule_period(&lb_infra::template::APP, "SweepSchedule").unwrap(),
            Duration::from_secs(60)
        );
        let err = schedule_period(&lb_infra::template::APP, "WakeRule").unwrap_err();
        assert!(err.to_string().contains("ScheduleExpression"), "{err}");
        assert_eq!(
            schedule_period(&lb_infra::template::APP, "ReaperSchedule").unwrap(),
            Duration::from_secs(300)
        );
    }

    #[test]
    fn a_failed_reaper_runs_again_after_lambda_s_waits_as_its_invoke_config_allows() {
        let app = &lb_infra::template::APP;
        assert_eq!(
            async_retry_waits(app, "FinalizeFunction").unwrap(),
            [Duration::from_secs(60), Duration::from_secs(120)]
        );
        // Without an EventInvokeConfig, Lambda's default: two retries.
        assert_eq!(async_retry_waits(app, "WakeFunction").unwrap().len(), 2);
        let none = Template::parse(
            "Resources:\n  F:\n    Type: AWS::Serverless::Function\n    Properties:\n      EventInvokeConfig: {MaximumRetryAttempts: 0}\n",
        )
        .unwrap();
        assert!(async_retry_waits(&none, "F").unwrap().is_empty());
        let bad = Template::parse(
            "Resources:\n  F:\n    Type: AWS::Serverless::Function\n    Properties:\n      EventInvokeConfig: {MaximumRetryAttempts: 5}\n",
        )
        .unwrap();
        assert!(async_retry_waits(&bad, "F").is_err());
        assert!(async_retry_waits(app, "NoSuchFunction").is_err());
    }
}
