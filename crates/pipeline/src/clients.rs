//! Clients built once per cold start from the environment, shared by the functions' `Deps`.

use aws_config::SdkConfig;
use lb_aws::admission::AdmissionTable;
use lb_aws::budget::BudgetTable;
use lb_aws::RequestCount;
use lb_domain::settings::Settings;
use lb_evalai::{BudgetPolicy, EvalAiClient, RetryPolicy};

use crate::cluster::Clusters;
use crate::config::Shared;
use crate::queue::Admission;
use crate::{FnError, FunctionConfig};

/// The settings secret, read and checked.
pub async fn settings(sdk: &SdkConfig, config: &FunctionConfig) -> Result<Settings, FnError> {
    let secrets = aws_sdk_secretsmanager::Client::new(sdk);
    Ok(lb_aws::secrets::load_settings(&secrets, &config.settings_secret).await?)
}

/// The EvalAI client for `settings`, with the host token from its secret, taking from the
/// shared budget when the function has one.
pub async fn evalai(
    sdk: &SdkConfig,
    config: &FunctionConfig,
    settings: &Settings,
) -> Result<EvalAiClient, FnError> {
    evalai_counted(sdk, config, settings, &RequestCount::default()).await
}

/// [`evalai`], the budget's requests counted in `count`.
pub async fn evalai_counted(
    sdk: &SdkConfig,
    config: &FunctionConfig,
    settings: &Settings,
    count: &RequestCount,
) -> Result<EvalAiClient, FnError> {
    let secrets = aws_sdk_secretsmanager::Client::new(sdk);
    let token = lb_aws::secrets::load_token(&secrets, &config.token_secret).await?;
    let client = EvalAiClient::new(
        &settings.evalai.api_server,
        &token,
        settings.evalai.auth_scheme,
        RetryPolicy::default(),
    )?;
    let crate::config::Shared::Table(table) = &config.budget else {
        return Ok(client);
    };
    let policy = BudgetPolicy::evalai(settings.evalai.requests_per_minute).ok_or_else(|| {
        FnError::Config("evalai.requests_per_minute is too small to share".into())
    })?;
    let budget = BudgetTable::new(lb_aws::dynamo_client(sdk, count), table, policy);
    Ok(client.with_budget(std::sync::Arc::new(budget)))
}

/// The leaderboards' queues as the function's configuration chose them.
pub fn admission(sdk: &SdkConfig, config: &FunctionConfig) -> Admission {
    admission_counted(sdk, config, &RequestCount::default())
}

/// [`admission`], its requests counted in `count`.
pub fn admission_counted(
    sdk: &SdkConfig,
    config: &FunctionConfig,
    count: &RequestCount,
) -> Admission {
    match &config.admission {
        Shared::Table(table) => Admission::Queue(AdmissionTable::new(
            lb_aws::dynamo_client(sdk, count),
            table,
        )),
        Shared::Unlimited => Admission::Unlimited,
    }
}

/// Now, in the records' time format (the original's `2024-03-07 10:31:02 UTC`).
pub fn now_record_time() -> String {
    lb_aws::dynamo::record_time(time::OffsetDateTime::now_utc())
}

/// Now, in epoch seconds (the run state's and the wake table's clock).
pub fn now_epoch_seconds() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

/// A Lambda's cold start: its environment read once and the SDK configuration built once.
pub async fn cold_start() -> Result<(FunctionConfig, SdkConfig), FnError> {
    let config = FunctionConfig::from_env()?;
    Ok((config, lb_aws::sdk_config().await))
}

/// What the stages that watch and end a run share (Monitor, Finalize): settings, EvalAI, the
/// Job clusters, S3 and DynamoDB, built once per cold start.
#[derive(Debug)]
pub struct RunClients {
    /// The operator's configuration.
    pub settings: Settings,
    /// EvalAI, as the host.
    pub evalai: EvalAiClient,
    /// The Job clusters.
    pub clusters: Clusters,
    /// S3.
    pub s3: aws_sdk_s3::Client,
    /// DynamoDB.
    pub dynamo: aws_sdk_dynamodb::Client,
    /// The leaderboards' queues.
    pub admission: Admission,
    /// The DynamoDB requests of these clients (the orchestration's cost).
    pub dynamo_requests: RequestCount,
    /// The function's memory, MB (its invocations' cost per second).
    pub memory_mb: u32,
}

impl RunClients {
    /// The clients from an SDK configuration and cluster access (each function's cold start
    /// reads them from the environment first; local mode and tests pass their own).
    pub async fn load(
        sdk: &SdkConfig,
        config: &FunctionConfig,
        clusters: Clusters,
    ) -> Result<RunClients, FnError> {
        let settings = settings(sdk, config).await?;
        let count = RequestCount::default();
        let evalai = evalai_counted(sdk, config, &settings, &count).await?;
        Ok(RunClients {
            settings,
            evalai,
            clusters,
            s3: lb_aws::s3_client(sdk),
            dynamo: lb_aws::dynamo_client(sdk, &count),
            admission: admission_counted(sdk, config, &count),
            dynamo_requests: count,
            memory_mb: config.memory_mb,
        })
    }
}

/// One invocation's share of the orchestration, measured from its start: its Lambda time and
/// the DynamoDB requests its clients sent since (`lb_domain::cost::Orchestration`). Every
/// stage that adds its share to the run's count measures it the same way.
#[derive(Debug)]
pub struct Meter<'a> {
    began: std::time::Instant,
    requests: u64,
    count: &'a RequestCount,
    memory_mb: u32,
}

impl<'a> Meter<'a> {
    /// Starts measuring an invocation of a function of `memory_mb` whose clients count their
    /// requests in `count`.
    pub fn start(count: &'a RequestCount, memory_mb: u32) -> Self {
        Meter {
            began: std::time::Instant::now(),
            requests: count.get(),
            count,
            memory_mb,
        }
    }

    /// The invocation so far, with the `transitions` it causes.
    pub fn invocation(&self, transitions: u64) -> lb_domain::cost::Orchestration {
        lb_domain::cost::Orchestration::invocation(
            transitions,
            self.memory_mb,
            u64::try_from(self.began.elapsed().as_millis()).unwrap_or(u64::MAX),
            self.count.get().saturating_sub(self.requests),
        )
    }
}

/// What a handler keeps for itself after its last EvalAI call: raising its error or writing
/// its record.
pub const REPORT_MARGIN: std::time::Duration = std::time::Duration::from_secs(10);

/// The instant a Lambda invocation's EvalAI calls must be done by: its deadline (from the
/// runtime's context, milliseconds since the epoch) less [`REPORT_MARGIN`].
pub fn invocation_deadline(context: &lambda_runtime::Context) -> std::time::Instant {
    let left = context
        .deadline()
        .duration_since(std::time::SystemTime::now())
        .unwrap_or_default()
        .saturating_sub(REPORT_MARGIN);
    std::time::Instant::now() + left
}

/// Runs one invocation's work with its EvalAI calls bounded by the invocation's deadline,
/// and the whole of it (AWS SDK and Kubernetes calls included) cut at half the margin after
/// it: a transient `DeadlineExceeded` the state machine retries (every handler is
/// idempotent), rather than Lambda's own timeout, which no Retry names.
pub async fn within_deadline<T>(
    context: &lambda_runtime::Context,
    work: impl std::future::Future<Output = Result<T, FnError>>,
) -> Result<T, FnError> {
    let deadline = invocation_deadline(context);
    bounded(deadline, deadline + REPORT_MARGIN / 2, work).await
}

async fn bounded<T>(
    evalai_deadline: std::time::Instant,
    cutoff: std::time::Instant,
    work: impl std::future::Future<Output = Result<T, FnError>>,
) -> Result<T, FnError> {
    let work = lb_evalai::within(evalai_deadline, work);
    match tokio::time::timeout_at(tokio::time::Instant::from_std(cutoff), work).await {
        Ok(done) => done,
        Err(_) => {
            tracing::warn!("the invocation's time ran out; the state machine retries it");
            Err(FnError::DeadlineExceeded)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

    #[test]
    fn the_evalai_deadline_leaves_the_handler_its_margin() {
        let mut context = lambda_runtime::Context::default();
        let in_30s = SystemTime::now() + Duration::from_secs(30);
        context.deadline = in_30s.duration_since(UNIX_EPOCH).unwrap().as_millis() as u64;
        let left = invocation_deadline(&context).saturating_duration_since(Instant::now());
        assert!(
            left > Duration::from_secs(19) && left <= Duration::from_secs(20),
            "{left:?}"
        );
        // A deadline already past gives no time at all, not a panic.
        context.deadline = 1;
        assert!(invocation_deadline(&context) <= Instant::now());
    }

    #[tokio::test]
    async fn work_that_outlasts_the_invocation_ends_as_a_transient_deadline_error() {
        let now = Instant::now();
        let stuck = async {
            // An SDK or Kubernetes call that hangs (no EvalAI deadline applies to it).
            tokio::time::sleep(Duration::from_secs(3600)).await;
            Ok::<_, FnError>(())
        };
        let err = bounded(now, now + Duration::from_millis(50), stuck)
            .await
            .unwrap_err();
        assert_eq!(err.name(), "DeadlineExceeded");
        assert!(err.is_transient());
        assert!(FnError::transient_names().contains(&err.name()));
        assert!(now.elapsed() < Duration::from_secs(5));
        let quick = bounded(now, now + Duration::from_secs(5), async {
            Ok::<_, FnError>(7)
        });
        assert_eq!(quick.await.unwrap(), 7);
    }
}
