//! What the simulator and agent subcommands share: outcome, errors, marker reads, runtime.

use std::io;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use lb_domain::job::protocol::{exit, Marker, Markers, PairId, PairView};
use tracing::warn;

use crate::config::EnvError;
use crate::status::StatusDir;

/// How a simulator or agent container ended; the exit code follows from it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PairOutcome {
    /// Done marker written: exit 0.
    Done,
    /// Crash marker written: exit 1; the pod fails and a new pod of the Job resumes.
    Crashed,
    /// Crash marker written, and the participant's image cannot run the evaluator at all:
    /// exit 3, which the Jobs' Pod failure policy turns into the end of the Job.
    Unrunnable,
    /// The submission was cancelled: exit 0 without a marker.
    Cancelled,
}

impl PairOutcome {
    /// The container's exit code (`lb_domain::job::protocol::exit`).
    pub fn exit_code(self) -> ExitCode {
        match self {
            PairOutcome::Done | PairOutcome::Cancelled => ExitCode::SUCCESS,
            PairOutcome::Crashed => ExitCode::from(exit::CRASHED),
            PairOutcome::Unrunnable => ExitCode::from(exit::IMAGE_UNUSABLE),
        }
    }
}

/// Why a simulator or agent subcommand could not do its job at all.
#[derive(Debug, thiserror::Error)]
pub enum PairError {
    /// The environment is incomplete or malformed.
    #[error(transparent)]
    Env(#[from] EnvError),
    /// The wrapped command could not be started.
    #[error("cannot start `{program}`: {source}")]
    Spawn {
        /// The program.
        program: String,
        /// Why.
        #[source]
        source: io::Error,
    },
    /// A marker could not be written: the pair cannot coordinate any more.
    #[error("cannot write marker `{marker}` in `{dir}`: {source}")]
    Marker {
        /// The marker.
        marker: Marker,
        /// The status directory.
        dir: PathBuf,
        /// Why.
        #[source]
        source: io::Error,
    },
    /// The async runtime or the signal handlers could not be set up.
    #[error("cannot set up the runtime: {0}")]
    Runtime(#[source] io::Error),
}

impl PairError {
    /// The container's exit code: a malformed environment is the Job's and fails every pod
    /// alike (`lb_domain::job::protocol::exit::MISCONFIGURED`); the rest may pass on a new pod.
    pub fn exit_code(&self) -> ExitCode {
        match self {
            PairError::Env(_) => ExitCode::from(exit::MISCONFIGURED),
            _ => ExitCode::from(exit::CRASHED),
        }
    }

    /// Stable name for scripts and logs.
    pub fn name(&self) -> &'static str {
        match self {
            PairError::Env(e) => e.name(),
            PairError::Spawn { .. } => "SpawnFailed",
            PairError::Marker { .. } => "MarkerWriteFailed",
            PairError::Runtime(_) => "RuntimeFailed",
        }
    }
}

/// Writes a marker or says which one could not be written.
pub fn write_marker(status: &StatusDir, marker: Marker) -> Result<(), PairError> {
    status.write(marker).map_err(|source| PairError::Marker {
        marker,
        dir: status.path().to_owned(),
        source,
    })
}

/// The markers now; a directory that cannot be read counts as empty until the next look.
pub fn markers(status: &StatusDir) -> Markers {
    status.markers().unwrap_or_else(|e| {
        warn!(dir = %status.path().display(), error = %e, "cannot list the status directory");
        Markers::default()
    })
}

/// The pair as this attempt sees it now.
pub fn view(status: &StatusDir, pair: PairId, attempt: u32) -> PairView {
    markers(status).pair_view(pair, attempt)
}

/// A single-threaded runtime: the sidecar waits on a handful of things at a time.
pub fn runtime() -> Result<tokio::runtime::Runtime, PairError> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(PairError::Runtime)
}

/// Whether something accepts TCP connections on the loopback port (CARLA is ready).
pub async fn port_open(port: u16) -> bool {
    let connect = tokio::net::TcpStream::connect(("127.0.0.1", port));
    matches!(
        tokio::time::timeout(Duration::from_secs(1), connect).await,
        Ok(Ok(_))
    )
}
