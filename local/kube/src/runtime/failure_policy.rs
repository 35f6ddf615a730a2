//! The Job controller's Pod failure policy: which rule a failed pod matches, and what follows.
//!
//! As `pkg/controller/job/pod_failure_policy.go` of Kubernetes (Kubernetes docs, "Handling
//! retriable and non-retriable pod failures with Pod failure policy"): rules are tried in
//! order and the first match decides; `onExitCodes` looks at the terminated, non-zero exit
//! codes of the app containers, then of the init containers (optionally of one container by
//! name); `onPodConditions` at the pod's conditions by type and status. No match counts the
//! failure against `backoffLimit`. A rule with an unknown action is skipped.

use k8s_openapi::api::batch::v1::{PodFailurePolicy, PodFailurePolicyOnExitCodesRequirement};
use k8s_openapi::api::core::v1::{ContainerStatus, Pod, PodStatus};

use crate::objects::pod::terminated_code;

/// The Job condition reason of a Job a `FailJob` rule ended.
pub const POD_FAILURE_POLICY: &str = "PodFailurePolicy";

/// What a failed pod does to its Job.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Outcome {
    /// Counted against `backoffLimit` (no rule matched, or a `Count` rule).
    Count,
    /// Not counted; a new pod replaces it (`Ignore`).
    Ignore,
    /// The Job fails at once with this message (`FailJob`).
    FailJob(String),
}

/// Matches a failed pod against the policy (none: every failure counts).
pub fn outcome(policy: Option<&PodFailurePolicy>, pod: &Pod) -> Outcome {
    let Some(policy) = policy else {
        return Outcome::Count;
    };
    let empty = PodStatus::default();
    let status = pod.status.as_ref().unwrap_or(&empty);
    let ns = pod.metadata.namespace.as_deref().unwrap_or_default();
    let name = pod.metadata.name.as_deref().unwrap_or_default();
    for (index, rule) in policy.rules.iter().enumerate() {
        let matched = if let Some(codes) = &rule.on_exit_codes {
            matching_container(status, codes).map(|c| {
                let code = terminated_code(c).unwrap_or(0);
                format!(
                    "Container {} for pod {ns}/{name} failed with exit code {code} matching {} rule at index {index}",
                    c.name, rule.action
                )
            })
        } else if let Some(patterns) = &rule.on_pod_conditions {
            status.conditions.iter().flatten().find_map(|c| {
                patterns
                    .iter()
                    .any(|p| {
                        p.type_ == c.type_ && p.status.as_deref().unwrap_or("True") == c.status
                    })
                    .then(|| {
                        format!(
                            "Pod {ns}/{name} has condition {} matching {} rule at index {index}",
                            c.type_, rule.action
                        )
                    })
            })
        } else {
            None
        };
        let Some(message) = matched else { continue };
        match rule.action.as_str() {
            "Ignore" => return Outcome::Ignore,
            "Count" => return Outcome::Count,
            "FailJob" => return Outcome::FailJob(message),
            _ => continue,
        }
    }
    Outcome::Count
}

fn matching_container<'a>(
    status: &'a PodStatus,
    req: &PodFailurePolicyOnExitCodesRequirement,
) -> Option<&'a ContainerStatus> {
    let lists = [&status.container_statuses, &status.init_container_statuses];
    lists.into_iter().flatten().flatten().find(|c| {
        let Some(code) = terminated_code(c) else {
            return false;
        };
        let named = req.container_name.as_ref().is_none_or(|n| *n == c.name);
        let listed = req.values.contains(&code);
        let operator = match req.operator.as_str() {
            "In" => listed,
            "NotIn" => !listed,
            _ => false,
        };
        named && code != 0 && operator
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn policy() -> PodFailurePolicy {
        serde_json::from_value(json!({"rules": [
            {"action": "Ignore", "onPodConditions": [{"type": "DisruptionTarget", "status": "True"}]},
            {"action": "FailJob", "onExitCodes": {"operator": "In", "values": [3, 78]}}
        ]}))
        .unwrap()
    }

    fn failed(exit: i32, conditions: serde_json::Value) -> Pod {
        serde_json::from_value(json!({
            "metadata": {"name": "p", "namespace": "ns"},
            "status": {"phase": "Failed", "conditions": conditions, "containerStatuses": [
                {"name": "simulator-1", "image": "i", "imageID": "", "ready": false, "restartCount": 0,
                 "state": {"terminated": {"exitCode": 0}}},
                {"name": "agent-1", "image": "i", "imageID": "", "ready": false, "restartCount": 0,
                 "state": {"terminated": {"exitCode": exit}}}
            ]}
        }))
        .unwrap()
    }

    #[test]
    fn the_first_matching_rule_decides_as_the_job_controller_does() {
        let p = policy();
        assert_eq!(outcome(Some(&p), &failed(1, json!([]))), Outcome::Count);
        assert_eq!(
            outcome(Some(&p), &failed(3, json!([]))),
            Outcome::FailJob(
                "Container agent-1 for pod ns/p failed with exit code 3 matching FailJob rule at index 1"
                    .into()
            )
        );
        let disrupted = json!([{"type": "DisruptionTarget", "status": "True", "reason": "EvictionByEvictionAPI"}]);
        assert_eq!(
            outcome(Some(&p), &failed(3, disrupted)),
            Outcome::Ignore,
            "rule 0 first"
        );
        let not_true = json!([{"type": "DisruptionTarget", "status": "False"}]);
        assert_eq!(outcome(Some(&p), &failed(1, not_true)), Outcome::Count);
        assert_eq!(outcome(None, &failed(3, json!([]))), Outcome::Count);
    }
}
