//! A fake EvalAI server that enforces the host-evaluation wire contract of
//! `reference/evalai-host-api.md`, for tests and local rehearsal.
//!
//! Start it with [`FakeEvalAi::start`] (inside a tokio runtime) or [`FakeEvalAi::spawn`]
//! (own thread), point an EvalAI client at [`FakeEvalAi::url`], and inspect what happened
//! with [`FakeEvalAi::state`] and [`FakeEvalAi::requests`] (or `GET /_admin/state`).

mod admin;
mod auth;
pub mod faults;
pub mod fixture;
mod html;
pub mod pyjson;
pub mod reqlog;
mod routes;
mod server;
pub mod state;
pub mod statuses;
mod throttle;
mod timefmt;

pub use faults::Faults;
pub use fixture::{Fixture, FixtureError, TokenKind};
pub use reqlog::RequestRecord;
pub use server::{shutdown_signal, FakeEvalAi, ServerError};
pub use state::{
    AdminError, LeaderboardRowSnapshot, NewSubmission, StateSnapshot, SubmissionFiles,
    SubmissionSnapshot,
};
