//! Task states: both Lambda integrations, Retry timing, Catch, TimeoutSeconds, the context
//! object, and the execution-level controls (cancel, deadline, limits, live events).

use crate::common;

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::*;
use local_stepfunctions::{EventType, Executor, Options, Status, TaskError, TaskMap};
use serde_json::{json, Value};

fn retry_machine(retry: Value, catch: Value) -> Value {
    let caught = catch.as_array().is_some_and(|c| !c.is_empty());
    let mut machine = json!({
        "StartAt": "HelloWorld",
        "States": {
            "HelloWorld": {
                "Type": "Task",
                "Resource": FLAKY,
                "Parameters": {"retry.$": "$$.State.RetryCount", "entered.$": "$$.State.EnteredTime"},
                "Retry": retry,
                "Catch": catch,
                "End": true
            }
        }
    });
    if caught {
        machine["States"]["Z"] = json!({"Type": "Pass", "End": true});
    }
    machine
}

#[tokio::test]
async fn retries_back_off_by_the_rate_and_stop_at_max_delay() {
    // IntervalSeconds 1, BackoffRate 2, MaxDelaySeconds 3: waits of 1, 2, then 3 (not 4).
    let machine = load(retry_machine(
        json!([{
            "ErrorEquals": ["HandledError"],
            "IntervalSeconds": 1,
            "MaxAttempts": 3,
            "BackoffRate": 2.0,
            "MaxDelaySeconds": 3,
            "JitterStrategy": "NONE"
        }]),
        json!([{"ErrorEquals": ["States.ALL"], "Next": "Z"}]),
    ));
    let calls = Calls::default();
    let tasks = failing(
        calls.clone(),
        vec!["HandledError", "HandledError", "HandledError"],
        json!("done"),
    );
    let r = run_with(&machine, tasks, options(0.2), json!({})).await;
    assert_eq!(r.status, Status::Succeeded, "{r:?}");
    assert_eq!(r.output, Some(json!("done")));
    let retries: Vec<Value> = calls.inputs().iter().map(|i| i["retry"].clone()).collect();
    assert_eq!(retries, [json!(0), json!(1), json!(2), json!(3)]);
    // EnteredTime is the state's, not the attempt's.
    let entered: Vec<Value> = calls
        .inputs()
        .iter()
        .map(|i| i["entered"].clone())
        .collect();
    assert!(entered.iter().all(|e| *e == entered[0]));
    let gaps = calls.gaps();
    let ms = |d: Duration| d.as_millis();
    // At scale 0.2: 200, 400, 600 ms (an uncapped third wait would be 800 ms).
    assert!(ms(gaps[0]) >= 200 && ms(gaps[0]) < 380, "{gaps:?}");
    assert!(ms(gaps[1]) >= 400 && ms(gaps[1]) < 580, "{gaps:?}");
    assert!(
        ms(gaps[2]) >= 600 && ms(gaps[2]) < 780,
        "capped at 3 s: {gaps:?}"
    );
    // One state, four invocations: no new TaskStateEntered per retry.
    assert_eq!(r.count(EventType::TaskStateEntered), 1);
    assert_eq!(r.count(EventType::LambdaFunctionScheduled), 4);
    assert_eq!(r.count(EventType::LambdaFunctionFailed), 3);
}

#[tokio::test]
async fn retrier_attempts_count_across_its_error_names() {
    // The ASL specification's complex retry scenario: ErrorA, ErrorB (first retrier, waits 1
    // and 2), ErrorC (second retrier, waits 5); the next ErrorB finds the first retrier's
    // two attempts used up and goes to Catch. (The developer guide tells an older variant
    // with a fifth error; the specification and AWS count attempts per retrier.)
    let machine = load(retry_machine(
        json!([
            {"ErrorEquals": ["ErrorA", "ErrorB"], "IntervalSeconds": 1, "BackoffRate": 2.0, "MaxAttempts": 2},
            {"ErrorEquals": ["ErrorC"], "IntervalSeconds": 5}
        ]),
        json!([{"ErrorEquals": ["States.ALL"], "Next": "Z"}]),
    ));
    let calls = Calls::default();
    let tasks = failing(
        calls.clone(),
        vec!["ErrorA", "ErrorB", "ErrorC", "ErrorB", "ErrorB"],
        json!("never"),
    );
    let r = run_with(&machine, tasks, options(0.1), json!({})).await;
    assert_eq!(calls.count(), 4);
    assert_eq!(r.status, Status::Succeeded);
    assert_eq!(r.states_entered(), ["HelloWorld", "Z"]);
    assert_eq!(r.output.as_ref().unwrap()["Error"], "ErrorB");
    let gaps: Vec<u128> = calls.gaps().iter().map(Duration::as_millis).collect();
    // 100, 200, 500 ms.
    assert_eq!(gaps.len(), 3);
    for (gap, expected) in gaps.iter().zip([100u128, 200, 500]) {
        assert!(*gap >= expected && *gap < expected + 180, "{gaps:?}");
    }
}

#[tokio::test]
async fn full_jitter_waits_at_most_the_computed_delay() {
    let machine = load(retry_machine(
        json!([{
            "ErrorEquals": ["States.TaskFailed"],
            "IntervalSeconds": 2,
            "MaxAttempts": 4,
            "BackoffRate": 1.0,
            "JitterStrategy": "FULL"
        }]),
        json!([]),
    ));
    let calls = Calls::default();
    let tasks = failing(calls.clone(), vec!["E", "E", "E", "E"], json!(1));
    let r = run_with(&machine, tasks, options(0.1), json!({})).await;
    assert_eq!(r.status, Status::Succeeded);
    let gaps = calls.gaps();
    assert_eq!(gaps.len(), 4);
    assert!(gaps.iter().all(|g| g.as_millis() < 380), "{gaps:?}");
    // Jitter draws differ (a seeded source: not all equal to the full 200 ms).
    assert!(gaps.iter().any(|g| g.as_millis() < 190), "{gaps:?}");
}

#[tokio::test]
async fn max_attempts_zero_never_retries_and_uncaught_errors_fail_the_execution() {
    let machine = load(retry_machine(
        json!([
            {"ErrorEquals": ["Fatal"], "MaxAttempts": 0},
            {"ErrorEquals": ["States.ALL"]}
        ]),
        json!([]),
    ));
    let calls = Calls::default();
    let r = run(
        &machine,
        failing(calls.clone(), vec!["Fatal"], json!(1)),
        json!({}),
    )
    .await;
    assert_eq!(calls.count(), 1);
    assert_eq!(r.status, Status::Failed);
    assert_eq!(r.error.as_deref(), Some("Fatal"));
    assert_eq!(
        r.cause.as_deref(),
        Some(r#"{"errorType":"Fatal","errorMessage":"attempt 1 failed"}"#)
    );
    assert_eq!(
        types(&r)[types(&r).len() - 2..],
        [EventType::LambdaFunctionFailed, EventType::ExecutionFailed]
    );
}

#[tokio::test]
async fn catch_result_path_puts_the_error_beside_the_input() {
    let machine = load(retry_machine(
        json!([]),
        json!([
            {"ErrorEquals": ["java.lang.Exception"], "ResultPath": "$.error-info", "Next": "Z"},
            {"ErrorEquals": ["States.ALL"], "Next": "Z"}
        ]),
    ));
    let calls = Calls::default();
    let tasks = failing(calls.clone(), vec!["java.lang.Exception"], json!(1));
    let r = run(&machine, tasks, json!({"foo": "bar"})).await;
    assert_eq!(
        r.output,
        Some(json!({
            "foo": "bar",
            "error-info": {
                "Error": "java.lang.Exception",
                "Cause": "{\"errorType\":\"java.lang.Exception\",\"errorMessage\":\"attempt 1 failed\"}"
            }
        }))
    );
    // A caught failure still exits the state (with the catcher's output).
    let exited = r
        .history
        .iter()
        .find(|e| e.event_type == EventType::TaskStateExited)
        .unwrap();
    assert_eq!(exited.details["output"], r.output.clone().unwrap());
    // Without ResultPath the error output replaces the input.
    let calls = Calls::default();
    let tasks = failing(calls, vec!["Other"], json!(1));
    let r = run(&machine, tasks, json!({"foo": "bar"})).await;
    assert_eq!(r.output.unwrap()["Error"], "Other");
}

fn sleeper() -> TaskMap {
    TaskMap::new().with("sleep10", |_| async {
        tokio::time::sleep(Duration::from_secs(10)).await;
        Ok(json!("woke"))
    })
}

#[tokio::test]
async fn timeout_seconds_raises_states_timeout_which_catch_handles() {
    // Developer guide, "Handling a timeout using Catch".
    let machine = load(json!({
        "StartAt": "HelloWorld",
        "States": {
            "HelloWorld": {
                "Type": "Task",
                "Resource": "arn:aws:lambda:us-east-1:123456789012:function:sleep10",
                "TimeoutSeconds": 2,
                "Catch": [
                    {"ErrorEquals": ["States.TaskFailed"], "Next": "wrong"},
                    {"ErrorEquals": ["States.Timeout"], "Next": "fallback"}
                ],
                "End": true
            },
            "wrong": {"Type": "Fail", "Error": "TaskFailedCaughtATimeout"},
            "fallback": {"Type": "Pass", "Result": "Hello, AWS Step Functions!", "End": true}
        }
    }));
    let started = Instant::now();
    let r = run_with(&machine, sleeper(), options(0.05), json!({})).await;
    let elapsed = started.elapsed();
    assert_eq!(r.output, Some(json!("Hello, AWS Step Functions!")), "{r:?}");
    assert!(
        elapsed >= Duration::from_millis(100) && elapsed < Duration::from_secs(3),
        "{elapsed:?}"
    );
    let timed_out = r
        .history
        .iter()
        .find(|e| e.event_type == EventType::LambdaFunctionTimedOut)
        .unwrap();
    assert_eq!(timed_out.details, json!({"error": "States.Timeout"}));
    let scheduled = r
        .history
        .iter()
        .find(|e| e.event_type == EventType::LambdaFunctionScheduled)
        .unwrap();
    assert_eq!(scheduled.details["timeoutInSeconds"], 2);
    assert_eq!(
        scheduled.details["resource"],
        "arn:aws:lambda:us-east-1:123456789012:function:sleep10"
    );
}

#[tokio::test]
async fn an_invocation_timeout_can_stay_real_while_the_waits_scale() {
    // A handler taking 300 ms under `TimeoutSeconds: 2` at a time scale of 0.05: scaled, its
    // limit is 100 ms and it times out; left real (local runs, whose handlers wait on a real
    // minute's EvalAI budget), it ends. The Wait before it scales either way.
    let machine = load(json!({
        "StartAt": "Pause",
        "States": {
            "Pause": {"Type": "Wait", "Seconds": 20, "Next": "Work"},
            "Work": {
                "Type": "Task",
                "Resource": "arn:aws:lambda:us-east-1:123456789012:function:work",
                "TimeoutSeconds": 2,
                "End": true
            }
        }
    }));
    let work = || {
        TaskMap::new().with("work", |_| async {
            tokio::time::sleep(Duration::from_millis(300)).await;
            Ok(json!("done"))
        })
    };
    let scaled = run_with(&machine, work(), options(0.05), json!({})).await;
    assert_eq!(
        scaled.error.as_deref(),
        Some("States.Timeout"),
        "{scaled:?}"
    );
    let started = Instant::now();
    let real = Options {
        scale_invocation_timeouts: false,
        ..options(0.05)
    };
    let r = run_with(&machine, work(), real, json!({})).await;
    assert_eq!(r.output, Some(json!("done")), "{r:?}");
    assert!(
        started.elapsed() < Duration::from_secs(5),
        "the 20 s Wait scaled"
    );
}

#[tokio::test]
async fn a_timed_out_task_can_be_retried() {
    // Developer guide, "Handling a timeout using Retry": two retries, then the error stands.
    let machine = load(json!({
        "StartAt": "HelloWorld",
        "States": {"HelloWorld": {
            "Type": "Task",
            "Resource": "arn:aws:lambda:us-east-1:123456789012:function:sleep10",
            "TimeoutSeconds": 2,
            "Retry": [{"ErrorEquals": ["States.Timeout"], "IntervalSeconds": 1, "MaxAttempts": 2, "BackoffRate": 2.0}],
            "End": true
        }}
    }));
    let r = run_with(&machine, sleeper(), options(0.02), json!({})).await;
    assert_eq!(r.status, Status::Failed);
    assert_eq!(r.error.as_deref(), Some("States.Timeout"));
    assert_eq!(r.cause, None);
    assert_eq!(r.count(EventType::LambdaFunctionTimedOut), 3);
}

#[tokio::test]
async fn the_optimized_lambda_integration_wraps_the_payload_and_uses_task_events() {
    let machine = load(json!({
        "StartAt": "Invoke",
        "States": {"Invoke": {
            "Type": "Task",
            "Resource": "arn:aws:states:::lambda:invoke",
            "Parameters": {"FunctionName": "echo", "Payload": {"who.$": "$.who", "static": 1}},
            "ResultSelector": {"answer.$": "$.Payload", "code.$": "$.StatusCode"},
            "ResultPath": "$.result",
            "TimeoutSeconds": 30,
            "End": true
        }}
    }));
    let tasks = TaskMap::new().with("echo", |v: Value| async move { Ok(json!({"got": v})) });
    let r = run(&machine, tasks, json!({"who": "me"})).await;
    assert_eq!(
        r.output,
        Some(
            json!({"who": "me", "result": {"answer": {"got": {"who": "me", "static": 1}}, "code": 200}})
        )
    );
    assert_eq!(
        types(&r),
        [
            EventType::ExecutionStarted,
            EventType::TaskStateEntered,
            EventType::TaskScheduled,
            EventType::TaskStarted,
            EventType::TaskSucceeded,
            EventType::TaskStateExited,
            EventType::ExecutionSucceeded
        ]
    );
    let scheduled = &r.history[2].details;
    assert_eq!(scheduled["resourceType"], "lambda");
    assert_eq!(scheduled["resource"], "invoke");
    assert_eq!(scheduled["region"], "us-east-1");
    assert_eq!(scheduled["timeoutInSeconds"], 30);
    assert_eq!(
        scheduled["parameters"],
        json!({"FunctionName": "echo", "Payload": {"who": "me", "static": 1}})
    );
    assert_eq!(r.history[4].details["output"]["StatusCode"], 200);
}

#[tokio::test]
async fn a_missing_function_fails_like_lambda_and_a_panic_is_lambda_unknown() {
    let machine = load(json!({
        "StartAt": "T",
        "States": {"T": {
            "Type": "Task",
            "Resource": "arn:aws:states:::lambda:invoke",
            "Parameters": {"FunctionName": "arn:aws:lambda:us-east-1:123456789012:function:nobody"},
            "End": true
        }}
    }));
    let r = run(&machine, TaskMap::new(), json!({})).await;
    assert_eq!(r.error.as_deref(), Some("Lambda.ResourceNotFoundException"));
    assert_eq!(r.count(EventType::TaskFailed), 1);
    let panicking = TaskMap::new().with("nobody", |_| async {
        if true {
            panic!("handler bug");
        }
        Ok(Value::Null)
    });
    let r = run(&machine, panicking, json!({})).await;
    assert_eq!(r.error.as_deref(), Some("Lambda.Unknown"));
    assert!(r.cause.unwrap().contains("handler bug"));
}

#[tokio::test]
async fn the_context_object_describes_execution_state_and_machine() {
    let machine = load(json!({
        "StartAt": "Look",
        "States": {"Look": {
            "Type": "Pass",
            "Parameters": {
                "id.$": "$$.Execution.Id",
                "name.$": "$$.Execution.Name",
                "input.$": "$$.Execution.Input",
                "start.$": "$$.Execution.StartTime",
                "role.$": "$$.Execution.RoleArn",
                "state.$": "$$.State.Name",
                "entered.$": "$$.State.EnteredTime",
                "retries.$": "$$.State.RetryCount",
                "machine.$": "$$.StateMachine.Id",
                "machine_name.$": "$$.StateMachine.Name"
            },
            "End": true
        }}
    }))
    .with_name("submission");
    let r = run(&machine, TaskMap::new(), json!({"k": "v"})).await;
    let out = r.output.unwrap();
    assert_eq!(
        out["id"],
        "arn:aws:states:us-east-1:123456789012:execution:submission:test-run"
    );
    assert_eq!(out["name"], "test-run");
    assert_eq!(out["input"], json!({"k": "v"}));
    assert_eq!(out["state"], "Look");
    assert_eq!(out["retries"], 0);
    assert_eq!(
        out["machine"],
        "arn:aws:states:us-east-1:123456789012:stateMachine:submission"
    );
    assert_eq!(out["machine_name"], "submission");
    assert!(out["role"]
        .as_str()
        .unwrap()
        .starts_with("arn:aws:iam::123456789012:role/"));
    for field in ["start", "entered"] {
        let text = out[field].as_str().unwrap();
        assert_eq!(text.len(), "2019-03-26T20:14:13.192Z".len(), "{text}");
        assert!(text.ends_with('Z') && &text[10..11] == "T", "{text}");
    }
}

#[tokio::test]
async fn a_parameters_path_that_matches_nothing_is_states_runtime_and_not_caught() {
    let machine = load(json!({
        "StartAt": "T",
        "States": {
            "T": {
                "Type": "Task",
                "Resource": FLAKY,
                "Parameters": {"x.$": "$.missing"},
                "Retry": [{"ErrorEquals": ["States.ALL"]}],
                "Catch": [{"ErrorEquals": ["States.ALL"], "Next": "Z"}],
                "End": true
            },
            "Z": {"Type": "Succeed"}
        }
    }));
    let calls = Calls::default();
    let r = run(
        &machine,
        failing(calls.clone(), vec![], json!(1)),
        json!({}),
    )
    .await;
    assert_eq!(r.status, Status::Failed);
    assert_eq!(r.error.as_deref(), Some("States.Runtime"));
    assert!(r.cause.unwrap().contains("$.missing"));
    assert_eq!(calls.count(), 0);
}

#[tokio::test]
async fn input_output_result_selector_and_result_path_apply_in_order() {
    let machine = load(json!({
        "StartAt": "T",
        "States": {"T": {
            "Type": "Task",
            "Resource": FLAKY,
            "InputPath": "$.lambda",
            "Parameters": {"n.$": "$.n"},
            "ResultSelector": {"doubled.$": "$.value"},
            "ResultPath": "$.lambda.result",
            "OutputPath": "$.lambda",
            "End": true
        }}
    }));
    let tasks = TaskMap::new().with("flaky", |v: Value| async move {
        Ok(json!({"value": v["n"].as_i64().unwrap_or(0) * 2, "noise": true}))
    });
    let r = run(&machine, tasks, json!({"lambda": {"n": 21}, "other": 1})).await;
    assert_eq!(r.output, Some(json!({"n": 21, "result": {"doubled": 42}})));
}

#[tokio::test]
async fn cancel_aborts_a_running_execution() {
    let machine = load(json!({
        "StartAt": "Long",
        "States": {"Long": {"Type": "Wait", "Seconds": 3600, "End": true}}
    }));
    let executor = Executor::new(TaskMap::new(), options(1.0)).unwrap();
    let execution = executor.start(&machine, "to-cancel", json!({})).unwrap();
    let mut events = execution.events();
    // Wait until the Wait state is entered, then cancel.
    let entered = tokio::time::timeout(BOUND, async {
        while let Some(e) = events.next().await {
            if e.event_type == EventType::WaitStateEntered {
                return true;
            }
        }
        false
    })
    .await
    .unwrap();
    assert!(entered);
    execution.cancel();
    let r = tokio::time::timeout(BOUND, execution.wait()).await.unwrap();
    assert_eq!(r.status, Status::Aborted);
    assert_eq!(
        r.history.last().unwrap().event_type,
        EventType::ExecutionAborted
    );
    // The stream ends after the final event.
    let rest = tokio::time::timeout(BOUND, async {
        let mut rest = Vec::new();
        while let Some(e) = events.next().await {
            rest.push(e.event_type);
        }
        rest
    })
    .await
    .unwrap();
    assert_eq!(rest, [EventType::ExecutionAborted]);
}

#[tokio::test]
async fn the_deadline_and_the_definition_timeout_end_an_execution_timed_out() {
    let waiting = json!({
        "StartAt": "Long",
        "States": {"Long": {"Type": "Wait", "Seconds": 3600, "End": true}}
    });
    let deadline = Options {
        deadline: Some(Duration::from_millis(50)),
        ..options(1.0)
    };
    let r = run_with(&load(waiting.clone()), TaskMap::new(), deadline, json!({})).await;
    assert_eq!(r.status, Status::TimedOut);
    assert_eq!(r.error.as_deref(), Some("States.Timeout"));
    assert_eq!(
        r.history.last().unwrap().event_type,
        EventType::ExecutionTimedOut
    );
    let mut own = waiting;
    own["TimeoutSeconds"] = json!(5);
    let started = Instant::now();
    let r = run_with(&load(own), TaskMap::new(), options(0.01), json!({})).await;
    assert_eq!(r.status, Status::TimedOut);
    assert!(started.elapsed() >= Duration::from_millis(50));
}

#[tokio::test]
async fn an_endless_loop_stops_at_the_history_limit() {
    let machine = load(json!({
        "StartAt": "Spin",
        "States": {
            "Spin": {"Type": "Pass", "Next": "Again?"},
            "Again?": {"Type": "Choice", "Choices": [{"Variable": "$.stop", "IsPresent": true, "Next": "Done"}], "Default": "Spin"},
            "Done": {"Type": "Succeed"}
        }
    }));
    let limit = Options {
        max_history_events: 101,
        ..options(0.01)
    };
    let r = run_with(&machine, TaskMap::new(), limit, json!({})).await;
    assert_eq!(r.status, Status::Failed);
    assert_eq!(r.error.as_deref(), Some("States.Runtime"));
    assert_eq!(r.history.len(), 101);
    assert_eq!(
        r.history.last().unwrap().event_type,
        EventType::ExecutionFailed
    );
}

#[tokio::test]
async fn a_payload_over_the_quota_is_data_limit_exceeded_and_not_caught() {
    let machine = load(json!({
        "StartAt": "T",
        "States": {
            "T": {
                "Type": "Task",
                "Resource": FLAKY,
                "Catch": [{"ErrorEquals": ["States.ALL"], "Next": "Z"}],
                "End": true
            },
            "Z": {"Type": "Succeed"}
        }
    }));
    let calls = Calls::default();
    let big = json!("x".repeat(2_000));
    let small = Options {
        max_payload_bytes: 1_000,
        ..options(0.01)
    };
    let r = run_with(&machine, failing(calls, vec![], big), small, json!({})).await;
    assert_eq!(r.error.as_deref(), Some("States.DataLimitExceeded"));
    let executor = Executor::new(
        TaskMap::new(),
        Options {
            max_payload_bytes: 10,
            ..options(1.0)
        },
    )
    .unwrap();
    let err = executor
        .start(&machine, "big", json!({"too": "large input"}))
        .unwrap_err();
    assert_eq!(err.name(), "InvalidExecutionInput");
}

#[tokio::test]
async fn events_are_chained_streamed_and_reported_to_the_callback() {
    let machine = load(json!({
        "StartAt": "A",
        "States": {
            "A": {"Type": "Pass", "Next": "B"},
            "B": {"Type": "Task", "Resource": FLAKY, "End": true}
        }
    }));
    let seen = Arc::new(AtomicUsize::new(0));
    let counter = seen.clone();
    let options = Options {
        on_event: Some(Arc::new(move |_| {
            counter.fetch_add(1, Ordering::SeqCst);
        })),
        ..options(0.01)
    };
    let executor = Executor::new(failing(Calls::default(), vec![], json!(1)), options).unwrap();
    let execution = executor.start(&machine, "watched", json!({})).unwrap();
    let mut stream = execution.events();
    let streamed = tokio::time::timeout(BOUND, async {
        let mut all = Vec::new();
        while let Some(e) = stream.next().await {
            all.push(e);
        }
        all
    })
    .await
    .unwrap();
    let r = tokio::time::timeout(BOUND, execution.wait()).await.unwrap();
    assert_eq!(streamed, r.history);
    assert_eq!(seen.load(Ordering::SeqCst), r.history.len());
    let ids: Vec<u64> = r.history.iter().map(|e| e.id).collect();
    assert_eq!(ids, (1..=r.history.len() as u64).collect::<Vec<_>>());
    let previous: Vec<u64> = r.history.iter().map(|e| e.previous_event_id).collect();
    // As AWS links them: the first state follows no event, the rest their predecessor.
    assert_eq!(previous, [0, 0, 2, 3, 4, 5, 6, 7, 8]);
    let json = r.history[1].to_aws_json();
    assert_eq!(json["type"], "PassStateEntered");
    assert_eq!(json["stateEnteredEventDetails"]["name"], "A");
    assert_eq!(json["stateEnteredEventDetails"]["input"], "{}");
}

#[tokio::test]
async fn invalid_names_and_options_are_refused() {
    let machine = load(json!({"StartAt": "S", "States": {"S": {"Type": "Succeed"}}}));
    let executor = Executor::new(TaskMap::new(), options(1.0)).unwrap();
    for bad in ["", "has space", "a/b", "x:y", &"n".repeat(81)] {
        let err = executor.start(&machine, bad, json!({})).unwrap_err();
        assert_eq!(err.name(), "InvalidName", "{bad:?}");
    }
    for scale in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        let err = Executor::new(
            TaskMap::new(),
            Options {
                time_scale: scale,
                ..Options::default()
            },
        )
        .unwrap_err();
        assert_eq!(err.name(), "InvalidTimeScale");
    }
    let err = Executor::new(
        TaskMap::new(),
        Options {
            max_history_events: 0,
            ..Options::default()
        },
    )
    .unwrap_err();
    assert_eq!(err.name(), "ZeroLimit");
    let _ = TaskError::new("x", "y");
}

#[test]
fn starting_outside_a_tokio_runtime_is_an_error_not_a_panic() {
    let machine = load(json!({"StartAt": "S", "States": {"S": {"Type": "Succeed"}}}));
    let executor = Executor::new(TaskMap::new(), Options::default()).unwrap();
    let err = executor
        .start(&machine, "no-runtime", json!({}))
        .unwrap_err();
    assert_eq!(err.name(), "NoRuntime");
}
