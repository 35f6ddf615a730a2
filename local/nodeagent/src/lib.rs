//! local-kube's process runner as the kubelet of GPU nodes of a real Kubernetes control plane:
//! it registers the nodes, runs the pods the real scheduler binds to them as local processes,
//! reports their phases and exit codes through the `status` subresource, ends deleted pods
//! as a kubelet does, evicts pods when a node's disk runs short as the kubelet's eviction
//! manager does, serves their logs to the API server, and (standing in for the Cluster
//! Autoscaler) says of a pod no node group could hold that it did not trigger a scale-up.

mod autoscaler;
pub mod eviction;
mod logs;
mod nodes;
mod sync;

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Duration;

use k8s_openapi::api::core::v1::Taint;
use local_kube::LocalKube;
use tokio::sync::watch;
use tracing::{info, warn};

pub use eviction::Disk;
pub use nodes::{cordon, uncordon, GPU_TAINT};

/// Why the agent could not start.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The kubeconfig or the API server.
    #[error("the control plane: {0}")]
    Api(String),
    /// The process runner.
    #[error("the process runner: {0}")]
    Runtime(#[from] local_kube::Error),
    /// The log endpoint's certificate or socket.
    #[error("the log endpoint: {0}")]
    Logs(String),
}

/// One GPU node, as a node group makes it.
#[derive(Debug, Clone, PartialEq)]
pub struct NodeSpec {
    /// The Node's name.
    pub name: String,
    /// Its `nvidia.com/gpu` capacity.
    pub gpus: u32,
    /// Its labels beyond the well-known ones a kubelet sets.
    pub labels: BTreeMap<String, String>,
    /// Its taints (the node group's).
    pub taints: Vec<Taint>,
    /// Its disk (`ephemeral-storage`).
    pub disk: Disk,
    /// Registered cordoned: a node the scheduler may not use until [`uncordon`] (one a node
    /// group's update launches mid-run, when the agent serves a fixed set of nodes).
    pub unschedulable: bool,
}

/// What the agent serves and how.
pub struct Config {
    /// A kubeconfig allowed to register nodes, write pod status, delete pods and write events.
    pub kubeconfig: PathBuf,
    /// The nodes it is the kubelet of.
    pub nodes: Vec<NodeSpec>,
    /// The process runner: image map, state directory, isolation and timing (its own node
    /// model is not used: the real scheduler places the pods).
    pub runtime: local_kube::Config,
    /// PEM certificate and key of the log endpoint (the API server does not verify them
    /// unless told to, as with a kubelet's self-signed serving certificate).
    pub tls: (PathBuf, PathBuf),
    /// Also stand in for the Cluster Autoscaler, whose node groups make nodes like these.
    pub autoscaler: bool,
    /// How long an evicted pod's terminal status follows its `DisruptionTarget` condition: a
    /// kubelet's status manager can be that late, and what reads the pods must not depend
    /// on seeing both at once.
    pub evictions_reported_late: Duration,
}

/// How often the agent looks at the API server's pods (a kubelet is told within about as long
/// through its watch).
const LOOK_EVERY: Duration = Duration::from_millis(250);

/// The agent, running on its own thread; dropping it stops every pod process.
pub struct NodeAgent {
    stop: watch::Sender<bool>,
    thread: Option<std::thread::JoinHandle<()>>,
    /// The nodes it serves.
    pub nodes: Vec<String>,
}

impl NodeAgent {
    /// Registers the nodes (Ready, their capacity, the log endpoint's port) and starts
    /// serving their pods.
    pub fn spawn(config: Config) -> Result<NodeAgent, Error> {
        let (ready_tx, ready_rx) = std::sync::mpsc::channel::<Result<(), Error>>();
        let (stop, stopped) = watch::channel(false);
        let names = config.nodes.iter().map(|n| n.name.clone()).collect();
        let thread = std::thread::Builder::new()
            .name("node-agent".into())
            .spawn(move || {
                let runtime = match tokio::runtime::Builder::new_multi_thread()
                    .worker_threads(2)
                    .enable_all()
                    .build()
                {
                    Ok(r) => r,
                    Err(e) => {
                        let _ = ready_tx.send(Err(Error::Api(format!("a runtime: {e}"))));
                        return;
                    }
                };
                runtime.block_on(serve(config, ready_tx, stopped));
                runtime.shutdown_timeout(Duration::from_secs(2));
            })
            .map_err(|e| Error::Api(format!("a thread: {e}")))?;
        ready_rx
            .recv()
            .map_err(|_| Error::Api("the agent ended before it was ready".into()))??;
        Ok(NodeAgent {
            stop,
            thread: Some(thread),
            nodes: names,
        })
    }

    /// Stops the pods' processes and the agent (bounded; idempotent). The Node objects stay.
    pub fn shutdown(&mut self) {
        let _ = self.stop.send(true);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

impl Drop for NodeAgent {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// The agent's life on its runtime: set up, report ready, loop until told to stop.
async fn serve(
    config: Config,
    ready: std::sync::mpsc::Sender<Result<(), Error>>,
    mut stopped: watch::Receiver<bool>,
) {
    let set_up = async {
        let client = client(&config.kubeconfig).await?;
        let runner = LocalKube::start(config.runtime).await?;
        let port = logs::serve(&config.tls, runner.url(), stopped.clone()).await?;
        for node in &config.nodes {
            nodes::register(&client, node, port).await?;
        }
        Ok::<_, Error>((client, runner))
    };
    let (client, runner) = match set_up.await {
        Ok(parts) => parts,
        Err(e) => {
            let _ = ready.send(Err(e));
            return;
        }
    };
    let _ = ready.send(Ok(()));
    info!(nodes = config.nodes.len(), "node agent serving");
    let mut runner = runner;
    let mut kubelet = sync::Kubelet::new(
        client.clone(),
        runner.runner(),
        &config.nodes,
        config.evictions_reported_late,
    );
    let mut scaler = config
        .autoscaler
        .then(|| autoscaler::StandIn::new(client.clone(), &config.nodes));
    loop {
        match kubelet.look().await {
            Ok(pending) => {
                if let Some(scaler) = scaler.as_mut() {
                    scaler.speak(&pending).await;
                }
            }
            Err(e) => warn!(error = %e, "cannot list pods"),
        }
        tokio::select! {
            _ = stopped.wait_for(|s| *s) => break,
            () = tokio::time::sleep(LOOK_EVERY) => {}
        }
    }
    // NB: the runner's shutdown ends every pod's processes.
    runner.shutdown();
}

/// A client of the kubeconfig's current context.
pub async fn client(kubeconfig: &std::path::Path) -> Result<kube::Client, Error> {
    let api = |e: String| Error::Api(format!("kubeconfig {}: {e}", kubeconfig.display()));
    let kc = kube::config::Kubeconfig::read_from(kubeconfig).map_err(|e| api(e.to_string()))?;
    let config = kube::Config::from_custom_kubeconfig(kc, &Default::default())
        .await
        .map_err(|e| api(e.to_string()))?;
    kube::Client::try_from(config).map_err(|e| api(e.to_string()))
}
