//! One pod is evicted through the Eviction API, and gone, between two Monitor rounds: no
//! round sees it disrupted, yet its route shows as run again in the record and the time lost
//! is counted, from what the API still says (the Job's failures, the replacement's start).
//! FINISHED with the honest scores.

use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, OnceLock};
use std::time::{Duration, SystemTime};

use lb_aws::s3::SubmissionStore;
use local_stack::workloads::Behaviour;
use serde_json::Value;

use super::{held, Begin, Findings, Rehearsal};
use crate::reclaim::{evict_one_until_gone, Reclaim};

/// The least seconds per route: the eviction must land mid-route.
const ROUTE_SECONDS: f64 = 4.0;

/// How long after its pair's last results the pod is evicted (S3's times are whole seconds:
/// between 1 and 3 s): whole seconds of a route run again, which the record counts in whole
/// seconds, and a second at least before the route ends.
const INTO_THE_ROUTE: Duration = Duration::from_secs(2);

/// An eviction no round sees.
#[derive(Default)]
pub struct EvictBetweenRounds {
    /// The cluster (an operator's kubeconfig), the namespace and the submission.
    at: OnceLock<(PathBuf, String, u64)>,
    /// The submission's results in S3.
    store: OnceLock<SubmissionStore>,
    /// A route is under way.
    under_way: AtomicBool,
    /// The pod evicted, with its `DisruptionTarget` reason.
    evicted: Mutex<Option<(String, Option<String>)>>,
    /// Counts the Jobs' failures (retries used) and the disruptions pods show.
    watcher: Mutex<Option<Reclaim>>,
}

impl Rehearsal for EvictBetweenRounds {
    fn expected(&self) -> &'static str {
        "finished"
    }

    fn set_up(&self, behaviour: &mut Behaviour, _once: &Path) {
        behaviour.route_seconds = behaviour.route_seconds.max(ROUTE_SECONDS);
    }

    fn acts(&self) -> bool {
        true
    }

    fn begin(&self, run: &Begin) {
        let at = (
            run.kubeconfig.clone(),
            run.namespace.clone(),
            run.submission,
        );
        let _ = self.at.set(at);
        let _ = self.store.set(run.store.clone());
        // Never cued: it only watches.
        let watcher = Reclaim::spawn(
            run.kubeconfig.clone(),
            run.namespace.clone(),
            run.submission,
            false,
            std::sync::Arc::new(AtomicBool::new(false)),
        );
        *held(&self.watcher) = Some(watcher);
    }

    /// Runs before the round's task: the eviction completes, and the pod is gone, before the
    /// round looks at the cluster.
    fn round_begins(&self, _n: u64) -> bool {
        if !self.under_way.load(Ordering::SeqCst) {
            return false;
        }
        let Some((kubeconfig, namespace, submission)) = self.at.get() else {
            return true;
        };
        let store = self.store.get();
        let evicted = tokio::task::block_in_place(|| {
            tokio::runtime::Handle::current().block_on(async {
                let job = match store {
                    Some(store) => into_a_route(store).await,
                    None => None,
                };
                evict_one_until_gone(kubeconfig, namespace, *submission, (job, None)).await
            })
        });
        let done = evicted.is_some();
        *held(&self.evicted) = evicted;
        done
    }

    fn round_ended(&self, monitor: &Value) {
        // A route's results are in: the next routes are under way.
        if monitor["progress"][0].as_u64() >= Some(1) {
            self.under_way.store(true, Ordering::SeqCst);
        }
    }

    fn finish<'a>(
        &'a self,
        logs: &'a [String],
    ) -> Pin<Box<dyn std::future::Future<Output = Findings> + Send + 'a>> {
        let watcher = held(&self.watcher).take();
        let evicted = held(&self.evicted).clone();
        Box::pin(async move {
            let mut reclaim = crate::reclaim::report(watcher, logs).await;
            if let (Some(report), Some((pod, reason))) = (reclaim.as_mut(), evicted) {
                if let Some(reason) = reason {
                    report.disrupted.insert(pod.clone(), reason);
                }
                report.evicted = vec![pod];
            }
            Findings {
                reclaim,
                ..Findings::default()
            }
        })
    }
}

/// Waits (bounded) until a pair's last results write is [`INTO_THE_ROUTE`] old: its pod is then
/// that far into its next route, whose time a replacement runs again. The Job of that pair
/// (`None`: none came to it in time). The pairs are asked one by one, not all at once: pairs
/// whose routes end a second apart are never all two seconds into theirs.
async fn into_a_route(store: &SubmissionStore) -> Option<u32> {
    for _ in 0..100 {
        let now = SystemTime::now()
            .duration_since(SystemTime::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        let partials = store.partials().await.unwrap_or_default();
        let due = partials.iter().find(|p| {
            p.modified
                .is_some_and(|at| now.saturating_sub(at) == INTO_THE_ROUTE.as_secs())
        });
        if let Some(partial) = due {
            return lb_domain::job::plan::job_of_pair(partial.pair_id);
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    None
}
