use lambda_runtime::{run, service_fn, LambdaEvent};

#[tokio::main]
async fn main() -> Result<(), lambda_runtime::Error> {
    lambda_runtime::tracing::init_default_subscriber();
    let deps = intake::Deps::from_env().await?;
    let deps = &deps;
    run(service_fn(
        move |event: LambdaEvent<serde_json::Value>| async move {
            // Every EvalAI retry stops in time for the handler to report (crates/evalai), and
            // nothing runs past the invocation's deadline.
            lb_pipeline::clients::within_deadline(
                &event.context,
                intake::handle_json(event.payload, deps),
            )
            .await
        },
    ))
    .await
}
