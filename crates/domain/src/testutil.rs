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

/// A Job named `name` at index 0 in `state`, with one pod active and ready, none counted, no
/// pods listed, and this `activeDeadlineSeconds`.
pub fn job(
    name: &str,
    state: crate::cluster::JobState,
    deadline: Option<u64>,
) -> crate::cluster::JobView {
    crate::cluster::JobView {
        name: name.into(),
        index: Some(0),
        state,
        active: 1,
        ready: 1,
        succeeded: 0,
        failed: 0,
        start_time: None,
        completion_time: None,
        terminating: false,
        deadline,
        backoff_limit: Some(4),
        pods: Vec::new(),
    }
}
