//! The local stack as the emulator tests begin with it: moto and the fake EvalAI started and
//! provisioned from `infra/app.yaml`, bounded in time, failing with what to do.

use std::time::Duration;

use fake_evalai::Fixture;
use lb_domain::settings::Settings;
use local_stack::stack::LOCAL_SETTINGS;
pub use local_stack::{EvalAi, Stack};

/// How long a stack may take to start and provision (moto's first start is the slow part).
const START_LIMIT: Duration = Duration::from_secs(60);

/// The stack with the local settings and the fake EvalAI's default fixture.
pub async fn provisioned() -> (Stack, Settings) {
    provisioned_with(Fixture::default(), LOCAL_SETTINGS).await
}

/// The stack with `settings_json` and a fake EvalAI serving `fixture`.
pub async fn provisioned_with(fixture: Fixture, settings_json: &str) -> (Stack, Settings) {
    tokio::time::timeout(
        START_LIMIT,
        Stack::provisioned(EvalAi::Fake(fixture), settings_json),
    )
    .await
    .expect("the stack starts in time")
    .expect("the stack starts and is provisioned (run `make venv` for moto)")
}
