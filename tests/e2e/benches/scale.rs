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
//! with its final update (urgent). `make bench-scale` runs 200 submissions for 15 (scaled)
//! minutes; without `--bench` (as `cargo test` runs benches) 20 for 5 minutes, with the same
//! assertions.

use std::sync::Arc;
use std::time::{Duration, Instant};

use fake_evalai::{Fixture, NewSubmission};
use lb_aws::budget::BudgetTable;
use lb_domain::submission::SubmissionStatus;
use lb_evalai::{
    AuthScheme, BudgetPolicy, EvalAiClient, EvalAiError, FinalUpdate, HostToken, PartialUpdate,
    RetryPolicy, SubmissionRef, WriteOutcome,
};
use local_stack::stack::{BUDGET_TABLE, LOCAL_SETTINGS};
use local_stack::{EvalAi, Stack};
use time::format_description::well_known::Rfc3339;
use time::OffsetDateTime;

/// Real life / this bench.
const SCALE: f64 = 10.0;
/// EvalAI's limit, in real life.
const LIMIT: u32 = 60;
/// `partial_update_seconds`, in real life.
const INTERVAL: f64 = 20.0;

/// A duration of real life, in the bench's time.
fn scaled(real_seconds: f64) -> Duration {
    Duration::from_secs_f64(real_seconds / SCALE)
}

/// A small deterministic generator (xorshift), so runs are comparable.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
    fn between(&mut self, low: f64, high: f64) -> f64 {
        low + (high - low) * self.next()
    }
}

/// What one submission saw, in real-life seconds.
#[derive(Default)]
struct Seen {
    record_delays: Vec<f64>,
    final_delay: Option<f64>,
    updates: u32,
    skipped: u32,
    /// Records that reached EvalAI only with the final update.
    in_final: u32,
}

async fn submission(
    client: EvalAiClient,
    at: SubmissionRef,
    seed: u64,
    run: Duration,
    started: Instant,
) -> Seen {
    let mut rng = Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
    // A route takes 1 to 4 minutes; the submission ends somewhere in the second half.
    let ends = started + run.mul_f64(rng.between(0.5, 1.0));
    let mut next_record = started + scaled(rng.between(60.0, 240.0));
    let mut pending: Vec<Instant> = Vec::new();
    let mut last_update: Option<Instant> = None;
    let mut retry_at: Option<Instant> = None;
    let mut seen = Seen::default();
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
            next_record += scaled(rng.between(60.0, 240.0));
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
        // The next thing that can happen: a record, or the update's slot.
        let mut wake = next_record.min(ends);
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
    let outcome = client.post_final(at, &done).await;
    assert_eq!(
        outcome.map_err(|e| e.to_string()),
        Ok(WriteOutcome::Written),
        "final update of {}",
        at.submission
    );
    seen.final_delay = Some((Instant::now() - ends).as_secs_f64() * SCALE);
    seen
}

fn quantile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let rank = (q * sorted.len() as f64).ceil().max(1.0) as usize;
    sorted[rank - 1]
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let full = std::env::args().any(|a| a == "--bench");
    let (count, minutes) = if full { (200, 15.0) } else { (20, 5.0) };
    let period = scaled(60.0);
    // The local stack as local mode provisions it from infra/app.yaml (the budget table
    // included), with EvalAI's throttle on at the bench's pace.
    let stack = Stack::start(EvalAi::Fake(Fixture {
        throttle_per_minute: LIMIT,
        throttle_window_secs: period.as_secs(),
        ..Fixture::default()
    }))
    .await
    .unwrap();
    stack.provision(LOCAL_SETTINGS).await.unwrap();
    let server = stack.fake();
    let token = server.host_token().unwrap().to_string();
    let policy = BudgetPolicy::for_limit(LIMIT, period).unwrap();
    let budget = Arc::new(BudgetTable::new(
        aws_sdk_dynamodb::Client::new(&stack.sdk),
        BUDGET_TABLE,
        policy,
    ));

    let started = Instant::now();
    let run = scaled(minutes * 60.0);
    let mut tasks = Vec::new();
    for seed in 0..count {
        let id = server
            .add_submission(NewSubmission {
                challenge_phase: 1,
                participant_team: 1,
                submitted_image_uri: "example/agent:1".into(),
                created_by: None,
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
        let at = SubmissionRef {
            challenge: 1,
            phase: 1,
            submission: id,
        };
        tasks.push(tokio::spawn(submission(client, at, seed + 1, run, started)));
    }
    let mut delays = Vec::new();
    let mut finals = Vec::new();
    let (mut updates, mut skipped, mut in_final) = (0, 0, 0);
    for task in tasks {
        let seen = task.await.unwrap();
        delays.extend(seen.record_delays);
        finals.extend(seen.final_delay);
        updates += seen.updates;
        skipped += seen.skipped;
        in_final += seen.in_final;
    }
    delays.sort_by(f64::total_cmp);
    finals.sort_by(f64::total_cmp);

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

    println!(
        "scale          {count} submissions in flight for {simulated:.1} minutes (time x{SCALE}), partial_update_seconds {INTERVAL}"
    );
    println!(
        "EvalAI         {} requests, {:.1} a minute on average, {busiest} in the busiest sliding minute (target <= {LIMIT}), {throttled} throttled (429)",
        log.len(),
        log.len() as f64 / simulated,
    );
    println!(
        "partial        {updates} updates sent, {skipped} deferred by the budget; record -> partial update p50 {:.0} s, p99 {:.0} s ({} records; {in_final} more only in the final update)",
        quantile(&delays, 0.5),
        quantile(&delays, 0.99),
        delays.len()
    );
    println!(
        "final          end -> final status p50 {:.1} s, max {:.1} s ({} submissions)",
        quantile(&finals, 0.5),
        finals.last().copied().unwrap_or(f64::NAN),
        finals.len()
    );
    println!("admission      not measured: admission (issue 13, item 2) is not built yet");

    assert_eq!(throttled, 0, "EvalAI throttled {throttled} requests");
    assert!(
        busiest <= LIMIT as usize,
        "{busiest} requests in one sliding minute"
    );
    assert_eq!(finals.len(), count as usize);
    assert!(updates > 0);
}
