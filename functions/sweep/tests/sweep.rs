//! The cancel sweep against the fake EvalAI and moto's wake table, with the deployed
//! definition's wait standing for each waiting execution and a recorder for Step Functions.

use test_support::{Answer, RecordingCallbacks};

use fake_evalai::NewSubmission;
use local_stack::integrations::{update_item, wait_for_change, wait_for_change_since};
use sweep::Deps;

/// A provisioned stack and the sweep's dependencies on it, reporting to a recorder.
async fn sweep_on_a_stack() -> (local_stack::stack::Stack, Deps<RecordingCallbacks>) {
    let (stack, _) = test_support::stack::provisioned().await;
    let config = local_stack::stack::function_config();
    let deps = Deps::load(&stack.sdk, &config, RecordingCallbacks::default())
        .await
        .unwrap();
    (stack, deps)
}

/// A new submission of `team` on phase 1, with this metadata; its id.
fn submit(fake: &fake_evalai::FakeEvalAi, team: u64, metadata: Option<serde_json::Value>) -> u64 {
    fake.add_submission(NewSubmission {
        challenge_phase: 1,
        participant_team: team,
        submitted_image_uri: "123456789012.dkr.ecr.us-west-2.amazonaws.com/t:1".into(),
        created_by: None,
        submission_metadata: metadata,
    })
    .unwrap()
    .id
}

#[tokio::test]
#[ignore = "needs moto"]
async fn one_request_per_challenge_finds_the_cancels_and_wakes_only_those_waiting() {
    let (stack, deps) = sweep_on_a_stack().await;
    let fake = stack.fake();
    let new = || submit(fake, 1, None);
    let (a, b, c) = (new(), new(), new());
    let client = aws_sdk_dynamodb::Client::new(&stack.sdk);
    // a and b wait; c does not (its execution is in a Monitor round, or not ours). Each wait
    // stores when EvalAI received its submission.
    let mut arrivals = Vec::new();
    for (id, token) in [(a, "token-a"), (b, "token-b")] {
        let at = deps
            .evalai
            .submission(id)
            .await
            .unwrap()
            .submitted_ms
            .unwrap()
            / 1000;
        arrivals.push(at);
        update_item(&client, wait_for_change_since(token, id, 1, 0, at))
            .await
            .unwrap();
    }

    // Nothing cancelled: one request, for what came since the oldest waiting, no wake.
    let before = fake.requests().len();
    let sweep = sweep::handle(&deps).await.unwrap();
    assert_eq!((sweep.waiting, sweep.challenges), (2, 1));
    assert!(sweep.cancelled.is_empty() && sweep.woken.is_empty());
    let requests = fake.requests()[before..].to_vec();
    assert_eq!(requests.len(), 1, "{requests:?}");
    assert_eq!(requests[0].path, "/api/jobs/challenge/1/submission/");
    let oldest = *arrivals.iter().min().unwrap() as i64;
    let after = time::OffsetDateTime::from_unix_timestamp(oldest)
        .unwrap()
        .format(&time::format_description::well_known::Rfc3339)
        .unwrap();
    assert_eq!(
        requests[0].query.as_deref(),
        Some(format!("status=cancelled&submitted_after={after}").as_str())
    );

    // a and c cancel: only a is waiting, so only a's token is reported, once.
    fake.cancel(a).unwrap();
    fake.cancel(c).unwrap();
    let sweep = sweep::handle(&deps).await.unwrap();
    assert_eq!(
        (sweep.cancelled.clone(), sweep.woken.clone()),
        (vec![a], vec![a])
    );
    assert_eq!(deps.callbacks.reported(), ["token-a"]);
    assert!(
        deps.wakes.state(a).await.unwrap().cancel,
        "the Monitor will confirm it"
    );
    let sweep = sweep::handle(&deps).await.unwrap();
    assert_eq!(sweep.waiting, 1, "a is no longer waiting");
    assert!(sweep.cancelled.is_empty());
    assert_eq!(deps.callbacks.reported().len(), 1);

    // b cancels while Step Functions is unreachable: the flag is undone and the token put
    // back, so the next sweep wakes it.
    fake.cancel(b).unwrap();
    deps.callbacks.answer_always(Answer::Unreachable);
    let err = sweep::handle(&deps).await.unwrap_err();
    assert_eq!(err.name(), "SweepIncomplete");
    assert!(!deps.wakes.state(b).await.unwrap().cancel);
    deps.callbacks.answer_always(Answer::Delivered);
    let sweep = sweep::handle(&deps).await.unwrap();
    assert_eq!(sweep.woken, vec![b]);
    assert_eq!(deps.callbacks.reported(), ["token-a", "token-b", "token-b"]);

    // A challenge EvalAI does not have: named in the error, the other challenges still swept.
    let d = new();
    update_item(&client, wait_for_change("token-d", d, 99, 0))
        .await
        .unwrap();
    fake.cancel(d).unwrap();
    let err = sweep::handle(&deps).await.unwrap_err();
    assert_eq!(err.name(), "SweepIncomplete");
    assert!(err.to_string().contains("challenge 99"), "{err}");
}

#[tokio::test]
#[ignore = "needs moto"]
async fn another_team_s_huge_cancelled_submissions_do_not_blind_the_sweep() {
    let (stack, deps) = sweep_on_a_stack().await;
    let fake = stack.fake();
    let new = |team, metadata| submit(fake, team, metadata);
    // Ours waits; then team 2 makes five submissions of 2.4 MB of metadata each (14 MB of
    // list, over any whole-body cap) and cancels them, after ours arrived.
    let ours = new(1, None);
    let at = deps
        .evalai
        .submission(ours)
        .await
        .unwrap()
        .submitted_ms
        .unwrap()
        / 1000;
    let client = aws_sdk_dynamodb::Client::new(&stack.sdk);
    update_item(&client, wait_for_change_since("token-ours", ours, 1, 0, at))
        .await
        .unwrap();
    let huge = serde_json::json!({"notes": "x".repeat(2_400_000)});
    for _ in 0..5 {
        let id = new(2, Some(huge.clone()));
        fake.cancel(id).unwrap();
    }
    fake.cancel(ours).unwrap();
    // One read of the list, element by element: the five skipped, ours found and woken.
    let started = std::time::Instant::now();
    let sweep = sweep::handle(&deps).await.unwrap();
    assert_eq!(
        (sweep.cancelled.clone(), sweep.woken.clone()),
        (vec![ours], vec![ours])
    );
    assert_eq!(deps.callbacks.reported(), ["token-ours"]);
    assert!(
        started.elapsed() < std::time::Duration::from_secs(30),
        "{:?}",
        started.elapsed()
    );
}

#[tokio::test]
#[ignore = "needs moto"]
async fn each_leaderboard_s_queue_gets_its_cluster_s_gpus_for_the_note_s_forecast() {
    let (mut stack, mut deps) = sweep_on_a_stack().await;
    stack
        .start_kube(local_kube::Config {
            gpus: Some(4),
            ..local_kube::Config::default()
        })
        .unwrap();
    let kubeconfig = stack.kubeconfig.clone().unwrap();
    deps.clusters = lb_pipeline::cluster::Clusters::kubeconfig(kubeconfig);
    // No EKS here: nothing is known of the node groups' maxima, so nothing is addable.
    deps.eks = None;
    let before = lb_pipeline::clients::now_epoch_seconds();
    let sweep = sweep::handle(&deps).await.unwrap();
    assert_eq!(sweep.gpus, Some((4, 0)), "{sweep:?}");
    assert!(
        sweep.drained.is_empty(),
        "one node drains nowhere: {sweep:?}"
    );
    let table = lb_aws::admission::AdmissionTable::new(
        aws_sdk_dynamodb::Client::new(&stack.sdk),
        local_stack::stack::ADMISSION_TABLE,
    );
    // Both leaderboards run on the one cluster: each queue has its count.
    for queue in ["1.0", "2.0"] {
        let (counted, at) = table.fleet(queue).await.unwrap().expect("counted");
        assert_eq!((counted.free, counted.booting, counted.addable), (4, 0, 0));
        assert!(at >= before, "{at} {before}");
    }
}
