//! The integration tests of `functions/intake`, one test binary (each file is a module: one link,
//! not one per file).

mod intake;
mod privilege;
