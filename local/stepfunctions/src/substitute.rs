//! `${Name}` definition substitutions (SAM `DefinitionSubstitutions`), resolved at load.

use std::collections::HashMap;

use serde_json::Value;

use crate::error::LoadError;

/// The definition with every `${Name}` replaced, and for each string that was exactly one
/// `${Name}`, its location and the name (Task resources are resolved by that name).
#[derive(Debug)]
pub(crate) struct Substituted {
    pub value: Value,
    pub exact: HashMap<String, String>,
}

/// Replaces `${Name}` in every string value. `Name` is letters, digits and `_`; any other
/// `${...}` is left as written. A well-formed reference without a value is an error.
pub(crate) fn substitute(
    definition: &Value,
    values: &HashMap<String, String>,
) -> Result<Substituted, LoadError> {
    let mut exact = HashMap::new();
    let value = walk(definition, "", values, &mut exact)?;
    Ok(Substituted { value, exact })
}

fn child(at: &str, key: &str) -> String {
    if at.is_empty() {
        key.to_owned()
    } else {
        format!("{at}.{key}")
    }
}

fn walk(
    value: &Value,
    at: &str,
    values: &HashMap<String, String>,
    exact: &mut HashMap<String, String>,
) -> Result<Value, LoadError> {
    Ok(match value {
        Value::String(text) => {
            let (replaced, whole) = replace(text, at, values)?;
            if let Some(name) = whole {
                exact.insert(at.to_owned(), name);
            }
            Value::String(replaced)
        }
        Value::Array(items) => Value::Array(
            items
                .iter()
                .enumerate()
                .map(|(i, item)| walk(item, &format!("{at}[{i}]"), values, exact))
                .collect::<Result<_, _>>()?,
        ),
        Value::Object(map) => Value::Object(
            map.iter()
                .map(|(k, v)| Ok((k.clone(), walk(v, &child(at, k), values, exact)?)))
                .collect::<Result<_, LoadError>>()?,
        ),
        other => other.clone(),
    })
}

/// The text with its references replaced, and the name when the text was one reference.
fn replace(
    text: &str,
    at: &str,
    values: &HashMap<String, String>,
) -> Result<(String, Option<String>), LoadError> {
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    let mut whole = None;
    while let Some(start) = rest.find("${") {
        out.push_str(&rest[..start]);
        let after = &rest[start + 2..];
        let name_len = after
            .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
            .unwrap_or(after.len());
        if name_len == 0 || !after[name_len..].starts_with('}') {
            out.push_str("${");
            rest = after;
            continue;
        }
        let name = &after[..name_len];
        let Some(replacement) = values.get(name) else {
            return Err(LoadError::MissingSubstitution {
                location: at.to_owned(),
                name: name.to_owned(),
            });
        };
        if start == 0 && name_len + 3 == rest.len() && out.is_empty() {
            whole = Some(name.to_owned());
        }
        out.push_str(replacement);
        rest = &after[name_len + 1..];
    }
    out.push_str(rest);
    Ok((out, whole))
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn subs() -> HashMap<String, String> {
        HashMap::from([
            (
                "Fn".to_owned(),
                "arn:aws:lambda:us-east-1:1:function:f".to_owned(),
            ),
            ("Bucket".to_owned(), "b".to_owned()),
        ])
    }

    #[test]
    fn references_are_replaced_everywhere_and_whole_ones_remembered() {
        let out = substitute(
            &json!({"States": {"A": {"Resource": "${Fn}", "Comment": "in ${Bucket}/${Bucket}", "L": ["${Bucket}"]}}}),
            &subs(),
        )
        .unwrap();
        assert_eq!(
            out.value,
            json!({"States": {"A": {"Resource": "arn:aws:lambda:us-east-1:1:function:f", "Comment": "in b/b", "L": ["b"]}}})
        );
        assert_eq!(
            out.exact.get("States.A.Resource").map(String::as_str),
            Some("Fn")
        );
        assert_eq!(
            out.exact.get("States.A.L[0]").map(String::as_str),
            Some("Bucket")
        );
        assert!(!out.exact.contains_key("States.A.Comment"));
    }

    #[test]
    fn a_missing_value_is_an_error_naming_the_location() {
        let err =
            substitute(&json!({"States": {"A": {"Resource": "${Nope}"}}}), &subs()).unwrap_err();
        assert_eq!(err.name(), "MissingSubstitution");
        assert_eq!(err.location(), "States.A.Resource");
    }

    #[test]
    fn malformed_references_are_left_as_written() {
        let out = substitute(
            &json!(["${", "${}", "${a b}", "$${Bucket}", "x${Bucket"]),
            &subs(),
        )
        .unwrap();
        assert_eq!(out.value, json!(["${", "${}", "${a b}", "$b", "x${Bucket"]));
    }
}
