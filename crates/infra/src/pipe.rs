//! The EventBridge Pipe's input transformation, as AWS documents it: what the Pipe between
//! EvalAI's SQS queue and the state machine hands each execution.
//!
//! What the real Pipe does, and so what this does (AWS EventBridge user guide):
//! - "Amazon SQS as a source": the Pipe sees each message as a record whose `body` is the
//!   message text.
//! - "Input transformation", implicit body data parsing: an SQS `body` holding valid JSON can
//!   be addressed field by field (`$.body.submission_pk`). The `InputTemplate` is applied to
//!   each record; a `<$.path>` placeholder becomes the value at that path, as JSON ("EventBridge
//!   replaces input transformers at runtime to ensure a valid JSON output"); inside a quoted
//!   string it becomes the value's text.
//! - "Batching and concurrency": "Even if the batch size is 1, the request is sent as a JSON
//!   array", so a Step Functions target receives `[<transformed record>, ...]`.
//!
//! Not documented, so chosen here and said: a path absent from the record becomes `null`
//! (Intake then names the missing field), and a template whose output is not JSON is an error
//! (the real Pipe would fail the delivery).
//!
//! The template itself is the Pipe's `InputTemplate` in `infra/app.yaml`: the one source that
//! the deployment, local mode and `lbctl submit` use.

use serde_json::Value;

/// The Pipe's `InputTemplate`, exactly as deployed (read from `infra/app.yaml`).
pub static INPUT_TEMPLATE: std::sync::LazyLock<String> = std::sync::LazyLock::new(|| {
    crate::template::pipe_input_template().expect("infra/app.yaml declares the Pipe's template")
});

/// Why a record could not be transformed.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum TransformError {
    /// A placeholder is not `<$.path>` with a path Pipes supports.
    #[error("input template placeholder `<{0}>` is not a path this emulation supports")]
    Placeholder(String),
    /// A `<` is never closed.
    #[error("input template has an unclosed `<` at byte {0}")]
    Unclosed(usize),
    /// The transformed text is not JSON.
    #[error("the input template produced invalid JSON ({error}): {text}")]
    NotJson {
        /// serde_json's message.
        error: String,
        /// The text produced.
        text: String,
    },
}

/// A record built from a message body alone, for callers that start executions as the Pipe
/// would without a queue (`lbctl submit`).
pub fn record_of_body(body: &str) -> Value {
    let mut record = aws_lambda_events::event::sqs::SqsMessage::default();
    record.message_id = Some(String::new());
    record.body = Some(body.to_owned());
    record.event_source = Some("aws:sqs".to_owned());
    serde_json::to_value(record).expect("an SqsMessage of strings and string maps serializes")
}

/// What the Pipe hands the state machine for a batch of records: the template applied to
/// each, as a JSON array.
pub fn batch(template: &str, records: &[Value]) -> Result<Value, TransformError> {
    records
        .iter()
        .map(|r| transform(template, r))
        .collect::<Result<Vec<_>, _>>()
        .map(Value::Array)
}

/// The template applied to one record.
pub fn transform(template: &str, record: &Value) -> Result<Value, TransformError> {
    let record = with_parsed_body(record);
    let mut out = String::with_capacity(template.len() + 64);
    let mut in_string = false;
    let mut escaped = false;
    let mut rest = template.char_indices().peekable();
    while let Some((at, c)) = rest.next() {
        if in_string && escaped {
            escaped = false;
            out.push(c);
            continue;
        }
        match c {
            '\\' if in_string => {
                escaped = true;
                out.push(c);
            }
            '"' => {
                in_string = !in_string;
                out.push(c);
            }
            '<' => {
                let end = template[at..]
                    .find('>')
                    .ok_or(TransformError::Unclosed(at))?
                    + at;
                let placeholder = &template[at + 1..end];
                let value = resolve(&record, placeholder)?;
                if in_string {
                    match value {
                        Value::String(s) => {
                            let quoted = Value::String(s).to_string();
                            out.push_str(&quoted[1..quoted.len() - 1]);
                        }
                        other => out.push_str(&other.to_string()),
                    }
                } else {
                    out.push_str(&value.to_string());
                }
                while rest.peek().is_some_and(|(i, _)| *i <= end) {
                    rest.next();
                }
            }
            _ => out.push(c),
        }
    }
    serde_json::from_str(&out).map_err(|e| TransformError::NotJson {
        error: e.to_string(),
        text: out,
    })
}

/// The record with `body` parsed when it holds JSON (implicit body data parsing).
fn with_parsed_body(record: &Value) -> Value {
    let mut record = record.clone();
    if let Some(parsed) = record
        .get("body")
        .and_then(Value::as_str)
        .and_then(|b| serde_json::from_str::<Value>(b).ok())
    {
        record["body"] = parsed;
    }
    record
}

/// `$.a.b[2]`: dot notation and array indices. A path that is absent is `null`.
fn resolve(record: &Value, placeholder: &str) -> Result<Value, TransformError> {
    let bad = || TransformError::Placeholder(placeholder.to_owned());
    let path = placeholder.strip_prefix('$').ok_or_else(bad)?;
    let mut here = Some(record);
    for segment in path.split('.').skip(1) {
        let (name, indices) = match segment.find('[') {
            Some(i) => (&segment[..i], &segment[i..]),
            None => (segment, ""),
        };
        if name.is_empty()
            || !name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-' || c == '/')
        {
            return Err(bad());
        }
        here = here.and_then(|v| v.get(name));
        for index in indices.split_terminator(']') {
            let n: usize = index
                .strip_prefix('[')
                .and_then(|n| n.parse().ok())
                .ok_or_else(bad)?;
            here = here.and_then(|v| v.get(n));
        }
    }
    Ok(here.cloned().unwrap_or(Value::Null))
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    /// EvalAI's message for a new submission: string challenge and phase ids, an int
    /// submission id, an extra key the template drops.
    fn evalai_body() -> String {
        json!({
            "challenge_pk": "12",
            "phase_pk": "1234",
            "submission_pk": 77,
            "is_static_dataset_code_upload_submission": false,
            "submitted_image_uri": "123.dkr.ecr.us-west-2.amazonaws.com/team:v1",
        })
        .to_string()
    }

    #[test]
    fn the_deployed_template_gives_the_four_fields_with_their_json_types_kept() {
        let out = transform(&INPUT_TEMPLATE, &record_of_body(&evalai_body())).unwrap();
        assert_eq!(
            out,
            json!({"challenge_pk": "12", "phase_pk": "1234", "submission_pk": 77,
                   "submitted_image_uri": "123.dkr.ecr.us-west-2.amazonaws.com/team:v1"})
        );
    }

    #[test]
    fn a_batch_of_one_is_a_one_element_array() {
        let out = batch(&INPUT_TEMPLATE, &[record_of_body(&evalai_body())]).unwrap();
        assert!(out.is_array());
        assert_eq!(out.as_array().unwrap().len(), 1);
        assert_eq!(out[0]["submission_pk"], 77);
    }

    #[test]
    fn the_template_is_applied_to_each_record_of_a_batch() {
        let records: Vec<Value> = (1..=3)
            .map(|i| record_of_body(&json!({"submission_pk": i}).to_string()))
            .collect();
        let out = batch(&INPUT_TEMPLATE, &records).unwrap();
        let ids: Vec<&Value> = out
            .as_array()
            .unwrap()
            .iter()
            .map(|r| &r["submission_pk"])
            .collect();
        assert_eq!(ids, [&json!(1), &json!(2), &json!(3)]);
    }

    #[test]
    fn a_field_missing_from_the_body_becomes_null() {
        let body = json!({"challenge_pk": 1, "phase_pk": 2, "submission_pk": 3}).to_string();
        let out = transform(&INPUT_TEMPLATE, &record_of_body(&body)).unwrap();
        assert_eq!(out["submitted_image_uri"], Value::Null);
    }

    #[test]
    fn a_body_that_is_not_json_cannot_be_addressed_and_every_field_is_null() {
        let out = transform(&INPUT_TEMPLATE, &record_of_body("not json")).unwrap();
        assert_eq!(out["submission_pk"], Value::Null);
    }

    #[test]
    fn inside_quotes_a_placeholder_gives_the_text_escaped() {
        let body = json!({"name": "a \"quoted\" team", "n": 5}).to_string();
        let out = transform(
            r#"{"who": "team <$.body.name> #<$.body.n>", "raw": <$.body.name>}"#,
            &record_of_body(&body),
        )
        .unwrap();
        assert_eq!(out["who"], "team a \"quoted\" team #5");
        assert_eq!(out["raw"], "a \"quoted\" team");
    }

    #[test]
    fn array_indices_and_record_fields_resolve() {
        let body = json!({"list": [10, 20]}).to_string();
        let record = record_of_body(&body);
        let out = transform(
            r#"{"x": <$.body.list[1]>, "src": <$.eventSource>}"#,
            &record,
        )
        .unwrap();
        assert_eq!(out, json!({"x": 20, "src": "aws:sqs"}));
    }

    #[test]
    fn unsupported_placeholders_and_broken_templates_are_named() {
        let record = record_of_body("{}");
        assert_eq!(
            transform(r#"{"x": <$..deep>}"#, &record).unwrap_err(),
            TransformError::Placeholder("$..deep".into())
        );
        assert_eq!(
            transform(r#"{"x": <$.body"#, &record).unwrap_err(),
            TransformError::Unclosed(6)
        );
        assert!(matches!(
            transform(r#"{"x": <$.body.a> <$.body.b>}"#, &record),
            Err(TransformError::NotJson { .. })
        ));
    }
}
