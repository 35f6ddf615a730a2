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
/// the sidecar that wraps it) on the lowest port.
fn own_carla() -> Option<(u32, u16)> {
    let me = nix::unistd::Pid::from_raw(i32::try_from(std::process::id()).ok()?);
    lb_proc::descendants(me)
        .into_iter()
        .filter_map(|pid| {
            let argv = std::fs::read(format!("/proc/{pid}/cmdline")).ok()?;
            let mut args = argv.split(|b| *b == 0).map(String::from_utf8_lossy);
            (args.next().as_deref() == Some("./CarlaUE4.sh")).then_some(())?;
            let port = args.find_map(|a| {
                a.strip_prefix("-carla-rpc-port=")
                    .and_then(|p| p.parse().ok())
            });
            Some((u32::try_from(pid.as_raw()).ok()?, port.unwrap_or(u16::MAX)))
        })
        .min_by_key(|(_, port)| *port)
}
