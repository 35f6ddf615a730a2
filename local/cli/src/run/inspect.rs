//! What a local run left, read back: the record, the markers, the merged results, the pods' logs
//! and GPUs, the registry's digest, the stages' times.

use std::collections::BTreeMap;

use anyhow::Context;
use lb_domain::results::Leaderboard;
use local_stack::Stack;

use crate::report::Merged;
use local_stepfunctions::HistoryEvent;
use serde_json::{json, Value};

/// The GPU each attempt of each pair's simulator rendered on, by pair, as its log in S3 notes
/// them (`simulator <ID> attempt <N>: rendering on GPU <index>`).
pub(super) async fn simulator_gpus(
    sdk: &aws_config::SdkConfig,
    bucket: &str,
    submission: u64,
    pairs: u32,
) -> BTreeMap<u32, Vec<u32>> {
    let logs = pair_logs(
        sdk,
        bucket,
        submission,
        pairs,
        lb_domain::job::protocol::simulator_log,
    )
    .await;
    (1..)
        .zip(logs)
        .map(|(pair, text)| {
            let indices: Vec<u32> = text
                .lines()
                .filter_map(|line| {
                    line.split_once(": rendering on GPU ")?
                        .1
                        .trim()
                        .parse()
                        .ok()
                })
                .collect();
            (pair, indices)
        })
        .collect()
}

/// The GPU index of each attempt's own GPU, by pair, as its agent's log notes it (`agent <ID>
/// attempt <N>: the pair's GPU is <UUID>`), the UUIDs being the local node's.
pub(super) fn agent_gpus(logs: &[String]) -> BTreeMap<u32, Vec<u32>> {
    let mut gpus = BTreeMap::new();
    for (pair, log) in (1..).zip(logs) {
        let indices: Vec<u32> = log
            .lines()
            .filter_map(|line| {
                let uuid = line.split_once(": the pair's GPU is ")?.1.trim();
                (0..local_kube::UNMODELLED_GPUS).find(|&i| local_kube::gpu_uuid(i) == uuid)
            })
            .collect();
        gpus.insert(pair, indices);
    }
    gpus
}

/// Each pair's agent log in S3 (`logs/agent/agent<ID>/agent.log`), which every new pod of the
/// pair continues.
pub(super) async fn agent_logs(
    sdk: &aws_config::SdkConfig,
    bucket: &str,
    submission: u64,
    pairs: u32,
) -> Vec<String> {
    let agent_log = |pair| {
        format!(
            "{}/agent.log",
            lb_domain::job::protocol::agent_logs_dir(pair)
        )
    };
    pair_logs(sdk, bucket, submission, pairs, agent_log).await
}

/// One log of each pair from S3 (`logs/<rel(pair)>`), in pair order; empty when missing.
pub(super) async fn pair_logs(
    sdk: &aws_config::SdkConfig,
    bucket: &str,
    submission: u64,
    pairs: u32,
    rel: impl Fn(u32) -> String,
) -> Vec<String> {
    let mut logs = Vec::new();
    for pair in 1..=pairs {
        let key = format!(
            "{submission}/{}/{}",
            lb_domain::job::protocol::LOGS_DIR,
            rel(pair)
        );
        let object = lb_aws::s3_client(sdk)
            .get_object()
            .bucket(bucket)
            .key(key)
            .send()
            .await;
        let text = match object {
            Ok(object) => match object.body.collect().await {
                Ok(bytes) => String::from_utf8_lossy(&bytes.into_bytes()).into_owned(),
                Err(_) => String::new(),
            },
            Err(_) => String::new(),
        };
        logs.push(text);
    }
    logs
}

/// `agent_results.json` summed up: its records and how many each route has (Leaderboard 1.0
/// runs every route 5 times under one id).
pub(super) async fn merged_summary(
    sdk: &aws_config::SdkConfig,
    bucket: &str,
    submission: u64,
) -> Option<Merged> {
    let object = lb_aws::s3_client(sdk)
        .get_object()
        .bucket(bucket)
        .key(format!(
            "{submission}/{}",
            lb_domain::job::protocol::derived::MERGED
        ))
        .send()
        .await
        .ok()?;
    let bytes = object.body.collect().await.ok()?.into_bytes();
    let merged: Value = serde_json::from_slice(&bytes).ok()?;
    let records = merged["_checkpoint"]["records"].as_array()?;
    let mut per_route: BTreeMap<&str, usize> = BTreeMap::new();
    for record in records {
        *per_route
            .entry(record["route_id"].as_str().unwrap_or_default())
            .or_default() += 1;
    }
    Some(Merged {
        records: records.len(),
        routes: per_route.len(),
        per_route: per_route.values().copied().collect(),
    })
}

/// The digest the participant's tag names in the registry now.
pub(super) async fn registry_digest(sdk: &aws_config::SdkConfig, image: &str) -> Option<String> {
    let reference = lb_jobs::parse_image(image).ok()?;
    let ecr = reference.ecr_tagged()?;
    let registry = lb_aws::ecr::Registry::new(sdk);
    match registry
        .digest_of((ecr.registry, ecr.region), ecr.repository, ecr.tag)
        .await
    {
        Ok(lb_aws::ecr::Lookup::Digest(digest)) => Some(digest),
        _ => None,
    }
}

/// What an ended run left: its Jobs, its team's places, its record's status.
pub(super) async fn left_behind(
    sdk: &aws_config::SdkConfig,
    settings: &lb_domain::settings::Settings,
    leaderboard: Leaderboard,
    kubeconfig: &std::path::Path,
    (team, submission): (u64, u64),
) -> crate::report::LeftBehind {
    let mut left = crate::report::LeftBehind::default();
    if let Ok(cluster) = lb_cluster::Cluster::from_kubeconfig(kubeconfig, None).await {
        let namespace = settings
            .leaderboards
            .get(&leaderboard)
            .map(|l| &l.namespace);
        let cluster = match namespace {
            Some(ns) => cluster.with_namespace(ns),
            None => cluster,
        };
        left.jobs = cluster
            .list(&submission.to_string())
            .await
            .ok()
            .map(|(jobs, _)| jobs.len());
    }
    let store = lb_aws::s3::SubmissionStore::new(
        lb_aws::s3_client(sdk),
        settings_bucket(settings, leaderboard),
        submission,
    );
    left.status_objects = store.markers().await.ok().map(|m| m.len());
    let dynamo = aws_sdk_dynamodb::Client::new(sdk);
    let queue =
        lb_aws::admission::AdmissionTable::new(dynamo.clone(), local_stack::stack::ADMISSION_TABLE);
    if let Ok(holds) = queue.holds(leaderboard.as_str()).await {
        left.places_held = Some(holds.iter().map(|(_, h)| h.len()).sum());
    }
    if let Some(table) = settings
        .leaderboards
        .get(&leaderboard)
        .map(|l| &l.submissions_table)
    {
        let records = lb_aws::dynamo::SubmissionsTable::new(dynamo, table);
        if let Ok(Some(record)) = records.record(team, submission).await {
            left.record_status = Some(record.status_word.clone()).filter(|s| !s.is_empty());
            left.failed_by_platform = record.failed_by_platform;
            left.recordings = record.recordings;
            left.recordings_failed = record.recordings_failed.clone();
            left.usage = record.usage.map(|usage| {
                serde_json::json!({
                    "gpu_seconds": usage.gpu_seconds,
                    "spot": usage.spot,
                    "run_again": usage.run_again,
                    "lost_to_reclaims": usage.lost,
                    "cost_usd": usage.dollars,
                    "orchestration_usd": usage.orchestration,
                    "state_transitions": record.state_transitions,
                    "log_bytes_stored": record.log_bytes_stored,
                    "uploads_refused": record.uploads_refused,
                    "image_digest": record.image_digest,
                })
            });
        }
    }
    left
}

pub(super) fn settings_bucket(
    settings: &lb_domain::settings::Settings,
    leaderboard: Leaderboard,
) -> String {
    settings
        .leaderboards
        .get(&leaderboard)
        .map(|l| l.bucket.clone())
        .unwrap_or_default()
}

/// Seconds spent in each state, summed over its visits.
pub(super) fn stage_times(history: &[HistoryEvent]) -> Vec<(String, f64)> {
    let mut out: Vec<(String, f64)> = Vec::new();
    let mut entered: Option<(String, f64)> = None;
    for event in history {
        if event.event_type.is_state_entered() {
            entered = event.state_name().map(|n| (n.to_string(), seconds(event)));
        } else if event.event_type.is_state_exited() {
            if let Some((name, at)) = entered.take() {
                let seconds = seconds(event) - at;
                match out.iter_mut().find(|(n, _)| *n == name) {
                    Some((_, total)) => *total += seconds,
                    None => out.push((name, seconds)),
                }
            }
        }
    }
    out
}

pub(super) fn seconds(event: &HistoryEvent) -> f64 {
    event.timestamp.unix_timestamp_nanos() as f64 / 1e9
}

/// Puts EvalAI's message on a moto SQS queue and takes it off as the EventBridge Pipe does:
/// the deployed input template applied to the record, handed over as a one-element batch.
pub(super) async fn sqs_round_trip(
    stack: &Stack,
    challenge: u64,
    phase: u64,
    submission: u64,
    image: &str,
) -> anyhow::Result<Value> {
    let sqs = aws_sdk_sqs::Client::new(&stack.sdk);
    // The queue `infra/app.yaml` declares, which the stack provisioned.
    let queue = sqs
        .get_queue_url()
        .queue_name(local_stack::stack::submissions_queue())
        .send()
        .await?;
    let url = queue.queue_url().context("no queue url")?.to_string();
    // As EvalAI publishes a new submission: string challenge and phase ids, int submission id.
    let body = json!({
        "challenge_pk": challenge.to_string(),
        "phase_pk": phase.to_string(),
        "submission_pk": submission,
        "is_static_dataset_code_upload_submission": false,
        "submitted_image_uri": image,
    });
    sqs.send_message()
        .queue_url(&url)
        .message_body(body.to_string())
        .send()
        .await?;
    local_stack::pipe::poll(&sqs, &url, 1, 5)
        .await?
        .context("the message did not arrive")
}
