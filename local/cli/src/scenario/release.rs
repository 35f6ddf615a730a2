//! A deploy or a rollback while a submission runs: the run moves the alias (`crate::release`)
//! and the report checks the versions each submission ran.

use super::Rehearsal;
use crate::release::Move;

/// The alias moved one way or the other after the first submission's first round.
pub struct Release(pub Move);

impl Rehearsal for Release {
    fn expected(&self) -> &'static str {
        "finished"
    }

    fn release(&self) -> Option<Move> {
        Some(self.0)
    }
}
