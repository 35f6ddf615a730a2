//! The wake table: what wakes a submission's waiting execution when its results or markers
//! change in S3, or when its participant cancels on EvalAI.
//!
//! One item per submission (partition key `submission_id`, S), ours alone (the stack creates
//! it; it is not one of the original system's tables):
//! - `changes` (N): wake-worthy events counted so far. The Monitor reads it before it looks at
//!   S3 and hands it to the next wait, whose write is conditional on it being unchanged, so an
//!   event during a Monitor round is never slept through.
//! - `token` (S), `execution` (S), `challenge` (N): the waiting task's token, written by the
//!   state machine's wait (`aws-sdk:dynamodb:updateItem.waitForTaskToken`), and whose it is.
//! - `cancel` (BOOL): the cancel sweep found the submission cancelled on EvalAI.
//! - `expires_at` (N): DynamoDB TTL, epoch seconds.
//!
//! A token is taken with the same write that counts the event (`REMOVE token`, old values
//! returned), so of a burst of events one wakes the execution and the others only count, and
//! a token is never handed out twice.

use std::collections::HashMap;

use aws_sdk_dynamodb::types::{AttributeValue, ReturnValue};
use aws_sdk_dynamodb::Client;

use crate::tasks::{Callbacks, Reported};
use crate::{condition_failed, AwsError, Result};

/// How long an item outlives its last write: longer than any evaluation and its queue time.
pub const RETENTION_SECONDS: u64 = 7 * 24 * 3600;

/// What the Monitor reads of the item.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct WakeState {
    /// Events counted so far.
    pub changes: u64,
    /// The participant cancelled (found by the sweep).
    pub cancel: bool,
}

/// A waiting execution's token, taken by the write that woke it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Taken {
    /// The task token to report to Step Functions.
    pub token: String,
    /// The execution it belongs to (for the logs).
    pub execution: Option<String>,
}

/// An execution waiting, as the sweep lists them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Waiting {
    /// EvalAI submission id.
    pub submission_id: u64,
    /// Its EvalAI challenge.
    pub challenge: u64,
    /// EvalAI's `submitted_at` (epoch seconds), when the wait stored one.
    pub submitted_at: Option<u64>,
}

/// The wake table.
#[derive(Debug, Clone)]
pub struct WakeTable {
    client: Client,
    table: String,
}

fn n(value: u64) -> AttributeValue {
    AttributeValue::N(value.to_string())
}

fn key(submission_id: u64) -> HashMap<String, AttributeValue> {
    HashMap::from([(
        "submission_id".to_string(),
        AttributeValue::S(submission_id.to_string()),
    )])
}

fn number(item: &HashMap<String, AttributeValue>, name: &str) -> Option<u64> {
    item.get(name)?.as_n().ok()?.parse().ok()
}

fn taken(old: Option<&HashMap<String, AttributeValue>>) -> Option<Taken> {
    let old = old?;
    let token = old.get("token")?.as_s().ok()?.clone();
    Some(Taken {
        token,
        execution: old.get("execution").and_then(|v| v.as_s().ok()).cloned(),
    })
}

impl WakeTable {
    /// The table named `table`.
    pub fn new(client: Client, table: impl Into<String>) -> Self {
        WakeTable {
            client,
            table: table.into(),
        }
    }

    /// The submission's count and cancel flag, read consistently (the next wait's condition
    /// compares with the item as it is now, not with a replica's).
    pub async fn state(&self, submission_id: u64) -> Result<WakeState> {
        let out = self
            .client
            .get_item()
            .table_name(&self.table)
            .set_key(Some(key(submission_id)))
            .consistent_read(true)
            .projection_expression("#changes, #cancel")
            .expression_attribute_names("#changes", "changes")
            .expression_attribute_names("#cancel", "cancel")
            .send()
            .await
            .map_err(|e| AwsError::sdk("dynamodb", "GetItem", e))?;
        let Some(item) = out.item() else {
            return Ok(WakeState::default());
        };
        Ok(WakeState {
            changes: number(item, "changes").unwrap_or(0),
            cancel: item
                .get("cancel")
                .and_then(|v| v.as_bool().ok())
                .copied()
                .unwrap_or(false),
        })
    }

    /// Counts an event for the submission and takes the waiting token, if any.
    pub async fn count_change(&self, submission_id: u64, now: u64) -> Result<Option<Taken>> {
        let out = self
            .client
            .update_item()
            .table_name(&self.table)
            .set_key(Some(key(submission_id)))
            .update_expression("ADD #changes :one SET #expires = :expires REMOVE #token")
            .expression_attribute_names("#changes", "changes")
            .expression_attribute_names("#expires", "expires_at")
            .expression_attribute_names("#token", "token")
            .expression_attribute_values(":one", n(1))
            .expression_attribute_values(":expires", n(now + RETENTION_SECONDS))
            .return_values(ReturnValue::AllOld)
            .send()
            .await
            .map_err(|e| AwsError::sdk("dynamodb", "UpdateItem", e))?;
        Ok(taken(out.attributes()))
    }

    /// Flags a submission the sweep found cancelled and takes its token. Only an item a wait
    /// created (with its challenge) and not flagged yet is touched: `None` otherwise.
    pub async fn flag_cancel(&self, submission_id: u64) -> Result<Option<Option<Taken>>> {
        let result = self
            .client
            .update_item()
            .table_name(&self.table)
            .set_key(Some(key(submission_id)))
            .update_expression("SET #cancel = :yes ADD #changes :one REMOVE #token")
            .condition_expression("attribute_exists(#challenge) AND attribute_not_exists(#cancel)")
            .expression_attribute_names("#cancel", "cancel")
            .expression_attribute_names("#changes", "changes")
            .expression_attribute_names("#challenge", "challenge")
            .expression_attribute_names("#token", "token")
            .expression_attribute_values(":yes", AttributeValue::Bool(true))
            .expression_attribute_values(":one", n(1))
            .return_values(ReturnValue::AllOld)
            .send()
            .await;
        match result {
            Ok(out) => Ok(Some(taken(out.attributes()))),
            Err(e) if condition_failed(&e) => Ok(None),
            Err(e) => Err(AwsError::sdk("dynamodb", "UpdateItem", e)),
        }
    }

    /// Counts a change for the submission and, if an execution waits on it, reports its token
    /// to `callbacks`: `Ok(None)` when none waited. A failed report puts the token back (a
    /// failed put-back is logged: the wait's own timeout then wakes it) and is the error.
    pub async fn wake<C: Callbacks>(
        &self,
        submission_id: u64,
        now: u64,
        callbacks: &C,
    ) -> Result<Option<Reported>> {
        let Some(taken) = self.count_change(submission_id, now).await? else {
            return Ok(None);
        };
        match callbacks.succeed(&taken.token, "{}").await {
            Ok(reported) => Ok(Some(reported)),
            Err(e) => {
                if let Err(restore) = self.restore_token(submission_id, &taken, false).await {
                    tracing::warn!(submission_id, error = %restore, "could not put the token back; the safety net wakes it");
                }
                Err(e)
            }
        }
    }

    /// Puts back a token whose report failed (Step Functions unreachable), unless a newer
    /// wait already stored one, so that the event's retry can wake the execution. With
    /// `undo_cancel`, the cancel flag the same write set goes too (the sweep's), so the next
    /// sweep finds the submission again.
    pub async fn restore_token(
        &self,
        submission_id: u64,
        taken: &Taken,
        undo_cancel: bool,
    ) -> Result<()> {
        let mut update = self
            .client
            .update_item()
            .table_name(&self.table)
            .set_key(Some(key(submission_id)))
            .expression_attribute_names("#token", "token")
            .expression_attribute_values(":token", AttributeValue::S(taken.token.clone()));
        update = if undo_cancel {
            update
                .update_expression("SET #token = :token REMOVE #cancel")
                .condition_expression("attribute_exists(#cancel) AND attribute_not_exists(#token)")
                .expression_attribute_names("#cancel", "cancel")
        } else {
            update
                .update_expression("SET #token = :token")
                .condition_expression(
                    "attribute_exists(submission_id) AND attribute_not_exists(#token)",
                )
        };
        match update.send().await {
            Ok(_) => Ok(()),
            Err(e) if condition_failed(&e) => Ok(()),
            Err(e) => Err(AwsError::sdk("dynamodb", "UpdateItem", e)),
        }
    }

    /// Every execution waiting now that is not flagged cancelled: what the sweep checks.
    /// The table holds in-flight submissions and, until their TTL, recent ones: one page
    /// (1 MB) covers thousands; the pages are bounded all the same.
    pub async fn waiting(&self) -> Result<Vec<Waiting>> {
        const MAX_PAGES: usize = 20;
        let mut out = Vec::new();
        let mut pages = self
            .client
            .scan()
            .table_name(&self.table)
            .projection_expression("submission_id, #challenge, submitted_at")
            .filter_expression("attribute_exists(#token) AND attribute_not_exists(#cancel)")
            .expression_attribute_names("#challenge", "challenge")
            .expression_attribute_names("#cancel", "cancel")
            .expression_attribute_names("#token", "token")
            .into_paginator()
            .send();
        let mut seen = 0;
        while let Some(page) = pages.next().await {
            let page = page.map_err(|e| AwsError::sdk("dynamodb", "Scan", e))?;
            for item in page.items() {
                let id = item
                    .get("submission_id")
                    .and_then(|v| v.as_s().ok())
                    .and_then(|s| s.parse().ok());
                if let (Some(submission_id), Some(challenge)) = (id, number(item, "challenge")) {
                    out.push(Waiting {
                        submission_id,
                        challenge,
                        submitted_at: number(item, "submitted_at").filter(|t| *t > 0),
                    });
                }
            }
            seen += 1;
            if seen >= MAX_PAGES {
                break;
            }
        }
        Ok(out)
    }
}
