//! The shared EvalAI budget in DynamoDB (`lb_evalai::budget` has the arithmetic): one item per
//! window, counted by a conditional increment, so every function of every submission takes
//! from the same count and two racing never exceed it. A booking is the same increment on a
//! later window's item.
//!
//! The budget table is ours alone (the stack creates it): partition key `window_start` (N,
//! epoch milliseconds of the window's start), `requests` (N) granted in it, `expires_at` (N,
//! DynamoDB TTL) an hour after the window.

use std::collections::HashMap;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use aws_sdk_dynamodb::types::AttributeValue;
use aws_sdk_dynamodb::Client;
use lb_evalai::{Admission, AdmissionFuture, Budget, BudgetPolicy, Priority};

use crate::{condition_failed, AwsError};

/// How often a grant that arrived after its window closed is asked for again.
const RETAKES: u32 = 2;

/// How long a window's item is kept after it (for an operator looking at the last hour).
const KEEP_SECONDS: u64 = 3600;

/// The budget table.
#[derive(Debug, Clone)]
pub struct BudgetTable {
    client: Client,
    table: String,
    policy: BudgetPolicy,
}

impl BudgetTable {
    /// The table named `table`, granting by `policy`.
    pub fn new(client: Client, table: impl Into<String>, policy: BudgetPolicy) -> Self {
        BudgetTable {
            client,
            table: table.into(),
            policy,
        }
    }

    /// Takes one request in the window of `at_ms` (epoch milliseconds); an urgent request
    /// finding it full books the first later window with room.
    pub async fn take_at(&self, priority: Priority, headroom: u32, at_ms: u64) -> Admission {
        self.take_by(priority, 1, headroom, &|| at_ms).await
    }

    /// [`Self::take_at`] on `clock`, read again after the writes: a grant counts in its window
    /// only, so one whose round trips outlasted that window (a slow table, a paused function)
    /// would be sent uncounted in the next; it is asked for again instead (a counted place
    /// unused is a request EvalAI never sees), at most [`RETAKES`] times.
    pub async fn take_by(
        &self,
        priority: Priority,
        places: u32,
        headroom: u32,
        clock: &(dyn Fn() -> u64 + Send + Sync),
    ) -> Admission {
        let (places, headroom) = (places.max(1), headroom.max(places));
        let mut late = Duration::ZERO;
        for _ in 0..=RETAKES {
            let at_ms = clock();
            let (index, retry_in) = self.policy.window_of(at_ms);
            let Some(most) = self.policy.limit(priority).checked_sub(headroom) else {
                // The call needs more than a window ever grants this priority.
                return Admission::Full { retry_in };
            };
            match self.increment(index, most, places).await {
                Ok(true) if clock() < self.policy.window_start(index + 1) => {
                    return Admission::Granted
                }
                Ok(true) => {
                    late = retry_in;
                    continue;
                }
                Ok(false) if priority == Priority::Routine => return Admission::Full { retry_in },
                Ok(false) => {}
                Err(why) => return Admission::Unavailable(why),
            }
            match self.book(index, at_ms, clock, places).await {
                Ok(Some(admission)) => return admission,
                Ok(None) => {
                    return Admission::Full {
                        retry_in: retry_in + self.policy.window * (BudgetPolicy::BOOK_AHEAD as u32),
                    }
                }
                Err(Some(why)) => return Admission::Unavailable(why),
                Err(None) => late = retry_in,
            }
        }
        Admission::Full { retry_in: late }
    }

    /// Books the first window after `index` with room: `Ok(None)` when none has, `Err(None)`
    /// when the booked window had passed by the time the write returned.
    async fn book(
        &self,
        index: u64,
        at_ms: u64,
        clock: &(dyn Fn() -> u64 + Send + Sync),
        places: u32,
    ) -> Result<Option<Admission>, Option<String>> {
        let most = self.policy.per_window.saturating_sub(places);
        for ahead in 1..=BudgetPolicy::BOOK_AHEAD {
            let booked = index + ahead;
            match self.increment(booked, most, places).await {
                Ok(true) => {
                    let now = clock();
                    if now >= self.policy.window_start(booked + 1) {
                        return Err(None);
                    }
                    // Spread over the window's first quarter, so the bookings of one window
                    // do not all arrive in its first millisecond.
                    let spread = (self.policy.window.as_millis() as u64 / 4).max(1);
                    let offset = (at_ms.wrapping_mul(2_654_435_761) >> 7) % spread;
                    let opens = self.policy.window_start(booked) + offset;
                    return Ok(Some(Admission::Booked {
                        wait: Duration::from_millis(opens.saturating_sub(now)),
                    }));
                }
                Ok(false) => continue,
                Err(why) => return Err(Some(why)),
            }
        }
        Ok(None)
    }

    /// Adds `places` to window `index`'s count if it is at most `most`: whether it did.
    async fn increment(&self, index: u64, most: u32, places: u32) -> Result<bool, String> {
        let start = self.policy.window_start(index);
        let end = self.policy.window_start(index + 1);
        let result = self
            .client
            .update_item()
            .table_name(&self.table)
            .set_key(Some(HashMap::from([(
                "window_start".to_string(),
                AttributeValue::N(start.to_string()),
            )])))
            .update_expression("ADD #requests :places SET #expires = :expires")
            .condition_expression("attribute_not_exists(#requests) OR #requests <= :most")
            .expression_attribute_names("#requests", "requests")
            .expression_attribute_names("#expires", "expires_at")
            .expression_attribute_values(":places", AttributeValue::N(places.to_string()))
            .expression_attribute_values(":most", AttributeValue::N(most.to_string()))
            .expression_attribute_values(
                ":expires",
                AttributeValue::N((end / 1000 + KEEP_SECONDS).to_string()),
            )
            .send()
            .await;
        match result {
            Ok(_) => Ok(true),
            Err(e) if condition_failed(&e) => Ok(false),
            Err(e) => Err(AwsError::sdk("dynamodb", "UpdateItem", e).to_string()),
        }
    }

    /// Requests granted in the window starting at `window_start` (epoch ms), for reports.
    pub async fn granted(&self, window_start: u64) -> crate::Result<u32> {
        let out = self
            .client
            .get_item()
            .table_name(&self.table)
            .key("window_start", AttributeValue::N(window_start.to_string()))
            .consistent_read(true)
            .send()
            .await
            .map_err(|e| AwsError::sdk("dynamodb", "GetItem", e))?;
        Ok(out
            .item()
            .and_then(|item| item.get("requests"))
            .and_then(|v| v.as_n().ok())
            .and_then(|n| n.parse().ok())
            .unwrap_or(0))
    }
}

fn now_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

impl Budget for BudgetTable {
    fn take(&self, priority: Priority, places: u32, headroom: u32) -> AdmissionFuture<'_> {
        Box::pin(self.take_by(priority, places, headroom, &now_ms))
    }
}
