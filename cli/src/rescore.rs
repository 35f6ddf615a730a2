//! `lbctl rescore`: a submission's workers' results merged again from S3 with the library the
//! functions use, shown (and written with `--out`), and with `--post` sent to EvalAI as the
//! final update.

use std::path::PathBuf;

use clap::Args;
use lb_aws::s3::SubmissionStore;
use lb_domain::job::plan::{plan, PlanInput};
use lb_domain::results::{EvalAiFiles, Leaderboard, RouteSubset};
use lb_domain::run::finalize::rescore_refusal;
use lb_domain::submission::SubmissionStatus;
use lb_evalai::{FinalUpdate, SubmissionRef, WriteOutcome};
use lb_pipeline::results::merge_partials;

use crate::deployment::evalai_id;
use crate::deployment::{Deployment, DeploymentArgs, EvalAiTokenArgs, Record, ScanFilter};
use crate::error::{CliError, Result};

/// `lbctl rescore` options.
#[derive(Debug, Clone, Args)]
#[command(after_help = "Examples:
  lbctl rescore 4242                      # merge the workers' files again, show the EvalAI files
  lbctl rescore 4242 --out /tmp/4242      # and write them there
  lbctl rescore 4242 --post --challenge 1 # send them to EvalAI as the final update (asks first)")]
pub struct Rescore {
    /// EvalAI submission id.
    #[arg(value_parser = evalai_id())]
    pub submission: u64,
    /// The leaderboard, when the submission has records in several.
    #[arg(long, value_name = "LEADERBOARD")]
    pub leaderboard: Option<String>,
    /// Write `agent_results.json`, `results.json`, `stdout.txt` and `metadata.json` here.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Send the files to EvalAI as the final update (FINISHED when every planned route has
    /// its records, else FAILED). Refused for a cancelled submission.
    #[arg(long, requires = "challenge")]
    pub post: bool,
    /// EvalAI challenge id (for --post).
    #[arg(long, value_parser = evalai_id())]
    pub challenge: Option<u64>,
    /// Do not ask before posting.
    #[arg(long)]
    pub yes: bool,
    /// Print the merge as JSON (`complete`, `progress`, `accuracies`) instead of the files.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub token: EvalAiTokenArgs,
    #[command(flatten)]
    pub deployment: DeploymentArgs,
}

/// `lbctl rescore`.
pub async fn rescore(args: Rescore) -> Result<u8> {
    let deployment = Deployment::load(&args.deployment).await?;
    let id = args.submission;
    let record = one_record(&deployment, &args).await?;
    let phase = record
        .track_id
        .ok_or_else(|| CliError::Refused(format!("the record of `{id}` has no `track_id`")))?;
    let target = deployment
        .settings
        .target(phase)
        .map_err(|e| CliError::Usage(format!("the record's phase: {e}")))?;
    let leaderboard = target.leaderboard;
    let workers = record
        .workers
        .and_then(|w| u32::try_from(w).ok())
        .unwrap_or(target.track_settings.workers);
    let team = record.team_name.as_deref().unwrap_or("team").to_owned();
    let the_plan = plan(PlanInput {
        submission_id: id,
        team_name: &team,
        routes: target.track_settings.routes,
        workers,
    })
    .map_err(|e| CliError::Refused(format!("the record's plan: {e}")))?;

    let store = SubmissionStore::new(deployment.s3.clone(), &target.deployment.bucket, id);
    let partials = store
        .partials()
        .await
        .map_err(|e| CliError::aws(format!("listing the results of `{id}`"), e))?;
    let pairs: Vec<(u32, RouteSubset)> = the_plan.pairs().map(|p| (p.id, p.routes)).collect();
    let merge = merge_partials(
        &store,
        &partials,
        leaderboard,
        &pairs,
        leaderboard.repetitions(),
    )
    .await
    .map_err(|e| CliError::Refused(format!("{}: {}", e.name(), e.chain())))?;
    let merged = merge.merged.as_ref();
    let complete = merge.complete;
    let progress = merge.progress;
    let files = EvalAiFiles::generate(merged, leaderboard);

    if let Some(dir) = &args.out {
        write_files(dir, merged.map(|m| m.to_json()), &files)?;
    }
    print_merge(
        &args,
        id,
        leaderboard,
        partials.len(),
        (complete, progress),
        &files,
    );
    if !args.post {
        return Ok(0);
    }
    let invalid = merged.and_then(|m| m.invalid_reason);
    if let Some(why) = rescore_refusal(record.status, complete, progress, invalid) {
        return Err(CliError::Refused(format!(
            "submission `{id}`: {why}; nothing is posted"
        )));
    }
    post(&deployment, &args, phase, &files).await
}

/// What the merge gave: as JSON, or the counts and the files EvalAI would get.
fn print_merge(
    args: &Rescore,
    id: u64,
    leaderboard: Leaderboard,
    files_read: usize,
    (complete, progress): (bool, (u64, u64)),
    files: &EvalAiFiles,
) {
    if args.json {
        let accuracies: serde_json::Map<String, serde_json::Value> = files
            .accuracies()
            .iter()
            .map(|(label, value)| (label.to_string(), serde_json::json!(value.as_f64())))
            .collect();
        let out = serde_json::json!({
            "submission_id": id,
            "leaderboard": leaderboard.as_str(),
            "files": files_read,
            "complete": complete,
            "progress": [progress.0, progress.1],
            "accuracies": accuracies,
        });
        outln!("{}", serde_json::to_string_pretty(&out).unwrap_or_default());
    } else {
        outln!(
            "submission {id}: {files_read} worker file(s), {}/{} records, {}",
            progress.0,
            progress.1,
            if complete { "complete" } else { "not complete" }
        );
        outln!("--- results.json");
        outln!("{}", files.results_json());
        outln!("--- stdout.txt");
        out!("{}", files.stdout);
    }
}

async fn one_record(deployment: &Deployment, args: &Rescore) -> Result<Record> {
    let id = args.submission;
    let found = deployment
        .records(args.leaderboard.as_deref(), ScanFilter::Submission(id))
        .await?;
    let mut records = found.records;
    match records.len() {
        0 => Err(CliError::NotFound(format!(
            "submission `{id}` has no record: nothing says which leaderboard, track and workers it ran with"
        ))),
        1 => Ok(records.remove(0)),
        _ => Err(CliError::Usage(format!(
            "submission `{id}` has records in several leaderboards ({}): choose one with --leaderboard",
            records
                .iter()
                .map(|r| r.leaderboard.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        ))),
    }
}

fn write_files(dir: &std::path::Path, merged: Option<String>, files: &EvalAiFiles) -> Result<()> {
    let io = |path: PathBuf| {
        move |e: std::io::Error| {
            CliError::Refused(format!("cannot write `{}`: {e}", path.display()))
        }
    };
    std::fs::create_dir_all(dir).map_err(io(dir.to_owned()))?;
    let mut outputs = vec![
        ("results.json", Some(files.results_json())),
        ("stdout.txt", Some(files.stdout.clone())),
        ("metadata.json", files.metadata.clone()),
        ("agent_results.json", merged),
    ];
    for (name, text) in outputs.drain(..) {
        let path = dir.join(name);
        match text {
            Some(text) => std::fs::write(&path, text).map_err(io(path.clone()))?,
            None => {
                let _ = std::fs::remove_file(&path);
            }
        }
    }
    Ok(())
}

async fn post(
    deployment: &Deployment,
    args: &Rescore,
    phase: u64,
    files: &EvalAiFiles,
) -> Result<u8> {
    let id = args.submission;
    let status = SubmissionStatus::Finished;
    if !args.yes && !confirm(id, status)? {
        outln!("nothing posted");
        return Ok(1);
    }
    let evalai = deployment
        .evalai(&args.token)
        .await
        .map_err(|source| CliError::EvalAi {
            submission: id,
            source: Box::new(source),
        })?;
    let update = FinalUpdate {
        status,
        result: files.results_json(),
        stdout: files.stdout.clone(),
        stderr: String::new(),
        metadata: files.metadata.clone().unwrap_or_else(|| "{}".into()),
    };
    let at = SubmissionRef {
        challenge: args.challenge.unwrap_or_default(),
        phase,
        submission: id,
    };
    let outcome = evalai
        .post_final(at, &update)
        .await
        .map_err(|e| CliError::EvalAi {
            submission: id,
            source: Box::new(e.into()),
        })?;
    match outcome {
        WriteOutcome::Written => {
            outln!("posted: EvalAI reports `{status}` for submission {id}");
            Ok(0)
        }
        WriteOutcome::Cancelled => Err(CliError::Refused(format!(
            "submission `{id}` is cancelled on EvalAI: nothing was posted"
        ))),
        WriteOutcome::AlreadyFinal(current) => Err(CliError::Refused(format!(
            "EvalAI keeps submission `{id}` as `{current}`: a final status is not replaced by `{status}`"
        ))),
    }
}

/// Asks on the terminal; anything but the submission id typed back is a no.
fn confirm(id: u64, status: SubmissionStatus) -> Result<bool> {
    let question =
        format!("send these files to EvalAI as the final `{status}` update of submission {id}");
    crate::output::confirm_id(&question, id)
        .map_err(|e| CliError::Usage(format!("no confirmation could be read ({e}); pass --yes")))
}
