//! SIGTERM/SIGINT (the kubelet stopping the container) and SIGCHLD, as interruptible sleeps.

use std::io;
use std::time::Duration;

use tokio::signal::unix::{signal, Signal, SignalKind};

/// Why a [`Signals::sleep`] returned.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Wake {
    /// The time passed.
    Timer,
    /// A child changed state: look at it now rather than at the next tick.
    Child,
    /// SIGTERM or SIGINT: the container is being stopped.
    Terminate,
}

/// The signals a subcommand reacts to; create it first thing, before any child exists.
#[derive(Debug)]
pub struct Signals {
    term: Signal,
    int: Signal,
    child: Signal,
    terminated: bool,
}

impl Signals {
    /// Installs the handlers (needs a Tokio runtime).
    pub fn install() -> io::Result<Signals> {
        Ok(Signals {
            term: signal(SignalKind::terminate())?,
            int: signal(SignalKind::interrupt())?,
            child: signal(SignalKind::child())?,
            terminated: false,
        })
    }

    /// Whether SIGTERM or SIGINT has arrived (sticky).
    pub fn terminated(&self) -> bool {
        self.terminated
    }

    /// Sleeps for `d`, or less when a signal arrives. Once terminated, returns at once.
    pub async fn sleep(&mut self, d: Duration) -> Wake {
        if self.terminated {
            return Wake::Terminate;
        }
        tokio::select! {
            _ = tokio::time::sleep(d) => Wake::Timer,
            _ = self.term.recv() => { self.terminated = true; Wake::Terminate }
            _ = self.int.recv() => { self.terminated = true; Wake::Terminate }
            _ = self.child.recv() => Wake::Child,
        }
    }

    /// Waits for SIGTERM or SIGINT only (for tasks that run beside other work).
    pub async fn terminate(&mut self) {
        if self.terminated {
            return;
        }
        tokio::select! {
            _ = self.term.recv() => {}
            _ = self.int.recv() => {}
        }
        self.terminated = true;
    }
}
