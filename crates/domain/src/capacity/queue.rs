//! The evaluation queue of a leaderboard: who is admitted next and how many are ahead.
//!
//! A submission is *admitted* when its Jobs may be created; from then on the Kubernetes
//! scheduler places its pods (oldest first) and the autoscaler adds nodes for them. Our part is
//! only the team cap: a team holds at most `team_limit` admitted evaluations, and its further
//! submissions wait, oldest first, without holding back other teams'. The cap itself is
//! enforced by a conditional write (`lb_aws::admission`); this module decides the order and
//! counts the places.

crate::status::words! {
    /// Where an entry of the queue stands, as the admission table stores it.
    #[derive(PartialOrd, Ord)]
    EntryState, "queue entry state" {
        /// Held by its team's cap: no Jobs yet.
        Waiting => "waiting",
        /// Jobs created; its pods wait for a GPU.
        Admitted => "admitted",
        /// Its first pair started.
        Running => "running",
    }
}

/// One submission in the queue.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Entry {
    /// EvalAI submission id.
    pub submission_id: u64,
    /// Its participant team.
    pub team_id: u64,
    /// When it arrived (epoch milliseconds): the queue's order.
    pub arrived_ms: u64,
    /// Where it stands.
    pub state: EntryState,
}

impl Entry {
    /// The queue's order: arrival, then id (two arrivals in one millisecond).
    fn before(&self, other: &Entry) -> bool {
        (self.arrived_ms, self.submission_id) < (other.arrived_ms, other.submission_id)
    }
}

/// A team in one leaderboard's queue, with the number of evaluations it may hold at once.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TeamQueue<'a> {
    /// The queue: the leaderboard's short name.
    pub queue: &'a str,
    /// The team's EvalAI id.
    pub team: u64,
    /// Its `team_limit`.
    pub limit: u32,
}

/// When a submission arrived for its place in the queue, epoch milliseconds: when EvalAI
/// received it, never later than `now` (epoch seconds; a clock ahead is not believed), and
/// `now` when EvalAI did not say (a resume arrives anew).
pub fn arrival_ms(received_ms: Option<u64>, now: u64) -> u64 {
    received_ms.map_or(now * 1000, |ms| ms.min(now * 1000))
}

/// Whether `me` may take one of its team's `free` places: fewer of its team's submissions that
/// arrived earlier still wait than there are free places. A team's places go in its own
/// arrival order, and every free place is offered at once: the oldest `free` waiting
/// teammates may all take theirs, in whatever order their rounds come. (The cap is the
/// conditional write's to enforce; this keeps a team's own order.)
pub fn team_turn(entries: &[Entry], me: &Entry, free: u32) -> bool {
    let older = entries
        .iter()
        .filter(|e| {
            e.team_id == me.team_id
                && e.submission_id != me.submission_id
                && e.state == EntryState::Waiting
                && e.before(me)
        })
        .count();
    older < free as usize
}

/// The team's `free` oldest waiting submissions: those whose turn it is when `free` places of
/// `team_id` are open.
pub fn next_of_team(entries: &[Entry], team_id: u64, free: u32) -> Vec<&Entry> {
    let mut waiting: Vec<&Entry> = entries
        .iter()
        .filter(|e| e.team_id == team_id && e.state == EntryState::Waiting)
        .collect();
    waiting.sort_by_key(|e| (e.arrived_ms, e.submission_id));
    waiting.truncate(free as usize);
    waiting
}

/// How many of a team's `limit` places are open while it holds `held`.
pub fn free_places(limit: u32, held: usize) -> u32 {
    limit.saturating_sub(u32::try_from(held).unwrap_or(u32::MAX))
}

/// The submissions that arrived before `me` and have not started: those that start first,
/// whatever holds `me` back. It only ever shrinks while `me` waits (a later arrival is never
/// counted, and a submission that started or ended leaves the count for good).
pub fn ahead(entries: &[Entry], me: &Entry) -> u32 {
    entries
        .iter()
        .filter(|e| e.state != EntryState::Running && e.before(me))
        .count() as u32
}

/// The submissions of `me`'s team that arrived before it and still wait for a place: those its
/// team's places go to first.
pub fn team_ahead(entries: &[Entry], me: &Entry) -> u32 {
    entries
        .iter()
        .filter(|e| e.team_id == me.team_id && e.state == EntryState::Waiting && e.before(me))
        .count() as u32
}

/// The count a participant is shown, `now` counted and `shown` shown before: never more than
/// before. Places only move up in arrival order, but the count is read at different moments
/// (waiting for the team's turn, then for a GPU) and an entry whose execution ended lingers
/// until the reaper's pass; a participant who saw 3 must not see 4 next.
pub fn shown_ahead(shown: Option<u32>, now: u32) -> u32 {
    shown.map_or(now, |before| before.min(now))
}

/// Whether the participant's note is rewritten now: the place `ahead` (`None`: the note goes,
/// the run started) differs from the one `shown` at `shown_at`, and a changed place was last
/// shown `interval` seconds ago or more (places move often in a busy queue); removing the note
/// waits for nothing.
pub fn note_due(
    (shown, shown_at): (Option<u32>, Option<u64>),
    ahead: Option<u32>,
    now: u64,
    interval: u64,
) -> bool {
    ahead != shown
        && (ahead.is_none() || shown_at.is_none_or(|t| now.saturating_sub(t) >= interval))
}

/// What holds a queued submission back, for its participant and the operator.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Hold {
    /// Its team already holds `limit` evaluations.
    TeamLimit {
        /// The leaderboard's cap.
        limit: u32,
    },
    /// Admitted: its pods wait for a free GPU.
    Capacity,
}

/// The participant's line: "3 submissions ahead of yours; ...".
pub fn describe(ahead: u32, hold: Hold) -> String {
    let queue = match ahead {
        0 => "no submission is ahead of yours".to_string(),
        1 => "1 submission is ahead of yours".to_string(),
        n => format!("{n} submissions are ahead of yours"),
    };
    let why = match hold {
        Hold::TeamLimit { limit } => format!(
            "it starts when one of your team's {limit} evaluations in progress ends (at most {limit} at once per team)"
        ),
        Hold::Capacity => "it starts when a GPU is free on the cluster".to_string(),
    };
    format!("{queue}; {why}")
}

/// Evaluations whose durations an estimate reads, most recent first: enough to follow a
/// track's pace, few enough to follow it when it changes.
pub const RECENT_DURATIONS: usize = 20;

/// A track's pace once an evaluation that ran `seconds` joins it: that one first, then the
/// most recent of `recent` (most recent first), [`RECENT_DURATIONS`] in all.
pub fn with_latest(recent: &[u64], seconds: u64) -> Vec<u64> {
    let kept = recent.iter().take(RECENT_DURATIONS - 1).copied();
    std::iter::once(seconds).chain(kept).collect()
}

/// When a queued submission may start, seconds from now: a range, never a promise.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StartEstimate {
    /// The earliest it likely starts.
    pub low: u64,
    /// The latest it likely starts.
    pub high: u64,
}

impl StartEstimate {
    /// The middle of the range: what the estimate's error is measured from.
    pub fn middle(&self) -> u64 {
        (self.low + self.high) / 2
    }

    /// The range as it is shown: whole minutes up to an hour and a half, whole hours beyond
    /// (the low end rounded down, the high end up).
    pub fn shown(&self) -> Shown {
        let minutes = |s: u64| s.div_ceil(60).max(1);
        let (low, high) = (minutes(self.low), minutes(self.high));
        if high <= 90 {
            Shown::Minutes(low.min(high), high)
        } else {
            Shown::Hours(low / 60, high.div_ceil(60))
        }
    }
}

/// A [`StartEstimate`] rounded for people: (low, high).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Shown {
    /// In minutes.
    Minutes(u64, u64),
    /// In hours.
    Hours(u64, u64),
}

/// The estimated start of a submission with `ahead` submissions before it, while `running`
/// evaluations hold the places it waits for, from the `recent` durations (seconds) of its
/// track's evaluations. Each running evaluation frees its place once per evaluation, so places
/// free at `running` per duration: it starts after `ahead + 1` have freed, between
/// `ahead` of them at the track's quick pace (the lower quartile) and `ahead + 1` at its slow
/// one (the upper quartile). `None` without a duration to go by or with nothing running (an
/// idle cluster starts it as soon as a node is up).
pub fn estimate_start(ahead: u32, running: u32, recent: &[u64]) -> Option<StartEstimate> {
    if recent.is_empty() || running == 0 {
        return None;
    }
    let mut sorted: Vec<u64> = recent.iter().take(RECENT_DURATIONS).copied().collect();
    sorted.sort_unstable();
    let quartile = |q: usize| sorted[(sorted.len() - 1) * q / 4];
    let (quick, slow) = (quartile(1), quartile(3));
    let running = u64::from(running);
    Some(StartEstimate {
        low: u64::from(ahead) * quick / running,
        high: (u64::from(ahead) + 1) * slow / running,
    })
}

/// The estimated start of a submission its team's cap holds back: its team's `limit` places
/// free at the track's pace, and its team's `team_ahead` older waiting submissions take them
/// first ([`estimate_start`] over the team's places).
pub fn estimate_team_turn(team_ahead: u32, limit: u32, recent: &[u64]) -> Option<StartEstimate> {
    estimate_start(team_ahead, limit, recent)
}

/// The estimate in the participant's words: "about 40 minutes", "between 1 and 3 hours".
pub fn describe_estimate(estimate: StartEstimate) -> String {
    let span = match estimate.shown() {
        Shown::Minutes(low, high) if high - low <= high / 4 => format!("about {high} minutes"),
        Shown::Minutes(low, high) => format!("between {low} and {high} minutes"),
        Shown::Hours(0, high) => format!("within {high} hours"),
        Shown::Hours(low, high) if high - low <= high / 4 => format!("about {high} hours"),
        Shown::Hours(low, high) => format!("between {low} and {high} hours"),
    };
    format!("it should start {span} from now (an estimate from this track's recent evaluations)")
}

/// A waiting submission's place, as its note tells it: those ahead of it, its own team's among
/// them, and (admitted, waiting for a GPU) the evaluations running.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Place {
    /// Submissions ahead of it.
    pub ahead: u32,
    /// Its team's submissions ahead of it.
    pub team_ahead: u32,
    /// Evaluations running now (0 when it waits on its team's limit).
    pub running: u32,
}

/// Where a submission stands after asking for its turn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Standing {
    /// It may have its Jobs created.
    pub admitted: bool,
    /// Submissions that arrived before it and have not started.
    pub ahead: u32,
    /// Its team's submissions that arrived before it and wait for a place.
    pub team_ahead: u32,
    /// What holds it back.
    pub hold: Hold,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_changed_place_is_shown_at_most_every_interval_and_a_removal_at_once() {
        let shown = (Some(3), Some(1000));
        assert!(!note_due(shown, Some(3), 9000, 300), "unchanged");
        assert!(!note_due(shown, Some(2), 1299, 300));
        assert!(note_due(shown, Some(2), 1300, 300));
        assert!(
            note_due(shown, None, 1001, 300),
            "it runs: the note goes at once"
        );
        assert!(note_due((None, None), Some(5), 0, 300), "never shown");
        assert!(!note_due((None, None), None, 0, 300), "nothing to remove");
    }

    #[test]
    fn the_start_estimate_reads_the_track_s_pace_over_the_places_running() {
        let hour = 3600;
        // Durations of one to two hours, four places turning over.
        let recent: Vec<u64> = (0..8).map(|i| hour + i * hour / 7).collect();
        let first = estimate_start(0, 4, &recent).unwrap();
        assert_eq!(first.low, 0, "next in line may start at once");
        assert!(first.high <= hour / 2, "{first:?}");
        let tenth = estimate_start(9, 4, &recent).unwrap();
        assert!(tenth.low >= 2 * hour && tenth.high <= 5 * hour, "{tenth:?}");
        assert!(tenth.low < tenth.middle() && tenth.middle() < tenth.high);
        assert_eq!(estimate_start(3, 0, &recent), None, "nothing to go by");
        assert_eq!(estimate_start(3, 4, &[]), None);
        // Only the most recent count.
        let mut changed = vec![600; RECENT_DURATIONS];
        changed.extend([100 * hour; 10]);
        assert!(estimate_start(1, 1, &changed).unwrap().high < hour);
    }

    #[test]
    fn a_submission_its_team_holds_back_waits_for_its_team_s_places() {
        let entries = [
            entry(1, 7, 100, EntryState::Running),
            entry(2, 7, 150, EntryState::Running),
            entry(3, 8, 200, EntryState::Waiting),
            entry(4, 7, 300, EntryState::Waiting),
            entry(5, 7, 400, EntryState::Waiting),
        ];
        assert_eq!(
            team_ahead(&entries, &entries[4]),
            1,
            "its teammate 4, not team 8's"
        );
        assert_eq!(team_ahead(&entries, &entries[3]), 0);
        let recent = [3600; 4];
        let turn = estimate_team_turn(1, 2, &recent).unwrap();
        assert_eq!((turn.low, turn.high), (1800, 3600));
    }

    #[test]
    fn the_estimate_reads_as_a_range_or_about_never_a_promise() {
        let words = |low, high| describe_estimate(StartEstimate { low, high });
        assert!(
            words(0, 1500).contains("between 1 and 25 minutes"),
            "{}",
            words(0, 1500)
        );
        assert!(
            words(2300, 2400).contains("about 40 minutes"),
            "{}",
            words(2300, 2400)
        );
        assert!(words(3 * 3600, 5 * 3600).contains("between 3 and 5 hours"));
        assert!(words(600, 3 * 3600).contains("within 3 hours"));
        assert!(words(0, 60).contains("estimate"));
    }

    #[test]
    fn the_count_shown_never_goes_up() {
        assert_eq!(shown_ahead(None, 4), 4);
        assert_eq!(shown_ahead(Some(3), 4), 3);
        assert_eq!(shown_ahead(Some(3), 1), 1);
        assert_eq!(shown_ahead(Some(0), 2), 0);
    }

    #[test]
    fn a_place_is_when_evalai_received_it_never_later_than_now() {
        for (received, now, expected) in [
            (Some(5_000), 10, 5_000),
            (Some(50_000), 10, 10_000),
            (None, 10, 10_000),
        ] {
            assert_eq!(arrival_ms(received, now), expected, "{received:?} {now}");
        }
    }

    fn entry(submission_id: u64, team_id: u64, arrived_ms: u64, state: EntryState) -> Entry {
        Entry {
            submission_id,
            team_id,
            arrived_ms,
            state,
        }
    }

    #[test]
    fn a_team_waits_its_own_turn_but_never_another_teams() {
        let entries = [
            entry(1, 7, 100, EntryState::Running),
            entry(2, 7, 200, EntryState::Waiting),
            entry(3, 7, 300, EntryState::Waiting),
            entry(4, 8, 400, EntryState::Waiting),
        ];
        assert!(team_turn(&entries, &entries[1], 1));
        // Team 7's third waits for its second while one place is open...
        assert!(!team_turn(&entries, &entries[2], 1));
        // ...but both go at once when two are, whichever round comes first.
        assert!(team_turn(&entries, &entries[2], 2));
        assert!(team_turn(&entries, &entries[1], 2));
        // No open place: nobody's turn.
        assert!(!team_turn(&entries, &entries[1], 0));
        // Team 8 is not held back by team 7's waiting submissions.
        assert!(team_turn(&entries, &entries[3], 1));
        let ids = |team, free| -> Vec<u64> {
            next_of_team(&entries, team, free)
                .iter()
                .map(|e| e.submission_id)
                .collect()
        };
        // Places of team 7 freed are its oldest waiting ones' turn; team 9 has nobody waiting.
        assert_eq!(ids(7, 1), [2]);
        assert_eq!(ids(7, 2), [2, 3]);
        assert_eq!(ids(7, 5), [2, 3]);
        assert_eq!(ids(7, 0), Vec::<u64>::new());
        assert_eq!(ids(8, 1), [4]);
        assert_eq!(ids(9, 1), Vec::<u64>::new());
    }

    #[test]
    fn free_places_never_go_below_zero() {
        assert_eq!(free_places(2, 0), 2);
        assert_eq!(free_places(2, 1), 1);
        // More holders than the cap (the cap lowered while they ran): none free.
        assert_eq!(free_places(2, 3), 0);
    }

    #[test]
    fn ahead_counts_earlier_arrivals_not_started_and_never_later_ones() {
        let mut entries = vec![
            entry(10, 1, 100, EntryState::Running),
            entry(11, 2, 200, EntryState::Admitted),
            entry(12, 3, 200, EntryState::Waiting),
            entry(13, 4, 300, EntryState::Waiting),
        ];
        let me = entries[3].clone();
        assert_eq!(ahead(&entries, &me), 2);
        // Same millisecond: the id decides, so two entries never count each other.
        assert_eq!(ahead(&entries, &entries[2].clone()), 1);
        assert_eq!(ahead(&entries, &entries[1].clone()), 0);
        // A later arrival never moves anyone back; a start moves everyone after it forward.
        entries.push(entry(14, 1, 50_000, EntryState::Waiting));
        assert_eq!(ahead(&entries, &me), 2);
        entries[1].state = EntryState::Running;
        assert_eq!(ahead(&entries, &me), 1);
        entries.remove(2);
        assert_eq!(ahead(&entries, &me), 0);
    }

    #[test]
    fn the_participants_line_says_how_many_and_why() {
        assert_eq!(
            describe(3, Hold::Capacity),
            "3 submissions are ahead of yours; it starts when a GPU is free on the cluster"
        );
        assert!(describe(1, Hold::TeamLimit { limit: 2 })
            .starts_with("1 submission is ahead of yours; it starts when one of your team's 2"));
        assert!(describe(0, Hold::Capacity).starts_with("no submission is ahead"));
    }

    #[test]
    fn states_round_trip_and_strangers_are_refused() {
        for state in [
            EntryState::Waiting,
            EntryState::Admitted,
            EntryState::Running,
        ] {
            assert_eq!(state.as_str().parse::<EntryState>().ok(), Some(state));
        }
        assert!("Running".parse::<EntryState>().is_err());
    }

    #[test]
    fn a_finished_evaluation_leads_its_track_s_pace_and_the_oldest_goes() {
        assert_eq!(with_latest(&[], 7), [7]);
        assert_eq!(with_latest(&[5, 4], 7), [7, 5, 4]);
        let full: Vec<u64> = (0..RECENT_DURATIONS as u64 + 3).collect();
        let paced = with_latest(&full, 99);
        assert_eq!(paced.len(), RECENT_DURATIONS);
        assert_eq!((paced[0], paced[1]), (99, 0));
        assert_eq!(paced.last(), Some(&(RECENT_DURATIONS as u64 - 2)));
    }
}
