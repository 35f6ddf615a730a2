//! `SubmissionSerializer(partial=True)` validation, as `update_submission_meta` runs it.

use axum::http::StatusCode;
use time::OffsetDateTime;

use std::collections::BTreeSet;

use crate::pyjson::{self, Constants, PyValue};
use crate::routes::body::Data;
use crate::routes::reply::{Reply, ViewResult};
use crate::state::Submission;
use crate::statuses::STATUSES;
use crate::timefmt;

const NOT_NULL: &str = "This field may not be null.";
const NOT_STRING: &str = "Not a valid string.";
const DATETIME_FORMAT: &str = "Datetime has wrong format. Use one of these formats instead: YYYY-MM-DDThh:mm[:ss[.uuuuuu]][+HH:MM|-HH:MM|Z].";

/// The ids the serializer's related fields may name (`PrimaryKeyRelatedField` querysets).
pub(crate) struct Related {
    pub teams: BTreeSet<u64>,
    pub users: BTreeSet<u64>,
    pub phases: BTreeSet<u64>,
}

enum Change {
    Status(String),
    Related(&'static str, u64),
    Time(&'static str, Option<OffsetDateTime>),
    Text(&'static str, String),
    Flag(&'static str, bool),
    Jobs(Option<Vec<String>>),
    Metadata(Option<PyValue>),
}

fn boolean(v: &PyValue) -> Result<bool, PyValue> {
    const TRUE: [&str; 13] = [
        "t", "T", "y", "Y", "yes", "YES", "true", "True", "TRUE", "on", "On", "ON", "1",
    ];
    const FALSE: [&str; 13] = [
        "f", "F", "n", "N", "no", "NO", "false", "False", "FALSE", "off", "Off", "OFF", "0",
    ];
    match v {
        PyValue::Bool(b) => Ok(*b),
        PyValue::Int(1) => Ok(true),
        PyValue::Int(0) => Ok(false),
        PyValue::Float(f) if *f == 1.0 => Ok(true),
        PyValue::Float(f) if *f == 0.0 => Ok(false),
        PyValue::Str(s) if TRUE.contains(&s.as_str()) => Ok(true),
        PyValue::Str(s) if FALSE.contains(&s.as_str()) => Ok(false),
        PyValue::None => Err(errors(NOT_NULL)),
        _ => Err(errors("Must be a valid boolean.")),
    }
}

fn errors(text: &str) -> PyValue {
    PyValue::List(vec![PyValue::str(text)])
}

fn char_field(v: &PyValue, max: Option<usize>) -> Result<String, PyValue> {
    let s = match v {
        PyValue::None => return Err(errors(NOT_NULL)),
        PyValue::Str(s) => s.trim().to_owned(),
        PyValue::Int(_) | PyValue::Float(_) => v.py_str(),
        _ => return Err(errors(NOT_STRING)),
    };
    if let Some(max) = max {
        if s.chars().count() > max {
            return Err(errors(&format!(
                "Ensure this field has no more than {max} characters."
            )));
        }
    }
    Ok(s)
}

/// `PrimaryKeyRelatedField.to_internal_value`: an id that names an existing object.
fn related(v: &PyValue, known: &BTreeSet<u64>) -> Result<u64, PyValue> {
    let id = match v {
        PyValue::None => return Err(errors(NOT_NULL)),
        PyValue::Int(i) => Some(*i),
        PyValue::Float(f) if f.is_finite() => Some(f.trunc() as i128),
        PyValue::Str(s) => s.trim().parse::<i128>().ok(),
        _ => None,
    };
    let Some(id) = id else {
        return Err(errors(&format!(
            "Incorrect type. Expected pk value, received {}.",
            v.type_name()
        )));
    };
    u64::try_from(id)
        .ok()
        .filter(|id| known.contains(id))
        .ok_or_else(|| {
            errors(&format!(
                "Invalid pk \"{}\" - object does not exist.",
                v.py_str()
            ))
        })
}

fn datetime(v: &PyValue) -> Result<Option<OffsetDateTime>, PyValue> {
    match v {
        PyValue::None => Ok(None),
        PyValue::Str(s) => timefmt::parse(s.trim())
            .map(Some)
            .ok_or_else(|| errors(DATETIME_FORMAT)),
        _ => Err(errors(DATETIME_FORMAT)),
    }
}

fn job_names(v: &PyValue) -> Result<Option<Vec<String>>, PyValue> {
    let items = match v {
        PyValue::None => return Ok(None),
        PyValue::List(items) => items,
        other => {
            return Err(errors(&format!(
                "Expected a list of items but got type \"{}\".",
                other.type_name()
            )))
        }
    };
    let mut out = Vec::new();
    let mut child_errors = Vec::new();
    for (i, item) in items.iter().enumerate() {
        match char_field(item, None) {
            Ok(s) => out.push(s),
            Err(e) => child_errors.push((i.to_string(), e)),
        }
    }
    if child_errors.is_empty() {
        Ok(Some(out))
    } else {
        Err(PyValue::Dict(child_errors))
    }
}

/// `JSONField`: a JSON body's value as it is; a form's text parsed as JSON, as DRF does for
/// form input.
fn metadata(v: &PyValue, form: bool) -> Result<Change, PyValue> {
    let value = match v {
        PyValue::Str(text) if form => pyjson::loads(text, Constants::Allow)
            .map_err(|_| errors("Value must be valid JSON."))?,
        other => other.clone(),
    };
    Ok(Change::Metadata(
        (!matches!(value, PyValue::None)).then_some(value),
    ))
}

/// Validates `request.data` as a partial serializer update; applies it when valid,
/// else answers 400 with DRF's `{field: [messages]}`.
pub(crate) fn apply(sub: &mut Submission, data: &Data, known: &Related) -> ViewResult<()> {
    if !matches!(data.value, PyValue::Dict(_)) {
        return Err(not_a_dictionary(&data.value));
    }
    let mut changes = Vec::new();
    let mut errs: Vec<(String, PyValue)> = Vec::new();
    let mut check = |field: &'static str, result: Result<Change, PyValue>| match result {
        Ok(c) => changes.push(c),
        Err(e) => errs.push((field.to_owned(), e)),
    };
    for (field, ids) in [
        ("participant_team", &known.teams),
        ("challenge_phase", &known.phases),
        ("created_by", &known.users),
    ] {
        if let Some(v) = data.value.get(field) {
            check(field, related(v, ids).map(|id| Change::Related(field, id)));
        }
    }
    if let Some(v) = data.value.get("status") {
        check("status", status(v));
    }
    for field in [
        "started_at",
        "completed_at",
        "rerun_resumed_at",
        "when_made_public",
    ] {
        if let Some(v) = data.value.get(field) {
            check(field, datetime(v).map(|t| Change::Time(field, t)));
        }
    }
    for (field, max) in [
        ("method_name", Some(1000)),
        ("method_description", None),
        ("project_url", Some(1000)),
        ("publication_url", Some(1000)),
    ] {
        if let Some(v) = data.value.get(field) {
            check(field, char_field(v, max).map(|s| Change::Text(field, s)));
        }
    }
    for field in [
        "is_public",
        "is_flagged",
        "ignore_submission",
        "is_baseline",
        "is_verified_by_host",
    ] {
        if let Some(v) = data.value.get(field) {
            check(field, boolean(v).map(|b| Change::Flag(field, b)));
        }
    }
    if let Some(v) = data.value.get("job_name") {
        // Form bodies give every value of a repeated key to a list field.
        let r = match data.getlist("job_name") {
            Some(list) => Ok(Change::Jobs(Some(list))),
            None => job_names(v).map(Change::Jobs),
        };
        check("job_name", r);
    }
    if let Some(v) = data.value.get("submission_metadata") {
        check(
            "submission_metadata",
            metadata(v, data.getlist("submission_metadata").is_some()),
        );
    }
    if !errs.is_empty() {
        return Err(Reply::json(StatusCode::BAD_REQUEST, PyValue::Dict(errs)));
    }
    for change in changes {
        change.make(sub);
    }
    Ok(())
}

/// The `status` field: one of EvalAI's choices, not null.
fn status(v: &PyValue) -> Result<Change, PyValue> {
    let key = v.py_str();
    match v {
        PyValue::None => Err(errors(NOT_NULL)),
        _ if STATUSES.contains(&key.as_str()) => Ok(Change::Status(key)),
        _ => Err(errors(&format!("\"{key}\" is not a valid choice."))),
    }
}

/// DRF's answer to a body that is not a JSON object.
fn not_a_dictionary(value: &PyValue) -> Reply {
    Reply::json(
        StatusCode::BAD_REQUEST,
        PyValue::dict(vec![(
            "non_field_errors",
            errors(&format!(
                "Invalid data. Expected a dictionary, but got {}.",
                value.type_name()
            )),
        )]),
    )
}

impl Change {
    /// Makes this validated change to `sub`.
    fn make(self, sub: &mut Submission) {
        match self {
            Change::Related(field, id) => match field {
                "participant_team" => sub.team = id,
                "challenge_phase" => sub.phase = id,
                _ => sub.created_by = id,
            },
            Change::Status(s) => sub.status = s,
            Change::Time(field, t) => match field {
                "started_at" => sub.started_at = t,
                "completed_at" => sub.completed_at = t,
                "rerun_resumed_at" => sub.rerun_resumed_at = t,
                _ => sub.when_made_public = t,
            },
            Change::Text(field, s) => match field {
                "method_name" => sub.method_name = s,
                "method_description" => sub.method_description = s,
                "project_url" => sub.project_url = s,
                _ => sub.publication_url = s,
            },
            Change::Flag(field, b) => match field {
                "is_public" => sub.is_public = b,
                "is_flagged" => sub.is_flagged = b,
                "ignore_submission" => sub.ignore_submission = b,
                "is_baseline" => sub.is_baseline = b,
                _ => sub.is_verified_by_host = b,
            },
            Change::Jobs(j) => sub.job_name = j,
            Change::Metadata(m) => sub.submission_metadata = m,
        }
    }
}
