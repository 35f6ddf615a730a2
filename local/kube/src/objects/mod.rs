//! Object rules: defaults, validation, names, the Job create path and pods built from templates.

pub mod defaults;
pub mod job;
pub mod names;
pub mod pod;
pub mod validation;

/// Label with the Job's name (legacy form).
pub const LEGACY_JOB_NAME_LABEL: &str = "job-name";
/// Label with the Job's name.
pub const JOB_NAME_LABEL: &str = "batch.kubernetes.io/job-name";
/// Label with the Job's uid (legacy form).
pub const LEGACY_CONTROLLER_UID_LABEL: &str = "controller-uid";
/// Label with the Job's uid; the generated selector selects it.
pub const CONTROLLER_UID_LABEL: &str = "batch.kubernetes.io/controller-uid";
/// Finalizer the job controller keeps on pods until it has counted them.
pub const JOB_TRACKING_FINALIZER: &str = "batch.kubernetes.io/job-tracking";
