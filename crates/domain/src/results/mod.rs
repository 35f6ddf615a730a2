//! The results engine: worker files in, the merged file and the three EvalAI files out.
//!
//! Parity with the official Leaderboard tooling is the contract here (see
//! `docs/reference/results.md`); the fixtures under `tests/fixtures/leaderboard-results/` are
//! the tests of record.

mod evalai;
mod merge;
mod model;
pub mod py;

pub use evalai::{EvalAiFiles, METADATA_MISSING_MESSAGE};
pub use merge::{
    merge, EntryStatus, Expected, GlobalRecord, MergeOptions, MergeOutcome, Merged, StdDev,
};
pub use model::{
    read_worker_file, read_worker_files, Cause, EmptyReason, Kind, Meta, ResultsFile, RouteId,
    RouteKind, RouteRecord, RouteStatus, RouteSubset, Scores, WorkerFile, WorkerInput,
    MAX_FILE_BYTES, MAX_NUMBER,
};

use std::fmt;

/// Which Leaderboard's evaluator wrote the files; the formats and rules differ. In JSON
/// (settings, payloads) it is its short name, `"1.0"` or `"2.0"`, and nothing else.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Default)]
pub enum Leaderboard {
    /// Leaderboard 1.0 (CARLA 0.9.10.1): 12 metrics, sorted keys, unrounded floats.
    V1,
    /// Leaderboard 2.0 (CARLA 0.9.14/15): 15 metrics, rounded scores, repetitions in ids.
    #[default]
    V2,
}

impl Leaderboard {
    /// The infraction kinds every record of this leaderboard carries.
    pub fn infraction_kinds(self) -> &'static [&'static str] {
        match self {
            Leaderboard::V1 => &[
                "collisions_layout",
                "collisions_pedestrian",
                "collisions_vehicle",
                "outside_route_lanes",
                "red_light",
                "route_dev",
                "stop_infraction",
                "route_timeout",
                "vehicle_blocked",
            ],
            Leaderboard::V2 => &[
                "collisions_layout",
                "collisions_pedestrian",
                "collisions_vehicle",
                "red_light",
                "stop_infraction",
                "outside_route_lanes",
                "min_speed_infractions",
                "yield_emergency_vehicle_infractions",
                "scenario_timeouts",
                "route_dev",
                "vehicle_blocked",
                "route_timeout",
            ],
        }
    }

    /// The metrics EvalAI shows, in leaderboard order.
    pub fn metrics(self) -> &'static [Metric] {
        match self {
            Leaderboard::V1 => &METRICS[..12],
            Leaderboard::V2 => &METRICS[..],
        }
    }

    /// How often the official evaluation runs each route (`--repetitions`): 1.0 five times,
    /// 2.0 once.
    pub fn repetitions(self) -> u32 {
        match self {
            Leaderboard::V1 => 5,
            Leaderboard::V2 => 1,
        }
    }

    /// How this leaderboard writes a route id, for error messages.
    pub fn route_id_form(self) -> &'static str {
        match self {
            Leaderboard::V1 => "RouteScenario_<n>",
            Leaderboard::V2 => "RouteScenario_<n>_rep<r>",
        }
    }

    /// The short name used on the command line and in configuration (`1.0`, `2.0`).
    pub fn as_str(self) -> &'static str {
        match self {
            Leaderboard::V1 => "1.0",
            Leaderboard::V2 => "2.0",
        }
    }
}

impl serde::Serialize for Leaderboard {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.as_str())
    }
}

impl<'de> serde::Deserialize<'de> for Leaderboard {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        // Only the short name: the command line's aliases (`FromStr`) are not a stored word.
        let word = String::deserialize(d)?;
        match word.parse::<Leaderboard>() {
            Ok(lb) if lb.as_str() == word => Ok(lb),
            _ => Err(serde::de::Error::custom(format!(
                "unknown leaderboard `{}`, expected `1.0` or `2.0`",
                word.escape_debug()
            ))),
        }
    }
}

impl fmt::Display for Leaderboard {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for Leaderboard {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "1.0" | "1" | "leaderboard-10" => Ok(Leaderboard::V1),
            "2.0" | "2" | "leaderboard-20" => Ok(Leaderboard::V2),
            other => Err(format!(
                "unknown leaderboard `{other}`, expected `1.0` or `2.0`"
            )),
        }
    }
}

/// Where a metric's value lives in the global record.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MetricSource {
    /// A key of the scores (`scores_mean` in 2.0, `scores` in 1.0).
    Score(&'static str),
    /// A key of the per-km infractions.
    Infraction(&'static str),
}

/// One leaderboard metric.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Metric {
    /// EvalAI's leaderboard label (the `accuracies` key).
    pub label: &'static str,
    /// The label in the results file's `labels` list.
    pub file_label: &'static str,
    /// The DynamoDB attribute that stores it.
    pub attribute: &'static str,
    /// Its place in the global record.
    pub source: MetricSource,
}

const fn metric(
    label: &'static str,
    file_label: &'static str,
    attribute: &'static str,
    source: MetricSource,
) -> Metric {
    Metric {
        label,
        file_label,
        attribute,
        source,
    }
}

use MetricSource::{Infraction as I, Score as S};

/// The 15 Leaderboard 2.0 metrics; Leaderboard 1.0 uses the first 12.
pub const METRICS: [Metric; 15] = [
    metric(
        "Driving score",
        "Avg. driving score",
        "driving_score",
        S("score_composed"),
    ),
    metric(
        "Route completion",
        "Avg. route completion",
        "route_completion",
        S("score_route"),
    ),
    metric(
        "Infraction penalty",
        "Avg. infraction penalty",
        "infraction_penalty",
        S("score_penalty"),
    ),
    metric(
        "Collisions pedestrians",
        "Collisions with pedestrians",
        "collisions_pedestrians",
        I("collisions_pedestrian"),
    ),
    metric(
        "Collisions vehicles",
        "Collisions with vehicles",
        "collisions_vehicles",
        I("collisions_vehicle"),
    ),
    metric(
        "Collisions layout",
        "Collisions with layout",
        "collisions_layout",
        I("collisions_layout"),
    ),
    metric(
        "Red light infractions",
        "Red lights infractions",
        "red_light_infractions",
        I("red_light"),
    ),
    metric(
        "Stop sign infractions",
        "Stop sign infractions",
        "stop_sign_infractions",
        I("stop_infraction"),
    ),
    metric(
        "Off-road infractions",
        "Off-road infractions",
        "off_road_infractions",
        I("outside_route_lanes"),
    ),
    metric(
        "Route deviations",
        "Route deviations",
        "route_deviations",
        I("route_dev"),
    ),
    metric(
        "Route timeouts",
        "Route timeouts",
        "route_timeouts",
        I("route_timeout"),
    ),
    metric(
        "Agent blocked",
        "Agent blocked",
        "agent_blocked",
        I("vehicle_blocked"),
    ),
    metric(
        "Yield emergency vehicle infractions",
        "Yield emergency vehicles infractions",
        "yield_emergency_vehicle_infractions",
        I("yield_emergency_vehicle_infractions"),
    ),
    metric(
        "Scenario timeouts",
        "Scenario timeouts",
        "scenario_timeouts",
        I("scenario_timeouts"),
    ),
    metric(
        "Min speed infractions",
        "Min speed infractions",
        "min_speed_infractions",
        I("min_speed_infractions"),
    ),
];

/// What can go wrong reading and merging results. Each variant has a stable [`name`](Self::name).
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ResultsError {
    /// The file exceeds [`MAX_FILE_BYTES`].
    #[error("`{file}` is {size} bytes, over the {limit}-byte limit for a results file")]
    TooLarge {
        /// The file.
        file: String,
        /// Its size.
        size: u64,
        /// The limit.
        limit: u64,
    },
    /// `NaN` or `Infinity` where a number belongs.
    #[error("`{file}` holds the non-finite number `{literal}` at line {line} column {column}")]
    NonFinite {
        /// The file.
        file: String,
        /// `NaN`, `Infinity` or `-Infinity`.
        literal: String,
        /// 1-based line.
        line: usize,
        /// 1-based column.
        column: usize,
    },
    /// A field has the wrong type or an impossible value.
    #[error("`{file}`: field `{field}` {problem}")]
    Invalid {
        /// The file.
        file: String,
        /// JSON path of the field.
        field: String,
        /// What is wrong with it.
        problem: String,
    },
    /// A record for a route the worker was not assigned.
    #[error("`{file}` holds route `{route_id}`, outside the worker's assigned routes `{subset}`")]
    OutsideSubset {
        /// The file.
        file: String,
        /// The route id.
        route_id: String,
        /// The worker's subset.
        subset: RouteSubset,
    },
    /// Two files disagree on the agent's sensors.
    #[error("Stopping. Found two files with different sensor configurations (`{file}` differs from `{first}`)")]
    SensorMismatch {
        /// The file whose sensors were taken first.
        first: String,
        /// The file that disagrees.
        file: String,
    },
    /// A route has more than one record.
    #[error("Stopping. Found that the route {route_id} has more than one record")]
    DuplicateRoute {
        /// The route id.
        route_id: String,
    },
    /// The route ids jump over a (route, repetition).
    #[error("Stopping. Missing some data as the ids jumped from {from} to {to}")]
    MissingRouteData {
        /// The id before the gap (empty when the first id is already past 0).
        from: String,
        /// The id after the gap.
        to: String,
    },
    /// More records than the plan assigned.
    #[error("found {found} route records but the plan assigned {expected}")]
    UnexpectedRecords {
        /// Records found.
        found: usize,
        /// Records planned.
        expected: u64,
    },
    /// As many records as planned, but a route has more or fewer than its repetitions.
    #[error("route `{route_id}` has {found} records but the plan runs it {expected} times")]
    RepetitionMismatch {
        /// The route id.
        route_id: String,
        /// Its records.
        found: u64,
        /// Repetitions planned.
        expected: u64,
    },
}

// Every name is a problem of a participant's own results (Finalize tells them so).
crate::error_names!(ResultsError {
    TooLarge => "ResultsTooLarge";
    NonFinite => "ResultsNonFinite";
    Invalid => "ResultsInvalid";
    OutsideSubset => "ResultsOutsideSubset";
    SensorMismatch => "SensorMismatch";
    DuplicateRoute => "DuplicateRoute";
    MissingRouteData => "MissingRouteData";
    UnexpectedRecords => "UnexpectedRecords";
    RepetitionMismatch => "RepetitionMismatch";
});
