//! EvalAI submission statuses (stored and returned lowercase).

/// Every status a submission can hold, as EvalAI stores them.
pub const STATUSES: [&str; 10] = [
    "submitted",
    "submitting",
    "queued",
    "running",
    "resuming",
    "partially_evaluated",
    "finished",
    "failed",
    "cancelled",
    "archived",
];

/// `submitted`: a new submission.
pub const SUBMITTED: &str = "submitted";
/// `queued`.
pub const QUEUED: &str = "queued";
/// `running`.
pub const RUNNING: &str = "running";
/// `resuming`: set by resume, only from `failed`.
pub const RESUMING: &str = "resuming";
/// `partially_evaluated`.
pub const PARTIALLY_EVALUATED: &str = "partially_evaluated";
/// `finished`.
pub const FINISHED: &str = "finished";
/// `failed`.
pub const FAILED: &str = "failed";
/// `cancelled`.
pub const CANCELLED: &str = "cancelled";

/// Statuses the list endpoint's `status` filter accepts.
pub const LISTABLE: [&str; 8] = [
    "submitted",
    "running",
    "queued",
    "resuming",
    "failed",
    "cancelled",
    "finished",
    "submitting",
];
