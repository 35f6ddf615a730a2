//! EvalAI fails from the moment the Monitor finds the run finished: Finalize cannot post, an
//! operator stops the execution, and the reaper's Finalize fails too at every attempt of the
//! status-change event, which is then dropped. Once EvalAI is back, the reaper's scheduled
//! pass ends the run: the Jobs gone, the team's place given back, EvalAI told `failed` (the
//! operator's stop) and the record written.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use cli::outln;
use local_stepfunctions::{EventType, Executor, HistoryEvent};
use serde_json::Value;

use super::{admin_request, Begin, Rehearsal};

/// Attempts of one status-change event: the first and Lambda's two retries.
const ATTEMPTS: u64 = 3;

/// EvalAI down through Finalize and the reaper's deliveries.
#[derive(Default)]
pub struct EvalAiDown {
    /// The fake EvalAI's address, and the reaper's failed attempts.
    at: OnceLock<(String, Arc<AtomicU64>)>,
    /// The Monitor found the run finished: Finalize comes next.
    finished: Arc<AtomicBool>,
}

impl Rehearsal for EvalAiDown {
    fn expected(&self) -> &'static str {
        "failed"
    }

    fn acts(&self) -> bool {
        true
    }

    fn begin(&self, run: &Begin) {
        if let Some(url) = &run.fake_evalai {
            let _ = self.at.set((url.clone(), run.reaper_failures.clone()));
        }
    }

    fn round_ended(&self, monitor: &Value) {
        if monitor["state"] == "finished" {
            self.finished.store(true, Ordering::SeqCst);
        }
    }

    fn started(
        &self,
        executor: &Executor,
        arn: &str,
        _rounds: &Arc<AtomicU64>,
        acted: &Arc<AtomicBool>,
    ) {
        let Some((url, failures)) = self.at.get().cloned() else {
            return;
        };
        let (executor, arn, acted) = (executor.clone(), arn.to_string(), acted.clone());
        let finished = self.finished.clone();
        tokio::spawn(async move {
            wait_for(|| finished.load(Ordering::SeqCst)).await;
            let failures_of_tasks = || {
                executor.history_of(&arn).map_or(0, |h| {
                    let failed =
                        |e: &&HistoryEvent| e.event_type == EventType::LambdaFunctionFailed;
                    h.iter().filter(failed).count()
                })
            };
            let before = failures_of_tasks();
            set_down(&url, true).await;
            // Finalize tried and failed; the operator, alarmed, stops the execution.
            wait_for(|| failures_of_tasks() > before).await;
            if executor.stop(&arn) {
                outln!("           scenario: Finalize cannot reach EvalAI; an operator stops the execution");
                acted.store(true, Ordering::SeqCst);
            }
            wait_for(|| failures.load(Ordering::SeqCst) >= ATTEMPTS).await;
            set_down(&url, false).await;
        });
    }
}

/// Polls `done` until it holds (bounded by the run's own timeout).
async fn wait_for(done: impl Fn() -> bool) {
    while !done() {
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Every EvalAI request answered with an HTML 500, or none.
async fn set_down(url: &str, down: bool) {
    let rate = if down { 1.0 } else { 0.0 };
    let body = format!("{{\"error_500_rate\": {rate}}}");
    let status = admin_request("PUT", url, "/_admin/faults", &body)
        .await
        .map(|(status, _)| status);
    let what = if down { "down" } else { "back" };
    outln!("           scenario: EvalAI is {what} ({status:?})");
}
