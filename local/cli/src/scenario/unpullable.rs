//! The participant's image cannot be pulled: FAILED with a message naming it.

use super::Rehearsal;

/// An image the registry does not have.
pub const UNPULLABLE: &str = "123456789012.dkr.ecr.us-west-2.amazonaws.com/team-one:never-pushed";

/// An image that was never pushed.
pub struct Unpullable;

impl Rehearsal for Unpullable {
    fn expected(&self) -> &'static str {
        "failed"
    }

    fn image(&self) -> &'static str {
        UNPULLABLE
    }
}
