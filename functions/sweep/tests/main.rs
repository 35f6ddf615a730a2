//! The integration tests of `functions/sweep`, one test binary (each file is a module: one link,
//! not one per file).

mod privilege;
mod sweep;
