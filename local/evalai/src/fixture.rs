//! The fixture: users, tokens, teams, challenges and submissions the fake starts with.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::statuses::STATUSES;
use crate::timefmt;

/// The embedded default fixture (also shipped as `fixtures/default.json`).
pub const DEFAULT_FIXTURE_JSON: &str = include_str!("../fixtures/default.json");

/// Everything the fake EvalAI knows at start-up. Loaded from JSON; unknown fields are errors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Fixture {
    /// Accounts.
    pub users: Vec<UserFixture>,
    /// Authentication tokens (JWT refresh tokens and legacy keys).
    pub tokens: Vec<TokenFixture>,
    /// Challenge host teams; a team hosts the challenges it lists.
    pub host_teams: Vec<HostTeamFixture>,
    /// Participant teams.
    pub participant_teams: Vec<ParticipantTeamFixture>,
    /// Challenges with their phases and splits.
    pub challenges: Vec<ChallengeFixture>,
    /// Existing submissions.
    #[serde(default)]
    pub submissions: Vec<SubmissionFixture>,
    /// DRF `UserRateThrottle` rate: requests per window per user (EvalAI: 60).
    #[serde(default = "default_throttle")]
    pub throttle_per_minute: u32,
    /// Length of the throttle's sliding window in seconds (EvalAI: 60). Tests may shorten it.
    #[serde(default = "default_window")]
    pub throttle_window_secs: u64,
    /// The largest request body the proxy in front of EvalAI passes (nginx's
    /// `client_max_body_size`); above it: 413 with nginx's HTML page, the view never runs.
    #[serde(default = "default_max_request")]
    pub max_request_bytes: usize,
}

fn default_max_request() -> usize {
    16 * 1024 * 1024
}

fn default_throttle() -> u32 {
    60
}

fn default_window() -> u64 {
    60
}

fn default_true() -> bool {
    true
}

/// An EvalAI account.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UserFixture {
    /// User primary key.
    pub id: u64,
    /// Login name (informational).
    #[serde(default)]
    pub username: String,
    /// Whether the account's e-mail is verified (unverified accounts get 403).
    #[serde(default = "default_true")]
    pub email_verified: bool,
    /// Inactive accounts fail authentication (401).
    #[serde(default = "default_true")]
    pub active: bool,
    /// Django staff flag (`update_submission` and the list endpoint let staff in).
    #[serde(default)]
    pub staff: bool,
}

/// Which authentication class a token belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TokenKind {
    /// simplejwt refresh token, sent as `Authorization: Bearer <value>`.
    Jwt,
    /// Legacy expiring DRF token, sent as `Authorization: Token <value>`.
    Legacy,
}

/// An authentication token.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TokenFixture {
    /// The exact header value after the scheme.
    pub value: String,
    /// JWT or legacy.
    pub kind: TokenKind,
    /// Owner user id.
    pub user: u64,
    /// An expired token is rejected (JWT: `token_not_valid`; legacy: "Token has expired").
    #[serde(default)]
    pub expired: bool,
    /// A blacklisted JWT (the user refreshed it on the profile page). JWT only.
    #[serde(default)]
    pub blacklisted: bool,
}

/// A challenge host team.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HostTeamFixture {
    /// Team primary key.
    pub id: u64,
    /// Team name.
    #[serde(default)]
    pub name: String,
    /// Member user ids.
    pub members: Vec<u64>,
    /// Challenges this team created (hosts).
    pub challenges: Vec<u64>,
}

/// A participant team.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ParticipantTeamFixture {
    /// Team primary key.
    pub id: u64,
    /// `team_name`, returned as `participant_team_name`.
    pub name: String,
    /// Member user ids.
    pub members: Vec<u64>,
    /// Challenges the team joined (challenges of its submissions are added automatically).
    #[serde(default)]
    pub challenges: Vec<u64>,
}

/// A challenge.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChallengeFixture {
    /// Challenge primary key.
    pub id: u64,
    /// Title (informational).
    #[serde(default)]
    pub title: String,
    /// Phases; phase ids are unique across all challenges.
    pub phases: Vec<PhaseFixture>,
}

/// A challenge phase.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhaseFixture {
    /// Phase primary key.
    pub id: u64,
    /// Phase codename (informational).
    #[serde(default)]
    pub codename: String,
    /// `is_partial_submission_evaluation_enabled`: unknown metric keys pass on the partial endpoint.
    #[serde(default)]
    pub partial_evaluation_enabled: bool,
    /// Phase splits, each with its leaderboard labels.
    pub splits: Vec<SplitFixture>,
}

/// A challenge phase split (dataset split + leaderboard).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SplitFixture {
    /// Dataset split codename (`split` in a result).
    pub codename: String,
    /// The leaderboard schema's `labels`, in order.
    pub labels: Vec<String>,
}

/// A submission present at start-up.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SubmissionFixture {
    /// Submission primary key.
    pub id: u64,
    /// Phase id.
    pub challenge_phase: u64,
    /// Participant team id.
    pub participant_team: u64,
    /// Creator user id (must be a member of the team).
    pub created_by: u64,
    /// Lowercase status (default `submitted`).
    #[serde(default = "default_status")]
    pub status: String,
    /// Docker image the participant pushed; served in the `input_file` JSON.
    #[serde(default)]
    pub submitted_image_uri: Option<String>,
    /// ISO-8601 timestamp (default: the server's start time).
    #[serde(default)]
    pub submitted_at: Option<String>,
    /// ISO-8601 timestamp or null.
    #[serde(default)]
    pub started_at: Option<String>,
    /// ISO-8601 timestamp or null.
    #[serde(default)]
    pub completed_at: Option<String>,
    /// ISO-8601 timestamp or null.
    #[serde(default)]
    pub rerun_resumed_at: Option<String>,
    /// Job names recorded so far (default empty list).
    #[serde(default)]
    pub job_name: Option<Vec<String>>,
    /// `method_name`.
    #[serde(default)]
    pub method_name: String,
    /// `is_public`.
    #[serde(default)]
    pub is_public: bool,
}

fn default_status() -> String {
    "submitted".to_owned()
}

/// Why a fixture could not be used.
#[derive(Debug, thiserror::Error)]
pub enum FixtureError {
    /// The file could not be read.
    #[error("cannot read fixture `{path}`: {source}")]
    Read {
        /// The path given.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The JSON does not match the fixture schema.
    #[error("fixture JSON is invalid at `{path}`: {message}")]
    Parse {
        /// JSON path of the offending element (`users[0].id`).
        path: String,
        /// serde's message (line and column included).
        message: String,
    },
    /// The fixture parsed but is inconsistent.
    #[error("fixture is inconsistent: {0}")]
    Invalid(String),
}

impl FixtureError {
    /// Stable PascalCase name of the error kind.
    pub fn name(&self) -> &'static str {
        match self {
            FixtureError::Read { .. } => "FixtureRead",
            FixtureError::Parse { .. } => "FixtureParse",
            FixtureError::Invalid(_) => "FixtureInvalid",
        }
    }
}

impl Default for Fixture {
    /// The embedded default: challenge 1 with phase 1 (Leaderboard 2.0, 15 labels) and
    /// phase 2 (Leaderboard 1.0, 12 labels), submission 1 `submitted` by "Team One", and
    /// tokens for every authentication path (see the crate README).
    fn default() -> Self {
        // NB: covered by a unit test; the embedded file is part of the crate.
        Fixture::from_json(DEFAULT_FIXTURE_JSON).expect("embedded default fixture is valid")
    }
}

impl Fixture {
    /// The embedded default with participant teams 1..=`teams` in challenge 1 (the default's
    /// own first), each of one verified member, for runs of several teams' submissions.
    pub fn with_teams(teams: usize) -> Fixture {
        let mut fixture = Fixture::default();
        let next_user = fixture.users.iter().map(|u| u.id).max().unwrap_or(0);
        for n in (fixture.participant_teams.len() + 1)..=teams {
            let user = next_user + n as u64;
            fixture.users.push(UserFixture {
                id: user,
                username: format!("participant-{n}"),
                email_verified: true,
                active: true,
                staff: false,
            });
            fixture.participant_teams.push(ParticipantTeamFixture {
                id: n as u64,
                name: format!("Team {n}"),
                members: vec![user],
                challenges: vec![1],
            });
        }
        fixture
    }

    /// Reads and validates a fixture file.
    pub fn from_path(path: &Path) -> Result<Fixture, FixtureError> {
        let text = std::fs::read_to_string(path).map_err(|source| FixtureError::Read {
            path: path.to_owned(),
            source,
        })?;
        Fixture::from_json(&text)
    }

    /// Parses and validates fixture JSON.
    pub fn from_json(text: &str) -> Result<Fixture, FixtureError> {
        let de = &mut serde_json::Deserializer::from_str(text);
        let fixture: Fixture =
            serde_path_to_error::deserialize(de).map_err(|e| FixtureError::Parse {
                path: e.path().to_string(),
                message: e.inner().to_string(),
            })?;
        fixture.validate()?;
        Ok(fixture)
    }

    /// The value of the first non-expired, non-blacklisted JWT of a host of `challenge`, if any.
    pub fn host_token(&self, challenge: u64) -> Option<&str> {
        let hosts: BTreeSet<u64> = self
            .host_teams
            .iter()
            .filter(|t| t.challenges.contains(&challenge))
            .flat_map(|t| t.members.iter().copied())
            .collect();
        self.tokens
            .iter()
            .find(|t| {
                t.kind == TokenKind::Jwt && !t.expired && !t.blacklisted && hosts.contains(&t.user)
            })
            .map(|t| t.value.as_str())
    }

    /// Checks cross-references, uniqueness and value ranges.
    pub fn validate(&self) -> Result<(), FixtureError> {
        if self.throttle_per_minute == 0 {
            return invalid("`throttle_per_minute` must be at least 1".to_owned());
        }
        if self.throttle_window_secs == 0 {
            return invalid("`throttle_window_secs` must be at least 1".to_owned());
        }
        let users = self.valid_users()?;
        self.valid_tokens(&users)?;
        let (challenges, phases) = self.valid_challenges()?;
        self.valid_host_teams(&users, &challenges)?;
        let teams = self.valid_participant_teams(&users, &challenges)?;
        self.valid_submissions(&phases, &teams)
    }

    /// The users' ids, each once.
    fn valid_users(&self) -> Result<BTreeSet<u64>, FixtureError> {
        let mut users = BTreeSet::new();
        for u in &self.users {
            if !users.insert(u.id) {
                return invalid(format!("user id `{}` appears twice", u.id));
            }
        }
        Ok(users)
    }

    /// Each token once, well formed, of a known user; only JWTs blacklisted.
    fn valid_tokens(&self, users: &BTreeSet<u64>) -> Result<(), FixtureError> {
        let mut token_values = BTreeSet::new();
        for t in &self.tokens {
            if t.value.is_empty() || t.value.chars().any(|c| c.is_whitespace() || c.is_control()) {
                return invalid(format!(
                    "token of user `{}` must be non-empty without whitespace",
                    t.user
                ));
            }
            if !token_values.insert(t.value.as_str()) {
                return invalid(format!("token `{}` appears twice", t.value));
            }
            if !users.contains(&t.user) {
                return invalid(format!(
                    "token `{}` names unknown user `{}`",
                    t.value, t.user
                ));
            }
            if t.blacklisted && t.kind != TokenKind::Jwt {
                return invalid(format!(
                    "token `{}`: only JWT tokens can be blacklisted",
                    t.value
                ));
            }
        }
        Ok(())
    }

    /// The challenges' ids and each phase's challenge, each once, with well-formed splits.
    fn valid_challenges(&self) -> Result<(BTreeSet<u64>, BTreeMap<u64, u64>), FixtureError> {
        let mut challenges = BTreeSet::new();
        let mut phases: BTreeMap<u64, u64> = BTreeMap::new();
        for c in &self.challenges {
            if !challenges.insert(c.id) {
                return invalid(format!("challenge id `{}` appears twice", c.id));
            }
            for p in &c.phases {
                if phases.insert(p.id, c.id).is_some() {
                    return invalid(format!("phase id `{}` appears twice", p.id));
                }
                let mut codenames = BTreeSet::new();
                for s in &p.splits {
                    if s.codename.is_empty() {
                        return invalid(format!(
                            "phase `{}` has a split with an empty codename",
                            p.id
                        ));
                    }
                    if !codenames.insert(s.codename.as_str()) {
                        return invalid(format!(
                            "phase `{}` has split `{}` twice",
                            p.id, s.codename
                        ));
                    }
                    if s.labels.is_empty() {
                        return invalid(format!(
                            "split `{}` of phase `{}` has no labels",
                            s.codename, p.id
                        ));
                    }
                    let mut labels = BTreeSet::new();
                    for l in &s.labels {
                        if !labels.insert(l.as_str()) {
                            return invalid(format!(
                                "split `{}` of phase `{}` has label `{l}` twice",
                                s.codename, p.id
                            ));
                        }
                    }
                }
            }
        }
        Ok((challenges, phases))
    }

    /// Each host team once, of known users, and each challenge hosted by exactly one.
    fn valid_host_teams(
        &self,
        users: &BTreeSet<u64>,
        challenges: &BTreeSet<u64>,
    ) -> Result<(), FixtureError> {
        let mut host_team_ids = BTreeSet::new();
        let mut hosted: BTreeMap<u64, u64> = BTreeMap::new();
        for t in &self.host_teams {
            if !host_team_ids.insert(t.id) {
                return invalid(format!("host team id `{}` appears twice", t.id));
            }
            for m in &t.members {
                if !users.contains(m) {
                    return invalid(format!("host team `{}` names unknown user `{m}`", t.id));
                }
            }
            for c in &t.challenges {
                if !challenges.contains(c) {
                    return invalid(format!(
                        "host team `{}` names unknown challenge `{c}`",
                        t.id
                    ));
                }
                if let Some(other) = hosted.insert(*c, t.id) {
                    return invalid(format!(
                        "challenge `{c}` is hosted by two teams (`{other}` and `{}`)",
                        t.id
                    ));
                }
            }
        }
        for c in challenges {
            if !hosted.contains_key(c) {
                return invalid(format!("challenge `{c}` has no host team"));
            }
        }
        Ok(())
    }

    /// The participant teams by id, each once, of known users and challenges.
    fn valid_participant_teams(
        &self,
        users: &BTreeSet<u64>,
        challenges: &BTreeSet<u64>,
    ) -> Result<BTreeMap<u64, &ParticipantTeamFixture>, FixtureError> {
        let mut teams: BTreeMap<u64, &ParticipantTeamFixture> = BTreeMap::new();
        for t in &self.participant_teams {
            if teams.insert(t.id, t).is_some() {
                return invalid(format!("participant team id `{}` appears twice", t.id));
            }
            for m in &t.members {
                if !users.contains(m) {
                    return invalid(format!(
                        "participant team `{}` names unknown user `{m}`",
                        t.id
                    ));
                }
            }
            for c in &t.challenges {
                if !challenges.contains(c) {
                    return invalid(format!(
                        "participant team `{}` names unknown challenge `{c}`",
                        t.id
                    ));
                }
            }
        }
        Ok(teams)
    }

    /// Each submission once, of a known phase and team, by a member, with a known status and
    /// ISO-8601 times.
    fn valid_submissions(
        &self,
        phases: &BTreeMap<u64, u64>,
        teams: &BTreeMap<u64, &ParticipantTeamFixture>,
    ) -> Result<(), FixtureError> {
        let mut submissions = BTreeSet::new();
        for s in &self.submissions {
            if s.id == 0 {
                return invalid("submission id `0` is not a valid primary key".to_owned());
            }
            if !submissions.insert(s.id) {
                return invalid(format!("submission id `{}` appears twice", s.id));
            }
            if !phases.contains_key(&s.challenge_phase) {
                return invalid(format!(
                    "submission `{}` names unknown phase `{}`",
                    s.id, s.challenge_phase
                ));
            }
            let Some(team) = teams.get(&s.participant_team) else {
                return invalid(format!(
                    "submission `{}` names unknown participant team `{}`",
                    s.id, s.participant_team
                ));
            };
            if !team.members.contains(&s.created_by) {
                return invalid(format!(
                    "submission `{}`: creator `{}` is not a member of team `{}`",
                    s.id, s.created_by, s.participant_team
                ));
            }
            if !STATUSES.contains(&s.status.as_str()) {
                return invalid(format!(
                    "submission `{}` has status `{}`; expected one of {}",
                    s.id,
                    s.status,
                    STATUSES.join(", ")
                ));
            }
            for (field, value) in [
                ("submitted_at", &s.submitted_at),
                ("started_at", &s.started_at),
                ("completed_at", &s.completed_at),
                ("rerun_resumed_at", &s.rerun_resumed_at),
            ] {
                if let Some(v) = value {
                    if timefmt::parse(v).is_none() {
                        return invalid(format!(
                            "submission `{}`: `{field}` `{v}` is not an ISO-8601 timestamp",
                            s.id
                        ));
                    }
                }
            }
        }
        Ok(())
    }
}

/// A fixture error naming what is wrong.
fn invalid<T>(msg: String) -> Result<T, FixtureError> {
    Err(FixtureError::Invalid(msg))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_default_fixture_is_valid_and_has_the_expected_shape() {
        let f = Fixture::from_json(DEFAULT_FIXTURE_JSON).unwrap();
        assert_eq!(f.host_token(1), Some("host-token"));
        let phase1 = &f.challenges[0].phases[0];
        assert_eq!(phase1.id, 1);
        assert_eq!(phase1.splits[0].codename, "leaderboard");
        assert_eq!(phase1.splits[0].labels.len(), 15);
        assert_eq!(f.challenges[0].phases[1].splits[0].labels.len(), 12);
        assert_eq!(f.submissions[0].status, "submitted");
        assert_eq!(f.throttle_per_minute, 60);
    }
}
