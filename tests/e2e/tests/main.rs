//! The integration tests of `tests/e2e`, one test binary (each file is a module: one link,
//! not one per file).

mod infra;
mod kube_contract;
mod layout;
mod payloads;
mod pipeline;
mod real_kube;
mod report;
