//! Pure mapping from a submission's Jobs and Pods (as the API server returns them) to the views
//! `lb_domain::cluster::view` judges: per-Job states, container states, and the verdict on them.

use std::collections::BTreeMap;

use k8s_openapi::api::batch::v1::Job;
use k8s_openapi::api::core::v1::{Container, ContainerStatus, Pod, PodStatus};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::{ObjectMeta, Time};
use k8s_openapi::jiff::Timestamp;

use lb_domain::status::PodPhase;

use crate::labels;
pub use lb_domain::cluster::view::{
    started, verdict, waited_at_least, ContainerState, ContainerView, Exit, FailureKind, JobState,
    JobView, Observation, PodView, Unschedulable, Verdict, VerdictPolicy,
};

/// Maps the listed Jobs and Pods of `submission_id` to an observation at `now`.
pub fn observe(submission_id: &str, jobs: &[Job], pods: &[Pod], now: Timestamp) -> Observation {
    let mut views: Vec<JobView> = jobs.iter().map(job_view).collect();
    views.sort_by(|a, b| (a.index, &a.name).cmp(&(b.index, &b.name)));
    let mut stray_pods = Vec::new();
    let mut pod_views: Vec<PodView> = pods.iter().map(pod_view).collect();
    pod_views.sort_by(|a, b| a.name.cmp(&b.name));
    for pod in pod_views {
        match views
            .iter_mut()
            .find(|j| pod.job.as_deref() == Some(j.name.as_str()))
        {
            Some(job) => job.pods.push(pod),
            None => stray_pods.push(pod),
        }
    }
    Observation {
        submission_id: submission_id.to_string(),
        observed_at: now,
        jobs: views,
        stray_pods,
    }
}

fn ts(t: &Option<Time>) -> Option<Timestamp> {
    t.as_ref().map(|t| t.0)
}

fn name_of(meta: &ObjectMeta) -> String {
    meta.name.clone().unwrap_or_default()
}

/// A Job's life stage from its conditions and counters.
pub(crate) fn job_state(job: &Job) -> JobState {
    let status = job.status.clone().unwrap_or_default();
    let conditions = status.conditions.unwrap_or_default();
    let is_true = |ty: &str| {
        conditions
            .iter()
            .find(|c| c.type_ == ty && c.status == "True")
    };
    if let Some(c) = is_true("Failed").or_else(|| is_true("FailureTarget")) {
        JobState::Failed {
            reason: c.reason.clone().unwrap_or_else(|| "Unknown".into()),
            message: c.message.clone().unwrap_or_default(),
        }
    } else if is_true("Complete")
        .or_else(|| is_true("SuccessCriteriaMet"))
        .is_some()
    {
        JobState::Complete
    } else if is_true("Suspended").is_some() {
        JobState::Suspended
    } else if status.active.unwrap_or(0) > 0 {
        JobState::Running
    } else {
        JobState::Pending
    }
}

fn job_view(job: &Job) -> JobView {
    let status = job.status.clone().unwrap_or_default();
    let active = status.active.unwrap_or(0);
    let state = job_state(job);
    JobView {
        name: name_of(&job.metadata),
        index: job
            .metadata
            .labels
            .as_ref()
            .and_then(|l| l.get(labels::JOB_INDEX))
            .and_then(|v| v.parse().ok()),
        state,
        active,
        ready: status.ready.unwrap_or(0),
        succeeded: status.succeeded.unwrap_or(0),
        failed: status.failed.unwrap_or(0),
        start_time: ts(&status.start_time),
        completion_time: ts(&status.completion_time),
        terminating: job.metadata.deletion_timestamp.is_some(),
        deadline: job
            .spec
            .as_ref()
            .and_then(|s| s.active_deadline_seconds)
            .and_then(|d| u64::try_from(d).ok()),
        backoff_limit: job
            .spec
            .as_ref()
            .and_then(|s| s.backoff_limit)
            .and_then(|b| u32::try_from(b).ok()),
        pods: Vec::new(),
    }
}

fn owning_job(meta: &ObjectMeta) -> Option<String> {
    let owner = meta
        .owner_references
        .iter()
        .flatten()
        .find(|o| o.kind == "Job" && o.api_version.starts_with("batch/"))
        .map(|o| o.name.clone());
    owner.or_else(|| {
        let labels = meta.labels.as_ref()?;
        labels::JOB_NAME_LABELS
            .iter()
            .find_map(|k| labels.get(*k).cloned())
    })
}

fn pod_view(pod: &Pod) -> PodView {
    let status = pod.status.clone().unwrap_or_default();
    let spec = pod.spec.clone().unwrap_or_default();
    let unschedulable = unschedulable_of(&status);
    let init_statuses = index_statuses(status.init_container_statuses.as_deref());
    let statuses = index_statuses(status.container_statuses.as_deref());
    let mut containers: Vec<ContainerView> = spec
        .init_containers
        .iter()
        .flatten()
        .map(|c| container_view(c, init_statuses.get(c.name.as_str()).copied(), true))
        .collect();
    containers.extend(
        spec.containers
            .iter()
            .map(|c| container_view(c, statuses.get(c.name.as_str()).copied(), false)),
    );
    let node_selector = spec
        .node_selector
        .as_ref()
        .filter(|s| !s.is_empty())
        .map(|s| {
            let pairs: Vec<String> = s.iter().map(|(k, v)| format!("{k}={v}")).collect();
            pairs.join(",")
        });
    let (disruption, disruption_message) =
        disruption(&status).map_or((None, None), |(reason, message)| (Some(reason), message));
    PodView {
        name: name_of(&pod.metadata),
        uid: pod.metadata.uid.clone(),
        node_selector,
        disruption,
        disruption_message,
        gpus: gpus(&spec),
        autoscaler: None,
        job: owning_job(&pod.metadata),
        phase: PodPhase::reported(status.phase.as_deref()),
        reason: status.reason,
        message: status.message,
        node: spec.node_name,
        start_time: ts(&status.start_time),
        terminating: pod.metadata.deletion_timestamp.is_some(),
        unschedulable,
        containers,
    }
}

/// The GPUs a pod holds: its containers' `nvidia.com/gpu` limits added up (extended resources
/// are requested by limit; init containers run before, on the same devices).
fn gpus(spec: &k8s_openapi::api::core::v1::PodSpec) -> u32 {
    spec.containers
        .iter()
        .filter_map(|c| c.resources.as_ref()?.limits.as_ref()?.get("nvidia.com/gpu"))
        .filter_map(|q| q.0.trim().parse::<u32>().ok())
        .sum()
}

/// Longest `DisruptionTarget` message kept: the kubelet's own are one sentence.
const MAX_DISRUPTION_MESSAGE: usize = 200;

/// The reason and message of a pod's `DisruptionTarget` condition: something is taking it away
/// (a drained or reclaimed node, preemption, an eviction, the kubelet), and its Job will not
/// count it; whose doing it was is the Monitor's to judge (`lb_domain::cluster::disruption`).
fn disruption(status: &k8s_openapi::api::core::v1::PodStatus) -> Option<(String, Option<String>)> {
    status
        .conditions
        .iter()
        .flatten()
        .find(|c| c.type_ == "DisruptionTarget" && c.status == "True")
        .map(|c| {
            let reason = c
                .reason
                .clone()
                .unwrap_or_else(|| "DisruptionTarget".into());
            let message = c
                .message
                .as_deref()
                .map(|m| m.chars().take(MAX_DISRUPTION_MESSAGE).collect::<String>());
            (reason, message)
        })
}

/// The scheduler's complaint in a pod's `PodScheduled=False`, reason `Unschedulable`.
fn unschedulable_of(status: &PodStatus) -> Option<Unschedulable> {
    status
        .conditions
        .iter()
        .flatten()
        .find(|c| {
            c.type_ == "PodScheduled"
                && c.status == "False"
                && c.reason.as_deref() == Some("Unschedulable")
        })
        .map(|c| Unschedulable {
            since: ts(&c.last_transition_time),
            message: c.message.clone().unwrap_or_default(),
        })
}

fn index_statuses(statuses: Option<&[ContainerStatus]>) -> BTreeMap<&str, &ContainerStatus> {
    statuses
        .unwrap_or_default()
        .iter()
        .map(|s| (s.name.as_str(), s))
        .collect()
}

fn exit(t: &k8s_openapi::api::core::v1::ContainerStateTerminated) -> Exit {
    Exit {
        exit_code: t.exit_code,
        reason: t.reason.clone(),
        message: t.message.clone(),
        finished_at: ts(&t.finished_at),
    }
}

fn container_view(spec: &Container, status: Option<&ContainerStatus>, init: bool) -> ContainerView {
    let image = spec
        .image
        .clone()
        .filter(|i| !i.is_empty())
        .or_else(|| status.map(|s| s.image.clone()))
        .unwrap_or_default();
    let Some(status) = status else {
        return ContainerView {
            name: spec.name.clone(),
            image,
            init,
            state: ContainerState::NotCreated,
            ready: false,
            restart_count: 0,
            last_exit: None,
            digest: None,
        };
    };
    let state = match &status.state {
        Some(s) => {
            if let Some(t) = &s.terminated {
                ContainerState::Terminated(exit(t))
            } else if let Some(r) = &s.running {
                ContainerState::Running {
                    started_at: ts(&r.started_at),
                }
            } else if let Some(w) = &s.waiting {
                ContainerState::Waiting {
                    reason: w.reason.clone().unwrap_or_default(),
                    message: w.message.clone(),
                }
            } else {
                ContainerState::NotCreated
            }
        }
        None => ContainerState::NotCreated,
    };
    ContainerView {
        name: spec.name.clone(),
        image,
        init,
        state,
        ready: status.ready,
        restart_count: status.restart_count,
        last_exit: status
            .last_state
            .as_ref()
            .and_then(|s| s.terminated.as_ref())
            .map(exit),
        digest: digest(&status.image_id),
    }
}

/// The registry digest (`sha256:...`) of a kubelet's `imageID` when it names one
/// (`repo@sha256:...`, after any runtime prefix); `None` while it has none, or when it is a bare
/// local image id: that is another kind of digest, which compared with a registry digest would
/// flag the same image as two.
fn digest(image_id: &str) -> Option<String> {
    let (_, digest) = image_id.rsplit_once('@')?;
    let hex = digest.strip_prefix("sha256:")?;
    (hex.len() == 64 && hex.bytes().all(|b| b.is_ascii_hexdigit())).then(|| digest.to_owned())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::autoscaler;
    use k8s_openapi::api::core::v1::Event;

    /// An observation with the verdict `policy` reaches on it, as the Monitor's round judges.
    #[derive(Debug, Clone)]
    struct Judged {
        obs: Observation,
        policy: VerdictPolicy,
        verdict: Verdict,
    }

    impl std::ops::Deref for Judged {
        type Target = Observation;
        fn deref(&self) -> &Observation {
            &self.obs
        }
    }

    impl Judged {
        /// The verdict on a run of `count` Jobs.
        fn expect_jobs(self, count: u32) -> Judged {
            let verdict = self.obs.judge(count, &BTreeMap::new(), &self.policy);
            Judged { verdict, ..self }
        }
    }

    /// [`super::observe`] with each pod told the autoscaler's word among `events` (as the
    /// Monitor's round does once it asks), judged with `policy`.
    fn observe(
        submission_id: &str,
        jobs: &[Job],
        pods: &[Pod],
        events: &[Event],
        now: Timestamp,
        policy: &VerdictPolicy,
    ) -> Judged {
        let mut obs = super::observe(submission_id, jobs, pods, now);
        for uid in pods.iter().filter_map(|p| p.metadata.uid.as_deref()) {
            if let Some(word) = autoscaler::latest_word(events, uid) {
                obs.hear_autoscaler(uid, word);
            }
        }
        Judged {
            verdict: obs.verdict(policy),
            obs,
            policy: *policy,
        }
    }
    use std::time::Duration;

    /// Jobs and Pods of a `kubectl get jobs,pods -o yaml` style `List`.
    fn load(text: &str) -> (Vec<Job>, Vec<Pod>) {
        let list: serde_json::Value = serde_yaml::from_str(text).expect("fixture is YAML");
        assert_eq!(list["kind"], "List");
        let mut jobs = Vec::new();
        let mut pods = Vec::new();
        for item in list["items"].as_array().expect("items") {
            match item["kind"].as_str() {
                Some("Job") => jobs.push(serde_json::from_value(item.clone()).expect("a Job")),
                Some("Pod") => pods.push(serde_json::from_value(item.clone()).expect("a Pod")),
                other => panic!("unexpected kind {other:?}"),
            }
        }
        (jobs, pods)
    }

    fn at(hh: i8, mm: i8) -> Timestamp {
        format!("2025-03-14T{hh:02}:{mm:02}:00Z").parse().unwrap()
    }

    fn run(text: &str) -> Judged {
        run_at(text, at(9, 45), &VerdictPolicy::default())
    }

    /// `jobs` and `pods` at 09:45 with the default policy and no events.
    fn observe_at_945(jobs: &[Job], pods: &[Pod]) -> Judged {
        observe(
            "4242",
            jobs,
            pods,
            &[],
            at(9, 45),
            &VerdictPolicy::default(),
        )
    }

    fn run_at(text: &str, now: Timestamp, policy: &VerdictPolicy) -> Judged {
        let (jobs, pods) = load(text);
        observe("4242", &jobs, &pods, &[], now, policy)
    }

    fn failed(obs: &Judged) -> (FailureKind, Option<&str>, Option<&str>, &str) {
        match &obs.verdict {
            Verdict::Failed {
                kind,
                job,
                container,
                message,
            } => (
                *kind,
                job.as_deref(),
                container.as_deref(),
                message.as_str(),
            ),
            other => panic!("expected a failure, got {other:?}"),
        }
    }

    const RUNNING: &str = include_str!("../tests/fixtures/running.yaml");
    const PENDING_INIT: &str = include_str!("../tests/fixtures/pending-init.yaml");
    const FINISHED: &str = include_str!("../tests/fixtures/finished-two-jobs.yaml");
    const BACKOFF: &str = include_str!("../tests/fixtures/backoff-limit.yaml");
    const DEADLINE: &str = include_str!("../tests/fixtures/deadline-exceeded.yaml");
    const PULL_BACKOFF: &str = include_str!("../tests/fixtures/image-pull-backoff.yaml");
    const ERR_PULL: &str = include_str!("../tests/fixtures/err-image-pull.yaml");
    const INVALID_NAME: &str = include_str!("../tests/fixtures/invalid-image-name.yaml");
    const RATE_LIMITED: &str = include_str!("../tests/fixtures/pull-rate-limited.yaml");
    const INFRA_PULL: &str = include_str!("../tests/fixtures/infra-image-pull.yaml");
    const UNSCHEDULABLE: &str = include_str!("../tests/fixtures/unschedulable.yaml");
    const CRASH_LOOP: &str = include_str!("../tests/fixtures/crash-loop.yaml");
    const HALF_DONE: &str = include_str!("../tests/fixtures/one-complete-one-running.yaml");
    const EVICTED: &str = include_str!("../tests/fixtures/evicted-replaced.yaml");
    const SUCCESS_CRITERIA: &str = include_str!("../tests/fixtures/success-criteria-met.yaml");
    const FAILURE_TARGET: &str = include_str!("../tests/fixtures/failure-target.yaml");
    const JOB_TERMINATING: &str = include_str!("../tests/fixtures/job-terminating.yaml");
    const STRAY: &str = include_str!("../tests/fixtures/stray-pod.yaml");
    const EMPTY: &str = include_str!("../tests/fixtures/empty.yaml");

    const ALL: [&str; 19] = [
        RUNNING,
        PENDING_INIT,
        FINISHED,
        BACKOFF,
        DEADLINE,
        PULL_BACKOFF,
        ERR_PULL,
        INVALID_NAME,
        RATE_LIMITED,
        INFRA_PULL,
        UNSCHEDULABLE,
        CRASH_LOOP,
        HALF_DONE,
        EVICTED,
        SUCCESS_CRITERIA,
        FAILURE_TARGET,
        JOB_TERMINATING,
        STRAY,
        EMPTY,
    ];

    #[test]
    fn every_fixture_decodes_as_the_api_server_sends_it() {
        for text in ALL {
            let (jobs, pods) = load(text);
            for j in &jobs {
                assert!(j.status.is_some() && j.metadata.uid.is_some());
                assert_eq!(
                    j.metadata.labels.as_ref().unwrap()[crate::labels::SUBMISSION_ID],
                    "4242"
                );
            }
            for p in &pods {
                assert!(p.status.as_ref().and_then(|s| s.phase.as_ref()).is_some());
            }
            // Every Job and Pod lands somewhere in the observation.
            let obs = observe_at_945(&jobs, &pods);
            let placed: usize =
                obs.jobs.iter().map(|j| j.pods.len()).sum::<usize>() + obs.stray_pods.len();
            assert_eq!((obs.jobs.len(), placed), (jobs.len(), pods.len()));
        }
    }

    #[test]
    fn a_running_job_is_running_and_reports_the_agent_restarts() {
        let obs = run(RUNNING);
        assert_eq!(obs.verdict, Verdict::Running);
        let job = &obs.jobs[0];
        assert_eq!(
            (job.name.as_str(), job.index),
            ("lb-4242-team-77-0", Some(0))
        );
        assert_eq!(job.state, JobState::Running);
        assert_eq!((job.active, job.ready), (1, 1));
        assert_eq!(job.start_time, Some(at(9, 0)));
        let pod = &job.pods[0];
        assert_eq!(pod.phase, PodPhase::Running);
        assert_eq!(
            pod.node.as_deref(),
            Some("ip-10-0-12-34.us-west-2.compute.internal")
        );
        let agent = pod.containers.iter().find(|c| c.name == "agent-1").unwrap();
        assert_eq!(agent.restart_count, 2);
        assert_eq!(agent.last_exit.as_ref().unwrap().exit_code, 1);
        assert_eq!(
            agent.last_exit.as_ref().unwrap().reason.as_deref(),
            Some("Error")
        );
        assert!(matches!(
            agent.state,
            ContainerState::Running {
                started_at: Some(_)
            }
        ));
        assert_eq!(obs.restarts(), 2);
        assert_eq!(obs.started_at(), Some(at(9, 0)));
        assert!(!obs.verdict.is_terminal());
    }

    #[test]
    fn containers_are_listed_init_first_in_spec_order_with_the_spec_image() {
        let obs = run(RUNNING);
        let names: Vec<(&str, bool)> = obs.jobs[0].pods[0]
            .containers
            .iter()
            .map(|c| (c.name.as_str(), c.init))
            .collect();
        assert_eq!(
            names,
            [
                ("private-contents", true),
                ("simulator-1", false),
                ("agent-1", false),
                ("logcopy", false)
            ]
        );
        let init = &obs.jobs[0].pods[0].containers[0];
        assert!(
            matches!(&init.state, ContainerState::Terminated(e) if e.exit_code == 0 && e.reason.as_deref() == Some("Completed"))
        );
        assert!(init
            .image
            .ends_with("leaderboard-20-private-contents:latest"));
    }

    #[test]
    fn a_pod_still_initialising_is_running_not_hopeless() {
        let obs = run(PENDING_INIT);
        assert_eq!(obs.verdict, Verdict::Running);
        assert_eq!(obs.jobs[0].state, JobState::Running);
        let agent = &obs.jobs[0].pods[0].containers[2];
        assert_eq!(
            agent.state,
            ContainerState::Waiting {
                reason: "PodInitializing".into(),
                message: None
            }
        );
    }

    #[test]
    fn two_complete_jobs_are_finished() {
        let obs = run(FINISHED);
        assert_eq!(obs.verdict, Verdict::Finished);
        assert!(obs.verdict.is_terminal());
        assert_eq!(obs.jobs.len(), 2);
        for (i, job) in obs.jobs.iter().enumerate() {
            assert_eq!(job.index, Some(i as u32));
            assert_eq!(job.state, JobState::Complete);
            assert_eq!(job.succeeded, 1);
            assert!(job.completion_time.is_some());
            assert_eq!(job.pods.len(), 1);
            assert_eq!(job.pods[0].phase, PodPhase::Succeeded);
        }
        assert_eq!(obs.clone().expect_jobs(2).verdict, Verdict::Finished);
    }

    #[test]
    fn backoff_limit_exceeded_fails_naming_the_reason_and_the_restarts() {
        let obs = run(BACKOFF);
        assert_eq!(
            obs.jobs[0].state,
            JobState::Failed {
                reason: "BackoffLimitExceeded".into(),
                message: "Job has reached the specified backoff limit".into()
            }
        );
        let (kind, job, container, message) = failed(&obs);
        assert_eq!(kind, FailureKind::BackoffLimitExceeded);
        assert_eq!(kind.name(), "BackoffLimitExceeded");
        assert_eq!(job, Some("lb-4242-team-77-0"));
        assert_eq!(container, None);
        assert!(
            message.contains("BackoffLimitExceeded: Job has reached the specified backoff limit"),
            "{message}"
        );
        assert!(
            message.contains("agent-1 restarted 3x, last exit code 1"),
            "{message}"
        );
    }

    #[test]
    fn deadline_exceeded_fails_with_its_own_kind() {
        let obs = run(DEADLINE);
        let (kind, _, _, message) = failed(&obs);
        assert_eq!(kind, FailureKind::DeadlineExceeded);
        assert!(message.contains("time limit"), "{message}");
        assert!(
            message.contains("Job was active longer than specified deadline"),
            "{message}"
        );
        assert!(obs.jobs[0].pods.is_empty());
    }

    #[test]
    fn an_agent_in_image_pull_back_off_fails_naming_the_image() {
        let obs = run(PULL_BACKOFF);
        let (kind, job, container, message) = failed(&obs);
        assert_eq!(kind, FailureKind::ParticipantImagePull);
        assert_eq!(job, Some("lb-4242-team-77-0"));
        assert_eq!(container, Some("agent-1"));
        assert!(
            message.contains(
                "`342236305043.dkr.ecr.us-west-2.amazonaws.com/evalai-team-77:submission-4242`"
            ),
            "{message}"
        );
        assert!(
            message.contains("check that the image URI is correct"),
            "{message}"
        );
        assert!(message.contains("ImagePullBackOff"), "{message}");
    }

    #[test]
    fn an_agent_in_err_image_pull_fails_at_once() {
        let obs = run(ERR_PULL);
        let (kind, _, container, message) = failed(&obs);
        assert_eq!(kind, FailureKind::ParticipantImagePull);
        assert_eq!(container, Some("agent-1"));
        assert!(
            message.contains("ErrImagePull: failed to pull and unpack image"),
            "{message}"
        );
        assert!(message.contains("not found"), "{message}");
    }

    #[test]
    fn an_invalid_image_name_tells_the_participant_to_check_the_uri() {
        let obs = run(INVALID_NAME);
        let (kind, _, _, message) = failed(&obs);
        assert_eq!(kind, FailureKind::ParticipantImagePull);
        assert!(
            message.contains("`Team77/Agent:V3` is not a valid image reference"),
            "{message}"
        );
        assert!(message.contains("must be lowercase"), "{message}");
        assert!(message.contains("check the image URI"), "{message}");
    }

    #[test]
    fn a_pull_throttled_by_the_registry_is_not_hopeless() {
        let obs = run(RATE_LIMITED);
        assert_eq!(obs.verdict, Verdict::Running);
        let agent = &obs.jobs[0].pods[0].containers[2];
        assert!(
            matches!(&agent.state, ContainerState::Waiting { reason, .. } if reason == "ErrImagePull")
        );
    }

    #[test]
    fn an_unpullable_organizers_image_is_not_blamed_on_the_participant() {
        let obs = run(INFRA_PULL);
        let (kind, _, container, message) = failed(&obs);
        assert_eq!(kind, FailureKind::InfrastructureImagePull);
        assert_eq!(container, Some("private-contents"));
        assert!(
            message.contains("not a problem with your submission"),
            "{message}"
        );
        assert!(
            message.contains("leaderboard-20-private-contents:latest"),
            "{message}"
        );
    }

    #[test]
    fn the_participant_image_wins_over_an_organizers_image_in_the_message() {
        let (jobs, mut pods) = load(PULL_BACKOFF);
        let (_, infra) = load(INFRA_PULL);
        let mut infra = infra[0].clone();
        // Sorted first by name, so it is met first.
        infra.metadata.name = Some("lb-4242-team-77-0-aaaaa".into());
        pods.push(infra);
        let obs = observe_at_945(&jobs, &pods);
        assert_eq!(failed(&obs).0, FailureKind::ParticipantImagePull);
    }

    #[test]
    fn a_pod_waiting_for_gpus_is_queued_until_the_queue_limit_and_never_failed_before() {
        let policy = VerdictPolicy {
            unschedulable_limit: Duration::from_secs(30 * 60),
            queue_limit: Duration::from_secs(2 * 3600),
            ..VerdictPolicy::default()
        };
        // Unschedulable since 09:01 for `Insufficient nvidia.com/gpu`: a full cluster.
        for minute in [30, 31, 59] {
            let obs = run_at(UNSCHEDULABLE, at(9, minute), &policy);
            assert_eq!(obs.verdict, Verdict::Running, "09:{minute}");
            assert!(!started(&obs.jobs));
        }
        assert_eq!(
            run_at(UNSCHEDULABLE, at(11, 0), &policy).verdict,
            Verdict::Running
        );
        let late = run_at(UNSCHEDULABLE, at(11, 1), &policy);
        let (kind, _, _, message) = failed(&late);
        assert_eq!(kind, FailureKind::Unschedulable);
        assert!(
            message.contains("waited 120 minutes for free capacity")
                && message.contains("queue limit of 2 hours")
                && message.contains("used none of your time"),
            "{message}"
        );
    }

    /// The autoscaler-events fixture with the autoscaler's message and time set.
    fn autoscaler_events(message: &str, last: &str) -> Vec<Event> {
        let text = include_str!("../tests/fixtures/autoscaler-events.yaml");
        let mut list: serde_json::Value = serde_yaml::from_str(text).unwrap();
        let items = list["items"].as_array_mut().unwrap();
        items[1]["message"] = message.into();
        items[1]["lastTimestamp"] = last.into();
        items
            .iter()
            .map(|e| serde_json::from_value(e.clone()).unwrap())
            .collect()
    }

    #[test]
    fn a_pod_no_node_group_could_hold_fails_after_the_grace_naming_what_to_fix() {
        let (jobs, pods) = load(UNSCHEDULABLE);
        let policy = VerdictPolicy::default();
        // Unschedulable since 09:01; the autoscaler's word is believed from 09:06.
        let seen = |now| super::observe("4242", &jobs, &pods, now);
        assert_eq!(seen(at(9, 5)).needs_autoscaler_word(&policy), None);
        assert_eq!(
            seen(at(9, 6)).needs_autoscaler_word(&policy),
            Some("8e61dbe7-90cf-4dec-4891-83cfd21a9a89")
        );
        let selector = autoscaler_events(
            "pod didn't trigger scale-up: 1 node(s) didn't match Pod's node affinity/selector",
            "2025-03-14T09:05:40Z",
        );
        let early = observe("4242", &jobs, &pods, &selector, at(9, 5), &policy);
        assert_eq!(early.verdict, Verdict::Running);
        assert_eq!(
            early.jobs[0].pods[0].autoscaler.as_ref().unwrap().reason,
            autoscaler::NOT_TRIGGERED
        );
        let obs = observe("4242", &jobs, &pods, &selector, at(9, 6), &policy);
        let (kind, job, _, message) = failed(&obs);
        assert_eq!(
            (kind, job),
            (FailureKind::NoNodeFits, Some("lb-4242-team-77-0"))
        );
        assert!(
            message.contains(
                "no node group of the evaluation cluster offers the nodes this leaderboard runs on (`node.kubernetes.io/instance-type=g5.12xlarge`)"
            ) && message.contains("not of your submission")
                && message.contains("used none of your time"),
            "{message}"
        );

        let too_large = autoscaler_events(
            "pod didn't trigger scale-up: 2 Insufficient nvidia.com/gpu, 1 Insufficient memory",
            "2025-03-14T09:05:40Z",
        );
        let obs = observe("4242", &jobs, &pods, &too_large, at(9, 7), &policy);
        let message = failed(&obs).3;
        assert!(
            message.contains("request more nvidia.com/gpu, memory than a node of any node group"),
            "{message}"
        );

        for (why, message, said, now) in [
            (
                "a group at its maximum is a queue: the capacity limit decides, hours later",
                "pod didn't trigger scale-up: 1 max node group size reached, 1 node(s) didn't match Pod's node affinity/selector",
                "2025-03-14T09:05:40Z",
                at(12, 0),
            ),
            (
                "a word from before this wait began is about another attempt",
                "pod didn't trigger scale-up: 1 Insufficient nvidia.com/gpu",
                "2025-03-14T08:59:00Z",
                at(9, 30),
            ),
        ] {
            let events = autoscaler_events(message, said);
            let obs = observe("4242", &jobs, &pods, &events, now, &policy);
            assert_eq!(obs.verdict, Verdict::Running, "{why}");
        }
        // The scheduler's own events alone change nothing.
        let scheduler_only = &autoscaler_events("", "2025-03-14T09:05:40Z")[..1];
        assert_eq!(
            observe("4242", &jobs, &pods, scheduler_only, at(9, 30), &policy).verdict,
            Verdict::Running
        );
    }

    #[test]
    fn an_unschedulable_pod_is_hopeless_only_after_the_limit() {
        let policy = VerdictPolicy {
            unschedulable_limit: Duration::from_secs(30 * 60),
            ..VerdictPolicy::default()
        };
        // The same pod, but no node of the instance type it asks for: waiting cannot help.
        const NO_MATCH: &str =
            "0/3 nodes are available: 3 node(s) didn't match Pod's node affinity/selector.";
        let text = UNSCHEDULABLE.replace(
            "0/3 nodes are available: 1 node(s) had untolerated taint {node-role.kubernetes.io/control-plane: }, 2 Insufficient nvidia.com/gpu. preemption: 0/3 nodes are available: 1 Preemption is not helpful for scheduling, 2 No preemption victims found for incoming pod.",
            NO_MATCH,
        );
        assert!(text.contains(NO_MATCH));

        // Unschedulable since 09:01.
        let early = run_at(&text, at(9, 30), &policy);
        assert_eq!(early.verdict, Verdict::Running);
        let unsched = early.jobs[0].pods[0].unschedulable.as_ref().unwrap();
        assert_eq!(unsched.since, Some(at(9, 1)));
        assert!(unsched.message.starts_with("0/3 nodes are available"));
        assert_eq!(early.jobs[0].pods[0].node, None);
        assert!(early.jobs[0].pods[0]
            .containers
            .iter()
            .all(|c| c.state == ContainerState::NotCreated));

        let late = run_at(&text, at(9, 31), &policy);
        let (kind, job, _, message) = failed(&late);
        assert_eq!(kind, FailureKind::Unschedulable);
        assert_eq!(job, Some("lb-4242-team-77-0"));
        assert!(message.contains("for 30 minutes"), "{message}");
        assert!(message.contains("didn't match"), "{message}");
    }

    #[test]
    fn the_queue_limit_is_configurable() {
        let short = VerdictPolicy {
            queue_limit: Duration::from_secs(60),
            ..VerdictPolicy::default()
        };
        assert_eq!(
            failed(&run_at(UNSCHEDULABLE, at(9, 2), &short)).0,
            FailureKind::Unschedulable
        );
        assert_eq!(
            run_at(UNSCHEDULABLE, at(9, 1), &short).verdict,
            Verdict::Running
        );
    }

    #[test]
    fn an_unschedulable_pod_without_a_transition_time_is_never_hopeless() {
        let (jobs, mut pods) = load(UNSCHEDULABLE);
        for c in pods[0]
            .status
            .as_mut()
            .unwrap()
            .conditions
            .as_mut()
            .unwrap()
        {
            c.last_transition_time = None;
        }
        let obs = observe(
            "4242",
            &jobs,
            &pods,
            &[],
            at(23, 0),
            &VerdictPolicy::default(),
        );
        assert_eq!(obs.verdict, Verdict::Running);
        assert_eq!(
            obs.jobs[0].pods[0].unschedulable.as_ref().unwrap().since,
            None
        );
    }

    #[test]
    fn a_clock_behind_the_transition_time_is_not_hopeless() {
        let short = VerdictPolicy {
            unschedulable_limit: Duration::ZERO,
            ..VerdictPolicy::default()
        };
        assert_eq!(
            run_at(UNSCHEDULABLE, at(8, 0), &short).verdict,
            Verdict::Running
        );
    }

    #[test]
    fn crash_loop_back_off_is_not_hopeless_but_restarts_are_counted() {
        let obs = run(CRASH_LOOP);
        assert_eq!(obs.verdict, Verdict::Running);
        let agent = &obs.jobs[0].pods[0].containers[2];
        assert!(
            matches!(&agent.state, ContainerState::Waiting { reason, message: Some(m) } if reason == "CrashLoopBackOff" && m.contains("back-off 40s"))
        );
        assert!(!agent.ready);
        assert_eq!(obs.restarts(), 6);
    }

    /// A pair out of retries (its own Job) beside others: they go on, and the submission
    /// fails, naming that pair's Job, only once every Job has ended.
    #[test]
    fn a_pair_out_of_retries_fails_the_submission_only_when_its_neighbours_have_ended() {
        let third = BACKOFF
            .replace("lb-4242-team-77-0", "lb-4242-team-77-2")
            .replace("job-index: \"0\"", "job-index: \"2\"");
        let (gave_up, gave_up_pods) = load(&third);
        let with = |text: &str| {
            let (mut jobs, mut pods) = load(text);
            jobs.extend(gave_up.clone());
            pods.extend(gave_up_pods.clone());
            observe_at_945(&jobs, &pods)
        };
        let running = with(HALF_DONE);
        assert_eq!(running.verdict, Verdict::Running);
        assert!(
            matches!(&running.jobs[2].state, JobState::Failed { reason, .. } if reason == "BackoffLimitExceeded")
        );

        let ended = with(FINISHED);
        let (kind, job, _, message) = failed(&ended);
        assert_eq!(kind, FailureKind::BackoffLimitExceeded);
        assert_eq!(job, Some("lb-4242-team-77-2"));
        assert!(message.contains("`lb-4242-team-77-2`"), "{message}");
        assert!(!message.contains("team-77-0`"), "{message}");
        // Any other failure of a Job still ends the run at once.
        assert_eq!(failed(&run(DEADLINE)).0, FailureKind::DeadlineExceeded);
    }

    #[test]
    fn one_complete_job_and_one_running_job_are_running() {
        let obs = run(HALF_DONE);
        assert_eq!(obs.verdict, Verdict::Running);
        assert_eq!(obs.jobs[0].state, JobState::Complete);
        assert_eq!(obs.jobs[1].state, JobState::Running);
        assert_eq!(obs.jobs[1].pods[0].name, "lb-4242-team-77-1-r5t6y");
    }

    #[test]
    fn only_a_registry_digest_is_an_image_s_digest() {
        let hex = "ab".repeat(32);
        for (image_id, expected) in [
            (
                format!("docker.io/team/agent@sha256:{hex}"),
                Some(format!("sha256:{hex}")),
            ),
            (
                format!("docker-pullable://team/agent@sha256:{hex}"),
                Some(format!("sha256:{hex}")),
            ),
            // A runtime's local image id, or nothing yet: not comparable.
            (format!("sha256:{hex}"), None),
            (String::new(), None),
            ("team/agent@sha256:short".into(), None),
        ] {
            assert_eq!(digest(&image_id), expected, "{image_id}");
        }
    }

    #[test]
    fn a_pod_the_control_plane_takes_away_says_why() {
        let (jobs, mut pods) = load(HALF_DONE);
        let running = pods
            .iter_mut()
            .find(|p| p.metadata.name.as_deref() == Some("lb-4242-team-77-1-r5t6y"))
            .unwrap();
        running
            .status
            .as_mut()
            .unwrap()
            .conditions
            .get_or_insert_with(Vec::new)
            .push(
                serde_json::from_value(serde_json::json!({
                    "type": "DisruptionTarget", "status": "True",
                    "reason": "EvictionByEvictionAPI", "message": "Eviction API: evicting"
                }))
                .unwrap(),
            );
        let obs = observe_at_945(&jobs, &pods);
        let pod = &obs.jobs[1].pods[0];
        assert_eq!(pod.disruption.as_deref(), Some("EvictionByEvictionAPI"));
        assert_eq!(
            pod.disruption_message.as_deref(),
            Some("Eviction API: evicting")
        );
        assert_eq!(
            obs.jobs[0].pods.iter().find_map(|p| p.disruption.clone()),
            None
        );
        assert_eq!(obs.verdict, Verdict::Running, "a new pod resumes it");
    }

    #[test]
    fn an_evicted_pod_replaced_by_a_running_one_is_running() {
        let obs = run(EVICTED);
        assert_eq!(obs.verdict, Verdict::Running);
        let job = &obs.jobs[0];
        assert_eq!((job.failed, job.active), (1, 1));
        let evicted = job
            .pods
            .iter()
            .find(|p| p.phase == PodPhase::Failed)
            .unwrap();
        assert_eq!(evicted.reason.as_deref(), Some("Evicted"));
        assert!(evicted
            .message
            .as_deref()
            .unwrap()
            .contains("ephemeral-storage"));
    }

    #[test]
    fn success_criteria_met_counts_as_complete_while_pods_terminate() {
        let obs = run(SUCCESS_CRITERIA);
        assert_eq!(obs.jobs[0].state, JobState::Complete);
        assert!(obs.jobs[0].pods[0].terminating);
        assert_eq!(obs.verdict, Verdict::Finished);
    }

    #[test]
    fn failure_target_counts_as_failed_before_the_failed_condition() {
        let obs = run(FAILURE_TARGET);
        assert!(
            matches!(&obs.jobs[0].state, JobState::Failed { reason, .. } if reason == "BackoffLimitExceeded")
        );
        assert_eq!(failed(&obs).0, FailureKind::BackoffLimitExceeded);
    }

    #[test]
    fn the_pods_of_a_job_being_deleted_do_not_make_the_submission_hopeless() {
        let obs = run(JOB_TERMINATING);
        assert!(obs.jobs[0].terminating);
        assert_eq!(obs.verdict, Verdict::Running);
    }

    #[test]
    fn stray_pods_are_reported_apart_and_do_not_decide() {
        let obs = run(STRAY);
        assert_eq!(obs.verdict, Verdict::Running);
        assert_eq!(obs.jobs.len(), 1);
        assert_eq!(obs.jobs[0].pods.len(), 1);
        assert_eq!(obs.stray_pods.len(), 1);
        // No owner reference: the job-name label still says whose it was.
        assert_eq!(obs.stray_pods[0].job.as_deref(), Some("lb-4242-team-77-1"));
    }

    #[test]
    fn pods_attach_to_their_job_by_label_without_an_owner_reference() {
        let (jobs, mut pods) = load(RUNNING);
        pods[0].metadata.owner_references = None;
        let obs = observe_at_945(&jobs, &pods);
        assert_eq!(obs.jobs[0].pods.len(), 1);
        let labels = |p: &mut Pod| p.metadata.labels.as_mut().unwrap().clone();
        let mut l = labels(&mut pods[0]);
        l.remove("batch.kubernetes.io/job-name");
        pods[0].metadata.labels = Some(l.clone());
        let obs = observe_at_945(&jobs, &pods);
        assert_eq!(obs.jobs[0].pods.len(), 1, "the legacy job-name label");
        l.remove("job-name");
        pods[0].metadata.labels = Some(l);
        let obs = observe_at_945(&jobs, &pods);
        assert_eq!((obs.jobs[0].pods.len(), obs.stray_pods.len()), (0, 1));
    }

    #[test]
    fn no_jobs_means_the_jobs_are_missing() {
        let obs = run(EMPTY);
        let (kind, job, _, message) = failed(&obs);
        assert_eq!((kind, job), (FailureKind::JobsMissing, None));
        assert!(message.contains("no longer exist"));
        assert_eq!(obs.restarts(), 0);
        assert_eq!(obs.started_at(), None);
    }

    #[test]
    fn expecting_more_jobs_than_exist_fails_a_finished_verdict() {
        let obs = run(FINISHED).expect_jobs(3);
        let (kind, _, _, message) = failed(&obs);
        assert_eq!(kind, FailureKind::JobsMissing);
        assert!(message.contains("index 2 of 3"), "{message}");
        let obs = run(RUNNING).expect_jobs(2);
        assert_eq!(failed(&obs).0, FailureKind::JobsMissing);
    }

    #[test]
    fn expecting_jobs_keeps_an_earlier_failure_and_accepts_a_full_set() {
        let obs = run(PULL_BACKOFF).expect_jobs(4);
        assert_eq!(failed(&obs).0, FailureKind::ParticipantImagePull);
        assert_eq!(run(HALF_DONE).expect_jobs(2).verdict, Verdict::Running);
        assert_eq!(run(HALF_DONE).expect_jobs(0).verdict, Verdict::Running);
    }

    #[test]
    fn a_malformed_job_index_label_is_ignored_not_fatal() {
        let (mut jobs, pods) = load(RUNNING);
        jobs[0]
            .metadata
            .labels
            .as_mut()
            .unwrap()
            .insert(crate::labels::JOB_INDEX.into(), "zero".into());
        let obs = observe_at_945(&jobs, &pods);
        assert_eq!(obs.jobs[0].index, None);
        assert_eq!(obs.verdict, Verdict::Running);
        assert_eq!(failed(&obs.expect_jobs(1)).0, FailureKind::JobsMissing);
    }

    #[test]
    fn a_suspended_job_is_reported_as_such_and_waited_for() {
        let (mut jobs, pods) = load(PENDING_INIT);
        let status = jobs[0].status.as_mut().unwrap();
        status.active = Some(0);
        status.conditions = Some(vec![k8s_openapi::api::batch::v1::JobCondition {
            type_: "Suspended".into(),
            status: "True".into(),
            reason: Some("JobSuspended".into()),
            message: Some("Job suspended".into()),
            last_probe_time: None,
            last_transition_time: Some(Time(at(9, 10))),
        }]);
        let obs = observe_at_945(&jobs, &pods);
        assert_eq!(obs.jobs[0].state, JobState::Suspended);
        assert_eq!(obs.verdict, Verdict::Running);
    }

    #[test]
    fn a_job_failed_for_another_reason_is_a_generic_job_failure() {
        let (mut jobs, pods) = load(BACKOFF);
        for c in jobs[0]
            .status
            .as_mut()
            .unwrap()
            .conditions
            .as_mut()
            .unwrap()
        {
            c.reason = Some("MaxFailedIndexesExceeded".into());
            c.message =
                Some("Job has exceeded the specified maximal number of failed indexes".into());
        }
        let obs = observe_at_945(&jobs, &pods);
        let (kind, _, _, message) = failed(&obs);
        assert_eq!(kind, FailureKind::JobFailed);
        assert!(
            message.contains("MaxFailedIndexesExceeded: Job has exceeded"),
            "{message}"
        );
    }

    #[test]
    fn a_condition_that_is_not_true_does_not_count() {
        let (mut jobs, pods) = load(BACKOFF);
        for c in jobs[0]
            .status
            .as_mut()
            .unwrap()
            .conditions
            .as_mut()
            .unwrap()
        {
            c.status = "False".into();
        }
        let obs = observe_at_945(&jobs, &pods);
        assert_eq!(obs.jobs[0].state, JobState::Pending);
        assert_eq!(obs.verdict, Verdict::Running);
    }

    #[test]
    fn objects_without_status_or_names_do_not_panic() {
        let jobs = vec![Job::default()];
        let pods = vec![Pod::default()];
        let obs = observe_at_945(&jobs, &pods);
        assert_eq!(obs.jobs[0].state, JobState::Pending);
        assert_eq!(obs.stray_pods[0].phase, PodPhase::Unknown);
        assert_eq!(obs.verdict, Verdict::Running);
    }

    #[test]
    fn the_observation_round_trips_through_json() {
        for text in [RUNNING, BACKOFF, PULL_BACKOFF, UNSCHEDULABLE] {
            let obs = run(text);
            let json = serde_json::to_value(&obs.obs).unwrap();
            let back: Observation = serde_json::from_value(json.clone()).unwrap();
            assert_eq!(back, obs.obs);
            assert!(json["jobs"].is_array());
        }
        let json = serde_json::to_value(run(BACKOFF).verdict).unwrap();
        assert_eq!(json["kind"], "BackoffLimitExceeded");
        assert_eq!(json["verdict"], "Failed");
    }

    #[test]
    fn a_container_that_cannot_be_created_is_hopeless_only_after_the_limit() {
        let (jobs, mut pods) = load(PENDING_INIT);
        let status = pods[0].status.as_mut().unwrap();
        let agent = status
            .container_statuses
            .as_mut()
            .unwrap()
            .iter_mut()
            .find(|c| c.name == "agent-1")
            .unwrap();
        agent.state.as_mut().unwrap().waiting =
            Some(k8s_openapi::api::core::v1::ContainerStateWaiting {
                reason: Some("CreateContainerConfigError".into()),
                message: Some("secret \"leaderboard-20-s3\" not found".into()),
            });
        let policy = VerdictPolicy {
            config_error_limit: Duration::from_secs(10 * 60),
            ..VerdictPolicy::default()
        };
        // The pod started at 09:01.
        let early = observe("4242", &jobs, &pods, &[], at(9, 10), &policy);
        assert_eq!(early.verdict, Verdict::Running);
        assert_eq!(early.jobs[0].pods[0].start_time, Some(at(9, 1)));
        let late = observe("4242", &jobs, &pods, &[], at(9, 11), &policy);
        let (kind, _, container, message) = failed(&late);
        assert_eq!(kind, FailureKind::ContainerConfig);
        assert_eq!(container, Some("agent-1"));
        assert!(
            message.contains("secret \"leaderboard-20-s3\" not found"),
            "{message}"
        );
        assert!(
            message.contains("not a problem with your submission"),
            "{message}"
        );
    }
}
