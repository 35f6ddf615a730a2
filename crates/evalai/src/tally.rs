//! What one invocation asked of EvalAI: requests sent, 429s, and the shared budget's
//! refusals and waits, counted per task so functions running side by side (local mode) keep
//! their own.

use std::cell::RefCell;
use std::future::Future;

/// The counts of one invocation.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Tally {
    /// Requests sent (each attempt).
    pub requests: u64,
    /// Of those, answered 429.
    pub throttled: u64,
    /// Routine requests the budget refused (not sent).
    pub over_budget: u64,
    /// Urgent requests that waited for the budget's next window.
    pub budget_waits: u64,
}

tokio::task_local! {
    static TALLY: RefCell<Tally>;
}

/// Runs `work`, counting what it asked of EvalAI. Only requests made on this task count: work
/// spawned on another task is not seen.
pub async fn counted<F: Future>(work: F) -> (F::Output, Tally) {
    TALLY
        .scope(RefCell::new(Tally::default()), async {
            let output = work.await;
            (output, TALLY.with(|t| *t.borrow()))
        })
        .await
}

/// Counts on the current task's tally, if it keeps one.
pub(crate) fn note(count: impl FnOnce(&mut Tally)) {
    let _ = TALLY.try_with(|t| count(&mut t.borrow_mut()));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn each_task_counts_its_own_and_none_outside_a_scope() {
        note(|t| t.requests += 1);
        let (a, b) = tokio::join!(
            counted(async {
                note(|t| t.requests += 2);
                note(|t| t.throttled += 1);
            }),
            counted(async { note(|t| t.over_budget += 1) })
        );
        assert_eq!(
            a.1,
            Tally {
                requests: 2,
                throttled: 1,
                ..Tally::default()
            }
        );
        assert_eq!(b.1.over_budget, 1);
        assert_eq!(b.1.requests, 0);
    }
}
