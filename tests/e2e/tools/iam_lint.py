"""Every IAM policy of the templates through parliament (pinned, tests/lint-requirements.txt).

    iam_lint.py TEMPLATE.json ...    print {"policies": N, "findings": [...], "unused_suppressions": [...]}

Each template is the JSON CloudFormation deploys (app.yaml after the SAM transform, cfn.py
transform; cluster.yaml as written). Every AWS::IAM::Role's inline policies and every
AWS::IAM::Policy / ManagedPolicy document is resolved to concrete ARNs (intrinsics replaced by
what CloudFormation would give, for account 123456789012 in us-east-1) and analysed:
unknown actions, resources that match no action's format, needless `*`, and the rest of
parliament's auditors.

A finding is suppressed inline, in the resource's `Metadata`, with its reason:

    Metadata:
      parliament:
        ignore:
          - {issue: RESOURCE_STAR, action: "ec2:DescribeInstanceTypes", reason: "..."}

`action` is optional (then every finding of that issue on the resource). A suppression that
matches nothing is reported too, so none outlives what it excused.
"""

import json
import re
import sys

from parliament import analyze_policy_string, enhance_finding

REGION = "us-east-1"
ACCOUNT = "123456789012"
PSEUDO = {
    "AWS::Region": REGION,
    "AWS::AccountId": ACCOUNT,
    "AWS::Partition": "aws",
    "AWS::StackName": "leaderboard",
    "AWS::URLSuffix": "amazonaws.com",
}

# What `Ref` and `GetAtt .Arn` give for each type the templates name in policies.
ARNS = {
    "AWS::DynamoDB::Table": ("{n}", "arn:aws:dynamodb:{r}:{a}:table/{n}"),
    "AWS::S3::Bucket": ("{n}", "arn:aws:s3:::{n}"),
    "AWS::SQS::Queue": ("https://sqs.{r}.amazonaws.com/{a}/{n}", "arn:aws:sqs:{r}:{a}:{n}"),
    "AWS::SecretsManager::Secret": (
        "arn:aws:secretsmanager:{r}:{a}:secret:{n}-AbCdEf",
        "arn:aws:secretsmanager:{r}:{a}:secret:{n}-AbCdEf",
    ),
    "AWS::SNS::Topic": ("arn:aws:sns:{r}:{a}:{n}", "arn:aws:sns:{r}:{a}:{n}"),
    "AWS::Lambda::Function": ("{n}", "arn:aws:lambda:{r}:{a}:function:{n}"),
    "AWS::StepFunctions::StateMachine": (
        "arn:aws:states:{r}:{a}:stateMachine:{n}",
        "arn:aws:states:{r}:{a}:stateMachine:{n}",
    ),
    "AWS::Logs::LogGroup": ("{n}", "arn:aws:logs:{r}:{a}:log-group:{n}:*"),
    "AWS::IAM::Role": ("{n}", "arn:aws:iam::{a}:role/{n}"),
    "AWS::EKS::Cluster": ("{n}", "arn:aws:eks:{r}:{a}:cluster/{n}"),
    "AWS::Events::Rule": ("{n}", "arn:aws:events:{r}:{a}:rule/{n}"),
    "AWS::Pipes::Pipe": ("{n}", "arn:aws:pipes:{r}:{a}:pipe/{n}"),
    "AWS::EC2::LaunchTemplate": ("lt-0123456789abcdef0", "lt-0123456789abcdef0"),
}


class Resolver:
    def __init__(self, template):
        self.resources = template.get("Resources", {})
        self.parameters = template.get("Parameters", {})

    def ref(self, name):
        if name in PSEUDO:
            return PSEUDO[name]
        if name in self.parameters:
            default = self.parameters[name].get("Default", f"param-{name.lower()}")
            return ",".join(default) if isinstance(default, list) else str(default)
        kind = self.resources.get(name, {}).get("Type")
        ref, _ = ARNS.get(kind, ("{n}", ""))
        return ref.format(n=self.physical(name), r=REGION, a=ACCOUNT)

    def physical(self, name):
        """The resource's name when the template gives one, else a generated-looking one."""
        props = self.resources.get(name, {}).get("Properties", {})
        for key in ("TableName", "BucketName", "QueueName", "Name", "TopicName",
                    "FunctionName", "StateMachineName", "LogGroupName", "RoleName"):
            if key in props:
                return self.value(props[key])
        return f"leaderboard-{name}-ABCDEF123456"

    def getatt(self, name, attribute):
        kind = self.resources.get(name, {}).get("Type")
        if attribute == "Arn" and kind in ARNS:
            return ARNS[kind][1].format(n=self.physical(name), r=REGION, a=ACCOUNT)
        return f"{name}.{attribute}"

    def value(self, node):
        if isinstance(node, list):
            return [self.value(v) for v in node if v != {"Ref": "AWS::NoValue"}]
        if not isinstance(node, dict):
            return node
        if len(node) == 1:
            (key, arg), = node.items()
            if key == "Ref":
                return self.ref(arg)
            if key == "Fn::GetAtt":
                name, attribute = arg if isinstance(arg, list) else arg.split(".", 1)
                return self.getatt(name, attribute)
            if key == "Fn::Sub":
                text, names = (arg, {}) if isinstance(arg, str) else arg
                return self.sub(text, {k: self.value(v) for k, v in names.items()})
            if key == "Fn::Join":
                sep, items = arg
                return sep.join(str(v) for v in self.value(items))
            if key == "Fn::If":
                return self.value(arg[1])
            if key == "Fn::ImportValue":
                return f"arn:aws:iam::{ACCOUNT}:role/imported-{self.value(arg)}"
            if key == "Fn::Select":
                return self.value(arg[1])[int(self.value(arg[0]))]
            if key == "Fn::Split":
                return str(self.value(arg[1])).split(arg[0])
        return {k: self.value(v) for k, v in node.items()}

    def sub(self, text, names):
        def one(match):
            word = match.group(1)
            if word in names:
                return str(names[word])
            if "." in word:
                return self.getatt(*word.split(".", 1))
            return self.ref(word)

        return re.sub(r"\$\{([^}!]+)\}", one, text)


def documents(resource):
    """(label, policy document) of an IAM resource."""
    props = resource.get("Properties", {})
    kind = resource["Type"]
    if kind == "AWS::IAM::Role":
        for policy in props.get("Policies", []):
            yield policy.get("PolicyName", "inline"), policy["PolicyDocument"]
    elif kind in ("AWS::IAM::Policy", "AWS::IAM::ManagedPolicy"):
        yield props.get("PolicyName", "policy"), props["PolicyDocument"]


def actions_of(finding):
    detail = finding.detail
    items = detail if isinstance(detail, list) else [detail]
    out = set()
    for item in items:
        if isinstance(item, dict) and "action" in item:
            out.add(item["action"])
        elif isinstance(item, str):
            out.add(item)
    return out


def lint(path):
    template = json.load(open(path))
    resolver = Resolver(template)
    findings, unused, checked = [], [], 0
    for name, resource in template.get("Resources", {}).items():
        ignores = resource.get("Metadata", {}).get("parliament", {}).get("ignore", [])
        used = [False] * len(ignores)
        for label, document in documents(resource):
            checked += 1
            policy = analyze_policy_string(json.dumps(resolver.value(document)))
            for finding in policy.findings:
                finding = enhance_finding(finding)
                actions = actions_of(finding)
                hit = None
                for i, rule in enumerate(ignores):
                    if rule.get("issue") != finding.issue:
                        continue
                    if "action" in rule and rule["action"] not in actions:
                        continue
                    if not rule.get("reason"):
                        continue
                    hit = i
                    break
                if hit is not None:
                    used[hit] = True
                    continue
                findings.append({
                    "template": path, "resource": name, "policy": label,
                    "issue": finding.issue, "severity": finding.severity,
                    "title": finding.title, "detail": finding.detail,
                })
        for rule, was_used in zip(ignores, used):
            if not rule.get("reason"):
                unused.append({"template": path, "resource": name, "rule": rule,
                               "why": "a suppression needs a reason"})
            elif not was_used:
                unused.append({"template": path, "resource": name, "rule": rule,
                               "why": "matches no finding"})
    return findings, unused, checked


def main():
    findings, unused, checked = [], [], 0
    for path in sys.argv[1:]:
        f, u, n = lint(path)
        findings += f
        unused += u
        checked += n
    print(json.dumps({"policies": checked, "findings": findings, "unused_suppressions": unused},
                     indent=1, default=str))
    return 1 if findings or unused else 0


if __name__ == "__main__":
    sys.exit(main())
