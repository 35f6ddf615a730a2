//! What the workspace's tests share: checks of the shipped artefacts against the templates
//! that deploy them, the provisioned local stack the emulator tests begin with, and Step
//! Functions' task reports recorded.

pub mod callbacks;
pub mod privilege;
pub mod stack;

pub use callbacks::{Answer, RecordingCallbacks};
