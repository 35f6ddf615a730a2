//! The admission table on moto's DynamoDB: the team cap held by conditional transactions, even
//! with admissions racing; arrival kept across retries; places given back; stale holds dropped.

use lb_aws::admission::{AdmissionTable, Admit};
use lb_domain::queue::{ahead, Entry, EntryState};
use local_stack::stack::ADMISSION_TABLE;
use local_stack::Stack;

const QUEUE: &str = "2.0";

/// The admission table as the local stack provisions it from `infra/app.yaml` (its key
/// schema, `queue` S and `key` S, included), on moto.
async fn admission_table() -> (Stack, AdmissionTable, aws_sdk_dynamodb::Client) {
    let (stack, _) = test_support::stack::provisioned().await;
    let client = aws_sdk_dynamodb::Client::new(&stack.sdk);
    let table = AdmissionTable::new(client.clone(), ADMISSION_TABLE);
    (stack, table, client)
}

fn waiting(submission_id: u64, team_id: u64, arrived_ms: u64) -> Entry {
    Entry {
        submission_id,
        team_id,
        arrived_ms,
        state: EntryState::Waiting,
    }
}

async fn admit(table: &AdmissionTable, id: u64, limit: u32) -> Admit {
    let entries = table.entries(QUEUE).await.unwrap();
    let me = entries.iter().find(|e| e.submission_id == id).unwrap();
    table.admit(QUEUE, me, limit, &entries).await.unwrap()
}

#[tokio::test]
#[ignore = "needs moto"]
async fn a_team_holds_at_most_its_cap_even_when_admissions_race() {
    let (_stack, table, _) = admission_table().await;
    for id in 1..=6 {
        table
            .enqueue(QUEUE, &waiting(id, 7, 1_000 + id))
            .await
            .unwrap();
    }
    table.enqueue(QUEUE, &waiting(50, 8, 2_000)).await.unwrap();

    // Six Launches of one team at once, each with its own view of the queue.
    let attempts = (1..=6).map(|id| {
        let table = table.clone();
        tokio::spawn(async move { (id, admit(&table, id, 2).await) })
    });
    let mut admitted = Vec::new();
    for attempt in attempts {
        let (id, outcome) = attempt.await.unwrap();
        if outcome == Admit::Admitted {
            admitted.push(id);
        }
    }
    assert_eq!(admitted.len(), 2, "the cap of 2 held: {admitted:?}");
    assert_eq!(table.holders(QUEUE, 7).await.unwrap().len(), 2);
    // Another team is not held back by team 7's queue.
    assert_eq!(admit(&table, 50, 2).await, Admit::Admitted);

    // An admitted entry asks again (a retried Launch): still admitted, no second place.
    assert_eq!(admit(&table, admitted[0], 2).await, Admit::Admitted);
    assert_eq!(table.holders(QUEUE, 7).await.unwrap().len(), 2);

    // One ends: its place goes back, once however often the release is repeated.
    table.release(QUEUE, admitted[0], 7).await.unwrap();
    table.release(QUEUE, admitted[0], 7).await.unwrap();
    assert_eq!(table.holders(QUEUE, 7).await.unwrap().len(), 1);
    assert!(table.entry(QUEUE, admitted[0]).await.unwrap().is_none());
    let next = (1..=6).find(|id| !admitted.contains(id)).unwrap();
    assert_eq!(admit(&table, next, 2).await, Admit::Admitted);
    let last = (1..=6).rev().find(|id| !admitted.contains(id)).unwrap();
    assert_eq!(admit(&table, last, 2).await, Admit::Held);
}

#[tokio::test]
#[ignore = "needs moto"]
async fn arrival_survives_a_retry_and_starts_move_the_queue_forward() {
    let (_stack, table, _) = admission_table().await;
    let first = table.enqueue(QUEUE, &waiting(1, 1, 100)).await.unwrap();
    // A retried Launch, later: the stored arrival (the place in the queue) stays.
    let again = table.enqueue(QUEUE, &waiting(1, 1, 999_999)).await.unwrap();
    assert_eq!(again, first);
    table.enqueue(QUEUE, &waiting(3, 3, 300)).await.unwrap();
    table.enqueue(QUEUE, &waiting(2, 2, 200)).await.unwrap();
    let entries = table.entries(QUEUE).await.unwrap();
    assert_eq!(
        entries.iter().map(|e| e.submission_id).collect::<Vec<_>>(),
        [1, 2, 3],
        "arrival order"
    );
    assert_eq!(ahead(&entries, &entries[2]), 2);

    assert_eq!(admit(&table, 1, 2).await, Admit::Admitted);
    table.mark_running(QUEUE, 1).await.unwrap();
    let entries = table.entries(QUEUE).await.unwrap();
    assert_eq!(entries[0].state, EntryState::Running);
    assert_eq!(ahead(&entries, &entries[2]), 1);
    // A run from before admission existed has no entry: nothing to mark.
    table.mark_running(QUEUE, 404).await.unwrap();
    assert!(table.entry(QUEUE, 404).await.unwrap().is_none());
}

#[tokio::test]
#[ignore = "needs moto"]
async fn a_hold_whose_entry_is_gone_is_dropped_rather_than_block_the_team() {
    let (_stack, table, client) = admission_table().await;
    table.enqueue(QUEUE, &waiting(1, 9, 100)).await.unwrap();
    table.enqueue(QUEUE, &waiting(2, 9, 200)).await.unwrap();
    assert_eq!(admit(&table, 1, 1).await, Admit::Admitted);
    assert_eq!(admit(&table, 2, 1).await, Admit::Held);
    // Entry 1 expires (its TTL) without its run ever reaching Finalize.
    client
        .delete_item()
        .table_name(ADMISSION_TABLE)
        .key(
            "queue",
            aws_sdk_dynamodb::types::AttributeValue::S(QUEUE.into()),
        )
        .key(
            "key",
            aws_sdk_dynamodb::types::AttributeValue::S("submission#1".into()),
        )
        .send()
        .await
        .unwrap();
    assert_eq!(admit(&table, 2, 1).await, Admit::Admitted);
    assert_eq!(table.holders(QUEUE, 9).await.unwrap(), ["2"]);
}
