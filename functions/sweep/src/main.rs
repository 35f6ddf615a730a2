// The sweep future nests the SDK and EvalAI calls inside the deadline's wrappers deeper than
// the default.
#![recursion_limit = "256"]

#[tokio::main]
async fn main() -> Result<(), lambda_runtime::Error> {
    lb_pipeline::serve::serve(sweep::Deps::from_env()).await
}
