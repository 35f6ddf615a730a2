//! Bounded retries: exponential backoff with jitter, `Retry-After` honoured, a total budget.

use std::time::{Duration, Instant};

use crate::EvalAiError;

/// How hard the client tries before giving up (the state machine's own Retry comes on top).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RetryPolicy {
    /// Attempts per call, the first included.
    pub max_attempts: u32,
    /// First backoff after a 5xx or a connection failure.
    pub initial_backoff: Duration,
    /// Cap of one backoff.
    pub max_backoff: Duration,
    /// Total time one call may take, waits included; a `Retry-After` beyond it fails now.
    pub budget: Duration,
    /// TCP connect timeout.
    pub connect_timeout: Duration,
    /// Timeout of one request.
    pub request_timeout: Duration,
}

impl Default for RetryPolicy {
    fn default() -> Self {
        RetryPolicy {
            max_attempts: 5,
            initial_backoff: Duration::from_millis(500),
            max_backoff: Duration::from_secs(20),
            // Lambda timeouts are minutes; leave room for the rest of the handler.
            budget: Duration::from_secs(90),
            connect_timeout: Duration::from_secs(5),
            request_timeout: Duration::from_secs(20),
        }
    }
}

/// Why the last attempt failed.
#[derive(Debug, Clone)]
pub(crate) enum Reason {
    Throttled,
    Unavailable(String),
}

impl std::fmt::Display for Reason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Reason::Throttled => f.write_str("throttled (429)"),
            Reason::Unavailable(last) => f.write_str(last),
        }
    }
}

tokio::task_local! {
    /// When the invocation running this task must be done (a Lambda's deadline, less the time
    /// its handler needs to report).
    static DEADLINE: Instant;
}

/// Runs `work` with every EvalAI call inside it bounded by `deadline`: retries stop, and a
/// request's timeout shrinks, so that a client's own budget never outlasts the Lambda that
/// runs it (whose timeout would then be raised as `States.Timeout`, not as our error).
pub async fn within<F: std::future::Future>(deadline: Instant, work: F) -> F::Output {
    DEADLINE.scope(deadline, work).await
}

/// Time left before the task's deadline, if it has one.
pub(crate) fn remaining() -> Option<Duration> {
    DEADLINE
        .try_with(|d| d.saturating_duration_since(Instant::now()))
        .ok()
}

/// The attempts of one call.
pub(crate) struct Attempts {
    policy: RetryPolicy,
    started: Instant,
    made: u32,
}

impl Attempts {
    pub(crate) fn new(policy: &RetryPolicy) -> Self {
        let mut policy = *policy;
        if let Some(left) = remaining() {
            policy.budget = policy.budget.min(left);
        }
        Attempts {
            policy,
            started: Instant::now(),
            made: 1,
        }
    }

    /// Sleeps before the next attempt, or fails when the attempts or the budget are spent.
    pub(crate) async fn wait(
        &mut self,
        reason: Reason,
        after: Option<Duration>,
    ) -> Result<(), EvalAiError> {
        let exhausted = |reason: Reason, made: u32, elapsed: Duration| match reason {
            Reason::Throttled => EvalAiError::Throttled(elapsed),
            Reason::Unavailable(last) => EvalAiError::Unavailable {
                attempts: made,
                last,
            },
        };
        let delay = after.unwrap_or_else(|| self.backoff());
        let elapsed = self.started.elapsed();
        if self.made >= self.policy.max_attempts || elapsed + delay > self.policy.budget {
            return Err(exhausted(reason, self.made, elapsed));
        }
        tracing::debug!(
            attempt = self.made,
            delay_ms = delay.as_millis() as u64,
            "evalai retry"
        );
        tokio::time::sleep(delay).await;
        self.made += 1;
        Ok(())
    }

    /// Exponential backoff with "equal jitter": half fixed, half random, so clients that
    /// failed together do not come back together.
    fn backoff(&self) -> Duration {
        let exp = self
            .policy
            .initial_backoff
            .saturating_mul(1 << (self.made - 1).min(16));
        let capped = exp.min(self.policy.max_backoff);
        let half = capped / 2;
        half + half.mul_f64(jitter())
    }
}

/// A number in [0, 1) that differs between processes and calls; not for cryptography.
pub(crate) fn jitter() -> f64 {
    use std::hash::{BuildHasher, Hasher};
    let mut hasher = std::collections::hash_map::RandomState::new().build_hasher();
    hasher.write_u128(Instant::now().elapsed().as_nanos());
    (hasher.finish() >> 11) as f64 / (1u64 << 53) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backoff_grows_to_the_cap_and_stays_within_it() {
        let policy = RetryPolicy {
            initial_backoff: Duration::from_millis(100),
            max_backoff: Duration::from_millis(1000),
            ..RetryPolicy::default()
        };
        let mut attempts = Attempts::new(&policy);
        let mut previous_floor = Duration::ZERO;
        for made in 1..=8 {
            attempts.made = made;
            let delay = attempts.backoff();
            let full =
                (Duration::from_millis(100) * (1 << (made - 1))).min(Duration::from_millis(1000));
            assert!(
                delay >= full / 2 && delay <= full,
                "attempt {made}: {delay:?}"
            );
            assert!(full / 2 >= previous_floor);
            previous_floor = full / 2;
        }
    }

    #[tokio::test]
    async fn a_retry_after_beyond_the_budget_fails_at_once() {
        let policy = RetryPolicy {
            budget: Duration::from_secs(5),
            ..RetryPolicy::default()
        };
        let mut attempts = Attempts::new(&policy);
        let started = Instant::now();
        let err = attempts
            .wait(Reason::Throttled, Some(Duration::from_secs(30)))
            .await
            .unwrap_err();
        assert_eq!(err.name(), "EvalAiThrottled");
        assert!(started.elapsed() < Duration::from_secs(1));
    }

    #[tokio::test]
    async fn attempts_end_at_the_limit() {
        let policy = RetryPolicy {
            max_attempts: 3,
            initial_backoff: Duration::from_millis(1),
            ..RetryPolicy::default()
        };
        let mut attempts = Attempts::new(&policy);
        attempts
            .wait(Reason::Unavailable("500".into()), None)
            .await
            .unwrap();
        attempts
            .wait(Reason::Unavailable("500".into()), None)
            .await
            .unwrap();
        let err = attempts
            .wait(Reason::Unavailable("502".into()), None)
            .await
            .unwrap_err();
        assert_eq!(err.to_string(), "EvalAI unavailable after 3 attempts: 502");
    }
}
