//! Runs a loaded state machine: the states' semantics, retries and catchers, the context
//! object, scaled time, the deadline and cancellation.

use std::collections::{BTreeSet, HashMap};
use std::fmt;
use std::future::Future;
use std::pin::Pin;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use lb_asl::{Env, RandomSource, ReferencePath};
use serde_json::{json, Map, Value};
use time::OffsetDateTime;
use tokio::sync::{mpsc, watch};
use tokio::task::{JoinHandle, JoinSet};

use crate::callback::{CallbackError, Callbacks, Outcome, Pending};
use crate::definition::{
    Catcher, Choice, Integration, Jitter, Kind, MapState, Parallel, Retrier, Scope, State,
    StateMachine, Task, Text, Wait,
};
use crate::error::{OptionsError, StartError};
use crate::history::{EventCallback, EventStream, EventType, FinishGuard, HistoryEvent, Recorder};
use crate::runtime::{matches, Failure, STATES_HEARTBEAT_TIMEOUT, STATES_TIMEOUT};
use crate::tasks::{FunctionRef, Tasks};
use crate::timestamp;
use crate::versions::{Registry, Resolved};

/// How an executor runs executions.
#[derive(Clone)]
pub struct Options {
    /// Multiplies every duration the definition states: Wait times, retry intervals, Task
    /// `TimeoutSeconds` and the definition's `TimeoutSeconds` (0.01 makes a 60 s Wait last
    /// 0.6 s). Must be finite and greater than 0.
    pub time_scale: f64,
    /// Wall-clock limit of one execution (not scaled); past it the execution ends
    /// `TIMED_OUT`. `None`: only the definition's own `TimeoutSeconds` applies.
    pub deadline: Option<Duration>,
    /// Region in the ARNs (`$$.Execution.Id`, `$$.StateMachine.Id`) and events.
    pub region: String,
    /// Account in the ARNs.
    pub account_id: String,
    /// `$$.Execution.RoleArn`; `None`: a placeholder role in `account_id`.
    pub role_arn: Option<String>,
    /// History events per execution, the final one included (AWS: 25,000). Reaching it fails
    /// the execution with `States.Runtime`.
    pub max_history_events: usize,
    /// Largest state input/output and task result, in bytes of compact JSON (AWS: 256 KiB).
    /// Beyond it the execution fails with `States.DataLimitExceeded`.
    pub max_payload_bytes: usize,
    /// Seed of the random numbers (retry jitter, `States.UUID`, `States.MathRandom`);
    /// `None`: from entropy.
    pub random_seed: Option<u64>,
    /// Called with every history event as it is recorded (live progress).
    pub on_event: Option<EventCallback>,
    /// Whether a function Task's `TimeoutSeconds` is scaled too (the default). Off, it stays
    /// the Lambda's own time, as real as the handler's work in-process: a handler waiting on
    /// something time does not compress (a budget of requests a minute) is not cut short,
    /// while callback waits and Wait states still scale.
    pub scale_invocation_timeouts: bool,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            time_scale: 1.0,
            deadline: None,
            region: "us-east-1".into(),
            account_id: "123456789012".into(),
            role_arn: None,
            max_history_events: 25_000,
            max_payload_bytes: 256 * 1024,
            random_seed: None,
            on_event: None,
            scale_invocation_timeouts: true,
        }
    }
}

impl fmt::Debug for Options {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Options")
            .field("time_scale", &self.time_scale)
            .field("deadline", &self.deadline)
            .field("region", &self.region)
            .field("account_id", &self.account_id)
            .field("role_arn", &self.role_arn)
            .field("max_history_events", &self.max_history_events)
            .field("max_payload_bytes", &self.max_payload_bytes)
            .field("random_seed", &self.random_seed)
            .field("on_event", &self.on_event.as_ref().map(|_| "<callback>"))
            .field("scale_invocation_timeouts", &self.scale_invocation_timeouts)
            .finish()
    }
}

/// How an execution ended, with Step Functions' status names.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Status {
    /// Reached a Succeed state or an `End`.
    Succeeded,
    /// An error nothing caught, or a Fail state.
    Failed,
    /// Past the deadline or the definition's `TimeoutSeconds`.
    TimedOut,
    /// Cancelled through [`Execution::cancel`].
    Aborted,
}

impl Status {
    /// `SUCCEEDED`, `FAILED`, `TIMED_OUT` or `ABORTED`.
    pub fn as_str(self) -> &'static str {
        match self {
            Status::Succeeded => "SUCCEEDED",
            Status::Failed => "FAILED",
            Status::TimedOut => "TIMED_OUT",
            Status::Aborted => "ABORTED",
        }
    }
}

impl fmt::Display for Status {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// The outcome of an execution.
#[derive(Debug, Clone, PartialEq)]
pub struct ExecutionResult {
    /// How it ended.
    pub status: Status,
    /// The output (when it succeeded).
    pub output: Option<Value>,
    /// The error name (when it failed or timed out).
    pub error: Option<String>,
    /// The cause (when it failed and there is one).
    pub cause: Option<String>,
    /// Every event, in order.
    pub history: Vec<HistoryEvent>,
    /// The execution's ARN.
    pub execution_arn: String,
    /// When it started and stopped.
    pub start_date: OffsetDateTime,
    /// When it stopped.
    pub stop_date: OffsetDateTime,
}

impl ExecutionResult {
    /// How many events of `event_type` the history holds.
    pub fn count(&self, event_type: EventType) -> usize {
        self.history
            .iter()
            .filter(|e| e.event_type == event_type)
            .count()
    }

    /// The states entered, in order (a CLI's stage list).
    pub fn states_entered(&self) -> Vec<&str> {
        self.history
            .iter()
            .filter(|e| e.event_type.is_state_entered())
            .filter_map(HistoryEvent::state_name)
            .collect()
    }
}

/// Runs state machines with in-process task handlers.
#[derive(Clone)]
pub struct Executor {
    tasks: Arc<dyn Tasks>,
    options: Arc<Options>,
    callbacks: Arc<Callbacks>,
    known: Arc<Known>,
}

/// The executions this executor started, by ARN, as `DescribeExecution`,
/// `GetExecutionHistory` and `StopExecution` find them; and who hears of their ends.
#[derive(Default)]
struct Known {
    executions: Mutex<HashMap<String, Started>>,
    listeners: Mutex<Vec<mpsc::UnboundedSender<Value>>>,
    /// The state machines executions were started of, with the versions and aliases
    /// published of them (for `StartExecution`).
    registry: Mutex<Registry>,
}

struct Started {
    recorder: Arc<Recorder>,
    cancel: watch::Sender<bool>,
    input: Value,
    start_date: OffsetDateTime,
    /// Its result once it ended.
    ended: watch::Receiver<Option<ExecutionResult>>,
    /// The version and alias it was started through.
    version_arn: Option<String>,
    alias_arn: Option<String>,
}

/// An execution as `DescribeExecution` tells it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Described {
    /// `None` while it runs.
    pub status: Option<Status>,
    /// The error it failed or timed out with.
    pub error: Option<String>,
    /// Its output, once it succeeded.
    pub output: Option<Value>,
    /// The state machine version it runs (`stateMachineVersionArn`): `None` when it was
    /// started through the unqualified ARN.
    pub version_arn: Option<String>,
    /// The alias it was started through (`stateMachineAliasArn`).
    pub alias_arn: Option<String>,
}

impl Known {
    fn registry(&self) -> std::sync::MutexGuard<'_, Registry> {
        self.registry.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Keeps an execution that starts; one started through the unqualified ARN makes its
    /// state machine the latest revision.
    fn remember(
        &self,
        machine_arn: &str,
        machine: &StateMachine,
        execution_arn: &str,
        started: Started,
    ) {
        if started.version_arn.is_none() {
            self.registry().revise(machine_arn, machine);
        }
        self.executions
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(execution_arn.to_owned(), started);
    }

    fn with<T>(&self, arn: &str, f: impl FnOnce(&Started) -> T) -> Option<T> {
        let executions = self
            .executions
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        executions.get(arn).map(f)
    }

    /// Sends the "Execution Status Change" event of an ended execution to every listener
    /// (those gone are forgotten).
    fn ended(&self, event: Value) {
        let mut listeners = self
            .listeners
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        listeners.retain(|l| l.send(event.clone()).is_ok());
    }
}

/// The EventBridge event Step Functions sends when an execution ends ("Step Functions
/// Execution Status Change", in the Step Functions developer guide's "Automating Step
/// Functions event delivery with EventBridge"): `detail` carries the execution's ARN, its
/// state machine's, its name, status, start and stop dates in epoch milliseconds, its input
/// as JSON text, and the error and cause of a failure.
pub fn status_change_event(
    result: &ExecutionResult,
    state_machine_arn: &str,
    input: &Value,
) -> Value {
    let epoch_ms = |t: OffsetDateTime| (t.unix_timestamp_nanos() / 1_000_000) as i64;
    let region = result.execution_arn.split(':').nth(3).unwrap_or_default();
    let account = result.execution_arn.split(':').nth(4).unwrap_or_default();
    let name = result.execution_arn.rsplit(':').next().unwrap_or_default();
    json!({
        "version": "0",
        "id": format!("{}-{}", name, epoch_ms(result.stop_date)),
        "detail-type": "Step Functions Execution Status Change",
        "source": "aws.states",
        "account": account,
        "time": timestamp::format(result.stop_date),
        "region": region,
        "resources": [result.execution_arn],
        "detail": {
            "executionArn": result.execution_arn,
            "stateMachineArn": state_machine_arn,
            "name": name,
            "status": result.status.as_str(),
            "startDate": epoch_ms(result.start_date),
            "stopDate": epoch_ms(result.stop_date),
            "input": input.to_string(),
            "inputDetails": {"included": true},
            "output": result.output.as_ref().map(Value::to_string),
            "outputDetails": result.output.as_ref().map(|_| json!({"included": true})),
            "error": result.error,
            "cause": result.cause,
        }
    })
}

impl fmt::Debug for Executor {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Executor")
            .field("options", &self.options)
            .finish_non_exhaustive()
    }
}

impl Executor {
    /// An executor calling `tasks`' handlers.
    pub fn new(tasks: impl Tasks, options: Options) -> Result<Executor, OptionsError> {
        if !(options.time_scale.is_finite() && options.time_scale > 0.0) {
            return Err(OptionsError::InvalidTimeScale(options.time_scale));
        }
        if options.max_history_events == 0 {
            return Err(OptionsError::ZeroLimit("max_history_events"));
        }
        if options.max_payload_bytes == 0 {
            return Err(OptionsError::ZeroLimit("max_payload_bytes"));
        }
        Ok(Executor {
            tasks: Arc::new(tasks),
            options: Arc::new(options),
            callbacks: Arc::new(Callbacks::default()),
            known: Arc::default(),
        })
    }

    /// Every "Execution Status Change" event of the executions started from now on (see
    /// [`status_change_event`]), as EventBridge would deliver them to a rule's target.
    pub fn status_changes(&self) -> mpsc::UnboundedReceiver<Value> {
        let (tx, rx) = mpsc::unbounded_channel();
        self.known
            .listeners
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(tx);
        rx
    }

    /// `DescribeExecution`: `None` for an ARN this executor never started.
    pub fn describe(&self, arn: &str) -> Option<Described> {
        self.known.with(arn, |started| {
            let history = started.recorder.snapshot();
            let end = history
                .iter()
                .rev()
                .find(|e| e.event_type.is_execution_end());
            Described {
                status: end.map(|e| match e.event_type {
                    EventType::ExecutionSucceeded => Status::Succeeded,
                    EventType::ExecutionAborted => Status::Aborted,
                    EventType::ExecutionTimedOut => Status::TimedOut,
                    _ => Status::Failed,
                }),
                error: end.and_then(|e| e.error().map(str::to_owned)),
                output: end
                    .filter(|e| e.event_type == EventType::ExecutionSucceeded)
                    .and_then(|e| e.details.get("output").cloned()),
                version_arn: started.version_arn.clone(),
                alias_arn: started.alias_arn.clone(),
            }
        })
    }

    /// `GetExecutionHistory`: `None` for an ARN this executor never started.
    pub fn history_of(&self, arn: &str) -> Option<Vec<HistoryEvent>> {
        self.known.with(arn, |started| started.recorder.snapshot())
    }

    /// `StopExecution`: the execution ends `ABORTED` (running handlers are dropped); `false`
    /// for an ARN this executor never started.
    pub fn stop(&self, arn: &str) -> bool {
        self.known
            .with(arn, |started| started.cancel.send_replace(true))
            .is_some()
    }

    /// `SendTaskSuccess`: the waiting `.waitForTaskToken` task of `token` succeeds with
    /// `output` as its result.
    pub fn send_task_success(&self, token: &str, output: Value) -> Result<(), CallbackError> {
        self.callbacks
            .success(token, output, self.options.max_payload_bytes)
    }

    /// `SendTaskFailure`: the waiting task of `token` fails with `error` and `cause`
    /// (retried and caught like any task error).
    pub fn send_task_failure(
        &self,
        token: &str,
        error: &str,
        cause: &str,
    ) -> Result<(), CallbackError> {
        self.callbacks.failure(token, error, cause)
    }

    /// `SendTaskHeartbeat`: restarts the waiting task's `HeartbeatSeconds`.
    pub fn send_task_heartbeat(&self, token: &str) -> Result<(), CallbackError> {
        self.callbacks.heartbeat(token)
    }

    /// The functions of `state_machine` no handler is registered for (each would fail with
    /// `Lambda.ResourceNotFoundException` when reached).
    pub fn missing_tasks(&self, state_machine: &StateMachine) -> Vec<FunctionRef> {
        state_machine
            .functions()
            .iter()
            .filter(|f| self.tasks.handler(f).is_none())
            .cloned()
            .collect()
    }

    /// The ARN of a Step Functions resource of this executor's region and account.
    fn arn(&self, kind: &str, rest: &str) -> String {
        let options = &self.options;
        format!(
            "arn:aws:states:{}:{}:{kind}:{rest}",
            options.region, options.account_id
        )
    }

    /// The ARN of execution `name` of the state machine called `machine`.
    fn execution_arn(&self, machine: &str, name: &str) -> String {
        self.arn("execution", &format!("{machine}:{name}"))
    }

    /// The role executions run as: the configured one, or Step Functions' default name.
    fn role_arn(&self) -> String {
        self.options.role_arn.clone().unwrap_or_else(|| {
            format!(
                "arn:aws:iam::{}:role/StepFunctionsExecutionRole",
                self.options.account_id
            )
        })
    }

    /// What an execution shares across its states: its context object's `Execution` and
    /// `StateMachine`, with this executor's tasks, options and callbacks.
    fn run_of(&self, recorder: Arc<Recorder>, execution: Value, state_machine: Value) -> Arc<Run> {
        Arc::new(Run {
            tasks: self.tasks.clone(),
            options: self.options.clone(),
            callbacks: self.callbacks.clone(),
            recorder,
            random: match self.options.random_seed {
                Some(seed) => RandomSource::seeded(seed),
                None => RandomSource::from_entropy(),
            },
            execution,
            state_machine,
        })
    }

    /// Starts an execution named `name` with `input` on the current Tokio runtime, through
    /// the state machine's unqualified ARN: `state_machine` becomes its latest revision.
    pub fn start(
        &self,
        state_machine: &StateMachine,
        name: &str,
        input: Value,
    ) -> Result<Execution, StartError> {
        self.launch(
            Resolved {
                machine: state_machine.clone(),
                version_arn: None,
                alias_arn: None,
            },
            name,
            input,
        )
    }

    /// `PublishStateMachineVersion`: `state_machine` becomes the latest revision of the state
    /// machine of its name and a version of it. The version's ARN.
    pub fn publish(&self, state_machine: &StateMachine) -> String {
        let arn = self.arn("stateMachine", state_machine.name());
        self.known.registry().publish(&arn, state_machine)
    }

    /// `CreateStateMachineAlias` or `UpdateStateMachineAlias`: `alias` names `version_arn`
    /// from now on; executions started through it before keep their version. The alias's ARN.
    pub fn point_alias(&self, alias: &str, version_arn: &str) -> Result<String, StartError> {
        self.known.registry().point(alias, version_arn)
    }

    /// The version an alias names now.
    pub fn alias_target(&self, alias_arn: &str) -> Option<String> {
        self.known.registry().target(alias_arn)
    }

    /// Starts an execution through `arn`: a state machine's unqualified ARN (its latest
    /// revision), a version's or an alias's (the version it names now).
    pub fn start_arn(&self, arn: &str, name: &str, input: Value) -> Result<Execution, StartError> {
        let resolved = self.known.registry().resolve(arn)?;
        self.launch(resolved, name, input)
    }

    /// Whether an execution `name` with `input` may start (the name's rules, the payload
    /// quota, a runtime to run on): the runtime.
    fn may_start(&self, name: &str, input: &Value) -> Result<tokio::runtime::Handle, StartError> {
        validate_name(name)?;
        let size = payload_size(input);
        if size > self.options.max_payload_bytes {
            return Err(StartError::InputTooLarge {
                size,
                limit: self.options.max_payload_bytes,
            });
        }
        tokio::runtime::Handle::try_current().map_err(|_| StartError::NoRuntime)
    }

    fn launch(
        &self,
        resolved: Resolved,
        name: &str,
        input: Value,
    ) -> Result<Execution, StartError> {
        let Resolved {
            machine: ref state_machine,
            version_arn,
            alias_arn,
        } = resolved;
        let runtime = self.may_start(name, &input)?;
        let state_machine_arn = self.arn("stateMachine", state_machine.name());
        let execution_arn = self.execution_arn(state_machine.name(), name);
        let role_arn = self.role_arn();
        let start_date = OffsetDateTime::now_utc();
        let recorder = Arc::new(Recorder::new(
            self.options.max_history_events,
            self.options.on_event.clone(),
        ));
        let execution = json!({
            "Id": execution_arn,
            "Input": input,
            "Name": name,
            "RoleArn": role_arn,
            "StartTime": timestamp::format(start_date),
            "RedriveCount": 0,
        });
        let machine = json!({"Id": state_machine_arn, "Name": state_machine.name()});
        let run = self.run_of(recorder.clone(), execution, machine);
        let (cancel, cancelled) = watch::channel(false);
        let deadline = [
            self.options.deadline,
            state_machine
                .timeout_seconds()
                .map(|s| run.scaled(s as f64)),
        ]
        .into_iter()
        .flatten()
        .min();
        let root = state_machine.definition.root.clone();
        tracing::info!(execution = %name, state_machine = %state_machine.name(), "execution started");
        let (ended_tx, ended) = watch::channel(None);
        let started_details = started_details(&input, &role_arn, &version_arn, &alias_arn);
        let started = Started {
            recorder: recorder.clone(),
            cancel: cancel.clone(),
            input: input.clone(),
            start_date,
            ended,
            version_arn,
            alias_arn,
        };
        self.known
            .remember(&state_machine_arn, state_machine, &execution_arn, started);
        let known = self.known.clone();
        let execution = execute(
            run,
            root,
            input.clone(),
            started_details,
            cancelled,
            deadline,
            execution_arn.clone(),
            start_date,
        );
        let join = runtime.spawn(async move {
            let result = execution.await;
            known.ended(status_change_event(&result, &state_machine_arn, &input));
            ended_tx.send_replace(Some(result.clone()));
            result
        });
        Ok(Execution {
            arn: execution_arn,
            name: name.to_owned(),
            recorder,
            cancel,
            join,
        })
    }

    /// `StartExecution` as the API answers it, for a state machine this executor has run an
    /// execution of: `{ExecutionArn, StartDate}` (the date in epoch seconds, as the optimized
    /// integration returns it). A name already taken is the same execution when it still runs
    /// with the same input (the call is idempotent), and `ExecutionAlreadyExists` otherwise
    /// (API reference, `StartExecution`).
    pub fn start_execution(
        &self,
        state_machine_arn: &str,
        name: &str,
        input: Value,
    ) -> Result<Value, StartError> {
        let resolved = self.known.registry().resolve(state_machine_arn)?;
        let arn = self.execution_arn(resolved.machine.name(), name);
        let response = |start: OffsetDateTime| {
            json!({
                "ExecutionArn": arn,
                "StartDate": start.unix_timestamp_nanos() as f64 / 1e9,
            })
        };
        let taken = self.known.with(&arn, |started| {
            let running = started.ended.borrow().is_none();
            (running && started.input == input).then_some(started.start_date)
        });
        match taken {
            Some(Some(start)) => return Ok(response(start)),
            Some(None) => {
                return Err(StartError::ExecutionAlreadyExists {
                    name: name.to_owned(),
                })
            }
            None => {}
        }
        let execution = self.launch(resolved, name, input)?;
        let start = self
            .known
            .with(execution.arn(), |started| started.start_date)
            .unwrap_or_else(OffsetDateTime::now_utc);
        // Detached: it runs on; its end is found through `wait_for`.
        drop(execution);
        Ok(response(start))
    }

    /// The result of execution `arn` once it ended (`None` for an ARN this executor never
    /// started).
    pub async fn wait_for(&self, arn: &str) -> Option<ExecutionResult> {
        let mut ended = self.known.with(arn, |started| started.ended.clone())?;
        let result = ended.wait_for(Option::is_some).await.ok()?.clone();
        result
    }

    /// Starts an execution and waits for its result.
    pub async fn run(
        &self,
        state_machine: &StateMachine,
        name: &str,
        input: Value,
    ) -> Result<ExecutionResult, StartError> {
        Ok(self.start(state_machine, name, input)?.wait().await)
    }
}

/// A running execution. Dropping the handle leaves it running.
pub struct Execution {
    arn: String,
    name: String,
    recorder: Arc<Recorder>,
    cancel: watch::Sender<bool>,
    join: JoinHandle<ExecutionResult>,
}

impl fmt::Debug for Execution {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Execution")
            .field("arn", &self.arn)
            .finish_non_exhaustive()
    }
}

impl Execution {
    /// The execution's ARN (`$$.Execution.Id`).
    pub fn arn(&self) -> &str {
        &self.arn
    }

    /// The execution's name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Every event from the first, then each as it is recorded, until the execution ends.
    pub fn events(&self) -> EventStream {
        EventStream::new(self.recorder.clone())
    }

    /// The events recorded so far.
    pub fn history(&self) -> Vec<HistoryEvent> {
        self.recorder.snapshot()
    }

    /// Stops the execution (status `ABORTED`); running handlers are dropped. (The same as
    /// [`Executor::stop`] with its ARN.)
    pub fn cancel(&self) {
        self.cancel.send_replace(true);
    }

    /// Waits for the execution to end.
    pub async fn wait(self) -> ExecutionResult {
        let Execution {
            arn,
            recorder,
            join,
            ..
        } = self;
        match join.await {
            Ok(result) => result,
            // NB: only a bug in the executor gets here (handler panics are caught per task).
            Err(e) => {
                let now = OffsetDateTime::now_utc();
                ExecutionResult {
                    status: Status::Failed,
                    output: None,
                    error: Some("States.Runtime".into()),
                    cause: Some(format!("the executor stopped unexpectedly: {e}")),
                    history: recorder.snapshot(),
                    execution_arn: arn,
                    start_date: now,
                    stop_date: now,
                }
            }
        }
    }
}

/// Step Functions' execution name rules.
fn validate_name(name: &str) -> Result<(), StartError> {
    let refuse = |reason: &str| {
        Err(StartError::InvalidName {
            name: name.to_owned(),
            reason: reason.to_owned(),
        })
    };
    let length = name.chars().count();
    if length == 0 || length > 80 {
        return refuse("must have 1 to 80 characters");
    }
    if let Some(c) = name
        .chars()
        .find(|c| c.is_whitespace() || c.is_control() || "<>{}[]?*\"#%\\^|~`$&,;:/".contains(*c))
    {
        return refuse(&format!("`{}` is not allowed", c.escape_default()));
    }
    Ok(())
}

fn payload_size(value: &Value) -> usize {
    serde_json::to_vec(value).map_or(usize::MAX, |v| v.len())
}

/// Aborts a spawned handler when its caller stops waiting (timeout, cancellation, a
/// sibling branch failing).
struct AbortOnDrop<T>(JoinHandle<T>);

impl<T> Drop for AbortOnDrop<T> {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// What one execution shares across its states and branches.
struct Run {
    tasks: Arc<dyn Tasks>,
    options: Arc<Options>,
    callbacks: Arc<Callbacks>,
    recorder: Arc<Recorder>,
    random: RandomSource,
    execution: Value,
    state_machine: Value,
}

/// The previous event of one line of execution (the machine, a branch, an iteration).
#[derive(Debug, Clone, Copy)]
struct Thread {
    last: u64,
}

type ScopeFuture = Pin<Box<dyn Future<Output = (Result<Value, Failure>, Thread)> + Send>>;

enum Recovery {
    Retry,
    Caught { next: String, output: Value },
}

enum Invocation {
    Failed(Failure),
    TimedOut,
}

/// How a callback task's wait ended.
enum CallbackEnd {
    Reported(Outcome),
    TimedOut(&'static str),
}

/// How a task's history events name what it runs.
struct Resource<'a> {
    /// A Lambda function named by its ARN: its events are the `LambdaFunction*` ones.
    lambda: bool,
    /// `resourceType`: `lambda` or the service.
    kind: &'a str,
    /// `resource`: the action, with `.waitForTaskToken` for a callback task.
    name: String,
}

impl Resource<'_> {
    fn of(task: &Task) -> Resource<'_> {
        let (kind, action) = match &task.integration {
            Integration::Service { service, action } => (service.as_str(), action.as_str()),
            _ => ("lambda", "invoke"),
        };
        Resource {
            lambda: task.integration == Integration::LambdaArn,
            kind,
            name: match task.callback {
                true => format!("{action}.waitForTaskToken"),
                false => action.to_owned(),
            },
        }
    }

    /// A task event's details: the resource's names, then `extra`'s fields.
    fn details(&self, extra: Value) -> Value {
        let mut details = json!({"resourceType": self.kind, "resource": self.name});
        if let (Value::Object(d), Value::Object(e)) = (&mut details, extra) {
            d.extend(e);
        }
        details
    }

    /// Of a pair of events (a Lambda function's, a task's), the one this resource records,
    /// with its details.
    fn event(&self, (lambda, task): (EventType, EventType), extra: Value) -> (EventType, Value) {
        match self.lambda {
            true => (lambda, extra),
            false => (task, self.details(extra)),
        }
    }
}

/// Closes a task token however its attempt ends (a result, a timeout, an abort).
struct CloseOnDrop(Arc<Callbacks>, String);

impl Drop for CloseOnDrop {
    fn drop(&mut self) {
        self.0.close(&self.1);
    }
}

#[allow(clippy::too_many_arguments)]
async fn execute(
    run: Arc<Run>,
    root: Arc<Scope>,
    input: Value,
    started: Value,
    mut cancelled: watch::Receiver<bool>,
    deadline: Option<Duration>,
    execution_arn: String,
    start_date: OffsetDateTime,
) -> ExecutionResult {
    let recorder = run.recorder.clone();
    let _finish = FinishGuard(recorder.clone());
    let outcome = match recorder.push(0, EventType::ExecutionStarted, started) {
        Err(failure) => Err((failure, 0)),
        Ok(_) => {
            // NB: AWS links the first state to no event (previousEventId 0).
            let machine = run.clone().run_scope(root, input, Thread { last: 0 });
            let cancel = async {
                if cancelled.wait_for(|c| *c).await.is_err() {
                    // The handle is gone: nobody can cancel any more.
                    std::future::pending::<()>().await;
                }
            };
            let timeout = async {
                match deadline {
                    Some(d) => tokio::time::sleep(d).await,
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                (result, thread) = machine => result
                    .map(|v| (v, thread.last))
                    .map_err(|f| (f, thread.last)),
                () = cancel => {
                    let last = recorder.last_id();
                    recorder.push_final(last, EventType::ExecutionAborted, Value::Null);
                    return finish(&recorder, Status::Aborted, None, None, None, execution_arn, start_date);
                }
                () = timeout => {
                    let last = recorder.last_id();
                    recorder.push_final(last, EventType::ExecutionTimedOut, json!({"error": STATES_TIMEOUT}));
                    return finish(&recorder, Status::TimedOut, None, Some(STATES_TIMEOUT.into()), None, execution_arn, start_date);
                }
            }
        }
    };
    match outcome {
        Ok((output, last)) => {
            recorder.push_final(
                last,
                EventType::ExecutionSucceeded,
                json!({ "output": output }),
            );
            finish(
                &recorder,
                Status::Succeeded,
                Some(output),
                None,
                None,
                execution_arn,
                start_date,
            )
        }
        Err((failure, last)) => {
            recorder.push_final(last, EventType::ExecutionFailed, failure_details(&failure));
            let error = (!failure.error.is_empty()).then_some(failure.error);
            finish(
                &recorder,
                Status::Failed,
                None,
                error,
                failure.cause,
                execution_arn,
                start_date,
            )
        }
    }
}

fn finish(
    recorder: &Recorder,
    status: Status,
    output: Option<Value>,
    error: Option<String>,
    cause: Option<String>,
    execution_arn: String,
    start_date: OffsetDateTime,
) -> ExecutionResult {
    tracing::info!(execution = %execution_arn, status = %status, error = ?error, "execution ended");
    ExecutionResult {
        status,
        output,
        error,
        cause,
        history: recorder.snapshot(),
        execution_arn,
        start_date,
        stop_date: OffsetDateTime::now_utc(),
    }
}

fn failure_details(failure: &Failure) -> Value {
    let mut details = Map::new();
    if !failure.error.is_empty() {
        details.insert("error".into(), failure.error.clone().into());
    }
    if let Some(cause) = &failure.cause {
        details.insert("cause".into(), cause.clone().into());
    }
    Value::Object(details)
}

impl Run {
    fn scaled(&self, seconds: f64) -> Duration {
        Duration::try_from_secs_f64(seconds * self.options.time_scale).unwrap_or(Duration::MAX)
    }

    fn record(
        &self,
        thread: &mut Thread,
        event_type: EventType,
        details: Value,
    ) -> Result<u64, Failure> {
        let id = self.recorder.push(thread.last, event_type, details)?;
        thread.last = id;
        Ok(id)
    }

    fn check_size(&self, value: &Value, what: &str, state: &str) -> Result<(), Failure> {
        let size = payload_size(value);
        if size > self.options.max_payload_bytes {
            return Err(Failure::new(
                crate::runtime::STATES_DATA_LIMIT_EXCEEDED,
                Some(format!(
                    "The state/task '{state}' returned a result with a size exceeding the maximum number of bytes service limit ({what}: {size} > {} bytes).",
                    self.options.max_payload_bytes
                )),
            ));
        }
        Ok(())
    }

    /// The context object (`$$`) of a state.
    fn context(&self, state: &str, entered: &str, retry_count: u64) -> Value {
        json!({
            "Execution": self.execution,
            "State": {"EnteredTime": entered, "Name": state, "RetryCount": retry_count},
            "StateMachine": self.state_machine,
        })
    }

    fn run_scope(
        self: Arc<Self>,
        scope: Arc<Scope>,
        input: Value,
        mut thread: Thread,
    ) -> ScopeFuture {
        Box::pin(async move {
            let mut current = scope.start_at.clone();
            let mut input = input;
            // Ends at a terminal state or a failure; loops in the definition end at the
            // deadline or when the history is full.
            loop {
                let Some(state) = scope.states.get(&current).cloned() else {
                    let failure = Failure::runtime(format!("no state named `{current}`"));
                    return (Err(failure), thread);
                };
                match self.run_state(&state, input, &mut thread).await {
                    Ok((Some(next), output)) => {
                        current = next;
                        input = output;
                    }
                    Ok((None, output)) => return (Ok(output), thread),
                    Err(failure) => return (Err(failure), thread),
                }
            }
        })
    }

    /// Runs one state: its transition and output, or the failure it ends its branch with.
    async fn run_state(
        self: &Arc<Self>,
        state: &State,
        input: Value,
        thread: &mut Thread,
    ) -> Result<(Option<String>, Value), Failure> {
        let prefix = state.kind.event_prefix();
        let entered = timestamp::format(OffsetDateTime::now_utc());
        self.record(
            thread,
            EventType::entered(prefix),
            json!({"name": state.name, "input": input}),
        )?;
        let (next, output) = match &state.kind {
            Kind::Pass { result } => {
                let ctx = self.context(&state.name, &entered, 0);
                let env = Env::with_context(&ctx).random(&self.random);
                let effective = state
                    .flow
                    .effective_input(&input, &env)
                    .map_err(Failure::from_asl)?;
                let result = result.clone().unwrap_or(effective);
                let output = state
                    .flow
                    .output(input, result, &env)
                    .map_err(Failure::from_asl)?;
                (state.next.clone(), output)
            }
            Kind::Wait(wait) => {
                let ctx = self.context(&state.name, &entered, 0);
                let effective = path_in(state, input)?;
                let seconds = wait_seconds(wait, &effective, &ctx)?;
                tokio::time::sleep(self.scaled(seconds)).await;
                (state.next.clone(), path_out(state, effective)?)
            }
            Kind::Choice(choice) => {
                let ctx = self.context(&state.name, &entered, 0);
                let effective = path_in(state, input)?;
                let next = chosen(&state.name, choice, &effective, &ctx)?;
                (Some(next), path_out(state, effective)?)
            }
            Kind::Succeed => (None, path_out(state, path_in(state, input)?)?),
            Kind::Fail(fail) => {
                let ctx = self.context(&state.name, &entered, 0);
                let env = Env::with_context(&ctx).random(&self.random);
                let error = fail_text(&fail.error, &input, &env)?;
                let cause = fail_text(&fail.cause, &input, &env)?;
                return Err(Failure::new(error.unwrap_or_default(), cause));
            }
            Kind::Task(_) | Kind::Parallel(_) | Kind::Map(_) => {
                return self.run_with_retries(state, input, thread, &entered).await;
            }
        };
        self.check_size(&output, "output", &state.name)?;
        self.record(
            thread,
            EventType::exited(prefix),
            json!({"name": state.name, "output": output}),
        )?;
        Ok((next, output))
    }

    /// Task, Parallel and Map: attempts, retriers, catchers.
    async fn run_with_retries(
        self: &Arc<Self>,
        state: &State,
        input: Value,
        thread: &mut Thread,
        entered: &str,
    ) -> Result<(Option<String>, Value), Failure> {
        let (retry, catch) = match &state.kind {
            Kind::Task(t) => (&t.retry, &t.catch),
            Kind::Parallel(p) => (&p.retry, &p.catch),
            Kind::Map(m) => (&m.retry, &m.catch),
            // NB: run_state only sends Task, Parallel and Map states here.
            _ => return Err(Failure::runtime("only Task, Parallel and Map states retry")),
        };
        let mut counts = vec![0u64; retry.len()];
        let mut retry_count = 0u64;
        // Ends: every retry uses up one of a retrier's finite `MaxAttempts`.
        loop {
            let ctx = self.context(&state.name, entered, retry_count);
            let attempt = match &state.kind {
                Kind::Task(task) => self.attempt_task(state, task, &input, &ctx, thread).await,
                Kind::Parallel(parallel) => {
                    self.attempt_parallel(state, parallel, &input, &ctx, thread)
                        .await
                }
                Kind::Map(map) => self.attempt_map(state, map, &input, &ctx, thread).await,
                _ => Err(Failure::runtime("only Task, Parallel and Map states retry")),
            };
            let (next, output) = match attempt {
                Ok(output) => (state.next.clone(), output),
                Err(failure) => {
                    match self
                        .recover(retry, catch, &mut counts, &input, failure, &state.name)
                        .await?
                    {
                        Recovery::Retry => {
                            retry_count += 1;
                            continue;
                        }
                        Recovery::Caught { next, output } => (Some(next), output),
                    }
                }
            };
            self.record(
                thread,
                EventType::exited(state.kind.event_prefix()),
                json!({"name": state.name, "output": output}),
            )?;
            return Ok((next, output));
        }
    }

    /// Applies the first matching retrier (waiting its delay) or else the first matching
    /// catcher; a failure neither handles is returned.
    async fn recover(
        &self,
        retry: &[Retrier],
        catch: &[Catcher],
        counts: &mut [u64],
        input: &Value,
        failure: Failure,
        state: &str,
    ) -> Result<Recovery, Failure> {
        if failure.is_terminal() {
            return Err(failure);
        }
        // NB: only the first matching retrier counts; once it is exhausted the error goes
        // to the catchers, even if a later retrier also matches (the developer guide's
        // "complex retry scenario").
        if let Some(i) = retry
            .iter()
            .position(|r| matches(&r.error_equals, &failure))
        {
            let retrier = &retry[i];
            if counts[i] < retrier.max_attempts {
                let base = retrier.base_delay(counts[i]);
                let delay = match retrier.jitter {
                    Jitter::None => base,
                    // Uniform in [0, base]: a draw over 2^53 steps.
                    Jitter::Full => {
                        base * (self.random.below(1 << 53) as f64 / (1u64 << 53) as f64)
                    }
                };
                counts[i] += 1;
                tracing::debug!(state, error = %failure.error, attempt = counts[i], delay, "retrying");
                tokio::time::sleep(self.scaled(delay)).await;
                return Ok(Recovery::Retry);
            }
        }
        if let Some(catcher) = catch.iter().find(|c| matches(&c.error_equals, &failure)) {
            tracing::debug!(state, error = %failure.error, next = %catcher.next, "caught");
            let output = catcher
                .result_path
                .apply(input.clone(), failure.output())
                .map_err(Failure::from_asl)?;
            self.check_size(&output, "output", state)?;
            return Ok(Recovery::Caught {
                next: catcher.next.clone(),
                output,
            });
        }
        Err(failure)
    }

    async fn attempt_task(
        &self,
        state: &State,
        task: &Task,
        input: &Value,
        ctx: &Value,
        thread: &mut Thread,
    ) -> Result<Value, Failure> {
        // A callback task's token: one per attempt, at `$$.Task.Token`, open before the
        // integration runs (its worker may answer before it returns).
        let mut ctx = ctx.clone();
        let mut wait = None;
        let mut _closing = None;
        if task.callback {
            let (token, pending) = self.callbacks.issue(&self.random.uuid_v4());
            ctx["Task"] = json!({ "Token": token });
            wait = Some(pending);
            _closing = Some(CloseOnDrop(self.callbacks.clone(), token));
        }
        let env = Env::with_context(&ctx).random(&self.random);
        let effective = state
            .flow
            .effective_input(input, &env)
            .map_err(Failure::from_asl)?;
        self.check_size(&effective, "input", &state.name)?;
        let resource = Resource::of(task);
        let timeout = timeout_of(task, input, &ctx)?;
        let payload = self.schedule(task, &resource, effective, timeout, thread)?;
        let started = tokio::time::Instant::now();
        let result = match self.invoke(task, payload, timeout).await {
            Ok(raw) if task.integration == Integration::LambdaInvoke => json!({
                "ExecutedVersion": executed_version(&task.function.function),
                "Payload": raw,
                "SdkHttpMetadata": {"HttpStatusCode": 200},
                "SdkResponseMetadata": {"RequestId": self.random.uuid_v4()},
                "StatusCode": 200,
            }),
            Ok(raw) => raw,
            Err(invocation) => {
                let (failure, events) = match invocation {
                    Invocation::Failed(failure) => (
                        failure,
                        (EventType::LambdaFunctionFailed, EventType::TaskFailed),
                    ),
                    Invocation::TimedOut => (
                        Failure::new(STATES_TIMEOUT, None),
                        (EventType::LambdaFunctionTimedOut, EventType::TaskTimedOut),
                    ),
                };
                let (event, details) = resource.event(events, failure_details(&failure));
                self.record(thread, event, details)?;
                return Err(failure);
            }
        };
        let result = match wait {
            None => result,
            Some(wait) => {
                let submitted = resource.details(json!({ "output": result }));
                self.record(thread, EventType::TaskSubmitted, submitted)?;
                let end = self.await_callback(task, wait, started, timeout).await;
                self.reported(end, &resource, thread)?
            }
        };
        let events = (EventType::LambdaFunctionSucceeded, EventType::TaskSucceeded);
        let (event, details) = resource.event(events, json!({ "output": result }));
        self.record(thread, event, details)?;
        self.check_size(&result, "result", &state.name)?;
        let output = state
            .flow
            .output(input.clone(), result, &env)
            .map_err(Failure::from_asl)?;
        self.check_size(&output, "output", &state.name)?;
        Ok(output)
    }

    /// Records a task's scheduling and start as its integration's history shows them, and
    /// gives what its handler is invoked with.
    fn schedule(
        &self,
        task: &Task,
        resource: &Resource<'_>,
        effective: Value,
        timeout: Option<u64>,
        thread: &mut Thread,
    ) -> Result<Value, Failure> {
        if resource.lambda {
            let mut details = json!({"resource": task.function.function, "input": effective});
            if let Some(t) = timeout {
                details["timeoutInSeconds"] = t.into();
            }
            self.record(thread, EventType::LambdaFunctionScheduled, details)?;
            self.record(thread, EventType::LambdaFunctionStarted, Value::Null)?;
            return Ok(effective);
        }
        let mut scheduled =
            resource.details(json!({"region": self.options.region, "parameters": effective}));
        if let Some(t) = timeout {
            scheduled["timeoutInSeconds"] = t.into();
        }
        if let Some(h) = task.heartbeat_seconds {
            scheduled["heartbeatInSeconds"] = h.into();
        }
        self.record(thread, EventType::TaskScheduled, scheduled)?;
        self.record(thread, EventType::TaskStarted, resource.details(json!({})))?;
        Ok(match task.integration {
            // NB: Lambda hands an empty payload to the function as `{}`.
            Integration::LambdaInvoke => effective
                .get("Payload")
                .cloned()
                .unwrap_or_else(|| json!({})),
            _ => effective,
        })
    }

    /// What a callback task's worker reported, recorded: its output, or the failure or
    /// timeout it ends the attempt with.
    fn reported(
        &self,
        end: CallbackEnd,
        resource: &Resource<'_>,
        thread: &mut Thread,
    ) -> Result<Value, Failure> {
        let (failure, event) = match end {
            CallbackEnd::Reported(Outcome::Success(output)) => return Ok(output),
            CallbackEnd::Reported(Outcome::Failure { error, cause }) => {
                (Failure::new(error, Some(cause)), EventType::TaskFailed)
            }
            CallbackEnd::TimedOut(error) => (Failure::new(error, None), EventType::TaskTimedOut),
        };
        let details = resource.details(failure_details(&failure));
        self.record(thread, event, details)?;
        Err(failure)
    }

    /// Waits for the token's report: `TimeoutSeconds` counts from the task's start,
    /// `HeartbeatSeconds` from the last heartbeat (or the start).
    async fn await_callback(
        &self,
        task: &Task,
        mut wait: Pending,
        started: tokio::time::Instant,
        timeout: Option<u64>,
    ) -> CallbackEnd {
        let deadline = timeout.map(|s| started + self.scaled(s as f64));
        let beat = task.heartbeat_seconds.map(|s| self.scaled(s as f64));
        // Ends: each heartbeat restarts a bounded timer; the deadline (when set) is fixed.
        loop {
            let timeout = async {
                match deadline {
                    Some(d) => tokio::time::sleep_until(d).await,
                    None => std::future::pending().await,
                }
            };
            let heartbeat = async {
                match beat {
                    Some(b) => tokio::time::sleep(b).await,
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                reported = &mut wait.done => {
                    return match reported {
                        Ok(outcome) => CallbackEnd::Reported(outcome),
                        Err(_) => CallbackEnd::TimedOut(STATES_TIMEOUT),
                    };
                }
                _ = wait.heartbeat.notified() => continue,
                _ = timeout => return CallbackEnd::TimedOut(STATES_TIMEOUT),
                _ = heartbeat => return CallbackEnd::TimedOut(STATES_HEARTBEAT_TIMEOUT),
            }
        }
    }

    async fn invoke(
        &self,
        task: &Task,
        payload: Value,
        timeout: Option<u64>,
    ) -> Result<Value, Invocation> {
        let Some(handler) = self.tasks.handler(&task.function) else {
            if let Integration::Service { .. } = task.integration {
                return Err(Invocation::Failed(Failure::new(
                    crate::runtime::STATES_TASK_FAILED,
                    Some(format!(
                        "no handler plays `{}` in the embedded executor (register one under that key)",
                        task.function.name
                    )),
                )));
            }
            return Err(Invocation::Failed(Failure::new(
                "Lambda.ResourceNotFoundException",
                Some(format!(
                    "Function not found: {} (Service: AWSLambda; Status Code: 404; Error Code: ResourceNotFoundException; no handler is registered with the embedded executor)",
                    task.function
                )),
            )));
        };
        let mut call = AbortOnDrop(tokio::spawn(handler(payload)));
        let joined = match timeout {
            Some(seconds) => {
                let limit = if self.options.scale_invocation_timeouts {
                    self.scaled(seconds as f64)
                } else {
                    Duration::from_secs(seconds)
                };
                match tokio::time::timeout(limit, &mut call.0).await {
                    Ok(joined) => joined,
                    Err(_) => return Err(Invocation::TimedOut),
                }
            }
            None => (&mut call.0).await,
        };
        match joined {
            Ok(Ok(value)) => Ok(value),
            Ok(Err(e)) => Err(Invocation::Failed(Failure::new(e.error, Some(e.cause)))),
            // A panicking handler is an unhandled function error, as Lambda reports it.
            Err(e) => Err(Invocation::Failed(Failure::new(
                "Lambda.Unknown",
                Some(format!(
                    "The function {} did not return: {e}",
                    task.function.name
                )),
            ))),
        }
    }

    async fn attempt_parallel(
        self: &Arc<Self>,
        state: &State,
        parallel: &Parallel,
        input: &Value,
        ctx: &Value,
        thread: &mut Thread,
    ) -> Result<Value, Failure> {
        let env = Env::with_context(ctx).random(&self.random);
        let effective = state
            .flow
            .effective_input(input, &env)
            .map_err(Failure::from_asl)?;
        let started = self.record(thread, EventType::ParallelStateStarted, Value::Null)?;
        let mut set = JoinSet::new();
        for (i, branch) in parallel.branches.iter().enumerate() {
            let branch =
                self.clone()
                    .run_scope(branch.clone(), effective.clone(), Thread { last: started });
            set.spawn(async move { (i, branch.await) });
        }
        let mut outputs = vec![Value::Null; parallel.branches.len()];
        let mut last = started;
        let mut failed = None;
        while let Some(joined) = set.join_next().await {
            match joined {
                Ok((i, (Ok(output), branch))) => {
                    outputs[i] = output;
                    last = last.max(branch.last);
                }
                Ok((_, (Err(failure), branch))) => {
                    failed = Some((failure, branch.last));
                    break;
                }
                Err(e) => {
                    failed = Some((Failure::runtime(format!("a branch stopped: {e}")), last));
                    break;
                }
            }
        }
        // The other branches stop with the first failure.
        set.abort_all();
        let outcome = match failed {
            Some(failed) => Err(failed),
            None => Ok((outputs, last)),
        };
        let events = (
            EventType::ParallelStateFailed,
            EventType::ParallelStateSucceeded,
        );
        self.branches_ended(state, input, &env, outcome, events, thread)
    }

    /// Ends a Parallel or Map state once its branches did: the first failure recorded (as
    /// the first of `events`) after the event it follows, or the branches' outputs in order
    /// recorded (as the second) after the last branch's event, and made its result.
    fn branches_ended(
        &self,
        state: &State,
        input: &Value,
        env: &Env<'_>,
        outcome: Result<(Vec<Value>, u64), (Failure, u64)>,
        (failed, succeeded): (EventType, EventType),
        thread: &mut Thread,
    ) -> Result<Value, Failure> {
        let (outputs, last) = match outcome {
            Ok(ended) => ended,
            Err((failure, at)) => {
                thread.last = at;
                self.record(thread, failed, failure_details(&failure))?;
                return Err(failure);
            }
        };
        thread.last = last;
        self.record(thread, succeeded, Value::Null)?;
        let output = state
            .flow
            .output(input.clone(), Value::Array(outputs), env)
            .map_err(Failure::from_asl)?;
        self.check_size(&output, "output", &state.name)?;
        Ok(output)
    }

    async fn attempt_map(
        self: &Arc<Self>,
        state: &State,
        map: &MapState,
        input: &Value,
        ctx: &Value,
        thread: &mut Thread,
    ) -> Result<Value, Failure> {
        let env = Env::with_context(ctx).random(&self.random);
        let effective = path_in(state, input.clone())?;
        let items = map_items(&state.name, map, &effective, ctx)?;
        let started = self.record(
            thread,
            EventType::MapStateStarted,
            json!({"length": items.len()}),
        )?;
        let iterations = Iterations {
            state: &state.name,
            map,
            effective: &effective,
            ctx,
        };
        let outcome = self.iterate(iterations, &items, started).await?;
        let events = (EventType::MapStateFailed, EventType::MapStateSucceeded);
        self.branches_ended(state, input, &env, outcome, events, thread)
    }

    /// Runs a Map state's iterations, in item order and up to its `MaxConcurrency` at a
    /// time: their outputs and the last event, or the first failure and the event it
    /// follows (the iterations still running recorded as aborted). The outer error is the
    /// history's own (it is full).
    async fn iterate(
        self: &Arc<Self>,
        each: Iterations<'_>,
        items: &[Value],
        started: u64,
    ) -> Result<Result<(Vec<Value>, u64), (Failure, u64)>, Failure> {
        let limit = match each.map.max_concurrency {
            0 => usize::MAX,
            n => usize::try_from(n).unwrap_or(usize::MAX),
        };
        let mut set = JoinSet::new();
        let mut running = BTreeSet::new();
        let mut outputs = vec![Value::Null; items.len()];
        let mut next_index = 0;
        let mut last = started;
        let iteration = |index: usize| json!({"name": each.state, "index": index});
        let outcome = 'iterations: loop {
            while running.len() < limit && next_index < items.len() {
                let index = next_index;
                next_index += 1;
                let item_input = match self.item_input(&each, &items[index], index) {
                    Ok(v) => v,
                    Err(failure) => break 'iterations Err((failure, last)),
                };
                let event = EventType::MapIterationStarted;
                let id = self.recorder.push(started, event, iteration(index))?;
                let body = self.clone().run_scope(
                    each.map.processor.clone(),
                    item_input,
                    Thread { last: id },
                );
                set.spawn(async move { (index, body.await) });
                running.insert(index);
            }
            let Some(joined) = set.join_next().await else {
                break Ok(());
            };
            let (index, (result, body)) = match joined {
                Ok(ended) => ended,
                Err(e) => {
                    let failure = Failure::runtime(format!("an iteration stopped: {e}"));
                    break Err((failure, last));
                }
            };
            running.remove(&index);
            match result {
                Ok(output) => {
                    outputs[index] = output;
                    let event = EventType::MapIterationSucceeded;
                    last = self.recorder.push(body.last, event, iteration(index))?;
                }
                Err(failure) => {
                    let event = EventType::MapIterationFailed;
                    let id = self.recorder.push(body.last, event, iteration(index))?;
                    break Err((failure, id));
                }
            }
        };
        set.abort_all();
        if let Err((failure, at)) = outcome {
            for index in running {
                self.recorder
                    .push(at, EventType::MapIterationAborted, iteration(index))?;
            }
            return Ok(Err((failure, at)));
        }
        Ok(Ok((outputs, last)))
    }

    /// One iteration's input: its item, or what the Map's `ItemSelector` makes of it with
    /// `$$.Map.Item` set.
    fn item_input(
        &self,
        each: &Iterations<'_>,
        item: &Value,
        index: usize,
    ) -> Result<Value, Failure> {
        let Some(selector) = &each.map.item_selector else {
            return Ok(item.clone());
        };
        let mut item_ctx = each.ctx.clone();
        item_ctx["Map"] = json!({"Item": {"Index": index, "Value": item}});
        let item_env = Env::with_context(&item_ctx).random(&self.random);
        selector
            .render(each.effective, &item_env)
            .map_err(Failure::from_asl)
    }
}

/// What every iteration of one Map state shares.
struct Iterations<'a> {
    /// The Map state's name.
    state: &'a str,
    map: &'a MapState,
    /// The Map state's effective input.
    effective: &'a Value,
    /// The Map state's context object.
    ctx: &'a Value,
}

/// The items a Map state iterates over: its effective input, or what its `ItemsPath`
/// selects in it, which must be an array.
fn map_items(
    state: &str,
    map: &MapState,
    effective: &Value,
    ctx: &Value,
) -> Result<Vec<Value>, Failure> {
    let items = match &map.items_path {
        None => effective.clone(),
        Some(path) => path.get(effective, ctx).cloned().ok_or_else(|| {
            Failure::runtime(format!(
                "Invalid path '{}': the ItemsPath of Map state '{state}' selects nothing",
                path.text(),
            ))
        })?,
    };
    match items {
        Value::Array(items) => Ok(items),
        other => Err(Failure::runtime(format!(
            "The ItemsPath of Map state '{state}' must select a JSON array, not {}",
            kind_of(&other)
        ))),
    }
}

/// A task's timeout: its `TimeoutSeconds`, or the seconds its `TimeoutSecondsPath` reads.
fn timeout_of(task: &Task, input: &Value, ctx: &Value) -> Result<Option<u64>, Failure> {
    match &task.timeout_path {
        None => Ok(task.timeout_seconds),
        Some(path) => seconds_at(path, input, ctx, ("TimeoutSecondsPath", "Task"), 1).map(Some),
    }
}

/// A state's input through its `InputPath`: its effective input.
fn path_in(state: &State, input: Value) -> Result<Value, Failure> {
    state
        .flow
        .input_path
        .apply(input)
        .map_err(Failure::from_asl)
}

/// What leaves a state that makes no result: its effective input through its `OutputPath`.
fn path_out(state: &State, effective: Value) -> Result<Value, Failure> {
    state
        .flow
        .output_path
        .apply(effective)
        .map_err(Failure::from_asl)
}

/// A Choice state's next state: that of its first rule that matches, or its default.
fn chosen(state: &str, choice: &Choice, effective: &Value, ctx: &Value) -> Result<String, Failure> {
    for (rule, target) in &choice.rules {
        if rule.evaluate(effective, ctx)? {
            return Ok(target.clone());
        }
    }
    choice.default.clone().ok_or_else(|| {
        Failure::new(
            "States.NoChoiceMatched",
            Some(format!(
                "No Choice matched in the Choice state '{state}' and it has no Default."
            )),
        )
    })
}

fn kind_of(value: &Value) -> &'static str {
    match value {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

/// Whole seconds a `...SecondsPath` field selects: an integer from `min` to 99999999, else a
/// runtime error naming the field (`field` of the `kind` state).
fn seconds_at(
    path: &ReferencePath,
    input: &Value,
    ctx: &Value,
    (field, kind): (&str, &str),
    min: u64,
) -> Result<u64, Failure> {
    let value = path.get(input, ctx).ok_or_else(|| {
        Failure::runtime(format!(
            "Invalid path '{}': the {field} of the {kind} state selects nothing",
            path.text()
        ))
    })?;
    match value.as_u64() {
        Some(s) if (min..=99_999_999).contains(&s) => Ok(s),
        _ => Err(Failure::runtime(format!(
            "The {field} '{}' must select an integer from {min} to 99999999, got {value}",
            path.text()
        ))),
    }
}

/// A Wait state's duration in (unscaled) seconds.
fn wait_seconds(wait: &Wait, input: &Value, ctx: &Value) -> Result<f64, Failure> {
    let until = |at: OffsetDateTime| (at - OffsetDateTime::now_utc()).as_seconds_f64().max(0.0);
    Ok(match wait {
        Wait::Seconds(s) => *s as f64,
        Wait::Timestamp(at) => until(*at),
        Wait::SecondsPath(path) => seconds_at(path, input, ctx, ("SecondsPath", "Wait"), 0)? as f64,
        Wait::TimestampPath(path) => {
            let value = path.get(input, ctx).ok_or_else(|| {
                Failure::runtime(format!(
                    "Invalid path '{}': the TimestampPath of the Wait state selects nothing",
                    path.text()
                ))
            })?;
            let at = value.as_str().and_then(timestamp::parse).ok_or_else(|| {
                Failure::runtime(format!(
                    "The TimestampPath '{}' must select an RFC 3339 timestamp, got {value}",
                    path.text()
                ))
            })?;
            until(at)
        }
    })
}

/// A Fail state's `Error`/`Cause` (literal, path or intrinsic function).
fn fail_text(text: &Text, input: &Value, env: &Env<'_>) -> Result<Option<String>, Failure> {
    let value = match text {
        Text::None => return Ok(None),
        Text::Literal(s) => return Ok(Some(s.clone())),
        Text::Path(path) => path.select(input, env.context).ok_or_else(|| {
            Failure::runtime(format!(
                "Invalid path '{}': the Fail state's path selects nothing",
                path.text()
            ))
        })?,
        Text::Call { field, call } => call
            .evaluate(field, input, env)
            .map_err(Failure::from_asl)?,
    };
    match value {
        Value::String(s) => Ok(Some(s)),
        other => Err(Failure::runtime(format!(
            "The Fail state's ErrorPath/CausePath must select a string, got {other}"
        ))),
    }
}

/// `ExecutionStarted`'s details: the input and role, and the version and alias the execution
/// was started through, as AWS's history names them.
fn started_details(
    input: &Value,
    role_arn: &str,
    version_arn: &Option<String>,
    alias_arn: &Option<String>,
) -> Value {
    let mut details = json!({"input": input, "roleArn": role_arn});
    if let Some(v) = version_arn {
        details["stateMachineVersionArn"] = json!(v);
    }
    if let Some(a) = alias_arn {
        details["stateMachineAliasArn"] = json!(a);
    }
    details
}

/// The version `lambda:invoke` reports having run: the function's qualifier, else `$LATEST`.
fn executed_version(function: &str) -> &str {
    let parts = function.split(':').count();
    let qualified = if function.starts_with("arn:") {
        parts == 8
    } else if function.contains(":function:") {
        parts == 4
    } else {
        parts == 2
    };
    match function.rsplit_once(':') {
        Some((_, qualifier)) if qualified => qualifier,
        _ => "$LATEST",
    }
}
