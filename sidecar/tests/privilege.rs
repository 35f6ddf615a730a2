//! The IRSA role of the init and logcopy containers (`JobsRole` in `infra/cluster.yaml`)
//! allows exactly the S3 calls `lb-sidecar` can make (read from its symbols), on this
//! leaderboard's bucket under the prefixes the sidecar writes, and nothing else.

use lb_infra::template::CLUSTER;
use test_support::privilege;

#[test]
fn the_jobs_role_allows_exactly_what_the_sidecar_calls() {
    let binary = std::path::Path::new(env!("CARGO_BIN_EXE_lb-sidecar"));
    let symbols = privilege::symbols(binary).unwrap();
    let needed = privilege::needed_actions(&symbols);
    assert!(
        needed.iter().all(|a| a.starts_with("s3:")),
        "the sidecar calls only S3: {needed:?}"
    );
    let statements = CLUSTER.role_statements("JobsRole", None).unwrap();
    let allowed = privilege::allowed(&statements);
    let problems = privilege::compare("lb-sidecar (JobsRole)", &needed, &allowed);
    assert!(problems.is_empty(), "{}", problems.join("\n"));

    let bucket = "arn:aws:s3:::leaderboard-20-results";
    for (action, resources) in &allowed {
        for r in resources {
            let scoped = if action == "s3:ListBucket" {
                r == bucket
            } else {
                ["agent", "logs", "containers-status", "recorder"]
                    .iter()
                    .any(|prefix| r == &format!("{bucket}/*/{prefix}/*"))
            };
            assert!(
                scoped,
                "`{action}` on `{r}` reaches beyond the sidecar's prefixes"
            );
        }
    }
    // Every folder logcopy uploads is writable, and the logs' and recordings' tags too (the
    // actions alone do not say where: a folder missing here fails only in the deployment).
    use lb_domain::job::protocol::{AGENT_DIR, LOGS_DIR, RECORDER_DIR, STATUS_DIR};
    let allows = |action: &str, dir: &str| {
        allowed
            .get(action)
            .is_some_and(|r| r.contains(&format!("{bucket}/*/{dir}/*")))
    };
    for dir in [AGENT_DIR, STATUS_DIR, LOGS_DIR, RECORDER_DIR] {
        assert!(
            allows("s3:PutObject", dir),
            "logcopy cannot upload `{dir}/`"
        );
    }
    for dir in [LOGS_DIR, RECORDER_DIR] {
        assert!(
            allows("s3:PutObjectTagging", dir),
            "logcopy cannot tag `{dir}/`"
        );
    }
    // Not the merged results nor the EvalAI files: those are the functions' to write.
    assert!(!allowed
        .values()
        .flatten()
        .any(|r| r == &format!("{bucket}/*")));
    let root = CLUSTER.root();
    assert!(root["Resources"]["JobsRole"]["Properties"]["ManagedPolicyArns"].is_null());
}
