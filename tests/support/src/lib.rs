//! What the workspace's tests share: checks of the shipped artefacts against the templates
//! that deploy them, and the set-up the emulator tests repeat.

pub mod privilege;
