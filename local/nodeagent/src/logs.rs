//! The kubelet's log endpoint: the API server serves `pods/log` by asking the node's kubelet
//! for `/containerLogs/{namespace}/{pod}/{container}` over TLS; this answers it from the
//! process runner's own log API.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use axum::body::Body;
use axum::extract::{Path, RawQuery, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use rustls_pki_types::pem::PemObject;
use rustls_pki_types::{CertificateDer, PrivateKeyDer};
use tokio::net::TcpListener;
use tokio::sync::watch;
use tokio_rustls::rustls;
use tracing::debug;

use crate::Error;

/// How long a TLS handshake may take before the connection is dropped.
const HANDSHAKE_WITHIN: Duration = Duration::from_secs(10);

#[derive(Clone)]
struct Runner {
    url: Arc<str>,
    http: reqwest::Client,
}

/// Serves the log endpoint on a free loopback port until `stopped`; returns the port.
pub async fn serve(
    (cert, key): &(PathBuf, PathBuf),
    runner_url: String,
    mut stopped: watch::Receiver<bool>,
) -> Result<u16, Error> {
    let tls = tls_config(cert, key)?;
    let acceptor = tokio_rustls::TlsAcceptor::from(Arc::new(tls));
    let listener = TcpListener::bind("127.0.0.1:0")
        .await
        .map_err(|e| Error::Logs(e.to_string()))?;
    let port = listener
        .local_addr()
        .map_err(|e| Error::Logs(e.to_string()))?
        .port();
    let runner = Runner {
        url: runner_url.into(),
        http: reqwest::Client::builder()
            .connect_timeout(Duration::from_secs(5))
            .build()
            .map_err(|e| Error::Logs(e.to_string()))?,
    };
    let app = axum::Router::new()
        .route("/containerLogs/{namespace}/{pod}/{container}", get(logs))
        .with_state(runner);
    tokio::spawn(async move {
        loop {
            let accepted = tokio::select! {
                _ = stopped.wait_for(|s| *s) => return,
                accepted = listener.accept() => accepted,
            };
            let Ok((tcp, _)) = accepted else { continue };
            let (acceptor, app) = (acceptor.clone(), app.clone());
            tokio::spawn(async move {
                let handshake = tokio::time::timeout(HANDSHAKE_WITHIN, acceptor.accept(tcp));
                let Ok(Ok(tls)) = handshake.await else {
                    debug!("log endpoint: handshake failed");
                    return;
                };
                let service = hyper_util::service::TowerToHyperService::new(app);
                let io = hyper_util::rt::TokioIo::new(tls);
                let _ = hyper::server::conn::http1::Builder::new()
                    .serve_connection(io, service)
                    .await;
            });
        }
    });
    Ok(port)
}

fn tls_config(
    cert: &std::path::Path,
    key: &std::path::Path,
) -> Result<rustls::ServerConfig, Error> {
    let bad = |what: &std::path::Path, e: String| Error::Logs(format!("{}: {e}", what.display()));
    let chain = CertificateDer::pem_file_iter(cert)
        .map_err(|e| bad(cert, e.to_string()))?
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| bad(cert, e.to_string()))?;
    let key_der = PrivateKeyDer::from_pem_file(key).map_err(|e| bad(key, e.to_string()))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| Error::Logs(e.to_string()))?
        .with_no_client_auth()
        .with_single_cert(chain, key_der)
        .map_err(|e| Error::Logs(e.to_string()))
}

/// One container's log, as the process runner serves it (`tailLines`, `limitBytes`,
/// `previous`, `follow` and the rest pass through).
async fn logs(
    State(runner): State<Runner>,
    Path((namespace, pod, container)): Path<(String, String, String)>,
    RawQuery(query): RawQuery,
) -> Response {
    let mut url = format!(
        "{}/api/v1/namespaces/{namespace}/pods/{pod}/log?container={container}",
        runner.url
    );
    if let Some(q) = query.filter(|q| !q.is_empty()) {
        url.push('&');
        url.push_str(&q);
    }
    match runner.http.get(&url).send().await {
        Ok(answer) => {
            let status =
                StatusCode::from_u16(answer.status().as_u16()).unwrap_or(StatusCode::BAD_GATEWAY);
            (status, Body::from_stream(answer.bytes_stream())).into_response()
        }
        Err(e) => (StatusCode::BAD_GATEWAY, e.to_string()).into_response(),
    }
}
