//! Load-time (definition) and run-time (evaluation) errors, with stable names.

use serde_json::Value;

/// How much of a JSON input an error message quotes. AWS quotes the whole input; a bounded
/// preview keeps error payloads, logs and Step Functions causes small.
pub const INPUT_PREVIEW_CHARS: usize = 1024;

/// A definition that cannot be loaded: a bad path, intrinsic call or payload template.
///
/// These are found once, when a template or state is compiled, so that a definition that
/// could never work is refused before anything runs. Each variant has a stable
/// [`name`](Self::name).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LoadError {
    /// A JSONPath that does not parse or uses an unsupported feature.
    #[error("invalid JSONPath `{path}` at `{location}`: {reason}")]
    InvalidJsonPath {
        /// Where in the definition (field path) the path was found.
        location: String,
        /// The path as written.
        path: String,
        /// What is wrong with it.
        reason: String,
    },
    /// A path that must be a reference path (single node, no wildcards) is not one.
    #[error("invalid reference path `{path}` at `{location}`: {reason}")]
    InvalidReferencePath {
        /// Where in the definition the path was found.
        location: String,
        /// The path as written.
        path: String,
        /// What is wrong with it.
        reason: String,
    },
    /// An intrinsic function call that does not parse, names an unknown function or breaks
    /// the function's argument rules.
    #[error("invalid intrinsic function call `{call}` at `{location}`: {reason}")]
    InvalidIntrinsic {
        /// Where in the definition the call was found.
        location: String,
        /// The call as written.
        call: String,
        /// What is wrong with it.
        reason: String,
    },
    /// A payload template (Parameters, ResultSelector) that is malformed: a `.$` field whose
    /// value is not a path or a call, or a field defined twice.
    #[error("invalid payload template at `{location}`: {reason}")]
    InvalidPayloadTemplate {
        /// The offending field.
        location: String,
        /// What is wrong with it.
        reason: String,
    },
}

impl LoadError {
    /// The stable PascalCase name callers match on.
    pub fn name(&self) -> &'static str {
        match self {
            LoadError::InvalidJsonPath { .. } => "InvalidJsonPath",
            LoadError::InvalidReferencePath { .. } => "InvalidReferencePath",
            LoadError::InvalidIntrinsic { .. } => "InvalidIntrinsicFunction",
            LoadError::InvalidPayloadTemplate { .. } => "InvalidPayloadTemplate",
        }
    }
}

/// An evaluation failure, named and worded as AWS Step Functions reports it.
///
/// [`name`](Self::name) is the Step Functions error name (`States.Runtime`, ...) that a
/// state machine's `Retry`/`Catch` would see; `Display` is the cause.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum AslError {
    /// A `.$` field's path matched nothing. AWS reports this as `States.Runtime` (not
    /// `States.ParameterPathFailure`, which the ASL specification names), and `States.ALL`
    /// does not catch it.
    #[error("The JSONPath '{path}' specified for the field '{field}' could not be found in the input '{input}'")]
    FieldPathNotFound {
        /// The field name, with its `.$` suffix.
        field: String,
        /// The path as written.
        path: String,
        /// A preview of the input (or context object) the path was applied to.
        input: String,
    },
    /// A path argument of an intrinsic function matched nothing.
    #[error(
        "The JsonPath argument for the field '{field}' could not be found in the input '{input}'"
    )]
    IntrinsicArgumentNotFound {
        /// The field name, with its `.$` suffix.
        field: String,
        /// The argument's path.
        path: String,
        /// A preview of the input (or context object).
        input: String,
    },
    /// An InputPath or OutputPath matched nothing.
    #[error("Invalid path '{path}' : No results for path: {normalized}")]
    PathNotFound {
        /// The path as written.
        path: String,
        /// Its normalized form (`$['a'][0]`), as AWS prints it.
        normalized: String,
    },
    /// An intrinsic function refused its arguments at run time.
    #[error("The function '{function}' for the field '{field}' failed: {reason}")]
    IntrinsicFailure {
        /// The field name, with its `.$` suffix.
        field: String,
        /// The function name (`States.ArrayGetItem`).
        function: String,
        /// What was wrong.
        reason: String,
    },
    /// ResultPath could not place the result into the input.
    #[error("Unable to apply ResultPath '{path}' to input '{input}': {reason}")]
    ResultPathMatchFailure {
        /// The ResultPath as written.
        path: String,
        /// A preview of the input.
        input: String,
        /// Why (which node is not an object or array).
        reason: String,
    },
}

impl AslError {
    /// The Step Functions error name.
    pub fn name(&self) -> &'static str {
        match self {
            AslError::FieldPathNotFound { .. }
            | AslError::IntrinsicArgumentNotFound { .. }
            | AslError::PathNotFound { .. } => "States.Runtime",
            AslError::IntrinsicFailure { .. } => "States.IntrinsicFailure",
            AslError::ResultPathMatchFailure { .. } => "States.ResultPathMatchFailure",
        }
    }
}

/// Compact JSON of `value`, cut at [`INPUT_PREVIEW_CHARS`] characters (with `...`).
pub fn preview(value: &Value) -> String {
    let text = value.to_string();
    match text.char_indices().nth(INPUT_PREVIEW_CHARS) {
        Some((cut, _)) => format!("{}...", &text[..cut]),
        None => text,
    }
}
