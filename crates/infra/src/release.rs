//! Versioned deploys, decided: the state machine version that ships one function's new version
//! (its definition with that function's ARN swapped), and the version the `live` alias routes
//! to and rolls back to. `lbctl ship` and `lbctl rollback` call the APIs around these.

use serde_json::Value;

/// Why a release step cannot be decided.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ReleaseError {
    /// Not `arn:<partition>:lambda:<region>:<account>:function:<name>:<version>`.
    #[error(
        "`{0}` is not a function version's ARN (arn:aws:lambda:<region>:<account>:function:<name>:<number>)"
    )]
    NotAFunctionVersion(String),
    /// Not a state machine's version (`...:stateMachine:<name>:<number>`).
    #[error("`{0}` is not a state machine version's ARN (...:stateMachine:<name>:<number>)")]
    NotAStateMachineVersion(String),
    /// The definition is not JSON.
    #[error("the state machine's definition is not JSON: {0}")]
    Definition(String),
    /// No Task of the definition invokes that function: its version ships alone.
    #[error("no state of the definition invokes `{0}`")]
    NotInDefinition(String),
    /// The alias routes to no version.
    #[error("the alias routes to no version")]
    NoRoute,
    /// There is no version before the one the alias names.
    #[error("version {0} is the first: there is nothing to roll back to")]
    NothingBefore(u32),
    /// `--to` names the version the alias already names, or a later one.
    #[error("version {to} is not before version {current}, which the alias names")]
    NotBefore {
        /// The version asked for.
        to: u32,
        /// The alias's.
        current: u32,
    },
}

/// A Lambda ARN split: `(function ARN without qualifier, function name, qualifier)`.
fn lambda_arn(text: &str) -> Option<(&str, &str, Option<&str>)> {
    let parts: Vec<&str> = text.split(':').collect();
    if !(7..=8).contains(&parts.len()) || parts[2] != "lambda" || parts[5] != "function" {
        return None;
    }
    let qualifier = parts.get(7).copied();
    let unqualified = match qualifier {
        Some(q) => &text[..text.len() - q.len() - 1],
        None => text,
    };
    Some((unqualified, parts[6], qualifier))
}

/// What shipping a function version does to a definition.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Swapped {
    /// The definition naming the new version.
    pub definition: String,
    /// The function ARNs it named before (one, normally).
    pub replaced: Vec<String>,
}

/// `definition` with every Task that invokes `version_arn`'s function invoking that version
/// instead; `replaced` empty when it already did.
pub fn with_function_version(definition: &str, version_arn: &str) -> Result<Swapped, ReleaseError> {
    let not_version = || ReleaseError::NotAFunctionVersion(version_arn.to_owned());
    let (function, name, qualifier) = lambda_arn(version_arn).ok_or_else(not_version)?;
    if !qualifier.is_some_and(|q| q.parse::<u32>().is_ok_and(|n| n > 0)) {
        return Err(not_version());
    }
    let mut root: Value =
        serde_json::from_str(definition).map_err(|e| ReleaseError::Definition(e.to_string()))?;
    let mut found = 0;
    let mut replaced = Vec::new();
    swap(&mut root, function, version_arn, &mut found, &mut replaced);
    if found == 0 {
        return Err(ReleaseError::NotInDefinition(name.to_owned()));
    }
    let definition =
        serde_json::to_string(&root).map_err(|e| ReleaseError::Definition(e.to_string()))?;
    Ok(Swapped {
        definition,
        replaced,
    })
}

/// Every `Resource` (or lambda:invoke's `FunctionName`) naming `function`, any qualifier.
fn swap(
    node: &mut Value,
    function: &str,
    version_arn: &str,
    found: &mut usize,
    replaced: &mut Vec<String>,
) {
    match node {
        Value::Object(map) => {
            for (key, value) in map.iter_mut() {
                let names = matches!(key.as_str(), "Resource" | "FunctionName");
                let hit = value
                    .as_str()
                    .and_then(lambda_arn)
                    .is_some_and(|(f, _, _)| f == function);
                if names && hit {
                    *found += 1;
                    if value.as_str() != Some(version_arn) {
                        replaced.push(value.as_str().unwrap_or_default().to_owned());
                        *value = Value::String(version_arn.to_owned());
                    }
                } else {
                    swap(value, function, version_arn, found, replaced);
                }
            }
        }
        Value::Array(items) => items
            .iter_mut()
            .for_each(|v| swap(v, function, version_arn, found, replaced)),
        _ => {}
    }
}

/// A state machine version's ARN split into the state machine's ARN and the number.
pub fn version_number(arn: &str) -> Result<(&str, u32), ReleaseError> {
    let not = || ReleaseError::NotAStateMachineVersion(arn.to_owned());
    let (machine, number) = arn.rsplit_once(':').ok_or_else(not)?;
    let number = number
        .parse::<u32>()
        .ok()
        .filter(|n| *n > 0)
        .ok_or_else(not)?;
    if machine.split(':').nth(5) != Some("stateMachine") || machine.split(':').count() != 7 {
        return Err(not());
    }
    Ok((machine, number))
}

/// The newest version an alias's routing sends executions to, whatever its weight: during a
/// gradual deploy, the new version (a ship builds on it, a rollback goes back from it to the
/// one before, which ends the canary).
pub fn newest<'a>(routing: &[(&'a str, i32)]) -> Result<&'a str, ReleaseError> {
    routing
        .iter()
        .filter(|(_, weight)| *weight > 0)
        .filter_map(|(arn, _)| version_number(arn).ok().map(|(_, n)| (n, *arn)))
        .max()
        .map(|(_, arn)| arn)
        .ok_or(ReleaseError::NoRoute)
}

/// The versions to try, newest first, when rolling back from `current`: `to` alone when
/// given, else every earlier one (some may have been deleted).
pub fn rollback_candidates(current: u32, to: Option<u32>) -> Result<Vec<u32>, ReleaseError> {
    match to {
        Some(to) if to == 0 || to >= current => Err(ReleaseError::NotBefore { to, current }),
        Some(to) => Ok(vec![to]),
        None if current <= 1 => Err(ReleaseError::NothingBefore(current)),
        None => Ok((1..current).rev().collect()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    const INTAKE_1: &str = "arn:aws:lambda:us-east-1:1:function:lb-intake:1";
    const INTAKE_2: &str = "arn:aws:lambda:us-east-1:1:function:lb-intake:2";

    fn definition() -> String {
        json!({
            "StartAt": "Intake",
            "States": {
                "Intake": {"Type": "Task", "Resource": INTAKE_1, "Next": "Again"},
                "Again": {"Type": "Task", "Resource": "arn:aws:states:::lambda:invoke",
                          "Parameters": {"FunctionName": INTAKE_1}, "Next": "Monitor"},
                "Monitor": {"Type": "Task", "Resource": "arn:aws:lambda:us-east-1:1:function:lb-intake-monitor:1", "End": true}
            }
        })
        .to_string()
    }

    #[test]
    fn shipping_a_version_swaps_only_that_function_s_arns() {
        let swapped = with_function_version(&definition(), INTAKE_2).unwrap();
        assert_eq!(swapped.replaced, [INTAKE_1, INTAKE_1]);
        let after: Value = serde_json::from_str(&swapped.definition).unwrap();
        assert_eq!(after["States"]["Intake"]["Resource"], INTAKE_2);
        assert_eq!(
            after["States"]["Again"]["Parameters"]["FunctionName"],
            INTAKE_2
        );
        // A function whose name starts the same is another function.
        assert_eq!(
            after["States"]["Monitor"]["Resource"],
            "arn:aws:lambda:us-east-1:1:function:lb-intake-monitor:1"
        );
        // Shipping it again changes nothing.
        let again = with_function_version(&swapped.definition, INTAKE_2).unwrap();
        assert!(again.replaced.is_empty());
    }

    #[test]
    fn what_is_not_a_version_or_not_in_the_definition_is_refused() {
        let d = definition();
        for bad in [
            "arn:aws:lambda:us-east-1:1:function:lb-intake",
            "arn:aws:lambda:us-east-1:1:function:lb-intake:live",
            "arn:aws:lambda:us-east-1:1:function:lb-intake:0",
            "lb-intake:2",
        ] {
            assert!(
                matches!(
                    with_function_version(&d, bad),
                    Err(ReleaseError::NotAFunctionVersion(_))
                ),
                "{bad}"
            );
        }
        assert_eq!(
            with_function_version(&d, "arn:aws:lambda:us-east-1:1:function:lb-wake:3"),
            Err(ReleaseError::NotInDefinition("lb-wake".into()))
        );
        assert!(matches!(
            with_function_version("{", INTAKE_2),
            Err(ReleaseError::Definition(_))
        ));
    }

    #[test]
    fn the_alias_s_newest_version_is_what_a_rollback_goes_back_from() {
        let m = "arn:aws:states:us-east-1:1:stateMachine:s";
        let (v6, v7) = (format!("{m}:6"), format!("{m}:7"));
        assert_eq!(newest(&[(&v7, 100)]), Ok(v7.as_str()));
        // A canary: 10% on 7. Rolling back from 7 goes to 6, which ends the canary.
        assert_eq!(newest(&[(&v6, 90), (&v7, 10)]), Ok(v7.as_str()));
        assert_eq!(newest(&[(&v7, 90), (&v6, 10)]), Ok(v7.as_str()));
        assert_eq!(newest(&[(&v6, 100), (&v7, 0)]), Ok(v6.as_str()));
        assert_eq!(newest(&[]), Err(ReleaseError::NoRoute));
        assert_eq!(version_number(&v7), Ok((m, 7)));
        assert!(version_number(&format!("{m}:live")).is_err());
        assert!(version_number(m).is_err());
        assert_eq!(rollback_candidates(7, None), Ok(vec![6, 5, 4, 3, 2, 1]));
        assert_eq!(rollback_candidates(7, Some(3)), Ok(vec![3]));
        assert!(rollback_candidates(7, Some(7)).is_err());
        assert!(rollback_candidates(7, Some(0)).is_err());
        assert_eq!(
            rollback_candidates(1, None),
            Err(ReleaseError::NothingBefore(1))
        );
    }
}
