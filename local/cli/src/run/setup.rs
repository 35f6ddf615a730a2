//! Setting a local run up: its settings, the stack and the workloads, the arrivals, the state
//! machine and the executor that runs it.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use fake_evalai::Fixture;
use lb_domain::results::Leaderboard;
use local_stack::stack::{LOCAL_SETTINGS, WAKE_TABLE};
use local_stack::workloads::{Behaviour, Binaries};
use local_stack::{EvalAi, Stack};

use crate::scenario::{Begin, Rehearsal};
use crate::wiring::Pace;
use local_stepfunctions::{Executor, Options, StateMachine};
use serde_json::{json, Value};

use super::*;

/// The stack, the settings provisioned in it, and the local cluster with the images as the
/// scenario sets them up (its kubeconfig).
pub(super) async fn set_up(
    args: &LocalRun,
    scenario: &dyn Rehearsal,
    teams: &[u32],
    started: Instant,
) -> anyhow::Result<(
    Stack,
    lb_domain::settings::Settings,
    PathBuf,
    std::sync::Arc<crate::emf::Collector>,
)> {
    let (mut stack, settings) = start_stack(args, teams.len(), started).await?;
    let record_log = record_log(&stack);
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
    let env = lbctl_env(&stack, &kubeconfig)?;
    say(
        started,
        format!(
            "lbctl against this stack: . {} (then lbctl top)",
            env.display()
        ),
    );
    // The functions' metrics documents: `--metrics`, else the run's working folder.
    let metrics_file =
        (args.metrics.clone()).unwrap_or_else(|| stack.workdir.path().join("metrics.jsonl"));
    let metrics = crate::emf::Collector::install(&metrics_file)?;
    Ok((stack, settings, kubeconfig, metrics))
}

/// Writes the environment that points `lbctl` at this stack (moto, its secrets and queue
/// table, the cluster): an operator's `lbctl top`, `list` or `watch` on the rehearsal.
fn lbctl_env(stack: &Stack, kubeconfig: &std::path::Path) -> anyhow::Result<PathBuf> {
    use local_stack::stack::{ADMISSION_TABLE, BUDGET_TABLE, SETTINGS_SECRET, TOKEN_SECRET};
    let mut vars = stack.moto.sdk_env();
    vars.push(("LB_SETTINGS_SECRET", SETTINGS_SECRET.into()));
    vars.push(("LB_EVALAI_TOKEN_SECRET", TOKEN_SECRET.into()));
    vars.push(("LB_ADMISSION_TABLE", ADMISSION_TABLE.into()));
    vars.push(("LB_BUDGET_TABLE", BUDGET_TABLE.into()));
    vars.push(("LB_KUBECONFIG", kubeconfig.display().to_string()));
    let text: String = vars
        .iter()
        .map(|(k, v)| format!("export {k}='{v}'\n"))
        .collect();
    let path = stack.workdir.path().join("lbctl.env");
    std::fs::write(&path, text)?;
    Ok(path)
}

/// What the scenario is told before the executions start: the operator's kubeconfig (the
/// functions' own on local-kube), the namespace, the submission it acts on.
pub(super) fn begin(
    args: &LocalRun,
    stack: &Stack,
    settings: &lb_domain::settings::Settings,
    kubeconfig: PathBuf,
    submission: u64,
    acted: &Arc<AtomicBool>,
    reaper_failures: &Arc<AtomicU64>,
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
        upgrader: stack.real.as_ref().map(|r| r.upgrader()),
    }
}

/// The embedded executor with the run's time scale and deadline.
pub(super) fn executor(
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

/// The phase of the local settings and the fake's fixture: 1 is Leaderboard 2.0, 2 is 1.0.
pub(super) fn local_phase(leaderboard: Leaderboard) -> u64 {
    match leaderboard {
        Leaderboard::V1 => 2,
        Leaderboard::V2 => 1,
    }
}

/// The submissions' namespace `infra/k8s` creates.
pub(super) const REAL_NAMESPACE: &str = "leaderboard";

/// The local settings with the run's track, pacing and team limit.
pub(super) fn settings_for(args: &LocalRun) -> anyhow::Result<Value> {
    let board = args.leaderboard.as_str();
    let mut settings: Value = serde_json::from_str(LOCAL_SETTINGS)?;
    let track = &mut settings["leaderboards"][board]["tracks"]["SENSORS"];
    track["routes"] = json!(args.routes);
    // The organisers' lengths of the fake evaluator's routes, one per route of this run (its
    // records repeat the fixture's, so the lengths repeat with them).
    if let Some(given) = track["route_lengths"]
        .as_array()
        .filter(|l| !l.is_empty())
        .cloned()
    {
        let each = (0..args.routes as usize).map(|n| given[n % given.len()].clone());
        track["route_lengths"] = Value::Array(each.collect());
    }
    track["workers"] = json!(args.workers);
    // The Monitor's clock is real while the executor scales every wait: the least interval
    // between partial updates is scaled here, or a fast run would defer its updates and spin.
    let interval = args.partial_update_seconds.unwrap_or(
        (lb_domain::settings::PARTIAL_UPDATE_INTERVAL.as_secs_f64() * args.time_scale)
            .round()
            .max(1.0) as u64,
    );
    settings["leaderboards"][board]["partial_update_seconds"] = json!(interval);
    // Likewise the window after a write in which a pod moves off a drained node: a route
    // lasts seconds here, so a window of minutes would move pods mid-route.
    let window = lb_domain::capacity::consolidation::MOVE_WINDOW_SECONDS as f64 * args.time_scale;
    settings["leaderboards"][board]["move_window_seconds"] = json!(window.round().max(1.0) as u64);
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
pub(super) async fn start_stack(
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
pub(super) async fn start_workloads(
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

/// Where the fake workloads log each record they write (for the latency measure).
pub(super) fn record_log(stack: &Stack) -> PathBuf {
    stack.workdir.path().join("record-writes.log")
}

/// The submissions EvalAI receives, in order: each (submission, team) of `teams` teams, to one
/// challenge phase, all with one image.
pub(super) struct Arrivals {
    pub challenge: u64,
    pub phase: u64,
    pub image: &'static str,
    pub each: Vec<(u64, u64)>,
    pub teams: usize,
}

/// The submissions on EvalAI (each team's, in order, on the fake; the one named on another).
pub(super) fn submissions(
    args: &LocalRun,
    stack: &Stack,
    teams: &[u32],
    image: &'static str,
) -> anyhow::Result<Arrivals> {
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
    .map(|(challenge, phase, each)| Arrivals {
        challenge,
        phase,
        image,
        each,
        teams: teams.len(),
    })
}

/// The rehearsal's pace: shorter sidecar timers, the autoscaler believed at once.
pub(super) fn pace(args: &LocalRun) -> Pace {
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

/// The deployed state machine as `make deploy` publishes it: version `version`'s definition,
/// naming that version of each function, and the wake table.
pub(crate) fn machine(version: u32) -> anyhow::Result<StateMachine> {
    let mut substitutions: HashMap<String, String> = ["Intake", "Launch", "Monitor", "Finalize"]
        .iter()
        .map(|f| {
            let arn = format!(
                "arn:aws:lambda:us-east-1:123456789012:function:{}:{version}",
                f.to_lowercase()
            );
            (format!("{f}FunctionArn"), arn)
        })
        .collect();
    substitutions.insert("WakeTable".into(), WAKE_TABLE.into());
    Ok(
        StateMachine::load(&serde_json::from_str(DEFINITION)?, &substitutions)
            .map_err(|e| anyhow::anyhow!("{e}"))?
            .with_name("submission"),
    )
}

/// Each team's number of submissions, checked against --submissions.
pub(super) fn team_sizes(args: &LocalRun) -> anyhow::Result<Vec<u32>> {
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
