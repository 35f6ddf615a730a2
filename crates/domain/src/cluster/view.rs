//! The cluster as the pipeline judges it: each Job, pod and container of a submission as a
//! view, and the one verdict the Monitor acts on (keep waiting, finished, or failed with a
//! message the participant can act on). `lb_cluster::observe` maps the API objects into these.

use std::collections::BTreeMap;
use std::time::Duration;

use jiff::Timestamp;
use serde::{Deserialize, Serialize};

use crate::cluster::autoscaler::{Outlook, ScaleUpWord};
use crate::job::protocol::exit;
use crate::status::PodPhase;

/// Waiting reasons that mean an image will not arrive by waiting.
const PULL_FAILURES: [&str; 4] = [
    "ErrImagePull",
    "ImagePullBackOff",
    "InvalidImageName",
    "ErrImageNeverPull",
];

/// Waiting reasons of a container whose configuration the kubelet cannot apply.
const CONFIG_FAILURES: [&str; 2] = ["CreateContainerConfigError", "CreateContainerError"];

/// Phrases of a pull failure caused by registry throttling, which goes away by itself.
const THROTTLED_PULL: [&str; 3] = ["toomanyrequests", "429 too many requests", "rate limit"];

/// The Job condition reason of a Job whose pods failed more often than its `backoffLimit`.
const OUT_OF_RETRIES: &str = "BackoffLimitExceeded";

/// The reason the verdict gives a Job out of retries by the platform's reclaims alone (no
/// failed pod, no disruption of its own): not a word Kubernetes writes.
const PLATFORM_RECLAIMS: &str = "PlatformReclaims";

/// A pair the Monitor found out of retries, whatever Kubernetes says of its Job.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Spent {
    /// Why, for the participant: whose each charge was.
    pub why: String,
    /// Every charge was the platform's (reclaims past the free ones): not the participant's
    /// failure.
    pub by_platform: bool,
}

/// Longest piece of a Kubernetes message copied into a participant message.
const MAX_QUOTED: usize = 600;

/// How patient the verdict is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct VerdictPolicy {
    /// A pod unschedulable for this long makes the submission hopeless. Generous by default:
    /// the cluster autoscaler needs minutes to add a GPU node, longer when capacity is short.
    pub unschedulable_limit: Duration,
    /// How long a pod may wait for capacity (`Insufficient nvidia.com/gpu`, `cpu`, `memory`,
    /// `Too many pods`: what frees up or what the autoscaler adds): a full cluster is a queue,
    /// and only this bound (a leaderboard setting, `max_queue_hours`) ends the wait.
    pub queue_limit: Duration,
    /// A container that cannot be created (`CreateContainerConfigError`: a missing Secret or
    /// ConfigMap, an unsupported volume) this long after its pod started makes the submission
    /// hopeless; Kubernetes retries forever, so without this the Job would hold its node
    /// until the deadline.
    pub config_error_limit: Duration,
    /// How long a pod waits before the Cluster Autoscaler's word that no node group could ever
    /// hold it is believed: the autoscaler re-simulates every 10 s, and a node group's
    /// template can be incomplete just after a node joined (its GPUs not yet advertised).
    pub never_fits_grace: Duration,
}

impl Default for VerdictPolicy {
    fn default() -> Self {
        VerdictPolicy {
            unschedulable_limit: Duration::from_secs(30 * 60),
            queue_limit: Duration::from_secs(24 * 3600),
            config_error_limit: Duration::from_secs(10 * 60),
            never_fits_grace: Duration::from_secs(5 * 60),
        }
    }
}

/// Everything the pipeline needs to know about a submission's Jobs at one instant.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Observation {
    /// The EvalAI submission id.
    pub submission_id: String,
    /// When the mapping was made (the clock that measured unschedulable durations).
    pub observed_at: Timestamp,
    /// The submission's Jobs, by index then name, each with its Pods.
    pub jobs: Vec<JobView>,
    /// Pods labelled with the submission whose Job is not among `jobs` (leftovers of a
    /// deleted Job). They never decide the verdict.
    pub stray_pods: Vec<PodView>,
}

/// One Job.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct JobView {
    /// Its name.
    pub name: String,
    /// The `job-index` label, when it is a number.
    pub index: Option<u32>,
    /// Where it is in its life.
    pub state: JobState,
    /// Pods running now (`status.active`).
    pub active: i32,
    /// Pods ready now (`status.ready`).
    pub ready: i32,
    /// Pods that succeeded.
    pub succeeded: i32,
    /// Pods that failed (a container restart in place does not count, a pod replacement does).
    pub failed: i32,
    /// When the Job controller started it.
    pub start_time: Option<Timestamp>,
    /// When it completed.
    pub completion_time: Option<Timestamp>,
    /// Whether it is being deleted.
    pub terminating: bool,
    /// Its `activeDeadlineSeconds`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub deadline: Option<u64>,
    /// Its `backoffLimit`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub backoff_limit: Option<u32>,
    /// Its Pods, by name.
    pub pods: Vec<PodView>,
}

/// Life stage of a Job, from its conditions.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "state")]
pub enum JobState {
    /// Created, no pod running yet.
    Pending,
    /// At least one pod active.
    Running,
    /// `spec.suspend` is set: nothing runs until someone resumes it.
    Suspended,
    /// `Complete` (or `SuccessCriteriaMet`, while its pods finish terminating).
    Complete,
    /// `Failed` (or `FailureTarget`, while its pods are being terminated).
    Failed {
        /// The condition reason: `BackoffLimitExceeded`, `DeadlineExceeded`, ...
        reason: String,
        /// The condition message.
        message: String,
    },
}

/// One Pod.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct PodView {
    /// Its name.
    pub name: String,
    /// The Job it belongs to (owner reference or `job-name` label).
    pub job: Option<String>,
    /// `Pending`, `Running`, `Succeeded`, `Failed` or `Unknown`.
    pub phase: PodPhase,
    /// `status.reason`, e.g. `Evicted`.
    pub reason: Option<String>,
    /// `status.message`.
    pub message: Option<String>,
    /// The node it runs on.
    pub node: Option<String>,
    /// When the kubelet accepted it.
    pub start_time: Option<Timestamp>,
    /// Whether it is being deleted.
    pub terminating: bool,
    /// Its uid.
    #[serde(default)]
    pub uid: Option<String>,
    /// Its `nodeSelector` as `key=value,...` (the GPU model, the capacity type when pinned).
    #[serde(default)]
    pub node_selector: Option<String>,
    /// The reason of its `DisruptionTarget` condition (`EvictionByEvictionAPI`, ...): the
    /// control plane is taking it away, and its Job will not count it as a failure.
    #[serde(default)]
    pub disruption: Option<String>,
    /// That condition's message: the kubelet's tells a node shutdown from node pressure
    /// (`lb_domain::cluster::disruption::classify`). Kept short.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub disruption_message: Option<String>,
    /// The GPUs (`nvidia.com/gpu`) it holds while it runs: its containers' limits added up.
    #[serde(default)]
    pub gpus: u32,
    /// Set while the scheduler cannot place it.
    pub unschedulable: Option<Unschedulable>,
    /// The Cluster Autoscaler's latest word on it, when asked
    /// ([`Observation::needs_autoscaler_word`]).
    #[serde(default)]
    pub autoscaler: Option<ScaleUpWord>,
    /// Init containers, then containers, in spec order.
    pub containers: Vec<ContainerView>,
}

/// The scheduler's complaint about a pod.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Unschedulable {
    /// Since when (`lastTransitionTime` of `PodScheduled`), when known.
    pub since: Option<Timestamp>,
    /// The scheduler's message (`0/3 nodes are available: ...`).
    pub message: String,
}

/// One container of a pod.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ContainerView {
    /// Its name (`simulator-1`, `agent-1`, `logcopy`, `private-contents`).
    pub name: String,
    /// The image as the spec names it.
    pub image: String,
    /// Whether it is an init container.
    pub init: bool,
    /// What it is doing now.
    pub state: ContainerState,
    /// Whether it passes its readiness check.
    pub ready: bool,
    /// How often the kubelet restarted it in place.
    pub restart_count: i32,
    /// How its previous run ended.
    pub last_exit: Option<Exit>,
    /// The digest of the image it runs (`sha256:...`), as the kubelet reports it once pulled.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub digest: Option<String>,
}

/// A container's current state.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "state")]
pub enum ContainerState {
    /// No status yet (the pod is not scheduled, or the kubelet has not reported).
    NotCreated,
    /// Waiting: `ContainerCreating`, `PodInitializing`, `CrashLoopBackOff`, `ImagePullBackOff`, ...
    Waiting {
        /// The kubelet's reason.
        reason: String,
        /// The kubelet's message.
        message: Option<String>,
    },
    /// Running.
    Running {
        /// Since when.
        started_at: Option<Timestamp>,
    },
    /// Ended.
    Terminated(Exit),
}

/// How a container run ended.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Exit {
    /// Exit code.
    pub exit_code: i32,
    /// `Completed`, `Error`, `OOMKilled`, ...
    pub reason: Option<String>,
    /// Termination message.
    pub message: Option<String>,
    /// When.
    pub finished_at: Option<Timestamp>,
}

/// What the Monitor should do about the submission.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "verdict")]
pub enum Verdict {
    /// Keep waiting: pending, running, restarting.
    Running,
    /// Every Job is complete.
    Finished,
    /// Nothing good will come from waiting.
    Failed {
        /// Why, as a stable name.
        kind: FailureKind,
        /// The Job concerned, when one is.
        job: Option<String>,
        /// The container concerned, when one is.
        container: Option<String>,
        /// A message the participant can read and act on.
        message: String,
    },
}

impl Verdict {
    /// Whether the submission's Jobs will not change by themselves any more.
    pub fn is_terminal(&self) -> bool {
        !matches!(self, Verdict::Running)
    }
}

/// Why a submission failed, as the Monitor sees it from Kubernetes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum FailureKind {
    /// The participant's image cannot be pulled or is not a valid reference.
    ParticipantImagePull,
    /// One of the evaluation's own images cannot be pulled.
    InfrastructureImagePull,
    /// A container cannot be created (its configuration refers to something missing).
    ContainerConfig,
    /// A pod stayed unschedulable longer than the policy allows.
    Unschedulable,
    /// The Cluster Autoscaler found no node group a new node of which could hold a pod (no
    /// group offers the instance type, or the request is larger than its nodes).
    NoNodeFits,
    /// A Job failed more often than its backoff limit.
    BackoffLimitExceeded,
    /// A Job ran longer than its active deadline.
    DeadlineExceeded,
    /// A container ended in a way no retry can change (the Pod failure policy's `FailJob`).
    NotRetriable,
    /// A Job failed for another reason.
    JobFailed,
    /// A Job of the submission does not exist.
    JobsMissing,
    /// Every pair that gave up was taken away by the platform more often than the free
    /// reclaims allow, none of its pods failing or disrupted by its own doing.
    PlatformReclaims,
}

impl FailureKind {
    /// Every kind.
    pub const ALL: [FailureKind; 11] = [
        FailureKind::ParticipantImagePull,
        FailureKind::InfrastructureImagePull,
        FailureKind::ContainerConfig,
        FailureKind::Unschedulable,
        FailureKind::NoNodeFits,
        FailureKind::BackoffLimitExceeded,
        FailureKind::DeadlineExceeded,
        FailureKind::NotRetriable,
        FailureKind::JobFailed,
        FailureKind::JobsMissing,
        FailureKind::PlatformReclaims,
    ];

    /// The stable PascalCase name.
    pub fn name(self) -> &'static str {
        match self {
            FailureKind::ParticipantImagePull => "ParticipantImagePull",
            FailureKind::InfrastructureImagePull => "InfrastructureImagePull",
            FailureKind::ContainerConfig => "ContainerConfig",
            FailureKind::Unschedulable => "Unschedulable",
            FailureKind::NoNodeFits => "NoNodeFits",
            FailureKind::BackoffLimitExceeded => "BackoffLimitExceeded",
            FailureKind::DeadlineExceeded => "DeadlineExceeded",
            FailureKind::NotRetriable => "NotRetriable",
            FailureKind::JobFailed => "JobFailed",
            FailureKind::JobsMissing => "JobsMissing",
            FailureKind::PlatformReclaims => "PlatformReclaims",
        }
    }

    /// Whether the failure is the platform's own, not the participant's.
    pub fn by_platform(self) -> bool {
        self == FailureKind::PlatformReclaims
    }
}

impl Observation {
    /// Container restarts across every Job's pods.
    pub fn restarts(&self) -> i64 {
        self.jobs
            .iter()
            .flat_map(|j| &j.pods)
            .flat_map(|p| &p.containers)
            .map(|c| i64::from(c.restart_count.max(0)))
            .sum()
    }

    /// When the first Job started, if any has.
    pub fn started_at(&self) -> Option<Timestamp> {
        self.jobs.iter().filter_map(|j| j.start_time).min()
    }

    /// The uid of a pod worth asking the Cluster Autoscaler about: one unschedulable for at
    /// least `never_fits_grace` and not yet heard of. The pairs of a submission request alike,
    /// so one pod speaks for all, and a submission that schedules costs no extra call.
    pub fn needs_autoscaler_word(&self, policy: &VerdictPolicy) -> Option<&str> {
        let pods = self.jobs.iter().flat_map(|j| &j.pods);
        pods.chain(&self.stray_pods)
            .filter(|p| p.phase == PodPhase::Pending && !p.terminating && p.autoscaler.is_none())
            .filter(|p| {
                (p.unschedulable.as_ref().and_then(|u| u.since)).is_some_and(|since| {
                    waited_at_least(self.observed_at, since, policy.never_fits_grace)
                })
            })
            .find_map(|p| p.uid.as_deref())
    }

    /// Gives the pod with uid `uid` the Cluster Autoscaler's latest `word` on it.
    pub fn hear_autoscaler(&mut self, uid: &str, word: ScaleUpWord) {
        let pods = self.jobs.iter_mut().flat_map(|j| &mut j.pods);
        if let Some(pod) = pods
            .chain(&mut self.stray_pods)
            .find(|p| p.uid.as_deref() == Some(uid))
        {
            pod.autoscaler = Some(word);
        }
    }

    /// The verdict on these Jobs as they stand, with `policy`'s patience ([`verdict`]).
    pub fn verdict(&self, policy: &VerdictPolicy) -> Verdict {
        verdict(&self.jobs, self.observed_at, policy)
    }

    /// The verdict on a run of `expected` Jobs whose Jobs in `spent` (by name, with why) are
    /// out of retries, whatever Kubernetes says of them: their pods' disruptions of their own
    /// counted against `backoffLimit` by the Monitor, which the Job controller cannot (its Pod
    /// failure policy ignores every `DisruptionTarget`). Each such pair gives up as a Job past
    /// its `backoffLimit` does: its neighbours go on. A Job index below `expected` that is
    /// absent (deleted outside the pipeline, or never created) fails a verdict not already
    /// failed: `Finished` over half the Jobs is not a finished submission.
    pub fn judge(
        &self,
        expected: u32,
        spent: &BTreeMap<String, Spent>,
        policy: &VerdictPolicy,
    ) -> Verdict {
        let seen = self.verdict(policy);
        let missing: Vec<String> = (0..expected)
            .filter(|i| !self.jobs.iter().any(|j| j.index == Some(*i)))
            .map(|i| i.to_string())
            .collect();
        if !missing.is_empty() && !matches!(seen, Verdict::Failed { .. }) {
            return Verdict::Failed {
                kind: FailureKind::JobsMissing,
                job: None,
                container: None,
                message: format!(
                    "the evaluation stopped unexpectedly: its Kubernetes Job(s) with index {} of {expected} no longer exist",
                    missing.join(", ")
                ),
            };
        }
        let jobs_gone = matches!(
            seen,
            Verdict::Failed {
                kind: FailureKind::JobsMissing,
                ..
            }
        );
        if spent.is_empty() || jobs_gone {
            return seen;
        }
        let mut jobs = self.jobs.clone();
        for job in jobs.iter_mut() {
            if let Some(spent) = spent.get(&job.name) {
                let reason = match spent.by_platform {
                    true => PLATFORM_RECLAIMS,
                    false => OUT_OF_RETRIES,
                };
                job.state = JobState::Failed {
                    reason: reason.into(),
                    message: spent.why.clone(),
                };
            }
        }
        verdict(&jobs, self.observed_at, policy)
    }
}

/// The verdict on a submission's Jobs (with their pods) at `now`: an image that cannot be
/// pulled (the participant's first: the one failure they can fix), a Job failed for another
/// reason than its retries, a container that cannot be created, a pod no node takes, then how
/// the Jobs ended.
pub fn verdict(jobs: &[JobView], now: Timestamp, policy: &VerdictPolicy) -> Verdict {
    if jobs.is_empty() {
        return Verdict::Failed {
            kind: FailureKind::JobsMissing,
            job: None,
            container: None,
            message: "the evaluation stopped unexpectedly: its Kubernetes Jobs no longer exist"
                .into(),
        };
    }
    if let Some(failed) = pull_failure(jobs) {
        return failed;
    }
    // One Job per pair, each with its own backoffLimit: a Job out of retries is one pair
    // giving up, and its neighbours go on; the submission ends when they have (below).
    if let Some(job) = jobs
        .iter()
        .find(|j| matches!(&j.state, JobState::Failed { reason, .. } if !gave_up(reason)))
    {
        return job_failed(job);
    }
    if let Some(failed) = config_failure(jobs, now, policy) {
        return failed;
    }
    if let Some(failed) = unschedulable_too_long(jobs, now, policy) {
        return failed;
    }
    if jobs.iter().all(|j| j.state == JobState::Complete) {
        Verdict::Finished
    } else if jobs
        .iter()
        .all(|j| matches!(j.state, JobState::Complete | JobState::Failed { .. }))
    {
        pairs_gave_up(jobs)
    } else {
        Verdict::Running
    }
}

/// Whether a failed Job's reason is its pair giving up (out of retries, or out of free
/// reclaims), which ends the submission only once its neighbours have ended too.
fn gave_up(reason: &str) -> bool {
    reason == OUT_OF_RETRIES || reason == PLATFORM_RECLAIMS
}

/// The pods that can still make progress, with their Jobs: a finished or dying Job's pods say
/// nothing about the future.
fn live(jobs: &[JobView]) -> impl Iterator<Item = (&JobView, &PodView)> {
    jobs.iter()
        .filter(|j| {
            !j.terminating && !matches!(j.state, JobState::Complete | JobState::Failed { .. })
        })
        .flat_map(|j| j.pods.iter().map(move |p| (j, p)))
        .filter(|(_, p)| !p.terminating && p.phase.is_live())
}

/// `reason: message`, the message quoted, or the reason alone.
fn detail(reason: &str, message: Option<&str>) -> String {
    match message {
        Some(m) if !m.is_empty() => format!("{reason}: {}", quote(m)),
        _ => reason.to_string(),
    }
}

/// An image that will not arrive by waiting: the participant's first, then ours.
fn pull_failure(jobs: &[JobView]) -> Option<Verdict> {
    let mut infra_pull = None;
    for (job, pod) in live(jobs) {
        for c in &pod.containers {
            let ContainerState::Waiting { reason, message } = &c.state else {
                continue;
            };
            if !PULL_FAILURES.contains(&reason.as_str()) || is_throttled(message.as_deref()) {
                continue;
            }
            let detail = detail(reason, message.as_deref());
            if is_participant(&c.name) {
                let message = if reason == "InvalidImageName" {
                    format!(
                        "the submitted image `{}` is not a valid image reference ({detail}); check the image URI you pushed to EvalAI",
                        c.image
                    )
                } else {
                    format!(
                        "the submitted image `{}` could not be pulled ({detail}); check that the image URI is correct and that the image was pushed (and is readable by the evaluation cluster)",
                        c.image
                    )
                };
                return Some(Verdict::Failed {
                    kind: FailureKind::ParticipantImagePull,
                    job: Some(job.name.clone()),
                    container: Some(c.name.clone()),
                    message,
                });
            }
            infra_pull.get_or_insert_with(|| Verdict::Failed {
                kind: FailureKind::InfrastructureImagePull,
                job: Some(job.name.clone()),
                container: Some(c.name.clone()),
                message: format!(
                    "the evaluation could not start: the organizers' image `{}` of container `{}` could not be pulled ({detail}); this is not a problem with your submission",
                    c.image, c.name
                ),
            });
        }
    }
    infra_pull
}

/// A container the kubelet cannot create, past the policy's limit since its pod started.
fn config_failure(jobs: &[JobView], now: Timestamp, policy: &VerdictPolicy) -> Option<Verdict> {
    for (job, pod) in live(jobs) {
        let Some(started) = pod.start_time else {
            continue;
        };
        if !waited_at_least(now, started, policy.config_error_limit) {
            continue;
        }
        for c in &pod.containers {
            let ContainerState::Waiting { reason, message } = &c.state else {
                continue;
            };
            if CONFIG_FAILURES.contains(&reason.as_str()) {
                return Some(Verdict::Failed {
                    kind: FailureKind::ContainerConfig,
                    job: Some(job.name.clone()),
                    container: Some(c.name.clone()),
                    message: format!(
                        "the evaluation could not start: container `{}` could not be created ({}); this is not a problem with your submission",
                        c.name,
                        detail(reason, message.as_deref())
                    ),
                });
            }
        }
    }
    None
}

/// A pod no new node could hold (the autoscaler's word), or one unschedulable longer than its
/// limit: the queue limit when it waits for capacity, the unschedulable limit otherwise.
fn unschedulable_too_long(
    jobs: &[JobView],
    now: Timestamp,
    policy: &VerdictPolicy,
) -> Option<Verdict> {
    for (job, pod) in live(jobs) {
        let Some(u) = &pod.unschedulable else {
            continue;
        };
        let Some(since) = u.since else { continue };
        if let Some(verdict) = never_fits(job, pod, since, now, policy) {
            return Some(verdict);
        }
        let capacity = waits_for_capacity(&u.message);
        let limit = if capacity {
            policy.queue_limit
        } else {
            policy.unschedulable_limit
        };
        if !waited_at_least(now, since, limit) {
            continue;
        }
        let waited = now.as_second().saturating_sub(since.as_second());
        let message = if capacity {
            format!(
                "the evaluation waited {} minutes for free capacity on the cluster, longer than this leaderboard's queue limit of {} hours ({}); it was not started and used none of your time: please submit again later",
                waited / 60,
                limit.as_secs() / 3600,
                quote(&u.message)
            )
        } else {
            format!(
                "the evaluation could not be scheduled on the cluster for {} minutes ({}); please try again later or contact the organizers",
                waited / 60,
                quote(&u.message)
            )
        };
        return Some(Verdict::Failed {
            kind: FailureKind::Unschedulable,
            job: Some(job.name.clone()),
            container: None,
            message,
        });
    }
    None
}

/// The failure of a pod unschedulable since `since` that the Cluster Autoscaler says no new
/// node could hold, once the grace has passed and the word is about this wait.
fn never_fits(
    job: &JobView,
    pod: &PodView,
    since: Timestamp,
    now: Timestamp,
    policy: &VerdictPolicy,
) -> Option<Verdict> {
    let word = pod.autoscaler.as_ref()?;
    let Outlook::Never { reasons } = word.outlook() else {
        return None;
    };
    // NB: a word from before this wait began (an older scheduling attempt) says nothing now.
    if word.at.is_some_and(|at| at < since) || !waited_at_least(now, since, policy.never_fits_grace)
    {
        return None;
    }
    let selector = reasons
        .iter()
        .any(|r| r.contains("didn't match Pod's node affinity/selector"));
    let too_large: Vec<&str> = reasons
        .iter()
        .filter_map(|r| r.split_once("Insufficient ").map(|(_, what)| what))
        .collect();
    let what = match (&pod.node_selector, selector) {
        (Some(labels), true) => format!(
            "no node group of the evaluation cluster offers the nodes this leaderboard runs on (`{labels}`)"
        ),
        _ if !too_large.is_empty() => format!(
            "its pods request more {} than a node of any node group of the evaluation cluster has",
            too_large.join(", ")
        ),
        _ => "no node group of the evaluation cluster can run its pods".to_string(),
    };
    Some(Verdict::Failed {
        kind: FailureKind::NoNodeFits,
        job: Some(job.name.clone()),
        container: None,
        message: format!(
            "the evaluation cannot start: {what} (cluster autoscaler: {}); this is a configuration problem of the leaderboard, not of your submission, and waiting would not help: please contact the organizers. It was not started and used none of your time",
            quote(&reasons.join(", "))
        ),
    })
}

/// Every Job has ended and some ran out of retries: the first one's failure, naming each.
fn pairs_gave_up(jobs: &[JobView]) -> Verdict {
    let mut messages = Vec::new();
    let mut first = None;
    for job in jobs
        .iter()
        .filter(|j| matches!(j.state, JobState::Failed { .. }))
    {
        if let Verdict::Failed { kind, message, .. } = job_failed(job) {
            // The participant's failure names the submission's: the platform's only when
            // every pair that gave up was the platform's.
            let platform = |k: &FailureKind| k.by_platform();
            if first
                .as_ref()
                .is_none_or(|(k, _)| platform(k) && !platform(&kind))
            {
                first = Some((kind, job.name.clone()));
            }
            messages.push(message);
        }
    }
    match first {
        Some((kind, job)) => Verdict::Failed {
            kind,
            job: Some(job),
            container: None,
            message: messages.join("; "),
        },
        None => Verdict::Running,
    }
}

/// Whether `since` is at least `limit` before `now` (a clock behind `since` never is).
/// Whether the scheduler's message says only that the nodes are full (what frees up, or what
/// the autoscaler adds), as kube-scheduler's `NodeResourcesFit` and `NodePorts` word it, as
/// opposed to a pod no node can take (selector, affinity, taints).
pub fn waits_for_capacity(message: &str) -> bool {
    let Some((_, reasons)) = message.split_once("nodes are available:") else {
        return false;
    };
    // The first sentence: "1 Insufficient nvidia.com/gpu, 2 node(s) ...". What follows is
    // the preemption summary, after a word on resource claims from 1.34 on.
    let reasons = reasons.split(" preemption:").next().unwrap_or(reasons);
    let reasons = reasons.split(". ").next().unwrap_or(reasons);
    reasons
        .trim()
        .trim_end_matches('.')
        .split(", ")
        .all(|reason| {
            let reason = reason
                .trim_start_matches(|c: char| c.is_ascii_digit())
                .trim();
            reason.starts_with("Insufficient ")
                || reason == "Too many pods"
                // The control plane's taint: never a place for Jobs, full or not.
                || reason.contains("untolerated taint {node-role.kubernetes.io/control-plane")
        })
}

/// Whether the submission's pairs have started: one of its pods is past `Pending`.
pub fn started(jobs: &[JobView]) -> bool {
    jobs.iter().any(|j| {
        j.state == JobState::Complete
            || j.pods
                .iter()
                .any(|p| p.phase == PodPhase::Running || p.phase.has_ended())
    })
}

/// Whether `since` is at least `limit` before `now`.
pub fn waited_at_least(now: Timestamp, since: Timestamp, limit: Duration) -> bool {
    let waited = now.as_second().saturating_sub(since.as_second());
    waited >= 0 && waited.unsigned_abs() >= limit.as_secs()
}

fn job_failed(job: &JobView) -> Verdict {
    let JobState::Failed { reason, message } = &job.state else {
        return Verdict::Running;
    };
    let detail = if message.is_empty() {
        reason.clone()
    } else {
        format!("{reason}: {}", quote(message))
    };
    let (kind, what) = match reason.as_str() {
        "BackoffLimitExceeded" => (
            FailureKind::BackoffLimitExceeded,
            "its pods failed more often than the retry limit allows",
        ),
        PLATFORM_RECLAIMS => (
            FailureKind::PlatformReclaims,
            "the platform took its pods away more often than the free reclaims allow",
        ),
        "DeadlineExceeded" => (
            FailureKind::DeadlineExceeded,
            "it ran longer than the time limit of an evaluation",
        ),
        "PodFailurePolicy" => (
            FailureKind::NotRetriable,
            failjob_exit_code(message)
                .and_then(exit::meaning)
                .unwrap_or("a container ended in a way no retry can change"),
        ),
        _ => (FailureKind::JobFailed, "Kubernetes marked it failed"),
    };
    Verdict::Failed {
        kind,
        job: Some(job.name.clone()),
        container: None,
        message: format!(
            "the evaluation Job `{}` failed: {what} ({detail}{})",
            job.name,
            failures(job)
        ),
    }
}

/// The exit code in the Job controller's `FailJob` message ("Container agent-1 for pod
/// ns/name failed with exit code 3 matching FailJob rule at index 1").
fn failjob_exit_code(message: &str) -> Option<i32> {
    let (_, rest) = message.split_once("failed with exit code ")?;
    rest.split(' ').next()?.parse().ok()
}

/// How the Job's pods failed: the count, and the failed exits of its last failed pod (every
/// crash ends a pod: `restartPolicy: Never`), or the in-place restarts of older Jobs.
fn failures(job: &JobView) -> String {
    let mut parts = Vec::new();
    if job.failed > 0 {
        parts.push(format!("{} failed pod(s)", job.failed));
    }
    let last_failed = job.pods.iter().rev().find(|p| p.phase == PodPhase::Failed);
    let exits: Vec<String> = last_failed
        .into_iter()
        .flat_map(|p| &p.containers)
        .filter_map(|c| match &c.state {
            ContainerState::Terminated(e) if e.exit_code != 0 => {
                Some(format!("{} exit code {}", c.name, e.exit_code))
            }
            _ => None,
        })
        .collect();
    if !exits.is_empty() {
        parts.push(format!("the last: {}", exits.join(", ")));
    }
    parts.extend(
        job.pods
            .iter()
            .flat_map(|p| &p.containers)
            .filter(|c| c.restart_count > 0)
            .map(|c| match &c.last_exit {
                Some(e) => format!(
                    "{} restarted {}x, last exit code {}",
                    c.name, c.restart_count, e.exit_code
                ),
                None => format!("{} restarted {}x", c.name, c.restart_count),
            }),
    );
    if parts.is_empty() {
        String::new()
    } else {
        format!("; {}", parts.join(", "))
    }
}

/// The agent containers run the participant's image (see the in-Job contract).
fn is_participant(container: &str) -> bool {
    container == "agent" || container.starts_with("agent-")
}

fn is_throttled(message: Option<&str>) -> bool {
    let Some(m) = message else { return false };
    let m = m.to_ascii_lowercase();
    THROTTLED_PULL.iter().any(|p| m.contains(p))
}

/// At most [`MAX_QUOTED`] characters of `text`, marked when cut.
pub fn quote(text: &str) -> String {
    let text = text.trim();
    match text.char_indices().nth(MAX_QUOTED) {
        Some((at, _)) => format!("{}...", &text[..at]),
        None => text.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(hh: i8, mm: i8) -> Timestamp {
        format!("2025-03-14T{hh:02}:{mm:02}:00Z").parse().unwrap()
    }

    fn container(name: &str, state: ContainerState) -> ContainerView {
        ContainerView {
            name: name.into(),
            image: format!("registry/{name}:1"),
            init: false,
            state,
            ready: false,
            restart_count: 0,
            last_exit: None,
            digest: None,
        }
    }

    fn waiting(reason: &str, message: &str) -> ContainerState {
        ContainerState::Waiting {
            reason: reason.into(),
            message: Some(message.into()),
        }
    }

    fn pod(phase: &str, containers: Vec<ContainerView>) -> PodView {
        PodView {
            start_time: Some(at(9, 0)),
            uid: Some("uid".into()),
            containers,
            ..crate::testutil::pod("pod", "job-0", phase.parse().unwrap())
        }
    }

    fn job(name: &str, state: JobState, pods: Vec<PodView>) -> JobView {
        JobView {
            name: name.into(),
            index: name.strip_prefix("job-").and_then(|i| i.parse().ok()),
            state,
            active: 0,
            ready: 0,
            succeeded: 0,
            failed: 0,
            start_time: Some(at(9, 0)),
            completion_time: None,
            terminating: false,
            deadline: None,
            backoff_limit: None,
            pods,
        }
    }

    fn out_of_retries() -> JobState {
        JobState::Failed {
            reason: "BackoffLimitExceeded".into(),
            message: "Job has reached the specified backoff limit".into(),
        }
    }

    fn unschedulable(message: &str) -> PodView {
        PodView {
            phase: PodPhase::Pending,
            start_time: None,
            unschedulable: Some(Unschedulable {
                since: Some(at(9, 0)),
                message: message.into(),
            }),
            ..pod(
                "Pending",
                vec![container("agent-1", ContainerState::NotCreated)],
            )
        }
    }

    const FULL: &str = "0/2 nodes are available: 2 Insufficient nvidia.com/gpu.";
    const NO_MATCH: &str =
        "0/3 nodes are available: 3 node(s) didn't match Pod's node affinity/selector.";

    /// The verdict's kind (`None`: running; `Some(None)`: finished) at `now`.
    fn kind_of(jobs: &[JobView], now: Timestamp) -> Option<Option<FailureKind>> {
        match verdict(jobs, now, &VerdictPolicy::default()) {
            Verdict::Running => None,
            Verdict::Finished => Some(None),
            Verdict::Failed { kind, .. } => Some(Some(kind)),
        }
    }

    #[test]
    fn an_exit_no_retry_can_change_ends_the_submission_at_once_saying_why() {
        let failed_pod = pod(
            "Failed",
            vec![container(
                "agent-1",
                ContainerState::Terminated(Exit {
                    exit_code: 3,
                    reason: Some("Error".into()),
                    message: None,
                    finished_at: None,
                }),
            )],
        );
        let failjob = JobState::Failed {
            reason: "PodFailurePolicy".into(),
            message: "Container agent-1 for pod submissions/lb-7-team-0-x2z9q failed with exit code 3 matching FailJob rule at index 1".into(),
        };
        let jobs = vec![
            job("job-0", failjob, vec![failed_pod]),
            job("job-1", JobState::Running, vec![]),
        ];
        match verdict(&jobs, at(9, 5), &VerdictPolicy::default()) {
            Verdict::Failed { kind, message, .. } => {
                assert_eq!(kind, FailureKind::NotRetriable);
                assert!(
                    message.contains("your image cannot run the Leaderboard evaluator"),
                    "{message}"
                );
                assert!(
                    message.contains("the last: agent-1 exit code 3"),
                    "{message}"
                );
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(
            failjob_exit_code("failed with exit code 78 matching"),
            Some(78)
        );
        assert_eq!(failjob_exit_code("Pod ns/p has condition X matching"), None);
    }

    #[test]
    fn the_verdict_on_each_situation() {
        let running = || {
            pod(
                "Running",
                vec![container(
                    "agent-1",
                    ContainerState::Running {
                        started_at: Some(at(9, 1)),
                    },
                )],
            )
        };
        type Case = (
            &'static str,
            Vec<JobView>,
            Timestamp,
            Option<Option<FailureKind>>,
        );
        let cases: Vec<Case> = vec![
            (
                "no Jobs",
                vec![],
                at(9, 5),
                Some(Some(FailureKind::JobsMissing)),
            ),
            (
                "running",
                vec![job("job-0", JobState::Running, vec![running()])],
                at(9, 5),
                None,
            ),
            (
                "every Job complete",
                vec![
                    job("job-0", JobState::Complete, vec![]),
                    job("job-1", JobState::Complete, vec![]),
                ],
                at(9, 5),
                Some(None),
            ),
            (
                "the participant's image cannot be pulled",
                vec![job(
                    "job-0",
                    JobState::Pending,
                    vec![pod(
                        "Pending",
                        vec![container(
                            "agent-1",
                            waiting("ImagePullBackOff", "not found"),
                        )],
                    )],
                )],
                at(9, 5),
                Some(Some(FailureKind::ParticipantImagePull)),
            ),
            (
                "our image cannot be pulled",
                vec![job(
                    "job-0",
                    JobState::Pending,
                    vec![pod(
                        "Pending",
                        vec![container("simulator-1", waiting("ErrImagePull", "denied"))],
                    )],
                )],
                at(9, 5),
                Some(Some(FailureKind::InfrastructureImagePull)),
            ),
            (
                "a registry's throttle passes by itself",
                vec![job(
                    "job-0",
                    JobState::Pending,
                    vec![pod(
                        "Pending",
                        vec![container(
                            "agent-1",
                            waiting("ErrImagePull", "429 Too Many Requests"),
                        )],
                    )],
                )],
                at(9, 5),
                None,
            ),
            (
                "a container that cannot be created, past its limit",
                vec![job(
                    "job-0",
                    JobState::Pending,
                    vec![pod(
                        "Pending",
                        vec![container(
                            "logcopy",
                            waiting("CreateContainerConfigError", "secret not found"),
                        )],
                    )],
                )],
                at(9, 11),
                Some(Some(FailureKind::ContainerConfig)),
            ),
            (
                "a pair out of retries while another runs",
                vec![
                    job("job-0", out_of_retries(), vec![]),
                    job("job-1", JobState::Running, vec![running()]),
                ],
                at(9, 5),
                None,
            ),
            (
                "every pair ended, one out of retries",
                vec![
                    job("job-0", out_of_retries(), vec![]),
                    job("job-1", JobState::Complete, vec![]),
                ],
                at(9, 5),
                Some(Some(FailureKind::BackoffLimitExceeded)),
            ),
            (
                "a full cluster is a queue",
                vec![job("job-0", JobState::Pending, vec![unschedulable(FULL)])],
                at(12, 0),
                None,
            ),
            (
                "a full cluster past the queue limit",
                vec![job("job-0", JobState::Pending, vec![unschedulable(FULL)])],
                Timestamp::from_second(at(9, 0).as_second() + 24 * 3600).unwrap(),
                Some(Some(FailureKind::Unschedulable)),
            ),
            (
                "no node matches for 30 minutes",
                vec![job(
                    "job-0",
                    JobState::Pending,
                    vec![unschedulable(NO_MATCH)],
                )],
                at(9, 30),
                Some(Some(FailureKind::Unschedulable)),
            ),
        ];
        for (situation, jobs, now, expected) in cases {
            assert_eq!(kind_of(&jobs, now), expected, "{situation}");
        }
    }

    #[test]
    fn the_autoscaler_s_word_that_no_group_fits_ends_the_wait_after_the_grace() {
        let word = |at_| ScaleUpWord {
            reason: crate::cluster::autoscaler::NOT_TRIGGERED.into(),
            message:
                "pod didn't trigger scale-up: 1 node(s) didn't match Pod's node affinity/selector"
                    .into(),
            at: Some(at_),
        };
        let never = |now| {
            let mut pod = unschedulable(FULL);
            pod.autoscaler = Some(word(at(9, 6)));
            kind_of(&[job("job-0", JobState::Pending, vec![pod])], now)
        };
        assert_eq!(never(at(9, 6)), Some(Some(FailureKind::NoNodeFits)));
        assert_eq!(never(at(9, 4)), None, "within the grace");
    }

    #[test]
    fn capacity_is_what_frees_up_or_the_autoscaler_adds() {
        assert!(waits_for_capacity(FULL));
        assert!(waits_for_capacity(
            "0/4 nodes are available: 2 Insufficient cpu, 2 Too many pods."
        ));
        assert!(!waits_for_capacity(NO_MATCH));
        assert!(!waits_for_capacity(""));
        // As kube-scheduler 1.35 words them (local/realkube/contract/scheduler.json).
        assert!(waits_for_capacity(
            "0/1 nodes are available: 1 Insufficient nvidia.com/gpu. no new claims to deallocate, preemption: 0/1 nodes are available: 1 Preemption is not helpful for scheduling."
        ));
        assert!(!waits_for_capacity(
            "0/2 nodes are available: 1 Insufficient nvidia.com/gpu, 1 node(s) didn't match Pod's node affinity/selector. no new claims to deallocate, preemption: 0/2 nodes are available: 2 Preemption is not helpful for scheduling."
        ));
    }

    #[test]
    fn long_kubelet_messages_are_cut_for_the_participant() {
        let long = "é".repeat(1000);
        let cut = quote(&long);
        assert_eq!(cut.chars().count(), MAX_QUOTED + 3);
        assert!(cut.ends_with("..."));
        assert_eq!(quote("  short  "), "short");
    }

    #[test]
    fn the_submission_fails_as_the_platform_s_only_when_every_pair_that_gave_up_was() {
        let deadline = JobState::Failed {
            reason: "DeadlineExceeded".into(),
            message: "Job was active longer than specified deadline".into(),
        };
        let observation = |states: [JobState; 3]| Observation {
            submission_id: "7".into(),
            observed_at: at(10, 0),
            jobs: states
                .into_iter()
                .enumerate()
                .map(|(i, state)| job(&format!("job-{i}"), state, vec![]))
                .collect(),
            stray_pods: vec![],
        };
        let spent = |by_platform: bool| Spent {
            why: format!("spent, by the platform: {by_platform}"),
            by_platform,
        };
        let kind = |states, spent_jobs: &[(&str, Spent)]| {
            let spent: BTreeMap<String, Spent> = spent_jobs
                .iter()
                .map(|(name, s)| (name.to_string(), s.clone()))
                .collect();
            match observation(states).judge(3, &spent, &VerdictPolicy::default()) {
                Verdict::Failed { kind, .. } => Some(kind),
                _ => None,
            }
        };
        let (d, c) = (|| deadline.clone(), || JobState::Complete);
        // One pair the platform took away, its neighbours done: the platform's.
        let platform = kind([d(), c(), c()], &[("job-0", spent(true))]);
        assert_eq!(platform, Some(FailureKind::PlatformReclaims));
        // Another pair spent by its own disruptions, before or after it: the participant's.
        let both = [("job-0", spent(true)), ("job-1", spent(false))];
        assert_eq!(
            kind([d(), d(), c()], &both),
            Some(FailureKind::BackoffLimitExceeded)
        );
        let reversed = [("job-0", spent(false)), ("job-1", spent(true))];
        assert_eq!(
            kind([d(), d(), c()], &reversed),
            Some(FailureKind::BackoffLimitExceeded)
        );
        // A pair out of retries by the Job controller's own count is the participant's too.
        let own = kind([d(), out_of_retries(), c()], &[("job-0", spent(true))]);
        assert_eq!(own, Some(FailureKind::BackoffLimitExceeded));
        // While a neighbour runs, the submission goes on.
        let running = kind([d(), JobState::Running, c()], &[("job-0", spent(true))]);
        assert_eq!(running, None);
    }
}
