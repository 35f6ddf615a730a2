//! The AWS configuration of the operator commands, checked before the first call so that a
//! missing region or missing credentials is one line that says what to do.

use std::time::Duration;

use aws_config::SdkConfig;
use aws_credential_types::provider::ProvideCredentials;

use crate::error::{CliError, Result};

/// How long the credential chain may look (the instance metadata service times out slowly).
const CREDENTIALS_WAIT: Duration = Duration::from_secs(20);

/// The standard AWS configuration (environment, profile, SSO, web identity, container and
/// instance metadata), with its region and credentials known to be there.
pub async fn config() -> Result<SdkConfig> {
    let sdk = lb_aws::sdk_config().await;
    check(&sdk).await?;
    Ok(sdk)
}

async fn check(sdk: &SdkConfig) -> Result<()> {
    let profile = std::env::var("AWS_PROFILE").unwrap_or_else(|_| "default".into());
    if sdk.region().is_none() {
        return Err(CliError::AwsNotConfigured(format!(
            "no AWS region: looked in AWS_REGION, AWS_DEFAULT_REGION and the `region` of \
             profile `{profile}` in ~/.aws/config; set one of them (e.g. `export AWS_REGION=us-west-2`)"
        )));
    }
    let Some(provider) = sdk.credentials_provider() else {
        return Err(no_credentials(
            &profile,
            "no credential provider is configured",
        ));
    };
    match tokio::time::timeout(CREDENTIALS_WAIT, provider.provide_credentials()).await {
        Ok(Ok(_)) => Ok(()),
        Ok(Err(e)) => Err(no_credentials(&profile, &e.to_string())),
        Err(_) => Err(no_credentials(
            &profile,
            &format!("none found within {} s", CREDENTIALS_WAIT.as_secs()),
        )),
    }
}

fn no_credentials(profile: &str, why: &str) -> CliError {
    CliError::AwsNotConfigured(format!(
        "no AWS credentials ({why}): looked in AWS_ACCESS_KEY_ID/AWS_SECRET_ACCESS_KEY, profile \
         `{profile}` in ~/.aws/credentials and ~/.aws/config (SSO and web identity included) and \
         the container and instance metadata; run `aws configure` or `aws sso login`, set \
         AWS_PROFILE to a configured profile, or export AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY"
    ))
}
