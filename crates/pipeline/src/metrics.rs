//! The fleet's metrics in CloudWatch's embedded metric format (EMF): the samples of one
//! invocation gathered on its task and written as one document when it ends.
//!
//! Written with serde rather than through a `metrics` facade backend: a facade's recorder is
//! global to the process, and local mode runs every function in one process, side by side;
//! a task's own samples keep each invocation's document its own, and the document is a few
//! lines of JSON whose every field a test checks against the format's specification.

use std::cell::RefCell;
use std::collections::BTreeMap;
use std::future::Future;
use std::sync::{Arc, OnceLock};

use lb_domain::results::Leaderboard;
use lb_domain::run::metrics::{Dimensions, Metric, Signals, NAMESPACE};
use serde_json::{json, Map, Value};

/// Values one metric keeps in a document (EMF's limit).
pub const MAX_VALUES: usize = 100;

/// Where documents go: a Lambda's stdout, where CloudWatch Logs extracts the metrics, unless
/// the process says otherwise (`lbctl local run` keeps its own).
pub type Sink = Arc<dyn Fn(&str) + Send + Sync>;

/// What one invocation gathered.
#[derive(Debug, Clone, Default)]
pub struct Gathered {
    /// Each metric's values, in the order sent.
    values: BTreeMap<Metric, Vec<f64>>,
    /// How a run ended here.
    outcome: Option<&'static str>,
    /// Why it failed.
    reason: Option<&'static str>,
    /// Values past [`MAX_VALUES`], left out.
    dropped: u64,
    /// The leaderboard, when the handler learned it (Intake's, from EvalAI).
    leaderboard: Option<Leaderboard>,
}

tokio::task_local! {
    static GATHERED: RefCell<Gathered>;
}

static SINK: OnceLock<Sink> = OnceLock::new();

/// Records what a stage's work said of the fleet on the current invocation.
pub fn record(signals: Signals) {
    let _ = GATHERED.try_with(|g| {
        let mut g = g.borrow_mut();
        for sample in signals.samples {
            g.push(sample.metric, sample.value);
        }
        g.outcome = signals.outcome.or(g.outcome);
        g.reason = signals.reason.or(g.reason);
    });
}

/// Records what a stage's work said of a submission of `leaderboard`: the document's
/// `Leaderboard` when its input did not name one.
pub fn record_for(leaderboard: Leaderboard, signals: Signals) {
    let _ = GATHERED.try_with(|g| g.borrow_mut().leaderboard = Some(leaderboard));
    record(signals);
}

/// Records one value on the current invocation (zeros are not sent).
pub fn sample(metric: Metric, value: f64) {
    let mut signals = Signals::default();
    signals.add(metric, value);
    record(signals);
}

impl Gathered {
    fn push(&mut self, metric: Metric, value: f64) {
        let values = self.values.entry(metric).or_default();
        if values.len() < MAX_VALUES {
            values.push(value);
        } else {
            self.dropped += 1;
        }
    }
}

/// Records one value on the current invocation, a zero too (a metric whose samples are
/// counted).
pub fn sample_count(metric: Metric, value: f64) {
    let _ = GATHERED.try_with(|g| g.borrow_mut().push(metric, value));
}

/// Runs `work` gathering its samples.
pub async fn gathering<F: Future>(work: F) -> (F::Output, Gathered) {
    GATHERED
        .scope(RefCell::new(Gathered::default()), async {
            let output = work.await;
            (output, GATHERED.with(|g| g.borrow().clone()))
        })
        .await
}

/// Sends this process's documents to `sink` instead of stdout; `false` when a sink was set
/// already (the first stays).
pub fn write_to(sink: Sink) -> bool {
    SINK.set(sink).is_ok()
}

/// Writes a document, one line, where this process's documents go.
pub fn write(document: &Value) {
    let line = document.to_string();
    match SINK.get() {
        Some(sink) => sink(&line),
        None => println!("{line}"),
    }
}

/// The invocation's document: the function's `stage`, its `leaderboard` when it knows one, at
/// `timestamp_ms`. One directive per dimension set a gathered metric needs; a metric whose
/// dimension has no value (a leaderboard metric of an invocation that knows none) is left out.
/// `None` when nothing is left.
pub fn document(
    stage: &str,
    leaderboard: Option<Leaderboard>,
    timestamp_ms: u64,
    gathered: &Gathered,
) -> Option<Value> {
    let leaderboard = leaderboard.or(gathered.leaderboard);
    let mut root = Map::new();
    root.insert("Stage".into(), stage.into());
    if let Some(lb) = leaderboard {
        root.insert("Leaderboard".into(), lb.as_str().into());
    }
    if let Some(outcome) = gathered.outcome {
        root.insert("Outcome".into(), outcome.into());
    }
    if let Some(reason) = gathered.reason {
        root.insert("Reason".into(), reason.into());
    }
    let mut directives: BTreeMap<Dimensions, Vec<Value>> = BTreeMap::new();
    for (metric, values) in &gathered.values {
        let dims = metric.dimensions();
        if values.is_empty() || !dims.keys().iter().all(|k| root.contains_key(*k)) {
            continue;
        }
        let value = match values.as_slice() {
            [one] => json!(one),
            many => json!(many),
        };
        root.insert(metric.name().into(), value);
        directives
            .entry(dims)
            .or_default()
            .push(json!({"Name": metric.name(), "Unit": metric.unit().as_str()}));
    }
    if directives.is_empty() {
        return None;
    }
    let directives: Vec<Value> = directives
        .into_iter()
        .map(|(dims, metrics)| {
            json!({"Namespace": NAMESPACE, "Dimensions": [dims.keys()], "Metrics": metrics})
        })
        .collect();
    root.insert(
        "_aws".into(),
        json!({"Timestamp": timestamp_ms, "CloudWatchMetrics": directives}),
    );
    Some(Value::Object(root))
}

/// What every invocation says of itself: its time (Lambda counts invocations and errors
/// itself), and what it asked of EvalAI.
pub fn invocation(
    gathered: &mut Gathered,
    elapsed: std::time::Duration,
    evalai: lb_evalai::tally::Tally,
) {
    gathered.push(Metric::Duration, elapsed.as_secs_f64() * 1000.0);
    let counts = [
        (Metric::EvalAiRequests, evalai.requests),
        (Metric::EvalAiThrottled, evalai.throttled),
        (Metric::EvalAiOverBudget, evalai.over_budget),
        (Metric::EvalAiBudgetWaits, evalai.budget_waits),
    ];
    for (metric, count) in counts {
        if count > 0 {
            gathered.push(metric, count as f64);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lb_domain::run::metrics::reason;

    #[tokio::test]
    async fn an_invocation_gathers_its_own_samples_into_one_document() {
        let (_, mut gathered) = gathering(async {
            sample(Metric::QueueLength, 3.0);
            sample(Metric::QueueLength, 4.0);
            sample(Metric::RoutesDone, 0.0);
            let mut end = Signals::default();
            end.ended("FAILED", Some(reason::PIPELINE));
            record(end);
        })
        .await;
        sample(Metric::Arrivals, 1.0); // outside any invocation: nowhere
        invocation(
            &mut gathered,
            std::time::Duration::from_millis(250),
            lb_evalai::tally::Tally {
                requests: 2,
                ..Default::default()
            },
        );
        let doc = document(
            "finalize",
            Some(Leaderboard::V2),
            1_700_000_000_000,
            &gathered,
        )
        .unwrap();
        assert_eq!(doc["Stage"], "finalize");
        assert_eq!(doc["Leaderboard"], "2.0");
        assert_eq!(doc["Reason"], "PipelineError");
        assert_eq!(doc["QueueLength"], json!([3.0, 4.0]));
        assert_eq!(doc["Duration"], json!(250.0));
        assert_eq!(doc["EvalAiRequests"], json!(2.0));
        assert!(doc.get("RoutesDone").is_none());
        assert!(doc.get("Arrivals").is_none());
        let directives = doc["_aws"]["CloudWatchMetrics"].as_array().unwrap();
        let sets: Vec<&Value> = directives.iter().map(|d| &d["Dimensions"]).collect();
        assert_eq!(
            sets,
            [
                &json!([[]]),
                &json!([["Stage"]]),
                &json!([["Leaderboard"]]),
                &json!([["Leaderboard", "Outcome"]]),
                &json!([["Leaderboard", "Reason"]]),
            ]
        );
        // Without a leaderboard, its metrics are left out rather than sent without it.
        let none = document("wake", None, 1, &gathered).unwrap();
        let sets = none["_aws"]["CloudWatchMetrics"].as_array().unwrap();
        assert_eq!(sets.len(), 2, "the account's and the stage's");
        assert!(none.get("QueueLength").is_none());
        assert!(document("wake", None, 1, &Gathered::default()).is_none());
    }

    #[test]
    fn a_metric_keeps_at_most_a_hundred_values() {
        let mut g = Gathered::default();
        for i in 0..150 {
            g.push(Metric::QueueLength, f64::from(i));
        }
        assert_eq!(g.values[&Metric::QueueLength].len(), MAX_VALUES);
        assert_eq!(g.dropped, 50);
    }
}
