//! The ledger's compact form in the run's state, and its check when read back: the only place
//! that knows it. Each Job's entry is spread over five strings of a character or a number per
//! Job, so 1,024 Jobs stay a few KB of the 256 KiB a state may hold:
//!
//! - `jobs`: `.` no pod running at the last round, `a` + n its pod ran on the kind of usage
//!   line n, `A` + n the same disrupted (its lost time counted), `-` its disrupted pod went and
//!   no next pod started yet; trailing `.` left out;
//! - `failed`, `reclaims`, `charged`, `excess`, `moves`: one base-36 digit per Job (`failed`
//!   only for the Jobs a round saw, the others trailing `0` left out; `excess` no more than
//!   `charged`);
//! - `starts`: base-36 epoch seconds separated by commas, an empty field for none, trailing
//!   ones left out.
//!
//! States written before this module read the same. A state whose ledger names a usage line it
//! does not hold, a character no field has, more Jobs than a run may have, or more usage lines
//! than a ledger keeps is refused whole (the stage fails `InvalidInput`, naming it), so no later
//! rule meets an index that is not there.

use serde::{Deserialize, Deserializer, Serialize, Serializer};

use crate::capacity::cost::{JobEntry, JobMark, Ledger, Running, UsageLine, COUNT_CAP, MAX_LINES};
use crate::job::plan::MAX_WORKERS;

/// The ledger as the state stores it.
#[derive(Default, Serialize, Deserialize)]
struct Stored {
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    lines: Vec<UsageLine>,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    jobs: String,
    #[serde(default)]
    gpus: u32,
    #[serde(default)]
    last: u64,
    #[serde(default, skip_serializing_if = "is_zero")]
    lost: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    lost_since: Option<u64>,
    #[serde(default, skip_serializing_if = "is_zero")]
    lost_until: u64,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    failed: String,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    reclaims: String,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    charged: String,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    excess: String,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    moves: String,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    starts: String,
}

fn is_zero(n: &u64) -> bool {
    *n == 0
}

impl Serialize for Ledger {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        let jobs = &self.jobs;
        let marks: String = jobs.iter().map(|e| mark_char(e.mark)).collect();
        let counted = jobs.iter().take_while(|e| e.failed.is_some());
        let stored = Stored {
            lines: self.lines.clone(),
            jobs: marks.trim_end_matches('.').to_owned(),
            gpus: self.gpus,
            last: self.last,
            lost: self.lost,
            lost_since: self.lost_since,
            lost_until: self.lost_until,
            failed: counted.map(|e| digit_char(e.failed.unwrap_or(0))).collect(),
            reclaims: digits(jobs.iter().map(|e| e.reclaims)),
            charged: digits(jobs.iter().map(|e| e.charged)),
            excess: digits(jobs.iter().map(|e| e.excess)),
            moves: digits(jobs.iter().map(|e| e.moves)),
            starts: starts(jobs.iter().map(|e| e.start)),
        };
        stored.serialize(serializer)
    }
}

impl<'de> Deserialize<'de> for Ledger {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Ledger, D::Error> {
        let stored = Stored::deserialize(deserializer)?;
        read(stored).map_err(serde::de::Error::custom)
    }
}

/// The ledger a stored one says, checked.
fn read(stored: Stored) -> Result<Ledger, String> {
    if stored.lines.len() > MAX_LINES {
        return Err(format!(
            "the ledger holds {} usage lines, more than the {MAX_LINES} it keeps",
            stored.lines.len()
        ));
    }
    let fields = [
        &stored.jobs,
        &stored.failed,
        &stored.reclaims,
        &stored.charged,
        &stored.excess,
        &stored.moves,
    ];
    let count = fields.iter().map(|f| f.chars().count()).max().unwrap_or(0);
    let count =
        count.max(stored.starts.split(',').count() * usize::from(!stored.starts.is_empty()));
    if count > MAX_WORKERS as usize {
        return Err(format!(
            "the ledger names {count} Jobs, more than the {MAX_WORKERS} a run may have"
        ));
    }
    let mut jobs = vec![JobEntry::default(); count];
    for (entry, c) in jobs.iter_mut().zip(stored.jobs.chars()) {
        entry.mark = mark(c, stored.lines.len())?;
    }
    for (entry, c) in jobs.iter_mut().zip(stored.failed.chars()) {
        entry.failed = Some(count_digit("failed", c)?);
    }
    for (entry, c) in jobs.iter_mut().zip(stored.reclaims.chars()) {
        entry.reclaims = count_digit("reclaims", c)?;
    }
    for (entry, c) in jobs.iter_mut().zip(stored.charged.chars()) {
        entry.charged = count_digit("charged", c)?;
    }
    for (entry, c) in jobs.iter_mut().zip(stored.excess.chars()) {
        entry.excess = count_digit("excess", c)?;
        if entry.excess > entry.charged {
            return Err(format!(
                "the ledger's `excess` counts {} reclaims of a Job it charged {}",
                entry.excess, entry.charged
            ));
        }
    }
    for (entry, c) in jobs.iter_mut().zip(stored.moves.chars()) {
        entry.moves = count_digit("moves", c)?;
    }
    if !stored.starts.is_empty() {
        for (entry, field) in jobs.iter_mut().zip(stored.starts.split(',')) {
            entry.start = start(field)?;
        }
    }
    Ok(Ledger {
        lines: stored.lines,
        jobs,
        gpus: stored.gpus,
        last: stored.last,
        lost: stored.lost,
        lost_since: stored.lost_since,
        lost_until: stored.lost_until,
    })
}

fn mark_char(mark: JobMark) -> char {
    // NB: a ledger has at most MAX_LINES (< 26) lines, so an offset fits a letter.
    let letter = |base: u8, line: usize| char::from(base + line.min(25) as u8);
    match mark {
        JobMark::Idle => '.',
        JobMark::Reclaimed => '-',
        JobMark::Running(r) if r.disrupted => letter(b'A', r.line),
        JobMark::Running(r) => letter(b'a', r.line),
    }
}

fn mark(c: char, lines: usize) -> Result<JobMark, String> {
    let running = |line: u8, disrupted: bool| {
        let line = usize::from(line);
        match line < lines {
            true => Ok(JobMark::Running(Running { line, disrupted })),
            false => Err(format!(
                "the ledger's Job marks name usage line {line}, and it holds {lines}"
            )),
        }
    };
    match c {
        '.' => Ok(JobMark::Idle),
        '-' => Ok(JobMark::Reclaimed),
        'a'..='z' => running(c as u8 - b'a', false),
        'A'..='Z' => running(c as u8 - b'A', true),
        other => Err(format!(
            "the ledger's Job marks hold `{}`, which is no mark",
            other.escape_debug()
        )),
    }
}

fn digit_char(n: u32) -> char {
    char::from_digit(n.min(COUNT_CAP), 36).unwrap_or('z')
}

/// One count per Job, trailing zeros left out.
fn digits(counts: impl Iterator<Item = u32>) -> String {
    let text: String = counts.map(digit_char).collect();
    text.trim_end_matches('0').to_owned()
}

fn count_digit(field: &str, c: char) -> Result<u32, String> {
    c.to_digit(36).ok_or_else(|| {
        format!(
            "the ledger's `{field}` holds `{}`, which is no count",
            c.escape_debug()
        )
    })
}

/// One start per Job (base 36, empty for none), trailing empty ones left out.
fn starts(starts: impl Iterator<Item = Option<u64>>) -> String {
    let fields: Vec<String> = starts
        .map(|s| s.filter(|s| *s != 0).map(base36).unwrap_or_default())
        .collect();
    let kept = fields.len() - fields.iter().rev().take_while(|f| f.is_empty()).count();
    fields[..kept].join(",")
}

fn start(field: &str) -> Result<Option<u64>, String> {
    if field.is_empty() {
        return Ok(None);
    }
    let at = u64::from_str_radix(field, 36).map_err(|_| {
        format!(
            "the ledger's `starts` holds `{}`, which is no time",
            field.escape_debug()
        )
    })?;
    Ok(Some(at).filter(|s| *s != 0))
}

/// `n` in base 36 (lowercase).
fn base36(mut n: u64) -> String {
    let mut digits = Vec::new();
    loop {
        digits.push(char::from_digit((n % 36) as u32, 36).unwrap_or('0'));
        n /= 36;
        if n == 0 {
            break;
        }
    }
    digits.iter().rev().collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capacity::cost::{CapacityType, NodeKind};

    fn line() -> UsageLine {
        UsageLine {
            kind: NodeKind {
                instance_type: "g5.12xlarge".into(),
                capacity: CapacityType::Spot,
            },
            held: 60,
            run_again: 0,
        }
    }

    #[test]
    fn a_ledger_round_trips_through_its_compact_form_as_states_before_it_wrote_it() {
        let stored = serde_json::json!({
            "lines": [{"type": "g5.12xlarge", "capacity": "spot", "held": 60, "run_again": 0}],
            "jobs": ".aA-", "gpus": 1, "last": 1000, "failed": "0102",
            "reclaims": "001", "charged": "02", "moves": "0001", "starts": ",rs,rt"
        });
        let ledger: Ledger = serde_json::from_value(stored.clone()).unwrap();
        assert_eq!(ledger.jobs.len(), 4);
        assert_eq!(ledger.jobs[3].moves, 1);
        assert_eq!(
            ledger.jobs[1].mark,
            JobMark::Running(Running {
                line: 0,
                disrupted: false
            })
        );
        assert_eq!(
            ledger.jobs[2].mark,
            JobMark::Running(Running {
                line: 0,
                disrupted: true
            })
        );
        assert_eq!(ledger.jobs[3].mark, JobMark::Reclaimed);
        assert_eq!(ledger.jobs[3].failed, Some(2));
        assert_eq!((ledger.jobs[2].reclaims, ledger.jobs[1].charged), (1, 2));
        assert_eq!(
            ledger.jobs[1].start,
            Some(u64::from_str_radix("rs", 36).unwrap())
        );
        assert_eq!(ledger.jobs[0].start, None);
        assert_eq!(serde_json::to_value(&ledger).unwrap(), stored);
        // A count's trailing zeros, as earlier versions kept them, read the same.
        let mut older = stored;
        older["reclaims"] = "0010".into();
        assert_eq!(serde_json::from_value::<Ledger>(older).unwrap(), ledger);
    }

    #[test]
    fn a_ledger_that_names_what_it_does_not_hold_is_refused_naming_it() {
        let refused = |ledger: serde_json::Value| {
            serde_json::from_value::<Ledger>(ledger)
                .unwrap_err()
                .to_string()
        };
        let no_line = refused(serde_json::json!({"jobs": "b", "lines": [line()]}));
        assert!(
            no_line.contains("usage line 1, and it holds 1"),
            "{no_line}"
        );
        assert!(refused(serde_json::json!({"jobs": "a"})).contains("usage line 0"));
        assert!(refused(serde_json::json!({"jobs": "*"})).contains("no mark"));
        assert!(refused(serde_json::json!({"charged": "!"})).contains("`charged`"));
        assert!(refused(serde_json::json!({"moves": "?"})).contains("`moves`"));
        let excess = refused(serde_json::json!({"charged": "1", "excess": "2"}));
        assert!(
            excess.contains("`excess` counts 2 reclaims of a Job it charged 1"),
            "{excess}"
        );
        let ok: Ledger =
            serde_json::from_value(serde_json::json!({"charged": "13", "excess": "02"})).unwrap();
        assert_eq!((ok.jobs[1].charged, ok.jobs[1].excess), (3, 2));
        assert_eq!(serde_json::to_value(&ok).unwrap()["excess"], "02");
        assert!(refused(serde_json::json!({"starts": "1,x!"})).contains("`starts`"));
        let many = "0".repeat(MAX_WORKERS as usize + 1);
        assert!(refused(serde_json::json!({ "failed": many })).contains("Jobs"));
        let lines = vec![line(); MAX_LINES + 1];
        assert!(refused(serde_json::json!({ "lines": lines })).contains("usage lines"));
    }

    #[test]
    fn counts_saturate_at_one_character_and_an_empty_ledger_stores_nothing_per_job() {
        let ledger = Ledger {
            jobs: vec![JobEntry {
                charged: 99,
                ..JobEntry::default()
            }],
            ..Ledger::default()
        };
        let stored = serde_json::to_value(&ledger).unwrap();
        assert_eq!(stored["charged"], "z");
        assert_eq!(
            serde_json::to_value(Ledger::default()).unwrap(),
            serde_json::json!({"gpus": 0, "last": 0})
        );
    }
}
