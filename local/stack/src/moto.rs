//! A `moto_server` on loopback with a free port, started from the project venv, stopped on drop.
//!
//! The AWS SDK reaches it through `AWS_ENDPOINT_URL` and dummy credentials (see
//! [`MotoServer::sdk_env`]); nothing else about AWS is faked in this project.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// How long moto may take to answer after start (its first import is slow on a cold disk).
pub const START_TIMEOUT: Duration = Duration::from_secs(30);

/// Why moto could not be started.
#[derive(Debug, thiserror::Error)]
pub enum MotoError {
    /// No `moto_server` executable where we looked.
    #[error("`moto_server` not found (looked at {}): run `make venv` in the project, put `moto_server` on PATH, or set LB_MOTO_SERVER", looked(.0))]
    NotInstalled(Vec<PathBuf>),
    /// The process could not be spawned or the port not reserved.
    #[error("cannot start `moto_server`: {0}")]
    Spawn(#[source] std::io::Error),
    /// The process exited before it answered.
    #[error("`moto_server` exited during start-up with {0}")]
    Exited(std::process::ExitStatus),
    /// It did not answer within [`START_TIMEOUT`].
    #[error("`moto_server` did not answer on {addr} within {timeout:?}")]
    Timeout {
        /// Where it should listen.
        addr: SocketAddr,
        /// How long we waited.
        timeout: Duration,
    },
}

/// A running moto server; killed when dropped.
#[derive(Debug)]
pub struct MotoServer {
    child: Child,
    addr: SocketAddr,
}

/// `moto_server` with DynamoDB's per-request atomicity (`python/moto_atomic.py` says why).
const ATOMIC_SHIM: &str = include_str!("../python/moto_atomic.py");

/// The interpreter a console script's `#!` line names (pip writes the venv's Python there).
fn interpreter(script: &Path) -> Option<PathBuf> {
    use std::io::BufRead;
    let mut first = String::new();
    std::io::BufReader::new(std::fs::File::open(script).ok()?)
        .take(4096)
        .read_line(&mut first)
        .ok()?;
    let line = first.strip_prefix("#!")?.trim();
    // A single path: `#!/usr/bin/env python3` and the like are left to the script itself.
    let python = PathBuf::from(line.split_whitespace().next()?);
    (python.is_absolute() && python.is_file() && !line.contains(' ')).then_some(python)
}

/// The variables that say where `moto_server` is.
#[derive(Debug, Clone, Default)]
pub struct Lookup {
    /// `LB_MOTO_SERVER`: this path and no other.
    pub override_path: Option<PathBuf>,
    /// `PATH`.
    pub path: Option<std::ffi::OsString>,
}

impl Lookup {
    /// This process's `LB_MOTO_SERVER` and `PATH`.
    pub fn from_env() -> Self {
        Self {
            override_path: std::env::var_os("LB_MOTO_SERVER").map(PathBuf::from),
            path: std::env::var_os("PATH"),
        }
    }
}

impl MotoServer {
    /// Where `moto_server` may be, in the order looked at: `$LB_MOTO_SERVER` alone when set;
    /// else beside this program, in the `.venv` of the current directory or any parent (a
    /// checkout of the project), in the `.venv` of the checkout this was built from, then
    /// every `PATH` entry.
    pub fn candidates() -> Vec<PathBuf> {
        Self::candidates_in(&Lookup::from_env())
    }

    /// [`candidates`](Self::candidates) for the given variables (the process's own are shared
    /// by every test of a binary, so tests pass theirs).
    pub fn candidates_in(lookup: &Lookup) -> Vec<PathBuf> {
        if let Some(path) = &lookup.override_path {
            return vec![path.clone()];
        }
        let mut out = Vec::new();
        if let Some(dir) = std::env::current_exe()
            .ok()
            .and_then(|e| e.parent().map(Path::to_owned))
        {
            out.push(dir.join("moto_server"));
        }
        if let Ok(cwd) = std::env::current_dir() {
            out.extend(cwd.ancestors().map(|d| d.join(".venv/bin/moto_server")));
        }
        out.push(workspace_root().join(".venv/bin/moto_server"));
        if let Some(path) = &lookup.path {
            out.extend(std::env::split_paths(path).map(|d| d.join("moto_server")));
        }
        out.dedup();
        out
    }

    /// The first of [`candidates`](Self::candidates) that is a file.
    pub fn executable() -> Result<PathBuf, MotoError> {
        Self::executable_in(&Lookup::from_env())
    }

    /// The first of [`candidates_in`](Self::candidates_in) that is a file.
    pub fn executable_in(lookup: &Lookup) -> Result<PathBuf, MotoError> {
        let candidates = Self::candidates_in(lookup);
        candidates
            .iter()
            .find(|p| p.is_file())
            .cloned()
            .ok_or(MotoError::NotInstalled(candidates))
    }

    /// Starts moto on `127.0.0.1` with a free port and waits until it answers.
    pub fn start() -> Result<MotoServer, MotoError> {
        let exe = Self::executable()?;
        // NB: one start at a time in this process, until the server answers: a port found
        // free is only reserved once moto binds it, and two stacks starting side by side (the
        // tests of one binary run in parallel) could otherwise pick the same one, the loser's
        // wait then finding the winner's server and both tests sharing one moto.
        static STARTING: std::sync::Mutex<()> = std::sync::Mutex::new(());
        let _one = STARTING
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let port = free_port().map_err(MotoError::Spawn)?;
        let addr = SocketAddr::from(([127, 0, 0, 1], port));
        let mut command = match interpreter(&exe) {
            Some(python) => {
                let mut c = Command::new(python);
                c.args(["-c", ATOMIC_SHIM]);
                c
            }
            None => {
                tracing::warn!(exe = %exe.display(), "no Python interpreter named in its first line: moto's DynamoDB without per-request atomicity");
                Command::new(&exe)
            }
        };
        let child = command
            .args(["-H", "127.0.0.1", "-p", &port.to_string()])
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .map_err(MotoError::Spawn)?;
        let mut server = MotoServer { child, addr };
        server.wait_ready(START_TIMEOUT)?;
        tracing::debug!(%addr, "moto server ready");
        Ok(server)
    }

    /// The endpoint URL to give the SDK (`AWS_ENDPOINT_URL`).
    pub fn endpoint(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// The socket address.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Environment for a process that should use this server through the AWS SDK.
    pub fn sdk_env(&self) -> Vec<(&'static str, String)> {
        vec![
            ("AWS_ENDPOINT_URL", self.endpoint()),
            ("AWS_ACCESS_KEY_ID", "testing".to_owned()),
            ("AWS_SECRET_ACCESS_KEY", "testing".to_owned()),
            ("AWS_REGION", "us-east-1".to_owned()),
        ]
    }

    /// Empties every service's state (moto's `/moto-api/reset`).
    pub fn reset(&self) -> std::io::Result<()> {
        let (status, _) = http(self.addr, "POST", "/moto-api/reset")?;
        if status == 200 {
            Ok(())
        } else {
            Err(std::io::Error::other(format!(
                "moto reset answered {status}"
            )))
        }
    }

    fn wait_ready(&mut self, timeout: Duration) -> Result<(), MotoError> {
        let deadline = Instant::now() + timeout;
        let mut delay = Duration::from_millis(20);
        loop {
            if let Some(status) = self.child.try_wait().map_err(MotoError::Spawn)? {
                return Err(MotoError::Exited(status));
            }
            if matches!(http(self.addr, "GET", "/moto-api/data.json"), Ok((200, _))) {
                return Ok(());
            }
            if Instant::now() >= deadline {
                return Err(MotoError::Timeout {
                    addr: self.addr,
                    timeout,
                });
            }
            std::thread::sleep(delay);
            delay = (delay * 2).min(Duration::from_millis(200));
        }
    }
}

impl Drop for MotoServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A port nobody listens on right now. NB: another process may take it before moto binds
/// it; moto then exits and [`MotoServer::start`] reports it rather than hanging.
fn free_port() -> std::io::Result<u16> {
    Ok(TcpListener::bind(("127.0.0.1", 0))?.local_addr()?.port())
}

/// A minimal HTTP/1.1 exchange, enough to probe a local server without an HTTP stack.
pub fn http(addr: SocketAddr, method: &str, path: &str) -> std::io::Result<(u16, String)> {
    let mut stream = TcpStream::connect_timeout(&addr, Duration::from_millis(500))?;
    stream.set_read_timeout(Some(Duration::from_secs(5)))?;
    write!(
        stream,
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
    )?;
    let mut response = String::new();
    stream
        .take(16 * 1024 * 1024)
        .read_to_string(&mut response)?;
    let status = response
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .ok_or_else(|| std::io::Error::other("malformed HTTP response"))?;
    let body = response
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_owned())
        .unwrap_or_default();
    Ok((status, body))
}

/// The places looked at, for an error message.
fn looked(places: &[PathBuf]) -> String {
    places
        .iter()
        .map(|p| format!("`{}`", p.display()))
        .collect::<Vec<_>>()
        .join(", ")
}

fn workspace_root() -> PathBuf {
    // local/stack -> workspace root
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

#[cfg(test)]
mod interpreter_tests {
    use super::interpreter;

    #[test]
    fn the_interpreter_is_the_absolute_path_a_console_script_names() {
        let dir = tempfile::tempdir().unwrap();
        let script = dir.path().join("moto_server");
        let python = std::env::current_exe().unwrap();
        std::fs::write(&script, format!("#!{}\nimport sys\n", python.display())).unwrap();
        assert_eq!(interpreter(&script), Some(python));
        for first in [
            "#!/usr/bin/env python3\n",
            "import sys\n",
            "#!relative/python\n",
            "",
        ] {
            std::fs::write(&script, first).unwrap();
            assert_eq!(interpreter(&script), None, "{first:?}");
        }
        assert_eq!(interpreter(&dir.path().join("absent")), None);
    }
}
