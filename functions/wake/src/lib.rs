//! Wake: a submission's results file or status marker landed in S3, so its execution, waiting
//! in `WaitForChange`, moves on now instead of at the safety net.
//!
//! The path (infra/app.yaml): the results buckets send their events to EventBridge; a rule
//! keeps `Object Created` for `*/agent/partial_agent_results*.json` and `*/containers-status/*`
//! and puts them on the wake queue; an event source mapping hands this function batches of
//! them with `ReportBatchItemFailures`. For each distinct submission of a batch, one write
//! counts the change and takes the waiting token (`lb_aws::wake`), and the token is reported
//! with `SendTaskSuccess`: a burst wakes an execution once, an event for a submission nobody
//! waits on only counts, and a token is never reported twice.

use lb_pipeline::serve::{Function, Invocation};
use std::collections::BTreeMap;

use lb_aws::tasks::{Callbacks, Reported, StepFunctions};
use lb_aws::wake::WakeTable;
use lb_pipeline::{clients, Result};
use serde::{Deserialize, Serialize};
use serde_json::Value;
use tracing::{debug, info, warn};

/// What the wake needs: the wake table and where tokens are reported.
#[derive(Debug, Clone)]
pub struct Deps<C = StepFunctions> {
    /// The wake table.
    pub wakes: WakeTable,
    /// Step Functions (the embedded executor in local mode).
    pub callbacks: C,
}

impl Deps {
    /// Cold start: the environment (only `LB_WAKE_TABLE` is used: no secret, no EvalAI) and
    /// the clients.
    pub async fn from_env() -> Result<Deps> {
        let (config, sdk) = clients::cold_start().await?;
        Ok(Deps {
            wakes: WakeTable::new(aws_sdk_dynamodb::Client::new(&sdk), config.wake_table()?),
            callbacks: StepFunctions::new(aws_sdk_sfn::Client::new(&sdk)),
        })
    }
}

/// Lambda's event for an SQS batch (Lambda developer guide, "Using Lambda with Amazon SQS").
#[derive(Debug, Clone, Deserialize)]
pub struct SqsEvent {
    /// The messages.
    #[serde(rename = "Records")]
    pub records: Vec<SqsRecord>,
}

/// One message of the batch (the fields this function reads).
#[derive(Debug, Clone, Deserialize)]
pub struct SqsRecord {
    /// What a batch item failure names.
    #[serde(rename = "messageId")]
    pub message_id: String,
    /// The EventBridge event, as text.
    pub body: String,
}

/// The partial batch response ("Handling errors for an SQS event source"): the messages to
/// deliver again; every other one is deleted.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct BatchResponse {
    /// The failed messages.
    #[serde(rename = "batchItemFailures")]
    pub batch_item_failures: Vec<ItemFailure>,
}

/// One failed message.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ItemFailure {
    /// Its `messageId`.
    #[serde(rename = "itemIdentifier")]
    pub item_identifier: String,
}

/// Why a message wakes nobody.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Ignored {
    /// Not an S3 `Object Created` event as EventBridge delivers it.
    NotAnS3Event(String),
    /// An object of the bucket that is neither a results file nor a marker.
    OtherKey(String),
}

/// The submission an EventBridge event from S3 wakes (S3 user guide, "EventBridge message
/// structure": `source` `aws.s3`, `detail-type` `Object Created`, `detail.object.key`).
pub fn submission_of(body: &str) -> std::result::Result<u64, Ignored> {
    let event: Value =
        serde_json::from_str(body).map_err(|e| Ignored::NotAnS3Event(format!("not JSON: {e}")))?;
    if event["source"] != "aws.s3" || event["detail-type"] != "Object Created" {
        return Err(Ignored::NotAnS3Event(format!(
            "source `{}`, detail-type `{}`",
            event["source"], event["detail-type"]
        )));
    }
    let key = event["detail"]["object"]["key"]
        .as_str()
        .ok_or_else(|| Ignored::NotAnS3Event("no detail.object.key".into()))?;
    lb_domain::protocol::wakes_submission(key).ok_or_else(|| Ignored::OtherKey(key.into()))
}

impl Invocation for SqsEvent {}

impl<C: Callbacks> Function for Deps<C> {
    const NAME: &'static str = "wake";
    type Input = SqsEvent;
    type Output = BatchResponse;
    /// Never fails: a message not handled is reported back for SQS to deliver again.
    async fn handle(&self, event: SqsEvent) -> Result<BatchResponse> {
        Ok(handle(event, self, clients::now_epoch_seconds()).await)
    }
}

/// Wakes each distinct submission of the batch once. A message that wakes nobody is dropped
/// (no retry could change it); the messages of a submission whose wake failed are reported
/// for another delivery.
pub async fn handle<C: Callbacks>(event: SqsEvent, deps: &Deps<C>, now: u64) -> BatchResponse {
    let mut by_submission: BTreeMap<u64, Vec<String>> = BTreeMap::new();
    for record in event.records {
        match submission_of(&record.body) {
            Ok(id) => by_submission.entry(id).or_default().push(record.message_id),
            Err(Ignored::OtherKey(key)) => debug!(%key, "not a results file or marker"),
            Err(Ignored::NotAnS3Event(why)) => {
                warn!(message_id = %record.message_id, %why, "dropped a message that is not an S3 event")
            }
        }
    }
    let mut response = BatchResponse::default();
    for (submission_id, messages) in by_submission {
        if let Err(e) = wake(submission_id, deps, now).await {
            warn!(submission_id, error = %e, "wake failed; its messages come back");
            response.batch_item_failures.extend(
                messages
                    .into_iter()
                    .map(|m| ItemFailure { item_identifier: m }),
            );
        }
    }
    response
}

/// Counts the change and reports the waiting token, if one was taken.
async fn wake<C: Callbacks>(submission_id: u64, deps: &Deps<C>, now: u64) -> lb_aws::Result<()> {
    match deps.wakes.wake(submission_id, now, &deps.callbacks).await? {
        None => debug!(submission_id, "counted; no execution waiting"),
        Some(Reported::Delivered) => info!(submission_id, "woke the execution"),
        Some(Reported::Stale) => info!(submission_id, "the wait had already ended"),
    }
    Ok(())
}
