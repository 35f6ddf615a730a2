//! The definition we deploy, `statemachine/submission.asl.json`, run end to end with fake
//! task handlers: the paths a submission takes and the history it leaves.

mod common;

use std::collections::HashMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use common::{options, run_with, Calls};
use local_stepfunctions::{
    EventType, ExecutionResult, Executor, StateMachine, Status, TaskError, TaskMap,
};
use serde_json::{json, Value};

const DEFINITION: &str = include_str!("../../../statemachine/submission.asl.json");

fn substitutions() -> HashMap<String, String> {
    ["Intake", "Launch", "Monitor", "Finalize"]
        .into_iter()
        .map(|stage| {
            (
                format!("{stage}FunctionArn"),
                format!(
                    "arn:aws:lambda:us-east-1:123456789012:function:lb-{}",
                    stage.to_lowercase()
                ),
            )
        })
        .chain([("WakeTable".to_owned(), "leaderboard-wakes".to_owned())])
        .collect()
}

fn machine() -> StateMachine {
    let definition: Value = serde_json::from_str(DEFINITION).unwrap();
    StateMachine::load(&definition, &substitutions())
        .expect("the deployed definition loads")
        .with_name("submission")
}

fn message() -> Value {
    json!({"challenge_pk": 1, "phase_pk": 1234, "submission_pk": 99, "submitted_image_uri": "repo/agent:1"})
}

/// What the EventBridge Pipe starts the execution with: its batch, a JSON array even for one.
fn pipe_batch() -> Value {
    json!([message()])
}

/// How the fake stages behave.
#[derive(Clone)]
struct Script {
    action: &'static str,
    /// Errors Launch returns before succeeding.
    launch_errors: Vec<&'static str>,
    /// Monitor rounds that report `running` before `done`.
    running_rounds: usize,
    /// Finalize always fails with this error.
    finalize_error: Option<&'static str>,
}

impl Default for Script {
    fn default() -> Self {
        Script {
            action: "run",
            launch_errors: vec![],
            running_rounds: 2,
            finalize_error: None,
        }
    }
}

struct Stages {
    intake: Calls,
    launch: Calls,
    monitor: Calls,
    finalize: Calls,
}

fn tasks(script: Script) -> (TaskMap, Stages) {
    let stages = Stages {
        intake: Calls::default(),
        launch: Calls::default(),
        monitor: Calls::default(),
        finalize: Calls::default(),
    };
    let (intake, launch, monitor, finalize) = (
        stages.intake.clone(),
        stages.launch.clone(),
        stages.monitor.clone(),
        stages.finalize.clone(),
    );
    let s = script.clone();
    let map = TaskMap::new()
        // The wake table's write: nothing wakes the wait, its timeout ends it.
        .with("aws-sdk:dynamodb:updateItem", |_| async { Ok(json!({})) })
        .with("IntakeFunctionArn", move |input: Value| {
            intake.record(&input);
            let action = s.action;
            async move {
                let submission = json!({"submission_id": input["message"]["submission_pk"], "challenge_id": input["message"]["challenge_pk"], "execution": input["execution"]});
                Ok(json!({"action": action, "submission": submission}))
            }
        })
        .with("LaunchFunctionArn", {
            let errors = script.launch_errors.clone();
            move |input: Value| {
                let n = launch.record(&input);
                let error = errors.get(n - 1).copied();
                async move {
                    match error {
                        Some(e) => Err(TaskError::lambda(e, "the participant image cannot be pulled")),
                        None => Ok(json!({"jobs": ["job-0"], "monitor": {"state": "running", "wait_seconds": 60, "seen": 0, "expires_at": 1}})),
                    }
                }
            }
        })
        .with("MonitorFunctionArn", {
            let running = script.running_rounds;
            move |input: Value| {
                let round = monitor.record(&input);
                let mut run = input["run"].clone();
                run["monitor"] = json!({
                    "state": if round <= running { "running" } else { "done" },
                    "wait_seconds": 60,
                    "seen": 0,
                    "expires_at": 1,
                    "round": round,
                });
                async move { Ok(run) }
            }
        })
        .with("FinalizeFunctionArn", {
            let failing = script.finalize_error;
            move |input: Value| {
                finalize.record(&input);
                async move {
                    if let Some(e) = failing {
                        return Err(TaskError::lambda(e, "EvalAI does not answer"));
                    }
                    let failed = input["state"].get("error").is_some()
                        || input["state"]["intake"]["action"] == "reject";
                    Ok(json!({"status": if failed { "FAILED" } else { "FINISHED" }, "pipeline_error": failed}))
                }
            }
        });
    (map, stages)
}

async fn submit(script: Script, scale: f64) -> (ExecutionResult, Stages) {
    let (tasks, stages) = tasks(script);
    let result = run_with(&machine(), tasks, options(scale), pipe_batch()).await;
    (result, stages)
}

fn round_types() -> Vec<EventType> {
    vec![
        EventType::TaskStateEntered,
        EventType::TaskScheduled,
        EventType::TaskStarted,
        EventType::TaskSubmitted,
        EventType::TaskTimedOut,
        EventType::TaskStateExited,
        EventType::TaskStateEntered,
        EventType::LambdaFunctionScheduled,
        EventType::LambdaFunctionStarted,
        EventType::LambdaFunctionSucceeded,
        EventType::TaskStateExited,
        EventType::ChoiceStateEntered,
        EventType::ChoiceStateExited,
    ]
}

#[test]
fn the_definition_loads_with_its_five_substitutions() {
    let sm = machine();
    let mut functions: Vec<(String, Option<String>)> = sm
        .functions()
        .iter()
        .map(|f| (f.name.clone(), f.substitution.clone()))
        .collect();
    functions.sort();
    // The wake table's wait is the service integration; the table's name is the fifth.
    let wait = functions.remove(0);
    assert_eq!(wait, ("aws-sdk:dynamodb:updateItem".to_owned(), None));
    assert_eq!(
        functions,
        ["finalize", "intake", "launch", "monitor"].map(|s| (
            format!("lb-{s}"),
            Some(format!("{}{}FunctionArn", s[..1].to_uppercase(), &s[1..]))
        ))
    );
    assert_eq!(sm.start_at(), "OneSubmission?");
    assert_eq!(sm.state_names().len(), 18);
    let (all, _) = tasks(Script::default());
    let executor = Executor::new(all, options(1.0)).unwrap();
    assert!(executor.missing_tasks(&sm).is_empty());
    let executor = Executor::new(
        TaskMap::new().with("lb-intake", |_| async { Ok(json!({})) }),
        options(1.0),
    )
    .unwrap();
    assert_eq!(executor.missing_tasks(&sm).len(), 4);
    // Without the substitutions it cannot load.
    let definition: Value = serde_json::from_str(DEFINITION).unwrap();
    let err = StateMachine::load(&definition, &HashMap::new()).unwrap_err();
    assert_eq!(err.name(), "MissingSubstitution");
}

#[tokio::test]
async fn a_submission_runs_intake_launch_three_monitor_rounds_finalize_done() {
    let (r, stages) = submit(Script::default(), 0.001).await;
    assert_eq!(r.status, Status::Succeeded, "{:?} {:?}", r.error, r.cause);
    assert_eq!(
        r.states_entered(),
        [
            "OneSubmission?",
            "Unbatch",
            "Intake",
            "Eligible?",
            "Launch",
            "Next?",
            "WaitForChange",
            "Monitor",
            "Next?",
            "WaitForChange",
            "Monitor",
            "Next?",
            "WaitForChange",
            "Monitor",
            "Next?",
            "Finalize",
            "Failed?",
            "Done"
        ]
    );
    assert_eq!(stages.monitor.count(), 3);
    // Intake gets the Pipe's one message, unwrapped, and the execution's name.
    assert_eq!(
        stages.intake.inputs()[0],
        json!({"message": message(), "execution": "test-run"})
    );
    // Monitor gets the submission and the run Launch (then itself) produced.
    let second = &stages.monitor.inputs()[1];
    assert_eq!(second["run"]["monitor"]["round"], 1);
    assert_eq!(second["submission"]["execution"], "test-run");
    // Finalize sees the whole state.
    let state = &stages.finalize.inputs()[0]["state"];
    assert_eq!(state["run"]["monitor"]["state"], "done");
    assert_eq!(state["intake"]["action"], "run");
    let output = r.output.clone().unwrap();
    assert_eq!(
        output["final"],
        json!({"status": "FINISHED", "pipeline_error": false})
    );

    // The history: plain Lambda ARNs give LambdaFunction* events; the wait is the callback
    // Task (Task* events, TaskSubmitted, here ended by its timeout): 13 per monitor round.
    assert_eq!(r.count(EventType::TaskScheduled), 3);
    assert_eq!(r.count(EventType::TaskSubmitted), 3);
    assert_eq!(r.count(EventType::TaskTimedOut), 3);
    assert_eq!(r.count(EventType::LambdaFunctionScheduled), 6);
    let waits: Vec<usize> = r
        .history
        .iter()
        .enumerate()
        .filter(|(_, e)| {
            e.event_type == EventType::TaskStateEntered && e.state_name() == Some("WaitForChange")
        })
        .map(|(i, _)| i)
        .collect();
    assert_eq!(waits.len(), 3);
    for (k, start) in waits.iter().enumerate() {
        let round: Vec<EventType> = r.history[*start..*start + 13]
            .iter()
            .map(|e| e.event_type)
            .collect();
        assert_eq!(round, round_types(), "round {k}");
        if k + 1 < waits.len() {
            assert_eq!(waits[k + 1] - start, 13);
        }
    }
    // 1 start + OneSubmission? 2 + Unbatch 2 + Intake 5 + Eligible? 2 + Launch 5 + 3 rounds
    // of 13 + Next? 2 + Finalize 5 + Failed? 2 + Done 2 + 1 end (crates/pipeline's
    // statemachine test does the 72-hour arithmetic from these counts).
    assert_eq!(r.history.len(), 68);
}

#[tokio::test]
async fn a_failing_launch_is_caught_into_finalize_and_ends_pipeline_failed() {
    let script = Script {
        launch_errors: vec!["LaunchFailed"],
        ..Script::default()
    };
    let (r, stages) = submit(script, 0.001).await;
    assert_eq!(r.status, Status::Failed);
    assert_eq!(r.error.as_deref(), Some("PipelineFailed"));
    assert_eq!(
        r.states_entered(),
        [
            "OneSubmission?",
            "Unbatch",
            "Intake",
            "Eligible?",
            "Launch",
            "Finalize",
            "Failed?",
            "PipelineFailed"
        ]
    );
    assert_eq!(stages.launch.count(), 1, "LaunchFailed is not retried");
    assert_eq!(stages.monitor.count(), 0);
    let state = &stages.finalize.inputs()[0]["state"];
    assert_eq!(
        state["error"],
        json!({
            "Error": "LaunchFailed",
            "Cause": "{\"errorType\":\"LaunchFailed\",\"errorMessage\":\"the participant image cannot be pulled\"}"
        })
    );
    assert_eq!(
        state["intake"]["action"], "run",
        "the error sits beside the input"
    );
    assert_eq!(
        r.history
            .iter()
            .rev()
            .map(|e| e.event_type)
            .take(2)
            .collect::<Vec<_>>(),
        [EventType::ExecutionFailed, EventType::FailStateEntered]
    );
    // 1 + OneSubmission? 2 + Unbatch 2 + Intake 5 + Eligible? 2 + Launch 5 (failed, caught,
    // exited) + Finalize 5 + Failed? 2 + PipelineFailed 1 + 1.
    assert_eq!(r.history.len(), 26);
    assert_eq!(r.count(EventType::LambdaFunctionFailed), 1);
}

#[tokio::test]
async fn a_transient_launch_error_is_retried_with_backoff() {
    let script = Script {
        launch_errors: vec!["KubeTransient", "Lambda.TooManyRequestsException"],
        running_rounds: 0,
        ..Script::default()
    };
    let (r, stages) = submit(script, 0.001).await;
    assert_eq!(r.status, Status::Succeeded);
    assert_eq!(stages.launch.count(), 3);
    assert_eq!(r.count(EventType::LambdaFunctionFailed), 2);
    // Intake, Launch, one wait, Monitor, Finalize.
    assert_eq!(r.count(EventType::TaskStateEntered), 5);
}

#[tokio::test]
async fn a_skipped_submission_ends_at_skipped_without_launching() {
    let script = Script {
        action: "skip",
        ..Script::default()
    };
    let (r, stages) = submit(script, 0.001).await;
    assert_eq!(r.status, Status::Succeeded);
    assert_eq!(
        r.states_entered(),
        [
            "OneSubmission?",
            "Unbatch",
            "Intake",
            "Eligible?",
            "Skipped"
        ]
    );
    assert_eq!(stages.launch.count() + stages.finalize.count(), 0);
    assert_eq!(r.history.len(), 15);
    assert_eq!(
        r.history[r.history.len() - 3].event_type,
        EventType::SucceedStateEntered
    );
}

#[tokio::test]
async fn a_rejected_submission_goes_straight_to_finalize() {
    let script = Script {
        action: "reject",
        ..Script::default()
    };
    let (r, stages) = submit(script, 0.001).await;
    assert_eq!(
        r.states_entered(),
        [
            "OneSubmission?",
            "Unbatch",
            "Intake",
            "Eligible?",
            "Finalize",
            "Failed?",
            "PipelineFailed"
        ]
    );
    assert_eq!(stages.launch.count(), 0);
}

#[tokio::test]
async fn a_finalize_that_keeps_failing_ends_finalize_failed_after_its_retries() {
    let script = Script {
        finalize_error: Some("EvalAiUnavailable"),
        running_rounds: 0,
        ..Script::default()
    };
    let (r, stages) = submit(script, 0.0001).await;
    assert_eq!(r.status, Status::Failed);
    assert_eq!(r.error.as_deref(), Some("FinalizeFailed"));
    // One call and MaxAttempts 60 retries: Finalize outlasts an outage of hours.
    assert_eq!(stages.finalize.count(), 61);
    assert_eq!(r.states_entered().last(), Some(&"FinalizeFailed"));
}

#[tokio::test]
async fn a_cli_can_follow_the_stages_live() {
    let seen = Arc::new(AtomicUsize::new(0));
    let (tasks, _) = tasks(Script::default());
    let executor = Executor::new(tasks, options(0.001)).unwrap();
    let execution = executor.start(&machine(), "live", pipe_batch()).unwrap();
    let mut events = execution.events();
    let mut stages = Vec::new();
    let follow = async {
        while let Some(event) = events.next().await {
            seen.fetch_add(1, Ordering::SeqCst);
            if event.event_type.is_state_entered() {
                stages.push(event.state_name().unwrap_or_default().to_owned());
            }
        }
    };
    tokio::time::timeout(common::BOUND, follow).await.unwrap();
    let r = execution.wait().await;
    assert_eq!(seen.load(Ordering::SeqCst), r.history.len());
    assert_eq!(stages, r.states_entered());
}

#[tokio::test]
async fn a_batch_of_any_size_but_one_fails_as_invalid_batch_before_intake() {
    let not_a_message = json!({"challenge_pk": 1, "phase_pk": 1234});
    let inputs = [
        json!([]),
        json!([message(), message()]),
        not_a_message,
        json!("77"),
        json!(77),
    ];
    for input in inputs {
        let (tasks, stages) = tasks(Script::default());
        let r = run_with(&machine(), tasks, options(0.001), input.clone()).await;
        assert_eq!(r.status, Status::Failed, "{input}");
        assert_eq!(r.error.as_deref(), Some("InvalidBatch"), "{input}");
        assert!(r.cause.as_deref().unwrap().contains("batch size to 1"));
        assert!(r.cause.as_deref().unwrap().contains("--print-input"));
        assert_eq!(r.states_entered(), ["OneSubmission?", "InvalidBatch"]);
        let called = stages.intake.count()
            + stages.launch.count()
            + stages.monitor.count()
            + stages.finalize.count();
        assert_eq!(called, 0, "nothing is claimed or launched for {input}");
    }
}

/// What a person types in the console: the message object, not the Pipe's array. It runs as
/// the Pipe's batch of one does, with Intake given the same message.
#[tokio::test]
async fn the_bare_message_typed_in_the_console_runs_as_the_pipes_batch_of_one() {
    let (tasks, stages) = tasks(Script::default());
    let r = run_with(&machine(), tasks, options(0.001), message()).await;
    assert_eq!(r.status, Status::Succeeded, "{:?} {:?}", r.error, r.cause);
    let entered = r.states_entered();
    assert_eq!(entered[..3], ["OneSubmission?", "Intake", "Eligible?"]);
    assert_eq!(entered.last(), Some(&"Done"));
    assert_eq!(
        stages.intake.inputs()[0],
        json!({"message": message(), "execution": "test-run"})
    );
    assert_eq!(stages.finalize.count(), 1);
    assert_eq!(r.output.unwrap()["final"]["status"], "FINISHED");
}
