//! Command lines and environment of both fakes, parsed once into typed settings; every error
//! names the argument or variable at fault.
//!
//! `fake-carla` reads `CarlaUE4.sh`'s Unreal-style flags (`-carla-rpc-port=2000`, `-vulkan`,
//! `-ini:...`); `fake-evaluator` reads `leaderboard_evaluator.py`'s argparse options
//! (`--port=2000` or `--port 2000`, unique prefixes, `-a`), with the environment the real
//! evaluator's shell command expands as a fallback.

use std::collections::BTreeMap;
use std::path::PathBuf;

use lb_domain::results::Leaderboard;

use crate::faults::{CarlaFaults, EvaluatorFaults};

/// The most seconds any duration setting may ask for (about four months).
pub const MAX_SECONDS: f64 = 1e7;

/// The most records (routes x repetitions) one fake evaluator runs.
pub const MAX_RECORDS: u64 = 100_000;

/// A snapshot of the environment, read once at start so nothing deeper reads `std::env`.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Env(BTreeMap<String, String>);

impl Env {
    /// The process environment; variables whose name or value is not UTF-8 are left out.
    pub fn from_process() -> Env {
        Env(std::env::vars_os()
            .filter_map(|(k, v)| Some((k.into_string().ok()?, v.into_string().ok()?)))
            .collect())
    }

    /// An environment made of the given pairs (tests, embedding).
    pub fn from_pairs<I, K, V>(pairs: I) -> Env
    where
        I: IntoIterator<Item = (K, V)>,
        K: Into<String>,
        V: Into<String>,
    {
        Env(pairs
            .into_iter()
            .map(|(k, v)| (k.into(), v.into()))
            .collect())
    }

    /// A variable's value, empty or not.
    pub fn get(&self, key: &str) -> Option<&str> {
        self.0.get(key).map(String::as_str)
    }

    /// A variable that is set and not empty: the Job templates export optional variables
    /// as `""`, which means "not set".
    pub fn non_empty(&self, key: &str) -> Option<&str> {
        self.get(key).filter(|v| !v.is_empty())
    }
}

/// A command line or environment that cannot be used. Each variant has a stable
/// [`name`](Self::name).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ArgsError {
    /// An option that takes a value came without one.
    #[error("argument {arg}: expected one argument")]
    MissingValue {
        /// The option, quoted (`` `--port` ``).
        arg: String,
    },
    /// A value of the wrong type.
    #[error("argument {arg}: invalid {kind} value: `{value}`")]
    InvalidValue {
        /// The option, quoted, with the variable it came from if any.
        arg: String,
        /// The expected type (`int`, `float`, ...).
        kind: &'static str,
        /// The value given.
        value: String,
    },
    /// A value of the right type that cannot be used.
    #[error("argument {arg}: {problem}")]
    Invalid {
        /// The option, quoted, with the variable it came from if any.
        arg: String,
        /// What is wrong.
        problem: String,
    },
    /// Options or positionals the program does not take.
    #[error("unrecognized arguments: {args}")]
    Unrecognized {
        /// The arguments, space separated.
        args: String,
    },
    /// Required options that were neither given nor found in the environment.
    #[error("the following arguments are required: {args}")]
    Required {
        /// The options, comma separated.
        args: String,
    },
    /// An abbreviation that fits more than one option.
    #[error("ambiguous option: `{arg}` could match {candidates}")]
    Ambiguous {
        /// The abbreviation.
        arg: String,
        /// The options it fits.
        candidates: String,
    },
    /// A variable of the fakes' own settings that cannot be used.
    #[error("environment variable `{var}`: {problem}")]
    Environment {
        /// The variable.
        var: String,
        /// What is wrong.
        problem: String,
    },
}

impl ArgsError {
    /// The stable PascalCase name of the error.
    pub fn name(&self) -> &'static str {
        match self {
            ArgsError::MissingValue { .. } => "MissingValue",
            ArgsError::InvalidValue { .. } => "InvalidValue",
            ArgsError::Invalid { .. } => "InvalidArgument",
            ArgsError::Unrecognized { .. } => "UnrecognizedArguments",
            ArgsError::Required { .. } => "MissingArguments",
            ArgsError::Ambiguous { .. } => "AmbiguousOption",
            ArgsError::Environment { .. } => "InvalidEnvironment",
        }
    }
}

/// What a command line asks for.
#[derive(Debug, Clone, PartialEq)]
pub enum Parsed<T> {
    /// Run with these settings.
    Run(T),
    /// Print this help text and exit 0.
    Help(String),
}

// ---- shared value parsers ------------------------------------------------------------------

/// Parses a duration in seconds (a float, `0..=MAX_SECONDS`).
pub(crate) fn seconds(value: &str) -> Result<f64, String> {
    let v: f64 = value
        .trim()
        .parse()
        .map_err(|_| format!("`{value}` is not a number of seconds"))?;
    if !v.is_finite() || !(0.0..=MAX_SECONDS).contains(&v) {
        return Err(format!(
            "`{value}` is not a number of seconds between 0 and {MAX_SECONDS:e}"
        ));
    }
    Ok(v)
}

/// Parses an on/off switch the way shell users write one.
pub(crate) fn switch(value: &str) -> Result<bool, String> {
    match value.trim().to_ascii_lowercase().as_str() {
        "1" | "true" | "yes" | "on" => Ok(true),
        "" | "0" | "false" | "no" | "off" => Ok(false),
        _ => Err(format!(
            "`{value}` is not one of 1, true, yes, on, 0, false, no, off"
        )),
    }
}

/// A fake's own variable, parsed by `parse`; unset or empty means `None`.
pub(crate) fn env_value<T>(
    env: &Env,
    var: &str,
    parse: impl FnOnce(&str) -> Result<T, String>,
) -> Result<Option<T>, ArgsError> {
    match env.non_empty(var) {
        None => Ok(None),
        Some(v) => parse(v)
            .map(Some)
            .map_err(|problem| ArgsError::Environment {
                var: var.to_owned(),
                problem,
            }),
    }
}

fn quoted(arg: &str) -> String {
    format!("`{arg}`")
}

// ---- fake-carla ----------------------------------------------------------------------------

/// What `fake-carla` was asked to be.
#[derive(Debug, Clone, PartialEq)]
pub struct CarlaConfig {
    /// `-carla-rpc-port` (default 2000); 0 lets the system pick a free port (tests).
    pub rpc_port: u16,
    /// `-carla-streaming-port`; `None` means RPC port + 1, as CARLA does.
    pub streaming_port: Option<u16>,
    /// The map given as a positional argument, if any.
    pub map: Option<String>,
    /// Flags CARLA knows that change nothing here (`-vulkan`, `-ini:...`), as given.
    pub accepted: Vec<String>,
    /// Arguments CARLA would not know; logged and ignored.
    pub ignored: Vec<String>,
    /// The failure modes asked for.
    pub faults: CarlaFaults,
}

const CARLA_HELP: &str = "\
usage: fake-carla [-carla-rpc-port=N] [-carla-streaming-port=N] [-vulkan|-opengl]
                  [-RenderOffScreen] [-nosound] [-ini:...] [fake options]

Stands in for ./CarlaUE4.sh: listens on the RPC port (default 2000) and the streaming
port (RPC + 1), holds client connections, exits 0 on SIGTERM/SIGINT. Unknown flags are
logged and ignored. Flags take `-name=value` or `--name value`, in any case.

fake options (each also an environment variable; the flag wins):
  -fake-crash-after=SECONDS   FAKE_CARLA_CRASH_AFTER   crash this long after listening
  -fake-crash-file=PATH       FAKE_CARLA_CRASH_FILE    crash when PATH appears (polled)
  -fake-fail-start            FAKE_CARLA_FAIL_START    exit 1 before listening
  -fake-once-dir=DIR          FAKE_CARLA_ONCE_DIR      each fault fires once (marker in DIR)
  -fake-start-delay=SECONDS   FAKE_CARLA_START_DELAY   wait before listening
  -fake-crash-signal=KIND     FAKE_CARLA_CRASH_SIGNAL  abort (SIGABRT, default), segv, exit (134)
";

/// Parses `CarlaUE4.sh`'s arguments (without the program name) and the fake's variables.
pub fn parse_carla(args: &[String], env: &Env) -> Result<Parsed<CarlaConfig>, ArgsError> {
    let mut cfg = CarlaConfig {
        rpc_port: 2000,
        streaming_port: None,
        map: None,
        accepted: Vec::new(),
        ignored: Vec::new(),
        faults: CarlaFaults::from_env(env)?,
    };
    let mut i = 0;
    while i < args.len() {
        let token = &args[i];
        i += 1;
        let Some(body) = token
            .strip_prefix("--")
            .or_else(|| token.strip_prefix('-'))
            .filter(|b| !b.is_empty())
        else {
            // NB: Unreal takes the first positional as the map to load; CarlaUE4.sh itself
            // passes `CarlaUE4` first when it execs the shipping binary.
            if cfg.map.is_none() && token != "CarlaUE4" {
                cfg.map = Some(token.clone());
            } else {
                cfg.ignored.push(token.clone());
            }
            continue;
        };
        let (name, inline) = match body.split_once('=') {
            Some((n, v)) => (n, Some(v)),
            None => (body, None),
        };
        let lower = name.to_ascii_lowercase();
        if lower.starts_with("ini:") {
            cfg.accepted.push(token.clone());
            continue;
        }
        let flag = format!("-{name}");
        match lower.as_str() {
            "carla-rpc-port" | "carla-port" | "carla-world-port" | "world-port" => {
                let v = carla_value(&flag, inline, args, &mut i)?;
                cfg.rpc_port = carla_port(&flag, &v)?;
            }
            "carla-streaming-port" => {
                let v = carla_value(&flag, inline, args, &mut i)?;
                let port = carla_port(&flag, &v)?;
                // CARLA reads 0 as "RPC port + 1".
                cfg.streaming_port = (port != 0).then_some(port);
            }
            "help" | "h" => return Ok(Parsed::Help(CARLA_HELP.to_owned())),
            _ if fault(&mut cfg.faults, &lower, (&flag, inline), (args, &mut i))? => {}
            _ if harmless(&lower, inline) => cfg.accepted.push(token.clone()),
            _ => cfg.ignored.push(token.clone()),
        }
    }
    if cfg.streaming_port.is_none() && cfg.rpc_port == u16::MAX {
        return Err(ArgsError::Invalid {
            arg: quoted("-carla-rpc-port"),
            problem: format!(
                "port {} leaves no room for the streaming port (RPC port + 1)",
                cfg.rpc_port
            ),
        });
    }
    Ok(Parsed::Run(cfg))
}

/// A fake CARLA's own fault flag (`-fake-*`), read into `faults`: whether `lower` is one.
fn fault(
    faults: &mut CarlaFaults,
    lower: &str,
    (flag, inline): (&str, Option<&str>),
    (args, i): (&[String], &mut usize),
) -> Result<bool, ArgsError> {
    match lower {
        "fake-crash-after" => {
            let v = carla_value(flag, inline, args, i)?;
            faults.crash_after = Some(seconds(&v).map_err(|problem| ArgsError::Invalid {
                arg: quoted(flag),
                problem,
            })?);
        }
        "fake-crash-file" => {
            let v = carla_value(flag, inline, args, i)?;
            faults.crash_file = Some(non_empty_path(flag, &v)?);
        }
        "fake-once-dir" => {
            let v = carla_value(flag, inline, args, i)?;
            faults.once_dir = Some(non_empty_path(flag, &v)?);
        }
        "fake-start-delay" => {
            let v = carla_value(flag, inline, args, i)?;
            faults.start_delay = seconds(&v).map_err(|problem| ArgsError::Invalid {
                arg: quoted(flag),
                problem,
            })?;
        }
        "fake-crash-signal" => {
            let v = carla_value(flag, inline, args, i)?;
            faults.crash_signal = v.parse().map_err(|problem| ArgsError::Invalid {
                arg: quoted(flag),
                problem,
            })?;
        }
        "fake-fail-start" => {
            faults.fail_start = match inline {
                None => true,
                Some(v) => switch(v).map_err(|problem| ArgsError::Invalid {
                    arg: quoted(flag),
                    problem,
                })?,
            };
        }
        _ => return Ok(false),
    }
    Ok(true)
}

/// Unreal's and CARLA's flags that change nothing for a fake: those that take an `=value`
/// (with it), and the switches.
fn harmless(lower: &str, inline: Option<&str>) -> bool {
    let with_value = matches!(
        lower,
        "carla-secondary-port"
            | "carla-primary-port"
            | "carla-primary-host"
            | "quality-level"
            | "fps"
            | "resx"
            | "resy"
            | "graphicsadapter"
            | "carla-settings"
            | "carla-server-timeout"
            | "ros2"
            | "log"
            | "abslog"
            | "execcmds"
    );
    let switch = matches!(
        lower,
        "vulkan"
            | "opengl"
            | "opengl3"
            | "opengl4"
            | "renderoffscreen"
            | "nosound"
            | "nullrhi"
            | "carla-server"
            | "windowed"
            | "fullscreen"
            | "prefernvidia"
            | "benchmark"
            | "unattended"
            | "nosplash"
            | "carla-no-hud"
            | "norhithread"
    );
    (with_value && (inline.is_some() || lower == "ros2" || lower == "log")) || switch
}

/// The value of a CARLA flag: after `=`, or (the `--flag N` style) the next argument.
fn carla_value(
    flag: &str,
    inline: Option<&str>,
    args: &[String],
    i: &mut usize,
) -> Result<String, ArgsError> {
    if let Some(v) = inline {
        return Ok(v.to_owned());
    }
    match args.get(*i) {
        Some(next) if !next.starts_with('-') => {
            *i += 1;
            Ok(next.clone())
        }
        _ => Err(ArgsError::MissingValue { arg: quoted(flag) }),
    }
}

fn carla_port(flag: &str, value: &str) -> Result<u16, ArgsError> {
    value
        .trim()
        .parse::<u16>()
        .map_err(|_| ArgsError::InvalidValue {
            arg: quoted(flag),
            kind: "port",
            value: value.to_owned(),
        })
}

fn non_empty_path(flag: &str, value: &str) -> Result<PathBuf, ArgsError> {
    if value.is_empty() {
        return Err(ArgsError::Invalid {
            arg: quoted(flag),
            problem: "is empty".into(),
        });
    }
    Ok(PathBuf::from(value))
}

// ---- fake-evaluator ------------------------------------------------------------------------

/// The Leaderboard's participation tracks (`--track`, `CHALLENGE_TRACK_CODENAME`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Track {
    /// `SENSORS`
    Sensors,
    /// `MAP`
    Map,
    /// `SENSORS_QUALIFIER`
    SensorsQualifier,
    /// `MAP_QUALIFIER`
    MapQualifier,
}

impl Track {
    /// The codename as written on the command line.
    pub fn as_str(self) -> &'static str {
        match self {
            Track::Sensors => "SENSORS",
            Track::Map => "MAP",
            Track::SensorsQualifier => "SENSORS_QUALIFIER",
            Track::MapQualifier => "MAP_QUALIFIER",
        }
    }
}

impl std::str::FromStr for Track {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "SENSORS" => Ok(Track::Sensors),
            "MAP" => Ok(Track::Map),
            "SENSORS_QUALIFIER" => Ok(Track::SensorsQualifier),
            "MAP_QUALIFIER" => Ok(Track::MapQualifier),
            _ => Err(format!(
                "`{s}` is not a track (SENSORS, MAP, SENSORS_QUALIFIER, MAP_QUALIFIER)"
            )),
        }
    }
}

/// The routes of `--routes-subset`: route ids in ascending order, each once.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RoutesSubset {
    /// The route numbers.
    pub routes: Vec<u64>,
    /// The subset as written.
    pub raw: String,
}

impl std::str::FromStr for RoutesSubset {
    type Err = String;

    /// Reads `a-b` (inclusive), single ids and comma-separated mixes of both, with the
    /// official parser's errors. Spaces are ignored, as upstream strips them.
    fn from_str(s: &str) -> Result<Self, String> {
        let compact: String = s.chars().filter(|c| *c != ' ').collect();
        if compact.is_empty() {
            return Err(
                "is empty: fake-evaluator does not read the routes file, give the \
                        subset as `a-b`"
                    .into(),
            );
        }
        let number = |t: &str| -> Result<u64, String> {
            if t.is_empty() || t.len() > 9 || !t.bytes().all(|b| b.is_ascii_digit()) {
                return Err(format!("`{t}` in `{s}` is not a route id"));
            }
            t.parse::<u64>().map_err(|e| e.to_string())
        };
        let mut routes: Vec<u64> = Vec::new();
        for group in compact.split(',') {
            let (first, last) = match group.split_once('-') {
                Some((a, b)) => (number(a)?, number(b)?),
                None => {
                    let a = number(group)?;
                    (a, a)
                }
            };
            if first > last {
                return Err(format!(
                    "malformed route subset `{group}`, found the end id before the starting one"
                ));
            }
            if last - first >= MAX_RECORDS || routes.len() as u64 + (last - first) >= MAX_RECORDS {
                return Err(format!("`{s}` holds more than {MAX_RECORDS} routes"));
            }
            for route in first..=last {
                if routes.contains(&route) {
                    return Err(format!("found a repeated route with id `{route}`"));
                }
                routes.push(route);
            }
        }
        routes.sort_unstable();
        Ok(RoutesSubset {
            routes,
            raw: s.to_owned(),
        })
    }
}

/// The real evaluator's options, typed.
#[derive(Debug, Clone, PartialEq)]
pub struct EvaluatorArgs {
    /// Which evaluator this is: `LB_LEADERBOARD`, else 1.0 when `--scenarios` is given.
    pub leaderboard: Leaderboard,
    /// The script path a `python3 -u <script>` shim passed first, for tracebacks.
    pub script: Option<String>,
    /// `--host` (default `localhost`).
    pub host: String,
    /// `--port` (default 2000), the CARLA RPC port.
    pub port: u16,
    /// `--traffic-manager-port` (1.0: `--trafficManagerPort`; default 8000).
    pub traffic_manager_port: u16,
    /// `--traffic-manager-seed` (1.0: `--trafficManagerSeed`; default 0).
    pub traffic_manager_seed: i64,
    /// `--debug` (default 0).
    pub debug: i64,
    /// `--record`: the recorder directory; empty means no recording.
    pub record: String,
    /// `--timeout`: the CARLA client timeout in seconds (2.0: 300, 1.0: 60).
    pub timeout: f64,
    /// `--routes` (required; not read by the fake).
    pub routes: String,
    /// `--scenarios` (1.0 only, required there; not read by the fake).
    pub scenarios: Option<String>,
    /// `--routes-subset`.
    pub routes_subset: RoutesSubset,
    /// `--repetitions` (default 1).
    pub repetitions: u64,
    /// `-a`/`--agent` (required; not read by the fake).
    pub agent: String,
    /// `--agent-config`.
    pub agent_config: String,
    /// `--track` (default `SENSORS`).
    pub track: Track,
    /// `--resume`: argparse `type=bool`, so any non-empty value (even `0`) means true.
    pub resume: bool,
    /// `--checkpoint` (default `./simulation_results.json`).
    pub checkpoint: PathBuf,
    /// `--debug-checkpoint` (2.0 only, default `./live_results.txt`): the live results text.
    pub debug_checkpoint: Option<PathBuf>,
}

/// Everything `fake-evaluator` runs with: the real options and the fake's own settings.
#[derive(Debug, Clone, PartialEq)]
pub struct EvaluatorConfig {
    /// The real evaluator's options.
    pub args: EvaluatorArgs,
    /// `FAKE_EVALUATOR_ROUTE_SECONDS` (default 0.2): wall time spent per route.
    pub route_seconds: f64,
    /// `FAKE_EVALUATOR_CONNECT_SECONDS`: how long to wait for CARLA (default `--timeout`).
    pub connect_seconds: Option<f64>,
    /// `FAKE_EVALUATOR_RECORDS`: a results file whose records are the templates.
    pub records: Option<PathBuf>,
    /// The failure modes asked for.
    pub faults: EvaluatorFaults,
    /// What `PYTHONPATH` lets it import.
    pub imports: crate::imports::Imports,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Only {
    Both,
    V1,
    V2,
}

struct Opt {
    long: &'static str,
    short: Option<&'static str>,
    only: Only,
    env: Option<&'static str>,
}

const fn opt(long: &'static str, only: Only, env: Option<&'static str>) -> Opt {
    Opt {
        long,
        short: None,
        only,
        env,
    }
}

/// `-a`/`--agent`, the one option with a short form.
const AGENT: Opt = Opt {
    long: "--agent",
    short: Some("-a"),
    only: Only::Both,
    env: Some("TEAM_AGENT"),
};

/// The options of `leaderboard_evaluator.py`, with the variables the cloud's shell command
/// expands into them.
const EVALUATOR_OPTIONS: &[Opt] = &[
    opt("--host", Only::Both, None),
    opt("--port", Only::Both, Some("CARLA_PORT")),
    opt("--traffic-manager-port", Only::V2, Some("CARLA_TM_PORT")),
    opt("--traffic-manager-seed", Only::V2, None),
    opt("--trafficManagerPort", Only::V1, Some("CARLA_TM_PORT")),
    opt("--trafficManagerSeed", Only::V1, None),
    opt("--debug", Only::Both, Some("DEBUG_CHALLENGE")),
    opt("--record", Only::Both, Some("RECORD_PATH")),
    opt("--timeout", Only::Both, None),
    opt("--routes", Only::Both, Some("ROUTES")),
    opt("--scenarios", Only::V1, Some("SCENARIOS")),
    opt("--routes-subset", Only::Both, Some("ROUTES_SUBSET")),
    opt("--repetitions", Only::Both, Some("REPETITIONS")),
    AGENT,
    opt("--agent-config", Only::Both, Some("TEAM_CONFIG")),
    opt("--track", Only::Both, Some("CHALLENGE_TRACK_CODENAME")),
    opt("--resume", Only::Both, Some("RESUME")),
    opt("--checkpoint", Only::Both, Some("CHECKPOINT_ENDPOINT")),
    opt(
        "--debug-checkpoint",
        Only::V2,
        Some("DEBUG_CHECKPOINT_ENDPOINT"),
    ),
];

/// Interpreter options a `python3` shim passes before the script; `-W`/`-X` take a value.
const PYTHON_FLAGS: &[&str] = &[
    "-u", "-B", "-O", "-OO", "-s", "-S", "-E", "-I", "-b", "-bb", "-q", "-d", "-v", "-x",
];

/// The usage line argparse prints before an error.
pub fn evaluator_usage(leaderboard: Leaderboard) -> String {
    let mut usage = String::from("usage: leaderboard_evaluator.py [-h]");
    for o in options_for(leaderboard) {
        let metavar = o
            .long
            .trim_start_matches("--")
            .replace('-', "_")
            .to_uppercase();
        let name = o.short.unwrap_or(o.long);
        if required(leaderboard).contains(&o.long) {
            usage.push_str(&format!(" {name} {metavar}"));
        } else {
            usage.push_str(&format!(" [{name} {metavar}]"));
        }
    }
    usage
}

/// The options argparse insists on.
fn required(leaderboard: Leaderboard) -> &'static [&'static str] {
    match leaderboard {
        Leaderboard::V1 => &["--routes", "--scenarios", "--agent"],
        Leaderboard::V2 => &["--routes", "--agent"],
    }
}

fn evaluator_help(leaderboard: Leaderboard) -> String {
    format!(
        "{}\n\nCARLA AD Leaderboard Evaluation (fake-evaluator, Leaderboard {leaderboard}).\n\n\
         Options take `--name=value` or `--name value`; a leading `-u <script.py>` (a python3\n\
         shim) is skipped. Unset options fall back to the variables the cloud's command\n\
         expands (CARLA_PORT, CHALLENGE_TRACK_CODENAME, ROUTES_SUBSET, REPETITIONS, RESUME,\n\
         CHECKPOINT_ENDPOINT, ...). See the crate README for the FAKE_EVALUATOR_* settings.\n",
        evaluator_usage(leaderboard)
    )
}

fn options_for(leaderboard: Leaderboard) -> impl Iterator<Item = &'static Opt> {
    EVALUATOR_OPTIONS.iter().filter(move |o| match o.only {
        Only::Both => true,
        Only::V1 => leaderboard == Leaderboard::V1,
        Only::V2 => leaderboard == Leaderboard::V2,
    })
}

/// Which evaluator the command line is for: `LB_LEADERBOARD`, else 1.0 when `--scenarios`
/// is there.
fn leaderboard_of(args: &[String], env: &Env) -> Result<Leaderboard, ArgsError> {
    if let Some(v) = env_value(env, "LB_LEADERBOARD", |v| v.parse::<Leaderboard>())? {
        return Ok(v);
    }
    let v1 = args
        .iter()
        .any(|a| a == "--scenarios" || a.starts_with("--scenarios="));
    Ok(if v1 { Leaderboard::V1 } else { Leaderboard::V2 })
}

/// Parses the evaluator's command line (without the program name) and the environment.
pub fn parse_evaluator(args: &[String], env: &Env) -> Result<Parsed<EvaluatorConfig>, ArgsError> {
    let (script, args) = python_script(args);
    let leaderboard = leaderboard_of(args, env)?;
    let Some((given, unrecognized)) = walk_evaluator(args, leaderboard)? else {
        return Ok(Parsed::Help(evaluator_help(leaderboard)));
    };
    let values = Values::resolve(leaderboard, given, env)?;
    if !unrecognized.is_empty() {
        return Err(ArgsError::Unrecognized {
            args: unrecognized.join(" "),
        });
    }
    let args = evaluator_args(&values, leaderboard, script)?;
    let route_seconds = env_value(env, "FAKE_EVALUATOR_ROUTE_SECONDS", seconds)?.unwrap_or(0.2);
    let connect_seconds = env_value(env, "FAKE_EVALUATOR_CONNECT_SECONDS", seconds)?;
    let records = env.non_empty("FAKE_EVALUATOR_RECORDS").map(PathBuf::from);
    Ok(Parsed::Run(EvaluatorConfig {
        args,
        route_seconds,
        connect_seconds,
        records,
        faults: EvaluatorFaults::from_env(env)?,
        imports: crate::imports::Imports::from_env(env),
    }))
}

/// The script a `python3` shim names (`fake-evaluator -u /path/leaderboard_evaluator.py ...`),
/// past the interpreter's own flags, and the script's arguments.
fn python_script(args: &[String]) -> (Option<String>, &[String]) {
    let mut i = 0;
    while let Some(a) = args.get(i) {
        if PYTHON_FLAGS.contains(&a.as_str()) {
            i += 1;
        } else if a == "-W" || a == "-X" {
            i += 2;
        } else if (a.starts_with("-W") || a.starts_with("-X")) && a.len() > 2 {
            i += 1;
        } else {
            break;
        }
    }
    let script = match args.get(i) {
        Some(a) if !a.starts_with('-') => {
            i += 1;
            Some(a.clone())
        }
        _ => None,
    };
    (script, args.get(i..).unwrap_or_default())
}

/// The options given, by long name, and the tokens argparse would not recognize.
type Walked = (BTreeMap<&'static str, String>, Vec<String>);

/// The evaluator's options walked as argparse does (the last occurrence wins, unknown ones
/// collected), or `None` for `--help`.
fn walk_evaluator(args: &[String], leaderboard: Leaderboard) -> Result<Option<Walked>, ArgsError> {
    let mut given: BTreeMap<&'static str, String> = BTreeMap::new();
    let mut unrecognized: Vec<String> = Vec::new();
    let mut i = 0;
    while i < args.len() {
        let token = &args[i];
        i += 1;
        if token == "-h" || token == "--help" {
            return Ok(None);
        }
        if token == "--" {
            unrecognized.extend(args[i..].iter().cloned());
            break;
        }
        let (opt, inline) = if let Some(body) = token.strip_prefix("--") {
            let (name, inline) = match body.split_once('=') {
                Some((n, v)) => (n, Some(v.to_owned())),
                None => (body, None),
            };
            match resolve(leaderboard, name)? {
                Some(o) => (o, inline),
                None => {
                    unrecognized.push(token.clone());
                    continue;
                }
            }
        } else if let Some(rest) = token.strip_prefix("-a").filter(|_| token.len() > 1) {
            let agent: &'static Opt = &AGENT;
            let inline = match rest {
                "" => None,
                r => Some(r.strip_prefix('=').unwrap_or(r).to_owned()),
            };
            (agent, inline)
        } else {
            // Positionals and unknown short options.
            unrecognized.push(token.clone());
            continue;
        };
        let value = match inline {
            Some(v) => v,
            None => match args.get(i) {
                Some(next) if !looks_like_option(next) => {
                    i += 1;
                    next.clone()
                }
                _ => {
                    return Err(ArgsError::MissingValue {
                        arg: quoted(&display_opt(opt)),
                    })
                }
            },
        };
        given.insert(opt.long, value);
    }
    Ok(Some((given, unrecognized)))
}

/// The evaluator's option values, each with how an error names where it came from.
struct Values(BTreeMap<&'static str, (String, String)>);

impl Values {
    /// The options given, the environment for what the command line left out; every required
    /// one present.
    fn resolve(
        leaderboard: Leaderboard,
        given: BTreeMap<&'static str, String>,
        env: &Env,
    ) -> Result<Values, ArgsError> {
        let mut values: BTreeMap<&'static str, (String, String)> = BTreeMap::new();
        for o in options_for(leaderboard) {
            if let Some(v) = given.get(o.long) {
                values.insert(o.long, (v.clone(), quoted(&display_opt(o))));
            } else if let Some((var, v)) = o.env.and_then(|var| Some((var, env.non_empty(var)?))) {
                let source = format!("{} (from `{var}`)", quoted(&display_opt(o)));
                values.insert(o.long, (v.to_owned(), source));
            }
        }
        let missing: Vec<String> = required(leaderboard)
            .iter()
            .filter(|r| !values.contains_key(*r))
            .map(|r| match *r {
                "--agent" => "-a/--agent".to_owned(),
                other => other.to_owned(),
            })
            .collect();
        if !missing.is_empty() {
            return Err(ArgsError::Required {
                args: missing.join(", "),
            });
        }
        Ok(Values(values))
    }

    fn get(&self, long: &str) -> Option<(&str, &str)> {
        self.0.get(long).map(|(v, src)| (v.as_str(), src.as_str()))
    }

    /// Where an option's value came from, as an error names it.
    fn source(&self, long: &str) -> String {
        self.get(long)
            .map_or_else(|| quoted(long), |(_, s)| s.to_owned())
    }

    fn int(&self, long: &str, default: i64) -> Result<i64, ArgsError> {
        match self.get(long) {
            None => Ok(default),
            Some((v, src)) => v
                .trim()
                .parse::<i64>()
                .map_err(|_| ArgsError::InvalidValue {
                    arg: src.to_owned(),
                    kind: "int",
                    value: v.to_owned(),
                }),
        }
    }

    fn port(&self, long: &str, default: i64) -> Result<u16, ArgsError> {
        let p = self.int(long, default)?;
        u16::try_from(p)
            .ok()
            .filter(|p| *p != 0)
            .ok_or_else(|| ArgsError::Invalid {
                arg: self.source(long),
                problem: format!("`{p}` is not a TCP port (1-65535)"),
            })
    }

    fn text(&self, long: &str, default: &str) -> String {
        self.get(long).map_or(default, |(v, _)| v).to_owned()
    }

    /// A value `parse` reads, named in its error.
    fn parsed<T>(
        &self,
        long: &str,
        parse: impl FnOnce(&str) -> Result<T, String>,
    ) -> Result<Option<T>, ArgsError> {
        let Some((v, src)) = self.get(long) else {
            return Ok(None);
        };
        parse(v).map(Some).map_err(|problem| ArgsError::Invalid {
            arg: src.to_owned(),
            problem,
        })
    }
}

/// The evaluator's arguments from its option values.
fn evaluator_args(
    values: &Values,
    leaderboard: Leaderboard,
    script: Option<String>,
) -> Result<EvaluatorArgs, ArgsError> {
    let (tm_port, tm_seed, timeout) = match leaderboard {
        Leaderboard::V1 => ("--trafficManagerPort", "--trafficManagerSeed", 60.0),
        Leaderboard::V2 => ("--traffic-manager-port", "--traffic-manager-seed", 300.0),
    };
    let (routes_subset, repetitions) = subset_and_repetitions(values)?;
    let checkpoint = values.text("--checkpoint", "./simulation_results.json");
    if checkpoint.is_empty() {
        return Err(ArgsError::Invalid {
            arg: values.source("--checkpoint"),
            problem: "is empty".into(),
        });
    }
    let debug_checkpoint = match leaderboard {
        Leaderboard::V1 => None,
        Leaderboard::V2 => Some(values.text("--debug-checkpoint", "./live_results.txt"))
            .filter(|p| !p.is_empty())
            .map(PathBuf::from),
    };
    Ok(EvaluatorArgs {
        leaderboard,
        script,
        host: values.text("--host", "localhost"),
        port: values.port("--port", 2000)?,
        traffic_manager_port: values.port(tm_port, 8000)?,
        traffic_manager_seed: values.int(tm_seed, 0)?,
        debug: values.int("--debug", 0)?,
        record: values.text("--record", ""),
        timeout: values.parsed("--timeout", seconds)?.unwrap_or(timeout),
        routes: values.text("--routes", ""),
        scenarios: values.get("--scenarios").map(|(v, _)| v.to_owned()),
        routes_subset,
        repetitions,
        agent: values.text("--agent", ""),
        agent_config: values.text("--agent-config", ""),
        track: values
            .parsed("--track", str::parse)?
            .unwrap_or(Track::Sensors),
        // NB: argparse's `type=bool` is Python's bool(str): only the empty string is false.
        resume: values.get("--resume").is_some_and(|(v, _)| !v.is_empty()),
        checkpoint: PathBuf::from(checkpoint),
        debug_checkpoint,
    })
}

/// `--routes-subset` and `--repetitions`, within the records a checkpoint may hold.
fn subset_and_repetitions(values: &Values) -> Result<(RoutesSubset, u64), ArgsError> {
    let repetitions = values.int("--repetitions", 1)?;
    if repetitions < 1 {
        return Err(ArgsError::Invalid {
            arg: values.source("--repetitions"),
            problem: format!("`{repetitions}` is not a positive number of repetitions"),
        });
    }
    let repetitions = repetitions as u64;
    let (subset_value, subset_src) = values
        .get("--routes-subset")
        .unwrap_or(("", "`--routes-subset`"));
    let routes_subset: RoutesSubset =
        subset_value.parse().map_err(|problem| ArgsError::Invalid {
            arg: subset_src.to_owned(),
            problem,
        })?;
    if routes_subset.routes.len() as u64 * repetitions > MAX_RECORDS {
        return Err(ArgsError::Invalid {
            arg: subset_src.to_owned(),
            problem: format!(
                "{} routes x {repetitions} repetitions is over the limit of {MAX_RECORDS} records",
                routes_subset.routes.len()
            ),
        });
    }
    Ok((routes_subset, repetitions))
}

/// argparse takes `-5` as a value but `-x` as the next option.
fn looks_like_option(token: &str) -> bool {
    token.starts_with('-') && token.len() > 1 && token.parse::<f64>().is_err()
}

fn display_opt(o: &Opt) -> String {
    match o.short {
        Some(s) => format!("{s}/{}", o.long),
        None => o.long.to_owned(),
    }
}

/// Finds the option a `--name` means: an exact match, else a unique prefix (argparse's
/// `allow_abbrev`).
fn resolve(leaderboard: Leaderboard, name: &str) -> Result<Option<&'static Opt>, ArgsError> {
    let long = format!("--{name}");
    if let Some(o) = options_for(leaderboard).find(|o| o.long == long) {
        return Ok(Some(o));
    }
    let candidates: Vec<&'static Opt> = options_for(leaderboard)
        .filter(|o| o.long.starts_with(&long))
        .collect();
    match candidates.as_slice() {
        [] => Ok(None),
        [one] => Ok(Some(one)),
        many => Err(ArgsError::Ambiguous {
            arg: long,
            candidates: many.iter().map(|o| o.long).collect::<Vec<_>>().join(", "),
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn strings(args: &[&str]) -> Vec<String> {
        args.iter().map(|s| s.to_string()).collect()
    }

    fn evaluator(args: &[&str], env: &[(&str, &str)]) -> Result<EvaluatorConfig, ArgsError> {
        match parse_evaluator(&strings(args), &Env::from_pairs(env.iter().copied()))? {
            Parsed::Run(cfg) => Ok(cfg),
            Parsed::Help(_) => panic!("unexpected help"),
        }
    }

    fn carla(args: &[&str], env: &[(&str, &str)]) -> Result<CarlaConfig, ArgsError> {
        match parse_carla(&strings(args), &Env::from_pairs(env.iter().copied()))? {
            Parsed::Run(cfg) => Ok(cfg),
            Parsed::Help(_) => panic!("unexpected help"),
        }
    }

    const BASE: &[&str] = &["--routes=r.xml", "--agent=a.py", "--routes-subset=0-4"];

    #[test]
    fn carla_takes_the_ports_in_both_styles_and_keeps_unknown_flags_aside() {
        let cfg = carla(
            &[
                "-vulkan",
                "-carla-rpc-port=2100",
                "-RenderOffScreen",
                "-nosound",
                "-ini:[/Script/Engine.RendererSettings]:r.GraphicsAdapter=1",
                "-bogus",
            ],
            &[],
        )
        .unwrap();
        assert_eq!(cfg.rpc_port, 2100);
        assert_eq!(cfg.streaming_port, None);
        assert_eq!(cfg.accepted.len(), 4);
        assert_eq!(cfg.ignored, vec!["-bogus".to_string()]);

        let cfg = carla(&["--carla-rpc-port", "3000", "-opengl"], &[]).unwrap();
        assert_eq!(cfg.rpc_port, 3000);
        let cfg = carla(&["-Carla-RPC-Port=3100", "-carla-streaming-port=4000"], &[]).unwrap();
        assert_eq!((cfg.rpc_port, cfg.streaming_port), (3100, Some(4000)));
        assert_eq!(carla(&[], &[]).unwrap().rpc_port, 2000);
    }

    #[test]
    fn carla_port_errors_name_the_flag() {
        let err = carla(&["-carla-rpc-port=abc"], &[]).unwrap_err();
        assert_eq!(err.name(), "InvalidValue");
        assert!(err.to_string().contains("-carla-rpc-port"), "{err}");
        let err = carla(&["--carla-rpc-port"], &[]).unwrap_err();
        assert_eq!(err.name(), "MissingValue");
        let err = carla(&["-carla-rpc-port=65535"], &[]).unwrap_err();
        assert!(err.to_string().contains("streaming"), "{err}");
    }

    #[test]
    fn carla_fault_flags_win_over_the_environment() {
        let env = [
            ("FAKE_CARLA_CRASH_AFTER", "5"),
            ("FAKE_CARLA_FAIL_START", "1"),
        ];
        let cfg = carla(&["-fake-crash-after=0.5", "-fake-fail-start=0"], &env).unwrap();
        assert_eq!(cfg.faults.crash_after, Some(0.5));
        assert!(!cfg.faults.fail_start);
        let err = carla(&[], &[("FAKE_CARLA_CRASH_AFTER", "soon")]).unwrap_err();
        assert!(err.to_string().contains("FAKE_CARLA_CRASH_AFTER"), "{err}");
    }

    #[test]
    fn evaluator_takes_both_value_styles_prefixes_and_the_short_agent_flag() {
        let cfg = evaluator(
            &[
                "--port",
                "2100",
                "--traffic-manager-port=2110",
                "-a",
                "agent.py",
                "--routes=r.xml",
                "--routes-sub=3-5",
                "--repetitions=2",
                "--resume=0",
            ],
            &[],
        )
        .unwrap();
        let a = cfg.args;
        assert_eq!((a.port, a.traffic_manager_port), (2100, 2110));
        assert_eq!(a.agent, "agent.py");
        assert_eq!(a.routes_subset.routes, vec![3, 4, 5]);
        assert_eq!(a.repetitions, 2);
        assert!(a.resume, "argparse's bool('0') is True");
        assert_eq!(a.leaderboard, Leaderboard::V2);
        assert_eq!(
            a.debug_checkpoint,
            Some(PathBuf::from("./live_results.txt"))
        );
    }

    #[test]
    fn evaluator_skips_a_python_shim_prefix() {
        let mut args = vec![
            "-u",
            "/workspace/leaderboard/leaderboard/leaderboard_evaluator.py",
        ];
        args.extend_from_slice(BASE);
        let cfg = evaluator(&args, &[]).unwrap();
        assert_eq!(
            cfg.args.script.as_deref(),
            Some("/workspace/leaderboard/leaderboard/leaderboard_evaluator.py")
        );
    }

    #[test]
    fn evaluator_falls_back_on_the_environment_but_the_command_line_wins() {
        let env = [
            ("CHALLENGE_TRACK_CODENAME", "MAP"),
            ("CARLA_PORT", "2300"),
            ("RESUME", ""),
            ("REPETITIONS", "3"),
        ];
        let cfg = evaluator(BASE, &env).unwrap();
        assert_eq!(cfg.args.track, Track::Map);
        assert_eq!(cfg.args.port, 2300);
        assert_eq!(cfg.args.repetitions, 3);
        assert!(!cfg.args.resume);
        let mut args = BASE.to_vec();
        args.push("--track=SENSORS");
        let cfg = evaluator(&args, &env).unwrap();
        assert_eq!(cfg.args.track, Track::Sensors);
    }

    #[test]
    fn evaluator_errors_name_the_argument() {
        let with = |extra: &[&str]| {
            let mut args = BASE.to_vec();
            args.extend_from_slice(extra);
            evaluator(&args, &[]).unwrap_err()
        };
        let err = with(&["--repetitions=x"]);
        assert_eq!(err.name(), "InvalidValue");
        assert!(err.to_string().contains("`--repetitions`"), "{err}");
        let err = with(&["--port=70000"]);
        assert!(err.to_string().contains("`--port`"), "{err}");
        let err = with(&["--bogus=1"]);
        assert_eq!(err.name(), "UnrecognizedArguments");
        assert!(err.to_string().contains("--bogus"), "{err}");
        let err = with(&["--routes-subset=5-2"]);
        assert!(err.to_string().contains("`--routes-subset`"), "{err}");
        let err = with(&["--track=CARS"]);
        assert!(err.to_string().contains("`--track`"), "{err}");
        let err = with(&["--port"]);
        assert_eq!(err.name(), "MissingValue");
        let err = with(&["--rout=x"]);
        assert_eq!(err.name(), "AmbiguousOption", "{err}");
        let err = evaluator(&["--agent=a.py"], &[]).unwrap_err();
        assert_eq!(
            err.to_string(),
            "the following arguments are required: --routes"
        );
        let err = evaluator(&BASE[..2], &[("REPETITIONS", "2")]).unwrap_err();
        assert!(err.to_string().contains("`--routes-subset`"), "{err}");
        let err = evaluator(BASE, &[("REPETITIONS", "0")]).unwrap_err();
        assert!(err.to_string().contains("from `REPETITIONS`"), "{err}");
        let err = evaluator(BASE, &[("FAKE_EVALUATOR_ROUTE_SECONDS", "-1")]).unwrap_err();
        assert_eq!(err.name(), "InvalidEnvironment");
    }

    #[test]
    fn leaderboard_one_takes_scenarios_and_refuses_the_two_only_flags() {
        let mut args = BASE.to_vec();
        args.push("--scenarios=s.json");
        let cfg = evaluator(&args, &[]).unwrap();
        assert_eq!(cfg.args.leaderboard, Leaderboard::V1);
        assert_eq!(cfg.args.debug_checkpoint, None);
        assert_eq!(cfg.args.timeout, 60.0);
        args.push("--debug-checkpoint=x");
        let err = evaluator(&args, &[]).unwrap_err();
        assert_eq!(err.name(), "UnrecognizedArguments");
        let err = evaluator(BASE, &[("LB_LEADERBOARD", "1.0")]).unwrap_err();
        assert!(err.to_string().contains("--scenarios"), "{err}");
    }

    #[test]
    fn routes_subsets_read_like_the_official_parser() {
        let s: RoutesSubset = "0-2, 5,7-8".parse().unwrap();
        assert_eq!(s.routes, vec![0, 1, 2, 5, 7, 8]);
        assert!("3-1".parse::<RoutesSubset>().is_err());
        assert!("1-3,2".parse::<RoutesSubset>().is_err());
        assert!("a-b".parse::<RoutesSubset>().is_err());
        assert!("".parse::<RoutesSubset>().is_err());
    }
}
