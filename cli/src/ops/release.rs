//! `lbctl release`: a place in a team's share of a queue given back by hand.

use clap::Args;
use lb_domain::status::ExecutionStatus;

use crate::deployment::{clean, evalai_id, Deployment, DeploymentArgs, ScanFilter};
use crate::error::{CliError, Result};

use super::*;

/// `lbctl release` options.
#[derive(Debug, Clone, Args)]
pub struct Release {
    /// EvalAI submission id.
    #[arg(value_parser = evalai_id())]
    pub submission: u64,
    /// Only this leaderboard's queue.
    #[arg(long, value_name = "LEADERBOARD")]
    pub leaderboard: Option<String>,
    /// Release it even while its record says its run is in flight (its team may then hold
    /// more evaluations than its cap).
    #[arg(long)]
    pub force: bool,
    /// Do not ask for confirmation.
    #[arg(long)]
    pub yes: bool,
    #[command(flatten)]
    pub deployment: DeploymentArgs,
    /// Where the execution holding the place is looked up, for advice that fits it.
    #[command(flatten)]
    pub machine: crate::executions::StateMachineArgs,
}

/// Where the execution that holds a place stands, as far as `lbctl` could tell.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Holder {
    /// Step Functions says it runs.
    Running(String),
    /// Step Functions says it ended (`FAILED`, `ABORTED`, ...).
    Ended(String, String),
    /// Not looked up (no state machine given) or not found, with why.
    Unknown(String),
}

/// What to do about a place whose record is in flight, for the execution's real state.
pub fn release_advice(id: u64, holder: &Holder) -> String {
    match holder {
        Holder::Running(name) => format!(
            "its execution `{name}` runs and holds this place: `lbctl cancel {id}` ends it, and \
             the place comes back with its end (--force releases the place anyway, and its team \
             may then exceed its cap)"
        ),
        Holder::Ended(name, status) => format!(
            "its execution `{name}` ended {status} before its Finalize gave the place back (EvalAI \
             or the cluster may have been out of reach): the reaper's pass, every 5 minutes, \
             finalizes it, releases the place and tells EvalAI once it answers; `lbctl release \
             {id} --force` releases the place now"
        ),
        Holder::Unknown(why) => format!(
            "{why}. If its execution still runs, `lbctl cancel {id}` ends it and the place comes \
             back with its end; if it ended, the reaper's pass (every 5 minutes) releases the \
             place, or --force releases it now. --state-machine ARN lets lbctl tell which"
        ),
    }
}

/// Where the run that execution `name` of `state_machine` began stands now: the execution it
/// continued as, when it did (`lb_aws::executions::current`).
async fn holder(sdk: &aws_config::SdkConfig, state_machine: Option<&str>, name: &str) -> Holder {
    let Some(machine) = state_machine else {
        return Holder::Unknown(format!(
            "its execution `{name}` was not looked up (no --state-machine)"
        ));
    };
    let Some(arn) = lb_aws::executions::execution_arn(machine, name) else {
        return Holder::Unknown(format!("no execution ARN from `{machine}`"));
    };
    let executions = lb_aws::tasks::StepFunctions::new(aws_sdk_sfn::Client::new(sdk));
    match lb_aws::executions::current(&executions, &arn).await {
        Ok(Some((now, described))) => {
            let now = now.rsplit(':').next().unwrap_or(name).to_owned();
            match described.status {
                ExecutionStatus::Running => Holder::Running(now),
                status => Holder::Ended(now, status.as_str().to_owned()),
            }
        }
        Ok(None) => Holder::Unknown(format!("Step Functions has no execution `{name}`")),
        Err(e) => Holder::Unknown(format!("its execution `{name}` could not be read ({e})")),
    }
}

/// `lbctl release`: gives back a place in its team's share of a leaderboard's queue by hand
/// (the reaper's pass does it within minutes for an execution that ended; this is for when an
/// operator cannot wait). Refused while the submission's record is in flight, unless --force;
/// asks for the id to be typed back, unless --yes.
pub async fn release(args: Release) -> Result<u8> {
    let deployment = Deployment::load(&args.deployment).await?;
    let Some(table) = &deployment.admission else {
        return Err(CliError::Usage(
            "releasing a place needs the admission table: --admission-table (the stack output `AdmissionTable`)".into(),
        ));
    };
    let id = args.submission;
    let only = args.leaderboard.as_deref();
    let mut held = Vec::new();
    for (name, _) in deployment.leaderboards(only)? {
        let holds = table
            .holds(name)
            .await
            .map_err(|e| CliError::aws(format!("reading the places of leaderboard {name}"), e))?;
        for (team, holders) in holds {
            if holders.iter().any(|h| *h == id.to_string()) {
                held.push((name.to_string(), team));
            }
        }
    }
    if held.is_empty() {
        return Err(CliError::NotFound(format!(
            "submission `{id}` holds no place in {}",
            tables(&deployment, only)
        )));
    }
    let found = deployment.records(only, ScanFilter::Submission(id)).await?;
    let in_flight: Vec<String> = found
        .records
        .iter()
        .filter(|r| !r.is_final())
        .map(|r| format!("{} in `{}`", clean(r.status_word.as_str()), r.table))
        .collect();
    if !in_flight.is_empty() && !args.force {
        let claimed = found.records.iter().find_map(|r| r.claimed_by.as_deref());
        let holder = match claimed.filter(|n| !n.is_empty() && *n != "-") {
            Some(name) => holder(&deployment.sdk, args.machine.arn().ok(), name).await,
            None => Holder::Unknown("its record names no execution".into()),
        };
        return Err(CliError::Refused(format!(
            "submission `{id}` is in flight ({}): {}",
            in_flight.join(", "),
            release_advice(id, &holder)
        )));
    }
    for (leaderboard, team) in &held {
        let execution = table.execution_of(leaderboard, id).await.ok().flatten();
        outln!(
            "submission {id} holds a place of team {team} in leaderboard {leaderboard} (queued by execution {})",
            execution.as_deref().map_or_else(|| "-".into(), clean)
        );
    }
    let question = format!("give back the place of submission {id}");
    if !args.yes
        && !crate::output::confirm_id(&question, id).map_err(|e| {
            CliError::Usage(format!("no confirmation could be read ({e}); pass --yes"))
        })?
    {
        errln!("not released");
        return Ok(1);
    }
    for (leaderboard, team) in held {
        table.release(&leaderboard, id, team).await.map_err(|e| {
            CliError::aws(
                format!("releasing the place in leaderboard {leaderboard}"),
                e,
            )
        })?;
        outln!(
            "released: team {team}'s next waiting submission in leaderboard {leaderboard} takes the place at its next round"
        );
    }
    Ok(0)
}
