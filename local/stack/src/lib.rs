//! Local stand-ins for the systems the backend talks to, for tests and local mode.

pub mod events;
pub mod integrations;
pub mod moto;
pub mod pipe;
pub mod real;
pub mod registry;
pub mod stack;
pub mod workloads;

pub use stack::{EvalAi, Stack, StackError};
