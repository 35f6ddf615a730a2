//! The submission's results as the workers left them in S3: fingerprinted cheaply, merged with
//! the Leaderboard's rules, turned into the EvalAI files and stored next to them.

use futures_util::{StreamExt as _, TryStreamExt as _};
use lb_aws::s3::{EvalAiObjects, PartialObject, SubmissionStore, MAX_PARTIAL_BYTES};
use lb_domain::results::py::Num;
use lb_domain::results::{
    self, read_worker_files, EvalAiFiles, Expected, Leaderboard, MergeOptions, Merged, ResultsFile,
    RouteSubset, WorkerFile, WorkerInput,
};
use lb_domain::run::audit;
use tracing::warn;

use crate::payload::PairRoutes;
use crate::FnError;

/// The merged view of one moment.
#[derive(Debug, Clone, PartialEq)]
pub struct Snapshot {
    /// What was read (see [`fingerprint`]).
    pub fingerprint: String,
    /// The digest of what a partial update is sent for ([`Merged::progress_view`]): routes
    /// done, each record's status and scores. The same in other bytes, or with another
    /// duration, gives the same digest.
    pub content: String,
    /// The EvalAI files.
    pub files: EvalAiFiles,
    /// `agent_results.json`, when any worker wrote results.
    pub merged_json: Option<String>,
    /// Routes done and planned.
    pub progress: (u64, u64),
    /// Every planned route has a record and the global statistics exist.
    pub complete: bool,
    /// The pairs that finished their routes, by ID.
    pub finished_pairs: Vec<u32>,
    /// (DynamoDB attribute, value) per metric.
    pub metrics: Vec<(&'static str, Num)>,
    /// The merged records as the recordings' audit needs them, in order.
    pub routes: Vec<audit::Route>,
}

/// The workers' files as one listing found them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Listing {
    /// Identifies them (pair IDs and ETags): unchanged means nothing new to send.
    pub fingerprint: String,
    partials: Vec<PartialObject>,
}

impl Listing {
    /// When the newest of the listed results was written (epoch seconds).
    pub fn newest(&self) -> Option<u64> {
        self.partials.iter().filter_map(|p| p.modified).max()
    }

    /// When each pair's results file was last written, by Job index (one pair per Job).
    pub fn written(&self) -> std::collections::BTreeMap<u32, u64> {
        written_of(&self.partials)
    }
}

fn written_of(partials: &[PartialObject]) -> std::collections::BTreeMap<u32, u64> {
    partials
        .iter()
        .filter_map(|p| Some((lb_domain::job::plan::job_of_pair(p.pair_id)?, p.modified?)))
        .collect()
}

/// When each pair's results file was last written, by Job index (one pair per Job); empty
/// when S3 cannot be listed (a reclaimed pod's whole life then counts as run again).
pub async fn written(store: &SubmissionStore) -> std::collections::BTreeMap<u32, u64> {
    match store.partials().await {
        Ok(partials) => written_of(&partials),
        Err(e) => {
            warn!(error = %e, "results not listed: a reclaimed pod's time counts as run again");
            std::collections::BTreeMap::new()
        }
    }
}

/// Lists the workers' files once.
pub async fn list(store: &SubmissionStore) -> Result<Listing, FnError> {
    let partials = store.partials().await?;
    Ok(Listing {
        fingerprint: fingerprint_of(&partials),
        partials,
    })
}

/// Identifies the workers' files as they are now (keys and ETags), from one listing.
pub async fn fingerprint(store: &SubmissionStore) -> Result<String, FnError> {
    Ok(list(store).await?.fingerprint)
}

fn fingerprint_of(partials: &[PartialObject]) -> String {
    fingerprint_of_pairs(partials.iter().map(|p| (p.pair_id, p.etag.as_str())))
}

/// A SHA-256 of `bytes`, in hex (64 bytes of the state).
fn digest(bytes: &[u8]) -> String {
    use sha2::{Digest, Sha256};
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// The fingerprint of workers' files given as (pair ID, ETag): a SHA-256 of them, so that it
/// takes 64 bytes of the state for any number of workers (empty for none).
pub fn fingerprint_of_pairs<E: AsRef<str>>(files: impl IntoIterator<Item = (u32, E)>) -> String {
    use sha2::{Digest, Sha256};
    let mut hasher = Sha256::new();
    let mut any = false;
    for (id, etag) in files {
        any = true;
        hasher.update(format!("{id}:{},", etag.as_ref().trim_matches('"')));
    }
    if !any {
        return String::new();
    }
    hasher
        .finalize()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// Downloads the workers' files and merges them; nothing is written ([`store`] keeps them).
///
/// A worker file is the participant's container's output: its errors (`ResultsInvalid`, ...)
/// are raised with their names so the run fails with a readable reason.
pub async fn collect(
    store: &SubmissionStore,
    leaderboard: Leaderboard,
    pairs: &[PairRoutes],
    repetitions: u32,
) -> Result<Snapshot, FnError> {
    let listing = list(store).await?;
    collect_listed(store, listing, leaderboard, pairs, repetitions).await
}

/// [`collect`] from a listing already made (the Monitor lists once to compare fingerprints).
pub async fn collect_listed(
    store: &SubmissionStore,
    listing: Listing,
    leaderboard: Leaderboard,
    pairs: &[PairRoutes],
    repetitions: u32,
) -> Result<Snapshot, FnError> {
    let Listing {
        fingerprint,
        partials,
    } = listing;
    let pairs = pairs
        .iter()
        .map(|pair| {
            pair.routes
                .parse::<RouteSubset>()
                .map(|s| (pair.id, s))
                .map_err(|e| {
                    FnError::RunState(format!("pair {} routes `{}`: {e}", pair.id, pair.routes))
                })
        })
        .collect::<Result<Vec<_>, _>>()?;
    let Merge {
        merged,
        complete,
        progress,
        finished_pairs,
    } = merge_partials(store, &partials, leaderboard, &pairs, repetitions).await?;
    let files = EvalAiFiles::generate(merged.as_ref(), leaderboard);
    let merged_json = merged.as_ref().map(|m| m.to_json());
    let routes = merged
        .as_ref()
        .map_or_else(Vec::new, |m| audited_routes(m, &pairs));
    let metrics = metrics(&files, leaderboard);
    let view = merged.as_ref().map(Merged::progress_view);
    let content = digest(view.unwrap_or_default().as_bytes());
    Ok(Snapshot {
        fingerprint,
        content,
        files,
        merged_json,
        progress,
        complete,
        finished_pairs,
        metrics,
        routes,
    })
}

/// Keeps a merge in S3: `agent_results.json` and the three files EvalAI gets, as sent.
pub async fn store(store: &SubmissionStore, snapshot: &Snapshot) -> Result<(), FnError> {
    let files = &snapshot.files;
    store
        .put_evalai_files(&EvalAiObjects {
            merged: snapshot.merged_json.as_deref(),
            results: &files.results_json(),
            stdout: &files.stdout,
            metadata: files.metadata.as_deref(),
        })
        .await?;
    Ok(())
}

/// Each merged record with the pair whose subset holds its route (the merge took each pair's
/// records from that pair's file only, within its subset), its simulated time and whether it
/// scores.
fn audited_routes(merged: &Merged, pairs: &[(u32, RouteSubset)]) -> Vec<audit::Route> {
    merged
        .records
        .iter()
        .filter_map(|r| {
            let pair = pairs
                .iter()
                .find(|(_, subset)| subset.contains(r.route_id.route))?
                .0;
            Some(audit::Route {
                pair,
                id: r.route_id.raw.clone(),
                route: r.route_id.route,
                game_seconds: r.meta.duration_game.as_f64(),
                completion: r.scores.score_route.as_f64(),
                scores: r.scores.score_route.as_f64() > 0.0
                    || r.scores.score_composed.as_f64() > 0.0,
            })
        })
        .collect()
}

/// The workers' files, a few at a time, in order: the reads are independent.
async fn read_all(store: &SubmissionStore, keys: &[String]) -> Result<Vec<Vec<u8>>, FnError> {
    // Owned keys: a future borrowing its key through the closure's argument is not `Send`
    // for every lifetime, which the Lambda runtime's spawn needs.
    let contents: Vec<Vec<u8>> = futures_util::stream::iter(keys.to_vec())
        .map(|key| async move { store.get_bounded(&key, MAX_PARTIAL_BYTES).await })
        .buffered(CONCURRENT_READS)
        .try_collect()
        .await?;
    Ok(contents)
}

/// How many workers' results files are read at once.
const CONCURRENT_READS: usize = 8;

/// The workers' files merged.
#[derive(Debug, Clone, PartialEq)]
pub struct Merge {
    /// The merged document, when any worker wrote results.
    pub merged: Option<Merged>,
    /// Every planned route has its records and the global statistics exist.
    pub complete: bool,
    /// Records found and planned.
    pub progress: (u64, u64),
    /// The pairs whose results file is finished (it has its global record), by ID.
    pub finished_pairs: Vec<u32>,
}

/// The planned workers' files read from S3 and merged with the leaderboard's rules: what the
/// Monitor, Finalize and `lbctl rescore` compute alike. `pairs` are (pair id, its routes); a
/// file of no planned pair is left out. A worker file is the participant's container's output:
/// its errors (`ResultsInvalid`, ...) are raised with their names.
pub async fn merge_partials(
    store: &SubmissionStore,
    partials: &[PartialObject],
    leaderboard: Leaderboard,
    pairs: &[(u32, RouteSubset)],
    repetitions: u32,
) -> Result<Merge, FnError> {
    let mut sources = Vec::new();
    let mut subsets = Vec::new();
    let mut ids = Vec::new();
    for partial in partials {
        let Some((_, subset)) = pairs.iter().find(|(id, _)| *id == partial.pair_id) else {
            warn!(key = %partial.key, "results file of no planned worker, ignored");
            continue;
        };
        sources.push(partial.key.clone());
        subsets.push(*subset);
        ids.push(partial.pair_id);
    }
    let contents = read_all(store, &sources).await?;
    let inputs: Vec<WorkerInput<'_>> = sources
        .iter()
        .zip(&contents)
        .zip(&subsets)
        .map(|((source, bytes), subset)| WorkerInput {
            source,
            bytes: Some(bytes),
            subset: Some(*subset),
        })
        .collect();
    let mut present: Vec<ResultsFile> = Vec::new();
    let mut finished_pairs = Vec::new();
    for (read, id) in read_worker_files(&inputs, leaderboard)
        .into_iter()
        .zip(&ids)
    {
        match read? {
            WorkerFile::Present(file) => {
                if file.has_global_record {
                    finished_pairs.push(*id);
                }
                present.push(file)
            }
            WorkerFile::Empty(reason) => warn!(%reason, "a results file counts as empty"),
        }
    }
    finished_pairs.sort_unstable();
    finished_pairs.dedup();
    let expected = Expected {
        routes: pairs.iter().map(|(_, s)| s.last - s.first + 1).sum(),
        repetitions: u64::from(repetitions),
    };
    if present.is_empty() {
        return Ok(Merge {
            merged: None,
            complete: false,
            progress: (0, expected.records()),
            finished_pairs,
        });
    }
    let outcome = results::merge(
        present,
        MergeOptions {
            leaderboard,
            expected: Some(expected),
        },
    )?;
    Ok(Merge {
        progress: outcome.merged.progress,
        complete: outcome.complete,
        merged: Some(outcome.merged),
        finished_pairs,
    })
}

/// (DynamoDB attribute, value) for each metric EvalAI gets.
fn metrics(files: &EvalAiFiles, leaderboard: Leaderboard) -> Vec<(&'static str, Num)> {
    let accuracies = files.accuracies();
    leaderboard
        .metrics()
        .iter()
        .filter_map(|m| {
            accuracies
                .iter()
                .find(|(label, _)| *label == m.label)
                .map(|(_, value)| (m.attribute, *value))
        })
        .collect()
}
