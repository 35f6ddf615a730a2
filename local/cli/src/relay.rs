//! Local mode's event-driven functions, fed as the deployment feeds them: the wake queue's
//! event source mapping hands S3's events (delivered by moto through EventBridge) to the
//! wake function, and the sweep runs at its schedule's period (scaled like the state
//! machine's waits); their task reports go to the embedded executor.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use aws_config::SdkConfig;
use cli::outln;
use lb_aws::wake::WakeTable;
use lb_infra::template::Template;
use lb_pipeline::FunctionConfig;
use local_stack::events::{schedule_period, ExecutorCallbacks, SqsEventSource};
use local_stepfunctions::Executor;

/// The running relays; dropping them stops them.
pub struct Relays {
    tasks: Vec<tokio::task::JoinHandle<()>>,
    /// Messages the wake function handled.
    pub wake_messages: Arc<AtomicU64>,
    /// Executions the sweep woke for a cancel.
    pub sweep_wakes: Arc<AtomicU64>,
}

impl Relays {
    /// Stops them: the messages the wake function handled and the sweep's wakes.
    pub fn stop(self) -> (u64, u64) {
        (
            self.wake_messages.load(Ordering::Relaxed),
            self.sweep_wakes.load(Ordering::Relaxed),
        )
    }
}

impl Drop for Relays {
    fn drop(&mut self) {
        for task in &self.tasks {
            task.abort();
        }
    }
}

/// Starts the wake queue's mapping (unless `wake` is false) and the sweep's schedule against
/// `executor`, the sweep counting the GPUs of `clusters`; the schedule's period is multiplied
/// by `time_scale`.
pub async fn spawn(
    sdk: &SdkConfig,
    template: &Template,
    config: &FunctionConfig,
    (executor, clusters): (Executor, lb_pipeline::cluster::Clusters),
    time_scale: f64,
    wake: bool,
) -> anyhow::Result<Relays> {
    let wake_table = config.wake_table()?;
    let source = SqsEventSource::from_template(sdk, template, "WakeEventSource").await?;
    let deps = wake::Deps {
        wakes: WakeTable::new(aws_sdk_dynamodb::Client::new(sdk), wake_table),
        callbacks: ExecutorCallbacks(executor.clone()),
    };
    let wake_messages = Arc::new(AtomicU64::new(0));
    let counted = wake_messages.clone();
    let wakes = tokio::spawn(async move {
        if !wake {
            return;
        }
        loop {
            match source.poll(Duration::from_secs(1)).await {
                Ok(Some(batch)) => {
                    let messages = batch.len() as u64;
                    let response = lb_pipeline::serve::call(&deps, batch.event.clone()).await;
                    if let Err(e) = &response {
                        tracing::warn!(error = %e, "the wake function failed; the batch comes back");
                    }
                    match source.settle(batch, response.as_ref().ok()).await {
                        Ok(_) => {
                            counted.fetch_add(messages, Ordering::Relaxed);
                        }
                        Err(e) => tracing::warn!(error = %e, "settling a wake batch"),
                    }
                }
                Ok(None) => {}
                Err(e) => {
                    tracing::warn!(error = %e, "polling the wake queue");
                    tokio::time::sleep(Duration::from_secs(1)).await;
                }
            }
        }
    });
    let period = schedule_period(template, "SweepSchedule")?.mul_f64(time_scale);
    let mut sweep = sweep::Deps::load(sdk, config, ExecutorCallbacks(executor)).await?;
    sweep.clusters = clusters;
    let sweep_wakes = Arc::new(AtomicU64::new(0));
    let woken = sweep_wakes.clone();
    let sweeps = tokio::spawn(async move {
        let mut ticks = tokio::time::interval(period);
        ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            ticks.tick().await;
            // Through the one entry path, as its schedule invokes it: its metrics are written.
            let done = lb_pipeline::serve::call(&sweep, serde_json::json!({})).await;
            match done.map(|v| serde_json::from_value::<Vec<u64>>(v["woken"].clone())) {
                Ok(Ok(ids)) => {
                    for id in &ids {
                        outln!("           the cancel sweep found submission {id} cancelled on EvalAI and woke its execution");
                    }
                    woken.fetch_add(ids.len() as u64, Ordering::Relaxed);
                }
                Ok(Err(e)) => tracing::warn!(error = %e, "the sweep's answer"),
                Err(e) => tracing::warn!(error = %e.chain(), "the sweep did not finish"),
            }
        }
    });
    Ok(Relays {
        tasks: vec![wakes, sweeps],
        wake_messages,
        sweep_wakes,
    })
}
