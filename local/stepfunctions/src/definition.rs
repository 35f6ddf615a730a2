//! A definition parsed and validated completely at load: states, transitions, data flow,
//! retriers and catchers. Anything this executor does not run is refused here, by location.

use std::collections::{BTreeMap, HashMap, HashSet, VecDeque};
use std::sync::Arc;

use lb_asl::{Call, DataFlow, Path, ReferencePath, ResultPath, Template};
use serde_json::{Map, Value};
use time::OffsetDateTime;

use crate::choice::{self, Rule};
use crate::error::LoadError;
use crate::substitute::{substitute, Substituted};
use crate::tasks::{function_name, FunctionRef};
use crate::timestamp;

/// The largest `Seconds`, `TimeoutSeconds`, `IntervalSeconds` and `MaxAttempts` AWS accepts.
const MAX_SECONDS: u64 = 99_999_999;
/// Optimized integrations without the callback pattern (developer guide, "Service integration
/// patterns", the table of optimized integrations); their AWS SDK integrations have it.
const NO_CALLBACK: &[&str] = &[
    "athena",
    "batch",
    "codebuild",
    "dynamodb",
    "elasticmapreduce",
    "emr-containers",
    "emr-serverless",
    "glue",
    "databrew",
    "sagemaker",
    "http",
];
/// The largest `MaxDelaySeconds` (one year and a day).
const MAX_DELAY_SECONDS: u64 = 31_622_400;
/// Step Functions' limit on state name length.
const MAX_STATE_NAME: usize = 80;

/// Fields of the language this executor knows but does not run; refused with this note.
const UNSUPPORTED_FIELDS: &[(&str, &str)] = &[
    ("HeartbeatSecondsPath", "use a fixed `HeartbeatSeconds`"),
    ("Credentials", "cross-account task credentials"),
    ("Arguments", "JSONata is not supported"),
    ("Output", "JSONata is not supported"),
    ("Assign", "workflow variables are not supported"),
    (
        "QueryLanguage",
        "only the default JSONPath query language is supported",
    ),
    ("MaxConcurrencyPath", "use a fixed `MaxConcurrency`"),
    ("ItemReader", "distributed Map is not supported"),
    ("ItemBatcher", "distributed Map is not supported"),
    ("ResultWriter", "distributed Map is not supported"),
    (
        "ToleratedFailurePercentage",
        "distributed Map is not supported",
    ),
    (
        "ToleratedFailurePercentagePath",
        "distributed Map is not supported",
    ),
    ("ToleratedFailureCount", "distributed Map is not supported"),
    (
        "ToleratedFailureCountPath",
        "distributed Map is not supported",
    ),
    ("Label", "distributed Map is not supported"),
    ("Items", "JSONata is not supported; use `ItemsPath`"),
];

/// A loaded, validated state machine definition. Cheap to clone.
#[derive(Debug, Clone)]
pub struct StateMachine {
    pub(crate) definition: Arc<Definition>,
    pub(crate) name: String,
}

#[derive(Debug)]
pub(crate) struct Definition {
    pub root: Arc<Scope>,
    pub timeout_seconds: Option<u64>,
    pub functions: Vec<FunctionRef>,
    pub state_names: Vec<String>,
}

/// A set of states with a start: the machine itself, a Parallel branch or a Map iterator.
#[derive(Debug)]
pub(crate) struct Scope {
    pub start_at: String,
    pub states: HashMap<String, Arc<State>>,
}

#[derive(Debug)]
pub(crate) struct State {
    pub name: String,
    pub flow: DataFlow,
    /// `Next`, or `None` for `End: true` and for Choice, Succeed and Fail states.
    pub next: Option<String>,
    pub kind: Kind,
}

#[derive(Debug)]
pub(crate) enum Kind {
    Task(Task),
    Pass { result: Option<Value> },
    Wait(Wait),
    Choice(Choice),
    Succeed,
    Fail(Fail),
    Parallel(Parallel),
    Map(MapState),
}

impl Kind {
    /// The prefix of the state's history event names (`Task` in `TaskStateEntered`).
    pub fn event_prefix(&self) -> &'static str {
        match self {
            Kind::Task(_) => "Task",
            Kind::Pass { .. } => "Pass",
            Kind::Wait(_) => "Wait",
            Kind::Choice(_) => "Choice",
            Kind::Succeed => "Succeed",
            Kind::Fail(_) => "Fail",
            Kind::Parallel(_) => "Parallel",
            Kind::Map(_) => "Map",
        }
    }
}

/// How a Task reaches its function: a plain function ARN (`LambdaFunction*` events), the
/// optimized integration `arn:aws:states:::lambda:invoke` (`Task*` events, wrapped result),
/// or another service's integration `arn:aws:states:::<service>:<action>` (`Task*` events; a
/// handler registered as `<service>:<action>` plays the service).
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Integration {
    LambdaArn,
    LambdaInvoke,
    Service { service: String, action: String },
}

#[derive(Debug)]
pub(crate) struct Task {
    pub integration: Integration,
    pub function: FunctionRef,
    /// `.waitForTaskToken`: the result is what `SendTaskSuccess` reports for `$$.Task.Token`.
    pub callback: bool,
    pub heartbeat_seconds: Option<u64>,
    pub timeout_seconds: Option<u64>,
    /// `TimeoutSecondsPath`: the timeout read from the state's input at each attempt.
    pub timeout_path: Option<ReferencePath>,
    pub retry: Vec<Retrier>,
    pub catch: Vec<Catcher>,
}

#[derive(Debug)]
pub(crate) enum Wait {
    Seconds(u64),
    SecondsPath(ReferencePath),
    Timestamp(OffsetDateTime),
    TimestampPath(ReferencePath),
}

#[derive(Debug)]
pub(crate) struct Choice {
    pub rules: Vec<(Rule, String)>,
    pub default: Option<String>,
}

/// A Fail state's `Error` or `Cause`: literal, path, or intrinsic function.
#[derive(Debug)]
pub(crate) enum Text {
    None,
    Literal(String),
    Path(Path),
    Call { field: String, call: Call },
}

#[derive(Debug)]
pub(crate) struct Fail {
    pub error: Text,
    pub cause: Text,
}

#[derive(Debug)]
pub(crate) struct Parallel {
    pub branches: Vec<Arc<Scope>>,
    pub retry: Vec<Retrier>,
    pub catch: Vec<Catcher>,
}

#[derive(Debug)]
pub(crate) struct MapState {
    pub items_path: Option<ReferencePath>,
    pub item_selector: Option<Template>,
    /// 0: no limit.
    pub max_concurrency: u64,
    pub processor: Arc<Scope>,
    pub retry: Vec<Retrier>,
    pub catch: Vec<Catcher>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Jitter {
    None,
    Full,
}

#[derive(Debug)]
pub(crate) struct Retrier {
    pub error_equals: Vec<String>,
    pub interval_seconds: u64,
    pub max_attempts: u64,
    pub backoff_rate: f64,
    pub max_delay_seconds: Option<u64>,
    pub jitter: Jitter,
}

impl Retrier {
    /// The delay before retry number `retry` (0 for the first) of this retrier, in seconds,
    /// before jitter: `IntervalSeconds * BackoffRate^retry`, capped by `MaxDelaySeconds`.
    pub fn base_delay(&self, retry: u64) -> f64 {
        let exponent = i32::try_from(retry).unwrap_or(i32::MAX);
        let delay = self.interval_seconds as f64 * self.backoff_rate.powi(exponent);
        let cap = self
            .max_delay_seconds
            .map_or(MAX_SECONDS as f64, |m| m as f64);
        if delay.is_finite() {
            delay.min(cap)
        } else {
            cap
        }
    }
}

#[derive(Debug)]
pub(crate) struct Catcher {
    pub error_equals: Vec<String>,
    pub result_path: ResultPath,
    pub next: String,
}

impl StateMachine {
    /// Parses and validates `definition`, replacing `${Name}` with `substitutions[Name]`.
    ///
    /// Every state, field, path, template, intrinsic call, retrier and catcher is checked
    /// here; anything this executor does not run is refused with the location of the field
    /// (`States.Launch.HeartbeatSeconds`), never ignored.
    pub fn load(
        definition: &Value,
        substitutions: &HashMap<String, String>,
    ) -> Result<StateMachine, LoadError> {
        let Substituted { value, exact } = substitute(definition, substitutions)?;
        let map = value.as_object().ok_or_else(|| {
            LoadError::invalid(
                "(definition)",
                "a state machine definition must be a JSON object",
            )
        })?;
        let mut loader = Loader {
            exact,
            names: HashMap::new(),
            functions: Vec::new(),
        };
        for key in map.keys() {
            match key.as_str() {
                "StartAt" | "States" | "Comment" | "TimeoutSeconds" | "Version" => {}
                "QueryLanguage" => {
                    if map[key] != "JSONPath" {
                        return Err(LoadError::unsupported(
                            key,
                            "only the JSONPath query language is supported (not JSONata)",
                        ));
                    }
                }
                _ => {
                    return Err(LoadError::invalid(
                        key.as_str(),
                        format!("`{key}` is not a field of a state machine"),
                    ))
                }
            }
        }
        let obj = Obj::new(map, "");
        if let Some(version) = obj.string("Version")? {
            if version != "1.0" {
                return Err(LoadError::unsupported(
                    "Version",
                    format!("only version `1.0` exists, got `{version}`"),
                ));
            }
        }
        obj.string("Comment")?;
        let timeout_seconds = obj.integer("TimeoutSeconds", 1, MAX_SECONDS)?;
        let root = loader.scope(map, "")?;
        let mut state_names: Vec<String> = loader.names.into_keys().collect();
        state_names.sort();
        Ok(StateMachine {
            definition: Arc::new(Definition {
                root,
                timeout_seconds,
                functions: loader.functions,
                state_names,
            }),
            name: "StateMachine".to_owned(),
        })
    }

    /// The same definition under another name (`$$.StateMachine.Name`, ARNs); the default is
    /// `StateMachine`.
    pub fn with_name(mut self, name: impl Into<String>) -> StateMachine {
        self.name = name.into();
        self
    }

    /// The state machine's name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The first state.
    pub fn start_at(&self) -> &str {
        &self.definition.root.start_at
    }

    /// Every state name, branches and iterators included, sorted.
    pub fn state_names(&self) -> &[String] {
        &self.definition.state_names
    }

    /// The functions the Tasks invoke, once each (in the order of their states' names).
    pub fn functions(&self) -> &[FunctionRef] {
        &self.definition.functions
    }

    /// The definition's own `TimeoutSeconds`, if any.
    pub fn timeout_seconds(&self) -> Option<u64> {
        self.definition.timeout_seconds
    }
}

/// A JSON object being read, with its location for errors.
struct Obj<'a> {
    map: &'a Map<String, Value>,
    at: String,
}

impl<'a> Obj<'a> {
    fn new(map: &'a Map<String, Value>, at: &str) -> Obj<'a> {
        Obj {
            map,
            at: at.to_owned(),
        }
    }

    fn loc(&self, key: &str) -> String {
        if self.at.is_empty() {
            key.to_owned()
        } else {
            format!("{}.{key}", self.at)
        }
    }

    fn string(&self, key: &str) -> Result<Option<&'a str>, LoadError> {
        match self.map.get(key) {
            None => Ok(None),
            Some(Value::String(s)) => Ok(Some(s)),
            Some(_) => Err(LoadError::invalid(self.loc(key), "must be a string")),
        }
    }

    fn required_string(&self, key: &str) -> Result<&'a str, LoadError> {
        self.string(key)?.ok_or_else(|| {
            LoadError::invalid(
                at_or_root(&self.at),
                format!("the field `{key}` is required"),
            )
        })
    }

    fn integer(&self, key: &str, min: u64, max: u64) -> Result<Option<u64>, LoadError> {
        match self.map.get(key) {
            None => Ok(None),
            Some(v) => match v.as_u64() {
                Some(n) if (min..=max).contains(&n) => Ok(Some(n)),
                _ => Err(LoadError::invalid(
                    self.loc(key),
                    format!("must be an integer from {min} to {max}, got `{v}`"),
                )),
            },
        }
    }

    fn object(&self, key: &str) -> Result<Option<&'a Map<String, Value>>, LoadError> {
        match self.map.get(key) {
            None => Ok(None),
            Some(Value::Object(m)) => Ok(Some(m)),
            Some(_) => Err(LoadError::invalid(self.loc(key), "must be an object")),
        }
    }

    fn array(&self, key: &str) -> Result<Option<&'a Vec<Value>>, LoadError> {
        match self.map.get(key) {
            None => Ok(None),
            Some(Value::Array(a)) => Ok(Some(a)),
            Some(_) => Err(LoadError::invalid(self.loc(key), "must be an array")),
        }
    }

    /// Refuses every field not in `allowed`, naming the field and why.
    fn only(&self, allowed: &[&str], what: &str) -> Result<(), LoadError> {
        for key in self.map.keys() {
            if allowed.contains(&key.as_str()) {
                continue;
            }
            if let Some((_, why)) = UNSUPPORTED_FIELDS.iter().find(|(name, _)| name == key) {
                return Err(LoadError::unsupported(
                    self.loc(key),
                    format!("`{key}` is not supported by the embedded executor: {why}"),
                ));
            }
            return Err(LoadError::invalid(
                self.loc(key),
                format!("`{key}` is not a field of {what}"),
            ));
        }
        Ok(())
    }
}

struct Loader {
    exact: HashMap<String, String>,
    /// Every state name and where it is defined.
    names: HashMap<String, String>,
    functions: Vec<FunctionRef>,
}

const COMMON: &[&str] = &["Type", "Comment"];
const IO: &[&str] = &["InputPath", "OutputPath"];
const TRANSITION: &[&str] = &["Next", "End"];
const RESULT: &[&str] = &["Parameters", "ResultSelector", "ResultPath"];
const ERRORS: &[&str] = &["Retry", "Catch"];

fn fields(groups: &[&[&'static str]]) -> Vec<&'static str> {
    groups.iter().flat_map(|g| g.iter().copied()).collect()
}

impl Loader {
    fn scope(&mut self, map: &Map<String, Value>, at: &str) -> Result<Arc<Scope>, LoadError> {
        let obj = Obj::new(map, at);
        let start_at = obj.required_string("StartAt")?.to_owned();
        let states_map = obj
            .object("States")?
            .ok_or_else(|| LoadError::invalid(at_or_root(at), "the field `States` is required"))?;
        if states_map.is_empty() {
            return Err(LoadError::invalid(
                obj.loc("States"),
                "must define at least one state",
            ));
        }
        let states_at = obj.loc("States");
        let mut states = HashMap::with_capacity(states_map.len());
        // NB: definition order matters for nothing but error messages; sort for stable ones.
        let ordered: BTreeMap<&String, &Value> = states_map.iter().collect();
        for (name, value) in &ordered {
            let location = format!("{states_at}.{name}");
            if name.is_empty() || name.chars().count() > MAX_STATE_NAME {
                return Err(LoadError::invalid(
                    &location,
                    format!("a state name must have 1 to {MAX_STATE_NAME} characters"),
                ));
            }
            if let Some(other) = self.names.get(*name) {
                return Err(LoadError::DuplicateStateName {
                    location,
                    state: (*name).clone(),
                    other: other.clone(),
                });
            }
            self.names.insert((*name).clone(), location.clone());
            let state = self.state(name, value, &location)?;
            states.insert((*name).clone(), Arc::new(state));
        }
        let scope = Scope { start_at, states };
        check_transitions(&scope, &obj, &states_at)?;
        Ok(Arc::new(scope))
    }

    fn state(&mut self, name: &str, value: &Value, at: &str) -> Result<State, LoadError> {
        let map = value
            .as_object()
            .ok_or_else(|| LoadError::invalid(at, "a state must be an object"))?;
        let obj = Obj::new(map, at);
        let state_type = obj.required_string("Type")?;
        obj.string("Comment")?;
        let (kind, flow) = self.kind(state_type, &obj)?;
        let next = transition(&obj, &kind)?;
        Ok(State {
            name: name.to_owned(),
            flow,
            next,
            kind,
        })
    }

    /// The state's kind from its `Type`, with its data flow, each field checked against
    /// what that type allows.
    fn kind(&mut self, state_type: &str, obj: &Obj<'_>) -> Result<(Kind, DataFlow), LoadError> {
        let (map, at) = (obj.map, obj.at.as_str());
        let kind = match state_type {
            "Task" => {
                obj.only(
                    &fields(&[COMMON, IO, TRANSITION, RESULT, ERRORS, &["Resource", "TimeoutSeconds", "TimeoutSecondsPath", "HeartbeatSeconds"]]),
                    "a Task state",
                )?;
                let task = self.task(obj)?;
                (Kind::Task(task), data_flow(map, at)?)
            }
            "Pass" => {
                obj.only(
                    &fields(&[COMMON, IO, TRANSITION, &["Parameters", "ResultPath", "Result"]]),
                    "a Pass state",
                )?;
                (
                    Kind::Pass {
                        result: map.get("Result").cloned(),
                    },
                    data_flow(map, at)?,
                )
            }
            "Wait" => {
                obj.only(
                    &fields(&[
                        COMMON,
                        IO,
                        TRANSITION,
                        &["Seconds", "SecondsPath", "Timestamp", "TimestampPath"],
                    ]),
                    "a Wait state",
                )?;
                (Kind::Wait(wait(obj)?), data_flow(map, at)?)
            }
            "Choice" => {
                obj.only(&fields(&[COMMON, IO, &["Choices", "Default"]]), "a Choice state")?;
                (Kind::Choice(choice_state(obj)?), data_flow(map, at)?)
            }
            "Succeed" => {
                obj.only(&fields(&[COMMON, IO]), "a Succeed state")?;
                (Kind::Succeed, data_flow(map, at)?)
            }
            "Fail" => {
                obj.only(
                    &fields(&[COMMON, &["Error", "Cause", "ErrorPath", "CausePath"]]),
                    "a Fail state",
                )?;
                (Kind::Fail(fail(obj)?), DataFlow::default())
            }
            "Parallel" => {
                obj.only(
                    &fields(&[COMMON, IO, TRANSITION, RESULT, ERRORS, &["Branches"]]),
                    "a Parallel state",
                )?;
                let parallel = self.parallel(obj)?;
                (Kind::Parallel(parallel), data_flow(map, at)?)
            }
            "Map" => self.map_kind(obj)?,
            other => {
                return Err(LoadError::invalid(
                    obj.loc("Type"),
                    format!(
                        "`{other}` is not a state type (Task, Pass, Wait, Choice, Succeed, Fail, Parallel, Map)"
                    ),
                ))
            }
        };
        Ok(kind)
    }

    /// A Map state, with its data flow: its `Parameters` is its per-item selector, not its
    /// effective input.
    fn map_kind(&mut self, obj: &Obj<'_>) -> Result<(Kind, DataFlow), LoadError> {
        obj.only(
            &fields(&[
                COMMON,
                IO,
                TRANSITION,
                RESULT,
                ERRORS,
                &[
                    "ItemsPath",
                    "ItemSelector",
                    "MaxConcurrency",
                    "Iterator",
                    "ItemProcessor",
                ],
            ]),
            "a Map state",
        )?;
        let map_state = self.map_state(obj)?;
        let mut without_parameters = obj.map.clone();
        without_parameters.remove("Parameters");
        Ok((
            Kind::Map(map_state),
            data_flow(&without_parameters, &obj.at)?,
        ))
    }

    /// A Parallel state's branches, each a scope of its own, with its retriers and catchers.
    fn parallel(&mut self, obj: &Obj<'_>) -> Result<Parallel, LoadError> {
        let branches = obj
            .array("Branches")?
            .filter(|b| !b.is_empty())
            .ok_or_else(|| {
                LoadError::invalid(&obj.at, "`Branches` must be a non-empty array of branches")
            })?;
        let branches = branches
            .iter()
            .enumerate()
            .map(|(i, branch)| {
                let here = obj.loc(&format!("Branches[{i}]"));
                let map = branch
                    .as_object()
                    .ok_or_else(|| LoadError::invalid(&here, "a branch must be an object"))?;
                Obj::new(map, &here).only(&["StartAt", "States", "Comment"], "a branch")?;
                self.scope(map, &here)
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Parallel {
            branches,
            retry: retriers(obj)?,
            catch: catchers(obj)?,
        })
    }

    fn task(&mut self, obj: &Obj<'_>) -> Result<Task, LoadError> {
        let resource = obj.required_string("Resource")?;
        let resource_at = obj.loc("Resource");
        let mut callback = false;
        let (integration, function) = if let Some(rest) = states_integration(resource) {
            let rest = match rest.strip_suffix(".waitForTaskToken") {
                Some(base) => {
                    callback = true;
                    base
                }
                None => rest,
            };
            if rest.ends_with(".sync") || rest.contains(".sync:") {
                return Err(LoadError::unsupported(
                    resource_at,
                    "the run-a-job pattern (`.sync`) is not supported",
                ));
            }
            if rest != "lambda:invoke" {
                let (integration, function) = service(rest, resource, &resource_at, callback)?;
                return self.finish_task(obj, integration, function, callback);
            }
            let function = self.lambda_invoke(obj)?;
            (Integration::LambdaInvoke, function)
        } else if resource.starts_with("arn:") && resource.split(':').nth(2) == Some("lambda") {
            let name = function_name(resource)
                .map_err(|reason| LoadError::invalid(&resource_at, reason))?;
            let function = FunctionRef {
                function: resource.to_owned(),
                name,
                substitution: self.exact.get(&resource_at).cloned(),
            };
            (Integration::LambdaArn, function)
        } else if resource.split(':').nth(2) == Some("states") && resource.contains(":activity:") {
            return Err(LoadError::unsupported(
                resource_at,
                "activities are not supported",
            ));
        } else {
            return Err(LoadError::invalid(
                resource_at,
                format!(
                    "`{resource}` is neither a Lambda function ARN nor `arn:aws:states:::lambda:invoke`"
                ),
            ));
        };
        self.finish_task(obj, integration, function, callback)
    }

    /// `lambda:invoke`'s parameters: a static `FunctionName`, and a `Payload` or `Payload.$`.
    fn lambda_invoke(&self, obj: &Obj<'_>) -> Result<FunctionRef, LoadError> {
        let params_at = obj.loc("Parameters");
        let params = obj.object("Parameters")?.ok_or_else(|| {
            LoadError::invalid(
                &obj.at,
                "`arn:aws:states:::lambda:invoke` needs `Parameters` with `FunctionName`",
            )
        })?;
        for key in params.keys() {
            match key.as_str() {
                "FunctionName" | "Payload" | "Payload.$" => {}
                "FunctionName.$" => {
                    return Err(LoadError::unsupported(
                        format!("{params_at}.{key}"),
                        "a dynamic `FunctionName.$` is not supported; name the function statically",
                    ))
                }
                "InvocationType" | "Qualifier" | "ClientContext" | "LogType" => {
                    return Err(LoadError::unsupported(
                        format!("{params_at}.{key}"),
                        format!("`{key}` is not supported by the embedded executor (it invokes synchronously)"),
                    ))
                }
                _ => {
                    return Err(LoadError::invalid(
                        format!("{params_at}.{key}"),
                        format!("`{key}` is not a parameter of lambda:invoke"),
                    ))
                }
            }
        }
        if params.contains_key("Payload") && params.contains_key("Payload.$") {
            return Err(LoadError::invalid(
                &params_at,
                "`Payload` and `Payload.$` are exclusive",
            ));
        }
        let name_at = format!("{params_at}.FunctionName");
        let text = match params.get("FunctionName") {
            Some(Value::String(s)) => s.as_str(),
            Some(_) => return Err(LoadError::invalid(name_at, "must be a string")),
            None => {
                return Err(LoadError::invalid(
                    params_at,
                    "`FunctionName` is required for lambda:invoke",
                ))
            }
        };
        let name = function_name(text).map_err(|reason| LoadError::invalid(&name_at, reason))?;
        let function = FunctionRef {
            function: text.to_owned(),
            name,
            substitution: self.exact.get(&name_at).cloned(),
        };
        Ok(function)
    }

    fn finish_task(
        &mut self,
        obj: &Obj<'_>,
        integration: Integration,
        function: FunctionRef,
        callback: bool,
    ) -> Result<Task, LoadError> {
        if !self.functions.contains(&function) {
            self.functions.push(function.clone());
        }
        let timeout_seconds = obj.integer("TimeoutSeconds", 1, MAX_SECONDS)?;
        let timeout_path = match obj.map.get("TimeoutSecondsPath") {
            None => None,
            Some(_) if timeout_seconds.is_some() => {
                return Err(LoadError::invalid(
                    obj.loc("TimeoutSecondsPath"),
                    "`TimeoutSeconds` and `TimeoutSecondsPath` are exclusive",
                ))
            }
            Some(_) => {
                let text = obj.required_string("TimeoutSecondsPath")?;
                Some(
                    ReferencePath::parse_at(text, "TimeoutSecondsPath").map_err(|source| {
                        LoadError::DataFlow {
                            location: obj.at.clone(),
                            source,
                        }
                    })?,
                )
            }
        };
        let heartbeat_seconds = obj.integer("HeartbeatSeconds", 1, MAX_SECONDS)?;
        if let (Some(h), Some(t)) = (heartbeat_seconds, timeout_seconds) {
            if h >= t {
                return Err(LoadError::invalid(
                    obj.loc("HeartbeatSeconds"),
                    "must be smaller than `TimeoutSeconds`",
                ));
            }
        }
        if heartbeat_seconds.is_some() && !callback {
            return Err(LoadError::unsupported(
                obj.loc("HeartbeatSeconds"),
                "heartbeats are not supported outside `.waitForTaskToken` tasks",
            ));
        }
        Ok(Task {
            integration,
            function,
            callback,
            heartbeat_seconds,
            timeout_seconds,
            timeout_path,
            retry: retriers(obj)?,
            catch: catchers(obj)?,
        })
    }

    fn map_state(&mut self, obj: &Obj<'_>) -> Result<MapState, LoadError> {
        let processor = match (obj.object("Iterator")?, obj.object("ItemProcessor")?) {
            (Some(_), Some(_)) => {
                return Err(LoadError::invalid(
                    &obj.at,
                    "`Iterator` and `ItemProcessor` are exclusive",
                ))
            }
            (None, None) => {
                return Err(LoadError::invalid(
                    &obj.at,
                    "a Map state needs `ItemProcessor` (or the older `Iterator`)",
                ))
            }
            (Some(iterator), None) => {
                let here = obj.loc("Iterator");
                Obj::new(iterator, &here).only(&["StartAt", "States", "Comment"], "an iterator")?;
                self.scope(iterator, &here)?
            }
            (None, Some(processor)) => {
                let here = obj.loc("ItemProcessor");
                let p = Obj::new(processor, &here);
                p.only(
                    &["StartAt", "States", "Comment", "ProcessorConfig"],
                    "an item processor",
                )?;
                inline_only(&p)?;
                self.scope(processor, &here)?
            }
        };
        let items_path = obj
            .string("ItemsPath")?
            .map(|text| ReferencePath::parse_at(text, "ItemsPath"))
            .transpose()
            .map_err(|source| LoadError::DataFlow {
                location: obj.at.clone(),
                source,
            })?;
        let selector = match (obj.map.get("ItemSelector"), obj.map.get("Parameters")) {
            (Some(_), Some(_)) => return Err(LoadError::invalid(
                &obj.at,
                "`ItemSelector` and `Parameters` are exclusive (`Parameters` is its older name)",
            )),
            (Some(v), None) => Some(("ItemSelector", v)),
            (None, Some(v)) => Some(("Parameters", v)),
            (None, None) => None,
        };
        let item_selector = selector
            .map(|(name, v)| {
                if !v.is_object() {
                    return Err(LoadError::invalid(obj.loc(name), "must be an object"));
                }
                Template::compile_at(v, name).map_err(|source| LoadError::DataFlow {
                    location: obj.at.clone(),
                    source,
                })
            })
            .transpose()?;
        Ok(MapState {
            items_path,
            item_selector,
            max_concurrency: obj
                .integer("MaxConcurrency", 0, u64::from(u32::MAX))?
                .unwrap_or(0),
            processor,
            retry: retriers(obj)?,
            catch: catchers(obj)?,
        })
    }
}

/// An item processor's `ProcessorConfig`: only the inline mode is supported.
fn inline_only(p: &Obj<'_>) -> Result<(), LoadError> {
    if let Some(config) = p.object("ProcessorConfig")? {
        let c = Obj::new(config, &p.loc("ProcessorConfig"));
        for key in config.keys() {
            if key != "Mode" {
                return Err(LoadError::unsupported(
                    c.loc(key),
                    format!("`{key}` is for distributed Map, which is not supported"),
                ));
            }
        }
        match c.string("Mode")? {
            None | Some("INLINE") => {}
            Some("DISTRIBUTED") => {
                return Err(LoadError::unsupported(
                    c.loc("Mode"),
                    "distributed Map is not supported; use `INLINE`",
                ))
            }
            Some(other) => {
                return Err(LoadError::invalid(
                    c.loc("Mode"),
                    format!("`{other}` is not a Map mode (INLINE, DISTRIBUTED)"),
                ))
            }
        }
    }
    Ok(())
}

fn at_or_root(at: &str) -> &str {
    if at.is_empty() {
        "(definition)"
    } else {
        at
    }
}
/// A service integration's resource (`rest` after `arn:aws:states:::`, without
/// `.waitForTaskToken`): the optimized integrations and the SDK's, with what the history names.
fn service(
    rest: &str,
    resource: &str,
    resource_at: &str,
    callback: bool,
) -> Result<(Integration, FunctionRef), LoadError> {
    // NB: `aws-sdk:<service>:<action>` is the SDK integration; its history shows
    // `aws-sdk:<service>` as the resource type.
    let (sdk, plain) = match rest.strip_prefix("aws-sdk:") {
        Some(plain) => (true, plain),
        None => (false, rest),
    };
    let (service, action) = plain
        .split_once(':')
        .filter(|(s, a)| {
            !s.is_empty()
                && !a.is_empty()
                && s.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-')
                && a.bytes().all(|b| b.is_ascii_alphanumeric())
        })
        .ok_or_else(|| {
            LoadError::invalid(
                resource_at,
                format!("`{resource}` is not a service integration (`arn:aws:states:::<service>:<action>`)"),
            )
        })?;
    if callback && !sdk && NO_CALLBACK.contains(&service) {
        return Err(LoadError::invalid(
            resource_at,
            format!(
                "the optimized `{service}` integration does not support `.waitForTaskToken` (developer guide, \"Service integration patterns\"); the AWS SDK integration `arn:aws:states:::aws-sdk:{service}:<action>.waitForTaskToken` does"
            ),
        ));
    }
    let function = FunctionRef {
        function: format!("arn:aws:states:::{rest}"),
        name: rest.to_owned(),
        substitution: None,
    };
    let integration = Integration::Service {
        service: if sdk {
            format!("aws-sdk:{service}")
        } else {
            service.to_owned()
        },
        action: action.to_owned(),
    };
    Ok((integration, function))
}

/// `arn:<partition>:states:::<rest>` gives `rest`.
fn states_integration(resource: &str) -> Option<&str> {
    let rest = resource.strip_prefix("arn:")?;
    let (_partition, rest) = rest.split_once(':')?;
    rest.strip_prefix("states:::")
}

fn data_flow(map: &Map<String, Value>, at: &str) -> Result<DataFlow, LoadError> {
    DataFlow::from_state(map).map_err(|source| LoadError::DataFlow {
        location: at.to_owned(),
        source,
    })
}

fn transition(obj: &Obj<'_>, kind: &Kind) -> Result<Option<String>, LoadError> {
    if matches!(kind, Kind::Choice(_) | Kind::Succeed | Kind::Fail(_)) {
        // Their field lists already refuse `Next` and `End`.
        return Ok(None);
    }
    let next = obj.string("Next")?;
    let end = match obj.map.get("End") {
        None => false,
        Some(Value::Bool(b)) => *b,
        Some(_) => return Err(LoadError::invalid(obj.loc("End"), "must be true or false")),
    };
    match (next, end) {
        (Some(_), true) => Err(LoadError::invalid(
            &obj.at,
            "a state cannot have both `Next` and `End: true`",
        )),
        (Some(next), false) => Ok(Some(next.to_owned())),
        (None, true) => Ok(None),
        (None, false) => Err(LoadError::invalid(
            &obj.at,
            "a state must have `Next` or `End: true`",
        )),
    }
}

fn wait(obj: &Obj<'_>) -> Result<Wait, LoadError> {
    let given: Vec<&str> = ["Seconds", "SecondsPath", "Timestamp", "TimestampPath"]
        .into_iter()
        .filter(|k| obj.map.contains_key(*k))
        .collect();
    let [field] = given.as_slice() else {
        return Err(LoadError::invalid(
            &obj.at,
            "a Wait state needs exactly one of `Seconds`, `SecondsPath`, `Timestamp`, `TimestampPath`",
        ));
    };
    let path = |name: &str| -> Result<ReferencePath, LoadError> {
        let text = obj.required_string(name)?;
        ReferencePath::parse_at(text, name).map_err(|source| LoadError::DataFlow {
            location: obj.at.clone(),
            source,
        })
    };
    Ok(match *field {
        "Seconds" => Wait::Seconds(obj.integer("Seconds", 0, MAX_SECONDS)?.unwrap_or(0)),
        "SecondsPath" => Wait::SecondsPath(path("SecondsPath")?),
        "TimestampPath" => Wait::TimestampPath(path("TimestampPath")?),
        _ => {
            let text = obj.required_string("Timestamp")?;
            Wait::Timestamp(timestamp::parse(text).ok_or_else(|| {
                LoadError::invalid(
                    obj.loc("Timestamp"),
                    format!("`{text}` is not an RFC 3339 timestamp with uppercase `T` and `Z`"),
                )
            })?)
        }
    })
}

fn choice_state(obj: &Obj<'_>) -> Result<Choice, LoadError> {
    let rules = obj
        .array("Choices")?
        .filter(|c| !c.is_empty())
        .ok_or_else(|| {
            LoadError::invalid(&obj.at, "`Choices` must be a non-empty array of rules")
        })?;
    let rules = rules
        .iter()
        .enumerate()
        .map(|(i, rule)| choice::compile_top(rule, &obj.loc(&format!("Choices[{i}]"))))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Choice {
        rules,
        default: obj.string("Default")?.map(str::to_owned),
    })
}

fn fail(obj: &Obj<'_>) -> Result<Fail, LoadError> {
    let text = |literal: &str, path: &str| -> Result<Text, LoadError> {
        match (obj.string(literal)?, obj.string(path)?) {
            (Some(_), Some(_)) => Err(LoadError::invalid(
                &obj.at,
                format!("`{literal}` and `{path}` are exclusive"),
            )),
            (Some(s), None) => Ok(Text::Literal(s.to_owned())),
            (None, None) => Ok(Text::None),
            (None, Some(p)) => {
                let wrap = |source| LoadError::DataFlow {
                    location: obj.at.clone(),
                    source,
                };
                if p.starts_with("States.") {
                    Ok(Text::Call {
                        field: path.to_owned(),
                        call: Call::parse_at(p, path).map_err(wrap)?,
                    })
                } else {
                    Ok(Text::Path(Path::parse_at(p, path).map_err(wrap)?))
                }
            }
        }
    };
    Ok(Fail {
        error: text("Error", "ErrorPath")?,
        cause: text("Cause", "CausePath")?,
    })
}

fn error_equals(obj: &Obj<'_>) -> Result<Vec<String>, LoadError> {
    let at = obj.loc("ErrorEquals");
    let names = obj
        .array("ErrorEquals")?
        .filter(|a| !a.is_empty())
        .ok_or_else(|| {
            LoadError::invalid(
                &at,
                "`ErrorEquals` must be a non-empty array of error names",
            )
        })?;
    let names = names
        .iter()
        .map(|n| match n.as_str() {
            Some(s) if !s.is_empty() => Ok(s.to_owned()),
            _ => Err(LoadError::invalid(
                &at,
                "error names must be non-empty strings",
            )),
        })
        .collect::<Result<Vec<_>, _>>()?;
    if names.len() > 1 && names.iter().any(|n| n == crate::runtime::STATES_ALL) {
        return Err(LoadError::invalid(
            at,
            "`States.ALL` must appear alone in `ErrorEquals`",
        ));
    }
    Ok(names)
}

/// Checks that `States.ALL` is only in the last element of `Retry`/`Catch`.
fn states_all_last(list: &[Vec<String>], at: &str) -> Result<(), LoadError> {
    for (i, names) in list.iter().enumerate() {
        if i + 1 < list.len() && names.iter().any(|n| n == crate::runtime::STATES_ALL) {
            return Err(LoadError::invalid(
                format!("{at}[{i}].ErrorEquals"),
                "`States.ALL` must be in the last element",
            ));
        }
    }
    Ok(())
}

fn retriers(obj: &Obj<'_>) -> Result<Vec<Retrier>, LoadError> {
    let Some(list) = obj.array("Retry")? else {
        return Ok(Vec::new());
    };
    let out = list
        .iter()
        .enumerate()
        .map(|(i, item)| {
            let here = obj.loc(&format!("Retry[{i}]"));
            let map = item
                .as_object()
                .ok_or_else(|| LoadError::invalid(&here, "a retrier must be an object"))?;
            let r = Obj::new(map, &here);
            r.only(
                &[
                    "ErrorEquals",
                    "IntervalSeconds",
                    "MaxAttempts",
                    "BackoffRate",
                    "MaxDelaySeconds",
                    "JitterStrategy",
                    "Comment",
                ],
                "a retrier",
            )?;
            r.string("Comment")?;
            let backoff_rate = match map.get("BackoffRate") {
                None => 2.0,
                Some(v) => match v.as_f64() {
                    Some(rate) if rate.is_finite() && rate >= 1.0 => rate,
                    _ => {
                        return Err(LoadError::invalid(
                            r.loc("BackoffRate"),
                            format!("must be a number of at least 1.0, got `{v}`"),
                        ))
                    }
                },
            };
            let jitter = match r.string("JitterStrategy")? {
                None | Some("NONE") => Jitter::None,
                Some("FULL") => Jitter::Full,
                Some(other) => {
                    return Err(LoadError::invalid(
                        r.loc("JitterStrategy"),
                        format!("`{other}` is not a jitter strategy (FULL, NONE)"),
                    ))
                }
            };
            Ok(Retrier {
                error_equals: error_equals(&r)?,
                interval_seconds: r.integer("IntervalSeconds", 1, MAX_SECONDS)?.unwrap_or(1),
                max_attempts: r.integer("MaxAttempts", 0, MAX_SECONDS)?.unwrap_or(3),
                backoff_rate,
                max_delay_seconds: r.integer("MaxDelaySeconds", 1, MAX_DELAY_SECONDS)?,
                jitter,
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    let names: Vec<Vec<String>> = out.iter().map(|r| r.error_equals.clone()).collect();
    states_all_last(&names, &obj.loc("Retry"))?;
    Ok(out)
}

fn catchers(obj: &Obj<'_>) -> Result<Vec<Catcher>, LoadError> {
    let Some(list) = obj.array("Catch")? else {
        return Ok(Vec::new());
    };
    let out = list
        .iter()
        .enumerate()
        .map(|(i, item)| {
            let here = obj.loc(&format!("Catch[{i}]"));
            let map = item
                .as_object()
                .ok_or_else(|| LoadError::invalid(&here, "a catcher must be an object"))?;
            let c = Obj::new(map, &here);
            c.only(
                &["ErrorEquals", "Next", "ResultPath", "Comment"],
                "a catcher",
            )?;
            c.string("Comment")?;
            Ok(Catcher {
                error_equals: error_equals(&c)?,
                result_path: ResultPath::from_field(map.get("ResultPath")).map_err(|source| {
                    LoadError::DataFlow {
                        location: here.clone(),
                        source,
                    }
                })?,
                next: c.required_string("Next")?.to_owned(),
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    let names: Vec<Vec<String>> = out.iter().map(|c| c.error_equals.clone()).collect();
    states_all_last(&names, &obj.loc("Catch"))?;
    Ok(out)
}

/// Every transition names a state of this scope, every state is reachable from `StartAt`
/// and the scope can end.
fn check_transitions(scope: &Scope, obj: &Obj<'_>, states_at: &str) -> Result<(), LoadError> {
    let known = |target: &str, location: String| -> Result<(), LoadError> {
        if scope.states.contains_key(target) {
            Ok(())
        } else {
            Err(LoadError::UnknownState {
                location,
                target: target.to_owned(),
            })
        }
    };
    known(&scope.start_at, obj.loc("StartAt"))?;
    let mut edges: HashMap<&str, Vec<&str>> = HashMap::new();
    let mut names: Vec<&String> = scope.states.keys().collect();
    names.sort();
    for name in &names {
        let state = &scope.states[*name];
        let at = format!("{states_at}.{name}");
        let out = edges.entry(name.as_str()).or_default();
        if let Some(next) = &state.next {
            known(next, format!("{at}.Next"))?;
            out.push(next);
        }
        let catch = match &state.kind {
            Kind::Task(t) => t.catch.as_slice(),
            Kind::Parallel(p) => p.catch.as_slice(),
            Kind::Map(m) => m.catch.as_slice(),
            _ => &[],
        };
        for (i, c) in catch.iter().enumerate() {
            known(&c.next, format!("{at}.Catch[{i}].Next"))?;
            out.push(&c.next);
        }
        if let Kind::Choice(choice) = &state.kind {
            for (i, (_, next)) in choice.rules.iter().enumerate() {
                known(next, format!("{at}.Choices[{i}].Next"))?;
                out.push(next);
            }
            if let Some(default) = &choice.default {
                known(default, format!("{at}.Default"))?;
                out.push(default);
            }
        }
    }
    let mut seen: HashSet<&str> = HashSet::from([scope.start_at.as_str()]);
    let mut queue = VecDeque::from([scope.start_at.as_str()]);
    while let Some(name) = queue.pop_front() {
        for next in edges.get(name).into_iter().flatten() {
            if seen.insert(next) {
                queue.push_back(next);
            }
        }
    }
    if let Some(unreached) = names.iter().find(|n| !seen.contains(n.as_str())) {
        return Err(LoadError::Unreachable {
            location: format!("{states_at}.{unreached}"),
            state: (*unreached).clone(),
        });
    }
    let terminal = scope.states.values().any(|s| {
        matches!(s.kind, Kind::Succeed | Kind::Fail(_))
            || (s.next.is_none() && !matches!(s.kind, Kind::Choice(_)))
    });
    if !terminal {
        return Err(LoadError::invalid(
            states_at,
            "no terminal state (`End: true`, Succeed or Fail): the machine could never end",
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn retry_delays_grow_by_the_backoff_rate_up_to_the_cap() {
        let r = Retrier {
            error_equals: vec![],
            interval_seconds: 3,
            max_attempts: 5,
            backoff_rate: 1.5,
            max_delay_seconds: Some(6),
            jitter: Jitter::None,
        };
        assert_eq!(r.base_delay(0), 3.0);
        assert_eq!(r.base_delay(1), 4.5);
        assert_eq!(r.base_delay(2), 6.0);
        assert_eq!(r.base_delay(40), 6.0);
        let huge = Retrier {
            max_delay_seconds: None,
            backoff_rate: 1e300,
            ..r
        };
        assert_eq!(huge.base_delay(5), MAX_SECONDS as f64);
    }

    #[test]
    fn integrations_are_recognised_by_partition() {
        assert_eq!(
            states_integration("arn:aws:states:::lambda:invoke"),
            Some("lambda:invoke")
        );
        assert_eq!(
            states_integration("arn:aws-cn:states:::sqs:sendMessage"),
            Some("sqs:sendMessage")
        );
        assert_eq!(
            states_integration("arn:aws:lambda:us-east-1:1:function:f"),
            None
        );
    }

    #[test]
    fn a_minimal_machine_loads() {
        let sm = StateMachine::load(
            &json!({"StartAt": "A", "States": {"A": {"Type": "Succeed"}}}),
            &HashMap::new(),
        )
        .unwrap();
        assert_eq!(sm.start_at(), "A");
        assert_eq!(sm.name(), "StateMachine");
        assert_eq!(sm.clone().with_name("x").name(), "x");
    }
}
