//! What operators can audit of a result: the CARLA recordings of its routes, judged by their
//! place, their header and their size.
//!
//! The evaluator runs in the participant's process and writes the scores; the CARLA server
//! (the organizers' image) writes a recording of each route, which replays the route as the
//! simulator ran it. The recordings folder of a pair (`recorder/pair<ID>`) is mounted only in
//! that pair's simulator container, so the participant's container can neither write nor
//! replace a recording. What a passing audit proves, and what it does not, is in
//! `docs/security.md` ("Recordings").

use std::collections::HashMap;

use crate::job::protocol::{recorder_dir, recording_of, PairId, RECORDER_DIR};

/// The first bytes of every CARLA recording (`CarlaRecorderInfo`): format version 1 as a
/// little-endian `u16`, then the magic as an `FString` (a `u16` length, 14, and its bytes).
pub const MAGIC: &[u8] = b"\x01\x00\x0e\x00CARLA_RECORDER";

/// Bytes read from the head of each recording: the magic, the date (`i64`), the map's name
/// (a `u16` length and its bytes).
pub const HEAD_BYTES: u64 = 256;

/// Frames per simulated second: the Leaderboard runs CARLA synchronously at 20 Hz.
const FRAMES_PER_SECOND: f64 = 20.0;

/// The least bytes CARLA writes per frame: a `FrameStart` packet (id `u8`, size `u32`, the
/// frame's id `u64`, its duration and the elapsed time as `f64`s: 29 bytes) and a `FrameEnd`
/// packet (id and size: 5 bytes). Positions, events and states only add to it.
const MIN_FRAME_BYTES: f64 = 34.0;

/// The share of a route's simulated time its recording must at least hold: the recorder
/// starts before the scenario's clock and stops after it, so a whole recording holds more.
const MIN_SHARE: f64 = 0.9;

/// How far before the Jobs' creation a recording's date may be: clocks of different
/// machines.
const CLOCK_SKEW_SECONDS: i64 = 3600;

/// How long after the Jobs' creation a recording may be dated: an evaluation ends by its
/// hard limit; this is only a bound on nonsense.
const LATEST_SECONDS: i64 = 30 * 86_400;

/// The longest map name a header may give (`/Game/Carla/Maps/Town12/Town12` is 30 bytes).
const MAX_MAP_NAME: usize = 200;

/// The most failing routes named in the record.
const NAMED: usize = 5;

/// The fastest a route's completed part is taken to be driven, in metres per simulated
/// second (144 km/h: above what the Leaderboard's vehicles reach in its towns), so the time
/// it gives is a floor no honest record is below.
pub const TOP_SPEED: f64 = 40.0;

/// A merged record as the audit needs it.
#[derive(Debug, Clone, PartialEq)]
pub struct Route {
    /// The pair whose subset holds the route (the only one whose simulator ran it).
    pub pair: PairId,
    /// Its route id (`RouteScenario_3_rep0`, or `RouteScenario_3` in Leaderboard 1.0).
    pub id: String,
    /// Its route number in the routes file.
    pub route: u64,
    /// Its simulated seconds (`meta.duration_game`).
    pub game_seconds: f64,
    /// Its route completion, percent (`scores.score_route`).
    pub completion: f64,
    /// Whether it adds anything to the result (a route completion or driving score above 0):
    /// a route that scores nothing needs no proof.
    pub scores: bool,
}

/// A recording a route needs.
#[derive(Debug, Clone, PartialEq)]
pub struct Expected {
    /// The pair whose folder must hold it.
    pub pair: PairId,
    /// Its file stem: the route id with its repetition.
    pub stem: String,
    /// Its route's simulated seconds, as its record claims them.
    pub game_seconds: f64,
    /// The least simulated seconds its completed part takes at [`TOP_SPEED`], from the
    /// organisers' length of its route (0 when none is given).
    pub floor_seconds: f64,
}

impl Expected {
    /// The submission-relative key it must have (`recorder/pair<ID>/<stem>.log`).
    pub fn key(&self) -> String {
        format!("{}/{}.log", recorder_dir(self.pair), self.stem)
    }

    /// The simulated seconds its recording must cover: what its record claims, and never
    /// less than its floor (a participant's record cannot shrink what is asked of CARLA).
    pub fn seconds(&self) -> f64 {
        self.game_seconds.max(self.floor_seconds).max(0.0)
    }

    /// The least size consistent with its route's simulated time.
    pub fn min_bytes(&self) -> u64 {
        let frames = self.seconds() * FRAMES_PER_SECOND * MIN_SHARE;
        (frames * MIN_FRAME_BYTES) as u64 + MAGIC.len() as u64
    }
}

/// The recordings the scoring routes need: `RouteScenario_3_rep1` is recorded as
/// `RouteScenario_3_rep1.log`; a route id without a repetition (Leaderboard 1.0) is recorded
/// once per record, as repetitions `_rep0`, `_rep1`, ... in the records' order. `lengths`
/// are the organisers' route lengths in metres by route number (empty: no floor).
pub fn expected(routes: &[Route], lengths: &[u32]) -> Vec<Expected> {
    let mut seen: HashMap<&str, u32> = HashMap::new();
    routes
        .iter()
        .filter_map(|route| {
            let stem = if has_repetition(&route.id) {
                route.id.clone()
            } else {
                let n = seen.entry(&route.id).or_default();
                let name = format!("{}_rep{n}", route.id);
                *n += 1;
                name
            };
            let at = usize::try_from(route.route).ok();
            let length = at.and_then(|at| lengths.get(at)).copied().unwrap_or(0);
            let done = (route.completion / 100.0).clamp(0.0, 1.0);
            route.scores.then_some(Expected {
                pair: route.pair,
                stem,
                game_seconds: route.game_seconds,
                floor_seconds: f64::from(length) * done / TOP_SPEED,
            })
        })
        .collect()
}

fn has_repetition(id: &str) -> bool {
    id.rsplit_once("_rep")
        .is_some_and(|(_, n)| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
}

/// The recordings in S3, by (pair, stem): their sizes. `listed` holds submission-relative
/// keys under `recorder/`; anything else is left out.
fn stored(listed: &[(String, u64)]) -> HashMap<(PairId, &str), u64> {
    listed
        .iter()
        .filter_map(|(key, size)| {
            let rel = key.strip_prefix(RECORDER_DIR)?.strip_prefix('/')?;
            let (pair, stem) = recording_of(rel)?;
            Some(((pair, stem), *size))
        })
        .collect()
}

/// The audit of a result's recordings.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Recordings {
    /// Routes whose recording passed.
    pub passed: u64,
    /// Routes that need one (those that score).
    pub expected: u64,
    /// The first few routes that did not pass, each with why.
    pub failures: Vec<String>,
}

impl Recordings {
    /// Every route that needs a recording has one that passed.
    pub fn complete(&self) -> bool {
        self.passed == self.expected
    }
}

/// The Jobs' creation (epoch seconds): a recording of this run is dated after it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Window {
    /// When the run's Jobs were created.
    pub launched_at: u64,
}

/// Judges each expected recording by its place, its size and its head (`heads`: the first
/// [`HEAD_BYTES`] of each expected key read; a missing head fails its route).
pub fn audit(
    expected: &[Expected],
    listed: &[(String, u64)],
    heads: &HashMap<String, Vec<u8>>,
    window: Window,
) -> Recordings {
    let stored = stored(listed);
    let mut failures = Vec::new();
    let mut failed = 0u64;
    for e in expected {
        let why = match stored.get(&(e.pair, e.stem.as_str())) {
            None => Some(missing(e, &stored)),
            Some(&size) if size < e.min_bytes() && e.floor_seconds > e.game_seconds => {
                Some(format!(
                    "{size} bytes for the {:.1} s its route's completed part takes at least \
                     (its record claims {:.1} s; at least {} expected)",
                    e.floor_seconds,
                    e.game_seconds.max(0.0),
                    e.min_bytes()
                ))
            }
            Some(&size) if size < e.min_bytes() => Some(format!(
                "{size} bytes for {:.1} s of simulated time (at least {} expected)",
                e.game_seconds,
                e.min_bytes()
            )),
            Some(_) => match heads.get(&e.key()) {
                None => Some("its header could not be read".to_string()),
                Some(head) => header_flaw(head, window),
            },
        };
        if let Some(why) = why {
            failed += 1;
            if failures.len() < NAMED {
                failures.push(format!("{}: {why}", e.stem));
            }
        }
    }
    Recordings {
        passed: expected.len() as u64 - failed,
        expected: expected.len() as u64,
        failures,
    }
}

fn missing(e: &Expected, stored: &HashMap<(PairId, &str), u64>) -> String {
    let mut elsewhere: Vec<PairId> = stored
        .keys()
        .filter(|(_, stem)| *stem == e.stem)
        .map(|(pair, _)| *pair)
        .collect();
    elsewhere.sort_unstable();
    match elsewhere.first() {
        Some(other) => format!(
            "recorded in pair {other}'s folder, not in pair {}'s, whose simulator ran the route",
            e.pair
        ),
        None => format!("no recording in pair {}'s folder", e.pair),
    }
}

/// What is wrong with a recording's head, if anything: CARLA's magic, a date within the run,
/// a map's name.
pub fn header_flaw(head: &[u8], window: Window) -> Option<String> {
    let Some(rest) = head.strip_prefix(MAGIC) else {
        return Some("not a CARLA recording (no CARLA_RECORDER header)".to_string());
    };
    let date = rest.get(..8).map(|b| {
        let mut bytes = [0u8; 8];
        bytes.copy_from_slice(b);
        i64::from_le_bytes(bytes)
    });
    let launched = i64::try_from(window.launched_at).unwrap_or(i64::MAX);
    match date {
        None => return Some("its header is cut short".to_string()),
        Some(d) if d < launched.saturating_sub(CLOCK_SKEW_SECONDS) => {
            return Some(format!(
                "dated {d}, before the run's Jobs were created at {launched}"
            ))
        }
        Some(d) if d > launched.saturating_add(LATEST_SECONDS) => {
            return Some(format!("dated {d}, long after the run"))
        }
        Some(_) => {}
    }
    let map = rest.get(8..10).and_then(|len| {
        let len = usize::from(u16::from_le_bytes([len[0], len[1]]));
        rest.get(10..10 + len)
    });
    match map {
        Some(name)
            if !name.is_empty()
                && name.len() <= MAX_MAP_NAME
                && name.iter().all(|b| b.is_ascii_graphic()) =>
        {
            None
        }
        _ => Some("its header names no map".to_string()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LAUNCHED: u64 = 1_800_000_000;

    /// A recording's head as CARLA writes it, dated `date`.
    fn head(date: i64) -> Vec<u8> {
        let map = b"Carla/Maps/Town12";
        let mut bytes = MAGIC.to_vec();
        bytes.extend_from_slice(&date.to_le_bytes());
        bytes.extend_from_slice(&(map.len() as u16).to_le_bytes());
        bytes.extend_from_slice(map);
        bytes
    }

    /// A record of `id` (`RouteScenario_<N>...`) that completed its route.
    fn route(pair: PairId, id: &str, game_seconds: f64) -> Route {
        let number = id.trim_start_matches("RouteScenario_").split('_').next();
        Route {
            pair,
            id: id.into(),
            route: number.and_then(|n| n.parse().ok()).unwrap(),
            game_seconds,
            completion: 100.0,
            scores: true,
        }
    }

    #[test]
    fn each_scoring_record_needs_its_own_recording_in_its_pair_s_folder() {
        let v2 = expected(
            &[
                route(1, "RouteScenario_3_rep0", 10.0),
                route(2, "RouteScenario_4_rep0", 10.0),
            ],
            &[],
        );
        let keys: Vec<String> = v2.iter().map(Expected::key).collect();
        assert_eq!(
            keys,
            [
                "recorder/pair1/RouteScenario_3_rep0.log",
                "recorder/pair2/RouteScenario_4_rep0.log"
            ]
        );
        // 1.0: repetitions of one route id, recorded _rep0, _rep1, ...; a record that scores
        // nothing needs no recording, but still takes its repetition's number.
        let mut nothing = route(1, "RouteScenario_0", 0.0);
        nothing.scores = false;
        let v1 = expected(
            &[
                route(1, "RouteScenario_0", 10.0),
                nothing,
                route(1, "RouteScenario_0", 10.0),
            ],
            &[],
        );
        let stems: Vec<&str> = v1.iter().map(|e| e.stem.as_str()).collect();
        assert_eq!(stems, ["RouteScenario_0_rep0", "RouteScenario_0_rep2"]);
    }

    #[test]
    fn a_recording_passes_in_its_place_at_its_size_with_carla_s_header() {
        let routes = [
            route(1, "RouteScenario_0_rep0", 100.0),
            route(1, "RouteScenario_1_rep0", 100.0),
            route(2, "RouteScenario_2_rep0", 100.0),
            route(2, "RouteScenario_3_rep0", 100.0),
            route(2, "RouteScenario_4_rep0", 100.0),
            route(2, "RouteScenario_5_rep0", 100.0),
            route(2, "RouteScenario_6_rep0", 100.0),
        ];
        let expected = expected(&routes, &[]);
        let min = expected[0].min_bytes();
        // 100 simulated seconds: 20 frames a second of at least 34 bytes, 90 % of them.
        assert_eq!(min, 61_200 + MAGIC.len() as u64);
        let listed: Vec<(String, u64)> = [
            // Passes.
            ("recorder/pair1/RouteScenario_0_rep0.log", min),
            // A 1-byte file.
            ("recorder/pair1/RouteScenario_1_rep0.log", 1),
            // In another pair's folder: pair 1's simulator did not run it.
            ("recorder/pair1/RouteScenario_2_rep0.log", min),
            // RouteScenario_3 has none at all; 4 is not CARLA's; 5 is dated before the run.
            ("recorder/pair2/RouteScenario_4_rep0.log", min),
            ("recorder/pair2/RouteScenario_5_rep0.log", min),
            ("recorder/pair2/RouteScenario_6_rep0.log", min),
            // The participant's own folder is not a recordings folder.
            ("logs/agent/agent2/recorder/RouteScenario_3_rep0.log", min),
        ]
        .iter()
        .map(|(k, s)| (k.to_string(), *s))
        .collect();
        let to_read = [
            "recorder/pair1/RouteScenario_0_rep0.log",
            "recorder/pair2/RouteScenario_4_rep0.log",
            "recorder/pair2/RouteScenario_5_rep0.log",
        ]
        .map(String::from);
        let date = LAUNCHED as i64 + 600;
        let heads: HashMap<String, Vec<u8>> = [
            (to_read[0].clone(), head(date)),
            (to_read[1].clone(), b"\x00".repeat(64)),
            (to_read[2].clone(), head(LAUNCHED as i64 - 86_400)),
            // RouteScenario_6: its head could not be read.
        ]
        .into_iter()
        .collect();
        let window = Window {
            launched_at: LAUNCHED,
        };
        let audit = audit(&expected, &listed, &heads, window);
        assert_eq!((audit.passed, audit.expected), (1, 7));
        assert!(!audit.complete());
        assert_eq!(
            audit.failures,
            [
                "RouteScenario_1_rep0: 1 bytes for 100.0 s of simulated time (at least 61218 expected)",
                "RouteScenario_2_rep0: recorded in pair 1's folder, not in pair 2's, whose simulator ran the route",
                "RouteScenario_3_rep0: no recording in pair 2's folder",
                "RouteScenario_4_rep0: not a CARLA recording (no CARLA_RECORDER header)",
                "RouteScenario_5_rep0: dated 1799913600, before the run's Jobs were created at 1800000000",
            ]
        );
    }

    #[test]
    fn a_record_cannot_claim_less_time_than_its_route_s_completed_part_takes() {
        // The organisers' routes: 0 is 4,000 m, 1 is 1,000 m.
        let lengths = [4_000, 1_000];
        let mut half = route(1, "RouteScenario_1_rep0", 600.0);
        half.completion = 50.0;
        let claims = [route(1, "RouteScenario_0_rep0", 0.0), half];
        let expected = expected(&claims, &lengths);
        // 4,000 m at 40 m/s: 100 s, whatever the record says; half of 1,000 m: 12.5 s, below
        // the 600 s the record claims, which stand.
        assert_eq!(expected[0].seconds(), 100.0);
        assert_eq!(expected[0].min_bytes(), 61_200 + MAGIC.len() as u64);
        assert_eq!(expected[1].seconds(), 600.0);
        // A header-only recording fits a claim of 0 s, not the floor.
        let listed: Vec<(String, u64)> = vec![(expected[0].key(), 45)];
        let window = Window {
            launched_at: LAUNCHED,
        };
        let heads = HashMap::from([(expected[0].key(), head(LAUNCHED as i64))]);
        let audit = audit(&expected[..1], &listed, &heads, window);
        assert_eq!(
            audit.failures,
            ["RouteScenario_0_rep0: 45 bytes for the 100.0 s its route's completed part takes at \
              least (its record claims 0.0 s; at least 61218 expected)"]
        );
        // Without the organisers' lengths, the claim alone sizes it (and a header passes).
        let claimed_only = super::expected(&claims, &[]);
        assert_eq!(claimed_only[0].seconds(), 0.0);
        assert_eq!(
            super::audit(&claimed_only[..1], &listed, &heads, window).failures,
            Vec::<String>::new()
        );
    }

    #[test]
    fn a_header_names_its_date_and_map() {
        let window = Window {
            launched_at: LAUNCHED,
        };
        let good = head(LAUNCHED as i64);
        assert_eq!(header_flaw(&good, window), None);
        assert!(
            header_flaw(&good[..MAGIC.len() + 4], window).is_some_and(|w| w.contains("cut short"))
        );
        assert!(
            header_flaw(&good[..MAGIC.len() + 12], window).is_some_and(|w| w.contains("no map"))
        );
        assert!(header_flaw(&head(LAUNCHED as i64 + 40 * 86_400), window)
            .is_some_and(|w| w.contains("long after")));
        let mut no_map = MAGIC.to_vec();
        no_map.extend_from_slice(&(LAUNCHED as i64).to_le_bytes());
        no_map.extend_from_slice(&0u16.to_le_bytes());
        assert!(header_flaw(&no_map, window).is_some_and(|w| w.contains("no map")));
    }

    #[test]
    fn a_complete_audit_is_every_expected_recording_passing() {
        let expected = expected(&[route(3, "RouteScenario_9_rep0", 0.0)], &[]);
        let listed = vec![(expected[0].key(), MAGIC.len() as u64 + 40)];
        let heads = [(expected[0].key(), head(LAUNCHED as i64))]
            .into_iter()
            .collect();
        let window = Window {
            launched_at: LAUNCHED,
        };
        assert!(audit(&expected, &listed, &heads, window).complete());
        assert!(audit(&[], &[], &HashMap::new(), window).complete());
    }
}
