//! The shared EvalAI budget on moto's DynamoDB, alone and in front of the fake EvalAI with its
//! throttle on (DRF's sliding window, reference section 1).

use std::sync::Arc;
use std::time::{Duration, Instant};

use aws_sdk_dynamodb::types::{
    AttributeDefinition, BillingMode, KeySchemaElement, KeyType, ScalarAttributeType,
};
use fake_evalai::{FakeEvalAi, Fixture, NewSubmission};
use lb_aws::budget::BudgetTable;
use lb_domain::submission::SubmissionStatus;
use lb_evalai::{
    Admission, AuthScheme, BudgetPolicy, EvalAiClient, EvalAiError, FinalUpdate, HostToken,
    PartialUpdate, Priority, RetryPolicy, SubmissionRef, WriteOutcome,
};
use local_stack::moto::MotoServer;

const TABLE: &str = "leaderboard-evalai-budget";

/// The budget table in the template's key schema (`window_start`, N).
async fn budget_table(moto: &MotoServer, policy: BudgetPolicy) -> BudgetTable {
    let config = lb_aws::sdk_config_at(&moto.endpoint(), "us-east-1").await;
    let client = aws_sdk_dynamodb::Client::new(&config);
    client
        .create_table()
        .table_name(TABLE)
        .billing_mode(BillingMode::PayPerRequest)
        .attribute_definitions(
            AttributeDefinition::builder()
                .attribute_name("window_start")
                .attribute_type(ScalarAttributeType::N)
                .build()
                .unwrap(),
        )
        .key_schema(
            KeySchemaElement::builder()
                .attribute_name("window_start")
                .key_type(KeyType::Hash)
                .build()
                .unwrap(),
        )
        .send()
        .await
        .unwrap();
    BudgetTable::new(client, TABLE, policy)
}

#[tokio::test]
#[ignore = "needs moto"]
async fn a_call_takes_its_requests_places_at_once_and_only_while_all_fit() {
    let moto = MotoServer::start().unwrap();
    let policy = BudgetPolicy::evalai(60).unwrap();
    let budget = budget_table(&moto, policy).await;
    let window_start = 1_800_000_000_000;
    let at = || window_start + 1_000;
    // A final post's read, write and read back: three places in one round trip.
    assert_eq!(
        budget.take_by(Priority::Urgent, 3, 3, &at).await,
        Admission::Granted
    );
    assert_eq!(budget.granted(window_start).await.unwrap(), 3);
    // Routine calls of two: the 7 routine places hold 3 + 2 + 2, and then no call of two.
    for _ in 0..2 {
        assert_eq!(
            budget.take_by(Priority::Routine, 2, 2, &at).await,
            Admission::Granted
        );
    }
    assert!(matches!(
        budget.take_by(Priority::Routine, 2, 2, &at).await,
        Admission::Full { .. }
    ));
    assert_eq!(budget.granted(window_start).await.unwrap(), 7);
    // The urgent reserve of 2 fits one urgent call of two; an urgent call of three then
    // books the next window, its three places there.
    assert_eq!(
        budget.take_by(Priority::Urgent, 2, 2, &at).await,
        Admission::Granted
    );
    assert!(matches!(
        budget.take_by(Priority::Urgent, 3, 3, &at).await,
        Admission::Booked { .. }
    ));
    assert_eq!(budget.granted(window_start).await.unwrap(), 9);
    assert_eq!(budget.granted(window_start + 12_000).await.unwrap(), 3);
}

#[tokio::test]
#[ignore = "needs moto"]
async fn a_window_grants_its_routine_share_then_its_reserve_to_urgent_requests_only() {
    let moto = MotoServer::start().unwrap();
    let policy = BudgetPolicy::evalai(60).unwrap();
    let budget = budget_table(&moto, policy).await;
    // 10.5 s into a 12 s window: the next opens in 1.5 s.
    let window_start = 1_800_000_000_000;
    assert_eq!(window_start % 12_000, 0);
    let at = window_start + 10_500;

    // NB: one after the other. DynamoDB applies a condition and its write as one atomic step
    // (Developer Guide, "Condition expressions" and "Atomic counters"), so racing takers
    // cannot pass the same count; moto's threaded server reads and writes an item without a
    // lock, so racing them here would test moto, not the budget.
    let mut granted = 0;
    for _ in 0..20 {
        match budget.take_at(Priority::Routine, 1, at).await {
            Admission::Granted => granted += 1,
            Admission::Full { retry_in } => assert_eq!(retry_in, Duration::from_millis(1_500)),
            other => panic!("a routine request got {other:?}"),
        }
    }
    assert_eq!(granted, policy.routine_per_window);
    assert_eq!(budget.granted(window_start).await.unwrap(), 7);

    // The reserve is the urgent requests' alone; then an urgent request books the next
    // window (opening in 1.5 s, spread over its first quarter) instead of waiting to ask.
    for _ in 0..(policy.per_window - policy.routine_per_window) {
        assert_eq!(
            budget.take_at(Priority::Urgent, 1, at).await,
            Admission::Granted
        );
    }
    let Admission::Booked { wait } = budget.take_at(Priority::Urgent, 1, at).await else {
        panic!("a full window must book the next for an urgent request");
    };
    assert!(
        wait >= Duration::from_millis(1_500) && wait < Duration::from_millis(1_500 + 3_000),
        "{wait:?}"
    );
    assert_eq!(budget.granted(window_start).await.unwrap(), 9);
    let next = window_start + 12_000;
    assert_eq!(budget.granted(next).await.unwrap(), 1);

    // In the next window the booking counts against the routine share: 6 routine requests
    // fit, not 7; a call needing two requests is refused while only one routine slot is
    // left, so its read is not spent on a write that could not follow.
    for _ in 0..5 {
        assert_eq!(
            budget.take_at(Priority::Routine, 1, next).await,
            Admission::Granted
        );
    }
    assert!(matches!(
        budget.take_at(Priority::Routine, 2, next).await,
        Admission::Full { .. }
    ));
    assert_eq!(
        budget.take_at(Priority::Routine, 1, next).await,
        Admission::Granted
    );
    assert!(matches!(
        budget.take_at(Priority::Routine, 1, next).await,
        Admission::Full { .. }
    ));
    assert_eq!(budget.granted(next).await.unwrap(), 7);

    // No table: the budget says it cannot tell (the client then sends, and honours 429s).
    let config = lb_aws::sdk_config_at(&moto.endpoint(), "us-east-1").await;
    let missing = BudgetTable::new(aws_sdk_dynamodb::Client::new(&config), "nope", policy);
    assert!(matches!(
        missing.take_at(Priority::Urgent, 1, at).await,
        Admission::Unavailable(why) if why.contains("UpdateItem")
    ));
}

#[tokio::test]
#[ignore = "needs moto"]
async fn eight_submissions_hammering_evalai_through_one_budget_are_never_throttled() {
    // EvalAI's throttle, shortened: 30 requests in any sliding 6 s.
    let server = FakeEvalAi::start(Fixture {
        throttle_per_minute: 30,
        throttle_window_secs: 6,
        ..Fixture::default()
    })
    .await
    .unwrap();
    let moto = MotoServer::start().unwrap();
    let policy = BudgetPolicy::for_limit(30, Duration::from_secs(6)).unwrap();
    let budget = Arc::new(budget_table(&moto, policy).await);
    let ids: Vec<u64> = (0..8)
        .map(|_| {
            server
                .add_submission(NewSubmission {
                    challenge_phase: 1,
                    participant_team: 1,
                    submitted_image_uri: "example/agent:1".into(),
                    created_by: None,
                    submission_metadata: None,
                })
                .unwrap()
                .id
        })
        .collect();

    // Each submission is its own function with its own client (as Lambdas are), sending a
    // partial update as fast as it may for 8 s, then its final update.
    let started = Instant::now();
    let runs: Vec<_> = ids
        .iter()
        .map(|&id| {
            let budget = budget.clone();
            let url = server.url();
            tokio::spawn(async move {
                let policy = RetryPolicy {
                    budget: Duration::from_secs(30),
                    ..RetryPolicy::default()
                };
                let client = EvalAiClient::new(
                    &url,
                    &HostToken::new("host-token"),
                    AuthScheme::Bearer,
                    policy,
                )
                .unwrap()
                .with_budget(budget);
                let at = SubmissionRef {
                    challenge: 1,
                    phase: 1,
                    submission: id,
                };
                let partial = PartialUpdate {
                    result: "[]".into(),
                    stdout: "route 1 done".into(),
                    metadata: "{}".into(),
                };
                let (mut sent, mut skipped) = (0, 0);
                while started.elapsed() < Duration::from_secs(8) {
                    match client.post_partial(at, &partial).await {
                        Ok(WriteOutcome::Written) => sent += 1,
                        Err(EvalAiError::OverBudget) => skipped += 1,
                        other => panic!("partial update of {id}: {other:?}"),
                    }
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
                let done = FinalUpdate {
                    status: SubmissionStatus::Finished,
                    result: "[]".into(),
                    stdout: "all routes done".into(),
                    stderr: String::new(),
                    metadata: "{}".into(),
                };
                let outcome = client.post_final(at, &done).await;
                (sent, skipped, outcome.map_err(|e| e.to_string()))
            })
        })
        .collect();
    let (mut sent, mut skipped) = (0, 0);
    for run in runs {
        let (s, k, outcome) = run.await.unwrap();
        assert_eq!(outcome, Ok(WriteOutcome::Written));
        sent += s;
        skipped += k;
    }

    let log: Vec<_> = server.requests().into_iter().filter(|r| !r.admin).collect();
    let throttled = log.iter().filter(|r| r.status == 429).count();
    assert_eq!(
        throttled,
        0,
        "EvalAI throttled {throttled} of {} requests",
        log.len()
    );
    // The budget was the limit: routine updates were skipped, not throttled, and still went
    // out steadily; every final update landed.
    assert!(
        skipped > 0,
        "nothing was ever skipped: the test did not press the limit"
    );
    // A partial update is a read and a write: the routine share of a 1.2 s window (3) holds
    // one, so 8 s carry six or seven of them, whoever sends them.
    assert!(sent >= 5, "only {sent} partial updates went out");
    for id in ids {
        assert_eq!(
            server.submission(id).unwrap().status,
            "finished",
            "submission {id}"
        );
    }
}

#[tokio::test]
#[ignore = "needs moto"]
async fn a_grant_that_returns_after_its_window_closed_is_asked_for_again() {
    let moto = MotoServer::start().unwrap();
    let policy = BudgetPolicy::evalai(60).unwrap();
    let budget = budget_table(&moto, policy).await;
    let window_start: u64 = 1_800_000_000_000;
    let granted = |start: u64| budget.granted(start);
    // The write is slow: 11.9 s into a 12 s window, and each reading of the clock 200 ms on.
    let ticks = std::sync::atomic::AtomicU64::new(window_start + 11_900);
    let clock = || ticks.fetch_add(200, std::sync::atomic::Ordering::SeqCst);
    // The grant came back in the next window: asked again there, granted there.
    assert_eq!(
        budget.take_by(Priority::Urgent, 1, 1, &clock).await,
        Admission::Granted
    );
    assert_eq!(
        granted(window_start).await.unwrap(),
        1,
        "the late place, unused"
    );
    assert_eq!(granted(window_start + 12_000).await.unwrap(), 1);
    // A clock a window ahead at every reading never finds its grant in time: it gives up.
    let ticks = std::sync::atomic::AtomicU64::new(window_start + 24_000);
    let clock = || ticks.fetch_add(12_000, std::sync::atomic::Ordering::SeqCst);
    assert!(matches!(
        budget.take_by(Priority::Urgent, 1, 1, &clock).await,
        Admission::Full { .. }
    ));
}
