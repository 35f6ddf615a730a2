//! The server's lifecycle: bind, serve in this runtime or on its own thread, kubeconfig,
//! shutdown that leaves nothing behind.

use std::collections::BTreeSet;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use tokio::net::TcpListener;
use tokio::sync::oneshot;
use tracing::info;

use crate::api::{router, AppState, Outage};
use crate::config::{Config, Isolation};
use crate::error::{Error, Result};
use crate::kubeconfig::kubeconfig_yaml;
use crate::runtime::process::{detect, Namespaces};
use crate::runtime::Runtime;
use crate::store::{time_now, ObjKey, Store};
use k8s_openapi::api::core::v1::Pod;

enum Serving {
    /// A task in the caller's runtime.
    Task,
    /// A thread with its own runtime; `done` reports that it ended.
    Thread {
        thread: Option<std::thread::JoinHandle<()>>,
        done: std::sync::mpsc::Receiver<()>,
    },
}

/// A running local Kubernetes API server with its process runtime.
pub struct LocalKube {
    addr: SocketAddr,
    token: Option<String>,
    outage: Arc<Outage>,
    rt: Arc<Runtime>,
    state_dir: Option<tempfile::TempDir>,
    stop_server: Option<oneshot::Sender<()>>,
    serving: Serving,
}

struct Prepared {
    addr: SocketAddr,
    token: Option<String>,
    outage: Arc<Outage>,
    rt: Arc<Runtime>,
    state_dir: Option<tempfile::TempDir>,
    listener: TcpListener,
    app: axum::Router,
}

async fn prepare(addr: SocketAddr, config: Config) -> Result<Prepared> {
    let ns = detect(config.isolation).map_err(Error::Isolation)?;
    if config.isolation == Isolation::Auto && ns == Namespaces::None {
        tracing::warn!(
            "no mount namespaces available: containers that mount volumes will not start"
        );
    }
    let (state_dir, owned) = match &config.state_dir {
        Some(dir) => {
            std::fs::create_dir_all(dir).map_err(|source| Error::StateDir {
                path: dir.clone(),
                source,
            })?;
            (dir.clone(), None)
        }
        None => {
            let tmp = tempfile::Builder::new()
                .prefix("local-kube-")
                .tempdir()
                .map_err(|source| Error::StateDir {
                    path: std::env::temp_dir(),
                    source,
                })?;
            (tmp.path().to_owned(), Some(tmp))
        }
    };
    let listener = TcpListener::bind(addr)
        .await
        .map_err(|source| Error::Bind {
            addr: addr.to_string(),
            source,
        })?;
    let addr = listener.local_addr().map_err(|source| Error::Bind {
        addr: addr.to_string(),
        source,
    })?;
    let store = Arc::new(Store::new());
    let node = config.node();
    let rt = Runtime::new(store, config.images, config.timing, ns, &state_dir, node).map_err(
        |source| Error::StateDir {
            path: state_dir.clone(),
            source,
        },
    )?;
    let outage = Arc::new(Outage::default());
    let state = AppState {
        rt: rt.clone(),
        token: config.token.as_deref().map(Arc::from),
        forbidden: Arc::new(
            config
                .forbidden_namespaces
                .iter()
                .cloned()
                .collect::<BTreeSet<_>>(),
        ),
        address: Arc::from(addr.to_string()),
        started: time_now(),
        outage: outage.clone(),
    };
    info!(%addr, state_dir = %state_dir.display(), isolation = ?rt.ns, "local-kube listening");
    Ok(Prepared {
        addr,
        token: config.token,
        outage,
        rt,
        state_dir: owned,
        listener,
        app: router(state),
    })
}

fn serve(p: Prepared) -> (LocalKubeParts, impl std::future::Future<Output = ()>) {
    let (tx, rx) = oneshot::channel::<()>();
    let server = axum::serve(p.listener, p.app).with_graceful_shutdown(async move {
        let _ = rx.await;
    });
    let fut = async move {
        if let Err(e) = server.await {
            tracing::error!(error = %e, "local-kube server failed");
        }
    };
    (
        LocalKubeParts {
            addr: p.addr,
            token: p.token,
            outage: p.outage,
            rt: p.rt,
            state_dir: p.state_dir,
            stop_server: tx,
        },
        fut,
    )
}

struct LocalKubeParts {
    addr: SocketAddr,
    token: Option<String>,
    outage: Arc<Outage>,
    rt: Arc<Runtime>,
    state_dir: Option<tempfile::TempDir>,
    stop_server: oneshot::Sender<()>,
}

impl LocalKube {
    /// Starts on `127.0.0.1:0` in the current tokio runtime.
    pub async fn start(config: Config) -> Result<LocalKube> {
        Self::bind(SocketAddr::from(([127, 0, 0, 1], 0)), config).await
    }

    /// Starts on `addr` in the current tokio runtime.
    pub async fn bind(addr: SocketAddr, config: Config) -> Result<LocalKube> {
        let prepared = prepare(addr, config).await?;
        let (parts, fut) = serve(prepared);
        tokio::spawn(fut);
        Ok(Self::from_parts(parts, Serving::Task))
    }

    /// Starts on `127.0.0.1:0` on a thread with its own runtime (for synchronous callers).
    pub fn spawn(config: Config) -> Result<LocalKube> {
        Self::spawn_on(SocketAddr::from(([127, 0, 0, 1], 0)), config)
    }

    /// Starts on `addr` on a thread with its own runtime.
    pub fn spawn_on(addr: SocketAddr, config: Config) -> Result<LocalKube> {
        let (ready_tx, ready_rx) = std::sync::mpsc::channel::<Result<LocalKubeParts>>();
        let (done_tx, done) = std::sync::mpsc::channel::<()>();
        let thread = std::thread::Builder::new()
            .name("local-kube".into())
            .spawn(move || {
                let runtime = match tokio::runtime::Builder::new_multi_thread()
                    .worker_threads(2)
                    .enable_all()
                    .build()
                {
                    Ok(r) => r,
                    Err(e) => {
                        let _ = ready_tx.send(Err(Error::Runtime(e.to_string())));
                        return;
                    }
                };
                runtime.block_on(async move {
                    match prepare(addr, config).await {
                        Err(e) => {
                            let _ = ready_tx.send(Err(e));
                        }
                        Ok(p) => {
                            let (parts, fut) = serve(p);
                            if ready_tx.send(Ok(parts)).is_ok() {
                                fut.await;
                            }
                        }
                    }
                });
                runtime.shutdown_timeout(Duration::from_secs(2));
                let _ = done_tx.send(());
            })
            .map_err(|e| Error::Runtime(e.to_string()))?;
        let parts = ready_rx
            .recv()
            .map_err(|_| Error::Runtime("the server thread ended before it was ready".into()))??;
        Ok(Self::from_parts(
            parts,
            Serving::Thread {
                thread: Some(thread),
                done,
            },
        ))
    }

    fn from_parts(parts: LocalKubeParts, serving: Serving) -> Self {
        Self {
            addr: parts.addr,
            token: parts.token,
            outage: parts.outage,
            rt: parts.rt,
            state_dir: parts.state_dir,
            stop_server: Some(parts.stop_server),
            serving,
        }
    }

    /// Answers every API request with 500 `InternalError` for `duration` from now (the Jobs
    /// run on: only the API is down). Health endpoints keep answering.
    pub fn fail_requests_for(&self, duration: Duration) {
        tracing::warn!(?duration, "injected API outage");
        self.outage.fail_for(duration);
    }

    /// The outage switch, to inject one from elsewhere (a scenario's own task).
    pub fn outage(&self) -> Arc<Outage> {
        self.outage.clone()
    }

    /// `http://127.0.0.1:<port>`.
    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// The bound address.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Where pod directories (volumes, logs) live.
    pub fn pods_dir(&self) -> PathBuf {
        self.rt.pods_dir.clone()
    }

    /// A handle on the pods this server runs, for a node agent that takes them from another
    /// control plane.
    pub fn runner(&self) -> PodRunner {
        PodRunner(self.rt.clone())
    }

    /// A kubeconfig for this server (with the bearer token when one is required).
    pub fn kubeconfig_yaml(&self) -> String {
        kubeconfig_yaml(&self.url(), self.token.as_deref())
    }

    /// Writes the kubeconfig (mode 0600: it may hold the token).
    pub fn write_kubeconfig(&self, path: &Path) -> Result<()> {
        use std::io::Write;
        use std::os::unix::fs::OpenOptionsExt;
        let err = |source| Error::Kubeconfig {
            path: path.to_owned(),
            source,
        };
        let mut f = std::fs::OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(true)
            .mode(0o600)
            .open(path)
            .map_err(err)?;
        f.write_all(self.kubeconfig_yaml().as_bytes()).map_err(err)
    }

    /// Stops serving, kills every pod process (SIGTERM, short grace, SIGKILL) and removes pod
    /// directories and created mount points. Blocks for a bounded time; idempotent.
    pub fn shutdown(&mut self) {
        if self.stop_server.is_none() {
            return;
        }
        self.rt.shutdown();
        if let Some(tx) = self.stop_server.take() {
            let _ = tx.send(());
        }
        if let Serving::Thread { thread, done } = &mut self.serving {
            if done.recv_timeout(Duration::from_secs(5)).is_ok() {
                if let Some(t) = thread.take() {
                    let _ = t.join();
                }
            }
        }
        self.state_dir.take();
        info!(addr = %self.addr, "local-kube stopped");
    }
}

impl Drop for LocalKube {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// The process runner of a [`LocalKube`], shared with a node agent.
#[derive(Clone)]
pub struct PodRunner(Arc<Runtime>);

impl PodRunner {
    /// Runs a pod another scheduler bound to a node this process serves (a node agent's):
    /// stored under its own name and uid, its containers started. 409 if it is already here.
    pub fn adopt(&self, pod: Pod) -> std::result::Result<Pod, crate::status::ApiError> {
        self.0.adopt(pod)
    }

    /// Every pod held here, as its kubelet last wrote it.
    pub fn pods(&self) -> Vec<Pod> {
        self.0.store.list::<Pod>(None, |_| true).0
    }

    /// What `pod` (one held here) holds on the node's disk.
    pub fn disk_usage(&self, pod: &Pod) -> crate::PodDisk {
        crate::runtime::disk::usage(pod, &self.0.pod_dir(pod))
    }

    /// Stops a pod's containers within `grace` (capped) and waits for them, bounded; the pod
    /// and its logs stay, with the status of its terminated containers.
    pub async fn stop_pod(&self, uid: &str, grace: Option<Duration>) {
        self.0.stop_pod(uid, grace).await;
    }

    /// Stops a pod, removes its directory and the object.
    pub async fn delete_pod(&self, namespace: &str, name: &str) {
        self.0
            .delete_pod(&ObjKey::new(namespace, name), Some(Duration::ZERO))
            .await;
    }
}
