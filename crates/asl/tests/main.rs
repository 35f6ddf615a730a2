//! The integration tests of `crates/asl`, one test binary (each file is a module: one link,
//! not one per file).

mod developer_guide;
mod robustness;
