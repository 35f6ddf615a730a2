//! Job validation with the real field paths and messages, plus refusals of what local-kube
//! does not implement.

use std::collections::{BTreeMap, BTreeSet};

use k8s_openapi::api::batch::v1::{Job, JobSpec};
use k8s_openapi::api::core::v1::{Container, PodSpec, Volume};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector as LabelSelectorSpec;

use super::names::{
    dns1123_label_errors, dns1123_subdomain_errors, label_value_errors, qualified_name_errors,
};
use super::{
    CONTROLLER_UID_LABEL, JOB_NAME_LABEL, LEGACY_CONTROLLER_UID_LABEL, LEGACY_JOB_NAME_LABEL,
};
use crate::selector::LabelSelector;
use crate::status::{go_quote, FieldError};

/// The `fieldRef.fieldPath` values a container env may use.
pub const SUPPORTED_FIELD_PATHS: &[&str] = &[
    "metadata.annotations",
    "metadata.labels",
    "metadata.name",
    "metadata.namespace",
    "metadata.uid",
    "spec.nodeName",
    "spec.serviceAccountName",
    "status.hostIP",
    "status.hostIPs",
    "status.podIP",
    "status.podIPs",
];

/// Go's `%#v` of a `map[string]string` (keys sorted, as fmt prints maps).
pub fn go_map(m: Option<&BTreeMap<String, String>>) -> String {
    let body: Vec<String> = m
        .into_iter()
        .flatten()
        .map(|(k, v)| format!("{}:{}", go_quote(k), go_quote(v)))
        .collect();
    format!("map[string]string{{{}}}", body.join(", "))
}

/// The protobuf `String()` of a LabelSelector, as Invalid messages print it.
pub fn go_selector(s: &LabelSelectorSpec) -> String {
    let labels: Vec<String> = s
        .match_labels
        .iter()
        .flatten()
        .map(|(k, v)| format!("{k}: {v},"))
        .collect();
    let exprs: Vec<String> = s
        .match_expressions
        .iter()
        .flatten()
        .map(|e| {
            format!(
                "LabelSelectorRequirement{{Key:{},Operator:{},Values:[{}],}},",
                e.key,
                e.operator,
                e.values.clone().unwrap_or_default().join(" ")
            )
        })
        .collect();
    format!(
        "&LabelSelector{{MatchLabels:map[string]string{{{}}},MatchExpressions:[]LabelSelectorRequirement{{{}}},}}",
        labels.join(""),
        exprs.join("")
    )
}

fn labels(map: Option<&BTreeMap<String, String>>, path: &str, errs: &mut Vec<FieldError>) {
    for (k, v) in map.into_iter().flatten() {
        for msg in qualified_name_errors(k) {
            errs.push(FieldError::invalid(path, k, msg));
        }
        for msg in label_value_errors(v) {
            errs.push(FieldError::invalid(path, v, msg));
        }
    }
}

fn annotations(map: Option<&BTreeMap<String, String>>, path: &str, errs: &mut Vec<FieldError>) {
    let mut total = 0;
    for (k, v) in map.into_iter().flatten() {
        for msg in qualified_name_errors(k) {
            errs.push(FieldError::invalid(path, &k.to_lowercase(), msg));
        }
        total += k.len() + v.len();
    }
    if total > 256 * 1024 {
        errs.push(FieldError {
            type_: crate::status::FieldErrorType::Invalid,
            field: path.into(),
            value: Some(String::new()),
            detail: "may not be more than 262144 bytes".into(),
        });
    }
}

fn nonnegative(v: Option<i64>, path: &str, errs: &mut Vec<FieldError>) {
    if let Some(v) = v.filter(|v| *v < 0) {
        errs.push(FieldError::invalid_raw(
            path,
            v.to_string(),
            "must be greater than or equal to 0",
        ));
    }
}

fn local_kube_refuses(path: &str, what: &str, errs: &mut Vec<FieldError>) {
    errs.push(FieldError::forbidden(
        path,
        format!("local-kube does not implement {what}"),
    ));
}

/// Every validation error of a Job about to be created (after defaults and selector generation).
pub fn validate_job(job: &Job, uid: &str) -> Vec<FieldError> {
    let mut errs = Vec::new();
    let name = job.metadata.name.clone().unwrap_or_default();
    if name.is_empty() {
        errs.push(FieldError::required(
            "metadata.name",
            "name or generateName is required",
        ));
    } else {
        for msg in dns1123_subdomain_errors(&name) {
            errs.push(FieldError::invalid("metadata.name", &name, msg));
        }
    }
    labels(job.metadata.labels.as_ref(), "metadata.labels", &mut errs);
    annotations(
        job.metadata.annotations.as_ref(),
        "metadata.annotations",
        &mut errs,
    );
    let Some(spec) = job.spec.as_ref() else {
        errs.push(FieldError::required("spec.template.spec.containers", ""));
        return errs;
    };
    let template_labels = spec
        .template
        .metadata
        .as_ref()
        .and_then(|m| m.labels.as_ref());
    let manual = spec.manual_selector == Some(true);
    if !manual && template_labels.is_some() {
        generated_labels(spec, (uid, &name), template_labels, &mut errs);
    }
    for (value, path) in [
        (spec.parallelism.map(i64::from), "spec.parallelism"),
        (spec.completions.map(i64::from), "spec.completions"),
        (spec.backoff_limit.map(i64::from), "spec.backoffLimit"),
        (spec.active_deadline_seconds, "spec.activeDeadlineSeconds"),
        (
            spec.ttl_seconds_after_finished.map(i64::from),
            "spec.ttlSecondsAfterFinished",
        ),
    ] {
        nonnegative(value, path, &mut errs);
    }
    selector_matches(spec, template_labels, &mut errs);
    if spec
        .completion_mode
        .as_deref()
        .is_some_and(|m| m != "NonIndexed")
    {
        local_kube_refuses("spec.completionMode", "Indexed Jobs", &mut errs);
    }
    replacement_and_failure_policies(spec, &mut errs);
    if spec.success_policy.is_some() {
        local_kube_refuses("spec.successPolicy", "success policies", &mut errs);
    }
    if spec.backoff_limit_per_index.is_some() || spec.max_failed_indexes.is_some() {
        local_kube_refuses("spec.backoffLimitPerIndex", "per-index backoff", &mut errs);
    }
    if spec.suspend == Some(true) {
        local_kube_refuses("spec.suspend", "suspended Jobs", &mut errs);
    }
    if let Some(m) = spec.template.metadata.as_ref() {
        labels(m.labels.as_ref(), "spec.template.labels", &mut errs);
        annotations(
            m.annotations.as_ref(),
            "spec.template.annotations",
            &mut errs,
        );
    }
    match &spec.template.spec {
        None => errs.push(FieldError::required("spec.template.spec.containers", "")),
        Some(pod) => validate_pod_spec(pod, "spec.template.spec", &mut errs),
    }
    errs
}

/// The labels and selector a generated selector puts on the Job's template: the Job's uid and
/// name under the current and the legacy keys.
fn generated_labels(
    spec: &JobSpec,
    (uid, name): (&str, &str),
    template_labels: Option<&BTreeMap<String, String>>,
    errs: &mut Vec<FieldError>,
) {
    // The generated selector must have put the job's own labels on the template.
    for (key, want) in [
        (LEGACY_CONTROLLER_UID_LABEL, uid),
        (LEGACY_JOB_NAME_LABEL, name),
        (CONTROLLER_UID_LABEL, uid),
        (JOB_NAME_LABEL, name),
    ] {
        let path = format!("spec.template.metadata.labels[{key}]");
        match template_labels.and_then(|l| l.get(key)) {
            None => errs.push(FieldError::required(path, format!("must be '{want}'"))),
            Some(v) if v != want => errs.push(FieldError::invalid_raw(
                path,
                go_map(template_labels),
                format!("must be '{want}'"),
            )),
            Some(_) => {}
        }
    }
    if let Some(sel) = &spec.selector {
        let expected: BTreeMap<String, String> =
            [(CONTROLLER_UID_LABEL.to_owned(), uid.to_owned())].into();
        if let Ok(parsed) = LabelSelector::from_spec(sel) {
            if !parsed.matches(Some(&expected)) {
                errs.push(FieldError::invalid_raw(
                    "spec.selector",
                    go_selector(sel),
                    "`selector` not auto-generated",
                ));
            }
        }
    }
}

/// The Job's selector: present, valid, not empty, and matching the template's labels.
fn selector_matches(
    spec: &JobSpec,
    template_labels: Option<&BTreeMap<String, String>>,
    errs: &mut Vec<FieldError>,
) {
    match &spec.selector {
        None => errs.push(FieldError::required("spec.selector", "")),
        Some(sel) => match LabelSelector::from_spec(sel) {
            Err(e) => errs.push(FieldError::invalid_raw(
                "spec.selector",
                go_selector(sel),
                e,
            )),
            Ok(parsed) => {
                if parsed.is_empty() {
                    errs.push(FieldError::invalid_raw(
                        "spec.selector",
                        go_selector(sel),
                        "empty selector is invalid for deployment",
                    ));
                } else if !parsed.matches(template_labels) {
                    errs.push(FieldError::invalid_raw(
                        "spec.template.metadata.labels",
                        go_map(template_labels),
                        "`selector` does not match template `labels`",
                    ));
                }
            }
        },
    }
}

/// `validatePodFailurePolicy` and the rules tying it to the restart and replacement policies
/// (`pkg/apis/batch/validation`): `restartPolicy: Never`, `podReplacementPolicy: Failed`, at
/// most 20 rules, each with exactly one requirement and a known action, exit codes in
/// increasing order without duplicates, no 0 under `In`, a container name of the template.
fn replacement_and_failure_policies(spec: &JobSpec, errs: &mut Vec<FieldError>) {
    let replacement = spec.pod_replacement_policy.as_deref();
    if let Some(r) = replacement.filter(|r| !["Failed", "TerminatingOrFailed"].contains(r)) {
        errs.push(FieldError::not_supported(
            "spec.podReplacementPolicy",
            r,
            &["Failed", "TerminatingOrFailed"],
        ));
    }
    let Some(policy) = &spec.pod_failure_policy else {
        return;
    };
    if let Some(r) = replacement.filter(|r| *r != "Failed") {
        errs.push(FieldError::not_supported(
            "spec.podReplacementPolicy",
            r,
            &["Failed"],
        ));
    }
    let template = spec.template.spec.as_ref();
    let restart = template
        .and_then(|t| t.restart_policy.as_deref())
        .unwrap_or_default();
    if restart != "Never" {
        errs.push(FieldError::invalid(
            "spec.template.spec.restartPolicy",
            restart,
            "only \"Never\" is supported when podFailurePolicy is specified",
        ));
    }
    let names: BTreeSet<&str> = template
        .map(|t| {
            t.containers
                .iter()
                .chain(t.init_containers.iter().flatten())
                .map(|c| c.name.as_str())
                .collect()
        })
        .unwrap_or_default();
    if policy.rules.len() > 20 {
        errs.push(FieldError::forbidden(
            "spec.podFailurePolicy.rules",
            format!("must have at most 20 items (got {})", policy.rules.len()),
        ));
    }
    for (i, rule) in policy.rules.iter().enumerate() {
        failure_policy_rule(
            rule,
            &format!("spec.podFailurePolicy.rules[{i}]"),
            &names,
            errs,
        );
    }
}

fn failure_policy_rule(
    rule: &k8s_openapi::api::batch::v1::PodFailurePolicyRule,
    at: &str,
    containers: &BTreeSet<&str>,
    errs: &mut Vec<FieldError>,
) {
    if !["FailJob", "Ignore", "Count"].contains(&rule.action.as_str()) {
        errs.push(FieldError::not_supported(
            format!("{at}.action"),
            &rule.action,
            &["Count", "FailJob", "Ignore"],
        ));
    }
    match (&rule.on_exit_codes, &rule.on_pod_conditions) {
        (Some(_), Some(_)) => errs.push(FieldError::forbidden(
            at,
            "specifying both OnExitCodes and OnPodConditions is not supported",
        )),
        (None, None) => errs.push(FieldError::required(
            at,
            "specifying one of OnExitCodes and OnPodConditions is required",
        )),
        _ => {}
    }
    if let Some(codes) = &rule.on_exit_codes {
        let here = format!("{at}.onExitCodes");
        if !["In", "NotIn"].contains(&codes.operator.as_str()) {
            errs.push(FieldError::not_supported(
                format!("{here}.operator"),
                &codes.operator,
                &["In", "NotIn"],
            ));
        }
        if let Some(name) = codes
            .container_name
            .as_deref()
            .filter(|n| !containers.contains(n))
        {
            errs.push(FieldError::invalid(
                format!("{here}.containerName"),
                name,
                "must be one of the container or initContainer names in the pod template",
            ));
        }
        for (j, &v) in codes.values.iter().enumerate() {
            let path = format!("{here}.values[{j}]");
            if v == 0 && codes.operator == "In" {
                // NB: Go renders an integer value without quotes.
                errs.push(FieldError::invalid_raw(
                    path,
                    "0",
                    "must not be 0 for the In operator",
                ));
            } else if j > 0 && codes.values[j - 1] >= v {
                let detail = if codes.values[j - 1] == v {
                    "duplicate"
                } else {
                    "must be ordered"
                };
                errs.push(FieldError::invalid_raw(path, v.to_string(), detail));
            }
        }
    }
}

fn volume_sources(v: &Volume) -> Vec<String> {
    match serde_json::to_value(v) {
        Ok(serde_json::Value::Object(m)) => m.keys().filter(|k| *k != "name").cloned().collect(),
        _ => Vec::new(),
    }
}

fn validate_pod_spec(pod: &PodSpec, path: &str, errs: &mut Vec<FieldError>) {
    let mut volume_names = BTreeSet::new();
    for (i, v) in pod.volumes.iter().flatten().enumerate() {
        let vpath = format!("{path}.volumes[{i}]");
        if v.name.is_empty() {
            errs.push(FieldError::required(format!("{vpath}.name"), ""));
        } else {
            for msg in dns1123_label_errors(&v.name) {
                errs.push(FieldError::invalid(format!("{vpath}.name"), &v.name, msg));
            }
            if !volume_names.insert(v.name.clone()) {
                errs.push(FieldError::duplicate(format!("{vpath}.name"), &v.name));
            }
        }
        let sources = volume_sources(v);
        match sources.len() {
            0 => errs.push(FieldError::required(vpath, "must specify a volume type")),
            1 => {}
            _ => errs.push(FieldError::forbidden(
                format!("{vpath}.{}", sources[1]),
                "may not specify more than 1 volume type",
            )),
        }
    }
    match pod.restart_policy.as_deref() {
        Some("OnFailure") | Some("Never") => {}
        other => errs.push(FieldError::not_supported(
            format!("{path}.restartPolicy"),
            other.unwrap_or_default(),
            &["OnFailure", "Never"],
        )),
    }
    if pod.containers.is_empty() {
        errs.push(FieldError::required(format!("{path}.containers"), ""));
    }
    let mut names = BTreeSet::new();
    for (i, c) in pod.init_containers.iter().flatten().enumerate() {
        let cpath = format!("{path}.initContainers[{i}]");
        validate_container(c, &cpath, &volume_names, &mut names, errs);
        if c.restart_policy.is_some() {
            local_kube_refuses(
                &format!("{cpath}.restartPolicy"),
                "sidecar (restartable init) containers",
                errs,
            );
        }
    }
    for (i, c) in pod.containers.iter().enumerate() {
        let cpath = format!("{path}.containers[{i}]");
        validate_container(c, &cpath, &volume_names, &mut names, errs);
    }
    nonnegative(
        pod.termination_grace_period_seconds,
        &format!("{path}.terminationGracePeriodSeconds"),
        errs,
    );
    if let Some(d) = pod.active_deadline_seconds.filter(|d| *d <= 0) {
        errs.push(FieldError::invalid_raw(
            format!("{path}.activeDeadlineSeconds"),
            d.to_string(),
            "must be between 1 and 2147483647, inclusive",
        ));
    }
}

fn validate_container(
    c: &Container,
    cpath: &str,
    volumes: &BTreeSet<String>,
    names: &mut BTreeSet<String>,
    errs: &mut Vec<FieldError>,
) {
    if c.name.is_empty() {
        errs.push(FieldError::required(format!("{cpath}.name"), ""));
    } else {
        for msg in dns1123_label_errors(&c.name) {
            errs.push(FieldError::invalid(format!("{cpath}.name"), &c.name, msg));
        }
        if !names.insert(c.name.clone()) {
            errs.push(FieldError::duplicate(format!("{cpath}.name"), &c.name));
        }
    }
    if c.image.as_deref().unwrap_or_default().trim().is_empty() {
        errs.push(FieldError::required(format!("{cpath}.image"), ""));
    }
    validate_mounts(c, cpath, volumes, errs);
    validate_env(c, cpath, errs);
}

/// A container's volume mounts: of known volumes, at distinct paths, with relative subpaths.
fn validate_mounts(
    c: &Container,
    cpath: &str,
    volumes: &BTreeSet<String>,
    errs: &mut Vec<FieldError>,
) {
    let mut mount_paths = BTreeSet::new();
    for (j, m) in c.volume_mounts.iter().flatten().enumerate() {
        let mpath = format!("{cpath}.volumeMounts[{j}]");
        if m.name.is_empty() {
            errs.push(FieldError::required(format!("{mpath}.name"), ""));
        } else if !volumes.contains(&m.name) {
            errs.push(FieldError::not_found(format!("{mpath}.name"), &m.name));
        }
        if m.mount_path.is_empty() {
            errs.push(FieldError::required(format!("{mpath}.mountPath"), ""));
        } else if !mount_paths.insert(m.mount_path.clone()) {
            errs.push(FieldError::invalid(
                format!("{mpath}.mountPath"),
                &m.mount_path,
                "must be unique",
            ));
        }
        if let Some(sub) = m.sub_path.as_deref().filter(|s| !s.is_empty()) {
            if sub.starts_with('/') {
                errs.push(FieldError::invalid(
                    format!("{mpath}.subPath"),
                    sub,
                    "must be a relative path",
                ));
            }
            if sub.split('/').any(|part| part == "..") {
                errs.push(FieldError::invalid(
                    format!("{mpath}.subPath"),
                    sub,
                    "must not contain '..'",
                ));
            }
        }
        if m.sub_path_expr.is_some() {
            local_kube_refuses(&format!("{mpath}.subPathExpr"), "subPathExpr", errs);
        }
    }
}

/// A container's environment: printable names without `=`, each `valueFrom` one supported
/// source.
fn validate_env(c: &Container, cpath: &str, errs: &mut Vec<FieldError>) {
    for (k, e) in c.env.iter().flatten().enumerate() {
        let epath = format!("{cpath}.env[{k}]");
        if e.name.is_empty() {
            errs.push(FieldError::required(format!("{epath}.name"), ""));
        } else if e.name.contains('=') || !e.name.bytes().all(|b| (0x20..0x7f).contains(&b)) {
            errs.push(FieldError::invalid(
                format!("{epath}.name"),
                &e.name,
                "a valid environment variable name must consist only of printable ASCII characters other than '='",
            ));
        }
        let Some(from) = &e.value_from else { continue };
        if e.value.as_deref().is_some_and(|v| !v.is_empty()) {
            errs.push(FieldError::invalid(
                format!("{epath}.valueFrom"),
                "",
                "may not be specified when `value` is not empty",
            ));
        }
        let count = [
            from.field_ref.is_some(),
            from.resource_field_ref.is_some(),
            from.config_map_key_ref.is_some(),
            from.secret_key_ref.is_some(),
            from.file_key_ref.is_some(),
        ]
        .iter()
        .filter(|b| **b)
        .count();
        if count != 1 {
            errs.push(FieldError::invalid(
                format!("{epath}.valueFrom"),
                "",
                "must specify one of: `fieldRef`, `resourceFieldRef`, `configMapKeyRef` or `secretKeyRef`",
            ));
        }
        if let Some(f) = &from.field_ref {
            let base = f.field_path.split('[').next().unwrap_or_default();
            let subscripted = f.field_path.contains('[');
            let ok = SUPPORTED_FIELD_PATHS.contains(&base)
                && (subscripted == matches!(base, "metadata.labels" | "metadata.annotations"));
            if !ok {
                errs.push(FieldError::not_supported(
                    format!("{epath}.valueFrom.fieldRef.fieldPath"),
                    &f.field_path,
                    SUPPORTED_FIELD_PATHS,
                ));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::objects::job::prepare_create;

    fn job(yaml: &str) -> Job {
        serde_yaml::from_str(yaml).unwrap()
    }

    const BASE: &str = r#"
apiVersion: batch/v1
kind: Job
metadata: {name: ok}
spec:
  template:
    spec:
      restartPolicy: Never
      containers: [{name: c, image: busybox, command: [true]}]
"#;

    fn causes(yaml: &str) -> Vec<String> {
        match prepare_create(job(yaml), "default", None) {
            Ok(_) => Vec::new(),
            Err(e) => e.details.unwrap()["causes"]
                .as_array()
                .unwrap()
                .iter()
                .map(|c| {
                    format!(
                        "{}: {}",
                        c["field"].as_str().unwrap(),
                        c["message"].as_str().unwrap()
                    )
                })
                .collect(),
        }
    }

    #[test]
    fn a_minimal_job_is_valid() {
        assert!(causes(BASE).is_empty());
    }

    #[test]
    fn restart_policy_always_is_refused_as_the_real_server_does() {
        let c = causes(&BASE.replace("restartPolicy: Never", "dnsPolicy: ClusterFirst"));
        assert_eq!(
            c,
            vec!["spec.template.spec.restartPolicy: Unsupported value: \"Always\": supported values: \"OnFailure\", \"Never\""]
        );
    }

    #[test]
    fn a_name_longer_than_a_label_fails_on_the_generated_template_labels() {
        let long = "a".repeat(64);
        let c = causes(&BASE.replace("name: ok", &format!("name: {long}")));
        assert_eq!(c.len(), 2, "{c:?}");
        assert!(c.iter().all(|m| m
            == &format!(
                "spec.template.labels: Invalid value: \"{long}\": must be no more than 63 bytes"
            )));
    }

    #[test]
    fn missing_volumes_duplicates_and_bad_subpaths_are_reported() {
        let y = r#"
metadata: {name: v}
spec:
  template:
    spec:
      restartPolicy: OnFailure
      volumes: [{name: logs, emptyDir: {}}, {name: logs, emptyDir: {}}]
      containers:
      - name: a
        image: x
        volumeMounts: [{name: nope, mountPath: /a}, {name: logs, mountPath: /a, subPath: ../up}]
      - name: a
        image: ""
"#;
        let c = causes(y);
        let want = [
            "spec.template.spec.volumes[1].name: Duplicate value: \"logs\"",
            "spec.template.spec.containers[0].volumeMounts[0].name: Not found: \"nope\"",
            "spec.template.spec.containers[0].volumeMounts[1].mountPath: Invalid value: \"/a\": must be unique",
            "spec.template.spec.containers[0].volumeMounts[1].subPath: Invalid value: \"../up\": must not contain '..'",
            "spec.template.spec.containers[1].name: Duplicate value: \"a\"",
            "spec.template.spec.containers[1].image: Required value",
        ];
        for w in want {
            assert!(c.iter().any(|m| m == w), "missing {w} in {c:?}");
        }
    }

    #[test]
    fn a_hand_written_selector_needs_manual_selector() {
        let y = BASE.replace(
            "spec:\n  template:",
            "spec:\n  selector: {matchLabels: {app: x}}\n  template:",
        );
        let c = causes(&y);
        assert!(c.iter().any(|m| m.starts_with("spec.selector: Invalid value: &LabelSelector{MatchLabels:map[string]string{app: x,") && m.ends_with("`selector` not auto-generated")), "{c:?}");
    }

    #[test]
    fn unsupported_field_refs_are_refused() {
        let y = BASE.replace(
            "command: [true]}",
            "command: [true], env: [{name: X, valueFrom: {fieldRef: {fieldPath: spec.bogus}}}]}",
        );
        let c = causes(&y);
        assert_eq!(c.len(), 1);
        assert!(c[0].starts_with("spec.template.spec.containers[0].env[0].valueFrom.fieldRef.fieldPath: Unsupported value: \"spec.bogus\""));
    }
}
