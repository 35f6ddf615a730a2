//! `lb-sidecar simulator -- CMD`: runs CARLA and plays the simulator's side of the protocol.
//!
//! Start CARLA in its own process group (output to `logs/simulator/simulator<ID>.log`); it
//! is ready when its port accepts connections and CARLA is what listens there (bounded by
//! `LB_CARLA_READY_SECONDS`; a port lost to another process moves it, `crate::handoff`); write
//! `simulator-<ID>.start<CRASH_ID>`; then agent done -> stop CARLA, `simulator-<ID>.done`,
//! exit 0; agent crashed -> stop, this attempt's crash marker, exit 1; CARLA died (or never
//! became ready) -> `simulator-<ID>.crash<CRASH_ID>`, wait (bounded) for the agent, exit 1;
//! cancel -> stop, exit 0. SIGTERM stops CARLA once the agent has ended its side (bounded) and
//! writes the marker the pair's state calls for.
//! With `LB_GPU_FROM_AGENT`, CARLA starts only once the agent handed over its GPU
//! (`crate::handoff`); no GPU in time is a crash of this attempt.

use std::path::PathBuf;
use std::time::Instant;

use lb_domain::job::protocol::{
    self, partner_finished, simulator_step, Marker, Role, SimulatorStep,
};
use tracing::{info, warn};

use crate::config::{process_env, Env, PairConfig};
use crate::handoff;
use crate::pair::{self, port_open, write_marker, PairError, PairOutcome};
use crate::signals::{Signals, Wake};
use crate::status::StatusDir;
use crate::supervise::{become_subreaper, listened_by_another, Supervised};

/// Runs the subcommand with the configuration from the environment.
pub fn run(command: &[String]) -> Result<PairOutcome, PairError> {
    let mut cfg = PairConfig::read(&Env::new(&process_env))?;
    // CARLA's variables that name the pair's GPU (`{gpu_index}`), filled in once it is known.
    cfg.gpu_templates = handoff::templated_env(std::env::vars_os());
    pair::runtime()?.block_on(simulate(&cfg, command))
}

/// The simulator's state machine: one phase after another, each returning the next, until
/// the pair's outcome.
pub async fn simulate(cfg: &PairConfig, command: &[String]) -> Result<PairOutcome, PairError> {
    let mut sim = match Simulator::begin(cfg)? {
        Ok(sim) => sim,
        Err(outcome) => return Ok(outcome),
    };
    let mut phase = Phase::TakeGpu;
    loop {
        phase = match phase {
            Phase::TakeGpu => sim.take_gpu().await?,
            Phase::Start(gpu) => Phase::Watch(sim.start(command, gpu)?),
            Phase::Watch(carla) => sim.watch(command, carla).await?,
            Phase::CarlaDied(child) => {
                Phase::Ended(crashed(cfg, &mut sim.signals, &sim.status, child, sim.attempt).await?)
            }
            Phase::Terminated(child) => sim.terminated(child).await?,
            Phase::Ended(outcome) => return Ok(outcome),
        };
    }
}

/// Where the simulator's attempt is.
enum Phase {
    /// With `LB_GPU_FROM_AGENT`, waiting for the agent's GPU.
    TakeGpu,
    /// Starting CARLA (on this GPU index, when one was handed over).
    Start(Option<u32>),
    /// CARLA runs: until it is ready, then until the agent ends its side.
    Watch(Carla),
    /// CARLA died or never became ready.
    CarlaDied(Supervised),
    /// SIGTERM: the pod is going.
    Terminated(Supervised),
    /// Nothing more to do.
    Ended(PairOutcome),
}

/// A running CARLA.
struct Carla {
    child: Supervised,
    port: u16,
    gpu: Option<u32>,
    /// Times its port was lost to another process before it bound it.
    races: u32,
    ready_by: Instant,
    ready: bool,
}

/// One attempt of the simulator's side of a pair.
struct Simulator<'a> {
    cfg: &'a PairConfig,
    signals: Signals,
    status: StatusDir,
    attempt: u32,
    log: PathBuf,
}

impl<'a> Simulator<'a> {
    /// Starts the attempt: the crash markers killed attempts owe; `Err(outcome)` when the
    /// pair has nothing left for it (the agent is done, or the submission was cancelled).
    fn begin(cfg: &'a PairConfig) -> Result<Result<Simulator<'a>, PairOutcome>, PairError> {
        let signals = Signals::install().map_err(PairError::Runtime)?;
        become_subreaper();
        let status = StatusDir::new(&cfg.status_dir);
        let id = cfg.pair;
        let (attempt, owed) = protocol::start_attempt(&pair::markers(&status), Role::Simulator, id);
        for marker in owed {
            warn!(%marker, "writing a crash marker a killed attempt did not write");
            write_marker(&status, marker)?;
        }
        let sim = Simulator {
            cfg,
            signals,
            status,
            attempt,
            log: cfg.logs_dir.join(protocol::simulator_log(id)),
        };
        match sim.step() {
            SimulatorStep::AgentDone => {
                info!(pair = id, "the agent is already done");
                write_marker(&sim.status, sim.done())?;
                Ok(Err(PairOutcome::Done))
            }
            SimulatorStep::Cancel => {
                info!(pair = id, "cancelled before start");
                Ok(Err(PairOutcome::Cancelled))
            }
            SimulatorStep::AgentCrashed | SimulatorStep::Continue => Ok(Ok(sim)),
        }
    }

    fn step(&self) -> SimulatorStep {
        simulator_step(&pair::view(&self.status, self.cfg.pair, self.attempt))
    }

    fn done(&self) -> Marker {
        Marker::Done {
            role: Role::Simulator,
            pair: self.cfg.pair,
        }
    }

    fn crash(&self) -> Marker {
        Marker::Crash {
            role: Role::Simulator,
            pair: self.cfg.pair,
            crash_id: self.attempt,
        }
    }

    /// A line in the pair's simulator log (the participant's to read).
    fn note(&self, line: &str) {
        if let Ok(f) = crate::supervise::open_log(&self.log) {
            crate::supervise::note(&f, line);
        }
    }

    /// With `LB_GPU_FROM_AGENT`, the agent's GPU (bounded): none in time is a crash.
    async fn take_gpu(&mut self) -> Result<Phase, PairError> {
        let (cfg, id, attempt) = (self.cfg, self.cfg.pair, self.attempt);
        if !cfg.gpu_from_agent {
            return Ok(Phase::Start(None));
        }
        let dirs = (cfg.handoff_dir.as_path(), cfg.gpu_pin_dir.as_path());
        match handoff::take_over(dirs, id, cfg.start_wait, cfg.poll, &mut self.signals).await {
            Ok(Some((uuid, index))) => {
                info!(pair = id, %uuid, index, "rendering on the agent's GPU");
                // The pair's own GPU only, by index: the log is the participant's to read.
                self.note(&format!(
                    "simulator {id} attempt {attempt}: rendering on GPU {index}"
                ));
                Ok(Phase::Start(Some(index)))
            }
            Ok(None) => {
                info!(pair = id, "SIGTERM before the agent handed over its GPU");
                write_marker(&self.status, self.crash())?;
                Ok(Phase::Ended(PairOutcome::Crashed))
            }
            Err(e) => {
                warn!(pair = id, error = %e, "no GPU to render on");
                self.note(&format!("simulator {id} attempt {attempt}: {e}"));
                write_marker(&self.status, self.crash())?;
                Ok(Phase::Ended(PairOutcome::Crashed))
            }
        }
    }

    /// CARLA started on a free port.
    fn start(&self, command: &[String], gpu: Option<u32>) -> Result<Carla, PairError> {
        let (child, port) = start_carla(self.cfg, command, gpu, &self.log, self.attempt)?;
        Ok(Carla {
            child,
            port,
            gpu,
            races: 0,
            ready_by: Instant::now() + self.cfg.carla_ready,
            ready: false,
        })
    }

    /// One look at CARLA and the pair, then the poll's wait: the next phase.
    async fn watch(&mut self, command: &[String], mut carla: Carla) -> Result<Phase, PairError> {
        let (cfg, id) = (self.cfg, self.cfg.pair);
        if let Some(exit) = carla.child.try_exit() {
            warn!(pair = id, %exit, ready = carla.ready, "CARLA exited");
            carla.child.note(&format!("CARLA exited ({exit})"));
            carla.child.stop(cfg.stop_grace).await;
            return self.lost_port(command, carla);
        }
        if !carla.ready {
            // NB: on a network pods share, the port may answer from another pod's CARLA.
            if port_open(carla.port).await && !listened_by_another(carla.port) {
                carla.ready = true;
                info!(
                    pair = id,
                    attempt = self.attempt,
                    "CARLA accepts connections"
                );
                carla.child.note("CARLA accepts connections");
                let start = Marker::Start {
                    pair: id,
                    crash_id: self.attempt,
                };
                write_marker(&self.status, start)?;
            } else if Instant::now() >= carla.ready_by {
                warn!(pair = id, waited = ?cfg.carla_ready, "CARLA did not open its port in time");
                carla.child.note(&format!(
                    "CARLA did not accept connections within {:?}",
                    cfg.carla_ready
                ));
                return Ok(Phase::CarlaDied(carla.child));
            }
        }
        let (why, marker, outcome) = match self.step() {
            SimulatorStep::Continue => {
                if self.signals.sleep(cfg.poll).await == Wake::Terminate {
                    return Ok(Phase::Terminated(carla.child));
                }
                return Ok(Phase::Watch(carla));
            }
            SimulatorStep::AgentDone => ("the agent is done", Some(self.done()), PairOutcome::Done),
            SimulatorStep::Cancel => ("submission cancelled", None, PairOutcome::Cancelled),
            SimulatorStep::AgentCrashed => (
                "the agent crashed",
                Some(self.crash()),
                PairOutcome::Crashed,
            ),
        };
        carla.child.note(&format!("{why}: stopping CARLA"));
        carla.child.stop(cfg.stop_grace).await;
        if let Some(marker) = marker {
            write_marker(&self.status, marker)?;
        }
        Ok(Phase::Ended(outcome))
    }

    /// CARLA exited: before it was ready, with its port held by another process, it lost a
    /// race for the port and starts again on another ([`handoff::PORT_RACES`] times at most);
    /// otherwise it died.
    fn lost_port(&self, command: &[String], carla: Carla) -> Result<Phase, PairError> {
        let (id, port) = (self.cfg.pair, carla.port);
        let lost = !carla.ready
            && carla.races < handoff::PORT_RACES
            && handoff::port_taken(port, self.cfg.tm_offset());
        if !lost {
            return Ok(Phase::CarlaDied(carla.child));
        }
        warn!(
            pair = id,
            attempt = self.attempt,
            port,
            "another process took CARLA's port first: starting CARLA on another"
        );
        carla.child.note(&format!(
            "port {port} was taken before CARLA could bind it: starting CARLA on another"
        ));
        // NB: the old one's drop kills every descendant: it goes before the new one.
        drop(carla.child);
        let mut next = self.start(command, carla.gpu)?;
        next.races = carla.races + 1;
        Ok(Phase::Watch(next))
    }

    /// The whole pod is stopping (a drained node): CARLA stays until the agent has stopped
    /// the evaluator (bounded), so that the evaluator never records the route in progress as
    /// a simulation crash, which would make the next pod run the route before it again too.
    async fn terminated(&self, mut child: Supervised) -> Result<Phase, PairError> {
        let (cfg, id) = (self.cfg, self.cfg.pair);
        info!(pair = id, "SIGTERM: CARLA stops once the evaluator has");
        child.note("SIGTERM: CARLA stops once the evaluator has");
        let until = Instant::now() + cfg.stop_grace + cfg.poll * 2;
        while Instant::now() < until
            && child.try_exit().is_none()
            && !partner_finished(&pair::view(&self.status, id, self.attempt), Role::Simulator)
        {
            tokio::time::sleep(cfg.poll).await;
        }
        child.stop(cfg.stop_grace).await;
        let outcome = match self.step() {
            SimulatorStep::AgentDone => {
                write_marker(&self.status, self.done())?;
                PairOutcome::Done
            }
            SimulatorStep::Cancel => PairOutcome::Cancelled,
            SimulatorStep::AgentCrashed | SimulatorStep::Continue => {
                write_marker(&self.status, self.crash())?;
                PairOutcome::Crashed
            }
        };
        Ok(Phase::Ended(outcome))
    }
}

/// Picks CARLA's port (`crate::handoff`), tells the agent, and starts CARLA on it.
fn start_carla(
    cfg: &PairConfig,
    command: &[String],
    gpu: Option<u32>,
    log: &std::path::Path,
    attempt: u32,
) -> Result<(Supervised, u16), PairError> {
    let id = cfg.pair;
    let port = handoff::pick_port(cfg.carla_port, cfg.tm_offset());
    if port != cfg.carla_port {
        warn!(
            pair = id,
            wanted = cfg.carla_port,
            port,
            "CARLA's port is taken: using another"
        );
    }
    if let Err(e) = handoff::announce_port(&cfg.handoff_dir, id, port) {
        warn!(pair = id, error = %e, "cannot tell the agent CARLA's port");
    }
    let command = handoff::substitute(command, gpu, port);
    let mut envs: Vec<(String, String)> = match gpu {
        Some(index) => handoff::substitute_env(&cfg.gpu_templates, index),
        None => Vec::new(),
    };
    envs.push((protocol::env::CARLA_PORT.to_owned(), port.to_string()));
    let envs: Vec<(&str, String)> = envs.iter().map(|(k, v)| (k.as_str(), v.clone())).collect();
    let child =
        Supervised::spawn(&command, &envs, log, true).map_err(|source| PairError::Spawn {
            program: command.first().cloned().unwrap_or_default(),
            source,
        })?;
    info!(pair = id, attempt, port, "simulator started");
    child.note(&format!(
        "simulator {id} attempt {attempt}: started, waiting for port {port}"
    ));
    Ok((child, port))
}

/// CARLA died or never became ready: crash marker, then wait (bounded) for the agent.
async fn crashed(
    cfg: &PairConfig,
    signals: &mut Signals,
    status: &StatusDir,
    mut child: Supervised,
    attempt: u32,
) -> Result<PairOutcome, PairError> {
    let id = cfg.pair;
    child.stop(cfg.stop_grace).await;
    write_marker(
        status,
        Marker::Crash {
            role: Role::Simulator,
            pair: id,
            crash_id: attempt,
        },
    )?;
    let wait_until = Instant::now() + cfg.end_wait;
    loop {
        let view = pair::view(status, id, attempt);
        if view.agent_done {
            // NB: the evaluator had finished every route; the pair is done after all.
            child.note("the agent is done after all");
            write_marker(
                status,
                Marker::Done {
                    role: Role::Simulator,
                    pair: id,
                },
            )?;
            return Ok(PairOutcome::Done);
        }
        if view.cancel {
            return Ok(PairOutcome::Cancelled);
        }
        if view.agent_crashed {
            return Ok(PairOutcome::Crashed);
        }
        if Instant::now() >= wait_until {
            warn!(pair = id, waited = ?cfg.end_wait, "the agent wrote no marker in time");
            return Ok(PairOutcome::Crashed);
        }
        if signals.sleep(cfg.poll).await == Wake::Terminate {
            return Ok(PairOutcome::Crashed);
        }
    }
}
