//! A Spot reclaim rehearsed on the local cluster: the node is drained as an EKS managed node
//! group drains a Spot node on its interruption notice (every pod evicted through the Eviction
//! API), and what the Jobs make of it is watched until the run ends.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use k8s_openapi::api::core::v1::Pod;
use kube::api::{Api, EvictParams};
use serde::Serialize;
use tokio::sync::{watch, Notify};
use tokio::task::JoinHandle;

use lb_domain::status::PodPhase;

/// How often the Jobs and pods are looked at.
const LOOK_EVERY: Duration = Duration::from_millis(200);

/// What the reclaim did and what followed.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ReclaimReport {
    /// The pods the drain evicted.
    pub evicted: Vec<String>,
    /// Every pod seen with the `DisruptionTarget` condition, with the condition's reason.
    pub disrupted: BTreeMap<String, String>,
    /// The most failed pods one of the submission's Jobs counted: its retries used.
    pub retries_used: i32,
    /// Runs of each route (`RouteScenario_<i>`), from the agents' logs in S3.
    pub route_runs: BTreeMap<String, u32>,
    /// Routes that ran more than once.
    pub routes_run_again: usize,
    /// Routes a pod was in when it stopped and a later pod of its pair went on (from the
    /// agents' logs): the routes a reclaim interrupted. A pod evicted while its pair was still
    /// setting up, or between two routes, interrupted none.
    pub interrupted: Vec<String>,
    /// Finished routes the next pod's evaluator ran again before the interrupted one: the
    /// Leaderboard resumes from the first finished route whose record says the agent or the
    /// simulation crashed (`validate_and_resume`; the fixtures' routes 3, 7 and 17 say so).
    pub resumed_behind: Vec<String>,
}

impl ReclaimReport {
    /// What a reclaim should come to: pods evicted, each with the condition the API server
    /// writes, no retry used, the routes the evicted pods were in (at most one each) run again
    /// once, no other route run again but those the evaluator resumed behind them, and no
    /// route more than twice.
    pub fn as_expected(&self) -> bool {
        !self.evicted.is_empty()
            && self.interrupted.len() <= self.evicted.len()
            && self.routes_run_again == self.interrupted.len() + self.resumed_behind.len()
            && self
                .interrupted
                .iter()
                .all(|r| self.route_runs.get(r) == Some(&2))
            && self
                .evicted
                .iter()
                .all(|p| self.disrupted.get(p).map(String::as_str) == Some("EvictionByEvictionAPI"))
            && self.retries_used == 0
            && self.route_runs.values().all(|n| *n <= 2)
    }
}

/// The watcher, waiting for its cue to drain the node.
pub struct Reclaim {
    cue: Arc<Notify>,
    stop: watch::Sender<bool>,
    task: JoinHandle<ReclaimReport>,
}

impl Reclaim {
    /// Starts watching the submission's Jobs; `acted` is set once the node was drained (and
    /// first cordoned, when `cordons`).
    pub fn spawn(
        kubeconfig: PathBuf,
        namespace: String,
        submission: u64,
        cordons: bool,
        acted: Arc<AtomicBool>,
    ) -> Reclaim {
        let cue = Arc::new(Notify::new());
        let (stop, stopped) = watch::channel(false);
        let task = tokio::spawn(watch_and_drain(
            (kubeconfig, namespace),
            (submission, cordons),
            cue.clone(),
            stopped,
            acted,
        ));
        Reclaim { cue, stop, task }
    }

    /// The cue: a route is under way, drain the node now.
    pub fn cue(&self) -> Arc<Notify> {
        self.cue.clone()
    }

    /// Stops watching and says what happened.
    pub async fn finish(self) -> ReclaimReport {
        let _ = self.stop.send(true);
        self.task.await.unwrap_or_default()
    }
}

async fn watch_and_drain(
    (kubeconfig, namespace): (PathBuf, String),
    (submission, cordons): (u64, bool),
    cue: Arc<Notify>,
    mut stopped: watch::Receiver<bool>,
    acted: Arc<AtomicBool>,
) -> ReclaimReport {
    let mut report = ReclaimReport::default();
    let Ok(cluster) = lb_cluster::Cluster::from_kubeconfig(&kubeconfig, None).await else {
        return report;
    };
    let cluster = cluster.with_namespace(namespace);
    let Ok(client) = node_agent::client(&kubeconfig).await else {
        return report;
    };
    let pods: Api<Pod> = Api::namespaced(client.clone(), cluster.namespace());
    let mut cued = false;
    loop {
        tokio::select! {
            () = cue.notified(), if !cued => {
                cued = true;
                let on_node = match cordons {
                    true => cordon(&client, &pods, submission).await,
                    false => None,
                };
                let evicted = drain(&cluster, &pods, submission, on_node).await;
                for (pod, reason) in &evicted {
                    if let Some(reason) = reason {
                        report.disrupted.insert(pod.clone(), reason.clone());
                    }
                }
                report.evicted = evicted.into_iter().map(|(pod, _)| pod).collect();
                acted.store(!report.evicted.is_empty(), Ordering::SeqCst);
            }
            _ = stopped.changed() => return report,
            () = tokio::time::sleep(LOOK_EVERY) => look(&cluster, submission, &mut report).await,
        }
    }
}

/// Cordons one node the submission's pods run on, as a managed node group does before it
/// drains a node on its interruption notice; the names of the pods on it.
async fn cordon(
    client: &kube::Client,
    api: &Api<Pod>,
    submission: u64,
) -> Option<std::collections::BTreeSet<String>> {
    let selector = format!("{}={submission}", lb_domain::job::plan::SUBMISSION_LABEL);
    let params = kube::api::ListParams::default().labels(&selector);
    let pods = api.list(&params).await.ok()?.items;
    let on = |p: &Pod| p.spec.as_ref().and_then(|s| s.node_name.clone());
    let node = pods.iter().find_map(on)?;
    match node_agent::cordon(client, &node).await {
        Ok(()) => cli::outln!("           scenario: node {node} cordoned"),
        Err(e) => cli::outln!("           scenario: cordoning {node} failed: {e}"),
    }
    Some(
        pods.iter()
            .filter(|p| on(p).as_deref() == Some(node.as_str()))
            .filter_map(|p| p.metadata.name.clone())
            .collect(),
    )
}

/// Evicts every running pod of the submission (on the drained node, when it is known), as `kubectl drain` and the node group do; each
/// evicted pod with its `DisruptionTarget` reason as read right after (the API server writes
/// it before the pod is deleted; a pod that stops at once may be gone before a later look).
async fn drain(
    cluster: &lb_cluster::Cluster,
    api: &Api<Pod>,
    submission: u64,
    on_node: Option<std::collections::BTreeSet<String>>,
) -> Vec<(String, Option<String>)> {
    let Ok(seen) = cluster.observe(&submission.to_string()).await else {
        return Vec::new();
    };
    let mut evicted = Vec::new();
    let pods = seen.jobs.iter().flat_map(|j| &j.pods);
    let on_node = |name: &String| on_node.as_ref().is_none_or(|n| n.contains(name));
    for pod in pods.filter(|p| p.phase == PodPhase::Running && !p.terminating && on_node(&p.name)) {
        match api.evict(&pod.name, &EvictParams::default()).await {
            Ok(_) => {
                let reason = disruption_of(api, &pod.name).await;
                evicted.push((pod.name.clone(), reason));
            }
            Err(e) => cli::outln!("           scenario: evicting {} failed: {e}", pod.name),
        }
    }
    cli::outln!(
        "           scenario: the node is reclaimed: {} pod(s) evicted",
        evicted.len()
    );
    evicted
}

/// Whether `pod` started more than a second before `time` (a start is read to the second).
fn started_well_before(
    pod: &lb_domain::cluster::view::PodView,
    time: std::time::SystemTime,
) -> bool {
    let time = time
        .duration_since(std::time::SystemTime::UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_secs()).unwrap_or(i64::MAX));
    pod.start_time.is_some_and(|t| t.as_second() + 1 < time)
}

/// Evicts one running pod of the submission (of the Job with index `job`, when given; one that
/// started more than a second before `started_before`, when given) through the Eviction API
/// and waits, bounded, until the API no longer has it: the pod and its `DisruptionTarget`
/// reason as read right after the eviction. `None` when no pod is such, or on an error.
pub async fn evict_one_until_gone(
    kubeconfig: &std::path::Path,
    namespace: &str,
    submission: u64,
    (job, started_before): (Option<u32>, Option<std::time::SystemTime>),
) -> Option<(String, Option<String>)> {
    let cluster = lb_cluster::Cluster::from_kubeconfig(kubeconfig, None)
        .await
        .ok()?;
    let cluster = cluster.with_namespace(namespace.to_owned());
    let client = node_agent::client(kubeconfig).await.ok()?;
    let api: Api<Pod> = Api::namespaced(client, cluster.namespace());
    let seen = cluster.observe(&submission.to_string()).await.ok()?;
    let pod = seen
        .jobs
        .iter()
        .filter(|j| job.is_none_or(|index| j.index == Some(index)))
        .flat_map(|j| &j.pods)
        .find(|p| {
            p.phase == PodPhase::Running
                && !p.terminating
                && started_before.is_none_or(|before| started_well_before(p, before))
        })?
        .name
        .clone();
    if let Err(e) = api.evict(&pod, &EvictParams::default()).await {
        cli::outln!("           scenario: evicting {pod} failed: {e}");
        return None;
    }
    let reason = disruption_of(&api, &pod).await;
    let deadline = tokio::time::Instant::now() + GONE_WITHIN;
    while api.get_opt(&pod).await.ok().flatten().is_some() {
        if tokio::time::Instant::now() >= deadline {
            cli::outln!("           scenario: {pod} was evicted but is still there");
            break;
        }
        tokio::time::sleep(LOOK_EVERY).await;
    }
    cli::outln!("           scenario: {pod} evicted and gone before the round looks");
    Some((pod, reason))
}

/// How long an evicted pod may take to go.
const GONE_WITHIN: Duration = Duration::from_secs(60);

/// The reason of pod `name`'s `DisruptionTarget` condition, if it has one.
async fn disruption_of(api: &Api<Pod>, name: &str) -> Option<String> {
    let pod = api.get_opt(name).await.ok()??;
    let conditions = pod.status?.conditions?;
    conditions
        .into_iter()
        .find(|c| c.type_ == "DisruptionTarget" && c.status == "True")?
        .reason
}

/// The Jobs' failures counted so far, and the pods the control plane is taking away, as the
/// Monitor observes them.
async fn look(cluster: &lb_cluster::Cluster, submission: u64, report: &mut ReclaimReport) {
    if let Ok(seen) = cluster.observe(&submission.to_string()).await {
        note_disruptions(&seen, report);
    }
}

/// What `seen` shows of the Jobs' failures and the pods taken away, added to `report`.
pub fn note_disruptions(seen: &lb_domain::cluster::view::Observation, report: &mut ReclaimReport) {
    for job in &seen.jobs {
        report.retries_used = report.retries_used.max(job.failed);
        for pod in &job.pods {
            if let Some(reason) = &pod.disruption {
                report.disrupted.insert(pod.name.clone(), reason.clone());
            }
        }
    }
}

/// What the watcher saw, with each route's runs from the agents' logs (`None`: no watcher).
pub async fn report(watcher: Option<Reclaim>, logs: &[String]) -> Option<ReclaimReport> {
    let mut report = watcher?.finish().await;
    count_route_runs(logs, &mut report);
    Some(report)
}

/// Counts the runs of each route in the agents' logs (`========= Preparing RouteScenario_3
/// (repetition 0) =========`), which a new pod continues, the routes a pod stopped in, and
/// those the next pod ran before it again: a pod's part of the log starts where the sidecar
/// says its evaluator started, and a route is over once its statistics are registered.
pub fn count_route_runs(logs: &[String], report: &mut ReclaimReport) {
    for log in logs {
        // The route the last pod stopped in, until the next pod runs it again.
        let mut stopped_in: Option<&str> = None;
        let mut within: Option<&str> = None;
        for line in log.lines() {
            if line.contains(EVALUATOR_STARTED) {
                if let Some(route) = within.take() {
                    report.interrupted.push(route.to_owned());
                    stopped_in = Some(route);
                }
            } else if line.contains(ROUTE_REGISTERED) {
                within = None;
            } else if let Some(rest) = line.split("Preparing ").nth(1) {
                let route = rest.split_whitespace().next().unwrap_or_default();
                if route.starts_with("RouteScenario_") {
                    *report.route_runs.entry(route.to_owned()).or_default() += 1;
                    within = Some(route);
                    match stopped_in {
                        Some(stopped) if stopped == route => stopped_in = None,
                        Some(_) => report.resumed_behind.push(route.to_owned()),
                        None => {}
                    }
                }
            }
        }
    }
    report.routes_run_again = report.route_runs.values().filter(|n| **n > 1).count();
}

/// The agent sidecar's line as a pod's evaluator starts (`lb_sidecar::agent`).
const EVALUATOR_STARTED: &str = ": evaluator started on routes ";

/// The evaluator's line once a route's record is written.
const ROUTE_REGISTERED: &str = "> Registering the route statistics";

#[cfg(test)]
mod tests {
    use super::*;

    /// A pod's part of a pair's log: the evaluator started, then `routes` prepared, the last
    /// one registered when `finished`.
    fn part(routes: &[u32], finished: bool) -> String {
        let mut log =
            "[lb-sidecar t] agent 1 attempt 0: evaluator started on routes 0-4\n".to_owned();
        for (i, route) in routes.iter().enumerate() {
            log += &format!("========= Preparing RouteScenario_{route} (repetition 0) =========\n");
            log += "> Running the route\n";
            if finished || i + 1 < routes.len() {
                log += "> Registering the route statistics\n";
            }
        }
        log
    }

    #[test]
    fn the_route_a_pod_stopped_in_and_ran_again_is_the_one_interrupted() {
        let mut report = ReclaimReport {
            evicted: vec!["pod-a".into(), "pod-b".into()],
            disrupted: [
                ("pod-a", "EvictionByEvictionAPI"),
                ("pod-b", "EvictionByEvictionAPI"),
            ]
            .map(|(p, r)| (p.to_owned(), r.to_owned()))
            .into(),
            ..ReclaimReport::default()
        };
        // Pair 1 stopped in route 1; pair 2's pod went while its pair was setting up.
        let logs = [
            part(&[0, 1], false) + &part(&[1, 2], true),
            "[lb-sidecar t] SIGTERM\n".to_owned() + &part(&[5, 6], true),
        ];
        count_route_runs(&logs, &mut report);
        assert_eq!(report.route_runs["RouteScenario_1"], 2);
        assert_eq!(report.route_runs.len(), 5);
        assert_eq!(report.routes_run_again, 1);
        assert_eq!(report.interrupted, ["RouteScenario_1"]);
        assert!(report.as_expected());
    }

    #[test]
    fn a_route_run_again_that_no_pod_stopped_in_is_not_what_a_reclaim_does() {
        let mut report = ReclaimReport {
            evicted: vec!["pod-a".into()],
            disrupted: [("pod-a".to_owned(), "EvictionByEvictionAPI".to_owned())].into(),
            ..ReclaimReport::default()
        };
        // A finished route prepared again by a pod that was not resuming behind an
        // interrupted one: the evaluator lost its checkpoint.
        count_route_runs(&[part(&[0, 1], true) + &part(&[0, 1], true)], &mut report);
        assert_eq!(report.routes_run_again, 2);
        assert!(report.interrupted.is_empty() && report.resumed_behind.is_empty());
        assert!(!report.as_expected());
        // Stopped in route 3 after route 2 recorded an agent crash: the evaluator resumes
        // from route 2, which runs again behind the interrupted one.
        let mut behind = ReclaimReport {
            route_runs: BTreeMap::new(),
            routes_run_again: 0,
            ..report.clone()
        };
        let log = part(&[0, 1, 2, 3], false) + &part(&[2, 3], true);
        count_route_runs(&[log], &mut behind);
        assert_eq!(behind.interrupted, ["RouteScenario_3"]);
        assert_eq!(behind.resumed_behind, ["RouteScenario_2"]);
        assert!(behind.as_expected());
        // The run ended inside a route: no later pod went on, so nothing was interrupted.
        let mut ended = ReclaimReport::default();
        count_route_runs(&[part(&[0, 1], false)], &mut ended);
        assert!(ended.interrupted.is_empty());
    }
}
