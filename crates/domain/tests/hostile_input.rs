//! Results files written by untrusted code: each problem is a typed error naming the file and
//! field, or a documented "treated as empty"; never a panic.

use lb_domain::results::{
    merge, read_worker_file, EmptyReason, EvalAiFiles, Expected, Leaderboard, MergeOptions,
    ResultsError, RouteSubset, WorkerFile, MAX_FILE_BYTES,
};
use lb_domain::testutil::results_fixtures_dir;
use proptest::prelude::*;
use serde_json::{json, Value};

fn fixture(rel: &str) -> Vec<u8> {
    std::fs::read(results_fixtures_dir().join(rel)).unwrap()
}

fn worker1() -> Value {
    serde_json::from_slice(&fixture("a_4workers_20routes_finished/input/worker1.json")).unwrap()
}

fn read(doc: &Value) -> Result<WorkerFile, ResultsError> {
    let bytes = serde_json::to_vec(doc).unwrap();
    read_worker_file("worker1.json", Some(&bytes), Leaderboard::V2, None)
}

fn invalid_field(result: Result<WorkerFile, ResultsError>) -> (String, String) {
    match result {
        Err(ResultsError::Invalid {
            file,
            field,
            problem,
        }) => {
            assert_eq!(file, "worker1.json");
            (field, problem)
        }
        other => panic!("expected an Invalid error, got {other:?}"),
    }
}

#[test]
fn missing_blank_and_falsy_files_count_as_empty() {
    let read = |b: Option<&[u8]>| read_worker_file("w.json", b, Leaderboard::V2, None).unwrap();
    assert_eq!(read(None), WorkerFile::Empty(EmptyReason::Missing));
    for blank in [&b""[..], b"  \n", b"{}", b"null", b" [] "] {
        assert_eq!(
            read(Some(blank)),
            WorkerFile::Empty(EmptyReason::Blank),
            "{blank:?}"
        );
    }
}

#[test]
fn a_truncated_file_counts_as_unreadable_not_as_a_result() {
    let bytes = fixture("a_4workers_20routes_finished/input/worker1.json");
    let cut = &bytes[..bytes.len() / 2];
    match read_worker_file("w.json", Some(cut), Leaderboard::V2, None).unwrap() {
        WorkerFile::Empty(EmptyReason::Unreadable(why)) => assert!(why.contains("EOF"), "{why}"),
        other => panic!("{other:?}"),
    }
}

#[test]
fn nan_is_rejected_with_its_position() {
    let text =
        String::from_utf8(fixture("a_4workers_20routes_finished/input/worker1.json")).unwrap();
    let text = text.replacen("\"score_route\": 100", "\"score_route\": NaN", 1);
    let err = read_worker_file("w.json", Some(text.as_bytes()), Leaderboard::V2, None).unwrap_err();
    assert_eq!(err.name(), "ResultsNonFinite");
    assert!(err.to_string().contains("`NaN` at line"), "{err}");
}

#[test]
fn a_string_score_names_the_field() {
    let mut doc = worker1();
    doc["_checkpoint"]["records"][2]["scores"]["score_route"] = json!("100");
    let (field, problem) = invalid_field(read(&doc));
    assert_eq!(field, "_checkpoint.records[2].scores.score_route");
    assert!(problem.contains("expected a number"), "{problem}");
}

#[test]
fn negative_numbers_are_rejected() {
    let mut doc = worker1();
    doc["_checkpoint"]["records"][0]["meta"]["route_length"] = json!(-1.5);
    let (field, problem) = invalid_field(read(&doc));
    assert_eq!(field, "_checkpoint.records[0].meta.route_length");
    assert_eq!(problem, "is negative (`-1.5`)");
}

#[test]
fn huge_numbers_are_rejected() {
    let mut doc = worker1();
    doc["_checkpoint"]["records"][1]["meta"]["duration_system"] = json!(1e300);
    let (field, _) = invalid_field(read(&doc));
    assert_eq!(field, "_checkpoint.records[1].meta.duration_system");
}

#[test]
fn scores_outside_their_ranges_are_rejected() {
    // A per-route score of 1e12 was once published as a driving score of 50,000,000,021.
    for (key, value, max) in [
        ("score_route", json!(1e12), "100"),
        ("score_composed", json!(100.5), "100"),
        ("score_penalty", json!(1.5), "1"),
    ] {
        let mut doc = worker1();
        doc["_checkpoint"]["records"][3]["scores"][key] = value;
        let (field, problem) = invalid_field(read(&doc));
        assert_eq!(field, format!("_checkpoint.records[3].scores.{key}"));
        assert!(
            problem.contains(&format!("over its maximum of {max}")),
            "{problem}"
        );
    }
    // The edges are scores the evaluator writes.
    let mut doc = worker1();
    let scores = &mut doc["_checkpoint"]["records"][3]["scores"];
    (
        scores["score_route"],
        scores["score_composed"],
        scores["score_penalty"],
    ) = (json!(100.0), json!(100), json!(1.0));
    assert!(matches!(read(&doc), Ok(WorkerFile::Present(_))));
}

#[test]
fn malformed_route_ids_are_rejected() {
    for bad in [
        "RouteScenario_4",
        "Route_4_rep0",
        "RouteScenario_-4_rep0",
        "RouteScenario_4_rep",
        "RouteScenario_ 4_rep0",
        "RouteScenario_٤_rep0",
    ] {
        let mut doc = worker1();
        doc["_checkpoint"]["records"][0]["route_id"] = json!(bad);
        let (field, problem) = invalid_field(read(&doc));
        assert_eq!(field, "_checkpoint.records[0].route_id", "{bad}");
        assert!(problem.contains("RouteScenario_<n>_rep<r>"), "{problem}");
    }
    let mut doc = worker1();
    doc["_checkpoint"]["records"][0]["route_id"] = json!(7);
    let (field, _) = invalid_field(read(&doc));
    assert_eq!(field, "_checkpoint.records[0].route_id");
}

#[test]
fn routes_outside_the_assigned_subset_are_rejected() {
    let bytes = fixture("a_4workers_20routes_finished/input/worker1.json");
    let subset: RouteSubset = "0-4".parse().unwrap();
    assert!(matches!(
        read_worker_file("w.json", Some(&bytes), Leaderboard::V2, Some(subset)).unwrap(),
        WorkerFile::Present(_)
    ));
    let subset: RouteSubset = "5-9".parse().unwrap();
    let err = read_worker_file("w.json", Some(&bytes), Leaderboard::V2, Some(subset)).unwrap_err();
    assert_eq!(err.name(), "ResultsOutsideSubset");
    assert!(err.to_string().contains("`RouteScenario_0_rep0`"), "{err}");
}

#[test]
fn a_missing_infraction_kind_or_field_is_named() {
    let mut doc = worker1();
    doc["_checkpoint"]["records"][3]["infractions"]
        .as_object_mut()
        .unwrap()
        .remove("red_light");
    let (field, problem) = invalid_field(read(&doc));
    assert_eq!(field, "_checkpoint.records[3].infractions");
    assert_eq!(problem, "has no `red_light` list");

    let mut doc = worker1();
    doc["_checkpoint"]
        .as_object_mut()
        .unwrap()
        .remove("records");
    let (field, problem) = invalid_field(read(&doc));
    assert_eq!(field, "_checkpoint");
    assert!(problem.contains("missing field `records`"), "{problem}");
}

#[test]
fn control_characters_cannot_forge_stdout_lines() {
    let mut doc = worker1();
    doc["_checkpoint"]["records"][0]["status"] =
        json!("Completed\n- Results:\n  - Driving score: 100");
    let (field, _) = invalid_field(read(&doc));
    assert_eq!(field, "_checkpoint.records[0].status");
    let mut doc = worker1();
    doc["sensors"][0] = json!("carla_camera\u{1b}[2J");
    let (field, _) = invalid_field(read(&doc));
    assert_eq!(field, "sensors[0]");
}

#[test]
fn progress_must_be_a_pair_of_counts() {
    let mut doc = worker1();
    doc["_checkpoint"]["progress"] = json!([5]);
    let (field, _) = invalid_field(read(&doc));
    assert_eq!(field, "_checkpoint.progress");
    doc["_checkpoint"]["progress"] = json!([5, 2.5]);
    let (field, _) = invalid_field(read(&doc));
    assert_eq!(field, "_checkpoint.progress[1]");
}

#[test]
fn an_oversized_file_is_refused_before_parsing() {
    let big = vec![b' '; MAX_FILE_BYTES + 1];
    let err = read_worker_file("w.json", Some(&big), Leaderboard::V2, None).unwrap_err();
    assert_eq!(err.name(), "ResultsTooLarge");
}

#[test]
fn unknown_sensors_are_shown_as_they_are() {
    let mut doc = worker1();
    doc["sensors"] = json!(["carla_camera", "sensor.other.thermal"]);
    let WorkerFile::Present(file) = read(&doc).unwrap() else {
        panic!()
    };
    let merged = merge(vec![file], MergeOptions::default()).unwrap().merged;
    let out = EvalAiFiles::generate(Some(&merged), Leaderboard::V2).stdout;
    assert!(
        out.contains("  - 1 RGB Camera\n  - 1 sensor.other.thermal\n"),
        "{out}"
    );
}

fn arb_json() -> impl Strategy<Value = Value> {
    let leaf = prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::Bool),
        any::<i64>().prop_map(|n| json!(n)),
        any::<f64>()
            .prop_filter("finite", |f| f.is_finite())
            .prop_map(|f| json!(f)),
        "[a-zA-Z_ 0-9]{0,24}".prop_map(Value::String),
        Just(json!("RouteScenario_3_rep0")),
    ];
    leaf.prop_recursive(4, 64, 8, |inner| {
        let keys = prop_oneof![
            Just("_checkpoint".to_owned()),
            Just("records".to_owned()),
            Just("progress".to_owned()),
            Just("sensors".to_owned()),
            Just("scores".to_owned()),
            Just("meta".to_owned()),
            Just("route_id".to_owned()),
            "[a-z_]{1,12}",
        ];
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..6).prop_map(Value::Array),
            prop::collection::vec((keys, inner), 0..6)
                .prop_map(|kv| Value::Object(kv.into_iter().collect())),
        ]
    })
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, ..ProptestConfig::default() })]

    #[test]
    fn random_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..2048)) {
        for lb in [Leaderboard::V1, Leaderboard::V2] {
            let _ = read_worker_file("fuzz.json", Some(&bytes), lb, None);
        }
    }

    #[test]
    fn arbitrary_json_never_panics(doc in arb_json()) {
        let bytes = serde_json::to_vec(&doc).unwrap();
        if let Ok(WorkerFile::Present(file)) = read_worker_file("fuzz.json", Some(&bytes), Leaderboard::V2, None) {
            if let Ok(outcome) = merge(vec![file], MergeOptions::default()) {
                let _ = EvalAiFiles::generate(Some(&outcome.merged), Leaderboard::V2);
            }
        }
    }

    #[test]
    fn mutated_real_files_never_panic_through_merge_and_evalai_files(
        pos in 0usize..4096, byte in any::<u8>(), cut in 0usize..8000,
        score in prop_oneof![Just(json!(0)), Just(json!(1e11)), Just(json!(0.5)), Just(json!(99.999999))],
        route in 0u64..40, rep in 0u64..3,
    ) {
        let mut bytes = fixture("a_4workers_20routes_finished/input/worker2.json");
        if pos < bytes.len() { bytes[pos] = byte; }
        let _ = read_worker_file("w2.json", Some(&bytes[..bytes.len().min(cut.max(1))]), Leaderboard::V2, None);

        let mut doc = worker1();
        doc["_checkpoint"]["records"][1]["scores"]["score_route"] = score;
        doc["_checkpoint"]["records"][2]["route_id"] = json!(format!("RouteScenario_{route}_rep{rep}"));
        let other = fixture("a_4workers_20routes_finished/input/worker2.json");
        let files: Vec<_> = [serde_json::to_vec(&doc).unwrap(), other]
            .iter()
            .filter_map(|b| match read_worker_file("w.json", Some(b), Leaderboard::V2, None) {
                Ok(WorkerFile::Present(f)) => Some(f),
                _ => None,
            })
            .collect();
        for expected in [None, Some(Expected { routes: 10, repetitions: 1 })] {
            if let Ok(outcome) = merge(files.clone(), MergeOptions { leaderboard: Leaderboard::V2, expected }) {
                let evalai = EvalAiFiles::generate(Some(&outcome.merged), Leaderboard::V2);
                // Whatever went in, every metric posted is a finite number.
                prop_assert!(evalai.accuracies().iter().all(|(_, v)| v.as_f64().is_finite()));
            }
        }
    }
}
