//! The integration tests of `cli`, one test binary (each file is a module: one link,
//! not one per file).

mod common;

mod help;
mod invoke;
mod logs;
mod operator;
mod people;
mod rescore;
mod watch;
