//! Load-time errors: a definition this executor refuses, named by where in it the problem is.

/// A definition that cannot be loaded. Every variant names the location in the definition
/// (`States.Launch.Retry[0].BackoffRate`), so the state and the field are always known, and
/// has a stable [`name`](Self::name).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LoadError {
    /// The structure is wrong: a required field is missing, a field has the wrong type or a
    /// value is out of range.
    #[error("invalid definition at `{location}`: {reason}")]
    Invalid {
        /// Where in the definition.
        location: String,
        /// What is wrong.
        reason: String,
    },
    /// Valid Amazon States Language that this executor does not run (a state type, field,
    /// resource or mode). Refused rather than ignored, so local runs never differ silently
    /// from AWS.
    #[error("unsupported at `{location}`: {reason}")]
    Unsupported {
        /// Where in the definition.
        location: String,
        /// Which feature, and what is supported instead.
        reason: String,
    },
    /// A `Next`, `Default`, `StartAt` or catcher names a state that does not exist in its
    /// scope (a branch can only reach its own states).
    #[error("`{location}` names state `{target}`, which is not defined in this scope")]
    UnknownState {
        /// The field holding the name.
        location: String,
        /// The missing state's name.
        target: String,
    },
    /// A state no transition leads to.
    #[error("state `{state}` at `{location}` is never reached")]
    Unreachable {
        /// Where the state is defined.
        location: String,
        /// Its name.
        state: String,
    },
    /// Two states share a name (names are unique across the whole definition, branches and
    /// iterators included, as Step Functions requires).
    #[error("state name `{state}` at `{location}` is also defined at `{other}`")]
    DuplicateStateName {
        /// The second definition.
        location: String,
        /// The name.
        state: String,
        /// The first definition.
        other: String,
    },
    /// A `${Name}` in the definition with no value in the substitution map.
    #[error("no substitution for `${{{name}}}` at `{location}`")]
    MissingSubstitution {
        /// Where the reference is.
        location: String,
        /// The substitution's name.
        name: String,
    },
    /// A path, payload template or intrinsic function that `lb-asl` refuses.
    #[error("in `{location}`: {source}")]
    DataFlow {
        /// The state (its location) whose field is wrong; the source names the field.
        location: String,
        /// The data-flow error.
        #[source]
        source: lb_asl::LoadError,
    },
}

impl LoadError {
    /// The stable PascalCase name callers match on (for [`LoadError::DataFlow`], the
    /// `lb-asl` error's name: `InvalidJsonPath`, ...).
    pub fn name(&self) -> &'static str {
        match self {
            LoadError::Invalid { .. } => "InvalidDefinition",
            LoadError::Unsupported { .. } => "UnsupportedFeature",
            LoadError::UnknownState { .. } => "UnknownStateName",
            LoadError::Unreachable { .. } => "UnreachableState",
            LoadError::DuplicateStateName { .. } => "DuplicateStateName",
            LoadError::MissingSubstitution { .. } => "MissingSubstitution",
            LoadError::DataFlow { source, .. } => source.name(),
        }
    }

    /// Where in the definition the problem is.
    pub fn location(&self) -> &str {
        match self {
            LoadError::Invalid { location, .. }
            | LoadError::Unsupported { location, .. }
            | LoadError::UnknownState { location, .. }
            | LoadError::Unreachable { location, .. }
            | LoadError::DuplicateStateName { location, .. }
            | LoadError::MissingSubstitution { location, .. }
            | LoadError::DataFlow { location, .. } => location,
        }
    }

    pub(crate) fn invalid(location: impl Into<String>, reason: impl Into<String>) -> LoadError {
        LoadError::Invalid {
            location: location.into(),
            reason: reason.into(),
        }
    }

    pub(crate) fn unsupported(location: impl Into<String>, reason: impl Into<String>) -> LoadError {
        LoadError::Unsupported {
            location: location.into(),
            reason: reason.into(),
        }
    }
}

/// Why an execution could not be started.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum StartError {
    /// The execution name breaks Step Functions' naming rules.
    #[error("invalid execution name `{name}`: {reason}")]
    InvalidName {
        /// The name given.
        name: String,
        /// Which rule it breaks.
        reason: String,
    },
    /// The input is larger than the payload quota.
    #[error("execution input is {size} bytes, more than the {limit}-byte payload quota")]
    InputTooLarge {
        /// Its size in bytes (compact JSON).
        size: usize,
        /// The quota.
        limit: usize,
    },
    /// `start` was called outside a Tokio runtime.
    #[error("an execution must be started from within a Tokio runtime")]
    NoRuntime,
    /// `StartExecution`: the name is taken by an execution that ended, or by a running one
    /// with another input (the same name and input is the running one, not an error).
    #[error("execution `{name}` already exists")]
    ExecutionAlreadyExists {
        /// The name asked for.
        name: String,
    },
    /// `StartExecution`: no state machine of that ARN ran here.
    #[error("state machine `{arn}` does not exist")]
    StateMachineDoesNotExist {
        /// The ARN asked for.
        arn: String,
    },
}

impl StartError {
    /// The stable PascalCase name.
    pub fn name(&self) -> &'static str {
        match self {
            StartError::InvalidName { .. } => "InvalidName",
            StartError::InputTooLarge { .. } => "InvalidExecutionInput",
            StartError::NoRuntime => "NoRuntime",
            StartError::ExecutionAlreadyExists { .. } => "ExecutionAlreadyExists",
            StartError::StateMachineDoesNotExist { .. } => "StateMachineDoesNotExist",
        }
    }
}

/// Options an [`Executor`](crate::Executor) cannot work with.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OptionsError {
    /// The time scale is not a finite positive number.
    #[error("time scale must be a finite number greater than 0, got `{0}`")]
    InvalidTimeScale(f64),
    /// A limit is zero.
    #[error("`{0}` must be greater than 0")]
    ZeroLimit(&'static str),
}

impl OptionsError {
    /// The stable PascalCase name.
    pub fn name(&self) -> &'static str {
        match self {
            OptionsError::InvalidTimeScale(_) => "InvalidTimeScale",
            OptionsError::ZeroLimit(_) => "ZeroLimit",
        }
    }
}
