//! Job template files: three payload-template sections assembled into one Job.
//!
//! ```yaml
//! pair:        # list of containers, rendered once per pair with the pair at `$.pair`
//! per_job:
//!   init_containers:  # list, rendered once
//!   containers:       # list, rendered once, placed after every pair's containers
//! job:         # the Job; `$.assembled.init_containers` and `$.assembled.containers`
//! ```
//!
//! Step Functions `Parameters` cannot loop, so the renderer does the one loop (over pairs)
//! and hands the results to the Job section through the `assembled` key. Every section is
//! compiled once and checked against [`JobContext::sample`]: a template reading a key the
//! context does not have fails to load.

use std::sync::LazyLock;

use k8s_openapi::api::batch::v1::Job;
use lb_asl::{DynamicField, Env, LoadError, Template};
use lb_domain::results::Leaderboard;
use serde::Deserialize;
use serde_json::{Map, Value};

use crate::context::JobContext;
use crate::RenderError;

/// The context key the pair section reads its pair from.
pub const PAIR_KEY: &str = "pair";
/// The context key the Job section reads the assembled containers from.
pub const ASSEMBLED_KEY: &str = "assembled";

/// The built-in template of Leaderboard 2.0.
pub const LEADERBOARD_20: &str = include_str!("../../../templates/leaderboard-20/job.yaml");
/// The built-in template of Leaderboard 1.0.
pub const LEADERBOARD_10: &str = include_str!("../../../templates/leaderboard-10/job.yaml");

/// A template that cannot be used. Name: `InvalidJobTemplate`.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TemplateError {
    /// Not YAML, or not the three sections.
    #[error("job template `{template}` is not a valid template file: {reason}")]
    Format {
        /// Which template.
        template: String,
        /// The parser's message.
        reason: String,
    },
    /// A bad path, call or `.$` field.
    #[error("job template `{template}`, section `{section}`: {source}")]
    Load {
        /// Which template.
        template: String,
        /// Which section.
        section: &'static str,
        /// The definition error.
        #[source]
        source: LoadError,
    },
    /// The template fails on the sample context: a path to a key the context does not have,
    /// or a Job that breaks the Kubernetes schema or our Job rules.
    #[error("job template `{template}` fails on the sample job context: {reason}")]
    Check {
        /// Which template.
        template: String,
        /// Why (the render error and its name).
        reason: String,
    },
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PerJobFile {
    init_containers: Value,
    containers: Value,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct TemplateFile {
    pair: Value,
    per_job: PerJobFile,
    job: Value,
}

/// A compiled Job template.
#[derive(Debug, Clone)]
pub struct JobTemplate {
    name: String,
    pair: Template,
    init_containers: Template,
    containers: Template,
    job: Template,
}

fn section_list(value: Value, section: &'static str) -> Result<Vec<Value>, RenderError> {
    match value {
        Value::Array(items) if items.iter().all(Value::is_object) => Ok(items),
        other => Err(RenderError::InvalidSpec {
            path: section.to_owned(),
            problem: format!(
                "the section must render to a list of containers, got {}",
                lb_asl::preview(&other)
            ),
        }),
    }
}

impl JobTemplate {
    /// Parses and checks a template file; `name` identifies it in errors.
    pub fn parse(name: &str, yaml: &str) -> Result<JobTemplate, TemplateError> {
        let file: TemplateFile = serde_yaml::from_str(yaml).map_err(|e| TemplateError::Format {
            template: name.into(),
            reason: e.to_string(),
        })?;
        let compile = |section: &'static str, value: &Value| {
            Template::compile_at(value, section).map_err(|source| TemplateError::Load {
                template: name.into(),
                section,
                source,
            })
        };
        let template = JobTemplate {
            name: name.to_owned(),
            pair: compile("pair", &file.pair)?,
            init_containers: compile("per_job.init_containers", &file.per_job.init_containers)?,
            containers: compile("per_job.containers", &file.per_job.containers)?,
            job: compile("job", &file.job)?,
        };
        // Every path must resolve against a complete context (both leaderboards' contexts
        // carry the same keys), and the result must be a valid Job.
        template
            .render(&JobContext::sample(Leaderboard::V2))
            .map_err(|e| TemplateError::Check {
                template: name.into(),
                reason: format!("{e} ({})", e.name()),
            })?;
        Ok(template)
    }

    /// The built-in template of `leaderboard` (compiled and checked once per process).
    pub fn builtin(leaderboard: Leaderboard) -> Result<&'static JobTemplate, TemplateError> {
        static V1: LazyLock<Result<JobTemplate, TemplateError>> =
            LazyLock::new(|| JobTemplate::parse("leaderboard-10/job.yaml", LEADERBOARD_10));
        static V2: LazyLock<Result<JobTemplate, TemplateError>> =
            LazyLock::new(|| JobTemplate::parse("leaderboard-20/job.yaml", LEADERBOARD_20));
        match leaderboard {
            Leaderboard::V1 => V1.as_ref(),
            Leaderboard::V2 => V2.as_ref(),
        }
        .map_err(Clone::clone)
    }

    /// Every `.$` field of every section, with the paths it reads.
    pub fn dynamic_fields(&self) -> Vec<(&'static str, DynamicField<'_>)> {
        [
            ("pair", &self.pair),
            ("per_job.init_containers", &self.init_containers),
            ("per_job.containers", &self.containers),
            ("job", &self.job),
        ]
        .into_iter()
        .flat_map(|(section, t)| t.dynamic_fields().into_iter().map(move |f| (section, f)))
        .collect()
    }

    /// The template's name (its file under `templates/`).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Renders the Job as JSON, before the Kubernetes checks.
    pub fn render_value(&self, context: &JobContext) -> Result<Value, RenderError> {
        let env = Env::none();
        let Ok(Value::Object(base)) = serde_json::to_value(context) else {
            unreachable!("a JobContext serializes to a JSON object")
        };
        let with = |key: &str, value: Value| -> Value {
            let mut map: Map<String, Value> = base.clone();
            map.insert(key.to_owned(), value);
            Value::Object(map)
        };
        let failed =
            |section: &'static str| move |source| RenderError::Evaluation { section, source };

        let mut containers = Vec::new();
        for pair in &context.pairs {
            let pair = serde_json::to_value(pair).unwrap_or(Value::Null);
            let rendered = self
                .pair
                .render(&with(PAIR_KEY, pair), &env)
                .map_err(failed("pair"))?;
            containers.extend(section_list(rendered, "pair")?);
        }
        let input = Value::Object(base.clone());
        let init = self
            .init_containers
            .render(&input, &env)
            .map_err(failed("per_job.init_containers"))?;
        let init = section_list(init, "per_job.init_containers")?;
        let tail = self
            .containers
            .render(&input, &env)
            .map_err(failed("per_job.containers"))?;
        containers.extend(section_list(tail, "per_job.containers")?);

        let assembled = serde_json::json!({
            "init_containers": init,
            "containers": containers,
        });
        self.job
            .render(&with(ASSEMBLED_KEY, assembled), &env)
            .map_err(failed("job"))
    }

    /// Renders the Job and checks it against the Kubernetes schema and the Job rules
    /// ([`crate::validate`]).
    pub fn render(&self, context: &JobContext) -> Result<Job, RenderError> {
        let job = crate::validate::check_job(&self.render_value(context)?)?;
        crate::security::check(&job, context)?;
        Ok(job)
    }
}
