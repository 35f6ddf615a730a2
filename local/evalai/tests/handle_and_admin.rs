//! The handle, the `/_admin/` API, fault injection and fixture validation.

use crate::common;

use std::time::Duration;

use common::*;
use fake_evalai::{AdminError, FakeEvalAi, Faults, Fixture, FixtureError, NewSubmission};
use reqwest::{Method, StatusCode};
use serde_json::json;

async fn server() -> (FakeEvalAi, Api) {
    let fake = FakeEvalAi::start(Fixture::default()).await.expect("start");
    let api = Api::new(fake.url());
    (fake, api)
}

#[tokio::test]
async fn the_request_log_records_bodies_and_users_but_never_credentials() {
    let (fake, api) = server().await;
    api.patch_json(
        UPDATE,
        HOST,
        json!({"submission": 1, "submission_status": "running"}),
    )
    .await;
    api.send(
        Method::PUT,
        UPDATE,
        Some("Token host-legacy-token"),
        Body::Form("submission=1&submission_status=failed"),
    )
    .await;
    api.get("/_admin/state", None).await;
    let log = api.get("/_admin/requests", None).await;
    assert_eq!(log.status, StatusCode::OK);
    assert!(!log.text.contains("host-token"), "{}", log.text);
    assert!(!log.text.contains("host-legacy-token"));
    let records = fake.requests();
    assert_eq!(records.len(), 4, "{records:#?}");
    assert_eq!(records[0].user_id, Some(1));
    assert_eq!(records[0].status, 200);
    assert_eq!(
        records[0].body,
        Some(json!({"submission": 1, "submission_status": "running"}))
    );
    assert_eq!(
        records[1].body,
        Some(json!({"submission": "1", "submission_status": "failed"}))
    );
    assert!(!records[0].admin);
    assert!(records[2].admin && records[3].admin);
    assert_eq!(records[2].path, "/_admin/state");
    let later = fake.requests_since(records[1].seq);
    assert_eq!(later.len(), 2);
}

#[tokio::test]
async fn admin_cancel_and_resume_follow_evalai_rules() {
    let (fake, api) = server().await;
    let r = api
        .send(
            Method::POST,
            "/_admin/submissions/1/resume",
            None,
            Body::None,
        )
        .await;
    assert_eq!(r.status, StatusCode::BAD_REQUEST);
    assert_eq!(r.json()["name"], "NotResumable");
    let r = api
        .send(
            Method::POST,
            "/_admin/submissions/1/cancel",
            None,
            Body::None,
        )
        .await;
    assert_eq!(r.status, StatusCode::OK);
    assert_eq!(r.json()["status"], "cancelled");
    let r = api
        .send(
            Method::POST,
            "/_admin/submissions/404/cancel",
            None,
            Body::None,
        )
        .await;
    assert_eq!(r.status, StatusCode::NOT_FOUND);

    api.put_json(
        UPDATE,
        HOST,
        json!({"submission": 2, "submission_status": "failed"}),
    )
    .await;
    let resumed = fake.resume(2).expect("failed can be resumed");
    assert_eq!(resumed.status, "resuming");
    assert!(resumed.rerun_resumed_at.is_some());
    assert!(
        resumed.completed_at.is_some(),
        "resume keeps the old timestamps"
    );
    assert_eq!(
        fake.resume(2),
        Err(AdminError::NotResumable {
            id: 2,
            status: "resuming".to_owned()
        })
    );
    assert_eq!(fake.cancel(9), Err(AdminError::UnknownSubmission(9)));
}

#[tokio::test]
async fn admin_can_add_a_submission_that_the_api_then_serves() {
    let (fake, api) = server().await;
    let r = api
        .send(
            Method::POST,
            "/_admin/submissions",
            None,
            Body::Json(json!({"challenge_phase": 2, "participant_team": 2, "submitted_image_uri": "repo/img:1"})),
        )
        .await;
    assert_eq!(r.status, StatusCode::CREATED, "{}", r.text);
    let v = r.json();
    assert_eq!(v["id"], 3);
    assert_eq!(v["status"], "submitted");
    assert_eq!(v["created_by"], 4);
    let r = api.get("/api/jobs/submission/3", Some(OTHER)).await;
    assert_eq!(r.status, StatusCode::OK);
    let r = api
        .send(
            Method::POST,
            "/_admin/submissions",
            None,
            Body::Json(
                json!({"challenge_phase": 7, "participant_team": 2, "submitted_image_uri": "x"}),
            ),
        )
        .await;
    assert_eq!(r.status, StatusCode::BAD_REQUEST);
    let added = fake
        .add_submission(NewSubmission {
            challenge_phase: 1,
            participant_team: 1,
            submitted_image_uri: "repo/img:2".to_owned(),
            created_by: Some(2),
            submission_metadata: None,
        })
        .unwrap();
    assert_eq!(added.id, 4);
    let url = api.get("/api/jobs/submission/4", Some(HOST)).await.json()["input_file"]
        .as_str()
        .unwrap()
        .to_owned();
    let input = api.get(url.strip_prefix(&fake.url()).unwrap(), None).await;
    assert_eq!(input.json(), json!({"submitted_image_uri": "repo/img:2"}));
}

#[tokio::test]
async fn injected_500s_are_html_and_only_hit_api_routes() {
    let (_fake, api) = server().await;
    let r = api
        .send(
            Method::PUT,
            "/_admin/faults",
            None,
            Body::Json(json!({"error_500_rate": 1.0, "seed": 1})),
        )
        .await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.text);
    let r = api.get("/api/jobs/submission/1", Some(HOST)).await;
    assert_eq!(r.status, StatusCode::INTERNAL_SERVER_ERROR);
    assert!(r.is_html());
    assert_eq!(api.get("/_admin/state", None).await.status, StatusCode::OK);
    let log = api.get("/_admin/requests", None).await.json();
    assert_eq!(log[1]["fault"], "error_500");
    let r = api
        .send(
            Method::PUT,
            "/_admin/faults",
            None,
            Body::Json(json!({"error_500_rate": 2.0})),
        )
        .await;
    assert_eq!(r.status, StatusCode::BAD_REQUEST);
    let r = api
        .send(
            Method::PUT,
            "/_admin/faults",
            None,
            Body::Json(json!({"error_rate": 0.5})),
        )
        .await;
    assert_eq!(
        r.status,
        StatusCode::BAD_REQUEST,
        "unknown fields are refused"
    );
}

#[tokio::test]
async fn injected_429s_carry_retry_after_and_500_after_write_applies_the_write() {
    let (fake, api) = server().await;
    fake.set_faults(Faults {
        throttle_429_rate: 1.0,
        retry_after_secs: 3,
        ..Faults::default()
    })
    .unwrap();
    let r = api.get("/api/jobs/submission/1", Some(HOST)).await;
    assert_eq!(r.status, StatusCode::TOO_MANY_REQUESTS);
    assert_eq!(r.header("retry-after"), Some("3"));
    assert_eq!(
        r.json(),
        json!({"detail": "Request was throttled. Expected available in 3 seconds."})
    );
    fake.set_faults(Faults {
        error_500_after_write_rate: 1.0,
        ..Faults::default()
    })
    .unwrap();
    let r = api
        .put_json(
            UPDATE,
            HOST,
            json!({"submission": 1, "submission_status": "failed"}),
        )
        .await;
    assert_eq!(r.status, StatusCode::INTERNAL_SERVER_ERROR);
    assert_eq!(fake.submission(1).unwrap().status, "failed");
    assert!(fake
        .set_faults(Faults {
            slow_rate: -0.1,
            ..Faults::default()
        })
        .is_err());
}

async fn statuses_with_seed(seed: u64) -> Vec<u16> {
    let (fake, api) = server().await;
    fake.set_faults(Faults {
        error_500_rate: 0.3,
        throttle_429_rate: 0.3,
        slow_rate: 0.2,
        slow_ms: 5,
        seed,
        ..Faults::default()
    })
    .unwrap();
    let mut out = Vec::new();
    for _ in 0..30 {
        out.push(
            api.get("/api/jobs/submission/1", Some(HOST))
                .await
                .status
                .as_u16(),
        );
    }
    out
}

#[tokio::test]
async fn faults_are_deterministic_for_a_seed() {
    let a = statuses_with_seed(7).await;
    let b = statuses_with_seed(7).await;
    assert_eq!(a, b);
    assert!(
        a.contains(&500) && a.contains(&429) && a.contains(&200),
        "{a:?}"
    );
}

#[tokio::test]
async fn slow_requests_are_delayed() {
    let (fake, api) = server().await;
    fake.set_faults(Faults {
        slow_rate: 1.0,
        slow_ms: 300,
        ..Faults::default()
    })
    .unwrap();
    let start = std::time::Instant::now();
    let r = api.get("/api/jobs/submission/1", Some(HOST)).await;
    assert_eq!(r.status, StatusCode::OK);
    assert!(start.elapsed() >= Duration::from_millis(300));
}

#[test]
fn spawn_serves_from_its_own_thread_and_drop_stops_it() {
    let fake = FakeEvalAi::spawn(Fixture::default()).expect("spawn");
    assert_eq!(fake.host_token(), Some("host-token"));
    let url = fake.url();
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(async {
        let api = Api::new(url.clone());
        let r = api.get("/api/jobs/submission/1", Some(HOST)).await;
        assert_eq!(r.status, StatusCode::OK);
    });
    let started = std::time::Instant::now();
    drop(fake);
    assert!(started.elapsed() < Duration::from_secs(5));
    let refused = std::net::TcpStream::connect_timeout(
        &url.trim_start_matches("http://").parse().unwrap(),
        Duration::from_secs(1),
    );
    assert!(refused.is_err(), "the port is closed after drop");
}

#[tokio::test]
async fn spawn_also_works_from_inside_a_runtime() {
    let fake = FakeEvalAi::spawn(Fixture::default()).expect("spawn");
    let api = Api::new(fake.url());
    assert_eq!(
        api.get("/api/jobs/submission/1", Some(HOST)).await.status,
        StatusCode::OK
    );
    fake.shutdown().await;
}

#[test]
fn fixture_errors_name_what_is_wrong() {
    let err = Fixture::from_json(r#"{"users": [{"id": 1, "emial_verified": true}]}"#).unwrap_err();
    assert_eq!(err.name(), "FixtureParse");
    let text = err.to_string();
    assert!(
        text.contains("users[0]") && text.contains("emial_verified"),
        "{text}"
    );

    let mut f = Fixture::default();
    f.tokens[0].user = 99;
    let err = f.validate().unwrap_err();
    assert_eq!(err.name(), "FixtureInvalid");
    assert!(err.to_string().contains("unknown user `99`"), "{err}");

    let mut f = Fixture::default();
    f.submissions[0].status = "Running".to_owned();
    assert!(f
        .validate()
        .unwrap_err()
        .to_string()
        .contains("status `Running`"));

    let mut f = Fixture::default();
    f.challenges[0].phases[0].splits[0]
        .labels
        .push("Driving score".to_owned());
    assert!(f.validate().unwrap_err().to_string().contains("twice"));

    let f = Fixture {
        throttle_per_minute: 0,
        ..Fixture::default()
    };
    assert!(f.validate().is_err());

    let err = Fixture::from_path(std::path::Path::new("/nonexistent/fixture.json")).unwrap_err();
    assert!(matches!(err, FixtureError::Read { .. }));
    assert_eq!(err.name(), "FixtureRead");

    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("f.json");
    std::fs::write(&path, fake_evalai::fixture::DEFAULT_FIXTURE_JSON).unwrap();
    assert_eq!(Fixture::from_path(&path).unwrap(), Fixture::default());
}

#[tokio::test]
async fn start_refuses_an_invalid_fixture() {
    let mut f = Fixture::default();
    f.host_teams.clear();
    let err = FakeEvalAi::start(f).await.unwrap_err();
    assert_eq!(err.name(), "FixtureInvalid");
}
