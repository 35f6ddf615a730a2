//! Definitions refused at load, each with a stable error name and the location of the field.

use std::collections::HashMap;

use local_stepfunctions::StateMachine;
use serde_json::{json, Value};

const FN: &str = "arn:aws:lambda:us-east-1:123456789012:function:f";

/// A machine whose only state is `state`, named `A`.
fn one(state: Value) -> Value {
    json!({"StartAt": "A", "States": {"A": state}})
}

fn task(extra: Value) -> Value {
    let mut t = json!({"Type": "Task", "Resource": FN, "End": true});
    for (k, v) in extra.as_object().unwrap() {
        t[k] = v.clone();
    }
    one(t)
}

#[track_caller]
fn refused(definition: Value, name: &str, location: &str) -> String {
    let err = StateMachine::load(&definition, &HashMap::new())
        .expect_err("the definition must be refused");
    assert_eq!(err.name(), name, "{err}");
    assert_eq!(err.location(), location, "{err}");
    let message = err.to_string();
    assert!(message.contains(location), "{message}");
    message
}

#[test]
fn unknown_and_unsupported_state_types_and_fields_are_refused() {
    refused(
        one(json!({"Type": "Magic", "End": true})),
        "InvalidDefinition",
        "States.A.Type",
    );
    let m = refused(
        task(json!({"HeartbeatSeconds": 10})),
        "UnsupportedFeature",
        "States.A.HeartbeatSeconds",
    );
    assert!(m.contains("not supported"), "{m}");
    refused(
        task(json!({"HeartbeatSecondsPath": "$.t"})),
        "UnsupportedFeature",
        "States.A.HeartbeatSecondsPath",
    );
    refused(
        task(json!({"Credentials": {}})),
        "UnsupportedFeature",
        "States.A.Credentials",
    );
    refused(
        task(json!({"Assign": {"x": 1}})),
        "UnsupportedFeature",
        "States.A.Assign",
    );
    refused(
        task(json!({"QueryLanguage": "JSONata"})),
        "UnsupportedFeature",
        "States.A.QueryLanguage",
    );
    refused(task(json!({"Foo": 1})), "InvalidDefinition", "States.A.Foo");
    refused(
        one(json!({"Type": "Pass", "ResultSelector": {}, "End": true})),
        "InvalidDefinition",
        "States.A.ResultSelector",
    );
    refused(
        one(json!({"Type": "Fail", "Error": "E", "InputPath": "$"})),
        "InvalidDefinition",
        "States.A.InputPath",
    );
}

#[test]
fn transitions_must_be_complete_and_lead_somewhere() {
    refused(
        one(json!({"Type": "Pass"})),
        "InvalidDefinition",
        "States.A",
    );
    refused(
        one(json!({"Type": "Pass", "Next": "A", "End": true})),
        "InvalidDefinition",
        "States.A",
    );
    refused(
        one(json!({"Type": "Pass", "End": "yes"})),
        "InvalidDefinition",
        "States.A.End",
    );
    refused(
        one(json!({"Type": "Pass", "Next": "Nowhere"})),
        "UnknownStateName",
        "States.A.Next",
    );
    refused(
        json!({"StartAt": "B", "States": {"A": {"Type": "Succeed"}}}),
        "UnknownStateName",
        "StartAt",
    );
    refused(
        json!({"StartAt": "A", "States": {"A": {"Type": "Succeed"}, "Lost": {"Type": "Succeed"}}}),
        "UnreachableState",
        "States.Lost",
    );
    refused(
        json!({"StartAt": "A", "States": {"A": {"Type": "Pass", "Next": "B"}, "B": {"Type": "Pass", "Next": "A"}}}),
        "InvalidDefinition",
        "States",
    );
    refused(
        one(
            json!({"Type": "Choice", "Choices": [{"Variable": "$.a", "IsNull": true, "Next": "A"}], "Next": "A"}),
        ),
        "InvalidDefinition",
        "States.A.Next",
    );
    refused(
        one(json!({"Type": "Choice", "Choices": [{"Variable": "$.a", "IsNull": true}]})),
        "InvalidDefinition",
        "States.A.Choices[0]",
    );
    refused(
        one(
            json!({"Type": "Choice", "Choices": [{"Variable": "$.a", "IsNull": true, "Next": "A"}], "Default": "X"}),
        ),
        "UnknownStateName",
        "States.A.Default",
    );
    refused(
        task(json!({"Catch": [{"ErrorEquals": ["States.ALL"], "Next": "X"}]})),
        "UnknownStateName",
        "States.A.Catch[0].Next",
    );
}

#[test]
fn branches_are_self_contained_and_names_unique() {
    let branch = |states: Value| {
        json!({
            "StartAt": "P",
            "States": {
                "P": {"Type": "Parallel", "Branches": [{"StartAt": "In", "States": states}], "Next": "Out"},
                "Out": {"Type": "Succeed"}
            }
        })
    };
    refused(
        branch(json!({"In": {"Type": "Pass", "Next": "Out"}})),
        "UnknownStateName",
        "States.P.Branches[0].States.In.Next",
    );
    let m = refused(
        branch(json!({"In": {"Type": "Pass", "Next": "P2"}, "P2": {"Type": "Pass", "End": true}, "Out": {"Type": "Succeed"}}).clone()),
        "DuplicateStateName",
        "States.P.Branches[0].States.Out",
    );
    assert!(m.contains("also defined at `States.Out`"), "{m}");
    refused(
        one(json!({"Type": "Parallel", "Branches": [], "End": true})),
        "InvalidDefinition",
        "States.A",
    );
    refused(
        one(
            json!({"Type": "Parallel", "Branches": [{"StartAt": "X", "States": {"X": {"Type": "Succeed"}}, "Extra": 1}], "End": true}),
        ),
        "InvalidDefinition",
        "States.A.Branches[0].Extra",
    );
    refused(
        one(json!({"Type": "Pass", "End": true, "Comment": 3})),
        "InvalidDefinition",
        "States.A.Comment",
    );
    refused(
        json!({"StartAt": "A", "States": {"A": {"Type": "Succeed"}, &"n".repeat(81): {"Type": "Succeed"}}}),
        "InvalidDefinition",
        &format!("States.{}", "n".repeat(81)),
    );
}

#[test]
fn bad_paths_templates_and_intrinsics_are_refused_naming_state_and_field() {
    let m = refused(
        one(json!({"Type": "Pass", "InputPath": "$.a[?(@.b)]", "End": true})),
        "InvalidJsonPath",
        "States.A",
    );
    assert!(m.contains("InputPath"), "{m}");
    let m = refused(
        one(json!({"Type": "Pass", "Parameters": {"x.$": "nope"}, "End": true})),
        "InvalidPayloadTemplate",
        "States.A",
    );
    assert!(m.contains("x.$"), "{m}");
    refused(
        one(json!({"Type": "Pass", "ResultPath": "$.a[*]", "End": true})),
        "InvalidReferencePath",
        "States.A",
    );
    refused(
        one(json!({"Type": "Pass", "OutputPath": "$$.Execution", "End": true})),
        "InvalidJsonPath",
        "States.A",
    );
    refused(
        one(
            json!({"Type": "Pass", "Parameters": {"x.$": "States.Format('{} {}', $.a)"}, "End": true}),
        ),
        "InvalidIntrinsicFunction",
        "States.A",
    );
    refused(
        one(json!({"Type": "Wait", "SecondsPath": "$..s", "End": true})),
        "InvalidReferencePath",
        "States.A",
    );
    refused(
        one(json!({"Type": "Fail", "ErrorPath": "States.Nope($.a)"})),
        "InvalidIntrinsicFunction",
        "States.A",
    );
    refused(
        task(
            json!({"Catch": [{"ErrorEquals": ["States.ALL"], "ResultPath": "$.x[0:1]", "Next": "A"}], "End": true}),
        ),
        "InvalidReferencePath",
        "States.A.Catch[0]",
    );
}

#[test]
fn retriers_and_catchers_are_checked_field_by_field() {
    let retry = |r: Value| task(json!({"Retry": [r]}));
    refused(
        retry(json!({"ErrorEquals": []})),
        "InvalidDefinition",
        "States.A.Retry[0].ErrorEquals",
    );
    refused(
        retry(json!({"ErrorEquals": ["E"], "IntervalSeconds": 0})),
        "InvalidDefinition",
        "States.A.Retry[0].IntervalSeconds",
    );
    refused(
        retry(json!({"ErrorEquals": ["E"], "IntervalSeconds": 1.5})),
        "InvalidDefinition",
        "States.A.Retry[0].IntervalSeconds",
    );
    refused(
        retry(json!({"ErrorEquals": ["E"], "MaxAttempts": -1})),
        "InvalidDefinition",
        "States.A.Retry[0].MaxAttempts",
    );
    refused(
        retry(json!({"ErrorEquals": ["E"], "BackoffRate": 0.5})),
        "InvalidDefinition",
        "States.A.Retry[0].BackoffRate",
    );
    refused(
        retry(json!({"ErrorEquals": ["E"], "MaxDelaySeconds": 0})),
        "InvalidDefinition",
        "States.A.Retry[0].MaxDelaySeconds",
    );
    refused(
        retry(json!({"ErrorEquals": ["E"], "JitterStrategy": "HALF"})),
        "InvalidDefinition",
        "States.A.Retry[0].JitterStrategy",
    );
    refused(
        retry(json!({"ErrorEquals": ["E"], "Next": "A"})),
        "InvalidDefinition",
        "States.A.Retry[0].Next",
    );
    refused(
        retry(json!({"ErrorEquals": ["States.ALL", "E"]})),
        "InvalidDefinition",
        "States.A.Retry[0].ErrorEquals",
    );
    refused(
        task(json!({"Retry": [{"ErrorEquals": ["States.ALL"]}, {"ErrorEquals": ["E"]}]})),
        "InvalidDefinition",
        "States.A.Retry[0].ErrorEquals",
    );
    refused(
        task(json!({"Catch": [{"ErrorEquals": ["E"]}]})),
        "InvalidDefinition",
        "States.A.Catch[0]",
    );
    refused(
        task(json!({"TimeoutSeconds": 0})),
        "InvalidDefinition",
        "States.A.TimeoutSeconds",
    );
}

#[test]
fn lambda_resources_service_integrations_and_callbacks_are_checked() {
    let resource = |r: &str| task(json!({"Resource": r}));
    // A service integration is played by a handler registered under `<service>:<action>`.
    let machine = StateMachine::load(
        &resource("arn:aws:states:::sqs:sendMessage"),
        &HashMap::new(),
    )
    .unwrap();
    assert_eq!(machine.functions()[0].name, "sqs:sendMessage");
    StateMachine::load(
        &task(
            json!({"Resource": "arn:aws:states:::lambda:invoke.waitForTaskToken",
                     "Parameters": {"FunctionName": "f", "Payload": {"t.$": "$$.Task.Token"}}}),
        ),
        &HashMap::new(),
    )
    .unwrap();
    refused(
        resource("arn:aws:states:::ecs:runTask.sync"),
        "UnsupportedFeature",
        "States.A.Resource",
    );
    refused(
        resource("arn:aws:states:::nothing"),
        "InvalidDefinition",
        "States.A.Resource",
    );
    refused(
        resource("arn:aws:states:us-east-1:123456789012:activity:x"),
        "UnsupportedFeature",
        "States.A.Resource",
    );
    refused(resource("hello"), "InvalidDefinition", "States.A.Resource");
    refused(
        resource("arn:aws:lambda:us-east-1:1:layer:x:1"),
        "InvalidDefinition",
        "States.A.Resource",
    );
    let invoke =
        |p: Value| task(json!({"Resource": "arn:aws:states:::lambda:invoke", "Parameters": p}));
    refused(
        task(json!({"Resource": "arn:aws:states:::lambda:invoke"})),
        "InvalidDefinition",
        "States.A",
    );
    refused(
        invoke(json!({"Payload": {}})),
        "InvalidDefinition",
        "States.A.Parameters",
    );
    refused(
        invoke(json!({"FunctionName": "f", "InvocationType": "Event"})),
        "UnsupportedFeature",
        "States.A.Parameters.InvocationType",
    );
    refused(
        invoke(json!({"FunctionName.$": "$.f"})),
        "UnsupportedFeature",
        "States.A.Parameters.FunctionName.$",
    );
    refused(
        invoke(json!({"FunctionName": "f", "Other": 1})),
        "InvalidDefinition",
        "States.A.Parameters.Other",
    );
    refused(
        invoke(json!({"FunctionName": "bad name"})),
        "InvalidDefinition",
        "States.A.Parameters.FunctionName",
    );
}

#[test]
fn wait_fail_and_map_fields_are_checked() {
    refused(
        one(json!({"Type": "Wait", "End": true})),
        "InvalidDefinition",
        "States.A",
    );
    refused(
        one(json!({"Type": "Wait", "Seconds": 1, "SecondsPath": "$.s", "End": true})),
        "InvalidDefinition",
        "States.A",
    );
    refused(
        one(json!({"Type": "Wait", "Seconds": -1, "End": true})),
        "InvalidDefinition",
        "States.A.Seconds",
    );
    refused(
        one(json!({"Type": "Wait", "Timestamp": "2016-03-14t01:59:00z", "End": true})),
        "InvalidDefinition",
        "States.A.Timestamp",
    );
    refused(
        one(json!({"Type": "Fail", "Error": "E", "ErrorPath": "$.e"})),
        "InvalidDefinition",
        "States.A",
    );
    refused(
        one(json!({"Type": "Fail", "Next": "A"})),
        "InvalidDefinition",
        "States.A.Next",
    );
    let processor = json!({"StartAt": "X", "States": {"X": {"Type": "Succeed"}}});
    let map = |extra: Value| {
        let mut m = json!({"Type": "Map", "End": true});
        for (k, v) in extra.as_object().unwrap() {
            m[k] = v.clone();
        }
        one(m)
    };
    refused(map(json!({})), "InvalidDefinition", "States.A");
    refused(
        map(json!({"Iterator": processor, "ItemProcessor": processor})),
        "InvalidDefinition",
        "States.A",
    );
    let mut distributed = processor.clone();
    distributed["ProcessorConfig"] = json!({"Mode": "DISTRIBUTED", "ExecutionType": "STANDARD"});
    refused(
        map(json!({"ItemProcessor": distributed})),
        "UnsupportedFeature",
        "States.A.ItemProcessor.ProcessorConfig.ExecutionType",
    );
    distributed["ProcessorConfig"] = json!({"Mode": "DISTRIBUTED"});
    refused(
        map(json!({"ItemProcessor": distributed})),
        "UnsupportedFeature",
        "States.A.ItemProcessor.ProcessorConfig.Mode",
    );
    refused(
        map(json!({"Iterator": processor, "ItemReader": {}})),
        "UnsupportedFeature",
        "States.A.ItemReader",
    );
    refused(
        map(json!({"Iterator": processor, "ItemSelector": {}, "Parameters": {}})),
        "InvalidDefinition",
        "States.A",
    );
    refused(
        map(json!({"Iterator": processor, "MaxConcurrency": -1})),
        "InvalidDefinition",
        "States.A.MaxConcurrency",
    );
    refused(
        map(json!({"Iterator": processor, "MaxConcurrencyPath": "$.n"})),
        "UnsupportedFeature",
        "States.A.MaxConcurrencyPath",
    );
}

#[test]
fn the_top_level_is_checked_and_substitutions_must_resolve() {
    refused(json!([1]), "InvalidDefinition", "(definition)");
    refused(
        json!({"States": {"A": {"Type": "Succeed"}}}),
        "InvalidDefinition",
        "(definition)",
    );
    refused(
        json!({"StartAt": "A", "States": {}}),
        "InvalidDefinition",
        "States",
    );
    refused(
        json!({"StartAt": "A", "States": {"A": {"Type": "Succeed"}}, "Extra": 1}),
        "InvalidDefinition",
        "Extra",
    );
    refused(
        json!({"StartAt": "A", "States": {"A": {"Type": "Succeed"}}, "QueryLanguage": "JSONata"}),
        "UnsupportedFeature",
        "QueryLanguage",
    );
    refused(
        json!({"StartAt": "A", "States": {"A": {"Type": "Succeed"}}, "Version": "2.0"}),
        "UnsupportedFeature",
        "Version",
    );
    refused(
        json!({"StartAt": "A", "States": {"A": {"Type": "Succeed"}}, "TimeoutSeconds": 0}),
        "InvalidDefinition",
        "TimeoutSeconds",
    );
    refused(
        task(json!({"Resource": "${MissingArn}"})),
        "MissingSubstitution",
        "States.A.Resource",
    );
    let ok = json!({"StartAt": "A", "States": {"A": {"Type": "Succeed"}}, "Version": "1.0", "QueryLanguage": "JSONPath", "TimeoutSeconds": 60, "Comment": "c"});
    StateMachine::load(&ok, &HashMap::new()).unwrap();
}
