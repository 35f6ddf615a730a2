//! What a submission's evaluation cost: GPU-seconds from its pods' lifetimes, on Spot or
//! on-demand capacity, the part spent again on routes a reclaim interrupted, an estimate in
//! dollars from the settings' price table, and the orchestration's own share beside it.
//!
//! The Monitor keeps a [`Ledger`] in the run's state: every round it charges each pod it sees
//! from where the last round left it to its end (or to now), so a pod the control plane deletes
//! between two rounds (an evicted one goes once its Job counted it) is not lost.

use std::collections::{BTreeMap, BTreeSet};

use serde::{Deserialize, Serialize};

use crate::cluster::disruption::{self, Disruption, FREE_RECLAIMS_PER_PAIR, MAX_TIME_OFF};
use crate::cluster::view::{ContainerState, JobView};
use crate::status::PodPhase;

/// The capacity a pod's node was, from its `eks.amazonaws.com/capacityType` label.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CapacityType {
    /// `SPOT`.
    Spot,
    /// `ON_DEMAND`.
    OnDemand,
    /// No label (a node outside a managed node group, or one gone before it was read): priced
    /// as on-demand.
    Unknown,
}

impl CapacityType {
    /// From the node label's value.
    pub fn from_label(value: Option<&str>) -> CapacityType {
        match value {
            Some("SPOT") => CapacityType::Spot,
            Some("ON_DEMAND") => CapacityType::OnDemand,
            _ => CapacityType::Unknown,
        }
    }
}

/// What a node is, as its node group's labels say.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub struct NodeKind {
    /// `node.kubernetes.io/instance-type`, `unknown` without one.
    #[serde(rename = "type")]
    pub instance_type: String,
    /// Its capacity type.
    pub capacity: CapacityType,
}

impl NodeKind {
    /// A node that could not be read (gone, or no labels).
    pub fn unknown() -> NodeKind {
        NodeKind {
            instance_type: "unknown".into(),
            capacity: CapacityType::Unknown,
        }
    }
}

/// One pod as a Monitor round sees it, times in epoch seconds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PodSeen {
    /// Its Job's index (one pair per Job: pair ID = index + 1).
    pub job: u32,
    /// The kubelet's `startTime`.
    pub started_at: u64,
    /// Its containers' last `finishedAt` once it ended (`Succeeded`, `Failed`).
    pub ended_at: Option<u64>,
    /// GPUs its containers hold.
    pub gpus: u32,
    /// The node it runs on.
    pub node: Option<String>,
    /// It carries `DisruptionTarget`, read: a reclaim (the control plane is taking it away),
    /// the pod's own doing, or the kubelet's until its node is judged ([`judge`]).
    pub disruption: Option<Disruption>,
    /// It ended `Succeeded`.
    pub succeeded: bool,
}

/// The pods of an observation that ran, with what costs.
/// Times are taken no later than `observed_at` (a node's clock ahead is not believed).
pub fn pods_seen(jobs: &[JobView], observed_at: jiff::Timestamp) -> Vec<PodSeen> {
    let epoch = |t: jiff::Timestamp| u64::try_from(t.min(observed_at).as_second()).unwrap_or(0);
    let mut out = Vec::new();
    for job in jobs {
        let Some(index) = job.index else { continue };
        for pod in &job.pods {
            let Some(started_at) = pod.start_time.map(epoch) else {
                continue;
            };
            let ended = pod.phase.has_ended();
            let finished = pod
                .containers
                .iter()
                .filter_map(|c| match &c.state {
                    ContainerState::Terminated(exit) => exit.finished_at.map(epoch),
                    _ => None,
                })
                .max();
            out.push(PodSeen {
                job: index,
                started_at,
                // A pod that ended without a container's time (never ran one) ended at its start.
                ended_at: ended.then(|| finished.unwrap_or(started_at).max(started_at)),
                gpus: pod.gpus,
                node: pod.node.clone(),
                disruption: pod
                    .disruption
                    .as_deref()
                    .map(|reason| disruption::classify(reason, pod.disruption_message.as_deref())),
                succeeded: pod.phase == PodPhase::Succeeded,
            });
        }
    }
    out
}

/// The kubelet's disruptions judged by their nodes: `leaving` says, by node name, whether the
/// node is going ([`disruption::leaving`]). A node not in it is taken as staying.
pub fn judge(pods: &mut [PodSeen], leaving: &BTreeMap<String, bool>) {
    for pod in pods {
        if let Some(d @ Disruption::ByKubelet) = pod.disruption {
            let gone = pod.node.as_ref().and_then(|n| leaving.get(n)).copied();
            pod.disruption = Some(disruption::judge(d, gone.unwrap_or(false)));
        }
    }
}

impl PodSeen {
    fn reclaimed(&self) -> bool {
        self.disruption == Some(Disruption::Reclaim)
    }
}

/// GPU-seconds on one kind of node.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct UsageLine {
    /// The node kind.
    #[serde(flatten)]
    pub kind: NodeKind,
    /// Every second a GPU was held.
    pub held: u64,
    /// The part spent on routes a reclaim interrupted (run again by the next pod).
    pub run_again: u64,
}

/// Node kinds a ledger tells apart (the GPU node groups have a few instance types, on two
/// capacity types).
pub const MAX_LINES: usize = 16;

/// A submission's GPU usage so far: a line per node kind, and which Jobs had a pod running at
/// the last round. It takes a few bytes per Job of the run's state: a pod is known by its Job
/// and whether it started before the last round, and every pod running then was charged up
/// to it.
///
/// It also keeps the time reclaims cost the evaluation, which is not the participant's: the
/// stretches in which at least one of its Jobs was catching up, from its pair's last results
/// write before the reclaim (what runs again) to its next pod's start.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Ledger {
    /// By node kind.
    pub lines: Vec<UsageLine>,
    /// Each Job as the last round left it, by Job index.
    pub jobs: Vec<JobEntry>,
    /// GPUs of one pod (a pair's).
    pub gpus: u32,
    /// When the last round counted (epoch seconds).
    pub last: u64,
    /// Seconds of the closed stretches in which a Job caught up on a reclaim.
    pub lost: u64,
    /// When the open stretch began, while a Job catches up (epoch seconds).
    pub lost_since: Option<u64>,
    /// When the last closed stretch ended: the next begins no earlier, so no second counts
    /// twice.
    pub lost_until: u64,
}

/// One Job as the ledger keeps it between rounds.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct JobEntry {
    /// Where it stood at the last round.
    pub mark: JobMark,
    /// Its failed pods at the last round (`None`: no round saw its count yet). A pod gone
    /// since without one more failure was one the Pod failure policy ignored, a disruption
    /// (`Ignore` is the policy's one rule for it), even when no round saw its
    /// `DisruptionTarget`.
    pub failed: Option<u32>,
    /// Reclaims given free so far: at [`FREE_RECLAIMS_PER_PAIR`] the next counts as a crash.
    pub reclaims: u32,
    /// Pods the Monitor moved off a drained node ([`crate::capacity::consolidation`]): each is seen as one more
    /// reclaim, and each adds one to the free ones, so a move never takes a pair's allowance.
    pub moves: u32,
    /// Pods that ended by a disruption of their own (or a reclaim beyond the free ones):
    /// crashes its Job did not count, which count against its `backoffLimit` all the same
    /// ([`Ledger::charged_to`]).
    pub charged: u32,
    /// Of those, the platform's reclaims beyond the free ones (the rest were the pods' own):
    /// what the participant is told, and what ends a pair as the platform's failure.
    pub excess: u32,
    /// Its pod counted running at the last round: its start as that round saw it. A pod seen
    /// now with another start is that one's replacement, however soon after the round it
    /// started: the one before went between the two rounds.
    pub start: Option<u64>,
}

/// The most a Job's count keeps: far above any `backoffLimit` and the free reclaims (the
/// state keeps each count in one character).
pub const COUNT_CAP: u32 = 35;

/// Each Job's failed pods (`status.failed`), by Job index.
pub fn failures(jobs: &[JobView]) -> BTreeMap<u32, u32> {
    jobs.iter()
        .filter_map(|j| Some((j.index?, u32::try_from(j.failed).unwrap_or(0))))
        .collect()
}

/// The totals a record and `lbctl` show.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Totals {
    /// GPU-seconds held.
    pub gpu_seconds: u64,
    /// Of which on Spot capacity.
    pub spot: u64,
    /// Of which spent again on routes a reclaim interrupted.
    pub run_again: u64,
    /// Seconds reclaims cost the evaluation (not counted against its time limit).
    pub lost: u64,
    /// The estimate in dollars, when every GPU-second had a price.
    pub dollars: Option<f64>,
    /// What the orchestration did for it, when counted.
    pub orchestration: Option<Orchestration>,
    /// What its pods' logcopy stored in S3 and refused, when read (Finalize's).
    pub stored: Option<crate::job::uploads::UploadReport>,
}

/// Seconds by which a pod's start (the kubelet's clock) may follow the round that listed it
/// (the Monitor's clock, read before the list).
const CLOCK_SLACK: u64 = 5;

/// A Job's pod at the last round: its line, and whether its disruption was counted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Running {
    /// Its usage line (an index into [`Ledger::lines`]).
    pub line: usize,
    /// Its disruption was counted: it is a reclaim, its Job catching up.
    pub disrupted: bool,
}

/// Where a Job stands at the end of a round.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum JobMark {
    /// No pod running.
    #[default]
    Idle,
    /// A pod running.
    Running(Running),
    /// Its disrupted pod went; its next one has not started.
    Reclaimed,
}

impl Ledger {
    /// Nothing counted yet.
    pub fn is_empty(&self) -> bool {
        self.lines.is_empty() && self.last == 0
    }

    /// Job `job`'s entry (a default one past the known Jobs).
    fn entry(&self, job: u32) -> JobEntry {
        self.jobs.get(job as usize).copied().unwrap_or_default()
    }

    /// Job `job`'s entry to change, the Jobs before it added as they were never seen.
    fn entry_mut(&mut self, job: u32) -> &mut JobEntry {
        let job = job as usize;
        if self.jobs.len() <= job {
            self.jobs.resize(job + 1, JobEntry::default());
        }
        &mut self.jobs[job]
    }

    fn running(&self, job: u32) -> Option<Running> {
        match self.entry(job).mark {
            JobMark::Running(running) => Some(running),
            JobMark::Idle | JobMark::Reclaimed => None,
        }
    }

    /// Whether the Job is catching up on a reclaim: its disrupted pod still goes, or went and
    /// its next one has not started.
    fn catching_up(&self, job: u32) -> bool {
        match self.entry(job).mark {
            JobMark::Running(running) => running.disrupted,
            JobMark::Reclaimed => true,
            JobMark::Idle => false,
        }
    }

    fn set_mark(&mut self, job: u32, mark: JobMark) {
        self.entry_mut(job).mark = mark;
    }

    /// The Jobs the ledger knows, by index.
    fn known_jobs(&self) -> std::ops::Range<u32> {
        0..self.jobs.len() as u32
    }

    /// Whether a pod seen now ran at the last round (and was charged up to it): its Job's, if
    /// it started by then. A disrupted pod stays disrupted, so an undisrupted one is its
    /// replacement even when it started within the last round's second.
    ///
    /// A start a few seconds after the last round is that round's pod too: it was listed
    /// then with its start clamped to the round's clock, which is read before the list and
    /// is not the kubelet's.
    fn continues(&self, pod: &PodSeen) -> Option<Running> {
        self.running(pod.job)
            .filter(|r| self.same_pod(pod) && (pod.disruption.is_some() || !r.disrupted))
    }

    /// Whether `pod` is the one its Job ran at the last round: the start that round saw, or
    /// (that start clamped to the round's clock, or not remembered by an older state) a start
    /// within [`CLOCK_SLACK`] of it. A pod that started before the start that round saw is an
    /// earlier one, whatever the clocks: its Job's ended pods stay listed beside the new one.
    fn same_pod(&self, pod: &PodSeen) -> bool {
        let slack = || pod.started_at <= self.last.saturating_add(CLOCK_SLACK);
        match self.entry(pod.job).start {
            None => slack(),
            Some(seen) => {
                pod.started_at == seen || (seen >= self.last && pod.started_at > seen && slack())
            }
        }
    }

    /// A pod that ended by the last round was counted then (a Job's ended pods stay listed
    /// until the Job goes), unless that round counted it running: its status lagged behind
    /// its containers (a crash marker can wake a round in between), and its end, a crash to
    /// charge among them, is counted now.
    fn counted_before(&self, pod: &PodSeen) -> bool {
        pod.ended_at.is_some_and(|end| end <= self.last) && self.continues(pod).is_none()
    }

    /// Nodes whose kind this round needs: those of pods that started since the last round.
    pub fn unknown_nodes(&self, pods: &[PodSeen]) -> Vec<String> {
        let mut nodes: Vec<String> = pods
            .iter()
            .filter(|p| self.continues(p).is_none() && !self.counted_before(p))
            .filter_map(|p| p.node.clone())
            .collect();
        nodes.sort();
        nodes.dedup();
        nodes
    }

    /// Nodes whose state this round needs: those of pods the kubelet evicted, not counted
    /// before, whose disruption is judged by whether their node is leaving ([`judge`]).
    pub fn nodes_to_judge(&self, pods: &[PodSeen]) -> Vec<String> {
        let mut nodes: Vec<String> = pods
            .iter()
            .filter(|p| p.disruption == Some(Disruption::ByKubelet) && !self.counted_before(p))
            .filter_map(|p| p.node.clone())
            .collect();
        nodes.sort();
        nodes.dedup();
        nodes
    }

    fn line(&mut self, kind: &NodeKind) -> usize {
        let found = self.lines.iter().position(|l| &l.kind == kind);
        // The run's state has room for a few kinds: beyond them, a kind is counted as unknown.
        let kind = match found {
            None if self.lines.len() + 1 >= MAX_LINES => &NodeKind::unknown(),
            _ => kind,
        };
        match self.lines.iter().position(|l| &l.kind == kind) {
            Some(i) => i,
            None => {
                self.lines.push(UsageLine {
                    kind: kind.clone(),
                    held: 0,
                    run_again: 0,
                });
                self.lines.len() - 1
            }
        }
    }

    /// Charges `seconds` of one pod to its line, as run again too when `lost`.
    fn charge(&mut self, line: usize, seconds: u64, gpus: u32, lost: bool) {
        let gpu_seconds = seconds.saturating_mul(u64::from(gpus));
        let line = &mut self.lines[line];
        line.held = line.held.saturating_add(gpu_seconds);
        if lost {
            line.run_again = line.run_again.saturating_add(gpu_seconds);
        }
    }

    /// One round at `now`: each pod seen is charged from the last round (or its start, if it
    /// started since) to its end or to now. A pod that ran at the last round and is no longer
    /// listed went between the two (a deleted one: evicted, reclaimed) and is charged up to now,
    /// or up to its Job's next pod's start. A disrupted pod's time after its pair's last
    /// results write (`results_at`, by Job index) is run again by the next pod, and is lost
    /// time until that pod starts.
    ///
    /// `failed` is each Job's failed pods now: a pod that went between the rounds without its
    /// Job counting a failure was disrupted (an eviction a round did not see), and its time
    /// after the results write is run again as a seen disruption's is.
    pub fn account(
        &mut self,
        pods: &[PodSeen],
        kinds: &BTreeMap<String, NodeKind>,
        (results_at, failed): (&BTreeMap<u32, u64>, &BTreeMap<u32, u32>),
        now: u64,
    ) {
        let listed = self.listed_before(pods);
        let mut pods: Vec<&PodSeen> = pods.iter().filter(|p| !self.counted_before(p)).collect();
        pods.sort_by_key(|p| (p.job, p.started_at));
        let mut handled = BTreeSet::new();
        // The latest start of a pod that ended a Job's catching up.
        let mut resumed: Option<u64> = None;
        for pod in pods {
            let (from, mut running) = match self.continues(pod) {
                Some(running) => (self.last, running),
                None => {
                    // The Job's earlier pod went unlisted: it ran until this one started.
                    if let Some(gone) = self
                        .running(pod.job)
                        .filter(|_| !handled.contains(&pod.job))
                    {
                        let end = pod.started_at.clamp(self.last, now);
                        self.charge(gone.line, end - self.last, self.gpus, gone.disrupted);
                        if !gone.disrupted
                            && !listed.contains(&pod.job)
                            && self.ignored_failure(pod.job, failed)
                            && self.reclaimed_unseen(gone.line, pod.job, results_at, end)
                        {
                            resumed = resumed.max(Some(pod.started_at.min(now)));
                        }
                    }
                    if self.catching_up(pod.job) && !pod.reclaimed() {
                        resumed = resumed.max(Some(pod.started_at.min(now)));
                    }
                    let kind = pod.node.as_ref().and_then(|n| kinds.get(n));
                    let line = self.line(kind.unwrap_or(&NodeKind::unknown()));
                    (
                        pod.started_at,
                        Running {
                            line,
                            disrupted: false,
                        },
                    )
                }
            };
            self.gpus = pod.gpus;
            let to = pod.ended_at.unwrap_or(now).min(now).max(from);
            self.charge(running.line, to - from, pod.gpus, running.disrupted);
            self.disrupted(pod, &mut running, (to, now), results_at);
            let (mark, caught_up) = after_round(pod, running, now);
            resumed = resumed.max(caught_up);
            self.set_mark(pod.job, mark);
            let running = matches!(mark, JobMark::Running(_));
            self.entry_mut(pod.job).start = Some(pod.started_at).filter(|s| running && *s != 0);
            handled.insert(pod.job);
        }
        self.charge_gone((&handled, &listed), (results_at, failed), now);
        for (&job, &n) in failed {
            self.entry_mut(job).failed = Some(n.min(COUNT_CAP));
        }
        for entry in &mut self.jobs {
            entry.failed = Some(entry.failed.unwrap_or(0));
        }
        self.last = self.last.max(now);
        if !self.known_jobs().any(|job| self.catching_up(job)) {
            self.end_lost(resumed.unwrap_or(now));
        }
    }

    /// A disrupted pod seen this round (running charged up to `to`): a reclaim, the first time
    /// it is seen so and while its pair has free ones, loses everything since its pair's last
    /// results write, what earlier rounds charged included; any other disruption is a crash
    /// its Job did not count, charged once the pod has ended (a pod is seen ended once: the
    /// next round counted it before).
    fn disrupted(
        &mut self,
        pod: &PodSeen,
        running: &mut Running,
        (to, now): (u64, u64),
        results_at: &BTreeMap<u32, u64>,
    ) {
        if pod.reclaimed() && !running.disrupted && self.free(pod.job) {
            self.count_reclaim(pod.job);
            let since = results_at
                .get(&pod.job)
                .map_or(pod.started_at, |&t| t.max(pod.started_at));
            let lost = to.saturating_sub(since).saturating_mul(u64::from(pod.gpus));
            let line = &mut self.lines[running.line];
            line.run_again = line.run_again.saturating_add(lost);
            running.disrupted = true;
            self.begin_lost(since.min(now));
        }
        let crashed = pod.ended_at.is_some() && !pod.succeeded;
        if crashed && pod.disruption.is_some() && !running.disrupted {
            match pod.reclaimed() {
                true => self.charge_excess(pod.job),
                false => self.charge_crash(pod.job),
            }
        }
    }

    /// Pods of the last round neither seen nor replaced (`handled` has the Jobs that were) went
    /// between the two rounds: charged up to `now`; a disrupted one leaves its Job catching up.
    fn charge_gone(
        &mut self,
        (handled, listed): (&BTreeSet<u32>, &BTreeSet<u32>),
        (results_at, failed): (&BTreeMap<u32, u64>, &BTreeMap<u32, u32>),
        now: u64,
    ) {
        for job in self.known_jobs() {
            if let Some(gone) = self.running(job).filter(|_| !handled.contains(&job)) {
                let seconds = now.saturating_sub(self.last);
                self.charge(gone.line, seconds, self.gpus, gone.disrupted);
                let reclaimed = !gone.disrupted
                    && !listed.contains(&job)
                    && self.ignored_failure(job, failed)
                    && self.reclaimed_unseen(gone.line, job, results_at, now);
                let mark = if gone.disrupted || reclaimed {
                    JobMark::Reclaimed
                } else {
                    JobMark::Idle
                };
                self.set_mark(job, mark);
                self.entry_mut(job).start = None;
            }
        }
    }

    /// Whether a pod running at the last round went since without its Job counting a failure
    /// (a disruption no round saw): its lost time needs the results' times.
    pub fn went_unfailed(&self, pods: &[PodSeen], failed: &BTreeMap<u32, u32>) -> bool {
        let listed = self.listed_before(pods);
        self.known_jobs().any(|job| {
            self.running(job).is_some_and(|r| !r.disrupted)
                && !listed.contains(&job)
                && self.ignored_failure(job, failed)
        })
    }

    /// The Jobs with a pod listed that started by the last round: their pod of then is still
    /// there (running, or ended, perhaps within that round's second), not gone.
    fn listed_before(&self, pods: &[PodSeen]) -> BTreeSet<u32> {
        pods.iter()
            .filter(|p| self.same_pod(p))
            .map(|p| p.job)
            .collect()
    }

    /// Whether the Job's pod that went since the last round went without a failure counted
    /// (known only when both rounds saw the Job's count).
    fn ignored_failure(&self, job: u32, failed: &BTreeMap<u32, u32>) -> bool {
        matches!((self.failed_before(job), failed.get(&job)), (Some(b), Some(&n)) if n <= b)
    }

    fn failed_before(&self, job: u32) -> Option<u32> {
        self.entry(job).failed
    }

    /// Whether the Job has a free reclaim left (its moves given back).
    fn free(&self, job: u32) -> bool {
        let entry = self.entry(job);
        entry.reclaims < FREE_RECLAIMS_PER_PAIR + entry.moves
    }

    /// The Job's pods moved off drained nodes so far.
    pub fn moves_of(&self, job: u32) -> u32 {
        self.entry(job).moves
    }

    /// One more pod of the Job moved off a drained node (its eviction accepted).
    pub fn count_move(&mut self, job: u32) {
        let entry = self.entry_mut(job);
        entry.moves = (entry.moves + 1).min(COUNT_CAP);
    }

    /// One more reclaim given free to the Job.
    fn count_reclaim(&mut self, job: u32) {
        let entry = self.entry_mut(job);
        entry.reclaims = (entry.reclaims + 1).min(COUNT_CAP);
    }

    /// One more crash its Job did not count, charged to it.
    fn charge_crash(&mut self, job: u32) {
        let entry = self.entry_mut(job);
        entry.charged = (entry.charged + 1).min(COUNT_CAP);
    }

    /// One more reclaim beyond the free ones: charged as a crash, known as the platform's.
    fn charge_excess(&mut self, job: u32) {
        self.charge_crash(job);
        let entry = self.entry_mut(job);
        entry.excess = (entry.excess + 1).min(entry.charged);
    }

    /// A pod of `job` went by `end` without its Job counting a failure, no round having seen
    /// why (a deletion: only the control plane deletes our pods): a reclaim, its time lost,
    /// while the Job has free ones (`true`); beyond them, a crash its Job did not count.
    fn reclaimed_unseen(
        &mut self,
        line: usize,
        job: u32,
        results_at: &BTreeMap<u32, u64>,
        end: u64,
    ) -> bool {
        if !self.free(job) {
            self.charge_excess(job);
            return false;
        }
        self.count_reclaim(job);
        self.lose(line, job, results_at, end);
        true
    }

    /// Of [`Ledger::charged_to`], the platform's reclaims beyond the free ones.
    pub fn excess_of(&self, job: u32) -> u32 {
        self.entry(job).excess
    }

    /// The Job's pods that ended by a disruption of their own (or a reclaim beyond the free
    /// ones): crashes its Job did not count.
    pub fn charged_to(&self, job: u32) -> u32 {
        self.entry(job).charged
    }

    /// Seconds taken off the 72-hour limit at `now`: the time reclaims cost, up to
    /// [`MAX_TIME_OFF`].
    pub fn time_off(&self, now: u64) -> u64 {
        self.lost_at(now).min(MAX_TIME_OFF)
    }

    /// Seconds the Jobs' deadlines grow by: the closed stretches reclaims cost, up to
    /// [`MAX_TIME_OFF`].
    pub fn deadline_extension(&self) -> u64 {
        self.lost.min(MAX_TIME_OFF)
    }

    /// A pod of `job` unseen disrupted went by `end`: its time after its pair's last results
    /// write is run again, and lost time from then. NB: without that write, from the last
    /// round (the pod's start is not kept), so the run-again time is a lower bound.
    fn lose(&mut self, line: usize, job: u32, results_at: &BTreeMap<u32, u64>, end: u64) {
        let since = results_at.get(&job).copied().unwrap_or(self.last).min(end);
        let lost = (end - since).saturating_mul(u64::from(self.gpus));
        let line = &mut self.lines[line];
        line.run_again = line.run_again.saturating_add(lost);
        self.begin_lost(since);
    }

    /// A Job starts catching up on work lost since `since`: the open stretch begins then, or
    /// earlier if it already began, and never before the last one ended.
    fn begin_lost(&mut self, since: u64) {
        let since = since.max(self.lost_until);
        self.lost_since = Some(self.lost_since.map_or(since, |open| open.min(since)));
    }

    /// No Job catches up any more, since `at`: the open stretch closes.
    fn end_lost(&mut self, at: u64) {
        if let Some(open) = self.lost_since.take() {
            let at = at.max(open);
            self.lost = self.lost.saturating_add(at - open);
            self.lost_until = at;
        }
    }

    /// Seconds reclaims cost the evaluation up to `now`: the closed stretches and the open one.
    pub fn lost_at(&self, now: u64) -> u64 {
        let open = self.lost_since.map_or(0, |t| now.saturating_sub(t));
        self.lost.saturating_add(open)
    }

    /// Finalize's last word: every pod still running is charged to `now` (the Jobs are deleted
    /// next).
    pub fn close_all(&mut self, now: u64) {
        self.account(
            &[],
            &BTreeMap::new(),
            (&BTreeMap::new(), &BTreeMap::new()),
            now,
        );
    }

    /// The totals over every line, priced by `prices`.
    pub fn summary(&self, prices: &BTreeMap<String, InstancePrice>) -> Totals {
        let estimate = self.estimate(prices);
        Totals {
            dollars: (estimate.unpriced_gpu_seconds == 0).then_some(estimate.dollars),
            ..self.totals()
        }
    }

    /// The totals over every line, unpriced.
    pub fn totals(&self) -> Totals {
        let mut totals = Totals {
            lost: self.lost_at(self.last),
            ..Totals::default()
        };
        for line in &self.lines {
            totals.gpu_seconds += line.held;
            totals.run_again += line.run_again;
            if line.kind.capacity == CapacityType::Spot {
                totals.spot += line.held;
            }
        }
        totals
    }
}

/// Where a pod seen at `now` leaves its Job, and when the Job caught up on a reclaim if it did
/// here: a disrupted pod that succeeded had finished its pair's routes, so its Job caught up
/// when it ended.
fn after_round(pod: &PodSeen, running: Running, now: u64) -> (JobMark, Option<u64>) {
    match pod.ended_at {
        None => (JobMark::Running(running), None),
        Some(_) if running.disrupted && !pod.succeeded => (JobMark::Reclaimed, None),
        Some(end) => (JobMark::Idle, running.disrupted.then_some(end.min(now))),
    }
}

/// What the orchestration did for one submission: Step Functions state transitions, Lambda
/// invocations and memory-time, DynamoDB requests. Each stage adds its own.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Orchestration {
    /// State transitions (Standard workflows bill each, retries included).
    #[serde(default)]
    pub transitions: u64,
    /// Lambda invocations.
    #[serde(default)]
    pub invocations: u64,
    /// Lambda memory-time, MB-milliseconds (billed per GB-second).
    #[serde(default)]
    pub mb_ms: u64,
    /// DynamoDB requests (on-demand tables bill each).
    #[serde(default)]
    pub dynamo_requests: u64,
}

/// The list prices the orchestration is estimated at, US East (N. Virginia):
/// - Step Functions Standard: $0.025 per 1,000 state transitions
///   (aws.amazon.com/step-functions/pricing);
/// - Lambda, x86: $0.20 per million requests and $0.0000166667 per GB-second
///   (aws.amazon.com/lambda/pricing);
/// - DynamoDB on-demand: $0.625 per million write request units (aws.amazon.com/dynamodb/pricing/on-demand);
///   every request is priced as a write, most of ours are (a read costs a fifth of it).
pub mod list_prices {
    /// Dollars per state transition.
    pub const TRANSITION: f64 = 0.025 / 1_000.0;
    /// Dollars per Lambda invocation.
    pub const INVOCATION: f64 = 0.20 / 1_000_000.0;
    /// Dollars per GB-second of Lambda.
    pub const GB_SECOND: f64 = 0.000_016_666_7;
    /// Dollars per DynamoDB request.
    pub const DYNAMO_REQUEST: f64 = 0.625 / 1_000_000.0;
}

impl Orchestration {
    /// One Lambda invocation of `memory_mb` that ran `millis` and sent `dynamo_requests`,
    /// with the `transitions` it causes.
    pub fn invocation(transitions: u64, memory_mb: u32, millis: u64, dynamo_requests: u64) -> Self {
        Orchestration {
            transitions,
            invocations: 1,
            mb_ms: u64::from(memory_mb).saturating_mul(millis),
            dynamo_requests,
        }
    }

    /// Its estimate in dollars at the [`list_prices`].
    pub fn dollars(&self) -> f64 {
        let gb_seconds = self.mb_ms as f64 / 1024.0 / 1000.0;
        self.transitions as f64 * list_prices::TRANSITION
            + self.invocations as f64 * list_prices::INVOCATION
            + gb_seconds * list_prices::GB_SECOND
            + self.dynamo_requests as f64 * list_prices::DYNAMO_REQUEST
    }
}

impl std::ops::Add for Orchestration {
    type Output = Orchestration;

    fn add(self, other: Orchestration) -> Orchestration {
        Orchestration {
            transitions: self.transitions.saturating_add(other.transitions),
            invocations: self.invocations.saturating_add(other.invocations),
            mb_ms: self.mb_ms.saturating_add(other.mb_ms),
            dynamo_requests: self.dynamo_requests.saturating_add(other.dynamo_requests),
        }
    }
}

/// Where the state machine goes after a task (`Next?` in `statemachine/submission.asl.json`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum After {
    /// The run goes on: `PollInstead` when polling, else `Hold` (if it holds) and
    /// `WaitForChange`.
    Wait {
        /// It polls.
        poll: bool,
        /// It holds first.
        hold: bool,
    },
    /// `LaunchAdmitted`, which counts itself.
    Launch,
    /// `ContinueAsNew`, `Continued`, then the next execution's `OneSubmission?`, `Resume`,
    /// `Hold` and `WaitForChange`.
    Continue,
    /// `Finalize`, which counts itself and the two states after it.
    Finalize,
}

/// State transitions before Launch: `OneSubmission?`, `Unbatch`, `Intake`, `Eligible?`.
pub const OPENING_TRANSITIONS: u64 = 4;

/// State transitions of Finalize and after it: `Finalize`, `Failed?`, `Done`.
pub const CLOSING_TRANSITIONS: u64 = 3;

/// The state transitions a task (Launch, LaunchAdmitted, Monitor) and its retries cause up to
/// the next task: itself, `Next?` and the states it leads to.
pub fn task_transitions(retries: u64, after: After) -> u64 {
    let next = match after {
        After::Wait { poll: true, .. } => 1,
        After::Wait { hold, .. } => 1 + u64::from(hold),
        After::Launch | After::Finalize => 0,
        After::Continue => 6,
    };
    1 + retries + 1 + next
}

/// Dollars per hour of one instance type (the settings' `prices`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InstancePrice {
    /// On-demand, dollars per instance-hour.
    pub on_demand: f64,
    /// Spot, dollars per instance-hour (a recent average: Spot prices move).
    pub spot: f64,
}

/// An estimate in dollars, and the GPU-seconds no price was known for.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Estimate {
    /// Dollars.
    pub dollars: f64,
    /// GPU-seconds of instance types the table does not price.
    pub unpriced_gpu_seconds: u64,
}

impl Ledger {
    /// Prices the usage: each GPU-second at its instance type's hourly price over its GPUs
    /// (a pair's share of the node), Spot or on-demand as the node was.
    pub fn estimate(&self, prices: &BTreeMap<String, InstancePrice>) -> Estimate {
        let mut out = Estimate::default();
        for line in &self.lines {
            let kind = &line.kind;
            let gpus = crate::cluster::resources::capacity(&kind.instance_type).map(|c| c.gpus);
            match (prices.get(&kind.instance_type), gpus) {
                (Some(price), Some(gpus)) if gpus > 0 => {
                    let hourly = match kind.capacity {
                        CapacityType::Spot => price.spot,
                        CapacityType::OnDemand | CapacityType::Unknown => price.on_demand,
                    };
                    out.dollars += hourly / f64::from(gpus) * line.held as f64 / 3600.0;
                }
                _ => out.unpriced_gpu_seconds += line.held,
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The Jobs' marks as the run's state keeps them (`.`, `a` + line, `A` + line, `-`).
    fn marks(ledger: &Ledger) -> String {
        let stored = serde_json::to_value(ledger).unwrap();
        stored["jobs"].as_str().unwrap_or_default().to_owned()
    }

    /// A ledger whose Job 0 has had `reclaims` free ones.
    fn with_reclaims(reclaims: u32) -> Ledger {
        Ledger {
            jobs: vec![JobEntry {
                reclaims,
                ..JobEntry::default()
            }],
            ..Ledger::default()
        }
    }

    fn pod(job: u32, start: u64, end: Option<u64>, node: &str, disrupted: bool) -> PodSeen {
        PodSeen {
            job,
            started_at: start,
            ended_at: end,
            gpus: 1,
            node: Some(node.into()),
            disruption: disrupted.then_some(Disruption::Reclaim),
            succeeded: false,
        }
    }

    /// Job 0's pod started at 100 that the kubelet evicted for its own disk use, ended at `end`.
    fn own(end: Option<u64>) -> PodSeen {
        PodSeen {
            disruption: Some(Disruption::Own),
            ..pod(0, 100, end, "od-a", false)
        }
    }

    fn kinds() -> BTreeMap<String, NodeKind> {
        let kind = |capacity| NodeKind {
            instance_type: "g5.12xlarge".into(),
            capacity,
        };
        BTreeMap::from([
            ("spot-a".to_string(), kind(CapacityType::Spot)),
            ("od-a".to_string(), kind(CapacityType::OnDemand)),
        ])
    }

    #[test]
    fn rounds_charge_each_pod_once_from_start_to_end_whatever_they_see() {
        let kinds = kinds();
        let none = BTreeMap::new();
        let mut ledger = Ledger::default();
        let running = [pod(0, 100, None, "od-a", false)];
        assert_eq!(ledger.unknown_nodes(&running), ["od-a"]);
        ledger.account(&running, &kinds, (&none, &BTreeMap::new()), 400);
        assert!(ledger.unknown_nodes(&running).is_empty(), "{ledger:?}");
        ledger.account(&running, &kinds, (&none, &BTreeMap::new()), 1000);
        // Ended at 1100; the next rounds still list it (a Job's pods stay until it goes).
        for now in [1200, 1300] {
            let ended = [pod(0, 100, Some(1100), "od-a", false)];
            ledger.account(&ended, &kinds, (&none, &BTreeMap::new()), now);
        }
        // Another Job's pod started and ended between two rounds, on a node never read.
        let brief = [pod(1, 1310, Some(1390), "gone", false)];
        ledger.account(&brief, &kinds, (&none, &BTreeMap::new()), 1400);
        assert_eq!(ledger.totals().gpu_seconds, 1000 + 80);
        assert_eq!(ledger.lines[1].kind, NodeKind::unknown());
        // A pod deleted between two rounds is charged up to the round that misses it.
        ledger.account(
            &[pod(3, 1450, None, "od-a", false)],
            &kinds,
            (&none, &BTreeMap::new()),
            1500,
        );
        assert_eq!(marks(&ledger), "...a");
        ledger.account(&[], &kinds, (&none, &BTreeMap::new()), 1600);
        assert_eq!(ledger.totals().gpu_seconds, 1080 + 150);
        assert!(marks(&ledger).is_empty(), "{ledger:?}");
        assert_eq!(ledger.totals().run_again, 0);
    }

    #[test]
    fn only_the_control_plane_s_disruptions_are_free_and_only_a_few_per_pair() {
        let kinds = kinds();
        let results = BTreeMap::from([(0, 700)]);
        let none_failed = BTreeMap::from([(0, 0)]);
        let with = |d: Option<Disruption>, end: Option<u64>| PodSeen {
            disruption: d,
            ..pod(0, 100, end, "spot-a", false)
        };
        let running = [with(None, None)];
        // One round sees the pod running, the next sees it ended by this disruption: what
        // the ledger charges the pair and gives back.
        let after = |d: Disruption, reclaims: u32| {
            let mut ledger = with_reclaims(reclaims);
            ledger.account(&running, &kinds, (&results, &none_failed), 500);
            ledger.account(
                &[with(Some(d), Some(900))],
                &kinds,
                (&results, &none_failed),
                1000,
            );
            (
                (ledger.charged_to(0), ledger.excess_of(0)),
                ledger.totals().run_again,
                ledger.lost_at(1000),
            )
        };
        // A reclaim: free, run again from the results at 700, lost until a next pod starts.
        assert_eq!(after(Disruption::Reclaim, 0), ((0, 0), 200, 300));
        // The kubelet's pressure eviction on a healthy node (judged `Own`): a crash, charged
        // to the pair's retries, nothing given back.
        assert_eq!(after(Disruption::Own, 0), ((1, 0), 0, 0));
        // A kubelet's eviction whose node was never judged is not taken as free either.
        assert_eq!(after(Disruption::ByKubelet, 0), ((1, 0), 0, 0));
        // Beyond the free reclaims a reclaim is a crash too, known as the platform's.
        assert_eq!(after(Disruption::Reclaim, 2), ((0, 0), 200, 300));
        assert_eq!(after(Disruption::Reclaim, 3), ((1, 1), 0, 0));
        // A move off a drained node is seen as a reclaim and gives one back: after three
        // reclaims and a move, the move itself is free, and the pair keeps its allowance.
        let moved = |reclaims: u32| {
            let mut ledger = with_reclaims(reclaims);
            ledger.count_move(0);
            ledger.account(&running, &kinds, (&results, &none_failed), 500);
            let evicted = [with(Some(Disruption::Reclaim), Some(900))];
            ledger.account(&evicted, &kinds, (&results, &none_failed), 1000);
            (
                ledger.charged_to(0),
                ledger.jobs[0].reclaims,
                ledger.moves_of(0),
            )
        };
        assert_eq!(moved(3), (0, 4, 1));
        assert_eq!(
            moved(4),
            (1, 4, 1),
            "a move gives back one reclaim, not more"
        );
        // A pod gone between two rounds unseen (only the control plane deletes): free while
        // the pair has free reclaims, then charged.
        let gone = |reclaims: u32| {
            let mut ledger = with_reclaims(reclaims);
            ledger.account(&running, &kinds, (&results, &none_failed), 500);
            let next = [pod(0, 960, None, "od-a", false)];
            ledger.account(&next, &kinds, (&results, &none_failed), 1000);
            (
                (ledger.charged_to(0), ledger.excess_of(0)),
                ledger.lost_at(1000),
                ledger.jobs[0].reclaims,
            )
        };
        assert_eq!(gone(0), ((0, 0), 260, 1));
        assert_eq!(gone(3), ((1, 1), 0, 3));
        // Judging by the node: leaving makes the kubelet's eviction free.
        let mut pods = [
            PodSeen {
                node: Some("cordoned".into()),
                ..with(Some(Disruption::ByKubelet), None)
            },
            PodSeen {
                node: Some("healthy".into()),
                ..with(Some(Disruption::ByKubelet), None)
            },
        ];
        let ledger = Ledger::default();
        assert_eq!(ledger.nodes_to_judge(&pods), ["cordoned", "healthy"]);
        judge(
            &mut pods,
            &BTreeMap::from([("cordoned".into(), true), ("healthy".into(), false)]),
        );
        let judged: Vec<_> = pods.iter().map(|p| p.disruption).collect();
        assert_eq!(judged, [Some(Disruption::Reclaim), Some(Disruption::Own)]);
    }

    #[test]
    fn an_own_disruption_is_charged_once_even_when_its_pod_s_status_lags() {
        let kinds = kinds();
        let results = BTreeMap::from([(0, 700)]);
        let none_failed = BTreeMap::from([(0, 0)]);
        // The rounds' sightings of one pod the kubelet evicted for its own disk use, its
        // containers done at 900: the charge to its pair once they are all seen.
        let charged = |sightings: &[(u64, PodSeen)]| {
            let mut ledger = Ledger::default();
            ledger.account(
                &[pod(0, 100, None, "od-a", false)],
                &kinds,
                (&results, &none_failed),
                500,
            );
            for (now, seen) in sightings {
                ledger.account(
                    std::slice::from_ref(seen),
                    &kinds,
                    (&results, &none_failed),
                    *now,
                );
            }
            (ledger.charged_to(0), ledger.totals().gpu_seconds)
        };
        // Its status said Failed by the next round.
        assert_eq!(charged(&[(1000, own(Some(900)))]), (1, 800));
        // Its status still said Running at the round a crash marker woke (after its end),
        // Failed only at the next: charged all the same, once, its time
        // charged up to that round (what it could see), not twice.
        assert_eq!(
            charged(&[
                (1000, own(None)),
                (1100, own(Some(900))),
                (1200, own(Some(900)))
            ]),
            (1, 900)
        );
        // Without the condition at the lagging round, the same.
        assert_eq!(
            charged(&[
                (1000, pod(0, 100, None, "od-a", false)),
                (1100, own(Some(900)))
            ]),
            (1, 900)
        );
    }

    #[test]
    fn an_own_disruption_is_charged_once_when_its_replacement_started_in_the_round_s_second() {
        let kinds = kinds();
        let results = BTreeMap::from([(0, 700)]);
        let none_failed = BTreeMap::from([(0, 0)]);
        let mut ledger = Ledger::default();
        let mut round = |pods: &[PodSeen], now: u64| {
            ledger.account(pods, &kinds, (&results, &none_failed), now);
            ledger.charged_to(0)
        };
        assert_eq!(round(&[pod(0, 100, None, "od-a", false)], 500), 0);
        // Stopped, its status still Running with the condition.
        assert_eq!(round(&[own(None)], 1000), 0);
        // Failed, and its replacement started in the very second of this round (the kubelet's
        // clock a little ahead of the Monitor's).
        let next = pod(0, 1100, None, "od-a", false);
        assert_eq!(round(&[own(Some(900)), next.clone()], 1100), 1);
        // The failed pod stays listed beside its replacement: not charged again, round after
        // round, though its replacement's start is not before the last round.
        assert_eq!(round(&[own(Some(900)), next.clone()], 1100), 1);
        assert_eq!(round(&[own(Some(900)), next], 1200), 1);
    }

    #[test]
    fn reclaimed_pods_listed_beside_their_replacements_are_counted_once() {
        let kinds = kinds();
        let results = BTreeMap::from([(0, 0)]);
        let none_failed = BTreeMap::from([(0, 0)]);
        let mut ledger = Ledger::default();
        let mut listed: Vec<PodSeen> = Vec::new();
        let mut now = 100;
        ledger.account(
            &[pod(0, 100, None, "od-a", false)],
            &kinds,
            (&results, &none_failed),
            now,
        );
        // Four reclaims in a row, each replacement started in the very second of the round
        // that sees its predecessor ended; every ended pod stays listed.
        for n in 0..4u64 {
            let start = 100 + n * 100;
            now = start + 100;
            listed.push(pod(0, start, Some(now - 10), "od-a", true));
            let mut seen = listed.clone();
            seen.push(pod(0, now, None, "od-a", false));
            ledger.account(&seen, &kinds, (&results, &none_failed), now);
            ledger.account(&seen, &kinds, (&results, &none_failed), now + 50);
        }
        assert_eq!((ledger.charged_to(0), ledger.excess_of(0)), (1, 1));
    }

    #[test]
    fn the_time_reclaims_take_off_the_limit_is_capped() {
        let ledger = Ledger {
            lost: 3 * MAX_TIME_OFF,
            lost_since: Some(0),
            ..Ledger::default()
        };
        assert_eq!(ledger.lost_at(1000), 3 * MAX_TIME_OFF + 1000);
        assert_eq!(ledger.time_off(1000), MAX_TIME_OFF);
        assert_eq!(ledger.deadline_extension(), MAX_TIME_OFF);
        let small = Ledger {
            lost: 600,
            ..Ledger::default()
        };
        assert_eq!((small.time_off(0), small.deadline_extension()), (600, 600));
    }

    #[test]
    fn a_pod_evicted_between_two_rounds_is_run_again_as_a_seen_one_unless_its_job_counted_it() {
        let kinds = kinds();
        let results = BTreeMap::from([(0, 700)]);
        let (none_failed, one_failed) = (BTreeMap::from([(0, 0)]), BTreeMap::from([(0, 1)]));
        let running = [pod(0, 100, None, "spot-a", false)];
        let replaced = [pod(0, 960, None, "od-a", false)];
        let start = || {
            let mut ledger = Ledger::default();
            ledger.account(&running, &kinds, (&results, &none_failed), 500);
            ledger
        };
        // Gone and replaced within one round's interval, no failure counted: a disruption.
        let mut evicted = start();
        assert!(evicted.went_unfailed(&replaced, &none_failed));
        evicted.account(&replaced, &kinds, (&results, &none_failed), 1000);
        let totals = evicted.totals();
        assert_eq!((totals.spot, totals.gpu_seconds), (860, 900), "{evicted:?}");
        assert_eq!(totals.run_again, 260, "since the results at 700");
        assert_eq!(evicted.lost_at(1000), 260, "to the next pod's start");
        // The same with one more failure counted: a crash, the participant's.
        let mut crashed = start();
        assert!(!crashed.went_unfailed(&replaced, &one_failed));
        crashed.account(&replaced, &kinds, (&results, &one_failed), 1000);
        assert_eq!((crashed.totals().run_again, crashed.lost_at(1000)), (0, 0));
        // Gone, its replacement still in the Job controller's backoff at the next round.
        let mut waiting = start();
        waiting.account(&[], &kinds, (&results, &none_failed), 900);
        assert_eq!(marks(&waiting), "-", "catching up");
        assert_eq!(waiting.totals().run_again, 200);
        waiting.account(&replaced, &kinds, (&results, &none_failed), 1000);
        assert_eq!(waiting.lost_at(1000), 260, "{waiting:?}");
        assert_eq!(marks(&waiting), "b");
        // A pod that started as a round listed it (its start clamped to that round's clock)
        // is the same pod at the next, a second or two later by the kubelet's clock.
        let mut clamped = Ledger::default();
        clamped.account(
            &[pod(0, 500, None, "od-a", false)],
            &kinds,
            (&results, &none_failed),
            500,
        );
        let later = [pod(0, 502, None, "od-a", false)];
        assert!(!clamped.went_unfailed(&later, &none_failed));
        clamped.account(&later, &kinds, (&results, &none_failed), 1000);
        assert_eq!((clamped.totals().run_again, clamped.lost_at(1000)), (0, 0));
        // A pod that ended within the second of the round that still saw it running is
        // listed ended at the next: it ended, it did not go.
        let mut ended = start();
        let done = [PodSeen {
            succeeded: true,
            ..pod(0, 100, Some(500), "spot-a", false)
        }];
        assert!(!ended.went_unfailed(&done, &none_failed));
        ended.account(&done, &kinds, (&results, &none_failed), 1000);
        assert_eq!((ended.totals().run_again, ended.lost_at(1000)), (0, 0));
        // Replaced within the clock's slack of the round that saw the first pod (its start
        // then well before that round): another start is another pod, gone and replaced.
        let before = BTreeMap::from([(0, 450)]);
        let seen_at_500 = || {
            let mut ledger = Ledger::default();
            ledger.account(&running, &kinds, (&before, &none_failed), 500);
            ledger
        };
        let mut soon = seen_at_500();
        let quick = [pod(0, 503, None, "od-a", false)];
        assert!(soon.went_unfailed(&quick, &none_failed));
        soon.account(&quick, &kinds, (&before, &none_failed), 1000);
        assert_eq!(
            soon.totals().run_again,
            53,
            "since the results at 450: {soon:?}"
        );
        assert_eq!(soon.lost_at(1000), 53, "to the next pod's start: {soon:?}");
        // A state from before the starts were kept judges by the clock's slack alone.
        let mut older = seen_at_500();
        older.jobs.iter_mut().for_each(|entry| entry.start = None);
        // Starts are kept compactly, per Job.
        assert_eq!(soon.jobs[0].start, Some(503));
        let stored = serde_json::to_value(&soon).unwrap();
        assert_eq!(stored["starts"], "dz");
        assert_eq!(serde_json::from_value::<Ledger>(stored).unwrap(), soon);
        older.account(&quick, &kinds, (&before, &none_failed), 1000);
        assert_eq!(older.totals().run_again, 0, "{older:?}");
        // A round that could not read the Jobs' counts decides nothing.
        let mut unknown = start();
        unknown.account(&replaced, &kinds, (&results, &BTreeMap::new()), 1000);
        assert_eq!(unknown.totals().run_again, 0);
    }

    #[test]
    fn a_reclaimed_pod_s_seconds_after_its_last_results_are_run_again() {
        let kinds = kinds();
        let mut ledger = Ledger::default();
        let results = BTreeMap::from([(0, 700)]);
        ledger.account(
            &[pod(0, 100, None, "spot-a", false)],
            &kinds,
            (&results, &BTreeMap::new()),
            500,
        );
        ledger.account(
            &[pod(0, 100, None, "spot-a", true)],
            &kinds,
            (&results, &BTreeMap::new()),
            900,
        );
        assert_eq!(ledger.totals().run_again, 200, "since the results at 700");
        // Deleted once its Job counted it; the next pod started at 960 on an on-demand node.
        ledger.account(
            &[pod(0, 960, None, "od-a", false)],
            &kinds,
            (&results, &BTreeMap::new()),
            1000,
        );
        let totals = ledger.totals();
        assert_eq!(totals.spot, 860, "{ledger:?}");
        assert_eq!(totals.gpu_seconds, 860 + 40);
        assert_eq!(totals.run_again, 260);
        assert_eq!(
            ledger.lost_at(1000),
            260,
            "from the results at 700 to the next pod"
        );
        // A replacement that started within the last round's second is not the disrupted pod.
        let mut same_second = Ledger::default();
        same_second.account(
            &[pod(0, 100, None, "spot-a", true)],
            &kinds,
            (&results, &BTreeMap::new()),
            900,
        );
        same_second.account(
            &[pod(0, 900, None, "spot-a", false)],
            &kinds,
            (&results, &BTreeMap::new()),
            950,
        );
        assert_eq!(same_second.totals().run_again, 200);
        assert_eq!(marks(&same_second), "a");
        assert_eq!((same_second.lost, same_second.lost_since), (200, None));
        // Finalize charges what still runs; the undisrupted pod runs nothing again.
        ledger.close_all(1100);
        assert_eq!(ledger.totals().gpu_seconds, 860 + 140);
        assert_eq!(ledger.totals().run_again, 260);
        assert!(marks(&ledger).is_empty());
    }

    #[test]
    fn time_lost_to_reclaims_counts_once_however_many_jobs_catch_up_at_once() {
        let kinds = kinds();
        let mut ledger = Ledger::default();
        let results = BTreeMap::from([(0, 700), (1, 650)]);
        let both = |disrupted| {
            [
                pod(0, 100, None, "spot-a", disrupted),
                pod(1, 100, None, "spot-a", disrupted),
            ]
        };
        ledger.account(&both(false), &kinds, (&results, &BTreeMap::new()), 600);
        assert_eq!(ledger.lost_at(600), 0);
        // One node reclaimed: both pairs lose what followed their last results.
        ledger.account(&both(true), &kinds, (&results, &BTreeMap::new()), 900);
        assert_eq!(
            ledger.lost_at(900),
            250,
            "since the earlier results, at 650"
        );
        // Deleted; no next pod yet: the stretch stays open.
        ledger.account(&[], &kinds, (&results, &BTreeMap::new()), 1000);
        assert_eq!(marks(&ledger), "--");
        assert_eq!(ledger.lost_at(1000), 350);
        // Job 0 starts again at 1100; Job 1 still waits for a GPU.
        ledger.account(
            &[pod(0, 1100, None, "od-a", false)],
            &kinds,
            (&results, &BTreeMap::new()),
            1200,
        );
        assert_eq!(ledger.lost_at(1200), 550);
        let both_back = [
            pod(0, 1100, None, "od-a", false),
            pod(1, 1300, None, "od-a", false),
        ];
        ledger.account(&both_back, &kinds, (&results, &BTreeMap::new()), 1400);
        assert_eq!((ledger.lost, ledger.lost_since), (650, None), "650 to 1300");
        assert_eq!(ledger.lost_at(5000), 650);
        // A later reclaim whose lost work began before the last stretch ended counts from its end.
        let results = BTreeMap::from([(0, 1250), (1, 1350)]);
        let again = [
            pod(0, 1100, None, "od-a", true),
            pod(1, 1300, None, "od-a", false),
        ];
        ledger.account(&again, &kinds, (&results, &BTreeMap::new()), 1500);
        let back = [
            pod(0, 1550, None, "od-a", false),
            pod(1, 1300, None, "od-a", false),
        ];
        ledger.account(&back, &kinds, (&results, &BTreeMap::new()), 1600);
        assert_eq!(ledger.lost, 650 + 250, "1300 to 1550");
        // A disrupted pod that succeeded finished its routes: its Job caught up when it ended.
        let (mut done, none) = (Ledger::default(), BTreeMap::new());
        done.account(
            &[pod(0, 100, None, "spot-a", true)],
            &kinds,
            (&none, &BTreeMap::new()),
            900,
        );
        let mut ended = pod(0, 100, Some(950), "spot-a", true);
        ended.succeeded = true;
        done.account(&[ended], &kinds, (&none, &BTreeMap::new()), 1000);
        assert_eq!((done.lost, done.lost_since), (950 - 100, None));
        assert!(marks(&done).is_empty());
    }

    #[test]
    fn the_estimate_prices_a_gpu_at_its_share_of_the_node_by_capacity() {
        let kinds = kinds();
        let mut ledger = Ledger::default();
        let pods = [
            pod(0, 0, Some(7200), "spot-a", false),
            pod(1, 0, Some(7200), "od-a", false),
            pod(2, 0, Some(3600), "gone", false),
        ];
        ledger.account(&pods, &kinds, (&BTreeMap::new(), &BTreeMap::new()), 7200);
        let prices = BTreeMap::from([(
            "g5.12xlarge".to_string(),
            InstancePrice {
                on_demand: 5.672,
                spot: 2.0,
            },
        )]);
        let e = ledger.estimate(&prices);
        // Two GPU-hours each at a quarter of the node's hourly price.
        let expected = 2.0 * 2.0 / 4.0 + 2.0 * 5.672 / 4.0;
        assert!((e.dollars - expected).abs() < 1e-9, "{e:?}");
        assert_eq!(e.unpriced_gpu_seconds, 3600);
    }

    #[test]
    fn the_orchestration_is_priced_per_transition_request_and_gb_second() {
        // A thousand rounds of four transitions, each a second of a 512 MB Lambda with ten
        // DynamoDB requests.
        let round = Orchestration::invocation(4, 512, 1000, 10);
        let run = (0..1000).fold(Orchestration::default(), |sum, _| sum + round);
        assert_eq!(run.transitions, 4000);
        assert_eq!(run.mb_ms, 512_000_000);
        let expected = 4000.0 * 0.000_025
            + 1000.0 * 0.000_000_2
            + 500.0 * 0.000_016_666_7
            + 10_000.0 * 0.000_000_625;
        assert!((run.dollars() - expected).abs() < 1e-9, "{}", run.dollars());
        assert!(run.dollars() < 0.12, "cents, beside GPU-hours of dollars");
        // A round that holds and waits: Monitor, Next?, Hold, WaitForChange.
        let waits = After::Wait {
            poll: false,
            hold: true,
        };
        assert_eq!(task_transitions(0, waits), 4);
        assert_eq!(task_transitions(2, After::Finalize), 4, "retries count");
        assert_eq!(task_transitions(0, After::Continue), 8);
    }

    #[test]
    fn the_capacity_comes_from_the_node_label() {
        assert_eq!(CapacityType::from_label(Some("SPOT")), CapacityType::Spot);
        assert_eq!(
            CapacityType::from_label(Some("ON_DEMAND")),
            CapacityType::OnDemand
        );
        assert_eq!(CapacityType::from_label(None), CapacityType::Unknown);
    }
}
