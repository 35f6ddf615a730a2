//! The integration tests of `crates/jobs`, one test binary (each file is a module: one link,
//! not one per file).

mod render;
