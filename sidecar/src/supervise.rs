//! A wrapped child: its own process group, output copied to a log file, reaped, and stopped
//! with every process it left behind.
//!
//! Participant code may fork children that outlive the evaluator, change their process group
//! or call `setsid`. The sidecar makes itself a child subreaper, so such orphans are
//! re-parented to it instead of to the container's init, and when the child is stopped the
//! sidecar signals the whole group and then every remaining descendant it can see in `/proc`.
//! Nothing the child started survives the sidecar.

use std::fs::{self, File, OpenOptions};
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

use lb_proc::descendants;
use nix::errno::Errno;
use nix::sys::signal::{kill, killpg, Signal};
use nix::sys::wait::{waitpid, WaitPidFlag, WaitStatus};
use nix::unistd::Pid;
use tracing::{debug, info, warn};

/// How the child ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ChildExit {
    /// It exited with this code.
    Code(i32),
    /// A signal killed it.
    Signal(i32),
}

impl std::fmt::Display for ChildExit {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ChildExit::Code(c) => write!(f, "exit code {c}"),
            ChildExit::Signal(s) => write!(f, "signal {s}"),
        }
    }
}

/// Makes this process a child subreaper (orphans of its descendants become its children).
pub fn become_subreaper() {
    if let Err(e) = nix::sys::prctl::set_child_subreaper(true) {
        warn!(error = %e, "cannot become a child subreaper; orphans may escape");
    }
}

/// A running child in its own process group.
#[derive(Debug)]
pub struct Supervised {
    pid: Pid,
    exit: Option<ChildExit>,
    log: Arc<File>,
    log_path: PathBuf,
    started: Instant,
    last_output_ms: Arc<AtomicU64>,
    pumps: mpsc::Receiver<()>,
    pumps_running: usize,
}

impl Supervised {
    /// Starts `argv` with extra environment; its stdout and stderr are appended to `log_path`
    /// (and echoed to ours when `echo` is set).
    pub fn spawn(
        argv: &[String],
        envs: &[(&str, String)],
        log_path: &Path,
        echo: bool,
    ) -> io::Result<Supervised> {
        let (program, args) = argv
            .split_first()
            .ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, "no command given"))?;
        let log = Arc::new(open_log(log_path)?);
        let mut command = Command::new(program);
        command
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        for (k, v) in envs {
            command.env(k, v);
        }
        std::os::unix::process::CommandExt::process_group(&mut command, 0);
        let mut child = command.spawn()?;
        let pid = Pid::from_raw(i32::try_from(child.id()).map_err(io::Error::other)?);
        let started = Instant::now();
        let last_output_ms = Arc::new(AtomicU64::new(0));
        let (done_tx, pumps) = mpsc::channel();
        let mut pumps_running = 0;
        let readers: [Option<Box<dyn Read + Send>>; 2] = [
            child
                .stdout
                .take()
                .map(|r| Box::new(r) as Box<dyn Read + Send>),
            child
                .stderr
                .take()
                .map(|r| Box::new(r) as Box<dyn Read + Send>),
        ];
        for reader in readers.into_iter().flatten() {
            let pump = Pump {
                log: Arc::clone(&log),
                echo,
                started,
                last_output_ms: Arc::clone(&last_output_ms),
            };
            let done = done_tx.clone();
            std::thread::Builder::new()
                .name("lb-output".into())
                .spawn(move || {
                    pump.run(reader);
                    let _ = done.send(());
                })?;
            pumps_running += 1;
        }
        // NB: the std handle is dropped without waiting: we reap with waitpid(-1) ourselves,
        // which also reaps re-parented orphans.
        drop(child);
        info!(pid = pid.as_raw(), program = %program, log = %log_path.display(), "child started");
        Ok(Supervised {
            pid,
            exit: None,
            log,
            log_path: log_path.to_owned(),
            started,
            last_output_ms,
            pumps,
            pumps_running,
        })
    }

    /// The child's process id (and process group id).
    pub fn pid(&self) -> i32 {
        self.pid.as_raw()
    }

    /// Where its output goes.
    pub fn log_path(&self) -> &Path {
        &self.log_path
    }

    /// Reaps every exited child of ours; returns how the wrapped child ended once it has.
    pub fn try_exit(&mut self) -> Option<ChildExit> {
        self.reap();
        self.exit
    }

    /// How long since the child last wrote anything (since its start when it never did).
    pub fn idle_for(&self) -> Duration {
        let last = Duration::from_millis(self.last_output_ms.load(Ordering::Relaxed));
        self.started.elapsed().saturating_sub(last)
    }

    /// Appends a line of ours to the child's log, so the log tells what the sidecar did.
    pub fn note(&self, text: &str) {
        note(&self.log, text);
    }

    /// Stops the child's process group and every other descendant: SIGTERM, up to `grace`
    /// for them to go, then SIGKILL. Returns once nothing is left (bounded) and the output
    /// is flushed to the log.
    pub async fn stop(&mut self, grace: Duration) {
        self.reap();
        let running = self.exit.is_none();
        let leftovers = self.remaining();
        if running || !leftovers.is_empty() {
            info!(
                pid = self.pid.as_raw(),
                running,
                leftovers = leftovers.len(),
                "stopping the child's processes"
            );
            self.signal_all(Signal::SIGTERM);
            let deadline = Instant::now() + grace;
            while Instant::now() < deadline {
                tokio::time::sleep(Duration::from_millis(50)).await;
                self.reap();
                if self.exit.is_some() && self.remaining().is_empty() {
                    break;
                }
            }
            // NB: the loop is bounded: a fork bomb cannot outrun SIGKILL for ever, and we
            // give up after a few seconds rather than miss the kubelet's grace period.
            for _ in 0..100 {
                self.reap();
                if self.exit.is_some() && self.remaining().is_empty() {
                    break;
                }
                self.signal_all(Signal::SIGKILL);
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            if self.exit.is_none() || !self.remaining().is_empty() {
                warn!(pid = self.pid.as_raw(), "processes remain after SIGKILL");
            }
        }
        self.drain_output(Duration::from_secs(2)).await;
    }

    /// Waits (bounded) until the output pumps have copied everything.
    async fn drain_output(&mut self, limit: Duration) {
        let deadline = Instant::now() + limit;
        while self.pumps_running > 0 && Instant::now() < deadline {
            match self.pumps.try_recv() {
                Ok(()) => self.pumps_running -= 1,
                Err(mpsc::TryRecvError::Disconnected) => self.pumps_running = 0,
                Err(mpsc::TryRecvError::Empty) => {
                    tokio::time::sleep(Duration::from_millis(10)).await;
                }
            }
        }
    }

    fn signal_all(&self, signal: Signal) {
        match killpg(self.pid, signal) {
            Ok(()) | Err(Errno::ESRCH) => {}
            Err(e) => warn!(error = %e, ?signal, "cannot signal the child's process group"),
        }
        for pid in self.remaining() {
            match kill(pid, signal) {
                Ok(()) | Err(Errno::ESRCH) => {}
                Err(e) => debug!(pid = pid.as_raw(), error = %e, "cannot signal a descendant"),
            }
        }
    }

    /// Live descendants of this process (the group's members and any escaped ones).
    fn remaining(&self) -> Vec<Pid> {
        descendants(nix::unistd::getpid())
    }

    fn reap(&mut self) {
        loop {
            match waitpid(Pid::from_raw(-1), Some(WaitPidFlag::WNOHANG)) {
                Ok(WaitStatus::StillAlive) | Err(Errno::ECHILD) => return,
                Ok(status) => {
                    let exit = match status {
                        WaitStatus::Exited(pid, code) => Some((pid, ChildExit::Code(code))),
                        WaitStatus::Signaled(pid, sig, _) => {
                            Some((pid, ChildExit::Signal(sig as i32)))
                        }
                        _ => None,
                    };
                    if let Some((pid, exit)) = exit {
                        if pid == self.pid {
                            info!(pid = pid.as_raw(), %exit, "child exited");
                            self.exit = Some(exit);
                        } else {
                            debug!(pid = pid.as_raw(), %exit, "reaped a descendant");
                        }
                    }
                }
                Err(Errno::EINTR) => {}
                Err(e) => {
                    warn!(error = %e, "waitpid failed");
                    return;
                }
            }
        }
    }
}

impl Drop for Supervised {
    /// The last line of defence when a subcommand returns early (an error): nothing it
    /// started may outlive it.
    fn drop(&mut self) {
        self.reap();
        if self.exit.is_none() || !self.remaining().is_empty() {
            warn!(
                pid = self.pid.as_raw(),
                "killing the child's processes on the way out"
            );
            self.signal_all(Signal::SIGKILL);
        }
    }
}

/// Opens a child's log for appending, creating it and its directory.
pub fn open_log(path: &Path) -> io::Result<File> {
    if let Some(dir) = path.parent() {
        fs::create_dir_all(dir)?;
    }
    OpenOptions::new().create(true).append(true).open(path)
}

/// Appends `[lb-sidecar <time>] text` to a log.
pub fn note(log: &File, text: &str) {
    let now = time::OffsetDateTime::now_utc()
        .format(&time::format_description::well_known::Rfc3339)
        .unwrap_or_default();
    let mut f = log;
    if let Err(e) = f.write_all(format!("[lb-sidecar {now}] {text}\n").as_bytes()) {
        debug!(error = %e, "cannot write a note to the child's log");
    }
}

struct Pump {
    log: Arc<File>,
    echo: bool,
    started: Instant,
    last_output_ms: Arc<AtomicU64>,
}

impl Pump {
    /// Copies until end of file with one fixed buffer: memory stays bounded however much the
    /// child writes.
    fn run(self, mut from: Box<dyn Read + Send>) {
        let mut buf = vec![0u8; 16 * 1024];
        let mut log_failed = false;
        loop {
            let n = match from.read(&mut buf) {
                Ok(0) => return,
                Ok(n) => n,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                Err(e) => {
                    warn!(error = %e, "cannot read the child's output");
                    return;
                }
            };
            let elapsed = u64::try_from(self.started.elapsed().as_millis()).unwrap_or(u64::MAX);
            self.last_output_ms.store(elapsed, Ordering::Relaxed);
            // NB: keep draining even when the log cannot be written (disk full): a full pipe
            // would block the child and look like a hang.
            if let Err(e) = (&*self.log).write_all(&buf[..n]) {
                if !log_failed {
                    warn!(error = %e, "cannot write the child's log");
                    log_failed = true;
                }
            }
            if self.echo {
                let _ = io::stdout().lock().write_all(&buf[..n]);
            }
        }
    }
}

/// Whether TCP `port` is listened on in this network by processes outside the sidecar's tree
/// only: it answers, but not from the child (on a network pods share, another pod's CARLA).
/// `false` when `/proc` cannot tell.
pub fn listened_by_another(port: u16) -> bool {
    let inodes: Vec<u64> = ["/proc/net/tcp", "/proc/net/tcp6"]
        .iter()
        .filter_map(|table| fs::read_to_string(table).ok())
        .flat_map(|table| listening_inodes(&table, port))
        .collect();
    if inodes.is_empty() {
        return false;
    }
    let ours = descendants(nix::unistd::getpid())
        .into_iter()
        .any(|pid| holds_socket(pid, &inodes));
    !ours
}

/// The inodes of the sockets listening (state `0A`) on `port` in a `/proc/net/tcp` table.
fn listening_inodes(table: &str, port: u16) -> Vec<u64> {
    table
        .lines()
        .skip(1)
        .filter_map(|line| {
            let fields: Vec<&str> = line.split_whitespace().collect();
            let (_, local_port) = fields.get(1)?.rsplit_once(':')?;
            let listening = *fields.get(3)? == "0A";
            let on_port = u16::from_str_radix(local_port, 16).ok()? == port;
            let inode = fields.get(9)?.parse().ok()?;
            (listening && on_port).then_some(inode)
        })
        .collect()
}

/// Whether process `pid` has one of the sockets `inodes` open.
fn holds_socket(pid: Pid, inodes: &[u64]) -> bool {
    let Ok(fds) = fs::read_dir(format!("/proc/{pid}/fd")) else {
        return false;
    };
    fds.flatten().any(|fd| {
        let Ok(target) = fs::read_link(fd.path()) else {
            return false;
        };
        let inode = target
            .to_str()
            .and_then(|t| t.strip_prefix("socket:["))
            .and_then(|t| t.strip_suffix(']'))
            .and_then(|t| t.parse::<u64>().ok());
        inode.is_some_and(|i| inodes.contains(&i))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn listeners_are_read_from_the_kernels_table_by_port_and_state() {
        let table = "  sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode
   0: 00000000:07D0 00000000:0000 0A 00000000:00000000 00:00000000 00000000     0        0 4242 1 0000000000000000 100 0 0 10 0
   1: 0100007F:07D0 0100007F:A1B2 01 00000000:00000000 00:00000000 00000000     0        0 4343 1 0000000000000000 20 4 30 10 -1
   2: 00000000:0834 00000000:0000 0A 00000000:00000000 00:00000000 00000000     0        0 4444 1 0000000000000000 100 0 0 10 0
   garbage";
        assert_eq!(listening_inodes(table, 2000), [4242]);
        assert_eq!(listening_inodes(table, 2100), [4444]);
        assert!(listening_inodes(table, 2001).is_empty());
    }

    #[test]
    fn a_port_held_outside_the_sidecars_tree_is_anothers() {
        // NB: the sidecar asks about its descendants; the test process is not its own.
        let held = std::net::TcpListener::bind(("0.0.0.0", 0)).unwrap();
        let port = held.local_addr().unwrap().port();
        assert!(listened_by_another(port));
        drop(held);
        assert!(!listened_by_another(port), "nobody listens any more");
    }
}
