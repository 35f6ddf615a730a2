//! Least privilege, checked both ways: the AWS calls a compiled binary can make against the
//! actions its role allows.
//!
//! What a binary can call is read from the binary itself: the linker keeps only code that is
//! reachable (`--gc-sections`, Rust's default for executables), and every SDK call leaves
//! symbols under `aws_sdk_<service>::operation::<operation>`. So the set is what the compiler
//! found reachable from `main`, not a list someone keeps. Symbols are read with `nm` (binutils,
//! beside gcc on every build machine) and matched in their mangled form, which spells each
//! path segment as `<length><name>` under both the legacy and the v0 mangling.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::process::Command;

use lb_infra::template::{Statement, Template};

/// One SDK operation, e.g. `("dynamodb", "get_item")`.
pub type Operation = (String, String);

/// Why the symbols could not be read.
#[derive(Debug, thiserror::Error)]
pub enum SymbolsError {
    /// `nm` did not run.
    #[error("running `nm {path}`: {source}")]
    Nm {
        /// The binary.
        path: String,
        /// Why.
        source: std::io::Error,
    },
    /// `nm` failed.
    #[error("`nm {path}` failed: {stderr}")]
    Failed {
        /// The binary.
        path: String,
        /// What it said.
        stderr: String,
    },
}

/// The symbol names of `binary`.
pub fn symbols(binary: &Path) -> Result<String, SymbolsError> {
    let path = binary.display().to_string();
    let out = Command::new("nm")
        .arg("--no-demangle")
        .arg(binary)
        .output()
        .map_err(|source| SymbolsError::Nm {
            path: path.clone(),
            source,
        })?;
    if !out.status.success() {
        return Err(SymbolsError::Failed {
            path,
            stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
        });
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// Reads `<len><ident>` at the start of `s`.
fn ident(s: &str) -> Option<(&str, &str)> {
    let digits = s.bytes().take_while(u8::is_ascii_digit).count();
    let len: usize = s[..digits].parse().ok()?;
    let rest = &s[digits..];
    (rest.len() >= len).then(|| (&rest[..len], &rest[len..]))
}

/// The SDK operations whose code is in `symbols`.
pub fn sdk_operations(symbols: &str) -> BTreeSet<Operation> {
    let mut out = BTreeSet::new();
    let mut rest = symbols;
    while let Some(at) = rest.find("aws_sdk_") {
        // Back up over the length prefix of the crate name.
        let start = rest[..at]
            .char_indices()
            .rev()
            .take_while(|(_, c)| c.is_ascii_digit())
            .last()
            .map_or(at, |(i, _)| i);
        let parsed = ident(&rest[start..]).and_then(|(krate, tail)| {
            let service = krate.strip_prefix("aws_sdk_")?;
            let (module, tail) = ident(tail)?;
            (module == "operation").then_some(())?;
            let (operation, _) = ident(tail)?;
            Some((service.to_string(), operation.to_string()))
        });
        if let Some(op) = parsed {
            out.insert(op);
        }
        rest = &rest[at + "aws_sdk_".len()..];
    }
    out
}

/// Whether `type_name` (a type of ours, e.g. `QualifierTable`) has code in `symbols`.
pub fn has_type(symbols: &str, module: &str, type_name: &str) -> bool {
    symbols.contains(&format!(
        "{}{module}{}{type_name}",
        module.len(),
        type_name.len()
    ))
}

/// The IAM action an SDK operation needs, or `None` for operations the SDK makes on its own
/// and no identity policy grants (Service Authorization Reference):
/// - `sts:AssumeRole*`: aws-config's credential providers (on Lambda the credentials come
///   from the environment; IRSA's `AssumeRoleWithWebIdentity` is granted by the role's trust
///   policy, not by an identity policy);
/// - `s3:CreateSession`: S3 Express directory buckets only; ours are general purpose buckets.
///
/// DynamoDB's `TransactWriteItems` is no action of its own: each of its items is authorized as
/// the operation it is (`PutItem`, `UpdateItem`, `DeleteItem`, `ConditionCheckItem`: "Using
/// IAM with DynamoDB transactions", DynamoDB developer guide). Ours (`lb_aws::admission`) are
/// `Update`s, `Delete`s and `ConditionCheck`s: the items' actions are counted by
/// [`needed_actions`] from their builders' code.
pub fn iam_action(service: &str, operation: &str) -> Option<String> {
    let pascal: String = operation
        .split('_')
        .map(|w| {
            let mut c = w.chars();
            c.next()
                .map(|f| f.to_ascii_uppercase().to_string() + c.as_str())
                .unwrap_or_default()
        })
        .collect();
    match (service, operation) {
        ("sts", _) => None,
        ("s3", "create_session") => None,
        ("dynamodb", "transact_write_items") => None,
        ("s3", "head_object") => Some("s3:GetObject".into()),
        ("s3", "list_objects_v2") => Some("s3:ListBucket".into()),
        ("s3", "create_multipart_upload" | "upload_part" | "complete_multipart_upload") => {
            Some("s3:PutObject".into())
        }
        ("sfn", _) => Some(format!("states:{pascal}")),
        _ => Some(format!("{service}:{pascal}")),
    }
}

/// The actions the code in `symbols` needs.
pub fn needed_actions(symbols: &str) -> BTreeSet<String> {
    let mut needed: BTreeSet<String> = sdk_operations(symbols)
        .iter()
        .filter_map(|(s, o)| iam_action(s, o))
        .collect();
    // A transaction's items (`aws_sdk_dynamodb::types::ConditionCheck::builder` and its
    // kin, mangled): only code that builds such an item links its builder.
    let items = [
        ("16_condition_check14ConditionCheck", "ConditionCheckItem"),
        ("7_update6Update", "UpdateItem"),
        ("7_delete6Delete", "DeleteItem"),
    ];
    for (item, action) in items {
        let builder = format!("16aws_sdk_dynamodb5types{item}7builder");
        if symbols.contains(&builder) {
            needed.insert(format!("dynamodb:{action}"));
        }
    }
    // An upload that tags its object (`set_tagging` on `PutObject` or
    // `CreateMultipartUpload`) needs `s3:PutObjectTagging` beside the upload's own action.
    let tags = [
        "22PutObjectFluentBuilder11set_tagging",
        "34CreateMultipartUploadFluentBuilder11set_tagging",
    ];
    if tags.iter().any(|t| symbols.contains(t)) {
        needed.insert("s3:PutObjectTagging".into());
    }
    needed
}

/// The actions `statements` allow, each with the resources it is allowed on.
pub fn allowed(statements: &[Statement]) -> BTreeMap<String, BTreeSet<String>> {
    let mut out: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for s in statements.iter().filter(|s| s.effect == "Allow") {
        for a in &s.actions {
            out.entry(a.clone())
                .or_default()
                .extend(s.resources.iter().cloned());
        }
    }
    out
}

/// Actions whose only resource is `*` (Service Authorization Reference: no resource type).
/// `states:SendTaskSuccess` reports a task token, which is not an ARN.
pub const UNSCOPED: [&str; 1] = ["states:SendTaskSuccess"];

/// What an SQS event source mapping does with its function's role (Lambda developer guide,
/// "Execution role permissions"), on its queue only.
pub const EVENT_SOURCE_ACTIONS: [&str; 3] = [
    "sqs:DeleteMessage",
    "sqs:GetQueueAttributes",
    "sqs:ReceiveMessage",
];

/// Every execution of one state machine (`...:execution:<machine>:*`): executions are named
/// as they start, so this is the narrowest an execution ARN can be written in a policy.
fn one_machines_executions(resource: &str) -> bool {
    resource
        .strip_suffix(":*")
        .and_then(|r| r.split_once(":execution:"))
        .is_some_and(|(_, machine)| !machine.is_empty() && !machine.contains([':', '*']))
}

/// The differences between what code needs and what a policy allows, in words.
pub fn compare(
    who: &str,
    needed: &BTreeSet<String>,
    allowed: &BTreeMap<String, BTreeSet<String>>,
) -> Vec<String> {
    let mut problems = Vec::new();
    for action in needed.iter().filter(|a| !allowed.contains_key(*a)) {
        problems.push(format!(
            "{who}'s code calls `{action}`, which its role does not allow"
        ));
    }
    for action in allowed.keys().filter(|a| !needed.contains(*a)) {
        problems.push(format!(
            "{who}'s role allows `{action}`, which its code never calls"
        ));
    }
    for (action, resources) in allowed {
        let unscoped_by_design =
            UNSCOPED.contains(&action.as_str()) && resources.iter().all(|r| r == "*");
        if !unscoped_by_design
            && (resources.is_empty()
                || resources
                    .iter()
                    .any(|r| r.contains('*') && !r.ends_with("/*") && !one_machines_executions(r)))
        {
            problems.push(format!(
                "{who}'s role allows `{action}` on {resources:?}: name the resources"
            ));
        }
    }
    problems
}

/// Everything wrong with the role of function `function` (a logical id of `template`) for
/// the binary at `binary`: actions both ways, resources named, DynamoDB tables of the kinds its
/// code uses, the runtime's log permissions on its own log group only, no managed policy.
pub fn check_function(template: &Template, function: &str, binary: &Path) -> Vec<String> {
    let symbols = match symbols(binary) {
        Ok(s) => s,
        Err(e) => return vec![e.to_string()],
    };
    let role = match template.text(function, &["Role"]) {
        Ok(r) => r
            .trim_start_matches('<')
            .trim_end_matches(".Arn>")
            .to_string(),
        Err(e) => return vec![e.to_string()],
    };
    let code = match template.role_statements(&role, Some("code")) {
        Ok(s) => s,
        Err(e) => return vec![e.to_string()],
    };
    let allowed = allowed(&code);
    let mut problems = compare(function, &needed_actions(&symbols), &allowed);

    // Tables: a statement on submissions tables only if the code has the submissions adapter,
    // on qualifier tables only if it has the qualifier adapter, and each used kind is named.
    let table_kinds: BTreeSet<&str> = allowed
        .iter()
        .filter(|(a, _)| a.starts_with("dynamodb:"))
        .flat_map(|(_, r)| r.iter())
        .filter_map(|arn| {
            let name = arn.rsplit("table/").next()?;
            ["Submissions", "Qualifier"].into_iter().find(|kind| {
                template
                    .parameter_names_with_value(name)
                    .iter()
                    .any(|p| p.ends_with(&format!("{kind}Table")))
            })
        })
        .collect();
    for (kind, type_name) in [
        ("Submissions", "SubmissionsTable"),
        ("Qualifier", "QualifierTable"),
    ] {
        let used = has_type(&symbols, "dynamo", type_name);
        if used != table_kinds.contains(kind) {
            problems.push(format!(
                "{function}: the code {} `{type_name}` but the role {} {kind} tables",
                if used { "uses" } else { "never uses" },
                if table_kinds.contains(kind) {
                    "names"
                } else {
                    "does not name"
                },
            ));
        }
    }

    let log_group = template
        .text(function, &["LoggingConfig", "LogGroup"])
        .unwrap_or_default();
    let logs = allowed_or_empty(template, &role, "logs");
    let expected: BTreeMap<String, BTreeSet<String>> =
        ["logs:CreateLogStream", "logs:PutLogEvents"]
            .into_iter()
            .map(|a| {
                (
                    a.to_string(),
                    BTreeSet::from([format!("{}.Arn>", log_group.trim_end_matches('>'))]),
                )
            })
            .collect();
    if logs != expected {
        problems.push(format!(
            "{function}: its `logs` policy must allow exactly writing to its own log group {log_group}, found {logs:?}"
        ));
    }
    let root = template.root();
    let props = &root["Resources"][role.as_str()]["Properties"];
    if !props["ManagedPolicyArns"].is_null() {
        problems.push(format!(
            "{function}: its role has managed policies, which no test can hold to the code"
        ));
    }
    let policies: Vec<_> = props["Policies"]
        .as_sequence()
        .into_iter()
        .flatten()
        .filter_map(|p| p["PolicyName"].as_str())
        .collect();
    let queues = event_source_queues(template, function);
    let expected: &[&str] = if queues.is_empty() {
        &["logs", "code"]
    } else {
        &["logs", "code", "source"]
    };
    if policies != expected {
        problems.push(format!(
            "{function}: its role's policies are {policies:?}, expected {expected:?}"
        ));
    }
    if !queues.is_empty() {
        let source = allowed_or_empty(template, &role, "source");
        let expected: BTreeMap<String, BTreeSet<String>> = EVENT_SOURCE_ACTIONS
            .iter()
            .map(|a| (a.to_string(), queues.clone()))
            .collect();
        if source != expected {
            problems.push(format!(
                "{function}: its `source` policy must allow exactly what its event source mapping does on {queues:?}, found {source:?}"
            ));
        }
    }
    problems
}

/// The queues (as `<Id.Arn>`) whose event source mappings invoke `function` (or its alias).
fn event_source_queues(template: &Template, function: &str) -> BTreeSet<String> {
    let names = [format!("<{function}>"), format!("<{function}.Alias>")];
    template
        .resources_of("AWS::Lambda::EventSourceMapping")
        .into_iter()
        .filter(|id| {
            let target = template.text(id, &["FunctionName"]).unwrap_or_default();
            names.contains(&target)
        })
        .filter_map(|id| template.text(&id, &["EventSourceArn"]).ok())
        .collect()
}

fn allowed_or_empty(
    template: &Template,
    role: &str,
    policy: &str,
) -> BTreeMap<String, BTreeSet<String>> {
    template
        .role_statements(role, Some(policy))
        .map(|s| allowed(&s))
        .unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn operations_are_read_from_legacy_and_v0_mangled_names() {
        let symbols = "\
0000 T _ZN16aws_sdk_dynamodb9operation8get_item8builders20GetItemFluentBuilder4send17h0E
0000 T _RNvMNtNtNtCs1_10aws_sdk_s39operation11head_object8buildersNtB2_1X4send
0000 T _ZN11aws_sdk_sts9operation11assume_role5Thing17h1E
0000 T _ZN16aws_sdk_dynamodb6config6Config3new17h2E
0000 T _ZN6lb_aws6dynamo14QualifierTable5admit17h3E
";
        let ops = sdk_operations(symbols);
        assert_eq!(
            ops.into_iter().collect::<Vec<_>>(),
            [
                ("dynamodb".to_string(), "get_item".to_string()),
                ("s3".into(), "head_object".into()),
                ("sts".into(), "assume_role".into()),
            ]
        );
        assert_eq!(
            needed_actions(symbols).into_iter().collect::<Vec<_>>(),
            ["dynamodb:GetItem", "s3:GetObject"]
        );
        assert!(has_type(symbols, "dynamo", "QualifierTable"));
        assert!(!has_type(symbols, "dynamo", "SubmissionsTable"));
    }

    #[test]
    fn actions_are_named_as_iam_names_them() {
        assert_eq!(
            iam_action("secretsmanager", "get_secret_value").as_deref(),
            Some("secretsmanager:GetSecretValue")
        );
        assert_eq!(
            iam_action("eks", "describe_cluster").as_deref(),
            Some("eks:DescribeCluster")
        );
        assert_eq!(
            iam_action("s3", "list_objects_v2").as_deref(),
            Some("s3:ListBucket")
        );
        assert_eq!(
            iam_action("sfn", "start_execution").as_deref(),
            Some("states:StartExecution")
        );
        assert_eq!(iam_action("s3", "create_session"), None);
    }
}
