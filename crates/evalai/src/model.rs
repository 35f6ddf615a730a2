//! EvalAI's answers, read as untrusted input, and the checks on what we send.

use lb_domain::submission::SubmissionStatus;
use serde_json::Value;

use crate::EvalAiError;

/// The fields of EvalAI's serialized submission we use (reference §3).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Submission {
    /// Submission id.
    pub id: u64,
    /// Participant team id.
    pub team_id: u64,
    /// Participant team name: free text chosen by the participant.
    pub team_name: String,
    /// The phase the submission belongs to.
    pub phase_id: u64,
    /// Current status.
    pub status: SubmissionStatus,
    /// The docker challenge's input file URL (holds `submitted_image_uri`).
    pub input_file: Option<String>,
    /// Job names EvalAI recorded (may hold duplicates and a previous run's names).
    pub job_names: Vec<String>,
    /// When EvalAI received it (`submitted_at`), epoch milliseconds: its place in the queue.
    /// `None` when absent or not an ISO-8601 time.
    pub submitted_ms: Option<u64>,
    /// `submission_metadata`: the participant's answers to the phase's metadata fields, and
    /// the queue note we add (`EvalAiClient::show_queue`). Any JSON; `Null` when unset.
    pub metadata: Value,
}

/// Longest team name we carry around; EvalAI allows long names, Kubernetes labels do not.
pub const MAX_TEAM_NAME: usize = 1000;

impl Submission {
    /// Reads GET `/api/jobs/submission/<id>`'s body.
    pub fn from_json(value: &Value) -> Result<Self, EvalAiError> {
        let bad = |field: &str, problem: &str| {
            EvalAiError::InvalidResponse(format!("submission field `{field}` {problem}"))
        };
        let uint = |field: &str| {
            value
                .get(field)
                .and_then(Value::as_u64)
                .ok_or_else(|| bad(field, "is not a positive integer"))
        };
        let status = value
            .get("status")
            .and_then(Value::as_str)
            .ok_or_else(|| bad("status", "is not a string"))?
            .parse::<SubmissionStatus>()
            .map_err(|e| bad("status", &e.to_string()))?;
        let team_name = value
            .get("participant_team_name")
            .and_then(Value::as_str)
            .ok_or_else(|| bad("participant_team_name", "is not a string"))?;
        if team_name.chars().count() > MAX_TEAM_NAME {
            return Err(bad("participant_team_name", "is too long"));
        }
        let input_file = match value.get("input_file") {
            None | Some(Value::Null) => None,
            Some(Value::String(s)) => Some(s.clone()),
            Some(_) => return Err(bad("input_file", "is not a string")),
        };
        let job_names = match value.get("job_name") {
            None | Some(Value::Null) => Vec::new(),
            Some(Value::Array(items)) => items
                .iter()
                .map(|v| v.as_str().map(str::to_owned))
                .collect::<Option<Vec<_>>>()
                .ok_or_else(|| bad("job_name", "is not a list of strings"))?,
            Some(_) => return Err(bad("job_name", "is not a list")),
        };
        let metadata = value
            .get("submission_metadata")
            .cloned()
            .unwrap_or(Value::Null);
        let submitted_ms = value
            .get("submitted_at")
            .and_then(Value::as_str)
            .and_then(|t| {
                time::OffsetDateTime::parse(t, &time::format_description::well_known::Rfc3339).ok()
            })
            .and_then(|t| u64::try_from(t.unix_timestamp_nanos() / 1_000_000).ok());
        Ok(Submission {
            submitted_ms,
            metadata,
            id: uint("id")?,
            team_id: uint("participant_team")?,
            team_name: team_name.to_owned(),
            phase_id: uint("challenge_phase")?,
            status,
            input_file,
            job_names,
        })
    }
}

/// The image URI out of a docker challenge's `input_file` JSON.
pub(crate) fn image_from_input_file(bytes: &[u8]) -> Result<String, EvalAiError> {
    let value: Value = serde_json::from_slice(bytes)
        .map_err(|e| EvalAiError::InvalidResponse(format!("input_file is not JSON: {e}")))?;
    match value.get("submitted_image_uri") {
        Some(Value::String(uri)) if !uri.trim().is_empty() => Ok(uri.clone()),
        _ => Err(EvalAiError::InvalidResponse(
            "input_file has no `submitted_image_uri` string".into(),
        )),
    }
}

/// The text of an EvalAI error body: `error`, `detail`, field errors, or the raw start of
/// an HTML page.
pub(crate) fn error_message(body: &str) -> String {
    match serde_json::from_str::<Value>(body) {
        Ok(Value::Object(map)) => {
            for key in ["error", "detail"] {
                if let Some(Value::String(s)) = map.get(key) {
                    return s.clone();
                }
            }
            Value::Object(map).to_string()
        }
        Ok(other) => other.to_string(),
        Err(_) => {
            let text: String = body.chars().filter(|c| !c.is_control()).take(200).collect();
            if text.is_empty() {
                "(empty body)".into()
            } else {
                text
            }
        }
    }
}

/// Checks a `result` text as EvalAI will (reference §4 and §9): a JSON list of
/// `{split, show_to_participant, accuracies}` with every accuracy a finite number, no split
/// twice. What EvalAI would answer with a 500 or store as garbage is refused here.
pub fn validate_result(result: &str) -> Result<(), String> {
    let value: Value =
        serde_json::from_str(result).map_err(|e| format!("`result` is not JSON: {e}"))?;
    let Value::Array(splits) = value else {
        return Err("`result` must be a JSON list of splits".into());
    };
    let mut seen = Vec::new();
    for (i, split) in splits.iter().enumerate() {
        let name = split
            .get("split")
            .and_then(Value::as_str)
            .ok_or_else(|| format!("`result[{i}].split` must be a string"))?;
        if seen.contains(&name) {
            return Err(format!("split `{name}` is listed twice"));
        }
        seen.push(name);
        let Some(Value::Object(accuracies)) = split.get("accuracies") else {
            return Err(format!("`result[{i}].accuracies` must be an object"));
        };
        for (label, v) in accuracies {
            match v {
                Value::Number(n) if n.as_f64().is_some_and(f64::is_finite) => {}
                other => {
                    return Err(format!(
                        "`result[{i}].accuracies[{label:?}]` must be a finite number, got `{other}`"
                    ))
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn a_submission_with_none_execution_time_and_null_job_names_is_read() {
        let s = Submission::from_json(&json!({
            "id": 7, "participant_team": 3, "participant_team_name": "Team 🚗 One",
            "execution_time": "None", "challenge_phase": 1234, "created_by": 2,
            "status": "submitted", "input_file": "https://x/input.json", "job_name": null
        }))
        .unwrap();
        assert_eq!(s.team_name, "Team 🚗 One");
        assert_eq!(s.status, SubmissionStatus::Submitted);
        assert!(s.job_names.is_empty());
    }

    #[test]
    fn an_unknown_status_or_a_string_id_is_an_invalid_response() {
        let base = json!({"id": 7, "participant_team": 3, "participant_team_name": "t",
                          "challenge_phase": 1, "status": "running"});
        let mut wrong_status = base.clone();
        wrong_status["status"] = json!("RUNNING");
        let err = Submission::from_json(&wrong_status).unwrap_err();
        assert_eq!(err.name(), "EvalAiInvalidResponse");
        let mut string_id = base.clone();
        string_id["id"] = json!("7");
        assert!(Submission::from_json(&string_id)
            .unwrap_err()
            .to_string()
            .contains("`id`"));
    }

    #[test]
    fn results_evalai_would_choke_on_are_refused() {
        let ok = r#"[{"split": "leaderboard", "show_to_participant": true, "accuracies": {"Driving score": 1.5}}]"#;
        assert_eq!(validate_result(ok), Ok(()));
        assert!(validate_result("[]").is_ok());
        for bad in [
            r#"{"split": "x"}"#,
            r#"[{"split": "l", "accuracies": {"Driving score": "85.2"}}]"#,
            r#"[{"split": "l", "accuracies": {"Driving score": null}}]"#,
            r#"[{"split": "l", "accuracies": []}]"#,
            r#"[{"split": "l", "accuracies": {}}, {"split": "l", "accuracies": {}}]"#,
            r#"[{"split": "l", "accuracies": {"Driving score": NaN}}]"#,
        ] {
            assert!(validate_result(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn error_bodies_are_read_from_either_key_or_html() {
        assert_eq!(error_message(r#"{"error": "Sorry"}"#), "Sorry");
        assert_eq!(
            error_message(r#"{"detail": "Invalid token"}"#),
            "Invalid token"
        );
        assert_eq!(
            error_message("<html>\n<h1>Server Error (500)</h1>"),
            "<html><h1>Server Error (500)</h1>"
        );
    }
}
