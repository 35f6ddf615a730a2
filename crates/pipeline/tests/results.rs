//! Collecting results from S3 (moto) gives exactly what the official tooling gives.

use lb_aws::s3::SubmissionStore;
use lb_domain::results::Leaderboard;
use lb_domain::testutil::results_fixtures_dir;
use lb_pipeline::payload::PairRoutes;
use lb_pipeline::results::{collect, fingerprint};
use local_stack::moto::MotoServer;

fn pairs(subsets: &[&str]) -> Vec<PairRoutes> {
    subsets
        .iter()
        .enumerate()
        .map(|(i, routes)| PairRoutes {
            id: i as u32 + 1,
            routes: routes.to_string(),
        })
        .collect()
}

async fn store(moto: &MotoServer, submission: u64) -> SubmissionStore {
    let sdk = lb_aws::sdk_config_at(&moto.endpoint(), "us-east-1").await;
    let client = lb_aws::s3_client(&sdk);
    let _ = client.create_bucket().bucket("results").send().await;
    SubmissionStore::new(client, "results", submission)
}

async fn stored(store: &SubmissionStore, key: &str) -> String {
    String::from_utf8(store.get_bounded(key, 1 << 20).await.unwrap()).unwrap()
}

#[tokio::test]
#[ignore = "needs moto"]
async fn the_finished_fixture_merges_to_the_official_files_and_lands_in_s3() {
    let moto = MotoServer::start().unwrap();
    let store = store(&moto, 42).await;
    let case = results_fixtures_dir().join("a_4workers_20routes_finished");
    let plan = pairs(&["0-4", "5-9", "10-14", "15-19"]);
    assert_eq!(fingerprint(&store).await.unwrap(), "");
    for id in 1..=4 {
        let bytes = std::fs::read(case.join(format!("input/worker{id}.json"))).unwrap();
        store
            .put(
                &format!("agent/partial_agent_results{id}.json"),
                bytes,
                "application/json",
            )
            .await
            .unwrap();
    }
    let snapshot = collect(&store, Leaderboard::V2, &plan, 1).await.unwrap();
    assert!(snapshot.complete);
    assert_eq!(snapshot.progress, (20, 20));
    assert_eq!(snapshot.metrics.len(), 15);
    assert_eq!(snapshot.fingerprint, fingerprint(&store).await.unwrap());
    // A read writes nothing: the files are kept only when asked.
    assert!(store
        .get_bounded("42/evalai/stdout.txt", 1 << 20)
        .await
        .is_err());
    lb_pipeline::results::store(&store, &snapshot)
        .await
        .unwrap();
    let expected = |name: &str| std::fs::read_to_string(case.join("expected").join(name)).unwrap();
    assert_eq!(
        stored(&store, "42/evalai/stdout.txt").await,
        expected("stdout.txt")
    );
    assert_eq!(
        stored(&store, "42/agent_results.json").await,
        expected("merged.json")
    );
    let results: serde_json::Value =
        serde_json::from_str(&stored(&store, "42/evalai/results.json").await).unwrap();
    let expected_results: serde_json::Value =
        serde_json::from_str(&expected("results.json")).unwrap();
    assert_eq!(results, expected_results);
}

#[tokio::test]
#[ignore = "needs moto"]
async fn two_of_four_workers_reported_is_partial_and_a_changed_file_changes_the_fingerprint() {
    let moto = MotoServer::start().unwrap();
    let store = store(&moto, 7).await;
    let case = results_fixtures_dir().join("a_4workers_20routes_finished");
    let plan = pairs(&["0-4", "5-9", "10-14", "15-19"]);
    for id in 1..=2 {
        let bytes = std::fs::read(case.join(format!("input/worker{id}.json"))).unwrap();
        store
            .put(
                &format!("agent/partial_agent_results{id}.json"),
                bytes,
                "application/json",
            )
            .await
            .unwrap();
    }
    let first = collect(&store, Leaderboard::V2, &plan, 1).await.unwrap();
    assert!(!first.complete);
    assert_eq!(first.progress, (10, 20));
    let bytes = std::fs::read(case.join("input/worker3.json")).unwrap();
    store
        .put(
            "agent/partial_agent_results3.json",
            bytes,
            "application/json",
        )
        .await
        .unwrap();
    assert_ne!(fingerprint(&store).await.unwrap(), first.fingerprint);
    let third = collect(&store, Leaderboard::V2, &plan, 1).await.unwrap();
    assert_ne!(
        third.content, first.content,
        "routes done: an update is due"
    );

    // The same records with a duration toggled and other bytes: read again, nothing to send.
    let text = std::fs::read_to_string(case.join("input/worker3.json")).unwrap();
    let mut file: serde_json::Value = serde_json::from_str(&text).unwrap();
    let meta = &mut file["_checkpoint"]["records"][0]["meta"]["duration_system"];
    *meta = serde_json::json!(meta.as_f64().unwrap() + 0.5);
    let toggled = serde_json::to_vec(&file).unwrap();
    store
        .put(
            "agent/partial_agent_results3.json",
            toggled,
            "application/json",
        )
        .await
        .unwrap();
    let fourth = collect(&store, Leaderboard::V2, &plan, 1).await.unwrap();
    assert_ne!(fourth.fingerprint, third.fingerprint);
    assert_eq!(fourth.content, third.content);
}

#[tokio::test]
#[ignore = "needs moto"]
async fn a_worker_file_outside_its_subset_is_a_named_error() {
    let moto = MotoServer::start().unwrap();
    let store = store(&moto, 8).await;
    let case = results_fixtures_dir().join("a_4workers_20routes_finished");
    let bytes = std::fs::read(case.join("input/worker2.json")).unwrap();
    // Worker 2's routes (5-9) uploaded as worker 1's (0-4): the participant cannot move routes.
    store
        .put(
            "agent/partial_agent_results1.json",
            bytes,
            "application/json",
        )
        .await
        .unwrap();
    let err = collect(&store, Leaderboard::V2, &pairs(&["0-4", "5-9"]), 1)
        .await
        .unwrap_err();
    assert_eq!(err.name(), "ResultsOutsideSubset", "{err}");
}
