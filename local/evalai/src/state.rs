//! The fake's in-memory database and its public snapshots.

use std::collections::{BTreeMap, HashMap};

use serde::{Deserialize, Serialize};
use time::OffsetDateTime;

use crate::faults::FaultState;
use crate::fixture::{Fixture, SubmissionFixture, TokenKind};
use crate::pyjson::PyValue;
use crate::reqlog::RequestLog;
use crate::statuses;
use crate::throttle::Throttle;
use crate::timefmt;

/// An account.
#[derive(Debug, Clone)]
pub(crate) struct User {
    pub email_verified: bool,
    pub active: bool,
    pub staff: bool,
}

/// An authentication token.
#[derive(Debug, Clone)]
pub(crate) struct Token {
    pub kind: TokenKind,
    pub user: u64,
    pub expired: bool,
    pub blacklisted: bool,
}

#[derive(Debug, Clone)]
pub(crate) struct HostTeam {
    pub members: Vec<u64>,
    pub challenges: Vec<u64>,
}

#[derive(Debug, Clone)]
pub(crate) struct Team {
    pub name: String,
    pub members: Vec<u64>,
    pub challenges: Vec<u64>,
}

#[derive(Debug, Clone)]
pub(crate) struct Split {
    pub id: u64,
    pub codename: String,
    pub labels: Vec<String>,
}

#[derive(Debug, Clone)]
pub(crate) struct Phase {
    pub challenge: u64,
    pub partial_evaluation_enabled: bool,
    pub splits: Vec<Split>,
}

/// Files EvalAI stores for a submission (the latest content of each).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct SubmissionFiles {
    /// `stdout.txt`.
    pub stdout: Option<String>,
    /// `stderr.txt`.
    pub stderr: Option<String>,
    /// `environment_log.txt` (host only).
    pub environment_log: Option<String>,
    /// `submission_result.json`: Python `str()` of the public accuracies list.
    pub result: Option<String>,
    /// `submission_metadata_file.json`: Python `str()` of `metadata` (host only).
    pub metadata: Option<String>,
}

#[derive(Debug, Clone)]
pub(crate) struct Submission {
    pub id: u64,
    pub phase: u64,
    pub team: u64,
    pub created_by: u64,
    pub status: String,
    pub submitted_image_uri: Option<String>,
    pub submitted_at: OffsetDateTime,
    pub started_at: Option<OffsetDateTime>,
    pub completed_at: Option<OffsetDateTime>,
    pub rerun_resumed_at: Option<OffsetDateTime>,
    pub when_made_public: Option<OffsetDateTime>,
    pub method_name: String,
    pub method_description: String,
    pub project_url: String,
    pub publication_url: String,
    pub is_public: bool,
    pub is_flagged: bool,
    pub ignore_submission: bool,
    pub is_baseline: bool,
    pub is_verified_by_host: bool,
    pub job_name: Option<Vec<String>>,
    pub submission_metadata: Option<PyValue>,
    pub files: SubmissionFiles,
}

/// A `LeaderboardData` row.
#[derive(Debug, Clone)]
pub(crate) struct Row {
    pub id: u64,
    pub submission: u64,
    pub phase: u64,
    pub split: u64,
    pub result: Vec<(String, PyValue)>,
    pub created_at: OffsetDateTime,
    pub updated_at: OffsetDateTime,
}

/// The files a submission serves, by name; the index is the kind in `World::media_path`.
pub(crate) const MEDIA_FILES: [&str; 5] = [
    "input_file.json",
    "stdout.txt",
    "stderr.txt",
    "environment_log.txt",
    "submission_result.json",
];

/// Everything behind the server's lock.
pub(crate) struct World {
    pub users: BTreeMap<u64, User>,
    pub tokens: HashMap<String, Token>,
    pub host_teams: Vec<HostTeam>,
    pub teams: BTreeMap<u64, Team>,
    pub phases: BTreeMap<u64, Phase>,
    pub submissions: BTreeMap<u64, Submission>,
    pub rows: Vec<Row>,
    pub next_row_id: u64,
    pub throttle: Throttle,
    pub faults: FaultState,
    pub log: RequestLog,
    /// The proxy's body limit (`Fixture::max_request_bytes`).
    pub max_request_bytes: usize,
}

/// A submission to add through the admin API (a participant pushing an image).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NewSubmission {
    /// Phase id.
    pub challenge_phase: u64,
    /// Participant team id.
    pub participant_team: u64,
    /// Docker image URI, served in the `input_file` JSON.
    pub submitted_image_uri: String,
    /// Creator (default: the team's first member).
    #[serde(default)]
    pub created_by: Option<u64>,
    /// What the participant's form sent as `submission_metadata` (any JSON, any size: EvalAI
    /// bounds neither).
    #[serde(default)]
    pub submission_metadata: Option<serde_json::Value>,
}

/// Why an admin operation was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum AdminError {
    /// No submission with that id.
    #[error("submission `{0}` does not exist")]
    UnknownSubmission(u64),
    /// Resume is only possible from `failed` (EvalAI's rule).
    #[error("only failed submissions can be resumed (submission `{id}` is `{status}`)")]
    NotResumable {
        /// Submission id.
        id: u64,
        /// Its current status.
        status: String,
    },
    /// The new submission names something unknown or inconsistent.
    #[error("invalid submission: {0}")]
    InvalidSubmission(String),
    /// A fault rate or parameter is out of range.
    #[error("invalid faults: {0}")]
    InvalidFaults(String),
}

impl AdminError {
    /// Stable PascalCase name of the error kind.
    pub fn name(&self) -> &'static str {
        match self {
            AdminError::UnknownSubmission(_) => "UnknownSubmission",
            AdminError::NotResumable { .. } => "NotResumable",
            AdminError::InvalidSubmission(_) => "InvalidSubmission",
            AdminError::InvalidFaults(_) => "InvalidFaults",
        }
    }
}

/// A leaderboard row as the admin API shows it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LeaderboardRowSnapshot {
    /// Row id.
    pub id: u64,
    /// Phase id of the split.
    pub challenge_phase: u64,
    /// Split codename.
    pub split: String,
    /// The stored `result` (accuracies).
    pub result: serde_json::Value,
    /// When the row was created (ISO-8601).
    pub created_at: String,
    /// When it was last written (ISO-8601).
    pub updated_at: String,
}

/// A submission as the admin API shows it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SubmissionSnapshot {
    /// Submission id.
    pub id: u64,
    /// Challenge id (derived from the phase).
    pub challenge: u64,
    /// Phase id.
    pub challenge_phase: u64,
    /// Participant team id.
    pub participant_team: u64,
    /// Participant team name.
    pub participant_team_name: String,
    /// Creator user id.
    pub created_by: u64,
    /// Lowercase status.
    pub status: String,
    /// Image URI from the input file.
    pub submitted_image_uri: Option<String>,
    /// ISO-8601.
    pub submitted_at: String,
    /// ISO-8601 or null.
    pub started_at: Option<String>,
    /// ISO-8601 or null.
    pub completed_at: Option<String>,
    /// ISO-8601 or null.
    pub rerun_resumed_at: Option<String>,
    /// Job names, in the order they were appended.
    pub job_name: Option<Vec<String>>,
    /// `ignore_submission` (participant "deleted" it).
    pub ignore_submission: bool,
    /// `submission_metadata` JSON field.
    pub submission_metadata: Option<serde_json::Value>,
    /// Stored files.
    pub files: SubmissionFiles,
    /// Leaderboard rows of this submission, in creation order.
    pub leaderboard: Vec<LeaderboardRowSnapshot>,
}

/// The whole observable state.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StateSnapshot {
    /// Every submission, by id.
    pub submissions: Vec<SubmissionSnapshot>,
}

impl StateSnapshot {
    /// The submission with that id, if any.
    pub fn submission(&self, id: u64) -> Option<&SubmissionSnapshot> {
        self.submissions.iter().find(|s| s.id == id)
    }
}

fn ts(value: &Option<String>) -> Option<OffsetDateTime> {
    value.as_deref().and_then(timefmt::parse)
}

impl World {
    /// Builds the database from a validated fixture.
    pub fn from_fixture(fixture: &Fixture) -> World {
        let started = timefmt::now();
        let users = fixture
            .users
            .iter()
            .map(|u| {
                (
                    u.id,
                    User {
                        email_verified: u.email_verified,
                        active: u.active,
                        staff: u.staff,
                    },
                )
            })
            .collect();
        let tokens = fixture
            .tokens
            .iter()
            .map(|t| {
                (
                    t.value.clone(),
                    Token {
                        kind: t.kind,
                        user: t.user,
                        expired: t.expired,
                        blacklisted: t.blacklisted,
                    },
                )
            })
            .collect();
        let host_teams = fixture
            .host_teams
            .iter()
            .map(|t| HostTeam {
                members: t.members.clone(),
                challenges: t.challenges.clone(),
            })
            .collect();
        let phases = phases_of(fixture);
        let mut teams: BTreeMap<u64, Team> = fixture
            .participant_teams
            .iter()
            .map(|t| {
                (
                    t.id,
                    Team {
                        name: t.name.clone(),
                        members: t.members.clone(),
                        challenges: t.challenges.clone(),
                    },
                )
            })
            .collect();
        let mut submissions = BTreeMap::new();
        for s in &fixture.submissions {
            let challenge = phases.get(&s.challenge_phase).map_or(0, |p| p.challenge);
            if let Some(team) = teams.get_mut(&s.participant_team) {
                if !team.challenges.contains(&challenge) {
                    team.challenges.push(challenge);
                }
            }
            submissions.insert(s.id, submission_of(s, started));
        }
        World {
            users,
            tokens,
            host_teams,
            teams,
            phases,
            submissions,
            rows: Vec::new(),
            next_row_id: 1,
            throttle: Throttle::new(fixture.throttle_per_minute, fixture.throttle_window_secs),
            faults: FaultState::default(),
            log: RequestLog::default(),
            max_request_bytes: fixture.max_request_bytes,
        }
    }

    /// `is_user_a_host_of_challenge`: member of the host team that created the challenge.
    pub fn is_host(&self, user: u64, challenge: u64) -> bool {
        self.host_teams
            .iter()
            .any(|t| t.challenges.contains(&challenge) && t.members.contains(&user))
    }

    /// Django's `is_staff`.
    pub fn is_staff(&self, user: u64) -> bool {
        self.users.get(&user).is_some_and(|u| u.staff)
    }

    /// `get_participant_team_id_of_user_for_a_challenge`.
    pub fn team_of_user_for_challenge(&self, user: u64, challenge: u64) -> Option<u64> {
        self.teams
            .iter()
            .find(|(_, t)| t.members.contains(&user) && t.challenges.contains(&challenge))
            .map(|(id, _)| *id)
    }

    /// The challenge a submission belongs to (through its phase).
    pub fn challenge_of(&self, submission: &Submission) -> u64 {
        self.phases
            .get(&submission.phase)
            .map_or(0, |p| p.challenge)
    }

    /// Whether any phase belongs to the challenge.
    pub fn challenge_exists(&self, challenge: u64) -> bool {
        self.host_teams
            .iter()
            .any(|t| t.challenges.contains(&challenge))
    }

    /// The split with that codename in that phase.
    pub fn split(&self, phase: u64, codename: &str) -> Option<(&Phase, &Split)> {
        let p = self.phases.get(&phase)?;
        p.splits
            .iter()
            .find(|s| s.codename == codename)
            .map(|s| (p, s))
    }

    fn split_by_id(&self, split: u64) -> Option<&Split> {
        self.phases
            .values()
            .flat_map(|p| p.splits.iter())
            .find(|s| s.id == split)
    }

    /// Where a submission's stored file is served, in EvalAI's media layout
    /// (`submission_files/challenge_<c>/phase_<p>/submission_<id>/<uuid>.<ext>`). The uuid is
    /// made of the file's kind and the submission id, so that a path leads back to its file.
    pub fn media_path(&self, s: &Submission, name: &str) -> String {
        let kind = MEDIA_FILES.iter().position(|f| *f == name).unwrap_or(0);
        let ext = name.rsplit('.').next().unwrap_or("txt");
        format!(
            "/media/submission_files/challenge_{}/phase_{}/submission_{}/{kind:08x}-0000-4000-8000-{:012x}.{ext}",
            self.challenge_of(s),
            s.phase,
            s.id,
            s.id
        )
    }

    /// The submission and file name a media path serves, if it is one `media_path` gives.
    pub fn resolve_media(&self, path: &str) -> Option<(u64, &'static str)> {
        let rest = path.strip_prefix("/media/submission_files/")?;
        let id = rest
            .split('/')
            .find_map(|part| part.strip_prefix("submission_"))?
            .parse::<u64>()
            .ok()?;
        let s = self.submissions.get(&id)?;
        MEDIA_FILES
            .iter()
            .find(|name| self.media_path(s, name) == path)
            .map(|name| (id, *name))
    }

    /// `SubmissionSerializer(submission).data`, fields in EvalAI's order.
    pub fn serialize_submission(&self, s: &Submission, base_url: &str, host: bool) -> PyValue {
        let url = |name: &str| PyValue::Str(format!("{base_url}{}", self.media_path(s, name)));
        let file = |present: bool, name: &str| {
            if present {
                url(name)
            } else {
                PyValue::None
            }
        };
        let time = |t: Option<OffsetDateTime>| {
            t.map_or(PyValue::None, |t| PyValue::Str(timefmt::format(t)))
        };
        let execution_time = match (s.started_at, s.completed_at) {
            (Some(start), Some(end)) => {
                let d = end - start;
                PyValue::Float(d.whole_microseconds() as f64 / 1e6)
            }
            _ => PyValue::str("None"),
        };
        let team_name = self
            .teams
            .get(&s.team)
            .map_or(String::new(), |t| t.name.clone());
        let mut fields: Vec<(&str, PyValue)> = vec![
            ("id", PyValue::Int(i128::from(s.id))),
            ("participant_team", PyValue::Int(i128::from(s.team))),
            ("participant_team_name", PyValue::Str(team_name)),
            ("execution_time", execution_time),
            ("challenge_phase", PyValue::Int(i128::from(s.phase))),
            ("created_by", PyValue::Int(i128::from(s.created_by))),
            ("status", PyValue::Str(s.status.clone())),
            ("input_file", url("input_file.json")),
            ("submission_input_file", PyValue::None),
            ("stdout_file", file(s.files.stdout.is_some(), "stdout.txt")),
            ("stderr_file", file(s.files.stderr.is_some(), "stderr.txt")),
        ];
        if host {
            fields.push((
                "environment_log_file",
                file(s.files.environment_log.is_some(), "environment_log.txt"),
            ));
        }
        fields.extend([
            ("started_at", time(s.started_at)),
            ("completed_at", time(s.completed_at)),
            ("submitted_at", time(Some(s.submitted_at))),
            ("rerun_resumed_at", time(s.rerun_resumed_at)),
            ("when_made_public", time(s.when_made_public)),
            ("method_name", PyValue::Str(s.method_name.clone())),
            (
                "method_description",
                PyValue::Str(s.method_description.clone()),
            ),
            ("project_url", PyValue::Str(s.project_url.clone())),
            ("publication_url", PyValue::Str(s.publication_url.clone())),
            ("is_public", PyValue::Bool(s.is_public)),
            ("is_flagged", PyValue::Bool(s.is_flagged)),
            ("ignore_submission", PyValue::Bool(s.ignore_submission)),
            ("is_baseline", PyValue::Bool(s.is_baseline)),
            ("is_verified_by_host", PyValue::Bool(s.is_verified_by_host)),
            (
                "submission_result_file",
                file(s.files.result.is_some(), "submission_result.json"),
            ),
            (
                "job_name",
                s.job_name.as_ref().map_or(PyValue::None, |names| {
                    PyValue::List(names.iter().cloned().map(PyValue::Str).collect())
                }),
            ),
            (
                "submission_metadata",
                s.submission_metadata.clone().unwrap_or(PyValue::None),
            ),
        ]);
        PyValue::dict(fields)
    }

    /// The content of a stored file, by its name (one of `MEDIA_FILES`).
    pub fn file(&self, submission: u64, name: &str) -> Option<(String, &'static str)> {
        let s = self.submissions.get(&submission)?;
        let text = |v: &Option<String>| v.clone();
        match name {
            "input_file.json" => {
                let body = match &s.submitted_image_uri {
                    Some(uri) => PyValue::dict(vec![("submitted_image_uri", PyValue::str(uri))]),
                    None => PyValue::Dict(Vec::new()),
                };
                Some((body.dumps_spaced(), "application/json"))
            }
            "stdout.txt" => text(&s.files.stdout).map(|t| (t, "text/plain; charset=utf-8")),
            "stderr.txt" => text(&s.files.stderr).map(|t| (t, "text/plain; charset=utf-8")),
            "environment_log.txt" => {
                text(&s.files.environment_log).map(|t| (t, "text/plain; charset=utf-8"))
            }
            "submission_result.json" => text(&s.files.result).map(|t| (t, "application/json")),
            _ => None,
        }
    }

    fn snapshot_of(&self, s: &Submission) -> SubmissionSnapshot {
        let fmt = |t: Option<OffsetDateTime>| t.map(timefmt::format);
        SubmissionSnapshot {
            id: s.id,
            challenge: self.challenge_of(s),
            challenge_phase: s.phase,
            participant_team: s.team,
            participant_team_name: self
                .teams
                .get(&s.team)
                .map_or(String::new(), |t| t.name.clone()),
            created_by: s.created_by,
            status: s.status.clone(),
            submitted_image_uri: s.submitted_image_uri.clone(),
            submitted_at: timefmt::format(s.submitted_at),
            started_at: fmt(s.started_at),
            completed_at: fmt(s.completed_at),
            rerun_resumed_at: fmt(s.rerun_resumed_at),
            job_name: s.job_name.clone(),
            ignore_submission: s.ignore_submission,
            submission_metadata: s.submission_metadata.as_ref().map(PyValue::to_json),
            files: s.files.clone(),
            leaderboard: self
                .rows
                .iter()
                .filter(|r| r.submission == s.id)
                .map(|r| LeaderboardRowSnapshot {
                    id: r.id,
                    challenge_phase: r.phase,
                    split: self
                        .split_by_id(r.split)
                        .map_or(String::new(), |sp| sp.codename.clone()),
                    result: PyValue::Dict(r.result.clone()).to_json(),
                    created_at: timefmt::format(r.created_at),
                    updated_at: timefmt::format(r.updated_at),
                })
                .collect(),
        }
    }

    /// The admin view of everything.
    pub fn snapshot(&self) -> StateSnapshot {
        StateSnapshot {
            submissions: self
                .submissions
                .values()
                .map(|s| self.snapshot_of(s))
                .collect(),
        }
    }

    /// The admin view of one submission.
    pub fn submission_snapshot(&self, id: u64) -> Option<SubmissionSnapshot> {
        self.submissions.get(&id).map(|s| self.snapshot_of(s))
    }

    /// The participant's cancel: `PATCH update_submission_meta {"status": "cancelled"}`.
    pub fn cancel(&mut self, id: u64) -> Result<SubmissionSnapshot, AdminError> {
        let s = self
            .submissions
            .get_mut(&id)
            .ok_or(AdminError::UnknownSubmission(id))?;
        s.status = statuses::CANCELLED.to_owned();
        Ok(self.snapshot_of(&self.submissions[&id]))
    }

    /// EvalAI's resume: only `failed` -> `resuming`, `rerun_resumed_at` = now.
    pub fn resume(&mut self, id: u64) -> Result<SubmissionSnapshot, AdminError> {
        let s = self
            .submissions
            .get_mut(&id)
            .ok_or(AdminError::UnknownSubmission(id))?;
        if s.status != statuses::FAILED {
            return Err(AdminError::NotResumable {
                id,
                status: s.status.clone(),
            });
        }
        s.status = statuses::RESUMING.to_owned();
        s.rerun_resumed_at = Some(timefmt::now());
        Ok(self.snapshot_of(&self.submissions[&id]))
    }

    /// A participant's new submission (status `submitted`, next free id).
    pub fn add_submission(&mut self, new: NewSubmission) -> Result<SubmissionSnapshot, AdminError> {
        let bad = |m: String| Err(AdminError::InvalidSubmission(m));
        let Some(phase) = self.phases.get(&new.challenge_phase) else {
            return bad(format!("unknown phase `{}`", new.challenge_phase));
        };
        let challenge = phase.challenge;
        let Some(team) = self.teams.get_mut(&new.participant_team) else {
            return bad(format!(
                "unknown participant team `{}`",
                new.participant_team
            ));
        };
        let created_by = match new.created_by {
            Some(u) if team.members.contains(&u) => u,
            Some(u) => {
                return bad(format!(
                    "user `{u}` is not a member of team `{}`",
                    new.participant_team
                ))
            }
            None => match team.members.first() {
                Some(u) => *u,
                None => return bad(format!("team `{}` has no members", new.participant_team)),
            },
        };
        if new.submitted_image_uri.trim().is_empty() {
            return bad("`submitted_image_uri` is empty".to_owned());
        }
        if !team.challenges.contains(&challenge) {
            team.challenges.push(challenge);
        }
        let id = self
            .submissions
            .keys()
            .next_back()
            .map_or(1, |last| last + 1);
        self.submissions.insert(
            id,
            Submission {
                id,
                phase: new.challenge_phase,
                team: new.participant_team,
                created_by,
                status: statuses::SUBMITTED.to_owned(),
                submitted_image_uri: Some(new.submitted_image_uri),
                submitted_at: timefmt::now(),
                started_at: None,
                completed_at: None,
                rerun_resumed_at: None,
                when_made_public: None,
                method_name: String::new(),
                method_description: String::new(),
                project_url: String::new(),
                publication_url: String::new(),
                is_public: false,
                is_flagged: false,
                ignore_submission: false,
                is_baseline: false,
                is_verified_by_host: false,
                job_name: Some(Vec::new()),
                submission_metadata: new.submission_metadata.as_ref().map(PyValue::from_json),
                files: SubmissionFiles::default(),
            },
        );
        Ok(self.snapshot_of(&self.submissions[&id]))
    }
}

/// Each phase of the fixture's challenges, by id, its splits numbered from 1 across them all.
fn phases_of(fixture: &Fixture) -> BTreeMap<u64, Phase> {
    let mut next_split = 1;
    let mut phases = BTreeMap::new();
    for c in &fixture.challenges {
        for p in &c.phases {
            let splits = p
                .splits
                .iter()
                .map(|s| {
                    let id = next_split;
                    next_split += 1;
                    Split {
                        id,
                        codename: s.codename.clone(),
                        labels: s.labels.clone(),
                    }
                })
                .collect();
            phases.insert(
                p.id,
                Phase {
                    challenge: c.id,
                    partial_evaluation_enabled: p.partial_evaluation_enabled,
                    splits,
                },
            );
        }
    }
    phases
}

/// A fixture's submission as the world holds it (`started`: its submission time if it has
/// none).
fn submission_of(s: &SubmissionFixture, started: OffsetDateTime) -> Submission {
    Submission {
        id: s.id,
        phase: s.challenge_phase,
        team: s.participant_team,
        created_by: s.created_by,
        status: s.status.clone(),
        submitted_image_uri: s.submitted_image_uri.clone(),
        submitted_at: ts(&s.submitted_at).unwrap_or(started),
        started_at: ts(&s.started_at),
        completed_at: ts(&s.completed_at),
        rerun_resumed_at: ts(&s.rerun_resumed_at),
        when_made_public: None,
        method_name: s.method_name.clone(),
        method_description: String::new(),
        project_url: String::new(),
        publication_url: String::new(),
        is_public: s.is_public,
        is_flagged: false,
        ignore_submission: false,
        is_baseline: false,
        is_verified_by_host: false,
        job_name: Some(s.job_name.clone().unwrap_or_default()),
        submission_metadata: None,
        files: SubmissionFiles::default(),
    }
}
