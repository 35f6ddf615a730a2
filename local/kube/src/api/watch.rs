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
use crate::store::{AnyObject, Event, Stored};

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

/// What one watch streams: the objects its filter keeps, with bookmarks if asked.
struct Stream {
    filter: Filter,
    list_kind: String,
    api_version: String,
    bookmarks: bool,
}

/// Where a watch starts: the lines sent first, the live events after them and the version
/// they follow; or, for a version the store no longer holds, the one ERROR line it gets.
enum Start {
    From {
        first: Vec<Bytes>,
        live: broadcast::Receiver<Arc<Event>>,
        rv: u64,
    },
    Expired(Bytes),
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
    let stream = Stream {
        filter: Filter {
            kind: res,
            namespace: namespace.map(str::to_owned),
            selectors,
        },
        list_kind: res.kind.to_owned(),
        api_version: res.api_version(),
        bookmarks: truthy(&p.allow_watch_bookmarks),
    };
    // Decide the starting point synchronously so bad versions fail the request itself.
    let (first, live, start_rv) = match stream.start(state, namespace, p)? {
        Start::From { first, live, rv } => (first, live, rv),
        Start::Expired(error) => {
            // NB: like the real server: 200 and one ERROR event; clients relist.
            let (tx, rx) = mpsc::channel::<Bytes>(1);
            let _ = tx.try_send(error);
            return Ok(stream_response(rx));
        }
    };
    let (tx, rx) = mpsc::channel::<Bytes>(64);
    let mut shutdown = state.rt.shutdown_signal();
    tokio::spawn(async move {
        let deadline = tokio::time::sleep(timeout);
        tokio::pin!(deadline);
        tokio::select! {
            _ = &mut deadline => {}
            _ = stream.send(&tx, first, live, start_rv) => {}
            _ = crate::runtime::Runtime::until_shutdown(&mut shutdown) => {}
        }
    });
    Ok(stream_response(rx))
}

impl Stream {
    /// The watch's starting point from its `resourceVersion`: a snapshot of what exists now
    /// (none, `0`, or `sendInitialEvents`), or the store's events since that version.
    fn start(
        &self,
        state: &AppState,
        namespace: Option<&str>,
        p: &Params,
    ) -> Result<Start, ApiError> {
        let store = &state.rt.store;
        let rv = p.resource_version.as_deref().unwrap_or_default();
        let initial = truthy(&p.send_initial_events);
        if rv.is_empty() || rv == "0" || initial {
            let (objects, live, now) = store.snapshot_and_subscribe(&self.filter.kind, namespace);
            let mut first: Vec<Bytes> = objects
                .iter()
                .filter(|o| self.filter.keep(o))
                .map(|o| line("ADDED", o.to_json()))
                .collect();
            if initial {
                first.push(bookmark(&self.list_kind, &self.api_version, now, true));
            }
            return Ok(Start::From {
                first,
                live,
                rv: now,
            });
        }
        let since: u64 = rv
            .parse()
            .map_err(|_| ApiError::bad_request(format!("invalid resource version {rv:?}")))?;
        Ok(match store.subscribe(since) {
            Ok(crate::store::Subscription { past, live, rv }) => Start::From {
                first: past
                    .iter()
                    .filter(|e| self.filter.keep(&e.object))
                    .map(|e| line(e.type_.as_str(), e.object.to_json()))
                    .collect(),
                live,
                rv,
            },
            Err(oldest) => Start::Expired(line(
                "ERROR",
                ApiError::expired(format!(
                    "too old resource version: {since} ({})",
                    oldest.saturating_sub(1)
                ))
                .to_status(),
            )),
        })
    }

    /// Sends the first lines, then each live event newer than `rv` that the filter keeps (and
    /// a bookmark every 30 s if asked), until the client goes or the store's events do.
    async fn send(
        &self,
        tx: &mpsc::Sender<Bytes>,
        first: Vec<Bytes>,
        mut live: broadcast::Receiver<Arc<Event>>,
        rv: u64,
    ) {
        for b in first {
            if tx.send(b).await.is_err() {
                return;
            }
        }
        let mut last_rv = rv;
        let mut tick = tokio::time::interval(Duration::from_secs(30));
        tick.tick().await;
        loop {
            let next = tokio::select! {
                _ = tick.tick(), if self.bookmarks => {
                    bookmark(&self.list_kind, &self.api_version, last_rv, false)
                }
                ev = live.recv() => match ev {
                    Ok(e) if e.rv <= last_rv => continue,
                    Ok(e) => {
                        last_rv = e.rv;
                        if !self.filter.keep(&e.object) {
                            continue;
                        }
                        line(e.type_.as_str(), e.object.to_json())
                    }
                    Err(broadcast::error::RecvError::Lagged(_)) => {
                        // NB: the client relists on Expired, as after any real watch gap.
                        let status = ApiError::expired("watch fell behind; resource version too old").to_status();
                        let _ = tx.send(line("ERROR", status)).await;
                        return;
                    }
                    Err(broadcast::error::RecvError::Closed) => return,
                },
            };
            if tx.send(next).await.is_err() {
                return;
            }
        }
    }
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
