//! `lbctl local run` as a maintainer runs it: each scenario ends as it should, with exit 0.

use std::process::Command;
use std::time::Instant;

#[test]
#[ignore = "needs moto"]
fn every_scenario_ends_as_expected() {
    // lbctl finds the sidecar and the fakes next to itself.
    local_stack::workloads::Binaries::build().expect("the workloads build");
    // One at a time: local Jobs share the host's CARLA ports.
    for (scenario, expected) in [
        ("happy", "FINISHED"),
        ("crash", "FINISHED"),
        ("hang", "FINISHED"),
        ("cancel", "CANCELLED"),
        ("unpullable", "FAILED"),
    ] {
        let started = Instant::now();
        let out = Command::new(env!("CARGO_BIN_EXE_lbctl"))
            .args(["local", "run", "--scenario", scenario, "--timeout", "240"])
            .output()
            .unwrap();
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(
            out.status.success(),
            "{scenario}: {stdout}\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert!(
            stdout.contains(&format!("EvalAI status  {}", expected.to_lowercase())),
            "{scenario}: {stdout}"
        );
        assert!(stdout.contains("OK: the"), "{scenario}: {stdout}");
        assert!(
            started.elapsed().as_secs() < 60,
            "{scenario} took {:?}",
            started.elapsed()
        );
    }
}

#[test]
fn bad_arguments_are_named() {
    let out = Command::new(env!("CARGO_BIN_EXE_lbctl"))
        .args(["local", "run", "--scenario", "nope"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("--scenario"));
    let out = Command::new(env!("CARGO_BIN_EXE_lbctl"))
        .args(["local", "run", "--time-scale", "0"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("--time-scale"));
}
