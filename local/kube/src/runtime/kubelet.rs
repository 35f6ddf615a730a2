//! The kubelet of one pod: volumes, init containers in order, then containers in parallel as
//! local processes, restarts under `OnFailure`, and the container states the API shows.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use k8s_openapi::api::core::v1::{
    Container, ContainerState, ContainerStateRunning, ContainerStateTerminated, ContainerStatus,
    HostIP, Pod, PodIP, PodStatus, Volume,
};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::Time;
use sha2::{Digest, Sha256};
use tokio::sync::watch;
use tokio::task::JoinSet;
use tracing::{debug, info, warn};

use super::disk::LAYER_MOUNT;
use super::env::{argv, environment, EnvBase, LOCAL_IP};
use super::mounts::{plan, Mount};
use super::process::{command, exit_code, signal_group, terminate, wait_group_gone, Launch};
use super::{scheduler, Runtime};
use crate::imagemap::{ImageEntry, Pull};
use crate::objects::names::random_u64;
use crate::objects::pod::{refresh_status, waiting};
use crate::store::{time_now, ObjKey};

/// Stop request: `None` keeps running; `Some(grace)` terminates with that grace period.
pub type StopRx = watch::Receiver<Option<Duration>>;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Slot {
    Init(usize),
    App(usize),
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Outcome {
    Succeeded,
    Failed,
    Stopped,
}

struct PodWorker {
    rt: Arc<Runtime>,
    key: ObjKey,
    pod: Pod,
    dir: PathBuf,
    restart_policy: String,
    owner: Option<String>,
}

/// Waits for a stop request and returns its grace period.
async fn stop_requested(stop: &mut StopRx) -> Duration {
    match stop.wait_for(Option::is_some).await {
        Ok(v) => v.unwrap_or_default(),
        // NB: the runtime dropped the handle: treat as an immediate stop.
        Err(_) => Duration::ZERO,
    }
}

/// The variable through which containers learn their GPUs.
const VISIBLE_DEVICES: &str = "NVIDIA_VISIBLE_DEVICES";

fn container_id() -> String {
    format!("local-kube://{:016x}{:016x}", random_u64(), random_u64())
}

/// The image's id as a runtime reports it: an image pulled by digest is that digest; one
/// pulled by tag gets a stable digest of its own.
fn image_id(image: &str) -> String {
    if image.contains("@sha256:") {
        return image.to_owned();
    }
    let digest = Sha256::digest(image.as_bytes());
    let hex: String = digest.iter().map(|b| format!("{b:02x}")).collect();
    let repo = image.split('@').next().unwrap_or(image);
    format!("{repo}@sha256:{hex}")
}

/// Runs one pod until its containers are done or a stop arrives, then signals `done`.
pub async fn run_pod(rt: Arc<Runtime>, pod: Pod, stop: StopRx, done: watch::Sender<bool>) {
    let key = ObjKey::of(&pod.metadata);
    let dir = rt.pod_dir(&pod);
    let restart_policy = pod
        .spec
        .as_ref()
        .and_then(|s| s.restart_policy.clone())
        .unwrap_or_else(|| "Never".into());
    let owner = crate::objects::pod::controller_uid(&pod);
    let worker = Arc::new(PodWorker {
        rt,
        key,
        pod,
        dir,
        restart_policy,
        owner,
    });
    worker.run(stop).await;
    let _ = done.send(true);
}

impl PodWorker {
    /// What the NVIDIA device plugin does for a container that requested GPUs: their UUIDs in
    /// `NVIDIA_VISIBLE_DEVICES` (the plugin's default `envvar` list strategy, `uuid` ids),
    /// over any value of the spec's own; and what the NVIDIA container toolkit does for a
    /// container with that variable set: `nvidia-smi` on its `PATH`, seeing those GPUs.
    fn with_gpus(
        &self,
        c: &Container,
        mut env: BTreeMap<String, String>,
    ) -> BTreeMap<String, String> {
        let need = scheduler::container_gpus(c) as usize;
        if need > 0 {
            let uid = self.pod.metadata.uid.as_deref().unwrap_or_default();
            let devices = self.rt.devices(uid);
            let spec = self.pod.spec.as_ref();
            // App containers hold their own devices in order; an init container runs before
            // them and may use the pod's first ones.
            let offset: usize = spec
                .filter(|s| s.containers.iter().any(|x| x.name == c.name))
                .map(|s| {
                    s.containers
                        .iter()
                        .take_while(|x| x.name != c.name)
                        .map(|x| scheduler::container_gpus(x) as usize)
                        .sum()
                })
                .unwrap_or(0);
            let uuids: Vec<String> = devices
                .iter()
                .skip(offset)
                .take(need)
                .map(|&i| scheduler::gpu_uuid(i))
                .collect();
            env.insert(VISIBLE_DEVICES.to_owned(), uuids.join(","));
        }
        if env.get(VISIBLE_DEVICES).is_some_and(|v| !v.is_empty()) {
            let path = env.get("PATH").cloned().unwrap_or_default();
            env.insert(
                "PATH".to_owned(),
                format!("{}:{path}", self.rt.nvidia_dir.display()),
            );
        }
        env
    }

    fn spec_container(&self, slot: Slot) -> &Container {
        let spec = self
            .pod
            .spec
            .as_ref()
            .expect("pods are created with a spec");
        match slot {
            Slot::Init(i) => &spec.init_containers.as_ref().expect("slot exists")[i],
            Slot::App(i) => &spec.containers[i],
        }
    }

    fn update(&self, f: impl FnOnce(&mut PodStatus)) {
        let policy = self.restart_policy.clone();
        self.rt.store.update::<Pod>(&self.key, |pod| {
            let status = pod.status.get_or_insert_with(Default::default);
            f(status);
            refresh_status(status, &policy);
        });
        if let Some(owner) = &self.owner {
            self.rt.notify_job(owner);
        }
    }

    fn set(&self, slot: Slot, f: impl FnOnce(&mut ContainerStatus)) {
        self.update(|status| {
            let list = match slot {
                Slot::Init(_) => status.init_container_statuses.as_mut(),
                Slot::App(_) => status.container_statuses.as_mut(),
            };
            let idx = match slot {
                Slot::Init(i) | Slot::App(i) => i,
            };
            if let Some(s) = list.and_then(|l| l.get_mut(idx)) {
                f(s);
            }
        });
    }

    fn initial_status(&self) {
        let spec = self
            .pod
            .spec
            .as_ref()
            .expect("pods are created with a spec");
        let inits = spec.init_containers.clone().unwrap_or_default();
        let first = if inits.is_empty() {
            "ContainerCreating"
        } else {
            "PodInitializing"
        };
        let status_of = |c: &Container, reason: &str| ContainerStatus {
            name: c.name.clone(),
            image: c.image.clone().unwrap_or_default(),
            image_id: String::new(),
            ready: false,
            restart_count: 0,
            started: Some(false),
            state: Some(waiting(reason, None)),
            ..Default::default()
        };
        let now = time_now();
        self.update(|status| {
            status.host_ip = Some(LOCAL_IP.into());
            status.host_ips = Some(vec![HostIP {
                ip: LOCAL_IP.into(),
            }]);
            status.pod_ip = Some(LOCAL_IP.into());
            status.pod_ips = Some(vec![PodIP {
                ip: LOCAL_IP.into(),
            }]);
            status.start_time = Some(now);
            status.init_container_statuses = (!inits.is_empty()).then(|| {
                inits
                    .iter()
                    .map(|c| status_of(c, "PodInitializing"))
                    .collect()
            });
            status.container_statuses = Some(
                spec.containers
                    .iter()
                    .map(|c| status_of(c, first))
                    .collect(),
            );
        });
    }

    async fn run(self: &Arc<Self>, mut stop: StopRx) {
        if let Err(e) = std::fs::create_dir_all(self.dir.join("logs")) {
            warn!(pod = %self.key.name, error = %e, "cannot create pod directory");
        }
        self.initial_status();
        let volumes = match self.prepare_volumes() {
            Ok(v) => Arc::new(v),
            Err(msg) => {
                let spec = self
                    .pod
                    .spec
                    .as_ref()
                    .expect("pods are created with a spec");
                let n = spec.containers.len();
                let reason = "CreateContainerConfigError";
                self.update(|status| {
                    for s in status.container_statuses.iter_mut().flatten().take(n) {
                        s.state = Some(waiting(reason, Some(msg.clone())));
                    }
                });
                stop_requested(&mut stop).await;
                return;
            }
        };
        let spec = self
            .pod
            .spec
            .as_ref()
            .expect("pods are created with a spec");
        let n_init = spec.init_containers.as_ref().map_or(0, Vec::len);
        for i in 0..n_init {
            match self
                .run_container(Slot::Init(i), &volumes, stop.clone())
                .await
            {
                Outcome::Succeeded => {
                    debug!(pod = %self.key.name, init = i, "init container done");
                }
                Outcome::Failed | Outcome::Stopped => return,
            }
        }
        if n_init > 0 {
            self.update(|status| {
                for s in status.container_statuses.iter_mut().flatten() {
                    s.state = Some(waiting("ContainerCreating", None));
                }
            });
        }
        let mut set = JoinSet::new();
        for i in 0..spec.containers.len() {
            let me = self.clone();
            let volumes = volumes.clone();
            let stop = stop.clone();
            set.spawn(async move { me.run_container(Slot::App(i), &volumes, stop).await });
        }
        while set.join_next().await.is_some() {}
        info!(pod = %self.key.name, "pod containers finished");
    }

    fn prepare_volumes(&self) -> Result<HashMap<String, PathBuf>, String> {
        let spec = self
            .pod
            .spec
            .as_ref()
            .expect("pods are created with a spec");
        let mut out = HashMap::new();
        for v in spec.volumes.iter().flatten() {
            let path = self.volume_path(v)?;
            out.insert(v.name.clone(), path);
        }
        Ok(out)
    }

    fn volume_path(&self, v: &Volume) -> Result<PathBuf, String> {
        if v.empty_dir.is_some() {
            let dir = self.dir.join("volumes").join(&v.name);
            std::fs::create_dir_all(&dir)
                .map_err(|e| format!("volume {:?}: cannot create emptyDir: {e}", v.name))?;
            return Ok(dir);
        }
        if let Some(hp) = &v.host_path {
            let path = PathBuf::from(&hp.path);
            let kind = hp.type_.as_deref().unwrap_or_default();
            let bad = |what: &str| {
                Err(format!(
                    "volume {:?}: hostPath {:?} {what}",
                    v.name, hp.path
                ))
            };
            match kind {
                "DirectoryOrCreate" => {
                    std::fs::create_dir_all(&path).map_err(|e| {
                        format!(
                            "volume {:?}: cannot create hostPath {:?}: {e}",
                            v.name, hp.path
                        )
                    })?;
                }
                "FileOrCreate" if !path.exists() => {
                    std::fs::File::create(&path).map_err(|e| {
                        format!(
                            "volume {:?}: cannot create hostPath {:?}: {e}",
                            v.name, hp.path
                        )
                    })?;
                }
                "Directory" if !path.is_dir() => return bad("is not a directory"),
                "File" if !path.is_file() => return bad("is not a file"),
                _ if !path.exists() => return bad("does not exist"),
                _ => {}
            }
            return Ok(path);
        }
        if let Some(projected) = &v.projected {
            return self.projected_volume(v, projected);
        }
        let kind = serde_json::to_value(v)
            .ok()
            .and_then(|j| {
                j.as_object()
                    .and_then(|m| m.keys().find(|k| *k != "name").cloned())
            })
            .unwrap_or_else(|| "this".into());
        Err(format!(
            "volume {:?}: local-kube does not implement {kind} volumes",
            v.name
        ))
    }

    /// A `projected` volume of service account tokens, as the kubelet writes it. There is no
    /// token issuer here: the file holds a placeholder that no AWS or Kubernetes API accepts,
    /// which is what a local run needs (credentials for moto come from the image map's env).
    fn projected_volume(
        &self,
        v: &Volume,
        projected: &k8s_openapi::api::core::v1::ProjectedVolumeSource,
    ) -> Result<PathBuf, String> {
        let dir = self.dir.join("volumes").join(&v.name);
        std::fs::create_dir_all(&dir)
            .map_err(|e| format!("volume {:?}: cannot create projected volume: {e}", v.name))?;
        for source in projected.sources.iter().flatten() {
            let Some(token) = &source.service_account_token else {
                return Err(format!(
                    "volume {:?}: local-kube implements only serviceAccountToken projections",
                    v.name
                ));
            };
            let relative = std::path::Path::new(&token.path);
            if token.path.is_empty()
                || relative.is_absolute()
                || relative
                    .components()
                    .any(|c| matches!(c, std::path::Component::ParentDir))
            {
                return Err(format!(
                    "volume {:?}: serviceAccountToken path {:?} must be relative, without `..`",
                    v.name, token.path
                ));
            }
            let file = dir.join(relative);
            if let Some(parent) = file.parent() {
                std::fs::create_dir_all(parent).map_err(|e| format!("volume {:?}: {e}", v.name))?;
            }
            let audience = token.audience.as_deref().unwrap_or("local-kube");
            std::fs::write(&file, format!("local-kube-unsigned-token.{audience}"))
                .map_err(|e| format!("volume {:?}: cannot write the token: {e}", v.name))?;
        }
        Ok(dir)
    }

    /// Waits in a state that only a stop ends (configuration errors, unpullable images).
    async fn wait_stuck(
        &self,
        slot: Slot,
        reason: &str,
        message: String,
        mut stop: StopRx,
    ) -> Outcome {
        if reason == "ErrImagePull" {
            let image = self.spec_container(slot).image.clone().unwrap_or_default();
            let period = self.rt.timing.image_pull_backoff;
            let mut pull_error = true;
            loop {
                let (r, m) = if pull_error {
                    ("ErrImagePull", message.clone())
                } else {
                    (
                        "ImagePullBackOff",
                        format!("Back-off pulling image {image:?}: ErrImagePull: {message}"),
                    )
                };
                self.set(slot, |s| s.state = Some(waiting(r, Some(m))));
                tokio::select! {
                    _ = stop_requested(&mut stop) => return Outcome::Stopped,
                    _ = tokio::time::sleep(period) => {}
                }
                pull_error = !pull_error;
            }
        }
        self.set(slot, |s| s.state = Some(waiting(reason, Some(message))));
        stop_requested(&mut stop).await;
        Outcome::Stopped
    }

    async fn run_container(
        self: &Arc<Self>,
        slot: Slot,
        volumes: &HashMap<String, PathBuf>,
        stop: StopRx,
    ) -> Outcome {
        let c = self.spec_container(slot).clone();
        let image = c.image.clone().unwrap_or_default();
        let entry = self.rt.images.lookup(&image);
        if entry.is_some_and(|e| e.pull == Pull::Fail) {
            let msg = format!(
                "failed to pull and unpack image {image:?}: the image map marks it `pull: fail`"
            );
            return self.wait_stuck(slot, "ErrImagePull", msg, stop).await;
        }
        let base = EnvBase {
            path: &self.rt.host_path,
            home: &self.rt.home,
        };
        let env = match environment(&c, entry, &self.pod, &base) {
            Ok(env) => self.with_gpus(&c, env),
            Err(e) => {
                return self
                    .wait_stuck(slot, "CreateContainerConfigError", e.0, stop)
                    .await
            }
        };
        let argv = match argv(&c, &image, entry, &env) {
            Ok(a) => a,
            Err(e) => return self.wait_stuck(slot, "ErrImagePull", e.0, stop).await,
        };
        let mounts = match self.mounts(&c, entry, volumes) {
            Ok(mounts) => mounts,
            Err(msg) => {
                return self
                    .wait_stuck(slot, "CreateContainerConfigError", msg, stop)
                    .await
            }
        };
        let workdir = c
            .working_dir
            .clone()
            .filter(|w| !w.is_empty())
            .or_else(|| entry.and_then(|e| e.working_dir.clone()))
            .map(PathBuf::from)
            .unwrap_or_else(|| self.dir.join("work"));
        if !mounts.is_empty() && self.rt.ns == super::process::Namespaces::None {
            let msg = format!(
                "container {:?} mounts {} path(s) but local-kube runs without mount namespaces (isolation None or unavailable)",
                c.name,
                mounts.len()
            );
            return self
                .wait_stuck(slot, "CreateContainerConfigError", msg, stop)
                .await;
        }
        let plan = match plan(mounts, &workdir) {
            Ok(p) => p,
            Err(msg) => {
                return self
                    .wait_stuck(slot, "CreateContainerConfigError", msg, stop)
                    .await
            }
        };
        for path in plan.created.iter().filter(|p| !p.starts_with(&self.dir)) {
            info!(container = %c.name, path = %path.display(), "created a missing mount point on the host");
        }
        let prepared = Prepared {
            c: &c,
            image: &image,
            argv: &argv,
            env: &env,
            workdir: &workdir,
            mounts: &plan.mounts,
        };
        self.attempts(slot, &prepared, stop).await
    }

    /// A container's mounts: its volumes, its image's files (read-only) and, when it runs in a
    /// mount namespace, its writable layer at [`LAYER_MOUNT`] (unless a volume is mounted
    /// there): what it writes outside its volumes is then its own, counted against its
    /// `ephemeral-storage` as a runtime's overlay is. Without a namespace it writes the host's
    /// directories, and has no layer to count.
    fn mounts(
        &self,
        c: &Container,
        entry: Option<&ImageEntry>,
        volumes: &HashMap<String, PathBuf>,
    ) -> Result<Vec<Mount>, String> {
        let mut mounts = volume_mounts(c, volumes)?;
        for (host, inside) in entry.map(|e| e.files.clone()).unwrap_or_default() {
            mounts.push(Mount {
                src: host,
                dst: PathBuf::from(inside),
                read_only: true,
            });
        }
        if mounts.is_empty() || mounts.iter().any(|m| m.dst == Path::new(LAYER_MOUNT)) {
            return Ok(mounts);
        }
        let layer = self.dir.join("layers").join(&c.name);
        std::fs::create_dir_all(&layer)
            .map_err(|e| format!("cannot create the writable layer of {:?}: {e}", c.name))?;
        mounts.push(Mount {
            src: layer,
            dst: PathBuf::from(LAYER_MOUNT),
            read_only: false,
        });
        Ok(mounts)
    }

    /// Runs a container's attempts: again after a failure under `OnFailure`, each time after
    /// a longer back-off (`CrashLoopBackOff`), until one succeeds, the pod stops it, or the
    /// restart policy says it is over.
    async fn attempts(&self, slot: Slot, run: &Prepared<'_>, mut stop: StopRx) -> Outcome {
        let log_dir = self.dir.join("logs").join(&run.c.name);
        let _ = std::fs::create_dir_all(&log_dir);
        let mut attempt: i32 = 0;
        let mut last: Option<ContainerStateTerminated> = None;
        loop {
            if stop.borrow().is_some() || self.rt.is_shutting_down() {
                return Outcome::Stopped;
            }
            let last_state = last.clone().map(|t| ContainerState {
                terminated: Some(t),
                ..Default::default()
            });
            let log = log_dir.join(format!("{attempt}.log"));
            let this = Attempt {
                number: attempt,
                last_state: &last_state,
                log: &log,
            };
            let Some((ended, terminated)) = self.attempt(slot, run, &this, &mut stop).await else {
                return Outcome::Stopped;
            };
            if ended.stopped || ended.code == 0 || self.restart_policy != "OnFailure" {
                let is_init = matches!(slot, Slot::Init(_));
                self.set(slot, |s| {
                    s.state = Some(ContainerState {
                        terminated: Some(terminated.clone()),
                        ..Default::default()
                    });
                    s.last_state = last_state.clone();
                    s.restart_count = attempt;
                    s.ready = is_init && terminated.exit_code == 0;
                    s.started = Some(false);
                });
                return match (ended.stopped, ended.code) {
                    (true, _) => Outcome::Stopped,
                    (false, 0) => Outcome::Succeeded,
                    _ => Outcome::Failed,
                };
            }
            let backoff = self.crash_loop(slot, run.c, attempt, &terminated);
            tokio::select! {
                _ = stop_requested(&mut stop) => return Outcome::Stopped,
                _ = tokio::time::sleep(backoff) => {}
            }
            last = Some(terminated);
            attempt += 1;
        }
    }

    /// One attempt of a container: started, shown running, waited for (or stopped), its
    /// processes gone; how it ended and its terminated state. `None` when the node shuts
    /// down under it.
    async fn attempt(
        &self,
        slot: Slot,
        run: &Prepared<'_>,
        this: &Attempt<'_>,
        stop: &mut StopRx,
    ) -> Option<(Ended, ContainerStateTerminated)> {
        let c = run.c;
        let id = container_id();
        let started_at = time_now();
        let launch = Launch {
            argv: run.argv,
            env: run.env,
            workdir: run.workdir,
            mounts: run.mounts,
            log: this.log,
        };
        let spawned =
            command(&launch, &self.rt.ns).and_then(|mut cmd| self.rt.procs.spawn(&mut cmd));
        let ended = match spawned {
            Err(e) => {
                if self.rt.is_shutting_down() {
                    return None;
                }
                let argv0 = &run.argv[0];
                let _ = std::fs::write(
                    this.log,
                    format!("local-kube: cannot start {argv0:?}: {e}\n"),
                );
                Ended {
                    code: 128,
                    message: Some(format!("exec: {argv0:?}: {e}")),
                    stopped: false,
                }
            }
            Ok((mut child, pgid)) => {
                let attempt = this.number;
                info!(pod = %self.key.name, container = %c.name, attempt, pgid, "container started");
                self.show_running(slot, run.image, this, started_at.clone(), id.clone());
                let (code, stopped) = tokio::select! {
                    status = child.wait() => {
                        // NB: like a container's PID namespace, nothing outlives the main process.
                        signal_group(pgid, nix::sys::signal::Signal::SIGKILL);
                        (status.map(|s| exit_code(&s)).unwrap_or(-1), false)
                    }
                    grace = stop_requested(stop) => {
                        let status = terminate(&mut child, pgid, grace).await;
                        (status.map(|s| exit_code(&s)).unwrap_or(137), true)
                    }
                };
                // NB: the pod only goes away once its processes have, as with a real runtime.
                if !wait_group_gone(pgid, Duration::from_secs(2)).await {
                    warn!(pod = %self.key.name, container = %c.name, pgid, "processes outlived SIGKILL");
                }
                self.rt.procs.forget(pgid);
                info!(pod = %self.key.name, container = %c.name, attempt, exit_code = code, "container exited");
                Ended {
                    code,
                    message: None,
                    stopped,
                }
            }
        };
        let terminated = ended.terminated(id, started_at);
        Some((ended, terminated))
    }

    /// Shows an attempt running: its start, the attempt before it, and its image and id.
    fn show_running(
        &self,
        slot: Slot,
        image: &str,
        this: &Attempt<'_>,
        started_at: Time,
        id: String,
    ) {
        let running = ContainerState {
            running: Some(ContainerStateRunning {
                started_at: Some(started_at),
            }),
            ..Default::default()
        };
        let (img, iid) = (image.to_owned(), image_id(image));
        self.set(slot, |s| {
            s.state = Some(running);
            s.last_state = this.last_state.clone();
            s.restart_count = this.number;
            s.ready = !matches!(slot, Slot::Init(_));
            s.started = Some(true);
            s.image = img;
            s.image_id = iid;
            s.container_id = Some(id);
        });
    }

    /// Shows a failed container waiting in `CrashLoopBackOff`, as the kubelet words it, and
    /// gives how long it waits: the back-off doubles at each attempt, up to its most.
    fn crash_loop(
        &self,
        slot: Slot,
        c: &Container,
        attempt: i32,
        terminated: &ContainerStateTerminated,
    ) -> Duration {
        let timing = &self.rt.timing;
        let factor = 1u32 << attempt.clamp(0, 16);
        let backoff = timing
            .restart_backoff
            .saturating_mul(factor)
            .min(timing.max_backoff);
        let pod = &self.pod.metadata;
        let msg = format!(
            "back-off {} restarting failed container={} pod={}_{}({})",
            go_duration(backoff),
            c.name,
            pod.name.as_deref().unwrap_or_default(),
            pod.namespace.as_deref().unwrap_or_default(),
            pod.uid.as_deref().unwrap_or_default()
        );
        let as_last = ContainerState {
            terminated: Some(terminated.clone()),
            ..Default::default()
        };
        self.set(slot, |s| {
            s.state = Some(waiting("CrashLoopBackOff", Some(msg)));
            s.last_state = Some(as_last);
            s.restart_count = attempt;
            s.ready = false;
            s.started = Some(false);
        });
        backoff
    }
}

/// What a container runs, worked out once for all its attempts.
struct Prepared<'a> {
    c: &'a Container,
    image: &'a str,
    argv: &'a [String],
    env: &'a BTreeMap<String, String>,
    workdir: &'a Path,
    mounts: &'a [Mount],
}

/// One attempt of a container: its number (the restart count), the state the one before
/// it ended in, and its log file.
struct Attempt<'a> {
    number: i32,
    last_state: &'a Option<ContainerState>,
    log: &'a Path,
}

/// How an attempt ended: its exit code, the runtime's message when it could not start, and
/// whether the pod stopped it.
struct Ended {
    code: i32,
    message: Option<String>,
    stopped: bool,
}

impl Ended {
    /// The container's terminated state for this end, with the runtime's reason.
    fn terminated(&self, id: String, started_at: Time) -> ContainerStateTerminated {
        let reason = match (self.code, &self.message) {
            (_, Some(_)) => "StartError",
            (0, None) => "Completed",
            _ => "Error",
        };
        ContainerStateTerminated {
            container_id: Some(id),
            exit_code: self.code,
            finished_at: Some(time_now()),
            message: self.message.clone(),
            reason: Some(reason.into()),
            signal: None,
            started_at: Some(started_at),
        }
    }
}

/// Go's `time.Duration` string for the short delays used here (`200ms`, `1.6s`, `10s`).
fn go_duration(d: Duration) -> String {
    if d < Duration::from_secs(1) {
        format!("{}ms", d.as_millis())
    } else {
        let s = d.as_secs_f64();
        if s.fract() == 0.0 {
            format!("{}s", s as u64)
        } else {
            format!("{s}s")
        }
    }
}

/// The container's volume mounts on the host: each volume's folder, a `subPath` in it made
/// when missing (as the kubelet does); or why the container cannot be created.
fn volume_mounts(c: &Container, volumes: &HashMap<String, PathBuf>) -> Result<Vec<Mount>, String> {
    let mut mounts = Vec::new();
    for m in c.volume_mounts.iter().flatten() {
        let Some(src) = volumes.get(&m.name) else {
            return Err(format!("volume {:?} is not defined", m.name));
        };
        let mut src = src.clone();
        if let Some(sub) = m.sub_path.as_deref().filter(|s| !s.is_empty()) {
            src = src.join(sub);
            // NB: the kubelet creates a missing subPath as a directory.
            if !src.exists() {
                std::fs::create_dir_all(&src).map_err(|e| {
                    format!("cannot create subPath {sub:?} of volume {:?}: {e}", m.name)
                })?;
            }
        }
        mounts.push(Mount {
            src,
            dst: PathBuf::from(&m.mount_path),
            read_only: m.read_only == Some(true),
        });
    }
    Ok(mounts)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_print_like_go() {
        assert_eq!(go_duration(Duration::from_millis(200)), "200ms");
        assert_eq!(go_duration(Duration::from_millis(1600)), "1.6s");
        assert_eq!(go_duration(Duration::from_secs(10)), "10s");
    }

    #[test]
    fn image_ids_are_stable_digests() {
        let pinned = format!("r.example/team@sha256:{}", "a".repeat(64));
        assert_eq!(image_id(&pinned), pinned, "pulled by digest: that digest");
        let a = image_id("carla:0.9.15");
        assert!(a.starts_with("carla:0.9.15@sha256:"));
        assert_eq!(a.len(), "carla:0.9.15@sha256:".len() + 64);
        assert_eq!(a, image_id("carla:0.9.15"));
    }
}
