//! Its own test binary: it changes the environment.

use local_stack::moto::MotoServer;

#[test]
fn a_missing_moto_is_reported_with_the_fix() {
    // Runs in its own test binary, so changing the environment is safe here.
    std::env::set_var("LB_MOTO_SERVER", "/nonexistent/moto_server");
    let err = MotoServer::start().unwrap_err();
    assert!(err.to_string().contains("run `make venv`"), "{err}");
}
