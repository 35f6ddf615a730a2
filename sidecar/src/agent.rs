//! `lb-sidecar agent -- CMD`: runs the Leaderboard evaluator and plays the agent's side.
//!
//! Wait (bounded by `LB_START_WAIT_SECONDS`) for `simulator-<ID>.start<CRASH_ID>`; start the
//! evaluator in its own process group with `RESUME` (`1` after an earlier crash or when
//! partial results exist), `CHECKPOINT_ENDPOINT`, `DEBUG_CHECKPOINT_ENDPOINT` and
//! `RECORD_PATH`, output to `logs/agent/agent<ID>/agent.log`; stop it when it is silent for
//! `LB_MAX_IDLE_SECONDS`, when the simulator crashed, on SIGTERM, or on cancel (exit 0); then
//! judge its results file (missing, unreadable, invalid or without a `global_record` ->
//! `agent-<ID>.crash<CRASH_ID>`, exit 1, or exit 3 when the image cannot run the evaluator at
//! all: not found, or the shell's 126/127 before any route ever finished; else
//! `agent-<ID>.done`, exit 0) and wait (bounded) for the simulator's marker.

use std::fs;
use std::io::{self, Read};
use std::path::{Path, PathBuf};
use std::time::Instant;

use lb_domain::job::protocol::{
    self, agent_step, env, exit, partner_finished, AgentStep, Marker, Role,
};
use lb_domain::results::{read_worker_file, ResultsError, WorkerFile, MAX_FILE_BYTES};
use tracing::{info, warn};

use crate::config::{process_env, AgentConfig, Env};
use crate::handoff;
use crate::pair::{self, write_marker, PairError, PairOutcome};
use crate::signals::{Signals, Wake};
use crate::status::StatusDir;
use crate::supervise::{become_subreaper, ChildExit, Supervised};

/// Runs the subcommand with the configuration from the environment.
pub fn run(command: &[String]) -> Result<PairOutcome, PairError> {
    let cfg = AgentConfig::read(&Env::new(&process_env))?;
    pair::runtime()?.block_on(evaluate(&cfg, command))
}

/// The files the evaluator is told about.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AgentPaths {
    /// `CHECKPOINT_ENDPOINT`: `$LB_AGENT_DIR/partial_agent_results<ID>.json`.
    pub checkpoint: PathBuf,
    /// `DEBUG_CHECKPOINT_ENDPOINT`: `$LB_LOGS_DIR/agent/agent<ID>/live_results.json`.
    pub live_results: PathBuf,
    /// `RECORD_PATH`: the pair's recordings folder as its simulator mounts it: the evaluator
    /// only passes the path to CARLA, which writes the files (`protocol::
    /// SIMULATOR_RECORDER_MOUNT`); this container does not mount it.
    pub recorder: PathBuf,
    /// The evaluator's output: `$LB_LOGS_DIR/agent/agent<ID>/agent.log`.
    pub log: PathBuf,
}

impl AgentPaths {
    /// The paths of a pair.
    pub fn of(cfg: &AgentConfig) -> AgentPaths {
        let p = &cfg.pair;
        let dir = p.logs_dir.join(protocol::agent_logs_dir(p.pair));
        AgentPaths {
            checkpoint: p.agent_dir.join(protocol::partial_results_name(p.pair)),
            live_results: dir.join("live_results.json"),
            recorder: PathBuf::from(protocol::SIMULATOR_RECORDER_MOUNT),
            log: dir.join("agent.log"),
        }
    }
}

/// What the results file says about the run.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Verdict {
    /// A valid file with a `global_record`: the subset is finished.
    Finished,
    /// Anything else, with the reason.
    Incomplete(String),
}

/// Reads the pair's results file as the protocol requires (`read_worker_file` with the
/// subset); `Err` when it cannot even be read.
fn read_results(cfg: &AgentConfig, path: &Path) -> io::Result<Result<WorkerFile, ResultsError>> {
    let bytes = read_limited(path)?;
    let source = path.display().to_string();
    Ok(read_worker_file(
        &source,
        bytes.as_deref(),
        cfg.pair.common.leaderboard,
        Some(cfg.pair.routes_subset),
    ))
}

/// Judges a results file as the protocol requires.
pub fn judge(cfg: &AgentConfig, path: &Path) -> Verdict {
    match read_results(cfg, path) {
        Err(e) => Verdict::Incomplete(format!("cannot read the results file: {e}")),
        Ok(Ok(WorkerFile::Present(file))) if file.has_global_record => Verdict::Finished,
        Ok(Ok(WorkerFile::Present(file))) => Verdict::Incomplete(format!(
            "the results file has no global record ({} of {} routes done)",
            file.progress.0, file.progress.1
        )),
        Ok(Ok(WorkerFile::Empty(reason))) => {
            Verdict::Incomplete(format!("the results file is {reason}"))
        }
        Ok(Err(e)) => {
            Verdict::Incomplete(format!("the results file is invalid: {} ({e})", e.name()))
        }
    }
}

/// Whether the results file holds any finished route (of this or an earlier pod): the image
/// did run the evaluator once.
fn has_progress(cfg: &AgentConfig, path: &Path) -> bool {
    matches!(read_results(cfg, path), Ok(Ok(WorkerFile::Present(file))) if file.progress.0 > 0)
}

fn read_limited(path: &Path) -> io::Result<Option<Vec<u8>>> {
    let file = match fs::File::open(path) {
        Ok(f) => f,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e),
    };
    let mut bytes = Vec::new();
    // One byte over the limit is enough for the parser to call the file too large.
    file.take(MAX_FILE_BYTES as u64 + 1)
        .read_to_end(&mut bytes)?;
    Ok(Some(bytes))
}

/// Whether a spawn error is the image's own (no such program, or not executable), which no
/// new pod can change.
fn image_cannot_run(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::NotFound | io::ErrorKind::PermissionDenied
    )
}

/// Whether a run resumes: after an earlier crash of this container, or over partial results.
pub fn resume(attempt: u32, checkpoint: &Path) -> bool {
    attempt > 0 || fs::metadata(checkpoint).is_ok_and(|m| m.len() > 0)
}

/// The agent's state machine: one phase after another, each returning the next, until the
/// pair's outcome.
pub async fn evaluate(cfg: &AgentConfig, command: &[String]) -> Result<PairOutcome, PairError> {
    let Some(mut agent) = Agent::begin(cfg)? else {
        return Ok(PairOutcome::Done);
    };
    let mut phase = Phase::WaitForCarla;
    loop {
        phase = match phase {
            Phase::WaitForCarla => agent.wait_for_carla().await?,
            Phase::Run => agent.run(command).await?,
            Phase::Judge(run) => agent.judge(run)?,
            Phase::WaitForPartner(outcome) => agent.wait_for_partner(outcome).await,
            Phase::Ended(outcome) => return Ok(outcome),
        };
    }
}

/// Where the agent's attempt is.
enum Phase {
    /// Waiting for this attempt's CARLA (its start marker).
    WaitForCarla,
    /// Starting the evaluator and watching it until it ends, is stopped or goes silent.
    Run,
    /// The evaluator stopped: its results decide the attempt.
    Judge(Ran),
    /// The attempt is decided: the simulator is given time to see it and end its side.
    WaitForPartner(PairOutcome),
    /// Nothing more to do.
    Ended(PairOutcome),
}

/// Why the watch of the evaluator ended.
enum Watched {
    /// It exited by itself.
    Exited(ChildExit),
    /// The submission was cancelled.
    Cancelled,
    /// The simulator crashed, or the evaluator went silent: it is stopped.
    Stopped,
    /// SIGTERM: the pod is going.
    Terminated,
}

/// How the evaluator's run ended, for the judgement.
struct Ran {
    child: Supervised,
    /// Its exit, when it ended by itself.
    ended: Option<ChildExit>,
    /// SIGTERM stopped it: the pod is going, nobody waits for the partner.
    terminated: bool,
}

/// One attempt of the agent's side of a pair.
struct Agent<'a> {
    cfg: &'a AgentConfig,
    signals: Signals,
    status: StatusDir,
    id: u32,
    attempt: u32,
    /// This attempt's crash marker.
    crash: Marker,
    /// The pair's GPU, handed to the simulator.
    gpu: Option<String>,
}

impl<'a> Agent<'a> {
    /// Starts the attempt: the crash markers killed attempts owe, then the GPU handed to the
    /// simulator before anything of the participant's runs (`crate::handoff`). `None` when
    /// the pair is already done.
    fn begin(cfg: &'a AgentConfig) -> Result<Option<Agent<'a>>, PairError> {
        let signals = Signals::install().map_err(PairError::Runtime)?;
        become_subreaper();
        let p = &cfg.pair;
        let id = p.pair;
        let status = StatusDir::new(&p.status_dir);
        let (attempt, owed) = protocol::start_attempt(&pair::markers(&status), Role::Agent, id);
        for marker in owed {
            warn!(%marker, "writing a crash marker a killed attempt did not write");
            write_marker(&status, marker)?;
        }
        if pair::view(&status, id, attempt).agent_done {
            info!(pair = id, "already done");
            return Ok(None);
        }
        let gpu = match handoff::hand_over(&p.handoff_dir, id, cfg.visible_devices.as_deref()) {
            Ok(Some(uuid)) => {
                info!(pair = id, %uuid, "GPU handed over to the simulator");
                Some(uuid)
            }
            Ok(None) => None,
            Err(e) => {
                warn!(pair = id, error = %e, "cannot hand the GPU over to the simulator");
                None
            }
        };
        let crash = Marker::Crash {
            role: Role::Agent,
            pair: id,
            crash_id: attempt,
        };
        Ok(Some(Agent {
            cfg,
            signals,
            status,
            id,
            attempt,
            crash,
            gpu,
        }))
    }

    fn step(&self, started: bool) -> AgentStep {
        agent_step(&pair::view(&self.status, self.id, self.attempt), started)
    }

    /// This attempt crashed: its marker, and the outcome.
    fn crashed(&self) -> Result<Phase, PairError> {
        write_marker(&self.status, self.crash)?;
        Ok(Phase::Ended(PairOutcome::Crashed))
    }

    /// Waits (bounded) for this attempt's CARLA.
    async fn wait_for_carla(&mut self) -> Result<Phase, PairError> {
        let (id, wait) = (self.id, self.cfg.pair.start_wait);
        let start_by = Instant::now() + wait;
        loop {
            match self.step(false) {
                AgentStep::Start => return Ok(Phase::Run),
                AgentStep::Cancel => {
                    info!(pair = id, "cancelled before start");
                    return Ok(Phase::Ended(PairOutcome::Cancelled));
                }
                AgentStep::SimulatorCrashed => {
                    warn!(
                        pair = id,
                        attempt = self.attempt,
                        "the simulator crashed before it was ready"
                    );
                    return self.crashed();
                }
                AgentStep::Continue => {}
            }
            if Instant::now() >= start_by {
                warn!(pair = id, waited = ?wait, "no simulator start marker in time");
                return self.crashed();
            }
            if self.signals.sleep(self.cfg.pair.poll).await == Wake::Terminate {
                return self.crashed();
            }
        }
    }

    /// Starts the evaluator on this attempt's CARLA and watches it.
    async fn run(&mut self, command: &[String]) -> Result<Phase, PairError> {
        let paths = AgentPaths::of(self.cfg);
        let mut child = match self.spawn(command, &paths)? {
            Ok(child) => child,
            Err(unrunnable) => return Ok(unrunnable),
        };
        let watched = self.watch(&mut child).await;
        // Also when it exited by itself: whatever it left behind goes too.
        child.stop(self.cfg.pair.stop_grace).await;
        let (ended, terminated) = match watched {
            Watched::Cancelled => return Ok(Phase::Ended(PairOutcome::Cancelled)),
            Watched::Exited(exit) => (Some(exit), false),
            Watched::Stopped => (None, false),
            Watched::Terminated => (None, true),
        };
        // NB: on a cancel the simulator may stop CARLA first, and the evaluator then dies
        // before the watch sees the marker: that is a cancel, not a crash.
        if self.step(true) == AgentStep::Cancel {
            child.note("submission cancelled: the evaluator stopped");
            return Ok(Phase::Ended(PairOutcome::Cancelled));
        }
        Ok(Phase::Judge(Ran {
            child,
            ended,
            terminated,
        }))
    }

    /// The evaluator started with CARLA's port and the resume flag (`Err(phase)`: the image
    /// cannot run it, which no new pod can change).
    fn spawn(
        &self,
        command: &[String],
        paths: &AgentPaths,
    ) -> Result<Result<Supervised, Phase>, PairError> {
        let (p, id, attempt) = (&self.cfg.pair, self.id, self.attempt);
        if let Err(e) = fs::create_dir_all(&p.agent_dir) {
            let dir = p.agent_dir.display();
            warn!(%dir, error = %e, "cannot create a directory for the evaluator");
        }
        let resuming = resume(attempt, &paths.checkpoint);
        // CARLA's port, as its sidecar announced it before writing the start marker.
        let port = handoff::announced_port(&p.handoff_dir, id).unwrap_or(p.carla_port);
        let envs = evaluator_env(paths, port, port.saturating_add(p.tm_offset()), resuming);
        let child = match Supervised::spawn(command, &envs, &paths.log, true) {
            Ok(child) => child,
            Err(source) if image_cannot_run(&source) => {
                warn!(pair = id, error = %source, "the image cannot run the evaluator");
                write_marker(&self.status, self.crash)?;
                return Ok(Err(Phase::Ended(PairOutcome::Unrunnable)));
            }
            Err(source) => {
                return Err(PairError::Spawn {
                    program: command.first().cloned().unwrap_or_default(),
                    source,
                })
            }
        };
        info!(pair = id, attempt, resume = resuming, "evaluator started");
        child.note(&format!(
            "agent {id} attempt {attempt}: evaluator started on routes {}{}",
            p.routes_subset,
            if resuming { " (resuming)" } else { "" }
        ));
        // The pair's own GPU (its agent's, which its code sees anyway): what the simulator's
        // log says it rendered on can be checked against it.
        if let Some(uuid) = &self.gpu {
            child.note(&format!(
                "agent {id} attempt {attempt}: the pair's GPU is {uuid}"
            ));
        }
        Ok(Ok(child))
    }

    /// Watches the evaluator until it exits, the submission is cancelled, the simulator
    /// crashes, it goes silent or SIGTERM comes.
    async fn watch(&mut self, child: &mut Supervised) -> Watched {
        let (id, max_idle, poll) = (self.id, self.cfg.max_idle, self.cfg.pair.poll);
        loop {
            if let Some(exit) = child.try_exit() {
                info!(pair = id, %exit, "evaluator ended");
                child.note(&format!("evaluator ended ({exit})"));
                return Watched::Exited(exit);
            }
            match self.step(true) {
                AgentStep::Cancel => {
                    child.note("submission cancelled: stopping the evaluator");
                    return Watched::Cancelled;
                }
                AgentStep::SimulatorCrashed => {
                    warn!(pair = id, "the simulator crashed: stopping the evaluator");
                    child.note("the simulator crashed: stopping the evaluator");
                    return Watched::Stopped;
                }
                AgentStep::Start | AgentStep::Continue => {}
            }
            let idle = child.idle_for();
            if idle >= max_idle {
                warn!(pair = id, idle = ?idle, "the evaluator is silent: stopping it");
                child.note(&format!(
                    "no output for {max_idle:?}: stopping the evaluator"
                ));
                return Watched::Stopped;
            }
            let tick = poll.min(max_idle.saturating_sub(idle)).max(poll / 10);
            if self.signals.sleep(tick).await == Wake::Terminate {
                info!(pair = id, "SIGTERM: stopping the evaluator");
                child.note("SIGTERM: stopping the evaluator");
                return Watched::Terminated;
            }
        }
    }

    /// The attempt's outcome from its results: complete is done, anything else a crash (and
    /// an image whose shell cannot run the evaluator, with no progress, is unrunnable).
    fn judge(&self, run: Ran) -> Result<Phase, PairError> {
        let (id, attempt, child) = (self.id, self.attempt, &run.child);
        let checkpoint = AgentPaths::of(self.cfg).checkpoint;
        let outcome = match judge(self.cfg, &checkpoint) {
            Verdict::Finished => {
                child.note("results complete");
                write_marker(
                    &self.status,
                    Marker::Done {
                        role: Role::Agent,
                        pair: id,
                    },
                )?;
                PairOutcome::Done
            }
            // Asked to stop (the pod deleted: a drain, a reclaim, the run's end), the attempt
            // did not crash, and its log says so: the next pod resumes it.
            Verdict::Incomplete(why) if run.terminated => {
                warn!(pair = id, attempt, reason = %why, "results incomplete: stopped");
                child.note(&format!(
                    "stopped: the pod was asked to stop before its routes were done ({why})"
                ));
                write_marker(&self.status, self.crash)?;
                PairOutcome::Crashed
            }
            Verdict::Incomplete(why) => {
                warn!(pair = id, attempt, reason = %why, "results incomplete: crash");
                child.note(&format!("crash: {why}"));
                write_marker(&self.status, self.crash)?;
                match run.ended {
                    Some(ChildExit::Code(code))
                        if exit::shell_cannot_run(code) && !has_progress(self.cfg, &checkpoint) =>
                    {
                        child.note(&format!(
                            "the image cannot run the evaluator (the shell's exit code {code}): no retry can help"
                        ));
                        PairOutcome::Unrunnable
                    }
                    _ => PairOutcome::Crashed,
                }
            }
        };
        Ok(if run.terminated {
            Phase::Ended(outcome)
        } else {
            Phase::WaitForPartner(outcome)
        })
    }

    /// Lets the simulator see our marker and end its side (bounded) before we go.
    async fn wait_for_partner(&mut self, outcome: PairOutcome) -> Phase {
        let (id, wait) = (self.id, self.cfg.pair.end_wait);
        let end_by = Instant::now() + wait;
        while !partner_finished(&pair::view(&self.status, id, self.attempt), Role::Agent) {
            if Instant::now() >= end_by {
                warn!(pair = id, waited = ?wait, "the simulator wrote no marker in time");
                break;
            }
            if self.signals.sleep(self.cfg.pair.poll).await == Wake::Terminate {
                break;
            }
        }
        Phase::Ended(outcome)
    }
}

/// The evaluator's variables: CARLA's and the traffic manager's ports, whether it resumes,
/// and where it writes its results and recordings.
fn evaluator_env(
    paths: &AgentPaths,
    port: u16,
    tm_port: u16,
    resuming: bool,
) -> [(&'static str, String); 6] {
    [
        (env::CARLA_PORT, port.to_string()),
        (env::CARLA_TM_PORT, tm_port.to_string()),
        (env::RESUME, if resuming { "1" } else { "" }.to_owned()),
        (
            env::CHECKPOINT_ENDPOINT,
            paths.checkpoint.display().to_string(),
        ),
        (
            env::DEBUG_CHECKPOINT_ENDPOINT,
            paths.live_results.display().to_string(),
        ),
        (env::RECORD_PATH, paths.recorder.display().to_string()),
    ]
}
