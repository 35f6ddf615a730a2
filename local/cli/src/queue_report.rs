//! What the fake EvalAI saw of several submissions run together (`lbctl local run
//! --submissions`): each one's statuses in order, the queue places its participant was shown,
//! when its Jobs were created (admitted), and the host token's requests a minute. Read from
//! the fake's request log, the ground truth of what EvalAI was told.

use cli::outln;
use serde::Serialize;
use serde_json::Value;
use time::format_description::well_known::Rfc3339;
use time::OffsetDateTime;

/// One submission as EvalAI saw it.
#[derive(Debug, Clone, Serialize)]
pub struct SubmissionSeen {
    /// EvalAI submission id.
    pub id: u64,
    /// Its team.
    pub team: u64,
    /// Its place in the order of arrival (0 first).
    pub arrival: usize,
    /// Its final status on EvalAI.
    pub status: String,
    /// Why it failed (the first line of its stderr), if it did.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// The statuses our writes set, in order (repeats folded).
    pub statuses: Vec<String>,
    /// The partial updates sent (writes of `partially_evaluated` results).
    pub partial_updates: usize,
    /// The `ahead` of each queue note shown, in order (`None`: the note was removed).
    pub places: Vec<Option<u64>>,
    /// Log sequence of the `queued` update that named its Jobs: its admission.
    pub admitted_seq: Option<u64>,
    /// Log sequence of the update that first set `running`.
    pub running_seq: Option<u64>,
    /// Log sequence of its final update (finished, failed, cancelled).
    pub final_seq: Option<u64>,
}

impl SubmissionSeen {
    /// One write of ours: a queue note (`set` none), or a status set, with its log sequence.
    fn saw(&mut self, set: Option<String>, body: &Value, seq: u64) {
        let Some(set) = set else {
            let note = &body["submission_metadata"][lb_evalai::QUEUE_NOTE_KEY];
            self.places.push(note["ahead"].as_u64());
            return;
        };
        let names = body["job_name"].as_str().is_some_and(|n| !n.is_empty());
        if set == "queued" && names {
            self.admitted_seq.get_or_insert(seq);
        }
        if set == "running" {
            self.running_seq.get_or_insert(seq);
        }
        if set == "partially_evaluated" {
            self.partial_updates += 1;
        }
        if matches!(set.as_str(), "finished" | "failed" | "cancelled") {
            self.final_seq.get_or_insert(seq);
        }
        if self.statuses.last() != Some(&set) {
            self.statuses.push(set);
        }
    }
}

/// The whole run.
#[derive(Debug, Clone, Serialize)]
pub struct QueueReport {
    /// In order of arrival.
    pub submissions: Vec<SubmissionSeen>,
    /// Requests of the API (the fake's admin calls left out).
    pub requests: usize,
    /// Of those, answered 429.
    pub throttled: usize,
    /// The most requests in any 60 seconds.
    pub most_in_a_minute: usize,
}

impl QueueReport {
    /// Every submission ended `status` on EvalAI.
    pub fn all_ended(&self, status: &str) -> bool {
        self.submissions.iter().all(|s| s.status == status)
    }
}

/// The submission a host write is about, and the status it sets, if it sets one.
fn write_of(record: &fake_evalai::RequestRecord) -> Option<(u64, Option<String>, &Value)> {
    let body = record.body.as_ref()?;
    if record.path.ends_with("/update_submission_meta/") {
        let id = record
            .path
            .trim_end_matches("/update_submission_meta/")
            .rsplit('/')
            .next()?
            .parse()
            .ok()?;
        return Some((id, None, body));
    }
    let id = match &body["submission"] {
        Value::Number(n) => n.as_u64()?,
        Value::String(s) => s.parse().ok()?,
        _ => return None,
    };
    let status = body["submission_status"].as_str()?.to_lowercase();
    Some((id, Some(status), body))
}

/// Reads the log for `arrivals` (id, team, in order of arrival); `status` gives each one's
/// final status and its stderr.
pub fn report(
    log: &[fake_evalai::RequestRecord],
    arrivals: &[(u64, u64)],
    status: impl Fn(u64) -> Option<(String, Option<String>)>,
) -> QueueReport {
    let api: Vec<&fake_evalai::RequestRecord> = log.iter().filter(|r| !r.admin).collect();
    let mut submissions: Vec<SubmissionSeen> = arrivals
        .iter()
        .enumerate()
        .map(|(arrival, (id, team))| {
            let (status, stderr) = status(*id).unwrap_or_default();
            (arrival, id, team, status, stderr)
        })
        .map(|(arrival, id, team, status, stderr)| SubmissionSeen {
            id: *id,
            team: *team,
            arrival,
            status,
            reason: stderr
                .as_deref()
                .and_then(|e| e.lines().find(|l| !l.trim().is_empty()))
                .map(str::to_owned),
            statuses: Vec::new(),
            partial_updates: 0,
            places: Vec::new(),
            admitted_seq: None,
            running_seq: None,
            final_seq: None,
        })
        .collect();
    for record in api.iter().filter(|r| r.status == 200) {
        let Some((id, set, body)) = write_of(record) else {
            continue;
        };
        let Some(seen) = submissions.iter_mut().find(|s| s.id == id) else {
            continue;
        };
        seen.saw(set, body, record.seq);
    }
    let times: Vec<i128> = api
        .iter()
        .filter_map(|r| OffsetDateTime::parse(&r.time, &Rfc3339).ok())
        .map(|t| t.unix_timestamp_nanos() / 1_000_000)
        .collect();
    let mut most = 0;
    let mut from = 0;
    for to in 0..times.len() {
        while times[to] - times[from] >= 60_000 {
            from += 1;
        }
        most = most.max(to - from + 1);
    }
    QueueReport {
        submissions,
        requests: api.len(),
        throttled: api.iter().filter(|r| r.status == 429).count(),
        most_in_a_minute: most,
    }
}

/// The report as the run's summary prints it.
pub fn print(report: &QueueReport) {
    outln!();
    outln!(
        "{:<10} {:>4} {:>7}  {:<10} {:<16} STATUSES",
        "SUBMISSION",
        "TEAM",
        "ARRIVAL",
        "STATUS",
        "PLACES SHOWN"
    );
    for s in &report.submissions {
        let places: Vec<String> = s
            .places
            .iter()
            .map(|p| p.map_or_else(|| "-".into(), |n| n.to_string()))
            .collect();
        outln!(
            "{:<10} {:>4} {:>7}  {:<10} {:<16} {}",
            s.id,
            s.team,
            s.arrival + 1,
            s.status,
            places.join(","),
            s.statuses.join(" > ")
        );
        if let Some(reason) = &s.reason {
            outln!("{:<10} {}", "", cli::clean(reason));
        }
    }
    outln!(
        "EvalAI calls   {} requests, at most {} in a minute, {} throttled (429)",
        report.requests,
        report.most_in_a_minute,
        report.throttled
    );
}
