//! Many submissions in flight against one EvalAI host token: every EvalAI request of every
//! submission goes through the shared budget (`lb_aws::budget` on moto's DynamoDB) to the fake
//! EvalAI with its throttle on, and the bench reports what EvalAI saw (requests in the busiest
//! sliding minute, 429s) and what participants see (record -> partial update, end -> final
//! status).
//!
//! Time runs ten times faster than real life: EvalAI's 60 requests a minute become 60 in 6 s
//! (the fake's throttle window and the budget's period alike), `partial_update_seconds` 20
//! becomes 2 s, and every duration reported is scaled back to real-life seconds. Each
//! submission behaves as its Monitor does: a new record wakes it; it sends a partial update
//! when it has unsent records and its last update is `partial_update_seconds` old; an update
//! the budget refuses is tried again one interval later. Each submission ends at a random time
//! with its final update (urgent).
//!
//! Admission is the pipeline's own (`lb_pipeline::queue::take_turn` on the stack's admission
//! table): submissions from teams of uneven sizes arrive over the first minutes, each is
//! marked `queued`, asks for its turn at Launch and then at each Monitor round while its team
//! holds `team_limit`: when Finalize wakes it (the team's oldest waiting, as
//! `lb_pipeline::queue::wake_team_next` picks it) or at the safety net, and once admitted waits for its pairs' GPUs on a simulated
//! cluster (a FIFO semaphore, as the scheduler takes pending pods oldest first), is marked
//! `running` when it has them, and gives both back when it ends. `make bench-scale` runs 200
//! submissions of 40 teams on 160 GPUs, evaluations of 3 to 8 minutes; without `--bench` (as
//! `cargo test` runs benches) 20 of 8 teams on 12 GPUs, of 1 to 3 minutes, with the same
//! assertions.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use e2e::report::{self, EvalAiRush};
use fake_evalai::{Fixture, NewSubmission};
use lb_aws::admission::AdmissionTable;
use lb_aws::budget::BudgetTable;
use lb_domain::capacity::cost::{PodSeen, Totals};
use lb_domain::capacity::fleet::Rng;
use lb_domain::capacity::queue::{free_places, next_of_team};
use lb_domain::run::schedule::queue_wait;
use lb_domain::submission::SubmissionStatus;
use lb_evalai::{
    AuthScheme, BudgetPolicy, EvalAiClient, EvalAiError, FinalUpdate, HostToken, PartialUpdate,
    RetryPolicy, SubmissionRef, WriteOutcome,
};
use lb_pipeline::payload::SubmissionInfo;
use lb_pipeline::queue::take_turn;
use local_stack::stack::{ADMISSION_TABLE, BUDGET_TABLE, LOCAL_SETTINGS};
use time::format_description::well_known::Rfc3339;
use time::OffsetDateTime;
use tokio::sync::{Notify, Semaphore};

/// Real life / this bench.
const SCALE: f64 = 10.0;

/// Prints a line of the bench's text and keeps it for its report.
macro_rules! say {
    ($lines:expr, $($arg:tt)*) => {{
        let line = format!($($arg)*);
        println!("{line}");
        $lines.push(line);
    }};
}
/// EvalAI's limit, in real life.
const LIMIT: u32 = 60;
/// `partial_update_seconds`, in real life.
const INTERVAL: f64 = 20.0;
/// `team_limit`: evaluations a team holds at once.
const TEAM_LIMIT: u32 = 2;
/// Simulator-agent pairs per submission, a GPU each.
const PAIRS: u32 = 2;
/// The leaderboard whose queue the submissions share.
const LEADERBOARD: &str = "2.0";

/// A duration of real life, in the bench's time.
fn scaled(real_seconds: f64) -> Duration {
    Duration::from_secs_f64(real_seconds / SCALE)
}

/// Uniform between `low` and `high`.
fn between(rng: &mut Rng, low: f64, high: f64) -> f64 {
    low + (high - low) * rng.uniform()
}

/// What one submission saw, in real-life seconds.
#[derive(Default)]
struct Seen {
    /// Arrival -> admitted (its Jobs created).
    admission_wait: f64,
    /// Arrival -> `running` (its GPUs found).
    start_wait: f64,
    /// Its team's holders when it was admitted.
    team_holders: usize,
    /// Urgent writes run again after EvalAI's budget stayed full.
    retries: u32,
    /// Times a released place woke it.
    woken: u32,
    record_delays: Vec<f64>,
    final_delay: Option<f64>,
    updates: u32,
    skipped: u32,
    /// Records that reached EvalAI only with the final update.
    in_final: u32,
    /// The start estimated when it was queued, real-life seconds after its arrival.
    predicted_start: Option<f64>,
    /// Its pods' GPU time, real-life seconds, as the Monitor counts it.
    usage: lb_domain::capacity::cost::Ledger,
    /// Times its pairs were reclaimed.
    reclaims: u32,
}

/// An urgent write as the pipeline makes it: the function fails when EvalAI's budget stays
/// full past its retry budget, and the state machine runs it again (Launch, Monitor and
/// Finalize retry with back-off); `retries` counts those runs.
async fn urgent<F, Fut>(what: &str, retries: &mut u32, mut write: F)
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Result<WriteOutcome, EvalAiError>>,
{
    for attempt in 0..20 {
        match write().await {
            Ok(WriteOutcome::Written) => return,
            // A write EvalAI stored before the client gave up: the next run finds it there.
            Ok(WriteOutcome::AlreadyFinal(_)) if attempt > 0 => return,
            Err(EvalAiError::Throttled(_)) => {
                *retries += 1;
                tokio::time::sleep(scaled(30.0 * f64::from(attempt + 1))).await;
            }
            other => panic!("{what}: {other:?}"),
        }
    }
    panic!("{what}: throttled 20 times");
}

/// Where a submission runs: the EvalAI client, its admission queue and the cluster's GPUs.
struct World {
    client: EvalAiClient,
    queue: Arc<AdmissionTable>,
    gpus: Arc<Semaphore>,
    /// Each submission's parked execution, as the wake table holds its token.
    parked: Arc<BTreeMap<u64, Notify>>,
    /// Shortest and longest evaluation, real-life minutes.
    minutes: (f64, f64),
    /// Spot or on-demand GPUs, and the reclaims.
    capacity: Arc<Capacity>,
    /// The durations (real-life seconds) of the evaluations that ended, most recent last.
    recent: Arc<std::sync::Mutex<Vec<u64>>>,
}

/// The rush's capacity: all on-demand, or Spot first (up to `spot_gpus` in use) then
/// on-demand, where a Spot pair is reclaimed mid-evaluation with `reclaim_chance`.
struct Capacity {
    spot_gpus: usize,
    spot_in_use: std::sync::Mutex<usize>,
    reclaim_chance: f64,
}

impl Capacity {
    /// Whether GPUs just taken are Spot ones (the autoscaler's priority: Spot while it has any).
    fn take(&self, gpus: usize) -> bool {
        let mut in_use = self.spot_in_use.lock().unwrap();
        let spot = *in_use + gpus <= self.spot_gpus;
        if spot {
            *in_use += gpus;
        }
        spot
    }

    fn give_back(&self, gpus: usize, spot: bool) {
        if spot {
            *self.spot_in_use.lock().unwrap() -= gpus;
        }
    }
}

async fn submission(world: World, info: SubmissionInfo, seed: u64, arrival: Duration) -> Seen {
    let World {
        client,
        queue,
        gpus,
        parked,
        minutes,
        capacity,
        recent,
    } = world;
    let at = SubmissionRef {
        challenge: info.challenge_id,
        phase: info.phase_id,
        submission: info.submission_id,
    };
    let mut rng = Rng::new(seed);
    let mut seen = Seen::default();
    tokio::time::sleep(arrival).await;
    let arrived = Instant::now();
    let arrived_ms = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_millis() as u64;
    // Launch: queued on EvalAI, then its turn; the Monitor asks again each round until then.
    let job = format!("lb-{}-0", info.submission_id);
    urgent("mark queued", &mut seen.retries, || {
        client.mark_queued(at, &job)
    })
    .await;
    let give_up = arrived + scaled(6.0 * 3600.0);
    loop {
        let standing = take_turn(&queue, &info, arrived_ms, TEAM_LIMIT)
            .await
            .expect("take a turn");
        if seen.predicted_start.is_none() {
            seen.predicted_start = Some(predict(&queue, &recent, &standing).await);
        }
        if standing.admitted {
            break;
        }
        assert!(
            Instant::now() < give_up,
            "{} never admitted",
            info.submission_id
        );
        let waited = (Instant::now() - arrived).mul_f64(SCALE);
        tokio::select! {
            _ = tokio::time::sleep(scaled(queue_wait(waited).as_secs_f64())) => {}
            _ = parked[&info.submission_id].notified() => seen.woken += 1,
        }
    }
    seen.admission_wait = arrived.elapsed().as_secs_f64() * SCALE;
    seen.team_holders = queue
        .holders(LEADERBOARD, info.team_id)
        .await
        .expect("holders")
        .len();
    // The scheduler: its pairs' GPUs, oldest pending first; `running` once it has them.
    let mut held = gpus
        .clone()
        .acquire_many_owned(PAIRS)
        .await
        .expect("the cluster is up");
    let mut spot = capacity.take(PAIRS as usize);
    seen.start_wait = arrived.elapsed().as_secs_f64() * SCALE;
    urgent("mark running", &mut seen.retries, || {
        client.mark_running(at, &job)
    })
    .await;
    queue
        .mark_running(
            LEADERBOARD,
            info.submission_id,
            arrived_ms / 1000 + started_after(arrived),
        )
        .await
        .expect("mark running in the queue");
    let started = Instant::now();
    let real_now = |at: Instant| (at - arrived).as_secs_f64() * SCALE;
    let kind = |spot: bool| lb_domain::capacity::cost::NodeKind {
        instance_type: "g5.12xlarge".into(),
        capacity: if spot {
            lb_domain::capacity::cost::CapacityType::Spot
        } else {
            lb_domain::capacity::cost::CapacityType::OnDemand
        },
    };
    let mut pod_started = started;
    let mut last_record = started;
    let mut ends = started + scaled(60.0 * between(&mut rng, minutes.0, minutes.1));
    // A Spot pair may be reclaimed once, somewhere in its evaluation.
    let mut reclaim_at = (spot && rng.uniform() < capacity.reclaim_chance)
        .then(|| started + (ends - started).mul_f64(rng.uniform()));
    let mut next_record = started + scaled(between(&mut rng, 60.0, 240.0));
    let mut pending: Vec<Instant> = Vec::new();
    let mut last_update: Option<Instant> = None;
    let mut retry_at: Option<Instant> = None;
    let partial = PartialUpdate {
        result: "[]".into(),
        stdout: "routes done so far".into(),
        metadata: "{}".into(),
    };
    loop {
        let now = Instant::now();
        if now >= ends {
            break;
        }
        if now >= next_record {
            pending.push(next_record);
            last_record = next_record;
            next_record += scaled(between(&mut rng, 60.0, 240.0));
        }
        if reclaim_at.is_some_and(|t| now >= t) {
            // The node goes: the pods stop, the route in progress is lost, and new pods wait
            // for GPUs again (behind whoever waits now) and run that route again.
            reclaim_at = None;
            seen.reclaims += 1;
            let pods: Vec<PodSeen> = (0..PAIRS)
                .map(|job| pod_span(job, (real_now(pod_started), real_now(now)), spot, true))
                .collect();
            let results_at = (0..PAIRS)
                .map(|job| (job, real_now(last_record) as u64))
                .collect();
            seen.usage.account(
                &pods,
                &kinds(&kind),
                (&results_at, &BTreeMap::new()),
                real_now(now) as u64,
            );
            capacity.give_back(PAIRS as usize, spot);
            drop(held);
            held = gpus
                .clone()
                .acquire_many_owned(PAIRS)
                .await
                .expect("the cluster is up");
            spot = capacity.take(PAIRS as usize);
            let resumed = Instant::now();
            let lost = now - last_record;
            ends += (resumed - now) + lost;
            next_record += (resumed - now) + lost;
            pod_started = resumed;
            continue;
        }
        let due = last_update.is_none_or(|t| now >= t + scaled(INTERVAL))
            && retry_at.is_none_or(|t| now >= t);
        if !pending.is_empty() && due {
            match client.post_partial(at, &partial).await {
                Ok(WriteOutcome::Written) => {
                    let sent = Instant::now();
                    for record in pending.drain(..) {
                        seen.record_delays
                            .push((sent - record).as_secs_f64() * SCALE);
                    }
                    seen.updates += 1;
                    last_update = Some(sent);
                    retry_at = None;
                }
                Err(EvalAiError::OverBudget) => {
                    seen.skipped += 1;
                    retry_at = Some(Instant::now() + scaled(INTERVAL));
                }
                other => panic!("partial update of {}: {other:?}", at.submission),
            }
        }
        // The next thing that can happen: a record, a reclaim, or the update's slot.
        let mut wake = next_record.min(ends).min(reclaim_at.unwrap_or(ends));
        if !pending.is_empty() {
            let slot = [last_update.map(|t| t + scaled(INTERVAL)), retry_at]
                .into_iter()
                .flatten()
                .max()
                .unwrap_or(now);
            wake = wake.min(slot);
        }
        tokio::time::sleep_until(tokio::time::Instant::from_std(wake.max(Instant::now()))).await;
    }
    let done = FinalUpdate {
        status: SubmissionStatus::Finished,
        result: "[]".into(),
        stdout: "all routes done".into(),
        stderr: String::new(),
        metadata: "{}".into(),
    };
    seen.in_final = pending.len() as u32;
    let what = format!("final update of {}", at.submission);
    urgent(&what, &mut seen.retries, || client.post_final(at, &done)).await;
    seen.final_delay = Some((Instant::now() - ends).as_secs_f64() * SCALE);
    // Finalize: the Jobs go (their GPUs free), the team's place last, and the team's next
    // waiting submission is woken.
    let pods: Vec<PodSeen> = (0..PAIRS)
        .map(|job| pod_span(job, (real_now(pod_started), real_now(ends)), spot, false))
        .collect();
    let end = real_now(ends) as u64;
    seen.usage.account(
        &pods,
        &kinds(&kind),
        (&BTreeMap::new(), &BTreeMap::new()),
        end,
    );
    // The track's pace as Finalize records it: from the first pair's start to now, its final
    // write done (what a place takes to turn over, the budget's delays included).
    recent
        .lock()
        .unwrap()
        .push((started.elapsed().as_secs_f64() * SCALE) as u64);
    capacity.give_back(PAIRS as usize, spot);
    drop(held);
    queue
        .release(LEADERBOARD, info.submission_id, info.team_id)
        .await
        .expect("release");
    let entries = queue.entries(LEADERBOARD).await.expect("the queue");
    let held = queue
        .holders(LEADERBOARD, info.team_id)
        .await
        .expect("the holders")
        .len();
    for next in next_of_team(&entries, info.team_id, free_places(TEAM_LIMIT, held)) {
        // NB: notify_one keeps the wake for a waiter between two polls, as the wake table's
        // count does for an execution between two waits.
        parked[&next.submission_id].notify_one();
    }
    seen
}

/// The pace estimate the queue note falls back on (`lb_pipeline::queue::note`) at its
/// arrival: its team's turn when its team's cap holds it, else the submissions ahead over the
/// evaluations running; from the durations of the latest that ended. (The note's forecast
/// plays the queue out over hours of routes: the fleet bench measures it in simulated time.)
async fn predict(
    queue: &AdmissionTable,
    recent: &std::sync::Mutex<Vec<u64>>,
    standing: &lb_pipeline::queue::Standing,
) -> f64 {
    let entries = queue.entries(LEADERBOARD).await.expect("the queue");
    let running = entries
        .iter()
        .filter(|e| e.state == lb_domain::capacity::queue::EntryState::Running)
        .count() as u32;
    let latest: Vec<u64> = recent.lock().unwrap().iter().rev().copied().collect();
    let estimate = match standing.hold {
        lb_domain::capacity::queue::Hold::TeamLimit { limit } => {
            lb_domain::capacity::queue::estimate_team_turn(standing.team_ahead, limit, &latest)
        }
        lb_domain::capacity::queue::Hold::Capacity => {
            lb_domain::capacity::queue::estimate_start(standing.ahead, running, &latest)
        }
    };
    // Nothing running yet (the rush's first minutes): the estimate is "soon".
    estimate.map_or(0.0, |e| e.middle() as f64)
}

/// Seconds since `arrived`, on the clock the queue's entries keep (the bench's).
fn started_after(arrived: Instant) -> u64 {
    arrived.elapsed().as_secs()
}

/// One pair's pod from `start` to `end` (real-life seconds since its arrival) on a node of its
/// capacity (named by it), reclaimed or ended.
fn pod_span(job: u32, (start, end): (f64, f64), spot: bool, reclaimed: bool) -> PodSeen {
    PodSeen {
        job,
        started_at: start as u64,
        ended_at: Some(end as u64),
        gpus: 1,
        node: Some(if spot { "spot" } else { "on-demand" }.into()),
        disruption: reclaimed.then_some(lb_domain::cluster::disruption::Disruption::Reclaim),
        succeeded: !reclaimed,
    }
}

/// The node kinds of [`pod_span`]'s nodes.
fn kinds(
    kind: &dyn Fn(bool) -> lb_domain::capacity::cost::NodeKind,
) -> BTreeMap<String, lb_domain::capacity::cost::NodeKind> {
    BTreeMap::from([
        ("spot".into(), kind(true)),
        ("on-demand".into(), kind(false)),
    ])
}

/// Places the shared budget granted in all: the sum of every window's count.
async fn granted(client: &aws_sdk_dynamodb::Client) -> u64 {
    let (mut total, mut start) = (0, None);
    loop {
        let page = client
            .scan()
            .table_name(BUDGET_TABLE)
            .set_exclusive_start_key(start)
            .send()
            .await
            .expect("the budget table scans");
        for item in page.items() {
            let requests = item.get("requests").and_then(|v| v.as_n().ok());
            total += requests.and_then(|n| n.parse::<u64>().ok()).unwrap_or(0);
        }
        match page.last_evaluated_key {
            Some(key) if !key.is_empty() => start = Some(key),
            _ => return total,
        }
    }
}

fn quantile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let rank = (q * sorted.len() as f64).ceil().max(1.0) as usize;
    sorted[rank - 1]
}

/// How the rush's GPUs are bought.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Mode {
    /// Every GPU on-demand.
    OnDemand,
    /// Spot first, up to this share of the GPUs (what the Spot market has), then on-demand;
    /// each Spot evaluation is reclaimed once mid-run with this chance.
    SpotThenOnDemand {
        spot_share: f64,
        reclaim_chance: f64,
    },
}

impl Mode {
    fn name(self) -> &'static str {
        match self {
            Mode::OnDemand => "on-demand",
            Mode::SpotThenOnDemand { .. } => "spot-then-on-demand",
        }
    }
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let full = std::env::args().any(|a| a == "--bench");
    // One Spot evaluation in ten loses a route to a reclaim: far more than AWS's Spot Instance
    // Advisor's worst bucket (more than 20% of a pool's instances interrupted in a month, well
    // under 0.1% an hour) gives an evaluation of a few hours, so the run-again cost is not
    // flattered. Three quarters of the GPUs from Spot: a g5 pool seldom has a whole rush's.
    let spot = Mode::SpotThenOnDemand {
        spot_share: 0.75,
        reclaim_chance: 0.1,
    };
    let (on_demand, mut text) = rush(full, Mode::OnDemand).await;
    let (spot, more) = rush(full, spot).await;
    text.extend(more);
    write_report(&[on_demand, spot], &text);
}

/// The HTML report of both parts: the fleet bench's runs (kept by `cargo bench -p lb-domain
/// --bench fleet`, which `make bench-scale` runs first) and this part's rushes.
fn write_report(rushes: &[EvalAiRush], text: &[String]) {
    let dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("bench-scale");
    let mut charts = Vec::new();
    let mut page_text = Vec::new();
    match std::fs::read_to_string(dir.join("fleet.json")) {
        Ok(json) => {
            let data: serde_json::Value =
                serde_json::from_str(&json).expect("the fleet bench's data");
            let runs: Vec<(String, lb_domain::capacity::fleet::Report)> = data["runs"]
                .as_array()
                .into_iter()
                .flatten()
                .map(|run| {
                    let name = run["name"].as_str().unwrap_or_default().to_owned();
                    let report = serde_json::from_value(run["report"].clone()).expect("a report");
                    (name, report)
                })
                .collect();
            page_text.push(lb_domain::capacity::fleet::table_header());
            page_text.extend(runs.iter().map(|(name, r)| r.row(name)));
            charts.extend(report::fleet_charts(&runs));
        }
        Err(e) => println!("report         without the fleet's charts (run its bench first: {e})"),
    }
    page_text.extend(text.iter().cloned());
    let window = scaled(60.0).as_millis() as i128;
    charts.extend(report::evalai_charts(rushes, window, SCALE, LIMIT));
    let page = report::page(
        "The deadline rush (make bench-scale)",
        &page_text.join("\n"),
        &charts,
    );
    let path = dir.join("report.html");
    let written = std::fs::create_dir_all(&dir).and_then(|()| std::fs::write(&path, page));
    match written {
        Ok(()) => println!(
            "report         {} ({} charts)",
            path.display(),
            charts.len()
        ),
        Err(e) => println!("report         not written ({}: {e})", path.display()),
    }
}

/// One rush on the capacity `mode` buys.
async fn rush(full: bool, mode: Mode) -> (EvalAiRush, Vec<String>) {
    let mut lines = Vec::new();
    // (submissions, teams, GPUs, minutes over which they arrive, evaluation minutes)
    let (count, teams, gpus, arriving, minutes): (u32, u32, usize, f64, (f64, f64)) = if full {
        (200, 40, 160, 15.0, (3.0, 8.0))
    } else {
        (20, 8, 12, 2.0, (1.0, 3.0))
    };
    let period = scaled(60.0);
    // The local stack as local mode provisions it from infra/app.yaml (the budget and
    // admission tables included), with EvalAI's throttle on at the bench's pace.
    let fixture = Fixture {
        throttle_per_minute: LIMIT,
        throttle_window_secs: period.as_secs(),
        ..Fixture::with_teams(teams as usize)
    };
    let (stack, _) = test_support::stack::provisioned_with(fixture, LOCAL_SETTINGS).await;
    let server = stack.fake();
    let token = server.host_token().unwrap().to_string();
    let policy = BudgetPolicy::for_limit(LIMIT, period).unwrap();
    let dynamo = aws_sdk_dynamodb::Client::new(&stack.sdk);
    // The budget on a moto of its own: one moto process answers every request in turn, and
    // the queue's hundreds of polls would otherwise hold grants past their window (6 real
    // seconds at this speed), which a table answering in milliseconds never does.
    let (budget_stack, _) =
        test_support::stack::provisioned_with(Fixture::default(), LOCAL_SETTINGS).await;
    let budget_dynamo = aws_sdk_dynamodb::Client::new(&budget_stack.sdk);
    let budget = Arc::new(BudgetTable::new(
        budget_dynamo.clone(),
        BUDGET_TABLE,
        policy,
    ));
    let queue = Arc::new(AdmissionTable::new(dynamo, ADMISSION_TABLE));
    let cluster = Arc::new(Semaphore::new(gpus));
    let capacity = Arc::new(match mode {
        Mode::OnDemand => Capacity {
            spot_gpus: 0,
            spot_in_use: Default::default(),
            reclaim_chance: 0.0,
        },
        Mode::SpotThenOnDemand {
            spot_share,
            reclaim_chance,
        } => Capacity {
            spot_gpus: (gpus as f64 * spot_share) as usize,
            spot_in_use: Default::default(),
            reclaim_chance,
        },
    });
    // The track's durations before the rush (its recent evaluations), spread over its range.
    let before: Vec<u64> = (0..lb_domain::capacity::queue::RECENT_DURATIONS)
        .map(|i| {
            let share = i as f64 / (lb_domain::capacity::queue::RECENT_DURATIONS - 1) as f64;
            (60.0 * (minutes.0 + (minutes.1 - minutes.0) * share)) as u64
        })
        .collect();
    let recent = Arc::new(std::sync::Mutex::new(before));
    let prices = lb_domain::settings::Settings::from_json(LOCAL_SETTINGS)
        .expect("the local settings")
        .prices;

    let started = Instant::now();
    let mut arrivals = Rng::new(0x5EED);
    let mut worlds = Vec::new();
    let mut team_sizes = vec![0u32; teams as usize];
    for seed in 0..u64::from(count) {
        // Uneven teams, as on a real leaderboard: a few submit most (u^1.25 favours low ids).
        let team = (arrivals.uniform().powf(1.25) * f64::from(teams)) as u64 + 1;
        team_sizes[team as usize - 1] += 1;
        let id = server
            .add_submission(NewSubmission {
                challenge_phase: 1,
                participant_team: team,
                submitted_image_uri: "example/agent:1".into(),
                created_by: None,
                submission_metadata: None,
            })
            .unwrap()
            .id;
        let client = EvalAiClient::new(
            &server.url(),
            &HostToken::new(token.as_str()),
            AuthScheme::Bearer,
            RetryPolicy {
                budget: Duration::from_secs(60),
                ..RetryPolicy::default()
            },
        )
        .unwrap()
        .with_budget(budget.clone());
        let info = SubmissionInfo {
            challenge_id: 1,
            phase_id: 1,
            submission_id: id,
            team_id: team,
            team_name: format!("team {team}"),
            leaderboard: LEADERBOARD.parse().unwrap(),
            track: "SENSORS".into(),
            image: "example/agent:1".into(),
            routes: 20,
            workers: PAIRS,
            resuming: false,
            execution: format!("bench-{id}"),
            arrived_ms: None,
            submitted_at: 0,
        };
        // Arrivals in submission-id order (EvalAI's), spread over the first minutes.
        let arrival = scaled(arriving * 60.0 * seed as f64 / f64::from(count));
        worlds.push((client, info, seed + 1, arrival));
    }
    let parked: Arc<BTreeMap<u64, Notify>> = Arc::new(
        worlds
            .iter()
            .map(|(_, info, ..)| (info.submission_id, Notify::new()))
            .collect(),
    );
    let mut tasks = Vec::new();
    for (client, info, seed, arrival) in worlds {
        let world = World {
            client,
            queue: queue.clone(),
            gpus: cluster.clone(),
            parked: parked.clone(),
            minutes,
            capacity: capacity.clone(),
            recent: recent.clone(),
        };
        tasks.push(tokio::spawn(submission(world, info, seed, arrival)));
    }
    let mut delays = Vec::new();
    let mut finals = Vec::new();
    let mut admission = Vec::new();
    let mut start = Vec::new();
    let mut most_held = 0;
    let (mut updates, mut skipped, mut in_final, mut retries, mut woken) = (0, 0, 0, 0, 0);
    let (mut usage, mut reclaims, mut estimate_errors) = (Totals::default(), 0, Vec::new());
    for task in tasks {
        let seen = task.await.unwrap();
        let totals = seen.usage.summary(&prices);
        usage.gpu_seconds += totals.gpu_seconds;
        usage.spot += totals.spot;
        usage.run_again += totals.run_again;
        reclaims += seen.reclaims;
        if let Some(predicted) = seen.predicted_start {
            estimate_errors.push((predicted - seen.start_wait).abs());
        }
        delays.extend(seen.record_delays);
        finals.extend(seen.final_delay);
        admission.push(seen.admission_wait);
        start.push(seen.start_wait);
        most_held = most_held.max(seen.team_holders);
        updates += seen.updates;
        skipped += seen.skipped;
        in_final += seen.in_final;
        retries += seen.retries;
        woken += seen.woken;
    }
    delays.sort_by(f64::total_cmp);
    finals.sort_by(f64::total_cmp);
    admission.sort_by(f64::total_cmp);
    start.sort_by(f64::total_cmp);
    team_sizes.sort_unstable_by(|a, b| b.cmp(a));

    // What EvalAI saw: arrival times from its own log, the busiest sliding (scaled) minute.
    let log: Vec<_> = server.requests().into_iter().filter(|r| !r.admin).collect();
    let throttled = log.iter().filter(|r| r.status == 429).count();
    let mut arrivals: Vec<i128> = log
        .iter()
        .filter_map(|r| OffsetDateTime::parse(&r.time, &Rfc3339).ok())
        .map(|t| t.unix_timestamp_nanos() / 1_000_000)
        .collect();
    arrivals.sort_unstable();
    let window = period.as_millis() as i128;
    let mut busiest = 0;
    let mut first = 0;
    for (last, &t) in arrivals.iter().enumerate() {
        while arrivals[first] <= t - window {
            first += 1;
        }
        busiest = busiest.max(last + 1 - first);
    }
    let simulated = started.elapsed().as_secs_f64() * SCALE / 60.0;

    say!(
        lines,
        "scale          {count} submissions of {teams} teams (largest {:?}) on {gpus} GPUs, {PAIRS} pairs each, for {simulated:.1} minutes (time x{SCALE}), partial_update_seconds {INTERVAL}, team_limit {TEAM_LIMIT}",
        &team_sizes[..3.min(team_sizes.len())]
    );
    say!(
        lines,
        "EvalAI         {} requests, {:.1} a minute on average, {busiest} in the busiest sliding minute (target <= {LIMIT}), {throttled} throttled (429)",
        log.len(),
        log.len() as f64 / simulated,
    );
    // A grant that comes back after its window closed is asked for again: its place is counted
    // and never sent. At 10x speed a window is 6 real seconds, so a slow table (moto, one busy
    // process serialising every request) wastes places a real one, answering in milliseconds
    // of a 60-second window, would not.
    let granted = granted(&budget_dynamo).await;
    say!(
        lines,
        "budget         {granted} places granted for {} requests sent: {} counted and never sent (a grant back after its window closed is asked for again)",
        log.len(),
        granted as i64 - log.len() as i64,
    );
    say!(
        lines,
        "urgent         {retries} queued/running/final writes run again after the budget stayed full past the client's minute (the state machine's retry)"
    );
    say!(
        lines,
        "partial        {updates} updates sent, {skipped} deferred by the budget; record -> partial update p50 {:.0} s, p99 {:.0} s ({} records; {in_final} more only in the final update)",
        quantile(&delays, 0.5),
        quantile(&delays, 0.99),
        delays.len()
    );
    say!(
        lines,
        "final          end -> final status p50 {:.1} s, max {:.1} s ({} submissions)",
        quantile(&finals, 0.5),
        finals.last().copied().unwrap_or(f64::NAN),
        finals.len()
    );
    let in_minutes = |q: f64, v: &[f64]| quantile(v, q) / 60.0;
    say!(
        lines,
        "admission      arrival -> admitted p50 {:.1} min, p99 {:.1} min, max {:.1} min; most places a team held {most_held} (limit {TEAM_LIMIT}); {woken} turns taken on a released place's wake",
        in_minutes(0.5, &admission),
        in_minutes(0.99, &admission),
        admission.last().copied().unwrap_or(f64::NAN) / 60.0,
    );
    say!(
        lines,
        "start          arrival -> running (its GPUs free) p50 {:.1} min, p99 {:.1} min, max {:.1} min",
        in_minutes(0.5, &start),
        in_minutes(0.99, &start),
        start.last().copied().unwrap_or(f64::NAN) / 60.0,
    );

    estimate_errors.sort_by(f64::total_cmp);
    let hours = |s: u64| s as f64 / 3600.0;
    say!(
        lines,
        "GPUs ({})  {} finished; {:.1} pod GPU-hours as the Monitor counts them ({:.1} on Spot), {:.2} run again after {reclaims} reclaims (what AWS bills: the fleet bench)",
        mode.name(),
        finals.len(),
        hours(usage.gpu_seconds),
        hours(usage.spot),
        hours(usage.run_again),
    );
    say!(
        lines,
        "estimate       the pace estimate (the note's fallback): predicted -> actual start error p50 {:.1} min, p90 {:.1} min (arrival -> running p50 {:.1} min)",
        quantile(&estimate_errors, 0.5) / 60.0,
        quantile(&estimate_errors, 0.9) / 60.0,
        quantile(&start, 0.5) / 60.0,
    );
    if let Mode::SpotThenOnDemand { .. } = mode {
        assert!(usage.spot > 0, "no Spot GPU was used");
        assert!(usage.run_again < usage.gpu_seconds / 10, "{usage:?}");
    } else {
        assert_eq!((usage.spot, usage.run_again), (0, 0));
    }
    assert_eq!(throttled, 0, "EvalAI throttled {throttled} requests");
    assert!(
        busiest <= LIMIT as usize,
        "{busiest} requests in one sliding minute"
    );
    assert_eq!(finals.len(), count as usize);
    assert!(
        most_held <= TEAM_LIMIT as usize,
        "a team held {most_held} places"
    );
    assert!(updates > 0);
    let minutes = |v: &[f64]| v.iter().map(|s| s / 60.0).collect();
    let seen = EvalAiRush {
        name: mode.name().into(),
        requests_ms: arrivals,
        admission: minutes(&admission),
        start: minutes(&start),
    };
    (seen, lines)
}
