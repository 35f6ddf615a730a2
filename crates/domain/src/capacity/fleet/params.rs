//! The model's parameters and where they come from: route lengths, images, the Spot market,
//! the fleet as deployed and with its levers, and a deadline rush.

use super::{Arrival, Model, Placement, Rush};

/// A route's wall-clock seconds on the leaderboard: log-normal with the median and shape of
/// the 1,188 routes of the results fixtures (`duration_system`: median 1,138 s, mean 1,746 s,
/// p90 3,935 s), at most the longest of them (15,467 s).
pub const ROUTE_MEDIAN_SECONDS: f64 = 1138.0;
/// The log-normal's shape: `sqrt(2 ln(mean / median))`.
pub const ROUTE_SIGMA: f64 = 0.925;
/// The longest route of the fixtures.
pub const ROUTE_LONGEST_SECONDS: f64 = 15_467.0;

/// Seconds to pull and unpack an image of `gigabytes` at `megabytes_per_second`.
pub fn pull_seconds(gigabytes: f64, megabytes_per_second: f64) -> u64 {
    (gigabytes * 1000.0 / megabytes_per_second).round() as u64
}

impl Model {
    /// g5.12xlarge GPU groups on EKS as `infra/` deployed them before the levers: the images
    /// pulled on every new node, the autoscaler's default scale-down, the default scheduler.
    /// `docs/performance.md` gives each number's source.
    pub fn eks_g5(price: crate::capacity::cost::InstancePrice, max_nodes: u32) -> Model {
        Model {
            gpus_per_node: 4,
            price,
            boot_seconds: 150,
            carla_pull_seconds: pull_seconds(CARLA_IMAGE_GB, PULL_MB_PER_SECOND),
            agent_pull_seconds: pull_seconds(AGENT_IMAGE_GB, PULL_MB_PER_SECOND),
            carla_start_seconds: 60,
            placement: Placement::Spread,
            unneeded_seconds: 600,
            delay_after_add_seconds: 600,
            reclaims_per_hour: spot_rate(SPOT_INTERRUPTED_A_MONTH),
            notice_seconds: 120,
            max_nodes,
            spot_available: max_nodes,
            step_seconds: 10,
            consolidate: false,
        }
    }
}

impl Model {
    /// The fleet with the levers `infra/` sets: the packing scheduler profile
    /// (`infra/k8s/scheduler.yaml`, named by the Job templates), the autoscaler's prompt
    /// scale-down (`infra/k8s/cluster-autoscaler.yaml`) and consolidation at route ends (the
    /// sweep and the Monitor, `ConsolidateNodes` in `infra/app.yaml`).
    pub fn with_levers(&self) -> Model {
        Model {
            placement: Placement::Pack,
            unneeded_seconds: 120,
            delay_after_add_seconds: 0,
            consolidate: true,
            ..self.clone()
        }
    }
}

/// CARLA's leaderboard image, compressed gigabytes.
pub const CARLA_IMAGE_GB: f64 = 12.0;
/// A participant's image (CUDA, PyTorch, weights), compressed gigabytes.
pub const AGENT_IMAGE_GB: f64 = 10.0;
/// Pull and unpack throughput from ECR in the region, megabytes a second.
pub const PULL_MB_PER_SECOND: f64 = 60.0;
/// The share of a Spot pool's instances interrupted in a month: above the Spot Instance
/// Advisor's worst band (">20%").
pub const SPOT_INTERRUPTED_A_MONTH: f64 = 0.3;

/// Interruptions per instance-hour when `share` of instances are interrupted in a month.
pub fn spot_rate(share: f64) -> f64 {
    -(1.0 - share).ln() / (365.25 * 24.0 / 12.0)
}

impl Rush {
    /// A deadline rush: `submissions` of `teams` (uneven: a few submit most) arriving evenly
    /// over `hours`, each of `routes` routes split over `pairs` pairs, route lengths drawn
    /// from the leaderboard's (`ROUTE_*`, each `scale` times as long: a slow agent).
    pub fn deadline(shape: Shape, seed: u64) -> Rush {
        let mut rng = Rng::new(seed);
        let arrivals = (0..shape.submissions)
            .map(|k| {
                let team = (rng.uniform().powf(1.25) * f64::from(shape.teams)) as u64 + 1;
                let at =
                    (shape.hours * 3600.0 * f64::from(k) / f64::from(shape.submissions)) as u64;
                let pairs = (0..shape.pairs)
                    .map(|p| {
                        let (first, next) = (
                            p * shape.routes / shape.pairs,
                            (p + 1) * shape.routes / shape.pairs,
                        );
                        (first..next)
                            .map(|_| route(&mut rng, shape.scale))
                            .collect()
                    })
                    .collect();
                Arrival { at, team, pairs }
            })
            .collect();
        // The track's recent pairs: as many again, drawn the same way.
        let history = (0..shape.submissions * shape.pairs)
            .map(|_| {
                (0..shape.routes / shape.pairs)
                    .map(|_| route(&mut rng, shape.scale))
                    .sum()
            })
            .collect();
        Rush {
            arrivals,
            team_limit: shape.team_limit,
            refresh_seconds: 600,
            seed,
            history,
            lend_idle: false,
        }
    }
}

/// The track's evaluations before the rush: its history's pairs taken an evaluation's worth at
/// a time, each as long as its slowest.
pub(super) fn history_durations(rush: &Rush) -> Vec<u64> {
    let pairs = rush.arrivals.first().map_or(1, |a| a.pairs.len()).max(1);
    rush.history
        .chunks(pairs)
        .map(|c| c.iter().copied().max().unwrap_or(0))
        .collect()
}

/// One route's seconds, `scale` times the leaderboard's.
fn route(rng: &mut Rng, scale: f64) -> u64 {
    let seconds = rng.log_normal(ROUTE_MEDIAN_SECONDS, ROUTE_SIGMA);
    (seconds.min(ROUTE_LONGEST_SECONDS) * scale) as u64
}

/// The shape of a [`Rush::deadline`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Shape {
    /// Submissions in the rush.
    pub submissions: u32,
    /// Teams submitting.
    pub teams: u32,
    /// Hours over which they arrive.
    pub hours: f64,
    /// Routes per submission.
    pub routes: u32,
    /// Pairs per submission.
    pub pairs: u32,
    /// Route lengths times the leaderboard's.
    pub scale: f64,
    /// `team_limit`.
    pub team_limit: u32,
}

/// A small deterministic generator (xorshift64), so runs are comparable.
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    /// A generator from `seed` (any value).
    pub fn new(seed: u64) -> Self {
        Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
    }

    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Log-normal with this median and shape (Box-Muller).
    pub fn log_normal(&mut self, median: f64, sigma: f64) -> f64 {
        let (u, v) = (1.0 - self.uniform(), self.uniform());
        let normal = (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos();
        median * (sigma * normal).exp()
    }
}
