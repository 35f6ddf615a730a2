//! The Monitor's round without I/O: the shell performs each [`Step`] the round asks for and
//! gives back what it found as an [`Answer`]; the round decides, in this one place, which rule
//! wins (a cancel before the verdict, the queue note before the results, the shortest wait)
//! and leaves the run state for the next wait.
//!
//! A round reads the wake count first (the next wait is conditional on it). A submission its
//! team's cap holds back confirms a cancel, ends a wait past the queue limit, asks for its turn
//! and otherwise shows its place. An admitted one looks at the cluster (charging the GPUs and
//! growing the Jobs' deadlines by the time reclaims cost), tells EvalAI when the first pair
//! started, keeps the queue note, sends changed results at most once per interval, reads
//! EvalAI's status only to confirm a cancel or as a fallback, and then takes the cluster's
//! verdict. Trouble with one service skips its part of the round, never the run.

use std::collections::BTreeMap;
use std::time::Duration;

use crate::capacity::consolidation;
use crate::capacity::cost::{self, InstancePrice, NodeKind, PodSeen, Totals};
use crate::capacity::queue::{self, Hold, Place, Standing};
use crate::cluster::autoscaler::ScaleUpWord;
use crate::cluster::disruption::{self, Disruption, NodeFacts};
use crate::cluster::view::{self as cluster, Observation, Verdict, VerdictPolicy};
use crate::job::protocol::Marker;
use crate::run::history;
use crate::run::monitor::{self, StatusRead};
use crate::run::schedule::{queue_wait, safety_net, MIN_ROUND_INTERVAL, POLL_WITHOUT_WAKE};
use crate::run::state::{PairRoutes, RunPhase, RunState};
use crate::submission::SubmissionStatus;

/// How soon to look again once every Job's logcopy is done.
pub const ENDING_POLL: Duration = Duration::from_secs(5);

/// What a round needs to know besides the run state: the clock, the leaderboard's bounds.
#[derive(Debug, Clone, PartialEq)]
pub struct Context {
    /// Now, epoch seconds.
    pub now: u64,
    /// `$$.Execution.Name`, when the state machine passed it.
    pub execution: Option<String>,
    /// `$$.State.RetryCount`.
    pub retries: u64,
    /// When it arrived in the queue (epoch ms), as Intake read it (`None`: the stored arrival).
    pub arrived_ms: Option<u64>,
    /// The leaderboard's `partial_update_seconds`.
    pub partial_update_seconds: u64,
    /// The leaderboard's `max_queue_hours`.
    pub max_queue_hours: u64,
    /// The leaderboard's `max_cluster_outage_hours`.
    pub max_cluster_outage_hours: u64,
    /// The leaderboard's `team_limit`.
    pub team_limit: u32,
    /// The leaderboard's `move_window_seconds`.
    pub move_window_seconds: u64,
    /// The least interval between two rewrites of the queue note, seconds.
    pub note_interval: u64,
    /// The GPU prices the record's usage is priced at.
    pub prices: BTreeMap<String, InstancePrice>,
    /// How long the wake item is kept after a round, seconds (its DynamoDB TTL).
    pub wake_retention: u64,
    /// How patient the cluster's verdict is (its `queue_limit` the leaderboard's
    /// `max_queue_hours`).
    pub policy: VerdictPolicy,
}

/// What the shell is asked to do next.
#[derive(Debug, Clone, PartialEq)]
pub enum Step {
    /// Name this execution on the queue entry ([`Answer::Adopted`]).
    Adopt(String),
    /// Read the wake count ([`Answer::Wake`]).
    ReadWake,
    /// Read the status on EvalAI ([`Answer::Status`]), urgent to confirm a cancel.
    ReadStatus(StatusRead),
    /// Ask for its turn ([`Answer::Turn`]).
    TakeTurn {
        /// When it arrived (epoch ms): its place in the queue.
        arrived_ms: u64,
        /// Its team's cap.
        limit: u32,
    },
    /// Count who is ahead of an admitted submission whose pods wait ([`Answer::Ahead`]).
    ReadAhead,
    /// Word the queue note for this place ([`Answer::Note`]): (ahead, of its team, running).
    ComposeNote(Place, Hold),
    /// Show the participant its place, or remove the note once it runs ([`Answer::Shown`]).
    ShowPlace(Option<(u32, String)>),
    /// Look at the submission's Jobs and pods ([`Answer::Observed`] or
    /// [`Answer::Unreachable`]).
    Observe,
    /// Read the Cluster Autoscaler's latest word on the pod with this uid, one the scheduler
    /// has not placed for the grace ([`Answer::Autoscaler`]).
    ReadAutoscaler(String),
    /// Read these nodes: the kinds of those new pods run on, whether the node of a pod the
    /// kubelet evicted is leaving, and whether the nodes of pods that may move are drained
    /// ([`Answer::Nodes`]).
    ReadNodes(Vec<String>),
    /// When each Job's pair last wrote results (epoch seconds; [`Answer::ResultsWritten`]).
    ResultsWritten,
    /// Evict these pods, each from a drained node just after its pair's results were written
    /// ([`consolidation`]; [`Answer::Moved`]).
    Evict(Vec<consolidation::Running>),
    /// Set these Jobs' `activeDeadlineSeconds` to these seconds: grown by the time reclaims
    /// cost, or [`monitor::END_NOW`] for a pair out of retries ([`Answer::Done`]; a failed
    /// patch is tried again next round).
    SetDeadlines(Vec<(String, u64)>),
    /// Tell EvalAI and the queue the first pair started ([`Answer::Started`]).
    MarkStarted(Vec<String>),
    /// List the workers' results ([`Answer::Listed`]).
    ListResults,
    /// Read and merge the listed results of these pairs ([`Answer::Collected`]).
    CollectResults {
        /// The pairs and the routes each runs.
        pairs: Vec<PairRoutes>,
        /// Repetitions of each route.
        repetitions: u32,
    },
    /// Keep the merged results and the files EvalAI gets in S3, before they are sent
    /// ([`Answer::Stored`]).
    StoreFiles,
    /// Send the merged results as a partial update ([`Answer::Posted`]).
    PostPartial,
    /// Write the S3 cancel marker ([`Answer::Done`]): the sidecars stop the Jobs.
    PutCancelMarker,
    /// Record progress and usage on the submission's record ([`Answer::Done`]).
    RecordRunning {
        /// Routes done and planned.
        progress: (u64, u64),
        /// The GPUs and orchestration so far.
        usage: Totals,
        /// The participant image's digest every pod runs, once one was pulled.
        image: Option<String>,
    },
    /// The status markers written since the run's launch (epoch seconds;
    /// [`Answer::Markers`]): whether every Job's logcopy is done.
    ListMarkers {
        /// The run's launch.
        since: u64,
    },
    /// The round is over: [`Round::finish`] gives the run state.
    Done,
}

/// The outcome of a write to EvalAI.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Write {
    /// Written.
    Written,
    /// Refused: the participant cancelled.
    Cancelled,
    /// Refused: the submission already has this final status.
    AlreadyFinal(SubmissionStatus),
    /// Deferred by the budget or skipped for transient trouble: a later round tries again.
    NotNow,
}

/// The workers' merged results, as far as the round needs them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Collected {
    /// Merged: routes done and planned, the fingerprint of what was read and the digest of
    /// what it says.
    Merged {
        /// Routes done and planned.
        progress: (u64, u64),
        /// What was read (the files' ETags).
        fingerprint: String,
        /// The merged records' digest: the same records rewritten (a trailing newline
        /// toggled) give the same digest, so nothing new is sent.
        content: String,
    },
    /// Transient trouble: tried again in a later round.
    NotNow,
    /// The participant's files are broken (the sidecar marks that pair crashed): not read
    /// again until they change.
    Unusable,
}

/// What the cluster showed this round, as the round judged it.
#[derive(Debug, Clone, PartialEq)]
struct Sighting {
    /// The Jobs, their pods and the verdict.
    observation: Observation,
    /// The pods as the GPU count takes them and the kinds of the nodes new ones run on
    /// (`None`: a node could not be read, and the count waits for the next round).
    counted: Option<(Vec<PodSeen>, BTreeMap<String, NodeKind>)>,
}

/// A node as the shell read it: its kind and its facts (`None`: it is gone).
pub type NodeRead = Option<(NodeKind, NodeFacts)>;

/// What the shell found doing a [`Step`].
#[derive(Debug, Clone, PartialEq)]
pub enum Answer {
    /// The step was done (or failed in a way the round does not act on).
    Done,
    /// The queue entry names this execution now.
    Adopted(bool),
    /// The wake count and the sweep's cancel flag (`None`: not read, poll instead).
    Wake(Option<(u64, bool)>),
    /// The status on EvalAI (`None`: not read this round).
    Status(Option<SubmissionStatus>),
    /// Where it stands in the queue.
    Turn(Standing),
    /// Ahead of it and running (`None`: no entry, or the queue not read).
    Ahead(Option<(u32, u32)>),
    /// The queue note's words.
    Note(String),
    /// What EvalAI did with the queue note.
    Shown(Write),
    /// The cluster as seen.
    Observed(Box<Observation>),
    /// The Cluster Autoscaler's latest word on the pod asked about (`None`: none, or not read).
    Autoscaler(Option<ScaleUpWord>),
    /// The files EvalAI gets are in S3 (`false`: not this round, so nothing is sent).
    Stored(bool),
    /// The nodes asked for (`None`: one could not be read, and the count waits).
    Nodes(Option<BTreeMap<String, NodeRead>>),
    /// The cluster's API was out of reach; the error's stable name.
    Unreachable(&'static str),
    /// When each Job's pair last wrote results.
    ResultsWritten(BTreeMap<u32, u64>),
    /// The Jobs whose pods' evictions were accepted.
    Moved(Vec<u32>),
    /// EvalAI was told the submission runs.
    Started(bool),
    /// The results' fingerprint (`None`: not listed this round).
    Listed(Option<String>),
    /// The results as read.
    Collected(Collected),
    /// What EvalAI did with the partial update.
    Posted(Write),
    /// The markers' names (`None`: not listed this round).
    Markers(Option<Vec<String>>),
}

/// Where a round is: the stage whose step is outstanding.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stage {
    Adopt,
    Wake,
    WaitStatus,
    Turn,
    Observe,
    Deadlines,
    Started,
    Note,
    Results,
    Move,
    Status,
    Cancel,
    Verdict,
    Ending,
    Done,
}

/// One Monitor round.
#[derive(Debug)]
pub struct Round {
    run: RunState,
    cx: Context,
    stage: Stage,
    /// A step that follows from the last answer, within the same stage.
    pending: Option<Step>,
    /// The sweep flagged a cancel.
    cancel_flagged: bool,
    /// What EvalAI said of the submission this round (a write's refusal, a read).
    status: Option<SubmissionStatus>,
    sighting: Option<Sighting>,
    /// The pods the GPU count takes, while the nodes it needs are read.
    pods: Option<Vec<PodSeen>>,
    /// The cluster's verdict, once the pairs out of retries are known.
    verdict: Option<Verdict>,
    /// What the shell is asked to do next.
    next: Step,
    /// The place of the queue note being shown (`None`: the note goes).
    showing: Option<u32>,
    /// The listed fingerprint while results are read.
    listed: Option<String>,
    /// The merged results' fingerprint while they are sent.
    merged: Option<(String, String)>,
    /// The results changed since those last sent: a pair may have just written.
    written: bool,
    /// The pods whose pairs just wrote, while their nodes are read.
    moving: Vec<consolidation::Running>,
}

impl Round {
    /// A round of `run`: its defaults (the safety net's timeout for the next wait, the least
    /// hold, no poll), and the round counted in this execution's history.
    pub fn begin(mut run: RunState, cx: Context) -> Round {
        let now = cx.now;
        let elapsed = Duration::from_secs(now.saturating_sub(run.launched_at));
        let monitor = &mut run.monitor;
        monitor.rounds += 1;
        monitor.state = RunPhase::Running;
        monitor.continue_as = None;
        monitor.wait_seconds = safety_net(elapsed).as_secs();
        monitor.hold_seconds = MIN_ROUND_INTERVAL.as_secs();
        monitor.poll = false;
        monitor.expires_at = now + cx.wake_retention;
        if let Some(execution) = &cx.execution {
            if let Some(entered) = history::entering(monitor.execution.as_deref(), execution) {
                monitor.execution = Some(execution.clone());
                monitor.events = entered.events;
                monitor.handover = entered.continued;
            }
        }
        monitor.events += history::round_events(cx.retries);
        let mut round = Round {
            run,
            cx,
            stage: Stage::Adopt,
            pending: None,
            cancel_flagged: false,
            status: None,
            sighting: None,
            pods: None,
            verdict: None,
            next: Step::Done,
            showing: None,
            listed: None,
            merged: None,
            written: false,
            moving: Vec::new(),
        };
        round.next = round.drive();
        round
    }

    /// The run state as the round leaves it so far.
    pub fn run(&self) -> &RunState {
        &self.run
    }

    /// What the shell does next; [`Step::Done`] once the round is over.
    pub fn poll(&self) -> Step {
        self.next.clone()
    }

    /// Moves to the next step: one that follows from the last answer, else the current
    /// stage's, past the stages with nothing to do.
    fn drive(&mut self) -> Step {
        if let Some(step) = self.pending.take() {
            return step;
        }
        loop {
            if let Some(step) = self.step() {
                return step;
            }
        }
    }

    /// The current stage's step, or `None` after moving past a stage with nothing to do.
    fn step(&mut self) -> Option<Step> {
        let now = self.cx.now;
        match self.stage {
            Stage::Adopt => match (&self.run.monitor.execution, self.run.monitor.handover) {
                (Some(execution), true) => return Some(Step::Adopt(execution.clone())),
                _ => self.advance(Stage::Wake),
            },
            Stage::Wake => return Some(Step::ReadWake),
            Stage::WaitStatus => {
                let waited = now.saturating_sub(self.run.queue.arrived_at);
                self.run.monitor.wait_seconds = queue_wait(Duration::from_secs(waited)).as_secs();
                match self.status_read() {
                    Some(read) => return Some(Step::ReadStatus(read)),
                    None => self.advance(Stage::Turn),
                }
            }
            Stage::Turn => {
                let waited = now.saturating_sub(self.run.queue.arrived_at);
                let (hours, limit) = (self.cx.max_queue_hours, self.cx.team_limit);
                if let Some(reason) = monitor::queue_limit_ends_wait(waited, hours, limit) {
                    return Some(self.end(RunPhase::Failed, Some(reason)));
                }
                // The entry exists since Launch: its stored arrival stands.
                let stored = self.run.queue.arrived_at * 1000;
                let arrived_ms = self.cx.arrived_ms.unwrap_or(stored);
                return Some(Step::TakeTurn { arrived_ms, limit });
            }
            Stage::Observe => return Some(Step::Observe),
            Stage::Deadlines => return self.deadlines(),
            Stage::Started => {
                let jobs = self.sighting.as_ref().map(|seen| &seen.observation.jobs);
                match jobs {
                    Some(jobs)
                        if self.run.monitor.started_at.is_none() && cluster::started(jobs) =>
                    {
                        return Some(Step::MarkStarted(
                            jobs.iter().map(|j| j.name.clone()).collect(),
                        ));
                    }
                    _ => self.advance(Stage::Note),
                }
            }
            Stage::Note => match (self.run.monitor.started_at, self.run.queue.shown) {
                (None, _) => return Some(Step::ReadAhead),
                (Some(_), Some(_)) if self.note_due(None) => {
                    self.showing = None;
                    return Some(Step::ShowPlace(None));
                }
                _ => self.advance(Stage::Results),
            },
            Stage::Results if self.status.is_none() => return Some(Step::ListResults),
            Stage::Results => self.advance(Stage::Move),
            Stage::Move => match self.may_move() {
                true => return Some(Step::ResultsWritten),
                false => self.advance(Stage::Status),
            },
            Stage::Status => match (self.status, self.status_read()) {
                (Some(SubmissionStatus::Cancelled), _) => self.advance(Stage::Cancel),
                (None, Some(read)) => return Some(Step::ReadStatus(read)),
                _ => self.advance(Stage::Verdict),
            },
            Stage::Cancel => return Some(Step::PutCancelMarker),
            Stage::Verdict => return Some(self.verdict()),
            Stage::Ending => {
                let since = self.run.launched_at;
                return Some(Step::ListMarkers { since });
            }
            Stage::Done => return Some(Step::Done),
        }
        None
    }

    /// The Jobs' deadlines to set (grown by the time reclaims cost, or ended for a pair out of
    /// retries), and the cluster's verdict once those pairs are known.
    fn deadlines(&mut self) -> Option<Step> {
        let (expected, policy) = (self.run.jobs, &self.cx.policy);
        let monitor = &mut self.run.monitor;
        let judged = self.sighting.as_ref().map(|seen| {
            let usage = &monitor.usage;
            let jobs = &seen.observation.jobs;
            let spent = monitor::spent_pairs(jobs, usage, &monitor.ended_by_platform);
            let set: Vec<(String, u64)> =
                monitor::deadlines_to_set(jobs, usage.deadline_extension(), &spent)
                    .into_iter()
                    .map(|(job, seconds)| (job.to_owned(), seconds))
                    .collect();
            let by_platform: Vec<u32> = jobs
                .iter()
                .filter(|j| spent.get(&j.name).is_some_and(|s| s.by_platform))
                .filter_map(|j| j.index)
                .collect();
            let verdict = seen.observation.judge(expected, &spent, policy);
            (set, verdict, by_platform)
        });
        let set = judged.map_or_else(Vec::new, |(set, verdict, by_platform)| {
            for index in by_platform {
                if !monitor.ended_by_platform.contains(&index) {
                    monitor.ended_by_platform.push(index);
                }
            }
            self.verdict = Some(verdict);
            set
        });
        if !set.is_empty() {
            return Some(Step::SetDeadlines(set));
        }
        self.advance(Stage::Started);
        None
    }

    /// Takes what the shell found doing the step [`Round::poll`] gave last. An answer that
    /// fits no outstanding step is a bug in the shell: the round ends there, with the run
    /// state as it stands (the next round starts from it).
    pub fn answer(&mut self, answer: Answer) {
        self.take(answer);
        self.next = self.drive();
    }

    fn take(&mut self, answer: Answer) {
        let now = self.cx.now;
        match (self.stage, answer) {
            (Stage::Adopt, Answer::Adopted(done)) => {
                self.run.monitor.handover = !done;
                self.advance(Stage::Wake);
            }
            (Stage::Wake, Answer::Wake(wake)) => self.woke(wake),
            (Stage::WaitStatus, Answer::Status(status)) => {
                self.read_status(status);
                match self.status {
                    Some(SubmissionStatus::Cancelled) => _ = self.end(RunPhase::Cancelled, None),
                    _ => self.advance(Stage::Turn),
                }
            }
            (Stage::Turn, Answer::Turn(standing)) => self.took_turn(standing),
            (Stage::Turn | Stage::Note, Answer::Note(text)) => {
                self.pending = Some(Step::ShowPlace(self.showing.map(|ahead| (ahead, text))));
            }
            (Stage::Turn | Stage::Note, Answer::Shown(write)) => self.shown(write),
            (Stage::Observe, Answer::Observed(seen)) => self.observed(*seen),
            (Stage::Observe, Answer::Autoscaler(word)) => self.heard(word),
            (Stage::Observe, Answer::Nodes(nodes)) => self.nodes_read(nodes),
            (Stage::Observe, Answer::ResultsWritten(at)) => self.charge(&at),
            (Stage::Observe, Answer::Unreachable(error)) => self.unreachable(error),
            (Stage::Deadlines, Answer::Done) => self.advance(Stage::Started),
            (Stage::Started, Answer::Started(started)) => {
                if started {
                    self.run.monitor.started_at = Some(now);
                }
                self.advance(Stage::Note);
            }
            (Stage::Note, Answer::Ahead(ahead)) => self.ahead(ahead),
            (Stage::Results, Answer::Listed(fingerprint)) => self.listed(fingerprint),
            (Stage::Results, Answer::Collected(collected)) => self.collected(collected),
            (Stage::Results, Answer::Stored(true)) => self.pending = Some(Step::PostPartial),
            (Stage::Results, Answer::Stored(false)) => {
                self.merged = None;
                self.shorten_wait(self.cx.partial_update_seconds);
                self.advance(Stage::Move);
            }
            (Stage::Results, Answer::Posted(write)) => self.posted(write),
            (Stage::Move, Answer::ResultsWritten(at)) => self.due_to_move(&at),
            (Stage::Move, Answer::Nodes(nodes)) => self.drained(nodes),
            (Stage::Move, Answer::Moved(jobs)) => {
                for job in jobs {
                    self.run.monitor.usage.count_move(job);
                }
                self.advance(Stage::Status);
            }
            (Stage::Status, Answer::Status(status)) => {
                self.read_status(status);
                // Only a cancel ends the round; any other word is left to the verdict.
                self.advance(match self.status {
                    Some(SubmissionStatus::Cancelled) => Stage::Cancel,
                    _ => Stage::Verdict,
                });
            }
            (Stage::Cancel, Answer::Done) => _ = self.end(RunPhase::Cancelled, None),
            (Stage::Verdict, Answer::Done) => self.advance(Stage::Ending),
            (Stage::Ending, Answer::Markers(names)) => {
                // Every Job's logcopy is done: the Jobs complete within seconds, and nothing
                // more will land in S3 to wake us.
                if names.is_some_and(|names| self.logcopy_done(&names)) {
                    self.shorten_wait(ENDING_POLL.as_secs());
                }
                self.advance(Stage::Done);
            }
            (_, _) => self.advance(Stage::Done),
        }
    }

    /// The run state the round leaves, continued as a new execution of `lineage` when this
    /// one's history leaves no room for another round (`history`).
    pub fn finish(mut self, history_budget: u64, lineage: &str) -> RunState {
        let monitor = &mut self.run.monitor;
        let running = monitor.state == RunPhase::Running;
        if running && history::continue_due(monitor.events, history_budget) {
            monitor.generation += 1;
            monitor.continue_as = Some(history::continuation_name(lineage, monitor.generation));
            monitor.state = RunPhase::Continued;
        }
        self.run
    }

    /// Whether every Job of the run has written `logcopy-<J>.done`.
    fn logcopy_done(&self, names: &[String]) -> bool {
        (0..self.run.jobs).all(|job| {
            let marker = Marker::LogcopyDone { job }.to_string();
            names.contains(&marker)
        })
    }

    fn advance(&mut self, stage: Stage) {
        self.stage = stage;
    }

    fn done(&mut self) -> Step {
        self.advance(Stage::Done);
        Step::Done
    }

    fn end(&mut self, state: RunPhase, reason: Option<String>) -> Step {
        self.run.monitor.state = state;
        self.run.monitor.reason = reason;
        self.advance(Stage::Done);
        Step::Done
    }

    fn shorten_wait(&mut self, seconds: u64) {
        let wait = &mut self.run.monitor.wait_seconds;
        *wait = (*wait).min(seconds);
    }

    fn status_read(&self) -> Option<StatusRead> {
        let last = self.run.monitor.status_read_at;
        monitor::status_read(self.cancel_flagged, last, self.cx.now)
    }

    fn read_status(&mut self, status: Option<SubmissionStatus>) {
        if status.is_some() {
            self.run.monitor.status_read_at = Some(self.cx.now);
        }
        self.status = status;
    }

    fn note_due(&self, ahead: Option<u32>) -> bool {
        let shown = (self.run.queue.shown, self.run.queue.shown_at);
        queue::note_due(shown, ahead, self.cx.now, self.cx.note_interval)
    }

    /// The wake count before anything else: unread, the next wait is a plain poll (a wait
    /// conditional on a count we do not know could end at once every time).
    fn woke(&mut self, wake: Option<(u64, bool)>) {
        match wake {
            Some((changes, cancel)) => {
                self.run.monitor.seen = changes;
                self.cancel_flagged = cancel;
            }
            None => {
                self.run.monitor.poll = true;
                self.run.monitor.wait_seconds = POLL_WITHOUT_WAKE.as_secs();
            }
        }
        self.advance(match self.run.queue.admitted {
            true => Stage::Observe,
            false => Stage::WaitStatus,
        });
    }

    /// A held submission's turn: admitted (Launch creates its Jobs next), or its place shown
    /// when it changed.
    fn took_turn(&mut self, standing: Standing) {
        if standing.admitted {
            self.end(RunPhase::Admitted, None);
            return;
        }
        let ahead = queue::shown_ahead(self.run.queue.shown, standing.ahead);
        if !self.note_due(Some(ahead)) {
            self.advance(Stage::Done);
            return;
        }
        self.showing = Some(ahead);
        let place = Place {
            ahead,
            team_ahead: standing.team_ahead,
            running: 0,
        };
        self.pending = Some(Step::ComposeNote(place, standing.hold));
    }

    /// An admitted submission whose pods wait: its place, when it changed.
    fn ahead(&mut self, ahead: Option<(u32, u32)>) {
        let Some((ahead, running)) = ahead else {
            return self.advance(Stage::Results);
        };
        let ahead = queue::shown_ahead(self.run.queue.shown, ahead);
        if !self.note_due(Some(ahead)) {
            return self.advance(Stage::Results);
        }
        self.showing = Some(ahead);
        let place = Place {
            ahead,
            team_ahead: 0,
            running,
        };
        self.pending = Some(Step::ComposeNote(place, Hold::Capacity));
    }

    /// What EvalAI did with the queue note. Held, a refusal for a cancel ends the wait; once
    /// admitted, only a cancel is kept (any other word is left to the rest of the round).
    fn shown(&mut self, write: Write) {
        if write == Write::Written {
            self.run.queue.shown = self.showing;
            self.run.queue.shown_at = Some(self.cx.now);
        }
        let cancelled = matches!(
            write,
            Write::Cancelled | Write::AlreadyFinal(SubmissionStatus::Cancelled)
        );
        match (self.stage, cancelled) {
            (Stage::Turn, true) => _ = self.end(RunPhase::Cancelled, None),
            (Stage::Turn, false) => self.advance(Stage::Done),
            (_, cancelled) => {
                self.status = cancelled.then_some(SubmissionStatus::Cancelled);
                self.advance(Stage::Results);
            }
        }
    }

    /// The cluster reached: the pods the GPU count takes, and the nodes it must read first
    /// (the kinds of those new pods run on, and whether an evicting kubelet's node is leaving).
    fn observed(&mut self, observation: Observation) {
        self.run.monitor.unreachable_since = None;
        let asking = observation.needs_autoscaler_word(&self.cx.policy);
        if let Some(uid) = asking.map(str::to_string) {
            self.pending = Some(Step::ReadAutoscaler(uid));
            self.sighting = Some(Sighting {
                observation,
                counted: None,
            });
            return;
        }
        self.count_pods(observation);
    }

    /// The autoscaler's word on the pod asked about, for the verdict; then the count.
    fn heard(&mut self, word: Option<ScaleUpWord>) {
        let Some(mut seen) = self.sighting.take() else {
            return self.charge(&BTreeMap::new());
        };
        // The pod asked about is the one the same observation still names.
        let asked = seen.observation.needs_autoscaler_word(&self.cx.policy);
        if let (Some(uid), Some(word)) = (asked.map(str::to_string), word) {
            seen.observation.hear_autoscaler(&uid, word);
        }
        self.count_pods(seen.observation);
    }

    /// The pods the GPU count takes, and the nodes it must read first.
    fn count_pods(&mut self, observation: Observation) {
        let pods = cost::pods_seen(&observation.jobs, observation.observed_at);
        let usage = &self.run.monitor.usage;
        let mut nodes = usage.unknown_nodes(&pods);
        nodes.extend(usage.nodes_to_judge(&pods));
        nodes.sort();
        nodes.dedup();
        self.sighting = Some(Sighting {
            observation,
            counted: None,
        });
        if nodes.is_empty() {
            self.counted(pods, BTreeMap::new());
        } else {
            self.pods = Some(pods);
            self.pending = Some(Step::ReadNodes(nodes));
        }
    }

    /// The nodes read: new pods' kinds, and each kubelet's disruption judged by its node
    /// ([`disruption::leaving`]). A node that could not be read leaves the count to the next
    /// round.
    fn nodes_read(&mut self, nodes: Option<BTreeMap<String, NodeRead>>) {
        let pods = self.pods.take().unwrap_or_default();
        let Some(nodes) = nodes else {
            return self.charge(&BTreeMap::new());
        };
        let usage = &self.run.monitor.usage;
        let read = |node: &String| nodes.get(node).and_then(Option::as_ref);
        let kinds = (usage.unknown_nodes(&pods).into_iter())
            .map(|node| {
                let kind = read(&node).map(|(kind, _)| kind.clone());
                (node, kind.unwrap_or_else(NodeKind::unknown))
            })
            .collect();
        let leaving = (usage.nodes_to_judge(&pods).into_iter())
            .map(|node| {
                let leaving = disruption::leaving(read(&node).map(|(_, facts)| facts));
                (node, leaving)
            })
            .collect();
        let mut pods = pods;
        cost::judge(&mut pods, &leaving);
        self.counted(pods, kinds);
    }

    /// The pods counted: the count of GPU time waits for the results' times when a pod was
    /// taken away (its run-again time counts from its pair's last write).
    fn counted(&mut self, pods: Vec<PodSeen>, kinds: BTreeMap<String, NodeKind>) {
        let Some(seen) = self.sighting.as_mut() else {
            return self.charge(&BTreeMap::new());
        };
        let failed = cost::failures(&seen.observation.jobs);
        let usage = &self.run.monitor.usage;
        let disrupted = pods
            .iter()
            .any(|p| p.disruption == Some(Disruption::Reclaim))
            || usage.went_unfailed(&pods, &failed);
        seen.counted = Some((pods, kinds));
        if disrupted {
            self.pending = Some(Step::ResultsWritten);
        } else {
            self.charge(&BTreeMap::new());
        }
    }

    /// Charges this round's GPU time up to when the pods were listed (`cost`).
    fn charge(&mut self, results_at: &BTreeMap<u32, u64>) {
        if let Some(seen) = &self.sighting {
            if let Some((pods, kinds)) = &seen.counted {
                let at = u64::try_from(seen.observation.observed_at.as_second()).unwrap_or(0);
                let failed = cost::failures(&seen.observation.jobs);
                self.run
                    .monitor
                    .usage
                    .account(pods, kinds, (results_at, &failed), at);
            }
        }
        self.advance(Stage::Deadlines);
    }

    /// The cluster's API out of reach skips the verdict this round; only an outage longer
    /// than the leaderboard allows ends the run.
    fn unreachable(&mut self, error: &str) {
        let now = self.cx.now;
        let since = *self.run.monitor.unreachable_since.get_or_insert(now);
        let bound = self.cx.max_cluster_outage_hours;
        if let Some(reason) = monitor::outage_ends_run(since, now, bound, error) {
            self.end(RunPhase::Failed, Some(reason));
            return;
        }
        // Its recovery writes nothing to S3: look again at the first outage's pace.
        self.shorten_wait(safety_net(Duration::ZERO).as_secs());
        self.advance(Stage::Started);
    }

    /// Results listed: changed ones are read when a partial update may go.
    fn listed(&mut self, fingerprint: Option<String>) {
        let interval = self.cx.partial_update_seconds;
        let Some(fingerprint) = fingerprint else {
            self.shorten_wait(interval);
            return self.advance(Stage::Move);
        };
        if fingerprint.is_empty() || Some(&fingerprint) == self.run.monitor.fingerprint.as_ref() {
            return self.advance(Stage::Move);
        }
        self.written = true;
        let last = self.run.monitor.updated_at;
        if let Err(wait) = monitor::partial_update_due(last, self.cx.now, interval) {
            // Too soon (a round the hold did not cover): the wait ends when it may go.
            self.shorten_wait(wait.as_secs());
            return self.advance(Stage::Move);
        }
        self.listed = Some(fingerprint);
        self.pending = Some(Step::CollectResults {
            pairs: self.run.pairs.clone(),
            repetitions: self.run.repetitions,
        });
    }

    /// Whether a pod may move this round: results changed since those sent (a pair wrote; a
    /// quiet round asks nothing more), no final word or cancel from EvalAI, and a pod running
    /// on a node.
    fn may_move(&self) -> bool {
        let running = |seen: &Sighting| !consolidation::running(&seen.observation.jobs).is_empty();
        let ending = self.status.is_some_and(|s| s.is_final());
        self.written && !ending && self.sighting.as_ref().is_some_and(running)
    }

    /// The pods whose pairs just wrote their results, and their nodes to read.
    fn due_to_move(&mut self, written: &BTreeMap<u32, u64>) {
        let Some(seen) = &self.sighting else {
            return self.advance(Stage::Status);
        };
        let usage = &self.run.monitor.usage;
        let running = consolidation::running(&seen.observation.jobs);
        let at = (self.cx.now, self.cx.move_window_seconds);
        let due = consolidation::due(&running, written, |job| usage.moves_of(job), at);
        let mut nodes: Vec<String> = due.iter().map(|p| p.node.clone()).collect();
        nodes.sort();
        nodes.dedup();
        if nodes.is_empty() {
            return self.advance(Stage::Status);
        }
        self.moving = due;
        self.pending = Some(Step::ReadNodes(nodes));
    }

    /// Those nodes read: the pods on drained ones are evicted.
    fn drained(&mut self, nodes: Option<BTreeMap<String, NodeRead>>) {
        let due = std::mem::take(&mut self.moving);
        let drained = (nodes.unwrap_or_default().into_iter())
            .filter(|(_, read)| {
                read.as_ref()
                    .is_some_and(|(_, facts)| consolidation::drained(facts))
            })
            .map(|(name, _)| name)
            .collect();
        let to_move = consolidation::to_move(due, &drained);
        match to_move.is_empty() {
            true => self.advance(Stage::Status),
            false => self.pending = Some(Step::Evict(to_move)),
        }
    }

    fn collected(&mut self, collected: Collected) {
        match collected {
            Collected::Merged {
                progress,
                fingerprint,
                content,
            } => {
                self.run.monitor.progress = progress;
                if self.run.monitor.posted.as_ref() == Some(&content) {
                    // Rewritten, not changed: not read again until the files change again.
                    self.run.monitor.fingerprint = Some(fingerprint);
                    return self.advance(Stage::Move);
                }
                self.merged = Some((fingerprint, content));
                self.pending = Some(Step::StoreFiles);
            }
            Collected::NotNow => {
                self.shorten_wait(self.cx.partial_update_seconds);
                self.advance(Stage::Move);
            }
            Collected::Unusable => {
                self.run.monitor.fingerprint = self.listed.take();
                self.advance(Stage::Move);
            }
        }
    }

    fn posted(&mut self, write: Write) {
        let (now, interval) = (self.cx.now, self.cx.partial_update_seconds);
        let (merged, content) = self.merged.take().unzip();
        self.status = match write {
            Write::Written => {
                let monitor = &mut self.run.monitor;
                monitor.fingerprint = merged;
                monitor.posted = content;
                monitor.updated_at = Some(now);
                monitor.hold_seconds = monitor.hold_seconds.max(interval);
                Some(SubmissionStatus::PartiallyEvaluated)
            }
            Write::Cancelled => Some(SubmissionStatus::Cancelled),
            Write::AlreadyFinal(status) => Some(status),
            // Nothing in S3 will change for it: the wait ends when it may go again.
            Write::NotNow => {
                self.shorten_wait(interval);
                None
            }
        };
        self.advance(Stage::Move);
    }

    /// The cluster's verdict on a run its status did not end: too long, still queued,
    /// running (progress recorded), finished or failed.
    fn verdict(&mut self) -> Step {
        let Some(seen) = &self.sighting else {
            return self.done();
        };
        let image = &mut self.run.monitor.image;
        if let Some(reason) = monitor::hold_image(image, &seen.observation.jobs) {
            return self.end(RunPhase::Failed, Some(reason));
        }
        let Some(verdict) = &self.verdict else {
            return self.done();
        };
        let monitor = &self.run.monitor;
        match verdict {
            Verdict::Running => {
                let lost = monitor.usage.time_off(self.cx.now);
                match (
                    monitor.started_at,
                    monitor::overran(monitor.started_at, lost, self.cx.now),
                ) {
                    (_, Some(reason)) => self.end(RunPhase::Failed, Some(reason)),
                    // Queued: waiting for capacity is no failure, and the record stays as
                    // Intake wrote it.
                    (None, None) => self.done(),
                    (Some(_), None) => Step::RecordRunning {
                        progress: monitor.progress,
                        usage: monitor.usage.summary(&self.cx.prices),
                        image: monitor.image.clone(),
                    },
                }
            }
            Verdict::Finished => self.end(RunPhase::Finished, None),
            Verdict::Failed { kind, message, .. } => {
                self.run.monitor.failure = Some(*kind);
                let message = message.clone();
                self.end(RunPhase::Failed, Some(message))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cluster::view::{FailureKind, JobState, JobView};
    use crate::run::schedule::{MAX_EVALUATION, STATUS_FALLBACK};
    use crate::run::state::{MonitorState, QueueState};
    use crate::status::PodPhase;

    const NOW: u64 = 1_000_000;
    const INTERVAL: u64 = 20;

    fn run(admitted: bool) -> RunState {
        RunState {
            jobs: 1,
            pairs: Vec::new(),
            repetitions: 1,
            launched_at: NOW - 600,
            recorder: true,
            monitor: MonitorState {
                status_read_at: Some(NOW - 60),
                ..MonitorState::starting(30, 0, 10, "exec-1", 0)
            },
            queue: QueueState {
                admitted,
                ..QueueState::arriving(NOW - 600)
            },
        }
    }

    fn cx() -> Context {
        Context {
            now: NOW,
            execution: Some("exec-1".into()),
            retries: 0,
            arrived_ms: None,
            partial_update_seconds: INTERVAL,
            move_window_seconds: crate::capacity::consolidation::MOVE_WINDOW_SECONDS,
            max_queue_hours: 24,
            max_cluster_outage_hours: 6,
            team_limit: 2,
            note_interval: 300,
            prices: BTreeMap::new(),
            wake_retention: 3600,
            policy: VerdictPolicy::default(),
        }
    }

    /// The cluster with its one Job in `state`, its pod running when `started`.
    fn seen(started: bool, state: JobState) -> Answer {
        let mut job = crate::testutil::job("lb-7-0", state, None);
        if started {
            let pod = crate::testutil::pod("lb-7-0-a", "lb-7-0", PodPhase::Running);
            job.pods.push(pod);
        }
        observed(vec![job])
    }

    /// The cluster with these Jobs.
    fn observed(jobs: Vec<JobView>) -> Answer {
        Answer::Observed(Box::new(Observation {
            submission_id: "7".into(),
            observed_at: jiff::Timestamp::from_second(NOW as i64).unwrap(),
            jobs,
            stray_pods: Vec::new(),
        }))
    }

    /// Runs a round, answering each step with `world`; the steps taken and the state left.
    fn drive(
        run: RunState,
        cx: Context,
        mut world: impl FnMut(&Step) -> Answer,
    ) -> (Vec<Step>, RunState) {
        let mut round = Round::begin(run, cx);
        let mut steps = Vec::new();
        loop {
            let step = round.poll();
            if step == Step::Done {
                return (steps, round.finish(u64::MAX, "exec-1"));
            }
            assert!(steps.len() < 50, "the round does not end: {steps:?}");
            let answer = world(&step);
            steps.push(step);
            round.answer(answer);
        }
    }

    /// A world where nothing happens: the wake count read, the cluster running, the results
    /// as last sent, EvalAI saying `running`.
    fn quiet(state: JobState) -> impl FnMut(&Step) -> Answer {
        move |step| match step {
            Step::Adopt(_) => Answer::Adopted(true),
            Step::ReadWake => Answer::Wake(Some((4, false))),
            Step::Observe => seen(true, state.clone()),
            Step::ListResults => Answer::Listed(Some("etag-1".into())),
            Step::ReadStatus(_) => Answer::Status(Some(SubmissionStatus::Running)),
            Step::StoreFiles => Answer::Stored(true),
            Step::ListMarkers { .. } => Answer::Markers(Some(Vec::new())),
            _ => Answer::Done,
        }
    }

    fn started(mut run: RunState) -> RunState {
        run.monitor.started_at = Some(NOW - 300);
        run.monitor.fingerprint = Some("etag-1".into());
        run
    }

    fn kinds(steps: &[Step]) -> Vec<&'static str> {
        steps
            .iter()
            .map(|s| match s {
                Step::Adopt(_) => "adopt",
                Step::ReadWake => "wake",
                Step::ReadStatus(_) => "status",
                Step::TakeTurn { .. } => "turn",
                Step::ReadAhead => "ahead",
                Step::ComposeNote(..) => "compose",
                Step::ShowPlace(_) => "show",
                Step::Observe => "observe",
                Step::ReadAutoscaler(_) => "autoscaler",
                Step::ReadNodes(_) => "nodes",
                Step::ResultsWritten => "written",
                Step::Evict(_) => "evict",
                Step::SetDeadlines(_) => "deadlines",
                Step::MarkStarted(_) => "started",
                Step::ListResults => "list",
                Step::CollectResults { .. } => "collect",
                Step::StoreFiles => "store",
                Step::PostPartial => "post",
                Step::PutCancelMarker => "cancel",
                Step::RecordRunning { .. } => "record",
                Step::ListMarkers { .. } => "ending",
                Step::Done => "done",
            })
            .collect()
    }

    #[test]
    fn a_quiet_running_round_records_progress_and_reads_nothing_it_does_not_need() {
        let (steps, run) = drive(started(run(true)), cx(), quiet(JobState::Running));
        assert_eq!(
            kinds(&steps),
            ["wake", "observe", "list", "record", "ending"]
        );
        assert_eq!(run.monitor.state, RunPhase::Running);
        assert_eq!(run.monitor.seen, 4);
        assert_eq!(run.monitor.rounds, 1);
        assert_eq!(run.monitor.hold_seconds, MIN_ROUND_INTERVAL.as_secs());
        assert!(!run.monitor.poll);
    }

    #[test]
    fn a_cancel_the_sweep_flagged_is_confirmed_and_wins_over_a_finished_verdict() {
        let (steps, run) = drive(started(run(true)), cx(), |step| match step {
            Step::ReadWake => Answer::Wake(Some((5, true))),
            Step::ReadStatus(read) => {
                assert_eq!(*read, StatusRead::ConfirmCancel);
                Answer::Status(Some(SubmissionStatus::Cancelled))
            }
            other => quiet(JobState::Complete)(other),
        });
        assert_eq!(
            kinds(&steps),
            ["wake", "observe", "list", "status", "cancel"]
        );
        assert_eq!(run.monitor.state, RunPhase::Cancelled);
        assert_eq!(run.monitor.status_read_at, Some(NOW));
    }

    #[test]
    fn a_flag_evalai_does_not_confirm_leaves_the_verdict_to_decide() {
        let (steps, run) = drive(started(run(true)), cx(), |step| match step {
            Step::ReadWake => Answer::Wake(Some((5, true))),
            other => quiet(JobState::Complete)(other),
        });
        assert_eq!(kinds(&steps), ["wake", "observe", "list", "status"]);
        assert_eq!(run.monitor.state, RunPhase::Finished);
    }

    #[test]
    fn a_cancel_met_by_the_queue_note_ends_the_round_before_the_results() {
        let mut waiting = run(true);
        waiting.monitor.status_read_at = Some(NOW);
        let (steps, run) = drive(waiting, cx(), |step| match step {
            Step::Observe => seen(false, JobState::Pending),
            Step::ReadAhead => Answer::Ahead(Some((3, 1))),
            Step::ComposeNote(place, hold) => {
                let place = (place.ahead, place.team_ahead, place.running);
                assert_eq!((place, *hold), ((3, 0, 1), Hold::Capacity));
                Answer::Note("3 ahead".into())
            }
            Step::ShowPlace(note) => {
                assert_eq!(note, &Some((3, "3 ahead".into())));
                Answer::Shown(Write::Cancelled)
            }
            other => quiet(JobState::Running)(other),
        });
        assert_eq!(
            kinds(&steps),
            ["wake", "observe", "ahead", "compose", "show", "cancel"]
        );
        assert_eq!(run.monitor.state, RunPhase::Cancelled);
        assert_eq!(run.queue.shown, None, "a refused note was not shown");
    }

    #[test]
    fn changed_results_go_once_per_interval_and_hold_the_next_wait() {
        let world = |step: &Step| match step {
            Step::ListResults => Answer::Listed(Some("etag-2".into())),
            Step::CollectResults { .. } => Answer::Collected(Collected::Merged {
                progress: (3, 10),
                fingerprint: "etag-2".into(),
                content: "records-2".into(),
            }),
            Step::PostPartial => Answer::Posted(Write::Written),
            other => quiet(JobState::Running)(other),
        };
        let (steps, run) = drive(started(run(true)), cx(), world);
        assert_eq!(
            kinds(&steps),
            ["wake", "observe", "list", "collect", "store", "post", "record", "ending"]
        );
        assert_eq!(run.monitor.fingerprint.as_deref(), Some("etag-2"));
        assert_eq!(run.monitor.posted.as_deref(), Some("records-2"));
        assert_eq!(
            (run.monitor.updated_at, run.monitor.progress),
            (Some(NOW), (3, 10))
        );
        assert_eq!(run.monitor.hold_seconds, INTERVAL);

        // Sent 5 seconds ago: the wait ends when it may go, nothing is read.
        let mut recent = started(self::run(true));
        recent.monitor.updated_at = Some(NOW - 5);
        let (steps, run) = drive(recent, cx(), world);
        assert_eq!(
            kinds(&steps),
            ["wake", "observe", "list", "record", "ending"]
        );
        assert_eq!(run.monitor.wait_seconds, 15);
        assert_eq!(run.monitor.fingerprint.as_deref(), Some("etag-1"));
    }

    #[test]
    fn the_same_records_rewritten_are_not_sent_again() {
        let mut sent = started(run(true));
        sent.monitor.posted = Some("records-2".into());
        let (steps, run) = drive(sent, cx(), |step| match step {
            Step::ListResults => Answer::Listed(Some("etag-3".into())),
            Step::CollectResults { .. } => Answer::Collected(Collected::Merged {
                progress: (3, 10),
                fingerprint: "etag-3".into(),
                content: "records-2".into(),
            }),
            other => quiet(JobState::Running)(other),
        });
        assert_eq!(
            kinds(&steps),
            ["wake", "observe", "list", "collect", "record", "ending"],
            "read, found the same, nothing posted"
        );
        assert_eq!(
            run.monitor.fingerprint.as_deref(),
            Some("etag-3"),
            "not read again"
        );
        assert_eq!(run.monitor.updated_at, None);
        assert_eq!(run.monitor.posted.as_deref(), Some("records-2"));
    }

    #[test]
    fn a_deferred_update_or_unreadable_results_shorten_the_wait_to_the_interval() {
        for (collected, posted) in [
            (Collected::NotNow, Write::Written),
            (
                Collected::Merged {
                    progress: (1, 10),
                    fingerprint: "etag-2".into(),
                    content: "records-2".into(),
                },
                Write::NotNow,
            ),
        ] {
            let (_, run) = drive(started(run(true)), cx(), |step| match step {
                Step::ListResults => Answer::Listed(Some("etag-2".into())),
                Step::CollectResults { .. } => Answer::Collected(collected.clone()),
                Step::PostPartial => Answer::Posted(posted),
                other => quiet(JobState::Running)(other),
            });
            assert_eq!(run.monitor.wait_seconds, INTERVAL);
            assert_eq!(run.monitor.fingerprint.as_deref(), Some("etag-1"));
        }
        // Broken files are not read again until they change.
        let (_, run) = drive(started(run(true)), cx(), |step| match step {
            Step::ListResults => Answer::Listed(Some("etag-3".into())),
            Step::CollectResults { .. } => Answer::Collected(Collected::Unusable),
            other => quiet(JobState::Running)(other),
        });
        assert_eq!(run.monitor.fingerprint.as_deref(), Some("etag-3"));
    }

    #[test]
    fn an_unreachable_cluster_skips_the_verdict_until_the_leaderboard_s_bound() {
        let world = |step: &Step| match step {
            Step::Observe => Answer::Unreachable("KubeUnavailable"),
            other => quiet(JobState::Complete)(other),
        };
        let (steps, run) = drive(started(run(true)), cx(), world);
        assert_eq!(kinds(&steps), ["wake", "observe", "list"]);
        assert_eq!(run.monitor.state, RunPhase::Running);
        assert_eq!(run.monitor.unreachable_since, Some(NOW));
        assert_eq!(
            run.monitor.wait_seconds,
            safety_net(Duration::ZERO).as_secs()
        );

        let mut long = started(self::run(true));
        long.monitor.unreachable_since = Some(NOW - 6 * 3600);
        let (steps, run) = drive(long, cx(), world);
        assert_eq!(kinds(&steps), ["wake", "observe"]);
        assert_eq!(run.monitor.state, RunPhase::Failed);
        let reason = run.monitor.reason.unwrap();
        assert!(reason.contains("(KubeUnavailable)"), "{reason}");
    }

    /// The cluster with one pod the scheduler has not placed since `since` (epoch seconds).
    fn unplaced(since: u64) -> Answer {
        let mut job = crate::testutil::job("lb-7-0", JobState::Pending, None);
        let mut pod = crate::testutil::pod("lb-7-0-a", "lb-7-0", PodPhase::Pending);
        pod.uid = Some("uid-a".into());
        pod.node_selector = Some("node.kubernetes.io/instance-type=g6.xlarge".into());
        pod.unschedulable = Some(crate::cluster::view::Unschedulable {
            since: Some(jiff::Timestamp::from_second(since as i64).unwrap()),
            message: "0/3 nodes are available".into(),
        });
        job.pods.push(pod);
        observed(vec![job])
    }

    #[test]
    fn the_autoscaler_is_asked_only_after_the_grace_and_its_no_ends_the_wait() {
        let grace = cx().policy.never_fits_grace.as_secs();
        let never = |step: &Step| match step {
            Step::ReadAutoscaler(uid) => {
                assert_eq!(uid, "uid-a");
                Answer::Autoscaler(Some(ScaleUpWord {
                    reason: crate::cluster::autoscaler::NOT_TRIGGERED.into(),
                    message: "pod didn't trigger scale-up: 1 node(s) didn't match Pod's node affinity/selector".into(),
                    at: Some(jiff::Timestamp::from_second(NOW as i64 - 5).unwrap()),
                }))
            }
            Step::ReadAhead => Answer::Ahead(None),
            other => quiet(JobState::Pending)(other),
        };
        let waiting = || {
            let mut admitted = run(true);
            admitted.monitor.fingerprint = Some("etag-1".into());
            admitted
        };
        // Not yet waited the grace: no question, and the pod waits.
        let (steps, left) = drive(waiting(), cx(), |step| match step {
            Step::Observe => unplaced(NOW - grace + 1),
            other => never(other),
        });
        assert!(!kinds(&steps).contains(&"autoscaler"), "{steps:?}");
        assert_eq!(left.monitor.state, RunPhase::Running);

        // Past it: one question, and a "no group could hold it" fails the run, unstarted.
        let (steps, left) = drive(waiting(), cx(), |step| match step {
            Step::Observe => unplaced(NOW - grace),
            other => never(other),
        });
        assert_eq!(kinds(&steps)[..3], ["wake", "observe", "autoscaler"]);
        assert_eq!(left.monitor.state, RunPhase::Failed);
        let reason = left.monitor.reason.unwrap();
        assert!(reason.contains("g6.xlarge"), "{reason}");

        // No word (none said, or the events not readable): the pod waits.
        let (_, left) = drive(waiting(), cx(), |step| match step {
            Step::Observe => unplaced(NOW - grace),
            Step::ReadAutoscaler(_) => Answer::Autoscaler(None),
            other => never(other),
        });
        assert_eq!(left.monitor.state, RunPhase::Running);
    }

    #[test]
    fn the_first_pair_started_tells_evalai_once_and_the_note_goes() {
        let mut queued = run(true);
        queued.queue.shown = Some(2);
        queued.queue.shown_at = Some(NOW - 10);
        queued.monitor.fingerprint = Some("etag-1".into());
        let (steps, run) = drive(queued, cx(), |step| match step {
            Step::MarkStarted(jobs) => {
                assert_eq!(jobs, &["lb-7-0".to_string()]);
                Answer::Started(true)
            }
            Step::ShowPlace(note) => {
                assert_eq!(note, &None);
                Answer::Shown(Write::Written)
            }
            other => quiet(JobState::Running)(other),
        });
        assert_eq!(
            kinds(&steps),
            ["wake", "observe", "started", "show", "list", "record", "ending"]
        );
        assert_eq!(run.monitor.started_at, Some(NOW));
        assert_eq!(run.queue.shown, None);

        // EvalAI not reached: tried again next round, and the run stays queued.
        let (_, run) = drive(self::run(true), cx(), |step| match step {
            Step::MarkStarted(_) => Answer::Started(false),
            Step::ReadAhead => Answer::Ahead(None),
            other => quiet(JobState::Running)(other),
        });
        assert_eq!(run.monitor.started_at, None);
    }

    #[test]
    fn a_held_submission_is_admitted_or_shown_its_changed_place() {
        let standing = |admitted| Standing {
            admitted,
            ahead: 4,
            team_ahead: 1,
            hold: Hold::TeamLimit { limit: 2 },
        };
        let (steps, run) = drive(run(false), cx(), |step| match step {
            Step::TakeTurn { arrived_ms, limit } => {
                assert_eq!((*arrived_ms, *limit), ((NOW - 600) * 1000, 2));
                Answer::Turn(standing(true))
            }
            other => quiet(JobState::Running)(other),
        });
        assert_eq!(kinds(&steps), ["wake", "turn"]);
        assert_eq!(run.monitor.state, RunPhase::Admitted);

        let (steps, run) = drive(self::run(false), cx(), |step| match step {
            Step::TakeTurn { .. } => Answer::Turn(standing(false)),
            Step::ComposeNote(place, _) => {
                assert_eq!((place.ahead, place.team_ahead, place.running), (4, 1, 0));
                Answer::Note("4 ahead".into())
            }
            Step::ShowPlace(_) => Answer::Shown(Write::Written),
            other => quiet(JobState::Running)(other),
        });
        assert_eq!(kinds(&steps), ["wake", "turn", "compose", "show"]);
        assert_eq!((run.queue.shown, run.queue.shown_at), (Some(4), Some(NOW)));
        assert_eq!(run.monitor.state, RunPhase::Running);
        assert_eq!(
            run.monitor.wait_seconds,
            queue_wait(Duration::from_secs(600)).as_secs()
        );
    }

    #[test]
    fn a_held_submission_confirms_a_cancel_first_and_ends_at_the_queue_limit() {
        let (steps, run) = drive(run(false), cx(), |step| match step {
            Step::ReadWake => Answer::Wake(Some((1, true))),
            Step::ReadStatus(_) => Answer::Status(Some(SubmissionStatus::Cancelled)),
            other => quiet(JobState::Running)(other),
        });
        assert_eq!(kinds(&steps), ["wake", "status"]);
        assert_eq!(run.monitor.state, RunPhase::Cancelled);

        let mut long = self::run(false);
        long.queue.arrived_at = NOW - 24 * 3600;
        let (steps, run) = drive(long, cx(), quiet(JobState::Running));
        assert_eq!(kinds(&steps), ["wake"]);
        assert_eq!(run.monitor.state, RunPhase::Failed);
        assert!(run
            .monitor
            .reason
            .unwrap()
            .contains("queue limit of 24 hours"));
    }

    #[test]
    fn an_unread_wake_count_makes_the_next_wait_a_poll() {
        let (_, run) = drive(started(run(true)), cx(), |step| match step {
            Step::ReadWake => Answer::Wake(None),
            other => quiet(JobState::Running)(other),
        });
        assert!(run.monitor.poll);
        assert_eq!(run.monitor.wait_seconds, POLL_WITHOUT_WAKE.as_secs());
    }

    #[test]
    fn the_status_fallback_is_read_when_due_and_yields_to_an_update() {
        let mut stale = started(run(true));
        stale.monitor.status_read_at = Some(NOW - STATUS_FALLBACK.as_secs());
        let (steps, _) = drive(stale.clone(), cx(), quiet(JobState::Running));
        assert_eq!(
            kinds(&steps),
            ["wake", "observe", "list", "status", "record", "ending"]
        );
        // A partial update's own read of the status stands for it.
        let (steps, _) = drive(stale, cx(), |step| match step {
            Step::ListResults => Answer::Listed(Some("etag-2".into())),
            Step::CollectResults { .. } => Answer::Collected(Collected::Merged {
                progress: (1, 10),
                fingerprint: "etag-2".into(),
                content: "records-2".into(),
            }),
            Step::PostPartial => Answer::Posted(Write::Written),
            other => quiet(JobState::Running)(other),
        });
        assert!(!kinds(&steps).contains(&"status"), "{steps:?}");
    }

    #[test]
    fn the_verdict_ends_a_finished_failed_or_overrun_run() {
        let (_, run) = drive(started(run(true)), cx(), quiet(JobState::Complete));
        assert_eq!(run.monitor.state, RunPhase::Finished);

        let failed = JobState::Failed {
            reason: "BackoffLimitExceeded".into(),
            message: "Job has reached the specified backoff limit".into(),
        };
        let (_, run) = drive(started(self::run(true)), cx(), quiet(failed));
        assert_eq!(run.monitor.state, RunPhase::Failed);
        let reason = run.monitor.reason.unwrap();
        assert!(
            reason.contains("failed more often than the retry limit"),
            "{reason}"
        );

        let mut long = started(self::run(true));
        long.monitor.started_at = Some(NOW - MAX_EVALUATION.as_secs() - 1);
        let (steps, run) = drive(long, cx(), quiet(JobState::Running));
        assert!(!kinds(&steps).contains(&"record"));
        assert_eq!(run.monitor.state, RunPhase::Failed);
        assert!(run.monitor.reason.unwrap().contains("72 hours"));
    }

    #[test]
    fn every_job_s_logcopy_done_shortens_the_wait() {
        let (_, run) = drive(started(run(true)), cx(), |step| match step {
            Step::ListMarkers { .. } => Answer::Markers(Some(vec!["logcopy-0.done".into()])),
            other => quiet(JobState::Running)(other),
        });
        assert_eq!(run.monitor.wait_seconds, ENDING_POLL.as_secs());
    }

    #[test]
    fn a_continuation_hands_the_queue_entry_over_until_it_is_done() {
        let mut continued = started(run(true));
        continued.monitor.execution = Some("exec-1".into());
        let cx = Context {
            execution: Some("exec-1-c1".into()),
            ..cx()
        };
        let (steps, run) = drive(continued.clone(), cx.clone(), |step| match step {
            Step::Adopt(execution) => {
                assert_eq!(execution, "exec-1-c1");
                Answer::Adopted(false)
            }
            other => quiet(JobState::Running)(other),
        });
        assert_eq!(kinds(&steps)[..2], ["adopt", "wake"]);
        assert!(run.monitor.handover, "tried again next round");
        let (steps, run) = drive(run, cx, quiet(JobState::Running));
        assert_eq!(kinds(&steps)[..3], ["adopt", "wake", "observe"]);
        assert!(!run.monitor.handover);
    }

    #[test]
    fn a_round_near_the_history_budget_continues_as_a_new_execution() {
        let mut round = Round::begin(started(run(true)), cx());
        while round.poll() != Step::Done {
            round.answer(Answer::Done);
        }
        let run = round.finish(0, "exec-1");
        assert_eq!(run.monitor.state, RunPhase::Continued);
        assert_eq!(run.monitor.continue_as.as_deref(), Some("exec-1-c1"));
        assert_eq!(run.monitor.generation, 1);
    }

    /// The cluster with one running pod of Job 0 on `node`, started a minute ago, evicted by
    /// its kubelet when `evicted`.
    fn on_node(node: &str, evicted: bool) -> Answer {
        let mut pod = crate::testutil::pod("lb-7-0-a", "lb-7-0", PodPhase::Running);
        pod.node = Some(node.into());
        pod.start_time = Some(jiff::Timestamp::from_second(NOW as i64 - 60).unwrap());
        if evicted {
            pod.disruption = Some(crate::cluster::disruption::BY_KUBELET.into());
        }
        let mut job = crate::testutil::job("lb-7-0", JobState::Running, None);
        job.pods.push(pod);
        observed(vec![job])
    }

    fn node(capacity: &str, leaving: bool) -> NodeRead {
        let kind = NodeKind {
            instance_type: "g5.12xlarge".into(),
            capacity: crate::capacity::cost::CapacityType::from_label(Some(capacity)),
        };
        let facts = NodeFacts {
            unschedulable: leaving,
            taints: Vec::new(),
            ready: true,
        };
        Some((kind, facts))
    }

    #[test]
    fn a_pod_on_a_drained_node_moves_just_after_its_pair_wrote_and_the_move_is_counted() {
        for (taint, moved) in [
            (crate::capacity::consolidation::TAINT, true),
            ("other", false),
        ] {
            let mut evicted = Vec::new();
            let (steps, after) = drive(started(run(true)), cx(), |step| match step {
                Step::Observe => on_node("n1", false),
                Step::ReadNodes(nodes) => {
                    let mut read = node("SPOT", false);
                    if let Some((_, facts)) = read.as_mut() {
                        facts.taints = vec![taint.to_string()];
                    }
                    Answer::Nodes(Some(
                        nodes.iter().map(|n| (n.clone(), read.clone())).collect(),
                    ))
                }
                Step::ListResults => Answer::Listed(Some("etag-2".into())),
                Step::CollectResults { .. } => Answer::Collected(Collected::Merged {
                    progress: (3, 10),
                    fingerprint: "etag-2".into(),
                    content: "c2".into(),
                }),
                Step::PostPartial => Answer::Posted(Write::Written),
                // The pod started at NOW - 60; its pair wrote 10 seconds ago.
                Step::ResultsWritten => Answer::ResultsWritten(BTreeMap::from([(0, NOW - 10)])),
                Step::Evict(pods) => {
                    evicted.extend(pods.iter().map(|p| (p.job, p.pod.clone(), p.node.clone())));
                    Answer::Moved(pods.iter().map(|p| p.job).collect())
                }
                other => quiet(JobState::Running)(other),
            });
            let expected = match moved {
                true => vec![(0, "lb-7-0-a".to_string(), "n1".to_string())],
                false => vec![],
            };
            assert_eq!(evicted, expected, "{taint}: {steps:?}");
            assert_eq!(after.monitor.usage.moves_of(0), u32::from(moved));
            assert!(
                kinds(&steps).contains(&"record"),
                "the round goes on: {steps:?}"
            );
        }
    }

    #[test]
    fn a_round_whose_results_did_not_change_asks_nothing_about_moves() {
        let (steps, _) = drive(started(run(true)), cx(), |step| match step {
            Step::Observe => on_node("n1", false),
            Step::ReadNodes(nodes) => Answer::Nodes(Some(
                nodes
                    .iter()
                    .map(|n| (n.clone(), node("SPOT", false)))
                    .collect(),
            )),
            other => quiet(JobState::Running)(other),
        });
        assert!(!kinds(&steps).contains(&"written"), "{steps:?}");
        assert!(!kinds(&steps).contains(&"evict"), "{steps:?}");
    }

    #[test]
    fn the_round_reads_the_node_of_a_new_pod_once_and_counts_its_gpus_on_that_kind() {
        let mut asked = Vec::new();
        let (steps, run) = drive(started(run(true)), cx(), |step| match step {
            Step::Observe => on_node("n1", false),
            Step::ReadNodes(nodes) => {
                asked.push(nodes.clone());
                Answer::Nodes(Some(BTreeMap::from([("n1".into(), node("SPOT", false))])))
            }
            other => quiet(JobState::Running)(other),
        });
        assert_eq!(asked, [vec!["n1".to_string()]]);
        assert_eq!(kinds(&steps)[..3], ["wake", "observe", "nodes"]);
        let line = &run.monitor.usage.lines[0];
        assert_eq!(
            line.kind.capacity,
            crate::capacity::cost::CapacityType::Spot
        );
        assert_eq!(line.held, 60);
    }

    #[test]
    fn a_node_that_cannot_be_read_leaves_the_count_to_the_next_round() {
        let (steps, run) = drive(started(run(true)), cx(), |step| match step {
            Step::Observe => on_node("n1", false),
            Step::ReadNodes(_) => Answer::Nodes(None),
            other => quiet(JobState::Running)(other),
        });
        assert!(
            kinds(&steps).contains(&"record"),
            "the round goes on: {steps:?}"
        );
        assert!(run.monitor.usage.lines.is_empty());
    }

    #[test]
    fn a_kubelet_eviction_is_a_reclaim_on_a_leaving_node_and_the_pods_own_on_a_staying_or_gone_one()
    {
        for (leaving, reclaim) in [(true, true), (false, false)] {
            let (steps, _) = drive(started(run(true)), cx(), |step| match step {
                Step::Observe => on_node("n2", true),
                Step::ReadNodes(nodes) => {
                    assert_eq!(nodes, &["n2".to_string()]);
                    Answer::Nodes(Some(BTreeMap::from([(
                        "n2".into(),
                        node("ON_DEMAND", leaving),
                    )])))
                }
                Step::ResultsWritten => Answer::ResultsWritten(BTreeMap::new()),
                other => quiet(JobState::Running)(other),
            });
            // A reclaim asks when the pair last wrote results: its time since is run again.
            assert_eq!(
                kinds(&steps).contains(&"written"),
                reclaim,
                "leaving {leaving}: {steps:?}"
            );
        }
        // A node gone before it was judged is taken as staying: the autoscaler removes the
        // node a pressure eviction emptied, and that is no reclaim.
        let (steps, after) = drive(started(run(true)), cx(), |step| match step {
            Step::Observe => on_node("n3", true),
            Step::ReadNodes(_) => Answer::Nodes(Some(BTreeMap::from([("n3".into(), None)]))),
            Step::ResultsWritten => Answer::ResultsWritten(BTreeMap::new()),
            other => quiet(JobState::Running)(other),
        });
        assert!(!kinds(&steps).contains(&"written"), "{steps:?}");
        assert_eq!(after.monitor.usage.jobs[0].reclaims, 0);
    }

    #[test]
    fn results_not_stored_are_not_sent_and_the_wait_shortens_to_the_interval() {
        let (steps, run) = drive(started(run(true)), cx(), |step| match step {
            Step::ListResults => Answer::Listed(Some("etag-2".into())),
            Step::CollectResults { .. } => Answer::Collected(Collected::Merged {
                progress: (3, 10),
                fingerprint: "etag-2".into(),
                content: "c2".into(),
            }),
            Step::StoreFiles => Answer::Stored(false),
            other => quiet(JobState::Running)(other),
        });
        assert!(!kinds(&steps).contains(&"post"), "{steps:?}");
        assert_eq!(run.monitor.wait_seconds, INTERVAL);
        assert_ne!(run.monitor.fingerprint.as_deref(), Some("etag-2"));
    }

    #[test]
    fn the_cluster_verdict_is_the_rounds_own_with_the_leaderboard_s_patience() {
        // A Job gone from a run of two fails it, however the other ends.
        let mut two = started(run(true));
        two.jobs = 2;
        let (_, after) = drive(two, cx(), quiet(JobState::Complete));
        assert_eq!(after.monitor.state, RunPhase::Failed);
        assert!(after.monitor.reason.unwrap().contains("index 1 of 2"));
        // A pod waiting for capacity past the leaderboard's queue limit fails the run; within
        // it, the run waits.
        let mut pod = crate::testutil::pod("lb-7-0-a", "lb-7-0", PodPhase::Pending);
        pod.unschedulable = Some(crate::cluster::view::Unschedulable {
            since: Some(jiff::Timestamp::from_second(NOW as i64 - 7200).unwrap()),
            message: "0/3 nodes are available: 3 Insufficient nvidia.com/gpu.".into(),
        });
        let mut job = crate::testutil::job("lb-7-0", JobState::Pending, None);
        job.pods.push(pod);
        for (limit_hours, ends) in [(1, true), (3, false)] {
            let mut cx = cx();
            cx.policy.queue_limit = Duration::from_secs(limit_hours * 3600);
            let seen = observed(vec![job.clone()]);
            let (steps, after) = drive(run(true), cx, |step| match step {
                Step::Observe => seen.clone(),
                Step::ReadAhead => Answer::Ahead(None),
                Step::ListResults => Answer::Listed(None),
                other => quiet(JobState::Running)(other),
            });
            let failed = after.monitor.state == RunPhase::Failed;
            assert_eq!(
                failed, ends,
                "{limit_hours} h: {steps:?} {:?}",
                after.monitor
            );
        }
    }

    #[test]
    fn the_jobs_deadlines_grow_by_the_time_reclaims_cost() {
        let mut reclaimed = started(run(true));
        reclaimed.monitor.usage.lost = 600;
        let mut observed = seen(true, JobState::Running);
        if let Answer::Observed(seen) = &mut observed {
            seen.jobs[0].state = JobState::Running;
            seen.jobs[0].deadline = Some(crate::run::schedule::JOB_DEADLINE.as_secs());
        }
        let (steps, _) = drive(reclaimed, cx(), |step| match step {
            Step::Observe => observed.clone(),
            other => quiet(JobState::Running)(other),
        });
        let wanted = crate::run::schedule::JOB_DEADLINE.as_secs() + 600;
        assert!(steps.contains(&Step::SetDeadlines(vec![("lb-7-0".into(), wanted)])));
    }

    #[test]
    fn the_72_hour_limit_binds_whatever_the_pods_do() {
        let max = MAX_EVALUATION.as_secs();
        let off = crate::cluster::disruption::MAX_TIME_OFF;
        // However much time reclaims cost (here the whole run, and more), at most the cap is
        // taken off the limit, and the Jobs' deadlines grow by no more.
        for (running_for, ends) in [(max + off, false), (max + off + 1, true)] {
            let mut run = started(run(true));
            run.monitor.started_at = Some(NOW - running_for);
            run.monitor.usage.lost = 10 * max;
            let mut observed = seen(true, JobState::Running);
            if let Answer::Observed(seen) = &mut observed {
                seen.jobs[0].state = JobState::Running;
                seen.jobs[0].deadline = Some(crate::run::schedule::JOB_DEADLINE.as_secs());
            }
            let (steps, run) = drive(run, cx(), |step| match step {
                Step::Observe => observed.clone(),
                other => quiet(JobState::Running)(other),
            });
            let wanted = crate::run::schedule::JOB_DEADLINE.as_secs() + off;
            assert!(steps.contains(&Step::SetDeadlines(vec![("lb-7-0".into(), wanted)])));
            assert_eq!(run.monitor.state == RunPhase::Failed, ends, "{running_for}");
        }
    }

    #[test]
    fn a_pair_out_of_retries_by_disruptions_of_its_own_ends_and_its_neighbour_goes_on() {
        let job = |name: &str, index: u32, failed: i32| JobView {
            index: Some(index),
            failed,
            state: JobState::Running,
            deadline: Some(crate::run::schedule::JOB_DEADLINE.as_secs()),
            ..crate::testutil::job(name, JobState::Running, None)
        };
        // Pair 1: 2 crashes its Job counted and 3 kubelet evictions on a healthy node the
        // ledger charged: 5 > backoffLimit 4. Pair 2: 4 crashes, none charged: its Job
        // controller decides alone.
        let mut run = started(run(true));
        run.jobs = 2;
        run.monitor.usage.jobs = vec![crate::capacity::cost::JobEntry {
            charged: 3,
            ..Default::default()
        }];
        let observe = |first: JobState, second: JobState| {
            let mut jobs = vec![job("lb-7-0", 0, 2), job("lb-7-1", 1, 4)];
            (jobs[0].state, jobs[1].state) = (first, second);
            observed(jobs)
        };
        let (steps, after) = drive(run.clone(), cx(), |step| match step {
            Step::Observe => observe(JobState::Running, JobState::Running),
            other => quiet(JobState::Running)(other),
        });
        let end = vec![("lb-7-0".to_string(), monitor::END_NOW)];
        assert!(steps.contains(&Step::SetDeadlines(end)), "{steps:?}");
        assert_eq!(after.monitor.state, RunPhase::Running, "pair 2 goes on");
        // Once its Job failed on that deadline, the pair is taken as out of retries, not as
        // an evaluation out of time; the neighbour still runs.
        let deadline = JobState::Failed {
            reason: "DeadlineExceeded".into(),
            message: "Job was active longer than specified deadline".into(),
        };
        let (steps, after) = drive(run.clone(), cx(), |step| match step {
            Step::Observe => observe(deadline.clone(), JobState::Running),
            other => quiet(JobState::Running)(other),
        });
        assert!(!kinds(&steps).contains(&"deadlines"), "{steps:?}");
        assert_eq!(after.monitor.state, RunPhase::Running);
        // Once the neighbour is done, the submission ends as when pairs give up, saying why.
        let (_, after) = drive(run, cx(), |step| match step {
            Step::Observe => observe(deadline.clone(), JobState::Complete),
            other => quiet(JobState::Running)(other),
        });
        assert_eq!(after.monitor.state, RunPhase::Failed);
        let reason = after.monitor.reason.unwrap();
        assert!(reason.contains("retry limit"), "{reason}");
        assert!(
            reason.contains("3 of its pods were stopped by a disruption of their own"),
            "{reason}"
        );
        assert_eq!(
            after.monitor.failure,
            Some(FailureKind::BackoffLimitExceeded)
        );
    }

    #[test]
    fn a_pair_the_platform_alone_took_away_fails_as_the_platform_s_failure() {
        use crate::capacity::cost::JobEntry;
        let job = |name: &str, index: u32, state: JobState| JobView {
            index: Some(index),
            deadline: Some(crate::run::schedule::JOB_DEADLINE.as_secs()),
            ..crate::testutil::job(name, state, None)
        };
        let deadline = JobState::Failed {
            reason: "DeadlineExceeded".into(),
            message: "Job was active longer than specified deadline".into(),
        };
        // 8 drains of pair 1: 3 free reclaims, then 5 charged as the platform's (> 4).
        let ended = |entry: JobEntry, failed: i32, ended_by_platform: Vec<u32>| {
            let mut run = started(run(true));
            run.jobs = 2;
            run.monitor.usage.jobs = vec![entry];
            run.monitor.ended_by_platform = ended_by_platform;
            let deadline = deadline.clone();
            let (_, after) = drive(run, cx(), move |step| match step {
                Step::Observe => {
                    let mut first = job("lb-7-0", 0, deadline.clone());
                    first.failed = failed;
                    observed(vec![first, job("lb-7-1", 1, JobState::Complete)])
                }
                other => quiet(JobState::Running)(other),
            });
            after.monitor
        };
        let drained = JobEntry {
            reclaims: 3,
            charged: 5,
            excess: 5,
            ..Default::default()
        };
        let platform = ended(drained, 0, vec![]);
        assert_eq!(platform.state, RunPhase::Failed);
        assert_eq!(platform.failure, Some(FailureKind::PlatformReclaims));
        assert_eq!(platform.ended_by_platform, [0]);
        // The pod our deadline stopped then counts as failed for the Job, not the participant.
        let stopped = ended(drained, 1, vec![0]);
        assert_eq!(stopped.failure, Some(FailureKind::PlatformReclaims));
        assert!(stopped.reason.unwrap().contains("with 0 failed pod(s)"));
        let reason = platform.reason.unwrap();
        assert!(
            reason.contains("the platform took its pods away"),
            "{reason}"
        );
        assert!(reason.contains("not your agent's"), "{reason}");
        assert!(!reason.contains("disruption of their own"), "{reason}");
        // One crash of its own among them, or one of the charges its own: the participant's.
        let crashed = ended(drained, 1, vec![]);
        assert_eq!(crashed.failure, Some(FailureKind::BackoffLimitExceeded));
        let own = JobEntry {
            excess: 4,
            ..drained
        };
        let mixed = ended(own, 0, vec![]);
        assert_eq!(mixed.failure, Some(FailureKind::BackoffLimitExceeded));
        assert!(mixed
            .reason
            .unwrap()
            .contains("1 of its pods were stopped by a disruption of their own"));
    }
}
