//! The integration tests of `crates/aws`, one test binary (each file is a module: one link,
//! not one per file).

mod admission;
mod budget;
mod conditional;
mod moto;
