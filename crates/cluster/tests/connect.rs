//! Connecting: kubeconfig files against a tiny in-process HTTP API server, and the EKS config.

use std::time::Duration;

use axum::extract::Path;
use axum::http::{HeaderMap, StatusCode};
use axum::routing::get;
use axum::{Json, Router};
use lb_cluster::{eks_config, Cluster, FailureKind, Timeouts, Verdict, VerdictPolicy};
use secrecy::ExposeSecret;
use serde_json::{json, Value};

const CA: &[u8] = include_bytes!("fixtures/eks-ca.pem");

/// Answers list calls in namespace `team-ns` to the bearer `s3cr3t` only.
async fn serve() -> (String, tokio::task::JoinHandle<()>) {
    async fn list(
        Path((ns, kind)): Path<(String, String)>,
        headers: HeaderMap,
    ) -> (StatusCode, Json<Value>) {
        let auth = headers.get("authorization").and_then(|v| v.to_str().ok());
        if auth != Some("Bearer s3cr3t") {
            let s = json!({"kind": "Status", "apiVersion": "v1", "status": "Failure", "message": "Unauthorized", "reason": "Unauthorized", "code": 401});
            return (StatusCode::UNAUTHORIZED, Json(s));
        }
        if ns != "team-ns" {
            let s = json!({"kind": "Status", "apiVersion": "v1", "status": "Failure", "message": format!("namespaces \"{ns}\" not found"), "reason": "NotFound", "code": 404});
            return (StatusCode::NOT_FOUND, Json(s));
        }
        let list_kind = if kind == "jobs" { "JobList" } else { "PodList" };
        (
            StatusCode::OK,
            Json(
                json!({"kind": list_kind, "apiVersion": "v1", "metadata": {"resourceVersion": "1"}, "items": []}),
            ),
        )
    }
    let app = Router::new()
        .route("/apis/batch/v1/namespaces/{ns}/{kind}", get(list))
        .route("/api/v1/namespaces/{ns}/{kind}", get(list));
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let task = tokio::spawn(async move {
        axum::serve(listener, app).await.unwrap();
    });
    (url, task)
}

fn kubeconfig(dir: &tempfile::TempDir, server: &str) -> std::path::PathBuf {
    let text = format!(
        r#"apiVersion: v1
kind: Config
clusters:
- name: local
  cluster:
    server: {server}
users:
- name: wrong
  user:
    token: nope
- name: right
  user:
    token: s3cr3t
contexts:
- name: first
  context: {{cluster: local, user: wrong, namespace: other-ns}}
- name: team
  context: {{cluster: local, user: right, namespace: team-ns}}
current-context: first
"#
    );
    let path = dir.path().join("kubeconfig");
    std::fs::write(&path, text).unwrap();
    path
}

#[tokio::test]
async fn a_kubeconfig_context_gives_the_server_the_token_and_the_namespace() {
    let (url, server) = serve().await;
    let dir = tempfile::tempdir().unwrap();
    let path = kubeconfig(&dir, &url);
    let cluster = Cluster::from_kubeconfig(&path, Some("team")).await.unwrap();
    assert_eq!(cluster.namespace(), "team-ns");
    let obs = tokio::time::timeout(Duration::from_secs(5), cluster.observe("4242"))
        .await
        .unwrap()
        .unwrap();
    assert!(obs.jobs.is_empty());
    assert!(matches!(
        obs.verdict(&VerdictPolicy::default()),
        Verdict::Failed {
            kind: FailureKind::JobsMissing,
            ..
        }
    ));

    // The current context has the wrong token.
    let current = Cluster::from_kubeconfig(&path, None).await.unwrap();
    assert_eq!(current.namespace(), "other-ns");
    let err = current.observe("4242").await.unwrap_err();
    assert_eq!(err.name(), "KubeUnauthorized");
    // The right token in a namespace that does not exist.
    let elsewhere = cluster.clone().with_namespace("gone");
    assert_eq!(
        elsewhere.observe("4242").await.unwrap_err().name(),
        "KubeRequestFailed"
    );
    server.abort();
}

#[tokio::test]
async fn a_missing_kubeconfig_or_context_is_a_config_error_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nope");
    let err = Cluster::from_kubeconfig(&missing, None).await.unwrap_err();
    assert_eq!(err.name(), "KubeConfigInvalid");
    assert!(err.to_string().contains("nope"), "{err}");

    let path = kubeconfig(&dir, "http://127.0.0.1:9");
    let err = Cluster::from_kubeconfig(&path, Some("staging"))
        .await
        .unwrap_err();
    assert_eq!(err.name(), "KubeConfigInvalid");
    assert!(err.to_string().contains("context `staging`"), "{err}");

    std::fs::write(&path, "clusters: [").unwrap();
    let err = Cluster::from_kubeconfig(&path, None).await.unwrap_err();
    assert_eq!(err.name(), "KubeConfigInvalid");
}

#[tokio::test]
async fn a_closed_port_is_unavailable_and_transient() {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    drop(listener);
    let dir = tempfile::tempdir().unwrap();
    let path = kubeconfig(&dir, &url);
    let timeouts = Timeouts {
        connect: Duration::from_secs(1),
        read: Duration::from_secs(1),
        call: Duration::from_secs(3),
    };
    let cluster = Cluster::from_kubeconfig_with(&path, Some("team"), timeouts)
        .await
        .unwrap();
    let err = tokio::time::timeout(Duration::from_secs(10), cluster.observe("4242"))
        .await
        .unwrap()
        .unwrap_err();
    assert!(
        matches!(err.name(), "KubeUnavailable" | "KubeTimeout"),
        "{}: {err}",
        err.name()
    );
    assert!(err.is_transient());
}

#[tokio::test]
async fn a_server_that_accepts_but_never_answers_is_bounded_by_the_read_timeout() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let silent = tokio::spawn(async move {
        let mut held = Vec::new();
        while let Ok((sock, _)) = listener.accept().await {
            held.push(sock);
        }
    });
    let dir = tempfile::tempdir().unwrap();
    let path = kubeconfig(&dir, &url);
    let timeouts = Timeouts {
        connect: Duration::from_secs(1),
        read: Duration::from_millis(300),
        call: Duration::from_secs(10),
    };
    let cluster = Cluster::from_kubeconfig_with(&path, Some("team"), timeouts)
        .await
        .unwrap();
    let started = std::time::Instant::now();
    let err = tokio::time::timeout(Duration::from_secs(10), cluster.observe("4242"))
        .await
        .unwrap()
        .unwrap_err();
    assert_eq!(err.name(), "KubeUnavailable", "{err}");
    assert!(started.elapsed() < Duration::from_secs(5));
    silent.abort();
}

#[test]
fn the_eks_config_trusts_only_the_cluster_ca_and_carries_the_token() {
    let timeouts = Timeouts::default();
    let config = eks_config(
        "https://abcdef.gr7.us-west-2.eks.amazonaws.com",
        CA,
        "k8s-aws-v1.aHR0cHM6Ly9zdHM",
        &timeouts,
    )
    .unwrap();
    assert_eq!(
        config.cluster_url.host(),
        Some("abcdef.gr7.us-west-2.eks.amazonaws.com")
    );
    let roots = config.root_cert.as_ref().unwrap();
    assert_eq!(roots.len(), 1);
    assert_eq!(roots[0].first(), Some(&0x30), "DER, not PEM");
    assert_eq!(
        config.auth_info.token.as_ref().unwrap().expose_secret(),
        "k8s-aws-v1.aHR0cHM6Ly9zdHM"
    );
    assert_eq!(config.connect_timeout, Some(timeouts.connect));
    assert_eq!(config.read_timeout, Some(timeouts.read));
    assert!(!config.accept_invalid_certs);
    assert!(
        !format!("{config:?}").contains("aHR0cHM6Ly9zdHM"),
        "the token never shows in Debug"
    );
}

#[test]
fn a_bad_eks_endpoint_ca_or_token_is_refused_by_name() {
    let t = Timeouts::default();
    let ok = "https://x.eks.amazonaws.com";
    for (endpoint, ca, token, needle) in [
        ("http://x.eks.amazonaws.com", CA, "tok", "not an https URL"),
        ("not a url at all", CA, "tok", "not"),
        (ok, &b"garbage"[..], "tok", "no certificate"),
        (
            ok,
            &b"-----BEGIN CERTIFICATE-----\n!!!\n-----END CERTIFICATE-----\n"[..],
            "tok",
            "CA",
        ),
        (ok, CA, "", "token"),
        (ok, CA, "two words", "token"),
    ] {
        let err = eks_config(endpoint, ca, token, &t).unwrap_err();
        assert_eq!(err.name(), "KubeConfigInvalid");
        assert!(err.to_string().contains(needle), "{endpoint}: {err}");
        assert!(!err.to_string().contains("two words"));
    }
}

#[test]
fn building_an_eks_client_outside_a_runtime_is_an_error_not_a_panic() {
    let err = Cluster::for_eks("https://x.eks.amazonaws.com", CA, "tok").unwrap_err();
    assert_eq!(err.name(), "KubeConfigInvalid");
    assert!(err.to_string().contains("Tokio runtime"));
}

#[tokio::test]
async fn an_eks_cluster_is_built_without_showing_its_token() {
    let cluster = Cluster::for_eks("https://x.eks.amazonaws.com", CA, "very-secret-token")
        .unwrap()
        .with_namespace("leaderboard");
    assert_eq!(cluster.namespace(), "leaderboard");
    assert!(!format!("{cluster:?}").contains("very-secret-token"));
}
