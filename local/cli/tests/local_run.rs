//! `lbctl local run` as a maintainer runs it (the shipped `lbctl` handing over to
//! `lbctl-local`): each scenario ends as it should, with exit 0.

use std::path::{Path, PathBuf};

use serde_json::{json, Value};
use std::process::Command;
use std::sync::OnceLock;

/// `lbctl`, built beside `lbctl-local` (and the workloads) as `make local` builds them.
pub(crate) fn lbctl() -> PathBuf {
    static BUILT: OnceLock<PathBuf> = OnceLock::new();
    BUILT
        .get_or_init(|| {
            local_stack::workloads::Binaries::build().expect("lbctl and the workloads build");
            Path::new(env!("CARGO_BIN_EXE_lbctl-local")).with_file_name("lbctl")
        })
        .clone()
}

/// `lbctl local run <args>` with `env`, which must succeed: its `--report` and its stdout (the
/// progress lines; the report holds the outcome).
pub(crate) fn local_run(args: &[&str], env: &[(&str, &str)]) -> (Value, String) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("report.json");
    let out = Command::new(lbctl())
        .args(["local", "run", "--report", path.to_str().unwrap()])
        .args(args)
        .envs(env.iter().copied())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{args:?}: {stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report = std::fs::read_to_string(&path).expect("the run writes its report");
    (serde_json::from_str(&report).unwrap(), stdout)
}

/// A text field of the report (empty when absent).
fn text<'a>(report: &'a Value, key: &str) -> &'a str {
    report[key].as_str().unwrap_or_default()
}

// Each local run takes its own ports (moto, the fake EvalAI, the local Kubernetes API, and
// CARLA's, which the simulator's sidecar moves past any taken), and the crash scenario kills
// only its own CARLA: the runs of these tests go side by side.

#[test]
#[ignore = "needs moto"]
fn the_happy_path_and_the_forged_and_reclaimed_runs_finish_with_the_same_scores() {
    let happy = scenario("happy", "FINISHED", &Value::Null);
    for (name, expected) in [
        ("forge", "FINISHED"),
        ("forge-recordings", "FINISHED"),
        ("spot", "FINISHED"),
        ("evict-between-rounds", "FINISHED"),
    ] {
        scenario(name, expected, &happy["scores"]);
    }
}

#[test]
#[ignore = "needs moto"]
fn a_crash_a_hang_and_a_planted_gpu_finish() {
    for name in ["crash", "hang", "plant-gpu"] {
        scenario(name, "FINISHED", &Value::Null);
    }
}

#[test]
#[ignore = "needs moto"]
fn a_cancel_ends_cancelled_and_a_stopped_execution_is_reaped() {
    scenario("cancel", "CANCELLED", &Value::Null);
    scenario("stop", "FAILED", &Value::Null);
}

#[test]
#[ignore = "needs moto"]
fn a_run_stopped_while_evalai_is_down_is_ended_by_the_reaper_s_pass_once_it_is_back() {
    scenario("evalai-down", "FAILED", &Value::Null);
}

#[test]
#[ignore = "needs moto"]
fn an_unpullable_image_a_crash_loop_and_no_node_fail_with_their_reasons() {
    for name in ["unpullable", "crash-loop", "no-node", "drain-loop"] {
        scenario(name, "FAILED", &Value::Null);
    }
}

/// A deploy and a rollback while a run is in flight, each run continuing as a new execution
/// after the move: the first submission finishes on the version it started on, across its
/// continuation; the one that arrives after the move on the version the alias names; nothing
/// is charged to any pair.
#[test]
#[ignore = "needs moto"]
fn a_run_in_flight_finishes_on_its_version_across_a_deploy_and_a_rollback() {
    let budget = lb_domain::run::history::MIN_BUDGET.to_string();
    for (name, expected) in [("deploy", [1, 2]), ("rollback", [2, 1])] {
        let args = [
            "--scenario",
            name,
            "--route-seconds",
            "1",
            "--history-budget",
            &budget,
            "--timeout",
            "300",
        ];
        let (report, _) = local_run(&args, &[]);
        assert_eq!(report["ok"], true, "{name}: {report}");
        assert_eq!(report["release"]["moved"], true, "{name}: {report}");
        assert_eq!(
            report["release"]["ran"],
            json!(expected),
            "{name}: {report}"
        );
        assert!(
            report["executions"].as_u64() > Some(1),
            "{name}: the first run continued: {report}"
        );
        assert_eq!(
            report["queue"]["submissions"].as_array().map(Vec::len),
            Some(2),
            "{name}: {report}"
        );
        for submission in report["queue"]["submissions"].as_array().unwrap() {
            assert_eq!(submission["status"], "finished", "{name}: {report}");
        }
        // Nothing lost, nothing run again, nothing left.
        let merged = &report["merged"];
        assert_eq!(
            (merged["records"].as_u64(), merged["routes"].as_u64()),
            (Some(20), Some(20)),
            "{name}: {report}"
        );
        let left = &report["left_behind"];
        assert_eq!(left["usage"]["run_again"], 0, "{name}: {report}");
        assert_eq!(
            (left["jobs"].as_u64(), left["places_held"].as_u64()),
            (Some(0), Some(0)),
            "{name}: {report}"
        );
    }
}

/// The Kubernetes upgrade rehearsed with an evaluation in flight (`docs/operations.md`,
/// "Upgrading Kubernetes"): the control plane one minor up in place, then the node group's
/// new node in and the old one drained. The evictions are free reclaims; FINISHED.
#[test]
#[ignore = "needs moto and the real control plane at both releases (make real-kube)"]
fn on_the_real_control_plane_an_upgrade_mid_route_costs_a_free_reclaim_and_finishes() {
    let report = scenario_on("real", "upgrade", "FINISHED", &Value::Null);
    let upgrade = &report["upgrade"];
    let (from, to) = (text(upgrade, "from"), text(upgrade, "to"));
    let minor = |v: &str| v.split('.').nth(1).and_then(|m| m.parse::<u32>().ok());
    assert_eq!(minor(to), minor(from).map(|m| m + 1), "{report}");
    assert_eq!(upgrade["new_node_joined"], true, "{report}");
    let reclaim = &report["reclaim"];
    assert!(
        !reclaim["evicted"].as_array().unwrap().is_empty(),
        "{report}"
    );
    assert_eq!(reclaim["retries_used"], 0, "{report}");
}

// The scenarios on the real control plane, one test each, so that they share the test
// threads with the others rather than run one after another at the end.

#[test]
#[ignore = "needs moto and the real control plane (make real-kube)"]
fn on_the_real_control_plane_a_spot_reclaim_and_consolidation_score_as_the_happy_run() {
    let happy = scenario_on("real", "happy", "FINISHED", &Value::Null);
    scenario_on("real", "spot", "FINISHED", &happy["scores"]);
    scenario_on("real", "consolidate", "FINISHED", &happy["scores"]);
}

#[test]
#[ignore = "needs moto and the real control plane (make real-kube)"]
fn on_the_real_control_plane_a_crash_finishes() {
    scenario_on("real", "crash", "FINISHED", &Value::Null);
}

#[test]
#[ignore = "needs moto and the real control plane (make real-kube)"]
fn on_the_real_control_plane_a_crash_loop_fails_with_its_reason() {
    scenario_on("real", "crash-loop", "FAILED", &Value::Null);
}

#[test]
#[ignore = "needs moto and the real control plane (make real-kube)"]
fn on_the_real_control_plane_a_cancel_ends_cancelled() {
    scenario_on("real", "cancel", "CANCELLED", &Value::Null);
}

#[test]
#[ignore = "needs moto and the real control plane (make real-kube)"]
fn on_the_real_control_plane_no_node_fails_with_its_reason() {
    scenario_on("real", "no-node", "FAILED", &Value::Null);
}

#[test]
#[ignore = "needs moto and the real control plane (make real-kube)"]
fn on_the_real_control_plane_a_disk_hog_is_evicted_past_its_retries() {
    scenario_on("real", "disk-hog", "FAILED", &Value::Null);
}

/// `lbctl local run --scenario <scenario>`, which must end `expected` with what the scenario
/// promises (`happy_scores`: the happy run's, for the runs that must score alike); its report.
fn scenario(scenario: &str, expected: &str, happy_scores: &Value) -> Value {
    scenario_on("local", scenario, expected, happy_scores)
}

/// [`scenario`] on the Kubernetes `kube` (`local` or `real`).
fn scenario_on(kube: &str, scenario: &str, expected: &str, happy_scores: &Value) -> Value {
    let args = ["--kube", kube, "--scenario", scenario, "--timeout", "240"];
    let (report, stdout) = local_run(&args, &[]);
    assert_eq!(
        text(&report, "evalai_status"),
        expected.to_lowercase(),
        "{scenario}: {report}"
    );
    assert_eq!(report["ok"], true, "{scenario}: {report}");
    let (stderr, participant_stdout) = (
        text(&report, "evalai_stderr"),
        text(&report, "evalai_stdout"),
    );
    // A failure tells the participant why, and shows their agent's own last words.
    match scenario {
        // Pushed, but no node can pull it: the Jobs named it by its digest.
        "unpullable" => assert!(stderr.contains("team-one@sha256:"), "{report}"),
        "crash-loop" => {
            assert!(
                stderr.contains("The last lines of agent 1's output:"),
                "{report}"
            );
            assert!(
                stderr.contains("Traceback (most recent call last)"),
                "{report}"
            );
            // Pair 1 crash-loops in a Job of its own: its retries run out, never its
            // neighbours'. Their routes are complete, and both files say which count.
            let note = "routes 0-4 (pair 1) were not evaluated; routes 5-9, 10-14, 15-19 (pairs 2, 3, 4) are complete";
            assert!(stderr.contains(note), "{report}");
            assert!(participant_stdout.contains(note), "{report}");
            // Pairs 2-4's 15 routes, and whatever pair 1 got through before each crash.
            let merged = report["merged"]["records"].as_u64().unwrap_or_default();
            assert!((15..20).contains(&merged), "{report}");
            assert!(
                stderr.contains("BackoffLimitExceeded") || stdout.contains("BackoffLimitExceeded"),
                "{report}\n{stdout}"
            );
            // The participant's own failure: the execution ends well, the record is theirs.
            assert_eq!(report["error"], Value::Null, "{report}");
            assert_eq!(
                report["left_behind"]["failed_by_platform"], false,
                "{report}"
            );
        }
        "drain-loop" => {
            // Pair 1 drained past its free reclaims, none of it the participant's doing: the
            // platform's own failure, told as such, and marked for operators.
            assert!(stderr.contains("PlatformReclaims"), "{report}");
            assert!(
                stderr.contains("5 of its pods were taken away by the platform")
                    && stderr.contains("not your agent's")
                    && !stderr.contains("disruption of their own"),
                "{report}"
            );
            assert!(!stderr.contains("The last lines of agent"), "{report}");
            let note = "routes 0-4 (pair 1) were not evaluated";
            assert!(stderr.contains(note), "{report}");
            assert!(
                text(&report, "error").starts_with("PlatformFailed"),
                "{report}"
            );
            assert_eq!(
                report["left_behind"]["failed_by_platform"], true,
                "{report}"
            );
            assert_eq!(report["left_behind"]["record_status"], "FAILED", "{report}");
        }
        "disk-hog" => {
            // Evicted for its own disk use at each of the 5 attempts past the 4 retries, each
            // charged once though its status came late: the participant's failure, told so.
            assert!(
                stderr.contains("5 of its pods were stopped by a disruption of their own"),
                "{report}"
            );
            assert!(
                stderr.contains("routes 0-4 (pair 1) were not evaluated"),
                "{report}"
            );
            assert_eq!(report["error"], Value::Null, "{report}");
            assert_eq!(
                report["left_behind"]["failed_by_platform"], false,
                "{report}"
            );
        }
        "no-node" => {
            // The autoscaler's word, with what to fix, before any time was used.
            assert!(
                stderr.contains("offers the nodes this leaderboard runs on (`leaderboard.carla.org/gpu-model=nvidia-a10g`)")
                    && stderr.contains("please contact the organizers"),
                "{report}"
            );
        }
        "stop" => {
            // Stopped mid-run, the execution never reached Finalize: the reaper did its
            // work on the status-change event, and nothing of the run is left.
            assert_eq!(text(&report, "execution"), "ABORTED", "{report}");
            assert!(
                stderr.contains("stopped by an operator before it finished"),
                "{report}"
            );
            let reaped = &report["reaped"][0];
            assert_eq!(reaped["via"], "event", "{report}");
            assert_eq!(reaped["attempts"], 1, "{report}");
            assert_eq!(reaped["answer"][0]["outcome"], "FAILED", "{report}");
            let left = &report["left_behind"];
            assert_eq!(left["jobs"], 0, "{report}");
            assert_eq!(left["places_held"], 0, "{report}");
            assert_eq!(left["record_status"], "FAILED", "{report}");
        }
        "evalai-down" => {
            // EvalAI failed through Finalize and through the three attempts of the reaper's
            // event, which was then dropped; once EvalAI was back, the scheduled pass ended
            // the run: nothing left, EvalAI told.
            assert_eq!(text(&report, "execution"), "ABORTED", "{report}");
            assert!(
                stderr.contains("stopped by an operator before it finished"),
                "{report}"
            );
            let reaped = report["reaped"].as_array().unwrap();
            let event = reaped.iter().find(|r| r["via"] == "event").unwrap();
            assert_eq!(event["attempts"], 3, "{report}");
            assert_eq!(event["dropped"], true, "{report}");
            let pass = reaped
                .iter()
                .find(|r| r["via"] == "scheduled pass")
                .unwrap();
            assert_eq!(pass["answer"][0]["outcome"], "FAILED", "{report}");
            let left = &report["left_behind"];
            assert_eq!(left["jobs"], 0, "{report}");
            assert_eq!(left["places_held"], 0, "{report}");
            assert_eq!(left["record_status"], "FAILED", "{report}");
        }
        "happy" => {
            // Intake pinned the Jobs to the digest the tag names in the registry: every pod
            // ran exactly it (a pod pulled by tag reports another digest here).
            let digest = &report["left_behind"]["registry_digest"];
            assert!(
                digest.as_str().is_some_and(|d| d.starts_with("sha256:")),
                "{report}"
            );
            assert_eq!(
                &report["left_behind"]["usage"]["image_digest"], digest,
                "{report}"
            );
            // Every route's recording is in S3, and the record says so.
            assert_eq!(
                report["left_behind"]["recordings"],
                json!([20, 20]),
                "{report}"
            );
            // Four pairs' GPUs for the run's seconds, on-demand, none run again, priced.
            let usage = &report["left_behind"]["usage"];
            assert!(usage["gpu_seconds"].as_u64().unwrap() >= 4, "{report}");
            assert_eq!(usage["spot"], 0, "{report}");
            assert_eq!(usage["run_again"], 0, "{report}");
            assert_eq!(usage["lost_to_reclaims"], 0, "{report}");
            assert!(usage["cost_usd"].as_f64().is_some(), "{report}");
            // Every state the executions entered was counted by the stage that caused it.
            assert_eq!(
                usage["state_transitions"], report["state_transitions"],
                "{report}"
            );
            assert!(
                usage["orchestration_usd"].as_f64().unwrap() > 0.0,
                "{report}"
            );
        }
        "evict-between-rounds" => {
            // The pod was evicted and gone before the round looked; its route ran again, and
            // the record counts it: run again, and time lost to the reclaim. No retry used.
            let reclaim = &report["reclaim"];
            let evicted = reclaim["evicted"].as_array().unwrap();
            assert_eq!(evicted.len(), 1, "{report}");
            let pod = evicted[0].as_str().unwrap();
            assert_eq!(
                reclaim["disrupted"][pod], "EvictionByEvictionAPI",
                "{report}"
            );
            assert_eq!(reclaim["retries_used"], 0, "{report}");
            let behind = reclaim["resumed_behind"].as_array().unwrap().len();
            assert_eq!(reclaim["routes_run_again"], 1 + behind, "{report}");
            assert_eq!(
                reclaim["interrupted"].as_array().unwrap().len(),
                1,
                "{report}"
            );
            let usage = &report["left_behind"]["usage"];
            assert!(usage["run_again"].as_u64().unwrap() > 0, "{report}");
            assert!(usage["lost_to_reclaims"].as_u64().unwrap() > 0, "{report}");
            assert_eq!(&report["scores"], happy_scores, "{report}");
        }
        "forge-recordings" => {
            // The scores stand on EvalAI, but not one scoring route's recording passed: each
            // holds CARLA's header only, which the records' claim of 0 s would fit but the
            // organisers' route lengths do not, and the 1-byte files the agents left in their
            // own logs are not recordings at all.
            assert_eq!(&report["scores"], happy_scores, "{report}");
            assert_eq!(
                report["left_behind"]["recordings"],
                json!([0, 20]),
                "{report}"
            );
            let failed = report["left_behind"]["recordings_failed"]
                .as_array()
                .unwrap();
            assert_eq!(failed.len(), 5, "the first few are named: {report}");
            assert!(
                failed[0]
                    .as_str()
                    .unwrap()
                    .starts_with("RouteScenario_0_rep0: 45 bytes for the 217.7 s its route's completed part takes at least (its record claims 0.0 s;"),
                "{report}"
            );
            assert!(stdout.contains("FINISHED*"), "{stdout}");
            // The participant reads it beside the scores: the audit comes before the post.
            let said = text(&report, "evalai_stderr");
            let all = "The CARLA recordings of 20 of the 20 scoring routes did not pass the audit";
            assert!(said.starts_with(all), "{report}");
            assert!(
                said.contains("\n- RouteScenario_0_rep0: 45 bytes for"),
                "{report}"
            );
        }
        "forge" => {
            // Pair 2's results as pair 2 wrote them: the same scores as the happy run,
            // although the other pairs' pods wrote its file and done marker last.
            assert_eq!(report["merged"]["records"], 20, "{report}");
            assert_eq!(&report["scores"], happy_scores, "{report}");
        }
        "plant-gpu" => {
            // Every pair crashed once after planting another GPU; at each attempt (each
            // pod, which may be given another GPU) the simulator rendered on a GPU one of its
            // own pair's agents was given.
            let gpus = report["simulator_gpus"].as_object().unwrap();
            assert_eq!(gpus.len(), 4, "{report}");
            for (pair, attempts) in gpus {
                let attempts = attempts.as_array().unwrap();
                assert!(attempts.len() >= 2, "pair {pair}: {report}");
                let given = report["agent_gpus"][pair.as_str()].as_array().unwrap();
                assert!(!given.is_empty(), "pair {pair}: {report}");
                assert!(
                    attempts.iter().all(|gpu| given.contains(gpu)),
                    "pair {pair}: {report}"
                );
            }
        }
        "consolidate" => {
            // The sweep drained the half-used node once the other joined, and each pod taken
            // off it was a move the Monitor made and counted, free: no retry used, the pairs
            // ended on the node that joined, the scores as the happy run's.
            let moved = &report["consolidation"];
            assert_eq!(moved["drained"], json!(["gpu-node-1"]), "{report}");
            let evicted = moved["evicted"].as_array().unwrap().len();
            assert!(evicted > 0, "{report}");
            assert_eq!(moved["moves"], evicted, "{report}");
            assert_eq!(moved["retries_used"], 0, "{report}");
            assert_eq!(moved["ended_on"], json!(["gpu-node-2"]), "{report}");
            assert_eq!(report["merged"]["records"], 20, "{report}");
            assert_eq!(&report["scores"], happy_scores, "{report}");
        }
        "spot" => {
            // Every evicted pod was replaced without using a retry; the route each was in
            // (none for a pod still setting up, as on the real control plane, where pods
            // start seconds apart) ran again once, no other route did, none was lost.
            let reclaim = &report["reclaim"];
            let evicted = reclaim["evicted"].as_array().unwrap();
            assert!(!evicted.is_empty(), "{report}");
            for pod in evicted {
                let pod = pod.as_str().unwrap();
                assert_eq!(
                    reclaim["disrupted"][pod], "EvictionByEvictionAPI",
                    "{report}"
                );
            }
            assert_eq!(reclaim["retries_used"], 0, "{report}");
            let runs = reclaim["route_runs"].as_object().unwrap();
            assert_eq!(runs.len(), 20, "{report}");
            assert!(runs.values().all(|n| n == 1 || n == 2), "{report}");
            let interrupted = reclaim["interrupted"].as_array().unwrap();
            assert!(interrupted.len() <= evicted.len(), "{report}");
            for route in interrupted {
                assert_eq!(runs[route.as_str().unwrap()], 2, "{report}");
            }
            // Besides them, only the finished routes the evaluator resumed behind them (it
            // runs again those whose record says the agent crashed).
            let behind = reclaim["resumed_behind"].as_array().unwrap().len();
            assert_eq!(
                reclaim["routes_run_again"],
                interrupted.len() + behind,
                "{report}"
            );
            assert_eq!(report["merged"]["records"], 20, "{report}");
            assert_eq!(&report["scores"], happy_scores, "{report}");
            // All of it on the Spot node; what was run again (the seconds after each
            // evicted pod's last results, under a second each with these short routes)
            // is part of it.
            let usage = &report["left_behind"]["usage"];
            let held = usage["gpu_seconds"].as_u64().unwrap();
            assert!(held > 0, "{report}");
            assert_eq!(usage["spot"].as_u64().unwrap(), held, "{report}");
            let run_again = usage["run_again"].as_u64().unwrap();
            assert!(run_again < held, "{report}");
            // The evaluation's time lost to the reclaim (not the participant's) runs from
            // a pair's last results to its next pod's start: it is there whenever the
            // Monitor saw a route's seconds run again.
            let lost = usage["lost_to_reclaims"].as_u64().unwrap();
            assert!(run_again == 0 || lost > 0, "{report}");
        }
        _ => {}
    }
    // Every state the executions entered was counted by the stage that caused it, however
    // the run went (no task was retried in these).
    if ["happy", "spot", "cancel", "crash-loop"].contains(&scenario) {
        assert_eq!(
            report["left_behind"]["usage"]["state_transitions"], report["state_transitions"],
            "{scenario}: {report}"
        );
    }
    let says_why = [
        "crash-loop",
        "unpullable",
        "no-node",
        "stop",
        "evalai-down",
        "forge-recordings",
        "drain-loop",
        "disk-hog",
    ];
    if !says_why.contains(&scenario) {
        assert!(report["evalai_stderr"].is_null(), "{scenario}: {report}");
    }
    report
}

#[test]
#[ignore = "needs moto"]
fn a_wake_flood_costs_rounds_at_the_least_interval_and_continues_under_its_budget() {
    // Every agent rewrites a status file and its results file 4 times a second; a small
    // history budget makes the run continue as new executions within seconds.
    let budget = lb_domain::run::history::MIN_BUDGET;
    let (report, stdout) = local_run(
        &[
            "--scenario",
            "wake-flood",
            "--history-budget",
            &budget.to_string(),
            "--route-seconds",
            "1",
            "--timeout",
            "240",
        ],
        &[],
    );
    assert_eq!(text(&report, "evalai_status"), "finished", "{report}");
    assert_eq!(report["ok"], true, "{report}");
    assert_eq!(report["merged"]["records"], 20, "{report}");
    // Continued at least once, and no execution's history came near its budget.
    let executions = report["executions"].as_u64().unwrap();
    assert!(executions >= 2, "{report}\n{stdout}");
    assert!(stdout.contains("stage ContinueAsNew"), "{stdout}");
    let longest = report["history_events"].as_u64().unwrap();
    assert!(longest < budget, "{longest} events: {report}");
    assert_rounds_bounded(&report, 0.05);
    // Each agent also wrote a new marker name every tick and a 200 MiB file at the top of
    // the logs volume: no marker beyond the protocol's bounded set reached S3 (so none woke
    // the execution or was written down), the large file stayed in the pod, and logcopy
    // counted what it refused once per name.
    let left = &report["left_behind"];
    let pairs = 4;
    let markers = left["status_objects"].as_u64().unwrap();
    let bound = u64::from(lb_domain::job::protocol::MARKERS_PER_PAIR) * pairs + pairs;
    assert!(markers <= bound, "{markers} markers: {report}");
    // What is stored is the 20 routes' recordings (about 15 MB at 20 frames a simulated
    // second) and the logs: none of the 200 MiB file.
    let usage = &left["usage"];
    assert!(
        usage["log_bytes_stored"].as_u64().unwrap() < 32 << 20,
        "{report}"
    );
    let refused = usage["uploads_refused"].as_u64().unwrap();
    assert!(refused > 2 * pairs, "{report}");

    // At production pacing (nothing scaled), with the deployment's budget: FINISHED in one
    // execution, a round per least interval at most while the wake function sees dozens of
    // uploads.
    let (report, _) = local_run(
        &[
            "--scenario",
            "wake-flood",
            "--time-scale",
            "1",
            "--route-seconds",
            "4",
            "--timeout",
            "240",
        ],
        &[],
    );
    assert_eq!(text(&report, "evalai_status"), "finished", "{report}");
    assert_eq!(report["merged"]["records"], 20, "{report}");
    assert_rounds_bounded(&report, 1.0);
    assert!(
        report["wake_messages"].as_u64().unwrap() > 2 * report["rounds"].as_u64().unwrap(),
        "{report}"
    );
}

#[test]
#[ignore = "needs moto"]
fn results_rewritten_with_the_same_records_send_nothing_new() {
    // Agents that rewrite their results four times a second with the same records (their
    // `duration_system` toggled by half a second, a trailing newline too), on routes longer
    // than the least interval between partial updates: only progress is sent, at most one
    // update per route and the first.
    let routes = 4;
    let (report, _) = local_run(
        &[
            "--scenario",
            "wake-flood",
            "--routes",
            &routes.to_string(),
            "--workers",
            "2",
            "--route-seconds",
            "6",
            "--partial-update-seconds",
            "1",
            "--timeout",
            "240",
        ],
        &[],
    );
    assert_eq!(text(&report, "evalai_status"), "finished", "{report}");
    let updates = report["queue"]["submissions"][0]["partial_updates"]
        .as_u64()
        .unwrap();
    assert!(updates <= routes + 1, "{updates} partial updates: {report}");
}

/// Each round is followed by the least interval (scaled by `time_scale`): the rounds are
/// bounded by the run's length, however often the files change.
fn assert_rounds_bounded(report: &Value, time_scale: f64) {
    let hold = lb_domain::run::schedule::MIN_ROUND_INTERVAL.as_secs_f64() * time_scale;
    let seconds = report["seconds"].as_f64().unwrap();
    let rounds = report["rounds"].as_u64().unwrap();
    assert!(
        (rounds as f64) <= seconds / hold + 1.0,
        "{rounds} rounds in {seconds} s: {report}"
    );
}

#[test]
#[ignore = "needs moto"]
fn a_leaderboard_1_run_ends_finished_with_five_records_per_route() {
    let (report, _) = local_run(
        &[
            "--leaderboard",
            "1.0",
            "--routes",
            "8",
            "--workers",
            "2",
            "--route-seconds",
            "0.05",
            "--timeout",
            "240",
        ],
        &[],
    );
    assert_eq!(text(&report, "evalai_status"), "finished", "{report}");
    let merged = &report["merged"];
    assert_eq!(
        (merged["records"].as_u64(), merged["routes"].as_u64()),
        (Some(40), Some(8)),
        "{report}"
    );
    assert!(
        merged["per_route"]
            .as_array()
            .unwrap()
            .iter()
            .all(|n| n == 5),
        "{report}"
    );
}

#[test]
#[ignore = "needs moto"]
fn a_30_minute_cluster_api_outage_mid_run_skips_rounds_and_the_run_ends_finished() {
    // 30 minutes at scale 0.01: 18 s of 500s from the first Monitor round, while the Jobs
    // (5 s of routes) run on and finish.
    let (report, stdout) = local_run(
        &[
            "--time-scale",
            "0.01",
            "--route-seconds",
            "1",
            "--kube-outage-minutes",
            "30",
            "--timeout",
            "240",
        ],
        &[],
    );
    assert!(
        stdout.contains("the cluster's API answers 500 for 30 minutes (scaled)"),
        "{stdout}"
    );
    let skipped = report["unreachable_rounds"].as_u64().unwrap();
    assert!(skipped >= 10, "{skipped} rounds skipped: {report}");
    assert_eq!(text(&report, "evalai_status"), "finished", "{report}");
    let merged = &report["merged"];
    assert_eq!(
        (merged["records"].as_u64(), merged["routes"].as_u64()),
        (Some(20), Some(20)),
        "{report}"
    );
}

#[test]
#[ignore = "needs moto"]
fn a_cancel_in_a_quiet_stretch_is_found_by_the_sweep_and_the_jobs_are_gone_within_two_minutes() {
    // Real time (scale 1), routes long enough that no results change for minutes, the cancel
    // after the second round (whose partial update was the last): only the once-a-minute
    // sweep can notice it (the Monitor reads EvalAI's status itself every 30 minutes, and at
    // each partial update).
    cancel_at_production_pace("cancel", 120.0);
}

#[test]
#[ignore = "needs moto"]
fn another_team_s_huge_cancelled_submissions_do_not_delay_a_cancel_beyond_90_seconds() {
    // As above, with another team's five cancelled submissions of 2.4 MB of metadata each in
    // EvalAI's list (created after ours arrived): the sweep reads the list element by element
    // and still finds the cancel at its next pass.
    cancel_at_production_pace("cancel-flood", 90.0);
}

/// A cancel scenario at real time with a quiet stretch after the second round: the sweep
/// wakes the execution once, and the Jobs are gone within `within` seconds of the cancel.
fn cancel_at_production_pace(scenario: &str, within: f64) {
    let (report, _) = local_run(
        &[
            "--scenario",
            scenario,
            "--cancel-after-round",
            "2",
            "--time-scale",
            "1",
            "--route-seconds",
            "300",
            "--timeout",
            "300",
        ],
        &[],
    );
    assert_eq!(text(&report, "evalai_status"), "cancelled", "{report}");
    assert_eq!(report["sweep_wakes"], 1, "the sweep woke it: {report}");
    let seconds = report["cancel_to_end_seconds"]
        .as_f64()
        .unwrap_or_else(|| panic!("no cancel timing: {report}"));
    assert!(
        seconds <= within,
        "{scenario}: the Jobs outlived the cancel by {seconds} s"
    );
}

/// The rehearsal's own executable, for what needs no build of the rest.
fn lbctl_local(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_lbctl-local"))
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn bad_arguments_are_named() {
    let out = lbctl_local(&["run", "--scenario", "nope"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("--scenario"));
    let out = lbctl_local(&["run", "--time-scale", "0"]);
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("--time-scale"));
    let out = lbctl_local(&["run", "--scenario", "disk-hog"]);
    assert_eq!(out.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("--scenario disk-hog needs --kube real"),
        "{stderr}"
    );
}

#[test]
fn the_run_documents_its_options_and_scenarios() {
    let out = lbctl_local(&["run", "--help"]);
    assert_eq!(out.status.code(), Some(0));
    let text = String::from_utf8_lossy(&out.stdout);
    for word in [
        "--scenario",
        "--workers",
        "--keep",
        "crash-loop",
        "LB_EVALAI_TOKEN",
        "Usage: lbctl local run",
    ] {
        assert!(text.contains(word), "`{word}` missing from\n{text}");
    }
}

#[test]
#[ignore = "needs moto"]
fn a_local_run_against_another_evalai_maps_its_phase_to_the_chosen_leaderboard() {
    // A separately started EvalAI whose ids are nothing like the local settings': challenge 7,
    // phase 4321 (a 2.0 phase), submission 55.
    let mut fixture: serde_json::Value =
        serde_json::from_str(fake_evalai::fixture::DEFAULT_FIXTURE_JSON).unwrap();
    fixture["challenges"][0]["id"] = 7.into();
    fixture["challenges"][0]["phases"][0]["id"] = 4321.into();
    fixture["host_teams"][0]["challenges"] = serde_json::json!([7]);
    for team in fixture["participant_teams"].as_array_mut().unwrap() {
        team["challenges"] = serde_json::json!([7]);
    }
    fixture["submissions"] = serde_json::json!([{
        "id": 55, "challenge_phase": 4321, "participant_team": 1, "created_by": 2,
        "status": "submitted", "submitted_at": "2026-11-24T00:00:00Z",
        "submitted_image_uri": "123456789012.dkr.ecr.us-west-2.amazonaws.com/team-one:local"
    }]);
    let fake = fake_evalai::FakeEvalAi::spawn(
        fake_evalai::Fixture::from_json(&fixture.to_string()).unwrap(),
    )
    .unwrap();
    let url = fake.url();
    let (_, stdout) = local_run(
        &[
            "--leaderboard",
            "2.0",
            "--routes",
            "4",
            "--workers",
            "2",
            "--route-seconds",
            "0.05",
            "--timeout",
            "240",
            "--evalai-url",
            &url,
            "--challenge",
            "7",
            "--phase",
            "4321",
            "--submission",
            "55",
        ],
        // The token from the environment, not the command line.
        &[("LB_EVALAI_TOKEN", "host-token")],
    );
    let on_evalai = fake.submission(55).unwrap();
    assert_eq!(on_evalai.status, "finished", "{stdout}");
    assert_eq!(
        on_evalai.leaderboard.len(),
        1,
        "the scores reached its leaderboard"
    );
}

/// Issue 13's capacity run: 12 submissions of 2 pairs from 4 teams (one sends 6) on a local
/// node of 4 GPUs, each team holding at most 2 evaluations, with the fake EvalAI's throttle
/// on. Read from what the fake EvalAI was told (`--report`).
#[test]
#[ignore = "needs moto"]
fn twelve_submissions_from_four_teams_take_their_turns_on_four_gpus() {
    let dir = tempfile::tempdir().unwrap();
    let metrics = dir.path().join("metrics.jsonl");
    let (whole, stdout) = local_run(
        &[
            "--metrics",
            metrics.to_str().unwrap(),
            "--submissions",
            "12",
            "--teams",
            "6,2,2,2",
            "--team-limit",
            "2",
            "--gpus",
            "4",
            "--workers",
            "2",
            "--routes",
            "2",
            "--timeout",
            "500",
        ],
        &[],
    );
    let report = &whole["queue"];
    let subs = report["submissions"].as_array().unwrap();
    assert_eq!(subs.len(), 12);
    the_metrics_add_up(&metrics, &whole, &stdout);
    let seq = |s: &serde_json::Value, key: &str| s[key].as_u64();
    for s in subs {
        // Every one finished: waiting for capacity or for its turn failed none.
        assert_eq!(s["status"], "finished", "{s}\n{stdout}");
        // Queued (EvalAI's PATCH) before it ran.
        let statuses: Vec<&str> = s["statuses"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_str().unwrap())
            .collect();
        assert_eq!(statuses.first(), Some(&"queued"), "{s}");
        let running = statuses.iter().position(|x| *x == "running").unwrap();
        assert!(running > 0, "{s}");
        // The places its participant was shown only ever went down (then the note went).
        let places: Vec<u64> = s["places"]
            .as_array()
            .unwrap()
            .iter()
            .filter_map(|v| v.as_u64())
            .collect();
        assert!(places.windows(2).all(|w| w[1] <= w[0]), "{s}");
        assert!(seq(s, "admitted_seq") < seq(s, "running_seq"), "{s}");
        assert!(seq(s, "running_seq") < seq(s, "final_seq"), "{s}");
    }
    // A team's evaluations in progress: admitted (its Jobs named on EvalAI) and not yet final.
    let holding = |team: u64, at: u64| {
        subs.iter()
            .filter(|s| s["team"] == team)
            .filter(|s| seq(s, "admitted_seq").unwrap() <= at && at < seq(s, "final_seq").unwrap())
            .count()
    };
    for s in subs {
        let team = s["team"].as_u64().unwrap();
        let admitted = seq(s, "admitted_seq").unwrap();
        // The cap held at every admission.
        assert!(
            holding(team, admitted) <= 2,
            "team {team} over its cap: {report}"
        );
        // A team's own submissions take their turns in the order they arrived (EvalAI's
        // `submitted_at`): one admitted later than a teammate that arrived after it would have
        // jumped its team's queue. (Across teams, admissions race each other's Launches: the
        // scheduler's order of creation decides who starts first, so the log shows no order.)
        for later in subs
            .iter()
            .filter(|l| l["team"] == team && l["arrival"].as_u64() > s["arrival"].as_u64())
        {
            let (mine, theirs) = (admitted, seq(later, "admitted_seq").unwrap());
            // Two admitted in one round of their team (both places free) may tell EvalAI in
            // either order; one admitted after a teammate's end never precedes it.
            let freed_between = subs.iter().any(|e| {
                e["team"] == team
                    && seq(e, "final_seq")
                        .is_some_and(|f| theirs.min(mine) < f && f < theirs.max(mine))
            });
            assert!(
                mine < theirs || !freed_between,
                "team {team}: {} arrived before {} but took its turn after: {report}",
                s["id"],
                later["id"]
            );
        }
    }
    // Team 1 sent 6 at once: others went ahead of its later ones (the cap did hold it back).
    let team_one_last = subs[5]["admitted_seq"].as_u64().unwrap();
    assert!(
        subs[6..]
            .iter()
            .any(|s| seq(s, "admitted_seq").unwrap() < team_one_last),
        "{report}"
    );
    // One budget for everyone: never more than EvalAI allows, never throttled.
    assert_eq!(report["throttled"], 0, "{report}");
    assert!(
        report["most_in_a_minute"].as_u64().unwrap() <= 60,
        "{report}"
    );
}

/// The documents the functions printed follow the format, one per invocation at most, and
/// add up to what happened: 12 arrivals, admissions, starts and finished ends, the GPU time and
/// the EvalAI requests the summary reports.
fn the_metrics_add_up(file: &std::path::Path, report: &Value, stdout: &str) {
    let text = std::fs::read_to_string(file).unwrap();
    let docs: Vec<Value> = text
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert!(!docs.is_empty(), "{stdout}");
    for doc in &docs {
        let problems = crate::emf::problems(doc);
        assert!(problems.is_empty(), "{problems:?} in {doc}");
        // One time per invocation: one document each.
        assert!(
            doc["Duration"].is_number(),
            "one document per invocation: {doc}"
        );
    }
    let total = |name: &str| -> f64 {
        docs.iter()
            .map(|d| match &d[name] {
                Value::Array(v) => v.iter().filter_map(Value::as_f64).sum(),
                v => v.as_f64().unwrap_or(0.0),
            })
            .sum()
    };
    for name in ["Arrivals", "Admissions", "Starts", "Ends"] {
        assert_eq!(total(name), 12.0, "{name}: {stdout}");
    }
    assert!(docs
        .iter()
        .filter(|d| d.get("Ends").is_some())
        .all(|d| d["Outcome"] == "FINISHED" && d["Leaderboard"] == "2.0"));
    assert_eq!(total("Failures"), 0.0);
    // 12 runs of 2 routes on 2 pairs: every route done, some GPU time held.
    assert_eq!(total("RoutesDone"), 24.0, "{stdout}");
    assert!(total("GpuSecondsOnDemand") > 0.0);
    // Every request the functions sent is one EvalAI saw (the summary's own reads besides).
    let seen = report["queue"]["requests"].as_f64().unwrap();
    let sent = total("EvalAiRequests");
    assert!(sent > 0.0 && sent <= seen, "{sent} sent, EvalAI saw {seen}");
    // The sweep counted the local node's 4 GPUs every time it ran, and at most those held.
    let sweeps: Vec<&Value> = docs.iter().filter(|d| d["Stage"] == "sweep").collect();
    assert!(!sweeps.is_empty(), "{stdout}");
    for doc in &sweeps {
        assert_eq!(doc["GpusBilled"], 4.0, "{doc}");
        assert!(
            doc["GpusHeld"]
                .as_f64()
                .is_some_and(|h| (0.0..=4.0).contains(&h)),
            "{doc}"
        );
    }
    // The summary says the same totals.
    let summary = &report["metrics"];
    assert_eq!(summary["documents"], docs.len());
    assert_eq!(summary["totals"]["Arrivals"], 12.0);
    assert!(
        stdout.contains("arrivals 12, admissions 12, starts 12, ends 12 (12 FINISHED)"),
        "{stdout}"
    );
}

#[test]
#[ignore = "needs moto and the real control plane (make real-kube)"]
fn sigterm_to_a_real_control_plane_run_leaves_no_process_of_it() {
    use std::io::{BufRead, BufReader};
    use std::time::{Duration, Instant};
    // Long routes: the pods still run when the signal comes, as when `timeout` or CI ends it.
    let mut child = Command::new(lbctl())
        .args(["local", "run", "--kube", "real", "--route-seconds", "60"])
        .args(["--timeout", "240"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let root = nix::unistd::Pid::from_raw(child.id() as i32);
    let lines = BufReader::new(child.stdout.take().unwrap()).lines();
    // Drained on a thread: a full pipe must not stall the run.
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in lines.map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    let comm = |pid: &nix::unistd::Pid| {
        std::fs::read_to_string(format!("/proc/{pid}/comm")).unwrap_or_default()
    };
    let deadline = Instant::now() + Duration::from_secs(180);
    let started = loop {
        let seen = lb_proc::descendants(root);
        // The control plane is up and a pod's agent runs.
        if seen.iter().any(|p| comm(p).starts_with("kube-apiserver"))
            && seen.iter().any(|p| comm(p).starts_with("fake-evaluator"))
        {
            break seen;
        }
        assert!(
            Instant::now() < deadline,
            "the run never got its pods running"
        );
        assert!(child.try_wait().unwrap().is_none(), "the run ended early");
        std::thread::sleep(Duration::from_millis(500));
    };
    nix::sys::signal::kill(root, nix::sys::signal::Signal::SIGTERM).unwrap();
    let deadline = Instant::now() + Duration::from_secs(60);
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        assert!(Instant::now() < deadline, "the run did not stop on SIGTERM");
        std::thread::sleep(Duration::from_millis(200));
    };
    let said: Vec<String> = rx.try_iter().collect();
    assert_eq!(status.code(), Some(143), "{said:?}");
    assert!(
        said.iter().any(|l| l.contains("stopped by SIGTERM")),
        "{said:?}"
    );
    // Everything it started is gone (a zombie is gone already: only its parent's reaping waits).
    let alive = |pid: &nix::unistd::Pid| {
        std::fs::read_to_string(format!("/proc/{pid}/stat"))
            .ok()
            .and_then(|stat| {
                stat.rsplit_once(')')
                    .map(|(_, rest)| rest.trim().to_owned())
            })
            .is_some_and(|rest| !rest.starts_with('Z'))
    };
    std::thread::sleep(Duration::from_secs(1));
    let left: Vec<String> = (started.iter())
        .filter(|p| alive(p))
        .map(|p| format!("{p} {}", comm(p).trim()))
        .collect();
    assert!(left.is_empty(), "left running: {left:?}");
}
