//! The real Kubernetes control plane on loopback: etcd, kube-apiserver (RBAC and Pod Security
//! Admission on), kube-controller-manager and kube-scheduler of the pinned release
//! (`versions.env`), built by `build.sh` into a cache outside the clone. Tests hold local-kube
//! to it and let it judge our manifests and permissions. No kubelet: a test acts as one.

mod front;

use std::fs;
use std::io;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

/// How long the servers get to become ready (a cold start takes about 5 s here).
const READY_WITHIN: Duration = Duration::from_secs(120);

/// Why the control plane is not there.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// `build.sh` failed.
    #[error("building the control plane failed: {0}")]
    Build(String),
    /// A server did not start or become ready.
    #[error("{what}: {why}")]
    Start {
        /// Which server or step.
        what: &'static str,
        /// What went wrong, with its log's end.
        why: String,
    },
    /// A file or a process could not be made.
    #[error(transparent)]
    Io(#[from] io::Error),
}

/// Who a request is made as: each has its own bearer token and kubeconfig.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Identity {
    /// `system:masters`: sets the cluster up, as an operator does.
    Admin,
    /// The group Launch, Monitor and Finalize get from their EKS access entries
    /// (`leaderboard-pipeline`, `infra/cluster.yaml`).
    Pipeline,
    /// The group the sweep gets from its access entry (`leaderboard-fleet`): it counts the
    /// GPUs.
    Fleet,
    /// The controller-manager and scheduler (`system:masters` too: they are not under test).
    Controllers,
}

impl Identity {
    const ALL: [Identity; 4] = [
        Identity::Admin,
        Identity::Pipeline,
        Identity::Fleet,
        Identity::Controllers,
    ];

    fn user(self) -> &'static str {
        match self {
            Identity::Admin => "admin",
            Identity::Pipeline => "leaderboard-finalize",
            Identity::Fleet => "leaderboard-sweep",
            Identity::Controllers => "controllers",
        }
    }

    fn groups(self) -> &'static str {
        match self {
            Identity::Admin | Identity::Controllers => "system:masters",
            Identity::Pipeline => "leaderboard-pipeline",
            Identity::Fleet => "leaderboard-fleet",
        }
    }
}

/// The pinned release's binaries: `build.sh` builds them once per machine (minutes the first
/// time, nothing after) and says where they are.
pub fn binaries() -> Result<PathBuf, Error> {
    build(&[])
}

/// The binaries of the release one minor up (`versions.env`'s `UPGRADE_K8S_VERSION`), which
/// [`ControlPlane::upgrade`] replaces the pinned one's with.
pub fn upgrade_binaries() -> Result<PathBuf, Error> {
    build(&["--upgrade"])
}

fn build(args: &[&str]) -> Result<PathBuf, Error> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("build.sh");
    let out = Command::new("bash")
        .arg(&script)
        .args(args)
        .stderr(Stdio::inherit())
        .output()?;
    let text = String::from_utf8_lossy(&out.stdout);
    match (out.status.success(), text.lines().last()) {
        (true, Some(dir)) if Path::new(dir).is_dir() => Ok(PathBuf::from(dir)),
        _ => Err(Error::Build(format!("{script:?} exited {}", out.status))),
    }
}

/// A running control plane; dropping it stops its servers by their PIDs.
#[derive(Debug)]
pub struct ControlPlane {
    dir: tempfile::TempDir,
    /// The servers, in the order they started (an upgrade replaces all but etcd).
    children: Mutex<Vec<(&'static str, Child)>>,
    /// `https://127.0.0.1:<port>`: the endpoint (`front`), as the kubeconfigs name it.
    pub server: String,
    /// The endpoint's load balancer, in front of the ready API server.
    front: front::Front,
    /// The API server's own port (a new one after an upgrade).
    api_port: Mutex<u16>,
    etcd_port: u16,
}

/// The servers an upgrade replaces, in the order they stop (the API server last).
const UPGRADED: [&str; 3] = [
    "kube-scheduler",
    "kube-controller-manager",
    "kube-apiserver",
];

impl ControlPlane {
    /// Starts etcd, kube-apiserver, kube-controller-manager and kube-scheduler from `bin` on
    /// free loopback ports, and waits until Jobs can be created (the default ServiceAccount
    /// exists).
    pub fn start(bin: &Path) -> Result<ControlPlane, Error> {
        // A port found free can be taken before its server binds it (another plane starting
        // beside this one asks the kernel for ports too): start again on new ones, a few times.
        let mut attempt = 1;
        loop {
            match ControlPlane::start_once(bin) {
                Err(e) if attempt < 3 && e.to_string().contains("address already in use") => {
                    attempt += 1;
                }
                started => return started,
            }
        }
    }

    fn start_once(bin: &Path) -> Result<ControlPlane, Error> {
        let dir = tempfile::Builder::new().prefix("real-kube.").tempdir()?;
        let (api, etcd, peer) = (free_port()?, free_port()?, free_port()?);
        let front = front::Front::start(api)?;
        let plane = ControlPlane {
            dir,
            children: Mutex::new(Vec::new()),
            server: format!("https://127.0.0.1:{}", front.port()),
            front,
            api_port: Mutex::new(api),
            etcd_port: etcd,
        };
        plane.credentials()?;
        let root = plane.dir.path().to_path_buf();
        let at = |name: &str| root.join(name).display().to_string();
        plane.launch(
            "etcd",
            Command::new("etcd").args([
                "--name=real-kube",
                &format!("--data-dir={}", at("etcd")),
                &format!("--listen-client-urls=http://127.0.0.1:{etcd}"),
                &format!("--advertise-client-urls=http://127.0.0.1:{etcd}"),
                &format!("--listen-peer-urls=http://127.0.0.1:{peer}"),
                &format!("--initial-advertise-peer-urls=http://127.0.0.1:{peer}"),
                &format!("--initial-cluster=real-kube=http://127.0.0.1:{peer}"),
            ]),
        )?;
        plane.launch_apiserver(bin)?;
        plane.wait("kube-apiserver", &["get", "--raw", "/readyz"])?;
        plane.launch_controllers(bin)?;
        let default_sa = ["-n", "default", "get", "serviceaccount", "default"];
        plane.wait("kube-controller-manager", &default_sa)?;
        Ok(plane)
    }

    /// Starts the API server of `bin` on the plane's port, against its etcd.
    fn launch_apiserver(&self, bin: &Path) -> Result<(), Error> {
        let root = self.dir.path().to_path_buf();
        let at = |name: &str| root.join(name).display().to_string();
        let api = *self.api_port.lock().unwrap_or_else(PoisonError::into_inner);
        let etcd = self.etcd_port;
        self.launch(
            "kube-apiserver",
            Command::new(bin.join("kube-apiserver")).args([
                &format!("--etcd-servers=http://127.0.0.1:{etcd}"),
                "--bind-address=127.0.0.1",
                "--advertise-address=127.0.0.1",
                &format!("--secure-port={api}"),
                "--endpoint-reconciler-type=none",
                &format!("--tls-cert-file={}", at("serving.crt")),
                &format!("--tls-private-key-file={}", at("serving.key")),
                "--service-account-issuer=https://kubernetes.default.svc",
                &format!("--service-account-key-file={}", at("sa.pub")),
                &format!("--service-account-signing-key-file={}", at("sa.key")),
                &format!("--token-auth-file={}", at("tokens.csv")),
                "--authorization-mode=Node,RBAC",
                // PodSecurity is in the default admission plugins: named so a change of default
                // cannot turn it off unseen.
                "--enable-admission-plugins=PodSecurity",
                // As EKS runs it (its device plugins are privileged): what keeps a privileged
                // pod out of our namespace is Pod Security, not this flag.
                "--allow-privileged=true",
                "--service-cluster-ip-range=10.96.0.0/16",
                "--enable-priority-and-fairness=false",
                "--profiling=false",
            ]),
        )?;
        Ok(())
    }

    /// Upgrades the control plane in place to `bin`'s release, as EKS upgrades one: the
    /// endpoint stops passing connections, the scheduler, the controller-manager and the API
    /// server stop, the new release's API server starts against the same etcd (every object
    /// kept) and the endpoint sends connections to it once it is ready, then the new
    /// controllers start. Pods on the nodes keep running meanwhile. How long the endpoint
    /// answered nothing.
    pub fn upgrade(&self, bin: &Path) -> Result<Duration, Error> {
        let stopped = Instant::now();
        self.front.route(None);
        {
            let mut children = self.children();
            for name in UPGRADED {
                if let Some(at) = children.iter().position(|(n, _)| *n == name) {
                    let (_, mut child) = children.remove(at);
                    let _ = child.kill();
                    let _ = child.wait();
                }
            }
        }
        let api = free_port()?;
        *self.api_port.lock().unwrap_or_else(PoisonError::into_inner) = api;
        self.launch_apiserver(bin)?;
        // Ready as the load balancer's health check sees it: on its own port.
        let direct = format!("--server=https://127.0.0.1:{api}");
        self.wait("kube-apiserver", &[&direct, "get", "--raw", "/readyz"])?;
        self.front.route(Some(api));
        let unavailable = stopped.elapsed();
        self.launch_controllers(bin)?;
        Ok(unavailable)
    }

    /// The API server's release (`gitVersion`, `v1.35.4`).
    pub fn version(&self) -> Result<String, Error> {
        let out = Command::new("kubectl")
            .arg(format!(
                "--kubeconfig={}",
                self.kubeconfig(Identity::Admin).display()
            ))
            .args(["get", "--raw", "/version"])
            .output()?;
        let version: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap_or_default();
        version["gitVersion"]
            .as_str()
            .map(str::to_owned)
            .ok_or_else(|| Error::Start {
                what: "kube-apiserver",
                why: format!("no version: {}", String::from_utf8_lossy(&out.stderr)),
            })
    }

    fn children(&self) -> MutexGuard<'_, Vec<(&'static str, Child)>> {
        self.children.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Starts the controller-manager and the scheduler, once the API server is ready.
    fn launch_controllers(&self, bin: &Path) -> Result<(), Error> {
        let root = self.dir.path().to_path_buf();
        let at = |name: &str| root.join(name).display().to_string();
        let kubeconfig = self.kubeconfig(Identity::Controllers).display().to_string();
        self.launch(
            "kube-controller-manager",
            Command::new(bin.join("kube-controller-manager")).args([
                &format!("--kubeconfig={kubeconfig}"),
                // No kubelet renews node leases: the node lifecycle controller would taint every
                // node unreachable after about 50 s.
                "--controllers=*,-nodelifecycle",
                "--use-service-account-credentials=false",
                "--leader-elect=false",
                "--secure-port=0",
                &format!("--root-ca-file={}", at("ca.crt")),
                &format!("--service-account-private-key-file={}", at("sa.key")),
                &format!("--flex-volume-plugin-dir={}", at("flexvolume")),
                "--profiling=false",
            ]),
        )?;
        let config = root.join("scheduler.json");
        fs::write(&config, scheduler_config(&kubeconfig)?)?;
        self.launch(
            "kube-scheduler",
            Command::new(bin.join("kube-scheduler")).args([
                &format!("--config={}", config.display()),
                &format!("--authentication-kubeconfig={kubeconfig}"),
                &format!("--authorization-kubeconfig={kubeconfig}"),
                "--secure-port=0",
                "--profiling=false",
            ]),
        )?;
        Ok(())
    }

    /// A kubeconfig that authenticates as `who`.
    pub fn kubeconfig(&self, who: Identity) -> PathBuf {
        self.dir.path().join(format!("{}.kubeconfig", who.user()))
    }

    /// The certificate and key (PEM) a node agent serves its kubelet endpoint with (signed by
    /// the cluster's CA, for 127.0.0.1).
    pub fn kubelet_tls(&self) -> (PathBuf, PathBuf) {
        let at = |name: &str| self.dir.path().join(name);
        (at("kubelet.crt"), at("kubelet.key"))
    }

    /// Applies manifests (a file or a folder) as the admin, as an operator does.
    pub fn apply(&self, manifests: &Path) -> Result<(), Error> {
        let out = Command::new("kubectl")
            .arg(format!(
                "--kubeconfig={}",
                self.kubeconfig(Identity::Admin).display()
            ))
            .args(["apply", "-f"])
            .arg(manifests)
            .output()?;
        match out.status.success() {
            true => Ok(()),
            false => Err(Error::Start {
                what: "kubectl apply",
                why: String::from_utf8_lossy(&out.stderr).into_owned(),
            }),
        }
    }

    /// The PIDs of the servers, by name (for memory readings).
    pub fn pids(&self) -> Vec<(&'static str, u32)> {
        self.children().iter().map(|(n, c)| (*n, c.id())).collect()
    }

    /// A self-signed serving certificate, the service-account key pair, one token per
    /// identity and a kubeconfig for each.
    fn credentials(&self) -> Result<(), Error> {
        let at = |name: &str| self.dir.path().join(name);
        // A CA and a serving certificate it signs: rustls (kube-rs) refuses a self-signed CA
        // presented as the server's own certificate.
        let path = |name: &str| at(name).to_str().unwrap_or_default().to_string();
        let (ca, ca_key) = (path("ca.crt"), path("ca.key"));
        let ext = path("serving.ext");
        fs::write(
            &ext,
            "subjectAltName=IP:127.0.0.1,DNS:localhost\nbasicConstraints=CA:FALSE\n\
            keyUsage=digitalSignature,keyEncipherment\nextendedKeyUsage=serverAuth\n",
        )?;
        openssl(&[
            "req",
            "-x509",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-days",
            "30",
            "-subj",
            "/CN=real-kube-ca",
            "-keyout",
            &ca_key,
            "-out",
            &ca,
        ])?;
        // The API server's, and the one a node agent serves its kubelet endpoint with.
        for (name, cn) in [("serving", "kube-apiserver"), ("kubelet", "kubelet")] {
            let (key, crt, csr) = (
                path(&format!("{name}.key")),
                path(&format!("{name}.crt")),
                path(&format!("{name}.csr")),
            );
            openssl(&[
                "req",
                "-newkey",
                "rsa:2048",
                "-nodes",
                "-subj",
                &format!("/CN={cn}"),
                "-keyout",
                &key,
                "-out",
                &csr,
            ])?;
            openssl(&[
                "x509",
                "-req",
                "-in",
                &csr,
                "-CA",
                &ca,
                "-CAkey",
                &ca_key,
                "-CAcreateserial",
                "-days",
                "30",
                "-extfile",
                &ext,
                "-out",
                &crt,
            ])?;
        }
        let (sa_key, sa_pub) = (at("sa.key"), at("sa.pub"));
        let sa_key = sa_key.to_str().unwrap_or_default();
        openssl(&["genrsa", "-out", sa_key, "2048"])?;
        openssl(&[
            "rsa",
            "-in",
            sa_key,
            "-pubout",
            "-out",
            sa_pub.to_str().unwrap_or_default(),
        ])?;
        self.tokens(&ca)
    }

    /// A token per identity (the API server's token file) and each one's kubeconfig.
    fn tokens(&self, ca: &str) -> Result<(), Error> {
        let mut tokens = String::new();
        for who in Identity::ALL {
            let token = random_token()?;
            tokens.push_str(&format!(
                "{token},{},{},\"{}\"\n",
                who.user(),
                who.user(),
                who.groups()
            ));
            fs::write(
                self.kubeconfig(who),
                kubeconfig(&self.server, ca, &token, who.user()),
            )?;
        }
        fs::write(self.dir.path().join("tokens.csv"), tokens)?;
        Ok(())
    }

    fn launch(&self, name: &'static str, command: &mut Command) -> Result<(), Error> {
        let log = fs::File::create(self.dir.path().join(format!("{name}.log")))?;
        let child = command
            .stdin(Stdio::null())
            .stdout(log.try_clone()?)
            .stderr(log)
            .spawn()
            .map_err(|e| Error::Start {
                what: name,
                why: e.to_string(),
            })?;
        self.children().push((name, child));
        Ok(())
    }

    /// Waits until `kubectl <check>` as admin succeeds; fails early when `name` exited.
    fn wait(&self, name: &'static str, check: &[&str]) -> Result<(), Error> {
        let deadline = Instant::now() + READY_WITHIN;
        let kubeconfig = self.kubeconfig(Identity::Admin);
        loop {
            let ok = Command::new("kubectl")
                .arg(format!("--kubeconfig={}", kubeconfig.display()))
                .args(check)
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .status()?;
            if ok.success() {
                return Ok(());
            }
            let exited = self
                .children()
                .iter_mut()
                .find(|(n, _)| *n == name)
                .and_then(|(_, c)| c.try_wait().ok().flatten());
            if exited.is_some() || Instant::now() > deadline {
                let log = fs::read_to_string(self.dir.path().join(format!("{name}.log")))
                    .unwrap_or_default();
                let tail: Vec<&str> = log.lines().rev().take(5).collect();
                let why = format!("not ready ({exited:?}): {}", tail.join(" | "));
                return Err(Error::Start { what: name, why });
            }
            std::thread::sleep(Duration::from_millis(250));
        }
    }
}

impl Drop for ControlPlane {
    fn drop(&mut self) {
        for (_, child) in self.children().iter_mut().rev() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// `openssl <args>`, its stderr dropped; an error naming the arguments when it fails.
fn openssl(args: &[&str]) -> Result<(), Error> {
    let ok = Command::new("openssl")
        .args(args)
        .stderr(Stdio::null())
        .status()?;
    match ok.success() {
        true => Ok(()),
        false => Err(Error::Start {
            what: "openssl",
            why: args.join(" "),
        }),
    }
}

fn kubeconfig(server: &str, ca: &str, token: &str, user: &str) -> String {
    format!(
        "apiVersion: v1\nkind: Config\nclusters:\n- name: real-kube\n  cluster:\n    server: {server}\n    certificate-authority: {ca}\nusers:\n- name: {user}\n  user:\n    token: {token}\ncontexts:\n- name: real-kube\n  context: {{cluster: real-kube, user: {user}, namespace: default}}\ncurrent-context: real-kube\n"
    )
}

fn free_port() -> io::Result<u16> {
    Ok(TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
}

/// 32 hex digits from the kernel's random source.
fn random_token() -> io::Result<String> {
    use std::io::Read;
    let mut bytes = [0u8; 16];
    fs::File::open("/dev/urandom")?.read_exact(&mut bytes)?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
}

/// The packing scheduler of the deployment (`infra/k8s/scheduler.yaml`), whose name the Job
/// templates give their pods.
const PACKING_SCHEDULER: &str = include_str!("../../../infra/k8s/scheduler.yaml");

/// The scheduler's configuration: the default profile, and the packing one exactly as
/// `infra/k8s/scheduler.yaml` configures it, both served by this one scheduler (which reads
/// the API server through `kubeconfig` and elects no leader).
fn scheduler_config(kubeconfig: &str) -> Result<String, Error> {
    use serde::Deserialize;
    let unreadable = |why: String| Error::Start {
        what: "kube-scheduler",
        why: format!("infra/k8s/scheduler.yaml: {why}"),
    };
    let text = serde_yaml::Deserializer::from_str(PACKING_SCHEDULER)
        .filter_map(|doc| serde_yaml::Value::deserialize(doc).ok())
        .find(|doc| doc["kind"] == "ConfigMap")
        .and_then(|doc| doc["data"]["config.yaml"].as_str().map(str::to_owned))
        .ok_or_else(|| unreadable("no ConfigMap with a config.yaml".into()))?;
    let mut config: serde_json::Value =
        serde_yaml::from_str(&text).map_err(|e| unreadable(e.to_string()))?;
    let mut profiles = vec![serde_json::json!({"schedulerName": "default-scheduler"})];
    profiles.extend(config["profiles"].as_array().cloned().unwrap_or_default());
    config["profiles"] = serde_json::Value::Array(profiles);
    config["leaderElection"] = serde_json::json!({"leaderElect": false});
    config["clientConnection"] = serde_json::json!({"kubeconfig": kubeconfig});
    Ok(config.to_string())
}
