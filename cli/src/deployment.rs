//! A real deployment as the operator commands see it: the settings secret and the submissions
//! tables and buckets it names, reached with the standard AWS environment.

use std::collections::BTreeSet;

use aws_config::SdkConfig;
use aws_sdk_dynamodb::types::AttributeValue;
use clap::Args;
use lb_aws::dynamo::SubmissionsTable;
use lb_aws::record::{RecordUsage, StoredRecord};
use lb_domain::settings::{LeaderboardSettings, Settings};
use serde_json::{json, Map, Value};

use crate::error::{CliError, Result};

/// Most Scan pages read per table (a page is at most 1 MB, about a thousand records): the
/// commands stay bounded on a table that grew beyond what a person reads anyway.
pub const MAX_SCAN_PAGES: usize = 100;

/// Where the deployment's configuration is.
#[derive(Debug, Clone, Args)]
pub struct DeploymentArgs {
    /// Id of the settings secret (Secrets Manager) naming each leaderboard's bucket and tables.
    #[arg(
        long,
        value_name = "ID",
        env = "LB_SETTINGS_SECRET",
        default_value = "leaderboard/settings"
    )]
    pub settings_secret: String,
    /// The deployment's admission table (stack output `AdmissionTable`): `status` and `list`
    /// then show each queued submission's place and what holds it back.
    #[arg(long, value_name = "TABLE", env = "LB_ADMISSION_TABLE")]
    pub admission_table: Option<String>,
}

/// Where the EvalAI host token is, for the commands that talk to EvalAI.
#[derive(Debug, Clone, Args)]
pub struct EvalAiTokenArgs {
    /// Id of the EvalAI host token secret (Secrets Manager).
    #[arg(
        long,
        value_name = "ID",
        env = "LB_EVALAI_TOKEN_SECRET",
        default_value = "leaderboard/evalai-token"
    )]
    pub token_secret: String,
    /// The deployment's EvalAI budget table (stack output `BudgetTable`): this command's
    /// requests then take from the same 60 a minute as the functions' (recommended while
    /// submissions are in flight; they share one host token).
    #[arg(long, value_name = "TABLE", env = "LB_BUDGET_TABLE")]
    pub budget_table: Option<String>,
}

/// The loaded deployment: settings and clients.
#[derive(Debug, Clone)]
pub struct Deployment {
    /// The SDK configuration (region, credentials, `AWS_ENDPOINT_URL`).
    pub sdk: SdkConfig,
    /// The settings secret's id.
    pub settings_secret: String,
    /// The checked settings.
    pub settings: Settings,
    /// DynamoDB.
    pub dynamo: aws_sdk_dynamodb::Client,
    /// S3 (path-style under an endpoint override).
    pub s3: aws_sdk_s3::Client,
    /// The leaderboards' queues, when named.
    pub admission: Option<lb_aws::admission::AdmissionTable>,
}

/// Parses an EvalAI id: EvalAI's primary keys are positive Postgres integers.
pub(crate) fn evalai_id() -> impl clap::builder::TypedValueParser<Value = u64> {
    clap::value_parser!(u64).range(1..=lb_domain::submission::MAX_ID)
}

/// One submission record and where it was found.
#[derive(Debug, Clone, PartialEq)]
pub struct Record {
    /// The leaderboard whose table holds it.
    pub leaderboard: String,
    /// The table.
    pub table: String,
    /// The record as stored, read back typed.
    pub stored: StoredRecord,
}

impl std::ops::Deref for Record {
    type Target = StoredRecord;
    fn deref(&self) -> &StoredRecord {
        &self.stored
    }
}

pub use lb_aws::dynamo::ScanFilter;

/// The records found, and the tables whose Scan stopped at [`MAX_SCAN_PAGES`].
#[derive(Debug, Clone, Default)]
pub struct Found {
    /// Records, in table order.
    pub records: Vec<Record>,
    /// Tables not read to the end.
    pub truncated: Vec<String>,
}

impl Deployment {
    /// Reads the settings secret through the standard AWS configuration.
    pub async fn load(args: &DeploymentArgs) -> Result<Deployment> {
        if args.settings_secret.trim().is_empty() {
            return Err(CliError::Usage(
                "`--settings-secret` (or LB_SETTINGS_SECRET) is empty".into(),
            ));
        }
        let sdk = crate::aws::config().await?;
        let secrets = aws_sdk_secretsmanager::Client::new(&sdk);
        let settings = lb_aws::secrets::load_settings(&secrets, &args.settings_secret)
            .await
            .map_err(|e| {
                CliError::aws(
                    format!(
                        "reading the settings secret `{}` (set --settings-secret or LB_SETTINGS_SECRET)",
                        args.settings_secret
                    ),
                    e,
                )
            })?;
        Ok(Deployment {
            // `unlimited` is what `invoke` takes for "no queue": no table to read then.
            admission: args
                .admission_table
                .as_ref()
                .filter(|t| t.as_str() != lb_pipeline::config::Shared::UNLIMITED)
                .map(|table| {
                    lb_aws::admission::AdmissionTable::new(
                        aws_sdk_dynamodb::Client::new(&sdk),
                        table,
                    )
                }),
            dynamo: aws_sdk_dynamodb::Client::new(&sdk),
            s3: lb_aws::s3_client(&sdk),
            settings_secret: args.settings_secret.clone(),
            settings,
            sdk,
        })
    }

    /// EvalAI as the functions reach it: the settings' server, the token from its secret.
    pub async fn evalai(
        &self,
        token: &EvalAiTokenArgs,
    ) -> std::result::Result<lb_evalai::EvalAiClient, lb_pipeline::FnError> {
        use lb_pipeline::config::Shared;
        let config = lb_pipeline::FunctionConfig {
            settings_secret: self.settings_secret.clone(),
            token_secret: token.token_secret.clone(),
            wake_table: None,
            // By hand, with no table named, the command's requests take from no budget.
            budget: match token.budget_table.as_deref() {
                None | Some(Shared::UNLIMITED) => Shared::Unlimited,
                Some(table) => Shared::Table(table.to_owned()),
            },
            admission: Shared::Unlimited,
            consolidate_nodes: false,
            memory_mb: 0,
        };
        lb_pipeline::clients::evalai(&self.sdk, &config, &self.settings).await
    }

    /// The leaderboards to look at: all, or the one named (which must exist).
    pub fn leaderboards(&self, only: Option<&str>) -> Result<Vec<(&str, &LeaderboardSettings)>> {
        let all: Vec<(&str, &LeaderboardSettings)> = self
            .settings
            .leaderboards
            .iter()
            .map(|(name, lb)| (name.as_str(), lb))
            .collect();
        match only {
            None => Ok(all),
            Some(name) => {
                let chosen: Vec<_> = all.iter().copied().filter(|(n, _)| *n == name).collect();
                if chosen.is_empty() {
                    let known: Vec<&str> = all.iter().map(|(n, _)| *n).collect();
                    return Err(CliError::Usage(format!(
                        "leaderboard `{}` is not in the settings secret `{}` (it has: {})",
                        name.escape_debug(),
                        self.settings_secret,
                        known.join(", ")
                    )));
                }
                Ok(chosen)
            }
        }
    }

    /// The settings of one leaderboard.
    pub fn leaderboard(&self, name: &str) -> Result<&LeaderboardSettings> {
        Ok(self.leaderboards(Some(name))?[0].1)
    }

    /// Scans the submissions tables of `leaderboards` (each table once), newest submission
    /// first.
    pub async fn records(&self, only: Option<&str>, filter: ScanFilter) -> Result<Found> {
        let mut found = Found::default();
        let mut seen = BTreeSet::new();
        for (name, lb) in self.leaderboards(only)? {
            // NB: two leaderboards may share a table; reading it twice would list records twice.
            if !seen.insert(lb.submissions_table.as_str()) {
                continue;
            }
            let table = SubmissionsTable::new(self.dynamo.clone(), &lb.submissions_table);
            let (records, complete) = table
                .scan(filter, MAX_SCAN_PAGES)
                .await
                .map_err(|e| CliError::aws(format!("reading `{}`", lb.submissions_table), e))?;
            if !complete {
                found.truncated.push(lb.submissions_table.clone());
            }
            found
                .records
                .extend(records.into_iter().map(|stored| Record {
                    leaderboard: name.to_string(),
                    table: lb.submissions_table.clone(),
                    stored,
                }));
        }
        found
            .records
            .sort_by_key(|r| std::cmp::Reverse(r.submission_id.unwrap_or(0)));
        Ok(found)
    }
}

impl Record {
    /// The GPUs the run used so far (the Monitor writes them each round, Finalize at the end).
    pub fn usage(&self) -> Option<Usage> {
        self.stored.usage.map(Usage)
    }

    /// The record as JSON, with where it was found.
    pub fn to_json(&self) -> Value {
        let mut keys: Vec<&String> = self.item.keys().collect();
        keys.sort();
        let record: Map<String, Value> = keys
            .into_iter()
            .map(|k| (k.clone(), attribute_json(&self.item[k])))
            .collect();
        json!({"leaderboard": self.leaderboard, "table": self.table, "record": record})
    }

    /// Attributes that are not part of the record's fixed layout (the metrics, mostly).
    pub fn extra_attributes(&self) -> Vec<(&str, String)> {
        (self.stored.extra_attributes().into_iter())
            .map(|(k, v)| (k, clean(&attribute_json(v).to_string())))
            .collect()
    }
}

/// A record's GPU usage and its estimated price, as `lbctl` shows it.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Usage(pub RecordUsage);

impl std::ops::Deref for Usage {
    type Target = RecordUsage;
    fn deref(&self) -> &RecordUsage {
        &self.0
    }
}

impl Usage {
    /// Adds another record's usage (a team's total); the price is known only if both are.
    pub fn add(self, other: Usage) -> Usage {
        Usage(RecordUsage {
            gpu_seconds: self.gpu_seconds + other.gpu_seconds,
            spot: self.spot + other.spot,
            run_again: self.run_again + other.run_again,
            lost: self.lost + other.lost,
            dollars: self.dollars.zip(other.dollars).map(|(a, b)| a + b),
            orchestration: match (self.orchestration, other.orchestration) {
                (Some(a), Some(b)) => Some(a + b),
                (a, b) => a.or(b),
            },
        })
    }

    /// GPU-hours.
    pub fn hours(&self) -> f64 {
        self.gpu_seconds as f64 / 3600.0
    }

    /// `2.50 GPU-hours (1.20 on Spot, 0.10 run again after reclaims), about $3.10;
    /// orchestration about $0.0120; 12 minutes lost to reclaims, not counted against the time
    /// limit`.
    pub fn describe(&self) -> String {
        let hours = |s: u64| s as f64 / 3600.0;
        let price = self.dollars.map_or_else(
            || ", no price in the settings".into(),
            |d| format!(", about ${d:.2}"),
        );
        let orchestration = self
            .orchestration
            .map_or_else(String::new, |d| format!("; orchestration about ${d:.4}"));
        let lost = match self.lost {
            0 => String::new(),
            s => format!(
                "; {} minutes lost to reclaims, not counted against the time limit",
                s.div_ceil(60)
            ),
        };
        format!(
            "{:.2} GPU-hours ({:.2} on Spot, {:.2} run again after reclaims){price}{orchestration}{lost}",
            self.hours(),
            hours(self.spot),
            hours(self.run_again)
        )
    }

    /// The list's column: `2.50h $3.10`.
    pub fn short(&self) -> String {
        match self.dollars {
            Some(d) => format!("{:.2}h ${d:.2}", self.hours()),
            None => format!("{:.2}h", self.hours()),
        }
    }
}

/// A DynamoDB value as plain JSON (numbers as numbers when they fit).
pub fn attribute_json(value: &AttributeValue) -> Value {
    let number = |n: &str| -> Value {
        if let Ok(i) = n.parse::<i64>() {
            json!(i)
        } else if let Some(f) = n.parse::<f64>().ok().filter(|f| f.is_finite()) {
            json!(f)
        } else {
            json!(n)
        }
    };
    match value {
        AttributeValue::S(s) => json!(s),
        AttributeValue::N(n) => number(n),
        AttributeValue::Bool(b) => json!(b),
        AttributeValue::Null(_) => Value::Null,
        AttributeValue::Ss(items) => json!(items),
        AttributeValue::Ns(items) => Value::Array(items.iter().map(|n| number(n)).collect()),
        AttributeValue::L(items) => Value::Array(items.iter().map(attribute_json).collect()),
        AttributeValue::M(map) => {
            let mut keys: Vec<&String> = map.keys().collect();
            keys.sort();
            Value::Object(
                keys.into_iter()
                    .map(|k| (k.clone(), attribute_json(&map[k])))
                    .collect(),
            )
        }
        AttributeValue::B(blob) => json!(format!("<{} bytes>", blob.as_ref().len())),
        AttributeValue::Bs(blobs) => json!(format!("<{} binary values>", blobs.len())),
        _ => json!("<unknown type>"),
    }
}

/// Text from records (team names are the participant's free text) made safe for a terminal:
/// control, bidirectional and zero-width characters shown as escapes.
pub fn clean(text: &str) -> String {
    text.chars()
        .flat_map(|c| {
            if c.is_control() || lb_domain::job::logtail::is_invisible_format(c) {
                c.escape_default().collect::<Vec<_>>()
            } else {
                vec![c]
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(pairs: &[(&str, AttributeValue)]) -> Record {
        Record {
            leaderboard: "2.0".into(),
            table: "t".into(),
            stored: StoredRecord::from_item(
                pairs
                    .iter()
                    .map(|(k, v)| (k.to_string(), v.clone()))
                    .collect(),
            ),
        }
    }

    #[test]
    fn a_record_becomes_plain_json_with_numbers_as_numbers() {
        let r = record(&[
            ("team_id", AttributeValue::N("3".into())),
            ("submission_id", AttributeValue::N("7".into())),
            ("driving_score", AttributeValue::N("41.25".into())),
            ("submission_status", AttributeValue::S("FAILED".into())),
        ]);
        assert_eq!(
            r.to_json(),
            json!({"leaderboard": "2.0", "table": "t", "record": {
                "driving_score": 41.25, "submission_id": 7,
                "submission_status": "FAILED", "team_id": 3}})
        );
        assert!(r.is_final());
        assert_eq!(
            r.extra_attributes(),
            vec![("driving_score", "41.25".into())]
        );
    }

    #[test]
    fn a_malformed_record_reads_as_missing_values_not_a_panic() {
        let r = record(&[("submission_id", AttributeValue::S("seven".into()))]);
        assert_eq!(r.submission_id, None);
        assert_eq!((r.status, r.status_word.as_str()), (None, ""));
        assert!(!r.is_final());
    }

    #[test]
    fn control_characters_in_team_names_are_escaped() {
        assert_eq!(clean("Team\u{1b}[31m One\n"), "Team\\u{1b}[31m One\\n");
        assert_eq!(
            clean("Team \u{202e}evil\u{200b}"),
            "Team \\u{202e}evil\\u{200b}"
        );
    }
}
