//! `lb-sidecar init`: fills the shared volumes before the pairs start.
//!
//! Copies the official Leaderboard, ScenarioRunner and CARLA PythonAPI over whatever the
//! volumes hold, and this binary to `$LB_BIN_DIR/lb-sidecar`; creates the logs tree (mode
//! 0777, the participant's code runs as another user); removes this Job's stale markers
//! (locally and in S3); on a participant resume removes the cancel marker (else mirrors it);
//! downloads this Job's partial results and logs from S3, so a new pod resumes from them and
//! appends to the logs instead of overwriting them in S3.

use std::fs;
use std::io;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};

use lb_domain::job::protocol::{
    self, is_pair_log, Marker, AGENT_DIR, CANCEL_MARKER, LOGS_DIR, STATUS_DIR,
};
use tracing::{info, warn};

use crate::config::{process_env, Env, EnvError, InitConfig};
use crate::s3::{S3Error, UploadError, S3};
use crate::status::StatusDir;
use crate::tree::rel_path_ok;

/// The most objects init lists under one prefix.
const LIST_LIMIT: usize = 100_000;

/// Why init failed.
#[derive(Debug, thiserror::Error)]
pub enum InitError {
    /// The environment is incomplete or malformed.
    #[error(transparent)]
    Env(#[from] EnvError),
    /// An official source directory is missing.
    #[error("`{var}` names `{path}`, which is not a readable directory: {source}")]
    Source {
        /// The variable.
        var: &'static str,
        /// Its value.
        path: PathBuf,
        /// Why.
        #[source]
        source: io::Error,
    },
    /// A local file operation failed.
    #[error("cannot write `{path}`: {source}")]
    Write {
        /// The path.
        path: PathBuf,
        /// Why.
        #[source]
        source: io::Error,
    },
    /// S3 failed (after the client's retries); the pod fails and the Job's next pod tries again.
    #[error(transparent)]
    S3(#[from] S3Error),
    /// The async runtime could not be set up.
    #[error("cannot set up the runtime: {0}")]
    Runtime(#[source] io::Error),
}

impl InitError {
    /// The container's exit code: a malformed environment fails every pod alike
    /// (`lb_domain::job::protocol::exit::MISCONFIGURED`).
    pub fn exit_code(&self) -> std::process::ExitCode {
        let code = match self {
            InitError::Env(_) => lb_domain::job::protocol::exit::MISCONFIGURED,
            _ => lb_domain::job::protocol::exit::CRASHED,
        };
        std::process::ExitCode::from(code)
    }

    /// Stable name for scripts and logs.
    pub fn name(&self) -> &'static str {
        match self {
            InitError::Env(e) => e.name(),
            InitError::Source { .. } => "SourceMissing",
            InitError::Write { .. } => "WriteFailed",
            InitError::S3(_) => "S3Failed",
            InitError::Runtime(_) => "RuntimeFailed",
        }
    }
}

impl From<UploadError> for InitError {
    fn from(e: UploadError) -> Self {
        match e {
            UploadError::S3(e) => InitError::S3(e),
            UploadError::Read { path, source } => InitError::Write {
                path: path.into(),
                source,
            },
        }
    }
}

fn write_err(path: &Path) -> impl FnOnce(io::Error) -> InitError + '_ {
    move |source| InitError::Write {
        path: path.to_owned(),
        source,
    }
}

/// What init did, for its log line and for tests.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct InitReport {
    /// Files copied from the official sources.
    pub code_files: usize,
    /// Stale markers removed from S3.
    pub stale_markers: usize,
    /// Files downloaded from S3 (partial results and logs).
    pub downloaded: Vec<String>,
    /// Whether the cancel marker was removed (participant resume).
    pub cancel_removed: bool,
}

/// Runs the subcommand with the configuration from the environment.
pub fn run() -> Result<InitReport, InitError> {
    let cfg = InitConfig::read(&Env::new(&process_env))?;
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(InitError::Runtime)?;
    rt.block_on(async {
        let s3 = S3::connect(&cfg.aws).await;
        init(&cfg, &s3).await
    })
}

/// Does init's work: the official code copied, this binary installed, the logs tree made,
/// the Job's stale markers gone, the cancel marker settled, and what earlier pods of its pairs
/// left downloaded.
pub async fn init(cfg: &InitConfig, s3: &S3) -> Result<InitReport, InitError> {
    let mut report = InitReport {
        code_files: copy_code(cfg)?,
        ..InitReport::default()
    };
    install_self(&cfg.bin_dir)?;
    make_logs_tree(cfg)?;
    let status = StatusDir::new(cfg.logs_root.join(STATUS_DIR));
    report.stale_markers = remove_stale_markers(cfg, s3, &status).await?;
    report.cancel_removed = settle_cancel(cfg, s3, &status).await?;
    report.downloaded = download_left(cfg, s3).await?;
    info!(
        code_files = report.code_files,
        stale_markers = report.stale_markers,
        downloaded = report.downloaded.len(),
        cancel_removed = report.cancel_removed,
        "init done"
    );
    Ok(report)
}

/// Copies each official source tree into its volume: the number of files.
fn copy_code(cfg: &InitConfig) -> Result<usize, InitError> {
    let mut files = 0;
    for code in &cfg.code {
        let meta = fs::metadata(&code.from).and_then(|m| {
            if m.is_dir() {
                Ok(m)
            } else {
                Err(io::Error::new(
                    io::ErrorKind::NotADirectory,
                    "not a directory",
                ))
            }
        });
        if let Err(source) = meta {
            return Err(InitError::Source {
                var: code.var,
                path: code.from.clone(),
                source,
            });
        }
        fs::create_dir_all(&code.to).map_err(write_err(&code.to))?;
        clear_dir(&code.to)?;
        files += copy_tree(&code.from, &code.to)?;
        info!(from = %code.from.display(), to = %code.to.display(), "official code copied");
    }
    Ok(files)
}

/// Removes this Job's markers, local (an init container re-run in the same pod) and in S3:
/// the number removed from S3.
async fn remove_stale_markers(
    cfg: &InitConfig,
    s3: &S3,
    status: &StatusDir,
) -> Result<usize, InitError> {
    let (sub, job) = (cfg.common.submission_id, cfg.common.job_index);
    for marker in status.markers().map_err(write_err(status.path()))?.iter() {
        if marker.belongs_to_job(&cfg.pairs, job) {
            status.remove(*marker).map_err(write_err(status.path()))?;
        }
    }
    let mut removed = 0;
    for (key, _) in s3.list(&format!("{sub}/{STATUS_DIR}/"), LIST_LIMIT).await? {
        let name = key.rsplit('/').next().unwrap_or_default();
        if Marker::parse(name).is_some_and(|m| m.belongs_to_job(&cfg.pairs, job)) {
            s3.delete(&key).await?;
            removed += 1;
        }
    }
    Ok(removed)
}

/// A participant's resume removes the cancel marker; otherwise one in S3 is copied here, so
/// the pairs stop at once instead of after logcopy's first period. Whether it was removed.
async fn settle_cancel(cfg: &InitConfig, s3: &S3, status: &StatusDir) -> Result<bool, InitError> {
    let cancel_key = format!("{}/{STATUS_DIR}/{CANCEL_MARKER}", cfg.common.submission_id);
    if cfg.participant_resume {
        s3.delete(&cancel_key).await?;
        status
            .remove(Marker::Cancel)
            .map_err(write_err(status.path()))?;
        info!("participant resume: cancel marker removed");
        return Ok(true);
    }
    if s3.exists(&cancel_key).await? {
        status
            .write(Marker::Cancel)
            .map_err(write_err(status.path()))?;
    }
    Ok(false)
}

/// Downloads what earlier pods of this Job's pairs left: their partial results and logs.
async fn download_left(cfg: &InitConfig, s3: &S3) -> Result<Vec<String>, InitError> {
    let mut downloaded = Vec::new();
    for &pair in &cfg.pairs {
        let rel = format!("{AGENT_DIR}/{}", protocol::partial_results_name(pair));
        if download(s3, cfg, &rel).await? {
            downloaded.push(rel);
        }
    }
    let logs_prefix = format!("{}/{LOGS_DIR}/", cfg.common.submission_id);
    for (key, _) in s3.list(&logs_prefix, LIST_LIMIT).await? {
        let Some(under_logs) = key.strip_prefix(&logs_prefix) else {
            continue;
        };
        if !is_pair_log(under_logs, &cfg.pairs) {
            continue;
        }
        let rel = format!("{LOGS_DIR}/{under_logs}");
        if !rel_path_ok(&rel) {
            warn!(%key, "skipping a key that is not a safe path");
            continue;
        }
        if download(s3, cfg, &rel).await? {
            downloaded.push(rel);
        }
    }
    Ok(downloaded)
}

impl InitReport {
    /// The downloaded files, relative to the logs root.
    pub fn downloaded(&self) -> &[String] {
        &self.downloaded
    }
}

/// Downloads `<submission>/<rel>` to `<logs root>/<rel>`, writable by the participant.
async fn download(s3: &S3, cfg: &InitConfig, rel: &str) -> Result<bool, InitError> {
    let dest = cfg.logs_root.join(rel);
    let mut dir = dest.parent().map(Path::to_path_buf).unwrap_or_default();
    fs::create_dir_all(&dir).map_err(write_err(&dir))?;
    // Every directory between the root and the file must be writable by the participant.
    while dir.starts_with(&cfg.logs_root) && dir != cfg.logs_root {
        open_up(&dir, 0o777)?;
        if !dir.pop() {
            break;
        }
    }
    let key = format!("{}/{rel}", cfg.common.submission_id);
    if !s3.download(&key, &dest).await? {
        return Ok(false);
    }
    open_up(&dest, 0o666)?;
    info!(%key, "downloaded");
    Ok(true)
}

fn open_up(path: &Path, mode: u32) -> Result<(), InitError> {
    fs::set_permissions(path, fs::Permissions::from_mode(mode)).map_err(write_err(path))
}

/// The logs tree of the contract, every directory 0777.
fn make_logs_tree(cfg: &InitConfig) -> Result<(), InitError> {
    let root = &cfg.logs_root;
    let mut dirs = vec![
        root.join(STATUS_DIR),
        root.join(AGENT_DIR),
        root.join(LOGS_DIR),
        root.join(LOGS_DIR).join("simulator"),
        root.join(LOGS_DIR).join("agent"),
        root.join(LOGS_DIR).join("logcopy"),
    ];
    for &pair in &cfg.pairs {
        dirs.push(root.join(LOGS_DIR).join(protocol::agent_logs_dir(pair)));
    }
    for dir in dirs {
        fs::create_dir_all(&dir).map_err(write_err(&dir))?;
        // NB: explicit chmod: mkdir's mode is filtered by the umask.
        open_up(&dir, 0o777)?;
    }
    // The recordings: written by CARLA (UID 1000, as init) in the simulator's container only,
    // which alone mounts its pair's folder; closed to everyone else as well.
    for &pair in &cfg.pairs {
        let dir = root.join(protocol::recorder_dir(pair));
        fs::create_dir_all(&dir).map_err(write_err(&dir))?;
        open_up(&dir, 0o755)?;
    }
    Ok(())
}

/// Copies this executable to `<dir>/lb-sidecar` (through a temporary file, then renamed).
fn install_self(dir: &Path) -> Result<(), InitError> {
    let exe = std::env::current_exe().map_err(write_err(dir))?;
    fs::create_dir_all(dir).map_err(write_err(dir))?;
    let dest = dir.join("lb-sidecar");
    let tmp = dir.join(".lb-sidecar.tmp");
    fs::copy(&exe, &tmp).map_err(write_err(&tmp))?;
    open_up(&tmp, 0o755)?;
    fs::rename(&tmp, &dest).map_err(write_err(&dest))?;
    info!(from = %exe.display(), to = %dest.display(), "sidecar installed");
    Ok(())
}

/// Removes everything inside `dir` (a volume's mount point cannot itself be removed).
fn clear_dir(dir: &Path) -> Result<(), InitError> {
    for entry in fs::read_dir(dir).map_err(write_err(dir))? {
        let entry = entry.map_err(write_err(dir))?;
        let path = entry.path();
        let is_dir = entry.file_type().is_ok_and(|t| t.is_dir());
        let removed = if is_dir {
            fs::remove_dir_all(&path)
        } else {
            fs::remove_file(&path)
        };
        removed.map_err(write_err(&path))?;
    }
    Ok(())
}

/// Copies a tree: directories, regular files (with their modes) and symbolic links as links.
/// Returns the number of files copied.
fn copy_tree(from: &Path, to: &Path) -> Result<usize, InitError> {
    let mut files = 0;
    let read_err = |path: &Path, source| InitError::Write {
        path: path.to_owned(),
        source,
    };
    for entry in fs::read_dir(from).map_err(|e| read_err(from, e))? {
        let entry = entry.map_err(|e| read_err(from, e))?;
        let src = entry.path();
        let dest = to.join(entry.file_name());
        let kind = entry.file_type().map_err(|e| read_err(&src, e))?;
        if kind.is_symlink() {
            let target = fs::read_link(&src).map_err(|e| read_err(&src, e))?;
            std::os::unix::fs::symlink(target, &dest).map_err(write_err(&dest))?;
        } else if kind.is_dir() {
            fs::create_dir_all(&dest).map_err(write_err(&dest))?;
            let mode = fs::metadata(&src).map_or(0o755, |m| m.permissions().mode());
            files += copy_tree(&src, &dest)?;
            open_up(&dest, mode | 0o555)?;
        } else if kind.is_file() {
            fs::copy(&src, &dest).map_err(write_err(&dest))?;
            files += 1;
        } else {
            warn!(path = %src.display(), "skipping a special file");
        }
    }
    Ok(files)
}
