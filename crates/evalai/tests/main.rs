//! The integration tests of `crates/evalai`, one test binary (each file is a module: one link,
//! not one per file).

mod fake_evalai;
