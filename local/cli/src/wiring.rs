//! The handlers of the four task states, loaded once as the deployment's Lambdas load them,
//! with the rehearsal's shorter timers: `lbctl local run` and the end-to-end tests share this
//! wiring, and the task map the embedded executor calls them through.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use aws_config::SdkConfig;
use lb_pipeline::cluster::Clusters;
use lb_pipeline::FnError;
use local_stack::events::LateCallbacks;
use local_stepfunctions::{TaskError, TaskMap};
use serde_json::Value;

/// How the rehearsal shortens what production waits for.
#[derive(Debug, Clone)]
pub struct Pace {
    /// The sidecar's timers in the Jobs Launch creates.
    pub timers: lb_jobs::Timers,
    /// How long Finalize waits for the Jobs to be gone.
    pub delete_wait: Duration,
    /// How long the Monitor waits before it believes the autoscaler's "no node group fits"
    /// (minutes on EKS; local-kube's word is final at once). `None`: production's.
    pub never_fits_grace: Option<Duration>,
    /// The events one execution may take before the run continues as a new one. `None`:
    /// production's.
    pub history_budget: Option<u64>,
}

/// The four handlers, each with its clients built once.
pub struct Handlers {
    /// Intake.
    pub intake: intake::Deps,
    /// Launch.
    pub launch: launch::Deps,
    /// The Monitor.
    pub monitor: monitor::Deps,
    /// Finalize (and the reaper).
    pub finalize: finalize::Deps,
}

impl Handlers {
    /// Loads them against the stack's AWS (`sdk`) and the cluster of `kubeconfig`, as the
    /// local stack's function configuration says, at `pace`.
    pub async fn load(
        sdk: &SdkConfig,
        kubeconfig: PathBuf,
        pace: &Pace,
    ) -> Result<Handlers, FnError> {
        let config = &local_stack::stack::function_config();
        let clusters = || Clusters::kubeconfig(kubeconfig.clone());
        let intake = intake::Deps::load(sdk, config).await?;
        let mut launch = launch::Deps::load(sdk, config, clusters()).await?;
        launch.timers = Some(pace.timers.clone());
        let mut monitor = monitor::Deps::load(sdk, config, clusters()).await?;
        if let Some(grace) = pace.never_fits_grace {
            monitor.policy.never_fits_grace = grace;
        }
        if let Some(budget) = pace.history_budget {
            monitor.history_budget = budget;
        }
        let mut finalize = finalize::Deps::load(sdk, config, clusters()).await?;
        finalize.delete_wait = pace.delete_wait;
        Ok(Handlers {
            intake,
            launch,
            monitor,
            finalize,
        })
    }

    /// The task map of the state machine's four function ARNs, each calling its handler
    /// through the one entry path (`lb_pipeline::serve::call`); Finalize wakes and sends its
    /// callbacks through `late`, bound to the executor once it exists. The Finalize deps, for
    /// the reaper.
    pub fn task_map(self, late: &LateCallbacks) -> (TaskMap, Arc<finalize::Deps<LateCallbacks>>) {
        let intake = Arc::new(self.intake);
        let launch = Arc::new(self.launch);
        let monitor = Arc::new(self.monitor);
        let finalize = Arc::new(self.finalize.with_callbacks(late.clone()));
        let reaper = finalize.clone();
        let tasks = TaskMap::new()
            .with("IntakeFunctionArn", move |v| {
                let deps = intake.clone();
                async move { lambda(lb_pipeline::serve::call(&*deps, v).await) }
            })
            .with("LaunchFunctionArn", move |v| {
                let deps = launch.clone();
                async move { lambda(lb_pipeline::serve::call(&*deps, v).await) }
            })
            .with("MonitorFunctionArn", move |v| {
                let deps = monitor.clone();
                async move { lambda(lb_pipeline::serve::call(&*deps, v).await) }
            })
            .with("FinalizeFunctionArn", move |v| {
                let deps = finalize.clone();
                async move { lambda(lb_pipeline::serve::call(&*deps, v).await) }
            });
        (tasks, reaper)
    }
}

/// A handler's result as Lambda reports it to Step Functions.
fn lambda(result: Result<Value, FnError>) -> Result<Value, TaskError> {
    result.map_err(|e| TaskError::lambda(e.name(), e.chain()))
}
