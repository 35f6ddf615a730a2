//! The first pair's pod is drained (evicted through the Eviction API) after each Monitor round
//! that saw it running, 8 times: 3 free reclaims, then 5 charged as the platform's, past the
//! Job's `backoffLimit` of 4 with no failure of the participant's. FAILED as the platform's own
//! failure: the participant told it was not its agent's doing, the record's `failed_by`
//! `platform`, the execution `PlatformFailed`.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex};
use std::time::SystemTime;

use local_stack::workloads::Behaviour;
use serde_json::Value;
use tokio::sync::Notify;

use super::{held, Begin, Rehearsal};
use crate::reclaim::evict_one_until_gone;

/// Drains of the pair: the free reclaims, then one more than the Job's `backoffLimit`.
pub const DRAINS: u32 = lb_domain::cluster::disruption::FREE_RECLAIMS_PER_PAIR + 5;

/// Seconds per route: long enough that the drained pair finishes none between two rounds.
const ROUTE_SECONDS: f64 = 8.0;

/// The drains, done beside the run (never inside the executor's hooks, which hold its history).
#[derive(Default)]
pub struct DrainLoop {
    /// A round ended: the drainer looks.
    cue: Arc<Notify>,
    /// When the last Monitor round ended: only a pod that started before it was seen running.
    last_round: Arc<Mutex<Option<SystemTime>>>,
    /// Pods drained so far.
    drained: Arc<AtomicU32>,
    drainer: Mutex<Option<tokio::task::JoinHandle<()>>>,
}

impl Rehearsal for DrainLoop {
    fn expected(&self) -> &'static str {
        "failed"
    }

    fn set_up(&self, behaviour: &mut Behaviour, _once: &Path) {
        behaviour.route_seconds = behaviour.route_seconds.max(ROUTE_SECONDS);
    }

    fn acts(&self) -> bool {
        true
    }

    fn begin(&self, run: &Begin) {
        let drainer = Drainer {
            at: (
                run.kubeconfig.clone(),
                run.namespace.clone(),
                run.submission,
            ),
            cue: self.cue.clone(),
            last_round: self.last_round.clone(),
            drained: self.drained.clone(),
        };
        *held(&self.drainer) = Some(tokio::spawn(drainer.run()));
    }

    /// Done once every drain was.
    fn round_begins(&self, _n: u64) -> bool {
        self.drained.load(Ordering::SeqCst) >= DRAINS
    }

    fn round_ended(&self, _monitor: &Value) {
        *held(&self.last_round) = Some(SystemTime::now());
        self.cue.notify_one();
    }

    fn finish<'a>(
        &'a self,
        _logs: &'a [String],
    ) -> std::pin::Pin<Box<dyn std::future::Future<Output = super::Findings> + Send + 'a>> {
        if let Some(drainer) = held(&self.drainer).take() {
            drainer.abort();
        }
        Box::pin(async { super::Findings::default() })
    }
}

/// What drains the pair, one pod per round that saw it running.
struct Drainer {
    /// The cluster (an operator's kubeconfig), the namespace and the submission.
    at: (PathBuf, String, u64),
    cue: Arc<Notify>,
    last_round: Arc<Mutex<Option<SystemTime>>>,
    drained: Arc<AtomicU32>,
}

impl Drainer {
    async fn run(self) {
        let (kubeconfig, namespace, submission) = &self.at;
        while self.drained.load(Ordering::SeqCst) < DRAINS {
            self.cue.notified().await;
            let Some(seen) = *held(&self.last_round) else {
                continue;
            };
            let only = (Some(0), Some(seen));
            if evict_one_until_gone(kubeconfig, namespace, *submission, only)
                .await
                .is_some()
            {
                let n = self.drained.fetch_add(1, Ordering::SeqCst) + 1;
                cli::outln!("           scenario: pair 1 drained ({n} of {DRAINS})");
            }
        }
    }
}
