//! The admission table on moto's DynamoDB: the team cap held by conditional transactions,
//! whether admissions race on threads or interleave step by step; arrival kept across
//! retries; places given back; holds whose entries are gone dropped, and only those.

use std::collections::BTreeSet;

use lb_aws::admission::{AdmissionTable, Admit};
use lb_domain::capacity::queue::{ahead, Entry, EntryState};
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

fn execution(id: u64) -> String {
    format!("exec-{id}")
}

async fn enqueue(table: &AdmissionTable, id: u64, team: u64, arrived_ms: u64) -> Entry {
    table
        .enqueue(QUEUE, &waiting(id, team, arrived_ms), &execution(id))
        .await
        .unwrap()
}

/// `id` asks for its place as its entry stands now.
async fn admit(table: &AdmissionTable, id: u64, limit: u32) -> Admit {
    let me = table.entry(QUEUE, id).await.unwrap().expect("an entry");
    table.admit(QUEUE, &me, limit).await.unwrap()
}

/// An entry deleted behind the pipeline's back (its TTL, an operator).
async fn expire(client: &aws_sdk_dynamodb::Client, id: u64) {
    use aws_sdk_dynamodb::types::AttributeValue::S;
    client
        .delete_item()
        .table_name(ADMISSION_TABLE)
        .key("queue", S(QUEUE.into()))
        .key("key", S(format!("submission#{id}")))
        .send()
        .await
        .unwrap();
}

#[tokio::test]
#[ignore = "needs moto"]
async fn a_team_holds_at_most_its_cap_even_when_admissions_race() {
    let (_stack, table, _) = admission_table().await;
    for id in 1..=6 {
        enqueue(&table, id, 7, 1_000 + id).await;
    }
    enqueue(&table, 50, 8, 2_000).await;

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

/// Thirty rounds of six admissions of one team on a multi-thread runtime, each round with a
/// hold whose entry is gone and a release racing them: the team never holds more than its
/// cap, every admitted entry is a holder and every holder an admitted entry.
#[tokio::test(flavor = "multi_thread", worker_threads = 6)]
#[ignore = "needs moto"]
async fn the_cap_holds_on_every_trial_of_threads_racing() {
    let (_stack, table, client) = admission_table().await;
    for trial in 0..30u64 {
        let team = 100 + trial;
        let base = trial * 100;
        // A run of this team that holds a place and ends during the round, and an orphan:
        // a hold whose entry expired.
        enqueue(&table, base + 90, team, 1).await;
        enqueue(&table, base + 91, team, 2).await;
        assert_eq!(admit(&table, base + 90, 2).await, Admit::Admitted);
        assert_eq!(admit(&table, base + 91, 2).await, Admit::Admitted);
        expire(&client, base + 91).await;
        for id in 1..=6 {
            enqueue(&table, base + id, team, 1_000 + id).await;
        }
        let mut racers = Vec::new();
        for id in 1..=6 {
            let table = table.clone();
            racers.push(tokio::spawn(
                async move { admit(&table, base + id, 2).await },
            ));
        }
        let releaser = {
            let table = table.clone();
            tokio::spawn(async move { table.release(QUEUE, base + 90, team).await })
        };
        let mut admitted = BTreeSet::new();
        for (id, racer) in (1..=6).zip(racers) {
            if racer.await.unwrap() == Admit::Admitted {
                admitted.insert((base + id).to_string());
            }
        }
        releaser.await.unwrap().unwrap();
        let holders: BTreeSet<String> = table
            .holders(QUEUE, team)
            .await
            .unwrap()
            .into_iter()
            .collect();
        assert!(holders.len() <= 2, "trial {trial}: {holders:?}");
        assert_eq!(holders, admitted, "trial {trial}: holders are the admitted");
        for id in 1..=6 {
            let state = table.entry(QUEUE, base + id).await.unwrap().unwrap().state;
            let holds = holders.contains(&(base + id).to_string());
            assert_eq!(state != EntryState::Waiting, holds, "trial {trial}, {id}");
        }
    }
}

/// The interleaving that once admitted two with a cap of one: B reads the queue while A still
/// waits, A is admitted, then B asks. B is held, and A keeps its place.
#[tokio::test]
#[ignore = "needs moto"]
async fn a_place_taken_after_the_queue_was_read_is_never_dropped() {
    let (_stack, table, _) = admission_table().await;
    enqueue(&table, 1, 4, 100).await;
    enqueue(&table, 2, 4, 200).await;
    let b_saw = table.entries(QUEUE).await.unwrap();
    assert!(b_saw.iter().all(|e| e.state == EntryState::Waiting));
    assert_eq!(admit(&table, 1, 1).await, Admit::Admitted);
    let b = b_saw.iter().find(|e| e.submission_id == 2).unwrap();
    assert_eq!(table.admit(QUEUE, b, 1).await.unwrap(), Admit::Held);
    assert_eq!(table.holders(QUEUE, 4).await.unwrap(), ["1"]);
}

/// A drop decided on a read is still conditional when written: the orphan's entry comes back
/// (a resume queues it again) between the read and the drop, and the hold stays; the resumed
/// run then takes that same hold, not a second place.
#[tokio::test]
#[ignore = "needs moto"]
async fn an_orphan_that_comes_back_before_the_drop_keeps_its_hold() {
    let (_stack, table, client) = admission_table().await;
    enqueue(&table, 1, 6, 100).await;
    enqueue(&table, 2, 6, 200).await;
    assert_eq!(admit(&table, 1, 1).await, Admit::Admitted);
    expire(&client, 1).await;
    assert_eq!(table.orphans(QUEUE, 6).await.unwrap(), ["1"]);
    // Meanwhile 1 is resumed by a new execution and queued again.
    table
        .enqueue(QUEUE, &waiting(1, 6, 300), "exec-1-resumed")
        .await
        .unwrap();
    assert!(!table.drop_orphan(QUEUE, 6, "1").await.unwrap());
    assert_eq!(table.holders(QUEUE, 6).await.unwrap(), ["1"]);
    assert_eq!(admit(&table, 2, 1).await, Admit::Held);
    // The resumed run's own hold is its place.
    assert_eq!(admit(&table, 1, 1).await, Admit::Admitted);
    assert_eq!(table.holders(QUEUE, 6).await.unwrap(), ["1"]);
    assert_eq!(
        table.execution_of(QUEUE, 1).await.unwrap().as_deref(),
        Some("exec-1-resumed"),
        "the entry is the new execution's"
    );
}

#[tokio::test]
#[ignore = "needs moto"]
async fn arrival_survives_a_retry_and_starts_move_the_queue_forward() {
    let (_stack, table, _) = admission_table().await;
    let first = enqueue(&table, 1, 1, 100).await;
    // A retried Launch, later: the stored arrival (the place in the queue) stays.
    let again = enqueue(&table, 1, 1, 999_999).await;
    assert_eq!(again, first);
    enqueue(&table, 3, 3, 300).await;
    enqueue(&table, 2, 2, 200).await;
    let entries = table.entries(QUEUE).await.unwrap();
    assert_eq!(
        entries.iter().map(|e| e.submission_id).collect::<Vec<_>>(),
        [1, 2, 3],
        "arrival order"
    );
    assert_eq!(ahead(&entries, &entries[2]), 2);

    assert_eq!(admit(&table, 1, 2).await, Admit::Admitted);
    table.mark_running(QUEUE, 1, 1_000).await.unwrap();
    let entries = table.entries(QUEUE).await.unwrap();
    assert_eq!(entries[0].state, EntryState::Running);
    assert_eq!(ahead(&entries, &entries[2]), 1);
    // Its progress, for the forecasts of those waiting: the first start kept, the latest
    // routes; a waiting entry's or a missing one's progress is not kept.
    table.mark_running(QUEUE, 1, 5_000).await.unwrap();
    table.record_progress(QUEUE, 1, 4, (7, 20)).await.unwrap();
    table.record_progress(QUEUE, 2, 4, (1, 20)).await.unwrap();
    table.record_progress(QUEUE, 404, 4, (1, 20)).await.unwrap();
    let read = table.entries_with_progress(QUEUE).await.unwrap();
    let progress: Vec<_> = read.iter().map(|(e, p)| (e.submission_id, *p)).collect();
    let running = lb_domain::capacity::forecast::Progress {
        pairs: 4,
        done: 7,
        routes: 20,
        since: 1_000,
    };
    assert_eq!(progress, [(1, Some(running)), (2, None), (3, None)]);
    // A run from before admission existed has no entry: nothing to mark.
    table.mark_running(QUEUE, 404, 1_000).await.unwrap();
    assert!(table.entry(QUEUE, 404).await.unwrap().is_none());
    // Every team's holds, for the reaper's sweep.
    assert_eq!(
        table.holds(QUEUE).await.unwrap(),
        [(1, vec!["1".to_string()])]
    );
    // The track's pace: the latest durations, most recent first, beside the entries.
    assert!(table.pace(QUEUE, "SENSORS").await.unwrap().is_empty());
    let recent = lb_domain::capacity::queue::RECENT_DURATIONS as u64;
    for seconds in 1..=recent + 3 {
        let read = table.pace(QUEUE, "SENSORS").await.unwrap();
        let durations = lb_domain::capacity::queue::with_latest(&read, seconds);
        table.keep_pace(QUEUE, "SENSORS", &durations).await.unwrap();
    }
    let pace = table.pace(QUEUE, "SENSORS").await.unwrap();
    assert_eq!(pace.len() as u64, recent);
    assert_eq!((pace[0], *pace.last().unwrap()), (recent + 3, 4));
    assert!(table.pace(QUEUE, "MAP").await.unwrap().is_empty());
    // The cluster as the sweep counted it, beside them too.
    assert_eq!(table.fleet(QUEUE).await.unwrap(), None);
    let counted = lb_domain::capacity::forecast::Capacity {
        free: 3,
        booting: 4,
        addable: 36,
    };
    table.keep_fleet(QUEUE, &counted, 1_700).await.unwrap();
    assert_eq!(table.fleet(QUEUE).await.unwrap(), Some((counted, 1_700)));
    assert_eq!(table.entries(QUEUE).await.unwrap().len(), 3, "not an entry");
}

#[tokio::test]
#[ignore = "needs moto"]
async fn a_hold_whose_entry_is_gone_is_dropped_rather_than_block_the_team() {
    let (_stack, table, client) = admission_table().await;
    enqueue(&table, 1, 9, 100).await;
    enqueue(&table, 2, 9, 200).await;
    assert_eq!(admit(&table, 1, 1).await, Admit::Admitted);
    assert_eq!(admit(&table, 2, 1).await, Admit::Held);
    // Entry 1 expires (its TTL) without its run ever reaching Finalize.
    expire(&client, 1).await;
    assert_eq!(admit(&table, 2, 1).await, Admit::Admitted);
    assert_eq!(table.holders(QUEUE, 9).await.unwrap(), ["2"]);
}
