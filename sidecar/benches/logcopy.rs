//! `make bench-sidecar`: resident memory of `lb-sidecar logcopy` uploading a 1 GiB logs tree
//! to moto (one 512 MiB file in parts, 512 files of 1 MiB), from `/proc/<pid>/status`.
//!
//! Target (issue 5): peak resident memory (VmHWM) under 20 MiB. Exits non-zero when missed.
//! Under `cargo test --all-targets` (no `--bench`) it runs once on a 32 MiB tree as a smoke
//! test (the memory target is only reported there), and skips when moto is not installed.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use local_stack::moto::MotoServer;

const LIMIT_KIB: u64 = 20 * 1024;
const BUCKET: &str = "lb-bench-bucket";

fn main() {
    let timed = std::env::args().any(|a| a == "--bench");
    let total: u64 = if timed { 1 << 30 } else { 32 << 20 };
    // `make test` runs this once, small, beside the tests (moto is in its venv then).
    let moto = MotoServer::start().unwrap_or_else(|e| panic!("moto is needed: {e}"));
    assert_eq!(request(moto.addr(), "PUT", &format!("/{BUCKET}")), 200);

    let tree = tempfile::tempdir().unwrap();
    let root = tree.path();
    let started = Instant::now();
    let files = make_tree(root, total);
    println!(
        "tree: {files} files, {} MiB, written in {:.1?}",
        total >> 20,
        started.elapsed()
    );

    let mut child = Command::new(env!("CARGO_BIN_EXE_lb-sidecar"))
        .arg("logcopy")
        .env_clear()
        .envs(moto.sdk_env())
        .env("RUST_LOG", "warn")
        .env("LB_SUBMISSION_ID", "1")
        .env("LB_JOB_INDEX", "0")
        .env("LB_LEADERBOARD", "2.0")
        .env("LB_PAIRS", "1")
        .env("LB_S3_BUCKET", BUCKET)
        .env("LB_LOGS_ROOT", root)
        .env("LB_PERIOD_SECONDS", "1")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    let pid = child.id();
    let started = Instant::now();
    let mut hwm_kib = 0;
    let status = loop {
        if let Some(kib) = vm_hwm_kib(pid) {
            hwm_kib = hwm_kib.max(kib);
        }
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        assert!(
            started.elapsed() < Duration::from_secs(1800),
            "logcopy did not finish"
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    let elapsed = started.elapsed();
    assert!(status.success(), "logcopy failed: {status}");
    let uploaded = listed_bytes(moto.addr(), "1/");
    assert!(
        uploaded >= total,
        "only {uploaded} of {total} bytes reached S3"
    );
    println!(
        "logcopy: {} MiB uploaded in {elapsed:.1?} ({:.0} MiB/s), peak resident memory \
         (VmHWM) {:.1} MiB, target < {} MiB",
        uploaded >> 20,
        (uploaded >> 20) as f64 / elapsed.as_secs_f64(),
        hwm_kib as f64 / 1024.0,
        LIMIT_KIB / 1024
    );
    // NB: a debug build's memory means nothing (its mapped binary alone is larger).
    if timed && hwm_kib >= LIMIT_KIB {
        eprintln!("FAILED: peak resident memory over the target");
        std::process::exit(1);
    }
}

/// Half the bytes in one big file (multipart), half in 1 MiB files; all pairs done.
fn make_tree(root: &Path, total: u64) -> usize {
    let mut seed = 0x9e37_79b9_7f4a_7c15u64;
    let mut chunk = vec![0u8; 1 << 20];
    let mut fill = |chunk: &mut Vec<u8>| {
        for word in chunk.chunks_mut(8) {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            word.copy_from_slice(&seed.to_le_bytes()[..word.len()]);
        }
    };
    std::fs::create_dir_all(root.join("logs/simulator")).unwrap();
    let mut big = std::fs::File::create(root.join("logs/simulator/simulator1.log")).unwrap();
    for _ in 0..(total / 2) >> 20 {
        fill(&mut chunk);
        big.write_all(&chunk).unwrap();
    }
    let small = (total / 2) >> 20;
    for i in 0..small {
        let dir = root.join("recorder/pair1");
        std::fs::create_dir_all(&dir).unwrap();
        fill(&mut chunk);
        std::fs::write(dir.join(format!("RouteScenario_{i}_rep0.log")), &chunk).unwrap();
    }
    std::fs::create_dir_all(root.join("containers-status")).unwrap();
    for m in ["simulator-1.done", "agent-1.done"] {
        std::fs::write(root.join("containers-status").join(m), "").unwrap();
    }
    1 + small as usize + 2
}

fn vm_hwm_kib(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

const AUTH: &str = "AWS4-HMAC-SHA256 Credential=testing/20240101/us-east-1/s3/aws4_request, \
                    SignedHeaders=host, Signature=00";

fn raw(addr: SocketAddr, method: &str, path: &str) -> (u16, String) {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Length: 0\r\nAuthorization: {AUTH}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).unwrap();
    let status = out
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap();
    (status, out)
}

fn request(addr: SocketAddr, method: &str, path: &str) -> u16 {
    raw(addr, method, path).0
}

/// Sum of object sizes under a prefix (follows continuation tokens).
fn listed_bytes(addr: SocketAddr, prefix: &str) -> u64 {
    let mut total = 0;
    let mut token = String::new();
    loop {
        let path = format!(
            "/{BUCKET}?list-type=2&prefix={prefix}{}",
            if token.is_empty() {
                String::new()
            } else {
                format!(
                    "&continuation-token={}",
                    token
                        .replace('=', "%3D")
                        .replace('+', "%2B")
                        .replace('/', "%2F")
                )
            }
        );
        let (status, body) = raw(addr, "GET", &path);
        assert_eq!(status, 200, "{body}");
        total += body
            .split("<Size>")
            .skip(1)
            .filter_map(|s| s.split_once("</Size>")?.0.parse::<u64>().ok())
            .sum::<u64>();
        match body
            .split_once("<NextContinuationToken>")
            .and_then(|(_, rest)| rest.split_once("</NextContinuationToken>"))
        {
            Some((t, _)) => token = t.to_owned(),
            None => return total,
        }
    }
}
