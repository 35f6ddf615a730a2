//! The callback pattern (`.waitForTaskToken`): one task token per attempt, and
//! `SendTaskSuccess`, `SendTaskFailure` and `SendTaskHeartbeat` with the errors the Step
//! Functions API reference gives them.

use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Mutex};

use serde_json::Value;
use tokio::sync::{oneshot, Notify};

/// Longest task token the API accepts.
pub const MAX_TOKEN_CHARS: usize = 1024;
/// Longest `error` of `SendTaskFailure`.
pub const MAX_ERROR_CHARS: usize = 256;
/// Longest `cause` of `SendTaskFailure`.
pub const MAX_CAUSE_CHARS: usize = 32_768;

/// What the worker reported for a token.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Outcome {
    Success(Value),
    Failure { error: String, cause: String },
}

/// Why a `SendTask*` call was refused (the API's error codes).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CallbackError {
    /// Not a token (empty, or longer than 1,024 characters).
    #[error("InvalidToken: Invalid Token: '{0}'")]
    InvalidToken(String),
    /// No task ever had this token.
    #[error("TaskDoesNotExist: Task does not exist")]
    TaskDoesNotExist,
    /// The task already ended (reported, timed out, failed or aborted): a token is used once.
    #[error("TaskTimedOut: Task Timed Out: 'Provided task does not exist anymore'")]
    TaskTimedOut,
    /// The output is not acceptable (larger than the payload limit).
    #[error("InvalidOutput: {0}")]
    InvalidOutput(String),
    /// `error` or `cause` longer than the API allows.
    #[error("ValidationException: {0}")]
    Validation(String),
}

impl CallbackError {
    /// The API's error code.
    pub fn name(&self) -> &'static str {
        match self {
            CallbackError::InvalidToken(_) => "InvalidToken",
            CallbackError::TaskDoesNotExist => "TaskDoesNotExist",
            CallbackError::TaskTimedOut => "TaskTimedOut",
            CallbackError::InvalidOutput(_) => "InvalidOutput",
            CallbackError::Validation(_) => "ValidationException",
        }
    }
}

struct Waiting {
    done: oneshot::Sender<Outcome>,
    heartbeat: Arc<Notify>,
}

#[derive(Default)]
struct Inner {
    open: HashMap<String, Waiting>,
    closed: HashSet<String>,
    /// Tokens issued: part of each, so that two executions seeded alike never share one.
    issued: u64,
}

/// The tokens of one executor's waiting tasks (tokens are account-wide on AWS).
#[derive(Default)]
pub(crate) struct Callbacks {
    inner: Mutex<Inner>,
}

/// A waiting task's side of its token.
pub(crate) struct Pending {
    pub done: oneshot::Receiver<Outcome>,
    pub heartbeat: Arc<Notify>,
}

impl Callbacks {
    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Issues a new token (from `random`, a UUID, and a count) open for reports.
    pub fn issue(&self, random: &str) -> (String, Pending) {
        let (tx, rx) = oneshot::channel();
        let heartbeat = Arc::new(Notify::new());
        let mut inner = self.lock();
        inner.issued += 1;
        let token = format!("AQ{}{:016x}", random.replace('-', ""), inner.issued);
        inner.open.insert(
            token.clone(),
            Waiting {
                done: tx,
                heartbeat: heartbeat.clone(),
            },
        );
        let pending = Pending {
            done: rx,
            heartbeat,
        };
        (token, pending)
    }

    /// Closes `token`: later reports are `TaskTimedOut`.
    pub fn close(&self, token: &str) {
        let mut inner = self.lock();
        inner.open.remove(token);
        inner.closed.insert(token.to_owned());
    }

    fn take(&self, token: &str) -> Result<Waiting, CallbackError> {
        check_token(token)?;
        let mut inner = self.lock();
        match inner.open.remove(token) {
            Some(waiting) => {
                inner.closed.insert(token.to_owned());
                Ok(waiting)
            }
            None if inner.closed.contains(token) => Err(CallbackError::TaskTimedOut),
            None => Err(CallbackError::TaskDoesNotExist),
        }
    }

    /// `SendTaskSuccess`.
    pub fn success(
        &self,
        token: &str,
        output: Value,
        max_bytes: usize,
    ) -> Result<(), CallbackError> {
        let size = serde_json::to_vec(&output).map_or(usize::MAX, |v| v.len());
        if size > max_bytes {
            check_token(token)?;
            return Err(CallbackError::InvalidOutput(format!(
                "the output is {size} bytes, more than {max_bytes}"
            )));
        }
        let waiting = self.take(token)?;
        // NB: a receiver gone (the execution aborted meanwhile) is a task that ended.
        waiting
            .done
            .send(Outcome::Success(output))
            .map_err(|_| CallbackError::TaskTimedOut)
    }

    /// `SendTaskFailure`.
    pub fn failure(&self, token: &str, error: &str, cause: &str) -> Result<(), CallbackError> {
        if error.chars().count() > MAX_ERROR_CHARS || cause.chars().count() > MAX_CAUSE_CHARS {
            return Err(CallbackError::Validation(format!(
                "error is at most {MAX_ERROR_CHARS} characters and cause {MAX_CAUSE_CHARS}"
            )));
        }
        let waiting = self.take(token)?;
        waiting
            .done
            .send(Outcome::Failure {
                error: error.to_owned(),
                cause: cause.to_owned(),
            })
            .map_err(|_| CallbackError::TaskTimedOut)
    }

    /// `SendTaskHeartbeat`.
    pub fn heartbeat(&self, token: &str) -> Result<(), CallbackError> {
        check_token(token)?;
        let inner = self.lock();
        match inner.open.get(token) {
            Some(waiting) => {
                waiting.heartbeat.notify_one();
                Ok(())
            }
            None if inner.closed.contains(token) => Err(CallbackError::TaskTimedOut),
            None => Err(CallbackError::TaskDoesNotExist),
        }
    }
}

fn check_token(token: &str) -> Result<(), CallbackError> {
    let n = token.chars().count();
    if n == 0 || n > MAX_TOKEN_CHARS {
        return Err(CallbackError::InvalidToken(
            token.chars().take(64).collect(),
        ));
    }
    Ok(())
}
