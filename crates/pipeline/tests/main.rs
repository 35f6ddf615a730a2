//! The integration tests of `crates/pipeline`, one test binary (each file is a module: one link,
//! not one per file).

mod payload;
mod queue;
mod results;
mod statemachine;
