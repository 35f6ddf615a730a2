//! `lbctl logs` against moto: a submission's logs as logcopy left them in S3.

use crate::common;

use std::time::{Duration, Instant};

use aws_sdk_dynamodb::types::AttributeValue;
use common::{lbctl, show, stderr, stdout};
use fake_evalai::Fixture;

const BUCKET: &str = "leaderboard-20-results";

async fn put_log(sdk: &aws_config::SdkConfig, key: &str, body: &str) {
    lb_aws::s3_client(sdk)
        .put_object()
        .bucket(BUCKET)
        .key(format!("1/{key}"))
        .body(body.as_bytes().to_vec().into())
        .send()
        .await
        .unwrap();
}

async fn put_record(sdk: &aws_config::SdkConfig, status: &str) {
    let text = |v: &str| AttributeValue::S(v.into());
    aws_sdk_dynamodb::Client::new(sdk)
        .put_item()
        .table_name("leaderboard-20-submissions")
        .item("team_id", text("1"))
        .item("submission_id", text("1"))
        .item("submission_status", text(status))
        .item("track_id", text("1"))
        .send()
        .await
        .unwrap();
}

#[tokio::test]
#[ignore = "needs moto"]
async fn logs_prints_each_workers_logs_and_follows_them_until_the_end() {
    let (stack, env) = common::stack(Fixture::default()).await;
    let sdk = &stack.sdk;
    put_record(sdk, "RUNNING").await;
    put_log(
        sdk,
        "logs/agent/agent1/agent.log",
        "agent one starts\n\x1b[31mred\x1b[0m route 0\n",
    )
    .await;
    put_log(sdk, "logs/agent/agent2/agent.log", "agent two starts\n").await;
    put_log(sdk, "logs/simulator/simulator1.log", "CARLA 1 up\n").await;
    put_log(sdk, "logs/logcopy/logcopy-0.log", "uploaded 3 files\n").await;
    put_log(sdk, "recorder/pair1/RouteScenario_0_rep0.log", "BINARY").await;
    put_log(sdk, "agent/partial_agent_results1.json", "{}").await;
    // A name an older logcopy let through: it reads as `agent1/cod.log` backwards.
    put_log(sdk, "logs/agent/agent1/gol.\u{202e}exe\u{200b}", "named\n").await;

    let out = lbctl(&["logs", "1"], &env, None);
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    let text = stdout(&out);
    for expected in [
        "==> logs/agent/agent1/agent.log <==\nagent one starts\nred route 0\n",
        "==> logs/agent/agent2/agent.log <==\nagent two starts\n",
        "==> logs/simulator/simulator1.log <==\nCARLA 1 up\n",
        "==> logs/logcopy/logcopy-0.log <==\nuploaded 3 files\n",
    ] {
        assert!(text.contains(expected), "`{expected}` missing:\n{text}");
    }
    assert!(!text.contains("recorder"), "{text}");
    assert!(
        !text.contains('\x1b'),
        "no terminal escape reaches the operator"
    );
    assert!(!text.contains("partial_agent_results"), "{text}");
    assert!(
        text.contains("==> logs/agent/agent1/gol.\\u{202e}exe\\u{200b} <==\nnamed\n"),
        "{text}"
    );
    assert!(!text.contains(['\u{202e}', '\u{200b}']), "{text}");

    let out = lbctl(&["logs", "1", "--worker", "2"], &env, None);
    let text = stdout(&out);
    assert!(text.contains("agent two starts"), "{text}");
    assert!(text.contains("uploaded 3 files"), "{text}");
    assert!(
        !text.contains("agent one") && !text.contains("CARLA 1"),
        "{text}"
    );

    // A worker with no log at all says so instead of printing only logcopy's.
    let out = lbctl(&["logs", "1", "--worker", "99"], &env, None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(
        stderr(&out).contains("no logs of worker 99")
            && stderr(&out).contains("workers with logs: 1, 2"),
        "{}",
        show(&out)
    );
    assert!(stdout(&out).is_empty(), "{}", show(&out));

    let out = lbctl(&["logs", "1", "--recorder"], &env, None);
    assert!(
        stdout(&out).contains(
            "==> recorder/pair1/RouteScenario_0_rep0.log <== (6 bytes, a recording: not printed)"
        ),
        "{}",
        show(&out)
    );
    assert!(!stdout(&out).contains("BINARY"));

    let out = lbctl(&["logs", "2"], &env, None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(stderr(&out).contains("`2` has no logs"), "{}", show(&out));

    // --follow: what logcopy adds is printed once, and it stops when the record is final.
    let child = common::lbctl_command(
        &["logs", "1", "--worker", "1", "--follow", "--interval", "1"],
        &env,
    )
    .spawn()
    .unwrap();
    tokio::time::sleep(Duration::from_secs(2)).await;
    put_log(
        sdk,
        "logs/agent/agent1/agent.log",
        "agent one starts\n\x1b[31mred\x1b[0m route 0\nroute 1 done\n",
    )
    .await;
    tokio::time::sleep(Duration::from_secs(2)).await;
    put_record(sdk, "FINISHED").await;
    let started = Instant::now();
    let out = tokio::task::spawn_blocking(move || child.wait_with_output())
        .await
        .unwrap()
        .unwrap();
    assert!(started.elapsed() < Duration::from_secs(20));
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    let text = stdout(&out);
    assert_eq!(text.matches("agent one starts").count(), 1, "{text}");
    assert!(
        text.contains("==> logs/agent/agent1/agent.log (continued) <==\nroute 1 done\n"),
        "{text}"
    );
    assert!(stderr(&out).contains("ended `FINISHED`"), "{}", show(&out));
}
