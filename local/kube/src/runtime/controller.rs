//! The job controller of one Job: creates pods, counts successes, failures and restarts as the
//! real controller does, honours the Pod failure policy and the pod replacement policy,
//! enforces backoffLimit and activeDeadlineSeconds, writes Job status, and drops the tracking
//! finalizer of every pod it has counted.

use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::time::Duration;

use k8s_openapi::api::batch::v1::{Job, JobCondition, JobStatus, UncountedTerminatedPods};
use k8s_openapi::api::core::v1::Pod;
use tokio::sync::{watch, Notify};
use tokio::time::Instant;
use tracing::{info, warn};

use super::failure_policy::{self, Outcome, POD_FAILURE_POLICY};
use super::Runtime;
use crate::objects::pod::{controller_uid, is_ready, phase_of, pod_for_job, restarts};
use crate::objects::JOB_TRACKING_FINALIZER;
use crate::store::{time_now, ObjKey};

const COMPLETIONS_REACHED: (&str, &str) = (
    "CompletionsReached",
    "Reached expected number of succeeded pods",
);
const BACKOFF_LIMIT: (&str, &str) = (
    "BackoffLimitExceeded",
    "Job has reached the specified backoff limit",
);
const DEADLINE: (&str, &str) = (
    "DeadlineExceeded",
    "Job was active longer than specified deadline",
);

fn condition(type_: &str, (reason, message): (&str, &str)) -> JobCondition {
    let now = time_now();
    JobCondition {
        type_: type_.into(),
        status: "True".into(),
        reason: Some(reason.into()),
        message: Some(message.into()),
        last_probe_time: Some(now.clone()),
        last_transition_time: Some(now),
    }
}

fn has(status: &JobStatus, type_: &str) -> bool {
    status
        .conditions
        .iter()
        .flatten()
        .any(|c| c.type_ == type_ && c.status == "True")
}

fn interim(status: &JobStatus) -> Option<JobCondition> {
    status
        .conditions
        .iter()
        .flatten()
        .find(|c| {
            (c.type_ == "SuccessCriteriaMet" || c.type_ == "FailureTarget") && c.status == "True"
        })
        .cloned()
}

/// `podReplacementPolicy: Failed`: a terminating pod holds its place until it has failed.
fn replaces_only_failed(spec: &k8s_openapi::api::batch::v1::JobSpec) -> bool {
    spec.pod_replacement_policy.as_deref() == Some("Failed")
}

struct Counts {
    active: Vec<Pod>,
    terminating: i32,
    succeeded: i32,
    failed: i32,
    ready: i32,
    restarts: i32,
}

struct Controller {
    rt: Arc<Runtime>,
    key: ObjKey,
    uid: String,
    started: Instant,
    /// Uids of pods seen Succeeded.
    succeeded: HashSet<String>,
    /// Uids of pods whose failure counts against backoffLimit.
    failed: HashSet<String>,
    /// Uids of failed pods an `Ignore` rule of the Pod failure policy matched.
    ignored: HashSet<String>,
    /// Pods not yet seen finished, as last seen (a pod gone before finishing is judged so).
    unfinished: HashMap<String, Pod>,
    /// The message of the first `FailJob` rule a failed pod matched.
    fail_job: Option<String>,
    failed_seen: i32,
    next_pod_at: Option<Instant>,
}

/// Runs the controller of one Job until it finishes, is deleted or `stop` fires.
pub async fn run(
    rt: Arc<Runtime>,
    key: ObjKey,
    uid: String,
    notify: Arc<Notify>,
    mut stop: watch::Receiver<bool>,
) {
    let mut c = Controller {
        rt,
        key,
        uid,
        started: Instant::now(),
        succeeded: HashSet::new(),
        failed: HashSet::new(),
        ignored: HashSet::new(),
        unfinished: HashMap::new(),
        fail_job: None,
        failed_seen: 0,
        next_pod_at: None,
    };
    let now = time_now();
    c.rt.store.update::<Job>(&c.key, |j| {
        let s = j.status.get_or_insert_with(Default::default);
        s.start_time.get_or_insert(now);
        s.uncounted_terminated_pods
            .get_or_insert_with(UncountedTerminatedPods::default);
    });
    loop {
        if *stop.borrow() || c.rt.is_shutting_down() {
            return;
        }
        let Some(wake) = c.sync().await else { return };
        let sleep = async {
            match wake {
                Some(at) => tokio::time::sleep_until(at).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            _ = notify.notified() => {}
            _ = sleep => {}
            _ = stop.changed() => {}
        }
    }
}

impl Controller {
    fn job(&self) -> Option<Job> {
        let job = self.rt.store.get::<Job>(&self.key)?;
        let same = job.metadata.uid.as_deref() == Some(self.uid.as_str());
        (same && job.metadata.deletion_timestamp.is_none()).then_some(job)
    }

    /// Counts pods as the real controller does: finished pods stay counted after they are
    /// removed, and a pod that disappears before finishing counts as failed. A failed pod is
    /// judged by the Pod failure policy. With `podReplacementPolicy: Failed` a terminating pod
    /// holds its place until it has failed; otherwise it counts as failed at once (Kubernetes
    /// docs, "Delayed creation of replacement pods").
    fn counts(&mut self, job: &Job) -> Counts {
        let ns = self.key.namespace.clone();
        let uid = self.uid.clone();
        let (pods, _) = self.rt.store.list::<Pod>(Some(&ns), |p| {
            controller_uid(p).as_deref() == Some(uid.as_str())
        });
        let spec = job.spec.clone().unwrap_or_default();
        let on_failure = spec
            .template
            .spec
            .as_ref()
            .and_then(|s| s.restart_policy.as_deref())
            == Some("OnFailure");
        let only_failed = replaces_only_failed(&spec);
        let policy = spec.pod_failure_policy.as_ref();
        let mut c = Counts {
            active: Vec::new(),
            terminating: 0,
            succeeded: 0,
            failed: 0,
            ready: 0,
            restarts: 0,
        };
        let mut present = HashSet::new();
        for p in pods {
            let pod_uid = p.metadata.uid.clone().unwrap_or_default();
            present.insert(pod_uid.clone());
            match phase_of(&p) {
                "Succeeded" => {
                    self.unfinished.remove(&pod_uid);
                    self.succeeded.insert(pod_uid);
                    self.release(&p);
                }
                "Failed" => {
                    self.unfinished.remove(&pod_uid);
                    self.judge(&p, policy);
                    self.release(&p);
                }
                _ if p.metadata.deletion_timestamp.is_some() => {
                    c.terminating += 1;
                    if only_failed {
                        self.unfinished.insert(pod_uid, p);
                    } else {
                        self.unfinished.remove(&pod_uid);
                        self.judge(&p, policy);
                    }
                }
                _ => {
                    if is_ready(&p) {
                        c.ready += 1;
                    }
                    if on_failure {
                        c.restarts += restarts(&p);
                    }
                    self.unfinished.insert(pod_uid, p.clone());
                    c.active.push(p);
                }
            }
        }
        let vanished: Vec<String> = self
            .unfinished
            .keys()
            .filter(|u| !present.contains(*u))
            .cloned()
            .collect();
        for u in vanished {
            if let Some(last) = self.unfinished.remove(&u) {
                self.judge(&last, policy);
            }
        }
        c.succeeded = self.succeeded.len() as i32;
        c.failed = self.failed.len() as i32;
        c
    }

    /// Judges a failed pod once: ignored, counted, or counted and failing the Job.
    fn judge(&mut self, pod: &Pod, policy: Option<&k8s_openapi::api::batch::v1::PodFailurePolicy>) {
        let uid = pod.metadata.uid.clone().unwrap_or_default();
        if self.failed.contains(&uid) || self.ignored.contains(&uid) {
            return;
        }
        let name = pod.metadata.name.as_deref().unwrap_or_default();
        match failure_policy::outcome(policy, pod) {
            Outcome::Ignore => {
                info!(job = %self.key.name, pod = name, "pod failure ignored by the Pod failure policy");
                self.ignored.insert(uid);
            }
            Outcome::Count => {
                self.failed.insert(uid);
            }
            Outcome::FailJob(message) => {
                info!(job = %self.key.name, pod = name, %message, "pod failure fails the job");
                self.failed.insert(uid);
                self.fail_job.get_or_insert(message);
            }
        }
    }

    /// Drops the tracking finalizer of a pod counted as finished; a pod being deleted is then
    /// gone, as the API server removes an object whose last finalizer went.
    fn release(&self, pod: &Pod) {
        let tracked = pod
            .metadata
            .finalizers
            .iter()
            .flatten()
            .any(|f| f == JOB_TRACKING_FINALIZER);
        if !tracked {
            return;
        }
        let key = ObjKey::of(&pod.metadata);
        let uid = pod.metadata.uid.clone();
        let released = self.rt.store.update::<Pod>(&key, |p| {
            if p.metadata.uid == uid {
                if let Some(f) = p.metadata.finalizers.as_mut() {
                    f.retain(|x| x != JOB_TRACKING_FINALIZER);
                }
                if p.metadata.finalizers.as_ref().is_some_and(Vec::is_empty) {
                    p.metadata.finalizers = None;
                }
            }
        });
        let gone = released.is_some_and(|p| {
            p.metadata.uid == uid
                && p.metadata.deletion_timestamp.is_some()
                && p.metadata.finalizers.is_none()
        });
        if gone {
            self.rt.store.remove::<Pod>(&key);
        }
    }

    fn write_status(&self, counts: &Counts, extra: impl FnOnce(&mut JobStatus)) {
        self.rt.store.update::<Job>(&self.key, |j| {
            let s = j.status.get_or_insert_with(Default::default);
            let n = counts.active.len() as i32;
            s.active = (n > 0).then_some(n);
            s.ready = Some(counts.ready);
            s.terminating = Some(counts.terminating);
            s.failed = (counts.failed > 0).then_some(counts.failed);
            s.succeeded = (counts.succeeded > 0).then_some(counts.succeeded);
            s.uncounted_terminated_pods
                .get_or_insert_with(UncountedTerminatedPods::default);
            extra(s);
        });
    }

    /// One reconcile pass; `None` when the controller is done, else when to wake at the latest.
    async fn sync(&mut self) -> Option<Option<Instant>> {
        let job = self.job()?;
        let spec = job.spec.clone().unwrap_or_default();
        let status = job.status.clone().unwrap_or_default();
        if has(&status, "Complete") || has(&status, "Failed") {
            return None;
        }
        let counts = self.counts(&job);
        let on_failure = spec
            .template
            .spec
            .as_ref()
            .and_then(|s| s.restart_policy.as_deref())
            == Some("OnFailure");
        let backoff_limit = spec.backoff_limit.unwrap_or(6);
        let deadline = spec
            .active_deadline_seconds
            .map(|s| self.started + Duration::from_secs(s.max(0) as u64));
        let mut target = interim(&status);
        if target.is_none() {
            let complete = match spec.completions {
                Some(n) => counts.succeeded >= n,
                None => counts.succeeded >= 1 && counts.active.is_empty(),
            };
            let restarts_exceeded = on_failure
                && if backoff_limit == 0 {
                    counts.restarts > 0
                } else {
                    counts.restarts >= backoff_limit
                };
            let new = if let Some(message) = self.fail_job.clone() {
                Some(condition(
                    "FailureTarget",
                    (POD_FAILURE_POLICY, message.as_str()),
                ))
            } else if complete {
                Some(condition("SuccessCriteriaMet", COMPLETIONS_REACHED))
            } else if counts.failed > backoff_limit || restarts_exceeded {
                Some(condition("FailureTarget", BACKOFF_LIMIT))
            } else if deadline.is_some_and(|d| Instant::now() >= d) {
                Some(condition("FailureTarget", DEADLINE))
            } else {
                None
            };
            if let Some(cond) = new {
                info!(job = %self.key.name, condition = %cond.type_, reason = ?cond.reason, "job finishing");
                let c = cond.clone();
                self.write_status(&counts, |s| {
                    s.conditions.get_or_insert_with(Vec::new).push(c)
                });
                target = Some(cond);
            }
        }
        if let Some(cond) = target {
            self.finish(&job, cond).await;
            return None;
        }
        self.create_pods(&job, &counts);
        let counts = self.counts(&job);
        self.write_status(&counts, |_| {});
        Some(match (deadline, self.next_pod_at) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        })
    }

    fn create_pods(&mut self, job: &Job, counts: &Counts) {
        let spec = job.spec.clone().unwrap_or_default();
        let parallelism = spec.parallelism.unwrap_or(1);
        let want = match spec.completions {
            Some(n) => parallelism.min(n - counts.succeeded),
            None if counts.succeeded > 0 => 0,
            None => parallelism,
        };
        // NB: a terminating pod holds its place only under `podReplacementPolicy: Failed`.
        let only_failed = replaces_only_failed(&spec);
        let occupied =
            counts.active.len() as i32 + if only_failed { counts.terminating } else { 0 };
        if occupied >= want {
            return;
        }
        if counts.failed > self.failed_seen {
            let timing = &self.rt.timing;
            let exp = (counts.failed - 1).clamp(0, 16) as u32;
            let delay = timing
                .pod_backoff
                .saturating_mul(1 << exp)
                .min(timing.max_backoff);
            self.next_pod_at = Some(Instant::now() + delay);
            self.failed_seen = counts.failed;
        }
        if self.next_pod_at.is_some_and(|at| Instant::now() < at) {
            return;
        }
        self.next_pod_at = None;
        for _ in occupied..want {
            let pod = pod_for_job(job);
            match self.rt.create_pod(pod) {
                Ok(p) => {
                    info!(job = %self.key.name, pod = p.metadata.name.as_deref().unwrap_or_default(), "pod created")
                }
                Err(e) => warn!(job = %self.key.name, error = %e, "pod creation failed"),
            }
        }
    }

    /// Deletes the still-active pods, then adds the final condition.
    async fn finish(&mut self, job: &Job, target: JobCondition) {
        let counts = self.counts(job);
        let failing = target.type_ == "FailureTarget";
        let mut deletions = Vec::new();
        for p in &counts.active {
            let rt = self.rt.clone();
            let key = ObjKey::of(&p.metadata);
            deletions.push(tokio::spawn(async move { rt.delete_pod(&key, None).await }));
        }
        let now = self.counts(job);
        self.write_status(&now, |_| {});
        for d in deletions {
            let _ = d.await;
        }
        // NB: counts() releases every finished pod: nothing is left for a controller that stops.
        let counts = self.counts(job);
        let reason = target.reason.clone().unwrap_or_default();
        let message = target.message.clone().unwrap_or_default();
        let final_type = if failing { "Failed" } else { "Complete" };
        let cond = condition(final_type, (reason.as_str(), message.as_str()));
        let done = time_now();
        self.write_status(&counts, |s| {
            s.conditions.get_or_insert_with(Vec::new).push(cond);
            if !failing {
                s.completion_time = Some(done);
            }
        });
        info!(job = %self.key.name, condition = final_type, reason = %reason, "job finished");
        if let Some(ttl) = job.spec.as_ref().and_then(|s| s.ttl_seconds_after_finished) {
            let rt = self.rt.clone();
            let key = self.key.clone();
            let uid = self.uid.clone();
            tokio::spawn(async move {
                tokio::time::sleep(Duration::from_secs(ttl.max(0) as u64)).await;
                let same = rt
                    .store
                    .get::<Job>(&key)
                    .is_some_and(|j| j.metadata.uid.as_deref() == Some(uid.as_str()));
                if same {
                    let _ = rt
                        .delete_job(&key, super::Propagation::Background, None, None)
                        .await;
                }
            });
        }
    }
}
