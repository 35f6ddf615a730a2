//! `v1` Nodes, read-only: the one node, with the labels its node group gives it (instance type,
//! GPU model, capacity type) and its GPUs, as `kubectl get node -o json` shows a node.

use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde_json::{json, Value};

use super::{json, AppState};
use crate::runtime::scheduler::{node_labels, UNMODELLED_GPUS};
use crate::status::{ApiError, Resource};

/// The `nodes` resource (cluster-scoped).
pub const NODES: Resource = Resource {
    group: "",
    version: "v1",
    plural: "nodes",
    singular: "node",
    kind: "Node",
    namespaced: false,
};

fn node(state: &AppState) -> Value {
    let rt = &state.rt;
    let gpus = rt.node_model.gpus.unwrap_or(UNMODELLED_GPUS).to_string();
    let cpus = std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .to_string();
    let resources = json!({"cpu": cpus, "nvidia.com/gpu": gpus, "pods": "110"});
    json!({
        "kind": "Node",
        "apiVersion": "v1",
        "metadata": {
            "name": rt.node,
            "labels": node_labels(&rt.node, &rt.node_model),
        },
        "spec": {},
        "status": {
            "capacity": resources,
            "allocatable": resources,
            "conditions": [{
                "type": "Ready", "status": "True",
                "reason": "KubeletReady", "message": "kubelet is posting ready status",
            }],
        },
    })
}

/// GET /api/v1/nodes/{name}
pub async fn get(State(state): State<AppState>, Path(name): Path<String>) -> Response {
    if name != state.rt.node {
        return ApiError::not_found(&NODES, &name).into_response();
    }
    json(StatusCode::OK, &node(&state))
}

/// GET /api/v1/nodes
pub async fn list(State(state): State<AppState>) -> Response {
    let mut item = node(&state);
    if let Value::Object(m) = &mut item {
        m.remove("kind");
        m.remove("apiVersion");
    }
    json(
        StatusCode::OK,
        &json!({
            "kind": "NodeList",
            "apiVersion": "v1",
            "metadata": {"resourceVersion": state.rt.store.resource_version().to_string()},
            "items": [item],
        }),
    )
}
