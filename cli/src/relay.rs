//! Local mode's event-driven functions, fed as the deployment feeds them: the wake queue's
//! event source mapping hands S3's events (delivered by moto through EventBridge) to the
//! wake function, whose task reports go to the embedded executor.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use aws_config::SdkConfig;
use lb_aws::wake::WakeTable;
use local_stack::events::{ExecutorCallbacks, SqsEventSource};
use local_stack::template::Template;
use local_stepfunctions::Executor;

/// The running relays; dropping them stops them.
pub struct Relays {
    tasks: Vec<tokio::task::JoinHandle<()>>,
    /// Messages the wake function handled.
    pub wake_messages: Arc<AtomicU64>,
}

impl Drop for Relays {
    fn drop(&mut self) {
        for task in &self.tasks {
            task.abort();
        }
    }
}

/// Starts the wake queue's mapping against `executor`.
pub async fn spawn(
    sdk: &SdkConfig,
    template: &Template,
    wake_table: &str,
    executor: Executor,
) -> anyhow::Result<Relays> {
    let source = SqsEventSource::from_template(sdk, template, "WakeEventSource").await?;
    let deps = wake::Deps {
        wakes: WakeTable::new(aws_sdk_dynamodb::Client::new(sdk), wake_table),
        callbacks: ExecutorCallbacks(executor),
    };
    let wake_messages = Arc::new(AtomicU64::new(0));
    let counted = wake_messages.clone();
    let wakes = tokio::spawn(async move {
        loop {
            match source.poll(Duration::from_secs(1)).await {
                Ok(Some(batch)) => {
                    let messages = batch.len() as u64;
                    let response = wake::handle_json(batch.event.clone(), &deps).await;
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
    Ok(Relays {
        tasks: vec![wakes],
        wake_messages,
    })
}
