//! Checks of a rendered Job: the Kubernetes schema, strictly, and the rules of our Jobs.
//!
//! Strict schema check: the rendered JSON is deserialized into
//! `k8s_openapi::api::batch::v1::Job` (a type error names its path), serialized back and
//! compared with the original (ignoring nulls and empty lists and objects). `k8s-openapi`
//! drops fields it does not know, so any difference is an unknown or misplaced field, and
//! the error names its path.

use std::collections::{BTreeMap, HashSet};

use k8s_openapi::api::batch::v1::{Job, JobSpec};
use k8s_openapi::api::core::v1::{Container, PodSpec};
use lb_domain::job::plan::{is_dns_label, is_label_key, is_label_value, SUBMISSION_LABEL};
use lb_domain::job::protocol::exit;
use serde_json::Value;

use crate::RenderError;

/// Containers that run untrusted or simulator code: they get no AWS access and no token.
pub const ISOLATED_PREFIXES: [&str; 2] = ["agent-", "simulator-"];

fn spec_error(path: impl Into<String>, problem: impl Into<String>) -> RenderError {
    RenderError::InvalidSpec {
        path: path.into(),
        problem: problem.into(),
    }
}

fn join(path: &str, key: &str) -> String {
    if path.is_empty() {
        key.to_owned()
    } else {
        format!("{path}.{key}")
    }
}

/// Drops nulls and empty lists and objects (what a serializer may omit), keeping list
/// positions.
fn prune(value: &Value) -> Option<Value> {
    match value {
        Value::Null => None,
        Value::Array(items) if items.is_empty() => None,
        Value::Array(items) => Some(Value::Array(
            items
                .iter()
                .map(|item| prune(item).unwrap_or_else(|| Value::Object(Default::default())))
                .collect(),
        )),
        Value::Object(map) => {
            let kept: serde_json::Map<String, Value> = map
                .iter()
                .filter_map(|(k, v)| prune(v).map(|v| (k.clone(), v)))
                .collect();
            (!kept.is_empty()).then_some(Value::Object(kept))
        }
        other => Some(other.clone()),
    }
}

fn same_number(a: &serde_json::Number, b: &serde_json::Number) -> bool {
    match (a.as_i64(), b.as_i64()) {
        (Some(x), Some(y)) => x == y,
        _ => a.as_f64() == b.as_f64(),
    }
}

/// The first difference between the rendered JSON and its round trip.
fn difference(rendered: &Value, back: &Value, path: &str) -> Option<(String, String)> {
    match (rendered, back) {
        (Value::Object(a), Value::Object(b)) => {
            for (key, va) in a {
                let here = join(path, key);
                match b.get(key) {
                    None => {
                        return Some((
                            here,
                            "is not a field of the Kubernetes type at this place (unknown or misplaced)"
                                .into(),
                        ))
                    }
                    Some(vb) => {
                        if let Some(d) = difference(va, vb, &here) {
                            return Some(d);
                        }
                    }
                }
            }
            b.keys().find(|k| !a.contains_key(*k)).map(|k| {
                (
                    join(path, k),
                    "appeared when read as a Kubernetes Job".into(),
                )
            })
        }
        (Value::Array(a), Value::Array(b)) => {
            if a.len() != b.len() {
                return Some((
                    path.to_owned(),
                    format!(
                        "has {} items, {} when read as a Kubernetes Job",
                        a.len(),
                        b.len()
                    ),
                ));
            }
            a.iter()
                .zip(b)
                .enumerate()
                .find_map(|(i, (x, y))| difference(x, y, &format!("{path}[{i}]")))
        }
        (Value::Number(a), Value::Number(b)) if same_number(a, b) => None,
        (a, b) if a == b => None,
        (a, b) => Some((path.to_owned(), format!("is `{a}` but reads back as `{b}`"))),
    }
}

/// Env values must be strings: Kubernetes refuses numbers and booleans.
fn check_env_values(rendered: &Value) -> Result<(), RenderError> {
    let spec = &rendered["spec"]["template"]["spec"];
    for list in ["initContainers", "containers"] {
        let Some(containers) = spec[list].as_array() else {
            continue;
        };
        for (i, container) in containers.iter().enumerate() {
            let Some(env) = container["env"].as_array() else {
                continue;
            };
            for (j, var) in env.iter().enumerate() {
                let value = &var["value"];
                if !(value.is_string() || value.is_null()) {
                    return Err(spec_error(
                        format!("spec.template.spec.{list}[{i}].env[{j}].value"),
                        format!("must be a string, got `{value}`"),
                    ));
                }
            }
        }
    }
    Ok(())
}

fn check_labels(labels: Option<&BTreeMap<String, String>>, at: &str) -> Result<(), RenderError> {
    let labels = labels.ok_or_else(|| spec_error(at, "the labels are missing"))?;
    for (key, value) in labels {
        if !is_label_key(key) {
            return Err(spec_error(
                format!("{at}.{key}"),
                "is not a valid label key",
            ));
        }
        if !is_label_value(value) {
            return Err(spec_error(
                format!("{at}.{key}"),
                format!("`{value}` is not a valid label value"),
            ));
        }
    }
    if !labels.contains_key(SUBMISSION_LABEL) {
        return Err(spec_error(
            at,
            format!("the `{SUBMISSION_LABEL}` label is missing"),
        ));
    }
    Ok(())
}

/// The rules of a pair's Job on failures: a failed pod is replaced by a new one (which
/// resumes) only once it has stopped, a disrupted pod is never counted, and the exits no
/// retry can change fail the Job at once (`lb_domain::job::protocol::exit`).
fn check_failure_policy(spec: &JobSpec) -> Result<(), RenderError> {
    if spec.pod_replacement_policy.as_deref() != Some("Failed") {
        return Err(spec_error(
            "spec.podReplacementPolicy",
            "must be `Failed`: a new pod never runs beside one that is still stopping (two evaluators writing one results file)",
        ));
    }
    let rules = spec
        .pod_failure_policy
        .as_ref()
        .map(|p| p.rules.as_slice())
        .unwrap_or_default();
    let ignores_disruption = rules.first().is_some_and(|r| {
        r.action == "Ignore"
            && r.on_pod_conditions.iter().flatten().any(|c| {
                c.type_ == "DisruptionTarget" && c.status.as_deref().unwrap_or("True") == "True"
            })
    });
    if !ignores_disruption {
        return Err(spec_error(
            "spec.podFailurePolicy.rules[0]",
            "must be `Ignore` on the `DisruptionTarget` condition: a pod lost to a reclaimed or drained node is no failure of the participant's",
        ));
    }
    let want: Vec<i32> = exit::FAIL_JOB.iter().map(|&c| i32::from(c)).collect();
    let fails_job = rules.iter().any(|r| {
        r.action == "FailJob"
            && r.on_exit_codes
                .as_ref()
                .is_some_and(|e| e.operator == "In" && e.values == want)
    });
    if !fails_job {
        return Err(spec_error(
            "spec.podFailurePolicy.rules",
            format!("must end the Job (`FailJob`) on the exit codes {want:?} (lb_domain::job::protocol::exit)"),
        ));
    }
    Ok(())
}

fn check_pod(pod: &PodSpec) -> Result<(), RenderError> {
    const AT: &str = "spec.template.spec";
    if pod.restart_policy.as_deref() != Some("Never") {
        return Err(spec_error(
            format!("{AT}.restartPolicy"),
            "must be `Never` (a crash ends the pod, and a new pod resumes; the Pod failure policy needs it)",
        ));
    }
    if pod.automount_service_account_token != Some(false) {
        return Err(spec_error(
            format!("{AT}.automountServiceAccountToken"),
            "must be false: no container gets the service-account token by default",
        ));
    }
    let volumes = pod.volumes.as_deref().unwrap_or_default();
    let mut volume_names = HashSet::new();
    let mut token_volumes = HashSet::new();
    for (i, v) in volumes.iter().enumerate() {
        if !volume_names.insert(v.name.as_str()) {
            return Err(spec_error(
                format!("{AT}.volumes[{i}].name"),
                format!("the volume `{}` is defined twice", v.name),
            ));
        }
        let projects_token = v.projected.as_ref().is_some_and(|p| {
            p.sources
                .iter()
                .flatten()
                .any(|s| s.service_account_token.is_some())
        });
        if projects_token || v.secret.is_some() {
            token_volumes.insert(v.name.as_str());
        }
    }
    let lists: [(&str, &[Container]); 2] = [
        (
            "initContainers",
            pod.init_containers.as_deref().unwrap_or_default(),
        ),
        ("containers", &pod.containers),
    ];
    let mut names = HashSet::new();
    for (list, containers) in lists {
        for (i, c) in containers.iter().enumerate() {
            let at = format!("{AT}.{list}[{i}]");
            if !is_dns_label(&c.name) {
                return Err(spec_error(
                    format!("{at}.name"),
                    format!("`{}` is not a DNS-1123 label", c.name),
                ));
            }
            if !names.insert(c.name.as_str()) {
                return Err(spec_error(
                    format!("{at}.name"),
                    format!("the container name `{}` is used twice", c.name),
                ));
            }
            check_container(c, &at, &volume_names, &token_volumes)?;
        }
    }
    Ok(())
}

fn check_container(
    c: &Container,
    at: &str,
    volumes: &HashSet<&str>,
    token_volumes: &HashSet<&str>,
) -> Result<(), RenderError> {
    let isolated = ISOLATED_PREFIXES.iter().any(|p| c.name.starts_with(p));
    let mut env_names = HashSet::new();
    for (j, var) in c.env.iter().flatten().enumerate() {
        if var.name.is_empty() || var.name.contains('=') {
            return Err(spec_error(
                format!("{at}.env[{j}].name"),
                format!("`{}` is not a valid variable name", var.name),
            ));
        }
        if !env_names.insert(var.name.as_str()) {
            return Err(spec_error(
                format!("{at}.env[{j}].name"),
                format!("`{}` is set twice", var.name),
            ));
        }
        if isolated && var.name.starts_with("AWS_") {
            return Err(spec_error(
                format!("{at}.env[{j}].name"),
                format!(
                    "`{}` must not be given to `{}`: only init and logcopy get AWS access",
                    var.name, c.name
                ),
            ));
        }
    }
    if isolated && c.env_from.as_ref().is_some_and(|e| !e.is_empty()) {
        return Err(spec_error(
            format!("{at}.envFrom"),
            format!(
                "`{}` must not import environment from ConfigMaps or Secrets",
                c.name
            ),
        ));
    }
    let mut paths = HashSet::new();
    for (j, mount) in c.volume_mounts.iter().flatten().enumerate() {
        let here = format!("{at}.volumeMounts[{j}]");
        if !volumes.contains(mount.name.as_str()) {
            return Err(spec_error(
                format!("{here}.name"),
                format!("no volume is named `{}`", mount.name),
            ));
        }
        if !mount.mount_path.starts_with('/') {
            return Err(spec_error(
                format!("{here}.mountPath"),
                format!("`{}` is not an absolute path", mount.mount_path),
            ));
        }
        if !paths.insert(mount.mount_path.as_str()) {
            return Err(spec_error(
                format!("{here}.mountPath"),
                format!("`{}` is mounted twice", mount.mount_path),
            ));
        }
        if isolated
            && (token_volumes.contains(mount.name.as_str())
                || mount.mount_path.starts_with("/var/run/secrets"))
        {
            return Err(spec_error(
                format!("{here}.name"),
                format!("`{}` must not mount a token or secret volume", c.name),
            ));
        }
    }
    Ok(())
}

/// Checks a rendered Job and returns it typed.
pub fn check_job(rendered: &Value) -> Result<Job, RenderError> {
    check_env_values(rendered)?;
    let job: Job = serde_path_to_error::deserialize(rendered).map_err(|e| {
        let path = e.path().to_string();
        spec_error(
            if path == "." { String::new() } else { path },
            e.into_inner().to_string(),
        )
    })?;
    let back = serde_json::to_value(&job).map_err(|e| spec_error("", e.to_string()))?;
    if let (Some(a), Some(b)) = (prune(rendered), prune(&back)) {
        if let Some((path, problem)) = difference(&a, &b, "") {
            return Err(spec_error(path, problem));
        }
    }
    let name = job.metadata.name.as_deref().unwrap_or_default();
    if !is_dns_label(name) {
        return Err(spec_error(
            "metadata.name",
            format!("`{name}` is not a DNS-1123 label of at most 63 characters"),
        ));
    }
    check_labels(job.metadata.labels.as_ref(), "metadata.labels")?;
    let spec = job
        .spec
        .as_ref()
        .ok_or_else(|| spec_error("spec", "the Job has no spec"))?;
    let template_meta = spec.template.metadata.as_ref();
    check_labels(
        template_meta.and_then(|m| m.labels.as_ref()),
        "spec.template.metadata.labels",
    )?;
    let job_submission = job
        .metadata
        .labels
        .as_ref()
        .and_then(|l| l.get(SUBMISSION_LABEL));
    let pod_submission = template_meta
        .and_then(|m| m.labels.as_ref())
        .and_then(|l| l.get(SUBMISSION_LABEL));
    if job_submission != pod_submission {
        return Err(spec_error(
            "spec.template.metadata.labels",
            "the Pods must carry the Job's submission label",
        ));
    }
    let pod = spec
        .template
        .spec
        .as_ref()
        .ok_or_else(|| spec_error("spec.template.spec", "the Pod template has no spec"))?;
    check_pod(pod)?;
    check_failure_policy(spec)?;
    Ok(job)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn minimal() -> Value {
        json!({
            "apiVersion": "batch/v1",
            "kind": "Job",
            "metadata": {"name": "lb-1-team-0", "labels": {SUBMISSION_LABEL: "1"}},
            "spec": {
                "backoffLimit": 4,
                "podReplacementPolicy": "Failed",
                "podFailurePolicy": {"rules": [
                    {"action": "Ignore", "onPodConditions": [{"type": "DisruptionTarget", "status": "True"}]},
                    {"action": "FailJob", "onExitCodes": {"operator": "In", "values": [3, 78]}}
                ]},
                "template": {
                    "metadata": {"labels": {SUBMISSION_LABEL: "1"}},
                    "spec": {
                        "restartPolicy": "Never",
                        "automountServiceAccountToken": false,
                        "containers": [{
                            "name": "agent-1", "image": "x",
                            "env": [{"name": "A", "value": "1"}],
                            "volumeMounts": [{"name": "logs", "mountPath": "/tmp/logs"}]
                        }],
                        "volumes": [{"name": "logs", "emptyDir": {}}]
                    }
                }
            }
        })
    }

    fn problem(doc: &Value) -> (String, String) {
        match check_job(doc) {
            Err(RenderError::InvalidSpec { path, problem }) => (path, problem),
            other => panic!("expected InvalidSpec, got {other:?}"),
        }
    }

    #[test]
    fn a_minimal_job_passes() {
        let job = check_job(&minimal()).unwrap();
        assert_eq!(job.metadata.name.as_deref(), Some("lb-1-team-0"));
    }

    #[test]
    fn an_unknown_or_misplaced_field_is_named_by_its_path() {
        let mut doc = minimal();
        doc["spec"]["template"]["spec"]["containers"][0]["imagePullPolicyy"] = json!("Always");
        let (path, why) = problem(&doc);
        assert_eq!(path, "spec.template.spec.containers[0].imagePullPolicyy");
        assert!(why.contains("unknown or misplaced"), "{why}");

        let mut doc = minimal();
        doc["spec"]["restartPolicy"] = json!("OnFailure");
        assert_eq!(problem(&doc).0, "spec.restartPolicy");
    }

    #[test]
    fn a_wrongly_typed_field_is_named_by_its_path() {
        let mut doc = minimal();
        doc["spec"]["backoffLimit"] = json!("eight");
        let (path, _) = problem(&doc);
        assert_eq!(path, "spec.backoffLimit");
        let mut doc = minimal();
        doc["spec"]["template"]["spec"]["containers"][0]["env"][0]["value"] = json!(1);
        assert_eq!(
            problem(&doc).0,
            "spec.template.spec.containers[0].env[0].value"
        );
    }

    #[test]
    fn job_rules_are_enforced() {
        type Edit = Box<dyn Fn(&mut Value)>;
        let edits: Vec<(&str, Edit)> = vec![
            (
                "metadata.name",
                Box::new(|d| d["metadata"]["name"] = json!("Bad_Name")),
            ),
            (
                "metadata.labels",
                Box::new(|d| d["metadata"]["labels"] = json!({"x": "y"})),
            ),
            (
                "metadata.labels.x",
                Box::new(|d| d["metadata"]["labels"]["x"] = json!("-bad")),
            ),
            (
                "spec.template.spec.restartPolicy",
                Box::new(|d| d["spec"]["template"]["spec"]["restartPolicy"] = json!("OnFailure")),
            ),
            (
                "spec.podReplacementPolicy",
                Box::new(|d| d["spec"]["podReplacementPolicy"] = json!("TerminatingOrFailed")),
            ),
            (
                "spec.podFailurePolicy.rules[0]",
                Box::new(|d| {
                    d["spec"]["podFailurePolicy"]["rules"][0]["onPodConditions"][0]["type"] =
                        json!("ConfigIssue")
                }),
            ),
            (
                "spec.podFailurePolicy.rules",
                Box::new(|d| {
                    d["spec"]["podFailurePolicy"]["rules"][1]["onExitCodes"]["values"] =
                        json!([1, 3, 78])
                }),
            ),
            (
                "spec.template.spec.automountServiceAccountToken",
                Box::new(|d| {
                    d["spec"]["template"]["spec"]["automountServiceAccountToken"] = json!(true)
                }),
            ),
            (
                "spec.template.spec.containers[0].volumeMounts[0].name",
                Box::new(|d| {
                    d["spec"]["template"]["spec"]["containers"][0]["volumeMounts"][0]["name"] =
                        json!("nope")
                }),
            ),
            (
                "spec.template.spec.containers[0].env[0].name",
                Box::new(|d| {
                    d["spec"]["template"]["spec"]["containers"][0]["env"][0]["name"] =
                        json!("AWS_ROLE_ARN")
                }),
            ),
            (
                "spec.template.spec.containers[1].name",
                Box::new(|d| {
                    let c = d["spec"]["template"]["spec"]["containers"][0].clone();
                    d["spec"]["template"]["spec"]["containers"]
                        .as_array_mut()
                        .unwrap()
                        .push(c);
                }),
            ),
            (
                "spec.template.metadata.labels",
                Box::new(|d| {
                    d["spec"]["template"]["metadata"]["labels"][SUBMISSION_LABEL] = json!("2")
                }),
            ),
        ];
        for (expected, edit) in edits {
            let mut doc = minimal();
            edit(&mut doc);
            assert_eq!(problem(&doc).0, expected);
        }
    }

    #[test]
    fn isolated_containers_may_not_mount_a_token_volume() {
        let mut doc = minimal();
        doc["spec"]["template"]["spec"]["volumes"]
            .as_array_mut()
            .unwrap()
            .push(json!({"name": "tok", "projected": {"sources": [{"serviceAccountToken": {"path": "token"}}]}}));
        doc["spec"]["template"]["spec"]["containers"][0]["volumeMounts"]
            .as_array_mut()
            .unwrap()
            .push(json!({"name": "tok", "mountPath": "/t"}));
        let (path, why) = problem(&doc);
        assert_eq!(
            path,
            "spec.template.spec.containers[0].volumeMounts[1].name"
        );
        assert!(why.contains("token"), "{why}");
    }
}
