//! The deployed state machine, checked as data: every path compiles, every error name is one
//! Step Functions or our functions raise, every Task is a function of this repository, every
//! state is reachable, every Task ends in the failure path, and 72 hours fit the history.

use std::collections::{BTreeSet, HashSet};
use std::path::PathBuf;

use lb_domain::schedule::{quiet_rounds, HISTORY_BUDGET, MAX_EVALUATION};
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
            assert_eq!(name, "WaitForChange", "an unexpected service integration");
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
/// Wait and Choice are entered and exited.
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
        "Succeed" | "Fail" => 1,
        other => panic!("unexpected state type {other}"),
    }
}

#[test]
fn a_72_hour_evaluation_stays_under_2000_history_events_however_its_routes_go() {
    let def = definition();
    let states = states(&def);
    let sum = |names: &[&str]| names.iter().map(|s| events(states, s)).sum::<u64>();
    // Every path of the loop the definition has, checked against the counts below.
    assert_eq!(states["Monitor"]["Next"], "Next?");
    assert_eq!(states["Hold"]["Next"], "WaitForChange");
    assert_eq!(states["WaitForChange"]["Next"], "Monitor");
    // A quiet round: the safety net's timeout ends the wait.
    let quiet = sum(&["Next?", "WaitForChange", "Monitor"]);
    // A round woken by a change that updated EvalAI: the hold, then the wait.
    let woken = sum(&["Next?", "Hold", "WaitForChange", "Monitor"]);
    // A change during the Monitor or the hold: the wait's write fails (one event fewer) and
    // the Monitor runs at once.
    let missed = sum(&["Next?", "Hold", "Monitor"]) + events(states, "WaitForChange") - 1;
    assert_eq!((quiet, woken, missed), (13, 15, 14));
    let once = 2 /* ExecutionStarted, ExecutionSucceeded */
        + sum(&["OneSubmission?", "Unbatch", "Intake", "Eligible?", "Launch", "Finalize", "Failed?", "Done"]);
    // A retried Lambda adds LambdaFunctionScheduled/Started/Failed: allow 20 retries a run.
    let retries = 20 * 3;
    let safety_net = quiet_rounds(MAX_EVALUATION);
    // Quiet: nothing but the safety net for 72 hours.
    let quiet_total = once + safety_net * quiet + retries;
    // Worst: an event for each of 100 routes, each costing a round of its own (no two in one
    // burst), on top of every safety-net round (a timeout needs a whole interval without
    // events, so there are never more than in the quiet case).
    let routes = 100;
    let worst_total = once + routes * woken.max(missed) + safety_net * quiet + retries;
    println!(
        "quiet: {once} once + {safety_net} rounds x {quiet} + {retries} retries = {quiet_total}"
    );
    println!(
        "worst: {once} once + {routes} routes x {} + {safety_net} rounds x {quiet} + {retries} retries = {worst_total}",
        woken.max(missed)
    );
    assert_eq!((once, safety_net), (26, 29));
    assert_eq!((quiet_total, worst_total), (463, 1963));
    assert!(worst_total < HISTORY_BUDGET, "{worst_total}");
    // Today's loop took 517 rounds of 9 events (4,739 in all) whatever happened.
}

#[test]
fn the_longest_wait_for_a_turn_and_the_longest_evaluation_fit_one_history() {
    let def = definition();
    let states = states(&def);
    let sum = |names: &[&str]| names.iter().map(|s| events(states, s)).sum::<u64>();
    // The turn comes: the Choice sends the run back to create its Jobs.
    let choices = states["Next?"]["Choices"].as_array().unwrap();
    assert_eq!(choices[0]["StringEquals"], "admitted");
    assert_eq!(choices[0]["Next"], "LaunchAdmitted");
    assert_eq!(states["LaunchAdmitted"]["Next"], "Next?");
    assert_eq!(
        states["LaunchAdmitted"]["Parameters"]["queue.$"],
        "$.run.queue"
    );
    // A waiting round is a quiet round (its wait is the queue's safety net); the longest queue
    // the settings allow (336 hours) at the queue's pace, woken at most once a round.
    let round = sum(&["Next?", "WaitForChange", "Monitor"]);
    let mut waited = std::time::Duration::ZERO;
    let mut rounds = 0u64;
    while waited < std::time::Duration::from_secs(336 * 3600) {
        waited += lb_domain::schedule::queue_wait(waited);
        rounds += 1;
    }
    let queue = rounds * round + sum(&["Next?", "LaunchAdmitted"]);
    println!("queue: {rounds} rounds x {round} = {queue}");
    assert!(
        queue + HISTORY_BUDGET < 25_000,
        "Step Functions' limit is 25,000 events: {queue} + {HISTORY_BUDGET}"
    );
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
