//! When the Monitor runs: when something changed (a results file or marker in S3, a cancel
//! on EvalAI wakes the waiting execution), and otherwise after a safety-net interval that
//! grows with the evaluation's age; never sooner than [`MIN_ROUND_INTERVAL`] after the last
//! round. A quiet 72-hour evaluation fits one execution's history; a busy one continues as new
//! executions (`crate::run::history`).

use std::time::Duration;

/// The longest evaluation we run, not counting what reclaimed nodes cost it.
pub const MAX_EVALUATION: Duration = Duration::from_secs(72 * 3600);

/// The Jobs' own `activeDeadlineSeconds`, counted from their creation: a backstop a day past
/// [`MAX_EVALUATION`] for when the orchestration is gone. The Monitor extends it by the time
/// reclaims cost the evaluation.
pub const JOB_DEADLINE: Duration = Duration::from_secs(MAX_EVALUATION.as_secs() + 24 * 3600);

/// The first wait after launch: pods need time to pull images and start CARLA.
pub const FIRST_WAIT: Duration = Duration::from_secs(30);

/// The least time between two Monitor rounds, whatever wakes the loop: every round is
/// followed by a hold at least this long, so a pod that changes its files many times a second
/// costs at most a round each time this elapses (`lb_domain::run::history` bounds what those rounds
/// cost one execution).
pub const MIN_ROUND_INTERVAL: Duration = Duration::from_secs(10);

/// How long the Monitor waits when it could not read the wake count (it then polls instead).
pub const POLL_WITHOUT_WAKE: Duration = Duration::from_secs(60);

/// How often the Monitor reads the status on EvalAI itself, in case the cancel sweep (once
/// a minute, functions/sweep) is down: a cancel then still ends the run within the next round
/// after this.
pub const STATUS_FALLBACK: Duration = Duration::from_secs(30 * 60);

/// The safety net, `elapsed` after launch: the longest a wait lasts without a change. Short
/// while pods pull images and start (the failures only the cluster shows happen then: an
/// image that cannot be pulled, a pod that cannot be scheduled), long once the run is going
/// and every step of it writes to S3.
pub fn safety_net(elapsed: Duration) -> Duration {
    let secs = match elapsed.as_secs() {
        0..600 => 120,
        600..3_600 => 600,
        _ => 4 * 3600,
    };
    Duration::from_secs(secs)
}

/// How long a submission held by its team's cap waits before it asks for its turn again,
/// `waited` after it arrived: a safety net, since Finalize wakes the team's next submission
/// when it gives a place back. Five minutes (the participant's place note is refreshed at
/// that pace too), half an hour after the first day.
pub fn queue_wait(waited: Duration) -> Duration {
    Duration::from_secs(match waited.as_secs() {
        0..86_400 => 300,
        _ => 1_800,
    })
}

/// The Monitor rounds an evaluation of `length` takes when nothing ever wakes it.
pub fn quiet_rounds(length: Duration) -> u64 {
    let mut elapsed = FIRST_WAIT;
    let mut rounds = 1;
    while elapsed < length {
        elapsed += safety_net(elapsed);
        rounds += 1;
    }
    rounds
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_quiet_72_hour_evaluation_takes_a_few_dozen_rounds() {
        // 5 in the first 10 minutes, 5 until hour 1, 18 after, and the first.
        assert_eq!(quiet_rounds(MAX_EVALUATION), 29);
    }

    #[test]
    fn the_safety_net_never_shrinks_and_always_outlasts_a_partial_update() {
        let mut last = Duration::ZERO;
        for minute in 0..(72 * 60) {
            let interval = safety_net(Duration::from_secs(minute * 60));
            assert!(interval >= last);
            assert!(interval > crate::settings::PARTIAL_UPDATE_INTERVAL);
            last = interval;
        }
    }
}
