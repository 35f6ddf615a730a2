//! Failure modes of the fakes, switched on by environment variables (or `fake-carla` flags),
//! and the "once" markers that let a restarted container behave.
//!
//! With a once directory, a fault fires only while its marker file is absent, and the marker
//! is written just before the fault fires: the first container crashes, its restart (same
//! directory) runs clean. Without one, the fault fires on every run.

use std::io::Write as _;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::str::FromStr;
use std::time::Duration;

use crate::args::{env_value, seconds, switch, ArgsError, Env};

/// Where a process keeps its "this fault already fired" markers.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OnceDir {
    dir: Option<PathBuf>,
    prefix: String,
}

impl OnceDir {
    /// Markers named `<dir>/<prefix>.<fault>`; no directory means every fault always fires.
    pub fn new(dir: Option<PathBuf>, prefix: impl Into<String>) -> Self {
        OnceDir {
            dir,
            prefix: prefix.into(),
        }
    }

    /// The marker file of a fault, if markers are kept.
    pub fn marker(&self, fault: &str) -> Option<PathBuf> {
        self.dir
            .as_ref()
            .map(|d| d.join(format!("{}.{fault}", self.prefix)))
    }

    /// Whether the fault may still fire.
    pub fn armed(&self, fault: &str) -> bool {
        match self.marker(fault) {
            None => true,
            Some(path) => {
                let armed = !path.exists();
                if !armed {
                    tracing::info!(fault, marker = %path.display(), "fault already fired once; skipping it");
                }
                armed
            }
        }
    }

    /// The markers of one fake (`fake-carla`, `fake-evaluator`) of one pair: keyed by the
    /// submission and pair the Job template exports (`LB_SUBMISSION_ID`, `LB_PAIR_ID`) when
    /// they are set, else by CARLA's port (a fake run by hand). Never by the port inside a Job:
    /// on local-kube a pod takes the first free port, so a pair whose first pod inherits a port
    /// another pair crashed on would find that pair's marker and skip its own fault.
    pub fn of_pair(dir: Option<PathBuf>, fake: &str, owner: Option<&str>, port: u16) -> Self {
        let prefix = match owner {
            Some(owner) => format!("{fake}-{owner}"),
            None => format!("{fake}-{port}"),
        };
        OnceDir::new(dir, prefix)
    }

    /// Records that the fault fires now. A marker that cannot be written is logged: the
    /// fault still fires, and would fire again after a restart.
    pub fn mark(&self, fault: &str) {
        let Some(path) = self.marker(fault) else {
            return;
        };
        let written = path
            .parent()
            .map_or(Ok(()), std::fs::create_dir_all)
            .and_then(|()| std::fs::write(&path, format!("pid {}\n", std::process::id())));
        if let Err(error) = written {
            tracing::warn!(fault, marker = %path.display(), %error, "cannot write the once marker");
        }
    }
}

/// How a fake dies when it crashes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum CrashSignal {
    /// `SIGABRT` through `std::process::abort` (a shell reports 134).
    #[default]
    Abort,
    /// `SIGSEGV`, sent to itself with the `kill` command, as a crashed Unreal engine dies.
    Segv,
    /// A plain exit with code 134, for places where a signal death is unwanted (no core).
    Exit,
}

impl CrashSignal {
    /// The signal number the crash reports in its last log lines.
    pub fn number(self) -> i32 {
        match self {
            CrashSignal::Abort | CrashSignal::Exit => 6,
            CrashSignal::Segv => 11,
        }
    }
}

impl FromStr for CrashSignal {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "abort" | "sigabrt" | "abrt" | "6" => Ok(CrashSignal::Abort),
            "segv" | "sigsegv" | "11" => Ok(CrashSignal::Segv),
            "exit" | "134" => Ok(CrashSignal::Exit),
            _ => Err(format!("`{s}` is not a crash kind (abort, segv, exit)")),
        }
    }
}

/// Dies the way a crashed native program does: no cleanup, listeners gone with the process.
pub fn crash(kind: CrashSignal) -> ! {
    let _ = std::io::stdout().flush();
    let _ = std::io::stderr().flush();
    match kind {
        CrashSignal::Exit => std::process::exit(134),
        CrashSignal::Segv => {
            // NB: no safe in-process way to raise SIGSEGV without a syscall crate; the
            // `kill` command is in every image we run in. Rust's runtime catches the first
            // SIGSEGV (stack-overflow detection) and restores the default action, so the
            // signal is sent until it lands. SIGABRT is the fallback.
            for _ in 0..5 {
                let _ = Command::new("kill")
                    .arg("-SEGV")
                    .arg(std::process::id().to_string())
                    .stdin(Stdio::null())
                    .status();
                std::thread::sleep(Duration::from_millis(200));
            }
            std::process::abort()
        }
        CrashSignal::Abort => std::process::abort(),
    }
}

/// `fake-carla`'s failure modes.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct CarlaFaults {
    /// `FAKE_CARLA_CRASH_AFTER`: crash this many seconds after listening.
    pub crash_after: Option<f64>,
    /// `FAKE_CARLA_CRASH_FILE`: crash when this file appears (polled every 100 ms).
    pub crash_file: Option<PathBuf>,
    /// `FAKE_CARLA_FAIL_START`: exit 1 before listening.
    pub fail_start: bool,
    /// `FAKE_CARLA_ONCE_DIR`: where the once markers live.
    pub once_dir: Option<PathBuf>,
    /// Whose markers they are: the submission and pair (`OnceDir::of_pair`).
    pub once_owner: Option<String>,
    /// `FAKE_CARLA_START_DELAY`: seconds to wait before listening (CARLA takes a while).
    pub start_delay: f64,
    /// `FAKE_CARLA_CRASH_SIGNAL`: how a crash dies.
    pub crash_signal: CrashSignal,
}

impl CarlaFaults {
    /// Reads the `FAKE_CARLA_*` variables.
    pub fn from_env(env: &Env) -> Result<Self, ArgsError> {
        Ok(CarlaFaults {
            crash_after: env_value(env, "FAKE_CARLA_CRASH_AFTER", seconds)?,
            crash_file: env.non_empty("FAKE_CARLA_CRASH_FILE").map(PathBuf::from),
            fail_start: env_value(env, "FAKE_CARLA_FAIL_START", switch)?.unwrap_or(false),
            once_dir: env.non_empty("FAKE_CARLA_ONCE_DIR").map(PathBuf::from),
            once_owner: once_owner(env),
            start_delay: env_value(env, "FAKE_CARLA_START_DELAY", seconds)?.unwrap_or(0.0),
            crash_signal: env_value(env, "FAKE_CARLA_CRASH_SIGNAL", |v| v.parse())?
                .unwrap_or_default(),
        })
    }
}

/// `<submission>-pair<id>` from the Job template's variables, when the pair's is set.
fn once_owner(env: &Env) -> Option<String> {
    let pair = env.non_empty("LB_PAIR_ID")?;
    let submission = env.non_empty("LB_SUBMISSION_ID").unwrap_or("0");
    Some(format!("{submission}-pair{pair}"))
}

/// A route a fault fires at: `7` (any repetition) or `7_rep1` (`RouteScenario_` optional).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RouteSelector {
    /// The route number.
    pub route: u64,
    /// The repetition, or any.
    pub rep: Option<u64>,
}

impl RouteSelector {
    /// Whether the fault fires at this route and repetition.
    pub fn matches(&self, route: u64, rep: u64) -> bool {
        self.route == route && self.rep.is_none_or(|r| r == rep)
    }

    /// The selector as written in marker names.
    pub fn label(&self) -> String {
        match self.rep {
            Some(r) => format!("{}_rep{r}", self.route),
            None => self.route.to_string(),
        }
    }
}

impl FromStr for RouteSelector {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || format!("`{s}` is not a route (`7`, `7_rep1` or `RouteScenario_7_rep1`)");
        let t = s.trim();
        let t = t.strip_prefix("RouteScenario_").unwrap_or(t);
        let (route, rep) = match t.split_once("_rep") {
            Some((r, p)) => (r, Some(p)),
            None => (t, None),
        };
        let number = |x: &str| -> Result<u64, String> {
            if x.is_empty() || x.len() > 12 || !x.bytes().all(|b| b.is_ascii_digit()) {
                return Err(bad());
            }
            x.parse().map_err(|_| bad())
        };
        Ok(RouteSelector {
            route: number(route)?,
            rep: rep.map(number).transpose()?,
        })
    }
}

/// What kind of invalid checkpoint `FAKE_EVALUATOR_GARBAGE` writes at the end.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GarbageKind {
    /// `1`/`truncated`: the final file cut in the middle (not JSON).
    Truncated,
    /// `schema`: JSON of the wrong shape (`progress` a string).
    Schema,
    /// `nan`: the final file with a bare `NaN` score, as Python's json writes one.
    NaN,
}

impl FromStr for GarbageKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "1" | "true" | "yes" | "truncated" => Ok(GarbageKind::Truncated),
            "schema" => Ok(GarbageKind::Schema),
            "nan" => Ok(GarbageKind::NaN),
            _ => Err(format!(
                "`{s}` is not a garbage kind (1, truncated, schema, nan)"
            )),
        }
    }
}

/// How the long-lived child of `FAKE_EVALUATOR_SPAWN_CHILD` behaves.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ChildMode {
    /// `1`: in the evaluator's process group, dies on SIGTERM.
    SameGroup,
    /// `group`: in a process group of its own (escapes a group kill), dies on SIGTERM.
    OwnGroup,
    /// `stubborn`: in the evaluator's group, ignores SIGTERM (only SIGKILL ends it).
    Stubborn,
}

impl ChildMode {
    fn as_str(self) -> &'static str {
        match self {
            ChildMode::SameGroup => "same-group",
            ChildMode::OwnGroup => "own-group",
            ChildMode::Stubborn => "stubborn",
        }
    }
}

impl FromStr for ChildMode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "1" | "true" | "yes" | "same-group" => Ok(ChildMode::SameGroup),
            "group" | "own-group" => Ok(ChildMode::OwnGroup),
            "stubborn" => Ok(ChildMode::Stubborn),
            _ => Err(format!("`{s}` is not a child mode (1, group, stubborn)")),
        }
    }
}

/// `fake-evaluator`'s failure modes.
#[derive(Debug, Clone, PartialEq)]
pub struct EvaluatorFaults {
    /// `FAKE_EVALUATOR_CRASH_AT_ROUTE`: a Python traceback and exit 1 while running it.
    pub crash_at: Option<RouteSelector>,
    /// `FAKE_EVALUATOR_HANG_AT_ROUTE`: stop printing and sleep until killed.
    pub hang_at: Option<RouteSelector>,
    /// `FAKE_EVALUATOR_FILL_AT_ROUTE`: when it starts, write [`FILL_LAYER_BYTES`] outside
    /// the volumes (the container's writable layer, `/var/tmp`), then go on: above the
    /// agent's `ephemeral-storage` request, within its limit.
    pub fill_at: Option<RouteSelector>,
    /// `FAKE_EVALUATOR_GARBAGE`: write an invalid checkpoint at the end (and exit 0).
    pub garbage: Option<GarbageKind>,
    /// `FAKE_EVALUATOR_SETUP_FAILURE`: the agent cannot be set up on any route.
    pub setup_failure: bool,
    /// `FAKE_EVALUATOR_SPAWN_CHILD`: spawn a process that outlives the evaluator.
    pub spawn_child: Option<ChildMode>,
    /// `FAKE_EVALUATOR_CHILD_SECONDS` (default 3600): how long that child lives.
    pub child_seconds: f64,
    /// `FAKE_EVALUATOR_CHILD_PID_FILE`: where the child's pid is written.
    pub child_pid_file: Option<PathBuf>,
    /// `FAKE_EVALUATOR_ONCE_DIR`: where the once markers live.
    pub once_dir: Option<PathBuf>,
    /// Whose markers they are: the submission and pair (`OnceDir::of_pair`).
    pub once_owner: Option<String>,
    /// `FAKE_EVALUATOR_RECORD_LOG` (instrumentation, not a fault): a file to which each
    /// record's write is appended as `<epoch ms> <route index>`, and the final write as
    /// `<epoch ms> global` (what `lbctl local run --latency` measures from).
    pub record_log: Option<PathBuf>,
    /// `FAKE_EVALUATOR_FLOOD_HZ` (1 to 50): this many times a second for the whole run,
    /// rewrite a file of its own in the status directory (`LB_STATUS_DIR`, default
    /// `/tmp/status`) and its results file with the same records (their durations and a
    /// trailing newline toggled), as a participant's code can.
    pub flood_hz: Option<u32>,
    /// The status directory the flood writes to.
    pub status_dir: PathBuf,
    /// `FAKE_EVALUATOR_FORGE_PAIR=<ID>`: before its first route and after its last, the
    /// evaluator of every other pair writes pair `<ID>`'s results file (its own records) and
    /// `agent-<ID>.done` beside its own, as a participant's code can in its pod.
    pub forge_pair: Option<u32>,
    /// This pair (`LB_PAIR_ID`).
    pub pair_id: Option<u32>,
    /// `FAKE_EVALUATOR_FORGE_RECORDINGS=1`: the participant's code tampers with the
    /// recordings as far as its container lets it: it stops CARLA's recorder as soon as the
    /// evaluator started it (a recording of nothing but its header), and writes a 1-byte file
    /// of each route's name where the recordings used to be (its own logs' `recorder/`); its
    /// records claim 0 s of simulated time, which a header-only recording fits.
    pub forge_recordings: bool,
    /// `FAKE_EVALUATOR_PLANT_GPU=<UUID>[,<UUID>...]`: once (with a once directory), write the
    /// first of these that is not this container's own GPU into the pair's GPU handoff
    /// (`$LB_HANDOFF_DIR/gpu-$LB_PAIR_ID`, default `/tmp/handoff`), then crash.
    pub plant_gpu: Vec<String>,
    /// This container's GPU (`NVIDIA_VISIBLE_DEVICES`).
    pub own_gpu: Option<String>,
    /// The pair's GPU handoff file.
    pub handoff_file: Option<PathBuf>,
}

impl EvaluatorFaults {
    /// Reads the `FAKE_EVALUATOR_*` failure variables.
    pub fn from_env(env: &Env) -> Result<Self, ArgsError> {
        let garbage = match env.non_empty("FAKE_EVALUATOR_GARBAGE") {
            Some(v) if switch(v) == Ok(false) => None,
            _ => env_value(env, "FAKE_EVALUATOR_GARBAGE", |v| v.parse())?,
        };
        let spawn_child = match env.non_empty("FAKE_EVALUATOR_SPAWN_CHILD") {
            Some(v) if switch(v) == Ok(false) => None,
            _ => env_value(env, "FAKE_EVALUATOR_SPAWN_CHILD", |v| v.parse())?,
        };
        Ok(EvaluatorFaults {
            crash_at: env_value(env, "FAKE_EVALUATOR_CRASH_AT_ROUTE", |v| v.parse())?,
            hang_at: env_value(env, "FAKE_EVALUATOR_HANG_AT_ROUTE", |v| v.parse())?,
            fill_at: env_value(env, "FAKE_EVALUATOR_FILL_AT_ROUTE", |v| v.parse())?,
            garbage,
            setup_failure: env_value(env, "FAKE_EVALUATOR_SETUP_FAILURE", switch)?.unwrap_or(false),
            spawn_child,
            child_seconds: env_value(env, "FAKE_EVALUATOR_CHILD_SECONDS", seconds)?
                .unwrap_or(3600.0),
            child_pid_file: env
                .non_empty("FAKE_EVALUATOR_CHILD_PID_FILE")
                .map(PathBuf::from),
            once_dir: env.non_empty("FAKE_EVALUATOR_ONCE_DIR").map(PathBuf::from),
            once_owner: once_owner(env),
            record_log: env
                .non_empty("FAKE_EVALUATOR_RECORD_LOG")
                .map(PathBuf::from),
            flood_hz: env_value(env, "FAKE_EVALUATOR_FLOOD_HZ", |v| {
                v.parse::<u32>()
                    .ok()
                    .filter(|hz| (1..=50).contains(hz))
                    .ok_or_else(|| "not a whole number from 1 to 50".to_string())
            })?,
            status_dir: env
                .non_empty("LB_STATUS_DIR")
                .map_or_else(|| PathBuf::from("/tmp/status"), PathBuf::from),
            forge_pair: env_value(env, "FAKE_EVALUATOR_FORGE_PAIR", |v| {
                v.parse::<u32>()
                    .ok()
                    .filter(|id| *id > 0)
                    .ok_or_else(|| "not a pair id (1 or more)".to_string())
            })?,
            forge_recordings: env_value(env, "FAKE_EVALUATOR_FORGE_RECORDINGS", switch)?
                .unwrap_or(false),
            plant_gpu: env
                .non_empty("FAKE_EVALUATOR_PLANT_GPU")
                .map(|v| v.split(',').map(|u| u.trim().to_owned()).collect())
                .unwrap_or_default(),
            own_gpu: env.non_empty("NVIDIA_VISIBLE_DEVICES").map(str::to_owned),
            pair_id: env.non_empty("LB_PAIR_ID").and_then(|p| p.parse().ok()),
            handoff_file: env.non_empty("LB_PAIR_ID").map(|pair| {
                let dir = env.non_empty("LB_HANDOFF_DIR").unwrap_or("/tmp/handoff");
                PathBuf::from(dir).join(format!("gpu-{pair}"))
            }),
        })
    }
}

/// Where the disk hog writes: the container's writable layer.
pub const FILL_LAYER_FILE: &str = "/var/tmp/fill.bin";

/// How much it writes: 12 GiB, above the agent's 4 GiB `ephemeral-storage` request and within
/// its 16 GiB limit (sparse: the size is what the node's kubelet counts here).
pub const FILL_LAYER_BYTES: u64 = 12 << 30;

/// Where the flood's large file goes: the top of the shared logs volume, as a participant's
/// code at `/tmp/logs/fill.bin` can.
const FILL_FILE: &str = "/tmp/logs/fill.bin";

/// Its size: the issue's reproduction wrote 200 MiB.
const FILL_BYTES: u64 = 200 << 20;

/// Rewrites `status_dir/flood.txt` and the results file `checkpoint` `hz` times a second,
/// forever (the flood fault), and writes a new marker name each time (an attempt beyond any a
/// pod reaches, `simulator-<pair>.start<16 + n>`); first, a 200 MiB file on the logs volume
/// (sparse: it takes no disk, its size is what matters). The results keep their records,
/// with only their durations and a trailing newline toggled ([`toggled`]), so every rewrite
/// is new content for logcopy and for the merge, and none is progress. Each
/// rewrite is a read and an atomic replace with no await between them, so on the evaluator's
/// single thread it never loses one of the evaluator's own writes.
pub async fn flood(status_dir: PathBuf, checkpoint: PathBuf, (hz, pair): (u32, Option<u32>)) {
    let period = Duration::from_secs_f64(1.0 / f64::from(hz.max(1)));
    let junk = status_dir.join("flood.txt");
    if let Err(error) = std::fs::File::create(FILL_FILE).and_then(|f| f.set_len(FILL_BYTES)) {
        tracing::debug!(%error, "flood: cannot write the large file");
    }
    let mut count = 0u64;
    loop {
        tokio::time::sleep(period).await;
        count += 1;
        if let Err(error) = std::fs::write(&junk, format!("{count}\n")) {
            tracing::debug!(%error, "flood: cannot write the status file");
        }
        if let Some(pair) = pair {
            let name = format!("simulator-{pair}.start{}", 16 + count);
            if let Err(error) = std::fs::write(status_dir.join(name), b"") {
                tracing::debug!(%error, "flood: cannot write a marker name");
            }
        }
        if let Ok(text) = std::fs::read_to_string(&checkpoint) {
            let next = toggled(&text, count);
            if let Err(error) = crate::records::write_atomic(&checkpoint, next.as_bytes()) {
                tracing::debug!(%error, "flood: cannot rewrite the results file");
            }
        }
    }
}

/// The results file `text` with the same records in other words: each record's
/// `meta.duration_system` half a second up on odd rewrites and down on even ones (never below
/// zero: the file stays valid), and a trailing newline that comes and goes.
fn toggled(text: &str, count: u64) -> String {
    let Ok(mut file) = serde_json::from_str::<serde_json::Value>(text) else {
        return text.to_owned();
    };
    let step = if count % 2 == 1 { 0.5 } else { -0.5 };
    let records = file["_checkpoint"]["records"].as_array_mut();
    for record in records.into_iter().flatten() {
        let meta = &mut record["meta"]["duration_system"];
        if let Some(seconds) = meta.as_f64() {
            *meta = serde_json::json!((seconds + step).max(0.0));
        }
    }
    let body = serde_json::to_string_pretty(&file).unwrap_or_else(|_| text.to_owned());
    if text.ends_with('\n') {
        body
    } else {
        format!("{body}\n")
    }
}

/// The first argument that turns `fake-evaluator` into the spawned child.
pub const CHILD_FLAG: &str = "--fake-participant-child";

/// Spawns the long-lived child (this same binary in child mode) and returns its pid. It
/// inherits stdout and stderr, as participant code does, and is never waited for.
pub fn spawn_child(mode: ChildMode, seconds: f64) -> std::io::Result<u32> {
    use std::os::unix::process::CommandExt as _;
    let mut cmd = Command::new(std::env::current_exe()?);
    cmd.arg0("fake-participant-child")
        .arg(CHILD_FLAG)
        .arg(mode.as_str())
        .arg(seconds.to_string())
        .stdin(Stdio::null());
    if mode == ChildMode::OwnGroup {
        cmd.process_group(0);
    }
    // NB: the handle is dropped on purpose: the child must outlive us, like a stray
    // participant process; init (or the container's subreaper) reaps it.
    let child = cmd.spawn()?;
    Ok(child.id())
}

/// The body of the spawned child: sleep for the given seconds (argument 2), ignoring
/// SIGTERM in `stubborn` mode. Returns the exit code.
pub async fn run_child(args: &[String]) -> i32 {
    let mode = args.first().and_then(|m| m.parse::<ChildMode>().ok());
    let secs = args.get(1).and_then(|s| seconds(s).ok());
    let (Some(mode), Some(secs)) = (mode, secs) else {
        eprintln!("fake-participant-child: usage: {CHILD_FLAG} <mode> <seconds>");
        return 2;
    };
    let life = tokio::time::sleep(Duration::from_secs_f64(secs));
    tokio::pin!(life);
    if mode != ChildMode::Stubborn {
        life.await;
        return 0;
    }
    let Ok(mut term) = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
    else {
        life.await;
        return 0;
    };
    loop {
        tokio::select! {
            () = &mut life => return 0,
            _ = term.recv() => eprintln!("fake-participant-child: ignoring SIGTERM"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_flood_toggles_durations_within_range_and_keeps_the_records() {
        let text = r#"{"_checkpoint": {"progress": [1, 2], "records": [
            {"route_id": "RouteScenario_0", "meta": {"duration_system": 0.2}}]}}"#;
        let up: serde_json::Value = serde_json::from_str(&toggled(text, 1)).unwrap();
        let down: serde_json::Value = serde_json::from_str(&toggled(text, 2)).unwrap();
        let seconds = |v: &serde_json::Value| {
            v["_checkpoint"]["records"][0]["meta"]["duration_system"].as_f64()
        };
        assert_eq!((seconds(&up), seconds(&down)), (Some(0.7), Some(0.0)));
        assert_eq!(
            up["_checkpoint"]["records"][0]["route_id"],
            "RouteScenario_0"
        );
        assert_eq!(up["_checkpoint"]["progress"], serde_json::json!([1, 2]));
        assert!(toggled(text, 1).ends_with('\n'));
        assert!(!toggled(&toggled(text, 1), 2).ends_with('\n'));
        assert_eq!(toggled("{not json", 1), "{not json");
    }

    #[test]
    fn once_markers_disarm_a_fault_after_it_fired() {
        let dir = tempfile::tempdir().unwrap();
        let once = OnceDir::new(Some(dir.path().join("markers")), "fake-carla-2000");
        assert!(once.armed("crash-after"));
        once.mark("crash-after");
        assert!(!once.armed("crash-after"));
        assert!(once.armed("crash-file"));
        assert!(dir
            .path()
            .join("markers/fake-carla-2000.crash-after")
            .exists());
        let always = OnceDir::new(None, "x");
        always.mark("crash-after");
        assert!(always.armed("crash-after"));
    }

    #[test]
    fn once_markers_belong_to_a_pair_whatever_port_its_pod_was_given() {
        // Pair 1 crashes on port 2100; pair 2's first pod is then given 2100 too.
        let dir = tempfile::tempdir().unwrap();
        let markers = || Some(dir.path().to_path_buf());
        let first = OnceDir::of_pair(markers(), "fake-evaluator", Some("7-pair1"), 2100);
        first.mark("plant-gpu");
        let second = OnceDir::of_pair(markers(), "fake-evaluator", Some("7-pair2"), 2100);
        assert!(second.armed("plant-gpu"), "pair 2 keeps its own fault");
        let again = OnceDir::of_pair(markers(), "fake-evaluator", Some("7-pair1"), 2200);
        assert!(
            !again.armed("plant-gpu"),
            "pair 1's retry on another port skips it"
        );
        // By hand, with no pair, the port keys the markers as before.
        let by_hand = OnceDir::of_pair(markers(), "fake-carla", None, 2000);
        assert_eq!(
            by_hand.marker("x").unwrap(),
            dir.path().join("fake-carla-2000.x")
        );
        let env = Env::from_pairs([("LB_SUBMISSION_ID", "7"), ("LB_PAIR_ID", "2")]);
        assert_eq!(once_owner(&env).as_deref(), Some("7-pair2"));
        assert_eq!(once_owner(&Env::from_pairs::<_, &str, &str>([])), None);
    }

    #[test]
    fn route_selectors_take_a_number_or_an_id() {
        let s: RouteSelector = "7".parse().unwrap();
        assert!(s.matches(7, 0) && s.matches(7, 3) && !s.matches(6, 0));
        let s: RouteSelector = "RouteScenario_7_rep1".parse().unwrap();
        assert!(s.matches(7, 1) && !s.matches(7, 0));
        assert_eq!(s.label(), "7_rep1");
        assert!("seven".parse::<RouteSelector>().is_err());
        assert!("7_rep".parse::<RouteSelector>().is_err());
    }

    #[test]
    fn evaluator_faults_read_switch_values_and_name_bad_variables() {
        let env = Env::from_pairs([
            ("FAKE_EVALUATOR_GARBAGE", "0"),
            ("FAKE_EVALUATOR_SPAWN_CHILD", "group"),
            ("FAKE_EVALUATOR_SETUP_FAILURE", "yes"),
        ]);
        let f = EvaluatorFaults::from_env(&env).unwrap();
        assert_eq!(f.garbage, None);
        assert_eq!(f.spawn_child, Some(ChildMode::OwnGroup));
        assert!(f.setup_failure);
        let err = EvaluatorFaults::from_env(&Env::from_pairs([("FAKE_EVALUATOR_GARBAGE", "lots")]))
            .unwrap_err();
        assert!(err.to_string().contains("FAKE_EVALUATOR_GARBAGE"), "{err}");
    }
}
