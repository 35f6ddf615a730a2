//! `lbctl status`: the records and S3 markers of one submission, as text or JSON.

use clap::Args;
use serde_json::{json, Value};

use crate::deployment::{clean, evalai_id, Deployment, DeploymentArgs, Found, Record, ScanFilter};
use crate::error::{CliError, Result};

use super::*;

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

/// The record's fixed attributes as (label, value) lines, made safe for a terminal.
fn record_rows(record: &Record) -> Vec<(&'static str, String)> {
    let text = |value: Option<&String>| value.map_or_else(|| "-".into(), |v| clean(v));
    let number = |value: Option<u64>| value.map_or_else(|| "-".to_string(), |n| n.to_string());
    vec![
        (
            "status",
            format!("{}{}", text(Some(&record.status_word)), status_mark(record)),
        ),
        (
            "team",
            format!(
                "{} (id {})",
                text(record.team_name.as_ref()),
                number(record.team_id)
            ),
        ),
        (
            "track",
            format!(
                "{} (phase {})",
                text(record.track_name.as_ref()),
                number(record.track_id)
            ),
        ),
        ("image", text(record.image.as_ref())),
        ("runs digest", text(record.image_digest.as_ref())),
        ("workers", number(record.workers)),
        (
            "routes",
            format!("{}/{}", number(record.routes.0), number(record.routes.1)),
        ),
        ("submitted", text(record.submitted_time.as_ref())),
        ("started", text(record.start_time.as_ref())),
        ("ended", text(record.end_time.as_ref())),
        ("results", text(record.results.as_ref())),
        ("claimed by", text(record.claimed_by.as_ref())),
    ]
}

fn print_record(record: &Record) {
    outln!(
        "record in `{}` (leaderboard {})",
        record.table,
        record.leaderboard
    );
    let rows = record_rows(record);
    for (label, value) in rows {
        outln!("  {label:<12} {value}");
    }
    if let Some(usage) = record.usage() {
        outln!("  {:<12} {}", "GPUs", usage.describe());
    }
    if let Some(bytes) = record.log_bytes_stored {
        let refused = record.uploads_refused.unwrap_or(0);
        let gib = bytes as f64 / f64::from(1u32 << 30);
        let objects = (record.log_objects_stored)
            .map(|n| format!(" in {n} object(s)"))
            .unwrap_or_default();
        outln!(
            "  {:<12} {gib:.2} GiB kept in S3{objects}; {refused} file(s) refused (not the protocol's, too large, over the logs' bytes or objects, or a marker said again)",
            "logs"
        );
    }
    if let Some(error) = record.error.as_deref() {
        outln!("  {:<12} {}", "error", clean(error));
    }
    if record.failed_by_platform {
        outln!(
            "  {:<12} the platform (its reclaims took a pair's pods away past the free ones), not the participant: EvalAI's `failed` does not count against the team's limits; `lbctl resume {}` once EvalAI reports it resuming",
            "failed by",
            record.submission_id.unwrap_or_default()
        );
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
        for failure in record.recordings_failed.iter() {
            outln!("  {:<12} {}", "", clean(failure));
        }
    }
    for (key, value) in record.extra_attributes() {
        outln!("  {:<12} {value}", clean(key));
    }
}
