//! The Monitor's I/O: each step the round asks for, performed and answered in the round's
//! terms. Transient trouble is logged here and answered as "not this round"; only errors no
//! later round can change are returned (the state machine's Retry and Catch see them).

use std::collections::BTreeMap;

use lb_aws::dynamo::SubmissionsTable;
use lb_aws::s3::SubmissionStore;
use lb_cluster::autoscaler::ScaleUpWord;
use lb_cluster::Cluster;
use lb_domain::capacity::consolidation::Running;
use lb_domain::capacity::cost::Totals;
use lb_domain::capacity::queue::{Hold, Place};
use lb_domain::run::metrics::Metric;
use lb_domain::run::monitor::StatusRead;
use lb_domain::run::round::{Answer, Collected, NodeRead, Step, Write};
use lb_domain::settings::Target;
use lb_evalai::{EvalAiError, PartialUpdate, Priority, SubmissionRef, WriteOutcome};
use lb_pipeline::clients;
use lb_pipeline::payload::{PairRoutes, SubmissionInfo};
use lb_pipeline::results::{self, Listing, Snapshot};
use lb_pipeline::{FnError, Result};
use tracing::{info, warn};

use crate::Deps;

/// What the shell keeps between a round's steps: its clients and what a later step acts on
/// (the cluster it observed with, the results it listed and merged).
pub struct Shell<'a> {
    deps: &'a Deps,
    target: &'a Target<'a>,
    submission: &'a SubmissionInfo,
    store: SubmissionStore,
    cluster: Option<Cluster>,
    listing: Option<Listing>,
    snapshot: Option<Snapshot>,
    /// When the newest results read this round were written (epoch seconds).
    newest: Option<u64>,
    /// When each pair's results were written, as this round's listing found them.
    written: Option<BTreeMap<u32, u64>>,
}

impl<'a> Shell<'a> {
    /// The shell of one round of `submission`.
    pub fn new(deps: &'a Deps, target: &'a Target<'a>, submission: &'a SubmissionInfo) -> Self {
        let bucket = &target.deployment.bucket;
        let store = SubmissionStore::new(deps.clients.s3.clone(), bucket, submission.submission_id);
        Shell {
            deps,
            target,
            submission,
            store,
            cluster: None,
            listing: None,
            snapshot: None,
            newest: None,
            written: None,
        }
    }

    fn id(&self) -> u64 {
        self.submission.submission_id
    }

    fn at(&self) -> SubmissionRef {
        self.submission.into()
    }

    /// Performs `step`.
    pub async fn perform(&mut self, step: Step) -> Result<Answer> {
        let admission = &self.deps.clients.admission;
        Ok(match step {
            Step::Adopt(execution) => Answer::Adopted(self.adopt(&execution).await),
            Step::ReadWake => Answer::Wake(self.read_wake().await?),
            Step::ReadStatus(read) => Answer::Status(self.read_status(read).await?),
            Step::TakeTurn { arrived_ms, limit } => Answer::Turn(
                admission
                    .take_turn(self.submission, arrived_ms, limit)
                    .await?,
            ),
            Step::ReadAhead => Answer::Ahead(self.read_ahead().await),
            Step::ComposeNote(place, hold) => Answer::Note(self.compose(place, hold).await),
            Step::ShowPlace(note) => Answer::Shown(self.show_place(note).await?),
            Step::Observe => self.observe().await?,
            Step::ReadAutoscaler(uid) => Answer::Autoscaler(self.autoscaler_word(&uid).await),
            Step::ReadNodes(nodes) => Answer::Nodes(self.read_nodes(nodes).await),
            Step::ResultsWritten => Answer::ResultsWritten(match &self.written {
                Some(written) => written.clone(),
                None => results::written(&self.store).await,
            }),
            Step::Evict(pods) => Answer::Moved(self.evict(pods).await),
            Step::SetDeadlines(jobs) => self.set_deadlines(jobs).await,
            Step::MarkStarted(jobs) => Answer::Started(self.mark_started(&jobs).await?),
            Step::ListResults => Answer::Listed(self.list().await?),
            Step::CollectResults { pairs, repetitions } => {
                Answer::Collected(self.collect(&pairs, repetitions).await?)
            }
            Step::StoreFiles => Answer::Stored(self.store_files().await?),
            Step::PostPartial => Answer::Posted(self.post_partial().await?),
            Step::PutCancelMarker => {
                self.store.put_cancel_marker().await?;
                info!(
                    submission_id = self.id(),
                    "the participant cancelled: cancel marker written"
                );
                Answer::Done
            }
            Step::RecordRunning {
                progress,
                usage,
                image,
            } => self.record(progress, (&usage, image.as_deref())).await,
            Step::ListMarkers { since } => Answer::Markers(self.markers(since).await),
            Step::Done => Answer::Done,
        })
    }

    /// The queue entry names the execution the reaper's pass checks; tried each round until
    /// it is done.
    async fn adopt(&self, execution: &str) -> bool {
        let adopted = self
            .deps
            .clients
            .admission
            .adopt(self.submission, execution);
        match adopted.await {
            Ok(()) => true,
            Err(e) => {
                warn!(submission_id = self.id(), error = %e, "queue entry not handed over this round");
                false
            }
        }
    }

    async fn read_wake(&self) -> Result<Option<(u64, bool)>> {
        match self.deps.wake.state(self.id()).await {
            Ok(wake) => Ok(Some((wake.changes, wake.cancel))),
            Err(e) if e.is_transient() => {
                warn!(submission_id = self.id(), error = %e, "wake count not read: polling this time");
                Ok(None)
            }
            Err(e) => Err(e.into()),
        }
    }

    /// The status on EvalAI: a cancel to confirm goes ahead of partial updates; the fallback
    /// yields to them.
    async fn read_status(
        &self,
        read: StatusRead,
    ) -> Result<Option<lb_domain::submission::SubmissionStatus>> {
        let priority = match read {
            StatusRead::ConfirmCancel => Priority::Urgent,
            StatusRead::Fallback => Priority::Routine,
        };
        let evalai = self.deps.clients.evalai.with_priority(priority);
        match evalai.submission(self.id()).await {
            Ok(current) => Ok(Some(current.status)),
            Err(e) => not_now(self.id(), "status read", e).map(|()| None),
        }
    }

    async fn read_ahead(&self) -> Option<(u32, u32)> {
        match self.deps.clients.admission.ahead_of(self.submission).await {
            Ok(ahead) => ahead,
            Err(e) => {
                warn!(submission_id = self.id(), error = %e, "queue not read this round");
                None
            }
        }
    }

    async fn compose(&self, place: Place, hold: Hold) -> String {
        self.deps
            .clients
            .admission
            .note(self.submission, (place, hold), clients::now_epoch_seconds())
            .await
    }

    async fn show_place(&self, note: Option<(u32, String)>) -> Result<Write> {
        let evalai = self.deps.clients.evalai.with_priority(Priority::Routine);
        let note = note.as_ref().map(|(ahead, text)| (*ahead, text.as_str()));
        let shown = evalai.show_queue(self.at(), note).await;
        if matches!(shown, Ok(WriteOutcome::Written)) {
            info!(submission_id = self.id(), ahead = ?note.map(|n| n.0), "queue place shown");
        }
        written(self.id(), "queue place", shown)
    }

    /// The submission's Jobs and pods as the cluster reports them now. The cluster out of
    /// reach (a 500, a timeout, DescribeCluster failing) skips the verdict this round.
    async fn observe(&mut self) -> Result<Answer> {
        let seen = async {
            let clusters = &self.deps.clients.clusters;
            let cluster = clusters.connect(self.target.deployment).await?;
            let observation = cluster.observe(&self.id().to_string()).await?;
            Ok::<_, FnError>((cluster, observation))
        };
        match seen.await {
            Ok((cluster, observation)) => {
                self.cluster = Some(cluster);
                Ok(Answer::Observed(Box::new(observation)))
            }
            Err(e) if e.is_transient() => {
                warn!(submission_id = self.id(), error = %e.chain(), "cluster not reached this round");
                Ok(Answer::Unreachable(e.name()))
            }
            Err(e) => Err(e),
        }
    }

    /// The Cluster Autoscaler's latest word on pod `uid` (`None`: none, or not read).
    async fn autoscaler_word(&self, uid: &str) -> Option<ScaleUpWord> {
        self.cluster.as_ref()?.autoscaler_word(uid).await
    }

    /// The nodes asked for, each read once (`None`: one could not be read).
    async fn read_nodes(&self, nodes: Vec<String>) -> Option<BTreeMap<String, NodeRead>> {
        let cluster = self.cluster.as_ref()?;
        let mut read = BTreeMap::new();
        for node in nodes {
            match cluster.node(&node).await {
                Ok(found) => _ = read.insert(node, found),
                Err(e) => {
                    warn!(submission_id = self.id(), %node, error = %e, "node not read: GPU usage counted next round");
                    return None;
                }
            }
        }
        Some(read)
    }

    /// Evicts each pod the round moves off its drained node: the Jobs whose evictions were
    /// accepted. One that fails waits for its pair's next write.
    async fn evict(&self, pods: Vec<Running>) -> Vec<u32> {
        let Some(cluster) = &self.cluster else {
            return Vec::new();
        };
        let mut moved = Vec::new();
        for pod in pods {
            match cluster.evict(&pod.pod).await {
                Ok(true) => {
                    info!(
                        submission_id = self.id(),
                        pod = pod.pod,
                        node = pod.node,
                        job = pod.job,
                        "pair moved off a drained node at its route's end"
                    );
                    moved.push(pod.job);
                }
                Ok(false) => {}
                Err(e) => {
                    warn!(submission_id = self.id(), pod = pod.pod, error = %e, "pod not moved this round");
                }
            }
        }
        moved
    }

    /// A patch that fails is tried again next round: the value set does not depend on what
    /// the Job has.
    async fn set_deadlines(&self, jobs: Vec<(String, u64)>) -> Answer {
        let Some(cluster) = &self.cluster else {
            return Answer::Done;
        };
        for (job, seconds) in jobs {
            if let Err(e) = cluster.set_deadline(&job, seconds).await {
                warn!(submission_id = self.id(), job, error = %e, "Job deadline not set this round");
            }
        }
        Answer::Done
    }

    /// Out of the count of those waiting, and `running` on EvalAI (its `started_at`, the
    /// participant's execution time, starts now).
    async fn mark_started(&self, jobs: &[String]) -> Result<bool> {
        if let Err(e) = self
            .deps
            .clients
            .admission
            .mark_running(self.submission, clients::now_epoch_seconds())
            .await
        {
            warn!(submission_id = self.id(), error = %e, "queue entry not marked running");
        }
        match self
            .deps
            .clients
            .evalai
            .mark_running(self.at(), &jobs.join(","))
            .await
        {
            Ok(outcome) => {
                info!(
                    submission_id = self.id(),
                    ?outcome,
                    "first pair started: running"
                );
                Ok(true)
            }
            Err(e) => not_now(self.id(), "running", e).map(|()| false),
        }
    }

    async fn list(&mut self) -> Result<Option<String>> {
        match results::list(&self.store).await {
            Ok(listing) => {
                let fingerprint = listing.fingerprint.clone();
                self.newest = listing.newest();
                self.written = Some(listing.written());
                self.listing = Some(listing);
                Ok(Some(fingerprint))
            }
            Err(e) if e.is_transient() => {
                warn!(submission_id = self.id(), error = %e.chain(), "results not listed this round");
                Ok(None)
            }
            Err(e) => Err(e),
        }
    }

    async fn collect(&mut self, pairs: &[PairRoutes], repetitions: u32) -> Result<Collected> {
        let Some(listing) = self.listing.take() else {
            return Ok(Collected::NotNow);
        };
        let leaderboard = self.target.leaderboard;
        let collected =
            results::collect_listed(&self.store, listing, leaderboard, pairs, repetitions);
        match collected.await {
            Ok(snapshot) => {
                let merged = Collected::Merged {
                    progress: snapshot.progress,
                    fingerprint: snapshot.fingerprint.clone(),
                    content: snapshot.content.clone(),
                };
                self.snapshot = Some(snapshot);
                Ok(merged)
            }
            Err(e) if e.is_transient() => {
                warn!(submission_id = self.id(), error = %e.chain(), "results not read this round");
                Ok(Collected::NotNow)
            }
            Err(e) => {
                // The participant's own files are broken; the sidecar marks that pair crashed.
                warn!(submission_id = self.id(), error = %e.chain(), "results unusable this round");
                Ok(Collected::Unusable)
            }
        }
    }

    /// The merge and the files EvalAI gets kept in S3 before they are sent.
    async fn store_files(&mut self) -> Result<bool> {
        let Some(snapshot) = &self.snapshot else {
            return Ok(false);
        };
        match results::store(&self.store, snapshot).await {
            Ok(()) => Ok(true),
            Err(e) if e.is_transient() => {
                warn!(submission_id = self.id(), error = %e.chain(), "results not stored this round");
                self.snapshot = None;
                Ok(false)
            }
            Err(e) => Err(e),
        }
    }

    async fn post_partial(&mut self) -> Result<Write> {
        let Some(snapshot) = self.snapshot.take() else {
            return Ok(Write::NotNow);
        };
        let files = snapshot.files;
        let update = PartialUpdate {
            result: files.results_json(),
            stdout: files.stdout,
            metadata: files.metadata.unwrap_or_else(|| "{}".into()),
        };
        let posted = self
            .deps
            .clients
            .evalai
            .post_partial(self.at(), &update)
            .await;
        let write = written(self.id(), "partial update", posted)?;
        if write == Write::Written {
            let delay = self
                .newest
                .map(|at| clients::now_epoch_seconds().saturating_sub(at));
            // Sent even at 0 s: its sample count is the updates sent.
            lb_pipeline::metrics::sample_count(
                Metric::PartialUpdateDelay,
                delay.unwrap_or(0) as f64,
            );
        }
        Ok(write)
    }

    /// Progress and usage on the record; a failure is tried again next round.
    async fn record(
        &self,
        progress: (u64, u64),
        (usage, image): (&Totals, Option<&str>),
    ) -> Answer {
        let table = &self.target.deployment.submissions_table;
        let table = SubmissionsTable::new(self.deps.clients.dynamo.clone(), table);
        let (time, location) = (clients::now_record_time(), self.store.location());
        let (team, id) = (self.submission.team_id, self.id());
        let marked =
            table.mark_running(team, id, (&time, &location), progress, (Some(usage), image));
        if let Err(e) = marked.await {
            warn!(submission_id = id, error = %e, "progress not recorded this round");
        }
        // The queue's copy, for the forecasts of those waiting.
        let admission = &self.deps.clients.admission;
        if let Err(e) = admission.record_progress(self.submission, progress).await {
            warn!(submission_id = id, error = %e, "progress not kept on the queue entry this round");
        }
        Answer::Done
    }

    /// The status markers written since `since` (epoch seconds; `None`: not listed).
    async fn markers(&self, since: u64) -> Option<Vec<String>> {
        match self.store.markers_since(since).await {
            Ok(names) => Some(names),
            Err(e) => {
                warn!(submission_id = self.id(), error = %e, "markers not listed this round");
                None
            }
        }
    }
}

/// An EvalAI write's outcome in the round's terms: deferred by the budget or transient
/// trouble is "not now"; anything else no later round changes is an error.
fn written(
    id: u64,
    what: &str,
    outcome: std::result::Result<WriteOutcome, EvalAiError>,
) -> Result<Write> {
    match outcome {
        Ok(WriteOutcome::Written) => Ok(Write::Written),
        Ok(WriteOutcome::Cancelled) => Ok(Write::Cancelled),
        Ok(WriteOutcome::AlreadyFinal(status)) => Ok(Write::AlreadyFinal(status)),
        Err(e) => not_now(id, what, e).map(|()| Write::NotNow),
    }
}

/// Logs an EvalAI call left for a later round (the budget's decision, or transient trouble);
/// any other error is returned.
fn not_now(id: u64, what: &str, e: EvalAiError) -> Result<()> {
    match e {
        EvalAiError::OverBudget => {
            info!(submission_id = id, what, "deferred by the EvalAI budget");
            Ok(())
        }
        e if e.is_transient() => {
            warn!(submission_id = id, what, error = %e, "not done this round");
            Ok(())
        }
        e => Err(e.into()),
    }
}
