//! The reaper's decisions: which ended executions it finishes, and with what reason, for an
//! execution that ended without reaching Finalize (stopped, timed out, failed outside any
//! Catch) or whose Finalize never completed.

use serde_json::Value;

use crate::status::ExecutionStatus;

/// The statuses of Step Functions' "Execution Status Change" events the reaper acts on: the
/// endings that can leave Jobs, a team's place and an unfinished EvalAI status behind.
pub const REAPED_STATUSES: [ExecutionStatus; 3] = [
    ExecutionStatus::Failed,
    ExecutionStatus::TimedOut,
    ExecutionStatus::Aborted,
];

/// The error names the reaper gives Finalize (see [`Verdict::Reap`]).
pub const ERROR_NAMES: [&str; 3] = ["ExecutionAborted", "ExecutionTimedOut", "ExecutionFailed"];

/// What the reaper does with an execution that ended with `status`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Verdict {
    /// Still running, or succeeded (Finalize ran): nothing.
    Leave,
    /// Finish it as Finalize would, with this caught error (`$.error` of the state handed
    /// to Finalize): its stable name and a plain reason for the participant and the record.
    Reap {
        /// `ExecutionAborted`, `ExecutionTimedOut` or `ExecutionFailed`.
        error: &'static str,
        /// What happened, in words.
        cause: String,
    },
}

/// The verdict on an execution that ended with `status` (`error` and `cause` as the event or
/// `DescribeExecution` give them), whose last state was `state`.
pub fn verdict(status: ExecutionStatus, error: Option<&str>, state: Option<&Value>) -> Verdict {
    let finalized = state.is_some_and(|s| s.get("final").is_some());
    if finalized {
        // Finalize ran to the end; the execution then failed on purpose so operators see a
        // pipeline error (the Choice after Finalize). Nothing is left to do.
        return Verdict::Leave;
    }
    let (name, cause) = match status {
        ExecutionStatus::Aborted => (
            "ExecutionAborted",
            "the evaluation was stopped by an operator before it finished".to_string(),
        ),
        ExecutionStatus::TimedOut => (
            "ExecutionTimedOut",
            "the evaluation ran past the pipeline's time limit".to_string(),
        ),
        ExecutionStatus::Failed => (
            "ExecutionFailed",
            match error.map(str::trim).filter(|e| !e.is_empty()) {
                Some(error) => {
                    format!("the pipeline failed ({error}) before the evaluation finished")
                }
                None => "the pipeline failed before the evaluation finished".to_string(),
            },
        ),
        ExecutionStatus::Running | ExecutionStatus::Succeeded | ExecutionStatus::PendingRedrive => {
            return Verdict::Leave
        }
    };
    Verdict::Reap { error: name, cause }
}

/// The state to hand Finalize for a reaped execution: its last state with the reaper's error
/// where a Catch would have put one (a state that is no object is left as it is: Finalize
/// then finds nothing it claimed).
pub fn finalize_state(mut state: Value, error: &str, cause: &str) -> Value {
    if let Some(object) = state.as_object_mut() {
        object.insert(
            "error".into(),
            serde_json::json!({"Error": error, "Cause": cause}),
        );
    }
    state
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn only_endings_without_finalize_are_reaped() {
        let running = json!({"intake": {}, "run": {}});
        let done = json!({"intake": {}, "final": {"status": "FINISHED"}});
        for status in REAPED_STATUSES {
            assert!(
                matches!(verdict(status, None, Some(&running)), Verdict::Reap { .. }),
                "{status}"
            );
            // Finalize ran (the execution failed after it on purpose): nothing to do.
            assert_eq!(
                verdict(status, None, Some(&done)),
                Verdict::Leave,
                "{status}"
            );
        }
        for status in [
            ExecutionStatus::Running,
            ExecutionStatus::Succeeded,
            ExecutionStatus::PendingRedrive,
        ] {
            assert_eq!(
                verdict(status, None, Some(&running)),
                Verdict::Leave,
                "{status}"
            );
        }
        // No state read (the history gone): still reaped, Finalize's claim check decides.
        assert!(matches!(
            verdict(ExecutionStatus::Aborted, None, None),
            Verdict::Reap { .. }
        ));
    }

    #[test]
    fn the_reason_says_what_happened_in_plain_words() {
        let cause = |status, error| match verdict(status, error, None) {
            Verdict::Reap { error, cause } => (error, cause),
            Verdict::Leave => panic!("{status} left"),
        };
        assert_eq!(
            cause(ExecutionStatus::Aborted, None),
            (
                "ExecutionAborted",
                "the evaluation was stopped by an operator before it finished".into()
            )
        );
        assert_eq!(
            cause(ExecutionStatus::TimedOut, None).0,
            "ExecutionTimedOut"
        );
        assert_eq!(
            cause(ExecutionStatus::Failed, Some("States.Runtime")).1,
            "the pipeline failed (States.Runtime) before the evaluation finished"
        );
        assert_eq!(
            cause(ExecutionStatus::Failed, Some("  ")).1,
            "the pipeline failed before the evaluation finished"
        );
    }

    #[test]
    fn the_error_goes_where_a_catch_puts_it() {
        let state = finalize_state(
            json!({"intake": {"action": "run"}}),
            "ExecutionAborted",
            "stopped",
        );
        assert_eq!(
            state["error"],
            json!({"Error": "ExecutionAborted", "Cause": "stopped"})
        );
        assert_eq!(state["intake"]["action"], "run");
        assert_eq!(finalize_state(json!([1]), "E", "c"), json!([1]));
        assert_eq!(
            crate::run::finalize::caught_error(&state).as_deref(),
            Some("ExecutionAborted: stopped")
        );
        // The participant reads the reaper's plain words, never only an error name.
        let Verdict::Reap { error, cause } = verdict(ExecutionStatus::Aborted, None, None) else {
            panic!("reaped")
        };
        let state = finalize_state(json!({}), error, &cause);
        let caught = crate::run::finalize::caught_error(&state).unwrap();
        assert_eq!(
            crate::run::finalize::participant_reason(&caught),
            "the evaluation was stopped by an operator before it finished, not because of your agent; the organisers have been alerted"
        );
    }
}
