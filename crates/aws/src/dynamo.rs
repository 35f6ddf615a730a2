//! DynamoDB: the claim that makes a duplicate SQS delivery harmless, the submission record,
//! and the qualifier table.
//!
//! Submissions table: partition key `team_id` (N), sort key `submission_id` (N). Qualifier
//! table: partition key `team_id` (N), sort key `track_codename` (S).

use std::collections::HashMap;

use aws_sdk_dynamodb::types::AttributeValue;
use aws_sdk_dynamodb::Client;

use crate::{AwsError, Result};

/// `submission_status` values of the record.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RecordStatus {
    /// Claimed, Jobs not yet running.
    Queued,
    /// Jobs running.
    Running,
    /// Final scores posted.
    Finished,
    /// Failed (the error is in `error`).
    Failed,
    /// Cancelled by the participant.
    Cancelled,
}

impl RecordStatus {
    /// As stored.
    pub fn as_str(self) -> &'static str {
        match self {
            RecordStatus::Queued => "QUEUED",
            RecordStatus::Running => "RUNNING",
            RecordStatus::Finished => "FINISHED",
            RecordStatus::Failed => "FAILED",
            RecordStatus::Cancelled => "CANCELLED",
        }
    }
}

/// The record written when a submission is claimed.
#[derive(Debug, Clone, PartialEq)]
pub struct NewRecord {
    /// EvalAI participant team id.
    pub team_id: u64,
    /// EvalAI submission id.
    pub submission_id: u64,
    /// Team name as EvalAI has it.
    pub team_name: String,
    /// EvalAI phase id.
    pub track_id: u64,
    /// Track codename.
    pub track_name: String,
    /// The participant's image.
    pub image: String,
    /// Simulator-agent pairs this evaluation uses.
    pub workers: u32,
    /// When the claim happened (RFC 3339).
    pub submitted_time: String,
    /// Who claimed it (the state machine execution), to tell a duplicate from ourselves.
    pub claimed_by: String,
    /// EvalAI said `resuming`: a finished, failed or cancelled record may be claimed again.
    pub resuming: bool,
}

/// What the claim found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Claim {
    /// Ours: go on.
    Claimed,
    /// Someone else already evaluates (or evaluated) it: stop without touching anything.
    Duplicate {
        /// The record's status, if it could be read.
        status: Option<String>,
        /// The execution that holds it.
        claimed_by: Option<String>,
    },
}

/// The final record: status, times, results location, one attribute per metric.
#[derive(Debug, Clone, PartialEq)]
pub struct FinalRecord {
    /// Final status.
    pub status: RecordStatus,
    /// RFC 3339.
    pub end_time: String,
    /// `s3://bucket/id/` of the results.
    pub results: String,
    /// (attribute, value) per metric, e.g. (`driving_score`, 41.2).
    pub metrics: Vec<(&'static str, f64)>,
    /// Routes done / planned.
    pub progress: (u64, u64),
    /// Why it failed, readable.
    pub error: Option<String>,
}

/// The submissions table.
#[derive(Debug, Clone)]
pub struct SubmissionsTable {
    client: Client,
    table: String,
}

fn n(v: impl ToString) -> AttributeValue {
    AttributeValue::N(v.to_string())
}

fn s(v: impl Into<String>) -> AttributeValue {
    AttributeValue::S(v.into())
}

impl SubmissionsTable {
    /// The table `table` through `client`.
    pub fn new(client: Client, table: impl Into<String>) -> Self {
        SubmissionsTable {
            client,
            table: table.into(),
        }
    }

    fn key(team_id: u64, submission_id: u64) -> HashMap<String, AttributeValue> {
        HashMap::from([
            ("team_id".to_string(), n(team_id)),
            ("submission_id".to_string(), n(submission_id)),
        ])
    }

    /// The whole record, if any.
    pub async fn get(
        &self,
        team_id: u64,
        submission_id: u64,
    ) -> Result<Option<HashMap<String, AttributeValue>>> {
        let out = self
            .client
            .get_item()
            .table_name(&self.table)
            .set_key(Some(Self::key(team_id, submission_id)))
            .consistent_read(true)
            .send()
            .await
            .map_err(|e| AwsError::sdk("dynamodb", "GetItem", e))?;
        Ok(out.item)
    }

    /// The operator's per-submission worker count (`parallelization_workers`), if set.
    pub async fn worker_override(&self, team_id: u64, submission_id: u64) -> Result<Option<u32>> {
        let Some(item) = self.get(team_id, submission_id).await? else {
            return Ok(None);
        };
        match item.get("parallelization_workers") {
            None => Ok(None),
            Some(AttributeValue::N(v)) => v
                .parse::<u32>()
                .ok()
                .filter(|w| *w > 0)
                .map(Some)
                .ok_or_else(|| AwsError::Malformed {
                    what: format!("team {team_id} submission {submission_id}"),
                    problem: format!("`parallelization_workers` is `{v}`, not a positive integer"),
                }),
            Some(_) => Err(AwsError::Malformed {
                what: format!("team {team_id} submission {submission_id}"),
                problem: "`parallelization_workers` is not a number".into(),
            }),
        }
    }

    /// Claims the submission with one conditional write. A new submission needs no record;
    /// a resume needs a record that is no longer being evaluated. Anything else is a
    /// duplicate delivery.
    pub async fn claim(&self, record: &NewRecord) -> Result<Claim> {
        let mut item = Self::key(record.team_id, record.submission_id);
        item.extend([
            (
                "submission_status".to_string(),
                s(RecordStatus::Queued.as_str()),
            ),
            ("team_name".to_string(), s(&record.team_name)),
            ("track_id".to_string(), n(record.track_id)),
            ("track_name".to_string(), s(&record.track_name)),
            ("submitted_image_uri".to_string(), s(&record.image)),
            ("parallelization_workers".to_string(), n(record.workers)),
            ("submitted_time".to_string(), s(&record.submitted_time)),
            ("claimed_by".to_string(), s(&record.claimed_by)),
        ]);
        let mut request = self
            .client
            .put_item()
            .table_name(&self.table)
            .set_item(Some(item));
        request = if record.resuming {
            request
                .condition_expression(
                    "attribute_not_exists(submission_id) OR submission_status IN (:finished, :failed, :cancelled)",
                )
                .expression_attribute_values(":finished", s(RecordStatus::Finished.as_str()))
                .expression_attribute_values(":failed", s(RecordStatus::Failed.as_str()))
                .expression_attribute_values(":cancelled", s(RecordStatus::Cancelled.as_str()))
        } else {
            request.condition_expression("attribute_not_exists(submission_id)")
        };
        match request.send().await {
            Ok(_) => Ok(Claim::Claimed),
            Err(e)
                if e.as_service_error()
                    .is_some_and(|e| e.is_conditional_check_failed_exception()) =>
            {
                let current = self.get(record.team_id, record.submission_id).await?;
                let text = |k: &str| {
                    current
                        .as_ref()
                        .and_then(|item| item.get(k))
                        .and_then(|v| v.as_s().ok())
                        .cloned()
                };
                if text("claimed_by").as_deref() == Some(record.claimed_by.as_str()) {
                    // Our own earlier attempt (a Lambda retry): the claim is ours.
                    return Ok(Claim::Claimed);
                }
                Ok(Claim::Duplicate {
                    status: text("submission_status"),
                    claimed_by: text("claimed_by"),
                })
            }
            Err(e) => Err(AwsError::sdk("dynamodb", "PutItem", e)),
        }
    }

    /// RUNNING, with the first start time kept and the progress updated.
    pub async fn mark_running(
        &self,
        team_id: u64,
        submission_id: u64,
        start_time: &str,
        progress: (u64, u64),
    ) -> Result<()> {
        self.client
            .update_item()
            .table_name(&self.table)
            .set_key(Some(Self::key(team_id, submission_id)))
            .update_expression(
                "SET submission_status = :running, start_time = if_not_exists(start_time, :start), routes_done = :done, routes_total = :total",
            )
            .condition_expression("attribute_exists(submission_id)")
            .expression_attribute_values(":running", s(RecordStatus::Running.as_str()))
            .expression_attribute_values(":start", s(start_time))
            .expression_attribute_values(":done", n(progress.0))
            .expression_attribute_values(":total", n(progress.1))
            .send()
            .await
            .map_err(|e| AwsError::sdk("dynamodb", "UpdateItem", e))?;
        Ok(())
    }

    /// The final record, every metric as its own attribute.
    pub async fn finish(
        &self,
        team_id: u64,
        submission_id: u64,
        record: &FinalRecord,
    ) -> Result<()> {
        let mut set = vec![
            "submission_status = :status".to_string(),
            "end_time = :end".to_string(),
            "results = :results".to_string(),
            "routes_done = :done".to_string(),
            "routes_total = :total".to_string(),
        ];
        let mut values = HashMap::from([
            (":status".to_string(), s(record.status.as_str())),
            (":end".to_string(), s(&record.end_time)),
            (":results".to_string(), s(&record.results)),
            (":done".to_string(), n(record.progress.0)),
            (":total".to_string(), n(record.progress.1)),
        ]);
        let mut names = HashMap::new();
        for (i, (attribute, value)) in record.metrics.iter().enumerate() {
            if !value.is_finite() {
                continue;
            }
            set.push(format!("#m{i} = :m{i}"));
            names.insert(format!("#m{i}"), attribute.to_string());
            values.insert(format!(":m{i}"), n(value));
        }
        let mut expression = format!("SET {}", set.join(", "));
        names.insert("#error".into(), "error".into());
        match &record.error {
            Some(error) => {
                expression.push_str(", #error = :error");
                values.insert(":error".into(), s(error));
            }
            // A resumed submission that now finishes must not keep the old run's error.
            None => expression.push_str(" REMOVE #error"),
        }
        self.client
            .update_item()
            .table_name(&self.table)
            .set_key(Some(Self::key(team_id, submission_id)))
            .update_expression(expression)
            .set_expression_attribute_names(Some(names))
            .set_expression_attribute_values(Some(values))
            .send()
            .await
            .map_err(|e| AwsError::sdk("dynamodb", "UpdateItem", e))?;
        Ok(())
    }
}

/// The qualifier table: which team passed which qualifier track.
#[derive(Debug, Clone)]
pub struct QualifierTable {
    client: Client,
    table: String,
}

impl QualifierTable {
    /// The table `table` through `client`.
    pub fn new(client: Client, table: impl Into<String>) -> Self {
        QualifierTable {
            client,
            table: table.into(),
        }
    }

    /// Whether the team passed `track` (a qualifier track codename).
    pub async fn passed(&self, team_id: u64, track: &str) -> Result<bool> {
        let out = self
            .client
            .get_item()
            .table_name(&self.table)
            .key("team_id", n(team_id))
            .key("track_codename", s(track))
            .consistent_read(true)
            .send()
            .await
            .map_err(|e| AwsError::sdk("dynamodb", "GetItem", e))?;
        Ok(out
            .item
            .and_then(|item| item.get("passed").and_then(|v| v.as_bool().ok()).copied())
            .unwrap_or(false))
    }

    /// Records a qualifier outcome. A pass is never overwritten by a later fail.
    pub async fn record(
        &self,
        team_id: u64,
        track: &str,
        submission_id: u64,
        passed: bool,
        metrics: &[(&'static str, f64)],
    ) -> Result<()> {
        let mut item = HashMap::from([
            ("team_id".to_string(), n(team_id)),
            ("track_codename".to_string(), s(track)),
            ("submission_id".to_string(), n(submission_id)),
            ("passed".to_string(), AttributeValue::Bool(passed)),
        ]);
        for (attribute, value) in metrics.iter().filter(|(_, v)| v.is_finite()) {
            item.insert(attribute.to_string(), n(value));
        }
        let result = self
            .client
            .put_item()
            .table_name(&self.table)
            .set_item(Some(item))
            .condition_expression(
                "attribute_not_exists(team_id) OR passed = :false OR :passed = :true",
            )
            .expression_attribute_values(":false", AttributeValue::Bool(false))
            .expression_attribute_values(":true", AttributeValue::Bool(true))
            .expression_attribute_values(":passed", AttributeValue::Bool(passed))
            .send()
            .await;
        match result {
            Ok(_) => Ok(()),
            Err(e)
                if e.as_service_error()
                    .is_some_and(|e| e.is_conditional_check_failed_exception()) =>
            {
                Ok(())
            }
            Err(e) => Err(AwsError::sdk("dynamodb", "PutItem", e)),
        }
    }
}
