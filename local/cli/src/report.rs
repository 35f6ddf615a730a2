//! What a local run ended with: one report, printed as the run's summary for people and
//! written as JSON with `--report` for the tests and scripts that check a run.

use std::path::PathBuf;

use cli::outln;
use serde::Serialize;
use serde_json::Value;

use crate::latency::Latency;
use crate::queue_report::QueueReport;
use crate::run::LocalRun;

/// The run's outcome.
#[derive(Debug, Clone, Serialize)]
pub struct RunReport {
    /// The scenario rehearsed.
    pub scenario: String,
    /// The status on EvalAI it should end with.
    pub expected: &'static str,
    /// It did, and the scenario's act happened (every submission's, when several ran).
    pub ok: bool,
    /// The (first) execution's status.
    pub execution: String,
    /// The longest history among its executions.
    pub history_events: usize,
    /// Its executions: the first and those its run continued as.
    pub executions: usize,
    /// Monitor rounds of the whole run.
    pub rounds: u64,
    /// States entered over its executions (each a billed state transition).
    pub state_transitions: usize,
    /// The execution's own error and cause, when it failed.
    pub error: Option<String>,
    /// The error a Catch routed to Finalize (the execution succeeded, the submission failed).
    pub caught_error: Option<String>,
    /// The submission's status on EvalAI.
    pub evalai_status: String,
    /// What the participant reads as stderr, when there is any.
    pub evalai_stderr: Option<String>,
    /// What the participant reads as stdout.
    pub evalai_stdout: Option<String>,
    /// The leaderboard row's scores.
    pub scores: Option<Value>,
    /// The merged results file in numbers.
    pub merged: Option<Merged>,
    /// The GPU index each attempt of each pair's simulator rendered on, by pair (from its log).
    pub simulator_gpus: std::collections::BTreeMap<u32, Vec<u32>>,
    /// The GPU each attempt of each pair was given (its agent's), by pair (from its log).
    pub agent_gpus: std::collections::BTreeMap<u32, Vec<u32>>,
    /// The spot scenario's reclaim: what was evicted and what the Jobs made of it.
    pub reclaim: Option<crate::reclaim::ReclaimReport>,
    /// Results files and markers S3's events brought to the wake function.
    pub wake_messages: u64,
    /// Times the cancel sweep woke the execution.
    pub sweep_wakes: u64,
    /// Monitor rounds that found the cluster's API out of reach.
    pub unreachable_rounds: u64,
    /// Seconds from the participant's cancel to the Jobs gone (the cancel scenario).
    pub cancel_to_end_seconds: Option<f64>,
    /// Seconds spent in each state, in order.
    pub stages: Vec<(String, f64)>,
    /// Where the results are on moto.
    pub results: String,
    /// Where the pods' logs are.
    pub pod_logs: PathBuf,
    /// The whole run's seconds.
    pub seconds: f64,
    /// What the fake EvalAI saw of every submission (none against another EvalAI).
    pub queue: Option<QueueReport>,
    /// The reaper's answers for the executions that ended without Finalize.
    pub reaped: Vec<Value>,
    /// What the (first) run left once everything ended.
    pub left_behind: LeftBehind,
    /// The versions the executions ran, when the alias moved during the run.
    pub release: Option<crate::release::ReleaseReport>,
    /// The control plane's upgrade (the upgrade scenario).
    pub upgrade: Option<crate::scenario::UpgradeReport>,
    /// The nodes drained and the pairs moved (the consolidate scenario).
    pub consolidation: Option<crate::scenario::ConsolidationReport>,
    /// The metrics the functions wrote.
    pub metrics: crate::emf::EmfReport,
}

/// What a run left behind it.
#[derive(Debug, Clone, Default, Serialize)]
pub struct LeftBehind {
    /// Its Jobs still on the cluster (`None`: the cluster was not read).
    pub jobs: Option<usize>,
    /// Places held in its leaderboard's queue, every team's.
    pub places_held: Option<usize>,
    /// Its record's status.
    pub record_status: Option<String>,
    /// Its record says the failure was the platform's own (`failed_by`).
    pub failed_by_platform: bool,
    /// The digest the participant's tag names in the registry (the Jobs run it).
    pub registry_digest: Option<String>,
    /// Its record's routes whose CARLA recording passed the audit, and the routes that need
    /// one (FINISHED only).
    pub recordings: Option<(u64, u64)>,
    /// The routes whose recording did not pass, each with why (the first few).
    pub recordings_failed: Vec<String>,
    /// Its record's GPU usage: `gpu_seconds`, `spot`, `run_again`, `cost_usd`.
    pub usage: Option<Value>,
    /// Objects under its `containers-status/` in S3: the markers logcopy let through.
    pub status_objects: Option<usize>,
}

/// `agent_results.json` in numbers.
#[derive(Debug, Clone, Serialize)]
pub struct Merged {
    /// Its records.
    pub records: usize,
    /// The distinct routes they cover.
    pub routes: usize,
    /// Records per route, route by route.
    pub per_route: Vec<usize>,
}

impl Merged {
    /// `40 records over 8 routes, 5 per route`.
    fn line(&self) -> String {
        let mut counts = self.per_route.clone();
        counts.sort_unstable();
        counts.dedup();
        let each = match counts.as_slice() {
            [one] => format!("{one} per route"),
            many => format!("{many:?} per route"),
        };
        format!(
            "{} records over {} routes, {each}",
            self.records, self.routes
        )
    }
}

impl RunReport {
    /// The summary a person reads at the end of the run.
    pub fn print(&self, args: &LocalRun, moto: &str, latency: Option<&Latency>, many: bool) {
        self.print_outcome(args);
        self.print_participant_view();
        self.print_costs(args, latency);
        outln!("time per stage");
        for (stage, seconds) in &self.stages {
            outln!("  {stage:<12} {seconds:>7.1}s");
        }
        self.metrics.print();
        outln!("results        {} on moto {moto}", self.results);
        outln!("pod logs       {}", self.pod_logs.display());
        if !args.keep {
            outln!("               (the stack and these go away on exit: --keep to look at them)");
        }
        outln!("total          {:.1}s", self.seconds);
        if let (true, Some(queue)) = (many, &self.queue) {
            crate::queue_report::print(queue);
        }
    }

    /// How the execution ended, what EvalAI says, and what woke it.
    fn print_outcome(&self, args: &LocalRun) {
        outln!();
        if self.executions > 1 {
            outln!(
                "execution      {} after {} executions ({} rounds, at most {} history events each)",
                self.execution,
                self.executions,
                self.rounds,
                self.history_events
            );
        } else {
            outln!(
                "execution      {} ({} history events)",
                self.execution,
                self.history_events
            );
        }
        if let Some(error) = &self.error {
            outln!("error          {error}");
        }
        if let Some(caught) = &self.caught_error {
            outln!("caught error   {caught}");
        }
        let unaudited = self
            .left_behind
            .recordings
            .is_some_and(|(passed, expected)| passed < expected);
        outln!(
            "EvalAI status  {}{}",
            self.evalai_status,
            if unaudited {
                " (FINISHED*: not every route's recording passed the audit)"
            } else {
                ""
            }
        );
        if let Some((passed, expected)) = self.left_behind.recordings {
            outln!("recordings     {passed}/{expected} passed the audit");
            for failure in &self.left_behind.recordings_failed {
                outln!("               {failure}");
            }
        }
        for answer in &self.reaped {
            outln!("reaper         {answer}");
        }
        self.print_changes();
        if let Some(queue) = &self.queue {
            // Every request took from the shared budget first: EvalAI never had to throttle.
            outln!(
                "EvalAI calls   {} requests through the shared budget, {} throttled (429)",
                queue.requests,
                queue.throttled
            );
        }
        outln!(
            "S3 events      {} results files and markers seen by the wake function",
            self.wake_messages
        );
        outln!(
            "cancel sweep   woke the execution {} times",
            self.sweep_wakes
        );
        if let Some(took) = self.cancel_to_end_seconds {
            outln!(
                "cancel to end  {took:.1}s from the participant's cancel to the Jobs gone (time scale {})",
                args.time_scale
            );
        }
    }

    /// What changed under the run: the control plane's upgrade, the alias's move.
    fn print_changes(&self) {
        if let Some(upgrade) = &self.upgrade {
            outln!(
                "upgrade        control plane {} -> {} (the API out for {:.1} s); the node group's new node joined: {}",
                upgrade.from,
                upgrade.to,
                upgrade.unavailable_seconds,
                upgrade.new_node_joined
            );
        }
        if let Some(release) = &self.release {
            let ran: Vec<String> = release
                .ran
                .iter()
                .map(|v| v.map_or("mixed".into(), |v| format!("version {v}")))
                .collect();
            outln!(
                "release        {}; the submissions ran {} (expected {:?})",
                release.change,
                ran.join(", "),
                release.expected
            );
        }
    }

    /// What the participant reads: on a failure the reason and the end of their agent's
    /// output, and the head of the summary beside it (which routes count); the scores.
    fn print_participant_view(&self) {
        if let Some(stderr) = &self.evalai_stderr {
            outln!("EvalAI stderr");
            for line in stderr.lines() {
                outln!("  | {line}");
            }
            if let Some(stdout) = &self.evalai_stdout {
                outln!("EvalAI stdout");
                for line in stdout.lines().take(3) {
                    outln!("  | {line}");
                }
            }
        }
        if let Some(scores) = &self.scores {
            outln!("scores         {scores}");
        }
        if let Some(merged) = &self.merged {
            outln!("merged         {}", merged.line());
        }
    }

    /// GPU time and its price, the reclaim, and the latencies (`--latency`).
    fn print_costs(&self, args: &LocalRun, latency: Option<&Latency>) {
        if let Some(usage) = &self.left_behind.usage {
            outln!(
                "GPUs           {} GPU-seconds ({} on Spot, {} run again), about ${} (time scale {}); orchestration about ${} ({} state transitions)",
                usage["gpu_seconds"],
                usage["spot"],
                usage["run_again"],
                usage["cost_usd"],
                args.time_scale,
                usage["orchestration_usd"],
                usage["state_transitions"],
            );
        }
        if let Some(c) = &self.consolidation {
            outln!(
                "consolidation  drained {:?}; {} pod(s) moved, {} move(s) in the ledger; retries used {}; {} route(s) run again ({} interrupted, {} resumed behind them); the pairs ended on {:?}",
                c.drained,
                c.reclaim.evicted.len(),
                c.moves,
                c.reclaim.retries_used,
                c.reclaim.routes_run_again,
                c.reclaim.interrupted.len(),
                c.reclaim.resumed_behind.len(),
                c.ended_on
            );
        }
        if let Some(r) = &self.reclaim {
            outln!(
                "reclaim        {} pod(s) evicted, {} with DisruptionTarget; retries used {}; {} route(s) run again ({} interrupted, {} resumed behind them)",
                r.evicted.len(),
                r.disrupted.len(),
                r.retries_used,
                r.routes_run_again,
                r.interrupted.len(),
                r.resumed_behind.len()
            );
        }
        if let Some(m) = latency {
            let secs = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.1}s"));
            outln!(
                "latency        record -> partial update: p50 {}, p99 {}, max {} ({} records, {} updates, {} only in the final update); last write -> final status {}",
                secs(m.quantile(0.5)),
                secs(m.quantile(0.99)),
                secs(m.record_delays.last().copied()),
                m.record_delays.len() + m.undelivered,
                m.updates,
                m.undelivered,
                secs(m.final_delay)
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_merged_line_says_records_routes_and_their_repetitions() {
        let merged = |per_route: Vec<usize>| Merged {
            records: per_route.iter().sum(),
            routes: per_route.len(),
            per_route,
        };
        assert_eq!(
            merged(vec![5; 8]).line(),
            "40 records over 8 routes, 5 per route"
        );
        assert_eq!(
            merged(vec![1, 2, 1]).line(),
            "4 records over 3 routes, [1, 2] per route"
        );
    }
}
