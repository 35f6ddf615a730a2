//! The environment every function reads once at cold start (never secrets: those come from
//! Secrets Manager).

use crate::FnError;

/// Environment of a function.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FunctionConfig {
    /// `LB_SETTINGS_SECRET`: id of the settings secret.
    pub settings_secret: String,
    /// `LB_EVALAI_TOKEN_SECRET`: id of the EvalAI host token secret.
    pub token_secret: String,
    /// `LB_WAKE_TABLE`: the wake table (`lb_aws::wake`), which the Monitor reads (the other
    /// stages do without it).
    pub wake_table: Option<String>,
    /// `LB_BUDGET_TABLE`: the shared EvalAI budget (`lb_aws::budget`) every EvalAI request
    /// takes from, or [`Shared::Unlimited`] where one function runs alone (a tool run by hand).
    pub budget: Shared,
    /// `LB_ADMISSION_TABLE`: the leaderboards' queues (`lb_aws::admission`), where Launch
    /// admits and the Monitor and Finalize move a submission on, or [`Shared::Unlimited`]
    /// (every submission is admitted at once: a tool run by hand).
    pub admission: Shared,
    /// `LB_CONSOLIDATE_NODES` (`true` or `false`, unset `false`): whether the sweep drains the
    /// GPU nodes consolidation chooses (`lb_domain::capacity::consolidation`). Off unless a
    /// deployment asks: a function run by hand changes no node.
    pub consolidate_nodes: bool,
    /// `AWS_LAMBDA_FUNCTION_MEMORY_SIZE` (the runtime sets it): the function's memory in MB,
    /// what its invocations cost per second; Lambda's default, 128, where it is not set.
    pub memory_mb: u32,
}

impl FunctionConfig {
    /// Reads the variables, naming the first one missing.
    pub fn from_env() -> Result<Self, FnError> {
        Self::from_lookup(|name| std::env::var(name).ok())
    }

    /// Reads through `lookup` (tests pass a map instead of touching the process environment).
    pub fn from_lookup(lookup: impl Fn(&str) -> Option<String>) -> Result<Self, FnError> {
        let get = |name: &str| {
            lookup(name)
                .filter(|v| !v.trim().is_empty())
                .ok_or_else(|| FnError::Config(format!("environment variable `{name}` is not set")))
        };
        Ok(FunctionConfig {
            settings_secret: get("LB_SETTINGS_SECRET")?,
            token_secret: get("LB_EVALAI_TOKEN_SECRET")?,
            wake_table: lookup("LB_WAKE_TABLE").filter(|v| !v.trim().is_empty()),
            budget: Shared::parse("LB_BUDGET_TABLE", &get("LB_BUDGET_TABLE")?)?,
            admission: Shared::parse("LB_ADMISSION_TABLE", &get("LB_ADMISSION_TABLE")?)?,
            consolidate_nodes: flag(&lookup, "LB_CONSOLIDATE_NODES")?,
            memory_mb: lookup("AWS_LAMBDA_FUNCTION_MEMORY_SIZE")
                .and_then(|v| v.trim().parse().ok())
                .unwrap_or(128),
        })
    }
}

/// A `true` / `false` variable, unset `false`; anything else an error naming it.
fn flag(lookup: &impl Fn(&str) -> Option<String>, name: &str) -> Result<bool, FnError> {
    match lookup(name).as_deref().map(str::trim) {
        None | Some("") | Some("false") => Ok(false),
        Some("true") => Ok(true),
        Some(other) => Err(FnError::Config(format!(
            "environment variable `{name}` is `{other}`: `true` or `false`"
        ))),
    }
}

/// A limit every function shares through a DynamoDB table (the EvalAI budget, the queues),
/// or none at all, which a person must ask for by name: a deployment that forgets the
/// variable fails at start instead of silently admitting everything.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Shared {
    /// The table of this name.
    Table(String),
    /// No limit (`unlimited`, a name DynamoDB tables of ours never take).
    Unlimited,
}

impl Shared {
    /// The word that asks for no limit.
    pub const UNLIMITED: &'static str = "unlimited";

    /// `value` of variable `name`: `unlimited`, or a DynamoDB table name (3 to 255 of
    /// `A-Za-z0-9_.-`), else an error naming the variable.
    pub fn parse(name: &str, value: &str) -> Result<Shared, FnError> {
        let value = value.trim();
        if value == Self::UNLIMITED {
            return Ok(Shared::Unlimited);
        }
        let valid = (3..=255).contains(&value.len())
            && value
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b"_.-".contains(&b));
        if !valid {
            return Err(FnError::Config(format!(
                "environment variable `{name}` is neither a DynamoDB table name nor `{}`: `{}`",
                Self::UNLIMITED,
                value.escape_debug()
            )));
        }
        Ok(Shared::Table(value.to_owned()))
    }
}

impl FunctionConfig {
    /// The wake table, for the functions that need it.
    pub fn wake_table(&self) -> Result<&str, FnError> {
        self.wake_table.as_deref().ok_or_else(|| {
            FnError::Config("environment variable `LB_WAKE_TABLE` is not set".into())
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env(missing: &str) -> impl Fn(&str) -> Option<String> + '_ {
        move |name| {
            let value = match name {
                "LB_SETTINGS_SECRET" => "cfg",
                "LB_EVALAI_TOKEN_SECRET" => "token",
                "LB_BUDGET_TABLE" => "leaderboard-budget",
                "LB_ADMISSION_TABLE" => "unlimited",
                _ => return None,
            };
            (name != missing).then(|| value.into())
        }
    }

    #[test]
    fn the_shared_limits_are_required_and_unlimited_only_by_name() {
        let config = FunctionConfig::from_lookup(env("")).unwrap();
        assert_eq!(config.budget, Shared::Table("leaderboard-budget".into()));
        assert_eq!(config.admission, Shared::Unlimited);
        for variable in ["LB_BUDGET_TABLE", "LB_ADMISSION_TABLE"] {
            let err = FunctionConfig::from_lookup(env(variable)).unwrap_err();
            assert_eq!(err.name(), "InvalidConfiguration");
            assert!(
                err.to_string()
                    .contains(&format!("`{variable}` is not set")),
                "{err}"
            );
        }
        for bad in ["ab", "no spaces", "Unlimited!", "a/b"] {
            let err = Shared::parse("LB_ADMISSION_TABLE", bad).unwrap_err();
            assert!(
                err.to_string().contains("`LB_ADMISSION_TABLE` is neither"),
                "{err}"
            );
        }
        assert_eq!(
            Shared::parse("X", " leaderboard-admission ").unwrap(),
            Shared::Table("leaderboard-admission".into())
        );
    }

    #[test]
    fn consolidation_is_off_unless_asked_and_a_word_other_than_true_or_false_is_refused() {
        assert!(
            !FunctionConfig::from_lookup(env(""))
                .unwrap()
                .consolidate_nodes
        );
        let with = |value: &'static str| {
            FunctionConfig::from_lookup(move |name| match name {
                "LB_CONSOLIDATE_NODES" => Some(value.into()),
                other => env("")(other),
            })
        };
        assert!(with("true").unwrap().consolidate_nodes);
        assert!(!with("false").unwrap().consolidate_nodes);
        let err = with("yes").unwrap_err();
        assert!(
            err.to_string().contains("`LB_CONSOLIDATE_NODES` is `yes`"),
            "{err}"
        );
    }

    #[test]
    fn a_missing_variable_is_named() {
        let err = FunctionConfig::from_lookup(|name| {
            (name == "LB_SETTINGS_SECRET").then(|| "cfg".into())
        })
        .unwrap_err();
        assert_eq!(err.to_string(), "invalid function configuration: environment variable `LB_EVALAI_TOKEN_SECRET` is not set");
    }
}
