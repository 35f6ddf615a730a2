//! The node is reclaimed mid-route (a Spot interruption: the managed node group drains it
//! through the Eviction API): every pod is replaced without using a retry, each interrupted
//! route runs again once. FINISHED.

use std::path::Path;
use std::pin::Pin;
use std::sync::Mutex;

use local_stack::workloads::Behaviour;
use serde_json::Value;

use super::{held, Begin, Findings, Rehearsal};
use crate::reclaim::Reclaim;

/// The least seconds per route: the drain must land mid-route.
const SPOT_ROUTE_SECONDS: f64 = 1.5;

/// A Spot node's reclaim.
#[derive(Default)]
pub struct Spot {
    watcher: Mutex<Option<Reclaim>>,
}

impl Rehearsal for Spot {
    fn expected(&self) -> &'static str {
        "finished"
    }

    fn set_up(&self, behaviour: &mut Behaviour, _once: &Path) {
        behaviour.route_seconds = behaviour.route_seconds.max(SPOT_ROUTE_SECONDS);
        behaviour.node_capacity = lb_domain::settings::Capacity::Spot;
        behaviour.spare_node = true;
    }

    fn acts(&self) -> bool {
        true
    }

    fn begin(&self, run: &Begin) {
        *held(&self.watcher) = Some(run.reclaim_watcher());
    }

    /// A route is under way: the node goes now (once; the watcher ignores more cues).
    fn round_ended(&self, monitor: &Value) {
        if monitor["progress"][0].as_u64() >= Some(1) {
            if let Some(watcher) = &*held(&self.watcher) {
                watcher.cue().notify_one();
            }
        }
    }

    fn finish<'a>(
        &'a self,
        logs: &'a [String],
    ) -> Pin<Box<dyn std::future::Future<Output = Findings> + Send + 'a>> {
        let watcher = held(&self.watcher).take();
        Box::pin(async move {
            Findings {
                reclaim: crate::reclaim::report(watcher, logs).await,
                ..Findings::default()
            }
        })
    }
}
