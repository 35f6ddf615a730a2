//! The metrics a local run's functions wrote in CloudWatch's embedded metric format: each
//! document kept as written, in a file beside the pods' logs, and their totals for the summary.

use std::collections::{BTreeMap, BTreeSet};
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use cli::outln;
use serde::Serialize;
use serde_json::Value;

/// What the run's documents add up to.
#[derive(Debug, Clone, Default, Serialize)]
pub struct EmfReport {
    /// Where the documents are, one a line.
    pub file: PathBuf,
    /// Documents written (at most one per invocation).
    pub documents: u64,
    /// Their bytes (what CloudWatch Logs ingests).
    pub bytes: u64,
    /// Distinct metrics sent (name and dimension values): what CloudWatch bills by the hour.
    pub series: usize,
    /// Each metric's values summed, by name (every stage and leaderboard together).
    pub totals: BTreeMap<String, f64>,
    /// Each metric's values counted, by name.
    pub samples: BTreeMap<String, u64>,
    /// How runs ended (`Outcome` of `Ends`), counted.
    pub outcomes: BTreeMap<String, u64>,
}

/// Keeps the documents the functions of this process write.
#[derive(Debug)]
pub struct Collector {
    file: Mutex<std::fs::File>,
    report: Mutex<(EmfReport, BTreeSet<String>)>,
}

impl Collector {
    /// Sends this process's documents to a new file at `path`.
    pub fn install(path: &Path) -> anyhow::Result<Arc<Collector>> {
        let file = std::fs::File::create(path)?;
        let collector = Arc::new(Collector {
            file: Mutex::new(file),
            report: Mutex::new((
                EmfReport {
                    file: path.to_owned(),
                    ..EmfReport::default()
                },
                BTreeSet::new(),
            )),
        });
        let sink = collector.clone();
        if !lb_pipeline::metrics::write_to(Arc::new(move |line: &str| sink.keep(line))) {
            anyhow::bail!("this process's metrics already go elsewhere");
        }
        Ok(collector)
    }

    fn keep(&self, line: &str) {
        if let Ok(mut file) = self.file.lock() {
            let _ = writeln!(file, "{line}");
        }
        let Ok(doc) = serde_json::from_str::<Value>(line) else {
            return;
        };
        let Ok(mut guard) = self.report.lock() else {
            return;
        };
        let (report, series) = &mut *guard;
        report.documents += 1;
        report.bytes += line.len() as u64 + 1;
        for directive in doc["_aws"]["CloudWatchMetrics"]
            .as_array()
            .into_iter()
            .flatten()
        {
            let sets = directive["Dimensions"]
                .as_array()
                .cloned()
                .unwrap_or_default();
            for metric in directive["Metrics"].as_array().into_iter().flatten() {
                let Some(name) = metric["Name"].as_str() else {
                    continue;
                };
                let values = match &doc[name] {
                    Value::Array(values) => values.iter().filter_map(Value::as_f64).collect(),
                    one => one.as_f64().into_iter().collect::<Vec<_>>(),
                };
                *report.totals.entry(name.into()).or_default() += values.iter().sum::<f64>();
                *report.samples.entry(name.into()).or_default() += values.len() as u64;
                if name == "Ends" {
                    let outcome = doc["Outcome"].as_str().unwrap_or("?").to_owned();
                    *report.outcomes.entry(outcome).or_default() += values.len() as u64;
                }
                for set in &sets {
                    let keys = set.as_array().cloned().unwrap_or_default();
                    let dims: Vec<String> = keys
                        .iter()
                        .filter_map(Value::as_str)
                        .map(|k| format!("{k}={}", doc[k].as_str().unwrap_or_default()))
                        .collect();
                    series.insert(format!("{name} {}", dims.join(",")));
                }
            }
        }
        report.series = series.len();
    }

    /// What the documents so far add up to.
    pub fn report(&self) -> EmfReport {
        if let Ok(mut file) = self.file.lock() {
            let _ = file.flush();
        }
        self.report.lock().map(|g| g.0.clone()).unwrap_or_default()
    }
}

impl EmfReport {
    /// The summary's lines.
    pub fn print(&self) {
        let total = |name: &str| self.totals.get(name).copied().unwrap_or(0.0);
        let count = |name: &str| self.samples.get(name).copied().unwrap_or(0);
        outln!(
            "metrics        {} documents ({} bytes, {} metrics by dimensions) in {}",
            self.documents,
            self.bytes,
            self.series,
            self.file.display()
        );
        let outcomes: Vec<String> = self
            .outcomes
            .iter()
            .map(|(o, n)| format!("{n} {o}"))
            .collect();
        outln!(
            "               arrivals {}, admissions {}, starts {}, ends {} ({}), failures {}",
            total("Arrivals"),
            total("Admissions"),
            total("Starts"),
            total("Ends"),
            outcomes.join(", "),
            total("Failures"),
        );
        outln!(
            "               GPU-seconds {} on-demand, {} Spot, {} run again; ${:.2}; {} reclaims, {} pods failed, {} routes",
            total("GpuSecondsOnDemand"),
            total("GpuSecondsSpot"),
            total("GpuSecondsRunAgain"),
            total("GpuCost"),
            total("Reclaims"),
            total("PodFailures"),
            total("RoutesDone"),
        );
        outln!(
            "               EvalAI {} requests, {} throttled, {} over budget, {} waited; {} partial updates; {} invocations",
            total("EvalAiRequests"),
            total("EvalAiThrottled"),
            total("EvalAiOverBudget"),
            total("EvalAiBudgetWaits"),
            count("PartialUpdateDelay"),
            count("Duration"),
        );
    }
}
