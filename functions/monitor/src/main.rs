#[tokio::main]
async fn main() -> Result<(), lambda_runtime::Error> {
    lb_pipeline::serve::serve(monitor::Deps::from_env()).await
}
