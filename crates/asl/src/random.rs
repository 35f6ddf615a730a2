//! Random numbers for `States.MathRandom` and `States.UUID`: SplitMix64, seedable, lock-free.
//!
//! Not cryptographic: Step Functions' own `States.UUID` is for identifiers, not secrets, and
//! nothing in this project derives a secret from it.

use std::collections::hash_map::RandomState;
use std::hash::{BuildHasher, Hasher};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::LazyLock;
use std::time::{SystemTime, UNIX_EPOCH};

const GAMMA: u64 = 0x9E37_79B9_7F4A_7C15;

fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A SplitMix64 generator shared through `&self` (an atomic counter), so one source can
/// serve concurrent evaluations.
#[derive(Debug)]
pub struct RandomSource {
    state: AtomicU64,
}

impl RandomSource {
    /// A generator whose sequence is fixed by `seed` (tests, `States.MathRandom` with a seed).
    pub fn seeded(seed: u64) -> RandomSource {
        RandomSource {
            state: AtomicU64::new(seed),
        }
    }

    /// A generator seeded from the process's hash keys (OS randomness) and the clock.
    pub fn from_entropy() -> RandomSource {
        let mut hasher = RandomState::new().build_hasher();
        let nanos = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or_default();
        hasher.write_u128(nanos);
        hasher.write_u32(std::process::id());
        RandomSource::seeded(hasher.finish())
    }

    /// The process-wide generator used when an [`Env`](crate::Env) names none.
    pub fn global() -> &'static RandomSource {
        static GLOBAL: LazyLock<RandomSource> = LazyLock::new(RandomSource::from_entropy);
        &GLOBAL
    }

    /// The next 64 random bits.
    pub fn next_u64(&self) -> u64 {
        mix(self
            .state
            .fetch_add(GAMMA, Ordering::Relaxed)
            .wrapping_add(GAMMA))
    }

    /// A uniform number in `0..bound` (`bound` > 0), without modulo bias.
    pub fn below(&self, bound: u64) -> u64 {
        debug_assert!(bound > 0);
        let bound = bound.max(1);
        // Reject the top partial bucket so every residue is equally likely.
        let zone = u64::MAX - (u64::MAX % bound);
        loop {
            let draw = self.next_u64();
            if draw < zone {
                return draw % bound;
            }
        }
    }

    /// A random (version 4, RFC 4122 variant) UUID in lowercase hyphenated form.
    pub fn uuid_v4(&self) -> String {
        let mut bytes = [0u8; 16];
        bytes[..8].copy_from_slice(&self.next_u64().to_le_bytes());
        bytes[8..].copy_from_slice(&self.next_u64().to_le_bytes());
        bytes[6] = (bytes[6] & 0x0f) | 0x40;
        bytes[8] = (bytes[8] & 0x3f) | 0x80;
        let hex: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
        format!(
            "{}-{}-{}-{}-{}",
            &hex[0..8],
            &hex[8..12],
            &hex[12..16],
            &hex[16..20],
            &hex[20..32]
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_seed_fixes_the_sequence() {
        let a = RandomSource::seeded(42);
        let b = RandomSource::seeded(42);
        let xs: Vec<u64> = (0..5).map(|_| a.next_u64()).collect();
        let ys: Vec<u64> = (0..5).map(|_| b.next_u64()).collect();
        assert_eq!(xs, ys);
        assert_ne!(xs[0], xs[1]);
        assert_ne!(RandomSource::seeded(43).next_u64(), xs[0]);
    }

    #[test]
    fn below_stays_in_range_and_covers_it() {
        let r = RandomSource::seeded(7);
        let mut seen = [false; 5];
        for _ in 0..500 {
            let v = r.below(5);
            assert!(v < 5);
            seen[v as usize] = true;
        }
        assert!(seen.iter().all(|s| *s));
    }

    #[test]
    fn uuids_are_version_4_with_the_rfc_variant() {
        let r = RandomSource::from_entropy();
        let u = r.uuid_v4();
        assert_eq!(u.len(), 36);
        let parts: Vec<&str> = u.split('-').collect();
        assert_eq!(
            parts.iter().map(|p| p.len()).collect::<Vec<_>>(),
            [8, 4, 4, 4, 12]
        );
        assert!(parts[2].starts_with('4'));
        assert!(matches!(parts[3].as_bytes()[0], b'8' | b'9' | b'a' | b'b'));
        assert_ne!(u, r.uuid_v4());
    }
}
