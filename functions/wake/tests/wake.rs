//! The wake function against moto's DynamoDB, with the deployed definition's wait standing
//! for a waiting execution and a recorder standing for Step Functions. The events are S3's
//! `Object Created` as EventBridge delivers them (`fixtures/object-created.json`, the S3 user
//! guide's "EventBridge message structure" example with one of our keys), in Lambda's SQS
//! batch (`{"Records": [{"messageId", "body", ...}]}`).

use test_support::{Answer, RecordingCallbacks};

use aws_lambda_events::event::sqs::SqsBatchResponse;
use lb_aws::wake::WakeTable;
use local_stack::integrations::{update_item, wait_for_change};
use local_stack::stack::WAKE_TABLE;
use serde_json::{json, Value};
use wake::{failure, Deps};

const EVENT: &str = include_str!("fixtures/object-created.json");

fn event_for(key: &str) -> String {
    let mut event: Value = serde_json::from_str(EVENT).unwrap();
    event["detail"]["object"]["key"] = json!(key);
    event.to_string()
}

fn batch(records: &[(&str, String)]) -> Value {
    let records: Vec<Value> = records
        .iter()
        .map(|(id, body)| {
            json!({
                "messageId": id, "receiptHandle": format!("handle-{id}"), "body": body,
                "attributes": {"ApproximateReceiveCount": "1"}, "messageAttributes": {},
                "md5OfBody": "", "eventSource": "aws:sqs",
                "eventSourceARN": "arn:aws:sqs:us-east-1:123456789012:leaderboard-wakes",
                "awsRegion": "us-east-1"
            })
        })
        .collect();
    json!({ "Records": records })
}

fn failures(ids: &[&str]) -> SqsBatchResponse {
    let mut response = SqsBatchResponse::default();
    response.batch_item_failures = ids.iter().map(|id| failure(id.to_string())).collect();
    response
}

async fn run(deps: &Deps<RecordingCallbacks>, records: &[(&str, String)]) -> SqsBatchResponse {
    let out = lb_pipeline::serve::call(deps, batch(records))
        .await
        .unwrap();
    let failed: Vec<String> = out["batchItemFailures"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["itemIdentifier"].as_str().unwrap().to_string())
        .collect();
    failures(&failed.iter().map(String::as_str).collect::<Vec<_>>())
}

#[tokio::test]
#[ignore = "needs moto"]
async fn a_burst_wakes_its_execution_once_and_a_failed_report_comes_back() {
    let (stack, _) = test_support::stack::provisioned().await;
    let client = aws_sdk_dynamodb::Client::new(&stack.sdk);
    let deps = Deps {
        wakes: WakeTable::new(client.clone(), WAKE_TABLE),
        callbacks: RecordingCallbacks::default(),
    };
    update_item(&client, wait_for_change("token-1", 42, 7, 0))
        .await
        .expect("submission 42 waits");

    // Two results files and a marker of 42, one of 43 (nobody waits), a log, and garbage.
    let response = run(
        &deps,
        &[
            ("m1", event_for("42/agent/partial_agent_results1.json")),
            ("m2", event_for("42/agent/partial_agent_results2.json")),
            ("m3", event_for("42/containers-status/agent-1.done")),
            ("m4", event_for("43/containers-status/agent-1.done")),
            ("m5", event_for("42/logs/simulator/simulator1.log")),
            ("m6", "{not json".into()),
            (
                "m7",
                json!({"source": "aws.ec2", "detail-type": "x"}).to_string(),
            ),
        ],
    )
    .await;
    assert_eq!(response, failures(&[]), "nothing to deliver again");
    assert_eq!(deps.callbacks.reported(), ["token-1"]);
    assert_eq!(
        deps.wakes.state(42).await.unwrap().changes,
        1,
        "once per batch"
    );
    assert_eq!(deps.wakes.state(43).await.unwrap().changes, 1, "counted");

    // A name the protocol does not define wakes nobody and is not even counted, however
    // often it comes.
    let flood: Vec<(String, String)> = (0..20)
        .map(|i| (format!("f{i}"), event_for("42/containers-status/flood.txt")))
        .collect();
    let flood: Vec<(&str, String)> = flood.iter().map(|(m, e)| (m.as_str(), e.clone())).collect();
    assert_eq!(run(&deps, &flood).await, failures(&[]));
    assert_eq!(deps.wakes.state(42).await.unwrap().changes, 1);

    // An event after the wake found no token: it only counts.
    run(
        &deps,
        &[("m8", event_for("42/containers-status/simulator-1.start0"))],
    )
    .await;
    assert_eq!(deps.callbacks.reported().len(), 1);
    assert_eq!(deps.wakes.state(42).await.unwrap().changes, 2);

    // Step Functions unreachable: 42's messages come back and its token is put back, while
    // 43's are done; the redelivery reports the same token.
    update_item(&client, wait_for_change("token-2", 42, 7, 2))
        .await
        .unwrap();
    deps.callbacks.answer_always(Answer::Unreachable);
    let response = run(
        &deps,
        &[
            ("m9", event_for("42/agent/partial_agent_results1.json")),
            ("m10", event_for("43/agent/partial_agent_results1.json")),
            ("m11", event_for("42/containers-status/agent-2.done")),
        ],
    )
    .await;
    assert_eq!(response, failures(&["m9", "m11"]));
    deps.callbacks.answer_always(Answer::Delivered);
    let response = run(
        &deps,
        &[
            ("m9", event_for("42/agent/partial_agent_results1.json")),
            ("m11", event_for("42/containers-status/agent-2.done")),
        ],
    )
    .await;
    assert_eq!(response, failures(&[]));
    assert_eq!(deps.callbacks.reported(), ["token-1", "token-2", "token-2"]);

    // A token whose wait already ended (timed out into the Monitor): harmless, not retried.
    update_item(&client, wait_for_change("token-3", 42, 7, 4))
        .await
        .unwrap();
    deps.callbacks.answer_always(Answer::Stale);
    let response = run(
        &deps,
        &[("m12", event_for("42/containers-status/agent-1.crash0"))],
    )
    .await;
    assert_eq!(response, failures(&[]));
    assert_eq!(deps.wakes.state(42).await.unwrap().changes, 5);

    // The table unreachable (here: missing): every wake-worthy message comes back.
    let broken = Deps {
        wakes: WakeTable::new(client.clone(), "no-such-table"),
        callbacks: RecordingCallbacks::default(),
    };
    let response = run(
        &broken,
        &[
            ("m13", event_for("42/containers-status/agent-1.done")),
            ("m14", event_for("42/logs/x.log")),
        ],
    )
    .await;
    assert_eq!(response, failures(&["m13"]));

    // Not Lambda's SQS event at all: an input error, nothing half done.
    let err = lb_pipeline::serve::call(&deps, json!({"Records": "x"}))
        .await
        .unwrap_err();
    assert_eq!(err.name(), "InvalidInput");
}
