//! One whole Job on the local Kubernetes API: init, a simulator-agent pair and logcopy,
//! with the contract's volumes, subPaths and commands, S3 served by moto.

use crate::support;

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant};

use serde_json::{json, Value};
use support::*;

fn request(addr: SocketAddr, method: &str, path: &str, body: Option<&Value>) -> (u16, Value) {
    let body = body.map(Value::to_string).unwrap_or_default();
    let mut s = TcpStream::connect_timeout(&addr, Duration::from_secs(2)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )
    .unwrap();
    let mut out = Vec::new();
    s.read_to_end(&mut out).unwrap();
    let text = String::from_utf8_lossy(&out);
    let status = text.split_whitespace().nth(1).unwrap().parse().unwrap();
    let payload = text.split_once("\r\n\r\n").map(|(_, b)| b).unwrap_or("");
    let payload = if text
        .to_ascii_lowercase()
        .contains("transfer-encoding: chunked")
    {
        // One JSON document per response: drop the chunk-size lines.
        payload
            .split("\r\n")
            .filter(|l| !l.chars().all(|c| c.is_ascii_hexdigit()) || l.is_empty())
            .collect::<String>()
    } else {
        payload.to_owned()
    };
    (
        status,
        serde_json::from_str(&payload).unwrap_or(Value::Null),
    )
}

fn env(pairs: &[(&str, String)]) -> Value {
    Value::Array(
        pairs
            .iter()
            .map(|(k, v)| json!({"name": k, "value": v}))
            .collect(),
    )
}

#[test]
#[ignore = "needs moto"]
fn a_job_with_init_a_pair_and_logcopy_completes_and_leaves_its_results_in_s3() {
    let moto = Moto::start();
    let kube = local_kube::LocalKube::spawn(local_kube::Config::default()).unwrap();
    let sources = tempfile::tempdir().unwrap();
    for name in ["leaderboard", "scenario_runner", "carla"] {
        std::fs::create_dir_all(sources.path().join(name)).unwrap();
        std::fs::write(sources.path().join(name).join("README"), name).unwrap();
    }
    // The CARLA egg the evaluator imports (the fake checks it is on PYTHONPATH).
    let dist = sources.path().join("carla/PythonAPI/carla/dist");
    std::fs::create_dir_all(&dist).unwrap();
    std::fs::write(dist.join("carla-0.9.15-py3.7-linux-x86_64.egg"), "egg").unwrap();
    let port = free_port();
    let common = [
        ("LB_SUBMISSION_ID", SUBMISSION.to_owned()),
        ("LB_JOB_INDEX", "0".to_owned()),
        ("LB_LEADERBOARD", "2.0".to_owned()),
    ];
    let aws: Vec<(&str, String)> = moto
        .env(None)
        .into_iter()
        .map(|(k, v)| (leak(k), v))
        .collect();
    let pair = [
        ("LB_PAIR_ID", "1".to_owned()),
        ("CARLA_PORT", port.to_string()),
        ("CARLA_TM_PORT", (port + 10).to_string()),
        ("ROUTES_SUBSET", "0-2".to_owned()),
        ("REPETITIONS", "1".to_owned()),
        ("LB_POLL_SECONDS", "0.2".to_owned()),
    ];
    let agent_env = [
        ("CHALLENGE_TRACK_CODENAME", "SENSORS".to_owned()),
        (
            "ROUTES",
            "/workspace/leaderboard/data/routes_testing.xml".to_owned(),
        ),
        ("TEAM_AGENT", "/workspace/team_code/agent.py".to_owned()),
        ("LEADERBOARD_ROOT", "/workspace/leaderboard".to_owned()),
        (
            "SCENARIO_RUNNER_ROOT",
            "/workspace/scenario_runner".to_owned(),
        ),
        ("CARLA_ROOT", "/workspace/CARLA".to_owned()),
        (
            "PYTHONPATH",
            "/workspace/CARLA/PythonAPI/carla/dist/carla-0.9.15-py3.7-linux-x86_64.egg:\
             /workspace/scenario_runner:/workspace/leaderboard"
                .to_owned(),
        ),
        ("FAKE_EVALUATOR_ROUTE_SECONDS", "0.2".to_owned()),
    ];
    let mut init_env: Vec<(&str, String)> = common.to_vec();
    init_env.extend(aws.iter().cloned());
    init_env.extend([
        ("LB_PAIRS", "1".to_owned()),
        (
            "LB_SOURCE_LEADERBOARD",
            sources.path().join("leaderboard").display().to_string(),
        ),
        (
            "LB_SOURCE_SCENARIO_RUNNER",
            sources.path().join("scenario_runner").display().to_string(),
        ),
        (
            "LB_SOURCE_CARLA_API",
            sources.path().join("carla").display().to_string(),
        ),
    ]);
    let mut sim_env: Vec<(&str, String)> = common.to_vec();
    sim_env.extend(pair.iter().cloned());
    let mut ag_env = sim_env.clone();
    ag_env.extend(agent_env.iter().cloned());
    let mut lc_env: Vec<(&str, String)> = common.to_vec();
    lc_env.extend(aws.iter().cloned());
    lc_env.extend([
        ("LB_PAIRS", "1".to_owned()),
        ("LB_PERIOD_SECONDS", "1".to_owned()),
    ]);
    let evaluator = format!(
        "{} --port=${{CARLA_PORT}} --traffic-manager-port=${{CARLA_TM_PORT}} --agent=${{TEAM_AGENT}} \
         --track=${{CHALLENGE_TRACK_CODENAME}} --routes=${{ROUTES}} --routes-subset=${{ROUTES_SUBSET}} \
         --repetitions=${{REPETITIONS}} --resume=${{RESUME}} --checkpoint=${{CHECKPOINT_ENDPOINT}} \
         --record=${{RECORD_PATH}} --debug-checkpoint=${{DEBUG_CHECKPOINT_ENDPOINT}}",
        fake("fake-evaluator").display()
    );
    let status_mount =
        json!({"name": "logs", "mountPath": "/tmp/status", "subPath": "containers-status"});
    let logs_mount = json!({"name": "logs", "mountPath": "/tmp/logs", "subPath": "logs"});
    let bin_mount = json!({"name": "lb-bin", "mountPath": "/opt/lb"});
    let handoff_mount = json!({"name": "handoff", "mountPath": "/tmp/handoff"});
    let code_mounts = [
        json!({"name": "leaderboard", "mountPath": "/workspace/leaderboard"}),
        json!({"name": "scenario-runner", "mountPath": "/workspace/scenario_runner"}),
        json!({"name": "carla-api", "mountPath": "/workspace/CARLA"}),
    ];
    let name = format!("submission-{SUBMISSION}-0");
    let job = json!({
        "apiVersion": "batch/v1",
        "kind": "Job",
        "metadata": {"name": name},
        "spec": {
            "backoffLimit": 4,
            "podReplacementPolicy": "Failed",
            "podFailurePolicy": {"rules": [
                {"action": "Ignore", "onPodConditions": [{"type": "DisruptionTarget", "status": "True"}]},
                {"action": "FailJob", "onExitCodes": {"operator": "In", "values": [3, 78]}}
            ]},
            "template": {"spec": {
                "restartPolicy": "Never",
                "volumes": [
                    {"name": "logs", "emptyDir": {}},
                    {"name": "lb-bin", "emptyDir": {}},
                    {"name": "leaderboard", "emptyDir": {}},
                    {"name": "scenario-runner", "emptyDir": {}},
                    {"name": "carla-api", "emptyDir": {}},
                    {"name": "handoff", "emptyDir": {}},
                ],
                "initContainers": [{
                    "name": "private-contents",
                    "image": "private-contents:test",
                    "command": [SIDECAR, "init"],
                    "env": env(&init_env),
                    "volumeMounts": [
                        {"name": "logs", "mountPath": "/logs"},
                        bin_mount.clone(),
                        code_mounts[0].clone(), code_mounts[1].clone(), code_mounts[2].clone(),
                    ],
                }],
                "containers": [
                    {
                        "name": "simulator-1",
                        "image": "carla:test",
                        "command": ["/opt/lb/lb-sidecar", "simulator", "--",
                                    fake("fake-carla").display().to_string(),
                                    "-vulkan", "-carla-rpc-port={carla_port}", "-RenderOffScreen", "-nosound"],
                        "env": env(&sim_env),
                        "volumeMounts": [status_mount.clone(), logs_mount.clone(), bin_mount.clone(), handoff_mount.clone()],
                    },
                    {
                        "name": "agent-1",
                        "image": "participant:test",
                        "command": ["/opt/lb/lb-sidecar", "agent", "--", "bash", "-c", evaluator],
                        "env": env(&ag_env),
                        "volumeMounts": [
                            status_mount,
                            {"name": "logs", "mountPath": "/tmp/agent", "subPath": "agent"},
                            logs_mount,
                            bin_mount.clone(),
                            handoff_mount,
                            code_mounts[0].clone(), code_mounts[1].clone(), code_mounts[2].clone(),
                        ],
                    },
                    {
                        "name": "logcopy",
                        "image": "private-contents:test",
                        "command": ["/opt/lb/lb-sidecar", "logcopy"],
                        "env": env(&lc_env),
                        "volumeMounts": [{"name": "logs", "mountPath": "/logs"}, bin_mount],
                    },
                ],
            }},
        },
    });
    let addr = kube.addr();
    let (status, body) = request(
        addr,
        "POST",
        "/apis/batch/v1/namespaces/default/jobs",
        Some(&job),
    );
    assert_eq!(status, 201, "{body}");

    let deadline = Instant::now() + Duration::from_secs(120);
    let job_path = format!("/apis/batch/v1/namespaces/default/jobs/{name}");
    loop {
        let (_, job) = request(addr, "GET", &job_path, None);
        let conditions = job["status"]["conditions"]
            .as_array()
            .cloned()
            .unwrap_or_default();
        if conditions
            .iter()
            .any(|c| c["type"] == "Complete" && c["status"] == "True")
        {
            break;
        }
        assert!(
            !conditions
                .iter()
                .any(|c| c["type"] == "Failed" && c["status"] == "True"),
            "the Job failed: {job}"
        );
        assert!(Instant::now() < deadline, "the Job did not complete: {job}");
        std::thread::sleep(Duration::from_millis(250));
    }

    let results = moto
        .get(&format!("{SUBMISSION}/agent/partial_agent_results1.json"))
        .expect("partial results in S3");
    assert!(finished(&results, "0-2"));
    for marker in [
        "agent-1.done",
        "simulator-1.done",
        "simulator-1.start0",
        "logcopy-0.done",
    ] {
        assert!(
            moto.exists(&format!("{SUBMISSION}/containers-status/{marker}")),
            "{marker}"
        );
    }
    let log = moto
        .get(&format!("{SUBMISSION}/logs/agent/agent1/agent.log"))
        .unwrap();
    assert!(String::from_utf8_lossy(&log).contains("Preparing RouteScenario_2"));
}

fn leak(s: String) -> &'static str {
    Box::leak(s.into_boxed_str())
}
