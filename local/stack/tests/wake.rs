//! The deployed definition's wait for a change, run against moto's DynamoDB with the wake
//! table adapter the wake and sweep functions use: the write the state machine makes and the
//! writes that take its token agree on one item.

use fake_evalai::Fixture;
use lb_aws::wake::{Taken, WakeTable};
use local_stack::integrations::{update_item, wait_for_change};
use local_stack::stack::{LOCAL_SETTINGS, WAKE_TABLE};
use local_stack::{EvalAi, Stack};
use serde_json::{json, Value};

fn wait_parameters(token: &str, seen: u64) -> Value {
    wait_for_change(token, 42, 7, seen)
}

#[tokio::test]
#[ignore = "needs moto"]
async fn a_burst_wakes_once_and_a_change_during_a_round_fails_the_next_wait() {
    let (stack, _) = Stack::provisioned(EvalAi::Fake(Fixture::default()), LOCAL_SETTINGS)
        .await
        .expect("the stack starts and is provisioned");
    let client = aws_sdk_dynamodb::Client::new(&stack.sdk);
    let wake = WakeTable::new(client.clone(), WAKE_TABLE);

    // No item yet: the first wait stores its token.
    assert_eq!(wake.state(42).await.unwrap().changes, 0);
    update_item(&client, wait_parameters("token-1", 0))
        .await
        .expect("the first wait's write");
    // A burst of three events: the first takes the token, the others only count.
    let first = wake.count_change(42, 1_000).await.unwrap();
    assert_eq!(
        first,
        Some(Taken {
            token: "token-1".into(),
            execution: Some("submission-42-a".into())
        })
    );
    assert_eq!(wake.count_change(42, 1_001).await.unwrap(), None);
    assert_eq!(wake.count_change(42, 1_002).await.unwrap(), None);
    // The Monitor read the count after the first; the other two came during its round, so
    // the next wait's write fails with the name its Catch matches.
    let err = update_item(&client, wait_parameters("token-2", 1))
        .await
        .unwrap_err();
    assert_eq!(err.error, "DynamoDb.ConditionalCheckFailedException");
    // The round that follows reads 3 and waits.
    let state = wake.state(42).await.unwrap();
    assert_eq!(state.changes, 3);
    update_item(&client, wait_parameters("token-3", 3))
        .await
        .expect("a wait with the current count");

    // A token whose report failed goes back, and is taken again by the event's retry.
    let taken = wake.count_change(42, 1_003).await.unwrap().unwrap();
    assert_eq!(taken.token, "token-3");
    wake.restore_token(42, &taken, false).await.unwrap();
    assert_eq!(wake.count_change(42, 1_004).await.unwrap(), Some(taken));

    // The sweep: waiting executions are listed with their challenge; a cancel is flagged once
    // and takes the token; a flagged item is no longer listed; the next wait clears the flag.
    update_item(&client, wait_parameters("token-4", 5))
        .await
        .unwrap();
    let waiting = wake.waiting().await.unwrap();
    assert_eq!(waiting.len(), 1);
    assert_eq!((waiting[0].submission_id, waiting[0].challenge), (42, 7));
    let flagged = wake.flag_cancel(42).await.unwrap();
    assert_eq!(
        flagged.flatten().map(|t| t.token).as_deref(),
        Some("token-4")
    );
    assert_eq!(wake.flag_cancel(42).await.unwrap(), None, "flagged once");
    assert!(wake.state(42).await.unwrap().cancel);
    assert!(wake.waiting().await.unwrap().is_empty());
    // A submission no wait ever stored (not ours, or long gone) is not touched.
    assert_eq!(wake.flag_cancel(43).await.unwrap(), None);
    update_item(&client, wait_parameters("token-5", 6))
        .await
        .unwrap();
    assert!(!wake.state(42).await.unwrap().cancel);
    // Parameters the API refuses are the integration's errors, never a panic.
    let err = update_item(
        &client,
        json!({"TableName": WAKE_TABLE, "Key": {"submission_id": {"Q": "1"}}}),
    )
    .await
    .unwrap_err();
    assert_eq!(err.error, "DynamoDb.ValidationException");
}
