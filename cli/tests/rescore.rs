//! `lbctl rescore` against moto and the fake EvalAI: the workers' files of a fixture case in
//! S3 give the fixture's EvalAI files; `--post` sends them, a cancelled submission is refused.

use crate::common;

use aws_sdk_dynamodb::types::AttributeValue;
use common::{lbctl, show, stderr, stdout};
use fake_evalai::Fixture;
use lb_domain::testutil::results_fixtures_dir;

const CASE: &str = "a_4workers_20routes_finished";

async fn put(sdk: &aws_config::SdkConfig, submission: u64, status: &str) {
    put_workers(sdk, submission, status, 4).await
}

/// The record, and the fixture's files of workers 1 to `files` (of 4).
async fn put_workers(sdk: &aws_config::SdkConfig, submission: u64, status: &str, files: u32) {
    let text = |v: &str| AttributeValue::S(v.into());
    aws_sdk_dynamodb::Client::new(sdk)
        .put_item()
        .table_name("leaderboard-20-submissions")
        .item("team_id", text("1"))
        .item("submission_id", text(&submission.to_string()))
        .item("submission_status", text(status))
        .item("team_name", text("Team One"))
        .item("track_id", text("1"))
        .item("track_name", text("SENSORS"))
        .item("parallelization_workers", text("4"))
        .send()
        .await
        .unwrap();
    let s3 = lb_aws::s3_client(sdk);
    for worker in 1..=files {
        let body = std::fs::read(
            results_fixtures_dir()
                .join(CASE)
                .join(format!("input/worker{worker}.json")),
        )
        .unwrap();
        s3.put_object()
            .bucket("leaderboard-20-results")
            .key(format!(
                "{submission}/agent/partial_agent_results{worker}.json"
            ))
            .body(body.into())
            .send()
            .await
            .unwrap();
    }
}

#[tokio::test]
#[ignore = "needs moto"]
async fn rescore_merges_the_workers_files_into_the_fixtures_evalai_files_and_posts_them() {
    let (stack, env) = common::stack(Fixture::default()).await;
    put(&stack.sdk, 1, "FAILED").await;
    let out_dir = tempfile::tempdir().unwrap();
    let out = lbctl(
        &["rescore", "1", "--out", out_dir.path().to_str().unwrap()],
        &env,
        None,
    );
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    assert!(
        stdout(&out).contains("4 worker file(s), 20/20 records, complete"),
        "{}",
        show(&out)
    );
    let expected = results_fixtures_dir().join(CASE).join("expected");
    for (ours, theirs) in [
        ("agent_results.json", "merged.json"),
        ("results.json", "results.json"),
        ("stdout.txt", "stdout.txt"),
        ("metadata.json", "metadata.json"),
    ] {
        assert_eq!(
            std::fs::read_to_string(out_dir.path().join(ours)).unwrap(),
            std::fs::read_to_string(expected.join(theirs)).unwrap(),
            "{ours}"
        );
    }
    // Nothing was sent without --post.
    assert_eq!(stack.fake().submission(1).unwrap().status, "submitted");

    // --post asks first: a wrong answer sends nothing.
    let out = lbctl(
        &["rescore", "1", "--post", "--challenge", "1"],
        &env,
        Some("no\n"),
    );
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(stdout(&out).contains("nothing posted"), "{}", show(&out));
    assert_eq!(stack.fake().submission(1).unwrap().status, "submitted");
    // Typing the id confirms: the final update is FINISHED with the fixture's scores.
    let out = lbctl(
        &["rescore", "1", "--post", "--challenge", "1"],
        &env,
        Some("1\n"),
    );
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    let on_evalai = stack.fake().submission(1).unwrap();
    assert_eq!(on_evalai.status, "finished");
    assert_eq!(
        on_evalai.files.stdout.as_deref(),
        Some(
            std::fs::read_to_string(expected.join("stdout.txt"))
                .unwrap()
                .as_str()
        )
    );

    // A cancelled submission is never posted.
    put(&stack.sdk, 2, "CANCELLED").await;
    let out = lbctl(
        &["rescore", "2", "--post", "--challenge", "1", "--yes"],
        &env,
        None,
    );
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(stderr(&out).contains("cancelled"), "{}", show(&out));
    assert_eq!(stack.fake().submission(2).unwrap().status, "submitted");

    // A submission an execution still holds is left to its Finalize; a merge missing routes
    // has no score to post. Neither asks, neither posts.
    put(&stack.sdk, 3, "RUNNING").await;
    put_workers(&stack.sdk, 4, "FAILED", 2).await;
    for (id, why) in [
        ("3", "record is `RUNNING`"),
        ("4", "not complete (10 of 20 records)"),
    ] {
        let before = stack.fake().requests().len();
        let out = lbctl(
            &["rescore", id, "--post", "--challenge", "1", "--yes"],
            &env,
            None,
        );
        assert_eq!(out.status.code(), Some(1), "{}", show(&out));
        assert!(stderr(&out).contains(why), "{}", show(&out));
        assert_eq!(
            stack.fake().requests().len(),
            before,
            "{id}: EvalAI was not asked"
        );
    }

    // --post without --challenge is a usage error; an unknown submission is named.
    let out = lbctl(&["rescore", "1", "--post"], &env, None);
    assert_eq!(out.status.code(), Some(2), "{}", show(&out));
    let out = lbctl(&["rescore", "77"], &env, None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(
        stderr(&out).contains("`77` has no record"),
        "{}",
        show(&out)
    );
}
