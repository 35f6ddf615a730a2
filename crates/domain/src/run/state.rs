//! A run's state as the state machine carries it between stages (`$.run`): what Launch
//! started, the Monitor's round-to-round state, its place in the queue. Pure data, so the
//! Monitor's round (`crate::run::round`) can decide on it without I/O.

use serde::{Deserialize, Serialize, Serializer};

/// The longest reason a payload carries; a longer one is cut with a note. Reasons can quote
/// untrusted text (a pod's message, EvalAI's answer) and stay in the state to the end.
pub const MAX_REASON_BYTES: usize = 4 * 1024;

/// `text` printable (no control characters, which JSON writes six bytes long) and cut to
/// `max` bytes with a note: what a payload may carry of a reason or an error message.
pub fn printable_bounded(text: &str, max: usize) -> String {
    let text = crate::job::logtail::printable(text);
    crate::job::logtail::cut_with_note(&text, max, || " [... cut]".into()).into_owned()
}

/// Serializes a reason printable and cut to [`MAX_REASON_BYTES`], whoever built it.
pub fn bounded_reason<S: Serializer>(reason: &Option<String>, s: S) -> Result<S::Ok, S::Error> {
    match reason {
        Some(text) => s.serialize_some(&printable_bounded(text, MAX_REASON_BYTES)),
        None => s.serialize_none(),
    }
}

/// The Job count, also from the list of names earlier versions carried (an execution started
/// before a deployment goes on after it).
fn job_count<'de, D: serde::Deserializer<'de>>(d: D) -> Result<u32, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Jobs {
        Count(u32),
        Names(Vec<serde::de::IgnoredAny>),
    }
    Ok(match Jobs::deserialize(d)? {
        Jobs::Count(n) => n,
        Jobs::Names(names) => names.len() as u32,
    })
}

/// The run as Launch started it and the Monitor carries it along (`$.run`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunState {
    /// How many Jobs the run has (their names are in the history's Launch logs and on the
    /// cluster under the submission's label; a list of 1,024 names would take 68 KB of the
    /// state's 256 KiB).
    #[serde(deserialize_with = "job_count")]
    pub jobs: u32,
    /// The workers' route subsets, by pair ID (1-based), for the merge.
    pub pairs: Vec<PairRoutes>,
    /// Evaluator repetitions (1.0: 5, 2.0: 1).
    pub repetitions: u32,
    /// When the Jobs were created (seconds since the Unix epoch).
    pub launched_at: u64,
    /// The Jobs' simulators record each route in their own folder, which only they can write
    /// (`protocol::RECORDER_DIR`): Finalize audits the recordings only then. A run whose Jobs
    /// an earlier version launched (recordings in the agents' logs) is not audited.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub recorder: bool,
    /// The Monitor's state between rounds.
    pub monitor: MonitorState,
    /// Its place in the leaderboard's queue (a run from before the queue was admitted).
    #[serde(default)]
    pub queue: QueueState,
}

/// A run's place in the queue (`crate::capacity::queue`): held by its team's cap until admitted,
/// then its pods wait for a GPU until the first pair starts.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct QueueState {
    /// When it arrived (epoch seconds): `max_queue_hours` counts from here.
    pub arrived_at: u64,
    /// Its Jobs may exist (they do once Launch ran after the admission).
    pub admitted: bool,
    /// What its participant last saw on EvalAI (`ahead`), and when (epoch seconds): the note
    /// is rewritten only when it changed, at most once per `QUEUE_NOTE_INTERVAL`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shown: Option<u32>,
    /// When it was shown.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shown_at: Option<u64>,
}

impl Default for QueueState {
    /// A run launched before admission existed: admitted, with no place to show.
    fn default() -> Self {
        QueueState {
            arrived_at: 0,
            admitted: true,
            shown: None,
            shown_at: None,
        }
    }
}

impl QueueState {
    /// A submission arriving now (epoch seconds), not admitted yet.
    pub fn arriving(now: u64) -> Self {
        QueueState {
            arrived_at: now,
            admitted: false,
            ..QueueState::default()
        }
    }
}

/// One worker's routes.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PairRoutes {
    /// Pair ID (1-based, global).
    pub id: u32,
    /// `a-b`.
    pub routes: String,
}

/// Where the run stands (the Choice after the Monitor reads `state`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MonitorState {
    /// `running`, or how it ended: `finished`, `failed`, `cancelled`.
    pub state: RunPhase,
    /// The next wait's timeout (the safety net), in seconds: a change wakes it earlier.
    pub wait_seconds: u64,
    /// A pause before that wait (EvalAI was just updated), in seconds; 0 for none.
    #[serde(default)]
    pub hold_seconds: u64,
    /// The wake count this round read before looking at S3: the next wait stores its token
    /// only while the count is still this (`lb_aws::wake`).
    #[serde(default)]
    pub seen: u64,
    /// The wake count could not be read: poll after `wait_seconds` instead of waiting.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub poll: bool,
    /// When the wake item may go (DynamoDB TTL, epoch seconds).
    #[serde(default)]
    pub expires_at: u64,
    /// When EvalAI last got a partial update (epoch seconds).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub updated_at: Option<u64>,
    /// When the status on EvalAI was last read (epoch seconds).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub status_read_at: Option<u64>,
    /// Monitor rounds so far.
    pub rounds: u64,
    /// The partial results last read or sent (object ETags); unchanged means nothing to read.
    #[serde(default)]
    pub fingerprint: Option<String>,
    /// The digest of the merged records last sent to EvalAI; the same records again (however
    /// their files' bytes changed) send nothing.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub posted: Option<String>,
    /// The participant image's digest (`sha256:...`) the first pod ran: every pod after it
    /// must run the same, whatever the tag points to since.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image: Option<String>,
    /// Routes done and planned.
    #[serde(default)]
    pub progress: (u64, u64),
    /// Why it ended, for the participant (failed runs).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        serialize_with = "bounded_reason"
    )]
    pub reason: Option<String>,
    /// The cluster's verdict when it failed the run: Finalize tells the platform's own
    /// failures from the participant's by it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub failure: Option<crate::cluster::view::FailureKind>,
    /// The Jobs whose pair the platform's reclaims alone ended (by index): so they stay once
    /// the deadline that ended them has failed their last pod.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub ended_by_platform: Vec<u32>,
    /// Since when (epoch seconds) the cluster's API could not be reached; a round that
    /// reaches it clears this.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub unreachable_since: Option<u64>,
    /// When the first pair started (epoch seconds): EvalAI was told `running` then, and the
    /// record's `start_time` is that moment. Unset while the Jobs wait for capacity (`queued`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub started_at: Option<u64>,
    /// This execution's history so far, an upper bound in events (`crate::run::history`).
    #[serde(default)]
    pub events: u64,
    /// The execution `events` counts for; a round in another one (a continuation's first)
    /// starts the count again.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub execution: Option<String>,
    /// Continuations so far: the next is named `<lineage>-c<generation + 1>`.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub generation: u32,
    /// The execution the run continues as (`continued`): `ContinueAsNew` starts it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub continue_as: Option<String>,
    /// The queue entry still names an earlier execution of this run: the reaper's pass reads
    /// it, so each round tries to name this one until it did.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub handover: bool,
    /// The GPUs its pods held so far (`crate::capacity::cost`).
    #[serde(
        default,
        skip_serializing_if = "crate::capacity::cost::Ledger::is_empty"
    )]
    pub usage: crate::capacity::cost::Ledger,
    /// What the orchestration did for it so far (every stage since its Intake).
    #[serde(default)]
    pub orchestration: crate::capacity::cost::Orchestration,
}

impl MonitorState {
    /// Where the state machine goes after the task that left this state.
    pub fn after(&self) -> crate::capacity::cost::After {
        use crate::capacity::cost::After;
        match self.state {
            RunPhase::Running => After::Wait {
                poll: self.poll,
                hold: self.hold_seconds > 0,
            },
            RunPhase::Admitted => After::Launch,
            RunPhase::Continued => After::Continue,
            _ => After::Finalize,
        }
    }
}

fn is_zero(n: &u32) -> bool {
    *n == 0
}

impl MonitorState {
    /// A run's first state: `wait_seconds` until the first round, the wake item kept until
    /// `expires_at`, `total` routes to run, counted in `execution`'s history from `events`.
    pub fn starting(
        wait_seconds: u64,
        expires_at: u64,
        total: u64,
        execution: &str,
        events: u64,
    ) -> MonitorState {
        MonitorState {
            state: RunPhase::Running,
            wait_seconds,
            hold_seconds: 0,
            seen: 0,
            poll: false,
            expires_at,
            updated_at: None,
            status_read_at: None,
            rounds: 0,
            fingerprint: None,
            posted: None,
            image: None,
            progress: (0, total),
            reason: None,
            failure: None,
            ended_by_platform: Vec::new(),
            unreachable_since: None,
            started_at: None,
            events,
            execution: Some(execution.to_owned()),
            generation: 0,
            continue_as: None,
            handover: false,
            usage: crate::capacity::cost::Ledger::default(),
            orchestration: crate::capacity::cost::Orchestration::default(),
        }
    }
}

/// The run's phase.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RunPhase {
    /// Jobs running: wait and look again.
    Running,
    /// Every pair done.
    Finished,
    /// Hopeless or out of retries.
    Failed,
    /// The participant cancelled.
    Cancelled,
    /// Held by its team's cap until now: Launch creates its Jobs next.
    Admitted,
    /// This execution's history is near its budget: the run goes on in the execution
    /// `continue_as` names, started with this state.
    Continued,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_reason_is_cut_to_its_bound_whoever_built_it() {
        let mut monitor = MonitorState {
            state: RunPhase::Failed,
            reason: Some("é".repeat(100_000)),
            failure: None,
            ended_by_platform: Vec::new(),
            ..MonitorState::starting(0, 0, 1, "exec-1", 0)
        };
        let text = serde_json::to_value(&monitor).unwrap()["reason"]
            .as_str()
            .unwrap()
            .to_owned();
        assert!(text.len() <= MAX_REASON_BYTES, "{}", text.len());
        assert!(text.ends_with(" [... cut]"));
        monitor.reason = Some("a \u{1b}[31mred\u{1} line".into());
        let text = serde_json::to_value(&monitor).unwrap()["reason"].clone();
        assert_eq!(text, "a red line");
        monitor.reason = Some("short".into());
        let back: MonitorState =
            serde_json::from_value(serde_json::to_value(&monitor).unwrap()).unwrap();
        assert_eq!(back, monitor);
    }

    #[test]
    fn the_job_count_reads_the_names_earlier_versions_carried() {
        let run = serde_json::json!({
            "jobs": ["lb-1-a-0", "lb-1-a-1"], "pairs": [], "repetitions": 1, "launched_at": 0,
            "monitor": {"state": "running", "wait_seconds": 60, "rounds": 0}
        });
        let run: RunState = serde_json::from_value(run).unwrap();
        assert_eq!(run.jobs, 2);
        assert_eq!(serde_json::to_value(&run).unwrap()["jobs"], 2);
    }
}
