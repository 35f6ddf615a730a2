//! `lbctl local run --latency`: how long a result takes to reach the participant, measured
//! from the fake evaluator's own write times (`FAKE_EVALUATOR_RECORD_LOG`) and the fake
//! EvalAI's request log.
//!
//! A record counts as delivered by the first accepted partial update, at or after its write,
//! whose progress ("Completed N out of ...") reaches its rank among the records written: the
//! k-th record written is in the first update showing at least k routes done. The final
//! delay is from the last evaluator's final write to the accepted `finished` status.

use fake_evalai::RequestRecord;
use time::format_description::well_known::Rfc3339;
use time::OffsetDateTime;

/// What was measured.
#[derive(Debug, Clone, PartialEq)]
pub struct Latency {
    /// Seconds from each record's write to the partial update carrying it, sorted.
    pub record_delays: Vec<f64>,
    /// Records no partial update carried (the final update did).
    pub undelivered: usize,
    /// Seconds from the last evaluator's final write to the final status.
    pub final_delay: Option<f64>,
    /// Accepted partial updates.
    pub updates: usize,
}

impl Latency {
    /// The `q`-quantile of the record delays (nearest rank), if any record was delivered.
    pub fn quantile(&self, q: f64) -> Option<f64> {
        if self.record_delays.is_empty() {
            return None;
        }
        let rank = (q * self.record_delays.len() as f64).ceil().max(1.0) as usize;
        self.record_delays.get(rank - 1).copied()
    }
}

/// The write log's lines: record writes (ms) and final writes (ms).
pub fn parse_record_log(text: &str) -> (Vec<i64>, Vec<i64>) {
    let (mut records, mut finals) = (Vec::new(), Vec::new());
    for line in text.lines() {
        let mut parts = line.split_whitespace();
        let (Some(ms), Some(what)) = (parts.next().and_then(|m| m.parse().ok()), parts.next())
        else {
            continue;
        };
        if what == "global" {
            finals.push(ms);
        } else {
            records.push(ms);
        }
    }
    records.sort_unstable();
    finals.sort_unstable();
    (records, finals)
}

/// Routes done according to an update's stdout.
fn progress(stdout: &str) -> Option<u64> {
    stdout.lines().find_map(|line| {
        let line = line.trim_start_matches("- ");
        if let Some(rest) = line.strip_prefix("Completed ") {
            return rest.split_whitespace().next()?.parse().ok();
        }
        let rest = line.strip_prefix("All ")?;
        rest.contains("have been completed")
            .then(|| rest.split_whitespace().next()?.parse().ok())?
    })
}

fn millis(record: &RequestRecord) -> Option<i64> {
    let t = OffsetDateTime::parse(&record.time, &Rfc3339).ok()?;
    Some((t.unix_timestamp_nanos() / 1_000_000) as i64)
}

/// Measures a run of `submission` from its write log and the request log.
pub fn measure(record_log: &str, requests: &[RequestRecord], submission: u64) -> Latency {
    let (records, finals) = parse_record_log(record_log);
    let ours = |r: &&RequestRecord| {
        r.method == "PUT"
            && (200..300).contains(&r.status)
            && r.body
                .as_ref()
                .and_then(|b| b["submission"].as_u64())
                .is_some_and(|s| s == submission)
    };
    let mut updates: Vec<(i64, u64)> = requests
        .iter()
        .filter(ours)
        .filter(|r| r.path.ends_with("/update_partially_evaluated_submission/"))
        .filter_map(|r| {
            let done = progress(r.body.as_ref()?["stdout"].as_str()?)?;
            Some((millis(r)?, done))
        })
        .collect();
    updates.sort_unstable();
    let finished = requests
        .iter()
        .filter(ours)
        .filter(|r| r.path.ends_with("/update_submission/"))
        .filter(|r| {
            r.body
                .as_ref()
                .is_some_and(|b| b["submission_status"] == "finished")
        })
        .filter_map(millis)
        .min();
    let mut record_delays = Vec::new();
    let mut undelivered = 0;
    for (rank, written) in records.iter().enumerate() {
        let carried = updates
            .iter()
            .find(|(at, done)| *at >= *written && *done as usize > rank);
        match carried {
            Some((at, _)) => record_delays.push((at - written) as f64 / 1000.0),
            None => undelivered += 1,
        }
    }
    record_delays.sort_by(f64::total_cmp);
    let final_delay = match (finals.last(), finished) {
        (Some(last), Some(at)) => Some((at - last) as f64 / 1000.0),
        _ => None,
    };
    Latency {
        record_delays,
        undelivered,
        final_delay,
        updates: updates.len(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn put(path: &str, time: &str, body: serde_json::Value) -> RequestRecord {
        RequestRecord {
            seq: 0,
            time: time.into(),
            method: "PUT".into(),
            path: path.into(),
            query: None,
            status: 200,
            user_id: Some(1),
            admin: false,
            body: Some(body),
            raw_body: None,
            fault: None,
            error: None,
        }
    }

    #[test]
    fn each_record_is_delivered_by_the_first_update_that_counts_it() {
        // Records written at 0 s, 1 s, 2 s (epoch 1_800_000_000 s); updates at 5 s showing 2
        // routes and at 12 s showing all 3; the final status 20 s after the final write.
        let base = 1_800_000_000_000i64;
        let log = format!(
            "{} 0\n{} 1\n{} 2\n{} global\nnot a line\n",
            base,
            base + 1000,
            base + 2000,
            base + 3000
        );
        let partial = "/api/jobs/challenges/1/update_partially_evaluated_submission/";
        let at = |s: i64| {
            OffsetDateTime::from_unix_timestamp(1_800_000_000 + s)
                .unwrap()
                .format(&Rfc3339)
                .unwrap()
        };
        let requests = vec![
            put(
                partial,
                &at(5),
                json!({"submission": 7, "stdout": "x\n- Completed 2 out of the 3 routes\n"}),
            ),
            // Another submission's and a refused update do not count.
            put(
                partial,
                &at(6),
                json!({"submission": 8, "stdout": "- All 3 route have been completed\n"}),
            ),
            RequestRecord {
                status: 400,
                ..put(
                    partial,
                    &at(7),
                    json!({"submission": 7, "stdout": "- All 3 route have been completed\n"}),
                )
            },
            put(
                partial,
                &at(12),
                json!({"submission": 7, "stdout": "- All 3 route have been completed\n"}),
            ),
            put(
                "/api/jobs/challenge/1/update_submission/",
                &at(23),
                json!({"submission": 7, "submission_status": "finished"}),
            ),
        ];
        let m = measure(&log, &requests, 7);
        assert_eq!(m.record_delays, [4.0, 5.0, 10.0]);
        assert_eq!((m.undelivered, m.updates), (0, 2));
        assert_eq!(m.final_delay, Some(20.0));
        assert_eq!(m.quantile(0.5), Some(5.0));
        assert_eq!(m.quantile(0.99), Some(10.0));
        // Without updates nothing is delivered early.
        let m = measure(&log, &requests[4..], 7);
        assert_eq!((m.undelivered, m.quantile(0.5)), (3, None));
    }
}
