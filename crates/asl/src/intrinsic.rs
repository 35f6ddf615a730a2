//! Intrinsic functions (`States.Format(...)` and friends): parsed and checked at load time,
//! evaluated against an input and the context object.
//!
//! Argument syntax, as the Amazon States Language defines it: string literals in single
//! quotes, where `\'`, `\{`, `\}` and `\\` stand for `'`, `{`, `}` and `\` (any other
//! backslash is an error; an unescaped `{` or `}` is only allowed as the `{}` pair); numbers;
//! `true`, `false`, `null`; paths (`$.a`, `$$.Execution.Id`); nested calls (at most 10
//! levels). Each function's argument rules follow the Step Functions developer guide; where
//! an argument is a literal, its rule is checked at load time.

use std::fmt;

use base64::Engine as _;
use serde_json::{Number, Value};

use crate::error::{preview, AslError, LoadError};
use crate::path::{kind, Path, Root};
use crate::random::RandomSource;
use crate::Env;

/// The deepest nesting of calls Step Functions accepts in one field.
pub const MAX_NESTING: usize = 10;

/// The longest string `States.Hash`, `States.Base64Encode` and `States.Base64Decode` take.
pub const MAX_STRING_CHARS: usize = 10_000;

/// The longest array `States.ArrayRange` may produce.
pub const MAX_RANGE_ITEMS: i128 = 1000;

/// The hash algorithms `States.Hash` accepts, as spelled in its second argument.
pub const HASH_ALGORITHMS: [&str; 5] = ["MD5", "SHA-1", "SHA-256", "SHA-384", "SHA-512"];

macro_rules! functions {
    ($($variant:ident => $name:literal),* $(,)?) => {
        /// An intrinsic function.
        #[derive(Debug, Clone, Copy, PartialEq, Eq)]
        pub enum Function { $(#[doc = $name] $variant),* }

        impl Function {
            /// All functions, in the developer guide's order.
            pub const ALL: &'static [Function] = &[$(Function::$variant),*];

            /// The name as written in a call (`States.Format`).
            pub fn name(self) -> &'static str {
                match self { $(Function::$variant => $name),* }
            }
        }
    };
}

functions! {
    Format => "States.Format",
    StringToJson => "States.StringToJson",
    JsonToString => "States.JsonToString",
    Array => "States.Array",
    ArrayPartition => "States.ArrayPartition",
    ArrayContains => "States.ArrayContains",
    ArrayRange => "States.ArrayRange",
    ArrayGetItem => "States.ArrayGetItem",
    ArrayLength => "States.ArrayLength",
    ArrayUnique => "States.ArrayUnique",
    Base64Encode => "States.Base64Encode",
    Base64Decode => "States.Base64Decode",
    Hash => "States.Hash",
    JsonMerge => "States.JsonMerge",
    MathRandom => "States.MathRandom",
    MathAdd => "States.MathAdd",
    StringSplit => "States.StringSplit",
    Uuid => "States.UUID",
}

impl fmt::Display for Function {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl Function {
    fn from_name(name: &str) -> Option<Function> {
        Function::ALL.iter().copied().find(|f| f.name() == name)
    }

    fn arity(self) -> (usize, usize) {
        use Function::*;
        match self {
            Format => (1, usize::MAX),
            Array => (0, usize::MAX),
            StringToJson | JsonToString | ArrayLength | ArrayUnique | Base64Encode
            | Base64Decode => (1, 1),
            ArrayPartition | ArrayContains | ArrayGetItem | Hash | MathAdd | StringSplit => (2, 2),
            ArrayRange | JsonMerge => (3, 3),
            MathRandom => (2, 3),
            Uuid => (0, 0),
        }
    }
}

/// A piece of a `States.Format` template.
#[derive(Debug, Clone, PartialEq)]
enum Piece {
    Text(String),
    Slot,
}

/// One argument of a call.
#[derive(Debug, Clone, PartialEq)]
enum Arg {
    /// A string literal, decoded, with its pieces as a `States.Format` template.
    Str {
        value: String,
        pieces: Vec<Piece>,
    },
    /// A number, `true`, `false` or `null`.
    Literal(Value),
    Path(Path),
    Call(Box<Call>),
}

impl Arg {
    fn literal(&self) -> Option<Value> {
        match self {
            Arg::Str { value, .. } => Some(Value::String(value.clone())),
            Arg::Literal(v) => Some(v.clone()),
            _ => None,
        }
    }
}

/// A parsed intrinsic function call.
#[derive(Debug, Clone, PartialEq)]
pub struct Call {
    function: Function,
    args: Vec<Arg>,
}

impl Call {
    /// Parses and checks `text` (`States.Format('{}', $.a)`); `location` names the field.
    pub fn parse_at(text: &str, location: &str) -> Result<Call, LoadError> {
        let refuse = |reason: String| LoadError::InvalidIntrinsic {
            location: location.to_owned(),
            call: text.to_owned(),
            reason,
        };
        let mut parser = CallParser {
            chars: text.chars().collect(),
            pos: 0,
            location,
        };
        let call = parser.call(1).map_err(refuse)?;
        if parser.pos != parser.chars.len() {
            return Err(refuse(format!(
                "unexpected text after the call at character {}",
                parser.pos + 1
            )));
        }
        Ok(call)
    }

    /// Parses `text` outside any definition.
    pub fn parse(text: &str) -> Result<Call, LoadError> {
        Call::parse_at(text, "")
    }

    /// The outermost function.
    pub fn function(&self) -> Function {
        self.function
    }

    /// Every path the call (and its nested calls) reads.
    pub fn paths(&self) -> Vec<&Path> {
        let mut out = Vec::new();
        for arg in &self.args {
            match arg {
                Arg::Path(p) => out.push(p),
                Arg::Call(c) => out.extend(c.paths()),
                _ => {}
            }
        }
        out
    }

    /// Evaluates the call; `field` (with its `.$`) names the field in errors.
    pub fn evaluate(&self, field: &str, input: &Value, env: &Env<'_>) -> Result<Value, AslError> {
        let mut values = Vec::with_capacity(self.args.len());
        for arg in &self.args {
            values.push(match arg {
                Arg::Str { value, .. } => Value::String(value.clone()),
                Arg::Literal(v) => v.clone(),
                Arg::Call(c) => c.evaluate(field, input, env)?,
                Arg::Path(p) => match p.select(input, env.context) {
                    Some(v) => v,
                    None => {
                        let read = match p.root() {
                            Root::Input => input,
                            Root::Context => env.context,
                        };
                        return Err(AslError::IntrinsicArgumentNotFound {
                            field: field.to_owned(),
                            path: p.text().to_owned(),
                            input: preview(read),
                        });
                    }
                },
            });
        }
        let template = match self.args.first() {
            Some(Arg::Str { pieces, .. }) => Some(pieces.as_slice()),
            _ => None,
        };
        run(self.function, values, template, env.random).map_err(|reason| {
            AslError::IntrinsicFailure {
                field: field.to_owned(),
                function: self.function.name().to_owned(),
                reason,
            }
        })
    }
}

struct CallParser<'a> {
    chars: Vec<char>,
    pos: usize,
    location: &'a str,
}

impl CallParser<'_> {
    fn peek(&self) -> Option<char> {
        self.chars.get(self.pos).copied()
    }

    fn rest_starts_with(&self, s: &str) -> bool {
        (self.pos..)
            .zip(s.chars())
            .all(|(i, c)| self.chars.get(i) == Some(&c))
    }

    fn skip_ws(&mut self) {
        while self.peek().is_some_and(char::is_whitespace) {
            self.pos += 1;
        }
    }

    fn call(&mut self, depth: usize) -> Result<Call, String> {
        if depth > MAX_NESTING {
            return Err(format!(
                "intrinsic functions nest at most {MAX_NESTING} deep"
            ));
        }
        if !self.rest_starts_with("States.") {
            return Err("an intrinsic function call starts with `States.`".into());
        }
        let start = self.pos;
        self.pos += "States.".len();
        while self.peek().is_some_and(|c| c.is_ascii_alphanumeric()) {
            self.pos += 1;
        }
        let name: String = self.chars[start..self.pos].iter().collect();
        let function = Function::from_name(&name).ok_or_else(|| {
            let known: Vec<&str> = Function::ALL.iter().map(|f| f.name()).collect();
            format!("unknown function `{name}` (known: {})", known.join(", "))
        })?;
        self.skip_ws();
        if self.peek() != Some('(') {
            return Err(format!("expected `(` after `{name}`"));
        }
        self.pos += 1;
        self.skip_ws();
        let mut args = Vec::new();
        if self.peek() == Some(')') {
            self.pos += 1;
        } else {
            loop {
                args.push(self.arg(depth)?);
                self.skip_ws();
                match self.peek() {
                    Some(',') => {
                        self.pos += 1;
                        self.skip_ws();
                    }
                    Some(')') => {
                        self.pos += 1;
                        break;
                    }
                    Some(c) => {
                        return Err(format!(
                            "expected `,` or `)` at character {} but found `{c}`",
                            self.pos + 1
                        ))
                    }
                    None => return Err(format!("unclosed `(` of `{name}`")),
                }
            }
        }
        let call = Call { function, args };
        check(&call)?;
        Ok(call)
    }

    fn arg(&mut self, depth: usize) -> Result<Arg, String> {
        match self.peek() {
            Some('\'') => self.string(),
            Some('$') => self.path(),
            Some('S') if self.rest_starts_with("States.") => {
                Ok(Arg::Call(Box::new(self.call(depth + 1)?)))
            }
            Some(c) if c == '-' || c.is_ascii_digit() => self.number(),
            Some(_) => {
                for (word, value) in [
                    ("true", Value::Bool(true)),
                    ("false", Value::Bool(false)),
                    ("null", Value::Null),
                ] {
                    if self.rest_starts_with(word) {
                        self.pos += word.len();
                        return Ok(Arg::Literal(value));
                    }
                }
                Err(format!(
                    "unexpected text at character {}: an argument is a 'string', a number, true, false, null, a path or a call",
                    self.pos + 1
                ))
            }
            None => Err("the call ends where an argument was expected".into()),
        }
    }

    fn string(&mut self) -> Result<Arg, String> {
        self.pos += 1;
        let mut value = String::new();
        let mut pieces = Vec::new();
        let mut text = String::new();
        loop {
            match self.peek() {
                None => return Err("unclosed string literal".into()),
                Some('\'') => {
                    self.pos += 1;
                    break;
                }
                Some('\\') => {
                    let escaped = self.chars.get(self.pos + 1).copied();
                    match escaped {
                        Some(c @ ('\'' | '{' | '}' | '\\')) => {
                            value.push(c);
                            text.push(c);
                            self.pos += 2;
                        }
                        _ => {
                            return Err(format!(
                                "open escape backslash at character {}: only \\', \\{{, \\}} and \\\\ are escapes",
                                self.pos + 1
                            ))
                        }
                    }
                }
                Some('{') if self.chars.get(self.pos + 1) == Some(&'}') => {
                    value.push_str("{}");
                    if !text.is_empty() {
                        pieces.push(Piece::Text(std::mem::take(&mut text)));
                    }
                    pieces.push(Piece::Slot);
                    self.pos += 2;
                }
                Some(c @ ('{' | '}')) => {
                    return Err(format!(
                        "unescaped `{c}` at character {}: write \\{c} (\\\\{c} in JSON)",
                        self.pos + 1
                    ))
                }
                Some(c) => {
                    value.push(c);
                    text.push(c);
                    self.pos += 1;
                }
            }
        }
        if !text.is_empty() {
            pieces.push(Piece::Text(text));
        }
        Ok(Arg::Str { value, pieces })
    }

    fn path(&mut self) -> Result<Arg, String> {
        let start = self.pos;
        let mut brackets = 0usize;
        let mut quote: Option<char> = None;
        while let Some(c) = self.peek() {
            match (quote, c) {
                (Some(_), '\\') => self.pos += 1,
                (Some(q), c) if c == q => quote = None,
                (Some(_), _) => {}
                (None, '\'' | '"') if brackets > 0 => quote = Some(c),
                (None, '[') => brackets += 1,
                (None, ']') => brackets = brackets.saturating_sub(1),
                (None, ',' | ')') if brackets == 0 => break,
                (None, c) if c.is_whitespace() && brackets == 0 => break,
                _ => {}
            }
            self.pos += 1;
        }
        let text: String = self.chars[start..self.pos.min(self.chars.len())]
            .iter()
            .collect();
        Path::parse_at(&text, self.location)
            .map(Arg::Path)
            .map_err(|e| match e {
                LoadError::InvalidJsonPath { path, reason, .. } => {
                    format!("argument `{path}`: {reason}")
                }
                other => other.to_string(),
            })
    }

    fn number(&mut self) -> Result<Arg, String> {
        let start = self.pos;
        while self
            .peek()
            .is_some_and(|c| c.is_ascii_digit() || "-+.eE".contains(c))
        {
            self.pos += 1;
        }
        let text: String = self.chars[start..self.pos].iter().collect();
        serde_json::from_str::<Number>(&text)
            .map(|n| Arg::Literal(Value::Number(n)))
            .map_err(|_| format!("`{text}` is not a number"))
    }
}

/// Load-time checks: arity and the rules that literal arguments already break.
fn check(call: &Call) -> Result<(), String> {
    use Function::*;
    check_arity(call)?;
    let f = call.function;
    let args = Literals(call);
    match f {
        Format => check_format(call)?,
        StringToJson | Base64Encode | Base64Decode => args.string(0, "the argument")?,
        JsonToString => {
            if !matches!(call.args[0], Arg::Path(_)) {
                return Err(format!("{f}: the argument must be a path"));
            }
        }
        ArrayPartition => {
            args.not_array(0, "the first argument")?;
            if args
                .number(1, "the chunk size")?
                .is_some_and(|size| size <= 0)
            {
                return Err(format!("{f}: the chunk size must be a positive integer"));
            }
        }
        ArrayContains | ArrayLength | ArrayUnique => args.not_array(0, "the first argument")?,
        ArrayGetItem => {
            args.not_array(0, "the first argument")?;
            if args.number(1, "the index")?.is_some_and(|index| index < 0) {
                return Err(format!("{f}: the index must not be negative"));
            }
        }
        ArrayRange => {
            args.number(0, "the first element")?;
            args.number(1, "the last element")?;
            if args.number(2, "the step")? == Some(0) {
                return Err(format!("{f}: the step must not be zero"));
            }
        }
        Hash => {
            args.string(0, "the data")?;
            if let Some(alg) = args.lit(1) {
                if !alg.as_str().is_some_and(|a| HASH_ALGORITHMS.contains(&a)) {
                    return Err(format!(
                        "{f}: the algorithm must be one of {}",
                        HASH_ALGORITHMS.join(", ")
                    ));
                }
            }
        }
        JsonMerge => check_json_merge(&args)?,
        MathRandom => {
            args.number(0, "the start")?;
            args.number(1, "the end")?;
            args.number(2, "the seed")?;
        }
        MathAdd => {
            args.number(0, "the first argument")?;
            args.number(1, "the second argument")?;
        }
        StringSplit => {
            args.string(0, "the string")?;
            args.string(1, "the delimiters")?;
        }
        Array | Uuid => {}
    }
    Ok(())
}

/// The call has as many arguments as its function takes.
fn check_arity(call: &Call) -> Result<(), String> {
    let f = call.function;
    let n = call.args.len();
    let (min, max) = f.arity();
    if n < min || n > max {
        let expected = match (min, max) {
            (a, b) if a == b => format!("{a}"),
            (a, usize::MAX) => format!("at least {a}"),
            (a, b) => format!("{a} to {b}"),
        };
        return Err(format!("{f} takes {expected} argument(s), got {n}"));
    }
    Ok(())
}

/// `States.Format`: a literal template has one `{}` per value after it.
fn check_format(call: &Call) -> Result<(), String> {
    let f = call.function;
    let n = call.args.len();
    Literals(call).string(0, "the template (first argument)")?;
    if let Some(Arg::Str { pieces, .. }) = call.args.first() {
        let slots = pieces.iter().filter(|p| **p == Piece::Slot).count();
        if slots != n - 1 {
            return Err(format!(
                "{f}: the template has {slots} `{{}}` but {} value(s) follow it",
                n - 1
            ));
        }
    }
    Ok(())
}

/// `States.JsonMerge`: two objects (no literal is one), and a shallow merge.
fn check_json_merge(args: &Literals<'_>) -> Result<(), String> {
    let f = args.0.function;
    for i in 0..2 {
        if let Some(v) = args.lit(i) {
            return Err(format!(
                "{f}: argument {} must be an object, got {}",
                i + 1,
                kind(&v)
            ));
        }
    }
    match args.lit(2) {
        None | Some(Value::Bool(false)) => Ok(()),
        Some(Value::Bool(true)) => Err(format!(
            "{f}: only shallow merging is supported; the third argument must be false"
        )),
        Some(v) => Err(format!(
            "{f}: the third argument must be the boolean false, got {}",
            kind(&v)
        )),
    }
}

/// A call's literal arguments, for the checks at load time (a path's value is only known
/// when the state runs).
struct Literals<'a>(&'a Call);

impl Literals<'_> {
    fn lit(&self, i: usize) -> Option<Value> {
        self.0.args.get(i).and_then(Arg::literal)
    }

    fn not_array(&self, i: usize, what: &str) -> Result<(), String> {
        match self.lit(i) {
            Some(v) => Err(format!(
                "{}: {what} must be an array, got {}",
                self.0.function,
                kind(&v)
            )),
            None => Ok(()),
        }
    }

    fn number(&self, i: usize, what: &str) -> Result<Option<i64>, String> {
        match self.lit(i) {
            Some(v) => round(&v, what)
                .map(Some)
                .map_err(|e| format!("{}: {e}", self.0.function)),
            None => Ok(None),
        }
    }

    fn string(&self, i: usize, what: &str) -> Result<(), String> {
        match self.lit(i) {
            Some(Value::String(_)) | None => Ok(()),
            Some(v) => Err(format!(
                "{}: {what} must be a string, got {}",
                self.0.function,
                kind(&v)
            )),
        }
    }
}

/// Rounds a number to the nearest integer, halves up, as Java's `Math.round` (and so Step
/// Functions) does.
fn round(v: &Value, what: &str) -> Result<i64, String> {
    if let Some(i) = v.as_i64() {
        return Ok(i);
    }
    let Some(x) = v.as_f64() else {
        return Err(format!("{what} must be a number, got {}", kind(v)));
    };
    let r = (x + 0.5).floor();
    if !r.is_finite() || r < i64::MIN as f64 || r >= i64::MAX as f64 {
        return Err(format!("{what} `{x}` is out of range"));
    }
    Ok(r as i64)
}

fn int32(v: &Value, what: &str) -> Result<i64, String> {
    let i = round(v, what)?;
    if i < i64::from(i32::MIN) || i > i64::from(i32::MAX) {
        return Err(format!(
            "{what} `{i}` is outside the range -2147483648 to 2147483647"
        ));
    }
    Ok(i)
}

fn array<'v>(v: &'v Value, what: &str) -> Result<&'v Vec<Value>, String> {
    v.as_array()
        .ok_or_else(|| format!("{what} must be an array, got {}", kind(v)))
}

fn string<'v>(v: &'v Value, what: &str) -> Result<&'v str, String> {
    v.as_str()
        .ok_or_else(|| format!("{what} must be a string, got {}", kind(v)))
}

fn bounded<'v>(v: &'v Value, what: &str) -> Result<&'v str, String> {
    let s = string(v, what)?;
    let chars = s.chars().count();
    if chars > MAX_STRING_CHARS {
        return Err(format!(
            "{what} has {chars} characters, over the limit of {MAX_STRING_CHARS}"
        ));
    }
    Ok(s)
}

/// JSON equality where `1` and `1.0` are the same number.
pub(crate) fn json_eq(a: &Value, b: &Value) -> bool {
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => match (x.as_i64(), y.as_i64()) {
            (Some(i), Some(j)) => i == j,
            _ => match (x.as_u64(), y.as_u64()) {
                (Some(i), Some(j)) => i == j,
                _ => x.as_f64() == y.as_f64(),
            },
        },
        (Value::Array(xs), Value::Array(ys)) => {
            xs.len() == ys.len() && xs.iter().zip(ys).all(|(x, y)| json_eq(x, y))
        }
        (Value::Object(xs), Value::Object(ys)) => {
            xs.len() == ys.len()
                && xs
                    .iter()
                    .all(|(k, x)| ys.get(k).is_some_and(|y| json_eq(x, y)))
        }
        _ => a == b,
    }
}

/// How `States.Format` writes a non-string value: JSON for scalars, Java's map and list
/// notation (`{a=1, b=[x, y]}`) for objects and arrays, as Step Functions prints them.
fn format_value(v: &Value) -> String {
    match v {
        Value::String(s) => s.clone(),
        Value::Array(items) => {
            let parts: Vec<String> = items.iter().map(format_value).collect();
            format!("[{}]", parts.join(", "))
        }
        Value::Object(map) => {
            let parts: Vec<String> = map
                .iter()
                .map(|(k, v)| format!("{k}={}", format_value(v)))
                .collect();
            format!("{{{}}}", parts.join(", "))
        }
        other => other.to_string(),
    }
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn run(
    f: Function,
    mut args: Vec<Value>,
    template: Option<&[Piece]>,
    random: &RandomSource,
) -> Result<Value, String> {
    use Function::*;
    Ok(match f {
        Format => states_format(&mut args, template)?,
        StringToJson => {
            let text = string(&args[0], "the argument")?;
            serde_json::from_str(text).map_err(|e| format!("the string is not valid JSON: {e}"))?
        }
        JsonToString => Value::String(args[0].to_string()),
        Array => Value::Array(args),
        ArrayPartition => array_partition(&args)?,
        ArrayContains => {
            let items = array(&args[0], "the first argument")?;
            Value::Bool(items.iter().any(|item| json_eq(item, &args[1])))
        }
        ArrayRange => array_range(&args)?,
        ArrayGetItem => array_get_item(&args)?,
        ArrayLength => Value::from(array(&args[0], "the argument")?.len()),
        ArrayUnique => array_unique(&args)?,
        Base64Encode => {
            let text = bounded(&args[0], "the string to encode")?;
            Value::String(base64::engine::general_purpose::STANDARD.encode(text))
        }
        Base64Decode => base64_decode(&args)?,
        Hash => hash(&args)?,
        JsonMerge => json_merge(args)?,
        MathRandom => math_random(&args, random)?,
        MathAdd => {
            let a = int32(&args[0], "the first argument")?;
            let b = int32(&args[1], "the second argument")?;
            Value::from(a + b)
        }
        StringSplit => string_split(&args)?,
        Uuid => Value::String(random.uuid_v4()),
    })
}

/// `States.Format`: the template's `{}` filled with the values after it.
fn states_format(args: &mut Vec<Value>, template: Option<&[Piece]>) -> Result<Value, String> {
    let rest = args.split_off(1);
    let pieces = match template {
        Some(pieces) => pieces.to_vec(),
        None => {
            let text = string(&args[0], "the template (first argument)")?;
            let mut pieces = Vec::new();
            for (i, part) in text.split("{}").enumerate() {
                if i > 0 {
                    pieces.push(Piece::Slot);
                }
                pieces.push(Piece::Text(part.to_owned()));
            }
            pieces
        }
    };
    let slots = pieces.iter().filter(|p| **p == Piece::Slot).count();
    if slots != rest.len() {
        return Err(format!(
            "the template has {slots} `{{}}` but {} value(s) follow it",
            rest.len()
        ));
    }
    let mut values = rest.iter();
    let mut out = String::new();
    for piece in &pieces {
        match piece {
            Piece::Text(t) => out.push_str(t),
            Piece::Slot => out.push_str(&format_value(values.next().unwrap_or(&Value::Null))),
        }
    }
    Ok(Value::String(out))
}

/// `States.ArrayPartition`.
fn array_partition(args: &[Value]) -> Result<Value, String> {
    let items = array(&args[0], "the first argument")?;
    let size = round(&args[1], "the chunk size")?;
    if size <= 0 {
        return Err(format!(
            "the chunk size must be a positive integer, got {size}"
        ));
    }
    let size = usize::try_from(size).unwrap_or(usize::MAX);
    Ok(Value::Array(
        items
            .chunks(size)
            .map(|chunk| Value::Array(chunk.to_vec()))
            .collect(),
    ))
}

/// `States.ArrayRange`: at most `MAX_RANGE_ITEMS` items.
fn array_range(args: &[Value]) -> Result<Value, String> {
    let first = i128::from(round(&args[0], "the first element")?);
    let last = i128::from(round(&args[1], "the last element")?);
    let step = i128::from(round(&args[2], "the step")?);
    if step == 0 {
        return Err("the step must not be zero".into());
    }
    let count = if (step > 0 && first <= last) || (step < 0 && first >= last) {
        (last - first) / step + 1
    } else {
        0
    };
    if count > MAX_RANGE_ITEMS {
        return Err(format!(
            "the range has {count} items, over the limit of {MAX_RANGE_ITEMS}"
        ));
    }
    Ok(Value::Array(
        (0..count)
            .map(|k| Value::from((first + k * step) as i64))
            .collect(),
    ))
}

/// `States.ArrayGetItem`.
fn array_get_item(args: &[Value]) -> Result<Value, String> {
    let items = array(&args[0], "the first argument")?;
    let index = round(&args[1], "the index")?;
    usize::try_from(index)
        .ok()
        .and_then(|i| items.get(i))
        .cloned()
        .ok_or_else(|| {
            format!(
                "the index {index} is out of bounds for an array of {} item(s)",
                items.len()
            )
        })
}

/// `States.ArrayUnique`: the first of equal items kept, in order.
fn array_unique(args: &[Value]) -> Result<Value, String> {
    let items = array(&args[0], "the argument")?;
    let mut unique: Vec<Value> = Vec::with_capacity(items.len());
    for item in items {
        if !unique.iter().any(|u| json_eq(u, item)) {
            unique.push(item.clone());
        }
    }
    Ok(Value::Array(unique))
}

/// `States.Base64Decode`: the decoded bytes as UTF-8 text.
fn base64_decode(args: &[Value]) -> Result<Value, String> {
    let text = bounded(&args[0], "the string to decode")?;
    let bytes = base64::engine::general_purpose::STANDARD
        .decode(text)
        .map_err(|e| format!("the string is not valid base64: {e}"))?;
    Ok(Value::String(String::from_utf8(bytes).map_err(|_| {
        "the decoded data is not UTF-8 text".to_owned()
    })?))
}

/// `States.Hash`: the data's digest in lowercase hex.
fn hash(args: &[Value]) -> Result<Value, String> {
    use sha2::Digest as _;
    let data = bounded(&args[0], "the data")?.as_bytes();
    let algorithm = string(&args[1], "the algorithm")?;
    Ok(Value::String(match algorithm {
        "MD5" => hex(&md5::Md5::digest(data)),
        "SHA-1" => hex(&sha1::Sha1::digest(data)),
        "SHA-256" => hex(&sha2::Sha256::digest(data)),
        "SHA-384" => hex(&sha2::Sha384::digest(data)),
        "SHA-512" => hex(&sha2::Sha512::digest(data)),
        other => {
            return Err(format!(
                "unknown algorithm `{other}`, expected one of {}",
                HASH_ALGORITHMS.join(", ")
            ))
        }
    }))
}

/// `States.JsonMerge`, shallow only.
fn json_merge(mut args: Vec<Value>) -> Result<Value, String> {
    match &args[2] {
        Value::Bool(false) => {}
        Value::Bool(true) => {
            return Err(
                "only shallow merging is supported; the third argument must be false".into(),
            )
        }
        other => {
            return Err(format!(
                "the third argument must be the boolean false, got {}",
                kind(other)
            ))
        }
    }
    let second = args.swap_remove(1);
    let first = args.swap_remove(0);
    Ok(match (first, second) {
        (Value::Object(mut a), Value::Object(b)) => {
            a.extend(b);
            Value::Object(a)
        }
        (a, b) => {
            let bad = if a.is_object() { (2, b) } else { (1, a) };
            return Err(format!(
                "argument {} must be an object, got {}",
                bad.0,
                kind(&bad.1)
            ));
        }
    })
}

/// `States.MathRandom`: in `[start, end)`, from the seed when one is given.
fn math_random(args: &[Value], random: &RandomSource) -> Result<Value, String> {
    let start = int32(&args[0], "the start")?;
    let end = int32(&args[1], "the end")?;
    if start >= end {
        return Err(format!(
            "the start ({start}) must be less than the end ({end})"
        ));
    }
    let span = (end - start) as u64;
    let draw = match args.get(2) {
        Some(seed) => {
            let seed = round(seed, "the seed")?;
            RandomSource::seeded(seed as u64).below(span)
        }
        None => random.below(span),
    };
    Ok(Value::from(start + draw as i64))
}

/// `States.StringSplit`: on any of the delimiter characters, empty parts dropped.
fn string_split(args: &[Value]) -> Result<Value, String> {
    let text = string(&args[0], "the string")?;
    let delimiters = string(&args[1], "the delimiters")?;
    if delimiters.is_empty() {
        return Err("the delimiters must not be empty".into());
    }
    Ok(Value::Array(
        text.split(|c| delimiters.contains(c))
            .filter(|part| !part.is_empty())
            .map(|part| Value::String(part.to_owned()))
            .collect(),
    ))
}
