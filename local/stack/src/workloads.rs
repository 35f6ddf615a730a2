//! What the Job images become on this machine: the image map that makes the rendered Jobs run
//! with the real sidecar, the fake CARLA and the fake evaluator, S3 served by moto.

use std::collections::BTreeMap;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::Command;

use lb_domain::settings::Settings;
use local_kube::{ImageEntry, ImageMap, Pull};

/// The three programs a local Job runs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Binaries {
    /// `lb-sidecar`.
    pub sidecar: PathBuf,
    /// `fake-carla`.
    pub fake_carla: PathBuf,
    /// `fake-evaluator`.
    pub fake_evaluator: PathBuf,
}

impl Binaries {
    /// The binaries in `dir` (a cargo profile directory such as `target/debug`).
    pub fn in_dir(dir: &Path) -> std::io::Result<Binaries> {
        let find = |name: &str| {
            let path = dir.join(name);
            if path.is_file() {
                Ok(path)
            } else {
                Err(std::io::Error::new(
                    std::io::ErrorKind::NotFound,
                    format!(
                        "`{}` not built (cargo build -p sidecar -p fake-workloads --bins)",
                        path.display()
                    ),
                ))
            }
        };
        Ok(Binaries {
            sidecar: find("lb-sidecar")?,
            fake_carla: find("fake-carla")?,
            fake_evaluator: find("fake-evaluator")?,
        })
    }

    /// The binaries beside the running program (where `cargo build` and `make local` put
    /// them), else on `PATH`; the error names every place looked at.
    pub fn find() -> std::io::Result<Binaries> {
        let mut dirs: Vec<PathBuf> = Vec::new();
        if let Some(dir) = std::env::current_exe()
            .ok()
            .and_then(|e| e.parent().map(Path::to_owned))
        {
            dirs.push(dir);
        }
        if let Some(path) = std::env::var_os("PATH") {
            dirs.extend(std::env::split_paths(&path));
        }
        let find = |name: &str| {
            dirs.iter()
                .map(|d| d.join(name))
                .find(|p| p.is_file())
                .ok_or_else(|| {
                    let looked: Vec<String> =
                        dirs.iter().map(|d| format!("`{}`", d.display())).collect();
                    std::io::Error::new(
                        std::io::ErrorKind::NotFound,
                        format!(
                            "`{name}` not found beside this program or on PATH (looked in {}): \
                             run `make local`, or `cargo build -p cli -p local-cli -p sidecar -p fake-workloads --bins`",
                            looked.join(", ")
                        ),
                    )
                })
        };
        Ok(Binaries {
            sidecar: find("lb-sidecar")?,
            fake_carla: find("fake-carla")?,
            fake_evaluator: find("fake-evaluator")?,
        })
    }

    /// Builds them with cargo (debug profile) and returns where they are.
    pub fn build() -> std::io::Result<Binaries> {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
        build_workspace_bins()?;
        let target = std::env::var_os("CARGO_TARGET_DIR")
            .map(PathBuf::from)
            .unwrap_or_else(|| root.join("target"));
        Self::in_dir(&target.join("debug"))
    }
}

/// What cargo tells a test or build script about its package: ring's build script reruns when
/// `CARGO_MANIFEST_DIR` or `CARGO_PKG_NAME` changes, so a build from a test that kept its own
/// values would rebuild ring and relink every binary while other tests run them.
const PACKAGE_VARIABLES: [&str; 3] = ["CARGO_MANIFEST_", "CARGO_PKG_", "CARGO_CRATE_"];

/// `cargo build --quiet --workspace --bins` in the workspace, as `make local` and the test
/// suite build: one selection resolves the dependencies' features once, so no caller rebuilds
/// them for a selection of its own. Run from a test, it builds without the variables cargo set
/// for that test ([`PACKAGE_VARIABLES`]): up to date, it changes nothing.
pub fn build_workspace_bins() -> std::io::Result<()> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let mut build = Command::new(cargo);
    build
        .current_dir(&root)
        .args(["build", "--quiet", "--workspace", "--bins"]);
    for (name, _) in std::env::vars_os() {
        let text = name.to_string_lossy();
        if PACKAGE_VARIABLES.iter().any(|p| text.starts_with(p)) {
            build.env_remove(&name);
        }
    }
    let status = build.status()?;
    if !status.success() {
        return Err(std::io::Error::other(format!(
            "cargo build of the workspace's binaries failed: {status}"
        )));
    }
    Ok(())
}

/// Where the local participant image keeps its own code (on its `PYTHONPATH`).
pub const PARTICIPANT_CODE_ROOT: &str = "/opt/team_code";

/// How the fake programs behave in a local run.
#[derive(Debug, Clone, PartialEq)]
pub struct Behaviour {
    /// Seconds the fake evaluator spends per route.
    pub route_seconds: f64,
    /// Extra environment of the participant's image (the fake evaluator's `FAKE_*` switches).
    pub evaluator_env: BTreeMap<String, String>,
    /// Extra environment of the CARLA image (`FAKE_CARLA_*`).
    pub carla_env: BTreeMap<String, String>,
    /// The local node's `nvidia.com/gpu`: pairs beyond it wait `Pending` (`Unschedulable`,
    /// `Insufficient nvidia.com/gpu`) until a GPU frees. `None`: GPUs not modelled.
    pub node_gpus: Option<u32>,
    /// The local node's instance type (`node.kubernetes.io/instance-type`), which the Jobs'
    /// `nodeSelector` must match. `None`: the one every leaderboard of the settings names
    /// (not modelled when they differ).
    pub node_instance_type: Option<String>,
    /// The local node's capacity type (`eks.amazonaws.com/capacityType`): on-demand unless
    /// `Capacity::Spot`.
    pub node_capacity: lb_domain::settings::Capacity,
    /// A second node the pods can move to once the first is drained (on the real control
    /// plane a drained node is cordoned; local-kube's one node is not).
    pub spare_node: bool,
    /// The spare node is registered cordoned and joins when the scenario uncordons it (the
    /// new node of a node group's update; the real control plane only).
    pub spare_node_joins_later: bool,
    /// The disk of the real control plane's nodes, which their kubelet evicts pods from when
    /// it runs short (local-kube's node has no disk modelled).
    pub node_disk: node_agent::Disk,
}

impl Default for Behaviour {
    fn default() -> Self {
        Behaviour {
            route_seconds: 0.1,
            evaluator_env: BTreeMap::new(),
            carla_env: BTreeMap::new(),
            node_gpus: None,
            node_instance_type: None,
            node_capacity: lb_domain::settings::Capacity::OnDemand,
            spare_node: false,
            spare_node_joins_later: false,
            node_disk: node_agent::Disk::default(),
        }
    }
}

/// Builds the image map of a local run in `scratch`: every leaderboard's CARLA and
/// private-contents images from `settings`, and participant images by `participant_glob`
/// (`*` matches any). `moto` is moto's endpoint, given to init and logcopy as their S3.
pub fn image_map(
    settings: &Settings,
    bins: &Binaries,
    moto: &str,
    scratch: &Path,
    participant_glob: &str,
    behaviour: &Behaviour,
    unpullable: &[&str],
) -> std::io::Result<ImageMap> {
    let (bin, shims, sources) = stage(bins, scratch)?;

    let aws_env = BTreeMap::from([
        ("AWS_ENDPOINT_URL".to_string(), moto.to_string()),
        ("AWS_ACCESS_KEY_ID".to_string(), "testing".to_string()),
        ("AWS_SECRET_ACCESS_KEY".to_string(), "testing".to_string()),
    ]);
    let mut map = ImageMap::default();
    let insert = |map: &mut ImageMap, image: &str, entry: ImageEntry| {
        map.insert(image, entry)
            .map(|_| ())
            .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidInput, e.to_string()))
    };
    for lb in settings.leaderboards.values() {
        insert(
            &mut map,
            &lb.images.carla,
            ImageEntry {
                files: BTreeMap::from([(
                    bins.fake_carla.clone(),
                    "/home/carla/CarlaUE4.sh".to_string(),
                )]),
                env: behaviour.carla_env.clone(),
                working_dir: Some("/home/carla".into()),
                ..ImageEntry::default()
            },
        )?;
        insert(
            &mut map,
            &lb.images.private_contents,
            ImageEntry {
                path: vec![bin.clone()],
                env: aws_env.clone(),
                files: BTreeMap::from([
                    (sources.join("leaderboard"), "/src/leaderboard".to_string()),
                    (
                        sources.join("scenario_runner"),
                        "/src/scenario_runner".to_string(),
                    ),
                    (sources.join("CARLA"), "/src/CARLA".to_string()),
                ]),
                ..ImageEntry::default()
            },
        )?;
    }
    let participant_env = participant_env(scratch, behaviour)?;
    for image in unpullable {
        insert(
            &mut map,
            image,
            ImageEntry {
                pull: Pull::Fail,
                ..ImageEntry::default()
            },
        )?;
    }
    insert(
        &mut map,
        participant_glob,
        ImageEntry {
            path: vec![shims],
            env: participant_env,
            ..ImageEntry::default()
        },
    )?;
    Ok(map)
}

/// The files the images' stand-ins use, in `scratch`: the sidecar under `bin/` (the
/// private-contents image's PATH), the `python3` shim that runs the fake evaluator under
/// `shims/`, and the official code's stand-ins under `sources/`.
fn stage(bins: &Binaries, scratch: &Path) -> std::io::Result<(PathBuf, PathBuf, PathBuf)> {
    let bin = scratch.join("bin");
    let shims = scratch.join("shims");
    let sources = scratch.join("sources");
    for dir in [&bin, &shims] {
        std::fs::create_dir_all(dir)?;
    }
    // init runs `lb-sidecar` from the image's PATH and copies itself into the Job's volume.
    let sidecar = bin.join("lb-sidecar");
    let _ = std::fs::remove_file(&sidecar);
    std::fs::copy(&bins.sidecar, &sidecar)?;
    // The agent runs `python3 -u .../leaderboard_evaluator.py ...`: python3 is the fake.
    let python = shims.join("python3");
    std::fs::write(
        &python,
        format!(
            "#!/bin/sh\nexec '{}' \"$@\"\n",
            bins.fake_evaluator.display()
        ),
    )?;
    std::fs::set_permissions(&python, std::fs::Permissions::from_mode(0o755))?;
    // The official code the private-contents image carries.
    for (dir, file) in [
        ("leaderboard/leaderboard", "leaderboard_evaluator.py"),
        ("leaderboard/data", "routes_testing.xml"),
        ("scenario_runner", "README"),
        ("CARLA/PythonAPI", "README"),
        // Named as the original images rename it; the agent finds it by pattern.
        ("CARLA/PythonAPI/carla/dist", "carla-leaderboard-py3x.egg"),
    ] {
        std::fs::create_dir_all(sources.join(dir))?;
        std::fs::write(
            sources.join(dir).join(file),
            "# stand-in: the fake evaluator runs instead\n",
        )?;
    }
    Ok((bin, shims, sources))
}

/// The participant image's environment: its own home, its agent and code root, the route
/// length, and the scenario's switches.
fn participant_env(
    scratch: &Path,
    behaviour: &Behaviour,
) -> std::io::Result<BTreeMap<String, String>> {
    // The participant image's own home: the agent sources its `.bashrc`, which must not be
    // the host's (a host `.bashrc` may put another python3 first on PATH).
    let home = scratch.join("participant-home");
    std::fs::create_dir_all(&home)?;
    std::fs::write(
        home.join(".bashrc"),
        "# the participant image's ~/.bashrc, sourced before agent_sources.sh\nexport TEAM_BASHRC=sourced\n",
    )?;
    let mut env = BTreeMap::from([
        ("HOME".to_string(), home.display().to_string()),
        (
            "FAKE_EVALUATOR_ROUTE_SECONDS".to_string(),
            behaviour.route_seconds.to_string(),
        ),
        (
            "TEAM_AGENT".to_string(),
            "/workspace/team_code/agent.py".to_string(),
        ),
        (
            "TEAM_CONFIG".to_string(),
            "/workspace/team_code/config.txt".to_string(),
        ),
        // The participant's image puts its code root on PYTHONPATH, and its agent imports
        // from there: a Job that replaced the image's PYTHONPATH fails as it would on EKS.
        ("PYTHONPATH".to_string(), PARTICIPANT_CODE_ROOT.to_string()),
        (
            "FAKE_EVALUATOR_TEAM_CODE".to_string(),
            PARTICIPANT_CODE_ROOT.to_string(),
        ),
    ]);
    env.extend(behaviour.evaluator_env.clone());
    Ok(env)
}
