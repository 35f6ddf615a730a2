//! The admission table: each leaderboard's evaluation queue and its teams' holds
//! (`lb_domain::capacity::queue` decides the order). Admitting is one `TransactWriteItems`: the team's
//! hold, conditional on the team holding fewer than its cap, and the entry's move from
//! `waiting` to `admitted`, conditional on it still waiting. Two Launches or Monitors racing
//! for a team's last place cannot both get it, and a retried admission changes nothing.
//!
//! The table is ours alone (the stack creates it). Partition key `queue` (S, the leaderboard:
//! `"2.0"`), sort key `key` (S):
//! - `submission#<id>`: an entry: `submission_id`, `team_id`, `arrived_ms` (N), `state` (S:
//!   `waiting`, `admitted`, `running`), `execution` (S, the execution that queued it last),
//!   `expires_at` (N, DynamoDB TTL) past any queue time and evaluation; once running,
//!   `running_since` (N, epoch seconds) and, from its Monitor's rounds, `pairs`, `routes` and
//!   `routes_done` (N): what the queue note's forecast reads of a run
//!   (`lb_domain::capacity::forecast`).
//! - `team#<id>`: a team's holds: `holders` (SS of submission ids).
//! - `pace#<track>`: `durations` (L of N): the seconds its latest evaluations ran, oldest first
//!   (`lb_domain::capacity::queue::RECENT_DURATIONS` of them), for the queue note's estimated start.
//! - `fleet`: the leaderboard's cluster as the sweep counted it last, `free`, `booting` and
//!   `addable` GPUs (N) at `at` (N, epoch seconds): what the note's forecast waits for besides
//!   the running pairs (`lb_domain::capacity::forecast::Capacity`).
//!
//! Admission decides on the holders as they are when it writes, never on an earlier read of
//! the queue: the hold is conditional on the set's size, and a holder whose entry is gone
//! (its TTL, an operator) is dropped by a transaction conditional on the entry still being
//! gone. A holder whose execution ended without Finalize is the reaper's to release.

use std::collections::HashMap;

use aws_sdk_dynamodb::operation::update_item::builders::UpdateItemFluentBuilder;
use aws_sdk_dynamodb::types::{AttributeValue, Delete, TransactWriteItem, Update};
use aws_sdk_dynamodb::Client;
use lb_domain::capacity::forecast::{Capacity, Progress};
use lb_domain::capacity::queue::{Entry, EntryState};

use crate::{condition_failed, AwsError, Result};

/// How long an entry is kept after its arrival: the longest queue (336 hours) and the longest
/// evaluation (72 hours), and a day for Finalize's retries.
pub const ENTRY_RETENTION_SECONDS: u64 = (336 + 72 + 24) * 3600;

/// The pages of one queue read at most (1 MB each: thousands of entries).
const MAX_PAGES: usize = 20;

/// What an admission attempt found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Admit {
    /// The submission holds one of its team's places (now, or since an earlier attempt).
    Admitted,
    /// Its team holds all its places: it waits.
    Held,
}

/// The admission table.
#[derive(Debug, Clone)]
pub struct AdmissionTable {
    client: Client,
    table: String,
}

fn s(value: impl Into<String>) -> AttributeValue {
    AttributeValue::S(value.into())
}

fn n(value: u64) -> AttributeValue {
    AttributeValue::N(value.to_string())
}

fn pace_key(queue: &str, track: &str) -> HashMap<String, AttributeValue> {
    HashMap::from([
        ("queue".to_string(), s(queue)),
        ("key".to_string(), s(format!("pace#{track}"))),
    ])
}

fn fleet_key(queue: &str) -> HashMap<String, AttributeValue> {
    HashMap::from([
        ("queue".to_string(), s(queue)),
        ("key".to_string(), s("fleet")),
    ])
}

fn entry_key(queue: &str, submission_id: u64) -> HashMap<String, AttributeValue> {
    HashMap::from([
        ("queue".to_string(), s(queue)),
        ("key".to_string(), s(format!("submission#{submission_id}"))),
    ])
}

fn team_key(queue: &str, team_id: u64) -> HashMap<String, AttributeValue> {
    HashMap::from([
        ("queue".to_string(), s(queue)),
        ("key".to_string(), s(format!("team#{team_id}"))),
    ])
}

fn malformed(problem: String) -> AwsError {
    AwsError::Malformed {
        what: "admission entry".into(),
        problem,
    }
}

/// An entry item read back; anything else than what [`AdmissionTable::enqueue`] writes is
/// refused by name.
fn entry_of(item: &HashMap<String, AttributeValue>) -> Result<Entry> {
    let number = |name: &str| -> Result<u64> {
        item.get(name)
            .and_then(|v| v.as_n().ok())
            .and_then(|v| v.parse().ok())
            .ok_or_else(|| malformed(format!("`{name}` is not a number")))
    };
    let state = item
        .get("state")
        .and_then(|v| v.as_s().ok())
        .and_then(|v| v.parse::<EntryState>().ok())
        .ok_or_else(|| malformed("`state` is not waiting, admitted or running".into()))?;
    Ok(Entry {
        submission_id: number("submission_id")?,
        team_id: number("team_id")?,
        arrived_ms: number("arrived_ms")?,
        state,
    })
}

/// A running entry's progress, when all of it is there.
fn progress_of(item: &HashMap<String, AttributeValue>) -> Option<Progress> {
    let number = |name: &str| item.get(name)?.as_n().ok()?.parse::<u64>().ok();
    Some(Progress {
        pairs: u32::try_from(number("pairs")?).ok()?,
        done: number("routes_done")?,
        routes: number("routes")?,
        since: number("running_since")?,
    })
}

/// A team item's holders, sorted (none when the item or its set is absent: DynamoDB removes
/// a set emptied by `DELETE`).
fn holders_of(item: Option<&HashMap<String, AttributeValue>>) -> Vec<String> {
    let mut holders = item
        .and_then(|item| item.get("holders"))
        .and_then(|v| v.as_ss().ok())
        .cloned()
        .unwrap_or_default();
    holders.sort();
    holders
}

/// A transaction one of whose conditions refused it (rather than a failure to retry).
fn transaction_refused<R>(
    e: &aws_sdk_dynamodb::error::SdkError<
        aws_sdk_dynamodb::operation::transact_write_items::TransactWriteItemsError,
        R,
    >,
) -> bool {
    use aws_sdk_dynamodb::operation::transact_write_items::TransactWriteItemsError;
    match e.as_service_error() {
        Some(TransactWriteItemsError::TransactionCanceledException(c)) => c
            .cancellation_reasons()
            .iter()
            .any(|r| r.code() == Some("ConditionalCheckFailed")),
        _ => false,
    }
}

impl AdmissionTable {
    /// The table named `table`.
    pub fn new(client: Client, table: impl Into<String>) -> Self {
        AdmissionTable {
            client,
            table: table.into(),
        }
    }

    /// Puts `entry` in `queue` for `execution` unless it is there already, and returns it as
    /// stored: a retried Launch keeps the first arrival, hence its place. An entry already
    /// there from another execution (a resume of a run that never reached Finalize) becomes
    /// this execution's, so the reaper of the old one leaves it alone.
    pub async fn enqueue(&self, queue: &str, entry: &Entry, execution: &str) -> Result<Entry> {
        let mut item = entry_key(queue, entry.submission_id);
        item.insert("execution".into(), s(execution));
        item.insert("submission_id".into(), n(entry.submission_id));
        item.insert("team_id".into(), n(entry.team_id));
        item.insert("arrived_ms".into(), n(entry.arrived_ms));
        item.insert("state".into(), s(entry.state.as_str()));
        item.insert(
            "expires_at".into(),
            n(entry.arrived_ms / 1000 + ENTRY_RETENTION_SECONDS),
        );
        let put = self
            .client
            .put_item()
            .table_name(&self.table)
            .set_item(Some(item))
            .condition_expression("attribute_not_exists(#key)")
            .expression_attribute_names("#key", "key")
            .send()
            .await;
        match put {
            Ok(_) => Ok(entry.clone()),
            Err(e) if condition_failed(&e) => {
                self.adopt(queue, entry.submission_id, execution).await?;
                self.entry(queue, entry.submission_id)
                    .await?
                    .ok_or_else(|| malformed("the entry vanished while it was written".into()))
            }
            Err(e) => Err(AwsError::sdk("dynamodb", "PutItem", e)),
        }
    }

    /// Makes an existing entry `execution`'s (nothing when it is already, or when there is no
    /// entry): a resume's new execution, or the execution a long run continued as.
    pub async fn adopt(&self, queue: &str, submission_id: u64, execution: &str) -> Result<()> {
        self.update_entry(queue, submission_id, |update| {
            update
                .update_expression("SET #execution = :me")
                .condition_expression("attribute_exists(#key) AND (attribute_not_exists(#execution) OR #execution <> :me)")
                .expression_attribute_names("#execution", "execution")
                .expression_attribute_names("#key", "key")
                .expression_attribute_values(":me", s(execution))
        })
        .await
    }

    /// The execution that queued `submission_id` last (`None`: no entry, or one written before
    /// entries named it).
    pub async fn execution_of(&self, queue: &str, submission_id: u64) -> Result<Option<String>> {
        Ok(self
            .get(entry_key(queue, submission_id))
            .await?
            .and_then(|item| item.get("execution")?.as_s().ok().cloned()))
    }

    /// The item of `key`, read consistently.
    async fn get(
        &self,
        key: HashMap<String, AttributeValue>,
    ) -> Result<Option<HashMap<String, AttributeValue>>> {
        let out = self
            .client
            .get_item()
            .table_name(&self.table)
            .set_key(Some(key))
            .consistent_read(true)
            .send()
            .await
            .map_err(|e| AwsError::sdk("dynamodb", "GetItem", e))?;
        Ok(out.item)
    }

    /// One submission's entry, read consistently.
    pub async fn entry(&self, queue: &str, submission_id: u64) -> Result<Option<Entry>> {
        self.get(entry_key(queue, submission_id))
            .await?
            .as_ref()
            .map(entry_of)
            .transpose()
    }

    /// Every item of `queue` whose key begins with `prefix`, read consistently, at most
    /// [`MAX_PAGES`] pages.
    async fn items_with_prefix(
        &self,
        queue: &str,
        prefix: &str,
    ) -> Result<Vec<HashMap<String, AttributeValue>>> {
        let mut pages = self
            .client
            .query()
            .table_name(&self.table)
            .consistent_read(true)
            .key_condition_expression("#queue = :queue AND begins_with(#key, :prefix)")
            .expression_attribute_names("#queue", "queue")
            .expression_attribute_names("#key", "key")
            .expression_attribute_values(":queue", s(queue))
            .expression_attribute_values(":prefix", s(prefix))
            .into_paginator()
            .send();
        let mut items = Vec::new();
        let mut read = 0;
        while let Some(page) = pages.next().await {
            let page = page.map_err(|e| AwsError::sdk("dynamodb", "Query", e))?;
            items.extend(page.items().iter().cloned());
            read += 1;
            if read >= MAX_PAGES {
                break;
            }
        }
        Ok(items)
    }

    /// Every entry of `queue`, in arrival order, read consistently. An entry someone edited
    /// into another shape is left out (and logged), not a reason to stop the queue.
    pub async fn entries(&self, queue: &str) -> Result<Vec<Entry>> {
        let entries = self.entries_with_progress(queue).await?;
        Ok(entries.into_iter().map(|(entry, _)| entry).collect())
    }

    /// Admits `me` (waiting in `queue`) if its team holds fewer than `limit` places. When the
    /// team is full, holders whose entries are gone are dropped first, each by a transaction
    /// conditional on its entry still being gone when the drop is written.
    pub async fn admit(&self, queue: &str, me: &Entry, limit: u32) -> Result<Admit> {
        if me.state != EntryState::Waiting {
            return Ok(Admit::Admitted);
        }
        if self.try_admit(queue, me, limit).await? {
            return Ok(Admit::Admitted);
        }
        let mut dropped = false;
        for orphan in self.orphans(queue, me.team_id).await? {
            dropped |= self.drop_orphan(queue, me.team_id, &orphan).await?;
        }
        Ok(if dropped && self.try_admit(queue, me, limit).await? {
            Admit::Admitted
        } else {
            Admit::Held
        })
    }

    /// The team's holders whose entries are gone, each entry read after the holders were.
    pub async fn orphans(&self, queue: &str, team_id: u64) -> Result<Vec<String>> {
        let mut orphans = Vec::new();
        for holder in self.holders(queue, team_id).await? {
            let Ok(id) = holder.parse::<u64>() else {
                // Nothing we write: an operator's edit, never an entry's key.
                orphans.push(holder);
                continue;
            };
            if self.get(entry_key(queue, id)).await?.is_none() {
                orphans.push(holder);
            }
        }
        Ok(orphans)
    }

    /// Drops `holder` from the team's holds if its entry is still gone: `false` when the entry
    /// came back meanwhile (a resume queued it again), and then the hold stays.
    pub async fn drop_orphan(&self, queue: &str, team_id: u64, holder: &str) -> Result<bool> {
        let gone = aws_sdk_dynamodb::types::ConditionCheck::builder()
            .table_name(&self.table)
            .set_key(Some(HashMap::from([
                ("queue".to_string(), s(queue)),
                ("key".to_string(), s(format!("submission#{holder}"))),
            ])))
            .condition_expression("attribute_not_exists(#key)")
            .expression_attribute_names("#key", "key")
            .build()
            .map_err(|e| malformed(e.to_string()))?;
        let drop = Update::builder()
            .table_name(&self.table)
            .set_key(Some(team_key(queue, team_id)))
            .update_expression("DELETE #holders :holder")
            .expression_attribute_names("#holders", "holders")
            .expression_attribute_values(":holder", AttributeValue::Ss(vec![holder.to_string()]))
            .build()
            .map_err(|e| malformed(e.to_string()))?;
        let result = self
            .client
            .transact_write_items()
            .transact_items(TransactWriteItem::builder().condition_check(gone).build())
            .transact_items(TransactWriteItem::builder().update(drop).build())
            .send()
            .await;
        match result {
            Ok(_) => {
                tracing::warn!(team_id, holder, "dropped a hold whose entry is gone");
                Ok(true)
            }
            Err(e) if transaction_refused(&e) => Ok(false),
            Err(e) => Err(AwsError::sdk("dynamodb", "TransactWriteItems", e)),
        }
    }

    /// The transaction: the team's hold and the entry's state, both or neither.
    async fn try_admit(&self, queue: &str, me: &Entry, limit: u32) -> Result<bool> {
        let id = me.submission_id.to_string();
        let hold = Update::builder()
            .table_name(&self.table)
            .set_key(Some(team_key(queue, me.team_id)))
            .update_expression("ADD #holders :me")
            // A hold under its own id is its own (an earlier attempt, or a run of it that
            // never gave its place back): taking it again takes no second place.
            .condition_expression(
                "attribute_not_exists(#holders) OR contains(#holders, :id) OR size(#holders) < :limit",
            )
            .expression_attribute_names("#holders", "holders")
            .expression_attribute_values(":me", AttributeValue::Ss(vec![id.clone()]))
            .expression_attribute_values(":id", s(id))
            .expression_attribute_values(":limit", n(u64::from(limit)))
            .build()
            .map_err(|e| malformed(e.to_string()))?;
        let state = Update::builder()
            .table_name(&self.table)
            .set_key(Some(entry_key(queue, me.submission_id)))
            .update_expression("SET #state = :admitted")
            .condition_expression("#state = :waiting")
            .expression_attribute_names("#state", "state")
            .expression_attribute_values(":admitted", s(EntryState::Admitted.as_str()))
            .expression_attribute_values(":waiting", s(EntryState::Waiting.as_str()))
            .build()
            .map_err(|e| malformed(e.to_string()))?;
        let result = self
            .client
            .transact_write_items()
            .transact_items(TransactWriteItem::builder().update(hold).build())
            .transact_items(TransactWriteItem::builder().update(state).build())
            .send()
            .await;
        match result {
            Ok(_) => Ok(true),
            // A condition refused: the team is full (or the entry moved on: read again).
            Err(e) if transaction_refused(&e) => {
                let now = self.entry(queue, me.submission_id).await?;
                Ok(now.is_some_and(|e| e.state != EntryState::Waiting))
            }
            Err(e) => Err(AwsError::sdk("dynamodb", "TransactWriteItems", e)),
        }
    }

    /// The submission ids a team holds places for.
    pub async fn holders(&self, queue: &str, team_id: u64) -> Result<Vec<String>> {
        let item = self.get(team_key(queue, team_id)).await?;
        Ok(holders_of(item.as_ref()))
    }

    /// Every team's holders in `queue`, by team id (a team item someone edited into another
    /// shape is left out, and logged).
    pub async fn holds(&self, queue: &str) -> Result<Vec<(u64, Vec<String>)>> {
        let mut holds = Vec::new();
        for item in self.items_with_prefix(queue, "team#").await? {
            let team = item
                .get("key")
                .and_then(|v| v.as_s().ok())
                .and_then(|k| k.strip_prefix("team#")?.parse::<u64>().ok());
            let Some(team) = team else {
                tracing::warn!(?item, "team item skipped: its key is no team id");
                continue;
            };
            holds.push((team, holders_of(Some(&item))));
        }
        Ok(holds)
    }

    /// Marks the entry running (its first pair started at `since`, epoch seconds; a second
    /// mark keeps the first time). An entry that is not there (a run launched before admission
    /// existed) is left alone.
    pub async fn mark_running(&self, queue: &str, submission_id: u64, since: u64) -> Result<()> {
        self.update_entry(queue, submission_id, |update| {
            update
                .update_expression("SET #state = :running, #since = if_not_exists(#since, :since)")
                .condition_expression("attribute_exists(#key)")
                .expression_attribute_names("#state", "state")
                .expression_attribute_names("#since", "running_since")
                .expression_attribute_names("#key", "key")
                .expression_attribute_values(":running", s(EntryState::Running.as_str()))
                .expression_attribute_values(":since", n(since))
        })
        .await
    }

    /// Keeps a running entry's progress: its `pairs`, routes `done` of `routes`. An entry
    /// that is gone or not running is left alone (nothing waits on it).
    pub async fn record_progress(
        &self,
        queue: &str,
        submission_id: u64,
        pairs: u32,
        (done, routes): (u64, u64),
    ) -> Result<()> {
        self.update_entry(queue, submission_id, |update| {
            update
                .update_expression("SET #pairs = :pairs, #routes = :routes, #done = :done")
                .condition_expression("attribute_exists(#key) AND #state = :running")
                .expression_attribute_names("#pairs", "pairs")
                .expression_attribute_names("#routes", "routes")
                .expression_attribute_names("#done", "routes_done")
                .expression_attribute_names("#state", "state")
                .expression_attribute_names("#key", "key")
                .expression_attribute_values(":pairs", n(u64::from(pairs)))
                .expression_attribute_values(":routes", n(routes))
                .expression_attribute_values(":done", n(done.min(routes)))
                .expression_attribute_values(":running", s(EntryState::Running.as_str()))
        })
        .await
    }

    /// An update of `submission_id`'s entry, made by `update`; one its condition refuses
    /// changes nothing and is no error.
    async fn update_entry(
        &self,
        queue: &str,
        submission_id: u64,
        update: impl FnOnce(UpdateItemFluentBuilder) -> UpdateItemFluentBuilder,
    ) -> Result<()> {
        let request = self
            .client
            .update_item()
            .table_name(&self.table)
            .set_key(Some(entry_key(queue, submission_id)));
        match update(request).send().await {
            Ok(_) => Ok(()),
            Err(e) if condition_failed(&e) => Ok(()),
            Err(e) => Err(AwsError::sdk("dynamodb", "UpdateItem", e)),
        }
    }

    /// [`AdmissionTable::entries`], each running one with its progress when its Monitor has
    /// recorded it (a number out of shape reads as no progress, never as an error).
    pub async fn entries_with_progress(
        &self,
        queue: &str,
    ) -> Result<Vec<(Entry, Option<Progress>)>> {
        let mut entries = Vec::new();
        for item in self.items_with_prefix(queue, "submission#").await? {
            match entry_of(&item) {
                Ok(entry) => entries.push((entry, progress_of(&item))),
                Err(e) => tracing::warn!(error = %e, "admission entry skipped"),
            }
        }
        entries.sort_by_key(|(e, _)| (e.arrived_ms, e.submission_id));
        Ok(entries)
    }

    /// The seconds the latest evaluations of `track` ran, most recent first.
    pub async fn pace(&self, queue: &str, track: &str) -> Result<Vec<u64>> {
        let item = self
            .client
            .get_item()
            .table_name(&self.table)
            .set_key(Some(pace_key(queue, track)))
            .send()
            .await
            .map_err(|e| AwsError::sdk("dynamodb", "GetItem", e))?;
        let durations = item
            .item()
            .and_then(|i| i.get("durations"))
            .and_then(|d| d.as_l().ok())
            .map(|l| {
                l.iter()
                    .filter_map(|v| v.as_n().ok()?.parse().ok())
                    .collect::<Vec<u64>>()
            })
            .unwrap_or_default();
        Ok(durations.into_iter().rev().collect())
    }

    /// Keeps `durations` (most recent first, as [`lb_domain::capacity::queue::with_latest`]
    /// makes them from a [`AdmissionTable::pace`] read) as `track`'s pace. Two at once may keep
    /// one of the two: the pace is an estimate's input, not a record.
    pub async fn keep_pace(&self, queue: &str, track: &str, durations: &[u64]) -> Result<()> {
        let durations = &durations[..durations
            .len()
            .min(lb_domain::capacity::queue::RECENT_DURATIONS)];
        let list = durations.iter().rev().map(|&d| n(d)).collect();
        let mut item = pace_key(queue, track);
        item.insert("durations".into(), AttributeValue::L(list));
        self.put(item).await
    }

    /// Keeps `capacity`, counted at `at` (epoch seconds), as `queue`'s cluster's.
    pub async fn keep_fleet(&self, queue: &str, capacity: &Capacity, at: u64) -> Result<()> {
        let mut item = fleet_key(queue);
        item.insert("free".into(), n(u64::from(capacity.free)));
        item.insert("booting".into(), n(u64::from(capacity.booting)));
        item.insert("addable".into(), n(u64::from(capacity.addable)));
        item.insert("at".into(), n(at));
        self.put(item).await
    }

    /// Writes `item` whole, over what its key held.
    async fn put(&self, item: HashMap<String, AttributeValue>) -> Result<()> {
        self.client
            .put_item()
            .table_name(&self.table)
            .set_item(Some(item))
            .send()
            .await
            .map_err(|e| AwsError::sdk("dynamodb", "PutItem", e))?;
        Ok(())
    }

    /// `queue`'s cluster as the sweep counted it last, and when (epoch seconds); none when it
    /// never did or the item is out of shape.
    pub async fn fleet(&self, queue: &str) -> Result<Option<(Capacity, u64)>> {
        let item = self.get(fleet_key(queue)).await?;
        Ok(item.and_then(|item| {
            let count = |name: &str| -> Option<u64> { item.get(name)?.as_n().ok()?.parse().ok() };
            let gpus = |name: &str| count(name).and_then(|v| u32::try_from(v).ok());
            let capacity = Capacity {
                free: gpus("free")?,
                booting: gpus("booting")?,
                addable: gpus("addable")?,
            };
            Some((capacity, count("at")?))
        }))
    }

    /// Gives the submission's team its place back and takes the submission out of the queue,
    /// in one transaction (both or neither: never an entry gone with its place still held);
    /// repeating it changes nothing.
    pub async fn release(&self, queue: &str, submission_id: u64, team_id: u64) -> Result<()> {
        let me = AttributeValue::Ss(vec![submission_id.to_string()]);
        let place = Update::builder()
            .table_name(&self.table)
            .set_key(Some(team_key(queue, team_id)))
            .update_expression("DELETE #holders :me")
            .expression_attribute_names("#holders", "holders")
            .expression_attribute_values(":me", me)
            .build()
            .map_err(|e| malformed(e.to_string()))?;
        let entry = Delete::builder()
            .table_name(&self.table)
            .set_key(Some(entry_key(queue, submission_id)))
            .build()
            .map_err(|e| malformed(e.to_string()))?;
        self.client
            .transact_write_items()
            .transact_items(TransactWriteItem::builder().update(place).build())
            .transact_items(TransactWriteItem::builder().delete(entry).build())
            .send()
            .await
            .map_err(|e| AwsError::sdk("dynamodb", "TransactWriteItems", e))?;
        Ok(())
    }
}
