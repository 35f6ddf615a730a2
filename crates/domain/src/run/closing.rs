//! Finalize's end of a run without I/O: the shell performs each batch of [`Step`]s (side by
//! side: a batch holds only steps independent of each other) and gives back what it found as
//! [`Answer`]s; [`Closing`] decides, in this one place, what happens and in which order.
//!
//! Only the execution that holds the claim ends the run, once: a superseded one touches
//! nothing of the submission, and a repeated one reports what stands and gives the place back.
//! The execution's own Jobs stop at once, beside the claim's read (GPUs cost money, and their
//! logcopy makes its last upload on the way out; those from before the execution label wait
//! for the claim, as they are its holder's), then what the run left is read, with EvalAI's
//! status beside it, and the final status decided
//! ([`crate::run::finalize::outcome`]); results that cannot be read for now fail the attempt (the
//! state machine retries it) unless the outcome does not need them. A failed run's
//! participant reads the end of its most crashed agent's log; a passed qualifier admits its
//! team. EvalAI gets the final word before the record, and the place is given back only after
//! it, so the team never shows more evaluations in progress than its cap. What needs only the
//! decision (keeping the files, the log's end, the admission, the recordings' listing and
//! heads, the upload reports, the track's pace) is asked at once, so a finished result's
//! recordings are audited before the post and a failed audit is said on EvalAI, and the post is
//! only the write and its confirmation (none over a cancel or a final status seen at the read);
//! the record, the pace and the place go together at the end: a Finalize waits on five batches.

use std::collections::{BTreeMap, HashMap};

use crate::capacity::cost::{InstancePrice, Totals};
use crate::capacity::queue;
use crate::job::logtail::{participant_tail, MAX_TAIL_CHARS};
use crate::job::protocol::{self, CANCEL_MARKER, LOGS_DIR};
use crate::job::uploads::{self, UploadReport};
use crate::results::py::Num;
use crate::run::audit::{self, Expected, Recordings, Window};
use crate::run::finalize::{self, Outcome, Posted};
use crate::run::state::{PairRoutes, RunPhase, RunState};
use crate::settings::QualifierSettings;
use crate::status::{RecordStatus, Settled};
use crate::submission::SubmissionStatus;

/// Bytes read from the end of an agent's log: enough for [`MAX_TAIL_CHARS`] characters of
/// multi-byte text and the escapes that are stripped from it.
pub const TAIL_BYTES: u64 = 64 * 1024;

/// What Finalize knows before it reads anything.
#[derive(Debug, Clone, Copy)]
pub struct Context<'a> {
    /// The execution this Finalize runs in (the claim it must hold).
    pub execution: &'a str,
    /// The error a Catch caught on the way here.
    pub caught: Option<&'a str>,
    /// The run, when Launch started one.
    pub run: Option<&'a RunState>,
    /// The submission's track.
    pub track: &'a str,
    /// The qualifier's settings, when the track is a qualifier.
    pub qualifier: Option<&'a QualifierSettings>,
    /// The track's route lengths in metres, by route number (empty: none given): the floor
    /// of each recording's audit.
    pub route_lengths: &'a [u32],
    /// Now, epoch seconds: the pods still running at the last round are charged until now.
    pub now: u64,
    /// The GPU prices the run's usage is priced at.
    pub prices: &'a BTreeMap<String, InstancePrice>,
}

/// What the shell is asked to do next.
#[derive(Debug, Clone, PartialEq)]
pub enum Step {
    /// Read the submission's record ([`Answer::Standing`]).
    ReadStanding,
    /// Delete this execution's Jobs and wait, bounded, for their pods ([`Answer::Stopped`]).
    StopJobs {
        /// Those from before the execution label too: they are the claim holder's, so only
        /// once the claim is known to be this execution's.
        unlabelled: bool,
    },
    /// Read the markers, and the merged results of these pairs when there was a run
    /// ([`Answer::Left`]).
    ReadLeft {
        /// The run's pairs and the repetitions of each route (`None`: no run).
        results: Option<(Vec<PairRoutes>, u32)>,
    },
    /// Keep the merge and the files EvalAI gets in S3, before the final update
    /// ([`Answer::Done`]).
    StoreFiles,
    /// The Jobs could not be stopped, or the results could not be read for now and the
    /// outcome needs them: fail with that error, so the state machine tries Finalize again.
    TryAgain,
    /// Read the end of the agent's log at this key, at most `bytes` ([`Answer::Tail`]).
    ReadAgentTail {
        /// The log's key under the submission.
        key: String,
        /// How much of its end.
        bytes: u64,
    },
    /// Read the upload reports of the run's Jobs at these keys ([`Answer::Reports`]).
    ReadReports(Vec<String>),
    /// Admit the team to these main tracks: it passed their qualifier ([`Answer::Done`]).
    Admit(Vec<String>),
    /// Read the submission's status on EvalAI, taking the places of the final update's write
    /// and read back beside it ([`Answer::OnEvalAi`]): a cancel or a final status there is not
    /// written over.
    ReadEvalAi,
    /// Post the final update to EvalAI and confirm it ([`Answer::Posted`]).
    Post {
        /// The final status.
        status: SubmissionStatus,
        /// The participant's stdout: the pairs note, the qualifier's verdict, the summary.
        stdout: String,
        /// The participant's stderr: the reason and the agent's log tail.
        stderr: String,
    },
    /// List the recordings folder (`recorder/`, [`Answer::Listed`]), to audit the recordings.
    ListRecordings,
    /// Read the first [`audit::HEAD_BYTES`] of each of these recordings (submission-relative
    /// keys of every recording the result needs, [`Answer::Heads`]), beside the listing.
    ReadHeads(Vec<String>),
    /// Write the final record ([`Answer::Recorded`]).
    WriteRecord {
        /// The record's status.
        status: RecordStatus,
        /// The error operators read: the whole caught chain, or the outcome's reason.
        error: Option<String>,
        /// The failure was the platform's own.
        failed_by_platform: bool,
        /// What can be audited of a FINISHED result (`None`: another outcome, or the logs
        /// could not be listed).
        recordings: Option<Recordings>,
        /// What the run used: its pods charged until now, its orchestration so far and what
        /// its Jobs' logcopy stored; `None` without a run.
        usage: Option<Totals>,
    },
    /// Read the track's pace, the durations of its latest evaluations ([`Answer::Pace`]), for
    /// this run's to join once EvalAI has the final word.
    ReadPace,
    /// Keep the track's pace, this run's duration first, best effort ([`Answer::Done`]).
    RecordPace {
        /// Seconds, most recent first ([`queue::with_latest`]).
        durations: Vec<u64>,
    },
    /// Give the team its place back and wake its next submission ([`Answer::Done`]).
    LeaveQueue,
}

/// The record as the shell read it.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Record {
    /// The execution that claimed it last.
    pub claimed_by: Option<String>,
    /// Its status.
    pub status: Option<RecordStatus>,
    /// Its stored failure reason.
    pub error: Option<String>,
    /// Its failure was the platform's own.
    pub failed_by_platform: bool,
}

/// What stands once Finalize decided.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Settlement {
    /// The final status, or why nothing of the submission was touched.
    pub status: Settled,
    /// Why, for a failure (or a superseded execution).
    pub reason: Option<String>,
    /// The failure was the platform's own, not the participant's: operators look.
    pub by_platform: bool,
}

/// The merged results as Finalize needs them.
#[derive(Debug, Clone, PartialEq)]
pub enum Read {
    /// Merged.
    Merged(Merged),
    /// The results themselves are broken: the error chain.
    Unusable(String),
    /// Transient trouble reading them: the error chain.
    NotNow(String),
}

/// What a merge of the results gave.
#[derive(Debug, Clone, PartialEq)]
pub struct Merged {
    /// Every planned route has its records.
    pub complete: bool,
    /// Records merged and planned.
    pub progress: (u64, u64),
    /// The pairs whose results file is complete.
    pub finished_pairs: Vec<u32>,
    /// (attribute, value) per metric, for the qualifier's verdict.
    pub metrics: Vec<(&'static str, Num)>,
    /// The merged records as the recordings' audit needs them.
    pub routes: Vec<audit::Route>,
    /// The summary the participant's stdout ends with.
    pub summary: String,
}

/// What the run left in S3.
#[derive(Debug, Clone, PartialEq)]
pub struct Left {
    /// The status markers' names.
    pub markers: Vec<String>,
    /// The results (`None`: there was no run to read).
    pub results: Option<Read>,
}

/// What the shell found doing a [`Step`].
#[derive(Debug, Clone, PartialEq)]
pub enum Answer {
    /// The step was done.
    Done,
    /// The Jobs were stopped, or could not be (the shell keeps why, for [`Step::TryAgain`]).
    Stopped {
        /// Objects without the execution label were seen and left.
        unlabelled_left: bool,
        /// The stop failed: only a run this execution still ends needs it.
        failed: bool,
    },
    /// The track's latest durations, most recent first (`None`: unreadable).
    Pace(Option<Vec<u64>>),
    /// The record (`None`: there is none).
    Standing(Option<Record>),
    /// What the run left.
    Left(Left),
    /// The end of the agent's log as stored (`None`: unreadable or absent).
    Tail(Option<Vec<u8>>),
    /// The upload reports that could be read and are reports.
    Reports(Vec<UploadReport>),
    /// The submission's status on EvalAI before the final update.
    OnEvalAi(SubmissionStatus),
    /// What EvalAI did with the final update.
    Posted(Posted),
    /// The recordings folder: (submission-relative key, size) (`None`: not listed).
    Listed(Option<Vec<(String, u64)>>),
    /// The heads read, by key (a head that could not be read is left out).
    Heads(HashMap<String, Vec<u8>>),
    /// The record was written (`false`: the claim moved on, the record is another's).
    Recorded(bool),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stage {
    /// The claim, and the execution's own Jobs stopped beside it.
    Standing,
    /// The claim is ours: the Jobs from before the execution label stop too.
    StopUnlabelled,
    /// What the run left, and EvalAI's status beside it.
    Read,
    TryAgain,
    /// What needs only the decision, side by side.
    Gather,
    /// The final word, and the recordings' heads beside it.
    Post,
    /// The record, the pace and the place.
    End,
    /// A repeated Finalize: only the place.
    Leave,
    Done,
}

/// One Finalize of a claimed run.
#[derive(Debug)]
pub struct Closing<'a> {
    cx: Context<'a>,
    stage: Stage,
    /// What stands once decided, and why.
    settled: Option<Settlement>,
    outcome: Option<Outcome>,
    merged: Option<Merged>,
    /// The most crashed agent's pair, whose log's end the participant reads.
    crashed: Option<u32>,
    /// The most crashed agent's pair and the end of its log, once read.
    tail: Option<(u32, String)>,
    /// The qualifier's verdict and the tracks a pass admits to.
    verdict: Option<(String, Vec<String>)>,
    recordings: Option<Recordings>,
    /// What the Jobs' logcopy stored and refused, added up, once the reports are read
    /// (`Some(None)`: none could be read).
    reports: Option<Option<UploadReport>>,
    /// The recordings listed, until their heads are read.
    listed: Option<Vec<(String, u64)>>,
    /// The submission's status on EvalAI before the final update.
    on_evalai: Option<SubmissionStatus>,
    /// Objects from before the execution label were left by the first stop.
    unlabelled_left: bool,
    /// A stop of the Jobs failed.
    stop_failed: bool,
    /// The track's pace as read before the post (`None`: not read, or unreadable).
    pace_read: Option<Vec<u64>>,
}

impl<'a> Closing<'a> {
    /// The end of a run Finalize's execution claimed.
    pub fn begin(cx: Context<'a>) -> Closing<'a> {
        Closing {
            cx,
            stage: Stage::Standing,
            settled: None,
            outcome: None,
            merged: None,
            crashed: None,
            tail: None,
            verdict: None,
            recordings: None,
            reports: None,
            listed: None,
            on_evalai: None,
            unlabelled_left: false,
            stop_failed: false,
            pace_read: None,
        }
    }

    /// What the shell does next, side by side: the steps of one batch, independent of each
    /// other; none once Finalize is over.
    pub fn poll(&self) -> Vec<Step> {
        match self.stage {
            // The stop first: connecting to the cluster takes the processor a while, and the
            // claim's read is on its way meanwhile.
            Stage::Standing => vec![Step::StopJobs { unlabelled: false }, Step::ReadStanding],
            Stage::StopUnlabelled => vec![Step::StopJobs { unlabelled: true }],
            Stage::Read => vec![
                Step::ReadLeft {
                    results: (self.cx.run).map(|run| (run.pairs.clone(), run.repetitions)),
                },
                Step::ReadEvalAi,
            ],
            Stage::TryAgain => vec![Step::TryAgain],
            Stage::Gather => self.gather(),
            Stage::Post => self.post().into_iter().collect(),
            Stage::End => {
                let recent = self.pace_read.as_deref();
                let pace = (self.pace().zip(recent))
                    .map(|(seconds, recent)| queue::with_latest(recent, seconds))
                    .map(|durations| Step::RecordPace { durations });
                let record = self.record();
                record
                    .into_iter()
                    .chain(pace)
                    .chain([Step::LeaveQueue])
                    .collect()
            }
            Stage::Leave => vec![Step::LeaveQueue],
            Stage::Done => Vec::new(),
        }
    }

    /// Takes what the shell found doing the batch [`Closing::poll`] gave last, an answer per
    /// step in its order. Answers that do not fit that batch are a bug in the shell: Finalize
    /// ends there unsettled.
    pub fn answer(&mut self, answers: Vec<Answer>) {
        let asked = self.poll();
        let fits = answers.len() == asked.len()
            && asked
                .iter()
                .zip(&answers)
                .all(|(step, answer)| answers_to(step, answer));
        if !fits {
            self.stage = Stage::Done;
            return;
        }
        let mut answers = answers.into_iter();
        self.stage = match self.stage {
            Stage::Standing => {
                let record = self.all_but(answers, |answer| match answer {
                    Answer::Standing(record) => Pick::This(record),
                    answer => Pick::Other(answer),
                });
                self.stood(record.flatten().unwrap_or_default())
            }
            Stage::StopUnlabelled => {
                answers.for_each(|answer| self.gathered(answer));
                match self.stop_failed {
                    true => Stage::TryAgain,
                    false => Stage::Read,
                }
            }
            Stage::Read => {
                let left = self.all_but(answers, |answer| match answer {
                    Answer::Left(left) => Pick::This(left),
                    answer => Pick::Other(answer),
                });
                match left.map(|left| self.decide(left)) {
                    // Nothing to gather (no run, no merge): straight to the post.
                    Some(Stage::Gather) if self.gather().is_empty() => self.all_gathered(None),
                    Some(stage) => stage,
                    None => Stage::Done,
                }
            }
            Stage::Gather => {
                let heads = self.all_but(answers, |answer| match answer {
                    Answer::Heads(heads) => Pick::This(heads),
                    answer => Pick::Other(answer),
                });
                self.all_gathered(heads)
            }
            Stage::Post => match answers.next() {
                Some(Answer::Posted(posted)) => self.posted(posted),
                _ => Stage::Done,
            },
            Stage::End => {
                self.recorded();
                Stage::Done
            }
            Stage::TryAgain | Stage::Leave | Stage::Done => Stage::Done,
        };
    }

    /// What stands, and why: `Settled::Ended` with the final status, or `Superseded`
    /// (`None`: it ended before deciding, which only a shell's misfit answer does).
    pub fn finish(self) -> Option<Settlement> {
        self.settled
    }

    fn settle(&mut self, status: Settled, reason: Option<String>, by_platform: bool) {
        self.settled = Some(Settlement {
            status,
            reason,
            by_platform,
        });
    }

    /// A superseded execution does nothing; a repeated Finalize reports what stands and only
    /// gives the place back (an earlier attempt may have ended before it did).
    fn stood(&mut self, record: Record) -> Stage {
        if let Some(why) = finalize::superseded(record.claimed_by.as_deref(), self.cx.execution) {
            self.settle(Settled::Superseded, Some(why), false);
            return Stage::Done;
        }
        match record.status.filter(|status| !status.is_in_flight()) {
            Some(status) => {
                let by_platform = record.failed_by_platform && status == RecordStatus::Failed;
                self.settle(Settled::Ended(status), record.error, by_platform);
                Stage::Leave
            }
            // A superseded or repeated Finalize ends without its stop, as it ended before it
            // stopped anything (a stale execution's Jobs left running end at their
            // `activeDeadlineSeconds`); this run's end needs it.
            None if self.stop_failed => Stage::TryAgain,
            None if self.unlabelled_left => Stage::StopUnlabelled,
            None => Stage::Read,
        }
    }

    /// The final status from what the run left ([`finalize::outcome`]).
    fn decide(&mut self, left: Left) -> Stage {
        let run = self.cx.run;
        let cancelled = run.is_some_and(|r| r.monitor.state == RunPhase::Cancelled)
            || left.markers.iter().any(|m| m == CANCEL_MARKER);
        if matches!(left.results, Some(Read::NotNow(_))) && !cancelled && self.cx.caught.is_none() {
            return Stage::TryAgain;
        }
        let pairs: Vec<(u32, &str)> = run
            .map(|r| r.pairs.iter().map(|p| (p.id, p.routes.as_str())).collect())
            .unwrap_or_default();
        let facts_run = match (run, &left.results) {
            (Some(run), Some(read)) => Some(finalize::Run {
                finished: run.monitor.state == RunPhase::Finished,
                reason: run.monitor.reason.as_deref(),
                by_platform: run.monitor.failure.is_some_and(|k| k.by_platform()),
                pairs: &pairs,
                results: match read {
                    Read::Merged(m) => Ok(finalize::Results {
                        complete: m.complete,
                        progress: m.progress,
                        finished_pairs: &m.finished_pairs,
                    }),
                    Read::Unusable(problem) | Read::NotNow(problem) => Err(problem.as_str()),
                },
            }),
            _ => None,
        };
        let outcome = finalize::outcome(&finalize::Facts {
            cancelled,
            caught: self.cx.caught,
            run: facts_run,
        });
        self.merged = match left.results {
            Some(Read::Merged(merged)) => Some(merged),
            _ => None,
        };
        match outcome.status {
            // The platform's own failure is not the agent's: its log has nothing to explain.
            SubmissionStatus::Failed if outcome.by_platform => {}
            SubmissionStatus::Failed => {
                self.crashed =
                    finalize::most_crashed_agent(left.markers.iter().map(String::as_str));
            }
            SubmissionStatus::Finished => self.qualify(),
            _ => {}
        }
        self.outcome = Some(outcome);
        Stage::Gather
    }

    /// A finished qualifier run: as the original, the verdict heads the participant's stdout
    /// either way, and a pass admits the team to the qualifier's target tracks.
    fn qualify(&mut self) {
        let Some(qualifier) = self.cx.qualifier else {
            return;
        };
        let targets = qualifier.targets_of(self.cx.track);
        let Some(first) = targets.first() else {
            return;
        };
        let metrics = self
            .merged
            .as_ref()
            .map_or(&[][..], |m| m.metrics.as_slice());
        let (passed, verdict) = qualifier.verdict(first, metrics);
        let admitted = if passed {
            targets.iter().map(|t| t.to_string()).collect()
        } else {
            Vec::new()
        };
        self.verdict = Some((verdict, admitted));
    }

    /// What needs only the decision: the merge kept, the crashed agent's log, the team
    /// admitted, a finished result's recordings listed, the Jobs' upload reports, the pace.
    fn gather(&self) -> Vec<Step> {
        let store = self.merged.is_some().then_some(Step::StoreFiles);
        let tail = self.crashed.map(|pair| Step::ReadAgentTail {
            key: format!("{LOGS_DIR}/{}/agent.log", protocol::agent_logs_dir(pair)),
            bytes: TAIL_BYTES,
        });
        let admit = (self.verdict.as_ref())
            .filter(|(_, tracks)| !tracks.is_empty())
            .map(|(_, tracks)| Step::Admit(tracks.clone()));
        let finished = self.outcome.as_ref().map(|o| o.status) == Some(SubmissionStatus::Finished);
        let recorded = self.cx.run.is_some_and(|run| run.recorder);
        let audited = finished && recorded && self.merged.is_some();
        let listing = audited.then_some(Step::ListRecordings);
        let keys = || self.expected().iter().map(Expected::key).collect();
        let heads = audited.then(|| Step::ReadHeads(keys()));
        let reports = (self.cx.run)
            .map(|run| Step::ReadReports((0..run.jobs).map(uploads::report_key).collect()));
        let pace = self.pace().map(|_| Step::ReadPace);
        [store, tail, admit, listing, heads, reports, pace]
            .into_iter()
            .flatten()
            .collect()
    }

    /// The answer `pick` takes out of a batch's; the others are kept as they come
    /// ([`Closing::gathered`]).
    fn all_but<T>(
        &mut self,
        answers: impl Iterator<Item = Answer>,
        pick: impl Fn(Answer) -> Pick<T>,
    ) -> Option<T> {
        let mut picked = None;
        for answer in answers {
            match pick(answer) {
                Pick::This(it) => picked = Some(it),
                Pick::Other(answer) => self.gathered(answer),
            }
        }
        picked
    }

    fn gathered(&mut self, answer: Answer) {
        match answer {
            Answer::Tail(bytes) => {
                let tail = bytes.map(|bytes| participant_tail(&bytes, MAX_TAIL_CHARS));
                let tail = tail.filter(|t| !t.is_empty());
                self.tail = self.crashed.zip(tail);
            }
            Answer::Listed(listed) => self.listed = listed,
            Answer::OnEvalAi(status) => self.on_evalai = Some(status),
            Answer::Stopped {
                unlabelled_left,
                failed,
            } => {
                self.unlabelled_left = unlabelled_left;
                self.stop_failed = failed;
            }
            Answer::Pace(recent) => self.pace_read = recent,
            Answer::Reports(reports) => {
                self.reports = Some(reports.into_iter().reduce(UploadReport::plus));
            }
            _ => {}
        }
    }

    /// Once all is gathered: the recordings judged, and the post, unless EvalAI's status
    /// already stands (a cancel, a final status).
    fn all_gathered(&mut self, heads: Option<HashMap<String, Vec<u8>>>) -> Stage {
        self.recordings = heads.and_then(|heads| self.audit(&heads));
        match self.on_evalai.and_then(finalize::unwritable) {
            Some(stands) => self.posted(stands),
            None => Stage::Post,
        }
    }

    fn post(&self) -> Option<Step> {
        let outcome = self.outcome.as_ref()?;
        let summary = self.merged.as_ref().map_or("", |m| m.summary.as_str());
        let verdict = self.verdict.as_ref().map(|(v, _)| v.as_str());
        let tail = self
            .tail
            .as_ref()
            .map(|(pair, tail)| (*pair, tail.as_str()));
        Some(Step::Post {
            status: outcome.status,
            stdout: finalize::stdout(outcome.pairs_note.as_deref(), verdict, summary),
            stderr: finalize::stderr(outcome, tail, self.recordings.as_ref()),
        })
    }

    /// EvalAI's final word wins over ours ([`finalize::settle`]); only a FINISHED result keeps
    /// its recordings' audit.
    fn posted(&mut self, posted: Posted) -> Stage {
        if let Some(outcome) = self.outcome.take() {
            self.outcome = Some(finalize::settle(outcome, posted));
        }
        let finished = self.outcome.as_ref().map(|o| o.status) == Some(SubmissionStatus::Finished);
        if !finished {
            self.recordings = None;
        }
        Stage::End
    }

    fn expected(&self) -> Vec<audit::Expected> {
        self.merged.as_ref().map_or_else(Vec::new, |m| {
            audit::expected(&m.routes, self.cx.route_lengths)
        })
    }

    /// The recordings judged (`None` without a run to date them by).
    fn audit(&self, heads: &HashMap<String, Vec<u8>>) -> Option<Recordings> {
        let run = self.cx.run?;
        let listed = self.listed.as_deref()?;
        let window = Window {
            launched_at: run.launched_at,
        };
        Some(audit::audit(&self.expected(), listed, heads, window))
    }

    fn record(&self) -> Option<Step> {
        let outcome = self.outcome.as_ref()?;
        Some(Step::WriteRecord {
            status: record_status(outcome.status),
            error: self
                .cx
                .caught
                .map(str::to_owned)
                .or_else(|| outcome.reason.clone()),
            failed_by_platform: outcome.by_platform,
            recordings: self.recordings.clone(),
            usage: self.usage(),
        })
    }

    /// A finished evaluation's seconds from its first pair's start to now, for its track's
    /// pace (`None`: another outcome, or it never started).
    fn pace(&self) -> Option<u64> {
        let outcome = self.outcome.as_ref()?;
        let started = self.cx.run.and_then(|r| r.monitor.started_at)?;
        let finished = record_status(outcome.status) == RecordStatus::Finished;
        finished.then(|| self.cx.now.saturating_sub(started))
    }

    /// What the run's GPUs came to: the Monitor's count, with the pods still running at its
    /// last round charged until now (their Jobs were just deleted), and the orchestration's
    /// so far.
    fn usage(&self) -> Option<Totals> {
        let run = self.cx.run?;
        let mut ledger = run.monitor.usage.clone();
        ledger.close_all(self.cx.now);
        Some(Totals {
            orchestration: Some(run.monitor.orchestration),
            stored: self.reports.flatten(),
            ..ledger.summary(self.cx.prices)
        })
    }

    /// The status stands whether or not the record was ours to write (a resume that claimed
    /// it anew owns it; EvalAI had our final word before that).
    fn recorded(&mut self) {
        if let Some(outcome) = &self.outcome {
            let status = Settled::Ended(record_status(outcome.status));
            let (reason, by_platform) = (outcome.reason.clone(), outcome.by_platform);
            self.settle(status, reason, by_platform);
        }
    }
}

/// An answer [`Closing::all_but`] takes, or one it keeps as it comes.
enum Pick<T> {
    This(T),
    Other(Answer),
}

/// Whether `answer` is what `step` is answered with.
fn answers_to(step: &Step, answer: &Answer) -> bool {
    matches!(
        (step, answer),
        (Step::ReadStanding, Answer::Standing(_))
            | (Step::ReadLeft { .. }, Answer::Left(_))
            | (Step::ReadAgentTail { .. }, Answer::Tail(_))
            | (Step::ReadReports(_), Answer::Reports(_))
            | (Step::ReadEvalAi, Answer::OnEvalAi(_))
            | (Step::Post { .. }, Answer::Posted(_))
            | (Step::ListRecordings, Answer::Listed(_))
            | (Step::ReadHeads(_), Answer::Heads(_))
            | (Step::WriteRecord { .. }, Answer::Recorded(_))
            | (Step::StopJobs { .. }, Answer::Stopped { .. })
            | (Step::ReadPace, Answer::Pace(_))
            | (
                Step::StoreFiles
                    | Step::TryAgain
                    | Step::Admit(_)
                    | Step::RecordPace { .. }
                    | Step::LeaveQueue,
                Answer::Done
            )
    )
}

/// The record's word for EvalAI's final status.
fn record_status(status: SubmissionStatus) -> RecordStatus {
    match status {
        SubmissionStatus::Finished => RecordStatus::Finished,
        SubmissionStatus::Cancelled => RecordStatus::Cancelled,
        _ => RecordStatus::Failed,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cluster::view::FailureKind;
    use crate::run::state::{MonitorState, PairRoutes, QueueState};
    use std::collections::BTreeMap;

    const EXECUTION: &str = "exec-1";

    fn run(state: RunPhase, started: bool) -> RunState {
        let mut monitor = MonitorState::starting(30, 0, 10, EXECUTION, 0);
        monitor.state = state;
        monitor.started_at = started.then_some(900);
        RunState {
            jobs: 2,
            pairs: vec![
                PairRoutes {
                    id: 1,
                    routes: "0-1".into(),
                },
                PairRoutes {
                    id: 2,
                    routes: "2-3".into(),
                },
            ],
            repetitions: 1,
            launched_at: 0,
            recorder: true,
            monitor,
            queue: QueueState::arriving(0),
        }
    }

    fn cx<'a>(run: Option<&'a RunState>, caught: Option<&'a str>) -> Context<'a> {
        Context {
            execution: EXECUTION,
            caught,
            run,
            track: "qualifier",
            qualifier: None,
            route_lengths: &[],
            now: 0,
            prices: &NO_PRICES,
        }
    }

    static NO_PRICES: BTreeMap<String, InstancePrice> = BTreeMap::new();

    fn merged(complete: bool, score: f64) -> Read {
        Read::Merged(Merged {
            complete,
            progress: if complete { (4, 4) } else { (2, 4) },
            finished_pairs: if complete { vec![1, 2] } else { vec![1] },
            metrics: vec![("driving_score", Num::Float(score))],
            routes: (0..2)
                .map(|n| audit::Route {
                    pair: 1,
                    id: format!("RouteScenario_{n}_rep0"),
                    route: n,
                    game_seconds: 1.0,
                    completion: 100.0,
                    scores: true,
                })
                .collect(),
            summary: "summary".into(),
        })
    }

    fn recording(route: u32, size: u64) -> (String, u64) {
        let key = format!("recorder/pair1/RouteScenario_{route}_rep0.log");
        (key, size)
    }

    /// Every head asked for, as CARLA writes it, dated at the run's launch.
    fn heads(keys: &[String]) -> Answer {
        let mut head = audit::MAGIC.to_vec();
        head.extend_from_slice(&0i64.to_le_bytes());
        head.extend_from_slice(&5u16.to_le_bytes());
        head.extend_from_slice(b"Town1");
        Answer::Heads(keys.iter().map(|k| (k.clone(), head.clone())).collect())
    }

    /// A world where everything goes well: the record is ours and in flight, the run left
    /// `results` and `markers`, EvalAI writes what it is sent, both recordings are there.
    fn world(results: Option<Read>, markers: &[&str]) -> impl FnMut(&Step) -> Answer {
        let markers: Vec<String> = markers.iter().map(|m| m.to_string()).collect();
        move |step| match step {
            Step::ReadStanding => Answer::Standing(Some(Record {
                claimed_by: Some(EXECUTION.into()),
                status: Some(RecordStatus::Running),
                error: None,
                failed_by_platform: false,
            })),
            Step::ReadLeft { .. } => Answer::Left(Left {
                markers: markers.clone(),
                results: results.clone(),
            }),
            Step::ReadAgentTail { .. } => Answer::Tail(Some(b"Traceback: boom".to_vec())),
            Step::ReadReports(keys) => Answer::Reports(
                keys.iter()
                    .map(|_| UploadReport {
                        log_bytes: 10,
                        ..UploadReport::default()
                    })
                    .collect(),
            ),
            Step::ReadEvalAi => Answer::OnEvalAi(SubmissionStatus::Running),
            Step::Post { .. } => Answer::Posted(Posted::Written),
            Step::ListRecordings => {
                Answer::Listed(Some(vec![recording(0, 1000), recording(1, 1000)]))
            }
            Step::ReadHeads(keys) => heads(keys),
            Step::WriteRecord { .. } => Answer::Recorded(true),
            Step::ReadPace => Answer::Pace(Some(vec![600, 500])),
            step => plain(step),
        }
    }

    /// The answer that says nothing more than that the step was done.
    fn plain(step: &Step) -> Answer {
        match step {
            Step::StopJobs { .. } => Answer::Stopped {
                unlabelled_left: false,
                failed: false,
            },
            _ => Answer::Done,
        }
    }

    /// What stands at the end, and why.
    type Stands = Option<(Settled, Option<String>)>;

    /// Runs a Finalize, answering each step with `world`; the batches asked and what stands.
    fn drive(cx: Context<'_>, world: impl FnMut(&Step) -> Answer) -> (Vec<Vec<Step>>, Stands) {
        let (batches, settled) = settle(cx, world);
        (batches, settled.map(|s| (s.status, s.reason)))
    }

    /// [`drive`], with the whole settlement.
    fn settle(
        cx: Context<'_>,
        mut world: impl FnMut(&Step) -> Answer,
    ) -> (Vec<Vec<Step>>, Option<Settlement>) {
        let mut closing = Closing::begin(cx);
        let mut batches = Vec::new();
        loop {
            let batch = closing.poll();
            if batch.is_empty() {
                return (batches, closing.finish());
            }
            assert!(batches.len() < 20, "Finalize does not end: {batches:?}");
            let answers = batch.iter().map(&mut world).collect();
            batches.push(batch);
            closing.answer(answers);
        }
    }

    /// Each batch's steps by kind.
    fn kinds(batches: &[Vec<Step>]) -> Vec<Vec<&'static str>> {
        batches.iter().map(|batch| kinds_of(batch)).collect()
    }

    /// Every step asked, batch after batch.
    fn flat(batches: &[Vec<Step>]) -> Vec<&'static str> {
        kinds(batches).concat()
    }

    fn kinds_of(steps: &[Step]) -> Vec<&'static str> {
        steps.iter().map(kind).collect()
    }

    fn kind(step: &Step) -> &'static str {
        match step {
            Step::ReadStanding => "standing",
            Step::StopJobs { unlabelled: false } => "stop",
            Step::StopJobs { unlabelled: true } => "stop-unlabelled",
            Step::ReadLeft { .. } => "read",
            Step::TryAgain => "again",
            Step::StoreFiles => "store",
            Step::ReadAgentTail { .. } => "tail",
            Step::ReadReports(_) => "reports",
            Step::Admit(_) => "admit",
            Step::ReadEvalAi => "evalai",
            Step::Post { .. } => "post",
            Step::ListRecordings => "recordings",
            Step::ReadHeads(_) => "heads",
            Step::WriteRecord { .. } => "record",
            Step::ReadPace => "read-pace",
            Step::RecordPace { .. } => "pace",
            Step::LeaveQueue => "leave",
        }
    }

    fn find<'s>(batches: &'s [Vec<Step>], wanted: &str) -> &'s Step {
        let mut steps = batches.iter().flatten();
        let found = steps.find(|step| kind(step) == wanted);
        found.unwrap_or_else(|| panic!("no {wanted} in {batches:?}"))
    }

    #[test]
    fn a_finished_run_stops_its_jobs_first_posts_before_the_record_and_leaves_the_queue_last() {
        let run = run(RunPhase::Finished, true);
        let at_end = Context {
            now: 2_100,
            ..cx(Some(&run), None)
        };
        let (steps, stands) = drive(at_end, world(Some(merged(true, 90.0)), &[]));
        // Five batches: the claim and the Jobs stopped side by side, what the run left with
        // EvalAI's status, what needs only the decision (the recordings' listing and heads too,
        // so the audit comes before the post), and the record, the pace and the place together
        // once EvalAI has the final word.
        let order: [&[&str]; 5] = [
            &["stop", "standing"],
            &["read", "evalai"],
            &["store", "recordings", "heads", "reports", "read-pace"],
            &["post"],
            &["record", "pace", "leave"],
        ];
        assert_eq!(kinds(&steps), order);
        // The track's pace as read before the post, with this run's duration first.
        let Step::RecordPace { durations } = find(&steps, "pace") else {
            unreachable!()
        };
        assert_eq!(durations, &[1_200, 600, 500]);
        let Step::Post {
            status,
            stdout,
            stderr,
        } = find(&steps, "post")
        else {
            unreachable!()
        };
        // Recordings that pass the audit leave nothing to say.
        assert_eq!(
            (*status, stdout.as_str(), stderr.as_str()),
            (SubmissionStatus::Finished, "summary", "")
        );
        let Step::WriteRecord {
            status,
            error,
            recordings,
            ..
        } = find(&steps, "record")
        else {
            unreachable!()
        };
        assert_eq!((*status, error.as_deref()), (RecordStatus::Finished, None));
        assert!(recordings.as_ref().is_some_and(Recordings::complete));
        assert_eq!(stands, Some((Settled::Ended(RecordStatus::Finished), None)));
    }

    #[test]
    fn another_execution_s_claim_leaves_the_submission_untouched_and_only_its_own_jobs_stop() {
        let run = run(RunPhase::Finished, true);
        let (steps, stands) = drive(cx(Some(&run), None), |step| match step {
            Step::ReadStanding => Answer::Standing(Some(Record {
                claimed_by: Some("exec-2".into()),
                ..Record::default()
            })),
            // Jobs from before the execution label are seen: they are exec-2's.
            Step::StopJobs { .. } => Answer::Stopped {
                unlabelled_left: true,
                failed: false,
            },
            step => plain(step),
        });
        assert_eq!(flat(&steps), ["stop", "standing"]);
        let (settled, why) = stands.unwrap();
        assert_eq!(settled, Settled::Superseded);
        assert!(why.unwrap().contains("exec-2"));
    }

    #[test]
    fn the_claim_holder_stops_the_jobs_from_before_the_label_before_it_reads_what_is_left() {
        let run = run(RunPhase::Finished, true);
        let mut world = world_of_finished();
        let (steps, stands) = drive(cx(Some(&run), None), |step| match step {
            Step::StopJobs { unlabelled: false } => Answer::Stopped {
                unlabelled_left: true,
                failed: false,
            },
            step => world(step),
        });
        let batches = kinds(&steps);
        assert_eq!(
            batches[..3],
            [
                &["stop", "standing"][..],
                &["stop-unlabelled"],
                &["read", "evalai"]
            ]
        );
        assert_eq!(stands.unwrap().0, Settled::Ended(RecordStatus::Finished));
    }

    #[test]
    fn a_stop_that_fails_fails_only_the_attempt_that_ends_the_run() {
        let run = run(RunPhase::Finished, true);
        let failed = |step: &Step| match step {
            Step::StopJobs { .. } => Some(Answer::Stopped {
                unlabelled_left: false,
                failed: true,
            }),
            _ => None,
        };
        // The run's end: the attempt fails with the stop's error, and the state machine tries
        // again; nothing is read, posted or written.
        let mut world = world_of_finished();
        let (steps, stands) = drive(cx(Some(&run), None), |step| {
            failed(step).unwrap_or_else(|| world(step))
        });
        assert_eq!(kinds(&steps), [&["stop", "standing"][..], &["again"]]);
        assert_eq!(stands, None);
        // A superseded execution still ends as it did.
        let (steps, stands) = drive(cx(Some(&run), None), |step| match step {
            Step::ReadStanding => Answer::Standing(Some(Record {
                claimed_by: Some("exec-2".into()),
                ..Record::default()
            })),
            step => failed(step).unwrap_or_else(|| plain(step)),
        });
        assert_eq!(flat(&steps), ["stop", "standing"]);
        assert_eq!(
            stands.map(|(settled, _)| settled),
            Some(Settled::Superseded)
        );
    }

    #[test]
    fn a_repeated_finalize_reports_what_stands_and_only_gives_the_place_back() {
        let run = run(RunPhase::Failed, true);
        let (steps, stands) = drive(cx(Some(&run), None), |step| match step {
            Step::ReadStanding => Answer::Standing(Some(Record {
                claimed_by: Some(EXECUTION.into()),
                status: Some(RecordStatus::Failed),
                error: Some("the agent crashed".into()),
                failed_by_platform: false,
            })),
            step => plain(step),
        });
        assert_eq!(flat(&steps), ["stop", "standing", "leave"]);
        let failed = Settled::Ended(RecordStatus::Failed);
        assert_eq!(stands, Some((failed, Some("the agent crashed".into()))));
    }

    #[test]
    fn results_unreadable_for_now_fail_the_attempt_unless_a_cancel_or_an_error_decides() {
        let run = run(RunPhase::Finished, true);
        let not_now = || Some(Read::NotNow("S3 throttled".into()));
        let (steps, _) = drive(cx(Some(&run), None), world(not_now(), &[]));
        assert_eq!(
            flat(&steps),
            ["stop", "standing", "read", "evalai", "again"]
        );
        // The participant's cancel does not need them, nor does a caught error.
        let (steps, stands) = drive(cx(Some(&run), None), world(not_now(), &[CANCEL_MARKER]));
        assert_eq!(
            flat(&steps),
            ["stop", "standing", "read", "evalai", "reports", "post", "record", "leave"]
        );
        assert_eq!(stands.unwrap().0, Settled::Ended(RecordStatus::Cancelled));
        let caught = "States.Timeout: the task timed out";
        let (steps, _) = drive(cx(Some(&run), Some(caught)), world(not_now(), &[]));
        let Step::WriteRecord { status, error, .. } = find(&steps, "record") else {
            unreachable!()
        };
        // Operators read the whole caught error; the participant read its plain words.
        assert_eq!(
            (*status, error.as_deref()),
            (RecordStatus::Failed, Some(caught))
        );
        let Step::Post { stderr, .. } = find(&steps, "post") else {
            unreachable!()
        };
        assert!(stderr.contains("evaluation service"), "{stderr}");
    }

    #[test]
    fn a_failed_run_shows_its_most_crashed_agent_s_log_and_counts_no_recordings() {
        let run = run(RunPhase::Failed, true);
        let markers = ["agent-2.crash0", "agent-2.crash1", "agent-1.crash0"];
        let (steps, stands) = drive(
            cx(Some(&run), None),
            world(Some(merged(false, 0.0)), &markers),
        );
        assert_eq!(
            kinds(&steps)[2..],
            [
                &["store", "tail", "reports"][..],
                &["post"],
                &["record", "leave"]
            ]
        );
        let key = "logs/agent/agent2/agent.log".to_string();
        let tail = Step::ReadAgentTail {
            key,
            bytes: TAIL_BYTES,
        };
        assert_eq!(find(&steps, "tail"), &tail);
        let Step::Post {
            status,
            stderr,
            stdout,
        } = find(&steps, "post")
        else {
            unreachable!()
        };
        assert_eq!(*status, SubmissionStatus::Failed);
        assert!(
            stderr.contains("agent 2's output:\nTraceback: boom"),
            "{stderr}"
        );
        // Pair 1 finished its routes: they are kept, and the participant is told which.
        assert!(
            stdout.contains("routes 0-1 (pair 1) are complete and kept"),
            "{stdout}"
        );
        assert_eq!(stands.unwrap().0, Settled::Ended(RecordStatus::Failed));
    }

    #[test]
    fn a_run_the_platform_s_reclaims_ended_is_recorded_and_settled_as_the_platform_s() {
        let mut run = run(RunPhase::Failed, true);
        run.monitor.failure = Some(FailureKind::PlatformReclaims);
        run.monitor.reason = Some("the platform took its pods away".into());
        // Each drained pod's agent wrote its crash marker on SIGTERM.
        let markers = ["agent-1.crash0", "agent-1.crash1"];
        let (steps, settled) = settle(
            cx(Some(&run), None),
            world(Some(merged(false, 0.0)), &markers),
        );
        let Step::Post { status, stderr, .. } = find(&steps, "post") else {
            unreachable!()
        };
        // EvalAI's `failed`: it does not count against the team's limits, and resumes. The
        // agent's log is not shown: nothing of it explains the platform's failure.
        assert_eq!(*status, SubmissionStatus::Failed);
        assert!(!flat(&steps).contains(&"tail"), "{steps:?}");
        assert!(!stderr.contains("output:"), "{stderr}");
        let Step::WriteRecord {
            failed_by_platform, ..
        } = find(&steps, "record")
        else {
            unreachable!()
        };
        assert!(*failed_by_platform);
        assert!(settled.unwrap().by_platform);
        // The participant's own failure is not.
        run.monitor.failure = Some(FailureKind::BackoffLimitExceeded);
        let (_, settled) = settle(cx(Some(&run), None), world(Some(merged(false, 0.0)), &[]));
        assert!(!settled.unwrap().by_platform);
        // A repeated Finalize reads it from the record.
        let (_, settled) = settle(cx(Some(&run), None), |step| match step {
            Step::ReadStanding => Answer::Standing(Some(Record {
                claimed_by: Some(EXECUTION.into()),
                status: Some(RecordStatus::Failed),
                error: Some("the platform took its pods away".into()),
                failed_by_platform: true,
            })),
            step => plain(step),
        });
        assert!(settled.unwrap().by_platform);
    }

    #[test]
    fn a_qualifier_pass_admits_the_team_before_the_post_and_a_fail_only_tells_it() {
        let qualifier = QualifierSettings {
            enabled: true,
            tracks: BTreeMap::from([("sensors".into(), "qualifier".into())]),
            thresholds: BTreeMap::from([("driving_score".into(), 50.0)]),
        };
        let run = run(RunPhase::Finished, true);
        let cx = Context {
            qualifier: Some(&qualifier),
            ..cx(Some(&run), None)
        };
        let (steps, _) = drive(cx, world(Some(merged(true, 90.0)), &[]));
        // Admitted in the batch before the post's.
        assert!(
            steps[2].contains(&Step::Admit(vec!["sensors".into()])),
            "{steps:?}"
        );
        assert_eq!(kinds_of(&steps[3])[0], "post");
        let Step::Post { stdout, .. } = find(&steps, "post") else {
            unreachable!()
        };
        assert!(stdout.starts_with("CONGRATULATIONS!"), "{stdout}");
        let (steps, _) = drive(cx, world(Some(merged(true, 40.0)), &[]));
        assert!(!flat(&steps).contains(&"admit"), "{steps:?}");
        let Step::Post { stdout, .. } = find(&steps, "post") else {
            unreachable!()
        };
        assert!(stdout.contains("Driving score: 40.0 / 50.0"), "{stdout}");
    }

    #[test]
    fn the_record_charges_the_pods_still_running_until_now_and_keeps_the_orchestration() {
        let mut run = run(RunPhase::Finished, true);
        // One pod on an unpriced kind running since the last round, 100 s ago.
        let pod = crate::capacity::cost::PodSeen {
            job: 0,
            started_at: 900,
            ended_at: None,
            gpus: 1,
            node: Some("n1".into()),
            disruption: None,
            succeeded: false,
        };
        let kind = crate::capacity::cost::NodeKind::unknown();
        let kinds = BTreeMap::from([("n1".to_string(), kind)]);
        let (written, failed) = (BTreeMap::new(), BTreeMap::new());
        run.monitor
            .usage
            .account(&[pod], &kinds, (&written, &failed), 1_000);
        let at_end = Context {
            now: 1_100,
            ..cx(Some(&run), None)
        };
        let (steps, _) = drive(at_end, world(Some(merged(true, 90.0)), &[]));
        let Step::WriteRecord { usage, .. } = find(&steps, "record") else {
            unreachable!()
        };
        let totals = usage.unwrap();
        assert_eq!(totals.gpu_seconds, 200);
        assert_eq!(totals.orchestration, Some(run.monitor.orchestration));
        // What every Job's logcopy stored, added up from the reports read before the record.
        let Step::ReadReports(keys) = find(&steps, "reports") else {
            unreachable!()
        };
        assert_eq!(keys.len() as u32, run.jobs);
        let stored = totals.stored.unwrap();
        assert_eq!(stored.log_bytes, 10 * u64::from(run.jobs));
        // Without a run there is nothing to charge.
        let (steps, _) = drive(cx(None, Some("States.TaskFailed")), world(None, &[]));
        assert!(matches!(
            find(&steps, "record"),
            Step::WriteRecord { usage: None, .. }
        ));
    }

    #[test]
    fn evalai_s_final_word_is_what_the_record_and_the_answer_say() {
        let run = run(RunPhase::Finished, true);
        // A cancel on EvalAI, seen before the post: nothing is written over it, the
        // recordings audited are not kept, no pace.
        let mut world = world_of_finished();
        let (steps, stands) = drive(cx(Some(&run), None), |step| match step {
            Step::ReadEvalAi => Answer::OnEvalAi(SubmissionStatus::Cancelled),
            step => world(step),
        });
        assert_eq!(kinds(&steps)[3], ["record", "leave"]);
        assert!(!flat(&steps).contains(&"post"), "{:?}", flat(&steps));
        let Step::WriteRecord {
            status, recordings, ..
        } = find(&steps, "record")
        else {
            unreachable!()
        };
        assert_eq!((*status, recordings), (RecordStatus::Cancelled, &None));
        let cancelled = Settled::Ended(RecordStatus::Cancelled);
        assert_eq!(stands, Some((cancelled, None)));
        // A cancel between the read and the write is EvalAI's answer to the post.
        let mut world = world_of_finished();
        let (steps, stands) = drive(cx(Some(&run), None), |step| match step {
            Step::Post { .. } => Answer::Posted(Posted::Cancelled),
            step => world(step),
        });
        assert_eq!(kinds(&steps)[4], ["record", "leave"]);
        assert_eq!(stands, Some((cancelled, None)));
        // An earlier attempt's final word stands, and is not posted again.
        let mut world = world_of_finished();
        let (steps, stands) = drive(cx(Some(&run), None), |step| match step {
            Step::ReadEvalAi => Answer::OnEvalAi(SubmissionStatus::Failed),
            step => world(step),
        });
        assert!(!flat(&steps).contains(&"post"), "{:?}", flat(&steps));
        assert_eq!(stands, Some((Settled::Ended(RecordStatus::Failed), None)));
    }

    /// A world whose run finished with every route scored.
    fn world_of_finished() -> impl FnMut(&Step) -> Answer {
        world(Some(merged(true, 90.0)), &[])
    }

    #[test]
    fn only_whole_recordings_pass_and_an_unlisted_folder_counts_nothing() {
        let run = run(RunPhase::Finished, false);
        let mut world = world(Some(merged(true, 90.0)), &[]);
        let (steps, _) = drive(cx(Some(&run), None), |step| match step {
            Step::ListRecordings => Answer::Listed(Some(vec![recording(0, 1000), recording(1, 1)])),
            step => world(step),
        });
        // Every needed recording's head is read, beside the listing.
        let Step::ReadHeads(keys) = find(&steps, "heads") else {
            unreachable!()
        };
        assert_eq!(keys, &[recording(0, 0).0, recording(1, 0).0]);
        let Step::WriteRecord { recordings, .. } = find(&steps, "record") else {
            unreachable!()
        };
        let audited = recordings.clone().unwrap();
        assert_eq!((audited.passed, audited.expected), (1, 2));
        let why =
            "RouteScenario_1_rep0: 1 bytes for 1.0 s of simulated time (at least 630 expected)";
        assert_eq!(audited.failures, [why]);
        // The participant reads it with the scores: audited before the post.
        let Step::Post { status, stderr, .. } = find(&steps, "post") else {
            unreachable!()
        };
        assert_eq!(*status, SubmissionStatus::Finished);
        assert!(stderr.contains("1 of the 2 scoring routes"), "{stderr}");
        assert!(stderr.contains(why), "{stderr}");
        // Not started: no pace to record.
        assert!(!flat(&steps).contains(&"pace"), "{steps:?}");
        let (steps, _) = drive(cx(Some(&run), None), |step| match step {
            Step::ListRecordings => Answer::Listed(None),
            step => world(step),
        });
        let Step::WriteRecord { recordings, .. } = find(&steps, "record") else {
            unreachable!()
        };
        assert_eq!(*recordings, None);
    }

    #[test]
    fn a_run_launched_before_the_recorder_is_not_audited() {
        let mut run = run(RunPhase::Finished, true);
        run.recorder = false;
        let (steps, _) = drive(cx(Some(&run), None), world(Some(merged(true, 90.0)), &[]));
        assert!(!flat(&steps).contains(&"recordings"), "{steps:?}");
        let Step::WriteRecord {
            status, recordings, ..
        } = find(&steps, "record")
        else {
            unreachable!()
        };
        assert_eq!((*status, recordings), (RecordStatus::Finished, &None));
        // Its state as that version left it: no field, so not audited.
        let mut state = serde_json::to_value(&run).unwrap();
        assert!(state.get("recorder").is_none(), "{state}");
        state["recorder"] = true.into();
        assert!(serde_json::from_value::<RunState>(state).unwrap().recorder);
    }

    #[test]
    fn without_a_run_it_did_not_start_and_an_answer_out_of_turn_settles_nothing() {
        let (steps, stands) = drive(cx(None, None), world(None, &[]));
        assert_eq!(
            flat(&steps),
            ["stop", "standing", "read", "evalai", "post", "record", "leave"]
        );
        let Step::Post { stderr, .. } = find(&steps, "post") else {
            unreachable!()
        };
        assert_eq!(stderr, "the evaluation did not start");
        assert_eq!(stands.unwrap().0, Settled::Ended(RecordStatus::Failed));
        let (steps, stands) = drive(cx(None, None), |_| Answer::Recorded(true));
        assert_eq!(flat(&steps), ["stop", "standing"]);
        assert_eq!(stands, None);
        // A batch answered short, or out of its order, settles nothing either.
        let run = run(RunPhase::Finished, true);
        let mut closing = Closing::begin(cx(Some(&run), None));
        let mut world = world(Some(merged(true, 90.0)), &[]);
        while closing.poll().len() < 2 {
            let answers = closing.poll().iter().map(&mut world).collect();
            closing.answer(answers);
        }
        let mut answers: Vec<Answer> = closing.poll().iter().map(&mut world).collect();
        answers.reverse();
        closing.answer(answers);
        assert!(closing.poll().is_empty());
        assert_eq!(closing.finish(), None);
    }
}
