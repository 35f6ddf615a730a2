//! Choice rules: compiled at load, evaluated against a Choice state's effective input.
//!
//! Semantics follow the Amazon States Language: a comparison whose operand has another type
//! is false (no coercion); string order is Java's `compareTo` (UTF-16 code units); numbers
//! compare as numbers (`1` equals `1.0`); timestamps compare as instants; `StringMatches`
//! knows only `*` (escape `\*` and `\\`). A `Variable` (or a `...Path` operand) that selects
//! nothing is a `States.Runtime` error, except for `IsPresent`; `And`/`Or` stop at the first
//! deciding rule, so `IsPresent` can guard a comparison.

use std::cmp::Ordering;

use lb_asl::ReferencePath;
use serde_json::{Map, Number, Value};
use time::OffsetDateTime;

use crate::error::LoadError;
use crate::runtime::Failure;
use crate::timestamp;

/// One compiled rule (top-level rules carry their `Next` beside it).
#[derive(Debug, Clone)]
pub(crate) enum Rule {
    And(Vec<Rule>),
    Or(Vec<Rule>),
    Not(Box<Rule>),
    Compare { variable: ReferencePath, test: Test },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Order {
    Eq,
    Lt,
    Gt,
    Le,
    Ge,
}

impl Order {
    fn holds(self, ordering: Ordering) -> bool {
        match self {
            Order::Eq => ordering == Ordering::Equal,
            Order::Lt => ordering == Ordering::Less,
            Order::Gt => ordering == Ordering::Greater,
            Order::Le => ordering != Ordering::Greater,
            Order::Ge => ordering != Ordering::Less,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Kind {
    String,
    Numeric,
    Boolean,
    Timestamp,
}

#[derive(Debug, Clone)]
pub(crate) enum Operand {
    Literal(Value),
    Path(ReferencePath),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum TypeTest {
    Present,
    Null,
    String,
    Numeric,
    Boolean,
    Timestamp,
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Glob {
    Char(char),
    Star,
}

/// What a comparison checks.
#[derive(Debug, Clone)]
pub(crate) enum Test {
    Compare(Kind, Order, Operand),
    Type(TypeTest, bool),
    Matches(Vec<Glob>),
}

const ORDERS: [(&str, Order); 5] = [
    ("Equals", Order::Eq),
    ("LessThan", Order::Lt),
    ("GreaterThan", Order::Gt),
    ("LessThanEquals", Order::Le),
    ("GreaterThanEquals", Order::Ge),
];

const KINDS: [(&str, Kind); 4] = [
    ("String", Kind::String),
    ("Numeric", Kind::Numeric),
    ("Boolean", Kind::Boolean),
    ("Timestamp", Kind::Timestamp),
];

const TYPE_TESTS: [(&str, TypeTest); 6] = [
    ("IsPresent", TypeTest::Present),
    ("IsNull", TypeTest::Null),
    ("IsString", TypeTest::String),
    ("IsNumeric", TypeTest::Numeric),
    ("IsBoolean", TypeTest::Boolean),
    ("IsTimestamp", TypeTest::Timestamp),
];

/// Reads a comparison operator name: (kind, order, takes a path).
fn comparison_operator(key: &str) -> Option<(Kind, Order, bool)> {
    let (base, path) = match key.strip_suffix("Path") {
        Some(base) => (base, true),
        None => (key, false),
    };
    for (prefix, kind) in KINDS {
        let Some(rest) = base.strip_prefix(prefix) else {
            continue;
        };
        for (suffix, order) in ORDERS {
            // BooleanEquals is the only Boolean comparison.
            if rest == suffix && (kind != Kind::Boolean || order == Order::Eq) {
                return Some((kind, order, path));
            }
        }
    }
    None
}

fn is_operator(key: &str) -> bool {
    comparison_operator(key).is_some()
        || key == "StringMatches"
        || TYPE_TESTS.iter().any(|(name, _)| *name == key)
}

/// Compiles a top-level rule; returns it with its `Next`.
pub(crate) fn compile_top(value: &Value, location: &str) -> Result<(Rule, String), LoadError> {
    let map = value
        .as_object()
        .ok_or_else(|| LoadError::invalid(location, "a choice rule must be an object"))?;
    let next = match map.get("Next") {
        Some(Value::String(next)) => next.clone(),
        Some(_) => {
            return Err(LoadError::invalid(
                format!("{location}.Next"),
                "must be a string",
            ))
        }
        None => {
            return Err(LoadError::invalid(
                location,
                "a top-level choice rule must have a `Next` field",
            ))
        }
    };
    Ok((compile(map, location, true)?, next))
}

/// The rule's fields are choice rule fields (`Next` only at the top), its comment a string.
fn check_fields(map: &Map<String, Value>, location: &str, top: bool) -> Result<(), LoadError> {
    let at = |key: &str| format!("{location}.{key}");
    for key in map.keys() {
        let known = matches!(key.as_str(), "Variable" | "Comment" | "And" | "Or" | "Not")
            || (top && key == "Next")
            || is_operator(key);
        if known {
            continue;
        }
        return Err(match key.as_str() {
            "Next" => LoadError::invalid(
                at(key),
                "a nested choice rule (inside `And`, `Or` or `Not`) must not have `Next`",
            ),
            "Condition" => LoadError::unsupported(
                at(key),
                "JSONata `Condition` rules are not supported; use JSONPath comparisons",
            ),
            _ => LoadError::invalid(at(key), format!("`{key}` is not a choice rule field")),
        });
    }
    if let Some(comment) = map.get("Comment") {
        if !comment.is_string() {
            return Err(LoadError::invalid(at("Comment"), "must be a string"));
        }
    }
    Ok(())
}

fn compile(map: &Map<String, Value>, location: &str, top: bool) -> Result<Rule, LoadError> {
    let at = |key: &str| format!("{location}.{key}");
    check_fields(map, location, top)?;
    let boolean: Vec<&str> = ["And", "Or", "Not"]
        .into_iter()
        .filter(|k| map.contains_key(*k))
        .collect();
    let operators: Vec<&String> = map.keys().filter(|k| is_operator(k)).collect();
    if !boolean.is_empty() {
        if boolean.len() > 1 || map.contains_key("Variable") || !operators.is_empty() {
            return Err(LoadError::invalid(
                location,
                "a rule with `And`, `Or` or `Not` must have exactly that one field besides `Next` and `Comment`",
            ));
        }
        let key = boolean[0];
        let value = &map[key];
        if key == "Not" {
            let inner = value
                .as_object()
                .ok_or_else(|| LoadError::invalid(at(key), "must be a choice rule object"))?;
            return Ok(Rule::Not(Box::new(compile(inner, &at(key), false)?)));
        }
        let items = value
            .as_array()
            .filter(|items| !items.is_empty())
            .ok_or_else(|| LoadError::invalid(at(key), "must be a non-empty array of rules"))?;
        let rules = items
            .iter()
            .enumerate()
            .map(|(i, item)| {
                let here = format!("{}[{i}]", at(key));
                let inner = item
                    .as_object()
                    .ok_or_else(|| LoadError::invalid(&here, "must be a choice rule object"))?;
                compile(inner, &here, false)
            })
            .collect::<Result<Vec<_>, _>>()?;
        return Ok(if key == "And" {
            Rule::And(rules)
        } else {
            Rule::Or(rules)
        });
    }
    let variable = match map.get("Variable") {
        Some(Value::String(text)) => {
            ReferencePath::parse_at(text, "Variable").map_err(|source| LoadError::DataFlow {
                location: location.to_owned(),
                source,
            })?
        }
        Some(_) => return Err(LoadError::invalid(at("Variable"), "must be a string")),
        None => {
            return Err(LoadError::invalid(
                location,
                "a comparison must have a `Variable` field (or use `And`, `Or`, `Not`)",
            ))
        }
    };
    let [operator] = operators.as_slice() else {
        return Err(LoadError::invalid(
            location,
            format!(
                "a comparison must have exactly one operator, found {}",
                operators.len()
            ),
        ));
    };
    let value = &map[operator.as_str()];
    let here = at(operator);
    let test = compile_test(operator, value, &here, location)?;
    Ok(Rule::Compare { variable, test })
}

fn compile_test(
    operator: &str,
    value: &Value,
    here: &str,
    location: &str,
) -> Result<Test, LoadError> {
    if let Some((_, test)) = TYPE_TESTS.iter().find(|(name, _)| *name == operator) {
        let expected = value
            .as_bool()
            .ok_or_else(|| LoadError::invalid(here, "must be true or false"))?;
        return Ok(Test::Type(*test, expected));
    }
    if operator == "StringMatches" {
        let pattern = value
            .as_str()
            .ok_or_else(|| LoadError::invalid(here, "must be a string"))?;
        return Ok(Test::Matches(compile_glob(pattern, here)?));
    }
    let Some((kind, order, path)) = comparison_operator(operator) else {
        return Err(LoadError::invalid(here, "unknown operator"));
    };
    let operand = if path {
        let text = value
            .as_str()
            .ok_or_else(|| LoadError::invalid(here, "must be a reference path string"))?;
        Operand::Path(ReferencePath::parse_at(text, operator).map_err(|source| {
            LoadError::DataFlow {
                location: location.to_owned(),
                source,
            }
        })?)
    } else {
        let ok = match kind {
            Kind::String => value.is_string(),
            Kind::Numeric => value.is_number(),
            Kind::Boolean => value.is_boolean(),
            Kind::Timestamp => value.as_str().and_then(timestamp::parse).is_some(),
        };
        if !ok {
            let wanted = match kind {
                Kind::String => "a string",
                Kind::Numeric => "a number",
                Kind::Boolean => "true or false",
                Kind::Timestamp => {
                    "an RFC 3339 timestamp with uppercase `T` and `Z` (`2016-08-18T17:33:00Z`)"
                }
            };
            return Err(LoadError::invalid(here, format!("must be {wanted}")));
        }
        Operand::Literal(value.clone())
    };
    Ok(Test::Compare(kind, order, operand))
}

fn compile_glob(pattern: &str, here: &str) -> Result<Vec<Glob>, LoadError> {
    let mut out = Vec::with_capacity(pattern.len());
    let mut chars = pattern.chars();
    while let Some(c) = chars.next() {
        match c {
            '*' => out.push(Glob::Star),
            '\\' => match chars.next() {
                Some(escaped @ ('*' | '\\')) => out.push(Glob::Char(escaped)),
                other => {
                    return Err(LoadError::invalid(
                        here,
                        format!(
                            "`\\` must be followed by `*` or `\\`, found {}",
                            other.map_or("the end".to_owned(), |c| format!("`{c}`"))
                        ),
                    ))
                }
            },
            other => out.push(Glob::Char(other)),
        }
    }
    Ok(out)
}

/// Wildcard match (`*` = any run of characters), iterative with one backtrack point.
fn glob_matches(pattern: &[Glob], text: &str) -> bool {
    let text: Vec<char> = text.chars().collect();
    let (mut p, mut t) = (0, 0);
    let mut backtrack: Option<(usize, usize)> = None;
    while t < text.len() {
        match pattern.get(p) {
            Some(Glob::Star) => {
                backtrack = Some((p, t));
                p += 1;
            }
            Some(Glob::Char(c)) if *c == text[t] => {
                p += 1;
                t += 1;
            }
            _ => match backtrack {
                Some((star, at)) => {
                    p = star + 1;
                    t = at + 1;
                    backtrack = Some((star, at + 1));
                }
                None => return false,
            },
        }
    }
    pattern[p..].iter().all(|g| *g == Glob::Star)
}

fn invalid_path(path: &ReferencePath) -> Failure {
    Failure::runtime(format!(
        "Invalid path '{}': The choice state's condition path references an invalid value.",
        path.text()
    ))
}

fn numeric_order(a: &Number, b: &Number) -> Option<Ordering> {
    if let (Some(x), Some(y)) = (a.as_i64(), b.as_i64()) {
        return Some(x.cmp(&y));
    }
    if let (Some(x), Some(y)) = (a.as_u64(), b.as_u64()) {
        return Some(x.cmp(&y));
    }
    a.as_f64()?.partial_cmp(&b.as_f64()?)
}

fn timestamp_of(value: &Value) -> Option<OffsetDateTime> {
    value.as_str().and_then(timestamp::parse)
}

impl Rule {
    /// Evaluates the rule against the effective input and the context object.
    pub(crate) fn evaluate(&self, input: &Value, context: &Value) -> Result<bool, Failure> {
        match self {
            Rule::And(rules) => {
                for rule in rules {
                    if !rule.evaluate(input, context)? {
                        return Ok(false);
                    }
                }
                Ok(true)
            }
            Rule::Or(rules) => {
                for rule in rules {
                    if rule.evaluate(input, context)? {
                        return Ok(true);
                    }
                }
                Ok(false)
            }
            Rule::Not(rule) => Ok(!rule.evaluate(input, context)?),
            Rule::Compare { variable, test } => {
                let found = variable.get(input, context);
                if let Test::Type(TypeTest::Present, expected) = test {
                    return Ok(found.is_some() == *expected);
                }
                let value = found.ok_or_else(|| invalid_path(variable))?;
                test.holds(value, input, context)
            }
        }
    }
}

impl Test {
    fn holds(&self, value: &Value, input: &Value, context: &Value) -> Result<bool, Failure> {
        match self {
            Test::Type(test, expected) => {
                let is = match test {
                    TypeTest::Present => true,
                    TypeTest::Null => value.is_null(),
                    TypeTest::String => value.is_string(),
                    TypeTest::Numeric => value.is_number(),
                    TypeTest::Boolean => value.is_boolean(),
                    TypeTest::Timestamp => timestamp_of(value).is_some(),
                };
                Ok(is == *expected)
            }
            Test::Matches(pattern) => Ok(value.as_str().is_some_and(|s| glob_matches(pattern, s))),
            Test::Compare(kind, order, operand) => {
                let other = match operand {
                    Operand::Literal(v) => v,
                    Operand::Path(path) => {
                        path.get(input, context).ok_or_else(|| invalid_path(path))?
                    }
                };
                let ordering = match kind {
                    Kind::String => match (value, other) {
                        (Value::String(a), Value::String(b)) => {
                            Some(a.encode_utf16().cmp(b.encode_utf16()))
                        }
                        _ => None,
                    },
                    Kind::Numeric => match (value, other) {
                        (Value::Number(a), Value::Number(b)) => numeric_order(a, b),
                        _ => None,
                    },
                    Kind::Boolean => match (value, other) {
                        (Value::Bool(a), Value::Bool(b)) => Some(a.cmp(b)),
                        _ => None,
                    },
                    Kind::Timestamp => match (timestamp_of(value), timestamp_of(other)) {
                        (Some(a), Some(b)) => Some(a.cmp(&b)),
                        _ => None,
                    },
                };
                Ok(ordering.is_some_and(|o| order.holds(o)))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn rule(value: Value) -> Rule {
        compile(value.as_object().unwrap(), "States.C.Choices[0]", false).unwrap()
    }

    fn holds(r: Value, input: Value) -> bool {
        rule(r).evaluate(&input, &Value::Null).unwrap()
    }

    #[test]
    fn every_comparison_operator_is_recognised_with_and_without_path() {
        let mut count = 0;
        for (prefix, _) in KINDS {
            for (suffix, _) in ORDERS {
                let name = format!("{prefix}{suffix}");
                let expected = prefix != "Boolean" || suffix == "Equals";
                assert_eq!(comparison_operator(&name).is_some(), expected, "{name}");
                assert_eq!(
                    comparison_operator(&format!("{name}Path")).is_some(),
                    expected
                );
                count += usize::from(expected) * 2;
            }
        }
        assert_eq!(count, 32);
        assert!(comparison_operator("StringMatchesPath").is_none());
    }

    #[test]
    fn string_comparisons_follow_java_compare_to() {
        let v = json!({"foo": "MyStringABD"});
        assert!(holds(
            json!({"Variable": "$.foo", "StringGreaterThan": "MyStringABC"}),
            v.clone()
        ));
        assert!(!holds(
            json!({"Variable": "$.foo", "StringLessThan": "MyStringABC"}),
            v.clone()
        ));
        assert!(holds(
            json!({"Variable": "$.foo", "StringLessThanEquals": "MyStringABD"}),
            v
        ));
        // UTF-16 order: U+FF61 sorts after U+1F600's surrogate (0xD83D), unlike code points.
        assert!(holds(
            json!({"Variable": "$.a", "StringGreaterThan": "\u{1F600}"}),
            json!({"a": "\u{FF61}"})
        ));
    }

    #[test]
    fn a_type_mismatch_is_false_not_an_error() {
        let v = json!({"n": 1, "s": "1", "b": true});
        assert!(!holds(
            json!({"Variable": "$.s", "NumericEquals": 1}),
            v.clone()
        ));
        assert!(!holds(
            json!({"Variable": "$.n", "StringEquals": "1"}),
            v.clone()
        ));
        assert!(!holds(
            json!({"Variable": "$.n", "BooleanEquals": true}),
            v.clone()
        ));
        assert!(!holds(
            json!({"Variable": "$.s", "TimestampEquals": "2001-01-01T12:00:00Z"}),
            v
        ));
    }

    #[test]
    fn numbers_compare_by_value() {
        let v = json!({"i": 1, "f": 1.0, "big": 18446744073709551615u64, "neg": -3});
        assert!(holds(
            json!({"Variable": "$.i", "NumericEquals": 1.0}),
            v.clone()
        ));
        assert!(holds(
            json!({"Variable": "$.f", "NumericEqualsPath": "$.i"}),
            v.clone()
        ));
        assert!(holds(
            json!({"Variable": "$.big", "NumericGreaterThan": 18446744073709551614u64}),
            v.clone()
        ));
        assert!(holds(
            json!({"Variable": "$.neg", "NumericLessThan": 0.5}),
            v
        ));
    }

    #[test]
    fn timestamps_compare_as_instants() {
        let v = json!({"t": "2001-01-01T14:00:00+02:00", "u": "2001-01-01T12:00:01Z"});
        assert!(holds(
            json!({"Variable": "$.t", "TimestampEquals": "2001-01-01T12:00:00Z"}),
            v.clone()
        ));
        assert!(holds(
            json!({"Variable": "$.t", "TimestampLessThanPath": "$.u"}),
            v.clone()
        ));
        assert!(holds(
            json!({"Variable": "$.u", "IsTimestamp": true}),
            v.clone()
        ));
        assert!(holds(
            json!({"Variable": "$.t", "TimestampGreaterThanEquals": "2001-01-01T12:00:00Z"}),
            v
        ));
    }

    #[test]
    fn string_matches_knows_only_the_star() {
        let m = |p: &str, s: &str| {
            holds(
                json!({"Variable": "$.s", "StringMatches": p}),
                json!({ "s": s }),
            )
        };
        assert!(m("log-*.txt", "log-2020.txt"));
        assert!(m("foo*.log", "foo23.log"));
        assert!(m("*.log", "zebra.log"));
        assert!(m("foo*.*", "foobar.zebra"));
        assert!(m("*", ""));
        assert!(!m("log-*.txt", "log-2020.txt.gz"));
        assert!(!m("a?c", "abc"));
        assert!(m("a?c", "a?c"));
        assert!(m(r"a\*c", "a*c"));
        assert!(!m(r"a\*c", "abc"));
        assert!(m(r"a\\*", r"a\bcd"));
        assert!(m("*a*b*", "xxaxxbxx"));
        assert!(!m("*a*b*", "xxbxxaxx"));
    }

    #[test]
    fn is_present_guards_a_comparison_inside_and() {
        let r = json!({"And": [
            {"Variable": "$.keyThatMightNotExist", "IsPresent": true},
            {"Variable": "$.keyThatMightNotExist", "StringEquals": "foo"}
        ]});
        assert!(!holds(r.clone(), json!({})));
        assert!(holds(r, json!({"keyThatMightNotExist": "foo"})));
    }

    #[test]
    fn a_missing_variable_is_a_runtime_error() {
        let err = rule(json!({"Variable": "$.type", "StringEquals": "Private"}))
            .evaluate(&json!({}), &Value::Null)
            .unwrap_err();
        assert_eq!(err.error, "States.Runtime");
        assert!(err.cause.unwrap().contains("'$.type'"));
        let err = rule(json!({"Variable": "$.a", "NumericEqualsPath": "$.b"}))
            .evaluate(&json!({"a": 1}), &Value::Null)
            .unwrap_err();
        assert!(err.cause.unwrap().contains("'$.b'"));
    }

    #[test]
    fn type_tests_and_null() {
        let v = json!({"n": null, "x": 1.5, "b": false, "s": "s"});
        assert!(holds(json!({"Variable": "$.n", "IsNull": true}), v.clone()));
        assert!(holds(
            json!({"Variable": "$.x", "IsNumeric": true}),
            v.clone()
        ));
        assert!(holds(
            json!({"Variable": "$.b", "IsBoolean": true}),
            v.clone()
        ));
        assert!(holds(
            json!({"Variable": "$.s", "IsString": true}),
            v.clone()
        ));
        assert!(holds(
            json!({"Variable": "$.s", "IsTimestamp": false}),
            v.clone()
        ));
        assert!(holds(
            json!({"Variable": "$.nope", "IsPresent": false}),
            v.clone()
        ));
        assert!(holds(
            json!({"Not": {"Variable": "$.x", "IsNull": true}}),
            v.clone()
        ));
        assert!(holds(
            json!({"Or": [{"Variable": "$.x", "NumericEquals": 2}, {"Variable": "$.b", "BooleanEqualsPath": "$.b"}]}),
            v
        ));
    }

    #[test]
    fn the_context_object_can_be_a_variable() {
        let r = rule(json!({"Variable": "$$.Execution.Name", "StringEquals": "run-1"}));
        assert!(r
            .evaluate(&json!({}), &json!({"Execution": {"Name": "run-1"}}))
            .unwrap());
    }

    #[test]
    fn malformed_rules_are_refused_with_their_location() {
        let bad =
            |v: Value| compile(v.as_object().unwrap(), "States.C.Choices[0]", false).unwrap_err();
        assert_eq!(
            bad(json!({"Variable": "$.a", "StringEquals": 1})).name(),
            "InvalidDefinition"
        );
        assert_eq!(
            bad(json!({"Variable": "$.a", "NumericEquals": "1"})).name(),
            "InvalidDefinition"
        );
        assert_eq!(
            bad(json!({"Variable": "$.a", "TimestampEquals": "2001-01-01 12:00:00"})).name(),
            "InvalidDefinition"
        );
        assert_eq!(
            bad(json!({"Variable": "$.a", "IsNull": "yes"})).name(),
            "InvalidDefinition"
        );
        assert_eq!(bad(json!({"Variable": "$.a"})).name(), "InvalidDefinition");
        assert_eq!(
            bad(json!({"Variable": "$.a", "StringEquals": "x", "IsNull": true})).name(),
            "InvalidDefinition"
        );
        assert_eq!(
            bad(json!({"Variable": "$..a", "IsNull": true})).name(),
            "InvalidReferencePath"
        );
        assert_eq!(
            bad(json!({"Variable": "$.a", "StringEqualsPath": "$.b[*]"})).name(),
            "InvalidReferencePath"
        );
        assert_eq!(
            bad(json!({"Variable": "$.a", "StringMatches": r"a\b"})).name(),
            "InvalidDefinition"
        );
        assert_eq!(bad(json!({"And": []})).name(), "InvalidDefinition");
        assert_eq!(
            bad(json!({"And": [{"Variable": "$.a", "IsNull": true}], "Variable": "$.a"})).name(),
            "InvalidDefinition"
        );
        let nested_next = bad(json!({"Not": {"Variable": "$.a", "IsNull": true, "Next": "X"}}));
        assert_eq!(nested_next.location(), "States.C.Choices[0].Not.Next");
        assert_eq!(
            bad(json!({"Condition": "{% true %}"})).name(),
            "UnsupportedFeature"
        );
        assert!(compile_top(
            &json!({"Variable": "$.a", "IsNull": true}),
            "States.C.Choices[0]"
        )
        .is_err());
    }
}
