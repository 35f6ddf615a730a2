//! The integration tests of `local/evalai`, one test binary (each file is a module: one link,
//! not one per file).

mod common;

mod api;
mod binary;
mod contract;
mod handle_and_admin;
