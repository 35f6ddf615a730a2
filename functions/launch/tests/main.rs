//! The integration tests of `functions/launch`, one test binary (each file is a module: one link,
//! not one per file).

mod privilege;
