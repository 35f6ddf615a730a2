//! The AWS service integrations the state machine calls directly, played for the embedded
//! executor by moto (DynamoDB) and by the executor itself (Step Functions): the Task's
//! Parameters go to the API as written, its errors come back under the names Step Functions
//! gives them.
//!
//! Followed: the developer guide's "AWS SDK integrations" (parameters are the API's, in
//! PascalCase; an error is `<Service>.<Error>` in PascalCase with the `Exception` suffix, so
//! DynamoDB's `ConditionalCheckFailedException` is `DynamoDb.ConditionalCheckFailedException`;
//! the result is the API's response) and DynamoDB's JSON wire format for attribute values.

use std::collections::HashMap;

use aws_config::SdkConfig;
use aws_sdk_dynamodb::error::ProvideErrorMetadata;
use aws_sdk_dynamodb::types::{AttributeValue, ReturnValue};
use local_stepfunctions::{TaskError, TaskMap};

use crate::events::LateCallbacks;
use serde_json::{json, Map, Value};

/// The handler key of the wake table's wait.
pub const DYNAMODB_UPDATE_ITEM: &str = "aws-sdk:dynamodb:updateItem";

/// The handler key of `ContinueAsNew` (the optimized Step Functions integration).
pub const STATES_START_EXECUTION: &str = "states:startExecution";

/// The handler key of `WhichVersion` (the AWS SDK integration's `DescribeExecution`).
pub const SFN_DESCRIBE_EXECUTION: &str = "aws-sdk:sfn:describeExecution";

/// The `WaitForChange` state's Parameters of the deployed definition as Step Functions
/// resolves them for a submission's wait (token, execution `submission-<id>-a`), with the
/// table named [`crate::stack::WAKE_TABLE`]: what tests write to stand for a waiting execution.
pub fn wait_for_change(token: &str, submission_id: u64, challenge: u64, seen: u64) -> Value {
    wait_for_change_since(token, submission_id, challenge, seen, 0)
}

/// The same for a submission EvalAI received at `submitted_at` (epoch seconds; 0: not known).
pub fn wait_for_change_since(
    token: &str,
    submission_id: u64,
    challenge: u64,
    seen: u64,
    submitted_at: u64,
) -> Value {
    let definition: Value =
        serde_json::from_str(include_str!("../../../statemachine/submission.asl.json"))
            .expect("the deployed definition is JSON");
    let state = definition["States"]["WaitForChange"]
        .as_object()
        .expect("the definition has WaitForChange");
    let flow = lb_asl::DataFlow::from_state(state).expect("WaitForChange's data flow");
    let input = json!({
        "intake": {"submission": {"submission_id": submission_id, "challenge_id": challenge, "submitted_at": submitted_at}},
        "run": {"monitor": {"seen": seen, "expires_at": 1_900_000_000u64, "wait_seconds": 60}}
    });
    let context = json!({
        "Task": {"Token": token},
        "Execution": {"Name": format!("submission-{submission_id}-a")}
    });
    let env = lb_asl::Env::with_context(&context);
    let mut params = flow
        .effective_input(&input, &env)
        .expect("WaitForChange's Parameters resolve");
    params["TableName"] = json!(crate::stack::WAKE_TABLE);
    params
}

/// `tasks` with the integrations the deployed definition uses: DynamoDB against `sdk`
/// (moto), Step Functions against the executor `executor` is bound to.
pub fn with_services(tasks: TaskMap, sdk: &SdkConfig, executor: LateCallbacks) -> TaskMap {
    let client = aws_sdk_dynamodb::Client::new(sdk);
    tasks
        .with(DYNAMODB_UPDATE_ITEM, move |params: Value| {
            let client = client.clone();
            async move { update_item(&client, params).await }
        })
        .with(STATES_START_EXECUTION, {
            let executor = executor.clone();
            move |params: Value| {
                let executor = executor.clone();
                async move { start_execution(&executor, params) }
            }
        })
        .with(SFN_DESCRIBE_EXECUTION, move |params: Value| {
            let executor = executor.clone();
            async move { describe_execution(&executor, &params) }
        })
}

/// `DescribeExecution` through the AWS SDK integration: the execution's ARN, status and the
/// version and alias it was started through (`StateMachineVersionArn`,
/// `StateMachineAliasArn`, absent for an unqualified start, as the API leaves them out). The
/// API's other fields (input, dates) are not played: nothing in the definition reads them.
pub fn describe_execution(executor: &LateCallbacks, params: &Value) -> Result<Value, TaskError> {
    let arn = params["ExecutionArn"].as_str().ok_or_else(|| {
        TaskError::new("Sfn.InvalidArnException", "`ExecutionArn` must be a string")
    })?;
    let described = executor
        .executor()
        .and_then(|e| e.describe(arn))
        .ok_or_else(|| {
            TaskError::new(
                "Sfn.ExecutionDoesNotExistException",
                format!("Execution Does Not Exist: '{arn}'"),
            )
        })?;
    let mut out = json!({
        "ExecutionArn": arn,
        "Status": crate::events::execution_status(described.status).as_str(),
    });
    if let Some(version) = described.version_arn {
        out["StateMachineVersionArn"] = json!(version);
    }
    if let Some(alias) = described.alias_arn {
        out["StateMachineAliasArn"] = json!(alias);
    }
    Ok(out)
}

/// `StartExecution` with the Task's parameters (`StateMachineArn`, `Name`, `Input` as JSON or
/// as its text), errors named as the optimized integration names them
/// (`StepFunctions.<Error>Exception`).
pub fn start_execution(executor: &LateCallbacks, params: Value) -> Result<Value, TaskError> {
    let refuse =
        |problem: String| TaskError::new("StepFunctions.InvalidExecutionInputException", problem);
    let text = |key: &str| {
        params[key]
            .as_str()
            .ok_or_else(|| refuse(format!("`{key}` must be a string")))
    };
    let machine = text("StateMachineArn")?;
    let name = text("Name")?;
    let input = match &params["Input"] {
        Value::String(text) => {
            serde_json::from_str(text).map_err(|e| refuse(format!("`Input` is not JSON: {e}")))?
        }
        Value::Null => json!({}),
        value => value.clone(),
    };
    let executor = executor
        .executor()
        .ok_or_else(|| TaskError::new("StepFunctions.AWSStepFunctionsException", "no executor"))?;
    executor.start_execution(machine, name, input).map_err(|e| {
        TaskError::new(
            format!("StepFunctions.{}Exception", e.name()),
            e.to_string(),
        )
    })
}

fn invalid(problem: impl Into<String>) -> TaskError {
    // What the SDK integration reports for parameters the API refuses before sending.
    TaskError::new("DynamoDb.ValidationException", problem.into())
}

/// DynamoDB `UpdateItem` with the Task's parameters.
pub async fn update_item(
    client: &aws_sdk_dynamodb::Client,
    params: Value,
) -> Result<Value, TaskError> {
    let Value::Object(params) = params else {
        return Err(invalid("the parameters must be an object"));
    };
    let mut request = client.update_item();
    for (key, value) in &params {
        request = match key.as_str() {
            "TableName" => request.table_name(text(key, value)?),
            "Key" => request.set_key(Some(item(key, value)?)),
            "UpdateExpression" => request.update_expression(text(key, value)?),
            "ConditionExpression" => request.condition_expression(text(key, value)?),
            "ExpressionAttributeNames" => {
                let Value::Object(names) = value else {
                    return Err(invalid(format!("`{key}` must be an object")));
                };
                names.iter().try_fold(request, |r, (k, v)| {
                    Ok::<_, TaskError>(r.expression_attribute_names(k, text(key, v)?))
                })?
            }
            "ExpressionAttributeValues" => {
                request.set_expression_attribute_values(Some(item(key, value)?))
            }
            "ReturnValues" => request.return_values(ReturnValue::from(text(key, value)?)),
            other => {
                return Err(invalid(format!(
                    "`{other}` is not a parameter this local integration passes on"
                )))
            }
        };
    }
    match request.send().await {
        Ok(out) => {
            let mut result = Map::new();
            if let Some(attributes) = out.attributes() {
                result.insert("Attributes".into(), to_json_item(attributes));
            }
            Ok(Value::Object(result))
        }
        Err(e) => {
            let code = e.code().unwrap_or("DynamoDbException").to_owned();
            let message = e.message().unwrap_or_default().to_owned();
            let code = if code.ends_with("Exception") {
                code
            } else {
                format!("{code}Exception")
            };
            Err(TaskError::new(
                format!("DynamoDb.{code}"),
                format!("{message} (Service: DynamoDb, Status Code: 400, Error Code: {code})"),
            ))
        }
    }
}

fn text<'a>(key: &str, value: &'a Value) -> Result<&'a str, TaskError> {
    value
        .as_str()
        .ok_or_else(|| invalid(format!("`{key}` must be a string")))
}

fn item(key: &str, value: &Value) -> Result<HashMap<String, AttributeValue>, TaskError> {
    let Value::Object(map) = value else {
        return Err(invalid(format!("`{key}` must be an object")));
    };
    map.iter()
        .map(|(k, v)| Ok((k.clone(), attribute(&format!("{key}.{k}"), v)?)))
        .collect()
}

/// One attribute value in DynamoDB's JSON form (`{"S": "..."}`, `{"N": "1"}`, ...).
fn attribute(at: &str, value: &Value) -> Result<AttributeValue, TaskError> {
    let bad = || invalid(format!("`{at}` is not a DynamoDB attribute value"));
    let Value::Object(map) = value else {
        return Err(bad());
    };
    let [(kind, inner)] = map.iter().collect::<Vec<_>>()[..] else {
        return Err(bad());
    };
    let strings = |v: &Value| -> Result<Vec<String>, TaskError> {
        v.as_array()
            .ok_or_else(bad)?
            .iter()
            .map(|s| s.as_str().map(str::to_owned).ok_or_else(bad))
            .collect()
    };
    Ok(match kind.as_str() {
        "S" => AttributeValue::S(inner.as_str().ok_or_else(bad)?.to_owned()),
        "N" => {
            let n = inner.as_str().ok_or_else(bad)?;
            if n.parse::<f64>().is_err() {
                return Err(invalid(format!("`{at}`: `{n}` is not a number")));
            }
            AttributeValue::N(n.to_owned())
        }
        "BOOL" => AttributeValue::Bool(inner.as_bool().ok_or_else(bad)?),
        "NULL" => AttributeValue::Null(inner.as_bool().ok_or_else(bad)?),
        "SS" => AttributeValue::Ss(strings(inner)?),
        "NS" => AttributeValue::Ns(strings(inner)?),
        "L" => AttributeValue::L(
            inner
                .as_array()
                .ok_or_else(bad)?
                .iter()
                .map(|v| attribute(at, v))
                .collect::<Result<_, _>>()?,
        ),
        "M" => AttributeValue::M(item(at, inner)?),
        _ => return Err(bad()),
    })
}

fn to_json_item(item: &HashMap<String, AttributeValue>) -> Value {
    Value::Object(item.iter().map(|(k, v)| (k.clone(), to_json(v))).collect())
}

fn to_json(value: &AttributeValue) -> Value {
    match value {
        AttributeValue::S(s) => json!({ "S": s }),
        AttributeValue::N(n) => json!({ "N": n }),
        AttributeValue::Bool(b) => json!({ "BOOL": b }),
        AttributeValue::Null(b) => json!({ "NULL": b }),
        AttributeValue::Ss(v) => json!({ "SS": v }),
        AttributeValue::Ns(v) => json!({ "NS": v }),
        AttributeValue::L(v) => json!({ "L": v.iter().map(to_json).collect::<Vec<_>>() }),
        AttributeValue::M(m) => json!({ "M": to_json_item(m) }),
        _ => Value::Null,
    }
}
