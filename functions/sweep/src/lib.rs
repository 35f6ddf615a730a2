//! Sweep: once a minute (an EventBridge schedule), the cancels of the submissions in flight,
//! the GPUs the clusters bill and hold (the fleet's idle share), and the GPU nodes
//! consolidation drains.
//!
//! A participant cancels on EvalAI, which writes nothing to S3, so no upload wakes the
//! execution. The sweep lists the executions waiting (the wake table), asks EvalAI for each of
//! their challenges' cancelled submissions in one request (host API reference, 7.3), flags
//! each waiting one it finds, and reports the token it took, so the Monitor runs within the
//! minute, confirms the cancel with EvalAI and writes the cancel marker. One request per
//! challenge a minute, whatever the number of submissions in flight.
//!
//! Then it counts each cluster's GPU nodes and the GPUs its pods hold (a list of each) for the
//! metrics: what the account pays for and leaves idle, which no submission's own rounds can
//! see. From the same lists it drains the nodes consolidation chooses and opens drained ones
//! again when pods wait without room (`lb_domain::capacity::consolidation`: a taint on the
//! node, its Kubernetes group's one write); each Monitor moves its pods off a drained node at
//! their routes' ends.

use lb_pipeline::serve::Function;
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::future::Future;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use aws_config::SdkConfig;
use lb_aws::admission::AdmissionTable;
use lb_aws::tasks::{Callbacks, Reported, StepFunctions};
use lb_aws::wake::{Waiting, WakeTable};
use lb_cluster::fleet::GpuFleet;
use lb_domain::capacity::consolidation;
use lb_domain::results::Leaderboard;
use lb_domain::run::metrics::Metric;
use lb_domain::settings::LeaderboardSettings;
use lb_domain::submission::SubmissionStatus;
use lb_evalai::EvalAiClient;
use lb_pipeline::cluster::Clusters;
use lb_pipeline::config::Shared;
use lb_pipeline::{clients, FnError, FunctionConfig, Result};
use serde::Serialize;
use tracing::{info, warn};

/// What the sweep needs: EvalAI, the wake table, where tokens are reported, the clusters.
#[derive(Debug)]
pub struct Deps<C = StepFunctions> {
    /// EvalAI, as the host.
    pub evalai: EvalAiClient,
    /// The leaderboards' clusters (EKS, or `LB_KUBECONFIG`).
    pub clusters: Clusters,
    /// Each leaderboard's deployment (its cluster).
    pub deployments: Vec<(Leaderboard, LeaderboardSettings)>,
    /// The queues, where each leaderboard's cluster count is kept for the queue note's
    /// forecast (none: a sweep run by hand, `LB_ADMISSION_TABLE=unlimited`).
    pub admission: Option<AdmissionTable>,
    /// EKS, for the GPU node groups' maxima (none where the clusters are a kubeconfig's).
    pub eks: Option<aws_sdk_eks::Client>,
    /// The maxima read, by node group, and when: they change with a stack update only.
    maxima: Mutex<HashMap<String, (Instant, Option<u32>)>>,
    /// The wake table.
    pub wakes: WakeTable,
    /// Step Functions (the embedded executor in local mode).
    pub callbacks: C,
    /// Drain the nodes consolidation chooses (`LB_CONSOLIDATE_NODES`).
    pub consolidate: bool,
}

impl Deps {
    /// Cold start: environment, secrets, clients.
    pub async fn from_env() -> Result<Deps> {
        let (config, sdk) = clients::cold_start().await?;
        let callbacks = StepFunctions::new(aws_sdk_sfn::Client::new(&sdk));
        Deps::load(&sdk, &config, callbacks).await
    }
}

impl<C: Callbacks> Deps<C> {
    /// The same from an explicit SDK configuration, reporting to `callbacks` (local mode, tests).
    pub async fn load(sdk: &SdkConfig, config: &FunctionConfig, callbacks: C) -> Result<Deps<C>> {
        let settings = clients::settings(sdk, config).await?;
        Ok(Deps {
            evalai: clients::evalai(sdk, config, &settings).await?,
            clusters: Clusters::from_env(sdk),
            deployments: (settings.leaderboards.iter())
                .map(|(board, deployment)| (*board, deployment.clone()))
                .collect(),
            admission: match &config.admission {
                Shared::Table(name) => Some(AdmissionTable::new(
                    aws_sdk_dynamodb::Client::new(sdk),
                    name,
                )),
                Shared::Unlimited => None,
            },
            eks: std::env::var_os("LB_KUBECONFIG")
                .is_none_or(|k| k.is_empty())
                .then(|| aws_sdk_eks::Client::new(sdk)),
            maxima: Mutex::new(HashMap::new()),
            wakes: WakeTable::new(aws_sdk_dynamodb::Client::new(sdk), config.wake_table()?),
            callbacks,
            consolidate: config.consolidate_nodes,
        })
    }
}

/// What one sweep did (its result, and its log line).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct Sweep {
    /// Executions waiting.
    pub waiting: usize,
    /// Challenges asked.
    pub challenges: usize,
    /// Waiting submissions found cancelled and flagged.
    pub cancelled: Vec<u64>,
    /// Of those, executions woken now.
    pub woken: Vec<u64>,
    /// GPUs the clusters' nodes offer and those their pods hold; none when a cluster could not
    /// be read (a partial count would read as idle GPUs).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gpus: Option<(u32, u32)>,
    /// Nodes drained now.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub drained: Vec<String>,
    /// Drained nodes opened again now.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub reopened: Vec<String>,
}

impl<C: Callbacks> Function for Deps<C> {
    const NAME: &'static str = "sweep";
    /// The schedule's event says nothing the sweep needs.
    type Input = serde::de::IgnoredAny;
    type Output = Sweep;
    fn handle(&self, _: serde::de::IgnoredAny) -> impl Future<Output = Result<Sweep>> {
        handle(self)
    }
}

/// One sweep. Everything it can do is done; if a challenge could not be read or a wake
/// failed, the error names them after the rest (the next sweep tries again).
pub async fn handle<C: Callbacks>(deps: &Deps<C>) -> Result<Sweep> {
    let waiting = deps.wakes.waiting().await?;
    let mut by_challenge: BTreeMap<u64, BTreeSet<u64>> = BTreeMap::new();
    for w in &waiting {
        by_challenge
            .entry(w.challenge)
            .or_default()
            .insert(w.submission_id);
    }
    let since = oldest_by_challenge(&waiting);
    let mut sweep = Sweep {
        waiting: waiting.len(),
        challenges: by_challenge.len(),
        ..Sweep::default()
    };
    let mut problems = Vec::new();
    for (challenge, ours) in by_challenge {
        let cancelled = match deps
            .evalai
            .submissions_with_status_since(
                challenge,
                SubmissionStatus::Cancelled,
                since.get(&challenge).copied().flatten(),
            )
            .await
        {
            Ok(list) => list,
            Err(e) => {
                warn!(challenge, error = %e, "cancels not read this sweep");
                problems.push(format!("challenge {challenge}: {e}"));
                continue;
            }
        };
        for id in cancelled
            .iter()
            .map(|s| s.id)
            .filter(|id| ours.contains(id))
        {
            match wake(deps, id).await {
                Ok(woken) => {
                    sweep.cancelled.push(id);
                    if woken {
                        sweep.woken.push(id);
                    }
                }
                Err(e) => {
                    warn!(submission_id = id, error = %e, "cancel not passed on this sweep");
                    problems.push(format!("submission {id}: {e}"));
                }
            }
        }
    }
    fleet(deps, &mut sweep).await;
    if let Some((billed, held)) = sweep.gpus {
        lb_pipeline::metrics::sample_count(Metric::GpusBilled, f64::from(billed));
        lb_pipeline::metrics::sample_count(Metric::GpusHeld, f64::from(held));
    }
    info!(
        waiting = sweep.waiting,
        challenges = sweep.challenges,
        cancelled = ?sweep.cancelled,
        woken = ?sweep.woken,
        gpus = ?sweep.gpus,
        drained = ?sweep.drained,
        reopened = ?sweep.reopened,
        "sweep"
    );
    if !problems.is_empty() {
        return Err(FnError::SweepIncomplete(problems));
    }
    Ok(sweep)
}

/// Every cluster's GPUs, each cluster once (two leaderboards may share one): those its nodes
/// offer and those its pods hold, none when one could not be read (a partial count would read
/// as idle GPUs); and, when asked, its nodes drained or opened again as consolidation says.
async fn fleet<C>(deps: &Deps<C>, sweep: &mut Sweep) {
    let mut seen = BTreeSet::new();
    let mut counted = Some((0, 0));
    for (_, deployment) in &deps.deployments {
        if !seen.insert(deployment.cluster.as_str()) {
            continue;
        }
        let read = match deps.clusters.connect(deployment).await {
            Ok(cluster) => (cluster.gpu_fleet().await)
                .map(|fleet| (cluster, fleet))
                .map_err(FnError::from),
            Err(e) => Err(e),
        };
        let (cluster, fleet) = match read {
            Ok(read) => read,
            Err(e) => {
                warn!(cluster = %deployment.cluster, error = %e.chain(), "GPUs not counted this sweep");
                counted = None;
                continue;
            }
        };
        if let Some((billed, held)) = counted.as_mut() {
            *billed += fleet.gpus();
            *held += fleet.held();
        }
        if deps.consolidate {
            consolidate(&cluster, &fleet, sweep).await;
        }
        keep_counts(deps, &deployment.cluster, &fleet).await;
    }
    sweep.gpus = counted;
}

/// How long a node group's maximum is believed before it is read again.
const MAXIMA_KEPT: Duration = Duration::from_secs(600);

/// Keeps, for each leaderboard on `cluster`, what its queue note's forecast waits for: the
/// GPUs free, booting and addable. Trouble is logged: the note then waits for running pairs.
async fn keep_counts<C>(deps: &Deps<C>, cluster: &str, fleet: &GpuFleet) {
    let Some(admission) = &deps.admission else {
        return;
    };
    let now = lb_pipeline::clients::now_epoch_seconds();
    let on_cluster = deps
        .deployments
        .iter()
        .filter(|(_, d)| d.cluster == cluster);
    for (board, deployment) in on_cluster {
        let groups = deployment.capacity.node_groups(cluster);
        let max = node_max(deps, cluster, &groups).await;
        let counted = fleet.capacity(deployment.gpus_per_node, max);
        if let Err(e) = admission.keep_fleet(board.as_str(), &counted, now).await {
            warn!(leaderboard = board.as_str(), error = %e, "GPU count not kept for the queue note");
        }
    }
}

/// The most GPU nodes `groups` of `cluster` may hold together; none when unknown (no EKS, a
/// group not read).
async fn node_max<C>(deps: &Deps<C>, cluster: &str, groups: &[String]) -> Option<u32> {
    let eks = deps.eks.as_ref()?;
    let mut total = 0u32;
    for group in groups {
        let kept = deps.maxima.lock().ok()?.get(group).copied();
        let max = match kept {
            Some((at, max)) if at.elapsed() < MAXIMA_KEPT => max,
            _ => match lb_aws::eks::nodegroup_max(eks, cluster, group).await {
                Ok(max) => {
                    deps.maxima
                        .lock()
                        .ok()?
                        .insert(group.clone(), (Instant::now(), max));
                    max
                }
                Err(e) => {
                    warn!(nodegroup = %group, error = %e, "node group's maximum not read");
                    return None;
                }
            },
        };
        total = total.saturating_add(max.unwrap_or(0));
    }
    Some(total)
}

/// Taints the nodes the plan drains and takes the taint off those it opens again. A patch
/// refused or failed is left to the next sweep, which reads the nodes afresh.
async fn consolidate(cluster: &lb_cluster::Cluster, fleet: &GpuFleet, sweep: &mut Sweep) {
    let plan = consolidation::plan(&fleet.uses(), fleet.pending);
    let drain = plan.drain.iter().map(|n| (n, true));
    for (name, draining) in drain.chain(plan.reopen.iter().map(|n| (n, false))) {
        let Some(node) = fleet.nodes.iter().find(|n| &n.name == name) else {
            continue;
        };
        match cluster.set_draining(node, draining).await {
            Ok(true) if draining => sweep.drained.push(name.clone()),
            Ok(true) => sweep.reopened.push(name.clone()),
            Ok(false) => {
                info!(node = %name, "node changed or gone since it was read: left to the next sweep");
            }
            Err(e) => {
                warn!(node = %name, error = %FnError::from(e).chain(), "node not changed this sweep");
            }
        }
    }
}

/// Per challenge, when EvalAI received the oldest submission waiting (epoch seconds): its
/// cancelled submissions from then on are all the sweep needs. `None` for a challenge with a
/// wait that stored no arrival (the whole list then).
fn oldest_by_challenge(waiting: &[Waiting]) -> BTreeMap<u64, Option<u64>> {
    let mut oldest: BTreeMap<u64, Option<u64>> = BTreeMap::new();
    for w in waiting {
        let slot = oldest.entry(w.challenge).or_insert(w.submitted_at);
        *slot = match (*slot, w.submitted_at) {
            (Some(a), Some(b)) => Some(a.min(b)),
            _ => None,
        };
    }
    oldest
}

/// Flags the cancel and reports the token it took; `true` when an execution was woken.
async fn wake<C: Callbacks>(deps: &Deps<C>, id: u64) -> lb_aws::Result<bool> {
    // `None`: flagged already, or the wait ended meanwhile (the Monitor reads the status
    // itself then).
    let Some(Some(taken)) = deps.wakes.flag_cancel(id).await? else {
        return Ok(false);
    };
    match deps.callbacks.succeed(&taken.token, "{}").await {
        Ok(Reported::Delivered) => {
            info!(submission_id = id, execution = ?taken.execution, "cancelled on EvalAI: woke the execution");
            Ok(true)
        }
        Ok(Reported::Stale) => Ok(false),
        Err(e) => {
            if let Err(undo) = deps.wakes.restore_token(id, &taken, true).await {
                warn!(submission_id = id, error = %undo, "could not undo the cancel flag; the safety net wakes it");
            }
            Err(e)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_challenge_is_asked_from_its_oldest_waiting_arrival() {
        let w = |submission_id, challenge, submitted_at| Waiting {
            submission_id,
            challenge,
            submitted_at,
        };
        let oldest = oldest_by_challenge(&[
            w(1, 7, Some(300)),
            w(2, 7, Some(100)),
            w(3, 7, Some(200)),
            w(4, 8, Some(50)),
            w(5, 8, None),
            w(6, 9, None),
        ]);
        // Challenge 8 has a wait without an arrival: its whole list, as before.
        assert_eq!(
            oldest,
            BTreeMap::from([(7, Some(100)), (8, None), (9, None)])
        );
    }
}
