//! Container processes: one process group each, optionally in a private mount namespace made by
//! util-linux `unshare`; signals to whole groups; a registry so shutdown can kill everything.

use std::collections::{BTreeMap, BTreeSet};
use std::io;
use std::path::{Path, PathBuf};
use std::process::{ExitStatus, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use nix::sys::signal::{killpg, Signal};
use nix::unistd::Pid;
use tokio::process::{Child, Command};

use super::mounts::Mount;
use crate::config::Isolation;

/// How containers get their own mounts.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Namespaces {
    /// No isolation: containers that need mounts cannot run.
    None,
    /// `unshare --mount` (root).
    Mount(Tools),
    /// `unshare --user --map-root-user --mount` (unprivileged).
    UserMount(Tools),
}

/// Host programs the mount helper runs.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Tools {
    /// util-linux `unshare`.
    pub unshare: PathBuf,
    /// util-linux `mount`.
    pub mount: PathBuf,
    /// A POSIX shell.
    pub sh: PathBuf,
}

fn find_program(name: &str) -> Option<PathBuf> {
    let path = std::env::var("PATH").unwrap_or_default();
    let dirs: Vec<&str> = path
        .split(':')
        .filter(|d| !d.is_empty())
        .chain(["/usr/local/bin", "/usr/bin", "/bin", "/usr/sbin", "/sbin"])
        .collect();
    dirs.into_iter()
        .map(|d| Path::new(d).join(name))
        .find(|p| p.is_file())
}

fn works(program: &Path, args: &[&str]) -> bool {
    std::process::Command::new(program)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// Picks the isolation this machine supports for the configured mode.
pub fn detect(isolation: Isolation) -> Result<Namespaces, String> {
    if isolation == Isolation::None {
        return Ok(Namespaces::None);
    }
    let tools = match (
        find_program("unshare"),
        find_program("mount"),
        find_program("sh"),
    ) {
        (Some(unshare), Some(mount), Some(sh)) => Some(Tools { unshare, mount, sh }),
        _ => None,
    };
    let found = tools.and_then(|t| {
        let root = nix::unistd::geteuid().is_root();
        if root && works(&t.unshare, &["--mount", "--propagation", "private", "true"]) {
            Some(Namespaces::Mount(t))
        } else if works(
            &t.unshare,
            &[
                "--user",
                "--map-root-user",
                "--mount",
                "--propagation",
                "private",
                "true",
            ],
        ) {
            Some(Namespaces::UserMount(t))
        } else {
            None
        }
    });
    match (found, isolation) {
        (Some(ns), _) => Ok(ns),
        (None, Isolation::Auto) => Ok(Namespaces::None),
        (None, _) => Err(
            "need util-linux `unshare` and `mount`, and either root or unprivileged user namespaces"
                .into(),
        ),
    }
}

/// The shell run inside the new mount namespace: bind each mount, remount read-only ones,
/// enter the working directory, exec the container command.
const MOUNT_SCRIPT: &str = r#"set -e
wd=$1; n=$2; mount=$3; shift 3
while [ "$n" -gt 0 ]; do
  "$mount" --bind -- "$1" "$2"
  if [ "$3" = ro ]; then "$mount" -o remount,bind,ro -- "$2"; fi
  shift 3
  n=$((n - 1))
done
cd -- "$wd"
exec "$@"
"#;

/// What to run for one container attempt.
pub struct Launch<'a> {
    /// Program and arguments.
    pub argv: &'a [String],
    /// The whole environment.
    pub env: &'a BTreeMap<String, String>,
    /// Working directory (inside the container's view).
    pub workdir: &'a Path,
    /// Bind mounts (parents first).
    pub mounts: &'a [Mount],
    /// File receiving stdout and stderr.
    pub log: &'a Path,
}

/// Builds the command: direct when nothing is mounted, else through `unshare` and the helper.
pub fn command(launch: &Launch<'_>, ns: &Namespaces) -> io::Result<Command> {
    let log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(launch.log)?;
    let log_err = log.try_clone()?;
    let mut cmd = if launch.mounts.is_empty() {
        let mut c = Command::new(&launch.argv[0]);
        c.args(&launch.argv[1..]).current_dir(launch.workdir);
        c
    } else {
        let (tools, user) = match ns {
            Namespaces::Mount(t) => (t, false),
            Namespaces::UserMount(t) => (t, true),
            Namespaces::None => {
                return Err(io::Error::other(
                    "volume mounts need a mount namespace, and isolation is off",
                ))
            }
        };
        let mut c = Command::new(&tools.unshare);
        if user {
            c.args(["--user", "--map-root-user"]);
        }
        c.args(["--mount", "--propagation", "private", "--"])
            .arg(&tools.sh)
            .arg("-c")
            .arg(MOUNT_SCRIPT)
            .arg("local-kube-mount")
            .arg(launch.workdir)
            .arg(launch.mounts.len().to_string())
            .arg(&tools.mount);
        for m in launch.mounts {
            c.arg(&m.src)
                .arg(&m.dst)
                .arg(if m.read_only { "ro" } else { "rw" });
        }
        c.args(launch.argv);
        // NB: the helper needs a directory that exists before the mounts.
        c.current_dir("/");
        c
    };
    cmd.env_clear()
        .envs(launch.env)
        .stdin(Stdio::null())
        .stdout(Stdio::from(log))
        .stderr(Stdio::from(log_err))
        .process_group(0)
        .kill_on_drop(true);
    Ok(cmd)
}

/// Sends `sig` to a process group; refuses the groups that would hit init, everything, or us.
pub fn signal_group(pgid: i32, sig: Signal) -> bool {
    if pgid <= 1 || pgid == nix::unistd::getpgrp().as_raw() {
        return false;
    }
    killpg(Pid::from_raw(pgid), sig).is_ok()
}

/// A process a container started, named by its pid and its start (the pid alone may be
/// another's by the time it is signalled).
pub type Escaped = (Pid, u64);

/// The processes below the container whose first process leads group `pgid` (its pid is the
/// group's id), wherever their group: a container's PID namespace ends them all with it, while
/// here one in a group of its own (a simulator's CARLA) would outlive a signal to the group.
/// Read before that signal: once the first process is gone, its children are init's.
pub fn escapees(pgid: i32) -> Vec<Escaped> {
    if pgid <= 1 {
        return Vec::new();
    }
    (lb_proc::descendants(Pid::from_raw(pgid)).into_iter())
        .filter_map(|pid| Some((pid, started_at(pid)?)))
        .collect()
}

/// SIGKILLs each of `escaped` that is still the process it was.
pub fn kill_escaped(escaped: Vec<Escaped>) {
    for (pid, started) in escaped {
        if started_at(pid) == Some(started) {
            let _ = nix::sys::signal::kill(pid, Signal::SIGKILL);
        }
    }
}

/// When `pid` started (clock ticks after boot, `/proc/<pid>/stat` field 22): with the pid, it
/// names one process; `None` when it is gone.
fn started_at(pid: Pid) -> Option<u64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // NB: the command name may hold spaces and parentheses; fields follow the last `)`.
    let rest = &stat[stat.rfind(')')? + 1..];
    rest.split_whitespace().nth(19)?.parse().ok()
}

/// Whether any live (non-zombie) process belongs to the group.
pub fn group_alive(pgid: i32) -> bool {
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return signal_group_probe(pgid);
    };
    entries.flatten().any(|e| {
        let name = e.file_name();
        let Some(pid) = name
            .to_str()
            .filter(|s| s.bytes().all(|b| b.is_ascii_digit()))
        else {
            return false;
        };
        let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
            return false;
        };
        // NB: the command name may hold spaces and parentheses; fields follow the last `)`.
        let Some(rest) = stat.rfind(')').map(|i| &stat[i + 1..]) else {
            return false;
        };
        let mut fields = rest.split_whitespace();
        let state = fields.next();
        let _ppid = fields.next();
        let pgrp = fields.next().and_then(|p| p.parse::<i32>().ok());
        pgrp == Some(pgid) && state != Some("Z") && state != Some("X")
    })
}

fn signal_group_probe(pgid: i32) -> bool {
    pgid > 1 && killpg(Pid::from_raw(pgid), None).is_ok()
}

/// Waits (polling, bounded) until no live process is left in the group.
pub async fn wait_group_gone(pgid: i32, bound: Duration) -> bool {
    let deadline = tokio::time::Instant::now() + bound;
    loop {
        if !group_alive(pgid) {
            return true;
        }
        if tokio::time::Instant::now() >= deadline {
            return false;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// Exit code as Kubernetes reports it (128 + signal for a signalled process).
pub fn exit_code(status: &ExitStatus) -> i32 {
    use std::os::unix::process::ExitStatusExt;
    status
        .code()
        .or_else(|| status.signal().map(|s| 128 + s))
        .unwrap_or(-1)
}

/// SIGTERM the container's main process, wait up to `grace` for it, then SIGKILL the group;
/// returns the main process's exit status. As a container runtime does, only the main process
/// is told: the processes it started are its to stop (a pair's sidecar keeps CARLA up until
/// the evaluator has stopped), and whatever is left goes with it, as a PID namespace does:
/// its group, and the processes it started in groups of their own ([`escapees`]).
pub async fn terminate(child: &mut Child, pgid: i32, grace: Duration) -> Option<ExitStatus> {
    let escaped = escapees(pgid);
    let status = stop_main(child, pgid, grace).await;
    kill_escaped(escaped);
    status
}

/// [`terminate`]'s signals to the main process and its group.
async fn stop_main(child: &mut Child, pgid: i32, grace: Duration) -> Option<ExitStatus> {
    if !grace.is_zero() {
        match child.id().and_then(|pid| i32::try_from(pid).ok()) {
            Some(pid) if pid > 1 => {
                let _ = nix::sys::signal::kill(Pid::from_raw(pid), Signal::SIGTERM);
            }
            _ => {
                signal_group(pgid, Signal::SIGTERM);
            }
        }
        if let Ok(Ok(status)) = tokio::time::timeout(grace, child.wait()).await {
            signal_group(pgid, Signal::SIGKILL);
            return Some(status);
        }
    }
    signal_group(pgid, Signal::SIGKILL);
    let status = tokio::time::timeout(Duration::from_secs(5), child.wait())
        .await
        .ok()
        .and_then(Result::ok);
    signal_group(pgid, Signal::SIGKILL);
    status
}

/// Every live container process group, so shutdown can end them all.
#[derive(Debug, Default)]
pub struct Processes {
    inner: Mutex<(BTreeSet<i32>, bool)>,
}

impl Processes {
    /// Spawns and registers the group, unless shutdown has begun.
    pub fn spawn(&self, cmd: &mut Command) -> io::Result<(Child, i32)> {
        let mut inner = self.inner.lock().unwrap_or_else(|e| e.into_inner());
        if inner.1 {
            return Err(io::Error::other("local-kube is shutting down"));
        }
        let child = cmd.spawn()?;
        let pid = child
            .id()
            .and_then(|p| i32::try_from(p).ok())
            .ok_or_else(|| io::Error::other("spawned process has no pid"))?;
        inner.0.insert(pid);
        Ok((child, pid))
    }

    /// Forgets a group whose processes are gone.
    pub fn forget(&self, pgid: i32) {
        self.inner
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .0
            .remove(&pgid);
    }

    /// Refuses new processes, SIGTERMs every group, waits up to `grace`, SIGKILLs the rest and
    /// waits (bounded) until they are gone; then, as a container's cgroup would, SIGKILLs
    /// what its processes started in groups of their own (a simulator's CARLA), found as their
    /// descendants before the first signal. Blocking; safe from `Drop`.
    pub fn kill_all(&self, grace: Duration) {
        let groups: Vec<i32> = {
            let mut inner = self.inner.lock().unwrap_or_else(|e| e.into_inner());
            inner.1 = true;
            std::mem::take(&mut inner.0).into_iter().collect()
        };
        if groups.is_empty() {
            return;
        }
        let escaped: Vec<Escaped> = groups.iter().flat_map(|&g| escapees(g)).collect();
        for g in &groups {
            signal_group(*g, Signal::SIGTERM);
        }
        let wait_until = |deadline: Instant| {
            while Instant::now() < deadline && groups.iter().any(|g| group_alive(*g)) {
                std::thread::sleep(Duration::from_millis(20));
            }
        };
        wait_until(Instant::now() + grace);
        for g in &groups {
            signal_group(*g, Signal::SIGKILL);
        }
        kill_escaped(escaped);
        wait_until(Instant::now() + Duration::from_secs(2));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_process_start_names_it_and_a_gone_one_has_none() {
        let me = nix::unistd::getpid();
        let start = started_at(me).expect("our own start");
        assert_eq!(started_at(me), Some(start));
        assert!(started_at(nix::unistd::getppid()).is_some_and(|parent| parent <= start));
        assert_eq!(started_at(Pid::from_raw(i32::MAX)), None);
    }

    #[test]
    fn signal_group_refuses_init_everything_and_ourselves() {
        assert!(!signal_group(0, Signal::SIGCONT));
        assert!(!signal_group(1, Signal::SIGCONT));
        assert!(!signal_group(-5, Signal::SIGCONT));
        assert!(!signal_group(
            nix::unistd::getpgrp().as_raw(),
            Signal::SIGCONT
        ));
    }

    #[tokio::test]
    async fn terminate_ends_the_whole_group() {
        let dir = tempfile::tempdir().unwrap();
        let log = dir.path().join("log");
        let env: BTreeMap<String, String> = [("PATH".into(), "/usr/bin:/bin".into())].into();
        let argv: Vec<String> = ["sh", "-c", "sleep 30 & echo $! > child; exec sleep 30"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        let launch = Launch {
            argv: &argv,
            env: &env,
            workdir: dir.path(),
            mounts: &[],
            log: &log,
        };
        let procs = Processes::default();
        let (mut child, pgid) = procs
            .spawn(&mut command(&launch, &Namespaces::None).unwrap())
            .unwrap();
        let deadline = Instant::now() + Duration::from_secs(5);
        while !dir.path().join("child").exists() && Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        assert!(group_alive(pgid));
        let status = terminate(&mut child, pgid, Duration::from_secs(2))
            .await
            .unwrap();
        assert_eq!(exit_code(&status), 128 + 15);
        let deadline = Instant::now() + Duration::from_secs(3);
        while group_alive(pgid) && Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        assert!(!group_alive(pgid), "background child survived");
        procs.kill_all(Duration::from_millis(100));
        assert!(procs
            .spawn(&mut command(&launch, &Namespaces::None).unwrap())
            .is_err());
    }
}
