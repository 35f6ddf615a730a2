//! The conditional writes, offline: each sends the condition that makes it safe, and reads a
//! refusal (`ConditionalCheckFailedException`, a cancelled transaction) as the answer it is,
//! never as a failure. The same writes run against moto in `moto.rs`, `admission.rs`,
//! `budget.rs` and the wake tests; here DynamoDB answers as scripted, in its own wire format
//! (the JSON protocol's bodies and error types), through the SDK's whole stack.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use aws_sdk_dynamodb::config::{BehaviorVersion, Credentials, Region};
use aws_sdk_dynamodb::Client;
use aws_smithy_runtime_api::client::http::{
    HttpClient, HttpConnector, HttpConnectorFuture, HttpConnectorSettings, SharedHttpConnector,
};
use aws_smithy_runtime_api::client::orchestrator::{HttpRequest, HttpResponse};
use aws_smithy_runtime_api::client::runtime_components::RuntimeComponents;
use aws_smithy_types::body::SdkBody;
use aws_smithy_types::retry::RetryConfig;
use lb_aws::admission::{AdmissionTable, Admit};
use lb_aws::budget::BudgetTable;
use lb_aws::dynamo::RecordStatus;
use lb_aws::dynamo::{Claim, NewRecord, SubmissionsTable};
use lb_aws::wake::WakeTable;
use lb_domain::capacity::queue::{Entry, EntryState};
use lb_evalai::{Admission, BudgetPolicy, Priority};
use serde_json::{json, Value};

/// One request as DynamoDB gets it: the operation (`PutItem`, ...) and its JSON body.
#[derive(Debug, Clone)]
struct Call {
    operation: String,
    body: Value,
}

/// DynamoDB's answer: the HTTP status and the JSON body.
type Answer = (u16, Value);

/// A DynamoDB that answers each call as the test says, and keeps the calls.
#[derive(Clone)]
struct Script {
    answer: Arc<dyn Fn(&Call) -> Answer + Send + Sync>,
    calls: Arc<Mutex<Vec<Call>>>,
}

impl std::fmt::Debug for Script {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Script")
    }
}

impl HttpConnector for Script {
    fn call(&self, request: HttpRequest) -> HttpConnectorFuture {
        let target = request.headers().get("x-amz-target").unwrap_or_default();
        let operation = target.rsplit('.').next().unwrap_or_default().to_string();
        let body = request.body().bytes().unwrap_or_default();
        let call = Call {
            operation,
            body: serde_json::from_slice(body).unwrap_or(Value::Null),
        };
        let (status, answer) = (self.answer)(&call);
        self.calls.lock().unwrap().push(call);
        let status = status.try_into().expect("an HTTP status");
        let response = HttpResponse::new(status, SdkBody::from(answer.to_string()));
        HttpConnectorFuture::ready(Ok(response))
    }
}

impl HttpClient for Script {
    fn http_connector(
        &self,
        _: &HttpConnectorSettings,
        _: &RuntimeComponents,
    ) -> SharedHttpConnector {
        SharedHttpConnector::new(self.clone())
    }
}

impl Script {
    /// The operations called, in order.
    fn operations(&self) -> Vec<String> {
        let calls = self.calls.lock().unwrap();
        calls.iter().map(|c| c.operation.clone()).collect()
    }

    /// The calls of `operation`.
    fn calls_of(&self, operation: &str) -> Vec<Call> {
        let calls = self.calls.lock().unwrap();
        calls
            .iter()
            .filter(|c| c.operation == operation)
            .cloned()
            .collect()
    }
}

/// A client of a DynamoDB that answers with `answer`, without retries (a refusal is answered
/// once; a server error is the caller's to read).
fn dynamodb(answer: impl Fn(&Call) -> Answer + Send + Sync + 'static) -> (Client, Script) {
    let script = Script {
        answer: Arc::new(answer),
        calls: Arc::default(),
    };
    let config = aws_sdk_dynamodb::Config::builder()
        .behavior_version(BehaviorVersion::latest())
        .region(Region::new("us-east-1"))
        .credentials_provider(Credentials::new("AKID", "secret", None, None, "test"))
        .retry_config(RetryConfig::disabled())
        .http_client(script.clone())
        .build();
    (Client::from_conf(config), script)
}

/// DynamoDB's error answer of `kind` (`ConditionalCheckFailedException`, ...).
fn error(status: u16, kind: &str, more: Value) -> Answer {
    let mut body = json!({
        "__type": format!("com.amazonaws.dynamodb.v20120810#{kind}"),
        "message": "as scripted",
    });
    if let (Some(body), Value::Object(more)) = (body.as_object_mut(), more) {
        body.extend(more);
    }
    (status, body)
}

fn condition_refused() -> Answer {
    error(400, "ConditionalCheckFailedException", json!({}))
}

fn ok(body: Value) -> Answer {
    (200, body)
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

/// A claim whose conditional write is refused, and the record read then shows `claimed_by`.
fn claimed_by(holder: &'static str) -> impl Fn(&Call) -> Answer + Send + Sync {
    move |call| match call.operation.as_str() {
        "PutItem" => condition_refused(),
        "GetItem" => ok(json!({"Item": {
            "claimed_by": {"S": holder},
            "submission_status": {"S": "RUNNING"},
        }})),
        other => panic!("unexpected {other}"),
    }
}

#[tokio::test]
async fn the_claim_is_conditional_and_a_refusal_is_a_duplicate_unless_the_claim_is_ours() {
    let (client, script) = dynamodb(|_| ok(json!({})));
    let table = SubmissionsTable::new(client, "subs");
    assert_eq!(
        table.claim(&record("exec-1")).await.unwrap(),
        Claim::Claimed
    );
    let puts = script.calls_of("PutItem");
    assert_eq!(script.operations(), ["PutItem"]);
    assert_eq!(
        puts[0].body["ConditionExpression"],
        "attribute_not_exists(submission_id)"
    );

    let (client, script) = dynamodb(claimed_by("exec-0"));
    let table = SubmissionsTable::new(client, "subs");
    assert_eq!(
        table.claim(&record("exec-1")).await.unwrap(),
        Claim::Duplicate {
            status: Some(RecordStatus::Running),
            claimed_by: Some("exec-0".into())
        }
    );
    assert_eq!(script.operations(), ["PutItem", "GetItem"]);

    // A Lambda retry of the claiming execution: its own earlier write stands.
    let (client, _) = dynamodb(claimed_by("exec-1"));
    let table = SubmissionsTable::new(client, "subs");
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

/// The key a GetItem of the admission table asks for.
fn key_of(call: &Call) -> &str {
    call.body["Key"]["key"]["S"].as_str().unwrap_or_default()
}

#[tokio::test]
async fn a_turn_is_one_transaction_on_the_team_s_count_and_the_entry_s_state() {
    let (client, script) = dynamodb(|_| ok(json!({})));
    let table = AdmissionTable::new(client, "admission");
    let admit = table.admit("2.0", &waiting(3), 2).await.unwrap();
    assert_eq!(admit, Admit::Admitted);
    assert_eq!(script.operations(), ["TransactWriteItems"]);
    let sent = &script.calls_of("TransactWriteItems")[0].body;
    let items = sent["TransactItems"].as_array().unwrap();
    let condition = |i: usize| items[i]["Update"]["ConditionExpression"].as_str().unwrap();
    assert_eq!(items.len(), 2, "{sent}");
    assert!(condition(0).contains("size(#holders) < :limit"), "{sent}");
    assert!(condition(0).contains("contains(#holders, :id)"), "{sent}");
    assert_eq!(condition(1), "#state = :waiting");

    // The team is full: the transaction is cancelled, the entry still waits, and each holder's
    // entry is there: held, nothing dropped.
    let (client, script) = dynamodb(|call| match call.operation.as_str() {
        "TransactWriteItems" => error(
            400,
            "TransactionCanceledException",
            json!({"CancellationReasons": [
                {"Code": "ConditionalCheckFailed", "Message": "The conditional request failed"},
                {"Code": "None"},
            ]}),
        ),
        "GetItem" => ok(match key_of(call) {
            "submission#3" => json!({"Item": {
                "submission_id": {"N": "3"}, "team_id": {"N": "5"},
                "arrived_ms": {"N": "1000"}, "state": {"S": "waiting"},
            }}),
            "submission#1" | "submission#2" => json!({"Item": {"state": {"S": "running"}}}),
            "team#5" => json!({"Item": {"holders": {"SS": ["1", "2"]}}}),
            other => panic!("unexpected read of {other}"),
        }),
        other => panic!("unexpected {other}"),
    });
    let table = AdmissionTable::new(client, "admission");
    let admit = table.admit("2.0", &waiting(3), 2).await.unwrap();
    assert_eq!(admit, Admit::Held);
    let mut read: Vec<String> = (script.calls_of("GetItem").iter())
        .map(|c| key_of(c).to_string())
        .collect();
    read.sort();
    assert_eq!(script.calls_of("TransactWriteItems").len(), 1);
    assert_eq!(
        read,
        ["submission#1", "submission#2", "submission#3", "team#5"]
    );
}

#[tokio::test]
async fn a_full_window_refuses_a_routine_request_and_a_budget_error_is_not_a_refusal() {
    let policy = BudgetPolicy::evalai(60).unwrap();
    let routine = policy.limit(Priority::Routine);
    let now_ms = || {
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_millis() as u64
    };
    let (client, script) = dynamodb(|_| ok(json!({})));
    let budget = BudgetTable::new(client, "budget", policy);
    assert_eq!(
        budget.take_by(Priority::Routine, 1, 1, &now_ms).await,
        Admission::Granted
    );
    let counted = &script.calls_of("UpdateItem")[0].body;
    assert_eq!(
        counted["ConditionExpression"],
        "attribute_not_exists(#requests) OR #requests <= :most"
    );
    let most = (routine - 1).to_string();
    assert_eq!(
        counted["ExpressionAttributeValues"][":most"]["N"],
        most.as_str()
    );

    let (client, _) = dynamodb(|_| condition_refused());
    let budget = BudgetTable::new(client, "budget", policy);
    assert!(matches!(
        budget.take_by(Priority::Routine, 1, 0, &now_ms).await,
        Admission::Full { retry_in } if retry_in <= Duration::from_secs(12)
    ));

    // The table failing is no answer about the window: the request is not held back for it.
    let (client, _) = dynamodb(|_| error(500, "InternalServerError", json!({})));
    let budget = BudgetTable::new(client, "budget", policy);
    assert!(matches!(
        budget.take_by(Priority::Routine, 1, 0, &now_ms).await,
        Admission::Unavailable(_)
    ));
}

#[tokio::test]
async fn the_sweep_flags_only_a_waiting_unflagged_submission() {
    let (client, script) = dynamodb(|_| {
        ok(json!({"Attributes": {
            "token": {"S": "token-1"},
            "execution": {"S": "exec-1"},
        }}))
    });
    let wakes = WakeTable::new(client, "wakes");
    let taken = wakes.flag_cancel(42).await.unwrap().unwrap().unwrap();
    assert_eq!(
        (taken.token.as_str(), taken.execution.as_deref()),
        ("token-1", Some("exec-1"))
    );
    assert_eq!(
        script.calls_of("UpdateItem")[0].body["ConditionExpression"],
        "attribute_exists(#challenge) AND attribute_not_exists(#cancel)"
    );

    let (client, _) = dynamodb(|_| condition_refused());
    let wakes = WakeTable::new(client, "wakes");
    assert_eq!(wakes.flag_cancel(42).await.unwrap(), None);
}
