//! What a rush cost and what its participants saw, and its table.

/// Billed GPU-seconds by what they did.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Causes {
    /// Routes that counted.
    pub work: f64,
    /// Launch to Ready.
    pub boot: f64,
    /// A pod's images and CARLA's start.
    pub pulls: f64,
    /// A node with no pod, waiting for the autoscaler to remove it.
    pub scale_down: f64,
    /// A GPU no pair uses on a node with pods.
    pub empty: f64,
    /// Routes lost to a reclaim (run again) and the notice.
    pub run_again: f64,
}

impl Causes {
    /// Every billed GPU-second.
    pub fn total(&self) -> f64 {
        self.work + self.boot + self.pulls + self.scale_down + self.empty + self.run_again
    }

    /// The share of billed GPU-seconds that ran no route that counted.
    pub fn idle_share(&self) -> f64 {
        let total = self.total();
        if total == 0.0 {
            0.0
        } else {
            1.0 - self.work / total
        }
    }
}

/// What the rush cost and what its participants saw.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Report {
    /// Instance-hours billed (per second, at least 60 s an instance).
    pub instance_hours: f64,
    /// Of them on Spot.
    pub spot_hours: f64,
    /// Dollars billed.
    pub dollars: f64,
    /// GPU-seconds by cause.
    pub causes: Causes,
    /// Evaluations finished.
    pub evaluations: u32,
    /// Nodes launched.
    pub nodes: u32,
    /// Spot nodes reclaimed.
    pub reclaims: u32,
    /// Each submission's wait, arrival to its first pair's routes, seconds.
    pub waits: Vec<u64>,
    /// The estimate made at each submission's arrival against its actual start.
    pub arrival_errors: Vec<Miss>,
    /// The same for every refresh while it waited.
    pub refresh_errors: Vec<i64>,
    /// The queue note's pace estimate at each submission's arrival against its actual start.
    pub pace_errors: Vec<Miss>,
    /// The forecast from the admission table alone (no view of the nodes), the same way.
    pub table_errors: Vec<Miss>,
    /// Seconds from the first arrival to the last evaluation's end.
    pub span: u64,
    /// The fleet every [`MOMENT_SECONDS`], from the first arrival to the last node's end.
    #[serde(default)]
    pub timeline: Vec<Moment>,
}

/// Seconds between two [`Moment`]s of a report's timeline.
pub const MOMENT_SECONDS: u64 = 300;

/// The fleet at one moment of a rush.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Moment {
    /// Seconds since the rush began.
    pub at: u64,
    /// Submissions arrived and not started (held by their team's cap, or their pods waiting).
    pub waiting: u32,
    /// Pairs running a route.
    pub pairs: u32,
    /// Nodes billed.
    pub nodes: u32,
    /// GPUs billed (every GPU of every node billed).
    pub gpus: u32,
}

impl Report {
    /// Dollars per finished evaluation.
    pub fn dollars_per_evaluation(&self) -> f64 {
        self.dollars / f64::from(self.evaluations.max(1))
    }

    /// One line of a table under [`table_header`]: the bill, the idle share by cause (percent
    /// of billed GPU-seconds), the nodes, and what participants waited.
    pub fn row(&self, name: &str) -> String {
        let c = &self.causes;
        let share = |x: f64| x / c.total().max(f64::MIN_POSITIVE) * 100.0;
        let mut waits = self.waits.clone();
        waits.sort_unstable();
        let minutes = |q: f64| quantile(&waits, q) as f64 / 60.0;
        format!(
            "{name:26} {:7.1} {:8.0} {:5} {:7.2} {:5.1}% | {:5.1} {:5.1} {:6.1} {:6.1} {:5.1} | {:6} {:8} {:5.0} m {:5.0} m {:4.1} h",
            self.instance_hours,
            self.dollars,
            self.evaluations,
            self.dollars_per_evaluation(),
            c.idle_share() * 100.0,
            share(c.boot),
            share(c.pulls),
            share(c.scale_down),
            share(c.empty),
            share(c.run_again),
            self.nodes,
            self.reclaims,
            minutes(0.5),
            minutes(0.9),
            self.span as f64 / 3600.0,
        )
    }
}

/// The columns of [`Report::row`].
pub fn table_header() -> String {
    format!(
        "{:26} {:>7} {:>8} {:>5} {:>7} {:>6} | {:>5} {:>5} {:>6} {:>6} {:>5} | {:>6} {:>8} {:>7} {:>7} {:>6}",
        "", "inst-h", "dollars", "evals", "$/eval", "idle", "boot", "pulls", "sc-dn", "empty", "again", "nodes", "reclaims", "wait50", "wait90", "span"
    )
}

/// The value at quantile `q` of `sorted` (nearest rank; the default when empty).
pub fn quantile<T: Copy + Default>(sorted: &[T], q: f64) -> T {
    let rank = (q * sorted.len() as f64).ceil().max(1.0) as usize;
    sorted.get(rank - 1).copied().unwrap_or_default()
}

/// An estimated start against the actual one.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Miss {
    /// Estimated minus actual, seconds.
    pub seconds: i64,
    /// Its team's cap held it when estimated (else it waited for a GPU).
    pub team_cap: bool,
}
