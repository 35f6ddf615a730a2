//! `lbctl logs`: a submission's logs as logcopy left them in S3: each worker's agent and
//! simulator output and the logcopy logs, recorder files only when asked, `--follow` for what
//! is added until the submission ends.

use std::collections::BTreeMap;
use std::io::Write;
use std::time::Duration;

use clap::Args;
use lb_aws::s3::SubmissionStore;
use lb_domain::job::logtail::printable;

use crate::deployment::evalai_id;
use crate::deployment::{Deployment, DeploymentArgs, ScanFilter};
use crate::error::{CliError, Result};

/// Longest `--follow` (a 72-hour evaluation and its queue, with room).
const MAX_FOLLOW: Duration = Duration::from_secs(96 * 3600);

/// `lbctl logs` options.
#[derive(Debug, Clone, Args)]
#[command(after_help = "Examples:
  lbctl logs 4242                      # every worker's agent and simulator logs, and logcopy's
  lbctl logs 4242 --worker 2           # worker 2 only (and logcopy)
  lbctl logs 4242 --follow             # then what is added, until the submission ends
  lbctl logs 4242 --recorder           # with the CARLA recorder files listed")]
pub struct Logs {
    /// EvalAI submission id.
    #[arg(value_parser = evalai_id())]
    pub submission: u64,
    /// Only this worker (pair id): its agent and simulator logs, and the logcopy logs.
    #[arg(long, value_name = "N")]
    pub worker: Option<u32>,
    /// Keep printing what is added until the submission's record is final.
    #[arg(long)]
    pub follow: bool,
    /// Seconds between two looks with --follow.
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u64).range(1..=3600))]
    pub interval: u64,
    /// Include the recorder files (large binary CARLA recordings): listed, not printed.
    #[arg(long)]
    pub recorder: bool,
    /// Only this leaderboard's bucket.
    #[arg(long, value_name = "LEADERBOARD")]
    pub leaderboard: Option<String>,
    #[command(flatten)]
    pub deployment: DeploymentArgs,
}

/// Whether a log (relative to the submission's folder) is one to show.
fn wanted(key: &str, worker: Option<u32>, recorder: bool) -> bool {
    if let Some(rel) = key.strip_prefix("recorder/") {
        let pair = rel
            .split_once('/')
            .and_then(|(dir, _)| dir.strip_prefix("pair"));
        return recorder && worker.is_none_or(|n| pair == Some(n.to_string().as_str()));
    }
    let Some(rel) = key.strip_prefix("logs/") else {
        return false;
    };
    match worker {
        None => true,
        Some(n) => {
            rel.starts_with(&format!("agent/agent{n}/"))
                || rel == format!("simulator/simulator{n}.log")
                || rel.starts_with("logcopy")
        }
    }
}

/// The workers (pair ids) with an agent or simulator log among `keys`.
fn workers_with_logs<'a>(
    keys: impl IntoIterator<Item = &'a str>,
) -> std::collections::BTreeSet<u32> {
    keys.into_iter()
        .filter_map(|key| {
            let rel = key.strip_prefix("logs/")?;
            let n = rel
                .strip_prefix("agent/agent")
                .and_then(|r| r.split_once('/').map(|(n, _)| n))
                .or_else(|| {
                    rel.strip_prefix("simulator/simulator")?
                        .strip_suffix(".log")
                })?;
            n.parse().ok()
        })
        .collect()
}

/// A CARLA recording (`recorder/pair<ID>/...`): binary, large.
fn is_recording(key: &str) -> bool {
    key.starts_with("recorder/")
}

/// `lbctl logs`.
pub async fn logs(args: Logs) -> Result<u8> {
    let deployment = Deployment::load(&args.deployment).await?;
    let id = args.submission;
    let found = deployment
        .records(args.leaderboard.as_deref(), ScanFilter::Submission(id))
        .await?;
    // The record says which bucket; without one, every bucket is looked at.
    let buckets: Vec<String> = match found.records.first() {
        Some(record) => deployment
            .leaderboards(Some(&record.leaderboard))?
            .into_iter()
            .map(|(_, lb)| lb.bucket.clone())
            .collect(),
        None => deployment
            .leaderboards(args.leaderboard.as_deref())?
            .into_iter()
            .map(|(_, lb)| lb.bucket.clone())
            .collect(),
    };
    let mut store = None;
    for bucket in &buckets {
        let candidate = SubmissionStore::new(deployment.s3.clone(), bucket, id);
        let listed = candidate
            .logs()
            .await
            .map_err(|e| CliError::aws(format!("listing the logs of `{id}` in `{bucket}`"), e))?;
        if !listed.is_empty() {
            // A worker with no log says so, unless following (its logs may come).
            let workers = workers_with_logs(listed.iter().map(|(key, _)| key.as_str()));
            if let Some(n) = args.worker.filter(|n| !args.follow && !workers.contains(n)) {
                let have: Vec<String> = workers.iter().map(u32::to_string).collect();
                return Err(CliError::NotFound(format!(
                    "submission `{id}` has no logs of worker {n} in `s3://{bucket}/{id}/logs/` \
                     (workers with logs: {})",
                    if have.is_empty() {
                        "none".into()
                    } else {
                        have.join(", ")
                    }
                )));
            }
            store = Some(candidate);
            break;
        }
    }
    let Some(store) = store else {
        if args.follow && !found.records.is_empty() {
            errln!("lbctl: no logs yet for submission `{id}`; waiting for them");
        } else {
            return Err(CliError::NotFound(format!(
                "submission `{id}` has no logs in {}",
                buckets
                    .iter()
                    .map(|b| format!("`s3://{b}/{id}/logs/`"))
                    .collect::<Vec<_>>()
                    .join(", ")
            )));
        }
        return follow_from(&deployment, &args, buckets, BTreeMap::new()).await;
    };
    let printed = print_new(&store, &args, &BTreeMap::new()).await?;
    if !args.follow {
        return Ok(0);
    }
    follow_from(&deployment, &args, buckets, printed).await
}

/// Prints what each wanted log has past what was printed; returns the new offsets.
async fn print_new(
    store: &SubmissionStore,
    args: &Logs,
    printed: &BTreeMap<String, u64>,
) -> Result<BTreeMap<String, u64>> {
    let mut offsets = printed.clone();
    let listing = |e| CliError::aws(format!("listing the logs of `{}`", args.submission), e);
    let mut listed = store.logs().await.map_err(listing)?;
    if args.recorder {
        listed.extend(store.recordings().await.map_err(listing)?);
    }
    let mut out = std::io::stdout().lock();
    for (key, size) in listed {
        if !wanted(&key, args.worker, args.recorder) {
            continue;
        }
        let from = offsets.get(&key).copied().unwrap_or(0);
        if size <= from && offsets.contains_key(&key) {
            continue;
        }
        // The participant names its files: shown escaped like everything it writes.
        let shown = crate::deployment::clean(&key);
        if is_recording(&key) {
            if !offsets.contains_key(&key) {
                let _ = writeln!(
                    out,
                    "==> {shown} <== ({size} bytes, a recording: not printed)"
                );
            }
            offsets.insert(key, size);
            continue;
        }
        let bytes = store
            .get_from(&key, from)
            .await
            .map_err(|e| CliError::aws(format!("reading `{shown}`"), e))?
            .unwrap_or_default();
        if from == 0 {
            let _ = writeln!(out, "==> {shown} <==");
        } else if !bytes.is_empty() {
            let _ = writeln!(out, "==> {shown} (continued) <==");
        }
        // Written by the participant's code too: no escape reaches the operator's terminal.
        let text = printable(&String::from_utf8_lossy(&bytes));
        let _ = out.write_all(text.as_bytes());
        if !text.is_empty() && !text.ends_with('\n') {
            let _ = writeln!(out);
        }
        offsets.insert(key, from + bytes.len() as u64);
    }
    let _ = out.flush();
    Ok(offsets)
}

async fn follow_from(
    deployment: &Deployment,
    args: &Logs,
    buckets: Vec<String>,
    mut printed: BTreeMap<String, u64>,
) -> Result<u8> {
    let started = std::time::Instant::now();
    let id = args.submission;
    while started.elapsed() < MAX_FOLLOW {
        let record = deployment
            .records(args.leaderboard.as_deref(), ScanFilter::Submission(id))
            .await?
            .records
            .into_iter()
            .next();
        let done = record.as_ref().is_some_and(|r| r.is_final());
        for bucket in &buckets {
            let store = SubmissionStore::new(deployment.s3.clone(), bucket, id);
            printed = print_new(&store, args, &printed).await?;
        }
        if done {
            let status = record
                .map(|r| r.status_word.as_str().to_owned())
                .unwrap_or_default();
            errln!("lbctl: submission {id} ended `{status}`");
            return Ok(0);
        }
        tokio::time::sleep(Duration::from_secs(args.interval)).await;
    }
    errln!(
        "lbctl: stopped following after {} hours",
        MAX_FOLLOW.as_secs() / 3600
    );
    Ok(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_workers_with_logs_are_read_off_the_agent_and_simulator_keys() {
        let keys = [
            "logs/agent/agent1/agent.log",
            "logs/agent/agent12/recorder/RouteScenario_0.log",
            "logs/simulator/simulator3.log",
            "logs/simulator/simulatorX.log",
            "logs/logcopy/logcopy-0.log",
            "agent/partial_agent_results2.json",
        ];
        assert_eq!(
            workers_with_logs(keys).into_iter().collect::<Vec<_>>(),
            [1, 3, 12]
        );
    }

    #[test]
    fn a_worker_sees_its_own_logs_and_logcopys_and_recordings_only_when_asked() {
        let keys = [
            "logs/agent/agent1/agent.log",
            "logs/agent/agent12/agent.log",
            "recorder/pair1/RouteScenario_0_rep0.log",
            "recorder/pair2/RouteScenario_1_rep0.log",
            "logs/simulator/simulator1.log",
            "logs/simulator/simulator2.log",
            "logs/logcopy/logcopy-0.log",
            "agent/partial_agent_results1.json",
        ];
        let shown = |worker, recorder| -> Vec<&str> {
            keys.iter()
                .copied()
                .filter(|k| wanted(k, worker, recorder))
                .collect()
        };
        assert_eq!(
            shown(Some(1), false),
            [
                "logs/agent/agent1/agent.log",
                "logs/simulator/simulator1.log",
                "logs/logcopy/logcopy-0.log"
            ]
        );
        assert_eq!(shown(None, false).len(), 5);
        assert_eq!(shown(None, true).len(), 7);
        assert_eq!(
            shown(Some(2), true),
            [
                "recorder/pair2/RouteScenario_1_rep0.log",
                "logs/simulator/simulator2.log",
                "logs/logcopy/logcopy-0.log"
            ]
        );
    }
}
