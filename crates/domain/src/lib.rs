//! Pure domain core of the CARLA Leaderboard evaluation backend: no AWS, Kubernetes or Lambda.

pub mod audit;
pub mod autoscaler;
pub mod closing;
pub mod cluster;
pub mod cost;
pub mod errors;
pub mod finalize;
pub mod history;
pub mod intake;
pub mod logtail;
pub mod monitor;
pub mod plan;
pub mod protocol;
pub mod py;
pub mod queue;
pub mod reaper;
pub mod resources;
pub mod results;
pub mod round;
pub mod run;
pub mod schedule;
pub mod settings;
pub mod status;
pub mod submission;
#[cfg(feature = "test-util")]
pub mod testutil;
