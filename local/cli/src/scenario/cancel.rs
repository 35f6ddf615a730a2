//! The participant cancels on EvalAI after a Monitor round: CANCELLED once the sweep (or a
//! partial update's own status read) notices, nothing left.

use std::sync::{Mutex, OnceLock};
use std::time::Instant;

use cli::outln;
use serde_json::Value;

use super::{held, Begin, Findings, Rehearsal};

/// A participant's cancel.
#[derive(Default)]
pub struct Cancel {
    /// The fake EvalAI, the submission and the round after which to cancel.
    at: OnceLock<(Option<String>, u64, u64)>,
    cancelled_at: Mutex<Option<Instant>>,
}

impl Rehearsal for Cancel {
    fn expected(&self) -> &'static str {
        "cancelled"
    }

    fn begin(&self, run: &Begin) {
        let _ = self.at.set((
            run.fake_evalai.clone(),
            run.submission,
            run.cancel_after_round,
        ));
    }

    /// The cancel comes after a round (the first read the status on EvalAI): from then on
    /// the cancel sweep notices it, or a partial update's own read.
    fn round_ended(&self, monitor: &Value) {
        let Some((fake, submission, after)) = self.at.get() else {
            return;
        };
        if monitor["rounds"] != *after {
            return;
        }
        held(&self.cancelled_at).get_or_insert_with(Instant::now);
        // The participant's button, on the fake's admin endpoint, without holding up the
        // executor's event callback.
        if let Some(url) = fake {
            let url = format!("{url}/_admin/submissions/{submission}/cancel");
            std::thread::spawn(move || {
                let status = std::process::Command::new("curl")
                    .args(["-s", "-o", "/dev/null", "-X", "POST", &url])
                    .status();
                outln!("           scenario: the participant cancels ({status:?})");
            });
        }
    }

    fn finish<'a>(
        &'a self,
        _logs: &'a [String],
    ) -> std::pin::Pin<Box<dyn std::future::Future<Output = Findings> + Send + 'a>> {
        let cancelled_at = *held(&self.cancelled_at);
        Box::pin(async move {
            Findings {
                cancelled_at,
                ..Findings::default()
            }
        })
    }
}
