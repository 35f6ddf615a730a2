//! The integration tests of `local/stack`, one test binary (each file is a module: one link,
//! not one per file).

mod events;
mod moto;
mod moto_missing;
mod provision;
mod wake;
