//! `lbctl cancel`: the operator's cancel, as the S3 cancel marker of the submission.

use clap::Args;
use lb_aws::s3::{SubmissionStore, CANCEL_MARKER};

use crate::deployment::{clean, evalai_id, Deployment, DeploymentArgs, Record, ScanFilter};
use crate::error::{CliError, Result};

use super::*;

/// `lbctl cancel` options.
#[derive(Debug, Clone, Args)]
pub struct Cancel {
    /// EvalAI submission id.
    #[arg(value_parser = evalai_id())]
    pub submission: u64,
    /// Write the marker even when the record is missing or already final.
    #[arg(long)]
    pub force: bool,
    /// Only this leaderboard (needed with --force when the submission has no record).
    #[arg(long, value_name = "LEADERBOARD")]
    pub leaderboard: Option<String>,
    #[command(flatten)]
    pub deployment: DeploymentArgs,
}

/// `lbctl cancel`: the S3 cancel marker of a submission's leaderboard.
pub async fn cancel(args: Cancel) -> Result<u8> {
    let deployment = Deployment::load(&args.deployment).await?;
    let id = args.submission;
    let only = args.leaderboard.as_deref();
    let found = deployment.records(only, ScanFilter::Submission(id)).await?;
    warn_truncated(&found);

    // The leaderboards whose bucket gets the marker, with the record status that justifies it.
    let mut targets: Vec<(String, String)> = Vec::new();
    if found.records.is_empty() {
        if !args.force {
            return Err(CliError::NotFound(format!(
                "submission `{id}` has no record in {}: it was never claimed, so nothing of it runs \
                 (with --force --leaderboard L the marker is written anyway)",
                tables(&deployment, only)
            )));
        }
        let Some(name) = only else {
            return Err(CliError::Usage(format!(
                "submission `{id}` has no record: name the bucket's leaderboard with --leaderboard"
            )));
        };
        targets.push((name.to_string(), "no record".into()));
    } else {
        let running: Vec<&Record> = found.records.iter().filter(|r| !r.is_final()).collect();
        if running.is_empty() && !args.force {
            let statuses: Vec<String> = found
                .records
                .iter()
                .map(|r| format!("{} in `{}`", clean(r.status_word.as_str()), r.table))
                .collect();
            return Err(CliError::Refused(format!(
                "submission `{id}` is already final ({}): nothing runs to cancel (--force writes the marker anyway)",
                statuses.join(", ")
            )));
        }
        let chosen = if args.force {
            found.records.iter().collect()
        } else {
            running
        };
        for record in chosen {
            if !targets.iter().any(|(lb, _)| *lb == record.leaderboard) {
                targets.push((
                    record.leaderboard.clone(),
                    format!("record {}", clean(record.status_word.as_str())),
                ));
            }
        }
    }

    for (leaderboard, status) in &targets {
        let bucket = &deployment.leaderboard(leaderboard)?.bucket;
        let store = SubmissionStore::new(deployment.s3.clone(), bucket, id);
        store.put_cancel_marker().await.map_err(|e| {
            CliError::aws(
                format!("writing the cancel marker of submission `{id}` in `{bucket}`"),
                e,
            )
        })?;
        outln!(
            "cancel marker written: {}{CANCEL_MARKER} (leaderboard {leaderboard}, {status})",
            marker_location(bucket, id)
        );
    }
    outln!(
        "The Jobs' logcopy mirrors it into the pods within its period; the simulators and agents \
         stop, the Jobs end, and Finalize reports CANCELLED to EvalAI and in the record \
         (`lbctl status {id}` shows it)."
    );
    Ok(0)
}
