//! Test support shared by the workspace's tests and benches. Always compiled (the binaries
//! drop it): behind a feature, the tests' build would differ from the binaries' and compile
//! every crate above this one a second time.

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
    state: crate::cluster::view::JobState,
    deadline: Option<u64>,
) -> crate::cluster::view::JobView {
    crate::cluster::view::JobView {
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

/// A pod `name` of Job `job` in `phase`, on no node and never started (the GPU count takes
/// no pod without a start), with no containers.
pub fn pod(name: &str, job: &str, phase: crate::status::PodPhase) -> crate::cluster::view::PodView {
    crate::cluster::view::PodView {
        name: name.into(),
        job: Some(job.into()),
        phase,
        reason: None,
        message: None,
        node: None,
        start_time: None,
        terminating: false,
        uid: None,
        node_selector: None,
        disruption: None,
        disruption_message: None,
        gpus: 1,
        unschedulable: None,
        autoscaler: None,
        containers: Vec::new(),
    }
}
