//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use local_stepfunctions::{
    EventType, ExecutionResult, Executor, Options, StateMachine, TaskError, TaskMap,
};
use serde_json::Value;

/// Every test execution must end well within this.
pub const BOUND: Duration = Duration::from_secs(20);

pub fn load(definition: Value) -> StateMachine {
    StateMachine::load(&definition, &HashMap::new()).expect("definition loads")
}

pub fn options(time_scale: f64) -> Options {
    Options {
        time_scale,
        random_seed: Some(7),
        ..Options::default()
    }
}

pub async fn run_with(
    machine: &StateMachine,
    tasks: TaskMap,
    options: Options,
    input: Value,
) -> ExecutionResult {
    let executor = Executor::new(tasks, options).expect("valid options");
    tokio::time::timeout(BOUND, executor.run(machine, "test-run", input))
        .await
        .expect("execution ends in time")
        .expect("execution starts")
}

pub async fn run(machine: &StateMachine, tasks: TaskMap, input: Value) -> ExecutionResult {
    run_with(machine, tasks, options(0.01), input).await
}

pub fn types(result: &ExecutionResult) -> Vec<EventType> {
    result.history.iter().map(|e| e.event_type).collect()
}

/// A handler's calls: when each happened and with what input.
#[derive(Clone, Default)]
pub struct Calls(Arc<Mutex<Vec<(Instant, Value)>>>);

impl Calls {
    pub fn record(&self, input: &Value) -> usize {
        let mut calls = self.0.lock().unwrap();
        calls.push((Instant::now(), input.clone()));
        calls.len()
    }

    pub fn inputs(&self) -> Vec<Value> {
        self.0
            .lock()
            .unwrap()
            .iter()
            .map(|(_, v)| v.clone())
            .collect()
    }

    pub fn count(&self) -> usize {
        self.0.lock().unwrap().len()
    }

    /// The time between consecutive calls.
    pub fn gaps(&self) -> Vec<Duration> {
        let calls = self.0.lock().unwrap();
        calls.windows(2).map(|w| w[1].0 - w[0].0).collect()
    }
}

/// A handler that fails with the given error types in turn, then returns `ok`.
pub fn failing(calls: Calls, errors: Vec<&'static str>, ok: Value) -> TaskMap {
    TaskMap::new().with("flaky", move |input| {
        let calls = calls.clone();
        let errors = errors.clone();
        let ok = ok.clone();
        async move {
            let n = calls.record(&input);
            match errors.get(n - 1) {
                Some(error) => Err(TaskError::lambda(*error, format!("attempt {n} failed"))),
                None => Ok(ok),
            }
        }
    })
}

pub const FLAKY: &str = "arn:aws:lambda:us-east-1:123456789012:function:flaky";
