//! The S3 client (built once) and the few operations init and logcopy need, all streaming.

use std::error::Error as StdError;
use std::io::{self, Read};
use std::path::Path;
use std::time::Duration;

use aws_config::retry::RetryConfig;
use aws_config::timeout::TimeoutConfig;
use aws_config::{BehaviorVersion, Region};
use aws_sdk_s3::config::RequestChecksumCalculation;
use aws_sdk_s3::error::DisplayErrorContext;
use aws_sdk_s3::primitives::ByteStream;
use aws_sdk_s3::types::{CompletedMultipartUpload, CompletedPart};
use aws_sdk_s3::Client;
use aws_smithy_http_client::tls;
use sha2::{Digest, Sha256};
use tokio::io::AsyncWriteExt;

use crate::config::AwsConfig;

/// Objects up to this size go in one PUT, read into memory once (and hashed on the way);
/// larger ones go in parts of this size, S3's smallest. It bounds the memory an upload holds
/// (logcopy's budget is 20 MiB resident, of which the mapped binary takes about 9).
pub const PART_BYTES: u64 = 5 * 1024 * 1024;

/// S3 allows at most this many parts in an upload.
const MAX_PARTS: u64 = 10_000;

/// The largest file uploaded: 10,000 parts of [`PART_BYTES`] (about 48 GiB).
pub const MAX_OBJECT_BYTES: u64 = PART_BYTES * MAX_PARTS;

/// A failed S3 call; the SDK error is kept as the source.
#[derive(Debug, thiserror::Error)]
#[error("S3 {op} of `{key}` failed: {}", DisplayErrorContext(&**.source))]
pub struct S3Error {
    /// The operation (`PutObject`, ...).
    pub op: &'static str,
    /// The key or prefix.
    pub key: String,
    /// The SDK's error.
    #[source]
    pub source: Box<dyn StdError + Send + Sync>,
}

/// A failed upload: the local file or S3.
#[derive(Debug, thiserror::Error)]
pub enum UploadError {
    /// The local file could not be read; S3 is not at fault.
    #[error("cannot read `{path}`: {source}")]
    Read {
        /// The file.
        path: String,
        /// Why.
        #[source]
        source: io::Error,
    },
    /// S3 refused or could not be reached.
    #[error(transparent)]
    S3(#[from] S3Error),
}

/// The bucket and a client for it.
#[derive(Debug, Clone)]
pub struct S3 {
    client: Client,
    bucket: String,
}

fn s3_err<'k, E: StdError + Send + Sync + 'static>(
    op: &'static str,
    key: &'k str,
) -> impl FnOnce(E) -> S3Error + 'k {
    move |e| S3Error {
        op,
        key: key.to_owned(),
        source: Box::new(e),
    }
}

impl S3 {
    /// Builds the client: rustls on ring, short connect timeout, a few retries with backoff,
    /// and path-style addressing when an endpoint override (moto) is set.
    pub async fn connect(cfg: &AwsConfig) -> S3 {
        let http = aws_smithy_http_client::Builder::new()
            .tls_provider(tls::Provider::Rustls(
                tls::rustls_provider::CryptoMode::Ring,
            ))
            .build_https();
        let mut loader = aws_config::defaults(BehaviorVersion::latest())
            .region(Region::new(cfg.region.clone()))
            .http_client(http)
            .timeout_config(
                TimeoutConfig::builder()
                    .connect_timeout(Duration::from_secs(5))
                    .read_timeout(Duration::from_secs(60))
                    .build(),
            )
            .retry_config(
                RetryConfig::standard()
                    .with_max_attempts(3)
                    .with_initial_backoff(Duration::from_millis(200))
                    .with_max_backoff(Duration::from_secs(5)),
            );
        if let Some(url) = &cfg.endpoint_url {
            loader = loader.endpoint_url(url);
        }
        let shared = loader.load().await;
        let conf = aws_sdk_s3::config::Builder::from(&shared)
            .force_path_style(cfg.endpoint_url.is_some())
            // NB: checksums only where S3 requires them: the SigV4 payload hash already
            // covers the bytes, and emulators differ in their trailing-checksum support.
            .request_checksum_calculation(RequestChecksumCalculation::WhenRequired)
            .build();
        S3 {
            client: Client::from_conf(conf),
            bucket: cfg.bucket.clone(),
        }
    }

    /// The bucket.
    pub fn bucket(&self) -> &str {
        &self.bucket
    }

    /// Whether an object exists.
    pub async fn exists(&self, key: &str) -> Result<bool, S3Error> {
        match self
            .client
            .head_object()
            .bucket(&self.bucket)
            .key(key)
            .send()
            .await
        {
            Ok(_) => Ok(true),
            Err(e) if e.as_service_error().is_some_and(|s| s.is_not_found()) => Ok(false),
            Err(e) => Err(s3_err("HeadObject", key)(e)),
        }
    }

    /// Writes an object from memory, with this tag (`key=value`) when one is given.
    pub async fn put(&self, key: &str, bytes: Vec<u8>, tag: Option<&str>) -> Result<(), S3Error> {
        let len = bytes.len() as i64;
        self.client
            .put_object()
            .bucket(&self.bucket)
            .key(key)
            .set_tagging(tag.map(str::to_owned))
            .content_length(len)
            .body(ByteStream::from(bytes))
            .send()
            .await
            .map_err(s3_err("PutObject", key))?;
        Ok(())
    }

    /// Deletes an object (a missing one is fine).
    pub async fn delete(&self, key: &str) -> Result<(), S3Error> {
        self.client
            .delete_object()
            .bucket(&self.bucket)
            .key(key)
            .send()
            .await
            .map_err(s3_err("DeleteObject", key))?;
        Ok(())
    }

    /// Keys and sizes under a prefix, at most `limit` of them.
    pub async fn list(&self, prefix: &str, limit: usize) -> Result<Vec<(String, u64)>, S3Error> {
        let mut out = Vec::new();
        let mut token: Option<String> = None;
        loop {
            let page = self
                .client
                .list_objects_v2()
                .bucket(&self.bucket)
                .prefix(prefix)
                .set_continuation_token(token.take())
                .send()
                .await
                .map_err(s3_err("ListObjectsV2", prefix))?;
            for object in page.contents() {
                if let Some(key) = object.key() {
                    out.push((
                        key.to_owned(),
                        u64::try_from(object.size().unwrap_or(0)).unwrap_or(0),
                    ));
                }
            }
            token = page.next_continuation_token().map(str::to_owned);
            if token.is_none() || out.len() >= limit {
                out.truncate(limit);
                return Ok(out);
            }
        }
    }

    /// An object's GetObject answer, its body still to read (`None`: no such object).
    async fn get(
        &self,
        key: &str,
    ) -> Result<Option<aws_sdk_s3::operation::get_object::GetObjectOutput>, S3Error> {
        match self
            .client
            .get_object()
            .bucket(&self.bucket)
            .key(key)
            .send()
            .await
        {
            Ok(resp) => Ok(Some(resp)),
            Err(e) if e.as_service_error().is_some_and(|s| s.is_no_such_key()) => Ok(None),
            Err(e) => Err(s3_err("GetObject", key)(e)),
        }
    }

    /// A small object's bytes, at most `limit` of them (`None`: no such object, or larger).
    pub async fn get_small(&self, key: &str, limit: usize) -> Result<Option<Vec<u8>>, S3Error> {
        let Some(resp) = self.get(key).await? else {
            return Ok(None);
        };
        if resp.content_length().unwrap_or(0) > limit as i64 {
            return Ok(None);
        }
        let mut body = resp.body;
        let mut bytes = Vec::new();
        while let Some(chunk) = body.next().await {
            bytes.extend_from_slice(&chunk.map_err(s3_err("GetObject", key))?);
            if bytes.len() > limit {
                return Ok(None);
            }
        }
        Ok(Some(bytes))
    }

    /// Streams an object into `dest` (through a temporary file beside it, then renamed).
    /// Returns `false` when there is no such object.
    pub async fn download(&self, key: &str, dest: &Path) -> Result<bool, UploadError> {
        let Some(resp) = self.get(key).await? else {
            return Ok(false);
        };
        let local = |source| UploadError::Read {
            path: dest.display().to_string(),
            source,
        };
        let dir = dest.parent().unwrap_or(Path::new("."));
        let tmp = tempfile::Builder::new()
            .prefix(".lb-download-")
            .tempfile_in(dir)
            .map_err(local)?;
        let (std_file, tmp_path) = tmp.into_parts();
        let mut file = tokio::fs::File::from_std(std_file);
        let mut body = resp.body;
        while let Some(chunk) = body.next().await {
            let chunk = chunk.map_err(s3_err("GetObject", key))?;
            file.write_all(&chunk).await.map_err(local)?;
        }
        file.flush().await.map_err(local)?;
        drop(file);
        tmp_path.persist(dest).map_err(|e| local(e.error))?;
        Ok(true)
    }

    /// Uploads `size` bytes of an open file in parts of [`PART_BYTES`], holding one part in
    /// memory at a time; returns the SHA-256 of what was sent. A failed upload is aborted so
    /// no parts linger.
    pub async fn put_multipart(
        &self,
        key: &str,
        file: &mut std::fs::File,
        size: u64,
        (path, tag): (&str, Option<&str>),
    ) -> Result<[u8; 32], UploadError> {
        let upload = self
            .client
            .create_multipart_upload()
            .bucket(&self.bucket)
            .key(key)
            .set_tagging(tag.map(str::to_owned))
            .send()
            .await
            .map_err(s3_err("CreateMultipartUpload", key))?;
        let upload_id = upload.upload_id().unwrap_or_default().to_owned();
        let result = self.upload_parts(key, &upload_id, file, size, path).await;
        match result {
            Ok((parts, hash)) => {
                self.client
                    .complete_multipart_upload()
                    .bucket(&self.bucket)
                    .key(key)
                    .upload_id(&upload_id)
                    .multipart_upload(
                        CompletedMultipartUpload::builder()
                            .set_parts(Some(parts))
                            .build(),
                    )
                    .send()
                    .await
                    .map_err(s3_err("CompleteMultipartUpload", key))?;
                Ok(hash)
            }
            Err(e) => {
                // NB: best effort; a bucket lifecycle rule cleans up what this misses.
                if let Err(abort) = self
                    .client
                    .abort_multipart_upload()
                    .bucket(&self.bucket)
                    .key(key)
                    .upload_id(&upload_id)
                    .send()
                    .await
                {
                    tracing::debug!(%key, error = %DisplayErrorContext(&abort), "cannot abort a multipart upload");
                }
                Err(e)
            }
        }
    }

    async fn upload_parts(
        &self,
        key: &str,
        upload_id: &str,
        file: &mut std::fs::File,
        size: u64,
        path: &str,
    ) -> Result<(Vec<CompletedPart>, [u8; 32]), UploadError> {
        let mut hasher = Sha256::new();
        let mut parts = Vec::new();
        let mut sent = 0u64;
        let mut number = 1i32;
        while sent < size {
            let want = PART_BYTES.min(size - sent);
            let mut buf = Vec::with_capacity(want as usize);
            (&mut *file)
                .take(want)
                .read_to_end(&mut buf)
                .map_err(|source| UploadError::Read {
                    path: path.to_owned(),
                    source,
                })?;
            if buf.is_empty() {
                // The file shrank while we read it; what was read is what we know.
                break;
            }
            hasher.update(&buf);
            sent += buf.len() as u64;
            let len = buf.len() as i64;
            let part = self
                .client
                .upload_part()
                .bucket(&self.bucket)
                .key(key)
                .upload_id(upload_id)
                .part_number(number)
                .content_length(len)
                .body(ByteStream::from(buf))
                .send()
                .await
                .map_err(s3_err("UploadPart", key))?;
            parts.push(
                CompletedPart::builder()
                    .part_number(number)
                    .set_e_tag(part.e_tag().map(str::to_owned))
                    .build(),
            );
            number += 1;
        }
        Ok((parts, hasher.finalize().into()))
    }
}
