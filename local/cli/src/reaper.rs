//! The reaper as the deployment runs it: Step Functions' status-change events go to Finalize
//! as an asynchronous invocation (an attempt that fails runs again after Lambda's waits, then
//! the event is dropped), and a scheduled pass over the held places catches what the events
//! left (`infra/app.yaml`: `ReaperRule`, `FinalizeFunction`'s `EventInvokeConfig`,
//! `ReaperSchedule`). Waits and period are scaled like the state machine's.

use std::collections::BTreeSet;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use cli::outln;
use lb_infra::template::{Template, TemplateError};
use local_stack::events::{async_retry_waits, schedule_period, LateCallbacks};
use local_stepfunctions::Executor;
use serde_json::{json, Value};
use tokio::sync::mpsc::{unbounded_channel, UnboundedReceiver, UnboundedSender};

/// Finalize, as the reaper calls it.
type Finalize = Arc<finalize::Deps<LateCallbacks>>;

/// What the reaper did: each delivery's and each pass's answer, and whether it settled an
/// execution (its ARN).
struct Answer {
    settled: Vec<String>,
    report: Value,
}

/// The reaper's deliveries and passes, and what they answered.
pub struct Reaper {
    answers: UnboundedReceiver<Answer>,
    tx: UnboundedSender<Answer>,
    finalize: Finalize,
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

impl Drop for Reaper {
    fn drop(&mut self) {
        for task in &self.tasks {
            task.abort();
        }
    }
}

impl Reaper {
    /// Delivers every execution's status change to Finalize (which leaves alone those that
    /// reached it), retrying a failed attempt after Lambda's waits as `FinalizeFunction`
    /// allows (times `time_scale`); `failed_attempts` counts the attempts that failed (the
    /// scenarios watch it).
    pub fn spawn(
        executor: &Executor,
        finalize: Finalize,
        (template, time_scale): (&Template, f64),
        failed_attempts: Arc<AtomicU64>,
    ) -> Result<Reaper, TemplateError> {
        let waits: Vec<Duration> = async_retry_waits(template, "FinalizeFunction")?
            .iter()
            .map(|w| w.mul_f64(time_scale))
            .collect();
        let (tx, answers) = unbounded_channel();
        let mut changes = executor.status_changes();
        let (deliver, failed) = ((finalize.clone(), tx.clone()), failed_attempts.clone());
        let events = tokio::spawn(async move {
            while let Some(event) = changes.recv().await {
                let status = event["detail"]["status"]
                    .as_str()
                    .and_then(|s| s.parse().ok());
                if !status.is_some_and(|s| lb_domain::run::reaper::REAPED_STATUSES.contains(&s)) {
                    continue;
                }
                let (finalize, tx, failed) = (deliver.0.clone(), deliver.1.clone(), failed.clone());
                let waits = waits.clone();
                tokio::spawn(async move {
                    let _ = tx.send(deliver_event(&finalize, event, &waits, &failed).await);
                });
            }
        });
        Ok(Reaper {
            answers,
            tx,
            finalize,
            tasks: vec![events],
        })
    }

    /// Runs the scheduled pass over the held places of `execution`'s state machine at
    /// `ReaperSchedule`'s period (times `time_scale`).
    pub fn schedule(
        &mut self,
        (template, time_scale): (&Template, f64),
        execution: &str,
    ) -> Result<(), TemplateError> {
        let period = schedule_period(template, "ReaperSchedule")?.mul_f64(time_scale);
        // `...:execution:<machine>:<name>` -> `...:stateMachine:<machine>`
        let head = execution
            .rsplit_once(':')
            .map_or(execution, |(head, _)| head);
        let state_machine = head.replacen(":execution:", ":stateMachine:", 1);
        let (finalize, tx) = (self.finalize.clone(), self.tx.clone());
        self.tasks.push(tokio::spawn(async move {
            let mut ticks = tokio::time::interval(period);
            ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            let input = json!({"reconcile": {"state_machine": state_machine}});
            loop {
                ticks.tick().await;
                match lb_pipeline::serve::call(&*finalize, input.clone()).await {
                    Ok(Value::Array(reaped)) if !reaped.is_empty() => {
                        let settled = reaped
                            .iter()
                            .filter_map(|r| r["execution"].as_str().map(str::to_owned))
                            .collect();
                        outln!(
                            "           the reaper's scheduled pass settled {} execution(s)",
                            reaped.len()
                        );
                        let report = json!({"via": "scheduled pass", "answer": reaped});
                        let _ = tx.send(Answer { settled, report });
                    }
                    Ok(_) => {}
                    Err(e) => {
                        tracing::warn!(error = %e.chain(), "the reaper's pass did not finish")
                    }
                }
            }
        }));
        Ok(())
    }

    /// What answered for the first `count` executions that ended without Finalize, once each
    /// is settled by a delivery or a pass (bounded: one never settled is reported as such).
    pub async fn collect(mut self, count: usize) -> Vec<Value> {
        let mut reports = Vec::new();
        let mut settled = BTreeSet::new();
        while settled.len() < count {
            match tokio::time::timeout(Duration::from_secs(600), self.answers.recv()).await {
                Ok(Some(answer)) => {
                    settled.extend(answer.settled);
                    reports.push(answer.report);
                }
                Ok(None) | Err(_) => {
                    reports.push(json!({"error": "the reaper did not settle every execution"}));
                    break;
                }
            }
        }
        reports
    }
}

/// One status change, delivered as Lambda runs an asynchronous invocation: again after each
/// wait while it fails, then dropped.
async fn deliver_event(
    finalize: &Finalize,
    event: Value,
    waits: &[Duration],
    failed: &AtomicU64,
) -> Answer {
    let execution = event["detail"]["executionArn"]
        .as_str()
        .unwrap_or_default()
        .to_owned();
    let mut errors = Vec::new();
    for attempt in 0..=waits.len() {
        match lb_pipeline::serve::call(&**finalize, event.clone()).await {
            Ok(answer) => {
                let report = json!({"via": "event", "attempts": attempt + 1, "answer": answer});
                return Answer {
                    settled: vec![execution],
                    report,
                };
            }
            Err(e) => {
                failed.fetch_add(1, Ordering::SeqCst);
                // NB: an unavailable service's error carries its error page: its start is enough.
                let error: String = e.chain().chars().take(160).collect();
                outln!(
                    "           the reaper's attempt {} failed: {error}",
                    attempt + 1
                );
                errors.push(error);
            }
        }
        if let Some(wait) = waits.get(attempt) {
            tokio::time::sleep(*wait).await;
        }
    }
    let report =
        json!({"via": "event", "attempts": waits.len() + 1, "dropped": true, "errors": errors});
    Answer {
        settled: Vec::new(),
        report,
    }
}
