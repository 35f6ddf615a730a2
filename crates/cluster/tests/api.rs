//! The client paths against a mock API server (the client's transport is a channel to an
//! `ApiServerVerifier` that asserts method, path, query and body of every request).

use std::collections::BTreeMap;
use std::future::Future;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;

use http::{Method, Request, Response, StatusCode};
use kube::client::Body;
use lb_cluster::{
    Cluster, ClusterError, FailureKind, Job, Timeouts, Verdict, VerdictPolicy, Whose,
};
use serde_json::{json, Value};

/// A request the client sent, with where its answer goes.
type Exchange = (Request<Body>, tokio::sync::oneshot::Sender<Response<Body>>);

/// The client's transport: each request goes to the test's [`Handle`], which answers it.
#[derive(Clone)]
struct Transport(tokio::sync::mpsc::UnboundedSender<Exchange>);

impl tower::Service<Request<Body>> for Transport {
    type Response = Response<Body>;
    type Error = Box<dyn std::error::Error + Send + Sync>;
    type Future = Pin<Box<dyn Future<Output = Result<Response<Body>, Self::Error>> + Send>>;

    fn poll_ready(&mut self, _: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        Poll::Ready(Ok(()))
    }

    fn call(&mut self, request: Request<Body>) -> Self::Future {
        let (answer, answered) = tokio::sync::oneshot::channel();
        let sent = self.0.send((request, answer));
        Box::pin(async move {
            sent.map_err(|_| "the test stopped listening")?;
            Ok(answered.await.map_err(|_| "the test dropped the request")?)
        })
    }
}

/// The test's end of the transport.
struct Handle(tokio::sync::mpsc::UnboundedReceiver<Exchange>);

impl Handle {
    async fn next_request(&mut self) -> Option<(Request<Body>, Responder)> {
        let (request, answer) = self.0.recv().await?;
        Some((request, Responder(answer)))
    }
}

/// Where one request's answer goes.
struct Responder(tokio::sync::oneshot::Sender<Response<Body>>);

impl Responder {
    fn send_response(self, response: Response<Body>) {
        // The client may have given up waiting (a timeout under test): nothing to answer.
        let _ = self.0.send(response);
    }
}

const NS: &str = "leaderboard";
const JOBS: &str = "/apis/batch/v1/namespaces/leaderboard/jobs";
const PODS: &str = "/api/v1/namespaces/leaderboard/pods";
const SELECTOR: &str =
    "leaderboard.carla.org/submission-id=4242,app.kubernetes.io/managed-by=leaderboard-cloud";

fn fixture(text: &str) -> (Vec<Value>, Vec<Value>) {
    let list: Value = serde_yaml::from_str(text).unwrap();
    let items = list["items"].as_array().unwrap().clone();
    let (jobs, pods) = items.into_iter().partition(|i| i["kind"] == "Job");
    (jobs, pods)
}

/// The Job of `running.yaml` as a template renders it: no server-set fields.
fn job_to_launch() -> Job {
    let (jobs, _) = fixture(include_str!("fixtures/running.yaml"));
    let mut job: Job = serde_json::from_value(jobs[0].clone()).unwrap();
    job.status = None;
    let m = &mut job.metadata;
    (
        m.uid,
        m.resource_version,
        m.creation_timestamp,
        m.managed_fields,
        m.generation,
    ) = (None, None, None, None, None);
    job
}

fn job_list(jobs: Vec<Value>) -> Value {
    json!({"apiVersion": "batch/v1", "kind": "JobList", "metadata": {"resourceVersion": "100999"}, "items": jobs})
}

fn pod_list(pods: Vec<Value>) -> Value {
    json!({"apiVersion": "v1", "kind": "PodList", "metadata": {"resourceVersion": "100999"}, "items": pods})
}

fn status(code: u16, reason: &str, message: &str, details: Value) -> Value {
    json!({
        "kind": "Status", "apiVersion": "v1", "metadata": {}, "status": "Failure",
        "message": message, "reason": reason, "details": details, "code": code
    })
}

fn mock() -> (Cluster, ApiServerVerifier) {
    let (requests, handle) = tokio::sync::mpsc::unbounded_channel();
    let cluster = Cluster::new(kube::Client::new(Transport(requests), NS), NS);
    (cluster, ApiServerVerifier(Handle(handle)))
}

fn decode(s: &str) -> String {
    let bytes = s.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        match bytes[i] {
            b'+' => out.push(b' '),
            b'%' if i + 2 < bytes.len() => {
                out.push(u8::from_str_radix(&s[i + 1..i + 3], 16).unwrap());
                i += 2;
            }
            b => out.push(b),
        }
        i += 1;
    }
    String::from_utf8(out).unwrap()
}

fn query_of(req: &Request<Body>) -> BTreeMap<String, String> {
    req.uri()
        .query()
        .unwrap_or("")
        .split('&')
        .filter(|kv| !kv.is_empty())
        .map(|kv| {
            let (k, v) = kv.split_once('=').unwrap_or((kv, ""));
            (decode(k), decode(v))
        })
        .collect()
}

/// One expected request: method, path, query pairs; its body is returned for checks.
struct Expect<'a> {
    method: Method,
    path: &'a str,
    query: &'a [(&'a str, &'a str)],
}

struct ApiServerVerifier(Handle);

impl ApiServerVerifier {
    /// Takes the next request, asserts it, answers `code` with `answer`; returns its body.
    async fn answer(&mut self, expect: Expect<'_>, code: u16, answer: Value) -> Value {
        let (req, send) = self.0.next_request().await.expect("a request");
        assert_eq!(req.method(), expect.method, "{}", req.uri());
        assert_eq!(req.uri().path(), expect.path);
        let want: BTreeMap<String, String> = expect
            .query
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        assert_eq!(query_of(&req), want, "{}", req.uri());
        let body = req.into_body().collect_bytes().await.unwrap();
        let body = if body.is_empty() {
            Value::Null
        } else {
            serde_json::from_slice(&body).expect("a JSON body")
        };
        send.send_response(
            Response::builder()
                .status(StatusCode::from_u16(code).unwrap())
                .header("content-type", "application/json")
                .body(Body::from(serde_json::to_vec(&answer).unwrap()))
                .unwrap(),
        );
        body
    }

    async fn create(&mut self, code: u16, answer: Value) -> Value {
        let e = Expect {
            method: Method::POST,
            path: JOBS,
            query: &[],
        };
        self.answer(e, code, answer).await
    }

    async fn get_job(&mut self, name: &str, code: u16, answer: Value) {
        let path = format!("{JOBS}/{name}");
        let e = Expect {
            method: Method::GET,
            path: &path,
            query: &[],
        };
        self.answer(e, code, answer).await;
    }

    async fn list(&mut self, path: &str, answer: Value) {
        let e = Expect {
            method: Method::GET,
            path,
            query: &[("labelSelector", SELECTOR)],
        };
        self.answer(e, 200, answer).await;
    }

    /// The Monitor's read of one pod's events (the autoscaler's word on it).
    async fn pod_events(&mut self, uid: &str, code: u16, answer: Value) {
        let selector = format!("involvedObject.uid={uid}");
        let e = Expect {
            method: Method::GET,
            path: "/api/v1/namespaces/leaderboard/events",
            query: &[("fieldSelector", &selector)],
        };
        self.answer(e, code, answer).await;
    }

    async fn delete(&mut self, path: &str, code: u16, answer: Value) -> Value {
        let e = Expect {
            method: Method::DELETE,
            path,
            query: &[],
        };
        self.answer(e, code, answer).await
    }

    /// Asserts that no request arrives for a moment.
    async fn assert_silent(&mut self) {
        let next = tokio::time::timeout(Duration::from_millis(100), self.0.next_request()).await;
        assert!(next.is_err(), "unexpected request");
    }
}

/// Runs the client call and the verifier together, the verifier bounded to one second.
async fn with_server<T, F>(client: impl std::future::Future<Output = T>, server: F) -> T
where
    F: std::future::Future<Output = ()> + Send + 'static,
{
    let server = tokio::spawn(async move {
        tokio::time::timeout(Duration::from_secs(1), server)
            .await
            .expect("the scenario finished within a second")
    });
    let out = tokio::time::timeout(Duration::from_secs(2), client)
        .await
        .expect("the client returned");
    server.await.expect("the verifier did not panic");
    out
}

#[tokio::test]
async fn create_posts_the_job_once_and_reports_it_created() {
    let (cluster, mut server) = mock();
    let job = job_to_launch();
    let sent = job.clone();
    let launched = with_server(cluster.create_or_adopt(&job), async move {
        let mut made = serde_json::to_value(&sent).unwrap();
        made["metadata"]["uid"] = json!("u-1");
        let body = server.create(201, made).await;
        let body: Job = serde_json::from_value(body).unwrap();
        assert_eq!(body, sent, "the Job is sent unchanged");
        server.assert_silent().await;
    })
    .await
    .unwrap();
    assert_eq!(launched.name, "lb-4242-team-77-0");
    assert_eq!(launched.submission_id, "4242");
    assert_eq!(launched.uid.as_deref(), Some("u-1"));
    assert!(!launched.adopted);
}

#[tokio::test]
async fn an_existing_job_of_the_same_submission_is_adopted_not_duplicated() {
    let (cluster, mut server) = mock();
    let job = job_to_launch();
    let (jobs, _) = fixture(include_str!("fixtures/running.yaml"));
    let launched = with_server(cluster.create_or_adopt(&job), async move {
        let exists = status(
            409,
            "AlreadyExists",
            "jobs.batch \"lb-4242-team-77-0\" already exists",
            json!({"name": "lb-4242-team-77-0", "group": "batch", "kind": "jobs"}),
        );
        server.create(409, exists).await;
        server
            .get_job("lb-4242-team-77-0", 200, jobs[0].clone())
            .await;
        server.assert_silent().await;
    })
    .await
    .unwrap();
    assert!(launched.adopted);
    assert!(!launched.already_ended);
    assert_eq!(
        launched.uid.as_deref(),
        Some("c2d35609-03b6-f241-e979-de8acaad8767")
    );
}

#[tokio::test]
async fn an_adopted_job_that_already_ended_says_so() {
    let (cluster, mut server) = mock();
    let job = job_to_launch();
    let (jobs, _) = fixture(include_str!("fixtures/backoff-limit.yaml"));
    let launched = with_server(cluster.create_or_adopt(&job), async move {
        server
            .create(409, status(409, "AlreadyExists", "exists", json!({})))
            .await;
        server
            .get_job("lb-4242-team-77-0", 200, jobs[0].clone())
            .await;
    })
    .await
    .unwrap();
    assert!(launched.adopted && launched.already_ended);
}

#[tokio::test]
async fn a_same_named_job_of_another_submission_is_refused_by_name() {
    let (cluster, mut server) = mock();
    let job = job_to_launch();
    let (jobs, _) = fixture(include_str!("fixtures/running.yaml"));
    let err = with_server(cluster.create_or_adopt(&job), async move {
        let exists = status(409, "AlreadyExists", "already exists", json!({}));
        server.create(409, exists).await;
        let mut other = jobs[0].clone();
        other["metadata"]["labels"]["leaderboard.carla.org/submission-id"] = json!("999");
        server.get_job("lb-4242-team-77-0", 200, other).await;
    })
    .await
    .unwrap_err();
    assert_eq!(err.name(), "JobNameTaken");
    assert!(!err.is_transient());
    let text = err.to_string();
    assert!(
        text.contains("`lb-4242-team-77-0`") && text.contains("`999`") && text.contains("`4242`"),
        "{text}"
    );
}

#[tokio::test]
async fn a_same_named_job_still_being_deleted_is_a_transient_wait() {
    let (cluster, mut server) = mock();
    let job = job_to_launch();
    let (jobs, _) = fixture(include_str!("fixtures/job-terminating.yaml"));
    let err = with_server(cluster.create_or_adopt(&job), async move {
        server
            .create(409, status(409, "AlreadyExists", "exists", json!({})))
            .await;
        server
            .get_job("lb-4242-team-77-0", 200, jobs[0].clone())
            .await;
    })
    .await
    .unwrap_err();
    assert_eq!(err.name(), "JobTerminating");
    assert!(err.is_transient());
}

#[tokio::test]
async fn a_job_refused_as_invalid_names_the_cause() {
    let (cluster, mut server) = mock();
    let job = job_to_launch();
    let err = with_server(cluster.create_or_adopt(&job), async move {
        let invalid = status(
            422,
            "Invalid",
            "Job.batch \"lb-4242-team-77-0\" is invalid: spec.template.spec.containers[1].image: Required value",
            json!({"name": "lb-4242-team-77-0", "group": "batch", "kind": "Job", "causes": [
                {"reason": "FieldValueRequired", "message": "Required value", "field": "spec.template.spec.containers[1].image"}
            ]}),
        );
        server.create(422, invalid).await;
        server.assert_silent().await;
    })
    .await
    .unwrap_err();
    assert_eq!(err.name(), "KubeInvalid");
    assert!(!err.is_transient());
    assert!(
        err.to_string()
            .contains("spec.template.spec.containers[1].image: Required value"),
        "{err}"
    );
}

#[tokio::test]
async fn a_forbidden_create_is_a_permissions_error() {
    let (cluster, mut server) = mock();
    let job = job_to_launch();
    let err = with_server(cluster.create_or_adopt(&job), async move {
        let forbidden = status(
            403,
            "Forbidden",
            "jobs.batch is forbidden: User \"arn:aws:sts::342236305043:assumed-role/launch/x\" cannot create resource \"jobs\" in API group \"batch\" in the namespace \"leaderboard\"",
            json!({"group": "batch", "kind": "jobs"}),
        );
        server.create(403, forbidden).await;
    })
    .await
    .unwrap_err();
    assert_eq!(err.name(), "KubeForbidden");
    assert!(!err.is_transient());
    assert!(err.to_string().contains("cannot create resource"), "{err}");
    assert!(matches!(
        err,
        ClusterError::Forbidden {
            operation: "create job",
            ..
        }
    ));
}

#[tokio::test]
async fn server_errors_and_throttling_are_transient() {
    for (code, reason) in [
        (500, "InternalError"),
        (503, "ServiceUnavailable"),
        (429, "TooManyRequests"),
    ] {
        let (cluster, mut server) = mock();
        let job = job_to_launch();
        let err = with_server(cluster.create_or_adopt(&job), async move {
            server
                .create(code, status(code, reason, "try later", json!({})))
                .await;
        })
        .await
        .unwrap_err();
        assert_eq!(err.name(), "KubeTransient", "{code}");
        assert!(err.is_transient());
    }
}

#[tokio::test]
async fn a_job_the_adapter_could_not_track_is_refused_before_any_request() {
    let (cluster, mut server) = mock();
    let mut unlabelled_pods = job_to_launch();
    let template = unlabelled_pods
        .spec
        .as_mut()
        .unwrap()
        .template
        .metadata
        .as_mut()
        .unwrap();
    template
        .labels
        .as_mut()
        .unwrap()
        .remove("app.kubernetes.io/managed-by");
    let mut other_ns = job_to_launch();
    other_ns.metadata.namespace = Some("default".into());
    let mut unnamed = job_to_launch();
    unnamed.metadata.name = None;
    let mut bad_id = job_to_launch();
    for labels in [
        bad_id.metadata.labels.as_mut().unwrap(),
        bad_id
            .spec
            .as_mut()
            .unwrap()
            .template
            .metadata
            .as_mut()
            .unwrap()
            .labels
            .as_mut()
            .unwrap(),
    ] {
        labels.insert("leaderboard.carla.org/submission-id".into(), "1,x=y".into());
    }
    for (job, name, needle) in [
        (
            &unlabelled_pods,
            "InvalidJobSpec",
            "its pod template lacks `app.kubernetes.io/managed-by=leaderboard-cloud`",
        ),
        (&other_ns, "InvalidJobSpec", "namespace `default`"),
        (&unnamed, "InvalidJobSpec", "no `metadata.name`"),
        (&bad_id, "InvalidSubmissionId", "1,x=y"),
    ] {
        let err = cluster.create_or_adopt(job).await.unwrap_err();
        assert_eq!(err.name(), name);
        assert!(err.to_string().contains(needle), "{err}");
    }
    server.assert_silent().await;
}

#[tokio::test]
async fn observe_lists_jobs_and_pods_by_label_and_maps_them_to_a_verdict() {
    let (cluster, mut server) = mock();
    let (jobs, pods) = fixture(include_str!("fixtures/image-pull-backoff.yaml"));
    let obs = with_server(cluster.observe("4242"), async move {
        server.list(JOBS, job_list(jobs)).await;
        server.list(PODS, pod_list(pods)).await;
    })
    .await
    .unwrap();
    assert_eq!(obs.submission_id, "4242");
    assert_eq!(obs.jobs.len(), 1);
    assert_eq!(obs.jobs[0].pods.len(), 1);
    match &obs.verdict(&VerdictPolicy::default()) {
        Verdict::Failed {
            kind, container, ..
        } => {
            assert_eq!(*kind, FailureKind::ParticipantImagePull);
            assert_eq!(container.as_deref(), Some("agent-1"));
        }
        other => panic!("{other:?}"),
    }
}

/// The pending pod of unschedulable.yaml, whose events the Monitor asks for.
const PENDING_POD_UID: &str = "8e61dbe7-90cf-4dec-4891-83cfd21a9a89";

#[tokio::test]
async fn a_pod_waiting_past_the_grace_is_looked_up_in_the_autoscalers_events() {
    let (cluster, mut server) = mock();
    let (jobs, pods) = fixture(include_str!("fixtures/unschedulable.yaml"));
    let events: Value =
        serde_yaml::from_str(include_str!("fixtures/autoscaler-events.yaml")).unwrap();
    // The listing alone reads no events: the Monitor's round asks when it needs the word.
    let mut obs = with_server(cluster.observe("4242"), async move {
        server.list(JOBS, job_list(jobs)).await;
        server.list(PODS, pod_list(pods)).await;
        server.assert_silent().await;
    })
    .await
    .unwrap();
    let policy = VerdictPolicy::default();
    assert_eq!(obs.needs_autoscaler_word(&policy), Some(PENDING_POD_UID));
    let (cluster, mut server) = mock();
    let word = with_server(cluster.autoscaler_word(PENDING_POD_UID), async move {
        server.pod_events(PENDING_POD_UID, 200, events).await;
    })
    .await
    .expect("the autoscaler's word");
    obs.hear_autoscaler(PENDING_POD_UID, word);
    assert_eq!(obs.needs_autoscaler_word(&policy), None);
    match &obs.verdict(&policy) {
        Verdict::Failed { kind, message, .. } => {
            assert_eq!(*kind, FailureKind::NoNodeFits);
            assert!(
                message.contains("(`node.kubernetes.io/instance-type=g5.12xlarge`)"),
                "{message}"
            );
        }
        other => panic!("{other:?}"),
    }
}

#[tokio::test]
async fn events_the_role_may_not_list_leave_the_pod_to_the_schedulers_limits() {
    let (cluster, mut server) = mock();
    let word = with_server(cluster.autoscaler_word(PENDING_POD_UID), async move {
        let forbidden = status(
            403,
            "Forbidden",
            "events is forbidden: User \"leaderboard-pipeline\" cannot list resource \"events\" in API group \"\" in the namespace \"leaderboard\"",
            json!({"kind": "events"}),
        );
        server.pod_events(PENDING_POD_UID, 403, forbidden).await;
    })
    .await;
    assert_eq!(word, None);
    let (cluster, mut server) = mock();
    let (jobs, pods) = fixture(include_str!("fixtures/unschedulable.yaml"));
    let obs = with_server(cluster.observe("4242"), async move {
        server.list(JOBS, job_list(jobs)).await;
        server.list(PODS, pod_list(pods)).await;
    })
    .await
    .unwrap();
    // Waiting since 2025 for GPUs: the queue limit (not the autoscaler) ended it.
    match &obs.verdict(&VerdictPolicy::default()) {
        Verdict::Failed { kind, .. } => assert_eq!(*kind, FailureKind::Unschedulable),
        other => panic!("{other:?}"),
    }
}

#[tokio::test]
async fn observe_of_a_finished_submission_is_finished() {
    let (cluster, mut server) = mock();
    let (jobs, pods) = fixture(include_str!("fixtures/finished-two-jobs.yaml"));
    let obs = with_server(cluster.observe("4242"), async move {
        server.list(JOBS, job_list(jobs)).await;
        server.list(PODS, pod_list(pods)).await;
    })
    .await
    .unwrap();
    assert_eq!(
        obs.judge(2, &Default::default(), &VerdictPolicy::default()),
        Verdict::Finished
    );
}

#[tokio::test]
async fn an_expired_token_is_unauthorized() {
    let (cluster, mut server) = mock();
    let err = with_server(cluster.observe("4242"), async move {
        let e = Expect {
            method: Method::GET,
            path: JOBS,
            query: &[("labelSelector", SELECTOR)],
        };
        server
            .answer(
                e,
                401,
                status(401, "Unauthorized", "Unauthorized", json!({})),
            )
            .await;
    })
    .await
    .unwrap_err();
    assert_eq!(err.name(), "KubeUnauthorized");
}

#[tokio::test]
async fn delete_all_deletes_every_job_in_the_foreground() {
    let (cluster, mut server) = mock();
    let (jobs, pods) = fixture(include_str!("fixtures/finished-two-jobs.yaml"));
    let deleted = with_server(cluster.delete_all("4242", Whose::Any), async move {
        let names: Vec<String> = jobs
            .iter()
            .map(|j| j["metadata"]["name"].as_str().unwrap().to_string())
            .collect();
        // Both lists side by side, then every deletion side by side (each arrives in the
        // order it was asked: Jobs first).
        server.list(JOBS, job_list(jobs.clone())).await;
        // Their pods are owned by the Jobs: left to the garbage collector.
        server.list(PODS, pod_list(pods)).await;
        for (name, job) in names.iter().zip(&jobs) {
            let mut dying = job.clone();
            dying["metadata"]["deletionTimestamp"] = json!("2025-03-14T10:00:00Z");
            dying["metadata"]["finalizers"] = json!(["foregroundDeletion"]);
            let body = server.delete(&format!("{JOBS}/{name}"), 200, dying).await;
            assert_eq!(body["propagationPolicy"], "Foreground", "{body}");
        }
        server.assert_silent().await;
    })
    .await
    .unwrap();
    assert_eq!(deleted.jobs, ["lb-4242-team-77-0", "lb-4242-team-77-1"]);
    assert!(deleted.orphan_pods.is_empty() && deleted.already_gone.is_empty());
}

#[tokio::test]
async fn delete_all_takes_not_found_as_gone_and_removes_orphan_pods() {
    let (cluster, mut server) = mock();
    let (jobs, pods) = fixture(include_str!("fixtures/stray-pod.yaml"));
    let deleted = with_server(cluster.delete_all("4242", Whose::Any), async move {
        server.list(JOBS, job_list(jobs)).await;
        server.list(PODS, pod_list(pods.clone())).await;
        let gone = status(
            404,
            "NotFound",
            "jobs.batch \"lb-4242-team-77-0\" not found",
            json!({"name": "lb-4242-team-77-0", "group": "batch", "kind": "jobs"}),
        );
        let body = server
            .delete(&format!("{JOBS}/lb-4242-team-77-0"), 404, gone)
            .await;
        assert_eq!(body["propagationPolicy"], "Foreground");
        let orphan = pods
            .iter()
            .find(|p| p["metadata"].get("ownerReferences").is_none())
            .unwrap()
            .clone();
        let name = orphan["metadata"]["name"].as_str().unwrap().to_string();
        server.delete(&format!("{PODS}/{name}"), 200, orphan).await;
        server.assert_silent().await;
    })
    .await
    .unwrap();
    assert!(deleted.jobs.is_empty());
    assert_eq!(deleted.already_gone, ["lb-4242-team-77-0"]);
    assert_eq!(deleted.orphan_pods, ["lb-4242-team-77-1-o9r8p"]);
}

#[tokio::test]
async fn delete_all_of_nothing_is_fine() {
    let (cluster, mut server) = mock();
    let deleted = with_server(cluster.delete_all("4242", Whose::Any), async move {
        server.list(JOBS, job_list(vec![])).await;
        server.list(PODS, pod_list(vec![])).await;
    })
    .await
    .unwrap();
    assert_eq!(deleted, lb_cluster::Deleted::default());
}

#[tokio::test]
async fn wait_gone_polls_until_nothing_is_left() {
    let (cluster, mut server) = mock();
    let (jobs, pods) = fixture(include_str!("fixtures/running.yaml"));
    let gone = with_server(
        cluster.wait_gone(
            "4242",
            Whose::Any,
            Duration::from_millis(800),
            Duration::from_millis(10),
        ),
        async move {
            server.list(JOBS, job_list(jobs)).await;
            server.list(PODS, pod_list(pods)).await;
            server.list(JOBS, job_list(vec![])).await;
            server.list(PODS, pod_list(vec![])).await;
        },
    )
    .await
    .unwrap();
    assert!(gone);
}

#[tokio::test]
async fn wait_gone_gives_up_at_its_deadline() {
    let (cluster, mut server) = mock();
    let (jobs, _) = fixture(include_str!("fixtures/running.yaml"));
    let waiting = tokio::spawn(async move {
        cluster
            .wait_gone(
                "4242",
                Whose::Any,
                Duration::from_millis(150),
                Duration::from_millis(20),
            )
            .await
    });
    // Answer every poll with a Job still there, until the client stops asking.
    let serve = async {
        loop {
            let Ok(Some((req, send))) =
                tokio::time::timeout(Duration::from_millis(500), server.0.next_request()).await
            else {
                break;
            };
            let answer = if req.uri().path() == JOBS {
                job_list(jobs.clone())
            } else {
                pod_list(vec![])
            };
            send.send_response(
                Response::builder()
                    .body(Body::from(serde_json::to_vec(&answer).unwrap()))
                    .unwrap(),
            );
        }
    };
    tokio::time::timeout(Duration::from_secs(1), serve)
        .await
        .expect("bounded");
    let gone = tokio::time::timeout(Duration::from_secs(1), waiting)
        .await
        .unwrap()
        .unwrap()
        .unwrap();
    assert!(!gone);
}

#[tokio::test]
async fn a_server_that_never_answers_hits_the_call_bound() {
    let (cluster, mut server) = mock();
    let cluster = cluster.with_timeouts(Timeouts {
        call: Duration::from_millis(200),
        ..Timeouts::default()
    });
    let held = tokio::spawn(async move {
        // Take the request and sit on it.
        let req = server.0.next_request().await;
        tokio::time::sleep(Duration::from_millis(600)).await;
        drop(req);
    });
    let started = std::time::Instant::now();
    let err = cluster.observe("4242").await.unwrap_err();
    assert!(started.elapsed() < Duration::from_millis(550));
    assert_eq!(err.name(), "KubeTimeout");
    assert!(err.is_transient());
    held.await.unwrap();
}

#[tokio::test]
async fn a_bad_submission_id_never_reaches_the_server() {
    let (cluster, mut server) = mock();
    for id in ["", "1,app=x", "a b"] {
        assert_eq!(
            cluster.observe(id).await.unwrap_err().name(),
            "InvalidSubmissionId"
        );
        assert_eq!(
            cluster.delete_all(id, Whose::Any).await.unwrap_err().name(),
            "InvalidSubmissionId"
        );
    }
    server.assert_silent().await;
}
