//! Everything works: FINISHED with scores.

use super::Rehearsal;

/// The happy path.
pub struct Happy;

impl Rehearsal for Happy {
    fn expected(&self) -> &'static str {
        "finished"
    }
}
