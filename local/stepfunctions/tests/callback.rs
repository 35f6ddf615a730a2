//! The callback pattern as the Step Functions developer guide describes it ("Wait for a
//! Callback with the Task Token"): the guide's example sends the token in an SQS message
//! (`arn:aws:states:::sqs:sendMessage.waitForTaskToken` with `"TaskToken.$": "$$.Task.Token"`)
//! and a worker calls `SendTaskSuccess` / `SendTaskFailure` / `SendTaskHeartbeat`. Here the
//! `sqs:sendMessage` handler plays SQS and hands the message to the test, which plays the
//! worker.

use crate::common;

use std::collections::HashMap;
use std::time::Duration;

use common::{load, options, types, BOUND};
use local_stepfunctions::{
    EventType, Executor, LoadError, StateMachine, Status, TaskMap, STATES_HEARTBEAT_TIMEOUT,
    STATES_TIMEOUT,
};
use serde_json::{json, Value};
use tokio::sync::mpsc;

/// The guide's example Task state, with `extra` merged in (a `null` removes a field).
fn task(extra: Value) -> Value {
    let mut task = json!({
        "Type": "Task",
        "Resource": "arn:aws:states:::sqs:sendMessage.waitForTaskToken",
        "Parameters": {
            "QueueUrl": "https://sqs.us-east-1.amazonaws.com/123456789012/callbacks",
            "MessageBody": {"Message.$": "$.message", "TaskToken.$": "$$.Task.Token"}
        },
        "ResultPath": "$.reply",
        "TimeoutSeconds": 60,
        "End": true
    });
    if let (Value::Object(t), Value::Object(e)) = (&mut task, extra) {
        for (k, v) in e {
            if v.is_null() {
                t.remove(&k);
            } else {
                t.insert(k, v);
            }
        }
    }
    task
}

fn machine(extra: Value) -> StateMachine {
    load(json!({"StartAt": "Notify", "States": {"Notify": task(extra)}}))
}

/// SQS, played: every message the machine sends, to the test.
fn sqs() -> (TaskMap, mpsc::UnboundedReceiver<Value>) {
    let (tx, rx) = mpsc::unbounded_channel();
    let tasks = TaskMap::new().with("sqs:sendMessage", move |params: Value| {
        let tx = tx.clone();
        async move {
            let _ = tx.send(params["MessageBody"].clone());
            Ok(json!({"MessageId": "5fea7756-0ea4-451a-a703-a558b933e274", "MD5OfMessageBody": "x"}))
        }
    });
    (tasks, rx)
}

async fn next_token(rx: &mut mpsc::UnboundedReceiver<Value>) -> String {
    let body = tokio::time::timeout(BOUND, rx.recv())
        .await
        .expect("a message in time")
        .expect("a message");
    body["TaskToken"].as_str().expect("the token").to_owned()
}

#[tokio::test]
async fn the_reported_output_is_the_tasks_result_after_a_submitted_event() {
    let (tasks, mut rx) = sqs();
    let executor = Executor::new(tasks, options(0.01)).unwrap();
    let execution = executor
        .start(&machine(json!({})), "ok", json!({"message": "hello"}))
        .unwrap();
    let token = next_token(&mut rx).await;
    assert!(token.len() <= 1024);
    executor
        .send_task_success(&token, json!({"approved": true}))
        .unwrap();
    let result = tokio::time::timeout(BOUND, execution.wait()).await.unwrap();
    assert_eq!(result.status, Status::Succeeded);
    assert_eq!(
        result.output,
        Some(json!({"message": "hello", "reply": {"approved": true}}))
    );
    assert_eq!(
        types(&result),
        [
            EventType::ExecutionStarted,
            EventType::TaskStateEntered,
            EventType::TaskScheduled,
            EventType::TaskStarted,
            EventType::TaskSubmitted,
            EventType::TaskSucceeded,
            EventType::TaskStateExited,
            EventType::ExecutionSucceeded,
        ]
    );
    let scheduled = &result.history[2].details;
    assert_eq!(scheduled["resourceType"], "sqs");
    assert_eq!(scheduled["resource"], "sendMessage.waitForTaskToken");
    assert_eq!(scheduled["parameters"]["MessageBody"]["TaskToken"], token);
    assert_eq!(scheduled["timeoutInSeconds"], 60);
    // The service's own answer is in TaskSubmitted, not in the result.
    let submitted = &result.history[4].details;
    assert_eq!(
        submitted["output"]["MessageId"],
        "5fea7756-0ea4-451a-a703-a558b933e274"
    );
    // A token is used once.
    let again = executor.send_task_success(&token, json!({})).unwrap_err();
    assert_eq!(again.name(), "TaskTimedOut");
}

#[tokio::test]
async fn a_reported_failure_is_the_tasks_error_for_retry_and_catch() {
    let (tasks, mut rx) = sqs();
    let executor = Executor::new(tasks, options(0.01)).unwrap();
    let notify = task(json!({
        "Retry": [{"ErrorEquals": ["Worker.Busy"], "IntervalSeconds": 1, "MaxAttempts": 1}],
        "Catch": [{"ErrorEquals": ["Worker.Busy"], "ResultPath": "$.error", "Next": "Caught"}],
        "End": null,
        "Next": "Caught"
    }));
    let definition = json!({"StartAt": "Notify", "States": {
        "Notify": notify,
        "Caught": {"Type": "Pass", "End": true}
    }});
    let execution = executor
        .start(&load(definition), "fail", json!({"message": "hello"}))
        .unwrap();
    let first = next_token(&mut rx).await;
    executor
        .send_task_failure(&first, "Worker.Busy", "try later")
        .unwrap();
    // The retry is a new attempt with a new token.
    let second = next_token(&mut rx).await;
    assert_ne!(first, second);
    executor
        .send_task_failure(&second, "Worker.Busy", "still busy")
        .unwrap();
    let result = tokio::time::timeout(BOUND, execution.wait()).await.unwrap();
    assert_eq!(result.status, Status::Succeeded);
    let output = result.output.clone().unwrap();
    assert_eq!(
        output["error"],
        json!({"Error": "Worker.Busy", "Cause": "still busy"})
    );
    assert_eq!(result.count(EventType::TaskFailed), 2);
    assert_eq!(result.count(EventType::TaskSubmitted), 2);
}

#[tokio::test]
async fn no_report_within_timeout_seconds_is_states_timeout_and_the_token_expires() {
    let (tasks, mut rx) = sqs();
    let executor = Executor::new(tasks, options(0.01)).unwrap();
    // 60 s at scale 0.01: 0.6 s.
    let execution = executor
        .start(&machine(json!({})), "late", json!({"message": "hello"}))
        .unwrap();
    let token = next_token(&mut rx).await;
    let result = tokio::time::timeout(BOUND, execution.wait()).await.unwrap();
    assert_eq!(result.status, Status::Failed);
    assert_eq!(result.error.as_deref(), Some(STATES_TIMEOUT));
    assert_eq!(result.count(EventType::TaskTimedOut), 1);
    let late = executor
        .send_task_success(&token, json!({"approved": true}))
        .unwrap_err();
    assert_eq!(late.name(), "TaskTimedOut");
}

#[tokio::test]
async fn heartbeats_keep_a_task_alive_and_their_absence_ends_it() {
    let (tasks, mut rx) = sqs();
    let executor = Executor::new(tasks, options(0.01)).unwrap();
    // Heartbeat every 10 s (0.1 s), timeout 60 s (0.6 s).
    let extra = json!({"HeartbeatSeconds": 10});
    let execution = executor
        .start(&machine(extra.clone()), "beating", json!({"message": "hi"}))
        .unwrap();
    let token = next_token(&mut rx).await;
    // Three heartbeat periods with heartbeats: still waiting.
    for _ in 0..6 {
        tokio::time::sleep(Duration::from_millis(50)).await;
        executor.send_task_heartbeat(&token).unwrap();
    }
    executor.send_task_success(&token, json!("done")).unwrap();
    let result = tokio::time::timeout(BOUND, execution.wait()).await.unwrap();
    assert_eq!(result.status, Status::Succeeded, "{:?}", result.error);
    assert_eq!(result.history[2].details["heartbeatInSeconds"], 10);

    let execution = executor
        .start(&machine(extra), "silent", json!({"message": "hi"}))
        .unwrap();
    let _token = next_token(&mut rx).await;
    let result = tokio::time::timeout(BOUND, execution.wait()).await.unwrap();
    assert_eq!(result.error.as_deref(), Some(STATES_HEARTBEAT_TIMEOUT));
    assert_eq!(result.count(EventType::TaskTimedOut), 1);
}

#[tokio::test]
async fn tokens_never_seen_or_malformed_are_refused_by_name() {
    let (tasks, _rx) = sqs();
    let executor = Executor::new(tasks, options(0.01)).unwrap();
    let unknown = executor.send_task_success("AQ-never-issued", json!({}));
    assert_eq!(unknown.unwrap_err().name(), "TaskDoesNotExist");
    assert_eq!(
        executor.send_task_heartbeat("").unwrap_err().name(),
        "InvalidToken"
    );
    let long = "x".repeat(1025);
    assert_eq!(
        executor
            .send_task_failure(&long, "E", "c")
            .unwrap_err()
            .name(),
        "InvalidToken"
    );
}

#[tokio::test]
async fn a_report_larger_than_the_payload_limit_is_invalid_output() {
    let (tasks, mut rx) = sqs();
    let mut opts = options(0.01);
    opts.max_payload_bytes = 1024;
    let executor = Executor::new(tasks, opts).unwrap();
    let execution = executor
        .start(&machine(json!({})), "big", json!({"message": "hello"}))
        .unwrap();
    let token = next_token(&mut rx).await;
    let err = executor
        .send_task_success(&token, json!("x".repeat(2000)))
        .unwrap_err();
    assert_eq!(err.name(), "InvalidOutput");
    // The task still waits: a valid report goes through.
    executor.send_task_success(&token, json!("ok")).unwrap();
    let result = tokio::time::timeout(BOUND, execution.wait()).await.unwrap();
    assert_eq!(result.status, Status::Succeeded);
}

#[test]
fn callback_definitions_are_checked_at_load() {
    let load_err = |extra: Value| -> LoadError {
        let mut task = json!({
            "Type": "Task",
            "Resource": "arn:aws:states:::sqs:sendMessage.waitForTaskToken",
            "Parameters": {"MessageBody": {"TaskToken.$": "$$.Task.Token"}},
            "End": true
        });
        if let (Value::Object(t), Value::Object(e)) = (&mut task, extra) {
            t.extend(e);
        }
        StateMachine::load(
            &json!({"StartAt": "T", "States": {"T": task}}),
            &HashMap::new(),
        )
        .unwrap_err()
    };
    let e = load_err(json!({"HeartbeatSeconds": 60, "TimeoutSeconds": 60}));
    assert!(e.to_string().contains("HeartbeatSeconds"), "{e}");
    let e = load_err(json!({"Resource": "arn:aws:states:::batch:submitJob.sync"}));
    assert!(e.to_string().contains(".sync"), "{e}");
    let e = load_err(
        json!({"Resource": "arn:aws:states:::lambda:invoke", "HeartbeatSeconds": 5,
                            "Parameters": {"FunctionName": "arn:aws:lambda:us-east-1:123456789012:function:f"}}),
    );
    assert!(e.to_string().contains("HeartbeatSeconds"), "{e}");
    // The optimized DynamoDB integration is request-response only (the guide's table of
    // optimized integrations); its AWS SDK integration has the callback pattern.
    let e = load_err(json!({"Resource": "arn:aws:states:::dynamodb:updateItem.waitForTaskToken"}));
    assert!(e.to_string().contains("aws-sdk:dynamodb"), "{e}");
    let e = load_err(json!({"TimeoutSeconds": 60, "TimeoutSecondsPath": "$.wait"}));
    assert!(e.to_string().contains("exclusive"), "{e}");
    let e = load_err(json!({"TimeoutSecondsPath": "wait"}));
    assert!(e.to_string().contains("TimeoutSecondsPath"), "{e}");
}

/// The AWS SDK integration for DynamoDB's `UpdateItem` with a token (the guide's syntax
/// `arn:aws:states:::aws-sdk:<service>:<action>.waitForTaskToken`), played by a handler
/// registered as `aws-sdk:dynamodb:updateItem`; the timeout read from the input.
#[tokio::test]
async fn an_sdk_integration_waits_for_its_token_with_the_timeout_its_input_names() {
    let (tx, mut rx) = mpsc::unbounded_channel();
    let tasks = TaskMap::new().with("aws-sdk:dynamodb:updateItem", move |params: Value| {
        let tx = tx.clone();
        async move {
            let _ = tx.send(params);
            Ok(json!({}))
        }
    });
    let definition = json!({"StartAt": "Wait", "States": {"Wait": {
        "Type": "Task",
        "Resource": "arn:aws:states:::aws-sdk:dynamodb:updateItem.waitForTaskToken",
        "Parameters": {
            "TableName": "wakes",
            "Key": {"submission_id": {"S": "42"}},
            "UpdateExpression": "SET #t = :t",
            "ExpressionAttributeNames": {"#t": "token"},
            "ExpressionAttributeValues": {":t": {"S.$": "$$.Task.Token"}}
        },
        "TimeoutSecondsPath": "$.wait",
        "ResultPath": "$.woken",
        "End": true
    }}});
    let machine = load(definition);
    let executor = Executor::new(tasks, options(0.01)).unwrap();
    // Woken before the timeout.
    let execution = executor
        .start(&machine, "woken", json!({"wait": 3600}))
        .unwrap();
    let params = tokio::time::timeout(BOUND, rx.recv())
        .await
        .unwrap()
        .unwrap();
    let token = params["ExpressionAttributeValues"][":t"]["S"]
        .as_str()
        .unwrap()
        .to_owned();
    executor
        .send_task_success(&token, json!({"by": "results"}))
        .unwrap();
    let result = tokio::time::timeout(BOUND, execution.wait()).await.unwrap();
    assert_eq!(result.status, Status::Succeeded);
    assert_eq!(result.output.unwrap()["woken"], json!({"by": "results"}));
    let scheduled = &result.history[2].details;
    assert_eq!(scheduled["resourceType"], "aws-sdk:dynamodb");
    assert_eq!(scheduled["resource"], "updateItem.waitForTaskToken");
    assert_eq!(scheduled["timeoutInSeconds"], 3600);
    // Not woken: the input's 30 s (0.3 s at this scale) end it.
    let started = std::time::Instant::now();
    let result = executor
        .run(&machine, "quiet", json!({"wait": 30}))
        .await
        .unwrap();
    assert_eq!(result.error.as_deref(), Some(STATES_TIMEOUT));
    assert!(started.elapsed() < Duration::from_secs(5));
    assert_eq!(result.history[2].details["timeoutInSeconds"], 30);
    // A path that selects no positive integer is a runtime error, not a wait without end.
    for (i, bad) in [json!({"wait": 0}), json!({"wait": "60"}), json!({})]
        .into_iter()
        .enumerate()
    {
        let result = executor
            .run(&machine, &format!("bad-{i}"), bad.clone())
            .await
            .unwrap();
        assert_eq!(result.error.as_deref(), Some("States.Runtime"), "{bad}");
    }
}
