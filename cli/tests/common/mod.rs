//! Running the `lbctl` binary with a bounded wait and a clean environment, and a provisioned
//! local stack to point it at.
#![allow(dead_code)]

use std::io::{Read, Write};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

/// Longest any one `lbctl` call may take in these tests.
pub const CALL_TIMEOUT: Duration = Duration::from_secs(60);

/// Variables the operator's shell may carry that would point `lbctl` elsewhere.
const SCRUBBED: &[&str] = &[
    "LB_SETTINGS_SECRET",
    "LB_EVALAI_TOKEN_SECRET",
    "LB_WAKE_TABLE",
    "LB_BUDGET_TABLE",
    "LB_ADMISSION_TABLE",
    "LB_STATE_MACHINE_ARN",
    "LB_KUBECONFIG",
    "AWS_ENDPOINT_URL",
    "AWS_PROFILE",
    "AWS_DEFAULT_PROFILE",
    "AWS_SESSION_TOKEN",
    "AWS_ACCESS_KEY_ID",
    "AWS_SECRET_ACCESS_KEY",
    "AWS_REGION",
    "AWS_DEFAULT_REGION",
];

/// `lbctl args...` with `env` and nothing else of AWS or LB_* inherited, its output piped:
/// for a test that runs it in the background.
pub fn lbctl_command(args: &[&str], env: &[(&str, String)]) -> Command {
    let mut command = Command::new(env!("CARGO_BIN_EXE_lbctl"));
    command.args(args);
    for name in SCRUBBED {
        command.env_remove(name);
    }
    command
        .env("AWS_CONFIG_FILE", "/dev/null")
        .env("AWS_SHARED_CREDENTIALS_FILE", "/dev/null")
        .env("AWS_EC2_METADATA_DISABLED", "true")
        .envs(env.iter().map(|(k, v)| (*k, v.as_str())))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    command
}

/// `lbctl args...` with `env` (nothing else of AWS or LB_* inherited) and `stdin`.
pub fn lbctl(args: &[&str], env: &[(&str, String)], stdin: Option<&str>) -> Output {
    let mut command = lbctl_command(args, env);
    command.stdin(if stdin.is_some() {
        Stdio::piped()
    } else {
        Stdio::null()
    });
    let mut child = command.spawn().expect("lbctl starts");
    if let Some(text) = stdin {
        let mut pipe = child.stdin.take().unwrap();
        pipe.write_all(text.as_bytes()).unwrap();
    }
    let mut out = child.stdout.take().unwrap();
    let mut err = child.stderr.take().unwrap();
    let stdout = std::thread::spawn(move || {
        let mut buf = Vec::new();
        let _ = out.read_to_end(&mut buf);
        buf
    });
    let stderr = std::thread::spawn(move || {
        let mut buf = Vec::new();
        let _ = err.read_to_end(&mut buf);
        buf
    });
    let deadline = Instant::now() + CALL_TIMEOUT;
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("lbctl {args:?} did not end within {CALL_TIMEOUT:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let out = Output {
        status,
        stdout: stdout.join().unwrap(),
        stderr: stderr.join().unwrap(),
    };
    // NB: `LBCTL_TEST_ECHO=1 cargo test -- --nocapture` shows every call, to read the texts.
    if std::env::var_os("LBCTL_TEST_ECHO").is_some() {
        eprintln!("$ lbctl {}\n{}\n", args.join(" "), show(&out));
    }
    out
}

/// stdout and stderr, for assertion messages.
pub fn show(out: &Output) -> String {
    format!(
        "exit {:?}\n--- stdout\n{}\n--- stderr\n{}",
        out.status.code(),
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

/// stdout as text.
pub fn stdout(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// stderr as text.
pub fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A local stack (moto and the fake EvalAI with `fixture`) provisioned with the local
/// settings, and the environment that points `lbctl` at it.
pub async fn stack(
    fixture: fake_evalai::Fixture,
) -> (local_stack::Stack, Vec<(&'static str, String)>) {
    use local_stack::stack::{LOCAL_SETTINGS, SETTINGS_SECRET, TOKEN_SECRET};
    let (stack, _) = test_support::stack::provisioned_with(fixture, LOCAL_SETTINGS).await;
    let mut env = stack.moto.sdk_env();
    env.push(("LB_SETTINGS_SECRET", SETTINGS_SECRET.to_string()));
    env.push(("LB_EVALAI_TOKEN_SECRET", TOKEN_SECRET.to_string()));
    env.push(("LB_WAKE_TABLE", local_stack::stack::WAKE_TABLE.to_string()));
    // An operator's `lbctl invoke` by hand: no shared budget or queue, asked for by name.
    env.push(("LB_BUDGET_TABLE", "unlimited".to_string()));
    env.push(("LB_ADMISSION_TABLE", "unlimited".to_string()));
    (stack, env)
}
