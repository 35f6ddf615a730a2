//! The in-Job marker protocol: marker names, CRASH_ID counting, pair and Job states, env names.
//!
//! The containers of a Job talk only through empty files in the shared `containers-status`
//! directory (mirrored to S3 `<submission_id>/containers-status/`). The names are the seeds'
//! and are a contract with the Monitor and Finalize states; everything that reads or writes
//! them goes through [`Marker`]. The decisions each container takes from the markers it sees
//! are the pure functions at the end of this module, so both sides agree by construction.

use std::collections::HashSet;
use std::fmt;

/// A pair's ID: 1-based and global across the submission's Jobs (worker `i` has ID `i + 1`).
pub type PairId = u32;

/// The cancel marker, written to S3 by Monitor and mirrored locally by logcopy.
pub const CANCEL_MARKER: &str = "simulation.cancel";

/// The status directory's name in the logs tree and under the submission's S3 prefix.
pub const STATUS_DIR: &str = "containers-status";
/// The agents' results directory's name in the logs tree and in S3.
pub const AGENT_DIR: &str = "agent";
/// The logs directory's name in the logs tree and in S3.
pub const LOGS_DIR: &str = "logs";
/// The CARLA recordings' directory in the logs tree and in S3: a folder per pair
/// (`recorder/pair<ID>`), which only that pair's simulator container mounts.
pub const RECORDER_DIR: &str = "recorder";
/// Where a simulator container mounts its pair's recordings folder: the path the evaluator
/// gives CARLA (`RECORD_PATH`), which the server, not the evaluator, writes into.
pub const SIMULATOR_RECORDER_MOUNT: &str = "/tmp/recorder";

/// The files the Monitor and Finalize derive from the workers' results, relative to the
/// submission's S3 prefix (and to `lb-sidecar merge`'s output directory): the merged results
/// file, then the three EvalAI files. Participant-side containers may not write them.
pub mod derived {
    /// The merged results file.
    pub const MERGED: &str = "agent_results.json";
    /// What EvalAI's `result` field was sent.
    pub const EVALAI_RESULTS: &str = "evalai/results.json";
    /// What EvalAI's `stdout` field was sent.
    pub const EVALAI_STDOUT: &str = "evalai/stdout.txt";
    /// What EvalAI's `metadata` field was sent (a copy of the merged file).
    pub const EVALAI_METADATA: &str = "evalai/metadata.json";
    /// The folder of the three EvalAI files.
    pub const EVALAI_DIR: &str = "evalai";
}

/// Environment variables of the in-Job contract (set by the Job templates).
pub mod env {
    /// Submission id (integer); every container.
    pub const SUBMISSION_ID: &str = "LB_SUBMISSION_ID";
    /// 0-based index of this Job among the submission's Jobs; every container.
    pub const JOB_INDEX: &str = "LB_JOB_INDEX";
    /// `1.0` or `2.0`; every container.
    pub const LEADERBOARD: &str = "LB_LEADERBOARD";
    /// Status markers directory (default `/tmp/status`).
    pub const STATUS_DIR: &str = "LB_STATUS_DIR";
    /// Agents' results directory (default `/tmp/agent`).
    pub const AGENT_DIR: &str = "LB_AGENT_DIR";
    /// The pair's logs directory (default `/tmp/logs`).
    pub const LOGS_DIR: &str = "LB_LOGS_DIR";
    /// The whole logs volume, for init and logcopy (default `/logs`).
    pub const LOGS_ROOT: &str = "LB_LOGS_ROOT";
    /// Where init puts the sidecar binary (default `/opt/lb`).
    pub const BIN_DIR: &str = "LB_BIN_DIR";
    /// This pair's ID; simulator and agent.
    pub const PAIR_ID: &str = "LB_PAIR_ID";
    /// CARLA's RPC port; simulator and agent.
    pub const CARLA_PORT: &str = "CARLA_PORT";
    /// The traffic manager's port (CARLA_PORT + 10); simulator and agent.
    pub const CARLA_TM_PORT: &str = "CARLA_TM_PORT";
    /// This pair's route subset `a-b`; simulator and agent.
    pub const ROUTES_SUBSET: &str = "ROUTES_SUBSET";
    /// Repetitions of each route; simulator and agent.
    pub const REPETITIONS: &str = "REPETITIONS";
    /// Bounded wait for the partner at the start, seconds (default 3600).
    pub const START_WAIT_SECONDS: &str = "LB_START_WAIT_SECONDS";
    /// Bounded wait for the partner at the end, seconds (default 600).
    pub const END_WAIT_SECONDS: &str = "LB_END_WAIT_SECONDS";
    /// Bounded wait for CARLA's port, seconds (default 300).
    pub const CARLA_READY_SECONDS: &str = "LB_CARLA_READY_SECONDS";
    /// Marker polling period, seconds (default 1).
    pub const POLL_SECONDS: &str = "LB_POLL_SECONDS";
    /// Agent idle watchdog, seconds without output (default 800).
    pub const MAX_IDLE_SECONDS: &str = "LB_MAX_IDLE_SECONDS";
    /// Grace between SIGTERM and SIGKILL when stopping a child, seconds (default 10).
    pub const STOP_GRACE_SECONDS: &str = "LB_STOP_GRACE_SECONDS";
    /// Comma list of this Job's pair IDs; logcopy and init.
    pub const PAIRS: &str = "LB_PAIRS";
    /// The submissions bucket; logcopy and init.
    pub const S3_BUCKET: &str = "LB_S3_BUCKET";
    /// Upload period, seconds (default 10); logcopy.
    pub const PERIOD_SECONDS: &str = "LB_PERIOD_SECONDS";
    /// Log objects each pair may store over the evaluation (default
    /// `uploads::LOG_OBJECTS_PER_PAIR`); logcopy.
    pub const MAX_LOG_OBJECTS: &str = "LB_MAX_LOG_OBJECTS";
    /// `1` when EvalAI said `resuming`: init removes the cancel marker.
    pub const PARTICIPANT_RESUME: &str = "LB_PARTICIPANT_RESUME";
    /// Official Leaderboard sources in the private-contents image; init.
    pub const SOURCE_LEADERBOARD: &str = "LB_SOURCE_LEADERBOARD";
    /// Official ScenarioRunner sources in the private-contents image; init.
    pub const SOURCE_SCENARIO_RUNNER: &str = "LB_SOURCE_SCENARIO_RUNNER";
    /// Official CARLA PythonAPI in the private-contents image; init.
    pub const SOURCE_CARLA_API: &str = "LB_SOURCE_CARLA_API";
    /// Leaderboard code volume (default `/workspace/leaderboard`).
    pub const LEADERBOARD_ROOT: &str = "LEADERBOARD_ROOT";
    /// ScenarioRunner code volume (default `/workspace/scenario_runner`).
    pub const SCENARIO_RUNNER_ROOT: &str = "SCENARIO_RUNNER_ROOT";
    /// CARLA PythonAPI code volume (default `/workspace/CARLA`).
    pub const CARLA_ROOT: &str = "CARLA_ROOT";
    /// Exported to the evaluator: `` or `1`.
    pub const RESUME: &str = "RESUME";
    /// Exported to the evaluator: its results (checkpoint) file.
    pub const CHECKPOINT_ENDPOINT: &str = "CHECKPOINT_ENDPOINT";
    /// Exported to the evaluator: its live results file.
    pub const DEBUG_CHECKPOINT_ENDPOINT: &str = "DEBUG_CHECKPOINT_ENDPOINT";
    /// Exported to the evaluator: the recorder directory, a path in the simulator's
    /// container ([`super::SIMULATOR_RECORDER_MOUNT`]).
    pub const RECORD_PATH: &str = "RECORD_PATH";
}

/// `partial_agent_results<ID>.json`: a pair's results file in the agent directory.
pub fn partial_results_name(pair: PairId) -> String {
    format!("partial_agent_results{pair}.json")
}

/// The pair of a results file's name, the inverse of [`partial_results_name`]: `None` for
/// any other name (temporaries, names without an ID, IDs of more than 4 digits).
pub fn pair_of_results_name(name: &str) -> Option<PairId> {
    let id = name
        .strip_prefix("partial_agent_results")?
        .strip_suffix(".json")?;
    if id.is_empty() || id.len() > 4 || !id.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    id.parse().ok()
}

/// The submission whose Monitor an S3 object key should wake, if the key is one: a worker's
/// results file (`<id>/agent/partial_agent_results<ID>.json`) or a status marker of the
/// protocol (`<id>/containers-status/<marker>`). Logs, other names in the status directory
/// and everything else wait for the next round.
///
/// Keys come from S3 events for the results buckets, written by logcopy (and so by whatever
/// the participant's container left in the shared directories): anything else is `None`.
pub fn wakes_submission(key: &str) -> Option<u64> {
    let (id, rest) = key.split_once('/')?;
    if id.is_empty() || id.len() > 20 || !id.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let submission: u64 = id.parse().ok()?;
    let wakes = if let Some(name) = rest
        .strip_prefix(AGENT_DIR)
        .and_then(|r| r.strip_prefix('/'))
    {
        pair_of_results_name(name).is_some()
    } else if let Some(name) = rest
        .strip_prefix(STATUS_DIR)
        .and_then(|r| r.strip_prefix('/'))
    {
        Marker::parse(name).is_some()
    } else {
        false
    };
    wakes.then_some(submission)
}

/// Whether the logcopy of the Job `job` running `pairs` uploads the file at `rel` (relative to
/// the logs volume): under `agent/` only these pairs' results files, under `containers-status/`
/// only the markers of these pairs and of this Job's logcopy (never the cancel marker: the
/// Monitor writes it), under `logs/` only these pairs' logs ([`log_kind`]), and nothing else. The volume is written by the
/// participant's code: another pair's results or markers, or files the protocol does not name,
/// would otherwise overwrite another pair's objects or wake the execution for nothing.
pub fn uploads(rel: &str, pairs: &[PairId], job: u32) -> bool {
    let (dir, name) = rel.split_once('/').unwrap_or(("", rel));
    match dir {
        AGENT_DIR => pair_of_results_name(name).is_some_and(|pair| pairs.contains(&pair)),
        STATUS_DIR => Marker::parse(name).is_some_and(|m| m.belongs_to_job(pairs, job)),
        LOGS_DIR | RECORDER_DIR => kept_as(rel, pairs).is_some(),
        _ => false,
    }
}

/// `recorder/pair<ID>`: a pair's recordings folder, relative to the logs volume and to the
/// submission's S3 prefix.
pub fn recorder_dir(pair: PairId) -> String {
    format!("{RECORDER_DIR}/pair{pair}")
}

/// The pair and route of a recording's path relative to the recordings directory
/// (`pair<ID>/RouteScenario_<n>[_rep<r>].log`): the name the evaluator gives CARLA for a
/// route; `None` for anything else (a name no route has is not the evaluation's).
pub fn recording_of(rel: &str) -> Option<(PairId, &str)> {
    let (dir, file) = rel.split_once('/')?;
    let pair: PairId = dir.strip_prefix("pair")?.parse().ok()?;
    if pair == 0 || dir != format!("pair{pair}") {
        return None;
    }
    let stem = file.strip_suffix(".log")?;
    let route = stem.strip_prefix("RouteScenario_")?;
    let (number, rep) = route.split_once("_rep").unwrap_or((route, "0"));
    let digits = |t: &str| !t.is_empty() && t.len() <= 12 && t.bytes().all(|b| b.is_ascii_digit());
    (digits(number) && digits(rep)).then_some((pair, stem))
}

/// What a file under `logs/` is, and so how long it is kept.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LogKind {
    /// A CARLA recording of a route (`recorder/pair<ID>/...`): kept as long as the
    /// leaderboard needs it.
    Recording,
    /// The evaluation's logs: CARLA's output, the evaluator's output and debug files.
    Log,
}

impl LogKind {
    /// The S3 object tag the buckets' lifecycle rules select by (`infra/app.yaml`).
    pub fn tag(self) -> &'static str {
        match self {
            LogKind::Recording => "retention=recording",
            LogKind::Log => "retention=log",
        }
    }
}

/// Whether a path relative to the logs directory is one of these pairs' logs:
/// `simulator/simulator<ID>.log` or anything under `agent/agent<ID>/` (the evaluator's
/// output, its debug checkpoint). Anything else under `logs/` is not the evaluation's and is
/// not uploaded. (The recordings are not under `logs/`: see [`RECORDER_DIR`].)
pub fn log_kind(rel: &str, pairs: &[PairId]) -> Option<LogKind> {
    pairs.iter().find_map(|&pair| {
        if rel == simulator_log(pair) {
            return Some(LogKind::Log);
        }
        let dir = agent_logs_dir(pair);
        let rest = rel.strip_prefix(dir.as_str())?.strip_prefix('/')?;
        (!rest.is_empty() && !rest.ends_with('/')).then_some(LogKind::Log)
    })
}

/// The kind of an uploaded file relative to the logs volume, for its retention tag: these
/// pairs' logs and recordings; `None` for the protocol's other files.
pub fn kept_as(rel: &str, pairs: &[PairId]) -> Option<LogKind> {
    let (dir, name) = rel.split_once('/')?;
    match dir {
        LOGS_DIR => log_kind(name, pairs),
        RECORDER_DIR => recording_of(name)
            .filter(|(pair, _)| pairs.contains(pair))
            .map(|_| LogKind::Recording),
        _ => None,
    }
}

/// `simulator/simulator<ID>.log`: CARLA's output, relative to the logs directory.
pub fn simulator_log(pair: PairId) -> String {
    format!("simulator/simulator{pair}.log")
}

/// `agent/agent<ID>`: the agent's logs directory, relative to the logs directory.
pub fn agent_logs_dir(pair: PairId) -> String {
    format!("agent/agent{pair}")
}

/// Whether a path relative to the logs directory is one of these pairs' logs that a new pod
/// must start from (so that appending continues them instead of overwriting them in S3).
///
/// Recordings are left out: each route writes its own, so nothing overwrites them, and they
/// are by far the largest files.
pub fn is_pair_log(rel: &str, pairs: &[PairId]) -> bool {
    pairs.iter().any(|&pair| {
        if rel == simulator_log(pair) {
            return true;
        }
        let dir = agent_logs_dir(pair);
        rel.strip_prefix(dir.as_str())
            .and_then(|rest| rest.strip_prefix('/'))
            .is_some_and(|rest| {
                !rest.is_empty() && rest != "recorder" && !rest.starts_with("recorder/")
            })
    })
}

/// The two containers of a pair.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Role {
    /// `simulator-<ID>`: the CARLA server.
    Simulator,
    /// `agent-<ID>`: the Leaderboard evaluator and the participant's agent.
    Agent,
}

impl Role {
    /// The marker prefix: `simulator` or `agent`.
    pub fn as_str(self) -> &'static str {
        match self {
            Role::Simulator => "simulator",
            Role::Agent => "agent",
        }
    }

    /// The other container of the pair.
    pub fn partner(self) -> Role {
        match self {
            Role::Simulator => Role::Agent,
            Role::Agent => Role::Simulator,
        }
    }
}

impl fmt::Display for Role {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A status marker: an empty file whose name is the message.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Marker {
    /// `simulator-<ID>.start<CRASH_ID>`: CARLA accepts connections in this attempt.
    Start {
        /// The pair.
        pair: PairId,
        /// The simulator's attempt.
        crash_id: u32,
    },
    /// `<role>-<ID>.done`: the container finished its part for good.
    Done {
        /// Which container.
        role: Role,
        /// The pair.
        pair: PairId,
    },
    /// `<role>-<ID>.crash<CRASH_ID>`: the container's attempt ended in failure.
    Crash {
        /// Which container.
        role: Role,
        /// The pair.
        pair: PairId,
        /// The attempt that crashed.
        crash_id: u32,
    },
    /// `simulation.cancel`: the participant cancelled the submission.
    Cancel,
    /// `logcopy-<J>.done`: Job `J`'s logcopy made its final upload.
    LogcopyDone {
        /// The Job index.
        job: u32,
    },
}

impl fmt::Display for Marker {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Marker::Start { pair, crash_id } => write!(f, "simulator-{pair}.start{crash_id}"),
            Marker::Done { role, pair } => write!(f, "{role}-{pair}.done"),
            Marker::Crash {
                role,
                pair,
                crash_id,
            } => write!(f, "{role}-{pair}.crash{crash_id}"),
            Marker::Cancel => f.write_str(CANCEL_MARKER),
            Marker::LogcopyDone { job } => write!(f, "logcopy-{job}.done"),
        }
    }
}

/// A canonical decimal (no sign, no leading zero): `01` is not the marker of pair 1.
fn canonical_number(text: &str) -> Option<u32> {
    if text.is_empty() || (text.len() > 1 && text.starts_with('0')) {
        return None;
    }
    if !text.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    text.parse().ok()
}

/// The highest attempt a marker may name. Every pod of a pair starts from a status directory
/// its init cleared, and each of its containers runs once (`restartPolicy: Never`): a pod's
/// attempts are 0, or 1 when a container catches up on its partner's crash
/// ([`start_attempt`]). The bound keeps every pair's marker names a small set (at most
/// [`MARKERS_PER_PAIR`]), so a pod writing new names cannot make an S3 object, an event, a
/// wake or a write for each.
pub const MAX_CRASH_ID: u32 = 15;

/// The most marker names one pair can have: a start and two crashes per attempt, two dones.
pub const MARKERS_PER_PAIR: u32 = 3 * (MAX_CRASH_ID + 1) + 2;

impl Marker {
    /// Parses a file name; anything that is not exactly a marker name (or names an attempt
    /// above [`MAX_CRASH_ID`]) is `None`.
    pub fn parse(name: &str) -> Option<Marker> {
        if name == CANCEL_MARKER {
            return Some(Marker::Cancel);
        }
        let (owner, event) = name.split_once('.')?;
        let (who, number) = owner.split_once('-')?;
        let number = canonical_number(number)?;
        let role = match who {
            "simulator" => Role::Simulator,
            "agent" => Role::Agent,
            "logcopy" => {
                return (event == "done").then_some(Marker::LogcopyDone { job: number });
            }
            _ => return None,
        };
        if event == "done" {
            return Some(Marker::Done { role, pair: number });
        }
        if let Some(id) = event.strip_prefix("crash") {
            let crash_id = canonical_number(id).filter(|&n| n <= MAX_CRASH_ID)?;
            return Some(Marker::Crash {
                role,
                pair: number,
                crash_id,
            });
        }
        if let (Role::Simulator, Some(id)) = (role, event.strip_prefix("start")) {
            let crash_id = canonical_number(id).filter(|&n| n <= MAX_CRASH_ID)?;
            return Some(Marker::Start {
                pair: number,
                crash_id,
            });
        }
        None
    }

    /// Whether the marker belongs to one of these pairs or to Job `job`'s logcopy: the stale
    /// markers a new pod of that Job removes. The cancel marker belongs to the submission.
    pub fn belongs_to_job(&self, pairs: &[PairId], job: u32) -> bool {
        match *self {
            Marker::Start { pair, .. } | Marker::Done { pair, .. } | Marker::Crash { pair, .. } => {
                pairs.contains(&pair)
            }
            Marker::LogcopyDone { job: j } => j == job,
            Marker::Cancel => false,
        }
    }
}

/// The markers present in a status directory (names that are not markers are ignored).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Markers(HashSet<Marker>);

impl Markers {
    /// Collects the markers among file names.
    pub fn from_names<'a>(names: impl IntoIterator<Item = &'a str>) -> Markers {
        Markers(names.into_iter().filter_map(Marker::parse).collect())
    }

    /// Whether a marker is present.
    pub fn contains(&self, marker: &Marker) -> bool {
        self.0.contains(marker)
    }

    /// The markers, in no particular order.
    pub fn iter(&self) -> impl Iterator<Item = &Marker> {
        self.0.iter()
    }

    /// Adds a marker.
    pub fn insert(&mut self, marker: Marker) {
        self.0.insert(marker);
    }

    /// How many crash markers a container has: its CRASH_ID for the next attempt.
    pub fn crash_count(&self, role: Role, pair: PairId) -> u32 {
        let n = self
            .0
            .iter()
            .filter(
                |m| matches!(m, Marker::Crash { role: r, pair: p, .. } if *r == role && *p == pair),
            )
            .count();
        u32::try_from(n).unwrap_or(u32::MAX)
    }

    /// What a container in attempt `crash_id` of `pair` needs to know.
    pub fn pair_view(&self, pair: PairId, crash_id: u32) -> PairView {
        let crashed = |role| {
            self.contains(&Marker::Crash {
                role,
                pair,
                crash_id,
            })
        };
        PairView {
            cancel: self.contains(&Marker::Cancel),
            simulator_started: self.contains(&Marker::Start { pair, crash_id }),
            simulator_done: self.contains(&Marker::Done {
                role: Role::Simulator,
                pair,
            }),
            simulator_crashed: crashed(Role::Simulator),
            agent_done: self.contains(&Marker::Done {
                role: Role::Agent,
                pair,
            }),
            agent_crashed: crashed(Role::Agent),
        }
    }

    /// Where a pair stands, for logcopy.
    pub fn pair_state(&self, pair: PairId) -> PairState {
        let done = |role| self.contains(&Marker::Done { role, pair });
        if done(Role::Simulator) && done(Role::Agent) {
            return PairState::Done;
        }
        let sim = self.crash_count(Role::Simulator, pair);
        let agent = self.crash_count(Role::Agent, pair);
        if sim > 0 && sim == agent {
            PairState::Crashed { attempts: sim }
        } else {
            PairState::Running
        }
    }
}

/// The attempt a container starts now, and the crash markers it owes first.
///
/// A container counts its own crash markers. One that was killed without writing its
/// marker (SIGKILL, node loss) while its partner wrote one for the same attempt would lag one
/// attempt behind for ever; it catches up by writing the missing markers before starting.
pub fn start_attempt(markers: &Markers, role: Role, pair: PairId) -> (u32, Vec<Marker>) {
    let mut attempt = markers.crash_count(role, pair);
    let mut owed = Vec::new();
    let crash = |role, crash_id| Marker::Crash {
        role,
        pair,
        crash_id,
    };
    while markers.contains(&crash(role.partner(), attempt))
        && !markers.contains(&crash(role, attempt))
    {
        owed.push(crash(role, attempt));
        attempt += 1;
    }
    (attempt, owed)
}

/// What one container of a pair sees of the pair in its current attempt.
///
/// Both containers of a pair count their own crash markers; they stay in step because a
/// container whose partner crashed writes its own crash marker for the same attempt.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PairView {
    /// The submission was cancelled.
    pub cancel: bool,
    /// `simulator-<ID>.start<CRASH_ID>`.
    pub simulator_started: bool,
    /// `simulator-<ID>.done`.
    pub simulator_done: bool,
    /// `simulator-<ID>.crash<CRASH_ID>`.
    pub simulator_crashed: bool,
    /// `agent-<ID>.done`.
    pub agent_done: bool,
    /// `agent-<ID>.crash<CRASH_ID>`.
    pub agent_crashed: bool,
}

/// The simulator's next move while CARLA runs (or starts).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SimulatorStep {
    /// Nothing new: keep CARLA running.
    Continue,
    /// The agent finished: stop CARLA, write `simulator-<ID>.done`, exit 0.
    AgentDone,
    /// Cancelled: stop CARLA, exit 0 without a marker.
    Cancel,
    /// The agent crashed: stop CARLA, write this attempt's crash marker, exit 1.
    AgentCrashed,
}

/// Decides the simulator's next move. The agent's done marker wins over a cancel, so a pair
/// that finished is counted as finished.
pub fn simulator_step(view: &PairView) -> SimulatorStep {
    if view.agent_done {
        SimulatorStep::AgentDone
    } else if view.cancel {
        SimulatorStep::Cancel
    } else if view.agent_crashed {
        SimulatorStep::AgentCrashed
    } else {
        SimulatorStep::Continue
    }
}

/// The agent's next move, while waiting for CARLA or while the evaluator runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AgentStep {
    /// Keep waiting (before the start marker) or keep running.
    Continue,
    /// The simulator's start marker is there (only while waiting).
    Start,
    /// Cancelled: stop the evaluator, exit 0 without a marker.
    Cancel,
    /// The simulator crashed in this attempt: stop the evaluator and judge its results.
    SimulatorCrashed,
}

/// Decides the agent's next move; `running` says whether the evaluator has been started.
pub fn agent_step(view: &PairView, running: bool) -> AgentStep {
    if view.cancel {
        AgentStep::Cancel
    } else if view.simulator_crashed {
        AgentStep::SimulatorCrashed
    } else if !running && view.simulator_started {
        AgentStep::Start
    } else {
        AgentStep::Continue
    }
}

/// Whether the partner has ended this attempt (done, crashed, or cancelled), so a container
/// that already wrote its own marker can exit.
pub fn partner_finished(view: &PairView, me: Role) -> bool {
    view.cancel
        || match me.partner() {
            Role::Simulator => view.simulator_done || view.simulator_crashed,
            Role::Agent => view.agent_done || view.agent_crashed,
        }
}

/// Where a pair stands, from logcopy's point of view.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PairState {
    /// Both done markers are there.
    Done,
    /// Its last attempt ended with both crash markers; `attempts` attempts crashed so far.
    Crashed {
        /// Crashed attempts.
        attempts: u32,
    },
    /// Anything else: running, starting, or restarting.
    Running,
}

/// Why a Job's logcopy finishes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JobEnd {
    /// The submission was cancelled.
    Cancelled,
    /// Every pair is done.
    AllDone,
    /// Every pair of this pod has ended its attempt and at least one crashed. Nothing
    /// restarts inside a pod (`restartPolicy: Never`): the pod ends, and the Job controller
    /// decides whether a new pod resumes the pairs.
    AttemptOver,
}

impl JobEnd {
    /// Whether the Job is over for good, so logcopy vouches for it with `logcopy-<J>.done`.
    /// After [`JobEnd::AttemptOver`] a new pod may follow, whose init removes the marker
    /// anyway, and the Monitor would take it for the end of the Job.
    pub fn closes_job(self) -> bool {
        matches!(self, JobEnd::Cancelled | JobEnd::AllDone)
    }
}

/// Decides whether this pod's part of a Job is over, from its status markers.
///
/// Every failed exit of a pair's container leaves one crash marker, and both containers of a
/// pair end the attempt together, so a pair whose last attempt has both crash markers has
/// nothing left running in this pod.
pub fn job_end(markers: &Markers, pairs: &[PairId]) -> Option<JobEnd> {
    if markers.contains(&Marker::Cancel) {
        return Some(JobEnd::Cancelled);
    }
    let states: Vec<PairState> = pairs.iter().map(|&p| markers.pair_state(p)).collect();
    if states.iter().all(|s| *s == PairState::Done) {
        return Some(JobEnd::AllDone);
    }
    let settled = states.iter().all(|s| *s != PairState::Running);
    settled.then_some(JobEnd::AttemptOver)
}

/// The exit codes of the sidecar's simulator and agent commands: the Jobs' Pod failure
/// policy ends a Job at once on [`exit::FAIL_JOB`], because the next pod would run the same
/// image with the same environment and fail the same way; every other failed exit counts
/// against the Job's `backoffLimit`.
pub mod exit {
    /// The attempt ended without finished results (crash marker written): a new pod
    /// resumes after the last completed route.
    pub const CRASHED: u8 = 1;
    /// The participant's image cannot run the Leaderboard evaluator at all: its shell or
    /// `python3` is missing or not executable (the shell's 127 and 126).
    pub const IMAGE_UNUSABLE: u8 = 3;
    /// The container's environment, which the Job template sets, is incomplete or malformed
    /// (`sysexits.h`'s `EX_CONFIG`).
    pub const MISCONFIGURED: u8 = 78;
    /// The codes of the Pod failure policy's `FailJob` rule, in increasing order (the API
    /// server requires it).
    pub const FAIL_JOB: [u8; 2] = [IMAGE_UNUSABLE, MISCONFIGURED];

    /// Whether the wrapped evaluator's exit code is the shell's "command not found" (127) or
    /// "found but not executable" (126).
    pub fn shell_cannot_run(code: i32) -> bool {
        matches!(code, 126 | 127)
    }

    /// What a Job failed by the `FailJob` rule tells the participant, by exit code.
    pub fn meaning(code: i32) -> Option<&'static str> {
        match u8::try_from(code).ok()? {
            IMAGE_UNUSABLE => Some(
                "your image cannot run the Leaderboard evaluator (`bash` or `python3` is missing or not executable in it); a retry would fail the same way, so none was made. Check that the image runs `bash -c 'python3 --version'`",
            ),
            MISCONFIGURED => Some(
                "the evaluation's own configuration is incomplete (a leaderboard setting, not your submission); please contact the organizers",
            ),
            _ => None,
        }
    }
}

/// Parses `LB_PAIRS`: a comma list of distinct positive pair IDs, at least one.
pub fn parse_pairs(text: &str) -> Result<Vec<PairId>, String> {
    let mut pairs = Vec::new();
    for part in text.split(',') {
        let part = part.trim();
        let id = canonical_number(part)
            .filter(|id| *id >= 1)
            .ok_or_else(|| format!("`{part}` is not a positive pair ID"))?;
        if pairs.contains(&id) {
            return Err(format!("pair ID `{id}` is listed twice"));
        }
        pairs.push(id);
    }
    Ok(pairs)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn results_files_and_markers_wake_their_submission_and_nothing_else_does() {
        for (key, wakes) in [
            ("42/agent/partial_agent_results1.json", Some(42)),
            ("42/agent/partial_agent_results12.json", Some(42)),
            ("7/containers-status/agent-1.done", Some(7)),
            ("7/containers-status/simulation.cancel", Some(7)),
            ("7/containers-status/logcopy-0.done", Some(7)),
            // Logs, temporaries, other folders and foreign keys keep their period.
            ("42/agent/partial_agent_results.json", None),
            ("42/agent/partial_agent_results1.json.tmp", None),
            ("42/agent/partial_agent_resultsX.json", None),
            ("42/agent/agent1/log.txt", None),
            ("42/logs/simulator/simulator1.log", None),
            ("42/containers-status/", None),
            ("42/containers-status/deep/x", None),
            // A file the protocol does not name, however often it changes.
            ("42/containers-status/flood.txt", None),
            ("42/containers-status/agent-1.don", None),
            ("42/evalai/results.json", None),
            ("abc/containers-status/x", None),
            ("/containers-status/x", None),
            ("99999999999999999999999/containers-status/x", None),
            ("containers-status/x", None),
            ("", None),
        ] {
            assert_eq!(wakes_submission(key), wakes, "{key}");
        }
    }

    #[test]
    fn logcopy_uploads_only_its_own_pairs_results_and_markers_and_the_logs() {
        let (pairs, job) = ([3, 4], 1);
        for (rel, up) in [
            ("agent/partial_agent_results3.json", true),
            ("agent/partial_agent_results4.json", true),
            ("containers-status/agent-3.done", true),
            ("containers-status/simulator-4.crash2", true),
            ("containers-status/simulator-4.start1", true),
            ("containers-status/logcopy-1.done", true),
            ("logs/simulator/simulator3.log", true),
            ("logs/agent/agent3/recorder/route0.log", true),
            ("logs/agent/agent4/agent.log", true),
            ("recorder/pair3/RouteScenario_7_rep0.log", true),
            ("recorder/pair4/RouteScenario_12.log", true),
            // Another pair's recordings, or names no route has.
            ("recorder/pair1/RouteScenario_0_rep0.log", false),
            ("recorder/pair3/fill.bin", false),
            ("recorder/pair3/RouteScenario_x_rep0.log", false),
            ("recorder/pair03/RouteScenario_7_rep0.log", false),
            ("recorder/pair3/deep/RouteScenario_7_rep0.log", false),
            ("recorder/RouteScenario_7_rep0.log", false),
            // Not the evaluation's logs, or another pair's.
            ("logs/fill.bin", false),
            ("logs/simulator/simulator1.log", false),
            ("logs/agent/agent1/agent.log", false),
            ("logs/agent/agent3", false),
            ("logs/other/agent3/x", false),
            // Attempts beyond any a pod can reach: a flood of new names.
            ("containers-status/simulator-4.start16", false),
            ("containers-status/agent-3.crash4294967295", false),
            ("containers-status/simulator-3.crash15", true),
            // Another pair's (another pod's) results and markers: never over its objects.
            ("agent/partial_agent_results1.json", false),
            ("containers-status/agent-1.done", false),
            ("containers-status/logcopy-0.done", false),
            // The Monitor's word, not the pod's.
            ("containers-status/simulation.cancel", false),
            // Names the protocol does not define.
            ("containers-status/flood.txt", false),
            ("agent/notes.txt", false),
            ("agent_results.json", false),
            ("evalai/results.json", false),
            ("logs", false),
            ("", false),
        ] {
            assert_eq!(uploads(rel, &pairs, job), up, "{rel}");
        }
    }

    #[test]
    fn recordings_are_kept_as_recordings_and_everything_else_under_logs_as_logs() {
        let pairs = [3];
        for (rel, kind) in [
            (
                "recorder/pair3/RouteScenario_7_rep0.log",
                Some(LogKind::Recording),
            ),
            ("logs/simulator/simulator3.log", Some(LogKind::Log)),
            // The agent's own folder is the participant's: what it writes there is a log.
            (
                "logs/agent/agent3/recorder/RouteScenario_7_rep0.log",
                Some(LogKind::Log),
            ),
            ("recorder/pair4/RouteScenario_7_rep0.log", None),
            ("agent/partial_agent_results3.json", None),
            ("containers-status/agent-3.done", None),
        ] {
            assert_eq!(kept_as(rel, &pairs), kind, "{rel}");
        }
    }

    fn markers(names: &[&str]) -> Markers {
        Markers::from_names(names.iter().copied())
    }

    #[test]
    fn marker_names_are_exactly_the_seeds_names_and_parse_back() {
        let cases = [
            (
                Marker::Start {
                    pair: 3,
                    crash_id: 0,
                },
                "simulator-3.start0",
            ),
            (
                Marker::Done {
                    role: Role::Simulator,
                    pair: 12,
                },
                "simulator-12.done",
            ),
            (
                Marker::Crash {
                    role: Role::Simulator,
                    pair: 1,
                    crash_id: 2,
                },
                "simulator-1.crash2",
            ),
            (
                Marker::Done {
                    role: Role::Agent,
                    pair: 4,
                },
                "agent-4.done",
            ),
            (
                Marker::Crash {
                    role: Role::Agent,
                    pair: 4,
                    crash_id: 10,
                },
                "agent-4.crash10",
            ),
            (Marker::Cancel, "simulation.cancel"),
            (Marker::LogcopyDone { job: 0 }, "logcopy-0.done"),
        ];
        for (marker, name) in cases {
            assert_eq!(marker.to_string(), name);
            assert_eq!(Marker::parse(name), Some(marker), "{name}");
        }
    }

    #[test]
    fn names_that_only_look_like_markers_are_not_markers() {
        for name in [
            "simulator-01.done",
            "simulator-1.crash01",
            "simulator--1.done",
            "simulator-1.done.tmp",
            "agent-1.start0",
            "agent-1.crash",
            "agent-.done",
            "logcopy-1.crash0",
            "simulation.cancel2",
            "partial_agent_results1.json",
            "simulator-99999999999.done",
            "",
        ] {
            assert_eq!(Marker::parse(name), None, "{name}");
        }
    }

    #[test]
    fn crash_id_counts_only_this_containers_crash_markers() {
        let m = markers(&[
            "simulator-1.crash0",
            "simulator-1.crash1",
            "agent-1.crash0",
            "simulator-2.crash0",
            "simulator-1.start0",
            "simulator-1.crash-x",
        ]);
        assert_eq!(m.crash_count(Role::Simulator, 1), 2);
        assert_eq!(m.crash_count(Role::Agent, 1), 1);
        assert_eq!(m.crash_count(Role::Agent, 2), 0);
        assert_eq!(m.crash_count(Role::Simulator, 3), 0);
    }

    #[test]
    fn a_container_killed_without_its_crash_marker_catches_up_with_its_partner() {
        let m = markers(&["agent-1.crash0", "simulator-1.crash0", "agent-1.crash1"]);
        assert_eq!(start_attempt(&m, Role::Agent, 1), (2, vec![]));
        assert_eq!(
            start_attempt(&m, Role::Simulator, 1),
            (
                2,
                vec![Marker::Crash {
                    role: Role::Simulator,
                    pair: 1,
                    crash_id: 1
                }]
            )
        );
        assert_eq!(
            start_attempt(&Markers::default(), Role::Simulator, 1),
            (0, vec![])
        );
    }

    #[test]
    fn a_pair_view_looks_at_the_current_attempt_only() {
        let m = markers(&["simulator-1.start0", "simulator-1.crash0", "agent-1.crash0"]);
        let old = m.pair_view(1, 0);
        assert!(old.simulator_started && old.simulator_crashed && old.agent_crashed);
        let new = m.pair_view(1, 1);
        assert_eq!(new, PairView::default());
        assert_eq!(agent_step(&new, false), AgentStep::Continue);
    }

    #[test]
    fn the_simulator_prefers_a_finished_agent_over_a_cancel() {
        let mut view = PairView {
            cancel: true,
            agent_done: true,
            ..PairView::default()
        };
        assert_eq!(simulator_step(&view), SimulatorStep::AgentDone);
        view.agent_done = false;
        view.agent_crashed = true;
        assert_eq!(simulator_step(&view), SimulatorStep::Cancel);
        view.cancel = false;
        assert_eq!(simulator_step(&view), SimulatorStep::AgentCrashed);
        assert_eq!(
            simulator_step(&PairView::default()),
            SimulatorStep::Continue
        );
    }

    #[test]
    fn the_agent_starts_on_the_start_marker_and_stops_on_crash_or_cancel() {
        let started = PairView {
            simulator_started: true,
            ..PairView::default()
        };
        assert_eq!(agent_step(&started, false), AgentStep::Start);
        assert_eq!(agent_step(&started, true), AgentStep::Continue);
        let crashed = PairView {
            simulator_crashed: true,
            ..started
        };
        assert_eq!(agent_step(&crashed, true), AgentStep::SimulatorCrashed);
        assert_eq!(agent_step(&crashed, false), AgentStep::SimulatorCrashed);
        let cancelled = PairView {
            cancel: true,
            ..crashed
        };
        assert_eq!(agent_step(&cancelled, true), AgentStep::Cancel);
    }

    #[test]
    fn a_container_waits_at_the_end_until_its_partner_has_a_marker() {
        let mut view = PairView {
            agent_done: true,
            ..PairView::default()
        };
        assert!(!partner_finished(&view, Role::Agent));
        assert!(partner_finished(&view, Role::Simulator));
        view.simulator_crashed = true;
        assert!(partner_finished(&view, Role::Agent));
        let cancelled = PairView {
            cancel: true,
            ..PairView::default()
        };
        assert!(partner_finished(&cancelled, Role::Agent));
    }

    #[test]
    fn a_job_ends_when_every_pair_is_done_or_on_cancel() {
        let pairs = [1, 2];
        let half = markers(&["simulator-1.done", "agent-1.done", "agent-2.done"]);
        assert_eq!(job_end(&half, &pairs), None);
        let all = markers(&[
            "simulator-1.done",
            "agent-1.done",
            "agent-2.done",
            "simulator-2.done",
            "simulator-3.crash0",
        ]);
        assert_eq!(job_end(&all, &pairs), Some(JobEnd::AllDone));
        assert!(JobEnd::AllDone.closes_job());
        let cancelled = markers(&["simulation.cancel"]);
        assert_eq!(job_end(&cancelled, &pairs), Some(JobEnd::Cancelled));
        assert!(JobEnd::Cancelled.closes_job());
    }

    #[test]
    fn a_pod_is_over_once_every_pair_ended_its_attempt_and_one_crashed() {
        let pairs = [1, 2];
        let mut m = markers(&["simulator-1.done", "agent-1.done", "simulator-2.crash0"]);
        assert_eq!(
            m.pair_state(2),
            PairState::Running,
            "the agent has not ended"
        );
        assert_eq!(job_end(&m, &pairs), None);
        m.insert(Marker::Crash {
            role: Role::Agent,
            pair: 2,
            crash_id: 0,
        });
        assert_eq!(job_end(&m, &pairs), Some(JobEnd::AttemptOver));
        assert!(!JobEnd::AttemptOver.closes_job(), "a new pod may follow");
        let running = markers(&["simulator-1.crash0", "agent-1.crash0"]);
        assert_eq!(job_end(&running, &[1, 2]), None, "pair 2 still runs");
    }

    #[test]
    fn only_exits_no_retry_can_change_fail_the_job_at_once() {
        assert!(exit::FAIL_JOB.windows(2).all(|w| w[0] < w[1]));
        assert!(!exit::FAIL_JOB.contains(&exit::CRASHED));
        assert!(!exit::FAIL_JOB.contains(&0));
        for code in exit::FAIL_JOB {
            assert!(exit::meaning(i32::from(code)).is_some(), "{code}");
        }
        assert_eq!(exit::meaning(1), None);
        assert_eq!(exit::meaning(137), None, "a SIGKILL (OOM) is retried");
        assert!(exit::shell_cannot_run(127) && exit::shell_cannot_run(126));
        assert!(!exit::shell_cannot_run(1));
    }

    #[test]
    fn stale_markers_of_a_job_are_its_pairs_and_its_logcopy_but_never_the_cancel() {
        let pairs = [5, 6];
        for (name, mine) in [
            ("simulator-5.start0", true),
            ("agent-6.crash3", true),
            ("simulator-6.done", true),
            ("logcopy-1.done", true),
            ("logcopy-0.done", false),
            ("agent-1.done", false),
            ("simulation.cancel", false),
        ] {
            let marker = Marker::parse(name).unwrap();
            assert_eq!(marker.belongs_to_job(&pairs, 1), mine, "{name}");
        }
    }

    #[test]
    fn pair_logs_are_the_simulator_log_and_the_agent_directory_without_recordings() {
        let pairs = [1, 2];
        for (rel, mine) in [
            ("simulator/simulator1.log", true),
            ("simulator/simulator10.log", false),
            ("agent/agent2/agent.log", true),
            ("agent/agent2/live_results.json", true),
            ("agent/agent2/recorder/RouteScenario_0_rep0.log", false),
            ("agent/agent2/recorder", false),
            ("agent/agent20/agent.log", false),
            ("agent/agent2", false),
            ("agent/agent3/agent.log", false),
        ] {
            assert_eq!(is_pair_log(rel, &pairs), mine, "{rel}");
        }
    }

    #[test]
    fn pairs_lists_are_positive_distinct_ids() {
        assert_eq!(parse_pairs("1,2,3,4"), Ok(vec![1, 2, 3, 4]));
        assert_eq!(parse_pairs(" 5 , 6"), Ok(vec![5, 6]));
        for bad in ["", "0", "1,1", "1,,2", "a", "-1", "01"] {
            assert!(parse_pairs(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn file_names_of_a_pair_follow_the_contract() {
        assert_eq!(partial_results_name(3), "partial_agent_results3.json");
        assert_eq!(simulator_log(3), "simulator/simulator3.log");
        assert_eq!(agent_logs_dir(3), "agent/agent3");
    }
}
