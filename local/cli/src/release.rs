//! Versioned deploys in a local run, as `infra/app.yaml` makes them: the state machine is
//! published as a version whose definition names its functions' versions, submissions start
//! through the `live` alias, and the deploy and rollback scenarios move the alias while the
//! first submission runs, then check that every execution ran the version it started on.

use std::time::Duration;

use local_stepfunctions::{EventType, ExecutionResult, Executor};
use serde::Serialize;

use crate::run::machine;

/// The alias the EventBridge Pipe, `lbctl` and the console start executions through.
pub const ALIAS: &str = "live";

/// What moves the alias during the run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Move {
    /// A new version is published and the alias moves to it after the first round.
    Deploy,
    /// Two versions exist, the alias on the newer; it moves back after the first round.
    Rollback,
}

/// The versions of one run and the alias.
pub struct Release {
    /// The alias's ARN.
    pub live: String,
    /// The state machine's unqualified ARN.
    machine_arn: String,
    /// The version the first submission starts on.
    before: u32,
    /// The version the alias names after the move (`before` when nothing moves).
    after: u32,
    moves: Option<Move>,
}

/// How the run's executions matched their versions.
#[derive(Debug, Clone, Serialize)]
pub struct ReleaseReport {
    /// What moved the alias.
    pub change: String,
    /// The version each submission's executions ran (`None`: they did not agree).
    pub ran: Vec<Option<u32>>,
    /// The version each submission should have run.
    pub expected: Vec<u32>,
    /// Whether the alias moved while the first one ran.
    pub moved: bool,
}

impl ReleaseReport {
    /// Every submission ran its own version throughout, and the alias did move.
    pub fn as_expected(&self) -> bool {
        self.moved
            && self
                .ran
                .iter()
                .copied()
                .eq(self.expected.iter().map(|v| Some(*v)))
    }
}

impl Release {
    /// Publishes the versions the run starts with and points the alias at the one the first
    /// submission starts on.
    pub fn publish(executor: &Executor, moves: Option<Move>) -> anyhow::Result<Release> {
        let v1 = executor.publish(&machine(1)?);
        let (before, after, start_on) = match moves {
            None => (1, 1, v1),
            Some(Move::Deploy) => (1, 2, v1),
            Some(Move::Rollback) => (2, 1, executor.publish(&machine(2)?)),
        };
        let live = executor
            .point_alias(ALIAS, &start_on)
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        let machine_arn = start_on.rsplit_once(':').map_or("", |(m, _)| m).to_owned();
        Ok(Release {
            live,
            machine_arn,
            before,
            after,
            moves,
        })
    }

    /// Whether the alias moves during the run: the submissions after the first wait for it.
    pub fn moves(&self) -> bool {
        self.moves.is_some()
    }

    /// Once the first submission's Monitor ended a round (it runs, with Jobs), deploys or
    /// rolls back: the alias names `after` from then on. `false` when no round came within
    /// `within`.
    pub async fn switch_after_first_round(
        &self,
        executor: &Executor,
        first: &str,
        within: Duration,
    ) -> anyhow::Result<bool> {
        let deadline = tokio::time::Instant::now() + within;
        loop {
            let rounded = executor.history_of(first).is_some_and(|history| {
                history.iter().any(|e| {
                    e.event_type == EventType::TaskStateExited && e.state_name() == Some("Monitor")
                })
            });
            if rounded {
                break;
            }
            if tokio::time::Instant::now() >= deadline {
                return Ok(false);
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let target = match self.moves {
            Some(Move::Deploy) => executor.publish(&machine(self.after)?),
            _ => format!("{}:{}", self.machine_arn, self.after),
        };
        executor
            .point_alias(ALIAS, &target)
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        Ok(true)
    }

    /// The version each submission's chain of executions ran, read from their histories:
    /// the version every execution started on and every function version it invoked.
    pub fn check(&self, results: &[ExecutionResult], moved: bool) -> Option<ReleaseReport> {
        let change = match self.moves? {
            Move::Deploy => format!("deploy: version {} -> {}", self.before, self.after),
            Move::Rollback => format!("rollback: version {} -> {}", self.before, self.after),
        };
        let ran = results.iter().map(ran_version).collect();
        let expected = (0..results.len())
            .map(|n| if n == 0 { self.before } else { self.after })
            .collect();
        Some(ReleaseReport {
            change,
            ran,
            expected,
            moved,
        })
    }
}

/// The one version a chain's histories show (each execution's start and each function it
/// invoked), or `None` when they show none or several.
fn ran_version(result: &ExecutionResult) -> Option<u32> {
    let qualifier = |arn: &str| {
        arn.rsplit_once(':')
            .and_then(|(_, q)| q.parse::<u32>().ok())
    };
    let mut seen = result.history.iter().filter_map(|e| match e.event_type {
        EventType::ExecutionStarted => Some(
            e.details["stateMachineVersionArn"]
                .as_str()
                .and_then(qualifier),
        ),
        EventType::LambdaFunctionScheduled => {
            Some(e.details["resource"].as_str().and_then(qualifier))
        }
        _ => None,
    });
    let first = seen.next()??;
    seen.all(|v| v == Some(first)).then_some(first)
}
