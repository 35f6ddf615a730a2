//! Intake's decision in the state: each kind keeps the shape the Choice and earlier versions
//! read, and a decision that names less than it must does not decode.

use lb_pipeline::payload::{Action, Decision, ExecutionState};
use serde_json::{json, Value};

fn submission(image: &str, workers: u32) -> Value {
    json!({
        "challenge_id": 1, "phase_id": 2, "submission_id": 3, "team_id": 4,
        "team_name": "team", "leaderboard": "2.0", "track": "SENSORS", "image": image,
        "routes": 20, "workers": workers, "resuming": false, "execution": "exec",
        "submitted_at": 0
    })
}

fn decoded(intake: Value) -> Result<Decision, String> {
    ExecutionState::from_value(json!({ "intake": intake }))
        .map(|state| state.intake.expect("an intake"))
        .map_err(|e| e.to_string())
}

#[test]
fn each_decision_keeps_the_state_s_shape() {
    let cases = [
        json!({"action": "run", "submission": submission("reg/img@sha256:ab", 4)}),
        json!({"action": "skip", "reason": "duplicate", "submission": submission("", 0)}),
        json!({"action": "skip", "reason": "not ours"}),
        json!({"action": "reject", "reason": "no image", "submission": submission("", 0)}),
    ];
    for (wire, action) in
        cases
            .iter()
            .zip([Action::Run, Action::Skip, Action::Skip, Action::Reject])
    {
        let decision = decoded(wire.clone()).unwrap();
        assert_eq!(decision.action(), action);
        assert_eq!(
            serde_json::to_value(&decision).unwrap(),
            *wire,
            "{decision:?}"
        );
    }
}

#[test]
fn a_run_or_a_refusal_without_what_it_needs_does_not_decode() {
    let cases = [
        (json!({"action": "run"}), "whole submission"),
        (
            json!({"action": "run", "submission": submission("", 4)}),
            "whole submission",
        ),
        (
            json!({"action": "run", "submission": submission("img:1", 0)}),
            "whole submission",
        ),
        (
            json!({"action": "reject", "reason": "no"}),
            "refusal needs the submission",
        ),
    ];
    for (wire, said) in cases {
        let error = decoded(wire.clone()).unwrap_err();
        assert!(
            error.contains("intake") && error.contains(said),
            "{wire}: {error}"
        );
    }
}

#[test]
fn a_reason_missing_from_an_older_state_reads_as_a_plain_one() {
    let skip = decoded(json!({"action": "skip"})).unwrap();
    assert_eq!(skip.reason(), Some("skipped"));
    assert!(skip.submission().is_none());
}
