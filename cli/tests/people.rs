//! `lbctl` as a newcomer meets it: readable log lines, and one clear line when AWS is not
//! configured.

use std::process::{Command, Output};

/// `lbctl` with nothing of AWS in its environment, and a home with no `~/.aws`.
fn lbctl_without_aws(args: &[&str], extra: &[(&str, &str)]) -> Output {
    let home = tempfile::tempdir().unwrap();
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_lbctl"));
    cmd.args(args)
        .env_clear()
        .env("PATH", std::env::var_os("PATH").unwrap_or_default())
        .env("HOME", home.path())
        // NB: no request may leave this machine: the chain must not try 169.254.169.254.
        .env("AWS_EC2_METADATA_DISABLED", "true");
    for (k, v) in extra {
        cmd.env(k, v);
    }
    cmd.output().unwrap()
}

fn stderr_lines(out: &Output) -> Vec<String> {
    String::from_utf8_lossy(&out.stderr)
        .lines()
        .map(str::to_owned)
        .collect()
}

#[test]
fn without_credentials_status_says_in_one_line_what_it_looked_for() {
    let out = lbctl_without_aws(&["status", "5"], &[("AWS_REGION", "us-west-2")]);
    assert_eq!(out.status.code(), Some(1));
    let lines = stderr_lines(&out);
    assert_eq!(lines.len(), 1, "{lines:?}");
    let line = &lines[0];
    assert!(line.starts_with("lbctl: no AWS credentials"), "{line}");
    for hint in ["AWS_ACCESS_KEY_ID", "AWS_PROFILE", "~/.aws/credentials"] {
        assert!(line.contains(hint), "{line}");
    }
    assert!(!line.contains("transient"), "{line}");
    assert!(out.stdout.is_empty());
}

#[test]
fn without_a_region_the_line_says_how_to_set_one() {
    let out = lbctl_without_aws(&["status", "5"], &[]);
    assert_eq!(out.status.code(), Some(1));
    let lines = stderr_lines(&out);
    assert_eq!(lines.len(), 1, "{lines:?}");
    assert!(lines[0].starts_with("lbctl: no AWS region"), "{}", lines[0]);
    assert!(lines[0].contains("AWS_REGION"), "{}", lines[0]);
}

#[test]
fn log_lines_are_text_by_default_and_the_format_is_checked() {
    // Info logs on: whatever is logged before the error is text, not JSON.
    let text = lbctl_without_aws(&["-v", "status", "5"], &[("AWS_REGION", "us-west-2")]);
    assert_eq!(text.status.code(), Some(1));
    assert!(
        stderr_lines(&text)
            .iter()
            .all(|l| !l.trim_start().starts_with('{')),
        "{:?}",
        stderr_lines(&text)
    );
    let bad = lbctl_without_aws(&["--log-format", "yaml", "status", "5"], &[]);
    assert_eq!(bad.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&bad.stderr).contains("--log-format"));
}
