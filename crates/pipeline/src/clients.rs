//! Clients built once per cold start from the environment, shared by the functions' `Deps`.

use aws_config::SdkConfig;
use lb_domain::settings::Settings;
use lb_evalai::{AuthScheme, EvalAiClient, RetryPolicy};

use crate::{FnError, FunctionConfig};

/// The settings secret, read and checked.
pub async fn settings(sdk: &SdkConfig, config: &FunctionConfig) -> Result<Settings, FnError> {
    let secrets = aws_sdk_secretsmanager::Client::new(sdk);
    Ok(lb_aws::secrets::load_settings(&secrets, &config.settings_secret).await?)
}

/// The EvalAI client for `settings`, with the host token from its secret.
pub async fn evalai(
    sdk: &SdkConfig,
    config: &FunctionConfig,
    settings: &Settings,
) -> Result<EvalAiClient, FnError> {
    let secrets = aws_sdk_secretsmanager::Client::new(sdk);
    let token = lb_aws::secrets::load_token(&secrets, &config.token_secret).await?;
    let scheme = match settings.evalai.auth_scheme.as_str() {
        "Token" => AuthScheme::Token,
        _ => AuthScheme::Bearer,
    };
    Ok(EvalAiClient::new(
        &settings.evalai.api_server,
        &token,
        scheme,
        RetryPolicy::default(),
    )?)
}

/// Now, as RFC 3339 UTC (the records' time format).
pub fn now_rfc3339() -> String {
    time::OffsetDateTime::now_utc()
        .replace_nanosecond(0)
        .unwrap_or_else(|_| time::OffsetDateTime::now_utc())
        .format(&time::format_description::well_known::Rfc3339)
        .unwrap_or_default()
}
