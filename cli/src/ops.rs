//! `lbctl status`, `lbctl list` and `lbctl cancel`: the submissions of a real deployment as
//! its DynamoDB records and S3 markers show them, and the operator's cancel.

use std::collections::{BTreeMap, HashMap};

use clap::Args;
use lb_aws::dynamo::RecordStatus;
use lb_aws::s3::{SubmissionStore, CANCEL_MARKER, STATUS_DIR};
use lb_domain::protocol::{Marker, Role};
use lb_domain::status::ExecutionStatus;
use serde_json::{json, Value};

use crate::deployment::{clean, Deployment, DeploymentArgs, Found, Record, ScanFilter, Usage};
use crate::error::{CliError, Result};

/// Parses an EvalAI id: EvalAI's primary keys are positive Postgres integers.
pub(crate) fn evalai_id() -> impl clap::builder::TypedValueParser<Value = u64> {
    clap::value_parser!(u64).range(1..=lb_domain::submission::MAX_ID)
}

/// `lbctl status` options.
#[derive(Debug, Clone, Args)]
#[command(after_help = "Examples:
  lbctl status 4242          # its record(s) and S3 markers, as text
  lbctl status 4242 --json   # the same for a script")]
pub struct Status {
    /// EvalAI submission id.
    #[arg(value_parser = evalai_id())]
    pub submission: u64,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub deployment: DeploymentArgs,
}

/// `lbctl list` options.
#[derive(Debug, Clone, Args)]
#[command(after_help = "Examples:
  lbctl list --running                  # what runs or waits, with queue positions and ages
  lbctl list --team 'Team One'          # one team's submissions (its name or EvalAI id)
  lbctl list --status failed --json     # for a script")]
pub struct List {
    /// Only submissions an execution still holds (`SUBMITTED`, `RESUMING`, `RUNNING`).
    #[arg(long)]
    pub running: bool,
    /// Only this leaderboard's table (a key of the settings' `leaderboards`, e.g. `2.0`).
    #[arg(long, value_name = "LEADERBOARD")]
    pub leaderboard: Option<String>,
    /// Only this team: its EvalAI id or its name (case-insensitive).
    #[arg(long, value_name = "TEAM")]
    pub team: Option<String>,
    /// Only this status (`SUBMITTED`, `RESUMING`, `RUNNING`, `FINISHED`, `FAILED`, `CANCELLED`;
    /// case-insensitive). Another word is a usage error, not an empty list.
    #[arg(long, value_name = "STATUS", value_parser = record_status)]
    pub status: Option<RecordStatus>,
    /// Most submissions shown (the newest).
    #[arg(long, default_value_t = 50, value_parser = clap::value_parser!(u64).range(1..=100_000))]
    pub limit: u64,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub deployment: DeploymentArgs,
}

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

/// The markers of one submission in one leaderboard's bucket.
#[derive(Debug, Clone)]
struct Markers {
    leaderboard: String,
    location: String,
    names: Vec<String>,
    /// Why the bucket could not be listed (one unreadable bucket does not hide the rest).
    error: Option<String>,
}

/// Names `--json` lists at most; the summary counts them all.
const MAX_LISTED: usize = 100;

impl Markers {
    fn cancel_requested(&self) -> bool {
        self.names.iter().any(|n| n == CANCEL_MARKER)
    }

    /// The markers counted, a line per pair, whatever their number: what each container did
    /// (started, crashed, done), which Jobs' logcopy finished, and how many objects are no
    /// marker of the protocol (left by an older system, or by hand).
    fn summary(&self) -> Vec<String> {
        let mut pairs: BTreeMap<u32, [u32; 5]> = BTreeMap::new();
        let (mut logcopy, mut other) = (0, 0);
        for name in &self.names {
            let slot = match Marker::parse(name) {
                Some(Marker::Start { pair, .. }) => (pair, 0),
                Some(Marker::Crash {
                    role: Role::Simulator,
                    pair,
                    ..
                }) => (pair, 1),
                Some(Marker::Done {
                    role: Role::Simulator,
                    pair,
                }) => (pair, 2),
                Some(Marker::Crash {
                    role: Role::Agent,
                    pair,
                    ..
                }) => (pair, 3),
                Some(Marker::Done {
                    role: Role::Agent,
                    pair,
                }) => (pair, 4),
                Some(Marker::LogcopyDone { .. }) => {
                    logcopy += 1;
                    continue;
                }
                Some(Marker::Cancel) => continue,
                None => {
                    other += 1;
                    continue;
                }
            };
            pairs.entry(slot.0).or_default()[slot.1] += 1;
        }
        let mut lines: Vec<String> = pairs
            .iter()
            .map(|(pair, [starts, sim_crashes, sim_done, agent_crashes, agent_done])| {
                let done = |n: &u32| if *n > 0 { ", done" } else { "" };
                format!(
                    "pair {pair}: simulator started {starts}, crashed {sim_crashes}{}; agent crashed {agent_crashes}{}",
                    done(sim_done),
                    done(agent_done)
                )
            })
            .collect();
        if logcopy > 0 {
            lines.push(format!("logcopy done in {logcopy} Job(s)"));
        }
        if self.cancel_requested() {
            lines.push(format!("{CANCEL_MARKER}  <- cancel requested"));
        }
        if other > 0 {
            lines.push(format!(
                "{other} object(s) that are no marker of the protocol"
            ));
        }
        lines
    }
}

fn marker_location(bucket: &str, submission: u64) -> String {
    format!("s3://{bucket}/{submission}/{STATUS_DIR}/")
}

/// The markers in every bucket of the settings (each bucket once).
async fn markers(deployment: &Deployment, submission: u64) -> Result<Vec<Markers>> {
    let mut out: Vec<Markers> = Vec::new();
    for (name, lb) in deployment.leaderboards(None)? {
        let location = marker_location(&lb.bucket, submission);
        if out.iter().any(|m| m.location == location) {
            continue;
        }
        let store = SubmissionStore::new(deployment.s3.clone(), &lb.bucket, submission);
        let (names, error) = match store.markers().await {
            Ok(mut names) => {
                names.sort();
                (names, None)
            }
            Err(e) => {
                let error = crate::describe(&anyhow::Error::new(e));
                errln!("lbctl: warning: listing the markers under `{location}` failed: {error}");
                (Vec::new(), Some(error))
            }
        };
        out.push(Markers {
            leaderboard: name.to_string(),
            location,
            names,
            error,
        });
    }
    Ok(out)
}

fn warn_truncated(found: &Found) {
    for table in &found.truncated {
        errln!(
            "lbctl: warning: stopped reading `{table}` after {} pages; the answer may be incomplete",
            crate::deployment::MAX_SCAN_PAGES
        );
    }
}

fn tables(deployment: &Deployment, only: Option<&str>) -> String {
    deployment
        .leaderboards(only)
        .map(|lbs| {
            lbs.iter()
                .map(|(_, lb)| format!("`{}`", lb.submissions_table))
                .collect::<Vec<_>>()
                .join(", ")
        })
        .unwrap_or_default()
}

/// A submission's place in its leaderboard's queue, as the admission table shows it.
#[derive(Debug, Clone, Copy)]
struct Place {
    /// Submissions that arrived before it and have not started.
    ahead: u32,
    /// Evaluations running in its leaderboard.
    running: u32,
    /// Waiting for its team's place, admitted (its pods wait for a GPU), or running.
    state: lb_domain::queue::EntryState,
}

impl Place {
    fn to_json(self) -> Value {
        json!({"ahead": self.ahead, "state": self.state.as_str()})
    }

    /// What holds it back, in words.
    fn describe(self) -> String {
        use lb_domain::queue::EntryState;
        match self.state {
            EntryState::Waiting => format!(
                "{} ahead; waiting for one of its team's evaluations to end (team limit)",
                self.ahead
            ),
            EntryState::Admitted => format!("{} ahead; its Jobs wait for a free GPU", self.ahead),
            EntryState::Running => "running".into(),
        }
    }
}

/// Every queued submission's place, by leaderboard and id (empty without `--admission-table`).
async fn places(
    deployment: &Deployment,
    only: Option<&str>,
) -> Result<HashMap<(String, u64), Place>> {
    let mut out = HashMap::new();
    let Some(table) = &deployment.admission else {
        return Ok(out);
    };
    for (name, _) in deployment.leaderboards(only)? {
        let entries = table
            .entries(name)
            .await
            .map_err(|e| CliError::aws(format!("reading the queue of leaderboard {name}"), e))?;
        let running = entries
            .iter()
            .filter(|e| e.state == lb_domain::queue::EntryState::Running)
            .count() as u32;
        for entry in &entries {
            out.insert(
                (name.to_string(), entry.submission_id),
                Place {
                    ahead: lb_domain::queue::ahead(&entries, entry),
                    running,
                    state: entry.state,
                },
            );
        }
    }
    Ok(out)
}

/// `lbctl status`: the records and markers of one submission.
pub async fn status(args: Status) -> Result<u8> {
    let deployment = Deployment::load(&args.deployment).await?;
    let id = args.submission;
    let found = deployment.records(None, ScanFilter::Submission(id)).await?;
    warn_truncated(&found);
    let markers: Vec<Markers> = markers(&deployment, id)
        .await?
        .into_iter()
        .filter(|m| {
            !m.names.is_empty()
                || m.error.is_some()
                || found.records.iter().any(|r| r.leaderboard == m.leaderboard)
        })
        .collect();
    if found.records.is_empty() && markers.iter().all(|m| m.names.is_empty()) {
        let unreadable = markers.iter().filter(|m| m.error.is_some()).count();
        let buckets = if unreadable == 0 {
            "the buckets".to_string()
        } else {
            format!("the buckets ({unreadable} unreadable)")
        };
        return Err(CliError::NotFound(format!(
            "submission `{id}` has no record in {} and no markers in {buckets}",
            tables(&deployment, None)
        )));
    }
    let places = places(&deployment, None).await?;
    let queue: Vec<(&str, Place)> = places
        .iter()
        .filter(|((_, sid), _)| *sid == id)
        .map(|((lb, _), place)| (lb.as_str(), *place))
        .collect();
    if args.json {
        outln!("{}", pretty(&status_json(id, &queue, &found, &markers)));
        return Ok(0);
    }
    print_status(&deployment, id, &queue, &found.records, &markers);
    Ok(0)
}

/// `lbctl status --json`.
fn status_json(id: u64, queue: &[(&str, Place)], found: &Found, markers: &[Markers]) -> Value {
    json!({
        "submission_id": id,
        "queue": queue.iter().map(|(lb, p)| {
            let mut v = p.to_json();
            v["leaderboard"] = json!(lb);
            v
        }).collect::<Vec<_>>(),
        "records": found.records.iter().map(Record::to_json).collect::<Vec<_>>(),
        "markers": markers.iter().map(|m| json!({
            "leaderboard": m.leaderboard,
            "location": m.location,
            "names": m.names.iter().take(MAX_LISTED).collect::<Vec<_>>(),
            "count": m.names.len(),
            "summary": m.summary(),
            "cancel_requested": m.cancel_requested(),
            "error": m.error,
        })).collect::<Vec<_>>(),
        "incomplete_scans": found.truncated,
    })
}

/// `lbctl status` as text.
fn print_status(
    deployment: &Deployment,
    id: u64,
    queue: &[(&str, Place)],
    records: &[Record],
    markers: &[Markers],
) {
    outln!("submission {id}");
    if records.is_empty() {
        outln!(
            "no record in {} (never claimed, or claimed elsewhere)",
            tables(deployment, None)
        );
    }
    for record in records {
        print_record(record);
    }
    for (lb, place) in queue {
        outln!("queue of leaderboard {lb}: {}", place.describe());
    }
    for m in markers {
        outln!("markers in {} (leaderboard {})", m.location, m.leaderboard);
        if let Some(error) = &m.error {
            outln!("  (unreadable: {error})");
        } else if m.names.is_empty() {
            outln!("  (none)");
        }
        for line in m.summary() {
            outln!("  {line}");
        }
    }
}

fn print_record(record: &Record) {
    let text = |key: &str| record.text(key).map(clean).unwrap_or_else(|| "-".into());
    let number = |key: &str| {
        record
            .number(key)
            .map_or_else(|| "-".to_string(), |n| n.to_string())
    };
    outln!(
        "record in `{}` (leaderboard {})",
        record.table,
        record.leaderboard
    );
    let rows = [
        (
            "status",
            format!(
                "{}{}",
                text("submission_status"),
                if unaudited(record) { "*" } else { "" }
            ),
        ),
        (
            "team",
            format!("{} (id {})", text("team_name"), number("team_id")),
        ),
        (
            "track",
            format!("{} (phase {})", text("track_name"), number("track_id")),
        ),
        ("image", text("submitted_image_uri")),
        ("runs digest", text("image_digest")),
        ("workers", number("parallelization_workers")),
        (
            "routes",
            format!("{}/{}", number("routes_done"), number("routes_total")),
        ),
        ("submitted", text("submitted_time")),
        ("started", text("start_time")),
        ("ended", text("end_time")),
        ("results", text("results")),
        ("claimed by", text("claimed_by")),
    ];
    for (label, value) in rows {
        outln!("  {label:<12} {value}");
    }
    if let Some(usage) = record.usage() {
        outln!("  {:<12} {}", "GPUs", usage.describe());
    }
    if let Some(bytes) = record.number("log_bytes_stored") {
        let refused = record.number("uploads_refused").unwrap_or(0);
        let gib = bytes as f64 / f64::from(1u32 << 30);
        outln!(
            "  {:<12} {gib:.2} GiB kept in S3; {refused} file(s) refused (not the protocol's, too large, or over the logs' budget)",
            "logs"
        );
    }
    if let Some(error) = record.text("error") {
        outln!("  {:<12} {}", "error", clean(error));
    }
    if let Some((passed, expected)) = recordings(record) {
        let note = if passed < expected {
            format!(
                " ({} route(s) without a CARLA recording that passed the audit: these scores cannot be audited; docs/security.md)",
                expected - passed
            )
        } else {
            String::new()
        };
        outln!("  {:<12} {passed}/{expected} passed{note}", "recordings");
        for failure in record.texts("recordings_failed") {
            outln!("  {:<12} {}", "", clean(failure));
        }
    }
    for (key, value) in record.extra_attributes() {
        outln!("  {:<12} {value}", clean(key));
    }
}

/// `lbctl list`: submissions, newest first, one line each, with each waiting submission's
/// place in the queue and every submission's age.
pub async fn list(args: List) -> Result<u8> {
    let deployment = Deployment::load(&args.deployment).await?;
    let filter = if args.running {
        ScanFilter::InFlight
    } else {
        ScanFilter::All
    };
    let found = deployment
        .records(args.leaderboard.as_deref(), filter)
        .await?;
    warn_truncated(&found);
    let now = time::OffsetDateTime::now_utc();
    let queue = queue_positions(&found.records);
    let places = places(&deployment, args.leaderboard.as_deref()).await?;
    let matching: Vec<&Record> = found.records.iter().filter(|r| wanted(&args, r)).collect();
    let limit = usize::try_from(args.limit).unwrap_or(usize::MAX);
    let shown = &matching[..matching.len().min(limit)];
    // 1 for the next to start in its leaderboard: the admission table's count when it is
    // named, else the records' order of arrival.
    let place = |r: &Record| {
        places
            .get(&(r.leaderboard.clone(), r.submission_id()?))
            .copied()
    };
    let position = |r: &Record| {
        let id = r.submission_id()?;
        if let Some(place) = place(r) {
            return (place.state != lb_domain::queue::EntryState::Running)
                .then_some(place.ahead as usize + 1);
        }
        queue
            .iter()
            .filter(|(lb, _)| *lb == r.leaderboard)
            .position(|(_, q)| *q == id)
            .map(|i| i + 1)
    };
    let estimates = estimates(&deployment, shown, &places).await;
    let estimate = |r: &Record| {
        estimates
            .get(&(r.leaderboard.clone(), r.submission_id()?))
            .copied()
    };
    if args.json {
        let out: Vec<Value> = shown
            .iter()
            .map(|r| {
                let mut v = r.to_json();
                v["queue_position"] = json!(position(r));
                v["estimated_start_seconds"] =
                    estimate(r).map_or(Value::Null, |e| json!({"low": e.low, "high": e.high}));
                v["queue"] = place(r).map_or(Value::Null, Place::to_json);
                v["age_seconds"] = json!(age(r, now).map(|d| d.whole_seconds()));
                v
            })
            .collect();
        outln!("{}", pretty(&Value::Array(out)));
        return Ok(0);
    }
    let row = |r: &Record| (position(r), estimate(r));
    print_list(&args, &deployment, (&matching, shown), &row, now);
    Ok(0)
}

/// Whether record `r` passes `lbctl list`'s `--team` and `--status`.
fn wanted(args: &List, r: &Record) -> bool {
    let team_ok = args.team.as_deref().is_none_or(|team| {
        r.number("team_id")
            .is_some_and(|id| id.to_string() == team.trim())
            || r.text("team_name")
                .is_some_and(|name| name.eq_ignore_ascii_case(team.trim()))
    });
    team_ok && args.status.is_none_or(|s| r.status() == Some(s))
}

/// A listed record's place in its queue and estimated start.
type QueueColumns = (Option<usize>, Option<lb_domain::queue::StartEstimate>);

/// `lbctl list` as text: a line per shown record (`row`: its queue position and estimated
/// start), then what was left out and each team's GPU usage.
fn print_list(
    args: &List,
    deployment: &Deployment,
    (matching, shown): (&[&Record], &[&Record]),
    row: &dyn Fn(&Record) -> QueueColumns,
    now: time::OffsetDateTime,
) {
    if shown.is_empty() {
        let what = if args.running {
            "no submission is queued or running"
        } else {
            "no submissions"
        };
        let filtered = if args.team.is_some() || args.status.is_some() {
            " match the filters"
        } else {
            ""
        };
        outln!(
            "{what}{filtered} ({})",
            tables(deployment, args.leaderboard.as_deref())
        );
        return;
    }
    outln!(
        "{:<10} {:<4} {:<9} {:>5} {:>9} {:>6} {:<28} {:<18} {:>7} {:>14}  {:<23} ENDED",
        "SUBMISSION",
        "LB",
        "STATUS",
        "QUEUE",
        "STARTS IN",
        "AGE",
        "TEAM",
        "TRACK",
        "ROUTES",
        "GPU COST",
        "SUBMITTED"
    );
    for record in shown {
        outln!("{}", list_line(record, row(record), age(record, now)));
    }
    if matching.len() > shown.len() {
        outln!("... {} more (raise --limit)", matching.len() - shown.len());
    }
    for (team, usage) in team_usage(matching) {
        outln!("team {team}: {}", usage.describe());
    }
    if shown.iter().any(|r| unaudited(r)) {
        outln!("* some routes have no CARLA recording that passed the audit: the scores cannot be audited (lbctl status <submission>)");
    }
}

/// Claimed submissions whose Jobs do not run yet, per leaderboard, oldest first: the queue.
pub(crate) fn queue_positions(records: &[Record]) -> Vec<(&str, u64)> {
    let mut waiting: Vec<(&str, &str, u64)> = records
        .iter()
        .filter(|r| {
            matches!(
                r.status(),
                Some(RecordStatus::Submitted | RecordStatus::Resuming)
            )
        })
        .filter_map(|r| {
            Some((
                r.leaderboard.as_str(),
                r.text("submitted_time").unwrap_or_default(),
                r.submission_id()?,
            ))
        })
        .collect();
    // NB: `2024-03-07 10:31:02 UTC` sorts as it reads; the id breaks ties (EvalAI's order).
    waiting.sort();
    waiting.into_iter().map(|(lb, _, id)| (lb, id)).collect()
}

/// How long ago the submission was claimed.
fn age(record: &Record, now: time::OffsetDateTime) -> Option<time::Duration> {
    let at = record.text("submitted_time")?;
    let parsed = time::PrimitiveDateTime::parse(
        at.trim_end_matches(" UTC"),
        time::macros::format_description!("[year]-[month]-[day] [hour]:[minute]:[second]"),
    )
    .map(time::PrimitiveDateTime::assume_utc)
    .or_else(|_| time::OffsetDateTime::parse(at, &time::format_description::well_known::Rfc3339))
    .ok()?;
    Some(now - parsed)
}

fn short_age(age: time::Duration) -> String {
    let minutes = age.whole_minutes().max(0);
    match minutes {
        m if m < 60 => format!("{m}m"),
        m if m < 48 * 60 => format!("{}h{:02}m", m / 60, m % 60),
        m => format!("{}d{:02}h", m / (24 * 60), (m / 60) % 24),
    }
}

/// A result's routes whose CARLA recording passed the audit, and the routes that need one
/// (FINISHED records only).
fn recordings(record: &Record) -> Option<(u64, u64)> {
    Some((
        record.number("recordings_found")?,
        record.number("recordings_expected")?,
    ))
}

/// A FINISHED result some of whose routes lack a recording that passed the audit.
fn unaudited(record: &Record) -> bool {
    recordings(record).is_some_and(|(found, expected)| found < expected)
}

/// The estimated start of every shown submission whose pods wait for a GPU, from its
/// leaderboard's running evaluations and its track's pace (none where it cannot be read).
async fn estimates(
    deployment: &Deployment,
    shown: &[&Record],
    places: &HashMap<(String, u64), Place>,
) -> HashMap<(String, u64), lb_domain::queue::StartEstimate> {
    let mut out = HashMap::new();
    let Some(table) = &deployment.admission else {
        return out;
    };
    let mut paces: HashMap<(String, String), Vec<u64>> = HashMap::new();
    for record in shown {
        let (Some(id), Some(track)) = (record.submission_id(), record.text("track_name")) else {
            continue;
        };
        let key = (record.leaderboard.clone(), id);
        let Some(place) = places.get(&key) else {
            continue;
        };
        if place.state != lb_domain::queue::EntryState::Admitted {
            continue;
        }
        let pace_key = (record.leaderboard.clone(), track.to_string());
        if !paces.contains_key(&pace_key) {
            let pace = table
                .pace(&record.leaderboard, track)
                .await
                .unwrap_or_default();
            paces.insert(pace_key.clone(), pace);
        }
        if let Some(e) =
            lb_domain::queue::estimate_start(place.ahead, place.running, &paces[&pace_key])
        {
            out.insert(key, e);
        }
    }
    out
}

/// `~40m`, `1h-3h`: an estimated start in a column.
fn short_estimate(e: lb_domain::queue::StartEstimate) -> String {
    match e.shown() {
        lb_domain::queue::Shown::Minutes(low, high) => format!("{low}-{high}m"),
        lb_domain::queue::Shown::Hours(low, high) => format!("{low}-{high}h"),
    }
}

fn list_line(
    record: &Record,
    (queue, estimate): (Option<usize>, Option<lb_domain::queue::StartEstimate>),
    age: Option<time::Duration>,
) -> String {
    let text = |key: &str| record.text(key).map(clean).unwrap_or_else(|| "-".into());
    let number = |key: &str| {
        record
            .number(key)
            .map_or_else(|| "-".to_string(), |n| n.to_string())
    };
    let team = format!("{} ({})", text("team_name"), number("team_id"));
    let line = format!(
        "{:<10} {:<4} {:<9} {:>5} {:>9} {:>6} {:<28} {:<18} {:>7} {:>14}  {:<23} {}",
        number("submission_id"),
        clean(&record.leaderboard),
        format!(
            "{}{}",
            text("submission_status"),
            if unaudited(record) { "*" } else { "" }
        ),
        queue.map_or_else(|| "-".to_string(), |q| q.to_string()),
        estimate.map_or_else(|| "-".to_string(), short_estimate),
        age.map_or_else(|| "-".to_string(), short_age),
        shorten(&team, 28),
        shorten(&text("track_name"), 18),
        format!("{}/{}", number("routes_done"), number("routes_total")),
        record.usage().map_or_else(|| "-".into(), |u| u.short()),
        text("submitted_time"),
        text("end_time"),
    );
    line.trim_end().to_string()
}

/// GPU usage added up per team over the listed records that have any, largest first.
fn team_usage(records: &[&Record]) -> Vec<(String, Usage)> {
    let mut teams: Vec<(String, Usage)> = Vec::new();
    for record in records {
        let Some(usage) = record.usage() else {
            continue;
        };
        let team = format!(
            "{} ({})",
            record
                .text("team_name")
                .map(clean)
                .unwrap_or_else(|| "-".into()),
            record
                .number("team_id")
                .map_or_else(|| "-".into(), |n| n.to_string())
        );
        match teams.iter_mut().find(|(t, _)| *t == team) {
            Some((_, total)) => *total = total.add(usage),
            None => teams.push((team, usage)),
        }
    }
    teams.sort_by(|a, b| b.1.gpu_seconds.cmp(&a.1.gpu_seconds).then(a.0.cmp(&b.0)));
    teams
}

fn shorten(text: &str, width: usize) -> String {
    if text.chars().count() <= width {
        return text.to_string();
    }
    let mut out: String = text.chars().take(width.saturating_sub(1)).collect();
    out.push('~');
    out
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
                .map(|r| format!("{} in `{}`", clean(r.status_word()), r.table))
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
                    format!("record {}", clean(record.status_word())),
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

fn pretty(value: &Value) -> String {
    serde_json::to_string_pretty(value).unwrap_or_else(|_| value.to_string())
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
        .map(|r| format!("{} in `{}`", clean(r.status_word()), r.table))
        .collect();
    if !in_flight.is_empty() && !args.force {
        let claimed = found.records.iter().find_map(|r| r.text("claimed_by"));
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

/// `--status`, in any case: one of the record's statuses.
fn record_status(word: &str) -> std::result::Result<RecordStatus, String> {
    word.trim()
        .to_ascii_uppercase()
        .parse()
        .map_err(|e: lb_domain::status::UnknownStatus| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use aws_sdk_dynamodb::types::AttributeValue;

    #[test]
    fn a_list_line_shows_the_record_and_never_a_raw_control_character() {
        let record = Record {
            leaderboard: "2.0".into(),
            table: "t".into(),
            item: [
                ("submission_id", AttributeValue::N("12".into())),
                ("team_id", AttributeValue::N("3".into())),
                (
                    "team_name",
                    AttributeValue::S("Evil\u{1b}[2J \u{202e}Team".into()),
                ),
                ("submission_status", AttributeValue::S("RUNNING".into())),
                ("track_name", AttributeValue::S("SENSORS".into())),
                ("routes_done", AttributeValue::N("5".into())),
                ("routes_total", AttributeValue::N("20".into())),
            ]
            .into_iter()
            .map(|(k, v)| (k.to_string(), v))
            .collect(),
        };
        let line = list_line(&record, (None, None), Some(time::Duration::minutes(135)));
        assert!(
            line.starts_with("12         2.0  RUNNING       -         -  2h15m"),
            "{line}"
        );
        let estimate = lb_domain::queue::StartEstimate {
            low: 600,
            high: 2400,
        };
        let line = list_line(&record, (Some(3), Some(estimate)), None);
        assert!(line.contains("    3    10-40m"), "{line}");
        assert!(line.contains("5/20"), "{line}");
        assert!(!line.contains('\u{1b}'), "{line}");
        assert!(!line.contains('\u{202e}'), "{line}");
    }

    fn record(team: u64, usage: &[(&str, &str)]) -> Record {
        let mut item: HashMap<String, AttributeValue> = [
            ("team_id".to_string(), AttributeValue::N(team.to_string())),
            (
                "team_name".to_string(),
                AttributeValue::S(format!("T{team}")),
            ),
        ]
        .into_iter()
        .collect();
        for (k, v) in usage {
            item.insert(k.to_string(), AttributeValue::N(v.to_string()));
        }
        Record {
            leaderboard: "2.0".into(),
            table: "t".into(),
            item,
        }
    }

    #[test]
    fn gpu_usage_is_shown_per_submission_and_added_up_per_team() {
        let priced = [
            ("gpu_seconds", "7200"),
            ("gpu_seconds_spot", "3600"),
            ("gpu_seconds_run_again", "180"),
            ("cost_usd", "2.05"),
        ];
        let a = record(1, &priced);
        let b = record(1, &priced[..3]);
        let reclaimed = record(
            1,
            &[("gpu_seconds", "60"), ("seconds_lost_to_reclaims", "601")],
        );
        assert!(
            reclaimed
                .usage()
                .unwrap()
                .describe()
                .ends_with("; 11 minutes lost to reclaims, not counted against the time limit"),
            "{}",
            reclaimed.usage().unwrap().describe()
        );
        let c = record(
            2,
            &[
                ("gpu_seconds", "36000"),
                ("cost_usd", "9.5"),
                ("orchestration_usd", "0.0125"),
            ],
        );
        let none = record(3, &[]);
        assert_eq!(
            a.usage().unwrap().describe(),
            "2.00 GPU-hours (1.00 on Spot, 0.05 run again after reclaims), about $2.05"
        );
        assert!(list_line(&a, (None, None), None).contains("2.00h $2.05"));
        assert!(b
            .usage()
            .unwrap()
            .describe()
            .ends_with("no price in the settings"));
        assert!(none.usage().is_none());
        let teams = team_usage(&[&a, &b, &c, &none]);
        assert_eq!(teams.len(), 2, "{teams:?}");
        assert_eq!(teams[0].0, "T2 (2)");
        assert!(
            teams[0]
                .1
                .describe()
                .ends_with("about $9.50; orchestration about $0.0125"),
            "{}",
            teams[0].1.describe()
        );
        assert_eq!(teams[1].1.gpu_seconds, 14_400);
        assert_eq!(teams[1].1.run_again, 360);
        assert_eq!(teams[1].1.dollars, None, "one of its runs had no price");
    }

    #[test]
    fn ages_read_in_minutes_hours_then_days() {
        assert_eq!(short_age(time::Duration::seconds(59)), "0m");
        assert_eq!(short_age(time::Duration::minutes(47 * 60 + 5)), "47h05m");
        assert_eq!(short_age(time::Duration::hours(73)), "3d01h");
    }

    #[test]
    fn long_names_are_shortened_to_their_column() {
        assert_eq!(shorten("abcdef", 4), "abc~");
        assert_eq!(shorten("abc", 4), "abc");
    }
}
