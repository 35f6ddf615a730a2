//! What logcopy may put in S3 for a pod, decided per file: its size by kind, the logs' bytes and
//! objects per pair, each marker once, and a count of what it refused (each name once), which it
//! reports with what it stored.
//!
//! The logs volume is written by the participant's code, and every byte kept is the
//! leaderboard's to pay for, for as long as the bucket keeps it. The protocol's own files are
//! small: a results file is read whole by the Monitor (at most the results' own cap), a marker
//! is an empty file whose name is the message. The logs are the evaluation's (CARLA's output,
//! the evaluator's, the recordings), bounded per file and per pair.

use std::collections::HashSet;

use serde::{Deserialize, Serialize};

use crate::job::protocol::{kept_as, LogKind, PairId, AGENT_DIR, LOGS_DIR, STATUS_DIR};

/// The largest results file uploaded: what the Monitor reads at most.
pub const MAX_RESULTS_BYTES: u64 = crate::results::MAX_FILE_BYTES as u64;

/// The largest marker uploaded: markers are empty, their name is the message.
pub const MAX_MARKER_BYTES: u64 = 1024;

/// The largest log uploaded: a CARLA recording of a long route with dense traffic is a few
/// hundred MiB; CARLA's and the evaluator's outputs are far smaller.
pub const MAX_LOG_BYTES: u64 = 1 << 30;

/// Bytes of logs one pair may keep in S3 over the whole evaluation: the `logs` volume's size
/// per pair (`lb_domain::cluster::resources::VolumeSizes`), so deleting and writing again, or a new
/// pod, cannot upload more than the volume could ever hold at once.
pub const LOG_BYTES_PER_PAIR: u64 = 8 << 30;

/// Log objects one pair may store over the whole evaluation, besides the protocol's own files
/// (results, markers, recordings), unless the leaderboard says otherwise
/// (`LeaderboardSettings::max_log_objects_per_pair`). An honest pair writes a handful
/// (CARLA's output, the evaluator's, a debug file per route); each object is a PUT and kept
/// until the logs' retention, whatever its size.
pub const LOG_OBJECTS_PER_PAIR: u32 = 1000;

/// Uploads of logs one pair may make over the whole evaluation (new objects and rewrites
/// alike), recordings aside: about $0.50 of PUTs. Logcopy sends a changed log at most once a
/// period (10 s), so an honest pair's two or three growing logs make under 80,000 in a whole
/// 72-hour run; a pod that rewrites its files every period runs out long before.
pub const LOG_PUTS_PER_PAIR: u64 = 100_000;

/// Names remembered to count each refused file once; beyond them refusals are counted per pass.
const MAX_REMEMBERED: usize = 4096;

/// Why a file is not uploaded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// A name the protocol does not define for this Job (or another pair's).
    NotOurs,
    /// Larger than its kind may be.
    TooLarge,
    /// The pair's logs already hold their bytes.
    OverBudget,
    /// The pair's logs already hold their count of objects, or of uploads.
    TooMany,
    /// A marker this pod uploaded already: a marker's name is its message, said once (each
    /// upload wakes the Monitor).
    Said,
}

/// What logcopy stored and refused for one pod: written next to the logs
/// (`logs/logcopy/job<J>.json`) and read into the submission's record.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct UploadReport {
    /// Bytes of logs kept in S3 (growth of an object counts once; a file deleted after its
    /// upload still counts: the object stays).
    pub log_bytes: u64,
    /// Log objects written (each new name once per pod; protocol files aside).
    #[serde(default)]
    pub log_objects: u64,
    /// Uploads of logs (new objects and rewrites; recordings aside).
    #[serde(default)]
    pub log_puts: u64,
    /// Files not uploaded, each name counted once per pod.
    pub refused_files: u64,
    /// Their bytes, at the size they were first refused at.
    pub refused_bytes: u64,
}

impl UploadReport {
    /// Another Job's added to this one (a submission's, over its Jobs).
    pub fn plus(self, other: UploadReport) -> UploadReport {
        UploadReport {
            log_bytes: self.log_bytes.saturating_add(other.log_bytes),
            log_objects: self.log_objects.saturating_add(other.log_objects),
            log_puts: self.log_puts.saturating_add(other.log_puts),
            refused_files: self.refused_files.saturating_add(other.refused_files),
            refused_bytes: self.refused_bytes.saturating_add(other.refused_bytes),
        }
    }

    /// As stored (JSON).
    pub fn to_bytes(&self) -> Vec<u8> {
        serde_json::to_vec(self).unwrap_or_default()
    }

    /// As stored; `None` for anything else (the object sits under `logs/`, next to files the
    /// participant's code wrote).
    pub fn parse(bytes: &[u8]) -> Option<UploadReport> {
        serde_json::from_slice(bytes).ok()
    }
}

/// The decisions for one pod's logcopy.
#[derive(Debug, Clone)]
pub struct UploadBudget {
    pairs: Vec<PairId>,
    job: u32,
    log_limit: u64,
    object_limit: u64,
    put_limit: u64,
    report: UploadReport,
    refused: HashSet<String>,
    /// The markers uploaded (only the protocol's names pass, so a few per pair).
    said: HashSet<String>,
}

impl UploadBudget {
    /// The budget of Job `job`'s pod running `pairs`, each pair's logs at most
    /// `objects_per_pair` objects.
    pub fn new(pairs: &[PairId], job: u32, objects_per_pair: u32) -> UploadBudget {
        let pair_count = pairs.len() as u64;
        UploadBudget {
            pairs: pairs.to_vec(),
            job,
            log_limit: LOG_BYTES_PER_PAIR.saturating_mul(pair_count),
            object_limit: u64::from(objects_per_pair).saturating_mul(pair_count),
            put_limit: LOG_PUTS_PER_PAIR.saturating_mul(pair_count),
            report: UploadReport::default(),
            refused: HashSet::new(),
            said: HashSet::new(),
        }
    }

    /// Continues from what the Job's earlier pods stored and refused: the logs' bytes are the
    /// pairs' for the whole evaluation, whatever pods it takes. (Each pod counts a refused
    /// name once; a name refused again by a new pod counts again.)
    pub fn resume(&mut self, earlier: &UploadReport) {
        self.report = *earlier;
    }

    /// Whether the file at `rel` (relative to the logs volume), now `size` bytes, last
    /// uploaded at `last` bytes (`None`: never, or not since it was last seen gone), goes to
    /// S3. An upload it admits is counted as stored; call [`UploadBudget::refuse`] with a
    /// refusal, and [`UploadBudget::stored`] once the file is sent.
    pub fn admit(&mut self, rel: &str, size: u64, last: Option<u64>) -> Result<(), Refusal> {
        if !crate::job::protocol::uploads(rel, &self.pairs, self.job) {
            return Err(Refusal::NotOurs);
        }
        if self.said.contains(rel) {
            return Err(Refusal::Said);
        }
        let (dir, _) = rel.split_once('/').unwrap_or(("", rel));
        let max = match dir {
            AGENT_DIR => MAX_RESULTS_BYTES,
            STATUS_DIR => MAX_MARKER_BYTES,
            _ => MAX_LOG_BYTES,
        };
        if size > max {
            return Err(Refusal::TooLarge);
        }
        if let Some(kind) = kept_as(rel, &self.pairs) {
            let grown = size.saturating_sub(last.unwrap_or(0));
            let stored = self.report.log_bytes.saturating_add(grown);
            if stored > self.log_limit {
                return Err(Refusal::OverBudget);
            }
            // A new object (or one written again after it was deleted: another PUT, and
            // another object when the name is new), recordings aside: routes bound those.
            let log = kind == LogKind::Log;
            let new_object = last.is_none() && log;
            if (new_object && self.report.log_objects >= self.object_limit)
                || (log && self.report.log_puts >= self.put_limit)
            {
                return Err(Refusal::TooMany);
            }
            self.report.log_bytes = stored;
            self.report.log_objects += u64::from(new_object);
        }
        Ok(())
    }

    /// The file at `rel` was uploaded (admitted, then sent: a same content found on reading
    /// sends nothing). A marker is not uploaded again by this pod, whatever becomes of the
    /// file (deleted and written again, changed); a log's upload is counted.
    pub fn stored(&mut self, rel: &str) {
        let (dir, _) = rel.split_once('/').unwrap_or(("", rel));
        if dir == STATUS_DIR {
            self.said.insert(rel.to_owned());
        } else if kept_as(rel, &self.pairs) == Some(LogKind::Log) {
            self.report.log_puts = self.report.log_puts.saturating_add(1);
        }
    }

    /// Counts a refused file, once per name (while the names fit in memory).
    pub fn refuse(&mut self, rel: &str, size: u64) -> bool {
        if self.refused.contains(rel) {
            return false;
        }
        if self.refused.len() < MAX_REMEMBERED {
            self.refused.insert(rel.to_owned());
        }
        self.report.refused_files = self.report.refused_files.saturating_add(1);
        self.report.refused_bytes = self.report.refused_bytes.saturating_add(size);
        true
    }

    /// What was stored and refused so far.
    pub fn report(&self) -> &UploadReport {
        &self.report
    }
}

/// The most bytes a stored report takes.
pub const MAX_REPORT_BYTES: usize = 4096;

/// The key of Job `job`'s upload report, relative to the submission's prefix.
pub fn report_key(job: u32) -> String {
    format!("{LOGS_DIR}/logcopy/job{job}.json")
}

#[cfg(test)]
mod tests {
    use super::*;

    const GIB: u64 = 1 << 30;

    /// A file (relative path, size, size last uploaded) and the decision on it.
    type Case = (&'static str, u64, Option<u64>, Result<(), Refusal>);

    #[test]
    fn each_kind_of_file_has_its_size_and_the_logs_their_bytes_per_pair() {
        let mut budget = UploadBudget::new(&[3], 2, LOG_OBJECTS_PER_PAIR);
        let cases: [Case; 10] = [
            ("agent/partial_agent_results3.json", 1 << 20, None, Ok(())),
            (
                "agent/partial_agent_results3.json",
                MAX_RESULTS_BYTES + 1,
                None,
                Err(Refusal::TooLarge),
            ),
            ("containers-status/agent-3.done", 0, None, Ok(())),
            (
                "containers-status/agent-3.crash0",
                200 << 20,
                None,
                Err(Refusal::TooLarge),
            ),
            // The 200 MiB file written at the top of the logs volume.
            ("logs/fill.bin", 200 << 20, None, Err(Refusal::NotOurs)),
            (
                "recorder/pair3/RouteScenario_0_rep0.log",
                MAX_LOG_BYTES + 1,
                None,
                Err(Refusal::TooLarge),
            ),
            ("recorder/pair3/RouteScenario_0_rep0.log", GIB, None, Ok(())),
            // A log that grows counts its growth only.
            ("logs/agent/agent3/agent.log", GIB, Some(GIB - 10), Ok(())),
            (
                "logs/agent/agent3/recorder/route1.log",
                6 * GIB,
                None,
                Err(Refusal::TooLarge),
            ),
            ("logs/agent/agent3/recorder/route1.log", GIB, None, Ok(())),
        ];
        for (rel, size, last, expected) in cases {
            assert_eq!(budget.admit(rel, size, last), expected, "{rel} {size}");
        }
        assert_eq!(budget.report().log_bytes, 2 * GIB + 10);
        // Files deleted after their upload stay counted: the pair's 8 GiB run out.
        for route in 2..8 {
            let rel = format!("recorder/pair3/RouteScenario_{route}_rep0.log");
            assert_eq!(budget.admit(&rel, GIB - 10, None), Ok(()), "{rel}");
        }
        let rel = "logs/agent/agent3/recorder/route8.log";
        assert_eq!(budget.admit(rel, GIB, None), Err(Refusal::OverBudget));
        assert!(budget.report().log_bytes <= LOG_BYTES_PER_PAIR);
        // Each refused name counts once, however many passes see it.
        assert!(budget.refuse("logs/fill.bin", 200 << 20));
        assert!(!budget.refuse("logs/fill.bin", 300 << 20));
        assert_eq!(
            (budget.report().refused_files, budget.report().refused_bytes),
            (1, 200 << 20)
        );
    }

    #[test]
    fn a_marker_is_said_once_and_log_objects_are_counted_per_pair() {
        let mut budget = UploadBudget::new(&[3], 2, 5);
        let marker = "containers-status/simulator-3.start0";
        assert_eq!(budget.admit(marker, 0, None), Ok(()));
        // Not stored (S3 failed): admitted again.
        assert_eq!(budget.admit(marker, 0, None), Ok(()));
        budget.stored(marker);
        // Deleted and written again, or changed: never again from this pod.
        assert_eq!(budget.admit(marker, 0, None), Err(Refusal::Said));
        assert_eq!(budget.admit(marker, 1, Some(0)), Err(Refusal::Said));
        let other = "containers-status/simulator-3.start1";
        assert_eq!(budget.admit(other, 0, None), Ok(()));
        // Results files are rewritten as the run goes.
        let results = "agent/partial_agent_results3.json";
        budget.stored(results);
        assert_eq!(budget.admit(results, 10, Some(5)), Ok(()));

        // Empty files cost a PUT each: five new log objects, then none.
        for n in 0..5 {
            let rel = format!("logs/agent/agent3/empty{n}");
            assert_eq!(budget.admit(&rel, 0, None), Ok(()), "{rel}");
            budget.stored(&rel);
        }
        assert_eq!(
            budget.admit("logs/agent/agent3/empty5", 0, None),
            Err(Refusal::TooMany)
        );
        // A log that grows is the same object; recordings are the routes'.
        assert_eq!(
            budget.admit("logs/agent/agent3/empty0", 100, Some(0)),
            Ok(())
        );
        budget.stored("logs/agent/agent3/empty0");
        assert_eq!(
            budget.admit("recorder/pair3/RouteScenario_0_rep0.log", 100, None),
            Ok(())
        );
        assert_eq!(budget.report().log_objects, 5);
        assert_eq!(budget.report().log_puts, 6);
        // Rewrites cost a PUT each too: a pair's uploads run out as well.
        let mut rewrites = UploadBudget::new(&[3], 2, 5);
        rewrites.resume(&UploadReport {
            log_puts: LOG_PUTS_PER_PAIR - 1,
            ..UploadReport::default()
        });
        let log = "logs/agent/agent3/agent.log";
        assert_eq!(rewrites.admit(log, 10, Some(10)), Ok(()));
        // Read and found the same: nothing sent, nothing counted.
        assert_eq!(rewrites.admit(log, 10, Some(10)), Ok(()));
        rewrites.stored(log);
        assert_eq!(rewrites.admit(log, 10, Some(10)), Err(Refusal::TooMany));
        // The count is the pair's over the evaluation: a new pod resumes it.
        let mut next = UploadBudget::new(&[3], 2, 5);
        next.resume(budget.report());
        assert_eq!(
            next.admit("logs/agent/agent3/new", 0, None),
            Err(Refusal::TooMany)
        );
        // Reports written before the count read as none.
        let old = UploadReport::parse(br#"{"log_bytes":1,"refused_files":2,"refused_bytes":3}"#);
        assert_eq!(old.map(|r| r.log_objects), Some(0));
    }
}
