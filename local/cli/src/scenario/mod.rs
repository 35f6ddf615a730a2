//! What `lbctl local run` rehearses: one type per scenario, in a file of its own, saying what
//! it sets up (the fakes' switches, the node), what it injects during the run, and how the
//! submission must end. Adding one is a file here and a line in [`Scenario`].

mod cancel;
mod cancel_flood;
mod consolidate;
mod crash;
mod crash_loop;
mod disk_hog;
mod drain_loop;
mod evalai_down;
mod evict_between_rounds;
mod forge;
mod forge_recordings;
mod hang;
mod happy;
mod no_node;
mod plant_gpu;
mod release;
mod spot;
mod stop;
mod unpullable;
mod upgrade;
mod wake_flood;

use std::future::Future;
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64};
use std::sync::Arc;
use std::time::Instant;

use clap::ValueEnum;
use local_stack::workloads::Behaviour;
use local_stepfunctions::Executor;
use serde_json::Value;

use crate::reclaim::ReclaimReport;
pub use consolidate::ConsolidationReport;
pub use upgrade::UpgradeReport;

/// The participant's image of every scenario but the unpullable one.
pub const IMAGE: &str = "123456789012.dkr.ecr.us-west-2.amazonaws.com/team-one:local";

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
    /// As `cancel`, with another team's five cancelled submissions of 2.4 MB of metadata each
    /// in EvalAI's list: the sweep still finds the cancel, CANCELLED.
    CancelFlood,
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
    /// Every agent stops CARLA's recorder as soon as the evaluator started it and leaves
    /// 1-byte files of its routes' names in its own logs: FINISHED on EvalAI, and `FINISHED*`
    /// for operators, every scoring route named with why its recording did not pass.
    ForgeRecordings,
    /// Every agent plants another GPU's UUID in its pair's handoff and crashes once: each
    /// simulator renders on its own pair's GPU at every attempt, FINISHED (a node of 4 GPUs
    /// unless --gpus says otherwise).
    PlantGpu,
    /// The node is reclaimed mid-route (a Spot interruption: the managed node group drains it
    /// through the Eviction API): every pod gets the `DisruptionTarget` condition and a new
    /// pod replaces it once it has stopped, without using a retry; each interrupted route runs
    /// again once. FINISHED (routes of at least 1.5 s, so that the drain lands mid-route).
    Spot,
    /// One pod is evicted (Eviction API) and gone between two Monitor rounds: no round sees
    /// it, yet its route shows as run again in the record and the lost time is counted.
    /// FINISHED (routes of at least 1.5 s).
    EvictBetweenRounds,
    /// An operator stops the execution (StopExecution) after its first Monitor round: the
    /// reaper (Finalize, on Step Functions' status-change event, which local mode delivers as
    /// EventBridge would) deletes the Jobs, gives the team's place back, tells EvalAI
    /// `failed` with the reason and writes the final record.
    Stop,
    /// The first pair's pod is drained (Eviction API) at every round after one saw it
    /// running, 8 times: 3 free reclaims, then 5 charged as the platform's, past its Job's
    /// `backoffLimit`. FAILED as the platform's own failure: the participant is told it was
    /// not their agent's doing, the record says `failed_by: platform`, and the execution ends
    /// `PlatformFailed` (routes of at least 8 s).
    DrainLoop,
    /// The first pair's agent writes 12 GiB outside its volumes at every attempt, on a node
    /// whose images leave little room: the kubelet evicts the pod for disk pressure naming
    /// the agent, and reports it failed seconds after the condition. Each eviction is charged
    /// once as the pod's own: FAILED past its Job's `backoffLimit`, the participant told that
    /// its pods were stopped by a disruption of their own (`--kube real` only: local-kube's
    /// node has no disk; routes of at least 4 s, so that the eviction lands mid-route).
    DiskHog,
    /// EvalAI fails from the moment the run is finished: Finalize cannot post, an operator
    /// stops the execution, every attempt of the reaper's event fails and it is dropped; once
    /// EvalAI is back the reaper's scheduled pass deletes the Jobs, gives the place back and
    /// tells EvalAI `failed`.
    EvalaiDown,
    /// A deploy mid-run: once the first submission's Monitor ended a round, a new state
    /// machine version (naming new function versions) is published and the `live` alias moves
    /// to it; a second submission then arrives. The first runs to its end, across its
    /// continuations, on the version it started on; the second on the new one. Both FINISHED.
    Deploy,
    /// A rollback mid-run: the first submission starts on version 2; after its first round the
    /// alias moves back to version 1 and a second submission arrives. The first finishes on
    /// version 2, the second on version 1. Both FINISHED.
    Rollback,
    /// A Kubernetes upgrade mid-route, as `docs/operations.md` does it: the control plane one
    /// minor up in place (`versions.env`'s `UPGRADE_K8S_VERSION`: the API answers nothing
    /// meanwhile), then the GPU node group replaced: its new node joins, the old one is
    /// cordoned and its pods evicted through the Eviction API. Each eviction is a free reclaim
    /// (no retry used), each interrupted route runs again once on the new node. FINISHED
    /// (`--kube real` only; routes of at least 4 s, so that the drain lands mid-route).
    Upgrade,
    /// Consolidation at route ends: the pairs hold half of a node of 8 GPUs; once a route is
    /// done a second node joins with room for them, the sweep drains the first and each
    /// Monitor round moves its pairs at their next results write (Eviction API). Each move is
    /// free (no retry used), the pairs end on the second node. FINISHED (`--kube real` only;
    /// routes of at least 8 s, so that a move lands just after a route's end).
    Consolidate,
}

impl Scenario {
    /// This scenario, for one run.
    pub fn rehearsal(self) -> Box<dyn Rehearsal> {
        match self {
            Scenario::Happy => Box::new(happy::Happy),
            Scenario::Crash => Box::new(crash::Crash),
            Scenario::Hang => Box::new(hang::Hang),
            Scenario::Cancel => Box::new(cancel::Cancel::default()),
            Scenario::CancelFlood => Box::new(cancel_flood::CancelFlood::default()),
            Scenario::Unpullable => Box::new(unpullable::Unpullable),
            Scenario::CrashLoop => Box::new(crash_loop::CrashLoop),
            Scenario::NoNode => Box::new(no_node::NoNode),
            Scenario::WakeFlood => Box::new(wake_flood::WakeFlood),
            Scenario::Forge => Box::new(forge::Forge),
            Scenario::ForgeRecordings => Box::new(forge_recordings::ForgeRecordings),
            Scenario::PlantGpu => Box::new(plant_gpu::PlantGpu),
            Scenario::Spot => Box::new(spot::Spot::default()),
            Scenario::EvictBetweenRounds => {
                Box::new(evict_between_rounds::EvictBetweenRounds::default())
            }
            Scenario::Stop => Box::new(stop::Stop),
            Scenario::EvalaiDown => Box::new(evalai_down::EvalAiDown::default()),
            Scenario::DrainLoop => Box::new(drain_loop::DrainLoop::default()),
            Scenario::DiskHog => Box::new(disk_hog::DiskHog),
            Scenario::Deploy => Box::new(release::Release(crate::release::Move::Deploy)),
            Scenario::Rollback => Box::new(release::Release(crate::release::Move::Rollback)),
            Scenario::Upgrade => Box::new(upgrade::Upgrade::default()),
            Scenario::Consolidate => Box::new(consolidate::Consolidate::default()),
        }
    }
}

/// Makes `node` schedulable, as a node group's new node joins: whether it did.
pub async fn node_joins(kubeconfig: &Path, node: &str) -> bool {
    match node_agent::client(kubeconfig).await {
        Ok(client) => node_agent::uncordon(&client, node).await.is_ok(),
        Err(_) => false,
    }
}

/// What a run tells its scenario before the executions start.
pub struct Begin {
    /// The local cluster's kubeconfig, as an operator (and a node group's drain) uses it.
    pub kubeconfig: PathBuf,
    /// Whether a drain cordons the node first (the real control plane has Node objects;
    /// local-kube's one node is not modelled as one).
    pub cordons: bool,
    /// The submissions' namespace.
    pub namespace: String,
    /// The submission the scenario acts on (the first to arrive).
    pub submission: u64,
    /// The fake EvalAI's address (none with another EvalAI).
    pub fake_evalai: Option<String>,
    /// `--cancel-after-round`.
    pub cancel_after_round: u64,
    /// Set once the scenario did its act (for those that [`act`](Rehearsal::acts)).
    pub acted: Arc<AtomicBool>,
    /// Attempts of the reaper's event deliveries that failed so far.
    pub reaper_failures: Arc<AtomicU64>,
    /// The submission's results in S3 (moto), as the Monitor reads them.
    pub store: lb_aws::s3::SubmissionStore,
    /// What upgrades the real control plane in place (`--kube real` only).
    pub upgrader: Option<local_stack::real::Upgrader>,
}

impl Begin {
    /// The reclaim watcher of this run's submission: cued, it drains the node (cordoned
    /// first where nodes are modelled), and `acted` is set once it did.
    pub fn reclaim_watcher(&self) -> crate::reclaim::Reclaim {
        crate::reclaim::Reclaim::spawn(
            self.kubeconfig.clone(),
            self.namespace.clone(),
            self.submission,
            self.cordons,
            self.acted.clone(),
        )
    }
}

/// A scenario's shared slot, locked: a hook that panicked does not keep the others out.
pub fn held<T>(slot: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    slot.lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// `<method> <url><path>` with a JSON body on a fake's admin API: its HTTP status and body
/// (bounded by the run's timeout: the fake answers at once).
pub async fn admin_request(
    method: &str,
    url: &str,
    path: &str,
    body: &str,
) -> std::io::Result<(u16, String)> {
    use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};
    let host = url.strip_prefix("http://").unwrap_or(url);
    let mut stream = tokio::net::TcpStream::connect(host).await?;
    let request = format!(
        "{method} {path} HTTP/1.1\r\nHost: {host}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    stream.write_all(request.as_bytes()).await?;
    let mut answer = Vec::new();
    stream.read_to_end(&mut answer).await?;
    let answer = String::from_utf8_lossy(&answer);
    let status = answer.get(9..12).and_then(|s| s.parse().ok());
    let body = answer.split_once("\r\n\r\n").map_or("", |(_, b)| b);
    match status {
        Some(status) => Ok((status, body.to_owned())),
        None => Err(std::io::Error::other("not an HTTP answer")),
    }
}

/// What a scenario found, for the report.
#[derive(Debug, Default)]
pub struct Findings {
    /// The spot scenario's reclaim: evictions, retries, routes run again.
    pub reclaim: Option<ReclaimReport>,
    /// When the participant cancelled (the cancel scenario).
    pub cancelled_at: Option<Instant>,
    /// The control plane's upgrade (the upgrade scenario).
    pub upgrade: Option<UpgradeReport>,
    /// The nodes drained and the pairs moved (the consolidate scenario).
    pub consolidation: Option<ConsolidationReport>,
}

/// A scenario for one run: what it sets up, what it injects, what it expects. Every hook but
/// [`expected`](Self::expected) does nothing unless the scenario says otherwise.
pub trait Rehearsal: Send + Sync {
    /// EvalAI's status the submission must end with (`finished`, `failed`, `cancelled`).
    fn expected(&self) -> &'static str;

    /// The images' and the node's behaviour (`once`: a folder for once-only faults).
    fn set_up(&self, _behaviour: &mut Behaviour, _once: &Path) {}

    /// Whether a finished run's CARLA recordings pass the audit.
    fn audit_passes(&self) -> bool {
        true
    }

    /// Whether it needs the real control plane (`--kube real`): its nodes' kubelet has a disk
    /// to run short of.
    fn needs_real_kube(&self) -> bool {
        false
    }

    /// The participant's image.
    fn image(&self) -> &'static str {
        IMAGE
    }

    /// Whether it acts during the run: the run is as expected only once it did.
    fn acts(&self) -> bool {
        false
    }

    /// What moves the state machine's alias during the run (a deploy, a rollback).
    fn release(&self) -> Option<crate::release::Move> {
        None
    }

    /// Before the executions start.
    fn begin(&self, _run: &Begin) {}

    /// Once the executions started (the first one's ARN), with the Monitor rounds counted so
    /// far and the flag of [`Begin::acted`].
    fn started(
        &self,
        _executor: &Executor,
        _arn: &str,
        _rounds: &Arc<AtomicU64>,
        _acted: &Arc<AtomicBool>,
    ) {
    }

    /// Monitor round `n` begins: its act, `true` once done (tried every round until then). It
    /// runs before the round's task is invoked, so what it does is done before the round
    /// looks (the executor waits for it).
    fn round_begins(&self, _n: u64) -> bool {
        true
    }

    /// A Monitor round ended, its run state's `monitor` part as it left it.
    fn round_ended(&self, _monitor: &Value) {}

    /// What it found, once the run ended (`logs`: each pair's agent log).
    fn finish<'a>(
        &'a self,
        _logs: &'a [String],
    ) -> Pin<Box<dyn Future<Output = Findings> + Send + 'a>> {
        Box::pin(async { Findings::default() })
    }
}
