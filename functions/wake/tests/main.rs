//! The integration tests of `functions/wake`, one test binary (each file is a module: one link,
//! not one per file).

mod events;
mod privilege;
mod wake;
