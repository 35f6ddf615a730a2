//! `?watch=true`: newline-delimited watch events from a resourceVersion, bounded by
//! `timeoutSeconds` and ended at shutdown.

use std::sync::Arc;
use std::time::Duration;

use axum::body::{Body, Bytes};
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::Response;
use serde_json::{json, Value};
use tokio::sync::{broadcast, mpsc};

use super::objects::Selectors;
use super::stream::ChannelBody;
use super::{int_param, truthy, AppState, Params};
use crate::status::ApiError;
use crate::store::{AnyObject, Event, EventType, Stored};

/// Longest watch before the server closes it (clients re-watch).
const MAX_WATCH: Duration = Duration::from_secs(1800);

fn line(type_: &str, object: Value) -> Bytes {
    let mut v = serde_json::to_vec(&json!({ "type": type_, "object": object })).unwrap_or_default();
    v.push(b'\n');
    Bytes::from(v)
}

fn bookmark(kind: &str, api_version: &str, rv: u64, initial_end: bool) -> Bytes {
    let mut meta = json!({ "resourceVersion": rv.to_string() });
    if initial_end {
        meta["annotations"] = json!({ "k8s.io/initial-events-end": "true" });
    }
    line(
        "BOOKMARK",
        json!({ "kind": kind, "apiVersion": api_version, "metadata": meta }),
    )
}

struct Filter {
    kind: crate::status::Resource,
    namespace: Option<String>,
    selectors: Selectors,
}

impl Filter {
    fn keep(&self, obj: &AnyObject) -> bool {
        if obj.resource() != self.kind {
            return false;
        }
        let meta = obj.meta();
        if self
            .namespace
            .as_deref()
            .is_some_and(|ns| meta.namespace.as_deref() != Some(ns))
        {
            return false;
        }
        self.selectors.labels.matches(meta.labels.as_ref())
            && self.selectors.fields.matches(|f| obj.field(f))
    }
}

/// Starts a watch response for kind `T`.
pub fn watch<T: Stored>(
    state: &AppState,
    namespace: Option<&str>,
    p: &Params,
    selectors: Selectors,
) -> Result<Response, ApiError> {
    let res = T::RESOURCE;
    let timeout = int_param("timeoutSeconds", &p.timeout_seconds)?
        .map(|s| Duration::from_secs(s as u64))
        .unwrap_or(MAX_WATCH)
        .min(MAX_WATCH);
    let rv = p.resource_version.as_deref().unwrap_or_default();
    let initial = truthy(&p.send_initial_events);
    let bookmarks = truthy(&p.allow_watch_bookmarks);
    let filter = Filter {
        kind: res,
        namespace: namespace.map(str::to_owned),
        selectors,
    };
    let store = state.rt.store.clone();
    let mut shutdown = state.rt.shutdown_signal();
    let (tx, rx) = mpsc::channel::<Bytes>(64);
    let list_kind = res.kind.to_owned();
    let api_version = res.api_version();
    // Decide the starting point synchronously so bad versions fail the request itself.
    let (first, mut live, start_rv): (Vec<Bytes>, broadcast::Receiver<Arc<Event>>, u64) =
        if rv.is_empty() || rv == "0" || initial {
            let (objects, live, now) = store.snapshot_and_subscribe(&res, namespace);
            let mut first: Vec<Bytes> = objects
                .iter()
                .filter(|o| filter.keep(o))
                .map(|o| line("ADDED", o.to_json()))
                .collect();
            if initial {
                first.push(bookmark(&list_kind, &api_version, now, true));
            }
            (first, live, now)
        } else {
            let since: u64 = rv
                .parse()
                .map_err(|_| ApiError::bad_request(format!("invalid resource version {rv:?}")))?;
            match store.subscribe(since) {
                Ok(crate::store::Subscription {
                    past,
                    live,
                    rv: now,
                }) => {
                    let first = past
                        .iter()
                        .filter(|e| filter.keep(&e.object))
                        .map(|e| line(e.type_.as_str(), e.object.to_json()))
                        .collect();
                    (first, live, now)
                }
                Err(oldest) => {
                    let status = ApiError::expired(format!(
                        "too old resource version: {since} ({})",
                        oldest.saturating_sub(1)
                    ))
                    .to_status();
                    // NB: like the real server: 200 and one ERROR event; clients relist.
                    let (tx1, rx1) = mpsc::channel::<Bytes>(1);
                    let _ = tx1.try_send(line("ERROR", status));
                    return Ok(stream_response(rx1));
                }
            }
        };
    tokio::spawn(async move {
        let deadline = tokio::time::sleep(timeout);
        tokio::pin!(deadline);
        for b in first {
            if tx.send(b).await.is_err() {
                return;
            }
        }
        let mut last_rv = start_rv;
        let mut tick = tokio::time::interval(Duration::from_secs(30));
        tick.tick().await;
        loop {
            tokio::select! {
                _ = &mut deadline => return,
                _ = crate::runtime::Runtime::until_shutdown(&mut shutdown) => return,
                _ = tick.tick(), if bookmarks => {
                    if tx.send(bookmark(&list_kind, &api_version, last_rv, false)).await.is_err() {
                        return;
                    }
                }
                ev = live.recv() => match ev {
                    Ok(e) => {
                        if e.rv <= last_rv {
                            continue;
                        }
                        last_rv = e.rv;
                        if filter.keep(&e.object) {
                            let type_ = match e.type_ {
                                EventType::Added => "ADDED",
                                EventType::Modified => "MODIFIED",
                                EventType::Deleted => "DELETED",
                            };
                            if tx.send(line(type_, e.object.to_json())).await.is_err() {
                                return;
                            }
                        }
                    }
                    Err(broadcast::error::RecvError::Lagged(_)) => {
                        // NB: the client relists on Expired, as after any real watch gap.
                        let status = ApiError::expired("watch fell behind; resource version too old").to_status();
                        let _ = tx.send(line("ERROR", status)).await;
                        return;
                    }
                    Err(broadcast::error::RecvError::Closed) => return,
                },
            }
        }
    });
    Ok(stream_response(rx))
}

/// A streaming `application/json` response.
pub fn stream_response(rx: mpsc::Receiver<Bytes>) -> Response {
    let mut resp = Response::new(Body::new(ChannelBody(rx)));
    *resp.status_mut() = StatusCode::OK;
    resp.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/json"),
    );
    resp
}
