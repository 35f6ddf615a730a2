//! Monitor's role in `infra/app.yaml` allows exactly the AWS calls this binary can make
//! (read from its symbols: `test_support::privilege`).

#[test]
fn the_role_allows_exactly_what_the_code_calls() {
    let binary = std::path::Path::new(env!("CARGO_BIN_EXE_monitor"));
    let problems = test_support::privilege::check_function(
        &lb_infra::template::APP,
        "MonitorFunction",
        binary,
    );
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}
