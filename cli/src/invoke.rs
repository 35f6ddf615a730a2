//! `lbctl invoke`: one function's handler in-process, configured from the environment exactly
//! as its Lambda is, with the Lambda's JSON result or error object on stdout.

use std::io::{IsTerminal, Read};
use std::path::{Path, PathBuf};

use clap::{Args, ValueEnum};
use lb_pipeline::FnError;
use serde_json::{json, Value};

use crate::error::{CliError, Result};

/// Biggest event accepted: Step Functions passes at most 256 KiB between states.
const MAX_EVENT_BYTES: u64 = 256 * 1024;

/// The functions: the state machine's, each with the event its Task's `Parameters` build,
/// and the event-driven ones with their source's event.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Function {
    /// Stage 1: validate, read EvalAI, gate, claim. Event: `{"message": <the Pipe's output>,
    /// "execution": "<execution name>"}`.
    Intake,
    /// Stages 2-3: plan, render and create the Jobs. Event: `{"submission": <$.intake.submission>}`.
    Launch,
    /// Stage 4: one monitor round. Event: `{"submission": <$.intake.submission>, "run": <$.run>}`.
    Monitor,
    /// Stage 5 and the failure path: delete the Jobs, final merge, EvalAI, DynamoDB. Event:
    /// `{"state": <the whole execution state>}`.
    Finalize,
    /// S3's events for results files and markers wake the waiting executions. Event: Lambda's
    /// SQS batch, `{"Records": [{"messageId": .., "body": <the EventBridge event>}, ..]}`.
    Wake,
    /// The cancel sweep: EvalAI's cancels of the executions waiting. Event: the schedule's
    /// (any JSON; `{}`).
    Sweep,
}

impl Function {
    fn as_str(self) -> &'static str {
        match self {
            Function::Intake => "intake",
            Function::Launch => "launch",
            Function::Monitor => "monitor",
            Function::Finalize => "finalize",
            Function::Wake => "wake",
            Function::Sweep => "sweep",
        }
    }
}

/// `lbctl invoke` options.
#[derive(Debug, Clone, Args)]
pub struct Invoke {
    /// The function whose handler runs.
    #[arg(value_enum)]
    pub function: Function,
    /// JSON file with the event the state machine would pass (`-` or absent: stdin).
    #[arg(long, value_name = "FILE")]
    pub event: Option<PathBuf>,
}

/// Reads and parses the event; errors name the file.
fn read_event(path: Option<&Path>) -> Result<Value> {
    let stdin = path.is_none_or(|p| p == Path::new("-"));
    let shown = path.map_or_else(|| PathBuf::from("-"), Path::to_path_buf);
    let mut text = Vec::new();
    let read = if stdin {
        if std::io::stdin().is_terminal() {
            return Err(CliError::Usage(
                "no event: pass `--event FILE` or pipe the event's JSON on stdin".into(),
            ));
        }
        std::io::stdin()
            .take(MAX_EVENT_BYTES + 1)
            .read_to_end(&mut text)
    } else {
        std::fs::File::open(&shown).and_then(|f| f.take(MAX_EVENT_BYTES + 1).read_to_end(&mut text))
    };
    read.map_err(|source| CliError::EventUnreadable {
        path: shown.clone(),
        source,
    })?;
    if text.len() as u64 > MAX_EVENT_BYTES {
        return Err(CliError::EventUnreadable {
            path: shown,
            source: std::io::Error::other(format!(
                "it is over {MAX_EVENT_BYTES} bytes, more than Step Functions passes to a task"
            )),
        });
    }
    serde_json::from_slice(&text).map_err(|source| CliError::InvalidEvent {
        path: shown,
        source,
    })
}

/// The object Lambda returns for a function error: what the state machine's `ErrorEquals`
/// and `Catch` see.
pub fn error_object(error: &FnError) -> Value {
    json!({ "errorType": error.name(), "errorMessage": error.chain() })
}

/// One invocation on the dependencies the function's cold start built, as Lambda makes it.
async fn invoke<F: lb_pipeline::serve::Function>(
    deps: lb_pipeline::Result<F>,
    event: Value,
) -> lb_pipeline::Result<Value> {
    lb_pipeline::serve::call(&deps?, event).await
}

/// Runs the handler; prints its result (exit 0) or its error object (exit 1) on stdout, and
/// its metrics document on stderr (stdout is the result a script reads).
pub async fn run(args: Invoke) -> Result<u8> {
    let event = read_event(args.event.as_deref())?;
    lb_pipeline::metrics::write_to(std::sync::Arc::new(|line: &str| eprintln!("{line}")));
    let name = args.function.as_str();
    let result = match args.function {
        Function::Intake => invoke(intake::Deps::from_env().await, event).await,
        Function::Launch => invoke(launch::Deps::from_env().await, event).await,
        Function::Monitor => invoke(monitor::Deps::from_env().await, event).await,
        Function::Finalize => invoke(finalize::Deps::from_env().await, event).await,
        Function::Wake => invoke(wake::Deps::from_env().await, event).await,
        Function::Sweep => invoke(sweep::Deps::from_env().await, event).await,
    };
    match result {
        Ok(output) => {
            outln!("{}", pretty(&output));
            Ok(0)
        }
        Err(error) => {
            outln!("{}", pretty(&error_object(&error)));
            errln!("lbctl: {name} raised `{}`", error.name());
            Ok(1)
        }
    }
}

fn pretty(value: &Value) -> String {
    serde_json::to_string_pretty(value).unwrap_or_else(|_| value.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_error_object_has_the_name_the_state_machine_matches() {
        let error =
            FnError::decode::<lb_pipeline::payload::IntakeInput>("intake", json!({})).unwrap_err();
        assert_eq!(
            error_object(&error),
            json!({"errorType": "InvalidInput",
                   "errorMessage": "invalid intake input: missing field `message`"})
        );
    }

    #[test]
    fn an_event_that_is_not_json_is_named_with_its_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("event.json");
        std::fs::write(&path, "{\"message\": ").unwrap();
        let err = read_event(Some(&path)).unwrap_err();
        assert_eq!(err.name(), "InvalidEvent");
        assert!(err.to_string().contains("event.json"), "{err}");
        let err = read_event(Some(&dir.path().join("missing.json"))).unwrap_err();
        assert_eq!(err.name(), "EventUnreadable");
        assert!(err.to_string().contains("missing.json"), "{err}");
    }

    #[test]
    fn an_oversized_event_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("big.json");
        std::fs::write(&path, vec![b' '; MAX_EVENT_BYTES as usize + 10]).unwrap();
        let err = read_event(Some(&path)).unwrap_err();
        assert!(err.to_string().contains("over"), "{err}");
    }
}
