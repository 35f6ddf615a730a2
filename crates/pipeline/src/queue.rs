//! A submission's turn in its leaderboard's queue, as Launch and the Monitor ask for it: put it
//! in the queue (once), admit it when its team has room and it is the team's oldest waiting,
//! and count who is ahead (`lb_domain::capacity::queue` for the rules, `lb_aws::admission` for the table).

use std::time::Duration;

use lb_aws::admission::{AdmissionTable, Admit};
use lb_aws::tasks::{Callbacks, Reported};
use lb_aws::wake::WakeTable;
use lb_domain::capacity::forecast;
pub use lb_domain::capacity::queue::Standing;
pub use lb_domain::capacity::queue::TeamQueue;
use lb_domain::capacity::queue::{self, Entry, EntryState, Hold, Place};

use lb_domain::run::metrics::Metric;

use crate::payload::SubmissionInfo;
use crate::Result;

/// The least interval between two rewrites of a participant's queue note on EvalAI (a GET
/// and a PATCH each, routine for the shared budget): places change often in a busy queue.
pub const QUEUE_NOTE_INTERVAL: Duration = Duration::from_secs(300);

/// The leaderboards' queues, chosen once at start (`LB_ADMISSION_TABLE`): the admission
/// table, or none at all, which an operator asks for by name (`unlimited`: a tool run by
/// hand). The stages ask the same questions of either; without a queue every submission has
/// its turn at once, nobody is ahead, and there is nothing to hold, release or wake.
#[derive(Debug, Clone)]
pub enum Admission {
    /// The admission table.
    Queue(AdmissionTable),
    /// No queue.
    Unlimited,
}

impl Admission {
    /// The places held in `queue`, per team (none without a queue).
    pub async fn holds(&self, queue: &str) -> Result<Vec<(u64, Vec<String>)>> {
        match self {
            Admission::Queue(table) => Ok(table.holds(queue).await?),
            Admission::Unlimited => Ok(Vec::new()),
        }
    }

    /// The execution that put `submission_id` in `queue`, when its entry names one.
    pub async fn execution_of(&self, queue: &str, submission_id: u64) -> Result<Option<String>> {
        match self {
            Admission::Queue(table) => Ok(table.execution_of(queue, submission_id).await?),
            Admission::Unlimited => Ok(None),
        }
    }

    /// Gives `submission_id`'s place in `team`'s queue back, takes its entry out, and wakes
    /// the team's next waiting submissions, one per open place. The queue is read beside the
    /// release, with this submission's place counted as given back, and the wakes go once
    /// both are done, so a woken submission finds the place open. The release's failure is
    /// the call's; the wake-up is best effort (said, and the polls come). `false`: no queue.
    pub async fn leave<C: Callbacks>(
        &self,
        team: TeamQueue<'_>,
        submission_id: u64,
        waker: Waker<'_, C>,
    ) -> Result<bool> {
        let Admission::Queue(table) = self else {
            return Ok(false);
        };
        let (released, next) = tokio::join!(
            table.release(team.queue, submission_id, team.team),
            team_next(table, team, Some(submission_id)),
        );
        released?;
        let woken = match next {
            Ok(next) => wake_each(&next, waker).await,
            Err(e) => Err(e),
        };
        match woken {
            Ok(woken) => tracing::info!(submission_id, ?woken, "the team's next submissions"),
            Err(e) => tracing::warn!(
                submission_id,
                error = %e,
                "cannot wake the team's next; its poll comes"
            ),
        }
        Ok(true)
    }

    /// [`take_turn`]; without a queue, admitted with nobody ahead.
    pub async fn take_turn(
        &self,
        submission: &SubmissionInfo,
        arrived_ms: u64,
        limit: u32,
    ) -> Result<Standing> {
        match self {
            Admission::Queue(table) => take_turn(table, submission, arrived_ms, limit).await,
            Admission::Unlimited => Ok(Standing {
                admitted: true,
                ahead: 0,
                team_ahead: 0,
                hold: Hold::Capacity,
            }),
        }
    }

    /// [`ahead_of`]; without a queue, no entry.
    pub async fn ahead_of(&self, submission: &SubmissionInfo) -> Result<Option<(u32, u32)>> {
        match self {
            Admission::Queue(table) => ahead_of(table, submission).await,
            Admission::Unlimited => Ok(None),
        }
    }

    /// [`note`]; without a queue, the place alone (no pace to estimate from).
    pub async fn note(
        &self,
        submission: &SubmissionInfo,
        (place, hold): (Place, Hold),
        now: u64,
    ) -> String {
        match self {
            Admission::Queue(table) => note(table, submission, (place, hold), now).await,
            Admission::Unlimited => queue::describe(place.ahead, hold),
        }
    }

    /// The entry names `execution` (a continuation's first round).
    pub async fn adopt(&self, submission: &SubmissionInfo, execution: &str) -> Result<()> {
        if let Admission::Queue(table) = self {
            let (leaderboard, id) = (submission.leaderboard.as_str(), submission.submission_id);
            table.adopt(leaderboard, id, execution).await?;
        }
        Ok(())
    }

    /// Out of the count of those waiting (its first pair started).
    pub async fn mark_running(&self, submission: &SubmissionInfo, now: u64) -> Result<()> {
        if let Admission::Queue(table) = self {
            let (leaderboard, id) = (submission.leaderboard.as_str(), submission.submission_id);
            table.mark_running(leaderboard, id, now).await?;
        }
        Ok(())
    }

    /// Its progress on its entry, for the forecasts of those waiting: routes `done` of
    /// `routes` over its pairs.
    pub async fn record_progress(
        &self,
        submission: &SubmissionInfo,
        progress: (u64, u64),
    ) -> Result<()> {
        if let Admission::Queue(table) = self {
            let (leaderboard, id) = (submission.leaderboard.as_str(), submission.submission_id);
            table
                .record_progress(leaderboard, id, submission.workers, progress)
                .await?;
        }
        Ok(())
    }

    /// The latest durations of `submission`'s track, most recent first (none without a
    /// queue).
    pub async fn pace(&self, submission: &SubmissionInfo) -> Result<Vec<u64>> {
        match self {
            Admission::Queue(table) => {
                let (leaderboard, track) = (submission.leaderboard.as_str(), &submission.track);
                Ok(table.pace(leaderboard, track).await?)
            }
            Admission::Unlimited => Ok(Vec::new()),
        }
    }

    /// Keeps `durations` as `submission`'s track's pace ([`Admission::pace`] with its duration
    /// joined).
    pub async fn keep_pace(&self, submission: &SubmissionInfo, durations: &[u64]) -> Result<()> {
        if let Admission::Queue(table) = self {
            let (leaderboard, track) = (submission.leaderboard.as_str(), &submission.track);
            table.keep_pace(leaderboard, track, durations).await?;
        }
        Ok(())
    }
}

/// Puts `submission` in the queue if it is not there (arrived at `arrived_ms`), and admits it
/// when its team holds fewer than `limit` and fewer older submissions of its team wait than
/// places are open.
pub async fn take_turn(
    table: &AdmissionTable,
    submission: &SubmissionInfo,
    arrived_ms: u64,
    limit: u32,
) -> Result<Standing> {
    let me = table
        .enqueue(
            submission.leaderboard.as_str(),
            &Entry {
                submission_id: submission.submission_id,
                team_id: submission.team_id,
                arrived_ms,
                state: EntryState::Waiting,
            },
            &submission.execution,
        )
        .await?;
    let entries = table.entries(submission.leaderboard.as_str()).await?;
    waiting(&entries);
    // The entry as the queue shows it now (an admission since `enqueue` read it).
    let me = entries
        .iter()
        .find(|e| e.submission_id == me.submission_id)
        .cloned()
        .unwrap_or(me);
    let admitted = me.state != EntryState::Waiting || {
        // The holders are read after the queue, and the conditional write has the last word
        // on the cap. With no place open the team's oldest still asks: `admit` then drops
        // holds whose entries are gone.
        let held = table
            .holders(submission.leaderboard.as_str(), submission.team_id)
            .await?
            .len();
        queue::team_turn(&entries, &me, queue::free_places(limit, held).max(1))
            && table
                .admit(submission.leaderboard.as_str(), &me, limit)
                .await?
                == Admit::Admitted
    };
    Ok(Standing {
        admitted,
        ahead: queue::ahead(&entries, &me),
        team_ahead: queue::team_ahead(&entries, &me),
        hold: if admitted {
            Hold::Capacity
        } else {
            Hold::TeamLimit { limit }
        },
    })
}

/// The queue's length as this read found it, for the invocation's metrics: the entries not
/// running yet (held by their team's cap, or admitted and waiting for GPUs).
fn waiting(entries: &[Entry]) {
    let length = entries
        .iter()
        .filter(|e| e.state != EntryState::Running)
        .count();
    crate::metrics::sample(Metric::QueueLength, length as f64);
}

/// How many are ahead of an admitted submission whose pods wait (its entry as the queue shows
/// it; `None` when it has none: a run from before the queue), and how many run.
pub async fn ahead_of(
    table: &AdmissionTable,
    submission: &SubmissionInfo,
) -> Result<Option<(u32, u32)>> {
    let entries = table.entries(submission.leaderboard.as_str()).await?;
    waiting(&entries);
    let running = entries
        .iter()
        .filter(|e| e.state == EntryState::Running)
        .count() as u32;
    Ok(entries
        .iter()
        .find(|e| e.submission_id == submission.submission_id)
        .map(|me| (queue::ahead(&entries, me), running)))
}

/// The queue note's words for a submission `ahead` of which wait (`team_ahead` of its own
/// team), while `running` run: the place, what holds it, and its estimated start at `now`
/// (epoch seconds): the queue played forward from its entries, the running ones' progress,
/// the track's pace and the cluster's GPUs as the sweep counted them
/// (`lb_domain::capacity::forecast`), or, when that cannot say, places ahead at the track's
/// pace. None when neither can be read: the note goes without it.
pub async fn note(
    table: &AdmissionTable,
    submission: &SubmissionInfo,
    (place, hold): (Place, Hold),
    now: u64,
) -> String {
    let Place {
        ahead,
        team_ahead,
        running,
    } = place;
    let leaderboard = submission.leaderboard.as_str();
    let (pace, entries, fleet) = tokio::join!(
        table.pace(leaderboard, &submission.track),
        table.entries_with_progress(leaderboard),
        table.fleet(leaderboard),
    );
    let free_at = counted_gpus(fleet, now).map_or_else(Vec::new, |c| c.free_at());
    let (pace, entries) = match (pace, entries) {
        (Ok(pace), Ok(entries)) => (pace, entries),
        (Err(e), _) | (_, Err(e)) => {
            tracing::warn!(submission_id = submission.submission_id, error = %e, "queue or pace not read: no estimate in the note");
            (Vec::new(), Vec::new())
        }
    };
    let view = forecast::QueueView {
        entries: &entries,
        durations: &pace,
        // Admitted, its pods are queued: later admissions, whatever the cap, queue behind.
        team_limit: match hold {
            Hold::TeamLimit { limit } => limit,
            Hold::Capacity => u32::MAX,
        },
        pairs: submission.workers,
        free_at: &free_at,
        now,
    };
    let estimate = forecast::estimate(&view, submission.submission_id).or(match hold {
        Hold::TeamLimit { limit } => queue::estimate_team_turn(team_ahead, limit, &pace),
        Hold::Capacity => queue::estimate_start(ahead, running, &pace),
    });
    let place = queue::describe(ahead, hold);
    match estimate {
        Some(estimate) => format!("{place}; {}", queue::describe_estimate(estimate)),
        None => place,
    }
}

/// How old the sweep's count of the cluster may be and still be believed: a few of its
/// minutes. Older (the sweep failing), the forecast waits for the running pairs alone.
const FLEET_COUNT_FRESH_SECONDS: u64 = 300;

/// The cluster's GPUs as the sweep counted them, when it did within
/// [`FLEET_COUNT_FRESH_SECONDS`] of `now`.
fn counted_gpus(
    fleet: lb_aws::Result<Option<(forecast::Capacity, u64)>>,
    now: u64,
) -> Option<forecast::Capacity> {
    match fleet {
        Ok(Some((capacity, at))) if now.saturating_sub(at) <= FLEET_COUNT_FRESH_SECONDS => {
            Some(capacity)
        }
        Ok(_) => None,
        Err(e) => {
            tracing::warn!(error = %e, "the sweep's GPU count not read: the estimate waits for running pairs");
            None
        }
    }
}

/// What [`wake_team_next`] did for one of the team's waiting submissions.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Woken {
    /// It is not waiting on a token now (in a round, or not yet parked): it asks for its turn
    /// at its round anyway.
    NotWaiting(u64),
    /// Its execution was woken.
    Delivered(u64),
    /// Its wait had already ended.
    Stale(u64),
}

/// Who wakes a waiting submission and how: the wake table, where its token is reported, and
/// the time of the wake.
#[derive(Debug)]
pub struct Waker<'a, C> {
    /// The wake table.
    pub wakes: &'a WakeTable,
    /// Where a waiting execution's token is reported.
    pub callbacks: &'a C,
    /// Epoch seconds.
    pub now: u64,
}

impl<C> Clone for Waker<'_, C> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<C> Copy for Waker<'_, C> {}

/// Wakes the executions of `team`'s oldest waiting submissions in its queue, one per place
/// open under its limit (none when nobody waits or no place is open), so their
/// Monitor rounds ask now instead of at their next poll (five minutes into a queue, half an
/// hour into a long one), through the same [`WakeTable::wake`] the wake function uses. A
/// failed report stops there with the error: the rest ask at their polls.
pub async fn wake_team_next<C: Callbacks>(
    table: &AdmissionTable,
    team: TeamQueue<'_>,
    waker: Waker<'_, C>,
) -> Result<Vec<Woken>> {
    let next = team_next(table, team, None).await?;
    wake_each(&next, waker).await
}

/// The submissions of `team` to wake, oldest first, one per open place: the queue and the
/// team's holders read at once, `leaving`'s place counted as given back (its release runs
/// beside the reads).
async fn team_next(
    table: &AdmissionTable,
    team: TeamQueue<'_>,
    leaving: Option<u64>,
) -> Result<Vec<u64>> {
    let (entries, held) = tokio::join!(
        table.entries(team.queue),
        table.holders(team.queue, team.team)
    );
    let (entries, mut held) = (entries?, held?);
    if let Some(leaving) = leaving {
        held.retain(|holder| *holder != leaving.to_string());
    }
    let free = queue::free_places(team.limit, held.len());
    let next = queue::next_of_team(&entries, team.team, free);
    Ok(next.iter().map(|entry| entry.submission_id).collect())
}

/// Reports each of `next`'s wakes, in order; the first failure stops there.
async fn wake_each<C: Callbacks>(next: &[u64], waker: Waker<'_, C>) -> Result<Vec<Woken>> {
    let mut woken = Vec::new();
    for &id in next {
        woken.push(
            match waker.wakes.wake(id, waker.now, waker.callbacks).await? {
                None => Woken::NotWaiting(id),
                Some(Reported::Delivered) => Woken::Delivered(id),
                Some(Reported::Stale) => Woken::Stale(id),
            },
        );
    }
    Ok(woken)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sweep_s_count_is_believed_for_a_few_minutes_and_never_when_unread() {
        let counted = forecast::Capacity {
            free: 2,
            booting: 4,
            addable: 8,
        };
        let at = 10_000;
        let fresh = counted_gpus(Ok(Some((counted, at))), at + FLEET_COUNT_FRESH_SECONDS);
        assert_eq!(fresh, Some(counted));
        let stale = counted_gpus(Ok(Some((counted, at))), at + FLEET_COUNT_FRESH_SECONDS + 1);
        assert_eq!(stale, None);
        assert_eq!(counted_gpus(Ok(None), at), None);
        let unread = lb_aws::AwsError::Malformed {
            what: "fleet".into(),
            problem: "unread".into(),
        };
        assert_eq!(counted_gpus(Err(unread), at), None);
        // Free GPUs now, the others once a node starts.
        let free_at = counted.free_at();
        assert_eq!(free_at.len(), 14);
        assert_eq!(free_at.iter().filter(|&&s| s == 0).count(), 2);
    }
}
