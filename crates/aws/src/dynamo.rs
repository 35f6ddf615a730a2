//! DynamoDB: the claim that makes a duplicate SQS delivery harmless, the submission record,
//! and the qualifier table, in the layout the original system left operators
//! (`docs/reference/original-system.md`), so they switch without a migration.
//!
//! Submissions table: partition key `team_id` (S), sort key `submission_id` (S); the original
//! attributes are strings, `-` for a value not known yet, times as `2024-03-07 10:31:02 UTC`.
//! Attributes of ours (`claimed_by`, `error`, `routes_done`, `routes_total`) may be typed.
//! Qualifier table: partition key `team_id` (S), sort key `track_codename` (S): an item admits
//! the team to the track it names (the target track, not the qualifier).

use std::collections::HashMap;

use aws_sdk_dynamodb::types::AttributeValue;
use aws_sdk_dynamodb::Client;

use lb_domain::capacity::cost::Totals;
use lb_domain::run::audit::Recordings;

use crate::record::{attr, StoredRecord};
use crate::{condition_failed, AwsError, Result};

pub use lb_domain::status::RecordStatus;

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
    /// When the claim happened ([`record_time`]).
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
        /// The record's status, if it could be read and is one of ours.
        status: Option<RecordStatus>,
        /// The execution that holds it.
        claimed_by: Option<String>,
    },
}

/// The final record: status, times, results location, one attribute per metric.
#[derive(Debug, Clone, PartialEq)]
pub struct FinalRecord {
    /// Final status.
    pub status: RecordStatus,
    /// [`record_time`].
    pub end_time: String,
    /// `s3://bucket/id` of the results.
    pub results: String,
    /// (attribute, value as EvalAI got it) per metric of the leaderboard, e.g.
    /// (`driving_score`, `Some("41.2")`); `None` is stored as `-`.
    pub metrics: Vec<(&'static str, Option<String>)>,
    /// Routes done / planned.
    pub progress: (u64, u64),
    /// Why it failed, readable.
    pub error: Option<String>,
    /// The failure was the platform's own (`failed_by`), not the participant's.
    pub failed_by_platform: bool,
    /// The audit of the result's CARLA recordings (FINISHED only): what an operator can check
    /// of its scores (`lb_domain::run::audit`).
    pub recordings: Option<Recordings>,
    /// The GPUs it used and their price (a run from before the Monitor counted them: none).
    pub usage: Option<Totals>,
}

/// What to keep of a Scan.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScanFilter {
    /// Every record.
    All,
    /// The records of one submission id (any team).
    Submission(u64),
    /// Records still queued or running.
    InFlight,
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

/// What the original writes for a value not known yet.
pub const UNKNOWN: &str = "-";

/// A time as the original records it: `2024-03-07 10:31:02 UTC`.
pub fn record_time(at: time::OffsetDateTime) -> String {
    let at = at.to_offset(time::UtcOffset::UTC);
    format!(
        "{:04}-{:02}-{:02} {:02}:{:02}:{:02} UTC",
        at.year(),
        u8::from(at.month()),
        at.day(),
        at.hour(),
        at.minute(),
        at.second()
    )
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
            (attr::TEAM_ID.to_string(), s(team_id.to_string())),
            (
                attr::SUBMISSION_ID.to_string(),
                s(submission_id.to_string()),
            ),
        ])
    }

    /// The record read back typed, if any.
    pub async fn record(&self, team_id: u64, submission_id: u64) -> Result<Option<StoredRecord>> {
        Ok(self
            .get(team_id, submission_id)
            .await?
            .map(StoredRecord::from_item))
    }

    /// The table's records (or those `filter` keeps), a Scan of at most `max_pages` pages;
    /// `false` when it stopped there.
    pub async fn scan(
        &self,
        filter: ScanFilter,
        max_pages: usize,
    ) -> Result<(Vec<StoredRecord>, bool)> {
        let mut records = Vec::new();
        let mut start: Option<HashMap<String, AttributeValue>> = None;
        for _ in 0..max_pages {
            let mut request = self
                .client
                .scan()
                .table_name(&self.table)
                .consistent_read(true)
                .set_exclusive_start_key(start.take());
            request = match filter {
                ScanFilter::All => request,
                ScanFilter::Submission(id) => request
                    .filter_expression("#id = :id")
                    .expression_attribute_names("#id", attr::SUBMISSION_ID)
                    // The original layout: ids are strings.
                    .expression_attribute_values(":id", s(id.to_string())),
                ScanFilter::InFlight => {
                    let [a, b, c] = RecordStatus::IN_FLIGHT.map(|v| s(v.as_str()));
                    request
                        .filter_expression("#status IN (:a, :b, :c)")
                        .expression_attribute_names("#status", attr::STATUS)
                        .expression_attribute_values(":a", a)
                        .expression_attribute_values(":b", b)
                        .expression_attribute_values(":c", c)
                }
            };
            let page = request
                .send()
                .await
                .map_err(|e| AwsError::sdk("dynamodb", "Scan", e))?;
            records.extend(
                page.items
                    .unwrap_or_default()
                    .into_iter()
                    .map(StoredRecord::from_item),
            );
            match page.last_evaluated_key {
                Some(key) if !key.is_empty() => start = Some(key),
                _ => return Ok((records, true)),
            }
        }
        Ok((records, false))
    }

    /// The whole item, if any.
    async fn get(
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

    /// The operator's per-submission worker count (`parallelization_workers`), if set: a
    /// string as the original writes it (`-` or empty: not set), or a number.
    pub async fn worker_override(&self, team_id: u64, submission_id: u64) -> Result<Option<u32>> {
        let Some(item) = self.get(team_id, submission_id).await? else {
            return Ok(None);
        };
        let malformed = |problem: String| AwsError::Malformed {
            what: format!("team {team_id} submission {submission_id}"),
            problem,
        };
        let text = match item.get(attr::WORKERS) {
            None => return Ok(None),
            Some(AttributeValue::S(v)) if v.trim().is_empty() || v.trim() == UNKNOWN => {
                return Ok(None)
            }
            Some(AttributeValue::S(v) | AttributeValue::N(v)) => v.trim(),
            Some(_) => {
                return Err(malformed(
                    "`parallelization_workers` is neither a string nor a number".into(),
                ))
            }
        };
        text.parse::<u32>()
            .ok()
            .filter(|w| *w > 0)
            .map(Some)
            .ok_or_else(|| {
                malformed(format!(
                    "`parallelization_workers` is `{}`, not a positive integer",
                    text.escape_debug()
                ))
            })
    }

    /// Claims the submission with one conditional write. A new submission needs no record;
    /// a resume needs a record that is no longer being evaluated. Anything else is a
    /// duplicate delivery.
    pub async fn claim(&self, record: &NewRecord) -> Result<Claim> {
        let status = if record.resuming {
            RecordStatus::Resuming
        } else {
            RecordStatus::Submitted
        };
        let mut item = Self::key(record.team_id, record.submission_id);
        item.extend([
            (attr::STATUS.to_string(), s(status.as_str())),
            (attr::TEAM_NAME.to_string(), s(&record.team_name)),
            (attr::TRACK_ID.to_string(), s(record.track_id.to_string())),
            (attr::TRACK_NAME.to_string(), s(&record.track_name)),
            (attr::IMAGE.to_string(), s(&record.image)),
            (attr::WORKERS.to_string(), s(record.workers.to_string())),
            (attr::SUBMITTED_TIME.to_string(), s(&record.submitted_time)),
            (attr::START_TIME.to_string(), s(UNKNOWN)),
            (attr::END_TIME.to_string(), s(UNKNOWN)),
            (attr::CLAIMED_BY.to_string(), s(&record.claimed_by)),
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
            Err(e) if condition_failed(&e) => {
                let current = self.get(record.team_id, record.submission_id).await?;
                let text = |k: &str| {
                    current
                        .as_ref()
                        .and_then(|item| item.get(k))
                        .and_then(|v| v.as_s().ok())
                        .cloned()
                };
                if text(attr::CLAIMED_BY).as_deref() == Some(record.claimed_by.as_str()) {
                    // Our own earlier attempt (a Lambda retry): the claim is ours.
                    return Ok(Claim::Claimed);
                }
                Ok(Claim::Duplicate {
                    status: text(attr::STATUS).and_then(|s| s.parse().ok()),
                    claimed_by: text(attr::CLAIMED_BY),
                })
            }
            Err(e) => Err(AwsError::sdk("dynamodb", "PutItem", e)),
        }
    }

    /// RUNNING, with the results location, the progress, the GPU usage so far, and the first
    /// start time kept (the original writes `-` until then). One write when the run had
    /// started before, two on the round that starts it.
    pub async fn mark_running(
        &self,
        team_id: u64,
        submission_id: u64,
        (start_time, results): (&str, &str),
        progress: (u64, u64),
        (usage, image): (Option<&Totals>, Option<&str>),
    ) -> Result<()> {
        let update = |first: bool| {
            let mut expression = "SET submission_status = :running, results = :results, routes_done = :done, routes_total = :total".to_string();
            let (mut usage_set, mut usage_values) = usage.map(usage_update).unwrap_or_default();
            if let Some(image) = image {
                // The digest every pod of the run is held to (`lb_domain::run::monitor::hold_image`).
                usage_set.push("image_digest = :image".into());
                usage_values.insert(":image".into(), s(image));
            }
            for set in usage_set {
                expression.push_str(", ");
                expression.push_str(&set);
            }
            let mut request = self
                .client
                .update_item()
                .table_name(&self.table)
                .set_key(Some(Self::key(team_id, submission_id)))
                .set_expression_attribute_values(Some(
                    usage_values
                        .into_iter()
                        .chain([
                            (":running".to_string(), s(RecordStatus::Running.as_str())),
                            (":results".to_string(), s(results)),
                            (":done".to_string(), n(progress.0)),
                            (":total".to_string(), n(progress.1)),
                        ])
                        .collect(),
                ));
            if first {
                expression.push_str(", start_time = :start");
                request = request
                    .condition_expression("attribute_exists(submission_id)")
                    .expression_attribute_values(":start", s(start_time));
            } else {
                // Fails (and the caller writes the start time) while it is `-` or absent.
                request = request
                    .condition_expression(
                        "attribute_exists(submission_id) AND start_time <> :unknown",
                    )
                    .expression_attribute_values(":unknown", s(UNKNOWN));
            }
            request.update_expression(expression)
        };
        match update(false).send().await {
            Ok(_) => Ok(()),
            Err(e) if condition_failed(&e) => {
                update(true)
                    .send()
                    .await
                    .map_err(|e| AwsError::sdk("dynamodb", "UpdateItem", e))?;
                Ok(())
            }
            Err(e) => Err(AwsError::sdk("dynamodb", "UpdateItem", e)),
        }
    }

    /// Who holds the submission and in which status, as stored (`None`: no record). A status
    /// that is none of ours is [`AwsError::Malformed`], naming it.
    pub async fn standing(&self, team_id: u64, submission_id: u64) -> Result<Option<Standing>> {
        let Some(item) = self.get(team_id, submission_id).await? else {
            return Ok(None);
        };
        let text = |k: &str| item.get(k).and_then(|v| v.as_s().ok()).cloned();
        let status = text(attr::STATUS)
            .map(|s| s.parse::<RecordStatus>())
            .transpose()
            .map_err(|e| AwsError::Malformed {
                what: format!("of submission {submission_id} (team {team_id})"),
                problem: e.to_string(),
            })?;
        Ok(Some(Standing {
            claimed_by: text(attr::CLAIMED_BY),
            status,
            error: text(attr::ERROR),
            failed_by_platform: text(attr::FAILED_BY).as_deref() == Some(attr::PLATFORM),
        }))
    }

    /// The final record, every metric as its own attribute, written only while execution
    /// `claimed_by` holds the submission and it is still in flight: a stale execution (one a
    /// resume superseded) or a second Finalize changes nothing. `false` when it did not write.
    pub async fn finish(
        &self,
        team_id: u64,
        submission_id: u64,
        claimed_by: &str,
        record: &FinalRecord,
    ) -> Result<bool> {
        let (expression, mut names, mut values) = final_update(record);
        names.insert("#claimed_by".into(), attr::CLAIMED_BY.into());
        names.insert("#status".into(), attr::STATUS.into());
        values.insert(":me".into(), s(claimed_by));
        let in_flight: Vec<String> = RecordStatus::IN_FLIGHT
            .iter()
            .enumerate()
            .map(|(i, status)| {
                values.insert(format!(":f{i}"), s(status.as_str()));
                format!(":f{i}")
            })
            .collect();
        let result = self
            .client
            .update_item()
            .table_name(&self.table)
            .set_key(Some(Self::key(team_id, submission_id)))
            .update_expression(expression)
            .condition_expression(format!(
                "#claimed_by = :me AND #status IN ({})",
                in_flight.join(", ")
            ))
            .set_expression_attribute_names(Some(names))
            .set_expression_attribute_values(Some(values))
            .send()
            .await;
        match result {
            Ok(_) => Ok(true),
            Err(e) if condition_failed(&e) => Ok(false),
            Err(e) => Err(AwsError::sdk("dynamodb", "UpdateItem", e)),
        }
    }
}

/// The usage attributes (`SET` clauses and their values): GPU-seconds in all, on Spot, run
/// again after a reclaim, the evaluation's seconds lost to reclaims, the estimate in dollars
/// when every second had a price, the logs' bytes stored and the uploads refused when read,
/// and the orchestration's own when counted.
fn usage_update(usage: &Totals) -> (Vec<String>, HashMap<String, AttributeValue>) {
    let mut set = vec![
        "gpu_seconds = :gpu".to_string(),
        "gpu_seconds_spot = :gpu_spot".to_string(),
        "gpu_seconds_run_again = :gpu_again".to_string(),
        "seconds_lost_to_reclaims = :lost".to_string(),
    ];
    let mut values = HashMap::from([
        (":gpu".to_string(), n(usage.gpu_seconds)),
        (":gpu_spot".to_string(), n(usage.spot)),
        (":gpu_again".to_string(), n(usage.run_again)),
        (":lost".to_string(), n(usage.lost)),
    ]);
    if let Some(dollars) = usage.dollars {
        set.push("cost_usd = :cost".into());
        values.insert(":cost".into(), n(format!("{dollars:.2}")));
    }
    if let Some(stored) = usage.stored {
        set.push(
            "log_bytes_stored = :stored, log_objects_stored = :objects, uploads_refused = :refused"
                .into(),
        );
        values.insert(":stored".into(), n(stored.log_bytes));
        values.insert(":objects".into(), n(stored.log_objects));
        values.insert(":refused".into(), n(stored.refused_files));
    }
    if let Some(orchestration) = usage.orchestration {
        set.push("orchestration_usd = :orchestration, state_transitions = :transitions".into());
        let dollars = orchestration.dollars();
        values.insert(":orchestration".into(), n(format!("{dollars:.4}")));
        values.insert(":transitions".into(), n(orchestration.transitions));
    }
    (set, values)
}

/// The final record's update: every attribute it sets, the error and the recordings' count
/// removed when the record has none (a resumed submission must not keep an older run's).
type Update = (
    String,
    HashMap<String, String>,
    HashMap<String, AttributeValue>,
);

/// Clauses of an update: what it sets, with the names and values they use, and what it
/// removes.
#[derive(Default)]
struct Clauses {
    set: Vec<String>,
    remove: Vec<&'static str>,
    names: HashMap<String, String>,
    values: HashMap<String, AttributeValue>,
}

/// The failure's reason and whose it was, set or removed: a resumed submission that now
/// finishes (or fails otherwise) must not keep the old run's.
fn failure_clauses(record: &FinalRecord) -> Clauses {
    let mut c = Clauses::default();
    c.names.insert("#error".into(), attr::ERROR.into());
    match &record.error {
        Some(error) => {
            c.set.push("#error = :error".into());
            c.values.insert(":error".into(), s(error));
        }
        None => c.remove.push("#error"),
    }
    c.names.insert("#failed_by".into(), attr::FAILED_BY.into());
    match record.failed_by_platform {
        true => {
            c.set.push("#failed_by = :failed_by".into());
            c.values.insert(":failed_by".into(), s(attr::PLATFORM));
        }
        false => c.remove.push("#failed_by"),
    }
    c
}

fn final_update(record: &FinalRecord) -> Update {
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
        set.push(format!("#m{i} = :m{i}"));
        names.insert(format!("#m{i}"), attribute.to_string());
        values.insert(format!(":m{i}"), s(value.as_deref().unwrap_or(UNKNOWN)));
    }
    let failure = failure_clauses(record);
    let mut remove = failure.remove;
    set.extend(failure.set);
    names.extend(failure.names);
    values.extend(failure.values);
    names.insert("#found".into(), attr::RECORDINGS_FOUND.into());
    names.insert("#expected".into(), attr::RECORDINGS_EXPECTED.into());
    names.insert("#failed".into(), attr::RECORDINGS_FAILED.into());
    match &record.recordings {
        Some(audited) => {
            set.push("#found = :found, #expected = :expected".into());
            values.insert(":found".into(), n(audited.passed));
            values.insert(":expected".into(), n(audited.expected));
            match audited.failures.is_empty() {
                true => remove.push("#failed"),
                false => {
                    set.push("#failed = :failed".into());
                    let failed = audited.failures.iter().map(s).collect();
                    values.insert(":failed".into(), AttributeValue::L(failed));
                }
            }
        }
        // Nor an old run's audit of recordings.
        None => remove.extend(["#found", "#expected", "#failed"]),
    }
    match &record.usage {
        Some(usage) => {
            let (usage_set, usage_values) = usage_update(usage);
            set.extend(usage_set);
            values.extend(usage_values);
        }
        // Nor an old run's usage, when this one counted none.
        None => remove.extend([
            attr::GPU_SECONDS,
            attr::GPU_SECONDS_SPOT,
            attr::GPU_SECONDS_RUN_AGAIN,
            attr::SECONDS_LOST,
            attr::ORCHESTRATION_USD,
            attr::STATE_TRANSITIONS,
        ]),
    }
    if record.usage.is_none_or(|u| u.stored.is_none()) {
        remove.extend([attr::LOG_BYTES_STORED, attr::UPLOADS_REFUSED]);
    }
    if record.usage.is_none_or(|u| u.dollars.is_none()) {
        remove.push(attr::COST_USD);
    }
    let mut expression = format!("SET {}", set.join(", "));
    if !remove.is_empty() {
        expression.push_str(&format!(" REMOVE {}", remove.join(", ")));
    }
    (expression, names, values)
}

/// Who holds a submission's record, and how it stands.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Standing {
    /// The execution that claimed it last.
    pub claimed_by: Option<String>,
    /// `submission_status` as stored.
    pub status: Option<RecordStatus>,
    /// The stored failure reason.
    pub error: Option<String>,
    /// The failure was the platform's own.
    pub failed_by_platform: bool,
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

    /// Whether the team may submit to `track` (a main track): the item `(team, track)` the
    /// original system, or we, put when the team passed the track's qualifier.
    pub async fn admitted(&self, team_id: u64, track: &str) -> Result<bool> {
        let out = self
            .client
            .get_item()
            .table_name(&self.table)
            .key("team_id", s(team_id.to_string()))
            .key("track_codename", s(track))
            .consistent_read(true)
            .send()
            .await
            .map_err(|e| AwsError::sdk("dynamodb", "GetItem", e))?;
        Ok(out.item.is_some())
    }

    /// Admits the team to `track` (the target of the qualifier it passed), as the original
    /// does: the item `(team_id, track_codename)` with the qualifying `submission_id`. The
    /// first pass stays; a later one changes nothing.
    pub async fn admit(&self, team_id: u64, track: &str, submission_id: u64) -> Result<()> {
        let result = self
            .client
            .put_item()
            .table_name(&self.table)
            .item("team_id", s(team_id.to_string()))
            .item("track_codename", s(track))
            .item("submission_id", s(submission_id.to_string()))
            .condition_expression("attribute_not_exists(team_id)")
            .send()
            .await;
        match result {
            Ok(_) => Ok(()),
            Err(e) if condition_failed(&e) => Ok(()),
            Err(e) => Err(AwsError::sdk("dynamodb", "PutItem", e)),
        }
    }
}
