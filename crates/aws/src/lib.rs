//! AWS adapters of the pipeline: settings and token from Secrets Manager, the DynamoDB claim
//! and records, the S3 layout of a submission, EKS access, the wake table, task callbacks,
//! the shared EvalAI budget and the admission queue.
//!
//! Clients are concrete SDK clients built once per cold start from one [`aws_config::SdkConfig`]
//! (see [`sdk_config`]); tests point them at moto through `AWS_ENDPOINT_URL`.

pub mod admission;
pub mod budget;
pub mod dynamo;
pub mod ecr;
pub mod eks;
mod error;
pub mod executions;
pub mod record;
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

/// The DynamoDB requests a function's clients sent (attempts, retries included): what its
/// share of the orchestration's cost counts. A Lambda runs one invocation at a time, so the
/// difference across a handler is that invocation's.
#[derive(Debug, Clone, Default)]
pub struct RequestCount(std::sync::Arc<std::sync::atomic::AtomicU64>);

impl RequestCount {
    /// Requests so far.
    pub fn get(&self) -> u64 {
        self.0.load(std::sync::atomic::Ordering::Relaxed)
    }
}

/// Adds one to a [`RequestCount`] before every attempt a client sends.
#[derive(Debug)]
struct Counting(RequestCount);

impl aws_sdk_dynamodb::config::Intercept for Counting {
    fn name(&self) -> &'static str {
        "RequestCount"
    }

    fn read_before_attempt(
        &self,
        _context: &aws_sdk_dynamodb::config::interceptors::BeforeTransmitInterceptorContextRef<'_>,
        _components: &aws_sdk_dynamodb::config::RuntimeComponents,
        _cfg: &mut aws_sdk_dynamodb::config::ConfigBag,
    ) -> std::result::Result<(), aws_sdk_dynamodb::error::BoxError> {
        (self.0)
            .0
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        Ok(())
    }
}

/// A DynamoDB client whose requests `count` counts.
pub fn dynamo_client(config: &SdkConfig, count: &RequestCount) -> aws_sdk_dynamodb::Client {
    let conf = aws_sdk_dynamodb::config::Builder::from(config)
        .interceptor(Counting(count.clone()))
        .build();
    aws_sdk_dynamodb::Client::from_conf(conf)
}
