//! The wake handler on the real-format events `aws_lambda_events` ships as its own fixtures
//! (`fixtures/sqs-event.json`, `sqs-batch-response.json` and `eventbridge-ec2.json`, copied
//! from the crate's `src/fixtures/`), offline: none of these messages reaches DynamoDB, so the
//! wake table's client points at an address nothing listens on.

use aws_lambda_events::event::sqs::{SqsBatchResponse, SqsEvent};
use serde_json::{json, Value};
use test_support::RecordingCallbacks;
use wake::{failure, submission_of, Deps, Ignored};

const SQS_EVENT: &str = include_str!("fixtures/sqs-event.json");
const BATCH_RESPONSE: &str = include_str!("fixtures/sqs-batch-response.json");
const EC2_EVENT: &str = include_str!("fixtures/eventbridge-ec2.json");
const OBJECT_CREATED: &str = include_str!("fixtures/object-created.json");

fn offline_deps() -> Deps<RecordingCallbacks> {
    let config = aws_sdk_dynamodb::Config::builder()
        .behavior_version_latest()
        .region(aws_sdk_dynamodb::config::Region::new("us-east-1"))
        .endpoint_url("http://127.0.0.1:9")
        .credentials_provider(aws_sdk_dynamodb::config::Credentials::for_tests())
        .build();
    Deps {
        wakes: lb_aws::wake::WakeTable::new(aws_sdk_dynamodb::Client::from_conf(config), "wakes"),
        callbacks: RecordingCallbacks::default(),
    }
}

/// The crate's SQS event with its first record's body replaced.
fn sqs_event_with_bodies(bodies: &[&str]) -> Value {
    let template: Value = serde_json::from_str(SQS_EVENT).unwrap();
    let record = &template["Records"][0];
    let records: Vec<Value> = bodies
        .iter()
        .enumerate()
        .map(|(i, body)| {
            let mut r = record.clone();
            r["messageId"] = json!(format!("m{i}"));
            r["body"] = json!(body);
            r
        })
        .collect();
    json!({ "Records": records })
}

#[tokio::test]
async fn the_crates_sqs_event_decodes_and_a_body_that_is_no_s3_event_is_dropped_not_retried() {
    let event: SqsEvent = serde_json::from_str(SQS_EVENT).expect("the crate's own fixture");
    assert_eq!(event.records[0].message_id.as_deref(), Some("MessageID_1"));

    let out = lb_pipeline::serve::call(&offline_deps(), serde_json::from_str(SQS_EVENT).unwrap())
        .await
        .expect("a batch of foreign messages is no failure");
    assert_eq!(out, json!({"batchItemFailures": []}));
}

#[tokio::test]
async fn events_of_other_sources_and_other_keys_wake_nobody() {
    let other_key = OBJECT_CREATED.replace(
        "42/agent/partial_agent_results1.json",
        "42/logs/simulator1.log",
    );
    let batch = sqs_event_with_bodies(&[EC2_EVENT, &other_key, "{}", "not json"]);
    let deps = offline_deps();
    let out = lb_pipeline::serve::call(&deps, batch).await.unwrap();
    assert_eq!(out, json!({"batchItemFailures": []}));
    assert!(deps.callbacks.reported().is_empty());

    assert!(matches!(
        submission_of(EC2_EVENT),
        Err(Ignored::NotAnS3Event(why)) if why.contains("aws.ec2")
    ));
    assert_eq!(
        submission_of(&other_key),
        Err(Ignored::OtherKey("42/logs/simulator1.log".into()))
    );
    assert_eq!(submission_of(OBJECT_CREATED), Ok(42));
}

#[tokio::test]
async fn an_s3_event_whose_detail_has_no_object_is_named_so() {
    let mut event: Value = serde_json::from_str(OBJECT_CREATED).unwrap();
    event["detail"] = json!({"bucket": {"name": "b"}});
    let Err(Ignored::NotAnS3Event(why)) = submission_of(&event.to_string()) else {
        panic!("not refused");
    };
    assert!(why.contains("object"), "{why}");
}

#[tokio::test]
async fn a_failed_wake_is_reported_as_the_crates_batch_response_format() {
    // The wake table is unreachable: the message of submission 42 comes back, by its id.
    let batch = sqs_event_with_bodies(&[OBJECT_CREATED]);
    let out = lb_pipeline::serve::call(&offline_deps(), batch)
        .await
        .unwrap();
    assert_eq!(
        out,
        json!({"batchItemFailures": [{"itemIdentifier": "m0"}]})
    );

    let mut ours = SqsBatchResponse::default();
    ours.batch_item_failures = vec![failure("id2".into()), failure("id4".into())];
    let theirs: Value = serde_json::from_str(BATCH_RESPONSE).unwrap();
    assert_eq!(serde_json::to_value(&ours).unwrap(), theirs);
}
