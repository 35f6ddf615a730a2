//! The wake path of the deployment, on moto: an object a Job uploads to a results bucket goes
//! S3 -> EventBridge (the bucket's EventBridgeConfiguration) -> the template's WakeRule ->
//! the wake queue, and the event source mapping hands it over as Lambda's SQS batch. Logs
//! and other objects are kept out by the rule's pattern.

use fake_evalai::Fixture;
use local_stack::events::SqsEventSource;
use local_stack::stack::{app_template, LOCAL_SETTINGS};
use local_stack::{EvalAi, Stack};
use serde_json::{json, Value};
use std::time::Duration;

fn keys(event: &Value) -> Vec<String> {
    let mut keys: Vec<String> = event["Records"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            assert_eq!(r["eventSource"], "aws:sqs");
            let body: Value = serde_json::from_str(r["body"].as_str().unwrap()).unwrap();
            assert_eq!(body["source"], "aws.s3");
            assert_eq!(body["detail-type"], "Object Created");
            body["detail"]["object"]["key"]
                .as_str()
                .unwrap()
                .to_string()
        })
        .collect();
    keys.sort();
    keys
}

#[tokio::test]
#[ignore = "needs moto"]
async fn results_and_markers_reach_the_wake_queue_and_logs_do_not() {
    let (stack, settings) = Stack::provisioned(EvalAi::Fake(Fixture::default()), LOCAL_SETTINGS)
        .await
        .expect("the stack starts and is provisioned");
    let template = app_template(&settings);
    let source = SqsEventSource::from_template(&stack.sdk, &template, "WakeEventSource")
        .await
        .expect("the wake queue exists");
    let s3 = lb_aws::s3_client(&stack.sdk);
    let bucket = &settings.leaderboards[&lb_domain::results::Leaderboard::V2].bucket;
    let put = |key: &'static str| {
        s3.put_object()
            .bucket(bucket)
            .key(key)
            .body(b"{}".to_vec().into())
            .send()
    };
    for key in [
        "42/agent/partial_agent_results1.json",
        "42/containers-status/agent-1.done",
        "42/logs/simulator/simulator1.log",
        "42/agent/agent1/log.txt",
        "42/evalai/results.json",
        "43/agent/partial_agent_results2.json",
    ] {
        put(key).await.unwrap();
    }
    // The mapping's batching window (1 s) gathers the three into one batch.
    let batch = source
        .poll(Duration::from_secs(2))
        .await
        .unwrap()
        .expect("a batch");
    assert_eq!(
        keys(&batch.event),
        [
            "42/agent/partial_agent_results1.json",
            "42/containers-status/agent-1.done",
            "43/agent/partial_agent_results2.json"
        ]
    );
    // The function names one message as failed: the others are deleted, that one stays.
    let failed = batch.event["Records"][0]["messageId"].clone();
    let deleted = source
        .settle(
            batch,
            Some(&json!({"batchItemFailures": [{"itemIdentifier": failed}]})),
        )
        .await
        .unwrap();
    assert_eq!(deleted, 2);
    // A response naming a message not in the batch fails it whole (nothing deleted).
    put("44/containers-status/x").await.unwrap();
    let batch = source
        .poll(Duration::from_secs(2))
        .await
        .unwrap()
        .expect("the new event");
    assert_eq!(keys(&batch.event), ["44/containers-status/x"]);
    let bogus = json!({"batchItemFailures": [{"itemIdentifier": "not-in-the-batch"}]});
    assert_eq!(source.settle(batch, Some(&bogus)).await.unwrap(), 0);
    // Nothing else is on the queue now (the failed ones wait out the visibility timeout).
    assert!(source.poll(Duration::from_secs(1)).await.unwrap().is_none());
}
