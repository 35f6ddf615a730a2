//! What a local run ended as: everything the summary is made of, and whether it ended as its
//! scenario expects.

use std::path::Path;
use std::sync::atomic::Ordering;
use std::time::Instant;

use anyhow::Context;
use local_stack::Stack;

use crate::latency::Latency;
use crate::report::RunReport;
use crate::scenario::Findings;
use cli::{clean, outln};
use local_stepfunctions::ExecutionResult;
use serde_json::Value;

use super::*;

/// Everything the summary is made of, once the run ended.
pub(super) struct Ran<'a> {
    pub(super) args: &'a LocalRun,
    pub(super) stack: &'a Stack,
    pub(super) settings: &'a lb_domain::settings::Settings,
    pub(super) kubeconfig: &'a Path,
    pub(super) arrivals: &'a [(u64, u64)],
    /// The first submission's execution, followed to its end.
    pub(super) result: ExecutionResult,
    pub(super) chains: &'a [Vec<usize>],
    pub(super) reaped: Vec<Value>,
    pub(super) logs: &'a [String],
    pub(super) findings: Findings,
    /// How the executions matched their versions (the deploy and rollback scenarios).
    pub(super) release: Option<crate::release::ReleaseReport>,
    pub(super) watch: &'a Watch,
    /// The scenario did its act (or had none).
    pub(super) acted: bool,
    /// Messages S3's events sent, and the sweep's wakes.
    pub(super) wakes: (u64, u64),
    /// When the run started and when its executions ended.
    pub(super) times: (Instant, Instant),
    pub(super) expected: &'static str,
    /// Whether a finished run's recordings must pass the audit.
    pub(super) audit_passes: bool,
}

impl Ran<'_> {
    /// The submission on the fake EvalAI, and its status there (or on another EvalAI, asked
    /// with the client the functions use).
    pub(super) async fn on_evalai(
        &self,
        evalai: &lb_evalai::EvalAiClient,
    ) -> (Option<fake_evalai::SubmissionSnapshot>, String) {
        let submission = self.arrivals[0].0;
        let Some(fake) = &self.stack.fake_evalai else {
            let status = match evalai.submission(submission).await {
                Ok(s) => s.status.as_str().to_string(),
                Err(e) => format!("(unknown: {e})"),
            };
            return (None, status);
        };
        let on_fake = fake.submission(submission);
        let status = on_fake
            .as_ref()
            .map(|s| s.status.clone())
            .unwrap_or_default();
        (on_fake, status)
    }

    /// What the fake EvalAI saw: each submission's statuses and the requests (the queue
    /// report), and with `--latency` how long results took to reach it.
    pub(super) fn on_fake_evalai(
        &self,
    ) -> (Option<crate::queue_report::QueueReport>, Option<Latency>) {
        let Some(fake) = &self.stack.fake_evalai else {
            return (None, None);
        };
        let requests = fake.requests();
        let queue = crate::queue_report::report(&requests, self.arrivals, |id| {
            fake.submission(id)
                .map(|s| (s.status.clone(), s.files.stderr.clone()))
        });
        let latency = self.args.latency.then(|| {
            let log =
                std::fs::read_to_string(super::setup::record_log(self.stack)).unwrap_or_default();
            crate::latency::measure(&log, &requests, self.arrivals[0].0)
        });
        (Some(queue), latency)
    }

    /// What the first submission left: its Jobs, places, record.
    pub(super) async fn left_behind(&self) -> crate::report::LeftBehind {
        let (submission, team) = self.arrivals[0];
        let (sdk, leaderboard) = (&self.stack.sdk, self.args.leaderboard);
        let at = (team, submission);
        let mut left = left_behind(sdk, self.settings, leaderboard, self.kubeconfig, at).await;
        left.registry_digest = registry_digest(sdk, self.args.scenario.rehearsal().image()).await;
        left
    }

    /// The run's report: what EvalAI shows, what the run left, and whether it is as expected;
    /// with the latencies measured (`--latency`).
    pub(super) async fn report(
        self,
        evalai: &lb_evalai::EvalAiClient,
    ) -> (RunReport, Option<Latency>) {
        let (args, stack, submission) = (self.args, self.stack, self.arrivals[0].0);
        let many = self.arrivals.len() > 1;
        let (on_fake, status_on_evalai) = self.on_evalai(evalai).await;
        let bucket = settings_bucket(self.settings, args.leaderboard);
        let expected = self.expected;
        let (queue, latency) = self.on_fake_evalai();
        let left = self.left_behind().await;
        let reclaim = self.findings.reclaim;
        let upgrade = self.findings.upgrade;
        let consolidation = self.findings.consolidation;
        let ok = self.acted
            && (consolidation.as_ref())
                .is_none_or(crate::scenario::ConsolidationReport::as_expected)
            && upgrade
                .as_ref()
                .is_none_or(|u| u.from != u.to && u.new_node_joined)
            && reclaim
                .as_ref()
                .is_none_or(crate::reclaim::ReclaimReport::as_expected)
            && status_on_evalai == expected
            && audit_as_expected(expected, &left, self.audit_passes)
            && queue
                .as_ref()
                .is_none_or(|q| !many || q.all_ended(expected))
            && self
                .release
                .as_ref()
                .is_none_or(crate::release::ReleaseReport::as_expected);
        let result = &self.result;
        let (started, ended) = self.times;
        let report = RunReport {
            scenario: format!("{:?}", args.scenario),
            expected,
            ok,
            execution: result.status.as_str().to_string(),
            history_events: self.chains[0].iter().copied().max().unwrap_or_default(),
            executions: self.chains[0].len(),
            rounds: self.watch.rounds.load(Ordering::SeqCst),
            state_transitions: result
                .history
                .iter()
                .filter(|e| e.event_type.as_str().ends_with("StateEntered"))
                .count(),
            error: result
                .error
                .as_ref()
                .map(|e| format!("{e}: {}", result.cause.clone().unwrap_or_default())),
            caught_error: result
                .output
                .as_ref()
                .and_then(lb_domain::run::finalize::caught_error)
                .map(|c| clean(&c)),
            evalai_status: status_on_evalai,
            evalai_stderr: on_fake
                .as_ref()
                .and_then(|s| s.files.stderr.clone())
                .filter(|e| !e.trim().is_empty()),
            evalai_stdout: on_fake.as_ref().and_then(|s| s.files.stdout.clone()),
            scores: on_fake
                .as_ref()
                .and_then(|s| s.leaderboard.first())
                .map(|row| row.result.clone()),
            merged: merged_summary(&stack.sdk, &bucket, submission).await,
            simulator_gpus: simulator_gpus(&stack.sdk, &bucket, submission, args.workers).await,
            agent_gpus: agent_gpus(self.logs),
            reclaim,
            wake_messages: self.wakes.0,
            sweep_wakes: self.wakes.1,
            unreachable_rounds: self.watch.unreachable_rounds.load(Ordering::SeqCst),
            // Finalize deletes the Jobs in the foreground: when the execution ends, they are
            // gone.
            cancel_to_end_seconds: self
                .findings
                .cancelled_at
                .map(|at| ended.saturating_duration_since(at).as_secs_f64()),
            stages: stage_times(&result.history),
            results: format!("s3://{bucket}/{submission}/"),
            pod_logs: stack.workdir.path().join("pods"),
            seconds: started.elapsed().as_secs_f64(),
            queue,
            reaped: self.reaped,
            left_behind: left,
            release: self.release,
            upgrade,
            consolidation,
            metrics: Default::default(),
        };
        (report, latency)
    }
}

/// A finished run's recordings pass the audit unless the scenario tampers with them (judged
/// when its record could be read: another EvalAI's team may not be the one assumed).
pub(super) fn audit_as_expected(
    expected: &str,
    left: &crate::report::LeftBehind,
    passes: bool,
) -> bool {
    let audited = left.recordings.map(|(passed, needed)| passed == needed);
    expected != "finished" || left.record_status.is_none() || audited == Some(passes)
}

/// Prints and writes the report, keeps the stack up when asked: the exit code.
pub(super) async fn finish(
    args: &LocalRun,
    stack: &Stack,
    report: &RunReport,
    latency: Option<&Latency>,
    many: bool,
    kubeconfig: &Path,
) -> anyhow::Result<u8> {
    report.print(args, &stack.moto.endpoint(), latency, many);
    if let Some(path) = &args.report {
        std::fs::write(path, serde_json::to_string_pretty(report)?)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    if args.keep {
        outln!(
            "\nthe stack stays up (kubeconfig {}); Ctrl-C to stop",
            kubeconfig.display()
        );
        // `run` stops it on the signal.
        std::future::pending::<()>().await;
    }
    let expected = report.expected;
    if report.ok {
        outln!(
            "OK: the {:?} scenario ended {expected} as expected",
            args.scenario
        );
        Ok(0)
    } else {
        outln!(
            "UNEXPECTED: the {:?} scenario should end {expected}",
            args.scenario
        );
        Ok(1)
    }
}
