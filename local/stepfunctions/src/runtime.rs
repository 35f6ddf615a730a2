//! A state's failure at run time (error name and cause) and how `ErrorEquals` matches it.

use lb_asl::AslError;
use serde_json::{Map, Value};

/// `States.ALL`: matches every error except the terminal ones.
pub const STATES_ALL: &str = "States.ALL";
/// `States.TaskFailed`: matches every error except `States.Timeout` (and the terminal ones).
pub const STATES_TASK_FAILED: &str = "States.TaskFailed";
/// A Task ran longer than its `TimeoutSeconds`.
pub const STATES_TIMEOUT: &str = "States.Timeout";
/// A callback task heard no heartbeat for its `HeartbeatSeconds`.
pub const STATES_HEARTBEAT_TIMEOUT: &str = "States.HeartbeatTimeout";
/// An evaluation failure the service cannot process; never retried, never caught.
pub const STATES_RUNTIME: &str = "States.Runtime";
/// A payload over the size quota; never retried, never caught.
pub const STATES_DATA_LIMIT_EXCEEDED: &str = "States.DataLimitExceeded";

/// An error a state reports: what `Retry`/`Catch` match and what a catcher's error output
/// (`{"Error": ..., "Cause": ...}`) holds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Failure {
    /// The error name (empty when a `Fail` state names none).
    pub error: String,
    /// The cause, when there is one (a `States.Timeout` has none).
    pub cause: Option<String>,
}

impl Failure {
    pub(crate) fn new(error: impl Into<String>, cause: Option<String>) -> Failure {
        Failure {
            error: error.into(),
            cause,
        }
    }

    pub(crate) fn runtime(cause: impl Into<String>) -> Failure {
        Failure::new(STATES_RUNTIME, Some(cause.into()))
    }

    pub(crate) fn from_asl(error: AslError) -> Failure {
        Failure::new(error.name(), Some(error.to_string()))
    }

    /// Errors that end the execution whatever the state's `Retry` and `Catch` say.
    pub(crate) fn is_terminal(&self) -> bool {
        self.error == STATES_RUNTIME || self.error == STATES_DATA_LIMIT_EXCEEDED
    }

    /// The error output a catcher places with its `ResultPath`.
    pub(crate) fn output(&self) -> Value {
        let mut map = Map::new();
        map.insert("Error".into(), Value::String(self.error.clone()));
        if let Some(cause) = &self.cause {
            map.insert("Cause".into(), Value::String(cause.clone()));
        }
        Value::Object(map)
    }
}

/// Whether a retrier's or catcher's `ErrorEquals` matches `failure`, as Step Functions
/// matches: exact names, `States.ALL` for anything, `States.TaskFailed` for anything but
/// `States.Timeout`; terminal errors (`States.Runtime`, `States.DataLimitExceeded`) never.
pub(crate) fn matches(error_equals: &[String], failure: &Failure) -> bool {
    if failure.is_terminal() {
        return false;
    }
    error_equals.iter().any(|name| {
        name == STATES_ALL
            || (name == STATES_TASK_FAILED && failure.error != STATES_TIMEOUT)
            || *name == failure.error
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(list: &[&str]) -> Vec<String> {
        list.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn states_all_matches_everything_but_terminal_errors() {
        let all = names(&["States.ALL"]);
        assert!(matches(&all, &Failure::new("KubeTransient", None)));
        assert!(matches(&all, &Failure::new("States.Timeout", None)));
        assert!(!matches(&all, &Failure::runtime("bad path")));
        assert!(!matches(
            &all,
            &Failure::new(STATES_DATA_LIMIT_EXCEEDED, None)
        ));
        // Naming them explicitly does not help: they always end the execution.
        assert!(!matches(
            &names(&["States.Runtime"]),
            &Failure::runtime("x")
        ));
    }

    #[test]
    fn task_failed_matches_everything_but_timeouts() {
        let tf = names(&["States.TaskFailed"]);
        assert!(matches(&tf, &Failure::new("Lambda.Unknown", None)));
        assert!(matches(
            &tf,
            &Failure::new("States.ResultPathMatchFailure", None)
        ));
        assert!(!matches(&tf, &Failure::new("States.Timeout", None)));
    }

    #[test]
    fn other_names_match_exactly() {
        let list = names(&["ErrorA", "ErrorB"]);
        assert!(matches(&list, &Failure::new("ErrorB", None)));
        assert!(!matches(&list, &Failure::new("errorb", None)));
        assert!(!matches(&list, &Failure::new("ErrorC", None)));
    }

    #[test]
    fn the_error_output_has_a_cause_only_when_there_is_one() {
        assert_eq!(
            Failure::new("Error here", None).output(),
            serde_json::json!({"Error": "Error here"})
        );
        assert_eq!(
            Failure::new("E", Some("c".into())).output(),
            serde_json::json!({"Error": "E", "Cause": "c"})
        );
    }
}
