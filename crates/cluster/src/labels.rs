//! The label keys that tie Jobs and Pods to their submission, and the selectors built from them.

use crate::error::{ClusterError, Result};

/// Every Job and Pod of a submission: its EvalAI submission id.
pub const SUBMISSION_ID: &str = "leaderboard.carla.org/submission-id";
/// The Job's 0-based index within the submission.
pub const JOB_INDEX: &str = "leaderboard.carla.org/job-index";
/// The EvalAI participant team id.
pub const TEAM_ID: &str = "leaderboard.carla.org/team-id";
/// `1.0` or `2.0`.
pub const LEADERBOARD: &str = "leaderboard.carla.org/leaderboard";
/// Who manages the object.
pub const MANAGED_BY: &str = "app.kubernetes.io/managed-by";
/// Value of [`MANAGED_BY`] on everything this project creates.
pub const MANAGED_BY_VALUE: &str = "leaderboard-cloud";

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
