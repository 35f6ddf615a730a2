//! The Cluster Autoscaler's events about a pending pod, read from the API
//! (`lb_domain::cluster::autoscaler` judges what they say).

use k8s_openapi::api::core::v1::Event;
use k8s_openapi::jiff::Timestamp;

pub use lb_domain::cluster::autoscaler::{
    Outlook, ScaleUpWord, COMPONENT, NOT_TRIGGERED, TRIGGERED,
};

/// The latest autoscaler word among `events` about the pod with uid `pod_uid`. Only the
/// autoscaler's own events count: anyone allowed to create events could write one with its
/// reasons, and a false `NotTriggerScaleUp` would fail a pod that only waits.
pub fn latest_word(events: &[Event], pod_uid: &str) -> Option<ScaleUpWord> {
    events
        .iter()
        .filter(|e| e.involved_object.uid.as_deref() == Some(pod_uid))
        .filter(|e| from_the_autoscaler(e))
        .filter(|e| matches!(e.reason.as_deref(), Some(NOT_TRIGGERED | TRIGGERED)))
        .map(|e| ScaleUpWord {
            reason: e.reason.clone().unwrap_or_default(),
            message: e.message.clone().unwrap_or_default(),
            at: last_said(e),
        })
        .max_by_key(|w| w.at)
}

/// Whether the autoscaler emitted `e`: client-go's core/v1 recorder names it in
/// `source.component`, an events.k8s.io/v1 recorder in `reportingComponent`.
fn from_the_autoscaler(e: &Event) -> bool {
    let source = e.source.as_ref().and_then(|s| s.component.as_deref());
    source == Some(COMPONENT) || e.reporting_component.as_deref() == Some(COMPONENT)
}

/// When an event was last emitted: `series.lastObservedTime` (events.k8s.io/v1 recorders),
/// `lastTimestamp` (client-go's core/v1 recorder, which the autoscaler uses, updating it and
/// `count` on each repeat), or `eventTime`.
fn last_said(e: &Event) -> Option<Timestamp> {
    let series = e
        .series
        .as_ref()
        .and_then(|s| s.last_observed_time.as_ref())
        .map(|t| t.0);
    [
        series,
        e.last_timestamp.as_ref().map(|t| t.0),
        e.event_time.as_ref().map(|t| t.0),
    ]
    .into_iter()
    .flatten()
    .max()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn event_from(component: &str, uid: &str, reason: &str, message: &str, at: &str) -> Event {
        serde_json::from_value(serde_json::json!({
            "metadata": {"name": format!("p.{at}"), "namespace": "leaderboard"},
            "involvedObject": {"kind": "Pod", "name": "p", "uid": uid},
            "reason": reason, "message": message, "type": "Normal",
            "source": {"component": component},
            "count": 3, "firstTimestamp": "2026-11-24T09:00:00Z", "lastTimestamp": at,
        }))
        .unwrap()
    }

    #[test]
    fn an_event_with_the_autoscalers_reason_from_anyone_else_is_not_its_word() {
        let said = "2026-11-24T09:05:00Z";
        let impostor = event_from(
            "my-controller",
            "u1",
            NOT_TRIGGERED,
            "pod didn't trigger scale-up: 1 max node group size reached",
            said,
        );
        assert_eq!(latest_word(std::slice::from_ref(&impostor), "u1"), None);
        let mut reported: Event = event_from("", "u1", TRIGGERED, "pod triggered scale-up", said);
        reported.source = None;
        reported.reporting_component = Some(COMPONENT.into());
        assert_eq!(
            latest_word(&[impostor, reported], "u1").unwrap().reason,
            TRIGGERED
        );
    }

    #[test]
    fn the_latest_word_about_the_pod_counts() {
        let event = |uid: &str, reason: &str, message: &str, at: &str| -> Event {
            event_from(COMPONENT, uid, reason, message, at)
        };
        let events = [
            event(
                "u1",
                NOT_TRIGGERED,
                "pod didn't trigger scale-up: 1 max node group size reached",
                "2026-11-24T09:05:00Z",
            ),
            event(
                "u1",
                NOT_TRIGGERED,
                "pod didn't trigger scale-up: 1 Insufficient nvidia.com/gpu",
                "2026-11-24T09:09:00Z",
            ),
            event(
                "u1",
                "FailedScheduling",
                "0/2 nodes are available: 2 Insufficient nvidia.com/gpu.",
                "2026-11-24T09:10:00Z",
            ),
            event(
                "u2",
                TRIGGERED,
                "pod triggered scale-up",
                "2026-11-24T09:11:00Z",
            ),
        ];
        let w = latest_word(&events, "u1").unwrap();
        assert!(
            w.message.ends_with("1 Insufficient nvidia.com/gpu"),
            "{w:?}"
        );
        assert_eq!(w.at.unwrap().to_string(), "2026-11-24T09:09:00Z");
        assert_eq!(latest_word(&events, "u2").unwrap().reason, TRIGGERED);
        assert_eq!(latest_word(&events, "u3"), None);
    }
}
