//! The state machine's payloads: what each Task receives and returns (see
//! `statemachine/submission.asl.json` for where they sit in the state).
//!
//! No secret ever goes in here: payloads are visible in the execution history.

use serde::{Deserialize, Serialize};

/// Intake's input: the Pipe's message and the execution's name (who claims).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IntakeInput {
    /// The EventBridge Pipe's output, validated by Intake.
    pub message: serde_json::Value,
    /// `$$.Execution.Name`.
    pub execution: String,
}

/// What Intake decided (`$.intake`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IntakeOutput {
    /// The Choice after Intake branches on it.
    pub action: Action,
    /// Why, in words (skip and reject).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// The submission, once known (absent when skipped before the EvalAI read).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub submission: Option<SubmissionInfo>,
}

/// Intake's decision.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Action {
    /// Evaluate it.
    Run,
    /// Not ours to run (status, duplicate): end without touching anything.
    Skip,
    /// Refuse it with a message to the participant (not qualified, no image).
    Reject,
}

/// Everything later stages need to know about the submission.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SubmissionInfo {
    /// EvalAI challenge id.
    pub challenge_id: u64,
    /// EvalAI phase id.
    pub phase_id: u64,
    /// EvalAI submission id.
    pub submission_id: u64,
    /// Participant team id.
    pub team_id: u64,
    /// Participant team name (free text).
    pub team_name: String,
    /// `1.0` or `2.0`.
    pub leaderboard: String,
    /// Track codename.
    pub track: String,
    /// The participant's image.
    pub image: String,
    /// Routes of the track.
    pub routes: u32,
    /// Simulator-agent pairs.
    pub workers: u32,
    /// EvalAI said `resuming`.
    pub resuming: bool,
    /// The execution that claimed it.
    pub execution: String,
}

/// The run as Launch started it and the Monitor carries it along (`$.run`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunState {
    /// The Jobs, by name.
    pub jobs: Vec<String>,
    /// The workers' route subsets, by pair ID (1-based), for the merge.
    pub pairs: Vec<PairRoutes>,
    /// Evaluator repetitions (1.0: 5, 2.0: 1).
    pub repetitions: u32,
    /// When the Jobs were created (seconds since the Unix epoch).
    pub launched_at: u64,
    /// The Monitor's state between rounds.
    pub monitor: MonitorState,
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
    /// The next Wait, in seconds.
    pub wait_seconds: u64,
    /// Monitor rounds so far.
    pub rounds: u64,
    /// The partial results last sent to EvalAI (object ETags); unchanged means no update.
    #[serde(default)]
    pub fingerprint: Option<String>,
    /// Routes done and planned.
    #[serde(default)]
    pub progress: (u64, u64),
    /// Why it ended, for the participant (failed runs).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// Since when (epoch seconds) the cluster's API could not be reached; a round that
    /// reaches it clears this.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub unreachable_since: Option<u64>,
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
}
