//! The least a submission's containers get, checked on every rendered Job: no root where the
//! images allow it, no capabilities, the runtime's seccomp filter, requests equal to limits
//! from the settings, a bounded `/dev/shm`, the recordings out of the participant's reach. A
//! template that loosens any of it does not render.

use k8s_openapi::api::batch::v1::Job;
use k8s_openapi::api::core::v1::{Container, PodSpec, ResourceRequirements};

use crate::context::{ContainerResources, JobContext};
use crate::RenderError;

/// The user the simulators, init and logcopy run as: `carla` (1000) in CARLA's release images,
/// a user with no privileges in the private-contents image. Participants' agent images run
/// as root (the official agent Dockerfile sets no user and the agent sources `~/.bashrc` of
/// root), so agents may; they still get no capabilities.
pub const UNPRIVILEGED_UID: i64 = 1000;

/// Containers that may run as root: the participant's agents.
const ROOT_ALLOWED_PREFIX: &str = "agent-";

/// The volume every container's logs, results and markers are in.
const LOGS_VOLUME: &str = "logs";

/// The volume mounted at `/dev/shm`.
pub const SHM_VOLUME: &str = "dshm";

fn refuse(path: String, problem: impl Into<String>) -> RenderError {
    RenderError::InvalidSpec {
        path,
        problem: problem.into(),
    }
}

/// Checks the Pod and every container of `job` against the confinement rules and `context`'s
/// resources.
pub fn check(job: &Job, context: &JobContext) -> Result<(), RenderError> {
    const AT: &str = "spec.template.spec";
    let Some(pod) = job.spec.as_ref().and_then(|s| s.template.spec.as_ref()) else {
        return Err(refuse(AT.into(), "the Pod template has no spec"));
    };
    check_pod(pod, context)?;
    let lists: [(&str, &[Container]); 2] = [
        (
            "initContainers",
            pod.init_containers.as_deref().unwrap_or_default(),
        ),
        ("containers", &pod.containers),
    ];
    for (list, containers) in lists {
        for (i, c) in containers.iter().enumerate() {
            check_container(c, &format!("{AT}.{list}[{i}]"), context)?;
        }
    }
    Ok(())
}

fn check_pod(pod: &PodSpec, context: &JobContext) -> Result<(), RenderError> {
    const AT: &str = "spec.template.spec";
    for (field, value) in [
        ("hostNetwork", pod.host_network),
        ("hostPID", pod.host_pid),
        ("hostIPC", pod.host_ipc),
    ] {
        if value == Some(true) {
            return Err(refuse(
                format!("{AT}.{field}"),
                "must not share the node's namespaces",
            ));
        }
    }
    if pod
        .ephemeral_containers
        .as_ref()
        .is_some_and(|e| !e.is_empty())
    {
        return Err(refuse(format!("{AT}.ephemeralContainers"), "must be empty"));
    }
    let security = pod.security_context.as_ref();
    let seccomp = security
        .and_then(|s| s.seccomp_profile.as_ref())
        .map(|p| p.type_.as_str());
    if seccomp != Some("RuntimeDefault") {
        return Err(refuse(
            format!("{AT}.securityContext.seccompProfile.type"),
            "must be `RuntimeDefault`: the container runtime's syscall filter for every container",
        ));
    }
    if security.is_some_and(|s| s.sysctls.as_ref().is_some_and(|v| !v.is_empty())) {
        return Err(refuse(
            format!("{AT}.securityContext.sysctls"),
            "must be empty",
        ));
    }
    if security.is_some_and(|s| s.run_as_user == Some(0) || s.run_as_group == Some(0)) {
        return Err(refuse(
            format!("{AT}.securityContext"),
            "must not make root the default user or group",
        ));
    }
    check_volumes(pod, context)
}

/// No volume from the node; every memory-backed one bounded, and `/dev/shm` among them at the
/// size the settings give it.
fn check_volumes(pod: &PodSpec, context: &JobContext) -> Result<(), RenderError> {
    const AT: &str = "spec.template.spec";
    let mut shm = false;
    for (i, v) in pod.volumes.iter().flatten().enumerate() {
        let at = format!("{AT}.volumes[{i}]");
        if v.host_path.is_some() {
            return Err(refuse(
                format!("{at}.hostPath"),
                "no volume may come from the node",
            ));
        }
        let Some(dir) = &v.empty_dir else { continue };
        if dir.size_limit.is_none() {
            // Unbounded, a disk-backed volume fills the node's disk: the kubelet then evicts
            // pods of every team on it for disk pressure, not only the writer's.
            return Err(refuse(
                format!("{at}.emptyDir.sizeLimit"),
                "every emptyDir volume must have a size limit",
            ));
        }
        if dir.medium.as_deref() == Some("Memory") {
            let Some(limit) = &dir.size_limit else {
                return Err(refuse(
                    format!("{at}.emptyDir.sizeLimit"),
                    "a memory-backed volume must have a size limit",
                ));
            };
            if v.name == SHM_VOLUME {
                shm = true;
                if limit.0 != context.resources.shm {
                    return Err(refuse(
                        format!("{at}.emptyDir.sizeLimit"),
                        format!(
                            "is `{}`; the settings give /dev/shm `{}`",
                            limit.0, context.resources.shm
                        ),
                    ));
                }
            }
        }
    }
    if !shm {
        return Err(refuse(
            format!("{AT}.volumes"),
            format!("the memory-backed `{SHM_VOLUME}` volume (/dev/shm) is missing"),
        ));
    }
    Ok(())
}

fn check_container(c: &Container, at: &str, context: &JobContext) -> Result<(), RenderError> {
    let Some(s) = &c.security_context else {
        return Err(refuse(
            format!("{at}.securityContext"),
            format!("`{}` has no security context", c.name),
        ));
    };
    let at_sc = |field: &str| format!("{at}.securityContext.{field}");
    if s.privileged == Some(true) {
        return Err(refuse(at_sc("privileged"), "must not be true"));
    }
    if s.allow_privilege_escalation != Some(false) {
        return Err(refuse(at_sc("allowPrivilegeEscalation"), "must be false"));
    }
    let caps = s.capabilities.as_ref();
    if !caps
        .and_then(|c| c.drop.as_ref())
        .is_some_and(|d| d.iter().any(|c| c == "ALL"))
    {
        return Err(refuse(at_sc("capabilities.drop"), "must contain `ALL`"));
    }
    if caps
        .and_then(|c| c.add.as_ref())
        .is_some_and(|a| !a.is_empty())
    {
        return Err(refuse(at_sc("capabilities.add"), "must be empty"));
    }
    if let Some(profile) = &s.seccomp_profile {
        if profile.type_ != "RuntimeDefault" {
            return Err(refuse(
                at_sc("seccompProfile.type"),
                "must be `RuntimeDefault` (or left to the Pod's)",
            ));
        }
    }
    if s.proc_mount.as_deref().is_some_and(|m| m != "Default") {
        return Err(refuse(at_sc("procMount"), "must be `Default`"));
    }
    if !c.name.starts_with(ROOT_ALLOWED_PREFIX) {
        if s.run_as_non_root != Some(true) {
            return Err(refuse(
                at_sc("runAsNonRoot"),
                format!("must be true: `{}` runs our or CARLA's code", c.name),
            ));
        }
        if s.run_as_user.is_some_and(|u| u == 0) {
            return Err(refuse(at_sc("runAsUser"), "must not be 0"));
        }
    }
    check_recordings(c, at)?;
    let expected = if c.name.starts_with("simulator-") {
        &context.resources.simulator
    } else if c.name.starts_with("agent-") {
        &context.resources.agent
    } else if c.name == "logcopy" {
        &context.resources.logcopy
    } else {
        &context.resources.sidecar
    };
    check_resources(c.resources.as_ref(), expected, &format!("{at}.resources"))
}

/// The CARLA recordings stay out of the participant's reach: an agent mounts only subfolders of
/// the logs volume and none under `recorder/`, and each simulator mounts its pair's folder
/// where the evaluator points CARLA (`docs/security.md`, "Recordings").
fn check_recordings(c: &Container, at: &str) -> Result<(), RenderError> {
    use lb_domain::job::protocol::{recorder_dir, RECORDER_DIR, SIMULATOR_RECORDER_MOUNT};
    let mounts = c.volume_mounts.as_deref().unwrap_or_default();
    let logs = || {
        mounts
            .iter()
            .enumerate()
            .filter(|(_, m)| m.name == LOGS_VOLUME)
    };
    if c.name.starts_with(ROOT_ALLOWED_PREFIX) {
        for (i, m) in logs() {
            let sub = m.sub_path.as_deref().unwrap_or_default();
            if sub.is_empty() || sub.split('/').next() == Some(RECORDER_DIR) {
                return Err(refuse(
                    format!("{at}.volumeMounts[{i}].subPath"),
                    format!("`{}` may mount only its own folders of `{LOGS_VOLUME}`, never the recordings", c.name),
                ));
            }
        }
    }
    if let Some(pair) = c.name.strip_prefix("simulator-") {
        let own = recorder_dir(pair.parse().unwrap_or_default());
        let mounted = logs().any(|(_, m)| {
            m.mount_path == SIMULATOR_RECORDER_MOUNT && m.sub_path.as_deref() == Some(&own)
        });
        if !mounted {
            return Err(refuse(
                format!("{at}.volumeMounts"),
                format!(
                    "`{}` must mount `{own}` of `{LOGS_VOLUME}` at {SIMULATOR_RECORDER_MOUNT}",
                    c.name
                ),
            ));
        }
    }
    Ok(())
}

fn check_resources(
    r: Option<&ResourceRequirements>,
    expected: &ContainerResources,
    at: &str,
) -> Result<(), RenderError> {
    for (kind, map, want) in [
        (
            "requests",
            r.and_then(|r| r.requests.as_ref()),
            &expected.requests,
        ),
        (
            "limits",
            r.and_then(|r| r.limits.as_ref()),
            &expected.limits,
        ),
    ] {
        for (name, value, rule) in [
            ("cpu", &want.cpu, "requests equal limits"),
            ("memory", &want.memory, "requests equal limits"),
            (
                "ephemeral-storage",
                &want.storage,
                "a pod filling the node's disk evicts others",
            ),
        ] {
            let got = map.and_then(|m| m.get(name)).map(|q| q.0.as_str());
            if got != Some(value.as_str()) {
                return Err(refuse(
                    format!("{at}.{kind}.{name}"),
                    format!(
                        "is `{}`; the settings give `{value}` ({rule})",
                        got.unwrap_or("unset")
                    ),
                ));
            }
        }
    }
    Ok(())
}
