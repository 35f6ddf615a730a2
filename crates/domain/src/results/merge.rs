//! The merge of the workers' files into one result, as the official `merge_statistics.py` does.
//!
//! Float operations follow the Python source operation by operation (same order, same
//! rounding points) so that every digit matches; the comments name the upstream step.

use super::model::{Cause, ResultsFile, RouteKind, RouteRecord};
use super::{Leaderboard, MetricSource, ResultsError};
use crate::results::py::{self, DumpOptions, JsonWriter, Num};

/// Digits of `round()` for scores (Leaderboard 2.0).
const ROUND_DIGITS_SCORE: usize = 6;
/// Digits of `round()` for infraction rates and standard deviations (Leaderboard 2.0).
const ROUND_DIGITS: usize = 3;

/// How to merge.
#[derive(Debug, Clone, Copy, Default)]
pub struct MergeOptions {
    /// Which evaluator wrote the files.
    pub leaderboard: Leaderboard,
    /// What the plan assigned. With it, a result with fewer records is partial and never
    /// final, whatever the workers' own progress says.
    pub expected: Option<Expected>,
}

/// What the plan assigned to the workers whose files are merged.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Expected {
    /// Routes over every worker.
    pub routes: u64,
    /// Times each route runs (Leaderboard 1.0: 5 by default, every one under the same id).
    pub repetitions: u64,
}

impl Expected {
    /// Records a complete result holds.
    pub fn records(self) -> u64 {
        self.routes.saturating_mul(self.repetitions)
    }
}

/// The merged result and what the caller needs to know about it.
#[derive(Debug, Clone, PartialEq)]
pub struct MergeOutcome {
    /// The merged document (`agent_results.json`).
    pub merged: Merged,
    /// Whether global statistics exist: every planned route has its record.
    pub complete: bool,
}

crate::status::words! {
    /// The merged file's `entry_status`, as the official tooling writes it.
    EntryStatus, "entry_status" {
        /// Not every route's record is in.
        Started => "Started",
        /// Every route ended (2.0), and nothing named the agent (1.0).
        Finished => "Finished",
        /// A route's simulation crashed.
        Crashed => "Crashed",
        /// The agent's sensors were invalid.
        Rejected => "Rejected",
        /// Validation found the file lacking.
        Invalid => "Invalid",
        /// 1.0: routes are missing.
        FinishedWithMissingData => "Finished with missing data",
        /// 1.0: a route's status names the agent.
        FinishedWithAgentErrors => "Finished with agent errors",
        /// 1.0: a fresh file, before its first route (`create_default_json_msg`).
        Blank => "",
    }
}

/// The merged document.
#[derive(Debug, Clone, PartialEq)]
pub struct Merged {
    /// Its format.
    pub leaderboard: Leaderboard,
    /// Records, sorted by (route, repetition) and re-indexed.
    pub records: Vec<RouteRecord>,
    /// `[records, total]`.
    pub progress: (u64, u64),
    /// Global statistics, when complete.
    pub global: Option<GlobalRecord>,
    /// `Started`, `Finished`, `Crashed`, `Rejected`, `Invalid` (1.0: `Finished with ...`).
    pub entry_status: EntryStatus,
    /// Whether the result may be published as a leaderboard entry.
    pub eligible: bool,
    /// The agent's sensors.
    pub sensors: Vec<String>,
    /// `values` as the evaluator writes them (strings).
    pub values: Vec<String>,
    /// `labels`, matching `values`.
    pub labels: Vec<&'static str>,
    /// Why validation set the status to `Invalid`, if it did.
    pub invalid_reason: Option<&'static str>,
}

/// Standard deviation of a score: a number, or the string `"NaN"` that Leaderboard 1.0
/// writes for a single route.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum StdDev {
    /// A number (`0` int for a single Leaderboard 2.0 route).
    Value(Num),
    /// The string `"NaN"`.
    NaNString,
}

/// Global statistics over every route.
#[derive(Debug, Clone, PartialEq)]
pub struct GlobalRecord {
    /// `Perfect`, `Completed`, `Failed` (or, copied from a route, any other status).
    pub status: String,
    /// Per-km infraction rates (off-road: km), in the evaluator's key order.
    pub infractions: Vec<(&'static str, Num)>,
    /// Mean scores: `score_composed`, `score_route`, `score_penalty`.
    pub scores: [(&'static str, Num); 3],
    /// Sample standard deviations of the scores, same keys.
    pub std_dev: [(&'static str, StdDev); 3],
    /// Sum of route lengths (m).
    pub total_length: Num,
    /// Sum of game durations (s).
    pub duration_game: Num,
    /// Sum of system durations (s).
    pub duration_system: Num,
    /// `(route_id, index, status)` of each failed route (1.0: of every route).
    pub exceptions: Vec<(String, i64, String)>,
}

impl GlobalRecord {
    /// A score by key.
    pub fn score(&self, key: &str) -> Option<Num> {
        self.scores.iter().find(|(k, _)| *k == key).map(|(_, v)| *v)
    }

    /// An infraction rate by key.
    pub fn infraction(&self, key: &str) -> Option<Num> {
        self.infractions
            .iter()
            .find(|(k, _)| *k == key)
            .map(|(_, v)| *v)
    }

    /// A metric's value.
    pub fn metric(&self, source: MetricSource) -> Option<Num> {
        match source {
            MetricSource::Score(k) => self.score(k),
            MetricSource::Infraction(k) => self.infraction(k),
        }
    }
}

/// Merges the workers' validated files.
///
/// Files that were missing or unreadable are simply not passed in, as the official merge
/// skips them; `opts.expected` is what keeps such a result from counting as final.
pub fn merge(files: Vec<ResultsFile>, opts: MergeOptions) -> Result<MergeOutcome, ResultsError> {
    let lb = opts.leaderboard;
    let Totals {
        records: total_records,
        progress: total_progress,
        sensors,
    } = file_totals(&files, opts.expected.map(Expected::records))?;

    // Step 2: concatenate and stably sort by (route, repetition).
    let mut records: Vec<RouteRecord> = Vec::with_capacity(total_records as usize);
    for file in files {
        records.extend(file.records);
    }
    records.sort_by_key(|r| r.route_id.key());

    let global_statistics = total_progress != 0 && total_records == total_progress;
    if global_statistics {
        // NB: the official 1.0 merge has neither check: its repetitions share one route id.
        if lb == Leaderboard::V2 {
            check_duplicates(&records)?;
            check_missing_data(&records)?;
        }
        if let Some(expected) = opts.expected {
            check_repetitions(&records, expected.repetitions)?;
        }
    }

    let mut merged = Merged {
        leaderboard: lb,
        records,
        progress: (total_records, total_progress),
        global: None,
        entry_status: EntryStatus::Started,
        eligible: false,
        sensors,
        values: Vec::new(),
        labels: Vec::new(),
        invalid_reason: None,
    };
    match lb {
        Leaderboard::V2 => {
            reindex(&mut merged.records);
            if global_statistics {
                global_v2(&mut merged, total_progress);
                validate_v2(&mut merged);
            }
        }
        Leaderboard::V1 => {
            // The 1.0 global record lists the workers' own indices; re-index afterwards.
            if global_statistics {
                global_v1(&mut merged, total_progress);
            }
            reindex(&mut merged.records);
        }
    }
    Ok(MergeOutcome {
        complete: merged.global.is_some(),
        merged,
    })
}

/// What step 1 of the merge finds over the workers' files.
struct Totals {
    /// Records of every file.
    records: u64,
    /// Records planned: the files' own totals, or the plan's when larger.
    progress: u64,
    /// The agent's sensors (every file that names them names the same).
    sensors: Vec<String>,
}

/// Step 1: route totals and the sensors check; `expected` records (the plan's) bound them.
fn file_totals(files: &[ResultsFile], expected: Option<u64>) -> Result<Totals, ResultsError> {
    let mut sensors: Option<&ResultsFile> = None;
    let mut total_records: u64 = 0;
    let mut total_progress: u64 = 0;
    for file in files {
        total_records += file.records.len() as u64;
        total_progress = total_progress.saturating_add(file.progress.1);
        if !file.sensors.is_empty() {
            match sensors {
                None => sensors = Some(file),
                Some(first) if first.sensors != file.sensors => {
                    return Err(ResultsError::SensorMismatch {
                        first: first.source.clone(),
                        file: file.source.clone(),
                    })
                }
                Some(_) => {}
            }
        }
    }
    if let Some(expected) = expected {
        if total_records > expected {
            return Err(ResultsError::UnexpectedRecords {
                found: total_records as usize,
                expected,
            });
        }
        // NB: a worker whose file is missing contributes no progress; the plan knows better.
        total_progress = total_progress.max(expected);
    }
    Ok(Totals {
        records: total_records,
        progress: total_progress,
        sensors: sensors.map(|f| f.sensors.clone()).unwrap_or_default(),
    })
}

fn reindex(records: &mut [RouteRecord]) {
    for (i, r) in records.iter_mut().enumerate() {
        r.index = i as i64;
    }
}

fn check_duplicates(records: &[RouteRecord]) -> Result<(), ResultsError> {
    // Sorted, so duplicates are neighbours; report the first in sorted order as upstream does.
    for pair in records.windows(2) {
        if pair[0].route_id.key() == pair[1].route_id.key() {
            return Err(ResultsError::DuplicateRoute {
                route_id: pair[0].route_id.raw.clone(),
            });
        }
    }
    Ok(())
}

/// Our completeness rule on top of the official merge: with as many records as planned,
/// every route must have exactly its planned repetitions (else some route ran too often).
fn check_repetitions(records: &[RouteRecord], repetitions: u64) -> Result<(), ResultsError> {
    // Sorted by (route, repetition): a route's records are neighbours.
    for group in records.chunk_by(|a, b| a.route_id.route == b.route_id.route) {
        if group.len() as u64 != repetitions {
            return Err(ResultsError::RepetitionMismatch {
                route_id: group[0].route_id.raw.clone(),
                found: group.len() as u64,
                expected: repetitions,
            });
        }
    }
    Ok(())
}

/// `check_missing_data`: the repetition count is learnt from the first reset of the
/// repetition number, and any jump of more than one (route, repetition) unit is a gap.
fn check_missing_data(records: &[RouteRecord]) -> Result<(), ResultsError> {
    let mut rep_num: i128 = 1;
    let mut prev_rep: i128 = 0;
    let mut prev_total: i128 = 0;
    let mut prev_id = "";
    for r in records {
        let (route, rep) = (r.route_id.route as i128, r.route_id.rep as i128);
        if rep < prev_rep {
            rep_num = prev_rep + 1;
        }
        let total = route * rep_num + rep;
        if total - prev_total > 1 {
            return Err(ResultsError::MissingRouteData {
                from: prev_id.to_owned(),
                to: r.route_id.raw.clone(),
            });
        }
        prev_rep = rep;
        prev_total = total;
        prev_id = &r.route_id.raw;
    }
    Ok(())
}

fn score_of(r: &RouteRecord, key: &str) -> Num {
    match key {
        "score_composed" => r.scores.score_composed,
        "score_route" => r.scores.score_route,
        _ => r.scores.score_penalty,
    }
}

const SCORE_KEYS: [&str; 3] = ["score_composed", "score_route", "score_penalty"];

/// Sum of the route lengths and durations, as `Num` so that all-int inputs stay int.
fn totals(records: &[RouteRecord]) -> (Num, Num, Num) {
    records
        .iter()
        .fold((Num::Int(0), Num::Int(0), Num::Int(0)), |(l, g, s), r| {
            (
                l + r.meta.route_length,
                g + r.meta.duration_game,
                s + r.meta.duration_system,
            )
        })
}

/// `StatisticsManager.compute_global_statistics` of Leaderboard 2.0.
fn global_v2(merged: &mut Merged, total_routes: u64) {
    let records = &merged.records;
    let n = total_routes as f64;

    // Means and the global result.
    let mut means = [0.0f64; 3];
    let mut failed = false;
    let mut first_imperfect: Option<&str> = None;
    let mut exceptions = Vec::new();
    for r in records {
        for (mean, key) in means.iter_mut().zip(SCORE_KEYS) {
            *mean += score_of(r, key).as_f64() / n;
        }
        match r.status.kind() {
            RouteKind::Failed => {
                let word = r.status.as_str().to_owned();
                exceptions.push((r.route_id.raw.clone(), r.index, word));
                failed = true;
            }
            RouteKind::Perfect => {}
            _ => _ = first_imperfect.get_or_insert(r.status.as_str()),
        }
    }
    // NB: `Failed` over everything, else the first route's word that is not `Perfect` (any
    // word, as the official tooling copies it).
    let status = match (failed, first_imperfect) {
        (true, _) => "Failed".to_owned(),
        (false, Some(word)) => word.to_owned(),
        (false, None) => "Perfect".to_owned(),
    };
    let means = means.map(|m| py::round(m, ROUND_DIGITS_SCORE));
    let (total_length, duration_game, duration_system) = totals(records);

    let std_dev = std_devs(records, means, total_routes);
    let infractions = infractions_per_km(records);

    let global = GlobalRecord {
        status,
        infractions,
        scores: [
            ("score_composed", Num::Float(means[0])),
            ("score_route", Num::Float(means[1])),
            ("score_penalty", Num::Float(means[2])),
        ],
        std_dev: [
            ("score_composed", std_dev[0]),
            ("score_route", std_dev[1]),
            ("score_penalty", std_dev[2]),
        ],
        total_length,
        duration_game,
        duration_system,
        exceptions,
    };

    let metrics = Leaderboard::V2.metrics();
    merged.values = metrics
        .iter()
        .map(|m| global.metric(m.source).map(Num::py_str).unwrap_or_default())
        .collect();
    merged.labels = metrics.iter().map(|m| m.file_label).collect();

    // Entry status: the last crashed or rejected route decides.
    let mut entry_status = EntryStatus::Finished;
    for r in records {
        match r.status.cause() {
            Some(Cause::SimulationCrashed) => entry_status = EntryStatus::Crashed,
            Some(Cause::SensorsInvalid) => entry_status = EntryStatus::Rejected,
            None => {}
        }
    }
    merged.global = Some(global);
    set_entry_status(merged, entry_status);
}

/// The scores' sample standard deviations around the rounded `means`, as the official 2.0
/// merge computes them (0 for a single route).
fn std_devs(records: &[RouteRecord], means: [f64; 3], total_routes: u64) -> [StdDev; 3] {
    if total_routes == 1 {
        return [StdDev::Value(Num::Int(0)); 3];
    }
    let mut sums = [0.0f64; 3];
    for r in records {
        for ((sum, key), mean) in sums.iter_mut().zip(SCORE_KEYS).zip(means) {
            let diff = score_of(r, key).as_f64() - mean;
            *sum += diff * diff;
        }
    }
    sums.map(|s| {
        StdDev::Value(Num::Float(py::round(
            (s / (total_routes - 1) as f64).sqrt(),
            ROUND_DIGITS,
        )))
    })
}

/// Infractions per km driven; off-road is the km driven off-road, not a rate.
fn infractions_per_km(records: &[RouteRecord]) -> Vec<(&'static str, Num)> {
    let kinds = Leaderboard::V2.infraction_kinds();
    let mut km_driven = 0.0f64;
    let mut sums: Vec<Num> = vec![Num::Int(0); kinds.len()];
    for r in records {
        km_driven += r.meta.route_length.as_f64() / 1000.0 * r.scores.score_route.as_f64() / 100.0;
        for (sum, kind) in sums.iter_mut().zip(kinds) {
            *sum = *sum + infraction_value(r, kind);
        }
    }
    let km_driven = km_driven.max(0.001);
    kinds
        .iter()
        .zip(sums)
        .map(|(kind, sum)| {
            let value = if *kind == "outside_route_lanes" {
                sum.as_f64()
            } else {
                sum.as_f64() / km_driven
            };
            (*kind, Num::Float(py::round(value, ROUND_DIGITS)))
        })
        .collect()
}

/// The metres off-road in a route's first off-road message (its 9th space-separated word),
/// in km; for every other kind, the number of messages.
fn infraction_value(r: &RouteRecord, kind: &str) -> Num {
    let messages = r.infraction(kind);
    if kind != "outside_route_lanes" {
        return Num::Int(messages.len() as i64);
    }
    let Some(first) = messages.first() else {
        return Num::Float(0.0);
    };
    // NB: upstream raises here on a malformed message; the messages are the evaluator's own
    // text, and a participant who forges one only loses the off-road metres it claimed.
    let metres = first
        .split(' ')
        .nth(8)
        .and_then(|w| w.trim().parse::<f64>().ok())
        .filter(|m| m.is_finite() && *m >= 0.0 && *m <= super::MAX_NUMBER)
        .unwrap_or(0.0);
    Num::Float(metres / 1000.0)
}

fn set_entry_status(merged: &mut Merged, status: EntryStatus) {
    merged.entry_status = status;
    merged.eligible = status == EntryStatus::Finished;
}

/// `validate_and_write_statistics(sensors_initialized=True, crashed=False)`.
fn validate_v2(merged: &mut Merged) {
    let reason = if merged.sensors.is_empty() {
        Some("Missing 'sensors' data")
    } else if merged.values.is_empty() {
        Some("Missing 'values' data")
    } else if merged.entry_status == EntryStatus::Started {
        Some("'entry_status' has the 'Started' value")
    } else if merged.progress.0 != merged.progress.1
        || merged.progress.0 != merged.records.len() as u64
    {
        Some("'progress' data doesn't match its expected value")
    } else if (merged.records.iter()).any(|r| r.status.kind() == RouteKind::Started) {
        Some("Found a route record with missing data")
    } else {
        None
    };
    if let Some(reason) = reason {
        merged.invalid_reason = Some(reason);
        set_entry_status(merged, EntryStatus::Invalid);
    }
}

/// `StatisticsManager.compute_global_statistics` and `save_global_record` of Leaderboard 1.0.
fn global_v1(merged: &mut Merged, total_routes: u64) {
    let records = &merged.records;
    let kinds = Leaderboard::V1.infraction_kinds();
    let mut sums = [Num::Int(0); 3];
    // A rate starts as the int 0 and becomes a float with the first route that counts.
    let mut rates: Vec<Num> = vec![Num::Int(0); kinds.len()];
    let mut exceptions = Vec::with_capacity(records.len());
    for r in records {
        for (sum, key) in sums.iter_mut().zip(SCORE_KEYS) {
            *sum = *sum + score_of(r, key);
        }
        // The global rate is the sum of each route's own rate over the km it drove. A route
        // that drove nothing is skipped (upstream: no 0.001 km floor in 1.0); a zero length
        // with a positive score, which upstream would divide by, is skipped too.
        let km = r.scores.score_route.as_f64() / 100.0 * r.meta.route_length.as_f64() / 1000.0;
        if r.scores.score_route.as_f64() > 0.0 && km > 0.0 {
            for (rate, kind) in rates.iter_mut().zip(kinds) {
                *rate = *rate + Num::Float(r.infraction(kind).len() as f64 / km);
            }
        }
        // NB: upstream compares with `is not 'Completed'`, which is always true for strings
        // read from JSON: every route is an "exception" and the status is always Failed.
        exceptions.push((
            r.route_id.raw.clone(),
            r.index,
            r.status.as_str().to_owned(),
        ));
    }
    let means = sums.map(|s| s.as_f64() / total_routes as f64);
    let std_dev = std_devs_v1(records, means, total_routes);
    let (total_length, duration_game, duration_system) = totals(records);
    let global = GlobalRecord {
        status: "Failed".to_owned(),
        infractions: kinds.iter().copied().zip(rates).collect(),
        scores: [
            ("score_composed", Num::Float(means[0])),
            ("score_route", Num::Float(means[1])),
            ("score_penalty", Num::Float(means[2])),
        ],
        std_dev: [
            ("score_composed", std_dev[0]),
            ("score_route", std_dev[1]),
            ("score_penalty", std_dev[2]),
        ],
        total_length,
        duration_game,
        duration_system,
        exceptions,
    };
    let metrics = Leaderboard::V1.metrics();
    merged.values = metrics
        .iter()
        .map(|m| {
            global
                .metric(m.source)
                .map(|v| py::format_fixed(v.as_f64(), 3))
                .unwrap_or_default()
        })
        .collect();
    merged.labels = metrics.iter().map(|m| m.file_label).collect();
    let (status, eligible) = if merged.progress.0 != merged.progress.1 {
        (EntryStatus::FinishedWithMissingData, false)
    } else if records.iter().any(|r| r.status.names_agent()) {
        (EntryStatus::FinishedWithAgentErrors, true)
    } else {
        (EntryStatus::Finished, true)
    };
    merged.global = Some(global);
    merged.entry_status = status;
    merged.eligible = eligible;
}

/// The scores' sample standard deviations around the unrounded `means`, as the official 1.0
/// merge computes them (`'NaN'` for a single route).
fn std_devs_v1(records: &[RouteRecord], means: [f64; 3], total_routes: u64) -> [StdDev; 3] {
    if total_routes == 1 {
        return [StdDev::NaNString; 3];
    }
    let mut acc = [0.0f64; 3];
    for r in records {
        for ((a, key), mean) in acc.iter_mut().zip(SCORE_KEYS).zip(means) {
            let diff = score_of(r, key).as_f64() - mean;
            *a += diff * diff;
        }
    }
    acc.map(|a| StdDev::Value(Num::Float((a / (total_routes - 1) as f64).sqrt())))
}

impl Merged {
    /// What a partial update is sent for, as text: the routes done, each record's route,
    /// status and scores, and the entry's status. A change of any other field (a duration, an
    /// infraction's wording) goes along with the next such change, not on its own: each
    /// update is an EvalAI request, and the participant's code can rewrite its files at will.
    pub fn progress_view(&self) -> String {
        let mut view = format!(
            "{:?} {} {:?}\n",
            self.progress, self.entry_status, self.eligible
        );
        for r in &self.records {
            view.push_str(&format!(
                "{:?} {} {:?}\n",
                r.route_id.key(),
                r.status,
                r.scores
            ));
        }
        view
    }

    /// How the evaluator of this leaderboard writes JSON files.
    pub fn dump_options(&self) -> DumpOptions {
        DumpOptions {
            indent: Some(4),
            sort_keys: self.leaderboard == Leaderboard::V1,
        }
    }

    /// `agent_results.json`, byte for byte as the official merge writes it.
    pub fn to_json(&self) -> String {
        // About 1.6 KiB per route in the official layout.
        let mut w = JsonWriter::new(self.dump_options(), 1024 + self.records.len() * 1800);
        let scores_key = match self.leaderboard {
            Leaderboard::V1 => "scores",
            Leaderboard::V2 => "scores_mean",
        };
        let global = match &self.global {
            Some(g) => global_field(g, scores_key),
            None => Field::Obj(vec![]),
        };
        let checkpoint = Field::Obj(vec![
            ("global_record", global),
            ("progress", Field::Progress(self.progress)),
            ("records", Field::Records(&self.records)),
        ]);
        write_field(
            &mut w,
            Field::Obj(vec![
                ("_checkpoint", checkpoint),
                ("entry_status", Field::Str(self.entry_status.as_str())),
                ("eligible", Field::Bool(self.eligible)),
                ("sensors", Field::Strs(&self.sensors)),
                ("values", Field::Strs(&self.values)),
                ("labels", Field::Labels(&self.labels)),
            ]),
        );
        w.finish()
    }
}

/// A piece of the merged document, written without building an intermediate tree.
enum Field<'a> {
    Num(Num),
    Str(&'a str),
    Bool(bool),
    Strs(&'a [String]),
    Labels(&'a [&'static str]),
    Progress((u64, u64)),
    Records(&'a [RouteRecord]),
    Infractions(&'a [(super::model::Kind, Vec<String>)]),
    Nums(&'a [(&'static str, Num)]),
    StdDevs(&'a [(&'static str, StdDev)]),
    Exceptions(&'a [(String, i64, String)]),
    Obj(Vec<(&'a str, Field<'a>)>),
}

fn global_field<'a>(g: &'a GlobalRecord, scores_key: &'a str) -> Field<'a> {
    Field::Obj(vec![
        ("index", Field::Num(Num::Int(-1))),
        ("route_id", Field::Num(Num::Int(-1))),
        ("status", Field::Str(&g.status)),
        ("infractions", Field::Nums(&g.infractions)),
        (scores_key, Field::Nums(&g.scores)),
        ("scores_std_dev", Field::StdDevs(&g.std_dev)),
        (
            "meta",
            Field::Obj(vec![
                ("total_length", Field::Num(g.total_length)),
                ("duration_game", Field::Num(g.duration_game)),
                ("duration_system", Field::Num(g.duration_system)),
                ("exceptions", Field::Exceptions(&g.exceptions)),
            ]),
        ),
    ])
}

fn record_field(r: &RouteRecord) -> Field<'_> {
    let mut fields = Vec::with_capacity(7);
    fields.push(("index", Field::Num(Num::Int(r.index))));
    fields.push(("route_id", Field::Str(&r.route_id.raw)));
    fields.push(("status", Field::Str(r.status.as_str())));
    if let Some(n) = r.num_infractions {
        fields.push(("num_infractions", Field::Num(n)));
    }
    fields.push(("infractions", Field::Infractions(&r.infractions)));
    fields.push((
        "scores",
        Field::Obj(vec![
            ("score_route", Field::Num(r.scores.score_route)),
            ("score_penalty", Field::Num(r.scores.score_penalty)),
            ("score_composed", Field::Num(r.scores.score_composed)),
        ]),
    ));
    fields.push((
        "meta",
        Field::Obj(vec![
            ("route_length", Field::Num(r.meta.route_length)),
            ("duration_game", Field::Num(r.meta.duration_game)),
            ("duration_system", Field::Num(r.meta.duration_system)),
        ]),
    ));
    Field::Obj(fields)
}

fn write_field(w: &mut JsonWriter, field: Field<'_>) {
    match field {
        Field::Num(n) => w.num(n),
        Field::Str(s) => w.str(s),
        Field::Bool(b) => w.bool(b),
        Field::Strs(items) => w.str_list(items),
        Field::Labels(items) => w.str_list(items),
        Field::Progress((done, total)) => {
            w.begin_list();
            w.num(Num::Int(done as i64));
            w.num(Num::Int(total as i64));
            w.end_list();
        }
        Field::Records(records) => {
            w.begin_list();
            for r in records {
                write_field(w, record_field(r));
            }
            w.end_list();
        }
        Field::Infractions(kinds) => w.object(
            kinds.iter().map(|(k, m)| (k.as_ref(), m)).collect(),
            |w, m| w.str_list(m),
        ),
        Field::Nums(nums) => write_field(
            w,
            Field::Obj(nums.iter().map(|(k, n)| (*k, Field::Num(*n))).collect()),
        ),
        Field::StdDevs(values) => {
            let fields = values
                .iter()
                .map(|(k, s)| {
                    let f = match s {
                        StdDev::Value(n) => Field::Num(*n),
                        StdDev::NaNString => Field::Str("NaN"),
                    };
                    (*k, f)
                })
                .collect();
            write_field(w, Field::Obj(fields))
        }
        Field::Exceptions(items) => {
            w.begin_list();
            for (id, index, status) in items {
                w.begin_list();
                w.str(id);
                w.num(Num::Int(*index));
                w.str(status);
                w.end_list();
            }
            w.end_list();
        }
        Field::Obj(fields) => w.object(fields, write_field),
    }
}
