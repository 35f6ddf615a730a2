//! The `fake-evalai` binary starts, prints its URL, answers, and stops on SIGTERM.

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

fn free_port() -> u16 {
    let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    l.local_addr().unwrap().port()
}

#[test]
fn the_binary_prints_its_url_serves_the_api_and_stops_on_sigterm() {
    let port = free_port();
    let dir = tempfile::tempdir().unwrap();
    let fixture = dir.path().join("fixture.json");
    std::fs::write(&fixture, fake_evalai::fixture::DEFAULT_FIXTURE_JSON).unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_fake-evalai"))
        .args(["--port", &port.to_string(), "--fixture"])
        .arg(&fixture)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("binary starts");
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let mut line = String::new();
        let _ = BufReader::new(stdout).read_line(&mut line);
        let _ = tx.send(line);
    });
    let line = match rx.recv_timeout(Duration::from_secs(20)) {
        Ok(line) => line,
        Err(e) => {
            let _ = child.kill();
            panic!("no URL line: {e}");
        }
    };
    let url = line.trim().to_owned();
    assert_eq!(url, format!("http://127.0.0.1:{port}"));

    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let status = rt.block_on(async {
        reqwest::Client::new()
            .get(format!("{url}/api/jobs/submission/1"))
            .header("Authorization", "Bearer host-token")
            .timeout(Duration::from_secs(10))
            .send()
            .await
            .map(|r| r.status().as_u16())
    });

    let killed = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .expect("kill runs");
    assert!(killed.success());
    let deadline = Instant::now() + Duration::from_secs(10);
    let exit = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break Some(s);
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            break None;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    assert_eq!(status.ok(), Some(200));
    let exit = exit.expect("the binary stops within 10 s of SIGTERM");
    assert!(exit.success(), "{exit:?}");
}

#[test]
fn the_binary_rejects_a_bad_fixture_with_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let fixture = dir.path().join("bad.json");
    std::fs::write(&fixture, r#"{"users": []}"#).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_fake-evalai"))
        .args(["--port", "0", "--fixture"])
        .arg(&fixture)
        .output()
        .expect("binary runs");
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("missing field `tokens`"), "{stderr}");
}
