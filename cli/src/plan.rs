//! `lbctl plan`: what a deadline rush would cost on the GPU fleet as `infra/` deploys it, the
//! original's way beside ours, on the node model `make bench-scale` measures
//! (`lb_domain::capacity::fleet`).

use std::path::PathBuf;

use clap::Args;
use lb_domain::capacity::fleet::{self, Mode, Model, Rush, Shape};

use crate::error::CliError;

/// The settings whose prices apply when none are given.
const EXAMPLE_SETTINGS: &str = include_str!("../../infra/settings.example.json");

/// `lbctl plan` options.
#[derive(Debug, Args)]
pub struct Plan {
    /// Submissions in the rush.
    #[arg(long, default_value_t = 200)]
    pub submissions: u32,
    /// Teams submitting them (a few submit most).
    #[arg(long, default_value_t = 40)]
    pub teams: u32,
    /// Hours over which they arrive.
    #[arg(long, default_value_t = 6.0)]
    pub hours: f64,
    /// Routes of an evaluation (the track's `routes`).
    #[arg(long, default_value_t = 20)]
    pub routes: u32,
    /// Simulator-agent pairs of an evaluation (the track's `workers`).
    #[arg(long, default_value_t = 4)]
    pub pairs: u32,
    /// The leaderboard's `team_limit`.
    #[arg(long, default_value_t = 2)]
    pub team_limit: u32,
    /// GPU nodes at most (the cluster stack's GpuNodesMax and SpotGpuNodesMax together).
    #[arg(long, default_value_t = 40)]
    pub nodes: u32,
    /// The share of those nodes the Spot market has (0 to 1).
    #[arg(long, default_value_t = 1.0)]
    pub spot_share: f64,
    /// Route lengths times the leaderboard's typical ones (a slower agent: more).
    #[arg(long, default_value_t = 1.0)]
    pub route_scale: f64,
    /// The GPU instance type, priced by the settings.
    #[arg(long, default_value = "g5.12xlarge")]
    pub instance_type: String,
    /// The operator's settings JSON, for `prices` (default: infra/settings.example.json's).
    #[arg(long)]
    pub settings: Option<PathBuf>,
}

/// Prints the rush's bill for the original's way, ours on-demand and ours Spot first.
pub fn run(args: Plan) -> anyhow::Result<u8> {
    let (original, rush) = planned(&args)?;
    // Ours with the levers infra/ sets; the original on the autoscaler's defaults.
    let model = original.with_levers();
    outln!(
        "{} submissions of {} teams over {} h, {} routes on {} pairs, team_limit {}, at most {} {} nodes ({} GPUs each, ${}/h on-demand, ${}/h Spot), Spot for {:.0}% of them",
        args.submissions,
        args.teams,
        args.hours,
        args.routes,
        args.pairs,
        args.team_limit,
        args.nodes,
        args.instance_type,
        model.gpus_per_node,
        model.price.on_demand,
        model.price.spot,
        args.spot_share * 100.0,
    );
    outln!("{}", fleet::table_header());
    for (name, fleet, mode) in [
        ("the original's way", &original, Mode::Original),
        ("ours, on-demand", &model, Mode::OnDemand),
        ("ours, Spot first", &model, Mode::SpotFirst),
    ] {
        outln!("{}", fleet::simulate(fleet, mode, &rush).row(name));
    }
    outln!("idle columns: percent of billed GPU-seconds; model and parameters: docs/performance.md, \"Billed capacity\"");
    Ok(0)
}

/// The fleet (as deployed before the levers) and the rush `args` describe, checked.
fn planned(args: &Plan) -> Result<(Model, Rush), CliError> {
    let usage = |what: &str| Err(CliError::Usage(what.to_string()));
    if !(1..=10_000).contains(&args.submissions) || args.teams == 0 || args.team_limit == 0 {
        return usage("--submissions must be 1 to 10000, --teams and --team-limit at least 1");
    }
    if !(args.hours.is_finite() && args.hours >= 0.0 && args.hours <= 24.0 * 30.0) {
        return usage("--hours must be 0 to 720");
    }
    if args.pairs == 0 || args.routes < args.pairs || args.routes > 10_000 {
        return usage("--pairs must be at least 1 and --routes at least --pairs (at most 10000)");
    }
    if !(1..=1000).contains(&args.nodes) || !(0.0..=1.0).contains(&args.spot_share) {
        return usage("--nodes must be 1 to 1000 and --spot-share 0 to 1");
    }
    if !(args.route_scale.is_finite() && args.route_scale > 0.0 && args.route_scale <= 100.0) {
        return usage("--route-scale must be above 0 and at most 100");
    }
    let text = match &args.settings {
        Some(path) => std::fs::read_to_string(path)
            .map_err(|e| CliError::Usage(format!("{}: {e}", path.display())))?,
        None => EXAMPLE_SETTINGS.to_string(),
    };
    let settings = lb_domain::settings::Settings::from_json(&text)
        .map_err(|e| CliError::Usage(format!("the settings: {e}")))?;
    let Some(&price) = settings.prices.get(&args.instance_type) else {
        return usage(&format!("the settings price no {}", args.instance_type));
    };
    let gpus = lb_domain::cluster::resources::capacity(&args.instance_type)
        .map(|c| c.gpus)
        .filter(|&g| g > 0)
        .ok_or_else(|| CliError::Usage(format!("{} has no GPU", args.instance_type)))?;
    let mut model = Model {
        gpus_per_node: gpus,
        ..Model::eks_g5(price, args.nodes)
    };
    model.spot_available = (f64::from(args.nodes) * args.spot_share).round() as u32;
    let shape = Shape {
        submissions: args.submissions,
        teams: args.teams,
        hours: args.hours,
        routes: args.routes,
        pairs: args.pairs,
        scale: args.route_scale,
        team_limit: args.team_limit,
    };
    Ok((model, Rush::deadline(shape, 7)))
}
