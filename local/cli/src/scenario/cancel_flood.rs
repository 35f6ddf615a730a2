//! Another team's five cancelled submissions of 2.4 MB of metadata each fill EvalAI's list of
//! the challenge's submissions (about 12 MB), created after ours arrived; the participant then
//! cancels: the sweep reads the list element by element, finds the cancel and the Jobs end,
//! CANCELLED.

use std::future::Future;
use std::pin::Pin;

use cli::outln;
use serde_json::{json, Value};

use super::cancel::Cancel;
use super::{admin_request, Begin, Findings, Rehearsal};

/// Another team's submissions, each with this much metadata.
const NOISE: usize = 5;
const METADATA_BYTES: usize = 2_400_000;

/// A cancel among another team's huge cancelled submissions.
#[derive(Default)]
pub struct CancelFlood {
    cancel: Cancel,
}

impl Rehearsal for CancelFlood {
    fn expected(&self) -> &'static str {
        "cancelled"
    }

    fn begin(&self, run: &Begin) {
        self.cancel.begin(run);
        let Some(url) = run.fake_evalai.clone() else {
            return;
        };
        tokio::spawn(async move {
            let metadata = json!({"notes": "x".repeat(METADATA_BYTES)});
            for _ in 0..NOISE {
                let new = json!({
                    "challenge_phase": 1,
                    "participant_team": 2,
                    "submitted_image_uri": "123456789012.dkr.ecr.us-west-2.amazonaws.com/team-two:noise",
                    "submission_metadata": metadata,
                });
                let created =
                    admin_request("POST", &url, "/_admin/submissions", &new.to_string()).await;
                let id = created.ok().and_then(|(_, body)| {
                    serde_json::from_str::<Value>(&body).ok()?["id"].as_u64()
                });
                if let Some(id) = id {
                    let path = format!("/_admin/submissions/{id}/cancel");
                    let _ = admin_request("POST", &url, &path, "").await;
                }
            }
            outln!("           scenario: another team cancelled {NOISE} submissions of {METADATA_BYTES} bytes of metadata each");
        });
    }

    fn round_ended(&self, monitor: &Value) {
        self.cancel.round_ended(monitor);
    }

    fn finish<'a>(
        &'a self,
        logs: &'a [String],
    ) -> Pin<Box<dyn Future<Output = Findings> + Send + 'a>> {
        self.cancel.finish(logs)
    }
}
