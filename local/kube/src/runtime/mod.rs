//! The process runtime behind the API: the job controller, the kubelet and what they share.

pub mod controller;
pub mod disk;
pub mod env;
pub mod events;
pub mod expand;
pub mod failure_policy;
pub mod kubelet;
pub mod mounts;
pub mod process;
pub mod scheduler;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use k8s_openapi::api::batch::v1::Job;
use k8s_openapi::api::core::v1::Pod;
use tokio::sync::{watch, Notify};
use tracing::{info, warn};

use crate::config::{Node, Timing};
use crate::imagemap::ImageMap;
use crate::objects::pod::controller_uid;
use crate::status::{success_status, ApiError, JOBS};
use crate::store::{time_now, ObjKey, Store};
use process::{Namespaces, Processes};

/// The node name pods run on.
pub const NODE_NAME: &str = "local-kube";

/// `propagationPolicy` of a delete.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Propagation {
    /// Remove the owner at once; dependents are deleted after.
    Background,
    /// Mark the owner, delete dependents, then remove the owner.
    Foreground,
    /// Remove the owner; dependents stay (their owner reference removed).
    Orphan,
}

/// The answer to a delete: the object while deletion is in progress, or a Success Status.
pub enum Deleted {
    /// Still there (Foreground): the object with `deletionTimestamp`.
    Pending(Box<Job>),
    /// Gone: the Status body.
    Gone(serde_json::Value),
}

struct JobHandle {
    notify: Arc<Notify>,
    stop: watch::Sender<bool>,
}

struct PodHandle {
    stop: watch::Sender<Option<Duration>>,
    done: watch::Receiver<bool>,
    grace: Duration,
}

/// Everything the controller, kubelet and API share.
pub struct Runtime {
    /// Objects.
    pub store: Arc<Store>,
    /// Image map.
    pub images: ImageMap,
    /// Delays.
    pub timing: Timing,
    /// Container isolation in use.
    pub ns: Namespaces,
    /// Root of pod directories.
    pub pods_dir: PathBuf,
    /// Node name.
    pub node: String,
    /// Host PATH for containers.
    pub host_path: String,
    /// Host HOME for containers.
    pub home: String,
    /// Live process groups.
    pub procs: Processes,
    /// The node's `nvidia.com/gpu` (`None`: GPUs not modelled, every pod fits), labels
    /// and whether the autoscaler's events are recorded.
    pub node_model: Node,
    /// Events about pods.
    pub events: Mutex<events::Events>,
    /// The directory holding the node's `nvidia-smi`, put first on the `PATH` of containers
    /// that see GPUs.
    pub nvidia_dir: PathBuf,
    allocations: Mutex<scheduler::Allocations>,
    jobs: Mutex<HashMap<String, JobHandle>>,
    pods: Mutex<HashMap<String, PodHandle>>,
    shutting_down: AtomicBool,
    shutdown_tx: watch::Sender<bool>,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Runtime {
    /// A runtime keeping pod directories under `state_dir/pods`.
    pub fn new(
        store: Arc<Store>,
        images: ImageMap,
        timing: Timing,
        ns: Namespaces,
        state_dir: &Path,
        node_model: Node,
    ) -> std::io::Result<Arc<Self>> {
        let gpus = node_model.gpus;
        let pods_dir = state_dir.join("pods");
        std::fs::create_dir_all(&pods_dir)?;
        let nvidia_dir = state_dir.join("nvidia");
        std::fs::create_dir_all(&nvidia_dir)?;
        let smi = nvidia_dir.join("nvidia-smi");
        std::fs::write(
            &smi,
            scheduler::nvidia_smi_script(gpus.unwrap_or(scheduler::UNMODELLED_GPUS)),
        )?;
        {
            use std::os::unix::fs::PermissionsExt as _;
            std::fs::set_permissions(&smi, std::fs::Permissions::from_mode(0o755))?;
        }
        let (shutdown_tx, _) = watch::channel(false);
        Ok(Arc::new(Self {
            store,
            images,
            timing,
            ns,
            pods_dir,
            node: NODE_NAME.into(),
            host_path: std::env::var("PATH").unwrap_or_else(|_| {
                "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin".into()
            }),
            home: std::env::var("HOME").unwrap_or_else(|_| "/root".into()),
            procs: Processes::default(),
            node_model,
            events: Mutex::new(Default::default()),
            nvidia_dir,
            allocations: Mutex::new(Default::default()),
            jobs: Mutex::new(HashMap::new()),
            pods: Mutex::new(HashMap::new()),
            shutting_down: AtomicBool::new(false),
            shutdown_tx,
        }))
    }

    /// Whether shutdown has begun.
    pub fn is_shutting_down(&self) -> bool {
        self.shutting_down.load(Ordering::SeqCst)
    }

    /// Resolves once shutdown has begun (streams end on it).
    pub async fn until_shutdown(rx: &mut watch::Receiver<bool>) {
        let _ = rx.wait_for(|s| *s).await;
    }

    /// A receiver that turns `true` at shutdown (streams end on it).
    pub fn shutdown_signal(&self) -> watch::Receiver<bool> {
        self.shutdown_tx.subscribe()
    }

    /// The directory of a pod (`<ns>_<name>_<uid>`, like /var/log/pods).
    pub fn pod_dir(&self, pod: &Pod) -> PathBuf {
        let m = &pod.metadata;
        self.pods_dir.join(format!(
            "{}_{}_{}",
            m.namespace.as_deref().unwrap_or_default(),
            m.name.as_deref().unwrap_or_default(),
            m.uid.as_deref().unwrap_or_default()
        ))
    }

    /// Log file of a container attempt (0-based; attempt N runs with restartCount N).
    pub fn log_path(&self, pod: &Pod, container: &str, attempt: i32) -> PathBuf {
        self.pod_dir(pod)
            .join("logs")
            .join(container)
            .join(format!("{attempt}.log"))
    }

    /// Starts the controller of a stored Job.
    pub fn start_job(self: &Arc<Self>, job: &Job) {
        let key = ObjKey::of(&job.metadata);
        let uid = job.metadata.uid.clone().unwrap_or_default();
        let notify = Arc::new(Notify::new());
        let (stop, stop_rx) = watch::channel(false);
        lock(&self.jobs).insert(
            uid.clone(),
            JobHandle {
                notify: notify.clone(),
                stop,
            },
        );
        let rt = self.clone();
        tokio::spawn(async move {
            controller::run(rt.clone(), key, uid.clone(), notify, stop_rx).await;
            lock(&rt.jobs).remove(&uid);
        });
    }

    /// Wakes the controller of the Job with this uid.
    pub fn notify_job(&self, uid: &str) {
        if let Some(h) = lock(&self.jobs).get(uid) {
            h.notify.notify_one();
        }
    }

    fn stop_job(&self, uid: &str) {
        if let Some(h) = lock(&self.jobs).remove(uid) {
            let _ = h.stop.send(true);
        }
    }

    /// Stores a pod (unbound) and schedules it.
    pub fn create_pod(self: &Arc<Self>, pod: Pod) -> Result<Pod, ApiError> {
        if self.is_shutting_down() {
            return Err(ApiError::unavailable("local-kube is shutting down"));
        }
        let pod = self.store.create(pod)?;
        self.schedule();
        Ok(self
            .store
            .get::<Pod>(&ObjKey::of(&pod.metadata))
            .unwrap_or(pod))
    }

    /// One scheduling pass over the unbound pods, oldest first: each that fits the node's
    /// free GPUs is bound and started; the others are marked unschedulable and wait for the
    /// next pass (a pod ending or going away starts one).
    pub fn schedule(self: &Arc<Self>) {
        // NB: held for the whole pass: one scheduler, no GPU handed out twice.
        let mut allocations = lock(&self.allocations);
        let (mut pending, _) = self.store.list::<Pod>(None, |p| {
            p.metadata.deletion_timestamp.is_none()
                && p.spec.as_ref().is_some_and(|s| s.node_name.is_none())
        });
        pending.sort_by(|a, b| {
            (&a.metadata.creation_timestamp, &a.metadata.name)
                .cmp(&(&b.metadata.creation_timestamp, &b.metadata.name))
        });
        let node = &self.node_model;
        let labels = scheduler::node_labels(&self.node, node);
        let no_spec = k8s_openapi::api::core::v1::PodSpec::default();
        for pod in pending {
            let key = ObjKey::of(&pod.metadata);
            let uid = pod.metadata.uid.clone().unwrap_or_default();
            let spec = pod.spec.as_ref().unwrap_or(&no_spec);
            let need = scheduler::gpu_request(spec);
            let selected = !scheduler::labels_modelled(node) || scheduler::selects(spec, &labels);
            if !selected || !scheduler::fits(node.gpus, allocations.in_use(), need) {
                let message = if selected {
                    scheduler::INSUFFICIENT_GPU
                } else {
                    scheduler::SELECTOR_MISMATCH
                };
                if let Some(waiting) = self
                    .store
                    .update::<Pod>(&key, |p| scheduler::mark_unschedulable(p, message))
                {
                    if node.autoscaler {
                        let word = scheduler::autoscaler_word(selected, need, node.gpus);
                        lock(&self.events).record(
                            &waiting,
                            scheduler::AUTOSCALER,
                            scheduler::NOT_TRIGGERED,
                            &word,
                        );
                    }
                }
                continue;
            }
            let Some(bound) = self
                .store
                .update::<Pod>(&key, |p| scheduler::bind(p, &self.node))
            else {
                continue;
            };
            let devices = allocations.bind(&uid, need, node.gpus);
            info!(pod = %key.name, gpus = need, ?devices, "pod scheduled");
            self.start_kubelet(bound);
        }
    }

    /// The GPU indexes bound to pod `uid`.
    pub fn devices(&self, uid: &str) -> Vec<u32> {
        lock(&self.allocations).devices(uid)
    }

    /// Frees a pod's GPUs once its kubelet is done, and schedules what waited for them.
    fn release(self: &Arc<Self>, uid: &str) {
        lock(&self.allocations).release(uid);
        self.schedule();
    }

    /// Starts the kubelet of a bound pod.
    fn start_kubelet(self: &Arc<Self>, pod: Pod) {
        let uid = pod.metadata.uid.clone().unwrap_or_default();
        let grace = pod
            .spec
            .as_ref()
            .and_then(|s| s.termination_grace_period_seconds)
            .map(|s| Duration::from_secs(s.max(0) as u64))
            .unwrap_or(Duration::from_secs(30))
            .min(self.timing.max_grace_period);
        let (stop, stop_rx) = watch::channel(None);
        let (done_tx, done) = watch::channel(false);
        lock(&self.pods).insert(uid.clone(), PodHandle { stop, done, grace });
        let rt = self.clone();
        tokio::spawn(async move {
            kubelet::run_pod(rt.clone(), pod, stop_rx, done_tx).await;
            rt.release(&uid);
        });
    }

    /// Runs a pod another scheduler bound (a node agent's pod from a real control plane):
    /// stored as it came, given GPUs as the device plugin would, and its kubelet started.
    pub fn adopt(self: &Arc<Self>, pod: Pod) -> Result<Pod, ApiError> {
        if self.is_shutting_down() {
            return Err(ApiError::unavailable("local-kube is shutting down"));
        }
        let pod = self.store.create(pod)?;
        let uid = pod.metadata.uid.clone().unwrap_or_default();
        let need = pod.spec.as_ref().map_or(0, scheduler::gpu_request);
        lock(&self.allocations).bind(&uid, need, None);
        self.start_kubelet(pod.clone());
        Ok(pod)
    }

    /// Stops a pod's containers (grace capped) and waits for them, bounded; the object and its
    /// logs stay with the status its kubelet wrote last.
    pub async fn stop_pod(&self, uid: &str, grace: Option<Duration>) {
        let handle = lock(&self.pods)
            .get(uid)
            .map(|h| (h.stop.clone(), h.done.clone(), h.grace));
        if let Some((stop, mut done, default_grace)) = handle {
            let grace = grace
                .unwrap_or(default_grace)
                .min(self.timing.max_grace_period);
            let _ = stop.send(Some(grace));
            let bound = grace + Duration::from_secs(10);
            if tokio::time::timeout(bound, done.wait_for(|d| *d))
                .await
                .is_err()
            {
                warn!(pod = uid, "pod did not stop in time");
            }
        }
    }

    /// Marks a pod deleted (so it shows as terminating) and returns it.
    pub fn mark_pod_deleted(&self, key: &ObjKey, grace: Option<Duration>) -> Option<Pod> {
        let now = time_now();
        self.store.update::<Pod>(key, |p| {
            if p.metadata.deletion_timestamp.is_none() {
                let secs = grace.map(|g| g.as_secs() as i64).unwrap_or_else(|| {
                    p.spec
                        .as_ref()
                        .and_then(|s| s.termination_grace_period_seconds)
                        .unwrap_or(30)
                });
                p.metadata.deletion_timestamp = Some(now);
                p.metadata.deletion_grace_period_seconds = Some(secs);
            }
        })
    }

    /// Deletes a pod: terminates its processes (grace capped), removes its directory, then the
    /// object. Bounded.
    pub async fn delete_pod(self: &Arc<Self>, key: &ObjKey, grace: Option<Duration>) {
        let Some(pod) = self.mark_pod_deleted(key, grace) else {
            return;
        };
        let uid = pod.metadata.uid.clone().unwrap_or_default();
        self.stop_pod(&uid, grace).await;
        lock(&self.pods).remove(&uid);
        let dir = self.pod_dir(&pod);
        if let Err(e) = std::fs::remove_dir_all(&dir) {
            if e.kind() != std::io::ErrorKind::NotFound {
                warn!(dir = %dir.display(), error = %e, "cannot remove pod directory");
            }
        }
        // NB: only the incarnation we stopped is touched, not a new pod of the same name.
        let current = self
            .store
            .get::<Pod>(key)
            .filter(|p| p.metadata.uid.as_deref() == Some(uid.as_str()));
        if let Some(current) = current {
            if self.counted_by_its_job(&current) {
                // The kubelet moves a deleted pod to a terminal phase; the Job controller
                // counts it, then drops its finalizer, and only then is the object gone
                // (Kubernetes docs, "Pod disruption conditions"; "Job tracking with finalizers").
                self.store.update::<Pod>(key, |p| {
                    let status = p.status.get_or_insert_with(Default::default);
                    if !matches!(status.phase.as_deref(), Some("Succeeded" | "Failed")) {
                        status.phase = Some("Failed".into());
                    }
                });
            } else {
                self.store.remove::<Pod>(key);
            }
        }
        lock(&self.events).forget(&uid);
        if let Some(owner) = controller_uid(&pod) {
            self.notify_job(&owner);
        }
        info!(pod = %key.name, "pod deleted");
    }

    /// Whether a pod still waits for its Job's controller to count it: it carries the Job's
    /// tracking finalizer and its Job runs (a deleted or finished Job's controller lets its
    /// pods go, as the real one removes the finalizers of orphans).
    fn counted_by_its_job(&self, pod: &Pod) -> bool {
        let tracked = pod
            .metadata
            .finalizers
            .iter()
            .flatten()
            .any(|f| f == crate::objects::JOB_TRACKING_FINALIZER);
        let Some(owner) = pod
            .metadata
            .owner_references
            .iter()
            .flatten()
            .find(|r| r.controller == Some(true) && r.kind == "Job")
        else {
            return false;
        };
        let ns = pod.metadata.namespace.as_deref().unwrap_or_default();
        let job = self.store.get::<Job>(&ObjKey::new(ns, &owner.name));
        let running = job.is_some_and(|j| {
            let finished = j
                .status
                .iter()
                .flat_map(|s| s.conditions.iter().flatten())
                .any(|c| (c.type_ == "Complete" || c.type_ == "Failed") && c.status == "True");
            j.metadata.uid.as_deref() == Some(owner.uid.as_str())
                && j.metadata.deletion_timestamp.is_none()
                && !finished
        });
        tracked && running
    }

    fn owned_pods(&self, namespace: &str, uid: &str) -> Vec<ObjKey> {
        let (pods, _) = self.store.list::<Pod>(Some(namespace), |p| {
            controller_uid(p).as_deref() == Some(uid)
        });
        pods.iter().map(|p| ObjKey::of(&p.metadata)).collect()
    }

    /// Leaves the pods of the Job `uid` without that owner (orphan propagation).
    fn orphan(&self, pods: Vec<ObjKey>, uid: &str) {
        for p in pods {
            self.store.update::<Pod>(&p, |pod| {
                if let Some(refs) = pod.metadata.owner_references.as_mut() {
                    refs.retain(|r| r.uid != uid);
                }
                if pod
                    .metadata
                    .owner_references
                    .as_ref()
                    .is_some_and(Vec::is_empty)
                {
                    pod.metadata.owner_references = None;
                }
            });
        }
    }

    /// Deletes a Job with the given propagation; `uid` is a precondition when set.
    pub async fn delete_job(
        self: &Arc<Self>,
        key: &ObjKey,
        propagation: Propagation,
        grace: Option<Duration>,
        uid_precondition: Option<&str>,
    ) -> Result<Deleted, ApiError> {
        let job = self
            .store
            .get::<Job>(key)
            .ok_or_else(|| ApiError::not_found(&JOBS, &key.name))?;
        let uid = job.metadata.uid.clone().unwrap_or_default();
        if let Some(want) = uid_precondition.filter(|w| *w != uid) {
            return Err(ApiError {
                code: 409,
                reason: "Conflict",
                message: format!(
                    "Precondition failed: UID in precondition: {want}, UID in object meta: {uid}"
                ),
                details: None,
            });
        }
        if job.metadata.deletion_timestamp.is_some() {
            // NB: a second delete of a job being deleted in the foreground just reports it.
            return Ok(Deleted::Pending(Box::new(job)));
        }
        self.stop_job(&uid);
        let pods = self.owned_pods(&key.namespace, &uid);
        info!(job = %key.name, ?propagation, pods = pods.len(), "deleting job");
        match propagation {
            Propagation::Background => {
                self.store.remove::<Job>(key);
                let rt = self.clone();
                tokio::spawn(async move { rt.delete_pods(pods, grace).await });
                Ok(Deleted::Gone(success_status(&JOBS, &key.name, &uid)))
            }
            Propagation::Orphan => {
                self.store.remove::<Job>(key);
                self.orphan(pods, &uid);
                Ok(Deleted::Gone(success_status(&JOBS, &key.name, &uid)))
            }
            Propagation::Foreground => {
                let now = time_now();
                let marked = self
                    .store
                    .update::<Job>(key, |j| {
                        j.metadata.deletion_timestamp = Some(now);
                        j.metadata.deletion_grace_period_seconds = Some(0);
                        j.metadata
                            .finalizers
                            .get_or_insert_with(Vec::new)
                            .push("foregroundDeletion".into());
                    })
                    .ok_or_else(|| ApiError::not_found(&JOBS, &key.name))?;
                let rt = self.clone();
                let job_key = key.clone();
                tokio::spawn(async move {
                    rt.delete_pods(pods, grace).await;
                    let same = rt
                        .store
                        .get::<Job>(&job_key)
                        .is_some_and(|j| j.metadata.uid.as_deref() == Some(uid.as_str()));
                    if same {
                        rt.store.remove::<Job>(&job_key);
                    }
                });
                Ok(Deleted::Pending(Box::new(marked)))
            }
        }
    }

    async fn delete_pods(self: &Arc<Self>, pods: Vec<ObjKey>, grace: Option<Duration>) {
        let mut tasks = Vec::new();
        for p in pods {
            let rt = self.clone();
            tasks.push(tokio::spawn(async move { rt.delete_pod(&p, grace).await }));
        }
        for t in tasks {
            let _ = t.await;
        }
    }

    /// Stops everything, blocking (bounded): no new processes, every group terminated, pod
    /// directories, created mount points and the node's `nvidia-smi` removed.
    pub fn shutdown(&self) {
        if self.shutting_down.swap(true, Ordering::SeqCst) {
            return;
        }
        let _ = self.shutdown_tx.send(true);
        for (_, h) in lock(&self.jobs).drain() {
            let _ = h.stop.send(true);
        }
        for h in lock(&self.pods).values() {
            let _ = h.stop.send(Some(Duration::ZERO));
        }
        self.procs.kill_all(self.timing.max_grace_period);
        if let Ok(entries) = std::fs::read_dir(&self.pods_dir) {
            for e in entries.flatten() {
                let _ = std::fs::remove_dir_all(e.path());
            }
        }
        let _ = std::fs::remove_dir(&self.pods_dir);
        let _ = std::fs::remove_dir_all(&self.nvidia_dir);
        info!("local-kube runtime stopped");
    }
}
