//! Finalize's I/O: each batch of steps `lb_domain::run::closing` asks for, performed side by
//! side and answered in its terms. A failed required step fails the attempt once its batch is
//! done (the state machine retries Finalize, whose every step is idempotent); the best-effort
//! ones (the agent's log, the logs' listing, the pace, the team's wake-up) are logged and
//! answered as unread.

use std::collections::HashMap;
use std::sync::{Mutex, OnceLock};
use std::time::Duration;

use futures_util::StreamExt as _;

use lb_aws::dynamo::{FinalRecord, QualifierTable, SubmissionsTable};
use lb_aws::s3::SubmissionStore;
use lb_aws::tasks::Callbacks;
use lb_cluster::Whose;
use lb_domain::capacity::cost::{self, Totals};
use lb_domain::job::uploads::{self, UploadReport};
use lb_domain::run::audit::{self, Recordings};
use lb_domain::run::closing::{Answer, Left, Merged, Read, Record, Step};
use lb_domain::run::finalize::Posted;
use lb_domain::settings::Target;
use lb_domain::status::RecordStatus;
use lb_domain::submission::SubmissionStatus;
use lb_evalai::FinalUpdate;
use lb_pipeline::clients::{self, Meter};
use lb_pipeline::payload::{PairRoutes, SubmissionInfo};
use lb_pipeline::queue::{TeamQueue, Waker};
use lb_pipeline::results::{self, Snapshot};
use lb_pipeline::{FnError, Result};
use tracing::{info, warn};

use crate::Deps;

/// Recordings' heads (or upload reports) read at once: a result has a recording per route, up
/// to hundreds. Each read holds 256 bytes and a connection, so a typical result (tens of
/// routes) is read in one wave, on the closing's chain of requests one after another.
const HEAD_READS: usize = 64;

/// What the shell keeps between steps: its clients, and the results it read (posted and
/// recorded whole; the closing only sees what it decides on).
pub struct Shell<'a, C> {
    deps: &'a Deps<C>,
    target: &'a Target<'a>,
    submission: &'a SubmissionInfo,
    meter: &'a Meter<'a>,
    store: SubmissionStore,
    table: SubmissionsTable,
    /// The results as read once, beside the other reads of their batch.
    snapshot: OnceLock<Snapshot>,
    /// Why the Jobs could not be stopped or the results read, for the attempt to fail with if
    /// the closing asks ([`Step::TryAgain`]).
    failure: Mutex<Option<FnError>>,
}

impl<'a, C: Callbacks> Shell<'a, C> {
    /// The shell of one Finalize of `submission`'s run.
    pub fn new(
        deps: &'a Deps<C>,
        target: &'a Target<'a>,
        submission: &'a SubmissionInfo,
        meter: &'a Meter<'a>,
    ) -> Self {
        let (s3, dynamo) = (deps.clients.s3.clone(), deps.clients.dynamo.clone());
        let bucket = &target.deployment.bucket;
        Shell {
            deps,
            target,
            submission,
            meter,
            store: SubmissionStore::new(s3, bucket, submission.submission_id),
            table: SubmissionsTable::new(dynamo, &target.deployment.submissions_table),
            snapshot: OnceLock::new(),
            failure: Mutex::new(None),
        }
    }

    fn id(&self) -> u64 {
        self.submission.submission_id
    }

    /// Performs the `steps` of a batch side by side and answers each, in their order. Every
    /// step runs to its end; the first failure is then the batch's.
    pub async fn perform(&mut self, steps: Vec<Step>) -> Result<Vec<Answer>> {
        if let [Step::TryAgain] = steps.as_slice() {
            // The attempt ends with the stop's error or the results' read error, which only the
            // shell holds.
            return match self.failure.get_mut().map(Option::take) {
                Ok(Some(e)) => Err(e),
                _ => Ok(vec![Answer::Done]),
            };
        }
        let this = &*self;
        let asked = steps.into_iter().map(|step| this.perform_beside(step));
        futures_util::future::join_all(asked)
            .await
            .into_iter()
            .collect()
    }

    /// One step, beside the others of its batch.
    async fn perform_beside(&self, step: Step) -> Result<Answer> {
        let sub = self.submission;
        Ok(match step {
            Step::ReadStanding => Answer::Standing(self.standing().await?),
            Step::StopJobs { unlabelled } => self.stopped(unlabelled).await,
            Step::ReadLeft { results } => Answer::Left(self.read_left(results).await?),
            // Only ever alone in its batch (`perform`); answered as a misfit if it were not,
            // which ends Finalize unsettled and said.
            Step::TryAgain => Answer::Done,
            Step::StoreFiles => {
                if let Some(snapshot) = self.merged() {
                    results::store(&self.store, snapshot).await?;
                }
                Answer::Done
            }
            Step::ReadAgentTail { key, bytes } => Answer::Tail(self.agent_tail(&key, bytes).await),
            Step::ReadReports(keys) => Answer::Reports(self.reports(keys).await),
            Step::Admit(tracks) => {
                let table = &self.target.deployment.qualifier_table;
                let table = QualifierTable::new(self.deps.clients.dynamo.clone(), table);
                for track in &tracks {
                    table.admit(sub.team_id, track, sub.submission_id).await?;
                }
                Answer::Done
            }
            Step::ReadEvalAi => {
                let evalai = &self.deps.clients.evalai;
                Answer::OnEvalAi(evalai.before_final(sub.submission_id).await?)
            }
            Step::Post {
                status,
                stdout,
                stderr,
            } => {
                let word = FinalWord {
                    status,
                    stdout,
                    stderr,
                };
                let update = final_update(self.merged(), word);
                let evalai = &self.deps.clients.evalai;
                Answer::Posted(evalai.write_final(sub.into(), &update).await?.into())
            }
            Step::ListRecordings => Answer::Listed(match self.store.recordings().await {
                Ok(listed) => Some(listed),
                Err(e) => {
                    warn!(error = %e, "recordings not listed: they are not audited");
                    None
                }
            }),
            Step::ReadHeads(keys) => Answer::Heads(self.heads(keys).await),
            Step::WriteRecord {
                status,
                error,
                failed_by_platform,
                recordings,
                usage,
            } => {
                let usage = usage.map(|totals| self.with_this_invocation(totals));
                let failure = Failure {
                    status,
                    error,
                    by_platform: failed_by_platform,
                };
                Answer::Recorded(self.write_record(failure, recordings, usage).await?)
            }
            Step::ReadPace => Answer::Pace(self.pace().await),
            Step::RecordPace { durations } => self.keep_pace(&durations).await,
            Step::LeaveQueue => {
                leave_queue(self.deps, sub, self.target).await?;
                Answer::Done
            }
        })
    }

    async fn standing(&self) -> Result<Option<Record>> {
        let standing = self
            .table
            .standing(self.submission.team_id, self.id())
            .await?;
        Ok(standing.map(|s| Record {
            claimed_by: s.claimed_by,
            status: s.status,
            error: s.error,
            failed_by_platform: s.failed_by_platform,
        }))
    }

    /// [`Shell::stop_jobs`] answered: a failure is kept (the closing fails the attempt with it
    /// only if it ends the run).
    async fn stopped(&self, unlabelled: bool) -> Answer {
        match self.stop_jobs(unlabelled).await {
            Ok(unlabelled_left) => Answer::Stopped {
                unlabelled_left,
                failed: false,
            },
            Err(e) => {
                warn!(submission_id = self.id(), error = %e, "the jobs could not be stopped");
                self.keep_failure(e);
                Answer::Stopped {
                    unlabelled_left: false,
                    failed: true,
                }
            }
        }
    }

    /// Only this execution's Jobs, and with `unlabelled` (the claim is this execution's) those
    /// from before the execution label; `true` when some of those were seen and left.
    async fn stop_jobs(&self, unlabelled: bool) -> Result<bool> {
        let (id, execution) = (self.id().to_string(), self.submission.execution.as_str());
        let whose = match unlabelled {
            true => Whose::Claimed(execution),
            false => Whose::Labelled(execution),
        };
        let cluster = self
            .deps
            .clients
            .clusters
            .connect(self.target.deployment)
            .await?;
        let deleted = cluster.delete_all(&id, whose).await?;
        info!(submission_id = self.id(), ?deleted, "jobs deleted");
        let (wait, poll) = (self.deps.delete_wait, Duration::from_secs(2));
        if !cluster.wait_gone(&id, whose, wait, poll).await? {
            warn!(
                submission_id = self.id(),
                "jobs still terminating; results as they are now"
            );
        }
        Ok(deleted.unlabelled_left > 0)
    }

    /// The markers and the results, read at once (the reads are independent).
    async fn read_left(&self, of: Option<(Vec<PairRoutes>, u32)>) -> Result<Left> {
        let results = async {
            let (pairs, repetitions) = of?;
            let leaderboard = self.target.leaderboard;
            Some(results::collect(&self.store, leaderboard, &pairs, repetitions).await)
        };
        let (markers, snapshot) = tokio::join!(self.store.markers(), results);
        let markers = markers?;
        let results = snapshot.map(|read| match read {
            Ok(s) => {
                let merged = Read::Merged(Merged {
                    complete: s.complete,
                    progress: s.progress,
                    finished_pairs: s.finished_pairs.clone(),
                    metrics: s.metrics.clone(),
                    routes: s.routes.clone(),
                    summary: s.files.stdout.clone(),
                });
                // Asked once per Finalize: a second read would be a shell's bug, and the first
                // stands.
                let _ = self.snapshot.set(s);
                merged
            }
            Err(e) => {
                let read = match e.is_transient() {
                    true => Read::NotNow(e.chain()),
                    false => Read::Unusable(e.chain()),
                };
                self.keep_failure(e);
                read
            }
        });
        Ok(Left { markers, results })
    }

    /// Keeps why this attempt may fail, for [`Step::TryAgain`].
    fn keep_failure(&self, e: FnError) {
        if let Ok(mut kept) = self.failure.lock() {
            *kept = Some(e);
        }
    }

    fn merged(&self) -> Option<&Snapshot> {
        self.snapshot.get()
    }

    /// The end of a crashed agent's output, as stored. Its container holds no secret (no AWS
    /// credentials, no token), so its output has none of ours to leak.
    async fn agent_tail(&self, key: &str, bytes: u64) -> Option<Vec<u8>> {
        match self.store.get_tail(key, bytes).await {
            Ok(tail) => tail,
            Err(e) => {
                warn!(%key, error = %e, "the agent's log could not be read");
                None
            }
        }
    }

    /// The record: every metric of the leaderboard as EvalAI got it (`-` where it got none),
    /// and what the run cost. `false` when the claim moved on while this ran.
    async fn write_record(
        &self,
        Failure {
            status,
            error,
            by_platform,
        }: Failure,
        recordings: Option<Recordings>,
        usage: Option<Totals>,
    ) -> Result<bool> {
        if let Some(audited) = recordings.as_ref().filter(|r| !r.complete()) {
            warn!(
                passed = audited.passed,
                expected = audited.expected,
                failures = ?audited.failures,
                "FINISHED without every route's CARLA recording passing: these scores cannot be audited"
            );
        }
        let snapshot = self.merged();
        let metrics = snapshot.map(|s| s.metrics.as_slice()).unwrap_or_default();
        let record = FinalRecord {
            status,
            end_time: clients::now_record_time(),
            results: self.store.location(),
            metrics: (self.target.leaderboard.metrics().iter())
                .map(|m| {
                    let value = metrics.iter().find(|(a, _)| *a == m.attribute);
                    (m.attribute, value.map(|(_, v)| v.py_str()))
                })
                .collect(),
            progress: snapshot.map_or((0, 0), |s| s.progress),
            error,
            failed_by_platform: by_platform,
            recordings,
            usage,
        };
        let sub = self.submission;
        let ours = (self.table)
            .finish(sub.team_id, sub.submission_id, &sub.execution, &record)
            .await?;
        if !ours {
            // A resume claimed it anew: EvalAI had the final word before that.
            warn!(
                submission_id = self.id(),
                "the claim moved on; the record is the new execution's"
            );
        }
        info!(submission_id = self.id(), %status, "finalized");
        Ok(ours)
    }

    /// The run's usage as the closing counted it, with this Finalize's share of the
    /// orchestration (the states after it included).
    fn with_this_invocation(&self, totals: Totals) -> Totals {
        let this = self.meter.invocation(cost::CLOSING_TRANSITIONS);
        Totals {
            orchestration: totals.orchestration.map(|o| o + this),
            ..totals
        }
    }

    /// The first bytes of each recording, a few at a time (one per route of the result); a
    /// head that cannot be read is left out, and its route fails the audit.
    async fn heads(&self, keys: Vec<String>) -> HashMap<String, Vec<u8>> {
        let store = &self.store;
        read_each(keys, |key| async move {
            match store.get_head(&key, audit::HEAD_BYTES).await {
                Ok(head) => head.map(|head| (key, head)),
                Err(e) => {
                    warn!(%key, error = %e, "a recording's head could not be read");
                    None
                }
            }
        })
        .await
    }

    /// The Jobs' upload reports, read at once (a report that cannot be read, or is not one,
    /// is left out, and said).
    async fn reports(&self, keys: Vec<String>) -> Vec<UploadReport> {
        let store = &self.store;
        read_each(keys, |key| async move {
            match store.get_tail(&key, uploads::MAX_REPORT_BYTES as u64).await {
                Ok(Some(bytes)) => {
                    let report = UploadReport::parse(&bytes);
                    if report.is_none() {
                        warn!(%key, "the upload report is not one");
                    }
                    report
                }
                Ok(None) => None,
                Err(e) => {
                    warn!(%key, error = %e, "the upload report could not be read");
                    None
                }
            }
        })
        .await
    }

    /// The track's pace, for a finished evaluation's duration to join (the queue note's
    /// estimate). Best effort: unread, it is not written.
    async fn pace(&self) -> Option<Vec<u64>> {
        let admission = &self.deps.clients.admission;
        match admission.pace(self.submission).await {
            Ok(recent) => Some(recent),
            Err(e) => {
                warn!(submission_id = self.id(), error = %e, "pace not read: not recorded");
                None
            }
        }
    }

    /// The track's pace with this evaluation's duration first. Best effort.
    async fn keep_pace(&self, durations: &[u64]) -> Answer {
        let admission = &self.deps.clients.admission;
        if let Err(e) = admission.keep_pace(self.submission, durations).await {
            warn!(submission_id = self.id(), error = %e, "pace not recorded");
        }
        Answer::Done
    }
}

/// `read` of each key, [`HEAD_READS`] at a time; a key it gives nothing for is left out.
async fn read_each<T, C, F>(keys: Vec<String>, read: impl FnMut(String) -> F) -> C
where
    F: std::future::Future<Output = Option<T>>,
    C: Default + Extend<T>,
{
    futures_util::stream::iter(keys)
        .map(read)
        .buffer_unordered(HEAD_READS)
        .filter_map(std::future::ready)
        .collect()
        .await
}

/// The record's final status, and why when it failed (whose failure too).
struct Failure {
    status: RecordStatus,
    error: Option<String>,
    by_platform: bool,
}

/// What the final EvalAI update says besides the files: the status, and the texts shown as
/// the submission's stdout and stderr.
pub struct FinalWord {
    pub status: SubmissionStatus,
    pub stdout: String,
    pub stderr: String,
}

/// The final EvalAI update: scores for a finished run; for a failed one, the partial summary
/// as stdout and the reason as stderr.
fn final_update(snapshot: Option<&Snapshot>, word: FinalWord) -> FinalUpdate {
    FinalUpdate {
        status: word.status,
        result: snapshot.map_or_else(|| "[]".to_string(), |s| s.files.results_json()),
        stdout: word.stdout,
        stderr: word.stderr,
        metadata: snapshot
            .and_then(|s| s.files.metadata.clone())
            .unwrap_or_else(|| "{}".into()),
    }
}

/// The final update with its read before and after, at once (a refusal, which has no run).
pub async fn post_final<C>(
    deps: &Deps<C>,
    submission: &SubmissionInfo,
    word: FinalWord,
) -> Result<Posted> {
    let update = final_update(None, word);
    let evalai = &deps.clients.evalai;
    Ok(evalai.post_final(submission.into(), &update).await?.into())
}

/// Gives the team its place back and takes the submission out of its leaderboard's queue,
/// last: EvalAI has its final status before the team's next submission is admitted, so the
/// team never shows more than its `team_limit` evaluations in progress. Repeating it is
/// harmless; the team's next waiting submissions are woken (best effort: their polls come).
async fn leave_queue<C: Callbacks>(
    deps: &Deps<C>,
    submission: &SubmissionInfo,
    target: &Target<'_>,
) -> Result<()> {
    let team = TeamQueue {
        queue: submission.leaderboard.as_str(),
        team: submission.team_id,
        limit: target.deployment.team_limit,
    };
    let waker = Waker {
        wakes: &deps.wakes,
        callbacks: &deps.callbacks,
        now: clients::now_epoch_seconds(),
    };
    let id = submission.submission_id;
    if deps.clients.admission.leave(team, id, waker).await? {
        info!(submission_id = id, "left the queue");
    }
    Ok(())
}
