//! Pure domain core of the CARLA Leaderboard evaluation backend: no AWS, Kubernetes or Lambda.

pub mod capacity;
pub mod cluster;
pub mod errors;
pub mod job;
pub mod results;
pub mod run;
pub mod settings;
pub mod status;
pub mod submission;
#[doc(hidden)]
pub mod testutil;
