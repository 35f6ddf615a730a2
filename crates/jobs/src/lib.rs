//! Kubernetes Jobs of a submission, rendered from the leaderboard's Job template and a typed
//! job context with Step Functions `Parameters` semantics, then checked strictly against the
//! Kubernetes schema and our Job rules.
//!
//! ```
//! use lb_domain::results::Leaderboard;
//! use lb_jobs::{render, JobContext};
//!
//! let job = render(Leaderboard::V2, &JobContext::sample(Leaderboard::V2)).unwrap();
//! assert_eq!(job.metadata.name.as_deref(), Some("lb-1-sample-0"));
//! ```
//!
//! The templates live in `templates/` at the repository root and are compiled into this
//! crate (`include_str!`), so a Lambda needs no files.

pub mod context;
pub mod image;
pub mod security;
pub mod template;
pub mod validate;

use k8s_openapi::api::batch::v1::Job;
use lb_asl::AslError;
use lb_domain::job::plan::Plan;
use lb_domain::results::Leaderboard;

pub use context::{ContextError, JobContext, JobSettings, Timers};
pub use image::{parse_image, ImageRef};
pub use lb_domain::submission::SubmissionInfo;
pub use template::{JobTemplate, TemplateError};

/// Why a Job could not be rendered. Each variant has a stable [`name`](Self::name).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RenderError {
    /// The template itself is broken (`InvalidJobTemplate`).
    #[error(transparent)]
    Template(#[from] TemplateError),
    /// An input of the job context is invalid (`InvalidImage`, `InvalidJobSetting`).
    #[error(transparent)]
    Context(#[from] ContextError),
    /// A section failed to render (`JobTemplateEvaluationFailed`).
    #[error("section `{section}` of the job template failed: {source} ({name})", name = source.name())]
    Evaluation {
        /// Which section.
        section: &'static str,
        /// The Step Functions error.
        #[source]
        source: AslError,
    },
    /// The rendered Job breaks the Kubernetes schema or our Job rules (`InvalidJobSpec`).
    #[error("invalid Job: `{path}` {problem}")]
    InvalidSpec {
        /// Where (`spec.template.spec.containers[0].name`).
        path: String,
        /// What is wrong.
        problem: String,
    },
}

lb_domain::error_names!(RenderError {
    Template => "InvalidJobTemplate";
    Evaluation => "JobTemplateEvaluationFailed";
    InvalidSpec => "InvalidJobSpec";
} wraps {
    Context => ContextError;
});

/// Renders one Job of `leaderboard` from its context, with the built-in template.
pub fn render(leaderboard: Leaderboard, context: &JobContext) -> Result<Job, RenderError> {
    JobTemplate::builtin(leaderboard)?.render(context)
}

/// Renders every Job of a planned submission, in Job index order.
pub fn render_plan(
    leaderboard: Leaderboard,
    plan: &Plan,
    submission: &SubmissionInfo,
    settings: &JobSettings,
) -> Result<Vec<Job>, RenderError> {
    let template = JobTemplate::builtin(leaderboard)?;
    plan.jobs
        .iter()
        .map(|job| {
            let context = JobContext::build(leaderboard, plan, job.index, submission, settings)?;
            template.render(&context)
        })
        .collect()
}
