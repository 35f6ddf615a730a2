//! The conditional writes, offline: each sends the condition that makes it safe, and reads a
//! refusal (`ConditionalCheckFailedException`, a cancelled transaction) as the answer it is,
//! never as a failure. The same writes run against moto in `moto.rs`, `admission.rs`,
//! `budget.rs` and the wake tests; here DynamoDB answers as scripted (`aws-smithy-mocks`).

use std::collections::HashMap;
use std::time::Duration;

use aws_sdk_dynamodb::error::ErrorMetadata;
use aws_sdk_dynamodb::operation::get_item::GetItemOutput;
use aws_sdk_dynamodb::operation::put_item::{PutItemError, PutItemOutput};
use aws_sdk_dynamodb::operation::transact_write_items::{
    TransactWriteItemsError, TransactWriteItemsOutput,
};
use aws_sdk_dynamodb::operation::update_item::{UpdateItemError, UpdateItemOutput};
use aws_sdk_dynamodb::types::error::{
    ConditionalCheckFailedException, InternalServerError, TransactionCanceledException,
};
use aws_sdk_dynamodb::types::{AttributeValue, CancellationReason};
use aws_sdk_dynamodb::Client;
use aws_smithy_mocks::{mock, mock_client, Rule, RuleMode};
use lb_aws::admission::{AdmissionTable, Admit};
use lb_aws::budget::BudgetTable;
use lb_aws::dynamo::RecordStatus;
use lb_aws::dynamo::{Claim, NewRecord, SubmissionsTable};
use lb_aws::wake::WakeTable;
use lb_domain::capacity::queue::{Entry, EntryState};
use lb_evalai::{Admission, BudgetPolicy, Priority};

fn client(rules: &[&Rule]) -> Client {
    mock_client!(aws_sdk_dynamodb, RuleMode::Sequential, rules)
}

fn s(v: &str) -> AttributeValue {
    AttributeValue::S(v.into())
}

/// The refusal as the SDK parses DynamoDB's answer: the modeled error, with its code.
fn condition_refused() -> ConditionalCheckFailedException {
    ConditionalCheckFailedException::builder()
        .meta(
            ErrorMetadata::builder()
                .code("ConditionalCheckFailedException")
                .build(),
        )
        .build()
}

fn refused_put() -> Rule {
    mock!(Client::put_item)
        .then_error(|| PutItemError::ConditionalCheckFailedException(condition_refused()))
}

fn refused_update() -> Rule {
    mock!(Client::update_item)
        .then_error(|| UpdateItemError::ConditionalCheckFailedException(condition_refused()))
}

fn record(claimed_by: &str) -> NewRecord {
    NewRecord {
        team_id: 5,
        submission_id: 42,
        team_name: "Team".into(),
        track_id: 1234,
        track_name: "SENSORS".into(),
        image: "registry/team:1".into(),
        workers: 4,
        submitted_time: "2026-11-25 10:00:00 UTC".into(),
        claimed_by: claimed_by.into(),
        resuming: false,
    }
}

fn standing(claimed_by: &str) -> Rule {
    let claimed_by = claimed_by.to_string();
    mock!(Client::get_item).then_output(move || {
        GetItemOutput::builder()
            .set_item(Some(HashMap::from([
                ("claimed_by".to_string(), s(&claimed_by)),
                ("submission_status".to_string(), s("RUNNING")),
            ])))
            .build()
    })
}

#[tokio::test]
async fn the_claim_is_conditional_and_a_refusal_is_a_duplicate_unless_the_claim_is_ours() {
    let conditional = mock!(Client::put_item)
        .match_requests(|r| r.condition_expression() == Some("attribute_not_exists(submission_id)"))
        .then_output(|| PutItemOutput::builder().build());
    let table = SubmissionsTable::new(client(&[&conditional]), "subs");
    assert_eq!(
        table.claim(&record("exec-1")).await.unwrap(),
        Claim::Claimed
    );
    assert_eq!(conditional.num_calls(), 1);

    let (refused, other) = (refused_put(), standing("exec-0"));
    let table = SubmissionsTable::new(client(&[&refused, &other]), "subs");
    assert_eq!(
        table.claim(&record("exec-1")).await.unwrap(),
        Claim::Duplicate {
            status: Some(RecordStatus::Running),
            claimed_by: Some("exec-0".into())
        }
    );

    // A Lambda retry of the claiming execution: its own earlier write stands.
    let (refused, ours) = (refused_put(), standing("exec-1"));
    let table = SubmissionsTable::new(client(&[&refused, &ours]), "subs");
    assert_eq!(
        table.claim(&record("exec-1")).await.unwrap(),
        Claim::Claimed
    );
}

fn waiting(submission_id: u64) -> Entry {
    Entry {
        submission_id,
        team_id: 5,
        arrived_ms: 1_000,
        state: EntryState::Waiting,
    }
}

/// The entry as the table holds it after a refused transaction.
fn entry_item(state: &str) -> Rule {
    let state = state.to_string();
    mock!(Client::get_item)
        .match_requests(|r| r.key().and_then(|k| k.get("key")) == Some(&s("submission#3")))
        .then_output(move || {
            GetItemOutput::builder()
                .set_item(Some(HashMap::from([
                    ("submission_id".to_string(), AttributeValue::N("3".into())),
                    ("team_id".to_string(), AttributeValue::N("5".into())),
                    ("arrived_ms".to_string(), AttributeValue::N("1000".into())),
                    ("state".to_string(), s(&state)),
                ])))
                .build()
        })
}

#[tokio::test]
async fn a_turn_is_one_transaction_on_the_team_s_count_and_the_entry_s_state() {
    let both = mock!(Client::transact_write_items)
        .match_requests(|r| {
            let items = r.transact_items();
            let conditions: Vec<&str> = items
                .iter()
                .filter_map(|i| i.update()?.condition_expression())
                .collect();
            items.len() == 2
                && conditions[0].contains("size(#holders) < :limit")
                && conditions[0].contains("contains(#holders, :id)")
                && conditions[1] == "#state = :waiting"
        })
        .then_output(|| TransactWriteItemsOutput::builder().build());
    let table = AdmissionTable::new(client(&[&both]), "admission");
    let admit = table.admit("2.0", &waiting(3), 2).await.unwrap();
    assert_eq!(admit, Admit::Admitted);
    assert_eq!(both.num_calls(), 1);

    // The team is full: the transaction is cancelled, the entry still waits, and each holder's
    // entry is there: held, nothing dropped.
    let refused = mock!(Client::transact_write_items).then_error(|| {
        TransactWriteItemsError::TransactionCanceledException(
            TransactionCanceledException::builder()
                .cancellation_reasons(
                    CancellationReason::builder()
                        .code("ConditionalCheckFailed")
                        .build(),
                )
                .cancellation_reasons(CancellationReason::builder().code("None").build())
                .build(),
        )
    });
    let still_waiting = entry_item("waiting");
    let holders = mock!(Client::get_item).then_output(|| {
        GetItemOutput::builder()
            .set_item(Some(HashMap::from([(
                "holders".to_string(),
                AttributeValue::Ss(vec!["1".into(), "2".into()]),
            )])))
            .build()
    });
    let holder_entry = |id: &'static str| {
        mock!(Client::get_item)
            .match_requests(move |r| {
                r.key().and_then(|k| k.get("key")) == Some(&s(&format!("submission#{id}")))
            })
            .then_output(|| {
                GetItemOutput::builder()
                    .set_item(Some(HashMap::from([("state".to_string(), s("running"))])))
                    .build()
            })
    };
    let (first, second) = (holder_entry("1"), holder_entry("2"));
    let table = AdmissionTable::new(
        client(&[&refused, &still_waiting, &holders, &first, &second]),
        "admission",
    );
    let admit = table.admit("2.0", &waiting(3), 2).await.unwrap();
    assert_eq!(admit, Admit::Held);
    assert_eq!(
        (
            refused.num_calls(),
            still_waiting.num_calls(),
            holders.num_calls(),
            first.num_calls() + second.num_calls()
        ),
        (1, 1, 1, 2)
    );
}

#[tokio::test]
async fn a_full_window_refuses_a_routine_request_and_a_budget_error_is_not_a_refusal() {
    let policy = BudgetPolicy::evalai(60).unwrap();
    let routine = policy.limit(Priority::Routine);
    let counted = mock!(Client::update_item)
        .match_requests(move |r| {
            r.condition_expression()
                == Some("attribute_not_exists(#requests) OR #requests <= :most")
                && r.expression_attribute_values().and_then(|v| v.get(":most"))
                    == Some(&AttributeValue::N((routine - 1).to_string()))
        })
        .then_output(|| UpdateItemOutput::builder().build());
    let budget = BudgetTable::new(client(&[&counted]), "budget", policy);
    let now_ms = || {
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_millis() as u64
    };
    assert_eq!(
        budget.take_by(Priority::Routine, 1, 1, &now_ms).await,
        Admission::Granted
    );

    let full = refused_update();
    let budget = BudgetTable::new(client(&[&full]), "budget", policy);
    assert!(matches!(
        budget.take_by(Priority::Routine, 1, 0, &now_ms).await,
        Admission::Full { retry_in } if retry_in <= Duration::from_secs(12)
    ));

    // The table failing is no answer about the window: the request is not held back for it.
    let broken = mock!(Client::update_item).then_error(|| {
        UpdateItemError::InternalServerError(
            InternalServerError::builder()
                .meta(ErrorMetadata::builder().code("InternalServerError").build())
                .build(),
        )
    });
    let budget = BudgetTable::new(client(&[&broken]), "budget", policy);
    assert!(matches!(
        budget.take_by(Priority::Routine, 1, 0, &now_ms).await,
        Admission::Unavailable(_)
    ));
}

#[tokio::test]
async fn the_sweep_flags_only_a_waiting_unflagged_submission() {
    let flagged = mock!(Client::update_item)
        .match_requests(|r| {
            r.condition_expression()
                == Some("attribute_exists(#challenge) AND attribute_not_exists(#cancel)")
        })
        .then_output(|| {
            UpdateItemOutput::builder()
                .set_attributes(Some(HashMap::from([
                    ("token".to_string(), s("token-1")),
                    ("execution".to_string(), s("exec-1")),
                ])))
                .build()
        });
    let wakes = WakeTable::new(client(&[&flagged]), "wakes");
    let taken = wakes.flag_cancel(42).await.unwrap().unwrap().unwrap();
    assert_eq!(
        (taken.token.as_str(), taken.execution.as_deref()),
        ("token-1", Some("exec-1"))
    );

    let refused = refused_update();
    let wakes = WakeTable::new(client(&[&refused]), "wakes");
    assert_eq!(wakes.flag_cancel(42).await.unwrap(), None);
}
