//! When a queued submission starts, read off the queue as it is: its GPUs, the pairs running
//! on them, the team cap and the submissions ahead, played forward at the track's pace.
//!
//! A count of places ahead divided by a pace (`queue::estimate_start`) misses in a rush: a
//! place turns over when its evaluation's last pair ends, teams at their cap let later
//! submissions past, and nodes still booting or not yet started add GPUs later. Playing the
//! queue forward pair by pair, with every pair not yet started taking the track's expected
//! length, keeps all of that; what it cannot know is how long each future route takes, which
//! averages out over the many pairs ahead of a long wait.

use std::cmp::Reverse;
use std::collections::{BTreeMap, BinaryHeap, VecDeque};

/// An admitted evaluation: its team, the pairs running (expected seconds until each ends) and
/// the pairs whose pods wait for a GPU.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Holder {
    /// EvalAI submission id.
    pub submission: u64,
    /// Its team.
    pub team: u64,
    /// Each running pair's expected seconds to its end.
    pub running: Vec<u64>,
    /// Pairs not started: pods waiting for a GPU, served oldest holder first.
    pub pending: u32,
    /// Expected seconds until its slowest running pair ends: past the latest of `running`,
    /// since the slowest of several uncertain ends comes later than the latest expected one.
    pub until: u64,
}

/// A submission its team's cap holds back.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Waiting {
    /// EvalAI submission id.
    pub submission: u64,
    /// Its team.
    pub team: u64,
}

/// A new GPU node's launch to its GPUs usable, seconds: what the forecast waits for a node
/// booting or one the autoscaler may still add (the fleet model's `boot_seconds`).
pub const NODE_START_SECONDS: u64 = 150;

/// A leaderboard's cluster as the sweep counts it each minute (the admission table's `fleet`
/// item): GPUs no pod holds on the nodes that take pods, GPUs of nodes still starting, and
/// GPUs of the nodes its GPU node groups may still add.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Capacity {
    /// Free now.
    pub free: u32,
    /// On nodes launched and not ready.
    pub booting: u32,
    /// On nodes the node groups' maxima leave room for.
    pub addable: u32,
}

impl Capacity {
    /// Seconds from now until each GPU is usable, as [`QueueView::free_at`] takes them: the
    /// free ones now, the others once a node starts (a booting one sooner at worst).
    pub fn free_at(&self) -> Vec<u64> {
        let later = self.booting.saturating_add(self.addable);
        let mut out = vec![0; self.free as usize];
        out.extend(std::iter::repeat_n(NODE_START_SECONDS, later as usize));
        out
    }
}

/// The queue as it is now.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Outlook {
    /// Seconds from now at which each GPU no pair holds is usable: 0 for a free one, a booting
    /// node's when it is ready, and the nodes the autoscaler may still add at a node's start.
    pub free_at: Vec<u64>,
    /// Admitted evaluations, in admission order (their pods' order in the scheduler's queue).
    pub holders: Vec<Holder>,
    /// Submissions held by their team's cap, in arrival order.
    pub waiting: Vec<Waiting>,
    /// The evaluations a team holds at once.
    pub team_limit: u32,
    /// The expected seconds of a new evaluation's pairs from taking their GPUs to their ends
    /// (images, CARLA's start, routes), shortest first: one per pair. Not all alike: the
    /// evaluation (and its team's place) lasts until its slowest pair ends.
    pub pair_seconds: Vec<u64>,
}

/// One admitted evaluation while the queue is played forward.
struct Held {
    submission: u64,
    team: u64,
    /// Pairs running or waiting: it ends (its place frees) when the last of them ends.
    outstanding: u32,
    /// Its pairs started so far while played forward.
    started: usize,
    /// Not over before this, whatever its pairs' GPUs do.
    until: u64,
}

/// The queue played forward: GPUs freeing, pods waiting for them, teams' places.
struct Play<'a> {
    outlook: &'a Outlook,
    held: Vec<Held>,
    /// When a GPU frees, and the evaluation whose pair held it.
    frees: BinaryHeap<Reverse<(u64, Option<usize>)>>,
    /// When an evaluation whose pairs all ended gives its team's place back.
    releases: BinaryHeap<Reverse<(u64, usize)>>,
    pods: VecDeque<usize>,
    idle: u32,
    waiting: VecDeque<Waiting>,
    team_held: BTreeMap<u64, u32>,
}

impl Play<'_> {
    /// Admits `w` at `now`: its pods join the scheduler's queue.
    fn admit(&mut self, w: Waiting) {
        let index = self.held.len();
        self.held.push(Held {
            submission: w.submission,
            team: w.team,
            outstanding: self.outlook.pair_seconds.len() as u32,
            started: 0,
            until: 0,
        });
        *self.team_held.entry(w.team).or_default() += 1;
        let pairs = self.outlook.pair_seconds.len();
        self.pods.extend(std::iter::repeat_n(index, pairs));
    }

    /// Admits the oldest waiting submissions whose teams are under their cap.
    fn admit_waiting(&mut self) {
        let limit = self.outlook.team_limit;
        let mut kept = VecDeque::new();
        while let Some(w) = self.waiting.pop_front() {
            if self.team_held.get(&w.team).copied().unwrap_or(0) < limit {
                self.admit(w);
            } else {
                kept.push_back(w);
            }
        }
        self.waiting = kept;
    }

    /// Gives back the place of the evaluation `held[index]`'s team: the team's oldest waiting
    /// submission is admitted.
    fn release(&mut self, index: usize) {
        let team = self.held[index].team;
        *self.team_held.entry(team).or_default() -= 1;
        self.admit_waiting();
    }

    /// Starts waiting pods on idle GPUs at `now`; the time `target` first starts, if it does.
    fn start_pods(&mut self, now: u64, target: u64) -> Option<u64> {
        while self.idle > 0 {
            let Some(index) = self.pods.pop_front() else {
                break;
            };
            self.idle -= 1;
            let held = &mut self.held[index];
            if held.submission == target {
                return Some(now);
            }
            // Its pairs take the lengths in turn; one resumed past them (a pair of a holder
            // already running) takes the longest.
            let lengths = &self.outlook.pair_seconds;
            let length = lengths.get(held.started).or(lengths.last()).copied();
            held.started += 1;
            let end = now + length.unwrap_or(0);
            self.frees.push(Reverse((end, Some(index))));
        }
        None
    }
}

/// Seconds from now until `submission`'s first pair starts, the queue played forward; `None`
/// when it is not in the queue or never gets a GPU (no GPU can come).
pub fn forecast(outlook: &Outlook, submission: u64) -> Option<u64> {
    let mut play = Play {
        outlook,
        held: Vec::new(),
        frees: outlook
            .free_at
            .iter()
            .map(|&at| Reverse((at, None)))
            .collect(),
        releases: BinaryHeap::new(),
        pods: VecDeque::new(),
        idle: 0,
        waiting: outlook.waiting.iter().copied().collect(),
        team_held: BTreeMap::new(),
    };
    for h in &outlook.holders {
        let index = play.held.len();
        play.held.push(Held {
            submission: h.submission,
            team: h.team,
            outstanding: h.running.len() as u32 + h.pending,
            started: h.running.len(),
            until: h.until,
        });
        *play.team_held.entry(h.team).or_default() += 1;
        for &end in &h.running {
            play.frees.push(Reverse((end, Some(index))));
        }
        play.pods
            .extend(std::iter::repeat_n(index, h.pending as usize));
    }
    play.admit_waiting();
    loop {
        let gpu = play.frees.peek().map(|Reverse((at, _))| *at);
        let place = play.releases.peek().map(|Reverse((at, _))| *at);
        match (gpu, place) {
            (_, Some(at)) if gpu.is_none_or(|g| at <= g) => {
                if let Some(Reverse((_, index))) = play.releases.pop() {
                    play.release(index);
                }
            }
            (Some(_), _) => {
                let Some(Reverse((now, from))) = play.frees.pop() else {
                    break;
                };
                if let Some(index) = from {
                    let held = &mut play.held[index];
                    held.outstanding -= 1;
                    if held.outstanding == 0 {
                        play.releases.push(Reverse((now.max(held.until), index)));
                    }
                }
                play.idle += 1;
            }
            (None, _) => break,
        }
        let now = gpu.into_iter().chain(place).min().unwrap_or(0);
        if let Some(at) = play.start_pods(now, submission) {
            return Some(at);
        }
    }
    None
}

/// A running evaluation's progress, as its Monitor records it on its queue entry.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Progress {
    /// Its simulator-agent pairs.
    pub pairs: u32,
    /// Routes done.
    pub done: u64,
    /// Routes planned.
    pub routes: u64,
    /// When its first pair started, epoch seconds.
    pub since: u64,
}

/// What a forecast from the admission table reads: the entries (in arrival order) with the
/// progress of those running, the track's latest evaluations, and the evaluation asked about.
#[derive(Debug, Clone, Copy)]
pub struct QueueView<'a> {
    /// Every entry of the queue, arrival order, with the progress of the running ones.
    pub entries: &'a [(super::queue::Entry, Option<Progress>)],
    /// The track's latest evaluations, seconds each (first pair's start to the end).
    pub durations: &'a [u64],
    /// `team_limit`.
    pub team_limit: u32,
    /// Pairs of an evaluation not started (the track's `workers`).
    pub pairs: u32,
    /// GPUs no pair holds, seconds from now until each is usable (none known: empty).
    pub free_at: &'a [u64],
    /// Epoch seconds.
    pub now: u64,
}

/// The expected seconds of a new evaluation's `pairs` pairs, shortest first, from the lengths
/// of whole evaluations (each its slowest pair's): if a pair's length has distribution `F`,
/// an evaluation's has `F^pairs`, so the `k`-th of `pairs` (Blom's position `q`) sits at the
/// evaluations' quantile `q^pairs`.
pub fn pair_lengths(durations: &[u64], pairs: u32) -> Vec<u64> {
    let mut sorted = durations.to_vec();
    sorted.sort_unstable();
    if sorted.is_empty() {
        return Vec::new();
    }
    let n = pairs.max(1) as usize;
    (0..n)
        .map(|k| at_position(&sorted, blom(k, n).powi(n as i32)))
        .collect()
}

/// Blom's plotting position of the `k`-th smallest (from 0) of `n` draws:
/// `(k + 1 - 3/8) / (n + 1/4)`, where its expected value sits in the distribution.
pub fn blom(k: usize, n: usize) -> f64 {
    (k as f64 + 0.625) / (n as f64 + 0.25)
}

/// The value of non-empty `sorted` at `position` (0 to 1) of its distribution.
pub fn at_position(sorted: &[u64], position: f64) -> u64 {
    let rank = (position * sorted.len() as f64).floor() as usize;
    sorted[rank.min(sorted.len() - 1)]
}

/// The queue as `view` reads it, every length scaled by `scale` (the track's quick or slow
/// pace); `None` without a duration to go by.
pub fn outlook(view: &QueueView, scale: f64) -> Option<Outlook> {
    use super::queue::EntryState;
    let pairs = view.pairs;
    let lengths = pair_lengths(view.durations, pairs);
    let slowest = *lengths.last()? as f64 * scale;
    let mut holders = Vec::new();
    let mut waiting = Vec::new();
    for (entry, progress) in view.entries {
        let (submission, team) = (entry.submission_id, entry.team_id);
        match (entry.state, progress) {
            (EntryState::Waiting, _) => waiting.push(Waiting { submission, team }),
            (EntryState::Admitted, _) => holders.push(Holder {
                submission,
                team,
                running: Vec::new(),
                pending: pairs,
                until: 0,
            }),
            (EntryState::Running, progress) => {
                let (n, left) = progress.map_or((pairs, 1.0), |p| {
                    let left = p.routes.saturating_sub(p.done) as f64 / p.routes.max(1) as f64;
                    (p.pairs.max(1), left)
                });
                let elapsed = progress.map_or(0, |p| view.now.saturating_sub(p.since)) as f64;
                // Each pair what its share of the routes left takes at the pace, and never
                // less than what a pair of its rank has still to run at this age.
                let rest = |length: f64| (left * length).max(length - elapsed).max(0.0) as u64;
                let ranks = pair_lengths(view.durations, n);
                let running: Vec<u64> = ranks.iter().map(|&l| rest(l as f64 * scale)).collect();
                let until = rest(slowest);
                holders.push(Holder {
                    submission,
                    team,
                    running,
                    pending: 0,
                    until,
                });
            }
        }
    }
    Some(Outlook {
        free_at: view.free_at.to_vec(),
        holders,
        waiting,
        team_limit: view.team_limit,
        pair_seconds: lengths.iter().map(|&l| (l as f64 * scale) as u64).collect(),
    })
}

/// When `me` may start, seconds from now: the queue played forward at the track's quick and
/// slow pace (its evaluations' lower and upper quartile against their median); `None` without
/// a duration to go by or with `me` not in the queue.
pub fn estimate(view: &QueueView, me: u64) -> Option<super::queue::StartEstimate> {
    let mut sorted = view.durations.to_vec();
    sorted.sort_unstable();
    let quantile = |q: usize| {
        sorted
            .get(sorted.len().saturating_sub(1) * q / 4)
            .map(|&d| d as f64)
    };
    let median = quantile(2)?.max(1.0);
    let at = |scale: f64| forecast(&outlook(view, scale)?, me);
    let (low, high) = (at(quantile(1)? / median)?, at(quantile(3)? / median)?);
    Some(super::queue::StartEstimate {
        low: low.min(high),
        high: low.max(high),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capacity::queue::{Entry, EntryState};

    fn holder(submission: u64, team: u64, running: &[u64], pending: u32) -> Holder {
        Holder {
            submission,
            team,
            running: running.to_vec(),
            pending,
            until: 0,
        }
    }

    fn outlook(free_at: &[u64], holders: Vec<Holder>, waiting: &[(u64, u64)]) -> Outlook {
        Outlook {
            free_at: free_at.to_vec(),
            holders,
            waiting: waiting
                .iter()
                .map(|&(submission, team)| Waiting { submission, team })
                .collect(),
            team_limit: 2,
            pair_seconds: vec![100, 100],
        }
    }

    #[test]
    fn an_admitted_submission_takes_the_first_gpu_its_elders_leave() {
        // Two GPUs busy until 30 and 50; submission 2's pods are behind submission 1's two.
        let o = outlook(
            &[],
            vec![holder(1, 1, &[30, 50], 2), holder(2, 2, &[], 2)],
            &[],
        );
        // Submission 1 holds both GPUs at first... its own pairs end at 30 and 50, then its
        // pending pairs take them, so 2 waits for the first of those to end: 30 + 100.
        assert_eq!(forecast(&o, 2), Some(130));
        assert_eq!(forecast(&o, 1), Some(30));
    }

    #[test]
    fn a_free_gpu_or_a_booting_node_starts_it_then() {
        let o = outlook(&[0], vec![holder(1, 1, &[], 2)], &[]);
        assert_eq!(forecast(&o, 1), Some(0));
        let o = outlook(
            &[180, 180],
            vec![holder(1, 1, &[500], 0), holder(2, 2, &[], 2)],
            &[],
        );
        assert_eq!(forecast(&o, 2), Some(180));
    }

    #[test]
    fn the_team_cap_holds_a_submission_until_its_teams_evaluation_ends() {
        // Team 1 holds two evaluations, ending at 300 (pairs at 200 and 300) and 400; its
        // third waits for the first of them to end, though GPUs are free earlier.
        let o = outlook(
            &[0, 0],
            vec![holder(1, 1, &[200, 300], 0), holder(2, 1, &[400, 400], 0)],
            &[(3, 1)],
        );
        assert_eq!(forecast(&o, 3), Some(300));
    }

    #[test]
    fn a_later_submission_of_another_team_passes_one_held_by_its_cap() {
        let o = outlook(
            &[0, 0],
            vec![holder(1, 1, &[900], 0), holder(2, 1, &[900], 0)],
            &[(3, 1), (4, 2)],
        );
        assert_eq!(forecast(&o, 4), Some(0));
        assert_eq!(forecast(&o, 3), Some(900));
    }

    #[test]
    fn pairs_are_read_off_whole_evaluations_each_as_long_as_its_slowest_pair() {
        let durations: Vec<u64> = (1..=100).collect();
        // Four pairs: the evaluations' quantiles at Blom's positions to the fourth power.
        assert_eq!(pair_lengths(&durations, 4), [1, 3, 15, 53]);
        assert_eq!(pair_lengths(&durations, 1), [51]);
        assert!(pair_lengths(&[], 4).is_empty());
    }

    fn entry(submission_id: u64, team_id: u64, state: EntryState) -> Entry {
        Entry {
            submission_id,
            team_id,
            arrived_ms: submission_id,
            state,
        }
    }

    #[test]
    fn the_table_s_view_plays_running_runs_out_by_their_progress() {
        // Evaluations of 100 to 200 minutes; one pair each. Team 1 runs two, one nearly done
        // (9 of 10 routes after 100 minutes) and one just started; its third waits for the
        // first to end: about a tenth of a run from now, well before the other.
        let minute = 60;
        let durations: Vec<u64> = (100..=200).map(|m| m * minute).collect();
        let now = 1_000_000;
        let progress = |done, age| Progress {
            pairs: 1,
            done,
            routes: 10,
            since: now - age,
        };
        let entries = vec![
            (
                entry(1, 1, EntryState::Running),
                Some(progress(9, 100 * minute)),
            ),
            (entry(2, 1, EntryState::Running), Some(progress(0, 0))),
            (entry(3, 1, EntryState::Waiting), None),
        ];
        let view = QueueView {
            entries: &entries,
            durations: &durations,
            team_limit: 2,
            pairs: 1,
            free_at: &[0, 0],
            now,
        };
        let estimate = estimate(&view, 3).unwrap();
        assert!(estimate.low <= estimate.high);
        assert!(
            (10 * minute..=60 * minute).contains(&estimate.middle()),
            "{estimate:?}"
        );
        // Without durations there is nothing to go by.
        assert_eq!(
            estimate_of(
                &QueueView {
                    durations: &[],
                    ..view
                },
                3
            ),
            None
        );
    }

    fn estimate_of(view: &QueueView, me: u64) -> Option<u64> {
        estimate(view, me).map(|e| e.middle())
    }

    #[test]
    fn a_submission_not_in_the_queue_or_without_gpus_has_no_forecast() {
        let o = outlook(&[], vec![holder(1, 1, &[], 2)], &[]);
        assert_eq!(forecast(&o, 1), None);
        assert_eq!(forecast(&outlook(&[0], vec![], &[]), 7), None);
    }
}
