//! EvalAI host API client (`docs/reference/evalai.md`): the only code that talks to EvalAI.
//!
//! The server protects nothing: a write lands on a cancelled or finished submission and
//! silently undoes it. So every write here reads the submission first and never revives a
//! cancelled one; a 5xx or timeout is followed by a read to learn what really happened;
//! throttling is honoured through `Retry-After`; every call has a bounded total time; every
//! request takes from the shared budget ([`budget`]) first.

pub mod budget;
mod model;
mod retry;
pub mod stream;
pub mod tally;

pub use budget::{Admission, AdmissionFuture, Budget, BudgetPolicy, Priority};
pub use model::{validate_result, Submission, MAX_TEAM_NAME};
pub use retry::{within, RetryPolicy};

use std::sync::Arc;
use std::time::{Duration, Instant};

use lb_domain::run::finalize::{self, Posted};
use lb_domain::submission::{SubmissionInfo, SubmissionStatus};
use reqwest::{Method, StatusCode};
use serde_json::{json, Value};
use tracing::{info, warn};

use retry::Attempts;

/// The host's EvalAI auth token. It is never printed, serialized or logged.
#[derive(Clone)]
pub struct HostToken(String);

impl HostToken {
    /// Wraps a token read from Secrets Manager.
    pub fn new(token: impl Into<String>) -> Self {
        HostToken(token.into())
    }

    /// The value, for tests that compare it; the client is the only other reader.
    pub fn expose(&self) -> &str {
        &self.0
    }
}

impl std::fmt::Debug for HostToken {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("HostToken(***)")
    }
}

/// How the token goes in `Authorization`, as the settings name it.
pub use lb_domain::settings::AuthScheme;

/// Result alias of this crate.
pub type Result<T, E = EvalAiError> = std::result::Result<T, E>;

/// What went wrong talking to EvalAI; `name()` is what the state machine matches.
#[derive(Debug, thiserror::Error)]
pub enum EvalAiError {
    /// The client could not be built (bad base URL).
    #[error("invalid EvalAI configuration: {0}")]
    Config(String),
    /// 401/403: the token is wrong, expired, not a host's, or the account unverified.
    #[error("EvalAI refused our credentials ({status}): {message}")]
    Unauthorized {
        /// HTTP status.
        status: u16,
        /// EvalAI's `detail`/`error`.
        message: String,
    },
    /// 404: no such submission.
    #[error("EvalAI has no submission `{0}`")]
    NotFound(u64),
    /// 400 (or a redirect, which means a wrong URL): the request itself is wrong.
    #[error("EvalAI rejected the request ({status}): {message}")]
    Rejected {
        /// HTTP status.
        status: u16,
        /// EvalAI's message.
        message: String,
    },
    /// Still throttled when the retry budget ran out.
    #[error("EvalAI kept throttling us (429) for {0:?}")]
    Throttled(Duration),
    /// A routine request found this window of the shared budget spent (not sent).
    #[error("the shared EvalAI budget has no room for routine requests until the next window")]
    OverBudget,
    /// 5xx, timeouts or connection failures until the retry budget ran out.
    #[error("EvalAI unavailable after {attempts} attempts: {last}")]
    Unavailable {
        /// Attempts made.
        attempts: u32,
        /// The last failure.
        last: String,
    },
    /// EvalAI answered 200 with something we cannot trust.
    #[error("EvalAI sent an invalid response: {0}")]
    InvalidResponse(String),
    /// We refused to send a payload EvalAI would reject or store as garbage.
    #[error("refusing to send an invalid result to EvalAI: {0}")]
    InvalidResult(String),
    /// The write was acknowledged but a read-back shows another status.
    #[error("EvalAI did not keep our update: expected `{expected}`, found `{found}`")]
    NotConfirmed {
        /// What we wrote.
        expected: SubmissionStatus,
        /// What the read-back said.
        found: SubmissionStatus,
    },
}

lb_domain::error_names!(EvalAiError {
    Config => "EvalAiConfig";
    Unauthorized => "EvalAiUnauthorized";
    NotFound => "SubmissionNotFound";
    Rejected => "EvalAiRejected";
    // Our own throttle is retried exactly like EvalAI's.
    Throttled | OverBudget => "EvalAiThrottled" [transient];
    Unavailable => "EvalAiUnavailable" [transient];
    InvalidResponse => "EvalAiInvalidResponse";
    InvalidResult => "InvalidResult";
    NotConfirmed => "EvalAiNotConfirmed" [transient];
});

/// What a guarded write did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WriteOutcome {
    /// The update is on EvalAI.
    Written,
    /// Not sent: the submission is `cancelled` (the participant's word is final).
    Cancelled,
    /// Not sent: the submission already has a final status this update must not undo.
    AlreadyFinal(SubmissionStatus),
}

/// The domain's word for what a final update did, and back: the same three answers.
impl From<Posted> for WriteOutcome {
    fn from(posted: Posted) -> Self {
        match posted {
            Posted::Written => WriteOutcome::Written,
            Posted::Cancelled => WriteOutcome::Cancelled,
            Posted::AlreadyFinal(status) => WriteOutcome::AlreadyFinal(status),
        }
    }
}

impl From<WriteOutcome> for Posted {
    fn from(outcome: WriteOutcome) -> Self {
        match outcome {
            WriteOutcome::Written => Posted::Written,
            WriteOutcome::Cancelled => Posted::Cancelled,
            WriteOutcome::AlreadyFinal(status) => Posted::AlreadyFinal(status),
        }
    }
}

/// A final update (PUT `update_submission`).
#[derive(Debug, Clone, PartialEq)]
pub struct FinalUpdate {
    /// `finished`, `failed` or `cancelled`.
    pub status: SubmissionStatus,
    /// The `result` JSON text (a list of splits); required for `finished`.
    pub result: String,
    /// Shown to the participant.
    pub stdout: String,
    /// Shown to the participant.
    pub stderr: String,
    /// Host-only metadata (a JSON text).
    pub metadata: String,
}

/// A partial update (PUT `update_partially_evaluated_submission`, `partially_evaluated`).
#[derive(Debug, Clone, PartialEq)]
pub struct PartialUpdate {
    /// The `result` JSON text.
    pub result: String,
    /// Shown to the participant.
    pub stdout: String,
    /// Host-only metadata (a JSON text).
    pub metadata: String,
}

/// The most of a participant-facing text (stdout, stderr) one update carries. EvalAI keeps
/// them as files, but the proxy in front of it refuses large bodies (413) and the page shows
/// the start anyway; the complete files stay in S3 with the submission's results.
pub const MAX_TEXT_BYTES: usize = 256 * 1024;

/// The most of the host-only metadata one update carries; a larger one is replaced by a note.
pub const MAX_METADATA_BYTES: usize = 256 * 1024;

/// The largest response we read from EvalAI (a page of a submissions list is far smaller).
pub const MAX_RESPONSE_BYTES: usize = 8 * 1024 * 1024;

/// The largest element of a submission list kept: an element is a few hundred bytes of ours
/// plus what its participant wrote (metadata, a method's description). A larger one is skipped
/// and logged, and the rest of the list stands.
pub const MAX_LIST_ELEMENT_BYTES: usize = 256 * 1024;

/// The most a submission list is read to, element by element in constant memory.
pub const MAX_LIST_BYTES: usize = 512 * 1024 * 1024;

/// What replaces stdout when EvalAI refused even the bounded final update.
pub const MINIMAL_STDOUT: &str = "The evaluation's output was too large for EvalAI to accept; \
the scores above are complete, and the challenge hosts keep the full output.";

/// `text` cut to at most `max` bytes, keeping its start (verdict and scores come first), with
/// a visible note saying so.
pub fn bounded_text(text: &str, max: usize) -> std::borrow::Cow<'_, str> {
    lb_domain::job::logtail::cut_with_note(text, max, || {
        format!(
            "\n\n[... cut here: the first {max} of {} bytes are shown; the complete output is \
             kept with the submission's results]\n",
            text.len()
        )
    })
}

/// The metadata JSON text, or a small JSON note in its place when it is over `max` bytes.
pub fn bounded_metadata(text: &str, max: usize) -> std::borrow::Cow<'_, str> {
    if text.len() <= max {
        return std::borrow::Cow::Borrowed(text);
    }
    std::borrow::Cow::Owned(
        json!({
            "cut": format!(
                "the metadata ({} bytes) is over the {max} bytes sent to EvalAI; the complete \
                 file is kept with the submission's results",
                text.len()
            )
        })
        .to_string(),
    )
}

/// Where the submission lives on EvalAI (the server cross-checks none of these: we must).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SubmissionRef {
    /// Challenge id (URL).
    pub challenge: u64,
    /// Phase id (body).
    pub phase: u64,
    /// Submission id (body).
    pub submission: u64,
}

impl From<&SubmissionInfo> for SubmissionRef {
    fn from(submission: &SubmissionInfo) -> Self {
        SubmissionRef {
            challenge: submission.challenge_id,
            phase: submission.phase_id,
            submission: submission.submission_id,
        }
    }
}

/// What one request asks of the budget.
#[derive(Debug, Clone, Copy)]
struct Ask {
    priority: Priority,
    /// This request and those its call needs right after it.
    headroom: u32,
    /// The places it takes: one, its whole call's (taken at once), or none (taken with the
    /// call's first request).
    places: u32,
}

impl Ask {
    /// One request, granted if the window has room for `headroom`.
    fn new(priority: Priority, headroom: u32) -> Self {
        Ask {
            priority,
            headroom,
            places: 1,
        }
    }

    /// The first of a call's `requests`, taking the places of all of them at once.
    fn whole(priority: Priority, requests: u32) -> Self {
        Ask {
            priority,
            headroom: requests,
            places: requests,
        }
    }

    /// A request whose place its call's first request took.
    fn paid(priority: Priority) -> Self {
        Ask {
            priority,
            headroom: 0,
            places: 0,
        }
    }

    /// The same request sent again: a retry takes its own place.
    fn again(self) -> Self {
        Ask::new(self.priority, 1)
    }
}

/// The EvalAI client; build once per cold start.
#[derive(Debug, Clone)]
pub struct EvalAiClient {
    http: reqwest::Client,
    base: String,
    /// Marked sensitive: `Debug` prints `Sensitive`, and hyper keeps it out of HPACK tables.
    auth: reqwest::header::HeaderValue,
    policy: RetryPolicy,
    /// Shared with every other function; `None`: unlimited (a tool run by hand).
    budget: Option<Arc<dyn Budget>>,
    /// Of the reads (`submission`, `submissions_with_status`); writes have their own.
    priority: Priority,
}

impl EvalAiClient {
    /// A client for `base_url` (e.g. `https://eval.ai`), authenticated as the host.
    pub fn new(
        base_url: &str,
        token: &HostToken,
        scheme: AuthScheme,
        policy: RetryPolicy,
    ) -> Result<Self> {
        let base = base_url.trim_end_matches('/').to_string();
        if !(base.starts_with("https://") || base.starts_with("http://")) {
            return Err(EvalAiError::Config(format!(
                "EvalAI URL `{}` must start with https:// or http://",
                base.escape_debug()
            )));
        }
        if token.0.is_empty() || token.0.chars().any(|c| c.is_whitespace() || c.is_control()) {
            return Err(EvalAiError::Config(
                "the EvalAI host token is empty or holds whitespace".into(),
            ));
        }
        let http = reqwest::Client::builder()
            // NB: a redirect here always means a wrong URL (a missing trailing slash); following
            // it would turn a PUT into a bodiless retry or a GET (reference §1).
            .redirect(reqwest::redirect::Policy::none())
            .connect_timeout(policy.connect_timeout)
            .timeout(policy.request_timeout)
            .user_agent(concat!("leaderboard-cloud/", env!("CARGO_PKG_VERSION")))
            .build()
            .map_err(|e| EvalAiError::Config(e.to_string()))?;
        let word = match scheme {
            AuthScheme::Bearer => "Bearer",
            AuthScheme::Token => "Token",
        };
        let mut auth = reqwest::header::HeaderValue::from_str(&format!("{word} {}", token.0))
            .map_err(|_| {
                EvalAiError::Config("the EvalAI host token is not a valid header value".into())
            })?;
        auth.set_sensitive(true);
        Ok(EvalAiClient {
            http,
            base,
            auth,
            policy,
            budget: None,
            priority: Priority::Urgent,
        })
    }

    /// The same client taking every request from `budget` first.
    pub fn with_budget(mut self, budget: Arc<dyn Budget>) -> Self {
        self.budget = Some(budget);
        self
    }

    /// The same client whose reads go at `priority` (default [`Priority::Urgent`]: a start,
    /// a cancel's confirmation, the sweep). Partial updates are always routine, final updates
    /// and `running` always urgent.
    pub fn with_priority(&self, priority: Priority) -> Self {
        EvalAiClient {
            priority,
            ..self.clone()
        }
    }

    /// GET `/api/jobs/submission/<id>` (no trailing slash).
    pub async fn submission(&self, id: u64) -> Result<Submission> {
        self.read_submission(id, Ask::new(self.priority, 1)).await
    }

    async fn read_submission(&self, id: u64, ask: Ask) -> Result<Submission> {
        let url = format!("{}/api/jobs/submission/{id}", self.base);
        let body = self.send(Method::GET, &url, None, id, ask).await?;
        Submission::from_json(&body)
    }

    /// GET `/api/jobs/challenge/<challenge>/submission/?status=<status>` (host API reference,
    /// 7.3): every submission of the challenge in that status, in one request (a plain list,
    /// not paginated), so one read a minute can find the cancels of every submission in
    /// flight. A 404 (no such challenge) is a configuration error.
    pub async fn submissions_with_status(
        &self,
        challenge: u64,
        status: SubmissionStatus,
    ) -> Result<Vec<Submission>> {
        self.submissions_with_status_since(challenge, status, None)
            .await
    }

    /// The same, only those EvalAI received at or after `since` (epoch seconds; its
    /// `submitted_after` filter): a list that does not grow with the challenge's history.
    pub async fn submissions_with_status_since(
        &self,
        challenge: u64,
        status: SubmissionStatus,
        since: Option<u64>,
    ) -> Result<Vec<Submission>> {
        let mut url = format!(
            "{}/api/jobs/challenge/{challenge}/submission/?status={status}",
            self.base
        );
        if let Some(after) = since.and_then(iso_utc) {
            url.push_str(&format!("&submitted_after={after}"));
        }
        let ask = Ask::new(self.priority, 1);
        let body = match self
            .send_as(Method::GET, &url, None, (challenge, ask), ReadAs::List)
            .await
        {
            Err(EvalAiError::NotFound(_)) => {
                return Err(EvalAiError::Config(format!(
                    "EvalAI has no challenge `{challenge}`"
                )))
            }
            other => other?,
        };
        let (submissions, skipped) = submissions_of(&body)?;
        for problem in skipped {
            warn!(challenge, %status, %problem, "a malformed submission in EvalAI's list, skipped");
        }
        Ok(submissions)
    }

    /// The image of a submission whose message had none: the docker `input_file` JSON.
    /// The file may be on another host (S3): the token is sent only to EvalAI itself.
    pub async fn submitted_image(&self, submission: &Submission) -> Result<String> {
        let Some(url) = submission.input_file.as_deref() else {
            return Err(EvalAiError::InvalidResponse(format!(
                "submission `{}` has no input_file to read the image from",
                submission.id
            )));
        };
        let same_origin = url.starts_with(&format!("{}/", self.base));
        let mut request = self.http.get(url);
        if same_origin {
            // On EvalAI itself it counts against the host token's limit like any other.
            self.admit(Ask::new(self.priority, 1)).await?;
            request = request.header(reqwest::header::AUTHORIZATION, self.auth.clone());
        }
        let response = request.send().await.map_err(|e| EvalAiError::Unavailable {
            attempts: 1,
            last: e.without_url().to_string(),
        })?;
        if !response.status().is_success() {
            return Err(EvalAiError::InvalidResponse(format!(
                "input_file answered {}",
                response.status()
            )));
        }
        // The input file is a few hundred bytes of JSON naming the image.
        let text = read_bounded(response, 64 * 1024).await?;
        model::image_from_input_file(text.as_bytes())
    }

    /// PATCH `queued` with our Job names (reference section 5): the Jobs exist and wait for
    /// capacity. Unless the submission was cancelled or ended meanwhile.
    pub async fn mark_queued(&self, at: SubmissionRef, job_name: &str) -> Result<WriteOutcome> {
        self.mark_progress(at, SubmissionStatus::Queued, job_name)
            .await
    }

    /// PATCH `running` with our Job names, unless the submission was cancelled or ended
    /// meanwhile. EvalAI sets `started_at` to now, which participants see as the start of
    /// their execution time: send it when the first pair starts, not when its Jobs are made.
    pub async fn mark_running(&self, at: SubmissionRef, job_name: &str) -> Result<WriteOutcome> {
        self.mark_progress(at, SubmissionStatus::Running, job_name)
            .await
    }

    /// Shows a queued submission's participant where it stands (`note`, e.g. "3 submissions
    /// are ahead of yours; ..."), or removes that line (`None`) once it started: the key
    /// [`QUEUE_NOTE_KEY`] of its `submission_metadata`, the one field a host may write that
    /// a participant sees while it is queued (reference 7.2, PATCH update_submission_meta).
    /// The participant's own keys are read first and kept. Routine for the budget: a GET and
    /// a PATCH. A cancelled or ended submission is left alone (the outcome says which), and
    /// metadata that is not a JSON object, or larger than [`MAX_METADATA_BYTES`], is not
    /// touched (nothing of the participant's is ever rewritten into another shape).
    pub async fn show_queue(
        &self,
        at: SubmissionRef,
        note: Option<(u32, &str)>,
    ) -> Result<WriteOutcome> {
        let ask = Ask::new(self.priority, 2);
        let current = self.read_submission(at.submission, ask).await?;
        if let Some(refused) = refuse_write(current.status) {
            return Ok(refused);
        }
        let Some(metadata) = queue_metadata(&current.metadata, note) else {
            return Ok(WriteOutcome::Written);
        };
        let url = format!(
            "{}/api/jobs/challenges/{}/submissions/{}/update_submission_meta/",
            self.base, at.challenge, at.submission
        );
        let body = json!({ "submission_metadata": metadata });
        let ask = Ask::new(ask.priority, 1);
        self.write(Method::PATCH, &url, body, at, current.status, ask)
            .await
    }

    async fn mark_progress(
        &self,
        at: SubmissionRef,
        status: SubmissionStatus,
        job_name: &str,
    ) -> Result<WriteOutcome> {
        let ask = Ask::whole(Priority::Urgent, 2);
        let current = self.read_submission(at.submission, ask).await?;
        if let Some(refused) = refuse_write(current.status) {
            return Ok(refused);
        }
        let url = format!(
            "{}/api/jobs/challenge/{}/update_submission/",
            self.base, at.challenge
        );
        let mut body = json!({
            "submission": at.submission,
            "submission_status": status.as_str(),
        });
        // EvalAI appends the name on every PATCH: `running` after `queued` names nothing new.
        let lowered = job_name.to_lowercase();
        if !current.job_names.contains(&lowered) {
            body["job_name"] = json!(job_name);
        }
        let paid = Ask::paid(ask.priority);
        self.write(Method::PATCH, &url, body, at, status, paid)
            .await
    }

    /// PUT a partial result, unless the submission was cancelled or already final.
    pub async fn post_partial(
        &self,
        at: SubmissionRef,
        update: &PartialUpdate,
    ) -> Result<WriteOutcome> {
        validate_result(&update.result).map_err(EvalAiError::InvalidResult)?;
        // The read and the write at once, in the same window.
        let ask = Ask::whole(Priority::Routine, 2);
        let current = self.read_submission(at.submission, ask).await?;
        if let Some(refused) = refuse_write(current.status) {
            return Ok(refused);
        }
        let url = format!(
            "{}/api/jobs/challenges/{}/update_partially_evaluated_submission/",
            self.base, at.challenge
        );
        let body = json!({
            "submission": at.submission,
            "submission_status": "partially_evaluated",
            "challenge_phase": at.phase,
            "result": update.result,
            "stdout": bounded_text(&update.stdout, MAX_TEXT_BYTES),
            "stderr": "",
            "metadata": bounded_metadata(&update.metadata, MAX_METADATA_BYTES),
        });
        self.write(
            Method::PUT,
            &url,
            body,
            at,
            SubmissionStatus::PartiallyEvaluated,
            Ask::paid(ask.priority),
        )
        .await
    }

    /// PUT the final update and confirm it with a GET. A cancelled submission is left
    /// cancelled whatever `update.status` says.
    pub async fn post_final(
        &self,
        at: SubmissionRef,
        update: &FinalUpdate,
    ) -> Result<WriteOutcome> {
        check_final(update)?;
        let current = self.before_final(at.submission).await?;
        match refuse_write(current) {
            Some(refused) => Ok(refused),
            None => self.write_final(at, update).await,
        }
    }

    /// The submission's status before its final update, with the places of the update's
    /// write and read back taken beside the read's (one budget take for the three): a caller
    /// that reads this apart from the write ([`Client::write_final`]) can do it beside other
    /// work.
    pub async fn before_final(&self, submission: u64) -> Result<SubmissionStatus> {
        let ask = Ask::whole(Priority::Urgent, 3);
        Ok(self.read_submission(submission, ask).await?.status)
    }

    /// The final update's PUT and the GET that confirms it, their places taken by
    /// [`Client::before_final`], whose status must not have refused the write
    /// ([`finalize::unwritable`]).
    pub async fn write_final(
        &self,
        at: SubmissionRef,
        update: &FinalUpdate,
    ) -> Result<WriteOutcome> {
        check_final(update)?;
        let outcome = self.put_final(at, update).await?;
        if outcome == WriteOutcome::Written {
            let after = self
                .read_submission(at.submission, Ask::paid(Priority::Urgent))
                .await?;
            if after.status != update.status {
                return Err(EvalAiError::NotConfirmed {
                    expected: update.status,
                    found: after.status,
                });
            }
        }
        Ok(outcome)
    }

    /// The final update's PUT. The final status must reach EvalAI: a refused body (413 from
    /// the proxy, a 400 from the view) gets one more try with only the status, the result and
    /// the reason, which EvalAI accepts whatever the participant's output was.
    async fn put_final(&self, at: SubmissionRef, update: &FinalUpdate) -> Result<WriteOutcome> {
        let url = format!(
            "{}/api/jobs/challenge/{}/update_submission/",
            self.base, at.challenge
        );
        let result = if update.status == SubmissionStatus::Finished {
            update.result.as_str()
        } else {
            "[]"
        };
        let body = |stdout: &str, stderr: &str, metadata: &str| {
            json!({
                "submission": at.submission,
                "submission_status": update.status.as_str(),
                "challenge_phase": at.phase,
                "result": result,
                "stdout": stdout,
                "stderr": stderr,
                "metadata": metadata,
            })
        };
        let full = body(
            &bounded_text(&update.stdout, MAX_TEXT_BYTES),
            &bounded_text(&update.stderr, MAX_TEXT_BYTES),
            &bounded_metadata(&update.metadata, MAX_METADATA_BYTES),
        );
        let (status, urgent) = (update.status, Priority::Urgent);
        match self
            .write(Method::PUT, &url, full, at, status, Ask::paid(urgent))
            .await
        {
            Err(EvalAiError::Rejected { status, message }) => {
                warn!(
                    submission_id = at.submission,
                    status,
                    %message,
                    "evalai refused the final update; sending the minimal one"
                );
                let minimal = body(
                    MINIMAL_STDOUT,
                    &bounded_text(&update.stderr, 4 * 1024),
                    "{}",
                );
                let ask = Ask::new(urgent, 1);
                self.write(Method::PUT, &url, minimal, at, update.status, ask)
                    .await
            }
            other => other,
        }
    }

    /// One write with its retries. After a 5xx or a timeout the write may have landed
    /// (reference §4): read the submission and stop if it already holds `target`.
    async fn write(
        &self,
        method: Method,
        url: &str,
        body: Value,
        at: SubmissionRef,
        target: SubmissionStatus,
        mut ask: Ask,
    ) -> Result<WriteOutcome> {
        let mut attempts = Attempts::new(&self.policy);
        let priority = ask.priority;
        loop {
            match self
                .once(
                    method.clone(),
                    url,
                    Some(&body),
                    (at.submission, ask),
                    ReadAs::Json,
                )
                .await
            {
                Ok(_) => {
                    info!(submission_id = at.submission, status = %target, "evalai updated");
                    return Ok(WriteOutcome::Written);
                }
                Err(Failure::Final(e)) => return Err(e),
                Err(Failure::Retry { reason, after }) => {
                    warn!(submission_id = at.submission, %reason, "evalai write failed, checking");
                    attempts.wait(reason, after).await?;
                    ask = ask.again();
                    let check = Ask::new(priority, 2);
                    let current = self.read_submission(at.submission, check).await?;
                    if current.status == target && target.is_final() {
                        return Ok(WriteOutcome::Written);
                    }
                    if let Some(refused) = refuse_write(current.status) {
                        return Ok(refused);
                    }
                }
            }
        }
    }

    /// A read with its retries.
    async fn send(
        &self,
        method: Method,
        url: &str,
        body: Option<&Value>,
        id: u64,
        ask: Ask,
    ) -> Result<Value> {
        self.send_as(method, url, body, (id, ask), ReadAs::Json)
            .await
    }

    async fn send_as(
        &self,
        method: Method,
        url: &str,
        body: Option<&Value>,
        (id, mut ask): (u64, Ask),
        read: ReadAs,
    ) -> Result<Value> {
        let mut attempts = Attempts::new(&self.policy);
        loop {
            match self.once(method.clone(), url, body, (id, ask), read).await {
                Ok(value) => return Ok(value),
                Err(Failure::Final(e)) => return Err(e),
                Err(Failure::Retry { reason, after }) => {
                    attempts.wait(reason, after).await?;
                    ask = ask.again();
                }
            }
        }
    }

    async fn once(
        &self,
        method: Method,
        url: &str,
        body: Option<&Value>,
        (id, ask): (u64, Ask),
        read: ReadAs,
    ) -> Result<Value, Failure> {
        self.admit(ask).await.map_err(Failure::Final)?;
        let mut request = self
            .http
            .request(method, url)
            .header(reqwest::header::AUTHORIZATION, self.auth.clone())
            .header(reqwest::header::ACCEPT, "application/json");
        if let Some(body) = body {
            request = request.json(body);
        }
        if let Some(left) = retry::remaining() {
            if left.is_zero() {
                return Err(Failure::Final(EvalAiError::Unavailable {
                    attempts: 0,
                    last: "no time left before the function's deadline".into(),
                }));
            }
            request = request.timeout(left.min(self.policy.request_timeout));
        }
        tally::note(|t| t.requests += 1);
        let response = match request.send().await {
            Ok(response) => response,
            Err(e) => {
                return Err(Failure::Retry {
                    reason: retry::Reason::Unavailable(e.without_url().to_string()),
                    after: None,
                })
            }
        };
        let status = response.status();
        let retry_after = response
            .headers()
            .get(reqwest::header::RETRY_AFTER)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.trim().parse::<u64>().ok())
            .map(Duration::from_secs);
        let location = response
            .headers()
            .get(reqwest::header::LOCATION)
            .and_then(|v| v.to_str().ok())
            .map(str::to_owned);
        if status.is_success() && read == ReadAs::List {
            return read_list(response).await.map_err(Failure::Final);
        }
        let text = match read_bounded(response, MAX_RESPONSE_BYTES).await {
            Ok(text) => text,
            Err(e) => return Err(Failure::Final(e)),
        };
        if status.is_success() {
            return serde_json::from_str(&text).map_err(|e| {
                Failure::Final(EvalAiError::InvalidResponse(format!(
                    "{status} with a body that is not JSON: {e}"
                )))
            });
        }
        Err(failure(status, &text, retry_after, location, id))
    }
}

/// What a refused request means: retried (throttled, a server error) or final, with EvalAI's
/// own words.
fn failure(
    status: StatusCode,
    text: &str,
    retry_after: Option<Duration>,
    location: Option<String>,
    id: u64,
) -> Failure {
    let message = model::error_message(text);
    match status {
        StatusCode::TOO_MANY_REQUESTS => {
            tally::note(|t| t.throttled += 1);
            Failure::Retry {
                reason: retry::Reason::Throttled,
                after: Some(retry_after.unwrap_or(Duration::from_secs(60))),
            }
        }
        s if s.is_server_error() => Failure::Retry {
            reason: retry::Reason::Unavailable(format!("{s}: {message}")),
            after: None,
        },
        StatusCode::NOT_FOUND => Failure::Final(EvalAiError::NotFound(id)),
        StatusCode::UNAUTHORIZED | StatusCode::FORBIDDEN => {
            Failure::Final(EvalAiError::Unauthorized {
                status: status.as_u16(),
                message,
            })
        }
        s if s.is_redirection() => Failure::Final(EvalAiError::Rejected {
            status: s.as_u16(),
            message: format!(
                "redirected to `{}`: the URL is wrong (trailing slash?)",
                location.unwrap_or_default()
            ),
        }),
        s => Failure::Final(EvalAiError::Rejected {
            status: s.as_u16(),
            message,
        }),
    }
}

impl EvalAiClient {
    /// Takes one request from the budget: a routine one is refused when its window is spent,
    /// an urgent one waits for the next window while its call has time.
    async fn admit(&self, ask: Ask) -> Result<()> {
        let Some(budget) = self.budget.as_deref().filter(|_| ask.places > 0) else {
            return Ok(());
        };
        let started = Instant::now();
        let mut waited = false;
        let allowed =
            retry::remaining().map_or(self.policy.budget, |left| left.min(self.policy.budget));
        loop {
            let headroom = ask.headroom.max(ask.places);
            match budget.take(ask.priority, ask.places, headroom).await {
                Admission::Granted => return Ok(()),
                Admission::Unavailable(why) => {
                    warn!(%why, "the EvalAI budget could not be asked: sending anyway");
                    return Ok(());
                }
                Admission::Full { .. } if ask.priority == Priority::Routine => {
                    tally::note(|t| t.over_budget += 1);
                    return Err(EvalAiError::OverBudget);
                }
                Admission::Booked { wait } => {
                    // A booked place unused is one request EvalAI never sees: harmless.
                    if started.elapsed() + wait > allowed {
                        return Err(EvalAiError::Throttled(started.elapsed() + wait));
                    }
                    if !waited {
                        tally::note(|t| t.budget_waits += 1);
                    }
                    tokio::time::sleep(wait).await;
                    return Ok(());
                }
                Admission::Full { retry_in } => {
                    // Past the window's start by a random part of a second, so the functions
                    // that waited together do not all ask at its first millisecond.
                    let wait = retry_in.max(Duration::from_millis(50))
                        + Duration::from_secs(1).mul_f64(retry::jitter());
                    if started.elapsed() + wait > allowed {
                        return Err(EvalAiError::Throttled(started.elapsed()));
                    }
                    tracing::debug!(
                        wait_ms = wait.as_millis() as u64,
                        "evalai budget full: waiting"
                    );
                    if !std::mem::replace(&mut waited, true) {
                        tally::note(|t| t.budget_waits += 1);
                    }
                    tokio::time::sleep(wait).await;
                }
            }
        }
    }
}

/// The response body, refused past `max` bytes (EvalAI's answers are untrusted input too).
async fn read_bounded(mut response: reqwest::Response, max: usize) -> Result<String> {
    let mut body = Vec::new();
    loop {
        match response.chunk().await {
            Ok(Some(chunk)) => {
                if body.len() + chunk.len() > max {
                    return Err(EvalAiError::InvalidResponse(format!(
                        "a response body over {max} bytes"
                    )));
                }
                body.extend_from_slice(&chunk);
            }
            Ok(None) => return Ok(String::from_utf8_lossy(&body).into_owned()),
            // A body cut short reads as what arrived; the JSON parse then says what is wrong.
            Err(_) => return Ok(String::from_utf8_lossy(&body).into_owned()),
        }
    }
}

/// How a successful response's body is read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ReadAs {
    /// Whole, up to [`MAX_RESPONSE_BYTES`].
    Json,
    /// A list, element by element ([`stream::ListSplitter`]): each element up to
    /// [`MAX_LIST_ELEMENT_BYTES`] (a larger or malformed one is skipped and logged), the whole
    /// up to [`MAX_LIST_BYTES`].
    List,
}

/// A JSON list's elements, each parsed on its own as it arrives.
async fn read_list(mut response: reqwest::Response) -> Result<Value> {
    let mut splitter = stream::ListSplitter::new(MAX_LIST_ELEMENT_BYTES);
    let (mut pieces, mut items, mut read) = (Vec::new(), Vec::new(), 0usize);
    loop {
        let chunk = match response.chunk().await {
            Ok(Some(chunk)) => chunk,
            Ok(None) => break,
            Err(e) => {
                return Err(EvalAiError::InvalidResponse(format!(
                    "the list was cut short: {}",
                    e.without_url()
                )))
            }
        };
        read += chunk.len();
        if read > MAX_LIST_BYTES {
            return Err(EvalAiError::InvalidResponse(format!(
                "a list over {MAX_LIST_BYTES} bytes"
            )));
        }
        splitter
            .feed(&chunk, &mut pieces)
            .map_err(EvalAiError::InvalidResponse)?;
        for piece in pieces.drain(..) {
            match piece {
                stream::Piece::Element(bytes) => match serde_json::from_slice::<Value>(&bytes) {
                    Ok(item) => items.push(item),
                    Err(e) => {
                        warn!(element = items.len(), error = %e, "a list element that is not JSON, skipped")
                    }
                },
                stream::Piece::Oversized { index, bytes } => {
                    warn!(
                        element = index,
                        bytes,
                        limit = MAX_LIST_ELEMENT_BYTES,
                        "a list element over the limit, skipped"
                    );
                }
            }
        }
    }
    splitter.finish().map_err(EvalAiError::InvalidResponse)?;
    Ok(Value::Array(items))
}

/// Why a single request failed.
enum Failure {
    Final(EvalAiError),
    Retry {
        reason: retry::Reason,
        after: Option<Duration>,
    },
}

/// The write policy: `cancelled` is final for everybody; a final status stands, undone
/// neither by a progress update (`running`, `partially_evaluated`) nor replaced by another
/// final update (a late or repeated Finalize must not turn `finished` into `failed`, nor send
/// the same update twice). A resume goes through EvalAI's own `resuming` first.
/// The key of `submission_metadata` that holds the queue note.
pub const QUEUE_NOTE_KEY: &str = "evaluation_queue";

/// The largest `submission_metadata` we rewrite to add the queue note.
pub const MAX_QUEUE_METADATA_BYTES: usize = 64 * 1024;

/// The participant's metadata with the queue note set (or removed): `None` when there is
/// nothing to write (no change) or it must not be touched (not an object, too large).
fn queue_metadata(current: &Value, note: Option<(u32, &str)>) -> Option<Value> {
    let mut object = match current {
        Value::Null => serde_json::Map::new(),
        Value::Object(object) if current.to_string().len() <= MAX_QUEUE_METADATA_BYTES => {
            object.clone()
        }
        _ => return None,
    };
    let before = object.get(QUEUE_NOTE_KEY).cloned();
    match note {
        Some((ahead, text)) => {
            object.insert(
                QUEUE_NOTE_KEY.into(),
                json!({ "ahead": ahead, "message": text }),
            );
        }
        None => {
            object.remove(QUEUE_NOTE_KEY);
        }
    }
    if object.get(QUEUE_NOTE_KEY) == before.as_ref() {
        return None;
    }
    Some(if object.is_empty() {
        Value::Null
    } else {
        Value::Object(object)
    })
}

/// A write EvalAI's `current` status refuses ([`finalize::unwritable`]).
fn refuse_write(current: SubmissionStatus) -> Option<WriteOutcome> {
    finalize::unwritable(current).map(WriteOutcome::from)
}

/// The submissions of a listing, element by element: participants write much of each element
/// (the metadata, the method fields), so one malformed element is skipped and named, never the
/// reason the whole list (every other cancel of the challenge) goes unread.
fn submissions_of(body: &Value) -> Result<(Vec<Submission>, Vec<String>)> {
    let items = body.as_array().ok_or_else(|| {
        EvalAiError::InvalidResponse("the submission list is not a JSON list".into())
    })?;
    let mut submissions = Vec::with_capacity(items.len());
    let mut skipped = Vec::new();
    for (index, item) in items.iter().enumerate() {
        match Submission::from_json(item) {
            Ok(s) => submissions.push(s),
            Err(e) => skipped.push(format!("element {index} (id {}): {e}", item["id"])),
        }
    }
    Ok((submissions, skipped))
}

#[cfg(test)]
mod listing_tests {
    use super::*;

    #[test]
    fn a_malformed_element_is_skipped_and_named_and_the_rest_of_the_list_kept() {
        let good = |id: u64| {
            serde_json::json!({"id": id, "participant_team": 1, "participant_team_name": "T",
                               "challenge_phase": 1, "created_by": 2, "status": "cancelled",
                               "submitted_at": "2026-11-24T10:00:00Z", "job_name": []})
        };
        let mut bad = good(8);
        bad["participant_team_name"] = serde_json::json!(12);
        let body = serde_json::json!([good(7), bad, good(9), "not an object"]);
        let (kept, skipped) = submissions_of(&body).unwrap();
        assert_eq!(kept.iter().map(|s| s.id).collect::<Vec<_>>(), [7, 9]);
        assert_eq!(skipped.len(), 2, "{skipped:?}");
        assert!(
            skipped[0].contains("element 1 (id 8)") && skipped[0].contains("participant_team_name")
        );
        assert!(submissions_of(&serde_json::json!({"results": []})).is_err());
    }
}

/// A final update's status is final, and a FINISHED one carries a valid result.
fn check_final(update: &FinalUpdate) -> Result<()> {
    if !matches!(
        update.status,
        SubmissionStatus::Finished | SubmissionStatus::Failed | SubmissionStatus::Cancelled
    ) {
        return Err(EvalAiError::InvalidResult(format!(
            "`{}` is not a final status",
            update.status
        )));
    }
    if update.status == SubmissionStatus::Finished {
        validate_result(&update.result).map_err(EvalAiError::InvalidResult)?;
    }
    Ok(())
}

/// `2026-11-26T04:31:05Z`: epoch seconds as EvalAI's datetime filters read them (RFC 3339,
/// which Django's `parse_datetime` reads).
fn iso_utc(epoch: u64) -> Option<String> {
    let t = time::OffsetDateTime::from_unix_timestamp(i64::try_from(epoch).ok()?).ok()?;
    t.format(&time::format_description::well_known::Rfc3339)
        .ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_bound_is_written_as_evalai_reads_it() {
        assert_eq!(iso_utc(0).as_deref(), Some("1970-01-01T00:00:00Z"));
        assert_eq!(
            iso_utc(1_795_000_000).as_deref(),
            Some("2026-11-18T11:06:40Z")
        );
    }

    #[test]
    fn the_queue_note_keeps_the_participants_keys_and_never_reshapes_them() {
        let theirs = json!({"method": "ours", "seed": 3});
        let with = queue_metadata(&theirs, Some((3, "3 ahead"))).unwrap();
        assert_eq!(
            with,
            json!({"method": "ours", "seed": 3, "evaluation_queue": {"ahead": 3, "message": "3 ahead"}})
        );
        // The same note again: nothing to write.
        assert_eq!(queue_metadata(&with, Some((3, "3 ahead"))), None);
        // Removed once it runs: the participant's keys as they were.
        assert_eq!(queue_metadata(&with, None).unwrap(), theirs);
        assert_eq!(queue_metadata(&theirs, None), None);
        // No metadata at all: the note alone, and back to null.
        let alone = queue_metadata(&Value::Null, Some((0, "none"))).unwrap();
        assert_eq!(queue_metadata(&alone, None).unwrap(), Value::Null);
        // Not an object, or too large: left as the participant made it.
        assert_eq!(queue_metadata(&json!([1, 2]), Some((1, "x"))), None);
        assert_eq!(queue_metadata(&json!("text"), Some((1, "x"))), None);
        let big = json!({"blob": "x".repeat(MAX_QUEUE_METADATA_BYTES)});
        assert_eq!(queue_metadata(&big, Some((1, "x"))), None);
    }

    #[test]
    fn cancelled_is_never_overwritten_and_a_final_status_stands() {
        use SubmissionStatus::*;
        assert_eq!(refuse_write(Cancelled), Some(WriteOutcome::Cancelled));
        for stands in [Finished, Failed, Archived] {
            assert_eq!(
                refuse_write(stands),
                Some(WriteOutcome::AlreadyFinal(stands))
            );
        }
        for open in [Submitted, Queued, Running, Resuming, PartiallyEvaluated] {
            assert_eq!(refuse_write(open), None, "{open}");
        }
    }

    #[test]
    fn a_write_s_outcome_and_the_domain_s_word_for_it_map_each_to_its_own() {
        let each = [
            (WriteOutcome::Written, Posted::Written),
            (WriteOutcome::Cancelled, Posted::Cancelled),
            (
                WriteOutcome::AlreadyFinal(SubmissionStatus::Failed),
                Posted::AlreadyFinal(SubmissionStatus::Failed),
            ),
        ];
        for (outcome, posted) in each {
            assert_eq!(Posted::from(outcome), posted);
            assert_eq!(WriteOutcome::from(posted), outcome);
        }
    }

    #[test]
    fn the_token_never_shows_in_debug_output() {
        let token = HostToken::new("very-secret");
        let client = EvalAiClient::new(
            "http://127.0.0.1:1",
            &token,
            AuthScheme::Bearer,
            RetryPolicy::default(),
        )
        .unwrap();
        assert!(!format!("{token:?}").contains("very-secret"));
        let debug = format!("{client:?}");
        assert!(!debug.contains("very-secret"), "{debug}");
        assert!(debug.contains("Sensitive"), "{debug}");
    }
}
