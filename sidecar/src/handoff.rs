//! What the two containers of a pair hand each other through the `handoff` volume (a small
//! emptyDir only they mount, never uploaded): the agent's GPU to the simulator, the
//! simulator's port to the agent.
//!
//! **One GPU per pair.**
//! The agent container requests `nvidia.com/gpu: 1`, so the NVIDIA device plugin allocates a
//! GPU of the node to it and sets its `NVIDIA_VISIBLE_DEVICES` to that GPU's UUID (the
//! plugin's default `envvar` device list strategy and `uuid` id strategy). The participant's
//! code sees that GPU only. The simulator runs the organizers' CARLA image with
//! `NVIDIA_VISIBLE_DEVICES=all` and must render on the same GPU: the agent's sidecar writes the
//! UUID to `$LB_GPU_DIR/gpu-<ID>` before the evaluator starts; the simulator's sidecar
//! (`LB_GPU_FROM_AGENT=true`) waits for it, finds the GPU's index with `nvidia-smi
//! --query-gpu=index,uuid --format=csv,noheader` (PCI bus order) and replaces `{gpu_index}` in
//! CARLA's arguments and environment. The original 2.0 Jobs did the same.
//!
//! **Once per pod.** The handoff volume is one the participant's code can write, so the
//! simulator reads it only at its first take-over, which comes before any of that code runs
//! (the agent starts its evaluator only after this attempt's start marker, which the simulator
//! writes once CARLA is up on the GPU it took). It keeps the UUID in `$LB_GPU_PIN_DIR/gpu-<ID>`,
//! a volume only simulators mount, and every later attempt of the pod renders on that GPU
//! whatever the handoff file says by then. Nothing it logs names another GPU of the node.
//!
//! **The port.** Every pod has its own network, so CARLA's port (`CARLA_PORT`, 2000) is free;
//! where it is not (pods sharing one network, as on `local-kube`, or a leftover process), the
//! simulator's sidecar takes the first free one of `CARLA_PORT + 100*k`, puts it in place of
//! `{carla_port}` in CARLA's arguments, and writes it to `$LB_HANDOFF_DIR/port-<ID>` before
//! CARLA starts; the agent's sidecar reads it once the start marker is there and gives the
//! evaluator that `CARLA_PORT` (and the traffic manager the same offset from it). A look is not
//! a hold: two simulators starting together can both find one port free, and the one whose
//! CARLA binds second exits at once. A CARLA that exits before it is ready while its port is
//! held by another process lost that race: the sidecar starts it again on the next free port
//! ([`PORT_RACES`] times at most), and the attempt is not a crash.

use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::{Duration, Instant};

use tokio::process::Command;

use crate::signals::{Signals, Wake};

/// What `{gpu_index}` becomes in CARLA's arguments and environment.
pub const PLACEHOLDER: &str = "{gpu_index}";
/// What `{carla_port}` becomes in CARLA's arguments.
pub const PORT_PLACEHOLDER: &str = "{carla_port}";
/// The handoff volume (a small emptyDir both containers of the pair mount).
pub const DEFAULT_DIR: &str = "/tmp/handoff";
/// `LB_HANDOFF_DIR`: where the handoff files live.
pub const DIR_VAR: &str = "LB_HANDOFF_DIR";
/// Port candidates: `CARLA_PORT + PORT_STRIDE * k`, k below this.
const PORT_CANDIDATES: u16 = 50;
/// Distance between candidates (CARLA also takes the two ports after its own).
const PORT_STRIDE: u16 = 100;
/// How many times one attempt starts CARLA again on another port after losing its port to
/// another process: each is a race lost to a simulator that started at the same moment.
pub const PORT_RACES: u32 = 3;
/// Where the simulator keeps the GPU it took over (a volume only simulators mount).
pub const DEFAULT_PIN_DIR: &str = "/tmp/gpu-pin";
/// `LB_GPU_PIN_DIR`: that folder.
pub const PIN_DIR_VAR: &str = "LB_GPU_PIN_DIR";
/// `LB_GPU_FROM_AGENT`: the simulator takes its GPU from the agent.
pub const FROM_AGENT_VAR: &str = "LB_GPU_FROM_AGENT";
/// Set by the device plugin in the container holding the GPU.
pub const VISIBLE_DEVICES: &str = "NVIDIA_VISIBLE_DEVICES";
/// How long `nvidia-smi` may take.
const QUERY_TIMEOUT: Duration = Duration::from_secs(30);
/// Longest handoff file read (a UUID is 40 characters).
const MAX_HANDOFF: u64 = 256;

/// Why the simulator has no GPU to render on.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// The agent's sidecar wrote no handoff in time.
    #[error("the agent handed over no GPU within {0:?} (`{1}` missing)")]
    NoHandoff(Duration, PathBuf),
    /// What the device plugin (or the handoff) holds is not one GPU.
    #[error("`{0}` is not one GPU UUID (GPU-... or MIG-...)")]
    NotOneGpu(String),
    /// `nvidia-smi` could not be run or failed.
    #[error("nvidia-smi: {0}")]
    Query(String),
    /// The agent's GPU is not among this container's GPUs. The others are counted, never
    /// named: the simulator's log is the participant's to read.
    #[error("GPU `{uuid}` is not among the {listed} GPU(s) nvidia-smi lists here")]
    NotOnNode {
        /// The handed-over UUID.
        uuid: String,
        /// How many nvidia-smi listed.
        listed: usize,
    },
    /// The GPU could not be kept for the pod's later attempts.
    #[error("cannot keep the GPU in `{0}`: {1}")]
    Pin(PathBuf, String),
}

/// The one GPU UUID in a `NVIDIA_VISIBLE_DEVICES` value or handoff file.
pub fn one_uuid(value: &str) -> Result<String, GpuError> {
    let v = value.trim();
    let well_formed = (v.starts_with("GPU-") || v.starts_with("MIG-"))
        && v.len() <= 80
        && v[4..]
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '/');
    if well_formed {
        Ok(v.to_owned())
    } else {
        Err(GpuError::NotOneGpu(v.chars().take(80).collect()))
    }
}

/// The handoff file of pair `pair`.
pub fn handoff_path(dir: &Path, pair: u32) -> PathBuf {
    dir.join(format!("gpu-{pair}"))
}

/// The index of `uuid` in `nvidia-smi --query-gpu=index,uuid --format=csv[,noheader]` output.
pub fn index_of(uuid: &str, csv: &str) -> Result<u32, GpuError> {
    let rows: Vec<(u32, &str)> = csv
        .lines()
        .filter_map(|line| {
            let (index, id) = line.split_once(',')?;
            Some((index.trim().parse().ok()?, id.trim()))
        })
        .collect();
    rows.iter()
        .find(|(_, id)| *id == uuid)
        .map(|(index, _)| *index)
        .ok_or_else(|| GpuError::NotOnNode {
            uuid: uuid.to_owned(),
            listed: rows.len(),
        })
}

/// `argv` with every `{gpu_index}` (when `index` is known) and `{carla_port}` replaced.
pub fn substitute(argv: &[String], index: Option<u32>, port: u16) -> Vec<String> {
    argv.iter()
        .map(|a| {
            let a = a.replace(PORT_PLACEHOLDER, &port.to_string());
            match index {
                Some(i) => a.replace(PLACEHOLDER, &i.to_string()),
                None => a,
            }
        })
        .collect()
}

/// The handoff file of pair `pair`'s port.
pub fn port_path(dir: &Path, pair: u32) -> PathBuf {
    dir.join(format!("port-{pair}"))
}

/// Whether CARLA could take `port` (and the two after it) and the traffic manager
/// `port + tm_offset`, on every interface as CARLA binds.
fn ports_free(port: u16, tm_offset: u16) -> bool {
    let wanted = [
        Some(port),
        port.checked_add(1),
        port.checked_add(2),
        port.checked_add(tm_offset),
    ];
    wanted.iter().all(|p| {
        p.is_some_and(|p| std::net::TcpListener::bind((std::net::Ipv4Addr::UNSPECIFIED, p)).is_ok())
    })
}

/// Whether another process holds `port` or one of the ports CARLA would take with it.
pub fn port_taken(port: u16, tm_offset: u16) -> bool {
    !ports_free(port, tm_offset)
}

/// The first free port of `preferred + 100*k` (`preferred` itself in a pod of its own).
pub fn pick_port(preferred: u16, tm_offset: u16) -> u16 {
    (0..PORT_CANDIDATES)
        .filter_map(|k| preferred.checked_add(k.checked_mul(PORT_STRIDE)?))
        .find(|p| ports_free(*p, tm_offset))
        .unwrap_or(preferred)
}

/// The simulator's side: tells the agent CARLA's port (write then rename).
pub fn announce_port(dir: &Path, pair: u32, port: u16) -> std::io::Result<()> {
    std::fs::create_dir_all(dir)?;
    let tmp = dir.join(format!(".port-{pair}.tmp"));
    std::fs::write(&tmp, port.to_string())?;
    std::fs::rename(&tmp, port_path(dir, pair))
}

/// The agent's side: the port the simulator announced, if it did.
pub fn announced_port(dir: &Path, pair: u32) -> Option<u16> {
    read_small(&port_path(dir, pair))?.trim().parse().ok()
}

/// The variables of `vars` whose value holds `{gpu_index}` (read once, into the config).
pub fn templated_env(
    vars: impl IntoIterator<Item = (OsString, OsString)>,
) -> Vec<(String, String)> {
    vars.into_iter()
        .filter_map(|(k, v)| Some((k.into_string().ok()?, v.into_string().ok()?)))
        .filter(|(_, v)| v.contains(PLACEHOLDER))
        .collect()
}

/// `templates` ([`templated_env`]) with `{gpu_index}` replaced by `index`.
pub fn substitute_env(templates: &[(String, String)], index: u32) -> Vec<(String, String)> {
    templates
        .iter()
        .map(|(k, v)| (k.clone(), v.replace(PLACEHOLDER, &index.to_string())))
        .collect()
}

/// The agent's side: records the device plugin's GPU for the simulator. A container without
/// one (`NVIDIA_VISIBLE_DEVICES` unset: no GPU requested) writes nothing.
pub fn hand_over(dir: &Path, pair: u32, visible: Option<&str>) -> Result<Option<String>, String> {
    let Some(visible) = visible.filter(|v| !v.trim().is_empty()) else {
        return Ok(None);
    };
    let uuid = one_uuid(visible).map_err(|e| e.to_string())?;
    std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let path = handoff_path(dir, pair);
    // NB: write then rename, so the simulator never reads half a UUID.
    let tmp = dir.join(format!(".gpu-{pair}.tmp"));
    std::fs::write(&tmp, &uuid)
        .and_then(|()| std::fs::rename(&tmp, &path))
        .map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(Some(uuid))
}

/// The simulator's side: the pair's GPU UUID and its index (`nvidia-smi`). `None` when
/// SIGTERM came first.
pub async fn take_over(
    dirs: (&Path, &Path),
    pair: u32,
    wait: Duration,
    poll: Duration,
    signals: &mut Signals,
) -> Result<Option<(String, u32)>, GpuError> {
    let Some(uuid) = pinned_gpu(dirs, pair, wait, poll, signals).await? else {
        return Ok(None);
    };
    let csv = query().await?;
    Ok(Some((uuid.clone(), index_of(&uuid, &csv)?)))
}

/// The pin file of pair `pair`.
pub fn pin_path(dir: &Path, pair: u32) -> PathBuf {
    dir.join(format!("gpu-{pair}"))
}

/// The pair's GPU UUID: the one pinned at the pod's first take-over, or else the agent's
/// handoff (waited for at most `wait` in `dirs.0`), pinned now in `dirs.1` before it is used.
/// `None` when SIGTERM came first.
pub async fn pinned_gpu(
    (handoff_dir, pin_dir): (&Path, &Path),
    pair: u32,
    wait: Duration,
    poll: Duration,
    signals: &mut Signals,
) -> Result<Option<String>, GpuError> {
    let pin = pin_path(pin_dir, pair);
    if let Some(text) = read_small(&pin) {
        return one_uuid(&text).map(Some);
    }
    let path = handoff_path(handoff_dir, pair);
    let until = Instant::now() + wait;
    let uuid = loop {
        if let Some(text) = read_small(&path) {
            break one_uuid(&text)?;
        }
        if Instant::now() >= until {
            return Err(GpuError::NoHandoff(wait, path));
        }
        if signals.sleep(poll).await == Wake::Terminate {
            return Ok(None);
        }
    };
    // NB: write then rename, so a later attempt never reads half a UUID.
    let tmp = pin_dir.join(format!(".gpu-{pair}.tmp"));
    std::fs::create_dir_all(pin_dir)
        .and_then(|()| std::fs::write(&tmp, &uuid))
        .and_then(|()| std::fs::rename(&tmp, &pin))
        .map_err(|e| GpuError::Pin(pin.clone(), e.to_string()))?;
    Ok(Some(uuid))
}

fn read_small(path: &Path) -> Option<String> {
    use std::io::Read;
    let mut text = String::new();
    std::fs::File::open(path)
        .ok()?
        .take(MAX_HANDOFF)
        .read_to_string(&mut text)
        .ok()?;
    Some(text).filter(|t| !t.trim().is_empty())
}

async fn query() -> Result<String, GpuError> {
    let run = Command::new("nvidia-smi")
        .args(["--query-gpu=index,uuid", "--format=csv,noheader"])
        .stdin(Stdio::null())
        .kill_on_drop(true)
        .output();
    let out = tokio::time::timeout(QUERY_TIMEOUT, run)
        .await
        .map_err(|_| GpuError::Query(format!("no answer within {QUERY_TIMEOUT:?}")))?
        .map_err(|e| GpuError::Query(e.to_string()))?;
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        return Err(GpuError::Query(format!(
            "{}: {}",
            out.status,
            err.trim().chars().take(300).collect::<String>()
        )));
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

#[cfg(test)]
mod tests {
    use super::*;

    const UUID: &str = "GPU-8f6b2c1e-3d4a-4b5c-9e7f-0a1b2c3d4e5f";

    #[test]
    fn only_one_well_formed_uuid_is_a_gpu() {
        assert_eq!(one_uuid(&format!(" {UUID}\n")).unwrap(), UUID);
        assert!(one_uuid("MIG-GPU-8f6b2c1e/1/0").is_ok());
        for bad in [
            "all",
            "none",
            "0",
            "",
            "void",
            "GPU-1,GPU-2",
            "GPU-$(reboot)",
            "GPU-../../etc",
        ] {
            assert!(
                matches!(one_uuid(bad), Err(GpuError::NotOneGpu(_))),
                "{bad}"
            );
        }
    }

    #[test]
    fn the_index_comes_from_nvidia_smi_s_csv_with_or_without_header() {
        let csv = format!("index, uuid\n0, GPU-aaaa\n1, {UUID}\n2, GPU-cccc\n");
        assert_eq!(index_of(UUID, &csv).unwrap(), 1);
        assert_eq!(index_of("GPU-cccc", "0, GPU-aaaa\n3, GPU-cccc").unwrap(), 3);
        // The error names the GPU asked for and counts the others without naming them.
        let err = index_of("GPU-ffff", &csv).unwrap_err().to_string();
        assert!(
            err.contains("GPU-ffff") && err.contains("3 GPU(s)"),
            "{err}"
        );
        assert!(
            !err.contains("GPU-8f6b") && !err.contains("GPU-aaaa"),
            "{err}"
        );
        assert!(index_of(UUID, "")
            .unwrap_err()
            .to_string()
            .contains(" 0 GPU"));
    }

    #[test]
    fn the_placeholder_is_replaced_in_arguments_and_only_matching_variables() {
        let argv: Vec<String> = [
            "./CarlaUE4.sh",
            "-carla-rpc-port={carla_port}",
            "r.GraphicsAdapter={gpu_index}",
        ]
        .map(String::from)
        .to_vec();
        assert_eq!(
            substitute(&argv, Some(3), 2100)[1..],
            ["-carla-rpc-port=2100", "r.GraphicsAdapter=3"]
        );
        assert_eq!(
            substitute(&argv, None, 2000)[2],
            "r.GraphicsAdapter={gpu_index}"
        );
        let vars = [("SDL_HINT_CUDA_DEVICE", "{gpu_index}"), ("OTHER", "1")]
            .map(|(k, v)| (OsString::from(k), OsString::from(v)));
        assert_eq!(
            substitute_env(&templated_env(vars), 2),
            [("SDL_HINT_CUDA_DEVICE".to_owned(), "2".to_owned())]
        );
    }

    #[test]
    fn a_taken_port_moves_the_pair_to_the_next_free_one_and_the_agent_learns_it() {
        // Something (another pod on a shared network) holds a port and its neighbours.
        // NB: below the ephemeral range, so there is room above it for every candidate.
        let held = (20_000..30_000u16)
            .step_by(7)
            .find_map(|p| std::net::TcpListener::bind((std::net::Ipv4Addr::UNSPECIFIED, p)).ok())
            .expect("a free port between 20000 and 30000");
        let taken = held.local_addr().unwrap().port();
        let picked = pick_port(taken, 10);
        assert_ne!(picked, taken);
        assert_eq!((picked - taken) % 100, 0);
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(announced_port(dir.path(), 1), None);
        announce_port(dir.path(), 1, picked).unwrap();
        assert_eq!(announced_port(dir.path(), 1), Some(picked));
    }

    #[tokio::test]
    async fn the_first_take_over_pins_the_gpu_and_a_planted_handoff_never_moves_it() {
        let (handoff, pin) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
        let dirs = (handoff.path(), pin.path());
        let mut signals = Signals::install().unwrap();
        let (wait, poll) = (Duration::from_millis(200), Duration::from_millis(10));
        // No handoff in time: no GPU (a crash of that attempt), nothing pinned.
        let err = pinned_gpu(dirs, 1, wait, poll, &mut signals)
            .await
            .unwrap_err();
        assert!(matches!(err, GpuError::NoHandoff(..)), "{err}");
        assert!(!pin_path(pin.path(), 1).exists());
        // The agent's handoff, before any participant code: taken and pinned.
        hand_over(handoff.path(), 1, Some(UUID)).unwrap();
        let got = pinned_gpu(dirs, 1, wait, poll, &mut signals).await.unwrap();
        assert_eq!(got.as_deref(), Some(UUID));
        assert_eq!(read_small(&pin_path(pin.path(), 1)).unwrap(), UUID);
        // The participant's code plants another GPU (or garbage), crashes, and the next
        // attempt of the simulator renders on the pinned one.
        let other = "GPU-00000000-0000-0000-0000-000000000002";
        for planted in [other, "GPU-$(reboot)", ""] {
            std::fs::write(handoff_path(handoff.path(), 1), planted).unwrap();
            let got = pinned_gpu(dirs, 1, wait, poll, &mut signals).await.unwrap();
            assert_eq!(got.as_deref(), Some(UUID), "{planted}");
        }
        std::fs::remove_file(handoff_path(handoff.path(), 1)).unwrap();
        let got = pinned_gpu(dirs, 1, wait, poll, &mut signals).await.unwrap();
        assert_eq!(got.as_deref(), Some(UUID));
        // A malformed handoff at the first take-over is refused, and not pinned.
        std::fs::write(handoff_path(handoff.path(), 2), "all").unwrap();
        assert!(pinned_gpu(dirs, 2, wait, poll, &mut signals).await.is_err());
        assert!(!pin_path(pin.path(), 2).exists());
    }

    #[test]
    fn the_agent_hands_over_its_one_gpu_and_nothing_without_one() {
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(hand_over(dir.path(), 2, None).unwrap(), None);
        assert_eq!(hand_over(dir.path(), 2, Some("  ")).unwrap(), None);
        assert!(!handoff_path(dir.path(), 2).exists());
        assert!(hand_over(dir.path(), 2, Some("all")).is_err());
        assert_eq!(
            hand_over(dir.path(), 2, Some(UUID)).unwrap().as_deref(),
            Some(UUID)
        );
        assert_eq!(read_small(&handoff_path(dir.path(), 2)).unwrap(), UUID);
    }
}
