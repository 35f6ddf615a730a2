//! `lbctl status`, `lbctl list`, `lbctl top`, `lbctl cancel` and `lbctl release`: the
//! submissions of a real deployment as its DynamoDB records and S3 markers show them, and the
//! operator's hand on them; one file per command, and here what they share.

mod cancel;
mod list;
mod release;
mod status;
mod top;

pub use cancel::{cancel, Cancel};
pub(crate) use list::queue_positions;
pub use list::{list, List};
pub use release::{release, Release};
pub use status::{status, Status};
pub use top::{top, Top};

use std::collections::{BTreeMap, HashMap};

use lb_aws::s3::{SubmissionStore, CANCEL_MARKER, STATUS_DIR};
use lb_domain::job::protocol::{Marker, Role};
use serde_json::{json, Value};

use crate::deployment::{Deployment, Found, Record};
use crate::error::{CliError, Result};

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
    state: lb_domain::capacity::queue::EntryState,
}

impl Place {
    fn to_json(self) -> Value {
        json!({"ahead": self.ahead, "state": self.state.as_str()})
    }

    /// What holds it back, in words.
    fn describe(self) -> String {
        use lb_domain::capacity::queue::EntryState;
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
            .filter(|e| e.state == lb_domain::capacity::queue::EntryState::Running)
            .count() as u32;
        for entry in &entries {
            out.insert(
                (name.to_string(), entry.submission_id),
                Place {
                    ahead: lb_domain::capacity::queue::ahead(&entries, entry),
                    running,
                    state: entry.state,
                },
            );
        }
    }
    Ok(out)
}

/// JSON for a person: indented.
fn pretty(value: &Value) -> String {
    serde_json::to_string_pretty(value).unwrap_or_else(|_| value.to_string())
}

/// A result's routes whose CARLA recording passed the audit, and the routes that need one
/// (FINISHED records only).
fn recordings(record: &Record) -> Option<(u64, u64)> {
    record.recordings
}

/// A FINISHED result some of whose routes lack a recording that passed the audit.
fn unaudited(record: &Record) -> bool {
    record.is_unaudited()
}

/// What follows a record's status: `*` for a result that cannot be audited, `!` for a
/// failure of the platform's own (footnoted where shown).
fn status_mark(record: &Record) -> &'static str {
    match (unaudited(record), record.failed_by_platform) {
        (true, _) => "*",
        (false, true) => "!",
        (false, false) => "",
    }
}
