//! The server handle: start in the current runtime or on its own thread, stop on drop.

use std::net::{Ipv4Addr, SocketAddr};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use axum::Router;
use tokio::net::TcpListener;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

use crate::admin;
use crate::faults::Faults;
use crate::fixture::{Fixture, FixtureError};
use crate::reqlog::RequestRecord;
use crate::routes;
use crate::state::{AdminError, NewSubmission, StateSnapshot, SubmissionSnapshot, World};

/// How long in-flight requests get after shutdown is requested before the server is aborted.
const GRACE: Duration = Duration::from_secs(2);

/// How long `spawn` waits for its thread to bind.
const SPAWN_TIMEOUT: Duration = Duration::from_secs(10);

/// State shared by the handlers and the handle.
pub(crate) struct Shared {
    world: Mutex<World>,
    /// `http://<addr>`, used for absolute file URLs when a request has no `Host`.
    pub base_url: String,
}

impl Shared {
    /// Locks the database; a panic in another handler does not make it unusable.
    pub fn lock(&self) -> MutexGuard<'_, World> {
        self.world
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }
}

/// Why the server could not start.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    /// The fixture is invalid.
    #[error(transparent)]
    Fixture(#[from] FixtureError),
    /// The address could not be bound.
    #[error("cannot bind `{addr}`: {source}")]
    Bind {
        /// The requested address.
        addr: SocketAddr,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// The server thread or its runtime could not be created.
    #[error("cannot start the server thread: {0}")]
    Thread(String),
}

impl ServerError {
    /// Stable PascalCase name of the error kind.
    pub fn name(&self) -> &'static str {
        match self {
            ServerError::Fixture(e) => e.name(),
            ServerError::Bind { .. } => "Bind",
            ServerError::Thread(_) => "Thread",
        }
    }
}

/// A running fake EvalAI. Dropping it stops the server (within a couple of seconds).
pub struct FakeEvalAi {
    shared: Arc<Shared>,
    addr: SocketAddr,
    host_token: Option<String>,
    shutdown: Option<oneshot::Sender<()>>,
    supervisor: Option<JoinHandle<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl std::fmt::Debug for FakeEvalAi {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FakeEvalAi")
            .field("addr", &self.addr)
            .finish()
    }
}

fn router(shared: Arc<Shared>) -> Router {
    Router::new()
        .merge(admin::router(shared.clone()))
        .fallback(routes::entry)
        .with_state(shared)
}

impl FakeEvalAi {
    /// Serves `fixture` on `127.0.0.1:<free port>` inside the current tokio runtime.
    pub async fn start(fixture: Fixture) -> Result<FakeEvalAi, ServerError> {
        FakeEvalAi::bind(SocketAddr::from((Ipv4Addr::LOCALHOST, 0)), fixture).await
    }

    /// Serves `fixture` on `addr` inside the current tokio runtime.
    pub async fn bind(addr: SocketAddr, fixture: Fixture) -> Result<FakeEvalAi, ServerError> {
        fixture.validate()?;
        let listener = TcpListener::bind(addr)
            .await
            .map_err(|source| ServerError::Bind { addr, source })?;
        let local = listener
            .local_addr()
            .map_err(|source| ServerError::Bind { addr, source })?;
        let base_url = format!("http://{local}");
        let shared = Arc::new(Shared {
            world: Mutex::new(World::from_fixture(&fixture)),
            base_url,
        });
        let (graceful_tx, graceful_rx) = oneshot::channel::<()>();
        let app = router(shared.clone());
        let mut server = tokio::spawn(async move {
            let result = axum::serve(listener, app)
                .with_graceful_shutdown(async move {
                    let _ = graceful_rx.await;
                })
                .await;
            if let Err(e) = result {
                tracing::error!(error = %e, "fake EvalAI server stopped with an error");
            }
        });
        let (shutdown_tx, shutdown_rx) = oneshot::channel::<()>();
        // NB: a dropped handle also closes `shutdown_rx`, which starts the shutdown.
        let supervisor = tokio::spawn(async move {
            tokio::select! {
                _ = shutdown_rx => {}
                _ = &mut server => return,
            }
            let _ = graceful_tx.send(());
            if tokio::time::timeout(GRACE, &mut server).await.is_err() {
                server.abort();
            }
        });
        tracing::info!(addr = %local, "fake EvalAI listening");
        Ok(FakeEvalAi {
            shared,
            addr: local,
            host_token: fixture
                .challenges
                .first()
                .and_then(|c| fixture.host_token(c.id))
                .map(str::to_owned),
            shutdown: Some(shutdown_tx),
            supervisor: Some(supervisor),
            thread: None,
        })
    }

    /// Serves `fixture` on `127.0.0.1:<free port>` from its own thread and runtime; usable
    /// from synchronous code and from inside another runtime.
    pub fn spawn(fixture: Fixture) -> Result<FakeEvalAi, ServerError> {
        fixture.validate()?;
        let (ready_tx, ready_rx) = std::sync::mpsc::channel();
        let thread = std::thread::Builder::new()
            .name("fake-evalai".to_owned())
            .spawn(move || {
                let runtime = match tokio::runtime::Builder::new_multi_thread()
                    .worker_threads(2)
                    .enable_all()
                    .build()
                {
                    Ok(rt) => rt,
                    Err(e) => {
                        let _ = ready_tx.send(Err(ServerError::Thread(e.to_string())));
                        return;
                    }
                };
                runtime.block_on(async move {
                    match FakeEvalAi::start(fixture).await {
                        Ok(mut handle) => {
                            let supervisor = handle.supervisor.take();
                            if ready_tx.send(Ok(handle)).is_ok() {
                                if let Some(s) = supervisor {
                                    let _ = s.await;
                                }
                            }
                        }
                        Err(e) => {
                            let _ = ready_tx.send(Err(e));
                        }
                    }
                });
                runtime.shutdown_timeout(GRACE);
            })
            .map_err(|e| ServerError::Thread(e.to_string()))?;
        let mut handle = match ready_rx.recv_timeout(SPAWN_TIMEOUT) {
            Ok(result) => result?,
            Err(e) => {
                return Err(ServerError::Thread(format!(
                    "server thread did not start: {e}"
                )))
            }
        };
        handle.thread = Some(thread);
        Ok(handle)
    }

    /// Base URL, `http://127.0.0.1:<port>` (no trailing slash).
    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// The bound address.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// A valid JWT of a host of the fixture's first challenge (`host-token` by default).
    pub fn host_token(&self) -> Option<&str> {
        self.host_token.as_deref()
    }

    /// Snapshot of every submission, its files and leaderboard rows.
    pub fn state(&self) -> StateSnapshot {
        self.shared.lock().snapshot()
    }

    /// Snapshot of one submission.
    pub fn submission(&self, id: u64) -> Option<SubmissionSnapshot> {
        self.shared.lock().submission_snapshot(id)
    }

    /// Every logged request, oldest first.
    pub fn requests(&self) -> Vec<RequestRecord> {
        self.shared.lock().log.since(0)
    }

    /// Logged requests with a sequence number above `seq`.
    pub fn requests_since(&self, seq: u64) -> Vec<RequestRecord> {
        self.shared.lock().log.since(seq)
    }

    /// The participant cancels: status becomes `cancelled` (no other effect).
    pub fn cancel(&self, id: u64) -> Result<SubmissionSnapshot, AdminError> {
        self.shared.lock().cancel(id)
    }

    /// EvalAI's resume: `failed` -> `resuming`; anything else is refused.
    pub fn resume(&self, id: u64) -> Result<SubmissionSnapshot, AdminError> {
        self.shared.lock().resume(id)
    }

    /// A new `submitted` submission with the next free id.
    pub fn add_submission(&self, new: NewSubmission) -> Result<SubmissionSnapshot, AdminError> {
        self.shared.lock().add_submission(new)
    }

    /// Empties every user's throttle window (`DELETE /_admin/throttle`).
    pub fn reset_throttle(&self) {
        self.shared.lock().throttle.reset();
    }

    /// Replaces the fault configuration (and reseeds the PRNG).
    pub fn set_faults(&self, faults: Faults) -> Result<(), AdminError> {
        faults.validate().map_err(AdminError::InvalidFaults)?;
        self.shared.lock().faults.set(faults);
        Ok(())
    }

    /// Stops the server, waiting (bounded) for in-flight requests.
    pub async fn shutdown(mut self) {
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
        if let Some(s) = self.supervisor.take() {
            let _ = tokio::time::timeout(GRACE * 2, s).await;
        }
    }
}

impl Drop for FakeEvalAi {
    fn drop(&mut self) {
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
        if let Some(thread) = self.thread.take() {
            // Bounded: the thread's supervisor aborts the server after GRACE.
            let _ = thread.join();
        }
    }
}

/// Installs the SIGINT and SIGTERM handlers now, and gives the wait for either: installed
/// before the server announces itself, a signal sent as soon as it is reachable is never lost
/// to the default action (which would end the process without its shutdown).
pub fn shutdown_signal() -> std::io::Result<impl std::future::Future<Output = ()>> {
    use tokio::signal::unix::{signal, SignalKind};
    let mut term = signal(SignalKind::terminate())?;
    let mut int = signal(SignalKind::interrupt())?;
    Ok(async move {
        tokio::select! {
            _ = term.recv() => {}
            _ = int.recv() => {}
        }
    })
}
