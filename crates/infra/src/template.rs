//! `infra/app.yaml` read as data: the one description of the queue, tables, buckets, secrets,
//! the Pipe's input template and the roles, which local mode provisions from and the tests
//! check the code against.
//!
//! Only what those uses need is evaluated: `!Ref`, `!Sub` and `!GetAtt` over parameters
//! (given values, else defaults), the pseudo parameters and `Condition`s made of `!Equals` and
//! `!Not`. A reference to another resource stays symbolic (`<Logical.Attr>`), as it would be
//! unknown until the stack exists.

use std::collections::BTreeMap;
use std::sync::LazyLock;

use serde_yaml::Value;

/// The application stack's template, as deployed.
pub const APP_TEMPLATE: &str = include_str!("../../../infra/app.yaml");

/// One leaderboard's cluster stack, as deployed.
pub const CLUSTER_TEMPLATE: &str = include_str!("../../../infra/cluster.yaml");

/// The parsed cluster template.
pub static CLUSTER: LazyLock<Template> =
    LazyLock::new(|| Template::parse(CLUSTER_TEMPLATE).expect("infra/cluster.yaml parses"));

/// The parsed template (it is part of this build: a parse failure is a build defect, and the
/// tests say so first).
pub static APP: LazyLock<Template> =
    LazyLock::new(|| Template::parse(APP_TEMPLATE).expect("infra/app.yaml parses"));

/// Why the template could not be read.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum TemplateError {
    /// Not YAML, or not a template.
    #[error("infra/app.yaml: {0}")]
    Invalid(String),
    /// A resource or property the caller needs is not there.
    #[error("infra/app.yaml: `{0}` is missing")]
    Missing(String),
}

/// One IAM statement, its values evaluated.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Statement {
    /// `Allow` or `Deny`.
    pub effect: String,
    /// Actions, e.g. `dynamodb:GetItem`.
    pub actions: Vec<String>,
    /// Resources, e.g. `arn:aws:dynamodb:us-east-1:123456789012:table/x`.
    pub resources: Vec<String>,
}

/// A CloudFormation template and the parameter values it is evaluated with.
#[derive(Debug, Clone)]
pub struct Template {
    root: Value,
    parameters: BTreeMap<String, String>,
    /// `AWS::StackName`.
    pub stack_name: String,
    /// `AWS::Region`.
    pub region: String,
    /// `AWS::AccountId`.
    pub account: String,
}

impl Template {
    /// Parses `text`, with the parameters' defaults, stack `leaderboard`, moto's account and
    /// region.
    pub fn parse(text: &str) -> Result<Template, TemplateError> {
        let root: Value =
            serde_yaml::from_str(text).map_err(|e| TemplateError::Invalid(e.to_string()))?;
        if !root["Resources"].is_mapping() {
            return Err(TemplateError::Invalid("no `Resources` mapping".into()));
        }
        let mut parameters = BTreeMap::new();
        if let Some(map) = root["Parameters"].as_mapping() {
            for (name, spec) in map {
                if let (Some(name), Some(default)) = (name.as_str(), scalar(&spec["Default"])) {
                    parameters.insert(name.to_string(), default);
                }
            }
        }
        Ok(Template {
            root,
            parameters,
            stack_name: "leaderboard".into(),
            region: "us-east-1".into(),
            account: "123456789012".into(),
        })
    }

    /// The same template with `name` set to `value`.
    pub fn with_parameter(mut self, name: &str, value: impl Into<String>) -> Template {
        self.parameters.insert(name.to_string(), value.into());
        self
    }

    /// With the stack's pseudo parameters.
    pub fn in_stack(mut self, stack: &str, region: &str, account: &str) -> Template {
        (self.stack_name, self.region, self.account) =
            (stack.into(), region.into(), account.into());
        self
    }

    /// The raw template.
    pub fn root(&self) -> &Value {
        &self.root
    }

    /// Logical ids and types of every resource whose condition holds.
    pub fn resources(&self) -> Vec<(String, String)> {
        let mut out = Vec::new();
        for (id, resource) in self.root["Resources"].as_mapping().into_iter().flatten() {
            let (Some(id), Some(kind)) = (id.as_str(), resource["Type"].as_str()) else {
                continue;
            };
            let active = match resource["Condition"].as_str() {
                Some(condition) => self.condition(condition),
                None => true,
            };
            if active {
                out.push((id.to_string(), kind.to_string()));
            }
        }
        out
    }

    /// Logical ids of the active resources of type `kind`.
    pub fn resources_of(&self, kind: &str) -> Vec<String> {
        self.resources()
            .into_iter()
            .filter(|(_, k)| k == kind)
            .map(|(id, _)| id)
            .collect()
    }

    /// A resource's property, unevaluated.
    pub fn property(&self, id: &str, path: &[&str]) -> Result<&Value, TemplateError> {
        let mut v = &self.root["Resources"][id];
        if v.is_null() {
            return Err(TemplateError::Missing(format!("Resources.{id}")));
        }
        v = &v["Properties"];
        for key in path {
            v = &v[*key];
        }
        if v.is_null() {
            return Err(TemplateError::Missing(format!(
                "Resources.{id}.Properties.{}",
                path.join(".")
            )));
        }
        Ok(v)
    }

    /// A resource's property evaluated to text.
    pub fn text(&self, id: &str, path: &[&str]) -> Result<String, TemplateError> {
        let value = self.property(id, path)?;
        self.eval(value)
            .ok_or_else(|| TemplateError::Invalid(format!("`{id}.{}` is not text", path.join("."))))
    }

    /// Whether the named condition holds.
    pub fn condition(&self, name: &str) -> bool {
        self.holds(&self.root["Conditions"][name])
    }

    fn holds(&self, v: &Value) -> bool {
        match v {
            Value::Tagged(t) if t.tag == "!Equals" => match t.value.as_sequence() {
                Some(pair) if pair.len() == 2 => self.eval(&pair[0]) == self.eval(&pair[1]),
                _ => false,
            },
            Value::Tagged(t) if t.tag == "!Not" => match t.value.as_sequence() {
                Some(one) if one.len() == 1 => !self.holds(&one[0]),
                _ => false,
            },
            Value::Tagged(t) if t.tag == "!Condition" => {
                t.value.as_str().is_some_and(|c| self.condition(c))
            }
            _ => false,
        }
    }

    /// Evaluates a scalar, `!Ref`, `!Sub`, `!GetAtt` or `!ImportValue` (short or long form)
    /// to text.
    pub fn eval(&self, v: &Value) -> Option<String> {
        if let Some(map) = v.as_mapping().filter(|m| m.len() == 1) {
            let (key, inner) = map.iter().next()?;
            let tag = match key.as_str()? {
                "Ref" => "!Ref".to_string(),
                long => format!("!{}", long.strip_prefix("Fn::")?),
            };
            let short = Value::Tagged(Box::new(serde_yaml::value::TaggedValue {
                tag: serde_yaml::value::Tag::new(tag),
                value: inner.clone(),
            }));
            return self.eval(&short);
        }
        match v {
            Value::Tagged(t) if t.tag == "!Ref" => Some(self.reference(t.value.as_str()?)),
            Value::Tagged(t) if t.tag == "!GetAtt" => Some(format!("<{}>", t.value.as_str()?)),
            Value::Tagged(t) if t.tag == "!Sub" => {
                let text = t.value.as_str()?;
                let mut out = String::new();
                let mut rest = text;
                while let Some(start) = rest.find("${") {
                    out.push_str(&rest[..start]);
                    let end = rest[start..].find('}')? + start;
                    let name = &rest[start + 2..end];
                    out.push_str(&if name.contains('.') {
                        format!("<{name}>")
                    } else {
                        self.reference(name)
                    });
                    rest = &rest[end + 1..];
                }
                out.push_str(rest);
                Some(out)
            }
            Value::Tagged(t) if t.tag == "!ImportValue" => {
                Some(format!("<import {}>", self.eval(&t.value)?))
            }
            other => scalar(other),
        }
    }

    fn reference(&self, name: &str) -> String {
        match name {
            "AWS::Region" => self.region.clone(),
            "AWS::AccountId" => self.account.clone(),
            "AWS::StackName" => self.stack_name.clone(),
            "AWS::Partition" => "aws".into(),
            _ => match self.parameters.get(name) {
                Some(value) => value.clone(),
                None => format!("<{name}>"),
            },
        }
    }

    /// The statements of the inline policies of role `role` (only the one named `policy`,
    /// when given), evaluated.
    pub fn role_statements(
        &self,
        role: &str,
        policy: Option<&str>,
    ) -> Result<Vec<Statement>, TemplateError> {
        let policies = self.property(role, &["Policies"])?;
        let mut out = Vec::new();
        for p in policies.as_sequence().into_iter().flatten() {
            if policy.is_some_and(|name| p["PolicyName"].as_str() != Some(name)) {
                continue;
            }
            self.push_statements(&p["PolicyDocument"], &mut out);
        }
        // Policies of their own attached to the role (one that names a resource which itself
        // depends on the role's function would otherwise make a dependency cycle).
        let root = self.root();
        for (_, resource) in root["Resources"].as_mapping().into_iter().flatten() {
            let props = &resource["Properties"];
            let attached = resource["Type"].as_str() == Some("AWS::IAM::Policy")
                && policy.is_none_or(|name| props["PolicyName"].as_str() == Some(name))
                && self
                    .list(&props["Roles"])
                    .iter()
                    .any(|r| r.trim_matches(['<', '>']) == role);
            if attached {
                self.push_statements(&props["PolicyDocument"], &mut out);
            }
        }
        Ok(out)
    }

    fn push_statements(&self, document: &Value, out: &mut Vec<Statement>) {
        for s in document["Statement"].as_sequence().into_iter().flatten() {
            out.push(Statement {
                effect: s["Effect"].as_str().unwrap_or_default().to_string(),
                actions: self.list(&s["Action"]),
                resources: self.list(&s["Resource"]),
            });
        }
    }

    /// The parameters whose value is `value`.
    pub fn parameter_names_with_value(&self, value: &str) -> Vec<String> {
        self.parameters
            .iter()
            .filter(|(_, v)| v.as_str() == value)
            .map(|(k, _)| k.clone())
            .collect()
    }

    /// A value or a list of values, each evaluated.
    pub fn list(&self, v: &Value) -> Vec<String> {
        match v.as_sequence() {
            Some(items) => items.iter().filter_map(|i| self.eval(i)).collect(),
            None => self.eval(v).into_iter().collect(),
        }
    }

    /// The ARN a `!Ref` or `!GetAtt X.Arn` of a resource stands for, once the stack exists
    /// (for the types local mode creates: secrets, queues).
    pub fn physical_name(&self, id: &str) -> Result<String, TemplateError> {
        let resource = &self.root["Resources"][id];
        let name_key = match resource["Type"].as_str() {
            Some("AWS::SQS::Queue") => "QueueName",
            Some("AWS::SecretsManager::Secret") => "Name",
            Some("AWS::DynamoDB::Table") => "TableName",
            Some("AWS::S3::Bucket") => "BucketName",
            _ => return Err(TemplateError::Missing(format!("a named resource `{id}`"))),
        };
        self.text(id, &[name_key])
    }
}

impl Template {
    /// A property as the JSON CloudFormation hands the service: intrinsics evaluated to
    /// their text (`!Ref`, `!Sub`, `!GetAtt` as `<Id.Attr>`), mappings and lists kept.
    pub fn json(&self, v: &Value) -> serde_json::Value {
        match v {
            Value::Tagged(_) => self.eval(v).map_or(serde_json::Value::Null, Into::into),
            Value::Mapping(m) if m.len() == 1 && is_intrinsic(m) => {
                self.eval(v).map_or(serde_json::Value::Null, Into::into)
            }
            Value::Mapping(m) => serde_json::Value::Object(
                m.iter()
                    .filter_map(|(k, v)| Some((k.as_str()?.to_string(), self.json(v))))
                    .collect(),
            ),
            Value::Sequence(items) => items.iter().map(|i| self.json(i)).collect(),
            Value::Number(n) => serde_json::to_value(n).unwrap_or(serde_json::Value::Null),
            Value::Bool(b) => serde_json::Value::Bool(*b),
            Value::String(s) => serde_json::Value::String(s.clone()),
            _ => serde_json::Value::Null,
        }
    }
}

fn is_intrinsic(m: &serde_yaml::Mapping) -> bool {
    m.keys()
        .next()
        .and_then(|k| k.as_str())
        .is_some_and(|k| k == "Ref" || k.starts_with("Fn::"))
}

fn scalar(v: &Value) -> Option<String> {
    match v {
        Value::String(s) => Some(s.clone()),
        Value::Number(n) => Some(n.to_string()),
        Value::Bool(b) => Some(b.to_string()),
        _ => None,
    }
}

/// The Pipe's `InputTemplate`, as deployed.
pub fn pipe_input_template() -> Result<String, TemplateError> {
    let pipes = APP.resources_of("AWS::Pipes::Pipe");
    let [pipe] = pipes.as_slice() else {
        return Err(TemplateError::Invalid(format!(
            "expected one AWS::Pipes::Pipe, found {}",
            pipes.len()
        )));
    };
    APP.text(pipe, &["TargetParameters", "InputTemplate"])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn references_substitutions_and_conditions_evaluate() {
        let t = APP.clone().with_parameter("Leaderboard20Bucket", "b20");
        let statements = t.role_statements("MonitorRole", Some("code")).unwrap();
        let objects = statements
            .iter()
            .find(|s| s.actions.contains(&"s3:GetObject".to_string()))
            .unwrap();
        assert!(objects
            .resources
            .contains(&"arn:aws:s3:::b20/*".to_string()));
        assert!(t.condition("CreateDataStores"));
        let t = t.with_parameter("CreateDataStores", "false");
        assert!(!t.condition("CreateDataStores"));
        // The original system's tables are the operator's; the wake, budget and admission
        // tables are ours.
        assert_eq!(
            t.resources_of("AWS::DynamoDB::Table"),
            ["WakeTable", "BudgetTable", "AdmissionTable"]
        );
    }

    #[test]
    fn the_pipe_template_is_the_original_one() {
        assert_eq!(
            pipe_input_template().unwrap(),
            "{\"challenge_pk\": <$.body.challenge_pk>, \"phase_pk\": <$.body.phase_pk>, \
             \"submission_pk\": <$.body.submission_pk>, \"submitted_image_uri\": <$.body.submitted_image_uri>}"
        );
    }
}
