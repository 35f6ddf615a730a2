//! The fake CARLA server: listens where CARLA would, holds client connections, records what
//! a client asks it to ([`crate::recorder`]), prints CARLA-like lines, exits 0 on
//! SIGTERM/SIGINT and crashes on request.

use std::net::{Ipv4Addr, TcpListener as StdListener};
use std::time::Duration;

use tokio::io::{AsyncBufReadExt as _, AsyncReadExt as _, AsyncWriteExt as _, BufReader};
use tokio::net::{TcpListener, TcpStream};

use crate::args::CarlaConfig;
use crate::faults::{crash, CarlaFaults, CrashSignal, OnceDir};
use crate::recorder::{Recorder, MAX_LINE, RECORDER_DONE};
use crate::signals::Signals;

/// How often `FAKE_CARLA_CRASH_FILE` is looked for.
const CRASH_FILE_POLL: Duration = Duration::from_millis(100);

/// The ports actually listened on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Ports {
    /// The RPC port clients connect to.
    pub rpc: u16,
    /// The streaming port (sensor data in the real server).
    pub streaming: u16,
}

/// The line `fake-carla` prints once both ports listen; tests and scripts wait for it.
pub fn ready_line(ports: Ports) -> String {
    format!(
        "fake-carla: listening rpc_port={} streaming_port={}",
        ports.rpc, ports.streaming
    )
}

/// Reads the ports back from [`ready_line`]'s text.
pub fn parse_ready_line(line: &str) -> Option<Ports> {
    let rest = line
        .trim()
        .strip_prefix("fake-carla: listening rpc_port=")?;
    let (rpc, streaming) = rest.split_once(" streaming_port=")?;
    Some(Ports {
        rpc: rpc.parse().ok()?,
        streaming: streaming.parse().ok()?,
    })
}

fn say(line: &str) {
    use std::io::Write as _;
    // NB: a closed stdout (the reader went away) must not kill the server.
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{line}");
    let _ = out.flush();
}

/// Runs the server until a stop signal (returns 0) or a failure mode ends it (returns the
/// exit code, or does not return at all for a crash).
pub async fn run(cfg: CarlaConfig) -> u8 {
    say("4.26.2-0+++UE4+Release-4.26 522 0");
    say("Disabling core dumps.");
    for arg in &cfg.ignored {
        say(&format!(
            "LogInit: Warning: fake-carla ignores the unknown argument `{arg}`"
        ));
    }
    let faults = &cfg.faults;
    let once = OnceDir::of_pair(
        faults.once_dir.clone(),
        "fake-carla",
        faults.once_owner.as_deref(),
        cfg.rpc_port,
    );
    let mut signals = match Signals::new() {
        Ok(s) => s,
        Err(error) => {
            say(&format!("fake-carla: cannot handle signals: {error}"));
            return 1;
        }
    };

    if faults.fail_start && once.armed("fail-start") {
        once.mark("fail-start");
        tracing::warn!(fault = "fail-start", "injected start failure");
        say("LowLevelFatalError [File:Unknown] [Line: 1214]");
        say("VulkanRHI: failed to create the Vulkan device (fake-carla: FAKE_CARLA_FAIL_START)");
        return 1;
    }
    if faults.start_delay > 0.0 {
        tokio::select! {
            () = tokio::time::sleep(Duration::from_secs_f64(faults.start_delay)) => {}
            stop = signals.recv() => {
                say(&format!("fake-carla: {} before listening, exiting", stop.name()));
                return 0;
            }
        }
    }

    let (rpc, streaming, ports) = match bind(cfg.rpc_port, cfg.streaming_port) {
        Ok(bound) => bound,
        Err(error) => {
            say(&format!("fake-carla: error: {error}"));
            return 1;
        }
    };
    let recorder = Recorder::new(cfg.map.as_deref());
    tokio::spawn(serve(rpc, "rpc", Some(recorder)));
    tokio::spawn(serve(streaming, "streaming", None));
    say(&format!(
        "fake-carla: CARLA server stand-in, map {}, flags [{}]",
        cfg.map.as_deref().unwrap_or("(default)"),
        cfg.accepted.join(" ")
    ));
    say(&ready_line(ports));

    until_stopped(faults, &once, &mut signals).await
}

/// Runs until a signal stops it (exit 0), or dies as the crash faults say.
async fn until_stopped(faults: &CarlaFaults, once: &OnceDir, signals: &mut Signals) -> u8 {
    let crash_after = faults
        .crash_after
        .filter(|_| once.armed("crash-after"))
        .map(Duration::from_secs_f64);
    let crash_file = faults
        .crash_file
        .clone()
        .filter(|_| once.armed("crash-file"));
    let timer = async {
        match crash_after {
            Some(d) => tokio::time::sleep(d).await,
            None => std::future::pending().await,
        }
    };
    tokio::pin!(timer);
    let mut poll = tokio::time::interval(CRASH_FILE_POLL);
    loop {
        tokio::select! {
            stop = signals.recv() => {
                say(&format!("fake-carla: {} received, shutting down", stop.name()));
                return 0;
            }
            () = &mut timer => die(once, "crash-after", faults.crash_signal),
            _ = poll.tick(), if crash_file.is_some() => {
                if crash_file.as_ref().is_some_and(|f| f.exists()) {
                    die(once, "crash-file", faults.crash_signal);
                }
            }
        }
    }
}

fn die(once: &OnceDir, fault: &str, kind: CrashSignal) -> ! {
    once.mark(fault);
    tracing::warn!(fault, ?kind, "injected crash");
    let n = kind.number();
    say(&format!("Signal {n} caught."));
    say("Malloc Size=65538 LargeMemoryPoolOffset=65554 ");
    say(&format!("CommonUnixCrashHandler: Signal={n}"));
    say("Malloc Size=65535 LargeMemoryPoolOffset=131119 ");
    say(&format!(
        "Engine crash handling finished; re-raising signal {n} for the default handler. Good bye."
    ));
    crash(kind)
}

/// Binds both ports on all interfaces, as CARLA does. Port 0 picks a free RPC port whose
/// successor is free too.
fn bind(rpc: u16, streaming: Option<u16>) -> Result<(TcpListener, TcpListener, Ports), String> {
    let listen = |port: u16| -> std::io::Result<StdListener> {
        let l = StdListener::bind((Ipv4Addr::UNSPECIFIED, port))?;
        l.set_nonblocking(true)?;
        Ok(l)
    };
    let attempts = if rpc == 0 { 50 } else { 1 };
    let mut last_error = String::new();
    for _ in 0..attempts {
        let rpc_listener =
            listen(rpc).map_err(|e| format!("cannot listen on the RPC port {rpc}: {e}"))?;
        let rpc_port = rpc_listener
            .local_addr()
            .map_err(|e| format!("cannot read the RPC port: {e}"))?
            .port();
        let Some(streaming_port) = streaming.or_else(|| rpc_port.checked_add(1)) else {
            last_error = format!("no streaming port after the RPC port {rpc_port}");
            continue;
        };
        match listen(streaming_port) {
            Ok(streaming_listener) => {
                let to_tokio = |l: StdListener| {
                    TcpListener::from_std(l).map_err(|e| format!("cannot listen: {e}"))
                };
                return Ok((
                    to_tokio(rpc_listener)?,
                    to_tokio(streaming_listener)?,
                    Ports {
                        rpc: rpc_port,
                        streaming: streaming_port,
                    },
                ));
            }
            // NB: with a picked port, its successor may be taken; try another pair.
            Err(e) => {
                last_error = format!("cannot listen on the streaming port {streaming_port}: {e}")
            }
        }
    }
    Err(last_error)
}

/// Accepts clients forever; each connection is held until the client closes it, and on the
/// RPC port its recorder commands are done.
async fn serve(listener: TcpListener, which: &'static str, recorder: Option<Recorder>) {
    loop {
        match listener.accept().await {
            Ok((stream, peer)) => {
                tracing::debug!(port = which, %peer, "client connected");
                match recorder.clone() {
                    Some(recorder) => tokio::spawn(commands(stream, recorder)),
                    None => tokio::spawn(hold(stream)),
                };
            }
            Err(error) => {
                // NB: e.g. out of file descriptors; back off instead of spinning.
                tracing::warn!(port = which, %error, "accept failed");
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    }
}

/// Reads a client's command lines, at most [`MAX_LINE`] bytes each (a longer one ends the
/// connection, as a real server drops a client that sends garbage).
async fn commands(stream: TcpStream, recorder: Recorder) {
    let mut reader = BufReader::new(stream);
    let mut line = Vec::new();
    loop {
        let buf = match reader.fill_buf().await {
            Ok(buf) if !buf.is_empty() => buf,
            _ => return,
        };
        let end = buf.iter().position(|&b| b == b'\n');
        let chunk = &buf[..end.map_or(buf.len(), |i| i + 1)];
        line.extend_from_slice(chunk);
        let used = chunk.len();
        reader.consume(used);
        if line.len() > MAX_LINE {
            return;
        }
        if end.is_some() {
            recorder.command(&String::from_utf8_lossy(&line));
            line.clear();
            // NB: an RPC call returns once the server did it; the client waits for this.
            if reader.get_mut().write_all(RECORDER_DONE).await.is_err() {
                return;
            }
        }
    }
}

async fn hold(mut stream: TcpStream) {
    let mut buf = [0u8; 4096];
    while let Ok(n) = stream.read(&mut buf).await {
        if n == 0 {
            return;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_ready_line_round_trips() {
        let ports = Ports {
            rpc: 2000,
            streaming: 2001,
        };
        assert_eq!(parse_ready_line(&ready_line(ports)), Some(ports));
        assert_eq!(parse_ready_line("4.26.2-0+++UE4+Release-4.26 522 0"), None);
    }
}
