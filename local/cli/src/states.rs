//! The states a run hands on, as the state machine gave them to each function and to the run it
//! continued as: recorded per release (`statemachine/states/`), the fixtures later code must read.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::Context;
use local_stepfunctions::{EventType, HistoryEvent};
use serde_json::Value;

/// What a chain of executions handed on, the first of each kind: `launch`, `launch-admitted`,
/// `monitor-<phase>` (the run's phase as the round receives it), `finalize`, and `continued` (a
/// continued execution's input).
pub fn handed_on(history: &[HistoryEvent]) -> BTreeMap<String, Value> {
    let mut found = BTreeMap::new();
    let mut state = "";
    for event in history {
        let input = event.details.get("input");
        let kind = match event.event_type {
            EventType::TaskStateEntered => {
                state = event.details["name"].as_str().unwrap_or_default();
                continue;
            }
            EventType::ExecutionStarted if input.is_some_and(|i| i.get("continued").is_some()) => {
                "continued".to_string()
            }
            EventType::LambdaFunctionScheduled => match state {
                "Launch" => "launch".to_string(),
                "LaunchAdmitted" => "launch-admitted".to_string(),
                "Finalize" => "finalize".to_string(),
                "Monitor" => {
                    let phase = input.and_then(|i| i["run"]["monitor"]["state"].as_str());
                    format!("monitor-{}", phase.unwrap_or("unknown"))
                }
                _ => continue,
            },
            _ => continue,
        };
        if let Some(input) = input {
            found.entry(kind).or_insert_with(|| input.clone());
        }
    }
    found
}

/// Writes what every chain handed on into `dir`, one `<kind>.json` each (the first chain that
/// handed a kind on gives it).
pub fn record<'a>(
    dir: &Path,
    chains: impl IntoIterator<Item = &'a [HistoryEvent]>,
) -> anyhow::Result<usize> {
    let mut all = BTreeMap::new();
    for history in chains {
        for (kind, input) in handed_on(history) {
            all.entry(kind).or_insert(input);
        }
    }
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    for (kind, input) in &all {
        let path = dir.join(format!("{kind}.json"));
        let text = serde_json::to_string_pretty(input)? + "\n";
        std::fs::write(&path, text).with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(all.len())
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn event(event_type: EventType, details: Value) -> HistoryEvent {
        HistoryEvent {
            id: 0,
            previous_event_id: 0,
            timestamp: time::OffsetDateTime::UNIX_EPOCH,
            event_type,
            details,
        }
    }

    fn task(state: &str, input: Value) -> [HistoryEvent; 2] {
        [
            event(
                EventType::TaskStateEntered,
                json!({"name": state, "input": {}}),
            ),
            event(
                EventType::LambdaFunctionScheduled,
                json!({"resource": "fn", "input": input}),
            ),
        ]
    }

    #[test]
    fn each_kind_is_kept_once_and_a_round_by_its_phase() {
        let running = |n: u64| json!({"run": {"monitor": {"state": "running", "round": n}}});
        let mut history = vec![event(
            EventType::ExecutionStarted,
            json!({"input": {"continued": {"from": "a"}}}),
        )];
        history.extend(task("Launch", json!({"submission": 1})));
        history.extend(task(
            "Monitor",
            json!({"run": {"monitor": {"state": "queued"}}}),
        ));
        history.extend(task("Monitor", running(1)));
        history.extend(task("Monitor", running(2)));
        history.extend(task("Finalize", json!({"state": {}})));
        // A service task (the wait for a change) hands nothing to our code.
        history.push(event(
            EventType::TaskStateEntered,
            json!({"name": "WaitForChange"}),
        ));
        history.push(event(EventType::TaskScheduled, json!({"parameters": {}})));
        let found = handed_on(&history);
        let kinds: Vec<&str> = found.keys().map(String::as_str).collect();
        assert_eq!(
            kinds,
            [
                "continued",
                "finalize",
                "launch",
                "monitor-queued",
                "monitor-running"
            ]
        );
        assert_eq!(found["monitor-running"], running(1));
        assert_eq!(found["continued"], json!({"continued": {"from": "a"}}));
    }

    #[test]
    fn an_execution_started_from_a_message_is_not_a_continuation() {
        let history = [event(
            EventType::ExecutionStarted,
            json!({"input": {"body": "{}"}}),
        )];
        assert!(handed_on(&history).is_empty());
    }
}
