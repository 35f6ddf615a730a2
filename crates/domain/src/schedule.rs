//! When the Monitor runs: an interval that grows with the evaluation's age, so a 72-hour
//! evaluation stays well inside Step Functions' 25,000-event history limit.
//!
//! Each Wait -> Monitor -> Choice round costs a fixed number of history events (counted from
//! the state machine in the pipeline's tests); the schedule keeps the rounds of the longest
//! evaluation under [`ROUNDS_BUDGET`].

use std::time::Duration;

/// The longest evaluation we run; the Jobs' `activeDeadlineSeconds` matches it.
pub const MAX_EVALUATION: Duration = Duration::from_secs(72 * 3600);

/// Monitor rounds a [`MAX_EVALUATION`] run may take (5,000 events at 9 per round, minus room
/// for intake, launch, retries and finalize).
pub const ROUNDS_BUDGET: u64 = 520;

/// The first wait after launch: pods need time to pull images and start CARLA.
pub const FIRST_WAIT: Duration = Duration::from_secs(30);

/// The wait before the next Monitor round, `elapsed` after launch: every minute in the first
/// hour (participants watch the start), every 5 minutes until hour 6, every 10 minutes after.
pub fn monitor_interval(elapsed: Duration) -> Duration {
    let secs = match elapsed.as_secs() {
        0..3_600 => 60,
        3_600..21_600 => 300,
        _ => 600,
    };
    Duration::from_secs(secs)
}

/// The Monitor rounds an evaluation of `length` takes under [`monitor_interval`].
pub fn rounds_for(length: Duration) -> u64 {
    let mut elapsed = FIRST_WAIT;
    let mut rounds = 1;
    while elapsed < length {
        elapsed += monitor_interval(elapsed);
        rounds += 1;
    }
    rounds
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_72_hour_evaluation_fits_the_rounds_budget() {
        let rounds = rounds_for(MAX_EVALUATION);
        // 60 rounds in hour 1, 60 until hour 6, 396 after.
        assert_eq!(rounds, 517);
        assert!(rounds <= ROUNDS_BUDGET);
    }

    #[test]
    fn the_interval_never_shrinks() {
        let mut last = Duration::ZERO;
        for minute in 0..(72 * 60) {
            let interval = monitor_interval(Duration::from_secs(minute * 60));
            assert!(interval >= last);
            last = interval;
        }
    }
}
