//! An operator stops the execution (StopExecution) after its first Monitor round: the reaper
//! (Finalize, on Step Functions' status-change event) deletes the Jobs, gives the team's place
//! back, tells EvalAI `failed` with the reason and writes the final record.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use local_stepfunctions::Executor;

use super::Rehearsal;

/// An operator's StopExecution.
pub struct Stop;

impl Rehearsal for Stop {
    fn expected(&self) -> &'static str {
        "failed"
    }

    /// Stops the execution once its first Monitor round began.
    fn started(
        &self,
        executor: &Executor,
        arn: &str,
        rounds: &Arc<AtomicU64>,
        acted: &Arc<AtomicBool>,
    ) {
        let (executor, arn, rounds, acted) = (
            executor.clone(),
            arn.to_string(),
            rounds.clone(),
            acted.clone(),
        );
        tokio::spawn(async move {
            while rounds.load(Ordering::SeqCst) < 1 {
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            // After the round: the run has Jobs and its team a place.
            tokio::time::sleep(Duration::from_secs(2)).await;
            if executor.stop(&arn) {
                acted.store(true, Ordering::SeqCst);
            }
        });
    }
}
