//! What the API server does to a Job on create: metadata, defaults, the generated selector and
//! labels, validation.

use k8s_openapi::api::batch::v1::{Job, JobStatus};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector as LabelSelectorSpec;

use super::names::{generate_name, new_uid};
use super::validation::validate_job;
use super::{
    defaults, CONTROLLER_UID_LABEL, JOB_NAME_LABEL, LEGACY_CONTROLLER_UID_LABEL,
    LEGACY_JOB_NAME_LABEL,
};
use crate::status::{ApiError, JOBS};
use crate::store::time_now;

/// Turns a posted Job into the object the server stores, or the error the server answers.
pub fn prepare_create(mut job: Job, namespace: &str, uid: Option<String>) -> Result<Job, ApiError> {
    if let Some(ns) = job
        .metadata
        .namespace
        .as_deref()
        .filter(|ns| !ns.is_empty())
    {
        if ns != namespace {
            return Err(ApiError::bad_request(
                "the namespace of the provided object does not match the namespace sent on the request",
            ));
        }
    }
    let meta = &mut job.metadata;
    if meta.name.as_deref().unwrap_or_default().is_empty() {
        if let Some(base) = meta.generate_name.as_deref().filter(|g| !g.is_empty()) {
            meta.name = Some(generate_name(base));
        }
    }
    let uid = uid.unwrap_or_else(new_uid);
    meta.namespace = Some(namespace.to_owned());
    meta.uid = Some(uid.clone());
    meta.creation_timestamp = Some(time_now());
    meta.generation = Some(1);
    meta.resource_version = None;
    meta.deletion_timestamp = None;
    meta.deletion_grace_period_seconds = None;
    meta.managed_fields = None;
    meta.self_link = None;
    job.status = Some(JobStatus::default());
    let name = job.metadata.name.clone().unwrap_or_default();

    let spec = job.spec.get_or_insert_with(Default::default);
    defaults::job_spec(spec);
    let template_meta = spec.template.metadata.get_or_insert_with(Default::default);
    // NB: decoding defaults copy the template's labels to an unlabeled Job before the
    // generated ones exist; reads then show the generated ones too (see below).
    let job_unlabeled = job.metadata.labels.as_ref().is_none_or(|l| l.is_empty());
    if job_unlabeled {
        if let Some(l) = template_meta.labels.clone().filter(|l| !l.is_empty()) {
            job.metadata.labels = Some(l);
        }
    }
    if spec.manual_selector != Some(true) {
        let labels = template_meta.labels.get_or_insert_with(Default::default);
        for key in [LEGACY_JOB_NAME_LABEL, JOB_NAME_LABEL] {
            labels.entry(key.to_owned()).or_insert_with(|| name.clone());
        }
        for key in [LEGACY_CONTROLLER_UID_LABEL, CONTROLLER_UID_LABEL] {
            labels.entry(key.to_owned()).or_insert_with(|| uid.clone());
        }
        let selector = spec.selector.get_or_insert_with(LabelSelectorSpec::default);
        selector
            .match_labels
            .get_or_insert_with(Default::default)
            .entry(CONTROLLER_UID_LABEL.to_owned())
            .or_insert_with(|| uid.clone());
    }

    let errors = validate_job(&job, &uid);
    if !errors.is_empty() {
        return Err(ApiError::invalid(&JOBS, &name, &errors));
    }
    if job_unlabeled {
        let template_labels = job
            .spec
            .as_ref()
            .and_then(|s| s.template.metadata.as_ref())
            .and_then(|m| m.labels.clone());
        job.metadata.labels = template_labels;
    }
    Ok(job)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn create_generates_the_selector_and_the_four_job_labels() {
        let job: Job = serde_yaml::from_str(
            "metadata: {generateName: sub-}\nspec: {template: {spec: {restartPolicy: Never, containers: [{name: c, image: i}]}}}",
        )
        .unwrap();
        let job = prepare_create(job, "ns", Some("u-1".into())).unwrap();
        let name = job.metadata.name.clone().unwrap();
        assert!(name.starts_with("sub-") && name.len() == 9, "{name}");
        let spec = job.spec.unwrap();
        let sel = spec.selector.unwrap().match_labels.unwrap();
        assert_eq!(
            sel.get(CONTROLLER_UID_LABEL).map(String::as_str),
            Some("u-1")
        );
        let labels = spec.template.metadata.unwrap().labels.unwrap();
        assert_eq!(labels.get(JOB_NAME_LABEL), Some(&name));
        assert_eq!(labels.get(LEGACY_JOB_NAME_LABEL), Some(&name));
        assert_eq!(
            labels.get(LEGACY_CONTROLLER_UID_LABEL).map(String::as_str),
            Some("u-1")
        );
        assert_eq!(job.metadata.labels, Some(labels));
        assert_eq!(spec.backoff_limit, Some(6));
        assert_eq!(job.metadata.namespace.as_deref(), Some("ns"));
    }

    #[test]
    fn a_job_with_its_own_labels_keeps_them() {
        let job: Job = serde_yaml::from_str(
            "metadata: {name: j, labels: {submission: '7'}}\nspec: {template: {spec: {restartPolicy: Never, containers: [{name: c, image: i}]}}}",
        )
        .unwrap();
        let job = prepare_create(job, "ns", None).unwrap();
        assert_eq!(job.metadata.labels.unwrap().len(), 1);
    }

    #[test]
    fn another_namespace_in_the_body_is_a_bad_request() {
        let job: Job = serde_yaml::from_str("metadata: {name: j, namespace: other}").unwrap();
        let err = prepare_create(job, "ns", None).unwrap_err();
        assert_eq!(err.code, 400);
    }

    #[test]
    fn a_manual_selector_must_match_the_template() {
        let job: Job = serde_yaml::from_str(
            "metadata: {name: j}\nspec: {manualSelector: true, selector: {matchLabels: {a: b}}, template: {metadata: {labels: {a: c}}, spec: {restartPolicy: Never, containers: [{name: c, image: i}]}}}",
        )
        .unwrap();
        let err = prepare_create(job, "ns", None).unwrap_err();
        assert!(
            err.message
                .contains("`selector` does not match template `labels`"),
            "{}",
            err.message
        );
    }
}
