//! The state contract across releases: what a run hands on (each function's input, a continued
//! execution's), recorded per release in `statemachine/states/<release>/`, is read by this code,
//! or the release says how the runs in flight cross the change (`crossing.json`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;
use serde::Serialize;
use serde_json::Value;

fn states_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../statemachine/states")
}

/// The releases, oldest first (their folders are named by date, `YYYY-MM-DD`).
fn releases() -> Vec<PathBuf> {
    let mut found: Vec<PathBuf> = std::fs::read_dir(states_dir())
        .expect("statemachine/states exists")
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_dir())
        .collect();
    found.sort();
    found
}

/// A release's fixtures by kind (`launch`, `monitor-running`, ...), and its crossing notes.
fn fixtures(release: &Path) -> (BTreeMap<String, Value>, BTreeMap<String, String>) {
    let mut found = BTreeMap::new();
    let mut crossing = BTreeMap::new();
    for entry in std::fs::read_dir(release).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_stem().unwrap().to_str().unwrap().to_string();
        let text = std::fs::read_to_string(&path).unwrap();
        if name == "crossing" {
            crossing = serde_json::from_str(&text).expect("crossing.json maps a kind to words");
        } else {
            found.insert(name, serde_json::from_str(&text).unwrap());
        }
    }
    (found, crossing)
}

/// Reads one value as `T` and writes it back as this code would hand it on.
fn through<T: DeserializeOwned + Serialize>(value: &Value) -> Result<Value, String> {
    let typed: T = serde_path_to_error::deserialize(value.clone())
        .map_err(|e| format!("at `{}`: {}", e.path(), e.inner()))?;
    Ok(serde_json::to_value(typed).unwrap())
}

/// What of a fixture its reader keeps: all of it, but for Finalize, which takes the whole
/// execution state and reads Intake's decision, the run and the caught error of it.
fn kept(kind: &str, value: &Value) -> Value {
    let mut kept = value.clone();
    if kind == "finalize" {
        if let Some(state) = kept.get_mut("state").and_then(Value::as_object_mut) {
            state.retain(|key, _| ["intake", "run", "error"].contains(&key.as_str()));
        }
    }
    kept
}

/// A fixture read by the function (or the state) that meets it.
fn read_back(kind: &str, value: &Value) -> Result<Value, String> {
    match kind.split_once('-').map_or(kind, |(head, _)| head) {
        "launch" => through::<launch::LaunchInput>(value),
        "monitor" => through::<monitor::MonitorInput>(value),
        "finalize" => through::<finalize::FinalizeInput>(value),
        "continued" => through::<lb_pipeline::payload::ContinuedInput>(value),
        other => Err(format!("no reader for a fixture of kind `{other}`")),
    }
}

/// What a release records at least: the first launch and the one after a wait for the team's
/// turn, a round of a running and of a continued run, Finalize's input and a continuation.
const KINDS: [&str; 6] = [
    "launch",
    "launch-admitted",
    "monitor-running",
    "monitor-continued",
    "finalize",
    "continued",
];

#[test]
fn every_release_s_states_are_read_or_say_how_runs_in_flight_cross() {
    let releases = releases();
    assert!(!releases.is_empty(), "no release's states are recorded");
    let mut problems = Vec::new();
    for release in &releases {
        let name = release.file_name().unwrap().to_string_lossy();
        let (found, crossing) = fixtures(release);
        for (kind, value) in &found {
            match (read_back(kind, value), crossing.get(kind)) {
                (Ok(_), None) => {}
                (Err(e), None) => problems.push(format!(
                    "{name}/{kind}.json no longer reads ({e}): a run in flight hands this on; \
                     say in {name}/crossing.json how such runs cross the change (for example: \
                     they finish on their version through the alias and never meet this code)"
                )),
                (Ok(_), Some(_)) => problems.push(format!(
                    "{name}/crossing.json explains `{kind}`, which reads: drop the note"
                )),
                (Err(_), Some(words)) if words.trim().len() < 20 => problems.push(format!(
                    "{name}/crossing.json: `{kind}` needs words on how runs in flight cross"
                )),
                (Err(_), Some(_)) => {}
            }
        }
        for kind in crossing.keys().filter(|k| !found.contains_key(*k)) {
            problems.push(format!(
                "{name}/crossing.json names `{kind}`, which it does not hold"
            ));
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn the_newest_release_s_states_are_what_this_code_hands_on() {
    let newest = releases().pop().expect("a release");
    let name = newest.file_name().unwrap().to_string_lossy().into_owned();
    let (found, _) = fixtures(&newest);
    for kind in KINDS {
        assert!(found.contains_key(kind), "{name} has no `{kind}` state");
    }
    for (kind, value) in &found {
        let written = read_back(kind, value).unwrap_or_else(|e| panic!("{name}/{kind}: {e}"));
        assert_eq!(
            written,
            kept(kind, value),
            "{name}/{kind}.json is not what this code hands on: the state changed since {name}. \
             Record this release's states (LB_RECORD_STATES=<YYYY-MM-DD> cargo test -p local-cli \
             --test integration states:: -- --ignored), keeping the older releases"
        );
    }
}

/// Records (with `LB_RECORD_STATES=<release>`) or checks what a whole local run hands on: two
/// submissions of one team held to one at a time (a queued round, an admitted launch) and a
/// history budget small enough to continue as new.
#[test]
#[ignore = "needs moto"]
fn a_local_run_hands_on_what_the_newest_release_recorded() {
    let dir = tempfile::tempdir().unwrap();
    let budget = lb_domain::run::history::MIN_BUDGET.to_string();
    let record = dir.path().join("states");
    let (report, _) = crate::local_run::local_run(
        &[
            "--submissions",
            "2",
            "--team-limit",
            "1",
            "--history-budget",
            &budget,
            "--route-seconds",
            "1",
            "--timeout",
            "300",
            "--record-states",
            record.to_str().unwrap(),
        ],
        &[],
    );
    assert_eq!(report["ok"], true, "{report}");
    let (recorded, _) = fixtures(&record);
    for (kind, value) in &recorded {
        let written = read_back(kind, value).unwrap_or_else(|e| panic!("{kind}: {e}"));
        assert_eq!(
            written,
            kept(kind, value),
            "{kind}: this code does not read back what it hands on"
        );
    }
    if let Ok(release) = std::env::var("LB_RECORD_STATES") {
        let into = states_dir().join(&release);
        std::fs::create_dir_all(&into).unwrap();
        for kind in recorded.keys() {
            let file = format!("{kind}.json");
            std::fs::copy(record.join(&file), into.join(&file)).unwrap();
        }
        return;
    }
    let (newest, _) = fixtures(&releases().pop().unwrap());
    let kinds = |m: &BTreeMap<String, Value>| m.keys().cloned().collect::<Vec<_>>();
    for kind in KINDS {
        assert!(
            recorded.contains_key(kind),
            "the run handed on no `{kind}`: {:?}",
            kinds(&recorded)
        );
        assert!(
            newest.contains_key(kind),
            "the newest release holds no `{kind}`"
        );
    }
}
