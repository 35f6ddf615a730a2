//! The S3 layout of a submission (`<bucket>/<submission_id>/...`, `docs/storage.md`)
//! and the reads and writes the pipeline makes there.

use aws_sdk_s3::primitives::ByteStream;
use aws_sdk_s3::Client;

use crate::{AwsError, Result};

// The marker folder and the cancel marker are the in-Job protocol's names.
use lb_domain::job::protocol::{self, derived};
pub use lb_domain::job::protocol::{CANCEL_MARKER, STATUS_DIR};
/// Biggest worker results file we read (the results engine refuses more anyway).
pub const MAX_PARTIAL_BYTES: u64 = 64 << 20;

/// One object a listing found.
struct Listed {
    relative: String,
    size: u64,
    etag: String,
    /// Last modified, epoch seconds.
    modified: Option<i64>,
}

/// One worker's partial results file in S3.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PartialObject {
    /// Full key.
    pub key: String,
    /// Pair ID from `partial_agent_results<ID>.json`.
    pub pair_id: u32,
    /// Size in bytes.
    pub size: u64,
    /// ETag: tells whether it changed since the last look without downloading it.
    pub etag: String,
    /// When it was last written (epoch seconds), as S3 lists it.
    pub modified: Option<u64>,
}

/// The EvalAI files and the merged results, written together.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EvalAiObjects<'a> {
    /// `agent_results.json` (merged).
    pub merged: Option<&'a str>,
    /// `evalai/results.json`.
    pub results: &'a str,
    /// `evalai/stdout.txt`.
    pub stdout: &'a str,
    /// `evalai/metadata.json`.
    pub metadata: Option<&'a str>,
}

/// A submission's folder in the results bucket.
#[derive(Debug, Clone)]
pub struct SubmissionStore {
    client: Client,
    bucket: String,
    prefix: String,
}

impl SubmissionStore {
    /// `s3://bucket/<submission_id>/`.
    pub fn new(client: Client, bucket: impl Into<String>, submission_id: u64) -> Self {
        SubmissionStore {
            client,
            bucket: bucket.into(),
            prefix: format!("{submission_id}/"),
        }
    }

    /// `s3://bucket/<id>`, for records (the original's `results`) and messages.
    pub fn location(&self) -> String {
        format!("s3://{}/{}", self.bucket, self.prefix.trim_end_matches('/'))
    }

    /// [`location`](Self::location) without a client.
    pub fn location_of(bucket: &str, submission_id: u64) -> String {
        format!("s3://{bucket}/{submission_id}")
    }

    /// Objects (keys relative to the submission) under `dir`; paginated.
    async fn list(&self, dir: &str) -> Result<Vec<Listed>> {
        let mut out = Vec::new();
        let mut pages = self
            .client
            .list_objects_v2()
            .bucket(&self.bucket)
            .prefix(format!("{}{dir}", self.prefix))
            .into_paginator()
            .send();
        while let Some(page) = pages.next().await {
            let page = page.map_err(|e| AwsError::sdk("s3", "ListObjectsV2", e))?;
            for object in page.contents() {
                let Some(key) = object.key() else { continue };
                out.push(Listed {
                    relative: key.strip_prefix(&self.prefix).unwrap_or(key).to_string(),
                    size: object.size().unwrap_or(0).max(0) as u64,
                    etag: object.e_tag().unwrap_or_default().to_string(),
                    modified: object.last_modified().map(|t| t.secs()),
                });
            }
        }
        Ok(out)
    }

    /// The workers' partial results files, by pair ID. Other names under `agent/` are ignored.
    pub async fn partials(&self) -> Result<Vec<PartialObject>> {
        let mut out: Vec<PartialObject> = self
            .list(&format!("{}/", protocol::AGENT_DIR))
            .await?
            .into_iter()
            .filter_map(
                |Listed {
                     relative,
                     size,
                     etag,
                     modified,
                 }| {
                    let pair_id = protocol::pair_of_results_name(
                        relative
                            .strip_prefix(protocol::AGENT_DIR)?
                            .strip_prefix('/')?,
                    )?;
                    Some(PartialObject {
                        key: format!("{}{relative}", self.prefix),
                        pair_id,
                        size,
                        etag,
                        modified: modified.and_then(|t| u64::try_from(t).ok()),
                    })
                },
            )
            .collect();
        out.sort_by_key(|p| p.pair_id);
        Ok(out)
    }

    /// The last `bytes` bytes of `key` (relative to the submission's folder; all of it when
    /// shorter), `None` when it does not exist: one ranged GET, whatever the object's size.
    pub async fn get_tail(&self, key: &str, bytes: u64) -> Result<Option<Vec<u8>>> {
        let body = self.ranged(key, format!("bytes=-{bytes}")).await?;
        // NB: a server that ignores the range sends everything; keep the tail anyway.
        Ok(body.map(|b| b[b.len().saturating_sub(bytes as usize)..].to_vec()))
    }

    /// `key` (relative to the submission's folder) from byte `offset` on: empty when it has no
    /// more, `None` when it does not exist. What `lbctl logs --follow` reads of a grown log.
    pub async fn get_from(&self, key: &str, offset: u64) -> Result<Option<Vec<u8>>> {
        self.ranged(key, format!("bytes={offset}-")).await
    }

    /// The files under `logs/`, relative to the submission's folder, with their sizes.
    pub async fn logs(&self) -> Result<Vec<(String, u64)>> {
        self.sized(lb_domain::job::protocol::LOGS_DIR).await
    }

    /// The files under `recorder/` (the CARLA recordings), relative to the submission's
    /// folder, with their sizes.
    pub async fn recordings(&self) -> Result<Vec<(String, u64)>> {
        self.sized(lb_domain::job::protocol::RECORDER_DIR).await
    }

    async fn sized(&self, dir: &str) -> Result<Vec<(String, u64)>> {
        let mut out: Vec<(String, u64)> = self
            .list(&format!("{dir}/"))
            .await?
            .into_iter()
            .map(|l| (l.relative, l.size))
            .collect();
        out.sort();
        Ok(out)
    }

    /// The first `bytes` of `key` (relative to the submission's folder), `None` when it does
    /// not exist.
    pub async fn get_head(&self, key: &str, bytes: u64) -> Result<Option<Vec<u8>>> {
        let last = bytes.saturating_sub(1);
        let body = self.ranged(key, format!("bytes=0-{last}")).await?;
        // NB: a server that ignores the range sends everything; keep the head only.
        Ok(body.map(|mut b| {
            b.truncate(bytes as usize);
            b
        }))
    }

    async fn ranged(&self, key: &str, range: String) -> Result<Option<Vec<u8>>> {
        let out = self
            .client
            .get_object()
            .bucket(&self.bucket)
            .key(format!("{}{key}", self.prefix))
            .range(range)
            .send()
            .await;
        let out = match out {
            Ok(out) => out,
            Err(e) if e.as_service_error().is_some_and(|e| e.is_no_such_key()) => return Ok(None),
            // No byte in the range (an empty object, nothing past the offset): 416 InvalidRange.
            Err(e) if e.raw_response().is_some_and(|r| r.status().as_u16() == 416) => {
                return Ok(Some(Vec::new()))
            }
            Err(e) => return Err(AwsError::sdk("s3", "GetObject", e)),
        };
        Ok(Some(read_body(out.body).await?))
    }

    /// Reads an object, refusing more than `limit` bytes (it may come from the participant).
    pub async fn get_bounded(&self, key: &str, limit: u64) -> Result<Vec<u8>> {
        let out = self
            .client
            .get_object()
            .bucket(&self.bucket)
            .key(key)
            .send()
            .await
            .map_err(|e| AwsError::sdk("s3", "GetObject", e))?;
        let size = out.content_length().unwrap_or(0).max(0) as u64;
        if size > limit {
            return Err(AwsError::TooLarge {
                bucket: self.bucket.clone(),
                key: key.to_string(),
                size,
                limit,
            });
        }
        let bytes = read_body(out.body).await?;
        if bytes.len() as u64 > limit {
            return Err(AwsError::TooLarge {
                bucket: self.bucket.clone(),
                key: key.to_string(),
                size: bytes.len() as u64,
                limit,
            });
        }
        Ok(bytes)
    }

    /// The marker file names under `containers-status/`.
    pub async fn markers(&self) -> Result<Vec<String>> {
        self.markers_since(0).await
    }

    /// The marker file names under `containers-status/` written at or after `since` (epoch
    /// seconds): a run's own, not those an earlier run of the submission left until its
    /// Jobs' init removes them.
    pub async fn markers_since(&self, since: u64) -> Result<Vec<String>> {
        let dir = format!("{STATUS_DIR}/");
        let since = i64::try_from(since).unwrap_or(i64::MAX);
        Ok(self
            .list(&dir)
            .await?
            .into_iter()
            .filter(|l| since == 0 || l.modified.is_some_and(|t| t >= since))
            .filter_map(|l| l.relative.strip_prefix(&dir).map(str::to_owned))
            .filter(|name| !name.is_empty() && !name.contains('/'))
            .collect())
    }

    /// Writes the cancel marker the Jobs' logcopy mirrors into the pods.
    pub async fn put_cancel_marker(&self) -> Result<()> {
        self.put(
            &format!("{STATUS_DIR}/{CANCEL_MARKER}"),
            Vec::new(),
            "application/octet-stream",
        )
        .await
    }

    /// Writes the merged results and the EvalAI files.
    pub async fn put_evalai_files(&self, files: &EvalAiObjects<'_>) -> Result<()> {
        // Independent objects: written at once, not one after another.
        tokio::try_join!(
            self.put_json(derived::MERGED, files.merged),
            self.put(
                derived::EVALAI_RESULTS,
                files.results.as_bytes().to_vec(),
                "application/json",
            ),
            self.put(
                derived::EVALAI_STDOUT,
                files.stdout.as_bytes().to_vec(),
                "text/plain; charset=utf-8",
            ),
            self.put_json(derived::EVALAI_METADATA, files.metadata),
        )?;
        Ok(())
    }

    /// A JSON object, when there is one to write.
    async fn put_json(&self, relative: &str, body: Option<&str>) -> Result<()> {
        match body {
            Some(body) => {
                self.put(relative, body.as_bytes().to_vec(), "application/json")
                    .await
            }
            None => Ok(()),
        }
    }

    /// Puts one object under the submission prefix.
    pub async fn put(&self, relative: &str, body: Vec<u8>, content_type: &str) -> Result<()> {
        self.client
            .put_object()
            .bucket(&self.bucket)
            .key(format!("{}{relative}", self.prefix))
            .content_type(content_type)
            .body(ByteStream::from(body))
            .send()
            .await
            .map_err(|e| AwsError::sdk("s3", "PutObject", e))?;
        Ok(())
    }
}

/// A GetObject body, read whole; a stream broken midway is transient (the next round reads
/// again).
async fn read_body(body: aws_sdk_s3::primitives::ByteStream) -> Result<Vec<u8>> {
    let bytes = body.collect().await.map_err(|e| AwsError::Transient {
        service: "s3",
        operation: "GetObject",
        source: Box::new(e),
    })?;
    Ok(bytes.into_bytes().to_vec())
}
