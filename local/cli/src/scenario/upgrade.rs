//! A Kubernetes upgrade with an evaluation in flight, in the order `docs/operations.md` gives:
//! the control plane one minor up in place, then the GPU node group replaced (its new node
//! joins, the old one is cordoned and drained through the Eviction API). The drain's evictions
//! are the platform's free reclaims. FINISHED.

use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

use local_stack::real::Upgrader;
use local_stack::workloads::Behaviour;
use serde::Serialize;
use serde_json::Value;

use super::{held, Begin, Findings, Rehearsal};
use crate::reclaim::Reclaim;

/// The least seconds per route: the upgrade's outage and the drain must land mid-route.
const UPGRADE_ROUTE_SECONDS: f64 = 4.0;

/// The node the node group's update launches (`local_stack::real`'s second node).
const NEW_NODE: &str = "gpu-node-2";

/// What the upgrade did, for the report.
#[derive(Debug, Clone, Serialize)]
pub struct UpgradeReport {
    /// The API server's release before and after.
    pub from: String,
    /// After.
    pub to: String,
    /// How long the API answered nothing.
    pub unavailable_seconds: f64,
    /// The new node joined before the old one was drained.
    pub new_node_joined: bool,
}

/// The control plane upgraded, then the node group replaced.
#[derive(Default)]
pub struct Upgrade {
    watcher: Mutex<Option<Reclaim>>,
    /// The control plane, the new release's binaries, the admin's kubeconfig.
    upgrader: Mutex<Option<(Upgrader, PathBuf, PathBuf)>>,
    cued: AtomicBool,
    done: std::sync::Arc<Mutex<Option<UpgradeReport>>>,
}

impl Rehearsal for Upgrade {
    fn expected(&self) -> &'static str {
        "finished"
    }

    fn needs_real_kube(&self) -> bool {
        true
    }

    fn set_up(&self, behaviour: &mut Behaviour, _once: &Path) {
        behaviour.route_seconds = behaviour.route_seconds.max(UPGRADE_ROUTE_SECONDS);
        behaviour.spare_node = true;
        behaviour.spare_node_joins_later = true;
    }

    fn acts(&self) -> bool {
        true
    }

    fn begin(&self, run: &Begin) {
        *held(&self.watcher) = Some(run.reclaim_watcher());
        // The new release built (or found) before the run starts, not mid-route.
        let ready = run.upgrader.clone().and_then(|u| match u.binaries() {
            Ok(bin) => Some((u, bin, run.kubeconfig.clone())),
            Err(e) => {
                cli::outln!("           scenario: {e}");
                None
            }
        });
        *held(&self.upgrader) = ready;
    }

    /// A route is under way: the control plane is upgraded, the new node joins, then the old
    /// node is drained (once).
    fn round_ended(&self, monitor: &Value) {
        if monitor["progress"][0].as_u64() < Some(1) || self.cued.swap(true, Ordering::SeqCst) {
            return;
        }
        let Some((upgrader, bin, kubeconfig)) = held(&self.upgrader).clone() else {
            cli::outln!("           scenario: no control plane to upgrade (--kube real)");
            return;
        };
        let Some(cue) = held(&self.watcher).as_ref().map(Reclaim::cue) else {
            return;
        };
        let done = self.done.clone();
        tokio::spawn(async move {
            let upgraded = tokio::task::spawn_blocking(move || upgrader.upgrade(&bin)).await;
            let upgraded = match upgraded {
                Ok(Ok(u)) => u,
                Ok(Err(e)) => return cli::outln!("           scenario: {e}"),
                Err(e) => return cli::outln!("           scenario: the upgrade panicked: {e}"),
            };
            cli::outln!(
                "           scenario: control plane {} -> {}, the API out for {:.1} s",
                upgraded.from,
                upgraded.to,
                upgraded.unavailable_seconds
            );
            let joined = super::node_joins(&kubeconfig, NEW_NODE).await;
            cli::outln!(
                "           scenario: the node group's new node {NEW_NODE} joined: {joined}"
            );
            *held(&done) = Some(UpgradeReport {
                from: upgraded.from,
                to: upgraded.to,
                unavailable_seconds: upgraded.unavailable_seconds,
                new_node_joined: joined,
            });
            cue.notify_one();
        });
    }

    fn finish<'a>(
        &'a self,
        logs: &'a [String],
    ) -> Pin<Box<dyn std::future::Future<Output = Findings> + Send + 'a>> {
        let watcher = held(&self.watcher).take();
        Box::pin(async move {
            Findings {
                reclaim: crate::reclaim::report(watcher, logs).await,
                upgrade: held(&self.done).take(),
                ..Findings::default()
            }
        })
    }
}
