//! A Monitor round's policy: when an unreachable cluster, a long queue or a long evaluation
//! ends the run and what the participant reads then, when EvalAI's status is read, and when
//! the round's results go out. The Monitor fetches the facts and acts on these.

use std::collections::BTreeMap;
use std::time::Duration;

use crate::capacity::cost::Ledger;
use crate::cluster::disruption::FREE_RECLAIMS_PER_PAIR;
use crate::cluster::view::{JobState, JobView, Spent};
use crate::run::schedule::{JOB_DEADLINE, MAX_EVALUATION, STATUS_FALLBACK};

/// Why the run ends after the cluster's API was out of reach since `since` (epoch seconds):
/// only an outage of `bound_hours` or more does; a shorter one skips the round's verdict while
/// the Jobs run on. `error` is the last error's stable name.
pub fn outage_ends_run(since: u64, now: u64, bound_hours: u64, error: &str) -> Option<String> {
    let outage = now.saturating_sub(since);
    (outage >= bound_hours * 3600).then(|| {
        format!(
            "the evaluation cluster could not be reached for {} minutes ({error})",
            outage / 60
        )
    })
}

/// Why a submission its team's cap held back ends after waiting `waited` seconds for its turn:
/// only a wait of `max_queue_hours` or more does, and it used none of the participant's time.
pub fn queue_limit_ends_wait(waited: u64, max_queue_hours: u64, team_limit: u32) -> Option<String> {
    (waited >= max_queue_hours * 3600).then(|| {
        format!(
            "the evaluation waited {} minutes for its turn, longer than this leaderboard's queue \
             limit of {max_queue_hours} hours (a team holds at most {team_limit} evaluations at \
             once, and your team's were still in progress); it was not started and used none of \
             your time: please submit again later",
            waited / 60
        )
    })
}

/// Why a running evaluation ends: it ran longer than [`MAX_EVALUATION`], counted from its start
/// without the `lost` seconds reclaims cost it (time spent queued or catching up after a
/// reclaimed node is not the participant's).
pub fn overran(started_at: Option<u64>, lost: u64, now: u64) -> Option<String> {
    let hours = MAX_EVALUATION.as_secs() / 3600;
    started_at
        .filter(|&t| now.saturating_sub(t).saturating_sub(lost) > MAX_EVALUATION.as_secs())
        .map(|_| match lost / 60 {
            0 => format!("the evaluation ran longer than the {hours} hours allowed"),
            minutes => format!(
                "the evaluation ran longer than the {hours} hours allowed (not counting the \
                 {minutes} minutes it lost to reclaimed GPU nodes)"
            ),
        })
}

/// The `activeDeadlineSeconds` that ends a Job at once: its `startTime` is older than that, so
/// the Job controller fails it (`DeadlineExceeded`) and stops its pod.
pub const END_NOW: u64 = 1;

/// The Jobs whose `activeDeadlineSeconds` should change, and to what: a pair out of retries
/// (in `spent`) ends now ([`END_NOW`]); every other Job still running keeps [`JOB_DEADLINE`]
/// plus the `lost` seconds (closed stretches) reclaims cost, so the backstop stays as far past
/// the participant's limit as it was.
pub fn deadlines_to_set<'a>(
    jobs: &'a [JobView],
    lost: u64,
    spent: &BTreeMap<String, Spent>,
) -> Vec<(&'a str, u64)> {
    let wanted = JOB_DEADLINE.as_secs().saturating_add(lost);
    jobs.iter()
        .filter(|j| !j.terminating && matches!(j.state, JobState::Pending | JobState::Running))
        .filter_map(|j| match spent.contains_key(&j.name) {
            true => (j.deadline != Some(END_NOW)).then_some((j.name.as_str(), END_NOW)),
            false => j
                .deadline
                .is_some_and(|d| d < wanted)
                .then_some((j.name.as_str(), wanted)),
        })
        .collect()
}

/// The pairs out of retries, by Job name, with why: a Job whose failed pods and the pods the
/// ledger charged to it (disruptions of their own, reclaims beyond the free ones) are more
/// than its `backoffLimit`. Without a charged pod the Job controller decides alone. The why
/// names whose each charge was: a pair the platform alone took away is not the participant's
/// failure, and is told so. `ended_by_platform` holds the Jobs an earlier round found so: the
/// pod our deadline then stopped counts as failed for the Job, not for the participant.
pub fn spent_pairs(
    jobs: &[JobView],
    usage: &Ledger,
    ended_by_platform: &[u32],
) -> BTreeMap<String, Spent> {
    jobs.iter()
        .filter_map(|j| {
            let index = j.index?;
            let charged = usage.charged_to(index);
            let failed = match ended_by_platform.contains(&index) {
                true => 0,
                false => u32::try_from(j.failed).unwrap_or(0),
            };
            let limit = j.backoff_limit?;
            let excess = usage.excess_of(index);
            (charged > 0 && failed.saturating_add(charged) > limit).then(|| {
                let spent = Spent {
                    why: spent_why(charged, excess, failed, limit),
                    by_platform: excess == charged && failed == 0,
                };
                (j.name.clone(), spent)
            })
        })
        .collect()
}

/// Why a pair is out of retries: `charged` pods charged to it, `excess` of them the
/// platform's reclaims beyond the free ones, `failed` failed pods, `limit` retries.
fn spent_why(charged: u32, excess: u32, failed: u32, limit: u32) -> String {
    let own = charged.saturating_sub(excess);
    let mut causes = Vec::new();
    if own > 0 {
        causes.push(format!(
            "{own} of its pods were stopped by a disruption of their own (evicted by the kubelet \
             from a healthy node, for disk, inodes or processes beyond the pod's share)"
        ));
    }
    if excess > 0 {
        causes.push(format!(
            "{excess} of its pods were taken away by the platform (nodes reclaimed or drained) \
             after the {FREE_RECLAIMS_PER_PAIR} reclaims a pair gets free"
        ));
    }
    let mut why = format!(
        "{}; with {failed} failed pod(s) that is more than the {limit} retries allowed",
        causes.join(", and ")
    );
    if own == 0 && failed == 0 {
        why.push_str(
            ": this is the evaluation platform's doing, not your agent's. The submission \
             does not count against your team's limits, and a resume keeps the routes it \
             completed",
        );
    }
    why
}

/// Holds every pod's participant image (its `agent-*` containers') to the first digest seen:
/// records it in `first` when none is, and says why the run ends when a pod ran another. The
/// tag EvalAI gave can be pushed again while the evaluation runs, and a replacement pod (after
/// a crash or a reclaim) or a pair on a new node would pull the new code.
pub fn hold_image(first: &mut Option<String>, jobs: &[JobView]) -> Option<String> {
    let mut pods: Vec<&crate::cluster::view::PodView> = jobs.iter().flat_map(|j| &j.pods).collect();
    pods.sort_by_key(|p| p.start_time);
    let mut seen = pods
        .iter()
        .flat_map(|p| &p.containers)
        .filter(|c| c.name.starts_with("agent-"))
        .filter_map(|c| Some((c.digest.as_deref()?, c.image.as_str())));
    if first.is_none() {
        *first = seen.next().map(|(digest, _)| digest.to_owned());
    }
    let held = first.as_deref()?;
    let (other, image) = seen.find(|(digest, _)| *digest != held)?;
    let short = |d: &str| d.chars().take(19).collect::<String>();
    Some(format!(
        "the evaluation stopped: your image `{image}` was pushed again while it ran (its pods \
         started with {}..., a later one ran {}...). Every pair must run the same code: submit \
         again, with a new tag for new code",
        short(held),
        short(other)
    ))
}

/// Why EvalAI's status is read this round, if it is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StatusRead {
    /// The sweep flagged a cancel: confirmed before any partial update (urgent).
    ConfirmCancel,
    /// The last read is [`STATUS_FALLBACK`] old, in case the sweep is down (routine).
    Fallback,
}

/// Whether this round reads EvalAI's status, and why.
pub fn status_read(cancel_flagged: bool, last_read: Option<u64>, now: u64) -> Option<StatusRead> {
    if cancel_flagged {
        return Some(StatusRead::ConfirmCancel);
    }
    last_read
        .is_none_or(|t| now.saturating_sub(t) >= STATUS_FALLBACK.as_secs())
        .then_some(StatusRead::Fallback)
}

/// When changed results may go to EvalAI: at once, or after `wait` (the last partial update
/// was sent less than `interval` seconds ago; the next wait ends when it may go).
pub fn partial_update_due(
    last_update: Option<u64>,
    now: u64,
    interval: u64,
) -> Result<(), Duration> {
    match last_update.map(|t| now.saturating_sub(t)) {
        Some(since) if since < interval => Err(Duration::from_secs((interval - since).max(1))),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_spent_pair_is_told_whose_each_charge_was() {
        let own = spent_why(5, 0, 0, 4);
        assert!(
            own.starts_with("5 of its pods were stopped by a disruption of their own"),
            "{own}"
        );
        assert!(!own.contains("platform"), "{own}");
        let platform = spent_why(5, 5, 0, 4);
        assert!(
            platform.starts_with("5 of its pods were taken away by the platform")
                && platform.contains("not your agent's"),
            "{platform}"
        );
        let both = spent_why(3, 1, 2, 4);
        assert!(
            both.contains("2 of its pods were stopped by a disruption of their own")
                && both.contains(", and 1 of its pods were taken away by the platform")
                && both.contains("with 2 failed pod(s)")
                && !both.contains("not your agent's"),
            "{both}"
        );
    }

    const HOUR: u64 = 3600;

    #[test]
    fn only_an_outage_as_long_as_the_bound_ends_the_run() {
        for (since, now, ends) in [
            (0, 6 * HOUR - 1, false),
            (0, 6 * HOUR, true),
            (100, 50, false),
        ] {
            let reason = outage_ends_run(since, now, 6, "KubeUnavailable");
            assert_eq!(reason.is_some(), ends, "{since} {now}");
        }
        assert_eq!(
            outage_ends_run(0, 6 * HOUR, 6, "KubeTimeout").unwrap(),
            "the evaluation cluster could not be reached for 360 minutes (KubeTimeout)"
        );
    }

    #[test]
    fn a_wait_for_the_turn_ends_at_the_queue_limit_and_says_no_time_was_used() {
        assert_eq!(queue_limit_ends_wait(24 * HOUR - 1, 24, 2), None);
        let reason = queue_limit_ends_wait(24 * HOUR, 24, 2).unwrap();
        assert!(
            reason.starts_with("the evaluation waited 1440 minutes"),
            "{reason}"
        );
        assert!(reason.contains("at most 2 evaluations"), "{reason}");
        assert!(reason.contains("used none of your time"), "{reason}");
    }

    #[test]
    fn the_evaluation_s_time_counts_from_its_start_not_from_the_queue() {
        let max = MAX_EVALUATION.as_secs();
        assert_eq!(overran(None, 0, 10 * max), None);
        assert_eq!(overran(Some(100), 0, 100 + max), None);
        assert_eq!(
            overran(Some(100), 0, 101 + max).unwrap(),
            "the evaluation ran longer than the 72 hours allowed"
        );
    }

    #[test]
    fn time_lost_to_reclaims_is_not_the_participant_s() {
        let max = MAX_EVALUATION.as_secs();
        assert_eq!(overran(Some(100), 3000, 3100 + max), None);
        assert_eq!(
            overran(Some(100), 3000, 3101 + max).unwrap(),
            "the evaluation ran longer than the 72 hours allowed (not counting the 50 minutes \
             it lost to reclaimed GPU nodes)"
        );
    }

    #[test]
    fn every_pod_runs_the_image_the_first_one_ran() {
        let digest = |c: char| format!("sha256:{}", c.to_string().repeat(64));
        let pod =
            |name: &str, start: i64, agent: Option<String>| -> crate::cluster::view::PodView {
                serde_json::from_value(serde_json::json!({
                    "name": name, "job": "lb-7-0", "phase": "Running", "reason": null,
                    "message": null, "node": "n", "terminating": false, "unschedulable": null,
                    "start_time": jiff::Timestamp::from_second(start).unwrap(),
                    "containers": [
                        {"name": "simulator-1", "image": "carla:0.9.15", "init": false,
                         "state": {"state": "NotCreated"}, "ready": true, "restart_count": 0,
                         "last_exit": null, "digest": digest('c')},
                        {"name": "agent-1", "image": "team/agent:v1", "init": false,
                         "state": {"state": "NotCreated"}, "ready": true, "restart_count": 0,
                         "last_exit": null, "digest": agent},
                    ],
                }))
                .unwrap()
            };
        let jobs = |pods: Vec<crate::cluster::view::PodView>| {
            let mut job = crate::testutil::job("lb-7-0", JobState::Running, None);
            job.pods = pods;
            vec![job]
        };
        // Not pulled yet: nothing held. The first digest seen is held.
        let mut held = None;
        assert_eq!(hold_image(&mut held, &jobs(vec![pod("a", 10, None)])), None);
        assert_eq!(held, None);
        let first = jobs(vec![pod("a", 10, Some(digest('a')))]);
        assert_eq!(hold_image(&mut held, &first), None);
        assert_eq!(held, Some(digest('a')));
        // A replacement pod on the same image: fine; on an image pushed again under the tag:
        // the run ends, naming both.
        let same = jobs(vec![
            pod("a", 10, Some(digest('a'))),
            pod("b", 20, Some(digest('a'))),
        ]);
        assert_eq!(hold_image(&mut held, &same), None);
        let pushed = jobs(vec![pod("b", 20, Some(digest('b')))]);
        let reason = hold_image(&mut held, &pushed).unwrap();
        assert!(
            reason.contains("`team/agent:v1` was pushed again"),
            "{reason}"
        );
        assert!(
            reason.contains("sha256:aaaaaaaaaaaa...") && reason.contains("sha256:bbbbbbbbbbbb..."),
            "{reason}"
        );
        assert_eq!(held, Some(digest('a')), "the first stays held");
    }

    #[test]
    fn running_jobs_deadlines_grow_by_the_lost_time_once() {
        let job = crate::testutil::job;
        let base = JOB_DEADLINE.as_secs();
        let jobs = [
            job("running", JobState::Running, Some(base)),
            job("pending", JobState::Pending, Some(base + 100)),
            job("extended", JobState::Running, Some(base + 600)),
            job("done", JobState::Complete, Some(base)),
            job("none", JobState::Running, None),
        ];
        assert!(deadlines_to_set(&jobs, 0, &BTreeMap::new()).is_empty());
        assert_eq!(
            deadlines_to_set(&jobs, 600, &BTreeMap::new()),
            [("running", base + 600), ("pending", base + 600)]
        );
    }

    #[test]
    fn the_status_is_read_to_confirm_a_cancel_or_when_the_fallback_is_due() {
        let fallback = STATUS_FALLBACK.as_secs();
        for (flagged, last, now, expected) in [
            (true, Some(1000), 1000, Some(StatusRead::ConfirmCancel)),
            (false, None, 1000, Some(StatusRead::Fallback)),
            (false, Some(1000), 1000 + fallback - 1, None),
            (
                false,
                Some(1000),
                1000 + fallback,
                Some(StatusRead::Fallback),
            ),
        ] {
            assert_eq!(
                status_read(flagged, last, now),
                expected,
                "{flagged} {last:?} {now}"
            );
        }
    }

    #[test]
    fn changed_results_wait_out_the_interval_since_the_last_update() {
        assert_eq!(partial_update_due(None, 100, 20), Ok(()));
        assert_eq!(partial_update_due(Some(80), 100, 20), Ok(()));
        assert_eq!(
            partial_update_due(Some(95), 100, 20),
            Err(Duration::from_secs(15))
        );
        assert_eq!(
            partial_update_due(Some(100), 100, 20),
            Err(Duration::from_secs(20))
        );
    }
}
