//! `status`, `list`, `cancel`, `submit` and `resume` against moto (DynamoDB, S3, Secrets
//! Manager, Step Functions) and the fake EvalAI, through the `lbctl` binary.

use crate::common;

use std::collections::HashMap;

use aws_sdk_dynamodb::types::AttributeValue;
use common::{lbctl, show, stderr, stdout};
use fake_evalai::Fixture;
use serde_json::{json, Value};

const TABLE_20: &str = "leaderboard-20-submissions";
const TABLE_10: &str = "leaderboard-10-submissions";
const BUCKET_20: &str = "leaderboard-20-results";
const IMAGE: &str = "342236305043.dkr.ecr.us-west-2.amazonaws.com/team-one:agent-v1";

/// A record as Intake, Monitor and Finalize leave it.
async fn put_record(
    sdk: &aws_config::SdkConfig,
    table: &str,
    team: u64,
    submission: u64,
    status: &str,
    extra: &[(&str, AttributeValue)],
) {
    let mut item: HashMap<String, AttributeValue> = [
        // The original layout: keys and its attributes are strings.
        ("team_id", AttributeValue::S(team.to_string())),
        ("submission_id", AttributeValue::S(submission.to_string())),
        ("submission_status", AttributeValue::S(status.into())),
        ("team_name", AttributeValue::S(format!("Team {team}"))),
        ("track_id", AttributeValue::S("1".into())),
        ("track_name", AttributeValue::S("SENSORS".into())),
        ("submitted_image_uri", AttributeValue::S(IMAGE.into())),
        ("parallelization_workers", AttributeValue::S("4".into())),
        (
            "submitted_time",
            AttributeValue::S("2026-01-01 00:00:00 UTC".into()),
        ),
        ("routes_done", AttributeValue::N("5".into())),
        ("routes_total", AttributeValue::N("20".into())),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .collect();
    item.extend(extra.iter().map(|(k, v)| (k.to_string(), v.clone())));
    aws_sdk_dynamodb::Client::new(sdk)
        .put_item()
        .table_name(table)
        .set_item(Some(item))
        .send()
        .await
        .unwrap();
}

async fn put_object(sdk: &aws_config::SdkConfig, bucket: &str, key: &str) {
    lb_aws::s3_client(sdk)
        .put_object()
        .bucket(bucket)
        .key(key)
        .body(Vec::new().into())
        .send()
        .await
        .unwrap();
}

async fn exists(sdk: &aws_config::SdkConfig, bucket: &str, key: &str) -> bool {
    lb_aws::s3_client(sdk)
        .head_object()
        .bucket(bucket)
        .key(key)
        .send()
        .await
        .is_ok()
}

fn cancel_key(submission: u64) -> String {
    format!("{submission}/containers-status/simulation.cancel")
}

/// A state machine in moto's Step Functions; its ARN.
async fn state_machine(sdk: &aws_config::SdkConfig) -> String {
    let definition = json!({"StartAt": "Done", "States": {"Done": {"Type": "Succeed"}}});
    aws_sdk_sfn::Client::new(sdk)
        .create_state_machine()
        .name("submission")
        .definition(definition.to_string())
        .role_arn("arn:aws:iam::123456789012:role/leaderboard-states")
        .send()
        .await
        .unwrap()
        .state_machine_arn
}

/// The execution ARN `lbctl submit`/`resume` printed, and its input as moto stored it.
async fn started_execution(sdk: &aws_config::SdkConfig, out: &str) -> (String, Value) {
    let arn = out
        .lines()
        .find_map(|l| l.trim().strip_prefix("arn"))
        .map(|a| a.trim().to_string())
        .unwrap_or_else(|| panic!("no execution ARN in\n{out}"));
    let described = aws_sdk_sfn::Client::new(sdk)
        .describe_execution()
        .execution_arn(&arn)
        .send()
        .await
        .unwrap();
    let input = serde_json::from_str(described.input().unwrap()).unwrap();
    (arn, input)
}

fn list_ids(text: &str) -> Vec<u64> {
    text.lines()
        .skip(1)
        .filter_map(|l| l.split_whitespace().next()?.parse().ok())
        .collect()
}

#[tokio::test]
#[ignore = "needs moto"]
async fn a_failure_of_the_platform_s_own_is_shown_apart_from_the_participant_s() {
    let (stack, env) = common::stack(Fixture::default()).await;
    let sdk = &stack.sdk;
    let error = (
        "error",
        AttributeValue::S("the platform took its pods away".into()),
    );
    let platform = [
        error.clone(),
        ("failed_by", AttributeValue::S("platform".into())),
    ];
    put_record(sdk, TABLE_20, 1, 201, "FAILED", &platform).await;
    put_record(sdk, TABLE_20, 2, 202, "FAILED", &[error]).await;

    let out = lbctl(&["status", "201"], &env, None);
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    for line in [
        "status       FAILED!",
        "failed by    the platform",
        "`lbctl resume 201` once EvalAI reports it resuming",
    ] {
        assert!(stdout(&out).contains(line), "{line}: {}", show(&out));
    }
    let out = lbctl(&["status", "202"], &env, None);
    assert!(
        stdout(&out).contains("status       FAILED\n"),
        "{}",
        show(&out)
    );
    assert!(!stdout(&out).contains("failed by"), "{}", show(&out));

    let out = lbctl(&["list"], &env, None);
    let text = stdout(&out);
    let line = |id: &str| text.lines().find(|l| l.starts_with(id)).unwrap_or_default();
    assert!(line("201").contains(" FAILED! "), "{text}");
    assert!(line("202").contains(" FAILED "), "{text}");
    assert!(
        text.contains("! failed by the platform's own failure"),
        "{text}"
    );
}

#[tokio::test]
#[ignore = "needs moto"]
async fn status_and_list_show_the_records_and_markers_put_in_the_deployment() {
    let (stack, env) = common::stack(Fixture::default()).await;
    let sdk = &stack.sdk;
    put_record(sdk, TABLE_20, 1, 101, "RUNNING", &[]).await;
    put_record(
        sdk,
        TABLE_20,
        2,
        102,
        "FINISHED",
        &[
            ("driving_score", AttributeValue::S("41.25".into())),
            (
                "end_time",
                AttributeValue::S("2026-01-02 00:00:00 UTC".into()),
            ),
            // Two of its routes have no CARLA recording that passed (Finalize's audit).
            ("recordings_found", AttributeValue::N("18".into())),
            ("recordings_expected", AttributeValue::N("20".into())),
            (
                "recordings_failed",
                AttributeValue::L(vec![
                    AttributeValue::S("RouteScenario_3_rep0: no recording in pair 2's folder".into()),
                    AttributeValue::S("RouteScenario_7_rep0: not a CARLA recording (no CARLA_RECORDER header)\x1b[2J".into()),
                ]),
            ),
            // Its GPUs, as Finalize wrote them.
            ("gpu_seconds", AttributeValue::N("28800".into())),
            ("gpu_seconds_spot", AttributeValue::N("21600".into())),
            ("gpu_seconds_run_again", AttributeValue::N("900".into())),
            ("cost_usd", AttributeValue::N("5.62".into())),
            ("orchestration_usd", AttributeValue::N("0.0312".into())),
            ("state_transitions", AttributeValue::N("1180".into())),
            ("log_bytes_stored", AttributeValue::N("3221225472".into())),
            ("log_objects_stored", AttributeValue::N("14".into())),
            ("uploads_refused", AttributeValue::N("2".into())),
            (
                "image_digest",
                AttributeValue::S(format!("sha256:{}", "d".repeat(64))),
            ),
        ],
    )
    .await;
    put_record(sdk, TABLE_10, 1, 103, "SUBMITTED", &[]).await;
    for marker in [
        "agent-1.crash0",
        "simulator-1.start0",
        "simulator-1.crash0",
        "simulator-1.start1",
    ] {
        put_object(sdk, BUCKET_20, &format!("101/containers-status/{marker}")).await;
    }
    // Names no pod of the protocol writes (beyond any attempt), by the hundred.
    for n in 16..166 {
        put_object(
            sdk,
            BUCKET_20,
            &format!("101/containers-status/simulator-1.start{n}"),
        )
        .await;
    }

    let out = lbctl(&["status", "101"], &env, None);
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    let text = stdout(&out);
    for expected in [
        "submission 101",
        "leaderboard-20-submissions",
        "RUNNING",
        "Team 1 (id 1)",
        "SENSORS (phase 1)",
        "5/20",
        IMAGE,
        "s3://leaderboard-20-results/101/containers-status/",
        "pair 1: simulator started 2, crashed 1; agent crashed 1",
        "150 object(s) that are no marker of the protocol",
    ] {
        assert!(text.contains(expected), "`{expected}` missing:\n{text}");
    }
    // Counted, not listed: the output stays a screen whatever the bucket holds.
    assert!(text.lines().count() < 40, "{text}");
    let out = lbctl(&["status", "101", "--json"], &env, None);
    let status: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(status["markers"][0]["count"], 154, "{status}");
    assert_eq!(status["markers"][0]["names"].as_array().unwrap().len(), 100);

    // A FINISHED result some of whose routes have no recording that passed says so, and
    // which routes and why.
    let out = lbctl(&["status", "102"], &env, None);
    for line in [
        "status       FINISHED*",
        "recordings   18/20 passed (2 route(s) without a CARLA recording that passed the audit: these scores cannot be audited",
        "             RouteScenario_3_rep0: no recording in pair 2's folder\n",
        "             RouteScenario_7_rep0: not a CARLA recording (no CARLA_RECORDER header)",
    ] {
        assert!(stdout(&out).contains(line), "{line}: {}", show(&out));
    }
    assert!(!stdout(&out).contains('\x1b'), "{}", show(&out));
    assert!(
        stdout(&out).contains("GPUs         8.00 GPU-hours (6.00 on Spot, 0.25 run again after reclaims), about $5.62; orchestration about $0.0312"),
        "{}",
        show(&out)
    );
    assert!(
        stdout(&out).contains(&format!("runs digest  sha256:{}", "d".repeat(64))),
        "{}",
        show(&out)
    );
    assert!(
        stdout(&out)
            .contains("logs         3.00 GiB kept in S3 in 14 object(s); 2 file(s) refused"),
        "{}",
        show(&out)
    );
    assert!(
        !stdout(&out).contains("state_transitions"),
        "{}",
        show(&out)
    );
    let out = lbctl(&["status", "101"], &env, None);
    assert!(!stdout(&out).contains("recordings"), "{}", show(&out));
    assert!(!stdout(&out).contains("GPU-hours"), "{}", show(&out));

    let out = lbctl(&["status", "102", "--json"], &env, None);
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    let status: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(status["submission_id"], 102);
    assert_eq!(status["records"][0]["leaderboard"], "2.0");
    assert_eq!(
        status["records"][0]["record"]["submission_status"],
        "FINISHED"
    );
    // As stored: the original layout keeps metrics as strings.
    assert_eq!(status["records"][0]["record"]["driving_score"], "41.25");
    assert_eq!(status["markers"][0]["names"], json!([]));
    assert_eq!(status["markers"][0]["cancel_requested"], false);

    let out = lbctl(&["status", "999"], &env, None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(
        stderr(&out).contains("`999` has no record"),
        "{}",
        show(&out)
    );

    let out = lbctl(&["list"], &env, None);
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    assert_eq!(list_ids(&stdout(&out)), [103, 102, 101], "{}", show(&out));
    assert!(stdout(&out).starts_with("SUBMISSION"), "{}", show(&out));
    assert!(stdout(&out).contains(" FINISHED* "), "{}", show(&out));
    assert!(
        stdout(&out).contains("* some routes have no CARLA recording"),
        "{}",
        show(&out)
    );

    let out = lbctl(&["list", "--running"], &env, None);
    assert_eq!(list_ids(&stdout(&out)), [103, 101], "{}", show(&out));

    let out = lbctl(
        &["list", "--leaderboard", "2.0", "--limit", "1"],
        &env,
        None,
    );
    assert_eq!(list_ids(&stdout(&out)), [102], "{}", show(&out));
    assert!(stdout(&out).contains("1 more"), "{}", show(&out));

    let out = lbctl(&["list", "--leaderboard", "1.0", "--json"], &env, None);
    let listed: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(listed.as_array().unwrap().len(), 1, "{listed}");
    assert_eq!(listed[0]["record"]["submission_id"], "103");
    assert_eq!(listed[0]["queue_position"], 1, "{listed}");
    assert!(listed[0]["age_seconds"].as_i64().unwrap() > 0, "{listed}");

    // Two more waiting in 2.0: the queue follows arrival, per leaderboard.
    for (id, at) in [
        (104, "2026-01-01 00:10:00 UTC"),
        (105, "2026-01-01 00:05:00 UTC"),
    ] {
        put_record(
            sdk,
            TABLE_20,
            3,
            id,
            "SUBMITTED",
            &[("submitted_time", AttributeValue::S(at.into()))],
        )
        .await;
    }
    let out = lbctl(&["list", "--json"], &env, None);
    let listed: Value = serde_json::from_slice(&out.stdout).unwrap();
    let queue: Vec<(String, Value)> = listed
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            (
                r["record"]["submission_id"].as_str().unwrap().to_owned(),
                r["queue_position"].clone(),
            )
        })
        .collect();
    assert_eq!(
        queue,
        [
            ("105".to_owned(), json!(1)),
            ("104".to_owned(), json!(2)),
            ("103".to_owned(), json!(1)),
            ("102".to_owned(), Value::Null),
            ("101".to_owned(), Value::Null),
        ],
        "{listed}"
    );
    let out = lbctl(&["list"], &env, None);
    assert!(
        stdout(&out).contains(" QUEUE STARTS IN    AGE "),
        "{}",
        show(&out)
    );
    // Each team's GPUs under the list, and each submission's in its column.
    assert!(stdout(&out).contains("8.00h $5.62"), "{}", show(&out));
    assert!(
        stdout(&out).contains("team Team 2 (2): 8.00 GPU-hours"),
        "{}",
        show(&out)
    );
    // Filters: a team by id or name, a status in any case.
    let out = lbctl(&["list", "--team", "3"], &env, None);
    assert_eq!(list_ids(&stdout(&out)), [105, 104], "{}", show(&out));
    let out = lbctl(&["list", "--team", "team 2"], &env, None);
    assert_eq!(list_ids(&stdout(&out)), [102], "{}", show(&out));
    let out = lbctl(&["list", "--status", "finished"], &env, None);
    assert_eq!(list_ids(&stdout(&out)), [102], "{}", show(&out));
    let out = lbctl(&["list", "--team", "nobody"], &env, None);
    assert!(stdout(&out).contains("match the filters"), "{}", show(&out));

    let out = lbctl(&["list", "--leaderboard", "3.0"], &env, None);
    assert_eq!(out.status.code(), Some(2), "{}", show(&out));
    assert!(stderr(&out).contains("1.0, 2.0"), "{}", show(&out));

    // One unreadable bucket is reported, and does not hide the rest.
    lb_aws::s3_client(sdk)
        .delete_bucket()
        .bucket("leaderboard-10-results")
        .send()
        .await
        .unwrap();
    let out = lbctl(&["status", "101"], &env, None);
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    assert!(
        stdout(&out).contains("pair 1: simulator started 2"),
        "{}",
        show(&out)
    );
    assert!(stdout(&out).contains("(unreadable: "), "{}", show(&out));
    assert!(
        stderr(&out).contains("warning: listing the markers under `s3://leaderboard-10-results/101/containers-status/`"),
        "{}",
        show(&out)
    );

    // A settings secret that is not there is named.
    let out = lbctl(&["list", "--settings-secret", "nope/settings"], &env, None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(stderr(&out).contains("`nope/settings`"), "{}", show(&out));
}

#[tokio::test]
#[ignore = "needs moto"]
async fn cancel_writes_the_marker_and_refuses_a_final_or_unknown_submission() {
    let (stack, env) = common::stack(Fixture::default()).await;
    let sdk = &stack.sdk;
    put_record(sdk, TABLE_20, 1, 201, "RUNNING", &[]).await;
    put_record(sdk, TABLE_20, 1, 202, "FINISHED", &[]).await;

    let out = lbctl(&["cancel", "201"], &env, None);
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    assert!(exists(sdk, BUCKET_20, &cancel_key(201)).await);
    assert!(
        stdout(&out)
            .contains("s3://leaderboard-20-results/201/containers-status/simulation.cancel"),
        "{}",
        show(&out)
    );
    let out = lbctl(&["status", "201", "--json"], &env, None);
    let status: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(status["markers"][0]["cancel_requested"], true, "{status}");
    let out = lbctl(&["status", "201"], &env, None);
    assert!(
        stdout(&out).contains("simulation.cancel  <- cancel requested"),
        "{}",
        show(&out)
    );

    let out = lbctl(&["cancel", "202"], &env, None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(
        stderr(&out).contains("already final (FINISHED"),
        "{}",
        show(&out)
    );
    assert!(!exists(sdk, BUCKET_20, &cancel_key(202)).await);
    let out = lbctl(&["cancel", "202", "--force"], &env, None);
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    assert!(exists(sdk, BUCKET_20, &cancel_key(202)).await);

    let out = lbctl(&["cancel", "203"], &env, None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(
        stderr(&out).contains("`203` has no record"),
        "{}",
        show(&out)
    );
    let out = lbctl(&["cancel", "203", "--force"], &env, None);
    assert_eq!(out.status.code(), Some(2), "{}", show(&out));
    assert!(stderr(&out).contains("--leaderboard"), "{}", show(&out));
    assert!(!exists(sdk, BUCKET_20, &cancel_key(203)).await);
    let out = lbctl(
        &["cancel", "203", "--force", "--leaderboard", "2.0"],
        &env,
        None,
    );
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    assert!(exists(sdk, BUCKET_20, &cancel_key(203)).await);
}

#[tokio::test]
#[ignore = "needs moto"]
async fn submit_starts_an_execution_with_exactly_the_pipes_input() {
    let (stack, mut env) = common::stack(Fixture::default()).await;
    let arn = state_machine(&stack.sdk).await;

    let args = [
        "submit",
        "--challenge",
        "1",
        "--phase",
        "1",
        "--submission",
        "7",
        "--image",
        IMAGE,
        "--state-machine",
        &arn,
    ];
    let out = lbctl(&args, &env, None);
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    let (execution, input) = started_execution(&stack.sdk, &stdout(&out)).await;
    assert!(
        execution.contains(":execution:submission:submission-7-"),
        "{execution}"
    );
    assert_eq!(
        input,
        json!([{"challenge_pk": 1, "phase_pk": 1, "submission_pk": 7, "submitted_image_uri": IMAGE}])
    );

    // The ARN from the environment, and no image: the template gives null.
    env.push(("LB_STATE_MACHINE_ARN", arn.clone()));
    let out = lbctl(
        &[
            "submit",
            "--challenge",
            "1",
            "--phase",
            "2",
            "--submission",
            "8",
        ],
        &env,
        None,
    );
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    let (_, input) = started_execution(&stack.sdk, &stdout(&out)).await;
    assert_eq!(
        input,
        json!([{"challenge_pk": 1, "phase_pk": 2, "submission_pk": 8, "submitted_image_uri": null}])
    );
    // Started on the state machine itself, not its alias: the operator is told what runs.
    assert!(
        stderr(&out).contains("runs its latest revision, not the version its `live` alias names"),
        "{}",
        show(&out)
    );

    // A state machine that does not exist: the call and the ARN are named.
    let missing = arn.replace(":submission", ":nope");
    let out = lbctl(
        &[
            "submit",
            "--challenge",
            "1",
            "--phase",
            "1",
            "--submission",
            "9",
            "--state-machine",
            &missing,
        ],
        &env,
        None,
    );
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(
        stderr(&out).contains("StartExecution") && stderr(&out).contains(&missing),
        "{}",
        show(&out)
    );
}

#[tokio::test]
#[ignore = "needs moto"]
async fn resume_clears_the_cancel_marker_and_starts_the_records_phase_and_image_again() {
    // EvalAI: submission 1 was set to `resuming` by the host; submission 2 is `submitted`.
    let mut fixture = Fixture::default();
    fixture.submissions[0].status = "resuming".into();
    let (stack, mut env) = common::stack(fixture).await;
    let sdk = &stack.sdk;
    let arn = state_machine(sdk).await;
    env.push(("LB_STATE_MACHINE_ARN", arn.clone()));

    // The first run: the Pipe's execution claimed it, and it was cancelled.
    let out = lbctl(
        &[
            "submit",
            "--challenge",
            "1",
            "--phase",
            "1",
            "--submission",
            "1",
            "--image",
            IMAGE,
        ],
        &env,
        None,
    );
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    let (first, _) = started_execution(sdk, &stdout(&out)).await;
    let first_name = first.rsplit(':').next().unwrap().to_string();
    put_record(
        sdk,
        TABLE_20,
        1,
        1,
        "CANCELLED",
        &[("claimed_by", AttributeValue::S(first_name))],
    )
    .await;
    put_object(sdk, BUCKET_20, &cancel_key(1)).await;

    // One second later at least, so the new execution's name differs from the first's.
    tokio::time::sleep(std::time::Duration::from_millis(1100)).await;
    let out = lbctl(&["resume", "1"], &env, None);
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    assert!(
        !exists(sdk, BUCKET_20, &cancel_key(1)).await,
        "{}",
        show(&out)
    );
    assert!(
        stdout(&out).contains("cancel marker removed"),
        "{}",
        show(&out)
    );
    assert!(stdout(&out).contains("resuming"), "{}", show(&out));
    let (second, input) = started_execution(sdk, &stdout(&out)).await;
    assert_ne!(first, second);
    assert_eq!(
        input,
        json!([{"challenge_pk": 1, "phase_pk": 1, "submission_pk": 1, "submitted_image_uri": IMAGE}])
    );
}

#[tokio::test]
#[ignore = "needs moto"]
async fn resume_refuses_what_intake_would_skip_unless_forced() {
    let mut fixture = Fixture::default();
    fixture.submissions[1].status = "failed".into();
    let (stack, mut env) = common::stack(fixture).await;
    let sdk = &stack.sdk;
    let arn = state_machine(sdk).await;
    env.push(("LB_STATE_MACHINE_ARN", arn));

    // Still running: an execution holds it.
    put_record(sdk, TABLE_20, 1, 1, "RUNNING", &[]).await;
    let out = lbctl(&["resume", "1", "--challenge", "1"], &env, None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(stderr(&out).contains("lbctl cancel 1"), "{}", show(&out));

    // FAILED here and on EvalAI: EvalAI's resume endpoint is named; nothing is started.
    put_record(sdk, TABLE_20, 2, 2, "FAILED", &[]).await;
    let out = lbctl(&["resume", "2", "--challenge", "1"], &env, None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(stderr(&out).contains("as `failed`"), "{}", show(&out));
    assert!(
        stderr(&out).contains("/api/jobs/submissions/2/resume/"),
        "{}",
        show(&out)
    );
    let executions = aws_sdk_sfn::Client::new(sdk)
        .list_executions()
        .state_machine_arn(
            env.iter()
                .find(|(k, _)| *k == "LB_STATE_MACHINE_ARN")
                .unwrap()
                .1
                .clone(),
        )
        .send()
        .await
        .unwrap();
    assert!(executions.executions().is_empty());

    // No claiming execution and no --challenge: the flag is named.
    let out = lbctl(&["resume", "2"], &env, None);
    assert_eq!(out.status.code(), Some(2), "{}", show(&out));
    assert!(stderr(&out).contains("--challenge"), "{}", show(&out));

    // Forced: started anyway, with a note.
    let out = lbctl(&["resume", "2", "--challenge", "1", "--force"], &env, None);
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    assert!(stdout(&out).contains("not checked"), "{}", show(&out));
    let (_, input) = started_execution(sdk, &stdout(&out)).await;
    assert_eq!(input[0]["submission_pk"], 2);

    // Never ran here.
    let out = lbctl(&["resume", "77", "--challenge", "1"], &env, None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(
        stderr(&out).contains("`77` has no record"),
        "{}",
        show(&out)
    );
}

#[tokio::test]
#[ignore = "needs moto"]
async fn a_reader_that_stops_early_ends_the_output_not_the_command_with_a_panic() {
    // `lbctl status 7 | head -1` once panicked on the closed pipe (exit 101).
    let (stack, env) = common::stack(Fixture::default()).await;
    put_record(&stack.sdk, TABLE_20, 1, 101, "RUNNING", &[]).await;
    for args in [&["status", "101"][..], &["list"][..]] {
        let mut child = common::lbctl_command(args, &env)
            .stdin(std::process::Stdio::null())
            .spawn()
            .unwrap();
        drop(child.stdout.take()); // the reader is gone before the first line
        let deadline = std::time::Instant::now() + common::CALL_TIMEOUT;
        let status = loop {
            if let Some(status) = child.try_wait().unwrap() {
                break status;
            }
            if std::time::Instant::now() > deadline {
                let _ = child.kill();
                panic!("lbctl {args:?} did not end");
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        };
        let mut stderr = String::new();
        std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut stderr).unwrap();
        assert_eq!(status.code(), Some(0), "{args:?}: {stderr}");
        assert!(!stderr.contains("panicked"), "{args:?}: {stderr}");
    }
}

#[tokio::test]
#[ignore = "needs moto"]
async fn release_gives_back_a_leaked_place_after_its_id_is_typed_back() {
    use lb_domain::capacity::queue::{Entry, EntryState};
    let (stack, mut env) = common::stack(Fixture::default()).await;
    env.push((
        "LB_ADMISSION_TABLE",
        local_stack::stack::ADMISSION_TABLE.to_string(),
    ));
    let table = lb_aws::admission::AdmissionTable::new(
        aws_sdk_dynamodb::Client::new(&stack.sdk),
        local_stack::stack::ADMISSION_TABLE,
    );
    // 301's run ended without giving its place back; 302 still runs.
    for (id, status) in [(301, "FAILED"), (302, "RUNNING")] {
        put_record(&stack.sdk, TABLE_20, 5, id, status, &[]).await;
        let entry = Entry {
            submission_id: id,
            team_id: 5,
            arrived_ms: 1_000 * id,
            state: EntryState::Waiting,
        };
        table
            .enqueue("2.0", &entry, &format!("exec-{id}"))
            .await
            .unwrap();
        let admitted = table.admit("2.0", &entry, 2).await.unwrap();
        assert_eq!(admitted, lb_aws::admission::Admit::Admitted);
    }
    let holders = || async { table.holders("2.0", 5).await.unwrap() };

    // A wrong answer (or none) releases nothing.
    let out = lbctl(&["release", "301"], &env, Some("30\n"));
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(
        stdout(&out)
            .contains("holds a place of team 5 in leaderboard 2.0 (queued by execution exec-301)"),
        "{}",
        show(&out)
    );
    assert!(stderr(&out).contains("not released"), "{}", show(&out));
    assert_eq!(holders().await.len(), 2);

    // Its id typed back: released.
    let out = lbctl(&["release", "301"], &env, Some("301\n"));
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    assert_eq!(holders().await, ["302"]);
    assert_eq!(table.entry("2.0", 301).await.unwrap(), None);

    // A running submission's place is refused without --force, with advice that fits where
    // its execution stands: unknown without the state machine, then running, then ended.
    let out = lbctl(&["release", "302", "--yes"], &env, None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(
        stderr(&out).contains("is in flight (RUNNING"),
        "{}",
        show(&out)
    );
    assert!(
        stderr(&out).contains("If its execution still runs"),
        "{}",
        show(&out)
    );
    let machine = state_machine(&stack.sdk).await;
    let sfn = aws_sdk_sfn::Client::new(&stack.sdk);
    let execution = sfn
        .start_execution()
        .state_machine_arn(&machine)
        .name("exec-302")
        .input("{}")
        .send()
        .await
        .unwrap()
        .execution_arn;
    let claimed = [("claimed_by", AttributeValue::S("exec-302".into()))];
    put_record(&stack.sdk, TABLE_20, 5, 302, "RUNNING", &claimed).await;
    env.push(("LB_STATE_MACHINE_ARN", machine.clone()));
    let out = lbctl(&["release", "302", "--yes"], &env, None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(
        stderr(&out).contains("execution `exec-302` runs and holds this place: `lbctl cancel 302`"),
        "{}",
        show(&out)
    );
    sfn.stop_execution()
        .execution_arn(&execution)
        .send()
        .await
        .unwrap();
    let out = lbctl(&["release", "302", "--yes"], &env, None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(
        stderr(&out).contains("execution `exec-302` ended ABORTED")
            && stderr(&out).contains("reaper's pass"),
        "{}",
        show(&out)
    );
    assert_eq!(holders().await, ["302"]);
    let out = lbctl(&["release", "301", "--yes"], &env, None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(stderr(&out).contains("holds no place"), "{}", show(&out));
    let out = lbctl(&["release", "302", "--yes", "--force"], &env, None);
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    assert!(holders().await.is_empty());
}

/// The deployed definition's shape as far as a release goes: two functions at version 1.
fn versioned_definition() -> Value {
    let function = |name: &str| format!("arn:aws:lambda:us-east-1:123456789012:function:{name}:1");
    json!({"StartAt": "Intake", "States": {
        "Intake": {"Type": "Task", "Resource": function("lb-intake"), "Next": "Monitor"},
        "Monitor": {"Type": "Task", "Resource": function("lb-monitor"), "End": true}
    }})
}

/// The version the alias routes to, and that version's definition.
async fn alias_target(sfn: &aws_sdk_sfn::Client, alias: &str) -> (String, Value) {
    let described = sfn
        .describe_state_machine_alias()
        .state_machine_alias_arn(alias)
        .send()
        .await
        .unwrap();
    let routes = described.routing_configuration();
    assert_eq!(routes.len(), 1);
    assert_eq!(routes[0].weight(), 100);
    let version = routes[0].state_machine_version_arn().to_owned();
    let definition = sfn
        .describe_state_machine()
        .state_machine_arn(&version)
        .send()
        .await
        .unwrap()
        .definition;
    (version, serde_json::from_str(&definition).unwrap())
}

#[tokio::test]
#[ignore = "needs moto"]
async fn ship_publishes_a_version_naming_the_function_s_and_rollback_moves_the_alias_back() {
    let (stack, mut env) = common::stack(Fixture::default()).await;
    let sfn = aws_sdk_sfn::Client::new(&stack.sdk);
    let created = sfn
        .create_state_machine()
        .name("submission")
        .definition(versioned_definition().to_string())
        .role_arn("arn:aws:iam::123456789012:role/leaderboard-states")
        .publish(true)
        .send()
        .await
        .unwrap();
    let v1 = created.state_machine_version_arn().unwrap().to_owned();
    let route = aws_sdk_sfn::types::RoutingConfigurationListItem::builder()
        .state_machine_version_arn(&v1)
        .weight(100)
        .build()
        .unwrap();
    let alias = sfn
        .create_state_machine_alias()
        .name("live")
        .routing_configuration(route)
        .send()
        .await
        .unwrap()
        .state_machine_alias_arn;
    env.push(("LB_STATE_MACHINE_ARN", alias.clone()));

    let intake_2 = "arn:aws:lambda:us-east-1:123456789012:function:lb-intake:2";
    let out = lbctl(&["ship", "--function-version", intake_2], &env, None);
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    let (v2, definition) = alias_target(&sfn, &alias).await;
    assert_ne!(v2, v1, "{}", show(&out));
    assert_eq!(definition["States"]["Intake"]["Resource"], intake_2);
    assert_eq!(
        definition["States"]["Monitor"]["Resource"],
        versioned_definition()["States"]["Monitor"]["Resource"],
        "only the shipped function changed"
    );
    assert!(
        stdout(&out).contains("executions already running stay on"),
        "{}",
        show(&out)
    );
    // Shipped twice: nothing new. A function no state invokes: refused, the alias unmoved.
    let out = lbctl(&["ship", "--function-version", intake_2], &env, None);
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    assert!(stdout(&out).contains("nothing to ship"), "{}", show(&out));
    let wake = "arn:aws:lambda:us-east-1:123456789012:function:lb-wake:3";
    let out = lbctl(&["ship", "--function-version", wake], &env, None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(
        stderr(&out).contains("no state of the definition invokes `lb-wake`"),
        "{}",
        show(&out)
    );
    assert_eq!(alias_target(&sfn, &alias).await.0, v2);

    // Rolling back: the alias names version 1 again; there is nothing before it.
    let out = lbctl(&["rollback"], &env, None);
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    assert_eq!(alias_target(&sfn, &alias).await.0, v1);
    let out = lbctl(&["rollback"], &env, None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(
        stderr(&out).contains("nothing to roll back to"),
        "{}",
        show(&out)
    );
    // Forward again is a rollback's undo: `--to` names only earlier versions.
    let out = lbctl(&["rollback", "--to", "2"], &env, None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    // The unqualified ARN is not the alias's.
    let machine = created.state_machine_arn;
    let out = lbctl(&["rollback", "--state-machine", &machine], &env, None);
    assert_eq!(out.status.code(), Some(2), "{}", show(&out));
    assert!(
        stderr(&out).contains("StateMachineAliasArn"),
        "{}",
        show(&out)
    );
}
