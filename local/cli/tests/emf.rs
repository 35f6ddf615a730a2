//! CloudWatch's embedded metric format, checked from its specification and not from our
//! writer: what a local run's functions printed is held to it.
//!
//! The specification (CloudWatch's "Specification: Embedded metric format"): a root object
//! with `_aws` holding `Timestamp` (epoch milliseconds) and `CloudWatchMetrics`, an array of
//! directives, each with `Namespace`, `Dimensions` (an array of dimension sets, each an array
//! of at most 30 member names) and `Metrics` (at most 100, each with `Name` and optionally
//! `Unit` from CloudWatch's list); every dimension a directive names is a string member of the
//! root, every metric a number member or an array of at most 100 numbers.

use serde_json::Value;

/// CloudWatch's units.
const UNITS: &[&str] = &[
    "Seconds",
    "Microseconds",
    "Milliseconds",
    "Bytes",
    "Kilobytes",
    "Megabytes",
    "Gigabytes",
    "Terabytes",
    "Bits",
    "Kilobits",
    "Megabits",
    "Gigabits",
    "Terabits",
    "Percent",
    "Count",
    "Bytes/Second",
    "Kilobytes/Second",
    "Megabytes/Second",
    "Gigabytes/Second",
    "Terabytes/Second",
    "Bits/Second",
    "Kilobits/Second",
    "Megabits/Second",
    "Gigabits/Second",
    "Terabits/Second",
    "Count/Second",
    "None",
];

/// The dimensions a document may use: a submission's or a team's id would make a metric per
/// submission.
const DIMENSIONS: &[&str] = &["Stage", "Leaderboard", "Outcome", "Reason"];

/// Every way `doc` breaks the specification or our bounds.
pub(crate) fn problems(doc: &Value) -> Vec<String> {
    let mut out = Vec::new();
    let Some(root) = doc.as_object() else {
        return vec!["not a JSON object".into()];
    };
    let aws = &doc["_aws"];
    match aws["Timestamp"].as_u64() {
        // Between 2020 and 2100: milliseconds, not seconds.
        Some(ms) if (1_577_836_800_000..4_102_444_800_000).contains(&ms) => {}
        other => out.push(format!(
            "_aws.Timestamp is not epoch milliseconds: {other:?}"
        )),
    }
    let Some(directives) = aws["CloudWatchMetrics"]
        .as_array()
        .filter(|d| !d.is_empty())
    else {
        out.push("_aws.CloudWatchMetrics is not a non-empty array".into());
        return out;
    };
    let mut seen = std::collections::BTreeSet::new();
    for (i, d) in directives.iter().enumerate() {
        match d["Namespace"].as_str() {
            Some(ns) if !ns.is_empty() && ns.len() <= 255 && !ns.starts_with(':') => {}
            other => out.push(format!("directive {i}: bad Namespace {other:?}")),
        }
        let Some(sets) = d["Dimensions"].as_array() else {
            out.push(format!("directive {i}: Dimensions is not an array"));
            continue;
        };
        for set in sets {
            let Some(keys) = set.as_array() else {
                out.push(format!("directive {i}: a dimension set is not an array"));
                continue;
            };
            if keys.len() > 30 {
                out.push(format!("directive {i}: {} dimensions in a set", keys.len()));
            }
            for key in keys {
                let Some(key) = key.as_str() else {
                    out.push(format!("directive {i}: a dimension name is not a string"));
                    continue;
                };
                if !DIMENSIONS.contains(&key) {
                    out.push(format!(
                        "directive {i}: dimension `{key}` is not one we allow"
                    ));
                }
                match root.get(key).and_then(Value::as_str) {
                    Some(v) if !v.is_empty() && v.len() <= 1024 => {}
                    other => out.push(format!("dimension `{key}` has no string value: {other:?}")),
                }
            }
        }
        let Some(metrics) = d["Metrics"].as_array() else {
            out.push(format!("directive {i}: Metrics is not an array"));
            continue;
        };
        if metrics.len() > 100 {
            out.push(format!("directive {i}: {} metrics", metrics.len()));
        }
        for m in metrics {
            let Some(name) = m["Name"]
                .as_str()
                .filter(|n| !n.is_empty() && n.len() <= 255)
            else {
                out.push(format!("directive {i}: a metric without a Name: {m}"));
                continue;
            };
            if !seen.insert(name.to_owned()) {
                out.push(format!("metric `{name}` defined twice"));
            }
            if let Some(unit) = m.get("Unit") {
                if !unit.as_str().is_some_and(|u| UNITS.contains(&u)) {
                    out.push(format!("metric `{name}`: unit {unit} is not CloudWatch's"));
                }
            }
            let ok = match root.get(name) {
                Some(Value::Number(_)) => true,
                Some(Value::Array(values)) => {
                    !values.is_empty() && values.len() <= 100 && values.iter().all(Value::is_number)
                }
                _ => false,
            };
            if !ok {
                out.push(format!(
                    "metric `{name}` has no number or array of at most 100 numbers"
                ));
            }
        }
    }
    out
}

#[test]
fn the_checker_finds_each_way_a_document_breaks_the_format() {
    let good = serde_json::json!({
        "_aws": {"Timestamp": 1_764_500_000_000u64, "CloudWatchMetrics": [
            {"Namespace": "CarlaLeaderboard", "Dimensions": [["Stage"]],
             "Metrics": [{"Name": "Invocations", "Unit": "Count"}]}]},
        "Stage": "monitor", "Invocations": 1
    });
    assert_eq!(problems(&good), Vec::<String>::new());
    let broken = |path: &str, value: Value| {
        let mut doc = good.clone();
        *doc.pointer_mut(path).unwrap() = value;
        problems(&doc)
    };
    assert!(
        !broken("/_aws/Timestamp", 1_764_500_000u64.into()).is_empty(),
        "seconds"
    );
    assert!(!broken("/_aws/CloudWatchMetrics", serde_json::json!([])).is_empty());
    let ns = "/_aws/CloudWatchMetrics/0/Namespace";
    assert!(!broken(ns, "".into()).is_empty());
    let dims = "/_aws/CloudWatchMetrics/0/Dimensions";
    assert!(!broken(dims, serde_json::json!([["SubmissionId"]])).is_empty());
    assert!(
        !broken(dims, serde_json::json!([["Leaderboard"]])).is_empty(),
        "no value"
    );
    let unit = "/_aws/CloudWatchMetrics/0/Metrics/0/Unit";
    assert!(!broken(unit, "Dollars".into()).is_empty());
    assert!(!broken("/Invocations", "1".into()).is_empty());
    assert!(!broken("/Invocations", serde_json::json!(vec![1; 101])).is_empty());
}
