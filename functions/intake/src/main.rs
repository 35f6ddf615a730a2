#[tokio::main]
async fn main() -> Result<(), lambda_runtime::Error> {
    lb_pipeline::serve::serve(intake::Deps::from_env()).await
}
