//! SIGTERM and SIGINT as awaitable events, so the fakes stop between writes, never inside one.

/// Why a fake was asked to stop.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stop {
    /// SIGTERM (Kubernetes stopping the container).
    Terminate,
    /// SIGINT (Ctrl-C).
    Interrupt,
}

impl Stop {
    /// The signal number.
    pub fn number(self) -> u8 {
        match self {
            Stop::Terminate => 15,
            Stop::Interrupt => 2,
        }
    }

    /// The exit code a shell reports for a process the signal killed (128 + signal).
    pub fn exit_code(self) -> u8 {
        128 + self.number()
    }

    /// The signal's name.
    pub fn name(self) -> &'static str {
        match self {
            Stop::Terminate => "SIGTERM",
            Stop::Interrupt => "SIGINT",
        }
    }
}

/// The stop signals of this process. Creating it replaces their default action (death), so
/// the fakes decide when to stop.
#[derive(Debug)]
pub struct Signals {
    term: tokio::signal::unix::Signal,
    int: tokio::signal::unix::Signal,
}

impl Signals {
    /// Starts listening; needs a Tokio runtime.
    pub fn new() -> std::io::Result<Signals> {
        use tokio::signal::unix::{signal, SignalKind};
        Ok(Signals {
            term: signal(SignalKind::terminate())?,
            int: signal(SignalKind::interrupt())?,
        })
    }

    /// Waits for the next stop signal.
    pub async fn recv(&mut self) -> Stop {
        tokio::select! {
            Some(()) = self.term.recv() => Stop::Terminate,
            Some(()) = self.int.recv() => Stop::Interrupt,
            else => std::future::pending().await,
        }
    }
}
