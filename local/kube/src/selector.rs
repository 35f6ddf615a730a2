//! Label selectors (`=`, `==`, `!=`, exists, `!`, `in`, `notin`, `>`, `<`) and field selectors.

use std::collections::BTreeMap;

use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector as LabelSelectorSpec;

use crate::objects::names::{label_value_errors, qualified_name_errors};

/// One requirement of a label selector.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Requirement {
    /// `key=value` or `key==value`.
    Eq(String, String),
    /// `key!=value` (also true when the key is absent).
    NotEq(String, String),
    /// `key in (a,b)`.
    In(String, Vec<String>),
    /// `key notin (a,b)` (also true when the key is absent).
    NotIn(String, Vec<String>),
    /// `key`.
    Exists(String),
    /// `!key`.
    NotExists(String),
    /// `key>n` (integer comparison).
    Gt(String, i64),
    /// `key<n` (integer comparison).
    Lt(String, i64),
}

impl Requirement {
    fn matches(&self, labels: &BTreeMap<String, String>) -> bool {
        match self {
            Self::Eq(k, v) => labels.get(k) == Some(v),
            Self::NotEq(k, v) => labels.get(k) != Some(v),
            Self::In(k, vs) => labels.get(k).is_some_and(|v| vs.contains(v)),
            Self::NotIn(k, vs) => labels.get(k).is_none_or(|v| !vs.contains(v)),
            Self::Exists(k) => labels.contains_key(k),
            Self::NotExists(k) => !labels.contains_key(k),
            Self::Gt(k, n) => labels
                .get(k)
                .and_then(|v| v.parse::<i64>().ok())
                .is_some_and(|v| v > *n),
            Self::Lt(k, n) => labels
                .get(k)
                .and_then(|v| v.parse::<i64>().ok())
                .is_some_and(|v| v < *n),
        }
    }
}

/// A parsed label selector: every requirement must hold. Empty selects everything.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct LabelSelector(pub Vec<Requirement>);

#[derive(Clone, Debug, PartialEq, Eq)]
enum Tok {
    Ident(String),
    Bang,
    Eq,
    DoubleEq,
    NotEq,
    Open,
    Close,
    Comma,
    Gt,
    Lt,
}

fn tokenize(s: &str) -> Result<Vec<Tok>, String> {
    let mut toks = Vec::new();
    let chars: Vec<char> = s.chars().collect();
    let mut i = 0;
    while i < chars.len() {
        let c = chars[i];
        match c {
            c if c.is_whitespace() => i += 1,
            '!' if chars.get(i + 1) == Some(&'=') => {
                toks.push(Tok::NotEq);
                i += 2;
            }
            '!' => {
                toks.push(Tok::Bang);
                i += 1;
            }
            '=' if chars.get(i + 1) == Some(&'=') => {
                toks.push(Tok::DoubleEq);
                i += 2;
            }
            '=' => {
                toks.push(Tok::Eq);
                i += 1;
            }
            '(' => {
                toks.push(Tok::Open);
                i += 1;
            }
            ')' => {
                toks.push(Tok::Close);
                i += 1;
            }
            ',' => {
                toks.push(Tok::Comma);
                i += 1;
            }
            '>' => {
                toks.push(Tok::Gt);
                i += 1;
            }
            '<' => {
                toks.push(Tok::Lt);
                i += 1;
            }
            _ => {
                let start = i;
                while i < chars.len()
                    && !chars[i].is_whitespace()
                    && !matches!(chars[i], '!' | '=' | '(' | ')' | ',' | '>' | '<')
                {
                    i += 1;
                }
                toks.push(Tok::Ident(chars[start..i].iter().collect()));
            }
        }
    }
    Ok(toks)
}

fn check_key(k: &str) -> Result<(), String> {
    match qualified_name_errors(k).first() {
        Some(msg) => Err(format!("key: Invalid value: {:?}: {msg}", k)),
        None => Ok(()),
    }
}

fn check_value(v: &str) -> Result<(), String> {
    match label_value_errors(v).first() {
        Some(msg) => Err(format!("values[0]: Invalid value: {:?}: {msg}", v)),
        None => Ok(()),
    }
}

struct Parser {
    toks: Vec<Tok>,
    pos: usize,
}

impl Parser {
    fn peek(&self) -> Option<&Tok> {
        self.toks.get(self.pos)
    }

    fn next(&mut self) -> Option<Tok> {
        let t = self.toks.get(self.pos).cloned();
        self.pos += 1;
        t
    }

    fn ident(&mut self, what: &str) -> Result<String, String> {
        match self.next() {
            Some(Tok::Ident(s)) => Ok(s),
            other => Err(format!("found {other:?}, expected: {what}")),
        }
    }

    fn value_or_empty(&mut self) -> Result<String, String> {
        match self.peek() {
            Some(Tok::Ident(_)) => self.ident("value"),
            // NB: `key=` selects the empty value, as in Kubernetes.
            _ => Ok(String::new()),
        }
    }

    fn set(&mut self) -> Result<Vec<String>, String> {
        match self.next() {
            Some(Tok::Open) => {}
            other => Err(format!("found {other:?}, expected: '('"))?,
        }
        let mut values = Vec::new();
        loop {
            match self.next() {
                Some(Tok::Ident(v)) => {
                    check_value(&v)?;
                    values.push(v);
                    match self.next() {
                        Some(Tok::Comma) => continue,
                        Some(Tok::Close) => break,
                        other => Err(format!("found {other:?}, expected: ',' or ')'"))?,
                    }
                }
                Some(Tok::Close) if values.is_empty() => {
                    return Err("for 'in', 'notin' operators, values set can't be empty".into())
                }
                other => Err(format!("found {other:?}, expected: value"))?,
            }
        }
        Ok(values)
    }

    fn requirement(&mut self) -> Result<Requirement, String> {
        if self.peek() == Some(&Tok::Bang) {
            self.next();
            let key = self.ident("identifier after '!'")?;
            check_key(&key)?;
            return Ok(Requirement::NotExists(key));
        }
        let key = self.ident("identifier")?;
        check_key(&key)?;
        let req = match self.peek() {
            None | Some(Tok::Comma) => Requirement::Exists(key),
            Some(Tok::Eq) | Some(Tok::DoubleEq) => {
                self.next();
                let v = self.value_or_empty()?;
                check_value(&v)?;
                Requirement::Eq(key, v)
            }
            Some(Tok::NotEq) => {
                self.next();
                let v = self.value_or_empty()?;
                check_value(&v)?;
                Requirement::NotEq(key, v)
            }
            Some(Tok::Gt) | Some(Tok::Lt) => {
                let gt = self.next() == Some(Tok::Gt);
                let v = self.ident("integer")?;
                let n: i64 = v.parse().map_err(|_| {
                    format!("for 'Gt', 'Lt' operators, the value must be an integer: {v:?}")
                })?;
                if gt {
                    Requirement::Gt(key, n)
                } else {
                    Requirement::Lt(key, n)
                }
            }
            Some(Tok::Ident(op)) if op == "in" => {
                self.next();
                Requirement::In(key, self.set()?)
            }
            Some(Tok::Ident(op)) if op == "notin" => {
                self.next();
                Requirement::NotIn(key, self.set()?)
            }
            Some(other) => {
                return Err(format!(
                    "found {other:?}, expected: in, notin, =, ==, !=, gt, lt"
                ))
            }
        };
        Ok(req)
    }
}

impl LabelSelector {
    /// Parses the `labelSelector` query syntax.
    pub fn parse(s: &str) -> Result<Self, String> {
        let toks = tokenize(s)?;
        if toks.is_empty() {
            return Ok(Self::default());
        }
        let mut p = Parser { toks, pos: 0 };
        let mut reqs = Vec::new();
        loop {
            reqs.push(
                p.requirement()
                    .map_err(|e| format!("unable to parse requirement: {e}"))?,
            );
            match p.next() {
                None => break,
                Some(Tok::Comma) => continue,
                Some(other) => {
                    return Err(format!(
                        "unable to parse requirement: found {other:?}, expected: ','"
                    ))
                }
            }
        }
        Ok(Self(reqs))
    }

    /// The selector of a Job's `spec.selector` (matchLabels and matchExpressions).
    pub fn from_spec(spec: &LabelSelectorSpec) -> Result<Self, String> {
        let mut reqs = Vec::new();
        for (k, v) in spec.match_labels.iter().flatten() {
            reqs.push(Requirement::Eq(k.clone(), v.clone()));
        }
        for e in spec.match_expressions.iter().flatten() {
            let values = e.values.clone().unwrap_or_default();
            let req = match e.operator.as_str() {
                "In" => Requirement::In(e.key.clone(), values),
                "NotIn" => Requirement::NotIn(e.key.clone(), values),
                "Exists" => Requirement::Exists(e.key.clone()),
                "DoesNotExist" => Requirement::NotExists(e.key.clone()),
                other => return Err(format!("{other:?} is not a valid label selector operator")),
            };
            reqs.push(req);
        }
        Ok(Self(reqs))
    }

    /// Whether the labels satisfy every requirement.
    pub fn matches(&self, labels: Option<&BTreeMap<String, String>>) -> bool {
        let empty = BTreeMap::new();
        let labels = labels.unwrap_or(&empty);
        self.0.iter().all(|r| r.matches(labels))
    }

    /// Whether this selector selects everything.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

/// A parsed field selector (`metadata.name=x,status.phase!=Running`).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct FieldSelector(pub Vec<(String, bool, String)>);

impl FieldSelector {
    /// Parses the selector, refusing fields outside `supported`.
    pub fn parse(s: &str, supported: &[&str]) -> Result<Self, String> {
        let mut out = Vec::new();
        for part in s.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            let (field, eq, value) = if let Some((f, v)) = part.split_once("!=") {
                (f, false, v)
            } else if let Some((f, v)) = part.split_once("==") {
                (f, true, v)
            } else if let Some((f, v)) = part.split_once('=') {
                (f, true, v)
            } else {
                return Err(format!(
                    "invalid selector: '{s}'; can't understand '{part}'"
                ));
            };
            let field = field.trim();
            if !supported.contains(&field) {
                return Err(format!("field label not supported: {field}"));
            }
            out.push((field.to_owned(), eq, value.trim().to_owned()));
        }
        Ok(Self(out))
    }

    /// Whether the object's fields (looked up by `get`) satisfy every term.
    pub fn matches(&self, get: impl Fn(&str) -> String) -> bool {
        self.0.iter().all(|(f, eq, v)| (get(f) == *v) == *eq)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn labels(pairs: &[(&str, &str)]) -> BTreeMap<String, String> {
        pairs
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect()
    }

    #[test]
    fn every_operator_selects_as_kubernetes_does() {
        let l = labels(&[("app", "lb"), ("tier", "sim"), ("n", "5")]);
        let m = |s: &str| LabelSelector::parse(s).unwrap().matches(Some(&l));
        assert!(m("app=lb"));
        assert!(m("app==lb"));
        assert!(!m("app!=lb"));
        assert!(m("other!=x"));
        assert!(m("app"));
        assert!(!m("!app"));
        assert!(m("!other"));
        assert!(m("tier in (sim, agent)"));
        assert!(!m("tier notin (sim,agent)"));
        assert!(m("other notin (x)"));
        assert!(!m("other in (x)"));
        assert!(m("app=lb, tier in (sim)"));
        assert!(!m("app=lb,tier=agent"));
        assert!(m("n>4"));
        assert!(!m("n<5"));
        assert!(m(""));
        assert!(m("batch.kubernetes.io/job-name notin (a,b),app"));
    }

    #[test]
    fn malformed_selectors_are_refused_with_a_reason() {
        assert!(LabelSelector::parse("app in (a").is_err());
        assert!(LabelSelector::parse("app in ()").is_err());
        assert!(LabelSelector::parse("app=a b").is_err());
        assert!(LabelSelector::parse("Bad Key=1").is_err());
        assert!(LabelSelector::parse("app=(").is_err());
    }

    #[test]
    fn field_selectors_refuse_unknown_fields() {
        let f = FieldSelector::parse("metadata.name=x", &["metadata.name"]).unwrap();
        assert!(f.matches(|_| "x".into()));
        assert!(!f.matches(|_| "y".into()));
        let e = FieldSelector::parse("spec.foo=1", &["metadata.name"]).unwrap_err();
        assert_eq!(e, "field label not supported: spec.foo");
        let ne = FieldSelector::parse("status.phase!=Running", &["status.phase"]).unwrap();
        assert!(ne.matches(|_| "Pending".into()));
    }
}
