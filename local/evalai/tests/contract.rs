//! The fake EvalAI against a recording of EvalAI's real server.
//!
//! `tests/fixtures/evalai-contract/real-transcript.json` holds what EvalAI's own Django code
//! (Cloud-CV/EvalAI at 0f04039, on PostgreSQL) answered to 199 requests of a host evaluation
//! backend, in order, plus 19 facts read off those answers; `fake-evalai-fixture.json` is the
//! seed it was recorded on, in this fake's fixture format. This test seeds the fake the same
//! way, sends the same requests in the same order with the same callers, normalises the
//! fake's answers as the recording was normalised, and compares status, media type, the
//! headers recorded and the body. Every difference must be one of `ACCEPTED` (cosmetic, each
//! with its reason); a new difference fails, and so does an accepted one that went away.

use std::collections::{BTreeMap, HashMap};
use std::path::PathBuf;

use fake_evalai::{FakeEvalAi, Fixture};
use serde_json::{json, Map, Value};

/// Differences that may stay: `(tag, where, why)`. `where` is `status`, `content-type`,
/// `header <name>` or a body path (`body`, `body.detail`, `body[0].id`); a difference is
/// accepted when its tag matches and its place starts with `where`.
const ACCEPTED: &[(&str, &str, &str)] = &[];

fn recording_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/evalai-contract")
}

/// The `Authorization` header each recorded caller label stands for, with the fixture's tokens.
fn authorization(label: Option<&str>) -> Option<String> {
    let jwt = |t: &str| format!("Bearer {t}");
    let legacy = |t: &str| format!("Token {t}");
    Some(match label? {
        "host" => jwt("host-jwt-token"),
        "participant" => jwt("participant-jwt-token"),
        "outsider" => jwt("outsider-jwt-token"),
        // The fixture gives the unverified user a login token: 403 comes before the scheme.
        "unverified" => legacy("fedcba9876543210fedcba9876543210fedcba98"),
        "host_drf" => legacy("0123456789abcdef0123456789abcdef01234567"),
        "host_jwt_as_Token" => legacy("host-jwt-token"),
        "host_drf_as_Bearer" => jwt("0123456789abcdef0123456789abcdef01234567"),
        "bad_jwt" => jwt("not-a-token-anyone-issued"),
        other => panic!("the recording names a caller this test does not know: {other}"),
    })
}

/// A recorded request body's placeholders given concrete values again.
fn concrete(value: &Value) -> Value {
    match value {
        Value::String(s) if s.starts_with("<float") => json!(12.5),
        Value::String(s) if s.starts_with("<ts:") => json!("2026-01-02T03:04:05Z"),
        Value::Array(items) => Value::Array(items.iter().map(concrete).collect()),
        Value::Object(map) => {
            Value::Object(map.iter().map(|(k, v)| (k.clone(), concrete(v))).collect())
        }
        other => other.clone(),
    }
}

fn form_value(value: &Value) -> String {
    match value {
        Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

/// One answer, as received.
struct Answer {
    status: u16,
    content_type: String,
    headers: BTreeMap<String, String>,
    /// JSON, or `"HTML"` for a page (its title in `html_title`).
    body: Value,
    html_title: Option<String>,
}

struct Replay {
    http: reqwest::Client,
    fake: FakeEvalAi,
    base: String,
}

impl Replay {
    async fn send(&self, method: &str, path: &str, auth: Option<&str>, body: &Value) -> Answer {
        let method = reqwest::Method::from_bytes(method.as_bytes()).unwrap();
        let mut request = self.http.request(method, format!("{}{path}", self.base));
        if let Some(header) = authorization(auth) {
            request = request.header("Authorization", header);
        }
        if let Some(json) = body.get("json") {
            request = request.json(&concrete(json));
        } else if let Some(form) = body.get("form").and_then(Value::as_object) {
            let pairs: Vec<(String, String)> = form
                .iter()
                .map(|(k, v)| (k.clone(), form_value(&concrete(v))))
                .collect();
            request = request.form(&pairs);
        } else if let Some(raw) = body.get("raw").and_then(Value::as_str) {
            let content_type = body["content_type"].as_str().unwrap_or("application/json");
            request = request
                .header("Content-Type", content_type)
                .body(raw.to_owned());
        }
        let response = request.send().await.expect("the fake answers");
        let status = response.status().as_u16();
        let headers: BTreeMap<String, String> =
            ["allow", "location", "retry-after", "www-authenticate"]
                .iter()
                .filter_map(|name| {
                    let value = response.headers().get(*name)?.to_str().ok()?;
                    Some((name.to_string(), value.to_owned()))
                })
                .collect();
        let content_type = response
            .headers()
            .get("content-type")
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
            .to_owned();
        let text = response.text().await.unwrap_or_default();
        let (body, html_title) =
            if content_type.starts_with("text/html") || text.trim_start().starts_with('<') {
                (json!("HTML"), title_of(&text))
            } else if text.is_empty() {
                (Value::Null, None)
            } else {
                (
                    serde_json::from_str(&text).unwrap_or(Value::String(text)),
                    None,
                )
            };
        Answer {
            status,
            content_type,
            headers,
            body,
            html_title,
        }
    }

    /// A stored file's answer, as the recording's checks give it: `{"status", "content"}`.
    async fn file(&self, url: &Value) -> Value {
        let Some(url) = url.as_str() else {
            return json!({"status": null, "content": null});
        };
        let response = self
            .http
            .get(url)
            .send()
            .await
            .expect("the fake serves files");
        let status = response.status().as_u16();
        json!({"status": status, "content": response.text().await.unwrap_or_default()})
    }
}

fn title_of(html: &str) -> Option<String> {
    let start = html.find("<title>")? + "<title>".len();
    let end = html[start..].find("</title>")? + start;
    Some(html[start..end].trim().to_owned())
}

/// The recording's normalisation: timestamps to `<ts:FORMAT>` (digits as 9), the base URL to
/// `{BASE}`, uuids and long hex to `<uuid>`, `execution_time` numbers to their sign.
fn normalise(value: &Value, base: &str, key: Option<&str>) -> Value {
    match value {
        Value::Number(n) if key == Some("execution_time") => {
            let f = n.as_f64().unwrap_or(0.0);
            json!(if f > 0.0 {
                "<float+>"
            } else if f < 0.0 {
                "<float->"
            } else {
                "<float0>"
            })
        }
        Value::String(s) => json!(normalise_text(s, base)),
        Value::Array(items) => {
            Value::Array(items.iter().map(|v| normalise(v, base, None)).collect())
        }
        Value::Object(map) => Value::Object(
            map.iter()
                .map(|(k, v)| (k.clone(), normalise(v, base, Some(k))))
                .collect::<Map<_, _>>(),
        ),
        other => other.clone(),
    }
}

fn normalise_text(s: &str, base: &str) -> String {
    if is_timestamp(s) {
        let shape: String = s
            .chars()
            .map(|c| if c.is_ascii_digit() { '9' } else { c })
            .collect();
        return format!("<ts:{shape}>");
    }
    let s = s.replace(base, "{BASE}");
    replace_hex_runs(&s)
}

/// `2026-11-25T21:50:13.123456Z` and the like, the whole string.
fn is_timestamp(s: &str) -> bool {
    let b = s.as_bytes();
    b.len() >= 20
        && b[..4].iter().all(u8::is_ascii_digit)
        && b[4] == b'-'
        && b[7] == b'-'
        && b[10] == b'T'
        && b[13] == b':'
        && s.chars()
            .all(|c| c.is_ascii_digit() || "-T:.Z+".contains(c))
}

/// Uuids (with dashes) and hex runs of 32 or more characters become `<uuid>`.
fn replace_hex_runs(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    let chars: Vec<char> = s.chars().collect();
    let mut i = 0;
    while i < chars.len() {
        let mut j = i;
        while j < chars.len() && (chars[j].is_ascii_hexdigit() || chars[j] == '-') {
            j += 1;
        }
        let run: String = chars[i..j].iter().collect();
        let hex = run.chars().filter(char::is_ascii_hexdigit).count();
        if j > i && hex >= 32 && (run.matches('-').count() == 4 || !run.contains('-')) {
            out.push_str("<uuid>");
            i = j;
        } else if j > i {
            out.push_str(&run);
            i = j;
        } else {
            out.push(chars[i]);
            i += 1;
        }
    }
    out
}

/// Throttle texts carry a number of seconds that depends on timing.
fn normalise_throttle(answer: &mut Answer) {
    if answer.status == 429 {
        if let Some(v) = answer.headers.get_mut("retry-after") {
            *v = "<int>".into();
        }
        if let Some(detail) = answer.body.get_mut("detail") {
            *detail = json!("Request was throttled. Expected available in <N> seconds.");
        }
    }
}

fn sorted_allow(value: &str) -> String {
    let mut methods: Vec<&str> = value.split(',').map(str::trim).collect();
    methods.sort_unstable();
    methods.join(", ")
}

/// Every place where `fake` differs from `real`, as `(place, real, fake)`.
fn diff(place: &str, real: &Value, fake: &Value, out: &mut Vec<(String, String, String)>) {
    match (real, fake) {
        (Value::Object(r), Value::Object(f)) => {
            for (k, rv) in r {
                let at = format!("{place}.{k}");
                match f.get(k) {
                    Some(fv) => diff(&at, rv, fv, out),
                    None => out.push((at, short(rv), "(absent)".into())),
                }
            }
            for (k, fv) in f {
                if !r.contains_key(k) {
                    out.push((format!("{place}.{k}"), "(absent)".into(), short(fv)));
                }
            }
        }
        (Value::Array(r), Value::Array(f)) if r.len() == f.len() => {
            for (i, (rv, fv)) in r.iter().zip(f).enumerate() {
                diff(&format!("{place}[{i}]"), rv, fv, out);
            }
        }
        _ if real != fake => out.push((place.to_owned(), short(real), short(fake))),
        _ => {}
    }
}

/// A value's JSON text, cut to a readable length.
fn short(value: &Value) -> String {
    let text = value.to_string();
    match text.char_indices().nth(160) {
        Some((at, _)) => format!("{}...", &text[..at]),
        None => text,
    }
}

fn compare(row: &Value, answer: &Answer) -> Vec<(String, String, String)> {
    let mut out = Vec::new();
    let status = row["status"].as_u64().unwrap_or(0);
    if status != u64::from(answer.status) {
        out.push((
            "status".into(),
            status.to_string(),
            answer.status.to_string(),
        ));
    }
    let media = |t: &str| t.split(';').next().unwrap_or("").trim().to_owned();
    let real_type = media(row["content_type"].as_str().unwrap_or(""));
    if real_type != media(&answer.content_type) {
        out.push((
            "content-type".into(),
            real_type,
            media(&answer.content_type),
        ));
    }
    let recorded: BTreeMap<String, String> = row["headers"]
        .as_object()
        .map(|h| {
            h.iter()
                .map(|(k, v)| (k.to_lowercase(), v.as_str().unwrap_or("").to_owned()))
                .collect()
        })
        .unwrap_or_default();
    for name in ["allow", "location", "retry-after", "www-authenticate"] {
        let real = recorded.get(name).map(|v| {
            if name == "allow" {
                sorted_allow(v)
            } else {
                v.clone()
            }
        });
        let fake = answer.headers.get(name).map(|v| {
            if name == "allow" {
                sorted_allow(v)
            } else {
                v.clone()
            }
        });
        if real != fake {
            out.push((
                format!("header {name}"),
                format!("{real:?}"),
                format!("{fake:?}"),
            ));
        }
    }
    diff("body", &row["body"], &answer.body, &mut out);
    if let Some(title) = row.get("html_title").and_then(Value::as_str) {
        if answer.html_title.as_deref() != Some(title) {
            out.push((
                "html_title".into(),
                title.to_owned(),
                format!("{:?}", answer.html_title),
            ));
        }
    }
    out
}

/// The 65 requests of the burst: the participant reading its submission, with a listing it
/// may not make (400, which still counts) as every twelfth request.
async fn burst(replay: &Replay) -> Value {
    replay.fake.reset_throttle();
    let mut counts: BTreeMap<String, u64> = BTreeMap::new();
    let mut first_429 = None;
    let mut after = Vec::new();
    for i in 1..=65u64 {
        let path = if i % 12 == 0 {
            "/api/jobs/challenge/1/submission/?status=submitted"
        } else {
            "/api/jobs/submission/1"
        };
        let answer = replay
            .send("GET", path, Some("participant"), &Value::Null)
            .await;
        *counts.entry(answer.status.to_string()).or_default() += 1;
        if first_429.is_some() {
            after.push(answer.status);
        } else if answer.status == 429 {
            first_429 = Some(i);
        }
    }
    after.sort_unstable();
    after.dedup();
    json!({
        "requests": 65,
        "status_counts": counts,
        "first_429_at": first_429,
        "4xx_counted": counts.get("400").copied().unwrap_or(0) > 0 && first_429 == Some(61),
        "statuses_after_first_429": after,
    })
}

/// The recording's facts, computed from the fake's raw answers (by request tag).
async fn check(tag: &str, replay: &Replay, seen: &HashMap<String, Value>) -> Value {
    let body = |t: &str| seen.get(t).unwrap_or_else(|| panic!("{tag} needs {t}"));
    let set = |t: &str, field: &str| !body(t)[field].is_null();
    let moved = |a: &str, b: &str| body(a)["started_at"] != body(b)["started_at"];
    let file_of = |t: &str, field: &str| body(t)[field].clone();
    match tag {
        "P3.s3-result-file" => {
            replay
                .file(&file_of("P3.get-s3-after-bool", "submission_result_file"))
                .await
        }
        "P5.s2-result-file" => {
            replay
                .file(&file_of("P5.get-s2", "submission_result_file"))
                .await
        }
        "F1.started_at-set-by-queued" => json!({
            "before": set("F1.get-submitted", "started_at"),
            "after_queued": set("F1.get-queued", "started_at"),
            "execution_time_after_queued":
                normalise(&body("F1.get-queued")["execution_time"], &replay.base, Some("execution_time")),
        }),
        "F1.started_at-moved-queued-to-running" => json!(moved("F1.get-queued", "F1.get-running")),
        "F1.job_name-after-running" => body("F1.get-running")["job_name"].clone(),
        "F1.started_at-moved-by-partial-put" => json!([
            moved("F1.get-running", "F1.get-partial-1"),
            moved("F1.get-partial-1", "F1.get-partial-2"),
        ]),
        "F1.completed_at-after-partial" => json!([
            set("F1.get-partial-1", "completed_at"),
            set("F1.get-partial-2", "completed_at"),
        ]),
        "F1.result-file-after-partial-2" => {
            replay
                .file(&file_of("F1.get-partial-2", "submission_result_file"))
                .await
        }
        "F1.started_at-moved-by-finished" => json!(moved("F1.get-partial-2", "F1.get-finished")),
        "F1.execution_time-after-finished" => normalise(
            &body("F1.get-finished")["execution_time"],
            &replay.base,
            Some("execution_time"),
        ),
        "F2.result-file" => {
            replay
                .file(&file_of("F2.get-finished", "submission_result_file"))
                .await
        }
        "M.round-trip-equal" => {
            let sent = seen["M.patch-meta.request"]["submission_metadata"].clone();
            json!({
                "patch_response": body("M.patch-meta")["submission_metadata"] == sent,
                "get": body("M.get")["submission_metadata"] == sent,
            })
        }
        "V.v2-result-file" => {
            replay
                .file(&file_of("V.get-v2", "submission_result_file"))
                .await
        }
        "V.x1-result-file" => {
            replay
                .file(&file_of("V.get-x1", "submission_result_file"))
                .await
        }
        "R.burst-summary" => burst(replay).await,
        t if t.starts_with("F1.file.") => {
            let field = &t["F1.file.".len()..];
            replay.file(&file_of("F1.get-finished", field)).await
        }
        other => panic!("the recording has a check this test does not compute: {other}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_fake_answers_the_recorded_requests_as_evalais_real_server_did() {
    let dir = recording_dir();
    let recording: Value =
        serde_json::from_slice(&std::fs::read(dir.join("real-transcript.json")).unwrap()).unwrap();
    let fixture = Fixture::from_path(&dir.join("fake-evalai-fixture.json"))
        .expect("the recording's seed is a valid fixture");
    let fake = FakeEvalAi::start(fixture).await.unwrap();
    let replay = Replay {
        http: reqwest::Client::builder()
            .redirect(reqwest::redirect::Policy::none())
            .build()
            .unwrap(),
        base: fake.url(),
        fake,
    };

    let mut seen: HashMap<String, Value> = HashMap::new();
    let mut differences: Vec<String> = Vec::new();
    let mut accepted_seen = vec![false; ACCEPTED.len()];
    let (mut requests, mut checks) = (0, 0);
    for row in recording["rows"].as_array().unwrap() {
        let tag = row["tag"].as_str().unwrap();
        let mut found: Vec<(String, String, String)> = Vec::new();
        match row["kind"].as_str() {
            Some("request") => {
                requests += 1;
                // Each caller was paced below 60 a minute: only the burst meets the throttle.
                if !tag.starts_with("R.") {
                    replay.fake.reset_throttle();
                }
                let body = row["request_body"].clone();
                let mut answer = replay
                    .send(
                        row["method"].as_str().unwrap(),
                        row["path"].as_str().unwrap(),
                        row["auth"].as_str(),
                        &body,
                    )
                    .await;
                seen.insert(tag.to_owned(), answer.body.clone());
                if let Some(json) = body.get("json") {
                    seen.insert(format!("{tag}.request"), concrete(json));
                }
                answer.body = normalise(&answer.body, &replay.base, None);
                normalise_throttle(&mut answer);
                found = compare(row, &answer);
            }
            Some("check") => {
                checks += 1;
                let value = normalise(&check(tag, &replay, &seen).await, &replay.base, None);
                diff("value", &row["value"], &value, &mut found);
            }
            other => panic!("unknown row kind {other:?} at {tag}"),
        }
        for (place, real, fake) in found {
            let accepted = ACCEPTED
                .iter()
                .position(|(t, at, _)| *t == tag && place.starts_with(at));
            match accepted {
                Some(i) => accepted_seen[i] = true,
                None => differences.push(format!("{tag} {place}: real {real}, fake {fake}")),
            }
        }
    }
    assert_eq!(
        (requests, checks),
        (199, 19),
        "the whole recording was replayed"
    );
    let gone: Vec<String> = ACCEPTED
        .iter()
        .zip(&accepted_seen)
        .filter(|(_, seen)| !**seen)
        .map(|((t, at, _), _)| format!("{t} {at}"))
        .collect();
    assert!(
        gone.is_empty(),
        "accepted differences that no longer occur (take them off the list):\n{}",
        gone.join("\n")
    );
    assert!(
        differences.is_empty(),
        "{} differences from EvalAI's real server:\n{}",
        differences.len(),
        differences.join("\n")
    );
}
