//! `lbctl invoke intake` against moto and the fake EvalAI: the handler runs in-process as the
//! Lambda would, its result or its Lambda error object on stdout.

use crate::common;

use aws_sdk_dynamodb::types::AttributeValue;
use common::{lbctl, show};
use fake_evalai::Fixture;
use serde_json::{json, Value};

#[tokio::test]
#[ignore = "needs moto"]
async fn invoke_intake_claims_a_submission_and_reports_errors_as_lambda_does() {
    let (stack, env) = common::stack(Fixture::default()).await;
    let image = "342236305043.dkr.ecr.us-west-2.amazonaws.com/team-one:agent-v1";
    // Pushed: Intake pins the tag to its digest.
    let digest = local_stack::registry::push(&stack.sdk, image)
        .await
        .unwrap()
        .unwrap();
    let pinned = format!("342236305043.dkr.ecr.us-west-2.amazonaws.com/team-one@{digest}");

    // The happy run, from a file: the Pipe's batch of one, as EvalAI sends a new submission.
    let dir = tempfile::tempdir().unwrap();
    let event = dir.path().join("intake.json");
    std::fs::write(
        &event,
        json!({
            "message": [{"challenge_pk": "1", "phase_pk": "1", "submission_pk": 1,
                         "submitted_image_uri": image}],
            "execution": "invoke-test-1",
        })
        .to_string(),
    )
    .unwrap();
    let out = lbctl(
        &["invoke", "intake", "--event", event.to_str().unwrap()],
        &env,
        None,
    );
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    let result: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(result["action"], "run", "{result}");
    // Its metrics document, beside the result and not in it: an arrival on leaderboard 2.0.
    let stderr = String::from_utf8_lossy(&out.stderr);
    let document = stderr
        .lines()
        .find(|l| l.contains("\"CloudWatchMetrics\""))
        .unwrap_or_else(|| panic!("no metrics document: {}", show(&out)));
    let document: Value = serde_json::from_str(document).unwrap();
    assert_eq!(
        (
            document["Arrivals"].as_f64(),
            document["Leaderboard"].as_str()
        ),
        (Some(1.0), Some("2.0"))
    );
    assert_eq!(result["submission"]["team_id"], 1, "{result}");
    assert_eq!(result["submission"]["image"], pinned, "{result}");
    assert_eq!(result["submission"]["workers"], 4, "{result}");
    let record = aws_sdk_dynamodb::Client::new(&stack.sdk)
        .get_item()
        .table_name("leaderboard-20-submissions")
        .key("team_id", AttributeValue::S("1".into()))
        .key("submission_id", AttributeValue::S("1".into()))
        .send()
        .await
        .unwrap()
        .item
        .expect("Intake wrote the record");
    assert_eq!(
        record["claimed_by"],
        AttributeValue::S("invoke-test-1".into())
    );
    assert_eq!(
        record["submission_status"],
        AttributeValue::S("SUBMITTED".into())
    );

    // Function errors, from stdin: the name the state machine matches, a non-zero exit.
    for (message, name, words) in [
        (
            json!({"challenge_pk": 1, "phase_pk": 99, "submission_pk": 2}),
            "UnknownPhase",
            "`99`",
        ),
        (
            json!({"challenge_pk": 1, "phase_pk": 2, "submission_pk": 2}),
            "PhaseMismatch",
            "phase `2`",
        ),
        (
            json!({"challenge_pk": true, "phase_pk": 1, "submission_pk": 2}),
            "InvalidMessage",
            "`challenge_pk`",
        ),
        // A Pipe whose batch is empty, or whose batch size is not 1.
        (json!([]), "InvalidBatch", "holds 0 messages"),
        (
            json!([{"challenge_pk": 1, "phase_pk": 1, "submission_pk": 2},
                   {"challenge_pk": 1, "phase_pk": 1, "submission_pk": 3}]),
            "InvalidBatch",
            "batch size to 1",
        ),
    ] {
        let event = json!({"message": message, "execution": "invoke-test-2"}).to_string();
        let out = lbctl(&["invoke", "intake"], &env, Some(&event));
        assert_eq!(out.status.code(), Some(1), "{name}: {}", show(&out));
        let error: Value = serde_json::from_slice(&out.stdout)
            .unwrap_or_else(|e| panic!("{name}: {e}: {}", show(&out)));
        assert_eq!(error["errorType"], name, "{error}");
        let text = error["errorMessage"].as_str().unwrap();
        assert!(text.contains(words), "{name}: {error}");
        assert_eq!(error.as_object().unwrap().len(), 2, "{error}");
    }

    // A Lambda event the handler does not take.
    let out = lbctl(&["invoke", "intake"], &env, Some(r#"{"execution": "x"}"#));
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    let error: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(error["errorType"], "InvalidInput", "{error}");
}
