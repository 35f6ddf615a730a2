//! Server-side printing (`meta.k8s.io/v1` Table) so `kubectl get` shows the usual columns.

use axum::http::{header, HeaderMap};
use k8s_openapi::api::batch::v1::Job;
use k8s_openapi::api::core::v1::Pod;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::{ObjectMeta, Time};
use serde_json::{json, Value};

use crate::store::time_now;

/// Whether the client asked for a Table (`Accept: application/json;as=Table;...`).
pub fn wants_table(headers: &HeaderMap) -> bool {
    headers
        .get(header::ACCEPT)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|a| {
            a.split(',')
                .next()
                .is_some_and(|first| first.contains("as=Table"))
        })
}

/// `k8s.io/apimachinery/pkg/util/duration.HumanDuration`.
pub fn human_duration(seconds: i64) -> String {
    if seconds < -1 {
        return "<invalid>".into();
    }
    if seconds < 0 {
        return "0s".into();
    }
    if seconds < 120 {
        return format!("{seconds}s");
    }
    let minutes = seconds / 60;
    if minutes < 10 {
        let s = seconds % 60;
        return if s == 0 {
            format!("{minutes}m")
        } else {
            format!("{minutes}m{s}s")
        };
    }
    if minutes < 180 {
        return format!("{minutes}m");
    }
    let hours = seconds / 3600;
    if hours < 8 {
        let m = minutes % 60;
        return if m == 0 {
            format!("{hours}h")
        } else {
            format!("{hours}h{m}m")
        };
    }
    if hours < 48 {
        return format!("{hours}h");
    }
    if hours < 24 * 8 {
        let h = hours % 24;
        return if h == 0 {
            format!("{}d", hours / 24)
        } else {
            format!("{}d{h}h", hours / 24)
        };
    }
    if hours < 24 * 365 * 2 {
        return format!("{}d", hours / 24);
    }
    if hours < 24 * 365 * 8 {
        let dy = (hours / 24) % 365;
        return if dy == 0 {
            format!("{}y", hours / 24 / 365)
        } else {
            format!("{}y{dy}d", hours / 24 / 365)
        };
    }
    format!("{}y", hours / 24 / 365)
}

fn since(t: Option<&Time>) -> String {
    match t {
        Some(t) => human_duration(time_now().0.duration_since(t.0).as_secs()),
        None => "<unknown>".into(),
    }
}

fn column(name: &str, type_: &str, description: &str, priority: i32) -> Value {
    let format = if name == "Name" { "name" } else { "" };
    json!({"name": name, "type": type_, "format": format, "description": description, "priority": priority})
}

fn partial(meta: &ObjectMeta) -> Value {
    json!({
        "kind": "PartialObjectMetadata",
        "apiVersion": "meta.k8s.io/v1",
        "metadata": serde_json::to_value(meta).unwrap_or_default(),
    })
}

/// Kinds that print as Table rows.
pub trait Tabular: Sized {
    /// Column definitions.
    fn columns() -> Vec<Value>;
    /// Cells of one row.
    fn cells(&self) -> Vec<Value>;
    /// Metadata of the row's object.
    fn metadata(&self) -> &ObjectMeta;

    /// The whole Table.
    fn table(items: &[Self], list_meta: Value) -> Value {
        let rows: Vec<Value> = items
            .iter()
            .map(|o| json!({"cells": o.cells(), "object": partial(o.metadata())}))
            .collect();
        json!({
            "kind": "Table",
            "apiVersion": "meta.k8s.io/v1",
            "metadata": list_meta,
            "columnDefinitions": Self::columns(),
            "rows": rows,
        })
    }
}

fn has(job: &Job, type_: &str) -> bool {
    job.status
        .as_ref()
        .and_then(|s| s.conditions.as_ref())
        .is_some_and(|cs| cs.iter().any(|c| c.type_ == type_ && c.status == "True"))
}

impl Tabular for Job {
    fn columns() -> Vec<Value> {
        vec![
            column("Name", "string", "Name must be unique within a namespace.", 0),
            column("Status", "string", "Status of the job.", 0),
            column("Completions", "string", "The completion status of the job.", 0),
            column("Duration", "string", "Time required to complete the job.", 0),
            column("Age", "string", "CreationTimestamp is a timestamp representing the server time when this object was created.", 0),
            column("Containers", "string", "Names of each container in the template.", 1),
            column("Images", "string", "Images referenced by each container in the template.", 1),
            column("Selector", "string", "Job's label selector.", 1),
        ]
    }

    fn cells(&self) -> Vec<Value> {
        let status = self.status.clone().unwrap_or_default();
        let spec = self.spec.clone().unwrap_or_default();
        let state = if has(self, "Complete") {
            "Complete"
        } else if has(self, "Failed") {
            "Failed"
        } else if self.metadata.deletion_timestamp.is_some() {
            "Terminating"
        } else if has(self, "Suspended") {
            "Suspended"
        } else if has(self, "FailureTarget") {
            "FailureTarget"
        } else if has(self, "SuccessCriteriaMet") {
            "SuccessCriteriaMet"
        } else {
            "Running"
        };
        let succeeded = status.succeeded.unwrap_or(0);
        let completions = match (spec.completions, spec.parallelism.unwrap_or(1)) {
            (Some(c), _) => format!("{succeeded}/{c}"),
            (None, p) if p > 1 => format!("{succeeded}/1 of {p}"),
            (None, _) => format!("{succeeded}/1"),
        };
        let duration = match (&status.start_time, &status.completion_time) {
            (Some(s), Some(c)) => human_duration(c.0.duration_since(s.0).as_secs()),
            (Some(s), None) => human_duration(time_now().0.duration_since(s.0).as_secs()),
            _ => String::new(),
        };
        let pod = spec.template.spec.unwrap_or_default();
        let names: Vec<String> = pod.containers.iter().map(|c| c.name.clone()).collect();
        let images: Vec<String> = pod
            .containers
            .iter()
            .map(|c| c.image.clone().unwrap_or_default())
            .collect();
        let selector: Vec<String> = spec
            .selector
            .and_then(|s| s.match_labels)
            .unwrap_or_default()
            .into_iter()
            .map(|(k, v)| format!("{k}={v}"))
            .collect();
        vec![
            json!(self.metadata.name),
            json!(state),
            json!(completions),
            json!(duration),
            json!(since(self.metadata.creation_timestamp.as_ref())),
            json!(names.join(",")),
            json!(images.join(",")),
            json!(selector.join(",")),
        ]
    }

    fn metadata(&self) -> &ObjectMeta {
        &self.metadata
    }
}

/// The STATUS column of `kubectl get pods`.
pub fn pod_status_reason(pod: &Pod) -> String {
    let status = pod.status.clone().unwrap_or_default();
    let mut reason = status
        .reason
        .clone()
        .or(status.phase.clone())
        .unwrap_or_else(|| "Pending".into());
    let inits = status.init_container_statuses.clone().unwrap_or_default();
    let mut initializing = false;
    for (i, s) in inits.iter().enumerate() {
        let st = s.state.clone().unwrap_or_default();
        if let Some(t) = &st.terminated {
            if t.exit_code == 0 {
                continue;
            }
            reason = match &t.reason {
                Some(r) if !r.is_empty() => format!("Init:{r}"),
                _ => format!("Init:ExitCode:{}", t.exit_code),
            };
        } else if let Some(r) = st
            .waiting
            .as_ref()
            .and_then(|w| w.reason.clone())
            .filter(|r| !r.is_empty() && r != "PodInitializing")
        {
            reason = format!("Init:{r}");
        } else {
            reason = format!("Init:{i}/{}", inits.len());
        }
        initializing = true;
        break;
    }
    if !initializing {
        let mut has_running = false;
        for s in status.container_statuses.iter().flatten().rev() {
            let st = s.state.clone().unwrap_or_default();
            if let Some(r) = st
                .waiting
                .as_ref()
                .and_then(|w| w.reason.clone())
                .filter(|r| !r.is_empty())
            {
                reason = r;
            } else if let Some(t) = &st.terminated {
                reason = t
                    .reason
                    .clone()
                    .filter(|r| !r.is_empty())
                    .unwrap_or_else(|| format!("ExitCode:{}", t.exit_code));
            } else if st.running.is_some() && s.ready {
                has_running = true;
            }
        }
        if reason == "Completed" && has_running {
            reason = "Running".into();
        }
    }
    if pod.metadata.deletion_timestamp.is_some() {
        reason = "Terminating".into();
    }
    reason
}

impl Tabular for Pod {
    fn columns() -> Vec<Value> {
        vec![
            column("Name", "string", "Name must be unique within a namespace.", 0),
            column("Ready", "string", "The aggregate readiness state of this pod for accepting traffic.", 0),
            column("Status", "string", "The aggregate status of the containers in this pod.", 0),
            column("Restarts", "string", "The number of times the containers in this pod have been restarted and when the last container in this pod has restarted.", 0),
            column("Age", "string", "CreationTimestamp is a timestamp representing the server time when this object was created.", 0),
            column("IP", "string", "IP address allocated to the pod.", 1),
            column("Node", "string", "Name of the node assigned to the pod.", 1),
            column("Nominated Node", "string", "Name of the node nominated for the pod.", 1),
            column("Readiness Gates", "string", "Pod readiness gates.", 1),
        ]
    }

    fn cells(&self) -> Vec<Value> {
        let status = self.status.clone().unwrap_or_default();
        let containers = status.container_statuses.clone().unwrap_or_default();
        let total = self.spec.as_ref().map_or(0, |s| s.containers.len());
        let ready = containers.iter().filter(|s| s.ready).count();
        let restarts: i32 = containers.iter().map(|s| s.restart_count).sum();
        let last_restart = containers
            .iter()
            .filter_map(|s| {
                s.last_state
                    .as_ref()?
                    .terminated
                    .as_ref()?
                    .finished_at
                    .clone()
            })
            .max();
        let restarts = match last_restart {
            Some(t) if restarts > 0 => format!("{restarts} ({} ago)", since(Some(&t))),
            _ => restarts.to_string(),
        };
        vec![
            json!(self.metadata.name),
            json!(format!("{ready}/{total}")),
            json!(pod_status_reason(self)),
            json!(restarts),
            json!(since(self.metadata.creation_timestamp.as_ref())),
            json!(status.pod_ip.unwrap_or_else(|| "<none>".into())),
            json!(self
                .spec
                .as_ref()
                .and_then(|s| s.node_name.clone())
                .unwrap_or_else(|| "<none>".into())),
            json!("<none>"),
            json!("<none>"),
        ]
    }

    fn metadata(&self) -> &ObjectMeta {
        &self.metadata
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_read_like_kubectl() {
        assert_eq!(human_duration(5), "5s");
        assert_eq!(human_duration(119), "119s");
        assert_eq!(human_duration(185), "3m5s");
        assert_eq!(human_duration(600), "10m");
        assert_eq!(human_duration(4 * 3600 + 60), "4h1m");
        assert_eq!(human_duration(50 * 3600), "2d2h");
    }

    #[test]
    fn pod_status_shows_the_waiting_reason() {
        let pod: Pod = serde_yaml::from_str(
            "metadata: {name: p}\nstatus: {phase: Pending, containerStatuses: [{name: a, image: i, imageID: '', ready: false, restartCount: 0, state: {waiting: {reason: ImagePullBackOff}}}]}",
        )
        .unwrap();
        assert_eq!(pod_status_reason(&pod), "ImagePullBackOff");
        let init: Pod = serde_yaml::from_str(
            "metadata: {name: p}\nstatus: {phase: Pending, initContainerStatuses: [{name: i, image: i, imageID: '', ready: false, restartCount: 0, state: {running: {}}}]}",
        )
        .unwrap();
        assert_eq!(pod_status_reason(&init), "Init:0/1");
    }
}
