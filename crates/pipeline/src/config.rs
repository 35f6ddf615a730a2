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
    /// takes from; unset only where one function runs alone (a tool run by hand).
    pub budget_table: Option<String>,
    /// `LB_ADMISSION_TABLE`: the leaderboards' queues (`lb_aws::admission`), where Launch
    /// admits and the Monitor and Finalize move a submission on; unset, nothing is queued
    /// (every submission is admitted at once: a tool run by hand).
    pub admission_table: Option<String>,
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
            budget_table: lookup("LB_BUDGET_TABLE").filter(|v| !v.trim().is_empty()),
            admission_table: lookup("LB_ADMISSION_TABLE").filter(|v| !v.trim().is_empty()),
            memory_mb: lookup("AWS_LAMBDA_FUNCTION_MEMORY_SIZE")
                .and_then(|v| v.trim().parse().ok())
                .unwrap_or(128),
        })
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

    #[test]
    fn a_missing_variable_is_named() {
        let err = FunctionConfig::from_lookup(|name| {
            (name == "LB_SETTINGS_SECRET").then(|| "cfg".into())
        })
        .unwrap_err();
        assert_eq!(err.to_string(), "invalid function configuration: environment variable `LB_EVALAI_TOKEN_SECRET` is not set");
    }
}
