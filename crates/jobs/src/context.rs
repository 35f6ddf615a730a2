//! The job context: everything a Job template may read, typed, validated and built from the
//! plan, the submission and the leaderboard's settings.
//!
//! It serializes to the JSON the templates' `.$` paths read (documented field by field in
//! `templates/README.md`). It has no `Option` fields, so a path that resolves against one
//! context resolves against all of them, and no field for any secret: the EvalAI token
//! cannot reach a Job because there is nowhere to put it.

use std::collections::BTreeMap;

use lb_domain::cluster::resources::{Allotment, PairAllotment, Storage, VolumeSizes};
use lb_domain::job::plan::{
    is_dns_label, is_label_key, is_label_value, label_value, JobPlan, Plan, COMPONENT_LABEL,
    COMPONENT_SUBMISSION, EXECUTION_LABEL, JOB_INDEX_LABEL, LEADERBOARD_LABEL, MANAGED_BY,
    MANAGED_BY_LABEL, SUBMISSION_LABEL, TEAM_ID_LABEL, TEAM_LABEL, TRACK_LABEL,
};
use lb_domain::results::Leaderboard;
use lb_domain::settings::LeaderboardSettings;
use lb_domain::submission::SubmissionInfo;
use serde::{Deserialize, Serialize};

use crate::image::parse_image;

/// How much of the team name the `team-name` annotation keeps.
pub const MAX_TEAM_NAME_ANNOTATION: usize = 256;

/// The service account submission pods run as (created un-annotated by `infra/k8s/rbac.yaml`;
/// the IRSA role of `infra/cluster.yaml` trusts its tokens).
pub const SERVICE_ACCOUNT: &str = "submission-worker";

/// Where the projected service-account token for IRSA is mounted in init and logcopy.
pub const AWS_TOKEN_DIR: &str = "/var/run/secrets/eks.amazonaws.com/serviceaccount";

/// Why a job context cannot be built. Each variant has a stable [`name`](Self::name).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ContextError {
    /// An image reference outside the reference grammar.
    #[error("the {field} `{image}` is not a valid image reference: {reason}")]
    InvalidImage {
        /// Which image (`participant image`, `CARLA image`, ...).
        field: &'static str,
        /// The reference as given (control characters escaped).
        image: String,
        /// What is wrong.
        reason: String,
    },
    /// A setting or submission field with an unusable value.
    #[error("`{field}` = `{value}` is invalid: {reason}")]
    InvalidSetting {
        /// The setting.
        field: &'static str,
        /// Its value (control characters escaped, shortened).
        value: String,
        /// What is wrong.
        reason: String,
    },
}

lb_domain::error_names!(ContextError {
    InvalidImage => "InvalidImage";
    InvalidSetting => "InvalidJobSetting";
});

fn shown(value: &str) -> String {
    let escaped: String = value.escape_debug().collect();
    if escaped.chars().count() > 200 {
        format!("{}...", escaped.chars().take(200).collect::<String>())
    } else {
        escaped
    }
}

fn invalid(field: &'static str, value: impl ToString, reason: impl Into<String>) -> ContextError {
    ContextError::InvalidSetting {
        field,
        value: shown(&value.to_string()),
        reason: reason.into(),
    }
}

/// Directories of the official code inside the private-contents image (init copies them).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Sources {
    /// Leaderboard (with the private routes under `data/`).
    pub leaderboard: String,
    /// ScenarioRunner.
    pub scenario_runner: String,
    /// CARLA PythonAPI.
    pub carla_api: String,
}

/// The sidecar's timers, in seconds (the in-Job contract's optional variables).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Timers {
    /// `LB_START_WAIT_SECONDS`: the agent waits this long for CARLA's start marker.
    pub start_wait_seconds: u32,
    /// `LB_END_WAIT_SECONDS`: a container waits this long for its partner at the end.
    pub end_wait_seconds: u32,
    /// `LB_CARLA_READY_SECONDS`: CARLA must accept connections within this.
    pub carla_ready_seconds: u32,
    /// `LB_POLL_SECONDS`: marker polling period.
    pub poll_seconds: u32,
    /// `LB_MAX_IDLE_SECONDS`: the agent is stopped after this long without output.
    pub max_idle_seconds: u32,
    /// `LB_PERIOD_SECONDS`: logcopy's upload period.
    pub logcopy_period_seconds: u32,
}

impl Default for Timers {
    fn default() -> Self {
        Timers {
            start_wait_seconds: 3600,
            end_wait_seconds: 600,
            carla_ready_seconds: 300,
            poll_seconds: 1,
            max_idle_seconds: 800,
            logcopy_period_seconds: 10,
        }
    }
}

/// What a Job needs from the deployment, per leaderboard. Build it with
/// [`JobSettings::from_deployment`] and adjust fields as the configuration says.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct JobSettings {
    /// Namespace of the Jobs.
    pub namespace: String,
    /// Service account of the Pods. It must carry no `eks.amazonaws.com/role-arn`
    /// annotation (see `templates/README.md`: the webhook would hand AWS credentials to
    /// every container); the IAM role trusts `system:serviceaccount:<namespace>:<this>`.
    pub service_account: String,
    /// IAM role init and logcopy assume (IRSA) to read and write the bucket.
    pub s3_role_arn: String,
    /// AWS region of the bucket and STS.
    pub region: String,
    /// Submissions bucket.
    pub bucket: String,
    /// The node labels a pair needs (`LeaderboardSettings::node_selector`): its GPU model, and
    /// the capacity type when the leaderboard pins it.
    pub node_selector: BTreeMap<String, String>,
    /// CARLA server image.
    pub carla_image: String,
    /// Init/logcopy image (official code, private routes, the sidecar).
    pub private_contents_image: String,
    /// Job `backoffLimit`: failed pods before the Job fails. Each crash ends a pod and the next
    /// one resumes (a disrupted pod is not counted): 4 allows four resumes.
    pub backoff_limit: u32,
    /// Job `activeDeadlineSeconds`.
    pub active_deadline_seconds: u64,
    /// Job `ttlSecondsAfterFinished` (a safety net: Finalize deletes the Jobs).
    pub ttl_seconds_after_finished: u32,
    /// Pod `terminationGracePeriodSeconds` (logcopy's final upload on deletion).
    pub termination_grace_seconds: u32,
    /// Evaluator `--repetitions` (1.0: 5, 2.0: 1).
    pub repetitions: u32,
    /// Routes file for regular tracks.
    pub routes_file: String,
    /// Routes file for qualifier tracks.
    pub qualifier_routes_file: String,
    /// The track is a qualifier: its Jobs run [`qualifier_routes_file`](Self::qualifier_routes_file).
    pub qualifier: bool,
    /// Scenarios file (Leaderboard 1.0 only; empty for 2.0).
    pub scenarios_file: String,
    /// Official code directories in the private-contents image.
    pub sources: Sources,
    /// The sidecar's timers.
    pub timers: Timers,
    /// CPU, memory and `/dev/shm` of each pair (requests equal limits).
    pub resources: PairAllotment,
    /// `LB_MAX_LOG_OBJECTS`: log objects each pair's logcopy may store over the evaluation.
    pub max_log_objects_per_pair: u32,
}

impl JobSettings {
    /// The defaults for `leaderboard`, with the cluster-specific values from the operator's
    /// deployment settings, the region and the S3 role.
    pub fn from_deployment(
        leaderboard: Leaderboard,
        deployment: &LeaderboardSettings,
        region: &str,
        s3_role_arn: &str,
    ) -> Result<JobSettings, ContextError> {
        let resources = deployment
            .pair_share()
            .map_err(|(field, reason)| ContextError::InvalidSetting {
                field,
                value: deployment.instance_type.clone(),
                reason,
            })?
            .allotment();
        let node_selector =
            deployment
                .node_selector()
                .map_err(|(field, reason)| ContextError::InvalidSetting {
                    field,
                    value: deployment.instance_type.clone(),
                    reason,
                })?;
        let repetitions = leaderboard.repetitions();
        let scenarios = match leaderboard {
            Leaderboard::V1 => {
                "/workspace/leaderboard/data/all_towns_traffic_scenarios_private.json"
            }
            Leaderboard::V2 => "",
        };
        Ok(JobSettings {
            namespace: deployment.namespace.clone(),
            service_account: SERVICE_ACCOUNT.into(),
            s3_role_arn: s3_role_arn.into(),
            region: region.into(),
            bucket: deployment.bucket.clone(),
            node_selector,
            carla_image: deployment.images.carla.clone(),
            private_contents_image: deployment.images.private_contents.clone(),
            backoff_limit: 4,
            active_deadline_seconds: lb_domain::run::schedule::JOB_DEADLINE.as_secs(),
            ttl_seconds_after_finished: 24 * 3600,
            termination_grace_seconds: 60,
            repetitions,
            routes_file: "/workspace/leaderboard/data/routes_testing.xml".into(),
            qualifier_routes_file: "/workspace/leaderboard/data/routes_qualifier.xml".into(),
            qualifier: false,
            scenarios_file: scenarios.into(),
            sources: Sources {
                leaderboard: "/src/leaderboard".into(),
                scenario_runner: "/src/scenario_runner".into(),
                carla_api: "/src/CARLA".into(),
            },
            timers: Timers::default(),
            resources,
            max_log_objects_per_pair: deployment.max_log_objects_per_pair,
        })
    }
}

/// What logcopy may store, besides its bytes per pair.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct UploadsContext {
    /// `LB_MAX_LOG_OBJECTS`.
    pub max_log_objects_per_pair: u32,
}

/// The team, as the Job may show it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct TeamContext {
    /// EvalAI participant team id.
    pub id: u64,
    /// The name without control characters, cut to 256 characters (annotation only).
    pub name: String,
    /// Label-safe form of the name (possibly empty).
    pub label: String,
}

/// Images of the Job's containers, each checked against the reference grammar.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ImagesContext {
    /// CARLA server.
    pub carla: String,
    /// Init and logcopy.
    pub private_contents: String,
    /// The participant's agent.
    pub participant: String,
}

/// What the evaluator runs.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct EvaluationContext {
    /// `ROUTES`: the routes file (qualifier routes on a qualifier track).
    pub routes_file: String,
    /// `SCENARIOS` (Leaderboard 1.0; empty for 2.0).
    pub scenarios_file: String,
    /// `REPETITIONS`.
    pub repetitions: u32,
}

/// AWS access of init and logcopy (IRSA through an explicitly projected token).
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct AwsContext {
    /// `AWS_REGION`.
    pub region: String,
    /// `LB_S3_BUCKET`.
    pub bucket: String,
    /// `AWS_ROLE_ARN`.
    pub role_arn: String,
    /// `AWS_WEB_IDENTITY_TOKEN_FILE`.
    pub token_file: String,
}

/// Kubernetes settings of the Job and its Pod.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct KubernetesContext {
    /// Namespace.
    pub namespace: String,
    /// Service account (no role annotation; see [`JobSettings::service_account`]).
    pub service_account: String,
    /// The Pod's `nodeSelector`.
    pub node_selector: BTreeMap<String, String>,
    /// `backoffLimit`.
    pub backoff_limit: u32,
    /// The `FailJob` rule's exit codes (`lb_domain::job::protocol::exit::FAIL_JOB`).
    pub fail_job_exit_codes: Vec<u8>,
    /// `activeDeadlineSeconds`.
    pub active_deadline_seconds: u64,
    /// `ttlSecondsAfterFinished`.
    pub ttl_seconds_after_finished: u32,
    /// `terminationGracePeriodSeconds`.
    pub termination_grace_seconds: u32,
}

/// Requests and limits of one container, in the shape of Kubernetes' `resources`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ContainerResources {
    /// What the scheduler reserves.
    pub requests: Quantities,
    /// The same CPU and memory: a container cannot take more than it reserved; more disk
    /// than it reserved, up to its limit ([`Storage`]).
    pub limits: Quantities,
}

/// CPU, memory and GPU quantities (`6000m`, `24576Mi`, `1`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Quantities {
    /// CPU, millicores.
    pub cpu: String,
    /// Memory, MiB.
    pub memory: String,
    /// GPUs the NVIDIA device plugin allocates (extended resource: request = limit).
    #[serde(rename = "nvidia.com/gpu", skip_serializing_if = "Option::is_none")]
    pub gpu: Option<String>,
    /// Local disk besides the volumes, GiB (`4Gi`).
    #[serde(rename = "ephemeral-storage")]
    pub storage: String,
}

impl ContainerResources {
    /// CPU and memory requested and limited alike, disk as `storage` says.
    pub fn of(a: Allotment, storage: Storage) -> Self {
        let q = |gib: u32| Quantities {
            cpu: format!("{}m", a.cpu_millis),
            memory: format!("{}Mi", a.memory_mib),
            gpu: None,
            storage: format!("{gib}Gi"),
        };
        ContainerResources {
            requests: q(storage.request_gib),
            limits: q(storage.limit_gib),
        }
    }

    /// The same with one GPU allocated by the device plugin: the pair's GPU is held by its
    /// agent (the untrusted container sees only that GPU) and handed to its simulator by
    /// UUID through the status volume (templates/README.md, "One GPU per pair").
    pub fn with_gpu(mut self) -> Self {
        self.requests.gpu = Some("1".into());
        self.limits.gpu = Some("1".into());
        self
    }
}

/// What the Job's containers may use.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ResourcesContext {
    /// Each `simulator-<ID>`.
    pub simulator: ContainerResources,
    /// Each `agent-<ID>`, with the pair's GPU.
    pub agent: ContainerResources,
    /// `private-contents`.
    pub sidecar: ContainerResources,
    /// `logcopy`: the sidecar's, with the disk-backed volumes' room requested
    /// ([`Storage::logcopy`]).
    pub logcopy: ContainerResources,
    /// `sizeLimit` of the Pod's `/dev/shm`: the per-pair size times the Job's pairs.
    pub shm: String,
    /// `sizeLimit`s of the disk-backed volumes.
    pub volumes: VolumesContext,
}

/// `sizeLimit`s of the Pod's disk-backed `emptyDir` volumes ([`VolumeSizes`]).
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct VolumesContext {
    /// `logs`: the per-pair size times the Job's pairs.
    pub logs: String,
    /// `lb-bin`.
    pub bin: String,
    /// Each of `leaderboard`, `scenario-runner` and `carla-api`.
    pub sources: String,
}

impl VolumesContext {
    fn of(sizes: VolumeSizes, pairs: u32) -> Self {
        VolumesContext {
            logs: format!("{}Gi", sizes.logs_per_pair_gib * pairs),
            bin: format!("{}Mi", sizes.bin_mib),
            sources: format!("{}Mi", sizes.sources_mib),
        }
    }
}

/// This Job within the submission.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct JobInfo {
    /// 0-based index.
    pub index: u32,
    /// Name (a DNS-1123 label).
    pub name: String,
    /// Its pair IDs, comma separated (`LB_PAIRS`).
    pub pair_ids: String,
    /// How many pairs it holds.
    pub pair_count: u32,
}

/// One simulator-agent pair (the `pair` of the pair section).
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct PairContext {
    /// 1-based global ID.
    pub id: u32,
    /// 0-based worker index.
    pub worker: u32,
    /// `ROUTES_SUBSET` (`a-b`).
    pub routes: String,
    /// `CARLA_PORT`.
    pub carla_port: u16,
    /// `CARLA_TM_PORT`.
    pub tm_port: u16,
}

/// Everything a Job template reads. Serialized, it is the input of the `.$` paths.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct JobContext {
    /// Which leaderboard (`"1.0"` or `"2.0"` to the template).
    pub leaderboard: Leaderboard,
    /// EvalAI submission id.
    pub submission_id: u64,
    /// EvalAI challenge id.
    pub challenge_id: u64,
    /// EvalAI phase id.
    pub phase_id: u64,
    /// The team.
    pub team: TeamContext,
    /// Track codename.
    pub track: String,
    /// `LB_PARTICIPANT_RESUME`: `1` or empty.
    pub participant_resume: String,
    /// Images.
    pub images: ImagesContext,
    /// Evaluator settings.
    pub evaluation: EvaluationContext,
    /// AWS access of init and logcopy.
    pub aws: AwsContext,
    /// Job and Pod settings.
    pub kubernetes: KubernetesContext,
    /// Requests and limits.
    pub resources: ResourcesContext,
    /// Sidecar timers.
    pub timers: Timers,
    /// What logcopy may store.
    pub uploads: UploadsContext,
    /// Official code in the private-contents image.
    pub sources: Sources,
    /// This Job.
    pub job: JobInfo,
    /// Labels of the Job and its Pods.
    pub labels: BTreeMap<String, String>,
    /// The Job's pairs.
    pub pairs: Vec<PairContext>,
}

fn check_path(field: &'static str, value: &str, allow_empty: bool) -> Result<(), ContextError> {
    if value.is_empty() && allow_empty {
        return Ok(());
    }
    // NB: restricted so nothing Kubernetes (`$(VAR)`) or a shell would expand can hide here.
    let ok = value.starts_with('/')
        && value.len() <= 1024
        && value
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b"/._-".contains(&b));
    if ok {
        Ok(())
    } else {
        Err(invalid(
            field,
            value,
            "expected an absolute path of letters, digits, `/`, `.`, `_` and `-`",
        ))
    }
}

fn check_range(field: &'static str, value: u64, min: u64, max: u64) -> Result<(), ContextError> {
    if (min..=max).contains(&value) {
        Ok(())
    } else {
        Err(invalid(field, value, format!("expected {min} to {max}")))
    }
}

fn check_image(field: &'static str, image: &str) -> Result<String, ContextError> {
    parse_image(image)
        .map(|r| r.to_string())
        .map_err(|reason| ContextError::InvalidImage {
            field,
            image: shown(image),
            reason,
        })
}

fn is_dns_subdomain(s: &str) -> bool {
    !s.is_empty() && s.len() <= 253 && s.split('.').all(is_dns_label)
}

fn check_settings(s: &JobSettings) -> Result<(), ContextError> {
    if !is_dns_label(&s.namespace) {
        return Err(invalid(
            "namespace",
            &s.namespace,
            "expected a DNS-1123 label",
        ));
    }
    if !is_dns_subdomain(&s.service_account) {
        return Err(invalid(
            "service_account",
            &s.service_account,
            "expected a DNS-1123 subdomain",
        ));
    }
    let role_ok = ["arn:aws:iam::", "arn:aws-cn:iam::", "arn:aws-us-gov:iam::"]
        .iter()
        .find_map(|p| s.s3_role_arn.strip_prefix(p))
        .and_then(|rest| rest.split_once(":role/"))
        .is_some_and(|(account, name)| {
            account.len() == 12
                && account.bytes().all(|b| b.is_ascii_digit())
                && !name.is_empty()
                && s.s3_role_arn.len() <= 2048
                && name
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b"+=,.@_/-".contains(&b))
        });
    if !role_ok {
        return Err(invalid(
            "s3_role_arn",
            &s.s3_role_arn,
            "expected an IAM role ARN (arn:aws:iam::<12 digits>:role/<name>)",
        ));
    }
    let region_ok = (1..=32).contains(&s.region.len())
        && s.region
            .bytes()
            .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-');
    if !region_ok {
        return Err(invalid(
            "region",
            &s.region,
            "expected a region such as `us-west-2`",
        ));
    }
    let b = s.bucket.as_bytes();
    let bucket_ok = (3..=63).contains(&b.len())
        && b.iter()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || *c == b'-' || *c == b'.')
        && b[0].is_ascii_alphanumeric()
        && b[b.len() - 1].is_ascii_alphanumeric();
    if !bucket_ok {
        return Err(invalid("bucket", &s.bucket, "expected an S3 bucket name"));
    }
    if s.node_selector.is_empty() {
        return Err(invalid(
            "node_selector",
            "",
            "expected the GPU model label at least",
        ));
    }
    for (key, value) in &s.node_selector {
        if !is_label_key(key) || !is_label_value(value) || value.is_empty() {
            return Err(invalid(
                "node_selector",
                format!("{key}={value}"),
                "expected a label key and a non-empty label value",
            ));
        }
    }
    check_bounds(s)
}

/// The Jobs' numbers within their bounds, and the paths of the official code and routes.
fn check_bounds(s: &JobSettings) -> Result<(), ContextError> {
    const WEEK: u64 = 7 * 24 * 3600;
    let t = &s.timers;
    for (field, value, low, high) in [
        ("backoff_limit", s.backoff_limit.into(), 0, 100),
        (
            "active_deadline_seconds",
            s.active_deadline_seconds,
            60,
            14 * 24 * 3600,
        ),
        (
            "ttl_seconds_after_finished",
            s.ttl_seconds_after_finished.into(),
            0,
            30 * 24 * 3600,
        ),
        // A Spot node gives two minutes' notice: the drain and the grace period fit in it.
        (
            "termination_grace_seconds",
            s.termination_grace_seconds.into(),
            1,
            110,
        ),
        ("repetitions", s.repetitions.into(), 1, 100),
        (
            "timers.start_wait_seconds",
            t.start_wait_seconds.into(),
            0,
            WEEK,
        ),
        (
            "timers.end_wait_seconds",
            t.end_wait_seconds.into(),
            0,
            WEEK,
        ),
        (
            "timers.carla_ready_seconds",
            t.carla_ready_seconds.into(),
            1,
            WEEK,
        ),
        ("timers.poll_seconds", t.poll_seconds.into(), 1, 3600),
        (
            "timers.max_idle_seconds",
            t.max_idle_seconds.into(),
            1,
            WEEK,
        ),
        (
            "timers.logcopy_period_seconds",
            t.logcopy_period_seconds.into(),
            1,
            3600,
        ),
        // The sidecar's own bound on the variable.
        (
            "max_log_objects_per_pair",
            s.max_log_objects_per_pair.into(),
            1,
            1_000_000,
        ),
    ] {
        check_range(field, value, low, high)?;
    }
    for (field, path, optional) in [
        ("routes_file", &s.routes_file, false),
        ("qualifier_routes_file", &s.qualifier_routes_file, false),
        ("scenarios_file", &s.scenarios_file, true),
        ("sources.leaderboard", &s.sources.leaderboard, false),
        ("sources.scenario_runner", &s.sources.scenario_runner, false),
        ("sources.carla_api", &s.sources.carla_api, false),
    ] {
        check_path(field, path, optional)?;
    }
    Ok(())
}

/// One line of text safe on an operator's terminal (`kubectl describe`): no control
/// characters, terminal escapes, or bidirectional and zero-width format characters (which can
/// make a name read as another).
fn printable(text: &str, max_chars: usize) -> String {
    lb_domain::job::logtail::printable(text)
        .chars()
        .filter(|c| !c.is_control())
        .take(max_chars)
        .collect()
}

impl AwsContext {
    /// What the Job's init and logcopy need of AWS.
    fn of(settings: &JobSettings) -> AwsContext {
        AwsContext {
            region: settings.region.clone(),
            bucket: settings.bucket.clone(),
            role_arn: settings.s3_role_arn.clone(),
            token_file: format!("{AWS_TOKEN_DIR}/token"),
        }
    }
}

impl KubernetesContext {
    /// Where and how long the Job runs.
    fn of(settings: &JobSettings) -> KubernetesContext {
        KubernetesContext {
            namespace: settings.namespace.clone(),
            service_account: settings.service_account.clone(),
            node_selector: settings.node_selector.clone(),
            backoff_limit: settings.backoff_limit,
            fail_job_exit_codes: lb_domain::job::protocol::exit::FAIL_JOB.to_vec(),
            active_deadline_seconds: settings.active_deadline_seconds,
            ttl_seconds_after_finished: settings.ttl_seconds_after_finished,
            termination_grace_seconds: settings.termination_grace_seconds,
        }
    }
}

/// Job `job_index` of `plan`, once the submission and the settings are known to fit it.
fn checked_job<'a>(
    leaderboard: Leaderboard,
    plan: &'a Plan,
    job_index: u32,
    submission: &SubmissionInfo,
    settings: &JobSettings,
) -> Result<&'a JobPlan, ContextError> {
    if plan.submission_id != submission.submission_id {
        return Err(invalid(
            "submission_id",
            submission.submission_id,
            format!("the plan is for submission {}", plan.submission_id),
        ));
    }
    let Some(job) = plan.jobs.get(job_index as usize) else {
        return Err(invalid(
            "job_index",
            job_index,
            format!("the plan has {} Job(s)", plan.jobs.len()),
        ));
    };
    let track_ok = !submission.track.is_empty()
        && submission.track.len() <= 63
        && submission
            .track
            .bytes()
            .all(|b| b.is_ascii_uppercase() || b.is_ascii_digit() || b == b'_');
    if !track_ok {
        return Err(invalid(
            "track",
            &submission.track,
            "expected a track codename of uppercase letters, digits and `_`",
        ));
    }
    if leaderboard == Leaderboard::V1 && settings.scenarios_file.is_empty() {
        return Err(invalid(
            "scenarios_file",
            "",
            "Leaderboard 1.0 needs a scenarios file",
        ));
    }
    Ok(job)
}

/// The labels of a Job and its pods: what selects a submission's, a team's and an
/// execution's objects.
fn job_labels(
    leaderboard: Leaderboard,
    job: &JobPlan,
    submission: &SubmissionInfo,
) -> BTreeMap<String, String> {
    [
        (COMPONENT_LABEL, COMPONENT_SUBMISSION.to_owned()),
        (MANAGED_BY_LABEL, MANAGED_BY.to_owned()),
        (SUBMISSION_LABEL, submission.submission_id.to_string()),
        (TEAM_ID_LABEL, submission.team_id.to_string()),
        (TEAM_LABEL, label_value(&submission.team_name)),
        (JOB_INDEX_LABEL, job.index.to_string()),
        (LEADERBOARD_LABEL, leaderboard.as_str().to_owned()),
        (TRACK_LABEL, label_value(&submission.track)),
        (EXECUTION_LABEL, label_value(&submission.execution)),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_owned(), v))
    .collect()
}

impl JobContext {
    /// Builds the context of Job `job_index` of `plan`, validating every input.
    pub fn build(
        leaderboard: Leaderboard,
        plan: &Plan,
        job_index: u32,
        submission: &SubmissionInfo,
        settings: &JobSettings,
    ) -> Result<JobContext, ContextError> {
        check_settings(settings)?;
        let job = checked_job(leaderboard, plan, job_index, submission, settings)?;
        let images = ImagesContext {
            carla: check_image("CARLA image", &settings.carla_image)?,
            private_contents: check_image(
                "private-contents image",
                &settings.private_contents_image,
            )?,
            participant: check_image("participant image", &submission.image)?,
        };
        let team_label = label_value(&submission.team_name);
        let labels = job_labels(leaderboard, job, submission);
        Ok(JobContext {
            leaderboard,
            submission_id: submission.submission_id,
            challenge_id: submission.challenge_id,
            phase_id: submission.phase_id,
            team: TeamContext {
                id: submission.team_id,
                name: printable(&submission.team_name, MAX_TEAM_NAME_ANNOTATION),
                label: team_label,
            },
            track: submission.track.clone(),
            participant_resume: if submission.resuming { "1" } else { "" }.to_owned(),
            images,
            evaluation: EvaluationContext {
                routes_file: if settings.qualifier {
                    settings.qualifier_routes_file.clone()
                } else {
                    settings.routes_file.clone()
                },
                scenarios_file: settings.scenarios_file.clone(),
                repetitions: settings.repetitions,
            },
            aws: AwsContext::of(settings),
            kubernetes: KubernetesContext::of(settings),
            resources: ResourcesContext {
                simulator: ContainerResources::of(settings.resources.simulator, Storage::SIMULATOR),
                agent: ContainerResources::of(settings.resources.agent, Storage::AGENT).with_gpu(),
                sidecar: ContainerResources::of(Allotment::SIDECAR, Storage::SIDECAR),
                logcopy: ContainerResources::of(
                    Allotment::SIDECAR,
                    Storage::logcopy(VolumeSizes::JOB, job.pairs.len() as u32),
                ),
                shm: format!("{}Mi", settings.resources.shm_mib * job.pairs.len() as u32),
                volumes: VolumesContext::of(VolumeSizes::JOB, job.pairs.len() as u32),
            },
            timers: settings.timers.clone(),
            uploads: UploadsContext {
                max_log_objects_per_pair: settings.max_log_objects_per_pair,
            },
            sources: settings.sources.clone(),
            job: JobInfo {
                index: job.index,
                name: job.name.clone(),
                pair_ids: job.pair_ids(),
                pair_count: job.pairs.len() as u32,
            },
            labels,
            pairs: job
                .pairs
                .iter()
                .map(|p| PairContext {
                    id: p.id,
                    worker: p.worker,
                    routes: p.routes.to_string(),
                    carla_port: p.carla_port,
                    tm_port: p.tm_port,
                })
                .collect(),
        })
    }

    /// A complete, valid context (20 routes, 4 workers, one Job) used to check templates at
    /// load time and in examples.
    pub fn sample(leaderboard: Leaderboard) -> JobContext {
        let deployment = LeaderboardSettings {
            cluster: "leaderboard".into(),
            namespace: "default".into(),
            bucket: "leaderboard-submissions".into(),
            submissions_table: "submissions".into(),
            qualifier_table: "qualifier".into(),
            images: lb_domain::settings::Images {
                carla: "carlasim/carla:0.9.15".into(),
                private_contents: "registry.example.com/private-contents:1".into(),
            },
            instance_type: "g5.12xlarge".into(),
            gpu_model: None,
            capacity: Default::default(),
            gpus_per_node: 4,
            tracks: BTreeMap::new(),
            qualifier: Default::default(),
            job_role_arn: String::new(),
            max_cluster_outage_hours: 6,
            max_queue_hours: 24,
            team_limit: 2,
            pair_resources: None,
            partial_update_seconds: 30,
            move_window_seconds: lb_domain::capacity::consolidation::MOVE_WINDOW_SECONDS,
            max_log_objects_per_pair: lb_domain::job::uploads::LOG_OBJECTS_PER_PAIR,
        };
        let settings = JobSettings::from_deployment(
            leaderboard,
            &deployment,
            "us-west-2",
            "arn:aws:iam::123456789012:role/leaderboard-s3",
        )
        .expect("the sample deployment is valid");
        let plan = lb_domain::job::plan::plan(lb_domain::job::plan::PlanInput {
            submission_id: 1,
            team_name: "sample",
            routes: 20,
            workers: 4,
        })
        .expect("the sample plan is valid");
        let submission = SubmissionInfo {
            submission_id: 1,
            challenge_id: 1,
            phase_id: 1,
            team_id: 1,
            team_name: "sample".into(),
            leaderboard,
            track: "SENSORS".into(),
            image: "registry.example.com/team/agent:1".into(),
            routes: 20,
            workers: 4,
            resuming: false,
            execution: "sample".into(),
            arrived_ms: None,
            submitted_at: 0,
        };
        JobContext::build(leaderboard, &plan, 0, &submission, &settings)
            .expect("the sample context is valid")
    }
}
