// The wake future nests the SDK calls inside the deadline's wrappers deeper than the default.
#![recursion_limit = "256"]

use lambda_runtime::{run, service_fn, LambdaEvent};

#[tokio::main]
async fn main() -> Result<(), lambda_runtime::Error> {
    lambda_runtime::tracing::init_default_subscriber();
    let deps = wake::Deps::from_env().await?;
    let deps = &deps;
    run(service_fn(
        move |event: LambdaEvent<serde_json::Value>| async move {
            // Past the deadline the whole batch comes back (the safety net covers the rest).
            lb_pipeline::clients::within_deadline(
                &event.context,
                wake::handle_json(event.payload, deps),
            )
            .await
        },
    ))
    .await
}
