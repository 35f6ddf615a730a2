//! CARLA of the first pair is killed mid-route: crash markers, restart, resume, FINISHED.

use cli::outln;

use super::Rehearsal;

/// A simulator crash.
pub struct Crash;

impl Rehearsal for Crash {
    fn expected(&self) -> &'static str {
        "finished"
    }

    fn acts(&self) -> bool {
        true
    }

    /// From the first round on, until CARLA was up to be killed (a busy machine may start it
    /// after the first round).
    fn round_begins(&self, n: u64) -> bool {
        // This run's own CARLA (a descendant of this process: local-kube runs in it), never
        // another local run's beside it; of this run's, the one on the lowest port.
        let Some((pid, port)) = own_carla() else {
            outln!("           scenario: round {n}: no CARLA of this run to kill");
            return false;
        };
        let killed = std::process::Command::new("kill")
            .args(["-KILL", &pid.to_string()])
            .status()
            .is_ok_and(|s| s.success());
        outln!("           scenario: round {n}: CARLA on port {port} killed: {killed}");
        killed
    }
}

/// The process id and RPC port of this process's descendant CARLA (`./CarlaUE4.sh ...`, not
/// the sidecar that wraps it) on the lowest port, read from `/proc`.
fn own_carla() -> Option<(u32, u16)> {
    let mut parent = std::collections::HashMap::new();
    let mut carla = Vec::new();
    for entry in std::fs::read_dir("/proc").ok()?.flatten() {
        let Some(pid) = entry
            .file_name()
            .to_str()
            .and_then(|n| n.parse::<u32>().ok())
        else {
            continue;
        };
        let Ok(stat) = std::fs::read_to_string(entry.path().join("stat")) else {
            continue;
        };
        // `pid (comm) state ppid ...`: comm may hold spaces and parentheses.
        let ppid = stat
            .rsplit_once(')')
            .and_then(|(_, rest)| rest.split_whitespace().nth(1))
            .and_then(|p| p.parse::<u32>().ok());
        if let Some(ppid) = ppid {
            parent.insert(pid, ppid);
        }
        let argv = std::fs::read(entry.path().join("cmdline")).unwrap_or_default();
        let mut args = argv.split(|b| *b == 0).map(String::from_utf8_lossy);
        if args.next().as_deref() == Some("./CarlaUE4.sh") {
            let port = args.find_map(|a| {
                a.strip_prefix("-carla-rpc-port=")
                    .and_then(|p| p.parse().ok())
            });
            carla.push((pid, port.unwrap_or(u16::MAX)));
        }
    }
    let me = std::process::id();
    let ours = |mut pid: u32| {
        while let Some(&up) = parent.get(&pid) {
            if up == me {
                return true;
            }
            pid = up;
        }
        false
    };
    carla
        .into_iter()
        .filter(|(pid, _)| ours(*pid))
        .min_by_key(|(_, port)| *port)
}
