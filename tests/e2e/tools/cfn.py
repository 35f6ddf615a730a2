"""infra/app.yaml as `sam deploy` handles it, offline: package, transform, deploy to moto.

    cfn.py transform TEMPLATE                 print the transformed template (JSON)
    cfn.py json TEMPLATE                      print a template without a transform as JSON
    cfn.py deploy TEMPLATE STACK [K=V ...]    package to moto's S3, transform, create the
                                              stack on moto's CloudFormation (AWS_ENDPOINT_URL),
                                              print {status, resources, tables} as JSON

`package` does what `sam package` documents: every local CodeUri / DefinitionUri is uploaded
to the artifacts bucket and replaced by its S3 location (the code directories of `make build`
may not exist in tests: an empty bootstrap stands in, moto never runs it).
"""

import io
import json
import os
import sys
import zipfile

import boto3
import yaml
from samtranslator.translator.transform import transform


class CfnLoader(yaml.SafeLoader):
    """YAML with CloudFormation's short-form tags (`!Ref X` -> {"Ref": "X"})."""


def _tag(loader, suffix, node):
    name = "Ref" if suffix == "Ref" else "Fn::" + suffix
    if isinstance(node, yaml.ScalarNode):
        value = loader.construct_scalar(node)
        if suffix == "GetAtt":
            value = value.split(".", 1)
    elif isinstance(node, yaml.SequenceNode):
        value = loader.construct_sequence(node, deep=True)
    else:
        value = loader.construct_mapping(node, deep=True)
    return {name: value}


CfnLoader.add_multi_constructor("!", _tag)


def load(path):
    with open(path) as f:
        return yaml.load(f, Loader=CfnLoader)


class NoManagedPolicies:
    """The template names no managed policy by name, so none has to be looked up."""

    def load(self):
        return {}


def package(template, base, s3=None, bucket="artifacts"):
    for resource in template["Resources"].values():
        props = resource.get("Properties", {})
        kind = resource["Type"]
        if kind == "AWS::Serverless::Function" and isinstance(props.get("CodeUri"), str):
            key = "code/" + props["CodeUri"].strip("/").replace("/", "-") + ".zip"
            if s3:
                s3.put_object(Bucket=bucket, Key=key, Body=_zip(os.path.join(base, props["CodeUri"])))
            props["CodeUri"] = f"s3://{bucket}/{key}"
        if kind == "AWS::Serverless::StateMachine" and isinstance(props.get("DefinitionUri"), str):
            path = os.path.join(base, props["DefinitionUri"])
            key = "statemachine/" + os.path.basename(path)
            if s3:
                with open(path, "rb") as f:
                    s3.put_object(Bucket=bucket, Key=key, Body=f.read())
            props["DefinitionUri"] = {"Bucket": bucket, "Key": key}
    return template


def _zip(directory):
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        bootstrap = os.path.join(directory, "bootstrap")
        if os.path.exists(bootstrap):
            z.write(bootstrap, "bootstrap")
        else:
            z.writestr("bootstrap", "")
    return buf.getvalue()


# What moto's CloudFormation does not model: it fails on a Ref to them. For moto only, the
# resource is left out and each Ref to one becomes an ARN moto knows: a function's alias its
# function's (moto has no alias to invoke), a state machine's alias or version its ARN so
# qualified. The test asserts they are declared, and what moto created.
UNMODELLED = {"AWS::Lambda::Alias", "AWS::StepFunctions::StateMachineVersion",
              "AWS::StepFunctions::StateMachineAlias"}


def for_moto(template):
    resources = template["Resources"]
    skipped = {k: v for k, v in resources.items() if v["Type"] in UNMODELLED}

    def arn(logical):
        props = skipped[logical]["Properties"]
        if skipped[logical]["Type"] == "AWS::Lambda::Alias":
            return {"Fn::GetAtt": [props["FunctionName"]["Ref"], "Arn"]}
        if skipped[logical]["Type"] == "AWS::StepFunctions::StateMachineAlias":
            version = props["DeploymentPreference"]["StateMachineVersionArn"]["Ref"]
            machine = skipped[version]["Properties"]["StateMachineArn"]
            return {"Fn::Join": [":", [machine, props["Name"]]]}
        return {"Fn::Join": [":", [props["StateMachineArn"], "1"]]}

    def walk(node):
        if isinstance(node, dict):
            if set(node) == {"Ref"} and node["Ref"] in skipped:
                return arn(node["Ref"])
            return {k: walk(v) for k, v in node.items()}
        if isinstance(node, list):
            return [walk(v) for v in node]
        return node

    kept = {k: v for k, v in resources.items() if k not in skipped}
    return {**template, "Resources": walk(kept), "Outputs": walk(template.get("Outputs", {}))}


def translated(path, parameters, s3=None):
    template = package(load(path), os.path.dirname(os.path.abspath(path)), s3)
    return transform(template, parameters, NoManagedPolicies())


def main(argv):
    command, path = argv[1], argv[2]
    if command == "transform":
        print(json.dumps(translated(path, {}), indent=1, sort_keys=True))
        return 0
    if command == "json":
        print(json.dumps(load(path), indent=1, sort_keys=True))
        return 0
    stack = argv[3]
    parameters = dict(a.split("=", 1) for a in argv[4:])
    s3 = boto3.client("s3")
    s3.create_bucket(Bucket="artifacts")
    body = translated(path, parameters, s3)
    cfn = boto3.client("cloudformation")
    cfn.create_stack(
        StackName=stack,
        TemplateBody=json.dumps(for_moto(body)),
        Parameters=[{"ParameterKey": k, "ParameterValue": v} for k, v in parameters.items()],
        Capabilities=["CAPABILITY_IAM", "CAPABILITY_AUTO_EXPAND"],
    )
    cfn.get_waiter("stack_create_complete").wait(
        StackName=stack, WaiterConfig={"Delay": 1, "MaxAttempts": 120}
    )
    status = cfn.describe_stacks(StackName=stack)["Stacks"][0]["StackStatus"]
    resources = cfn.list_stack_resources(StackName=stack)["StackResourceSummaries"]
    dynamodb = boto3.client("dynamodb")
    tables = {}
    for name in dynamodb.list_tables()["TableNames"]:
        table = dynamodb.describe_table(TableName=name)["Table"]
        tables[name] = {
            "keys": [[k["AttributeName"], k["KeyType"]] for k in table["KeySchema"]],
            "types": {a["AttributeName"]: a["AttributeType"] for a in table["AttributeDefinitions"]},
        }
    print(json.dumps({
        "status": status,
        "declared": {k: v["Type"] for k, v in body["Resources"].items()},
        "created": {r["LogicalResourceId"]: r["ResourceType"] for r in resources},
        "tables": tables,
        "buckets": [b["Name"] for b in s3.list_buckets()["Buckets"]],
        "queues": boto3.client("sqs").list_queues().get("QueueUrls", []),
        "rules": [
            {"name": r["Name"], "pattern": json.loads(r.get("EventPattern", "{}"))}
            for r in boto3.client("events").list_rules()["Rules"]
        ],
        "mappings": [
            {"source": m["EventSourceArn"], "function": m["FunctionArn"], "batch": m["BatchSize"],
             "window": m.get("MaximumBatchingWindowInSeconds"), "responses": m.get("FunctionResponseTypes", [])}
            for m in boto3.client("lambda").list_event_source_mappings()["EventSourceMappings"]
        ],
        "state_machines": [m["name"] for m in boto3.client("stepfunctions").list_state_machines()["stateMachines"]],
        "functions": sorted(f["FunctionName"] for f in boto3.client("lambda").list_functions()["Functions"]),
    }, indent=1, sort_keys=True))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
