//! The client side: connecting (kubeconfig or EKS), create-or-adopt, observe, delete.

use std::future::Future;
use std::path::Path;
use std::time::Duration;

use k8s_openapi::api::batch::v1::Job;
use k8s_openapi::api::core::v1::{Event, Node, Pod};
use k8s_openapi::jiff::Timestamp;
use kube::api::{Api, DeleteParams, EvictParams, ListParams, Patch, PatchParams, PostParams};
use kube::config::{KubeConfigOptions, Kubeconfig};
use lb_domain::capacity::cost::{CapacityType, NodeKind};
use lb_domain::cluster::disruption::NodeFacts;
use serde::{Deserialize, Serialize};
use tracing::{debug, info, instrument, warn};

use crate::autoscaler::{self, ScaleUpWord};
use crate::error::{ClusterError, Result};
use crate::labels::{self, Whose};
use crate::observe::{self, JobState, Observation};

/// Bounds on talking to the API server.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Timeouts {
    /// Establishing a connection (TCP and TLS).
    pub connect: Duration,
    /// Waiting for a response once the request is sent.
    pub read: Duration,
    /// One whole call, including kube's own bounded retries of 429/503/504.
    pub call: Duration,
}

impl Default for Timeouts {
    fn default() -> Self {
        Timeouts {
            connect: Duration::from_secs(5),
            read: Duration::from_secs(20),
            call: Duration::from_secs(30),
        }
    }
}

/// The result of [`Cluster::create_or_adopt`].
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Launched {
    /// The Job's name.
    pub name: String,
    /// Its uid, as the server reports it.
    pub uid: Option<String>,
    /// The submission it belongs to.
    pub submission_id: String,
    /// `true` when it already existed (a retry or a duplicate Launch) and was adopted.
    pub adopted: bool,
    /// `true` when the adopted Job had already completed or failed (a leftover of an earlier
    /// run that was never deleted): the caller decides whether to delete and launch again.
    pub already_ended: bool,
}

/// The result of [`Cluster::delete_all`].
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Deleted {
    /// Jobs whose deletion was requested (their pods go first: foreground propagation).
    pub jobs: Vec<String>,
    /// Pods of the submission that no Job owned any more, deleted directly.
    pub orphan_pods: Vec<String>,
    /// Objects that vanished between the list and the delete.
    pub already_gone: Vec<String>,
    /// Objects from before the execution label, left by a [`Whose::Labelled`] deletion.
    pub unlabelled_left: usize,
}

/// A namespace of a Kubernetes cluster holding submissions' Jobs.
#[derive(Clone)]
pub struct Cluster {
    client: kube::Client,
    namespace: String,
    timeouts: Timeouts,
}

impl std::fmt::Debug for Cluster {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // NB: no client: its config holds the bearer token.
        f.debug_struct("Cluster")
            .field("namespace", &self.namespace)
            .field("timeouts", &self.timeouts)
            .finish_non_exhaustive()
    }
}

impl Cluster {
    /// Wraps an existing client (tests pass one whose transport they answer themselves).
    pub fn new(client: kube::Client, namespace: impl Into<String>) -> Self {
        Cluster {
            client,
            namespace: namespace.into(),
            timeouts: Timeouts::default(),
        }
    }

    /// Connects with a kubeconfig file (local mode, a developer's cluster); `context` defaults
    /// to the file's current context, the namespace to the context's (else `default`).
    ///
    /// Must run inside a Tokio runtime.
    pub async fn from_kubeconfig(path: &Path, context: Option<&str>) -> Result<Self> {
        Self::from_kubeconfig_with(path, context, Timeouts::default()).await
    }

    /// [`Cluster::from_kubeconfig`] with explicit timeouts.
    pub async fn from_kubeconfig_with(
        path: &Path,
        context: Option<&str>,
        timeouts: Timeouts,
    ) -> Result<Self> {
        let config_error =
            |problem: String, e: kube::config::KubeconfigError| ClusterError::Config {
                problem,
                source: Some(Box::new(e)),
            };
        let kubeconfig = Kubeconfig::read_from(path)
            .map_err(|e| config_error(format!("kubeconfig `{}` is unusable", path.display()), e))?;
        let options = KubeConfigOptions {
            context: context.map(str::to_owned),
            ..KubeConfigOptions::default()
        };
        let mut config = kube::Config::from_custom_kubeconfig(kubeconfig, &options)
            .await
            .map_err(|e| {
                let which = context.map_or("the current context".to_string(), |c| {
                    format!("context `{c}`")
                });
                config_error(
                    format!("kubeconfig `{}`: {which} is unusable", path.display()),
                    e,
                )
            })?;
        apply_timeouts(&mut config, &timeouts);
        let namespace = config.default_namespace.clone();
        let client = client_from(config)?;
        Ok(Cluster::new(client, namespace).with_timeouts(timeouts))
    }

    /// Connects to an EKS cluster: `endpoint` and `ca_pem` from `DescribeCluster`, `token` the
    /// EKS IAM bearer token. The token lives ~15 minutes: build a `Cluster` per invocation from
    /// a fresh (cached) token. Namespace `default` until [`Cluster::with_namespace`].
    ///
    /// Must run inside a Tokio runtime.
    pub fn for_eks(endpoint: &str, ca_pem: &[u8], token: &str) -> Result<Self> {
        let timeouts = Timeouts::default();
        let config = eks_config(endpoint, ca_pem, token, &timeouts)?;
        let namespace = config.default_namespace.clone();
        Ok(Cluster::new(client_from(config)?, namespace).with_timeouts(timeouts))
    }

    /// Uses `namespace` for every call.
    pub fn with_namespace(mut self, namespace: impl Into<String>) -> Self {
        self.namespace = namespace.into();
        self
    }

    /// Uses `timeouts.call` as the bound on each call (connect and read bounds are fixed
    /// when the client is built).
    pub fn with_timeouts(mut self, timeouts: Timeouts) -> Self {
        self.timeouts = timeouts;
        self
    }

    /// The namespace of every call.
    pub fn namespace(&self) -> &str {
        &self.namespace
    }

    fn jobs(&self) -> Api<Job> {
        Api::namespaced(self.client.clone(), &self.namespace)
    }

    pub(crate) fn pods(&self) -> Api<Pod> {
        Api::namespaced(self.client.clone(), &self.namespace)
    }

    fn events(&self) -> Api<Event> {
        Api::namespaced(self.client.clone(), &self.namespace)
    }

    pub(crate) fn nodes(&self) -> Api<Node> {
        Api::all(self.client.clone())
    }

    /// Runs one API call under the call bound.
    pub(crate) async fn call<T>(
        &self,
        operation: &'static str,
        fut: impl Future<Output = kube::Result<T>>,
    ) -> Result<kube::Result<T>> {
        tokio::time::timeout(self.timeouts.call, fut)
            .await
            .map_err(|_| ClusterError::Timeout {
                operation,
                limit: self.timeouts.call,
            })
    }

    /// Creates `job`, or adopts the existing Job of that name when it belongs to the same
    /// submission, so retries and duplicate Launches never make a second Job.
    ///
    /// The Job (and its pod template) must carry the submission-id and managed-by labels, or
    /// [`Cluster::observe`] could not find it.
    #[instrument(skip_all, fields(submission_id = tracing::field::Empty, job = tracing::field::Empty))]
    pub async fn create_or_adopt(&self, job: &Job) -> Result<Launched> {
        let (name, submission_id) = self.check_launchable(job)?;
        tracing::Span::current()
            .record("submission_id", submission_id.as_str())
            .record("job", name.as_str());
        let api = self.jobs();
        let created = self
            .call("create job", api.create(&PostParams::default(), job))
            .await?;
        let status = match created {
            Ok(made) => {
                let uid = made.metadata.uid.clone();
                info!(uid = uid.as_deref().unwrap_or(""), "job created");
                return Ok(Launched {
                    name,
                    uid,
                    submission_id,
                    adopted: false,
                    already_ended: false,
                });
            }
            Err(kube::Error::Api(status))
                if status.reason == "AlreadyExists"
                    || (status.code == 409 && status.reason.is_empty()) =>
            {
                status
            }
            Err(e) => {
                let e = ClusterError::from_kube("create job", &format!("Job `{name}`"), e);
                warn!(error = %e, name = e.name(), "job not created");
                return Err(e);
            }
        };
        debug!(message = %status.message, "job exists; checking whose it is");
        self.adopt(job, name, submission_id).await
    }

    /// A Job of this name exists already: adopted when it is this submission's and this
    /// execution's (a retried Launch); an earlier execution's is deleted and the launch retried
    /// once it is gone; another submission's is refused.
    async fn adopt(&self, job: &Job, name: String, submission_id: String) -> Result<Launched> {
        let terminating = |name: String, submission_id: String| ClusterError::JobTerminating {
            job: name,
            submission_id,
        };
        let existing = match self.call("get job", self.jobs().get(&name)).await? {
            Ok(j) => j,
            // NB: it was deleted between our create and get; the next attempt creates it.
            Err(kube::Error::Api(s)) if s.is_not_found() => {
                return Err(terminating(name, submission_id))
            }
            Err(e) => {
                return Err(ClusterError::from_kube(
                    "get job",
                    &format!("Job `{name}`"),
                    e,
                ))
            }
        };
        let owner = existing
            .metadata
            .labels
            .as_ref()
            .and_then(|l| l.get(labels::SUBMISSION_ID))
            .cloned();
        if owner.as_deref() != Some(submission_id.as_str()) {
            let e = ClusterError::JobNameTaken {
                job: name,
                submission_id,
                owner: owner.unwrap_or_else(|| "<none>".into()),
            };
            warn!(error = %e, "job name taken");
            return Err(e);
        }
        if existing.metadata.deletion_timestamp.is_some() {
            // A resume launched while the previous run's Job is still being deleted.
            return Err(terminating(name, submission_id));
        }
        let ours = labels::execution_of(job.metadata.labels.as_ref());
        let theirs = labels::execution_of(existing.metadata.labels.as_ref());
        if let (Some(ours), Some(theirs)) = (ours, theirs) {
            if ours != theirs {
                // An earlier execution's Job (the submission was resumed, and the claim moved
                // to us): it is replaced, never adopted, so that our Finalize, which deletes
                // only our execution's Jobs, leaves nothing behind.
                warn!(
                    execution = theirs,
                    "job of an earlier execution; deleting it to launch ours"
                );
                self.delete_job(&name).await?;
                return Err(terminating(name, submission_id));
            }
        }
        let uid = existing.metadata.uid.clone();
        let already_ended = matches!(
            observe::job_state(&existing),
            JobState::Complete | JobState::Failed { .. }
        );
        info!(
            uid = uid.as_deref().unwrap_or(""),
            already_ended, "existing job adopted"
        );
        Ok(Launched {
            name,
            uid,
            submission_id,
            adopted: true,
            already_ended,
        })
    }

    /// Deletes Job `name` in the foreground: `false` when it was gone already.
    async fn delete_job(&self, name: &str) -> Result<bool> {
        let deleted = self
            .call(
                "delete job",
                self.jobs().delete(name, &DeleteParams::foreground()),
            )
            .await?;
        match deleted {
            Ok(_) => Ok(true),
            Err(kube::Error::Api(s)) if s.is_not_found() => Ok(false),
            Err(e) => Err(ClusterError::from_kube(
                "delete job",
                &format!("Job `{name}`"),
                e,
            )),
        }
    }

    /// Deletes Pod `name`: `false` when it was gone already.
    async fn delete_pod(&self, name: &str) -> Result<bool> {
        let deleted = self
            .call(
                "delete pod",
                self.pods().delete(name, &DeleteParams::default()),
            )
            .await?;
        match deleted {
            Ok(_) => Ok(true),
            Err(kube::Error::Api(s)) if s.is_not_found() => Ok(false),
            Err(e) => Err(ClusterError::from_kube(
                "delete pod",
                &format!("Pod `{name}`"),
                e,
            )),
        }
    }

    /// The Job's name and submission id, once it is known to be trackable.
    fn check_launchable(&self, job: &Job) -> Result<(String, String)> {
        let name = job.metadata.name.clone().unwrap_or_default();
        let invalid = |problem: String| ClusterError::InvalidJobSpec {
            job: if name.is_empty() {
                "<unnamed>".into()
            } else {
                name.clone()
            },
            problem,
        };
        if name.is_empty() {
            return Err(invalid("it has no `metadata.name`".into()));
        }
        if let Some(ns) = &job.metadata.namespace {
            if ns != &self.namespace {
                return Err(invalid(format!(
                    "its namespace `{ns}` is not the cluster namespace `{}`",
                    self.namespace
                )));
            }
        }
        let job_labels = job.metadata.labels.clone().unwrap_or_default();
        let Some(submission_id) = job_labels.get(labels::SUBMISSION_ID).cloned() else {
            return Err(invalid(format!(
                "it has no `{}` label",
                labels::SUBMISSION_ID
            )));
        };
        labels::validate_submission_id(&submission_id)?;
        let pod_labels = job
            .spec
            .as_ref()
            .and_then(|s| s.template.metadata.as_ref())
            .and_then(|m| m.labels.clone())
            .unwrap_or_default();
        for (what, l) in [("the Job", &job_labels), ("its pod template", &pod_labels)] {
            if l.get(labels::SUBMISSION_ID) != Some(&submission_id) {
                return Err(invalid(format!(
                    "{what} lacks `{}={submission_id}`",
                    labels::SUBMISSION_ID
                )));
            }
            if l.get(labels::MANAGED_BY).map(String::as_str) != Some(labels::MANAGED_BY_VALUE) {
                return Err(invalid(format!(
                    "{what} lacks `{}={}`",
                    labels::MANAGED_BY,
                    labels::MANAGED_BY_VALUE
                )));
            }
        }
        Ok((name, submission_id))
    }

    /// Lists the submission's Jobs and Pods and maps them to an [`Observation`] now, as seen:
    /// no autoscaler word yet ([`Cluster::autoscaler_word`] reads it when asked).
    #[instrument(skip(self))]
    pub async fn observe(&self, submission_id: &str) -> Result<Observation> {
        let (jobs, pods) = self.list(submission_id).await?;
        let obs = observe::observe(submission_id, &jobs, &pods, Timestamp::now());
        debug!(jobs = obs.jobs.len(), restarts = obs.restarts(), "observed");
        Ok(obs)
    }

    /// The Cluster Autoscaler's latest word on pod `uid`, from the events about it. Advisory:
    /// a refusal (a Role without `list` on events) or a timeout leaves the pod to the
    /// scheduler's own limits, logged, and never fails the round.
    pub async fn autoscaler_word(&self, uid: &str) -> Option<ScaleUpWord> {
        let params = ListParams::default().fields(&format!("involvedObject.uid={uid}"));
        match self.call("list events", self.events().list(&params)).await {
            Ok(Ok(list)) => autoscaler::latest_word(&list.items, uid),
            Ok(Err(e)) => {
                warn!(pod_uid = uid, error = %e, "cannot list the pod's events; the autoscaler's word is not read");
                None
            }
            Err(e) => {
                warn!(pod_uid = uid, error = %e, "listing the pod's events timed out");
                None
            }
        }
    }

    /// What node `name` is, from the labels its node group gives it
    /// (`node.kubernetes.io/instance-type`, `eks.amazonaws.com/capacityType`): what a pod on
    /// it costs; and what its object says of its going: cordoned, its taints, `Ready`. One
    /// read for both. `None` when the node is gone (a reclaimed one goes soon after its pods).
    pub async fn node(&self, name: &str) -> Result<Option<(NodeKind, NodeFacts)>> {
        let node = self
            .call("get node", self.nodes().get_opt(name))
            .await?
            .map_err(|e| ClusterError::from_kube("get node", name, e))?;
        Ok(node.map(|node| (kind_of(&node), facts_of(&node))))
    }

    /// Sets Job `name`'s `activeDeadlineSeconds` to `seconds` (a merge patch: the field is
    /// mutable, and the Job controller re-arms its timer when it changes). `Ok(false)` when
    /// the Job is gone.
    pub async fn set_deadline(&self, name: &str, seconds: u64) -> Result<bool> {
        let patch = Patch::Merge(serde_json::json!({
            "spec": { "activeDeadlineSeconds": seconds }
        }));
        let patched = self
            .call(
                "patch job",
                self.jobs().patch(name, &PatchParams::default(), &patch),
            )
            .await?;
        match patched {
            Ok(_) => {
                info!(job = name, seconds, "Job deadline set");
                Ok(true)
            }
            Err(kube::Error::Api(s)) if s.is_not_found() => Ok(false),
            Err(e) => Err(ClusterError::from_kube(
                "patch job",
                &format!("Job `{name}`"),
                e,
            )),
        }
    }

    /// Evicts pod `name` through the Eviction API: the pod gets `DisruptionTarget` (reason
    /// `EvictionByEvictionAPI`), so its Job's failure policy ignores it and the Job starts a
    /// pod in its place, where the scheduler finds room. `Ok(false)` when the pod is gone or
    /// already going (nothing moved).
    pub async fn evict(&self, name: &str) -> Result<bool> {
        let pods = self.pods();
        let evicted = self
            .call("evict pod", pods.evict(name, &EvictParams::default()))
            .await?;
        match evicted {
            Ok(_) => {
                info!(pod = name, "pod evicted from a drained node");
                Ok(true)
            }
            Err(kube::Error::Api(s)) if s.is_not_found() || s.code == 409 || s.code == 429 => {
                Ok(false)
            }
            Err(e) => Err(ClusterError::from_kube(
                "evict pod",
                &format!("Pod `{name}`"),
                e,
            )),
        }
    }

    /// The submission's Jobs and Pods, as the server lists them.
    pub async fn list(&self, submission_id: &str) -> Result<(Vec<Job>, Vec<Pod>)> {
        let params = ListParams::default().labels(&labels::submission_selector(submission_id)?);
        let job_api = self.jobs();
        let pod_api = self.pods();
        let (jobs, pods) = tokio::join!(
            self.call("list jobs", job_api.list(&params)),
            self.call("list pods", pod_api.list(&params)),
        );
        let jobs = jobs?.map_err(|e| ClusterError::from_kube("list jobs", "", e))?;
        let pods = pods?.map_err(|e| ClusterError::from_kube("list pods", "", e))?;
        Ok((jobs.items, pods.items))
    }

    /// Deletes every Job of the submission with foreground propagation (their pods go first),
    /// then any pod of the submission no Job owns. Idempotent: what is already gone is fine.
    ///
    /// `whose` says which: a stale execution never deletes the Jobs of the one holding the
    /// submission now.
    #[instrument(skip(self))]
    pub async fn delete_all(&self, submission_id: &str, whose: Whose<'_>) -> Result<Deleted> {
        // Pods are told from Jobs by their owner, not by when they were listed: both lists at
        // once, then every deletion at once (a Finalize waits on each round trip).
        let (jobs, pods) = self.list(submission_id).await?;
        let unlabelled_left = (jobs.iter().map(|j| &j.metadata))
            .chain(pods.iter().map(|p| &p.metadata))
            .filter(|meta| whose.leaves_unlabelled(meta.labels.as_ref()))
            .count();
        let ours = whose.taker();
        let owned = |p: &Pod| {
            p.metadata
                .owner_references
                .iter()
                .flatten()
                .any(|o| o.kind == "Job")
        };
        let jobs: Vec<String> = (jobs.iter())
            .filter(|j| ours(j.metadata.labels.as_ref()))
            .filter_map(|j| j.metadata.name.clone())
            .collect();
        let orphans: Vec<String> = (pods.iter())
            .filter(|p| !owned(p) && ours(p.metadata.labels.as_ref()))
            .filter_map(|p| p.metadata.name.clone())
            .collect();
        let (jobs, orphans) = tokio::join!(
            at_once(&jobs, |name| self.delete_job(name)),
            at_once(&orphans, |name| self.delete_pod(name)),
        );
        let mut deleted = Deleted {
            unlabelled_left,
            ..Deleted::default()
        };
        for (name, gone_now) in jobs? {
            match gone_now {
                true => deleted.jobs.push(name),
                false => deleted.already_gone.push(name),
            }
        }
        for (name, gone_now) in orphans? {
            match gone_now {
                true => deleted.orphan_pods.push(name),
                false => deleted.already_gone.push(name),
            }
        }
        info!(
            jobs = deleted.jobs.len(),
            orphan_pods = deleted.orphan_pods.len(),
            already_gone = deleted.already_gone.len(),
            "deletion requested"
        );
        Ok(deleted)
    }

    /// Polls (at most until `timeout`) until the submission has no Job and no Pod left (of
    /// `whose`, as [`Cluster::delete_all`] selects them). The first looks come soon and
    /// then every `poll` ([`next_look`]): a finished run's pods go within a fraction of a
    /// second, a running one's take their grace period. `Ok(true)` when gone, `Ok(false)` when
    /// time ran out first.
    #[instrument(skip(self))]
    pub async fn wait_gone(
        &self,
        submission_id: &str,
        whose: Whose<'_>,
        timeout: Duration,
        poll: Duration,
    ) -> Result<bool> {
        let deadline = tokio::time::Instant::now() + timeout;
        let poll = poll.max(Duration::from_millis(10));
        let mut wait = Duration::ZERO;
        let takes = whose.taker();
        loop {
            let (mut jobs, mut pods) = self.list(submission_id).await?;
            jobs.retain(|j| takes(j.metadata.labels.as_ref()));
            pods.retain(|p| takes(p.metadata.labels.as_ref()));
            if jobs.is_empty() && pods.is_empty() {
                return Ok(true);
            }
            let now = tokio::time::Instant::now();
            if now >= deadline {
                debug!(
                    jobs = jobs.len(),
                    pods = pods.len(),
                    "still there at the deadline"
                );
                return Ok(false);
            }
            wait = next_look(wait, poll);
            tokio::time::sleep(wait.min(deadline - now)).await;
        }
    }
}

/// Deletions asked at most this many at a time (a submission has a Job per worker).
const DELETES_AT_ONCE: usize = 16;

/// `delete` of each name, [`DELETES_AT_ONCE`] at a time, each name with its answer in the
/// order given; the first error wins.
async fn at_once<'a, F>(
    names: &'a [String],
    delete: impl Fn(&'a str) -> F,
) -> Result<Vec<(String, bool)>>
where
    F: std::future::Future<Output = Result<bool>> + 'a,
{
    let mut answers = Vec::with_capacity(names.len());
    for chunk in names.chunks(DELETES_AT_ONCE) {
        let asked = chunk.iter().map(|name| delete(name));
        for (name, answer) in chunk
            .iter()
            .zip(futures_util::future::join_all(asked).await)
        {
            answers.push((name.clone(), answer?));
        }
    }
    Ok(answers)
}

/// What a node is, from the labels its node group gives it
/// (`node.kubernetes.io/instance-type`, `eks.amazonaws.com/capacityType`): what a pod on it
/// costs.
pub(crate) fn kind_of(node: &Node) -> NodeKind {
    let labels = node.metadata.labels.as_ref();
    let label = |key: &str| labels.and_then(|l| l.get(key)).map(String::as_str);
    NodeKind {
        instance_type: label("node.kubernetes.io/instance-type")
            .unwrap_or("unknown")
            .to_string(),
        capacity: CapacityType::from_label(label(lb_domain::settings::Capacity::LABEL)),
    }
}

/// What the node's object says of its going: cordoned, its taints' keys, `Ready`.
pub(crate) fn facts_of(node: &Node) -> NodeFacts {
    let conditions = node.status.as_ref().and_then(|s| s.conditions.as_ref());
    let ready =
        (conditions.into_iter().flatten()).any(|c| c.type_ == "Ready" && c.status == "True");
    let spec = node.spec.as_ref();
    NodeFacts {
        unschedulable: spec.and_then(|s| s.unschedulable).unwrap_or(false),
        taints: (spec.and_then(|s| s.taints.as_ref()).into_iter().flatten())
            .map(|t| t.key.clone())
            .collect(),
        ready,
    }
}

/// The wait before the next look when the last waited `previous` (zero before the first):
/// a sixteenth of `poll` first, doubling up to `poll`.
pub fn next_look(previous: Duration, poll: Duration) -> Duration {
    if previous.is_zero() {
        (poll / 16).max(Duration::from_millis(10)).min(poll)
    } else {
        (previous * 2).min(poll)
    }
}

fn apply_timeouts(config: &mut kube::Config, timeouts: &Timeouts) {
    config.connect_timeout = Some(timeouts.connect);
    config.read_timeout = Some(timeouts.read);
    config.write_timeout = Some(timeouts.read);
    // NB: with a read timeout, count it from the request, not from when a pooled
    // connection went idle.
    config.reset_reader_on_write = true;
}

/// The kube config of an EKS cluster: `https` endpoint, its CA (PEM) as the only root, the
/// bearer token, bounded timeouts.
pub fn eks_config(
    endpoint: &str,
    ca_pem: &[u8],
    token: &str,
    timeouts: &Timeouts,
) -> Result<kube::Config> {
    let problem = |p: String| ClusterError::Config {
        problem: p,
        source: None,
    };
    let url: http::Uri =
        endpoint
            .parse()
            .map_err(|e: http::uri::InvalidUri| ClusterError::Config {
                problem: format!("EKS endpoint `{endpoint}` is not a URL"),
                source: Some(Box::new(e)),
            })?;
    if url.scheme_str() != Some("https") || url.host().is_none() {
        return Err(problem(format!(
            "EKS endpoint `{endpoint}` is not an https URL"
        )));
    }
    let certs: Vec<Vec<u8>> = pem::parse_many(ca_pem)
        .map_err(|e| ClusterError::Config {
            problem: "the cluster CA is not PEM".into(),
            source: Some(Box::new(e)),
        })?
        .into_iter()
        .filter(|p| p.tag() == "CERTIFICATE")
        .map(pem::Pem::into_contents)
        .collect();
    if certs.is_empty() {
        return Err(problem("the cluster CA holds no certificate".into()));
    }
    let token = token.trim();
    if token.is_empty() || token.chars().any(|c| c.is_whitespace() || c.is_control()) {
        return Err(problem(
            "the bearer token is empty or not a single word".into(),
        ));
    }
    let mut config = kube::Config::new(url);
    config.root_cert = Some(certs);
    config.auth_info.token = Some(secrecy::SecretString::from(token.to_owned()));
    apply_timeouts(&mut config, timeouts);
    Ok(config)
}

/// Builds the client; kube spawns its request buffer, hence the runtime check.
fn client_from(config: kube::Config) -> Result<kube::Client> {
    if tokio::runtime::Handle::try_current().is_err() {
        return Err(ClusterError::Config {
            problem: "a Kubernetes client must be built inside a Tokio runtime".into(),
            source: None,
        });
    }
    kube::Client::try_from(config).map_err(|e| ClusterError::Config {
        problem: "cannot build the HTTPS client (bad CA or TLS settings?)".into(),
        source: Some(Box::new(e)),
    })
}

#[cfg(test)]
mod tests {
    use super::next_look;
    use std::time::Duration;

    #[test]
    fn the_first_looks_come_soon_and_then_every_poll() {
        let poll = Duration::from_secs(2);
        let mut wait = Duration::ZERO;
        let waits: Vec<u128> = (0..7)
            .map(|_| {
                wait = next_look(wait, poll);
                wait.as_millis()
            })
            .collect();
        assert_eq!(waits, [125, 250, 500, 1000, 2000, 2000, 2000]);
        // A poll shorter than the floor is not lengthened.
        let short = Duration::from_millis(5);
        assert_eq!(next_look(Duration::ZERO, short), short);
    }
}
