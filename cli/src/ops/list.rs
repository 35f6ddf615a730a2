//! `lbctl list`: the submissions of a deployment, newest first, a line each, with their
//! places in the queue, estimated starts and ages.

use std::collections::HashMap;

use clap::Args;
use lb_aws::dynamo::RecordStatus;
use serde_json::{json, Value};

use crate::deployment::{clean, Deployment, DeploymentArgs, Record, ScanFilter, Usage};
use crate::error::Result;

use super::*;

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
            .get(&(r.leaderboard.clone(), r.submission_id?))
            .copied()
    };
    let position = |r: &Record| {
        let id = r.submission_id?;
        if let Some(place) = place(r) {
            return (place.state != lb_domain::capacity::queue::EntryState::Running)
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
            .get(&(r.leaderboard.clone(), r.submission_id?))
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
        r.team_id.is_some_and(|id| id.to_string() == team.trim())
            || r.team_name
                .as_deref()
                .is_some_and(|name| name.eq_ignore_ascii_case(team.trim()))
    });
    team_ok && args.status.is_none_or(|s| r.status == Some(s))
}

/// A listed record's place in its queue and estimated start.
type QueueColumns = (
    Option<usize>,
    Option<lb_domain::capacity::queue::StartEstimate>,
);

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
    if shown.iter().any(|r| status_mark(r) == "!") {
        outln!("! failed by the platform's own failure, not the participant's: resumable, and not counted against the team's limits (lbctl status <submission>)");
    }
}

/// Claimed submissions whose Jobs do not run yet, per leaderboard, oldest first: the queue.
pub(crate) fn queue_positions(records: &[Record]) -> Vec<(&str, u64)> {
    let mut waiting: Vec<(&str, &str, u64)> = records
        .iter()
        .filter(|r| {
            matches!(
                r.status,
                Some(RecordStatus::Submitted | RecordStatus::Resuming)
            )
        })
        .filter_map(|r| {
            Some((
                r.leaderboard.as_str(),
                r.submitted_time.as_deref().unwrap_or_default(),
                r.submission_id?,
            ))
        })
        .collect();
    // NB: `2024-03-07 10:31:02 UTC` sorts as it reads; the id breaks ties (EvalAI's order).
    waiting.sort();
    waiting.into_iter().map(|(lb, _, id)| (lb, id)).collect()
}

/// How long ago the submission was claimed.
pub(super) fn age(record: &Record, now: time::OffsetDateTime) -> Option<time::Duration> {
    Some(now - parse_time(record.submitted_time.as_deref()?)?)
}

/// A record's time (`2024-03-07 10:31:02 UTC`, as the original system wrote it, or RFC 3339).
pub(super) fn parse_time(at: &str) -> Option<time::OffsetDateTime> {
    time::PrimitiveDateTime::parse(
        at.trim_end_matches(" UTC"),
        time::macros::format_description!("[year]-[month]-[day] [hour]:[minute]:[second]"),
    )
    .map(time::PrimitiveDateTime::assume_utc)
    .or_else(|_| time::OffsetDateTime::parse(at, &time::format_description::well_known::Rfc3339))
    .ok()
}

pub(super) fn short_age(age: time::Duration) -> String {
    let minutes = age.whole_minutes().max(0);
    match minutes {
        m if m < 60 => format!("{m}m"),
        m if m < 48 * 60 => format!("{}h{:02}m", m / 60, m % 60),
        m => format!("{}d{:02}h", m / (24 * 60), (m / 60) % 24),
    }
}

/// The estimated start of every shown submission whose pods wait for a GPU, as its queue
/// note gives it (`lb_domain::capacity::forecast::estimate`, else places ahead at its track's
/// pace): none where neither can be read.
pub(super) async fn estimates(
    deployment: &Deployment,
    shown: &[&Record],
    places: &HashMap<(String, u64), Place>,
) -> HashMap<(String, u64), lb_domain::capacity::queue::StartEstimate> {
    use lb_domain::capacity::{forecast, queue};
    let mut out = HashMap::new();
    let Some(table) = &deployment.admission else {
        return out;
    };
    let now = time::OffsetDateTime::now_utc().unix_timestamp().max(0) as u64;
    let mut paces: HashMap<(String, String), Vec<u64>> = HashMap::new();
    let mut queues: HashMap<String, Vec<_>> = HashMap::new();
    for record in shown {
        let (Some(id), Some(track)) = (record.submission_id, record.track_name.as_deref()) else {
            continue;
        };
        let key = (record.leaderboard.clone(), id);
        let Some(place) = places.get(&key) else {
            continue;
        };
        if place.state != queue::EntryState::Admitted {
            continue;
        }
        let pace_key = (record.leaderboard.clone(), track.to_string());
        if !paces.contains_key(&pace_key) {
            let pace = table.pace(&record.leaderboard, track).await;
            paces.insert(pace_key.clone(), pace.unwrap_or_default());
        }
        if !queues.contains_key(&record.leaderboard) {
            let entries = table.entries_with_progress(&record.leaderboard).await;
            queues.insert(record.leaderboard.clone(), entries.unwrap_or_default());
        }
        let view = forecast::QueueView {
            entries: &queues[&record.leaderboard],
            durations: &paces[&pace_key],
            // Admitted: later admissions queue behind it, whatever the cap.
            team_limit: u32::MAX,
            pairs: record
                .workers
                .and_then(|w| u32::try_from(w).ok())
                .unwrap_or(1),
            free_at: &[],
            now,
        };
        let paced = || queue::estimate_start(place.ahead, place.running, &paces[&pace_key]);
        if let Some(e) = forecast::estimate(&view, id).or_else(paced) {
            out.insert(key, e);
        }
    }
    out
}

/// `~40m`, `1h-3h`: an estimated start in a column.
pub(super) fn short_estimate(e: lb_domain::capacity::queue::StartEstimate) -> String {
    match e.shown() {
        lb_domain::capacity::queue::Shown::Minutes(low, high) => format!("{low}-{high}m"),
        lb_domain::capacity::queue::Shown::Hours(low, high) => format!("{low}-{high}h"),
    }
}

fn list_line(
    record: &Record,
    (queue, estimate): (
        Option<usize>,
        Option<lb_domain::capacity::queue::StartEstimate>,
    ),
    age: Option<time::Duration>,
) -> String {
    let text = |value: Option<&String>| value.map_or_else(|| "-".into(), |v| clean(v));
    let number = |value: Option<u64>| value.map_or_else(|| "-".to_string(), |n| n.to_string());
    let team = format!(
        "{} ({})",
        text(record.team_name.as_ref()),
        number(record.team_id)
    );
    let line = format!(
        "{:<10} {:<4} {:<9} {:>5} {:>9} {:>6} {:<28} {:<18} {:>7} {:>14}  {:<23} {}",
        number(record.submission_id),
        clean(&record.leaderboard),
        format!("{}{}", text(Some(&record.status_word)), status_mark(record)),
        queue.map_or_else(|| "-".to_string(), |q| q.to_string()),
        estimate.map_or_else(|| "-".to_string(), short_estimate),
        age.map_or_else(|| "-".to_string(), short_age),
        shorten(&team, 28),
        shorten(&text(record.track_name.as_ref()), 18),
        format!("{}/{}", number(record.routes.0), number(record.routes.1)),
        record.usage().map_or_else(|| "-".into(), |u| u.short()),
        text(record.submitted_time.as_ref()),
        text(record.end_time.as_ref()),
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
                .team_name
                .as_deref()
                .map(clean)
                .unwrap_or_else(|| "-".into()),
            record.team_id.map_or_else(|| "-".into(), |n| n.to_string())
        );
        match teams.iter_mut().find(|(t, _)| *t == team) {
            Some((_, total)) => *total = total.add(usage),
            None => teams.push((team, usage)),
        }
    }
    teams.sort_by(|a, b| b.1.gpu_seconds.cmp(&a.1.gpu_seconds).then(a.0.cmp(&b.0)));
    teams
}

pub(super) fn shorten(text: &str, width: usize) -> String {
    if text.chars().count() <= width {
        return text.to_string();
    }
    let mut out: String = text.chars().take(width.saturating_sub(1)).collect();
    out.push('~');
    out
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
    use lb_aws::record::StoredRecord;

    #[test]
    fn a_list_line_shows_the_record_and_never_a_raw_control_character() {
        let record = Record {
            leaderboard: "2.0".into(),
            table: "t".into(),
            stored: StoredRecord::from_item(
                [
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
            ),
        };
        let line = list_line(&record, (None, None), Some(time::Duration::minutes(135)));
        assert!(
            line.starts_with("12         2.0  RUNNING       -         -  2h15m"),
            "{line}"
        );
        let estimate = lb_domain::capacity::queue::StartEstimate {
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
            stored: StoredRecord::from_item(item),
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
