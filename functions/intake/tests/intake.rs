//! Intake against the local stack: moto for Secrets Manager and DynamoDB, the fake EvalAI.

use aws_sdk_dynamodb::types::AttributeValue;
use fake_evalai::{Faults, Fixture};
use intake::{handle, Deps};
use lb_pipeline::payload::{Action, IntakeInput};
use local_stack::stack::LOCAL_SETTINGS;
use local_stack::Stack;
use serde_json::json;

async fn stack(settings: &str) -> (Stack, Deps) {
    let (stack, _) = test_support::stack::provisioned_with(Fixture::default(), settings).await;
    let config = local_stack::stack::function_config();
    let deps = Deps::load(&stack.sdk, &config).await.unwrap();
    (stack, deps)
}

fn input(message: serde_json::Value, execution: &str) -> IntakeInput {
    IntakeInput {
        message,
        execution: execution.into(),
    }
}

async fn record(
    stack: &Stack,
    team: u64,
    submission: u64,
) -> Option<std::collections::HashMap<String, AttributeValue>> {
    aws_sdk_dynamodb::Client::new(&stack.sdk)
        .get_item()
        .table_name("leaderboard-20-submissions")
        .key("team_id", AttributeValue::S(team.to_string()))
        .key("submission_id", AttributeValue::S(submission.to_string()))
        .send()
        .await
        .unwrap()
        .item
}

#[tokio::test]
#[ignore = "needs moto"]
async fn an_ecr_tag_is_pinned_to_its_digest_and_a_tag_never_pushed_is_refused_at_once() {
    let (stack, deps) = stack(LOCAL_SETTINGS).await;
    let tag = "123456789012.dkr.ecr.us-west-2.amazonaws.com/team-one:v7";
    let digest = local_stack::registry::push(&stack.sdk, tag)
        .await
        .unwrap()
        .unwrap();
    let message = |submission: u64, image: &str| {
        json!({"challenge_pk": 1, "phase_pk": 1, "submission_pk": submission,
               "submitted_image_uri": image})
    };
    let out = handle(input(message(1, tag), "exec-1"), &deps)
        .await
        .unwrap();
    assert_eq!(out.action(), Action::Run, "{out:?}");
    // The Jobs run the digest; the record keeps what the participant submitted.
    let info = out.submission().cloned().unwrap();
    assert_eq!(
        info.image,
        format!("123456789012.dkr.ecr.us-west-2.amazonaws.com/team-one@{digest}")
    );
    let item = record(&stack, 1, 1).await.unwrap();
    assert_eq!(item["submitted_image_uri"], AttributeValue::S(tag.into()));

    // A tag the registry does not have: refused before anything is claimed, saying so.
    let never = "123456789012.dkr.ecr.us-west-2.amazonaws.com/team-one:never-pushed";
    let second = stack
        .fake()
        .add_submission(fake_evalai::NewSubmission {
            challenge_phase: 1,
            participant_team: 1,
            submitted_image_uri: never.into(),
            created_by: None,
            submission_metadata: None,
        })
        .unwrap()
        .id;
    let out = handle(input(message(second, never), "exec-2"), &deps)
        .await
        .unwrap();
    assert_eq!(out.action(), Action::Reject, "{out:?}");
    let reason = out.reason().unwrap();
    assert!(
        reason.contains(never) && reason.contains("not in its registry"),
        "{reason}"
    );
    assert!(record(&stack, 1, second).await.is_none(), "nothing claimed");
}

#[tokio::test]
#[ignore = "needs moto"]
async fn a_new_submission_is_claimed_once_and_a_duplicate_delivery_skipped() {
    let (stack, deps) = stack(LOCAL_SETTINGS).await;
    // As EvalAI publishes a new submission: string challenge/phase ids, int submission id.
    let message = json!({"challenge_pk": "1", "phase_pk": "1", "submission_pk": 1,
                         "is_static_dataset_code_upload_submission": false,
                         "submitted_image_uri": "123.dkr.ecr.us-west-2.amazonaws.com/team-one:1"});
    let out = handle(input(message.clone(), "exec-1"), &deps)
        .await
        .unwrap();
    assert_eq!(out.action(), Action::Run, "{out:?}");
    let info = out.submission().cloned().unwrap();
    assert_eq!((info.team_id, info.team_name.as_str()), (1, "Team One"));
    assert_eq!(
        (info.leaderboard.as_str(), info.track.as_str()),
        ("2.0", "SENSORS")
    );
    assert_eq!((info.routes, info.workers), (20, 4));
    assert_eq!(info.image, "123.dkr.ecr.us-west-2.amazonaws.com/team-one:1");
    let item = record(&stack, 1, 1).await.expect("claimed");
    assert_eq!(
        item["submission_status"],
        AttributeValue::S("SUBMITTED".into())
    );
    assert_eq!(item["claimed_by"], AttributeValue::S("exec-1".into()));

    let again = handle(input(message, "exec-2"), &deps).await.unwrap();
    assert_eq!(again.action(), Action::Skip);
    assert!(again.reason().unwrap().contains("duplicate"));
    assert_eq!(
        record(&stack, 1, 1).await.unwrap()["claimed_by"],
        AttributeValue::S("exec-1".into())
    );
}

#[tokio::test]
#[ignore = "needs moto"]
async fn a_message_without_image_uses_the_input_file_and_the_override_sets_workers() {
    let (stack, deps) = stack(LOCAL_SETTINGS).await;
    aws_sdk_dynamodb::Client::new(&stack.sdk)
        .put_item()
        .table_name("leaderboard-20-submissions")
        .item("team_id", AttributeValue::S("1".into()))
        .item("submission_id", AttributeValue::S("1".into()))
        // The original system's (and operators') override: a string.
        .item("parallelization_workers", AttributeValue::S("2".into()))
        .item("submission_status", AttributeValue::S("FAILED".into()))
        .send()
        .await
        .unwrap();
    // Not failed on EvalAI: the fake refuses, as EvalAI does.
    stack.fake().resume(1).unwrap_err();
    // The fake's input file holds the image the participant pushed (to the registry too).
    let pushed = stack
        .fake()
        .submission(1)
        .unwrap()
        .submitted_image_uri
        .unwrap();
    let digest = local_stack::registry::push(&stack.sdk, &pushed)
        .await
        .unwrap()
        .unwrap();
    let message = json!({"challenge_pk": 1, "phase_pk": 1, "submission_pk": 1});
    let out = handle(input(message, "exec-1"), &deps).await.unwrap();
    let info = out.submission().cloned().unwrap();
    let repository = pushed.rsplit_once(':').unwrap().0;
    assert_eq!(info.image, format!("{repository}@{digest}"));
    assert_eq!(
        out.action(),
        Action::Skip,
        "a record exists and EvalAI says submitted, not resuming"
    );
    assert_eq!(
        info.workers, 2,
        "the operator's override wins over the track's 4"
    );
}

#[tokio::test]
#[ignore = "needs moto"]
async fn bad_messages_unknown_phases_and_missing_submissions_are_named_errors_with_nothing_claimed()
{
    let (stack, deps) = stack(LOCAL_SETTINGS).await;
    let cases = [
        (
            json!({"challenge_pk": 1, "submission_pk": 1}),
            "InvalidMessage",
        ),
        (
            json!({"challenge_pk": 1, "phase_pk": "one", "submission_pk": 1}),
            "InvalidMessage",
        ),
        (
            json!({"challenge_pk": 1, "phase_pk": 1, "submission_pk": 1, "submitted_image_uri": 7}),
            "InvalidMessage",
        ),
        (json!("not an object"), "InvalidMessage"),
        (
            json!({"challenge_pk": 1, "phase_pk": 99, "submission_pk": 1}),
            "UnknownPhase",
        ),
        (
            json!({"challenge_pk": 1, "phase_pk": 1, "submission_pk": 999}),
            "SubmissionNotFound",
        ),
        (
            json!({"challenge_pk": 1, "phase_pk": 2, "submission_pk": 1}),
            "PhaseMismatch",
        ),
    ];
    for (message, name) in cases {
        let err = handle(input(message.clone(), "exec"), &deps)
            .await
            .unwrap_err();
        assert_eq!(err.name(), name, "{message}: {err}");
        assert!(!err.is_transient());
    }
    assert!(record(&stack, 1, 1).await.is_none(), "nothing was claimed");
}

#[tokio::test]
#[ignore = "needs moto"]
async fn an_ineligible_status_is_skipped_and_an_unqualified_team_rejected() {
    let gated = LOCAL_SETTINGS.replace(r#""enabled": false"#, r#""enabled": true"#);
    let (stack, deps) = stack(&gated).await;
    let message = json!({"challenge_pk": 1, "phase_pk": 1, "submission_pk": 1, "submitted_image_uri": "img:1"});

    let out = handle(input(message.clone(), "exec"), &deps).await.unwrap();
    assert_eq!(out.action(), Action::Reject);
    assert!(out
        .reason()
        .unwrap()
        .contains("qualifier track `SENSORS_QUALIFIER`"));
    assert!(record(&stack, 1, 1).await.is_none());

    // The pass as the original system recorded it: the team may now enter `SENSORS`.
    aws_sdk_dynamodb::Client::new(&stack.sdk)
        .put_item()
        .table_name("leaderboard-20-qualifier")
        .item("team_id", AttributeValue::S("1".into()))
        .item("track_codename", AttributeValue::S("SENSORS".into()))
        .item("submission_id", AttributeValue::S("9".into()))
        .send()
        .await
        .unwrap();
    assert_eq!(
        handle(input(message.clone(), "exec"), &deps)
            .await
            .unwrap()
            .action(),
        Action::Run
    );

    stack.fake().cancel(1).unwrap();
    let out = handle(input(message, "exec-later"), &deps).await.unwrap();
    assert_eq!(out.action(), Action::Skip);
    assert!(out.reason().unwrap().contains("`cancelled`"));
}

#[tokio::test]
#[ignore = "needs moto"]
async fn evalai_failures_are_transient_errors_the_state_machine_retries() {
    let (stack, deps) = stack(LOCAL_SETTINGS).await;
    stack
        .fake()
        .set_faults(Faults {
            error_500_rate: 1.0,
            ..Faults::default()
        })
        .unwrap();
    let message = json!({"challenge_pk": 1, "phase_pk": 1, "submission_pk": 1, "submitted_image_uri": "img:1"});
    let err = handle(input(message, "exec"), &deps).await.unwrap_err();
    assert_eq!(err.name(), "EvalAiUnavailable");
    assert!(err.is_transient());
    assert!(record(&stack, 1, 1).await.is_none());
}

#[tokio::test]
#[ignore = "needs moto"]
async fn an_invalid_or_oversized_image_is_rejected_before_anything_is_claimed() {
    let (stack, deps) = stack(LOCAL_SETTINGS).await;
    // A 300 KB image string was once claimed, and grew every payload after it past AWS's
    // 256 KiB limit.
    for image in [
        format!(
            "123.dkr.ecr.us-west-2.amazonaws.com/team:{}",
            "a".repeat(300_000)
        ),
        "Team Image With Spaces".to_string(),
    ] {
        let message = json!({"challenge_pk": 1, "phase_pk": 1, "submission_pk": 1,
                             "submitted_image_uri": image});
        let out = handle(input(message, "exec"), &deps).await.unwrap();
        assert_eq!(out.action(), Action::Reject, "{:.300}", format!("{out:?}"));
        let reason = out.reason().unwrap().to_string();
        assert!(
            reason.contains("is not a valid image reference"),
            "{reason:.300}"
        );
        assert!(
            reason.len() < 1024,
            "the reason is bounded: {} bytes",
            reason.len()
        );
        assert!(out.submission().unwrap().image.is_empty());
        assert!(serde_json::to_string(&out).unwrap().len() < 8 * 1024);
        assert!(record(&stack, 1, 1).await.is_none(), "nothing was claimed");
    }
}
