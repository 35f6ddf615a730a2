//! `lbctl watch`: one submission, live, until it ends: its stage and place in the queue, its
//! pods and their restarts, the routes each worker has done, the last partial scores and what
//! EvalAI says; then a one-screen summary.

use std::fmt::Write as _;
use std::io::{IsTerminal, Write};
use std::time::{Duration, Instant};

use clap::Args;
use lb_aws::dynamo::RecordStatus;
use lb_aws::s3::SubmissionStore;
use lb_domain::cluster::disruption::Disruption;
use lb_domain::results::{read_worker_file, Leaderboard, WorkerFile, MAX_FILE_BYTES};
use lb_pipeline::cluster::Clusters;

use crate::deployment::evalai_id;
use crate::deployment::{clean, Deployment, DeploymentArgs, EvalAiTokenArgs, Record, ScanFilter};
use crate::error::{CliError, Result};
use crate::ops::queue_positions;

/// Longest watch (a 72-hour evaluation and its queue, with room).
const MAX_WATCH: Duration = Duration::from_secs(96 * 3600);
/// The scores a screen shows, of the EvalAI labels.
const SHOWN_SCORES: [&str; 3] = ["Driving score", "Route completion", "Infraction penalty"];

/// `lbctl watch` options.
#[derive(Debug, Clone, Args)]
#[command(after_help = "Examples:
  lbctl watch 4242                 # refreshes every 10 s until the submission ends
  lbctl watch 4242 --interval 60   # less often
  lbctl watch 4242 --once          # one screen and exit (scripts: add --json)

Pods come from the cluster of the submission's leaderboard (EKS, or LB_KUBECONFIG); EvalAI's
status through the token secret. What cannot be reached is said on the screen, not fatal.")]
pub struct Watch {
    /// EvalAI submission id.
    #[arg(value_parser = evalai_id())]
    pub submission: u64,
    /// Seconds between two screens.
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u64).range(1..=3600))]
    pub interval: u64,
    /// One screen, then exit.
    #[arg(long)]
    pub once: bool,
    /// One JSON object per screen instead of text.
    #[arg(long)]
    pub json: bool,
    /// Only this leaderboard (when the submission has records in several).
    #[arg(long, value_name = "LEADERBOARD")]
    pub leaderboard: Option<String>,
    #[command(flatten)]
    pub token: EvalAiTokenArgs,
    #[command(flatten)]
    pub deployment: DeploymentArgs,
}

/// What one look found.
#[derive(Debug, Clone, Default, serde::Serialize)]
struct Screen {
    submission_id: u64,
    leaderboard: String,
    team: String,
    track: String,
    stage: String,
    status: String,
    /// `status` when it is one of ours.
    #[serde(skip)]
    record_status: Option<RecordStatus>,
    queue_position: Option<usize>,
    queue_length: usize,
    started: String,
    ended: String,
    routes: String,
    workers: Vec<WorkerLine>,
    pods: Vec<PodLine>,
    pods_note: Option<String>,
    scores: Vec<(String, f64)>,
    evalai_status: String,
    error: Option<String>,
    /// GPU-hours and their price so far (`Usage::describe`).
    usage: Option<String>,
}

#[derive(Debug, Clone, serde::Serialize)]
struct WorkerLine {
    worker: u32,
    done: u64,
    total: u64,
    entry_status: Option<String>,
}

#[derive(Debug, Clone, serde::Serialize)]
struct PodLine {
    name: String,
    phase: String,
    restarts: i32,
    detail: String,
}

/// `lbctl watch`.
pub async fn watch(args: Watch) -> Result<u8> {
    let deployment = Deployment::load(&args.deployment).await?;
    // EvalAI and the cluster are optional: the screen says when they cannot be reached.
    let evalai = deployment.evalai(&args.token).await.map_err(|e| e.chain());
    let clusters = Clusters::from_env(&deployment.sdk);
    let tty = std::io::stdout().is_terminal() && !args.json;
    let started = Instant::now();
    let mut last: Option<Screen> = None;
    while started.elapsed() < MAX_WATCH {
        let screen = look(&deployment, &args, &evalai, &clusters).await?;
        let ended = screen.record_status.is_some_and(RecordStatus::is_final)
            && is_final_on_evalai(&screen.evalai_status);
        if args.json {
            outln!("{}", serde_json::to_string(&screen).unwrap_or_default());
        } else {
            if tty {
                out!("\x1b[2J\x1b[H");
            }
            out!("{}", render(&screen, tty));
            if !tty {
                outln!("--");
            }
        }
        let _ = std::io::stdout().flush();
        last = Some(screen);
        if args.once || ended {
            break;
        }
        tokio::time::sleep(Duration::from_secs(args.interval)).await;
    }
    let Some(last) = last else { return Ok(1) };
    if !args.once && !args.json {
        outln!("summary");
        out!("{}", summary(&last, started.elapsed()));
    }
    Ok(0)
}

fn is_final_on_evalai(status: &str) -> bool {
    // Unknown (EvalAI unreachable) does not keep the watch going once the record is final.
    status
        .parse::<lb_domain::submission::SubmissionStatus>()
        .map_or(true, lb_domain::submission::SubmissionStatus::is_final)
}

/// What the record itself shows of submission `id`.
fn screen_of(record: &Record, id: u64) -> Screen {
    let mut screen = Screen {
        submission_id: id,
        leaderboard: record.leaderboard.clone(),
        team: format!(
            "{} (id {})",
            clean(record.team_name.as_deref().unwrap_or("-")),
            record.team_id.map_or("-".into(), |n| n.to_string())
        ),
        track: clean(record.track_name.as_deref().unwrap_or("-")),
        status: record.status_word.as_str().to_owned(),
        record_status: record.status,
        started: clean(record.start_time.as_deref().unwrap_or("-")),
        ended: clean(record.end_time.as_deref().unwrap_or("-")),
        routes: format!(
            "{}/{}",
            record.routes.0.map_or("-".into(), |n| n.to_string()),
            record.routes.1.map_or("-".into(), |n| n.to_string())
        ),
        error: record.error.as_deref().map(clean),
        usage: record.usage().map(|u| u.describe()),
        ..Screen::default()
    };
    screen.stage = match screen.record_status {
        Some(RecordStatus::Submitted | RecordStatus::Resuming) => {
            "claimed, waiting for its Jobs to run".into()
        }
        Some(RecordStatus::Running) => "running".into(),
        Some(status) => format!("ended {}", status.as_str().to_lowercase()),
        None => format!("`{}`", clean(&screen.status)),
    };
    screen
}

async fn look(
    deployment: &Deployment,
    args: &Watch,
    evalai: &std::result::Result<lb_evalai::EvalAiClient, String>,
    clusters: &Clusters,
) -> Result<Screen> {
    let id = args.submission;
    let found = deployment
        .records(args.leaderboard.as_deref(), ScanFilter::Submission(id))
        .await?;
    let Some(record) = found.records.into_iter().next() else {
        return Err(CliError::NotFound(format!(
            "submission `{id}` has no record yet: Intake has not claimed it (is it on the queue?)"
        )));
    };
    let mut screen = screen_of(&record, id);
    let claimed = matches!(
        screen.record_status,
        Some(RecordStatus::Submitted | RecordStatus::Resuming)
    );
    // The queue: claimed submissions of this leaderboard that do not run yet.
    if claimed {
        let waiting = deployment
            .records(Some(&record.leaderboard), ScanFilter::InFlight)
            .await?;
        let queue = queue_positions(&waiting.records);
        screen.queue_length = queue.len();
        screen.queue_position = queue.iter().position(|(_, q)| *q == id).map(|i| i + 1);
    }
    let Ok(lb) = deployment.leaderboards(Some(&record.leaderboard)) else {
        return Ok(screen);
    };
    let Some((_, lb)) = lb.into_iter().next() else {
        return Ok(screen);
    };
    let Ok(leaderboard) = record.leaderboard.parse::<Leaderboard>() else {
        return Ok(screen);
    };
    let store = SubmissionStore::new(deployment.s3.clone(), &lb.bucket, id);
    screen.workers = workers(&store, leaderboard).await;
    screen.scores = scores(&store, id).await;
    if !screen.record_status.is_some_and(RecordStatus::is_final) {
        match clusters.connect(lb).await {
            Ok(cluster) => match cluster.observe(&id.to_string()).await {
                Ok(observation) => screen.pods = pods(&observation),
                Err(e) => screen.pods_note = Some(format!("cluster not readable: {e}")),
            },
            Err(e) => screen.pods_note = Some(format!("cluster not reachable: {}", e.chain())),
        }
    }
    screen.evalai_status = match evalai {
        Ok(client) => match client.submission(id).await {
            Ok(s) => s.status.to_string(),
            Err(e) => format!("(unreadable: {e})"),
        },
        Err(e) => format!("(not configured: {e})"),
    };
    Ok(screen)
}

async fn workers(store: &SubmissionStore, leaderboard: Leaderboard) -> Vec<WorkerLine> {
    let Ok(partials) = store.partials().await else {
        return Vec::new();
    };
    let mut out = Vec::new();
    for partial in partials {
        let Ok(bytes) = store.get_bounded(&partial.key, MAX_FILE_BYTES as u64).await else {
            continue;
        };
        let line = match read_worker_file(&partial.key, Some(&bytes), leaderboard, None) {
            Ok(WorkerFile::Present(file)) => WorkerLine {
                worker: partial.pair_id,
                done: file.records.len() as u64,
                total: file.progress.1,
                entry_status: file.entry_status.map(|s| clean(&s)),
            },
            _ => WorkerLine {
                worker: partial.pair_id,
                done: 0,
                total: 0,
                entry_status: Some("(unreadable)".into()),
            },
        };
        out.push(line);
    }
    out
}

async fn scores(store: &SubmissionStore, id: u64) -> Vec<(String, f64)> {
    let Ok(bytes) = store
        .get_bounded(&format!("{id}/evalai/results.json"), 1 << 20)
        .await
    else {
        return Vec::new();
    };
    let Ok(results) = serde_json::from_slice::<serde_json::Value>(&bytes) else {
        return Vec::new();
    };
    SHOWN_SCORES
        .iter()
        .filter_map(|label| {
            let value = results[0]["accuracies"][label].as_f64()?;
            Some((label.to_string(), value))
        })
        .collect()
}

fn pods(observation: &lb_cluster::Observation) -> Vec<PodLine> {
    observation
        .jobs
        .iter()
        .flat_map(|j| j.pods.iter())
        .chain(observation.stray_pods.iter())
        .map(|pod| {
            let restarts = pod.containers.iter().map(|c| c.restart_count).sum();
            let mut detail = String::new();
            if let Some(u) = &pod.unschedulable {
                let _ = write!(detail, "{}", clean(&u.message));
            }
            if let Some(w) = &pod.autoscaler {
                let _ = write!(detail, " (autoscaler: {})", clean(&w.message));
            }
            for c in pod.containers.iter().filter(|c| c.restart_count > 0) {
                let _ = write!(detail, " {}x{}", clean(&c.name), c.restart_count);
            }
            if let Some(reason) = &pod.disruption {
                // The Monitor's judgement, as far as the pod alone tells it: a kubelet's
                // eviction is free only when its node is leaving, which the node tells.
                let message = pod.disruption_message.as_deref();
                let whose = match lb_domain::cluster::disruption::classify(reason, message) {
                    Disruption::Reclaim => "a reclaim: not counted, a new pod resumes",
                    Disruption::ByKubelet => "by the kubelet: free only if its node is leaving",
                    Disruption::Own => "counted as a crash",
                };
                let _ = write!(detail, " disrupted ({}): {whose}", clean(reason));
            }
            PodLine {
                name: clean(&pod.name),
                phase: clean(pod.phase.as_str()),
                restarts,
                detail: detail.trim().to_owned(),
            }
        })
        .collect()
}

fn render(s: &Screen, tty: bool) -> String {
    let mut out = String::new();
    let bold = |t: &str| {
        if tty {
            format!("\x1b[1m{t}\x1b[0m")
        } else {
            t.to_owned()
        }
    };
    let _ = writeln!(
        out,
        "{} {}  (leaderboard {}, {}, team {})",
        bold("submission"),
        s.submission_id,
        s.leaderboard,
        s.track,
        s.team
    );
    let queue = match s.queue_position {
        Some(p) if p > 1 => format!(
            " — {} submission(s) ahead ({p} of {})",
            p - 1,
            s.queue_length
        ),
        Some(_) => format!(" — next to start (1 of {})", s.queue_length),
        None => String::new(),
    };
    let _ = writeln!(out, "  stage     {}{queue}", s.stage);
    let _ = writeln!(
        out,
        "  record    {}  started {}  ended {}",
        s.status, s.started, s.ended
    );
    let _ = writeln!(out, "  EvalAI    {}", s.evalai_status);
    let _ = writeln!(out, "  routes    {}", s.routes);
    if let Some(usage) = &s.usage {
        let _ = writeln!(out, "  GPUs      {usage}");
    }
    for w in &s.workers {
        let _ = writeln!(
            out,
            "    worker {:<3} {}/{} {}",
            w.worker,
            w.done,
            w.total,
            w.entry_status.as_deref().unwrap_or("")
        );
    }
    if !s.pods.is_empty() || s.pods_note.is_some() {
        let _ = writeln!(out, "  pods");
        if let Some(note) = &s.pods_note {
            let _ = writeln!(out, "    {note}");
        }
        for p in &s.pods {
            let line = format!(
                "    {:<40} {:<9} restarts {:<3} {}",
                p.name, p.phase, p.restarts, p.detail
            );
            let _ = writeln!(out, "{}", line.trim_end());
        }
    }
    if !s.scores.is_empty() {
        let scores: Vec<String> = s.scores.iter().map(|(l, v)| format!("{l} {v}")).collect();
        let _ = writeln!(out, "  scores    {}", scores.join(", "));
    }
    if let Some(error) = &s.error {
        let _ = writeln!(out, "  error     {error}");
    }
    out
}

fn summary(s: &Screen, watched: Duration) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "  submission {} ended {} (EvalAI: {})",
        s.submission_id, s.status, s.evalai_status
    );
    let _ = writeln!(out, "  started {}, ended {}", s.started, s.ended);
    let _ = writeln!(out, "  routes {}", s.routes);
    if let Some(usage) = &s.usage {
        let _ = writeln!(out, "  GPUs {usage}");
    }
    if !s.scores.is_empty() {
        for (label, value) in &s.scores {
            let _ = writeln!(out, "  {label:<20} {value}");
        }
    }
    if let Some(error) = &s.error {
        let _ = writeln!(out, "  why: {error}");
    }
    let _ = writeln!(out, "  watched {:.0}s", watched.as_secs_f64());
    out
}
