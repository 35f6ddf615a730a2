//! An embedded Amazon States Language executor: runs `statemachine/*.asl.json` on one
//! machine, with the Lambda handlers called in-process (the project's local mode).
//!
//! The definition is parsed and validated completely at load ([`StateMachine::load`]);
//! anything this executor does not run is refused with the location of the field. The
//! JSONPath, `.$`, intrinsic-function and InputPath/Parameters/ResultSelector/ResultPath/
//! OutputPath evaluation is `lb-asl`'s, the same code the Job template renderer uses.
//!
//! ```
//! use std::collections::HashMap;
//! use local_stepfunctions::{Executor, Options, StateMachine, Status, TaskError, TaskMap};
//! use serde_json::json;
//!
//! # tokio::runtime::Runtime::new().unwrap().block_on(async {
//! let definition = json!({
//!     "StartAt": "Add",
//!     "States": {
//!         "Add": {
//!             "Type": "Task",
//!             "Resource": "${AddFunctionArn}",
//!             "ResultPath": "$.sum",
//!             "End": true
//!         }
//!     }
//! });
//! let substitutions = HashMap::from([(
//!     "AddFunctionArn".to_owned(),
//!     "arn:aws:lambda:us-east-1:123456789012:function:add".to_owned(),
//! )]);
//! let machine = StateMachine::load(&definition, &substitutions).unwrap();
//! let tasks = TaskMap::new().with("add", |input: serde_json::Value| async move {
//!     let (a, b) = (input["a"].as_i64(), input["b"].as_i64());
//!     match (a, b) {
//!         (Some(a), Some(b)) => Ok(json!(a + b)),
//!         _ => Err(TaskError::lambda("BadInput", "a and b must be integers")),
//!     }
//! });
//! let executor = Executor::new(tasks, Options { time_scale: 0.01, ..Options::default() }).unwrap();
//! let result = executor.run(&machine, "first", json!({"a": 3, "b": 4})).await.unwrap();
//! assert_eq!(result.status, Status::Succeeded);
//! assert_eq!(result.output, Some(json!({"a": 3, "b": 4, "sum": 7})));
//! # });
//! ```

mod callback;
mod choice;
mod definition;
mod error;
mod executor;
mod history;
mod runtime;
mod substitute;
mod tasks;
mod timestamp;
mod versions;

pub use callback::CallbackError;
pub use definition::StateMachine;
pub use error::{LoadError, OptionsError, StartError};
pub use executor::{
    status_change_event, Described, Execution, ExecutionResult, Executor, Options, Status,
};
pub use history::{EventCallback, EventStream, EventType, HistoryEvent};
pub use runtime::{
    STATES_ALL, STATES_DATA_LIMIT_EXCEEDED, STATES_HEARTBEAT_TIMEOUT, STATES_RUNTIME,
    STATES_TASK_FAILED, STATES_TIMEOUT,
};
pub use tasks::{handler, FunctionRef, Handler, TaskError, TaskFuture, TaskMap, Tasks};
