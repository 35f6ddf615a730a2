//! `fake-carla` as a process: ports, signals, crashes and once-semantics.

use crate::common;

use std::io::Read as _;
use std::net::TcpStream;
use std::os::unix::process::ExitStatusExt as _;
use std::time::{Duration, Instant};

use common::*;

fn connect(port: u16) -> std::io::Result<TcpStream> {
    TcpStream::connect_timeout(
        &std::net::SocketAddr::from(([127, 0, 0, 1], port)),
        Duration::from_secs(2),
    )
}

/// Whether the server closed the connection within `limit` (EOF or reset).
fn closed_within(stream: &mut TcpStream, limit: Duration) -> bool {
    stream.set_read_timeout(Some(limit)).unwrap();
    let mut buf = [0u8; 16];
    match stream.read(&mut buf) {
        Ok(0) => true,
        Ok(_) => false,
        Err(e) => !matches!(
            e.kind(),
            std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
        ),
    }
}

#[test]
fn it_listens_on_both_ports_holds_connections_and_exits_zero_on_sigterm() {
    let dir = tempfile::tempdir().unwrap();
    let mut carla = start_carla(
        dir.path(),
        &[
            "-vulkan",
            "-RenderOffScreen",
            "-nosound",
            "-ini:[/Script/Engine.RendererSettings]:r.GraphicsAdapter=0",
            "-made-up-flag",
        ],
        &[],
    );
    assert_eq!(carla.streaming, carla.port + 1);
    assert!(
        carla
            .proc
            .seen
            .iter()
            .any(|l| l.contains("ignores the unknown argument `-made-up-flag`")),
        "{:?}",
        carla.proc.seen
    );
    let mut rpc = connect(carla.port).expect("rpc port accepts");
    let mut streaming = connect(carla.streaming).expect("streaming port accepts");
    assert!(
        !closed_within(&mut rpc, Duration::from_millis(200)),
        "rpc connection held"
    );
    assert!(!closed_within(&mut streaming, Duration::from_millis(50)));

    carla.proc.signal("TERM");
    let status = carla.proc.wait();
    assert_eq!(status.code(), Some(0), "{status:?}");
    assert!(closed_within(&mut rpc, Duration::from_secs(2)));
    assert!(connect(carla.port).is_err(), "the listener is gone");
}

#[test]
fn it_exits_zero_on_sigint() {
    let dir = tempfile::tempdir().unwrap();
    let mut carla = start_carla(dir.path(), &["-opengl", "-nosound"], &[]);
    carla.proc.signal("INT");
    assert_eq!(carla.proc.wait().code(), Some(0));
}

#[test]
fn it_crashes_by_sigabrt_after_the_configured_seconds_and_its_ports_close() {
    let dir = tempfile::tempdir().unwrap();
    let started = Instant::now();
    let mut carla = start_carla(dir.path(), &[], &[("FAKE_CARLA_CRASH_AFTER", "0.4")]);
    let mut rpc = connect(carla.port).expect("rpc port accepts");
    let status = carla.proc.wait();
    assert!(started.elapsed() >= Duration::from_millis(400));
    assert_eq!(status.signal(), Some(6), "{status:?}");
    assert!(carla.proc.stdout().contains("Signal 6 caught."));
    assert!(closed_within(&mut rpc, Duration::from_secs(2)));
    assert!(connect(carla.port).is_err());
    assert!(connect(carla.streaming).is_err());
}

#[test]
fn it_crashes_when_the_crash_file_appears() {
    let dir = tempfile::tempdir().unwrap();
    let trigger = dir.path().join("crash-now");
    let flag = format!("-fake-crash-file={}", trigger.display());
    let mut carla = start_carla(dir.path(), &[&flag, "-fake-crash-signal=exit"], &[]);
    std::thread::sleep(Duration::from_millis(300));
    assert!(carla.proc.is_running(), "no crash before the file exists");
    std::fs::write(&trigger, "").unwrap();
    let status = carla.proc.wait();
    assert_eq!(status.code(), Some(134), "{status:?}");
}

#[test]
fn a_segv_crash_dies_by_sigsegv() {
    let dir = tempfile::tempdir().unwrap();
    let mut carla = start_carla(
        dir.path(),
        &[],
        &[
            ("FAKE_CARLA_CRASH_AFTER", "0"),
            ("FAKE_CARLA_CRASH_SIGNAL", "segv"),
        ],
    );
    let status = carla.proc.wait();
    assert_eq!(status.signal(), Some(11), "{status:?}");
}

#[test]
fn with_a_once_directory_only_the_first_server_crashes() {
    let dir = tempfile::tempdir().unwrap();
    let once = dir.path().join("once");
    let once = once.to_str().unwrap();
    let env = [
        ("FAKE_CARLA_CRASH_AFTER", "0.2"),
        ("FAKE_CARLA_ONCE_DIR", once),
    ];
    let mut first = start_carla(dir.path(), &[], &env);
    assert_eq!(first.proc.wait().signal(), Some(6));
    assert!(dir.path().join("once/fake-carla-0.crash-after").exists());

    let mut second = start_carla(dir.path(), &[], &env);
    std::thread::sleep(Duration::from_millis(600));
    assert!(second.proc.is_running(), "the restarted server runs clean");
    second.proc.signal("TERM");
    assert_eq!(second.proc.wait().code(), Some(0));
}

#[test]
fn a_start_failure_exits_before_listening_and_once_lets_the_restart_listen() {
    let dir = tempfile::tempdir().unwrap();
    let once = dir.path().join("once");
    let once_flag = format!("-fake-once-dir={}", once.display());
    let env = [("FAKE_CARLA_FAIL_START", "1")];
    // NB: port 0 (a picked free pair) rather than a fixed port that another test's
    // ephemeral client port may take meanwhile.
    let mut cmd = command(CARLA, dir.path(), &env);
    cmd.args(["-carla-rpc-port=0", &once_flag]);
    let mut failing = Proc::spawn(cmd);
    assert_eq!(failing.wait().code(), Some(1));
    let out = failing.stdout();
    assert!(!out.contains("listening"), "{out}");
    assert!(out.contains("LowLevelFatalError"), "{out}");
    assert!(once.join("fake-carla-0.fail-start").exists());

    let mut restarted = start_carla(dir.path(), &[&once_flag], &env);
    assert!(connect(restarted.port).is_ok());
    restarted.proc.signal("TERM");
    assert_eq!(restarted.proc.wait().code(), Some(0));
}

#[test]
fn a_bad_port_is_refused_naming_the_flag() {
    let dir = tempfile::tempdir().unwrap();
    let mut cmd = command(CARLA, dir.path(), &[]);
    cmd.arg("-carla-rpc-port=twothousand");
    let mut p = Proc::spawn(cmd);
    assert_eq!(p.wait().code(), Some(2));
    assert!(p.stderr().contains("`-carla-rpc-port`"), "{}", p.stderr());

    let mut cmd = command(CARLA, dir.path(), &[("FAKE_CARLA_CRASH_AFTER", "later")]);
    cmd.arg("-carla-rpc-port=0");
    let mut p = Proc::spawn(cmd);
    assert_eq!(p.wait().code(), Some(2));
    assert!(
        p.stderr().contains("FAKE_CARLA_CRASH_AFTER"),
        "{}",
        p.stderr()
    );
}
