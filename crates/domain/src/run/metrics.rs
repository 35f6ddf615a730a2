//! The fleet's metrics: the catalog every function emits from and the dashboard and alarms
//! name (each metric's name, unit and dimensions), and what a run's state changing says.
//!
//! Dimensions stay few so a metric is never one per submission: `Stage` (the function) for
//! what a function does, `Leaderboard` for what the fleet does, one bounded word more for how
//! runs end (`Outcome`, `Reason`), none for the EvalAI budget the whole account shares.
//! CloudWatch bills each name-and-dimensions pair for every hour it is sent in, so a count of
//! zero is not sent (a gauge's zero is), and what Lambda publishes free (`AWS/Lambda`'s invocations and errors) is
//! not sent again.

use crate::capacity::cost::Totals;
use crate::run::state::RunState;

/// The CloudWatch namespace of every metric here.
pub const NAMESPACE: &str = "CarlaLeaderboard";

/// A metric's unit, as CloudWatch spells it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Unit {
    /// A number of things.
    Count,
    /// Seconds.
    Seconds,
    /// Milliseconds.
    Milliseconds,
    /// Dollars (CloudWatch has no currency unit).
    None,
}

impl Unit {
    /// The name EMF and CloudWatch use.
    pub fn as_str(self) -> &'static str {
        match self {
            Unit::Count => "Count",
            Unit::Seconds => "Seconds",
            Unit::Milliseconds => "Milliseconds",
            Unit::None => "None",
        }
    }
}

/// Which dimensions a metric is sent with (one set each).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Dimensions {
    /// None: one metric for the account.
    Account,
    /// The function (`Stage`).
    Stage,
    /// The leaderboard (`"1.0"`, `"2.0"`).
    Leaderboard,
    /// The leaderboard and how a run ended (`FINISHED`, `FAILED`, `CANCELLED`).
    Outcome,
    /// The leaderboard and why a run failed (a [`Reason`]).
    Reason,
}

impl Dimensions {
    /// The dimension names, as the documents and the dashboard spell them.
    pub fn keys(self) -> &'static [&'static str] {
        match self {
            Dimensions::Account => &[],
            Dimensions::Stage => &["Stage"],
            Dimensions::Leaderboard => &["Leaderboard"],
            Dimensions::Outcome => &["Leaderboard", "Outcome"],
            Dimensions::Reason => &["Leaderboard", "Reason"],
        }
    }
}

macro_rules! catalog {
    ($($(#[$doc:meta])* $metric:ident => $unit:ident, $dims:ident;)*) => {
        /// Every metric the functions emit.
        #[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
        pub enum Metric {
            $($(#[$doc])* $metric,)*
        }

        impl Metric {
            /// The whole catalog.
            pub const ALL: &'static [Metric] = &[$(Metric::$metric,)*];

            /// Its name in CloudWatch.
            pub fn name(self) -> &'static str {
                match self {
                    $(Metric::$metric => stringify!($metric),)*
                }
            }

            /// Its unit.
            pub fn unit(self) -> Unit {
                match self {
                    $(Metric::$metric => Unit::$unit,)*
                }
            }

            /// The dimensions it is sent with.
            pub fn dimensions(self) -> Dimensions {
                match self {
                    $(Metric::$metric => Dimensions::$dims,)*
                }
            }
        }
    };
}

catalog! {
    /// The handler's time (one value per invocation).
    Duration => Milliseconds, Stage;
    /// Requests sent to EvalAI (each attempt).
    EvalAiRequests => Count, Account;
    /// EvalAI's 429s.
    EvalAiThrottled => Count, Account;
    /// Routine requests the shared budget refused (sent in a later round).
    EvalAiOverBudget => Count, Account;
    /// Urgent requests that waited for the budget's next window.
    EvalAiBudgetWaits => Count, Account;
    /// GPUs the clusters' nodes offer, every one billed (the sweep's count, a zero too).
    GpusBilled => Count, Account;
    /// Of those, GPUs pods hold (the sweep's count, a zero too).
    GpusHeld => Count, Account;
    /// A submission Intake claimed.
    Arrivals => Count, Leaderboard;
    /// A submission Intake refused (told `failed` with the reason).
    Refusals => Count, Leaderboard;
    /// A submission past its team's cap: its Jobs may start.
    Admissions => Count, Leaderboard;
    /// Arrival -> admission.
    QueueWait => Seconds, Leaderboard;
    /// Submissions waiting for their team's cap, as a Monitor round read the queue.
    QueueLength => Count, Leaderboard;
    /// A run's first pair started (EvalAI told `running`).
    Starts => Count, Leaderboard;
    /// Arrival -> first pair running.
    StartWait => Seconds, Leaderboard;
    /// A run ended, by outcome.
    Ends => Count, Outcome;
    /// A run failed, by reason.
    Failures => Count, Reason;
    /// GPU-seconds its pods held on Spot nodes.
    GpuSecondsSpot => Seconds, Leaderboard;
    /// GPU-seconds its pods held on on-demand nodes.
    GpuSecondsOnDemand => Seconds, Leaderboard;
    /// Of those, time spent again on routes a reclaim interrupted.
    GpuSecondsRunAgain => Seconds, Leaderboard;
    /// Dollars of GPU time at the settings' prices.
    GpuCost => None, Leaderboard;
    /// Pods the platform took away (Spot reclaims, node drains, moves) and the Job ran again.
    Reclaims => Count, Leaderboard;
    /// Of those, pods the Monitor moved off a node consolidation drains, at a route's end.
    Moves => Count, Leaderboard;
    /// Pods that failed and their Job ran again (the participant's crashes among them).
    PodFailures => Count, Leaderboard;
    /// Routes finished.
    RoutesDone => Count, Leaderboard;
    /// A pair's newest results write -> the partial update carrying it, one value per update
    /// sent (its sample count is the updates).
    PartialUpdateDelay => Seconds, Leaderboard;
}

impl Metric {
    /// The metric of this name.
    pub fn named(name: &str) -> Option<Metric> {
        Metric::ALL.iter().copied().find(|m| m.name() == name)
    }
}

/// Every word a run's failure may carry as `Reason`: the cluster's verdicts and ours.
pub fn reasons() -> Vec<&'static str> {
    let verdicts = crate::cluster::view::FailureKind::ALL.map(|k| k.name());
    let ours = [reason::REFUSED, reason::PIPELINE, reason::EVALUATION];
    verdicts.into_iter().chain(ours).collect()
}

/// Why a run failed, in a few words a dashboard can hold: the cluster's verdict
/// ([`crate::cluster::view::FailureKind`]'s names), or one of these.
pub mod reason {
    /// Intake refused the submission.
    pub const REFUSED: &str = "Refused";
    /// A stage of ours failed (the execution's caught error).
    pub const PIPELINE: &str = "PipelineError";
    /// The evaluation itself failed (its results say so, or a pair's time ran out).
    pub const EVALUATION: &str = "Evaluation";
}

/// One value of one metric.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    /// Which.
    pub metric: Metric,
    /// Its value in the metric's unit.
    pub value: f64,
}

/// What one stage's work says of the fleet: samples, and the words the dimensions need.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Signals {
    /// The samples, zeros left out.
    pub samples: Vec<Sample>,
    /// How the run ended, when it did here.
    pub outcome: Option<&'static str>,
    /// Why it failed, when it did here.
    pub reason: Option<&'static str>,
}

impl Signals {
    /// Adds `value` of `metric` unless it is zero.
    pub fn add(&mut self, metric: Metric, value: f64) {
        if value != 0.0 && value.is_finite() {
            self.samples.push(Sample { metric, value });
        }
    }

    /// A run ended as `outcome`, failing for `reason` when it failed.
    pub fn ended(&mut self, outcome: &'static str, reason: Option<&'static str>) {
        self.add(Metric::Ends, 1.0);
        self.outcome = Some(outcome);
        if let Some(reason) = reason {
            self.add(Metric::Failures, 1.0);
            self.reason = Some(reason);
        }
    }
}

/// Launch admitted a run that arrived at `arrived_at` (epoch seconds; 0 for a run from before
/// the queue) at `now`.
pub fn admitted(arrived_at: u64, now: u64) -> Signals {
    let mut signals = Signals::default();
    signals.add(Metric::Admissions, 1.0);
    signals.add(Metric::QueueWait, waited(arrived_at, now));
    signals
}

/// How a claimed run ended (Finalize's settlement): a failure's reason is the cluster's
/// verdict when it gave one, our own stage's error when one was caught, else the evaluation's.
pub fn ending(
    status: crate::status::RecordStatus,
    failure: Option<crate::cluster::view::FailureKind>,
    caught_error: bool,
) -> Signals {
    use crate::status::RecordStatus;
    let mut signals = Signals::default();
    let reason = (status == RecordStatus::Failed).then(|| match failure {
        Some(kind) => kind.name(),
        None if caught_error => reason::PIPELINE,
        None => reason::EVALUATION,
    });
    signals.ended(status.as_str(), reason);
    signals
}

/// What a Monitor round changed in a run: its start with its wait, the GPU time and cost its
/// ledger charged, reclaims and failed pods, routes done. How a run ends is Finalize's to say
/// ([`Signals::ended`]): every run ends there.
pub fn of_round(
    before: &RunState,
    after: &RunState,
    prices: &std::collections::BTreeMap<String, crate::capacity::cost::InstancePrice>,
) -> Signals {
    let mut signals = Signals::default();
    let arrived = after.queue.arrived_at;
    let started_before = before.monitor.started_at;
    if let (None, Some(started)) = (started_before, after.monitor.started_at) {
        signals.add(Metric::Starts, 1.0);
        signals.add(Metric::StartWait, waited(arrived, started));
    }
    let old = usage(before, prices);
    let new = usage(after, prices);
    let spot = new.spot.saturating_sub(old.spot);
    let held = new.gpu_seconds.saturating_sub(old.gpu_seconds);
    signals.add(Metric::GpuSecondsSpot, spot as f64);
    signals.add(Metric::GpuSecondsOnDemand, held.saturating_sub(spot) as f64);
    let again = new.run_again.saturating_sub(old.run_again);
    signals.add(Metric::GpuSecondsRunAgain, again as f64);
    let dollars = new.dollars.unwrap_or(0.0) - old.dollars.unwrap_or(0.0);
    signals.add(Metric::GpuCost, dollars.max(0.0));
    let (reclaims, failed) = pods(after);
    let (reclaims_before, failed_before) = pods(before);
    let moves = |run: &RunState| -> u64 {
        (run.monitor.usage.jobs.iter())
            .map(|job| u64::from(job.moves))
            .sum()
    };
    signals.add(
        Metric::Moves,
        moves(after).saturating_sub(moves(before)) as f64,
    );
    signals.add(
        Metric::Reclaims,
        reclaims.saturating_sub(reclaims_before) as f64,
    );
    signals.add(
        Metric::PodFailures,
        failed.saturating_sub(failed_before) as f64,
    );
    let done = after
        .monitor
        .progress
        .0
        .saturating_sub(before.monitor.progress.0);
    signals.add(Metric::RoutesDone, done as f64);
    signals
}

fn waited(from: u64, to: u64) -> f64 {
    if from == 0 {
        // A run from before the queue existed: its arrival is unknown.
        return 0.0;
    }
    to.saturating_sub(from) as f64
}

fn usage(
    run: &RunState,
    prices: &std::collections::BTreeMap<String, crate::capacity::cost::InstancePrice>,
) -> Totals {
    run.monitor.usage.summary(prices)
}

/// Reclaims and failed pods counted so far, over the run's Jobs.
fn pods(run: &RunState) -> (u64, u64) {
    run.monitor.usage.jobs.iter().fold((0, 0), |(r, f), job| {
        (
            r + u64::from(job.reclaims) + u64::from(job.excess),
            f + u64::from(job.failed.unwrap_or(0)),
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_catalog_names_each_metric_once_and_finds_it_by_name() {
        let mut names: Vec<&str> = Metric::ALL.iter().map(|m| m.name()).collect();
        let count = names.len();
        names.sort();
        names.dedup();
        assert_eq!(names.len(), count);
        for metric in Metric::ALL {
            assert_eq!(Metric::named(metric.name()), Some(*metric));
        }
        assert_eq!(Metric::named("Nope"), None);
    }

    #[test]
    fn zeros_are_not_sent_and_an_end_carries_its_words() {
        let mut s = Signals::default();
        s.add(Metric::RoutesDone, 0.0);
        s.add(Metric::GpuCost, f64::NAN);
        assert!(s.samples.is_empty());
        s.ended("FAILED", Some(reason::EVALUATION));
        assert_eq!(s.samples.len(), 2);
        assert_eq!((s.outcome, s.reason), (Some("FAILED"), Some("Evaluation")));
        let mut f = Signals::default();
        f.ended("FINISHED", None);
        assert_eq!(f.samples.len(), 1);
        assert_eq!(f.reason, None);
    }

    #[test]
    fn an_end_names_the_clusters_verdict_before_our_error_before_the_evaluation() {
        use crate::cluster::view::FailureKind;
        use crate::status::RecordStatus;
        let reason = |failure, caught| ending(RecordStatus::Failed, failure, caught).reason;
        let reclaims = Some(FailureKind::PlatformReclaims);
        assert_eq!(reason(reclaims, true), Some("PlatformReclaims"));
        assert_eq!(reason(None, true), Some(reason::PIPELINE));
        assert_eq!(reason(None, false), Some(reason::EVALUATION));
        let finished = ending(RecordStatus::Finished, None, false);
        assert_eq!(
            (finished.outcome, finished.reason),
            (Some("FINISHED"), None)
        );
    }

    #[test]
    fn a_round_says_what_changed_and_nothing_twice() {
        use crate::capacity::cost::{CapacityType, InstancePrice, JobEntry, NodeKind, UsageLine};
        use crate::run::state::{MonitorState, QueueState, RunState};
        let prices = [(
            "g5.12xlarge".to_owned(),
            InstancePrice {
                on_demand: 5.672,
                spot: 2.0,
            },
        )]
        .into_iter()
        .collect();
        let line = |capacity, held, run_again| UsageLine {
            kind: NodeKind {
                instance_type: "g5.12xlarge".into(),
                capacity,
            },
            held,
            run_again,
        };
        let before = RunState {
            jobs: 2,
            pairs: Vec::new(),
            repetitions: 1,
            launched_at: 1_000,
            recorder: true,
            monitor: MonitorState::starting(30, 0, 10, "exec-1", 0),
            queue: QueueState {
                admitted: true,
                ..QueueState::arriving(400)
            },
        };
        let mut after = before.clone();
        after.monitor.started_at = Some(1_300);
        after.monitor.progress = (3, 10);
        after.monitor.usage.lines = vec![
            line(CapacityType::Spot, 7_200, 100),
            line(CapacityType::OnDemand, 3_600, 0),
        ];
        after.monitor.usage.jobs = vec![
            JobEntry {
                reclaims: 1,
                moves: 1,
                failed: Some(2),
                ..JobEntry::default()
            },
            JobEntry::default(),
        ];
        let signals = of_round(&before, &after, &prices);
        let value = |m: Metric| {
            signals
                .samples
                .iter()
                .find(|s| s.metric == m)
                .map(|s| s.value)
        };
        assert_eq!(value(Metric::Starts), Some(1.0));
        assert_eq!(value(Metric::StartWait), Some(900.0));
        assert_eq!(value(Metric::GpuSecondsSpot), Some(7_200.0));
        assert_eq!(value(Metric::GpuSecondsOnDemand), Some(3_600.0));
        assert_eq!(value(Metric::GpuSecondsRunAgain), Some(100.0));
        // Two Spot GPU-hours at $2 an instance-hour of 4 GPUs, one on-demand at $5.672.
        let dollars = value(Metric::GpuCost).unwrap();
        assert!((dollars - (1.0 + 5.672 / 4.0)).abs() < 1e-9, "{dollars}");
        assert_eq!(value(Metric::Reclaims), Some(1.0));
        assert_eq!(value(Metric::Moves), Some(1.0));
        assert_eq!(value(Metric::PodFailures), Some(2.0));
        assert_eq!(value(Metric::RoutesDone), Some(3.0));
        // The next round with nothing new sends nothing.
        assert!(of_round(&after, &after, &prices).samples.is_empty());
        let admitted = admitted(400, 1_000);
        assert_eq!(admitted.samples.len(), 2);
        assert_eq!(admitted.samples[1].value, 600.0);
        assert_eq!(
            super::admitted(0, 1_000).samples.len(),
            1,
            "arrival unknown"
        );
    }
}
