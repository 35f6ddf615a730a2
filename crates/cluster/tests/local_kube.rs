//! The adapter against the project's local Kubernetes API server, whose pods run as local
//! processes: real Jobs of shell-command containers, through `Cluster::from_kubeconfig`.

use std::future::Future;
use std::path::Path;
use std::time::{Duration, Instant};

use lb_cluster::{
    Cluster, ContainerState, FailureKind, Job, JobState, Observation, Verdict, VerdictPolicy, Whose,
};
use local_kube::{Config, ImageMap, LocalKube};
use serde_json::json;

/// Bound on every wait for the local server to get somewhere.
const WAIT: Duration = Duration::from_secs(20);
const UNPULLABLE: &str = "registry.example/team-77/agent:missing";

async fn start(config: Config) -> (LocalKube, Cluster, tempfile::TempDir) {
    let lk = LocalKube::start(config).await.expect("local-kube starts");
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("kubeconfig");
    lk.write_kubeconfig(&path).expect("kubeconfig written");
    let cluster = Cluster::from_kubeconfig(&path, None)
        .await
        .expect("cluster from kubeconfig");
    (lk, cluster, dir)
}

fn images() -> ImageMap {
    ImageMap::from_yaml(&format!("'{UNPULLABLE}': {{pull: fail}}"), Path::new("/")).unwrap()
}

/// A Job of submission `sub` with the labels the templates set, one container per
/// `(name, image, shell script)`.
fn job(
    sub: &str,
    index: u32,
    restart: &str,
    backoff: i32,
    containers: &[(&str, &str, &str)],
) -> Job {
    let labels = json!({
        "leaderboard.carla.org/submission-id": sub,
        "leaderboard.carla.org/job-index": index.to_string(),
        "leaderboard.carla.org/team-id": "77",
        "leaderboard.carla.org/leaderboard": "2.0",
        "app.kubernetes.io/managed-by": "leaderboard-cloud",
    });
    let containers: Vec<_> = containers
        .iter()
        .map(|(name, image, script)| json!({"name": name, "image": image, "command": ["sh", "-c", script]}))
        .collect();
    serde_json::from_value(json!({
        "apiVersion": "batch/v1",
        "kind": "Job",
        "metadata": {"name": format!("lb-{sub}-team-77-{index}"), "labels": labels},
        "spec": {
            "backoffLimit": backoff,
            "template": {
                "metadata": {"labels": labels},
                "spec": {"restartPolicy": restart, "terminationGracePeriodSeconds": 1, "containers": containers}
            }
        }
    }))
    .unwrap()
}

/// The pod template's spec of a Job, to change before creating it.
fn pod_spec(job: &mut Job) -> &mut k8s_openapi::api::core::v1::PodSpec {
    job.spec.as_mut().unwrap().template.spec.as_mut().unwrap()
}

/// Observes as the Monitor's round does with `policy` (the autoscaler's word read once a pod
/// has waited the grace) every 50 ms until `done` accepts an observation or `WAIT` passes.
async fn observe_until<F>(
    (cluster, policy): (&Cluster, &VerdictPolicy),
    sub: &str,
    what: &str,
    mut done: F,
) -> Observation
where
    F: FnMut(&Observation) -> bool,
{
    let deadline = Instant::now() + WAIT;
    loop {
        let mut obs = cluster.observe(sub).await.expect("observe");
        if let Some(uid) = obs.needs_autoscaler_word(policy).map(str::to_string) {
            if let Some(word) = cluster.autoscaler_word(&uid).await {
                obs.hear_autoscaler(&uid, word);
            }
        }
        if done(&obs) {
            return obs;
        }
        assert!(
            Instant::now() < deadline,
            "timed out waiting for {what}; last: {obs:#?}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

async fn bounded<T>(f: impl Future<Output = T>) -> T {
    tokio::time::timeout(WAIT, f).await.expect("bounded wait")
}

#[tokio::test]
async fn a_job_of_shell_containers_is_observed_running_then_finished() {
    let (_lk, cluster, _dir) = start(Config::default()).await;
    let policy = VerdictPolicy::default();
    let j = job(
        "5001",
        0,
        "OnFailure",
        2,
        &[
            ("simulator-1", "busybox", "sleep 1"),
            ("agent-1", "team/agent:v1", "sleep 1; echo done"),
        ],
    );
    let launched = bounded(cluster.create_or_adopt(&j)).await.unwrap();
    assert!(!launched.adopted);
    // A retried Launch adopts the same Job.
    let again = bounded(cluster.create_or_adopt(&j)).await.unwrap();
    assert!(again.adopted);
    assert_eq!(again.uid, launched.uid);

    let running = observe_until((&cluster, &policy), "5001", "a running agent", |o| {
        o.jobs.first().is_some_and(|j| {
            j.pods
                .iter()
                .flat_map(|p| &p.containers)
                .any(|c| c.name == "agent-1" && matches!(c.state, ContainerState::Running { .. }))
        })
    })
    .await;
    assert_eq!(running.verdict(&policy), Verdict::Running);
    assert_eq!(running.jobs.len(), 1);
    assert_eq!(running.jobs[0].index, Some(0));

    let finished = observe_until((&cluster, &policy), "5001", "Finished", |o| {
        o.verdict(&policy) == Verdict::Finished
    })
    .await;
    assert_eq!(finished.jobs[0].state, JobState::Complete);
    assert_eq!(
        finished.judge(1, &Default::default(), &policy),
        Verdict::Finished
    );
    let agent = finished.jobs[0].pods[0]
        .containers
        .iter()
        .find(|c| c.name == "agent-1")
        .unwrap();
    assert!(matches!(&agent.state, ContainerState::Terminated(e) if e.exit_code == 0));
}

#[tokio::test]
async fn a_crashing_job_is_observed_failed_with_backoff_limit_exceeded() {
    let (_lk, cluster, _dir) = start(Config::default()).await;
    let policy = VerdictPolicy::default();
    let j = job(
        "5002",
        0,
        "Never",
        1,
        &[("agent-1", "team/agent:v1", "echo crash; exit 3")],
    );
    bounded(cluster.create_or_adopt(&j)).await.unwrap();
    let obs = observe_until((&cluster, &policy), "5002", "Failed", |o| {
        o.verdict(&policy).is_terminal()
    })
    .await;
    match &obs.verdict(&policy) {
        Verdict::Failed {
            kind, job, message, ..
        } => {
            assert_eq!(*kind, FailureKind::BackoffLimitExceeded, "{message}");
            assert_eq!(job.as_deref(), Some("lb-5002-team-77-0"));
            assert!(message.contains("BackoffLimitExceeded"), "{message}");
        }
        other => panic!("{other:?}"),
    }
    assert!(
        matches!(&obs.jobs[0].state, JobState::Failed { reason, .. } if reason == "BackoffLimitExceeded")
    );
}

#[tokio::test]
async fn an_unpullable_participant_image_is_observed_failed_naming_the_image() {
    let (_lk, cluster, _dir) = start(Config {
        images: images(),
        ..Config::default()
    })
    .await;
    let policy = VerdictPolicy::default();
    let j = job(
        "5003",
        0,
        "OnFailure",
        2,
        &[
            ("simulator-1", "busybox", "sleep 30"),
            ("agent-1", UNPULLABLE, "echo never"),
        ],
    );
    bounded(cluster.create_or_adopt(&j)).await.unwrap();
    let obs = observe_until((&cluster, &policy), "5003", "an image failure", |o| {
        o.verdict(&policy).is_terminal()
    })
    .await;
    match &obs.verdict(&policy) {
        Verdict::Failed {
            kind,
            container,
            message,
            ..
        } => {
            assert_eq!(*kind, FailureKind::ParticipantImagePull, "{message}");
            assert_eq!(container.as_deref(), Some("agent-1"));
            assert!(message.contains(&format!("`{UNPULLABLE}`")), "{message}");
            assert!(
                message.contains("check that the image URI is correct"),
                "{message}"
            );
        }
        other => panic!("{other:?}"),
    }
    let deleted = bounded(cluster.delete_all("5003", Whose::Any))
        .await
        .unwrap();
    assert_eq!(deleted.jobs, ["lb-5003-team-77-0"]);
}

#[tokio::test]
async fn delete_all_leaves_nothing_and_is_idempotent() {
    let (_lk, cluster, _dir) = start(Config::default()).await;
    let policy = VerdictPolicy::default();
    for index in 0..2 {
        let j = job(
            "5004",
            index,
            "OnFailure",
            2,
            &[("simulator-1", "busybox", "sleep 60")],
        );
        bounded(cluster.create_or_adopt(&j)).await.unwrap();
    }
    // Another submission's Job must survive.
    let other = job(
        "5005",
        0,
        "OnFailure",
        2,
        &[("simulator-1", "busybox", "sleep 60")],
    );
    bounded(cluster.create_or_adopt(&other)).await.unwrap();
    observe_until((&cluster, &policy), "5004", "two running Jobs", |o| {
        o.jobs.len() == 2 && o.jobs.iter().all(|j| j.state == JobState::Running)
    })
    .await;

    let deleted = bounded(cluster.delete_all("5004", Whose::Any))
        .await
        .unwrap();
    assert_eq!(deleted.jobs, ["lb-5004-team-77-0", "lb-5004-team-77-1"]);
    let gone = cluster
        .wait_gone(
            "5004",
            Whose::Any,
            Duration::from_secs(10),
            Duration::from_millis(100),
        )
        .await
        .unwrap();
    assert!(gone, "the Jobs and their pods are gone");
    let (jobs, pods) = cluster.list("5004").await.unwrap();
    assert!(jobs.is_empty() && pods.is_empty());
    let again = bounded(cluster.delete_all("5004", Whose::Any))
        .await
        .unwrap();
    assert_eq!(again, lb_cluster::Deleted::default());

    let (jobs, _) = cluster.list("5005").await.unwrap();
    assert_eq!(jobs.len(), 1, "the other submission is untouched");
    bounded(cluster.delete_all("5005", Whose::Any))
        .await
        .unwrap();
}

#[tokio::test]
async fn a_job_s_deadline_is_extended_in_place_and_a_gone_job_says_so() {
    let (_lk, cluster, _dir) = start(Config::default()).await;
    let policy = VerdictPolicy::default();
    let mut j = job(
        "5006",
        0,
        "Never",
        2,
        &[("simulator-1", "busybox", "sleep 60")],
    );
    j.spec.as_mut().unwrap().active_deadline_seconds = Some(345_600);
    bounded(cluster.create_or_adopt(&j)).await.unwrap();
    let name = "lb-5006-team-77-0";
    let extended = bounded(cluster.set_deadline(name, 345_600 + 900)).await;
    assert!(extended.unwrap());
    let seen = observe_until((&cluster, &policy), "5006", "the new deadline", |o| {
        o.jobs.iter().any(|j| j.deadline == Some(345_600 + 900))
    })
    .await;
    assert!(
        matches!(seen.jobs[0].state, JobState::Pending | JobState::Running),
        "{seen:?}"
    );
    bounded(cluster.delete_all("5006", Whose::Any))
        .await
        .unwrap();
    let gone = bounded(cluster.set_deadline("lb-5006-team-77-9", 1)).await;
    assert!(!gone.unwrap(), "no such Job");
}

#[tokio::test]
async fn a_same_named_job_of_another_submission_is_refused() {
    let (_lk, cluster, _dir) = start(Config::default()).await;
    let mine = job(
        "5006",
        0,
        "OnFailure",
        2,
        &[("simulator-1", "busybox", "sleep 30")],
    );
    bounded(cluster.create_or_adopt(&mine)).await.unwrap();
    // Same name, different submission label.
    let mut theirs = job(
        "5007",
        0,
        "OnFailure",
        2,
        &[("simulator-1", "busybox", "sleep 30")],
    );
    theirs.metadata.name = mine.metadata.name.clone();
    let err = bounded(cluster.create_or_adopt(&theirs)).await.unwrap_err();
    assert_eq!(err.name(), "JobNameTaken", "{err}");
    assert!(err.to_string().contains("`5006`"), "{err}");
    bounded(cluster.delete_all("5006", Whose::Any))
        .await
        .unwrap();
}

#[tokio::test]
async fn the_real_server_refusals_map_to_invalid_and_forbidden() {
    let (_lk, cluster, _dir) = start(Config {
        forbidden_namespaces: vec!["locked".into()],
        ..Config::default()
    })
    .await;
    let mut invalid = job(
        "5008",
        0,
        "OnFailure",
        2,
        &[("simulator-1", "busybox", "true")],
    );
    pod_spec(&mut invalid).containers[0].image = None;
    let err = bounded(cluster.create_or_adopt(&invalid))
        .await
        .unwrap_err();
    assert_eq!(err.name(), "KubeInvalid", "{err}");
    assert!(
        err.to_string()
            .contains("spec.template.spec.containers[0].image"),
        "{err}"
    );

    let locked = cluster.clone().with_namespace("locked");
    let j = job(
        "5008",
        0,
        "OnFailure",
        2,
        &[("simulator-1", "busybox", "true")],
    );
    let err = bounded(locked.create_or_adopt(&j)).await.unwrap_err();
    assert_eq!(err.name(), "KubeForbidden", "{err}");
    assert_eq!(
        bounded(locked.observe("5008")).await.unwrap_err().name(),
        "KubeForbidden"
    );
}

#[tokio::test]
async fn zero_hopeless_limits_do_not_fail_a_healthy_job() {
    // Local pods are scheduled and created at once; zero limits must not invent a failure.
    let (_lk, cluster, _dir) = start(Config::default()).await;
    let policy = VerdictPolicy {
        unschedulable_limit: Duration::ZERO,
        queue_limit: Duration::ZERO,
        config_error_limit: Duration::ZERO,
        never_fits_grace: Duration::ZERO,
    };
    let j = job(
        "5009",
        0,
        "OnFailure",
        2,
        &[("simulator-1", "busybox", "sleep 1")],
    );
    bounded(cluster.create_or_adopt(&j)).await.unwrap();
    let obs = observe_until((&cluster, &policy), "5009", "Finished", |o| {
        o.verdict(&policy).is_terminal()
    })
    .await;
    assert_eq!(obs.verdict(&policy), Verdict::Finished);
}

/// `job` labelled as launched by `execution`, Job and Pods alike.
fn job_of(execution: &str, sub: &str, index: u32) -> Job {
    let mut j = job(
        sub,
        index,
        "OnFailure",
        2,
        &[("simulator-1", "busybox", "sleep 60")],
    );
    for labels in [
        j.metadata.labels.as_mut(),
        j.spec
            .as_mut()
            .and_then(|s| s.template.metadata.as_mut())
            .and_then(|m| m.labels.as_mut()),
    ] {
        labels
            .unwrap()
            .insert(lb_cluster::labels::EXECUTION.into(), execution.into());
    }
    j
}

#[tokio::test]
async fn an_execution_deletes_and_waits_for_its_own_jobs_only() {
    let (_lk, cluster, _dir) = start(Config::default()).await;
    let policy = VerdictPolicy::default();
    bounded(cluster.create_or_adopt(&job_of("exec-new", "5007", 0)))
        .await
        .unwrap();
    // A Job of another execution of the same submission (left by a race), and one from
    // before the execution label.
    bounded(cluster.create_or_adopt(&job_of("exec-old", "5007", 1)))
        .await
        .unwrap();
    let unlabelled = job(
        "5007",
        2,
        "OnFailure",
        2,
        &[("simulator-1", "busybox", "sleep 60")],
    );
    bounded(cluster.create_or_adopt(&unlabelled)).await.unwrap();
    observe_until((&cluster, &policy), "5007", "three Jobs", |o| {
        o.jobs.len() == 3
    })
    .await;
    let names = |jobs: &[Job]| -> Vec<String> {
        (jobs.iter().filter_map(|j| j.metadata.name.clone())).collect()
    };

    // Before its claim is known, an execution stops only what bears its label, and says
    // what it left for lack of one.
    let deleted = bounded(cluster.delete_all("5007", Whose::Labelled("exec-new")))
        .await
        .unwrap();
    assert_eq!(deleted.jobs, ["lb-5007-team-77-0"]);
    assert!(deleted.unlabelled_left >= 1, "{deleted:?}");
    let gone = cluster
        .wait_gone(
            "5007",
            Whose::Labelled("exec-new"),
            Duration::from_secs(10),
            Duration::from_millis(100),
        )
        .await
        .unwrap();
    assert!(gone, "exec-new's Job and pods are gone");
    let (jobs, _) = cluster.list("5007").await.unwrap();
    assert_eq!(names(&jobs), ["lb-5007-team-77-1", "lb-5007-team-77-2"]);

    // Holding the claim, it stops those from before the label too, never another's.
    let deleted = bounded(cluster.delete_all("5007", Whose::Claimed("exec-new")))
        .await
        .unwrap();
    assert_eq!(deleted.jobs, ["lb-5007-team-77-2"]);
    assert_eq!(deleted.unlabelled_left, 0);
    let gone = cluster
        .wait_gone(
            "5007",
            Whose::Claimed("exec-new"),
            Duration::from_secs(10),
            Duration::from_millis(100),
        )
        .await
        .unwrap();
    assert!(gone, "the unlabelled Job and its pods are gone");
    let (jobs, _) = cluster.list("5007").await.unwrap();
    assert_eq!(
        names(&jobs),
        ["lb-5007-team-77-1"],
        "exec-old's Job is not exec-new's to delete"
    );
    bounded(cluster.delete_all("5007", Whose::Any))
        .await
        .unwrap();
}

#[tokio::test]
async fn a_resume_replaces_an_earlier_executions_job_instead_of_adopting_it() {
    let (_lk, cluster, _dir) = start(Config::default()).await;
    let first = bounded(cluster.create_or_adopt(&job_of("exec-1", "5008", 0)))
        .await
        .unwrap();
    // The same execution retrying its Launch adopts its own Job.
    let again = bounded(cluster.create_or_adopt(&job_of("exec-1", "5008", 0)))
        .await
        .unwrap();
    assert!(again.adopted);
    assert_eq!(again.uid, first.uid);
    // A resume's execution: the old Job is deleted and the Launch retried until it is gone.
    let err = bounded(cluster.create_or_adopt(&job_of("exec-2", "5008", 0)))
        .await
        .unwrap_err();
    assert_eq!(err.name(), "JobTerminating");
    assert!(err.is_transient());
    let mut launched = None;
    for _ in 0..100 {
        match bounded(cluster.create_or_adopt(&job_of("exec-2", "5008", 0))).await {
            Ok(l) => {
                launched = Some(l);
                break;
            }
            Err(e) => {
                assert_eq!(e.name(), "JobTerminating", "{e}");
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    }
    let launched = launched.expect("the new execution's Job is created");
    assert!(!launched.adopted);
    assert_ne!(launched.uid, first.uid);
    bounded(cluster.delete_all("5008", Whose::Any))
        .await
        .unwrap();
}

/// `job` whose pod asks for `gpus` GPUs on instance type `instance_type`.
fn gpu_job(sub: &str, gpus: u32, instance_type: &str, script: &str) -> Job {
    let mut j = job(sub, 0, "OnFailure", 2, &[("agent-1", "busybox", script)]);
    let spec = pod_spec(&mut j);
    spec.node_selector = Some(
        [(
            "node.kubernetes.io/instance-type".to_string(),
            instance_type.to_string(),
        )]
        .into(),
    );
    spec.containers[0].resources = Some(
        serde_json::from_value(json!({"limits": {"nvidia.com/gpu": gpus.to_string()}})).unwrap(),
    );
    j
}

#[tokio::test]
async fn a_pod_no_node_could_ever_hold_fails_and_a_pod_waiting_for_room_waits() {
    // One g5.12xlarge node with one GPU, the autoscaler's group at its maximum.
    let (_lk, cluster, _dir) = start(Config {
        gpus: Some(1),
        instance_type: Some("g5.12xlarge".into()),
        autoscaler: true,
        ..Config::default()
    })
    .await;
    let policy = VerdictPolicy {
        never_fits_grace: Duration::ZERO,
        ..VerdictPolicy::default()
    };
    for (sub, gpus, instance_type, script) in [
        ("5101", 1, "g5.12xlarge", "sleep 30"),
        ("5102", 1, "g5.12xlarge", "true"),
        ("5103", 1, "g6.xlarge", "true"),
        ("5104", 2, "g5.12xlarge", "true"),
    ] {
        let j = gpu_job(sub, gpus, instance_type, script);
        bounded(cluster.create_or_adopt(&j)).await.unwrap();
    }
    observe_until((&cluster, &policy), "5101", "running", |o| {
        o.jobs[0].state == JobState::Running
    })
    .await;

    // Waits for the GPU 5101 holds: a queue, never a failure.
    let queued = observe_until((&cluster, &policy), "5102", "the autoscaler's word", |o| {
        o.jobs[0].pods.iter().any(|p| p.autoscaler.is_some())
    })
    .await;
    assert_eq!(queued.verdict(&policy), Verdict::Running);
    let word = queued.jobs[0].pods[0].autoscaler.as_ref().unwrap();
    assert_eq!(
        word.message,
        "pod didn't trigger scale-up: 1 max node group size reached"
    );

    for (sub, expect) in [
        (
            "5103",
            "no node group of the evaluation cluster offers the nodes this leaderboard runs on (`node.kubernetes.io/instance-type=g6.xlarge`)",
        ),
        (
            "5104",
            "its pods request more nvidia.com/gpu than a node of any node group",
        ),
    ] {
        let obs = observe_until((&cluster, &policy), sub, "a verdict", |o| o.verdict(&policy).is_terminal()).await;
        match &obs.verdict(&policy) {
            Verdict::Failed { kind, message, .. } => {
                assert_eq!(*kind, FailureKind::NoNodeFits, "{message}");
                assert!(message.contains(expect), "{sub}: {message}");
            }
            other => panic!("{sub}: {other:?}"),
        }
    }
    for sub in ["5101", "5102", "5103", "5104"] {
        bounded(cluster.delete_all(sub, Whose::Any)).await.unwrap();
    }
}
