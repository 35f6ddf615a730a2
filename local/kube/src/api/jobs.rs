//! `batch/v1` Job handlers: create (validation, strict field checks, dry run), list, get,
//! merge patch, delete.

use std::time::Duration;

use axum::body::Bytes;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode};
use axum::response::Response;
use k8s_openapi::api::batch::v1::Job;
use serde_json::Value;

use super::objects::{into_response, to_json};
use super::{decode_body, int_param, json, truthy, valid_namespace, AppState, Params};
use crate::objects::job::prepare_create;
use crate::objects::validation::validate_job;
use crate::runtime::{Deleted, Propagation};
use crate::status::{go_quote, ApiError, FieldError, JOBS};
use crate::store::ObjKey;

/// Paths of fields the typed object dropped: unknown to the schema.
pub fn unknown_fields(input: &Value, typed: &Value, path: &str, out: &mut Vec<String>) {
    match (input, typed) {
        (Value::Object(a), Value::Object(b)) => {
            for (k, v) in a {
                if v.is_null() {
                    continue;
                }
                let p = if path.is_empty() {
                    k.clone()
                } else {
                    format!("{path}.{k}")
                };
                match b.get(k) {
                    None => out.push(p),
                    Some(tv) => unknown_fields(v, tv, &p, out),
                }
            }
        }
        (Value::Array(a), Value::Array(b)) => {
            for (i, (v, tv)) in a.iter().zip(b).enumerate() {
                unknown_fields(v, tv, &format!("{path}[{i}]"), out);
            }
        }
        _ => {}
    }
}

fn decode_job(v: Value, strict: bool) -> Result<(Job, Vec<String>), ApiError> {
    if let Some(av) = v.get("apiVersion").and_then(Value::as_str) {
        if av != "batch/v1" {
            return Err(ApiError::bad_request(format!(
                "the API version in the data ({av}) does not match the expected API version (batch/v1)"
            )));
        }
    }
    if let Some(kind) = v.get("kind").and_then(Value::as_str) {
        if kind != "Job" {
            return Err(ApiError::bad_request(format!(
                "the kind in the data ({kind}) does not match the expected kind (Job)"
            )));
        }
    }
    let job: Job = serde_json::from_value(v.clone()).map_err(|e| {
        ApiError::bad_request(format!(
            "Job in version \"v1\" cannot be handled as a Job: {e}"
        ))
    })?;
    let mut unknown = Vec::new();
    unknown_fields(&v, &to_json(&job), "", &mut unknown);
    let warnings: Vec<String> = unknown
        .iter()
        .map(|f| format!("unknown field {}", go_quote(f)))
        .collect();
    if strict && !warnings.is_empty() {
        return Err(ApiError::bad_request(format!(
            "strict decoding error: {}",
            warnings.join(", ")
        )));
    }
    Ok((job, warnings))
}

/// POST /apis/batch/v1/namespaces/{ns}/jobs
pub async fn create(
    State(state): State<AppState>,
    Path(ns): Path<String>,
    Query(p): Query<Params>,
    headers: HeaderMap,
    body: Bytes,
) -> Response {
    into_response(create_inner(&state, &ns, &p, &headers, &body))
}

fn create_inner(
    state: &AppState,
    ns: &str,
    p: &Params,
    headers: &HeaderMap,
    body: &Bytes,
) -> Result<Response, ApiError> {
    state.check("create", &JOBS, ns, None)?;
    valid_namespace(ns)?;
    if state.rt.is_shutting_down() {
        return Err(ApiError::unavailable("local-kube is shutting down"));
    }
    let value = decode_body(headers, body)?;
    let strict = p.field_validation.as_deref() == Some("Strict");
    let ignore = p.field_validation.as_deref() == Some("Ignore");
    let (job, warnings) = decode_job(value, strict)?;
    let job = prepare_create(job, ns, None)?;
    let dry_run = p.dry_run.as_deref() == Some("All");
    let job = if dry_run {
        job
    } else {
        let stored = state.rt.store.create(job)?;
        state.rt.start_job(&stored);
        stored
    };
    let mut resp = json(StatusCode::CREATED, &to_json(&job));
    if !ignore {
        for w in warnings {
            let header = format!("299 - {}", go_quote(&w));
            if let Ok(v) = HeaderValue::from_str(&header) {
                resp.headers_mut().append("warning", v);
            }
        }
    }
    Ok(resp)
}

/// PATCH /apis/batch/v1/namespaces/{ns}/jobs/{name}: a JSON merge patch (RFC 7386), as
/// `kubectl patch --type merge` and kube's `Patch::Merge` send it. Of a Job's spec, only
/// `activeDeadlineSeconds` may change here (the real server also lets `parallelism`,
/// `suspend` and a few others change, which this server does not model); the Job controller
/// re-arms its deadline, as the real one does when the field changes ("Job termination and
/// cleanup" in the Kubernetes docs). Labels and annotations may change too; the status is not
/// the main resource's to change.
pub async fn patch(
    State(state): State<AppState>,
    Path((ns, name)): Path<(String, String)>,
    Query(p): Query<Params>,
    headers: HeaderMap,
    body: Bytes,
) -> Response {
    into_response(patch_inner(&state, &ns, &name, &p, &headers, &body))
}

fn patch_inner(
    state: &AppState,
    ns: &str,
    name: &str,
    p: &Params,
    headers: &HeaderMap,
    body: &Bytes,
) -> Result<Response, ApiError> {
    state.check("patch", &JOBS, ns, Some(name))?;
    let content_type = headers
        .get(axum::http::header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or_default();
    let media_type = content_type.split(';').next().unwrap_or_default().trim();
    if media_type != "application/merge-patch+json" {
        return Err(ApiError::unsupported_media_type(content_type));
    }
    let patch: Value = serde_json::from_slice(body)
        .map_err(|e| ApiError::bad_request(format!("error decoding patch: {e}")))?;
    let key = ObjKey::new(ns, name);
    let current = state
        .rt
        .store
        .get::<Job>(&key)
        .ok_or_else(|| ApiError::not_found(&JOBS, name))?;
    let mut merged = to_json(&current);
    merge_patch(&mut merged, &patch);
    let strict = p.field_validation.as_deref() == Some("Strict");
    let (patched, _) = decode_job(merged, strict)?;
    let uid = current.metadata.uid.clone().unwrap_or_default();
    let mut errors = validate_job(&patched, &uid);
    let (mut was, mut now) = (current.spec.clone(), patched.spec.clone());
    for spec in [&mut was, &mut now].into_iter().flatten() {
        spec.active_deadline_seconds = None;
    }
    if was != now {
        errors.push(FieldError::forbidden(
            "spec",
            "only spec.activeDeadlineSeconds may change on this server",
        ));
    }
    if !errors.is_empty() {
        return Err(ApiError::invalid(&JOBS, name, &errors));
    }
    let apply = |job: &mut Job| {
        if job.spec != patched.spec {
            job.metadata.generation = Some(job.metadata.generation.unwrap_or(1) + 1);
            job.spec = patched.spec.clone();
        }
        job.metadata.labels = patched.metadata.labels.clone();
        job.metadata.annotations = patched.metadata.annotations.clone();
    };
    if p.dry_run.as_deref() == Some("All") {
        let mut job = current;
        apply(&mut job);
        return Ok(json(StatusCode::OK, &to_json(&job)));
    }
    let job = state
        .rt
        .store
        .update::<Job>(&key, apply)
        .ok_or_else(|| ApiError::not_found(&JOBS, name))?;
    state.rt.notify_job(&uid);
    Ok(json(StatusCode::OK, &to_json(&job)))
}

/// RFC 7386: objects merge key by key, `null` removes a key, anything else replaces.
fn merge_patch(target: &mut Value, patch: &Value) {
    let Value::Object(fields) = patch else {
        *target = patch.clone();
        return;
    };
    if !target.is_object() {
        *target = Value::Object(Default::default());
    }
    if let Value::Object(target) = target {
        for (key, value) in fields {
            if value.is_null() {
                target.remove(key);
            } else {
                merge_patch(target.entry(key.clone()).or_insert(Value::Null), value);
            }
        }
    }
}

/// `propagationPolicy`, `gracePeriodSeconds`, uid precondition and dry run of a delete, from
/// the query and the DeleteOptions body.
pub struct DeleteOptions {
    /// Propagation (`None`: the resource's default).
    pub propagation: Option<Propagation>,
    /// Grace period override.
    pub grace: Option<Duration>,
    /// `preconditions.uid`.
    pub uid: Option<String>,
    /// `dryRun=All`.
    pub dry_run: bool,
}

fn propagation(s: &str) -> Result<Propagation, ApiError> {
    match s {
        "Foreground" => Ok(Propagation::Foreground),
        "Background" => Ok(Propagation::Background),
        "Orphan" => Ok(Propagation::Orphan),
        other => Err(ApiError::bad_request(format!(
            "propagationPolicy: Unsupported value: {}: supported values: \"Foreground\", \"Background\", \"Orphan\"",
            go_quote(other)
        ))),
    }
}

/// Parses delete options (400 for a malformed body or value).
pub fn delete_options(
    p: &Params,
    headers: &HeaderMap,
    body: &Bytes,
) -> Result<DeleteOptions, ApiError> {
    let mut out = DeleteOptions {
        propagation: None,
        grace: int_param("gracePeriodSeconds", &p.grace_period_seconds)?
            .map(|s| Duration::from_secs(s as u64)),
        uid: None,
        dry_run: p.dry_run.as_deref() == Some("All"),
    };
    if let Some(pp) = p.propagation_policy.as_deref().filter(|s| !s.is_empty()) {
        out.propagation = Some(propagation(pp)?);
    } else if let Some(o) = p.orphan_dependents.as_deref() {
        out.propagation = Some(if truthy(&Some(o.to_owned())) {
            Propagation::Orphan
        } else {
            Propagation::Background
        });
    }
    let trimmed = body.iter().all(u8::is_ascii_whitespace);
    if !trimmed {
        let v = decode_body(headers, body)?;
        if let Some(pp) = v.get("propagationPolicy").and_then(Value::as_str) {
            out.propagation = Some(propagation(pp)?);
        } else if let Some(o) = v.get("orphanDependents").and_then(Value::as_bool) {
            out.propagation = Some(if o {
                Propagation::Orphan
            } else {
                Propagation::Background
            });
        }
        if let Some(g) = v.get("gracePeriodSeconds").and_then(Value::as_i64) {
            out.grace = Some(Duration::from_secs(g.max(0) as u64));
        }
        if let Some(uid) = v.pointer("/preconditions/uid").and_then(Value::as_str) {
            out.uid = Some(uid.to_owned());
        }
        if v.get("dryRun")
            .and_then(Value::as_array)
            .is_some_and(|a| a.iter().any(|x| x == "All"))
        {
            out.dry_run = true;
        }
    }
    Ok(out)
}

/// DELETE /apis/batch/v1/namespaces/{ns}/jobs/{name}
pub async fn delete(
    State(state): State<AppState>,
    Path((ns, name)): Path<(String, String)>,
    Query(p): Query<Params>,
    headers: HeaderMap,
    body: Bytes,
) -> Response {
    let result = async {
        state.check("delete", &JOBS, &ns, Some(&name))?;
        let opts = delete_options(&p, &headers, &body)?;
        let key = ObjKey::new(&ns, &name);
        if opts.dry_run {
            let job = state
                .rt
                .store
                .get::<Job>(&key)
                .ok_or_else(|| ApiError::not_found(&JOBS, &name))?;
            return Ok(json(StatusCode::OK, &to_json(&job)));
        }
        // NB: batch/v1 Jobs orphan their pods by default, as on a real cluster (kubectl
        // always asks for Background).
        let policy = opts.propagation.unwrap_or(Propagation::Orphan);
        match state
            .rt
            .delete_job(&key, policy, opts.grace, opts.uid.as_deref())
            .await?
        {
            Deleted::Pending(job) => Ok(json(StatusCode::OK, &to_json(job.as_ref()))),
            Deleted::Gone(status) => Ok(json(StatusCode::OK, &status)),
        }
    }
    .await;
    into_response(result)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_merge_patch_merges_objects_removes_nulls_and_replaces_the_rest() {
        let mut job = serde_json::json!({
            "metadata": {"labels": {"a": "1", "b": "2"}},
            "spec": {"activeDeadlineSeconds": 60, "parallelism": 1}
        });
        let patch = serde_json::json!({
            "metadata": {"labels": {"b": null, "c": "3"}},
            "spec": {"activeDeadlineSeconds": 120}
        });
        merge_patch(&mut job, &patch);
        assert_eq!(
            job,
            serde_json::json!({
                "metadata": {"labels": {"a": "1", "c": "3"}},
                "spec": {"activeDeadlineSeconds": 120, "parallelism": 1}
            })
        );
    }

    #[test]
    fn unknown_fields_are_found_with_their_paths() {
        let input: Value = serde_json::from_str(
            r#"{"apiVersion":"batch/v1","kind":"Job","metadata":{"name":"x","creationTimestamp":null},
                "spec":{"bogus":1,"template":{"spec":{"restartPolicy":"Never","containers":[{"name":"c","image":"i","imagee":"j"}]}}}}"#,
        )
        .unwrap();
        let (_, warnings) = decode_job(input.clone(), false).unwrap();
        assert_eq!(
            warnings,
            vec![
                "unknown field \"spec.bogus\"".to_owned(),
                "unknown field \"spec.template.spec.containers[0].imagee\"".to_owned()
            ]
        );
        let err = decode_job(input, true).unwrap_err();
        assert_eq!(err.code, 400);
        assert!(err
            .message
            .starts_with("strict decoding error: unknown field \"spec.bogus\""));
    }

    #[test]
    fn wrong_types_and_kinds_are_bad_requests() {
        let e =
            decode_job(serde_json::json!({"spec": {"backoffLimit": "six"}}), false).unwrap_err();
        assert!(
            e.message
                .starts_with("Job in version \"v1\" cannot be handled as a Job:"),
            "{}",
            e.message
        );
        let e = decode_job(
            serde_json::json!({"apiVersion": "v1", "kind": "Pod"}),
            false,
        )
        .unwrap_err();
        assert!(
            e.message
                .contains("does not match the expected API version"),
            "{}",
            e.message
        );
    }
}
