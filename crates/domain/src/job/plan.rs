//! The evaluation plan: routes split over simulator-agent pairs, one Job per pair, and the
//! Kubernetes names and label values that tie every Job to its submission.
//!
//! R routes go to W = min(R, workers) pairs; worker i runs routes
//! `ceil(i*R/W) .. ceil((i+1)*R/W)-1` (20 routes, 4 workers: 0-4, 5-9, 10-14, 15-19). Each pair
//! is a Job of its own (as later versions of the original system ran them): its own
//! `backoffLimit`, so a pair that keeps crashing uses up its own retries and never its
//! neighbours', and its own pod requesting one GPU, so the scheduler places pairs wherever a
//! GPU is free. Pair IDs are 1-based and global, so result files never collide between Jobs;
//! every pair has its pod's network to itself: CARLA port 2000, traffic manager 2010.

use std::fmt;

use crate::results::RouteSubset;

/// CARLA RPC port of every pair (each has its pod's network namespace to itself).
pub const CARLA_PORT: u16 = 2000;
/// Traffic-manager port = CARLA port + this.
pub const TM_PORT_OFFSET: u16 = 10;
/// The most workers a submission may ask for.
pub const MAX_WORKERS: u32 = 1024;
/// The most routes a track may have.
pub const MAX_ROUTES: u32 = 100_000;

/// Longest Kubernetes name that is also a valid label value (Job names become the
/// `job-name` label of their Pods).
pub const MAX_NAME_LEN: usize = 63;
/// Longest Kubernetes label value.
pub const MAX_LABEL_VALUE_LEN: usize = 63;

/// Label key prefix of everything this project labels.
pub const LABEL_PREFIX: &str = "leaderboard.carla.org";
/// Label on every Job and Pod of a submission: its EvalAI submission id.
pub const SUBMISSION_LABEL: &str = "leaderboard.carla.org/submission-id";
/// Label: the EvalAI participant team id.
pub const TEAM_ID_LABEL: &str = "leaderboard.carla.org/team-id";
/// Label: a label-safe form of the team name (for humans; the id is authoritative).
pub const TEAM_LABEL: &str = "leaderboard.carla.org/team";
/// Label: the Job's 0-based index within the submission.
pub const JOB_INDEX_LABEL: &str = "leaderboard.carla.org/job-index";
/// Label: `1.0` or `2.0`.
pub const LEADERBOARD_LABEL: &str = "leaderboard.carla.org/leaderboard";
/// Label: the track codename (`SENSORS`, `MAP`, ...).
pub const TRACK_LABEL: &str = "leaderboard.carla.org/track";
/// Label: the Step Functions execution that launched the Job (label-safe form of its name).
/// Finalize deletes only its own execution's Jobs, and a resume replaces an earlier
/// execution's Jobs instead of adopting them.
pub const EXECUTION_LABEL: &str = "leaderboard.carla.org/execution";
/// Label: what the object is (`submission`), for anti-affinity and cleanup.
pub const COMPONENT_LABEL: &str = "app.kubernetes.io/component";
/// Value of [`COMPONENT_LABEL`] on submission Jobs and Pods.
pub const COMPONENT_SUBMISSION: &str = "submission";
/// Label: who manages the object.
pub const MANAGED_BY_LABEL: &str = "app.kubernetes.io/managed-by";
/// Value of [`MANAGED_BY_LABEL`].
pub const MANAGED_BY: &str = "leaderboard-cloud";

/// Why a plan cannot be made. Each variant has a stable [`name`](Self::name).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PlanError {
    /// Zero or absurd routes, workers or GPUs per node.
    #[error("invalid plan: {reason}")]
    InvalidPlan {
        /// What is wrong.
        reason: String,
    },
}

crate::error_names!(PlanError {
    InvalidPlan => "InvalidPlan";
});

/// One simulator-agent pair.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PairPlan {
    /// 1-based ID, global across the submission's Jobs (worker index + 1).
    pub id: u32,
    /// 0-based worker index (also its Job's index).
    pub worker: u32,
    /// The routes it runs.
    pub routes: RouteSubset,
    /// CARLA RPC port.
    pub carla_port: u16,
    /// Traffic-manager port: CARLA port + 10.
    pub tm_port: u16,
}

/// One Kubernetes Job of the submission.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct JobPlan {
    /// 0-based index within the submission.
    pub index: u32,
    /// The Job's name (a DNS-1123 label of at most 63 characters).
    pub name: String,
    /// Its pair (a list, as the templates' per-pair section renders it).
    pub pairs: Vec<PairPlan>,
}

impl JobPlan {
    /// The pair IDs as the logcopy sidecar takes them (`1,2,3,4`).
    pub fn pair_ids(&self) -> String {
        let ids: Vec<String> = self.pairs.iter().map(|p| p.id.to_string()).collect();
        ids.join(",")
    }
}

/// The Job index of pair `pair_id` (one pair per Job, pair IDs from 1).
pub fn job_of_pair(pair_id: u32) -> Option<u32> {
    pair_id.checked_sub(1)
}

/// The whole plan of one submission.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Plan {
    /// EvalAI submission id.
    pub submission_id: u64,
    /// Routes of the track (R).
    pub routes: u32,
    /// Pairs actually used (W = min(R, workers)), one Job each.
    pub workers: u32,
    /// The Jobs, in index order.
    pub jobs: Vec<JobPlan>,
}

impl Plan {
    /// Every pair, in ID order.
    pub fn pairs(&self) -> impl Iterator<Item = &PairPlan> {
        self.jobs.iter().flat_map(|j| j.pairs.iter())
    }
}

/// What the plan is made from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PlanInput<'a> {
    /// EvalAI submission id.
    pub submission_id: u64,
    /// The participant team's name, as EvalAI gives it (untrusted; only used in names).
    pub team_name: &'a str,
    /// Routes of the track (R).
    pub routes: u32,
    /// Workers requested (track default or the submission's override).
    pub workers: u32,
}

fn invalid(reason: impl Into<String>) -> PlanError {
    PlanError::InvalidPlan {
        reason: reason.into(),
    }
}

/// `ceil(a / b)` for `b > 0`.
fn ceil_div(a: u64, b: u64) -> u64 {
    a.div_ceil(b)
}

/// The route subsets of W workers over R routes: worker i gets `ceil(i*R/W)..ceil((i+1)*R/W)-1`.
pub fn split_routes(routes: u32, workers: u32) -> Result<Vec<RouteSubset>, PlanError> {
    if routes == 0 {
        return Err(invalid("a track needs at least one route"));
    }
    if workers == 0 {
        return Err(invalid("a submission needs at least one worker"));
    }
    if routes > MAX_ROUTES {
        return Err(invalid(format!(
            "{routes} routes is over the limit of {MAX_ROUTES}"
        )));
    }
    let r = u64::from(routes);
    let w = u64::from(workers.min(routes));
    Ok((0..w)
        .map(|i| RouteSubset {
            first: ceil_div(i * r, w),
            last: ceil_div((i + 1) * r, w) - 1,
        })
        .collect())
}

/// Makes the plan: route subsets, pairs, one Job per pair, names.
pub fn plan(input: PlanInput<'_>) -> Result<Plan, PlanError> {
    if input.workers > MAX_WORKERS {
        return Err(invalid(format!(
            "{} workers is over the limit of {MAX_WORKERS}",
            input.workers
        )));
    }
    let subsets = split_routes(input.routes, input.workers)?;
    let workers = subsets.len() as u32;
    let slug = team_slug(input.team_name);
    let jobs = subsets
        .iter()
        .enumerate()
        .map(|(i, routes)| {
            let worker = i as u32;
            JobPlan {
                index: worker,
                name: job_name_with_slug(input.submission_id, &slug, worker),
                pairs: vec![PairPlan {
                    id: worker + 1,
                    worker,
                    routes: *routes,
                    carla_port: CARLA_PORT,
                    tm_port: CARLA_PORT + TM_PORT_OFFSET,
                }],
            }
        })
        .collect();
    Ok(Plan {
        submission_id: input.submission_id,
        routes: input.routes,
        workers,
        jobs,
    })
}

/// Folds common Latin letters with diacritics to ASCII, so `Zoë` reads `zoe`, not `zo`.
fn fold(c: char) -> Option<&'static str> {
    Some(match c {
        'à' | 'á' | 'â' | 'ã' | 'ä' | 'å' | 'ā' | 'ă' | 'ą' => "a",
        'æ' => "ae",
        'ç' | 'ć' | 'č' => "c",
        'ď' | 'đ' | 'ð' => "d",
        'è' | 'é' | 'ê' | 'ë' | 'ē' | 'ė' | 'ę' | 'ě' => "e",
        'ğ' => "g",
        'ì' | 'í' | 'î' | 'ï' | 'ī' | 'į' | 'ı' => "i",
        'ł' | 'ľ' => "l",
        'ñ' | 'ń' | 'ň' => "n",
        'ò' | 'ó' | 'ô' | 'õ' | 'ö' | 'ø' | 'ō' | 'ő' => "o",
        'œ' => "oe",
        'ř' => "r",
        'ś' | 'š' | 'ş' | 'ș' => "s",
        'ß' => "ss",
        'ť' | 'ț' | 'þ' => "t",
        'ù' | 'ú' | 'û' | 'ü' | 'ū' | 'ů' | 'ű' | 'ų' => "u",
        'ý' | 'ÿ' => "y",
        'ź' | 'ż' | 'ž' => "z",
        _ => return None,
    })
}

/// A lowercase `[a-z0-9-]` slug of any text: letters with diacritics folded, every other
/// run of characters one `-`, no leading or trailing `-`; possibly empty.
pub fn slug(text: &str) -> String {
    let mut out = String::new();
    let mut dash = false;
    for c in text.chars().flat_map(char::to_lowercase) {
        let piece: Option<String> = if c.is_ascii_alphanumeric() {
            Some(c.to_string())
        } else {
            fold(c).map(str::to_owned)
        };
        match piece {
            Some(p) => {
                if dash && !out.is_empty() {
                    out.push('-');
                }
                dash = false;
                out.push_str(&p);
            }
            None => dash = true,
        }
        // NB: bounded work for hostile 1 MB names; names never need more than this.
        if out.len() > 2 * MAX_NAME_LEN {
            break;
        }
    }
    out
}

/// The team part of Job names: [`slug`] of the name, `team` when nothing is left.
pub fn team_slug(team_name: &str) -> String {
    let s = slug(team_name);
    if s.is_empty() {
        "team".to_owned()
    } else {
        s
    }
}

/// Cuts `s` to at most `max` bytes (ASCII input) and drops trailing `-`, `_` and `.`.
fn cut(s: &str, max: usize) -> &str {
    let s = &s[..s.len().min(max)];
    s.trim_end_matches(['-', '_', '.'])
}

/// The Job name: `lb-<submission>-<team slug>-<index>`, at most 63 characters.
///
/// Deterministic, readable, a valid DNS-1123 label for any team name, and unique per
/// (submission id, index): the submission id is the first number after `lb-` and the index
/// the last one, and the team slug between them is cut to fit (dropped if nothing fits).
pub fn job_name(submission_id: u64, team_name: &str, index: u32) -> String {
    job_name_with_slug(submission_id, &team_slug(team_name), index)
}

fn job_name_with_slug(submission_id: u64, slug: &str, index: u32) -> String {
    let fixed = format!("lb-{submission_id}--{index}");
    let room = MAX_NAME_LEN.saturating_sub(fixed.len());
    let team = cut(slug, room);
    if team.is_empty() {
        format!("lb-{submission_id}-{index}")
    } else {
        format!("lb-{submission_id}-{team}-{index}")
    }
}

/// A Kubernetes label value for any text: at most 63 characters of `[A-Za-z0-9-_.]`,
/// starting and ending alphanumeric (possibly empty, which Kubernetes allows).
pub fn label_value(text: &str) -> String {
    let mut out = String::new();
    let mut sep = false;
    for c in text.chars() {
        if c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.') {
            if sep && !out.is_empty() {
                out.push('-');
            }
            sep = false;
            out.push(c);
        } else if let Some(f) = c.to_lowercase().next().and_then(fold) {
            if sep && !out.is_empty() {
                out.push('-');
            }
            sep = false;
            out.push_str(f);
        } else {
            sep = true;
        }
        if out.len() > 2 * MAX_LABEL_VALUE_LEN {
            break;
        }
    }
    let out = out.trim_start_matches(['-', '_', '.']);
    let out = &out[..out.len().min(MAX_LABEL_VALUE_LEN)];
    out.trim_end_matches(['-', '_', '.']).to_owned()
}

/// Whether `s` is a DNS-1123 label (`[a-z0-9]([-a-z0-9]*[a-z0-9])?`, at most 63).
pub fn is_dns_label(s: &str) -> bool {
    let b = s.as_bytes();
    !b.is_empty()
        && b.len() <= MAX_NAME_LEN
        && b.iter()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || *c == b'-')
        && b[0] != b'-'
        && b[b.len() - 1] != b'-'
}

/// Whether `s` is a valid label value (`(([A-Za-z0-9][-A-Za-z0-9_.]*)?[A-Za-z0-9])?`, <= 63).
pub fn is_label_value(s: &str) -> bool {
    let b = s.as_bytes();
    if b.is_empty() {
        return true;
    }
    b.len() <= MAX_LABEL_VALUE_LEN
        && b.iter()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, b'-' | b'_' | b'.'))
        && b[0].is_ascii_alphanumeric()
        && b[b.len() - 1].is_ascii_alphanumeric()
}

/// Whether `s` is a valid label key (`[prefix/]name`: a DNS subdomain prefix of at most 253
/// and a name of at most 63 `[A-Za-z0-9-_.]`, alphanumeric at both ends).
pub fn is_label_key(s: &str) -> bool {
    let (prefix, name) = match s.rsplit_once('/') {
        Some((p, n)) => (Some(p), n),
        None => (None, s),
    };
    let prefix_ok =
        prefix.is_none_or(|p| !p.is_empty() && p.len() <= 253 && p.split('.').all(is_dns_label));
    prefix_ok && !name.is_empty() && is_label_value(name)
}

impl fmt::Display for PairPlan {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "pair {} (routes {}, port {})",
            self.id, self.routes, self.carla_port
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn input(routes: u32, workers: u32) -> PlanInput<'static> {
        PlanInput {
            submission_id: 4242,
            team_name: "Team Zoë",
            routes,
            workers,
        }
    }

    fn subsets(routes: u32, workers: u32) -> Vec<String> {
        split_routes(routes, workers)
            .unwrap()
            .iter()
            .map(|s| s.to_string())
            .collect()
    }

    #[test]
    fn twenty_routes_over_four_workers_give_the_design_s_subsets() {
        assert_eq!(subsets(20, 4), ["0-4", "5-9", "10-14", "15-19"]);
    }

    #[test]
    fn uneven_splits_follow_the_ceil_formula() {
        assert_eq!(subsets(10, 3), ["0-3", "4-6", "7-9"]);
        assert_eq!(subsets(12, 3), ["0-3", "4-7", "8-11"]);
        assert_eq!(subsets(3, 8), ["0-0", "1-1", "2-2"]);
        assert_eq!(subsets(1, 1), ["0-0"]);
    }

    #[test]
    fn zero_routes_or_workers_is_an_invalid_plan() {
        for (r, w) in [(0, 4), (20, 0), (20, 2000)] {
            let err = plan(input(r, w)).unwrap_err();
            assert_eq!(err.name(), "InvalidPlan", "{r} {w}");
        }
    }

    #[test]
    fn every_pair_is_a_job_of_its_own_with_the_seed_ports() {
        let p = plan(input(20, 4)).unwrap();
        assert_eq!(p.workers, 4);
        let shape: Vec<(u32, String, String, u16, u16)> = p
            .jobs
            .iter()
            .map(|j| {
                let pair = &j.pairs[0];
                (
                    j.index,
                    j.name.clone(),
                    format!("{}:{}", j.pair_ids(), pair.routes),
                    pair.carla_port,
                    pair.tm_port,
                )
            })
            .collect();
        let expect = |i: u32, pair: &str| {
            (
                i,
                format!("lb-4242-team-zoe-{i}"),
                pair.to_owned(),
                2000,
                2010,
            )
        };
        assert_eq!(
            shape,
            [
                expect(0, "1:0-4"),
                expect(1, "2:5-9"),
                expect(2, "3:10-14"),
                expect(3, "4:15-19")
            ]
        );
        assert_eq!(plan(input(20, 10)).unwrap().jobs.len(), 10);
        assert_eq!(plan(input(3, 8)).unwrap().jobs.len(), 3);
    }

    #[test]
    fn names_fold_diacritics_and_fall_back_for_empty_slugs() {
        assert_eq!(
            job_name(1, "Équipe Zoë & Søren", 0),
            "lb-1-equipe-zoe-soren-0"
        );
        assert_eq!(job_name(1, "", 2), "lb-1-team-2");
        assert_eq!(job_name(1, "!!!", 2), "lb-1-team-2");
        assert_eq!(job_name(1, "🚗🚗", 2), "lb-1-team-2");
        let long = job_name(u64::MAX, &"x".repeat(300), u32::MAX);
        assert_eq!(long.len(), 63);
        assert!(long.starts_with("lb-18446744073709551615-xxx"));
        assert!(long.ends_with("-4294967295"));
        assert!(is_dns_label(&long));
    }

    #[test]
    fn label_values_keep_what_kubernetes_allows() {
        assert_eq!(label_value("Team_A.b-c"), "Team_A.b-c");
        assert_eq!(label_value("  --Zoë's team!! "), "Zoe-s-team");
        assert_eq!(label_value("🚗"), "");
        assert_eq!(label_value(&"a.".repeat(100)).len(), 63);
        assert!(is_label_value(&label_value(&"a.".repeat(100))));
    }

    #[test]
    fn label_keys_are_checked_with_their_prefix() {
        for key in [SUBMISSION_LABEL, TEAM_LABEL, COMPONENT_LABEL, "simple"] {
            assert!(is_label_key(key), "{key}");
        }
        for key in ["", "/x", "a/", "Bad_Prefix/x", "x/-y", "a/b/c"] {
            assert!(!is_label_key(key), "{key}");
        }
    }

    mod properties {
        use super::*;
        use proptest::prelude::*;
        use std::collections::HashSet;

        fn any_name() -> impl Strategy<Value = String> {
            prop_oneof![
                ".{0,300}",
                "[ -~]{0,80}",
                "[\\p{L}\\p{So} ._'-]{0,120}",
                Just(String::new()),
                Just("!!!---...".to_owned()),
            ]
        }

        proptest! {
            #[test]
            fn every_job_name_is_a_dns_label_and_unique_per_submission_and_index(
                names in proptest::collection::vec(any_name(), 1..6),
                subs in proptest::collection::vec(prop_oneof![0u64..30, Just(u64::MAX), any::<u64>()], 1..4),
                indexes in proptest::collection::vec(prop_oneof![0u32..30, Just(u32::MAX)], 1..4),
            ) {
                let mut owner: std::collections::HashMap<String, (u64, u32)> = Default::default();
                for sub in &subs {
                    for index in &indexes {
                        // Any team name may come with a submission: uniqueness must not
                        // depend on it.
                        for name in &names {
                            let n = job_name(*sub, name, *index);
                            prop_assert!(is_dns_label(&n), "{n}");
                            prop_assert!(n.len() <= MAX_NAME_LEN);
                            prop_assert_eq!(&n, &job_name(*sub, name, *index));
                            if let Some(prev) = owner.insert(n.clone(), (*sub, *index)) {
                                prop_assert_eq!(prev, (*sub, *index), "{} names two Jobs", n);
                            }
                        }
                    }
                }
            }

            #[test]
            fn every_label_value_is_valid(name in any_name()) {
                let v = label_value(&name);
                prop_assert!(is_label_value(&v), "{v:?}");
                let s = team_slug(&name);
                prop_assert!(s.bytes().all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-'));
                prop_assert!(!s.starts_with('-') && !s.ends_with('-') && !s.contains("--"), "{s}");
            }

            #[test]
            fn every_route_is_planned_exactly_once(
                routes in 1u32..400, workers in 1u32..64, sub in any::<u64>(),
                name in any_name(),
            ) {
                let p = plan(PlanInput { submission_id: sub, team_name: &name, routes, workers }).unwrap();
                prop_assert_eq!(p.workers, workers.min(routes));
                let mut next = 0u64;
                for (i, pair) in p.pairs().enumerate() {
                    prop_assert_eq!(pair.id as usize, i + 1);
                    prop_assert_eq!(pair.routes.first, next);
                    prop_assert!(pair.routes.last >= pair.routes.first);
                    next = pair.routes.last + 1;
                    prop_assert_eq!(pair.tm_port, pair.carla_port + 10);
                }
                prop_assert_eq!(next, u64::from(routes));
                let names: HashSet<&str> = p.jobs.iter().map(|j| j.name.as_str()).collect();
                prop_assert_eq!(names.len(), p.jobs.len());
                for j in &p.jobs {
                    prop_assert!(is_dns_label(&j.name));
                    prop_assert_eq!(j.pairs.len(), 1);
                    prop_assert_eq!(j.pairs[0].worker, j.index);
                }
            }
        }
    }
}
