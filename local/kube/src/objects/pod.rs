//! Pods the job controller creates from a Job's template, and pod phase and conditions as the
//! kubelet derives them from container states.

use std::collections::BTreeMap;

use k8s_openapi::api::batch::v1::Job;
use k8s_openapi::api::core::v1::{
    Container, ContainerState, ContainerStateWaiting, ContainerStatus, Pod, PodCondition, PodSpec,
    PodStatus,
};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::{ObjectMeta, OwnerReference, Time};

use super::defaults::{default_tolerations, pod_spec};
use super::names::{generate_name, new_uid};
use super::JOB_TRACKING_FINALIZER;
use crate::store::time_now;

/// The pod the controller creates for a Job (`<job>-<5 random>`), owned by the Job, not yet
/// bound to the node (the scheduler binds it).
pub fn pod_for_job(job: &Job) -> Pod {
    let job_name = job.metadata.name.clone().unwrap_or_default();
    let template = job
        .spec
        .as_ref()
        .map(|s| s.template.clone())
        .unwrap_or_default();
    let tmeta = template.metadata.unwrap_or_default();
    let mut spec = template.spec.unwrap_or_default();
    pod_spec(&mut spec);
    spec.service_account_name
        .get_or_insert_with(|| "default".into());
    spec.service_account = spec.service_account_name.clone();
    spec.enable_service_links.get_or_insert(true);
    spec.priority.get_or_insert(0);
    spec.preemption_policy
        .get_or_insert_with(|| "PreemptLowerPriority".into());
    spec.tolerations.get_or_insert_with(default_tolerations);
    let generate = format!("{job_name}-");
    Pod {
        metadata: ObjectMeta {
            name: Some(generate_name(&generate)),
            generate_name: Some(generate),
            namespace: job.metadata.namespace.clone(),
            uid: Some(new_uid()),
            creation_timestamp: Some(time_now()),
            labels: tmeta.labels,
            annotations: tmeta.annotations,
            finalizers: Some(vec![JOB_TRACKING_FINALIZER.into()]),
            owner_references: Some(vec![OwnerReference {
                api_version: "batch/v1".into(),
                kind: "Job".into(),
                name: job_name,
                uid: job.metadata.uid.clone().unwrap_or_default(),
                controller: Some(true),
                block_owner_deletion: Some(true),
            }]),
            ..Default::default()
        },
        status: Some(PodStatus {
            phase: Some("Pending".into()),
            qos_class: Some(qos_class(&spec).into()),
            ..Default::default()
        }),
        spec: Some(spec),
    }
}

/// The QoS class from cpu and memory requests and limits (`Guaranteed`, `Burstable`,
/// `BestEffort`).
pub fn qos_class(spec: &PodSpec) -> &'static str {
    let all: Vec<&Container> = spec
        .init_containers
        .iter()
        .flatten()
        .chain(spec.containers.iter())
        .collect();
    let get = |c: &Container, limits: bool, res: &str| {
        let r = c.resources.as_ref()?;
        let m = if limits {
            r.limits.as_ref()
        } else {
            r.requests.as_ref()
        };
        m?.get(res).map(|q| q.0.clone())
    };
    let any = all.iter().any(|c| {
        ["cpu", "memory"]
            .iter()
            .any(|r| get(c, true, r).is_some() || get(c, false, r).is_some())
    });
    if !any {
        return "BestEffort";
    }
    let guaranteed = all.iter().all(|c| {
        ["cpu", "memory"].iter().all(|r| {
            let limit = get(c, true, r);
            limit.is_some() && get(c, false, r).is_none_or(|req| Some(req) == limit)
        })
    });
    if guaranteed {
        "Guaranteed"
    } else {
        "Burstable"
    }
}

/// The uid of the Job controlling this pod, if any.
pub fn controller_uid(pod: &Pod) -> Option<String> {
    pod.metadata
        .owner_references
        .iter()
        .flatten()
        .find(|o| o.controller == Some(true))
        .map(|o| o.uid.clone())
}

/// A waiting state with a reason and optional message.
pub fn waiting(reason: &str, message: Option<String>) -> ContainerState {
    ContainerState {
        waiting: Some(ContainerStateWaiting {
            reason: Some(reason.into()),
            message,
        }),
        ..Default::default()
    }
}

fn is_running(s: &ContainerStatus) -> bool {
    s.state.as_ref().is_some_and(|st| st.running.is_some())
}

/// The exit code of a container that has terminated.
pub fn terminated_code(s: &ContainerStatus) -> Option<i32> {
    s.state
        .as_ref()
        .and_then(|st| st.terminated.as_ref())
        .map(|t| t.exit_code)
}

fn ever_started(s: &ContainerStatus) -> bool {
    s.restart_count > 0
        || s.last_state
            .as_ref()
            .is_some_and(|l| l.terminated.is_some())
        || s.state
            .as_ref()
            .is_some_and(|st| st.running.is_some() || st.terminated.is_some())
}

/// The phase the kubelet reports for these container states.
pub fn phase(
    init: &[ContainerStatus],
    containers: &[ContainerStatus],
    restart_policy: &str,
    previous: &str,
) -> &'static str {
    match previous {
        "Succeeded" => return "Succeeded",
        "Failed" => return "Failed",
        _ => {}
    }
    let init_failed = init
        .iter()
        .any(|s| terminated_code(s).is_some_and(|c| c != 0));
    if init_failed && restart_policy == "Never" {
        return "Failed";
    }
    if !init.iter().all(|s| terminated_code(s) == Some(0)) {
        return "Pending";
    }
    if containers.is_empty() || containers.iter().any(|s| !ever_started(s)) {
        return "Pending";
    }
    if containers.iter().all(|s| terminated_code(s).is_some()) {
        if containers.iter().all(|s| terminated_code(s) == Some(0)) {
            return "Succeeded";
        }
        return "Failed";
    }
    "Running"
}

fn condition(
    old: &BTreeMap<String, PodCondition>,
    type_: &str,
    ok: bool,
    reason: Option<&str>,
    message: Option<String>,
    now: &Time,
) -> PodCondition {
    let status = if ok { "True" } else { "False" };
    let since = old
        .get(type_)
        .filter(|c| c.status == status)
        .and_then(|c| c.last_transition_time.clone())
        .unwrap_or_else(|| now.clone());
    PodCondition {
        type_: type_.into(),
        status: status.into(),
        reason: reason.map(Into::into),
        message,
        last_transition_time: Some(since),
        ..Default::default()
    }
}

fn names(list: &[&ContainerStatus]) -> String {
    let n: Vec<&str> = list.iter().map(|s| s.name.as_str()).collect();
    format!("[{}]", n.join(" "))
}

/// Recomputes phase and conditions from the container states.
pub fn refresh_status(status: &mut PodStatus, restart_policy: &str) {
    let now = time_now();
    let init = status.init_container_statuses.clone().unwrap_or_default();
    let containers = status.container_statuses.clone().unwrap_or_default();
    let previous = status.phase.clone().unwrap_or_default();
    let phase = phase(&init, &containers, restart_policy, &previous);
    status.phase = Some(phase.into());
    let old: BTreeMap<String, PodCondition> = status
        .conditions
        .iter()
        .flatten()
        .map(|c| (c.type_.clone(), c.clone()))
        .collect();
    let terminal = matches!(phase, "Succeeded" | "Failed");
    let succeeded = phase == "Succeeded";
    let incomplete: Vec<&ContainerStatus> = init
        .iter()
        .filter(|s| terminated_code(s) != Some(0))
        .collect();
    let unready: Vec<&ContainerStatus> = containers.iter().filter(|s| !s.ready).collect();
    let initialized = if succeeded {
        condition(&old, "Initialized", true, Some("PodCompleted"), None, &now)
    } else if incomplete.is_empty() {
        condition(&old, "Initialized", true, None, None, &now)
    } else {
        condition(
            &old,
            "Initialized",
            false,
            Some("ContainersNotInitialized"),
            Some(format!(
                "containers with incomplete status: {}",
                names(&incomplete)
            )),
            &now,
        )
    };
    let ready = |type_: &str| {
        if succeeded {
            condition(&old, type_, false, Some("PodCompleted"), None, &now)
        } else if unready.is_empty() && !containers.is_empty() {
            condition(&old, type_, true, None, None, &now)
        } else {
            condition(
                &old,
                type_,
                false,
                Some("ContainersNotReady"),
                Some(format!(
                    "containers with unready status: {}",
                    names(&unready)
                )),
                &now,
            )
        }
    };
    let mut conditions = vec![
        condition(
            &old,
            "PodReadyToStartContainers",
            !terminal,
            None,
            None,
            &now,
        ),
        initialized,
        ready("Ready"),
        ready("ContainersReady"),
        condition(&old, "PodScheduled", true, None, None, &now),
    ];
    // Conditions others wrote (the API server's or the control plane's `DisruptionTarget`)
    // stay as they are: the kubelet owns only its own.
    let own: Vec<String> = conditions.iter().map(|c| c.type_.clone()).collect();
    conditions.extend(old.into_values().filter(|c| !own.contains(&c.type_)));
    status.conditions = Some(conditions);
}

/// The condition the control plane adds to a pod it is about to take away (Kubernetes docs,
/// "Pod disruption conditions"): `reason` says who, e.g. `EvictionByEvictionAPI` with the
/// message `Eviction API: evicting`. An existing one keeps its transition time.
pub fn set_disruption_target(status: &mut PodStatus, reason: &str, message: &str) {
    let conditions = status.conditions.get_or_insert_with(Vec::new);
    if conditions
        .iter()
        .any(|c| c.type_ == "DisruptionTarget" && c.status == "True")
    {
        return;
    }
    conditions.retain(|c| c.type_ != "DisruptionTarget");
    conditions.push(PodCondition {
        type_: "DisruptionTarget".into(),
        status: "True".into(),
        reason: Some(reason.into()),
        message: Some(message.into()),
        last_transition_time: Some(time_now()),
        ..Default::default()
    });
}

/// Whether the pod counts as ready for the Job's `ready` count.
pub fn is_ready(pod: &Pod) -> bool {
    pod.status
        .as_ref()
        .and_then(|s| s.conditions.as_ref())
        .is_some_and(|cs| cs.iter().any(|c| c.type_ == "Ready" && c.status == "True"))
}

/// Sum of restart counts over init and app containers.
pub fn restarts(pod: &Pod) -> i32 {
    let Some(status) = pod.status.as_ref() else {
        return 0;
    };
    status
        .init_container_statuses
        .iter()
        .flatten()
        .chain(status.container_statuses.iter().flatten())
        .map(|s| s.restart_count)
        .sum()
}

/// The pod phase string.
pub fn phase_of(pod: &Pod) -> &str {
    pod.status
        .as_ref()
        .and_then(|s| s.phase.as_deref())
        .unwrap_or("Pending")
}

/// Whether any container runs (used by the log endpoint's follow mode).
pub fn any_running(status: &PodStatus) -> bool {
    status
        .init_container_statuses
        .iter()
        .flatten()
        .chain(status.container_statuses.iter().flatten())
        .any(is_running)
}

#[cfg(test)]
mod tests {
    use super::*;
    use k8s_openapi::api::core::v1::{ContainerStateRunning, ContainerStateTerminated};

    fn st(name: &str, state: ContainerState) -> ContainerStatus {
        ContainerStatus {
            name: name.into(),
            ready: state.running.is_some(),
            state: Some(state),
            ..Default::default()
        }
    }

    fn running() -> ContainerState {
        ContainerState {
            running: Some(ContainerStateRunning::default()),
            ..Default::default()
        }
    }

    fn exited(code: i32) -> ContainerState {
        ContainerState {
            terminated: Some(ContainerStateTerminated {
                exit_code: code,
                ..Default::default()
            }),
            ..Default::default()
        }
    }

    #[test]
    fn phases_follow_the_container_states() {
        let creating = st("a", waiting("ContainerCreating", None));
        assert_eq!(
            phase(&[], std::slice::from_ref(&creating), "Never", "Pending"),
            "Pending"
        );
        assert_eq!(
            phase(&[], &[st("a", running()), creating], "Never", "Pending"),
            "Pending"
        );
        assert_eq!(
            phase(
                &[],
                &[st("a", running()), st("b", exited(0))],
                "Never",
                "Pending"
            ),
            "Running"
        );
        assert_eq!(
            phase(
                &[],
                &[st("a", exited(0)), st("b", exited(0))],
                "Never",
                "Running"
            ),
            "Succeeded"
        );
        assert_eq!(
            phase(
                &[],
                &[st("a", exited(1)), st("b", exited(0))],
                "Never",
                "Running"
            ),
            "Failed"
        );
        assert_eq!(
            phase(
                &[st("i", running())],
                &[st("a", waiting("PodInitializing", None))],
                "Never",
                "Pending"
            ),
            "Pending"
        );
        assert_eq!(
            phase(
                &[st("i", exited(2))],
                &[st("a", waiting("PodInitializing", None))],
                "Never",
                "Pending"
            ),
            "Failed"
        );
        assert_eq!(
            phase(
                &[st("i", exited(2))],
                &[st("a", waiting("PodInitializing", None))],
                "OnFailure",
                "Pending"
            ),
            "Pending"
        );
        assert_eq!(
            phase(&[], &[st("a", running())], "Never", "Failed"),
            "Failed"
        );
    }

    #[test]
    fn qos_follows_cpu_and_memory_resources() {
        let spec = |res: &str| -> PodSpec {
            serde_yaml::from_str(&format!("containers: [{{name: a, resources: {res}}}]")).unwrap()
        };
        assert_eq!(qos_class(&spec("{}")), "BestEffort");
        assert_eq!(
            qos_class(&spec("{limits: {nvidia.com/gpu: 1}}")),
            "BestEffort"
        );
        assert_eq!(qos_class(&spec("{requests: {cpu: 1}}")), "Burstable");
        assert_eq!(
            qos_class(&spec("{limits: {cpu: 1, memory: 1Gi}}")),
            "Guaranteed"
        );
    }

    #[test]
    fn conditions_name_the_unready_containers() {
        let mut status = PodStatus {
            container_statuses: Some(vec![
                st("a", running()),
                st("b", waiting("ContainerCreating", None)),
            ]),
            ..Default::default()
        };
        refresh_status(&mut status, "Never");
        let conds = status.conditions.unwrap();
        let types: Vec<&str> = conds.iter().map(|c| c.type_.as_str()).collect();
        assert_eq!(
            types,
            [
                "PodReadyToStartContainers",
                "Initialized",
                "Ready",
                "ContainersReady",
                "PodScheduled"
            ]
        );
        assert_eq!(conds[2].status, "False");
        assert_eq!(
            conds[2].message.as_deref(),
            Some("containers with unready status: [b]")
        );
        assert_eq!(status.phase.as_deref(), Some("Pending"));
    }
}
