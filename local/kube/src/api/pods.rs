//! `v1` Pod handlers: list, get, delete, and the `log` subresource (current, previous, tail,
//! follow).

use std::io::{Read, Seek, SeekFrom};
use std::time::Duration;

use axum::body::Bytes;
use axum::extract::{Path, Query, State};
use axum::http::HeaderMap;
use axum::response::Response;
use k8s_openapi::api::core::v1::{ContainerStatus, Pod};
use tokio::sync::mpsc;

use super::jobs::delete_options;
use super::objects::{into_response, text, to_json};
use super::watch::stream_response;
use super::{int_param, json, truthy, AppState, Params};
use crate::objects::pod::set_disruption_target;
use crate::status::{go_quote, ApiError, PODS};
use crate::store::ObjKey;

/// DELETE /api/v1/namespaces/{ns}/pods/{name}: marks the pod, terminates it in the background.
pub async fn delete(
    State(state): State<AppState>,
    Path((ns, name)): Path<(String, String)>,
    Query(p): Query<Params>,
    headers: HeaderMap,
    body: Bytes,
) -> Response {
    let result = (|| {
        state.check("delete", &PODS, &ns, Some(&name))?;
        let opts = delete_options(&p, &headers, &body)?;
        let key = ObjKey::new(&ns, &name);
        let pod = existing(&state, &key)?;
        if let Some(want) = opts.uid.as_deref() {
            let uid = pod.metadata.uid.clone().unwrap_or_default();
            if want != uid {
                return Err(ApiError {
                    code: 409,
                    reason: "Conflict",
                    message: format!("Precondition failed: UID in precondition: {want}, UID in object meta: {uid}"),
                    details: None,
                });
            }
        }
        if opts.dry_run {
            return Ok(json(axum::http::StatusCode::OK, &to_json(&pod)));
        }
        let marked = delete_gracefully(&state, key, opts.grace).unwrap_or(pod);
        Ok(json(axum::http::StatusCode::OK, &to_json(&marked)))
    })();
    into_response(result)
}

/// POST /api/v1/namespaces/{ns}/pods/{name}/eviction (`policy/v1` Eviction): what a drain
/// does to each pod of a node (`kubectl drain`; EKS managed node groups on a Spot
/// interruption or rebalance recommendation). No PodDisruptionBudget exists here, so every
/// eviction is allowed: the pod gets the `DisruptionTarget` condition (reason
/// `EvictionByEvictionAPI`, message `Eviction API: evicting`) and is deleted gracefully
/// (Kubernetes docs, "API-initiated Eviction"; "Pod disruption conditions"). A pod that has
/// finished is just deleted.
pub async fn evict(
    State(state): State<AppState>,
    Path((ns, name)): Path<(String, String)>,
    headers: HeaderMap,
    body: Bytes,
) -> Response {
    let result = (|| {
        state.check("create", &PODS, &ns, Some(&name))?;
        let eviction = super::decode_body(&headers, &body)?;
        let named = eviction["metadata"]["name"].as_str().unwrap_or_default();
        if named != name {
            return Err(ApiError::bad_request(
                "name in URL does not match name in Eviction object",
            ));
        }
        let grace = eviction["deleteOptions"]["gracePeriodSeconds"]
            .as_i64()
            .map(|s| Duration::from_secs(s.max(0) as u64));
        let key = ObjKey::new(&ns, &name);
        let pod = existing(&state, &key)?;
        let finished = matches!(
            pod.status.as_ref().and_then(|s| s.phase.as_deref()),
            Some("Succeeded" | "Failed")
        );
        if !finished && pod.metadata.deletion_timestamp.is_none() {
            state.rt.store.update::<Pod>(&key, |p| {
                set_disruption_target(
                    p.status.get_or_insert_with(Default::default),
                    "EvictionByEvictionAPI",
                    "Eviction API: evicting",
                );
            });
        }
        delete_gracefully(&state, key, grace);
        let done = serde_json::json!({
            "kind": "Status", "apiVersion": "v1", "metadata": {},
            "status": "Success", "code": 201
        });
        Ok(json(axum::http::StatusCode::CREATED, &done))
    })();
    into_response(result)
}

fn existing(state: &AppState, key: &ObjKey) -> Result<Pod, ApiError> {
    state
        .rt
        .store
        .get::<Pod>(key)
        .ok_or_else(|| ApiError::not_found(&PODS, &key.name))
}

/// Marks the pod deleted (returned as it is now) and terminates it in the background.
fn delete_gracefully(state: &AppState, key: ObjKey, grace: Option<Duration>) -> Option<Pod> {
    let marked = state.rt.mark_pod_deleted(&key, grace);
    let rt = state.rt.clone();
    tokio::spawn(async move { rt.delete_pod(&key, grace).await });
    marked
}

fn status_of<'a>(pod: &'a Pod, container: &str) -> Option<&'a ContainerStatus> {
    let status = pod.status.as_ref()?;
    status
        .container_statuses
        .iter()
        .flatten()
        .chain(status.init_container_statuses.iter().flatten())
        .find(|s| s.name == container)
}

fn never_started(s: &ContainerStatus) -> Option<String> {
    let st = s.state.as_ref()?;
    let waiting = st.waiting.as_ref()?;
    let ran = s.restart_count > 0
        || s.last_state
            .as_ref()
            .is_some_and(|l| l.terminated.is_some());
    (!ran).then(|| waiting.reason.clone().unwrap_or_default())
}

fn tail(data: &[u8], lines: Option<i64>) -> &[u8] {
    let Some(n) = lines else { return data };
    if n == 0 {
        return &data[data.len()..];
    }
    let body = data.strip_suffix(b"\n").unwrap_or(data);
    let mut count = 0;
    for (i, b) in body.iter().enumerate().rev() {
        if *b == b'\n' {
            count += 1;
            if count == n {
                return &data[i + 1..];
            }
        }
    }
    data
}

/// GET /api/v1/namespaces/{ns}/pods/{name}/log
pub async fn log(
    State(state): State<AppState>,
    Path((ns, name)): Path<(String, String)>,
    Query(p): Query<Params>,
) -> Response {
    into_response(log_inner(&state, &ns, &name, &p))
}

fn log_inner(state: &AppState, ns: &str, name: &str, p: &Params) -> Result<Response, ApiError> {
    state.check("get", &PODS, ns, Some(name))?;
    let key = ObjKey::new(ns, name);
    let pod = state
        .rt
        .store
        .get::<Pod>(&key)
        .ok_or_else(|| ApiError::not_found(&PODS, name))?;
    let container = container_of(&pod, name, p)?;
    let status = status_of(&pod, &container).cloned().unwrap_or_default();
    let previous = truthy(&p.previous);
    let attempt = if previous {
        if status.restart_count == 0 {
            return Err(ApiError::bad_request(format!(
                "previous terminated container {} in pod {} not found",
                go_quote(&container),
                go_quote(name)
            )));
        }
        status.restart_count - 1
    } else {
        if let Some(reason) = never_started(&status) {
            return Err(ApiError::bad_request(format!(
                "container {} in pod {} is waiting to start: {reason}",
                go_quote(&container),
                go_quote(name)
            )));
        }
        status.restart_count
    };
    let path = state.rt.log_path(&pod, &container, attempt);
    let data = std::fs::read(&path).unwrap_or_default();
    let tail_lines = int_param("tailLines", &p.tail_lines)?;
    let limit = int_param("limitBytes", &p.limit_bytes)?.map(|l| l as usize);
    let mut out = tail(&data, tail_lines).to_vec();
    if let Some(l) = limit {
        out.truncate(l);
    }
    if !truthy(&p.follow) || previous {
        return Ok(text(out));
    }
    let follow = Follow {
        key,
        container,
        attempt,
        path,
    };
    Ok(follow.stream(state.rt.clone(), out, data.len() as u64))
}

/// The container a log request names (the pod's only app container when it names none), one
/// of the pod's.
fn container_of(pod: &Pod, name: &str, p: &Params) -> Result<String, ApiError> {
    let spec = pod.spec.clone().unwrap_or_default();
    let app: Vec<String> = spec.containers.iter().map(|c| c.name.clone()).collect();
    let init: Vec<String> = spec
        .init_containers
        .iter()
        .flatten()
        .map(|c| c.name.clone())
        .collect();
    let container = match p.container.clone().filter(|c| !c.is_empty()) {
        Some(c) => c,
        None if app.len() == 1 => app[0].clone(),
        None => {
            let mut msg = format!(
                "a container name must be specified for pod {name}, choose one of: [{}]",
                app.join(" ")
            );
            if !init.is_empty() {
                msg.push_str(&format!(
                    " or one of the init containers: [{}]",
                    init.join(" ")
                ));
            }
            return Err(ApiError::bad_request(msg));
        }
    };
    if !app.contains(&container) && !init.contains(&container) {
        return Err(ApiError::bad_request(format!(
            "container {container} is not valid for pod {name}"
        )));
    }
    Ok(container)
}

/// What a followed log streams: one attempt of one container of a pod.
struct Follow {
    key: ObjKey,
    container: String,
    attempt: i32,
    path: std::path::PathBuf,
}

impl Follow {
    /// `first` (the log so far, tailed and limited), then what the attempt writes from byte
    /// `start` on, until it stops running or the server shuts down.
    fn stream(
        self,
        rt: std::sync::Arc<crate::runtime::Runtime>,
        first: Vec<u8>,
        start: u64,
    ) -> Response {
        let (tx, rx) = mpsc::channel::<Bytes>(16);
        let mut shutdown = rt.shutdown_signal();
        let Follow {
            key,
            container,
            attempt,
            path,
        } = self;
        tokio::spawn(async move {
            if !first.is_empty() && tx.send(Bytes::from(first)).await.is_err() {
                return;
            }
            let mut offset = start;
            let still_running = || {
                rt.store.get::<Pod>(&key).is_some_and(|p| {
                    status_of(&p, &container).is_some_and(|s| {
                        s.restart_count == attempt
                            && s.state.as_ref().is_some_and(|st| st.running.is_some())
                    })
                })
            };
            loop {
                let running = still_running();
                let chunk = read_from(&path, offset);
                if !chunk.is_empty() {
                    offset += chunk.len() as u64;
                    if tx.send(Bytes::from(chunk)).await.is_err() {
                        return;
                    }
                }
                if !running {
                    return;
                }
                tokio::select! {
                    _ = tokio::time::sleep(Duration::from_millis(100)) => {}
                    _ = crate::runtime::Runtime::until_shutdown(&mut shutdown) => return,
                }
            }
        });
        let mut resp = stream_response(rx);
        resp.headers_mut().insert(
            axum::http::header::CONTENT_TYPE,
            axum::http::HeaderValue::from_static("text/plain"),
        );
        resp
    }
}

fn read_from(path: &std::path::Path, offset: u64) -> Vec<u8> {
    let mut buf = Vec::new();
    if let Ok(mut f) = std::fs::File::open(path) {
        if f.seek(SeekFrom::Start(offset)).is_ok() {
            let _ = f.take(1 << 20).read_to_end(&mut buf);
        }
    }
    buf
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tail_keeps_the_last_lines() {
        assert_eq!(tail(b"a\nb\nc\n", Some(2)), b"b\nc\n");
        assert_eq!(tail(b"a\nb\nc", Some(2)), b"b\nc");
        assert_eq!(tail(b"a\nb\n", Some(5)), b"a\nb\n");
        assert_eq!(tail(b"a\nb\n", Some(0)), b"");
        assert_eq!(tail(b"a\nb\n", None), b"a\nb\n");
    }
}
