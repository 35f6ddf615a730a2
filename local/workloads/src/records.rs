//! Route plans, record templates and the checkpoint file, in the official evaluator's format.
//!
//! Records are copies of real ones (fixtures embedded from `data/`, or any results file) with
//! the route id and index rewritten. Files are written through `lb-domain`'s Python-exact JSON
//! writer, and the final global record is `lb-domain`'s merge run on this worker's own file,
//! so it is what the official tooling computes.

use std::borrow::Cow;
use std::path::{Path, PathBuf};

use lb_domain::results::py::{self, Num};
use lb_domain::results::{
    self, EntryStatus, Leaderboard, MergeOptions, Merged, Meta, ResultsError, ResultsFile, RouteId,
    RouteKind, RouteRecord, RouteStatus, Scores, WorkerFile,
};

/// Fixture `a_4workers_20routes_finished`'s merged file: 20 Leaderboard 2.0 records.
const LB2_TEMPLATE: &str = include_str!("../data/lb2_records.json");
/// Fixture `k1_lb1_3workers_12routes`'s merged file: 12 Leaderboard 1.0 records.
const LB1_TEMPLATE: &str = include_str!("../data/lb1_records.json");

/// Status of a route whose simulator went away.
pub const SIMULATION_CRASHED: &str = "Failed - Simulation crashed";
/// Status of a route whose agent could not be set up.
pub const AGENT_SETUP_FAILED: &str = "Failed - Agent couldn't be set up";

/// What can go wrong with templates and checkpoint files. Each variant has a stable
/// [`name`](Self::name).
#[derive(Debug, thiserror::Error)]
pub enum RecordsError {
    /// The template file cannot be read.
    #[error("cannot read the records template `{path}`: {source}")]
    TemplateUnreadable {
        /// The file.
        path: String,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The template file is not a results file of this leaderboard.
    #[error("`{path}` is not a Leaderboard {leaderboard} results file: {source}")]
    TemplateInvalid {
        /// The file.
        path: String,
        /// The leaderboard it was read as.
        leaderboard: Leaderboard,
        /// Why.
        #[source]
        source: ResultsError,
    },
    /// The template file has no record a normal route could produce.
    #[error("`{path}` holds no route record usable as a template")]
    TemplateEmpty {
        /// The file.
        path: String,
    },
    /// A checkpoint or side file cannot be written.
    #[error("cannot write `{path}`: {source}")]
    Unwritable {
        /// The file.
        path: String,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The merge refused this worker's records.
    #[error("cannot compute the global statistics: {0}")]
    Global(#[source] ResultsError),
    /// A record index past the end of the records, as the 1.0 evaluator reports it.
    #[error("Error! No enough entries in the list (record {index}, {len} entries)")]
    NotEnoughEntries {
        /// The index written.
        index: usize,
        /// Records held.
        len: usize,
    },
}

impl RecordsError {
    /// The stable PascalCase name of the error.
    pub fn name(&self) -> &'static str {
        match self {
            RecordsError::TemplateUnreadable { .. } => "TemplateUnreadable",
            RecordsError::TemplateInvalid { .. } => "TemplateInvalid",
            RecordsError::TemplateEmpty { .. } => "TemplateEmpty",
            RecordsError::Unwritable { .. } => "CheckpointUnwritable",
            RecordsError::Global(_) => "GlobalStatistics",
            RecordsError::NotEnoughEntries { .. } => "NotEnoughEntries",
        }
    }
}

/// One route run of the worker's plan.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RouteConfig {
    /// Route number (the routes file's id).
    pub route: u64,
    /// Repetition number.
    pub rep: u64,
    /// Position in the plan, the record's `index`.
    pub index: usize,
    /// `RouteScenario_<n>`, the evaluator's `config.name`.
    pub name: String,
    /// The record's id: `RouteScenario_<n>_rep<r>` (Leaderboard 1.0: `RouteScenario_<n>`).
    pub route_id: String,
}

/// The evaluator's route list: every route of the subset, each repeated in turn (route-major,
/// as both evaluators' `RouteIndexer` builds it).
pub fn plan(routes: &[u64], repetitions: u64, leaderboard: Leaderboard) -> Vec<RouteConfig> {
    let mut out = Vec::with_capacity(routes.len() * repetitions as usize);
    for &route in routes {
        for rep in 0..repetitions {
            let name = format!("RouteScenario_{route}");
            let route_id = match leaderboard {
                Leaderboard::V1 => name.clone(),
                Leaderboard::V2 => format!("{name}_rep{rep}"),
            };
            out.push(RouteConfig {
                route,
                rep,
                index: out.len(),
                name,
                route_id,
            });
        }
    }
    out
}

/// Real records to copy from, and the agent's sensors that go with them.
#[derive(Debug, Clone)]
pub struct Template {
    records: Vec<RouteRecord>,
    sensors: Vec<String>,
}

impl Template {
    /// The records embedded in the crate for this leaderboard.
    pub fn builtin(leaderboard: Leaderboard) -> Result<Template, RecordsError> {
        let (name, text) = match leaderboard {
            Leaderboard::V1 => ("data/lb1_records.json", LB1_TEMPLATE),
            Leaderboard::V2 => ("data/lb2_records.json", LB2_TEMPLATE),
        };
        Template::from_bytes(name, text.as_bytes(), leaderboard)
    }

    /// The records of a results file (a worker's or a merged one).
    pub fn from_file(path: &Path, leaderboard: Leaderboard) -> Result<Template, RecordsError> {
        let bytes = std::fs::read(path).map_err(|source| RecordsError::TemplateUnreadable {
            path: path.display().to_string(),
            source,
        })?;
        Template::from_bytes(&path.display().to_string(), &bytes, leaderboard)
    }

    fn from_bytes(
        source: &str,
        bytes: &[u8],
        leaderboard: Leaderboard,
    ) -> Result<Template, RecordsError> {
        let file = match results::read_worker_file(source, Some(bytes), leaderboard, None) {
            Ok(WorkerFile::Present(file)) => file,
            Ok(WorkerFile::Empty(_)) => {
                return Err(RecordsError::TemplateEmpty {
                    path: source.to_owned(),
                })
            }
            Err(source_err) => {
                return Err(RecordsError::TemplateInvalid {
                    path: source.to_owned(),
                    leaderboard,
                    source: source_err,
                })
            }
        };
        // NB: these statuses come from how a run ended, not from driving a route; copying
        // them would make a clean run report a crash.
        let records: Vec<RouteRecord> = file
            .records
            .into_iter()
            .filter(|r| r.status.kind() != RouteKind::Started && r.status.cause().is_none())
            .collect();
        if records.is_empty() {
            return Err(RecordsError::TemplateEmpty {
                path: source.to_owned(),
            });
        }
        Ok(Template {
            records,
            sensors: file.sensors,
        })
    }

    /// The sensors the agent reports (may be empty).
    pub fn sensors(&self) -> &[String] {
        &self.sensors
    }

    /// The record of a route: template record `k mod len`, where `k` is the route's place in
    /// a plan that starts at route 0 (`route * repetitions + rep`), so that workers given
    /// a fixture's merged file reproduce the fixture's records.
    pub fn record(&self, cfg: &RouteConfig, repetitions: u64) -> RouteRecord {
        let k = cfg
            .route
            .saturating_mul(repetitions)
            .saturating_add(cfg.rep);
        let mut record = self.records[(k % self.records.len() as u64) as usize].clone();
        relabel(&mut record, cfg);
        record
    }
}

fn relabel(record: &mut RouteRecord, cfg: &RouteConfig) {
    record.index = cfg.index as i64;
    record.route_id = RouteId {
        raw: cfg.route_id.clone(),
        route: cfg.route,
        rep: cfg.rep,
    };
}

/// The record the 2.0 evaluator creates when a route starts (`create_route_data`).
pub fn started_record(cfg: &RouteConfig, leaderboard: Leaderboard) -> RouteRecord {
    let zero = Num::Int(0);
    let mut record = RouteRecord {
        index: 0,
        route_id: RouteId {
            raw: String::new(),
            route: 0,
            rep: 0,
        },
        status: RouteStatus::read("Started".to_owned()),
        num_infractions: (leaderboard == Leaderboard::V2).then_some(zero),
        infractions: leaderboard
            .infraction_kinds()
            .iter()
            .map(|k| (Cow::Borrowed(*k), Vec::new()))
            .collect(),
        scores: Scores {
            score_route: zero,
            score_penalty: zero,
            score_composed: zero,
        },
        meta: Meta {
            route_length: zero,
            duration_game: zero,
            duration_system: zero,
        },
    };
    relabel(&mut record, cfg);
    record
}

/// A route whose agent could not be set up, as fixture `l` shows it: no infractions,
/// completion 0, penalty 1.0, no time spent, the route length kept.
pub fn setup_failure(mut record: RouteRecord) -> RouteRecord {
    record.status = RouteStatus::read(AGENT_SETUP_FAILED.to_owned());
    for (_, messages) in &mut record.infractions {
        messages.clear();
    }
    if record.num_infractions.is_some() {
        record.num_infractions = Some(Num::Int(0));
    }
    record.scores = Scores {
        score_route: Num::Int(0),
        score_penalty: Num::Float(1.0),
        score_composed: Num::Float(0.0),
    };
    record.meta.duration_game = Num::Float(0.0);
    record.meta.duration_system = Num::Float(0.0);
    record
}

/// A route cut short by a simulator crash after `fraction` of it ran: its completion and
/// durations scale down, its status says so.
pub fn simulation_crashed(mut record: RouteRecord, fraction: f64) -> RouteRecord {
    let f = if fraction.is_finite() {
        fraction.clamp(0.0, 1.0)
    } else {
        0.0
    };
    record.status = RouteStatus::read(SIMULATION_CRASHED.to_owned());
    let route = py::round(record.scores.score_route.as_f64() * f, 2);
    record.scores.score_route = Num::Float(route);
    record.scores.score_composed =
        Num::Float(py::round(route * record.scores.score_penalty.as_f64(), 6));
    record.meta.duration_game = Num::Float(py::round(record.meta.duration_game.as_f64() * f, 3));
    record.meta.duration_system =
        Num::Float(py::round(record.meta.duration_system.as_f64() * f, 3));
    record
}

/// Statuses after which the 2.0 evaluator's resume runs the route again.
const RERUN_STATUSES: [&str; 3] = ["Failed", SIMULATION_CRASHED, "Failed - Agent crashed"];

/// A worker's checkpoint (`--checkpoint`), held in memory as the evaluator holds it.
#[derive(Debug, Clone)]
pub struct Checkpoint {
    leaderboard: Leaderboard,
    path: PathBuf,
    total: u64,
    /// `_checkpoint.progress[0]`: routes started so far.
    pub done: u64,
    /// The records, by index.
    pub records: Vec<RouteRecord>,
    /// The agent's sensors, once it has been set up.
    pub sensors: Vec<String>,
    /// `entry_status` (`""` in a fresh Leaderboard 1.0 file).
    pub entry_status: EntryStatus,
    /// Per record, whether this process produced it (rather than read it back on resume).
    fresh: Vec<bool>,
}

impl Checkpoint {
    /// A fresh checkpoint for `total` routes.
    pub fn new(leaderboard: Leaderboard, path: PathBuf, total: u64) -> Checkpoint {
        Checkpoint {
            leaderboard,
            path,
            total,
            done: 0,
            records: Vec::new(),
            sensors: Vec::new(),
            entry_status: match leaderboard {
                Leaderboard::V1 => EntryStatus::Blank,
                Leaderboard::V2 => EntryStatus::Started,
            },
            fresh: Vec::new(),
        }
    }

    /// The file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Reads the file for `--resume`: the state to continue from and the plan index to start
    /// at, or the message the evaluator prints when it refuses to resume (the caller then
    /// starts over).
    pub fn resume(
        leaderboard: Leaderboard,
        path: PathBuf,
        plan: &[RouteConfig],
    ) -> (Checkpoint, Result<usize, &'static str>) {
        let total = plan.len() as u64;
        let fresh = Checkpoint::new(leaderboard, path.clone(), total);
        // `fetch_dict`: a missing or unparsable file is "no data".
        let read = std::fs::read(&path).ok().map(|bytes| {
            results::read_worker_file(&path.display().to_string(), Some(&bytes), leaderboard, None)
        });
        let file = match read {
            None | Some(Ok(WorkerFile::Empty(_))) => None,
            Some(Ok(WorkerFile::Present(file))) => Some(Ok(file)),
            Some(Err(e)) => Some(Err(e)),
        };
        match leaderboard {
            Leaderboard::V2 => match file {
                None => (fresh, Err("Problem reading checkpoint. Found no data")),
                Some(Err(_)) => (
                    fresh,
                    Err("Problem reading checkpoint. Given checkpoint is malformed"),
                ),
                Some(Ok(file)) => resume_v2(fresh, file, plan),
            },
            Leaderboard::V1 => {
                let Some(Ok(file)) = file else {
                    return (fresh, Ok(0));
                };
                // 1.0 keeps the file as it is and takes `progress[0]` as the next route.
                let next = file.progress.0;
                let state = Checkpoint {
                    done: file.progress.0,
                    fresh: vec![false; file.records.len()],
                    records: file.records,
                    sensors: file.sensors,
                    entry_status: (file.entry_status.as_deref())
                        .and_then(|s| s.parse().ok())
                        .unwrap_or(EntryStatus::Blank),
                    ..fresh
                };
                if next <= total {
                    (state, Ok(next as usize))
                } else {
                    (
                        state,
                        Err("Problem reading checkpoint. Route id larger than maximum number of routes"),
                    )
                }
            }
        }
    }

    /// Stores a route's record at its index: appended, or replacing an earlier one (resume).
    pub fn set_record(&mut self, index: usize, record: RouteRecord) -> Result<(), RecordsError> {
        self.fresh.resize(self.records.len(), false);
        match index.cmp(&self.records.len()) {
            std::cmp::Ordering::Less => {
                self.records[index] = record;
                self.fresh[index] = true;
            }
            std::cmp::Ordering::Equal => {
                self.records.push(record);
                self.fresh.push(true);
            }
            std::cmp::Ordering::Greater => {
                return Err(RecordsError::NotEnoughEntries {
                    index,
                    len: self.records.len(),
                })
            }
        }
        Ok(())
    }

    /// The file's text as the evaluator writes it mid-run (no global record yet).
    pub fn to_json(&self) -> String {
        let merged = Merged {
            leaderboard: self.leaderboard,
            records: self.records.clone(),
            progress: (self.done, self.total),
            global: None,
            entry_status: self.entry_status,
            eligible: self.entry_status == EntryStatus::Finished,
            sensors: self.sensors.clone(),
            values: Vec::new(),
            labels: Vec::new(),
            invalid_reason: None,
        };
        let text = merged.to_json();
        if self.leaderboard == Leaderboard::V1 && self.entry_status == EntryStatus::Blank {
            // NB: 1.0's `create_default_json_msg` starts with `"eligible": ""`, which the
            // typed writer cannot express; sorted keys put it at one known place.
            return text.replacen("\n    \"eligible\": false,", "\n    \"eligible\": \"\",", 1);
        }
        text
    }

    /// Writes [`to_json`](Self::to_json) atomically.
    pub fn write(&self) -> Result<(), RecordsError> {
        write_atomic(&self.path, self.to_json().as_bytes())
    }

    /// The final file and its text: global statistics by `lb-domain`'s merge of this
    /// worker's records.
    ///
    /// `sensors_initialized` is the 2.0 evaluator's flag: when the agent never came up in
    /// this process, missing sensors do not make the result invalid (fixture `l`).
    pub fn finish(&self, sensors_initialized: bool) -> Result<(Merged, String), RecordsError> {
        // NB: the merge's cross-worker checks (duplicate ids, gaps between route numbers) are
        // not part of the evaluator's own statistics: a subset like `0-2,7` or 1.0's repeated
        // ids are fine here. Keys by position keep the records' order and pass those checks.
        let records = self
            .records
            .iter()
            .enumerate()
            .map(|(i, r)| {
                let mut r = r.clone();
                r.route_id.route = i as u64;
                r.route_id.rep = 0;
                r
            })
            .collect();
        let placeholder =
            self.leaderboard == Leaderboard::V2 && !sensors_initialized && self.sensors.is_empty();
        let file = ResultsFile {
            source: self.path.display().to_string(),
            progress: (self.records.len() as u64, self.total),
            records,
            sensors: if placeholder {
                vec!["sensors-not-initialized".to_owned()]
            } else {
                self.sensors.clone()
            },
            has_global_record: false,
            entry_status: None,
        };
        let outcome = results::merge(
            vec![file],
            MergeOptions {
                leaderboard: self.leaderboard,
                // NB: the evaluator knows its own records only; the plan is the backend's.
                expected: None,
            },
        )
        .map_err(RecordsError::Global)?;
        let mut merged = outcome.merged;
        merged.sensors = self.sensors.clone();
        for (m, original) in merged.records.iter_mut().zip(&self.records) {
            m.route_id = original.route_id.clone();
        }
        let mut no_exceptions = false;
        if let (Leaderboard::V1, Some(global)) = (self.leaderboard, merged.global.as_mut()) {
            // NB: 1.0's evaluator tests `status is not 'Completed'`, identity not equality:
            // statuses it set itself are the interned literal, those read back from the
            // file (resume) never are. The merge script lists every route instead.
            global.exceptions = self
                .records
                .iter()
                .enumerate()
                .filter(|(i, r)| {
                    !(self.fresh.get(*i) == Some(&true) && r.status.kind() == RouteKind::Completed)
                })
                .map(|(_, r)| (r.route_id.raw.clone(), r.index, r.status.to_string()))
                .collect();
            no_exceptions = global.exceptions.is_empty();
            global.status = if no_exceptions { "Completed" } else { "Failed" }.to_owned();
        }
        let mut text = merged.to_json();
        if no_exceptions {
            // 1.0 only creates `meta.exceptions` with the first failed route.
            text = text.replacen("\n                \"exceptions\": [],", "", 1);
        }
        Ok((merged, text))
    }
}

fn resume_v2(
    fresh: Checkpoint,
    file: ResultsFile,
    plan: &[RouteConfig],
) -> (Checkpoint, Result<usize, &'static str>) {
    let entry_status = file.entry_status.clone().unwrap_or_default();
    if entry_status.is_empty() {
        return (
            fresh,
            Err("Problem reading checkpoint. Given checkpoint is malformed"),
        );
    }
    if entry_status == "Invalid" {
        return (
            fresh,
            Err("Problem reading checkpoint. The 'entry_status' is 'Invalid'"),
        );
    }
    if file.progress.1 != plan.len() as u64 {
        return (
            fresh,
            Err("Problem reading checkpoint. Endpoint's amount of routes does not match the given one"),
        );
    }
    // `RouteIndexer.validate_and_resume`: walk the finished routes, stop at the first one
    // that failed in a way worth running again.
    let mut check = 0usize;
    let mut resume = usize::try_from(file.progress.0).unwrap_or(usize::MAX);
    while check < resume {
        let Some(record) = file.records.get(check) else {
            // Upstream's patch for a progress ahead of the records.
            resume = check.saturating_sub(1);
            break;
        };
        let Some(cfg) = plan.get(check) else {
            resume = check.saturating_sub(1);
            break;
        };
        if record.route_id.raw != cfg.route_id {
            return (
                fresh,
                Err("Problem reading checkpoint. Checkpoint routes don't match the current ones"),
            );
        }
        if RERUN_STATUSES.contains(&record.status.as_str()) {
            resume = check;
            break;
        }
        check += 1;
    }
    // "Something went wrong, repeat the last route."
    let index = if entry_status == "Crashed" {
        resume.saturating_sub(1)
    } else {
        resume
    };
    let state = Checkpoint {
        done: index as u64,
        fresh: vec![false; file.records.len()],
        records: file.records,
        ..fresh
    };
    (state, Ok(index))
}

/// Writes a file through a temporary sibling and a rename, so a reader (or a kill) never
/// sees half of it.
pub fn write_atomic(path: &Path, contents: &[u8]) -> Result<(), RecordsError> {
    let unwritable = |source| RecordsError::Unwritable {
        path: path.display().to_string(),
        source,
    };
    let name = path
        .file_name()
        .ok_or_else(|| unwritable(std::io::Error::other("the path names no file")))?;
    let tmp = path.with_file_name(format!(
        ".{}.tmp-{}",
        name.to_string_lossy(),
        std::process::id()
    ));
    let written = std::fs::write(&tmp, contents).and_then(|()| std::fs::rename(&tmp, path));
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    written.map_err(unwritable)
}

/// Event names and penalties of the infraction kinds, as the live results list them.
fn event_of(kind: &str) -> (&'static str, Option<f64>) {
    match kind {
        "collisions_layout" => ("COLLISION_STATIC", Some(0.65)),
        "collisions_pedestrian" => ("COLLISION_PEDESTRIAN", Some(0.5)),
        "collisions_vehicle" => ("COLLISION_VEHICLE", Some(0.6)),
        "red_light" => ("TRAFFIC_LIGHT_INFRACTION", Some(0.7)),
        "stop_infraction" => ("STOP_INFRACTION", Some(0.8)),
        "scenario_timeouts" => ("SCENARIO_TIMEOUT", Some(0.7)),
        "yield_emergency_vehicle_infractions" => ("YIELD_TO_EMERGENCY_VEHICLE", Some(0.7)),
        "outside_route_lanes" => ("OUTSIDE_ROUTE_LANES_INFRACTION", None),
        "min_speed_infractions" => ("MIN_SPEED_INFRACTION", None),
        "route_dev" => ("ROUTE_DEVIATION", None),
        "vehicle_blocked" => ("VEHICLE_BLOCKED", None),
        _ => ("ROUTE_TIMEOUT", None),
    }
}

/// The 2.0 evaluator's live results text (`--debug-checkpoint`) for a route `fraction` done.
pub fn live_results(record: &RouteRecord, fraction: f64) -> String {
    let f = fraction.clamp(0.0, 1.0);
    let route = record.scores.score_route.as_f64() * f;
    let penalty = record.scores.score_penalty.as_f64();
    // Infractions seen so far: the route's, in proportion to how far it got.
    let all: Vec<(&str, &String)> = record
        .infractions
        .iter()
        .flat_map(|(k, msgs)| msgs.iter().map(move |m| (k.as_ref(), m)))
        .collect();
    let seen = ((all.len() as f64) * f).floor() as usize;
    let mut text = format!(
        "Route id: {}\n\n\
         Scores:\n\
         \x20   Driving score:      {:.3}\n\
         \x20   Route completion:   {:.3}\n\
         \x20   Infraction penalty: {:.3}\n\n\
         \x20   Route length:    {:.3}\n\
         \x20   Game duration:   {:.3}\n\
         \x20   System duration: {:.3}\n\n\
         Ego:\n\
         \x20   Throttle:           {:.3}\n\
         \x20   Brake:              {:.3}\n\
         \x20   Steer:              {:.3}\n\n\
         \x20   Speed:           {:.3} km/h\n\n\
         \x20   Location:           ({:.3} {:.3} {:.3})\n\n\
         Total infractions: {}\n\
         Last 5 infractions:\n",
        record.route_id.raw,
        route * penalty,
        route,
        penalty,
        record.meta.route_length.as_f64(),
        record.meta.duration_game.as_f64() * f,
        record.meta.duration_system.as_f64() * f,
        0.75,
        0.0,
        0.02 * (f * 10.0).sin(),
        30.0 + 5.0 * (f * 7.0).cos(),
        record.meta.route_length.as_f64() * f,
        0.0,
        0.0,
        seen,
    );
    for (kind, _) in all[..seen].iter().rev().take(5) {
        let (event, penalty) = event_of(kind);
        match penalty {
            Some(p) => text.push_str(&format!("    {event} (penalty: {p})\n")),
            None => text.push_str(&format!("    {event}\n")),
        }
    }
    text
}

/// The invalid checkpoint `FAKE_EVALUATOR_GARBAGE` asks for, made from the valid final text.
pub fn garbage(kind: crate::faults::GarbageKind, valid: &str) -> String {
    use crate::faults::GarbageKind;
    match kind {
        GarbageKind::Truncated => {
            let mut cut = valid.len() / 2;
            while !valid.is_char_boundary(cut) {
                cut -= 1;
            }
            valid[..cut].to_owned()
        }
        GarbageKind::Schema => {
            "{\n    \"_checkpoint\": {\n        \"progress\": \"done\",\n        \"records\": \"all of them\"\n    },\n    \"entry_status\": \"Finished\"\n}".to_owned()
        }
        GarbageKind::NaN => {
            let key = "\"score_composed\": ";
            match valid.find(key) {
                Some(at) => {
                    let start = at + key.len();
                    let end = valid[start..]
                        .find([',', '\n'])
                        .map_or(valid.len(), |e| start + e);
                    format!("{}NaN{}", &valid[..start], &valid[end..])
                }
                None => format!("{valid}NaN"),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lb_domain::testutil::results_fixtures_dir;

    fn fixture(path: &str) -> String {
        std::fs::read_to_string(results_fixtures_dir().join(path)).unwrap()
    }

    fn read(text: &str, lb: Leaderboard) -> ResultsFile {
        match results::read_worker_file("t", Some(text.as_bytes()), lb, None).unwrap() {
            WorkerFile::Present(f) => f,
            WorkerFile::Empty(r) => panic!("empty: {r}"),
        }
    }

    /// A worker file as the evaluator would rebuild it from its own records.
    fn rebuilt(text: &str, lb: Leaderboard, sensors_initialized: bool) -> String {
        let file = read(text, lb);
        let cp = Checkpoint {
            leaderboard: lb,
            path: PathBuf::from("worker.json"),
            total: file.progress.1,
            done: file.progress.0,
            fresh: vec![true; file.records.len()],
            records: file.records,
            sensors: file.sensors,
            entry_status: EntryStatus::Started,
        };
        cp.finish(sensors_initialized).unwrap().1
    }

    #[test]
    fn the_embedded_templates_are_real_results_files() {
        let t = Template::builtin(Leaderboard::V2).unwrap();
        assert_eq!(t.records.len(), 20);
        assert_eq!(t.sensors().len(), 6);
        assert_eq!(
            Template::builtin(Leaderboard::V1).unwrap().records.len(),
            12
        );
    }

    #[test]
    fn the_merge_on_a_single_worker_file_rebuilds_the_fixtures_worker_files_byte_for_byte() {
        for path in [
            "a_4workers_20routes_finished/input/worker1.json",
            "a_4workers_20routes_finished/input/worker4.json",
            "d_repetitions_2routes_3reps/input/worker2.json",
            "i_single_route/input/worker1.json",
        ] {
            let text = fixture(path);
            assert_eq!(rebuilt(&text, Leaderboard::V2, true), text, "{path}");
        }
        for path in [
            "k1_lb1_3workers_12routes/input/worker1.json",
            "k1_lb1_3workers_12routes/input/worker3.json",
        ] {
            let text = fixture(path);
            assert_eq!(rebuilt(&text, Leaderboard::V1, true), text, "{path}");
        }
        // The agent never came up: no sensors, yet the worker says Finished.
        let text = fixture("l_agent_setup_failure_invalid/input/worker1.json");
        assert_eq!(rebuilt(&text, Leaderboard::V2, false), text);
    }

    #[test]
    fn a_mid_run_file_matches_the_fixtures_layout() {
        let text = fixture("b_partial_progress_midrun/input/worker2.json");
        let file = read(&text, Leaderboard::V2);
        let cp = Checkpoint {
            leaderboard: Leaderboard::V2,
            path: PathBuf::from("w.json"),
            total: file.progress.1,
            done: file.progress.0,
            fresh: vec![false; file.records.len()],
            records: file.records,
            sensors: file.sensors,
            entry_status: EntryStatus::Started,
        };
        assert_eq!(cp.to_json(), text);
        let text = fixture("c1_simulation_crash_last_route/input/worker3.json");
        let file = read(&text, Leaderboard::V2);
        let cp = Checkpoint {
            leaderboard: Leaderboard::V2,
            path: PathBuf::from("w.json"),
            total: file.progress.1,
            done: file.progress.0,
            fresh: vec![false; file.records.len()],
            records: file.records,
            sensors: file.sensors,
            entry_status: EntryStatus::Crashed,
        };
        assert_eq!(cp.to_json(), text);
    }

    #[test]
    fn a_setup_failure_record_looks_like_fixture_l() {
        let l = read(
            &fixture("l_agent_setup_failure_invalid/input/worker1.json"),
            Leaderboard::V2,
        );
        let t = Template::builtin(Leaderboard::V2).unwrap();
        let cfg = &plan(&[0], 1, Leaderboard::V2)[0];
        let mut got = setup_failure(t.record(cfg, 1));
        got.meta.route_length = l.records[0].meta.route_length;
        assert_eq!(got, l.records[0]);
    }

    #[test]
    fn resume_restarts_at_the_first_crashed_route_and_once_more_before_a_crash() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cp.json");
        let p = plan(&[0, 1, 2, 3], 1, Leaderboard::V2);
        let t = Template::builtin(Leaderboard::V2).unwrap();
        let mut cp = Checkpoint::new(Leaderboard::V2, path.clone(), 4);
        for cfg in &p[..2] {
            let mut r = t.record(cfg, 1);
            r.status = RouteStatus::read("Completed".into());
            cp.set_record(cfg.index, r).unwrap();
        }
        cp.done = 2;
        cp.write().unwrap();
        let (state, at) = Checkpoint::resume(Leaderboard::V2, path.clone(), &p);
        assert_eq!(at, Ok(2));
        assert_eq!(state.records.len(), 2);

        let mut r = t.record(&p[2], 1);
        r.status = RouteStatus::read(SIMULATION_CRASHED.into());
        cp.set_record(2, r).unwrap();
        cp.done = 3;
        cp.entry_status = EntryStatus::Crashed;
        cp.write().unwrap();
        let (_, at) = Checkpoint::resume(Leaderboard::V2, path.clone(), &p);
        assert_eq!(at, Ok(1), "upstream repeats the route before a crash");

        let (_, at) = Checkpoint::resume(Leaderboard::V2, path.clone(), &p[..3]);
        assert!(at.unwrap_err().contains("amount of routes"));
        std::fs::write(&path, "{\"_checkpoint\": ").unwrap();
        let (_, at) = Checkpoint::resume(Leaderboard::V2, path, &p);
        assert!(at.unwrap_err().contains("Found no data"));
    }

    #[test]
    fn garbage_is_garbage_to_the_domain_reader() {
        use crate::faults::GarbageKind;
        let valid = fixture("a_4workers_20routes_finished/input/worker1.json");
        let truncated = garbage(GarbageKind::Truncated, &valid);
        assert!(matches!(
            results::read_worker_file("g", Some(truncated.as_bytes()), Leaderboard::V2, None),
            Ok(WorkerFile::Empty(_))
        ));
        for kind in [GarbageKind::Schema, GarbageKind::NaN] {
            let text = garbage(kind, &valid);
            assert!(
                results::read_worker_file("g", Some(text.as_bytes()), Leaderboard::V2, None)
                    .is_err(),
                "{kind:?}"
            );
        }
    }
}
