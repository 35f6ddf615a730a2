//! The operator's configuration (the `config` secret in Secrets Manager), typed and checked once.
//!
//! The layout is documented in the README ("Configuration"). Unknown keys are refused so a
//! typo cannot silently fall back to a default; every problem names its JSON path.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::cluster::resources::{self, PairShare};
use crate::results::py::Num;

use crate::results::Leaderboard;

/// The whole configuration.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Settings {
    /// Where EvalAI is and how we authenticate (the token itself is a separate secret).
    pub evalai: EvalAiSettings,
    /// EvalAI phase id -> leaderboard and track.
    pub phases: BTreeMap<u64, PhaseSettings>,
    /// Per leaderboard (`"1.0"`, `"2.0"`): cluster, storage, images, tracks.
    pub leaderboards: BTreeMap<Leaderboard, LeaderboardSettings>,
    /// Dollars per instance-hour by EC2 instance type, on-demand and Spot: what a
    /// submission's GPU-seconds are priced at (`lb_domain::capacity::cost`). Empty: no estimate.
    #[serde(default)]
    pub prices: BTreeMap<String, crate::capacity::cost::InstancePrice>,
}

/// EvalAI endpoint settings.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EvalAiSettings {
    /// Base URL, e.g. `https://eval.ai`.
    pub api_server: String,
    /// `Bearer` (JWT from the profile page, the default) or `Token` (legacy key).
    #[serde(default)]
    pub auth_scheme: AuthScheme,
    /// The host token's limit (EvalAI's `UserRateThrottle`: 60 a minute, reference section 1),
    /// shared by every function of every submission in flight (`lb_evalai::budget`).
    #[serde(default = "default_requests_per_minute")]
    pub requests_per_minute: u32,
}

/// How the host token goes in `Authorization` (EvalAI accepts both, each for its own kind);
/// any other word is refused when the settings are read.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
pub enum AuthScheme {
    /// `Bearer <jwt>`: the profile page's refresh token.
    #[default]
    Bearer,
    /// `Token <key>`: the legacy DRF token.
    Token,
}

fn default_requests_per_minute() -> u32 {
    60
}

/// What a phase evaluates.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhaseSettings {
    /// `"1.0"` or `"2.0"`.
    pub leaderboard: Leaderboard,
    /// Track codename, e.g. `SENSORS`, `MAP`, `SENSORS_QUALIFIER`.
    pub track: String,
}

/// One leaderboard's deployment.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LeaderboardSettings {
    /// EKS cluster name.
    pub cluster: String,
    /// Namespace of the Jobs.
    #[serde(default = "default_namespace")]
    pub namespace: String,
    /// Results bucket.
    pub bucket: String,
    /// DynamoDB submissions table.
    pub submissions_table: String,
    /// DynamoDB qualifier table.
    pub qualifier_table: String,
    /// Container images.
    pub images: Images,
    /// The instance type whose share of a node each pair gets (`pair_resources` by default)
    /// and whose GPU model the Jobs ask for. Pairs run on any node of that GPU model
    /// (`infra/cluster.yaml`'s node groups), never on one instance type name.
    pub instance_type: String,
    /// The GPU model the Jobs select nodes by (`lb_domain::cluster::resources::GPU_MODEL_LABEL`); by
    /// default the instance type's (required for a type `lb_domain::cluster::resources` does not know).
    #[serde(default)]
    pub gpu_model: Option<String>,
    /// Which capacity the pairs may run on: `on-demand`, `spot`, or `spot-then-on-demand` (the
    /// default: the cluster autoscaler adds Spot nodes first, on-demand ones when it cannot).
    /// `on-demand` pins the final days of a challenge to capacity that is never reclaimed.
    #[serde(default)]
    pub capacity: Capacity,
    /// GPUs per node: the number of simulator-agent pairs one Job holds.
    pub gpus_per_node: u32,
    /// Per track codename.
    pub tracks: BTreeMap<String, TrackSettings>,
    /// Qualifier gating.
    #[serde(default)]
    pub qualifier: QualifierSettings,
    /// IAM role the Jobs' init and logcopy containers assume (IRSA) for the bucket; empty
    /// where credentials come otherwise (local mode).
    #[serde(default)]
    pub job_role_arn: String,
    /// How long the cluster's API may stay unreachable before a run is failed for it (hours).
    /// Shorter outages skip Monitor rounds, as an unreachable S3 or EvalAI does: the Jobs run
    /// on without the API, and their own deadline is the last safety net.
    #[serde(default = "default_outage_hours")]
    pub max_cluster_outage_hours: u64,
    /// How long a submission may wait for capacity (its pods `Insufficient nvidia.com/gpu`)
    /// before it is failed with that reason, hours. Waiting is never a failure before.
    #[serde(default = "default_queue_hours")]
    pub max_queue_hours: u64,
    /// How many evaluations one team may hold at once (admitted or running); its further
    /// submissions wait their turn without holding back other teams' (`crate::capacity::queue`).
    #[serde(default = "default_team_limit")]
    pub team_limit: u32,
    /// CPU, memory and `/dev/shm` of each simulator-agent pair; by default derived from
    /// `instance_type` (required for a type `lb_domain::cluster::resources` does not know).
    #[serde(default)]
    pub pair_resources: Option<PairShare>,
    /// The least interval between two partial updates of one submission on EvalAI, seconds
    /// (changes meanwhile are sent together at its end).
    #[serde(default = "default_partial_update_seconds")]
    pub partial_update_seconds: u64,
    /// How long after its pair's results write a pod on a drained node is still moved, seconds
    /// (`crate::capacity::consolidation`): the most of a route a move may run again.
    #[serde(default = "default_move_window_seconds")]
    pub move_window_seconds: u64,
    /// Log objects each pair may store over an evaluation besides the protocol's own files;
    /// the rest are refused and counted in the record (`crate::job::uploads`).
    #[serde(default = "default_log_objects")]
    pub max_log_objects_per_pair: u32,
}

/// Which EC2 capacity a leaderboard's pairs run on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Capacity {
    /// On-demand nodes only.
    OnDemand,
    /// Spot nodes only (reclaimed nodes cost a route, never a retry).
    Spot,
    /// Whatever the cluster autoscaler adds: Spot first (its priority expander), then
    /// on-demand.
    #[default]
    SpotThenOnDemand,
}

impl Capacity {
    /// The label EKS managed node groups put on their nodes with the capacity type.
    pub const LABEL: &'static str = "eks.amazonaws.com/capacityType";

    /// The GPU node groups of `cluster` its pairs may run on, as `infra/cluster.yaml` names
    /// them: what the autoscaler may still add nodes to.
    pub fn node_groups(self, cluster: &str) -> Vec<String> {
        let on_demand = format!("{cluster}-gpu-on-demand");
        let spot = format!("{cluster}-gpu-spot");
        match self {
            Capacity::OnDemand => vec![on_demand],
            Capacity::Spot => vec![spot],
            Capacity::SpotThenOnDemand => vec![spot, on_demand],
        }
    }

    /// The value of [`Capacity::LABEL`] the pairs must have, when pinned.
    pub fn node_label(self) -> Option<&'static str> {
        match self {
            Capacity::OnDemand => Some("ON_DEMAND"),
            Capacity::Spot => Some("SPOT"),
            Capacity::SpotThenOnDemand => None,
        }
    }
}

impl LeaderboardSettings {
    /// The GPU model the Jobs ask for: the operator's, else the instance type's.
    pub fn gpu_model(&self) -> Result<String, (&'static str, String)> {
        match (&self.gpu_model, resources::gpu_model(&self.instance_type)) {
            (Some(model), _) => Ok(model.clone()),
            (None, Some(model)) => Ok(model.to_owned()),
            (None, None) => Err((
                "gpu_model",
                format!(
                    "`{}` is not a GPU instance type whose GPU model the defaults know: set `gpu_model`",
                    self.instance_type
                ),
            )),
        }
    }

    /// The node labels the pairs require: the GPU model, and the capacity type when pinned.
    pub fn node_selector(&self) -> Result<BTreeMap<String, String>, (&'static str, String)> {
        let mut selector =
            BTreeMap::from([(resources::GPU_MODEL_LABEL.to_owned(), self.gpu_model()?)]);
        if let Some(capacity) = self.capacity.node_label() {
            selector.insert(Capacity::LABEL.to_owned(), capacity.to_owned());
        }
        Ok(selector)
    }

    /// What each pair gets: the operator's `pair_resources`, checked against the node, or
    /// the instance type's default share.
    pub fn pair_share(&self) -> Result<PairShare, (&'static str, String)> {
        let node = resources::capacity(&self.instance_type);
        if let Some(node) = node {
            if self.gpus_per_node > node.gpus {
                return Err((
                    "gpus_per_node",
                    format!("{} has {} GPU(s)", self.instance_type, node.gpus),
                ));
            }
        }
        let share = match (self.pair_resources, node) {
            (Some(share), _) => share,
            (None, Some(node)) => PairShare::derive(node, self.gpus_per_node),
            (None, None) => {
                return Err((
                    "instance_type",
                    format!(
                        "`{}` is not a GPU instance type the defaults know: set `pair_resources`",
                        self.instance_type
                    ),
                ))
            }
        };
        share
            .check(self.gpus_per_node, node)
            .map_err(|e| ("pair_resources", e))?;
        Ok(share)
    }
}

fn default_namespace() -> String {
    "default".into()
}

fn default_outage_hours() -> u64 {
    6
}

fn default_queue_hours() -> u64 {
    24
}

fn default_team_limit() -> u32 {
    2
}

/// The default least interval between two partial updates of one submission on EvalAI: a
/// route's record reaches its participant within 20 s at most, 10 s in the median. Safe with
/// many submissions in flight because every update takes from the shared EvalAI budget
/// (`lb_evalai::budget`), which skips a routine update rather than exceed the host token's
/// limit.
pub const PARTIAL_UPDATE_INTERVAL: std::time::Duration = std::time::Duration::from_secs(20);

fn default_log_objects() -> u32 {
    crate::job::uploads::LOG_OBJECTS_PER_PAIR
}

fn default_partial_update_seconds() -> u64 {
    PARTIAL_UPDATE_INTERVAL.as_secs()
}

fn default_move_window_seconds() -> u64 {
    crate::capacity::consolidation::MOVE_WINDOW_SECONDS
}

/// Images of the Job containers (the participant's comes with the submission).
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Images {
    /// CARLA server image.
    pub carla: String,
    /// Init/logcopy image: official Leaderboard code, routes, the sidecar.
    pub private_contents: String,
}

/// One track.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrackSettings {
    /// Routes of the track's routes file.
    pub routes: u32,
    /// Default simulator-agent pairs (a per-submission override in DynamoDB wins).
    pub workers: u32,
    /// This track is a qualifier (its result gates the main track).
    #[serde(default)]
    pub qualifier: bool,
    /// Each route's length in metres, by route number, from the organisers' routes file
    /// (empty: none given). The recordings' audit asks each scoring route for at least the
    /// time its completed part takes at a top speed, whatever time its record claims
    /// (`lb_domain::run::audit`).
    #[serde(default)]
    pub route_lengths: Vec<u32>,
}

/// Qualifier gating: which qualifier track opens which track, and the pass marks.
#[derive(Debug, Clone, PartialEq, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct QualifierSettings {
    /// Off: every team may run every track.
    #[serde(default)]
    pub enabled: bool,
    /// Main track codename -> the qualifier track a team must have passed.
    #[serde(default)]
    pub tracks: BTreeMap<String, String>,
    /// Metric attribute (e.g. `driving_score`) -> minimum value to pass.
    #[serde(default)]
    pub thresholds: BTreeMap<String, f64>,
}

impl QualifierSettings {
    /// The main tracks a pass of qualifier track `qualifier` admits to (the original's
    /// qualifier -> target map, read backwards from ours).
    pub fn targets_of(&self, qualifier: &str) -> Vec<&str> {
        self.tracks
            .iter()
            .filter(|(_, q)| q.as_str() == qualifier)
            .map(|(target, _)| target.as_str())
            .collect()
    }

    /// Whether `metrics` ((attribute, EvalAI value) pairs) pass every threshold, as the
    /// original judges it (every metric **strictly greater** than its threshold; a missing
    /// metric fails), and the text the original puts in front of the participant's stdout.
    pub fn verdict(&self, target_track: &str, metrics: &[(&str, Num)]) -> (bool, String) {
        let mut passed = true;
        let mut lines = String::new();
        for (attribute, threshold) in &self.thresholds {
            let value = metrics
                .iter()
                .find(|(a, _)| a == attribute)
                .map(|(_, v)| *v);
            passed &= value.is_some_and(|v| v.as_f64() > *threshold);
            let shown = value.map_or_else(|| "-".to_string(), Num::py_str);
            lines.push_str(&format!(
                "- {}: {shown} / {}\n",
                capitalised(attribute),
                Num::Float(*threshold).py_str()
            ));
        }
        let head = if passed {
            format!("CONGRATULATIONS! You have qualified for the {target_track} track:")
        } else {
            format!(
                "Unfortunately, you haven't scored high enough to qualify for the {target_track} track:"
            )
        };
        (
            passed,
            format!("{head}\n\nFind below the relevant qualifying scores:\n{lines}\n"),
        )
    }
}

/// `driving_score` -> `Driving score`, as Python's `.replace('_', ' ').capitalize()`.
fn capitalised(attribute: &str) -> String {
    let spaced = attribute.replace('_', " ").to_lowercase();
    let mut chars = spaced.chars();
    chars
        .next()
        .map(|c| c.to_uppercase().chain(chars).collect())
        .unwrap_or_default()
}

/// A setting's JSON path and what is wrong with it.
type Problem = (String, String);

impl EvalAiSettings {
    fn check(&self) -> Result<(), Problem> {
        let invalid = |field: &str, problem: &str| Err((format!("evalai.{field}"), problem.into()));
        let api = &self.api_server;
        if !(api.starts_with("https://") || api.starts_with("http://")) {
            return invalid("api_server", "must be an http(s) URL");
        }
        if !(14..=6000).contains(&self.requests_per_minute) {
            return invalid(
                "requests_per_minute",
                "must be between 14 and 6000 (EvalAI's own limit is 60)",
            );
        }
        Ok(())
    }
}

impl LeaderboardSettings {
    /// Checks leaderboard `name`'s settings (its key parsed as a leaderboard): the names it
    /// needs, the bounds of its numbers, its pairs' share of a node, its tracks and its
    /// qualifier.
    fn check(&self, name: &str) -> Result<(), Problem> {
        let invalid = |field: &str, problem: &str| {
            Err((format!("leaderboards.{name}.{field}"), problem.to_string()))
        };
        for (field, value) in [
            ("cluster", &self.cluster),
            ("namespace", &self.namespace),
            ("bucket", &self.bucket),
            ("submissions_table", &self.submissions_table),
            ("qualifier_table", &self.qualifier_table),
            ("images.carla", &self.images.carla),
            ("images.private_contents", &self.images.private_contents),
            ("instance_type", &self.instance_type),
        ] {
            if value.trim().is_empty() {
                return invalid(field, "must not be empty");
            }
        }
        for (field, value, range, problem) in [
            (
                "max_queue_hours",
                self.max_queue_hours,
                1..=336,
                "must be between 1 and 336 (two weeks)",
            ),
            (
                "team_limit",
                u64::from(self.team_limit),
                1..=100,
                "must be between 1 and 100",
            ),
            (
                "partial_update_seconds",
                self.partial_update_seconds,
                1..=3600,
                "must be between 1 and 3600",
            ),
            (
                "move_window_seconds",
                self.move_window_seconds,
                1..=3600,
                "must be between 1 and 3600",
            ),
            (
                "gpus_per_node",
                u64::from(self.gpus_per_node),
                1..=16,
                "must be between 1 and 16",
            ),
            (
                "max_log_objects_per_pair",
                u64::from(self.max_log_objects_per_pair),
                1..=100_000,
                "must be between 1 and 100000",
            ),
        ] {
            if !range.contains(&value) {
                return invalid(field, problem);
            }
        }
        if let Err((field, problem)) = self.pair_share() {
            return invalid(field, &problem);
        }
        if let Err((field, problem)) = self.check_gpu_model() {
            return invalid(field, &problem);
        }
        if let Err((field, problem)) = self.check_tracks() {
            return invalid(&field, &problem);
        }
        self.check_qualifier()
            .map_err(|(field, problem)| (format!("leaderboards.{name}.{field}"), problem))
    }

    /// Each track has routes and workers, and the organisers' route lengths when given are
    /// one per route.
    fn check_tracks(&self) -> Result<(), (String, String)> {
        let empty = |t: &TrackSettings| t.routes == 0 || t.workers == 0;
        if let Some((track, _)) = self.tracks.iter().find(|(_, t)| empty(t)) {
            let problem = "routes and workers must be at least 1";
            return Err((format!("tracks.{track}"), problem.into()));
        }
        let lengths = |t: &TrackSettings| {
            let given = t.route_lengths.len();
            given != 0 && (given != t.routes as usize || t.route_lengths.contains(&0))
        };
        match self.tracks.iter().find(|(_, t)| lengths(t)) {
            Some((track, t)) => Err((
                format!("tracks.{track}.route_lengths"),
                format!(
                    "one length in metres above 0 per route: {} given for {} routes",
                    t.route_lengths.len(),
                    t.routes
                ),
            )),
            None => Ok(()),
        }
    }

    /// A GPU model the Jobs can select by: the operator's, a label value, or the instance
    /// type's.
    fn check_gpu_model(&self) -> Result<(), (&'static str, String)> {
        self.gpu_model()?;
        match &self.gpu_model {
            Some(model) if model.is_empty() || !crate::job::plan::is_label_value(model) => Err((
                "gpu_model",
                "must be a non-empty Kubernetes label value".into(),
            )),
            _ => Ok(()),
        }
    }

    /// The qualifier's tracks name qualifier tracks, and its thresholds are finite and metrics.
    fn check_qualifier(&self) -> Result<(), Problem> {
        for (main, qualifier) in &self.qualifier.tracks {
            if !self.tracks.get(qualifier).is_some_and(|t| t.qualifier) {
                let field = format!("qualifier.tracks.{main}");
                return Err((field, "must name a track marked `qualifier: true`".into()));
            }
        }
        for (metric, min) in &self.qualifier.thresholds {
            let field = format!("qualifier.thresholds.{metric}");
            if !min.is_finite() {
                return Err((field, "must be finite".into()));
            }
            if !crate::results::METRICS
                .iter()
                .any(|m| m.attribute == metric)
            {
                return Err((field, "is not a metric".into()));
            }
        }
        Ok(())
    }
}

/// Why the configuration is unusable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SettingsError {
    /// Not the documented layout.
    #[error("invalid configuration at `{path}`: {problem}")]
    Invalid {
        /// JSON path of the problem.
        path: String,
        /// What is wrong.
        problem: String,
    },
    /// The phase is not configured (the message is for another challenge, or config lags).
    #[error("phase `{0}` is not configured")]
    UnknownPhase(u64),
}

crate::error_names!(SettingsError {
    Invalid => "InvalidSettings";
    UnknownPhase => "UnknownPhase";
});

/// What a phase resolves to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Target<'a> {
    /// Which leaderboard.
    pub leaderboard: Leaderboard,
    /// Track codename.
    pub track: &'a str,
    /// The leaderboard's deployment.
    pub deployment: &'a LeaderboardSettings,
    /// The track's settings.
    pub track_settings: &'a TrackSettings,
}

impl Target<'_> {
    /// The qualifier track this team must have passed first, if gating applies.
    pub fn required_qualifier(&self) -> Option<&str> {
        let q = &self.deployment.qualifier;
        if !q.enabled || self.track_settings.qualifier {
            return None;
        }
        q.tracks.get(self.track).map(String::as_str)
    }
}

/// A price is a GPU's share of its node's: the instance type must have a known GPU count, and
/// both prices must be finite and not negative.
fn check_price(
    instance_type: &str,
    price: &crate::capacity::cost::InstancePrice,
) -> Result<(), (String, String)> {
    let path = |field: &str| format!("prices.{instance_type}{field}");
    if resources::capacity(instance_type).is_none_or(|c| c.gpus == 0) {
        return Err((
            path(""),
            "is not a GPU instance type this version knows (crates/domain/src/cluster/resources.rs)".into(),
        ));
    }
    for (field, value) in [(".on_demand", price.on_demand), (".spot", price.spot)] {
        if !value.is_finite() || value < 0.0 {
            return Err((
                path(field),
                format!("must be dollars per hour, not {value}"),
            ));
        }
    }
    Ok(())
}

impl Settings {
    /// Parses and checks the secret's JSON text.
    pub fn from_json(text: &str) -> Result<Self, SettingsError> {
        let de = &mut serde_json::Deserializer::from_str(text);
        let settings: Settings =
            serde_path_to_error::deserialize(de).map_err(|e| SettingsError::Invalid {
                path: e.path().to_string(),
                problem: e.inner().to_string(),
            })?;
        settings.check()?;
        Ok(settings)
    }

    fn check(&self) -> Result<(), SettingsError> {
        let invalid = |(path, problem): (String, String)| SettingsError::Invalid { path, problem };
        self.evalai.check().map_err(invalid)?;
        for (name, lb) in &self.leaderboards {
            lb.check(name.as_str()).map_err(invalid)?;
        }
        for (instance_type, price) in &self.prices {
            check_price(instance_type, price).map_err(invalid)?;
        }
        for (phase, p) in &self.phases {
            let Some(lb) = self.leaderboards.get(&p.leaderboard) else {
                let path = format!("phases.{phase}.leaderboard");
                return Err(invalid((path, "names no configured leaderboard".into())));
            };
            if !lb.tracks.contains_key(&p.track) {
                let path = format!("phases.{phase}.track");
                return Err(invalid((path, "names no track of its leaderboard".into())));
            }
        }
        Ok(())
    }

    /// The leaderboard and track of an EvalAI phase.
    pub fn target(&self, phase_id: u64) -> Result<Target<'_>, SettingsError> {
        let phase = self
            .phases
            .get(&phase_id)
            .ok_or(SettingsError::UnknownPhase(phase_id))?;
        // Both lookups were checked at load.
        let deployment = &self.leaderboards[&phase.leaderboard];
        Ok(Target {
            leaderboard: phase.leaderboard,
            track: &phase.track,
            deployment,
            track_settings: &deployment.tracks[&phase.track],
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const EXAMPLE: &str = r#"{
      "evalai": {"api_server": "https://eval.ai"},
      "phases": {"1234": {"leaderboard": "2.0", "track": "SENSORS"},
                 "1235": {"leaderboard": "2.0", "track": "SENSORS_QUALIFIER"}},
      "leaderboards": {"2.0": {
        "cluster": "leaderboard-20", "bucket": "lb20-results",
        "submissions_table": "lb20-submissions", "qualifier_table": "lb20-qualifier",
        "images": {"carla": "carlasim/carla:0.9.15", "private_contents": "123.dkr.ecr.us-west-2.amazonaws.com/private:2.0"},
        "instance_type": "g5.12xlarge", "gpus_per_node": 4,
        "tracks": {"SENSORS": {"routes": 20, "workers": 4},
                   "SENSORS_QUALIFIER": {"routes": 2, "workers": 1, "qualifier": true}},
        "qualifier": {"enabled": true, "tracks": {"SENSORS": "SENSORS_QUALIFIER"},
                      "thresholds": {"driving_score": 10.0}}
      }}
    }"#;

    #[test]
    fn the_documented_example_resolves_phases_to_tracks() {
        let settings = Settings::from_json(EXAMPLE).unwrap();
        let target = settings.target(1234).unwrap();
        assert_eq!(target.leaderboard, Leaderboard::V2);
        assert_eq!(target.track_settings.workers, 4);
        assert_eq!(target.deployment.namespace, "default");
        assert_eq!(target.required_qualifier(), Some("SENSORS_QUALIFIER"));
        assert_eq!(settings.target(1235).unwrap().required_qualifier(), None);
        assert_eq!(settings.target(9).unwrap_err().name(), "UnknownPhase");
    }

    #[test]
    fn route_lengths_are_optional_and_one_per_route_when_given() {
        let settings = Settings::from_json(EXAMPLE).unwrap();
        assert!(settings
            .target(1235)
            .unwrap()
            .track_settings
            .route_lengths
            .is_empty());
        let two = r#""routes": 2, "workers": 1, "#;
        let given = EXAMPLE.replacen(two, &format!(r#"{two}"route_lengths": [1500, 820], "#), 1);
        let settings = Settings::from_json(&given).unwrap();
        let lengths = &settings.target(1235).unwrap().track_settings.route_lengths;
        assert_eq!(lengths, &[1500, 820]);
        for wrong in ["[1500]", "[1500, 0]", "[1, 2, 3]"] {
            let json = EXAMPLE.replacen(two, &format!(r#"{two}"route_lengths": {wrong}, "#), 1);
            let err = Settings::from_json(&json).unwrap_err().to_string();
            assert!(
                err.contains("tracks.SENSORS_QUALIFIER.route_lengths"),
                "{wrong}: {err}"
            );
            assert!(err.contains("for 2 routes"), "{wrong}: {err}");
        }
    }

    #[test]
    fn the_auth_scheme_is_bearer_or_token_and_nothing_else_falls_back() {
        let settings = Settings::from_json(EXAMPLE).unwrap();
        assert_eq!(settings.evalai.auth_scheme, AuthScheme::Bearer);
        let token = EXAMPLE.replacen(
            r#""api_server""#,
            r#""auth_scheme": "Token", "api_server""#,
            1,
        );
        assert_eq!(
            Settings::from_json(&token).unwrap().evalai.auth_scheme,
            AuthScheme::Token
        );
        let typo = EXAMPLE.replacen(
            r#""api_server""#,
            r#""auth_scheme": "token", "api_server""#,
            1,
        );
        let err = Settings::from_json(&typo).unwrap_err().to_string();
        assert!(err.contains("evalai.auth_scheme"), "{err}");
        assert!(
            err.contains("`Bearer`, `Token`") || err.contains("Bearer"),
            "{err}"
        );
    }

    #[test]
    fn the_qualifier_verdict_needs_every_metric_strictly_above_its_threshold() {
        let q = Settings::from_json(EXAMPLE).unwrap().leaderboards[&Leaderboard::V2]
            .qualifier
            .clone();
        assert_eq!(q.targets_of("SENSORS_QUALIFIER"), ["SENSORS"]);
        assert_eq!(
            q.verdict("SENSORS", &[("driving_score", Num::Float(12.5))]),
            (
                true,
                "CONGRATULATIONS! You have qualified for the SENSORS track:\n\n\
                 Find below the relevant qualifying scores:\n\
                 - Driving score: 12.5 / 10.0\n\n"
                    .to_string()
            )
        );
        // Equal is not enough, as in the original.
        assert!(
            !q.verdict("SENSORS", &[("driving_score", Num::Float(10.0))])
                .0
        );
        let (passed, text) = q.verdict("SENSORS", &[("driving_score", Num::Int(0))]);
        assert!(!passed);
        assert!(text.starts_with(
            "Unfortunately, you haven't scored high enough to qualify for the SENSORS track:\n"
        ));
        assert!(text.contains("- Driving score: 0 / 10.0\n"), "{text}");
        assert!(q
            .verdict("SENSORS", &[])
            .1
            .contains("- Driving score: - / 10.0\n"));
    }

    #[test]
    fn pair_resources_default_from_the_instance_type_or_come_from_the_operator() {
        let settings = Settings::from_json(EXAMPLE).unwrap();
        let share = settings.leaderboards[&Leaderboard::V2]
            .pair_share()
            .unwrap();
        assert_eq!((share.simulator.cpu, share.agent.memory_gib), (4.0, 24.0));
        let own = EXAMPLE.replace(
            r#""instance_type": "g5.12xlarge", "gpus_per_node": 4,"#,
            r#""instance_type": "x9.large", "gpu_model": "nvidia-x9", "gpus_per_node": 2, "pair_resources": {
                "simulator": {"cpu": 3, "memory_gib": 12},
                "agent": {"cpu": 5.5, "memory_gib": 20}, "shm_gib": 2},"#,
        );
        let share = Settings::from_json(&own).unwrap().leaderboards[&Leaderboard::V2]
            .pair_share()
            .unwrap();
        assert_eq!(share.allotment().agent.cpu_millis, 5500);
        assert_eq!(share.allotment().shm_mib, 2048);
    }

    #[test]
    fn pairs_select_nodes_by_gpu_model_and_pinned_capacity() {
        let settings = Settings::from_json(EXAMPLE).unwrap();
        let board = &settings.leaderboards[&Leaderboard::V2];
        assert_eq!(board.capacity, Capacity::SpotThenOnDemand, "the default");
        assert_eq!(
            board.node_selector().unwrap(),
            BTreeMap::from([(
                resources::GPU_MODEL_LABEL.to_owned(),
                "nvidia-a10g".to_owned()
            )])
        );
        let pinned = EXAMPLE.replace(
            r#""gpus_per_node": 4,"#,
            r#""gpus_per_node": 4, "capacity": "on-demand", "gpu_model": "nvidia-a10g-24gb","#,
        );
        let pinned = Settings::from_json(&pinned).unwrap();
        let selector = pinned.leaderboards[&Leaderboard::V2]
            .node_selector()
            .unwrap();
        assert_eq!(selector[Capacity::LABEL], "ON_DEMAND");
        assert_eq!(selector[resources::GPU_MODEL_LABEL], "nvidia-a10g-24gb");
        let spot = EXAMPLE.replace(
            r#""gpus_per_node": 4,"#,
            r#""gpus_per_node": 4, "capacity": "spot","#,
        );
        let spot = Settings::from_json(&spot).unwrap();
        assert_eq!(
            spot.leaderboards[&Leaderboard::V2].node_selector().unwrap()[Capacity::LABEL],
            "SPOT"
        );
    }

    #[test]
    fn gating_off_requires_no_qualifier() {
        let settings =
            Settings::from_json(&EXAMPLE.replace(r#""enabled": true"#, r#""enabled": false"#))
                .unwrap();
        assert_eq!(settings.target(1234).unwrap().required_qualifier(), None);
    }

    #[test]
    fn each_problem_names_its_path() {
        let cases = [
            (
                EXAMPLE.replace(r#""workers": 4"#, r#""workers": 0"#),
                "leaderboards.2.0.tracks.SENSORS",
            ),
            (
                EXAMPLE.replace(r#""gpus_per_node": 4"#, r#""gpus_per_node": "4""#),
                "leaderboards.2.0.gpus_per_node",
            ),
            (
                EXAMPLE.replace(r#""bucket": "lb20-results""#, r#""bucket": " ""#),
                "leaderboards.2.0.bucket",
            ),
            (
                EXAMPLE.replace(r#""track": "SENSORS"}"#, r#""track": "MAP"}"#),
                "phases.1234.track",
            ),
            (
                EXAMPLE.replace(r#""driving_score": 10.0"#, r#""score": 10.0"#),
                "leaderboards.2.0.qualifier.thresholds.score",
            ),
            (
                EXAMPLE.replace(r#""cluster""#, r#""clustr""#),
                "leaderboards.2.0",
            ),
            (
                EXAMPLE.replace("https://eval.ai", "eval.ai"),
                "evalai.api_server",
            ),
            (
                EXAMPLE.replace(
                    r#""SENSORS": "SENSORS_QUALIFIER""#,
                    r#""SENSORS": "SENSORS""#,
                ),
                "leaderboards.2.0.qualifier.tracks.SENSORS",
            ),
            (
                EXAMPLE.replace("g5.12xlarge", "x9.large"),
                "leaderboards.2.0.instance_type",
            ),
            (
                EXAMPLE.replace("g5.12xlarge", "g5.2xlarge"),
                "leaderboards.2.0.gpus_per_node",
            ),
            (
                EXAMPLE.replace(
                    r#""gpus_per_node": 4,"#,
                    r#""gpus_per_node": 4, "pair_resources": {
                        "simulator": {"cpu": 8, "memory_gib": 16},
                        "agent": {"cpu": 8, "memory_gib": 24}, "shm_gib": 4},"#,
                ),
                "leaderboards.2.0.pair_resources",
            ),
            (
                EXAMPLE.replace(
                    r#""gpus_per_node": 4,"#,
                    r#""gpus_per_node": 4, "capacity": "cheap","#,
                ),
                "leaderboards.2.0.capacity",
            ),
            (
                EXAMPLE.replace(
                    r#""gpus_per_node": 4,"#,
                    r#""gpus_per_node": 4, "gpu_model": "A10G / 24 GB","#,
                ),
                "leaderboards.2.0.gpu_model",
            ),
            (
                EXAMPLE.replace(
                    r#""instance_type": "g5.12xlarge", "gpus_per_node": 4,"#,
                    r#""instance_type": "x9.large", "gpus_per_node": 2, "pair_resources": {
                        "simulator": {"cpu": 3, "memory_gib": 12},
                        "agent": {"cpu": 5.5, "memory_gib": 20}, "shm_gib": 2},"#,
                ),
                "leaderboards.2.0.gpu_model",
            ),
            (
                EXAMPLE.replace(
                    r#""evalai": {"#,
                    r#""prices": {"g5.12xlarge": {"on_demand": 5.672, "spot": -1}}, "evalai": {"#,
                ),
                "prices.g5.12xlarge.spot",
            ),
            (
                EXAMPLE.replace(
                    r#""evalai": {"#,
                    r#""prices": {"m5.large": {"on_demand": 0.096, "spot": 0.04}}, "evalai": {"#,
                ),
                "prices.m5.large",
            ),
        ];
        for (text, path) in cases {
            let err = Settings::from_json(&text).unwrap_err();
            assert!(
                err.to_string().contains(&format!("`{path}")),
                "{path}: {err}"
            );
            assert_eq!(err.name(), "InvalidSettings");
        }
    }
}
