//! Intake's rules: which submissions start, what the participant reads when one is refused,
//! and how many simulator-agent pairs it gets. Intake fetches the facts and acts on these.

use crate::status::RecordStatus;
use crate::submission::SubmissionStatus;

/// Why a submission with this EvalAI status is not ours to start, if it is not.
pub fn skip_reason(status: SubmissionStatus) -> Option<String> {
    (!status.starts_evaluation()).then(|| {
        format!("EvalAI status is `{status}`; only submitted or resuming submissions start")
    })
}

/// What the participant reads when no image could be found for the submission.
pub fn no_image(problem: &str) -> String {
    format!(
        "the submission has no docker image URI ({problem}); push the image again with `evalai push`"
    )
}

/// The most of an unusable image reference quoted back to the participant.
const QUOTED_IMAGE_CHARS: usize = 120;

/// What the participant reads when the image reference cannot be pulled by any cluster
/// (`problem` is the parser's word): quoted, escaped and cut, since the text is theirs.
pub fn invalid_image(image: &str, problem: &str) -> String {
    let shown: String = image.chars().take(QUOTED_IMAGE_CHARS).collect();
    let cut = if shown.len() < image.len() { "..." } else { "" };
    format!(
        "the docker image URI `{}{cut}` is not a valid image reference: {problem}; push the \
         image again with `evalai push`",
        shown.escape_debug()
    )
}

/// What the participant reads when the registry has no image of the reference's tag (never
/// pushed, or deleted since).
pub fn image_not_found(image: &str) -> String {
    format!(
        "the docker image `{}` is not in its registry; push it again with `evalai push` and \
         submit again",
        image.escape_debug()
    )
}

/// What the participant reads when their team has not passed the qualifier the track needs.
pub fn not_qualified(team: &str, qualifier: &str, track: &str) -> String {
    format!("team `{team}` has not passed the qualifier track `{qualifier}` yet, which `{track}` requires")
}

/// The pairs a submission runs on: an operator's override wins over the track's default, and
/// there are never more pairs than routes, nor fewer than one.
pub fn worker_count(overridden: Option<u32>, track_default: u32, routes: u32) -> u32 {
    overridden.unwrap_or(track_default).min(routes).max(1)
}

/// Why a second delivery of a claimed submission is skipped.
pub fn duplicate(claimed_by: Option<&str>, status: Option<RecordStatus>) -> String {
    format!(
        "already claimed by `{}` (record status `{}`): a duplicate delivery",
        claimed_by.unwrap_or_default(),
        status.map_or("", RecordStatus::as_str)
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_submitted_and_resuming_submissions_start() {
        for (status, starts) in [
            (SubmissionStatus::Submitted, true),
            (SubmissionStatus::Resuming, true),
            (SubmissionStatus::Running, false),
            (SubmissionStatus::Cancelled, false),
            (SubmissionStatus::Finished, false),
            (SubmissionStatus::Failed, false),
        ] {
            let reason = skip_reason(status);
            assert_eq!(reason.is_none(), starts, "{status}");
            if let Some(reason) = reason {
                assert!(reason.contains(&format!("`{status}`")), "{reason}");
            }
        }
    }

    #[test]
    fn the_worker_count_is_the_override_or_the_default_bounded_by_the_routes() {
        for (overridden, default, routes, expected) in [
            (None, 4, 20, 4),
            (Some(8), 4, 20, 8),
            (Some(8), 4, 5, 5),
            (None, 4, 2, 2),
            (Some(0), 4, 20, 1),
            (None, 0, 20, 1),
        ] {
            assert_eq!(
                worker_count(overridden, default, routes),
                expected,
                "{overridden:?} {default} {routes}"
            );
        }
    }

    #[test]
    fn an_unusable_image_is_quoted_escaped_and_cut() {
        let long = "a".repeat(500);
        let message = invalid_image(&long, "too long");
        assert!(
            message.contains(&format!("`{}...`", "a".repeat(120))),
            "{message}"
        );
        let message = invalid_image("bad\nimage", "a newline");
        assert!(message.contains("`bad\\nimage`"), "{message}");
        assert!(message.ends_with("push the image again with `evalai push`"));
    }

    #[test]
    fn refusals_name_what_to_do() {
        assert!(no_image("404").contains("push the image again"));
        assert_eq!(
            not_qualified("Team", "SENSORS_QUALIFIER", "SENSORS"),
            "team `Team` has not passed the qualifier track `SENSORS_QUALIFIER` yet, which `SENSORS` requires"
        );
        assert!(duplicate(Some("exec-1"), None).starts_with("already claimed by `exec-1`"));
    }
}
