//! The integration tests of `local/workloads`, one test binary (each file is a module: one link,
//! not one per file).

mod common;

mod fake_carla;
mod fake_evaluator;
