//! `lbctl local run`: one submission from the SQS message to the final scores on this machine,
//! through the deployed state machine definition, the real handlers, Job templates and sidecar.

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use clap::{Args, ValueEnum};
use fake_evalai::Fixture;
use lb_domain::results::Leaderboard;
use lb_pipeline::cluster::Clusters;
use lb_pipeline::FnError;
use local_stack::stack::{LOCAL_SETTINGS, WAKE_TABLE};
use local_stack::workloads::{Behaviour, Binaries};
use local_stack::{EvalAi, Stack};

use crate::report::{Merged, RunReport};
use cli::{clean, outln};
use local_stepfunctions::{
    EventType, Executor, HistoryEvent, Options, StateMachine, TaskError, TaskMap,
};
use serde_json::{json, Value};

/// The least seconds per route of the spot scenario: the drain must land mid-route.
const SPOT_ROUTE_SECONDS: f64 = 1.5;

/// The deployed definition, embedded so `lbctl` runs from anywhere.
const DEFINITION: &str = include_str!("../../../statemachine/submission.asl.json");

/// What the run rehearses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Scenario {
    /// Everything works: FINISHED with scores.
    Happy,
    /// CARLA of the first pair is killed mid-route: crash markers, restart, resume, FINISHED.
    Crash,
    /// The first pair's evaluator hangs: the idle watchdog ends it, it resumes, FINISHED.
    Hang,
    /// The participant cancels on EvalAI after the first round: CANCELLED once the sweep (or
    /// a partial update's status read) notices, nothing left.
    Cancel,
    /// The participant's image cannot be pulled: FAILED with a message naming it.
    Unpullable,
    /// The first pair's evaluator crashes at every attempt: out of retries, FAILED, and the
    /// participant's stderr shows the reason and the end of that agent's output.
    CrashLoop,
    /// The cluster's node has another GPU model than the leaderboard's: the autoscaler says no
    /// node group could hold the pods, FAILED at once naming the labels the pods need (a
    /// configuration problem of the leaderboard), none of the participant's time used.
    NoNode,
    /// Every agent rewrites a file in its status directory and its own results file several
    /// times a second for the whole run: only the protocol's files wake the execution, rounds
    /// come no sooner than the least interval, and a history near its budget continues as a
    /// new execution. FINISHED.
    WakeFlood,
    /// Every other pair's agent writes pair 2's results file and done marker in its own pod:
    /// none of it leaves the pod, pair 2's honest results stand, FINISHED.
    Forge,
    /// Every agent plants another GPU's UUID in its pair's handoff and crashes once: each
    /// simulator renders on its own pair's GPU at every attempt, FINISHED (a node of 4 GPUs
    /// unless --gpus says otherwise).
    PlantGpu,
    /// The node is reclaimed mid-route (a Spot interruption: the managed node group drains it
    /// through the Eviction API): every pod gets the `DisruptionTarget` condition and a new
    /// pod replaces it once it has stopped, without using a retry; each interrupted route runs
    /// again once. FINISHED (routes of at least 1.5 s, so that the drain lands mid-route).
    Spot,
    /// An operator stops the execution (StopExecution) after its first Monitor round: the
    /// reaper (Finalize, on Step Functions' status-change event, which local mode delivers as
    /// EventBridge would) deletes the Jobs, gives the team's place back, tells EvalAI
    /// `failed` with the reason and writes the final record.
    Stop,
}

impl Scenario {
    fn expected(self) -> &'static str {
        match self {
            Scenario::Happy
            | Scenario::Crash
            | Scenario::Hang
            | Scenario::WakeFlood
            | Scenario::Forge
            | Scenario::PlantGpu
            | Scenario::Spot => "finished",
            Scenario::Cancel => "cancelled",
            Scenario::Unpullable | Scenario::CrashLoop | Scenario::NoNode | Scenario::Stop => {
                "failed"
            }
        }
    }
}

/// `lbctl local run` options.
#[derive(Debug, Clone, Args)]
pub struct LocalRun {
    /// What to rehearse.
    #[arg(long, value_enum, default_value = "happy")]
    pub scenario: Scenario,
    /// Simulator-agent pairs.
    #[arg(long, default_value_t = 4)]
    pub workers: u32,
    /// GPUs of the local node (`nvidia.com/gpu`; each pair's agent requests one): pairs
    /// beyond them wait Pending, Unschedulable, until a GPU frees. Default: not modelled.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub gpus: Option<u32>,
    /// Submissions run together, from the teams of --teams, arriving on EvalAI in that order.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=50))]
    pub submissions: u32,
    /// How many of the submissions each team sends, e.g. `6,2,2,2` (summing to
    /// --submissions; the first team's go first). Default: one team for all.
    #[arg(long, value_delimiter = ',', value_parser = clap::value_parser!(u32).range(1..=50))]
    pub teams: Vec<u32>,
    /// The leaderboard's `team_limit`: evaluations one team may hold at once.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=100))]
    pub team_limit: Option<u32>,
    /// Write what the fake EvalAI saw of each submission (statuses in order, queue places
    /// shown, admission order, requests a minute) to this JSON file.
    #[arg(long, value_name = "FILE")]
    pub report: Option<std::path::PathBuf>,
    /// Routes of the track.
    #[arg(long, default_value_t = 20)]
    pub routes: u32,
    /// Seconds the fake evaluator spends per route.
    #[arg(long, default_value_t = 0.2)]
    pub route_seconds: f64,
    /// Leaderboard of the submission's phase (`1.0` or `2.0`).
    #[arg(long, default_value = "2.0", value_parser = |s: &str| s.parse::<Leaderboard>())]
    pub leaderboard: Leaderboard,
    /// Multiplies the state machine's waits and retry intervals (0.05: a 60 s Wait lasts 3 s).
    #[arg(long, default_value_t = 0.05)]
    pub time_scale: f64,
    /// From the first Monitor round, the local cluster's API answers every request with 500
    /// `InternalError` for this many minutes (scaled by --time-scale); the Jobs run on.
    #[arg(long, default_value_t = 0.0)]
    pub kube_outage_minutes: f64,
    /// The cancel scenario: the participant cancels when this Monitor round ends.
    #[arg(long, default_value_t = 1)]
    pub cancel_after_round: u64,
    /// The events one execution may take before the run continues as a new execution (the
    /// deployment's is 10,000; a small one rehearses continuations in a short run).
    #[arg(long, default_value_t = lb_domain::history::EXECUTION_BUDGET, value_parser = clap::value_parser!(u64).range(lb_domain::history::MIN_BUDGET..=lb_domain::history::EXECUTION_BUDGET))]
    pub history_budget: u64,
    /// Wall-clock limit of the whole run, in seconds.
    #[arg(long, default_value_t = 600)]
    pub timeout: u64,
    /// An EvalAI to use instead of the fake (needs --evalai-token, --challenge, --phase, --submission).
    #[arg(long, requires_all = ["evalai_token", "challenge", "phase", "submission"])]
    pub evalai_url: Option<String>,
    /// Host token of that EvalAI (better from the environment: a flag shows in `ps`).
    #[arg(long, env = "LB_EVALAI_TOKEN", hide_env_values = true)]
    pub evalai_token: Option<String>,
    /// Challenge id on that EvalAI.
    #[arg(long)]
    pub challenge: Option<u64>,
    /// Phase id on that EvalAI.
    #[arg(long)]
    pub phase: Option<u64>,
    /// Submission id on that EvalAI.
    #[arg(long)]
    pub submission: Option<u64>,
    /// The leaderboard's `partial_update_seconds` (default: 20 s scaled by --time-scale).
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..=3600))]
    pub partial_update_seconds: Option<u64>,
    /// Measure how long results take to reach EvalAI (record -> partial update, last write ->
    /// final status; `make bench-latency`).
    #[arg(long)]
    pub latency: bool,
    /// Leave S3's events undelivered (no wake function): rounds come only from the safety
    /// net, holds and the sweep, as in a deployment whose buckets send no events.
    #[arg(long)]
    pub no_wake: bool,
    /// Keep the stack running after the summary (until Ctrl-C) to look at S3, EvalAI, logs.
    #[arg(long)]
    pub keep: bool,
}

const IMAGE: &str = "123456789012.dkr.ecr.us-west-2.amazonaws.com/team-one:local";
const UNPULLABLE: &str = "123456789012.dkr.ecr.us-west-2.amazonaws.com/team-one:never-pushed";
/// How often a flooding agent rewrites its files (the wake-flood scenario): the issue's
/// reproduction rewrote one four times a second.
const FLOOD_HZ: u32 = 4;
/// The node type of the no-node scenario: not of the GPU model the local settings name.
const OTHER_INSTANCE_TYPE: &str = "g6.xlarge";

fn say(started: Instant, text: impl AsRef<str>) {
    outln!(
        "[{:>6.1}s] {}",
        started.elapsed().as_secs_f64(),
        text.as_ref()
    );
}

/// Runs one local submission; the exit code is 0 only when it ended as the scenario expects.
pub async fn run(args: LocalRun) -> anyhow::Result<u8> {
    if !(args.time_scale > 0.0 && args.time_scale <= 1.0) {
        bail!("--time-scale must be in (0, 1], got {}", args.time_scale);
    }
    if args.routes == 0 || args.workers == 0 {
        bail!("--routes and --workers must be at least 1");
    }
    if !(args.kube_outage_minutes >= 0.0 && args.kube_outage_minutes <= 7.0 * 24.0 * 60.0) {
        bail!(
            "--kube-outage-minutes must be between 0 and a week, got {}",
            args.kube_outage_minutes
        );
    }
    let teams = team_sizes(&args)?;
    if teams.len() > 1 && args.evalai_url.is_some() {
        bail!("--teams needs the fake EvalAI (an external one has its own teams)");
    }
    let started = Instant::now();
    let bins = Binaries::find()?;

    // The phase: 1 is Leaderboard 2.0, 2 is 1.0 in the local settings and the fake's fixture.
    let phase = match args.leaderboard {
        Leaderboard::V1 => 2,
        Leaderboard::V2 => 1,
    };
    let board = args.leaderboard.as_str();
    let mut settings: Value = serde_json::from_str(LOCAL_SETTINGS)?;
    let track = &mut settings["leaderboards"][board]["tracks"]["SENSORS"];
    track["routes"] = json!(args.routes);
    track["workers"] = json!(args.workers);
    // The Monitor's clock is real while the executor scales every wait: the least interval
    // between partial updates is scaled here, or a fast run would defer its updates and spin.
    let interval = args.partial_update_seconds.unwrap_or(
        (lb_domain::schedule::PARTIAL_UPDATE_INTERVAL.as_secs_f64() * args.time_scale)
            .round()
            .max(1.0) as u64,
    );
    settings["leaderboards"][board]["partial_update_seconds"] = json!(interval);
    if let Some(limit) = args.team_limit {
        settings["leaderboards"][board]["team_limit"] = json!(limit);
    }
    // Another EvalAI has its own phase ids: its phase runs the chosen leaderboard's track.
    if let (Some(_), Some(p)) = (&args.evalai_url, args.phase) {
        settings["phases"][p.to_string()] =
            json!({"leaderboard": args.leaderboard, "track": "SENSORS"});
    }

    let external = args.evalai_url.clone().map(|url| EvalAi::External {
        url,
        token: args.evalai_token.clone().unwrap_or_default(),
    });
    let mut stack =
        Stack::start(external.unwrap_or(EvalAi::Fake(Fixture::with_teams(teams.len()))))
            .await
            .context("starting the local stack (run `make venv` for moto)")?;
    say(
        started,
        format!(
            "stack up in {:.1}s: moto {}, EvalAI {}",
            stack.started_in.as_secs_f64(),
            stack.moto.endpoint(),
            stack.evalai_url
        ),
    );
    let settings = stack.provision(&settings.to_string()).await?;

    let scratch = stack.workdir.path().join("images");
    let once = scratch.join("once");
    std::fs::create_dir_all(&once)?;
    let mut behaviour = Behaviour {
        route_seconds: args.route_seconds,
        node_gpus: args.gpus,
        ..Behaviour::default()
    };
    if args.scenario == Scenario::Spot {
        behaviour.route_seconds = args.route_seconds.max(SPOT_ROUTE_SECONDS);
        behaviour.node_capacity = lb_domain::settings::Capacity::Spot;
    }
    if args.scenario == Scenario::Hang {
        behaviour.evaluator_env = BTreeMap::from([
            ("FAKE_EVALUATOR_HANG_AT_ROUTE".into(), "1".into()),
            ("FAKE_EVALUATOR_ONCE_DIR".into(), once.display().to_string()),
        ]);
    }
    if args.scenario == Scenario::CrashLoop {
        // No once-dir: every attempt of the pair that runs route 1 crashes there.
        behaviour.evaluator_env =
            BTreeMap::from([("FAKE_EVALUATOR_CRASH_AT_ROUTE".into(), "1".into())]);
    }
    if args.scenario == Scenario::NoNode {
        behaviour.node_instance_type = Some(OTHER_INSTANCE_TYPE.into());
    }
    if args.scenario == Scenario::Forge {
        behaviour
            .evaluator_env
            .insert("FAKE_EVALUATOR_FORGE_PAIR".into(), "2".into());
    }
    if args.scenario == Scenario::PlantGpu {
        // Two of the node's GPUs: at least one is another pair's.
        let planted = [0, 1].map(local_kube::gpu_uuid).join(",");
        behaviour.node_gpus = Some(args.gpus.unwrap_or(4));
        behaviour.evaluator_env.extend([
            ("FAKE_EVALUATOR_PLANT_GPU".into(), planted),
            ("FAKE_EVALUATOR_ONCE_DIR".into(), once.display().to_string()),
        ]);
    }
    if args.scenario == Scenario::WakeFlood {
        behaviour
            .evaluator_env
            .insert("FAKE_EVALUATOR_FLOOD_HZ".into(), FLOOD_HZ.to_string());
    }
    let record_log = stack.workdir.path().join("record-writes.log");
    if args.latency {
        behaviour.evaluator_env.insert(
            "FAKE_EVALUATOR_RECORD_LOG".into(),
            record_log.display().to_string(),
        );
    }
    let unpullable: &[&str] = if args.scenario == Scenario::Unpullable {
        &[UNPULLABLE]
    } else {
        &[]
    };
    stack
        .start_workloads(&settings, &bins, &behaviour, unpullable)
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let kubeconfig = stack.kubeconfig.clone().context("no kubeconfig")?;
    say(
        started,
        format!(
            "local Kubernetes API {} (kubeconfig {})",
            stack.kube.as_ref().map(|k| k.url()).unwrap_or_default(),
            kubeconfig.display()
        ),
    );

    // The submission on EvalAI and the message EvalAI publishes for it.
    let image = if args.scenario == Scenario::Unpullable {
        UNPULLABLE
    } else {
        IMAGE
    };
    let (challenge, phase, arrivals) = match (
        &stack.fake_evalai,
        args.challenge,
        args.phase,
        args.submission,
    ) {
        (Some(fake), _, _, _) => {
            let mut arrivals = Vec::new();
            for (index, size) in teams.iter().enumerate() {
                for _ in 0..*size {
                    let team = index as u64 + 1;
                    let new = fake
                        .add_submission(fake_evalai::NewSubmission {
                            challenge_phase: phase,
                            participant_team: team,
                            submitted_image_uri: image.into(),
                            created_by: None,
                        })
                        .map_err(|e| anyhow::anyhow!("{e}"))?;
                    arrivals.push((new.id, team));
                }
            }
            (1, phase, arrivals)
        }
        (None, Some(c), Some(p), Some(s)) => (c, p, vec![(s, 0)]),
        _ => bail!("an external EvalAI needs --challenge, --phase and --submission"),
    };
    // The first is the one the summary describes in detail (and the scenarios act on).
    let submission = arrivals[0].0;

    // The handlers, in-process, each with its clients built once.
    let config = local_stack::stack::function_config();
    let clusters = || Clusters::kubeconfig(kubeconfig.clone());
    let intake = Arc::new(intake::Deps::load(&stack.sdk, &config).await?);
    let mut launch = launch::Deps::load(&stack.sdk, &config, clusters()).await?;
    launch.timers = Some(lb_jobs::Timers {
        start_wait_seconds: 120,
        end_wait_seconds: 60,
        carla_ready_seconds: 60,
        poll_seconds: 1,
        max_idle_seconds: 5,
        logcopy_period_seconds: 1,
    });
    let launch = Arc::new(launch);
    let mut monitor = monitor::Deps::load(&stack.sdk, &config, clusters()).await?;
    // The autoscaler's word is believed after minutes on EKS; local-kube's is final at once.
    monitor.policy.never_fits_grace = Duration::from_secs(2);
    monitor.history_budget = args.history_budget;
    let monitor = Arc::new(monitor);
    // Finalize wakes a team's next submission through the executor, which the task map below
    // is made for: bound once it exists.
    let late = local_stack::events::LateCallbacks::default();
    let mut finalize = finalize::Deps::load(&stack.sdk, &config, clusters())
        .await?
        .with_callbacks(late.clone());
    finalize.delete_wait = Duration::from_secs(60);
    let finalize = Arc::new(finalize);
    let reaper_deps = finalize.clone();
    // The summary reads the outcome from EvalAI with the functions' own client.
    let evalai = intake.evalai.clone();
    let tasks = TaskMap::new()
        .with("IntakeFunctionArn", move |v| {
            let deps = intake.clone();
            async move { lambda(lb_pipeline::serve::call(&*deps, v).await) }
        })
        .with("LaunchFunctionArn", move |v| {
            let deps = launch.clone();
            async move { lambda(lb_pipeline::serve::call(&*deps, v).await) }
        })
        .with("MonitorFunctionArn", move |v| {
            let deps = monitor.clone();
            async move { lambda(lb_pipeline::serve::call(&*deps, v).await) }
        })
        .with("FinalizeFunctionArn", move |v| {
            let deps = finalize.clone();
            async move { lambda(lb_pipeline::serve::call(&*deps, v).await) }
        });
    // The wake table's wait, on moto's DynamoDB; a continuation, on the executor.
    let tasks = local_stack::integrations::with_services(tasks, &stack.sdk, late.clone());

    let mut substitutions: HashMap<String, String> = ["Intake", "Launch", "Monitor", "Finalize"]
        .iter()
        .map(|f| {
            (
                format!("{f}FunctionArn"),
                format!(
                    "arn:aws:lambda:us-east-1:123456789012:function:{}",
                    f.to_lowercase()
                ),
            )
        })
        .collect();
    substitutions.insert("WakeTable".into(), WAKE_TABLE.into());
    let machine = StateMachine::load(&serde_json::from_str(DEFINITION)?, &substitutions)
        .map_err(|e| anyhow::anyhow!("{e}"))?;

    // Live progress, and the scenario's own act at the right moment.
    let rounds = Arc::new(AtomicU64::new(0));
    // Rounds that found the cluster's API out of reach (their verdict skipped).
    let unreachable_rounds = Arc::new(AtomicU64::new(0));
    // The crash scenario has acted once CARLA was killed, the spot one once the node was
    // drained; the others have nothing to do.
    let acted = Arc::new(AtomicBool::new(
        args.scenario != Scenario::Crash && args.scenario != Scenario::Spot,
    ));
    let reclaim = (args.scenario == Scenario::Spot)
        .then(|| crate::reclaim::Reclaim::spawn(kubeconfig.clone(), submission, acted.clone()));
    let reclaim_cue = reclaim.as_ref().map(|r| r.cue());
    // When the participant cancelled (the cancel scenario), to time how long the Jobs outlive it.
    let cancelled_at: Arc<std::sync::Mutex<Option<Instant>>> = Arc::default();
    let fake = stack.fake_evalai.as_ref().map(|f| f.url());
    let outage = stack
        .kube
        .as_ref()
        .map(|k| k.outage())
        .filter(|_| args.kube_outage_minutes > 0.0);
    let outage_for = Duration::from_secs_f64(args.kube_outage_minutes * 60.0 * args.time_scale);
    let outage_minutes = args.kube_outage_minutes;
    let many = arrivals.len() > 1;
    let on_event = {
        let rounds = rounds.clone();
        let unreachable_rounds = unreachable_rounds.clone();
        let acted = acted.clone();
        let cancelled_at = cancelled_at.clone();
        let scenario = args.scenario;
        let cancel_after = args.cancel_after_round;
        let reclaim_cue = reclaim_cue.clone();
        Arc::new(move |event: &HistoryEvent| {
            if many {
                // Many executions: the per-round lines of each would drown the summary.
                return;
            }
            if event.event_type == EventType::TaskStateEntered {
                let name = event.state_name().unwrap_or_default();
                if name == "Monitor" {
                    let n = rounds.fetch_add(1, Ordering::SeqCst) + 1;
                    if let (1, Some(outage)) = (n, &outage) {
                        outage.fail_for(outage_for);
                        say(
                            started,
                            format!("the cluster's API answers 500 for {outage_minutes} minutes (scaled)"),
                        );
                    }
                    // From the first round on, until CARLA was up to be killed (a busy machine
                    // may start it after the first round).
                    if !acted.load(Ordering::SeqCst) && act(scenario, n) {
                        acted.store(true, Ordering::SeqCst);
                    }
                } else {
                    say(started, format!("stage {name}"));
                }
            }
            if event.event_type == EventType::TaskStateExited
                && event.state_name() == Some("Monitor")
            {
                let output = &event.details["output"]["run"]["monitor"];
                let unreachable = if output["unreachable_since"].is_null() {
                    ""
                } else {
                    unreachable_rounds.fetch_add(1, Ordering::SeqCst);
                    " (cluster unreachable: verdict skipped)"
                };
                // The cancel comes after a round (the first read the status on EvalAI): from
                // then on the cancel sweep notices it, or a partial update's own read.
                if scenario == Scenario::Cancel && output["rounds"] == cancel_after {
                    if let Ok(mut at) = cancelled_at.lock() {
                        at.get_or_insert_with(Instant::now);
                    }
                    cancel_on(fake.as_deref(), submission);
                }
                // A route is under way: the node goes now (once; the watcher ignores more).
                if let Some(cue) = reclaim_cue
                    .as_ref()
                    .filter(|_| output["progress"][0].as_u64() >= Some(1))
                {
                    cue.notify_one();
                }
                say(
                    started,
                    format!(
                        "monitor round {}: {} routes {}/{}{unreachable}",
                        output["rounds"],
                        output["state"],
                        output["progress"][0],
                        output["progress"][1]
                    ),
                );
            }
        }) as local_stepfunctions::EventCallback
    };
    let executor = Executor::new(
        tasks,
        Options {
            time_scale: args.time_scale,
            deadline: Some(Duration::from_secs(args.timeout)),
            on_event: Some(on_event),
            // The handlers run in-process at real speed, and the shared EvalAI budget is a
            // real minute's requests: a Lambda's timeout is not scaled (its waits are).
            scale_invocation_timeouts: false,
            ..Options::default()
        },
    )
    .map_err(|e| anyhow::anyhow!("{e}"))?;
    late.bind(executor.clone());
    // Step Functions' "Execution Status Change" events go to Finalize as the reaper, as the
    // deployment's EventBridge rule sends them.
    let reaper = spawn_reaper(&executor, reaper_deps);
    // S3's events and the cancel sweep wake the waiting execution, as in the deployment.
    let relays = crate::relay::spawn(
        &stack.sdk,
        &local_stack::stack::app_template(&settings),
        &config,
        executor.clone(),
        args.time_scale,
        !args.no_wake,
    )
    .await?;
    // All at once, as EvalAI's messages come: each one's place in the queue is when EvalAI
    // received it (`submitted_at`), the order of `arrivals`.
    let mut executions = Vec::new();
    for (id, team) in &arrivals {
        let input = sqs_round_trip(&stack, challenge, phase, *id, image).await?;
        if !many {
            say(
                started,
                format!("message for submission {id} received from SQS; Pipe output {input}"),
            );
        }
        let execution = executor
            .start(&machine, &format!("local-{id}"), input)
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        executions.push((*id, *team, execution));
    }
    if args.scenario == Scenario::Stop {
        stop_after_first_round(&executor, executions[0].2.arn(), &rounds, &acted);
    }
    if many {
        say(
            started,
            format!(
                "{} submissions from {} teams arrived",
                arrivals.len(),
                teams.len()
            ),
        );
    }
    let mut results = Vec::new();
    let mut chains = Vec::new();
    for (id, team, execution) in executions {
        let (result, lengths) = follow(&executor, execution.wait().await).await;
        chains.push(lengths);
        if many {
            say(
                started,
                format!(
                    "submission {id} (team {team}): execution {}",
                    result.status.as_str()
                ),
            );
        }
        results.push(result);
    }
    let ended_without_finalize = results
        .iter()
        .filter(|r| {
            let status = local_stack::events::execution_status(Some(r.status));
            lb_domain::reaper::REAPED_STATUSES.contains(&status)
        })
        .count();
    let reaped = reaper.collect(ended_without_finalize).await;
    let result = results.remove(0);
    let ended = Instant::now();
    let logs = agent_logs(
        &stack.sdk,
        &settings_bucket(&settings, args.leaderboard),
        submission,
        args.workers,
    )
    .await;
    let reclaim = match reclaim {
        Some(watcher) => {
            let mut report = watcher.finish().await;
            crate::reclaim::count_route_runs(&logs, &mut report);
            Some(report)
        }
        None => None,
    };
    let wake_messages = relays.wake_messages.load(Ordering::Relaxed);
    let sweep_wakes = relays.sweep_wakes.load(Ordering::Relaxed);
    drop(relays);

    // The summary: one report, printed for people and written with --report for tests.
    let on_fake = stack
        .fake_evalai
        .as_ref()
        .and_then(|fake| fake.submission(submission));
    let status_on_evalai = match (&stack.fake_evalai, &on_fake) {
        (Some(_), Some(s)) => s.status.clone(),
        (Some(_), None) => String::new(),
        // Another EvalAI: ask it, with the client the functions use.
        (None, _) => match evalai.submission(submission).await {
            Ok(s) => s.status.as_str().to_string(),
            Err(e) => format!("(unknown: {e})"),
        },
    };
    let bucket = settings_bucket(&settings, args.leaderboard);
    let expected = args.scenario.expected();
    let queue = stack.fake_evalai.as_ref().map(|fake| {
        crate::queue_report::report(&fake.requests(), &arrivals, |id| {
            fake.submission(id)
                .map(|s| (s.status.clone(), s.files.stderr.clone()))
        })
    });
    let latency = match (args.latency, &stack.fake_evalai) {
        (true, Some(fake)) => {
            let log = std::fs::read_to_string(&record_log).unwrap_or_default();
            Some(crate::latency::measure(&log, &fake.requests(), submission))
        }
        _ => None,
    };
    let report = RunReport {
        scenario: format!("{:?}", args.scenario),
        expected,
        ok: acted.load(Ordering::SeqCst)
            && reclaim
                .as_ref()
                .is_none_or(crate::reclaim::ReclaimReport::as_expected)
            && status_on_evalai == expected
            && queue
                .as_ref()
                .is_none_or(|q| !many || q.submissions.iter().all(|s| s.status == expected)),
        execution: result.status.as_str().to_string(),
        history_events: chains[0].iter().copied().max().unwrap_or_default(),
        executions: chains[0].len(),
        rounds: rounds.load(Ordering::SeqCst),
        state_transitions: result
            .history
            .iter()
            .filter(|e| e.event_type.as_str().ends_with("StateEntered"))
            .count(),
        error: result
            .error
            .as_ref()
            .map(|e| format!("{e}: {}", result.cause.clone().unwrap_or_default())),
        caught_error: result
            .output
            .as_ref()
            .and_then(lb_domain::finalize::caught_error)
            .map(|c| clean(&c)),
        evalai_status: status_on_evalai,
        evalai_stderr: on_fake
            .as_ref()
            .and_then(|s| s.files.stderr.clone())
            .filter(|e| !e.trim().is_empty()),
        evalai_stdout: on_fake.as_ref().and_then(|s| s.files.stdout.clone()),
        scores: on_fake
            .as_ref()
            .and_then(|s| s.leaderboard.first())
            .map(|row| row.result.clone()),
        merged: merged_summary(&stack.sdk, &bucket, submission).await,
        simulator_gpus: simulator_gpus(&stack.sdk, &bucket, submission, args.workers).await,
        agent_gpus: agent_gpus(&logs),
        reclaim,
        wake_messages,
        sweep_wakes,
        unreachable_rounds: unreachable_rounds.load(Ordering::SeqCst),
        // Finalize deletes the Jobs in the foreground: when the execution ends, they are gone.
        cancel_to_end_seconds: cancelled_at
            .lock()
            .ok()
            .and_then(|at| *at)
            .map(|at| ended.saturating_duration_since(at).as_secs_f64()),
        stages: stage_times(&result.history),
        results: format!("s3://{bucket}/{submission}/"),
        pod_logs: stack.workdir.path().join("pods"),
        seconds: started.elapsed().as_secs_f64(),
        queue,
        reaped,
        left_behind: left_behind(
            &stack.sdk,
            &settings,
            args.leaderboard,
            &kubeconfig,
            (arrivals[0].1, submission),
        )
        .await,
    };
    report.print(&args, &stack.moto.endpoint(), latency.as_ref(), many);
    if let Some(path) = &args.report {
        std::fs::write(path, serde_json::to_string_pretty(&report)?)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    let ok = report.ok;
    if args.keep {
        outln!(
            "\nthe stack stays up (kubeconfig {}); Ctrl-C to stop",
            kubeconfig.display()
        );
        let _ = tokio::signal::ctrl_c().await;
    }
    if ok {
        outln!(
            "OK: the {:?} scenario ended {expected} as expected",
            args.scenario
        );
        Ok(0)
    } else {
        outln!(
            "UNEXPECTED: the {:?} scenario should end {expected}",
            args.scenario
        );
        Ok(1)
    }
}

/// The most executions one run is followed through (72 hours at the least round interval
/// take fewer than 100).
const MAX_CHAIN: usize = 200;

/// An execution's result followed through the executions its run continued as: how the last
/// one ended, with every history in order (for the stages); and each history's length.
async fn follow(
    executor: &Executor,
    mut result: local_stepfunctions::ExecutionResult,
) -> (local_stepfunctions::ExecutionResult, Vec<usize>) {
    let mut lengths = vec![result.history.len()];
    while lengths.len() < MAX_CHAIN {
        let next = (result.status == local_stepfunctions::Status::Succeeded)
            .then_some(result.output.as_ref())
            .flatten()
            .and_then(lb_domain::history::continued_as)
            .map(str::to_owned);
        let Some(next) = next else { break };
        let Some(mut continued) = executor.wait_for(&next).await else {
            break;
        };
        lengths.push(continued.history.len());
        let mut history = std::mem::take(&mut result.history);
        history.append(&mut continued.history);
        continued.history = history;
        result = continued;
    }
    (result, lengths)
}

/// Each team's number of submissions, checked against --submissions.
fn team_sizes(args: &LocalRun) -> anyhow::Result<Vec<u32>> {
    if args.teams.is_empty() {
        return Ok(vec![args.submissions]);
    }
    let total: u32 = args.teams.iter().sum();
    if total != args.submissions {
        bail!(
            "--teams {:?} sends {total} submissions, --submissions says {}",
            args.teams,
            args.submissions
        );
    }
    if args.teams.len() > 20 {
        bail!("--teams: at most 20 teams");
    }
    Ok(args.teams.clone())
}

/// The GPU each attempt of each pair's simulator rendered on, by pair, as its log in S3 notes
/// them (`simulator <ID> attempt <N>: rendering on GPU <index>`).
async fn simulator_gpus(
    sdk: &aws_config::SdkConfig,
    bucket: &str,
    submission: u64,
    pairs: u32,
) -> BTreeMap<u32, Vec<u32>> {
    let logs = pair_logs(
        sdk,
        bucket,
        submission,
        pairs,
        lb_domain::protocol::simulator_log,
    )
    .await;
    (1..)
        .zip(logs)
        .map(|(pair, text)| {
            let indices: Vec<u32> = text
                .lines()
                .filter_map(|line| {
                    line.split_once(": rendering on GPU ")?
                        .1
                        .trim()
                        .parse()
                        .ok()
                })
                .collect();
            (pair, indices)
        })
        .collect()
}

/// The GPU index of each attempt's own GPU, by pair, as its agent's log notes it (`agent <ID>
/// attempt <N>: the pair's GPU is <UUID>`), the UUIDs being the local node's.
fn agent_gpus(logs: &[String]) -> BTreeMap<u32, Vec<u32>> {
    let mut gpus = BTreeMap::new();
    for (pair, log) in (1..).zip(logs) {
        let indices: Vec<u32> = log
            .lines()
            .filter_map(|line| {
                let uuid = line.split_once(": the pair's GPU is ")?.1.trim();
                (0..local_kube::UNMODELLED_GPUS).find(|&i| local_kube::gpu_uuid(i) == uuid)
            })
            .collect();
        gpus.insert(pair, indices);
    }
    gpus
}

/// Each pair's agent log in S3 (`logs/agent/agent<ID>/agent.log`), which every new pod of the
/// pair continues.
async fn agent_logs(
    sdk: &aws_config::SdkConfig,
    bucket: &str,
    submission: u64,
    pairs: u32,
) -> Vec<String> {
    let agent_log = |pair| format!("{}/agent.log", lb_domain::protocol::agent_logs_dir(pair));
    pair_logs(sdk, bucket, submission, pairs, agent_log).await
}

/// One log of each pair from S3 (`logs/<rel(pair)>`), in pair order; empty when missing.
async fn pair_logs(
    sdk: &aws_config::SdkConfig,
    bucket: &str,
    submission: u64,
    pairs: u32,
    rel: impl Fn(u32) -> String,
) -> Vec<String> {
    let mut logs = Vec::new();
    for pair in 1..=pairs {
        let key = format!(
            "{submission}/{}/{}",
            lb_domain::protocol::LOGS_DIR,
            rel(pair)
        );
        let object = lb_aws::s3_client(sdk)
            .get_object()
            .bucket(bucket)
            .key(key)
            .send()
            .await;
        let text = match object {
            Ok(object) => match object.body.collect().await {
                Ok(bytes) => String::from_utf8_lossy(&bytes.into_bytes()).into_owned(),
                Err(_) => String::new(),
            },
            Err(_) => String::new(),
        };
        logs.push(text);
    }
    logs
}

/// `agent_results.json` summed up: its records and how many each route has (Leaderboard 1.0
/// runs every route 5 times under one id).
async fn merged_summary(
    sdk: &aws_config::SdkConfig,
    bucket: &str,
    submission: u64,
) -> Option<Merged> {
    let object = lb_aws::s3_client(sdk)
        .get_object()
        .bucket(bucket)
        .key(format!(
            "{submission}/{}",
            lb_domain::protocol::derived::MERGED
        ))
        .send()
        .await
        .ok()?;
    let bytes = object.body.collect().await.ok()?.into_bytes();
    let merged: Value = serde_json::from_slice(&bytes).ok()?;
    let records = merged["_checkpoint"]["records"].as_array()?;
    let mut per_route: BTreeMap<&str, usize> = BTreeMap::new();
    for record in records {
        *per_route
            .entry(record["route_id"].as_str().unwrap_or_default())
            .or_default() += 1;
    }
    Some(Merged {
        records: records.len(),
        routes: per_route.len(),
        per_route: per_route.values().copied().collect(),
    })
}

/// The reaper's deliveries and what it answered.
struct Reaper {
    answers: tokio::sync::mpsc::UnboundedReceiver<Value>,
}

impl Reaper {
    /// The answers to the first `count` ended executions (bounded: a reaper that never
    /// answers is reported as such, not waited on forever).
    async fn collect(mut self, count: usize) -> Vec<Value> {
        let mut answers = Vec::new();
        while answers.len() < count {
            match tokio::time::timeout(Duration::from_secs(600), self.answers.recv()).await {
                Ok(Some(answer)) => answers.push(answer),
                Ok(None) | Err(_) => {
                    answers.push(serde_json::json!({"error": "the reaper did not answer"}));
                    break;
                }
            }
        }
        answers
    }
}

/// Delivers every execution's status change to `finalize` (which leaves alone those that
/// reached it) and keeps the answers of those that ended without it.
fn spawn_reaper(
    executor: &Executor,
    finalize: Arc<finalize::Deps<local_stack::events::LateCallbacks>>,
) -> Reaper {
    let mut changes = executor.status_changes();
    let (tx, answers) = tokio::sync::mpsc::unbounded_channel();
    tokio::spawn(async move {
        while let Some(event) = changes.recv().await {
            let status = event["detail"]["status"]
                .as_str()
                .and_then(|s| s.parse().ok());
            if !status.is_some_and(|s| lb_domain::reaper::REAPED_STATUSES.contains(&s)) {
                continue;
            }
            let answer = match lb_pipeline::serve::call(&*finalize, event).await {
                Ok(out) => out,
                Err(e) => serde_json::json!({"error": e.chain()}),
            };
            let _ = tx.send(answer);
        }
    });
    Reaper { answers }
}

/// Stops execution `arn` once its first Monitor round began (the stop scenario's act).
fn stop_after_first_round(
    executor: &Executor,
    arn: &str,
    rounds: &Arc<AtomicU64>,
    acted: &Arc<AtomicBool>,
) {
    let (executor, arn, rounds, acted) = (
        executor.clone(),
        arn.to_string(),
        rounds.clone(),
        acted.clone(),
    );
    tokio::spawn(async move {
        while rounds.load(Ordering::SeqCst) < 1 {
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        // After the round: the run has Jobs and its team a place.
        tokio::time::sleep(Duration::from_secs(2)).await;
        if executor.stop(&arn) {
            acted.store(true, Ordering::SeqCst);
        }
    });
}

/// What an ended run left: its Jobs, its team's places, its record's status.
async fn left_behind(
    sdk: &aws_config::SdkConfig,
    settings: &lb_domain::settings::Settings,
    leaderboard: Leaderboard,
    kubeconfig: &std::path::Path,
    (team, submission): (u64, u64),
) -> crate::report::LeftBehind {
    let mut left = crate::report::LeftBehind::default();
    if let Ok(cluster) = lb_cluster::Cluster::from_kubeconfig(kubeconfig, None).await {
        left.jobs = cluster
            .list(&submission.to_string())
            .await
            .ok()
            .map(|(jobs, _)| jobs.len());
    }
    let dynamo = aws_sdk_dynamodb::Client::new(sdk);
    let queue =
        lb_aws::admission::AdmissionTable::new(dynamo.clone(), local_stack::stack::ADMISSION_TABLE);
    if let Ok(holds) = queue.holds(leaderboard.as_str()).await {
        left.places_held = Some(holds.iter().map(|(_, h)| h.len()).sum());
    }
    if let Some(table) = settings
        .leaderboards
        .get(&leaderboard)
        .map(|l| &l.submissions_table)
    {
        let records = lb_aws::dynamo::SubmissionsTable::new(dynamo, table);
        if let Ok(Some(standing)) = records.standing(team, submission).await {
            left.record_status = standing.status.map(|s| s.as_str().to_owned());
        }
        if let Ok(Some(item)) = records.get(team, submission).await {
            let number = |key: &str| item.get(key)?.as_n().ok()?.parse::<u64>().ok();
            left.recordings = number("recordings_found").zip(number("recordings_expected"));
            let amount = |key: &str| item.get(key)?.as_n().ok()?.parse::<f64>().ok();
            left.usage = number("gpu_seconds").map(|gpu_seconds| {
                serde_json::json!({
                    "gpu_seconds": gpu_seconds,
                    "spot": number("gpu_seconds_spot"),
                    "run_again": number("gpu_seconds_run_again"),
                    "lost_to_reclaims": number("seconds_lost_to_reclaims"),
                    "cost_usd": amount("cost_usd"),
                    "orchestration_usd": amount("orchestration_usd"),
                    "state_transitions": number("state_transitions"),
                })
            });
        }
    }
    left
}

fn settings_bucket(settings: &lb_domain::settings::Settings, leaderboard: Leaderboard) -> String {
    settings
        .leaderboards
        .get(&leaderboard)
        .map(|l| l.bucket.clone())
        .unwrap_or_default()
}

/// A handler's result as Lambda reports it to Step Functions.
fn lambda(result: Result<Value, FnError>) -> Result<Value, TaskError> {
    result.map_err(|e| TaskError::lambda(e.name(), e.chain()))
}

/// The scenario's intervention at monitor round `n`; `false` when it could not be done.
fn act(scenario: Scenario, n: u64) -> bool {
    if scenario != Scenario::Crash {
        return true;
    }
    // This run's own CARLA (a descendant of this process: local-kube runs in it), never
    // another local run's beside it; of this run's, the one on the lowest port.
    let Some((pid, port)) = own_carla() else {
        outln!("           scenario: round {n}: no CARLA of this run to kill");
        return false;
    };
    let killed = std::process::Command::new("kill")
        .args(["-KILL", &pid.to_string()])
        .status()
        .is_ok_and(|s| s.success());
    outln!("           scenario: round {n}: CARLA on port {port} killed: {killed}");
    killed
}

/// The process id and RPC port of this process's descendant CARLA (`./CarlaUE4.sh ...`, not
/// the sidecar that wraps it) on the lowest port, read from `/proc`.
fn own_carla() -> Option<(u32, u16)> {
    let mut parent = std::collections::HashMap::new();
    let mut carla = Vec::new();
    for entry in std::fs::read_dir("/proc").ok()?.flatten() {
        let Some(pid) = entry
            .file_name()
            .to_str()
            .and_then(|n| n.parse::<u32>().ok())
        else {
            continue;
        };
        let Ok(stat) = std::fs::read_to_string(entry.path().join("stat")) else {
            continue;
        };
        // `pid (comm) state ppid ...`: comm may hold spaces and parentheses.
        let ppid = stat
            .rsplit_once(')')
            .and_then(|(_, rest)| rest.split_whitespace().nth(1))
            .and_then(|p| p.parse::<u32>().ok());
        if let Some(ppid) = ppid {
            parent.insert(pid, ppid);
        }
        let argv = std::fs::read(entry.path().join("cmdline")).unwrap_or_default();
        let mut args = argv.split(|b| *b == 0).map(String::from_utf8_lossy);
        if args.next().as_deref() == Some("./CarlaUE4.sh") {
            let port = args.find_map(|a| {
                a.strip_prefix("-carla-rpc-port=")
                    .and_then(|p| p.parse().ok())
            });
            carla.push((pid, port.unwrap_or(u16::MAX)));
        }
    }
    let me = std::process::id();
    let ours = |mut pid: u32| {
        while let Some(&up) = parent.get(&pid) {
            if up == me {
                return true;
            }
            pid = up;
        }
        false
    };
    carla
        .into_iter()
        .filter(|(pid, _)| ours(*pid))
        .min_by_key(|(_, port)| *port)
}

/// The participant cancels on the fake EvalAI (its admin endpoint, as the participant's
/// button would), without holding up the executor's event callback.
fn cancel_on(fake: Option<&str>, submission: u64) {
    if let Some(url) = fake {
        let url = format!("{url}/_admin/submissions/{submission}/cancel");
        std::thread::spawn(move || {
            let status = std::process::Command::new("curl")
                .args(["-s", "-o", "/dev/null", "-X", "POST", &url])
                .status();
            outln!("           scenario: the participant cancels ({status:?})");
        });
    }
}

/// Seconds spent in each state, summed over its visits.
fn stage_times(history: &[HistoryEvent]) -> Vec<(String, f64)> {
    let mut out: Vec<(String, f64)> = Vec::new();
    let mut entered: Option<(String, f64)> = None;
    for event in history {
        if event.event_type.is_state_entered() {
            entered = event.state_name().map(|n| (n.to_string(), seconds(event)));
        } else if event.event_type.is_state_exited() {
            if let Some((name, at)) = entered.take() {
                let seconds = seconds(event) - at;
                match out.iter_mut().find(|(n, _)| *n == name) {
                    Some((_, total)) => *total += seconds,
                    None => out.push((name, seconds)),
                }
            }
        }
    }
    out
}

fn seconds(event: &HistoryEvent) -> f64 {
    event.timestamp.unix_timestamp_nanos() as f64 / 1e9
}

/// Puts EvalAI's message on a moto SQS queue and takes it off as the EventBridge Pipe does:
/// the deployed input template applied to the record, handed over as a one-element batch.
async fn sqs_round_trip(
    stack: &Stack,
    challenge: u64,
    phase: u64,
    submission: u64,
    image: &str,
) -> anyhow::Result<Value> {
    let sqs = aws_sdk_sqs::Client::new(&stack.sdk);
    // The queue `infra/app.yaml` declares, which the stack provisioned.
    let queue = sqs
        .get_queue_url()
        .queue_name(local_stack::stack::submissions_queue())
        .send()
        .await?;
    let url = queue.queue_url().context("no queue url")?.to_string();
    // As EvalAI publishes a new submission: string challenge and phase ids, int submission id.
    let body = json!({
        "challenge_pk": challenge.to_string(),
        "phase_pk": phase.to_string(),
        "submission_pk": submission,
        "is_static_dataset_code_upload_submission": false,
        "submitted_image_uri": image,
    });
    sqs.send_message()
        .queue_url(&url)
        .message_body(body.to_string())
        .send()
        .await?;
    local_stack::pipe::poll(&sqs, &url, 1, 5)
        .await?
        .context("the message did not arrive")
}
