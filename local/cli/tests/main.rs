//! The integration tests of `local/cli`, one test binary (each file is a module: one link,
//! not one per file).

mod emf;
mod local_run;
mod states;
mod top;
