//! Python-flavoured JSON values: parsing like `json.loads`, `str()`/`repr()` and `json.dumps` output.
//!
//! EvalAI's behaviour depends on Python semantics (bools are ints, `NaN` parses, `str()` of
//! a dict uses single quotes, parser messages quoted verbatim in 400 bodies), so the fake
//! models values the way Python sees them instead of using `serde_json::Value`.

use std::fmt::Write as _;

use serde::ser::{SerializeMap, SerializeSeq};

/// A value as Python's `json` module produces it. Dicts keep insertion order.
#[derive(Debug, Clone, PartialEq)]
pub enum PyValue {
    /// `None` (JSON `null`).
    None,
    /// `True` / `False`.
    Bool(bool),
    /// An `int` (values beyond `i128` are parsed as floats).
    Int(i128),
    /// A `float`, possibly NaN or infinite (Python's parser accepts `NaN` and `Infinity`).
    Float(f64),
    /// A `str`.
    Str(String),
    /// A `list`.
    List(Vec<PyValue>),
    /// A `dict` with string keys, in insertion order.
    Dict(Vec<(String, PyValue)>),
}

impl PyValue {
    /// Builds a dict from `(key, value)` pairs.
    pub fn dict<K: Into<String>>(pairs: Vec<(K, PyValue)>) -> PyValue {
        PyValue::Dict(pairs.into_iter().map(|(k, v)| (k.into(), v)).collect())
    }

    /// Builds a string value.
    pub fn str(s: impl Into<String>) -> PyValue {
        PyValue::Str(s.into())
    }

    /// `dict.get(key)` for dicts; `None` for a missing key or a non-dict.
    pub fn get(&self, key: &str) -> Option<&PyValue> {
        match self {
            PyValue::Dict(pairs) => pairs.iter().find(|(k, _)| k == key).map(|(_, v)| v),
            _ => None,
        }
    }

    /// `d[key] = value`: replaces in place (keeping the position) or appends.
    pub fn dict_set(pairs: &mut Vec<(String, PyValue)>, key: String, value: PyValue) {
        if let Some(slot) = pairs.iter_mut().find(|(k, _)| *k == key) {
            slot.1 = value;
        } else {
            pairs.push((key, value));
        }
    }

    /// Python's `type(x).__name__`.
    pub fn type_name(&self) -> &'static str {
        match self {
            PyValue::None => "NoneType",
            PyValue::Bool(_) => "bool",
            PyValue::Int(_) => "int",
            PyValue::Float(_) => "float",
            PyValue::Str(_) => "str",
            PyValue::List(_) => "list",
            PyValue::Dict(_) => "dict",
        }
    }

    /// Python truthiness (`bool(x)`).
    pub fn truthy(&self) -> bool {
        match self {
            PyValue::None => false,
            PyValue::Bool(b) => *b,
            PyValue::Int(i) => *i != 0,
            PyValue::Float(f) => *f != 0.0,
            PyValue::Str(s) => !s.is_empty(),
            PyValue::List(l) => !l.is_empty(),
            PyValue::Dict(d) => !d.is_empty(),
        }
    }

    /// `isinstance(x, (int, float))`: bools pass because `bool` subclasses `int`.
    pub fn is_number(&self) -> bool {
        matches!(self, PyValue::Bool(_) | PyValue::Int(_) | PyValue::Float(_))
    }

    /// True when the value (recursively) holds a NaN or infinite float, which
    /// Postgres refuses to store in a JSON column.
    pub fn has_non_finite(&self) -> bool {
        match self {
            PyValue::Float(f) => !f.is_finite(),
            PyValue::List(l) => l.iter().any(PyValue::has_non_finite),
            PyValue::Dict(d) => d.iter().any(|(_, v)| v.has_non_finite()),
            _ => false,
        }
    }

    /// Python's `repr(x)`.
    pub fn repr(&self) -> String {
        let mut out = String::new();
        self.write_repr(&mut out);
        out
    }

    /// Python's `str(x)`: a string is itself, everything else is its repr.
    pub fn py_str(&self) -> String {
        match self {
            PyValue::Str(s) => s.clone(),
            other => other.repr(),
        }
    }

    fn write_repr(&self, out: &mut String) {
        match self {
            PyValue::None => out.push_str("None"),
            PyValue::Bool(true) => out.push_str("True"),
            PyValue::Bool(false) => out.push_str("False"),
            PyValue::Int(i) => {
                let _ = write!(out, "{i}");
            }
            PyValue::Float(f) => out.push_str(&float_repr(*f)),
            PyValue::Str(s) => out.push_str(&str_repr(s)),
            PyValue::List(items) => {
                out.push('[');
                for (i, item) in items.iter().enumerate() {
                    if i > 0 {
                        out.push_str(", ");
                    }
                    item.write_repr(out);
                }
                out.push(']');
            }
            PyValue::Dict(pairs) => {
                out.push('{');
                for (i, (k, v)) in pairs.iter().enumerate() {
                    if i > 0 {
                        out.push_str(", ");
                    }
                    out.push_str(&str_repr(k));
                    out.push_str(": ");
                    v.write_repr(out);
                }
                out.push('}');
            }
        }
    }

    /// `json.dumps(x, separators=(",", ":"), ensure_ascii=False)`, as DRF renders responses.
    pub fn dumps(&self) -> String {
        let mut out = String::new();
        self.write_json(&mut out, (",", ":"));
        out
    }

    /// `json.dumps(x)`'s separators (`", "`, `": "`), as a stored file written by Python reads.
    pub fn dumps_spaced(&self) -> String {
        let mut out = String::new();
        self.write_json(&mut out, (", ", ": "));
        out
    }

    fn write_json(&self, out: &mut String, separators: (&str, &str)) {
        match self {
            PyValue::None => out.push_str("null"),
            PyValue::Bool(b) => out.push_str(if *b { "true" } else { "false" }),
            PyValue::Int(i) => {
                let _ = write!(out, "{i}");
            }
            PyValue::Float(f) => {
                if f.is_nan() {
                    out.push_str("NaN");
                } else if f.is_infinite() {
                    out.push_str(if *f > 0.0 { "Infinity" } else { "-Infinity" });
                } else {
                    out.push_str(&float_repr(*f));
                }
            }
            PyValue::Str(s) => write_json_string(s, out),
            PyValue::List(items) => {
                out.push('[');
                for (i, item) in items.iter().enumerate() {
                    if i > 0 {
                        out.push_str(separators.0);
                    }
                    item.write_json(out, separators);
                }
                out.push(']');
            }
            PyValue::Dict(pairs) => {
                out.push('{');
                for (i, (k, v)) in pairs.iter().enumerate() {
                    if i > 0 {
                        out.push_str(separators.0);
                    }
                    write_json_string(k, out);
                    out.push_str(separators.1);
                    v.write_json(out, separators);
                }
                out.push('}');
            }
        }
    }

    /// Converts to a `serde_json::Value` (non-finite floats become `null`).
    pub fn to_json(&self) -> serde_json::Value {
        use serde_json::Value;
        match self {
            PyValue::None => Value::Null,
            PyValue::Bool(b) => Value::Bool(*b),
            PyValue::Int(i) => {
                if let Ok(v) = i64::try_from(*i) {
                    Value::from(v)
                } else if let Ok(v) = u64::try_from(*i) {
                    Value::from(v)
                } else {
                    serde_json::Number::from_f64(*i as f64).map_or(Value::Null, Value::Number)
                }
            }
            PyValue::Float(f) => {
                serde_json::Number::from_f64(*f).map_or(Value::Null, Value::Number)
            }
            PyValue::Str(s) => Value::String(s.clone()),
            PyValue::List(items) => Value::Array(items.iter().map(PyValue::to_json).collect()),
            PyValue::Dict(pairs) => Value::Object(
                pairs
                    .iter()
                    .map(|(k, v)| (k.clone(), v.to_json()))
                    .collect(),
            ),
        }
    }

    /// Converts from a `serde_json::Value` (integers stay ints, other numbers become floats).
    pub fn from_json(value: &serde_json::Value) -> PyValue {
        use serde_json::Value;
        match value {
            Value::Null => PyValue::None,
            Value::Bool(b) => PyValue::Bool(*b),
            Value::Number(n) => {
                if let Some(i) = n.as_i64() {
                    PyValue::Int(i128::from(i))
                } else if let Some(u) = n.as_u64() {
                    PyValue::Int(i128::from(u))
                } else {
                    PyValue::Float(n.as_f64().unwrap_or(f64::NAN))
                }
            }
            Value::String(s) => PyValue::Str(s.clone()),
            Value::Array(items) => PyValue::List(items.iter().map(PyValue::from_json).collect()),
            Value::Object(map) => PyValue::Dict(
                map.iter()
                    .map(|(k, v)| (k.clone(), PyValue::from_json(v)))
                    .collect(),
            ),
        }
    }
}

impl serde::Serialize for PyValue {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        match self {
            PyValue::None => serializer.serialize_unit(),
            PyValue::Bool(b) => serializer.serialize_bool(*b),
            PyValue::Int(i) => {
                if let Ok(v) = i64::try_from(*i) {
                    serializer.serialize_i64(v)
                } else {
                    serializer.serialize_f64(*i as f64)
                }
            }
            PyValue::Float(f) if f.is_finite() => serializer.serialize_f64(*f),
            PyValue::Float(_) => serializer.serialize_unit(),
            PyValue::Str(s) => serializer.serialize_str(s),
            PyValue::List(items) => {
                let mut seq = serializer.serialize_seq(Some(items.len()))?;
                for item in items {
                    seq.serialize_element(item)?;
                }
                seq.end()
            }
            PyValue::Dict(pairs) => {
                let mut map = serializer.serialize_map(Some(pairs.len()))?;
                for (k, v) in pairs {
                    map.serialize_entry(k, v)?;
                }
                map.end()
            }
        }
    }
}

fn write_json_string(s: &str, out: &mut String) {
    out.push('"');
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            '\n' => out.push_str("\\n"),
            '\r' => out.push_str("\\r"),
            '\t' => out.push_str("\\t"),
            '\u{08}' => out.push_str("\\b"),
            '\u{0c}' => out.push_str("\\f"),
            c if (c as u32) < 0x20 => {
                let _ = write!(out, "\\u{:04x}", c as u32);
            }
            c => out.push(c),
        }
    }
    out.push('"');
}

/// Python's `repr()` of a `str`: single quotes unless the text holds `'` and no `"`.
pub fn str_repr(s: &str) -> String {
    let quote = if s.contains('\'') && !s.contains('"') {
        '"'
    } else {
        '\''
    };
    let mut out = String::with_capacity(s.len() + 2);
    out.push(quote);
    for c in s.chars() {
        match c {
            '\\' => out.push_str("\\\\"),
            '\n' => out.push_str("\\n"),
            '\r' => out.push_str("\\r"),
            '\t' => out.push_str("\\t"),
            c if c == quote => {
                out.push('\\');
                out.push(c);
            }
            c if (c as u32) < 0x20 || c as u32 == 0x7f => {
                let _ = write!(out, "\\x{:02x}", c as u32);
            }
            c if (0x80..0xa0).contains(&(c as u32)) => {
                let _ = write!(out, "\\x{:02x}", c as u32);
            }
            c => out.push(c),
        }
    }
    out.push(quote);
    out
}

/// Python's `repr()` of a `float`: shortest round-trip digits, scientific notation
/// when the decimal exponent is below -4 or at least 16 (`1e-05`, `1e+16`, `100.0`).
pub fn float_repr(f: f64) -> String {
    if f.is_nan() {
        return "nan".to_owned();
    }
    if f.is_infinite() {
        return if f > 0.0 { "inf" } else { "-inf" }.to_owned();
    }
    if f == 0.0 {
        return if f.is_sign_negative() { "-0.0" } else { "0.0" }.to_owned();
    }
    // `{:e}` gives the shortest round-trip digits as `d.ddde<exp>`.
    let sci = format!("{f:e}");
    let (mantissa, exp) = sci.split_once('e').unwrap_or((sci.as_str(), "0"));
    let exp: i32 = exp.parse().unwrap_or(0);
    let (sign, mantissa) = match mantissa.strip_prefix('-') {
        Some(m) => ("-", m),
        None => ("", mantissa),
    };
    let digits: String = mantissa.chars().filter(|c| *c != '.').collect();
    if !(-5 < exp && exp < 16) {
        let mut m = String::new();
        m.push_str(&digits[..1]);
        if digits.len() > 1 {
            m.push('.');
            m.push_str(&digits[1..]);
        }
        let esign = if exp < 0 { '-' } else { '+' };
        return format!("{sign}{m}e{esign}{:02}", exp.abs());
    }
    let point = exp + 1; // digits before the decimal point
    let body = if point <= 0 {
        format!("0.{}{}", "0".repeat(point.unsigned_abs() as usize), digits)
    } else if (point as usize) >= digits.len() {
        format!("{}{}.0", digits, "0".repeat(point as usize - digits.len()))
    } else {
        let (int, frac) = digits.split_at(point as usize);
        format!("{int}.{frac}")
    };
    format!("{sign}{body}")
}

/// How the parser treats `NaN`, `Infinity` and `-Infinity`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Constants {
    /// `json.loads` default: accepted as floats.
    Allow,
    /// DRF's request parser: rejected with "Out of range float values are not JSON compliant".
    Reject,
}

/// Parses like Python's `json.loads(s)`; the error is Python's message text
/// (`Expecting value: line 1 column 1 (char 0)`).
pub fn loads(s: &str, constants: Constants) -> Result<PyValue, String> {
    let chars: Vec<char> = s.chars().collect();
    if chars.first() == Some(&'\u{feff}') {
        return Err(errmsg(
            "Unexpected UTF-8 BOM (decode using utf-8-sig)",
            &chars,
            0,
        ));
    }
    let mut p = Parser {
        s: &chars,
        constants,
        depth: 0,
    };
    let start = p.ws(0);
    let (value, end) = p.value(start).map_err(|e| e.render(&chars))?;
    let end = p.ws(end);
    if end != chars.len() {
        return Err(errmsg("Extra data", &chars, end));
    }
    Ok(value)
}

fn errmsg(msg: &str, s: &[char], pos: usize) -> String {
    let before = &s[..pos.min(s.len())];
    let lineno = before.iter().filter(|c| **c == '\n').count() + 1;
    let colno = match before.iter().rposition(|c| *c == '\n') {
        Some(nl) => pos - nl,
        None => pos + 1,
    };
    format!("{msg}: line {lineno} column {colno} (char {pos})")
}

enum ParseError {
    At(String, usize),
    /// Raised by `parse_constant` (no position in the message).
    Plain(String),
}

impl ParseError {
    fn render(self, s: &[char]) -> String {
        match self {
            ParseError::At(msg, pos) => errmsg(&msg, s, pos),
            ParseError::Plain(msg) => msg,
        }
    }
}

struct Parser<'a> {
    s: &'a [char],
    constants: Constants,
    depth: usize,
}

/// Deep nesting makes CPython raise RecursionError; we refuse well before the stack is at risk.
const MAX_DEPTH: usize = 512;

impl Parser<'_> {
    fn ws(&self, mut i: usize) -> usize {
        while i < self.s.len() && matches!(self.s[i], ' ' | '\t' | '\n' | '\r') {
            i += 1;
        }
        i
    }

    fn starts_with(&self, i: usize, lit: &str) -> bool {
        lit.chars()
            .enumerate()
            .all(|(k, c)| self.s.get(i + k) == Some(&c))
    }

    fn constant(&self, name: &str, value: f64) -> Result<PyValue, ParseError> {
        match self.constants {
            Constants::Allow => Ok(PyValue::Float(value)),
            Constants::Reject => Err(ParseError::Plain(format!(
                "Out of range float values are not JSON compliant: {}",
                str_repr(name)
            ))),
        }
    }

    fn value(&mut self, i: usize) -> Result<(PyValue, usize), ParseError> {
        let expecting = || ParseError::At("Expecting value".to_owned(), i);
        let Some(&c) = self.s.get(i) else {
            return Err(expecting());
        };
        match c {
            '"' => {
                let (s, end) = self.string(i + 1)?;
                Ok((PyValue::Str(s), end))
            }
            '{' | '[' => {
                self.depth += 1;
                if self.depth > MAX_DEPTH {
                    return Err(ParseError::Plain(
                        "maximum recursion depth exceeded while decoding a JSON document"
                            .to_owned(),
                    ));
                }
                let r = if c == '{' {
                    self.object(i + 1)
                } else {
                    self.array(i + 1)
                };
                self.depth -= 1;
                r
            }
            'n' if self.starts_with(i, "null") => Ok((PyValue::None, i + 4)),
            't' if self.starts_with(i, "true") => Ok((PyValue::Bool(true), i + 4)),
            'f' if self.starts_with(i, "false") => Ok((PyValue::Bool(false), i + 5)),
            'N' if self.starts_with(i, "NaN") => Ok((self.constant("NaN", f64::NAN)?, i + 3)),
            'I' if self.starts_with(i, "Infinity") => {
                Ok((self.constant("Infinity", f64::INFINITY)?, i + 8))
            }
            '-' if self.starts_with(i, "-Infinity") => {
                Ok((self.constant("-Infinity", f64::NEG_INFINITY)?, i + 9))
            }
            '-' | '0'..='9' => self.number(i).ok_or_else(expecting),
            _ => Err(expecting()),
        }
    }

    /// Python's NUMBER_RE: `(-?(?:0|[1-9]\d*))(\.\d+)?([eE][-+]?\d+)?`.
    fn number(&self, start: usize) -> Option<(PyValue, usize)> {
        let s = self.s;
        let digit = |i: usize| s.get(i).is_some_and(|c| c.is_ascii_digit());
        let mut i = start;
        if s.get(i) == Some(&'-') {
            i += 1;
        }
        match s.get(i) {
            Some('0') => i += 1,
            Some('1'..='9') => {
                while digit(i) {
                    i += 1;
                }
            }
            _ => return None,
        }
        let int_end = i;
        let mut is_float = false;
        if s.get(i) == Some(&'.') && digit(i + 1) {
            i += 1;
            while digit(i) {
                i += 1;
            }
            is_float = true;
        }
        if matches!(s.get(i), Some('e' | 'E')) {
            let mut j = i + 1;
            if matches!(s.get(j), Some('+' | '-')) {
                j += 1;
            }
            if digit(j) {
                while digit(j) {
                    j += 1;
                }
                i = j;
                is_float = true;
            }
        }
        let text: String = s[start..i].iter().collect();
        if !is_float {
            debug_assert_eq!(int_end, i);
            if let Ok(v) = text.parse::<i128>() {
                return Some((PyValue::Int(v), i));
            }
        }
        let f: f64 = text.parse().unwrap_or(f64::NAN);
        Some((PyValue::Float(f), i))
    }

    fn string(&self, mut i: usize) -> Result<(String, usize), ParseError> {
        let begin = i - 1;
        let mut out = String::new();
        loop {
            let Some(&c) = self.s.get(i) else {
                return Err(ParseError::At(
                    "Unterminated string starting at".to_owned(),
                    begin,
                ));
            };
            match c {
                '"' => return Ok((out, i + 1)),
                '\\' => {
                    let Some(&esc) = self.s.get(i + 1) else {
                        return Err(ParseError::At(
                            "Unterminated string starting at".to_owned(),
                            begin,
                        ));
                    };
                    match esc {
                        '"' => out.push('"'),
                        '\\' => out.push('\\'),
                        '/' => out.push('/'),
                        'b' => out.push('\u{08}'),
                        'f' => out.push('\u{0c}'),
                        'n' => out.push('\n'),
                        'r' => out.push('\r'),
                        't' => out.push('\t'),
                        'u' => {
                            let (ch, next) = self.unicode_escape(i)?;
                            out.push(ch);
                            i = next;
                            continue;
                        }
                        other => {
                            return Err(ParseError::At(
                                format!("Invalid \\escape: {}", str_repr(&other.to_string())),
                                i,
                            ))
                        }
                    }
                    i += 2;
                }
                c if (c as u32) < 0x20 => {
                    return Err(ParseError::At("Invalid control character at".to_owned(), i));
                }
                c => {
                    out.push(c);
                    i += 1;
                }
            }
        }
    }

    fn hex4(&self, at: usize) -> Option<u32> {
        let text: String = self.s.get(at..at + 4)?.iter().collect();
        if text.len() != 4 || !text.chars().all(|c| c.is_ascii_hexdigit()) {
            return None;
        }
        u32::from_str_radix(&text, 16).ok()
    }

    /// `i` points at the backslash of `\uXXXX`; returns the char and the index after it.
    fn unicode_escape(&self, i: usize) -> Result<(char, usize), ParseError> {
        let bad = || ParseError::At("Invalid \\uXXXX escape".to_owned(), i + 1);
        let hi = self.hex4(i + 2).ok_or_else(bad)?;
        let mut next = i + 6;
        let code = if (0xd800..0xdc00).contains(&hi)
            && self.s.get(next) == Some(&'\\')
            && self.s.get(next + 1) == Some(&'u')
        {
            match self.hex4(next + 2) {
                Some(lo) if (0xdc00..0xe000).contains(&lo) => {
                    next += 6;
                    0x10000 + ((hi - 0xd800) << 10) + (lo - 0xdc00)
                }
                Some(_) => hi,
                None => {
                    return Err(ParseError::At(
                        "Invalid \\uXXXX escape".to_owned(),
                        next + 1,
                    ))
                }
            }
        } else {
            hi
        };
        // Python keeps lone surrogates; Rust strings cannot, so they become U+FFFD.
        Ok((char::from_u32(code).unwrap_or('\u{fffd}'), next))
    }

    fn object(&mut self, start: usize) -> Result<(PyValue, usize), ParseError> {
        let mut pairs: Vec<(String, PyValue)> = Vec::new();
        let mut i = self.ws(start);
        match self.s.get(i) {
            Some('}') => return Ok((PyValue::Dict(pairs), i + 1)),
            Some('"') => {}
            _ => {
                return Err(ParseError::At(
                    "Expecting property name enclosed in double quotes".to_owned(),
                    i,
                ))
            }
        }
        loop {
            let (key, after_key) = self.string(i + 1)?;
            i = self.ws(after_key);
            if self.s.get(i) != Some(&':') {
                return Err(ParseError::At("Expecting ':' delimiter".to_owned(), i));
            }
            i = self.ws(i + 1);
            let (value, after_value) = self.value(i)?;
            PyValue::dict_set(&mut pairs, key, value);
            i = self.ws(after_value);
            match self.s.get(i) {
                Some('}') => return Ok((PyValue::Dict(pairs), i + 1)),
                Some(',') => {}
                _ => return Err(ParseError::At("Expecting ',' delimiter".to_owned(), i)),
            }
            i = self.ws(i + 1);
            if self.s.get(i) != Some(&'"') {
                return Err(ParseError::At(
                    "Expecting property name enclosed in double quotes".to_owned(),
                    i,
                ));
            }
        }
    }

    fn array(&mut self, start: usize) -> Result<(PyValue, usize), ParseError> {
        let mut items = Vec::new();
        let mut i = self.ws(start);
        if self.s.get(i) == Some(&']') {
            return Ok((PyValue::List(items), i + 1));
        }
        loop {
            let (value, after) = self.value(i)?;
            items.push(value);
            i = self.ws(after);
            match self.s.get(i) {
                Some(']') => return Ok((PyValue::List(items), i + 1)),
                Some(',') => {}
                _ => return Err(ParseError::At("Expecting ',' delimiter".to_owned(), i)),
            }
            i = self.ws(i + 1);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn float_repr_matches_python() {
        assert_eq!(float_repr(1.0), "1.0");
        assert_eq!(float_repr(0.1), "0.1");
        assert_eq!(float_repr(100.0), "100.0");
        assert_eq!(float_repr(1e-5), "1e-05");
        assert_eq!(float_repr(0.0001), "0.0001");
        assert_eq!(float_repr(6.8e-05), "6.8e-05");
        assert_eq!(float_repr(1e16), "1e+16");
        assert_eq!(float_repr(1e15), "1000000000000000.0");
        assert_eq!(float_repr(-2.5), "-2.5");
        assert_eq!(float_repr(23.699655), "23.699655");
        assert_eq!(float_repr(1.5e300), "1.5e+300");
    }

    #[test]
    fn repr_of_containers_uses_python_quoting() {
        let v = PyValue::dict(vec![
            ("a", PyValue::str("it's")),
            ("b", PyValue::List(vec![PyValue::Bool(true), PyValue::None])),
            ("c", PyValue::Float(2.0)),
        ]);
        assert_eq!(v.repr(), "{'a': \"it's\", 'b': [True, None], 'c': 2.0}");
        assert_eq!(PyValue::str("x").py_str(), "x");
    }

    #[test]
    fn loads_reports_python_messages() {
        assert_eq!(
            loads("", Constants::Allow).unwrap_err(),
            "Expecting value: line 1 column 1 (char 0)"
        );
        assert_eq!(
            loads("[1,]", Constants::Allow).unwrap_err(),
            "Expecting value: line 1 column 4 (char 3)"
        );
        assert_eq!(
            loads("{\"a\" 1}", Constants::Allow).unwrap_err(),
            "Expecting ':' delimiter: line 1 column 6 (char 5)"
        );
        assert_eq!(
            loads("[1]\n x", Constants::Allow).unwrap_err(),
            "Extra data: line 2 column 2 (char 5)"
        );
        assert_eq!(
            loads("{'a': 1}", Constants::Allow).unwrap_err(),
            "Expecting property name enclosed in double quotes: line 1 column 2 (char 1)"
        );
        assert_eq!(
            loads("[NaN]", Constants::Reject).unwrap_err(),
            "Out of range float values are not JSON compliant: 'NaN'"
        );
    }

    #[test]
    fn loads_keeps_python_types() {
        let v = loads(
            r#"{"i": 1, "f": 1.0, "e": 1e2, "b": true, "n": NaN, "s": "\u00e9\ud83d\ude00", "i": 2}"#,
            Constants::Allow,
        )
        .unwrap();
        assert_eq!(v.get("i"), Some(&PyValue::Int(2)));
        assert_eq!(v.get("f"), Some(&PyValue::Float(1.0)));
        assert_eq!(v.get("e"), Some(&PyValue::Float(100.0)));
        assert_eq!(v.get("b"), Some(&PyValue::Bool(true)));
        assert!(matches!(v.get("n"), Some(PyValue::Float(f)) if f.is_nan()));
        assert_eq!(v.get("s"), Some(&PyValue::str("é😀")));
        let PyValue::Dict(pairs) = &v else {
            panic!("not a dict")
        };
        assert_eq!(pairs[0].0, "i", "a repeated key keeps its first position");
    }

    #[test]
    fn dumps_is_compact_and_python_like() {
        let v = loads(
            r#"{"a": [1, 2.5, 1e-7, null], "b": "x\"y"}"#,
            Constants::Allow,
        )
        .unwrap();
        assert_eq!(v.dumps(), r#"{"a":[1,2.5,1e-07,null],"b":"x\"y"}"#);
    }
}
