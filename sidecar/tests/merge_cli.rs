//! `lb-sidecar merge` as operators run it: a whole process on the fixture files.

use std::path::{Path, PathBuf};

use lb_domain::testutil::results_fixtures_dir;
use std::process::{Command, Output};

fn inputs(case: &str) -> Vec<PathBuf> {
    let dir = results_fixtures_dir().join(case);
    let spec: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("case.json")).unwrap()).unwrap();
    spec["merge_file_paths"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| dir.join(p.as_str().unwrap()))
        .collect()
}

fn merge(out: &Path, extra: &[&str], files: &[PathBuf]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_lb-sidecar"))
        .arg("merge")
        .arg("--out")
        .arg(out)
        .args(extra)
        .args(files)
        .env("RUST_LOG", "warn")
        .output()
        .unwrap()
}

fn read(path: PathBuf) -> String {
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn listing(dir: &Path) -> Vec<String> {
    let mut names = Vec::new();
    for entry in walk(dir) {
        names.push(entry.strip_prefix(dir).unwrap().display().to_string());
    }
    names.sort();
    names
}

fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            out.extend(walk(&path));
        } else {
            out.push(path);
        }
    }
    out
}

#[test]
fn merge_writes_the_four_files_identical_to_the_official_ones() {
    for (case, lb) in [
        ("a_4workers_20routes_finished", "2.0"),
        ("b_partial_progress_midrun", "2.0"),
        ("d_repetitions_2routes_3reps", "2.0"),
        ("k1_lb1_3workers_12routes", "1.0"),
        ("e4_no_worker_files", "2.0"),
    ] {
        let out = tempfile::tempdir().unwrap();
        let result = merge(out.path(), &["--leaderboard", lb], &inputs(case));
        assert!(
            result.status.success(),
            "{case}: {}",
            String::from_utf8_lossy(&result.stderr)
        );
        let expected = results_fixtures_dir().join(case).join("expected");
        for (ours, theirs) in [
            ("agent_results.json", "merged.json"),
            ("evalai/results.json", "results.json"),
            ("evalai/stdout.txt", "stdout.txt"),
            ("evalai/metadata.json", "metadata.json"),
        ] {
            assert_eq!(
                read(out.path().join(ours)),
                read(expected.join(theirs)),
                "{case}: {ours}"
            );
        }
        assert_eq!(
            listing(out.path()),
            [
                "agent_results.json",
                "evalai/metadata.json",
                "evalai/results.json",
                "evalai/stdout.txt"
            ],
            "{case}: no staging files left"
        );
    }
}

#[test]
fn a_merge_error_exits_non_zero_and_leaves_no_stale_or_partial_output() {
    let out = tempfile::tempdir().unwrap();
    // A previous successful merge...
    assert!(
        merge(out.path(), &[], &inputs("a_4workers_20routes_finished"))
            .status
            .success()
    );
    std::fs::write(out.path().join("notes.txt"), "operator's own file").unwrap();
    // ...then one that fails: its error is reported and the old result is gone.
    for (case, message) in [
        ("g1_sensor_mismatch", "Stopping. Found two files with different sensor configurations"),
        ("f1_duplicate_route_finished", "Stopping. Found that the route RouteScenario_4_rep0 has more than one record"),
        ("h1_gap_in_route_ids", "Stopping. Missing some data as the ids jumped from RouteScenario_4_rep0 to RouteScenario_6_rep0"),
    ] {
        let result = merge(out.path(), &[], &inputs(case));
        assert_eq!(result.status.code(), Some(1), "{case}");
        let stderr = String::from_utf8_lossy(&result.stderr);
        assert!(stderr.contains(message), "{case}: {stderr}");
        assert_eq!(listing(out.path()), ["notes.txt"], "{case}");
    }
}

#[test]
fn fewer_records_than_planned_is_written_as_partial() {
    let out = tempfile::tempdir().unwrap();
    let mut files = inputs("a_4workers_20routes_finished");
    files[3] = out.path().join("never-written.json");
    let result = merge(out.path(), &["--expect-routes", "20"], &files);
    assert!(
        result.status.success(),
        "{}",
        String::from_utf8_lossy(&result.stderr)
    );
    let stdout = String::from_utf8_lossy(&result.stdout);
    assert!(stdout.contains("partial"), "{stdout}");
    let merged: serde_json::Value =
        serde_json::from_str(&read(out.path().join("agent_results.json"))).unwrap();
    assert_eq!(merged["entry_status"], "Started");
    assert_eq!(merged["eligible"], false);
    assert_eq!(
        merged["_checkpoint"]["progress"],
        serde_json::json!([15, 20])
    );
    let results: serde_json::Value =
        serde_json::from_str(&read(out.path().join("evalai/results.json"))).unwrap();
    assert_eq!(results[0]["accuracies"]["Driving score"], 0);
}

#[test]
fn subsets_catch_a_worker_reporting_someone_elses_routes() {
    let out = tempfile::tempdir().unwrap();
    let files = inputs("a_4workers_20routes_finished");
    let ok = merge(out.path(), &["--subsets", "0-4,5-9,10-14,15-19"], &files);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    let bad = merge(out.path(), &["--subsets", "0-4,10-14,5-9,15-19"], &files);
    assert_eq!(bad.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&bad.stderr);
    assert!(stderr.contains("ResultsOutsideSubset"), "{stderr}");
    assert!(stderr.contains("worker2.json"), "{stderr}");
    let count = merge(out.path(), &["--subsets", "0-4"], &files);
    assert_eq!(count.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&count.stderr).contains("--subsets gives 1 subsets for 4 files")
    );
}

#[test]
fn bad_arguments_are_named() {
    let out = tempfile::tempdir().unwrap();
    let result = merge(
        out.path(),
        &["--leaderboard", "3.0"],
        &inputs("i_single_route"),
    );
    assert_eq!(result.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&result.stderr).contains("unknown leaderboard `3.0`"));
    let result = merge(out.path(), &["--subsets", "9-2"], &inputs("i_single_route"));
    assert_eq!(result.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&result.stderr).contains("route subset `9-2`"));
}

#[test]
fn invalid_results_print_the_official_validation_message() {
    let out = tempfile::tempdir().unwrap();
    let result = merge(out.path(), &[], &inputs("l_agent_setup_failure_invalid"));
    assert!(result.status.success());
    let stdout = String::from_utf8_lossy(&result.stdout);
    assert!(
        stdout.contains("Setting their status to 'Invalid': Missing 'sensors' data"),
        "{stdout}"
    );
    assert!(stdout.contains("entry status Invalid"), "{stdout}");
}
