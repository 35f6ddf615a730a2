//! The EvalAI-facing server: URL resolution, APPEND_SLASH, auth, permissions, throttle, 405, views.

pub(crate) mod body;
pub(crate) mod meta;
pub(crate) mod pyops;
pub(crate) mod reply;
pub(crate) mod views;

use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::body::Bytes;
use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, Method, StatusCode};
use axum::response::{IntoResponse, Response};

use crate::auth::{self, WWW_AUTHENTICATE};
use crate::faults::Decision;
use crate::pyjson::PyValue;
use crate::reqlog::RequestRecord;
use crate::server::Shared;
use crate::state::World;
use crate::timefmt;
use reply::Reply;
use views::Ctx;

/// nginx's page for a body over `client_max_body_size` (EvalAI runs behind nginx): the request
/// never reaches Django, so the answer is HTML, not DRF's JSON.
const TOO_LARGE_PAGE: &str =
    "<html>\r\n<head><title>413 Request Entity Too Large</title></head>\r\n\
<body>\r\n<center><h1>413 Request Entity Too Large</h1></center>\r\n<hr><center>nginx</center>\r\n\
</body>\r\n</html>\r\n";

/// A resolved `jobs` URL.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Route {
    GetSubmission(u64),
    UpdateSubmission(u64),
    UpdatePartial(u64),
    UpdateMeta(u64, u64),
    ListSubmissions(u64),
    UpdateStartedAt(u64),
}

impl Route {
    /// The methods of the route's `@api_view([...])`.
    fn allowed(self) -> &'static [Method] {
        match self {
            Route::GetSubmission(_) => &[Method::GET, Method::DELETE],
            Route::UpdateSubmission(_) | Route::UpdatePartial(_) => &[Method::PUT, Method::PATCH],
            Route::UpdateMeta(..) | Route::UpdateStartedAt(_) => &[Method::PATCH],
            Route::ListSubmissions(_) => &[Method::GET],
        }
    }

    /// DRF's view name (shown by OPTIONS).
    fn name(self) -> &'static str {
        match self {
            Route::GetSubmission(_) => "Get Submission By Pk",
            Route::UpdateSubmission(_) => "Update Submission",
            Route::UpdatePartial(_) => "Update Partially Evaluated Submission",
            Route::UpdateMeta(..) => "Update Submission Meta",
            Route::ListSubmissions(_) => "Get Submissions For Challenge",
            Route::UpdateStartedAt(_) => "Update Submission Started At",
        }
    }
}

/// Matches `path` against a Django pattern where `{n}` is `[0-9]+`.
fn match_pattern(path: &str, pattern: &str) -> Option<Vec<u64>> {
    let got: Vec<&str> = path.split('/').collect();
    let want: Vec<&str> = pattern.split('/').collect();
    if got.len() != want.len() {
        return None;
    }
    let mut ids = Vec::new();
    for (g, w) in got.iter().zip(&want) {
        if *w == "{n}" {
            if g.is_empty() || !g.bytes().all(|b| b.is_ascii_digit()) {
                return None;
            }
            // An id too large for the database matches nothing.
            ids.push(g.parse().unwrap_or(u64::MAX));
        } else if g != w {
            return None;
        }
    }
    Some(ids)
}

/// Django URL resolution for the routes the fake serves.
pub(crate) fn resolve(path: &str) -> Option<Route> {
    let rest = path.strip_prefix("/api/jobs/")?;
    let m = |p: &str| match_pattern(rest, p);
    if let Some(ids) = m("submission/{n}") {
        return Some(Route::GetSubmission(ids[0]));
    }
    if let Some(ids) = m("challenge/{n}/update_submission/") {
        return Some(Route::UpdateSubmission(ids[0]));
    }
    if let Some(ids) = m("challenges/{n}/update_partially_evaluated_submission/") {
        return Some(Route::UpdatePartial(ids[0]));
    }
    if let Some(ids) = m("challenges/{n}/submissions/{n}/update_submission_meta/") {
        return Some(Route::UpdateMeta(ids[0], ids[1]));
    }
    if let Some(ids) = m("challenge/{n}/submission/") {
        return Some(Route::ListSubmissions(ids[0]));
    }
    if let Some(ids) = m("submission/{n}/update_started_at/") {
        return Some(Route::UpdateStartedAt(ids[0]));
    }
    None
}

/// The raw request, read once.
pub(crate) struct Incoming<'a> {
    pub method: &'a Method,
    pub path: &'a str,
    pub query: Option<&'a str>,
    pub headers: &'a HeaderMap,
    pub body: &'a [u8],
    pub base_url: &'a str,
}

/// Everything after fault injection: returns the reply and the authenticated user.
pub(crate) fn process(world: &mut World, req: &Incoming<'_>) -> (Reply, Option<u64>) {
    if req.path.starts_with("/media/") {
        return (media(world, req.path), None);
    }
    let Some(route) = resolve(req.path) else {
        // APPEND_SLASH (CommonMiddleware) runs before any view, so before authentication.
        if !req.path.ends_with('/') && resolve(&format!("{}/", req.path)).is_some() {
            let mut location = format!("{}/", req.path);
            if let Some(q) = req.query {
                location.push('?');
                location.push_str(q);
            }
            return (Reply::redirect(location), None);
        }
        return (Reply::not_found_page(), None);
    };
    let (reply, user) = through_view(world, req, route);
    (with_allow(reply, route), user)
}

/// DRF's `finalize_response` sets `Allow` on every answer of an API view, errors included
/// (401, 403, 405, 429); Django's own pages (404, 500) and the redirect carry none.
fn with_allow(reply: Reply, route: Route) -> Reply {
    let has_allow = reply.headers.iter().any(|(name, _)| name == header::ALLOW);
    if matches!(reply.body, reply::ReplyBody::Html(_)) || has_allow {
        return reply;
    }
    let mut allow: Vec<String> = route.allowed().iter().map(|m| m.to_string()).collect();
    allow.push("OPTIONS".to_owned());
    reply.with_header(header::ALLOW, allow.join(", "))
}

/// Authentication, permission, throttle and method checks, then the view.
fn through_view(world: &mut World, req: &Incoming<'_>, route: Route) -> (Reply, Option<u64>) {
    let header = req.headers.get(header::AUTHORIZATION).map(|v| v.as_bytes());
    let user = match auth::authenticate(world, header) {
        Ok(user) => user,
        Err(failure) => {
            let reply = Reply::json(StatusCode::UNAUTHORIZED, failure.body())
                .with_header(header::WWW_AUTHENTICATE, WWW_AUTHENTICATE);
            return (reply, None);
        }
    };
    if !world.users.get(&user).is_some_and(|u| u.email_verified) {
        return (
            Reply::detail(StatusCode::FORBIDDEN, "Please verify your email!"),
            Some(user),
        );
    }
    if let Err(wait) = world.throttle.check(user, Instant::now()) {
        return (Reply::throttled(wait), Some(user));
    }
    if req.method == Method::OPTIONS {
        return (options(route), Some(user));
    }
    let method = if req.method == Method::HEAD && route.allowed().contains(&Method::GET) {
        &Method::GET
    } else {
        req.method
    };
    if !route.allowed().contains(method) {
        return (
            Reply::detail(
                StatusCode::METHOD_NOT_ALLOWED,
                format!("Method \"{}\" not allowed.", req.method),
            ),
            Some(user),
        );
    }
    let content_type = req
        .headers
        .get(header::CONTENT_TYPE)
        .map(|v| String::from_utf8_lossy(v.as_bytes()).into_owned());
    let mut ctx = Ctx {
        world,
        user,
        base_url: req.base_url,
        content_type: content_type.as_deref(),
        body: req.body,
        query: req.query,
    };
    let reply = match route {
        Route::GetSubmission(id) => views::get_submission(&mut ctx, method, id),
        Route::UpdateSubmission(c) => views::update_submission(&mut ctx, method, c),
        Route::UpdatePartial(c) => views::update_partial(&mut ctx, method, c),
        Route::UpdateMeta(c, s) => views::update_meta(&mut ctx, c, s),
        Route::ListSubmissions(c) => views::list_submissions(&mut ctx, c),
        Route::UpdateStartedAt(s) => views::update_started_at(&mut ctx, s),
    };
    (reply, Some(user))
}

/// DRF's `SimpleMetadata` answer to OPTIONS (`Allow` added as on every view answer).
fn options(route: Route) -> Reply {
    let strs = |items: &[&str]| PyValue::List(items.iter().map(|s| PyValue::str(*s)).collect());
    Reply::json(
        StatusCode::OK,
        PyValue::dict(vec![
            ("name", PyValue::str(route.name())),
            ("description", PyValue::str("")),
            ("renders", strs(&["application/json", "text/html"])),
            (
                "parses",
                strs(&[
                    "application/json",
                    "application/x-www-form-urlencoded",
                    "multipart/form-data",
                ]),
            ),
        ]),
    )
}

/// Files EvalAI would serve from S3: the input file, stdout, stderr, ...
fn media(world: &World, path: &str) -> Reply {
    let file = world
        .resolve_media(path)
        .and_then(|(id, name)| world.file(id, name));
    match file {
        Some((text, content_type)) => Reply {
            status: StatusCode::OK,
            body: reply::ReplyBody::Raw(text),
            headers: vec![(header::CONTENT_TYPE, content_type.to_owned())],
            error: None,
        },
        None => Reply::not_found_page(),
    }
}

fn record_body(headers: &HeaderMap, body: &[u8]) -> (Option<serde_json::Value>, Option<String>) {
    if body.is_empty() {
        return (None, None);
    }
    let ct = headers
        .get(header::CONTENT_TYPE)
        .map(|v| String::from_utf8_lossy(v.as_bytes()).into_owned());
    match body::parse(ct.as_deref(), body) {
        Ok(data) => (Some(data.value.to_json()), None),
        Err(_) => {
            let text = String::from_utf8_lossy(&body[..body.len().min(64 * 1024)]).into_owned();
            (None, Some(text))
        }
    }
}

/// The proxy's refusal of a body over `limit` bytes: still a request a test may look for.
fn too_large(
    shared: &Shared,
    parts: &axum::http::request::Parts,
    time: String,
    limit: usize,
) -> Response {
    shared.lock().log.push(RequestRecord {
        seq: 0,
        time,
        method: parts.method.to_string(),
        path: parts.uri.path().to_owned(),
        query: parts.uri.query().map(str::to_owned),
        status: StatusCode::PAYLOAD_TOO_LARGE.as_u16(),
        user_id: None,
        admin: false,
        body: None,
        raw_body: None,
        fault: None,
        error: Some(format!("body over the proxy's {limit} bytes")),
    });
    (
        StatusCode::PAYLOAD_TOO_LARGE,
        [(header::CONTENT_TYPE, "text/html")],
        TOO_LARGE_PAGE,
    )
        .into_response()
}

/// The fallback handler: every non-admin request.
pub(crate) async fn entry(State(shared): State<Arc<Shared>>, req: Request) -> Response {
    let time = timefmt::format(timefmt::now());
    let (parts, body) = req.into_parts();
    let limit = shared.lock().max_request_bytes;
    let bytes: Bytes = match axum::body::to_bytes(body, limit).await {
        Ok(b) => b,
        Err(_) => return too_large(&shared, &parts, time, limit),
    };
    let path = parts.uri.path().to_owned();
    let query = parts.uri.query().map(str::to_owned);
    let is_api = path.starts_with("/api/");
    let decision = if is_api {
        shared.lock().faults.decide()
    } else {
        Decision::default()
    };
    let mut fault = None;
    if let Some(ms) = decision.slow_ms {
        fault = Some("slow");
        tokio::time::sleep(Duration::from_millis(ms)).await;
    }
    let base_url = parts
        .headers
        .get(header::HOST)
        .and_then(|h| h.to_str().ok())
        .map_or_else(|| shared.base_url.clone(), |h| format!("http://{h}"));
    let (mut reply, user) = if let Some(wait) = decision.throttle {
        fault = Some("throttle_429");
        (Reply::throttled(wait), None)
    } else if decision.error_500 {
        fault = Some("error_500");
        (Reply::server_error("injected fault: error_500"), None)
    } else {
        let incoming = Incoming {
            method: &parts.method,
            path: &path,
            query: query.as_deref(),
            headers: &parts.headers,
            body: &bytes,
            base_url: &base_url,
        };
        let mut world = shared.lock();
        process(&mut world, &incoming)
    };
    if decision.error_500_after && fault.is_none_or(|f| f == "slow") {
        fault = Some("error_500_after");
        reply = Reply::server_error("injected fault: error_500_after (the request was applied)");
    }
    let (body_json, raw_body) = record_body(&parts.headers, &bytes);
    let record = RequestRecord {
        seq: 0,
        time,
        method: parts.method.to_string(),
        path: path.clone(),
        query: query.clone(),
        status: reply.status.as_u16(),
        user_id: user,
        admin: false,
        body: body_json,
        raw_body,
        fault: fault.map(str::to_owned),
        error: reply.error.clone(),
    };
    tracing::info!(
        method = %record.method,
        path = %record.path,
        status = record.status,
        user_id = ?record.user_id,
        fault = ?record.fault,
        error = ?record.error,
        "request"
    );
    shared.lock().log.push(record);
    reply.into_response(parts.method == Method::HEAD)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn routes_resolve_like_evalai_urls() {
        assert_eq!(
            resolve("/api/jobs/submission/12"),
            Some(Route::GetSubmission(12))
        );
        assert_eq!(resolve("/api/jobs/submission/12/"), None);
        assert_eq!(resolve("/api/jobs/submission/1a"), None);
        assert_eq!(
            resolve("/api/jobs/challenges/3/submissions/4/update_submission_meta/"),
            Some(Route::UpdateMeta(3, 4))
        );
        assert_eq!(resolve("/api/jobs/challenge/3/update_submission"), None);
        assert_eq!(
            resolve("/api/jobs/challenge/3/update_submission/"),
            Some(Route::UpdateSubmission(3))
        );
    }
}
