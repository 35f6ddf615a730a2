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

use lb_domain::protocol::{self, agent_step, env, exit, partner_finished, AgentStep, Marker, Role};
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
    /// `RECORD_PATH`: `$LB_LOGS_DIR/agent/agent<ID>/recorder`.
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
            recorder: dir.join("recorder"),
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

/// The agent's state machine.
pub async fn evaluate(cfg: &AgentConfig, command: &[String]) -> Result<PairOutcome, PairError> {
    let mut signals = Signals::install().map_err(PairError::Runtime)?;
    become_subreaper();
    let p = &cfg.pair;
    let id = p.pair;
    let status = StatusDir::new(&p.status_dir);
    let (attempt, owed) = protocol::start_attempt(&pair::markers(&status), Role::Agent, id);
    for marker in owed {
        warn!(%marker, "writing a crash marker a killed attempt did not write");
        write_marker(&status, marker)?;
    }
    let crash = Marker::Crash {
        role: Role::Agent,
        pair: id,
        crash_id: attempt,
    };
    let view = pair::view(&status, id, attempt);
    if view.agent_done {
        info!(pair = id, "already done");
        return Ok(PairOutcome::Done);
    }

    // The pair's GPU, before anything of the participant's runs (crate::handoff).
    let visible = std::env::var(handoff::VISIBLE_DEVICES).ok();
    let handed = match handoff::hand_over(&p.handoff_dir, id, visible.as_deref()) {
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

    // Wait for this attempt's CARLA.
    let start_by = Instant::now() + p.start_wait;
    loop {
        match agent_step(&pair::view(&status, id, attempt), false) {
            AgentStep::Start => break,
            AgentStep::Cancel => {
                info!(pair = id, "cancelled before start");
                return Ok(PairOutcome::Cancelled);
            }
            AgentStep::SimulatorCrashed => {
                warn!(
                    pair = id,
                    attempt, "the simulator crashed before it was ready"
                );
                write_marker(&status, crash)?;
                return Ok(PairOutcome::Crashed);
            }
            AgentStep::Continue => {}
        }
        if Instant::now() >= start_by {
            warn!(pair = id, waited = ?p.start_wait, "no simulator start marker in time");
            write_marker(&status, crash)?;
            return Ok(PairOutcome::Crashed);
        }
        if signals.sleep(p.poll).await == Wake::Terminate {
            write_marker(&status, crash)?;
            return Ok(PairOutcome::Crashed);
        }
    }

    let paths = AgentPaths::of(cfg);
    for dir in [&paths.recorder, &p.agent_dir] {
        if let Err(e) = fs::create_dir_all(dir) {
            warn!(dir = %dir.display(), error = %e, "cannot create a directory for the evaluator");
        }
    }
    let resuming = resume(attempt, &paths.checkpoint);
    // CARLA's port, as its sidecar announced it before writing the start marker.
    let port = handoff::announced_port(&p.handoff_dir, id).unwrap_or(p.carla_port);
    let tm_port = port.saturating_add(p.tm_offset());
    let envs = [
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
    ];
    let mut child = match Supervised::spawn(command, &envs, &paths.log, true) {
        Ok(child) => child,
        // The participant's image has no such program: every new pod would fail the same way.
        Err(source) if image_cannot_run(&source) => {
            warn!(pair = id, error = %source, "the image cannot run the evaluator");
            write_marker(&status, crash)?;
            return Ok(PairOutcome::Unrunnable);
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
    // The pair's own GPU (its agent's, which its code sees anyway): what the simulator's log
    // says it rendered on can be checked against it.
    if let Some(uuid) = &handed {
        child.note(&format!(
            "agent {id} attempt {attempt}: the pair's GPU is {uuid}"
        ));
    }

    let mut terminated = false;
    let mut ended = None;
    loop {
        if let Some(exit) = child.try_exit() {
            info!(pair = id, %exit, "evaluator ended");
            child.note(&format!("evaluator ended ({exit})"));
            ended = Some(exit);
            break;
        }
        match agent_step(&pair::view(&status, id, attempt), true) {
            AgentStep::Cancel => {
                child.note("submission cancelled: stopping the evaluator");
                child.stop(p.stop_grace).await;
                return Ok(PairOutcome::Cancelled);
            }
            AgentStep::SimulatorCrashed => {
                warn!(pair = id, "the simulator crashed: stopping the evaluator");
                child.note("the simulator crashed: stopping the evaluator");
                break;
            }
            AgentStep::Start | AgentStep::Continue => {}
        }
        let idle = child.idle_for();
        if idle >= cfg.max_idle {
            warn!(pair = id, idle = ?idle, "the evaluator is silent: stopping it");
            child.note(&format!(
                "no output for {:?}: stopping the evaluator",
                cfg.max_idle
            ));
            break;
        }
        let tick = p
            .poll
            .min(cfg.max_idle.saturating_sub(idle))
            .max(p.poll / 10);
        if signals.sleep(tick).await == Wake::Terminate {
            info!(pair = id, "SIGTERM: stopping the evaluator");
            child.note("SIGTERM: stopping the evaluator");
            terminated = true;
            break;
        }
    }
    // Also when it exited by itself: whatever it left behind goes too.
    child.stop(p.stop_grace).await;
    // NB: on a cancel the simulator may stop CARLA first, and the evaluator then dies before
    // this loop sees the marker: that is a cancel, not a crash.
    if agent_step(&pair::view(&status, id, attempt), true) == AgentStep::Cancel {
        child.note("submission cancelled: the evaluator stopped");
        return Ok(PairOutcome::Cancelled);
    }

    let outcome = match judge(cfg, &paths.checkpoint) {
        Verdict::Finished => {
            child.note("results complete");
            write_marker(
                &status,
                Marker::Done {
                    role: Role::Agent,
                    pair: id,
                },
            )?;
            PairOutcome::Done
        }
        Verdict::Incomplete(why) => {
            warn!(pair = id, attempt, reason = %why, "results incomplete: crash");
            child.note(&format!("crash: {why}"));
            write_marker(&status, crash)?;
            match ended {
                Some(ChildExit::Code(code))
                    if exit::shell_cannot_run(code) && !has_progress(cfg, &paths.checkpoint) =>
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
    if terminated {
        return Ok(outcome);
    }

    // Let the simulator see our marker and end its side before we go.
    let end_by = Instant::now() + p.end_wait;
    while !partner_finished(&pair::view(&status, id, attempt), Role::Agent) {
        if Instant::now() >= end_by {
            warn!(pair = id, waited = ?p.end_wait, "the simulator wrote no marker in time");
            break;
        }
        if signals.sleep(p.poll).await == Wake::Terminate {
            break;
        }
    }
    Ok(outcome)
}
