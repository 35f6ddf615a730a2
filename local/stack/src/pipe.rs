//! The EventBridge Pipe's SQS side, as AWS documents it ("Amazon SQS as a source"): the Pipe
//! polls the queue and sees each message as a record `{messageId, receiptHandle, body,
//! attributes, messageAttributes, md5OfBody, eventSource, eventSourceARN, awsRegion}` whose
//! `body` is the message text; the transformation itself is `lb_infra::pipe`, as deployed.

use aws_sdk_sqs::types::{Message, MessageSystemAttributeName};
use lb_infra::pipe::{batch, TransformError, INPUT_TEMPLATE};
use serde_json::{json, Map, Value};

/// Why a poll of the queue failed.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum PipeError {
    /// The template could not be applied to a record.
    #[error(transparent)]
    Transform(#[from] TransformError),
    /// The queue could not be read or a message not deleted.
    #[error("sqs {operation}: {message}")]
    Sqs {
        /// The SQS operation.
        operation: &'static str,
        /// What the SDK said.
        message: String,
    },
}

/// The record a Pipe sees for one SQS message ("Amazon SQS as a source").
pub fn sqs_record(message: &Message, queue_arn: &str, region: &str) -> Value {
    let attributes: Map<String, Value> = message
        .attributes()
        .map(|a| {
            a.iter()
                .map(|(k, v)| (k.as_str().to_owned(), json!(v)))
                .collect()
        })
        .unwrap_or_default();
    json!({
        "messageId": message.message_id().unwrap_or_default(),
        "receiptHandle": message.receipt_handle().unwrap_or_default(),
        "body": message.body().unwrap_or_default(),
        "attributes": attributes,
        "messageAttributes": {},
        "md5OfBody": message.md5_of_body().unwrap_or_default(),
        "eventSource": "aws:sqs",
        "eventSourceARN": queue_arn,
        "awsRegion": region,
    })
}

/// A queue's ARN, as its records name it (`eventSourceARN`).
pub async fn queue_arn(sqs: &aws_sdk_sqs::Client, queue_url: &str) -> Result<String, PipeError> {
    use aws_sdk_sqs::types::QueueAttributeName;
    Ok(sqs
        .get_queue_attributes()
        .queue_url(queue_url)
        .attribute_names(QueueAttributeName::QueueArn)
        .send()
        .await
        .map_err(|e| sqs_error("GetQueueAttributes", e))?
        .attributes()
        .and_then(|a| a.get(&QueueAttributeName::QueueArn).cloned())
        .unwrap_or_default())
}

/// The region of an ARN (`arn:aws:sqs:<region>:<account>:<name>`), as records name it.
pub fn region_of(arn: &str) -> String {
    arn.split(':').nth(3).unwrap_or_default().to_owned()
}

/// One poll of the queue as the Pipe makes it: receive up to `batch_size` messages (waiting
/// at most `wait_seconds`), transform them, delete them (a FIRE_AND_FORGET target took them)
/// and return the batch as the state machine receives it; `None` when nothing arrived.
pub async fn poll(
    sqs: &aws_sdk_sqs::Client,
    queue_url: &str,
    batch_size: i32,
    wait_seconds: i32,
) -> Result<Option<Value>, PipeError> {
    let arn = queue_arn(sqs, queue_url).await?;
    let region = region_of(&arn);
    let received = sqs
        .receive_message()
        .queue_url(queue_url)
        .max_number_of_messages(batch_size)
        .wait_time_seconds(wait_seconds)
        .message_system_attribute_names(MessageSystemAttributeName::All)
        .send()
        .await
        .map_err(|e| sqs_error("ReceiveMessage", e))?;
    let messages = received.messages();
    if messages.is_empty() {
        return Ok(None);
    }
    let records: Vec<Value> = messages
        .iter()
        .map(|m| sqs_record(m, &arn, &region))
        .collect();
    let out = batch(&INPUT_TEMPLATE, &records)?;
    for handle in messages.iter().filter_map(Message::receipt_handle) {
        sqs.delete_message()
            .queue_url(queue_url)
            .receipt_handle(handle)
            .send()
            .await
            .map_err(|e| sqs_error("DeleteMessage", e))?;
    }
    Ok(Some(out))
}

pub(crate) fn sqs_error<E, R>(
    operation: &'static str,
    e: aws_sdk_sqs::error::SdkError<E, R>,
) -> PipeError
where
    E: std::error::Error + 'static,
    R: std::fmt::Debug,
{
    PipeError::Sqs {
        operation,
        message: aws_sdk_sqs::error::DisplayErrorContext(e).to_string(),
    }
}
