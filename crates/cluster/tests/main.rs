//! The integration tests of `crates/cluster`, one test binary (each file is a module: one link,
//! not one per file).

mod api;
mod connect;
mod local_kube;
