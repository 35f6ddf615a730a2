//! `fake-evalai`: serve the fake EvalAI API until SIGINT/SIGTERM.

use std::io::Write as _;
use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;

use anyhow::Context as _;
use clap::Parser;
use fake_evalai::{FakeEvalAi, Fixture};

/// Serve a fake EvalAI (host-evaluation API + `/_admin/`) on loopback.
#[derive(Debug, Parser)]
#[command(name = "fake-evalai", version)]
struct Args {
    /// Port to listen on (0 picks a free one).
    #[arg(long)]
    port: u16,
    /// Fixture JSON (default: the embedded default fixture).
    #[arg(long)]
    fixture: Option<PathBuf>,
    /// Address to bind.
    #[arg(long, default_value = "127.0.0.1")]
    host: IpAddr,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    tracing_subscriber::fmt()
        .json()
        .with_writer(std::io::stderr)
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .init();
    let fixture = match &args.fixture {
        Some(path) => Fixture::from_path(path)?,
        None => Fixture::default(),
    };
    let server = FakeEvalAi::bind(SocketAddr::new(args.host, args.port), fixture).await?;
    let stop = fake_evalai::shutdown_signal().context("installing the SIGINT/SIGTERM handlers")?;
    let mut stdout = std::io::stdout();
    writeln!(stdout, "{}", server.url()).context("writing the URL to stdout")?;
    stdout.flush().context("flushing stdout")?;
    stop.await;
    tracing::info!("stopping");
    server.shutdown().await;
    Ok(())
}
