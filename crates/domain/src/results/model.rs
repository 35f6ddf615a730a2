//! A worker's results (checkpoint) file, read as untrusted input and validated field by field.
//!
//! The file is written inside the participant's container, so anything may be in it. Parsing
//! is typed (serde, with the JSON path of a bad field kept), then every value is checked
//! against what the official evaluator can produce: finite, non-negative, bounded numbers
//! (scores within their ranges: 0-100, penalties 0-1),
//! route ids of the form `RouteScenario_<n>[_rep<r>]`, routes inside the worker's subset and
//! text without control characters (the text ends up in the participant-facing stdout).

use std::borrow::Cow;
use std::fmt;

use serde::de::{self, Deserializer, MapAccess, Visitor};
use serde::Deserialize;

use super::{Leaderboard, ResultsError};
use crate::results::py::Num;

/// The largest results file we read. The official evaluator writes a few KiB per route; a
/// 10,000-route worker file stays far below this.
pub const MAX_FILE_BYTES: usize = 64 * 1024 * 1024;

/// Upper bound for any number in a results file (metres, seconds, scores). It keeps sums of
/// hundreds of thousands of records exact in `i64` and finite in `f64`.
pub const MAX_NUMBER: f64 = 1e12;

/// How long an identifier-like string (sensor id, status) may be.
const MAX_LABEL_LEN: usize = 512;

/// A worker's file as read from disk or S3: absent ones are legitimate mid-run.
#[derive(Debug, Clone, PartialEq)]
pub enum WorkerFile {
    /// The file contributed nothing; the reason is kept for logs.
    Empty(EmptyReason),
    /// A validated results file.
    Present(ResultsFile),
}

/// Why a worker's file counts as empty, as the official merge treats it.
#[derive(Debug, Clone, PartialEq)]
pub enum EmptyReason {
    /// No file (the worker has not written one yet).
    Missing,
    /// Zero bytes, blanks only, or a JSON value that Python reads as falsy (`{}`, `null`, `[]`).
    Blank,
    /// Not JSON at all, or cut short: the evaluator rewrites the file after every route, so a
    /// read can race a write. The official pipeline counts it as empty; so do we, and the
    /// expected-routes check keeps such a result from ever being final.
    Unreadable(String),
}

impl fmt::Display for EmptyReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            EmptyReason::Missing => f.write_str("missing"),
            EmptyReason::Blank => f.write_str("empty"),
            EmptyReason::Unreadable(why) => write!(f, "unreadable ({why})"),
        }
    }
}

/// The routes a worker was assigned, `first..=last` by route number (`ROUTES_SUBSET` `a-b`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RouteSubset {
    /// First route number of the subset.
    pub first: u64,
    /// Last route number of the subset, inclusive.
    pub last: u64,
}

impl RouteSubset {
    /// Whether a route number belongs to the subset.
    pub fn contains(&self, route: u64) -> bool {
        (self.first..=self.last).contains(&route)
    }
}

impl fmt::Display for RouteSubset {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}-{}", self.first, self.last)
    }
}

impl std::str::FromStr for RouteSubset {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let parse = |t: &str| {
            if t.is_empty() || t.len() > 9 || !t.bytes().all(|b| b.is_ascii_digit()) {
                Err(format!(
                    "route subset `{s}` is not of the form `a-b` with a <= b"
                ))
            } else {
                t.parse::<u64>().map_err(|e| e.to_string())
            }
        };
        let (first, last) = match s.split_once('-') {
            Some((a, b)) => (parse(a)?, parse(b)?),
            None => {
                let a = parse(s)?;
                (a, a)
            }
        };
        if first > last {
            return Err(format!(
                "route subset `{s}` is not of the form `a-b` with a <= b"
            ));
        }
        Ok(RouteSubset { first, last })
    }
}

/// A parsed route id: `RouteScenario_<route>_rep<rep>` (Leaderboard 1.0 has no `_rep`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RouteId {
    /// The id as written.
    pub raw: String,
    /// Route number.
    pub route: u64,
    /// Repetition number; 0 when absent.
    pub rep: u64,
}

impl RouteId {
    /// Parses an id, accepting `_rep<r>` only where the leaderboard writes it.
    pub fn parse(raw: &str, leaderboard: Leaderboard) -> Option<RouteId> {
        let rest = raw.strip_prefix("RouteScenario_")?;
        let (route, rep) = match (leaderboard, rest.split_once("_rep")) {
            (Leaderboard::V2, Some((route, rep))) => (route, Some(rep)),
            (Leaderboard::V1, None) => (rest, None),
            _ => return None,
        };
        let number = |t: &str| -> Option<u64> {
            // Python's int() would also take `+1`, ` 1` or `1_0`; the evaluator never writes them.
            if t.is_empty() || t.len() > 12 || !t.bytes().all(|b| b.is_ascii_digit()) {
                return None;
            }
            t.parse().ok()
        };
        Some(RouteId {
            raw: raw.to_owned(),
            route: number(route)?,
            rep: match rep {
                Some(r) => number(r)?,
                None => 0,
            },
        })
    }

    /// The sort key of the official merge: (route number, repetition).
    pub fn key(&self) -> (u64, u64) {
        (self.route, self.rep)
    }
}

/// Per-route scores.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
pub struct Scores {
    /// Route completion, percent.
    pub score_route: Num,
    /// Infraction penalty factor.
    pub score_penalty: Num,
    /// Driving score.
    pub score_composed: Num,
}

/// Per-route meta data.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
pub struct Meta {
    /// Route length in metres.
    pub route_length: Num,
    /// Simulated seconds.
    pub duration_game: Num,
    /// Wall-clock seconds.
    pub duration_system: Num,
}

/// A route record's `status`: its exact text, which the files we write repeat byte for byte,
/// read once for what the official tooling reads in it (by substring, as Python's `in`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RouteStatus {
    text: String,
    kind: RouteKind,
    cause: Option<Cause>,
    names_agent: bool,
}

/// What a route's status says of how it ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RouteKind {
    /// `Perfect`: completed without infractions.
    Perfect,
    /// `Completed`.
    Completed,
    /// `Started`: the record was written before the route ended (missing data).
    Started,
    /// Any status naming `Failed` (`Failed - Agent crashed`, ...).
    Failed,
    /// A status the tooling gives no meaning to (kept, and counted as the others are).
    Other,
}

/// What ended a run, as a route's status names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Cause {
    /// `Simulation crashed`: the entry is `Crashed`.
    SimulationCrashed,
    /// `Agent's sensors were invalid`: the entry is `Rejected`.
    SensorsInvalid,
}

impl RouteStatus {
    /// The status as the worker wrote it.
    pub fn read(text: String) -> RouteStatus {
        let kind = match text.as_str() {
            _ if text.contains("Failed") => RouteKind::Failed,
            "Perfect" => RouteKind::Perfect,
            "Completed" => RouteKind::Completed,
            "Started" => RouteKind::Started,
            _ => RouteKind::Other,
        };
        let cause = if text.contains("Simulation crashed") {
            Some(Cause::SimulationCrashed)
        } else if text.contains("Agent's sensors were invalid") {
            Some(Cause::SensorsInvalid)
        } else {
            None
        };
        let names_agent = text.contains("Agent");
        RouteStatus {
            text,
            kind,
            cause,
            names_agent,
        }
    }

    /// The exact text.
    pub fn as_str(&self) -> &str {
        &self.text
    }

    /// How the route ended.
    pub fn kind(&self) -> RouteKind {
        self.kind
    }

    /// The crash or rejection it names, if any.
    pub fn cause(&self) -> Option<Cause> {
        self.cause
    }

    /// Whether it names the agent (Leaderboard 1.0's `"Agent" in status`).
    pub fn names_agent(&self) -> bool {
        self.names_agent
    }
}

impl std::fmt::Display for RouteStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.text)
    }
}

/// One route's record, validated.
#[derive(Debug, Clone, PartialEq)]
pub struct RouteRecord {
    /// The index the worker gave it (Leaderboard 1.0 reports it in `exceptions`).
    pub index: i64,
    /// The route id.
    pub route_id: RouteId,
    /// `Perfect`, `Completed`, `Started` or `Failed - <reason>`, read once.
    pub status: RouteStatus,
    /// Total infractions (Leaderboard 2.0 only).
    pub num_infractions: Option<Num>,
    /// Infraction messages per kind, in the file's order.
    pub infractions: Vec<(Kind, Vec<String>)>,
    /// Scores.
    pub scores: Scores,
    /// Length and durations.
    pub meta: Meta,
}

impl RouteRecord {
    /// The messages of one infraction kind; validation guarantees every kind is present.
    pub fn infraction(&self, kind: &str) -> &[String] {
        self.infraction_at(kind)
            .map_or(&[], |i| self.infractions[i].1.as_slice())
    }

    /// Where a kind is in [`infractions`](Self::infractions). Files list the kinds in the
    /// evaluator's order, so the canonical position is tried before a scan.
    fn infraction_at(&self, kind: &str) -> Option<usize> {
        let canonical = Leaderboard::V2
            .infraction_kinds()
            .iter()
            .position(|k| *k == kind)
            .filter(|&i| self.infractions.get(i).is_some_and(|(k, _)| k == kind));
        canonical.or_else(|| self.infractions.iter().position(|(k, _)| k == kind))
    }
}

/// A validated worker results file: what the merge needs of it.
#[derive(Debug, Clone, PartialEq)]
pub struct ResultsFile {
    /// Where it came from (file path or S3 key), for error messages.
    pub source: String,
    /// `_checkpoint.progress` as `[done, total]`.
    pub progress: (u64, u64),
    /// `_checkpoint.records`.
    pub records: Vec<RouteRecord>,
    /// Sensor type ids, in the agent's order.
    pub sensors: Vec<String>,
    /// Whether `_checkpoint.global_record` is non-empty (the worker finished its subset).
    pub has_global_record: bool,
    /// `entry_status` as the worker wrote it.
    pub entry_status: Option<String>,
}

// ---- raw serde shapes -------------------------------------------------------------------

#[derive(Deserialize)]
struct RawFile {
    #[serde(rename = "_checkpoint")]
    checkpoint: RawCheckpoint,
    sensors: Vec<String>,
    #[serde(default)]
    entry_status: Option<String>,
}

#[derive(Deserialize)]
struct RawCheckpoint {
    #[serde(default)]
    global_record: Option<OrderedMap<serde::de::IgnoredAny>>,
    progress: Vec<Num>,
    records: Vec<RawRecord>,
}

#[derive(Deserialize)]
struct RawRecord {
    index: Num,
    route_id: String,
    status: String,
    #[serde(default)]
    num_infractions: Option<Num>,
    infractions: OrderedMap<Vec<String>, KindKey>,
    scores: Scores,
    meta: Meta,
}

/// A JSON object kept in the file's key order.
struct OrderedMap<V, K = String>(Vec<(K, V)>);

impl<'de, V: Deserialize<'de>, K: Deserialize<'de> + PartialEq + fmt::Display> Deserialize<'de>
    for OrderedMap<V, K>
{
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct MapVisitor<V, K>(std::marker::PhantomData<(V, K)>);
        impl<'de, V: Deserialize<'de>, K: Deserialize<'de> + PartialEq + fmt::Display> Visitor<'de>
            for MapVisitor<V, K>
        {
            type Value = OrderedMap<V, K>;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("an object")
            }
            fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Self::Value, A::Error> {
                let mut out: Vec<(K, V)> = Vec::new();
                while let Some((k, v)) = map.next_entry::<K, V>()? {
                    if out.iter().any(|(seen, _)| *seen == k) {
                        return Err(de::Error::custom(format_args!("duplicate key `{k}`")));
                    }
                    out.push((k, v));
                }
                Ok(OrderedMap(out))
            }
        }
        d.deserialize_map(MapVisitor(std::marker::PhantomData))
    }
}

/// An infraction kind; the known ones are interned, so a 1,000-route merge does not allocate
/// 12,000 copies of the same dozen names.
pub type Kind = Cow<'static, str>;

struct KindSeed;

impl<'de> Visitor<'de> for KindSeed {
    type Value = Kind;
    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("an infraction kind")
    }
    fn visit_str<E: de::Error>(self, v: &str) -> Result<Kind, E> {
        let known = Leaderboard::V2.infraction_kinds().iter().find(|k| **k == v);
        Ok(match known {
            Some(k) => Cow::Borrowed(*k),
            None => Cow::Owned(v.to_owned()),
        })
    }
}

/// Deserializes a [`Kind`] through [`KindSeed`].
struct KindKey(Kind);

impl<'de> Deserialize<'de> for KindKey {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        d.deserialize_str(KindSeed).map(KindKey)
    }
}
impl PartialEq for KindKey {
    fn eq(&self, other: &Self) -> bool {
        self.0 == other.0
    }
}
impl fmt::Display for KindKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl<'de> Deserialize<'de> for Num {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct NumVisitor;
        impl Visitor<'_> for NumVisitor {
            type Value = Num;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a number")
            }
            fn visit_i64<E: de::Error>(self, v: i64) -> Result<Num, E> {
                Ok(Num::Int(v))
            }
            fn visit_u64<E: de::Error>(self, v: u64) -> Result<Num, E> {
                i64::try_from(v)
                    .map(Num::Int)
                    .map_err(|_| E::custom(format_args!("number `{v}` is out of range")))
            }
            fn visit_f64<E: de::Error>(self, v: f64) -> Result<Num, E> {
                Ok(Num::Float(v))
            }
        }
        d.deserialize_any(NumVisitor)
    }
}

// ---- parsing and validation ------------------------------------------------------------

/// Reads one worker's file. `bytes` is `None` when the file does not exist.
///
/// Missing, blank and unreadable files count as empty (see [`EmptyReason`]); a file that is
/// JSON but not a valid results file is an error naming the file and the field.
pub fn read_worker_file(
    source: &str,
    bytes: Option<&[u8]>,
    leaderboard: Leaderboard,
    subset: Option<RouteSubset>,
) -> Result<WorkerFile, ResultsError> {
    let Some(bytes) = bytes else {
        return Ok(WorkerFile::Empty(EmptyReason::Missing));
    };
    if bytes.len() > MAX_FILE_BYTES {
        return Err(ResultsError::TooLarge {
            file: source.to_owned(),
            size: bytes.len() as u64,
            limit: MAX_FILE_BYTES as u64,
        });
    }
    if bytes.iter().all(u8::is_ascii_whitespace) {
        return Ok(WorkerFile::Empty(EmptyReason::Blank));
    }
    // Python's `if not data: continue` skips falsy documents before looking inside them.
    match trimmed(bytes) {
        b"{}" | b"[]" | b"null" | b"\"\"" | b"false" | b"0" => {
            return Ok(WorkerFile::Empty(EmptyReason::Blank))
        }
        _ => {}
    }
    // NB: tracking the JSON path costs a third of the parse; only a failed parse pays for it.
    let raw: RawFile = match serde_json::from_slice(bytes) {
        Ok(raw) => raw,
        Err(_) => {
            let mut de = serde_json::Deserializer::from_slice(bytes);
            return match serde_path_to_error::deserialize::<_, RawFile>(&mut de) {
                Ok(_) => {
                    let err = de.end().err().unwrap_or_else(unreachable_parse);
                    classify_parse_error(source, bytes, ".", err)
                }
                Err(err) => {
                    let path = err.path().to_string();
                    classify_parse_error(source, bytes, &path, err.into_inner())
                }
            };
        }
    };
    validate(source, raw, leaderboard, subset).map(WorkerFile::Present)
}

/// One worker's file to read with [`read_worker_files`].
#[derive(Debug, Clone, Copy)]
pub struct WorkerInput<'a> {
    /// Where it came from, for error messages.
    pub source: &'a str,
    /// Its bytes; `None` when it does not exist.
    pub bytes: Option<&'a [u8]>,
    /// The routes the worker was assigned, when known.
    pub subset: Option<RouteSubset>,
}

/// Reads many workers' files, in parallel when they are large enough for it to pay off.
///
/// Results come back in input order, one per input.
pub fn read_worker_files(
    inputs: &[WorkerInput<'_>],
    leaderboard: Leaderboard,
) -> Vec<Result<WorkerFile, ResultsError>> {
    let read = |i: &WorkerInput<'_>| read_worker_file(i.source, i.bytes, leaderboard, i.subset);
    let total: usize = inputs.iter().map(|i| i.bytes.map_or(0, <[u8]>::len)).sum();
    let threads = std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .min(inputs.len());
    // NB: below ~256 KiB a thread costs more than it saves.
    if threads < 2 || total < 256 * 1024 {
        return inputs.iter().map(read).collect();
    }
    let chunk = inputs.len().div_ceil(threads);
    std::thread::scope(|scope| {
        let handles: Vec<_> = inputs
            .chunks(chunk)
            .map(|part| scope.spawn(move || part.iter().map(read).collect::<Vec<_>>()))
            .collect();
        handles
            .into_iter()
            .flat_map(|h| {
                h.join()
                    .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
            })
            .collect()
    })
}

/// `serde_json::from_slice` failed but the same parse with path tracking did not: cannot
/// happen, and is reported as an unreadable document rather than a panic.
fn unreachable_parse() -> serde_json::Error {
    serde::de::Error::custom("the document parses only with path tracking")
}

fn trimmed(bytes: &[u8]) -> &[u8] {
    let start = bytes
        .iter()
        .position(|b| !b.is_ascii_whitespace())
        .unwrap_or(bytes.len());
    let end = bytes
        .iter()
        .rposition(|b| !b.is_ascii_whitespace())
        .map_or(start, |e| e + 1);
    &bytes[start..end]
}

fn classify_parse_error(
    source: &str,
    bytes: &[u8],
    path: &str,
    inner: serde_json::Error,
) -> Result<WorkerFile, ResultsError> {
    match inner.classify() {
        serde_json::error::Category::Syntax | serde_json::error::Category::Eof => {
            // Python writes NaN/Infinity bare; they are not JSON and never a valid score.
            if let Some(literal) = non_finite_at(bytes, inner.line(), inner.column()) {
                return Err(ResultsError::NonFinite {
                    file: source.to_owned(),
                    literal,
                    line: inner.line(),
                    column: inner.column(),
                });
            }
            Ok(WorkerFile::Empty(EmptyReason::Unreadable(
                inner.to_string(),
            )))
        }
        serde_json::error::Category::Data | serde_json::error::Category::Io => {
            Err(ResultsError::Invalid {
                file: source.to_owned(),
                field: if path == "." {
                    "(document)".to_owned()
                } else {
                    path.to_owned()
                },
                problem: strip_position(&inner.to_string()),
            })
        }
    }
}

/// serde_json appends " at line L column C"; the field path says more.
fn strip_position(msg: &str) -> String {
    match msg.rfind(" at line ") {
        Some(i) => msg[..i].to_owned(),
        None => msg.to_owned(),
    }
}

fn non_finite_at(bytes: &[u8], line: usize, column: usize) -> Option<String> {
    let mut offset = 0usize;
    for _ in 1..line {
        offset += bytes[offset..].iter().position(|b| *b == b'\n')? + 1;
    }
    // serde_json reports the column of the offending character; look a few bytes around it.
    let at = offset + column.saturating_sub(1);
    let lo = at.saturating_sub(9);
    let window = bytes.get(lo..(at + 9).min(bytes.len()))?;
    let text = String::from_utf8_lossy(window);
    ["-Infinity", "Infinity", "NaN"]
        .into_iter()
        .find(|lit| text.contains(lit))
        .map(str::to_owned)
}

fn validate(
    source: &str,
    raw: RawFile,
    leaderboard: Leaderboard,
    subset: Option<RouteSubset>,
) -> Result<ResultsFile, ResultsError> {
    let progress = progress_of(source, &raw.checkpoint.progress)?;
    for (i, sensor) in raw.sensors.iter().enumerate() {
        check_label(sensor, true).map_err(|p| invalid(source, format!("sensors[{i}]"), p))?;
    }
    let records = raw
        .checkpoint
        .records
        .into_iter()
        .enumerate()
        .map(|(i, r)| validate_record(source, i, r, leaderboard, subset))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(ResultsFile {
        source: source.to_owned(),
        progress,
        records,
        sensors: raw.sensors,
        has_global_record: raw
            .checkpoint
            .global_record
            .is_some_and(|g| !g.0.is_empty()),
        entry_status: raw.entry_status,
    })
}

/// A field of a results file that breaks a rule.
fn invalid(source: &str, field: String, problem: String) -> ResultsError {
    ResultsError::Invalid {
        file: source.to_owned(),
        field,
        problem,
    }
}

/// `_checkpoint.progress`: `[done, total]`, or empty (nothing yet).
fn progress_of(source: &str, progress: &[Num]) -> Result<(u64, u64), ResultsError> {
    let at = |i: usize| {
        invalid(
            source,
            format!("_checkpoint.progress[{i}]"),
            "is not a non-negative integer".into(),
        )
    };
    match progress {
        [] => Ok((0, 0)),
        [done, total] => Ok((
            count(*done).ok_or_else(|| at(0))?,
            count(*total).ok_or_else(|| at(1))?,
        )),
        other => Err(invalid(
            source,
            "_checkpoint.progress".into(),
            format!("has {} elements, expected `[done, total]`", other.len()),
        )),
    }
}

/// Record `i` of a results file, checked against what the official evaluator can write for
/// a route of the worker's `subset`.
fn validate_record(
    source: &str,
    i: usize,
    r: RawRecord,
    leaderboard: Leaderboard,
    subset: Option<RouteSubset>,
) -> Result<RouteRecord, ResultsError> {
    let field = |name: &str| format!("_checkpoint.records[{i}].{name}");
    let bad = |name: &str, problem: String| invalid(source, field(name), problem);
    let route_id = RouteId::parse(&r.route_id, leaderboard).ok_or_else(|| {
        bad(
            "route_id",
            format!(
                "`{}` is not of the form `{}`",
                shown(&r.route_id),
                leaderboard.route_id_form()
            ),
        )
    })?;
    if let Some(subset) = subset.filter(|s| !s.contains(route_id.route)) {
        return Err(ResultsError::OutsideSubset {
            file: source.to_owned(),
            route_id: route_id.raw,
            subset,
        });
    }
    let index = match r.index {
        Num::Int(i) if (i as f64).abs() <= MAX_NUMBER => i,
        _ => return Err(bad("index", "is not an integer".into())),
    };
    check_label(&r.status, false).map_err(|p| bad("status", p))?;
    if let Some(n) = r.num_infractions {
        non_negative(n).map_err(|p| bad("num_infractions", p))?;
    }
    for kind in leaderboard.infraction_kinds() {
        if !r.infractions.0.iter().any(|(k, _)| k.0 == *kind) {
            return Err(bad("infractions", format!("has no `{kind}` list")));
        }
    }
    if let Some((kind, msg)) = r
        .infractions
        .0
        .iter()
        .find_map(|(k, msgs)| msgs.iter().find(|m| m.len() > 64 * 1024).map(|m| (k, m)))
    {
        return Err(bad(
            &format!("infractions.{kind}"),
            format!("holds a {}-byte message", msg.len()),
        ));
    }
    for (name, value) in [
        ("scores.score_route", r.scores.score_route),
        ("scores.score_penalty", r.scores.score_penalty),
        ("scores.score_composed", r.scores.score_composed),
        ("meta.route_length", r.meta.route_length),
        ("meta.duration_game", r.meta.duration_game),
        ("meta.duration_system", r.meta.duration_system),
    ] {
        non_negative(value).map_err(|p| bad(name, p))?;
    }
    // The official evaluator's ranges: completion and the composed score are percentages,
    // the penalty a product of factors in (0, 1]. A score outside them would be published
    // as the participant wrote it.
    for (name, value, max) in [
        ("scores.score_route", r.scores.score_route, 100.0),
        ("scores.score_composed", r.scores.score_composed, 100.0),
        ("scores.score_penalty", r.scores.score_penalty, 1.0),
    ] {
        within(value, max).map_err(|p| bad(name, p))?;
    }
    Ok(RouteRecord {
        index,
        route_id,
        status: RouteStatus::read(r.status),
        num_infractions: r.num_infractions,
        infractions: r.infractions.0.into_iter().map(|(k, v)| (k.0, v)).collect(),
        scores: r.scores,
        meta: r.meta,
    })
}

fn count(n: Num) -> Option<u64> {
    match n {
        Num::Int(i) if i >= 0 && (i as f64) <= MAX_NUMBER => Some(i as u64),
        _ => None,
    }
}

fn non_negative(n: Num) -> Result<(), String> {
    let v = n.as_f64();
    if !v.is_finite() {
        Err(format!("is `{}`, not a finite number", n.py_str()))
    } else if v < 0.0 {
        Err(format!("is negative (`{}`)", n.py_str()))
    } else if v > MAX_NUMBER {
        Err(format!(
            "is `{}`, over the limit of {MAX_NUMBER:e}",
            n.py_str()
        ))
    } else {
        Ok(())
    }
}

/// Untrusted text quoted in an error message: at most 100 characters, escaped.
fn shown(text: &str) -> String {
    let mut out: String = text
        .chars()
        .take(100)
        .collect::<String>()
        .escape_debug()
        .to_string();
    if text.chars().count() > 100 {
        out.push_str("...");
    }
    out
}

/// At most `max`, with room for the rounding of a float printed by Python.
fn within(n: Num, max: f64) -> Result<(), String> {
    if n.as_f64() > max + 1e-9 {
        Err(format!("is `{}`, over its maximum of {max}", n.py_str()))
    } else {
        Ok(())
    }
}

/// Text that reaches the participant's stdout must not forge lines or escape sequences.
fn check_label(s: &str, identifier: bool) -> Result<(), String> {
    if s.len() > MAX_LABEL_LEN {
        return Err(format!(
            "is {} bytes long, over the limit of {MAX_LABEL_LEN}",
            s.len()
        ));
    }
    if let Some(c) = s.chars().find(|c| c.is_control()) {
        return Err(format!("holds the control character {c:?}"));
    }
    if identifier && (s.is_empty() || s.chars().any(char::is_whitespace)) {
        return Err(format!("`{s}` is not a sensor type id"));
    }
    Ok(())
}
