//! Our manifests and permissions judged by the real Kubernetes control plane (`real-kube`,
//! the pinned release): `infra/k8s` and the rendered Jobs pass its validation and the
//! namespace's Pod Security level, the pipeline's calls (`lb_cluster`) are authorized by its
//! RBAC as the pipeline's own identity, and a request outside that Role is refused.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use lb_cluster::{Cluster, Job, Whose};
use real_kube::{ControlPlane, Identity};

/// The namespace `infra/k8s` makes (the settings' `namespace` in a deployment).
const NAMESPACE: &str = "leaderboard";

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn kubectl(plane: &ControlPlane, who: Identity, args: &[&str]) -> Output {
    Command::new("kubectl")
        .arg(format!("--kubeconfig={}", plane.kubeconfig(who).display()))
        .args(args)
        .output()
        .expect("kubectl runs")
}

fn text(out: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

/// The golden rendered Jobs (crates/jobs/tests/golden), in the namespace `infra/k8s` makes.
fn rendered_jobs() -> Vec<Job> {
    let golden = root().join("crates/jobs/tests/golden/leaderboard-20.yaml");
    let text = std::fs::read_to_string(&golden).unwrap();
    serde_yaml::Deserializer::from_str(&text)
        .map(|doc| {
            let mut job: Job = serde::Deserialize::deserialize(doc).unwrap();
            job.metadata.namespace = Some(NAMESPACE.into());
            job
        })
        .collect()
}

/// `infra/k8s` applied as an operator applies it; the server validates each object.
fn apply_infra(plane: &ControlPlane) {
    let k8s = root().join("infra/k8s");
    let applied = kubectl(
        plane,
        Identity::Admin,
        &["apply", "-f", k8s.to_str().unwrap()],
    );
    assert!(
        applied.status.success(),
        "infra/k8s refused: {}",
        text(&applied)
    );
}

/// Pod resident memory, MiB.
fn rss_mib(pid: u32) -> f64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    let kib: f64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches(" kB").trim().parse().ok())
        .unwrap_or(0.0);
    kib / 1024.0
}

#[tokio::test]
#[ignore = "builds and starts the real control plane (minutes the first time): make test runs it"]
async fn the_real_control_plane_admits_our_manifests_and_only_the_pipeline_s_own_requests() {
    let bin = real_kube::binaries().expect("the control plane builds");
    let started = Instant::now();
    let plane = ControlPlane::start(&bin).expect("the control plane starts");
    let ready = started.elapsed();
    let memory: Vec<String> = (plane.pids().into_iter())
        .map(|(name, pid)| format!("{name} {:.0} MiB", rss_mib(pid)))
        .collect();
    println!(
        "real-kube ready in {:.1} s; {}",
        ready.as_secs_f64(),
        memory.join(", ")
    );

    apply_infra(&plane);

    // The pipeline's own calls, as the pipeline's identity.
    let cluster = Cluster::from_kubeconfig(&plane.kubeconfig(Identity::Pipeline), None)
        .await
        .unwrap()
        .with_namespace(NAMESPACE);
    let jobs = rendered_jobs();
    for job in &jobs {
        cluster
            .create_or_adopt(job)
            .await
            .expect("the pipeline creates its Jobs");
    }
    // The Job controller makes their pods: Pod Security `baseline` admitted the template.
    let deadline = Instant::now() + Duration::from_secs(60);
    let seen = loop {
        let seen = cluster
            .observe("4242")
            .await
            .expect("the pipeline observes");
        let pods: usize = seen.jobs.iter().map(|j| j.pods.len()).sum();
        if pods == jobs.len() {
            break seen;
        }
        if Instant::now() > deadline {
            let events = kubectl(&plane, Identity::Admin, &["-n", NAMESPACE, "get", "events"]);
            panic!("{pods} of {} pods made: {}", jobs.len(), text(&events));
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    };
    assert_eq!(seen.jobs.len(), jobs.len());
    let first = &seen.jobs[0].name;
    assert!(cluster.set_deadline(first, 300_000).await.unwrap());
    assert_eq!(cluster.node("no-such-node").await.unwrap(), None);
    // A pair moved off a drained node: the Eviction API, as the pipeline; a pod gone already
    // moves nothing.
    let pod = &seen.jobs[0].pods[0].name;
    assert!(cluster.evict(pod).await.expect("the pipeline evicts"));
    assert!(!cluster.evict("no-such-pod").await.unwrap());
    cluster
        .delete_all("4242", Whose::Any)
        .await
        .expect("the pipeline deletes its Jobs");
    let gone = cluster.wait_gone(
        "4242",
        Whose::Any,
        Duration::from_secs(60),
        Duration::from_secs(1),
    );
    assert!(gone.await.unwrap(), "the Jobs and pods went");

    // Outside the Role, as the same identity: refused by the real authorizer.
    for request in [
        &["-n", NAMESPACE, "get", "secrets"][..],
        &[
            "-n",
            NAMESPACE,
            "run",
            "sneak",
            "--image=busybox",
            "--restart=Never",
        ],
        &["-n", "default", "get", "jobs"],
        &["delete", "node", "any"],
    ] {
        let out = kubectl(&plane, Identity::Pipeline, request);
        assert!(!out.status.success(), "{request:?} was allowed");
        assert!(
            text(&out).contains("Forbidden"),
            "{request:?}: {}",
            text(&out)
        );
    }

    // The sweep's count of the GPUs, as its group; and nothing more.
    let fleet = Cluster::from_kubeconfig(&plane.kubeconfig(Identity::Fleet), None)
        .await
        .unwrap()
        .with_namespace(NAMESPACE);
    add_named_node(&plane, "drained", "A10G", 4);
    let counted = fleet
        .gpu_fleet()
        .await
        .expect("the sweep lists nodes and pods");
    assert_eq!(counted.held(), 0, "the Jobs are gone");
    // Consolidation: the sweep taints the node and takes the taint off again; a patch of a
    // node changed since it was read is refused, left to the next sweep.
    let node = counted.nodes.iter().find(|n| n.name == "drained").unwrap();
    assert!(fleet
        .set_draining(node, true)
        .await
        .expect("the sweep drains"));
    let tainted = fleet.gpu_fleet().await.unwrap();
    let read = tainted.nodes.iter().find(|n| n.name == "drained").unwrap();
    assert!(read.draining && read.open, "{read:?}");
    assert!(
        !fleet.set_draining(node, false).await.unwrap(),
        "stale version"
    );
    assert!(fleet.set_draining(read, false).await.unwrap());
    let again = fleet.gpu_fleet().await.unwrap();
    assert!(!again.nodes.iter().any(|n| n.draining));
    for request in [
        &["-n", NAMESPACE, "get", "jobs"][..],
        &["-n", NAMESPACE, "get", "secrets"],
        &["-n", "default", "get", "pods"],
        &["get", "node", "any"],
        &["delete", "node", "any"],
    ] {
        let out = kubectl(&plane, Identity::Fleet, request);
        assert!(
            !out.status.success(),
            "{request:?} was allowed to the sweep"
        );
        assert!(
            text(&out).contains("Forbidden"),
            "{request:?}: {}",
            text(&out)
        );
    }

    // The namespace's level holds whoever asks: a privileged pod is refused even to an admin.
    let privileged = r#"{"apiVersion":"v1","kind":"Pod","metadata":{"name":"privileged"},
        "spec":{"containers":[{"name":"c","image":"busybox",
        "securityContext":{"privileged":true}}]}}"#;
    let file = tempfile::NamedTempFile::with_suffix(".json").unwrap();
    std::fs::write(file.path(), privileged).unwrap();
    let out = kubectl(
        &plane,
        Identity::Admin,
        &[
            "-n",
            NAMESPACE,
            "create",
            "-f",
            file.path().to_str().unwrap(),
        ],
    );
    assert!(!out.status.success(), "a privileged pod was admitted");
    assert!(
        text(&out).contains("violates PodSecurity \"baseline"),
        "{}",
        text(&out)
    );
}

#[test]
fn the_control_plane_is_the_release_our_clusters_run() {
    let pins = std::fs::read_to_string(root().join("local/realkube/versions.env")).unwrap();
    let pinned = pins
        .lines()
        .find_map(|l| l.strip_prefix("K8S_VERSION=v"))
        .expect("versions.env pins K8S_VERSION");
    let minor: Vec<&str> = pinned.split('.').take(2).collect();
    let template = std::fs::read_to_string(root().join("infra/cluster.yaml")).unwrap();
    let default = template
        .split("KubernetesVersion:")
        .nth(1)
        .and_then(|rest| rest.lines().find_map(|l| l.trim().strip_prefix("Default:")))
        .map(|v| v.trim().trim_matches('"').to_string())
        .expect("infra/cluster.yaml has a KubernetesVersion default");
    assert_eq!(minor.join("."), default, "upgrade the pin with the cluster");
    // The upgrade rehearsal's release is one minor up: EKS upgrades one minor at a time.
    let upgrade = pins
        .lines()
        .find_map(|l| l.strip_prefix("UPGRADE_K8S_VERSION=v"))
        .expect("versions.env pins UPGRADE_K8S_VERSION");
    let minor_of = |v: &str| v.split('.').nth(1).and_then(|m| m.parse::<u32>().ok());
    assert_eq!(
        minor_of(upgrade),
        minor_of(pinned).map(|m| m + 1),
        "{upgrade}"
    );
}

/// A GPU node as a node group makes it: labelled with its GPU model, `nvidia.com/gpu` of
/// `gpus`, Ready, and without the `not-ready` taint a new Node is created with (no node
/// lifecycle controller runs here to lift it).
fn add_node(plane: &ControlPlane, gpu_model: &str, gpus: u32) {
    add_named_node(plane, "gpu-node", gpu_model, gpus);
}

/// [`add_node`] under `name`.
fn add_named_node(plane: &ControlPlane, name: &str, gpu_model: &str, gpus: u32) {
    let node = format!(
        r#"{{"apiVersion":"v1","kind":"Node","metadata":{{"name":"{name}",
        "labels":{{"leaderboard.carla.org/gpu-model":"{gpu_model}"}}}}}}"#
    );
    // A file of its own: tests that add nodes run side by side in this process.
    let file = tempfile::NamedTempFile::with_suffix(".json").unwrap();
    std::fs::write(file.path(), node).unwrap();
    let created = kubectl(
        plane,
        Identity::Admin,
        &["create", "-f", file.path().to_str().unwrap()],
    );
    assert!(created.status.success(), "{}", text(&created));
    let resources = format!(
        r#"{{"cpu":"32","memory":"128Gi","pods":"110","ephemeral-storage":"200Gi","nvidia.com/gpu":"{gpus}"}}"#
    );
    let status = format!(
        r#"{{"status":{{"capacity":{resources},"allocatable":{resources},
        "conditions":[{{"type":"Ready","status":"True","reason":"KubeletReady","message":"ready"}}]}}}}"#
    );
    let patch = [
        "patch",
        "node",
        name,
        "--subresource=status",
        "--type=merge",
        "-p",
        &status,
    ];
    let patched = kubectl(plane, Identity::Admin, &patch);
    assert!(patched.status.success(), "{}", text(&patched));
    let untaint = [
        "taint",
        "nodes",
        name,
        "node.kubernetes.io/not-ready:NoSchedule-",
    ];
    let _ = kubectl(plane, Identity::Admin, &untaint);
}

/// The scheduler's complaint about the first pod of submission 4242, as `lb_cluster` reads it.
async fn unschedulable(cluster: &Cluster) -> String {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let seen = cluster.observe("4242").await.unwrap();
        let pod = seen.jobs.iter().flat_map(|j| &j.pods).next();
        if let Some(waiting) = pod.and_then(|p| p.unschedulable.as_ref()) {
            return waiting.message.clone();
        }
        assert!(Instant::now() < deadline, "no pod was found unschedulable");
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
}

/// The same Job on local-kube, whose one node has `gpus` GPUs of `gpu_model`.
async fn local_unschedulable(gpu_model: &str, gpus: u32) -> String {
    let config = local_kube::Config {
        gpus: Some(gpus),
        labels: [("leaderboard.carla.org/gpu-model".into(), gpu_model.into())].into(),
        ..Default::default()
    };
    let lk = local_kube::LocalKube::start(config).await.unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("kubeconfig");
    lk.write_kubeconfig(&path).unwrap();
    let cluster = Cluster::from_kubeconfig(&path, None).await.unwrap();
    let mut job = rendered_jobs().remove(0);
    job.metadata.namespace = Some(cluster.namespace().to_string());
    cluster.create_or_adopt(&job).await.unwrap();
    unschedulable(&cluster).await
}

/// What the real control plane answered, committed (`LB_RECORD_KUBE_CONTRACT=1` re-records it).
fn contract_path() -> PathBuf {
    root().join("local/realkube/contract/scheduler.json")
}

fn recorded() -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(contract_path()).unwrap()).unwrap()
}

/// The one node's GPU model and count, for a pod asking one `nvidia-a10g`: too few GPUs, and
/// the wrong model.
const NODES: [(&str, u32); 2] = [("nvidia-a10g", 0), ("nvidia-l4", 8)];

fn case(gpu_model: &str, gpus: u32) -> String {
    format!("a node with {gpus} GPUs of {gpu_model}")
}

#[tokio::test]
#[ignore = "builds and starts the real control plane (minutes the first time): make test runs it"]
async fn local_kube_s_scheduler_complains_as_the_real_one_does() {
    let bin = real_kube::binaries().expect("the control plane builds");
    let recorded = recorded();
    let mut answered = serde_json::Map::new();
    for (gpu_model, gpus) in NODES {
        let case = case(gpu_model, gpus);
        let plane = ControlPlane::start(&bin).expect("the control plane starts");
        add_node(&plane, gpu_model, gpus);
        apply_infra(&plane);
        let cluster = Cluster::from_kubeconfig(&plane.kubeconfig(Identity::Pipeline), None)
            .await
            .unwrap()
            .with_namespace(NAMESPACE);
        cluster.create_or_adopt(&rendered_jobs()[0]).await.unwrap();
        let real = unschedulable(&cluster).await;
        let local = local_unschedulable(gpu_model, gpus).await;
        assert_eq!(local, real, "{case}: local-kube against the real scheduler");
        if std::env::var_os("LB_RECORD_KUBE_CONTRACT").is_none() {
            assert_eq!(
                recorded[&case],
                real.as_str(),
                "{case}: the recording is stale"
            );
        }
        answered.insert(case, real.into());
    }
    if std::env::var_os("LB_RECORD_KUBE_CONTRACT").is_some() {
        let text = serde_json::to_string_pretty(&answered).unwrap();
        std::fs::write(contract_path(), text + "\n").unwrap();
    }
}

/// local-kube against the recording alone: what a machine without the real control plane
/// still checks.
#[tokio::test]
async fn local_kube_s_scheduler_answers_as_recorded() {
    let recorded = recorded();
    for (gpu_model, gpus) in NODES {
        let case = case(gpu_model, gpus);
        let local = local_unschedulable(gpu_model, gpus).await;
        assert_eq!(recorded[&case], local.as_str(), "{case}");
    }
}

/// A pod of `cpu` CPUs and one GPU, placed by `scheduler` (or bound to `node`).
fn gpu_pod(name: &str, cpu: u32, scheduler: &str, node: Option<&str>) -> String {
    let node = node.map_or(String::new(), |n| format!(r#""nodeName":"{n}","#));
    format!(
        r#"{{"apiVersion":"v1","kind":"Pod","metadata":{{"name":"{name}","namespace":"default"}},
        "spec":{{{node}"schedulerName":"{scheduler}","containers":[{{"name":"c","image":"example/agent:1",
        "resources":{{"requests":{{"cpu":"{cpu}","nvidia.com/gpu":"1"}},"limits":{{"nvidia.com/gpu":"1"}}}}}}]}}}}"#
    )
}

/// The node the scheduler bound pod `name` to.
fn bound_to(plane: &ControlPlane, name: &str) -> String {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let args = [
            "get",
            "pod",
            name,
            "-n",
            "default",
            "-o",
            "jsonpath={.spec.nodeName}",
        ];
        let node = text(&kubectl(plane, Identity::Admin, &args))
            .trim()
            .to_string();
        if !node.is_empty() {
            return node;
        }
        assert!(Instant::now() < deadline, "{name} was never bound");
        std::thread::sleep(Duration::from_millis(250));
    }
}

#[test]
#[ignore = "builds and starts the real control plane (minutes the first time): make test runs it"]
fn the_packing_profile_puts_a_pair_on_the_fullest_gpu_node() {
    // The profile infra/k8s/scheduler.yaml configures, as the real scheduler serves it beside
    // the default one: with one node partly used, packing fills it and the default spreads.
    let bin = real_kube::binaries().expect("the control plane builds");
    let plane = ControlPlane::start(&bin).expect("the control plane starts");
    add_named_node(&plane, "gpu-a", "nvidia-a10g", 4);
    add_named_node(&plane, "gpu-b", "nvidia-a10g", 4);
    apply_infra(&plane);
    let template =
        std::fs::read_to_string(root().join("templates/leaderboard-20/job.yaml")).unwrap();
    let packing = template
        .lines()
        .find_map(|l| l.trim().strip_prefix("schedulerName: "))
        .expect("the Job template names its scheduler");
    let dir = tempfile::tempdir().unwrap();
    let pods = [
        (
            "running",
            gpu_pod("running", 8, "default-scheduler", Some("gpu-a")),
        ),
        ("packed", gpu_pod("packed", 1, packing, None)),
        ("spread", gpu_pod("spread", 1, "default-scheduler", None)),
    ];
    for (name, pod) in pods {
        let path = dir.path().join(format!("{name}.json"));
        std::fs::write(&path, pod).unwrap();
        let created = kubectl(
            &plane,
            Identity::Admin,
            &["create", "-f", path.to_str().unwrap()],
        );
        assert!(created.status.success(), "{}", text(&created));
        if name != "running" {
            let node = bound_to(&plane, name);
            let expected = if name == "packed" { "gpu-a" } else { "gpu-b" };
            assert_eq!(
                node,
                expected,
                "{name} by {}",
                if name == "packed" {
                    packing
                } else {
                    "default-scheduler"
                }
            );
            let deleted = kubectl(
                &plane,
                Identity::Admin,
                &["delete", "pod", name, "-n", "default", "--wait=false"],
            );
            assert!(deleted.status.success(), "{}", text(&deleted));
        }
    }
}
