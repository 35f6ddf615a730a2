//! How long EKS supports the clusters' Kubernetes minor at the standard price: past its end, a
//! cluster pays extended support (about $0.50 more per cluster-hour) and is upgraded for us.

use time::{Date, Month};

/// The end of EKS standard support of each minor the template has used or may use next (EKS's
/// release calendar). A new minor is added here before the template's default moves to it.
pub const STANDARD_SUPPORT_ENDS: &[(&str, (i32, Month, u8))] = &[
    ("1.33", (2026, Month::July, 29)),
    ("1.34", (2026, Month::December, 2)),
    ("1.35", (2027, Month::March, 27)),
];

/// How early to say that a minor's standard support is ending: an upgrade is rehearsed,
/// scheduled between deadline rushes and carried out across a cluster's two node groups.
pub const WARN_DAYS: i64 = 60;

/// The minor `infra/cluster.yaml` creates clusters with (its `KubernetesVersion` default).
pub fn template_minor() -> Option<String> {
    let template = &*crate::template::CLUSTER;
    template.eval(&template.root()["Parameters"]["KubernetesVersion"]["Default"])
}

/// Where a minor stands on a day.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Standing {
    /// In standard support for more than [`WARN_DAYS`].
    Supported { ends: Date, days_left: i64 },
    /// Its standard support ends within [`WARN_DAYS`]: time to upgrade.
    Ending { ends: Date, days_left: i64 },
    /// Past its standard support: every cluster on it pays extended support.
    Ended { ended: Date },
    /// No date is known for it here.
    Unknown,
}

impl Standing {
    /// Whether an operator must act (upgrade, or tell this table the minor's date).
    pub fn needs_action(&self) -> bool {
        !matches!(self, Standing::Supported { .. })
    }
}

/// The minor's standing on `today`.
pub fn standing(minor: &str, today: Date) -> Standing {
    let Some(ends) = STANDARD_SUPPORT_ENDS
        .iter()
        .find(|(m, _)| *m == minor)
        .and_then(|(_, (y, m, d))| Date::from_calendar_date(*y, *m, *d).ok())
    else {
        return Standing::Unknown;
    };
    let days_left = (ends - today).whole_days();
    match days_left {
        n if n < 0 => Standing::Ended { ended: ends },
        n if n <= WARN_DAYS => Standing::Ending { ends, days_left },
        _ => Standing::Supported { ends, days_left },
    }
}

/// The standing in one line, for operators and CI's output.
pub fn describe(minor: &str, standing: Standing) -> String {
    match standing {
        Standing::Supported { ends, days_left } => {
            format!("Kubernetes {minor}: EKS standard support until {ends} ({days_left} days left)")
        }
        Standing::Ending { ends, days_left } => format!(
            "Kubernetes {minor}: EKS standard support ends {ends}, in {days_left} days: upgrade \
             the clusters (docs/operations.md, \"Upgrading Kubernetes\") and move the template's \
             default to a newer minor"
        ),
        Standing::Ended { ended } => format!(
            "Kubernetes {minor}: EKS standard support ended {ended}; every cluster on it pays \
             extended support: upgrade now (docs/operations.md, \"Upgrading Kubernetes\")"
        ),
        Standing::Unknown => format!(
            "Kubernetes {minor}: no EKS support date known; add it to \
             crates/infra/src/support.rs from EKS's release calendar"
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn day(y: i32, m: Month, d: u8) -> Date {
        Date::from_calendar_date(y, m, d).unwrap()
    }

    #[test]
    fn a_minor_is_supported_then_ending_within_sixty_days_then_ended() {
        let ends = day(2027, Month::March, 27);
        assert_eq!(
            standing("1.35", day(2026, Month::November, 29)),
            Standing::Supported {
                ends,
                days_left: 118
            }
        );
        assert_eq!(
            standing("1.35", day(2027, Month::January, 26)),
            Standing::Ending {
                ends,
                days_left: 60
            }
        );
        assert_eq!(
            standing("1.35", day(2027, Month::March, 27)),
            Standing::Ending { ends, days_left: 0 }
        );
        assert_eq!(
            standing("1.35", day(2027, Month::March, 28)),
            Standing::Ended { ended: ends }
        );
        assert_eq!(
            standing("1.36", day(2026, Month::November, 29)),
            Standing::Unknown
        );
        assert!(!standing("1.35", day(2026, Month::November, 29)).needs_action());
        assert!(standing("1.34", day(2026, Month::November, 29)).needs_action());
    }

    #[test]
    fn each_standing_says_what_to_do() {
        let today = day(2026, Month::November, 29);
        assert!(describe("1.35", standing("1.35", today)).contains("until 2027-03-27 (118 days"));
        assert!(describe("1.34", standing("1.34", today)).contains("in 3 days: upgrade"));
        assert!(describe("1.33", standing("1.33", today)).contains("pays extended support"));
        assert!(describe("1.36", standing("1.36", today)).contains("support.rs"));
    }

    #[test]
    fn the_minors_are_listed_in_order_with_their_ends_in_order() {
        let ends: Vec<Date> = STANDARD_SUPPORT_ENDS
            .iter()
            .map(|(_, (y, m, d))| Date::from_calendar_date(*y, *m, *d).unwrap())
            .collect();
        assert!(ends.windows(2).all(|w| w[0] < w[1]));
        let minors: Vec<u32> = STANDARD_SUPPORT_ENDS
            .iter()
            .map(|(m, _)| m.strip_prefix("1.").unwrap().parse().unwrap())
            .collect();
        assert!(minors.windows(2).all(|w| w[1] == w[0] + 1), "{minors:?}");
    }
}
