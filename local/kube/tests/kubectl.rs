//! The real kubectl against the `local-kube` binary: create -f, get -o json, logs, delete.
//! Ignored by plain `cargo test` (it needs kubectl); `make test` installs kubectl and runs it.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

fn kubectl_path() -> Option<PathBuf> {
    let path = std::env::var("PATH").unwrap_or_default();
    path.split(':')
        .map(|d| Path::new(d).join("kubectl"))
        .find(|p| p.is_file())
}

struct Server {
    child: Child,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start_server(dir: &Path) -> (Server, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_local-kube"))
        .args(["--port", "0", "--kubeconfig"])
        .arg(dir.join("kubeconfig"))
        .arg("--state-dir")
        .arg(dir.join("state"))
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("local-kube binary starts");
    let stdout = child.stdout.take().expect("piped stdout");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut line = String::new();
        let _ = BufReader::new(stdout).read_line(&mut line);
        let _ = tx.send(line);
    });
    let url = rx
        .recv_timeout(Duration::from_secs(20))
        .expect("local-kube prints its URL");
    (Server { child }, url.trim().to_owned())
}

struct Kubectl {
    bin: PathBuf,
    kubeconfig: PathBuf,
    cache: PathBuf,
}

impl Kubectl {
    fn run(&self, args: &[&str]) -> Output {
        let mut cmd = Command::new(&self.bin);
        cmd.arg("--kubeconfig")
            .arg(&self.kubeconfig)
            .arg("--cache-dir")
            .arg(&self.cache)
            .args(["--request-timeout", "20s"])
            .args(args)
            .stdin(Stdio::null());
        cmd.output().expect("kubectl runs")
    }

    fn ok(&self, args: &[&str]) -> String {
        let out = self.run(args);
        assert!(
            out.status.success(),
            "kubectl {args:?} failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8(out.stdout).expect("utf-8 output")
    }

    fn json(&self, args: &[&str]) -> Value {
        serde_json::from_str(&self.ok(args)).expect("kubectl printed JSON")
    }
}

const JOB: &str = r#"
apiVersion: batch/v1
kind: Job
metadata:
  name: demo
  labels: {app: demo}
spec:
  backoffLimit: 2
  template:
    spec:
      restartPolicy: OnFailure
      volumes:
      - name: logs
        emptyDir: {}
      containers:
      - name: main
        image: busybox
        command: [sh, -c, 'echo "main says hi"; echo ok > /tmp/status/main.done']
        volumeMounts: [{name: logs, mountPath: /tmp/status, subPath: containers-status}]
      - name: side
        image: busybox
        command: [sh, -c, 'i=0; while [ ! -s /tmp/status/main.done ] && [ $$i -lt 200 ]; do sleep 0.05; i=$$((i+1)); done; echo "side saw $$(cat /tmp/status/main.done)"']
        volumeMounts: [{name: logs, mountPath: /tmp/status, subPath: containers-status}]
---
apiVersion: batch/v1
kind: Job
metadata:
  name: forever
spec:
  template:
    spec:
      restartPolicy: Never
      terminationGracePeriodSeconds: 1
      containers:
      - {name: c, image: busybox, command: [sh, -c, 'echo started; exec sleep 300']}
"#;

fn items_of_kind<'a>(list: &'a Value, kind: &str) -> Vec<&'a Value> {
    list["items"]
        .as_array()
        .expect("a List")
        .iter()
        .filter(|i| i["kind"] == kind)
        .collect()
}

fn job_condition(job: &Value, type_: &str) -> bool {
    job["status"]["conditions"].as_array().is_some_and(|cs| {
        cs.iter()
            .any(|c| c["type"] == type_ && c["status"] == "True")
    })
}

fn poll<T>(what: &str, mut f: impl FnMut() -> Option<T>) -> T {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        if let Some(v) = f() {
            return v;
        }
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
#[ignore = "needs kubectl on PATH (make test installs it)"]
fn the_real_kubectl_creates_lists_reads_logs_of_and_deletes_jobs() {
    let bin = kubectl_path().expect("kubectl is not on PATH: run `make kubectl`");
    let dir = tempfile::tempdir().unwrap();
    let (mut server, url) = start_server(dir.path());
    assert!(url.starts_with("http://127.0.0.1:"), "{url}");
    let k = Kubectl {
        bin,
        kubeconfig: dir.path().join("kubeconfig"),
        cache: dir.path().join("cache"),
    };
    let manifest = dir.path().join("job.yaml");
    std::fs::write(&manifest, JOB).unwrap();
    let created = k.ok(&["create", "-f", manifest.to_str().unwrap()]);
    assert_eq!(
        created,
        "job.batch/demo created\njob.batch/forever created\n"
    );

    let list = poll("demo to complete", || {
        let list = k.json(&["get", "jobs,pods", "-o", "json"]);
        let done = items_of_kind(&list, "Job")
            .iter()
            .any(|j| j["metadata"]["name"] == "demo" && job_condition(j, "Complete"));
        done.then_some(list)
    });
    let demo_pod = items_of_kind(&list, "Pod")
        .into_iter()
        .find(|p| p["metadata"]["labels"]["job-name"] == "demo")
        .expect("a demo pod");
    assert_eq!(demo_pod["status"]["phase"], "Succeeded");
    assert_eq!(demo_pod["metadata"]["ownerReferences"][0]["kind"], "Job");
    let pod_name = demo_pod["metadata"]["name"].as_str().unwrap().to_owned();

    assert_eq!(k.ok(&["logs", "job/demo", "-c", "main"]), "main says hi\n");
    assert_eq!(
        k.ok(&["logs", &format!("pod/{pod_name}"), "-c", "side"]),
        "side saw ok\n"
    );
    let table = k.ok(&["get", "jobs"]);
    assert!(table.starts_with("NAME"), "{table}");
    assert!(
        table
            .lines()
            .any(|l| l.starts_with("demo") && l.contains("Complete") && l.contains("1/1")),
        "{table}"
    );

    let missing = k.run(&["get", "job", "nope"]);
    assert!(!missing.status.success());
    assert!(String::from_utf8_lossy(&missing.stderr)
        .contains("Error from server (NotFound): jobs.batch \"nope\" not found"));

    poll("forever to start", || {
        let out = k.run(&["logs", "job/forever"]);
        (out.status.success() && out.stdout == b"started\n").then_some(())
    });
    assert_eq!(
        k.ok(&["delete", "job", "forever"]),
        "job.batch \"forever\" deleted\n"
    );
    assert_eq!(
        k.ok(&["delete", "job", "demo"]),
        "job.batch \"demo\" deleted\n"
    );
    poll("every pod to go", || {
        let list = k.json(&["get", "jobs,pods", "-o", "json"]);
        list["items"]
            .as_array()
            .is_some_and(Vec::is_empty)
            .then_some(())
    });

    let pid = server.child.id() as i32;
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(pid),
        nix::sys::signal::Signal::SIGTERM,
    )
    .unwrap();
    let status = poll("the server to exit on SIGTERM", || {
        server.child.try_wait().ok().flatten()
    });
    assert!(status.success(), "{status:?}");
    assert!(
        std::fs::read_dir(dir.path().join("state")).map_or(true, |mut d| d.next().is_none()),
        "pod directories removed"
    );
}
