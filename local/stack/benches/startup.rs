//! Start-up of the whole local stack (moto, the fake EvalAI, the local Kubernetes API) until
//! each answers; the target is under 5 s. Run with `make bench-stack`.

use std::time::{Duration, Instant};

use fake_evalai::Fixture;
use local_stack::{EvalAi, Stack};

fn main() {
    let timed = std::env::args().any(|a| a == "--bench");
    let runs = if timed { 5 } else { 1 };
    let runtime = tokio::runtime::Runtime::new().expect("runtime");
    let mut times: Vec<Duration> = (0..runs)
        .map(|_| {
            runtime.block_on(async {
                let started = Instant::now();
                let stack = Stack::start_with(
                    EvalAi::Fake(Fixture::default()),
                    Some(local_kube::Config::default()),
                )
                .await
                .expect("the stack starts (run `make venv` for moto)");
                // Each answers a real request before we stop the clock.
                let http = reqwest::Client::new();
                let kube = stack.kube.as_ref().expect("local kube");
                assert!(http
                    .get(format!("{}/version", kube.url()))
                    .send()
                    .await
                    .unwrap()
                    .status()
                    .is_success());
                assert!(http
                    .get(format!("{}/_admin/state", stack.evalai_url))
                    .send()
                    .await
                    .unwrap()
                    .status()
                    .is_success());
                let s3 = lb_aws::s3_client(&stack.sdk);
                s3.list_buckets().send().await.expect("moto answers");
                let elapsed = started.elapsed();
                drop(stack);
                elapsed
            })
        })
        .collect();
    times.sort();
    let median = times[times.len() / 2];
    if timed {
        println!("local stack start-up (moto + fake EvalAI + local Kubernetes API): median {median:?} of {runs}, min {:?}, max {:?} (target < 5 s)", times[0], times[times.len() - 1]);
    } else {
        println!("local stack start-up smoke run: {median:?}");
    }
}
