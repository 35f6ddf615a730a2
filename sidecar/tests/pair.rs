//! `lb-sidecar simulator` and `agent` as the kubelet runs them: whole processes around the
//! fake CARLA and the fake evaluator, with temp dirs standing in for the Job's volumes.

use crate::support;

use std::time::{Duration, Instant};

use nix::sys::signal::Signal;
use support::*;

const LIMIT: Duration = Duration::from_secs(60);

#[test]
fn a_pair_runs_its_routes_and_both_write_done_markers() {
    let vols = Volumes::new();
    let pair = Pair::new(1, "0-4");
    let mut sim = pair.simulator(&vols);
    let mut agent = pair.agent(&vols);
    assert_eq!(agent.wait(LIMIT).code(), Some(0), "{}", agent.log());
    assert_eq!(sim.wait(LIMIT).code(), Some(0), "{}", sim.log());
    assert_eq!(
        vols.markers(),
        ["agent-1.done", "simulator-1.done", "simulator-1.start0"]
    );
    let results = std::fs::read(vols.checkpoint(1)).unwrap();
    assert!(finished(&results, "0-4"));
    assert_eq!(route_ids(&vols.checkpoint(1)).len(), 5);
    let log = vols.agent_log(1);
    assert!(log.contains("Preparing RouteScenario_4"), "{log}");
    assert!(
        log.contains("evaluator started on routes 0-4\n"),
        "not a resume: {log}"
    );
    assert!(
        vols.root()
            .join("logs/agent/agent1/live_results.json")
            .exists(),
        "DEBUG_CHECKPOINT_ENDPOINT is the live results file"
    );
    assert!(vols.simulator_log(1).contains("CARLA accepts connections"));
}

#[test]
fn carla_dying_mid_route_crashes_the_pair_and_the_rerun_resumes_every_route_once() {
    let vols = Volumes::new();
    let once = tempfile::tempdir().unwrap();
    let pair = Pair::new(2, "5-9").with_carla_crash(once.path());
    let mut sim = pair.simulator(&vols);
    let mut agent = pair.agent(&vols);
    assert_eq!(sim.wait(LIMIT).code(), Some(1), "{}", sim.log());
    assert_eq!(agent.wait(LIMIT).code(), Some(1), "{}", agent.log());
    assert_eq!(
        vols.markers(),
        ["agent-2.crash0", "simulator-2.crash0", "simulator-2.start0"]
    );
    let partial = route_ids(&vols.checkpoint(2));
    assert!(partial.len() < 5, "the crash came mid-run: {partial:?}");

    // Both run again on the same volumes (the protocol still counts attempts in one pod).
    let mut sim = pair.simulator(&vols);
    let mut agent = pair.agent(&vols);
    assert_eq!(agent.wait(LIMIT).code(), Some(0), "{}", agent.log());
    assert_eq!(sim.wait(LIMIT).code(), Some(0), "{}", sim.log());
    assert!(vols.marker("simulator-2.start1"));
    assert!(vols.marker("agent-2.done") && vols.marker("simulator-2.done"));
    assert!(
        vols.agent_log(2).contains("(resuming)"),
        "RESUME=1 on the re-run"
    );
    let ids = route_ids(&vols.checkpoint(2));
    let expected: Vec<String> = (5..=9).map(|r| format!("RouteScenario_{r}_rep0")).collect();
    assert_eq!(ids, expected, "every route exactly once");
    assert!(finished(&std::fs::read(vols.checkpoint(2)).unwrap(), "5-9"));
}

#[test]
fn a_silent_evaluator_is_stopped_by_the_watchdog_and_counts_as_a_crash() {
    let vols = Volumes::new();
    let child_pid = vols.root().join("child.pid");
    let pair = Pair::new(3, "0-4")
        .with("LB_MAX_IDLE_SECONDS", "2")
        .with("FAKE_EVALUATOR_HANG_AT_ROUTE", "2")
        .with("FAKE_EVALUATOR_SPAWN_CHILD", "group")
        .with(
            "FAKE_EVALUATOR_CHILD_PID_FILE",
            child_pid.display().to_string(),
        );
    let mut sim = pair.simulator(&vols);
    let mut agent = pair.agent(&vols);
    let started = Instant::now();
    assert_eq!(agent.wait(LIMIT).code(), Some(1), "{}", agent.log());
    assert!(started.elapsed() < Duration::from_secs(20));
    assert_eq!(sim.wait(LIMIT).code(), Some(1), "{}", sim.log());
    assert!(vols.marker("agent-3.crash0") && vols.marker("simulator-3.crash0"));
    assert!(vols
        .agent_log(3)
        .contains("no output for 2s: stopping the evaluator"));
    // The participant's child left the process group; it is gone all the same.
    let pid: i32 = std::fs::read_to_string(&child_pid)
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    assert!(!alive(pid), "orphan {pid} survived the agent");
}

#[test]
fn invalid_results_are_a_crash() {
    let vols = Volumes::new();
    let pair = Pair::new(4, "0-2").with("FAKE_EVALUATOR_GARBAGE", "schema");
    let mut sim = pair.simulator(&vols);
    let mut agent = pair.agent(&vols);
    assert_eq!(agent.wait(LIMIT).code(), Some(1), "{}", agent.log());
    assert_eq!(sim.wait(LIMIT).code(), Some(1), "{}", sim.log());
    assert!(vols.marker("agent-4.crash0"), "{:?}", vols.markers());
    assert!(!vols.marker("agent-4.done"));
    assert!(vols
        .agent_log(4)
        .contains("crash: the results file is invalid"));
}

#[test]
fn the_cancel_marker_stops_both_containers_within_a_poll_without_markers() {
    let vols = Volumes::new();
    let pair = Pair::new(5, "0-4").with("FAKE_EVALUATOR_ROUTE_SECONDS", "30");
    let mut sim = pair.simulator(&vols);
    let mut agent = pair.agent(&vols);
    wait_until("the evaluator runs", LIMIT, || {
        vols.agent_log(5).contains("Running the route")
    });
    std::fs::write(vols.status().join("simulation.cancel"), "").unwrap();
    let cancelled = Instant::now();
    assert_eq!(agent.wait(LIMIT).code(), Some(0));
    assert_eq!(sim.wait(LIMIT).code(), Some(0));
    assert!(
        cancelled.elapsed() < Duration::from_secs(3),
        "took {:?}",
        cancelled.elapsed()
    );
    assert_eq!(vols.markers(), ["simulation.cancel", "simulator-5.start0"]);
}

#[test]
fn sigterm_stops_the_evaluator_and_every_child_and_writes_a_crash_marker() {
    let vols = Volumes::new();
    let child_pid = vols.root().join("child.pid");
    let pair = Pair::new(6, "0-4")
        .with("FAKE_EVALUATOR_ROUTE_SECONDS", "30")
        .with("FAKE_EVALUATOR_SPAWN_CHILD", "stubborn")
        .with(
            "FAKE_EVALUATOR_CHILD_PID_FILE",
            child_pid.display().to_string(),
        );
    let mut sim = pair.simulator(&vols);
    let mut agent = pair.agent(&vols);
    wait_until("the participant's child", LIMIT, || child_pid.exists());
    let pid: i32 = std::fs::read_to_string(&child_pid)
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    assert!(alive(pid));
    agent.signal(Signal::SIGTERM);
    sim.signal(Signal::SIGTERM);
    let sent = Instant::now();
    assert_eq!(agent.wait(LIMIT).code(), Some(1), "{}", agent.log());
    assert_eq!(sim.wait(LIMIT).code(), Some(1), "{}", sim.log());
    // Grace 2 s for the stubborn child, then SIGKILL.
    assert!(
        sent.elapsed() < Duration::from_secs(8),
        "{:?}",
        sent.elapsed()
    );
    assert!(!alive(pid), "the stubborn child survived");
    assert!(vols.marker("agent-6.crash0") && vols.marker("simulator-6.crash0"));
    // The agent's log says the attempt was stopped, not that the participant's code crashed.
    let log = vols.agent_log(6);
    assert!(log.contains("stopped: the pod was asked to stop"), "{log}");
    assert!(!log.contains("crash:"), "{log}");
}

#[test]
fn an_evaluator_that_leaves_a_child_behind_does_not_leave_an_orphan() {
    let vols = Volumes::new();
    let child_pid = vols.root().join("child.pid");
    let pair = Pair::new(7, "0-1")
        .with("FAKE_EVALUATOR_SPAWN_CHILD", "group")
        .with(
            "FAKE_EVALUATOR_CHILD_PID_FILE",
            child_pid.display().to_string(),
        );
    let mut sim = pair.simulator(&vols);
    let mut agent = pair.agent(&vols);
    assert_eq!(agent.wait(LIMIT).code(), Some(0), "{}", agent.log());
    assert_eq!(sim.wait(LIMIT).code(), Some(0));
    let pid: i32 = std::fs::read_to_string(&child_pid)
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    assert!(!alive(pid), "orphan {pid} survived");
}

#[test]
fn an_agent_whose_simulator_never_starts_gives_up_after_the_start_wait() {
    let vols = Volumes::new();
    let pair = Pair::new(8, "0-4").with("LB_START_WAIT_SECONDS", "1");
    let mut agent = pair.agent(&vols);
    assert_eq!(agent.wait(LIMIT).code(), Some(1));
    assert_eq!(vols.markers(), ["agent-8.crash0"]);
}

/// Before CARLA starts, the wrapper names the port the sidecar gave it (in `$1/port`) and waits
/// until something else listens there: the test takes the port between the sidecar's look and
/// CARLA's bind, as a pod starting at the same moment does on a network pods share. CARLA then
/// takes a second to start (the real one takes longer), in which the port answers, not from it.
const PORT_THIEF: &str = r#"if mkdir "$1/raced" 2>/dev/null; then
  echo "$2" > "$1/port.tmp" && mv "$1/port.tmp" "$1/port"
  for _ in $(seq 100); do (exec 3<>"/dev/tcp/127.0.0.1/$2") 2>/dev/null && break; sleep 0.1; done
  sleep 1
fi
exec "$3" -carla-rpc-port="$2" -RenderOffScreen"#;

#[test]
fn a_port_taken_before_carla_binds_it_moves_carla_and_is_no_crash() {
    let vols = Volumes::new();
    let race = tempfile::tempdir().unwrap();
    let pair = Pair::new(5, "0-2");
    let command = [
        "bash".to_owned(),
        "-c".to_owned(),
        PORT_THIEF.to_owned(),
        "carla".to_owned(),
        race.path().display().to_string(),
        "{carla_port}".to_owned(),
        fake("fake-carla").display().to_string(),
    ];
    let mut sim = pair.simulator_running(&vols, &command);
    let named = race.path().join("port");
    wait_until("CARLA's port named", LIMIT, || named.exists());
    let port: u16 = std::fs::read_to_string(&named)
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    // NB: held until the end, so the sidecar must not take the thief's answer for CARLA's.
    let thief = std::net::TcpListener::bind(("0.0.0.0", port)).unwrap();
    let mut agent = pair.agent(&vols);
    assert_eq!(sim.wait(LIMIT).code(), Some(0), "{}", sim.log());
    assert_eq!(agent.wait(LIMIT).code(), Some(0), "{}", agent.log());
    assert_eq!(
        vols.markers(),
        ["agent-5.done", "simulator-5.done", "simulator-5.start0"]
    );
    let log = vols.simulator_log(5);
    assert!(
        log.contains(&format!("port {port} was taken before CARLA could bind it")),
        "{log}"
    );
    let moved: u16 = std::fs::read_to_string(vols.root().join("handoff/port-5"))
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    assert_ne!(moved, port, "the agent was told the port CARLA got");
    assert!(log.contains(&format!("waiting for port {moved}")), "{log}");
    assert!(finished(&std::fs::read(vols.checkpoint(5)).unwrap(), "0-2"));
    drop(thief);
}

#[test]
fn a_simulator_whose_carla_never_opens_its_port_crashes_after_the_ready_wait() {
    let vols = Volumes::new();
    let pair = Pair::new(9, "0-4")
        .with("LB_CARLA_READY_SECONDS", "1")
        .with("LB_END_WAIT_SECONDS", "1")
        .with("FAKE_CARLA_START_DELAY", "30");
    let mut sim = pair.simulator(&vols);
    assert_eq!(sim.wait(LIMIT).code(), Some(1), "{}", sim.log());
    assert_eq!(vols.markers(), ["simulator-9.crash0"]);
    assert!(vols.simulator_log(9).contains("did not accept connections"));
}

#[test]
fn a_bad_variable_is_named_and_nothing_starts() {
    let vols = Volumes::new();
    let pair = Pair::new(10, "0-4").with("LB_PAIR_ID", "zero");
    let mut agent = pair.agent(&vols);
    assert_eq!(
        agent.wait(LIMIT).code(),
        Some(78),
        "EX_CONFIG: the Job fails at once"
    );
    let log = agent.log();
    assert!(
        log.contains("lb-sidecar: InvalidEnvironment: `LB_PAIR_ID` is `zero`"),
        "{log}"
    );
    assert!(vols.markers().is_empty());
}

#[test]
fn an_image_that_cannot_run_the_evaluator_exits_3_so_the_job_fails_at_once() {
    // The shell finds no `python3` (127), and an image without the shell at all.
    let commands: [&[&str]; 2] = [
        &[
            "bash",
            "-c",
            "exec python3-not-in-this-image -u evaluator.py",
        ],
        &["/image/has/no/bash", "-c", "true"],
    ];
    for (i, command) in commands.into_iter().enumerate() {
        let vols = Volumes::new();
        let pair = Pair::new(1, "0-4");
        let mut sim = pair.simulator(&vols);
        let mut agent = pair.agent_running(&vols, command);
        assert_eq!(agent.wait(LIMIT).code(), Some(3), "{i}: {}", agent.log());
        // The crash marker ends the simulator's side too, so the pod ends.
        assert_eq!(sim.wait(LIMIT).code(), Some(1), "{i}: {}", sim.log());
        assert!(vols.marker("agent-1.crash0"), "{i}");
    }
}

#[test]
fn an_evaluator_that_fails_by_itself_is_an_ordinary_crash() {
    let vols = Volumes::new();
    let pair = Pair::new(1, "0-4");
    let mut sim = pair.simulator(&vols);
    let mut agent = pair.agent_running(&vols, &["bash", "-c", "exit 2"]);
    assert_eq!(agent.wait(LIMIT).code(), Some(1), "{}", agent.log());
    assert_eq!(sim.wait(LIMIT).code(), Some(1), "{}", sim.log());

    // A 127 once a route of the pair has finished: the image did run the evaluator, so the
    // next pod may well pass; an ordinary crash.
    let vols = Volumes::new();
    let once = tempfile::tempdir().unwrap();
    let pair = Pair::new(2, "5-9").with_carla_crash(once.path());
    let (mut sim, mut agent) = (pair.simulator(&vols), pair.agent(&vols));
    assert_eq!(agent.wait(LIMIT).code(), Some(1), "{}", agent.log());
    assert_eq!(sim.wait(LIMIT).code(), Some(1), "{}", sim.log());
    assert!(!route_ids(&vols.checkpoint(2)).is_empty());
    // The next pod starts from the results alone, as init leaves them.
    for marker in vols.markers() {
        std::fs::remove_file(vols.status().join(marker)).unwrap();
    }
    let mut sim = pair.simulator(&vols);
    let mut agent = pair.agent_running(&vols, &["bash", "-c", "exit 127"]);
    assert_eq!(agent.wait(LIMIT).code(), Some(1), "{}", agent.log());
    assert_eq!(sim.wait(LIMIT).code(), Some(1), "{}", sim.log());
}
