//! One execution's history, bounded by construction: every Monitor round adds an upper bound
//! of the events it cost, and before the next round could take the count past
//! [`EXECUTION_BUDGET`] the run continues as a new execution of the same state machine (Step
//! Functions' documented pattern for long loops: start a new execution, end this one), well
//! under the service's 25,000-event limit whatever wakes the loop and however often.
//!
//! The constants are upper bounds of the deployed definition's events (Step Functions
//! developer guide, "Execution history events"); `crates/pipeline/tests/statemachine.rs`
//! recounts them from `statemachine/submission.asl.json`, so the two cannot drift apart.

/// Step Functions ends an execution that reaches this many history events (`States.Runtime`,
/// which nothing catches).
pub const SERVICE_LIMIT: u64 = 25_000;

/// The events one execution may take before its run continues as a new execution.
pub const EXECUTION_BUDGET: u64 = 10_000;

// Well under the service's limit: the bounds could be off by half and still hold.
const _: () = assert!(EXECUTION_BUDGET * 2 < SERVICE_LIMIT);

/// The smallest budget a deployment (or a rehearsal) may set: room for the opening, a round
/// and the closing at their worst, and then some.
pub const MIN_BUDGET: u64 = 600;

/// A first execution's events up to its first Monitor round, at their worst: started,
/// `OneSubmission?`, `Unbatch`, Intake and Launch with every retry, `Eligible?`.
pub const OPENING_EVENTS: u64 = 90;

/// A continued execution's events up to its first Monitor round: started, `OneSubmission?`,
/// `Resume`.
pub const RESUMED_EVENTS: u64 = 5;

/// One round without the Monitor's retries, at its worst: `Next?`, the hold, the wait with
/// every retry of its write (or its failure and the plain poll after it), the Monitor.
pub const ROUND_EVENTS: u64 = 30;

/// What each retried attempt of a Lambda Task adds (scheduled, started, failed).
pub const RETRY_EVENTS: u64 = 3;

/// The Monitor Task's retries at most (the sum of its retriers' `MaxAttempts`).
pub const MONITOR_MAX_RETRIES: u64 = 14;

/// `LaunchAdmitted` (and the `Next?` before it) with every retry: a waiting submission's
/// turn came.
pub const ADMITTED_EVENTS: u64 = 40;

/// The most any ending adds after a Monitor round: `ContinueAsNew` failing after its retries,
/// then Finalize with every retry, `Failed?` and the end.
pub const CLOSING_EVENTS: u64 = 240;

/// What a round whose Monitor invocation was retried `retries` times cost at most.
pub fn round_events(retries: u64) -> u64 {
    ROUND_EVENTS + RETRY_EVENTS * retries.min(MONITOR_MAX_RETRIES)
}

/// Whether the run must continue as a new execution now, after a round that left this
/// execution's count at `events`: the next round at its worst (every retry, a Launch for an
/// admitted turn) and the closing at its worst would no longer fit `budget`.
pub fn continue_due(events: u64, budget: u64) -> bool {
    let next = round_events(MONITOR_MAX_RETRIES) + ADMITTED_EVENTS + CLOSING_EVENTS;
    events.saturating_add(next) > budget
}

/// Where the count of an execution's events starts when a round runs in `current` and the
/// count so far was `known`'s: `None` when it is the same execution (the count goes on).
/// Another one is a continuation starting its own history; no known execution is a run
/// launched before the count existed, counted from a first execution's opening.
pub fn entering(known: Option<&str>, current: &str) -> Option<Entered> {
    match known {
        Some(known) if known == current => None,
        Some(_) => Some(Entered {
            events: RESUMED_EVENTS,
            continued: true,
        }),
        None => Some(Entered {
            events: OPENING_EVENTS,
            continued: false,
        }),
    }
}

/// A round in an execution the count had not seen yet.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Entered {
    /// Its events before the round.
    pub events: u64,
    /// It continues an earlier execution of the run (whose queue entry names the earlier one).
    pub continued: bool,
}

/// The rounds one execution holds at most when every round is at its worst (no retries):
/// what the budget buys.
pub fn rounds_per_execution(budget: u64) -> u64 {
    let mut events = OPENING_EVENTS;
    let mut rounds = 0;
    loop {
        events += round_events(0);
        rounds += 1;
        if continue_due(events, budget) {
            return rounds;
        }
    }
}

/// The execution a run continued as, from the output of the execution that ended to start it
/// (`Continued` outputs `StartExecution`'s answer, `{ExecutionArn, StartDate}`); `None` for
/// any other output.
pub fn continued_as(output: &serde_json::Value) -> Option<&str> {
    output
        .get("ExecutionArn")?
        .as_str()
        .filter(|arn| arn.starts_with("arn:") && arn.contains(":execution:"))
}

/// The longest execution name Step Functions accepts.
pub const MAX_EXECUTION_NAME: usize = 80;

/// The name of the `generation`-th continuation of the run whose first execution is
/// `lineage`: `<lineage>-c<generation>`, the lineage cut so the name fits 80 characters.
/// Deterministic, so a retried `StartExecution` asks for the same execution (the API then
/// answers with it instead of starting a second one).
pub fn continuation_name(lineage: &str, generation: u32) -> String {
    let suffix = format!("-c{generation}");
    let room = MAX_EXECUTION_NAME.saturating_sub(suffix.len());
    // Execution names are ASCII (letters, digits, `-`, `_`); cut on a character anyway.
    let cut = lineage
        .char_indices()
        .map(|(i, c)| i + c.len_utf8())
        .take_while(|end| *end <= room)
        .last()
        .unwrap_or(0);
    format!("{}{suffix}", &lineage[..cut])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_budgeted_execution_never_reaches_its_budget_whatever_each_round_costs() {
        for budget in [MIN_BUDGET, 2_000, EXECUTION_BUDGET] {
            for retries in [0, 1, MONITOR_MAX_RETRIES, 1_000] {
                let mut events = OPENING_EVENTS;
                let mut rounds = 0u64;
                loop {
                    events += round_events(retries) + ADMITTED_EVENTS * u64::from(rounds == 3);
                    rounds += 1;
                    assert!(
                        events + CLOSING_EVENTS <= budget,
                        "{budget} {retries} {rounds}"
                    );
                    if continue_due(events, budget) {
                        break;
                    }
                }
                assert!(rounds >= 1, "{budget}");
            }
        }
    }

    #[test]
    fn the_default_budget_holds_hundreds_of_rounds() {
        assert_eq!(rounds_per_execution(EXECUTION_BUDGET), 319);
        assert!(rounds_per_execution(MIN_BUDGET) >= 2);
    }

    #[test]
    fn a_new_execution_starts_its_own_count() {
        assert_eq!(entering(Some("a"), "a"), None);
        assert_eq!(
            entering(Some("a"), "a-c1"),
            Some(Entered {
                events: RESUMED_EVENTS,
                continued: true
            })
        );
        assert_eq!(entering(None, "a").map(|e| e.continued), Some(false));
    }

    #[test]
    fn only_a_continuation_output_names_the_next_execution() {
        let arn = "arn:aws:states:us-east-1:1:execution:m:a-c1";
        let out = serde_json::json!({"ExecutionArn": arn, "StartDate": 1.5});
        assert_eq!(continued_as(&out), Some(arn));
        for other in [
            serde_json::json!({"intake": {}, "final": {}}),
            serde_json::json!({"ExecutionArn": "a-c1"}),
            serde_json::json!({"ExecutionArn": 7}),
            serde_json::json!([arn]),
        ] {
            assert_eq!(continued_as(&other), None, "{other}");
        }
    }

    #[test]
    fn continuation_names_are_deterministic_and_fit() {
        assert_eq!(continuation_name("local-7", 1), "local-7-c1");
        assert_eq!(continuation_name("local-7", 12), "local-7-c12");
        let long = "x".repeat(80);
        let name = continuation_name(&long, 123);
        assert_eq!(name.len(), MAX_EXECUTION_NAME);
        assert!(name.ends_with("-c123"));
        assert_eq!(continuation_name(&long, 123), name);
    }
}
