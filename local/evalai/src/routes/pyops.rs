//! The Python/Django operations EvalAI's views perform on request data, with their failures.

use crate::pyjson::{self, Constants, PyValue};
use crate::routes::body::Data;
use crate::routes::reply::{Reply, ViewResult};
use crate::state::World;
use axum::http::StatusCode;

/// `AttributeError` on a value of the wrong type: an HTML 500.
pub(crate) fn attribute_error(v: &PyValue, attr: &str) -> Reply {
    Reply::server_error(format!(
        "AttributeError: '{}' object has no attribute '{attr}'",
        v.type_name()
    ))
}

impl Data {
    /// `request.data.get(key)`: a 500 when the body is JSON but not an object.
    pub fn get(&self, key: &str) -> ViewResult<Option<&PyValue>> {
        match &self.value {
            PyValue::Dict(_) => Ok(self.value.get(key)),
            other => Err(attribute_error(other, "get")),
        }
    }

    /// `request.data.get(key, "")`.
    pub fn get_or_empty(&self, key: &str) -> ViewResult<PyValue> {
        Ok(self
            .get(key)?
            .cloned()
            .unwrap_or(PyValue::Str(String::new())))
    }

    /// `QueryDict.getlist(key)` for form bodies.
    pub fn getlist(&self, key: &str) -> Option<Vec<String>> {
        self.fields.as_ref().map(|fields| {
            fields
                .iter()
                .filter(|(k, _)| k == key)
                .map(|(_, v)| v.clone())
                .collect()
        })
    }
}

/// `value.lower()`.
pub(crate) fn lower(v: &PyValue) -> ViewResult<String> {
    match v {
        PyValue::Str(s) => Ok(s.to_lowercase()),
        other => Err(attribute_error(other, "lower")),
    }
}

/// `value.encode("utf-8")`.
pub(crate) fn encode(v: &PyValue) -> ViewResult<String> {
    match v {
        PyValue::Str(s) => Ok(s.clone()),
        other => Err(attribute_error(other, "encode")),
    }
}

/// `ContentFile(value)`: only text (or bytes) can be stored.
pub(crate) fn content_file(v: &PyValue) -> ViewResult<String> {
    match v {
        PyValue::Str(s) => Ok(s.clone()),
        PyValue::None => Err(Reply::server_error(
            "TypeError: object of type 'NoneType' has no len()",
        )),
        other => Err(Reply::server_error(format!(
            "TypeError: a bytes-like object is required, not '{}'",
            other.type_name()
        ))),
    }
}

/// Python's `int(str)`: surrounding whitespace, a sign, digits with single underscores.
pub(crate) fn py_int(s: &str) -> Option<i128> {
    let t = s.trim();
    let (neg, digits) = match t.as_bytes().first() {
        Some(b'-') => (true, &t[1..]),
        Some(b'+') => (false, &t[1..]),
        _ => (false, t),
    };
    if digits.is_empty()
        || digits.starts_with('_')
        || digits.ends_with('_')
        || digits.contains("__")
        || !digits.chars().all(|c| c.is_ascii_digit() || c == '_')
    {
        return None;
    }
    let clean: String = digits.chars().filter(|c| *c != '_').collect();
    let v: i128 = clean.parse().ok()?;
    Some(if neg { -v } else { v })
}

/// The value Django's `IntegerField.get_prep_value` (`int(value)`) gives a lookup;
/// `None` means `IS NULL` (matches nothing).
pub(crate) fn int_lookup(v: &PyValue) -> ViewResult<Option<i128>> {
    match v {
        PyValue::None => Ok(None),
        PyValue::Bool(b) => Ok(Some(i128::from(*b))),
        PyValue::Int(i) => Ok(Some(*i)),
        PyValue::Float(f) if f.is_nan() => Err(Reply::server_error(
            "ValueError: cannot convert float NaN to integer",
        )),
        PyValue::Float(f) if f.is_infinite() => Err(Reply::server_error(
            "OverflowError: cannot convert float infinity to integer",
        )),
        PyValue::Float(f) => Ok(Some(f.trunc() as i128)),
        PyValue::Str(s) => py_int(s).map(Some).ok_or_else(|| {
            Reply::server_error(format!(
                "ValueError: invalid literal for int() with base 10: {}",
                pyjson::str_repr(s)
            ))
        }),
        other => Err(Reply::server_error(format!(
            "TypeError: int() argument must be a string, a bytes-like object or a number, not '{}'",
            other.type_name()
        ))),
    }
}

/// The value Django's `CharField` gives a lookup (`str(value)`); `None` means `IS NULL`.
pub(crate) fn char_lookup(v: Option<&PyValue>) -> Option<String> {
    match v {
        None | Some(PyValue::None) => None,
        Some(v) => Some(v.py_str()),
    }
}

/// `str(value)` of an optional request field (`None` when absent).
pub(crate) fn shown(v: Option<&PyValue>) -> String {
    v.map_or_else(|| "None".to_owned(), PyValue::py_str)
}

/// `get_submission_model(pk)`: 404 `{"detail": "Submission <pk> does not exist"}`.
pub(crate) fn get_submission_model(world: &World, pk: Option<&PyValue>) -> ViewResult<u64> {
    let id = match pk {
        None => None,
        Some(v) => int_lookup(v)?,
    };
    match id.and_then(|i| u64::try_from(i).ok()) {
        Some(id) if world.submissions.contains_key(&id) => Ok(id),
        _ => Err(Reply::detail(
            StatusCode::NOT_FOUND,
            format!("Submission {} does not exist", shown(pk)),
        )),
    }
}

/// `json.loads(value)` on a request field: the error text is Python's.
pub(crate) fn json_loads_field(v: &PyValue) -> Result<PyValue, String> {
    match v {
        PyValue::Str(s) => pyjson::loads(s, Constants::Allow),
        other => Err(format!(
            "the JSON object must be str, bytes or bytearray, not {}",
            other.type_name()
        )),
    }
}

/// `for x in value`: lists yield items, dicts their keys, strings their characters.
pub(crate) fn iterate(v: PyValue) -> ViewResult<Vec<PyValue>> {
    match v {
        PyValue::List(items) => Ok(items),
        PyValue::Dict(pairs) => Ok(pairs.into_iter().map(|(k, _)| PyValue::Str(k)).collect()),
        PyValue::Str(s) => Ok(s.chars().map(|c| PyValue::Str(c.to_string())).collect()),
        other => Err(Reply::server_error(format!(
            "TypeError: '{}' object is not iterable",
            other.type_name()
        ))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn py_int_accepts_what_python_accepts() {
        assert_eq!(py_int(" 7 "), Some(7));
        assert_eq!(py_int("+7"), Some(7));
        assert_eq!(py_int("-1_000"), Some(-1000));
        assert_eq!(py_int("1.0"), None);
        assert_eq!(py_int("abc"), None);
        assert_eq!(py_int(""), None);
        assert_eq!(py_int("1__0"), None);
    }
}
