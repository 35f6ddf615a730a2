// The wake future nests the SDK calls inside the deadline's wrappers deeper than the default.
#![recursion_limit = "256"]

#[tokio::main]
async fn main() -> Result<(), lambda_runtime::Error> {
    lb_pipeline::serve::serve(wake::Deps::from_env()).await
}
