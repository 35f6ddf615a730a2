//! AWS adapters of the pipeline: settings and token from Secrets Manager, the DynamoDB claim
//! and records, the S3 layout of a submission, EKS access, the wake table, task callbacks,
//! the shared EvalAI budget and the admission queue.
//!
//! Clients are concrete SDK clients built once per cold start from one [`aws_config::SdkConfig`]
//! (see [`sdk_config`]); tests point them at moto through `AWS_ENDPOINT_URL`.

pub mod admission;
pub mod budget;
pub mod dynamo;
pub mod eks;
mod error;
pub mod executions;
pub mod s3;
pub mod secrets;
pub mod tasks;
pub mod wake;

use error::condition_failed;
pub use error::{AwsError, Result};

use aws_config::{BehaviorVersion, SdkConfig};
use aws_smithy_http_client::tls::{self, rustls_provider::CryptoMode};

/// The shared SDK configuration: rustls on ring (no OpenSSL, no C toolchain), region and
/// credentials from the standard chain, `AWS_ENDPOINT_URL` honoured.
pub async fn sdk_config() -> SdkConfig {
    let http = aws_smithy_http_client::Builder::new()
        .tls_provider(tls::Provider::Rustls(CryptoMode::Ring))
        .build_https();
    aws_config::defaults(BehaviorVersion::latest())
        .http_client(http)
        .load()
        .await
}

/// The SDK configuration for an explicit endpoint (moto in tests and local mode) with dummy
/// credentials, without touching the process environment.
pub async fn sdk_config_at(endpoint: &str, region: &str) -> SdkConfig {
    let http = aws_smithy_http_client::Builder::new()
        .tls_provider(tls::Provider::Rustls(CryptoMode::Ring))
        .build_https();
    aws_config::defaults(BehaviorVersion::latest())
        .http_client(http)
        .endpoint_url(endpoint)
        .region(aws_config::Region::new(region.to_string()))
        .credentials_provider(aws_credential_types::Credentials::new(
            "testing",
            "testing",
            None,
            None,
            "lb-aws-static",
        ))
        .load()
        .await
}

/// An S3 client; path-style addressing when an endpoint override is set (moto, MinIO).
pub fn s3_client(config: &SdkConfig) -> aws_sdk_s3::Client {
    let path_style = config.endpoint_url().is_some();
    let s3 = aws_sdk_s3::config::Builder::from(config)
        .force_path_style(path_style)
        .build();
    aws_sdk_s3::Client::from_conf(s3)
}
