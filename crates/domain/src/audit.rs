//! What operators can audit of a result: the CARLA recordings of its routes. The evaluator
//! runs in the participant's process and writes the scores; the CARLA server (the organizers'
//! image) writes a recording of each route into the pair's `recorder` folder, which replays
//! the route as the simulator ran it. A FINISHED result whose routes lack recordings cannot be
//! checked that way, and is flagged (`docs/security.md`).

use std::collections::{HashMap, HashSet};

use crate::protocol::{agent_logs_dir, LOGS_DIR};

/// The recordings folder in a pair's agent logs (the evaluator's `--record`).
pub const RECORDER_DIR: &str = "recorder";

/// The recording a key names, relative to the submission's folder
/// (`logs/agent/agent<ID>/recorder/<route>_rep<r>.log`): its file stem, `None` for any other
/// key.
pub fn recording_of(relative: &str) -> Option<&str> {
    let rest = relative.strip_prefix(LOGS_DIR)?.strip_prefix('/')?;
    let (dir, file) = rest.rsplit_once('/')?;
    let (pair_dir, recorder) = dir.rsplit_once('/')?;
    let pair: u32 = pair_dir
        .strip_prefix("agent/agent")?
        .parse()
        .ok()
        .filter(|p| *p > 0)?;
    if recorder != RECORDER_DIR || pair_dir != agent_logs_dir(pair) {
        return None;
    }
    file.strip_suffix(".log").filter(|stem| !stem.is_empty())
}

/// The recording each record needs, by its route id: `RouteScenario_3_rep1` is recorded as
/// `RouteScenario_3_rep1.log`; a route id without a repetition (Leaderboard 1.0) is recorded
/// once per record, as repetitions `_rep0`, `_rep1`, ... in the records' order.
pub fn expected_recordings<'a>(route_ids: impl IntoIterator<Item = &'a str>) -> Vec<String> {
    let mut seen: HashMap<&str, u32> = HashMap::new();
    route_ids
        .into_iter()
        .map(|id| {
            if has_repetition(id) {
                id.to_string()
            } else {
                let n = seen.entry(id).or_default();
                let name = format!("{id}_rep{n}");
                *n += 1;
                name
            }
        })
        .collect()
}

fn has_repetition(id: &str) -> bool {
    id.rsplit_once("_rep")
        .is_some_and(|(_, n)| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
}

/// How many of a result's routes have their recording.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Recordings {
    /// Routes with a (non-empty) recording.
    pub found: u64,
    /// Routes of the result.
    pub expected: u64,
    /// The first few routes without one, for the record.
    pub missing: Vec<String>,
}

impl Recordings {
    /// Every route has its recording.
    pub fn complete(&self) -> bool {
        self.found == self.expected
    }
}

/// The most missing routes named.
const NAMED: usize = 5;

/// The recordings `expected` checked against the non-empty recordings `present` (stems).
pub fn audit(expected: &[String], present: &HashSet<&str>) -> Recordings {
    let missing: Vec<&String> = expected
        .iter()
        .filter(|name| !present.contains(name.as_str()))
        .collect();
    Recordings {
        found: (expected.len() - missing.len()) as u64,
        expected: expected.len() as u64,
        missing: missing.into_iter().take(NAMED).cloned().collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_a_pairs_recorder_files_are_recordings() {
        assert_eq!(
            recording_of("logs/agent/agent2/recorder/RouteScenario_7_rep0.log"),
            Some("RouteScenario_7_rep0")
        );
        for other in [
            "logs/agent/agent2/agent.log",
            "logs/agent/agent2/recorder/",
            "logs/agent/agent2/recorder/.log",
            "logs/agent/agent2/recorder/x.txt",
            "logs/agent/agent0/recorder/a.log",
            "logs/agent/agentx/recorder/a.log",
            "logs/agent/agent02/recorder/a.log",
            "logs/agent/agent2/recorder/deep/a.log",
            "logs/simulator/simulator2.log",
            "agent/partial_agent_results2.json",
        ] {
            assert_eq!(recording_of(other), None, "{other}");
        }
    }

    #[test]
    fn each_record_needs_its_own_recording() {
        let v2 = expected_recordings(["RouteScenario_3_rep0", "RouteScenario_4_rep0"]);
        assert_eq!(v2, ["RouteScenario_3_rep0", "RouteScenario_4_rep0"]);
        // 1.0: five repetitions of one route id, recorded _rep0 to _rep4.
        let v1 = expected_recordings(["RouteScenario_0"; 3]);
        assert_eq!(
            v1,
            [
                "RouteScenario_0_rep0",
                "RouteScenario_0_rep1",
                "RouteScenario_0_rep2"
            ]
        );
        let present = HashSet::from(["RouteScenario_0_rep0", "RouteScenario_0_rep2"]);
        let audit = audit(&v1, &present);
        assert_eq!((audit.found, audit.expected), (2, 3));
        assert_eq!(audit.missing, ["RouteScenario_0_rep1"]);
        assert!(!audit.complete());
        assert!(super::audit(
            &v2,
            &HashSet::from(["RouteScenario_3_rep0", "RouteScenario_4_rep0"])
        )
        .complete());
    }
}
