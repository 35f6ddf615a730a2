//! `lb-sidecar logcopy`: uploads what changed under the logs tree every period, results files
//! and markers within a second of their change (they wake the Monitor), mirrors the cancel
//! marker, and finishes with a final upload and `logcopy-<J>.done`.
//!
//! A file is recorded as uploaded only after S3 accepted it, so an S3 outage loses nothing:
//! the pass stops at the first S3 error, the next one (after an exponential backoff) tries
//! again. Memory is bounded by one part ([`PART_BYTES`]) plus one entry per tracked file.
//!
//! What goes is decided by [`UploadBudget`]: the protocol's names for this Job only, each kind
//! within its size, the logs within their bytes per pair. What it refuses is counted once per
//! name and reported with the bytes stored (`logs/logcopy/job<J>.json`) after each pass.

use std::io::{self, Read, Seek};
use std::os::unix::fs::MetadataExt;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use lb_domain::job::protocol::STATUS_DIR;
use lb_domain::job::protocol::{self, job_end, JobEnd, LogKind, Marker, CANCEL_MARKER};
use lb_domain::job::uploads::{self, Refusal, UploadBudget, UploadReport};
use sha2::{Digest, Sha256};
use tracing::{debug, info, warn};

use crate::config::{process_env, Env, EnvError, LogcopyConfig};
use crate::s3::{S3Error, UploadError, MAX_OBJECT_BYTES, PART_BYTES, S3};
use crate::signals::{Signals, Wake};
use crate::status::StatusDir;
use crate::tree::{self, Action, Tracker};

/// Between full passes, how often the results files and markers are looked at, so that a
/// change reaches S3 (and wakes the Monitor) within seconds while logs keep their period.
pub const WAKE_CHECK: Duration = Duration::from_secs(1);
/// Longest pause between passes while S3 keeps failing.
const MAX_BACKOFF: Duration = Duration::from_secs(300);
/// How long the final upload may keep retrying after a normal end.
const FINAL_UPLOAD_LIMIT: Duration = Duration::from_secs(600);
/// After SIGTERM: how long to wait for the pairs' last markers, and the whole budget (the
/// kubelet's default grace period is 30 s).
const TERM_SETTLE: Duration = Duration::from_secs(12);
const TERM_BUDGET: Duration = Duration::from_secs(25);

/// Why logcopy failed.
#[derive(Debug, thiserror::Error)]
pub enum LogcopyError {
    /// The environment is incomplete or malformed.
    #[error(transparent)]
    Env(#[from] EnvError),
    /// The logs tree is not there.
    #[error("cannot read the logs tree `{path}`: {source}")]
    Tree {
        /// `LB_LOGS_ROOT`.
        path: PathBuf,
        /// Why.
        #[source]
        source: io::Error,
    },
    /// The final upload did not get through before the deadline.
    #[error("the final upload did not complete: {0}")]
    FinalUpload(#[source] S3Error),
    /// The async runtime or the signal handlers could not be set up.
    #[error("cannot set up the runtime: {0}")]
    Runtime(#[source] io::Error),
}

impl LogcopyError {
    /// The container's exit code: a malformed environment fails every pod alike
    /// (`lb_domain::job::protocol::exit::MISCONFIGURED`).
    pub fn exit_code(&self) -> std::process::ExitCode {
        let code = match self {
            LogcopyError::Env(_) => lb_domain::job::protocol::exit::MISCONFIGURED,
            _ => lb_domain::job::protocol::exit::CRASHED,
        };
        std::process::ExitCode::from(code)
    }

    /// Stable name for scripts and logs.
    pub fn name(&self) -> &'static str {
        match self {
            LogcopyError::Env(e) => e.name(),
            LogcopyError::Tree { .. } => "LogsTreeUnreadable",
            LogcopyError::FinalUpload(_) => "FinalUploadFailed",
            LogcopyError::Runtime(_) => "RuntimeFailed",
        }
    }
}

/// How logcopy ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LogcopyEnd {
    /// The Job is over (`logcopy-<J>.done` written).
    Job(JobEnd),
    /// SIGTERM: final upload made, no done marker (the pod is going away).
    Terminated,
}

/// Runs the subcommand with the configuration from the environment.
pub fn run() -> Result<LogcopyEnd, LogcopyError> {
    let cfg = LogcopyConfig::read(&Env::new(&process_env))?;
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(LogcopyError::Runtime)?;
    rt.block_on(async {
        let mut signals = Signals::install().map_err(LogcopyError::Runtime)?;
        let s3 = S3::connect(&cfg.aws).await;
        Logcopy::new(&cfg, s3)?.run(&mut signals).await
    })
}

/// What one pass did; logged as one line per pass (tests count uploads from it).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PassStats {
    /// Regular files in the tree.
    pub files: usize,
    /// Objects written.
    pub uploaded: usize,
    /// Bytes written.
    pub uploaded_bytes: u64,
    /// Files whose metadata changed but whose content was hashed and found the same.
    pub same_content: usize,
    /// Files that could not be read (they are tried again next pass).
    pub unreadable: usize,
    /// Files left alone: another pair's results or markers, names the protocol does not
    /// define, files larger than their kind may be, logs beyond the pairs' bytes.
    pub refused: usize,
}

/// The uploader's state.
pub struct Logcopy<'a> {
    cfg: &'a LogcopyConfig,
    s3: S3,
    status: StatusDir,
    dev: u64,
    tracker: Tracker,
    budget: UploadBudget,
    /// The report as last written to S3.
    reported: Option<UploadReport>,
}

impl<'a> Logcopy<'a> {
    /// Checks the logs tree and prepares the state.
    pub fn new(cfg: &'a LogcopyConfig, s3: S3) -> Result<Logcopy<'a>, LogcopyError> {
        let tree_err = |source| LogcopyError::Tree {
            path: cfg.logs_root.clone(),
            source,
        };
        let dev = std::fs::metadata(&cfg.logs_root).map_err(tree_err)?.dev();
        let status = StatusDir::new(cfg.logs_root.join(STATUS_DIR));
        std::fs::create_dir_all(status.path()).map_err(tree_err)?;
        Ok(Logcopy {
            cfg,
            s3,
            status,
            dev,
            tracker: Tracker::default(),
            budget: UploadBudget::new(&cfg.pairs, cfg.common.job_index, cfg.max_log_objects),
            reported: None,
        })
    }

    /// Whether this Job's logcopy uploads the file now (`lb_domain::job::uploads`): its own pairs'
    /// results and markers and logs, each within its size and the logs within their bytes;
    /// never another pair's objects or files the protocol does not name. A refusal is counted
    /// (once per name).
    fn admit(&mut self, entry: &tree::Entry, last: Option<&tree::Uploaded>) -> bool {
        let size = entry.meta.size;
        match self
            .budget
            .admit(&entry.rel, size, last.map(|u| u.meta.size))
        {
            Ok(()) => true,
            // The marker it sent, looked at again (its metadata too fresh to trust): not a
            // refusal of anything new.
            Err(Refusal::Said) if last.is_some() => false,
            Err(why) => {
                if self.budget.refuse(&entry.rel, size) {
                    info!(rel = %entry.rel, bytes = size, ?why, "not uploaded");
                }
                false
            }
        }
    }

    /// The S3 object tag of a file: its logs' kind, which the buckets' lifecycle rules keep
    /// for their own time (`infra/app.yaml`).
    fn tag(&self, rel: &str) -> Option<&'static str> {
        protocol::kept_as(rel, &self.cfg.pairs).map(LogKind::tag)
    }

    /// The results files init restored from S3 are S3's already: known as uploaded, so this
    /// pod does not write them again unchanged. (Each write moves the object's time, which
    /// the Monitor reads as its pair's last results: a reclaimed pod's run-again time counts
    /// from it.) A file that differs from the object, or cannot be compared, uploads as usual.
    async fn seed_restored_results(&mut self) {
        for &pair in &self.cfg.pairs {
            let rel = format!(
                "{}/{}",
                protocol::AGENT_DIR,
                protocol::partial_results_name(pair)
            );
            let Ok((mut file, meta)) = tree::open_checked(&self.cfg.logs_root, &rel, self.dev)
            else {
                continue;
            };
            let mut local = Vec::new();
            let limit = uploads::MAX_RESULTS_BYTES;
            if meta.size > limit || (&mut file).take(limit).read_to_end(&mut local).is_err() {
                continue;
            }
            let stored = self.s3.get_small(&self.key(&rel), limit as usize).await;
            if matches!(stored, Ok(Some(ref bytes)) if *bytes == local) {
                let hash: [u8; 32] = Sha256::digest(&local).into();
                self.tracker.record(&rel, meta, hash);
                debug!(%rel, "restored results known as uploaded");
            }
        }
    }

    /// Continues the count of the Job's earlier pods, if any stored one (a report that cannot
    /// be read now counts from zero: the bucket's rules still bound what is kept).
    async fn resume_budget(&mut self) {
        let key = self.key(&uploads::report_key(self.cfg.common.job_index));
        match self.s3.get_small(&key, uploads::MAX_REPORT_BYTES).await {
            Ok(Some(bytes)) => {
                if let Some(earlier) = UploadReport::parse(&bytes) {
                    info!(
                        log_bytes = earlier.log_bytes,
                        "continuing the Job's earlier pods' log bytes"
                    );
                    self.budget.resume(&earlier);
                    self.reported = Some(*self.budget.report());
                }
            }
            Ok(None) => {}
            Err(e) => warn!(error = %e, "the earlier pods' upload report not read"),
        }
    }

    /// Writes what was stored and refused when it changed since it was last written.
    async fn report(&mut self) -> Result<(), S3Error> {
        let report = *self.budget.report();
        if self.reported.as_ref() == Some(&report) {
            return Ok(());
        }
        let key = self.key(&uploads::report_key(self.cfg.common.job_index));
        let body = report.to_bytes();
        self.s3.put(&key, body, Some(LogKind::Log.tag())).await?;
        self.reported = Some(report);
        Ok(())
    }

    fn key(&self, rel: &str) -> String {
        format!("{}/{rel}", self.cfg.common.submission_id)
    }

    /// The period loop, until the Job ends or SIGTERM.
    pub async fn run(&mut self, signals: &mut Signals) -> Result<LogcopyEnd, LogcopyError> {
        info!(
            pairs = ?self.cfg.pairs,
            period = ?self.cfg.period,
            bucket = %self.s3.bucket(),
            "logcopy started"
        );
        self.resume_budget().await;
        self.seed_restored_results().await;
        let mut failures = 0u32;
        loop {
            let period = tokio::select! {
                result = self.period() => Some(result),
                () = signals.terminate() => None,
            };
            match period {
                None => return self.terminated().await,
                Some(Ok(_)) => failures = 0,
                Some(Err(e)) => {
                    failures = failures.saturating_add(1);
                    warn!(error = %e, failures, "S3 is failing; the next pass retries");
                }
            }
            let markers = self.status.markers().unwrap_or_default();
            if let Some(end) = job_end(&markers, &self.cfg.pairs) {
                return self.finish(end, signals).await;
            }
            let pause = backoff(self.cfg.period, failures);
            if failures > 0 {
                if signals.sleep(pause).await == Wake::Terminate {
                    return self.terminated().await;
                }
                continue;
            }
            // Until the next full pass: the results files and markers, every second.
            let next = Instant::now() + pause;
            while Instant::now() + WAKE_CHECK < next {
                if signals.sleep(WAKE_CHECK).await == Wake::Terminate {
                    return self.terminated().await;
                }
                let quick = tokio::select! {
                    result = self.wake_pass() => Some(result),
                    () = signals.terminate() => None,
                };
                match quick {
                    None => return self.terminated().await,
                    // S3 failing: the full pass after the period retries (and backs off).
                    Some(Err(_)) => break,
                    Some(Ok(_)) => {}
                }
            }
            let rest = next.saturating_duration_since(Instant::now());
            if signals.sleep(rest).await == Wake::Terminate {
                return self.terminated().await;
            }
        }
    }

    /// Uploads the results files and markers that changed since they were last uploaded
    /// (the full pass's bookkeeping: nothing is uploaded twice), then the recordings CARLA
    /// finished (`tree::scan_finished_recordings`). Logs wait for their period.
    pub async fn wake_pass(&mut self) -> Result<usize, S3Error> {
        let mut uploaded = 0;
        let root = &self.cfg.logs_root;
        let recordings = tree::scan_finished_recordings(root, self.dev, &self.cfg.pairs);
        for entry in tree::scan_wake_worthy(root, self.dev)
            .into_iter()
            .chain(recordings)
        {
            let last = self.tracker.get(&entry.rel).copied();
            if tree::action(last.as_ref(), &entry.meta) == Action::Skip {
                continue;
            }
            if !self.admit(&entry, last.as_ref()) {
                continue;
            }
            match self.sync_file(&entry, last.as_ref()).await {
                Ok(Some(_)) => uploaded += 1,
                Ok(None) => {}
                Err(UploadError::Read { path, source }) => {
                    debug!(%path, error = %source, "cannot read a file; next pass retries");
                }
                Err(UploadError::S3(e)) => return Err(e),
            }
        }
        if uploaded > 0 {
            debug!(uploaded, "results or markers uploaded between passes");
        }
        Ok(uploaded)
    }

    /// One period: mirror the cancel marker, then upload what changed.
    async fn period(&mut self) -> Result<PassStats, S3Error> {
        self.mirror_cancel().await?;
        self.pass().await
    }

    async fn mirror_cancel(&self) -> Result<(), S3Error> {
        let key = self.key(&format!("{STATUS_DIR}/{CANCEL_MARKER}"));
        if !self.status.contains(Marker::Cancel) && self.s3.exists(&key).await? {
            info!("the submission was cancelled: mirroring the cancel marker");
            if let Err(e) = self.status.write(Marker::Cancel) {
                warn!(error = %e, "cannot write the cancel marker");
            }
        }
        Ok(())
    }

    /// Uploads every changed file; stops at the first S3 error.
    pub async fn pass(&mut self) -> Result<PassStats, S3Error> {
        let started = Instant::now();
        let (entries, skipped) = match tree::scan(&self.cfg.logs_root, self.dev) {
            Ok(found) => found,
            Err(e) => {
                warn!(root = %self.cfg.logs_root.display(), error = %e, "cannot walk the logs tree");
                return Ok(PassStats::default());
            }
        };
        if skipped != tree::Skipped::default() {
            debug!(?skipped, "files left out of the upload");
        }
        self.tracker.retain_present(&entries);
        let mut stats = PassStats {
            files: entries.len(),
            ..PassStats::default()
        };
        for entry in &entries {
            let last = self.tracker.get(&entry.rel).copied();
            if tree::action(last.as_ref(), &entry.meta) == Action::Skip {
                continue;
            }
            if !self.admit(entry, last.as_ref()) {
                stats.refused += 1;
                continue;
            }
            match self.sync_file(entry, last.as_ref()).await {
                Ok(Some(bytes)) => {
                    stats.uploaded += 1;
                    stats.uploaded_bytes += bytes;
                }
                Ok(None) => stats.same_content += 1,
                Err(UploadError::Read { path, source }) => {
                    debug!(%path, error = %source, "cannot read a file; next pass retries");
                    stats.unreadable += 1;
                }
                Err(UploadError::S3(e)) => {
                    info!(
                        uploaded = stats.uploaded,
                        uploaded_bytes = stats.uploaded_bytes,
                        "logcopy pass interrupted"
                    );
                    return Err(e);
                }
            }
        }
        info!(
            files = stats.files,
            uploaded = stats.uploaded,
            uploaded_bytes = stats.uploaded_bytes,
            same_content = stats.same_content,
            unreadable = stats.unreadable,
            refused = stats.refused,
            log_bytes = self.budget.report().log_bytes,
            tracked = self.tracker.len(),
            elapsed_ms = started.elapsed().as_millis() as u64,
            "logcopy pass"
        );
        self.report().await?;
        Ok(stats)
    }

    /// Uploads one file if its content changed; `Some(bytes)` when it was uploaded.
    async fn sync_file(
        &mut self,
        entry: &tree::Entry,
        last: Option<&tree::Uploaded>,
    ) -> Result<Option<u64>, UploadError> {
        let path = entry.path.display().to_string();
        let read_err = |source| UploadError::Read {
            path: path.clone(),
            source,
        };
        let (mut file, meta) =
            tree::open_checked(&self.cfg.logs_root, &entry.rel, self.dev).map_err(read_err)?;
        if meta.size > MAX_OBJECT_BYTES {
            return Err(read_err(io::Error::other(format!(
                "{} bytes is over the {MAX_OBJECT_BYTES}-byte upload limit",
                meta.size
            ))));
        }
        let key = self.key(&entry.rel);
        let same_size = last.is_some_and(|u| u.meta.size == meta.size);
        if meta.size <= PART_BYTES {
            let mut bytes = Vec::with_capacity(meta.size as usize);
            (&mut file)
                .take(meta.size)
                .read_to_end(&mut bytes)
                .map_err(read_err)?;
            let hash: [u8; 32] = Sha256::digest(&bytes).into();
            if same_size && last.is_some_and(|u| u.hash == hash) {
                self.tracker.record(&entry.rel, meta, hash);
                return Ok(None);
            }
            let len = bytes.len() as u64;
            self.s3.put(&key, bytes, self.tag(&entry.rel)).await?;
            self.tracker.record(&entry.rel, meta, hash);
            self.budget.stored(&entry.rel);
            debug!(%key, bytes = len, "uploaded");
            return Ok(Some(len));
        }
        if same_size {
            let hash = tree::hash_file(&mut file, meta.size).map_err(read_err)?;
            if last.is_some_and(|u| u.hash == hash) {
                self.tracker.record(&entry.rel, meta, hash);
                return Ok(None);
            }
            file.rewind().map_err(read_err)?;
        }
        let hash = self
            .s3
            .put_multipart(&key, &mut file, meta.size, (&path, self.tag(&entry.rel)))
            .await?;
        self.tracker.record(&entry.rel, meta, hash);
        self.budget.stored(&entry.rel);
        debug!(%key, bytes = meta.size, "uploaded in parts");
        Ok(Some(meta.size))
    }

    /// This pod's part is over: final upload (retried until it gets through, bounded), then
    /// the done marker when the Job is over for good.
    async fn finish(
        &mut self,
        end: JobEnd,
        signals: &mut Signals,
    ) -> Result<LogcopyEnd, LogcopyError> {
        info!(?end, "the Job is over: final upload");
        if end == JobEnd::Cancelled {
            // Give the pairs a moment to stop and write their last lines.
            let settle = self.cfg.period.min(Duration::from_secs(5));
            if signals.sleep(settle).await == Wake::Terminate {
                return self.terminated().await;
            }
        }
        let deadline = Instant::now() + FINAL_UPLOAD_LIMIT;
        let marker = Marker::LogcopyDone {
            job: self.cfg.common.job_index,
        };
        let mut failures = 0u32;
        loop {
            let attempt = async {
                self.pass().await?;
                if !end.closes_job() {
                    return Ok(());
                }
                // NB: written after the final pass so it never precedes what it vouches for.
                if let Err(e) = self.status.write(marker) {
                    warn!(error = %e, "cannot write the done marker locally");
                }
                self.s3
                    .put(
                        &self.key(&format!("{STATUS_DIR}/{marker}")),
                        Vec::new(),
                        None,
                    )
                    .await
            };
            let result = tokio::select! {
                r = attempt => Some(r),
                () = signals.terminate() => None,
            };
            match result {
                None => return self.terminated().await,
                Some(Ok(())) => {
                    info!(?end, done_marker = end.closes_job(), "logcopy done");
                    return Ok(LogcopyEnd::Job(end));
                }
                Some(Err(e)) => {
                    failures = failures.saturating_add(1);
                    if Instant::now() >= deadline {
                        return Err(LogcopyError::FinalUpload(e));
                    }
                    warn!(error = %e, failures, "final upload failed; retrying");
                    let pause = backoff(self.cfg.period, failures)
                        .min(deadline.saturating_duration_since(Instant::now()));
                    if signals.sleep(pause).await == Wake::Terminate {
                        return self.terminated().await;
                    }
                }
            }
        }
    }

    /// SIGTERM (a drained or reclaimed node, a deleted Job): while the pairs stop (bounded),
    /// their results files and markers go to S3 as soon as they change, so that the next pod
    /// resumes after the last route that finished here even if this pod is killed early;
    /// then one bounded final upload of everything.
    async fn terminated(&mut self) -> Result<LogcopyEnd, LogcopyError> {
        let started = Instant::now();
        info!("SIGTERM: results and markers as they change, then the final upload");
        while started.elapsed() < TERM_SETTLE {
            // NB: at every look, not only the first: a route that finishes while the pair
            // stops must not wait for the final upload, which a short grace may never allow.
            let left = TERM_SETTLE.saturating_sub(started.elapsed());
            match tokio::time::timeout(left, self.wake_pass()).await {
                Ok(Ok(0)) => {}
                Ok(Ok(n)) => info!(uploaded = n, "results and markers uploaded"),
                Ok(Err(e)) => warn!(error = %e, "results and markers not uploaded; retrying"),
                Err(_) => warn!("the results and markers upload ran out of time"),
            }
            let markers = self.status.markers().unwrap_or_default();
            let settled = markers.contains(&Marker::Cancel)
                || self
                    .cfg
                    .pairs
                    .iter()
                    .all(|&p| markers.pair_state(p) != protocol::PairState::Running);
            if settled {
                break;
            }
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
        let budget = TERM_BUDGET.saturating_sub(started.elapsed());
        let mut failures = 0u32;
        let deadline = Instant::now() + budget;
        loop {
            match tokio::time::timeout(
                deadline.saturating_duration_since(Instant::now()),
                self.pass(),
            )
            .await
            {
                Ok(Ok(_)) => return Ok(LogcopyEnd::Terminated),
                Ok(Err(e)) => {
                    failures += 1;
                    if Instant::now() >= deadline {
                        return Err(LogcopyError::FinalUpload(e));
                    }
                    warn!(error = %e, failures, "final upload failed; retrying");
                    let pause = Duration::from_millis(500 * u64::from(failures))
                        .min(deadline.saturating_duration_since(Instant::now()));
                    tokio::time::sleep(pause).await;
                }
                Err(_) => {
                    warn!("the final upload ran out of time");
                    return Ok(LogcopyEnd::Terminated);
                }
            }
        }
    }
}

/// The pause before the next pass: the period, doubled per consecutive failure, capped.
pub fn backoff(period: Duration, failures: u32) -> Duration {
    if failures == 0 {
        return period;
    }
    let factor = 1u32 << failures.min(6);
    period.saturating_mul(factor).min(MAX_BACKOFF.max(period))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backoff_doubles_per_failure_and_is_capped() {
        let p = Duration::from_secs(10);
        assert_eq!(backoff(p, 0), p);
        assert_eq!(backoff(p, 1), Duration::from_secs(20));
        assert_eq!(backoff(p, 3), Duration::from_secs(80));
        assert_eq!(backoff(p, 30), MAX_BACKOFF);
        assert_eq!(
            backoff(Duration::from_secs(600), 2),
            Duration::from_secs(600)
        );
    }
}
