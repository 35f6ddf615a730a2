//! Versions and aliases: an execution runs the version it started on to its end, whatever the
//! alias names meanwhile; a version names its own functions' versions.

use crate::common;

use std::collections::HashMap;

use common::*;
use local_stepfunctions::{Executor, StateMachine, Status, TaskMap};
use serde_json::{json, Value};
use tokio::sync::watch;

/// A Task that waits for `release`, then asks `Work` (whose version answers which it is).
fn machine(version: u32) -> StateMachine {
    let definition = json!({
        "StartAt": "Hold",
        "States": {
            "Hold": {"Type": "Task", "Resource": "${HoldFunctionArn}", "ResultPath": null, "Next": "Work"},
            "Work": {"Type": "Task", "Resource": "${WorkFunctionArn}", "End": true}
        }
    });
    let function =
        |name: &str| format!("arn:aws:lambda:us-east-1:123456789012:function:{name}:{version}");
    let substitutions = HashMap::from([
        ("HoldFunctionArn".to_owned(), function("hold")),
        ("WorkFunctionArn".to_owned(), function("work")),
    ]);
    StateMachine::load(&definition, &substitutions)
        .unwrap()
        .with_name("submission")
}

#[tokio::test]
async fn an_execution_keeps_its_version_when_the_alias_moves() {
    // The Holds wait until the deploy is done.
    let (release, gate) = watch::channel(false);
    let work = |v: u32| move |_: Value| async move { Ok(json!({"ran": v})) };
    let tasks = TaskMap::new()
        .with("hold", move |_| {
            let mut gate = gate.clone();
            async move {
                let _ = gate.wait_for(|open| *open).await;
                Ok(json!({}))
            }
        })
        .with(
            "arn:aws:lambda:us-east-1:123456789012:function:work:1",
            work(1),
        )
        .with(
            "arn:aws:lambda:us-east-1:123456789012:function:work:2",
            work(2),
        );
    let executor = Executor::new(tasks, options(0.01)).unwrap();
    let v1 = executor.publish(&machine(1));
    let live = executor.point_alias("live", &v1).unwrap();
    let first = executor.start_arn(&live, "first", json!({})).unwrap();

    // A deploy while it waits: version 2, the alias moved to it.
    let v2 = executor.publish(&machine(2));
    executor.point_alias("live", &v2).unwrap();
    assert_eq!(executor.alias_target(&live).as_deref(), Some(v2.as_str()));
    let second = executor.start_arn(&live, "second", json!({})).unwrap();

    let described = executor.describe(first.arn()).unwrap();
    assert_eq!(described.version_arn.as_deref(), Some(v1.as_str()));
    assert_eq!(described.alias_arn.as_deref(), Some(live.as_str()));
    release.send_replace(true);
    let (first, second) = (first.wait().await, second.wait().await);
    assert_eq!(first.status, Status::Succeeded);
    assert_eq!(
        first.output,
        Some(json!({"ran": 1})),
        "the first kept version 1's functions"
    );
    assert_eq!(second.output, Some(json!({"ran": 2})));
    assert_eq!(
        first.history[0].details["stateMachineVersionArn"],
        json!(v1),
        "ExecutionStarted names the version, as AWS's does"
    );
    assert_eq!(
        second.history[0].details["stateMachineAliasArn"],
        json!(live)
    );

    // Rolling back is the alias moved back; a version's ARN starts that version.
    executor.point_alias("live", &v1).unwrap();
    let third = executor
        .start_arn(&live, "third", json!({}))
        .unwrap()
        .wait()
        .await;
    assert_eq!(third.output, Some(json!({"ran": 1})));
    let fourth = executor.start_execution(&v2, "fourth", json!({})).unwrap();
    let fourth = executor
        .wait_for(fourth["ExecutionArn"].as_str().unwrap())
        .await
        .unwrap();
    assert_eq!(fourth.output, Some(json!({"ran": 2})));
    assert!(executor
        .start_execution(&format!("{live}-gone"), "fifth", json!({}))
        .is_err());
}
