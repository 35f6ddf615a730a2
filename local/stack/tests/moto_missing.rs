//! Where `moto_server` is looked for, and what a missing one says.

use local_stack::moto::{Lookup, MotoServer};

#[test]
fn a_missing_moto_is_reported_with_every_place_looked_at_and_the_fix() {
    let err = MotoServer::executable_in(&Lookup {
        override_path: Some("/nonexistent/moto_server".into()),
        path: None,
    })
    .unwrap_err();
    assert!(err.to_string().contains("run `make venv`"), "{err}");
    assert!(
        err.to_string().contains("`/nonexistent/moto_server`"),
        "{err}"
    );
}

#[test]
fn without_the_variable_moto_is_looked_for_beside_this_program_in_the_venvs_then_on_path() {
    let dir = tempfile::tempdir().unwrap();
    let bin = dir.path().join("bin");
    std::fs::create_dir_all(&bin).unwrap();
    let lookup = Lookup {
        override_path: None,
        path: Some(bin.clone().into_os_string()),
    };
    let candidates = MotoServer::candidates_in(&lookup);
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
    // One on PATH is found when nothing before it is a file: here, a venv of the checkout
    // usually is, so only its place in the order is checked.
    std::fs::write(bin.join("moto_server"), "#!/bin/sh\n").unwrap();
    let found = MotoServer::executable_in(&lookup).unwrap();
    assert!(found.is_file(), "{}", found.display());
    assert!(candidates.contains(&found), "{}", found.display());
}
