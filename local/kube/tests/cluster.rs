//! local-kube against kube-rs typed APIs (so every object deserializes as k8s-openapi types) and
//! raw HTTP (for Status bodies). Every wait is bounded.

use std::future::Future;
use std::path::Path;
use std::time::{Duration, Instant};

use k8s_openapi::api::batch::v1::Job;
use k8s_openapi::api::core::v1::{ContainerStatus, Pod};
use kube::api::{Api, DeleteParams, ListParams, LogParams, Patch, PatchParams, PostParams};
use kube::config::{KubeConfigOptions, Kubeconfig};
use kube::Client;
use local_kube::{Config, ImageMap, LocalKube};
use serde_json::Value;

const WAIT: Duration = Duration::from_secs(20);

async fn client_for(yaml: &str) -> Client {
    let kc = Kubeconfig::from_yaml(yaml).expect("kubeconfig parses");
    let cfg = kube::Config::from_custom_kubeconfig(kc, &KubeConfigOptions::default())
        .await
        .expect("kubeconfig loads");
    Client::try_from(cfg).expect("client builds")
}

async fn start(config: Config) -> (LocalKube, Client) {
    let lk = LocalKube::start(config).await.expect("local-kube starts");
    let client = client_for(&lk.kubeconfig_yaml()).await;
    (lk, client)
}

/// The first container of a Job's pod template, to change before creating it.
fn first_container(job: &mut Job) -> &mut k8s_openapi::api::core::v1::Container {
    &mut job
        .spec
        .as_mut()
        .unwrap()
        .template
        .spec
        .as_mut()
        .unwrap()
        .containers[0]
}

fn job(yaml: &str) -> Job {
    serde_yaml::from_str(yaml).expect("test manifest parses")
}

/// Polls `check` every 50 ms until it yields a value or `WAIT` passes.
async fn eventually<T, F, Fut>(what: &str, mut check: F) -> T
where
    F: FnMut() -> Fut,
    Fut: Future<Output = Option<T>>,
{
    let deadline = Instant::now() + WAIT;
    loop {
        if let Some(v) = check().await {
            return v;
        }
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

fn condition<'a>(
    job: &'a Job,
    type_: &str,
) -> Option<&'a k8s_openapi::api::batch::v1::JobCondition> {
    job.status
        .as_ref()?
        .conditions
        .as_ref()?
        .iter()
        .find(|c| c.type_ == type_ && c.status == "True")
}

async fn wait_condition(jobs: &Api<Job>, name: &str, type_: &str) -> Job {
    eventually(&format!("job {name} {type_}"), || async {
        let j = jobs.get(name).await.ok()?;
        condition(&j, type_).is_some().then_some(j)
    })
    .await
}

async fn pods_of(pods: &Api<Pod>, job: &str) -> Vec<Pod> {
    pods.list(&ListParams::default().labels(&format!("job-name={job}")))
        .await
        .expect("pods list")
        .items
}

async fn one_pod(pods: &Api<Pod>, job: &str) -> Pod {
    eventually(&format!("a pod of {job}"), || async {
        pods_of(pods, job).await.into_iter().next()
    })
    .await
}

fn container<'a>(pod: &'a Pod, name: &str) -> Option<&'a ContainerStatus> {
    pod.status
        .as_ref()?
        .container_statuses
        .as_ref()?
        .iter()
        .find(|c| c.name == name)
}

/// Whether a process exists and is not a zombie.
fn alive(pid: i32) -> bool {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        Ok(stat) => {
            let state = stat
                .rfind(')')
                .and_then(|i| stat[i + 1..].split_whitespace().next());
            !matches!(state, Some("Z") | Some("X"))
        }
        Err(_) => false,
    }
}

async fn read_pid(path: &Path) -> i32 {
    eventually(&format!("pid file {}", path.display()), || async {
        std::fs::read_to_string(path).ok()?.trim().parse().ok()
    })
    .await
}

async fn raw(
    lk: &LocalKube,
    method: reqwest::Method,
    path: &str,
    token: Option<&str>,
    body: Option<&str>,
) -> (u16, Value) {
    let mut req = reqwest::Client::new().request(method, format!("{}{path}", lk.url()));
    if let Some(t) = token {
        req = req.bearer_auth(t);
    }
    if let Some(b) = body {
        req = req
            .header("content-type", "application/json")
            .body(b.to_owned());
    }
    let resp = req.send().await.expect("request sent");
    let code = resp.status().as_u16();
    let text = resp.text().await.expect("body read");
    (
        code,
        serde_json::from_str(&text).unwrap_or(Value::String(text)),
    )
}

const RESTART_ONCE: &str = r#"
apiVersion: batch/v1
kind: Job
metadata:
  name: restart-once
  labels: {lb/submission: "101"}
spec:
  template:
    spec:
      restartPolicy: OnFailure
      terminationGracePeriodSeconds: 1
      volumes:
      - name: logs
        emptyDir: {}
      containers:
      - name: simulator
        image: busybox
        command: [sh, -c]
        args:
        - |
          if [ ! -f /tmp/status/first-attempt ]; then
            echo "attempt 1 at $$(date +%s)" > /tmp/status/first-attempt
            echo "attempt 1 failing"
            exit 3
          fi
          echo "attempt 2 found: $$(cat /tmp/status/first-attempt)"
          touch /tmp/status/simulator.done
        volumeMounts:
        - {name: logs, mountPath: /tmp/status, subPath: containers-status}
      - name: agent
        image: busybox
        command: [sh, -c]
        args:
        - |
          i=0
          while [ ! -f /tmp/status/simulator.done ] && [ $$i -lt 200 ]; do sleep 0.05; i=$$((i+1)); done
          ls /tmp/status
          test -f /tmp/status/simulator.done
        volumeMounts:
        - {name: logs, mountPath: /tmp/status, subPath: containers-status}
"#;

#[tokio::test]
async fn a_container_that_fails_once_restarts_in_place_keeps_its_volume_and_the_job_completes() {
    let (_lk, client) = start(Config::default()).await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let pods: Api<Pod> = Api::namespaced(client, "default");
    let created = jobs
        .create(&PostParams::default(), &job(RESTART_ONCE))
        .await
        .unwrap();
    let meta = &created.metadata;
    assert_eq!(meta.uid.as_ref().map(String::len), Some(36));
    assert!(meta.creation_timestamp.is_some());
    assert_eq!(meta.generation, Some(1));
    let spec = created.spec.as_ref().unwrap();
    assert_eq!(spec.backoff_limit, Some(6));
    assert_eq!(spec.completions, Some(1));
    let done = wait_condition(&jobs, "restart-once", "Complete").await;
    let status = done.status.clone().unwrap();
    assert_eq!(status.succeeded, Some(1));
    assert_eq!(status.active, None);
    assert!(status.completion_time.is_some());
    let types: Vec<&str> = status
        .conditions
        .iter()
        .flatten()
        .map(|c| c.type_.as_str())
        .collect();
    assert_eq!(types, ["SuccessCriteriaMet", "Complete"]);
    let complete = condition(&done, "Complete").unwrap();
    assert_eq!(complete.reason.as_deref(), Some("CompletionsReached"));
    assert!(
        done.metadata
            .resource_version
            .as_deref()
            .unwrap()
            .parse::<u64>()
            .unwrap()
            > created
                .metadata
                .resource_version
                .as_deref()
                .unwrap()
                .parse::<u64>()
                .unwrap()
    );

    let pod = one_pod(&pods, "restart-once").await;
    assert_eq!(
        pod.status.as_ref().unwrap().phase.as_deref(),
        Some("Succeeded")
    );
    let owner = &pod.metadata.owner_references.as_ref().unwrap()[0];
    assert_eq!(
        (owner.kind.as_str(), owner.name.as_str()),
        ("Job", "restart-once")
    );
    assert_eq!(owner.uid, created.metadata.uid.clone().unwrap());
    let sim = container(&pod, "simulator").unwrap();
    assert_eq!(sim.restart_count, 1);
    let last = sim
        .last_state
        .as_ref()
        .unwrap()
        .terminated
        .as_ref()
        .unwrap();
    assert_eq!(last.exit_code, 3);
    assert_eq!(last.reason.as_deref(), Some("Error"));
    let now = sim.state.as_ref().unwrap().terminated.as_ref().unwrap();
    assert_eq!(
        (now.exit_code, now.reason.as_deref()),
        (0, Some("Completed"))
    );
    assert_eq!(container(&pod, "agent").unwrap().restart_count, 0);

    let name = pod.metadata.name.clone().unwrap();
    let sim_logs = |previous| LogParams {
        container: Some("simulator".into()),
        previous,
        ..Default::default()
    };
    let previous = pods.logs(&name, &sim_logs(true)).await.unwrap();
    assert_eq!(previous, "attempt 1 failing\n");
    let current = pods.logs(&name, &sim_logs(false)).await.unwrap();
    assert!(
        current.starts_with("attempt 2 found: attempt 1 at "),
        "volume content survived: {current:?}"
    );
    let agent = pods
        .logs(
            &name,
            &LogParams {
                container: Some("agent".into()),
                ..Default::default()
            },
        )
        .await
        .unwrap();
    assert_eq!(agent, "first-attempt\nsimulator.done\n");
    let tail = pods
        .logs(
            &name,
            &LogParams {
                container: Some("agent".into()),
                tail_lines: Some(1),
                ..Default::default()
            },
        )
        .await
        .unwrap();
    assert_eq!(tail, "simulator.done\n");
}

const FAILING: &str = r#"
metadata: {name: always-fails}
spec:
  backoffLimit: 2
  template:
    spec:
      restartPolicy: OnFailure
      terminationGracePeriodSeconds: 1
      containers:
      - {name: c, image: busybox, command: [sh, -c, 'echo boom; exit 1']}
"#;

#[tokio::test]
async fn a_job_over_its_backoff_limit_with_on_failure_fails_with_backoff_limit_exceeded() {
    let mut config = Config::default();
    config.timing.restart_backoff = Duration::from_millis(500);
    let (_lk, client) = start(config).await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let pods: Api<Pod> = Api::namespaced(client, "default");
    jobs.create(&PostParams::default(), &job(FAILING))
        .await
        .unwrap();
    let (pod, c) = eventually("CrashLoopBackOff", || async {
        let pod = pods_of(&pods, "always-fails").await.into_iter().next()?;
        let c = container(&pod, "c")?.clone();
        let reason = c.state.as_ref()?.waiting.as_ref()?.reason.clone()?;
        (reason == "CrashLoopBackOff").then_some((pod, c))
    })
    .await;
    assert_eq!(
        pod.status.as_ref().unwrap().phase.as_deref(),
        Some("Running")
    );
    let last = c.last_state.as_ref().unwrap().terminated.as_ref().unwrap();
    assert_eq!((last.exit_code, last.reason.as_deref()), (1, Some("Error")));
    let message = c.state.clone().unwrap().waiting.unwrap().message.unwrap();
    assert!(message.starts_with("back-off "), "{message}");
    let failed = wait_condition(&jobs, "always-fails", "Failed").await;
    let c = condition(&failed, "Failed").unwrap();
    assert_eq!(c.reason.as_deref(), Some("BackoffLimitExceeded"));
    assert_eq!(
        c.message.as_deref(),
        Some("Job has reached the specified backoff limit")
    );
    assert!(c.last_probe_time.is_some() && c.last_transition_time.is_some());
    assert!(condition(&failed, "FailureTarget").is_some());
    let status = failed.status.unwrap();
    assert_eq!(status.failed, Some(1));
    assert_eq!(status.active, None);
    assert!(status.completion_time.is_none());
    let gone = eventually("pods of the failed job to be deleted", || async {
        pods_of(&pods, "always-fails")
            .await
            .is_empty()
            .then_some(())
    })
    .await;
    assert_eq!(gone, ());
}

#[tokio::test]
async fn a_job_with_restart_policy_never_replaces_failed_pods_until_its_backoff_limit() {
    let (_lk, client) = start(Config::default()).await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let pods: Api<Pod> = Api::namespaced(client, "default");
    let manifest = FAILING
        .replace("always-fails", "never-restarts")
        .replace("backoffLimit: 2", "backoffLimit: 1")
        .replace("OnFailure", "Never");
    jobs.create(&PostParams::default(), &job(&manifest))
        .await
        .unwrap();
    let failed = wait_condition(&jobs, "never-restarts", "Failed").await;
    assert_eq!(
        condition(&failed, "Failed").unwrap().reason.as_deref(),
        Some("BackoffLimitExceeded")
    );
    assert_eq!(failed.status.unwrap().failed, Some(2));
    let left = pods_of(&pods, "never-restarts").await;
    assert_eq!(left.len(), 2, "failed pods stay, as on a real cluster");
    for p in &left {
        assert_eq!(p.status.as_ref().unwrap().phase.as_deref(), Some("Failed"));
        let c = container(p, "c").unwrap();
        assert_eq!(c.restart_count, 0);
        assert_eq!(
            c.state
                .as_ref()
                .unwrap()
                .terminated
                .as_ref()
                .unwrap()
                .exit_code,
            1
        );
    }
}

#[tokio::test]
async fn active_deadline_seconds_fails_the_job_with_deadline_exceeded_and_kills_its_pod() {
    let dir = tempfile::tempdir().unwrap();
    let (_lk, client) = start(Config::default()).await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let pods: Api<Pod> = Api::namespaced(client, "default");
    let pid_file = dir.path().join("pid");
    let manifest = format!(
        r#"
metadata: {{name: too-slow}}
spec:
  activeDeadlineSeconds: 1
  template:
    spec:
      restartPolicy: Never
      terminationGracePeriodSeconds: 1
      containers:
      - {{name: c, image: busybox, command: [sh, -c, 'echo $$$$ > {}; exec sleep 60']}}
"#,
        pid_file.display()
    );
    jobs.create(&PostParams::default(), &job(&manifest))
        .await
        .unwrap();
    let pid = read_pid(&pid_file).await;
    let failed = wait_condition(&jobs, "too-slow", "Failed").await;
    let c = condition(&failed, "Failed").unwrap();
    assert_eq!(c.reason.as_deref(), Some("DeadlineExceeded"));
    assert_eq!(
        c.message.as_deref(),
        Some("Job was active longer than specified deadline")
    );
    assert!(!alive(pid), "the container process was killed");
    assert!(pods_of(&pods, "too-slow").await.is_empty());
}

#[tokio::test]
async fn a_patched_deadline_is_the_one_the_job_controller_keeps() {
    let (_lk, client) = start(Config::default()).await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let manifest = r#"
metadata: {name: extended}
spec:
  activeDeadlineSeconds: 2
  template:
    spec:
      restartPolicy: Never
      terminationGracePeriodSeconds: 1
      containers:
      - {name: c, image: busybox, command: [sleep, "60"]}
"#;
    jobs.create(&PostParams::default(), &job(manifest))
        .await
        .unwrap();
    let merge = |patch: Value| Patch::Merge(patch);
    let longer = merge(serde_json::json!({"spec": {"activeDeadlineSeconds": 600}}));
    let patched = jobs
        .patch("extended", &PatchParams::default(), &longer)
        .await
        .unwrap();
    assert_eq!(patched.spec.unwrap().active_deadline_seconds, Some(600));
    assert_eq!(patched.metadata.generation, Some(2));
    // Past the old deadline, the Job still runs.
    tokio::time::sleep(Duration::from_secs(4)).await;
    let job = jobs.get("extended").await.unwrap();
    assert!(condition(&job, "Failed").is_none(), "{:?}", job.status);
    // Anything else in the spec is refused, with the server's Invalid status.
    let other = merge(serde_json::json!({"spec": {"backoffLimit": 9}}));
    match jobs
        .patch("extended", &PatchParams::default(), &other)
        .await
    {
        Err(kube::Error::Api(e)) => assert_eq!((e.code, e.reason.as_str()), (422, "Invalid")),
        other => panic!("a backoffLimit patch was not refused: {other:?}"),
    }
    // A deadline already past fails the Job at once, as the controller's re-armed timer does.
    let shorter = merge(serde_json::json!({"spec": {"activeDeadlineSeconds": 1}}));
    jobs.patch("extended", &PatchParams::default(), &shorter)
        .await
        .unwrap();
    let failed = wait_condition(&jobs, "extended", "Failed").await;
    let c = condition(&failed, "Failed").unwrap();
    assert_eq!(c.reason.as_deref(), Some("DeadlineExceeded"));
}

/// Waits (bounded) until the API no longer has Job `name`.
async fn gone(jobs: &Api<Job>, name: &str) {
    eventually("the job to disappear", || async {
        jobs.get_opt(name).await.unwrap().is_none().then_some(())
    })
    .await;
}

fn sleeper(name: &str, dir: &Path) -> Job {
    job(&format!(
        r#"
metadata: {{name: {name}}}
spec:
  template:
    spec:
      restartPolicy: OnFailure
      terminationGracePeriodSeconds: 5
      containers:
      - name: c
        image: busybox
        command: [sh, -c]
        args: ['echo $$$$ > {d}/pid; sleep 300 & echo $$! > {d}/child; wait']
"#,
        d = dir.display()
    ))
}

#[tokio::test]
async fn deleting_a_running_job_in_the_foreground_leaves_no_process_and_no_pod_behind() {
    let dir = tempfile::tempdir().unwrap();
    let (lk, client) = start(Config::default()).await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let pods: Api<Pod> = Api::namespaced(client, "default");
    jobs.create(&PostParams::default(), &sleeper("sleeper", dir.path()))
        .await
        .unwrap();
    let pid = read_pid(&dir.path().join("pid")).await;
    let child = read_pid(&dir.path().join("child")).await;
    assert!(alive(pid) && alive(child));
    let pod_dir_count = std::fs::read_dir(lk.pods_dir()).unwrap().count();
    assert_eq!(pod_dir_count, 1);
    let started = Instant::now();
    let answer = jobs
        .delete("sleeper", &DeleteParams::foreground())
        .await
        .unwrap();
    let j = answer
        .left()
        .expect("a foreground delete answers the job being deleted");
    assert!(j.metadata.deletion_timestamp.is_some());
    assert_eq!(
        j.metadata.finalizers,
        Some(vec!["foregroundDeletion".to_owned()])
    );
    gone(&jobs, "sleeper").await;
    assert!(pods_of(&pods, "sleeper").await.is_empty());
    assert!(!alive(pid), "container process {pid} survived");
    assert!(
        !alive(child),
        "grandchild {child} survived: {:?}",
        std::fs::read_to_string(format!("/proc/{child}/stat"))
    );
    assert!(
        started.elapsed() < Duration::from_secs(4),
        "SIGTERM ended it within the grace period"
    );
    assert_eq!(
        std::fs::read_dir(lk.pods_dir()).unwrap().count(),
        0,
        "pod directory removed"
    );
}

#[tokio::test]
async fn a_stopping_containers_sigterm_reaches_its_main_process_only() {
    // As a container runtime does: the processes the main one started are its to stop (a
    // pair's sidecar stops CARLA after the evaluator), and go with it once it exits.
    let dir = tempfile::tempdir().unwrap();
    let (_lk, client) = start(Config::default()).await;
    let jobs: Api<Job> = Api::namespaced(client, "default");
    let d = dir.path().display();
    let spec = job(&format!(
        r#"
metadata: {{name: ordered}}
spec:
  template:
    spec:
      restartPolicy: Never
      terminationGracePeriodSeconds: 5
      containers:
      - name: c
        image: busybox
        command: [sh, -c]
        args:
        - |
          sh -c 'trap "echo child >> {d}/term" TERM; while :; do sleep 0.1; done' &
          echo $! > {d}/child
          trap 'echo main >> {d}/term; sleep 0.5; exit 0' TERM
          while :; do sleep 0.1; done
"#
    ));
    jobs.create(&PostParams::default(), &spec).await.unwrap();
    let child = read_pid(&dir.path().join("child")).await;
    assert!(alive(child));
    jobs.delete("ordered", &DeleteParams::foreground())
        .await
        .unwrap();
    gone(&jobs, "ordered").await;
    let told = std::fs::read_to_string(dir.path().join("term")).unwrap_or_default();
    assert_eq!(told, "main\n", "only the main process gets SIGTERM");
    assert!(!alive(child), "the child went with the main process");
}

#[tokio::test]
async fn deleting_in_the_background_answers_a_success_status_and_kills_the_pods() {
    let dir = tempfile::tempdir().unwrap();
    let (_lk, client) = start(Config::default()).await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let pods: Api<Pod> = Api::namespaced(client, "default");
    jobs.create(&PostParams::default(), &sleeper("bg", dir.path()))
        .await
        .unwrap();
    let child = read_pid(&dir.path().join("child")).await;
    let answer = jobs
        .delete("bg", &DeleteParams::background())
        .await
        .unwrap();
    let status = answer
        .right()
        .expect("a background delete answers a Status");
    assert_eq!(
        status.status,
        Some(kube::core::response::StatusSummary::Success)
    );
    assert!(jobs.get_opt("bg").await.unwrap().is_none());
    eventually("pods to go", || async {
        pods_of(&pods, "bg").await.is_empty().then_some(())
    })
    .await;
    assert!(!alive(child));
}

fn status_peek(name: &str, marker: &str, dir: &Path, other: &str) -> Job {
    job(&format!(
        r#"
metadata: {{name: {name}}}
spec:
  template:
    spec:
      restartPolicy: Never
      volumes: [{{name: logs, emptyDir: {{}}}}]
      containers:
      - name: c
        image: busybox
        command: [sh, -c]
        args:
        - |
          touch /tmp/status/{marker}
          touch {d}/{marker}.ready
          i=0
          while [ ! -f {d}/{other}.ready ] && [ $$i -lt 200 ]; do sleep 0.05; i=$$((i+1)); done
          ls /tmp/status
        volumeMounts: [{{name: logs, mountPath: /tmp/status, subPath: containers-status}}]
"#,
        d = dir.display()
    ))
}

#[tokio::test]
async fn two_pods_mounting_tmp_status_do_not_see_each_others_files() {
    let dir = tempfile::tempdir().unwrap();
    let (_lk, client) = start(Config::default()).await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let pods: Api<Pod> = Api::namespaced(client, "default");
    let a = format!("lk-test-a-{}", std::process::id());
    let b = format!("lk-test-b-{}", std::process::id());
    jobs.create(
        &PostParams::default(),
        &status_peek("peek-a", &a, dir.path(), &b),
    )
    .await
    .unwrap();
    jobs.create(
        &PostParams::default(),
        &status_peek("peek-b", &b, dir.path(), &a),
    )
    .await
    .unwrap();
    for (job_name, mine) in [("peek-a", &a), ("peek-b", &b)] {
        wait_condition(&jobs, job_name, "Complete").await;
        let pod = one_pod(&pods, job_name).await;
        let log = pods
            .logs(&pod.metadata.name.unwrap(), &LogParams::default())
            .await
            .unwrap();
        assert_eq!(
            log.trim(),
            mine.as_str(),
            "{job_name} saw only its own marker"
        );
    }
    assert!(
        !Path::new("/tmp/status").join(&a).exists(),
        "nothing leaked to the host"
    );
    assert!(
        !Path::new("/tmp/status").join(&b).exists(),
        "nothing leaked to the host"
    );
}

const MINIMAL: &str = r#"
apiVersion: batch/v1
kind: Job
metadata: {name: NAME}
spec:
  template:
    spec:
      restartPolicy: Never
      containers: [{name: c, image: busybox, command: ["true"]}]
"#;

#[tokio::test]
async fn api_errors_are_status_objects_shaped_like_the_real_servers() {
    let config = Config {
        forbidden_namespaces: vec!["kube-system".into()],
        ..Config::default()
    };
    let (lk, client) = start(config).await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let post = |name: &str| serde_json::to_string(&job(&MINIMAL.replace("NAME", name))).unwrap();
    let path = "/apis/batch/v1/namespaces/default/jobs";

    let (code, s) = raw(
        &lk,
        reqwest::Method::POST,
        path,
        None,
        Some(&post("Bad_Name")),
    )
    .await;
    assert_eq!(code, 422);
    assert_eq!(
        (s["kind"].as_str(), s["apiVersion"].as_str()),
        (Some("Status"), Some("v1"))
    );
    assert_eq!(
        (
            s["status"].as_str(),
            s["reason"].as_str(),
            s["code"].as_u64()
        ),
        (Some("Failure"), Some("Invalid"), Some(422))
    );
    assert!(s["message"].as_str().unwrap().starts_with(
        "Job.batch \"Bad_Name\" is invalid: metadata.name: Invalid value: \"Bad_Name\": a lowercase RFC 1123 subdomain must consist of"
    ));
    assert_eq!(s["details"]["causes"][0]["reason"], "FieldValueInvalid");
    assert_eq!(s["details"]["causes"][0]["field"], "metadata.name");
    assert_eq!(
        (
            s["details"]["kind"].as_str(),
            s["details"]["group"].as_str()
        ),
        (Some("Job"), Some("batch"))
    );

    let long = "a".repeat(64);
    let (code, s) = raw(&lk, reqwest::Method::POST, path, None, Some(&post(&long))).await;
    assert_eq!(code, 422);
    assert_eq!(
        s["message"].as_str().unwrap(),
        format!("Job.batch \"{long}\" is invalid: spec.template.labels: Invalid value: \"{long}\": must be no more than 63 bytes")
    );
    assert_eq!(s["details"]["causes"].as_array().unwrap().len(), 2);

    let always = MINIMAL
        .replace("NAME", "always")
        .replace("restartPolicy: Never", "dnsPolicy: ClusterFirst");
    let e = jobs
        .create(&PostParams::default(), &job(&always))
        .await
        .unwrap_err();
    let kube::Error::Api(status) = e else {
        panic!("expected a Status, got {e:?}")
    };
    assert_eq!(status.code, 422);
    assert!(status.message.ends_with(
        "spec.template.spec.restartPolicy: Unsupported value: \"Always\": supported values: \"OnFailure\", \"Never\""
    ), "{}", status.message);

    jobs.create(
        &PostParams::default(),
        &job(&MINIMAL.replace("NAME", "twice")),
    )
    .await
    .unwrap();
    let (code, s) = raw(&lk, reqwest::Method::POST, path, None, Some(&post("twice"))).await;
    assert_eq!(code, 409);
    assert_eq!(s["reason"], "AlreadyExists");
    assert_eq!(s["message"], "jobs.batch \"twice\" already exists");

    let (code, s) = raw(
        &lk,
        reqwest::Method::GET,
        &format!("{path}/missing"),
        None,
        None,
    )
    .await;
    assert_eq!(code, 404);
    assert_eq!(s["message"], "jobs.batch \"missing\" not found");
    assert_eq!(
        (s["details"]["name"].as_str(), s["details"]["kind"].as_str()),
        (Some("missing"), Some("jobs"))
    );
    assert!(jobs.get_opt("missing").await.unwrap().is_none());

    let (code, s) = raw(&lk, reqwest::Method::POST, path, None, Some("{not json")).await;
    assert_eq!(code, 400);
    assert_eq!(s["reason"], "BadRequest");
    let (code, s) = raw(
        &lk,
        reqwest::Method::POST,
        path,
        None,
        Some(r#"{"spec": {"backoffLimit": "six"}}"#),
    )
    .await;
    assert_eq!(code, 400);
    assert!(s["message"]
        .as_str()
        .unwrap()
        .starts_with("Job in version \"v1\" cannot be handled as a Job"));
    let (code, s) = raw(
        &lk,
        reqwest::Method::POST,
        &format!("{path}?fieldValidation=Strict"),
        None,
        Some(&post("strict").replace(
            "\"restartPolicy\"",
            "\"restartPolicyy\":1,\"restartPolicy\"",
        )),
    )
    .await;
    assert_eq!(code, 400, "{s}");
    assert_eq!(
        s["message"],
        "strict decoding error: unknown field \"spec.template.spec.restartPolicyy\""
    );

    let forbidden: Api<Job> = Api::namespaced(client.clone(), "kube-system");
    let e = forbidden.list(&ListParams::default()).await.unwrap_err();
    let kube::Error::Api(status) = e else {
        panic!("expected a Status, got {e:?}")
    };
    assert_eq!((status.code, status.reason.as_str()), (403, "Forbidden"));
    assert_eq!(
        status.message,
        "jobs.batch is forbidden: User \"local-kube\" cannot list resource \"jobs\" in API group \"batch\" in the namespace \"kube-system\""
    );

    let (code, s) = raw(
        &lk,
        reqwest::Method::GET,
        &format!("{path}?watch=true&resourceVersion=bogus"),
        None,
        None,
    )
    .await;
    assert_eq!((code, s["reason"].as_str()), (400, Some("BadRequest")));
    let (code, s) = raw(
        &lk,
        reqwest::Method::PUT,
        &format!("{path}/twice"),
        None,
        Some("{}"),
    )
    .await;
    assert_eq!(
        (code, s["reason"].as_str()),
        (405, Some("MethodNotAllowed"))
    );
    let (code, s) = raw(
        &lk,
        reqwest::Method::GET,
        "/apis/apps/v1/deployments",
        None,
        None,
    )
    .await;
    assert_eq!((code, s["reason"].as_str()), (404, Some("NotFound")));
    let (code, ns) = raw(
        &lk,
        reqwest::Method::GET,
        "/api/v1/namespaces/anything-goes",
        None,
        None,
    )
    .await;
    assert_eq!(
        (code, ns["kind"].as_str(), ns["status"]["phase"].as_str()),
        (200, Some("Namespace"), Some("Active"))
    );
}

#[tokio::test]
async fn a_wrong_or_missing_bearer_token_is_answered_401() {
    let config = Config {
        token: Some("s3cr3t".into()),
        ..Config::default()
    };
    let (lk, client) = start(config).await;
    let jobs: Api<Job> = Api::namespaced(client, "default");
    assert!(jobs
        .list(&ListParams::default())
        .await
        .unwrap()
        .items
        .is_empty());
    let path = "/apis/batch/v1/namespaces/default/jobs";
    for token in [Some("wrong"), None] {
        let (code, s) = raw(&lk, reqwest::Method::GET, path, token, None).await;
        assert_eq!(code, 401);
        assert_eq!(
            (s["reason"].as_str(), s["message"].as_str()),
            (Some("Unauthorized"), Some("Unauthorized"))
        );
    }
    let wrong = lk.kubeconfig_yaml().replace("s3cr3t", "nope");
    let bad: Api<Job> = Api::namespaced(client_for(&wrong).await, "default");
    let e = bad.list(&ListParams::default()).await.unwrap_err();
    assert!(
        matches!(e, kube::Error::Api(ref s) if s.code == 401),
        "{e:?}"
    );
}

#[tokio::test]
async fn label_selectors_list_the_matching_jobs_and_pods() {
    let (lk, client) = start(Config::default()).await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let pods: Api<Pod> = Api::namespaced(client.clone(), "default");
    for (name, sub, role) in [("j1", "1", "sim"), ("j2", "1", "agent"), ("j3", "2", "sim")] {
        let mut j = job(&MINIMAL.replace("NAME", name));
        j.metadata.labels = Some(
            [
                ("submission".into(), sub.into()),
                ("role".into(), role.into()),
            ]
            .into(),
        );
        jobs.create(&PostParams::default(), &j).await.unwrap();
    }
    jobs.create(
        &PostParams::default(),
        &job(&MINIMAL.replace("NAME", "bare")),
    )
    .await
    .unwrap();
    let names = |sel: &'static str| {
        let jobs = jobs.clone();
        async move {
            let mut n: Vec<String> = jobs
                .list(&ListParams::default().labels(sel))
                .await
                .unwrap()
                .items
                .into_iter()
                .map(|j| j.metadata.name.unwrap())
                .collect();
            n.sort();
            n
        }
    };
    assert_eq!(names("submission=1").await, ["j1", "j2"]);
    assert_eq!(names("submission==1,role=sim").await, ["j1"]);
    assert_eq!(names("submission!=1").await, ["bare", "j3"]);
    assert_eq!(names("submission").await, ["j1", "j2", "j3"]);
    assert_eq!(names("!submission").await, ["bare"]);
    assert_eq!(names("role in (agent, other)").await, ["j2"]);
    assert_eq!(names("role notin (agent)").await, ["bare", "j1", "j3"]);
    let by_field = jobs
        .list(&ListParams::default().fields("metadata.name=j3"))
        .await
        .unwrap();
    assert_eq!(by_field.items.len(), 1);
    let paged = jobs.list(&ListParams::default().limit(2)).await.unwrap();
    assert_eq!(paged.items.len(), 2);
    let token = paged.metadata.continue_.clone().expect("a continue token");
    let rest = jobs
        .list(&ListParams::default().limit(2).continue_token(&token))
        .await
        .unwrap();
    assert_eq!(rest.items.len(), 2);
    assert!(rest.metadata.continue_.is_none());

    let j1 = jobs.get("j1").await.unwrap();
    let uid = j1.metadata.uid.clone().unwrap();
    for selector in [
        "job-name=j1".to_owned(),
        "batch.kubernetes.io/job-name=j1".to_owned(),
        format!("controller-uid={uid}"),
        format!("batch.kubernetes.io/controller-uid={uid}"),
    ] {
        let owned = eventually(&selector, || async {
            let items = pods
                .list(&ListParams::default().labels(&selector))
                .await
                .ok()?
                .items;
            (!items.is_empty()).then_some(items)
        })
        .await;
        assert_eq!(owned.len(), 1, "{selector}");
        assert!(owned[0]
            .metadata
            .name
            .as_deref()
            .unwrap()
            .starts_with("j1-"));
    }
    let pod_name = pods_of(&pods, "j1").await[0].metadata.name.clone().unwrap();
    let suffix = pod_name.strip_prefix("j1-").unwrap();
    assert_eq!(suffix.len(), 5);
    assert!(suffix
        .bytes()
        .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit()));
    let (code, s) = raw(
        &lk,
        reqwest::Method::DELETE,
        "/apis/batch/v1/namespaces/default/jobs/j3?propagationPolicy=Background",
        None,
        None,
    )
    .await;
    assert_eq!(
        (code, s["kind"].as_str(), s["status"].as_str()),
        (200, Some("Status"), Some("Success"))
    );
    assert_eq!(s["details"]["uid"].as_str().map(str::len), Some(36));
    let all: Api<Pod> = Api::all(client);
    assert_eq!(
        all.list(&ListParams::default().labels("job-name in (j1,j2)"))
            .await
            .unwrap()
            .items
            .len(),
        2
    );
}

#[tokio::test]
async fn variables_expand_and_field_refs_resolve_in_env_and_args() {
    let (_lk, client) = start(Config::default()).await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let pods: Api<Pod> = Api::namespaced(client, "default");
    let manifest = r#"
metadata: {name: env-check, labels: {submission: "77"}}
spec:
  template:
    metadata: {labels: {submission: "77"}}
    spec:
      restartPolicy: Never
      containers:
      - name: c
        image: busybox
        env:
        - {name: CARLA_PORT, value: "2000"}
        - {name: CARLA_TM_PORT, value: "$(CARLA_PORT)0"}
        - {name: POD_NAME, valueFrom: {fieldRef: {fieldPath: metadata.name}}}
        - {name: POD_NS, valueFrom: {fieldRef: {fieldPath: metadata.namespace}}}
        - {name: SUBMISSION, valueFrom: {fieldRef: {fieldPath: "metadata.labels['submission']"}}}
        - {name: NODE, valueFrom: {fieldRef: {fieldPath: spec.nodeName}}}
        - {name: POD_IP, valueFrom: {fieldRef: {fieldPath: status.podIP}}}
        - {name: UNKNOWN, value: "$(NOPE)"}
        - {name: LITERAL, value: "$$(CARLA_PORT)"}
        command: [sh, -c]
        args: ['echo "rpc=$(CARLA_PORT) tm=$CARLA_TM_PORT pod=$POD_NAME ns=$POD_NS sub=$SUBMISSION node=$NODE ip=$POD_IP lit=$LITERAL unknown=$UNKNOWN"; pwd']
        workingDir: /
"#;
    jobs.create(&PostParams::default(), &job(manifest))
        .await
        .unwrap();
    wait_condition(&jobs, "env-check", "Complete").await;
    let pod = one_pod(&pods, "env-check").await;
    let name = pod.metadata.name.clone().unwrap();
    let log = pods.logs(&name, &LogParams::default()).await.unwrap();
    assert_eq!(
        log,
        format!("rpc=2000 tm=20000 pod={name} ns=default sub=77 node=local-kube ip=127.0.0.1 lit=$(CARLA_PORT) unknown=$(NOPE)\n/\n")
    );
}

#[tokio::test]
async fn an_unpullable_image_leaves_the_pod_pending_with_err_image_pull_then_image_pull_back_off() {
    let images =
        ImageMap::from_yaml("'registry.example/private:1': {pull: fail}", Path::new("/")).unwrap();
    let mut config = Config {
        images,
        ..Config::default()
    };
    config.timing.image_pull_backoff = Duration::from_millis(200);
    let (_lk, client) = start(config).await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let pods: Api<Pod> = Api::namespaced(client, "default");
    let mut j = job(&MINIMAL.replace("NAME", "no-pull"));
    first_container(&mut j).image = Some("registry.example/private:1".into());
    jobs.create(&PostParams::default(), &j).await.unwrap();
    let mut unknown = job(&MINIMAL.replace("NAME", "no-command"));
    let c = first_container(&mut unknown);
    c.image = Some("carlasim/carla:0.9.15".into());
    c.command = None;
    jobs.create(&PostParams::default(), &unknown).await.unwrap();
    for reason in ["ErrImagePull", "ImagePullBackOff"] {
        let pod = eventually(reason, || async {
            let pod = pods_of(&pods, "no-pull").await.into_iter().next()?;
            let w = container(&pod, "c")?
                .state
                .as_ref()?
                .waiting
                .as_ref()?
                .reason
                .clone()?;
            (w == reason).then_some(pod)
        })
        .await;
        assert_eq!(
            pod.status.as_ref().unwrap().phase.as_deref(),
            Some("Pending")
        );
        let c = container(&pod, "c").unwrap();
        assert!(c
            .state
            .as_ref()
            .unwrap()
            .waiting
            .as_ref()
            .unwrap()
            .message
            .as_deref()
            .unwrap()
            .contains("registry.example/private:1"));
    }
    let waiting = eventually("no-command waiting", || async {
        let pod = pods_of(&pods, "no-command").await.into_iter().next()?;
        container(&pod, "c")?
            .state
            .as_ref()?
            .waiting
            .as_ref()?
            .message
            .clone()
    })
    .await;
    assert!(
        waiting.contains("\"carlasim/carla:0.9.15\" is not in the image map"),
        "{waiting}"
    );
    let name = pods_of(&pods, "no-pull").await[0]
        .metadata
        .name
        .clone()
        .unwrap();
    let e = pods.logs(&name, &LogParams::default()).await.unwrap_err();
    assert!(
        matches!(e, kube::Error::Api(ref s) if s.code == 400 && s.message.contains("is waiting to start")),
        "{e:?}"
    );
    let job = jobs.get("no-pull").await.unwrap();
    assert_eq!(job.status.unwrap().active, Some(1));
}

#[tokio::test]
async fn the_image_map_supplies_entrypoint_env_path_working_dir_and_files() {
    let dir = tempfile::tempdir().unwrap();
    let fake = dir.path().join("fake-carla.sh");
    std::fs::write(&fake, "#!/bin/sh\necho \"carla args: $*\"\necho \"image env: $IMAGE_VAR\"\necho \"cwd: $(pwd)\"\nhello-tool\n").unwrap();
    let bin = dir.path().join("bin");
    std::fs::create_dir(&bin).unwrap();
    std::fs::write(bin.join("hello-tool"), "#!/bin/sh\necho tool on PATH\n").unwrap();
    use std::os::unix::fs::PermissionsExt;
    for p in [&fake, &bin.join("hello-tool")] {
        std::fs::set_permissions(p, std::fs::Permissions::from_mode(0o755)).unwrap();
    }
    let home = dir.path().join("rootfs/home/carla");
    let map = format!(
        r#"
"carlasim/carla:0.9.15":
  command: ["{home}/CarlaUE4.sh"]
  env: {{IMAGE_VAR: from-image}}
  workingDir: {home}
  files: {{fake-carla.sh: {home}/CarlaUE4.sh}}
  path: [bin]
"#,
        home = home.display()
    );
    std::fs::write(dir.path().join("images.yaml"), map).unwrap();
    let images = ImageMap::from_path(&dir.path().join("images.yaml")).unwrap();
    let (_lk, client) = start(Config {
        images,
        ..Config::default()
    })
    .await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let pods: Api<Pod> = Api::namespaced(client, "default");
    let manifest = r#"
metadata: {name: carla}
spec:
  template:
    spec:
      restartPolicy: Never
      containers:
      - name: simulator-1
        image: carlasim/carla:0.9.15
        args: ["-carla-rpc-port=$(CARLA_PORT)", "-RenderOffScreen"]
        env: [{name: CARLA_PORT, value: "2000"}]
"#;
    jobs.create(&PostParams::default(), &job(manifest))
        .await
        .unwrap();
    wait_condition(&jobs, "carla", "Complete").await;
    let pod = one_pod(&pods, "carla").await;
    let log = pods
        .logs(&pod.metadata.name.unwrap(), &LogParams::default())
        .await
        .unwrap();
    assert_eq!(
        log,
        format!(
            "carla args: -carla-rpc-port=2000 -RenderOffScreen\nimage env: from-image\ncwd: {}\ntool on PATH\n",
            home.display()
        )
    );
    let c = container(&one_pod(&pods, "carla").await, "simulator-1")
        .unwrap()
        .clone();
    assert!(c.image_id.starts_with("carlasim/carla:0.9.15@sha256:"));
    assert!(c.container_id.is_some());
    assert_eq!(
        std::fs::metadata(home.join("CarlaUE4.sh")).unwrap().len(),
        0,
        "on the host only the empty mount point exists"
    );
}

#[tokio::test]
async fn watches_stream_job_changes_from_a_resource_version() {
    let (lk, client) = start(Config::default()).await;
    let jobs: Api<Job> = Api::namespaced(client, "default");
    let before = jobs
        .list(&ListParams::default())
        .await
        .unwrap()
        .metadata
        .resource_version
        .unwrap();
    let mut resp = reqwest::Client::new()
        .get(format!(
            "{}/apis/batch/v1/namespaces/default/jobs?watch=true&resourceVersion={before}&timeoutSeconds=10",
            lk.url()
        ))
        .send()
        .await
        .unwrap();
    assert_eq!(resp.status().as_u16(), 200);
    jobs.create(
        &PostParams::default(),
        &job(&MINIMAL.replace("NAME", "watched")),
    )
    .await
    .unwrap();
    let mut buf = String::new();
    let deadline = Instant::now() + WAIT;
    while !buf.contains("\"Complete\"") {
        assert!(Instant::now() < deadline, "no Complete event in {buf}");
        match tokio::time::timeout(WAIT, resp.chunk())
            .await
            .unwrap()
            .unwrap()
        {
            Some(chunk) => buf.push_str(&String::from_utf8_lossy(&chunk)),
            None => panic!("watch ended early: {buf}"),
        }
    }
    let events: Vec<Value> = buf
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(events[0]["type"], "ADDED");
    assert_eq!(events[0]["object"]["kind"], "Job");
    assert!(events.iter().skip(1).all(|e| e["type"] == "MODIFIED"));
    let rvs: Vec<u64> = events
        .iter()
        .map(|e| {
            e["object"]["metadata"]["resourceVersion"]
                .as_str()
                .unwrap()
                .parse()
                .unwrap()
        })
        .collect();
    assert!(
        rvs.windows(2).all(|w| w[0] < w[1]),
        "increasing resourceVersions {rvs:?}"
    );
}

#[test]
fn a_spawned_server_shuts_down_killing_every_process_and_removing_its_state() {
    let dir = tempfile::tempdir().unwrap();
    let mut lk = LocalKube::spawn(Config::default()).unwrap();
    let pods_dir = lk.pods_dir();
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let child = rt.block_on(async {
        let client = client_for(&lk.kubeconfig_yaml()).await;
        let jobs: Api<Job> = Api::namespaced(client, "default");
        jobs.create(&PostParams::default(), &sleeper("left-running", dir.path()))
            .await
            .unwrap();
        read_pid(&dir.path().join("child")).await
    });
    let pid = std::fs::read_to_string(dir.path().join("pid"))
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    assert!(alive(pid) && alive(child));
    let started = Instant::now();
    lk.shutdown();
    assert!(
        started.elapsed() < Duration::from_secs(8),
        "bounded shutdown"
    );
    assert!(!alive(pid) && !alive(child), "processes survived shutdown");
    assert!(!pods_dir.exists(), "state directory removed");
    let refused = rt.block_on(async {
        tokio::time::timeout(
            Duration::from_secs(5),
            reqwest::get(format!("{}/version", lk.url())),
        )
        .await
    });
    assert!(matches!(refused, Ok(Err(_))), "server stopped listening");
}

#[tokio::test]
async fn init_containers_run_in_order_and_host_paths_and_read_only_mounts_work() {
    let (_lk, client) = start(Config::default()).await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let pods: Api<Pod> = Api::namespaced(client, "default");
    let manifest = r#"
metadata: {name: with-init}
spec:
  template:
    spec:
      restartPolicy: OnFailure
      volumes: [{name: work, emptyDir: {}}, {name: host, hostPath: {path: HOSTDIR, type: Directory}}]
      initContainers:
      - {name: first, image: busybox, command: [sh, -c, 'sleep 0.2; echo first >> /w/order'], volumeMounts: [{name: work, mountPath: /w}]}
      - {name: second, image: busybox, command: [sh, -c, 'echo second >> /w/order'], volumeMounts: [{name: work, mountPath: /w}]}
      containers:
      - name: main
        image: busybox
        command: [sh, -c, 'echo main >> /w/order; cat /w/order; cat /host/greeting; (touch /ro/x 2>/dev/null && echo writable) || echo read-only']
        volumeMounts: [{name: work, mountPath: /w}, {name: host, mountPath: /host}, {name: work, mountPath: /ro, readOnly: true}]
"#;
    let host = tempfile::tempdir().unwrap();
    std::fs::write(host.path().join("greeting"), "from the host\n").unwrap();
    let manifest = manifest.replace("HOSTDIR", host.path().to_str().unwrap());
    jobs.create(&PostParams::default(), &job(&manifest))
        .await
        .unwrap();
    let initializing = eventually("the pod to initialize", || async {
        let pod = pods_of(&pods, "with-init").await.into_iter().next()?;
        let waiting = container(&pod, "main")?
            .state
            .as_ref()?
            .waiting
            .as_ref()?
            .reason
            .clone()?;
        (waiting == "PodInitializing").then_some(pod)
    })
    .await;
    assert_eq!(
        initializing.status.as_ref().unwrap().phase.as_deref(),
        Some("Pending")
    );
    wait_condition(&jobs, "with-init", "Complete").await;
    let pod = one_pod(&pods, "with-init").await;
    let inits = pod
        .status
        .as_ref()
        .unwrap()
        .init_container_statuses
        .clone()
        .unwrap();
    assert_eq!(inits.len(), 2);
    for s in &inits {
        let t = s.state.as_ref().unwrap().terminated.as_ref().unwrap();
        assert_eq!((t.exit_code, t.reason.as_deref()), (0, Some("Completed")));
    }
    let log = pods
        .logs(&pod.metadata.name.unwrap(), &LogParams::default())
        .await
        .unwrap();
    assert_eq!(log, "first\nsecond\nmain\nfrom the host\nread-only\n");
}

#[tokio::test]
async fn deleting_a_job_without_a_policy_orphans_its_pods_as_a_real_cluster_does() {
    let dir = tempfile::tempdir().unwrap();
    let (_lk, client) = start(Config::default()).await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let pods: Api<Pod> = Api::namespaced(client, "default");
    jobs.create(&PostParams::default(), &sleeper("orphaning", dir.path()))
        .await
        .unwrap();
    let child = read_pid(&dir.path().join("child")).await;
    let answer = jobs
        .delete("orphaning", &DeleteParams::default())
        .await
        .unwrap();
    assert!(answer.is_right(), "the job is gone at once");
    let orphan = one_pod(&pods, "orphaning").await;
    assert!(orphan.metadata.owner_references.is_none());
    assert!(alive(child), "orphaned pods keep running");
    let name = orphan.metadata.name.clone().unwrap();
    let deleted = pods.delete(&name, &DeleteParams::default()).await.unwrap();
    let marked = deleted
        .left()
        .expect("a pod delete answers the terminating pod");
    assert!(marked.metadata.deletion_timestamp.is_some());
    eventually("the pod to go", || async {
        pods.get_opt(&name).await.unwrap().is_none().then_some(())
    })
    .await;
    assert!(!alive(child));
}

#[tokio::test]
async fn deleting_a_running_pod_counts_it_as_failed_and_the_job_replaces_it() {
    let dir = tempfile::tempdir().unwrap();
    let (_lk, client) = start(Config::default()).await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let pods: Api<Pod> = Api::namespaced(client, "default");
    jobs.create(&PostParams::default(), &sleeper("replaced", dir.path()))
        .await
        .unwrap();
    read_pid(&dir.path().join("child")).await;
    let first = one_pod(&pods, "replaced").await.metadata.name.unwrap();
    pods.delete(&first, &DeleteParams::default()).await.unwrap();
    let second = eventually("a replacement pod", || async {
        let names: Vec<String> = pods_of(&pods, "replaced")
            .await
            .into_iter()
            .filter_map(|p| p.metadata.name)
            .collect();
        names.into_iter().find(|n| *n != first)
    })
    .await;
    assert_ne!(second, first);
    let failed = eventually("failed=1", || async {
        let j = jobs.get("replaced").await.ok()?;
        j.status?.failed.filter(|f| *f == 1)
    })
    .await;
    assert_eq!(failed, 1);
    jobs.delete("replaced", &DeleteParams::background())
        .await
        .unwrap();
}

#[tokio::test]
async fn without_isolation_containers_run_but_mounts_are_a_clear_configuration_error() {
    let config = Config {
        isolation: local_kube::Isolation::None,
        ..Config::default()
    };
    let (_lk, client) = start(config).await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let pods: Api<Pod> = Api::namespaced(client, "default");
    jobs.create(
        &PostParams::default(),
        &job(&MINIMAL.replace("NAME", "plain")),
    )
    .await
    .unwrap();
    wait_condition(&jobs, "plain", "Complete").await;
    let mounting = r#"
metadata: {name: mounting}
spec:
  template:
    spec:
      restartPolicy: Never
      volumes: [{name: v, emptyDir: {}}]
      containers: [{name: c, image: busybox, command: ["true"], volumeMounts: [{name: v, mountPath: /tmp/status}]}]
"#;
    jobs.create(&PostParams::default(), &job(mounting))
        .await
        .unwrap();
    let (reason, message) = eventually("a configuration error", || async {
        let pod = pods_of(&pods, "mounting").await.into_iter().next()?;
        let w = container(&pod, "c")?.state.as_ref()?.waiting.clone()?;
        let (reason, message) = (w.reason?, w.message?);
        (reason == "CreateContainerConfigError").then_some((reason, message))
    })
    .await;
    assert_eq!(reason, "CreateContainerConfigError");
    assert!(message.contains("without mount namespaces"), "{message}");
}

/// The apiserver answers 500 `InternalError` (`Internal error occurred: ...`, its cause in
/// `details.causes`) when its storage fails; health endpoints and the running Jobs are not
/// the API and go on.
#[tokio::test]
async fn an_injected_outage_answers_500_internal_error_then_ends() {
    let (lk, client) = start(Config::default()).await;
    let jobs: Api<Job> = Api::namespaced(client, "default");
    jobs.list(&ListParams::default()).await.expect("up before");
    lk.fail_requests_for(Duration::from_millis(400));
    let (code, body) = raw(
        &lk,
        reqwest::Method::GET,
        "/apis/batch/v1/namespaces/default/jobs",
        None,
        None,
    )
    .await;
    assert_eq!(code, 500);
    assert_eq!(body["kind"], "Status");
    assert_eq!(body["reason"], "InternalError");
    assert_eq!(body["code"], 500);
    assert_eq!(
        body["message"],
        "Internal error occurred: etcdserver: request timed out"
    );
    assert_eq!(
        body["details"]["causes"][0]["message"],
        "etcdserver: request timed out"
    );
    match jobs.list(&ListParams::default()).await {
        Err(kube::Error::Api(status)) => assert_eq!(status.code, 500),
        other => panic!("expected a 500, got {other:?}"),
    }
    let (code, _) = raw(&lk, reqwest::Method::GET, "/healthz", None, None).await;
    assert_eq!(code, 200);
    eventually("the outage to end", || async {
        jobs.list(&ListParams::default()).await.ok()
    })
    .await;
}

/// local-kube with a node of `gpus` GPUs, and its Jobs and Pods in `default`.
async fn gpu_node(gpus: u32) -> (LocalKube, Api<Job>, Api<Pod>) {
    let (lk, client) = start(Config {
        gpus: Some(gpus),
        ..Config::default()
    })
    .await;
    let jobs = Api::namespaced(client.clone(), "default");
    (lk, jobs, Api::namespaced(client, "default"))
}

/// A Job of one container that requests `gpus` and runs `script`.
fn gpu_job(name: &str, gpus: u32, script: &str) -> Job {
    job(&format!(
        r#"
apiVersion: batch/v1
kind: Job
metadata: {{name: {name}}}
spec:
  backoffLimit: 0
  template:
    spec:
      restartPolicy: Never
      terminationGracePeriodSeconds: 1
      containers:
      - name: work
        image: busybox
        command: [sh, -c, "{script}"]
        resources: {{limits: {{nvidia.com/gpu: {gpus}}}}}
"#
    ))
}

fn scheduled(pod: &Pod) -> Option<k8s_openapi::api::core::v1::PodCondition> {
    pod.status
        .as_ref()?
        .conditions
        .as_ref()?
        .iter()
        .find(|c| c.type_ == "PodScheduled")
        .cloned()
}

/// As the real scheduler: a pod whose `nvidia.com/gpu` does not fit the node's free GPUs stays
/// Pending, unbound, with `PodScheduled=False`, reason `Unschedulable` and its message, and
/// is bound when room frees; one larger than the node waits for good.
#[tokio::test]
async fn pods_wait_pending_unschedulable_until_the_nodes_gpus_free() {
    let (_lk, jobs, pods) = gpu_node(2).await;
    let pp = PostParams::default();
    jobs.create(&pp, &gpu_job("first", 2, "sleep 1"))
        .await
        .unwrap();
    jobs.create(&pp, &gpu_job("second", 1, "true"))
        .await
        .unwrap();
    jobs.create(&pp, &gpu_job("too-big", 3, "true"))
        .await
        .unwrap();

    let first = one_pod(&pods, "first").await;
    assert_eq!(
        first.spec.as_ref().unwrap().node_name.as_deref(),
        Some("local-kube")
    );
    assert_eq!(scheduled(&first).unwrap().status, "True");
    for name in ["second", "too-big"] {
        let pod = one_pod(&pods, name).await;
        assert_eq!(pod.spec.as_ref().unwrap().node_name, None, "{name}");
        assert_eq!(
            pod.status.as_ref().unwrap().phase.as_deref(),
            Some("Pending")
        );
        let c = scheduled(&pod).unwrap();
        assert_eq!(
            (c.status.as_str(), c.reason.as_deref(), c.message.as_deref()),
            (
                "False",
                Some("Unschedulable"),
                Some(local_kube::INSUFFICIENT_GPU)
            ),
            "{name}"
        );
        assert!(pod.status.as_ref().unwrap().container_statuses.is_none());
    }

    // `first` ends: its 2 GPUs go to `second`, which runs and completes.
    wait_condition(&jobs, "first", "Complete").await;
    wait_condition(&jobs, "second", "Complete").await;
    let second = one_pod(&pods, "second").await;
    assert_eq!(scheduled(&second).unwrap().status, "True");
    // No node could ever hold 3: still waiting.
    let big = one_pod(&pods, "too-big").await;
    assert_eq!(big.spec.as_ref().unwrap().node_name, None);
    assert_eq!(
        scheduled(&big).unwrap().reason.as_deref(),
        Some("Unschedulable")
    );
    // Deleting a pending pod's Job is clean.
    jobs.delete("too-big", &DeleteParams::foreground())
        .await
        .unwrap();
    eventually("too-big gone", || async {
        pods_of(&pods, "too-big").await.is_empty().then_some(())
    })
    .await;
}

/// As the NVIDIA device plugin and container toolkit: a container that requested GPUs finds
/// their UUIDs in `NVIDIA_VISIBLE_DEVICES` (its spec's own value overridden), two pods never
/// get the same GPU, and `nvidia-smi` lists what the variable makes visible (`all`: the node's).
#[tokio::test]
async fn containers_get_their_own_gpus_by_uuid_and_nvidia_smi_lists_the_visible_ones() {
    let (_lk, jobs, pods) = gpu_node(3).await;
    let pp = PostParams::default();
    let show = "echo visible=$NVIDIA_VISIBLE_DEVICES; nvidia-smi --query-gpu=index,uuid --format=csv,noheader; sleep 1";
    for name in ["one", "two"] {
        jobs.create(&pp, &gpu_job(name, 1, show)).await.unwrap();
    }
    let mut all = gpu_job("all", 0, show);
    let c = first_container(&mut all);
    c.resources = None;
    c.env = Some(vec![k8s_openapi::api::core::v1::EnvVar {
        name: "NVIDIA_VISIBLE_DEVICES".into(),
        value: Some("all".into()),
        ..Default::default()
    }]);
    jobs.create(&pp, &all).await.unwrap();
    let mut seen = Vec::new();
    for name in ["one", "two", "all"] {
        wait_condition(&jobs, name, "Complete").await;
        let pod = one_pod(&pods, name).await;
        let log = pods
            .logs(&pod.metadata.name.unwrap(), &LogParams::default())
            .await
            .unwrap();
        seen.push(log);
    }
    let uuid = |i: u32| format!("GPU-6c6f6361-6c6b-4b75-8265-{i:012x}");
    let visible = |log: &str| {
        log.lines()
            .next()
            .unwrap()
            .trim_start_matches("visible=")
            .to_owned()
    };
    let (one, two) = (visible(&seen[0]), visible(&seen[1]));
    assert_ne!(one, two, "two pods share a GPU");
    for (log, v) in [(&seen[0], &one), (&seen[1], &two)] {
        assert!([uuid(0), uuid(1)].contains(v), "{log}");
        // nvidia-smi shows the container's one GPU, with its node index.
        let rows: Vec<&str> = log.lines().skip(1).collect();
        assert_eq!(rows.len(), 1, "{log}");
        assert!(rows[0].ends_with(v.as_str()), "{log}");
    }
    assert_eq!(
        seen[2].lines().skip(1).collect::<Vec<_>>(),
        [0, 1, 2].map(|i| format!("{i}, {}", uuid(i)))
    );
}

/// A pair's Job as the templates make it: `restartPolicy: Never`, a disrupted pod ignored, the
/// sidecar's exits no retry can change ending the Job at once, a new pod only once the old one
/// has failed. The pod counts its attempts in `dir` and takes 1 s to stop on SIGTERM.
fn pair_job(name: &str, dir: &Path, backoff_limit: u32, exit: u32) -> Job {
    job(&format!(
        r#"
metadata: {{name: {name}}}
spec:
  backoffLimit: {backoff_limit}
  podReplacementPolicy: Failed
  podFailurePolicy:
    rules:
    - action: Ignore
      onPodConditions: [{{type: DisruptionTarget, status: "True"}}]
    - action: FailJob
      onExitCodes: {{operator: In, values: [3, 78]}}
  template:
    spec:
      restartPolicy: Never
      terminationGracePeriodSeconds: 5
      containers:
      - name: agent-1
        image: busybox
        command: [sh, -c]
        args: ['echo x >> {d}/attempts; echo $$$$ > {d}/pid; trap "sleep 1; exit 1" TERM; if [ {exit} -ne 0 ]; then exit {exit}; fi; sleep 300 & wait']
"#,
        d = dir.display()
    ))
}

fn disruption(pod: &Pod) -> Option<(String, String)> {
    let c = pod
        .status
        .as_ref()?
        .conditions
        .iter()
        .flatten()
        .find(|c| c.type_ == "DisruptionTarget" && c.status == "True")?;
    Some((c.reason.clone()?, c.message.clone()?))
}

#[tokio::test]
async fn an_evicted_pod_is_replaced_once_it_has_stopped_without_counting_against_backoff_limit() {
    let dir = tempfile::tempdir().unwrap();
    let (lk, client) = start(Config::default()).await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let pods: Api<Pod> = Api::namespaced(client, "default");
    // backoffLimit 0: a single counted failure would fail the Job.
    jobs.create(
        &PostParams::default(),
        &pair_job("reclaimed", dir.path(), 0, 0),
    )
    .await
    .unwrap();
    read_pid(&dir.path().join("pid")).await;
    let first = one_pod(&pods, "reclaimed").await.metadata.name.unwrap();
    let path = format!("/api/v1/namespaces/default/pods/{first}/eviction");
    let body = format!(
        r#"{{"apiVersion":"policy/v1","kind":"Eviction","metadata":{{"name":"{first}","namespace":"default"}}}}"#
    );
    let (code, status) = raw(&lk, reqwest::Method::POST, &path, None, Some(&body)).await;
    assert_eq!(
        (code, status["status"].as_str()),
        (201, Some("Success")),
        "{status}"
    );

    // Terminating, with the condition the API server writes; no replacement beside it.
    let evicted = pods.get(&first).await.unwrap();
    assert!(evicted.metadata.deletion_timestamp.is_some());
    assert_eq!(
        disruption(&evicted),
        Some((
            "EvictionByEvictionAPI".into(),
            "Eviction API: evicting".into()
        ))
    );
    assert_eq!(
        pods_of(&pods, "reclaimed").await.len(),
        1,
        "no pod beside a terminating one"
    );

    let second = eventually("a replacement pod", || async {
        let now = pods_of(&pods, "reclaimed").await;
        now.into_iter()
            .filter_map(|p| p.metadata.name)
            .find(|n| *n != first)
    })
    .await;
    assert_ne!(second, first);
    eventually("the second attempt", || async {
        let attempts = std::fs::read_to_string(dir.path().join("attempts")).ok()?;
        (attempts.lines().count() == 2).then_some(())
    })
    .await;
    let job = jobs.get("reclaimed").await.unwrap();
    let status = job.status.unwrap();
    assert_eq!(
        status.failed.unwrap_or(0),
        0,
        "the eviction is not a failure"
    );
    assert!(condition(&jobs.get("reclaimed").await.unwrap(), "Failed").is_none());
    // The evicted pod is gone once counted; its finalizer went with it.
    assert!(pods.get_opt(&first).await.unwrap().is_none());
    jobs.delete("reclaimed", &DeleteParams::background())
        .await
        .unwrap();

    // A pod failing by itself counts, and with backoffLimit 0 that fails the Job.
    let (code, _) = raw(
        &lk,
        reqwest::Method::POST,
        "/api/v1/namespaces/default/pods/nope/eviction",
        None,
        Some(r#"{"apiVersion":"policy/v1","kind":"Eviction","metadata":{"name":"nope"}}"#),
    )
    .await;
    assert_eq!(code, 404);
}

#[tokio::test]
async fn a_fail_job_exit_ends_the_job_at_once_with_the_rule_in_its_reason() {
    let dir = tempfile::tempdir().unwrap();
    let (_lk, client) = start(Config::default()).await;
    let jobs: Api<Job> = Api::namespaced(client.clone(), "default");
    let pods: Api<Pod> = Api::namespaced(client, "default");
    jobs.create(
        &PostParams::default(),
        &pair_job("unrunnable", dir.path(), 4, 3),
    )
    .await
    .unwrap();
    let failed = wait_condition(&jobs, "unrunnable", "Failed").await;
    let cond = condition(&failed, "Failed").unwrap();
    assert_eq!(cond.reason.as_deref(), Some("PodFailurePolicy"));
    let pod = one_pod(&pods, "unrunnable").await.metadata.name.unwrap();
    assert_eq!(
        cond.message.as_deref(),
        Some(format!("Container agent-1 for pod default/{pod} failed with exit code 3 matching FailJob rule at index 1").as_str())
    );
    assert_eq!(failed.status.unwrap().failed, Some(1));
    let attempts = std::fs::read_to_string(dir.path().join("attempts")).unwrap();
    assert_eq!(attempts.lines().count(), 1, "no retry of 4 was made");

    // Exit 1 is an ordinary crash: counted, and a new pod follows.
    jobs.create(
        &PostParams::default(),
        &pair_job("crashes", dir.path(), 1, 1),
    )
    .await
    .unwrap();
    let failed = wait_condition(&jobs, "crashes", "Failed").await;
    assert_eq!(
        condition(&failed, "Failed").unwrap().reason.as_deref(),
        Some("BackoffLimitExceeded")
    );
    assert_eq!(failed.status.unwrap().failed, Some(2));
}

#[tokio::test]
async fn a_failure_policy_needs_restart_policy_never_as_the_real_server_says() {
    let (lk, _client) = start(Config::default()).await;
    let dir = tempfile::tempdir().unwrap();
    let mut bad = serde_json::to_value(pair_job("bad", dir.path(), 1, 0)).unwrap();
    bad["spec"]["template"]["spec"]["restartPolicy"] = "OnFailure".into();
    bad["spec"]["podFailurePolicy"]["rules"][1]["onExitCodes"]["values"] =
        serde_json::json!([78, 3]);
    let (code, status) = raw(
        &lk,
        reqwest::Method::POST,
        "/apis/batch/v1/namespaces/default/jobs",
        None,
        Some(&bad.to_string()),
    )
    .await;
    assert_eq!(code, 422, "{status}");
    let message = status["message"].as_str().unwrap();
    assert!(
        message.contains(r#"spec.template.spec.restartPolicy: Invalid value: "OnFailure": only "Never" is supported when podFailurePolicy is specified"#),
        "{message}"
    );
    assert!(
        message.contains("spec.podFailurePolicy.rules[1].onExitCodes.values[1]: Invalid value: 3: must be ordered"),
        "{message}"
    );
}

#[tokio::test]
async fn the_node_shows_its_node_groups_labels_and_its_gpus() {
    let mut labels = std::collections::BTreeMap::new();
    labels.insert(
        "eks.amazonaws.com/capacityType".to_string(),
        "SPOT".to_string(),
    );
    let (_lk, client) = start(Config {
        gpus: Some(4),
        instance_type: Some("g5.12xlarge".into()),
        labels,
        ..Config::default()
    })
    .await;
    let nodes: Api<k8s_openapi::api::core::v1::Node> = Api::all(client);
    let list = nodes.list(&ListParams::default()).await.unwrap();
    assert_eq!(list.items.len(), 1);
    let name = list.items[0].metadata.name.clone().unwrap();
    let node = nodes.get(&name).await.unwrap();
    let labels = node.metadata.labels.unwrap();
    assert_eq!(labels["eks.amazonaws.com/capacityType"], "SPOT");
    assert_eq!(labels["node.kubernetes.io/instance-type"], "g5.12xlarge");
    let status = node.status.unwrap();
    assert_eq!(status.allocatable.unwrap()["nvidia.com/gpu"].0, "4");
    let err = nodes.get("elsewhere").await.unwrap_err();
    assert!(
        err.to_string().contains(r#"nodes "elsewhere" not found"#),
        "{err}"
    );
}
