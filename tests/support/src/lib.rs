//! What the workspace's tests share: checks of the shipped artefacts against the templates
//! that deploy them, the provisioned local stack the emulator tests begin with, Step Functions'
//! task reports recorded, and a recording proxy that counts a process's requests in sequence.

pub mod callbacks;
pub mod privilege;
pub mod stack;
pub mod wire;

pub use callbacks::{Answer, RecordingCallbacks};
