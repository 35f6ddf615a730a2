//! Test support shared by the workspace's tests and benches (feature `test-util`).

use std::path::{Path, PathBuf};

/// The results fixtures the repository keeps (`tests/fixtures/leaderboard-results`), or
/// `$LB_FIXTURES_DIR`.
pub fn results_fixtures_dir() -> PathBuf {
    match std::env::var_os("LB_FIXTURES_DIR") {
        Some(dir) => PathBuf::from(dir),
        None => {
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/leaderboard-results")
        }
    }
}
