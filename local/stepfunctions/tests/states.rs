//! Each state type against the behaviour the Step Functions developer guide documents.

use crate::common;

use std::time::{Duration, Instant};

use common::*;
use local_stepfunctions::{EventType, Status, TaskError, TaskMap};
use serde_json::{json, Value};

#[tokio::test]
async fn pass_places_its_result_with_result_path() {
    // Developer guide, Pass state example.
    let machine = load(json!({
        "StartAt": "No-op",
        "States": {
            "No-op": {
                "Type": "Pass",
                "Result": {"x-datum": 0.381018, "y-datum": 622.2269926397355},
                "ResultPath": "$.coords",
                "End": true
            }
        }
    }));
    let result = run(&machine, TaskMap::new(), json!({"georefOf": "Home"})).await;
    assert_eq!(result.status, Status::Succeeded);
    assert_eq!(
        result.output,
        Some(json!({
            "georefOf": "Home",
            "coords": {"x-datum": 0.381018, "y-datum": 622.2269926397355}
        }))
    );
    assert_eq!(
        types(&result),
        [
            EventType::ExecutionStarted,
            EventType::PassStateEntered,
            EventType::PassStateExited,
            EventType::ExecutionSucceeded
        ]
    );
}

#[tokio::test]
async fn pass_without_result_passes_its_effective_input() {
    let machine = load(json!({
        "StartAt": "P",
        "States": {"P": {
            "Type": "Pass",
            "InputPath": "$.a",
            "Parameters": {"copy.$": "$.b", "name.$": "$$.State.Name"},
            "ResultPath": "$.a.params",
            "OutputPath": "$.a",
            "End": true
        }}
    }));
    let result = run(&machine, TaskMap::new(), json!({"a": {"b": 1}})).await;
    // ResultPath applies to the raw input, OutputPath after it.
    assert_eq!(
        result.output,
        Some(json!({"b": 1, "params": {"copy": 1, "name": "P"}}))
    );
}

fn choice_machine() -> Value {
    // Developer guide, Choice state example (Tasks replaced by Pass states naming themselves).
    let leaf = |name: &str| json!({"Type": "Pass", "Result": name, "End": true});
    json!({
        "StartAt": "ChoiceStateX",
        "States": {
            "ChoiceStateX": {
                "Type": "Choice",
                "Choices": [
                    {"Not": {"Variable": "$.type", "StringEquals": "Private"}, "Next": "Public"},
                    {"Variable": "$.value", "NumericEquals": 0, "Next": "ValueIsZero"},
                    {"And": [
                        {"Variable": "$.value", "NumericGreaterThanEquals": 20},
                        {"Variable": "$.value", "NumericLessThan": 30}
                    ], "Next": "ValueInTwenties"}
                ],
                "Default": "DefaultState"
            },
            "Public": leaf("Public"),
            "ValueIsZero": leaf("ValueIsZero"),
            "ValueInTwenties": leaf("ValueInTwenties"),
            "DefaultState": {"Type": "Fail", "Cause": "No Matches!"}
        }
    })
}

#[tokio::test]
async fn choice_takes_the_first_matching_rule() {
    let machine = load(choice_machine());
    let go = |input: Value| {
        let machine = machine.clone();
        async move { run(&machine, TaskMap::new(), input).await }
    };
    let r = go(json!({"type": "Private", "value": 22})).await;
    assert_eq!(r.output, Some(json!("ValueInTwenties")));
    assert_eq!(r.states_entered(), ["ChoiceStateX", "ValueInTwenties"]);
    assert_eq!(r.count(EventType::ChoiceStateExited), 1);
    assert_eq!(
        go(json!({"type": "Public", "value": 22})).await.output,
        Some(json!("Public"))
    );
    assert_eq!(
        go(json!({"type": "Private", "value": 0})).await.output,
        Some(json!("ValueIsZero"))
    );
    let default = go(json!({"type": "Private", "value": 99})).await;
    assert_eq!(default.status, Status::Failed);
    assert_eq!(default.error, None);
    assert_eq!(default.cause.as_deref(), Some("No Matches!"));
    assert_eq!(
        default.history.last().unwrap().event_type,
        EventType::ExecutionFailed
    );
    assert_eq!(default.count(EventType::FailStateEntered), 1);
}

#[tokio::test]
async fn a_choice_variable_that_is_missing_fails_the_execution_with_states_runtime() {
    // "If the state input doesn't contain the $.type field, the execution fails".
    let machine = load(choice_machine());
    let r = run(&machine, TaskMap::new(), json!({"value": 22})).await;
    assert_eq!(r.status, Status::Failed);
    assert_eq!(r.error.as_deref(), Some("States.Runtime"));
    assert!(r.cause.unwrap().contains("'$.type'"));
}

#[tokio::test]
async fn states_all_does_not_catch_states_runtime() {
    let machine = load(json!({
        "StartAt": "Guard",
        "States": {
            "Guard": {
                "Type": "Parallel",
                "Branches": [{"StartAt": "C", "States": {"C": {
                    "Type": "Choice",
                    "Choices": [{"Variable": "$.missing", "BooleanEquals": true, "Next": "T"}],
                    "Default": "T"
                }, "T": {"Type": "Succeed"}}}],
                "Catch": [{"ErrorEquals": ["States.ALL"], "Next": "Caught"}],
                "Retry": [{"ErrorEquals": ["States.ALL"], "MaxAttempts": 5}],
                "End": true
            },
            "Caught": {"Type": "Succeed"}
        }
    }));
    let r = run(&machine, TaskMap::new(), json!({})).await;
    assert_eq!(r.status, Status::Failed);
    assert_eq!(r.error.as_deref(), Some("States.Runtime"));
    assert!(!r.states_entered().contains(&"Caught"));
    assert_eq!(r.count(EventType::ParallelStateStarted), 1, "never retried");
}

#[tokio::test]
async fn a_choice_without_match_or_default_fails_with_no_choice_matched() {
    let machine = load(json!({
        "StartAt": "C",
        "States": {
            "C": {"Type": "Choice", "Choices": [{"Variable": "$.a", "IsNull": true, "Next": "S"}]},
            "S": {"Type": "Succeed"}
        }
    }));
    let r = run(&machine, TaskMap::new(), json!({"a": 1})).await;
    assert_eq!(r.error.as_deref(), Some("States.NoChoiceMatched"));
}

#[tokio::test]
async fn choice_rules_cover_strings_timestamps_matches_and_paths() {
    let machine = load(json!({
        "StartAt": "C",
        "States": {
            "C": {
                "Type": "Choice",
                "InputPath": "$.in",
                "OutputPath": "$.keep",
                "Choices": [
                    {"Variable": "$.file", "StringMatches": "log-*.txt", "Next": "Log"},
                    {"And": [
                        {"Variable": "$.when", "IsTimestamp": true},
                        {"Variable": "$.when", "TimestampGreaterThanPath": "$.since"}
                    ], "Next": "Recent"},
                    {"Variable": "$$.Execution.Name", "StringEquals": "test-run", "Next": "Named"}
                ]
            },
            "Log": {"Type": "Pass", "Result": "Log", "ResultPath": "$.went", "End": true},
            "Recent": {"Type": "Pass", "Result": "Recent", "ResultPath": "$.went", "End": true},
            "Named": {"Type": "Pass", "Result": "Named", "ResultPath": "$.went", "End": true}
        }
    }));
    let go = |input: Value| {
        let machine = machine.clone();
        async move {
            run(&machine, TaskMap::new(), json!({"in": input}))
                .await
                .output
                .unwrap()
        }
    };
    assert_eq!(
        go(json!({"file": "log-1.txt", "keep": {}})).await,
        json!({"went": "Log"})
    );
    assert_eq!(
        go(json!({"file": "x", "when": "2024-01-02T00:00:00Z", "since": "2024-01-01T00:00:00Z", "keep": {}})).await,
        json!({"went": "Recent"})
    );
    assert_eq!(
        go(json!({"file": "x", "when": "soon", "since": "2024-01-01T00:00:00Z", "keep": {"k": 1}}))
            .await,
        json!({"k": 1, "went": "Named"})
    );
}

#[tokio::test]
async fn wait_seconds_are_scaled() {
    let machine = load(json!({
        "StartAt": "wait_ten_seconds",
        "States": {"wait_ten_seconds": {"Type": "Wait", "Seconds": 10, "End": true}}
    }));
    let started = Instant::now();
    let r = run_with(&machine, TaskMap::new(), options(0.02), json!({"a": 1})).await;
    let elapsed = started.elapsed();
    assert_eq!(r.output, Some(json!({"a": 1})));
    assert!(elapsed >= Duration::from_millis(200), "{elapsed:?}");
    assert!(elapsed < Duration::from_secs(5), "{elapsed:?}");
    assert_eq!(
        types(&r)[1..3],
        [EventType::WaitStateEntered, EventType::WaitStateExited]
    );
}

#[tokio::test]
async fn wait_reads_seconds_and_timestamps_from_the_input() {
    let machine = load(json!({
        "StartAt": "ByPath",
        "States": {
            "ByPath": {"Type": "Wait", "SecondsPath": "$.delay", "Next": "Past"},
            "Past": {"Type": "Wait", "Timestamp": "2016-03-14T01:59:00Z", "Next": "Until"},
            "Until": {"Type": "Wait", "TimestampPath": "$.expirydate", "End": true}
        }
    }));
    let until = time::OffsetDateTime::now_utc() + time::Duration::seconds(10);
    let until = until
        .format(&time::format_description::well_known::Rfc3339)
        .unwrap();
    let started = Instant::now();
    let r = run_with(
        &machine,
        TaskMap::new(),
        options(0.02),
        json!({"delay": 10, "expirydate": until}),
    )
    .await;
    let elapsed = started.elapsed();
    assert_eq!(r.status, Status::Succeeded, "{r:?}");
    // 10 s by path and about 10 s until the timestamp, both at 0.02: about 0.4 s.
    assert!(elapsed >= Duration::from_millis(350), "{elapsed:?}");
    assert!(elapsed < Duration::from_secs(5), "{elapsed:?}");
}

#[tokio::test]
async fn a_seconds_path_that_is_not_a_count_of_seconds_is_a_runtime_error() {
    let machine = load(json!({
        "StartAt": "W",
        "States": {"W": {"Type": "Wait", "SecondsPath": "$.delay", "End": true}}
    }));
    for bad in [
        json!({"delay": -1}),
        json!({"delay": "10"}),
        json!({"delay": 1.5}),
        json!({}),
    ] {
        let r = run(&machine, TaskMap::new(), bad.clone()).await;
        assert_eq!(r.error.as_deref(), Some("States.Runtime"), "{bad}");
    }
}

fn math_tasks() -> TaskMap {
    TaskMap::new()
        .with("Add", |v: Value| async move {
            Ok(json!(
                v[0].as_i64().unwrap_or(0) + v[1].as_i64().unwrap_or(0)
            ))
        })
        .with("Subtract", |v: Value| async move {
            Ok(json!(
                v[0].as_i64().unwrap_or(0) - v[1].as_i64().unwrap_or(0)
            ))
        })
}

#[tokio::test]
async fn parallel_outputs_one_element_per_branch_in_order() {
    // Developer guide, Parallel state input and output processing: [3, 2] gives [5, 1].
    let machine = load(json!({
        "StartAt": "FunWithMath",
        "States": {
            "FunWithMath": {
                "Type": "Parallel",
                "End": true,
                "Branches": [
                    {"StartAt": "Add", "States": {"Add": {
                        "Type": "Task",
                        "Resource": "arn:aws:lambda:us-east-1:123456789012:function:Add",
                        "End": true
                    }}},
                    {"StartAt": "Subtract", "States": {"Subtract": {
                        "Type": "Task",
                        "Resource": "arn:aws:lambda:us-east-1:123456789012:function:Subtract",
                        "End": true
                    }}}
                ]
            }
        }
    }));
    let r = run(&machine, math_tasks(), json!([3, 2])).await;
    assert_eq!(r.output, Some(json!([5, 1])));
    assert_eq!(r.count(EventType::ParallelStateStarted), 1);
    assert_eq!(r.count(EventType::ParallelStateSucceeded), 1);
    assert_eq!(r.count(EventType::LambdaFunctionSucceeded), 2);
    // Each branch's chain starts at ParallelStateStarted.
    let started = r
        .history
        .iter()
        .find(|e| e.event_type == EventType::ParallelStateStarted)
        .unwrap()
        .id;
    let branch_starts: Vec<u64> = r
        .history
        .iter()
        .filter(|e| e.event_type == EventType::TaskStateEntered)
        .map(|e| e.previous_event_id)
        .collect();
    assert_eq!(branch_starts, [started, started]);
    assert_eq!(
        r.history.last().unwrap().event_type,
        EventType::ExecutionSucceeded
    );
}

#[tokio::test]
async fn a_failing_branch_fails_the_parallel_state_and_its_catcher_keeps_the_input() {
    // Developer guide, "Use ResultPath to include both error and input in a Catch".
    let machine = load(json!({
        "StartAt": "Work",
        "States": {
            "Work": {
                "Type": "Parallel",
                "Branches": [
                    {"StartAt": "Boom", "States": {"Boom": {"Type": "Fail", "Error": "Error here"}}},
                    {"StartAt": "Slow", "States": {"Slow": {"Type": "Wait", "Seconds": 1000, "End": true}}}
                ],
                "Catch": [{"ErrorEquals": ["States.ALL"], "Next": "NextTask", "ResultPath": "$.error"}],
                "End": true
            },
            "NextTask": {"Type": "Pass", "End": true}
        }
    }));
    let started = Instant::now();
    let r = run(&machine, TaskMap::new(), json!({"foo": "bar"})).await;
    assert_eq!(
        r.output,
        Some(json!({"foo": "bar", "error": {"Error": "Error here"}}))
    );
    assert!(
        started.elapsed() < Duration::from_secs(1),
        "the slow branch was stopped"
    );
    assert_eq!(r.count(EventType::ParallelStateFailed), 1);
    assert_eq!(r.count(EventType::ParallelStateExited), 1);
}

fn shipping_input() -> Value {
    json!({
        "ship-date": "2016-03-14T01:59:00Z",
        "detail": {
            "delivery-partner": "UQS",
            "shipped": [
                {"prod": "R31", "dest-code": 9511, "quantity": 1344},
                {"prod": "S39", "dest-code": 9511, "quantity": 40},
                {"prod": "R31", "dest-code": 9833, "quantity": 12},
                {"prod": "R40", "dest-code": 9860, "quantity": 887},
                {"prod": "R40", "dest-code": 9511, "quantity": 1220}
            ]
        }
    })
}

fn ship_val(calls: Calls) -> TaskMap {
    TaskMap::new().with("ship-val", move |input: Value| {
        let calls = calls.clone();
        async move {
            calls.record(&input);
            Ok(json!({"validated": input}))
        }
    })
}

#[tokio::test]
async fn map_runs_the_iterator_per_item_with_parameters() {
    // Developer guide, Map state example with Parameters.
    for selector in ["Parameters", "ItemSelector"] {
        let machine = load(json!({
            "StartAt": "Validate-All",
            "States": {
                "Validate-All": {
                    "Type": "Map",
                    "InputPath": "$.detail",
                    "ItemsPath": "$.shipped",
                    "MaxConcurrency": 0,
                    "ResultPath": "$.detail.shipped",
                    selector: {
                        "parcel.$": "$$.Map.Item.Value",
                        "courier.$": "$.delivery-partner",
                        "index.$": "$$.Map.Item.Index"
                    },
                    "Iterator": {
                        "StartAt": "Validate",
                        "States": {"Validate": {
                            "Type": "Task",
                            "Resource": "arn:aws:lambda:us-east-1:123456789012:function:ship-val",
                            "End": true
                        }}
                    },
                    "End": true
                }
            }
        }));
        let calls = Calls::default();
        let r = run(&machine, ship_val(calls.clone()), shipping_input()).await;
        assert_eq!(r.status, Status::Succeeded, "{r:?}");
        let output = r.output.clone().unwrap();
        let shipped = output["detail"]["shipped"].as_array().unwrap();
        assert_eq!(shipped.len(), 5);
        assert_eq!(
            shipped[0],
            json!({"validated": {
                "parcel": {"prod": "R31", "dest-code": 9511, "quantity": 1344},
                "courier": "UQS",
                "index": 0
            }})
        );
        assert_eq!(shipped[4]["validated"]["index"], 4);
        // ResultPath "$.detail.shipped" overwrites the array inside the raw input.
        assert_eq!(output["ship-date"], "2016-03-14T01:59:00Z");
        assert_eq!(output["detail"]["delivery-partner"], "UQS");
        assert_eq!(r.count(EventType::MapStateStarted), 1);
        assert_eq!(r.count(EventType::MapIterationStarted), 5);
        assert_eq!(r.count(EventType::MapIterationSucceeded), 5);
        assert_eq!(r.history[2].details["length"], 5);
    }
}

#[tokio::test]
async fn map_with_max_concurrency_one_runs_items_in_order() {
    let machine = load(json!({
        "StartAt": "M",
        "States": {"M": {
            "Type": "Map",
            "ItemsPath": "$.detail.shipped",
            "MaxConcurrency": 1,
            "ItemProcessor": {
                "ProcessorConfig": {"Mode": "INLINE"},
                "StartAt": "Validate",
                "States": {"Validate": {
                    "Type": "Task",
                    "Resource": "arn:aws:lambda:us-east-1:123456789012:function:ship-val",
                    "End": true
                }}
            },
            "End": true
        }}
    }));
    let calls = Calls::default();
    let r = run(&machine, ship_val(calls.clone()), shipping_input()).await;
    assert_eq!(r.status, Status::Succeeded);
    let quantities: Vec<Value> = calls
        .inputs()
        .iter()
        .map(|i| i["quantity"].clone())
        .collect();
    assert_eq!(
        quantities,
        [json!(1344), json!(40), json!(12), json!(887), json!(1220)]
    );
    assert_eq!(r.output.unwrap().as_array().unwrap().len(), 5);
}

#[tokio::test]
async fn a_failing_iteration_fails_the_map_and_aborts_the_others() {
    let machine = load(json!({
        "StartAt": "M",
        "States": {
            "M": {
                "Type": "Map",
                "Iterator": {"StartAt": "V", "States": {"V": {
                    "Type": "Task",
                    "Resource": "arn:aws:lambda:us-east-1:123456789012:function:check",
                    "End": true
                }}},
                "Catch": [{"ErrorEquals": ["BadItem"], "ResultPath": "$.failure", "Next": "Report"}],
                "ResultPath": "$.checked",
                "ItemsPath": "$.items",
                "End": true
            },
            "Report": {"Type": "Pass", "End": true}
        }
    }));
    let tasks = TaskMap::new().with("check", |item: Value| async move {
        if item == json!("bad") {
            Err(TaskError::lambda("BadItem", "item is bad"))
        } else {
            tokio::time::sleep(Duration::from_secs(60)).await;
            Ok(item)
        }
    });
    let started = Instant::now();
    let r = run(&machine, tasks, json!({"items": ["slow", "bad", "slow"]})).await;
    assert!(started.elapsed() < Duration::from_secs(5));
    assert_eq!(r.status, Status::Succeeded);
    let output = r.output.clone().unwrap();
    assert_eq!(output["failure"]["Error"], "BadItem");
    assert_eq!(r.count(EventType::MapIterationFailed), 1);
    assert_eq!(r.count(EventType::MapIterationAborted), 2);
    assert_eq!(r.count(EventType::MapStateFailed), 1);
    assert_eq!(r.count(EventType::MapStateExited), 1);
}

#[tokio::test]
async fn an_items_path_that_is_not_an_array_is_a_runtime_error() {
    let machine = load(json!({
        "StartAt": "M",
        "States": {"M": {
            "Type": "Map", "ItemsPath": "$.items",
            "Iterator": {"StartAt": "P", "States": {"P": {"Type": "Pass", "End": true}}},
            "End": true
        }}
    }));
    let r = run(&machine, TaskMap::new(), json!({"items": {"a": 1}})).await;
    assert_eq!(r.error.as_deref(), Some("States.Runtime"));
    let r = run(&machine, TaskMap::new(), json!({"items": []})).await;
    assert_eq!(r.output, Some(json!([])));
}

#[tokio::test]
async fn fail_reads_error_and_cause_from_paths_and_intrinsics() {
    let machine = load(json!({
        "StartAt": "F",
        "States": {"F": {
            "Type": "Fail",
            "ErrorPath": "$.Error",
            "CausePath": "States.Format('This is a custom error message for {}, caused by {}.', $.Error, $.Cause)"
        }}
    }));
    let r = run(
        &machine,
        TaskMap::new(),
        json!({"Error": "MyError", "Cause": "a bug"}),
    )
    .await;
    assert_eq!(r.status, Status::Failed);
    assert_eq!(r.error.as_deref(), Some("MyError"));
    assert_eq!(
        r.cause.as_deref(),
        Some("This is a custom error message for MyError, caused by a bug.")
    );
    let last = r.history.last().unwrap();
    assert_eq!(last.event_type, EventType::ExecutionFailed);
    assert_eq!(last.details["error"], "MyError");
    let r = run(&machine, TaskMap::new(), json!({"Error": 3, "Cause": "x"})).await;
    assert_eq!(r.error.as_deref(), Some("States.Runtime"));
}
