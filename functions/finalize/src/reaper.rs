//! Finalize as the reaper: for an execution that ended without reaching Finalize (stopped,
//! timed out, failed outside every Catch, or whose Finalize never completed), the same work
//! Finalize does, on the last state the execution carried. Two requests bring it here: Step
//! Functions' "Execution Status Change" event (FAILED, TIMED_OUT, ABORTED) through an
//! EventBridge rule, and a scheduled pass over the held places whose executions no longer
//! run (an event lost, a place held from before the rule existed).

use aws_lambda_events::event::eventbridge::EventBridgeEvent;
use lb_aws::executions::{self, execution_arn, Executions};
use lb_aws::tasks::Callbacks;
use lb_domain::run::reaper::{self, Verdict, REAPED_STATUSES};
use lb_domain::status::{ExecutionStatus, Reaping};
use lb_pipeline::queue::{TeamQueue, Waker};
use lb_pipeline::{FnError, Result};
use serde::{Deserialize, Serialize};
use serde_json::Value;
use tracing::{error, info, warn};

use crate::{handle, Deps, FinalizeInput};
use lb_pipeline::payload::ExecutionState;

/// The event's `detail-type` for an execution's change of status.
pub const STATUS_CHANGE: &str = "Step Functions Execution Status Change";

/// The scheduled pass's input (the rule's constant `Input`).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReconcileInput {
    /// What to check.
    pub reconcile: Reconcile,
}

/// The state machine whose executions hold places.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Reconcile {
    /// Its ARN.
    pub state_machine: String,
}

/// What the reaper did with one execution.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Reaped {
    /// The execution's ARN.
    pub execution: String,
    /// How it ended (absent: Step Functions does not know it).
    pub status: Option<ExecutionStatus>,
    /// What the reaper did: nothing, only the place given back, or Finalize's settled status.
    pub outcome: Reaping,
}

/// The fields of a status change's `detail` the reaper reads, validated.
struct Ended<'a> {
    arn: &'a str,
    status: ExecutionStatus,
    error: Option<&'a str>,
}

fn ended(event: &EventBridgeEvent<Value>) -> Result<Ended<'_>> {
    let bad = |what: String| FnError::Event(what);
    if event.detail_type != STATUS_CHANGE || event.source != "aws.states" {
        return Err(bad(format!(
            "expected `{STATUS_CHANGE}` from `aws.states`, got `{}` from `{}`",
            event.detail_type.escape_debug(),
            event.source.escape_debug()
        )));
    }
    let text = |name: &str| event.detail.get(name).and_then(Value::as_str);
    let arn = text("executionArn")
        .filter(|a| a.starts_with("arn:") && a.contains(":states:") && a.contains(":execution:"))
        .ok_or_else(|| bad("`detail.executionArn` is not an execution ARN".into()))?;
    let status = text("status")
        .ok_or_else(|| bad("`detail.status` is missing".into()))?
        .parse()
        .map_err(|e: lb_domain::status::UnknownStatus| bad(format!("`detail.status`: {e}")))?;
    Ok(Ended {
        arn,
        status,
        error: text("error"),
    })
}

/// An "Execution Status Change" event: the execution reaped when it ended without Finalize.
pub async fn on_event<C: Callbacks + Executions>(
    event: EventBridgeEvent<Value>,
    deps: &Deps<C>,
) -> Result<Reaped> {
    let ended = ended(&event)?;
    if !REAPED_STATUSES.contains(&ended.status) {
        // The rule asks only for these; anything else is not ours to act on.
        return Ok(left(ended.arn, ended.status));
    }
    reap(deps, ended.arn, ended.status, ended.error).await
}

fn left(arn: &str, status: ExecutionStatus) -> Reaped {
    Reaped {
        execution: arn.to_string(),
        status: Some(status),
        outcome: Reaping::Left,
    }
}

/// Finishes execution `arn`, which ended with `status`, as Finalize would have.
pub async fn reap<C: Callbacks + Executions>(
    deps: &Deps<C>,
    arn: &str,
    status: ExecutionStatus,
    error: Option<&str>,
) -> Result<Reaped> {
    let state = deps.callbacks.last_state(arn).await?;
    let (name, cause) = match reaper::verdict(status, error, state.as_ref()) {
        Verdict::Leave => return Ok(left(arn, status)),
        Verdict::Reap { error, cause } => (error, cause),
    };
    let Some(state) = state else {
        warn!(
            execution = arn,
            %status, "no state recorded: nothing claimed to finish"
        );
        return Ok(left(arn, status));
    };
    let state = ExecutionState::from_value(reaper::finalize_state(state, name, &cause))?;
    let out = handle(FinalizeInput { state }, deps).await?;
    // Alarmed through the state machine's ExecutionsAborted/TimedOut/Failed metrics; this
    // line says what the reaper did about it.
    error!(
        execution = arn,
        %status,
        outcome = out.status.as_str(),
        reason = %cause,
        "reaped an execution that ended without Finalize"
    );
    Ok(Reaped {
        execution: arn.to_string(),
        status: Some(status),
        outcome: Reaping::Finalized(out.status),
    })
}

/// The scheduled pass: every held place whose execution no longer runs is reaped (its place
/// given back by Finalize), and a place whose execution Step Functions does not know is
/// given back directly. Failures are collected; the next pass retries them.
pub async fn reconcile<C: Callbacks + Executions>(
    input: ReconcileInput,
    deps: &Deps<C>,
) -> Result<Vec<Reaped>> {
    let machine = input.reconcile.state_machine;
    if execution_arn(&machine, "x").is_none() {
        return Err(FnError::Event(format!(
            "`reconcile.state_machine` is not a state machine ARN: `{}`",
            machine.escape_debug()
        )));
    }
    let mut reaped = Vec::new();
    let mut failed = Vec::new();
    let admission = &deps.clients.admission;
    for (queue, leaderboard) in &deps.clients.settings.leaderboards {
        let (queue, limit) = (queue.as_str(), leaderboard.team_limit);
        for (team, holders) in admission.holds(queue).await? {
            let team = TeamQueue { queue, team, limit };
            for holder in holders {
                match check(deps, &machine, team, &holder).await {
                    Ok(Some(done)) => reaped.push(done),
                    Ok(None) => {}
                    Err(e) => failed.push(format!("{queue} place of `{holder}`: {e}")),
                }
            }
        }
    }
    info!(
        reaped = reaped.len(),
        failed = failed.len(),
        "held places checked"
    );
    if failed.is_empty() {
        Ok(reaped)
    } else {
        Err(FnError::ReconcileIncomplete(failed))
    }
}

/// One held place: `None` when its execution runs (or it names none: a place from before
/// entries named their execution, left to its TTL).
async fn check<C: Callbacks + Executions>(
    deps: &Deps<C>,
    machine: &str,
    team: TeamQueue<'_>,
    holder: &str,
) -> Result<Option<Reaped>> {
    let Ok(id) = holder.parse::<u64>() else {
        return Ok(None);
    };
    let Some(name) = deps.clients.admission.execution_of(team.queue, id).await? else {
        return Ok(None);
    };
    let Some(arn) = execution_arn(machine, &name) else {
        return Ok(None);
    };
    // A run that continued as a new execution names it in its entry once its first round ran:
    // until then the entry's execution ended to start it, and the one it runs in now is judged.
    match executions::current(&deps.callbacks, &arn).await? {
        Some((_, d)) if d.status == ExecutionStatus::Running => Ok(None),
        Some((arn, d)) => {
            let mut done = reap(deps, &arn, d.status, d.error.as_deref()).await?;
            if done.outcome == Reaping::Left {
                // Ended and nothing to finish, yet still holding: Finalize ran but its
                // release did not.
                give_back(deps, team, id).await?;
                done.outcome = Reaping::Released;
            }
            Ok(Some(done))
        }
        None => {
            warn!(submission_id = id, execution = %arn, "a place held by an execution Step Functions does not know: given back");
            give_back(deps, team, id).await?;
            Ok(Some(Reaped {
                execution: arn,
                status: None,
                outcome: Reaping::Released,
            }))
        }
    }
}

/// Gives `id`'s place back and wakes the team's next waiting submissions (best effort: their
/// polls come anyway).
async fn give_back<C: Callbacks>(deps: &Deps<C>, team: TeamQueue<'_>, id: u64) -> Result<()> {
    let waker = Waker {
        wakes: &deps.wakes,
        callbacks: &deps.callbacks,
        now: lb_pipeline::clients::now_epoch_seconds(),
    };
    deps.clients.admission.leave(team, id, waker).await?;
    Ok(())
}
