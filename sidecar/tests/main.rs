//! The integration tests of `sidecar`, one test binary (each file is a module: one link,
//! not one per file).

mod support;

mod init;
mod job;
mod logcopy;
mod merge_cli;
mod pair;
mod privilege;
