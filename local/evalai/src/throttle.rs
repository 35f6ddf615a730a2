//! DRF `UserRateThrottle`: a sliding window of request times per user, shared by all endpoints.

use std::collections::{HashMap, VecDeque};
use std::time::{Duration, Instant};

/// Per-user sliding-window throttle.
#[derive(Debug)]
pub(crate) struct Throttle {
    limit: usize,
    window: Duration,
    history: HashMap<u64, VecDeque<Instant>>,
}

impl Throttle {
    pub fn new(limit: u32, window_secs: u64) -> Throttle {
        Throttle {
            limit: limit as usize,
            window: Duration::from_secs(window_secs),
            history: HashMap::new(),
        }
    }

    /// Forgets every request: what a minute without requests would do to every window.
    pub fn reset(&mut self) {
        self.history.clear();
    }

    /// `allow_request`: records the request, or returns the whole seconds to wait
    /// (DRF's `wait()`, rounded up) without recording it.
    pub fn check(&mut self, user: u64, now: Instant) -> Result<(), u64> {
        let history = self.history.entry(user).or_default();
        // Newest first, as DRF keeps it; drop what fell out of the window.
        while let Some(oldest) = history.back() {
            if now.duration_since(*oldest) >= self.window {
                history.pop_back();
            } else {
                break;
            }
        }
        if history.len() >= self.limit {
            let oldest = history.back().copied().unwrap_or(now);
            let remaining = self.window.saturating_sub(now.duration_since(oldest));
            let available = self.limit as i64 - history.len() as i64 + 1;
            let wait = if available <= 0 {
                remaining.as_secs_f64()
            } else {
                remaining.as_secs_f64() / available as f64
            };
            return Err((wait.ceil() as u64).max(1));
        }
        history.push_front(now);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_window_slides_and_wait_is_rounded_up() {
        let mut t = Throttle::new(2, 60);
        let start = Instant::now();
        assert!(t.check(7, start).is_ok());
        assert!(t.check(7, start + Duration::from_millis(500)).is_ok());
        assert_eq!(t.check(7, start + Duration::from_millis(1500)), Err(59));
        assert!(
            t.check(8, start).is_ok(),
            "other users have their own window"
        );
        assert!(t.check(7, start + Duration::from_secs(60)).is_ok());
    }
}
