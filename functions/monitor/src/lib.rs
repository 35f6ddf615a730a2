//! Monitor (stage 4): one round of the wait -> Monitor -> Choice loop.
//!
//! A round runs when something changed (a results file or marker landed in S3, the cancel
//! sweep found a cancel: both wake the waiting execution) or when the safety net's timeout
//! ends the wait. It reads the wake count first (the next wait is conditional on it), then the
//! Jobs and the workers' results in S3, and sends EvalAI a partial update only when the results
//! changed and the last update is `partial_update_seconds` old (EvalAI allows 60 requests a
//! minute for every submission in flight together); the status on EvalAI is read only to
//! confirm a cancel the sweep found, or every [`STATUS_FALLBACK`] in case the sweep is down
//! (partial updates and that fallback are routine for the shared EvalAI budget: when it is
//! short they wait for a later round, never fail the run). A
//! participant's cancel becomes the S3 cancel marker; a hopeless run (image that cannot be
//! pulled, unschedulable, out of retries) ends with a reason the participant can act on.
//! Transient trouble with EvalAI or S3 skips this round's part instead of failing a run that
//! may last three days. Every round is followed by a hold of at least `MIN_ROUND_INTERVAL`,
//! and counts its history events: near the budget, the run continues as a new execution
//! (`lb_domain::history`).

use lb_pipeline::serve::{Function, Invocation};
use std::collections::BTreeMap;
use std::future::Future;
use std::time::Duration;

use aws_config::SdkConfig;
use lb_aws::dynamo::SubmissionsTable;
use lb_aws::s3::SubmissionStore;
use lb_aws::wake::{WakeState, WakeTable, RETENTION_SECONDS};
use lb_cluster::{Verdict, VerdictPolicy};
use lb_domain::cluster::JobView;
use lb_domain::cost::{self, Ledger, NodeKind};
use lb_domain::history;
use lb_domain::monitor::{self, StatusRead};
use lb_domain::protocol::Marker;
use lb_domain::results::Leaderboard;
use lb_domain::schedule::{queue_wait, safety_net, MIN_ROUND_INTERVAL, POLL_WITHOUT_WAKE};
use lb_domain::settings::Target;
use lb_domain::submission::SubmissionStatus;
use lb_evalai::{EvalAiError, PartialUpdate, Priority, SubmissionRef, WriteOutcome};
use lb_pipeline::clients::{self, RunClients};
use lb_pipeline::cluster::Clusters;
use lb_pipeline::payload::{RunPhase, RunState, SubmissionInfo};
use lb_pipeline::queue::{self, QUEUE_NOTE_INTERVAL};
use lb_pipeline::results::{collect_listed, list};
use lb_pipeline::{FunctionConfig, Result};
use serde::Deserialize;
use tracing::{info, warn};

/// What the Monitor needs: settings, clusters, EvalAI, S3, the submissions table.
#[derive(Debug)]
pub struct Deps {
    /// Settings, EvalAI, clusters, S3, DynamoDB.
    pub clients: RunClients,
    /// How long an unschedulable pod is waited for.
    pub policy: VerdictPolicy,
    /// The wake table.
    pub wake: WakeTable,
    /// The events one execution may take before the run continues as a new one.
    pub history_budget: u64,
}

impl Deps {
    /// Cold start: environment, secrets, clients.
    pub async fn from_env() -> Result<Deps> {
        let (config, sdk) = clients::cold_start().await?;
        let clusters = Clusters::from_env(&sdk);
        Self::load(&sdk, &config, clusters).await
    }

    /// The same from an explicit SDK configuration and cluster access (local mode, tests).
    pub async fn load(
        sdk: &SdkConfig,
        config: &FunctionConfig,
        clusters: Clusters,
    ) -> Result<Deps> {
        let clients = RunClients::load(sdk, config, clusters).await?;
        let wake = WakeTable::new(clients.dynamo.clone(), config.wake_table()?);
        Ok(Deps {
            clients,
            policy: VerdictPolicy::default(),
            wake,
            history_budget: history::EXECUTION_BUDGET,
        })
    }
}

/// The Monitor's input.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MonitorInput {
    /// As Intake established it.
    pub submission: SubmissionInfo,
    /// As Launch or the previous round left it.
    pub run: RunState,
    /// `$$.Execution.Name`: the execution this round runs in (its history is counted).
    #[serde(default)]
    pub execution: Option<String>,
    /// `$$.State.RetryCount`: attempts of this round that failed before this one.
    #[serde(default)]
    pub retries: u64,
}

impl Invocation for MonitorInput {
    fn submission_id(&self) -> Option<u64> {
        Some(self.submission.submission_id)
    }
    fn execution(&self) -> Option<&str> {
        Some(&self.submission.execution)
    }
}

impl Function for Deps {
    const NAME: &'static str = "monitor";
    type Input = MonitorInput;
    type Output = RunState;
    fn handle(&self, input: MonitorInput) -> impl Future<Output = Result<RunState>> {
        handle(input, self)
    }
}

/// What a round saw of the cluster, and the client it saw it with (the round acts on it).
struct Sighting {
    cluster: lb_cluster::Cluster,
    observation: lb_cluster::Observation,
    /// The pods as the GPU count takes them, with what the nodes `usage` does not know yet
    /// are (`None`: a node could not be read this round, and the count waits for the next).
    counted: Option<PodsOnNodes>,
}

/// The submission's Jobs and pods as the cluster reports them now.
async fn observe(
    deps: &Deps,
    deployment: &lb_domain::settings::LeaderboardSettings,
    id: u64,
    usage: &Ledger,
) -> Result<Sighting> {
    let policy = VerdictPolicy {
        queue_limit: Duration::from_secs(deployment.max_queue_hours * 3600),
        ..deps.policy
    };
    let cluster = deps
        .clients
        .clusters
        .connect(deployment)
        .await?
        .with_policy(policy);
    let observation = cluster.observe(&id.to_string()).await?;
    let pods = cost::pods_seen(&observation.jobs, observation.observed_at);
    let mut kinds = NodeKinds::new();
    for node in usage.unknown_nodes(&pods) {
        match cluster.node_kind(&node).await {
            Ok(kind) => {
                kinds.insert(node, kind.unwrap_or_else(NodeKind::unknown));
            }
            Err(e) => {
                warn!(submission_id = id, %node, error = %e, "node not read: GPU usage counted next round");
                return Ok(Sighting {
                    cluster,
                    observation,
                    counted: None,
                });
            }
        }
    }
    let counted = Some(PodsOnNodes { pods, kinds });
    Ok(Sighting {
        cluster,
        observation,
        counted,
    })
}

/// The Jobs' own deadline grows by the time reclaims cost the evaluation (the stretches closed
/// by this round's count), as the participant's limit does. A patch that fails is tried again
/// next round: the value set does not depend on what the Job has.
async fn extend_deadlines(cluster: &lb_cluster::Cluster, jobs: &[JobView], lost: u64, id: u64) {
    for (job, seconds) in monitor::deadlines_to_extend(jobs, lost) {
        if let Err(e) = cluster.extend_deadline(job, seconds).await {
            warn!(submission_id = id, job, error = %e, "Job deadline not extended this round");
        }
    }
}

/// Node name -> what it is.
type NodeKinds = BTreeMap<String, NodeKind>;

/// A round's pods as the GPU count takes them, and the kinds of the nodes new ones run on.
struct PodsOnNodes {
    pods: Vec<cost::PodSeen>,
    kinds: NodeKinds,
}

/// Charges this round's GPU time up to `now`, when the pods were listed (`lb_domain::cost`). A disrupted pod's run-again seconds
/// count from its pair's last results write, so S3 is listed only in a round that sees one.
async fn count_usage(
    store: &SubmissionStore,
    now: u64,
    PodsOnNodes { pods, kinds }: &PodsOnNodes,
    run: &mut RunState,
) {
    let results_at = if pods.iter().any(|p| p.disrupted) {
        lb_pipeline::results::written(store).await
    } else {
        BTreeMap::new()
    };
    run.monitor.usage.account(pods, kinds, &results_at, now);
}

/// One monitor round, then whether the run goes on in this execution: a round whose count
/// of events leaves no room for another continues as a new execution (`lb_domain::history`).
pub async fn handle(input: MonitorInput, deps: &Deps) -> Result<RunState> {
    let MonitorInput {
        submission,
        mut run,
        execution,
        retries,
    } = input;
    let now = clients::now_epoch_seconds();
    let (began, requests) = (
        std::time::Instant::now(),
        deps.clients.dynamo_requests.get(),
    );
    begin_round(&mut run, now, execution.as_deref(), retries);
    if run.monitor.handover {
        hand_over(deps, &submission, &mut run).await;
    }
    // Boxed: the round's future is large, and nested in the runtime's it overflows the
    // compiler's layout depth.
    let mut run = Box::pin(round(&submission, run, deps, now)).await?;
    let monitor = &mut run.monitor;
    if monitor.state == RunPhase::Running
        && history::continue_due(monitor.events, deps.history_budget)
    {
        monitor.generation += 1;
        let next = history::continuation_name(&submission.execution, monitor.generation);
        info!(submission_id = submission.submission_id, events = monitor.events, %next, "history budget reached: continuing as a new execution");
        monitor.continue_as = Some(next);
        monitor.state = RunPhase::Continued;
    }
    // This round's share of the orchestration, up to the next task.
    let round = cost::Orchestration::invocation(
        cost::task_transitions(retries, run.monitor.after()),
        deps.clients.memory_mb,
        u64::try_from(began.elapsed().as_millis()).unwrap_or(u64::MAX),
        deps.clients.dynamo_requests.get().saturating_sub(requests),
    );
    run.monitor.orchestration = run.monitor.orchestration + round;
    Ok(run)
}

/// The queue entry names the execution the reaper's pass checks: a continuation names itself
/// there (until then the pass follows the ended execution's output to it). Tried each round
/// until it is done.
async fn hand_over(deps: &Deps, submission: &SubmissionInfo, run: &mut RunState) {
    let (Some(table), Some(execution)) = (&deps.clients.admission, &run.monitor.execution) else {
        run.monitor.handover = false;
        return;
    };
    let id = submission.submission_id;
    match table.adopt(&submission.leaderboard, id, execution).await {
        Ok(()) => run.monitor.handover = false,
        Err(e) => warn!(submission_id = id, error = %e, "queue entry not handed over this round"),
    }
}

/// One monitor round: the wake count, the cluster, the queue note, the results and EvalAI's
/// status, then the cluster's verdict (`lb_domain::monitor` has the round's rules).
async fn round(
    submission: &SubmissionInfo,
    mut run: RunState,
    deps: &Deps,
    now: u64,
) -> Result<RunState> {
    let id = submission.submission_id;
    let target = deps.clients.settings.target(submission.phase_id)?;
    let wake = read_wake(deps, id, &mut run).await?;
    if !run.queue.admitted {
        return waiting_round(deps, submission, run, wake, target.deployment, now).await;
    }
    let observation = match observe_round(deps, &target, id, &mut run, now).await? {
        Seen::Ended => return Ok(run),
        Seen::Observed(seen) => Some(*seen),
        Seen::Unreachable => None,
    };
    let store = SubmissionStore::new(deps.clients.s3.clone(), &target.deployment.bucket, id);
    let observation = match observation {
        Some(seen) => {
            if let Some(counted) = &seen.counted {
                let observed_at = seen.observation.observed_at.as_second();
                let observed_at = u64::try_from(observed_at).unwrap_or(0);
                count_usage(&store, observed_at, counted, &mut run).await;
            }
            let lost = run.monitor.usage.lost;
            extend_deadlines(&seen.cluster, &seen.observation.jobs, lost, id).await;
            Some(seen.observation)
        }
        None => None,
    };
    let at = submission_ref(submission);
    // The first pair started: now the submission runs, for EvalAI and for the record (before
    // any partial update, which a later `running` would otherwise undo).
    if let Some(observation) = &observation {
        if run.monitor.started_at.is_none() && lb_cluster::observe::started(&observation.jobs) {
            mark_started(deps, submission, observation, &mut run, now).await?;
        }
    }
    // Only a cancel the note found ends the round here; any other word is left to the rest.
    let mut evalai_status = queue_note(deps, submission, at, &mut run, now)
        .await?
        .filter(|s| *s == SubmissionStatus::Cancelled);
    if evalai_status.is_none() {
        let interval = target.deployment.partial_update_seconds;
        let (leaderboard, store) = (target.leaderboard, &store);
        evalai_status =
            send_changed_results(deps, store, at, leaderboard, &mut run, now, interval).await?;
    }
    // The status itself: to confirm a cancel the sweep found (a flag an earlier run left is
    // not believed without it), or now and then in case the sweep is not running.
    if evalai_status.is_none() {
        evalai_status = read_status(deps, id, wake.cancel, &mut run, now).await?;
    }
    if evalai_status == Some(SubmissionStatus::Cancelled) {
        store.put_cancel_marker().await?;
        info!(
            submission_id = id,
            "the participant cancelled: cancel marker written"
        );
        run.monitor.state = RunPhase::Cancelled;
        return Ok(run);
    }
    if let Some(observation) = observation {
        judge(
            deps,
            &target,
            submission,
            &store,
            &mut run,
            observation.verdict,
            now,
        )
        .await;
    }
    Ok(run)
}

/// A round's defaults: the safety net's timeout for the next wait, the least hold, no poll;
/// and the round counted in this execution's history.
fn begin_round(run: &mut RunState, now: u64, execution: Option<&str>, retries: u64) {
    let elapsed = Duration::from_secs(now.saturating_sub(run.launched_at));
    let monitor = &mut run.monitor;
    monitor.rounds += 1;
    monitor.state = RunPhase::Running;
    monitor.continue_as = None;
    monitor.wait_seconds = safety_net(elapsed).as_secs();
    monitor.hold_seconds = MIN_ROUND_INTERVAL.as_secs();
    monitor.poll = false;
    monitor.expires_at = now + RETENTION_SECONDS;
    if let Some(execution) = execution {
        if let Some(entered) = history::entering(monitor.execution.as_deref(), execution) {
            monitor.execution = Some(execution.to_owned());
            monitor.events = entered.events;
            monitor.handover = entered.continued;
        }
    }
    monitor.events += history::round_events(retries);
}

/// The wake count before anything else: a change after this read makes the next wait end at
/// once. Unreadable, the next wait is a plain poll (a wait conditional on a count we do not
/// know could end at once every time).
async fn read_wake(deps: &Deps, id: u64, run: &mut RunState) -> Result<WakeState> {
    match deps.wake.state(id).await {
        Ok(wake) => {
            run.monitor.seen = wake.changes;
            Ok(wake)
        }
        Err(e) if e.is_transient() => {
            warn!(submission_id = id, error = %e, "wake count not read: polling this time");
            run.monitor.poll = true;
            run.monitor.wait_seconds = POLL_WITHOUT_WAKE.as_secs();
            Ok(WakeState::default())
        }
        Err(e) => Err(e.into()),
    }
}

/// What the round saw of the cluster.
enum Seen {
    Observed(Box<Sighting>),
    /// Out of reach this round: the verdict is skipped, the Jobs run on without it.
    Unreachable,
    /// Out of reach for longer than the leaderboard allows: the run has ended.
    Ended,
}

/// The cluster's API out of reach (a 500, a timeout, DescribeCluster failing) skips the
/// verdict this round, as an unreachable S3 or EvalAI skips their part. Only an outage longer
/// than the setting ends the run.
async fn observe_round(
    deps: &Deps,
    target: &Target<'_>,
    id: u64,
    run: &mut RunState,
    now: u64,
) -> Result<Seen> {
    let e = match observe(deps, target.deployment, id, &run.monitor.usage).await {
        Ok(mut seen) => {
            run.monitor.unreachable_since = None;
            seen.observation = seen.observation.expect_jobs(run.jobs);
            return Ok(Seen::Observed(Box::new(seen)));
        }
        Err(e) if e.is_transient() => e,
        Err(e) => return Err(e),
    };
    let since = *run.monitor.unreachable_since.get_or_insert(now);
    warn!(submission_id = id, error = %e.chain(), outage_seconds = now.saturating_sub(since), "cluster not reached this round");
    let bound = target.deployment.max_cluster_outage_hours;
    if let Some(reason) = monitor::outage_ends_run(since, now, bound, e.name()) {
        run.monitor.state = RunPhase::Failed;
        run.monitor.reason = Some(reason);
        return Ok(Seen::Ended);
    }
    // Its recovery writes nothing to S3: look again at the first outage's pace.
    let first_pace = safety_net(Duration::ZERO).as_secs();
    run.monitor.wait_seconds = run.monitor.wait_seconds.min(first_pace);
    Ok(Seen::Unreachable)
}

/// Its place while its pods wait for a GPU; once it runs, the note goes. Returns the status
/// EvalAI refused the note for (cancelled, ended), if it did.
async fn queue_note(
    deps: &Deps,
    submission: &SubmissionInfo,
    at: SubmissionRef,
    run: &mut RunState,
    now: u64,
) -> Result<Option<SubmissionStatus>> {
    // `None`: nothing to do this round (no queue, no entry, or the queue not read).
    let note = match (&deps.clients.admission, run.monitor.started_at) {
        (Some(table), None) => match queue::ahead_of(table, submission).await {
            Ok(Some((ahead, running))) => {
                let ahead = lb_domain::queue::shown_ahead(run.queue.shown, ahead);
                if note_due(run, Some(ahead), now) {
                    let hold = lb_domain::queue::Hold::Capacity;
                    let text = queue::note(table, submission, (ahead, 0, running), hold).await;
                    Some(Some((ahead, text)))
                } else {
                    None
                }
            }
            Ok(None) => None,
            Err(e) => {
                warn!(submission_id = at.submission, error = %e, "queue not read this round");
                None
            }
        },
        (_, Some(_)) if run.queue.shown.is_some() => Some(None),
        _ => None,
    };
    match note {
        Some(note) => show_place(deps, at, run, note, now).await,
        None => Ok(None),
    }
}

/// The cluster's verdict on a run whose status did not end it: too long, still queued,
/// running (progress recorded), finished or failed.
async fn judge(
    deps: &Deps,
    target: &Target<'_>,
    submission: &SubmissionInfo,
    store: &SubmissionStore,
    run: &mut RunState,
    verdict: Verdict,
    now: u64,
) {
    let id = submission.submission_id;
    match verdict {
        Verdict::Running => match (
            run.monitor.started_at,
            monitor::overran(run.monitor.started_at, run.monitor.usage.lost_at(now), now),
        ) {
            (_, Some(reason)) => {
                run.monitor.state = RunPhase::Failed;
                run.monitor.reason = Some(reason);
            }
            // Queued: waiting for capacity is no failure, and the record stays as Intake wrote it.
            (None, None) => {}
            (Some(_), None) => {
                let table = &target.deployment.submissions_table;
                let table = SubmissionsTable::new(deps.clients.dynamo.clone(), table);
                let (time, location) = (clients::now_record_time(), store.location());
                let progress = run.monitor.progress;
                let usage = run.monitor.usage.summary(&deps.clients.settings.prices);
                let marked = table.mark_running(
                    submission.team_id,
                    id,
                    &time,
                    &location,
                    progress,
                    Some(&usage),
                );
                if let Err(e) = marked.await {
                    warn!(submission_id = id, error = %e, "progress not recorded this round");
                }
                // Every Job's logcopy is done (its last upload is in): the Jobs complete within
                // seconds, and nothing more will land in S3 to wake us.
                if ending(store, run.jobs, run.launched_at).await {
                    run.monitor.wait_seconds = run.monitor.wait_seconds.min(ENDING_POLL.as_secs());
                }
            }
        },
        Verdict::Finished => run.monitor.state = RunPhase::Finished,
        Verdict::Failed { kind, message, .. } => {
            info!(submission_id = id, kind = kind.name(), %message, "run failed");
            run.monitor.state = RunPhase::Failed;
            run.monitor.reason = Some(message);
        }
    }
}

/// The status on EvalAI, when a cancel the sweep flagged is to be confirmed or the fallback
/// read is due; `None` when not read this round.
async fn read_status(
    deps: &Deps,
    id: u64,
    cancel_flagged: bool,
    run: &mut RunState,
    now: u64,
) -> Result<Option<SubmissionStatus>> {
    // A cancel to confirm goes ahead of partial updates; the fallback yields to them.
    let priority = match monitor::status_read(cancel_flagged, run.monitor.status_read_at, now) {
        None => return Ok(None),
        Some(StatusRead::ConfirmCancel) => Priority::Urgent,
        Some(StatusRead::Fallback) => Priority::Routine,
    };
    let evalai = deps.clients.evalai.with_priority(priority);
    match evalai.submission(id).await {
        Ok(current) => {
            run.monitor.status_read_at = Some(now);
            Ok(Some(current.status))
        }
        // The budget's decision, not trouble: a later round reads it.
        Err(EvalAiError::OverBudget) => {
            info!(
                submission_id = id,
                "status read deferred by the EvalAI budget"
            );
            Ok(None)
        }
        Err(e) if e.is_transient() => {
            warn!(submission_id = id, error = %e, "status not read this round");
            Ok(None)
        }
        Err(e) => Err(e.into()),
    }
}

/// A round of a submission its team's cap holds back (no Jobs yet): confirm a cancel, end a
/// wait longer than `max_queue_hours`, ask for its turn (admitted: Launch creates its Jobs
/// next), and otherwise show its participant where it stands.
async fn waiting_round(
    deps: &Deps,
    submission: &SubmissionInfo,
    mut run: RunState,
    wake: WakeState,
    deployment: &lb_domain::settings::LeaderboardSettings,
    now: u64,
) -> Result<RunState> {
    let id = submission.submission_id;
    let at = submission_ref(submission);
    let waited = now.saturating_sub(run.queue.arrived_at);
    run.monitor.wait_seconds = queue_wait(Duration::from_secs(waited)).as_secs();
    if read_status(deps, id, wake.cancel, &mut run, now).await? == Some(SubmissionStatus::Cancelled)
    {
        info!(
            submission_id = id,
            "the participant cancelled while it waited for its turn"
        );
        run.monitor.state = RunPhase::Cancelled;
        return Ok(run);
    }
    let limit = deployment.team_limit;
    if let Some(reason) = monitor::queue_limit_ends_wait(waited, deployment.max_queue_hours, limit)
    {
        run.monitor.state = RunPhase::Failed;
        run.monitor.reason = Some(reason);
        return Ok(run);
    }
    let Some(table) = &deps.clients.admission else {
        // No queue configured: every submission has its turn.
        run.monitor.state = RunPhase::Admitted;
        return Ok(run);
    };
    // The entry exists since Launch: its stored arrival stands, whatever is passed here.
    let arrived_ms = submission.arrived_ms.unwrap_or(run.queue.arrived_at * 1000);
    let standing = queue::take_turn(table, submission, arrived_ms, limit).await?;
    if standing.admitted {
        info!(
            submission_id = id,
            ahead = standing.ahead,
            "its turn: admitted"
        );
        run.monitor.state = RunPhase::Admitted;
        return Ok(run);
    }
    let ahead = lb_domain::queue::shown_ahead(run.queue.shown, standing.ahead);
    if !note_due(&run, Some(ahead), now) {
        return Ok(run);
    }
    // The estimate reads the track's pace: only for a note that is written.
    let place = (ahead, standing.team_ahead, 0);
    let note = queue::note(table, submission, place, standing.hold).await;
    if show_place(deps, at, &mut run, Some((ahead, note)), now).await?
        == Some(SubmissionStatus::Cancelled)
    {
        run.monitor.state = RunPhase::Cancelled;
    }
    Ok(run)
}

/// Shows the participant the queue note (`None`: removes it once the run started), when it
/// changed and the last was shown [`QUEUE_NOTE_INTERVAL`] ago. Returns the status EvalAI
/// refused the write for (cancelled, ended), if it did. A throttled or failed write is
/// tried again in a later round, never a failed run.
async fn show_place(
    deps: &Deps,
    at: SubmissionRef,
    run: &mut RunState,
    note: Option<(u32, String)>,
    now: u64,
) -> Result<Option<SubmissionStatus>> {
    let ahead = note.as_ref().map(|(ahead, _)| *ahead);
    if !note_due(run, ahead, now) {
        return Ok(None);
    }
    let evalai = deps.clients.evalai.with_priority(Priority::Routine);
    let outcome = evalai
        .show_queue(
            at,
            note.as_ref().map(|(ahead, text)| (*ahead, text.as_str())),
        )
        .await;
    match outcome {
        Ok(WriteOutcome::Written) => {
            info!(submission_id = at.submission, ?ahead, "queue place shown");
            run.queue.shown = ahead;
            run.queue.shown_at = Some(now);
            Ok(None)
        }
        Ok(WriteOutcome::Cancelled) => Ok(Some(SubmissionStatus::Cancelled)),
        Ok(WriteOutcome::AlreadyFinal(status)) => Ok(Some(status)),
        Err(EvalAiError::OverBudget) => {
            info!(
                submission_id = at.submission,
                "queue place deferred by the EvalAI budget"
            );
            Ok(None)
        }
        Err(e) if e.is_transient() => {
            warn!(submission_id = at.submission, error = %e, "queue place not shown this round");
            Ok(None)
        }
        Err(e) => Err(e.into()),
    }
}

/// Whether the queue note showing `ahead` is written this round (`lb_domain::queue::note_due`).
fn note_due(run: &RunState, ahead: Option<u32>, now: u64) -> bool {
    let shown = (run.queue.shown, run.queue.shown_at);
    lb_domain::queue::note_due(shown, ahead, now, QUEUE_NOTE_INTERVAL.as_secs())
}

/// Where the submission is on EvalAI.
fn submission_ref(submission: &SubmissionInfo) -> SubmissionRef {
    SubmissionRef {
        challenge: submission.challenge_id,
        phase: submission.phase_id,
        submission: submission.submission_id,
    }
}

/// Results: a changed set is merged and sent, at most once per `interval` seconds; an
/// unchanged one costs one listing. Returns the status the PUT's own GET read, if it ran.
async fn send_changed_results(
    deps: &Deps,
    store: &SubmissionStore,
    at: SubmissionRef,
    leaderboard: Leaderboard,
    run: &mut RunState,
    now: u64,
    interval: u64,
) -> Result<Option<SubmissionStatus>> {
    let id = at.submission;
    let listing = match list(store).await {
        Ok(listing) => listing,
        Err(e) if e.is_transient() => {
            warn!(submission_id = id, error = %e.chain(), "results not listed this round");
            run.monitor.wait_seconds = run.monitor.wait_seconds.min(interval);
            return Ok(None);
        }
        Err(e) => return Err(e),
    };
    if listing.fingerprint.is_empty()
        || Some(&listing.fingerprint) == run.monitor.fingerprint.as_ref()
    {
        return Ok(None);
    }
    if let Err(wait) = monitor::partial_update_due(run.monitor.updated_at, now, interval) {
        // Too soon (a round the hold did not cover): the wait ends when it may go.
        run.monitor.wait_seconds = run.monitor.wait_seconds.min(wait.as_secs());
        return Ok(None);
    }
    let current = listing.fingerprint.clone();
    let snapshot =
        match collect_listed(store, listing, leaderboard, &run.pairs, run.repetitions).await {
            Ok(snapshot) => snapshot,
            Err(e) if e.is_transient() => {
                warn!(submission_id = id, error = %e.chain(), "results not read this round");
                run.monitor.wait_seconds = run.monitor.wait_seconds.min(interval);
                return Ok(None);
            }
            Err(e) => {
                // The participant's own files are broken; the sidecar marks that pair crashed.
                warn!(submission_id = id, error = %e.chain(), "results unusable this round");
                run.monitor.fingerprint = Some(current);
                return Ok(None);
            }
        };
    run.monitor.progress = snapshot.progress;
    let update = PartialUpdate {
        result: snapshot.files.results_json(),
        stdout: snapshot.files.stdout.clone(),
        metadata: snapshot
            .files
            .metadata
            .clone()
            .unwrap_or_else(|| "{}".into()),
    };
    match deps.clients.evalai.post_partial(at, &update).await {
        Ok(WriteOutcome::Written) => {
            run.monitor.fingerprint = Some(snapshot.fingerprint);
            run.monitor.updated_at = Some(now);
            run.monitor.hold_seconds = run.monitor.hold_seconds.max(interval);
            Ok(Some(SubmissionStatus::PartiallyEvaluated))
        }
        Ok(WriteOutcome::Cancelled) => Ok(Some(SubmissionStatus::Cancelled)),
        Ok(WriteOutcome::AlreadyFinal(status)) => Ok(Some(status)),
        // Deferred by the EvalAI budget, or skipped for trouble: nothing in S3 will change
        // for it, so the next wait ends when it may go again.
        Err(e) if e.is_transient() => {
            match e {
                EvalAiError::OverBudget => info!(
                    submission_id = id,
                    "partial update deferred by the EvalAI budget"
                ),
                e => warn!(submission_id = id, error = %e, "partial update skipped this round"),
            }
            run.monitor.wait_seconds = run.monitor.wait_seconds.min(interval);
            Ok(None)
        }
        Err(e) => Err(e.into()),
    }
}

/// Tells EvalAI the submission runs (its `started_at`, the participant's execution time, starts
/// now). A transient failure leaves it for the next round; a cancel or an end found instead
/// is left to the rest of the round.
async fn mark_started(
    deps: &Deps,
    submission: &SubmissionInfo,
    observation: &lb_cluster::Observation,
    run: &mut RunState,
    now: u64,
) -> Result<()> {
    let at = submission_ref(submission);
    if let Some(table) = &deps.clients.admission {
        // Out of the count of those waiting: everyone after it moves up.
        if let Err(e) = table
            .mark_running(&submission.leaderboard, submission.submission_id)
            .await
        {
            warn!(submission_id = at.submission, error = %e, "queue entry not marked running");
        }
    }
    let names: Vec<&str> = observation.jobs.iter().map(|j| j.name.as_str()).collect();
    match deps.clients.evalai.mark_running(at, &names.join(",")).await {
        Ok(outcome) => {
            info!(
                submission_id = at.submission,
                ?outcome,
                "first pair started: running"
            );
            run.monitor.started_at = Some(now);
            Ok(())
        }
        Err(e) if e.is_transient() => {
            warn!(submission_id = at.submission, error = %e, "running not sent this round");
            Ok(())
        }
        Err(e) => Err(e.into()),
    }
}

/// How soon to look again once every Job's logcopy is done.
const ENDING_POLL: Duration = Duration::from_secs(5);

/// Whether every Job of this run has written `logcopy-<J>.done` (since the launch).
async fn ending(store: &SubmissionStore, jobs: u32, launched_at: u64) -> bool {
    match store.markers_since(launched_at).await {
        Ok(names) => (0..jobs).all(|job| {
            let marker = Marker::LogcopyDone { job }.to_string();
            names.contains(&marker)
        }),
        Err(e) => {
            warn!(error = %e, "markers not listed this round");
            false
        }
    }
}
