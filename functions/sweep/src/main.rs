// The sweep future nests the SDK and EvalAI calls inside the deadline's wrappers deeper than
// the default.
#![recursion_limit = "256"]

use lambda_runtime::{run, service_fn, LambdaEvent};

#[tokio::main]
async fn main() -> Result<(), lambda_runtime::Error> {
    lambda_runtime::tracing::init_default_subscriber();
    let deps = sweep::Deps::from_env().await?;
    let deps = &deps;
    run(service_fn(
        move |event: LambdaEvent<serde_json::Value>| async move {
            // The schedule's event carries nothing the sweep needs.
            let _ = event.payload;
            lb_pipeline::clients::within_deadline(&event.context, sweep::handle_json(deps)).await
        },
    ))
    .await
}
