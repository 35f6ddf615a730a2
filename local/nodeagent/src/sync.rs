//! The kubelet's loop: each look at the API server's pods decides, per pod bound to one of
//! the agent's nodes, whether to start it here, report its status, or end it (a deletion:
//! stop its containers within the grace, report the terminal phase, then remove the object as
//! a kubelet does, with grace 0 and the pod's uid as precondition); and, once a second, its
//! eviction manager's pass over each node's disk (`crate::eviction`).

use std::collections::{BTreeSet, HashMap, HashSet};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use k8s_openapi::api::core::v1::{Pod, PodStatus};
use kube::api::{Api, DeleteParams, ListParams, Patch, PatchParams, Preconditions};
use local_kube::PodRunner;
use serde_json::{json, Value};
use tracing::{debug, info, warn};

use crate::eviction::{self, Disk, PodUse};
use crate::NodeSpec;

/// How often the eviction manager looks at the nodes' disks (the kubelet's is 10 s).
const PRESSURE_EVERY: Duration = Duration::from_secs(1);

/// The conditions a kubelet owns; the others (`PodScheduled`, `DisruptionTarget`) are the
/// scheduler's and the control plane's, and a strategic merge by type leaves them be.
const KUBELET_CONDITIONS: [&str; 4] = [
    "PodReadyToStartContainers",
    "Initialized",
    "ContainersReady",
    "Ready",
];

/// What to do about one pod bound to one of the agent's nodes.
#[derive(Debug, Clone, PartialEq)]
pub enum Action {
    /// Start its containers here.
    Start,
    /// Report its status when it changed.
    Report,
    /// It is being deleted: stop it within this grace, report, remove it.
    End(Option<Duration>),
    /// Nothing (being ended, ended, or finished before this agent saw it).
    Nothing,
}

/// The decision for a pod as the API server has it (`real`) and as it runs here (`local`);
/// `ending`: its deletion is under way here; `evicted`: the eviction manager reports it.
pub fn decide(real: &Pod, local: Option<&Pod>, (ending, evicted): (bool, bool)) -> Action {
    if ending {
        return Action::Nothing;
    }
    if real.metadata.deletion_timestamp.is_some() {
        let grace = real
            .metadata
            .deletion_grace_period_seconds
            .map(|s| Duration::from_secs(s.max(0) as u64));
        return Action::End(grace);
    }
    if evicted {
        return Action::Nothing;
    }
    match local {
        Some(_) => Action::Report,
        None if terminal(real.status.as_ref()) => Action::Nothing,
        None => Action::Start,
    }
}

fn is_running(pod: &Pod) -> bool {
    pod.status.as_ref().and_then(|s| s.phase.as_deref()) == Some("Running")
}

fn terminal(status: Option<&PodStatus>) -> bool {
    matches!(
        status.and_then(|s| s.phase.as_deref()),
        Some("Succeeded" | "Failed")
    )
}

/// The status patch that reports `local` (the kubelet's view); `last` forces a terminal phase,
/// as a kubelet reports a deleted pod whose containers it stopped.
pub fn report(local: &PodStatus, last: bool) -> Value {
    let conditions: Vec<_> = local
        .conditions
        .iter()
        .flatten()
        .filter(|c| KUBELET_CONDITIONS.contains(&c.type_.as_str()))
        .collect();
    let mut phase = local.phase.clone().unwrap_or_else(|| "Pending".into());
    if last && !matches!(phase.as_str(), "Succeeded" | "Failed") {
        phase = "Failed".into();
    }
    let ip = local.pod_ip.clone().unwrap_or_else(|| "127.0.0.1".into());
    json!({"status": {
        "phase": phase,
        "conditions": conditions,
        "containerStatuses": local.container_statuses,
        "initContainerStatuses": local.init_container_statuses,
        "startTime": local.start_time,
        "hostIP": "127.0.0.1",
        "hostIPs": [{"ip": "127.0.0.1"}],
        "podIP": ip,
        "podIPs": [{"ip": ip}],
    }})
}

/// The kubelet of the agent's nodes.
pub struct Kubelet {
    client: kube::Client,
    runner: PodRunner,
    nodes: BTreeSet<String>,
    /// The last status reported, by pod uid.
    reported: HashMap<String, Value>,
    /// Pods being ended (or ended) by their own task, by uid.
    ending: Arc<Mutex<HashSet<String>>>,
    /// Each node's disk, by name.
    disks: HashMap<String, Disk>,
    /// Pods the eviction manager evicted, by uid: it reports them.
    evicted: Arc<Mutex<HashSet<String>>>,
    /// How long an evicted pod's terminal status waits after its condition.
    late: Duration,
    /// When the eviction manager last looked.
    pressure_looked: Option<Instant>,
}

impl Kubelet {
    /// The kubelet of `nodes`, running pods with `runner`; an evicted pod's terminal status
    /// follows its `DisruptionTarget` condition by `late`.
    pub fn new(
        client: kube::Client,
        runner: PodRunner,
        nodes: &[NodeSpec],
        late: Duration,
    ) -> Kubelet {
        Kubelet {
            client,
            runner,
            nodes: nodes.iter().map(|n| n.name.clone()).collect(),
            reported: HashMap::new(),
            ending: Arc::default(),
            disks: nodes.iter().map(|n| (n.name.clone(), n.disk)).collect(),
            evicted: Arc::default(),
            late,
            pressure_looked: None,
        }
    }

    /// One look: acts on every pod bound to the agent's nodes and forgets pods the API server
    /// no longer has. Returns the pods no node holds yet (for the autoscaler's word).
    pub async fn look(&mut self) -> Result<Vec<Pod>, kube::Error> {
        let api: Api<Pod> = Api::all(self.client.clone());
        let pods = api.list(&ListParams::default()).await?.items;
        let local: HashMap<String, Pod> = self
            .runner
            .pods()
            .into_iter()
            .filter_map(|p| Some((p.metadata.uid.clone()?, p)))
            .collect();
        let mut seen = HashSet::new();
        let mut unbound = Vec::new();
        // The eviction manager runs less often than the looks: only its looks gather for it.
        let pressure_due = self
            .pressure_looked
            .is_none_or(|t| t.elapsed() >= PRESSURE_EVERY);
        let mut running: HashMap<String, Vec<Pod>> = HashMap::new();
        for real in pods {
            let node = real.spec.as_ref().and_then(|s| s.node_name.as_deref());
            let Some(uid) = real.metadata.uid.clone() else {
                continue;
            };
            match node {
                None => unbound.push(real),
                Some(n) if self.nodes.contains(n) => {
                    seen.insert(uid.clone());
                    let ending = lock(&self.ending).contains(&uid);
                    let evicted = lock(&self.evicted).contains(&uid);
                    let here = local.get(&uid);
                    let watched = pressure_due && !ending && !evicted;
                    if let Some(pod) = here.filter(|p| watched && is_running(p)) {
                        running.entry(n.to_owned()).or_default().push(pod.clone());
                    }
                    match decide(&real, here, (ending, evicted)) {
                        Action::Start => self.start(real),
                        Action::Report => {
                            if let Some(status) = here.and_then(|p| p.status.as_ref()) {
                                self.report(&real, &uid, report(status, false)).await;
                            }
                        }
                        Action::End(grace) => self.end(real, uid, grace),
                        Action::Nothing => {}
                    }
                }
                Some(_) => {}
            }
        }
        for (uid, gone) in local.into_iter().filter(|(uid, _)| !seen.contains(uid)) {
            let ns = gone.metadata.namespace.clone().unwrap_or_default();
            let name = gone.metadata.name.clone().unwrap_or_default();
            debug!(pod = %name, "the API server removed it: cleaning up");
            self.runner.delete_pod(&ns, &name).await;
            self.reported.remove(&uid);
            lock(&self.ending).remove(&uid);
            lock(&self.evicted).remove(&uid);
        }
        if pressure_due {
            self.pressure_looked = Some(Instant::now());
            self.relieve(&running);
        }
        Ok(unbound)
    }

    /// The eviction manager's pass: on each node whose disk is below its threshold, evicts
    /// the pod the kubelet would (one per pass, as the kubelet waits to see what that freed).
    fn relieve(&self, running: &HashMap<String, Vec<Pod>>) {
        for (node, pods) in running {
            let Some(disk) = self.disks.get(node) else {
                continue;
            };
            let uses: Vec<PodUse> = pods
                .iter()
                .map(|p| PodUse::of(p, &self.runner.disk_usage(p)))
                .collect();
            if let Some(eviction) = eviction::choose(disk, &uses) {
                self.evict(pods[eviction.pod].clone(), eviction.message);
            }
        }
    }

    /// Evicts a pod as the kubelet does for a hard threshold: its containers stopped at once,
    /// the `DisruptionTarget` condition written, and then (late by `self.late`, as a busy
    /// kubelet's status manager can be) the terminal phase with reason `Evicted`.
    fn evict(&self, pod: Pod, message: String) {
        let uid = pod.metadata.uid.clone().unwrap_or_default();
        lock(&self.evicted).insert(uid.clone());
        let name = pod.metadata.name.clone().unwrap_or_default();
        warn!(pod = %name, message = %message, "evicting for disk pressure");
        let (client, runner, late) = (self.client.clone(), self.runner.clone(), self.late);
        tokio::spawn(async move {
            runner.stop_pod(&uid, Some(Duration::ZERO)).await;
            let condition = json!({
                "type": "DisruptionTarget", "status": "True", "reason": "TerminationByKubelet",
                "message": message,
                "lastTransitionTime": k8s_openapi::apimachinery::pkg::apis::meta::v1::Time(
                    k8s_openapi::jiff::Timestamp::now()),
            });
            put_status(
                &client,
                &pod,
                &json!({"status": {"conditions": [condition]}}),
            )
            .await;
            tokio::time::sleep(late).await;
            if let Some(status) = last_status(&runner, &pod) {
                let mut patch = report(&status, true);
                patch["status"]["reason"] = json!("Evicted");
                patch["status"]["message"] = json!(message);
                put_status(&client, &pod, &patch).await;
            }
        });
    }

    fn start(&mut self, real: Pod) {
        let name = real.metadata.name.clone().unwrap_or_default();
        let mut pod = real;
        pod.metadata.resource_version = None;
        match self.runner.adopt(pod) {
            Ok(_) => info!(pod = %name, "pod started"),
            Err(e) => warn!(pod = %name, error = %e, "cannot start pod"),
        }
    }

    async fn report(&mut self, real: &Pod, uid: &str, patch: Value) {
        if self.reported.get(uid) == Some(&patch) {
            return;
        }
        if put_status(&self.client, real, &patch).await {
            self.reported.insert(uid.to_owned(), patch);
        }
    }

    /// Ends a deleted pod on its own task, so a long grace holds up no other pod.
    fn end(&self, real: Pod, uid: String, grace: Option<Duration>) {
        lock(&self.ending).insert(uid.clone());
        let (client, runner) = (self.client.clone(), self.runner.clone());
        let ending = self.ending.clone();
        tokio::spawn(async move {
            runner.stop_pod(&uid, grace).await;
            if let Some(status) = last_status(&runner, &real) {
                put_status(&client, &real, &report(&status, true)).await;
            }
            let ns = real.metadata.namespace.clone().unwrap_or_default();
            let name = real.metadata.name.clone().unwrap_or_default();
            let api: Api<Pod> = Api::namespaced(client, &ns);
            let params = DeleteParams {
                grace_period_seconds: Some(0),
                preconditions: Some(Preconditions {
                    uid: Some(uid.clone()),
                    resource_version: None,
                }),
                ..DeleteParams::default()
            };
            match api.delete(&name, &params).await {
                Ok(_) => info!(pod = %name, "pod ended"),
                Err(kube::Error::Api(s)) if s.code == 404 || s.code == 409 => {}
                Err(e) => {
                    // NB: the next look ends it again (its containers are already stopped).
                    warn!(pod = %name, error = %e, "cannot remove pod: trying again");
                    lock(&ending).remove(&uid);
                }
            }
        });
    }
}

/// The status of a pod whose containers were stopped: as its kubelet here last wrote it, or
/// as the API server had it.
fn last_status(runner: &PodRunner, real: &Pod) -> Option<PodStatus> {
    let uid = real.metadata.uid.as_deref();
    let local = runner
        .pods()
        .into_iter()
        .find(|p| p.metadata.uid.as_deref() == uid);
    local.and_then(|p| p.status).or_else(|| real.status.clone())
}

/// Writes a pod's status; whether the API server took it.
async fn put_status(client: &kube::Client, real: &Pod, patch: &Value) -> bool {
    let ns = real.metadata.namespace.clone().unwrap_or_default();
    let name = real.metadata.name.clone().unwrap_or_default();
    let api: Api<Pod> = Api::namespaced(client.clone(), &ns);
    match api
        .patch_status(&name, &PatchParams::default(), &Patch::Strategic(patch))
        .await
    {
        Ok(_) => true,
        Err(e) => {
            debug!(pod = %name, error = %e, "status not written");
            false
        }
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pod(value: Value) -> Pod {
        serde_json::from_value(value).unwrap()
    }

    #[test]
    fn a_bound_pod_starts_once_and_is_then_reported() {
        let real =
            pod(json!({"metadata": {"name": "p", "uid": "u"}, "status": {"phase": "Pending"}}));
        assert_eq!(decide(&real, None, (false, false)), Action::Start);
        assert_eq!(decide(&real, Some(&real), (false, false)), Action::Report);
    }

    #[test]
    fn a_deleted_pod_is_ended_once_within_its_grace() {
        let real = pod(json!({"metadata": {"name": "p", "uid": "u",
            "deletionTimestamp": "2026-11-28T10:00:00Z", "deletionGracePeriodSeconds": 30}}));
        assert_eq!(
            decide(&real, None, (false, false)),
            Action::End(Some(Duration::from_secs(30)))
        );
        assert_eq!(decide(&real, Some(&real), (true, false)), Action::Nothing);
    }

    #[test]
    fn an_evicted_pod_is_left_to_the_eviction_manager_until_it_is_deleted() {
        let real = pod(json!({"metadata": {"name": "p", "uid": "u"}}));
        assert_eq!(decide(&real, Some(&real), (false, true)), Action::Nothing);
        let deleted = pod(json!({"metadata": {"name": "p", "uid": "u",
            "deletionTimestamp": "2026-11-28T10:00:00Z", "deletionGracePeriodSeconds": 0}}));
        assert_eq!(
            decide(&deleted, Some(&deleted), (false, true)),
            Action::End(Some(Duration::ZERO))
        );
    }

    #[test]
    fn a_pod_that_ended_before_the_agent_saw_it_is_not_run_again() {
        let real =
            pod(json!({"metadata": {"name": "p", "uid": "u"}, "status": {"phase": "Failed"}}));
        assert_eq!(decide(&real, None, (false, false)), Action::Nothing);
    }

    #[test]
    fn the_last_report_is_terminal_and_leaves_the_control_plane_s_conditions_be() {
        let status: PodStatus = serde_json::from_value(json!({
            "phase": "Running",
            "conditions": [{"type": "Ready", "status": "True"},
                           {"type": "PodScheduled", "status": "True"},
                           {"type": "DisruptionTarget", "status": "True"}],
        }))
        .unwrap();
        let running = report(&status, false);
        assert_eq!(running["status"]["phase"], "Running");
        let last = report(&status, true);
        assert_eq!(last["status"]["phase"], "Failed");
        let types: Vec<&str> = last["status"]["conditions"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c["type"].as_str().unwrap())
            .collect();
        assert_eq!(types, ["Ready"]);
    }
}
