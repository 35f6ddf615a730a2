//! A place given back wakes its team's next waiting submissions, one per open place, on moto's DynamoDB with the
//! stack's admission and wake tables and the state machine's own wait write.

use test_support::{Answer, RecordingCallbacks};

use lb_aws::admission::AdmissionTable;
use lb_aws::wake::WakeTable;
use lb_domain::capacity::queue::{Entry, EntryState};
use lb_pipeline::payload::SubmissionInfo;
use lb_pipeline::queue::{take_turn, wake_team_next, Admission, TeamQueue, Waker, Woken};
use local_stack::integrations::{update_item, wait_for_change};
use local_stack::stack::{ADMISSION_TABLE, WAKE_TABLE};

/// Wakes at a fixed time.
fn waker<'a, C>(wakes: &'a WakeTable, callbacks: &'a C) -> Waker<'a, C> {
    Waker {
        wakes,
        callbacks,
        now: 1_000,
    }
}

fn info(submission_id: u64, team_id: u64) -> SubmissionInfo {
    SubmissionInfo {
        challenge_id: 7,
        phase_id: 1,
        submission_id,
        team_id,
        team_name: format!("team {team_id}"),
        leaderboard: lb_domain::results::Leaderboard::V2,
        track: "SENSORS".into(),
        image: "example/agent:1".into(),
        routes: 20,
        workers: 2,
        resuming: false,
        execution: format!("exec-{submission_id}"),
        arrived_ms: None,
        submitted_at: 0,
    }
}

#[tokio::test]
#[ignore = "needs moto"]
async fn a_place_given_back_wakes_the_teams_oldest_waiting_submission() {
    let (stack, _) = test_support::stack::provisioned().await;
    let client = aws_sdk_dynamodb::Client::new(&stack.sdk);
    let table = AdmissionTable::new(client.clone(), ADMISSION_TABLE);
    let wakes = WakeTable::new(client.clone(), WAKE_TABLE);
    let callbacks = RecordingCallbacks::default();

    // Team 5 holds its one place with 1; 2 and 3 wait behind it, 4 of team 6 runs.
    for (id, team, arrived) in [(1, 5, 100), (2, 5, 200), (3, 5, 300), (4, 6, 250)] {
        take_turn(&table, &info(id, team), arrived, 1)
            .await
            .unwrap();
    }
    let wake = |team| {
        let team = TeamQueue {
            queue: "2.0",
            team,
            limit: 1,
        };
        wake_team_next(&table, team, waker(&wakes, &callbacks))
    };
    // Nobody of team 6 waits; team 5 has no place open.
    assert_eq!(wake(6).await.unwrap(), []);
    assert_eq!(wake(5).await.unwrap(), []);

    // 2 and 3 park in the state machine's wait, each with its token.
    for (id, token) in [(2, "token-2"), (3, "token-3")] {
        // The changes its Monitor round read.
        let seen = wakes.state(id).await.unwrap().changes;
        update_item(&client, wait_for_change(token, id, 7, seen))
            .await
            .expect("the wait's write");
    }
    // 1 ends and gives its place back: 2 (the older) is woken, never 3.
    table.release("2.0", 1, 5).await.unwrap();
    callbacks.answer_next(Answer::Unreachable);
    assert!(wake(5).await.is_err(), "a failed report is an error");
    // The token went back: the next try delivers it.
    assert_eq!(wake(5).await.unwrap(), [Woken::Delivered(2)]);
    assert_eq!(callbacks.delivered(), ["token-2"]);
    // Its token is taken: a second wake finds it not waiting, and 3 stays parked.
    assert_eq!(wake(5).await.unwrap(), [Woken::NotWaiting(2)]);
    let parked: Vec<u64> = wakes
        .waiting()
        .await
        .unwrap()
        .iter()
        .map(|w| w.submission_id)
        .collect();
    assert_eq!(parked, [3]);
    // Woken, 2 takes its turn at once.
    let standing = take_turn(&table, &info(2, 5), 200, 1).await.unwrap();
    assert!(standing.admitted);
    let entries = table.entries("2.0").await.unwrap();
    let state = |id: u64| {
        entries
            .iter()
            .find(|e: &&Entry| e.submission_id == id)
            .map(|e| e.state)
    };
    assert_eq!(state(2), Some(EntryState::Admitted));
    assert_eq!(state(3), Some(EntryState::Waiting));
}

#[tokio::test]
#[ignore = "needs moto"]
async fn every_place_given_back_is_offered_at_once() {
    let (stack, _) = test_support::stack::provisioned().await;
    let client = aws_sdk_dynamodb::Client::new(&stack.sdk);
    let table = AdmissionTable::new(client.clone(), ADMISSION_TABLE);
    let wakes = WakeTable::new(client.clone(), WAKE_TABLE);
    let callbacks = RecordingCallbacks::default();

    // Team 8 holds both its places with 1 and 2; 3, 4 and 5 wait, each parked.
    for (id, arrived) in [(1, 100), (2, 200), (3, 300), (4, 400), (5, 500)] {
        take_turn(&table, &info(id, 8), arrived, 2).await.unwrap();
    }
    for id in [3, 4, 5] {
        let seen = wakes.state(id).await.unwrap().changes;
        update_item(
            &client,
            wait_for_change(&format!("token-{id}"), id, 7, seen),
        )
        .await
        .expect("the wait's write");
    }
    // Both end (a cluster lost, say): both places are offered, to the two oldest.
    table.release("2.0", 1, 8).await.unwrap();
    table.release("2.0", 2, 8).await.unwrap();
    let team = TeamQueue {
        queue: "2.0",
        team: 8,
        limit: 2,
    };
    let woken = wake_team_next(&table, team, waker(&wakes, &callbacks))
        .await
        .unwrap();
    assert_eq!(woken, [Woken::Delivered(3), Woken::Delivered(4)]);
    // Whichever round comes first, both take their places; 5 still waits its turn.
    for id in [4, 3] {
        let standing = take_turn(&table, &info(id, 8), id * 100, 2).await.unwrap();
        assert!(standing.admitted, "{id} admitted");
    }
    assert!(
        !take_turn(&table, &info(5, 8), 500, 2)
            .await
            .unwrap()
            .admitted
    );
    assert_eq!(table.holders("2.0", 8).await.unwrap(), ["3", "4"]);
}

#[tokio::test]
#[ignore = "needs moto"]
async fn leaving_wakes_the_next_for_the_place_it_gives_back_read_beside_the_release() {
    let (stack, _) = test_support::stack::provisioned().await;
    let client = aws_sdk_dynamodb::Client::new(&stack.sdk);
    let table = AdmissionTable::new(client.clone(), ADMISSION_TABLE);
    let wakes = WakeTable::new(client.clone(), WAKE_TABLE);
    let callbacks = RecordingCallbacks::default();
    // Team 9 holds its one place with 1; 2 and 3 wait, parked.
    for (id, arrived) in [(1, 100), (2, 200), (3, 300)] {
        take_turn(&table, &info(id, 9), arrived, 1).await.unwrap();
    }
    for id in [2, 3] {
        let seen = wakes.state(id).await.unwrap().changes;
        let wait = wait_for_change(&format!("token-{id}"), id, 7, seen);
        update_item(&client, wait).await.expect("the wait's write");
    }
    let admission = Admission::Queue(table.clone());
    let team = TeamQueue {
        queue: "2.0",
        team: 9,
        limit: 1,
    };
    // The queue is read while 1 still holds its place: that place counts as given back, so
    // 2 (the oldest) is woken, and only once the place is free.
    assert!(admission
        .leave(team, 1, waker(&wakes, &callbacks))
        .await
        .unwrap());
    assert_eq!(callbacks.delivered(), ["token-2"]);
    assert!(table.holders("2.0", 9).await.unwrap().is_empty());
    assert!(
        take_turn(&table, &info(2, 9), 200, 1)
            .await
            .unwrap()
            .admitted
    );
    // A wake that cannot be reported leaves the place given back all the same.
    callbacks.answer_next(Answer::Unreachable);
    assert!(admission
        .leave(team, 2, waker(&wakes, &callbacks))
        .await
        .unwrap());
    assert!(table.holders("2.0", 9).await.unwrap().is_empty());
    assert_eq!(
        callbacks.delivered(),
        ["token-2"],
        "3's wake was not delivered"
    );
    // Without a queue there is nothing to leave.
    let none = Admission::Unlimited.leave(team, 3, waker(&wakes, &callbacks));
    assert!(!none.await.unwrap());
}

#[tokio::test]
#[ignore = "needs moto"]
async fn the_note_plays_the_queue_out_from_the_runs_progress() {
    let (stack, _) = test_support::stack::provisioned().await;
    let client = aws_sdk_dynamodb::Client::new(&stack.sdk);
    let table = AdmissionTable::new(client, ADMISSION_TABLE);
    let admission = Admission::Queue(table.clone());
    let hour = 3600;
    let now = 100 * hour;
    // The track's evaluations took two to three hours.
    let durations: Vec<u64> = (0..20).map(|k| 2 * hour + k * hour / 20).collect();
    table.keep_pace("2.0", "SENSORS", &durations).await.unwrap();
    // Team 5 holds its one place with 1, nine tenths through its routes after two hours; 2
    // waits behind it.
    for (id, arrived) in [(1, 100), (2, 200)] {
        take_turn(&table, &info(id, 5), arrived, 1).await.unwrap();
    }
    admission
        .mark_running(&info(1, 5), now - 2 * hour)
        .await
        .unwrap();
    admission
        .record_progress(&info(1, 5), (18, 20))
        .await
        .unwrap();
    let place = lb_domain::capacity::queue::Place {
        ahead: 1,
        team_ahead: 0,
        running: 1,
    };
    let hold = lb_domain::capacity::queue::Hold::TeamLimit { limit: 1 };
    let note = admission.note(&info(2, 5), (place, hold), now).await;
    // A tenth of its routes left: well within the hour, where places ahead at the pace (a
    // whole evaluation) would say two to three hours.
    assert!(note.contains("it should start"), "{note}");
    assert!(note.contains("minutes"), "{note}");
    // Just started instead: hours.
    admission
        .record_progress(&info(1, 5), (0, 20))
        .await
        .unwrap();
    let note = admission
        .note(&info(2, 5), (place, hold), now - 2 * hour + 60)
        .await;
    assert!(note.contains("hours"), "{note}");
}
