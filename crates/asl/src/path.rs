//! JSONPath as Step Functions evaluates it (Jayway semantics), and reference paths.
//!
//! Supported: `$` (the input) and `$$` (the context object), dotted names (`$.a.b`),
//! bracketed names (`$['a b']`, `$.abc.['def ghi']`), indexes including negative ones
//! (`$.a[-1]` is the last element), wildcards (`.*`, `[*]`), slices (`[1:3]`, `[-2:]`),
//! unions (`[0,2]`, `['a','b']`) and deep scan (`$..name`). Filter expressions (`[?(...)]`)
//! and functions (`.length()`) are refused at load time with a clear error.
//!
//! A path is *definite* when it can only name one node (names and indexes only). A definite
//! path that matches nothing is "not found"; an indefinite one always yields an array (maybe
//! empty), which is what Jayway, and so Step Functions, returns.

use std::fmt;

use serde_json::{Map, Value};

use crate::error::LoadError;

/// Which document a path reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Root {
    /// `$`: the state's (effective) input.
    Input,
    /// `$$`: the context object.
    Context,
}

#[derive(Debug, Clone, PartialEq)]
enum Selector {
    Name(String),
    Index(i64),
    Wildcard,
    Slice(Option<i64>, Option<i64>),
    Names(Vec<String>),
    Indexes(Vec<i64>),
}

#[derive(Debug, Clone, PartialEq)]
enum Step {
    Child(Selector),
    Descendant(Selector),
}

/// A parsed JSONPath. Parse once with [`Path::parse_at`], apply many times.
#[derive(Debug, Clone, PartialEq)]
pub struct Path {
    text: String,
    root: Root,
    steps: Vec<Step>,
}

impl fmt::Display for Path {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.text)
    }
}

impl Path {
    /// Parses `text`; `location` names where it was found, for the error.
    pub fn parse_at(text: &str, location: &str) -> Result<Path, LoadError> {
        Parser::new(text)
            .path()
            .map_err(|reason| LoadError::InvalidJsonPath {
                location: location.to_owned(),
                path: text.to_owned(),
                reason,
            })
    }

    /// Parses `text` outside any definition (the location is left empty).
    pub fn parse(text: &str) -> Result<Path, LoadError> {
        Path::parse_at(text, "")
    }

    /// The path as written.
    pub fn text(&self) -> &str {
        &self.text
    }

    /// Whether it reads the input or the context object.
    pub fn root(&self) -> Root {
        self.root
    }

    /// Whether the path can only name a single node (no wildcard, slice, union or deep scan).
    pub fn is_definite(&self) -> bool {
        self.steps.iter().all(|step| {
            matches!(
                step,
                Step::Child(Selector::Name(_)) | Step::Child(Selector::Index(_))
            )
        })
    }

    /// The normalized form AWS prints in errors: `$['a'][0]`.
    pub fn normalized(&self) -> String {
        let mut out = String::from(match self.root {
            Root::Input => "$",
            Root::Context => "$$",
        });
        for step in &self.steps {
            let selector = match step {
                Step::Child(s) => s,
                Step::Descendant(s) => {
                    out.push_str("..");
                    s
                }
            };
            match selector {
                Selector::Name(name) => out.push_str(&format!("['{name}']")),
                Selector::Index(i) => out.push_str(&format!("[{i}]")),
                Selector::Wildcard => out.push_str("[*]"),
                Selector::Slice(a, b) => out.push_str(&format!(
                    "[{}:{}]",
                    a.map(|v| v.to_string()).unwrap_or_default(),
                    b.map(|v| v.to_string()).unwrap_or_default()
                )),
                Selector::Names(names) => {
                    let quoted: Vec<String> = names.iter().map(|n| format!("'{n}'")).collect();
                    out.push_str(&format!("[{}]", quoted.join(",")));
                }
                Selector::Indexes(indexes) => {
                    let items: Vec<String> = indexes.iter().map(|i| i.to_string()).collect();
                    out.push_str(&format!("[{}]", items.join(",")));
                }
            }
        }
        out
    }

    /// Applies the path to `input` (for `$`) or `context` (for `$$`).
    ///
    /// A definite path yields the node it names, or `None` when there is none. An
    /// indefinite path always yields an array of the matches, in document order.
    pub fn select(&self, input: &Value, context: &Value) -> Option<Value> {
        let root = match self.root {
            Root::Input => input,
            Root::Context => context,
        };
        let mut current = vec![root];
        for step in &self.steps {
            let mut next = Vec::new();
            for node in current {
                match step {
                    Step::Child(selector) => apply(selector, node, &mut next),
                    Step::Descendant(selector) => descend(selector, node, &mut next),
                }
            }
            current = next;
        }
        if self.is_definite() {
            current.first().map(|v| (*v).clone())
        } else {
            Some(Value::Array(current.into_iter().cloned().collect()))
        }
    }
}

fn index_of(i: i64, len: usize) -> Option<usize> {
    let len = i64::try_from(len).ok()?;
    let resolved = if i < 0 { len + i } else { i };
    (0..len).contains(&resolved).then_some(resolved as usize)
}

fn apply<'v>(selector: &Selector, node: &'v Value, out: &mut Vec<&'v Value>) {
    match (selector, node) {
        (Selector::Name(name), Value::Object(map)) => out.extend(map.get(name)),
        (Selector::Names(names), Value::Object(map)) => {
            out.extend(names.iter().filter_map(|n| map.get(n)))
        }
        (Selector::Index(i), Value::Array(items)) => {
            out.extend(index_of(*i, items.len()).map(|k| &items[k]))
        }
        (Selector::Indexes(indexes), Value::Array(items)) => out.extend(
            indexes
                .iter()
                .filter_map(|i| index_of(*i, items.len()).map(|k| &items[k])),
        ),
        (Selector::Wildcard, Value::Object(map)) => out.extend(map.values()),
        (Selector::Wildcard, Value::Array(items)) => out.extend(items.iter()),
        (Selector::Slice(start, end), Value::Array(items)) => {
            let len = items.len() as i64;
            let clamp = |v: i64| -> usize {
                let v = if v < 0 { len + v } else { v };
                v.clamp(0, len) as usize
            };
            let from = start.map(clamp).unwrap_or(0);
            let to = end.map(clamp).unwrap_or(items.len());
            if from < to {
                out.extend(items[from..to].iter());
            }
        }
        _ => {}
    }
}

fn descend<'v>(selector: &Selector, node: &'v Value, out: &mut Vec<&'v Value>) {
    apply(selector, node, out);
    match node {
        Value::Object(map) => map.values().for_each(|child| descend(selector, child, out)),
        Value::Array(items) => items.iter().for_each(|child| descend(selector, child, out)),
        _ => {}
    }
}

/// One step of a reference path.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RefStep {
    /// An object member.
    Name(String),
    /// An array element (negative counts from the end).
    Index(i64),
}

/// A reference path: a path that names exactly one node (dot and bracket notation only; no
/// `@ .. , : ? *`, no functions). ResultPath, ItemsPath and Choice variables use these.
#[derive(Debug, Clone, PartialEq)]
pub struct ReferencePath {
    path: Path,
    steps: Vec<RefStep>,
}

impl fmt::Display for ReferencePath {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.path.text)
    }
}

impl ReferencePath {
    /// Parses `text` and checks it is a reference path; `location` names where it was found.
    pub fn parse_at(text: &str, location: &str) -> Result<ReferencePath, LoadError> {
        let refuse = |reason: &str| LoadError::InvalidReferencePath {
            location: location.to_owned(),
            path: text.to_owned(),
            reason: reason.to_owned(),
        };
        let path = Path::parse_at(text, location).map_err(|e| match e {
            LoadError::InvalidJsonPath { reason, .. } => refuse(&reason),
            other => other,
        })?;
        let mut steps = Vec::with_capacity(path.steps.len());
        for step in &path.steps {
            match step {
                Step::Child(Selector::Name(n)) => steps.push(RefStep::Name(n.clone())),
                Step::Child(Selector::Index(i)) => steps.push(RefStep::Index(*i)),
                Step::Descendant(_) => return Err(refuse("deep scan `..` names many nodes")),
                Step::Child(Selector::Wildcard) => {
                    return Err(refuse("a wildcard `*` names many nodes"))
                }
                Step::Child(Selector::Slice(..)) => {
                    return Err(refuse("a slice `:` names many nodes"))
                }
                Step::Child(Selector::Names(_) | Selector::Indexes(_)) => {
                    return Err(refuse("a union `,` names many nodes"))
                }
            }
        }
        Ok(ReferencePath { path, steps })
    }

    /// Parses `text` outside any definition.
    pub fn parse(text: &str) -> Result<ReferencePath, LoadError> {
        ReferencePath::parse_at(text, "")
    }

    /// The path as written.
    pub fn text(&self) -> &str {
        &self.path.text
    }

    /// Whether it reads the input or the context object.
    pub fn root(&self) -> Root {
        self.path.root
    }

    /// The steps after the root.
    pub fn steps(&self) -> &[RefStep] {
        &self.steps
    }

    /// The normalized form (`$['a'][0]`).
    pub fn normalized(&self) -> String {
        self.path.normalized()
    }

    /// The node the path names, if any.
    pub fn get<'v>(&self, input: &'v Value, context: &'v Value) -> Option<&'v Value> {
        let mut node = match self.path.root {
            Root::Input => input,
            Root::Context => context,
        };
        for step in &self.steps {
            node = match (step, node) {
                (RefStep::Name(n), Value::Object(map)) => map.get(n)?,
                (RefStep::Index(i), Value::Array(items)) => &items[index_of(*i, items.len())?],
                _ => return None,
            };
        }
        Some(node)
    }

    /// Places `value` at the path inside `input`, creating missing object members on the
    /// way (`$.a.b` on `{}` gives `{"a": {"b": value}}`). `$` replaces the whole input.
    ///
    /// Fails (with the reason) when a node on the way exists but is not an object (for a
    /// name) or an array holding the index (for an index).
    pub fn set(&self, input: Value, value: Value) -> Result<Value, String> {
        fn place(node: Value, steps: &[RefStep], value: Value, at: &str) -> Result<Value, String> {
            let Some((first, rest)) = steps.split_first() else {
                return Ok(value);
            };
            match (first, node) {
                (RefStep::Name(name), Value::Object(mut map)) => {
                    let here = format!("{at}['{name}']");
                    let child = map
                        .remove(name)
                        .unwrap_or_else(|| Value::Object(Map::new()));
                    let placed = place(child, rest, value, &here)?;
                    map.insert(name.clone(), placed);
                    Ok(Value::Object(map))
                }
                (RefStep::Index(i), Value::Array(mut items)) => {
                    let Some(k) = index_of(*i, items.len()) else {
                        return Err(format!("{at} has no element {i}"));
                    };
                    let child = std::mem::take(&mut items[k]);
                    items[k] = place(child, rest, value, &format!("{at}[{i}]"))?;
                    Ok(Value::Array(items))
                }
                (RefStep::Name(_), other) => {
                    Err(format!("{at} is {}, not an object", kind(&other)))
                }
                (RefStep::Index(_), other) => {
                    Err(format!("{at} is {}, not an array", kind(&other)))
                }
            }
        }
        let root = match self.path.root {
            Root::Input => "$",
            Root::Context => "$$",
        };
        place(input, &self.steps, value, root)
    }
}

/// The JSON type of a value, for messages.
pub(crate) fn kind(value: &Value) -> &'static str {
    match value {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

/// Characters that end a dotted name.
fn ends_name(c: char) -> bool {
    c.is_whitespace() || ".[]()'\",*?@".contains(c)
}

struct Parser<'a> {
    text: &'a str,
    chars: Vec<char>,
    pos: usize,
}

impl<'a> Parser<'a> {
    fn new(text: &'a str) -> Self {
        Parser {
            text,
            chars: text.chars().collect(),
            pos: 0,
        }
    }

    fn peek(&self) -> Option<char> {
        self.chars.get(self.pos).copied()
    }

    fn peek_at(&self, offset: usize) -> Option<char> {
        self.chars.get(self.pos + offset).copied()
    }

    fn skip_ws(&mut self) {
        while self.peek().is_some_and(char::is_whitespace) {
            self.pos += 1;
        }
    }

    fn expect(&mut self, c: char) -> Result<(), String> {
        match self.peek() {
            Some(found) if found == c => {
                self.pos += 1;
                Ok(())
            }
            Some(found) => Err(format!(
                "expected `{c}` at character {} but found `{found}`",
                self.pos + 1
            )),
            None => Err(format!("expected `{c}` but the path ended")),
        }
    }

    fn path(mut self) -> Result<Path, String> {
        if self.peek() != Some('$') {
            return Err("a path must start with `$`".into());
        }
        self.pos += 1;
        let root = if self.peek() == Some('$') {
            self.pos += 1;
            Root::Context
        } else {
            Root::Input
        };
        let mut steps = Vec::new();
        while let Some(c) = self.peek() {
            match c {
                '.' if self.peek_at(1) == Some('.') => {
                    self.pos += 2;
                    let selector = match self.peek() {
                        Some('[') => self.bracket()?,
                        Some('*') => {
                            self.pos += 1;
                            Selector::Wildcard
                        }
                        _ => Selector::Name(self.dotted_name()?),
                    };
                    steps.push(Step::Descendant(selector));
                }
                '.' => {
                    self.pos += 1;
                    let selector = match self.peek() {
                        Some('[') => self.bracket()?,
                        Some('*') => {
                            self.pos += 1;
                            Selector::Wildcard
                        }
                        _ => Selector::Name(self.dotted_name()?),
                    };
                    steps.push(Step::Child(selector));
                }
                '[' => steps.push(Step::Child(self.bracket()?)),
                other => {
                    return Err(if self.pos == 1 && root == Root::Input {
                        format!("unexpected `{other}` after `$` (variables are not supported; use `$.` or `$[`)")
                    } else {
                        format!("unexpected `{other}` at character {}", self.pos + 1)
                    })
                }
            }
        }
        Ok(Path {
            text: self.text.to_owned(),
            root,
            steps,
        })
    }

    fn dotted_name(&mut self) -> Result<String, String> {
        let start = self.pos;
        while self.peek().is_some_and(|c| !ends_name(c)) {
            self.pos += 1;
        }
        if self.pos == start {
            return Err(match self.peek() {
                None => "the path ends with `.`".into(),
                Some(c) => format!(
                    "expected a field name at character {} but found `{c}` (use `['...']` for names with special characters)",
                    self.pos + 1
                ),
            });
        }
        let name: String = self.chars[start..self.pos].iter().collect();
        if self.peek() == Some('(') {
            return Err(format!(
                "functions such as `{name}()` are not supported in Step Functions paths"
            ));
        }
        Ok(name)
    }

    fn bracket(&mut self) -> Result<Selector, String> {
        self.expect('[')?;
        self.skip_ws();
        let selector = match self.peek() {
            Some('*') => {
                self.pos += 1;
                Selector::Wildcard
            }
            Some('\'' | '"') => {
                let mut names = vec![self.quoted()?];
                self.skip_ws();
                while self.peek() == Some(',') {
                    self.pos += 1;
                    self.skip_ws();
                    names.push(self.quoted()?);
                    self.skip_ws();
                }
                if names.len() == 1 {
                    Selector::Name(names.remove(0))
                } else {
                    Selector::Names(names)
                }
            }
            Some('?') => return Err("filter expressions `[?(...)]` are not supported".into()),
            Some('(') => return Err("script expressions `[(...)]` are not supported".into()),
            Some(c) if c == '-' || c == ':' || c.is_ascii_digit() => self.numeric()?,
            Some(c) => {
                return Err(format!(
                    "unexpected `{c}` inside `[...]` at character {}",
                    self.pos + 1
                ))
            }
            None => return Err("unclosed `[`".into()),
        };
        self.skip_ws();
        self.expect(']')?;
        Ok(selector)
    }

    fn quoted(&mut self) -> Result<String, String> {
        let Some(quote) = self.peek() else {
            return Err("expected a quoted name".into());
        };
        self.pos += 1;
        let mut name = String::new();
        loop {
            match self.peek() {
                None => return Err("unclosed quoted name".into()),
                Some('\\') => {
                    let Some(escaped) = self.peek_at(1) else {
                        return Err("the path ends inside an escape".into());
                    };
                    name.push(escaped);
                    self.pos += 2;
                }
                Some(c) if c == quote => {
                    self.pos += 1;
                    return Ok(name);
                }
                Some(c) => {
                    name.push(c);
                    self.pos += 1;
                }
            }
        }
    }

    fn integer(&mut self) -> Result<Option<i64>, String> {
        let start = self.pos;
        if self.peek() == Some('-') {
            self.pos += 1;
        }
        while self.peek().is_some_and(|c| c.is_ascii_digit()) {
            self.pos += 1;
        }
        let digits: String = self.chars[start..self.pos].iter().collect();
        match digits.as_str() {
            "" => Ok(None),
            "-" => Err(format!(
                "expected digits after `-` at character {}",
                self.pos + 1
            )),
            _ => digits
                .parse::<i64>()
                .map(Some)
                .map_err(|_| format!("index `{digits}` is out of range")),
        }
    }

    fn numeric(&mut self) -> Result<Selector, String> {
        let first = self.integer()?;
        self.skip_ws();
        match self.peek() {
            Some(':') => {
                self.pos += 1;
                self.skip_ws();
                let end = self.integer()?;
                self.skip_ws();
                if self.peek() == Some(':') {
                    return Err("slice steps `[a:b:step]` are not supported".into());
                }
                Ok(Selector::Slice(first, end))
            }
            Some(',') => {
                let mut indexes = vec![first.ok_or("expected an index before `,`")?];
                while self.peek() == Some(',') {
                    self.pos += 1;
                    self.skip_ws();
                    indexes.push(self.integer()?.ok_or("expected an index after `,`")?);
                    self.skip_ws();
                }
                Ok(Selector::Indexes(indexes))
            }
            _ => Ok(Selector::Index(first.ok_or("expected an index")?)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn sel(path: &str, input: &Value) -> Option<Value> {
        Path::parse(path).unwrap().select(input, &Value::Null)
    }

    fn reference_doc() -> Value {
        // The developer guide's reference path example.
        json!({"foo": 123, "bar": ["a", "b", "c"], "car": {"cdr": true}})
    }

    #[test]
    fn the_developer_guide_reference_paths_return_the_documented_nodes() {
        let doc = reference_doc();
        assert_eq!(sel("$.foo", &doc), Some(json!(123)));
        assert_eq!(sel("$.bar", &doc), Some(json!(["a", "b", "c"])));
        assert_eq!(sel("$.car.cdr", &doc), Some(json!(true)));
        for text in ["$.foo", "$.bar", "$.car.cdr"] {
            assert!(ReferencePath::parse(text).is_ok(), "{text}");
        }
    }

    #[test]
    fn a_slice_yields_the_selection_the_guide_shows() {
        assert_eq!(
            sel("$.a[0:2]", &json!({"a": [1, 2, 3, 4]})),
            Some(json!([1, 2]))
        );
    }

    #[test]
    fn dollar_alone_is_the_whole_input() {
        let doc = reference_doc();
        assert_eq!(sel("$", &doc), Some(doc.clone()));
    }

    #[test]
    fn bracket_names_take_characters_dots_cannot() {
        let doc = json!({"abc": {"def ghi": 1, "x.y": 2, "it's": 3}});
        assert_eq!(sel("$.abc.['def ghi']", &doc), Some(json!(1)));
        assert_eq!(sel("$['abc']['x.y']", &doc), Some(json!(2)));
        assert_eq!(sel("$.abc[\"it's\"]", &doc), Some(json!(3)));
        assert_eq!(sel("$.abc['it\\'s']", &doc), Some(json!(3)));
    }

    #[test]
    fn indexes_count_from_the_end_when_negative() {
        let doc = json!({"a": [10, 20, 30]});
        assert_eq!(sel("$.a[0]", &doc), Some(json!(10)));
        assert_eq!(sel("$.a[-1]", &doc), Some(json!(30)));
        assert_eq!(sel("$.a[3]", &doc), None);
        assert_eq!(sel("$.a[-4]", &doc), None);
        assert_eq!(sel("$.a[-2:]", &doc), Some(json!([20, 30])));
        assert_eq!(sel("$.a[:1]", &doc), Some(json!([10])));
        assert_eq!(sel("$.a[0,2]", &doc), Some(json!([10, 30])));
    }

    #[test]
    fn wildcards_and_deep_scan_collect_matches_in_document_order() {
        let doc = json!({"items": [{"id": 1, "sub": {"id": 3}}, {"id": 2}, {"other": 0}]});
        assert_eq!(sel("$.items[*].id", &doc), Some(json!([1, 2])));
        assert_eq!(sel("$.items.*.id", &doc), Some(json!([1, 2])));
        assert_eq!(sel("$..id", &doc), Some(json!([1, 3, 2])));
        assert_eq!(sel("$.nothing[*]", &doc), Some(json!([])));
        assert_eq!(
            sel("$['items','x']", &doc)
                .unwrap()
                .as_array()
                .unwrap()
                .len(),
            1
        );
    }

    #[test]
    fn a_definite_path_that_matches_nothing_is_not_found() {
        let doc = reference_doc();
        assert_eq!(sel("$.nope", &doc), None);
        assert_eq!(sel("$.foo.bar", &doc), None);
        assert_eq!(sel("$.bar.x", &doc), None);
        assert_eq!(sel("$.car[0]", &doc), None);
    }

    #[test]
    fn double_dollar_reads_the_context_object() {
        let ctx = json!({"Execution": {"Id": "arn:x"}});
        let p = Path::parse("$$.Execution.Id").unwrap();
        assert_eq!(p.root(), Root::Context);
        assert_eq!(p.select(&json!({}), &ctx), Some(json!("arn:x")));
    }

    #[test]
    fn the_normalized_form_is_the_one_aws_prints() {
        let p = Path::parse("$.a.b[0]").unwrap();
        assert_eq!(p.normalized(), "$['a']['b'][0]");
        assert_eq!(Path::parse("$..x[*]").unwrap().normalized(), "$..['x'][*]");
    }

    #[test]
    fn malformed_and_unsupported_paths_are_refused_with_the_reason() {
        for (text, needle) in [
            ("", "must start with `$`"),
            ("a.b", "must start with `$`"),
            ("$.", "ends with `.`"),
            ("$a", "variables are not supported"),
            ("$.a[", "unclosed"),
            ("$.a['b'", "expected `]`"),
            ("$.a[?(@.b)]", "filter expressions"),
            ("$.a.length()", "functions such as"),
            ("$.a[0:4:2]", "slice steps"),
            ("$.a[x]", "unexpected `x`"),
            ("$.a[-]", "expected digits"),
            ("$.a[99999999999999999999]", "out of range"),
        ] {
            let err = Path::parse_at(text, "f.$").unwrap_err();
            assert_eq!(err.name(), "InvalidJsonPath");
            let msg = err.to_string();
            assert!(msg.contains(needle), "{text}: {msg}");
            assert!(msg.contains("`f.$`"), "{msg}");
        }
    }

    #[test]
    fn reference_paths_refuse_anything_that_names_many_nodes() {
        for text in [
            "$.a[*]",
            "$..a",
            "$.a[0:1]",
            "$.a[0,1]",
            "$.*",
            "$['a','b']",
        ] {
            let err = ReferencePath::parse(text).unwrap_err();
            assert_eq!(err.name(), "InvalidReferencePath", "{text}");
        }
        assert_eq!(
            ReferencePath::parse("$.a['b c'][2]").unwrap().steps(),
            &[
                RefStep::Name("a".into()),
                RefStep::Name("b c".into()),
                RefStep::Index(2)
            ]
        );
    }

    #[test]
    fn setting_creates_missing_members_and_overwrites_existing_ones() {
        let input = json!({"comment": "c", "strings": {"s1": "foo"}});
        let set = |p: &str, v: Value| ReferencePath::parse(p).unwrap().set(input.clone(), v);
        assert_eq!(
            set("$.strings.lambdaresult", json!("hi")).unwrap(),
            json!({"comment": "c", "strings": {"s1": "foo", "lambdaresult": "hi"}})
        );
        assert_eq!(
            set("$.comment", json!("new")).unwrap(),
            json!({"comment": "new", "strings": {"s1": "foo"}})
        );
        assert_eq!(
            set("$.x.y.z", json!(1)).unwrap(),
            json!({"comment": "c", "strings": {"s1": "foo"}, "x": {"y": {"z": 1}}})
        );
        assert_eq!(set("$", json!(7)).unwrap(), json!(7));
        let err = set("$.comment.deeper", json!(1)).unwrap_err();
        assert!(err.contains("$['comment'] is a string"), "{err}");
        let err = ReferencePath::parse("$.a")
            .unwrap()
            .set(json!("text"), json!(1))
            .unwrap_err();
        assert!(err.contains("not an object"), "{err}");
        assert_eq!(
            ReferencePath::parse("$.l[-1]")
                .unwrap()
                .set(json!({"l": [1, 2]}), json!(9))
                .unwrap(),
            json!({"l": [1, 9]})
        );
        assert!(ReferencePath::parse("$.l[5]")
            .unwrap()
            .set(json!({"l": [1]}), json!(9))
            .is_err());
    }
}
