//! The submission as EvalAI describes it: the SQS message, statuses and who may start.
//!
//! The message is untrusted input (`docs/reference/evalai.md` §8): ids arrive as JSON
//! numbers or as numeric strings depending on the path that published them, and
//! `submitted_image_uri` can be absent. Everything is checked here, once, before anything
//! is launched.

use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::results::Leaderboard;

/// The biggest id we accept: EvalAI's primary keys are Postgres `integer`s.
pub const MAX_ID: u64 = i32::MAX as u64;

/// A validated submission message (the EventBridge Pipe's input transformer output, or the
/// raw SQS body: both carry the same keys).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SubmissionMessage {
    /// `challenge_pk`.
    pub challenge_id: u64,
    /// `phase_pk`.
    pub phase_id: u64,
    /// `submission_pk`.
    pub submission_id: u64,
    /// `submitted_image_uri`, absent on some re-runs (the GET's `input_file` has it then).
    pub image: Option<String>,
}

/// Why a submission message was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MessageError {
    /// The body is not a JSON object.
    #[error("submission message is not a JSON object: {0}")]
    NotAnObject(String),
    /// A field is missing or has the wrong shape.
    #[error("submission message field `{field}` {problem}")]
    Field {
        /// The offending key.
        field: &'static str,
        /// What is wrong with it.
        problem: String,
    },
    /// The Pipe's batch does not hold exactly one message.
    #[error("the Pipe's batch holds {0} messages, not 1: set the Pipe's batch size to 1")]
    Batch(usize),
}

crate::error_names!(MessageError {
    NotAnObject | Field => "InvalidMessage";
    Batch => "InvalidBatch";
});

impl SubmissionMessage {
    /// Parses the message body (a JSON text).
    pub fn parse(body: &str) -> Result<Self, MessageError> {
        let value: Value = serde_json::from_str(body)
            .map_err(|e| MessageError::NotAnObject(format!("invalid JSON ({e})")))?;
        Self::from_value(&value)
    }

    /// Validates what the state machine's Intake gets: the Pipe's batch (a JSON array, even
    /// for one message) or its single element (the definition unwraps it with `$[0]`).
    pub fn from_pipe(value: &Value) -> Result<Self, MessageError> {
        match value {
            Value::Array(batch) if batch.len() == 1 => Self::from_value(&batch[0]),
            Value::Array(batch) => Err(MessageError::Batch(batch.len())),
            one => Self::from_value(one),
        }
    }

    /// Validates an already-parsed message.
    pub fn from_value(value: &Value) -> Result<Self, MessageError> {
        let Value::Object(map) = value else {
            return Err(MessageError::NotAnObject(format!(
                "got {}",
                json_type(value)
            )));
        };
        let id = |field: &'static str| -> Result<u64, MessageError> {
            let problem = |problem: String| MessageError::Field { field, problem };
            match map.get(field) {
                None | Some(Value::Null) => Err(problem("is missing".into())),
                Some(v) => parse_id(v).map_err(problem),
            }
        };
        let image = match map.get("submitted_image_uri") {
            None | Some(Value::Null) => None,
            Some(Value::String(s)) if s.trim().is_empty() => None,
            Some(Value::String(s)) => Some(s.clone()),
            Some(other) => {
                return Err(MessageError::Field {
                    field: "submitted_image_uri",
                    problem: format!("must be a string, got {}", json_type(other)),
                })
            }
        };
        Ok(SubmissionMessage {
            challenge_id: id("challenge_pk")?,
            phase_id: id("phase_pk")?,
            submission_id: id("submission_pk")?,
            image,
        })
    }
}

/// An EvalAI primary key: a positive JSON integer or a string of ASCII digits.
fn parse_id(value: &Value) -> Result<u64, String> {
    let n = match value {
        Value::Number(n) => n
            .as_u64()
            .ok_or_else(|| format!("must be a positive integer, got `{n}`"))?,
        Value::String(s) => {
            if s.is_empty() || s.len() > 10 || !s.bytes().all(|b| b.is_ascii_digit()) {
                return Err(format!(
                    "must be a positive integer, got the string `{}`",
                    s.escape_debug()
                ));
            }
            s.parse::<u64>().map_err(|e| e.to_string())?
        }
        other => return Err(format!("must be an integer, got {}", json_type(other))),
    };
    if n == 0 || n > MAX_ID {
        return Err(format!("must be between 1 and {MAX_ID}, got {n}"));
    }
    Ok(n)
}

fn json_type(value: &Value) -> &'static str {
    match value {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

crate::status::words! {
    /// A submission status as EvalAI stores it (always lowercase on the wire), in EvalAI's
    /// order.
    SubmissionStatus, "submission status" {
        /// Just submitted: start an evaluation.
        Submitted => "submitted",
        /// Being uploaded by the participant.
        Submitting => "submitting",
        /// A host backend accepted it.
        Queued => "queued",
        /// Being evaluated.
        Running => "running",
        /// A failed submission the host or participant asked to resume: start again.
        Resuming => "resuming",
        /// Some results were posted.
        PartiallyEvaluated => "partially_evaluated",
        /// Final scores posted.
        Finished => "finished",
        /// The evaluation failed.
        Failed => "failed",
        /// The participant (or a re-run) cancelled it.
        Cancelled => "cancelled",
        /// Archived by the host.
        Archived => "archived",
    }
}

impl SubmissionStatus {
    /// Only these start an evaluation; anything else is a duplicate or stale message.
    pub fn starts_evaluation(self) -> bool {
        matches!(self, Self::Submitted | Self::Resuming)
    }

    /// After these nothing may be written over the submission: a write would silently undo
    /// the participant's cancel or a published score (the server does not protect them).
    pub fn is_final(self) -> bool {
        matches!(
            self,
            Self::Finished | Self::Failed | Self::Cancelled | Self::Archived
        )
    }
}

/// The submission as Intake established it: everything later stages (and the Job renderer)
/// need to know about it, carried in the execution state.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SubmissionInfo {
    /// EvalAI challenge id.
    pub challenge_id: u64,
    /// EvalAI phase id.
    pub phase_id: u64,
    /// EvalAI submission id.
    pub submission_id: u64,
    /// Participant team id.
    pub team_id: u64,
    /// Participant team name (free text, untrusted: only label-safe forms reach a Job).
    pub team_name: String,
    /// Which leaderboard (`"1.0"` or `"2.0"` in JSON).
    pub leaderboard: Leaderboard,
    /// Track codename.
    pub track: String,
    /// The participant's image (untrusted; the renderer checks it against the reference
    /// grammar).
    pub image: String,
    /// Routes of the track.
    pub routes: u32,
    /// Simulator-agent pairs.
    pub workers: u32,
    /// EvalAI said `resuming` (init removes the cancel marker).
    pub resuming: bool,
    /// The execution that claimed it (the Jobs' execution label).
    pub execution: String,
    /// When it arrived (EvalAI's `submitted_at`, epoch milliseconds): its place in the queue.
    /// `None` for a resume (it arrives again now) or when EvalAI did not say.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub arrived_ms: Option<u64>,
    /// EvalAI's `submitted_at` in epoch seconds, a resume's too (0 when EvalAI did not say):
    /// the wait stores it, so the cancel sweep asks EvalAI only for what came since the
    /// oldest submission waiting.
    #[serde(default)]
    pub submitted_at: u64,
}

impl SubmissionInfo {
    /// Everything a run needs is known: the image to run and at least one pair.
    pub fn is_complete(&self) -> bool {
        !self.image.is_empty() && self.workers >= 1
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn problem(value: Value) -> String {
        SubmissionMessage::from_value(&value)
            .unwrap_err()
            .to_string()
    }

    #[test]
    fn string_ids_from_a_new_submission_are_read_as_integers() {
        let msg = SubmissionMessage::parse(
            r#"{"challenge_pk": "12", "phase_pk": "1234", "submission_pk": 77,
                "is_static_dataset_code_upload_submission": false,
                "submitted_image_uri": "123.dkr.ecr.us-west-2.amazonaws.com/team:latest"}"#,
        )
        .unwrap();
        assert_eq!(
            msg,
            SubmissionMessage {
                challenge_id: 12,
                phase_id: 1234,
                submission_id: 77,
                image: Some("123.dkr.ecr.us-west-2.amazonaws.com/team:latest".into()),
            }
        );
    }

    #[test]
    fn a_rerun_without_image_uri_is_accepted_with_no_image() {
        let msg = SubmissionMessage::from_value(
            &json!({"challenge_pk": 1, "phase_pk": 2, "submission_pk": 3}),
        )
        .unwrap();
        assert_eq!(msg.image, None);
        let msg = SubmissionMessage::from_value(
            &json!({"challenge_pk": 1, "phase_pk": 2, "submission_pk": 3, "submitted_image_uri": null}),
        )
        .unwrap();
        assert_eq!(msg.image, None);
    }

    #[test]
    fn each_malformed_field_is_named() {
        let base = json!({"challenge_pk": 1, "phase_pk": 2, "submission_pk": 3});
        let with = |key: &str, v: Value| {
            let mut m = base.clone();
            m[key] = v;
            m
        };
        let without = |key: &str| {
            let mut m = base.clone();
            m.as_object_mut().unwrap().remove(key);
            m
        };
        assert_eq!(
            problem(without("phase_pk")),
            "submission message field `phase_pk` is missing"
        );
        assert!(problem(with("submission_pk", json!("12a"))).contains("`submission_pk`"));
        assert!(problem(with("submission_pk", json!(-4))).contains("positive integer"));
        assert!(problem(with("submission_pk", json!(4.5))).contains("positive integer"));
        assert!(problem(with("submission_pk", json!(0))).contains("between 1 and"));
        assert!(problem(with("challenge_pk", json!(true))).contains("a boolean"));
        assert!(problem(with("challenge_pk", json!(" 12"))).contains("`challenge_pk`"));
        assert!(problem(with("challenge_pk", json!("99999999999"))).contains("`challenge_pk`"));
        assert!(problem(with("submitted_image_uri", json!(5))).contains("must be a string"));
        assert!(problem(json!([1, 2])).contains("not a JSON object"));
        assert!(SubmissionMessage::parse("{not json").is_err());
    }

    #[test]
    fn the_pipes_batch_of_one_is_unwrapped_and_any_other_size_is_invalid_batch() {
        let one = serde_json::json!({"challenge_pk": 1, "phase_pk": 2, "submission_pk": 3});
        let batch = serde_json::json!([one.clone()]);
        assert_eq!(
            SubmissionMessage::from_pipe(&batch).unwrap(),
            SubmissionMessage::from_pipe(&one).unwrap()
        );
        for size in [0, 2] {
            let batch = serde_json::Value::Array(vec![one.clone(); size]);
            let err = SubmissionMessage::from_pipe(&batch).unwrap_err();
            assert_eq!(err.name(), "InvalidBatch");
            assert!(err.to_string().contains(&format!("holds {size} messages")));
        }
        let err = SubmissionMessage::from_pipe(&serde_json::json!([5])).unwrap_err();
        assert_eq!(err.name(), "InvalidMessage");
    }

    #[test]
    fn only_submitted_and_resuming_start_an_evaluation() {
        let starting: Vec<_> = (SubmissionStatus::ALL.iter().copied())
            .filter(|s| s.starts_evaluation())
            .collect();
        assert_eq!(
            starting,
            [SubmissionStatus::Submitted, SubmissionStatus::Resuming]
        );
        for &status in SubmissionStatus::ALL {
            assert_eq!(status.as_str().parse::<SubmissionStatus>(), Ok(status));
        }
        assert!("RUNNING".parse::<SubmissionStatus>().is_err());
    }
}
