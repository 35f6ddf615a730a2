//! The adapters against a real moto server, through the real SDK clients.

use aws_sdk_dynamodb::types::{
    AttributeDefinition, AttributeValue, BillingMode, KeySchemaElement, KeyType,
    ScalarAttributeType,
};
use lb_aws::dynamo::{
    Claim, FinalRecord, NewRecord, QualifierTable, RecordStatus, SubmissionsTable,
};
use lb_aws::s3::{EvalAiObjects, SubmissionStore};
use local_stack::moto::MotoServer;

async fn config(moto: &MotoServer) -> aws_config::SdkConfig {
    lb_aws::sdk_config_at(&moto.endpoint(), "us-west-2").await
}

/// A table in the original system's key schema: `team_id` (S) and `sort` (S).
async fn create_table(client: &aws_sdk_dynamodb::Client, name: &str, sort: &str) {
    let attribute = |name: &str| {
        AttributeDefinition::builder()
            .attribute_name(name)
            .attribute_type(ScalarAttributeType::S)
            .build()
            .unwrap()
    };
    let key = |name: &str, kind| {
        KeySchemaElement::builder()
            .attribute_name(name)
            .key_type(kind)
            .build()
            .unwrap()
    };
    client
        .create_table()
        .table_name(name)
        .billing_mode(BillingMode::PayPerRequest)
        .attribute_definitions(attribute("team_id"))
        .attribute_definitions(attribute(sort))
        .key_schema(key("team_id", KeyType::Hash))
        .key_schema(key(sort, KeyType::Range))
        .send()
        .await
        .unwrap();
}

fn record(claimed_by: &str, resuming: bool) -> NewRecord {
    NewRecord {
        team_id: 7,
        submission_id: 42,
        team_name: "Team 🚗 One".into(),
        track_id: 1234,
        track_name: "SENSORS".into(),
        image: "123.dkr.ecr.us-west-2.amazonaws.com/team:1".into(),
        workers: 4,
        submitted_time: "2026-11-21 05:00:00 UTC".into(),
        claimed_by: claimed_by.into(),
        resuming,
    }
}

fn text(v: &str) -> AttributeValue {
    AttributeValue::S(v.into())
}

#[test]
fn record_times_are_written_as_the_original_writes_them() {
    let at = time::macros::datetime!(2024-03-07 10:31:02.75 UTC);
    assert_eq!(lb_aws::dynamo::record_time(at), "2024-03-07 10:31:02 UTC");
    let elsewhere = time::macros::datetime!(2024-03-07 12:31:02 +02:00);
    assert_eq!(
        lb_aws::dynamo::record_time(elsewhere),
        "2024-03-07 10:31:02 UTC"
    );
}

#[tokio::test]
#[ignore = "needs moto"]
async fn the_claim_admits_one_evaluation_per_delivery_and_a_resume_after_it_ended() {
    let moto = MotoServer::start().unwrap();
    let client = aws_sdk_dynamodb::Client::new(&config(&moto).await);
    create_table(&client, "subs", "submission_id").await;
    let table = SubmissionsTable::new(client.clone(), "subs");

    assert_eq!(
        table.claim(&record("exec-1", false)).await.unwrap(),
        Claim::Claimed
    );
    // Written at intake in the original layout: string keys and values, `-` for the times
    // not known yet, EvalAI's status upper-cased.
    let item = table.record(7, 42).await.unwrap().unwrap().item;
    for (attribute, value) in [
        ("team_id", "7"),
        ("submission_id", "42"),
        ("submission_status", "SUBMITTED"),
        ("track_id", "1234"),
        ("track_name", "SENSORS"),
        ("parallelization_workers", "4"),
        ("submitted_time", "2026-11-21 05:00:00 UTC"),
        ("start_time", "-"),
        ("end_time", "-"),
    ] {
        assert_eq!(item[attribute], text(value), "{attribute}");
    }
    // The same execution retrying its Lambda keeps its claim.
    assert_eq!(
        table.claim(&record("exec-1", false)).await.unwrap(),
        Claim::Claimed
    );
    // A duplicate SQS delivery starts a second execution: refused.
    assert_eq!(
        table.claim(&record("exec-2", false)).await.unwrap(),
        Claim::Duplicate {
            status: Some(RecordStatus::Submitted),
            claimed_by: Some("exec-1".into())
        }
    );
    // A resume while the first run is still going: refused too.
    table
        .mark_running(
            7,
            42,
            ("2026-11-21 05:01:00 UTC", "s3://b/42"),
            (0, 20),
            (None, None),
        )
        .await
        .unwrap();
    let item = table.record(7, 42).await.unwrap().unwrap().item;
    assert_eq!(item["submission_status"], text("RUNNING"));
    assert_eq!(item["start_time"], text("2026-11-21 05:01:00 UTC"));
    assert_eq!(item["results"], text("s3://b/42"));
    // Later rounds keep the first start time, and record the GPUs used so far.
    let usage = lb_domain::capacity::cost::Totals {
        gpu_seconds: 7200,
        spot: 3600,
        run_again: 60,
        lost: 240,
        dollars: Some(2.0468),
        orchestration: Some(lb_domain::capacity::cost::Orchestration {
            transitions: 400,
            invocations: 100,
            mb_ms: 100 * 512 * 1000,
            dynamo_requests: 1000,
        }),
        stored: None,
    };
    table
        .mark_running(
            7,
            42,
            ("2026-11-21 05:30:00 UTC", "s3://b/42"),
            (4, 20),
            (Some(&usage), Some(&format!("sha256:{}", "a".repeat(64)))),
        )
        .await
        .unwrap();
    let item = table.record(7, 42).await.unwrap().unwrap().item;
    assert_eq!(
        item["image_digest"],
        text(&format!("sha256:{}", "a".repeat(64)))
    );
    assert_eq!(item["start_time"], text("2026-11-21 05:01:00 UTC"));
    assert_eq!(item["routes_done"], AttributeValue::N("4".into()));
    assert_eq!(item["gpu_seconds"], AttributeValue::N("7200".into()));
    assert_eq!(item["gpu_seconds_spot"], AttributeValue::N("3600".into()));
    assert_eq!(
        item["gpu_seconds_run_again"],
        AttributeValue::N("60".into())
    );
    assert_eq!(
        item["seconds_lost_to_reclaims"],
        AttributeValue::N("240".into())
    );
    assert_eq!(item["cost_usd"], AttributeValue::N("2.05".into()));
    // 400 transitions $0.01, 100 invocations, 50 GB-seconds $0.00083, 1,000 requests.
    assert_eq!(
        item["orchestration_usd"],
        AttributeValue::N("0.0115".into())
    );
    assert_eq!(item["state_transitions"], AttributeValue::N("400".into()));
    assert!(matches!(
        table.claim(&record("exec-3", true)).await.unwrap(),
        Claim::Duplicate { .. }
    ));

    let failed = FinalRecord {
        status: RecordStatus::Failed,
        end_time: "2026-11-21 06:00:00 UTC".into(),
        results: "s3://b/42".into(),
        metrics: vec![("driving_score", None)],
        progress: (5, 20),
        error: Some("CARLA crashed too often".into()),
        failed_by_platform: true,
        recordings: Some(lb_domain::run::audit::Recordings {
            passed: 4,
            expected: 5,
            failures: vec!["RouteScenario_3_rep0: no recording in pair 2's folder".into()],
        }),
        usage: Some(lb_domain::capacity::cost::Totals {
            dollars: None,
            stored: Some(lb_domain::job::uploads::UploadReport {
                log_bytes: 3 << 30,
                log_objects: 12,
                log_puts: 40,
                refused_files: 2,
                refused_bytes: 200 << 20,
            }),
            ..usage
        }),
    };
    // Only the execution holding the claim writes the final record, and only once.
    assert!(!table.finish(7, 42, "exec-2", &failed).await.unwrap());
    assert_eq!(
        table.record(7, 42).await.unwrap().unwrap().item["submission_status"],
        text("RUNNING")
    );
    assert!(table.finish(7, 42, "exec-1", &failed).await.unwrap());
    assert!(!table.finish(7, 42, "exec-1", &failed).await.unwrap());
    let standing = table.standing(7, 42).await.unwrap().unwrap();
    assert_eq!(standing.claimed_by.as_deref(), Some("exec-1"));
    assert_eq!(standing.status, Some(RecordStatus::Failed));
    assert_eq!(standing.error.as_deref(), Some("CARLA crashed too often"));
    assert!(standing.failed_by_platform);
    let item = table.record(7, 42).await.unwrap().unwrap().item;
    assert_eq!(
        item["driving_score"],
        text("-"),
        "a metric EvalAI never got"
    );
    assert_eq!(item["recordings_found"], AttributeValue::N("4".into()));
    assert_eq!(item["recordings_expected"], AttributeValue::N("5".into()));
    assert_eq!(
        item["recordings_failed"],
        AttributeValue::L(vec![text(
            "RouteScenario_3_rep0: no recording in pair 2's folder"
        )])
    );
    assert_eq!(item["gpu_seconds"], AttributeValue::N("7200".into()));
    assert!(!item.contains_key("cost_usd"), "no price: no estimate");
    // What the logs keep in S3, and what logcopy refused to upload.
    assert_eq!(
        item["log_bytes_stored"],
        AttributeValue::N("3221225472".into())
    );
    assert_eq!(item["uploads_refused"], AttributeValue::N("2".into()));
    // Now a resume may claim it, and its finish clears the old error and stores every metric.
    assert_eq!(
        table.claim(&record("exec-4", true)).await.unwrap(),
        Claim::Claimed
    );
    let item = table.record(7, 42).await.unwrap().unwrap().item;
    assert_eq!(item["submission_status"], text("RESUMING"));
    assert_eq!(item["start_time"], text("-"), "the resume starts afresh");
    table
        .mark_running(
            7,
            42,
            ("2026-11-21 07:00:00 UTC", "s3://b/42"),
            (3, 20),
            (None, None),
        )
        .await
        .unwrap();
    let metrics: Vec<(&'static str, Option<String>)> = lb_domain::results::METRICS
        .iter()
        .enumerate()
        .map(|(i, m)| (m.attribute, Some(format!("{}.5", i))))
        .collect();
    let finished = table
        .finish(
            7,
            42,
            "exec-4",
            &FinalRecord {
                status: RecordStatus::Finished,
                end_time: "2026-11-21 08:00:00 UTC".into(),
                results: "s3://b/42".into(),
                metrics: metrics.clone(),
                progress: (20, 20),
                error: None,
                failed_by_platform: false,
                recordings: None,
                usage: None,
            },
        )
        .await
        .unwrap();
    assert!(finished, "the resume's execution holds the claim");
    let item = table.record(7, 42).await.unwrap().unwrap().item;
    assert_eq!(item["submission_status"], text("FINISHED"));
    assert_eq!(
        item["start_time"],
        text("2026-11-21 07:00:00 UTC"),
        "the resume's start"
    );
    assert_eq!(item["end_time"], text("2026-11-21 08:00:00 UTC"));
    assert_eq!(item["team_name"], text("Team 🚗 One"));
    assert!(!item.contains_key("error"));
    assert!(
        !item.contains_key("failed_by"),
        "nor whose the old failure was"
    );
    // Nor the old run's count of recordings, when this one has none.
    for attribute in [
        "recordings_found",
        "recordings_expected",
        "recordings_failed",
    ] {
        assert!(!item.contains_key(attribute), "{attribute}");
    }
    assert!(!item.contains_key("gpu_seconds"), "nor its usage");
    for (attribute, value) in metrics {
        assert_eq!(item[attribute], text(&value.unwrap()), "{attribute}");
    }
    assert_eq!(
        item["agent_blocked"],
        text("11.5"),
        "the key the original missed"
    );
    assert_eq!(item["routes_done"], AttributeValue::N("20".into()));
}

#[tokio::test]
#[ignore = "needs moto"]
async fn the_worker_override_and_the_qualifier_table_are_read_as_the_original_wrote_them() {
    let moto = MotoServer::start().unwrap();
    let client = aws_sdk_dynamodb::Client::new(&config(&moto).await);
    create_table(&client, "subs", "submission_id").await;
    create_table(&client, "quals", "track_codename").await;
    let table = SubmissionsTable::new(client.clone(), "subs");
    assert_eq!(table.worker_override(7, 42).await.unwrap(), None);
    // The original writes a string; a number typed by hand works too.
    let cases = [
        (text("8"), Ok(Some(8))),
        (text(" 2 "), Ok(Some(2))),
        (text("-"), Ok(None)),
        (AttributeValue::N("3".into()), Ok(Some(3))),
        (text("0"), Err("MalformedRecord")),
        (text("x"), Err("MalformedRecord")),
        (AttributeValue::Bool(true), Err("MalformedRecord")),
    ];
    for (value, expected) in cases {
        client
            .put_item()
            .table_name("subs")
            .item("team_id", text("7"))
            .item("submission_id", text("42"))
            .item("parallelization_workers", value.clone())
            .send()
            .await
            .unwrap();
        let got = table.worker_override(7, 42).await.map_err(|e| e.name());
        assert_eq!(got, expected, "{value:?}");
    }

    let quals = QualifierTable::new(client.clone(), "quals");
    assert!(!quals.admitted(7, "SENSORS").await.unwrap());
    // A pass the original system recorded: the target track, string keys.
    client
        .put_item()
        .table_name("quals")
        .item("team_id", text("9"))
        .item("track_codename", text("SENSORS"))
        .item("submission_id", text("301"))
        .send()
        .await
        .unwrap();
    assert!(quals.admitted(9, "SENSORS").await.unwrap());
    assert!(!quals.admitted(9, "MAP").await.unwrap());
    // Ours, written so the original reads it the same way; the first pass stays.
    quals.admit(7, "SENSORS", 40).await.unwrap();
    quals.admit(7, "SENSORS", 41).await.unwrap();
    assert!(quals.admitted(7, "SENSORS").await.unwrap());
    let item = client
        .get_item()
        .table_name("quals")
        .key("team_id", text("7"))
        .key("track_codename", text("SENSORS"))
        .send()
        .await
        .unwrap()
        .item
        .unwrap();
    assert_eq!(item["submission_id"], text("40"));
    assert!(!quals.admitted(8, "SENSORS").await.unwrap());
}

#[tokio::test]
#[ignore = "needs moto"]
async fn the_submission_folder_lists_partials_and_markers_and_refuses_huge_objects() {
    let moto = MotoServer::start().unwrap();
    let client = lb_aws::s3_client(&config(&moto).await);
    client
        .create_bucket()
        .bucket("results")
        .create_bucket_configuration(
            aws_sdk_s3::types::CreateBucketConfiguration::builder()
                .location_constraint(aws_sdk_s3::types::BucketLocationConstraint::UsWest2)
                .build(),
        )
        .send()
        .await
        .unwrap();
    let store = SubmissionStore::new(client.clone(), "results", 42);
    let other = SubmissionStore::new(client, "results", 420);
    for (key, body) in [
        ("agent/partial_agent_results2.json", "{\"b\": 2}"),
        ("agent/partial_agent_results1.json", "{\"a\": 1}"),
        ("agent/partial_agent_results.json", "no id"),
        ("agent/partial_agent_results1.json.tmp", "temp"),
        ("agent/notes.txt", "x"),
        ("containers-status/agent-1.done", ""),
        ("containers-status/simulator-1.start0", ""),
    ] {
        store
            .put(key, body.as_bytes().to_vec(), "application/json")
            .await
            .unwrap();
    }
    other
        .put(
            "agent/partial_agent_results9.json",
            b"{}".to_vec(),
            "application/json",
        )
        .await
        .unwrap();

    let partials = store.partials().await.unwrap();
    assert_eq!(
        partials.iter().map(|p| p.pair_id).collect::<Vec<_>>(),
        [1, 2]
    );
    assert_eq!(partials[0].key, "42/agent/partial_agent_results1.json");
    assert!(!partials[0].etag.is_empty());
    assert_eq!(
        store.get_bounded(&partials[0].key, 100).await.unwrap(),
        b"{\"a\": 1}"
    );
    assert_eq!(
        store
            .get_bounded(&partials[0].key, 3)
            .await
            .unwrap_err()
            .name(),
        "ObjectTooLarge"
    );

    let mut markers = store.markers().await.unwrap();
    markers.sort();
    assert_eq!(markers, ["agent-1.done", "simulator-1.start0"]);
    store.put_cancel_marker().await.unwrap();
    assert!(store
        .markers()
        .await
        .unwrap()
        .contains(&"simulation.cancel".to_string()));
    assert!(
        other.markers().await.unwrap().is_empty(),
        "one submission's markers are its own"
    );

    store
        .put_evalai_files(&EvalAiObjects {
            merged: Some("{}"),
            results: "[]",
            stdout: "out",
            metadata: None,
        })
        .await
        .unwrap();
    assert_eq!(
        store.get_bounded("42/evalai/stdout.txt", 10).await.unwrap(),
        b"out"
    );
    // The original's `results` attribute: no trailing slash.
    assert_eq!(store.location(), "s3://results/42");
}

#[tokio::test]
#[ignore = "needs moto"]
async fn settings_and_token_come_from_their_secrets_with_clear_errors() {
    let moto = MotoServer::start().unwrap();
    let client = aws_sdk_secretsmanager::Client::new(&config(&moto).await);
    let settings = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/fixtures/settings.json"
    ))
    .unwrap();
    for (name, value) in [
        ("config", settings.as_str()),
        ("token", r#"{"token": "host-token"}"#),
        ("broken", "{\"evalai\": 1}"),
    ] {
        client
            .create_secret()
            .name(name)
            .secret_string(value)
            .send()
            .await
            .unwrap();
    }
    let loaded = lb_aws::secrets::load_settings(&client, "config")
        .await
        .unwrap();
    assert_eq!(loaded.target(1234).unwrap().track, "SENSORS");
    assert_eq!(
        lb_aws::secrets::load_token(&client, "token")
            .await
            .unwrap()
            .expose(),
        "host-token"
    );
    let err = lb_aws::secrets::load_settings(&client, "broken")
        .await
        .unwrap_err();
    assert_eq!(err.name(), "InvalidSecret");
    assert!(err.to_string().contains("`evalai`"), "{err}");
    let err = lb_aws::secrets::load_settings(&client, "missing")
        .await
        .unwrap_err();
    assert_eq!(err.name(), "AwsServiceError");
}

#[tokio::test]
#[ignore = "needs moto"]
async fn the_cluster_endpoint_and_ca_come_from_describe_cluster() {
    let moto = MotoServer::start().unwrap();
    let config = config(&moto).await;
    let eks = aws_sdk_eks::Client::new(&config);
    eks.create_cluster()
        .name("leaderboard-20")
        .role_arn("arn:aws:iam::123456789012:role/eks")
        .resources_vpc_config(
            aws_sdk_eks::types::VpcConfigRequest::builder()
                .subnet_ids("subnet-1")
                .build(),
        )
        .send()
        .await
        .unwrap();
    let access = lb_aws::eks::describe_cluster(&eks, "leaderboard-20")
        .await
        .unwrap();
    assert!(
        access.endpoint.starts_with("https://"),
        "{}",
        access.endpoint
    );
    assert!(!access.ca_pem.is_empty());
    let err = lb_aws::eks::describe_cluster(&eks, "nope")
        .await
        .unwrap_err();
    assert_eq!(err.name(), "AwsServiceError");
}
