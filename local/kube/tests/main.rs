//! The integration tests of `local/kube`, one test binary (each file is a module: one link,
//! not one per file).

mod cluster;
mod kubectl;
