//! The request log: what every caller sent and got, without credentials.

use serde::{Deserialize, Serialize};

/// One request as the fake saw it. The `Authorization` header is never recorded.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RequestRecord {
    /// Sequence number, from 1.
    pub seq: u64,
    /// Arrival time (ISO-8601 UTC).
    pub time: String,
    /// HTTP method.
    pub method: String,
    /// Path (no query).
    pub path: String,
    /// Raw query string, if any.
    pub query: Option<String>,
    /// Response status.
    pub status: u16,
    /// Authenticated user id (when authentication passed).
    pub user_id: Option<u64>,
    /// True for `/_admin/` calls (not part of the EvalAI API).
    pub admin: bool,
    /// The body parsed as the server parsed it (JSON, or form/multipart fields as an object).
    pub body: Option<serde_json::Value>,
    /// The body as text when it could not be parsed (truncated to 64 KiB).
    pub raw_body: Option<String>,
    /// The injected fault, if any (`error_500`, `throttle_429`, `error_500_after`, `slow`).
    pub fault: Option<String>,
    /// Why the server answered HTML 500 (the Python exception EvalAI would raise).
    pub error: Option<String>,
}

/// Bounded in-memory log.
#[derive(Debug, Default)]
pub(crate) struct RequestLog {
    records: Vec<RequestRecord>,
    next_seq: u64,
}

/// Oldest records are dropped beyond this, so a long local run cannot grow without bound.
const MAX_RECORDS: usize = 100_000;

impl RequestLog {
    pub fn push(&mut self, mut record: RequestRecord) {
        self.next_seq += 1;
        record.seq = self.next_seq;
        if self.records.len() >= MAX_RECORDS {
            self.records.remove(0);
        }
        self.records.push(record);
    }

    pub fn since(&self, seq: u64) -> Vec<RequestRecord> {
        self.records
            .iter()
            .filter(|r| r.seq > seq)
            .cloned()
            .collect()
    }
}
