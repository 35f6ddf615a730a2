//! The start estimates the model measures: the forecast from its whole view, from what the
//! admission table holds, and the pace estimate of before.

use std::collections::BTreeMap;

use super::{Mode, Pair, Pod, PodState, Sim};
use crate::capacity::forecast::{self, Outlook};

/// The expected `k`-th shortest (from 0) of `n` draws from the `sorted` sample: its quantile at
/// Blom's plotting position `(k + 1 - 3/8) / (n + 1/4)`.
pub fn expected_order_statistic(sorted: &[u64], k: usize, n: usize) -> u64 {
    if sorted.is_empty() {
        return 0;
    }
    forecast::at_position(sorted, forecast::blom(k, n))
}

/// The expected largest of `n` standard normal draws (Blom's positions, `n` up to 8).
pub fn max_of_normals(n: usize) -> f64 {
    const TABLE: [f64; 9] = [0.0, 0.0, 0.56, 0.85, 1.03, 1.16, 1.27, 1.35, 1.42];
    TABLE[n.min(8)]
}

/// The standard deviation of `sample`.
fn spread_of(sample: &[u64]) -> f64 {
    let n = sample.len().max(1) as f64;
    let mean = sample.iter().sum::<u64>() as f64 / n;
    (sample
        .iter()
        .map(|&x| (x as f64 - mean).powi(2))
        .sum::<f64>()
        / n)
        .sqrt()
}

/// A pair's expected end, `routes` still to run with this `spread` each, pushed out to where
/// the slowest of an evaluation's four such pairs is expected to end.
fn late(expected: Option<&u64>, routes: u64, spread: f64) -> u64 {
    let margin = max_of_normals(4) * spread * (routes as f64).sqrt();
    expected.map_or(0, |&e| e + margin as u64)
}

impl Sim<'_> {
    /// Ours: each queued submission's start estimated at its arrival and again every refresh,
    /// from the queue as the model has it now (what production reads off the admission
    /// table, the runs' progress and the cluster).
    pub(super) fn estimate(&mut self) {
        if self.mode == Mode::Original {
            return;
        }
        let now = self.now;
        let refresh = self.rush.refresh_seconds;
        let due: Vec<usize> = (0..self.subs.len())
            .filter(|&i| {
                let s = &self.subs[i];
                s.arrived
                    && s.started.is_none()
                    && s.estimated_at.is_none_or(|t| now >= t + refresh)
            })
            .collect();
        if due.is_empty() {
            return;
        }
        let outlook = self.outlook();
        for index in due {
            if let Some(after) = forecast::forecast(&outlook, index as u64) {
                let sub = &mut self.subs[index];
                if sub.estimates.is_empty() {
                    sub.capped_at_arrival = !sub.admitted;
                }
                sub.estimates.push(now + after);
            }
            if self.subs[index].paced_at_arrival.is_none() {
                let paced = self.pace_estimate(index).map(|after| now + after);
                self.subs[index].paced_at_arrival = Some(paced);
                let viewed = self.table_estimate(index).map(|after| now + after);
                self.subs[index].viewed_at_arrival = viewed;
            }
            self.subs[index].estimated_at = Some(now);
        }
    }

    /// The forecast from what the admission table holds (`forecast::estimate`): entries, the
    /// running ones' progress, the track's latest evaluations, and the cluster's GPUs as the
    /// sweep counts them each minute (free, booting, addable).
    fn table_estimate(&self, index: usize) -> Option<u64> {
        let free_at = self.capacity().free_at();
        let entries: Vec<_> = (0..self.subs.len())
            .filter(|&i| self.subs[i].arrived && self.subs[i].ended.is_none())
            .map(|i| (self.entry(i), self.progress_of(i)))
            .collect();
        let latest = &self.durations[self
            .durations
            .len()
            .saturating_sub(crate::capacity::queue::RECENT_DURATIONS)..];
        let view = forecast::QueueView {
            entries: &entries,
            durations: latest,
            team_limit: self.rush.team_limit,
            pairs: self.rush.arrivals[index].pairs.len() as u32,
            free_at: &free_at,
            now: self.now,
        };
        forecast::estimate(&view, index as u64).map(|e| e.middle())
    }

    /// The cluster's GPUs as the sweep counts them: free on the nodes taking pods, on nodes
    /// booting, and on the nodes the group's maximum leaves room for.
    fn capacity(&self) -> forecast::Capacity {
        let (now, gpus) = (self.now, self.model.gpus_per_node);
        let live = |n: &&super::Node| n.live(now) && n.notice.is_none();
        let free = (self.nodes.iter().filter(live))
            .filter(|n| n.schedulable(now))
            .map(|n| n.free)
            .sum();
        let booting = self
            .nodes
            .iter()
            .filter(live)
            .filter(|n| now < n.ready)
            .count() as u32;
        let addable = self.model.max_nodes.saturating_sub(self.group_size(None));
        forecast::Capacity {
            free,
            booting: booting * gpus,
            addable: addable * gpus,
        }
    }

    /// Submission `i`'s queue entry.
    fn entry(&self, i: usize) -> crate::capacity::queue::Entry {
        use crate::capacity::queue::EntryState;
        let sub = &self.subs[i];
        let state = match (sub.admitted, sub.started) {
            (false, _) => EntryState::Waiting,
            (true, None) => EntryState::Admitted,
            (true, Some(_)) => EntryState::Running,
        };
        let a = &self.rush.arrivals[i];
        crate::capacity::queue::Entry {
            submission_id: i as u64,
            team_id: a.team,
            arrived_ms: a.at * 1000,
            state,
        }
    }

    /// Submission `i`'s progress as its Monitor records it: routes done of all its pairs.
    fn progress_of(&self, i: usize) -> Option<forecast::Progress> {
        let since = self.subs[i].started?;
        let pairs = &self.rush.arrivals[i].pairs;
        let mut done = 0;
        for pod in self.pods.iter().filter(|p| p.submission == i) {
            for (slot, &pair) in pod.pairs.iter().enumerate() {
                done += match &pod.state {
                    PodState::Running { pairs: running, .. } => match running[slot] {
                        Pair::Route { route, .. } => route,
                        Pair::Done => pairs[pair].len(),
                    },
                    PodState::Done => pairs[pair].len(),
                    _ => pod.resume[slot].min(pairs[pair].len()),
                } as u64;
            }
        }
        let routes = pairs.iter().map(Vec::len).sum::<usize>() as u64;
        Some(forecast::Progress {
            pairs: pairs.len() as u32,
            done,
            routes,
            since,
        })
    }

    /// What the queue note estimates today (`queue::estimate_start`, `estimate_team_turn`):
    /// places ahead at the pace of the track's latest evaluations.
    fn pace_estimate(&self, index: usize) -> Option<u64> {
        let team = self.rush.arrivals[index].team;
        let (mut ahead, mut team_ahead, mut running) = (0, 0, 0);
        for (i, s) in self.subs.iter().enumerate() {
            let waiting = s.arrived && s.started.is_none();
            ahead += u32::from(i < index && waiting);
            team_ahead += u32::from(
                i < index && !s.admitted && s.arrived && self.rush.arrivals[i].team == team,
            );
            running += u32::from(s.started.is_some() && s.ended.is_none());
        }
        let latest: Vec<u64> = self.durations.iter().rev().copied().collect();
        let estimate = if self.subs[index].admitted {
            crate::capacity::queue::estimate_start(ahead, running, &latest)
        } else {
            crate::capacity::queue::estimate_team_turn(team_ahead, self.rush.team_limit, &latest)
        };
        Some(estimate.map_or(0, |e| e.middle()))
    }

    /// The track's latest pairs' seconds, shortest first.
    fn latest_pairs(&self) -> Vec<u64> {
        const LATEST: usize = 1000;
        let mut latest = self.pace[self.pace.len().saturating_sub(LATEST)..].to_vec();
        latest.sort_unstable();
        latest
    }

    /// The queue as a forecast reads it: free and coming GPUs, admitted evaluations with their
    /// pairs' expected ends, the waiting ones.
    fn outlook(&self) -> Outlook {
        let (now, model) = (self.now, self.model);
        let latest = self.latest_pairs();
        let routes = self
            .rush
            .arrivals
            .first()
            .map_or(1, |a| a.pairs.first().map_or(1, Vec::len)) as u64;
        let pace = latest.iter().sum::<u64>() / (latest.len() as u64 * routes).max(1);
        let mut free_at = Vec::new();
        for node in self
            .nodes
            .iter()
            .filter(|n| n.live(now) && n.notice.is_none())
        {
            free_at.extend(std::iter::repeat_n(
                node.ready.saturating_sub(now),
                node.free as usize,
            ));
        }
        let addable = model.max_nodes.saturating_sub(self.group_size(None)) * model.gpus_per_node;
        free_at.extend(std::iter::repeat_n(model.boot_seconds, addable as usize));
        let mut order: Vec<usize> = (0..self.subs.len())
            .filter(|&i| self.subs[i].admitted && self.subs[i].ended.is_none())
            .collect();
        order.sort_by_key(|&i| (self.subs[i].admitted_at, i));
        let position: BTreeMap<usize, usize> =
            order.iter().enumerate().map(|(k, &i)| (i, k)).collect();
        let mut holders: Vec<forecast::Holder> = order
            .iter()
            .map(|&i| forecast::Holder {
                submission: i as u64,
                team: self.rush.arrivals[i].team,
                running: Vec::new(),
                pending: 0,
                until: 0,
            })
            .collect();
        // A route's spread, from the pairs': the slowest of a holder's pairs ends about
        // `max_of_normals(n)` of its spread past the latest expected end.
        let spread = spread_of(&latest) / (routes as f64).sqrt();
        for pod in &self.pods {
            if let Some(&k) = position.get(&pod.submission) {
                self.expected_ends(pod, (pace, spread), &mut holders[k]);
            }
        }
        let waiting = (0..self.subs.len())
            .filter(|&i| self.subs[i].arrived && !self.subs[i].admitted)
            .map(|i| forecast::Waiting {
                submission: i as u64,
                team: self.rush.arrivals[i].team,
            })
            .collect();
        let pairs = self.rush.arrivals.first().map_or(0, |a| a.pairs.len());
        let startup = model.agent_pull_seconds + model.carla_start_seconds;
        Outlook {
            free_at,
            holders,
            waiting,
            team_limit: self.rush.team_limit,
            pair_seconds: (0..pairs)
                .map(|k| expected_order_statistic(&latest, k, pairs) + startup)
                .collect(),
        }
    }

    /// A pod's pairs as a forecast counts them: waiting for a GPU, or running with the seconds
    /// they are expected to take still (their routes left at `pace`).
    fn expected_ends(&self, pod: &Pod, (pace, spread): (u64, f64), holder: &mut forecast::Holder) {
        let now = self.now;
        let routes = &self.rush.arrivals[pod.submission].pairs;
        let left =
            |slot: usize, from: usize| routes[pod.pairs[slot]].len().saturating_sub(from) as u64;
        match &pod.state {
            PodState::Pending { .. } => holder.pending += pod.pairs.len() as u32,
            PodState::Starting { until, .. } => {
                for slot in 0..pod.pairs.len() {
                    let routes = left(slot, pod.resume[slot]);
                    holder
                        .running
                        .push(until.saturating_sub(now) + routes * pace);
                    holder.until = holder
                        .until
                        .max(late(holder.running.last(), routes, spread));
                }
            }
            PodState::Running { pairs, .. } => {
                for (slot, pair) in pairs.iter().enumerate() {
                    if let Pair::Route { route, since } = *pair {
                        // The route in progress takes at least a quarter of the pace more: a
                        // long one runs on (route times have a long tail).
                        let current = pace.saturating_sub(now - since).max(pace / 4);
                        let routes = left(slot, route + 1);
                        holder.running.push(current + routes * pace);
                        holder.until =
                            holder
                                .until
                                .max(late(holder.running.last(), routes + 1, spread));
                    }
                }
            }
            PodState::Done => {}
        }
    }
}
