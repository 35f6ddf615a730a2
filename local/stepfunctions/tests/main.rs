//! The integration tests of `local/stepfunctions`, one test binary (each file is a module: one link,
//! not one per file).

mod common;

mod callback;
mod load;
mod states;
mod submission;
mod tasks;
mod versions;
