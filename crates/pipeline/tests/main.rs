//! The integration tests of `crates/pipeline`, one test binary (each file is a module: one link,
//! not one per file).

mod queue;
mod results;
mod statemachine;
