//! `local-kube`: serve the local Kubernetes API until SIGINT/SIGTERM.

use std::net::SocketAddr;
use std::path::PathBuf;

use anyhow::Context;
use clap::{Parser, ValueEnum};
use local_kube::{Config, ImageMap, Isolation, LocalKube};

#[derive(Clone, Copy, Debug, ValueEnum)]
enum IsolationArg {
    Auto,
    Mount,
    None,
}

/// A local Kubernetes API server whose Job pods run as local processes.
#[derive(Debug, Parser)]
#[command(name = "local-kube", version)]
struct Args {
    /// Port on 127.0.0.1 (0 picks a free one).
    #[arg(long, default_value_t = 0)]
    port: u16,
    /// Where to write the kubeconfig.
    #[arg(long)]
    kubeconfig: PathBuf,
    /// Image -> local command map (YAML or JSON).
    #[arg(long)]
    images: Option<PathBuf>,
    /// Directory for pod volumes and logs (default: a temporary directory).
    #[arg(long)]
    state_dir: Option<PathBuf>,
    /// File holding the bearer token clients must send (written into the kubeconfig).
    #[arg(long)]
    token_file: Option<PathBuf>,
    /// Namespace answered with 403 Forbidden (repeatable).
    #[arg(long = "forbid-namespace")]
    forbidden_namespaces: Vec<String>,
    /// Container isolation.
    #[arg(long, value_enum, default_value_t = IsolationArg::Auto)]
    isolation: IsolationArg,
    /// The node's `nvidia.com/gpu` capacity: pods wait Pending (Unschedulable) until their GPU
    /// request fits (default: GPUs not modelled, every pod fits).
    #[arg(long)]
    gpus: Option<u32>,
    /// The node's `node.kubernetes.io/instance-type` label; pods' `nodeSelector` is then
    /// honoured (default: node selectors not modelled).
    #[arg(long)]
    instance_type: Option<String>,
    /// A further node label, `KEY=VALUE` (repeatable), as a node group sets them; pods'
    /// `nodeSelector` is then honoured.
    #[arg(long = "label", value_parser = parse_label)]
    labels: Vec<(String, String)>,
    /// Record the Cluster Autoscaler's `NotTriggerScaleUp` events on waiting pods, as for a
    /// node group of this one node at its maximum size.
    #[arg(long)]
    autoscaler: bool,
}

fn parse_label(text: &str) -> Result<(String, String), String> {
    let (key, value) = text
        .split_once('=')
        .ok_or_else(|| format!("`{text}` is not KEY=VALUE"))?;
    Ok((key.to_owned(), value.to_owned()))
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "local_kube=info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let args = Args::parse();
    let images = match &args.images {
        Some(p) => ImageMap::from_path(p)?,
        None => ImageMap::default(),
    };
    let token = match &args.token_file {
        Some(p) => Some(
            std::fs::read_to_string(p)
                .with_context(|| format!("reading token file {}", p.display()))?
                .trim()
                .to_owned(),
        )
        .filter(|t| !t.is_empty()),
        None => None,
    };
    let config = Config {
        images,
        state_dir: args.state_dir,
        token,
        forbidden_namespaces: args.forbidden_namespaces,
        isolation: match args.isolation {
            IsolationArg::Auto => Isolation::Auto,
            IsolationArg::Mount => Isolation::MountNamespace,
            IsolationArg::None => Isolation::None,
        },
        gpus: args.gpus,
        instance_type: args.instance_type,
        labels: args.labels.into_iter().collect(),
        autoscaler: args.autoscaler,
        ..Config::default()
    };
    let mut server = LocalKube::bind(SocketAddr::from(([127, 0, 0, 1], args.port)), config).await?;
    server
        .write_kubeconfig(&args.kubeconfig)
        .with_context(|| format!("writing {}", args.kubeconfig.display()))?;
    println!("{}", server.url());
    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
    tokio::select! {
        _ = tokio::signal::ctrl_c() => {}
        _ = term.recv() => {}
    }
    tokio::task::spawn_blocking(move || server.shutdown()).await?;
    Ok(())
}
