//! Core/v1 Events about pods, as client-go's event recorder writes them: one Event per
//! (pod, source, reason, message), its `count` and `lastTimestamp` growing while the same
//! thing is said again. Today only the Cluster Autoscaler's word on waiting pods (see
//! [`super::scheduler::autoscaler_word`]) is recorded.

use std::collections::BTreeMap;

use k8s_openapi::api::core::v1::{Event, EventSource, ObjectReference, Pod};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::ObjectMeta;

use crate::store::time_now;

/// Fields an Event list may select on (kube-apiserver's `pkg/registry/core/event`
/// `ToSelectableFields`, plus the metadata pair every resource has).
pub const FIELDS: [&str; 13] = [
    "metadata.name",
    "metadata.namespace",
    "involvedObject.kind",
    "involvedObject.namespace",
    "involvedObject.name",
    "involvedObject.uid",
    "involvedObject.apiVersion",
    "involvedObject.resourceVersion",
    "involvedObject.fieldPath",
    "reason",
    "reportingComponent",
    "source",
    "type",
];

/// Events by (pod uid, component, reason, message).
#[derive(Debug, Default)]
pub struct Events {
    by_key: BTreeMap<(String, String, String, String), Event>,
    next: u64,
}

impl Events {
    /// Records that `component` said `reason: message` (type `Normal`) about `pod` now: a new
    /// Event, or the same one counted again.
    pub fn record(&mut self, pod: &Pod, component: &str, reason: &str, message: &str) {
        let uid = pod.metadata.uid.clone().unwrap_or_default();
        let key = (
            uid.clone(),
            component.to_owned(),
            reason.to_owned(),
            message.to_owned(),
        );
        let now = time_now();
        if let Some(e) = self.by_key.get_mut(&key) {
            e.count = Some(e.count.unwrap_or(1) + 1);
            e.last_timestamp = Some(now);
            return;
        }
        self.next += 1;
        let pod_name = pod.metadata.name.clone().unwrap_or_default();
        let namespace = pod.metadata.namespace.clone();
        let event = Event {
            metadata: ObjectMeta {
                // client-go names an Event `<object>.<unix nanoseconds in hex>`.
                name: Some(format!("{pod_name}.{:016x}", self.next)),
                namespace: namespace.clone(),
                ..Default::default()
            },
            involved_object: ObjectReference {
                api_version: Some("v1".into()),
                kind: Some("Pod".into()),
                name: Some(pod_name),
                namespace,
                uid: Some(uid),
                resource_version: pod.metadata.resource_version.clone(),
                ..Default::default()
            },
            reason: Some(reason.into()),
            message: Some(message.into()),
            source: Some(EventSource {
                component: Some(component.into()),
                host: None,
            }),
            first_timestamp: Some(now.clone()),
            last_timestamp: Some(now),
            count: Some(1),
            type_: Some("Normal".into()),
            reporting_component: Some(String::new()),
            reporting_instance: Some(String::new()),
            ..Default::default()
        };
        self.by_key.insert(key, event);
    }

    /// Drops the events about pod `uid`, once it is gone (a real cluster keeps events an
    /// hour, local-kube as long as their pod).
    pub fn forget(&mut self, uid: &str) {
        self.by_key.retain(|(pod, ..), _| pod != uid);
    }

    /// The events of `namespace` that `accept` takes, oldest first.
    pub fn list(&self, namespace: &str, accept: impl Fn(&Event) -> bool) -> Vec<Event> {
        let mut out: Vec<Event> = self
            .by_key
            .values()
            .filter(|e| e.metadata.namespace.as_deref() == Some(namespace))
            .filter(|e| accept(e))
            .cloned()
            .collect();
        out.sort_by(|a, b| a.metadata.name.cmp(&b.metadata.name));
        out
    }
}

/// The value of selectable field `field` of `e`.
pub fn field(e: &Event, field: &str) -> String {
    let o = &e.involved_object;
    let s = |v: &Option<String>| v.clone().unwrap_or_default();
    match field {
        "metadata.name" => s(&e.metadata.name),
        "metadata.namespace" => s(&e.metadata.namespace),
        "involvedObject.kind" => s(&o.kind),
        "involvedObject.namespace" => s(&o.namespace),
        "involvedObject.name" => s(&o.name),
        "involvedObject.uid" => s(&o.uid),
        "involvedObject.apiVersion" => s(&o.api_version),
        "involvedObject.resourceVersion" => s(&o.resource_version),
        "involvedObject.fieldPath" => s(&o.field_path),
        "reason" => s(&e.reason),
        "reportingComponent" => s(&e.reporting_component),
        "source" => e
            .source
            .as_ref()
            .map(|src| s(&src.component))
            .unwrap_or_default(),
        "type" => s(&e.type_),
        _ => String::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pod(name: &str, uid: &str) -> Pod {
        serde_json::from_value(serde_json::json!({
            "metadata": {"name": name, "namespace": "default", "uid": uid, "resourceVersion": "7"}
        }))
        .unwrap()
    }

    #[test]
    fn the_same_word_is_counted_and_a_new_one_is_a_new_event() {
        let mut events = Events::default();
        let a = pod("a", "u-a");
        events.record(&a, "cluster-autoscaler", "NotTriggerScaleUp", "m1");
        events.record(&a, "cluster-autoscaler", "NotTriggerScaleUp", "m1");
        events.record(&a, "cluster-autoscaler", "NotTriggerScaleUp", "m2");
        events.record(
            &pod("b", "u-b"),
            "cluster-autoscaler",
            "NotTriggerScaleUp",
            "m1",
        );
        let about_a = events.list("default", |e| field(e, "involvedObject.uid") == "u-a");
        assert_eq!(about_a.len(), 2);
        assert_eq!(about_a[0].count, Some(2));
        assert_eq!(about_a[0].message.as_deref(), Some("m1"));
        assert_eq!(field(&about_a[0], "source"), "cluster-autoscaler");
        assert_eq!(field(&about_a[0], "involvedObject.kind"), "Pod");
        assert!(events.list("other", |_| true).is_empty());
        events.forget("u-a");
        assert_eq!(events.list("default", |_| true).len(), 1);
    }
}
