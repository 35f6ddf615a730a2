//! A run's rules, stage by stage: Intake's, the Monitor's round and policy, Finalize's closing
//! and rules, the reaper's, the schedule, the history and the state handed between them.

pub mod audit;
pub mod closing;
pub mod finalize;
pub mod history;
pub mod intake;
pub mod metrics;
pub mod monitor;
pub mod reaper;
pub mod round;
pub mod schedule;
pub mod state;
