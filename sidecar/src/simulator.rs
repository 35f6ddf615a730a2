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

use std::time::Instant;

use lb_domain::protocol::{self, partner_finished, simulator_step, Marker, Role, SimulatorStep};
use tracing::{info, warn};

use crate::config::{process_env, Env, PairConfig};
use crate::handoff;
use crate::pair::{self, port_open, write_marker, PairError, PairOutcome};
use crate::signals::{Signals, Wake};
use crate::status::StatusDir;
use crate::supervise::{become_subreaper, listened_by_another, Supervised};

/// Runs the subcommand with the configuration from the environment.
pub fn run(command: &[String]) -> Result<PairOutcome, PairError> {
    let cfg = PairConfig::read(&Env::new(&process_env))?;
    pair::runtime()?.block_on(simulate(&cfg, command))
}

/// The simulator's state machine.
pub async fn simulate(cfg: &PairConfig, command: &[String]) -> Result<PairOutcome, PairError> {
    let mut signals = Signals::install().map_err(PairError::Runtime)?;
    become_subreaper();
    let status = StatusDir::new(&cfg.status_dir);
    let id = cfg.pair;
    let (attempt, owed) = protocol::start_attempt(&pair::markers(&status), Role::Simulator, id);
    for marker in owed {
        warn!(%marker, "writing a crash marker a killed attempt did not write");
        write_marker(&status, marker)?;
    }
    let done = Marker::Done {
        role: Role::Simulator,
        pair: id,
    };
    let crash = Marker::Crash {
        role: Role::Simulator,
        pair: id,
        crash_id: attempt,
    };
    match simulator_step(&pair::view(&status, id, attempt)) {
        SimulatorStep::AgentDone => {
            info!(pair = id, "the agent is already done");
            write_marker(&status, done)?;
            return Ok(PairOutcome::Done);
        }
        SimulatorStep::Cancel => {
            info!(pair = id, "cancelled before start");
            return Ok(PairOutcome::Cancelled);
        }
        SimulatorStep::AgentCrashed | SimulatorStep::Continue => {}
    }

    let log = cfg.logs_dir.join(protocol::simulator_log(id));
    let gpu = if cfg.gpu_from_agent {
        let dirs = (cfg.handoff_dir.as_path(), cfg.gpu_pin_dir.as_path());
        match handoff::take_over(dirs, id, cfg.start_wait, cfg.poll, &mut signals).await {
            Ok(Some((uuid, index))) => {
                info!(pair = id, %uuid, index, "rendering on the agent's GPU");
                // The pair's own GPU only, by index: the log is the participant's to read.
                if let Ok(f) = crate::supervise::open_log(&log) {
                    let line =
                        format!("simulator {id} attempt {attempt}: rendering on GPU {index}");
                    crate::supervise::note(&f, &line);
                }
                Some(index)
            }
            Ok(None) => {
                info!(pair = id, "SIGTERM before the agent handed over its GPU");
                write_marker(&status, crash)?;
                return Ok(PairOutcome::Crashed);
            }
            Err(e) => {
                warn!(pair = id, error = %e, "no GPU to render on");
                if let Ok(f) = crate::supervise::open_log(&log) {
                    crate::supervise::note(&f, &format!("simulator {id} attempt {attempt}: {e}"));
                }
                write_marker(&status, crash)?;
                return Ok(PairOutcome::Crashed);
            }
        }
    } else {
        None
    };
    let (mut child, mut port) = start_carla(cfg, command, gpu, &log, attempt)?;
    let mut races = 0;
    let mut ready_by = Instant::now() + cfg.carla_ready;
    let mut ready = false;
    loop {
        if let Some(exit) = child.try_exit() {
            warn!(pair = id, %exit, ready, "CARLA exited");
            child.note(&format!("CARLA exited ({exit})"));
            child.stop(cfg.stop_grace).await;
            if !ready && races < handoff::PORT_RACES && handoff::port_taken(port, cfg.tm_offset()) {
                races += 1;
                warn!(
                    pair = id,
                    attempt,
                    port,
                    "another process took CARLA's port first: starting CARLA on another"
                );
                child.note(&format!(
                    "port {port} was taken before CARLA could bind it: starting CARLA on another"
                ));
                // NB: the old one's drop kills every descendant: it goes before the new one.
                drop(child);
                (child, port) = start_carla(cfg, command, gpu, &log, attempt)?;
                ready_by = Instant::now() + cfg.carla_ready;
                continue;
            }
            return crashed(cfg, &mut signals, &status, child, attempt).await;
        }
        if !ready {
            // NB: on a network pods share, the port may answer from another pod's CARLA.
            if port_open(port).await && !listened_by_another(port) {
                ready = true;
                info!(pair = id, attempt, "CARLA accepts connections");
                child.note("CARLA accepts connections");
                write_marker(
                    &status,
                    Marker::Start {
                        pair: id,
                        crash_id: attempt,
                    },
                )?;
            } else if Instant::now() >= ready_by {
                warn!(pair = id, waited = ?cfg.carla_ready, "CARLA did not open its port in time");
                child.note(&format!(
                    "CARLA did not accept connections within {:?}",
                    cfg.carla_ready
                ));
                return crashed(cfg, &mut signals, &status, child, attempt).await;
            }
        }
        match simulator_step(&pair::view(&status, id, attempt)) {
            SimulatorStep::Continue => {}
            SimulatorStep::AgentDone => {
                child.note("the agent is done: stopping CARLA");
                child.stop(cfg.stop_grace).await;
                write_marker(&status, done)?;
                return Ok(PairOutcome::Done);
            }
            SimulatorStep::Cancel => {
                child.note("submission cancelled: stopping CARLA");
                child.stop(cfg.stop_grace).await;
                return Ok(PairOutcome::Cancelled);
            }
            SimulatorStep::AgentCrashed => {
                child.note("the agent crashed: stopping CARLA");
                child.stop(cfg.stop_grace).await;
                write_marker(&status, crash)?;
                return Ok(PairOutcome::Crashed);
            }
        }
        if signals.sleep(cfg.poll).await == Wake::Terminate {
            // The whole pod is stopping (a drained node): CARLA stays until the agent has
            // stopped the evaluator (bounded), so that the evaluator never records the route
            // in progress as a simulation crash, which would make the next pod run the route
            // before it again too.
            info!(pair = id, "SIGTERM: CARLA stops once the evaluator has");
            child.note("SIGTERM: CARLA stops once the evaluator has");
            let until = Instant::now() + cfg.stop_grace + cfg.poll * 2;
            while Instant::now() < until
                && child.try_exit().is_none()
                && !partner_finished(&pair::view(&status, id, attempt), Role::Simulator)
            {
                tokio::time::sleep(cfg.poll).await;
            }
            child.stop(cfg.stop_grace).await;
            return match simulator_step(&pair::view(&status, id, attempt)) {
                SimulatorStep::AgentDone => {
                    write_marker(&status, done)?;
                    Ok(PairOutcome::Done)
                }
                SimulatorStep::Cancel => Ok(PairOutcome::Cancelled),
                SimulatorStep::AgentCrashed | SimulatorStep::Continue => {
                    write_marker(&status, crash)?;
                    Ok(PairOutcome::Crashed)
                }
            };
        }
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
        Some(index) => handoff::substitute_env(std::env::vars_os(), index),
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
