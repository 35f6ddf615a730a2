//! A state's input and output processing: InputPath, Parameters, ResultSelector, ResultPath,
//! OutputPath, applied in the order Step Functions applies them.
//!
//! ```text
//! raw input --InputPath--> --Parameters--> effective input --(task)--> result
//! result --ResultSelector--> --ResultPath (into the raw input)--> --OutputPath--> output
//! ```

use serde_json::{Map, Value};

use crate::error::{preview, AslError, LoadError};
use crate::path::{Path, ReferencePath, Root};
use crate::template::Template;
use crate::Env;

/// InputPath or OutputPath: keep the whole document, discard it, or select part of it.
#[derive(Debug, Clone, PartialEq)]
pub enum Selection {
    /// Field absent or `"$"`: the whole document.
    Whole,
    /// Field `null`: an empty object `{}`.
    Discard,
    /// A path; a definite path that matches nothing is an error.
    Path(Path),
}

impl Selection {
    /// Reads the field `name` of a state definition (`None` when absent).
    pub fn from_field(value: Option<&Value>, name: &str) -> Result<Selection, LoadError> {
        match value {
            None => Ok(Selection::Whole),
            Some(Value::Null) => Ok(Selection::Discard),
            Some(Value::String(text)) => {
                let path = Path::parse_at(text, name)?;
                if path.root() == Root::Context {
                    return Err(LoadError::InvalidJsonPath {
                        location: name.to_owned(),
                        path: text.clone(),
                        reason: "the context object (`$$`) cannot be selected here".into(),
                    });
                }
                Ok(if text == "$" {
                    Selection::Whole
                } else {
                    Selection::Path(path)
                })
            }
            Some(other) => Err(LoadError::InvalidJsonPath {
                location: name.to_owned(),
                path: other.to_string(),
                reason: "must be a string or null".into(),
            }),
        }
    }

    /// Applies the selection to `document`.
    pub fn apply(&self, document: Value) -> Result<Value, AslError> {
        match self {
            Selection::Whole => Ok(document),
            Selection::Discard => Ok(Value::Object(Map::new())),
            Selection::Path(path) => {
                path.select(&document, &Value::Null)
                    .ok_or_else(|| AslError::PathNotFound {
                        path: path.text().to_owned(),
                        normalized: path.normalized(),
                    })
            }
        }
    }
}

/// ResultPath: where the result goes in the raw input.
#[derive(Debug, Clone, PartialEq)]
pub enum ResultPath {
    /// Field absent or `"$"`: the result replaces the input.
    Replace,
    /// Field `null`: the result is discarded and the input passes through.
    Discard,
    /// A reference path: the result is placed there, creating missing members.
    At(ReferencePath),
}

impl ResultPath {
    /// Reads the `ResultPath` field of a state definition (`None` when absent).
    pub fn from_field(value: Option<&Value>) -> Result<ResultPath, LoadError> {
        const NAME: &str = "ResultPath";
        match value {
            None => Ok(ResultPath::Replace),
            Some(Value::Null) => Ok(ResultPath::Discard),
            Some(Value::String(text)) => {
                let path = ReferencePath::parse_at(text, NAME)?;
                if path.root() == Root::Context {
                    return Err(LoadError::InvalidReferencePath {
                        location: NAME.to_owned(),
                        path: text.clone(),
                        reason: "the result cannot be written into the context object (`$$`)"
                            .into(),
                    });
                }
                Ok(if path.steps().is_empty() {
                    ResultPath::Replace
                } else {
                    ResultPath::At(path)
                })
            }
            Some(other) => Err(LoadError::InvalidReferencePath {
                location: NAME.to_owned(),
                path: other.to_string(),
                reason: "must be a string or null".into(),
            }),
        }
    }

    /// Combines the raw `input` and the `result`.
    pub fn apply(&self, input: Value, result: Value) -> Result<Value, AslError> {
        match self {
            ResultPath::Replace => Ok(result),
            ResultPath::Discard => Ok(input),
            ResultPath::At(path) => {
                let shown = preview(&input);
                path.set(input, result)
                    .map_err(|reason| AslError::ResultPathMatchFailure {
                        path: path.text().to_owned(),
                        input: shown,
                        reason,
                    })
            }
        }
    }
}

/// The five data-flow fields of one state, compiled.
#[derive(Debug, Clone, PartialEq)]
pub struct DataFlow {
    /// InputPath.
    pub input_path: Selection,
    /// Parameters.
    pub parameters: Option<Template>,
    /// ResultSelector.
    pub result_selector: Option<Template>,
    /// ResultPath.
    pub result_path: ResultPath,
    /// OutputPath.
    pub output_path: Selection,
}

impl Default for DataFlow {
    fn default() -> Self {
        DataFlow {
            input_path: Selection::Whole,
            parameters: None,
            result_selector: None,
            result_path: ResultPath::Replace,
            output_path: Selection::Whole,
        }
    }
}

impl DataFlow {
    /// Compiles the data-flow fields of a state definition (other fields are ignored).
    pub fn from_state(state: &Map<String, Value>) -> Result<DataFlow, LoadError> {
        let template = |name: &str| {
            state
                .get(name)
                .map(|v| Template::compile_at(v, name))
                .transpose()
        };
        Ok(DataFlow {
            input_path: Selection::from_field(state.get("InputPath"), "InputPath")?,
            parameters: template("Parameters")?,
            result_selector: template("ResultSelector")?,
            result_path: ResultPath::from_field(state.get("ResultPath"))?,
            output_path: Selection::from_field(state.get("OutputPath"), "OutputPath")?,
        })
    }

    /// The effective input a task receives: InputPath, then Parameters.
    pub fn effective_input(&self, raw_input: &Value, env: &Env<'_>) -> Result<Value, AslError> {
        let selected = self.input_path.apply(raw_input.clone())?;
        match &self.parameters {
            Some(parameters) => parameters.render(&selected, env),
            None => Ok(selected),
        }
    }

    /// The state's output: ResultSelector on the result, ResultPath into the raw input, then
    /// OutputPath.
    pub fn output(
        &self,
        raw_input: Value,
        result: Value,
        env: &Env<'_>,
    ) -> Result<Value, AslError> {
        let result = match &self.result_selector {
            Some(selector) => selector.render(&result, env)?,
            None => result,
        };
        let combined = self.result_path.apply(raw_input, result)?;
        self.output_path.apply(combined)
    }
}
