//! The client against the fake EvalAI, which enforces the real server's rules.

use std::time::Duration;

use fake_evalai::{FakeEvalAi, Faults, Fixture};
use lb_domain::submission::SubmissionStatus;
use lb_evalai::{
    AuthScheme, EvalAiClient, FinalUpdate, HostToken, PartialUpdate, RetryPolicy, SubmissionRef,
    WriteOutcome,
};

const AT: SubmissionRef = SubmissionRef {
    challenge: 1,
    phase: 1,
    submission: 1,
};

fn policy() -> RetryPolicy {
    RetryPolicy {
        initial_backoff: Duration::from_millis(10),
        max_backoff: Duration::from_millis(50),
        budget: Duration::from_secs(10),
        ..RetryPolicy::default()
    }
}

fn client(server: &FakeEvalAi, token: &str) -> EvalAiClient {
    EvalAiClient::new(
        &server.url(),
        &HostToken::new(token),
        AuthScheme::Bearer,
        policy(),
    )
    .unwrap()
}

/// A `result` with every Leaderboard 2.0 label, as the results engine writes it.
fn full_result(driving_score: f64) -> String {
    let accuracies: serde_json::Map<String, serde_json::Value> = lb_domain::results::METRICS
        .iter()
        .map(|m| {
            (
                m.label.to_string(),
                serde_json::json!(if m.label == "Driving score" {
                    driving_score
                } else {
                    1.0
                }),
            )
        })
        .collect();
    serde_json::json!([{"split": "leaderboard", "show_to_participant": true, "accuracies": accuracies}]).to_string()
}

fn writes(server: &FakeEvalAi) -> Vec<(String, String)> {
    server
        .requests()
        .into_iter()
        .filter(|r| !r.admin && r.method != "GET")
        .map(|r| (r.method, r.path))
        .collect()
}

/// The fake behind a proxy refusing bodies over `limit` bytes (413), as the real server's
/// nginx does, and the host's client.
async fn behind_proxy(limit: usize) -> (FakeEvalAi, EvalAiClient) {
    let server = FakeEvalAi::start(Fixture {
        max_request_bytes: limit,
        ..Fixture::default()
    })
    .await
    .unwrap();
    let evalai = client(&server, "host-token");
    (server, evalai)
}

#[tokio::test]
async fn reads_the_submission_and_names_404_and_bad_tokens() {
    let server = FakeEvalAi::start(Fixture::default()).await.unwrap();
    let submission = client(&server, "host-token").submission(1).await.unwrap();
    assert_eq!(
        (submission.team_id, submission.team_name.as_str()),
        (1, "Team One")
    );
    assert_eq!(
        (submission.phase_id, submission.status),
        (1, SubmissionStatus::Submitted)
    );
    assert_eq!(
        client(&server, "host-token")
            .submission(999)
            .await
            .unwrap_err()
            .name(),
        "SubmissionNotFound"
    );
    assert_eq!(
        client(&server, "not-a-token")
            .submission(1)
            .await
            .unwrap_err()
            .name(),
        "EvalAiUnauthorized"
    );
    let image = client(&server, "host-token")
        .submitted_image(&submission)
        .await
        .unwrap();
    assert!(!image.is_empty());
}

#[tokio::test]
async fn a_whole_run_is_accepted_and_confirmed() {
    let server = FakeEvalAi::start(Fixture::default()).await.unwrap();
    let evalai = client(&server, "host-token");
    // Queued while the Jobs wait for capacity, then running when the first pair starts: the
    // second PATCH moves `started_at` to the real start (EvalAI sets it on every PATCH).
    assert_eq!(
        evalai.mark_queued(AT, "lb-1-team-0").await.unwrap(),
        WriteOutcome::Written
    );
    let queued = server.submission(1).unwrap();
    assert_eq!(queued.status, "queued");
    assert_eq!(queued.job_name, Some(vec!["lb-1-team-0".to_string()]));
    tokio::time::sleep(Duration::from_millis(20)).await;
    assert_eq!(
        evalai.mark_running(AT, "lb-1-team-0").await.unwrap(),
        WriteOutcome::Written
    );
    let running = server.submission(1).unwrap();
    assert_eq!(running.status, "running");
    assert!(running.started_at > queued.started_at, "{running:?}");
    let partial = PartialUpdate {
        result: full_result(10.0),
        stdout: "10 of 20 routes".into(),
        metadata: "{}".into(),
    };
    assert_eq!(
        evalai.post_partial(AT, &partial).await.unwrap(),
        WriteOutcome::Written
    );
    assert_eq!(server.submission(1).unwrap().status, "partially_evaluated");
    let final_update = FinalUpdate {
        status: SubmissionStatus::Finished,
        result: full_result(42.5),
        stdout: "done".into(),
        stderr: String::new(),
        metadata: "{}".into(),
    };
    assert_eq!(
        evalai.post_final(AT, &final_update).await.unwrap(),
        WriteOutcome::Written
    );
    let after = server.submission(1).unwrap();
    assert_eq!(after.status, "finished");
    assert_eq!(
        after.job_name,
        Some(vec!["lb-1-team-0".to_string()]),
        "EvalAI lowercases job names"
    );
    let row = &after.leaderboard[0];
    assert_eq!(row.result["Driving score"], serde_json::json!(42.5));
    assert_eq!(row.result.as_object().unwrap().len(), 15);
    // A late partial update never undoes the final one.
    assert_eq!(
        evalai.post_partial(AT, &partial).await.unwrap(),
        WriteOutcome::AlreadyFinal(SubmissionStatus::Finished)
    );
    assert_eq!(server.submission(1).unwrap().status, "finished");
}

#[tokio::test]
async fn a_participant_cancel_is_never_overwritten() {
    let server = FakeEvalAi::start(Fixture::default()).await.unwrap();
    let evalai = client(&server, "host-token");
    evalai.mark_running(AT, "job").await.unwrap();
    server.cancel(1).unwrap();
    let before = writes(&server).len();
    let partial = PartialUpdate {
        result: full_result(1.0),
        stdout: String::new(),
        metadata: "{}".into(),
    };
    assert_eq!(
        evalai.post_partial(AT, &partial).await.unwrap(),
        WriteOutcome::Cancelled
    );
    assert_eq!(
        evalai.mark_running(AT, "job").await.unwrap(),
        WriteOutcome::Cancelled
    );
    let finished = FinalUpdate {
        status: SubmissionStatus::Finished,
        result: full_result(1.0),
        stdout: String::new(),
        stderr: String::new(),
        metadata: "{}".into(),
    };
    assert_eq!(
        evalai.post_final(AT, &finished).await.unwrap(),
        WriteOutcome::Cancelled
    );
    assert_eq!(
        writes(&server).len(),
        before,
        "no write reached EvalAI after the cancel"
    );
    assert_eq!(server.submission(1).unwrap().status, "cancelled");
}

#[tokio::test]
async fn throttling_is_waited_out_through_retry_after() {
    let fixture = Fixture {
        throttle_per_minute: 2,
        throttle_window_secs: 1,
        ..Fixture::default()
    };
    let server = FakeEvalAi::start(fixture).await.unwrap();
    let evalai = client(&server, "host-token");
    for _ in 0..4 {
        evalai.submission(1).await.unwrap();
    }
    assert!(
        server.requests().iter().any(|r| r.status == 429),
        "the fake did throttle"
    );
}

#[tokio::test]
async fn a_500_after_the_write_is_resolved_by_reading_not_by_writing_twice() {
    let failed = FinalUpdate {
        status: SubmissionStatus::Failed,
        result: "[]".into(),
        stdout: String::new(),
        stderr: "CARLA crashed five times".into(),
        metadata: "{}".into(),
    };
    // Half the answers are 500s sent after the request was applied; the seeds decide which.
    let mut exercised = 0;
    for seed in 0..16 {
        let server = FakeEvalAi::start(Fixture::default()).await.unwrap();
        server
            .set_faults(Faults {
                error_500_after_write_rate: 0.5,
                seed,
                ..Faults::default()
            })
            .unwrap();
        let outcome = client(&server, "host-token").post_final(AT, &failed).await;
        let log = server.requests();
        let puts: Vec<_> = log.iter().filter(|r| r.method == "PUT").collect();
        if let Some(first) = puts.first() {
            // Once a PUT landed, the truth is read, never written again.
            if first.fault.as_deref() == Some("error_500_after") {
                assert_eq!(puts.len(), 1, "seed {seed}: {log:?}");
                if outcome.is_ok() {
                    exercised += 1;
                }
            }
        }
        match outcome {
            Ok(outcome) => assert_eq!(outcome, WriteOutcome::Written, "seed {seed}"),
            Err(e) => assert_eq!(e.name(), "EvalAiUnavailable", "seed {seed}"),
        }
        server.set_faults(Faults::default()).unwrap();
        if !puts.is_empty() {
            assert_eq!(
                server.submission(1).unwrap().status,
                "failed",
                "seed {seed}"
            );
        }
    }
    assert!(
        exercised > 0,
        "no seed produced a landed PUT answered with a 500"
    );
}

#[tokio::test]
async fn transient_500s_are_retried_until_the_write_lands() {
    let server = FakeEvalAi::start(Fixture::default()).await.unwrap();
    let evalai = client(&server, "host-token");
    server
        .set_faults(Faults {
            error_500_rate: 0.5,
            seed: 7,
            ..Faults::default()
        })
        .unwrap();
    assert_eq!(
        evalai.mark_running(AT, "job").await.unwrap(),
        WriteOutcome::Written
    );
    server.set_faults(Faults::default()).unwrap();
    assert_eq!(server.submission(1).unwrap().status, "running");
}

#[tokio::test]
async fn garbage_results_are_refused_before_any_request() {
    let server = FakeEvalAi::start(Fixture::default()).await.unwrap();
    let evalai = client(&server, "host-token");
    let bad = FinalUpdate {
        status: SubmissionStatus::Finished,
        result: r#"[{"split": "leaderboard", "accuracies": {"Driving score": "85.2"}}]"#.into(),
        stdout: String::new(),
        stderr: String::new(),
        metadata: "{}".into(),
    };
    assert_eq!(
        evalai.post_final(AT, &bad).await.unwrap_err().name(),
        "InvalidResult"
    );
    assert!(server.requests().is_empty());
}

#[tokio::test]
async fn a_20_mb_output_is_cut_so_the_proxy_takes_the_partial_and_the_final_update() {
    // Behind a proxy refusing bodies over 1 MiB (413), as the real server's nginx does.
    let (server, evalai) = behind_proxy(1024 * 1024).await;
    let huge = format!("Scores first\n{}", "x".repeat(20 * 1024 * 1024));
    let huge_metadata = format!("{{\"routes\": \"{}\"}}", "y".repeat(20 * 1024 * 1024));
    let partial = PartialUpdate {
        result: full_result(10.0),
        stdout: huge.clone(),
        metadata: huge_metadata.clone(),
    };
    assert_eq!(
        evalai.post_partial(AT, &partial).await.unwrap(),
        WriteOutcome::Written
    );
    let final_update = FinalUpdate {
        status: SubmissionStatus::Finished,
        result: full_result(42.5),
        stdout: huge,
        stderr: String::new(),
        metadata: huge_metadata,
    };
    assert_eq!(
        evalai.post_final(AT, &final_update).await.unwrap(),
        WriteOutcome::Written
    );
    let after = server.submission(1).unwrap();
    assert_eq!(after.status, "finished");
    assert_eq!(
        after.leaderboard[0].result["Driving score"],
        serde_json::json!(42.5)
    );
    let stdout = after.files.stdout.unwrap();
    assert!(stdout.starts_with("Scores first\n"));
    assert!(stdout.len() <= lb_evalai::MAX_TEXT_BYTES);
    assert!(
        stdout.contains("[... cut here: the first"),
        "a visible note"
    );
    // No request was refused: each body was bounded before it was sent.
    assert!(server.requests().iter().all(|r| r.status != 413));
}

#[tokio::test]
async fn a_final_update_the_proxy_still_refuses_is_replaced_by_the_minimal_one() {
    // A proxy stricter than our bounds: the full final update gets 413.
    let (server, evalai) = behind_proxy(64 * 1024).await;
    let final_update = FinalUpdate {
        status: SubmissionStatus::Failed,
        result: "[]".into(),
        stdout: "z".repeat(200 * 1024),
        stderr: format!(
            "Your agent crashed: ModuleNotFoundError\n{}",
            "trace\n".repeat(40_000)
        ),
        metadata: "{}".into(),
    };
    assert_eq!(
        evalai.post_final(AT, &final_update).await.unwrap(),
        WriteOutcome::Written
    );
    let after = server.submission(1).unwrap();
    assert_eq!(after.status, "failed", "EvalAI was told");
    assert_eq!(
        after.files.stdout.as_deref(),
        Some(lb_evalai::MINIMAL_STDOUT)
    );
    let stderr = after.files.stderr.unwrap();
    assert!(
        stderr.starts_with("Your agent crashed: ModuleNotFoundError"),
        "{stderr:.200}"
    );
    assert!(stderr.len() <= 4 * 1024);
    let statuses: Vec<u16> = server
        .requests()
        .iter()
        .filter(|r| r.method == "PUT")
        .map(|r| r.status)
        .collect();
    assert_eq!(statuses, [413, 200]);
}

#[tokio::test]
async fn a_final_status_is_never_replaced_nor_sent_twice() {
    let server = FakeEvalAi::start(Fixture::default()).await.unwrap();
    let evalai = client(&server, "host-token");
    let finished = FinalUpdate {
        status: SubmissionStatus::Finished,
        result: full_result(42.5),
        stdout: "done".into(),
        stderr: String::new(),
        metadata: "{}".into(),
    };
    assert_eq!(
        evalai.post_final(AT, &finished).await.unwrap(),
        WriteOutcome::Written
    );
    let puts = || writes(&server).len();
    let before = puts();
    // A late Finalize carrying an error: once it turned `finished` into `failed`.
    let failed = FinalUpdate {
        status: SubmissionStatus::Failed,
        result: "[]".into(),
        stdout: String::new(),
        stderr: "the evaluation failed".into(),
        metadata: "{}".into(),
    };
    assert_eq!(
        evalai.post_final(AT, &failed).await.unwrap(),
        WriteOutcome::AlreadyFinal(SubmissionStatus::Finished)
    );
    // A repeated Finalize: nothing re-sent.
    assert_eq!(
        evalai.post_final(AT, &finished).await.unwrap(),
        WriteOutcome::AlreadyFinal(SubmissionStatus::Finished)
    );
    assert_eq!(puts(), before, "no write after the first final update");
    let after = server.submission(1).unwrap();
    assert_eq!(after.status, "finished");
    assert_eq!(after.files.stdout.as_deref(), Some("done"));
}

#[tokio::test]
async fn retries_stop_at_the_invocations_deadline_not_at_the_clients_budget() {
    // A client whose own budget is generous (60 s) inside an invocation with 2 s left: an
    // EvalAI that keeps failing must end the call in time for the handler to report, not let
    // the Lambda time out (States.Timeout, which the state machine never retried).
    let server = FakeEvalAi::start(Fixture::default()).await.unwrap();
    let evalai = EvalAiClient::new(
        &server.url(),
        &HostToken::new("host-token"),
        AuthScheme::Bearer,
        RetryPolicy {
            max_attempts: 100,
            initial_backoff: Duration::from_millis(200),
            max_backoff: Duration::from_millis(400),
            budget: Duration::from_secs(60),
            ..RetryPolicy::default()
        },
    )
    .unwrap();
    server
        .set_faults(Faults {
            error_500_rate: 1.0,
            ..Faults::default()
        })
        .unwrap();
    let started = std::time::Instant::now();
    let deadline = started + Duration::from_secs(2);
    let err = lb_evalai::within(deadline, evalai.mark_running(AT, "job"))
        .await
        .unwrap_err();
    let took = started.elapsed();
    assert_eq!(err.name(), "EvalAiUnavailable", "{err}");
    assert!(err.is_transient());
    assert!(took < Duration::from_millis(2600), "took {took:?}");
}

#[tokio::test]
async fn one_request_lists_a_challenges_submissions_in_a_status() {
    let server = FakeEvalAi::start(Fixture::default()).await.unwrap();
    let host = client(&server, "host-token");
    let submitted = host
        .submissions_with_status(1, SubmissionStatus::Submitted)
        .await
        .unwrap();
    assert!(submitted.iter().any(|s| s.id == 1), "{submitted:?}");
    assert!(submitted
        .iter()
        .all(|s| s.status == SubmissionStatus::Submitted));
    assert!(host
        .submissions_with_status(1, SubmissionStatus::Cancelled)
        .await
        .unwrap()
        .is_empty());
    // A participant's cancel shows in the next listing.
    server.cancel(1).unwrap();
    let cancelled = host
        .submissions_with_status(1, SubmissionStatus::Cancelled)
        .await
        .unwrap();
    assert_eq!(cancelled.iter().map(|s| s.id).collect::<Vec<_>>(), [1]);
    let before = server.requests().len();
    host.submissions_with_status(1, SubmissionStatus::Running)
        .await
        .unwrap();
    assert_eq!(server.requests().len(), before + 1, "one request");
    // No such challenge: a configuration error, not a missing submission.
    let err = host
        .submissions_with_status(999, SubmissionStatus::Cancelled)
        .await
        .unwrap_err();
    assert_eq!(err.name(), "EvalAiConfig");
    assert!(err.to_string().contains("999"), "{err}");
    // Not the host: the view answers 400 (reference 7.3).
    let err = client(&server, "participant-token")
        .submissions_with_status(1, SubmissionStatus::Cancelled)
        .await
        .unwrap_err();
    assert_eq!(err.name(), "EvalAiRejected", "{err}");
}

/// A budget that grants everything and keeps each take: (places, headroom).
#[derive(Debug, Default)]
struct Counting(std::sync::Mutex<Vec<(u32, u32)>>);

impl lb_evalai::Budget for Counting {
    fn take(
        &self,
        _: lb_evalai::Priority,
        places: u32,
        headroom: u32,
    ) -> lb_evalai::AdmissionFuture<'_> {
        self.0.lock().unwrap().push((places, headroom));
        Box::pin(async { lb_evalai::Admission::Granted })
    }
}

#[tokio::test]
async fn a_call_takes_its_requests_places_at_once_and_a_retry_its_own() {
    let server = FakeEvalAi::start(Fixture::default()).await.unwrap();
    let budget = std::sync::Arc::new(Counting::default());
    let evalai = client(&server, "host-token").with_budget(budget.clone());
    let sent = |server: &FakeEvalAi| server.requests().iter().filter(|r| !r.admin).count();
    // running: its read and its write in one take.
    evalai.mark_running(AT, "job").await.unwrap();
    assert_eq!(*budget.0.lock().unwrap(), [(2, 2)]);
    assert_eq!(sent(&server), 2);
    // The final post's read, write and read back in one take.
    budget.0.lock().unwrap().clear();
    let done = FinalUpdate {
        status: SubmissionStatus::Finished,
        result: full_result(90.0),
        stdout: String::new(),
        stderr: String::new(),
        metadata: "{}".into(),
    };
    evalai.post_final(AT, &done).await.unwrap();
    assert_eq!(*budget.0.lock().unwrap(), [(3, 3)]);
    assert_eq!(sent(&server), 5);
    // A request sent again takes a place of its own: as many places as requests.
    let server = FakeEvalAi::start(Fixture::default()).await.unwrap();
    let faults = Faults {
        error_500_rate: 0.5,
        seed: 7,
        ..Faults::default()
    };
    server.set_faults(faults).unwrap();
    let budget = std::sync::Arc::new(Counting::default());
    let evalai = client(&server, "host-token").with_budget(budget.clone());
    evalai.mark_running(AT, "job").await.unwrap();
    let places: u32 = budget.0.lock().unwrap().iter().map(|(p, _)| p).sum();
    assert!(sent(&server) > 2, "seed 7 retries nothing");
    assert_eq!(places as usize, sent(&server));
}
