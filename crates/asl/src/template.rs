//! Payload templates (`Parameters`, `ResultSelector`): fields whose name ends in `.$` take a
//! path or an intrinsic function call; everything else is literal.
//!
//! A template is compiled once ([`Template::compile`]), which refuses bad paths, bad calls,
//! non-string `.$` values and fields defined twice (`a` beside `a.$`), then rendered any
//! number of times. Nested objects and objects inside arrays are templates too.

use std::collections::BTreeSet;

use serde_json::{Map, Value};

use crate::error::{preview, AslError, LoadError};
use crate::intrinsic::Call;
use crate::path::{Path, Root};
use crate::Env;

#[derive(Debug, Clone, PartialEq)]
enum Node {
    Literal(Value),
    Object(Vec<(String, Node)>),
    Array(Vec<Node>),
    Path { field: String, path: Path },
    Call { field: String, call: Call },
}

/// A compiled payload template.
#[derive(Debug, Clone, PartialEq)]
pub struct Template {
    root: Node,
}

/// One `.$` field of a template: where it is and the paths it reads.
#[derive(Debug, Clone)]
pub struct DynamicField<'t> {
    /// Location of the field in the template, with its `.$` (`spec.containers[0].name.$`).
    pub location: String,
    /// The paths it reads: one for a path field, those of every argument for a call.
    pub paths: Vec<&'t Path>,
}

fn child(location: &str, key: &str) -> String {
    if location.is_empty() {
        key.to_owned()
    } else {
        format!("{location}.{key}")
    }
}

fn has_dynamic(value: &Value) -> bool {
    match value {
        Value::Object(map) => map.iter().any(|(k, v)| k.ends_with(".$") || has_dynamic(v)),
        Value::Array(items) => items.iter().any(has_dynamic),
        _ => false,
    }
}

fn compile(value: &Value, location: &str) -> Result<Node, LoadError> {
    if !has_dynamic(value) {
        return Ok(Node::Literal(value.clone()));
    }
    match value {
        Value::Object(map) => {
            let mut names = BTreeSet::new();
            let mut fields = Vec::with_capacity(map.len());
            for (key, item) in map {
                let here = child(location, key);
                let (name, node) = match key.strip_suffix(".$") {
                    Some(name) => (name, dynamic(key, item, &here)?),
                    None => (key.as_str(), compile(item, &here)?),
                };
                if name.is_empty() {
                    return Err(LoadError::InvalidPayloadTemplate {
                        location: here,
                        reason: "a field name cannot be empty".into(),
                    });
                }
                if !names.insert(name.to_owned()) {
                    return Err(LoadError::InvalidPayloadTemplate {
                        location: here,
                        reason: format!(
                            "the field `{name}` is defined twice (as `{name}` and `{name}.$`)"
                        ),
                    });
                }
                fields.push((name.to_owned(), node));
            }
            Ok(Node::Object(fields))
        }
        Value::Array(items) => items
            .iter()
            .enumerate()
            .map(|(i, item)| compile(item, &format!("{location}[{i}]")))
            .collect::<Result<Vec<_>, _>>()
            .map(Node::Array),
        other => Ok(Node::Literal(other.clone())),
    }
}

fn dynamic(key: &str, value: &Value, location: &str) -> Result<Node, LoadError> {
    let Some(text) = value.as_str() else {
        return Err(LoadError::InvalidPayloadTemplate {
            location: location.to_owned(),
            reason: format!(
                "the value of `{key}` must be a string holding a JSONPath or an intrinsic function call"
            ),
        });
    };
    if text.starts_with("States.") {
        Ok(Node::Call {
            field: key.to_owned(),
            call: Call::parse_at(text, location)?,
        })
    } else if text.starts_with('$') {
        Ok(Node::Path {
            field: key.to_owned(),
            path: Path::parse_at(text, location)?,
        })
    } else {
        Err(LoadError::InvalidPayloadTemplate {
            location: location.to_owned(),
            reason: format!(
                "`{text}` is neither a JSONPath (starting with `$`) nor an intrinsic function call (starting with `States.`)"
            ),
        })
    }
}

fn render(node: &Node, input: &Value, env: &Env<'_>) -> Result<Value, AslError> {
    Ok(match node {
        Node::Literal(v) => v.clone(),
        Node::Object(fields) => {
            let mut map = Map::new();
            for (name, field) in fields {
                map.insert(name.clone(), render(field, input, env)?);
            }
            Value::Object(map)
        }
        Node::Array(items) => Value::Array(
            items
                .iter()
                .map(|item| render(item, input, env))
                .collect::<Result<_, _>>()?,
        ),
        Node::Path { field, path } => match path.select(input, env.context) {
            Some(v) => v,
            None => {
                let read = match path.root() {
                    Root::Input => input,
                    Root::Context => env.context,
                };
                return Err(AslError::FieldPathNotFound {
                    field: field.clone(),
                    path: path.text().to_owned(),
                    input: preview(read),
                });
            }
        },
        Node::Call { field, call } => call.evaluate(field, input, env)?,
    })
}

impl Template {
    /// Compiles a payload template from its JSON definition.
    pub fn compile(definition: &Value) -> Result<Template, LoadError> {
        Template::compile_at(definition, "")
    }

    /// Compiles a template found at `location` (prefixed to the locations in errors).
    pub fn compile_at(definition: &Value, location: &str) -> Result<Template, LoadError> {
        Ok(Template {
            root: compile(definition, location)?,
        })
    }

    /// Renders the template against `input` (for `$`) and `env.context` (for `$$`).
    pub fn render(&self, input: &Value, env: &Env<'_>) -> Result<Value, AslError> {
        render(&self.root, input, env)
    }

    /// Whether the template has no `.$` field (it renders to itself).
    pub fn is_literal(&self) -> bool {
        matches!(self.root, Node::Literal(_))
    }

    /// Every `.$` field with the paths it reads, for static checks of a definition.
    pub fn dynamic_fields(&self) -> Vec<DynamicField<'_>> {
        fn walk<'t>(node: &'t Node, at: &str, out: &mut Vec<DynamicField<'t>>) {
            match node {
                Node::Literal(_) => {}
                Node::Object(fields) => {
                    for (name, field) in fields {
                        walk(field, &child(at, name), out);
                    }
                }
                Node::Array(items) => {
                    for (i, item) in items.iter().enumerate() {
                        walk(item, &format!("{at}[{i}]"), out);
                    }
                }
                Node::Path { path, .. } => out.push(DynamicField {
                    location: format!("{at}.$"),
                    paths: vec![path],
                }),
                Node::Call { call, .. } => out.push(DynamicField {
                    location: format!("{at}.$"),
                    paths: call.paths(),
                }),
            }
        }
        let mut out = Vec::new();
        walk(&self.root, "", &mut out);
        out
    }
}
