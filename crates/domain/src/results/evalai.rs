//! The three files EvalAI receives: `results.json`, `stdout.txt` and `metadata.json`.
//!
//! `stdout.txt` is what participants read and compare across submissions, so its text is
//! kept exactly as the original pipeline printed it, typos included.

use std::fmt::Write as _;

use super::merge::Merged;
use super::Leaderboard;
use crate::results::py::{self, DumpOptions, Num, PyValue};

/// What the original generator printed when there was no merged file to copy.
pub const METADATA_MISSING_MESSAGE: &str =
    "Couldn't generate the metadata, missing input file 'agent_results.json'";

/// The EvalAI files of one merged result (or of none yet).
#[derive(Debug, Clone, PartialEq)]
pub struct EvalAiFiles {
    /// `results.json`: the `result` list posted to EvalAI.
    pub results: PyValue,
    /// `stdout.txt`: the participant's summary.
    pub stdout: String,
    /// `metadata.json`: a copy of the merged file; `None` before any merge.
    pub metadata: Option<String>,
    /// The leaderboard, which decides the JSON layout.
    pub leaderboard: Leaderboard,
}

impl EvalAiFiles {
    /// Builds the files from the merged result, or the placeholders when there is none yet.
    pub fn generate(merged: Option<&Merged>, leaderboard: Leaderboard) -> EvalAiFiles {
        EvalAiFiles {
            results: results(merged, leaderboard),
            stdout: match merged {
                Some(m) => stdout(m),
                None => INITIALIZING.to_owned(),
            },
            metadata: merged.map(Merged::to_json),
            leaderboard,
        }
    }

    /// `results.json` text, laid out as the original generator wrote it.
    pub fn results_json(&self) -> String {
        self.results.dumps(DumpOptions {
            indent: Some(4),
            sort_keys: self.leaderboard == Leaderboard::V1,
        })
    }

    /// The metrics as `(EvalAI label, value)`, for the EvalAI API and the database.
    pub fn accuracies(&self) -> Vec<(&str, Num)> {
        let PyValue::List(splits) = &self.results else {
            return vec![];
        };
        let Some(PyValue::Dict(acc)) = splits.first().and_then(|s| s.get("accuracies")) else {
            return vec![];
        };
        acc.iter()
            .filter_map(|(k, v)| match v {
                PyValue::Num(n) => Some((k.as_str(), *n)),
                _ => None,
            })
            .collect()
    }
}

const INITIALIZING: &str = "Initializing the submission, no data avaialable yet.\n\
More information will be found here once the submission starts running.\n";

fn results(merged: Option<&Merged>, lb: Leaderboard) -> PyValue {
    let global = merged.and_then(|m| m.global.as_ref());
    let accuracies = lb
        .metrics()
        .iter()
        .map(|m| {
            // EvalAI rejects strings: until global statistics exist every metric is int 0.
            let value = global
                .and_then(|g| g.metric(m.source))
                .unwrap_or(Num::Int(0));
            (m.label.to_owned(), PyValue::Num(value))
        })
        .collect();
    PyValue::List(vec![PyValue::Dict(vec![
        ("split".into(), "leaderboard".into()),
        ("show_to_participant".into(), true.into()),
        ("accuracies".into(), PyValue::Dict(accuracies)),
    ])])
}

fn pretty_sensor(id: &str) -> &str {
    match id {
        "carla_camera" => "RGB Camera",
        "carla_lidar" => "LIDAR",
        "carla_radar" => "Radar",
        "carla_gnss" => "GNSS",
        "carla_imu" => "IMU",
        "carla_opendrive_map" => "OpenDrive Map",
        "carla_speedometer" => "Speedometer",
        // Upstream raised KeyError here; an unknown id is shown as it is.
        other => other,
    }
}

fn stdout(m: &Merged) -> String {
    let mut out = String::with_capacity(256 + m.records.len() * 128);
    out.push_str(if m.global.is_some() {
        "Here is a summary of the submission's results\n\n"
    } else {
        "Here is a summary of the submission's current results\n\n"
    });
    out.push_str("General information:\n- Sensors:\n");
    let mut counts: Vec<(&str, usize)> = Vec::new();
    for s in &m.sensors {
        let pretty = pretty_sensor(s);
        match counts.iter_mut().find(|(p, _)| *p == pretty) {
            Some((_, n)) => *n += 1,
            None => counts.push((pretty, 1)),
        }
    }
    for (pretty, n) in counts {
        let _ = writeln!(out, "  - {n} {pretty}");
    }
    let (done, total) = m.progress;
    if done == total {
        let _ = writeln!(out, "- All {total} route have been completed");
    } else {
        let _ = writeln!(out, "- Completed {done} out of the {total} routes");
    }

    let (mut game, mut system) = (Num::Int(0), Num::Int(0));
    for r in &m.records {
        game = game + r.meta.duration_game;
        system = system + r.meta.duration_system;
    }
    let (ratio, fps) = if system.as_f64() == 0.0 {
        (0.0, 0.0)
    } else {
        let ratio = py::round(game.as_f64() / system.as_f64(), 4);
        (ratio, py::round(20.0 * ratio, 4))
    };
    let _ = writeln!(out, "- Submission ratio of {}x", py::float_repr(ratio));
    let _ = writeln!(out, "- Submission FPS of {}", py::float_repr(fps));

    if let Some(global) = &m.global {
        out.push_str("- Results:\n");
        for metric in m.leaderboard.metrics() {
            let value = global.metric(metric.source).unwrap_or(Num::Int(0));
            let _ = writeln!(out, "  - {}: {}", metric.label, value.py_str());
        }
    }
    out.push('\n');

    if !m.records.is_empty() {
        out.push_str("Glossary of each route:\n");
        for r in &m.records {
            let system = r.meta.duration_system.as_f64();
            let (ratio, fps) = if system == 0.0 {
                (Num::Int(0), Num::Int(0))
            } else {
                let ratio = r.meta.duration_game.as_f64() / system;
                (
                    Num::Float(py::round(ratio, 4)),
                    Num::Float(py::round(20.0 * ratio, 4)),
                )
            };
            let _ = write!(
                out,
                "\n- Index: {}\n  - Route ID: {}\n  - Status: {}\n  - Ratio: {}x\n  - FPS: {}\n",
                r.index,
                r.route_id.raw,
                r.status,
                ratio.py_str(),
                fps.py_str()
            );
        }
    }
    out
}
