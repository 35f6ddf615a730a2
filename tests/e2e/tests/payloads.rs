//! The largest payload each state of the deployed state machine can produce, computed from the
//! bounds the code enforces, against Step Functions' 256 KiB (`States.DataLimitExceeded`,
//! which no Catch handles): every field at its bound, every string made of the character
//! JSON escapes longest, run through `statemachine/submission.asl.json` in the executor.

use lb_domain::capacity::cost::{
    CapacityType, JobEntry, JobMark, Ledger, NodeKind, Running, UsageLine, COUNT_CAP,
};
use std::collections::{BTreeMap, HashMap};

use lb_domain::job::plan::{MAX_ROUTES, MAX_WORKERS};
use lb_pipeline::error::MAX_ERROR_MESSAGE_BYTES;
use lb_pipeline::payload::{
    Action, IntakeOutput, MonitorState, PairRoutes, QueueState, RunPhase, RunState, SubmissionInfo,
    MAX_MESSAGE_BYTES, MAX_REASON_BYTES,
};
use local_stepfunctions::{Executor, Options, StateMachine, Status, TaskError, TaskMap};
use serde_json::{json, Value};

/// Step Functions' limit on a state's input or output and a task's result.
const LIMIT: usize = 256 * 1024;

/// One byte of UTF-8 that JSON writes as six (`\u0001`), for text carried as it came.
const WORST_RAW: char = '\u{1}';

/// The longest-escaped character of text made printable (reasons, error messages): `"`,
/// written `\"`, and `\\\"` once the error's JSON `Cause` is a string in the state.
fn worst(bytes: usize) -> String {
    "\"".repeat(bytes)
}

fn machine() -> StateMachine {
    let definition: Value =
        serde_json::from_str(include_str!("../../../statemachine/submission.asl.json")).unwrap();
    let substitutions: HashMap<String, String> = ["Intake", "Launch", "Monitor", "Finalize"]
        .into_iter()
        .map(|s| {
            (
                format!("{s}FunctionArn"),
                format!("arn:aws:lambda:us-west-2:123456789012:function:{s}"),
            )
        })
        .chain([("WakeTable".to_owned(), "leaderboard-wakes".to_owned())])
        .collect();
    StateMachine::load(&definition, &substitutions).unwrap()
}

/// The Pipe's batch: one message as large as the queue accepts.
fn batch() -> Value {
    let mut message = json!({"challenge_pk": 1, "phase_pk": 1, "submission_pk": 1,
                             "submitted_image_uri": ""});
    let room = MAX_MESSAGE_BYTES - message.to_string().len();
    message["submitted_image_uri"] = json!("x".repeat(room));
    assert_eq!(message.to_string().len(), MAX_MESSAGE_BYTES);
    json!([message])
}

fn submission() -> SubmissionInfo {
    SubmissionInfo {
        challenge_id: u64::MAX,
        phase_id: u64::MAX,
        submission_id: u64::MAX,
        team_id: u64::MAX,
        team_name: WORST_RAW.to_string().repeat(lb_evalai::MAX_TEAM_NAME),
        leaderboard: lb_domain::results::Leaderboard::V2,
        track: "T".repeat(63),
        image: "x".repeat(lb_jobs::image::MAX_REFERENCE_LEN),
        routes: MAX_ROUTES,
        workers: MAX_WORKERS,
        resuming: true,
        // Step Functions execution names are at most 80 characters.
        execution: "e".repeat(80),
        arrived_ms: Some(u64::MAX),
        submitted_at: u64::MAX,
    }
}

/// A run of the most workers, one per Job, every field at its bound.
fn run(phase: RunPhase) -> RunState {
    let route = format!("{MAX_ROUTES}-{MAX_ROUTES}");
    RunState {
        jobs: MAX_WORKERS,
        pairs: (1..=MAX_WORKERS)
            .map(|id| PairRoutes {
                id,
                routes: route.clone(),
            })
            .collect(),
        repetitions: 5,
        launched_at: u64::MAX,
        recorder: true,
        queue: QueueState {
            arrived_at: u64::MAX,
            admitted: false,
            shown: Some(u32::MAX),
            shown_at: Some(u64::MAX),
        },
        monitor: MonitorState {
            state: phase,
            wait_seconds: 1,
            // NB: the wait and the hold are real time here; the wait below is never woken.
            hold_seconds: 1,
            seen: u64::MAX,
            poll: false,
            expires_at: u64::MAX,
            updated_at: Some(u64::MAX),
            status_read_at: Some(u64::MAX),
            rounds: u64::MAX,
            fingerprint: Some(lb_pipeline::results::fingerprint_of_pairs(
                (1..=MAX_WORKERS).map(|id| (id, format!("{}-10000", "f".repeat(32)))),
            )),
            // A SHA-256 in hex, as every digest.
            posted: Some("f".repeat(64)),
            image: Some(format!("sha256:{}", "f".repeat(64))),
            progress: (u64::MAX, u64::MAX),
            reason: Some(worst(MAX_REASON_BYTES * 4)),
            // The longest kind's name.
            failure: Some(lb_domain::cluster::view::FailureKind::InfrastructureImagePull),
            // Every pair ended so.
            ended_by_platform: (0..MAX_WORKERS).collect(),
            unreachable_since: Some(u64::MAX),
            started_at: Some(u64::MAX),
            events: u64::MAX,
            execution: Some("e".repeat(80)),
            generation: u32::MAX,
            continue_as: Some("c".repeat(80)),
            handover: true,
            usage: worst_usage(),
            orchestration: lb_domain::capacity::cost::Orchestration {
                transitions: u64::MAX,
                invocations: u64::MAX,
                mb_ms: u64::MAX,
                dynamo_requests: u64::MAX,
            },
        },
    }
}

/// The most a run's GPU count holds: every kind it tells apart, with a label value's longest
/// instance type, and a pod running in every Job.
fn worst_usage() -> Ledger {
    let lines = (0..lb_domain::capacity::cost::MAX_LINES)
        .map(|i| UsageLine {
            kind: NodeKind {
                instance_type: format!("{i:x}").repeat(63),
                capacity: CapacityType::OnDemand,
            },
            held: u64::MAX,
            run_again: u64::MAX,
        })
        .collect();
    // Every Job running disrupted on the last line, at the largest counts and starts.
    let entry = JobEntry {
        mark: JobMark::Running(Running {
            line: lb_domain::capacity::cost::MAX_LINES - 1,
            disrupted: true,
        }),
        failed: Some(COUNT_CAP),
        reclaims: COUNT_CAP,
        charged: COUNT_CAP,
        excess: COUNT_CAP,
        moves: COUNT_CAP,
        start: Some(u64::MAX),
    };
    Ledger {
        lines,
        jobs: vec![entry; MAX_WORKERS as usize],
        gpus: u32::MAX,
        last: u64::MAX,
        lost: u64::MAX,
        lost_since: Some(u64::MAX),
        lost_until: u64::MAX,
    }
}

/// A Lambda error with the longest message a function reports, as the runtime reports it.
fn error() -> TaskError {
    let diagnostic = lambda_runtime::Diagnostic::from(lb_pipeline::FnError::RunState(worst(
        MAX_ERROR_MESSAGE_BYTES * 4,
    )));
    assert!(diagnostic.error_message.len() <= MAX_ERROR_MESSAGE_BYTES);
    TaskError::lambda(diagnostic.error_type, diagnostic.error_message)
}

/// Which stage fails, if any.
#[derive(Clone, Copy, Debug)]
enum Failing {
    None,
    Intake,
    Launch,
    Monitor,
    Finalize,
}

fn tasks(failing: Failing) -> TaskMap {
    let fails = move |stage: &str| format!("{failing:?}") == stage;
    let (i, l, m, f) = (
        fails("Intake"),
        fails("Launch"),
        fails("Monitor"),
        fails("Finalize"),
    );
    TaskMap::new()
        // The wake table's write succeeds; nothing wakes the wait, its timeout ends it.
        .with("aws-sdk:dynamodb:updateItem", |_| async {
            Ok(serde_json::json!({}))
        })
        .with("IntakeFunctionArn", move |_| async move {
            if i {
                return Err(error());
            }
            Ok(serde_json::to_value(IntakeOutput {
                action: Action::Run,
                reason: Some(worst(MAX_REASON_BYTES * 4)),
                submission: Some(submission()),
            })
            .unwrap())
        })
        .with("LaunchFunctionArn", move |_| async move {
            if l {
                return Err(error());
            }
            Ok(serde_json::to_value(run(RunPhase::Running)).unwrap())
        })
        .with("MonitorFunctionArn", move |input: Value| async move {
            if m {
                return Err(error());
            }
            let rounds = input["run"]["monitor"]["rounds"].as_u64().unwrap_or(0);
            let phase = if rounds == u64::MAX {
                RunPhase::Finished
            } else {
                RunPhase::Running
            };
            Ok(serde_json::to_value(run(phase)).unwrap())
        })
        .with("FinalizeFunctionArn", move |_| async move {
            if f {
                return Err(error());
            }
            Ok(serde_json::to_value(finalize::FinalizeOutput {
                status: "FAILED".parse().unwrap(),
                pipeline_error: true,
                platform_failure: true,
                reason: Some(worst(MAX_REASON_BYTES * 4)),
            })
            .unwrap())
        })
}

/// The largest input, output or result of each state over a run.
async fn largest(failing: Failing) -> (Status, BTreeMap<String, usize>) {
    let options = Options {
        time_scale: 0.001,
        random_seed: Some(1),
        ..Options::default()
    };
    let result = Executor::new(tasks(failing), options)
        .unwrap()
        .run(&machine(), "payloads", batch())
        .await
        .unwrap();
    let mut sizes = BTreeMap::new();
    let mut state = "(execution)".to_owned();
    for event in &result.history {
        if let Some(name) = event.state_name() {
            state = name.to_owned();
        }
        for key in ["input", "output"] {
            let Some(value) = event.details.get(key) else {
                continue;
            };
            let label = if event.event_type.is_state_entered() || event.event_type.is_state_exited()
            {
                state.clone()
            } else {
                format!("{state} ({})", event.event_type.as_str())
            };
            let size = value.to_string().len();
            let entry = sizes.entry(label).or_insert(0);
            *entry = (*entry).max(size);
        }
    }
    (result.status, sizes)
}

#[tokio::test]
async fn every_state_stays_far_below_the_payload_limit() {
    let mut overall: BTreeMap<String, usize> = BTreeMap::new();
    for (failing, ends) in [
        (Failing::None, Status::Failed), // FAILED with pipeline_error: the execution fails
        (Failing::Intake, Status::Failed),
        (Failing::Launch, Status::Failed),
        (Failing::Monitor, Status::Failed),
        (Failing::Finalize, Status::Failed),
    ] {
        let (status, sizes) = largest(failing).await;
        assert_eq!(status, ends, "{failing:?}");
        assert!(
            sizes.keys().any(|s| s.starts_with("Finalize")),
            "{failing:?} reached Finalize: {sizes:?}"
        );
        for (state, size) in sizes {
            let entry = overall.entry(state).or_insert(0);
            *entry = (*entry).max(size);
        }
    }
    println!("largest payload per state (bytes, limit {LIMIT}):");
    for (state, size) in &overall {
        println!(
            "  {state:<36} {size:>7}  {:>4.1}%",
            *size as f64 * 100.0 / LIMIT as f64
        );
    }
    // Far below: at most half, so a field that grows later does not tip a run into a failure
    // no Catch handles.
    for (state, size) in &overall {
        assert!(*size <= LIMIT / 2, "{state}: {size} bytes");
    }
}
