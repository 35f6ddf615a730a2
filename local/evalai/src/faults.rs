//! Fault injection for `/api/` routes: HTML 500s, 429s, slow answers, from a seeded PRNG.

use serde::{Deserialize, Serialize};

/// Fault rates (each in `0.0..=1.0`) and their parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Faults {
    /// Share of requests answered with an HTML 500 before anything happens.
    #[serde(default)]
    pub error_500_rate: f64,
    /// Share of requests processed normally whose answer is then replaced by an HTML 500
    /// (EvalAI can fail after it stored the status).
    #[serde(default)]
    pub error_500_after_write_rate: f64,
    /// Share of requests answered 429 with `Retry-After` (not counted by the throttle).
    #[serde(default)]
    pub throttle_429_rate: f64,
    /// `Retry-After` seconds of injected 429s.
    #[serde(default = "default_retry_after")]
    pub retry_after_secs: u64,
    /// Share of requests delayed by `slow_ms` before processing.
    #[serde(default)]
    pub slow_rate: f64,
    /// Delay of slow requests in milliseconds.
    #[serde(default)]
    pub slow_ms: u64,
    /// PRNG seed: the same seed and request sequence give the same faults.
    #[serde(default)]
    pub seed: u64,
}

fn default_retry_after() -> u64 {
    1
}

impl Default for Faults {
    fn default() -> Self {
        Faults {
            error_500_rate: 0.0,
            error_500_after_write_rate: 0.0,
            throttle_429_rate: 0.0,
            retry_after_secs: 1,
            slow_rate: 0.0,
            slow_ms: 0,
            seed: 0,
        }
    }
}

impl Faults {
    /// Checks that rates are probabilities and the delay is sane.
    pub fn validate(&self) -> Result<(), String> {
        for (name, rate) in [
            ("error_500_rate", self.error_500_rate),
            (
                "error_500_after_write_rate",
                self.error_500_after_write_rate,
            ),
            ("throttle_429_rate", self.throttle_429_rate),
            ("slow_rate", self.slow_rate),
        ] {
            if !(0.0..=1.0).contains(&rate) {
                return Err(format!("`{name}` must be between 0 and 1, got {rate}"));
            }
        }
        if self.slow_ms > 600_000 {
            return Err(format!(
                "`slow_ms` must be at most 600000, got {}",
                self.slow_ms
            ));
        }
        if self.retry_after_secs == 0 || self.retry_after_secs > 3600 {
            return Err(format!(
                "`retry_after_secs` must be between 1 and 3600, got {}",
                self.retry_after_secs
            ));
        }
        Ok(())
    }
}

/// What to do to one request.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct Decision {
    pub slow_ms: Option<u64>,
    pub throttle: Option<u64>,
    pub error_500: bool,
    pub error_500_after: bool,
}

/// Current faults and the PRNG state.
#[derive(Debug, Default)]
pub(crate) struct FaultState {
    pub faults: Faults,
    rng: u64,
}

impl FaultState {
    pub fn set(&mut self, faults: Faults) {
        self.rng = faults.seed;
        self.faults = faults;
    }

    /// SplitMix64: small, deterministic, good enough for fault dice.
    fn next_unit(&mut self) -> f64 {
        self.rng = self.rng.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.rng;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Rolls the dice for one request (always four draws, so decisions stay reproducible).
    pub fn decide(&mut self) -> Decision {
        let f = self.faults.clone();
        let (slow, throttle, e500, after) = (
            self.next_unit(),
            self.next_unit(),
            self.next_unit(),
            self.next_unit(),
        );
        Decision {
            slow_ms: (slow < f.slow_rate && f.slow_ms > 0).then_some(f.slow_ms),
            throttle: (throttle < f.throttle_429_rate).then_some(f.retry_after_secs),
            error_500: e500 < f.error_500_rate,
            error_500_after: after < f.error_500_after_write_rate,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_same_seed_gives_the_same_decisions() {
        let faults = Faults {
            error_500_rate: 0.5,
            throttle_429_rate: 0.5,
            seed: 42,
            ..Faults::default()
        };
        let mut a = FaultState::default();
        let mut b = FaultState::default();
        a.set(faults.clone());
        b.set(faults);
        let da: Vec<_> = (0..50).map(|_| a.decide()).collect();
        let db: Vec<_> = (0..50).map(|_| b.decide()).collect();
        assert_eq!(da, db);
        assert!(da.iter().any(|d| d.error_500) && da.iter().any(|d| !d.error_500));
    }

    #[test]
    fn rates_outside_zero_to_one_are_refused() {
        let f = Faults {
            slow_rate: 1.5,
            ..Faults::default()
        };
        assert!(f.validate().unwrap_err().contains("slow_rate"));
    }
}
