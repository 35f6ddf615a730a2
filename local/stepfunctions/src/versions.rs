//! State machine versions and aliases as Step Functions keeps them: a version is an immutable
//! snapshot numbered from 1 per state machine (numbers never reused), an alias names one
//! version, and `StartExecution` takes the unqualified ARN (the latest revision), a version's
//! or an alias's ("Associating executions with a version or alias").

use std::collections::HashMap;

use crate::definition::StateMachine;
use crate::error::StartError;

/// What a state machine ARN names once resolved: the definition an execution runs, and the
/// version and alias it is associated with (`None` for an unqualified start).
#[derive(Debug, Clone)]
pub(crate) struct Resolved {
    pub machine: StateMachine,
    pub version_arn: Option<String>,
    pub alias_arn: Option<String>,
}

/// One state machine's latest revision, its versions (index + 1 is the number) and aliases.
#[derive(Default)]
struct Machine {
    latest: Option<StateMachine>,
    versions: Vec<StateMachine>,
    aliases: HashMap<String, u32>,
}

/// Every state machine by its unqualified ARN.
#[derive(Default)]
pub(crate) struct Registry {
    machines: HashMap<String, Machine>,
}

/// `arn:aws:states:<region>:<account>:stateMachine:<name>[:<qualifier>]` split into its
/// unqualified ARN and qualifier.
fn split(arn: &str) -> Option<(&str, Option<&str>)> {
    let parts: Vec<&str> = arn.split(':').collect();
    if parts.len() < 7 || parts.len() > 8 || parts[2] != "states" || parts[5] != "stateMachine" {
        return None;
    }
    match parts.get(7) {
        Some(q) => Some((&arn[..arn.len() - q.len() - 1], Some(q))),
        None => Some((arn, None)),
    }
}

fn does_not_exist(arn: &str) -> StartError {
    StartError::StateMachineDoesNotExist {
        arn: arn.to_owned(),
    }
}

impl Registry {
    /// `machine` becomes the latest revision of the state machine at `arn` (unqualified).
    pub fn revise(&mut self, arn: &str, machine: &StateMachine) {
        self.machines.entry(arn.to_owned()).or_default().latest = Some(machine.clone());
    }

    /// `PublishStateMachineVersion` of `machine` as the latest revision: the version's ARN.
    pub fn publish(&mut self, arn: &str, machine: &StateMachine) -> String {
        let entry = self.machines.entry(arn.to_owned()).or_default();
        entry.latest = Some(machine.clone());
        entry.versions.push(machine.clone());
        format!("{arn}:{}", entry.versions.len())
    }

    /// `CreateStateMachineAlias` / `UpdateStateMachineAlias`: `alias` of the state machine
    /// `version_arn` belongs to now names that version. The alias's ARN.
    pub fn point(&mut self, alias: &str, version_arn: &str) -> Result<String, StartError> {
        let (arn, number) = match split(version_arn) {
            Some((arn, Some(q))) => (arn, q.parse::<u32>().ok()),
            _ => return Err(does_not_exist(version_arn)),
        };
        let machine = self
            .machines
            .get_mut(arn)
            .ok_or_else(|| does_not_exist(version_arn))?;
        let number = number
            .filter(|n| (1..=machine.versions.len() as u32).contains(n))
            .ok_or_else(|| does_not_exist(version_arn))?;
        let valid = !alias.is_empty()
            && alias.len() <= 80
            && alias.parse::<u32>().is_err()
            && alias
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_');
        if !valid {
            return Err(StartError::InvalidName {
                name: alias.to_owned(),
                reason: "an alias is 1 to 80 letters, digits, `-` and `_`, not a number".into(),
            });
        }
        machine.aliases.insert(alias.to_owned(), number);
        Ok(format!("{arn}:{alias}"))
    }

    /// The version `alias_arn` names now, as its ARN.
    pub fn target(&self, alias_arn: &str) -> Option<String> {
        let (arn, Some(alias)) = split(alias_arn)? else {
            return None;
        };
        let number = self.machines.get(arn)?.aliases.get(alias)?;
        Some(format!("{arn}:{number}"))
    }

    /// What `StartExecution` of `arn` runs.
    pub fn resolve(&self, arn: &str) -> Result<Resolved, StartError> {
        let (unqualified, qualifier) = split(arn).ok_or_else(|| does_not_exist(arn))?;
        let machine = self
            .machines
            .get(unqualified)
            .ok_or_else(|| does_not_exist(arn))?;
        let version = |number: u32| {
            machine
                .versions
                .get((number as usize).wrapping_sub(1))
                .map(|m| (m.clone(), format!("{unqualified}:{number}")))
        };
        let (machine, version_arn, alias_arn) = match qualifier {
            None => (machine.latest.clone(), None, None),
            Some(q) => match q.parse::<u32>() {
                Ok(number) => match version(number) {
                    Some((m, v)) => (Some(m), Some(v), None),
                    None => (None, None, None),
                },
                Err(_) => match machine.aliases.get(q).and_then(|n| version(*n)) {
                    Some((m, v)) => (Some(m), Some(v), Some(arn.to_owned())),
                    None => (None, None, None),
                },
            },
        };
        Ok(Resolved {
            machine: machine.ok_or_else(|| does_not_exist(arn))?,
            version_arn,
            alias_arn,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn machine(comment: &str) -> StateMachine {
        let definition = json!({
            "Comment": comment,
            "StartAt": "Done",
            "States": {"Done": {"Type": "Succeed"}}
        });
        StateMachine::load(&definition, &HashMap::new())
            .unwrap()
            .with_name("m")
    }

    const ARN: &str = "arn:aws:states:us-east-1:1:stateMachine:m";

    #[test]
    fn versions_are_numbered_and_an_alias_names_one() {
        let mut registry = Registry::default();
        let v1 = registry.publish(ARN, &machine("one"));
        let v2 = registry.publish(ARN, &machine("two"));
        assert_eq!(v1, format!("{ARN}:1"));
        assert_eq!(v2, format!("{ARN}:2"));
        let live = registry.point("live", &v1).unwrap();
        assert_eq!(live, format!("{ARN}:live"));
        let at = registry.resolve(&live).unwrap();
        assert_eq!(at.version_arn.as_deref(), Some(v1.as_str()));
        assert_eq!(at.alias_arn.as_deref(), Some(live.as_str()));
        registry.point("live", &v2).unwrap();
        assert_eq!(registry.target(&live).as_deref(), Some(v2.as_str()));
        // A version ARN is that version, with no alias; the unqualified ARN is the latest.
        let one = registry.resolve(&v1).unwrap();
        assert_eq!(
            (one.version_arn.as_deref(), one.alias_arn),
            (Some(v1.as_str()), None)
        );
        let latest = registry.resolve(ARN).unwrap();
        assert_eq!((latest.version_arn, latest.alias_arn), (None, None));
    }

    #[test]
    fn what_does_not_exist_is_refused() {
        let mut registry = Registry::default();
        assert!(registry.resolve(ARN).is_err());
        registry.revise(ARN, &machine("draft"));
        assert!(registry.resolve(ARN).is_ok());
        assert!(registry.resolve(&format!("{ARN}:1")).is_err());
        assert!(registry.resolve(&format!("{ARN}:live")).is_err());
        assert!(registry.point("live", &format!("{ARN}:1")).is_err());
        let v1 = registry.publish(ARN, &machine("one"));
        assert!(
            registry.point("7", &v1).is_err(),
            "an alias is not a number"
        );
        assert!(registry.point("a b", &v1).is_err());
        assert!(registry.resolve("arn:aws:lambda:r:1:function:f").is_err());
    }
}
