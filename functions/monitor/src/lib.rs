//! Monitor (stage 4): one round of the Wait -> Monitor -> Choice loop.
//!
//! Per round it reads the Jobs, the workers' results in S3 and the EvalAI status: one GET
//! always, one partial PUT only when the results changed (EvalAI allows 60 requests a minute
//! for every submission in flight together). A participant's cancel becomes the S3 cancel
//! marker; a hopeless run (image that cannot be pulled, unschedulable, out of retries) ends
//! with a reason the participant can act on. Transient trouble with EvalAI or S3 skips this
//! round's update instead of failing a run that may last three days.

use std::time::{Duration, SystemTime, UNIX_EPOCH};

use aws_config::SdkConfig;
use lb_aws::dynamo::SubmissionsTable;
use lb_aws::s3::SubmissionStore;
use lb_cluster::{Verdict, VerdictPolicy};
use lb_domain::results::Leaderboard;
use lb_domain::schedule::{monitor_interval, MAX_EVALUATION};
use lb_domain::submission::SubmissionStatus;
use lb_evalai::{PartialUpdate, SubmissionRef, WriteOutcome};
use lb_pipeline::clients::{self, RunClients};
use lb_pipeline::cluster::{cluster_error, Clusters};
use lb_pipeline::payload::{RunPhase, RunState, SubmissionInfo};
use lb_pipeline::results::{collect_listed, list};
use lb_pipeline::{FnError, FunctionConfig, Result};
use serde::Deserialize;
use tracing::{info, warn};

/// What the Monitor needs: settings, clusters, EvalAI, S3, the submissions table.
#[derive(Debug)]
pub struct Deps {
    /// Settings, EvalAI, clusters, S3, DynamoDB.
    pub clients: RunClients,
    /// How long an unschedulable pod is waited for.
    pub policy: VerdictPolicy,
}

impl Deps {
    /// Cold start: environment, secrets, clients.
    pub async fn from_env() -> Result<Deps> {
        Ok(Self::with(RunClients::from_env().await?))
    }

    /// The same from an explicit SDK configuration and cluster access (local mode, tests).
    pub async fn load(
        sdk: &SdkConfig,
        config: &FunctionConfig,
        clusters: Clusters,
    ) -> Result<Deps> {
        Ok(Self::with(RunClients::load(sdk, config, clusters).await?))
    }

    fn with(clients: RunClients) -> Deps {
        Deps {
            clients,
            policy: VerdictPolicy::default(),
        }
    }
}

/// The Monitor's input.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MonitorInput {
    /// As Intake established it.
    pub submission: SubmissionInfo,
    /// As Launch or the previous round left it.
    pub run: RunState,
}

/// The Lambda entry: JSON in, JSON out.
pub async fn handle_json(input: serde_json::Value, deps: &Deps) -> Result<serde_json::Value> {
    let input: MonitorInput =
        serde_json::from_value(input).map_err(|e| FnError::Input(format!("monitor input: {e}")))?;
    let output = handle(input, deps).await?;
    serde_json::to_value(output).map_err(|e| FnError::Input(e.to_string()))
}

fn now_secs() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

/// The submission's Jobs and pods as the cluster reports them now.
async fn observe(
    deps: &Deps,
    deployment: &lb_domain::settings::LeaderboardSettings,
    id: u64,
) -> Result<lb_cluster::Observation> {
    let cluster = deps
        .clients
        .clusters
        .connect(deployment)
        .await?
        .with_policy(deps.policy);
    cluster
        .observe(&id.to_string())
        .await
        .map_err(cluster_error)
}

/// One monitor round.
pub async fn handle(input: MonitorInput, deps: &Deps) -> Result<RunState> {
    let MonitorInput {
        submission,
        mut run,
    } = input;
    let id = submission.submission_id;
    let target = deps.clients.settings.target(submission.phase_id)?;
    let leaderboard: Leaderboard = target.leaderboard;
    let elapsed = Duration::from_secs(now_secs().saturating_sub(run.launched_at));
    run.monitor.rounds += 1;
    run.monitor.wait_seconds = monitor_interval(elapsed).as_secs();

    // The cluster's API out of reach (a 500, a timeout, DescribeCluster failing) skips the
    // verdict this round, as an unreachable S3 or EvalAI skips their part: the Jobs run on
    // without it. Only an outage longer than the setting ends the run.
    let observation = match observe(deps, target.deployment, id).await {
        Ok(observation) => {
            run.monitor.unreachable_since = None;
            Some(observation.expect_jobs(run.jobs))
        }
        Err(e) if e.is_transient() => {
            let since = *run.monitor.unreachable_since.get_or_insert(now_secs());
            let outage = Duration::from_secs(now_secs().saturating_sub(since));
            let bound = Duration::from_secs(target.deployment.max_cluster_outage_hours * 3600);
            warn!(
                submission_id = id,
                error = %e.chain(),
                outage_seconds = outage.as_secs(),
                "cluster not reached this round"
            );
            if outage >= bound {
                run.monitor.state = RunPhase::Failed;
                run.monitor.reason = Some(format!(
                    "the evaluation cluster could not be reached for {} minutes ({})",
                    outage.as_secs() / 60,
                    e.name()
                ));
                return Ok(run);
            }
            None
        }
        Err(e) => return Err(e),
    };
    let store = SubmissionStore::new(deps.clients.s3.clone(), &target.deployment.bucket, id);
    let at = SubmissionRef {
        challenge: submission.challenge_id,
        phase: submission.phase_id,
        submission: id,
    };

    // Results first: a changed set is merged and sent (the PUT's own GET reads the status);
    // an unchanged one costs one listing and one GET.
    let mut evalai_status = None;
    match list(&store).await {
        Ok(listing)
            if Some(&listing.fingerprint) != run.monitor.fingerprint.as_ref()
                && !listing.fingerprint.is_empty() =>
        {
            let current = listing.fingerprint.clone();
            match collect_listed(&store, listing, leaderboard, &run.pairs, run.repetitions).await {
                Ok(snapshot) => {
                    run.monitor.progress = snapshot.progress;
                    let update = PartialUpdate {
                        result: snapshot.files.results_json(),
                        stdout: snapshot.files.stdout.clone(),
                        metadata: snapshot
                            .files
                            .metadata
                            .clone()
                            .unwrap_or_else(|| "{}".into()),
                    };
                    match deps.clients.evalai.post_partial(at, &update).await {
                        Ok(WriteOutcome::Written) => {
                            run.monitor.fingerprint = Some(snapshot.fingerprint);
                            evalai_status = Some(SubmissionStatus::PartiallyEvaluated);
                        }
                        Ok(WriteOutcome::Cancelled) => {
                            evalai_status = Some(SubmissionStatus::Cancelled)
                        }
                        Ok(WriteOutcome::AlreadyFinal(status)) => evalai_status = Some(status),
                        Err(e) if e.is_transient() => {
                            warn!(submission_id = id, error = %e, "partial update skipped this round")
                        }
                        Err(e) => return Err(e.into()),
                    }
                }
                Err(e) if e.is_transient() => {
                    warn!(submission_id = id, error = %e.chain(), "results not read this round")
                }
                Err(e) => {
                    // The participant's own files are broken; the sidecar marks that pair crashed.
                    warn!(submission_id = id, error = %e.chain(), "results unusable this round");
                    run.monitor.fingerprint = Some(current);
                }
            }
        }
        Ok(_) => {}
        Err(e) if e.is_transient() => {
            warn!(submission_id = id, error = %e.chain(), "results not listed this round")
        }
        Err(e) => return Err(e),
    }
    if evalai_status.is_none() {
        match deps.clients.evalai.submission(id).await {
            Ok(current) => evalai_status = Some(current.status),
            Err(e) if e.is_transient() => {
                warn!(submission_id = id, error = %e, "status not read this round")
            }
            Err(e) => return Err(e.into()),
        }
    }

    if evalai_status == Some(SubmissionStatus::Cancelled) {
        store.put_cancel_marker().await?;
        info!(
            submission_id = id,
            "the participant cancelled: cancel marker written"
        );
        run.monitor.state = RunPhase::Cancelled;
        return Ok(run);
    }
    let Some(observation) = observation else {
        return Ok(run);
    };
    match observation.verdict {
        Verdict::Running if elapsed > MAX_EVALUATION => {
            run.monitor.state = RunPhase::Failed;
            run.monitor.reason = Some(format!(
                "the evaluation ran longer than the {} hours allowed",
                MAX_EVALUATION.as_secs() / 3600
            ));
        }
        Verdict::Running => {
            let table = SubmissionsTable::new(
                deps.clients.dynamo.clone(),
                &target.deployment.submissions_table,
            );
            if let Err(e) = table
                .mark_running(
                    submission.team_id,
                    id,
                    &clients::now_record_time(),
                    &store.location(),
                    run.monitor.progress,
                )
                .await
            {
                warn!(submission_id = id, error = %e, "progress not recorded this round");
            }
        }
        Verdict::Finished => run.monitor.state = RunPhase::Finished,
        Verdict::Failed { kind, message, .. } => {
            info!(submission_id = id, kind = kind.name(), %message, "run failed");
            run.monitor.state = RunPhase::Failed;
            run.monitor.reason = Some(message);
        }
    }
    Ok(run)
}
