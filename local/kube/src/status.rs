//! `Status` error bodies (kind Status, apiVersion v1) in the shapes and wording of the real API server.

use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde_json::{json, Map, Value};

/// A served resource type, as Status messages and discovery name it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Resource {
    /// API group (`""` for core).
    pub group: &'static str,
    /// API version.
    pub version: &'static str,
    /// Plural resource name (`jobs`).
    pub plural: &'static str,
    /// Singular resource name (`job`).
    pub singular: &'static str,
    /// Kind (`Job`).
    pub kind: &'static str,
    /// Whether objects live in namespaces.
    pub namespaced: bool,
}

/// `batch/v1` Jobs.
pub const JOBS: Resource = Resource {
    group: "batch",
    version: "v1",
    plural: "jobs",
    singular: "job",
    kind: "Job",
    namespaced: true,
};

/// `v1` Pods.
pub const PODS: Resource = Resource {
    group: "",
    version: "v1",
    plural: "pods",
    singular: "pod",
    kind: "Pod",
    namespaced: true,
};

/// `v1` Namespaces.
pub const NAMESPACES: Resource = Resource {
    group: "",
    version: "v1",
    plural: "namespaces",
    singular: "namespace",
    kind: "Namespace",
    namespaced: false,
};

impl Resource {
    /// `jobs.batch`, `pods`: how messages name the resource.
    pub fn qualified(&self) -> String {
        if self.group.is_empty() {
            self.plural.to_owned()
        } else {
            format!("{}.{}", self.plural, self.group)
        }
    }

    /// `Job.batch`, `Pod`: how Invalid messages name the kind.
    pub fn group_kind(&self) -> String {
        if self.group.is_empty() {
            self.kind.to_owned()
        } else {
            format!("{}.{}", self.kind, self.group)
        }
    }

    /// `batch/v1` or `v1`.
    pub fn api_version(&self) -> String {
        if self.group.is_empty() {
            self.version.to_owned()
        } else {
            format!("{}/{}", self.group, self.version)
        }
    }

    fn details(&self, name: Option<&str>) -> Map<String, Value> {
        let mut details = Map::new();
        if let Some(name) = name {
            details.insert("name".into(), json!(name));
        }
        if !self.group.is_empty() {
            details.insert("group".into(), json!(self.group));
        }
        details.insert("kind".into(), json!(self.plural));
        details
    }
}

/// The kind of a field validation error (`metav1.CauseType`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FieldErrorType {
    /// `FieldValueInvalid`.
    Invalid,
    /// `FieldValueRequired`.
    Required,
    /// `FieldValueNotSupported`.
    NotSupported,
    /// `FieldValueDuplicate`.
    Duplicate,
    /// `FieldValueNotFound`.
    NotFound,
    /// `FieldValueForbidden`.
    Forbidden,
}

impl FieldErrorType {
    fn cause(self) -> &'static str {
        match self {
            Self::Invalid => "FieldValueInvalid",
            Self::Required => "FieldValueRequired",
            Self::NotSupported => "FieldValueNotSupported",
            Self::Duplicate => "FieldValueDuplicate",
            Self::NotFound => "FieldValueNotFound",
            Self::Forbidden => "FieldValueForbidden",
        }
    }
}

/// One validation failure (`field.Error`): type, field path, rendered value and detail.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FieldError {
    /// What is wrong.
    pub type_: FieldErrorType,
    /// Field path, e.g. `spec.template.spec.containers[0].image`.
    pub field: String,
    /// The offending value, already rendered as Go would (`"x"` quoted, numbers bare).
    pub value: Option<String>,
    /// Free-form detail.
    pub detail: String,
}

/// Go's `%q` for the ASCII strings we quote (JSON escaping matches it there).
pub fn go_quote(s: &str) -> String {
    serde_json::to_string(s).unwrap_or_else(|_| format!("\"{s}\""))
}

impl FieldError {
    /// `Invalid value: "<value>": <detail>` for a string value.
    pub fn invalid(field: impl Into<String>, value: &str, detail: impl Into<String>) -> Self {
        Self::invalid_raw(field, go_quote(value), detail)
    }

    /// `Invalid value: <rendered>: <detail>` for an already rendered value.
    pub fn invalid_raw(
        field: impl Into<String>,
        rendered: impl Into<String>,
        detail: impl Into<String>,
    ) -> Self {
        Self {
            type_: FieldErrorType::Invalid,
            field: field.into(),
            value: Some(rendered.into()),
            detail: detail.into(),
        }
    }

    /// `Required value[: <detail>]`.
    pub fn required(field: impl Into<String>, detail: impl Into<String>) -> Self {
        Self {
            type_: FieldErrorType::Required,
            field: field.into(),
            value: None,
            detail: detail.into(),
        }
    }

    /// `Unsupported value: "<value>": supported values: "a", "b"`.
    pub fn not_supported(field: impl Into<String>, value: &str, supported: &[&str]) -> Self {
        let list: Vec<String> = supported.iter().map(|s| go_quote(s)).collect();
        Self {
            type_: FieldErrorType::NotSupported,
            field: field.into(),
            value: Some(go_quote(value)),
            detail: format!("supported values: {}", list.join(", ")),
        }
    }

    /// `Duplicate value: "<value>"`.
    pub fn duplicate(field: impl Into<String>, value: &str) -> Self {
        Self {
            type_: FieldErrorType::Duplicate,
            field: field.into(),
            value: Some(go_quote(value)),
            detail: String::new(),
        }
    }

    /// `Not found: "<value>"`.
    pub fn not_found(field: impl Into<String>, value: &str) -> Self {
        Self {
            type_: FieldErrorType::NotFound,
            field: field.into(),
            value: Some(go_quote(value)),
            detail: String::new(),
        }
    }

    /// `Forbidden: <detail>`.
    pub fn forbidden(field: impl Into<String>, detail: impl Into<String>) -> Self {
        Self {
            type_: FieldErrorType::Forbidden,
            field: field.into(),
            value: None,
            detail: detail.into(),
        }
    }

    /// The message without the field (`field.Error.ErrorBody`).
    pub fn body(&self) -> String {
        let mut s = match self.type_ {
            FieldErrorType::Invalid => "Invalid value",
            FieldErrorType::Required => "Required value",
            FieldErrorType::NotSupported => "Unsupported value",
            FieldErrorType::Duplicate => "Duplicate value",
            FieldErrorType::NotFound => "Not found",
            FieldErrorType::Forbidden => "Forbidden",
        }
        .to_owned();
        let shows_value = !matches!(
            self.type_,
            FieldErrorType::Required | FieldErrorType::Forbidden
        );
        if let (true, Some(value)) = (shows_value, &self.value) {
            s.push_str(": ");
            s.push_str(value);
        }
        if !self.detail.is_empty() {
            s.push_str(": ");
            s.push_str(&self.detail);
        }
        s
    }
}

impl std::fmt::Display for FieldError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.field, self.body())
    }
}

/// An API failure answered with a `Status` body.
#[derive(Clone, Debug, PartialEq)]
pub struct ApiError {
    /// HTTP status code (also `code` in the body).
    pub code: u16,
    /// `reason` (`NotFound`, `AlreadyExists`, ...).
    pub reason: &'static str,
    /// Human-readable `message`.
    pub message: String,
    /// `details`, when the real server sends them.
    pub details: Option<Map<String, Value>>,
}

impl std::fmt::Display for ApiError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} ({}): {}", self.code, self.reason, self.message)
    }
}

impl std::error::Error for ApiError {}

impl ApiError {
    /// 404 `jobs.batch "x" not found`.
    pub fn not_found(res: &Resource, name: &str) -> Self {
        Self {
            code: 404,
            reason: "NotFound",
            message: format!("{} {} not found", res.qualified(), go_quote(name)),
            details: Some(res.details(Some(name))),
        }
    }

    /// 404 for a path the server does not serve.
    pub fn no_route() -> Self {
        Self {
            code: 404,
            reason: "NotFound",
            message: "the server could not find the requested resource".into(),
            details: Some(Map::new()),
        }
    }

    /// 409 `jobs.batch "x" already exists`.
    pub fn already_exists(res: &Resource, name: &str) -> Self {
        Self {
            code: 409,
            reason: "AlreadyExists",
            message: format!("{} {} already exists", res.qualified(), go_quote(name)),
            details: Some(res.details(Some(name))),
        }
    }

    /// 422 `Job.batch "x" is invalid: ...` with one cause per field error.
    pub fn invalid(res: &Resource, name: &str, errors: &[FieldError]) -> Self {
        let causes: Vec<Value> = errors
            .iter()
            .map(|e| json!({"reason": e.type_.cause(), "message": e.body(), "field": e.field}))
            .collect();
        // NB: the real aggregate drops repeated messages but keeps every cause.
        let mut seen = Vec::<String>::new();
        for e in errors {
            let s = e.to_string();
            if !seen.contains(&s) {
                seen.push(s);
            }
        }
        let aggregate = match seen.len() {
            0 => String::new(),
            1 => format!(": {}", seen[0]),
            _ => format!(": [{}]", seen.join(", ")),
        };
        let mut details = Map::new();
        details.insert("name".into(), json!(name));
        if !res.group.is_empty() {
            details.insert("group".into(), json!(res.group));
        }
        details.insert("kind".into(), json!(res.kind));
        details.insert("causes".into(), Value::Array(causes));
        Self {
            code: 422,
            reason: "Invalid",
            message: format!(
                "{} {} is invalid{aggregate}",
                res.group_kind(),
                go_quote(name)
            ),
            details: Some(details),
        }
    }

    /// 400 BadRequest with a message.
    pub fn bad_request(message: impl Into<String>) -> Self {
        Self {
            code: 400,
            reason: "BadRequest",
            message: message.into(),
            details: None,
        }
    }

    /// 401 for a missing or wrong bearer token.
    pub fn unauthorized() -> Self {
        Self {
            code: 401,
            reason: "Unauthorized",
            message: "Unauthorized".into(),
            details: None,
        }
    }

    /// 403 in the RBAC form: `jobs.batch "x" is forbidden: User "u" cannot get resource "jobs" ...`.
    pub fn forbidden(
        user: &str,
        verb: &str,
        res: &Resource,
        namespace: &str,
        name: Option<&str>,
    ) -> Self {
        let subject = match name {
            Some(n) => format!("{} {}", res.qualified(), go_quote(n)),
            None => res.qualified(),
        };
        Self {
            code: 403,
            reason: "Forbidden",
            message: format!(
                "{subject} is forbidden: User {} cannot {verb} resource {} in API group {} in the namespace {}",
                go_quote(user),
                go_quote(res.plural),
                go_quote(res.group),
                go_quote(namespace)
            ),
            details: Some(res.details(name)),
        }
    }

    /// 405 for a verb the resource does not support.
    pub fn method_not_allowed() -> Self {
        Self {
            code: 405,
            reason: "MethodNotAllowed",
            message: "the server does not allow this method on the requested resource".into(),
            details: Some(Map::new()),
        }
    }

    /// 406 for an `Accept` the server cannot produce.
    pub fn not_acceptable(message: impl Into<String>) -> Self {
        Self {
            code: 406,
            reason: "NotAcceptable",
            message: message.into(),
            details: None,
        }
    }

    /// 410 Expired for a watch or list from a resourceVersion no longer kept.
    pub fn expired(message: impl Into<String>) -> Self {
        Self {
            code: 410,
            reason: "Expired",
            message: message.into(),
            details: None,
        }
    }

    /// 415 for a body the server cannot decode.
    pub fn unsupported_media_type(content_type: &str) -> Self {
        Self {
            code: 415,
            reason: "UnsupportedMediaType",
            message: format!("the body of the request was in an unknown format - accepted media types include: application/json, application/yaml (got {content_type})"),
            details: None,
        }
    }

    /// 500 for a failure of this server.
    pub fn internal(message: impl Into<String>) -> Self {
        Self {
            code: 500,
            reason: "InternalError",
            message: message.into(),
            details: None,
        }
    }

    /// 500 `Internal error occurred: <cause>` with the cause, as the apiserver's
    /// `NewInternalError` writes it (its storage failing, say).
    pub fn internal_error_occurred(cause: &str) -> Self {
        let mut details = Map::new();
        details.insert("causes".into(), serde_json::json!([{ "message": cause }]));
        Self {
            details: Some(details),
            ..Self::internal(format!("Internal error occurred: {cause}"))
        }
    }

    /// 503 while the server shuts down.
    pub fn unavailable(message: impl Into<String>) -> Self {
        Self {
            code: 503,
            reason: "ServiceUnavailable",
            message: message.into(),
            details: None,
        }
    }

    /// The `Status` object.
    pub fn to_status(&self) -> Value {
        let mut status = Map::new();
        status.insert("kind".into(), json!("Status"));
        status.insert("apiVersion".into(), json!("v1"));
        status.insert("metadata".into(), json!({}));
        status.insert("status".into(), json!("Failure"));
        status.insert("message".into(), json!(self.message));
        status.insert("reason".into(), json!(self.reason));
        if let Some(details) = &self.details {
            status.insert("details".into(), Value::Object(details.clone()));
        }
        status.insert("code".into(), json!(self.code));
        Value::Object(status)
    }
}

/// The `Status` of a successful delete (`status: Success` with the object's details).
pub fn success_status(res: &Resource, name: &str, uid: &str) -> Value {
    let mut details = res.details(Some(name));
    details.insert("uid".into(), json!(uid));
    json!({
        "kind": "Status",
        "apiVersion": "v1",
        "metadata": {},
        "status": "Success",
        "details": details,
    })
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let code = StatusCode::from_u16(self.code).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR);
        let body = serde_json::to_vec(&self.to_status()).unwrap_or_default();
        let mut resp = (code, body).into_response();
        resp.headers_mut().insert(
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/json"),
        );
        resp
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn not_found_names_the_qualified_resource_like_the_real_server() {
        let s = ApiError::not_found(&JOBS, "x").to_status();
        assert_eq!(s["message"], "jobs.batch \"x\" not found");
        assert_eq!(s["details"]["group"], "batch");
        assert_eq!(s["details"]["kind"], "jobs");
        assert_eq!(s["code"], 404);
        let p = ApiError::not_found(&PODS, "p").to_status();
        assert_eq!(p["message"], "pods \"p\" not found");
        assert!(p["details"].get("group").is_none());
    }

    #[test]
    fn invalid_aggregates_distinct_messages_and_keeps_every_cause() {
        let e = FieldError::invalid("spec.template.labels", "n", "must be no more than 63 bytes");
        let s = ApiError::invalid(&JOBS, "n", &[e.clone(), e]).to_status();
        assert_eq!(
            s["message"],
            "Job.batch \"n\" is invalid: spec.template.labels: Invalid value: \"n\": must be no more than 63 bytes"
        );
        assert_eq!(s["details"]["causes"].as_array().map(Vec::len), Some(2));
        assert_eq!(s["details"]["causes"][0]["reason"], "FieldValueInvalid");
        let two = ApiError::invalid(
            &JOBS,
            "n",
            &[
                FieldError::required("spec.template.spec.containers", ""),
                FieldError::not_supported(
                    "spec.template.spec.restartPolicy",
                    "Always",
                    &["OnFailure", "Never"],
                ),
            ],
        );
        assert_eq!(
            two.message,
            "Job.batch \"n\" is invalid: [spec.template.spec.containers: Required value, spec.template.spec.restartPolicy: Unsupported value: \"Always\": supported values: \"OnFailure\", \"Never\"]"
        );
    }

    #[test]
    fn forbidden_uses_the_rbac_sentence() {
        let e = ApiError::forbidden("local-kube", "create", &JOBS, "kube-system", None);
        assert_eq!(
            e.message,
            "jobs.batch is forbidden: User \"local-kube\" cannot create resource \"jobs\" in API group \"batch\" in the namespace \"kube-system\""
        );
        assert_eq!(e.code, 403);
    }
}
