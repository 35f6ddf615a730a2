//! End-to-end tests: the pipeline's handlers in the state machine's order against the local
//! stack, real Jobs included.
//!
//! They live in `tests/` and `benches/`; this library holds what a bench and a test share:
//! the deadline rush's HTML report (`report`).

pub mod report;
