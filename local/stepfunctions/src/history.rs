//! The execution history: events with Step Functions' names, ids, previous ids, timestamps
//! and details, recorded as the execution runs and streamed to whoever watches.

use std::fmt;
use std::sync::{Arc, Mutex, MutexGuard};

use serde_json::{Map, Value};
use time::OffsetDateTime;
use tokio::sync::watch;

use crate::runtime::Failure;
use crate::timestamp;

macro_rules! event_types {
    ($($name:ident),* $(,)?) => {
        /// A history event type, named exactly as Step Functions names it.
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
        pub enum EventType {
            $(
                #[doc = concat!("`", stringify!($name), "`")]
                $name,
            )*
        }

        impl EventType {
            /// The AWS name (`TaskStateEntered`).
            pub fn as_str(self) -> &'static str {
                match self {
                    $(EventType::$name => stringify!($name),)*
                }
            }
        }
    };
}

event_types!(
    ExecutionStarted,
    ExecutionSucceeded,
    ExecutionFailed,
    ExecutionAborted,
    ExecutionTimedOut,
    TaskStateEntered,
    TaskStateExited,
    TaskScheduled,
    TaskStarted,
    TaskSubmitted,
    TaskSucceeded,
    TaskFailed,
    TaskTimedOut,
    LambdaFunctionScheduled,
    LambdaFunctionStarted,
    LambdaFunctionSucceeded,
    LambdaFunctionFailed,
    LambdaFunctionTimedOut,
    ChoiceStateEntered,
    ChoiceStateExited,
    WaitStateEntered,
    WaitStateExited,
    PassStateEntered,
    PassStateExited,
    SucceedStateEntered,
    SucceedStateExited,
    FailStateEntered,
    ParallelStateEntered,
    ParallelStateStarted,
    ParallelStateSucceeded,
    ParallelStateFailed,
    ParallelStateExited,
    MapStateEntered,
    MapStateStarted,
    MapIterationStarted,
    MapIterationSucceeded,
    MapIterationFailed,
    MapIterationAborted,
    MapStateSucceeded,
    MapStateFailed,
    MapStateExited,
);

impl fmt::Display for EventType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl EventType {
    /// `<Prefix>StateEntered` for a state type prefix (`Task`, `Choice`, ...).
    pub(crate) fn entered(prefix: &str) -> EventType {
        match prefix {
            "Task" => EventType::TaskStateEntered,
            "Pass" => EventType::PassStateEntered,
            "Wait" => EventType::WaitStateEntered,
            "Choice" => EventType::ChoiceStateEntered,
            "Succeed" => EventType::SucceedStateEntered,
            "Fail" => EventType::FailStateEntered,
            "Parallel" => EventType::ParallelStateEntered,
            _ => EventType::MapStateEntered,
        }
    }

    /// `<Prefix>StateExited` (a Fail state never exits; it ends the branch).
    pub(crate) fn exited(prefix: &str) -> EventType {
        match prefix {
            "Task" => EventType::TaskStateExited,
            "Pass" => EventType::PassStateExited,
            "Wait" => EventType::WaitStateExited,
            "Choice" => EventType::ChoiceStateExited,
            "Succeed" => EventType::SucceedStateExited,
            "Parallel" => EventType::ParallelStateExited,
            _ => EventType::MapStateExited,
        }
    }

    /// Whether this is a `...StateEntered` event.
    pub fn is_state_entered(self) -> bool {
        self.as_str().ends_with("StateEntered")
    }

    /// Whether this is a `...StateExited` event.
    pub fn is_state_exited(self) -> bool {
        self.as_str().ends_with("StateExited")
    }

    /// Whether this ends the execution.
    pub fn is_execution_end(self) -> bool {
        matches!(
            self,
            EventType::ExecutionSucceeded
                | EventType::ExecutionFailed
                | EventType::ExecutionAborted
                | EventType::ExecutionTimedOut
        )
    }

    /// The key of the details object in AWS's `GetExecutionHistory` output.
    fn details_key(self) -> String {
        let name = self.as_str();
        if self.is_state_entered() {
            return "stateEnteredEventDetails".into();
        }
        if self.is_state_exited() {
            return "stateExitedEventDetails".into();
        }
        let mut chars = name.chars();
        let first = chars.next().map(|c| c.to_ascii_lowercase()).unwrap_or('x');
        format!("{first}{}EventDetails", chars.as_str())
    }
}

/// One history event.
#[derive(Debug, Clone, PartialEq)]
pub struct HistoryEvent {
    /// Sequential from 1.
    pub id: u64,
    /// The event this one follows in its branch of the execution (0 for none), as AWS links
    /// them: concurrent branches and iterations each form their own chain.
    pub previous_event_id: u64,
    /// When it was recorded (wall clock, not scaled).
    pub timestamp: OffsetDateTime,
    /// What happened.
    pub event_type: EventType,
    /// The details object with AWS's field names (`name`, `input`, `output`, `resource`,
    /// `error`, `cause`, ...); `input`/`output`/`parameters` hold JSON values here (AWS sends
    /// them as JSON text, see [`to_aws_json`](Self::to_aws_json)). `Null` when none.
    pub details: Value,
}

impl HistoryEvent {
    /// The state this event belongs to, for state entered/exited events (and the Map state
    /// of iteration events).
    pub fn state_name(&self) -> Option<&str> {
        self.details.get("name").and_then(Value::as_str)
    }

    /// The `error` of a failure event.
    pub fn error(&self) -> Option<&str> {
        self.details.get("error").and_then(Value::as_str)
    }

    /// The event as `GetExecutionHistory` returns it: `{"id", "previousEventId",
    /// "timestamp", "type", "<type>EventDetails": {...}}`, with `input`, `output` and
    /// `parameters` as JSON text.
    pub fn to_aws_json(&self) -> Value {
        let mut out = Map::new();
        out.insert("id".into(), self.id.into());
        out.insert("previousEventId".into(), self.previous_event_id.into());
        out.insert("timestamp".into(), timestamp::format(self.timestamp).into());
        out.insert("type".into(), self.event_type.as_str().into());
        if let Value::Object(details) = &self.details {
            let details: Map<String, Value> = details
                .iter()
                .map(|(k, v)| {
                    let v = match k.as_str() {
                        "input" | "output" | "parameters" => Value::String(v.to_string()),
                        _ => v.clone(),
                    };
                    (k.clone(), v)
                })
                .collect();
            out.insert(self.event_type.details_key(), Value::Object(details));
        }
        Value::Object(out)
    }
}

impl fmt::Display for HistoryEvent {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "#{} {}", self.id, self.event_type)?;
        if let Some(name) = self.state_name() {
            write!(f, " {name}")?;
        }
        if let Some(error) = self.error() {
            write!(f, " {error}")?;
        }
        Ok(())
    }
}

/// Called with every event as it is recorded (from the executor's tasks; keep it quick and
/// never call back into the execution from it).
pub type EventCallback = Arc<dyn Fn(&HistoryEvent) + Send + Sync>;

#[derive(Debug, Clone, Copy, Default)]
struct Progress {
    done: bool,
}

/// The history of one execution, shared by the executor and the watchers.
pub(crate) struct Recorder {
    events: Mutex<Vec<HistoryEvent>>,
    progress: watch::Sender<Progress>,
    limit: usize,
    callback: Option<EventCallback>,
}

impl Recorder {
    pub(crate) fn new(limit: usize, callback: Option<EventCallback>) -> Recorder {
        Recorder {
            events: Mutex::new(Vec::new()),
            progress: watch::Sender::new(Progress::default()),
            limit,
            callback,
        }
    }

    fn lock(&self) -> MutexGuard<'_, Vec<HistoryEvent>> {
        // A panicking callback must not take the history down with it.
        self.events.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn append(
        &self,
        prev: u64,
        event_type: EventType,
        details: Value,
        bypass: bool,
    ) -> Result<u64, Failure> {
        let mut events = self.lock();
        // NB: one slot stays free for the event that ends the execution.
        if !bypass && events.len() + 1 >= self.limit {
            return Err(Failure::runtime(format!(
                "The execution reached the maximum number of history events ({}).",
                self.limit
            )));
        }
        let id = events.len() as u64 + 1;
        let event = HistoryEvent {
            id,
            previous_event_id: prev,
            timestamp: OffsetDateTime::now_utc(),
            event_type,
            details,
        };
        tracing::debug!(id, previous = prev, event = %event, "history event");
        if let Some(callback) = &self.callback {
            callback(&event);
        }
        events.push(event);
        drop(events);
        self.progress.send_modify(|_| {});
        Ok(id)
    }

    /// Records an event; fails with `States.Runtime` when the history is full.
    pub(crate) fn push(
        &self,
        prev: u64,
        event_type: EventType,
        details: Value,
    ) -> Result<u64, Failure> {
        self.append(prev, event_type, details, false)
    }

    /// Records the event that ends the execution, whatever the limit.
    pub(crate) fn push_final(&self, prev: u64, event_type: EventType, details: Value) -> u64 {
        self.append(prev, event_type, details, true)
            .unwrap_or_default()
    }

    pub(crate) fn finish(&self) {
        self.progress.send_modify(|p| p.done = true);
    }

    pub(crate) fn snapshot(&self) -> Vec<HistoryEvent> {
        self.lock().clone()
    }

    pub(crate) fn last_id(&self) -> u64 {
        self.lock().len() as u64
    }

    fn get(&self, index: usize) -> Option<HistoryEvent> {
        self.lock().get(index).cloned()
    }
}

/// Marks the history finished when dropped, so watchers end even if the run panics.
pub(crate) struct FinishGuard(pub Arc<Recorder>);

impl Drop for FinishGuard {
    fn drop(&mut self) {
        self.0.finish();
    }
}

/// Every event of an execution in order, from the first, as they are recorded; ends after
/// the event that ends the execution.
pub struct EventStream {
    recorder: Arc<Recorder>,
    progress: watch::Receiver<Progress>,
    next: usize,
}

impl EventStream {
    pub(crate) fn new(recorder: Arc<Recorder>) -> EventStream {
        let progress = recorder.progress.subscribe();
        EventStream {
            recorder,
            progress,
            next: 0,
        }
    }

    /// The next event, waiting for it if needed; `None` once the execution has ended and
    /// every event was returned.
    pub async fn next(&mut self) -> Option<HistoryEvent> {
        loop {
            // NB: mark the state seen before reading, so an event recorded in between
            // still wakes `changed` below.
            let done = self.progress.borrow_and_update().done;
            if let Some(event) = self.recorder.get(self.next) {
                self.next += 1;
                return Some(event);
            }
            if done {
                return None;
            }
            if self.progress.changed().await.is_err() {
                return self.recorder.get(self.next).inspect(|_| self.next += 1);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn details_keys_follow_aws_naming() {
        assert_eq!(
            EventType::TaskStateEntered.details_key(),
            "stateEnteredEventDetails"
        );
        assert_eq!(
            EventType::ChoiceStateExited.details_key(),
            "stateExitedEventDetails"
        );
        assert_eq!(
            EventType::LambdaFunctionScheduled.details_key(),
            "lambdaFunctionScheduledEventDetails"
        );
        assert_eq!(
            EventType::MapIterationStarted.details_key(),
            "mapIterationStartedEventDetails"
        );
        assert_eq!(
            EventType::ExecutionFailed.details_key(),
            "executionFailedEventDetails"
        );
    }

    #[test]
    fn aws_json_encodes_payloads_as_text() {
        let recorder = Recorder::new(10, None);
        recorder
            .push(
                0,
                EventType::PassStateExited,
                json!({"name": "P", "output": {"a": 1}}),
            )
            .unwrap();
        let json = recorder.snapshot()[0].to_aws_json();
        assert_eq!(json["type"], "PassStateExited");
        assert_eq!(json["id"], 1);
        assert_eq!(json["stateExitedEventDetails"]["output"], "{\"a\":1}");
        assert!(json["timestamp"].as_str().unwrap().ends_with('Z'));
    }

    #[test]
    fn the_limit_keeps_a_slot_for_the_final_event() {
        let recorder = Recorder::new(3, None);
        recorder
            .push(0, EventType::ExecutionStarted, Value::Null)
            .unwrap();
        recorder
            .push(1, EventType::PassStateEntered, Value::Null)
            .unwrap();
        let err = recorder
            .push(2, EventType::PassStateExited, Value::Null)
            .unwrap_err();
        assert_eq!(err.error, "States.Runtime");
        assert_eq!(
            recorder.push_final(2, EventType::ExecutionFailed, Value::Null),
            3
        );
        assert_eq!(recorder.last_id(), 3);
    }

    #[tokio::test]
    async fn a_stream_sees_every_event_then_ends() {
        let recorder = Arc::new(Recorder::new(100, None));
        let mut stream = EventStream::new(recorder.clone());
        let writer = {
            let recorder = recorder.clone();
            tokio::spawn(async move {
                for i in 0..50 {
                    recorder
                        .push(i, EventType::PassStateEntered, Value::Null)
                        .unwrap();
                    tokio::task::yield_now().await;
                }
                recorder.finish();
            })
        };
        let mut ids = Vec::new();
        let read = async {
            while let Some(e) = stream.next().await {
                ids.push(e.id);
            }
        };
        tokio::time::timeout(std::time::Duration::from_secs(5), read)
            .await
            .unwrap();
        writer.await.unwrap();
        assert_eq!(ids, (1..=50).collect::<Vec<u64>>());
    }
}
