//! The whole local stack in one handle: moto, the fake EvalAI (or an external EvalAI), and the
//! AWS resources the pipeline expects, provisioned from the operator settings.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use aws_config::SdkConfig;
use aws_sdk_dynamodb::types::{
    AttributeDefinition, BillingMode, KeySchemaElement, KeyType, ScalarAttributeType,
};
use aws_sdk_sqs::types::QueueAttributeName;
use fake_evalai::{FakeEvalAi, Fixture};
use lb_domain::settings::Settings;
use local_kube::LocalKube;

use crate::moto::{MotoError, MotoServer};
use crate::real::{node_of, RealCluster};
use crate::workloads::{image_map, Behaviour, Binaries};
use lb_infra::template::{Template, TemplateError, APP};

/// The region the local stack uses.
pub const REGION: &str = "us-east-1";
/// Secret ids the functions are configured with locally.
pub const SETTINGS_SECRET: &str = "leaderboard/settings";
/// The EvalAI token's secret id.
pub const TOKEN_SECRET: &str = "leaderboard/evalai-token";
/// The wake table's name in local mode (`${AWS::StackName}-wakes`).
pub const WAKE_TABLE: &str = "leaderboard-wakes";
/// The EvalAI budget table's name in local mode (`${AWS::StackName}-evalai-budget`).
pub const BUDGET_TABLE: &str = "leaderboard-evalai-budget";
/// The admission table's name in local mode (`${AWS::StackName}-admission`).
pub const ADMISSION_TABLE: &str = "leaderboard-admission";

/// The environment the template gives every function, with local mode's names.
pub fn function_config() -> lb_pipeline::FunctionConfig {
    lb_pipeline::FunctionConfig {
        settings_secret: SETTINGS_SECRET.into(),
        token_secret: TOKEN_SECRET.into(),
        wake_table: Some(WAKE_TABLE.into()),
        budget: lb_pipeline::config::Shared::Table(BUDGET_TABLE.into()),
        admission: lb_pipeline::config::Shared::Table(ADMISSION_TABLE.into()),
        // The template's default (`ConsolidateNodes`): the sweep drains as it would deployed.
        consolidate_nodes: true,
        // The template's Monitor and Finalize, which take most of a run's Lambda time.
        memory_mb: 512,
    }
}
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
    /// The functions' kubeconfig.
    pub kubeconfig: Option<std::path::PathBuf>,
    /// The operator's kubeconfig, when it is another identity.
    pub operator_kubeconfig: Option<std::path::PathBuf>,
    /// The sweep's kubeconfig (the fleet's group), when it is another identity.
    pub fleet_kubeconfig: Option<std::path::PathBuf>,
    /// The real control plane and its node agent, when the workloads run there.
    pub real: Option<RealCluster>,
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

    /// Starts moto and EvalAI and provisions what `infra/app.yaml` declares for the settings
    /// `settings_json` (the stack every emulator test and the rehearsal begin with).
    pub async fn provisioned(
        evalai: EvalAi,
        settings_json: &str,
    ) -> Result<(Stack, Settings), StackError> {
        let stack = Self::start(evalai).await?;
        let settings = stack.provision(settings_json).await?;
        Ok((stack, settings))
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
            operator_kubeconfig: None,
            fleet_kubeconfig: None,
            real: None,
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
        let images = self.images(settings, bins, behaviour, unpullable)?;
        let node = node_of(settings, behaviour);
        self.start_kube(local_kube::Config {
            images,
            gpus: behaviour.node_gpus,
            instance_type: node.instance_type,
            labels: node.labels,
            autoscaler: true,
            ..local_kube::Config::default()
        })
    }

    /// The same workloads on the real Kubernetes control plane (`make real-kube` builds it):
    /// `infra/k8s` applied, its scheduler placing the pods on GPU nodes of the settings'
    /// instance type, local-kube's process runner as their kubelet, and a stand-in for the
    /// Cluster Autoscaler's word. The functions' kubeconfig is the pipeline's identity.
    pub fn start_real_workloads(
        &mut self,
        settings: &Settings,
        bins: &Binaries,
        behaviour: &Behaviour,
        unpullable: &[&str],
    ) -> Result<(), StackError> {
        let images = self.images(settings, bins, behaviour, unpullable)?;
        let real = RealCluster::start(settings, behaviour, images, self.workdir.path())?;
        self.kubeconfig = Some(real.plane.kubeconfig(real_kube::Identity::Pipeline));
        self.operator_kubeconfig = Some(real.plane.kubeconfig(real_kube::Identity::Admin));
        self.fleet_kubeconfig = Some(real.plane.kubeconfig(real_kube::Identity::Fleet));
        self.real = Some(real);
        Ok(())
    }

    /// The image map of a local run.
    fn images(
        &self,
        settings: &Settings,
        bins: &Binaries,
        behaviour: &Behaviour,
        unpullable: &[&str],
    ) -> Result<local_kube::ImageMap, StackError> {
        let scratch = self.workdir.path().join("images");
        image_map(
            settings,
            bins,
            &self.moto.endpoint(),
            &scratch,
            "*",
            behaviour,
            unpullable,
        )
        .map_err(|e| StackError::Kube(format!("image map: {e}")))
    }

    /// The kubeconfig an operator uses (and a managed node group's drain acts as): the
    /// functions' own on local-kube, the admin's on the real control plane.
    pub fn operator_kubeconfig(&self) -> Option<&std::path::Path> {
        self.operator_kubeconfig
            .as_deref()
            .or(self.kubeconfig.as_deref())
    }

    /// The kubeconfig the sweep counts and drains the nodes with: the functions' own on
    /// local-kube, the fleet group's on the real control plane.
    pub fn fleet_kubeconfig(&self) -> Option<&std::path::Path> {
        self.fleet_kubeconfig
            .as_deref()
            .or(self.kubeconfig.as_deref())
    }

    /// The fake EvalAI (panics if the stack uses an external one: a test bug).
    pub fn fake(&self) -> &FakeEvalAi {
        self.fake_evalai
            .as_ref()
            .expect("this stack runs the fake EvalAI")
    }

    /// Creates the queues, secrets, buckets and tables `infra/app.yaml` declares, with the
    /// names `settings` gives them (as an operator's parameter overrides would), and puts the
    /// settings (EvalAI pointed at this stack's) and the token in the secrets. `settings_json`
    /// is the settings text; its `evalai.api_server` is replaced.
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
        let template = app_template(&settings);
        let token = serde_json::json!({ "token": self.evalai_token }).to_string();
        let provisioner = Provisioner {
            template: &template,
            sdk: &self.sdk,
        };
        provisioner
            .secrets(&[("SettingsSecret", &text), ("EvalAiTokenSecret", &token)])
            .await?;
        provisioner.buckets().await?;
        provisioner.tables().await?;
        let queues = provisioner.queues().await?;
        provisioner.rules(&queues).await?;
        Ok(settings)
    }
}

/// `infra/app.yaml` as local mode deploys it: stack `leaderboard` (so the secrets are
/// [`SETTINGS_SECRET`] and [`TOKEN_SECRET`]), moto's account, this region, and each
/// leaderboard's names from `settings`.
pub fn app_template(settings: &Settings) -> Template {
    let mut template = APP.clone().in_stack("leaderboard", REGION, MOTO_ACCOUNT);
    for (key, lb) in &settings.leaderboards {
        let prefix = format!("Leaderboard{}", key.as_str().replace('.', ""));
        for (suffix, value) in [
            ("Bucket", &lb.bucket),
            ("SubmissionsTable", &lb.submissions_table),
            ("QualifierTable", &lb.qualifier_table),
            ("Cluster", &lb.cluster),
        ] {
            template = template.with_parameter(&format!("{prefix}{suffix}"), value.clone());
        }
    }
    template
}

/// The account moto reports.
pub const MOTO_ACCOUNT: &str = "123456789012";

/// Creates a template's resources of the types local mode needs, through the SDK.
struct Provisioner<'a> {
    template: &'a Template,
    sdk: &'a SdkConfig,
}

impl Provisioner<'_> {
    fn name(&self, id: &str) -> Result<String, StackError> {
        self.template
            .physical_name(id)
            .map_err(|e| provision(id, e))
    }

    /// Each declared secret, with the value given for its logical id.
    async fn secrets(&self, values: &[(&str, &str)]) -> Result<(), StackError> {
        let client = aws_sdk_secretsmanager::Client::new(self.sdk);
        for id in self.template.resources_of("AWS::SecretsManager::Secret") {
            let name = self.name(&id)?;
            let mut create = client.create_secret().name(&name);
            if let Some((_, value)) = values.iter().find(|(i, _)| *i == id) {
                create = create.secret_string(*value);
            }
            create.send().await.map_err(|e| provision(&name, e))?;
        }
        for (expected, id) in [
            (SETTINGS_SECRET, "SettingsSecret"),
            (TOKEN_SECRET, "EvalAiTokenSecret"),
        ] {
            let name = self.name(id)?;
            if name != expected {
                return Err(provision(
                    id,
                    TemplateError::Invalid(format!(
                        "secret `{id}` is named `{name}`, local mode configures `{expected}`"
                    )),
                ));
            }
        }
        Ok(())
    }

    async fn buckets(&self) -> Result<(), StackError> {
        let s3 = lb_aws::s3_client(self.sdk);
        for id in self.template.resources_of("AWS::S3::Bucket") {
            let name = self.name(&id)?;
            s3.create_bucket()
                .bucket(&name)
                .send()
                .await
                .map_err(|e| provision(&name, e))?;
            // The bucket's events to EventBridge, as the template declares (moto then hands
            // each object event to the rules, as S3 does: moto/s3/notifications.py).
            let eventbridge = self
                .template
                .text(
                    &id,
                    &[
                        "NotificationConfiguration",
                        "EventBridgeConfiguration",
                        "EventBridgeEnabled",
                    ],
                )
                .is_ok_and(|v| v == "true");
            if eventbridge {
                s3.put_bucket_notification_configuration()
                    .bucket(&name)
                    .notification_configuration(
                        aws_sdk_s3::types::NotificationConfiguration::builder()
                            .event_bridge_configuration(
                                aws_sdk_s3::types::EventBridgeConfiguration::builder().build(),
                            )
                            .build(),
                    )
                    .send()
                    .await
                    .map_err(|e| provision(&name, e))?;
            }
        }
        Ok(())
    }

    /// EventBridge rules with an event pattern, on the default bus, with their SQS targets
    /// (by the queue ARNs `queues` maps from `<Id.Arn>`), named by logical id. Scheduled rules
    /// and function targets are local mode's to play (`lbctl local run`'s relays).
    async fn rules(&self, queues: &BTreeMap<String, String>) -> Result<(), StackError> {
        let client = aws_sdk_eventbridge::Client::new(self.sdk);
        let root = self.template.root();
        for id in self.template.resources_of("AWS::Events::Rule") {
            let props = &root["Resources"][id.as_str()]["Properties"];
            if props["EventPattern"].is_null() {
                continue;
            }
            let pattern = self.template.json(&props["EventPattern"]);
            client
                .put_rule()
                .name(&id)
                .event_pattern(pattern.to_string())
                .send()
                .await
                .map_err(|e| provision(&id, e))?;
            for target in props["Targets"].as_sequence().into_iter().flatten() {
                let reference = self.template.eval(&target["Arn"]).unwrap_or_default();
                let Some(arn) = queues.get(&reference) else {
                    continue;
                };
                let built = aws_sdk_eventbridge::types::Target::builder()
                    .id(self.template.eval(&target["Id"]).unwrap_or_default())
                    .arn(arn)
                    .build()
                    .map_err(|e| provision(&id, e))?;
                client
                    .put_targets()
                    .rule(&id)
                    .targets(built)
                    .send()
                    .await
                    .map_err(|e| provision(&id, e))?;
            }
        }
        Ok(())
    }

    /// Tables with the template's key schema and attribute types.
    async fn tables(&self) -> Result<(), StackError> {
        let client = aws_sdk_dynamodb::Client::new(self.sdk);
        for id in self.template.resources_of("AWS::DynamoDB::Table") {
            let name = self.name(&id)?;
            let root = self.template.root();
            let props = &root["Resources"][id.as_str()]["Properties"];
            let mut create = client
                .create_table()
                .table_name(&name)
                .billing_mode(BillingMode::PayPerRequest);
            for a in props["AttributeDefinitions"]
                .as_sequence()
                .into_iter()
                .flatten()
            {
                let kind =
                    ScalarAttributeType::from(a["AttributeType"].as_str().unwrap_or_default());
                create = create.attribute_definitions(
                    AttributeDefinition::builder()
                        .attribute_name(a["AttributeName"].as_str().unwrap_or_default())
                        .attribute_type(kind)
                        .build()
                        .map_err(|e| provision(&name, e))?,
                );
            }
            for k in props["KeySchema"].as_sequence().into_iter().flatten() {
                let kind = KeyType::from(k["KeyType"].as_str().unwrap_or_default());
                create = create.key_schema(
                    KeySchemaElement::builder()
                        .attribute_name(k["AttributeName"].as_str().unwrap_or_default())
                        .key_type(kind)
                        .build()
                        .map_err(|e| provision(&name, e))?,
                );
            }
            create.send().await.map_err(|e| provision(&name, e))?;
        }
        Ok(())
    }

    /// Queues with their attributes; a redrive target is created before the queue naming it.
    /// Returns each queue's ARN by `<Id.Arn>`.
    async fn queues(&self) -> Result<BTreeMap<String, String>, StackError> {
        let client = aws_sdk_sqs::Client::new(self.sdk);
        let root = self.template.root();
        let mut ids = self.template.resources_of("AWS::SQS::Queue");
        ids.sort_by_key(|id| {
            !root["Resources"][id.as_str()]["Properties"]["RedrivePolicy"].is_null()
        });
        let mut arns = BTreeMap::new();
        for id in ids {
            let name = self.name(&id)?;
            let props = &root["Resources"][id.as_str()]["Properties"];
            let mut create = client.create_queue().queue_name(&name);
            for (key, attribute) in [
                ("VisibilityTimeout", QueueAttributeName::VisibilityTimeout),
                (
                    "MessageRetentionPeriod",
                    QueueAttributeName::MessageRetentionPeriod,
                ),
                ("MaximumMessageSize", QueueAttributeName::MaximumMessageSize),
            ] {
                if let Some(value) = self.template.eval(&props[key]) {
                    create = create.attributes(attribute, value);
                }
            }
            let redrive = &props["RedrivePolicy"];
            if !redrive.is_null() {
                let target = self
                    .template
                    .eval(&redrive["deadLetterTargetArn"])
                    .unwrap_or_default();
                let arn = arns.get(&target).cloned().ok_or_else(|| {
                    provision(
                        &name,
                        TemplateError::Missing(format!("redrive target {target}")),
                    )
                })?;
                let policy = serde_json::json!({
                    "deadLetterTargetArn": arn,
                    "maxReceiveCount": self.template.eval(&redrive["maxReceiveCount"]),
                });
                create = create.attributes(QueueAttributeName::RedrivePolicy, policy.to_string());
            }
            let url = create
                .send()
                .await
                .map_err(|e| provision(&name, e))?
                .queue_url
                .unwrap_or_default();
            let arn = crate::pipe::queue_arn(&client, &url)
                .await
                .map_err(|e| provision(&name, e))?;
            arns.insert(format!("<{id}.Arn>"), arn);
        }
        Ok(arns)
    }
}

/// The name of EvalAI's queue in local mode.
pub fn submissions_queue() -> String {
    APP.physical_name("SubmissionsQueue")
        .expect("infra/app.yaml declares SubmissionsQueue")
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
