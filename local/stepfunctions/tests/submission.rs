//! The definition we deploy, `statemachine/submission.asl.json`, run end to end with fake
//! task handlers: the paths a submission takes and the history it leaves.

use crate::common;

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
    /// Finalize says the platform's own failure ended the submission.
    platform_failure: bool,
}

impl Default for Script {
    fn default() -> Self {
        Script {
            action: "run",
            launch_errors: vec![],
            running_rounds: 2,
            finalize_error: None,
            platform_failure: false,
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
        // No run of these scripts continues (the continuation's own test has its handlers).
        .with("aws-sdk:sfn:describeExecution", |_| async {
            Err(TaskError::new("Sfn.SfnException", "not here"))
        })
        .with("states:startExecution", |_| async {
            Err(TaskError::new("StepFunctions.AWSStepFunctionsException", "not here"))
        })
        .with("IntakeFunctionArn", move |input: Value| {
            intake.record(&input);
            let action = s.action;
            async move {
                let submission = json!({"submission_id": input["message"]["submission_pk"], "challenge_id": input["message"]["challenge_pk"], "execution": input["execution"], "submitted_at": 0});
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
            let platform = script.platform_failure;
            move |input: Value| {
                finalize.record(&input);
                async move {
                    if let Some(e) = failing {
                        return Err(TaskError::lambda(e, "EvalAI does not answer"));
                    }
                    let failed = input["state"].get("error").is_some()
                        || input["state"]["intake"]["action"] == "reject";
                    let mut out = json!({"status": if failed { "FAILED" } else { "FINISHED" }, "pipeline_error": failed});
                    if platform {
                        out = json!({"status": "FAILED", "pipeline_error": false, "platform_failure": true});
                    }
                    Ok(out)
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
    // The wake table's wait and the continuation are the service integrations; the table's
    // name is the fifth substitution.
    let wait = functions.remove(0);
    assert_eq!(wait, ("aws-sdk:dynamodb:updateItem".to_owned(), None));
    let start = functions.pop().unwrap();
    assert_eq!(start, ("states:startExecution".to_owned(), None));
    let describe = functions.remove(0);
    assert_eq!(describe, ("aws-sdk:sfn:describeExecution".to_owned(), None));
    assert_eq!(
        functions,
        ["finalize", "intake", "launch", "monitor"].map(|s| (
            format!("lb-{s}"),
            Some(format!("{}{}FunctionArn", s[..1].to_uppercase(), &s[1..]))
        ))
    );
    assert_eq!(sm.start_at(), "OneSubmission?");
    assert_eq!(sm.state_names().len(), 25);
    let (all, _) = tasks(Script::default());
    let executor = Executor::new(all, options(1.0)).unwrap();
    assert!(executor.missing_tasks(&sm).is_empty());
    let executor = Executor::new(
        TaskMap::new().with("lb-intake", |_| async { Ok(json!({})) }),
        options(1.0),
    )
    .unwrap();
    assert_eq!(executor.missing_tasks(&sm).len(), 6);
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
async fn the_platform_s_own_failure_ends_the_execution_failed_apart() {
    let script = Script {
        platform_failure: true,
        ..Script::default()
    };
    let (r, stages) = submit(script, 0.001).await;
    assert_eq!(r.status, Status::Failed);
    assert_eq!(r.error.as_deref(), Some("PlatformFailed"));
    let entered = r.states_entered();
    assert_eq!(
        entered[entered.len() - 3..],
        ["Finalize", "Failed?", "PlatformFailed"]
    );
    assert_eq!(stages.finalize.count(), 1);
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

/// A Monitor that asks to continue every `per_execution` rounds of one execution, and ends
/// the run after `total` rounds; StartExecution played by the executor itself.
fn continuing_tasks(
    per_execution: u64,
    total: u64,
    executor: Arc<std::sync::OnceLock<Executor>>,
) -> TaskMap {
    let (base, _) = tasks(Script::default());
    let rounds = Arc::new(AtomicUsize::new(0));
    base.with("MonitorFunctionArn", move |input: Value| {
        let round = rounds.fetch_add(1, Ordering::SeqCst) as u64 + 1;
        let mut run = input["run"].clone();
        let execution = input["execution"].as_str().unwrap_or_default().to_owned();
        // Rounds of this execution: a new execution's first round starts the count.
        let mine = if run["monitor"]["execution"] == execution.as_str() {
            run["monitor"]["in_execution"].as_u64().unwrap_or(0) + 1
        } else {
            1
        };
        let generation = run["monitor"]["generation"].as_u64().unwrap_or(0);
        let lineage = input["submission"]["execution"]
            .as_str()
            .unwrap_or_default()
            .to_owned();
        run["monitor"] = json!({
            "state": "running", "wait_seconds": 60, "hold_seconds": 1, "seen": 0,
            "expires_at": 1, "execution": execution, "in_execution": mine,
            "generation": generation,
        });
        if round >= total {
            run["monitor"]["state"] = json!("finished");
        } else if mine >= per_execution {
            run["monitor"]["state"] = json!("continued");
            run["monitor"]["generation"] = json!(generation + 1);
            run["monitor"]["continue_as"] = json!(format!("{lineage}-c{}", generation + 1));
        }
        async move { Ok(run) }
    })
    .with("aws-sdk:sfn:describeExecution", {
        let executor = executor.clone();
        move |params: Value| {
            // DescribeExecution as the SDK integration answers: the version only when the
            // execution was started through one.
            let described = executor
                .get()
                .and_then(|e| e.describe(params["ExecutionArn"].as_str().unwrap_or_default()));
            async move {
                let described = described.ok_or_else(|| {
                    TaskError::new("Sfn.ExecutionDoesNotExistException", "no such execution")
                })?;
                Ok(match described.version_arn {
                    Some(v) => json!({"StateMachineVersionArn": v}),
                    None => json!({}),
                })
            }
        }
    })
    .with("states:startExecution", move |params: Value| {
        let executor = executor.clone();
        async move {
            let executor = executor.get().expect("bound");
            let arn = params["StateMachineArn"].as_str().unwrap_or_default();
            let name = params["Name"].as_str().unwrap_or_default();
            executor
                .start_execution(arn, name, params["Input"].clone())
                .map_err(|e| {
                    TaskError::new(
                        format!("StepFunctions.{}Exception", e.name()),
                        e.to_string(),
                    )
                })
        }
    })
}

#[tokio::test]
async fn a_long_run_continues_as_new_executions_of_the_same_state_machine() {
    let bound = Arc::new(std::sync::OnceLock::new());
    let executor = Executor::new(continuing_tasks(3, 8, bound.clone()), options(0.001)).unwrap();
    bound.set(executor.clone()).unwrap();
    // Started through an alias, as the Pipe starts it; a deploy moves the alias on at once.
    let v1 = executor.publish(&machine());
    let live = executor.point_alias("live", &v1).unwrap();
    let first = executor.start_arn(&live, "sub-99", pipe_batch()).unwrap();
    let v2 = executor.publish(&machine());
    executor.point_alias("live", &v2).unwrap();
    let mut result = first.wait().await;
    let mut chain = vec![result.clone()];
    while let Some(next) = result
        .output
        .as_ref()
        .and_then(|o| o["ExecutionArn"].as_str())
        .map(str::to_owned)
    {
        result = executor
            .wait_for(&next)
            .await
            .expect("the continuation ran");
        chain.push(result.clone());
        assert!(chain.len() <= 4, "the chain does not end");
    }
    // Rounds 1-3 in the first, 4-6 in the second, 7-8 in the third, which finalizes.
    assert_eq!(chain.len(), 3);
    for (n, r) in chain.iter().enumerate() {
        assert_eq!(
            r.status,
            Status::Succeeded,
            "{n}: {:?} {:?}",
            r.error,
            r.cause
        );
    }
    assert!(chain[2].execution_arn.ends_with(":submission:sub-99-c2"));
    // Every continuation ran the version the run started on, not the one deployed since.
    for r in &chain {
        let described = executor.describe(&r.execution_arn).unwrap();
        assert_eq!(described.version_arn.as_deref(), Some(v1.as_str()));
    }
    // Each earlier one ends in `Continued` with StartExecution's answer as its output.
    for r in &chain[..2] {
        assert_eq!(r.states_entered().last(), Some(&"Continued"));
        let out = r.output.as_ref().unwrap();
        assert!(out["StartDate"].is_number(), "{out}");
    }
    // A continuation resumes the loop with the run's state: no Intake, no Launch.
    let entered = chain[1].states_entered();
    assert_eq!(
        entered[..4],
        ["OneSubmission?", "Resume", "Hold", "WaitForChange"]
    );
    assert!(!entered.contains(&"Intake") && !entered.contains(&"Launch"));
    assert_eq!(chain[2].states_entered().last(), Some(&"Done"));
    // The run's state went along: the Monitor of the second saw the first's count.
    let input = chain[1].history[0].details["input"].clone();
    let input: Value = match input {
        Value::String(text) => serde_json::from_str(&text).unwrap(),
        other => other,
    };
    assert_eq!(input["continued"]["from"], "sub-99");
    assert_eq!(
        input["continued"]["intake"]["submission"]["execution"],
        "sub-99"
    );
    assert_eq!(
        input["continued"]["run"]["monitor"]["continue_as"],
        "sub-99-c1"
    );
    // StartExecution's name rules: the same name and input while it runs is that execution;
    // another input, or a name of an execution that ended, is refused.
    let arn = chain[0]
        .execution_arn
        .replace(":execution:", ":stateMachine:");
    let arn = arn.rsplit_once(':').unwrap().0;
    let err = executor
        .start_execution(arn, "sub-99-c1", json!({}))
        .unwrap_err();
    assert_eq!(err.name(), "ExecutionAlreadyExists");
    let err = executor
        .start_execution(
            "arn:aws:states:us-east-1:123456789012:stateMachine:other",
            "x",
            json!({}),
        )
        .unwrap_err();
    assert_eq!(err.name(), "StateMachineDoesNotExist");
}
