//! Version, legacy discovery (`/api`, `/apis`, resource lists), a minimal OpenAPI v3 (so kubectl
//! delegates field validation to the server) and implied namespaces.

use axum::extract::{Path, Query, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde_json::{json, Value};
use sha2::{Digest, Sha256};

use super::{json, valid_namespace, AppState, Params};
use crate::selector::FieldSelector;
use crate::status::{ApiError, NAMESPACES};

/// Kubernetes version this server answers as.
pub const MAJOR: &str = "1";
/// Minor version.
pub const MINOR: &str = "35";
/// `gitVersion`.
pub const GIT_VERSION: &str = "v1.35.0-local-kube";

/// GET /version
pub async fn version() -> Response {
    json(
        StatusCode::OK,
        &json!({
            "major": MAJOR,
            "minor": MINOR,
            "emulationMajor": MAJOR,
            "emulationMinor": MINOR,
            "minCompatibilityMajor": MAJOR,
            "minCompatibilityMinor": "34",
            "gitVersion": GIT_VERSION,
            "gitCommit": "0000000000000000000000000000000000000000",
            "gitTreeState": "clean",
            "buildDate": "2025-12-17T00:00:00Z",
            "goVersion": "go1.25.5",
            "compiler": "gc",
            "platform": "linux/amd64",
        }),
    )
}

/// GET /api
pub async fn api_versions(State(state): State<AppState>) -> Response {
    json(
        StatusCode::OK,
        &json!({
            "kind": "APIVersions",
            "versions": ["v1"],
            "serverAddressByClientCIDRs": [{"clientCIDR": "0.0.0.0/0", "serverAddress": &*state.address}],
        }),
    )
}

fn resource(
    name: &str,
    singular: &str,
    kind: &str,
    namespaced: bool,
    verbs: &[&str],
    short: &[&str],
    all: bool,
) -> Value {
    let mut r = json!({
        "name": name,
        "singularName": singular,
        "namespaced": namespaced,
        "kind": kind,
        "verbs": verbs,
    });
    if !short.is_empty() {
        r["shortNames"] = json!(short);
    }
    if all {
        r["categories"] = json!(["all"]);
    }
    r
}

/// `pods/eviction`, as the real server lists it: the subresource's kind is policy/v1's.
fn eviction() -> Value {
    let mut r = resource(
        "pods/eviction",
        "",
        "Eviction",
        true,
        &["create"],
        &[],
        false,
    );
    r["group"] = json!("policy");
    r["version"] = json!("v1");
    r
}

/// GET /api/v1
pub async fn core_v1() -> Response {
    json(
        StatusCode::OK,
        &json!({
            "kind": "APIResourceList",
            "groupVersion": "v1",
            "resources": [
                resource("events", "event", "Event", true, &["list"], &["ev"], false),
                resource("namespaces", "namespace", "Namespace", false, &["get", "list"], &["ns"], false),
                resource("nodes", "node", "Node", false, &["get", "list"], &["no"], false),
                resource("pods", "pod", "Pod", true, &["delete", "get", "list", "watch"], &["po"], true),
                eviction(),
                resource("pods/log", "", "Pod", true, &["get"], &[], false),
                resource("pods/status", "", "Pod", true, &["get"], &[], false),
            ],
        }),
    )
}

/// GET /apis
pub async fn api_groups() -> Response {
    json(
        StatusCode::OK,
        &json!({
            "kind": "APIGroupList",
            "apiVersion": "v1",
            "groups": [batch_group_doc()],
        }),
    )
}

fn batch_group_doc() -> Value {
    json!({
        "name": "batch",
        "versions": [{"groupVersion": "batch/v1", "version": "v1"}],
        "preferredVersion": {"groupVersion": "batch/v1", "version": "v1"},
    })
}

/// GET /apis/batch
pub async fn batch_group() -> Response {
    let mut doc = batch_group_doc();
    doc["kind"] = json!("APIGroup");
    doc["apiVersion"] = json!("v1");
    json(StatusCode::OK, &doc)
}

/// GET /apis/batch/v1
pub async fn batch_v1() -> Response {
    json(
        StatusCode::OK,
        &json!({
            "kind": "APIResourceList",
            "apiVersion": "v1",
            "groupVersion": "batch/v1",
            "resources": [
                resource("jobs", "job", "Job", true, &["create", "delete", "get", "list", "watch"], &[], true),
                resource("jobs/status", "", "Job", true, &["get"], &[], false),
            ],
        }),
    )
}

/// GET /openapi/v2: an empty document (no schemas), so clients that validate against it
/// (kubectl before 1.25) skip client-side validation. Protobuf when asked for (an empty
/// `openapi_v2.Document` is zero bytes), else JSON.
pub async fn openapi_v2(headers: axum::http::HeaderMap) -> Response {
    let accept = headers
        .get(axum::http::header::ACCEPT)
        .and_then(|v| v.to_str().ok())
        .unwrap_or_default();
    if accept.contains("protobuf") {
        let mut resp = (StatusCode::OK, Vec::<u8>::new()).into_response();
        resp.headers_mut().insert(
            axum::http::header::CONTENT_TYPE,
            axum::http::HeaderValue::from_static("application/octet-stream"),
        );
        return resp;
    }
    json(
        StatusCode::OK,
        &json!({
            "swagger": "2.0",
            "info": {"title": "Kubernetes", "version": GIT_VERSION},
            "paths": {},
            "definitions": {},
        }),
    )
}

const OPENAPI_HASH: &str = "6C0CA1D7ED3B6C33A7A5FB3E1C0F7A0E2F11B1B6A9B8E1D7C4F1F5B0E8E2D4C0";

/// GET /openapi/v3: the group-versions with documents.
pub async fn openapi_v3_index() -> Response {
    json(
        StatusCode::OK,
        &json!({
            "paths": {
                "api/v1": {"serverRelativeURL": format!("/openapi/v3/api/v1?hash={OPENAPI_HASH}")},
                "apis/batch/v1": {"serverRelativeURL": format!("/openapi/v3/apis/batch/v1?hash={OPENAPI_HASH}")},
            }
        }),
    )
}

/// A resource's group, version and kind, as OpenAPI names them.
struct Gvk {
    group: &'static str,
    version: &'static str,
    kind: &'static str,
}

fn operation(gvk: &Gvk, action: &str) -> Value {
    json!({
        "operationId": format!("{action}{}", gvk.kind),
        "parameters": [
            {"name": "dryRun", "in": "query", "schema": {"type": "string", "uniqueItems": true}},
            {"name": "fieldManager", "in": "query", "schema": {"type": "string", "uniqueItems": true}},
            {"name": "fieldValidation", "in": "query", "schema": {"type": "string", "uniqueItems": true}},
        ],
        "responses": {"200": {"description": "OK"}},
        "x-kubernetes-action": action,
        "x-kubernetes-group-version-kind": {"group": gvk.group, "version": gvk.version, "kind": gvk.kind},
    })
}

/// GET /openapi/v3/{gv}: operations only (no schemas), enough for kubectl to see that the
/// server validates fields itself.
pub async fn openapi_v3_doc(Path(path): Path<String>) -> Response {
    let (collection, item, gvk) = match path.as_str() {
        "apis/batch/v1" => (
            "/apis/batch/v1/namespaces/{namespace}/jobs",
            "/apis/batch/v1/namespaces/{namespace}/jobs/{name}",
            Gvk {
                group: "batch",
                version: "v1",
                kind: "Job",
            },
        ),
        "api/v1" => (
            "/api/v1/namespaces/{namespace}/pods",
            "/api/v1/namespaces/{namespace}/pods/{name}",
            Gvk {
                group: "",
                version: "v1",
                kind: "Pod",
            },
        ),
        _ => return ApiError::no_route().into_response(),
    };
    let mut paths = serde_json::Map::new();
    paths.insert(
        collection.into(),
        json!({ "post": operation(&gvk, "post") }),
    );
    paths.insert(item.into(), json!({ "patch": operation(&gvk, "patch") }));
    json(
        StatusCode::OK,
        &json!({
            "openapi": "3.0.0",
            "info": {"title": "Kubernetes", "version": GIT_VERSION},
            "paths": paths,
            "components": {"schemas": {}},
        }),
    )
}

fn namespace_uid(ns: &str) -> String {
    let d = Sha256::digest(ns.as_bytes());
    let h: String = d.iter().take(16).map(|b| format!("{b:02x}")).collect();
    format!(
        "{}-{}-4{}-a{}-{}",
        &h[0..8],
        &h[8..12],
        &h[13..16],
        &h[17..20],
        &h[20..32]
    )
}

fn namespace(state: &AppState, ns: &str) -> Value {
    json!({
        "kind": "Namespace",
        "apiVersion": "v1",
        "metadata": {
            "name": ns,
            "uid": namespace_uid(ns),
            "resourceVersion": "1",
            "creationTimestamp": serde_json::to_value(&state.started).unwrap_or_default(),
            "labels": {"kubernetes.io/metadata.name": ns},
        },
        "spec": {"finalizers": ["kubernetes"]},
        "status": {"phase": "Active"},
    })
}

/// GET /api/v1/namespaces/{ns}: every valid namespace exists.
pub async fn get_namespace(State(state): State<AppState>, Path(ns): Path<String>) -> Response {
    let result = (|| {
        if state.forbidden.contains(&ns) {
            return Err(ApiError::forbidden(
                super::USER,
                "get",
                &NAMESPACES,
                &ns,
                Some(&ns),
            ));
        }
        valid_namespace(&ns)?;
        Ok(json(StatusCode::OK, &namespace(&state, &ns)))
    })();
    result.unwrap_or_else(IntoResponse::into_response)
}

/// GET /api/v1/namespaces: the usual ones plus every namespace holding objects.
pub async fn list_namespaces(State(state): State<AppState>) -> Response {
    let mut names: Vec<String> = ["default", "kube-node-lease", "kube-public", "kube-system"]
        .iter()
        .map(|s| s.to_string())
        .chain(state.rt.store.namespaces())
        .filter(|n| !state.forbidden.contains(n))
        .collect();
    names.sort();
    names.dedup();
    let items: Vec<Value> = names
        .iter()
        .map(|n| {
            let mut v = namespace(&state, n);
            if let Value::Object(m) = &mut v {
                m.remove("kind");
                m.remove("apiVersion");
            }
            v
        })
        .collect();
    json(
        StatusCode::OK,
        &json!({
            "kind": "NamespaceList",
            "apiVersion": "v1",
            "metadata": {"resourceVersion": state.rt.store.resource_version().to_string()},
            "items": items,
        }),
    )
}

/// GET /api/v1/namespaces/{ns}/events: the events local-kube records (the Cluster
/// Autoscaler's, with `Config::autoscaler`), field selectors as the real server takes them.
pub async fn list_events(
    State(state): State<AppState>,
    Path(ns): Path<String>,
    Query(p): Query<Params>,
) -> Response {
    let events = crate::status::Resource {
        group: "",
        version: "v1",
        plural: "events",
        singular: "event",
        kind: "Event",
        namespaced: true,
    };
    if let Err(e) = state.check("list", &events, &ns, None) {
        return e.into_response();
    }
    let fields = match FieldSelector::parse(
        p.field_selector.as_deref().unwrap_or_default(),
        &crate::runtime::events::FIELDS,
    ) {
        Ok(f) => f,
        Err(e) => return ApiError::bad_request(e).into_response(),
    };
    let items = state
        .rt
        .events
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .list(&ns, |e| {
            fields.matches(|f| crate::runtime::events::field(e, f))
        })
        .into_iter()
        .map(|e| super::objects::as_list_item(serde_json::to_value(e).unwrap_or_default()))
        .collect::<Vec<_>>();
    json(
        StatusCode::OK,
        &json!({
            "kind": "EventList",
            "apiVersion": "v1",
            "metadata": {"resourceVersion": state.rt.store.resource_version().to_string()},
            "items": items,
        }),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn namespace_uids_are_stable_uuids() {
        let a = namespace_uid("default");
        assert_eq!(a, namespace_uid("default"));
        assert_ne!(a, namespace_uid("other"));
        assert_eq!(a.len(), 36);
        assert_eq!(a.as_bytes()[14], b'4');
    }
}
