//! Running the real binaries from tests: bounded waits, live stdout lines, cleanup on drop.
#![allow(dead_code)]

use std::io::{BufRead as _, BufReader, Read as _};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError};
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, Instant};

use lb_domain::results::{self, Leaderboard, ResultsFile, WorkerFile};

pub const CARLA: &str = env!("CARGO_BIN_EXE_fake-carla");
pub const EVALUATOR: &str = env!("CARGO_BIN_EXE_fake-evaluator");

/// The longest any single step of a test may take.
pub const STEP: Duration = Duration::from_secs(20);

/// A child process whose stdout arrives line by line; killed (SIGKILL) when dropped.
pub struct Proc {
    pub child: Child,
    lines: Receiver<String>,
    pub seen: Vec<String>,
    stderr: Arc<Mutex<String>>,
    stderr_reader: Option<thread::JoinHandle<()>>,
}

impl Proc {
    pub fn spawn(mut cmd: Command) -> Proc {
        cmd.stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        let mut child = cmd.spawn().expect("spawn");
        let (tx, lines) = mpsc::channel();
        let stdout = child.stdout.take().expect("stdout");
        thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let stderr = Arc::new(Mutex::new(String::new()));
        let sink = stderr.clone();
        let mut err = child.stderr.take().expect("stderr");
        let stderr_reader = thread::spawn(move || {
            let mut buf = [0u8; 4096];
            while let Ok(n) = err.read(&mut buf) {
                if n == 0 {
                    break;
                }
                sink.lock()
                    .unwrap()
                    .push_str(&String::from_utf8_lossy(&buf[..n]));
            }
        });
        Proc {
            child,
            lines,
            seen: Vec::new(),
            stderr,
            stderr_reader: Some(stderr_reader),
        }
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Waits (bounded) for a stdout line matching `pred` and returns it.
    pub fn wait_line(&mut self, what: &str, pred: impl Fn(&str) -> bool) -> String {
        let deadline = Instant::now() + STEP;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(line) => {
                    self.seen.push(line.clone());
                    if pred(&line) {
                        return line;
                    }
                }
                Err(RecvTimeoutError::Timeout) => panic!(
                    "no line {what} within {STEP:?}; stdout so far:\n{}\nstderr:\n{}",
                    self.seen.join("\n"),
                    self.stderr()
                ),
                Err(RecvTimeoutError::Disconnected) => panic!(
                    "stdout closed before a line {what}; stdout:\n{}\nstderr:\n{}",
                    self.seen.join("\n"),
                    self.stderr()
                ),
            }
        }
    }

    /// Lines that arrive within `quiet`; none expected when the process is silent.
    pub fn lines_within(&mut self, quiet: Duration) -> Vec<String> {
        let deadline = Instant::now() + quiet;
        let mut got = Vec::new();
        while let Ok(line) = self
            .lines
            .recv_timeout(deadline.saturating_duration_since(Instant::now()))
        {
            self.seen.push(line.clone());
            got.push(line);
        }
        got
    }

    pub fn stderr(&self) -> String {
        self.stderr.lock().unwrap().clone()
    }

    /// All stdout, after the process ended.
    pub fn stdout(&mut self) -> String {
        while let Ok(line) = self.lines.recv_timeout(Duration::from_millis(200)) {
            self.seen.push(line);
        }
        self.seen.join("\n")
    }

    pub fn signal(&self, sig: &str) {
        let ok = Command::new("kill")
            .arg(format!("-{sig}"))
            .arg(self.pid().to_string())
            .status()
            .expect("kill")
            .success();
        assert!(ok, "kill -{sig} failed");
    }

    /// Waits (bounded) for the exit, then for stderr to be read to its end; kills and
    /// panics on timeout.
    pub fn wait(&mut self) -> ExitStatus {
        let status = wait_child(&mut self.child, STEP);
        if let Some(reader) = self.stderr_reader.take() {
            // NB: bounded, as a grandchild may hold the pipe open.
            let deadline = Instant::now() + Duration::from_secs(2);
            while !reader.is_finished() && Instant::now() < deadline {
                thread::sleep(Duration::from_millis(5));
            }
            if reader.is_finished() {
                let _ = reader.join();
            }
        }
        status
    }

    pub fn is_running(&mut self) -> bool {
        self.child.try_wait().expect("try_wait").is_none()
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub fn wait_child(child: &mut Child, limit: Duration) -> ExitStatus {
    let deadline = Instant::now() + limit;
    loop {
        if let Some(status) = child.try_wait().expect("try_wait") {
            return status;
        }
        if Instant::now() >= deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("process {} did not exit within {limit:?}", child.id());
        }
        thread::sleep(Duration::from_millis(10));
    }
}

/// A command with a clean environment (only PATH kept), run in `dir`.
pub fn command(program: &str, dir: &Path, env: &[(&str, &str)]) -> Command {
    let mut cmd = Command::new(program);
    cmd.env_clear()
        .env("PATH", std::env::var_os("PATH").unwrap_or_default())
        .env("RUST_LOG", "info")
        .envs(env.iter().copied())
        .current_dir(dir);
    cmd
}

/// A running fake CARLA on a free port.
pub struct Carla {
    pub proc: Proc,
    pub port: u16,
    pub streaming: u16,
}

pub fn start_carla(dir: &Path, args: &[&str], env: &[(&str, &str)]) -> Carla {
    let mut cmd = command(CARLA, dir, env);
    cmd.arg("-carla-rpc-port=0").args(args);
    let mut proc = Proc::spawn(cmd);
    let line = proc.wait_line("saying it listens", |l| {
        fake_workloads::carla::parse_ready_line(l).is_some()
    });
    let ports = fake_workloads::carla::parse_ready_line(&line).expect("ready line");
    Carla {
        proc,
        port: ports.rpc,
        streaming: ports.streaming,
    }
}

/// A port nothing listens on (bound then released).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .expect("bind")
        .local_addr()
        .expect("addr")
        .port()
}

/// The evaluator command line the cloud's Job template runs (2.0), through a python shim.
pub fn evaluator_args(dir: &Path, port: u16, subset: &str, reps: u32, resume: bool) -> Vec<String> {
    vec![
        "-u".into(),
        "/workspace/leaderboard/leaderboard/leaderboard_evaluator.py".into(),
        format!("--port={port}"),
        format!("--traffic-manager-port={}", port.wrapping_add(10)),
        "--agent=/workspace/team_code/agent.py".into(),
        "--agent-config=/workspace/team_code/config.yml".into(),
        "--track=SENSORS".into(),
        "--routes=/workspace/leaderboard/data/routes_testing.xml".into(),
        format!("--routes-subset={subset}"),
        format!("--repetitions={reps}"),
        format!("--resume={}", if resume { "1" } else { "" }),
        format!("--checkpoint={}", dir.join("results.json").display()),
        format!("--record={}", dir.join("recorder").display()),
        format!(
            "--debug-checkpoint={}",
            dir.join("live_results.txt").display()
        ),
        "--debug=0".into(),
    ]
}

pub fn evaluator(dir: &Path, args: &[String], env: &[(&str, &str)]) -> Proc {
    let mut env = env.to_vec();
    if !env
        .iter()
        .any(|(k, _)| *k == "FAKE_EVALUATOR_ROUTE_SECONDS")
    {
        env.push(("FAKE_EVALUATOR_ROUTE_SECONDS", "0.01"));
    }
    let mut cmd = command(EVALUATOR, dir, &env);
    cmd.args(args);
    Proc::spawn(cmd)
}

/// Runs an evaluator to its end; returns (exit status, stdout, stderr).
pub fn run_evaluator(
    dir: &Path,
    args: &[String],
    env: &[(&str, &str)],
) -> (ExitStatus, String, String) {
    let mut p = evaluator(dir, args, env);
    let status = p.wait();
    let out = p.stdout();
    (status, out, p.stderr())
}

pub fn fixtures() -> PathBuf {
    lb_domain::testutil::results_fixtures_dir()
}

pub fn fixture_text(path: &str) -> String {
    std::fs::read_to_string(fixtures().join(path)).expect("fixture")
}

/// Reads a checkpoint through the domain reader; panics unless it is a present, valid file.
pub fn read_checkpoint(path: &Path, lb: Leaderboard, subset: Option<&str>) -> ResultsFile {
    let bytes = std::fs::read(path).expect("checkpoint exists");
    let subset = subset.map(|s| s.parse().expect("subset"));
    match results::read_worker_file(&path.display().to_string(), Some(&bytes), lb, subset)
        .expect("valid results file")
    {
        WorkerFile::Present(f) => f,
        WorkerFile::Empty(why) => panic!("checkpoint is empty: {why}"),
    }
}

pub fn json(path: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).expect("file")).expect("json")
}

/// The shape of a JSON document: keys and value types; lists of scalars (and empty lists)
/// are just "list", lists of objects show their first element's shape.
pub fn shape(v: &serde_json::Value) -> serde_json::Value {
    use serde_json::Value;
    match v {
        Value::Object(m) => Value::Object(m.iter().map(|(k, v)| (k.clone(), shape(v))).collect()),
        Value::Array(items) => match items.first() {
            Some(first @ Value::Object(_)) => Value::Array(vec![shape(first)]),
            _ => Value::String("list".into()),
        },
        Value::Number(_) => Value::String("number".into()),
        Value::String(_) => Value::String("string".into()),
        Value::Bool(_) => Value::String("bool".into()),
        Value::Null => Value::Null,
    }
}

/// Files in `dir` whose name marks an unfinished write.
pub fn temp_files(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .expect("dir")
        .filter_map(|e| e.ok()?.file_name().into_string().ok())
        .filter(|n| n.contains(".tmp-"))
        .collect()
}
