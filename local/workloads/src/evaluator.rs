//! The fake Leaderboard evaluator: connects to CARLA, runs its routes in order and keeps the
//! checkpoint as `leaderboard_evaluator.py` does, failing on request (see [`crate::faults`]).
//!
//! What the real one does and the fake copies: it writes the checkpoint at start, when the
//! agent is first set up and after every route; a simulator that goes away ends the run with
//! a `Failed - Simulation crashed` record, entry status `Crashed` and exit status 255; a
//! finished run gets its global record and exits 0; `--resume` continues where the file says,
//! re-running crashed routes.

use std::io::Write as _;
use std::path::Path;
use std::time::{Duration, Instant};

use lb_domain::results::{EntryStatus, Leaderboard};
use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};
use tokio::net::TcpStream;

use crate::args::EvaluatorConfig;
use crate::faults::{spawn_child, OnceDir};
use crate::records::{self, Checkpoint, RecordsError, RouteConfig, Template};
use crate::signals::{Signals, Stop};

/// How long a call to CARLA's recorder may take.
const RECORDER_CALL: Duration = Duration::from_secs(10);

/// How a run ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Exit {
    /// Every route ran and the global record is written: exit 0.
    Finished,
    /// The simulator went away: `sys.exit(-1)`, exit 255.
    SimulationCrashed,
    /// An uncaught Python exception (traceback on stderr): exit 1.
    Traceback,
    /// The fake's own settings were unusable: exit 2, like an argparse error.
    Usage,
    /// A stop signal arrived: the shell's 128 + signal.
    Stopped(Stop),
}

impl Exit {
    /// The process exit code.
    pub fn code(self) -> u8 {
        match self {
            Exit::Finished => 0,
            Exit::SimulationCrashed => 255,
            Exit::Traceback => 1,
            Exit::Usage => 2,
            Exit::Stopped(stop) => stop.exit_code(),
        }
    }
}

/// How often a running route prints progress, so idle watchdogs see life in long routes.
const PROGRESS_EVERY: Duration = Duration::from_secs(1);

/// Simulated frames per second: the Leaderboard runs CARLA synchronously at 20 Hz.
const SIMULATED_HZ: f64 = 20.0;
/// How long one connection attempt to CARLA may take.
const CONNECT_ATTEMPT: Duration = Duration::from_secs(1);

fn say(line: &str) {
    // NB: `python -u` writes every line at once; a vanished reader must not kill us.
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{line}");
    let _ = out.flush();
}

fn say_err(text: &str) {
    let mut err = std::io::stderr().lock();
    let _ = write!(err, "{text}");
    let _ = err.flush();
}

fn bold(text: &str) -> String {
    format!("\x1b[1m{text}\x1b[0m")
}

/// Runs the evaluator to its end.
pub async fn run(cfg: EvaluatorConfig) -> Exit {
    let mut signals = match Signals::new() {
        Ok(s) => s,
        Err(error) => {
            say_err(&format!("fake-evaluator: cannot handle signals: {error}\n"));
            return Exit::Traceback;
        }
    };
    let lb = cfg.args.leaderboard;
    let template = match &cfg.records {
        Some(path) => Template::from_file(path, lb),
        None => Template::builtin(lb),
    };
    let Ok(template) = template.map_err(|error| {
        say_err(&format!(
            "fake-evaluator: error: FAKE_EVALUATOR_RECORDS: {error}\n"
        ));
    }) else {
        return Exit::Usage;
    };
    let plan = records::plan(&cfg.args.routes_subset.routes, cfg.args.repetitions, lb);
    tracing::info!(
        leaderboard = %lb,
        port = cfg.args.port,
        subset = %cfg.args.routes_subset.raw,
        repetitions = cfg.args.repetitions,
        routes = plan.len(),
        resume = cfg.args.resume,
        checkpoint = %cfg.args.checkpoint.display(),
        "fake evaluator starting"
    );
    let once = OnceDir::of_pair(
        cfg.faults.once_dir.clone(),
        "fake-evaluator",
        cfg.faults.once_owner.as_deref(),
        cfg.args.port,
    );
    let mut run = Run {
        checkpoint: Checkpoint::new(lb, cfg.args.checkpoint.clone(), plan.len() as u64),
        cfg,
        lb,
        once,
        template,
        sensors_initialized: false,
        setup_failure: false,
    };
    run.setup_failure = run.cfg.faults.setup_failure && run.once.armed("setup-failure");

    // The module-level imports and the agent's, before anything talks to CARLA.
    if let Err(failure) = run.cfg.imports.check() {
        run.traceback(&[failure.frame], &failure.error);
        return Exit::Traceback;
    }

    // `LeaderboardEvaluator.__init__`: no simulator, no checkpoint.
    let mut carla = match run.connect(&mut signals).await {
        Ok(carla) => carla,
        Err(exit) => return exit,
    };

    let start = match run.start(&plan) {
        Ok(start) => start,
        Err(exit) => return exit,
    };
    if let Some(exit) = run.tamper() {
        return exit;
    }
    run.start_flood();
    for cfg in plan.iter().skip(start) {
        if let Some(exit) = run.route(cfg, &mut carla, &mut signals).await {
            return exit;
        }
    }
    run.global()
}

/// How long a forging evaluator waits after its last route before its last forgery.
const FORGE_LAST_WORD: Duration = Duration::from_secs(3);

struct Run {
    cfg: EvaluatorConfig,
    lb: Leaderboard,
    once: OnceDir,
    template: Template,
    checkpoint: Checkpoint,
    /// Whether the agent came up in this process (the 2.0 evaluator's flag).
    sensors_initialized: bool,
    /// Whether this run's agent cannot be set up (decided once, marked on first use).
    setup_failure: bool,
}

impl Run {
    fn script(&self) -> &str {
        self.cfg
            .args
            .script
            .as_deref()
            .unwrap_or("leaderboard/leaderboard_evaluator.py")
    }

    /// Prints an uncaught Python exception to stderr, as the interpreter does before exit 1.
    fn traceback(&self, frames: &[(&str, &str)], error: &str) {
        let script = self.script();
        let mut text = String::from("Traceback (most recent call last):\n");
        text.push_str(&format!(
            "  File \"{script}\", line 517, in <module>\n    main()\n"
        ));
        for (i, (function, code)) in frames.iter().enumerate() {
            text.push_str(&format!(
                "  File \"{script}\", line {}, in {function}\n    {code}\n",
                500 - i * 97
            ));
        }
        text.push_str(error);
        text.push('\n');
        say_err(&text);
    }

    fn write_failed(&self, error: &RecordsError, function: &str) -> Exit {
        let detail = match error {
            RecordsError::Unwritable { path, source } => match source.kind() {
                std::io::ErrorKind::NotFound => {
                    format!("FileNotFoundError: [Errno 2] No such file or directory: '{path}'")
                }
                std::io::ErrorKind::PermissionDenied => {
                    format!("PermissionError: [Errno 13] Permission denied: '{path}'")
                }
                _ => format!("OSError: {source}: '{path}'"),
            },
            other => format!("RuntimeError: {other}"),
        };
        self.traceback(
            &[
                ("main", "crashed = leaderboard_evaluator.run(arguments)"),
                ("run", function),
            ],
            &detail,
        );
        Exit::Traceback
    }

    fn write(&self, function: &str) -> Result<(), Exit> {
        self.checkpoint
            .write()
            .map_err(|e| self.write_failed(&e, function))
    }

    /// Loads or clears the checkpoint; returns the plan index to start at.
    fn start(&mut self, plan: &[RouteConfig]) -> Result<usize, Exit> {
        let path = self.cfg.args.checkpoint.clone();
        let total = plan.len() as u64;
        if !self.cfg.args.resume {
            self.checkpoint = Checkpoint::new(self.lb, path, total);
            self.write("self.statistics_manager.write_statistics()")?;
            return Ok(0);
        }
        let (state, at) = Checkpoint::resume(self.lb, path.clone(), plan);
        match (self.lb, at) {
            (Leaderboard::V2, Ok(index)) => {
                self.checkpoint = state;
                self.write("self.statistics_manager.write_statistics()")?;
                tracing::info!(index, "resuming");
                Ok(index)
            }
            (Leaderboard::V2, Err(message)) => {
                say(message);
                self.checkpoint = Checkpoint::new(self.lb, path, total);
                self.write("self.statistics_manager.write_statistics()")?;
                Ok(0)
            }
            // 1.0 leaves the file alone until the next save.
            (Leaderboard::V1, Ok(index)) => {
                self.checkpoint = state;
                tracing::info!(index, "resuming");
                Ok(index)
            }
            (Leaderboard::V1, Err(message)) => {
                say(message);
                self.checkpoint = state;
                Ok(0)
            }
        }
    }

    /// Runs one route; `Some` ends the run.
    async fn route(
        &mut self,
        cfg: &RouteConfig,
        carla: &mut TcpStream,
        signals: &mut Signals,
    ) -> Option<Exit> {
        say("");
        say(&bold(&format!(
            "========= Preparing {} (repetition {}) =========",
            cfg.name, cfg.rep
        )));
        if self.lb == Leaderboard::V2 {
            // `create_route_data`: a `Started` record, saved with the next write.
            let started = records::started_record(cfg, self.lb);
            if let Err(e) = self.checkpoint.set_record(cfg.index, started) {
                return Some(self.not_enough_entries(&e));
            }
        }

        say(&bold("> Loading the world"));
        if !probe(&self.cfg.args.host, self.cfg.args.port).await {
            say("\n\x1b[91mThe scenario could not be loaded:");
            say(&format!(
                "\n{}\x1b[0m",
                self.simulator_traceback("self._load_and_wait_for_world(args, config.town)")
            ));
            return Some(self.simulation_crashed(cfg, 0.0));
        }

        say(&bold("> Setting up the agent"));
        if self.setup_failure {
            return self.agent_setup_failed(cfg);
        }
        if !self.sensors_initialized {
            self.sensors_initialized = true;
            self.checkpoint.sensors = self.template.sensors().to_vec();
            if let Err(exit) = self.write("self.statistics_manager.write_statistics()") {
                return Some(exit);
            }
            self.spawn_child();
        }

        say(&bold("> Running the route"));
        self.start_recorder(cfg, carla).await;
        self.fill_disk(cfg);
        if let Some(exit) = self.crash(cfg) {
            return Some(exit);
        }
        if let Some(exit) = self.hang(cfg, signals).await {
            return Some(exit);
        }

        let record = self.template.record(cfg, self.cfg.args.repetitions);
        match self.drive(cfg, &record, carla, signals).await {
            Driven::Done => {
                say(&bold("> Stopping the route"));
                self.recorder(carla, "stop_recorder").await;
                self.register(cfg, self.as_claimed(record), EntryStatus::Started)
            }
            Driven::CarlaGone(fraction) => {
                say("\n\x1b[91mError during the simulation:");
                say(&format!(
                    "\n{}\x1b[0m",
                    self.simulator_traceback("self.manager.run_scenario()")
                ));
                say(&bold("> Stopping the route"));
                Some(self.simulation_crashed(cfg, fraction))
            }
            Driven::Stopped(stop) => Some(Exit::Stopped(stop)),
        }
    }

    /// `LeaderboardEvaluator.__init__`'s connection to CARLA, within the client's timeout:
    /// the evaluator's traceback when it times out, or the signal that ended the wait.
    async fn connect(&self, signals: &mut Signals) -> Result<TcpStream, Exit> {
        let deadline = self.cfg.connect_seconds.unwrap_or(self.cfg.args.timeout);
        tokio::select! {
            conn = connect(&self.cfg.args.host, self.cfg.args.port, deadline) => conn.ok_or_else(|| {
                self.traceback(
                    &[
                        ("main", "leaderboard_evaluator = LeaderboardEvaluator(arguments, statistics_manager)"),
                        ("__init__", "self.client, self.client_timeout, self.traffic_manager = self._setup_simulation(args)"),
                        ("_setup_simulation", "client.get_world().apply_settings(settings)"),
                    ],
                    &format!(
                        "RuntimeError: time-out of {}ms while waiting for the simulator, make sure \
                         the simulator is ready and connected to {}:{}",
                        (deadline * 1000.0).round() as u64,
                        self.cfg.args.host,
                        self.cfg.args.port
                    ),
                );
                Exit::Traceback
            }),
            stop = signals.recv() => Err(Exit::Stopped(stop)),
        }
    }

    /// The flood fault (`FAKE_EVALUATOR_FLOOD_HZ`), for the rest of the run.
    fn start_flood(&self) {
        let Some(hz) = self.cfg.faults.flood_hz else {
            return;
        };
        tracing::warn!(
            hz,
            "injected flood: rewriting a status file and the results file"
        );
        let faults = &self.cfg.faults;
        tokio::spawn(crate::faults::flood(
            faults.status_dir.clone(),
            self.cfg.args.checkpoint.clone(),
            (hz, faults.pair_id),
        ));
    }

    /// The agent cannot be set up (`FAKE_EVALUATOR_SETUP_FAILURE`): the evaluator's traceback,
    /// and the route's record says so.
    fn agent_setup_failed(&mut self, cfg: &RouteConfig) -> Option<Exit> {
        self.once.mark("setup-failure");
        say("\n\x1b[91mCould not set up the required agent:");
        say(&format!(
            "\nTraceback (most recent call last):\n  File \"{}\", line 331, in \
             _load_and_run_scenario\n    self.agent_instance.setup(args.agent_config)\n\
             RuntimeError: fake-evaluator: the agent cannot be set up \
             (FAKE_EVALUATOR_SETUP_FAILURE)\n\x1b[0m",
            self.script()
        ));
        let record = records::setup_failure(self.template.record(cfg, self.cfg.args.repetitions));
        self.register(cfg, record, EntryStatus::Started)
    }

    /// The hang fault (`FAKE_EVALUATOR_HANG_AT_ROUTE`): silent until a signal ends it.
    async fn hang(&mut self, cfg: &RouteConfig, signals: &mut Signals) -> Option<Exit> {
        let sel = self
            .cfg
            .faults
            .hang_at
            .filter(|s| s.matches(cfg.route, cfg.rep))?;
        let fault = format!("hang-at-route-{}", sel.label());
        if !self.once.armed(&fault) {
            return None;
        }
        self.once.mark(&fault);
        tracing::warn!(route = %cfg.route_id, "injected hang: silent until killed");
        Some(Exit::Stopped(signals.recv().await))
    }

    /// The crash fault (`FAKE_EVALUATOR_CRASH_AT_ROUTE`): a traceback, and the exit it makes.
    fn crash(&mut self, cfg: &RouteConfig) -> Option<Exit> {
        let faults = &self.cfg.faults;
        if let Some(sel) = faults.crash_at.filter(|s| s.matches(cfg.route, cfg.rep)) {
            let fault = format!("crash-at-route-{}", sel.label());
            if self.once.armed(&fault) {
                self.once.mark(&fault);
                tracing::warn!(route = %cfg.route_id, "injected evaluator crash");
                self.traceback(
                    &[
                        ("main", "crashed = leaderboard_evaluator.run(arguments)"),
                        ("run", "crashed = self._load_and_run_scenario(args, config)"),
                        ("_load_and_run_scenario", "self._cleanup()"),
                    ],
                    &format!(
                        "RuntimeError: fake-evaluator: injected crash at {} \
                         (FAKE_EVALUATOR_CRASH_AT_ROUTE)",
                        cfg.route_id
                    ),
                );
                return Some(Exit::Traceback);
            }
        }
        None
    }

    /// The disk hog (`FAKE_EVALUATOR_FILL_AT_ROUTE`): a large file in the writable layer.
    fn fill_disk(&mut self, cfg: &RouteConfig) {
        let faults = &self.cfg.faults;
        if let Some(sel) = faults.fill_at.filter(|s| s.matches(cfg.route, cfg.rep)) {
            let fault = format!("fill-at-route-{}", sel.label());
            if self.once.armed(&fault) {
                self.once.mark(&fault);
                let file = std::path::Path::new(crate::faults::FILL_LAYER_FILE);
                let filled = std::fs::File::create(file)
                    .and_then(|f| f.set_len(crate::faults::FILL_LAYER_BYTES));
                tracing::warn!(route = %cfg.route_id, ?filled, "injected disk hog");
            }
        }
    }

    /// The record as the participant's evaluator writes it: with
    /// `FAKE_EVALUATOR_FORGE_RECORDINGS` it claims no simulated time, so a recording of
    /// CARLA's header alone would fit the claim.
    fn as_claimed(
        &self,
        mut record: lb_domain::results::RouteRecord,
    ) -> lb_domain::results::RouteRecord {
        if self.cfg.faults.forge_recordings {
            record.meta.duration_game = lb_domain::results::py::Num::Float(0.0);
        }
        record
    }

    /// Spends the route's time, watching the simulator connection and the stop signals.
    async fn drive(
        &self,
        cfg: &RouteConfig,
        record: &lb_domain::results::RouteRecord,
        carla: &mut TcpStream,
        signals: &mut Signals,
    ) -> Driven {
        let total = Duration::from_secs_f64(self.cfg.route_seconds);
        let start = Instant::now();
        let mut next_report = start;
        let mut buf = [0u8; 1024];
        // The simulated frames CARLA was told to tick (and record) so far.
        let frames = |fraction: f64| {
            (fraction * record.meta.duration_game.as_f64().max(0.0) * SIMULATED_HZ) as u64
        };
        let mut ticked = 0;
        loop {
            let elapsed = start.elapsed();
            let fraction = if total.is_zero() {
                1.0
            } else {
                (elapsed.as_secs_f64() / total.as_secs_f64()).min(1.0)
            };
            if Instant::now() >= next_report {
                next_report += PROGRESS_EVERY;
                say(&format!(
                    "[fake-evaluator] {} {:.0}% (route {} of {})",
                    cfg.route_id,
                    fraction * 100.0,
                    cfg.index + 1,
                    self.checkpoint_total()
                ));
                self.live_results(record, fraction);
                ticked = self.tick(carla, ticked, frames(fraction)).await;
            }
            if elapsed >= total {
                self.live_results(record, 1.0);
                self.tick(carla, ticked, frames(1.0)).await;
                return Driven::Done;
            }
            let wait = (total - elapsed).min(next_report.saturating_duration_since(Instant::now()));
            tokio::select! {
                () = tokio::time::sleep(wait) => {}
                read = carla.read(&mut buf) => match read {
                    Ok(0) | Err(_) => return Driven::CarlaGone(fraction),
                    // The fake server sends nothing; a real one's bytes are not ours to read.
                    Ok(_) => {}
                },
                stop = signals.recv() => return Driven::Stopped(stop),
            }
        }
    }

    fn checkpoint_total(&self) -> usize {
        self.cfg.args.routes_subset.routes.len() * self.cfg.args.repetitions as usize
    }

    /// `_register_statistics` and the write after the route.
    fn register(
        &mut self,
        cfg: &RouteConfig,
        record: lb_domain::results::RouteRecord,
        entry_status: EntryStatus,
    ) -> Option<Exit> {
        say(&bold("> Registering the route statistics"));
        if let Err(e) = self.checkpoint.set_record(cfg.index, record) {
            return Some(self.not_enough_entries(&e));
        }
        self.checkpoint.entry_status = entry_status;
        self.checkpoint.done = cfg.index as u64 + 1;
        let written = self
            .write("self.statistics_manager.write_statistics()")
            .err();
        if written.is_none() {
            self.note_write(&cfg.index.to_string());
        }
        written
    }

    /// Appends a write's time to `FAKE_EVALUATOR_RECORD_LOG` (one short line: appends of
    /// several evaluators to one file do not interleave).
    fn note_write(&self, what: &str) {
        let Some(path) = &self.cfg.faults.record_log else {
            return;
        };
        let ms = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_millis());
        let line = format!("{ms} {what}\n");
        let appended = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)
            .and_then(|mut f| std::io::Write::write_all(&mut f, line.as_bytes()));
        if let Err(e) = appended {
            tracing::warn!(path = %path.display(), error = %e, "cannot note a write");
        }
    }

    fn not_enough_entries(&self, error: &RecordsError) -> Exit {
        say(&error.to_string());
        Exit::SimulationCrashed
    }

    /// The record, file and exit of a run whose simulator went away.
    fn simulation_crashed(&mut self, cfg: &RouteConfig, fraction: f64) -> Exit {
        say(&bold("> Registering the route statistics"));
        let record = records::simulation_crashed(
            self.template.record(cfg, self.cfg.args.repetitions),
            fraction,
        );
        if let Err(e) = self.checkpoint.set_record(cfg.index, record) {
            return self.not_enough_entries(&e);
        }
        self.checkpoint.entry_status = EntryStatus::Crashed;
        // 2.0 saves the progress after the crashed route; 1.0 exits before `save_state`.
        if self.lb == Leaderboard::V2 {
            self.checkpoint.done = cfg.index as u64 + 1;
        }
        if let Err(exit) = self.write("self.statistics_manager.write_statistics()") {
            return exit;
        }
        tracing::warn!(route = %cfg.route_id, "the simulator went away; route recorded as crashed");
        Exit::SimulationCrashed
    }

    fn simulator_traceback(&self, code: &str) -> String {
        format!(
            "Traceback (most recent call last):\n  File \"{}\", line 380, in \
             _load_and_run_scenario\n    {code}\nRuntimeError: time-out of {}ms while waiting \
             for the simulator, make sure the simulator is ready and connected to {}:{}",
            self.script(),
            (self.cfg.args.timeout * 1000.0).round() as u64,
            self.cfg.args.host,
            self.cfg.args.port
        )
    }

    /// The end of a complete run: global statistics, `Finished`, exit 0.
    /// The tampering faults, before the first route: another pair's results file and done
    /// marker written beside this pair's own (`FAKE_EVALUATOR_FORGE_PAIR`), another GPU planted
    /// in the pair's handoff, then a crash (`FAKE_EVALUATOR_PLANT_GPU`, once).
    fn tamper(&self) -> Option<Exit> {
        self.forge();
        let faults = &self.cfg.faults;
        let planted = faults
            .plant_gpu
            .iter()
            .find(|uuid| Some(uuid.as_str()) != faults.own_gpu.as_deref())?;
        let handoff = faults.handoff_file.as_ref()?;
        if !self.once.armed("plant-gpu") {
            return None;
        }
        self.once.mark("plant-gpu");
        if let Err(error) = std::fs::write(handoff, planted) {
            tracing::warn!(%error, path = %handoff.display(), "cannot plant the GPU");
        }
        tracing::warn!(%planted, "injected: another GPU planted in the handoff, then a crash");
        self.traceback(
            &[("main", "crashed = leaderboard_evaluator.run(arguments)")],
            &format!("RuntimeError: fake-evaluator: planted {planted} (FAKE_EVALUATOR_PLANT_GPU)"),
        );
        Some(Exit::Traceback)
    }

    /// Writes pair `FAKE_EVALUATOR_FORGE_PAIR`'s results file (this pair's records, outside
    /// that pair's routes) and its done marker, as a participant's code can in its own pod.
    fn forge(&self) {
        let Some(other) = self
            .cfg
            .faults
            .forge_pair
            .filter(|other| Some(*other) != self.cfg.faults.pair_id)
        else {
            return;
        };
        let Some(dir) = self.cfg.args.checkpoint.parent() else {
            return;
        };
        let forged = dir.join(lb_domain::job::protocol::partial_results_name(other));
        let marker = lb_domain::job::protocol::Marker::Done {
            role: lb_domain::job::protocol::Role::Agent,
            pair: other,
        };
        let written = records::write_atomic(&forged, self.checkpoint.to_json().as_bytes())
            .map_err(|e| e.to_string())
            .and_then(|()| {
                std::fs::write(self.cfg.faults.status_dir.join(marker.to_string()), b"")
                    .map_err(|e| e.to_string())
            });
        match written {
            Ok(()) => tracing::warn!(
                pair = other,
                "injected: another pair's results and done marker forged"
            ),
            Err(error) => tracing::warn!(%error, "cannot forge another pair's files"),
        }
    }

    fn global(&mut self) -> Exit {
        // The forger's last word, a while after every route of its own: later than the forged
        // pair's own last write, so that, were it uploaded, it would stand.
        if self.cfg.faults.forge_pair.is_some() {
            std::thread::sleep(FORGE_LAST_WORD);
        }
        self.forge();
        say(&bold("> Registering the global statistics"));
        let (merged, mut text) = match self.checkpoint.finish(self.sensors_initialized) {
            Ok(done) => done,
            Err(e) => {
                self.traceback(
                    &[
                        ("main", "crashed = leaderboard_evaluator.run(arguments)"),
                        ("run", "self.statistics_manager.compute_global_statistics()"),
                    ],
                    &format!("RuntimeError: {e}"),
                );
                return Exit::Traceback;
            }
        };
        if let Some(reason) = merged.invalid_reason {
            say("\n\x1b[91mThe statistics are badly formed. Setting their status to 'Invalid':");
            say(&format!("> {reason}\x1b[0m\n"));
        }
        if let Some(kind) = self.cfg.faults.garbage {
            if self.once.armed("garbage") {
                self.once.mark("garbage");
                tracing::warn!(?kind, "injected garbage checkpoint");
                text = records::garbage(kind, &text);
            }
        }
        match records::write_atomic(self.checkpoint.path(), text.as_bytes()) {
            Ok(()) => {
                self.note_write("global");
                Exit::Finished
            }
            Err(e) => self.write_failed(
                &e,
                "self.statistics_manager.validate_and_write_statistics(self.sensors_initialized, crashed)",
            ),
        }
    }

    fn spawn_child(&self) {
        let Some(mode) = self.cfg.faults.spawn_child else {
            return;
        };
        if !self.once.armed("spawn-child") {
            return;
        }
        self.once.mark("spawn-child");
        match spawn_child(mode, self.cfg.faults.child_seconds) {
            Ok(pid) => {
                tracing::info!(pid, ?mode, "spawned a participant helper that outlives us");
                if let Some(path) = &self.cfg.faults.child_pid_file {
                    if let Err(error) = records::write_atomic(path, format!("{pid}\n").as_bytes()) {
                        tracing::warn!(%error, "cannot write the child's pid file");
                    }
                }
            }
            Err(error) => tracing::warn!(%error, "cannot spawn the participant helper"),
        }
    }

    /// `client.start_recorder("<--record>/<route>_rep<r>.log")`: CARLA, not the evaluator,
    /// writes the file, in its own container. With `FAKE_EVALUATOR_FORGE_RECORDINGS` the
    /// participant's code then stops the recorder and leaves 1-byte files of the route's name
    /// where the recordings used to be (and its records claim no simulated time).
    async fn start_recorder(&self, cfg: &RouteConfig, carla: &mut TcpStream) {
        if self.cfg.args.record.is_empty() {
            return;
        }
        let name = format!("{}_rep{}.log", cfg.name, cfg.rep);
        let path = Path::new(&self.cfg.args.record).join(&name);
        let command = format!("start_recorder {}", path.display());
        self.recorder(carla, &command).await;
        if !self.cfg.faults.forge_recordings {
            return;
        }
        self.recorder(carla, "stop_recorder").await;
        let Some(own) = self
            .cfg
            .args
            .debug_checkpoint
            .as_deref()
            .and_then(Path::parent)
        else {
            return;
        };
        let forged = own.join("recorder").join(&name);
        let written = std::fs::create_dir_all(own.join("recorder"))
            .and_then(|()| std::fs::write(&forged, b"\0"));
        match written {
            Ok(()) => {
                tracing::warn!(path = %forged.display(), "injected: recorder stopped, a 1-byte recording left")
            }
            Err(error) => tracing::warn!(%error, "cannot forge a recording"),
        }
    }

    /// Calls CARLA's recorder with one command (`lb_workloads::carla`'s line protocol) and
    /// waits, bounded, until it is done: the recording exists once `start_recorder` returns.
    async fn recorder(&self, carla: &mut TcpStream, command: &str) {
        if self.cfg.args.record.is_empty() {
            return;
        }
        let call = async {
            carla.write_all(format!("{command}\n").as_bytes()).await?;
            let mut done = [0u8; crate::recorder::RECORDER_DONE.len()];
            carla.read_exact(&mut done).await.map(|_| ())
        };
        match tokio::time::timeout(RECORDER_CALL, call).await {
            Ok(Ok(())) => {}
            Ok(Err(error)) => tracing::warn!(%error, command, "cannot reach CARLA's recorder"),
            Err(_) => tracing::warn!(command, "CARLA's recorder did not answer"),
        }
    }

    /// Ticks CARLA up to `to` simulated frames from `from`; the frames ticked.
    async fn tick(&self, carla: &mut TcpStream, from: u64, to: u64) -> u64 {
        if to > from {
            self.recorder(carla, &format!("tick {}", to - from)).await;
        }
        to.max(from)
    }

    /// `write_live_results` (2.0 only) to `--debug-checkpoint`.
    fn live_results(&self, record: &lb_domain::results::RouteRecord, fraction: f64) {
        let Some(path) = &self.cfg.args.debug_checkpoint else {
            return;
        };
        let text = records::live_results(record, fraction);
        if let Err(error) = records::write_atomic(path, text.as_bytes()) {
            tracing::warn!(%error, "cannot write the live results");
        }
    }
}

enum Driven {
    Done,
    CarlaGone(f64),
    Stopped(Stop),
}

/// Connects to CARLA, retrying with backoff until `deadline_seconds` have passed.
async fn connect(host: &str, port: u16, deadline_seconds: f64) -> Option<TcpStream> {
    let deadline = Instant::now() + Duration::from_secs_f64(deadline_seconds);
    let mut backoff = Duration::from_millis(50);
    loop {
        if let Ok(Ok(stream)) =
            tokio::time::timeout(CONNECT_ATTEMPT, TcpStream::connect((host, port))).await
        {
            return Some(stream);
        }
        let now = Instant::now();
        if now >= deadline {
            return None;
        }
        tokio::time::sleep(backoff.min(deadline - now)).await;
        backoff = (backoff * 2).min(Duration::from_secs(1));
    }
}

/// Whether CARLA still accepts connections (the fake's `load_world`).
async fn probe(host: &str, port: u16) -> bool {
    matches!(
        tokio::time::timeout(CONNECT_ATTEMPT, TcpStream::connect((host, port))).await,
        Ok(Ok(_))
    )
}
