//! Shared test harness: a Job's volumes in a temp dir, the pair's environment, the fakes,
//! bounded waits, and (for moto tests) an S3 client and a proxy that can play an outage.
#![allow(dead_code)]

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

pub const SIDECAR: &str = env!("CARGO_BIN_EXE_lb-sidecar");
pub const SUBMISSION: &str = "4242";

/// `target/debug` (or the profile dir) of this test binary.
fn profile_dir() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    exe.parent().unwrap().parent().unwrap().to_owned()
}

/// A binary of `fake-workloads`, built once per test binary (cheap when up to date).
pub fn fake(name: &str) -> PathBuf {
    static BUILT: OnceLock<()> = OnceLock::new();
    BUILT.get_or_init(|| {
        local_stack::workloads::build_workspace_bins().expect("cannot build the fakes");
    });
    let path = profile_dir().join(name);
    assert!(path.is_file(), "{} missing", path.display());
    path
}

/// A loopback port free with what a pair takes beside it (CARLA N to N+2, the traffic
/// manager N+10: the simulator's sidecar moves the pair when any is taken), from blocks of
/// 20 in 20000-29999, below Linux's ephemeral range, so no outgoing connection of a parallel
/// test can grab one between this check and the binds.
pub fn free_port() -> u16 {
    static NEXT: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    let offset = std::process::id() % 500 * 20;
    for _ in 0..500 {
        let step = NEXT.fetch_add(20, std::sync::atomic::Ordering::SeqCst);
        let port = 20000 + ((offset + step) % 10000) as u16;
        let free = |p: u16| TcpListener::bind(("0.0.0.0", p)).is_ok();
        if [0, 1, 2, 10].iter().all(|d| free(port + d)) {
            return port;
        }
    }
    panic!("no free block of loopback ports in 20000-29999");
}

/// One Job's `logs` volume: `containers-status`, `agent`, `logs` under a temp root.
pub struct Volumes {
    pub dir: tempfile::TempDir,
}

impl Volumes {
    pub fn new() -> Volumes {
        let dir = tempfile::tempdir().unwrap();
        for sub in ["containers-status", "agent", "logs"] {
            std::fs::create_dir_all(dir.path().join(sub)).unwrap();
        }
        Volumes { dir }
    }
    pub fn root(&self) -> &Path {
        self.dir.path()
    }
    pub fn status(&self) -> PathBuf {
        self.root().join("containers-status")
    }
    pub fn marker(&self, name: &str) -> bool {
        self.status().join(name).exists()
    }
    pub fn markers(&self) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(self.status())
            .map(|d| {
                d.flatten()
                    .map(|e| e.file_name().to_string_lossy().into_owned())
                    .collect()
            })
            .unwrap_or_default();
        names.sort();
        names
    }
    pub fn checkpoint(&self, pair: u32) -> PathBuf {
        self.root()
            .join(format!("agent/partial_agent_results{pair}.json"))
    }
    pub fn agent_log(&self, pair: u32) -> String {
        std::fs::read_to_string(
            self.root()
                .join(format!("logs/agent/agent{pair}/agent.log")),
        )
        .unwrap_or_default()
    }
    pub fn simulator_log(&self, pair: u32) -> String {
        std::fs::read_to_string(
            self.root()
                .join(format!("logs/simulator/simulator{pair}.log")),
        )
        .unwrap_or_default()
    }
}

/// A pair's settings for a test run.
#[derive(Clone)]
pub struct Pair {
    pub id: u32,
    pub port: u16,
    pub subset: &'static str,
    pub env: Vec<(String, String)>,
}

impl Pair {
    pub fn new(id: u32, subset: &'static str) -> Pair {
        Pair {
            id,
            port: free_port(),
            subset,
            env: Vec::new(),
        }
    }
    pub fn with(mut self, k: &str, v: impl Into<String>) -> Pair {
        self.env.push((k.to_owned(), v.into()));
        self
    }

    /// Routes of 0.5 s and a CARLA that dies 1.2 s in, once (the marker goes to `once`): the
    /// first attempt crashes mid-run with a route or two done, the next one finishes.
    pub fn with_carla_crash(self, once: &Path) -> Pair {
        self.with("FAKE_EVALUATOR_ROUTE_SECONDS", "0.5")
            .with("FAKE_CARLA_CRASH_AFTER", "1.2")
            .with("FAKE_CARLA_ONCE_DIR", once.display().to_string())
    }

    fn command(&self, vols: &Volumes, args: &[String]) -> Command {
        let mut c = Command::new(SIDECAR);
        c.args(args)
            .env_clear()
            .env("PATH", std::env::var("PATH").unwrap_or_default())
            .env("RUST_LOG", "info")
            .env("LB_SUBMISSION_ID", SUBMISSION)
            .env("LB_JOB_INDEX", "0")
            .env("LB_LEADERBOARD", "2.0")
            .env("LB_STATUS_DIR", vols.status())
            .env("LB_AGENT_DIR", vols.root().join("agent"))
            .env("LB_HANDOFF_DIR", vols.root().join("handoff"))
            .env("LB_LOGS_DIR", vols.root().join("logs"))
            .env("LB_PAIR_ID", self.id.to_string())
            .env("CARLA_PORT", self.port.to_string())
            .env("CARLA_TM_PORT", (self.port + 10).to_string())
            .env("ROUTES_SUBSET", self.subset)
            .env("REPETITIONS", "1")
            .env("LB_POLL_SECONDS", "0.2")
            .env("LB_STOP_GRACE_SECONDS", "2")
            .env("LB_END_WAIT_SECONDS", "20")
            .env("LB_START_WAIT_SECONDS", "30")
            .env("LB_CARLA_READY_SECONDS", "20")
            .env("CHALLENGE_TRACK_CODENAME", "SENSORS")
            .env("ROUTES", "/workspace/leaderboard/data/routes_testing.xml")
            .env("TEAM_AGENT", "/workspace/team_code/agent.py")
            .env("TEAM_CONFIG", "/workspace/team_code/config.txt")
            .env("FAKE_EVALUATOR_ROUTE_SECONDS", "0.2")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped());
        for (k, v) in &self.env {
            c.env(k, v);
        }
        c
    }

    /// `lb-sidecar simulator -- fake-carla -carla-rpc-port=PORT ...` (the template's shape).
    pub fn simulator(&self, vols: &Volumes) -> Proc {
        let args = vec![
            "simulator".to_owned(),
            "--".to_owned(),
            fake("fake-carla").display().to_string(),
            "-vulkan".to_owned(),
            "-carla-rpc-port={carla_port}".to_owned(),
            "-RenderOffScreen".to_owned(),
            "-nosound".to_owned(),
        ];
        Proc::spawn(self.command(vols, &args), "simulator")
    }

    /// `lb-sidecar simulator -- COMMAND...`: a simulator container running something else.
    pub fn simulator_running(&self, vols: &Volumes, command: &[String]) -> Proc {
        let mut args = vec!["simulator".to_owned(), "--".to_owned()];
        args.extend(command.iter().cloned());
        Proc::spawn(self.command(vols, &args), "simulator")
    }

    /// `lb-sidecar agent -- COMMAND...`: an agent whose image runs something else.
    pub fn agent_running(&self, vols: &Volumes, command: &[&str]) -> Proc {
        let mut args = vec!["agent".to_owned(), "--".to_owned()];
        args.extend(command.iter().map(|a| (*a).to_owned()));
        Proc::spawn(self.command(vols, &args), "agent")
    }

    /// `lb-sidecar agent -- bash -c '<evaluator command>'` as the template writes it.
    pub fn agent(&self, vols: &Volumes) -> Proc {
        let evaluator = format!(
            "{} --port=${{CARLA_PORT}} --traffic-manager-port=${{CARLA_TM_PORT}} \
             --agent=${{TEAM_AGENT}} --agent-config=${{TEAM_CONFIG}} \
             --track=${{CHALLENGE_TRACK_CODENAME}} --routes=${{ROUTES}} \
             --routes-subset=${{ROUTES_SUBSET}} --repetitions=${{REPETITIONS}} \
             --resume=${{RESUME}} --checkpoint=${{CHECKPOINT_ENDPOINT}} \
             --record=${{RECORD_PATH}} --debug-checkpoint=${{DEBUG_CHECKPOINT_ENDPOINT}} --debug=0",
            fake("fake-evaluator").display()
        );
        let args = vec![
            "agent".to_owned(),
            "--".to_owned(),
            "bash".to_owned(),
            "-c".to_owned(),
            evaluator,
        ];
        Proc::spawn(self.command(vols, &args), "agent")
    }
}

/// A sidecar process whose stderr (JSON log lines) is collected in the background.
pub struct Proc {
    pub child: Child,
    pub name: &'static str,
    pub stderr: Arc<Mutex<Vec<String>>>,
    reader: Option<std::thread::JoinHandle<()>>,
}

impl Proc {
    pub fn spawn(mut command: Command, name: &'static str) -> Proc {
        let mut child = command.spawn().unwrap();
        let stderr = Arc::new(Mutex::new(Vec::new()));
        let lines = Arc::clone(&stderr);
        let pipe = child.stderr.take().unwrap();
        let reader = std::thread::spawn(move || {
            for line in BufReader::new(pipe).lines() {
                let Ok(line) = line else { break };
                lines.lock().unwrap().push(line);
            }
        });
        Proc {
            child,
            name,
            stderr,
            reader: Some(reader),
        }
    }

    pub fn pid(&self) -> i32 {
        self.child.id() as i32
    }

    /// Waits for the exit, failing the test after `limit`.
    pub fn wait(&mut self, limit: Duration) -> ExitStatus {
        let deadline = Instant::now() + limit;
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                if let Some(r) = self.reader.take() {
                    let _ = r.join();
                }
                return status;
            }
            if Instant::now() >= deadline {
                let _ = self.child.kill();
                let _ = self.child.wait();
                panic!(
                    "{} did not exit within {limit:?}; its log:\n{}",
                    self.name,
                    self.log()
                );
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    pub fn try_exit(&mut self) -> Option<ExitStatus> {
        self.child.try_wait().unwrap()
    }

    pub fn log(&self) -> String {
        self.stderr.lock().unwrap().join("\n")
    }

    /// The JSON log lines with this message.
    pub fn events(&self, message: &str) -> Vec<serde_json::Value> {
        self.stderr
            .lock()
            .unwrap()
            .iter()
            .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
            .filter(|v| v["fields"]["message"] == message)
            .collect()
    }

    /// Waits until a log line with this message satisfies `pred`.
    pub fn wait_event(
        &self,
        message: &str,
        limit: Duration,
        pred: impl Fn(&serde_json::Value) -> bool,
    ) -> serde_json::Value {
        let deadline = Instant::now() + limit;
        loop {
            if let Some(v) = self.events(message).into_iter().rev().find(|v| pred(v)) {
                return v;
            }
            assert!(
                Instant::now() < deadline,
                "no `{message}` event as expected from {} within {limit:?}:\n{}",
                self.name,
                self.log()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    pub fn signal(&self, signal: nix::sys::signal::Signal) {
        nix::sys::signal::kill(nix::unistd::Pid::from_raw(self.pid()), signal).unwrap();
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        if self.child.try_wait().ok().flatten().is_none() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

/// Whether a process exists (and is not a zombie).
pub fn alive(pid: i32) -> bool {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        Ok(stat) => {
            let state = stat
                .rsplit_once(')')
                .and_then(|(_, rest)| rest.split_whitespace().next())
                .unwrap_or("Z");
            state != "Z" && state != "X"
        }
        Err(_) => false,
    }
}

/// Polls `cond` until true, failing after `limit`.
pub fn wait_until(what: &str, limit: Duration, mut cond: impl FnMut() -> bool) {
    let deadline = Instant::now() + limit;
    while !cond() {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// The route ids of a results file, in order.
pub fn route_ids(path: &Path) -> Vec<String> {
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap();
    v["_checkpoint"]["records"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["route_id"].as_str().unwrap().to_owned())
        .collect()
}

/// Whether a results file is finished per the results engine (a global record, valid).
pub fn finished(bytes: &[u8], subset: &str) -> bool {
    use lb_domain::results::{read_worker_file, Leaderboard, WorkerFile};
    matches!(
        read_worker_file("test", Some(bytes), Leaderboard::V2, Some(subset.parse().unwrap())),
        Ok(WorkerFile::Present(f)) if f.has_global_record
    )
}

// ---- S3 through moto --------------------------------------------------------------------

/// A moto server, a bucket, and an S3 client for checks.
pub struct Moto {
    pub server: local_stack::moto::MotoServer,
    pub bucket: String,
}

impl Moto {
    pub fn start() -> Moto {
        let server = local_stack::moto::MotoServer::start().expect("moto (run `make venv`)");
        let moto = Moto {
            server,
            bucket: "lb-test-bucket".to_owned(),
        };
        moto.cli(&["create-bucket"], &[]);
        moto
    }

    pub fn endpoint(&self) -> String {
        self.server.endpoint()
    }

    /// Environment for init/logcopy using this moto (or `endpoint` when given, e.g. a proxy).
    pub fn env(&self, endpoint: Option<&str>) -> Vec<(String, String)> {
        let mut env: Vec<(String, String)> = self
            .server
            .sdk_env()
            .into_iter()
            .map(|(k, v)| (k.to_owned(), v))
            .collect();
        if let Some(e) = endpoint {
            env.retain(|(k, _)| k != "AWS_ENDPOINT_URL");
            env.push(("AWS_ENDPOINT_URL".into(), e.to_owned()));
        }
        env.push(("LB_S3_BUCKET".into(), self.bucket.clone()));
        env
    }

    /// Minimal S3 calls over plain HTTP (path style, moto ignores signatures).
    fn cli(&self, op: &[&str], body: &[u8]) -> (u16, Vec<u8>) {
        let (method, path) = match op {
            ["create-bucket"] => ("PUT", format!("/{}", self.bucket)),
            ["put", key] => ("PUT", format!("/{}/{key}", self.bucket)),
            ["get", key] => ("GET", format!("/{}/{key}", self.bucket)),
            ["tagging", key] => ("GET", format!("/{}/{key}?tagging", self.bucket)),
            ["delete", key] => ("DELETE", format!("/{}/{key}", self.bucket)),
            ["list", prefix] => (
                "GET",
                format!("/{}?list-type=2&max-keys=1000&prefix={prefix}", self.bucket),
            ),
            _ => unreachable!(),
        };
        http(self.server.addr(), method, &path, body)
    }

    pub fn put(&self, key: &str, body: &[u8]) {
        let (status, _) = self.cli(&["put", key], body);
        assert_eq!(status, 200, "put {key}");
    }

    pub fn get(&self, key: &str) -> Option<Vec<u8>> {
        match self.cli(&["get", key], &[]) {
            (200, body) => Some(body),
            (404, _) => None,
            (status, body) => panic!("get {key}: {status} {}", String::from_utf8_lossy(&body)),
        }
    }

    /// The object's tags as `key=value`, in the order S3 lists them.
    pub fn tags(&self, key: &str) -> Vec<String> {
        let (status, body) = self.cli(&["tagging", key], &[]);
        assert_eq!(status, 200, "tagging {key}");
        let xml = String::from_utf8_lossy(&body);
        let field = |tag: &str, from: &str| -> String {
            let open = format!("<{tag}>");
            from.split_once(&open)
                .and_then(|(_, rest)| rest.split_once(&format!("</{tag}>")))
                .map(|(v, _)| v.to_owned())
                .unwrap_or_default()
        };
        xml.split("<Tag>")
            .skip(1)
            .map(|t| format!("{}={}", field("Key", t), field("Value", t)))
            .collect()
    }

    pub fn exists(&self, key: &str) -> bool {
        self.get(key).is_some()
    }

    /// Keys under a prefix (up to 1,000).
    pub fn keys(&self, prefix: &str) -> Vec<String> {
        let (status, body) = self.cli(&["list", prefix], &[]);
        assert_eq!(status, 200);
        let text = String::from_utf8_lossy(&body);
        let mut keys: Vec<String> = text
            .split("<Key>")
            .skip(1)
            .filter_map(|s| s.split_once("</Key>").map(|(k, _)| k.to_owned()))
            .collect();
        keys.sort();
        keys
    }
}

/// moto does not check signatures, but answers anonymous reads with 403.
const AUTH: &str = "AWS4-HMAC-SHA256 Credential=testing/20240101/us-east-1/s3/aws4_request, \
                    SignedHeaders=host, Signature=00";

/// One HTTP/1.1 request with a body; returns status and body.
pub fn http(addr: SocketAddr, method: &str, path: &str, body: &[u8]) -> (u16, Vec<u8>) {
    let mut stream = TcpStream::connect_timeout(&addr, Duration::from_secs(2)).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(30)))
        .unwrap();
    write!(
        stream,
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Length: {}\r\n\
         Authorization: {AUTH}\r\nConnection: close\r\n\r\n",
        body.len()
    )
    .unwrap();
    stream.write_all(body).unwrap();
    let mut response = Vec::new();
    stream.read_to_end(&mut response).unwrap();
    let split = response
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("HTTP response");
    let head = String::from_utf8_lossy(&response[..split]).to_string();
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap();
    let mut payload = response[split + 4..].to_vec();
    if head
        .to_ascii_lowercase()
        .contains("transfer-encoding: chunked")
    {
        payload = dechunk(&payload);
    }
    (status, payload)
}

fn dechunk(mut data: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    loop {
        let Some(eol) = data.windows(2).position(|w| w == b"\r\n") else {
            return out;
        };
        let size = usize::from_str_radix(
            String::from_utf8_lossy(&data[..eol])
                .split(';')
                .next()
                .unwrap()
                .trim(),
            16,
        )
        .unwrap_or(0);
        if size == 0 {
            return out;
        }
        out.extend_from_slice(&data[eol + 2..eol + 2 + size]);
        data = &data[eol + 2 + size + 2..];
    }
}

/// A TCP proxy in front of moto that can refuse service (an S3 outage) and come back.
pub struct Proxy {
    pub addr: SocketAddr,
    up: Arc<AtomicBool>,
    stop: Arc<AtomicBool>,
}

impl Proxy {
    pub fn start(target: SocketAddr) -> Proxy {
        let listener = TcpListener::bind(("127.0.0.1", 0)).unwrap();
        listener.set_nonblocking(true).unwrap();
        let addr = listener.local_addr().unwrap();
        let up = Arc::new(AtomicBool::new(true));
        let stop = Arc::new(AtomicBool::new(false));
        let (up2, stop2) = (Arc::clone(&up), Arc::clone(&stop));
        std::thread::spawn(move || {
            while !stop2.load(Ordering::Relaxed) {
                match listener.accept() {
                    Ok((client, _)) => {
                        if !up2.load(Ordering::Relaxed) {
                            drop(client);
                            continue;
                        }
                        let _ = client.set_nonblocking(false);
                        let Ok(server) = TcpStream::connect(target) else {
                            continue;
                        };
                        pipe(client, server, Arc::clone(&up2));
                    }
                    Err(_) => std::thread::sleep(Duration::from_millis(10)),
                }
            }
        });
        Proxy { addr, up, stop }
    }

    pub fn endpoint(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// Down: new connections are dropped, open ones are cut.
    pub fn set_up(&self, up: bool) {
        self.up.store(up, Ordering::Relaxed);
    }
}

impl Drop for Proxy {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

fn pipe(a: TcpStream, b: TcpStream, up: Arc<AtomicBool>) {
    for (mut from, mut to) in [(a.try_clone().unwrap(), b.try_clone().unwrap()), (b, a)] {
        let up = Arc::clone(&up);
        std::thread::spawn(move || {
            let _ = from.set_read_timeout(Some(Duration::from_millis(200)));
            let mut buf = vec![0u8; 64 * 1024];
            loop {
                if !up.load(Ordering::Relaxed) {
                    let _ = to.shutdown(std::net::Shutdown::Both);
                    let _ = from.shutdown(std::net::Shutdown::Both);
                    return;
                }
                match from.read(&mut buf) {
                    Ok(0) => {
                        let _ = to.shutdown(std::net::Shutdown::Write);
                        return;
                    }
                    Ok(n) => {
                        if to.write_all(&buf[..n]).is_err() {
                            return;
                        }
                    }
                    Err(e)
                        if e.kind() == std::io::ErrorKind::WouldBlock
                            || e.kind() == std::io::ErrorKind::TimedOut => {}
                    Err(_) => {
                        let _ = to.shutdown(std::net::Shutdown::Both);
                        return;
                    }
                }
            }
        });
    }
}

/// `lb-sidecar logcopy` on a volume root.
pub fn logcopy(
    vols: &Volumes,
    moto: &Moto,
    endpoint: Option<&str>,
    extra: &[(&str, &str)],
) -> Proc {
    let mut c = Command::new(SIDECAR);
    c.arg("logcopy")
        .env_clear()
        .env("PATH", std::env::var("PATH").unwrap_or_default())
        .env("RUST_LOG", "info")
        .env("LB_SUBMISSION_ID", SUBMISSION)
        .env("LB_JOB_INDEX", "0")
        .env("LB_LEADERBOARD", "2.0")
        .env("LB_LOGS_ROOT", vols.root())
        .env("LB_PAIRS", "1")
        .env("LB_PERIOD_SECONDS", "1")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    for (k, v) in moto.env(endpoint) {
        c.env(k, v);
    }
    for (k, v) in extra {
        c.env(k, v);
    }
    Proc::spawn(c, "logcopy")
}

/// `lb-sidecar init` for a pod whose volumes are `vols`, with official sources and code
/// volumes under `code` (`src/<name>` filled with a file each, `dst/<name>`, `bin`).
pub fn init_command(vols: &Volumes, moto: &Moto, code: &Path, extra: &[(&str, &str)]) -> Proc {
    for name in ["leaderboard", "scenario_runner", "carla"] {
        let src = code.join("src").join(name);
        std::fs::create_dir_all(src.join("sub")).unwrap();
        std::fs::write(src.join("sub/official.py"), format!("# official {name}\n")).unwrap();
    }
    let mut c = Command::new(SIDECAR);
    c.arg("init")
        .env_clear()
        .env("PATH", std::env::var("PATH").unwrap_or_default())
        .env("RUST_LOG", "info")
        .env("LB_SUBMISSION_ID", SUBMISSION)
        .env("LB_JOB_INDEX", "0")
        .env("LB_LEADERBOARD", "2.0")
        .env("LB_LOGS_ROOT", vols.root())
        .env("LB_BIN_DIR", code.join("bin"))
        .env("LB_PAIRS", "1")
        .env("LB_SOURCE_LEADERBOARD", code.join("src/leaderboard"))
        .env(
            "LB_SOURCE_SCENARIO_RUNNER",
            code.join("src/scenario_runner"),
        )
        .env("LB_SOURCE_CARLA_API", code.join("src/carla"))
        .env("LEADERBOARD_ROOT", code.join("dst/leaderboard"))
        .env("SCENARIO_RUNNER_ROOT", code.join("dst/scenario_runner"))
        .env("CARLA_ROOT", code.join("dst/CARLA"))
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    for (k, v) in moto.env(None) {
        c.env(k, v);
    }
    for (k, v) in extra {
        c.env(k, v);
    }
    Proc::spawn(c, "init")
}
