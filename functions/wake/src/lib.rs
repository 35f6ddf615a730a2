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

use std::collections::BTreeMap;

use aws_lambda_events::event::eventbridge::EventBridgeEvent;
use aws_lambda_events::event::s3::{S3Bucket, S3Object};
use aws_lambda_events::event::sqs::{BatchItemFailure, SqsBatchResponse, SqsEvent};
use lb_aws::tasks::{Callbacks, Reported, StepFunctions};
use lb_aws::wake::WakeTable;
use lb_pipeline::serve::Function;
use lb_pipeline::{clients, Result};
use serde::Deserialize;
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

/// Why a message wakes nobody.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Ignored {
    /// Not an S3 `Object Created` event as EventBridge delivers it.
    NotAnS3Event(String),
    /// An object of the bucket that is neither a results file nor a marker.
    OtherKey(String),
}

/// The `detail` of S3's `Object Created` event on EventBridge (S3 user guide, "EventBridge
/// message structure"). `aws_lambda_events` types the envelope, the bucket and the object but
/// has no type for this detail, so it is only these two of the crate's types side by side.
#[derive(Debug, Clone, Deserialize)]
struct ObjectCreated {
    bucket: S3Bucket,
    object: S3Object,
}

/// The submission an EventBridge event from S3 wakes: `source` `aws.s3`, `detail-type`
/// `Object Created`, and a key of a results file or a marker.
pub fn submission_of(body: &str) -> std::result::Result<u64, Ignored> {
    let event: EventBridgeEvent<Value> = serde_json::from_str(body)
        .map_err(|e| Ignored::NotAnS3Event(format!("not an EventBridge event: {e}")))?;
    if event.source != "aws.s3" || event.detail_type != "Object Created" {
        return Err(Ignored::NotAnS3Event(format!(
            "source `{}`, detail-type `{}`",
            event.source, event.detail_type
        )));
    }
    let detail: ObjectCreated = serde_json::from_value(event.detail)
        .map_err(|e| Ignored::NotAnS3Event(format!("detail: {e}")))?;
    let key = detail
        .object
        .key
        .ok_or_else(|| Ignored::NotAnS3Event("no detail.object.key".into()))?;
    debug!(bucket = detail.bucket.name.as_deref().unwrap_or(""), %key, "object created");
    lb_domain::job::protocol::wakes_submission(&key).ok_or(Ignored::OtherKey(key))
}

impl<C: Callbacks> Function for Deps<C> {
    const NAME: &'static str = "wake";
    type Input = SqsEvent;
    type Output = SqsBatchResponse;
    /// Never fails: a message not handled is reported back for SQS to deliver again.
    async fn handle(&self, event: SqsEvent) -> Result<SqsBatchResponse> {
        Ok(handle(event, self, clients::now_epoch_seconds()).await)
    }
}

/// Wakes each distinct submission of the batch once. A message that wakes nobody is dropped
/// (no retry could change it); the messages of a submission whose wake failed are reported
/// for another delivery.
pub async fn handle<C: Callbacks>(event: SqsEvent, deps: &Deps<C>, now: u64) -> SqsBatchResponse {
    let mut by_submission: BTreeMap<u64, Vec<String>> = BTreeMap::new();
    for record in event.records {
        // SQS always sets both; a record without an id could not be reported back anyway.
        let (Some(message_id), Some(body)) = (record.message_id, record.body) else {
            warn!("dropped a record without a messageId or body");
            continue;
        };
        match submission_of(&body) {
            Ok(id) => by_submission.entry(id).or_default().push(message_id),
            Err(Ignored::OtherKey(key)) => debug!(%key, "not a results file or marker"),
            Err(Ignored::NotAnS3Event(why)) => {
                warn!(%message_id, %why, "dropped a message that is not an S3 event")
            }
        }
    }
    let mut response = SqsBatchResponse::default();
    for (submission_id, messages) in by_submission {
        if let Err(e) = wake(submission_id, deps, now).await {
            warn!(submission_id, error = %e, "wake failed; its messages come back");
            response
                .batch_item_failures
                .extend(messages.into_iter().map(failure));
        }
    }
    response
}

/// A batch item failure naming one message (the crate's type is non-exhaustive).
pub fn failure(message_id: String) -> BatchItemFailure {
    let mut failure = BatchItemFailure::default();
    failure.item_identifier = message_id;
    failure
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
