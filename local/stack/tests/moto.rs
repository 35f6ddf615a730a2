//! The moto harness against a real `moto_server` from the project venv.

use local_stack::moto::{http, MotoServer};

#[test]
#[ignore = "needs moto"]
fn moto_starts_on_a_free_loopback_port_answers_and_stops_on_drop() {
    let server = MotoServer::start().expect("moto starts");
    let addr = server.addr();
    assert!(addr.ip().is_loopback());
    assert_eq!(server.endpoint(), format!("http://{addr}"));
    let (status, body) = http(addr, "GET", "/moto-api/data.json").unwrap();
    assert_eq!(status, 200);
    assert!(body.trim_start().starts_with('{'), "{body}");
    server.reset().unwrap();
    // Two servers side by side get distinct ports.
    let other = MotoServer::start().expect("second moto starts");
    assert_ne!(other.addr(), addr);
    drop(server);
    assert!(
        http(addr, "GET", "/moto-api/data.json").is_err(),
        "stopped on drop"
    );
}
