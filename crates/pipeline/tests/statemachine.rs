//! The deployed state machine, checked as data: every path compiles, every error name is one
//! Step Functions or our functions raise, every Task is a function of this repository, every
//! state is reachable, every Task ends in the failure path, and 72 hours fit the history.

use std::collections::{BTreeSet, HashSet};
use std::path::PathBuf;

use lb_domain::run::history;
use lb_domain::run::schedule::{quiet_rounds, MAX_EVALUATION, MIN_ROUND_INTERVAL};
use lb_pipeline::FnError;
use serde_json::{Map, Value};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn definition() -> Value {
    let path = root().join("statemachine/submission.asl.json");
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

fn states(def: &Value) -> &Map<String, Value> {
    def["States"].as_object().unwrap()
}

/// Step Functions' own error names, plus the Lambda service errors STYLE.md retries.
const BUILT_IN: &[&str] = &[
    "States.ALL",
    "States.Timeout",
    "States.TaskFailed",
    "States.Permissions",
    "States.Runtime",
    "States.HeartbeatTimeout",
    "States.DataLimitExceeded",
    "Lambda.ServiceException",
    "Lambda.AWSLambdaException",
    "Lambda.SdkClientException",
    "Lambda.TooManyRequestsException",
    "Lambda.Unknown",
    // The wake table's wait (AWS SDK integration): DynamoDB UpdateItem's documented errors,
    // named as the developer guide's "AWS SDK integrations" says (`DynamoDb.` + the error,
    // with the `Exception` suffix).
    "DynamoDb.ConditionalCheckFailedException",
    "DynamoDb.ProvisionedThroughputExceededException",
    "DynamoDb.ThrottlingException",
    "DynamoDb.RequestLimitExceededException",
    "DynamoDb.InternalServerErrorException",
    // ContinueAsNew's StartExecution (the optimized Step Functions integration): the API's
    // errors under the service's prefix, as the Java SDK names its exceptions.
    "StepFunctions.ExecutionLimitExceededException",
    "StepFunctions.AWSStepFunctionsException",
];

/// A Task that invokes one of our functions (the others are service integrations).
fn invokes_function(state: &Value) -> bool {
    state["Type"] == "Task"
        && state["Resource"]
            .as_str()
            .is_some_and(|r| r.starts_with("${"))
}

fn successors(state: &Value) -> Vec<&str> {
    let mut next: Vec<&str> = ["Next", "Default"]
        .iter()
        .filter_map(|k| state[*k].as_str())
        .collect();
    for list in ["Choices", "Catch"] {
        if let Some(items) = state[list].as_array() {
            next.extend(items.iter().filter_map(|c| c["Next"].as_str()));
        }
    }
    next
}

#[test]
fn every_path_and_template_compiles_with_the_shared_asl_implementation() {
    for (name, state) in states(&definition()) {
        lb_asl::DataFlow::from_state(state.as_object().unwrap())
            .unwrap_or_else(|e| panic!("{name}: {e}"));
    }
}

#[test]
fn every_error_name_is_built_in_or_raised_by_our_functions() {
    let ours = FnError::names();
    for (name, state) in states(&definition()) {
        for list in ["Retry", "Catch"] {
            for rule in state[list].as_array().into_iter().flatten() {
                for error in rule["ErrorEquals"].as_array().unwrap() {
                    let error = error.as_str().unwrap();
                    assert!(
                        BUILT_IN.contains(&error) || ours.contains(&error),
                        "{name}.{list}: `{error}` is neither built in nor one of ours"
                    );
                    assert!(!ours.contains(&error) || !error.starts_with("States."));
                }
            }
        }
    }
}

#[test]
fn every_task_retries_every_transient_error_and_its_own_timeout() {
    for (name, state) in states(&definition()) {
        if !invokes_function(state) {
            continue;
        }
        let retried: BTreeSet<&str> = state["Retry"]
            .as_array()
            .into_iter()
            .flatten()
            .filter(|r| r["MaxAttempts"].as_u64().unwrap_or(3) > 0)
            .flat_map(|r| r["ErrorEquals"].as_array().unwrap())
            .filter_map(Value::as_str)
            .collect();
        for error in FnError::transient_names().iter().chain(&["States.Timeout"]) {
            assert!(retried.contains(error), "{name} does not retry {error}");
        }
    }
}

#[test]
fn every_task_is_a_function_of_this_repository_and_is_caught() {
    let mut functions = BTreeSet::new();
    for (name, state) in states(&definition()) {
        if state["Type"] != "Task" {
            continue;
        }
        if !invokes_function(state) {
            assert!(
                ["WaitForChange", "WhichVersion", "ContinueAsNew"].contains(&name.as_str()),
                "an unexpected service integration: {name}"
            );
            continue;
        }
        let resource = state["Resource"].as_str().unwrap();
        let function = resource
            .strip_prefix("${")
            .and_then(|r| r.strip_suffix("FunctionArn}"))
            .unwrap_or_else(|| {
                panic!("{name}: `{resource}` is not a ${{<Name>FunctionArn}} substitution")
            })
            .to_lowercase();
        let manifest = root().join("functions").join(&function).join("Cargo.toml");
        let text = std::fs::read_to_string(&manifest)
            .unwrap_or_else(|_| panic!("{name}: no {}", manifest.display()));
        assert!(
            text.contains(&format!("name = \"{function}\"")),
            "{}",
            manifest.display()
        );
        let catches_all = state["Catch"].as_array().into_iter().flatten().any(|c| {
            c["ErrorEquals"]
                .as_array()
                .unwrap()
                .iter()
                .any(|e| e == "States.ALL")
        });
        assert!(catches_all, "{name} has no States.ALL catch");
        assert!(
            state["TimeoutSeconds"].as_u64().is_some(),
            "{name} has no timeout"
        );
        functions.insert(function);
    }
    assert_eq!(
        functions.into_iter().collect::<Vec<_>>(),
        ["finalize", "intake", "launch", "monitor"]
    );
}

#[test]
fn every_state_is_reachable_and_every_transition_lands() {
    let def = definition();
    let states = states(&def);
    let mut seen = HashSet::new();
    let mut todo = vec![def["StartAt"].as_str().unwrap()];
    while let Some(name) = todo.pop() {
        if !seen.insert(name) {
            continue;
        }
        let state = states
            .get(name)
            .unwrap_or_else(|| panic!("transition to missing state `{name}`"));
        todo.extend(successors(state));
    }
    let unreachable: Vec<_> = states
        .keys()
        .filter(|k| !seen.contains(k.as_str()))
        .collect();
    assert!(unreachable.is_empty(), "unreachable: {unreachable:?}");
    // Every Choice branch is reachable too: its rules' targets were visited above; each Choice
    // must itself be the start or the target of some state.
    for (name, state) in states {
        if state["Type"] == "Choice" {
            assert!(
                def["StartAt"] == name.as_str()
                    || states
                        .values()
                        .any(|s| successors(s).contains(&name.as_str())),
                "{name}"
            );
        }
    }
}

/// Events per state, as the execution history records them: a Task calling a Lambda ARN is
/// TaskStateEntered, LambdaFunctionScheduled, LambdaFunctionStarted, LambdaFunctionSucceeded,
/// TaskStateExited; a callback Task adds TaskSubmitted to TaskScheduled, TaskStarted and its
/// end (TaskSucceeded, or TaskTimedOut caught); one whose write fails has no TaskSubmitted;
/// Wait, Choice and Pass are entered and exited; Succeed and Fail are entered (their exit and
/// the execution's end are counted with them: 2).
fn events(states: &Map<String, Value>, name: &str) -> u64 {
    let state = &states[name];
    match state["Type"].as_str().unwrap() {
        "Task"
            if state["Resource"]
                .as_str()
                .unwrap()
                .ends_with(".waitForTaskToken") =>
        {
            6
        }
        "Task" => 5,
        "Wait" | "Choice" | "Pass" => 2,
        "Succeed" | "Fail" => 2,
        other => panic!("unexpected state type {other}"),
    }
}

/// A state's retries at most: the sum of its retriers' `MaxAttempts` (3 when unset).
fn max_retries(states: &Map<String, Value>, name: &str) -> u64 {
    states[name]["Retry"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|r| r["MaxAttempts"].as_u64().unwrap_or(3))
        .sum()
}

/// A state's events at their worst: every retry adds its scheduled, started and failed.
fn worst(states: &Map<String, Value>, name: &str) -> u64 {
    events(states, name) + history::RETRY_EVENTS * max_retries(states, name)
}

#[test]
fn the_history_bounds_hold_for_the_deployed_definition() {
    let def = definition();
    let states = states(&def);
    let sum = |names: &[&str]| names.iter().map(|s| worst(states, s)).sum::<u64>();
    // Every path of the loop, and where the budget's arithmetic enters it.
    assert_eq!(states["Monitor"]["Next"], "Next?");
    assert_eq!(states["Hold"]["Next"], "WaitForChange");
    assert_eq!(states["WaitForChange"]["Next"], "Monitor");
    assert_eq!(states["PollInstead"]["Next"], "Monitor");
    assert_eq!(states["Resume"]["Next"], "Hold");
    assert_eq!(states["ContinueAsNew"]["Next"], "Continued");
    assert_eq!(
        states["Monitor"]["Parameters"]["retries.$"],
        "$$.State.RetryCount"
    );
    assert_eq!(
        states["LaunchAdmitted"]["Parameters"]["events.$"],
        "$.run.monitor.events"
    );
    assert_eq!(max_retries(states, "Monitor"), history::MONITOR_MAX_RETRIES);
    // The first execution until its first round: started, then every state with every retry.
    let opening = 1 + sum(&["OneSubmission?", "Unbatch", "Intake", "Eligible?", "Launch"]);
    let resumed = 1 + sum(&["OneSubmission?", "Resume"]);
    // A round: the Choice, the hold, the wait with its retries and, when it fails, the poll,
    // then the Monitor (its own retries counted from `$$.State.RetryCount`).
    let round = sum(&["Next?", "Hold", "WaitForChange", "PollInstead"]) + events(states, "Monitor");
    let admitted = sum(&["Next?", "LaunchAdmitted"]);
    // The worst ending: the continuation fails after its retries and Finalize runs with all of
    // its own; the Choice after it and the end.
    let closing = sum(&[
        "Next?",
        "ContinueAsNew",
        "Finalize",
        "Failed?",
        "PipelineFailed",
    ]);
    let counted = (opening, resumed, round, admitted, closing);
    println!("opening, resumed, round, admitted, closing: {counted:?}");
    assert!(opening <= history::OPENING_EVENTS, "{counted:?}");
    assert!(resumed <= history::RESUMED_EVENTS, "{counted:?}");
    assert!(round <= history::ROUND_EVENTS, "{counted:?}");
    assert!(admitted <= history::ADMITTED_EVENTS, "{counted:?}");
    assert!(closing <= history::CLOSING_EVENTS, "{counted:?}");
}

#[test]
fn a_quiet_72_hour_evaluation_fits_one_execution() {
    // Nothing but the safety net for 72 hours: no continuation.
    let rounds = quiet_rounds(MAX_EVALUATION);
    let events = history::OPENING_EVENTS + rounds * history::round_events(0);
    assert_eq!(rounds, 29);
    assert!(!history::continue_due(events, history::EXECUTION_BUDGET));
}

#[test]
fn the_worst_72_hours_cost_a_bounded_chain_of_executions() {
    // A round at most every MIN_ROUND_INTERVAL, whatever wakes the loop: each round is
    // followed by a hold at least that long.
    let rounds = MAX_EVALUATION.as_secs() / MIN_ROUND_INTERVAL.as_secs();
    let per_execution = history::rounds_per_execution(history::EXECUTION_BUDGET);
    let executions = rounds.div_ceil(per_execution);
    // Transitions billed per round: Next?, Hold, WaitForChange, Monitor.
    let transitions = rounds * 4;
    println!(
        "worst 72 h: {rounds} rounds, {per_execution} per execution, {executions} executions, \
         {transitions} state transitions"
    );
    assert_eq!((rounds, per_execution, executions), (25_920, 319, 82));
}

#[test]
fn the_wait_for_a_change_stores_its_token_only_while_the_count_is_what_the_monitor_read() {
    let def = definition();
    let wait = &states(&def)["WaitForChange"];
    assert_eq!(
        wait["Resource"],
        "arn:aws:states:::aws-sdk:dynamodb:updateItem.waitForTaskToken"
    );
    let params = &wait["Parameters"];
    assert_eq!(params["TableName"], "${WakeTable}");
    assert_eq!(
        params["ConditionExpression"],
        "attribute_not_exists(#changes) OR #changes = :seen"
    );
    let values = &params["ExpressionAttributeValues"];
    assert_eq!(values[":token"]["S.$"], "$$.Task.Token");
    assert_eq!(
        values[":seen"]["N.$"],
        "States.Format('{}', $.run.monitor.seen)"
    );
    assert_eq!(wait["TimeoutSecondsPath"], "$.run.monitor.wait_seconds");
    // Its result is dropped: the run state the Monitor needs stays as it was.
    assert!(wait["ResultPath"].is_null() && wait.get("ResultPath").is_some());
    let catch = |error: &str| {
        wait["Catch"]
            .as_array()
            .unwrap()
            .iter()
            .find(|c| {
                c["ErrorEquals"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .any(|e| e == error)
            })
            .map(|c| c["Next"].as_str().unwrap())
    };
    assert_eq!(catch("States.Timeout"), Some("Monitor"));
    assert_eq!(
        catch("DynamoDb.ConditionalCheckFailedException"),
        Some("Monitor")
    );
    // Anything else (permissions, a missing table) degrades to polling, never to a loop
    // without pause and never to a failed run.
    assert_eq!(catch("States.ALL"), Some("PollInstead"));
    assert_eq!(
        states(&def)["PollInstead"]["SecondsPath"],
        "$.run.monitor.wait_seconds"
    );
}

#[test]
#[ignore = "needs venv"]
fn statelint_accepts_the_definition_with_its_substitutions_filled() {
    let text = std::fs::read_to_string(root().join("statemachine/submission.asl.json")).unwrap();
    let mut filled = text.clone();
    filled = filled.replace("${WakeTable}", "leaderboard-wakes");
    for function in ["Intake", "Launch", "Monitor", "Finalize"] {
        filled = filled.replace(
            &format!("${{{function}FunctionArn}}"),
            &format!(
                "arn:aws:lambda:us-east-1:123456789012:function:{}",
                function.to_lowercase()
            ),
        );
    }
    assert!(!filled.contains("${"), "an unknown substitution is left");
    let file = std::env::temp_dir().join(format!("submission-{}.asl.json", std::process::id()));
    std::fs::write(&file, filled).unwrap();
    let out = std::process::Command::new(root().join(".venv/bin/statelint"))
        .arg(&file)
        .output()
        .expect("run `make venv`");
    let _ = std::fs::remove_file(&file);
    assert!(
        out.status.success(),
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn a_task_that_times_out_is_retried_before_the_failure_path() {
    // A Lambda that outlives its Task (a slow EvalAI, a cluster API stalling) raises
    // States.Timeout; every Task is idempotent, so that is a transient error like ours, not the
    // end of a healthy run.
    for (name, state) in states(&definition()) {
        if !invokes_function(state) {
            continue;
        }
        let retried = state["Retry"].as_array().into_iter().flatten().any(|r| {
            r["MaxAttempts"].as_u64().unwrap_or(3) > 0
                && r["ErrorEquals"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .any(|e| e == "States.Timeout" || e == "States.ALL")
        });
        assert!(retried, "{name} does not retry States.Timeout");
    }
}
