//! Capacity and cost: what a run's pods cost, and who of a leaderboard's queue runs next.

pub mod consolidation;
pub mod cost;
pub mod fleet;
pub mod forecast;
mod ledger_code;
pub mod queue;
