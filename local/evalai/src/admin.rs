//! The `/_admin/` API: state, request log, participant actions and faults (no auth, no throttle).

use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::{Path, Query, Request, State};
use axum::http::StatusCode;
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::Deserialize;

use crate::faults::Faults;
use crate::reqlog::RequestRecord;
use crate::server::Shared;
use crate::state::{AdminError, NewSubmission};
use crate::timefmt;

fn error(status: StatusCode, text: impl Into<String>) -> Response {
    (status, Json(serde_json::json!({ "error": text.into() }))).into_response()
}

fn admin_error(e: &AdminError) -> Response {
    let status = match e {
        AdminError::UnknownSubmission(_) => StatusCode::NOT_FOUND,
        _ => StatusCode::BAD_REQUEST,
    };
    (
        status,
        Json(serde_json::json!({ "error": e.to_string(), "name": e.name() })),
    )
        .into_response()
}

fn parse_id(raw: &str) -> Result<u64, Box<Response>> {
    raw.parse().map_err(|_| {
        Box::new(error(
            StatusCode::BAD_REQUEST,
            format!("`{raw}` is not a submission id"),
        ))
    })
}

async fn state(State(shared): State<Arc<Shared>>) -> Response {
    Json(shared.lock().snapshot()).into_response()
}

#[derive(Deserialize)]
struct Since {
    #[serde(default)]
    since: u64,
}

async fn requests(State(shared): State<Arc<Shared>>, Query(q): Query<Since>) -> Response {
    Json(shared.lock().log.since(q.since)).into_response()
}

async fn cancel(State(shared): State<Arc<Shared>>, Path(id): Path<String>) -> Response {
    let id = match parse_id(&id) {
        Ok(id) => id,
        Err(r) => return *r,
    };
    match shared.lock().cancel(id) {
        Ok(s) => Json(s).into_response(),
        Err(e) => admin_error(&e),
    }
}

async fn resume(State(shared): State<Arc<Shared>>, Path(id): Path<String>) -> Response {
    let id = match parse_id(&id) {
        Ok(id) => id,
        Err(r) => return *r,
    };
    match shared.lock().resume(id) {
        Ok(s) => Json(s).into_response(),
        Err(e) => admin_error(&e),
    }
}

async fn add_submission(State(shared): State<Arc<Shared>>, body: Bytes) -> Response {
    let new: NewSubmission = match serde_json::from_slice(&body) {
        Ok(n) => n,
        Err(e) => {
            return error(
                StatusCode::BAD_REQUEST,
                format!("invalid submission JSON: {e}"),
            )
        }
    };
    match shared.lock().add_submission(new) {
        Ok(s) => (StatusCode::CREATED, Json(s)).into_response(),
        Err(e) => admin_error(&e),
    }
}

async fn put_faults(State(shared): State<Arc<Shared>>, body: Bytes) -> Response {
    let faults: Faults = match serde_json::from_slice(&body) {
        Ok(f) => f,
        Err(e) => return error(StatusCode::BAD_REQUEST, format!("invalid faults JSON: {e}")),
    };
    if let Err(e) = faults.validate() {
        return error(StatusCode::BAD_REQUEST, e);
    }
    shared.lock().faults.set(faults.clone());
    Json(faults).into_response()
}

/// Every user's throttle window emptied, as after a minute without requests: a replay of
/// requests that were paced below the limit needs no real minute between them.
async fn reset_throttle(State(shared): State<Arc<Shared>>) -> Response {
    shared.lock().throttle.reset();
    StatusCode::NO_CONTENT.into_response()
}

async fn get_faults(State(shared): State<Arc<Shared>>) -> Response {
    Json(shared.lock().faults.faults.clone()).into_response()
}

/// Logs admin calls with `admin: true` (they are not EvalAI traffic).
async fn log_admin(State(shared): State<Arc<Shared>>, req: Request, next: Next) -> Response {
    let time = timefmt::format(timefmt::now());
    let method = req.method().to_string();
    let path = req.uri().path().to_owned();
    let query = req.uri().query().map(str::to_owned);
    let response = next.run(req).await;
    let record = RequestRecord {
        seq: 0,
        time,
        method,
        path,
        query,
        status: response.status().as_u16(),
        user_id: None,
        admin: true,
        body: None,
        raw_body: None,
        fault: None,
        error: None,
    };
    shared.lock().log.push(record);
    response
}

/// The admin routes, with their logging layer.
pub(crate) fn router(shared: Arc<Shared>) -> Router<Arc<Shared>> {
    Router::new()
        .route("/_admin/state", get(state))
        .route("/_admin/requests", get(requests))
        .route("/_admin/submissions", post(add_submission))
        .route("/_admin/submissions/{id}/cancel", post(cancel))
        .route("/_admin/submissions/{id}/resume", post(resume))
        .route("/_admin/faults", get(get_faults).put(put_faults))
        .route("/_admin/throttle", axum::routing::delete(reset_throttle))
        .route_layer(middleware::from_fn_with_state(shared, log_admin))
}
