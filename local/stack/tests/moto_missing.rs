//! Its own test binary: it changes the environment.

use local_stack::moto::MotoServer;

#[test]
fn a_missing_moto_is_reported_with_every_place_looked_at_and_the_fix() {
    // Runs in its own test binary, so changing the environment is safe here.
    std::env::set_var("LB_MOTO_SERVER", "/nonexistent/moto_server");
    let err = MotoServer::start().unwrap_err();
    assert!(err.to_string().contains("run `make venv`"), "{err}");
    assert!(
        err.to_string().contains("`/nonexistent/moto_server`"),
        "{err}"
    );

    // NB: one test, not two: both halves change the process environment.
    // Without the variable: beside this program, in the venvs, on PATH, in that order.
    std::env::remove_var("LB_MOTO_SERVER");
    let dir = tempfile::tempdir().unwrap();
    let bin = dir.path().join("bin");
    std::fs::create_dir_all(&bin).unwrap();
    std::env::set_var("PATH", &bin);
    let candidates = MotoServer::candidates();
    let exe_dir = std::env::current_exe()
        .unwrap()
        .parent()
        .unwrap()
        .to_owned();
    assert_eq!(candidates[0], exe_dir.join("moto_server"));
    assert!(candidates
        .iter()
        .any(|p| p.ends_with(".venv/bin/moto_server")));
    assert_eq!(candidates.last().unwrap(), &bin.join("moto_server"));
    // One on PATH is found (when no venv comes first).
    std::fs::write(bin.join("moto_server"), "#!/bin/sh\n").unwrap();
    let found = MotoServer::executable().unwrap();
    assert!(found.is_file(), "{}", found.display());
}
