//! The `jobs` views, step for step in EvalAI's order (which error wins matters to clients).

use axum::http::{Method, StatusCode};

use crate::pyjson::PyValue;
use crate::routes::body::{self, BodyError, Data};
use crate::routes::meta;
use crate::routes::pyops::{
    attribute_error, char_lookup, content_file, encode, get_submission_model, int_lookup, iterate,
    json_loads_field, lower, shown,
};
use crate::routes::reply::{Reply, ReplyBody, ViewResult};
use crate::state::{Phase, Row, Split, World};
use crate::statuses;
use crate::timefmt;

/// What a view gets: the locked database, the caller and the raw request.
pub(crate) struct Ctx<'a> {
    pub world: &'a mut World,
    pub user: u64,
    pub base_url: &'a str,
    pub content_type: Option<&'a str>,
    pub body: &'a [u8],
    pub query: Option<&'a str>,
}

impl Ctx<'_> {
    /// `request.data`: parsed on first use, which is after the host check.
    fn data(&self) -> ViewResult<Data> {
        body::parse(self.content_type, self.body).map_err(|e| match e {
            BodyError::Unsupported(ct) => Reply::detail(
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                format!("Unsupported media type \"{ct}\" in request."),
            ),
            BodyError::Parse(m) => Reply::detail(StatusCode::BAD_REQUEST, m),
        })
    }

    fn is_host(&self, challenge: u64) -> bool {
        self.world.is_host(self.user, challenge)
    }

    fn serialized(&self, id: u64) -> Reply {
        let s = &self.world.submissions[&id];
        let host = self.is_host(self.world.challenge_of(s));
        Reply::json(
            StatusCode::OK,
            self.world.serialize_submission(s, self.base_url, host),
        )
    }
}

fn not_authorized() -> Reply {
    Reply::error(
        StatusCode::BAD_REQUEST,
        "Sorry, you are not authorized to make this request!",
    )
}

fn invalid_status() -> Reply {
    Reply::error(
        StatusCode::BAD_REQUEST,
        "Sorry, submission status is invalid",
    )
}

fn result_error(message: &str) -> Reply {
    Reply::error(
        StatusCode::BAD_REQUEST,
        format!(
            "`result` key contains invalid data with error {message}.Please try again with correct format."
        ),
    )
}

fn multiple_rows(count: usize) -> Reply {
    Reply::server_error(format!(
        "MultipleObjectsReturned: get() returned more than one LeaderboardData -- it returned {count}!"
    ))
}

/// GET (and DELETE) `/api/jobs/submission/<id>`.
pub(crate) fn get_submission(ctx: &mut Ctx<'_>, method: &Method, id: u64) -> Reply {
    let Some(sub) = ctx.world.submissions.get(&id) else {
        return Reply::error(
            StatusCode::NOT_FOUND,
            format!("Submission {id} does not exist"),
        );
    };
    let challenge = ctx.world.challenge_of(sub);
    if sub.created_by != ctx.user && !ctx.is_host(challenge) {
        return Reply::error(
            StatusCode::UNAUTHORIZED,
            "Sorry, you are not authorized to access this submission.",
        );
    }
    if method == Method::DELETE {
        if let Some(sub) = ctx.world.submissions.get_mut(&id) {
            sub.ignore_submission = true;
        }
        return Reply {
            status: StatusCode::NO_CONTENT,
            body: ReplyBody::Empty,
            headers: Vec::new(),
            error: None,
        };
    }
    ctx.serialized(id)
}

/// Which endpoint validates a `result`.
#[derive(Clone, Copy, PartialEq)]
enum Endpoint {
    /// `update_submission` PUT.
    Final,
    /// `update_partially_evaluated_submission` PUT.
    PartialPut,
    /// `update_partially_evaluated_submission` PATCH (merge into existing rows).
    PartialPatch,
}

enum Target {
    Existing(usize),
    New { phase: u64, split: u64 },
}

struct Write {
    target: Target,
    result: Vec<(String, PyValue)>,
}

/// Validates every split of `result` and plans the row writes; also returns the
/// accuracies shown to the participant.
fn plan_results(
    world: &World,
    endpoint: Endpoint,
    phase_value: Option<&PyValue>,
    submission_value: Option<&PyValue>,
    submission: u64,
    results: PyValue,
) -> ViewResult<(Vec<Write>, Vec<PyValue>)> {
    let mut writes = Vec::new();
    let mut public = Vec::new();
    for element in iterate(results)? {
        if !matches!(element, PyValue::Dict(_)) {
            return Err(attribute_error(&element, "get"));
        }
        let split_value = element.get("split");
        let accuracies = element.get("accuracies");
        let show = element
            .get("show_to_participant")
            .is_some_and(PyValue::truthy);
        let (phase_id, phase, split) = split_of(world, phase_value, split_value)?;
        let rows: Vec<usize> = world
            .rows
            .iter()
            .enumerate()
            .filter(|(_, r)| r.submission == submission && r.split == split.id)
            .map(|(i, _)| i)
            .collect();
        let mut merged = None;
        if endpoint == Endpoint::PartialPatch {
            match rows.as_slice() {
                [] => {
                    return Err(Reply::error(
                        StatusCode::BAD_REQUEST,
                        format!(
                        "Leaderboard Data does not exist with phase_id: {} andsubmission id: {}",
                        shown(phase_value),
                        shown(submission_value)
                    ),
                    ))
                }
                [one] => merged = Some((*one, world.rows[*one].result.clone())),
                many => return Err(multiple_rows(many.len())),
            }
        }
        let pairs = match accuracies {
            Some(PyValue::Dict(pairs)) => pairs.clone(),
            Some(other) => return Err(attribute_error(other, "items")),
            None => return Err(attribute_error(&PyValue::None, "items")),
        };
        let partial_endpoint = endpoint != Endpoint::Final;
        let unknown_keys_allowed = partial_endpoint && phase.partial_evaluation_enabled;
        check_metrics(
            &pairs,
            &split.labels,
            merged.as_mut().map(|(_, m)| m),
            (partial_endpoint, unknown_keys_allowed),
            phase_value,
        )?;
        let write = write_of(merged, &rows, (phase_id, split.id), &pairs)?;
        writes.push(write);
        if show {
            public.push(PyValue::Dict(pairs));
        }
    }
    Ok((writes, public))
}

/// The phase and split an element names (the phase by the URL's id, the split by its
/// codename), in the server's words when there is none.
fn split_of<'w>(
    world: &'w World,
    phase_value: Option<&PyValue>,
    split_value: Option<&PyValue>,
) -> ViewResult<(u64, &'w Phase, &'w Split)> {
    let phase_id = match phase_value {
        None => None,
        Some(v) => int_lookup(v)?,
    };
    let codename = char_lookup(split_value);
    let found = match (phase_id.and_then(|p| u64::try_from(p).ok()), codename) {
        (Some(p), Some(c)) => world.split(p, &c).map(|(ph, sp)| (p, ph, sp)),
        _ => None,
    };
    found.ok_or_else(|| {
        Reply::error(
            StatusCode::BAD_REQUEST,
            format!(
                "Challenge Phase Split does not exist with phase_id: {} andsplit codename: {}",
                shown(phase_value),
                shown(split_value)
            ),
        )
    })
}

/// The accuracies' metrics against the split's `labels`: each a known label (unless
/// `unknown_keys_allowed`) with a number for its value, in the server's words for the first
/// that is not; folded into `merged` (the patched row's result) as they go.
fn check_metrics(
    pairs: &[(String, PyValue)],
    labels: &[String],
    mut merged: Option<&mut Vec<(String, PyValue)>>,
    (partial_endpoint, unknown_keys_allowed): (bool, bool),
    phase_value: Option<&PyValue>,
) -> ViewResult<()> {
    let mut missing = Vec::new();
    let mut malformed = Vec::new();
    for (metric, value) in pairs {
        if !labels.contains(metric) {
            missing.push(PyValue::Str(metric.clone()));
        }
        if !value.is_number() {
            malformed.push(format!(
                "({}, <class '{}'>)",
                PyValue::Str(metric.clone()).repr(),
                value.type_name()
            ));
        }
        if let Some(m) = merged.as_deref_mut() {
            PyValue::dict_set(m, metric.clone(), value.clone());
        }
    }
    if !missing.is_empty() && !unknown_keys_allowed {
        let mut text = format!(
            "Following metrics are missing in theleaderboard data: {}",
            PyValue::List(missing).repr()
        );
        if partial_endpoint {
            text.push_str(&format!(" of challenge phase: {}", shown(phase_value)));
        }
        return Err(Reply::error(StatusCode::BAD_REQUEST, text));
    }
    if !malformed.is_empty() {
        return Err(Reply::error(
            StatusCode::BAD_REQUEST,
            format!(
                "Values for following metrics are not offloat/int: [{}]",
                malformed.join(", ")
            ),
        ));
    }
    Ok(())
}

/// The row write of one split's accuracies: the patched row (`merged`), else the split's one
/// row of this submission, else a new row for (phase, split) `ids`.
fn write_of(
    merged: Option<(usize, Vec<(String, PyValue)>)>,
    rows: &[usize],
    ids: (u64, u64),
    pairs: &[(String, PyValue)],
) -> ViewResult<Write> {
    Ok(match merged {
        Some((row, result)) => Write {
            target: Target::Existing(row),
            result,
        },
        None => match rows {
            [] => Write {
                target: Target::New {
                    phase: ids.0,
                    split: ids.1,
                },
                result: pairs.to_vec(),
            },
            [one] => Write {
                target: Target::Existing(*one),
                result: pairs.to_vec(),
            },
            many => return Err(multiple_rows(many.len())),
        },
    })
}

/// Writes the rows in one transaction. A NaN or infinity is refused before anything is
/// written, by the leaderboard row serializer's JSON field (as recorded from the real server).
fn commit(world: &mut World, submission: u64, writes: Vec<Write>) -> ViewResult<()> {
    if writes
        .iter()
        .any(|w| w.result.iter().any(|(_, v)| v.has_non_finite()))
    {
        return Err(Reply::json(
            StatusCode::BAD_REQUEST,
            PyValue::dict(vec![(
                "result",
                PyValue::List(vec![PyValue::str("Value must be valid JSON.")]),
            )]),
        ));
    }
    let now = timefmt::now();
    for w in writes {
        match w.target {
            Target::Existing(i) => {
                world.rows[i].result = w.result;
                world.rows[i].updated_at = now;
            }
            Target::New { phase, split } => {
                let id = world.next_row_id;
                world.next_row_id += 1;
                world.rows.push(Row {
                    id,
                    submission,
                    phase,
                    split,
                    result: w.result,
                    created_at: now,
                    updated_at: now,
                });
            }
        }
    }
    Ok(())
}

fn loads_result(value: &PyValue) -> ViewResult<PyValue> {
    json_loads_field(value).map_err(|m| result_error(&m))
}

/// PUT/PATCH `/api/jobs/challenge/<c>/update_submission/`.
pub(crate) fn update_submission(ctx: &mut Ctx<'_>, method: &Method, challenge: u64) -> Reply {
    let r = if !ctx.world.is_staff(ctx.user) && !ctx.is_host(challenge) {
        Err(not_authorized())
    } else if method == Method::PUT {
        final_put(ctx)
    } else {
        running_patch(ctx)
    };
    r.unwrap_or_else(|e| e)
}

fn final_put(ctx: &mut Ctx<'_>) -> ViewResult {
    let data = ctx.data()?;
    let phase_value = data.get("challenge_phase")?.cloned();
    let submission_value = data.get("submission")?.cloned();
    let status = lower(&data.get_or_empty("submission_status")?)?;
    let stdout = encode(&data.get_or_empty("stdout")?)?;
    let stderr = encode(&data.get_or_empty("stderr")?)?;
    let environment_log = encode(&data.get_or_empty("environment_log")?)?;
    let result = data.get_or_empty("result")?;
    let metadata = data.get_or_empty("metadata")?;
    let id = get_submission_model(ctx.world, submission_value.as_ref())?;
    if ![statuses::FAILED, statuses::CANCELLED, statuses::FINISHED].contains(&status.as_str()) {
        return Err(invalid_status());
    }
    let mut public = Vec::new();
    if status == statuses::FINISHED {
        let results = loads_result(&result)?;
        let (writes, shown_results) = plan_results(
            ctx.world,
            Endpoint::Final,
            phase_value.as_ref(),
            submission_value.as_ref(),
            id,
            results,
        )?;
        commit(ctx.world, id, writes)?;
        public = shown_results;
    }
    let sub = ctx
        .world
        .submissions
        .get_mut(&id)
        .ok_or_else(not_authorized)?;
    sub.status = status;
    sub.completed_at = Some(timefmt::now());
    sub.files.stdout = Some(stdout);
    sub.files.stderr = Some(stderr);
    sub.files.environment_log = Some(environment_log);
    sub.files.result = Some(PyValue::List(public).repr());
    sub.files.metadata = Some(metadata.py_str());
    Ok(Reply::success_updated())
}

/// The job name a running update appends: trimmed and lower-cased, as the real server
/// stores it (`" Spaced Name "` -> `"spaced name"`).
fn job_name(data: &Data) -> ViewResult<String> {
    Ok(lower(&data.get_or_empty("job_name")?)?.trim().to_owned())
}

/// The `job_name` list after `jobs.append(name)` (a null list cannot be appended to).
fn appended_jobs(current: &Option<Vec<String>>, name: &str) -> ViewResult<Option<Vec<String>>> {
    let mut jobs = current.clone();
    if !name.is_empty() {
        match jobs.as_mut() {
            Some(list) => list.push(name.to_owned()),
            None => return Err(attribute_error(&PyValue::None, "append")),
        }
    }
    Ok(jobs)
}

fn set_running(ctx: &mut Ctx<'_>, id: u64, status: String, jobs: Option<Vec<String>>) -> Reply {
    if let Some(sub) = ctx.world.submissions.get_mut(&id) {
        sub.status = status;
        sub.started_at = Some(timefmt::now());
        sub.job_name = jobs;
    }
    ctx.serialized(id)
}

fn running_patch(ctx: &mut Ctx<'_>) -> ViewResult {
    let data = ctx.data()?;
    let submission_value = data.get("submission")?.cloned();
    let id = get_submission_model(ctx.world, submission_value.as_ref())?;
    let status = lower(&data.get_or_empty("submission_status")?)?;
    let job = job_name(&data)?;
    let jobs = appended_jobs(&ctx.world.submissions[&id].job_name, &job)?;
    if ![statuses::QUEUED, statuses::RUNNING].contains(&status.as_str()) {
        return Err(invalid_status());
    }
    Ok(set_running(ctx, id, status, jobs))
}

/// PUT/PATCH `/api/jobs/challenges/<c>/update_partially_evaluated_submission/` (hosts only).
pub(crate) fn update_partial(ctx: &mut Ctx<'_>, method: &Method, challenge: u64) -> Reply {
    let r = if !ctx.is_host(challenge) {
        Err(not_authorized())
    } else if method == Method::PUT {
        partial_put(ctx)
    } else {
        partial_patch(ctx)
    };
    r.unwrap_or_else(|e| e)
}

/// What a successful partial update stores on the submission.
struct Outcome<'a> {
    status: String,
    /// The appended `job_name` list (PATCH only).
    jobs: Option<Option<Vec<String>>>,
    stdout: &'a PyValue,
    stderr: &'a PyValue,
    public: Vec<PyValue>,
    /// `metadata` (PUT only).
    metadata: Option<&'a PyValue>,
}

/// Stores status, `completed_at` and the files the way the view saves them one by one:
/// a bad `stdout` fails before anything is saved, a bad `stderr` after the status was.
fn save_files(ctx: &mut Ctx<'_>, id: u64, outcome: Outcome<'_>) -> ViewResult<()> {
    let now = timefmt::now();
    let stdout = content_file(outcome.stdout)?;
    let sub = ctx
        .world
        .submissions
        .get_mut(&id)
        .ok_or_else(not_authorized)?;
    sub.status = outcome.status;
    sub.completed_at = Some(now);
    if let Some(jobs) = outcome.jobs {
        sub.job_name = jobs;
    }
    sub.files.stdout = Some(stdout);
    sub.files.stderr = Some(content_file(outcome.stderr)?);
    sub.files.result = Some(PyValue::List(outcome.public).repr());
    if let Some(metadata) = outcome.metadata {
        sub.files.metadata = Some(metadata.py_str());
    }
    Ok(())
}

fn partial_put(ctx: &mut Ctx<'_>) -> ViewResult {
    let data = ctx.data()?;
    let phase_value = data.get("challenge_phase")?.cloned();
    let submission_value = data.get("submission")?.cloned();
    let status = lower(&data.get_or_empty("submission_status")?)?;
    let stdout = data.get_or_empty("stdout")?;
    let stderr = data.get_or_empty("stderr")?;
    let result = data.get_or_empty("result")?;
    let metadata = data.get_or_empty("metadata")?;
    let id = get_submission_model(ctx.world, submission_value.as_ref())?;
    if ![
        statuses::FAILED,
        statuses::CANCELLED,
        statuses::FINISHED,
        statuses::PARTIALLY_EVALUATED,
    ]
    .contains(&status.as_str())
    {
        return Err(invalid_status());
    }
    let mut public = Vec::new();
    if status == statuses::FINISHED || status == statuses::PARTIALLY_EVALUATED {
        let results = loads_result(&result)?;
        let (writes, shown_results) = plan_results(
            ctx.world,
            Endpoint::PartialPut,
            phase_value.as_ref(),
            submission_value.as_ref(),
            id,
            results,
        )?;
        commit(ctx.world, id, writes)?;
        public = shown_results;
    }
    let outcome = Outcome {
        status,
        jobs: None,
        stdout: &stdout,
        stderr: &stderr,
        public,
        metadata: Some(&metadata),
    };
    save_files(ctx, id, outcome)?;
    Ok(Reply::success_updated())
}

fn partial_patch(ctx: &mut Ctx<'_>) -> ViewResult {
    let data = ctx.data()?;
    let submission_value = data.get("submission")?.cloned();
    let status = lower(&data.get_or_empty("submission_status")?)?;
    let job = job_name(&data)?;
    let id = get_submission_model(ctx.world, submission_value.as_ref())?;
    let jobs = appended_jobs(&ctx.world.submissions[&id].job_name, &job)?;
    if status == statuses::RUNNING {
        return Ok(set_running(ctx, id, status, jobs));
    }
    if status != statuses::PARTIALLY_EVALUATED && status != statuses::FINISHED {
        return Err(invalid_status());
    }
    let phase_value = data.get("challenge_phase")?.cloned();
    let stdout = data.get_or_empty("stdout")?;
    let stderr = data.get_or_empty("stderr")?;
    let result = data.get_or_empty("result")?;
    let results = loads_result(&result)?;
    let (writes, public) = plan_results(
        ctx.world,
        Endpoint::PartialPatch,
        phase_value.as_ref(),
        submission_value.as_ref(),
        id,
        results,
    )?;
    commit(ctx.world, id, writes)?;
    let outcome = Outcome {
        status,
        jobs: Some(jobs),
        stdout: &stdout,
        stderr: &stderr,
        public,
        metadata: None,
    };
    save_files(ctx, id, outcome)?;
    Ok(Reply::success_updated())
}

/// PATCH `/api/jobs/challenges/<c>/submissions/<s>/update_submission_meta/`.
pub(crate) fn update_meta(ctx: &mut Ctx<'_>, challenge: u64, submission: u64) -> Reply {
    update_meta_inner(ctx, challenge, submission).unwrap_or_else(|e| e)
}

fn update_meta_inner(ctx: &mut Ctx<'_>, challenge: u64, submission: u64) -> ViewResult {
    let id = if ctx.is_host(challenge) {
        get_submission_model(ctx.world, Some(&PyValue::Int(i128::from(submission))))?
    } else {
        let Some(team) = ctx.world.team_of_user_for_challenge(ctx.user, challenge) else {
            // EvalAI looks the team up with a `None` id and reports the failed lookup.
            return Err(Reply::detail(
                StatusCode::NOT_FOUND,
                "ParticipantTeam None does not exist",
            ));
        };
        match ctx.world.submissions.get(&submission) {
            Some(s) if s.team == team => submission,
            _ => {
                return Err(Reply::error(
                    StatusCode::NOT_FOUND,
                    format!("Submission {submission} does not exist"),
                ))
            }
        }
    };
    let data = ctx.data()?;
    let known = meta::Related {
        teams: ctx.world.teams.keys().copied().collect(),
        users: ctx.world.users.keys().copied().collect(),
        phases: ctx.world.phases.keys().copied().collect(),
    };
    let sub = ctx
        .world
        .submissions
        .get_mut(&id)
        .ok_or_else(not_authorized)?;
    meta::apply(sub, &data, &known)?;
    Ok(ctx.serialized(id))
}

/// PATCH `/api/jobs/submission/<s>/update_started_at/` (any verified user).
pub(crate) fn update_started_at(ctx: &mut Ctx<'_>, submission: u64) -> Reply {
    let Some(sub) = ctx.world.submissions.get_mut(&submission) else {
        return Reply::error(StatusCode::FORBIDDEN, "Submission does not exist");
    };
    sub.started_at = Some(timefmt::now());
    ctx.serialized(submission)
}

/// GET `/api/jobs/challenge/<c>/submission/?status=...` (staff or host).
pub(crate) fn list_submissions(ctx: &mut Ctx<'_>, challenge: u64) -> Reply {
    if !ctx.world.challenge_exists(challenge) {
        return Reply::detail(
            StatusCode::NOT_FOUND,
            format!("Challenge {challenge} does not exist"),
        );
    }
    if !ctx.world.is_staff(ctx.user) && !ctx.is_host(challenge) {
        return not_authorized();
    }
    let query = body::parse_urlencoded(ctx.query.unwrap_or("").as_bytes());
    let param = |name: &str| {
        query
            .iter()
            .rev()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v.clone())
    };
    // No `status`, or an empty one, filters nothing: every submission of the challenge.
    let status = param("status").filter(|s| !s.is_empty());
    if let Some(status) = status.as_deref() {
        if !statuses::LISTABLE.contains(&status) {
            return Reply::error(
                StatusCode::BAD_REQUEST,
                format!("Invalid submission status {status}"),
            );
        }
    }
    let mut bounds = [None, None];
    for (i, name) in ["submitted_after", "submitted_before"].iter().enumerate() {
        if let Some(v) = param(name) {
            match timefmt::parse(&v) {
                Some(t) => bounds[i] = Some(t),
                None => {
                    return Reply::error(
                        StatusCode::BAD_REQUEST,
                        format!("Invalid datetime format for '{name}'"),
                    )
                }
            }
        }
    }
    let host = ctx.is_host(challenge);
    let list: Vec<PyValue> = ctx
        .world
        .submissions
        .values()
        .filter(|s| ctx.world.challenge_of(s) == challenge)
        .filter(|s| status.as_deref().is_none_or(|wanted| s.status == wanted))
        .filter(|s| bounds[0].is_none_or(|after| s.submitted_at >= after))
        .filter(|s| bounds[1].is_none_or(|before| s.submitted_at <= before))
        .map(|s| ctx.world.serialize_submission(s, ctx.base_url, host))
        .collect();
    Reply::json(StatusCode::OK, PyValue::List(list))
}
