//! `lbctl watch` against moto, the fake EvalAI and the local Kubernetes API: a submission
//! driven through its stages while it is watched.

use crate::common;

use std::time::{Duration, Instant};

use aws_sdk_dynamodb::types::AttributeValue;
use common::show;
use fake_evalai::Fixture;
use lb_domain::testutil::results_fixtures_dir;

const TABLE: &str = "leaderboard-20-submissions";
const BUCKET: &str = "leaderboard-20-results";
const CASE: &str = "a_4workers_20routes_finished";

async fn put_record(sdk: &aws_config::SdkConfig, id: u64, attributes: &[(&str, &str)]) {
    let mut request = aws_sdk_dynamodb::Client::new(sdk)
        .put_item()
        .table_name(TABLE)
        .item("team_id", AttributeValue::S("1".into()))
        .item("submission_id", AttributeValue::S(id.to_string()))
        .item("team_name", AttributeValue::S("Team One".into()))
        .item("track_id", AttributeValue::S("1".into()))
        .item("track_name", AttributeValue::S("SENSORS".into()));
    for (k, v) in attributes {
        request = request.item(*k, AttributeValue::S((*v).into()));
    }
    request.send().await.unwrap();
}

async fn put_object(sdk: &aws_config::SdkConfig, key: &str, body: Vec<u8>) {
    lb_aws::s3_client(sdk)
        .put_object()
        .bucket(BUCKET)
        .key(key)
        .body(body.into())
        .send()
        .await
        .unwrap();
}

fn fixture(path: &str) -> Vec<u8> {
    std::fs::read(results_fixtures_dir().join(CASE).join(path)).unwrap()
}

#[tokio::test]
#[ignore = "needs moto"]
async fn watch_follows_a_submission_from_the_queue_to_its_scores() {
    let (stack, env) = common::stack(Fixture::default()).await;
    let sdk = &stack.sdk;
    // The cluster: one pod of the submission, whose image this machine cannot pull.
    let kube = local_kube::LocalKube::spawn(local_kube::Config::default()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let kubeconfig = dir.path().join("kubeconfig");
    kube.write_kubeconfig(&kubeconfig).unwrap();
    let job: lb_cluster::Job = serde_json::from_value(serde_json::json!({
        "apiVersion": "batch/v1", "kind": "Job",
        "metadata": {"name": "lb-1-team-one-0", "namespace": "default",
                     "labels": {lb_domain::job::plan::SUBMISSION_LABEL: "1",
                                "app.kubernetes.io/managed-by": "leaderboard-cloud"}},
        "spec": {"backoffLimit": 4, "template": {
            "metadata": {"labels": {lb_domain::job::plan::SUBMISSION_LABEL: "1",
                                    "app.kubernetes.io/managed-by": "leaderboard-cloud"}},
            "spec": {"restartPolicy": "OnFailure",
                     "containers": [{"name": "agent-1", "image": "never-pushed:1"}]}}}
    }))
    .unwrap();
    lb_cluster::Cluster::from_kubeconfig(&kubeconfig, None)
        .await
        .unwrap()
        .create_or_adopt(&job)
        .await
        .unwrap();

    // Claimed, behind an earlier submission of the same leaderboard.
    put_record(
        sdk,
        7,
        &[
            ("submission_status", "SUBMITTED"),
            ("submitted_time", "2026-01-01 00:00:00 UTC"),
        ],
    )
    .await;
    put_record(
        sdk,
        1,
        &[
            ("submission_status", "SUBMITTED"),
            ("submitted_time", "2026-01-01 00:05:00 UTC"),
        ],
    )
    .await;

    let child = common::lbctl_command(&["watch", "1", "--interval", "1"], &env)
        .env("LB_KUBECONFIG", &kubeconfig)
        .spawn()
        .unwrap();
    tokio::time::sleep(Duration::from_secs(3)).await;

    // Running: a worker's results and the partial scores arrive; EvalAI says running.
    put_record(
        sdk,
        1,
        &[
            ("submission_status", "RUNNING"),
            ("start_time", "2026-01-01 00:06:00 UTC"),
        ],
    )
    .await;
    put_object(
        sdk,
        "1/agent/partial_agent_results1.json",
        fixture("input/worker1.json"),
    )
    .await;
    put_object(
        sdk,
        "1/evalai/results.json",
        fixture("expected/results.json"),
    )
    .await;
    let evalai = lb_evalai::EvalAiClient::new(
        &stack.evalai_url,
        &lb_evalai::HostToken::new("host-token"),
        lb_evalai::AuthScheme::Bearer,
        lb_evalai::RetryPolicy::default(),
    )
    .unwrap();
    let at = lb_evalai::SubmissionRef {
        challenge: 1,
        phase: 1,
        submission: 1,
    };
    evalai.mark_running(at, "lb-1-team-one-0").await.unwrap();
    tokio::time::sleep(Duration::from_secs(3)).await;

    // The end: FINISHED in the record and on EvalAI.
    put_record(
        sdk,
        1,
        &[
            ("submission_status", "FINISHED"),
            ("start_time", "2026-01-01 00:06:00 UTC"),
            ("end_time", "2026-01-01 01:00:00 UTC"),
        ],
    )
    .await;
    let results = String::from_utf8(fixture("expected/results.json")).unwrap();
    evalai
        .post_final(
            at,
            &lb_evalai::FinalUpdate {
                status: lb_domain::submission::SubmissionStatus::Finished,
                result: results,
                stdout: "scores".into(),
                stderr: String::new(),
                metadata: "{}".into(),
            },
        )
        .await
        .unwrap();
    let started = Instant::now();
    let out = tokio::task::spawn_blocking(move || child.wait_with_output())
        .await
        .unwrap()
        .unwrap();
    assert!(started.elapsed() < Duration::from_secs(30));
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    let text = String::from_utf8_lossy(&out.stdout);
    let screens: Vec<&str> = text.split("\n--\n").collect();
    assert!(screens.len() >= 3, "{text}");
    // In the queue, one ahead; its pod waits for an image it cannot pull.
    assert!(
        screens[0].contains(
            "stage     claimed, waiting for its Jobs to run — 1 submission(s) ahead (2 of 2)"
        ),
        "{}",
        screens[0]
    );
    assert!(screens[0].contains("EvalAI    submitted"), "{}", screens[0]);
    assert!(text.contains("lb-1-team-one-0"), "{text}");
    // Running: the worker's routes, EvalAI's status, the partial scores.
    let running = screens
        .iter()
        .find(|s| s.contains("stage     running"))
        .unwrap_or_else(|| panic!("no running screen:\n{text}"));
    assert!(text.contains("worker 1   5/5"), "{text}");
    assert!(
        text.contains("EvalAI    running") || text.contains("EvalAI    finished"),
        "{running}"
    );
    assert!(text.contains("scores    Driving score"), "{text}");
    // The one-screen summary.
    let summary = text
        .split("summary\n")
        .nth(1)
        .unwrap_or_else(|| panic!("{text}"));
    assert!(
        summary.contains("submission 1 ended FINISHED (EvalAI: finished)"),
        "{summary}"
    );
    assert!(summary.contains("Driving score"), "{summary}");
}
