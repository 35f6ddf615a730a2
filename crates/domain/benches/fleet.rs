//! What AWS bills for a deadline rush, on the node model of `lb_domain::capacity::fleet`: the
//! original's way (a whole on-demand g5.12xlarge per Job), ours on-demand and ours Spot first,
//! before and after the levers `infra/` adopts, each lever alone, and the start estimate's
//! error. `make bench-scale` runs it with `--bench` (200 submissions of 40 teams on at most 40
//! nodes, and a long-run rush); `cargo test` runs a small rush with the same checks.

use lb_domain::capacity::cost::InstancePrice;
use lb_domain::capacity::fleet::{
    self, quantile, Miss, Mode, Model, Placement, Report, Rush, Shape,
};

/// One run of the rush: its name, the fleet and the admission.
struct Row {
    name: &'static str,
    model: Model,
    mode: Mode,
    rush: Rush,
}

fn main() {
    let full = std::env::args().any(|a| a == "--bench");
    let settings = include_str!("../../../infra/settings.example.json");
    let prices = lb_domain::settings::Settings::from_json(settings)
        .expect("the example settings")
        .prices;
    let price = prices["g5.12xlarge"];
    let single = prices["g5.4xlarge"];
    let (shape, nodes) = if full {
        (shape(200, 40, 6.0, 20), 40)
    } else {
        (shape(40, 10, 2.0, 20), 10)
    };
    let before = Model::eks_g5(price, nodes);
    print_parameters(&before, &shape);
    let rush = Rush::deadline(shape, 7);
    print_evaluations(&rush);
    let rows = rows(&before, single, &rush);
    let reports: Vec<Report> = rows
        .iter()
        .map(|row| fleet::simulate(&row.model, row.mode, &row.rush))
        .collect();
    println!("{}", fleet::table_header());
    for (row, report) in rows.iter().zip(&reports) {
        println!("{}", report.row(row.name));
        assert_eq!(report.evaluations, shape.submissions, "{}", row.name);
        let billed = report.instance_hours * 3600.0 * f64::from(row.model.gpus_per_node);
        assert!(
            (report.causes.total() - billed).abs() < billed * 1e-3,
            "{}",
            row.name
        );
    }
    keep(&rows, &reports);
    let find = |name: &str| &reports[rows.iter().position(|r| r.name == name).unwrap()];
    let (original, on_demand, spot) = (
        find("original"),
        find("on-demand, levers"),
        find("spot-first, levers"),
    );
    let per_dollar = |r: &Report| f64::from(r.evaluations) / r.dollars;
    let ratio = per_dollar(spot) / per_dollar(on_demand);
    let limit = price.on_demand / price.spot;
    println!(
        "compared       spot-first buys {ratio:.2}x the evaluations per billed dollar of on-demand (the prices' ratio {limit:.2}, target {:.2}), {:.2}x the original's way; idle {:.1}% (target 10%)",
        0.95 * limit,
        per_dollar(spot) / per_dollar(original),
        spot.causes.idle_share() * 100.0
    );
    estimates("on-demand, levers", on_demand);
    estimates("spot-first, levers", spot);
    let floor = estimate_floor(&rush, on_demand);
    assert!(per_dollar(on_demand) > per_dollar(original));
    assert!(ratio >= if full { 0.95 * limit } else { 2.0 }, "{ratio}");
    if full {
        assert!(
            spot.causes.idle_share() <= 0.10,
            "{}",
            spot.causes.idle_share()
        );
        // Why the start estimate's target (25%) is not met for the submissions a team's cap
        // holds: no single estimate can be, on these evaluations' lengths.
        assert!(floor > 0.25, "{floor}");
    }
    assert!(find("on-demand, packing").causes.empty < find("on-demand, as deployed").causes.empty);
    let staying = find("on-demand, no consolidation");
    assert!(on_demand.causes.empty < staying.causes.empty);
    assert!(
        on_demand.causes.run_again <= staying.causes.run_again,
        "moved at route ends"
    );
    assert!(
        find("on-demand, consolidation").causes.empty < find("on-demand, as deployed").causes.empty
    );
    if full {
        long_run(&before);
    }
}

/// Where the rush's runs are kept for the report `make bench-scale` draws after the EvalAI
/// part (`tests/e2e/benches/scale.rs`).
pub fn data_file() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("bench-scale/fleet.json")
}

/// Keeps every run's report, by name.
fn keep(rows: &[Row], reports: &[Report]) {
    let runs: Vec<serde_json::Value> = rows
        .iter()
        .zip(reports)
        .map(|(row, report)| serde_json::json!({"name": row.name, "report": report}))
        .collect();
    let path = data_file();
    let written = std::fs::create_dir_all(path.parent().unwrap())
        .and_then(|()| std::fs::write(&path, serde_json::json!({"runs": runs}).to_string()));
    match written {
        Ok(()) => println!("data           {}", path.display()),
        Err(e) => println!("data           not kept ({}: {e})", path.display()),
    }
}

fn shape(submissions: u32, teams: u32, hours: f64, routes: u32) -> Shape {
    Shape {
        submissions,
        teams,
        hours,
        routes,
        pairs: 4,
        scale: 1.0,
        team_limit: 2,
    }
}

/// The rush run on the fleet as it was deployed, with each lever alone, with those `infra/`
/// adopts, and under stresses of the Spot market.
fn rows(before: &Model, single: InstancePrice, rush: &Rush) -> Vec<Row> {
    let adopted = before.with_levers();
    let row = |name, model: &Model, mode| Row {
        name,
        model: model.clone(),
        mode,
        rush: rush.clone(),
    };
    let packing = Model {
        placement: Placement::Pack,
        ..before.clone()
    };
    let scale_down = Model {
        unneeded_seconds: adopted.unneeded_seconds,
        delay_after_add_seconds: adopted.delay_after_add_seconds,
        ..before.clone()
    };
    let cached = Model {
        carla_pull_seconds: 0,
        ..before.clone()
    };
    let stormy = Model {
        reclaims_per_hour: adopted.reclaims_per_hour * 10.0,
        ..adopted.clone()
    };
    let scarce = Model {
        spot_available: adopted.max_nodes * 3 / 4,
        ..adopted.clone()
    };
    // The same GPUs one to a node (the per-pair CPU and memory fit a g5.4xlarge too).
    let one_gpu = Model {
        gpus_per_node: 1,
        price: single,
        max_nodes: adopted.max_nodes * adopted.gpus_per_node,
        spot_available: adopted.spot_available * adopted.gpus_per_node,
        ..adopted.clone()
    };
    let consolidating = Model {
        consolidate: true,
        ..before.clone()
    };
    let staying = Model {
        consolidate: false,
        ..adopted.clone()
    };
    let lending = Rush {
        lend_idle: true,
        ..rush.clone()
    };
    vec![
        row("original", before, Mode::Original),
        row("on-demand, as deployed", before, Mode::OnDemand),
        row("spot-first, as deployed", before, Mode::SpotFirst),
        row("on-demand, packing", &packing, Mode::OnDemand),
        row("on-demand, scale-down", &scale_down, Mode::OnDemand),
        row("on-demand, CARLA cached", &cached, Mode::OnDemand),
        row("on-demand, consolidation", &consolidating, Mode::OnDemand),
        row("on-demand, no consolidation", &staying, Mode::OnDemand),
        row("spot-first, no consolidation", &staying, Mode::SpotFirst),
        row("on-demand, levers", &adopted, Mode::OnDemand),
        row("spot-first, levers", &adopted, Mode::SpotFirst),
        row("spot-first, 10x reclaims", &stormy, Mode::SpotFirst),
        row("spot-first, 3/4 Spot", &scarce, Mode::SpotFirst),
        row("on-demand, 1-GPU nodes", &one_gpu, Mode::OnDemand),
        row("spot-first, 1-GPU nodes", &one_gpu, Mode::SpotFirst),
        Row {
            name: "spot-first, cap lends",
            model: adopted.clone(),
            mode: Mode::SpotFirst,
            rush: lending,
        },
    ]
}

fn print_parameters(m: &Model, s: &Shape) {
    println!(
        "fleet          g5.12xlarge, {} GPUs, ${}/h on-demand, ${}/h Spot (infra/settings.example.json), at most {} nodes; launch -> Ready {} s; CARLA's image {} s and the participant's {} s ({} and {} GB at {} MB/s), CARLA's start {} s; autoscaler scan {} s, scale-down after {} s unneeded, {} s after a scale-up; Spot reclaims {:.3}% an instance-hour ({:.0}% of a pool a month), {} s notice",
        m.gpus_per_node,
        m.price.on_demand,
        m.price.spot,
        m.max_nodes,
        m.boot_seconds,
        m.carla_pull_seconds,
        m.agent_pull_seconds,
        fleet::CARLA_IMAGE_GB,
        fleet::AGENT_IMAGE_GB,
        fleet::PULL_MB_PER_SECOND,
        m.carla_start_seconds,
        m.step_seconds,
        m.unneeded_seconds,
        m.delay_after_add_seconds,
        m.reclaims_per_hour * 100.0,
        fleet::SPOT_INTERRUPTED_A_MONTH * 100.0,
        m.notice_seconds,
    );
    println!(
        "rush           {} submissions of {} teams (uneven) arriving over {} h, {} routes on {} pairs each, team_limit {}; a route log-normal, median {} s, sigma {} (the results fixtures' 1,188 routes), at most {} s",
        s.submissions,
        s.teams,
        s.hours,
        s.routes,
        s.pairs,
        s.team_limit,
        fleet::ROUTE_MEDIAN_SECONDS,
        fleet::ROUTE_SIGMA,
        fleet::ROUTE_LONGEST_SECONDS,
    );
}

/// How long the rush's evaluations take on their own (their slowest pair's routes): the
/// spread a forecast of a team's next turn cannot know.
fn print_evaluations(rush: &Rush) {
    let mut lengths = evaluation_lengths(rush);
    lengths.sort_unstable();
    let minutes = |q: f64| quantile(&lengths, q) as f64 / 60.0;
    println!(
        "evaluations    their slowest pair's routes: p10 {:.0} min, p50 {:.0} min, p90 {:.0} min",
        minutes(0.1),
        minutes(0.5),
        minutes(0.9)
    );
}

/// Each evaluation's length on its own: its slowest pair's routes, seconds.
fn evaluation_lengths(rush: &Rush) -> Vec<u64> {
    (rush.arrivals.iter())
        .map(|a| {
            a.pairs
                .iter()
                .map(|p| p.iter().sum::<u64>())
                .max()
                .unwrap_or(0)
        })
        .collect()
}

/// The start estimate's p90 error against the median wait, at arrival (all, and by what held
/// the submission) and over every refresh.
fn estimates(name: &str, r: &Report) {
    let mut waits = r.waits.clone();
    waits.sort_unstable();
    let median = quantile(&waits, 0.5) as f64 / 60.0;
    let p90 = |misses: &mut dyn Iterator<Item = i64>| {
        let mut errors: Vec<u64> = misses.map(i64::unsigned_abs).collect();
        errors.sort_unstable();
        (quantile(&errors, 0.9) as f64 / 60.0, errors.len())
    };
    let arrival = |misses: &[Miss], team_cap: Option<bool>| {
        let mut chosen = misses
            .iter()
            .filter(move |m: &&Miss| team_cap.is_none_or(|t| m.team_cap == t))
            .map(|m| m.seconds);
        p90(&mut chosen)
    };
    let (refreshed, _) = p90(&mut r.refresh_errors.iter().copied());
    for (what, misses) in [
        ("forecast, the model's view", &r.arrival_errors),
        ("forecast, the admission table's view", &r.table_errors),
        ("pace (the note before)", &r.pace_errors),
    ] {
        let (all, _) = arrival(misses, None);
        let (capacity, held_by_capacity) = arrival(misses, Some(false));
        let (team, held_by_team) = arrival(misses, Some(true));
        println!(
            "estimate       {name}, {what}: median wait {median:.0} min; p90 error at arrival {all:.0} min ({:.0}% of it, target 25%): {capacity:.0} min for {held_by_capacity} waiting for GPUs, {team:.0} min for {held_by_team} held by their team's cap",
            all / median.max(1e-9) * 100.0,
        );
    }
    println!("estimate       {name}, forecast over every refresh: p90 error {refreshed:.0} min");
}

/// The least p90 error any single estimate can have for a submission its team's cap holds
/// behind two evaluations that just started: it starts when the earlier of them ends. Over
/// every two of the rush's own evaluations (their slowest pair's routes), the best estimate is
/// the median of the earlier end; its p90 error against the median wait of `r`. Returns that
/// share of the median wait.
fn estimate_floor(rush: &Rush, r: &Report) -> f64 {
    let lengths = evaluation_lengths(rush);
    let mut earlier: Vec<u64> = Vec::new();
    for (i, a) in lengths.iter().enumerate() {
        earlier.extend(lengths[i + 1..].iter().map(|b| (*a).min(*b)));
    }
    earlier.sort_unstable();
    let best = quantile(&earlier, 0.5);
    let mut errors: Vec<u64> = earlier.iter().map(|e| e.abs_diff(best)).collect();
    errors.sort_unstable();
    let mut waits = r.waits.clone();
    waits.sort_unstable();
    let median = quantile(&waits, 0.5) as f64;
    let p90 = quantile(&errors, 0.9) as f64;
    println!(
        "estimate floor a submission its team's cap holds behind two evaluations just started starts when the earlier ends: over every two of the rush's evaluations the best single estimate ({:.0} min) misses by p90 {:.0} min, {:.0}% of the median wait",
        best as f64 / 60.0,
        p90 / 60.0,
        p90 / median.max(1.0) * 100.0
    );
    p90 / median.max(1.0)
}

/// Evaluations of a hundred routes (25 a pair, about half a day): the original, ours with the
/// levers, on-demand and Spot first.
fn long_run(before: &Model) {
    let shape = shape(100, 40, 12.0, 100);
    let rush = Rush::deadline(shape, 11);
    let adopted = before.with_levers();
    println!(
        "long run       {} submissions of {} routes on {} pairs arriving over {} h",
        shape.submissions, shape.routes, shape.pairs, shape.hours
    );
    println!("{}", fleet::table_header());
    for (name, model, mode) in [
        ("original", before, Mode::Original),
        ("on-demand, levers", &adopted, Mode::OnDemand),
        ("spot-first, levers", &adopted, Mode::SpotFirst),
    ] {
        println!("{}", fleet::simulate(model, mode, &rush).row(name));
    }
}
