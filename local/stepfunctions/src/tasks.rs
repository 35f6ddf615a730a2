//! The in-process Lambda handlers a Task state calls, and how a function name finds one.

use std::collections::HashMap;
use std::fmt;
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;

use serde_json::Value;

/// The function a Task state invokes, as the definition names it.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct FunctionRef {
    /// The function as written after substitution: the `Resource` ARN, or the
    /// `Parameters.FunctionName` of `arn:aws:states:::lambda:invoke` (name or ARN).
    pub function: String,
    /// The function's name: the ARN's `function:` segment (or the plain name), without a
    /// version or alias qualifier.
    pub name: String,
    /// The substitution the definition used, when the field was exactly `${Name}`
    /// (`IntakeFunctionArn` for `"Resource": "${IntakeFunctionArn}"`).
    pub substitution: Option<String>,
}

impl fmt::Display for FunctionRef {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.substitution {
            Some(name) => write!(f, "{} (${{{name}}})", self.function),
            None => f.write_str(&self.function),
        }
    }
}

/// A failed invocation, as the state machine sees it: `error` is what `ErrorEquals`
/// matches, `cause` what a catcher's error output carries.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{error}: {cause}")]
pub struct TaskError {
    /// The error name (for a Lambda error: its `errorType`).
    pub error: String,
    /// The cause (for a Lambda error: the JSON text `{"errorType":..,"errorMessage":..}`).
    pub cause: String,
}

impl TaskError {
    /// An error exactly as given (for example a Lambda service error such as
    /// `Lambda.TooManyRequestsException` with a plain-text cause).
    pub fn new(error: impl Into<String>, cause: impl Into<String>) -> TaskError {
        TaskError {
            error: error.into(),
            cause: cause.into(),
        }
    }

    /// An error a Lambda function returned, shaped as Step Functions shows it: the error is
    /// the `errorType`, the cause the function's error payload as JSON text
    /// (`{"errorType":"KubeTransient","errorMessage":"..."}`, the order the Rust runtime
    /// writes).
    pub fn lambda(error_type: impl Into<String>, error_message: impl Into<String>) -> TaskError {
        let error_type = error_type.into();
        let error_message = error_message.into();
        let cause = format!(
            "{{\"errorType\":{},\"errorMessage\":{}}}",
            Value::String(error_type.clone()),
            Value::String(error_message)
        );
        TaskError {
            error: error_type,
            cause,
        }
    }
}

/// What a handler returns: a boxed future, so handlers of different types share one map.
pub type TaskFuture = Pin<Box<dyn Future<Output = Result<Value, TaskError>> + Send + 'static>>;

/// An in-process Lambda handler: the function's input in, its result (or error) out.
pub type Handler = Arc<dyn Fn(Value) -> TaskFuture + Send + Sync>;

/// Wraps an async closure as a [`Handler`].
pub fn handler<F, Fut>(f: F) -> Handler
where
    F: Fn(Value) -> Fut + Send + Sync + 'static,
    Fut: Future<Output = Result<Value, TaskError>> + Send + 'static,
{
    Arc::new(move |input| Box::pin(f(input)) as TaskFuture)
}

/// Resolves the function a Task names to its handler.
pub trait Tasks: Send + Sync + 'static {
    /// The handler for `function`, or `None` (the Task then fails with
    /// `Lambda.ResourceNotFoundException`, as a missing function does on AWS).
    fn handler(&self, function: &FunctionRef) -> Option<Handler>;
}

/// Handlers by key. A Task's function is looked up by the full text as written (a version's
/// own handler: `arn:...:function:intake:2`), then its substitution name
/// (`IntakeFunctionArn`), then its function name (`intake`).
#[derive(Clone, Default)]
pub struct TaskMap {
    handlers: HashMap<String, Handler>,
}

impl fmt::Debug for TaskMap {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut keys: Vec<&String> = self.handlers.keys().collect();
        keys.sort();
        f.debug_struct("TaskMap").field("keys", &keys).finish()
    }
}

impl TaskMap {
    /// An empty map.
    pub fn new() -> TaskMap {
        TaskMap::default()
    }

    /// Adds a handler under `key` (replacing any), builder style.
    pub fn with<F, Fut>(mut self, key: impl Into<String>, f: F) -> TaskMap
    where
        F: Fn(Value) -> Fut + Send + Sync + 'static,
        Fut: Future<Output = Result<Value, TaskError>> + Send + 'static,
    {
        self.insert(key, handler(f));
        self
    }

    /// Adds a ready-made handler under `key` (replacing any).
    pub fn insert(&mut self, key: impl Into<String>, handler: Handler) -> &mut TaskMap {
        self.handlers.insert(key.into(), handler);
        self
    }

    /// The keys registered.
    pub fn keys(&self) -> impl Iterator<Item = &str> {
        self.handlers.keys().map(String::as_str)
    }
}

impl Tasks for TaskMap {
    fn handler(&self, function: &FunctionRef) -> Option<Handler> {
        std::iter::once(&function.function)
            .chain(function.substitution.iter())
            .chain([&function.name])
            .find_map(|key| self.handlers.get(key))
            .cloned()
    }
}

impl<T: Tasks> Tasks for Arc<T> {
    fn handler(&self, function: &FunctionRef) -> Option<Handler> {
        (**self).handler(function)
    }
}

/// The function name in a Lambda ARN (`arn:aws:lambda:region:account:function:name[:qualifier]`),
/// a partial ARN (`account:function:name`) or a plain name (`name[:qualifier]`).
pub(crate) fn function_name(text: &str) -> Result<String, String> {
    let name = if text.starts_with("arn:") {
        let parts: Vec<&str> = text.split(':').collect();
        if parts.len() < 7 || parts.len() > 8 || parts[2] != "lambda" || parts[5] != "function" {
            return Err(format!(
                "`{text}` is not a Lambda function ARN (arn:aws:lambda:<region>:<account>:function:<name>)"
            ));
        }
        parts[6]
    } else if let Some((_, rest)) = text.split_once(":function:") {
        rest.split(':').next().unwrap_or_default()
    } else {
        text.split(':').next().unwrap_or_default()
    };
    let valid = !name.is_empty()
        && name.len() <= 64
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_');
    if valid {
        Ok(name.to_owned())
    } else {
        Err(format!(
            "`{text}` does not name a Lambda function (1 to 64 letters, digits, `-`, `_`)"
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn function_names_come_from_arns_partial_arns_and_plain_names() {
        assert_eq!(
            function_name("arn:aws:lambda:us-east-1:123456789012:function:lb-intake").unwrap(),
            "lb-intake"
        );
        assert_eq!(
            function_name("arn:aws:lambda:us-east-1:123456789012:function:f:live").unwrap(),
            "f"
        );
        assert_eq!(function_name("123456789012:function:f").unwrap(), "f");
        assert_eq!(function_name("f:3").unwrap(), "f");
        assert_eq!(function_name("f").unwrap(), "f");
        assert!(function_name("arn:aws:sqs:us-east-1:1:queue").is_err());
        assert!(function_name("arn:aws:lambda:us-east-1:1:layer:x").is_err());
        assert!(function_name("").is_err());
        assert!(function_name("bad name").is_err());
    }

    #[test]
    fn lambda_errors_carry_their_payload_as_json_text() {
        let e = TaskError::lambda("KubeTransient", "the API said \"no\"");
        assert_eq!(e.error, "KubeTransient");
        assert_eq!(
            e.cause,
            r#"{"errorType":"KubeTransient","errorMessage":"the API said \"no\""}"#
        );
        let parsed: Value = serde_json::from_str(&e.cause).unwrap();
        assert_eq!(parsed["errorMessage"], "the API said \"no\"");
    }

    #[tokio::test]
    async fn a_function_is_found_by_text_then_substitution_then_name() {
        let map = TaskMap::new()
            .with("IntakeFunctionArn", |_| async { Ok(Value::from(1)) })
            .with("monitor", |_| async { Ok(Value::from(2)) })
            .with("arn:aws:lambda:r:1:function:other", |_| async {
                Ok(Value::from(3))
            })
            .with("arn:x:function:intake:2", |_| async { Ok(Value::from(4)) });
        let call = |f: FunctionRef| {
            let h = map.handler(&f);
            async move {
                match h {
                    Some(h) => h(Value::Null).await.ok(),
                    None => None,
                }
            }
        };
        let f = |function: &str, name: &str, sub: Option<&str>| FunctionRef {
            function: function.into(),
            name: name.into(),
            substitution: sub.map(Into::into),
        };
        assert_eq!(
            call(f(
                "arn:x:function:intake",
                "intake",
                Some("IntakeFunctionArn")
            ))
            .await,
            Some(Value::from(1))
        );
        assert_eq!(
            call(f(
                "arn:x:function:monitor",
                "monitor",
                Some("MonitorFunctionArn")
            ))
            .await,
            Some(Value::from(2))
        );
        assert_eq!(
            call(f("arn:aws:lambda:r:1:function:other", "other", None)).await,
            Some(Value::from(3))
        );
        assert_eq!(
            call(f(
                "arn:x:function:intake:2",
                "intake",
                Some("IntakeFunctionArn")
            ))
            .await,
            Some(Value::from(4)),
            "a version's own handler comes first"
        );
        assert_eq!(call(f("x", "x", None)).await, None);
    }
}
