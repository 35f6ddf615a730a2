//! Typed configuration of each subcommand, read once from the environment and validated.
//!
//! The Job templates set the variables (see `docs/reference/in-job.md` and the README); a
//! missing or malformed one stops the subcommand at start with an error naming it, before
//! anything is started or written.

use std::ffi::OsString;
use std::path::PathBuf;
use std::time::Duration;

use lb_domain::job::protocol::{env, parse_pairs, PairId};
use lb_domain::results::{Leaderboard, RouteSubset};

/// A variable is missing or malformed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("`{var}` {problem}")]
pub struct EnvError {
    /// The variable.
    pub var: &'static str,
    /// What is wrong with it.
    pub problem: String,
}

impl EnvError {
    /// Stable name for scripts and logs.
    pub fn name(&self) -> &'static str {
        "InvalidEnvironment"
    }
}

/// The longest duration any variable may ask for (a week): longer is a typo.
const MAX_SECONDS: f64 = 7.0 * 24.0 * 3600.0;

/// Reads variables through a lookup function, so tests need not touch the process env.
pub struct Env<'a> {
    get: &'a dyn Fn(&str) -> Option<OsString>,
}

impl<'a> Env<'a> {
    /// Variables from `get`.
    pub fn new(get: &'a dyn Fn(&str) -> Option<OsString>) -> Env<'a> {
        Env { get }
    }

    fn raw(&self, var: &'static str) -> Result<Option<String>, EnvError> {
        match (self.get)(var) {
            None => Ok(None),
            Some(value) => match value.into_string() {
                Ok(s) if s.trim().is_empty() => Ok(None),
                Ok(s) => Ok(Some(s.trim().to_owned())),
                Err(_) => Err(EnvError {
                    var,
                    problem: "is not valid UTF-8".into(),
                }),
            },
        }
    }

    fn required(&self, var: &'static str) -> Result<String, EnvError> {
        self.raw(var)?.ok_or_else(|| EnvError {
            var,
            problem: "is not set".into(),
        })
    }

    fn parsed<T>(
        &self,
        var: &'static str,
        default: Option<T>,
        parse: impl FnOnce(&str) -> Result<T, String>,
    ) -> Result<T, EnvError> {
        match self.raw(var)? {
            Some(text) => parse(&text).map_err(|why| EnvError {
                var,
                problem: format!("is `{}`: {why}", shorten(&text)),
            }),
            None => default.ok_or_else(|| EnvError {
                var,
                problem: "is not set".into(),
            }),
        }
    }

    fn integer<T: std::str::FromStr>(
        &self,
        var: &'static str,
        default: Option<T>,
        min: u64,
        max: u64,
    ) -> Result<T, EnvError> {
        self.parsed(var, default, |text| {
            let n: u64 = text
                .parse()
                .map_err(|_| "expected a whole number".to_owned())?;
            if n < min || n > max {
                return Err(format!("expected a number from {min} to {max}"));
            }
            text.parse().map_err(|_| "out of range".to_owned())
        })
    }

    fn seconds(
        &self,
        var: &'static str,
        default: f64,
        allow_zero: bool,
    ) -> Result<Duration, EnvError> {
        self.parsed(var, Some(Duration::from_secs_f64(default)), |text| {
            let s: f64 = text
                .parse()
                .map_err(|_| "expected a number of seconds".to_owned())?;
            if !s.is_finite() || !(0.0..=MAX_SECONDS).contains(&s) || (!allow_zero && s == 0.0) {
                return Err(format!(
                    "expected {} seconds up to {MAX_SECONDS}",
                    if allow_zero {
                        "0 or more"
                    } else {
                        "more than 0"
                    }
                ));
            }
            Ok(Duration::from_secs_f64(s))
        })
    }

    fn path(&self, var: &'static str, default: Option<&str>) -> Result<PathBuf, EnvError> {
        self.parsed(var, default.map(PathBuf::from), |text| {
            if text.starts_with('/') {
                Ok(PathBuf::from(text))
            } else {
                Err("expected an absolute path".into())
            }
        })
    }

    fn flag(&self, var: &'static str) -> Result<bool, EnvError> {
        self.parsed(var, Some(false), |text| match text {
            "1" | "true" => Ok(true),
            "0" | "false" => Ok(false),
            _ => Err("expected `1` or nothing".into()),
        })
    }

    fn pairs(&self) -> Result<Vec<PairId>, EnvError> {
        self.parsed(env::PAIRS, None, parse_pairs)
    }
}

fn shorten(text: &str) -> String {
    if text.chars().count() > 80 {
        format!("{}...", text.chars().take(80).collect::<String>())
    } else {
        text.to_owned()
    }
}

/// What every container knows about its Job.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Common {
    /// `LB_SUBMISSION_ID`.
    pub submission_id: u64,
    /// `LB_JOB_INDEX`, 0-based.
    pub job_index: u32,
    /// `LB_LEADERBOARD`.
    pub leaderboard: Leaderboard,
}

impl Common {
    /// Reads the common variables.
    pub fn read(e: &Env<'_>) -> Result<Common, EnvError> {
        Ok(Common {
            submission_id: e.integer(env::SUBMISSION_ID, None, 0, i64::MAX as u64)?,
            job_index: e.integer(env::JOB_INDEX, None, 0, 9999)?,
            leaderboard: e.parsed(env::LEADERBOARD, None, |t| t.parse())?,
        })
    }
}

/// A simulator or agent container.
#[derive(Debug, Clone, PartialEq)]
pub struct PairConfig {
    /// The Job.
    pub common: Common,
    /// `LB_PAIR_ID`.
    pub pair: PairId,
    /// `LB_STATUS_DIR`: the markers.
    pub status_dir: PathBuf,
    /// `LB_AGENT_DIR`: the results files.
    pub agent_dir: PathBuf,
    /// `LB_LOGS_DIR`: this container's logs go under it.
    pub logs_dir: PathBuf,
    /// `CARLA_PORT`.
    pub carla_port: u16,
    /// `CARLA_TM_PORT`.
    pub carla_tm_port: u16,
    /// `ROUTES_SUBSET`.
    pub routes_subset: RouteSubset,
    /// `REPETITIONS`.
    pub repetitions: u32,
    /// `LB_START_WAIT_SECONDS`: how long the agent waits for CARLA's start marker.
    pub start_wait: Duration,
    /// `LB_END_WAIT_SECONDS`: how long a container waits for its partner's marker at the end.
    pub end_wait: Duration,
    /// `LB_CARLA_READY_SECONDS`: how long CARLA may take to accept connections.
    pub carla_ready: Duration,
    /// `LB_POLL_SECONDS`: how often markers and children are looked at.
    pub poll: Duration,
    /// `LB_STOP_GRACE_SECONDS`: SIGTERM to SIGKILL when stopping a child.
    pub stop_grace: Duration,
    /// `LB_HANDOFF_DIR`: where the pair's containers hand each other the GPU and the port
    /// (`crate::handoff`).
    pub handoff_dir: PathBuf,
    /// `LB_GPU_FROM_AGENT`: the simulator renders on the agent's GPU.
    pub gpu_from_agent: bool,
    /// `LB_GPU_PIN_DIR`: where the simulator keeps the GPU it took over, for the pod's later
    /// attempts (a volume only simulators mount).
    pub gpu_pin_dir: PathBuf,
    /// CARLA's variables whose value holds `{gpu_index}` (the simulator fills in the pair's
    /// GPU): read with the rest of the environment, by `simulator::run`.
    pub gpu_templates: Vec<(String, String)>,
}

impl PairConfig {
    /// How far the traffic manager's port is from CARLA's (kept when CARLA's port moves).
    pub fn tm_offset(&self) -> u16 {
        self.carla_tm_port.wrapping_sub(self.carla_port)
    }

    /// Reads the pair's variables.
    pub fn read(e: &Env<'_>) -> Result<PairConfig, EnvError> {
        let common = Common::read(e)?;
        let carla_port: u16 = e.integer(env::CARLA_PORT, None, 1, 65535)?;
        let carla_tm_port: u16 = e.integer(env::CARLA_TM_PORT, None, 1, 65535)?;
        if carla_tm_port == carla_port {
            return Err(EnvError {
                var: env::CARLA_TM_PORT,
                problem: format!("is `{carla_tm_port}`, the same as `CARLA_PORT`"),
            });
        }
        Ok(PairConfig {
            common,
            pair: e.integer(env::PAIR_ID, None, 1, u64::from(u32::MAX))?,
            status_dir: e.path(env::STATUS_DIR, Some("/tmp/status"))?,
            agent_dir: e.path(env::AGENT_DIR, Some("/tmp/agent"))?,
            logs_dir: e.path(env::LOGS_DIR, Some("/tmp/logs"))?,
            carla_port,
            carla_tm_port,
            routes_subset: e.parsed(env::ROUTES_SUBSET, None, |t| t.parse())?,
            repetitions: e.integer(env::REPETITIONS, None, 1, 100)?,
            start_wait: e.seconds(env::START_WAIT_SECONDS, 3600.0, true)?,
            end_wait: e.seconds(env::END_WAIT_SECONDS, 600.0, true)?,
            carla_ready: e.seconds(env::CARLA_READY_SECONDS, 300.0, false)?,
            poll: e.seconds(env::POLL_SECONDS, 1.0, false)?,
            stop_grace: e.seconds(env::STOP_GRACE_SECONDS, 10.0, true)?,
            handoff_dir: e.path(crate::handoff::DIR_VAR, Some(crate::handoff::DEFAULT_DIR))?,
            gpu_from_agent: e.flag(crate::handoff::FROM_AGENT_VAR)?,
            gpu_pin_dir: e.path(
                crate::handoff::PIN_DIR_VAR,
                Some(crate::handoff::DEFAULT_PIN_DIR),
            )?,
            gpu_templates: Vec::new(),
        })
    }
}

/// An agent container: the pair's settings plus the evaluator's.
#[derive(Debug, Clone, PartialEq)]
pub struct AgentConfig {
    /// The pair.
    pub pair: PairConfig,
    /// `LB_MAX_IDLE_SECONDS`: the evaluator is stopped after this long without output.
    pub max_idle: Duration,
    /// `NVIDIA_VISIBLE_DEVICES`: the GPU the device plugin gave this container, handed to the
    /// simulator (`crate::handoff`); unset without a GPU.
    pub visible_devices: Option<String>,
}

impl AgentConfig {
    /// Reads the agent's variables. The evaluator's own (`ROUTES`, ...) are checked for
    /// presence only: the sidecar passes them through untouched.
    pub fn read(e: &Env<'_>) -> Result<AgentConfig, EnvError> {
        let pair = PairConfig::read(e)?;
        e.required("CHALLENGE_TRACK_CODENAME")?;
        e.required("ROUTES")?;
        if pair.common.leaderboard == Leaderboard::V1 {
            e.required("SCENARIOS")?;
        }
        Ok(AgentConfig {
            pair,
            max_idle: e.seconds(env::MAX_IDLE_SECONDS, 800.0, false)?,
            visible_devices: e.raw(crate::handoff::VISIBLE_DEVICES)?,
        })
    }
}

/// How to reach S3: the region, and an endpoint override for emulators.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AwsConfig {
    /// `AWS_REGION`.
    pub region: String,
    /// `AWS_ENDPOINT_URL`, when set (moto): path-style addressing is used with it.
    pub endpoint_url: Option<String>,
    /// `LB_S3_BUCKET`.
    pub bucket: String,
}

impl AwsConfig {
    /// Reads the AWS variables.
    pub fn read(e: &Env<'_>) -> Result<AwsConfig, EnvError> {
        Ok(AwsConfig {
            region: e.parsed("AWS_REGION", None, |t| {
                if t.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-') {
                    Ok(t.to_owned())
                } else {
                    Err("expected a region name such as `us-west-2`".into())
                }
            })?,
            endpoint_url: e.parsed("AWS_ENDPOINT_URL", Some(None), |t| {
                if t.starts_with("http://") || t.starts_with("https://") {
                    Ok(Some(t.to_owned()))
                } else {
                    Err("expected an http:// or https:// URL".into())
                }
            })?,
            bucket: e.parsed(env::S3_BUCKET, None, |t| {
                let ok = (3..=63).contains(&t.len())
                    && t.bytes().all(|b| {
                        b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-' || b == b'.'
                    });
                if ok {
                    Ok(t.to_owned())
                } else {
                    Err("expected an S3 bucket name".into())
                }
            })?,
        })
    }
}

/// The logcopy container.
#[derive(Debug, Clone, PartialEq)]
pub struct LogcopyConfig {
    /// The Job.
    pub common: Common,
    /// S3.
    pub aws: AwsConfig,
    /// `LB_LOGS_ROOT`: the whole logs volume.
    pub logs_root: PathBuf,
    /// `LB_PAIRS`: this Job's pairs.
    pub pairs: Vec<PairId>,
    /// `LB_PERIOD_SECONDS`.
    pub period: Duration,
    /// `LB_MAX_LOG_OBJECTS`: log objects each pair may store over the evaluation.
    pub max_log_objects: u32,
}

impl LogcopyConfig {
    /// Reads logcopy's variables.
    pub fn read(e: &Env<'_>) -> Result<LogcopyConfig, EnvError> {
        Ok(LogcopyConfig {
            common: Common::read(e)?,
            aws: AwsConfig::read(e)?,
            logs_root: e.path(env::LOGS_ROOT, Some("/logs"))?,
            pairs: e.pairs()?,
            period: e.seconds(env::PERIOD_SECONDS, 10.0, false)?,
            max_log_objects: e.integer(
                env::MAX_LOG_OBJECTS,
                Some(lb_domain::job::uploads::LOG_OBJECTS_PER_PAIR),
                1,
                1_000_000,
            )?,
        })
    }
}

/// One official code tree init copies: from the private-contents image into a volume.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CodeCopy {
    /// The variable naming the source, for errors.
    pub var: &'static str,
    /// The source directory.
    pub from: PathBuf,
    /// The volume it goes into.
    pub to: PathBuf,
}

/// The init container.
#[derive(Debug, Clone, PartialEq)]
pub struct InitConfig {
    /// The Job.
    pub common: Common,
    /// S3.
    pub aws: AwsConfig,
    /// `LB_LOGS_ROOT`.
    pub logs_root: PathBuf,
    /// `LB_BIN_DIR`: where the sidecar binary goes.
    pub bin_dir: PathBuf,
    /// `LB_PAIRS`: this Job's pairs (their markers, results and logs).
    pub pairs: Vec<PairId>,
    /// `LB_PARTICIPANT_RESUME`.
    pub participant_resume: bool,
    /// Leaderboard, ScenarioRunner, CARLA PythonAPI.
    pub code: Vec<CodeCopy>,
}

impl InitConfig {
    /// Reads init's variables.
    pub fn read(e: &Env<'_>) -> Result<InitConfig, EnvError> {
        let mut code = Vec::new();
        for (source, dest, default) in [
            (
                env::SOURCE_LEADERBOARD,
                env::LEADERBOARD_ROOT,
                "/workspace/leaderboard",
            ),
            (
                env::SOURCE_SCENARIO_RUNNER,
                env::SCENARIO_RUNNER_ROOT,
                "/workspace/scenario_runner",
            ),
            (env::SOURCE_CARLA_API, env::CARLA_ROOT, "/workspace/CARLA"),
        ] {
            code.push(CodeCopy {
                var: source,
                from: e.path(source, None)?,
                to: e.path(dest, Some(default))?,
            });
        }
        Ok(InitConfig {
            common: Common::read(e)?,
            aws: AwsConfig::read(e)?,
            logs_root: e.path(env::LOGS_ROOT, Some("/logs"))?,
            bin_dir: e.path(env::BIN_DIR, Some("/opt/lb"))?,
            pairs: e.pairs()?,
            participant_resume: e.flag(env::PARTICIPANT_RESUME)?,
            code,
        })
    }
}

/// The process environment as an [`Env`] lookup.
pub fn process_env(var: &str) -> Option<OsString> {
    std::env::var_os(var)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn with(vars: &[(&str, &str)], f: impl FnOnce(&Env<'_>)) {
        let map: HashMap<String, OsString> = vars
            .iter()
            .map(|(k, v)| ((*k).to_owned(), OsString::from(v)))
            .collect();
        let get = move |k: &str| map.get(k).cloned();
        f(&Env::new(&get));
    }

    const PAIR: &[(&str, &str)] = &[
        ("LB_SUBMISSION_ID", "42"),
        ("LB_JOB_INDEX", "0"),
        ("LB_LEADERBOARD", "2.0"),
        ("LB_PAIR_ID", "3"),
        ("CARLA_PORT", "2000"),
        ("CARLA_TM_PORT", "2010"),
        ("ROUTES_SUBSET", "10-14"),
        ("REPETITIONS", "1"),
    ];

    #[test]
    fn a_pair_config_takes_the_contract_defaults() {
        with(PAIR, |e| {
            let c = PairConfig::read(e).unwrap();
            assert_eq!(c.pair, 3);
            assert_eq!(c.status_dir, PathBuf::from("/tmp/status"));
            assert_eq!(c.agent_dir, PathBuf::from("/tmp/agent"));
            assert_eq!(c.logs_dir, PathBuf::from("/tmp/logs"));
            assert_eq!(c.start_wait, Duration::from_secs(3600));
            assert_eq!(c.end_wait, Duration::from_secs(600));
            assert_eq!(c.carla_ready, Duration::from_secs(300));
            assert_eq!(c.poll, Duration::from_secs(1));
            assert_eq!(c.routes_subset.to_string(), "10-14");
        });
    }

    #[test]
    fn every_bad_variable_is_named_in_the_error() {
        for (var, value) in [
            ("LB_SUBMISSION_ID", "abc"),
            ("LB_JOB_INDEX", "-1"),
            ("LB_LEADERBOARD", "3.0"),
            ("LB_PAIR_ID", "0"),
            ("CARLA_PORT", "70000"),
            ("CARLA_TM_PORT", "2000"),
            ("ROUTES_SUBSET", "5-1"),
            ("REPETITIONS", "0"),
            ("LB_POLL_SECONDS", "0"),
            ("LB_END_WAIT_SECONDS", "NaN"),
            ("LB_STATUS_DIR", "relative/dir"),
        ] {
            let mut vars: Vec<(&str, &str)> =
                PAIR.iter().filter(|(k, _)| *k != var).copied().collect();
            vars.push((var, value));
            with(&vars, |e| {
                let err = PairConfig::read(e).unwrap_err();
                assert_eq!(err.var, var, "{err}");
                assert_eq!(err.name(), "InvalidEnvironment");
                assert!(err.to_string().contains(var), "{err}");
            });
        }
    }

    #[test]
    fn a_missing_variable_is_reported_as_not_set() {
        let vars: Vec<_> = PAIR
            .iter()
            .filter(|(k, _)| *k != "LB_PAIR_ID")
            .copied()
            .collect();
        with(&vars, |e| {
            assert_eq!(
                PairConfig::read(e).unwrap_err().to_string(),
                "`LB_PAIR_ID` is not set"
            );
        });
    }

    #[test]
    fn fractional_seconds_are_accepted_for_timers() {
        let mut vars = PAIR.to_vec();
        vars.push(("LB_POLL_SECONDS", "0.2"));
        vars.push(("CHALLENGE_TRACK_CODENAME", "SENSORS"));
        vars.push(("ROUTES", "/r.xml"));
        vars.push(("LB_MAX_IDLE_SECONDS", "2.5"));
        with(&vars, |e| {
            let c = AgentConfig::read(e).unwrap();
            assert_eq!(c.pair.poll, Duration::from_millis(200));
            assert_eq!(c.max_idle, Duration::from_millis(2500));
        });
    }

    #[test]
    fn leaderboard_1_agents_need_scenarios() {
        let mut vars: Vec<_> = PAIR
            .iter()
            .filter(|(k, _)| *k != "LB_LEADERBOARD")
            .copied()
            .collect();
        vars.extend([
            ("LB_LEADERBOARD", "1.0"),
            ("CHALLENGE_TRACK_CODENAME", "SENSORS"),
            ("ROUTES", "/r.xml"),
        ]);
        with(&vars, |e| {
            assert_eq!(AgentConfig::read(e).unwrap_err().var, "SCENARIOS");
        });
    }

    #[test]
    fn logcopy_reads_pairs_and_bucket() {
        let vars = [
            ("LB_SUBMISSION_ID", "42"),
            ("LB_JOB_INDEX", "1"),
            ("LB_LEADERBOARD", "2.0"),
            ("LB_PAIRS", "5,6,7,8"),
            ("LB_S3_BUCKET", "leaderboard-20-submissions"),
            ("AWS_REGION", "us-west-2"),
        ];
        with(&vars, |e| {
            let c = LogcopyConfig::read(e).unwrap();
            assert_eq!(c.pairs, vec![5, 6, 7, 8]);
            assert_eq!(c.period, Duration::from_secs(10));
            assert_eq!(c.logs_root, PathBuf::from("/logs"));
            assert_eq!(c.aws.endpoint_url, None);
        });
        let mut bad = vars.to_vec();
        bad[4] = ("LB_S3_BUCKET", "Bad_Bucket");
        with(&bad, |e| {
            assert_eq!(LogcopyConfig::read(e).unwrap_err().var, "LB_S3_BUCKET");
        });
    }

    #[test]
    fn init_needs_the_three_sources_and_defaults_the_volumes() {
        let vars = [
            ("LB_SUBMISSION_ID", "42"),
            ("LB_JOB_INDEX", "0"),
            ("LB_LEADERBOARD", "1.0"),
            ("LB_PAIRS", "1"),
            ("LB_S3_BUCKET", "bucket"),
            ("AWS_REGION", "us-east-1"),
            ("LB_SOURCE_LEADERBOARD", "/src/leaderboard"),
            ("LB_SOURCE_SCENARIO_RUNNER", "/src/scenario_runner"),
            ("LB_SOURCE_CARLA_API", "/src/carla"),
            ("LB_PARTICIPANT_RESUME", "1"),
        ];
        with(&vars, |e| {
            let c = InitConfig::read(e).unwrap();
            assert!(c.participant_resume);
            assert_eq!(c.bin_dir, PathBuf::from("/opt/lb"));
            assert_eq!(c.code[2].to, PathBuf::from("/workspace/CARLA"));
            assert_eq!(c.code[0].from, PathBuf::from("/src/leaderboard"));
        });
        with(&vars[..8], |e| {
            assert_eq!(InitConfig::read(e).unwrap_err().var, "LB_SOURCE_CARLA_API");
        });
    }
}
