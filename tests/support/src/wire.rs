//! A recording HTTP proxy for benchmarks: what a process asked of each service, when, and
//! how many of its requests ran one after another.

use std::sync::{Arc, Mutex};
use std::time::Instant;

use axum::body::{to_bytes, Body};
use axum::extract::{Request, State};
use axum::http::{HeaderName, StatusCode};
use axum::response::Response;
use axum::Router;

/// Requests larger than this are refused by the proxy (a benchmark's requests are small).
const MAX_BODY: usize = 64 << 20;

/// One request as the proxy saw it.
#[derive(Debug, Clone)]
pub struct Exchange {
    /// The service's name, as the tap was told.
    pub service: &'static str,
    /// What was asked: method and path (and the operation, for AWS' JSON protocols).
    pub what: String,
    /// When its head arrived.
    pub started: Instant,
    /// When its answer was ready to go back.
    pub ended: Instant,
}

/// The requests of every proxy started from it, in the order they ended.
#[derive(Debug, Clone, Default)]
pub struct Wiretap {
    log: Arc<Mutex<Vec<Exchange>>>,
}

#[derive(Clone)]
struct Hop {
    service: &'static str,
    upstream: String,
    client: reqwest::Client,
    log: Arc<Mutex<Vec<Exchange>>>,
}

impl Wiretap {
    /// Serves a proxy to `upstream` (`http://host:port`) on a loopback port and returns its
    /// URL; each request through it is recorded as `service`'s.
    pub async fn proxy(&self, service: &'static str, upstream: &str) -> std::io::Result<String> {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let url = format!("http://{}", listener.local_addr()?);
        let hop = Hop {
            service,
            upstream: upstream.trim_end_matches('/').to_string(),
            client: reqwest::Client::new(),
            log: self.log.clone(),
        };
        let app = Router::new().fallback(forward).with_state(hop);
        tokio::spawn(async move { axum::serve(listener, app).await });
        Ok(url)
    }

    /// The requests recorded since the last take.
    pub fn take(&self) -> Vec<Exchange> {
        std::mem::take(&mut *self.log.lock().unwrap())
    }
}

/// Passes one request on and its answer back, buffered (no request a benchmark makes streams).
async fn forward(State(hop): State<Hop>, request: Request) -> Result<Response, StatusCode> {
    let started = Instant::now();
    let (parts, body) = request.into_parts();
    let target = parts.uri.path_and_query().map_or("/", |p| p.as_str());
    let operation = parts
        .headers
        .get("x-amz-target")
        .and_then(|v| v.to_str().ok());
    let what = match operation {
        Some(op) => format!("{} {target} {op}", parts.method),
        None => format!("{} {target}", parts.method),
    };
    let body = to_bytes(body, MAX_BODY)
        .await
        .map_err(|_| StatusCode::PAYLOAD_TOO_LARGE)?;
    let mut out = hop
        .client
        .request(parts.method, format!("{}{target}", hop.upstream))
        .body(body);
    for (name, value) in parts.headers.iter().filter(|(n, _)| passes(n)) {
        out = out.header(name, value);
    }
    let answer = out.send().await.map_err(|_| StatusCode::BAD_GATEWAY)?;
    let mut response = Response::builder().status(answer.status());
    for (name, value) in answer.headers().iter().filter(|(n, _)| passes(n)) {
        response = response.header(name, value);
    }
    let bytes = answer.bytes().await.map_err(|_| StatusCode::BAD_GATEWAY)?;
    hop.log.lock().unwrap().push(Exchange {
        service: hop.service,
        what,
        started,
        ended: Instant::now(),
    });
    response
        .body(Body::from(bytes))
        .map_err(|_| StatusCode::BAD_GATEWAY)
}

/// Headers of one hop only (the proxy frames each side itself).
fn passes(name: &HeaderName) -> bool {
    !matches!(
        name.as_str(),
        "host" | "connection" | "content-length" | "transfer-encoding" | "keep-alive"
    )
}

/// The longest run of `exchanges` each of which began after the one before it ended: how
/// many requests the process made one after another, whatever it made beside them.
pub fn in_sequence(exchanges: &[Exchange]) -> Vec<&Exchange> {
    // Earliest end first: the greedy choice keeps the most non-overlapping requests, and
    // requests that do not overlap are a sequence.
    let mut by_end: Vec<&Exchange> = exchanges.iter().collect();
    by_end.sort_by_key(|e| e.ended);
    let mut chain: Vec<&Exchange> = Vec::new();
    for exchange in by_end {
        if chain
            .last()
            .is_none_or(|last| exchange.started >= last.ended)
        {
            chain.push(exchange);
        }
    }
    chain
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;

    fn at(base: Instant, from_ms: u64, to_ms: u64) -> Exchange {
        Exchange {
            service: "s",
            what: format!("{from_ms}-{to_ms}"),
            started: base + Duration::from_millis(from_ms),
            ended: base + Duration::from_millis(to_ms),
        }
    }

    fn names(chain: Vec<&Exchange>) -> Vec<&str> {
        chain.into_iter().map(|e| e.what.as_str()).collect()
    }

    #[test]
    fn requests_side_by_side_count_once_and_one_after_another_each() {
        let t = Instant::now();
        let side_by_side = [at(t, 0, 10), at(t, 1, 12), at(t, 2, 9)];
        assert_eq!(in_sequence(&side_by_side).len(), 1);
        let one_after_another = [at(t, 20, 30), at(t, 0, 10), at(t, 10, 20)];
        assert_eq!(
            names(in_sequence(&one_after_another)),
            ["0-10", "10-20", "20-30"]
        );
        assert!(in_sequence(&[]).is_empty());
    }

    #[test]
    fn a_long_request_beside_a_chain_does_not_hide_it() {
        let t = Instant::now();
        let exchanges = [at(t, 0, 100), at(t, 0, 10), at(t, 11, 20), at(t, 21, 30)];
        assert_eq!(names(in_sequence(&exchanges)), ["0-10", "11-20", "21-30"]);
    }

    #[tokio::test]
    async fn a_proxied_request_reaches_the_service_and_is_recorded() {
        let service = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let upstream = format!("http://{}", service.local_addr().unwrap());
        let app = Router::new().fallback(|request: Request| async move {
            let target = request.uri().to_string();
            let op = request.headers().get("x-amz-target").cloned();
            let body = to_bytes(request.into_body(), 1024).await.unwrap();
            let op = op
                .map(|v| v.to_str().unwrap().to_string())
                .unwrap_or_default();
            format!("{target} {op} {}", String::from_utf8_lossy(&body))
        });
        tokio::spawn(async move { axum::serve(service, app).await });
        let tap = Wiretap::default();
        let url = tap.proxy("dynamodb", &upstream).await.unwrap();
        let answer = reqwest::Client::new()
            .post(format!("{url}/a?b=1"))
            .header("x-amz-target", "DynamoDB_20120810.GetItem")
            .body("{}")
            .send()
            .await
            .unwrap();
        assert_eq!(answer.status(), 200);
        assert_eq!(
            answer.text().await.unwrap(),
            "/a?b=1 DynamoDB_20120810.GetItem {}"
        );
        let recorded = tap.take();
        assert_eq!(recorded.len(), 1);
        assert_eq!(recorded[0].service, "dynamodb");
        assert_eq!(recorded[0].what, "POST /a?b=1 DynamoDB_20120810.GetItem");
        assert!(tap.take().is_empty(), "a take empties the log");
    }
}
