//! The whole local stack in one handle: moto, the fake EvalAI (or an external EvalAI), and the
//! AWS resources the pipeline expects, provisioned from the operator settings.

use std::time::{Duration, Instant};

use aws_config::SdkConfig;
use aws_sdk_dynamodb::types::{
    AttributeDefinition, BillingMode, KeySchemaElement, KeyType, ScalarAttributeType,
};
use fake_evalai::{FakeEvalAi, Fixture};
use lb_domain::settings::Settings;
use local_kube::LocalKube;

use crate::moto::{MotoError, MotoServer};
use crate::workloads::{image_map, Behaviour, Binaries};

/// The region the local stack uses.
pub const REGION: &str = "us-east-1";
/// Secret ids the functions are configured with locally.
pub const SETTINGS_SECRET: &str = "leaderboard/settings";
/// The EvalAI token's secret id.
pub const TOKEN_SECRET: &str = "leaderboard/evalai-token";
/// The settings of local runs and tests: phase 1 is Leaderboard 2.0 SENSORS (20 routes, 4
/// workers), phase 2 Leaderboard 1.0 SENSORS (12 routes, 3 workers), phase 3 the 2.0
/// qualifier; gating off. Matches the fake EvalAI's default fixture.
pub const LOCAL_SETTINGS: &str = include_str!("../settings/local.json");

/// Why the stack did not come up.
#[derive(Debug, thiserror::Error)]
pub enum StackError {
    /// moto.
    #[error(transparent)]
    Moto(#[from] MotoError),
    /// The fake EvalAI.
    #[error("fake EvalAI: {0}")]
    EvalAi(String),
    /// The local Kubernetes API.
    #[error("local Kubernetes API: {0}")]
    Kube(String),
    /// Creating a table, bucket or secret failed.
    #[error("provisioning `{what}` failed: {source}")]
    Provision {
        /// What was being created.
        what: String,
        /// The SDK error.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
}

impl StackError {
    /// Stable name.
    pub fn name(&self) -> &'static str {
        match self {
            StackError::Moto(_) => "MotoUnavailable",
            StackError::EvalAi(_) => "FakeEvalAiUnavailable",
            StackError::Kube(_) => "LocalKubeUnavailable",
            StackError::Provision { .. } => "ProvisionFailed",
        }
    }
}

/// Which EvalAI the stack talks to.
#[derive(Debug, Clone)]
pub enum EvalAi {
    /// Start the fake with this fixture.
    Fake(Fixture),
    /// Use a server that already runs (a real staging EvalAI, or a fake started by hand).
    External {
        /// Base URL.
        url: String,
        /// Host token.
        token: String,
    },
}

/// A running local stack. Dropping it stops every server it started.
pub struct Stack {
    /// moto on loopback.
    pub moto: MotoServer,
    /// The fake EvalAI, when the stack started one.
    pub fake_evalai: Option<FakeEvalAi>,
    /// EvalAI base URL.
    pub evalai_url: String,
    /// EvalAI host token.
    pub evalai_token: String,
    /// SDK configuration pointing at moto.
    pub sdk: SdkConfig,
    /// The local Kubernetes API, when the stack started one.
    pub kube: Option<LocalKube>,
    /// Its kubeconfig (in `workdir`).
    pub kubeconfig: Option<std::path::PathBuf>,
    /// Scratch directory of this stack (kubeconfig, pod directories); removed on drop.
    pub workdir: tempfile::TempDir,
    /// How long start-up took.
    pub started_in: Duration,
}

impl std::fmt::Debug for Stack {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Stack")
            .field("moto", &self.moto.endpoint())
            .field("evalai_url", &self.evalai_url)
            .finish_non_exhaustive()
    }
}

impl Stack {
    /// Starts moto and EvalAI side by side.
    pub async fn start(evalai: EvalAi) -> Result<Stack, StackError> {
        Self::start_with(evalai, None).await
    }

    /// Starts moto, EvalAI and, with a configuration, the local Kubernetes API, side by side.
    pub async fn start_with(
        evalai: EvalAi,
        kube: Option<local_kube::Config>,
    ) -> Result<Stack, StackError> {
        let started = Instant::now();
        let workdir = tempfile::Builder::new()
            .prefix("lb-stack-")
            .tempdir()
            .map_err(|e| StackError::Kube(format!("scratch directory: {e}")))?;
        // NB: moto's start-up (a Python import) dominates; the fake EvalAI starts meanwhile.
        let moto = tokio::task::spawn_blocking(MotoServer::start);
        let (fake_evalai, evalai_url, evalai_token) = match evalai {
            EvalAi::Fake(fixture) => {
                let server =
                    FakeEvalAi::spawn(fixture).map_err(|e| StackError::EvalAi(e.to_string()))?;
                let token = server
                    .host_token()
                    .ok_or_else(|| StackError::EvalAi("the fixture has no host token".into()))?
                    .to_string();
                let url = server.url();
                (Some(server), url, token)
            }
            EvalAi::External { url, token } => (None, url, token),
        };
        let (kube, kubeconfig) = match kube {
            Some(config) => {
                let (server, path) = spawn_kube(workdir.path(), config)?;
                (Some(server), Some(path))
            }
            None => (None, None),
        };
        let moto = moto
            .await
            .map_err(|e| StackError::EvalAi(format!("moto start-up task: {e}")))??;
        let sdk = lb_aws::sdk_config_at(&moto.endpoint(), REGION).await;
        Ok(Stack {
            moto,
            fake_evalai,
            evalai_url,
            evalai_token,
            sdk,
            kube,
            kubeconfig,
            workdir,
            started_in: started.elapsed(),
        })
    }

    /// Starts the local Kubernetes API now (when its image map needs moto's endpoint).
    pub fn start_kube(&mut self, config: local_kube::Config) -> Result<(), StackError> {
        let (server, path) = spawn_kube(self.workdir.path(), config)?;
        self.kube = Some(server);
        self.kubeconfig = Some(path);
        Ok(())
    }

    /// Starts the local Kubernetes API with the image map of a local run: the rendered Jobs run
    /// the real sidecar, the fake CARLA and the fake evaluator, S3 on this stack's moto.
    pub fn start_workloads(
        &mut self,
        settings: &Settings,
        bins: &Binaries,
        behaviour: &Behaviour,
        unpullable: &[&str],
    ) -> Result<(), StackError> {
        let scratch = self.workdir.path().join("images");
        let images = image_map(
            settings,
            bins,
            &self.moto.endpoint(),
            &scratch,
            "*",
            behaviour,
            unpullable,
        )
        .map_err(|e| StackError::Kube(format!("image map: {e}")))?;
        self.start_kube(local_kube::Config {
            images,
            ..local_kube::Config::default()
        })
    }

    /// The fake EvalAI (panics if the stack uses an external one: a test bug).
    pub fn fake(&self) -> &FakeEvalAi {
        self.fake_evalai
            .as_ref()
            .expect("this stack runs the fake EvalAI")
    }

    /// Creates what `settings` names (secrets, buckets, tables), with EvalAI pointed at this
    /// stack's. `settings_json` is the settings text; its `evalai.api_server` is replaced.
    pub async fn provision(&self, settings_json: &str) -> Result<Settings, StackError> {
        let invalid = |source: Box<dyn std::error::Error + Send + Sync>| StackError::Provision {
            what: "settings".into(),
            source,
        };
        let mut value: serde_json::Value =
            serde_json::from_str(settings_json).map_err(|e| invalid(e.into()))?;
        value["evalai"]["api_server"] = serde_json::Value::String(self.evalai_url.clone());
        let text = value.to_string();
        let settings = Settings::from_json(&text).map_err(|e| invalid(e.into()))?;

        let secrets = aws_sdk_secretsmanager::Client::new(&self.sdk);
        for (name, secret) in [
            (SETTINGS_SECRET, text.clone()),
            (
                TOKEN_SECRET,
                serde_json::json!({ "token": self.evalai_token }).to_string(),
            ),
        ] {
            secrets
                .create_secret()
                .name(name)
                .secret_string(secret)
                .send()
                .await
                .map_err(|e| provision(name, e))?;
        }
        let s3 = lb_aws::s3_client(&self.sdk);
        let dynamo = aws_sdk_dynamodb::Client::new(&self.sdk);
        for lb in settings.leaderboards.values() {
            s3.create_bucket()
                .bucket(&lb.bucket)
                .send()
                .await
                .map_err(|e| provision(&lb.bucket, e))?;
            // The original system's key schemas (reference original-system.md): all strings.
            create_table(&dynamo, &lb.submissions_table, "submission_id").await?;
            create_table(&dynamo, &lb.qualifier_table, "track_codename").await?;
        }
        Ok(settings)
    }
}

/// The local Kubernetes API with its pods and kubeconfig under `workdir`.
fn spawn_kube(
    workdir: &std::path::Path,
    mut config: local_kube::Config,
) -> Result<(LocalKube, std::path::PathBuf), StackError> {
    if config.state_dir.is_none() {
        config.state_dir = Some(workdir.join("pods"));
    }
    let server = LocalKube::spawn(config).map_err(|e| StackError::Kube(e.to_string()))?;
    let path = workdir.join("kubeconfig");
    server
        .write_kubeconfig(&path)
        .map_err(|e| StackError::Kube(e.to_string()))?;
    Ok((server, path))
}

fn provision<E>(what: &str, source: E) -> StackError
where
    E: std::error::Error + Send + Sync + 'static,
{
    StackError::Provision {
        what: what.to_string(),
        source: Box::new(source),
    }
}

/// A table keyed by `team_id` (S) and `sort_key` (S).
async fn create_table(
    client: &aws_sdk_dynamodb::Client,
    name: &str,
    sort_key: &str,
) -> Result<(), StackError> {
    let attribute = |name: &str, kind: ScalarAttributeType| {
        AttributeDefinition::builder()
            .attribute_name(name)
            .attribute_type(kind)
            .build()
            .expect("name and type are set")
    };
    let key = |name: &str, kind: KeyType| {
        KeySchemaElement::builder()
            .attribute_name(name)
            .key_type(kind)
            .build()
            .expect("name and type are set")
    };
    client
        .create_table()
        .table_name(name)
        .billing_mode(BillingMode::PayPerRequest)
        .attribute_definitions(attribute("team_id", ScalarAttributeType::S))
        .attribute_definitions(attribute(sort_key, ScalarAttributeType::S))
        .key_schema(key("team_id", KeyType::Hash))
        .key_schema(key(sort_key, KeyType::Range))
        .send()
        .await
        .map_err(|e| provision(name, e))?;
    Ok(())
}
