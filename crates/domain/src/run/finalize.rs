//! Finalize's rules: the final status and the participant's reason from what the run left,
//! the texts EvalAI gets, and what stands when EvalAI already holds a final word. Finalize
//! reads the facts and acts on these.

use serde_json::Value;

use crate::job::protocol::{Marker, Role};
use crate::run::audit::Recordings;
use crate::status::RecordStatus;
use crate::submission::SubmissionStatus;

/// What the run left, as Finalize read it.
#[derive(Debug, Clone, Copy)]
pub struct Facts<'a> {
    /// The participant cancelled (the run's state or the S3 cancel marker says so).
    pub cancelled: bool,
    /// The error a Catch caught (`Name: message`, [`caught_error`]).
    pub caught: Option<&'a str>,
    /// The run, when Launch started one.
    pub run: Option<Run<'a>>,
}

/// How the Monitor left the run, and what its results are.
#[derive(Debug, Clone, Copy)]
pub struct Run<'a> {
    /// The Monitor saw every pair end well.
    pub finished: bool,
    /// The Monitor's reason when it ended the run otherwise.
    pub reason: Option<&'a str>,
    /// The Monitor ended it for a failure of the platform's own (its reclaims past the free
    /// ones), not the participant's.
    pub by_platform: bool,
    /// Each pair's id and routes.
    pub pairs: &'a [(u32, &'a str)],
    /// The merged results, or why they cannot be used (a problem of the results themselves).
    pub results: Result<Results<'a>, &'a str>,
}

/// The merged results, as far as Finalize needs them.
#[derive(Debug, Clone, Copy)]
pub struct Results<'a> {
    /// Every planned route has its records.
    pub complete: bool,
    /// Records merged and planned.
    pub progress: (u64, u64),
    /// The pairs whose results file is complete.
    pub finished_pairs: &'a [u32],
}

/// The final status, and what the participant reads about it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Outcome {
    /// `finished`, `failed` or `cancelled`.
    pub status: SubmissionStatus,
    /// Why it is not `finished` (with the pairs note, when some routes are kept).
    pub reason: Option<String>,
    /// Which routes were evaluated and kept, when some pairs finished and some did not: it
    /// heads the participant's stdout too.
    pub pairs_note: Option<String>,
    /// A failure of the platform's own: EvalAI is told `failed` all the same (it does not
    /// count against the team's limits, and a resume keeps the routes done), and operators
    /// are shown it apart.
    pub by_platform: bool,
}

/// The final status from what the run left: a cancel wins, then a caught error, then results
/// that cannot be used, then how the Monitor ended the run.
pub fn outcome(facts: &Facts<'_>) -> Outcome {
    let failed = |reason: String| (SubmissionStatus::Failed, Some(reason));
    let mut by_platform = false;
    let (status, reason) = match (facts.cancelled, facts.caught, &facts.run) {
        (true, _, _) => (SubmissionStatus::Cancelled, None),
        (false, Some(caught), _) => failed(participant_reason(caught)),
        (false, None, None) => failed("the evaluation did not start".into()),
        (false, None, Some(run)) => match (&run.results, run.finished) {
            (Err(problem), _) => failed(format!("the results cannot be used: {problem}")),
            (Ok(results), true) if results.complete => (SubmissionStatus::Finished, None),
            (Ok(results), true) => failed(format!(
                "the evaluation ended with {} of {} routes evaluated",
                results.progress.0, results.progress.1
            )),
            (Ok(_), false) => {
                by_platform = run.by_platform;
                failed(run.reason.unwrap_or("the evaluation failed").into())
            }
        },
    };
    // A pair that gave up leaves its routes missing; its neighbours' are complete and kept.
    let pairs_note = match (&facts.run, status) {
        (
            Some(Run {
                results: Ok(results),
                pairs,
                ..
            }),
            SubmissionStatus::Failed,
        ) => pairs_note(pairs, results.finished_pairs),
        _ => None,
    };
    let reason = match (&pairs_note, reason) {
        (Some(note), Some(reason)) => Some(format!("{reason}. {note}")),
        (_, reason) => reason,
    };
    Outcome {
        status,
        reason,
        pairs_note,
        by_platform,
    }
}

/// Why `lbctl rescore --post` must not post, if it must not: a cancelled submission stays
/// cancelled; a submission an execution still holds gets its final status from that
/// execution's Finalize (which never replaces a final status, so one posted first would stand
/// instead of the real one); and only a complete, valid merge is a result worth replacing a
/// final status with. `record_status` is the record's (`None`: absent, or a word we never
/// write); `invalid` is the validation's reason when it set the entry `Invalid`.
pub fn rescore_refusal(
    record_status: Option<RecordStatus>,
    complete: bool,
    progress: (u64, u64),
    invalid: Option<&str>,
) -> Option<String> {
    if record_status == Some(RecordStatus::Cancelled) {
        return Some("it was cancelled: its participant's word is final".into());
    }
    if let Some(record_status) = record_status.filter(|s| s.is_in_flight()) {
        return Some(format!(
            "its record is `{record_status}`: the execution that holds it posts the final status \
             (lbctl cancel it, or wait for it to end)"
        ));
    }
    if !complete {
        return Some(format!(
            "the merge is not complete ({} of {} records): there is no score to post",
            progress.0, progress.1
        ));
    }
    invalid.map(|reason| format!("the merge is complete but invalid: {reason}"))
}

/// The error a Catch put at `$.error`, in words: Lambda's `Cause` is a JSON text holding
/// `errorMessage`.
pub fn caught_error(state: &Value) -> Option<String> {
    state.get("error").map(caught)
}

/// A caught error (`{"Error", "Cause"}`, as a Catch writes it) in words: `Name: message`.
pub fn caught(error: &Value) -> String {
    let name = error
        .get("Error")
        .and_then(Value::as_str)
        .unwrap_or("Error");
    let cause = error
        .get("Cause")
        .and_then(Value::as_str)
        .unwrap_or_default();
    let message = serde_json::from_str::<Value>(cause)
        .ok()
        .and_then(|c| {
            c.get("errorMessage")
                .and_then(Value::as_str)
                .map(str::to_owned)
        })
        .unwrap_or_else(|| cause.to_string());
    if message.is_empty() {
        name.to_string()
    } else {
        format!("{name}: {message}")
    }
}

/// Which routes a failed run evaluated, when some pairs finished and some did not (a pair out
/// of retries, one Job per pair): `None` when none or all finished.
pub fn pairs_note(pairs: &[(u32, &str)], finished: &[u32]) -> Option<String> {
    type Pairs<'a, 'b> = Vec<&'a (u32, &'b str)>;
    let (done, missing): (Pairs, Pairs) = pairs.iter().partition(|(id, _)| finished.contains(id));
    if done.is_empty() || missing.is_empty() {
        return None;
    }
    let describe = |ps: &[&(u32, &str)]| {
        let routes: Vec<&str> = ps.iter().map(|(_, routes)| *routes).collect();
        let ids: Vec<String> = ps.iter().map(|(id, _)| id.to_string()).collect();
        let pairs = if ids.len() == 1 { "pair" } else { "pairs" };
        format!("routes {} ({pairs} {})", routes.join(", "), ids.join(", "))
    };
    Some(format!(
        "{} were not evaluated; {} are complete and kept: resuming this submission evaluates only the missing routes",
        describe(&missing),
        describe(&done)
    ))
}

/// What the participant reads for a caught error (`Name: message`, from [`caught_error`]): a
/// problem with their results in full; anything on our side as a plain sentence with the
/// error's stable name, its chain (ARNs, table names, endpoints) staying in our logs and in the
/// submission's record.
pub fn participant_reason(error: &str) -> String {
    let name = error.split_once(": ").map_or(error, |(name, _)| name);
    // The participant's own results: the message names the file, field or route to fix.
    if crate::results::ResultsError::names().contains(&name) {
        format!("the evaluation failed: {error}")
    } else if let Some((_, cause)) = error
        .split_once(": ")
        .filter(|_| crate::run::reaper::ERROR_NAMES.contains(&name))
    {
        // The reaper's own words about how the execution ended: nothing internal in them.
        format!("{cause}, not because of your agent; the organisers have been alerted")
    } else {
        format!(
            "the evaluation failed because of an error on the evaluation service's side \
             ({name}), not because of your agent; the organisers have been alerted"
        )
    }
}

/// Why this execution must not end the run: another execution holds the claim (a resume
/// superseded this one), or nobody does.
pub fn superseded(holder: Option<&str>, execution: &str) -> Option<String> {
    (holder != Some(execution)).then(|| {
        format!(
            "execution `{}` holds the submission now",
            holder.unwrap_or_default()
        )
    })
}

/// The pair whose agent crashed most (the lowest id among equals), from the markers: its
/// output's end is what the participant reads with a failure.
pub fn most_crashed_agent<'a>(markers: impl IntoIterator<Item = &'a str>) -> Option<u32> {
    let mut crashes: std::collections::BTreeMap<u32, u32> = Default::default();
    for name in markers {
        if let Some(Marker::Crash {
            role: Role::Agent,
            pair,
            ..
        }) = Marker::parse(name)
        {
            *crashes.entry(pair).or_default() += 1;
        }
    }
    crashes
        .iter()
        .max_by_key(|(pair, n)| (**n, std::cmp::Reverse(**pair)))
        .map(|(pair, _)| *pair)
}

/// The participant's stdout: the pairs note, then the qualifier's verdict, then the summary.
pub fn stdout(pairs_note: Option<&str>, verdict: Option<&str>, summary: &str) -> String {
    let mut out = String::new();
    if let Some(note) = pairs_note {
        out.push_str(note);
        out.push_str("\n\n");
    }
    out.push_str(verdict.unwrap_or_default());
    out.push_str(summary);
    out
}

/// The participant's stderr: the reason, then the end of the agent's output that crashed
/// most (`(pair, tail)`), on a failure.
pub fn stderr(
    outcome: &Outcome,
    agent_tail: Option<(u32, &str)>,
    recordings: Option<&Recordings>,
) -> String {
    let mut out = outcome.reason.clone().unwrap_or_default();
    if let (SubmissionStatus::Failed, Some((pair, tail))) = (outcome.status, agent_tail) {
        out.push_str(&format!(
            "\n\nThe last lines of agent {pair}'s output:\n{tail}\n"
        ));
    }
    let unaudited = recordings.filter(|r| !r.complete());
    if let (SubmissionStatus::Finished, Some(audit)) = (outcome.status, unaudited) {
        out.push_str(&format!(
            "The CARLA recordings of {} of the {} scoring routes did not pass the audit, so these \
             scores cannot be checked against what the simulator ran; the organisers may replay \
             or disqualify them:\n",
            audit.expected - audit.passed,
            audit.expected
        ));
        for failure in &audit.failures {
            out.push_str(&format!("- {failure}\n"));
        }
    }
    out
}

/// What EvalAI did with the final update.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Posted {
    /// It holds the status we sent.
    Written,
    /// The participant had cancelled: their word is final.
    Cancelled,
    /// It already held this final status (an earlier attempt posted it before failing).
    AlreadyFinal(SubmissionStatus),
}

/// What EvalAI's status before the final update leaves unwritten: a participant's cancel (their
/// word is final) or a final status already there (an earlier attempt posted it before
/// failing); `None`: the final update is to be written.
pub fn unwritable(current: SubmissionStatus) -> Option<Posted> {
    if current == SubmissionStatus::Cancelled {
        return Some(Posted::Cancelled);
    }
    current.is_final().then_some(Posted::AlreadyFinal(current))
}

/// What stands once EvalAI answered: its final word wins over ours, and a status that is
/// `finished` after all has no failure reason.
pub fn settle(outcome: Outcome, posted: Posted) -> Outcome {
    match posted {
        Posted::Written => outcome,
        Posted::Cancelled => Outcome {
            status: SubmissionStatus::Cancelled,
            reason: None,
            by_platform: false,
            ..outcome
        },
        Posted::AlreadyFinal(stands) if stands == outcome.status => outcome,
        Posted::AlreadyFinal(stands) => Outcome {
            status: stands,
            reason: outcome
                .reason
                .filter(|_| stands != SubmissionStatus::Finished),
            by_platform: outcome.by_platform && stands == SubmissionStatus::Failed,
            ..outcome
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    const PAIRS: [(u32, &str); 4] = [(1, "0-4"), (2, "5-9"), (3, "10-14"), (4, "15-19")];

    fn run<'a>(finished: bool, results: Result<Results<'a>, &'a str>) -> Run<'a> {
        Run {
            finished,
            reason: Some("pair 1 gave up"),
            by_platform: false,
            pairs: &PAIRS,
            results,
        }
    }

    #[test]
    fn only_a_run_the_monitor_ended_for_the_platform_s_failure_is_the_platform_s() {
        let finished = [1, 2, 3];
        let platform = |facts: Facts<'_>| outcome(&facts).by_platform;
        let taken = Run {
            by_platform: true,
            ..run(false, Ok(results(false, &finished)))
        };
        let facts = |cancelled, caught, run| Facts {
            cancelled,
            caught,
            run: Some(run),
        };
        let ended = outcome(&facts(false, None, taken));
        assert_eq!(ended.status, SubmissionStatus::Failed);
        assert!(ended.by_platform);
        // The kept routes are still named.
        assert!(ended.reason.unwrap().contains("pair 1 gave up. "));
        // A cancel, a caught error or results that cannot be used are not the platform's
        // reclaims, whatever the Monitor said.
        assert!(!platform(facts(true, None, taken)));
        assert!(!platform(facts(false, Some("Boom: x"), taken)));
        let unusable = Run {
            results: Err("not JSON"),
            ..taken
        };
        assert!(!platform(facts(false, None, unusable)));
        assert!(!platform(facts(
            false,
            None,
            run(false, Ok(results(false, &finished)))
        )));
        // EvalAI's own final word stands over ours.
        let failed = outcome(&facts(false, None, taken));
        let cancelled = settle(failed.clone(), Posted::Cancelled);
        assert!(!cancelled.by_platform);
        assert!(settle(failed, Posted::AlreadyFinal(SubmissionStatus::Failed)).by_platform);
    }

    fn results(complete: bool, finished_pairs: &[u32]) -> Results<'_> {
        Results {
            complete,
            progress: if complete { (20, 20) } else { (15, 20) },
            finished_pairs,
        }
    }

    #[test]
    fn the_final_status_follows_cancel_then_error_then_results_then_the_monitor() {
        let all = [1, 2, 3, 4];
        let some = [2, 3, 4];
        let cases: [(Facts, SubmissionStatus, Option<&str>); 8] = [
            (
                Facts {
                    cancelled: true,
                    caught: Some("KubeForbidden: x"),
                    run: None,
                },
                SubmissionStatus::Cancelled,
                None,
            ),
            (
                Facts {
                    cancelled: false,
                    caught: Some("States.Timeout"),
                    run: Some(run(true, Ok(results(true, &all)))),
                },
                SubmissionStatus::Failed,
                Some("error on the evaluation service's side (States.Timeout)"),
            ),
            (
                Facts {
                    cancelled: false,
                    caught: None,
                    run: None,
                },
                SubmissionStatus::Failed,
                Some("the evaluation did not start"),
            ),
            (
                Facts {
                    cancelled: false,
                    caught: None,
                    run: Some(run(true, Ok(results(true, &all)))),
                },
                SubmissionStatus::Finished,
                None,
            ),
            (
                Facts {
                    cancelled: false,
                    caught: None,
                    run: Some(run(true, Ok(results(false, &all)))),
                },
                SubmissionStatus::Failed,
                Some("the evaluation ended with 15 of 20 routes evaluated"),
            ),
            (
                Facts {
                    cancelled: false,
                    caught: None,
                    run: Some(run(false, Ok(results(false, &some)))),
                },
                SubmissionStatus::Failed,
                Some("pair 1 gave up. routes 0-4 (pair 1) were not evaluated"),
            ),
            (
                Facts {
                    cancelled: false,
                    caught: None,
                    run: Some(run(false, Err("SensorMismatch: x"))),
                },
                SubmissionStatus::Failed,
                Some("the results cannot be used: SensorMismatch: x"),
            ),
            (
                Facts {
                    cancelled: true,
                    caught: None,
                    run: Some(run(false, Ok(results(false, &some)))),
                },
                SubmissionStatus::Cancelled,
                None,
            ),
        ];
        for (facts, status, reason) in cases {
            let out = outcome(&facts);
            assert_eq!(out.status, status, "{facts:?}");
            match reason {
                None => assert_eq!(out.reason, None, "{facts:?}"),
                Some(reason) => assert!(
                    out.reason.as_deref().unwrap_or_default().contains(reason),
                    "{facts:?}: {:?}",
                    out.reason
                ),
            }
            assert_eq!(
                out.pairs_note.is_some(),
                status == SubmissionStatus::Failed
                    && facts
                        .run
                        .is_some_and(|r| r.results.is_ok_and(|r| r.finished_pairs.len() == 3))
            );
        }
    }

    #[test]
    fn evalai_s_final_word_stands() {
        let failed = Outcome {
            status: SubmissionStatus::Failed,
            reason: Some("why".into()),
            pairs_note: None,
            by_platform: false,
        };
        assert_eq!(settle(failed.clone(), Posted::Written), failed);
        let cancelled = settle(failed.clone(), Posted::Cancelled);
        assert_eq!(
            (cancelled.status, cancelled.reason),
            (SubmissionStatus::Cancelled, None)
        );
        let finished = settle(
            failed.clone(),
            Posted::AlreadyFinal(SubmissionStatus::Finished),
        );
        assert_eq!(
            (finished.status, finished.reason),
            (SubmissionStatus::Finished, None)
        );
        let same = settle(
            failed.clone(),
            Posted::AlreadyFinal(SubmissionStatus::Failed),
        );
        assert_eq!(same, failed);
    }

    #[test]
    fn the_participant_texts_put_the_note_first_and_the_agent_s_words_last() {
        assert_eq!(
            stdout(Some("note"), Some("verdict\n"), "summary"),
            "note\n\nverdict\nsummary"
        );
        assert_eq!(stdout(None, None, "summary"), "summary");
        let failed = Outcome {
            status: SubmissionStatus::Failed,
            reason: Some("why".into()),
            pairs_note: None,
            by_platform: false,
        };
        assert_eq!(
            stderr(&failed, Some((2, "Traceback")), None),
            "why\n\nThe last lines of agent 2's output:\nTraceback\n"
        );
        let finished = Outcome {
            status: SubmissionStatus::Finished,
            reason: None,
            pairs_note: None,
            by_platform: false,
        };
        assert_eq!(stderr(&finished, Some((2, "x")), None), "");
        // A finished result whose recordings fail the audit tells the participant which.
        let mut audit = Recordings {
            passed: 3,
            expected: 4,
            failures: vec!["RouteScenario_1_rep0: 45 bytes for 0.0 s".into()],
        };
        let said = stderr(&finished, None, Some(&audit));
        assert!(
            said.starts_with("The CARLA recordings of 1 of the 4 scoring routes"),
            "{said}"
        );
        assert!(
            said.ends_with("\n- RouteScenario_1_rep0: 45 bytes for 0.0 s\n"),
            "{said}"
        );
        audit.passed = 4;
        assert_eq!(stderr(&finished, None, Some(&audit)), "");
        assert!(!stderr(&failed, None, Some(&Recordings { passed: 0, ..audit })).contains("CARLA"));
    }

    #[test]
    fn the_agent_that_crashed_most_is_shown_the_lowest_among_equals() {
        let markers = [
            "agent-2.crash0",
            "agent-2.crash1",
            "agent-3.crash0",
            "simulator-1.crash0",
            "agent-1.crash0",
            "agent-3.crash1",
        ];
        assert_eq!(most_crashed_agent(markers), Some(2));
        assert_eq!(most_crashed_agent(["agent-1.done"]), None);
    }

    #[test]
    fn only_the_execution_holding_the_claim_ends_the_run() {
        assert_eq!(superseded(Some("a"), "a"), None);
        assert_eq!(
            superseded(Some("b"), "a").unwrap(),
            "execution `b` holds the submission now"
        );
        assert!(superseded(None, "a").is_some());
    }

    #[test]
    fn rescore_posts_only_a_complete_valid_merge_of_a_submission_no_execution_holds() {
        let cases: [(&str, bool, Option<&str>, Option<&str>); 7] = [
            ("FAILED", true, None, None),
            ("FINISHED", true, None, None),
            (
                "RUNNING",
                true,
                None,
                Some("`RUNNING`: the execution that holds it"),
            ),
            ("SUBMITTED", true, None, Some("`SUBMITTED`")),
            ("RESUMING", true, None, Some("`RESUMING`")),
            (
                "FAILED",
                false,
                None,
                Some("not complete (3 of 20 records)"),
            ),
            (
                "FAILED",
                true,
                Some("a route was run twice"),
                Some("invalid: a route was run twice"),
            ),
        ];
        for (status, complete, invalid, refused) in cases {
            let got = rescore_refusal(
                Some(status.parse().unwrap()),
                complete,
                (if complete { 20 } else { 3 }, 20),
                invalid,
            );
            match (refused, got) {
                (None, None) => {}
                (Some(part), Some(text)) => assert!(text.contains(part), "{status}: {text}"),
                (want, got) => {
                    panic!("{status} {complete} {invalid:?}: want {want:?}, got {got:?}")
                }
            }
        }
    }

    #[test]
    fn a_failed_run_names_the_missing_routes_and_the_complete_ones() {
        assert_eq!(
            pairs_note(&PAIRS, &[2, 3, 4]).unwrap(),
            "routes 0-4 (pair 1) were not evaluated; routes 5-9, 10-14, 15-19 (pairs 2, 3, 4) are complete and kept: resuming this submission evaluates only the missing routes"
        );
        assert!(pairs_note(&PAIRS, &[]).is_none());
        assert!(pairs_note(&PAIRS, &[1, 2, 3, 4]).is_none());
        assert!(pairs_note(&PAIRS, &[9]).is_none());
    }

    #[test]
    fn a_caught_lambda_error_reads_as_its_name_and_message() {
        let state = json!({"error": {"Error": "KubeForbidden",
            "Cause": "{\"errorType\":\"KubeForbidden\",\"errorMessage\":\"jobs.batch is forbidden\"}"}});
        assert_eq!(
            caught_error(&state).unwrap(),
            "KubeForbidden: jobs.batch is forbidden"
        );
        let timeout = json!({"error": {"Error": "States.Timeout", "Cause": ""}});
        assert_eq!(caught_error(&timeout).unwrap(), "States.Timeout");
        assert_eq!(caught_error(&json!({})), None);
    }

    #[test]
    fn participants_read_their_results_problems_but_never_our_internals() {
        let ours = "AwsTransient: dynamodb UpdateItem on `leaderboard-20-submissions` \
                    (arn:aws:iam::123456789012:role/leaderboard-FinalizeRole-X): timed out";
        let reason = participant_reason(ours);
        assert!(reason.contains("(AwsTransient)"), "{reason}");
        for secret in ["arn:aws", "leaderboard-20-submissions", "UpdateItem"] {
            assert!(!reason.contains(secret), "{reason}");
        }
        assert_eq!(
            participant_reason("States.Timeout"),
            participant_reason("States.Timeout: ")
        );
        let theirs = "ResultsInvalid: `worker1.json` field `_checkpoint.records[3].scores.score_route` is negative";
        assert_eq!(
            participant_reason(theirs),
            format!("the evaluation failed: {theirs}")
        );
    }
}
