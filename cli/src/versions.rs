//! `lbctl ship` and `lbctl rollback`: the state machine's `live` alias moved to a version that
//! ships one function's new version, or back to an earlier version. New submissions start on
//! the version the alias names; executions already running keep the one they started on.

use aws_sdk_sfn::error::ProvideErrorMetadata as _;
use aws_sdk_sfn::types::RoutingConfigurationListItem;
use clap::Args;
use lb_infra::release::{self, ReleaseError};

use crate::error::{CliError, Result};
use crate::executions::StateMachineArgs;

/// `lbctl ship` options.
#[derive(Debug, Clone, Args)]
pub struct Ship {
    /// The function version to ship (`arn:aws:lambda:<region>:<account>:function:<name>:<n>`),
    /// as `make deploy-function` publishes it.
    #[arg(long = "function-version", value_name = "ARN")]
    pub function_version: String,
    #[command(flatten)]
    pub machine: StateMachineArgs,
}

/// `lbctl rollback` options.
#[derive(Debug, Clone, Args)]
pub struct Rollback {
    /// The version to go back to (default: the newest one before the alias's).
    #[arg(long, value_name = "N")]
    pub to: Option<u32>,
    #[command(flatten)]
    pub machine: StateMachineArgs,
}

/// The alias's ARN given, split: the state machine's ARN and the alias's name.
fn alias_of(args: &StateMachineArgs) -> Result<(String, &str)> {
    let arn = args.arn()?;
    let qualified = arn.split(':').count() == 8;
    match arn.rsplit_once(':') {
        Some((machine, alias)) if qualified && alias.parse::<u32>().is_err() => {
            Ok((machine.to_owned(), arn))
        }
        _ => Err(CliError::Usage(format!(
            "`{arn}` is not a state machine alias's ARN: pass the stack's StateMachineAliasArn \
             output (`...:stateMachine:<name>:live`)"
        ))),
    }
}

fn refused(e: ReleaseError) -> CliError {
    CliError::Refused(e.to_string())
}

/// The newest version the alias routes executions to (during a canary, the new one).
async fn current(sfn: &aws_sdk_sfn::Client, alias: &str) -> Result<String> {
    let described = sfn
        .describe_state_machine_alias()
        .state_machine_alias_arn(alias)
        .send()
        .await
        .map_err(|e| {
            CliError::sdk(
                format!("states `DescribeStateMachineAlias` of `{alias}`"),
                e,
            )
        })?;
    let routing: Vec<(&str, i32)> = described
        .routing_configuration()
        .iter()
        .map(|r| (r.state_machine_version_arn(), r.weight()))
        .collect();
    release::newest(&routing)
        .map(str::to_owned)
        .map_err(refused)
}

/// Every new execution through `alias` starts on `version` from now on.
async fn point(sfn: &aws_sdk_sfn::Client, alias: &str, version: &str) -> Result<()> {
    let route = RoutingConfigurationListItem::builder()
        .state_machine_version_arn(version)
        .weight(100)
        .build()
        .map_err(|e| CliError::sdk("a routing configuration", e))?;
    sfn.update_state_machine_alias()
        .state_machine_alias_arn(alias)
        .routing_configuration(route)
        .send()
        .await
        .map_err(|e| CliError::sdk(format!("states `UpdateStateMachineAlias` of `{alias}`"), e))?;
    Ok(())
}

/// `lbctl ship`: a state machine version whose definition is the alias's with the function's
/// ARN swapped for `--function-version`, published, and the alias moved to it.
pub async fn ship(args: Ship) -> Result<u8> {
    let (machine, alias) = alias_of(&args.machine)?;
    let sdk = crate::aws::config().await?;
    let sfn = aws_sdk_sfn::Client::new(&sdk);
    let from = current(&sfn, alias).await?;
    let definition = sfn
        .describe_state_machine()
        .state_machine_arn(&from)
        .send()
        .await
        .map_err(|e| CliError::sdk(format!("states `DescribeStateMachine` of `{from}`"), e))?
        .definition;
    let swapped =
        release::with_function_version(&definition, &args.function_version).map_err(refused)?;
    if swapped.replaced.is_empty() {
        outln!(
            "{from} already runs {}: nothing to ship",
            args.function_version
        );
        return Ok(0);
    }
    let published = sfn
        .update_state_machine()
        .state_machine_arn(&machine)
        .definition(&swapped.definition)
        .publish(true)
        .version_description(format!("ships {}", args.function_version))
        .send()
        .await
        .map_err(|e| CliError::sdk(format!("states `UpdateStateMachine` of `{machine}`"), e))?;
    let to = published.state_machine_version_arn().ok_or_else(|| {
        CliError::Refused(format!(
            "`UpdateStateMachine` of `{machine}` published no version"
        ))
    })?;
    point(&sfn, alias, to).await?;
    outln!("{alias}: {from} -> {to}");
    outln!(
        "  ships  {} (was {})",
        args.function_version,
        swapped.replaced.join(", ")
    );
    outln!("  executions already running stay on {from}; `lbctl rollback` goes back");
    Ok(0)
}

/// `lbctl rollback`: the alias moved back to `--to`, or to the newest version before its own
/// that still exists.
pub async fn rollback(args: Rollback) -> Result<u8> {
    let (_, alias) = alias_of(&args.machine)?;
    let sdk = crate::aws::config().await?;
    let sfn = aws_sdk_sfn::Client::new(&sdk);
    let from = current(&sfn, alias).await?;
    let (machine, number) = release::version_number(&from).map_err(refused)?;
    let mut target = None;
    for candidate in release::rollback_candidates(number, args.to).map_err(refused)? {
        let arn = format!("{machine}:{candidate}");
        match sfn
            .describe_state_machine()
            .state_machine_arn(&arn)
            .send()
            .await
        {
            Ok(_) => {
                target = Some(arn);
                break;
            }
            Err(e) if e.code() == Some("StateMachineDoesNotExist") => continue,
            Err(e) => {
                return Err(CliError::sdk(
                    format!("states `DescribeStateMachine` of `{arn}`"),
                    e,
                ))
            }
        }
    }
    let to = target
        .ok_or_else(|| CliError::NotFound(format!("no version before {from} exists any more")))?;
    point(&sfn, alias, &to).await?;
    outln!("{alias}: {from} -> {to}");
    outln!("  new submissions start on {to}; executions running on {from} finish there");
    Ok(0)
}
