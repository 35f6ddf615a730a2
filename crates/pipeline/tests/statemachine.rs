//! The deployed state machine, checked as data: every path compiles, every error name is one
//! Step Functions or our functions raise, every Task is a function of this repository, every
//! state is reachable, every Task ends in the failure path, and 72 hours fit the history.

use std::collections::{BTreeSet, HashSet};
use std::path::PathBuf;

use lb_domain::schedule::{rounds_for, MAX_EVALUATION};
use lb_pipeline::error::{ERROR_NAMES, TRANSIENT_NAMES};
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
];

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
    for (name, state) in states(&definition()) {
        for list in ["Retry", "Catch"] {
            for rule in state[list].as_array().into_iter().flatten() {
                for error in rule["ErrorEquals"].as_array().unwrap() {
                    let error = error.as_str().unwrap();
                    assert!(
                        BUILT_IN.contains(&error) || ERROR_NAMES.contains(&error),
                        "{name}.{list}: `{error}` is neither built in nor one of ours"
                    );
                    assert!(!ERROR_NAMES.contains(&error) || !error.starts_with("States."));
                }
            }
        }
    }
}

#[test]
fn every_task_retries_every_transient_error_and_its_own_timeout() {
    for (name, state) in states(&definition()) {
        if state["Type"] != "Task" {
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
        for error in TRANSIENT_NAMES.iter().chain(&["States.Timeout"]) {
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

#[test]
fn a_72_hour_evaluation_stays_under_5000_history_events() {
    let def = definition();
    let states = states(&def);
    // Events per state, as the execution history records them: a Task calling a Lambda ARN
    // is TaskStateEntered, LambdaFunctionScheduled, LambdaFunctionStarted,
    // LambdaFunctionSucceeded, TaskStateExited; Wait and Choice are entered and exited.
    let events = |name: &str| match states[name]["Type"].as_str().unwrap() {
        "Task" => 5,
        "Wait" | "Choice" | "Pass" => 2,
        "Succeed" | "Fail" => 1,
        other => panic!("unexpected state type {other}"),
    };
    let per_round: u64 = ["Wait", "Monitor", "Done?"].iter().map(|s| events(s)).sum();
    assert_eq!(per_round, 9);
    let once: u64 = 2 /* ExecutionStarted, ExecutionSucceeded */
        + ["OneSubmission?", "Unbatch", "Intake", "Eligible?", "Launch", "Finalize", "Failed?", "Done"].iter().map(|s| events(s)).sum::<u64>();
    // A retried Lambda adds LambdaFunctionScheduled/Started/Failed: allow 20 retries a run.
    let retries = 20 * 3;
    let rounds = rounds_for(MAX_EVALUATION);
    let total = once + rounds * per_round + retries;
    assert_eq!((rounds, total), (517, 517 * 9 + once + retries));
    assert!(
        total < 5_000,
        "{total} events for 72 hours (limit 25,000, our budget 5,000)"
    );
}

#[test]
#[ignore = "needs venv"]
fn statelint_accepts_the_definition_with_its_substitutions_filled() {
    let text = std::fs::read_to_string(root().join("statemachine/submission.asl.json")).unwrap();
    let mut filled = text.clone();
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
        if state["Type"] != "Task" {
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
