//! Cold start + one invocation of each Lambda as a whole process, against the local stack
//! (moto, the fake EvalAI, the local Kubernetes API), with its peak memory.
//!
//! Each bootstrap is started as Lambda starts it: environment only, the Runtime API on
//! `AWS_LAMBDA_RUNTIME_API` (served here), one event; the clock stops when its response
//! arrives and the peak resident set (VmHWM) is read from /proc before the process is stopped.
//! `make bench-functions` builds the bootstraps with `cargo lambda build --release` first;
//! without `--bench` (as `cargo test` runs benches) it uses the debug binaries once.
//!
//! Every request a function makes (AWS, EvalAI, Kubernetes) passes a recording proxy, so each
//! line also says how many it made and how many of them ran one after another: the chain a
//! function's latency is made of, counted from the event's arrival (its cold start's reads
//! aside).

use std::collections::HashMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use local_stack::stack::{SETTINGS_SECRET, TOKEN_SECRET};
use local_stack::workloads::{Behaviour, Binaries};
use serde_json::{json, Value};
use test_support::wire::{self, Exchange, Wiretap};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpListener;
use tokio::sync::oneshot;

/// One invocation served by the fake Runtime API: the event out, the answer back.
struct Invocation {
    event: Value,
    answer: Mutex<Option<oneshot::Sender<(String, Value)>>>,
    /// When the event was handed out.
    served: Mutex<Option<Instant>>,
}

/// A minimal Lambda Runtime API: `next` hands out the event once (later calls hang, as the
/// real one does between invocations), `response`/`error` carry the result back.
async fn runtime_api(invocation: Arc<Invocation>) -> SocketAddr {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(async move {
        loop {
            let Ok((mut socket, _)) = listener.accept().await else {
                return;
            };
            let invocation = invocation.clone();
            tokio::spawn(async move {
                let mut buf = Vec::new();
                let mut chunk = [0u8; 8192];
                // Read the head, then Content-Length bytes of body.
                let (head, mut body) = loop {
                    let n = socket.read(&mut chunk).await.unwrap_or(0);
                    if n == 0 {
                        return;
                    }
                    buf.extend_from_slice(&chunk[..n]);
                    if let Some(end) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
                        let head = String::from_utf8_lossy(&buf[..end]).to_string();
                        break (head, buf[end + 4..].to_vec());
                    }
                };
                let length = head
                    .lines()
                    .find_map(|l| {
                        l.to_ascii_lowercase()
                            .strip_prefix("content-length:")
                            .map(|v| v.trim().parse::<usize>().unwrap_or(0))
                    })
                    .unwrap_or(0);
                while body.len() < length {
                    let n = socket.read(&mut chunk).await.unwrap_or(0);
                    if n == 0 {
                        break;
                    }
                    body.extend_from_slice(&chunk[..n]);
                }
                let path = head
                    .split_whitespace()
                    .nth(1)
                    .unwrap_or_default()
                    .to_string();
                if path.ends_with("/invocation/next") {
                    let first = invocation.served.lock().unwrap().replace(Instant::now());
                    if first.is_some() {
                        std::future::pending::<()>().await;
                    }
                    let payload = invocation.event.to_string();
                    let deadline = std::time::SystemTime::now()
                        .duration_since(std::time::UNIX_EPOCH)
                        .unwrap()
                        .as_millis()
                        + 300_000;
                    let response = format!(
                        "HTTP/1.1 200 OK\r\nconnection: close\r\ncontent-type: application/json\r\nlambda-runtime-aws-request-id: bench-1\r\n\
                         lambda-runtime-deadline-ms: {deadline}\r\nlambda-runtime-invoked-function-arn: arn:aws:lambda:us-east-1:123456789012:function:bench\r\n\
                         lambda-runtime-trace-id: Root=1-00000000-000000000000000000000000\r\ncontent-length: {}\r\n\r\n{payload}",
                        payload.len()
                    );
                    let _ = socket.write_all(response.as_bytes()).await;
                } else {
                    let kind = if path.ends_with("/response") {
                        "response"
                    } else {
                        "error"
                    };
                    let value = serde_json::from_slice(&body).unwrap_or(Value::Null);
                    let _ = socket
                        .write_all(b"HTTP/1.1 202 Accepted\r\nconnection: close\r\ncontent-length: 2\r\n\r\n{}")
                        .await;
                    if let Some(tx) = invocation.answer.lock().unwrap().take() {
                        let _ = tx.send((kind.to_string(), value));
                    }
                }
            });
        }
    });
    addr
}

fn peak_rss_kib(pid: u32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap_or_default()
        .lines()
        .find_map(|l| {
            l.strip_prefix("VmHWM:")
                .map(|v| v.trim().trim_end_matches(" kB").trim().parse().unwrap_or(0))
        })
        .unwrap_or(0)
}

struct Measured {
    function: &'static str,
    elapsed: Duration,
    peak_kib: u64,
    outcome: String,
    output: Value,
    /// Every request it made, and when its event arrived.
    requests: Vec<Exchange>,
    event_at: Option<Instant>,
}

impl Measured {
    /// The requests made once the event had arrived.
    fn after_the_event(&self) -> Vec<Exchange> {
        let Some(at) = self.event_at else {
            return Vec::new();
        };
        self.requests
            .iter()
            .filter(|r| r.started >= at)
            .cloned()
            .collect()
    }
}

async fn invoke(
    function: &'static str,
    binary: &Path,
    env: &HashMap<String, String>,
    event: Value,
    tap: &Wiretap,
) -> Measured {
    let (tx, rx) = oneshot::channel();
    let invocation = Arc::new(Invocation {
        event,
        answer: Mutex::new(Some(tx)),
        served: Mutex::new(None),
    });
    tap.take();
    let api = runtime_api(invocation.clone()).await;
    let started = Instant::now();
    let mut child: Child = Command::new(binary)
        .env_clear()
        .envs(env)
        .env("PATH", std::env::var("PATH").unwrap_or_default())
        .env("AWS_LAMBDA_RUNTIME_API", api.to_string())
        .env("AWS_LAMBDA_FUNCTION_NAME", function)
        .env("AWS_LAMBDA_FUNCTION_MEMORY_SIZE", "512")
        .env("AWS_LAMBDA_FUNCTION_VERSION", "$LATEST")
        .env("AWS_LAMBDA_LOG_FORMAT", "JSON")
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap_or_else(|e| panic!("start {}: {e}", binary.display()));
    let answer = tokio::time::timeout(Duration::from_secs(300), rx).await;
    let elapsed = started.elapsed();
    // The runtime now waits for its next event (served never): still alive, peak readable.
    let peak_kib = peak_rss_kib(child.id());
    assert!(peak_kib > 0, "{function} exited after its invocation");
    let _ = child.kill();
    let _ = child.wait();
    let (outcome, output) = match answer {
        Ok(Ok(answer)) => answer,
        _ => ("timeout".into(), Value::Null),
    };
    let event_at = *invocation.served.lock().unwrap();
    Measured {
        function,
        elapsed,
        peak_kib,
        outcome,
        output,
        requests: tap.take(),
        event_at,
    }
}

fn binaries(target: &Path, release: bool) -> Vec<(&'static str, PathBuf)> {
    ["intake", "launch", "monitor", "finalize", "wake", "sweep"]
        .into_iter()
        .map(|f| {
            let lambda = target.join("lambda").join(f).join("bootstrap");
            let path = if release && lambda.is_file() {
                lambda
            } else if release {
                target.join("release").join(f)
            } else {
                target.join("debug").join(f)
            };
            assert!(
                path.is_file(),
                "{} missing: run `make build` (or cargo build -p {f})",
                path.display()
            );
            (f, path)
        })
        .collect()
}

/// Waits (bounded) until every Job of `submission` is complete.
async fn run_ended(kubeconfig: &Path, submission: &str) {
    let cluster = lb_cluster::Cluster::from_kubeconfig(kubeconfig, None)
        .await
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(240);
    loop {
        let seen = cluster.observe(submission).await.unwrap();
        let verdict = seen.verdict(&lb_domain::cluster::view::VerdictPolicy::default());
        if verdict == lb_domain::cluster::view::Verdict::Finished {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "the run did not end: {verdict:?}"
        );
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
}

/// Puts the recording proxy between the functions and every service: AWS (the endpoint to
/// give them), EvalAI (the settings secret names it) and Kubernetes (the kubeconfig to give
/// them).
async fn tapped(stack: &local_stack::stack::Stack, tap: &Wiretap) -> (String, PathBuf) {
    let aws = tap.proxy("aws", &stack.moto.endpoint()).await.unwrap();
    let evalai = tap.proxy("evalai", &stack.evalai_url).await.unwrap();
    let secrets = aws_sdk_secretsmanager::Client::new(&stack.sdk);
    let settings = secrets
        .get_secret_value()
        .secret_id(SETTINGS_SECRET)
        .send()
        .await
        .unwrap();
    let mut settings: Value = serde_json::from_str(settings.secret_string().unwrap()).unwrap();
    settings["evalai"]["api_server"] = Value::String(evalai);
    let settings = settings.to_string();
    let put = secrets
        .put_secret_value()
        .secret_id(SETTINGS_SECRET)
        .secret_string(settings);
    put.send().await.unwrap();
    let original = stack.kubeconfig.as_ref().unwrap();
    let mut config: serde_yaml::Value =
        serde_yaml::from_str(&std::fs::read_to_string(original).unwrap()).unwrap();
    let server = &mut config["clusters"][0]["cluster"]["server"];
    let kube = tap
        .proxy("kubernetes", server.as_str().unwrap())
        .await
        .unwrap();
    *server = serde_yaml::Value::String(kube);
    let kubeconfig = stack.workdir.path().join("kubeconfig-tapped");
    std::fs::write(&kubeconfig, serde_yaml::to_string(&config).unwrap()).unwrap();
    (aws, kubeconfig)
}

fn main() {
    let release = std::env::args().any(|a| a == "--bench");
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let target = std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| root.join("target"));
    if !release {
        local_stack::workloads::build_workspace_bins().expect("the workspace's binaries");
    }
    let functions = binaries(&target, release);
    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(async {
        let bins = tokio::task::spawn_blocking(Binaries::build).await.unwrap().unwrap();
        let (mut stack, settings) = test_support::stack::provisioned().await;
        stack.start_workloads(&settings, &bins, &Behaviour::default(), &[]).unwrap();
        // The participant's image in the registry: Intake resolves its tag (one ECR call).
        let image = "123456789012.dkr.ecr.us-west-2.amazonaws.com/team-one:v1";
        local_stack::registry::push(&stack.sdk, image).await.unwrap();
        let tap = Wiretap::default();
        let (aws, kubeconfig) = tapped(&stack, &tap).await;
        let env: HashMap<String, String> = stack
            .moto
            .sdk_env()
            .into_iter()
            .map(|(k, v)| (k.to_string(), if k == "AWS_ENDPOINT_URL" { aws.clone() } else { v }))
            .chain([
                ("LB_SETTINGS_SECRET".to_string(), SETTINGS_SECRET.to_string()),
                ("LB_EVALAI_TOKEN_SECRET".to_string(), TOKEN_SECRET.to_string()),
                ("LB_WAKE_TABLE".to_string(), "leaderboard-wakes".to_string()),
                ("LB_BUDGET_TABLE".to_string(), local_stack::stack::BUDGET_TABLE.to_string()),
                ("LB_ADMISSION_TABLE".to_string(), local_stack::stack::ADMISSION_TABLE.to_string()),
                ("LB_KUBECONFIG".to_string(), kubeconfig.display().to_string()),
            ])
            .collect();

        let mut results = Vec::new();
        let message = json!({"challenge_pk": "1", "phase_pk": "1", "submission_pk": 1,
                             "submitted_image_uri": "123456789012.dkr.ecr.us-west-2.amazonaws.com/team-one:v1"});
        let mut state = json!({});
        for (function, binary) in &functions {
            if *function == "monitor" {
                // The Monitor's round then sees the run end, and Finalize does the whole of a
                // finished run's work (merge, final post, recordings, record) with nothing left
                // to wait for: its own I/O is what is measured, not the pods' termination.
                let kubeconfig = stack.kubeconfig.as_ref().unwrap();
                run_ended(kubeconfig, "1").await;
            }
            let event = match *function {
                "intake" => json!({"message": message, "execution": "bench"}),
                "launch" => json!({"submission": state["intake"]["submission"]}),
                "monitor" => json!({"submission": state["intake"]["submission"], "run": state["run"]}),
                "finalize" => json!({"state": state}),
                // A results file of submission 1 landed (S3 -> EventBridge -> SQS), one record.
                "wake" => json!({"Records": [{
                    "messageId": "bench-1", "receiptHandle": "r", "eventSource": "aws:sqs",
                    "attributes": {}, "messageAttributes": {},
                    "body": json!({"version": "0", "source": "aws.s3", "detail-type": "Object Created",
                                   "detail": {"bucket": {"name": "leaderboard-20-results"},
                                              "object": {"key": "1/agent/partial_agent_results1.json"}}})
                        .to_string(),
                }]}),
                // The schedule's event: the sweep reads EvalAI's cancels of every challenge.
                _ => json!({}),
            };
            let measured = invoke(function, binary, &env, event, &tap).await;
            assert_eq!(measured.outcome, "response", "{function}: {}", measured.output);
            if *function == "finalize" {
                assert_eq!(measured.output["status"], "FINISHED", "the whole path was measured");
            }
            if *function == "wake" {
                assert_eq!(measured.output, json!({"batchItemFailures": []}), "the wake counted it");
            }
            match *function {
                "intake" => state["intake"] = measured.output.clone(),
                "launch" | "monitor" => state["run"] = measured.output.clone(),
                _ => {}
            }
            results.push(measured);
        }
        println!(
            "cold start + one invocation as a process, {} binaries, against moto + fake EvalAI + local Kubernetes API:",
            if release { "release (cargo lambda)" } else { "debug" }
        );
        println!("  (requests: all the process made / those after its event; in sequence: the longest chain of them one after another)");
        for m in &results {
            let after = m.after_the_event();
            println!(
                "  {:<9} {:>8.1} ms  peak RSS {:>6.1} MiB  requests {:>2} / {:>2}  in sequence {:>2} / {:>2}  ({})",
                m.function, m.elapsed.as_secs_f64() * 1000.0, m.peak_kib as f64 / 1024.0,
                m.requests.len(), after.len(), wire::in_sequence(&m.requests).len(), wire::in_sequence(&after).len(),
                m.outcome
            );
        }
        // The closing's chain, request by request: where Finalize's time goes.
        for m in results.iter().filter(|m| m.function == "finalize") {
            let after = m.after_the_event();
            let Some(start) = m.event_at else { continue };
            println!("  finalize's requests in sequence after its event:");
            for r in wire::in_sequence(&after) {
                let (from, to) = (r.started - start, r.ended - start);
                println!("    {:>7.1} .. {:>7.1} ms  {:<10} {}", from.as_secs_f64() * 1000.0, to.as_secs_f64() * 1000.0, r.service, r.what);
            }
        }
    });
}
