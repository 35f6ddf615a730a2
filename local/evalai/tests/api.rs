//! The EvalAI wire contract, rule by rule, over HTTP.

use crate::common;

use common::*;
use fake_evalai::{FakeEvalAi, Fixture};
use reqwest::{Method, StatusCode};
use serde_json::{json, Value};

async fn server() -> (FakeEvalAi, Api) {
    let fake = FakeEvalAi::start(Fixture::default()).await.expect("start");
    let api = Api::new(fake.url());
    (fake, api)
}

fn final_put(result: &str) -> Value {
    json!({
        "challenge_phase": 1,
        "submission": 1,
        "submission_status": "FINISHED",
        "result": result,
        "stdout": "out",
        "stderr": "",
        "metadata": {"k": "v", "n": 1},
    })
}

fn error_of(r: &Resp) -> String {
    r.json()["error"].as_str().unwrap_or_default().to_owned()
}

#[tokio::test]
async fn a_missing_trailing_slash_answers_301_to_the_slashed_url_before_any_auth() {
    let (_fake, api) = server().await;
    let r = api
        .send(
            Method::PUT,
            "/api/jobs/challenge/1/update_submission?x=1",
            None,
            Body::Json(json!({})),
        )
        .await;
    assert_eq!(r.status, StatusCode::MOVED_PERMANENTLY);
    assert_eq!(
        r.header("location"),
        Some("/api/jobs/challenge/1/update_submission/?x=1")
    );
    assert!(r.text.is_empty());
    let r = api
        .send(
            Method::PATCH,
            "/api/jobs/challenges/1/update_partially_evaluated_submission",
            Some("Bearer nonsense"),
            Body::None,
        )
        .await;
    assert_eq!(r.status, StatusCode::MOVED_PERMANENTLY);
}

#[tokio::test]
async fn get_submission_with_a_trailing_slash_or_an_unknown_url_is_an_html_404() {
    let (_fake, api) = server().await;
    for path in [
        "/api/jobs/submission/1/",
        "/api/jobs/nothing/",
        "/api/jobs/submission/x",
    ] {
        let r = api.get(path, Some(HOST)).await;
        assert_eq!(r.status, StatusCode::NOT_FOUND, "{path}");
        assert!(r.is_html(), "{path}: {}", r.content_type());
    }
}

#[tokio::test]
async fn missing_or_unknown_credentials_get_401_with_the_bearer_challenge() {
    let (_fake, api) = server().await;
    for auth in [None, Some("Basic abc"), Some("bearer host-token"), Some("")] {
        let r = api.get("/api/jobs/submission/1", auth).await;
        assert_eq!(r.status, StatusCode::UNAUTHORIZED, "{auth:?}");
        assert_eq!(r.header("www-authenticate"), Some("Bearer realm=\"api\""));
        assert_eq!(
            r.json(),
            json!({"detail": "Authentication credentials were not provided."})
        );
    }
}

#[tokio::test]
async fn bad_tokens_get_the_authentication_class_bodies() {
    let (_fake, api) = server().await;
    let not_valid = |message: &str| {
        json!({
            "detail": "Given token not valid for any token type",
            "code": "token_not_valid",
            "messages": [{"token_class": "RefreshToken", "token_type": "refresh", "message": message}],
        })
    };
    let cases = [
        ("Bearer unknown", not_valid("Token is invalid or expired")),
        (
            "Bearer host-legacy-token",
            not_valid("Token is invalid or expired"),
        ),
        (
            "Bearer expired-token",
            not_valid("Token is invalid or expired"),
        ),
        (
            "Bearer blacklisted-token",
            not_valid("Token is blacklisted"),
        ),
        (
            "Bearer",
            json!({"detail": "Authorization header must contain two space-delimited values"}),
        ),
        (
            "Bearer a b",
            json!({"detail": "Authorization header must contain two space-delimited values"}),
        ),
        (
            "Bearer inactive-token",
            json!({"detail": "User is inactive"}),
        ),
        ("Token host-token", json!({"detail": "Invalid token"})),
        (
            "Token expired-legacy-token",
            json!({"detail": "Token has expired"}),
        ),
        (
            "Token",
            json!({"detail": "Invalid token header. No credentials provided."}),
        ),
        (
            "Token a b",
            json!({"detail": "Invalid token header. Token string should not contain spaces."}),
        ),
    ];
    for (auth, body) in cases {
        let r = api.get("/api/jobs/submission/1", Some(auth)).await;
        assert_eq!(r.status, StatusCode::UNAUTHORIZED, "{auth}");
        assert_eq!(r.json(), body, "{auth}");
        assert_eq!(r.header("www-authenticate"), Some("Bearer realm=\"api\""));
    }
    let r = api
        .get("/api/jobs/submission/1", Some("tOkEn host-legacy-token"))
        .await;
    assert_eq!(
        r.status,
        StatusCode::OK,
        "the Token scheme is case-insensitive"
    );
}

#[tokio::test]
async fn an_unverified_email_gets_403() {
    let (_fake, api) = server().await;
    let r = api
        .get("/api/jobs/submission/1", Some("Bearer unverified-token"))
        .await;
    assert_eq!(r.status, StatusCode::FORBIDDEN);
    assert_eq!(r.json(), json!({"detail": "Please verify your email!"}));
}

#[tokio::test]
async fn a_non_host_gets_400_before_the_body_is_even_parsed() {
    let (_fake, api) = server().await;
    for path in [UPDATE, PARTIAL] {
        for method in [Method::PUT, Method::PATCH] {
            let r = api
                .send(
                    method.clone(),
                    path,
                    Some(PARTICIPANT),
                    Body::Raw("application/json", b"{not json".to_vec()),
                )
                .await;
            assert_eq!(r.status, StatusCode::BAD_REQUEST, "{method} {path}");
            assert_eq!(
                r.json(),
                json!({"error": "Sorry, you are not authorized to make this request!"})
            );
        }
    }
    let r = api
        .put_json(
            "/api/jobs/challenge/9/update_submission/",
            HOST,
            final_put("[]"),
        )
        .await;
    assert_eq!(
        r.status,
        StatusCode::BAD_REQUEST,
        "host of another challenge"
    );
}

#[tokio::test]
async fn get_submission_lets_the_creator_and_hosts_in_and_answers_401_to_others() {
    let (fake, api) = server().await;
    let r = api.get("/api/jobs/submission/2", Some(PARTICIPANT)).await;
    assert_eq!(r.status, StatusCode::UNAUTHORIZED);
    assert_eq!(
        r.json(),
        json!({"error": "Sorry, you are not authorized to access this submission."})
    );
    let r = api.get("/api/jobs/submission/999", Some(HOST)).await;
    assert_eq!(r.status, StatusCode::NOT_FOUND);
    assert_eq!(r.json(), json!({"error": "Submission 999 does not exist"}));

    let own = api.get("/api/jobs/submission/1", Some(PARTICIPANT)).await;
    assert_eq!(own.status, StatusCode::OK);
    assert!(own.json().get("environment_log_file").is_none());

    let host = api.get("/api/jobs/submission/1", Some(HOST)).await;
    assert_eq!(host.status, StatusCode::OK);
    assert_eq!(host.content_type(), "application/json");
    let keys: Vec<String> = {
        // Field order is part of the contract: read it from the raw text.
        let v: serde_json::Map<String, Value> = serde_json::from_str(&host.text).unwrap();
        let mut positions: Vec<(usize, String)> = v
            .keys()
            .map(|k| (host.text.find(&format!("\"{k}\":")).unwrap(), k.clone()))
            .collect();
        positions.sort();
        positions.into_iter().map(|(_, k)| k).collect()
    };
    assert_eq!(
        keys,
        [
            "id",
            "participant_team",
            "participant_team_name",
            "execution_time",
            "challenge_phase",
            "created_by",
            "status",
            "input_file",
            "submission_input_file",
            "stdout_file",
            "stderr_file",
            "environment_log_file",
            "started_at",
            "completed_at",
            "submitted_at",
            "rerun_resumed_at",
            "when_made_public",
            "method_name",
            "method_description",
            "project_url",
            "publication_url",
            "is_public",
            "is_flagged",
            "ignore_submission",
            "is_baseline",
            "is_verified_by_host",
            "submission_result_file",
            "job_name",
            "submission_metadata",
        ]
    );
    let v = host.json();
    assert_eq!(v["id"], 1);
    assert_eq!(v["participant_team_name"], "Team One");
    assert_eq!(v["execution_time"], "None");
    assert_eq!(v["status"], "submitted");
    assert_eq!(v["submitted_at"], "2026-01-01T00:00:00Z");
    assert_eq!(v["job_name"], json!([]));
    assert!(v["started_at"].is_null());
    let input = v["input_file"].as_str().unwrap();
    // EvalAI's media layout: the challenge, phase and submission, then a uuid file name.
    let prefix = format!(
        "{}/media/submission_files/challenge_1/phase_1/submission_1/",
        fake.url()
    );
    assert!(
        input.starts_with(&prefix) && input.ends_with(".json"),
        "{input}"
    );
    let file = api
        .get(input.strip_prefix(&fake.url()).unwrap(), None)
        .await;
    assert_eq!(
        file.json(),
        json!({"submitted_image_uri": "342236305043.dkr.ecr.us-west-2.amazonaws.com/team-one:agent-v1"})
    );
}

#[tokio::test]
async fn method_not_allowed_comes_only_after_auth() {
    let (_fake, api) = server().await;
    let r = api.get(UPDATE, None).await;
    assert_eq!(r.status, StatusCode::UNAUTHORIZED);
    let r = api.get(UPDATE, Some(HOST)).await;
    assert_eq!(r.status, StatusCode::METHOD_NOT_ALLOWED);
    assert_eq!(r.json(), json!({"detail": "Method \"GET\" not allowed."}));
    let r = api
        .send(
            Method::POST,
            "/api/jobs/submission/1",
            Some(HOST),
            Body::None,
        )
        .await;
    assert_eq!(r.json(), json!({"detail": "Method \"POST\" not allowed."}));
}

#[tokio::test]
async fn bodies_are_parsed_like_drf() {
    let (_fake, api) = server().await;
    let r = api
        .send(
            Method::PUT,
            UPDATE,
            Some(HOST),
            Body::Raw("text/plain", b"submission=1".to_vec()),
        )
        .await;
    assert_eq!(r.status, StatusCode::UNSUPPORTED_MEDIA_TYPE);
    assert_eq!(
        r.json(),
        json!({"detail": "Unsupported media type \"text/plain\" in request."})
    );
    let r = api
        .send(
            Method::PUT,
            UPDATE,
            Some(HOST),
            Body::Raw("application/json", b"{\"submission\": 1,}".to_vec()),
        )
        .await;
    assert_eq!(r.status, StatusCode::BAD_REQUEST);
    assert_eq!(
        r.json(),
        json!({"detail": "JSON parse error - Expecting property name enclosed in double quotes: line 1 column 18 (char 17)"})
    );
    let r = api
        .send(
            Method::PUT,
            UPDATE,
            Some(HOST),
            Body::Raw("application/json", b"{\"submission\": NaN}".to_vec()),
        )
        .await;
    assert_eq!(r.status, StatusCode::BAD_REQUEST);
    assert_eq!(
        r.json(),
        json!({"detail": "JSON parse error - Out of range float values are not JSON compliant: 'NaN'"})
    );
}

#[tokio::test]
async fn unknown_or_missing_submission_on_updates_is_404_with_detail() {
    let (_fake, api) = server().await;
    let r = api
        .put_json(
            UPDATE,
            HOST,
            json!({"submission": 999, "submission_status": "failed"}),
        )
        .await;
    assert_eq!(r.status, StatusCode::NOT_FOUND);
    assert_eq!(r.json(), json!({"detail": "Submission 999 does not exist"}));
    let r = api
        .patch_json(UPDATE, HOST, json!({"submission_status": "running"}))
        .await;
    assert_eq!(
        r.json(),
        json!({"detail": "Submission None does not exist"})
    );
}

#[tokio::test]
async fn statuses_are_lowercased_and_checked_per_endpoint() {
    let (_fake, api) = server().await;
    let invalid = json!({"error": "Sorry, submission status is invalid"});
    let r = api
        .put_json(
            UPDATE,
            HOST,
            json!({"submission": 1, "submission_status": "RUNNING"}),
        )
        .await;
    assert_eq!(
        (r.status, r.json()),
        (StatusCode::BAD_REQUEST, invalid.clone())
    );
    let r = api
        .patch_json(
            UPDATE,
            HOST,
            json!({"submission": 1, "submission_status": "finished"}),
        )
        .await;
    assert_eq!(
        (r.status, r.json()),
        (StatusCode::BAD_REQUEST, invalid.clone())
    );
    let r = api
        .patch_json(
            PARTIAL,
            HOST,
            json!({"submission": 1, "submission_status": "queued"}),
        )
        .await;
    assert_eq!(
        (r.status, r.json()),
        (StatusCode::BAD_REQUEST, invalid.clone()),
        "queued is refused by the partial PATCH"
    );
    let r = api
        .put_json(
            PARTIAL,
            HOST,
            json!({"submission": 1, "submission_status": "running"}),
        )
        .await;
    assert_eq!((r.status, r.json()), (StatusCode::BAD_REQUEST, invalid));
}

#[tokio::test]
async fn queued_and_running_patches_append_lowercased_job_names_and_set_started_at() {
    let (fake, api) = server().await;
    let r = api
        .patch_json(
            UPDATE,
            HOST,
            json!({"submission": 1, "submission_status": "QUEUED", "job_name": "Sub-1-Job"}),
        )
        .await;
    assert_eq!(r.status, StatusCode::OK);
    let v = r.json();
    assert_eq!(v["status"], "queued");
    assert!(v["started_at"].as_str().unwrap().ends_with('Z'));
    assert!(
        v.get("environment_log_file").is_some(),
        "the caller is a host"
    );
    let r = api
        .send(
            Method::PATCH,
            UPDATE,
            Some(HOST),
            Body::Form("submission=1&submission_status=Running&job_name=sub-1-job"),
        )
        .await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.text);
    assert_eq!(r.json()["job_name"], json!(["sub-1-job", "sub-1-job"]));
    assert_eq!(fake.submission(1).unwrap().status, "running");
}

#[tokio::test]
async fn a_final_put_with_the_15_labels_is_stored_and_visible() {
    let (fake, api) = server().await;
    let r = api.put_json(UPDATE, HOST, final_put(LB2_RESULTS)).await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.text);
    assert_eq!(
        r.json(),
        json!({"success": "Submission result has been successfully updated"})
    );
    let v = api.get("/api/jobs/submission/1", Some(HOST)).await.json();
    assert_eq!(v["status"], "finished");
    assert!(v["completed_at"].as_str().unwrap().ends_with('Z'));
    assert_eq!(v["execution_time"], "None", "started_at was never set");
    let stdout_url = v["stdout_file"].as_str().unwrap();
    let stdout = api
        .get(stdout_url.strip_prefix(&fake.url()).unwrap(), None)
        .await;
    assert_eq!(stdout.text, "out");

    let state = fake.state();
    let sub = state.submission(1).unwrap();
    assert_eq!(sub.status, "finished");
    assert_eq!(sub.leaderboard.len(), 1);
    assert_eq!(sub.leaderboard[0].split, "leaderboard");
    assert_eq!(sub.leaderboard[0].result["Driving score"], json!(23.699655));
    assert_eq!(sub.leaderboard[0].result.as_object().unwrap().len(), 15);
    assert_eq!(sub.files.metadata.as_deref(), Some("{'k': 'v', 'n': 1}"));
    assert!(sub
        .files
        .result
        .as_deref()
        .unwrap()
        .starts_with("[{'Driving score': 23.699655, 'Route completion': 62.1875,"));

    let admin = api.get("/_admin/state", None).await.json();
    let row = &admin["submissions"][0]["leaderboard"][0];
    assert_eq!(row["result"]["Min speed infractions"], json!(0.328));

    // The same PUT again replaces the row instead of adding one.
    let r = api.put_json(UPDATE, HOST, final_put(LB2_RESULTS)).await;
    assert_eq!(r.status, StatusCode::OK);
    assert_eq!(fake.submission(1).unwrap().leaderboard.len(), 1);
}

#[tokio::test]
async fn result_validation_rejects_what_evalai_rejects_with_its_texts() {
    let (fake, api) = server().await;
    let cases = [
        (
            r#"[{"split": "leaderboard", "accuracies": {"Driving score": "85.2"}}]"#,
            "Values for following metrics are not offloat/int: [('Driving score', <class 'str'>)]",
        ),
        (
            r#"[{"split": "leaderboard", "accuracies": {"Driving score": null, "Agent blocked": [1]}}]"#,
            "Values for following metrics are not offloat/int: [('Driving score', <class 'NoneType'>), ('Agent blocked', <class 'list'>)]",
        ),
        (
            r#"[{"split": "leaderboard", "accuracies": {"Driving Score": 1, "Route completion": 2, "bogus": 3}}]"#,
            "Following metrics are missing in theleaderboard data: ['Driving Score', 'bogus']",
        ),
        (
            r#"[{"split": "test", "accuracies": {"Driving score": 1}}]"#,
            "Challenge Phase Split does not exist with phase_id: 1 andsplit codename: test",
        ),
        (
            "not json",
            "`result` key contains invalid data with error Expecting value: line 1 column 1 (char 0).Please try again with correct format.",
        ),
    ];
    for (result, text) in cases {
        let r = api.put_json(UPDATE, HOST, final_put(result)).await;
        assert_eq!(r.status, StatusCode::BAD_REQUEST, "{result}");
        assert_eq!(r.json(), json!({"error": text}), "{result}");
    }
    let mut body = final_put("");
    body["result"] = serde_json::from_str(LB2_RESULTS).unwrap();
    let r = api.put_json(UPDATE, HOST, body).await;
    assert_eq!(r.status, StatusCode::BAD_REQUEST);
    assert_eq!(
        error_of(&r),
        "`result` key contains invalid data with error the JSON object must be str, bytes or bytearray, not list.Please try again with correct format."
    );
    let mut body = final_put(LB2_RESULTS);
    body.as_object_mut().unwrap().remove("challenge_phase");
    let r = api.put_json(UPDATE, HOST, body).await;
    assert_eq!(
        error_of(&r),
        "Challenge Phase Split does not exist with phase_id: None andsplit codename: leaderboard"
    );
    // Booleans are ints to Python: accepted. Labels left out are not reported.
    let r = api
        .put_json(
            UPDATE,
            HOST,
            final_put(r#"[{"split": "leaderboard", "accuracies": {"Driving score": true}}]"#),
        )
        .await;
    assert_eq!(r.status, StatusCode::OK);
    let sub = fake.submission(1).unwrap();
    assert_eq!(sub.status, "finished");
    assert_eq!(
        sub.files.result.as_deref(),
        Some("[]"),
        "show_to_participant defaults to false"
    );
}

#[tokio::test]
async fn unvalidated_inputs_give_html_500_like_evalai() {
    let (fake, api) = server().await;
    let mut cases: Vec<Value> = Vec::new();
    let mut b = final_put(LB2_RESULTS);
    b["submission"] = json!("abc");
    cases.push(b);
    let mut b = final_put(LB2_RESULTS);
    b["stdout"] = Value::Null;
    cases.push(b);
    let mut b = final_put(LB2_RESULTS);
    b["submission_status"] = json!(3);
    cases.push(b);
    cases.push(final_put(r#"[{"split": "leaderboard"}]"#));
    cases.push(final_put(r#"["leaderboard"]"#));
    cases.push(final_put(r#"{"split": "leaderboard"}"#));
    cases.push(final_put("3"));
    for body in cases {
        let r = api.put_json(UPDATE, HOST, body.clone()).await;
        assert_eq!(r.status, StatusCode::INTERNAL_SERVER_ERROR, "{body}");
        assert!(r.is_html(), "{body}");
    }
    // NaN inside the result is refused by the leaderboard row's JSON field: 400, not 500.
    let r = api
        .put_json(
            UPDATE,
            HOST,
            final_put(r#"[{"split": "leaderboard", "accuracies": {"Driving score": NaN}}]"#),
        )
        .await;
    assert_eq!(r.status, StatusCode::BAD_REQUEST);
    assert_eq!(r.json(), json!({"result": ["Value must be valid JSON."]}));
    assert_eq!(
        fake.submission(1).unwrap().status,
        "submitted",
        "none of these stored anything"
    );
    assert!(fake.submission(1).unwrap().leaderboard.is_empty());
    let r = api
        .patch_json(
            UPDATE,
            HOST,
            json!({"submission": 1, "submission_status": "running", "job_name": 5}),
        )
        .await;
    assert_eq!(r.status, StatusCode::INTERNAL_SERVER_ERROR);
    let r = api
        .send(Method::PUT, UPDATE, Some(HOST), Body::Json(json!([1, 2])))
        .await;
    assert_eq!(
        r.status,
        StatusCode::INTERNAL_SERVER_ERROR,
        "a JSON list body"
    );
    let log = fake.requests();
    assert!(log
        .iter()
        .any(|r| r.error.as_deref()
            == Some("ValueError: invalid literal for int() with base 10: 'abc'")));
}

#[tokio::test]
async fn a_repeated_split_creates_two_rows_and_then_every_update_is_a_500() {
    let (fake, api) = server().await;
    let one: Value = serde_json::from_str(LB2_RESULTS).unwrap();
    let twice = Value::Array(vec![one[0].clone(), one[0].clone()]).to_string();
    let r = api.put_json(UPDATE, HOST, final_put(&twice)).await;
    assert_eq!(r.status, StatusCode::OK);
    assert_eq!(fake.submission(1).unwrap().leaderboard.len(), 2);
    let r = api.put_json(UPDATE, HOST, final_put(LB2_RESULTS)).await;
    assert_eq!(r.status, StatusCode::INTERNAL_SERVER_ERROR);
    assert!(r.is_html());
}

#[tokio::test]
async fn form_encoded_bodies_work_and_the_last_repeated_key_wins() {
    let (fake, api) = server().await;
    let r = api
        .send(
            Method::PUT,
            UPDATE,
            Some(HOST),
            Body::Form("submission=2&submission=1&submission_status=failed&stderr=boom+%21&metadata=%7B%7D"),
        )
        .await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.text);
    let sub = fake.submission(1).unwrap();
    assert_eq!(sub.status, "failed");
    assert_eq!(sub.files.stderr.as_deref(), Some("boom !"));
    assert_eq!(
        sub.files.metadata.as_deref(),
        Some("{}"),
        "a form value is a string"
    );
    assert_eq!(fake.submission(2).unwrap().status, "submitted");
}

#[tokio::test]
async fn partial_patch_needs_existing_rows_and_merges_into_them() {
    let (fake, api) = server().await;
    let patch = |result: &str| {
        json!({
            "submission": 1,
            "submission_status": "partially_evaluated",
            "challenge_phase": 1,
            "result": result,
            "stdout": "partial",
        })
    };
    let r = api
        .patch_json(
            PARTIAL,
            HOST,
            patch(r#"[{"split": "leaderboard", "accuracies": {"Driving score": 1}}]"#),
        )
        .await;
    assert_eq!(r.status, StatusCode::BAD_REQUEST);
    assert_eq!(
        r.json(),
        json!({"error": "Leaderboard Data does not exist with phase_id: 1 andsubmission id: 1"})
    );
    let r = api
        .put_json(
            PARTIAL,
            HOST,
            json!({
                "submission": "1",
                "submission_status": "PARTIALLY_EVALUATED",
                "challenge_phase": "1",
                "result": r#"[{"split": "leaderboard", "accuracies": {"Driving score": 1, "Route completion": 2}}]"#,
            }),
        )
        .await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.text);
    let r = api
        .patch_json(
            PARTIAL,
            HOST,
            patch(r#"[{"split": "leaderboard", "accuracies": {"Route completion": 5, "Agent blocked": 0.5}}]"#),
        )
        .await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.text);
    let sub = fake.submission(1).unwrap();
    assert_eq!(sub.status, "partially_evaluated");
    assert_eq!(
        sub.leaderboard[0].result,
        json!({"Driving score": 1, "Route completion": 5, "Agent blocked": 0.5})
    );
    let r = api
        .patch_json(
            PARTIAL,
            HOST,
            patch(r#"[{"split": "leaderboard", "accuracies": {"nope": 1}}]"#),
        )
        .await;
    assert_eq!(
        r.json(),
        json!({"error": "Following metrics are missing in theleaderboard data: ['nope'] of challenge phase: 1"})
    );
}

#[tokio::test]
async fn a_partial_evaluation_phase_allows_unknown_keys_only_on_the_partial_endpoint() {
    let mut fixture = Fixture::default();
    fixture.challenges[0].phases[0].partial_evaluation_enabled = true;
    let fake = FakeEvalAi::start(fixture).await.unwrap();
    let api = Api::new(fake.url());
    let result = r#"[{"split": "leaderboard", "accuracies": {"Driving score": 1, "extra": 2}}]"#;
    let r = api
        .put_json(
            PARTIAL,
            HOST,
            json!({"submission": 1, "submission_status": "partially_evaluated", "challenge_phase": 1, "result": result}),
        )
        .await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.text);
    let r = api
        .put_json(
            PARTIAL,
            HOST,
            json!({"submission": 1, "submission_status": "finished", "challenge_phase": 1,
                   "result": r#"[{"split": "leaderboard", "accuracies": {"extra": "x"}}]"#}),
        )
        .await;
    assert_eq!(
        error_of(&r),
        "Values for following metrics are not offloat/int: [('extra', <class 'str'>)]",
        "the type check always applies"
    );
    let r = api.put_json(UPDATE, HOST, final_put(result)).await;
    assert_eq!(
        error_of(&r),
        "Following metrics are missing in theleaderboard data: ['extra']"
    );
}

#[tokio::test]
async fn a_bad_stderr_on_the_partial_put_fails_after_status_and_rows_were_stored() {
    let (fake, api) = server().await;
    let r = api
        .put_json(
            PARTIAL,
            HOST,
            json!({"submission": 1, "submission_status": "partially_evaluated", "challenge_phase": 1,
                   "result": LB2_RESULTS, "stdout": "ok", "stderr": null}),
        )
        .await;
    assert_eq!(r.status, StatusCode::INTERNAL_SERVER_ERROR);
    let sub = fake.submission(1).unwrap();
    assert_eq!(sub.status, "partially_evaluated");
    assert_eq!(sub.leaderboard.len(), 1);
}

#[tokio::test]
async fn a_write_after_the_participant_cancelled_is_accepted() {
    let (fake, api) = server().await;
    let meta = "/api/jobs/challenges/1/submissions/1/update_submission_meta/";
    let r = api
        .patch_json(meta, PARTICIPANT, json!({"status": "Cancelled"}))
        .await;
    assert_eq!(r.status, StatusCode::BAD_REQUEST);
    assert_eq!(
        r.json(),
        json!({"status": ["\"Cancelled\" is not a valid choice."]})
    );
    let r = api
        .patch_json(
            meta,
            PARTICIPANT,
            json!({"status": "cancelled", "unknown": 1}),
        )
        .await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.text);
    assert_eq!(r.json()["status"], "cancelled");
    let r = api
        .patch_json(
            "/api/jobs/challenges/1/submissions/2/update_submission_meta/",
            PARTICIPANT,
            json!({"status": "cancelled"}),
        )
        .await;
    assert_eq!(r.status, StatusCode::NOT_FOUND);
    assert_eq!(r.json(), json!({"error": "Submission 2 does not exist"}));

    let r = api
        .patch_json(
            UPDATE,
            HOST,
            json!({"submission": 1, "submission_status": "running"}),
        )
        .await;
    assert_eq!(
        r.status,
        StatusCode::OK,
        "the server does not protect cancelled"
    );
    assert_eq!(fake.submission(1).unwrap().status, "running");
    let r = api.put_json(UPDATE, HOST, final_put(LB2_RESULTS)).await;
    assert_eq!(r.status, StatusCode::OK);
    assert_eq!(fake.submission(1).unwrap().status, "finished");
}

#[tokio::test]
async fn the_host_can_patch_meta_fields_with_drf_validation() {
    let (_fake, api) = server().await;
    let meta = "/api/jobs/challenges/1/submissions/1/update_submission_meta/";
    let r = api
        .patch_json(
            meta,
            HOST,
            json!({"is_public": "maybe", "started_at": "yesterday", "job_name": "x"}),
        )
        .await;
    assert_eq!(r.status, StatusCode::BAD_REQUEST);
    assert_eq!(
        r.json(),
        json!({
            "started_at": ["Datetime has wrong format. Use one of these formats instead: YYYY-MM-DDThh:mm[:ss[.uuuuuu]][+HH:MM|-HH:MM|Z]."],
            "is_public": ["Must be a valid boolean."],
            "job_name": ["Expected a list of items but got type \"str\"."],
        })
    );
    let r = api
        .patch_json(
            meta,
            HOST,
            json!({"started_at": "2026-01-01T00:00:00Z", "completed_at": "2026-01-01T00:01:30.5Z", "submission_metadata": {"a": [1]}}),
        )
        .await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.text);
    let v = r.json();
    assert_eq!(v["execution_time"], json!(90.5));
    assert_eq!(v["completed_at"], "2026-01-01T00:01:30.500000Z");
    assert_eq!(v["submission_metadata"], json!({"a": [1]}));
    let r = api
        .patch_json(
            "/api/jobs/challenges/1/submissions/77/update_submission_meta/",
            HOST,
            json!({}),
        )
        .await;
    assert_eq!(r.json(), json!({"detail": "Submission 77 does not exist"}));
}

#[tokio::test]
async fn the_list_endpoint_filters_by_status_and_checks_its_inputs() {
    let (_fake, api) = server().await;
    let r = api
        .get(
            "/api/jobs/challenge/1/submission/?status=submitted",
            Some(HOST),
        )
        .await;
    assert_eq!(r.status, StatusCode::OK);
    let ids: Vec<i64> = r
        .json()
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["id"].as_i64().unwrap())
        .collect();
    assert_eq!(ids, [1, 2]);
    let r = api
        .get(
            "/api/jobs/challenge/1/submission/?status=partially_evaluated",
            Some(HOST),
        )
        .await;
    assert_eq!(
        r.json(),
        json!({"error": "Invalid submission status partially_evaluated"})
    );
    let r = api
        .get(
            "/api/jobs/challenge/1/submission/?status=submitted",
            Some(PARTICIPANT),
        )
        .await;
    assert_eq!(r.status, StatusCode::BAD_REQUEST);
    let r = api
        .get(
            "/api/jobs/challenge/5/submission/?status=submitted",
            Some(HOST),
        )
        .await;
    assert_eq!(r.status, StatusCode::NOT_FOUND);
    assert_eq!(r.json(), json!({"detail": "Challenge 5 does not exist"}));
}

#[tokio::test]
async fn update_started_at_answers_403_for_an_unknown_submission() {
    let (_fake, api) = server().await;
    let r = api
        .send(
            Method::PATCH,
            "/api/jobs/submission/42/update_started_at/",
            Some(PARTICIPANT),
            Body::None,
        )
        .await;
    assert_eq!(r.status, StatusCode::FORBIDDEN);
    assert_eq!(r.json(), json!({"error": "Submission does not exist"}));
    let r = api
        .send(
            Method::PATCH,
            "/api/jobs/submission/1/update_started_at/",
            Some(OTHER),
            Body::None,
        )
        .await;
    assert_eq!(r.status, StatusCode::OK, "no host check on this endpoint");
}

#[tokio::test]
async fn throttling_counts_authenticated_requests_across_endpoints_and_sets_retry_after() {
    let fixture = Fixture {
        throttle_per_minute: 3,
        ..Fixture::default()
    };
    let fake = FakeEvalAi::start(fixture).await.unwrap();
    let api = Api::new(fake.url());
    // Failed authentication and permission checks are not counted.
    for _ in 0..5 {
        assert_eq!(
            api.get("/api/jobs/submission/1", Some("Bearer wrong"))
                .await
                .status,
            StatusCode::UNAUTHORIZED
        );
        assert_eq!(
            api.get("/api/jobs/submission/1", Some("Bearer unverified-token"))
                .await
                .status,
            StatusCode::FORBIDDEN
        );
    }
    // Counted whatever the view answers (404, 400), on any endpoint.
    assert_eq!(
        api.get("/api/jobs/submission/99", Some(HOST)).await.status,
        StatusCode::NOT_FOUND
    );
    assert_eq!(
        api.patch_json(
            UPDATE,
            HOST,
            json!({"submission": 1, "submission_status": "x"})
        )
        .await
        .status,
        StatusCode::BAD_REQUEST
    );
    assert_eq!(
        api.get("/api/jobs/submission/1", Some(HOST)).await.status,
        StatusCode::OK
    );
    let r = api.get("/api/jobs/submission/1", Some(HOST)).await;
    assert_eq!(r.status, StatusCode::TOO_MANY_REQUESTS);
    let wait: u64 = r.header("retry-after").unwrap().parse().unwrap();
    assert!((59..=60).contains(&wait), "{wait}");
    assert_eq!(
        r.json(),
        json!({"detail": format!("Request was throttled. Expected available in {wait} seconds.")})
    );
    // Another user has their own window; the throttled one stays throttled everywhere.
    assert_eq!(
        api.get("/api/jobs/submission/1", Some(PARTICIPANT))
            .await
            .status,
        StatusCode::OK
    );
    let r = api
        .put_json(UPDATE, "Token host-legacy-token", json!({}))
        .await;
    assert_eq!(
        r.status,
        StatusCode::TOO_MANY_REQUESTS,
        "per user, not per token"
    );
    // A missing slash is still redirected: the redirect happens before the throttle.
    let r = api
        .send(
            Method::PUT,
            "/api/jobs/challenge/1/update_submission",
            Some(HOST),
            Body::None,
        )
        .await;
    assert_eq!(r.status, StatusCode::MOVED_PERMANENTLY);
}

#[tokio::test]
async fn the_throttle_window_slides() {
    let fixture = Fixture {
        throttle_per_minute: 1,
        throttle_window_secs: 1,
        ..Fixture::default()
    };
    let fake = FakeEvalAi::start(fixture).await.unwrap();
    let api = Api::new(fake.url());
    assert_eq!(
        api.get("/api/jobs/submission/1", Some(HOST)).await.status,
        StatusCode::OK
    );
    let r = api.get("/api/jobs/submission/1", Some(HOST)).await;
    assert_eq!(r.status, StatusCode::TOO_MANY_REQUESTS);
    assert_eq!(r.header("retry-after"), Some("1"));
    assert_eq!(
        r.json(),
        json!({"detail": "Request was throttled. Expected available in 1 second."})
    );
    tokio::time::sleep(std::time::Duration::from_millis(1100)).await;
    assert_eq!(
        api.get("/api/jobs/submission/1", Some(HOST)).await.status,
        StatusCode::OK
    );
}
