//! `fake-evaluator` as a process against `fake-carla`: checkpoints in the official format,
//! merges equal to the fixtures', resume, crashes, hangs and the other failure modes.

use crate::common;

use std::path::Path;
use std::time::Duration;

use common::*;
use lb_domain::results::{self, Leaderboard, MergeOptions, WorkerFile};

const CHECKPOINT: &str = "results.json";

fn worker_dir(root: &Path, name: &str) -> std::path::PathBuf {
    let dir = root.join(name);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Merges worker files with the domain merge, as the backend does.
fn merge_files(paths: &[std::path::PathBuf], lb: Leaderboard) -> String {
    let files = paths
        .iter()
        .map(|p| read_checkpoint(p, lb, None))
        .collect::<Vec<_>>();
    results::merge(
        files,
        MergeOptions {
            leaderboard: lb,
            expected: None,
        },
    )
    .expect("merge")
    .merged
    .to_json()
}

#[test]
fn a_five_route_subset_writes_a_checkpoint_the_domain_reader_accepts_with_its_global_record() {
    let dir = tempfile::tempdir().unwrap();
    let carla = start_carla(dir.path(), &[], &[]);
    // The recordings' folder, as the simulator's mount of it (CARLA creates no folder).
    std::fs::create_dir_all(dir.path().join("recorder")).unwrap();
    let args = evaluator_args(dir.path(), carla.port, "5-9", 1, false);
    let (status, stdout, stderr) = run_evaluator(dir.path(), &args, &[]);
    assert_eq!(status.code(), Some(0), "{stdout}\n{stderr}");
    assert!(stdout.contains("========= Preparing RouteScenario_7 (repetition 0) ========="));
    assert!(stdout.contains("> Registering the global statistics"));

    let path = dir.path().join(CHECKPOINT);
    let file = read_checkpoint(&path, Leaderboard::V2, Some("5-9"));
    assert_eq!(file.progress, (5, 5));
    let ids: Vec<&str> = file
        .records
        .iter()
        .map(|r| r.route_id.raw.as_str())
        .collect();
    assert_eq!(
        ids,
        [
            "RouteScenario_5_rep0",
            "RouteScenario_6_rep0",
            "RouteScenario_7_rep0",
            "RouteScenario_8_rep0",
            "RouteScenario_9_rep0"
        ]
    );
    let indices: Vec<i64> = file.records.iter().map(|r| r.index).collect();
    assert_eq!(indices, [0, 1, 2, 3, 4]);
    assert!(file.has_global_record);
    assert_eq!(file.entry_status.as_deref(), Some("Finished"));
    assert_eq!(file.sensors.len(), 6);

    // The global record holds the statistics of these records.
    let v = json(&path);
    let global = &v["_checkpoint"]["global_record"];
    let round6 = |x: f64| format!("{x:.6}").parse::<f64>().unwrap();
    for key in ["score_route", "score_penalty", "score_composed"] {
        let mean = v["_checkpoint"]["records"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| r["scores"][key].as_f64().unwrap() / 5.0)
            .sum::<f64>();
        let got = global["scores_mean"][key].as_f64().unwrap();
        assert!((got - round6(mean)).abs() < 1e-9, "{key}: {got} vs {mean}");
    }
    let failed: Vec<&str> = file
        .records
        .iter()
        .filter(|r| r.status.as_str().contains("Failed"))
        .map(|r| r.route_id.raw.as_str())
        .collect();
    let exceptions: Vec<&str> = global["meta"]["exceptions"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e[0].as_str().unwrap())
        .collect();
    assert_eq!(exceptions, failed);
    assert_eq!(global["index"], -1);
    assert_eq!(v["values"].as_array().unwrap().len(), 15);
    assert_eq!(v["labels"].as_array().unwrap().len(), 15);
    assert_eq!(
        v["values"][0],
        global["scores_mean"]["score_composed"].to_string()
    );
    assert_eq!(v["eligible"], true);

    let live = std::fs::read_to_string(dir.path().join("live_results.txt")).unwrap();
    assert!(
        live.starts_with("Route id: RouteScenario_9_rep0\n\nScores:\n"),
        "{live}"
    );
    // CARLA, not the evaluator, wrote each route's recording: its header and a frame per
    // simulated tick, as large as the audit wants for the route's simulated time.
    for record in &file.records {
        let path = dir
            .path()
            .join(format!("recorder/{}.log", record.route_id.raw));
        let recording = std::fs::read(&path).unwrap();
        let expected = lb_domain::run::audit::Expected {
            pair: 1,
            stem: record.route_id.raw.clone(),
            game_seconds: record.meta.duration_game.as_f64(),
            floor_seconds: 0.0,
        };
        assert!(recording.starts_with(lb_domain::run::audit::MAGIC));
        assert!(
            recording.len() as u64 >= expected.min_bytes(),
            "{}",
            path.display()
        );
    }
    assert!(temp_files(dir.path()).is_empty());
}

#[test]
fn four_workers_reproduce_fixture_a_and_merge_into_its_merged_file() {
    let root = tempfile::tempdir().unwrap();
    let carla = start_carla(root.path(), &[], &[]);
    let mut procs = Vec::new();
    let mut paths = Vec::new();
    for (i, subset) in ["0-4", "5-9", "10-14", "15-19"].iter().enumerate() {
        let dir = worker_dir(root.path(), &format!("w{}", i + 1));
        procs.push(evaluator(
            &dir,
            &evaluator_args(&dir, carla.port, subset, 1, false),
            &[],
        ));
        paths.push(dir.join(CHECKPOINT));
    }
    for p in &mut procs {
        let status = p.wait();
        assert_eq!(status.code(), Some(0), "{}", p.stderr());
    }
    for (i, path) in paths.iter().enumerate() {
        let expected = fixture_text(&format!(
            "a_4workers_20routes_finished/input/worker{}.json",
            i + 1
        ));
        assert_eq!(
            std::fs::read_to_string(path).unwrap(),
            expected,
            "worker {}",
            i + 1
        );
    }
    let merged = merge_files(&paths, Leaderboard::V2);
    assert_eq!(
        merged,
        fixture_text("a_4workers_20routes_finished/expected/merged.json")
    );
}

#[test]
fn repetitions_give_rep_ids_and_reproduce_fixture_d() {
    let root = tempfile::tempdir().unwrap();
    let carla = start_carla(root.path(), &[], &[]);
    let records = fixtures().join("d_repetitions_2routes_3reps/expected/merged.json");
    let records = records.to_str().unwrap();
    let mut paths = Vec::new();
    for (i, subset) in ["0-0", "1-1"].iter().enumerate() {
        let dir = worker_dir(root.path(), &format!("w{}", i + 1));
        let args = evaluator_args(&dir, carla.port, subset, 3, false);
        let (status, out, err) = run_evaluator(&dir, &args, &[("FAKE_EVALUATOR_RECORDS", records)]);
        assert_eq!(status.code(), Some(0), "{out}\n{err}");
        assert!(out.contains("(repetition 2)"));
        paths.push(dir.join(CHECKPOINT));
    }
    let ids: Vec<String> = read_checkpoint(&paths[1], Leaderboard::V2, Some("1-1"))
        .records
        .iter()
        .map(|r| r.route_id.raw.clone())
        .collect();
    assert_eq!(
        ids,
        [
            "RouteScenario_1_rep0",
            "RouteScenario_1_rep1",
            "RouteScenario_1_rep2"
        ]
    );
    for (i, path) in paths.iter().enumerate() {
        let expected = fixture_text(&format!(
            "d_repetitions_2routes_3reps/input/worker{}.json",
            i + 1
        ));
        assert_eq!(std::fs::read_to_string(path).unwrap(), expected);
    }
    assert_eq!(
        merge_files(&paths, Leaderboard::V2),
        fixture_text("d_repetitions_2routes_3reps/expected/merged.json")
    );
}

#[test]
fn resuming_after_a_crash_at_route_k_records_every_route_exactly_once() {
    let dir = tempfile::tempdir().unwrap();
    let carla = start_carla(dir.path(), &[], &[]);
    let once = dir.path().join("once");
    let env = [
        ("FAKE_EVALUATOR_CRASH_AT_ROUTE", "2"),
        ("FAKE_EVALUATOR_ONCE_DIR", once.to_str().unwrap()),
    ];
    let args = evaluator_args(dir.path(), carla.port, "0-4", 1, false);
    let (status, _, stderr) = run_evaluator(dir.path(), &args, &env);
    assert_eq!(status.code(), Some(1));
    assert!(
        stderr.contains("Traceback (most recent call last):"),
        "{stderr}"
    );
    assert!(stderr.contains("RouteScenario_2_rep0"), "{stderr}");
    let path = dir.path().join(CHECKPOINT);
    let file = read_checkpoint(&path, Leaderboard::V2, Some("0-4"));
    assert_eq!(file.progress, (2, 5), "the file as the last route left it");
    assert_eq!(file.records.len(), 2);
    assert!(!file.has_global_record);
    assert_eq!(file.entry_status.as_deref(), Some("Started"));

    // The restarted container: RESUME=1 through the environment, `--resume` left out.
    let args: Vec<String> = args
        .into_iter()
        .filter(|a| !a.starts_with("--resume"))
        .collect();
    let mut env = env.to_vec();
    env.push(("RESUME", "1"));
    let (status, out, err) = run_evaluator(dir.path(), &args, &env);
    assert_eq!(status.code(), Some(0), "{out}\n{err}");
    assert!(
        !out.contains("Preparing RouteScenario_1 "),
        "routes 0-1 are not run again"
    );
    // Every route once, and the same file an uninterrupted run writes.
    assert_eq!(
        std::fs::read_to_string(&path).unwrap(),
        fixture_text("a_4workers_20routes_finished/input/worker1.json")
    );
}

#[test]
fn carla_dying_mid_route_records_a_crashed_route_and_exits_non_zero_then_resume_finishes() {
    let dir = tempfile::tempdir().unwrap();
    let trigger = dir.path().join("kill-carla");
    let crash_flag = format!("-fake-crash-file={}", trigger.display());
    let mut carla = start_carla(dir.path(), &[&crash_flag], &[]);
    let args = evaluator_args(dir.path(), carla.port, "0-4", 1, false);
    let mut ev = evaluator(
        dir.path(),
        &args,
        &[("FAKE_EVALUATOR_ROUTE_SECONDS", "1.5")],
    );
    ev.wait_line("running route 1", |l| l.contains("RouteScenario_1_rep0 0%"));
    std::fs::write(&trigger, "").unwrap();
    let status = ev.wait();
    assert_eq!(status.code(), Some(255), "{}\n{}", ev.stdout(), ev.stderr());
    assert!(ev.stdout().contains("Error during the simulation:"));
    carla.proc.wait();

    let path = dir.path().join(CHECKPOINT);
    let file = read_checkpoint(&path, Leaderboard::V2, Some("0-4"));
    assert_eq!(file.progress, (2, 5));
    assert_eq!(file.records.len(), 2);
    assert_eq!(file.records[0].status.as_str(), "Completed");
    assert_eq!(
        file.records[1].status.as_str(),
        "Failed - Simulation crashed"
    );
    assert!(
        file.records[1].meta.duration_system.as_f64() < 399.133,
        "cut short"
    );
    assert_eq!(file.entry_status.as_deref(), Some("Crashed"));
    let v = json(&path);
    assert_eq!(v["eligible"], false);
    assert_eq!(v["_checkpoint"]["global_record"], serde_json::json!({}));
    assert_eq!(
        shape(&v),
        shape(&json(
            &fixtures().join("c1_simulation_crash_last_route/input/worker3.json")
        )),
        "the layout of fixture c1's crashed worker"
    );

    // A new simulator, and the evaluator resumes (re-running the route before the crash).
    let carla = start_carla(dir.path(), &[], &[]);
    let args = evaluator_args(dir.path(), carla.port, "0-4", 1, true);
    let (status, out, err) = run_evaluator(dir.path(), &args, &[]);
    assert_eq!(status.code(), Some(0), "{out}\n{err}");
    assert!(out.contains("Preparing RouteScenario_0 "));
    assert_eq!(
        std::fs::read_to_string(&path).unwrap(),
        fixture_text("a_4workers_20routes_finished/input/worker1.json")
    );
}

#[test]
fn without_carla_it_fails_like_the_real_evaluator_and_writes_no_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let args = evaluator_args(dir.path(), port, "0-4", 1, false);
    let (status, _, stderr) = run_evaluator(
        dir.path(),
        &args,
        &[("FAKE_EVALUATOR_CONNECT_SECONDS", "0.3")],
    );
    assert_eq!(status.code(), Some(1));
    assert!(
        stderr.contains("while waiting for the simulator, make sure the simulator is ready"),
        "{stderr}"
    );
    assert!(stderr.contains(&format!("localhost:{port}")), "{stderr}");
    assert!(!dir.path().join(CHECKPOINT).exists());
}

#[test]
fn a_hang_goes_silent_and_still_dies_on_sigterm_leaving_a_whole_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let carla = start_carla(dir.path(), &[], &[]);
    let args = evaluator_args(dir.path(), carla.port, "0-4", 1, false);
    let mut ev = evaluator(dir.path(), &args, &[("FAKE_EVALUATOR_HANG_AT_ROUTE", "1")]);
    ev.wait_line("preparing route 1", |l| {
        l.contains("Preparing RouteScenario_1 ")
    });
    ev.wait_line("running route 1", |l| l.contains("> Running the route"));
    assert!(
        ev.lines_within(Duration::from_millis(600)).is_empty(),
        "silent"
    );
    assert!(ev.is_running());
    ev.signal("TERM");
    assert_eq!(ev.wait().code(), Some(143));
    let file = read_checkpoint(&dir.path().join(CHECKPOINT), Leaderboard::V2, Some("0-4"));
    assert_eq!(file.progress, (1, 5));
    assert!(temp_files(dir.path()).is_empty());
    drop(carla);
}

#[test]
fn sigterm_mid_route_exits_without_a_half_written_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let carla = start_carla(dir.path(), &[], &[]);
    let args = evaluator_args(dir.path(), carla.port, "0-4", 1, false);
    let mut ev = evaluator(
        dir.path(),
        &args,
        &[("FAKE_EVALUATOR_ROUTE_SECONDS", "0.5")],
    );
    ev.wait_line("running route 2", |l| l.contains("RouteScenario_2_rep0 0%"));
    ev.signal("TERM");
    assert_eq!(ev.wait().code(), Some(143));
    let file = read_checkpoint(&dir.path().join(CHECKPOINT), Leaderboard::V2, Some("0-4"));
    // NB: a machine stalled past the route's end may let route 2 finish first.
    assert!(
        matches!(file.progress, (2, 5) | (3, 5)),
        "{:?}",
        file.progress
    );
    assert_eq!(file.records.len() as u64, file.progress.0);
    assert!(!file.has_global_record);
    assert!(temp_files(dir.path()).is_empty());
}

#[test]
fn garbage_mode_writes_a_checkpoint_the_domain_rejects_once() {
    let dir = tempfile::tempdir().unwrap();
    let carla = start_carla(dir.path(), &[], &[]);
    let once = dir.path().join("once");
    let args = evaluator_args(dir.path(), carla.port, "0-2", 1, false);
    let path = dir.path().join(CHECKPOINT);
    let env = [
        ("FAKE_EVALUATOR_GARBAGE", "1"),
        ("FAKE_EVALUATOR_ONCE_DIR", once.to_str().unwrap()),
    ];
    let (status, _, _) = run_evaluator(dir.path(), &args, &env);
    assert_eq!(status.code(), Some(0));
    let bytes = std::fs::read(&path).unwrap();
    assert!(matches!(
        results::read_worker_file("w", Some(&bytes), Leaderboard::V2, None),
        Ok(WorkerFile::Empty(_))
    ));
    // The once marker is there: the next run writes a good file.
    let (status, _, _) = run_evaluator(dir.path(), &args, &env);
    assert_eq!(status.code(), Some(0));
    assert!(read_checkpoint(&path, Leaderboard::V2, None).has_global_record);

    let (status, _, _) = run_evaluator(dir.path(), &args, &[("FAKE_EVALUATOR_GARBAGE", "schema")]);
    assert_eq!(status.code(), Some(0));
    let bytes = std::fs::read(&path).unwrap();
    let err = results::read_worker_file("w", Some(&bytes), Leaderboard::V2, None).unwrap_err();
    assert_eq!(err.name(), "ResultsInvalid");
}

#[test]
fn an_agent_setup_failure_reproduces_fixture_l() {
    let root = tempfile::tempdir().unwrap();
    let carla = start_carla(root.path(), &[], &[]);
    let records = fixtures().join("l_agent_setup_failure_invalid/expected/merged.json");
    let env = [
        ("FAKE_EVALUATOR_SETUP_FAILURE", "1"),
        ("FAKE_EVALUATOR_RECORDS", records.to_str().unwrap()),
    ];
    let mut paths = Vec::new();
    for (i, subset) in ["0-4", "5-9"].iter().enumerate() {
        let dir = worker_dir(root.path(), &format!("w{}", i + 1));
        let args = evaluator_args(&dir, carla.port, subset, 1, false);
        let (status, out, err) = run_evaluator(&dir, &args, &env);
        assert_eq!(status.code(), Some(0), "{out}\n{err}");
        assert!(out.contains("Could not set up the required agent:"));
        assert!(!out.contains("> Running the route"));
        paths.push(dir.join(CHECKPOINT));
    }
    for (i, path) in paths.iter().enumerate() {
        let expected = fixture_text(&format!(
            "l_agent_setup_failure_invalid/input/worker{}.json",
            i + 1
        ));
        assert_eq!(std::fs::read_to_string(path).unwrap(), expected);
    }
    assert_eq!(
        merge_files(&paths, Leaderboard::V2),
        fixture_text("l_agent_setup_failure_invalid/expected/merged.json")
    );
}

#[test]
fn a_spawned_child_outlives_the_evaluator() {
    let dir = tempfile::tempdir().unwrap();
    let carla = start_carla(dir.path(), &[], &[]);
    let pid_file = dir.path().join("child.pid");
    let args = evaluator_args(dir.path(), carla.port, "0-1", 1, false);
    let out = std::fs::File::create(dir.path().join("stdout.txt")).unwrap();
    let err = std::fs::File::create(dir.path().join("stderr.txt")).unwrap();
    // NB: files, not pipes: the child inherits the evaluator's stdout and keeps it open.
    let mut cmd = command(
        EVALUATOR,
        dir.path(),
        &[
            ("FAKE_EVALUATOR_ROUTE_SECONDS", "0.01"),
            ("FAKE_EVALUATOR_SPAWN_CHILD", "1"),
            ("FAKE_EVALUATOR_CHILD_SECONDS", "30"),
            ("FAKE_EVALUATOR_CHILD_PID_FILE", pid_file.to_str().unwrap()),
        ],
    );
    cmd.args(&args).stdout(out).stderr(err);
    let mut child = cmd.spawn().unwrap();
    let status = wait_child(&mut child, STEP);
    assert_eq!(status.code(), Some(0));
    let pid: u32 = std::fs::read_to_string(&pid_file)
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    let proc_dir = std::path::PathBuf::from(format!("/proc/{pid}"));
    let alive = std::fs::read_to_string(proc_dir.join("stat"))
        .map(|s| !s.contains(") Z "))
        .unwrap_or(false);
    let cmdline = std::fs::read(proc_dir.join("cmdline")).unwrap_or_default();
    // Clean up before asserting, so a failure leaves nothing behind.
    let _ = std::process::Command::new("kill")
        .args(["-KILL", &pid.to_string()])
        .status();
    assert!(alive, "the child lives on after the evaluator exited");
    assert!(
        String::from_utf8_lossy(&cmdline).contains("fake-participant-child"),
        "{cmdline:?}"
    );
}

#[test]
fn argument_errors_name_the_argument() {
    let dir = tempfile::tempdir().unwrap();
    let base = evaluator_args(dir.path(), 2000, "0-4", 1, false);
    let with = |extra: &[&str], env: &[(&str, &str)]| {
        let mut args = base.clone();
        args.extend(extra.iter().map(|s| s.to_string()));
        let (status, _, stderr) = run_evaluator(dir.path(), &args, env);
        assert_eq!(status.code(), Some(2), "{stderr}");
        assert!(
            stderr.starts_with("usage: leaderboard_evaluator.py"),
            "{stderr}"
        );
        stderr
    };
    assert!(with(&["--repetitions=x"], &[])
        .contains("argument `--repetitions`: invalid int value: `x`"));
    assert!(with(&["--routes-subset=4-1"], &[]).contains("`--routes-subset`"));
    assert!(with(&["--made-up=1"], &[]).contains("unrecognized arguments: --made-up=1"));
    assert!(with(&[], &[("FAKE_EVALUATOR_HANG_AT_ROUTE", "later")])
        .contains("FAKE_EVALUATOR_HANG_AT_ROUTE"));
    let args: Vec<String> = base
        .iter()
        .filter(|a| !a.starts_with("--agent="))
        .cloned()
        .collect();
    let (status, _, stderr) = run_evaluator(dir.path(), &args, &[]);
    assert_eq!(status.code(), Some(2));
    assert!(
        stderr.contains("the following arguments are required: -a/--agent"),
        "{stderr}"
    );
    assert!(!dir.path().join(CHECKPOINT).exists());
}

#[test]
fn leaderboard_one_workers_reproduce_fixture_k1() {
    let root = tempfile::tempdir().unwrap();
    let carla = start_carla(root.path(), &[], &[]);
    let mut paths = Vec::new();
    for (i, subset) in ["0-3", "4-7", "8-11"].iter().enumerate() {
        let dir = worker_dir(root.path(), &format!("w{}", i + 1));
        let checkpoint = dir.join(CHECKPOINT);
        let args: Vec<String> = vec![
            "-u".into(),
            "/workspace/leaderboard/leaderboard/leaderboard_evaluator.py".into(),
            "--scenarios=/workspace/leaderboard/data/all_towns_traffic_scenarios_private.json"
                .into(),
            "--routes=/workspace/leaderboard/data/routes_testing.xml".into(),
            format!("--routes-subset={subset}"),
            format!("--port={}", carla.port),
            "--agent=/agent.py".into(),
            "--track=SENSORS".into(),
            format!("--checkpoint={}", checkpoint.display()),
            "--resume=".into(),
        ];
        let (status, out, err) = run_evaluator(&dir, &args, &[]);
        assert_eq!(status.code(), Some(0), "{out}\n{err}");
        assert!(
            !dir.join("live_results.txt").exists(),
            "1.0 has no live results"
        );
        paths.push(checkpoint);
    }
    for (i, path) in paths.iter().enumerate() {
        let expected = fixture_text(&format!(
            "k1_lb1_3workers_12routes/input/worker{}.json",
            i + 1
        ));
        assert_eq!(
            std::fs::read_to_string(path).unwrap(),
            expected,
            "worker {}",
            i + 1
        );
    }
    assert_eq!(
        merge_files(&paths, Leaderboard::V1),
        fixture_text("k1_lb1_3workers_12routes/expected/merged.json")
    );
}
