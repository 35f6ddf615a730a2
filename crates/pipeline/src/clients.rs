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
/// the DynamoDB requests its clients sent since (`lb_domain::capacity::cost::Orchestration`). Every
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
    pub fn invocation(&self, transitions: u64) -> lb_domain::capacity::cost::Orchestration {
        lb_domain::capacity::cost::Orchestration::invocation(
            transitions,
            self.memory_mb,
            u64::try_from(self.began.elapsed().as_millis()).unwrap_or(u64::MAX),
            self.count.get().saturating_sub(self.requests),
        )
    }
}
