//! `lb-sidecar logcopy` (and whole Jobs around it) against moto.

use crate::support;

use std::path::Path;
use std::time::{Duration, Instant};

use nix::sys::signal::Signal;
use support::*;

const LIMIT: Duration = Duration::from_secs(60);

fn key(rel: &str) -> String {
    format!("{SUBMISSION}/{rel}")
}

fn write(root: &Path, rel: &str, bytes: &[u8]) {
    let path = root.join(rel);
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(path, bytes).unwrap();
}

/// Uploads counted from logcopy's own pass lines, from the `skip`-th line on.
fn uploads(lc: &Proc, skip: usize) -> (usize, u64) {
    let passes = lc.events("logcopy pass");
    let n = passes[skip.min(passes.len())..]
        .iter()
        .map(|p| p["fields"]["uploaded"].as_u64().unwrap())
        .sum::<u64>();
    (passes.len(), n)
}

fn wait_passes(lc: &Proc, count: usize) {
    wait_until("logcopy passes", LIMIT, || {
        lc.events("logcopy pass").len() >= count
    });
}

#[test]
#[ignore = "needs moto"]
fn an_unchanged_tree_sends_nothing_and_a_changed_file_is_sent_alone() {
    let moto = Moto::start();
    let vols = Volumes::new();
    let big: Vec<u8> = (0..9 * 1024 * 1024u32).map(|i| (i % 251) as u8).collect();
    write(vols.root(), "logs/agent/agent1/agent.log", b"route 0\n");
    write(vols.root(), "logs/simulator/simulator1.log", &big);
    write(vols.root(), "agent/partial_agent_results1.json", b"{}");
    let mut lc = logcopy(&vols, &moto, None, &[]);
    let first = lc.wait_event("logcopy pass", LIMIT, |_| true);
    assert_eq!(first["fields"]["uploaded"], 3, "{}", lc.log());
    assert_eq!(
        moto.get(&key("logs/simulator/simulator1.log")).unwrap(),
        big
    );

    // Several periods with nothing new: no object is sent.
    let (seen, _) = uploads(&lc, 0);
    wait_passes(&lc, seen + 4);
    assert_eq!(uploads(&lc, 1).1, 0, "{}", lc.log());

    // One file changes: that file only.
    let (seen, _) = uploads(&lc, 0);
    std::fs::OpenOptions::new()
        .append(true)
        .open(vols.root().join("logs/agent/agent1/agent.log"))
        .and_then(|mut f| std::io::Write::write_all(&mut f, b"route 1\n"))
        .unwrap();
    wait_passes(&lc, seen + 3);
    assert_eq!(uploads(&lc, seen).1, 1, "{}", lc.log());
    assert_eq!(
        moto.get(&key("logs/agent/agent1/agent.log")).unwrap(),
        b"route 0\nroute 1\n"
    );

    // Rewritten with the same bytes: hashed, found the same, not sent.
    let (seen, _) = uploads(&lc, 0);
    write(vols.root(), "logs/simulator/simulator1.log", &big);
    wait_passes(&lc, seen + 3);
    assert_eq!(uploads(&lc, seen).1, 0, "{}", lc.log());
    let same: u64 = lc.events("logcopy pass")[seen..]
        .iter()
        .map(|p| p["fields"]["same_content"].as_u64().unwrap())
        .sum();
    assert!(same >= 1, "{}", lc.log());

    lc.signal(Signal::SIGTERM);
    write(vols.status().as_path(), "simulator-1.crash0", b"");
    write(vols.status().as_path(), "agent-1.crash0", b"");
    assert_eq!(lc.wait(LIMIT).code(), Some(0), "{}", lc.log());
}

#[test]
#[ignore = "needs moto"]
fn results_and_markers_are_sent_within_seconds_and_logs_keep_their_period() {
    let moto = Moto::start();
    let vols = Volumes::new();
    write(vols.root(), "logs/agent/agent1/agent.log", b"route 0\n");
    // A long period: only the between-pass check can send within seconds.
    let mut lc = logcopy(&vols, &moto, None, &[("LB_PERIOD_SECONDS", "120")]);
    lc.wait_event("logcopy pass", LIMIT, |_| true);

    write(
        vols.root(),
        "agent/partial_agent_results1.json",
        b"{\"records\": 1}",
    );
    write(
        vols.root(),
        "logs/agent/agent1/agent.log",
        b"route 0\nroute 1\n",
    );
    write(vols.status().as_path(), "simulator-1.start1", b"");
    // Not wake-worthy: a file next to the results that is not one.
    write(vols.root(), "agent/notes.json", b"{}");
    // Sent long before the next full pass (how soon is a benchmark's to measure).
    wait_until("the results file and the marker in S3", LIMIT, || {
        moto.get(&key("agent/partial_agent_results1.json"))
            .is_some()
            && moto
                .get(&key("containers-status/simulator-1.start1"))
                .is_some()
    });
    assert_eq!(lc.events("logcopy pass").len(), 1, "no full pass meanwhile");
    // The log and the other file wait for the next full pass (120 s away).
    assert_eq!(
        moto.get(&key("logs/agent/agent1/agent.log")).unwrap(),
        b"route 0\n"
    );
    assert!(moto.get(&key("agent/notes.json")).is_none());
    // A second change of the results file is sent again; an unchanged one is not re-sent.
    write(
        vols.root(),
        "agent/partial_agent_results1.json",
        b"{\"records\": 2}",
    );
    wait_until("the new results in S3", LIMIT, || {
        moto.get(&key("agent/partial_agent_results1.json"))
            .as_deref()
            == Some(b"{\"records\": 2}".as_slice())
    });
    assert_eq!(lc.events("logcopy pass").len(), 1, "no full pass meanwhile");

    lc.signal(Signal::SIGTERM);
    assert_eq!(lc.wait(LIMIT).code(), Some(0), "{}", lc.log());
    // The final upload on SIGTERM sends the log.
    assert_eq!(
        moto.get(&key("logs/agent/agent1/agent.log")).unwrap(),
        b"route 0\nroute 1\n"
    );
}

#[test]
#[ignore = "needs moto"]
fn another_pairs_results_and_markers_and_unnamed_files_never_leave_the_pod() {
    let moto = Moto::start();
    let vols = Volumes::new();
    // This Job runs pair 1. Its participant's code writes pair 2's results and markers, a
    // cancel of its own, and files the protocol does not name, rewritten often.
    write(
        vols.root(),
        "agent/partial_agent_results1.json",
        b"{\"mine\": 1}",
    );
    write(
        vols.root(),
        "agent/partial_agent_results2.json",
        b"{\"forged\": 1}",
    );
    write(vols.status().as_path(), "simulator-1.start1", b"");
    write(vols.status().as_path(), "agent-2.done", b"");
    write(vols.status().as_path(), "simulation.cancel", b"");
    write(vols.status().as_path(), "flood.txt", b"1");
    write(vols.root(), "agent_results.json", b"{}");
    // Marker names beyond any attempt a pod reaches, a "marker" with a body, and a file at
    // the top of the logs volume: none is the protocol's or the evaluation's logs.
    for n in 16..40 {
        write(
            vols.status().as_path(),
            &format!("simulator-1.start{n}"),
            b"",
        );
    }
    write(vols.status().as_path(), "simulator-1.start0", &[7; 4096]);
    write(vols.root(), "logs/fill.bin", &[0; 64 * 1024]);
    // The evaluation's logs, each tagged for the bucket's rules.
    write(vols.root(), "logs/agent/agent1/agent.log", b"route 0\n");
    write(
        vols.root(),
        "recorder/pair1/RouteScenario_0_rep0.log",
        b"CARLA",
    );
    // Another pair's recording, and a name no route has, in the recordings' folders.
    write(
        vols.root(),
        "recorder/pair2/RouteScenario_5_rep0.log",
        b"CARLA",
    );
    write(vols.root(), "recorder/pair1/notes.txt", b"x");
    let mut lc = logcopy(&vols, &moto, None, &[]);
    let first = lc.wait_event("logcopy pass", LIMIT, |_| true);
    assert_eq!(first["fields"]["refused"], 5 + 24 + 4, "{}", lc.log());
    // Rewritten many times between passes: still nothing of it leaves.
    for n in 0..20 {
        write(
            vols.status().as_path(),
            "flood.txt",
            format!("{n}").as_bytes(),
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    // The cancel it saw ends its Job: it makes its final upload and leaves by itself (a
    // SIGTERM here would race the done marker's upload on a busy machine).
    assert_eq!(lc.wait(LIMIT).code(), Some(0), "{}", lc.log());
    assert!(moto
        .get(&key("agent/partial_agent_results1.json"))
        .is_some());
    assert!(moto
        .get(&key("containers-status/simulator-1.start1"))
        .is_some());
    for foreign in [
        "agent/partial_agent_results2.json",
        "containers-status/agent-2.done",
        "containers-status/simulation.cancel",
        "containers-status/flood.txt",
        "agent_results.json",
        "containers-status/simulator-1.start16",
        "containers-status/simulator-1.start0",
        "logs/fill.bin",
        "recorder/pair2/RouteScenario_5_rep0.log",
        "recorder/pair1/notes.txt",
    ] {
        assert!(moto.get(&key(foreign)).is_none(), "{foreign} was uploaded");
    }
    // Its own start and, the cancel it saw being the end of its Job, its done marker.
    let markers = moto.keys(&key("containers-status/"));
    let expected =
        ["logcopy-0.done", "simulator-1.start1"].map(|m| key(&format!("containers-status/{m}")));
    assert_eq!(markers, expected);
    // What logcopy refused, each name once however often it was rewritten, and the logs'
    // bytes it stored.
    let report = moto.get(&key("logs/logcopy/job0.json")).unwrap();
    let report: serde_json::Value = serde_json::from_slice(&report).unwrap();
    assert_eq!(report["refused_files"], 5 + 24 + 4, "{report}");
    assert_eq!(report["log_bytes"], 8 + 5, "{report}");
    assert_eq!(
        moto.tags(&key("logs/agent/agent1/agent.log")),
        ["retention=log"]
    );
    assert_eq!(
        moto.tags(&key("recorder/pair1/RouteScenario_0_rep0.log")),
        ["retention=recording"]
    );
}

#[test]
#[ignore = "needs moto"]
fn re_created_markers_are_sent_once_and_empty_files_stop_at_the_pair_s_count() {
    let moto = Moto::start();
    let vols = Volumes::new();
    let extra = [
        ("RUST_LOG", "info,sidecar::logcopy=debug"),
        ("LB_MAX_LOG_OBJECTS", "30"),
    ];
    let mut lc = logcopy(&vols, &moto, None, &extra);
    lc.wait_event("logcopy pass", LIMIT, |_| true);
    // Its 14 in-bound marker names, deleted and written again every 300 ms for 6 s: each
    // upload would wake the Monitor.
    let status = vols.status();
    let names: Vec<String> = (0..14).map(|n| format!("simulator-1.start{n}")).collect();
    let until = Instant::now() + Duration::from_secs(6);
    while Instant::now() < until {
        for name in &names {
            let _ = std::fs::remove_file(status.join(name));
            write(status.as_path(), name, b"");
        }
        std::thread::sleep(Duration::from_millis(300));
    }
    // Waves of 40 empty log files, each wave deleted and written anew.
    for wave in 0..3 {
        for n in 0..40 {
            write(vols.root(), &format!("logs/agent/agent1/w{wave}-{n}"), b"");
        }
        let (seen, _) = uploads(&lc, 0);
        wait_passes(&lc, seen + 2);
        std::fs::remove_dir_all(vols.root().join("logs/agent/agent1")).unwrap();
    }
    lc.signal(Signal::SIGTERM);
    assert_eq!(lc.wait(LIMIT).code(), Some(0), "{}", lc.log());
    let marker_puts = (lc.events("uploaded").iter())
        .filter(|e| (e["fields"]["key"].as_str()).is_some_and(|k| k.contains("simulator-1.start")))
        .count();
    assert_eq!(marker_puts, 14, "{}", lc.log());
    let objects = moto.keys(&key("logs/agent/agent1/"));
    assert_eq!(objects.len(), 30, "{objects:?}");
    let report = moto.get(&key("logs/logcopy/job0.json")).unwrap();
    let report: serde_json::Value = serde_json::from_slice(&report).unwrap();
    assert_eq!(report["log_objects"], 30, "{report}");
    // The 90 files past the count, each name once (and the markers written again that a
    // pass found gone first, as the timing falls).
    let refused = report["refused_files"].as_u64().unwrap();
    assert!((90..=90 + 14).contains(&refused), "{report}");
}

#[test]
#[ignore = "needs moto"]
fn sigterm_makes_a_final_upload_and_exits_cleanly_without_the_done_marker() {
    let moto = Moto::start();
    let vols = Volumes::new();
    write(vols.root(), "logs/agent/agent1/agent.log", b"one\n");
    let mut lc = logcopy(&vols, &moto, None, &[("LB_PERIOD_SECONDS", "30")]);
    lc.wait_event("logcopy pass", LIMIT, |_| true);
    write(vols.root(), "logs/agent/agent1/agent.log", b"one\ntwo\n");
    lc.signal(Signal::SIGTERM);
    // The pair gets SIGTERM too and writes its markers a moment later.
    std::thread::sleep(Duration::from_millis(300));
    write(vols.status().as_path(), "simulator-1.crash0", b"");
    write(vols.status().as_path(), "agent-1.crash0", b"");
    let sent = Instant::now();
    assert_eq!(lc.wait(LIMIT).code(), Some(0), "{}", lc.log());
    assert!(sent.elapsed() < Duration::from_secs(10));
    assert_eq!(
        moto.get(&key("logs/agent/agent1/agent.log")).unwrap(),
        b"one\ntwo\n"
    );
    assert!(moto.exists(&key("containers-status/agent-1.crash0")));
    assert!(!moto.exists(&key("containers-status/logcopy-0.done")));
}

#[test]
#[ignore = "needs moto"]
fn a_new_pod_does_not_write_again_the_results_init_restored_but_writes_a_changed_one() {
    let moto = Moto::start();
    let vols = Volumes::new();
    // As init leaves them: pair 1's results as S3 has them, pair 2's (another Job's pod of
    // this one) changed since.
    let (mine, changed) = (
        "agent/partial_agent_results1.json",
        "agent/partial_agent_results2.json",
    );
    moto.put(&key(mine), b"{\"routes\": 3}");
    moto.put(&key(changed), b"{\"routes\": 3}");
    write(vols.root(), mine, b"{\"routes\": 3}");
    write(vols.root(), changed, b"{\"routes\": 4}");
    let mut lc = logcopy(&vols, &moto, None, &[("LB_PAIRS", "1,2")]);
    let first = lc.wait_event("logcopy pass", LIMIT, |_| true);
    // Only the changed one went up: the restored one's object (and its time) stays as it was.
    assert_eq!(first["fields"]["uploaded"], 1, "{}", lc.log());
    assert_eq!(moto.get(&key(changed)).unwrap(), b"{\"routes\": 4}");
    lc.signal(Signal::SIGTERM);
    assert_eq!(lc.wait(LIMIT).code(), Some(0), "{}", lc.log());
}

#[test]
#[ignore = "needs moto"]
fn a_recording_carla_finished_is_sent_within_seconds_and_the_one_it_writes_waits() {
    let moto = Moto::start();
    let vols = Volumes::new();
    // A long period: only the between-pass check can send within seconds.
    let mut lc = logcopy(&vols, &moto, None, &[("LB_PERIOD_SECONDS", "120")]);
    lc.wait_event("logcopy pass", LIMIT, |_| true);
    let (done, writing) = (
        "recorder/pair1/RouteScenario_0_rep0.log",
        "recorder/pair1/RouteScenario_1_rep0.log",
    );
    write(vols.root(), done, b"route 0 recorded");
    write(vols.root(), writing, b"route 1 so far");
    let earlier = std::time::SystemTime::now() - Duration::from_secs(30);
    std::fs::File::options()
        .write(true)
        .open(vols.root().join(done))
        .and_then(|f| f.set_modified(earlier))
        .unwrap();
    wait_until("the finished recording in S3", LIMIT, || {
        moto.get(&key(done)).is_some()
    });
    assert_eq!(lc.events("logcopy pass").len(), 1, "no full pass meanwhile");
    assert_eq!(moto.tags(&key(done)), ["retention=recording"]);
    // The one still being written waits for the period (or the final upload).
    std::thread::sleep(Duration::from_secs(3));
    assert!(moto.get(&key(writing)).is_none(), "{}", lc.log());

    lc.signal(Signal::SIGTERM);
    write(vols.status().as_path(), "simulator-1.crash0", b"");
    write(vols.status().as_path(), "agent-1.crash0", b"");
    assert_eq!(lc.wait(LIMIT).code(), Some(0), "{}", lc.log());
    assert_eq!(moto.get(&key(writing)).unwrap(), b"route 1 so far");
}

#[test]
#[ignore = "needs moto"]
fn on_sigterm_the_results_reach_s3_at_once_even_if_the_pod_is_killed_soon_after() {
    let moto = Moto::start();
    let vols = Volumes::new();
    let results = "agent/partial_agent_results1.json";
    write(vols.root(), results, b"{\"routes\": 1}");
    // A long period and no wake check yet: only SIGTERM's own upload can send it in time.
    let mut lc = logcopy(&vols, &moto, None, &[("LB_PERIOD_SECONDS", "30")]);
    lc.wait_event("logcopy pass", LIMIT, |_| true);
    write(vols.root(), results, b"{\"routes\": 2}");
    lc.signal(Signal::SIGTERM);
    // The pairs never settle, and the pod is killed before logcopy's next look (1 s).
    std::thread::sleep(Duration::from_millis(500));
    lc.signal(Signal::SIGKILL);
    lc.wait(LIMIT);
    assert_eq!(moto.get(&key(results)).unwrap(), b"{\"routes\": 2}");
}

#[test]
#[ignore = "needs moto"]
fn an_s3_outage_loses_nothing() {
    let moto = Moto::start();
    let proxy = Proxy::start(moto.server.addr());
    let vols = Volumes::new();
    write(vols.root(), "logs/agent/agent1/a.log", b"a1");
    let mut lc = logcopy(&vols, &moto, Some(&proxy.endpoint()), &[]);
    lc.wait_event("logcopy pass", LIMIT, |p| p["fields"]["uploaded"] == 1);

    proxy.set_up(false);
    write(vols.root(), "logs/agent/agent1/a.log", b"a1 a2");
    write(vols.root(), "logs/agent/agent1/b.log", b"b1");
    let big: Vec<u8> = (0..10 * 1024 * 1024u32).map(|i| (i % 241) as u8).collect();
    write(vols.root(), "logs/agent/agent1/c.bin", &big);
    lc.wait_event("S3 is failing; the next pass retries", LIMIT, |e| {
        e["fields"]["failures"].as_u64() >= Some(2)
    });
    assert_eq!(
        moto.get(&key("logs/agent/agent1/a.log")).unwrap(),
        b"a1",
        "nothing got through"
    );

    proxy.set_up(true);
    wait_until("everything uploaded", LIMIT, || {
        moto.get(&key("logs/agent/agent1/a.log")).as_deref() == Some(&b"a1 a2"[..])
            && moto.get(&key("logs/agent/agent1/b.log")).as_deref() == Some(&b"b1"[..])
            && moto.get(&key("logs/agent/agent1/c.bin")).as_deref() == Some(&big[..])
    });
    lc.signal(Signal::SIGTERM);
    write(vols.status().as_path(), "simulator-1.crash0", b"");
    write(vols.status().as_path(), "agent-1.crash0", b"");
    assert_eq!(lc.wait(LIMIT).code(), Some(0), "{}", lc.log());
}

#[test]
#[ignore = "needs moto"]
fn a_whole_job_leaves_finished_partial_results_ready_for_merge_in_s3() {
    let moto = Moto::start();
    let vols = Volumes::new();
    let pair = Pair::new(1, "0-4");
    let mut lc = logcopy(&vols, &moto, None, &[]);
    let mut sim = pair.simulator(&vols);
    let mut agent = pair.agent(&vols);
    assert_eq!(agent.wait(LIMIT).code(), Some(0), "{}", agent.log());
    assert_eq!(sim.wait(LIMIT).code(), Some(0), "{}", sim.log());
    assert_eq!(lc.wait(LIMIT).code(), Some(0), "{}", lc.log());

    let keys = moto.keys(SUBMISSION);
    for expected in [
        "agent/partial_agent_results1.json",
        "logs/agent/agent1/agent.log",
        "logs/agent/agent1/live_results.json",
        "logs/simulator/simulator1.log",
        "containers-status/simulator-1.start0",
        "containers-status/agent-1.done",
        "containers-status/simulator-1.done",
        "containers-status/logcopy-0.done",
    ] {
        assert!(
            keys.contains(&key(expected)),
            "{expected} missing from {keys:?}"
        );
    }
    let results = moto.get(&key("agent/partial_agent_results1.json")).unwrap();
    assert!(finished(&results, "0-4"));
    // What Monitor does with it: the merge.
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("worker1.json");
    std::fs::write(&file, &results).unwrap();
    let out = std::process::Command::new(SIDECAR)
        .args(["merge", "--expect-routes", "5", "--subsets", "0-4", "--out"])
        .arg(dir.path().join("out"))
        .arg(&file)
        .output()
        .unwrap();
    assert!(out.status.success());
    assert!(String::from_utf8_lossy(&out.stdout).contains("complete"));
}

#[test]
#[ignore = "needs moto"]
fn a_cancel_in_s3_stops_every_process_within_one_period() {
    let moto = Moto::start();
    let vols = Volumes::new();
    let pair = Pair::new(1, "0-4").with("FAKE_EVALUATOR_ROUTE_SECONDS", "30");
    let mut lc = logcopy(&vols, &moto, None, &[]);
    let mut sim = pair.simulator(&vols);
    let mut agent = pair.agent(&vols);
    wait_until("the evaluator runs", LIMIT, || {
        vols.agent_log(1).contains("Running the route")
    });
    moto.put(&key("containers-status/simulation.cancel"), b"");
    let cancelled = Instant::now();
    assert_eq!(agent.wait(LIMIT).code(), Some(0), "{}", agent.log());
    assert_eq!(sim.wait(LIMIT).code(), Some(0), "{}", sim.log());
    let pairs_stopped = cancelled.elapsed();
    assert_eq!(lc.wait(LIMIT).code(), Some(0), "{}", lc.log());
    // One period (1 s) to see it, one poll (0.2 s) to act, plus the evaluator's stop.
    assert!(pairs_stopped < Duration::from_secs(4), "{pairs_stopped:?}");
    assert!(
        cancelled.elapsed() < Duration::from_secs(6),
        "{:?}",
        cancelled.elapsed()
    );
    assert!(vols.marker("simulation.cancel"));
    assert!(!vols.marker("agent-1.crash0") && !vols.marker("agent-1.done"));
    assert!(moto.exists(&key("containers-status/logcopy-0.done")));
}

#[test]
#[ignore = "needs moto"]
fn logcopy_ends_the_pod_without_the_done_marker_once_every_pair_ended_its_attempt() {
    let moto = Moto::start();
    let vols = Volumes::new();
    // The simulator has crashed, the agent still runs: the pod goes on.
    write(vols.status().as_path(), "simulator-1.crash0", b"");
    let mut lc = logcopy(&vols, &moto, None, &[]);
    lc.wait_event("logcopy pass", LIMIT, |_| true);
    std::thread::sleep(Duration::from_secs(2));
    assert!(
        lc.try_exit().is_none(),
        "the agent has not ended its attempt"
    );
    // The agent ends it too: nothing restarts in the pod (restartPolicy Never), so logcopy
    // makes its final upload and ends, and a new pod of the Job may follow.
    write(vols.status().as_path(), "agent-1.crash0", b"");
    assert_eq!(lc.wait(LIMIT).code(), Some(0), "{}", lc.log());
    assert!(!lc.events("the Job is over: final upload").is_empty());
    assert!(moto.exists(&key("containers-status/agent-1.crash0")));
    assert!(!moto.exists(&key("containers-status/logcopy-0.done")));
    assert!(!vols.marker("logcopy-0.done"));
}

#[test]
#[ignore = "needs moto"]
fn a_new_pod_resumes_from_s3_after_a_crash_and_appends_to_the_logs() {
    let moto = Moto::start();
    let once = tempfile::tempdir().unwrap();
    let pair = Pair::new(1, "0-4").with_carla_crash(once.path());

    // Pod 1: CARLA crashes, then the pod is deleted (node lost): logcopy's final upload.
    let pod1 = Volumes::new();
    let mut lc = logcopy(&pod1, &moto, None, &[]);
    let mut sim = pair.simulator(&pod1);
    let mut agent = pair.agent(&pod1);
    assert_eq!(agent.wait(LIMIT).code(), Some(1), "{}", agent.log());
    assert_eq!(sim.wait(LIMIT).code(), Some(1));
    lc.signal(Signal::SIGTERM);
    assert_eq!(lc.wait(LIMIT).code(), Some(0), "{}", lc.log());
    assert!(moto.exists(&key("containers-status/agent-1.crash0")));
    let partial = route_ids(&pod1.checkpoint(1));
    assert!(partial.len() < 5);

    // Pod 2: init brings the results and logs back, the markers are cleared.
    let pod2 = Volumes::new();
    let code = tempfile::tempdir().unwrap();
    let mut init = init_command(&pod2, &moto, code.path(), &[]);
    assert_eq!(init.wait(LIMIT).code(), Some(0), "{}", init.log());
    assert!(!moto.exists(&key("containers-status/agent-1.crash0")));
    assert_eq!(route_ids(&pod2.checkpoint(1)), partial);
    let mut lc = logcopy(&pod2, &moto, None, &[]);
    let mut sim = pair.simulator(&pod2);
    let mut agent = pair.agent(&pod2);
    assert_eq!(agent.wait(LIMIT).code(), Some(0), "{}", agent.log());
    assert_eq!(sim.wait(LIMIT).code(), Some(0));
    assert_eq!(lc.wait(LIMIT).code(), Some(0), "{}", lc.log());
    assert!(pod2.agent_log(1).contains("(resuming)"));

    let results = moto.get(&key("agent/partial_agent_results1.json")).unwrap();
    assert!(finished(&results, "0-4"));
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("r.json"), &results).unwrap();
    let expected: Vec<String> = (0..=4).map(|r| format!("RouteScenario_{r}_rep0")).collect();
    assert_eq!(route_ids(&dir.path().join("r.json")), expected);
    let log = String::from_utf8(moto.get(&key("logs/agent/agent1/agent.log")).unwrap()).unwrap();
    assert_eq!(
        log.matches("evaluator started").count(),
        2,
        "both pods' output is kept: {log}"
    );
}
