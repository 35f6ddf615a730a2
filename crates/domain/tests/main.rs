//! The integration tests of `crates/domain`, one test binary (each file is a module: one link,
//! not one per file).

mod fixtures;
mod hostile_input;
