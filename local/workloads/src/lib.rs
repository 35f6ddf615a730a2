//! Stand-ins for the CARLA server (`fake-carla`) and the Leaderboard evaluator (`fake-evaluator`).
//!
//! Tests and the local rehearsal mode run them where the Job containers would run
//! `./CarlaUE4.sh ...` and `python3 -u .../leaderboard_evaluator.py ...`. They take the same
//! arguments, write checkpoint files in the official format (through `lb-domain`), and fail on
//! request in the ways the real ones do (see [`faults`]).

pub mod args;
pub mod carla;
pub mod evaluator;
pub mod faults;
pub mod imports;
pub mod recorder;
pub mod records;
pub mod signals;

/// Sets up `tracing` for the binaries: the fakes' own diagnostics go to stderr, so stdout
/// carries only what the real program would print. The level comes from `RUST_LOG` (default
/// `info`).
pub fn init_tracing() {
    use std::io::IsTerminal;
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    // NB: a second call (tests, embedding) keeps the first subscriber instead of panicking.
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .try_init();
}
