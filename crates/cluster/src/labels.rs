//! The label keys that tie Jobs and Pods to their submission, and the selectors built from them.

use crate::error::{ClusterError, Result};

// NB: the keys are the plan's, the ones the Job templates put on every Job and Pod.
pub use lb_domain::job::plan::{
    EXECUTION_LABEL as EXECUTION, JOB_INDEX_LABEL as JOB_INDEX, LEADERBOARD_LABEL as LEADERBOARD,
    MANAGED_BY as MANAGED_BY_VALUE, MANAGED_BY_LABEL as MANAGED_BY,
    SUBMISSION_LABEL as SUBMISSION_ID, TEAM_ID_LABEL as TEAM_ID,
};

/// Labels the Job controller itself puts on a Job's Pods (the first is the current one).
pub(crate) const JOB_NAME_LABELS: [&str; 2] = ["batch.kubernetes.io/job-name", "job-name"];

/// Checks that `id` can be a label value, so it can go into a selector unescaped.
///
/// EvalAI ids are integers; anything else reaching here came from a malformed message.
pub fn validate_submission_id(id: &str) -> Result<()> {
    let ok = !id.is_empty()
        && id.len() <= 63
        && id
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b"-_.".contains(&b))
        && id.as_bytes()[0].is_ascii_alphanumeric()
        && id.as_bytes()[id.len() - 1].is_ascii_alphanumeric();
    if ok {
        Ok(())
    } else {
        Err(ClusterError::InvalidSubmissionId {
            id: id.chars().take(80).collect(),
        })
    }
}

/// The execution label's value for an execution name (the label-safe form the Job templates
/// put on Jobs and Pods).
pub fn execution_value(execution: &str) -> String {
    lb_domain::job::plan::label_value(execution)
}

/// The execution label of an object's labels, `None` when absent or empty (Jobs launched
/// before the label existed belong to whichever execution holds the submission).
pub fn execution_of(labels: Option<&std::collections::BTreeMap<String, String>>) -> Option<&str> {
    labels
        .and_then(|l| l.get(EXECUTION))
        .map(String::as_str)
        .filter(|e| !e.is_empty())
}

/// Whose of a submission's objects a deletion (and the wait for it) takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Whose<'a> {
    /// Every one of the submission's objects.
    Any,
    /// Those labelled with this execution (its name): all that an execution may stop before it
    /// knows it holds the submission's claim.
    Labelled(&'a str),
    /// Those labelled with this execution and those from before the label, which belong to
    /// whichever execution holds the claim: this one, as its caller checked.
    Claimed(&'a str),
}

impl Whose<'_> {
    /// Whether an object with `labels` is taken.
    pub fn takes(&self, labels: Option<&std::collections::BTreeMap<String, String>>) -> bool {
        self.taker()(labels)
    }

    /// [`Whose::takes`] made once for many objects: the execution's label value is worked out
    /// here, not per object and per look.
    pub fn taker(&self) -> impl Fn(Option<&std::collections::BTreeMap<String, String>>) -> bool {
        let mine = match self {
            Whose::Any => None,
            Whose::Labelled(execution) | Whose::Claimed(execution) => {
                Some(execution_value(execution))
            }
        };
        let unlabelled_too = !matches!(self, Whose::Labelled(_));
        move |labels| match (&mine, execution_of(labels)) {
            (None, _) => true,
            (Some(mine), Some(theirs)) => mine == theirs,
            (Some(_), None) => unlabelled_too,
        }
    }

    /// Whether an object with `labels` is left only because it has no execution label.
    pub fn leaves_unlabelled(
        &self,
        labels: Option<&std::collections::BTreeMap<String, String>>,
    ) -> bool {
        matches!(self, Whose::Labelled(_)) && execution_of(labels).is_none()
    }
}

/// The label selector of one submission's objects (only ours: managed-by must match too).
pub fn submission_selector(id: &str) -> Result<String> {
    validate_submission_id(id)?;
    Ok(format!(
        "{SUBMISSION_ID}={id},{MANAGED_BY}={MANAGED_BY_VALUE}"
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_execution_takes_its_own_and_those_from_before_the_label_only_with_the_claim() {
        let labelled = |e: &str| {
            Some(std::collections::BTreeMap::from([(
                EXECUTION.into(),
                e.into(),
            )]))
        };
        let mine = labelled(&execution_value("arn:exec-1"));
        let (theirs, none) = (labelled("exec-2"), None);
        let labelled = Whose::Labelled("arn:exec-1");
        let claimed = Whose::Claimed("arn:exec-1");
        // Its own, under the label-safe form of its name.
        assert!(labelled.takes(mine.as_ref()) && claimed.takes(mine.as_ref()));
        assert!(!labelled.takes(theirs.as_ref()) && !claimed.takes(theirs.as_ref()));
        assert!(!labelled.takes(none) && claimed.takes(none));
        assert!(labelled.leaves_unlabelled(none) && !claimed.leaves_unlabelled(none));
        assert!(!labelled.leaves_unlabelled(theirs.as_ref()));
        assert!(Whose::Any.takes(theirs.as_ref()) && Whose::Any.takes(none));
    }

    #[test]
    fn the_selector_names_the_submission_and_the_manager() {
        assert_eq!(
            submission_selector("4242").unwrap(),
            "leaderboard.carla.org/submission-id=4242,app.kubernetes.io/managed-by=leaderboard-cloud"
        );
    }

    #[test]
    fn ids_that_could_change_the_selector_are_refused() {
        for bad in [
            "",
            "1,leaderboard.carla.org/team-id=3",
            "1 ",
            "-1",
            "1=2",
            "a/b",
            "é",
            &"9".repeat(64),
        ] {
            let err = submission_selector(bad).unwrap_err();
            assert_eq!(err.name(), "InvalidSubmissionId", "{bad:?}");
        }
    }

    #[test]
    fn label_value_shaped_ids_are_accepted() {
        for good in ["1", "123456", "a.b-c_d", &"9".repeat(63)] {
            validate_submission_id(good).unwrap();
        }
    }
}
