//! One EvalAI budget for every submission in flight: the host token's requests a minute,
//! shared by all functions, with final updates and cancels ahead of partial updates.
//!
//! EvalAI throttles a user at 60 requests in any sliding 60 s (reference §1, DRF's
//! `UserRateThrottle`, counted across all endpoints). The budget cuts time into fixed windows
//! of a fifth of that period and grants at most [`BudgetPolicy::per_window`] requests in each:
//! a sliding period overlaps at most six windows, so it never holds more than six windows'
//! worth, kept at 90% of the limit for the requests' own jitter in flight. A counter per window
//! is one conditional increment (no read, no lock), so two functions racing can never exceed
//! it. [`Priority::Routine`] requests (partial updates, fallback status reads) stop at a lower
//! mark, leaving the rest of each window to [`Priority::Urgent`] ones (final updates, the
//! cancel sweep, a submission's start). An urgent request finding its window full books a
//! place in the first later window with room, and that booking counts against the routine
//! mark there too: while urgent requests queue, routine ones yield entirely.

use std::future::Future;
use std::pin::Pin;
use std::time::Duration;

/// Who asks, and so who yields when the budget is short.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Priority {
    /// Must happen: a start, a final update, a cancel. Waits for the next window when full.
    Urgent,
    /// Can wait for the next round: partial updates and fallback status reads. Skipped when
    /// the window's routine share is spent.
    Routine,
}

/// What the budget said to one request.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Admission {
    /// Send it.
    Granted,
    /// A place is booked in a later window: send it after `wait` (urgent requests only).
    Booked {
        /// Until the booked window opens (plus a spread within it).
        wait: Duration,
    },
    /// This window has no room for the priority; the next one opens in `retry_in`.
    Full {
        /// Until the next window.
        retry_in: Duration,
    },
    /// The budget's store could not be asked (the request then goes anyway: EvalAI's own 429
    /// with `Retry-After` stays the second line).
    Unavailable(String),
}

/// A boxed future, so the client can hold any budget behind one pointer.
pub type AdmissionFuture<'a> = Pin<Box<dyn Future<Output = Admission> + Send + 'a>>;

/// A shared request budget (DynamoDB in the deployment: `lb_aws::budget`).
pub trait Budget: Send + Sync + std::fmt::Debug {
    /// Takes `places` requests at `priority` (a call's requests taken at once: one round trip
    /// to the budget instead of one before each), granted only if the window still has room
    /// for `headroom` requests (these and those the same call will need right after them, at
    /// least `places`), so a read is not spent on a write that could not follow.
    fn take(&self, priority: Priority, places: u32, headroom: u32) -> AdmissionFuture<'_>;
}

/// The window arithmetic, from EvalAI's limit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BudgetPolicy {
    /// Length of one window.
    pub window: Duration,
    /// Requests granted per window.
    pub per_window: u32,
    /// Of those, how many routine requests may take.
    pub routine_per_window: u32,
}

/// Windows per throttle period: a period then overlaps at most this many plus one.
const WINDOWS_PER_PERIOD: u32 = 5;

impl BudgetPolicy {
    /// For a limit of `requests` in any sliding `period` (EvalAI: 60 in 60 s), or `None` when
    /// the limit is too small to share (fewer than 14 requests).
    pub fn for_limit(requests: u32, period: Duration) -> Option<BudgetPolicy> {
        // A sliding period meets at most WINDOWS_PER_PERIOD + 1 fixed windows.
        let per_window = requests.saturating_mul(9) / 10 / (WINDOWS_PER_PERIOD + 1);
        if per_window < 2 || period.is_zero() {
            return None;
        }
        let reserve = (per_window / 4).max(1);
        Some(BudgetPolicy {
            window: period / WINDOWS_PER_PERIOD,
            per_window,
            routine_per_window: per_window - reserve,
        })
    }

    /// EvalAI's: 60 requests a minute.
    pub fn evalai(requests_per_minute: u32) -> Option<BudgetPolicy> {
        Self::for_limit(requests_per_minute, Duration::from_secs(60))
    }

    /// How far ahead an urgent request may book (windows): beyond it, it waits and asks again.
    pub const BOOK_AHEAD: u64 = 25;

    /// The window `at_ms` (milliseconds since the epoch) falls in, and the time until the next.
    pub fn window_of(&self, at_ms: u64) -> (u64, Duration) {
        let length = (self.window.as_millis() as u64).max(1);
        let index = at_ms / length;
        let next = (index + 1) * length;
        (index, Duration::from_millis(next - at_ms))
    }

    /// When window `index` starts, in epoch milliseconds.
    pub fn window_start(&self, index: u64) -> u64 {
        index * (self.window.as_millis() as u64).max(1)
    }

    /// The most requests of `priority` a window holds.
    pub fn limit(&self, priority: Priority) -> u32 {
        match priority {
            Priority::Urgent => self.per_window,
            Priority::Routine => self.routine_per_window,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn evalai_limit_gives_nine_per_twelve_seconds_with_two_kept_for_urgent_requests() {
        let p = BudgetPolicy::evalai(60).unwrap();
        assert_eq!(p.window, Duration::from_secs(12));
        assert_eq!(p.per_window, 9);
        assert_eq!(p.routine_per_window, 7);
        assert_eq!(p.limit(Priority::Urgent), 9);
        assert_eq!(p.limit(Priority::Routine), 7);
        assert!(BudgetPolicy::evalai(13).is_none());
        assert_eq!(
            p.window_of(25_000),
            (2, Duration::from_millis(36_000 - 25_000))
        );
    }

    #[test]
    fn no_sliding_period_ever_holds_more_than_the_limit() {
        // Whatever a period's start, it meets so few windows that all of them full stay
        // within the limit.
        for requests in [14, 30, 60, 61, 100, 600] {
            for period_ms in [1_000u64, 6_000, 60_000] {
                let period = Duration::from_millis(period_ms);
                let p = BudgetPolicy::for_limit(requests, period).unwrap();
                let w = p.window.as_millis() as u64;
                for start in (0..5 * period_ms).step_by(7) {
                    let end = start + period_ms - 1;
                    let windows = end / w - start / w + 1;
                    let most = windows * u64::from(p.per_window);
                    assert!(
                        most <= u64::from(requests),
                        "{requests} per {period_ms} ms: {windows} windows of {} from {start}",
                        p.per_window
                    );
                }
                assert!(p.routine_per_window < p.per_window);
            }
        }
    }
}
