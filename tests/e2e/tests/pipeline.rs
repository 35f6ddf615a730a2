//! The pipeline's handlers driven in the state machine's order (Intake, Launch, Monitor
//! rounds, Finalize) against the local stack: moto, the fake EvalAI, and the local Kubernetes
//! API running the rendered Jobs with the real sidecar, fake CARLA and fake evaluator.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use aws_sdk_dynamodb::types::AttributeValue;
use lb_pipeline::cluster::Clusters;
use lb_pipeline::payload::{Action, IntakeInput, RunPhase, RunState, SubmissionInfo};
use local_cli::wiring::{Handlers, Pace};
use local_stack::stack::LOCAL_SETTINGS;
use local_stack::workloads::{Behaviour, Binaries};
use local_stack::Stack;
use serde_json::json;

const PARTICIPANT_IMAGE: &str = "123456789012.dkr.ecr.us-west-2.amazonaws.com/team-one:v1";

struct Harness {
    stack: Stack,
    intake: intake::Deps,
    launch: launch::Deps,
    monitor: monitor::Deps,
    finalize: finalize::Deps,
}

/// The rehearsal's wiring of the handlers (`lbctl local run`'s), with sidecar timers for
/// runs of a few short routes and production's Monitor policy.
fn pace() -> Pace {
    Pace {
        timers: lb_jobs::Timers {
            start_wait_seconds: 60,
            end_wait_seconds: 30,
            carla_ready_seconds: 30,
            poll_seconds: 1,
            max_idle_seconds: 60,
            logcopy_period_seconds: 1,
        },
        delete_wait: Duration::from_secs(30),
        never_fits_grace: None,
        history_budget: None,
    }
}

async fn harness(behaviour: Behaviour, unpullable: &[&str]) -> Harness {
    let bins = tokio::task::spawn_blocking(Binaries::build)
        .await
        .unwrap()
        .unwrap();
    let (mut stack, settings) = test_support::stack::provisioned().await;
    // The participant's images are in the registry (Intake pins the Jobs to their digests);
    // an unpullable one is there too, but its repository is one no node can pull from.
    for image in std::iter::once(&PARTICIPANT_IMAGE).chain(unpullable) {
        local_stack::registry::push(&stack.sdk, image)
            .await
            .unwrap();
    }
    let repositories: Vec<String> = unpullable
        .iter()
        .map(|i| i.rsplit_once(':').map_or(*i, |(repo, _)| repo).to_owned())
        .collect();
    let unpullable: Vec<&str> = repositories.iter().map(String::as_str).collect();
    stack
        .start_workloads(&settings, &bins, &behaviour, &unpullable)
        .unwrap();
    let kubeconfig = stack.kubeconfig.clone().unwrap();
    let Handlers {
        intake,
        launch,
        monitor,
        finalize,
    } = Handlers::load(&stack.sdk, kubeconfig, &pace())
        .await
        .unwrap();
    Harness {
        stack,
        intake,
        launch,
        monitor,
        finalize,
    }
}

impl Harness {
    async fn intake(&self, image: &str) -> SubmissionInfo {
        self.intake_as(image, "e2e").await
    }

    async fn intake_as(&self, image: &str, execution: &str) -> SubmissionInfo {
        let message = json!({"challenge_pk": "1", "phase_pk": "1", "submission_pk": 1, "submitted_image_uri": image});
        let out = intake::handle(
            IntakeInput {
                message,
                execution: execution.into(),
            },
            &self.intake,
        )
        .await
        .unwrap();
        assert_eq!(out.action(), Action::Run, "{out:?}");
        out.submission().cloned().unwrap()
    }

    async fn launch(&self, submission: &SubmissionInfo) -> RunState {
        launch::handle(
            launch::LaunchInput {
                submission: submission.clone(),
                queue: None,
                events: None,
                execution: None,
                orchestration: None,
            },
            &self.launch,
        )
        .await
        .unwrap()
    }

    /// Monitor rounds until the run ends, as the Wait/Monitor/Choice loop would (bounded).
    async fn monitor_until_done(
        &self,
        submission: &SubmissionInfo,
        mut run: RunState,
        on_round: impl Fn(u64),
    ) -> RunState {
        let deadline = Instant::now() + Duration::from_secs(180);
        while run.monitor.state == RunPhase::Running {
            assert!(
                Instant::now() < deadline,
                "the run did not end in time: {:?}",
                run.monitor
            );
            tokio::time::sleep(Duration::from_secs(1)).await;
            run = monitor::handle(
                monitor::MonitorInput {
                    submission: submission.clone(),
                    run,
                    execution: None,
                    retries: 0,
                },
                &self.monitor,
            )
            .await
            .unwrap();
            on_round(run.monitor.rounds);
        }
        run
    }

    async fn finalize(
        &self,
        submission: &SubmissionInfo,
        run: &RunState,
    ) -> finalize::FinalizeOutput {
        let state = json!({"intake": {"action": "run", "submission": submission}, "run": run});
        let state = lb_pipeline::payload::ExecutionState::from_value(state).unwrap();
        finalize::handle(finalize::FinalizeInput { state }, &self.finalize)
            .await
            .unwrap()
    }

    /// Finalize in failure mode: a Catch put `error` in the state.
    async fn finalize_after_error(
        &self,
        submission: &SubmissionInfo,
        run: &RunState,
    ) -> finalize::FinalizeOutput {
        let state = json!({"intake": {"action": "run", "submission": submission}, "run": run,
            "error": {"Error": "States.Timeout", "Cause": ""}});
        let state = lb_pipeline::payload::ExecutionState::from_value(state).unwrap();
        finalize::handle(finalize::FinalizeInput { state }, &self.finalize)
            .await
            .unwrap()
    }

    fn evalai_puts(&self) -> usize {
        self.stack
            .fake()
            .requests()
            .iter()
            .filter(|r| !r.admin && r.method == "PUT")
            .count()
    }

    async fn record(&self) -> std::collections::HashMap<String, AttributeValue> {
        aws_sdk_dynamodb::Client::new(&self.stack.sdk)
            .get_item()
            .table_name("leaderboard-20-submissions")
            .key("team_id", AttributeValue::S("1".into()))
            .key("submission_id", AttributeValue::S("1".into()))
            .send()
            .await
            .unwrap()
            .item
            .unwrap()
    }

    async fn cluster_jobs(&self) -> (Vec<lb_cluster::Job>, Vec<lb_cluster::Pod>) {
        lb_cluster::Cluster::from_kubeconfig(self.stack.kubeconfig.as_ref().unwrap(), None)
            .await
            .unwrap()
            .list("1")
            .await
            .unwrap()
    }

    fn evalai_writes(&self, path_part: &str) -> usize {
        self.stack
            .fake()
            .requests()
            .iter()
            .filter(|r| {
                !r.admin && r.method == "PUT" && r.path.contains(path_part) && r.status == 200
            })
            .count()
    }
}

#[tokio::test]
#[ignore = "needs moto"]
async fn a_20_route_4_worker_submission_goes_from_message_to_scores() {
    // A node of 2 GPUs for 4 pairs: two wait for a GPU, and waiting never fails the run.
    let h = harness(
        Behaviour {
            route_seconds: 0.5,
            node_gpus: Some(2),
            ..Behaviour::default()
        },
        &[],
    )
    .await;
    let submission = h.intake(PARTICIPANT_IMAGE).await;
    assert_eq!((submission.routes, submission.workers), (20, 4));
    let record = h.record().await;
    assert_eq!(
        record["submission_status"],
        AttributeValue::S("SUBMITTED".into())
    );

    let run = h.launch(&submission).await;
    assert_eq!(run.jobs, 4, "one Job per pair");
    let subsets: Vec<&str> = run.pairs.iter().map(|p| p.routes.as_str()).collect();
    assert_eq!(subsets, ["0-4", "5-9", "10-14", "15-19"]);
    // Created, not started: the participant's time has not begun.
    assert_eq!(h.stack.fake().submission(1).unwrap().status, "queued");

    // The Jobs as created on the cluster: each pair's agent holds one GPU.
    let (mut jobs, _) = h.cluster_jobs().await;
    jobs.sort_by_key(|j| j.metadata.name.clone());
    assert_eq!(jobs.len(), 4);
    for (i, subset) in subsets.iter().enumerate() {
        let job = serde_json::to_value(&jobs[i]).unwrap();
        assert_eq!(
            job["metadata"]["labels"]["leaderboard.carla.org/submission-id"],
            "1"
        );
        assert_eq!(
            job["spec"]["template"]["metadata"]["labels"]["leaderboard.carla.org/submission-id"],
            "1"
        );
        assert!(job["spec"]["template"]["spec"]["affinity"].is_null());
        let containers = job["spec"]["template"]["spec"]["containers"]
            .as_array()
            .unwrap();
        let agent_spec = containers
            .iter()
            .find(|c| c["name"] == format!("agent-{}", i + 1))
            .unwrap();
        let agent: BTreeMap<String, String> = agent_spec["env"]
            .as_array()
            .unwrap()
            .iter()
            .map(|e| {
                (
                    e["name"].as_str().unwrap().to_string(),
                    e["value"].as_str().unwrap_or_default().to_string(),
                )
            })
            .collect();
        assert_eq!(agent["ROUTES_SUBSET"], *subset);
        assert_eq!(agent["CARLA_PORT"], "2000");
        assert!(
            agent.keys().all(|k| !k.starts_with("AWS_")),
            "no AWS access for the participant"
        );
        // The digest the tag named at Intake, never the tag.
        assert_eq!(agent_spec["image"], submission.image.as_str());
        assert!(submission.image.contains("team-one@sha256:"));
        assert_eq!(agent_spec["resources"]["limits"]["nvidia.com/gpu"], "1");
    }
    // Two pairs run; two wait Pending with the scheduler's own reason.
    let waiting = tokio::time::timeout(Duration::from_secs(30), async {
        loop {
            let (_, pods) = h.cluster_jobs().await;
            let unschedulable = pods
                .iter()
                .filter(|p| {
                    p.status
                        .as_ref()
                        .and_then(|s| s.conditions.as_ref())
                        .is_some_and(|c| {
                            c.iter().any(|c| {
                                c.type_ == "PodScheduled"
                                    && c.reason.as_deref() == Some("Unschedulable")
                                    && c.message.as_deref() == Some(local_kube::INSUFFICIENT_GPU)
                            })
                        })
                })
                .count();
            if pods.len() == 4 && unschedulable == 2 {
                break unschedulable;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await
    .expect("two pods wait for a GPU");
    assert_eq!(waiting, 2);
    let job = serde_json::to_value(&jobs[0]).unwrap();
    assert_eq!(
        job["spec"]["template"]["spec"]["automountServiceAccountToken"],
        false
    );
    let text = job.to_string();
    assert!(!text.contains("host-token"), "no EvalAI token in the Job");

    let run = h.monitor_until_done(&submission, run, |_| {}).await;
    assert_eq!(run.monitor.state, RunPhase::Finished, "{:?}", run.monitor);
    assert!(
        run.monitor.started_at.is_some(),
        "the first pair's start was seen"
    );
    // EvalAI saw `queued` (Launch), then `running` once the pod ran (the Monitor), before any
    // partial update; the Job's name once.
    let progress: Vec<String> = h
        .stack
        .fake()
        .requests()
        .into_iter()
        .filter(|r| !r.admin && r.status == 200 && r.method != "GET")
        .map(|r| {
            let body = r.body.unwrap_or_default();
            format!(
                "{} {}",
                r.method,
                body["submission_status"].as_str().unwrap_or_default()
            )
        })
        .collect();
    assert_eq!(
        progress[..3],
        ["PATCH queued", "PATCH running", "PUT partially_evaluated"],
        "{progress:?}"
    );
    // The Jobs' names, once (queued carried them; running did not repeat them).
    let names = h.stack.fake().submission(1).unwrap().job_name.unwrap();
    assert_eq!(names.len(), 1, "{names:?}");
    assert_eq!(names[0].split(',').count(), 4, "{names:?}");
    let partial_puts = h.evalai_writes("update_partially_evaluated_submission");
    assert!(partial_puts >= 1, "partial results reached EvalAI");
    assert!(
        partial_puts as u64 <= run.monitor.rounds,
        "at most one partial update a round"
    );
    // One more round with nothing new sends nothing.
    let before = h.evalai_writes("update_partially_evaluated_submission");
    let mut again = run.clone();
    again.monitor.state = RunPhase::Running;
    monitor::handle(
        monitor::MonitorInput {
            submission: submission.clone(),
            run: again,
            execution: None,
            retries: 0,
        },
        &h.monitor,
    )
    .await
    .unwrap();
    assert_eq!(
        h.evalai_writes("update_partially_evaluated_submission"),
        before
    );

    let out = h.finalize(&submission, &run).await;
    assert_eq!(
        (out.status.as_str(), out.pipeline_error),
        ("FINISHED", false),
        "{out:?}"
    );
    let evalai = h.stack.fake().submission(1).unwrap();
    assert_eq!(evalai.status, "finished");
    let row = &evalai.leaderboard[0].result;
    assert_eq!(
        row.as_object().unwrap().len(),
        15,
        "the 15 metrics were accepted"
    );
    let record = h.record().await;
    assert_eq!(
        record["submission_status"],
        AttributeValue::S("FINISHED".into())
    );
    for metric in lb_domain::results::METRICS {
        assert!(
            record.contains_key(metric.attribute),
            "{} in the record",
            metric.attribute
        );
    }
    let (jobs, pods) = h.cluster_jobs().await;
    assert!(jobs.is_empty() && pods.is_empty(), "the Jobs were deleted");
}

/// Step Functions as the sweep sees it: the tokens it reported.
#[derive(Default)]
struct Tokens(std::sync::Mutex<Vec<String>>);

impl lb_aws::tasks::Callbacks for Tokens {
    async fn succeed(&self, token: &str, _output: &str) -> lb_aws::Result<lb_aws::tasks::Reported> {
        self.0.lock().unwrap().push(token.to_string());
        Ok(lb_aws::tasks::Reported::Delivered)
    }
}

#[tokio::test]
#[ignore = "needs moto"]
async fn a_participant_cancel_ends_cancelled_with_the_jobs_gone() {
    let slow = Behaviour {
        route_seconds: 2.0,
        ..Behaviour::default()
    };
    let h = harness(slow, &[]).await;
    let submission = h.intake(PARTICIPANT_IMAGE).await;
    let mut run = h.launch(&submission).await;
    let fake = h.stack.fake();
    let dynamo = aws_sdk_dynamodb::Client::new(&h.stack.sdk);
    let config = local_stack::stack::function_config();
    let sweeper = sweep::Deps::load(&h.stack.sdk, &config, Tokens::default())
        .await
        .unwrap();
    // The state machine's loop, with its wait written as WaitForChange writes it, and the
    // sweep's schedule between rounds.
    let mut cancelled_at_round = None;
    while run.monitor.state == RunPhase::Running {
        assert!(run.monitor.rounds < 60, "{:?}", run.monitor);
        run = monitor::handle(
            monitor::MonitorInput {
                submission: submission.clone(),
                run,
                execution: None,
                retries: 0,
            },
            &h.monitor,
        )
        .await
        .unwrap();
        if run.monitor.state != RunPhase::Running {
            break;
        }
        let token = format!("token-{}", run.monitor.rounds);
        let wait = local_stack::integrations::wait_for_change(
            &token,
            submission.submission_id,
            submission.challenge_id,
            run.monitor.seen,
        );
        // A change during the round fails the wait's write: the state machine goes straight
        // to the next round, as here.
        let _ = local_stack::integrations::update_item(&dynamo, wait).await;
        if run.monitor.rounds == 2 {
            fake.cancel(1).unwrap();
            cancelled_at_round = Some(2);
        }
        // Nothing counts changes in this harness (no wake function), so every wait's write
        // holds: the sweep after the cancel finds the execution waiting, flags it and takes
        // that round's token, and the next round confirms the cancel with EvalAI.
        let swept = sweep::handle(&sweeper).await.unwrap();
        let expected: &[u64] = if cancelled_at_round.is_some() {
            &[1]
        } else {
            &[]
        };
        assert_eq!(swept.woken, expected, "round {}", run.monitor.rounds);
        if cancelled_at_round.is_some() {
            assert_eq!(*sweeper.callbacks.0.lock().unwrap(), [token.as_str()]);
            cancelled_at_round = None;
        }
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
    assert_eq!(run.monitor.state, RunPhase::Cancelled);
    assert!(
        run.monitor.rounds <= 4,
        "cancelled within two rounds of the cancel: {}",
        run.monitor.rounds
    );
    let s3 = lb_aws::s3::SubmissionStore::new(
        lb_aws::s3_client(&h.stack.sdk),
        "leaderboard-20-results",
        1,
    );
    assert!(s3
        .markers()
        .await
        .unwrap()
        .iter()
        .any(|m| m == "simulation.cancel"));
    let out = h.finalize(&submission, &run).await;
    assert_eq!(out.status.as_str(), "CANCELLED");
    assert_eq!(h.stack.fake().submission(1).unwrap().status, "cancelled");
    let (jobs, pods) = h.cluster_jobs().await;
    assert!(jobs.is_empty() && pods.is_empty());
}

#[tokio::test]
#[ignore = "needs moto"]
async fn an_image_that_cannot_be_pulled_fails_with_a_message_the_participant_can_act_on() {
    // In the registry, but no node can pull it (the Jobs name it by its digest).
    let bad = "123456789012.dkr.ecr.us-west-2.amazonaws.com/team-two:unpullable";
    let h = harness(Behaviour::default(), &[bad]).await;
    let submission = h.intake(bad).await;
    let bad = submission.image.clone();
    assert!(bad.contains("team-two@sha256:"), "{bad}");
    let run = h.launch(&submission).await;
    let run = h.monitor_until_done(&submission, run, |_| {}).await;
    assert_eq!(run.monitor.state, RunPhase::Failed);
    let reason = run.monitor.reason.clone().unwrap();
    assert!(reason.contains(&bad), "{reason}");
    let out = h.finalize(&submission, &run).await;
    assert_eq!(out.status.as_str(), "FAILED");
    let evalai = h.stack.fake().submission(1).unwrap();
    assert_eq!(evalai.status, "failed");
    assert!(evalai.files.stderr.unwrap_or_default().contains(&bad));
    let (jobs, pods) = h.cluster_jobs().await;
    assert!(jobs.is_empty() && pods.is_empty(), "no orphaned Job");
}

#[tokio::test]
#[ignore = "needs moto"]
async fn finalize_acts_once_and_only_for_the_execution_holding_the_claim() {
    let h = harness(Behaviour::default(), &[]).await;
    let submission = h.intake_as(PARTICIPANT_IMAGE, "exec-1").await;
    let run = h.launch(&submission).await;
    let run = h.monitor_until_done(&submission, run, |_| {}).await;
    // The run ended in failure mode (a Catch), so the participant may resume it.
    assert_eq!(
        h.finalize_after_error(&submission, &run)
            .await
            .status
            .as_str(),
        "FAILED"
    );
    let record = h.record().await;
    let puts = h.evalai_puts();

    // A second Finalize, even one whose own reading says FINISHED, reports what stands and
    // sends nothing: a final status is never replaced (lb-evalai's tests cover `finished` ->
    // `failed` on EvalAI itself).
    for again in [
        h.finalize(&submission, &run).await,
        h.finalize_after_error(&submission, &run).await,
    ] {
        assert_eq!(again.status.as_str(), "FAILED");
    }
    assert_eq!(h.evalai_puts(), puts, "nothing re-sent to EvalAI");
    assert_eq!(h.stack.fake().submission(1).unwrap().status, "failed");
    assert_eq!(h.record().await, record, "the record unchanged");

    // The participant resumes; a new execution claims the submission and launches its Job.
    h.stack.fake().resume(1).unwrap();
    let resumed = h.intake_as(PARTICIPANT_IMAGE, "exec-2").await;
    let new_run = h.launch(&resumed).await;
    let (jobs, _) = h.cluster_jobs().await;
    assert!(!jobs.is_empty(), "the resume's Job runs");
    let puts = h.evalai_puts();
    let status = h.stack.fake().submission(1).unwrap().status;

    // The first execution's Finalize, late (a retry after the resume): it touches nothing.
    let stale = h.finalize_after_error(&submission, &run).await;
    assert_eq!(stale.status.as_str(), "SUPERSEDED", "{stale:?}");
    let (jobs_after, _) = h.cluster_jobs().await;
    assert_eq!(
        jobs_after
            .iter()
            .map(|j| &j.metadata.uid)
            .collect::<Vec<_>>(),
        jobs.iter().map(|j| &j.metadata.uid).collect::<Vec<_>>(),
        "the resume's Job was not deleted"
    );
    assert_eq!(h.evalai_puts(), puts, "nothing posted");
    assert_eq!(h.stack.fake().submission(1).unwrap().status, status);
    let record = h.record().await;
    assert_eq!(record["claimed_by"], AttributeValue::S("exec-2".into()));
    assert_ne!(
        record["submission_status"],
        AttributeValue::S("FAILED".into())
    );

    // The resume's own Finalize ends it.
    let out = h.finalize(&resumed, &new_run).await;
    assert_ne!(out.status.as_str(), "SUPERSEDED");
}

#[tokio::test]
#[ignore = "needs moto"]
async fn a_cluster_api_outage_skips_monitor_rounds_and_the_run_still_finishes() {
    let slow = Behaviour {
        route_seconds: 1.0,
        ..Behaviour::default()
    };
    let h = harness(slow, &[]).await;
    let submission = h.intake(PARTICIPANT_IMAGE).await;
    let run = h.launch(&submission).await;

    // The same Monitor, but the cluster's API refuses connections (a kubeconfig pointing at a
    // closed port): once, the round raised and the run went to Finalize, which needs the same
    // API, and ended FinalizeFailed with the Jobs left behind.
    let kubeconfig = h.stack.kubeconfig.clone().unwrap();
    let text = std::fs::read_to_string(&kubeconfig).unwrap();
    let server = text
        .lines()
        .find_map(|l| l.trim().strip_prefix("server: "))
        .unwrap()
        .to_string();
    let down = kubeconfig.with_file_name("kubeconfig-down");
    std::fs::write(&down, text.replace(&server, "http://127.0.0.1:9")).unwrap();
    let config = local_stack::stack::function_config();
    let unreachable = monitor::Deps::load(&h.stack.sdk, &config, Clusters::kubeconfig(down))
        .await
        .unwrap();
    let mut run = run;
    for _ in 0..3 {
        run = monitor::handle(
            monitor::MonitorInput {
                submission: submission.clone(),
                run,
                execution: None,
                retries: 0,
            },
            &unreachable,
        )
        .await
        .expect("an unreachable cluster skips the round");
        assert_eq!(run.monitor.state, RunPhase::Running);
        assert!(run.monitor.unreachable_since.is_some());
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    // The API is back: the run goes on and finishes.
    let run = h.monitor_until_done(&submission, run, |_| {}).await;
    assert_eq!(run.monitor.state, RunPhase::Finished, "{:?}", run.monitor);
    assert_eq!(run.monitor.unreachable_since, None);
    assert_eq!(
        h.finalize(&submission, &run).await.status.as_str(),
        "FINISHED"
    );

    // An outage longer than the setting ends a run, saying why (0 hours: the first round).
    let mut settings: serde_json::Value = serde_json::from_str(LOCAL_SETTINGS).unwrap();
    settings["leaderboards"]["2.0"]["max_cluster_outage_hours"] = json!(0);
    let mut deps = unreachable;
    deps.clients.settings =
        lb_domain::settings::Settings::from_json(&settings.to_string()).unwrap();
    let mut fresh = run.clone();
    fresh.monitor.state = RunPhase::Running;
    let ended = monitor::handle(
        monitor::MonitorInput {
            submission: submission.clone(),
            run: fresh,
            execution: None,
            retries: 0,
        },
        &deps,
    )
    .await
    .unwrap();
    assert_eq!(ended.monitor.state, RunPhase::Failed);
    let reason = ended.monitor.reason.unwrap();
    assert!(reason.contains("could not be reached"), "{reason}");
}
