//! The one entry path of every function: tracing, dependencies built once, the event decoded
//! into the function's typed input, one span per invocation naming the function, submission
//! and execution, the invocation's deadline, and a failure reported under its stable name.

use std::future::Future;

use serde::de::DeserializeOwned;
use serde::Serialize;
use serde_json::Value;
use tracing::Instrument;

use crate::{FnError, Result};

/// What an invocation's span says of its input (the submission and the execution, when the
/// input names them).
pub trait Invocation: DeserializeOwned {
    /// The EvalAI submission this invocation is about.
    fn submission_id(&self) -> Option<u64> {
        None
    }
    /// The Step Functions execution that invoked it.
    fn execution(&self) -> Option<&str> {
        None
    }
    /// The leaderboard of its submission: its metrics' `Leaderboard`.
    fn leaderboard(&self) -> Option<lb_domain::results::Leaderboard> {
        None
    }
}

/// An event whose content the function does not read (the sweep's schedule).
impl Invocation for serde::de::IgnoredAny {}

/// A batch of SQS messages (the wake's queue): about many submissions, so no single one.
impl Invocation for aws_lambda_events::event::sqs::SqsEvent {}

/// A function: its typed input and output, and its handler on the dependencies it was given.
pub trait Function {
    /// The function's name, as its folder, binary and `ErrorEquals` messages say it.
    const NAME: &'static str;
    /// What the state machine (or AWS) sends it.
    type Input: Invocation;
    /// What it returns.
    type Output: Serialize;
    /// Handles one decoded input.
    fn handle(&self, input: Self::Input) -> impl Future<Output = Result<Self::Output>>;
}

/// One invocation of `function` on a JSON event: decoded, handled inside its span, encoded,
/// and its metrics written as one document (`crate::metrics`). Lambda, `lbctl invoke` and
/// local mode all call functions through here.
pub async fn call<F: Function>(function: &F, event: Value) -> Result<Value> {
    let started = std::time::Instant::now();
    let input: F::Input = match FnError::decode(F::NAME, event) {
        Ok(input) => input,
        Err(e) => {
            emit(F::NAME, None, started, Default::default());
            return Err(e);
        }
    };
    let leaderboard = input.leaderboard();
    let span = tracing::info_span!(
        "invocation",
        function = F::NAME,
        submission_id = input.submission_id(),
        execution = input.execution(),
    );
    // Boxed: a handler's future nested in these scopes and the runtime's would overflow the
    // compiler's layout depth.
    let work = async {
        let output = Box::pin(function.handle(input)).await;
        if let Err(e) = &output {
            tracing::warn!(error = e.name(), reason = %e.chain(), "the invocation failed");
        }
        FnError::encode(F::NAME, &output?)
    };
    let work = lb_evalai::tally::counted(crate::metrics::gathering(work));
    let ((output, gathered), evalai) = work.instrument(span).await;
    emit(F::NAME, leaderboard, started, (gathered, evalai));
    output
}

/// Writes an invocation's document.
fn emit(
    stage: &str,
    leaderboard: Option<lb_domain::results::Leaderboard>,
    started: std::time::Instant,
    (mut gathered, evalai): (crate::metrics::Gathered, lb_evalai::tally::Tally),
) {
    crate::metrics::invocation(&mut gathered, started.elapsed(), evalai);
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap_or_default();
    let at = now.as_millis() as u64;
    if let Some(doc) = crate::metrics::document(stage, leaderboard, at, &gathered) {
        crate::metrics::write(&doc);
    }
}

/// Runs a function as a Lambda until the runtime stops it: tracing (JSON when the log format
/// says so), `deps` built once at cold start, every event through [`call`] within the
/// invocation's deadline, a failure as the Lambda diagnostic carrying its stable name.
pub async fn serve<F: Function>(
    deps: impl Future<Output = Result<F>>,
) -> std::result::Result<(), lambda_runtime::Error> {
    lambda_runtime::tracing::init_default_subscriber();
    let function = deps.await?;
    let function = &function;
    lambda_runtime::run(lambda_runtime::service_fn(
        move |event: lambda_runtime::LambdaEvent<Value>| async move {
            within_deadline(&event.context, call(function, event.payload)).await
        },
    ))
    .await
}

/// What a handler keeps for itself after its last EvalAI call: raising its error or writing
/// its record.
pub const REPORT_MARGIN: std::time::Duration = std::time::Duration::from_secs(10);

/// The instant a Lambda invocation's EvalAI calls must be done by: its deadline (from the
/// runtime's context, milliseconds since the epoch) less [`REPORT_MARGIN`].
pub fn invocation_deadline(context: &lambda_runtime::Context) -> std::time::Instant {
    let left = context
        .deadline()
        .duration_since(std::time::SystemTime::now())
        .unwrap_or_default()
        .saturating_sub(REPORT_MARGIN);
    std::time::Instant::now() + left
}

/// Runs one invocation's work with its EvalAI calls bounded by the invocation's deadline,
/// and the whole of it (AWS SDK and Kubernetes calls included) cut at half the margin after
/// it: a transient `DeadlineExceeded` the state machine retries (every handler is
/// idempotent), rather than Lambda's own timeout, which no Retry names.
pub async fn within_deadline<T>(
    context: &lambda_runtime::Context,
    work: impl std::future::Future<Output = Result<T, FnError>>,
) -> Result<T, FnError> {
    let deadline = invocation_deadline(context);
    bounded(deadline, deadline + REPORT_MARGIN / 2, work).await
}

async fn bounded<T>(
    evalai_deadline: std::time::Instant,
    cutoff: std::time::Instant,
    work: impl std::future::Future<Output = Result<T, FnError>>,
) -> Result<T, FnError> {
    let work = lb_evalai::within(evalai_deadline, work);
    match tokio::time::timeout_at(tokio::time::Instant::from_std(cutoff), work).await {
        Ok(done) => done,
        Err(_) => {
            tracing::warn!("the invocation's time ran out; the state machine retries it");
            Err(FnError::DeadlineExceeded)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

    #[derive(serde::Deserialize)]
    struct Echo {
        submission: u64,
        fail: bool,
    }
    impl Invocation for Echo {
        fn submission_id(&self) -> Option<u64> {
            Some(self.submission)
        }
    }

    struct Doubler;
    impl Function for Doubler {
        const NAME: &'static str = "doubler";
        type Input = Echo;
        type Output = u64;
        async fn handle(&self, input: Echo) -> Result<u64> {
            if input.fail {
                return Err(FnError::DeadlineExceeded);
            }
            Ok(input.submission * 2)
        }
    }

    #[tokio::test]
    async fn an_event_is_decoded_handled_and_encoded_and_each_failure_keeps_its_name() {
        let ok = call(
            &Doubler,
            serde_json::json!({"submission": 21, "fail": false}),
        )
        .await;
        assert_eq!(ok.unwrap(), serde_json::json!(42));
        let failed = call(&Doubler, serde_json::json!({"submission": 1, "fail": true})).await;
        assert_eq!(failed.unwrap_err().name(), "DeadlineExceeded");
        let undecodable = call(&Doubler, serde_json::json!({"submission": "x"})).await;
        let e = undecodable.unwrap_err();
        assert_eq!(e.name(), "InvalidInput");
        assert!(
            e.chain().starts_with("invalid doubler input: "),
            "{}",
            e.chain()
        );
    }

    #[test]
    fn the_evalai_deadline_leaves_the_handler_its_margin() {
        let mut context = lambda_runtime::Context::default();
        let in_30s = SystemTime::now() + Duration::from_secs(30);
        context.deadline = in_30s.duration_since(UNIX_EPOCH).unwrap().as_millis() as u64;
        let left = invocation_deadline(&context).saturating_duration_since(Instant::now());
        assert!(
            left > Duration::from_secs(19) && left <= Duration::from_secs(20),
            "{left:?}"
        );
        // A deadline already past gives no time at all, not a panic.
        context.deadline = 1;
        assert!(invocation_deadline(&context) <= Instant::now());
    }

    #[tokio::test]
    async fn work_that_outlasts_the_invocation_ends_as_a_transient_deadline_error() {
        let now = Instant::now();
        let stuck = async {
            // An SDK or Kubernetes call that hangs (no EvalAI deadline applies to it).
            tokio::time::sleep(Duration::from_secs(3600)).await;
            Ok::<_, FnError>(())
        };
        let err = bounded(now, now + Duration::from_millis(50), stuck)
            .await
            .unwrap_err();
        assert_eq!(err.name(), "DeadlineExceeded");
        assert!(err.is_transient());
        assert!(FnError::transient_names().contains(&err.name()));
        assert!(now.elapsed() < Duration::from_secs(5));
        let quick = bounded(now, now + Duration::from_secs(5), async {
            Ok::<_, FnError>(7)
        });
        assert_eq!(quick.await.unwrap(), 7);
    }
}
