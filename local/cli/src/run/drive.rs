//! Driving a local run: its executions started at their arrivals, watched, and followed
//! through their continuations to their ends.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use local_stack::Stack;

use crate::scenario::Rehearsal;
use local_stepfunctions::{EventType, Execution, ExecutionResult, Executor, HistoryEvent};

use crate::release::{Release, ALIAS};

use super::*;

/// What the run watches of its executions: Monitor rounds, and those that found the cluster's
/// API out of reach (their verdict skipped).
#[derive(Default)]
pub(super) struct Watch {
    pub(super) rounds: Arc<AtomicU64>,
    pub(super) unreachable_rounds: Arc<AtomicU64>,
}

impl Watch {
    /// Live progress, the outage from the first round, and the scenario's hooks at each round.
    pub(super) fn on_event(
        &self,
        args: &LocalRun,
        stack: &Stack,
        scenario: &Arc<dyn Rehearsal>,
        acted: &Arc<AtomicBool>,
        started: Instant,
    ) -> local_stepfunctions::EventCallback {
        let (rounds, unreachable) = (self.rounds.clone(), self.unreachable_rounds.clone());
        let (scenario, acted) = (scenario.clone(), acted.clone());
        let outage = stack
            .kube
            .as_ref()
            .map(|k| k.outage())
            .filter(|_| args.kube_outage_minutes > 0.0);
        let outage_for = Duration::from_secs_f64(args.kube_outage_minutes * 60.0 * args.time_scale);
        let outage_minutes = args.kube_outage_minutes;
        Arc::new(move |event: &HistoryEvent| {
            let name = event.state_name().unwrap_or_default();
            if event.event_type == EventType::TaskStateEntered && name != "Monitor" {
                say(started, format!("stage {name}"));
            } else if event.event_type == EventType::TaskStateEntered {
                let n = rounds.fetch_add(1, Ordering::SeqCst) + 1;
                if let (1, Some(outage)) = (n, &outage) {
                    outage.fail_for(outage_for);
                    say(
                        started,
                        format!(
                            "the cluster's API answers 500 for {outage_minutes} minutes (scaled)"
                        ),
                    );
                }
                if !acted.load(Ordering::SeqCst) && scenario.round_begins(n) {
                    acted.store(true, Ordering::SeqCst);
                }
            } else if event.event_type == EventType::TaskStateExited && name == "Monitor" {
                let output = &event.details["output"]["run"]["monitor"];
                let skipped = if output["unreachable_since"].is_null() {
                    ""
                } else {
                    unreachable.fetch_add(1, Ordering::SeqCst);
                    " (cluster unreachable: verdict skipped)"
                };
                scenario.round_ended(output);
                say(
                    started,
                    format!(
                        "monitor round {}: {} routes {}/{}{skipped}",
                        output["rounds"],
                        output["state"],
                        output["progress"][0],
                        output["progress"][1]
                    ),
                );
            }
        })
    }
}

/// Starts an execution per arrival of `which`, all at once, as EvalAI's messages come,
/// through `through` (the alias, as the Pipe starts them): each one's place in the queue is
/// when EvalAI received it (`submitted_at`), the order of `arrivals`.
pub(super) async fn start(
    stack: &Stack,
    executor: &Executor,
    sent: &Arrivals,
    which: std::ops::Range<usize>,
    through: &str,
    started: Instant,
) -> anyhow::Result<Vec<(u64, u64, Execution)>> {
    let Arrivals {
        challenge,
        phase,
        image,
        ref each,
        teams,
    } = *sent;
    let arrivals = &each[which];
    let mut executions = Vec::new();
    for (id, team) in arrivals {
        let input = sqs_round_trip(stack, challenge, phase, *id, image).await?;
        if arrivals.len() == 1 {
            say(
                started,
                format!("message for submission {id} received from SQS; Pipe output {input}"),
            );
        }
        let execution = executor
            .start_arn(through, &format!("local-{id}"), input)
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        executions.push((*id, *team, execution));
    }
    if each.len() > 1 && !arrivals.is_empty() {
        let count = arrivals.len();
        say(
            started,
            format!("{count} submissions from {teams} teams arrived"),
        );
    }
    Ok(executions)
}

/// What the deployment delivers to the functions beside the state machine: Step Functions'
/// "Execution Status Change" events to Finalize as the reaper (as the EventBridge rule and
/// Lambda's asynchronous invocation do), S3's events and the cancel sweep to the waiting
/// execution.
pub(super) async fn deliveries(
    args: &LocalRun,
    stack: &Stack,
    scaled: (&lb_infra::Template, f64),
    (executor, kubeconfig): (&Executor, &std::path::Path),
    (finalize, failures): (
        Arc<finalize::Deps<local_stack::events::LateCallbacks>>,
        Arc<AtomicU64>,
    ),
) -> anyhow::Result<(crate::reaper::Reaper, crate::relay::Relays)> {
    let reaper = crate::reaper::Reaper::spawn(executor, finalize, scaled, failures)?;
    let relays = crate::relay::spawn(
        &stack.sdk,
        scaled.0,
        &local_stack::stack::function_config(),
        (
            executor.clone(),
            // The sweep as its own group where the cluster tells identities apart.
            lb_pipeline::cluster::Clusters::kubeconfig(
                stack.fleet_kubeconfig().unwrap_or(kubeconfig).to_owned(),
            ),
        ),
        args.time_scale,
        !args.no_wake,
    )
    .await?;
    Ok((reaper, relays))
}

/// What the run's start tells: the scenario with its round count and act, the reaper and the
/// template with the time scale.
pub(super) type Hooks<'a> = (
    &'a dyn Rehearsal,
    &'a Watch,
    &'a Arc<AtomicBool>,
    &'a mut crate::reaper::Reaper,
    (&'a lb_infra::Template, f64),
);

/// Starts the arrivals through the release's alias, as the deployment does, and tells the
/// scenario and the reaper of the first; a release scenario holds the later submissions back
/// until it moved the alias after the first one's round. The executions, and whether the
/// alias moved.
pub(super) async fn start_through(
    args: &LocalRun,
    stack: &Stack,
    executor: &Executor,
    arrivals: &Arrivals,
    release: &Release,
    (scenario, watch, acted, reaper, scaled): Hooks<'_>,
    started: Instant,
) -> anyhow::Result<(Vec<(u64, u64, Execution)>, bool)> {
    let count = arrivals.each.len();
    let first = if release.moves() { 1 } else { count };
    let live = &release.live;
    let mut executions = start(stack, executor, arrivals, 0..first, live, started).await?;
    reaper.schedule(scaled, executions[0].2.arn())?;
    scenario.started(executor, executions[0].2.arn(), &watch.rounds, acted);
    if !release.moves() {
        return Ok((executions, false));
    }
    let within = Duration::from_secs(args.timeout);
    let moved = release
        .switch_after_first_round(executor, executions[0].2.arn(), within)
        .await?;
    say(started, format!("the alias `{ALIAS}` moved: {moved}"));
    executions.extend(start(stack, executor, arrivals, first..count, live, started).await?);
    Ok((executions, moved))
}

/// Every execution's result, followed through its continuations, in arrival order; and each
/// one's history lengths.
/// With `record`, what they handed on is written there (`crate::states`).
pub(super) async fn wait_all(
    executor: &Executor,
    executions: Vec<(u64, u64, Execution)>,
    record: Option<&std::path::Path>,
    started: Instant,
) -> anyhow::Result<(Vec<ExecutionResult>, Vec<Vec<usize>>)> {
    let many = executions.len() > 1;
    let mut results = Vec::new();
    let mut chains = Vec::new();
    for (id, team, execution) in executions {
        let (result, lengths) = follow(executor, execution.wait().await).await;
        chains.push(lengths);
        if many {
            let status = result.status.as_str();
            say(
                started,
                format!("submission {id} (team {team}): execution {status}"),
            );
        }
        results.push(result);
    }
    if let Some(dir) = record {
        crate::states::record(dir, results.iter().map(|r| r.history.as_slice()))?;
    }
    Ok((results, chains))
}

/// How many executions ended without Finalize (the reaper answers for those).
pub(super) fn ended_without_finalize(results: &[ExecutionResult]) -> usize {
    results
        .iter()
        .filter(|r| {
            let status = local_stack::events::execution_status(Some(r.status));
            lb_domain::run::reaper::REAPED_STATUSES.contains(&status)
        })
        .count()
}

/// The most executions one run is followed through (72 hours at the least round interval
/// take fewer than 100).
pub(super) const MAX_CHAIN: usize = 200;

/// An execution's result followed through the executions its run continued as: how the last
/// one ended, with every history in order (for the stages); and each history's length.
pub(super) async fn follow(
    executor: &Executor,
    mut result: local_stepfunctions::ExecutionResult,
) -> (local_stepfunctions::ExecutionResult, Vec<usize>) {
    let mut lengths = vec![result.history.len()];
    while lengths.len() < MAX_CHAIN {
        let next = (result.status == local_stepfunctions::Status::Succeeded)
            .then_some(result.output.as_ref())
            .flatten()
            .and_then(lb_domain::run::history::continued_as)
            .map(str::to_owned);
        let Some(next) = next else { break };
        let Some(mut continued) = executor.wait_for(&next).await else {
            break;
        };
        lengths.push(continued.history.len());
        let mut history = std::mem::take(&mut result.history);
        history.append(&mut continued.history);
        continued.history = history;
        result = continued;
    }
    (result, lengths)
}
