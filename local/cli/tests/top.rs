//! `lbctl top` as an operator uses it: in a terminal (tmux, from Debian's packages), against
//! a local stack whose submissions queue and run, read off the screen, and quit with a key.

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::local_run::lbctl;

/// A tmux server of the test's own (its own socket), killed on drop.
struct Tmux {
    socket: String,
}

impl Tmux {
    fn new() -> Tmux {
        Tmux {
            socket: format!("lbctl-top-{}", std::process::id()),
        }
    }

    fn run(&self, args: &[&str]) -> String {
        let out = Command::new("tmux")
            .args(["-L", &self.socket])
            .args(args)
            .output()
            .expect("tmux runs (make test installs it)");
        assert!(
            out.status.success(),
            "tmux {args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    /// The pane's screen as a person sees it.
    fn screen(&self) -> String {
        self.run(&["capture-pane", "-p", "-t", "top"])
    }

    /// Waits (at most `within`) for the screen to hold every one of `wanted`.
    fn wait_for(&self, wanted: &[&str], within: Duration) -> String {
        let started = Instant::now();
        loop {
            let screen = self.screen();
            if wanted.iter().all(|w| screen.contains(w)) {
                return screen;
            }
            assert!(
                started.elapsed() < within,
                "waited for {wanted:?}; the screen:\n{screen}"
            );
            std::thread::sleep(Duration::from_millis(250));
        }
    }
}

impl Drop for Tmux {
    fn drop(&mut self) {
        let _ = Command::new("tmux")
            .args(["-L", &self.socket, "kill-server"])
            .output();
    }
}

/// A local run left going in the background, stopped (SIGINT, as Ctrl-C) on drop.
struct Run {
    child: Child,
    log: PathBuf,
    _dir: tempfile::TempDir,
}

impl Run {
    fn start(args: &[&str]) -> Run {
        let dir = tempfile::tempdir().unwrap();
        let log = dir.path().join("run.log");
        let child = Command::new(lbctl())
            .args(["local", "run"])
            .args(args)
            .stdout(std::fs::File::create(&log).unwrap())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        Run {
            child,
            log,
            _dir: dir,
        }
    }

    /// The file `lbctl local run` says points lbctl at its stack.
    fn lbctl_env(&self) -> PathBuf {
        let started = Instant::now();
        loop {
            let log = std::fs::read_to_string(&self.log).unwrap_or_default();
            let line = log
                .lines()
                .find_map(|l| l.split_once("lbctl against this stack: . "));
            if let Some((_, rest)) = line {
                return PathBuf::from(rest.split_whitespace().next().unwrap());
            }
            assert!(
                started.elapsed() < Duration::from_secs(120),
                "no stack:\n{log}"
            );
            std::thread::sleep(Duration::from_millis(250));
        }
    }
}

impl Drop for Run {
    fn drop(&mut self) {
        let _ = nix::sys::signal::kill(
            nix::unistd::Pid::from_raw(self.child.id() as i32),
            nix::sys::signal::Signal::SIGINT,
        );
        let _ = self.child.wait();
    }
}

#[test]
#[ignore = "needs moto and tmux"]
fn top_in_a_terminal_shows_the_queue_and_the_runs_and_quits_on_q() {
    // Six submissions of two pairs on four GPUs, two a team at most: two run, four wait (one
    // of them for its team's cap), for minutes.
    let run = Run::start(&[
        "--submissions",
        "6",
        "--teams",
        "3,2,1",
        "--team-limit",
        "2",
        "--gpus",
        "4",
        "--workers",
        "2",
        "--routes",
        "4",
        "--route-seconds",
        "40",
        "--timeout",
        "900",
    ]);
    let env = run.lbctl_env();
    let tmux = Tmux::new();
    // As at a shell: the exit status said once it ends, and the shell waits.
    let command = format!(
        ". '{}' && '{}' top --leaderboard 2.0 --interval 1; echo \"lbctl top exited $?\"; sleep 600",
        env.display(),
        lbctl().display()
    );
    tmux.run(&[
        "new-session",
        "-d",
        "-s",
        "top",
        "-x",
        "110",
        "-y",
        "40",
        "bash",
        "-c",
        &command,
    ]);
    let screen = tmux.wait_for(
        &["LEADERBOARD 2.0", "WAITING", "RUNNING", "q quits"],
        Duration::from_secs(120),
    );
    // It drew on the alternate screen, as a full-screen program does.
    assert_eq!(
        tmux.run(&["display", "-p", "-t", "top", "#{alternate_on}"])
            .trim(),
        "1"
    );
    // The queue: the waiting ones, each with its place and what holds it.
    let waiting: Vec<&str> = screen
        .lines()
        .skip_while(|l| !l.trim_start().starts_with("WAITING"))
        .skip(1)
        .take_while(|l| !l.trim().is_empty())
        .collect();
    assert!(!waiting.is_empty(), "{screen}");
    assert!(
        waiting
            .iter()
            .all(|l| l.contains("team cap") || l.contains("GPUs")),
        "{screen}"
    );
    assert!(screen.contains("queue    "), "{screen}");
    // The runs: routes done of 4, on the local node's on-demand capacity, and the node's GPUs.
    let running: Vec<&str> = screen
        .lines()
        .skip_while(|l| !l.trim_start().starts_with("RUNNING"))
        .skip(1)
        .take_while(|l| !l.trim().is_empty())
        .collect();
    assert!(!running.is_empty() && running.len() <= 2, "{screen}");
    assert!(running.iter().all(|l| l.contains("/4")), "{screen}");
    assert!(
        screen.contains("1 node (0 Spot), 4 GPUs paid for"),
        "{screen}"
    );
    // Every line fits the window.
    assert!(screen.lines().all(|l| l.chars().count() <= 110), "{screen}");
    // `q` ends it: exit 0, the terminal given back (the alternate screen left, the shell's
    // own screen as it was).
    tmux.run(&["send-keys", "-t", "top", "q"]);
    let after = tmux.wait_for(&["lbctl top exited 0"], Duration::from_secs(10));
    assert!(!after.contains("LEADERBOARD"), "{after}");
    assert_eq!(
        tmux.run(&["display", "-p", "-t", "top", "#{alternate_on}"])
            .trim(),
        "0"
    );
    drop(run);
}
