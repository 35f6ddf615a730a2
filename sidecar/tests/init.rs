//! `lb-sidecar init` against moto: code, binary, logs tree, stale state, downloads.

use crate::support;

use std::os::unix::fs::PermissionsExt;
use std::time::Duration;

use support::*;

const LIMIT: Duration = Duration::from_secs(60);

fn key(rel: &str) -> String {
    format!("{SUBMISSION}/{rel}")
}

fn mode(path: &std::path::Path) -> u32 {
    std::fs::metadata(path).unwrap().permissions().mode() & 0o777
}

#[test]
#[ignore = "needs moto"]
fn init_fills_the_volumes_and_clears_this_jobs_stale_state_on_a_participant_resume() {
    let moto = Moto::start();
    let vols = Volumes::new();
    let code = tempfile::tempdir().unwrap();
    // The participant's image put its own (modified) leaderboard in the volume.
    std::fs::create_dir_all(code.path().join("dst/leaderboard")).unwrap();
    std::fs::write(code.path().join("dst/leaderboard/hacked.py"), "x").unwrap();
    // A previous pod of this Job (pair 1) and another Job (pair 2) left state in S3.
    for m in [
        "simulator-1.start0",
        "agent-1.crash0",
        "logcopy-0.done",
        "agent-2.done",
        "logcopy-1.done",
        "simulation.cancel",
    ] {
        moto.put(&key(&format!("containers-status/{m}")), b"");
    }
    moto.put(
        &key("agent/partial_agent_results1.json"),
        b"{\"partial\": 1}",
    );
    moto.put(
        &key("agent/partial_agent_results2.json"),
        b"{\"other job\": 1}",
    );
    moto.put(&key("logs/agent/agent1/agent.log"), b"first pod\n");
    moto.put(&key("recorder/pair1/RouteScenario_0_rep0.log"), b"big");
    moto.put(&key("logs/simulator/simulator1.log"), b"carla\n");
    moto.put(&key("logs/simulator/simulator2.log"), b"other\n");
    // And a stale local marker (an init re-run in the same pod).
    std::fs::write(vols.status().join("agent-1.crash0"), "").unwrap();

    let mut init = init_command(&vols, &moto, code.path(), &[("LB_PARTICIPANT_RESUME", "1")]);
    assert_eq!(init.wait(LIMIT).code(), Some(0), "{}", init.log());

    // Official code, overwriting the participant's.
    let lb = code.path().join("dst/leaderboard");
    assert!(!lb.join("hacked.py").exists());
    assert_eq!(
        std::fs::read_to_string(lb.join("sub/official.py")).unwrap(),
        "# official leaderboard\n"
    );
    assert!(code.path().join("dst/CARLA/sub/official.py").exists());
    // The sidecar itself, executable.
    let bin = code.path().join("bin/lb-sidecar");
    assert_eq!(
        std::fs::read(&bin).unwrap(),
        std::fs::read(SIDECAR).unwrap()
    );
    assert_eq!(mode(&bin), 0o755);
    // The logs tree, open to the participant's user.
    for dir in [
        "containers-status",
        "agent",
        "logs/simulator",
        "logs/agent/agent1",
        "logs/logcopy",
    ] {
        assert_eq!(mode(&vols.root().join(dir)), 0o777, "{dir}");
    }
    // The recordings' folder: CARLA's alone (only its simulator mounts it).
    assert_eq!(mode(&vols.root().join("recorder/pair1")), 0o755);
    // This Job's markers are gone, locally and in S3; the other Job's stay; cancel removed.
    assert_eq!(
        moto.keys(&key("containers-status/")),
        [
            key("containers-status/agent-2.done"),
            key("containers-status/logcopy-1.done")
        ]
    );
    assert!(vols.markers().is_empty(), "{:?}", vols.markers());
    // This Job's results and logs are back; recordings and other Jobs' files are not.
    assert_eq!(
        std::fs::read(vols.checkpoint(1)).unwrap(),
        b"{\"partial\": 1}"
    );
    assert_eq!(mode(&vols.checkpoint(1)), 0o666);
    assert!(!vols.checkpoint(2).exists());
    assert_eq!(vols.agent_log(1), "first pod\n");
    assert_eq!(vols.simulator_log(1), "carla\n");
    assert!(!vols.root().join("logs/simulator/simulator2.log").exists());
    assert!(!vols
        .root()
        .join("recorder/pair1/RouteScenario_0_rep0.log")
        .exists());
}

#[test]
#[ignore = "needs moto"]
fn without_a_participant_resume_init_keeps_and_mirrors_the_cancel_marker() {
    let moto = Moto::start();
    let vols = Volumes::new();
    let code = tempfile::tempdir().unwrap();
    moto.put(&key("containers-status/simulation.cancel"), b"");
    let mut init = init_command(&vols, &moto, code.path(), &[]);
    assert_eq!(init.wait(LIMIT).code(), Some(0), "{}", init.log());
    assert!(moto.exists(&key("containers-status/simulation.cancel")));
    assert_eq!(vols.markers(), ["simulation.cancel"]);
}

#[test]
fn init_names_a_missing_source_variable() {
    let out = std::process::Command::new(SIDECAR)
        .arg("init")
        .env_clear()
        .env("LB_SUBMISSION_ID", "1")
        .env("LB_JOB_INDEX", "0")
        .env("LB_LEADERBOARD", "2.0")
        .env("LB_PAIRS", "1")
        .env("LB_S3_BUCKET", "bucket")
        .env("AWS_REGION", "us-east-1")
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(78),
        "a malformed environment: no new pod can help"
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("lb-sidecar: InvalidEnvironment: `LB_SOURCE_LEADERBOARD` is not set"),
        "{err}"
    );
}
