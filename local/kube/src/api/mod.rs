//! HTTP routes of the API server: discovery, Jobs, Pods, logs, watches, auth and RBAC-like checks.

mod discovery;
mod jobs;
mod nodes;
mod objects;
mod pods;
mod stream;
mod table;
mod watch;

use std::collections::BTreeSet;
use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use k8s_openapi::api::batch::v1::Job;
use k8s_openapi::api::core::v1::Pod;
use serde::Deserialize;
use serde_json::Value;

use crate::objects::names::dns1123_label_errors;
use crate::runtime::Runtime;
use crate::status::{ApiError, Resource, NAMESPACES};

/// The user every request acts as (named in Forbidden messages).
pub const USER: &str = "local-kube";

/// Shared state of the handlers.
#[derive(Clone)]
pub struct AppState {
    /// The runtime (and its store).
    pub rt: Arc<Runtime>,
    /// Required bearer token.
    pub token: Option<Arc<str>>,
    /// Namespaces answered with 403.
    pub forbidden: Arc<BTreeSet<String>>,
    /// `host:port` clients reach us on.
    pub address: Arc<str>,
    /// When the server started (namespaces' creationTimestamp).
    pub started: k8s_openapi::apimachinery::pkg::apis::meta::v1::Time,
    /// An injected outage: every API request is answered 500 until then.
    pub outage: Arc<Outage>,
}

/// Fault injection: the API server failing every request with 500 `InternalError` (as an
/// apiserver whose etcd is unreachable does) for a while; health endpoints keep answering.
#[derive(Debug, Default)]
pub struct Outage {
    until: std::sync::Mutex<Option<std::time::Instant>>,
}

impl Outage {
    /// Fails every API request for `duration` from now.
    pub fn fail_for(&self, duration: std::time::Duration) {
        let until = std::time::Instant::now() + duration;
        *self.until.lock().unwrap_or_else(|e| e.into_inner()) = Some(until);
    }

    fn active(&self) -> bool {
        self.until
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .is_some_and(|until| std::time::Instant::now() < until)
    }
}

impl AppState {
    /// 403 when the namespace is forbidden.
    pub fn check(
        &self,
        verb: &str,
        res: &Resource,
        namespace: &str,
        name: Option<&str>,
    ) -> Result<(), ApiError> {
        if self.forbidden.contains(namespace) {
            return Err(ApiError::forbidden(USER, verb, res, namespace, name));
        }
        Ok(())
    }
}

/// Query parameters the handlers understand (all optional, parsed leniently).
#[derive(Debug, Default, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct Params {
    /// `labelSelector`.
    pub label_selector: Option<String>,
    /// `fieldSelector`.
    pub field_selector: Option<String>,
    /// `limit`.
    pub limit: Option<String>,
    /// `continue`.
    #[serde(rename = "continue")]
    pub continue_: Option<String>,
    /// `watch`.
    pub watch: Option<String>,
    /// `resourceVersion`.
    pub resource_version: Option<String>,
    /// `timeoutSeconds`.
    pub timeout_seconds: Option<String>,
    /// `sendInitialEvents`.
    pub send_initial_events: Option<String>,
    /// `allowWatchBookmarks`.
    pub allow_watch_bookmarks: Option<String>,
    /// `propagationPolicy`.
    pub propagation_policy: Option<String>,
    /// `gracePeriodSeconds`.
    pub grace_period_seconds: Option<String>,
    /// `orphanDependents`.
    pub orphan_dependents: Option<String>,
    /// `dryRun`.
    pub dry_run: Option<String>,
    /// `fieldValidation`.
    pub field_validation: Option<String>,
    /// `container` (logs).
    pub container: Option<String>,
    /// `previous` (logs).
    pub previous: Option<String>,
    /// `tailLines` (logs).
    pub tail_lines: Option<String>,
    /// `follow` (logs).
    pub follow: Option<String>,
    /// `limitBytes` (logs).
    pub limit_bytes: Option<String>,
}

/// `true`, `1` (and `True`) are true, as Go's strconv.ParseBool.
pub fn truthy(v: &Option<String>) -> bool {
    matches!(
        v.as_deref(),
        Some("true" | "1" | "True" | "TRUE" | "t" | "T")
    )
}

/// A non-negative integer parameter, or a 400 naming it.
pub fn int_param(name: &str, v: &Option<String>) -> Result<Option<i64>, ApiError> {
    match v.as_deref().filter(|s| !s.is_empty()) {
        None => Ok(None),
        Some(s) => s
            .parse::<i64>()
            .ok()
            .filter(|n| *n >= 0)
            .map(Some)
            .ok_or_else(|| {
                ApiError::bad_request(format!("invalid value {s:?} for parameter {name}"))
            }),
    }
}

/// A JSON response with a status code.
pub fn json(code: StatusCode, value: &Value) -> Response {
    let body = serde_json::to_vec(value).unwrap_or_default();
    let mut resp = (code, body).into_response();
    resp.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/json"),
    );
    resp
}

/// Decodes a request body (JSON or YAML) into a JSON value.
pub fn decode_body(headers: &HeaderMap, body: &Bytes) -> Result<Value, ApiError> {
    let ct = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("application/json")
        .to_ascii_lowercase();
    if ct.contains("protobuf") || ct.contains("cbor") {
        return Err(ApiError::unsupported_media_type(&ct));
    }
    if ct.contains("yaml") {
        serde_yaml::from_slice::<Value>(body).map_err(|e| {
            ApiError::bad_request(format!("couldn't get version/kind; yaml parse error: {e}"))
        })
    } else {
        serde_json::from_slice::<Value>(body).map_err(|e| {
            ApiError::bad_request(format!("couldn't get version/kind; json parse error: {e}"))
        })
    }
}

/// 404 for a namespace name that cannot exist.
pub fn valid_namespace(ns: &str) -> Result<(), ApiError> {
    if dns1123_label_errors(ns).is_empty() {
        Ok(())
    } else {
        Err(ApiError::not_found(&NAMESPACES, ns))
    }
}

async fn auth(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let path = req.uri().path();
    let open = matches!(path, "/healthz" | "/livez" | "/readyz");
    if let (Some(token), false) = (&state.token, open) {
        let given = req
            .headers()
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "))
            .map(str::trim);
        let ok = given.is_some_and(|g| constant_time_eq(g.as_bytes(), token.as_bytes()));
        if !ok {
            return ApiError::unauthorized().into_response();
        }
    }
    let method = req.method().clone();
    let uri = req.uri().clone();
    if !open && state.outage.active() {
        tracing::debug!(%method, %uri, "injected outage: 500");
        return ApiError::internal_error_occurred("etcdserver: request timed out").into_response();
    }
    let resp = next.run(req).await;
    tracing::debug!(%method, %uri, status = resp.status().as_u16(), "request");
    resp
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

async fn not_found() -> Response {
    ApiError::no_route().into_response()
}

async fn not_allowed() -> Response {
    ApiError::method_not_allowed().into_response()
}

async fn healthz() -> &'static str {
    "ok"
}

/// The router with every route of the server.
pub fn router(state: AppState) -> Router {
    Router::new()
        .route("/healthz", get(healthz))
        .route("/livez", get(healthz))
        .route("/readyz", get(healthz))
        .route("/version", get(discovery::version))
        .route("/api", get(discovery::api_versions))
        .route("/api/v1", get(discovery::core_v1))
        .route("/apis", get(discovery::api_groups))
        .route("/apis/batch", get(discovery::batch_group))
        .route("/apis/batch/v1", get(discovery::batch_v1))
        .route("/openapi/v2", get(discovery::openapi_v2))
        .route("/openapi/v3", get(discovery::openapi_v3_index))
        .route("/openapi/v3/{*path}", get(discovery::openapi_v3_doc))
        .route("/api/v1/namespaces", get(discovery::list_namespaces))
        .route("/api/v1/namespaces/{ns}", get(discovery::get_namespace))
        .route(
            "/api/v1/namespaces/{ns}/events",
            get(discovery::list_events),
        )
        .route("/api/v1/nodes", get(nodes::list))
        .route("/api/v1/nodes/{name}", get(nodes::get))
        .route("/api/v1/pods", get(objects::list_everywhere::<Pod>))
        .route("/api/v1/namespaces/{ns}/pods", get(objects::list_in::<Pod>))
        .route(
            "/api/v1/namespaces/{ns}/pods/{name}",
            get(objects::get_named::<Pod>).delete(pods::delete),
        )
        .route(
            "/api/v1/namespaces/{ns}/pods/{name}/status",
            get(objects::get_named::<Pod>),
        )
        .route("/api/v1/namespaces/{ns}/pods/{name}/log", get(pods::log))
        .route(
            "/api/v1/namespaces/{ns}/pods/{name}/eviction",
            axum::routing::post(pods::evict),
        )
        .route("/apis/batch/v1/jobs", get(objects::list_everywhere::<Job>))
        .route(
            "/apis/batch/v1/namespaces/{ns}/jobs",
            get(objects::list_in::<Job>).post(jobs::create),
        )
        .route(
            "/apis/batch/v1/namespaces/{ns}/jobs/{name}",
            get(objects::get_named::<Job>)
                .patch(jobs::patch)
                .delete(jobs::delete),
        )
        .route(
            "/apis/batch/v1/namespaces/{ns}/jobs/{name}/status",
            get(objects::get_named::<Job>),
        )
        .fallback(not_found)
        .method_not_allowed_fallback(not_allowed)
        .layer(axum::middleware::from_fn_with_state(state.clone(), auth))
        .with_state(state)
}
