//! Our statuses as types, parsed once where they arrive: the submission record's
//! `submission_status`, Step Functions' execution statuses, pods' phases, what Finalize settled
//! and what the reaper did. Past the edge no status is compared as a string.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// A status word that is none of its type's.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown {kind} `{value}` (expected one of {expected})")]
pub struct UnknownStatus {
    /// What was parsed: `submission_status`, `execution status`, ...
    pub kind: &'static str,
    /// The word, escaped.
    pub value: String,
    /// The words of the type.
    pub expected: String,
}

/// An enum of fixed words: `as_str`, `ALL`, `Display`, `FromStr` (naming the word and the
/// ones expected) and serde as the word.
macro_rules! words {
    ($(#[$meta:meta])* $name:ident, $kind:literal { $($(#[$vmeta:meta])* $variant:ident => $word:literal,)+ }) => {
        $(#[$meta])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
        pub enum $name {
            $($(#[$vmeta])* $variant,)+
        }

        impl $name {
            /// Every value, in declaration order.
            pub const ALL: &'static [$name] = &[$($name::$variant,)+];

            /// The word as stored and sent.
            pub fn as_str(self) -> &'static str {
                match self {
                    $($name::$variant => $word,)+
                }
            }
        }

        impl ::std::fmt::Display for $name {
            fn fmt(&self, f: &mut ::std::fmt::Formatter<'_>) -> ::std::fmt::Result {
                f.write_str(self.as_str())
            }
        }

        impl ::std::str::FromStr for $name {
            type Err = $crate::status::UnknownStatus;
            fn from_str(s: &str) -> ::std::result::Result<Self, $crate::status::UnknownStatus> {
                Self::ALL.iter().copied().find(|v| v.as_str() == s).ok_or_else(|| $crate::status::UnknownStatus {
                    kind: $kind,
                    value: s.escape_debug().to_string(),
                    expected: Self::ALL.iter().map(|v| format!("`{v}`")).collect::<Vec<_>>().join(", "),
                })
            }
        }

        impl ::serde::Serialize for $name {
            fn serialize<S: ::serde::Serializer>(&self, s: S) -> ::std::result::Result<S::Ok, S::Error> {
                s.serialize_str(self.as_str())
            }
        }

        impl<'de> ::serde::Deserialize<'de> for $name {
            fn deserialize<D: ::serde::Deserializer<'de>>(d: D) -> ::std::result::Result<Self, D::Error> {
                let word = <::std::string::String as ::serde::Deserialize>::deserialize(d)?;
                word.parse().map_err(<D::Error as ::serde::de::Error>::custom)
            }
        }
    };
}
pub(crate) use words;

words! {
    /// `submission_status` of the submission record, upper-cased as the original system wrote
    /// it (`docs/reference/original-system.md`).
    RecordStatus, "submission_status" {
        /// Claimed for a new submission (EvalAI's `submitted`).
        Submitted => "SUBMITTED",
        /// Claimed for a resume (EvalAI's `resuming`).
        Resuming => "RESUMING",
        /// Jobs running.
        Running => "RUNNING",
        /// Final scores posted.
        Finished => "FINISHED",
        /// Failed (the error is in `error`).
        Failed => "FAILED",
        /// Cancelled by the participant.
        Cancelled => "CANCELLED",
    }
}

words! {
    /// A pod's `status.phase`, as Kubernetes reports it.
    PodPhase, "pod phase" {
        /// Accepted, not every container started yet (scheduling, pulling images).
        Pending => "Pending",
        /// Bound to a node, a container running or starting again.
        Running => "Running",
        /// Every container ended with exit code 0.
        Succeeded => "Succeeded",
        /// Every container ended, one at least in failure (or the pod was stopped).
        Failed => "Failed",
        /// The node could not be reached (or no phase was reported).
        Unknown => "Unknown",
    }
}

impl PodPhase {
    /// The phase a status reports, read at the edge: a missing phase or one this version does
    /// not know is [`PodPhase::Unknown`], as Kubernetes itself says of a pod it cannot read.
    pub fn reported(phase: Option<&str>) -> PodPhase {
        phase
            .and_then(|p| p.parse().ok())
            .unwrap_or(PodPhase::Unknown)
    }

    /// Whether the pod ended: its containers will not run again.
    pub fn has_ended(self) -> bool {
        matches!(self, PodPhase::Succeeded | PodPhase::Failed)
    }

    /// Whether the pod is on its way or running: pending or running.
    pub fn is_live(self) -> bool {
        matches!(self, PodPhase::Pending | PodPhase::Running)
    }
}

impl RecordStatus {
    /// The statuses of a submission an execution still holds (claimed or running).
    pub const IN_FLIGHT: [RecordStatus; 3] = [
        RecordStatus::Submitted,
        RecordStatus::Resuming,
        RecordStatus::Running,
    ];

    /// Whether an execution still holds the submission (one of [`IN_FLIGHT`](Self::IN_FLIGHT)).
    pub fn is_in_flight(self) -> bool {
        Self::IN_FLIGHT.contains(&self)
    }

    /// Whether the submission ended (finished, failed or cancelled): what is not in flight.
    pub fn is_final(self) -> bool {
        !self.is_in_flight()
    }
}

words! {
    /// An execution's status as Step Functions reports it (`DescribeExecution`, the "Execution
    /// Status Change" event).
    ExecutionStatus, "execution status" {
        /// Still running.
        Running => "RUNNING",
        /// Ended well (or ended to continue as a new execution).
        Succeeded => "SUCCEEDED",
        /// Failed outside every Catch, or on purpose after Finalize.
        Failed => "FAILED",
        /// Ran past its time limit.
        TimedOut => "TIMED_OUT",
        /// Stopped by an operator.
        Aborted => "ABORTED",
        /// Failed, and may be redriven.
        PendingRedrive => "PENDING_REDRIVE",
    }
}

/// What Finalize settled for its execution (`$.final.status`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Settled {
    /// The submission's final status on our side (for a repeated Finalize, the one that
    /// stands).
    Ended(RecordStatus),
    /// This execution never claimed the submission: nothing of it was touched.
    Unclaimed,
    /// Another execution (a resume) holds the submission now: nothing of it was touched.
    Superseded,
}

impl Settled {
    /// The word in `$.final.status`.
    pub fn as_str(self) -> &'static str {
        match self {
            Settled::Ended(status) => status.as_str(),
            Settled::Unclaimed => "UNCLAIMED",
            Settled::Superseded => "SUPERSEDED",
        }
    }
}

impl fmt::Display for Settled {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for Settled {
    type Err = UnknownStatus;
    fn from_str(s: &str) -> Result<Self, UnknownStatus> {
        match s {
            "UNCLAIMED" => Ok(Settled::Unclaimed),
            "SUPERSEDED" => Ok(Settled::Superseded),
            _ => s
                .parse()
                .map(Settled::Ended)
                .map_err(|e: UnknownStatus| UnknownStatus {
                    kind: "settled status",
                    expected: format!("{}, `UNCLAIMED`, `SUPERSEDED`", e.expected),
                    ..e
                }),
        }
    }
}

impl Serialize for Settled {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.as_str())
    }
}

impl<'de> Deserialize<'de> for Settled {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        String::deserialize(d)?
            .parse()
            .map_err(serde::de::Error::custom)
    }
}

/// What the reaper did with one ended execution.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Reaping {
    /// Nothing was to be done (it runs, or Finalize ran to the end).
    Left,
    /// Only its held place was given back (Finalize ran, its release did not).
    Released,
    /// Finalize ran for it, and settled this.
    Finalized(Settled),
}

impl Reaping {
    /// The word in the reaper's report.
    pub fn as_str(self) -> &'static str {
        match self {
            Reaping::Left => "left",
            Reaping::Released => "released",
            Reaping::Finalized(settled) => settled.as_str(),
        }
    }
}

impl Serialize for Reaping {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.as_str())
    }
}

impl<'de> Deserialize<'de> for Reaping {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let word = String::deserialize(d)?;
        match word.as_str() {
            "left" => Ok(Reaping::Left),
            "released" => Ok(Reaping::Released),
            other => other
                .parse()
                .map(Reaping::Finalized)
                .map_err(serde::de::Error::custom),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_word_parses_back_to_its_value_and_an_unknown_one_is_named_with_the_expected() {
        for status in RecordStatus::ALL {
            assert_eq!(status.as_str().parse::<RecordStatus>(), Ok(*status));
        }
        for status in ExecutionStatus::ALL {
            assert_eq!(status.as_str().parse::<ExecutionStatus>(), Ok(*status));
        }
        let err = "finished".parse::<RecordStatus>().unwrap_err();
        assert_eq!(
            err.to_string(),
            "unknown submission_status `finished` (expected one of `SUBMITTED`, `RESUMING`, \
             `RUNNING`, `FINISHED`, `FAILED`, `CANCELLED`)"
        );
        let err = "DONE\n".parse::<ExecutionStatus>().unwrap_err();
        assert!(
            err.to_string()
                .starts_with("unknown execution status `DONE\\n`"),
            "{err}"
        );
    }

    #[test]
    fn only_a_claimed_or_running_record_is_in_flight() {
        let in_flight: Vec<_> = RecordStatus::ALL
            .iter()
            .filter(|s| s.is_in_flight())
            .map(|s| s.as_str())
            .collect();
        assert_eq!(in_flight, ["SUBMITTED", "RESUMING", "RUNNING"]);
    }

    #[test]
    fn settled_and_reaping_round_trip_through_their_words() {
        for settled in [
            Settled::Ended(RecordStatus::Finished),
            Settled::Ended(RecordStatus::Cancelled),
            Settled::Unclaimed,
            Settled::Superseded,
        ] {
            let json = serde_json::to_value(settled).unwrap();
            assert_eq!(json, settled.as_str());
            assert_eq!(serde_json::from_value::<Settled>(json).unwrap(), settled);
        }
        for reaping in [
            Reaping::Left,
            Reaping::Released,
            Reaping::Finalized(Settled::Ended(RecordStatus::Failed)),
            Reaping::Finalized(Settled::Superseded),
        ] {
            let json = serde_json::to_value(reaping).unwrap();
            assert_eq!(serde_json::from_value::<Reaping>(json).unwrap(), reaping);
        }
        let err = serde_json::from_value::<Settled>("RUNNING?".into()).unwrap_err();
        assert!(err.to_string().contains("UNCLAIMED"), "{err}");
    }
}
