//! The submission record's attributes, named once, and the record read back typed: what
//! Intake, the Monitor and Finalize write (`dynamo`) and what `lbctl` and the rehearsal read.
//!
//! The original layout keeps strings (`-` for a value not known yet); attributes of ours may
//! be numbers. A reader takes either, and a value of the wrong shape reads as absent.

use std::collections::HashMap;

use aws_sdk_dynamodb::types::AttributeValue;

use lb_domain::status::RecordStatus;

/// The attributes' names, as stored.
pub mod attr {
    /// Partition key: EvalAI's participant team id.
    pub const TEAM_ID: &str = "team_id";
    /// Sort key: EvalAI's submission id.
    pub const SUBMISSION_ID: &str = "submission_id";
    /// [`lb_domain::status::RecordStatus`].
    pub const STATUS: &str = "submission_status";
    /// The team's name on EvalAI.
    pub const TEAM_NAME: &str = "team_name";
    /// EvalAI's phase id.
    pub const TRACK_ID: &str = "track_id";
    /// The track's codename.
    pub const TRACK_NAME: &str = "track_name";
    /// The participant's image as submitted.
    pub const IMAGE: &str = "submitted_image_uri";
    /// Simulator-agent pairs (an operator may set it before a resume).
    pub const WORKERS: &str = "parallelization_workers";
    /// When it was claimed.
    pub const SUBMITTED_TIME: &str = "submitted_time";
    /// When its first pair started.
    pub const START_TIME: &str = "start_time";
    /// When it ended.
    pub const END_TIME: &str = "end_time";
    /// Routes done.
    pub const ROUTES_DONE: &str = "routes_done";
    /// Routes planned.
    pub const ROUTES_TOTAL: &str = "routes_total";
    /// `s3://bucket/id` of the results.
    pub const RESULTS: &str = "results";
    /// Why it failed.
    pub const ERROR: &str = "error";
    /// Whose failure it was, when the platform's own ([`PLATFORM`]); absent otherwise.
    pub const FAILED_BY: &str = "failed_by";
    /// [`FAILED_BY`]'s one value.
    pub const PLATFORM: &str = "platform";
    /// The execution that claimed it.
    pub const CLAIMED_BY: &str = "claimed_by";
    /// Routes whose recording passed the audit.
    pub const RECORDINGS_FOUND: &str = "recordings_found";
    /// Routes that need one.
    pub const RECORDINGS_EXPECTED: &str = "recordings_expected";
    /// The first failures of the audit, with their reasons.
    pub const RECORDINGS_FAILED: &str = "recordings_failed";
    /// GPU-seconds held by its pods.
    pub const GPU_SECONDS: &str = "gpu_seconds";
    /// Of which on Spot.
    pub const GPU_SECONDS_SPOT: &str = "gpu_seconds_spot";
    /// Of which run again after reclaims.
    pub const GPU_SECONDS_RUN_AGAIN: &str = "gpu_seconds_run_again";
    /// Seconds reclaims cost the evaluation.
    pub const SECONDS_LOST: &str = "seconds_lost_to_reclaims";
    /// Dollars for the GPUs, when every second had a price.
    pub const COST_USD: &str = "cost_usd";
    /// The orchestration's dollars.
    pub const ORCHESTRATION_USD: &str = "orchestration_usd";
    /// State transitions counted.
    pub const STATE_TRANSITIONS: &str = "state_transitions";
    /// Bytes of logs kept in S3.
    pub const LOG_BYTES_STORED: &str = "log_bytes_stored";
    /// Log objects kept in S3 (the protocol's own files aside).
    pub const LOG_OBJECTS_STORED: &str = "log_objects_stored";
    /// Files logcopy refused.
    pub const UPLOADS_REFUSED: &str = "uploads_refused";
    /// The image digest the pods ran.
    pub const IMAGE_DIGEST: &str = "image_digest";

    /// Every attribute of the layout, in the order `lbctl` shows them; anything else in a
    /// record is a metric.
    pub const LAYOUT: &[&str] = &[
        TEAM_ID,
        SUBMISSION_ID,
        STATUS,
        TEAM_NAME,
        TRACK_ID,
        TRACK_NAME,
        IMAGE,
        WORKERS,
        SUBMITTED_TIME,
        START_TIME,
        END_TIME,
        ROUTES_DONE,
        ROUTES_TOTAL,
        RESULTS,
        ERROR,
        FAILED_BY,
        CLAIMED_BY,
        RECORDINGS_FOUND,
        RECORDINGS_EXPECTED,
        RECORDINGS_FAILED,
        GPU_SECONDS,
        GPU_SECONDS_SPOT,
        GPU_SECONDS_RUN_AGAIN,
        SECONDS_LOST,
        COST_USD,
        ORCHESTRATION_USD,
        STATE_TRANSITIONS,
        LOG_BYTES_STORED,
        LOG_OBJECTS_STORED,
        IMAGE_DIGEST,
        UPLOADS_REFUSED,
    ];
}

/// The GPUs a run used, as the record keeps them (the Monitor each round, Finalize at the end).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RecordUsage {
    /// GPU-seconds held by its pods.
    pub gpu_seconds: u64,
    /// Of which on Spot capacity.
    pub spot: u64,
    /// Of which spent again on routes a reclaim interrupted.
    pub run_again: u64,
    /// Seconds reclaims cost the evaluation (not counted against its time limit).
    pub lost: u64,
    /// Dollars, when every second had a price.
    pub dollars: Option<f64>,
    /// The orchestration's dollars (state transitions, Lambda, DynamoDB), once counted.
    pub orchestration: Option<f64>,
}

/// A submission record read back: each attribute of the layout typed, absent when missing or
/// of another shape, and the item whole for what only shows it (metrics, `--json`).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct StoredRecord {
    /// EvalAI's team id.
    pub team_id: Option<u64>,
    /// EvalAI's submission id.
    pub submission_id: Option<u64>,
    /// The status, when it is one of ours.
    pub status: Option<RecordStatus>,
    /// The status as stored (empty when absent), for display.
    pub status_word: String,
    /// The team's name.
    pub team_name: Option<String>,
    /// EvalAI's phase id.
    pub track_id: Option<u64>,
    /// The track's codename.
    pub track_name: Option<String>,
    /// The image as submitted.
    pub image: Option<String>,
    /// The digest its pods ran.
    pub image_digest: Option<String>,
    /// Simulator-agent pairs.
    pub workers: Option<u64>,
    /// Routes done and planned.
    pub routes: (Option<u64>, Option<u64>),
    /// When it was claimed, started and ended (`2024-03-07 10:31:02 UTC`, or `-`).
    pub submitted_time: Option<String>,
    /// See [`submitted_time`](Self::submitted_time).
    pub start_time: Option<String>,
    /// See [`submitted_time`](Self::submitted_time).
    pub end_time: Option<String>,
    /// Where the results are.
    pub results: Option<String>,
    /// Why it failed.
    pub error: Option<String>,
    /// It failed for the platform's own failure, not the participant's.
    pub failed_by_platform: bool,
    /// The execution that claimed it.
    pub claimed_by: Option<String>,
    /// Routes whose recording passed the audit, and the routes that need one (FINISHED only).
    pub recordings: Option<(u64, u64)>,
    /// The audit's first failures, each with its reason.
    pub recordings_failed: Vec<String>,
    /// The GPUs it used, once counted.
    pub usage: Option<RecordUsage>,
    /// State transitions counted.
    pub state_transitions: Option<u64>,
    /// Bytes of logs kept in S3.
    pub log_bytes_stored: Option<u64>,
    /// Log objects kept in S3.
    pub log_objects_stored: Option<u64>,
    /// Files logcopy refused.
    pub uploads_refused: Option<u64>,
    /// The item as stored.
    pub item: HashMap<String, AttributeValue>,
}

impl StoredRecord {
    /// Reads `item`, which came from the submissions table.
    pub fn from_item(item: HashMap<String, AttributeValue>) -> StoredRecord {
        let text = |key: &str| item.get(key)?.as_s().ok().cloned();
        let number = |key: &str| match item.get(key)? {
            AttributeValue::S(v) | AttributeValue::N(v) => v.trim().parse::<u64>().ok(),
            _ => None,
        };
        let amount = |key: &str| match item.get(key)? {
            AttributeValue::N(v) => v
                .trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite() && *v >= 0.0),
            _ => None,
        };
        let status_word = text(attr::STATUS).unwrap_or_default();
        let usage = number(attr::GPU_SECONDS).map(|gpu_seconds| RecordUsage {
            gpu_seconds,
            spot: number(attr::GPU_SECONDS_SPOT).unwrap_or(0),
            run_again: number(attr::GPU_SECONDS_RUN_AGAIN).unwrap_or(0),
            lost: number(attr::SECONDS_LOST).unwrap_or(0),
            dollars: amount(attr::COST_USD),
            orchestration: amount(attr::ORCHESTRATION_USD),
        });
        let recordings_failed = match item.get(attr::RECORDINGS_FAILED) {
            Some(AttributeValue::L(items)) => items
                .iter()
                .filter_map(|v| v.as_s().ok().cloned())
                .collect(),
            _ => Vec::new(),
        };
        StoredRecord {
            team_id: number(attr::TEAM_ID),
            submission_id: number(attr::SUBMISSION_ID),
            status: status_word.parse().ok(),
            status_word,
            team_name: text(attr::TEAM_NAME),
            track_id: number(attr::TRACK_ID),
            track_name: text(attr::TRACK_NAME),
            image: text(attr::IMAGE),
            image_digest: text(attr::IMAGE_DIGEST),
            workers: number(attr::WORKERS),
            routes: (number(attr::ROUTES_DONE), number(attr::ROUTES_TOTAL)),
            submitted_time: text(attr::SUBMITTED_TIME),
            start_time: text(attr::START_TIME),
            end_time: text(attr::END_TIME),
            results: text(attr::RESULTS),
            error: text(attr::ERROR),
            failed_by_platform: text(attr::FAILED_BY).as_deref() == Some(attr::PLATFORM),
            claimed_by: text(attr::CLAIMED_BY),
            recordings: number(attr::RECORDINGS_FOUND).zip(number(attr::RECORDINGS_EXPECTED)),
            recordings_failed,
            usage,
            state_transitions: number(attr::STATE_TRANSITIONS),
            log_bytes_stored: number(attr::LOG_BYTES_STORED),
            log_objects_stored: number(attr::LOG_OBJECTS_STORED),
            uploads_refused: number(attr::UPLOADS_REFUSED),
            item,
        }
    }

    /// FINISHED, FAILED or CANCELLED.
    pub fn is_final(&self) -> bool {
        self.status.is_some_and(RecordStatus::is_final)
    }

    /// A FINISHED result some of whose routes lack a recording that passed the audit.
    pub fn is_unaudited(&self) -> bool {
        self.recordings
            .is_some_and(|(found, expected)| found < expected)
    }

    /// The attributes outside the layout (the metrics, mostly), sorted by name.
    pub fn extra_attributes(&self) -> Vec<(&str, &AttributeValue)> {
        let mut out: Vec<(&str, &AttributeValue)> = self
            .item
            .iter()
            .filter(|(k, _)| !attr::LAYOUT.contains(&k.as_str()))
            .map(|(k, v)| (k.as_str(), v))
            .collect();
        out.sort_by(|a, b| a.0.cmp(b.0));
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn item(pairs: &[(&str, AttributeValue)]) -> HashMap<String, AttributeValue> {
        pairs
            .iter()
            .map(|(k, v)| (k.to_string(), v.clone()))
            .collect()
    }

    #[test]
    fn the_original_strings_and_our_numbers_both_read_and_a_wrong_shape_reads_as_absent() {
        let s = |v: &str| AttributeValue::S(v.into());
        let n = |v: &str| AttributeValue::N(v.into());
        let record = StoredRecord::from_item(item(&[
            (attr::TEAM_ID, s("3")),
            (attr::SUBMISSION_ID, n("7")),
            (attr::STATUS, s("FINISHED")),
            (attr::ROUTES_DONE, s("-")),
            (attr::ROUTES_TOTAL, n("20")),
            (attr::RECORDINGS_FOUND, n("18")),
            (attr::RECORDINGS_EXPECTED, n("20")),
            (
                attr::RECORDINGS_FAILED,
                AttributeValue::L(vec![s("r1: 45 bytes"), n("1")]),
            ),
            (attr::GPU_SECONDS, n("7200")),
            (attr::COST_USD, n("-1")),
            (attr::TEAM_NAME, AttributeValue::Bool(true)),
            ("driving_score", n("41.25")),
        ]));
        assert_eq!((record.team_id, record.submission_id), (Some(3), Some(7)));
        assert_eq!(record.status, Some(RecordStatus::Finished));
        assert_eq!(record.routes, (None, Some(20)));
        assert_eq!(record.team_name, None);
        assert!(record.is_final() && record.is_unaudited());
        assert_eq!(record.recordings_failed, ["r1: 45 bytes"]);
        let usage = record.usage.unwrap();
        assert_eq!(
            (usage.gpu_seconds, usage.spot, usage.dollars),
            (7200, 0, None)
        );
        let extra: Vec<&str> = record.extra_attributes().iter().map(|(k, _)| *k).collect();
        assert_eq!(extra, ["driving_score"]);
    }

    #[test]
    fn a_status_that_is_none_of_ours_is_kept_as_a_word_only() {
        let record =
            StoredRecord::from_item(item(&[(attr::STATUS, AttributeValue::S("PAUSED".into()))]));
        assert_eq!(
            (record.status, record.status_word.as_str()),
            (None, "PAUSED")
        );
        assert!(!record.is_final());
    }
}
