//! `lbctl local run`: one submission from the SQS message to the final scores on this machine,
//! through the deployed state machine definition, the real handlers, Job templates and sidecar.
//! What differs per scenario is in `crate::scenario`; the handlers' wiring in `crate::wiring`.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use clap::Args;
use fake_evalai::Fixture;
use lb_domain::results::Leaderboard;
use local_stack::events::LateCallbacks;
use local_stack::stack::{LOCAL_SETTINGS, WAKE_TABLE};
use local_stack::workloads::{Behaviour, Binaries};
use local_stack::{EvalAi, Stack};

use crate::latency::Latency;
use crate::report::{Merged, RunReport};
use crate::scenario::{Begin, Findings, Rehearsal, Scenario};
use crate::wiring::{Handlers, Pace};
use cli::{clean, outln};
use local_stepfunctions::{
    EventType, Execution, ExecutionResult, Executor, HistoryEvent, Options, StateMachine,
};
use serde_json::{json, Value};

/// The deployed definition, embedded so `lbctl` runs from anywhere.
const DEFINITION: &str = include_str!("../../../statemachine/submission.asl.json");

/// `lbctl local run` options.
#[derive(Debug, Clone, Args)]
pub struct LocalRun {
    /// What to rehearse.
    #[arg(long, value_enum, default_value = "happy")]
    pub scenario: Scenario,
    /// Simulator-agent pairs.
    #[arg(long, default_value_t = 4)]
    pub workers: u32,
    /// The Kubernetes the Jobs run on: local-kube (embedded, fast), or the real control plane
    /// of the pinned release (`make real-kube` builds it) with local-kube's process runner as
    /// the kubelet of its GPU nodes.
    #[arg(long, value_enum, default_value = "local")]
    pub kube: KubeKind,
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
    #[arg(long, default_value_t = lb_domain::run::history::EXECUTION_BUDGET, value_parser = clap::value_parser!(u64).range(lb_domain::run::history::MIN_BUDGET..=lb_domain::run::history::EXECUTION_BUDGET))]
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

/// The Kubernetes of a local run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum KubeKind {
    /// local-kube: one node, its own API server, job controller and scheduler.
    Local,
    /// The real kube-apiserver, Job controller and scheduler; local-kube runs the pods.
    Real,
}

fn say(started: Instant, text: impl AsRef<str>) {
    outln!(
        "[{:>6.1}s] {}",
        started.elapsed().as_secs_f64(),
        text.as_ref()
    );
}

/// Runs one local submission; the exit code is 0 only when it ended as the scenario expects.
pub async fn run(args: LocalRun) -> anyhow::Result<u8> {
    check(&args)?;
    let teams = team_sizes(&args)?;
    let started = Instant::now();
    let scenario: Arc<dyn Rehearsal> = Arc::from(args.scenario.rehearsal());
    let (stack, settings, kubeconfig) = set_up(&args, &*scenario, teams.len(), started).await?;
    let record_log = stack.workdir.path().join("record-writes.log");
    let (challenge, phase, arrivals) = submissions(&args, &stack, &teams, scenario.image())?;
    // The first is the one the summary describes in detail (and the scenarios act on).
    let submission = arrivals[0].0;
    let handlers = Handlers::load(&stack.sdk, kubeconfig.clone(), &pace(&args)).await?;
    // The summary reads the outcome from EvalAI with the functions' own client.
    let evalai = handlers.intake.evalai.clone();
    let late = LateCallbacks::default();
    let (tasks, reaper_deps) = handlers.task_map(&late);
    // The wake table's wait, on moto's DynamoDB; a continuation, on the executor.
    let tasks = local_stack::integrations::with_services(tasks, &stack.sdk, late.clone());
    let acted = Arc::new(AtomicBool::new(!scenario.acts()));
    let reaper_failures = Arc::new(AtomicU64::new(0));
    scenario.begin(&begin(
        &args,
        &stack,
        &settings,
        kubeconfig.clone(),
        (submission, &acted, &reaper_failures),
    ));
    let many = arrivals.len() > 1;
    let watch = Watch::default();
    // Many executions: the per-round lines of each would drown the summary.
    let on_event = (!many).then(|| watch.on_event(&args, &stack, &scenario, &acted, started));
    let executor = executor(&args, tasks, on_event)?;
    late.bind(executor.clone());
    // Step Functions' "Execution Status Change" events go to Finalize as the reaper, as the
    // deployment's EventBridge rule and Lambda's asynchronous invocation deliver them.
    let template = local_stack::stack::app_template(&settings);
    let scaled = (&template, args.time_scale);
    let mut reaper = crate::reaper::Reaper::spawn(&executor, reaper_deps, scaled, reaper_failures)?;
    // S3's events and the cancel sweep wake the waiting execution, as in the deployment.
    let relays = crate::relay::spawn(
        &stack.sdk,
        &template,
        &local_stack::stack::function_config(),
        executor.clone(),
        args.time_scale,
        !args.no_wake,
    )
    .await?;
    let at = (challenge, phase, scenario.image());
    let executions = start(&stack, &executor, at, (&arrivals, teams.len()), started).await?;
    reaper.schedule(scaled, executions[0].2.arn())?;
    scenario.started(&executor, executions[0].2.arn(), &watch.rounds, &acted);
    let (mut results, chains) = wait_all(&executor, executions, many, started).await;
    let reaped = reaper.collect(ended_without_finalize(&results)).await;
    let ended = Instant::now();
    let bucket = settings_bucket(&settings, args.leaderboard);
    let logs = agent_logs(&stack.sdk, &bucket, submission, args.workers).await;
    let findings = scenario.finish(&logs).await;
    let wakes = relays.stop();
    let ran = Ran {
        args: &args,
        stack: &stack,
        settings: &settings,
        kubeconfig: &kubeconfig,
        arrivals: &arrivals,
        result: results.remove(0),
        chains: &chains,
        reaped,
        logs: &logs,
        findings,
        watch: &watch,
        acted: acted.load(Ordering::SeqCst),
        wakes,
        times: (started, ended),
        record_log: &record_log,
        expected: scenario.expected(),
        audit_passes: scenario.audit_passes(),
    };
    let (report, latency) = ran.report(&evalai).await;
    finish(&args, &stack, (report, latency, many), &kubeconfig).await
}

/// The stack, the settings provisioned in it, and the local cluster with the images as the
/// scenario sets them up (its kubeconfig).
async fn set_up(
    args: &LocalRun,
    scenario: &dyn Rehearsal,
    teams: usize,
    started: Instant,
) -> anyhow::Result<(Stack, lb_domain::settings::Settings, PathBuf)> {
    let (mut stack, settings) = start_stack(args, teams, started).await?;
    let record_log = stack.workdir.path().join("record-writes.log");
    let kubeconfig = start_workloads(args, scenario, &mut stack, &settings, &record_log).await?;
    say(
        started,
        format!(
            "{} {} (kubeconfig {})",
            match args.kube {
                KubeKind::Local => "local Kubernetes API",
                KubeKind::Real => "real Kubernetes control plane",
            },
            stack
                .kube
                .as_ref()
                .map(|k| k.url())
                .or_else(|| stack.real.as_ref().map(|r| r.plane.server.clone()))
                .unwrap_or_default(),
            kubeconfig.display()
        ),
    );
    Ok((stack, settings, kubeconfig))
}

/// What the scenario is told before the executions start: the operator's kubeconfig (the
/// functions' own on local-kube), the namespace, the submission it acts on.
fn begin(
    args: &LocalRun,
    stack: &Stack,
    settings: &lb_domain::settings::Settings,
    kubeconfig: PathBuf,
    (submission, acted, reaper_failures): (u64, &Arc<AtomicBool>, &Arc<AtomicU64>),
) -> Begin {
    Begin {
        kubeconfig: stack
            .operator_kubeconfig()
            .map_or(kubeconfig, Path::to_path_buf),
        cordons: args.kube == KubeKind::Real,
        namespace: settings
            .leaderboards
            .get(&args.leaderboard)
            .map(|l| l.namespace.clone())
            .unwrap_or_default(),
        submission,
        fake_evalai: stack.fake_evalai.as_ref().map(|f| f.url()),
        cancel_after_round: args.cancel_after_round,
        acted: acted.clone(),
        reaper_failures: reaper_failures.clone(),
        store: lb_aws::s3::SubmissionStore::new(
            lb_aws::s3_client(&stack.sdk),
            settings_bucket(settings, args.leaderboard),
            submission,
        ),
    }
}

/// The embedded executor with the run's time scale and deadline.
fn executor(
    args: &LocalRun,
    tasks: local_stepfunctions::TaskMap,
    on_event: Option<local_stepfunctions::EventCallback>,
) -> anyhow::Result<Executor> {
    Executor::new(
        tasks,
        Options {
            time_scale: args.time_scale,
            deadline: Some(Duration::from_secs(args.timeout)),
            on_event,
            // The handlers run in-process at real speed, and the shared EvalAI budget is a
            // real minute's requests: a Lambda's timeout is not scaled (its waits are).
            scale_invocation_timeouts: false,
            ..Options::default()
        },
    )
    .map_err(|e| anyhow::anyhow!("{e}"))
}

/// The options no parser checks alone.
fn check(args: &LocalRun) -> anyhow::Result<()> {
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
    if args.teams.len() > 1 && args.evalai_url.is_some() {
        bail!("--teams needs the fake EvalAI (an external one has its own teams)");
    }
    Ok(())
}

/// The phase of the local settings and the fake's fixture: 1 is Leaderboard 2.0, 2 is 1.0.
fn local_phase(leaderboard: Leaderboard) -> u64 {
    match leaderboard {
        Leaderboard::V1 => 2,
        Leaderboard::V2 => 1,
    }
}

/// The submissions' namespace `infra/k8s` creates.
const REAL_NAMESPACE: &str = "leaderboard";

/// The local settings with the run's track, pacing and team limit.
fn settings_for(args: &LocalRun) -> anyhow::Result<Value> {
    let board = args.leaderboard.as_str();
    let mut settings: Value = serde_json::from_str(LOCAL_SETTINGS)?;
    let track = &mut settings["leaderboards"][board]["tracks"]["SENSORS"];
    track["routes"] = json!(args.routes);
    track["workers"] = json!(args.workers);
    // The Monitor's clock is real while the executor scales every wait: the least interval
    // between partial updates is scaled here, or a fast run would defer its updates and spin.
    let interval = args.partial_update_seconds.unwrap_or(
        (lb_domain::settings::PARTIAL_UPDATE_INTERVAL.as_secs_f64() * args.time_scale)
            .round()
            .max(1.0) as u64,
    );
    settings["leaderboards"][board]["partial_update_seconds"] = json!(interval);
    if args.kube == KubeKind::Real {
        // The namespace infra/k8s declares (Pod Security baseline, the pipeline's Role).
        for leaderboard in settings["leaderboards"]
            .as_object_mut()
            .into_iter()
            .flat_map(|l| l.values_mut())
        {
            leaderboard["namespace"] = json!(REAL_NAMESPACE);
        }
    }
    if let Some(limit) = args.team_limit {
        settings["leaderboards"][board]["team_limit"] = json!(limit);
    }
    // Another EvalAI has its own phase ids: its phase runs the chosen leaderboard's track.
    if let (Some(_), Some(p)) = (&args.evalai_url, args.phase) {
        settings["phases"][p.to_string()] = json!({"leaderboard": board, "track": "SENSORS"});
    }
    Ok(settings)
}

/// moto, EvalAI (the fake with `teams` teams, or another) and the provisioned settings.
async fn start_stack(
    args: &LocalRun,
    teams: usize,
    started: Instant,
) -> anyhow::Result<(Stack, lb_domain::settings::Settings)> {
    let settings = settings_for(args)?;
    let external = args.evalai_url.clone().map(|url| EvalAi::External {
        url,
        token: args.evalai_token.clone().unwrap_or_default(),
    });
    let stack = Stack::start(external.unwrap_or(EvalAi::Fake(Fixture::with_teams(teams))))
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
    Ok((stack, settings))
}

/// The local Kubernetes API and the images, as the scenario sets them up: the kubeconfig.
async fn start_workloads(
    args: &LocalRun,
    scenario: &dyn Rehearsal,
    stack: &mut Stack,
    settings: &lb_domain::settings::Settings,
    record_log: &Path,
) -> anyhow::Result<PathBuf> {
    let bins = Binaries::find()?;
    let once = stack.workdir.path().join("images").join("once");
    std::fs::create_dir_all(&once)?;
    let mut behaviour = Behaviour {
        route_seconds: args.route_seconds,
        node_gpus: args.gpus,
        ..Behaviour::default()
    };
    scenario.set_up(&mut behaviour, &once);
    if args.latency {
        behaviour.evaluator_env.insert(
            "FAKE_EVALUATOR_RECORD_LOG".into(),
            record_log.display().to_string(),
        );
    }
    // The participant's image is in the registry under its tag (Intake pins the Jobs to its
    // digest); the unpullable one is there too, but no node can pull it.
    let image = scenario.image();
    local_stack::registry::push(&stack.sdk, image).await?;
    let repository = lb_jobs::parse_image(image)
        .map(|r| format!("{}/{}", r.domain.unwrap_or_default(), r.path))
        .unwrap_or_default();
    let unpullable: &[&str] = if image == crate::scenario::IMAGE {
        &[]
    } else {
        &[repository.as_str()]
    };
    match args.kube {
        KubeKind::Local => stack.start_workloads(settings, &bins, &behaviour, unpullable),
        KubeKind::Real => stack.start_real_workloads(settings, &bins, &behaviour, unpullable),
    }
    .map_err(|e| anyhow::anyhow!("{e}"))?;
    stack.kubeconfig.clone().context("no kubeconfig")
}

/// Each submission with its team, in order of arrival.
type Arrivals = Vec<(u64, u64)>;

/// The submissions on EvalAI (each team's, in order, on the fake; the one named on another):
/// the challenge, the phase, and each submission with its team.
fn submissions(
    args: &LocalRun,
    stack: &Stack,
    teams: &[u32],
    image: &str,
) -> anyhow::Result<(u64, u64, Arrivals)> {
    let phase = local_phase(args.leaderboard);
    match (
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
                            submission_metadata: None,
                        })
                        .map_err(|e| anyhow::anyhow!("{e}"))?;
                    arrivals.push((new.id, team));
                }
            }
            Ok((1, phase, arrivals))
        }
        (None, Some(c), Some(p), Some(s)) => Ok((c, p, vec![(s, 0)])),
        _ => bail!("an external EvalAI needs --challenge, --phase and --submission"),
    }
}

/// The rehearsal's pace: shorter sidecar timers, the autoscaler believed at once.
fn pace(args: &LocalRun) -> Pace {
    Pace {
        timers: lb_jobs::Timers {
            start_wait_seconds: 120,
            end_wait_seconds: 60,
            carla_ready_seconds: 60,
            poll_seconds: 1,
            max_idle_seconds: 5,
            logcopy_period_seconds: 1,
        },
        delete_wait: Duration::from_secs(60),
        // The autoscaler's word is believed after minutes on EKS; local-kube's is final at once.
        never_fits_grace: Some(Duration::from_secs(2)),
        history_budget: Some(args.history_budget),
    }
}

/// The deployed state machine, its function ARNs and wake table filled in.
fn machine() -> anyhow::Result<StateMachine> {
    let mut substitutions: HashMap<String, String> = ["Intake", "Launch", "Monitor", "Finalize"]
        .iter()
        .map(|f| {
            let arn = format!(
                "arn:aws:lambda:us-east-1:123456789012:function:{}",
                f.to_lowercase()
            );
            (format!("{f}FunctionArn"), arn)
        })
        .collect();
    substitutions.insert("WakeTable".into(), WAKE_TABLE.into());
    StateMachine::load(&serde_json::from_str(DEFINITION)?, &substitutions)
        .map_err(|e| anyhow::anyhow!("{e}"))
}

/// What the run watches of its executions: Monitor rounds, and those that found the cluster's
/// API out of reach (their verdict skipped).
#[derive(Default)]
struct Watch {
    rounds: Arc<AtomicU64>,
    unreachable_rounds: Arc<AtomicU64>,
}

impl Watch {
    /// Live progress, the outage from the first round, and the scenario's hooks at each round.
    fn on_event(
        &self,
        args: &LocalRun,
        stack: &Stack,
        scenario: &Arc<dyn Rehearsal>,
        acted: &Arc<AtomicBool>,
        started: Instant,
    ) -> local_stepfunctions::EventCallback {
        let (rounds, unreachable) = (self.rounds.clone(), self.unreachable_rounds.clone());
        let (scenario, acted) = (scenario.clone(), acted.clone());
        let outage = stack
            .kube
            .as_ref()
            .map(|k| k.outage())
            .filter(|_| args.kube_outage_minutes > 0.0);
        let outage_for = Duration::from_secs_f64(args.kube_outage_minutes * 60.0 * args.time_scale);
        let outage_minutes = args.kube_outage_minutes;
        Arc::new(move |event: &HistoryEvent| {
            let name = event.state_name().unwrap_or_default();
            if event.event_type == EventType::TaskStateEntered && name != "Monitor" {
                say(started, format!("stage {name}"));
            } else if event.event_type == EventType::TaskStateEntered {
                let n = rounds.fetch_add(1, Ordering::SeqCst) + 1;
                if let (1, Some(outage)) = (n, &outage) {
                    outage.fail_for(outage_for);
                    say(
                        started,
                        format!(
                            "the cluster's API answers 500 for {outage_minutes} minutes (scaled)"
                        ),
                    );
                }
                if !acted.load(Ordering::SeqCst) && scenario.round_begins(n) {
                    acted.store(true, Ordering::SeqCst);
                }
            } else if event.event_type == EventType::TaskStateExited && name == "Monitor" {
                let output = &event.details["output"]["run"]["monitor"];
                let skipped = if output["unreachable_since"].is_null() {
                    ""
                } else {
                    unreachable.fetch_add(1, Ordering::SeqCst);
                    " (cluster unreachable: verdict skipped)"
                };
                scenario.round_ended(output);
                say(
                    started,
                    format!(
                        "monitor round {}: {} routes {}/{}{skipped}",
                        output["rounds"],
                        output["state"],
                        output["progress"][0],
                        output["progress"][1]
                    ),
                );
            }
        })
    }
}

/// Starts an execution per arrival, all at once, as EvalAI's messages come: each one's place
/// in the queue is when EvalAI received it (`submitted_at`), the order of `arrivals`.
async fn start(
    stack: &Stack,
    executor: &Executor,
    (challenge, phase, image): (u64, u64, &str),
    (arrivals, teams): (&[(u64, u64)], usize),
    started: Instant,
) -> anyhow::Result<Vec<(u64, u64, Execution)>> {
    let machine = machine()?;
    let mut executions = Vec::new();
    for (id, team) in arrivals {
        let input = sqs_round_trip(stack, challenge, phase, *id, image).await?;
        if arrivals.len() == 1 {
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
    if arrivals.len() > 1 {
        let count = arrivals.len();
        say(
            started,
            format!("{count} submissions from {teams} teams arrived"),
        );
    }
    Ok(executions)
}

/// Every execution's result, followed through its continuations, in arrival order; and each
/// one's history lengths.
async fn wait_all(
    executor: &Executor,
    executions: Vec<(u64, u64, Execution)>,
    many: bool,
    started: Instant,
) -> (Vec<ExecutionResult>, Vec<Vec<usize>>) {
    let mut results = Vec::new();
    let mut chains = Vec::new();
    for (id, team, execution) in executions {
        let (result, lengths) = follow(executor, execution.wait().await).await;
        chains.push(lengths);
        if many {
            let status = result.status.as_str();
            say(
                started,
                format!("submission {id} (team {team}): execution {status}"),
            );
        }
        results.push(result);
    }
    (results, chains)
}

/// How many executions ended without Finalize (the reaper answers for those).
fn ended_without_finalize(results: &[ExecutionResult]) -> usize {
    results
        .iter()
        .filter(|r| {
            let status = local_stack::events::execution_status(Some(r.status));
            lb_domain::run::reaper::REAPED_STATUSES.contains(&status)
        })
        .count()
}

/// Everything the summary is made of, once the run ended.
struct Ran<'a> {
    args: &'a LocalRun,
    stack: &'a Stack,
    settings: &'a lb_domain::settings::Settings,
    kubeconfig: &'a Path,
    arrivals: &'a [(u64, u64)],
    /// The first submission's execution, followed to its end.
    result: ExecutionResult,
    chains: &'a [Vec<usize>],
    reaped: Vec<Value>,
    logs: &'a [String],
    findings: Findings,
    watch: &'a Watch,
    /// The scenario did its act (or had none).
    acted: bool,
    /// Messages S3's events sent, and the sweep's wakes.
    wakes: (u64, u64),
    /// When the run started and when its executions ended.
    times: (Instant, Instant),
    record_log: &'a Path,
    expected: &'static str,
    /// Whether a finished run's recordings must pass the audit.
    audit_passes: bool,
}

impl Ran<'_> {
    /// The submission on the fake EvalAI, and its status there (or on another EvalAI, asked
    /// with the client the functions use).
    async fn on_evalai(
        &self,
        evalai: &lb_evalai::EvalAiClient,
    ) -> (Option<fake_evalai::SubmissionSnapshot>, String) {
        let submission = self.arrivals[0].0;
        let Some(fake) = &self.stack.fake_evalai else {
            let status = match evalai.submission(submission).await {
                Ok(s) => s.status.as_str().to_string(),
                Err(e) => format!("(unknown: {e})"),
            };
            return (None, status);
        };
        let on_fake = fake.submission(submission);
        let status = on_fake
            .as_ref()
            .map(|s| s.status.clone())
            .unwrap_or_default();
        (on_fake, status)
    }

    /// What the fake EvalAI saw: each submission's statuses and the requests (the queue
    /// report), and with `--latency` how long results took to reach it.
    fn on_fake_evalai(&self) -> (Option<crate::queue_report::QueueReport>, Option<Latency>) {
        let Some(fake) = &self.stack.fake_evalai else {
            return (None, None);
        };
        let requests = fake.requests();
        let queue = crate::queue_report::report(&requests, self.arrivals, |id| {
            fake.submission(id)
                .map(|s| (s.status.clone(), s.files.stderr.clone()))
        });
        let latency = self.args.latency.then(|| {
            let log = std::fs::read_to_string(self.record_log).unwrap_or_default();
            crate::latency::measure(&log, &requests, self.arrivals[0].0)
        });
        (Some(queue), latency)
    }

    /// What the first submission left: its Jobs, places, record.
    async fn left_behind(&self) -> crate::report::LeftBehind {
        let (submission, team) = self.arrivals[0];
        let (sdk, leaderboard) = (&self.stack.sdk, self.args.leaderboard);
        let at = (team, submission);
        let mut left = left_behind(sdk, self.settings, leaderboard, self.kubeconfig, at).await;
        left.registry_digest = registry_digest(sdk, self.args.scenario.rehearsal().image()).await;
        left
    }

    /// The run's report: what EvalAI shows, what the run left, and whether it is as expected;
    /// with the latencies measured (`--latency`).
    async fn report(self, evalai: &lb_evalai::EvalAiClient) -> (RunReport, Option<Latency>) {
        let (args, stack, submission) = (self.args, self.stack, self.arrivals[0].0);
        let many = self.arrivals.len() > 1;
        let (on_fake, status_on_evalai) = self.on_evalai(evalai).await;
        let bucket = settings_bucket(self.settings, args.leaderboard);
        let expected = self.expected;
        let (queue, latency) = self.on_fake_evalai();
        let left = self.left_behind().await;
        let reclaim = self.findings.reclaim;
        let ok = self.acted
            && reclaim
                .as_ref()
                .is_none_or(crate::reclaim::ReclaimReport::as_expected)
            && status_on_evalai == expected
            && audit_as_expected(expected, &left, self.audit_passes)
            && queue
                .as_ref()
                .is_none_or(|q| !many || q.all_ended(expected));
        let result = &self.result;
        let (started, ended) = self.times;
        let report = RunReport {
            scenario: format!("{:?}", args.scenario),
            expected,
            ok,
            execution: result.status.as_str().to_string(),
            history_events: self.chains[0].iter().copied().max().unwrap_or_default(),
            executions: self.chains[0].len(),
            rounds: self.watch.rounds.load(Ordering::SeqCst),
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
                .and_then(lb_domain::run::finalize::caught_error)
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
            agent_gpus: agent_gpus(self.logs),
            reclaim,
            wake_messages: self.wakes.0,
            sweep_wakes: self.wakes.1,
            unreachable_rounds: self.watch.unreachable_rounds.load(Ordering::SeqCst),
            // Finalize deletes the Jobs in the foreground: when the execution ends, they are
            // gone.
            cancel_to_end_seconds: self
                .findings
                .cancelled_at
                .map(|at| ended.saturating_duration_since(at).as_secs_f64()),
            stages: stage_times(&result.history),
            results: format!("s3://{bucket}/{submission}/"),
            pod_logs: stack.workdir.path().join("pods"),
            seconds: started.elapsed().as_secs_f64(),
            queue,
            reaped: self.reaped,
            left_behind: left,
        };
        (report, latency)
    }
}

/// A finished run's recordings pass the audit unless the scenario tampers with them (judged
/// when its record could be read: another EvalAI's team may not be the one assumed).
fn audit_as_expected(expected: &str, left: &crate::report::LeftBehind, passes: bool) -> bool {
    let audited = left.recordings.map(|(passed, needed)| passed == needed);
    expected != "finished" || left.record_status.is_none() || audited == Some(passes)
}

/// Prints and writes the report, keeps the stack up when asked: the exit code.
async fn finish(
    args: &LocalRun,
    stack: &Stack,
    (report, latency, many): (RunReport, Option<Latency>, bool),
    kubeconfig: &Path,
) -> anyhow::Result<u8> {
    report.print(args, &stack.moto.endpoint(), latency.as_ref(), many);
    if let Some(path) = &args.report {
        std::fs::write(path, serde_json::to_string_pretty(&report)?)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    if args.keep {
        outln!(
            "\nthe stack stays up (kubeconfig {}); Ctrl-C to stop",
            kubeconfig.display()
        );
        let _ = tokio::signal::ctrl_c().await;
    }
    let expected = report.expected;
    if report.ok {
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
            .and_then(lb_domain::run::history::continued_as)
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
        lb_domain::job::protocol::simulator_log,
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
    let agent_log = |pair| {
        format!(
            "{}/agent.log",
            lb_domain::job::protocol::agent_logs_dir(pair)
        )
    };
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
            lb_domain::job::protocol::LOGS_DIR,
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
            lb_domain::job::protocol::derived::MERGED
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

/// The digest the participant's tag names in the registry now.
async fn registry_digest(sdk: &aws_config::SdkConfig, image: &str) -> Option<String> {
    let reference = lb_jobs::parse_image(image).ok()?;
    let ecr = reference.ecr_tagged()?;
    let registry = lb_aws::ecr::Registry::new(sdk);
    match registry
        .digest_of((ecr.registry, ecr.region), ecr.repository, ecr.tag)
        .await
    {
        Ok(lb_aws::ecr::Lookup::Digest(digest)) => Some(digest),
        _ => None,
    }
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
        let namespace = settings
            .leaderboards
            .get(&leaderboard)
            .map(|l| &l.namespace);
        let cluster = match namespace {
            Some(ns) => cluster.with_namespace(ns),
            None => cluster,
        };
        left.jobs = cluster
            .list(&submission.to_string())
            .await
            .ok()
            .map(|(jobs, _)| jobs.len());
    }
    let store = lb_aws::s3::SubmissionStore::new(
        lb_aws::s3_client(sdk),
        settings_bucket(settings, leaderboard),
        submission,
    );
    left.status_objects = store.markers().await.ok().map(|m| m.len());
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
        if let Ok(Some(record)) = records.record(team, submission).await {
            left.record_status = Some(record.status_word.clone()).filter(|s| !s.is_empty());
            left.recordings = record.recordings;
            left.recordings_failed = record.recordings_failed.clone();
            left.usage = record.usage.map(|usage| {
                serde_json::json!({
                    "gpu_seconds": usage.gpu_seconds,
                    "spot": usage.spot,
                    "run_again": usage.run_again,
                    "lost_to_reclaims": usage.lost,
                    "cost_usd": usage.dollars,
                    "orchestration_usd": usage.orchestration,
                    "state_transitions": record.state_transitions,
                    "log_bytes_stored": record.log_bytes_stored,
                    "uploads_refused": record.uploads_refused,
                    "image_digest": record.image_digest,
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
