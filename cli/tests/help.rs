//! What an operator sees without any AWS: help texts, usage errors and their exit codes, and
//! `invoke`'s errors that happen before any call.

use crate::common;

use common::{lbctl, show, stderr, stdout};

const SUBCOMMANDS: &[&str] = &[
    "local",
    "invoke",
    "status",
    "list",
    "watch",
    "logs",
    "rescore",
    "cancel",
    "submit",
    "resume",
    "kubernetes-support",
    "plan",
];

#[test]
fn the_help_lists_every_subcommand_and_the_exit_codes() {
    let out = lbctl(&["--help"], &[], None);
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    let text = stdout(&out);
    for sub in SUBCOMMANDS {
        assert!(
            text.lines().any(|l| l.trim_start().starts_with(sub)),
            "`{sub}` missing from\n{text}"
        );
    }
    assert!(text.contains("Exit codes: 0 ok, 1 failure"), "{text}");
    assert!(text.contains("2 usage"), "{text}");
}

#[test]
fn every_subcommand_documents_its_arguments() {
    let expected: &[(&[&str], &[&str])] = &[
        (
            &["invoke"],
            &["intake", "launch", "monitor", "finalize", "--event"],
        ),
        (
            &["status"],
            &[
                "<SUBMISSION>",
                "--json",
                "--settings-secret",
                "LB_SETTINGS_SECRET",
            ],
        ),
        (
            &["list"],
            &[
                "--running",
                "--team",
                "--status",
                "--leaderboard",
                "--limit",
                "--json",
                "Examples:",
            ],
        ),
        (
            &["watch"],
            &[
                "<SUBMISSION>",
                "--interval",
                "--once",
                "--json",
                "Examples:",
            ],
        ),
        (
            &["logs"],
            &[
                "<SUBMISSION>",
                "--worker",
                "--follow",
                "--recorder",
                "Examples:",
            ],
        ),
        (
            &["rescore"],
            &[
                "<SUBMISSION>",
                "--out",
                "--post",
                "--challenge",
                "--yes",
                "Examples:",
            ],
        ),
        (&["cancel"], &["<SUBMISSION>", "--force", "--leaderboard"]),
        (
            &["submit"],
            &[
                "--challenge",
                "--phase",
                "--submission",
                "--image",
                "--state-machine",
                "LB_STATE_MACHINE_ARN",
            ],
        ),
        (
            &["resume"],
            &[
                "<SUBMISSION>",
                "--challenge",
                "--force",
                "--token-secret",
                "--state-machine",
                "resuming",
            ],
        ),
    ];
    for (command, words) in expected {
        let mut args = command.to_vec();
        args.push("--help");
        let out = lbctl(&args, &[], None);
        assert_eq!(out.status.code(), Some(0), "{command:?}: {}", show(&out));
        let text = stdout(&out);
        for word in *words {
            assert!(
                text.contains(word),
                "{command:?} --help lacks `{word}`:\n{text}"
            );
        }
    }
}

/// `lbctl submit` with everything but the state machine.
const SUBMIT_WITHOUT_MACHINE: &[&str] = &[
    "submit",
    "--challenge",
    "1",
    "--phase",
    "1",
    "--submission",
    "1",
];

#[test]
fn submit_without_a_state_machine_is_a_usage_error_naming_both_sources() {
    let out = lbctl(SUBMIT_WITHOUT_MACHINE, &[], None);
    assert_eq!(out.status.code(), Some(2), "{}", show(&out));
    let err = stderr(&out);
    assert!(
        err.contains("--state-machine") && err.contains("LB_STATE_MACHINE_ARN"),
        "{err}"
    );
}

#[test]
fn ids_that_are_not_evalai_ids_are_usage_errors() {
    for args in [
        &["status", "0"][..],
        &["cancel", "-3"],
        &["resume", "2147483648"],
        &["list", "--limit", "0"],
    ] {
        let out = lbctl(args, &[], None);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {}", show(&out));
    }
}

#[test]
fn invoke_names_an_event_file_that_is_not_json() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("broken-event.json");
    std::fs::write(&path, "{\"message\": {\"challenge_pk\": 1,").unwrap();
    let out = lbctl(
        &["invoke", "intake", "--event", path.to_str().unwrap()],
        &[],
        None,
    );
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    let err = stderr(&out);
    assert!(
        err.contains("broken-event.json") && err.contains("not valid JSON"),
        "{err}"
    );
    assert!(stdout(&out).is_empty(), "{}", show(&out));

    let out = lbctl(&["invoke", "intake", "--event", "-"], &[], Some("not json"));
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(stderr(&out).contains("`-`"), "{}", show(&out));
}

#[test]
fn invoke_without_its_environment_prints_the_lambda_error_object() {
    let event =
        r#"{"message": {"challenge_pk": 1, "phase_pk": 1, "submission_pk": 1}, "execution": "x"}"#;
    for function in ["intake", "launch", "monitor", "finalize", "wake", "sweep"] {
        let out = lbctl(&["invoke", function], &[], Some(event));
        assert_eq!(out.status.code(), Some(1), "{function}: {}", show(&out));
        let error: serde_json::Value = serde_json::from_slice(&out.stdout)
            .unwrap_or_else(|e| panic!("{function}: {e}: {}", show(&out)));
        assert_eq!(
            error["errorType"], "InvalidConfiguration",
            "{function}: {error}"
        );
        assert!(
            error["errorMessage"]
                .as_str()
                .unwrap()
                .contains("LB_SETTINGS_SECRET"),
            "{function}: {error}"
        );
    }
}

/// `--print-input` needs no state machine and no AWS: it prints the Pipe's one-element batch
/// for the console, which Intake reads as the same message the Pipe would give it.
#[test]
fn submit_print_input_prints_the_pipes_batch_for_the_console() {
    let out = lbctl(
        &[
            "submit",
            "--challenge",
            "12",
            "--phase",
            "1234",
            "--submission",
            "77",
            "--image",
            "repo/agent:1",
            "--print-input",
        ],
        &[],
        None,
    );
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    let printed: serde_json::Value = serde_json::from_str(&stdout(&out)).expect("JSON");
    assert_eq!(
        printed,
        serde_json::json!([{"challenge_pk": 12, "phase_pk": 1234, "submission_pk": 77,
                            "submitted_image_uri": "repo/agent:1"}])
    );
    let message = lb_domain::submission::SubmissionMessage::from_pipe(&printed).unwrap();
    assert_eq!(message.submission_id, 77);
    let bare = lb_domain::submission::SubmissionMessage::from_pipe(&printed[0]).unwrap();
    assert_eq!(bare, message, "the element typed alone is the same message");
}

/// `lbctl ... 2>&1 | head -0`: both streams closed before the first byte. The command ends with
/// its own exit code, never a panic (101).
#[test]
fn closed_stdout_and_stderr_end_with_the_commands_own_exit_code() {
    let cases: [(&[&str], i32); 3] = [
        // Our own usage error, written to stderr by lbctl.
        (SUBMIT_WITHOUT_MACHINE, 2),
        // clap's.
        (&["status", "0"], 2),
        // Help, on stdout.
        (&["--help"], 0),
    ];
    for (args, code) in cases {
        let mut child = common::lbctl_command(args, &[])
            .stdin(std::process::Stdio::null())
            .spawn()
            .unwrap();
        drop(child.stdout.take());
        drop(child.stderr.take());
        let deadline = std::time::Instant::now() + common::CALL_TIMEOUT;
        let status = loop {
            if let Some(status) = child.try_wait().unwrap() {
                break status;
            }
            assert!(
                std::time::Instant::now() < deadline,
                "lbctl {args:?} did not end"
            );
            std::thread::sleep(std::time::Duration::from_millis(10));
        };
        assert_eq!(status.code(), Some(code), "lbctl {args:?}");
    }
}

/// A status filter no record can have is a usage error naming the ones there are, not an
/// empty list; the known ones are accepted in any case.
#[test]
fn list_refuses_a_status_no_record_can_have() {
    let out = lbctl(&["list", "--status", "BOGUS"], &[], None);
    assert_eq!(out.status.code(), Some(2), "{}", show(&out));
    let err = stderr(&out);
    assert!(err.contains("BOGUS") && err.contains("CANCELLED"), "{err}");
    // `failed` passes the parser: it fails later, for want of an AWS region, not as usage.
    let out = lbctl(&["list", "--status", "failed"], &[], None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(stderr(&out).contains("no AWS region"), "{}", show(&out));
}

#[test]
fn kubernetes_support_says_the_template_s_minor_and_asks_to_act_on_an_ending_one() {
    let out = lbctl(&["kubernetes-support"], &[], None);
    let text = stdout(&out);
    let minor = lb_infra::support::template_minor().unwrap();
    assert!(
        text.starts_with(&format!("Kubernetes {minor}: EKS standard support")),
        "{}",
        show(&out)
    );
    assert!(!text.contains("no EKS support date known"), "{text}");

    // 1.33's standard support ended on 2026-07-29, before this test was written.
    let out = lbctl(&["kubernetes-support", "--minor", "1.33"], &[], None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(stdout(&out).contains("ended 2026-07-29"), "{}", show(&out));
    assert!(
        stdout(&out).contains("Upgrading Kubernetes"),
        "{}",
        show(&out)
    );

    let out = lbctl(&["kubernetes-support", "--minor", "1.99"], &[], None);
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    assert!(stdout(&out).contains("support.rs"), "{}", show(&out));
}

#[test]
fn plan_prices_a_rush_three_ways_and_refuses_a_fleet_that_cannot_be() {
    let args = [
        "plan",
        "--submissions",
        "30",
        "--teams",
        "6",
        "--nodes",
        "6",
    ];
    let out = lbctl(&args, &[], None);
    assert_eq!(out.status.code(), Some(0), "{}", show(&out));
    let text = stdout(&out);
    // Each way's dollars per evaluation, the fifth column of its row.
    let per_evaluation = |name: &str| -> f64 {
        let row = text
            .lines()
            .find(|l| l.starts_with(name))
            .unwrap_or_else(|| panic!("{name} in\n{text}"));
        let columns: Vec<&str> = row[name.len()..].split_whitespace().collect();
        columns[3].parse().unwrap_or_else(|_| panic!("{row}"))
    };
    let (original, on_demand, spot) = (
        per_evaluation("the original's way"),
        per_evaluation("ours, on-demand"),
        per_evaluation("ours, Spot first"),
    );
    assert!(spot < on_demand && on_demand < original, "{text}");
    assert!(text.contains("30 submissions of 6 teams"), "{text}");

    for bad in [
        &["plan", "--nodes", "0"][..],
        &["plan", "--spot-share", "2"],
        &["plan", "--instance-type", "m5.large"],
    ] {
        let out = lbctl(bad, &[], None);
        assert_eq!(out.status.code(), Some(2), "{bad:?}: {}", show(&out));
        assert!(
            stderr(&out).contains("--") || stderr(&out).contains("m5.large"),
            "{}",
            show(&out)
        );
    }
}
